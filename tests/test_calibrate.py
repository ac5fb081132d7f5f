"""Calibration on real data (OpenCV's stereo chessboard, discorpy's X-ray dot grid) and the
``bsipipe calibrate`` command's files and errors.

References: ``tests/data/real/*/PROVENANCE.md`` (from shared/data/real/README.md).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.imaging.calibrate import (CameraModel, ModelSpec, ViewData, calibrate_camera, calibrate_with_rejection,
                                       heldout_error, stereo_calibrate)
from bsipipe.imaging.distortion import RadialDistortion, fit_straightness
from bsipipe.imaging.gridfind import detect_blobs, find_chessboard, lattice_indices
from bsipipe.io.mayacam import read_mayacam

REAL = Path(__file__).parent / "data" / "real"
STEREO = REAL / "opencv_stereo"
DOTS = REAL / "xray_dot_grid_discorpy"


def _chessboard_views(side: str, half_window: int | None = 11) -> list[ViewData]:
    out = []
    for f in sorted(STEREO.glob(f"{side}*.jpg")):
        d = find_chessboard(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), (9, 6), 25.0, subpix_half_window=half_window)
        out.append(ViewData(f.name[len(side):], d.image_points, d.object_points, d.ids))
    return out


@pytest.fixture(scope="module")
def left_views():
    return _chessboard_views("left")


@pytest.fixture(scope="module")
def right_views():
    return _chessboard_views("right")


def _calibrate_images(folder: Path, images: dict, *options: str):
    """Copy the real chessboard ``images`` (name in ``folder`` -> file of the pair) into
    ``folder`` and calibrate them as one camera (``--images``, chessboard 9x6, 25 mm unless
    ``options`` say otherwise); returns the click result and the output folder."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, src in images.items():
        shutil.copy(src, folder / name)
    out = folder.parent / "out"
    args = {"--pattern": "chessboard", "--grid": "9x6", "--spacing-mm": "25"}
    opts = list(options)
    for k in list(args):
        if k in opts:
            del args[k]
    r = CliRunner().invoke(cli, ["calibrate", "--images", str(folder), *[x for kv in args.items() for x in kv],
                                 *opts, "-o", str(out)])
    print(r.output)
    return r, out


def test_real_chessboard_left_matches_opencv(left_views):
    """13 left views, 25 mm: RMS 0.408 px (default 5-coefficient model, all views) and the
    CALIB_FIX_ASPECT_RATIO intrinsics of left_intrinsics.yml (flags: 2, aspectRatio 1).

    Apples to apples: the reference detection is OpenCV's calibration sample
    (findChessboardCorners + cornerSubPix with an 11x11 half window), so the same window is
    used here; fx = fy is compared with the run that fixes the aspect ratio, as the stored
    result does; the RMS with the free-aspect default model, as the README states it.
    """
    assert len(left_views) == 13
    cal = calibrate_camera(left_views, (640, 480))
    print(f"left, default model: RMS {cal.rms_px:.4f} px (reference 0.408)")
    assert abs(cal.rms_px - 0.408) < 0.02
    fix = calibrate_camera(left_views, (640, 480), ModelSpec(fix_aspect_ratio=True))
    K = fix.camera.camera_matrix
    got = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    ref = {"fx": 535.9, "fy": 535.9, "cx": 342.3, "cy": 235.6}
    print("left, fixed aspect:", {k: round(v, 3) for k, v in got.items()}, "reference", ref,
          "std", {k: round(fix.std[k], 3) for k in ref})
    for k in ref:
        assert abs(got[k] - ref[k]) / ref[k] < 0.005, k
    assert K[0, 0] == K[1, 1]
    # OpenCV's standard deviations are there and small for a 13-view calibration
    assert all(0 < fix.std[k] < 2.0 for k in ("fx", "cx", "cy"))
    # view 2 is the worst, about 1.2 px (the README)
    worst = max(cal.per_view_rms_px, key=cal.per_view_rms_px.get)
    assert worst == "02.jpg" and 1.0 < cal.per_view_rms_px[worst] < 1.4


def test_noisy_but_consistent_view_is_flagged_and_kept(left_views):
    """View 2's corners are poor (1.2 px, the README) but consistent with the other views:
    leaving it out changes their RMS by under 5 %, so it is kept, as OpenCV keeps it, and
    flagged with the reason."""
    cal = calibrate_with_rejection(left_views, (640, 480))
    assert cal.rejected == {} and len(cal.views) == 13
    assert list(cal.flagged) == ["02.jpg"] and cal.flagged["02.jpg"].startswith("kept: reprojection RMS 1.2")
    assert abs(cal.rms_px - 0.408) < 0.02


def test_mislabelled_view_is_reported_and_left_out(left_views):
    """A board with two corner rows swapped (a detector that mis-orders rows) pulls the
    model (leaving it out lowers the others' RMS by ~20-30 %): it is left out and reported,
    and the result equals the calibration without that view.  (A mirrored labelling would
    not do: on a planar board it is just another valid pose.)"""
    bad = left_views[4]
    rows = bad.image_points.reshape(6, 9, 2).copy()
    rows[[2, 3]] = rows[[3, 2]]
    views = list(left_views)
    views[4] = ViewData(bad.name, rows.reshape(-1, 2), bad.object_points, bad.ids)
    cal = calibrate_with_rejection(views, (640, 480))
    assert list(cal.rejected) == [bad.name]
    assert cal.rejected[bad.name].startswith("outlier: reprojection RMS")
    clean = calibrate_with_rejection([v for v in left_views if v.name != bad.name], (640, 480))
    print(f"mislabelled view left out: RMS {cal.rms_px:.4f} px (without that view: {clean.rms_px:.4f} px)")
    assert abs(cal.rms_px - clean.rms_px) < 1e-6
    assert "02.jpg" in cal.flagged
    kept = calibrate_with_rejection(views, (640, 480), reject_outliers=False)
    assert kept.rejected == {} and len(kept.views) == 13 and kept.rms_px > 1.0


def test_heldout_error_is_leave_one_view_out(left_views):
    cal = calibrate_camera(left_views, (640, 480))
    h, per = heldout_error(cal)
    print(f"left: RMS {cal.rms_px:.4f} px, held-out {h:.4f} px")
    assert set(per) == {v.name for v in left_views}
    # a view the fit has not seen is predicted a little worse than the views it fitted
    assert cal.rms_px < h < 1.2 * cal.rms_px


