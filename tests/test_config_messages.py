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
