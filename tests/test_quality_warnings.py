"""Quality warnings (issue 7, item 5): flagged in the JSON result and on the console.

* fit-ogden: parameters that are not identifiable (|r| > 0.99, a 95 % interval spanning
  zero) -> ``fit.json`` ``warnings``;
* calibrate: the detected target points cover less than half the field of view ->
  ``calibration.json`` ``warnings``;
* track: a triangulated point whose rays pass far apart -> ``track.json`` ``warnings`` and
  the ``flag`` column of ``markers3d.csv``.

Each is tested both ways: the flawed input is flagged, the sound one is not.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from bsipipe.cli import cli
from bsipipe.quality import (CORRELATION_MAX, RAY_GAP_FLOOR_MM, correlation_matrix, fit_warnings, hull_coverage,
                             ray_gap_flags)

ROOT = Path(__file__).resolve().parents[1]
SLOW_LOG = ROOT / "sample_data" / "logs" / "sheep_s1_1mm_min.csv"     # 1 mm/min: 2,470 samples
FAST_LOG = ROOT / "sample_data" / "logs" / "sheep_s3_100mm_min.csv"   # 100 mm/min: 124 samples


def _invoke(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r


def _codes(warnings: list[dict]) -> list[str]:
    return [w["code"] for w in warnings]


# --------------------------------------------------------------------------- the helpers


def test_correlation_and_zero_interval_rules():
    # cov of (a, b, c): a and b correlated at exactly 0.995, c independent
    s = np.array([2.0, 3.0, 0.5])
    r = np.array([[1.0, 0.995, 0.0], [0.995, 1.0, 0.0], [0.0, 0.0, 1.0]])
    cov = r * np.outer(s, s)
    np.testing.assert_allclose(correlation_matrix(cov), r, atol=1e-15)
    ci = {"a": [1.0, 3.0], "b": [-1.0, 2.0], "c": [-0.5, -0.1]}
    w = fit_warnings(["a", "b", "c"], cov, ci, zero_checked=["a", "b", "c"])
    assert _codes(w) == ["parameter-correlation", "interval-spans-zero"]
    assert w[0]["params"] == ["a", "b"] and w[0]["r"] == pytest.approx(0.995)
    assert w[1]["param"] == "b" and w[1]["ci95"] == [-1.0, 2.0]
    # just under the limit, and an offset allowed to be zero (not zero-checked): nothing
    cov2 = np.array([[1.0, 0.989], [0.989, 1.0]])
    assert fit_warnings(["a", "b"], cov2, {"a": [1, 2], "b": [-1, 1]}, zero_checked=["a"]) == []
    assert CORRELATION_MAX == 0.99
    # a direction the data do not determine
    cov3 = np.array([[1.0, np.nan], [np.nan, np.nan]])
    assert _codes(fit_warnings(["a", "b"], cov3, {})) == ["parameter-undetermined"]


def test_hull_coverage_is_the_covered_fraction_of_the_field():
    mask = np.ones((400, 400), bool)
    square = np.array([[0, 0], [199.5, 0], [199.5, 199.5], [0, 199.5], [100, 100]], float)
    assert hull_coverage(square, mask, step_px=1) == pytest.approx(0.25, abs=0.005)
    # a disc field: the square's points inside the circle of radius 200 about (200, 200)
    yy, xx = np.mgrid[:400, :400]
    disc = (xx - 200) ** 2 + (yy - 200) ** 2 <= 200 ** 2
    frac = hull_coverage([[100, 100], [300, 100], [300, 300], [100, 300]], disc, step_px=1)
    assert frac == pytest.approx(200 * 200 / (np.pi * 200 ** 2), abs=0.005)
    assert hull_coverage([[0, 0], [1, 1], [2, 2]], mask) == 0.0   # collinear: no area


def test_ray_gap_rule():
    rng = np.random.default_rng(0)
    g = np.abs(rng.normal(0.0, 0.02, 500))                # median ~0.013 mm: the 0.1 mm floor rules
    g[[10, 20]] = [0.3, 0.09]
    g[30] = np.nan                                        # a one-view point is never flagged
    flag, rule = ray_gap_flags(g)
    assert rule["threshold_mm"] == {"": RAY_GAP_FLOOR_MM} and RAY_GAP_FLOOR_MM == 0.1
    assert set(np.flatnonzero(flag)) == set(np.flatnonzero(np.nan_to_num(g) > 0.1)) and flag[10] and not flag[20]
    assert not flag[30]
    big = g * 10                                          # median ~0.13 mm: 5x the median rules
    flag, rule = ray_gap_flags(big)
    assert rule["threshold_mm"][""] == pytest.approx(5 * np.nanmedian(big))
    assert set(np.flatnonzero(flag)) == set(np.flatnonzero(np.nan_to_num(big) > 5 * np.nanmedian(big)))
    flag, _ = ray_gap_flags(big, max_mm=1.0)              # a stated limit adds its own
    assert set(np.flatnonzero(flag)) == set(np.flatnonzero(np.nan_to_num(big) > min(1.0, 5 * np.nanmedian(big))))
    # a marker with a steady gap (a calibration bias at its place) is judged by its own median
    markers = np.array(["A"] * 250 + ["B"] * 250)
    biased = np.where(markers == "B", 0.15 + np.abs(rng.normal(0.0, 0.01, 500)), np.abs(rng.normal(0.0, 0.02, 500)))
    biased[5], biased[300] = 0.3, 0.9                     # a bad point of each
    flag, rule = ray_gap_flags(biased, markers)
    assert set(np.flatnonzero(flag)) == {5, 300}
    assert rule["threshold_mm"]["B"] == pytest.approx(5 * np.median(biased[markers == "B"]))
    assert rule["threshold_mm"]["A"] == pytest.approx(max(5 * np.median(biased[markers == "A"]), 0.1))


# --------------------------------------------------------------------------- fit-ogden


def test_fit_warns_when_parameters_are_not_identifiable(tmp_path):
    """A relaxation term fitted to one fast ramp (2.5 s of loading) has neither its fraction nor its
    time determined: g1's interval spans zero and g1, tau1 move together."""
    r = _invoke("fit-ogden", FAST_LOG, "--prony", "1", "--no-loop", "--bootstrap", "0", "--boundary", "frictionless",
                "-o", tmp_path / "qlv")
    fit = json.loads((tmp_path / "qlv" / "fit.json").read_text())
    codes = _codes(fit["warnings"])
    assert "interval-spans-zero" in codes and "parameter-correlation" in codes
    spans = [w for w in fit["warnings"] if w["code"] == "interval-spans-zero"]
    assert [w["param"] for w in spans] == ["g1"]
    lo, hi = fit["ci95"]["g1"]
    assert lo < 0 < hi and spans[0]["ci95"] == pytest.approx([lo, hi])
    pairs = [set(w["params"]) for w in fit["warnings"] if w["code"] == "parameter-correlation"]
    assert {"g1", "tau1_s"} in pairs
    assert all(abs(w["r"]) > 0.99 for w in fit["warnings"] if w["code"] == "parameter-correlation")
    # and on the console, one WARNING line per warning
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("WARNING") and "fit:" in ln]
    assert len(lines) == len(fit["warnings"])
    assert "g1" in " ".join(lines)