def test_real_stereo_baseline(left_views, right_views):
    left = calibrate_camera(left_views, (640, 480))
    right = calibrate_camera(right_views, (640, 480))
    print(f"right: RMS {right.rms_px:.4f} px (reference 0.458)")
    assert abs(right.rms_px - 0.458) < 0.02
    st = stereo_calibrate(left.camera, right.camera, ("left", "right"), {v.name: v for v in left_views},
                          {v.name: v for v in right_views})
    base = float(np.linalg.norm(st.T_mm))
    print(f"stereo: baseline {base:.3f} mm (reference 83.6), RMS {st.rms_px:.4f} px (reference 0.447)")
    assert abs(base - 83.6) < 0.5
    assert abs(st.rms_px - 0.447) < 0.02


def test_one_folder_given_for_both_stereo_cameras_is_exit_2(tmp_path):
    """The same images for both C-arms (one folder twice, or a copy): exit 1 had said the
    relative poses disagree ("median 1.71e-06 deg ... names shifted?") when they agree exactly."""
    (tmp_path / "left").mkdir()
    for f in sorted(STEREO.glob("left*.jpg"))[:6]:
        shutil.copy(f, tmp_path / "left" / f.name)
    shutil.copytree(tmp_path / "left", tmp_path / "copy")
    for b in ("left", "copy"):
        out = tmp_path / f"out_{b}"
        r = CliRunner().invoke(cli, ["calibrate", "--stereo", f"a={tmp_path / 'left'}", "--stereo", f"b={tmp_path / b}",
                                     "--pattern", "chessboard", "--grid", "9x6", "--spacing-mm", "25", "--no-loop",
                                     "-o", str(out)])
        assert r.exit_code == 2 and "every image of camera b is one of camera a's" in r.output, r.output
        assert str(tmp_path / b) in r.output and not out.exists()


def test_calibrate_command_stereo_files(tmp_path):
    """The contract's --stereo form on the real pair: calibration.json keys, MayaCam files
    that parse, residual figures; the loop report in its contract shape."""
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
        for f in STEREO.glob(f"{side}*.jpg"):
            shutil.copy(f, tmp_path / side / f.name[len(side):])  # same names in both folders
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["calibrate", "--stereo", f"left={tmp_path / 'left'}", "--stereo",
                                 f"right={tmp_path / 'right'}", "--pattern", "chessboard", "--grid", "9x6",
                                 "--spacing-mm", "25", "--subpix-window-px", "11", "--no-loop", "-o", str(out)])
    print(r.output)
    assert r.exit_code == 0, r.output
    d = json.loads((out / "calibration.json").read_text())
    for name in ("left", "right"):
        v = d["views"][name]
        for key in ("image_size", "camera_matrix", "dist_model", "dist_coeffs", "rms_px", "per_image_rms_px",
                    "heldout_rms_px", "std", "rejected_views"):
            assert key in v, key
        assert v["image_size"] == [640, 480]
        # the default rule leaves out each camera's blurred view, and says so
        assert all("outlier" in why for why in v["rejected_views"].values())
        assert len(v["per_image_rms_px"]) + len(v["rejected_views"]) == 13
        cm = CameraModel.from_dict(v)  # calibration.json gives the camera back
        pose = v["poses"][next(iter(v["per_image_rms_px"]))]
        assert cm.project(np.zeros((1, 3)), pose["rvec"], pose["tvec_mm"]).shape == (1, 2)
        m = read_mayacam(out / f"mayacam_{name}.txt")
        assert np.allclose(m["camera_matrix"], v["camera_matrix"], rtol=1e-9)
        assert (out / f"residuals_{name}.png").stat().st_size > 1000
    s = d["stereo"]
    assert s["views"] == ["left", "right"] and abs(np.linalg.norm(s["T_mm"]) - 83.6) < 0.5
    assert np.allclose(np.asarray(s["R"]) @ np.asarray(s["R"]).T, np.eye(3), atol=1e-9)
    # MayaCam extrinsics agree with the stereo result: x_right = R x_left + T
    ml, mr = read_mayacam(out / "mayacam_left.txt"), read_mayacam(out / "mayacam_right.txt")
    assert np.allclose(mr["R"], np.asarray(s["R"]) @ ml["R"], atol=1e-9)
    assert np.allclose(mr["t_mm"], np.asarray(s["R"]) @ ml["t_mm"] + s["T_mm"], atol=1e-6)
    assert d["loop"] is None and "inputs_sha256" in d["provenance"]


@pytest.mark.parametrize("case", ["exchanged", "shifted", "unpaired"])
def test_stereo_pairs_that_were_not_taken_together(tmp_path, case):
    """Stereo extrinsics come from same-named files; a right folder whose names were
    exchanged (01 <-> 04, 07 <-> 12), shifted by one, or lacking two frames is what a real
    export can give.  Exchanged pairs are left out and named (their relative pose 16 deg and
    109 mm from the others'): the baseline stays within 0.5 mm of 83.6 (it had been 168.6 mm,
    exit 0); names shifted throughout are exit 1 naming the disagreement (RMS 58 px, exit 0
    before); frames without a partner are named in a warning (they had been dropped without a
    word)."""
    for side in ("left", "right"):
        (tmp_path / side).mkdir()
    for f in STEREO.glob("left*.jpg"):
        shutil.copy(f, tmp_path / "left" / f.name[4:])
    names = sorted(f.name[5:] for f in STEREO.glob("right*.jpg"))
    if case == "exchanged":
        swap = {"01.jpg": "04.jpg", "04.jpg": "01.jpg", "07.jpg": "12.jpg", "12.jpg": "07.jpg"}
        dest = {n: swap.get(n, n) for n in names}
    elif case == "shifted":
        dest = dict(zip(names, names[1:] + names[:1]))
    else:
        dest = {n: n for n in names if n not in ("05.jpg", "06.jpg")}
    for n, d in dest.items():
        shutil.copy(STEREO / f"right{n}", tmp_path / "right" / d)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["calibrate", "--stereo", f"left={tmp_path / 'left'}", "--stereo",
                                 f"right={tmp_path / 'right'}", "--pattern", "chessboard", "--grid", "9x6",
                                 "--spacing-mm", "25", "--subpix-window-px", "11", "--no-loop", "-o", str(out)])
    print(r.output)
    if case == "shifted":
        assert r.exit_code == 1 and "relative poses of left and right disagree" in r.output and not out.exists()
        return
    assert r.exit_code == 0, r.output
    d = json.loads((out / "calibration.json").read_text())
    s = d["stereo"]
    assert abs(s["baseline_mm"] - 83.6) < 0.5
    codes = {w["code"]: w for w in d["warnings"]}
    if case == "exchanged":
        assert set(s["rejected_frames"]) == {"01.jpg", "04.jpg", "07.jpg", "12.jpg"}
        assert "stereo-pairs-left-out" in codes and not set(s["frames"]) & set(s["rejected_frames"])
        assert all(s["pair_deviation"][n]["deg"] > 10 for n in s["rejected_frames"])
        assert max(v["deg"] for n, v in s["pair_deviation"].items() if n not in s["rejected_frames"]) < 2
    else:
        assert s["unpaired_frames"] == {"left": ["05.jpg", "06.jpg"]} and s["rejected_frames"] == {}
        assert "stereo-unpaired-frames" in codes and "05.jpg" in codes["stereo-unpaired-frames"]["message"]


