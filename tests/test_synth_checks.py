"""Config checks and small output fixes of ``bsipipe synth`` (each fast: no frames rendered
except the tiny runs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from bsipipe.config import validate
from bsipipe.errors import InputError
from bsipipe.synth.config import ARUCO_DICTIONARIES, SynthConfig
from bsipipe.synth.twin import Twin

_TINY = {"image": {"size_px": 512, "supersample": 1},
         "calibration": {"views": 0, "stereo_views": 1, "pattern": "circles", "grid": [3, 3]},
         "sequence": {"n_frames": 1}}


def _err(data) -> InputError:
    with pytest.raises(InputError) as e:
        validate(SynthConfig, data)
    return e.value


def test_dictionary_table_matches_opencv():
    cv2 = pytest.importorskip("cv2")
    for name, n in ARUCO_DICTIONARIES.items():
        assert cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0] == n


def test_unknown_charuco_dictionary_names_the_key():
    e = _err({"calibration": {"pattern": "charuco", "grid": [5, 5], "charuco_dictionary": "DICT_FOO"}})
    assert e.key == "calibration.charuco_dictionary" and "DICT_4X4_50" in str(e)


def test_charuco_grid_larger_than_dictionary():
    e = _err({"calibration": {"pattern": "charuco", "grid": [12, 12], "charuco_dictionary": "DICT_4X4_50"}})
    assert "calibration.grid" in str(e) and "DICT_4X4_50" in str(e)
    validate(SynthConfig, {"calibration": {"pattern": "charuco", "grid": [10, 10], "charuco_dictionary": "DICT_4X4_50"}})


@pytest.mark.parametrize("seq, key", [({"hold_s": 1e6}, "sequence.hold_s"),
                                      ({"speed_mm_per_min": 0.0001}, "sequence.speed_mm_per_min"),
                                      ({"fps": 1000.0}, "sequence.fps"),
                                      ({"n_frames": 10 ** 6}, "sequence.n_frames")])
def test_timeline_is_bounded(seq, key):
    e = _err({"sequence": seq})
    assert key in str(e) and "limit" in str(e)


@pytest.mark.parametrize("n", [3, 5, 6, 8])
def test_any_number_of_references_can_be_placed(n):
    cfg = validate(SynthConfig, {"image": {"size_px": 512}, "sequence": {"n_references": n}})
    sc = Twin(cfg).scene
    assert sum(m.kind == "reference" for m in sc.markers) == n


def test_occlusion_without_unloading():
    cfg = validate(SynthConfig, {"image": {"size_px": 512}, "sequence": {"unload": False}})
    assert {"M2", "M4"} <= {m.name for m in Twin(cfg).scene.markers}


def test_placement_failure_names_the_key():
    from bsipipe.synth.twin import TwinError
    cfg = validate(SynthConfig, {"image": {"size_px": 512}, "sequence": {"n_markers": 12, "indentor_diameter_mm": 12.0}})
    with pytest.raises(TwinError) as e:
        Twin(cfg)
    assert e.value.key != "sequence" and e.value.key in str(e.value)


def _run(cfg: dict, tmp_path, out):
    import yaml
    from bsipipe.commands.synth import run
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return run(p, out)


def test_files_list_calibration_yaml_and_empty_truth_has_header(tmp_path):
    cfg = {**_TINY, "sequence": {"n_frames": 1, "n_markers": 0, "n_references": 0, "indentor_markers": 0}}
    res = _run(cfg, tmp_path, tmp_path / "o")
    assert "calibration.yaml" in res["files"] and "calibration/..." in res["files"]
    head = (tmp_path / "o" / "truth_markers.csv").read_text().splitlines()
    assert head and head[0].startswith("view,frame,time_s,marker")


def test_stale_staging_of_a_dead_run_is_removed(tmp_path):
    from bsipipe.commands.synth import remove_stale_staging
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    out = tmp_path / "o"
    dead = out / f".synth-staging-{p.pid}-abc"
    live = out / f".synth-staging-{os.getpid()}-abc"
    legacy = out / ".synth-staging-k2j3h4"
    for d in (dead, live, legacy):
        (d / "sequence").mkdir(parents=True)
    assert remove_stale_staging(out) == [dead]
    os.utime(legacy, (0, 0))
    assert remove_stale_staging(out) == [legacy]
    assert live.exists()
    _run(_TINY, tmp_path, out)
    assert [d.name for d in out.glob(".synth-staging-*")] == [live.name]
    assert json.loads((out / "synth.json").read_text())["counts"]


def test_beads_that_cannot_clear_the_rod_at_a_narrow_angle_name_the_angle():
    """At 60 degrees between the beams the indentor's beads, on the bisector, are seen 3 mm from
    the rod's axis against its 2.5 mm radius: the twin cannot place them, and the message names
    the angle with the numbers (it had named only the beads' keys)."""
    from bsipipe.synth.twin import TwinError
    cfg = validate(SynthConfig, {"seed": 0, "geometry": {"angle_between_deg": 60}, "image": {"size_px": 512},
                                 "calibration": {"views": 0, "stereo_views": 0}, "sequence": {"n_frames": 5}})
    with pytest.raises(TwinError, match=r"angle_between_deg 60 each view sees them 3 mm from the rod's axis") as e:
        Twin(cfg).truth()
    assert "geometry.angle_between_deg" in str(e.value)