def test_fit_without_warnings_when_parameters_are_determined(tmp_path):
    """One-term Ogden on the same log: mu and alpha correlate at about 0.97, both intervals are
    far from zero: no parameter is warned about.  Without the loop the one-term law leaves a
    residual with lag-1 0.31 (the loop's model-order takes it out), which is said."""
    r = _invoke("fit-ogden", FAST_LOG, "--no-loop", "--bootstrap", "0", "--boundary", "frictionless", "-o",
                tmp_path / "elastic")
    fit = json.loads((tmp_path / "elastic" / "fit.json").read_text())
    assert [w["code"] for w in fit["warnings"]] == ["residual-correlated"]
    assert fit["warnings"][0]["turned_down"] == []          # the loop was off: nothing turned down
    assert "correlated (r" not in r.stderr and "contains zero" not in r.stderr


# --------------------------------------------------------------------------- calibrate

K = np.array([[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]])
COLS, ROWS, SQUARE_MM = 7, 5, 10.0


def _chessboard_view(centre_px, distance_mm, rotvec, size=(640, 480), ppm=8) -> np.ndarray:
    """A 7x5 (inner corners) chessboard of 10 mm squares seen by a pinhole camera ``K``, its
    centre on the ray through ``centre_px`` at ``distance_mm``."""
    import cv2

    nx, ny, border = COLS + 1, ROWS + 1, 1
    tex = np.full((int((ny + 2 * border) * SQUARE_MM * ppm), int((nx + 2 * border) * SQUARE_MM * ppm)), 255, np.uint8)
    s = int(SQUARE_MM * ppm)
    for i in range(nx):
        for j in range(ny):
            if (i + j) % 2 == 0:
                tex[(j + border) * s:(j + border + 1) * s, (i + border) * s:(i + border + 1) * s] = 0
    A = np.array([[1 / ppm, 0, -(border + 1) * SQUARE_MM], [0, 1 / ppm, -(border + 1) * SQUARE_MM], [0, 0, 1]])
    R = Rotation.from_rotvec(rotvec).as_matrix()
    c_board = np.array([(COLS - 1) * SQUARE_MM / 2, (ROWS - 1) * SQUARE_MM / 2, 0.0])
    ray = np.linalg.solve(K, [centre_px[0], centre_px[1], 1.0])
    t = ray / ray[2] * distance_mm - R @ c_board
    H = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
    return cv2.warpPerspective(tex, H, size, flags=cv2.INTER_AREA, borderValue=128)


def _chessboard_views(folder: Path, centres, distance_mm: float, seed: int = 1) -> Path:
    import cv2

    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i, c in enumerate(centres):
        cv2.imwrite(str(folder / f"view_{i}.png"),
                    _chessboard_view(c, distance_mm, rng.uniform(-0.35, 0.35, 3) * [1.0, 1.0, 0.3]))
    return folder


def _calibrate(folder: Path, out: Path) -> tuple[dict, str]:
    r = _invoke("calibrate", "--images", folder, "--pattern", "chessboard", "--grid", f"{COLS}x{ROWS}",
                "--spacing-mm", SQUARE_MM, "--no-loop", "-o", out)
    return json.loads((out / "calibration.json").read_text()), r.stderr


def test_calibration_warns_about_poor_coverage(tmp_path):
    """Six views of the board, all in the top-left quarter of the image."""
    rng = np.random.default_rng(1)
    centres = [(150 + rng.uniform(-40, 40), 120 + rng.uniform(-30, 30)) for _ in range(6)]
    cal, stderr = _calibrate(_chessboard_views(tmp_path / "corner", centres, 350.0), tmp_path / "out")
    cov = cal["views"]["cam1"]["coverage"]
    assert cov["field"] == "image" and cov["hull_fraction"] < 0.15
    assert _codes(cal["warnings"]) == ["poor-coverage"]
    w = cal["warnings"][0]
    assert w["view"] == "cam1" and w["hull_fraction"] == cov["hull_fraction"] and w["min_fraction"] == 0.5
    assert any(ln.startswith("WARNING") and "cover" in ln for ln in stderr.splitlines())


def test_calibration_with_the_field_covered_has_no_warning(tmp_path):
    centres = [(120, 90), (520, 90), (120, 390), (520, 390), (320, 240), (320, 100)]
    cal, stderr = _calibrate(_chessboard_views(tmp_path / "spread", centres, 300.0), tmp_path / "out")
    assert cal["views"]["cam1"]["coverage"]["hull_fraction"] > 0.6
    assert cal["warnings"] == []
    assert "WARNING" not in stderr
    # the calibration itself is sound (the check is about coverage, not a failed fit)
    assert np.asarray(cal["views"]["cam1"]["camera_matrix"])[0, 0] == pytest.approx(700.0, rel=0.05)


# --------------------------------------------------------------------------- track

# The twin of configs/study_tiny.yaml (256 px frames, 4 + 3 calibration views, 8 frames).
SYNTH_TINY = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "study_tiny.yaml").read_text())["synth"]


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """The tiny twin of configs/study_tiny.yaml, calibrated and tracked once."""
    root = tmp_path_factory.mktemp("quality_twin")
    (root / "synth.yaml").write_text(yaml.safe_dump(SYNTH_TINY))
    _invoke("synth", root / "synth.yaml", "-o", root / "synth")
    s = root / "synth"
    (root / "calibrate.yaml").write_text(yaml.safe_dump({
        "pattern": "asymmetric-circles", "grid": "4x9", "spacing_mm": 3.0, "loop": False,
        "views": {"cam1": str(s / "calibration/cam1"), "cam2": str(s / "calibration/cam2")},
        "stereo": {"cam1": str(s / "calibration/stereo/cam1"), "cam2": str(s / "calibration/stereo/cam2")}}))
    _invoke("calibrate", root / "calibrate.yaml", "-o", root / "calibrate")
    return root