def test_squares_counted_for_corners_names_the_board(tmp_path):
    """--grid 10x7 for the 9x6-corner board (its squares counted): no image shows a 10x7
    board; the one it does show is named and the exit is 2 (bad input), not 1 with 'no 10x7
    chessboard found'."""
    src = tmp_path / "img"
    r, out = _calibrate_images(src, {f"left{n}.jpg": STEREO / f"left{n}.jpg" for n in ("01", "03", "04")},
                               "--grid", "10x7")
    assert r.exit_code == 2 and "has 9x6 inner corners: is it --grid 9x6?" in r.output, r.output
    assert str(src / "left01.jpg") in r.output and not out.exists()


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_a_subpix_window_wider_than_the_corners_is_warned_about(tmp_path, scale):
    """The left views at half size (corners 13-16 px apart at the closest in a view): the
    default cornerSubPix half window of 11 px holds neighbouring corners (RMS 1.36 px, fx 276,
    a view rejected with a hint at --grid) and a subpix-window-large warning names
    --subpix-window-px auto; at full size (22-30 px) it is not warned about."""
    folder = tmp_path / "img"
    folder.mkdir()
    for f in sorted(STEREO.glob("left*.jpg")):
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(folder / f"{f.stem}.png"), cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    r, out = _calibrate_images(folder, {}, "--no-loop")
    assert r.exit_code == 0, r.output
    w = [x for x in json.loads((out / "calibration.json").read_text())["warnings"] if x["code"] == "subpix-window-large"]
    assert bool(w) == (scale < 1)
    if w:
        assert "--subpix-window-px auto" in w[0]["message"] and w[0]["half_window_px"] == 11


def test_config_grid_as_a_list_and_every_bad_key_named(tmp_path):
    """A calibrate config's grid as [COLS, ROWS] (as synth's config writes it) is COLSxROWS (it
    had been refused); a camera name with a / (it names files) is refused; a config with
    several bad keys names all of them, not 'and 2 more problems'."""
    src = tmp_path / "img"
    src.mkdir()
    for n in ("01", "03", "04"):
        shutil.copy(STEREO / f"left{n}.jpg", src)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"images: {src}\npattern: chessboard\ngrid: [9, 6]\nspacing_mm: 25\nloop: false\n")
    r = CliRunner().invoke(cli, ["calibrate", str(cfg), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "out" / "calibration.json").read_text())["provenance"]["config"]["grid"] == "9x6"
    r = CliRunner().invoke(cli, ["calibrate", "--view", f"C-arm 1/left={src}", "--pattern", "chessboard", "--grid", "9x6",
                                 "--spacing-mm", "25", "-o", str(tmp_path / "out3")])
    assert r.exit_code == 2 and "camera name 'C-arm 1/left' cannot name a file" in r.output  # had made subfolders
    cfg.write_text(f"images: {src}\npattern: chessboard\ngrid: 9x6\nspacing_mm: x\nloop: 7\nbogus: 1\n")
    r = CliRunner().invoke(cli, ["calibrate", str(cfg), "-o", str(tmp_path / "out2")])
    assert r.exit_code == 2 and "more problems (keys " in r.output and "'loop'" in r.output and "'bogus'" in r.output


def test_identical_images_are_one_view(tmp_path):
    """Copies of one image (byte for byte, or the same pixels in another format) are one view:
    five copies of left13 had been counted as six views (18 for 13 images), moving k3 from
    0.25 to 0.63 and shrinking the parameters' spread, with no warning."""
    images = {f.name: f for f in sorted(STEREO.glob("left*.jpg"))}
    images.update({f"left13_copy{k}.jpg": STEREO / "left13.jpg" for k in range(3)})
    (tmp_path / "img").mkdir()
    cv2.imwrite(str(tmp_path / "img" / "left13_again.png"), cv2.imread(str(STEREO / "left13.jpg"), cv2.IMREAD_UNCHANGED))
    r, out = _calibrate_images(tmp_path / "img", images, "--view", "left", "--no-loop")
    assert r.exit_code == 0, r.output
    d = json.loads((out / "calibration.json").read_text())
    v = d["views"]["left"]
    dup = {k: why for k, why in v["rejected_views"].items() if "same image as left13.jpg" in why}
    assert set(dup) == {"left13_copy0.jpg", "left13_copy1.jpg", "left13_copy2.jpg", "left13_again.png"}
    assert v["n_views"] + len(v["rejected_views"]) == 17 and "left13.jpg" in v["per_image_rms_px"]
    assert abs(v["rms_px"] - 0.408) < 0.02
    assert any(w["code"] == "duplicate-views" for w in d["warnings"])


def test_calibrate_command_single_camera_with_loop(tmp_path):
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["calibrate", "--images", str(STEREO / "left*.jpg"), "--pattern", "chessboard",
                                 "--grid", "9x6", "--spacing-mm", "25", "--view", "left", "-o", str(out)])
    print(r.output)
    assert r.exit_code == 0, r.output
    d = json.loads((out / "calibration.json").read_text())
    loop = d["loop"]
    assert set(loop) >= {"baseline", "steps", "final", "residual_structure"}
    assert "heldout_rms_px" in loop["baseline"] and "heldout_rms_px" in loop["final"]
    assert [t["effect"] for t in loop["tried"][0]] == ["higher-order-distortion", "s-distortion",
                                                        "local-distortion"]
    v = d["views"]["left"]
    assert v["heldout_rms_px"] > v["rms_px"] > 0


