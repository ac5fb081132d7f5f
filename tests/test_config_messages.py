"""Config errors name the user's key, not pydantic's names of the alternatives it tried."""

import pytest

from bsipipe.commands.track import TrackConfig
from bsipipe.config import validate
from bsipipe.errors import InputError


def test_a_union_key_is_named_as_the_user_wrote_it():
    """'diameter_px: 4px' had been reported under the key 'diameter_px.constrained-float'."""
    with pytest.raises(InputError) as e:
        validate(TrackConfig, {"views": {"cam1": "frames/"}, "diameter_px": "4px"}, "track.yaml")
    assert e.value.key == "diameter_px" and "constrained" not in str(e.value), str(e.value)
    assert "more problem" in str(e.value) and "with this key" in str(e.value)


def test_a_whole_model_check_names_the_file_without_an_empty_key(tmp_path):
    """A track config whose per-view regions miss a view: a check of the whole config, whose
    message had named "key ''"."""
    from bsipipe.commands.track import build_config
    from bsipipe.errors import InputError
    p = tmp_path / "t.yaml"
    p.write_text("views: {cam1: a, cam2: b}\ndetection: {roi: {cam1: auto}}\n")
    with pytest.raises(InputError) as e:
        build_config(p)
    assert e.value.key is None and "key ''" not in str(e.value) and "detection.roi" in str(e.value)


def test_a_switch_given_other_than_true_or_false_is_refused():
    """pydantic's lax mode had read loop: "yes" (quoted in YAML) and loop: 1 as true."""
    from pydantic import ValidationError

    from bsipipe.commands.register import RegisterConfig
    for v in ("yes", 1, "true"):
        with pytest.raises(ValidationError, match="expected true or false"):
            RegisterConfig(references=["R1"], loop=v)
    assert RegisterConfig(references=["R1"], loop=False).loop is False


def test_a_per_log_count_from_the_config_names_the_config(tmp_path):
    """Two contacts in the config for one log: the error names the config file and the key
    (it had named the log)."""
    from click.testing import CliRunner

    from bsipipe.cli import cli
    from bsipipe.synth.machine_log import synth_compression_log, write_bluehill2
    frame, _ = synth_compression_log(seed=1)
    log = tmp_path / "log.csv"
    write_bluehill2(frame, log, geometry={"diameter_mm": 18.0, "height_mm": 12.0})
    cfg = tmp_path / "fit.yaml"
    cfg.write_text("diameter_mm: 18\nheight_mm: 12\ncontact_mm: [0.5, 0.6]\n")
    r = CliRunner().invoke(cli, ["fit-ogden", str(log), "--config", str(cfg), "-o", str(tmp_path / "out")])
    assert r.exit_code == 2, r.output
    assert "fit.yaml" in r.output and "contact_mm" in r.output