def _track_dir(twin: Path, cam2: Path, seeds: Path, out: Path) -> Path:
    r = _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view", f"cam2={cam2}",
                "--calibration", twin / "calibrate/calibration.json", "--seeds", seeds, "--fps", "0.5", "-o", out)
    assert r.exit_code == 0, r.output
    return out


def _track(twin: Path, cam2: Path, out: Path):
    r = _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view", f"cam2={cam2}",
                "--calibration", twin / "calibrate/calibration.json", "--seeds", twin / "synth/seeds.csv",
                "--fps", "0.5", "-o", out)
    res = json.loads((out / "track.json").read_text())
    m3 = pd.read_csv(out / "markers3d.csv", keep_default_na=False, na_values=[""])
    return res, m3, r.stderr


def test_track_flags_a_point_with_a_large_ray_gap(twin, tmp_path):
    """cam2's frame 4 with marker M1 moved 2 px across the epipolar lines (a bad detection):
    M1's rays miss each other there by ~0.4 mm, about 25 times M1's median gap (on the clean
    twin every point stays under its marker's threshold, though R1 and M4 keep a steady gap of
    0.06-0.08 mm from the calibration)."""
    import cv2

    clean, m3_clean, err_clean = _track(twin, twin / "synth/sequence/cam2", tmp_path / "clean")
    assert clean["warnings"] == [] and "WARNING" not in err_clean
    assert "flag" in m3_clean.columns and m3_clean["flag"].isna().all()

    cam2 = tmp_path / "cam2"
    shutil.copytree(twin / "synth/sequence/cam2", cam2)
    m2 = pd.read_csv(tmp_path / "clean" / "markers2d.csv")
    row = m2[(m2.view == "cam2") & (m2.frame == 4) & (m2.marker == "M1")].iloc[0]
    img = cv2.imread(str(cam2 / "frame_0004.png"), cv2.IMREAD_UNCHANGED)
    x, y, r = int(round(row.x_px)), int(round(row.y_px)), 4
    a = img[y - r:y + r + 1, x - r:x + r + 1].copy()
    b = img[y - r + 2:y + r + 3, x - r:x + r + 1].copy()
    img[y - r:y + r + 1, x - r:x + r + 1] = b
    img[y - r + 2:y + r + 3, x - r:x + r + 1] = a
    cv2.imwrite(str(cam2 / "frame_0004.png"), img)

    res, m3, err = _track(twin, cam2, tmp_path / "bad")
    flagged = m3[m3["flag"] == "large-ray-gap"]
    assert list(zip(flagged["frame"], flagged["marker"])) == [(4, "M1")]
    # the flag judges the raw detections; the smoother leaves the bad centre out
    gap = float(flagged["ray_gap_mm_raw"].iloc[0])
    m1 = m3.loc[(m3["marker"] == "M1") & (m3["n_views"] == 2), "ray_gap_mm_raw"]
    assert gap > 0.2 and gap > 5 * m1.median()
    assert float(flagged["ray_gap_mm"].iloc[0]) < 0.2 * gap
    m2b = pd.read_csv(tmp_path / "bad" / "markers2d.csv")
    out = m2b[m2b["smooth_outlier"].astype(bool)]
    assert list(zip(out["view"], out["frame"], out["marker"])) == [("cam2", 4, "M1")]
    assert _codes(res["warnings"]) == ["large-ray-gap"]
    w = res["warnings"][0]
    assert w["n_points"] == 1 and w["points"] == [{"frame": 4, "marker": "M1", "ray_gap_mm": pytest.approx(gap, abs=1e-6)}]
    assert w["threshold_mm"]["M1"] == pytest.approx(max(5 * m1.median(), RAY_GAP_FLOOR_MM), abs=1e-5)
    assert any(ln.startswith("WARNING") and "M1: frame 4" in ln for ln in err.splitlines())


def test_track_warns_of_seeded_markers_found_in_few_frames(twin, tmp_path):
    """cam2's M2 painted over (the background's median) in frames 1-7 of 8: found in 1 of 8
    frames.  Markers lost to noise had given exit 0 with an empty warnings list (on a twin with
    extra noise of sd 6: M2 found in 1 of 111 frames, M4 in 2); the clean twin has none."""
    import cv2

    cam2 = tmp_path / "cam2"
    shutil.copytree(twin / "synth/sequence/cam2", cam2)
    m2 = pd.read_csv(twin / "synth/seeds.csv")
    x, y = m2.loc[(m2.view == "cam2") & (m2.marker == "M2"), ["x_px", "y_px"]].to_numpy()[0]
    xi, yi, r = int(round(x)), int(round(y)), 8          # the marker moves a few px over the 8 frames
    for k in range(1, 8):
        f = cam2 / f"frame_{k:04d}.png"
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        img[yi - r:yi + r + 1, xi - r:xi + r + 1] = np.median(img[yi - 3 * r:yi + 3 * r, xi - 3 * r:xi + 3 * r])
        cv2.imwrite(str(f), img)
    res, _, err = _track(twin, cam2, tmp_path / "faint")
    w = [w for w in res["warnings"] if w["code"] == "markers-rarely-found"]
    assert len(w) == 1 and w[0]["markers"] == {"cam2": {"M2": {"found": 1, "frames": 8}}}, res["warnings"]
    assert "cam2: M2 1 of 8" in w[0]["message"]