@pytest.mark.parametrize("names", [("01", "03", "04"), ("01", "03", "04", "05")])
def test_calibrate_command_few_views(tmp_path, names):
    """3 views (the fewest a camera needs: none can be held out) and 4 (cx alone weakly
    pinned) calibrate: they had ended in internal errors (a held-out refit of 2 views; a
    principal-point shift from one coordinate)."""
    r, out = _calibrate_images(tmp_path / "img", {f"left{n}.jpg": STEREO / f"left{n}.jpg" for n in names},
                               "--view", "left")
    assert r.exit_code == 0, r.output
    d = json.loads((out / "calibration.json").read_text())
    v = d["views"]["left"]
    assert v["n_views"] == len(names) and 0 < v["rms_px"] < 0.5
    codes = [w["code"] for w in d["warnings"]]
    if len(names) == 3:
        assert v["heldout_rms_px"] is None and v["std_jackknife"] == {} and "few-views" in codes
        assert "no view held out" in r.output
        assert all(s["evidence"].get("criterion") != "heldout" for s in d["loop"]["steps"])
    else:
        assert v["heldout_rms_px"] > v["rms_px"] and "few-views" not in codes


def test_unreadable_and_mismatched_images_exit_2(tmp_path):
    d = tmp_path / "views"
    d.mkdir()
    for f in sorted(STEREO.glob("left0*.jpg"))[:3]:
        shutil.copy(f, d / f.name)
    (d / "left05.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    args = ["calibrate", "--images", str(d), "--pattern", "chessboard", "--grid", "9x6", "--spacing-mm", "25",
            "-o", str(tmp_path / "o")]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2 and "left05.jpg" in r.output, r.output
    (d / "left05.jpg").unlink()
    cv2.imwrite(str(d / "left05.png"), np.zeros((240, 320), np.uint8))
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2 and "left05.png" in r.output and "expected 640x480" in r.output, r.output
    assert not (tmp_path / "o" / "calibration.json").exists()
    # the images as a glob: the message names the file (it had named the glob, "*.png, frame 4";
    # frame 4: the files' counter skips left04)
    for f in d.glob("*.jpg"):
        cv2.imwrite(str(f.with_suffix(".png")), cv2.imread(str(f)))
    args[2] = str(d / "*.png")
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2 and f"{d / 'left05.png'}, frame 4" in r.output and "*" not in r.output, r.output


# --- the X-ray dot grid -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dot_grid():
    img = cv2.imread(str(DOTS / "dot_pattern_05.jpg"), cv2.IMREAD_GRAYSCALE)
    blobs = detect_blobs(img, "dark")
    ij, ok = lattice_indices(blobs.xy)
    return img, blobs, blobs.xy[ok], ij[ok]


def test_real_xray_dots_are_dark_and_on_a_lattice(dot_grid):
    img, blobs, xy, ij = dot_grid
    # the dots absorb: darker than the background around them
    inside = img[np.round(xy[:, 1]).astype(int), np.round(xy[:, 0]).astype(int)]
    assert np.median(inside) < 0.5 * np.median(img)
    assert 7 < blobs.diameter_px < 10
    span = ij.max(axis=0) - ij.min(axis=0) + 1
    print(f"{len(xy)} dots on a {span[0]} x {span[1]} lattice")
    assert len(xy) > 4300 and tuple(span) == (85, 52)


def _coarse_centre_from_lines(rows: list[np.ndarray], cols: list[np.ndarray]) -> np.ndarray:
    """discorpy's ``find_cod_coarse`` (Vo et al. 2015), written out as its documentation
    describes it: lines of (x, y) dots in order, rows top to bottom and columns left to
    right; parabolas in image coordinates (rows y(x), columns x(y)), the first adjacent pair
    of lines whose curvatures differ in sign, the mean of their intercepts and slopes as a
    straight line, and the two lines' intersection."""
    def pair(lines, t, s):
        abc = np.array([np.polyfit(p[:, t], p[:, s], 2) for p in lines])
        k = int(np.argmax(np.abs(np.diff(np.sign(abc[:, 0]))))) + 1
        return 0.5 * (abc[k - 1, 2] + abc[k, 2]), 0.5 * (abc[k - 1, 1] + abc[k, 1])
    y0, bh = pair(rows, 0, 1)  # row: y = y0 + bh x
    x0, bv = pair(cols, 1, 0)  # column: x = x0 + bv y
    return np.array([(x0 + y0 * bv) / (1 - bh * bv), (y0 + x0 * bh) / (1 - bh * bv)])


def _discorpy_coarse_centre(xy: np.ndarray, ij: np.ndarray) -> np.ndarray:
    """:func:`_coarse_centre_from_lines` on dots ``xy`` with lattice indices ``ij`` (column, row)."""
    rows = [xy[ij[:, 1] == v] for v in np.unique(ij[:, 1])]
    cols = [xy[ij[:, 0] == v] for v in np.unique(ij[:, 0])]
    return _coarse_centre_from_lines(rows, cols)


def _discorpy_lines() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """discorpy's own grouped dot lines of ``dot_pattern_05`` (PROVENANCE.md), as (x, y)."""
    d = np.load(DOTS / "discorpy_lines_dot05.npz")
    out = []
    for pts, lab in ((d["rows_yx"], d["row_line"]), (d["cols_yx"], d["col_line"])):
        out.append([pts[lab == k][:, ::-1] for k in np.unique(lab)])
    return out[0], out[1]


