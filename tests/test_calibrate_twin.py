"""Calibration on the X-ray twin (bsipipe.synth.twin), where the truth is known.

- pincushion (and the twin's small tangential term) only: intrinsics within 0.5 %, the
  distortion map within 0.1 px RMS over the intensifier's field, stereo rotation within
  0.1 deg and translation within 0.5 mm;
- an S-distortion the command line does not declare: the loop adds ``s-distortion`` (or
  ``local-distortion``) and the held-out RMS ends within 1.5 x the bead-centre noise.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

from bsipipe.cli import cli
from bsipipe.imaging.calibrate import CameraModel, ModelSpec, ViewData, calibrate_with_rejection
from bsipipe.imaging.calibration_effects import close_loop
from bsipipe.imaging.gridfind import field_centre, find_circles
from bsipipe.synth.config import SynthConfig
from bsipipe.synth.twin import Twin, stereo_extrinsics

GRID, SPACING = (7, 15), 7.0  # an asymmetric bead grid, pinned so the test does not follow the twin's default


def _config(distortion: dict, views: int, stereo_views: int, seed: int = 0) -> SynthConfig:
    return SynthConfig.model_validate({"seed": seed, "sequence": {"enabled": False}, "distortion": distortion,
                                       "calibration": {"views": views, "stereo_views": stereo_views,
                                                       "pattern": "asymmetric-circles", "grid": list(GRID),
                                                       "spacing_mm": SPACING}})


@pytest.fixture(scope="module")
def pincushion(tmp_path_factory):
    """Twin with the default pincushion + tangential distortion, no S or local distortion."""
    root = tmp_path_factory.mktemp("twin_pincushion")
    tw = Twin(_config({}, views=12, stereo_views=6))
    for rel, img in tw.calibration_images():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(p), img)
    out = root / "out"
    c = root / "calibration"
    r = CliRunner().invoke(cli, ["calibrate", "--view", f"cam1={c / 'cam1'}", "--view", f"cam2={c / 'cam2'}",
                                 "--stereo", f"cam1={c / 'stereo' / 'cam1'}", "--stereo",
                                 f"cam2={c / 'stereo' / 'cam2'}", "--pattern", "asymmetric-circles",
                                 "--grid", "7x15", "--spacing-mm", "7", "-o", str(out)])
    print(r.output)
    assert r.exit_code == 0, r.output
    return tw, json.loads((out / "calibration.json").read_text()), c


def test_twin_pincushion_intrinsics_and_distortion_map(pincushion):
    tw, res, _ = pincushion
    for name in ("cam1", "cam2"):
        arm, v = tw.arms[name], res["views"][name]
        K, Kt = np.asarray(v["camera_matrix"]), arm.camera.K
        idx = ([0, 1, 0, 1], [0, 1, 2, 2])
        rel = (K[idx] - Kt[idx]) / Kt[idx]
        print(name, "fx fy cx cy relative error %", np.round(100 * rel, 3), "RMS", round(v["rms_px"], 4),
              "held-out", round(v["heldout_rms_px"], 4), "model", v["dist_model"],
              "std cx cy (px)", round(v["std"]["cx"], 3), round(v["std"]["cy"], 3))
        assert np.all(np.abs(rel) < 0.005)
        # no hidden effect: the loop adds none
        assert v["loop"]["steps"] == []
        # distortion map over the intensifier's field, raw-pixel displacements compared
        truth = arm.camera.distortion_map(16.0, arm.fov_centre_px, arm.fov_radius_px)
        mine = CameraModel(tuple(v["image_size"]), K, np.asarray(v["dist_coeffs"]), ModelSpec())
        und = mine.undistort_points(truth.raw_px) * [K[0, 0], K[1, 1]] + K[:2, 2]
        err = np.hypot(*((truth.raw_px - und) - truth.displacement_px).T)
        rms = float(np.sqrt(np.mean(err ** 2)))
        print(f"{name}: distortion map error {rms:.4f} px RMS, {err.max():.4f} px max over the field "
              f"(true displacement up to {np.hypot(*truth.displacement_px.T).max():.1f} px)")
        assert rms < 0.1


def test_twin_stereo_extrinsics(pincushion):
    tw, res, _ = pincushion
    st, truth = res["stereo"], stereo_extrinsics(tw.arms["cam1"].camera, tw.arms["cam2"].camera)
    R, Rt = np.asarray(st["R"]), np.asarray(truth["R"])
    ang = float(np.degrees(np.linalg.norm(cv2.Rodrigues(R @ Rt.T)[0])))
    dt = float(np.linalg.norm(np.asarray(st["T_mm"]) - np.asarray(truth["T_mm"])))
    print(f"stereo: rotation error {ang:.4f} deg, translation error {dt:.3f} mm "
          f"(baseline {np.linalg.norm(truth['T_mm']):.1f} mm), RMS {st['rms_px']:.4f} px")
    assert ang < 0.1 and dt < 0.5


def test_stereo_folders_given_the_wrong_way_round_are_refused(pincushion, tmp_path):
    """--stereo cam1=<cam2's frames> --stereo cam2=<cam1's>: each camera had calibrated with 6
    of its 18 views from the other C-arm, exit 0 (the probe: fx 39 px off, the stereo rotation
    177 degrees off at an RMS of 0.27 px).  Each camera's stereo frames are now posed under its
    own views' intrinsics: they fit the other camera's and not their own, exit 2 naming it; the
    right way round (the fixture) has no such warning."""
    _, res, c = pincushion
    assert not [w for w in res["warnings"] if w["code"] == "stereo-frames-disagree"]
    r = CliRunner().invoke(cli, ["calibrate", "--view", f"cam1={c / 'cam1'}", "--view", f"cam2={c / 'cam2'}",
                                 "--stereo", f"cam1={c / 'stereo' / 'cam2'}", "--stereo",
                                 f"cam2={c / 'stereo' / 'cam1'}", "--pattern", "asymmetric-circles",
                                 "--grid", "7x15", "--spacing-mm", "7", "--no-loop", "-o", str(tmp_path / "out")])
    assert r.exit_code == 2, r.output
    assert "the --stereo folders look swapped" in r.output
    assert not (tmp_path / "out" / "calibration.json").exists()


def test_twin_undeclared_s_distortion_is_found_by_the_loop():
    tw = Twin(_config({"s_distortion_deg": 1.0}, views=8, stereo_views=0, seed=3))
    views, centre = [], None
    for rel, img in tw.calibration_images():
        if not rel.startswith("calibration/cam1/"):
            break
        if centre is None:
            centre = field_centre(img)
        d = find_circles(img, GRID, SPACING, asymmetric=True)
        views.append(ViewData(rel.rsplit("/", 1)[-1], d.image_points, d.object_points, d.ids))
    # bead-centre noise: detected centres against the true projections, matched by position
    truth = {t["file"]: np.asarray(t["image_points_px"]) for t in tw._calib_truth["views"]["cam1"]}
    err = []
    for v in views:
        dist, _ = cKDTree(truth[v.name]).query(v.image_points)
        err.append(dist)
    noise = float(np.sqrt(np.mean(np.concatenate(err) ** 2)))
    base = calibrate_with_rejection(views, (1024, 1024), twist_centre_px=centre)
    report, final, lp = close_loop(base.views, (1024, 1024), base)
    h0, h1 = lp.heldout(base.camera.spec), lp.heldout(final.camera.spec)
    print(f"S-distortion twin: bead-centre noise {noise:.4f} px; loop added {report.effects}; "
          f"held-out RMS {h0:.4f} -> {h1:.4f} px ({h1 / noise:.2f} x noise); field centre {centre}")
    assert report.effects and report.effects[0] in ("s-distortion", "local-distortion")
    assert h1 <= 1.5 * noise
    if report.effects[0] == "s-distortion":
        t_true = tw.arms["cam1"].camera.s_distortion
        # theta(r) = s_rad (r / r_ref)^2 = t1 (r / s)^2: t1 = s_rad (s / r_ref)^2
        t1_true = t_true.s_rad * (final.camera.norm_radius_px / t_true.r_ref_px) ** 2
        print(f"twist t1 {final.camera.twist_rad[0]:.5f} rad, truth {t1_true:.5f} rad")
        assert abs(final.camera.twist_rad[0] - t1_true) < 0.05 * abs(t1_true)


# --- the twin's own default calibration views, calibrated as a user would ---------------------

def _synth(root, config_yaml: str) -> None:
    """``bsipipe synth`` of ``config_yaml`` into ``root/tw``."""
    (root / "synth.yaml").write_text(config_yaml)
    r = CliRunner().invoke(cli, ["synth", str(root / "synth.yaml"), "-o", str(root / "tw")])
    assert r.exit_code == 0, r.output


@pytest.fixture(scope="module")
def default_plate(tmp_path_factory):
    """``bsipipe synth`` with every calibration default (plate, noise, distortion) but few
    views, then ``bsipipe calibrate DIR/calibration.yaml``, the config synth writes."""
    root = tmp_path_factory.mktemp("twin_default_plate")
    _synth(root, "calibration: {views: 4, stereo_views: 3}\nsequence: {enabled: false}\n")
    r = CliRunner().invoke(cli, ["calibrate", str(root / "tw" / "calibration.yaml"), "-o", str(root / "cal")])
    print(r.output)
    assert r.exit_code == 0, r.output
    return (root, json.loads((root / "tw" / "truth.json").read_text()),
            json.loads((root / "cal" / "calibration.json").read_text()))


def test_calibrate_on_the_twins_default_views(default_plate):
    """Every view of the default plate (an OpenCV 8x17 asymmetric bead grid, 7 mm) is found
    and used, fx, fy, cx, cy are within 0.5 % of truth.json (the issue's tolerance) with 7
    views per C-arm, and the stereo pose within 0.1 deg and 0.5 mm."""
    root, truth, cal = default_plate
    tc = truth["calibration"]
    assert cal["provenance"]["config"]["grid"] == f"{tc['grid'][0]}x{tc['grid'][1]}"
    assert cal["provenance"]["config"]["pattern"] == tc["pattern"]
    for name in ("cam1", "cam2"):
        v = cal["views"][name]
        assert not v["rejected_views"]
        assert len(v["per_image_rms_px"]) == len(tc["views"][name]) + len(tc["stereo"])
        K, Kt = np.asarray(v["camera_matrix"]), np.asarray(truth["cameras"][name]["camera_matrix"])
        idx = ([0, 1, 0, 1], [0, 1, 2, 2])
        rel = (K[idx] - Kt[idx]) / Kt[idx]
        print(f"{name}: fx fy cx cy relative error % {np.round(100 * rel, 3)}, RMS {v['rms_px']:.4f} px, "
              f"held-out {v['heldout_rms_px']:.4f} px, {len(v['per_image_rms_px'])} views")
        assert np.all(np.abs(rel) < 0.005)
    st, tst = cal["stereo"], truth["stereo_extrinsics"]
    ang = float(np.degrees(np.linalg.norm(cv2.Rodrigues(np.asarray(st["R"]) @ np.asarray(tst["R"]).T)[0])))
    dt = float(np.linalg.norm(np.asarray(st["T_mm"]) - np.asarray(tst["T_mm"])))
    print(f"stereo: rotation error {ang:.4f} deg, translation error {dt:.3f} mm")
    assert ang < 0.1 and dt < 0.5


def test_calibrate_names_the_grid_the_views_show(default_plate):
    """A wrong ``--grid`` (the old 7x15 plate) is bad input: exit 2 (it was exit 1 until
    session 5) and a message that names the grid the beads do form, once for all the views
    it applies to."""
    root, truth, _ = default_plate
    r = CliRunner().invoke(cli, ["calibrate", "--images", str(root / "tw" / "calibration" / "cam1"),
                                 "--pattern", "asymmetric-circles", "--grid", "7x15", "--spacing-mm", "7",
                                 "--no-loop", "-o", str(root / "wrong")])
    print(r.output)
    assert r.exit_code == 2
    err = [line for line in r.output.splitlines() if line.startswith("bsipipe calibrate: error:")]
    assert len(err) == 1
    assert "complete 8x17 asymmetric-circles grid" in err[0] and "--grid 8x17" in err[0]
    assert err[0].count("8x17 asymmetric-circles") == 1 and "4 of 4 views" in err[0]


def test_two_views_that_hide_each_other_are_both_left_out(tmp_path):
    """A dark wire across the plate in every view touches beads in two of them (cal_006,
    cal_007: RMS about 0.84 px against 0.07 px).  Left out one at a time, each leaves the other
    to hold the model, so neither looked like an outlier (-0.6 %) and both were kept: fx 1734
    for 1670, cy 293 for 252, with exit 0 and no warning.  Judged together they are both left
    out: fx, fy back within 0.5 %, the principal point within 2 % of the image."""
    _synth(tmp_path, "seed: 1\nimage: {size_px: 512, supersample: 2}\ncalibration: {views: 8, stereo_views: 0, "
                     "pattern: circles, grid: [9, 7], spacing_mm: 10.0, bead_diameter_mm: 2.0}\n"
                     "sequence: {enabled: false}\n")
    src = sorted((tmp_path / "tw" / "calibration" / "cam1").glob("*.png"))
    wire = tmp_path / "wire"
    wire.mkdir()
    for i, p in enumerate(src):
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(wire / p.name), cv2.line(im.copy(), (0, 200 + 10 * i), (511, 260 + 10 * i), int(im.min()), 6))
    r = CliRunner().invoke(cli, ["calibrate", "--images", str(wire), "--pattern", "circles", "--grid", "9x7",
                                 "--spacing-mm", "10", "--no-loop", "-o", str(tmp_path / "cal")])
    print(r.output)
    assert r.exit_code == 0, r.output
    v = json.loads((tmp_path / "cal" / "calibration.json").read_text())["views"]["cam1"]
    assert set(v["rejected_views"]) == {"cal_006.png", "cal_007.png"}
    assert all("together" in why for why in v["rejected_views"].values())
    # fx, fy within 0.5 % (the tolerance); the principal point of six views of a 9x7
    # plate within 2 % of the 512 px image (the six clean views alone put cx 2.9 px, cy 2.1 px
    # off; the wire's views kept had put cy 41 px off)
    K = np.asarray(v["camera_matrix"])
    Kt = np.asarray(json.loads((tmp_path / "tw" / "truth.json").read_text())["cameras"]["cam1"]["camera_matrix"])
    print(f"fx fy cx cy {np.round(K[[0, 1, 0, 1], [0, 1, 2, 2]], 2)}, truth {np.round(Kt[[0, 1, 0, 1], [0, 1, 2, 2]], 2)}")
    assert np.all(np.abs(np.diag(K)[:2] / np.diag(Kt)[:2] - 1) < 0.005)
    assert np.all(np.abs(K[:2, 2] - Kt[:2, 2]) < 0.02 * 512)


def test_loop_fits_a_richer_model_from_the_model_it_augments():
    """An S-distortion twisting about a point 50 px from the field centre the calibration
    assumes (corners found in 12 rendered views, ``tests/data/calibration``): the loop adds
    s-distortion, then a local correction for what the twist centre leaves.  Fitted from the
    declared camera, S-distortion plus the local correction had run off (fx 3014, fy 2762, cy
    -70 px) and its leave-one-view-out refits to a held-out RMS of 65 px, so the loop turned
    the correction down and stopped at RMS 0.35 px, five times the corners' noise.  Started
    from the model it augments, the held-out RMS is 0.094 px."""
    z = np.load(Path(__file__).parent / "data" / "calibration" / "sdist_offcentre_views.npz")
    views = [ViewData(str(n), ip, op, ids) for n, ip, op, ids in
             zip(z["names"], z["image_points"], z["object_points"], z["ids"])]
    size = tuple(int(v) for v in z["size"])
    base = calibrate_with_rejection(views, size, twist_centre_px=tuple(z["centre"]))
    report, final, lp = close_loop(base.views, size, base)
    h = lp.heldout(final.camera.spec)
    print(f"off-centre twist: loop added {report.effects}; RMS {final.rms_px:.4f} px, held-out {h:.4f} px")
    assert report.effects == ["s-distortion", "local-distortion"]
    assert h < 0.12 and final.rms_px < 0.08


def test_field_centre_principal_point_is_what_the_report_describes(pincushion, tmp_path):
    """principal_point field-centre: the loop's ``final`` had described the fit with cx, cy free
    (cx 447.0, held-out 0.0733 px) beside a delivered model with them fixed (cx 509.1, 0.0880
    px), unsaid.  ``loop.final.delivered`` now gives the delivered model's RMS and held-out RMS,
    the ones at the top of the camera's entry."""
    _, _, c = pincushion
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["calibrate", "--view", f"cam1={c / 'cam1'}", "--pattern", "asymmetric-circles",
                                 "--grid", "7x15", "--spacing-mm", "7", "--principal-point", "field-centre",
                                 "-o", str(out)])
    assert r.exit_code == 0, r.output
    v = json.loads((out / "calibration.json").read_text())["views"]["cam1"]
    K = np.asarray(v["camera_matrix"])
    assert [K[0, 2], K[1, 2]] == pytest.approx(v["field_centre_px"], abs=1e-9)
    got = v["loop"]["final"]["delivered"]
    assert got["principal_point"] == "field-centre"
    assert got["rms_px"] == pytest.approx(v["rms_px"]) and got["heldout_rms_px"] == pytest.approx(v["heldout_rms_px"])
    assert v["std_jackknife"]["cx"] == 0.0 and v["std_jackknife"]["cy"] == 0.0