def test_track_views_swapped_against_the_calibration_are_exchanged(twin, tmp_path):
    """Each --view given the other camera's frames (and seeds named accordingly): the tool had
    worked out that the views were swapped (a view-orientation warning), then written
    markers3d.csv with every point millimetres off and exited 0; then it refused (exit 2).  The
    loop's view-orientation step triangulates each view through the other's camera: the 3-D
    points are the correctly named run's within 1e-6 mm, markers2d.csv keeps the names as
    given.  With --no-loop it is exit 2, nothing written."""
    seeds = pd.read_csv(twin / "synth/seeds.csv")
    seeds["view"] = seeds["view"].map({"cam1": "cam2", "cam2": "cam1"})
    seeds.to_csv(tmp_path / "seeds.csv", index=False)
    clean = pd.read_csv(_track_dir(twin, twin / "synth/sequence/cam2", twin / "synth/seeds.csv", tmp_path / "clean")
                        / "markers3d.csv")
    args = ["track", "--view", f"cam1={twin / 'synth/sequence/cam2'}", "--view", f"cam2={twin / 'synth/sequence/cam1'}",
            "--calibration", twin / "calibrate/calibration.json", "--seeds", tmp_path / "seeds.csv", "--fps", "0.5"]
    r = CliRunner().invoke(cli, [str(a) for a in args + ["-o", tmp_path / "out"]])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "out" / "track.json").read_text())
    w = next(w for w in res["warnings"] if w["code"] == "view-orientation")
    assert w["orientation"] == "swapped" and "look swapped against the calibration" in w["message"]
    step = res["loop"]["steps"][0]
    assert step["effect"] == "view-orientation" and step["ray_gap_rms_mm_before"] > 10 * step["ray_gap_rms_mm_after"]
    both = clean.merge(pd.read_csv(tmp_path / "out" / "markers3d.csv"), on=["frame", "marker"], suffixes=("_c", ""))
    assert len(both) == len(clean)
    for a in "xyz":
        assert np.nanmax(np.abs(both[f"{a}_mm"] - both[f"{a}_mm_c"])) < 1e-6
    m2 = pd.read_csv(tmp_path / "out" / "markers2d.csv")
    assert sorted(m2["view"].unique()) == ["cam1", "cam2"]
    out = tmp_path / "no_loop"
    r = CliRunner().invoke(cli, [str(a) for a in args + ["--no-loop", "-o", out]])
    assert r.exit_code == 2 and "look swapped against the calibration" in r.output, r.output
    assert "sequence/cam2" in r.output and not out.exists()


def _turned_cam2(twin, tmp_path, how: str):
    """cam2's frames of the tiny twin mirrored left-right (``fliplr``) or turned a quarter
    anticlockwise (``rot90``, as np.rot90), and the seeds clicked on them."""
    import cv2
    src = twin / "synth/sequence/cam2"
    dst = tmp_path / f"cam2_{how}"
    dst.mkdir()
    for f in sorted(src.iterdir()):
        im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(dst / f.name), np.ascontiguousarray(im[:, ::-1] if how == "fliplr" else np.rot90(im)))
    h, w = im.shape[:2]
    seeds = pd.read_csv(twin / "synth/seeds.csv")
    c = seeds["view"] == "cam2"
    x, y = seeds.loc[c, "x_px"].to_numpy(), seeds.loc[c, "y_px"].to_numpy()
    seeds.loc[c, "x_px"], seeds.loc[c, "y_px"] = (w - 1 - x, y) if how == "fliplr" else (y, w - 1 - x)
    seeds.to_csv(tmp_path / f"seeds_{how}.csv", index=False)
    return dst, tmp_path / f"seeds_{how}.csv"


@pytest.mark.parametrize("how, said", [("fliplr", "mirrored left-right"), ("rot90", "turned 90 degrees anticlockwise")])
def test_track_view_mirrored_against_the_calibration_is_turned_back(twin, tmp_path, how, said):
    """cam2's frames mirrored left-right or turned a quarter (an export that flips the picture),
    its seeds clicked on them.  A view-orientation warning had stood beside a markers3d.csv of
    points off by the ray gap (exit 0), then the command refused (exit 2).  The loop's first
    step now takes cam2's positions back to the calibration's orientation: the 3-D points are
    the unturned frames' (within 1e-6 mm mirrored, 0.01 mm turned), the step reports the ray gap before and after, and
    markers2d.csv keeps the frames' own pixels.  With --no-loop it is exit 2 naming the view
    and how its frames look, nothing written; without --calibration the frames track in 2-D."""
    turned, seeds = _turned_cam2(twin, tmp_path, how)
    clean = pd.read_csv(_track_dir(twin, twin / "synth/sequence/cam2", twin / "synth/seeds.csv", tmp_path / "clean")
                        / "markers3d.csv")
    out = _track_dir(twin, turned, seeds, tmp_path / "out")
    res = json.loads((out / "track.json").read_text())
    w = next(w for w in res["warnings"] if w["code"] == "view-orientation")
    assert w["view"] == "cam2" and w["orientation"] == said
    step = res["loop"]["steps"][0]
    assert step["effect"] == "view-orientation" and step["effect_params"]["orientation"] == said
    assert step["ray_gap_rms_mm_before"] > 10 * step["ray_gap_rms_mm_after"]
    assert res["loop"]["final"]["model"].startswith("stereo+view-orientation")
    m3 = pd.read_csv(out / "markers3d.csv")
    both = clean.merge(m3, on=["frame", "marker"], suffixes=("_c", ""))
    assert len(both) == len(clean) and np.isfinite(both["x_mm"]).sum() == np.isfinite(both["x_mm_c"]).sum()
    # mirrored, the centres are the unturned frames' to rounding; a quarter turn moves some by a
    # few hundredths of a pixel (the detector's background and noise estimates work along rows):
    # up to 6 um in 3-D, a median under 1 um
    tol = 1e-6 if how == "fliplr" else 0.01
    for a in "xyz":
        d = np.abs(both[f"{a}_mm"] - both[f"{a}_mm_c"])
        assert np.nanmax(d) < tol and np.nanmedian(d) < 1e-3
    m2 = pd.read_csv(out / "markers2d.csv")
    s = pd.read_csv(seeds)
    first = m2[(m2["view"] == "cam2") & (m2["frame"] == 0)].merge(s[s["view"] == "cam2"], on="marker")
    assert np.hypot(first["x_px_x"] - first["x_px_y"], first["y_px_x"] - first["y_px_y"]).max() < 1.5
    args = ["track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view", f"cam2={turned}",
            "--seeds", seeds, "--fps", "0.5"]
    r = CliRunner().invoke(cli, [str(a) for a in args + ["--calibration", twin / "calibrate/calibration.json",
                                                         "--no-loop", "-o", tmp_path / "no_loop"]])
    assert r.exit_code == 2 and f"cam2's frames look {said} against the calibration" in r.output, r.output
    assert str(turned) in r.output and not (tmp_path / "no_loop").exists()
    r = CliRunner().invoke(cli, [str(a) for a in args + ["-o", tmp_path / "two_d"]])
    assert r.exit_code == 0, r.output
    assert pd.read_csv(tmp_path / "two_d" / "markers2d.csv")["found"].mean() > 0.9