def test_discorpy_reference_centre_resolution():
    """How precisely discorpy's published centre is known.  Its ``find_cod_coarse`` on its own
    dot lines reproduces the published (588.693, 462.093); resampling the dots within each
    line (a bootstrap: the same procedure on a slightly different draw of the same dots)
    moves it by whole line pitches (15 px), because the columns' curvature changes sign more
    than once and the procedure takes the first change.  Its standard deviation in x is
    several times the 5 px the issue asks us to match it to: the published x is one draw."""
    rows, cols = _discorpy_lines()
    ref = np.array([588.693, 462.093])
    c = _coarse_centre_from_lines(rows, cols)
    assert np.allclose(c, ref, atol=0.01), c
    rng = np.random.default_rng(0)
    boot = np.array([_coarse_centre_from_lines([p[np.sort(rng.integers(0, len(p), len(p)))] for p in rows],
                                               [p[np.sort(rng.integers(0, len(p), len(p)))] for p in cols])
                     for _ in range(300)])
    sd = boot.std(axis=0)
    xs = np.sort(boot[:, 0])
    outcomes_x = np.array([g.mean() for g in np.split(xs, np.flatnonzero(np.diff(xs) > 5.0) + 1)]).round(1)
    frac_published = np.mean(np.hypot(*(boot - ref).T) < 1.0)
    print(f"discorpy's procedure on its own dots, 300 bootstrap draws: sd ({sd[0]:.1f}, {sd[1]:.1f}) px, "
          f"x outcomes (clusters) {outcomes_x.tolist()}, the published value in {100 * frac_published:.0f} %")
    assert sd[0] > 3 * 5.0           # the reference's own spread is far beyond the 5 px criterion
    assert 0.5 < frac_published < 0.95
    assert len(outcomes_x) >= 2 and np.min(np.diff(outcomes_x)) >= 10.0   # quantised at the line pitch


def test_real_xray_dot_grid_distortion(dot_grid):
    """Off the straight grid by more than 5 px before, under 0.5 px after the correction,
    with the centre of distortion from the zero crossing of the lines' curvatures, held
    fixed, and its uncertainty.

    discorpy's published centre (588.693, 462.093), ``coef_dot_05.txt``, is its
    ``find_cod_coarse`` on its own binarised dot centroids (discorpy 1.7.0 reproduces it to
    0.01 px); the same procedure on these sub-pixel centroids gives (603.4, 446.4).  It
    places the centre midway between the first two lines whose curvatures differ in sign,
    so it is good to half a line pitch (7.5 px here), and the binarised centroids'
    curvatures scatter by about one line's step (a Monte Carlo of that scatter spreads its
    centre by 29 px in x and 11 px in y).  So the comparison that tests the estimator is
    with discorpy's procedure on the same dots, to its half-pitch resolution; the published
    value is printed with its distance.
    """
    img, _, xy, ij = dot_grid
    fit = fit_straightness(xy, ij, (img.shape[1], img.shape[0]), n_coeffs=4)
    s = fit.summary()
    ref = np.array([588.693, 462.093])  # discorpy, coef_dot_05.txt (find_cod_coarse on its centroids)
    c = np.array(s["centre_px"])
    std = np.array(s["centre_std_px"])
    coarse = _discorpy_coarse_centre(xy, ij)
    joint = s["joint_fit"]
    print(json.dumps({k: s[k] for k in s if k not in ("coeffs",)}, indent=1))
    print(f"centre {c.round(2).tolist()} +- {std.round(2).tolist()} px (noise "
          f"{np.round(s['centre']['noise_std_px'], 2).tolist()}); discorpy's find_cod_coarse on the same dots "
          f"{coarse.round(2).tolist()} is {np.hypot(*(c - coarse)):.1f} px away; discorpy's published "
          f"{ref.tolist()} (its own centroids) {np.hypot(*(c - ref)):.1f} px; joint fit "
          f"{np.round(joint['centre_px'], 2).tolist()}")
    assert s["centre_method"] == "curvature-zero-crossing"
    assert s["grid_offset_before_max_px"] > 5.0
    assert s["grid_offset_after_max_inliers_px"] < 0.5
    assert s["n_outlier_dots"] < 0.005 * s["n_dots"]
    assert s["line_residual_after_rms_px"] < 0.05 < s["line_residual_before_rms_px"]
    # the same zero crossing as discorpy's procedure finds on the same dots, to its resolution
    step, *_ = np.linalg.lstsq(np.column_stack([ij, np.ones(len(ij))]), xy, rcond=None)
    half_pitch = 0.5 * np.hypot(*step[:2].T)  # x: spacing of the columns, y: of the rows
    assert np.all(np.abs(c - coarse) < half_pitch)
    # an uncertainty is reported; the dots' noise is the small part of it (the split halves disagree)
    assert np.all(np.isfinite(std)) and np.all(np.array(s["centre"]["noise_std_px"]) < 1.0)
    assert np.all(std >= np.array(s["centre"]["noise_std_px"]))
    # identifiability check: the joint fit's centre moves within the reported uncertainty
    # (its own Jacobian standard deviation, noise only, is far smaller than that move)
    # and the fixed centre costs little straightness
    assert np.all(np.abs(np.array(joint["centre_px"]) - c) < 3 * std)
    assert joint["line_residual_rms_px_fixed_centre"] < joint["line_residual_rms_px"] + 0.01


def test_straightness_recovers_a_known_centre():
    """Synthetic dot grid, known radial distortion about (600, 450), seeded noise 0.02 px."""
    rng = np.random.default_rng(4)
    true = RadialDistortion((600.0, 450.0), (-0.002, 0.015, -0.006, 0.003), 0.5 * np.hypot(1280, 800))
    j, i = np.meshgrid(np.arange(-40, 41), np.arange(-25, 26))
    ij = np.column_stack([j.ravel(), i.ravel()])
    th = np.deg2rad(0.4)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    und = np.array([640.0, 400.0]) + 15.2 * ij @ R.T
    und = und[(und[:, 0] > 5) & (und[:, 0] < 1275) & (und[:, 1] > 5) & (und[:, 1] < 795)]
    ij = np.round((und - [640.0, 400.0]) @ R / 15.2).astype(int)
    xy = true.distort(und) + rng.normal(0, 0.02, und.shape)
    fit = fit_straightness(xy, ij, (1280, 800))
    c = np.array(fit.distortion.centre_px)
    print("recovered centre", c, "+-", fit.centre_std_px)
    assert np.hypot(*(c - [600.0, 450.0])) < 5 * np.hypot(*fit.centre_std_px) + 0.2
    # within 3 standard deviations of the noise part alone (the distortion is purely radial)
    assert np.hypot(*(c - [600.0, 450.0])) < 3 * np.hypot(*fit.centre.noise_std_px)
    back = fit.distortion.undistort(true.distort(und))
    assert np.sqrt(np.mean(np.sum((back - und - (back - und).mean(0)) ** 2, axis=1))) < 0.1