def test_track_without_seeds_turns_a_mirrored_view_back(twin, tmp_path):
    """Without seeds the tracks are paired across the views by their ray gaps before any 3-D:
    with cam2's frames mirrored they had paired few tracks, some by chance, and the loop then
    took a view-time-offset for the rest (exit 0, points millimetres off).  The pairing is tried
    with each view turned back (pairing_orientation): mirrored back, every track pairs as on
    the unturned frames, the same number of two-view points, the same ray gaps."""
    turned, _ = _turned_cam2(twin, tmp_path, "fliplr")
    runs = {}
    for name, cam2 in (("clean", twin / "synth/sequence/cam2"), ("mirrored", turned)):
        r = _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view", f"cam2={cam2}",
                    "--calibration", twin / "calibrate/calibration.json", "--fps", "0.5", "-o", tmp_path / name)
        assert r.exit_code == 0, r.output
        runs[name] = json.loads((tmp_path / name / "track.json").read_text())
    c, m = runs["clean"], runs["mirrored"]
    assert "view-orientation" not in [w["code"] for w in c["warnings"]]
    assert [s["effect"] for s in m["loop"]["steps"]][:1] == ["view-orientation"]
    assert m["loop"]["steps"][0]["evidence"]["criterion"] == "median-pair-cost-ratio"
    assert m["summary"]["n_two_view"] == c["summary"]["n_two_view"]
    assert m["summary"]["ray_gap_rms_mm"] == pytest.approx(c["summary"]["ray_gap_rms_mm"], rel=1e-6)


def test_track_warns_when_the_calibration_no_longer_fits(twin, tmp_path):
    """The stereo calibration's rotation turned by 2 degrees (a C-arm moved after it was
    calibrated): every point's rays miss by about as much, which the ray-gap flags, judging
    each point against its marker's median, cannot see (a 1 degree turn and a 5 mm shift on
    the default twin had been exit 0 without a warning).  The reprojection RMS against what
    the calibration's own RMS and the markers' centre error explain says so; the clean twin
    says nothing (test_track_flags_a_point_with_a_large_ray_gap)."""
    from scipy.spatial.transform import Rotation
    cal = json.loads((twin / "calibrate/calibration.json").read_text())
    R = np.asarray(cal["stereo"]["R"])
    cal["stereo"]["R"] = (Rotation.from_euler("y", 2.0, degrees=True).as_matrix() @ R).tolist()
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    r = _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view",
                f"cam2={twin / 'synth/sequence/cam2'}", "--calibration", tmp_path / "cal.json",
                "--seeds", twin / "synth/seeds.csv", "--fps", "0.5", "-o", tmp_path / "out")
    res = json.loads((tmp_path / "out" / "track.json").read_text())
    w = [w for w in res["warnings"] if w["code"] == "calibration-mismatch"]
    assert len(w) == 1 and w[0]["reprojection_rms_px"] > 1.5 * w[0]["expected_px"], res["warnings"]


def test_track_seeds_clicked_off_alike_are_no_jolt(twin, tmp_path):
    """Every seed clicked 3 px to the right (and 1 px down): the frame-shift test had taken the
    clicks for frame 0's predictions and called the picture jolted by 3 px in frame 0 (a
    frame-shifts warning, the positions said to carry it).  Seeds are refined, not measured."""
    seeds = pd.read_csv(twin / "synth/seeds.csv")
    seeds["x_px"] += 3.0
    seeds["y_px"] += 1.0
    seeds.to_csv(tmp_path / "seeds.csv", index=False)
    r = _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view",
                f"cam2={twin / 'synth/sequence/cam2'}", "--calibration", twin / "calibrate/calibration.json",
                "--seeds", tmp_path / "seeds.csv", "--fps", "0.5", "-o", tmp_path / "out")
    res = json.loads((tmp_path / "out" / "track.json").read_text())
    assert not [e for e in res["events"] if e["kind"] == "frame-shift"]
    assert res["warnings"] == [], res["warnings"]


def test_track_output_inside_a_view_folder_is_exit_2(twin, tmp_path):
    """-o inside a --view folder of frames: the run wrote overlay.png and track.png among the
    frames, and the next run on that folder failed on them.  Exit 2 before anything is written."""
    cam1 = tmp_path / "cam1"
    shutil.copytree(twin / "synth/sequence/cam1", cam1)
    before = sorted(p.name for p in cam1.iterdir())
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={cam1}", "--fps", "0.5", "-o", str(cam1 / "out")])
    assert r.exit_code == 2 and "inside view cam1's folder of frames" in r.output, r.output
    assert sorted(p.name for p in cam1.iterdir()) == before


def test_track_names_a_seeded_marker_much_larger_than_the_rest():
    """A 16 px bead seeded among 4 px ones: the diameter comes from the majority, the big bead
    is rarely found, and the markers-rarely-found warning had said only "too faint for the
    noise, or hidden" (the probe: found in 24 and 18 of 200 frames).  The warning now says how
    large the seeded marker looks in the first frame (probed at 2-4 times the diameter) and
    that such sizes need separate runs; a small marker rarely found gets no such words."""
    import cv2

    from bsipipe.commands.track import _larger_markers_said
    rng = np.random.default_rng(0)
    img = 180.0 + rng.normal(0, 2.0, (200, 200))
    yy, xx = np.mgrid[:200, :200]
    for (x, y, d) in ((60, 60, 16.0), (140, 60, 4.0), (100, 140, 4.0)):
        r2 = (xx - x) ** 2 + (yy - y) ** 2
        img *= 1.0 - 0.4 * np.sqrt(np.clip(1.0 - r2 / (d / 2) ** 2, 0, None))
    img = cv2.GaussianBlur(img, (0, 0), 0.7).astype(np.uint8)
    seeds = pd.DataFrame({"view": "cam2", "marker": ["BIG", "S1", "S2"], "x_px": [60.5, 140.0, 100.0],
                          "y_px": [59.5, 60.0, 140.0]})
    w = [{"code": "markers-rarely-found", "message": "track: ...",
          "markers": {"cam2": {"BIG": {"found": 3, "frames": 50}, "S1": {"found": 3, "frames": 50}}}}]
    _larger_markers_said(w, {"cam2": img}, seeds, {"cam2": 4.0}, "dark")
    print(w[0]["message"])
    assert set(w[0]["larger_markers_px"]["cam2"]) == {"BIG"}
    assert 12 <= w[0]["larger_markers_px"]["cam2"]["BIG"] <= 20 and "separate runs" in w[0]["message"]


def test_calibration_mismatch_allows_for_the_loops_jolt_estimates():
    """The study's twin with 5 px jolts, frame-shift kept by the loop: the two-view points
    reprojected 2.0 times what the calibration and the centres explain (each frame's shift is
    an estimate from its few markers), its 3-D error 0.02 mm, and a calibration-mismatch
    warning said the C-arms had moved.  With frame-shift in the final model the bar is 3 times
    (a C-arm moved 5 mm or turned 3 degrees: 4.1 and 5.8)."""
    from bsipipe.commands.track import _calibration_fit_warning
    table = pd.DataFrame({"view": ["cam1", "cam2"] * 50, "found": True, "snr": 10.0})
    centre = float(np.sqrt(2.0 * (0.798 / 10.0) ** 2))
    expected = float(np.hypot(0.066, centre))
    for model, factor, warned in (("stereo+frame-shift", 2.0, False), ("stereo", 2.0, True),
                                  ("stereo+frame-shift", 4.1, True)):
        loop = {"final": {"reprojection_rms_px": factor * 1.01 * expected, "ray_gap_rms_mm": 0.1, "model": model}}
        w = _calibration_fit_warning(loop, table, 0.066, ("cam1", "cam2"))
        assert (w is not None) == warned, (model, factor)


def test_calibration_mismatch_without_a_stereo_rms_in_the_file(twin, tmp_path):
    """A calibration.json with no ``stereo.rms_px`` (another tool's, or a rig's true cameras)
    had left the calibration-mismatch check out, unlogged: cam2's frames cropped 15 px
    since the calibration (a frame grabber's offset) gave 3-D points about 3 mm off on the
    probe's twin with only large-ray-gap flags.  0.5 px is assumed for such a file and the
    warning says so; the same file uncropped says nothing."""
    import cv2
    cal = json.loads((twin / "calibrate/calibration.json").read_text())
    del cal["stereo"]["rms_px"]
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    cam2 = tmp_path / "cam2"
    cam2.mkdir()
    for f in sorted((twin / "synth/sequence/cam2").glob("*.png")):
        img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(cam2 / f.name), np.pad(img, ((0, 8), (0, 15)), mode="edge")[8:, 15:])
    seeds = pd.read_csv(twin / "synth/seeds.csv")
    seeds.loc[seeds["view"] == "cam2", "x_px"] -= 15.0
    seeds.loc[seeds["view"] == "cam2", "y_px"] -= 8.0
    seeds.to_csv(tmp_path / "seeds.csv", index=False)
    for name, c2, s, warned in (("clean", twin / "synth/sequence/cam2", twin / "synth/seeds.csv", False),
                                ("cropped", cam2, tmp_path / "seeds.csv", True)):
        _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view", f"cam2={c2}",
                "--calibration", tmp_path / "cal.json", "--seeds", s, "--fps", "0.5", "-o", tmp_path / name)
        res = json.loads((tmp_path / name / "track.json").read_text())
        w = [w for w in res["warnings"] if w["code"] == "calibration-mismatch"]
        print(name, [(x["reprojection_rms_px"], x["expected_px"]) for x in w])
        assert bool(w) == warned, res["warnings"]
        if warned:
            assert w[0]["calibration_rms_assumed"] and "assumed: the file gives none" in w[0]["message"]


def test_a_view_filmed_at_half_the_rate_gets_its_own_fps(twin, tmp_path):
    """cam1 kept every second frame (a C-arm at half the other's rate) and one --fps for both:
    frames paired by index, 3-D points 0.33 mm RMS off on the probe's twin, and the only
    warning said the longer view's last frames had no partner.  The warning now names the
    whole-number ratio and the per-view --fps; given them (--fps cam1=F/2 --fps cam2=F) the
    views are paired by time, as sources at different rates are, and every reference stays
    where the full-rate run puts it."""
    import cv2
    src = sorted((twin / "synth/sequence/cam1").glob("*.png"))
    half = tmp_path / "cam1"
    half.mkdir()
    for k, f in enumerate(src[::2]):
        cv2.imwrite(str(half / f"frame_{k:04d}.png"), cv2.imread(str(f), cv2.IMREAD_UNCHANGED))
    n2 = len(list((twin / "synth/sequence/cam2").glob("*.png")))
    if n2 % 2:                       # a whole-number ratio of the counts
        pytest.skip("odd frame count")
    fps = float(SYNTH_TINY["sequence"]["fps"])
    base = ["track", "--view", f"cam1={half}", "--view", f"cam2={twin / 'synth/sequence/cam2'}",
            "--calibration", twin / "calibrate/calibration.json", "--seeds", twin / "synth/seeds.csv"]
    _invoke(*base, "--fps", fps, "-o", tmp_path / "one")
    res = json.loads((tmp_path / "one" / "track.json").read_text())
    w = [w for w in res["warnings"] if w["code"] == "frame-count-mismatch"]
    assert len(w) == 1 and f"--fps cam1={fps / 2:g} --fps cam2={fps:g}" in w[0]["message"], res["warnings"]
    _invoke(*base, "--fps", f"cam1={fps / 2:g}", "--fps", f"cam2={fps:g}", "-o", tmp_path / "two")
    res = json.loads((tmp_path / "two" / "track.json").read_text())
    assert res["views"]["cam1"]["time_source"] == f"--fps {fps / 2:g}"
    assert "frame-count-mismatch" not in _codes(res["warnings"])
    _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view", f"cam2={twin / 'synth/sequence/cam2'}",
            "--calibration", twin / "calibrate/calibration.json", "--seeds", twin / "synth/seeds.csv",
            "--fps", fps, "-o", tmp_path / "full")
    mean = {k: pd.read_csv(tmp_path / k / "markers3d.csv", dtype={"marker": str}).groupby("marker")[
        ["x_mm", "y_mm", "z_mm"]].mean() for k in ("two", "full", "one")}
    refs = [m for m in mean["full"].index if m.startswith("R")]
    assert refs
    d_two = np.linalg.norm(mean["two"].loc[refs].to_numpy() - mean["full"].loc[refs].to_numpy(), axis=1)
    print("references, per-view fps vs full rate (mm):", np.round(d_two, 4))
    assert d_two.max() < 0.02
    # the moving markers at the same times: paired by time they follow the full-rate run;
    # paired by index (one --fps) they lag it
    tabs = {k: pd.read_csv(tmp_path / k / "markers3d.csv", dtype={"marker": str}) for k in ("two", "one", "full")}
    for t in tabs.values():
        t["t"] = np.rint(t["time_s"] * 1000).astype(int)
    dev = {}
    for k in ("two", "one"):
        m = tabs[k].merge(tabs["full"], on=["marker", "t"], suffixes=("", "_f"))
        m = m[~m["marker"].str.startswith("R")].dropna(subset=["x_mm", "x_mm_f"])
        dev[k] = float(np.sqrt(np.mean(np.sum((m[["x_mm", "y_mm", "z_mm"]].to_numpy()
                                               - m[["x_mm_f", "y_mm_f", "z_mm_f"]].to_numpy()) ** 2, axis=1))))
    print("moving markers vs the full-rate run at the same times (mm RMS):", dev)
    assert dev["two"] < 0.03 and dev["one"] > 2 * dev["two"]
    # a view that is not given, or both forms mixed: exit 2 naming the option
    r = CliRunner().invoke(cli, [str(a) for a in base] + ["--fps", f"cam1={fps}", "-o", str(tmp_path / "x")])
    assert r.exit_code == 2 and "fps" in r.output, r.output
    r = CliRunner().invoke(cli, [str(a) for a in base] + ["--fps", "2", "--fps", "cam1=1", "-o", str(tmp_path / "y")])
    assert r.exit_code == 2 and "--fps" in r.output, r.output