def _twin_dot_grid(arm, tilt: tuple[float, float], seed: int, spacing_px: float = 12.0, noise_px: float = 0.02):
    """A dense dot grid seen by a twin C-arm: ideal pixels of a square grid (turned 0.7 deg,
    with the projective terms ``tilt`` of a tilted plate) through the camera's distortion,
    inside the intensifier's field, with seeded centroid noise (the real grid's ~0.02 px)."""
    cam = arm.camera
    w, h = cam.image_size
    n = int(1.6 * max(w, h) / spacing_px)
    j, i = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))
    ij = np.column_stack([j.ravel(), i.ravel()])
    th = np.deg2rad(0.7)
    p = spacing_px * ij @ np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
    g = 1.0 + tilt[0] * p[:, 0] + tilt[1] * p[:, 1]
    raw = cam.distort_pixels(np.array([w / 2 + 3.3, h / 2 - 2.1]) + p / g[:, None])
    keep = np.hypot(*(raw - arm.fov_centre_px).T) < arm.fov_radius_px - 8
    keep &= (raw[:, 0] > 8) & (raw[:, 0] < w - 9) & (raw[:, 1] > 8) & (raw[:, 1] < h - 9)
    return raw[keep] + np.random.default_rng(seed).normal(0, noise_px, (keep.sum(), 2)), ij[keep]


@pytest.mark.parametrize("tangential", [False, True])
def test_centre_of_distortion_on_twin_cameras(tangential):
    """The twin's C-arms (pincushion k1 about the principal point, jittered per arm), a
    front-on and a tilted plate.  Radial only: the centre is the principal point.  With the
    default decentring (p1, p2) the lines show the first-order equivalent centre, the
    principal point moved by (-p2, -p1) / k1 (times fx, fy): straightness cannot tell a
    centre shift from decentring.  Tolerance 0.5 px: ~5000 dots with 0.02 px noise place
    the centre to ~0.1 px; the equivalence is first order (0.15 px left over)."""
    from bsipipe.imaging.distortion import centre_of_distortion
    from bsipipe.synth.config import SynthConfig
    from bsipipe.synth.twin import build_carms
    cfg = SynthConfig.model_validate({"distortion": {} if tangential else {"tangential_edge_px": 0.0}})
    for k, (name, arm) in enumerate(build_carms(cfg).items()):
        cam = arm.camera
        k1, _, p1, p2 = cam.dist[:4]
        truth = np.array([cam.cx - p2 / k1 * cam.fx, cam.cy - p1 / k1 * cam.fy])
        for tilt in ((0.0, 0.0), (2e-4, -1.5e-4)):
            xy, ij = _twin_dot_grid(arm, tilt, seed=k)
            est = centre_of_distortion(xy, ij)
            err = float(np.hypot(*(est.centre_px - truth)))
            print(f"{name} tilt {tilt}: centre {est.centre_px.round(2)} +- {est.std_px.round(2)} px, truth "
                  f"{truth.round(2)} (principal point {np.round([cam.cx, cam.cy], 2)}), error {err:.3f} px")
            assert err < 0.5
            assert err < 3 * float(np.hypot(*est.std_px))
            if tangential:
                assert np.hypot(cam.cx - truth[0], cam.cy - truth[1]) > 5  # the decentring moves it


def test_centre_uncertainty_flags_a_distortion_that_is_not_radial():
    """An S-distortion (1 deg twist at the field edge) bends the two halves of each line
    differently: the split-half part of the uncertainty grows beyond 10 px, where the
    radial twin's stays under 1 px (test above)."""
    from bsipipe.imaging.distortion import centre_of_distortion
    from bsipipe.synth.config import SynthConfig
    from bsipipe.synth.twin import build_carms
    arm = build_carms(SynthConfig.model_validate({"distortion": {"tangential_edge_px": 0.0,
                                                                 "s_distortion_deg": 1.0}}))["cam1"]
    est = centre_of_distortion(*_twin_dot_grid(arm, (0.0, 0.0), seed=0))
    print(f"S-distortion: centre {est.centre_px.round(2)} +- {est.std_px.round(2)} px "
          f"(noise {est.noise_std_px.round(2)}, split halves {est.split_half_std_px.round(2)})")
    assert np.all(est.split_half_std_px > 10.0)


# --- other targets, the config form -----------------------------------------------------------

def test_charuco_board_is_found_with_its_ids():
    from bsipipe.imaging.gridfind import find_charuco
    aruco = cv2.aruco
    board = aruco.CharucoBoard((7, 5), 20.0, 15.0, aruco.getPredefinedDictionary(aruco.DICT_4X4_50))
    img = board.generateImage((700, 500), marginSize=20)  # 20 mm squares drawn at 92 px
    det = find_charuco(img, (7, 5), 20.0, marker_mm=15.0)
    assert det.n == 24 and det.complete and not det.ambiguous
    # corner (col 0, row 0) of the inner grid is one square in from the board's corner
    assert np.allclose(det.object_points[0], [20.0, 20.0, 0.0])
    px = (det.image_points - det.image_points[0]) / 92.0
    assert np.allclose(px, det.object_points[:, :2] / 20.0 - 1.0, atol=0.02)


def test_dark_symmetric_circle_grid_subpixel():
    from bsipipe.imaging.gridfind import find_circles
    rng = np.random.default_rng(0)
    img = np.full((400, 500), 200.0)
    yy, xx = np.mgrid[0:400, 0:500]
    centres = np.array([[60.3 + c * 50.25, 70.6 + r * 49.8] for r in range(5) for c in range(6)])
    for cx, cy in centres:  # anti-aliased dark discs of radius 8 px
        img -= 160.0 * np.clip(8.5 - np.hypot(xx - cx, yy - cy), 0, 1)
    img = cv2.GaussianBlur(img, (0, 0), 1.0) + rng.normal(0, 2.0, img.shape)
    det = find_circles(img.astype(np.float32), (6, 5), 10.0, polarity="dark")
    assert det.n == 30 and det.complete
    err = np.hypot(*(det.image_points - centres).T)
    print(f"circle centres: {err.max():.4f} px max error")
    assert err.max() < 0.05
    assert np.array_equal(det.ids, np.arange(30))


def test_calibrate_config_form_and_strict_keys(tmp_path):
    cfg = tmp_path / "cal.yaml"
    cfg.write_text(f"pattern: chessboard\ngrid: 9x6\nspacing_mm: 25\nimages: '{STEREO}/left*.jpg'\n"
                   "view_name: left\nloop: false\nsubpix_window_px: 11\nreject_outliers: false\n")
    r = CliRunner().invoke(cli, ["calibrate", str(cfg), "-o", str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "o" / "calibration.json").read_text())
    assert abs(d["views"]["left"]["rms_px"] - 0.408) < 0.02
    assert d["provenance"]["config"]["subpix_window_px"] == 11
    cfg.write_text("pattern: chessboard\ngrid: 9x6\nspacing_mm: 25\nimagez: x\n")
    r = CliRunner().invoke(cli, ["calibrate", str(cfg), "-o", str(tmp_path / "o2")])
    assert r.exit_code == 2 and "imagez" in r.output and "cal.yaml" in r.output, r.output


@pytest.mark.parametrize("pattern, grid", [("asymmetric-circles", (8, 17)), ("circles", (9, 7))])
@pytest.mark.parametrize("deg", [0.0, 0.1, 45.0, 90.0, 135.0])
def test_lattice_found_whatever_the_grid_turn(pattern, grid, deg):
    """A grid whose nearest neighbours lie at +-45 degrees to the image axes (an
    asymmetric-circles plate square to the image, a symmetric one turned 45 degrees): the two
    lattice steps were each the neighbour nearest +x and +y, tied between two, and could be
    the same step: the view was rejected ("only 0 of 136 grid points found") in 22 of 40
    noise draws at 0 degrees, 14-23 of 40 for the circles at 45 and 135.  Every point of every
    draw is indexed now."""
    from bsipipe.imaging.gridfind import target_points
    P = target_points(pattern, grid, 20.0)[:, :2]
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    for s in range(40):
        rng = np.random.default_rng(s)
        xy = P @ R.T + 300 + rng.normal(0, 0.1, P.shape)
        ij, ok = lattice_indices(xy[rng.permutation(len(xy))])
        assert ok.all(), (s, int(ok.sum()), len(xy))


@pytest.mark.parametrize("pattern, grid", [("asymmetric-circles", (8, 17)), ("circles", (10, 10))])
@pytest.mark.parametrize("tilt", [30.0, 46.0, 55.0, 60.0])
def test_lattice_found_on_a_plate_tilted_far(pattern, grid, tilt):
    """A plate tilted 45-60 degrees (a stereo frame of C-arms 90 degrees apart sees it about
    45 degrees from each): one axis foreshortened by cos(tilt), the lattice's second neighbours
    fell beyond the seed's 1.4 x median spacing and no seed had four: "0 of 136 grid points
    found" with every bead detected (4 of 12 stereo images of the probe's symmetric twin).  Every
    point is indexed, whatever the axis of the tilt."""
    from bsipipe.imaging.gridfind import target_points
    P = target_points(pattern, grid, 20.0)[:, :2]
    c = np.cos(np.radians(tilt))
    for k, axis in enumerate((0.0, 20.0, 45.0, 80.0, 130.0)):
        a = np.radians(axis)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        A = R @ np.diag([1.0, c]) @ R.T
        rng = np.random.default_rng(k)
        xy = (P - P.mean(axis=0)) @ A.T + 500 + rng.normal(0, 0.1, P.shape)
        ij, ok = lattice_indices(xy[rng.permutation(len(xy))])
        assert ok.all(), (axis, int(ok.sum()), len(xy))


def test_faint_blurred_beads_are_found_with_a_matched_filter():
    """Beads blurred to a sigma of 2.6 px, 15 grey levels deep under noise of sd 3: each pixel
    near the noise, the sum well above it (plainly visible).  The plain threshold found no blob
    to size ("give --diameter-px"; on the probe's blur-2 twin 63 of 136 points, every view lost,
    exit 1).  find_circles retries with the signal smoothed: all 136, centres within 0.4 px RMS
    (the Cramer-Rao bound is 0.16 px; the centroid's own spread about twice it)."""
    from bsipipe.imaging.gridfind import DetectionFailed, find_circles, target_points
    P = target_points("asymmetric-circles", (8, 17), 1.0)[:, :2] * 28 + [200, 150]
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:800, 0:800]
    img = np.full((800, 800), 120.0)
    for x, y in P:
        img -= 15.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 2.6 ** 2))
    img = np.clip(np.rint(img + rng.normal(0, 3.0, img.shape)), 0, 255).astype(np.uint8)
    with pytest.raises(DetectionFailed):
        detect_blobs(img, "dark")
    det = find_circles(img, (8, 17), 1.0, asymmetric=True)
    assert len(det.image_points) == 136 and det.info["smooth_px"] > 0
    err = np.hypot(*(det.image_points - P[det.ids]).T)
    assert np.sqrt(np.mean(err ** 2)) < 0.4