def test_fps_over_stamps_wins_over_a_videos_container_rate(twin, tmp_path):
    """A video exported at a container rate of 25 frames/s for an acquisition at the twin's
    rate: its times ran 6.25 times too fast and --fps could not say otherwise (an fps-ignored
    warning).  --fps-over-stamps makes the rate given win, and the warning points to it."""
    import cv2
    fps = float(SYNTH_TINY["sequence"]["fps"])
    views = []
    for v in ("cam1", "cam2"):
        frames = sorted((twin / "synth/sequence" / v).glob("*.png"))
        first = cv2.imread(str(frames[0]), cv2.IMREAD_GRAYSCALE)
        out = tmp_path / f"{v}.avi"
        w = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, first.shape[::-1], isColor=False)
        for f in frames:
            w.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
        w.release()
        views += ["--view", f"{v}={out}"]
    base = ["track", *views, "--seeds", twin / "synth/seeds.csv", "--fps", fps, "--no-loop"]
    _invoke(*base, "-o", tmp_path / "stamps")
    res = json.loads((tmp_path / "stamps" / "track.json").read_text())
    w = [w for w in res["warnings"] if w["code"] == "fps-ignored"]
    assert len(w) == 1 and "--fps-over-stamps" in w[0]["message"]
    t = pd.read_csv(tmp_path / "stamps" / "markers2d.csv")
    assert t["time_s"].max() == pytest.approx((t["frame"].max()) / 25.0, rel=1e-3)
    _invoke(*base, "--fps-over-stamps", "-o", tmp_path / "given")
    res = json.loads((tmp_path / "given" / "track.json").read_text())
    assert "fps-ignored" not in _codes(res["warnings"])
    assert "over the source's own stamps" in res["views"]["cam1"]["time_source"]
    t = pd.read_csv(tmp_path / "given" / "markers2d.csv")
    np.testing.assert_allclose(t["time_s"], t["frame"] / fps)


def test_a_rate_for_the_view_without_stamps_only(twin, tmp_path):
    """A stamped video for cam1 beside cam2's PNG folder: --fps cam2=F had been refused ("a
    frame rate per view must give every view and only them"); it is taken, cam1 keeping its
    video's times.  A view whose frames have no stamps and no rate is exit 2 naming it; and a
    source's stamps used at the rate --fps gives are named as the source's (it had said
    "--fps 2")."""
    import cv2
    fps = float(SYNTH_TINY["sequence"]["fps"])
    frames = sorted((twin / "synth/sequence/cam1").glob("*.png"))
    first = cv2.imread(str(frames[0]), cv2.IMREAD_GRAYSCALE)
    video = tmp_path / "cam1.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), fps, first.shape[::-1], isColor=False)
    for f in frames:
        w.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    w.release()
    base = ["track", "--view", f"cam1={video}", "--view", f"cam2={twin / 'synth/sequence/cam2'}",
            "--seeds", twin / "synth/seeds.csv", "--no-loop"]
    _invoke(*base, "--fps", f"cam2={fps:g}", "-o", tmp_path / "mixed")
    res = json.loads((tmp_path / "mixed" / "track.json").read_text())
    assert res["views"]["cam1"]["time_source"] == "the source's time stamps"
    assert res["views"]["cam2"]["time_source"] == f"--fps {fps:g}"
    r = CliRunner().invoke(cli, [str(a) for a in base] + ["--fps", f"cam1={fps:g}", "-o", str(tmp_path / "no")])
    assert r.exit_code == 2 and "none for cam2, whose frames have no time stamps" in r.output, r.output
    _invoke(*base, "--fps", f"{fps:g}", "-o", tmp_path / "same")
    res = json.loads((tmp_path / "same" / "track.json").read_text())
    assert res["views"]["cam1"]["time_source"] == "the source's time stamps"


def test_two_view_automatic_tracks_without_a_calibration_keep_apart(twin, tmp_path):
    """Without seeds and without a calibration nothing pairs the views' tracks, yet each view
    numbered its own M1, M2, ... and the XMALab 2-D file put cam1's M3 beside an unrelated cam2
    M3 as one marker (the probe: a reference beside clutter).  The second view's names carry
    the view, and track.json says why."""
    _invoke("track", "--view", f"cam1={twin / 'synth/sequence/cam1'}", "--view",
            f"cam2={twin / 'synth/sequence/cam2'}", "--fps", "0.5", "-o", tmp_path / "o")
    t = pd.read_csv(tmp_path / "o" / "markers2d.csv", dtype={"marker": str})
    assert t.loc[t["view"] == "cam2", "marker"].str.startswith("cam2:").all()
    assert not t.loc[t["view"] == "cam1", "marker"].str.contains(":").any()
    header = (tmp_path / "o" / "xmalab_2d.csv").read_text().splitlines()[0].split(",")
    cam1_markers = {h.rsplit("_", 2)[0] for h in header}
    assert all(m.startswith("cam2:") or not m.startswith("cam") for m in cam1_markers)
    res = json.loads((tmp_path / "o" / "track.json").read_text())
    assert "not paired" in res["cross_view_names"]["rule"]