def test_stereo_pairs_with_a_grid_cut_off_are_left_out():
    """A dot grid cut off in one camera's stereo image is numbered from the first row and column
    seen, so its ids need not be the other camera's: the probe's twin with cam1's stereo images
    cut by 30 % had a stereo RMS of 17.3 px, 3-D error 0.87 mm, exit 0 under a large-rms
    warning that blamed timing or --grid.  With at least 3 pairs whole in both images the cut
    ones are left out (here the pose comes back exact); with fewer, the message says why."""
    import cv2

    from bsipipe.imaging.gridfind import target_points
    tgt = target_points("asymmetric-circles", (8, 17), 7.0)
    K = np.array([[3300.0, 0, 512], [0, 3300.0, 512], [0, 0, 1]])
    spec = ModelSpec()
    cam_a = CameraModel((1024, 1024), K, np.zeros(5), spec)
    cam_b = CameraModel((1024, 1024), K.copy(), np.zeros(5), spec)
    R_ab = cv2.Rodrigues(np.array([0.0, np.radians(60.0), 0.0]))[0]
    t_ab = np.array([-700.0, 0.0, 300.0])
    rng = np.random.default_rng(0)
    fa, fb = {}, {}
    for k in range(6):
        ra = np.array([rng.uniform(-0.3, 0.3), 0.5 + rng.uniform(-0.2, 0.2), rng.uniform(-0.5, 0.5)])
        Ra = cv2.Rodrigues(ra)[0]
        ta = np.array([0.0, 0.0, 900.0]) - Ra @ tgt.mean(axis=0)
        Rb, tb = R_ab @ Ra, R_ab @ ta + t_ab
        pa = cv2.projectPoints(tgt, ra, ta, K, None)[0].reshape(-1, 2)
        pb = cv2.projectPoints(tgt, cv2.Rodrigues(Rb)[0], tb, K, None)[0].reshape(-1, 2)
        ids = np.arange(len(tgt))
        name = f"s{k}"
        if k < 3:
            # cam A sees only the lower 70 % of the grid, numbered from its first visible row
            keep = ids >= int(0.3 * len(tgt))
            kept = ids[keep]
            fa[name] = ViewData(name, pa[keep], tgt[kept - kept[0]], kept - kept[0])
        else:
            fa[name] = ViewData(name, pa, tgt, ids)
        fb[name] = ViewData(name, pb, tgt, ids)
    st = stereo_calibrate(cam_a, cam_b, ("a", "b"), fa, fb, target_all=tgt, ambiguous=True)
    assert sorted(st.rejected) == ["s0", "s1", "s2"] and "cut off" in st.rejected["s0"]
    assert st.rms_px < 0.01 and np.linalg.norm(st.T_mm - t_ab) < 0.01
    # only the cut pairs and one whole: kept, and the note says why they may not fit
    with pytest.raises(ValueError, match="shared frames show the grid cut off in a camera"):
        stereo_calibrate(cam_a, cam_b, ("a", "b"), {n: fa[n] for n in ("s0", "s1", "s2", "s3")},
                         {n: fb[n] for n in ("s0", "s1", "s2", "s3")}, target_all=tgt, ambiguous=True)


def test_a_speck_on_a_lattice_site_beyond_the_grid_is_left_out():
    """One extra blob on the lattice one row beyond an 8x17 asymmetric grid (dust, a bead):
    "137 blobs on the lattice, more than the 8x17 grid holds", and the view was lost with
    nothing said (3 of 12 views on the probe's twin).  A lone point on an outer lattice line
    is left out where the rest is the whole grid; two specks on inner sites are not."""
    from bsipipe.imaging.gridfind import _without_stray_edges, fit_to_target, target_points
    P = target_points("asymmetric-circles", (8, 17), 20.0)[:, :2] + 300
    ij0, ok0 = lattice_indices(P)
    assert ok0.all()
    A = np.column_stack([ij0, np.ones(len(ij0))])
    coef = np.linalg.lstsq(A, P, rcond=None)[0]                  # lattice -> image
    k = int(np.argmax(ij0[:, 0]))
    site = np.array([ij0[k, 0] + 1, ij0[k, 1], 1.0]) @ coef      # the lattice site beyond the grid's edge
    xy = np.vstack([P, site])
    ij, ok = lattice_indices(xy)
    assert ok.all()
    from bsipipe.imaging.gridfind import DetectionFailed

    def whole(mask):
        try:
            return fit_to_target(ij[mask], "asymmetric-circles", (8, 17), xy[mask])[1]
        except DetectionFailed:
            return False

    keep = _without_stray_edges(ij, 1, whole)
    assert keep is not None and not keep[-1] and keep[:-1].all()
    assert _without_stray_edges(ij[:-1], 0, whole) is None


def test_a_grid_larger_than_the_chessboard_is_named():
    """--grid 10x6 on OpenCV's 9x6 board: on left13.jpg OpenCV's finder returns 10x6 "corners",
    one line of them along the board's edge, whose cells are all squares; the view had been
    calibrated with every point a square off.  The margin beyond that line does not alternate:
    the board's size is named; every real view is still found with the right grid."""
    from bsipipe.imaging.gridfind import GridMismatch
    im = cv2.imread(str(STEREO / "left13.jpg"), cv2.IMREAD_GRAYSCALE)
    with pytest.raises(GridMismatch, match=r"the board has 9x6 inner corners, --grid says 10x6 .*board's edge"):
        find_chessboard(im, (10, 6), 25.0)
    for f in sorted(STEREO.glob("*.jpg")):
        assert len(find_chessboard(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), (9, 6), 25.0).image_points) == 54


def test_dot_pattern_01_straightened_as_discorpy_reports():
    """discorpy's dot_pattern_01 (2560 x 2160, strong distortion): its demo reports the dots
    off their straight lines by more than 12 px before correction and by less than 1 px after,
    centre (1252.15, 1008.91).  bsipipe's straightness fit: 14.5 px before, 0.19 px after
    (the dots it keeps; 336 outliers of 6,594 left out).  discorpy's own coarse centre finder,
    run on bsipipe's dots, gives its published centre within 1 px (the dots agree); bsipipe's
    centre, the zero curvature crossing interpolated over many lines, lies 11 px from it,
    within half a line spacing (26 px), the resolution of a finder that takes the crossing
    between the first two lines whose curvatures differ in sign."""
    img = cv2.imread(str(DOTS / "dot_pattern_01.jpg"), cv2.IMREAD_GRAYSCALE)
    b = detect_blobs(img, "dark")
    ij, ok = lattice_indices(b.xy)
    xy, ij = b.xy[ok], ij[ok]
    assert len(xy) > 6000

    def off_line(P, I):
        out = np.zeros(len(P))
        for axis in (0, 1):
            for v in np.unique(I[:, axis]):
                m = I[:, axis] == v
                if m.sum() >= 3:
                    Q = P[m] - P[m].mean(axis=0)
                    out[m] = np.maximum(out[m], np.abs(Q @ np.linalg.svd(Q)[2][1]))
        return out

    fit = fit_straightness(xy, ij, (img.shape[1], img.shape[0]))
    before = off_line(xy, ij)
    keep = fit.inlier
    after = off_line(fit.distortion.undistort(xy[keep]), ij[keep])
    print(f"off the lines: before {before.max():.2f} px, after {after.max():.3f} px ({keep.sum()} dots); centre "
          f"{np.round(fit.summary()['centre_px'], 2)}")
    assert before.max() > 12.0 and after.max() < 1.0 and keep.mean() > 0.9
    coarse = _discorpy_coarse_centre(xy, ij)
    assert np.hypot(*(coarse - [1252.15, 1008.91])) < 1.0
    assert np.hypot(*(np.asarray(fit.summary()["centre_px"]) - coarse)) < 13.0