def test_an_undeclared_boundary_one_shape_cannot_show_is_warned(tmp_path):
    """Without --boundary and with one height/diameter the force cannot tell bonded platens
    from free ones; a no-slip 18 x 6 mm specimen had been fitted at 2.2 times its modulus with
    only an INFO line (hidden by -q, not in fit.json).  boundary-undeclared says so; declared
    (test_fit_without_warnings_when_parameters_are_determined) it is not said."""
    _invoke("fit-ogden", FAST_LOG, "--no-loop", "--bootstrap", "0", "-o", tmp_path / "o")
    fit = json.loads((tmp_path / "o" / "fit.json").read_text())
    w = [w for w in fit["warnings"] if w["code"] == "boundary-undeclared"]
    assert len(w) == 1 and "--boundary no-slip" in w[0]["message"]


def test_a_drift_no_load_cell_has_is_warned():
    """load-baseline-drift that moves a log's zero by a tenth of its peak force over the record
    (three specimens fitted together, one 10 % shorter than declared: -1.1 mN/s, 70 mN) is
    warned: it stands in for another effect.  A drift of a fraction of a per cent is not."""
    from types import SimpleNamespace

    from bsipipe.commands.fit_ogden import _drift_implausible
    t = np.linspace(0.0, 65.0, 651)
    lg = SimpleNamespace(name="c", time_s=t, force_n=0.7 * (t / 65.0) ** 3)
    def fit(drift):                     # a fit's per-log parameters (FitResult.log_params)
        return SimpleNamespace(log_params=lambda i: {"drift_n_per_s": drift})

    w = _drift_implausible(fit(-1.1e-3), [lg])
    assert len(w) == 1 and w[0]["code"] == "implausible-drift" and w[0]["moved_n"] == pytest.approx(0.0715)
    assert _drift_implausible(fit(-2e-5), [lg]) == []


def test_track_takes_opencv_and_bouguet_stereo_calibrations(twin, tmp_path):
    """The twin's calibration.json written as OpenCV's stereo_calib sample writes a pair
    (intrinsics.yml with M1, D1, M2, D2; extrinsics.yml with R, T) and as Bouguet's toolbox's
    Calib_Results_stereo.mat (fc, cc, kc per side, om, T, nx, ny): track through each gives the
    3-D points of calibration.json to 1e-9 mm (the first --view is camera 1 / left); so does
    calibrate's own opencv_stereo.yml, which reads back to calibration.json's numbers exactly."""
    import shutil

    import cv2
    from scipy.io import savemat
    cal = json.loads((twin / "calibrate/calibration.json").read_text())
    a, b = cal["stereo"]["views"]
    va, vb = cal["views"][a], cal["views"][b]
    if len(va["dist_coeffs"]) > 5 or len(vb["dist_coeffs"]) > 5 or va.get("s_distortion") or va.get("local_distortion"):
        pytest.skip("the tiny twin's calibration is beyond OpenCV's five coefficients")
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in (("M1", va["camera_matrix"]), ("D1", [va["dist_coeffs"]]), ("M2", vb["camera_matrix"]),
                 ("D2", [vb["dist_coeffs"]])):
        fs.write(k, np.asarray(v, float))
    fs.release()
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("R", np.asarray(cal["stereo"]["R"], float))
    fs.write("T", np.asarray(cal["stereo"]["T_mm"], float).reshape(3, 1))
    fs.release()
    K1, K2 = np.asarray(va["camera_matrix"]), np.asarray(vb["camera_matrix"])
    om, _ = cv2.Rodrigues(np.asarray(cal["stereo"]["R"], float))
    savemat(str(tmp_path / "Calib_Results_stereo.mat"), {
        "fc_left": [[K1[0, 0]], [K1[1, 1]]], "cc_left": [[K1[0, 2]], [K1[1, 2]]], "alpha_c_left": 0.0,
        "kc_left": np.asarray(va["dist_coeffs"], float)[:, None], "fc_right": [[K2[0, 0]], [K2[1, 1]]],
        "cc_right": [[K2[0, 2]], [K2[1, 2]]], "alpha_c_right": 0.0, "kc_right": np.asarray(vb["dist_coeffs"], float)[:, None],
        "om": om, "T": np.asarray(cal["stereo"]["T_mm"], float)[:, None],
        "nx": float(va["image_size"][0]), "ny": float(va["image_size"][1])})
    ref = pd.read_csv(_track_dir(twin, twin / "synth/sequence/cam2", twin / "synth/seeds.csv", tmp_path / "json")
                      / "markers3d.csv")
    # calibrate's own OpenCV export of the pair, read back
    from bsipipe.io.stereo_calibration import read_stereo_calibration
    assert cal["stereo"]["opencv"]["written"] == "opencv_stereo.yml"
    shutil.copy(twin / "calibrate/opencv_stereo.yml", tmp_path / "opencv_stereo.yml")
    back = read_stereo_calibration(tmp_path / "opencv_stereo.yml", [a, b])
    for v in (a, b):
        assert back["views"][v]["camera_matrix"] == cal["views"][v]["camera_matrix"]
        assert back["views"][v]["dist_coeffs"] == cal["views"][v]["dist_coeffs"]
        assert back["views"][v]["image_size"] == cal["views"][v]["image_size"]
    assert back["stereo"]["R"] == cal["stereo"]["R"] and back["stereo"]["T_mm"] == cal["stereo"]["T_mm"]
    for name in ("intrinsics.yml", "extrinsics.yml", "Calib_Results_stereo.mat", "opencv_stereo.yml"):
        r = _invoke("track", "--view", f"{a}={twin / 'synth/sequence' / a}", "--view", f"{b}={twin / 'synth/sequence' / b}",
                    "--calibration", tmp_path / name, "--seeds", twin / "synth/seeds.csv", "--fps", "0.5",
                    "-o", tmp_path / name.replace(".", "_"))
        m3 = pd.read_csv(tmp_path / name.replace(".", "_") / "markers3d.csv")
        assert len(m3) == len(ref)
        for c in ("x_mm", "y_mm", "z_mm"):
            assert np.nanmax(np.abs(m3[c] - ref[c])) < 1e-9, (name, c)
