"""Stereo calibrations of other tools read for ``bsipipe track`` (bsipipe/io/stereo_calibration.py):
OpenCV's FileStorage files, on the real ``stereo_calib`` sample's ``intrinsics.yml``
(tests/data/real/opencv_stereo/PROVENANCE.md), and Bouguet's toolbox's ``Calib_Results_stereo.mat``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.io import savemat

from bsipipe.errors import InputError
from bsipipe.imaging.gridfind import find_chessboard
from bsipipe.imaging.triangulate import triangulate, triangulate_dlt, views_from_calibration
from bsipipe.io.stereo_calibration import read_stereo_calibration

STEREO = Path(__file__).parent / "data" / "real" / "opencv_stereo"


def _board(name: str):
    return find_chessboard(cv2.imread(str(STEREO / name), cv2.IMREAD_GRAYSCALE), (9, 6), 25.0)


def _corners(name: str) -> np.ndarray:
    return _board(name).image_points


def _real_pairs():
    names = [f"{k:02d}" for k in range(1, 15) if k != 10]
    boards = [(_board(f"left{n}.jpg"), _board(f"right{n}.jpg")) for n in names]
    obj = [a.object_points.astype(np.float32).reshape(-1, 1, 3) for a, _ in boards]
    left = [a.image_points.astype(np.float32).reshape(-1, 1, 2) for a, _ in boards]
    right = [b.image_points.astype(np.float32).reshape(-1, 1, 2) for _, b in boards]
    return boards, obj, left, right


def test_opencv_stereo_sample_files_are_read_by_either_name(tmp_path):
    """OpenCV's own intrinsics.yml of the real pair (M1, D1, M2, D2 as the stereo_calib sample
    wrote them) with an extrinsics.yml beside it (the R, T cv2.stereoCalibrate finds for those
    intrinsics on the 13 real pairs; they fit them at 1.80 px, the cameras' own fits at 0.41
    and 0.46): read by the name of either file, the matrices are the files', the image size
    the frames'."""
    shutil.copy(STEREO / "intrinsics.yml", tmp_path / "intrinsics.yml")
    fs = cv2.FileStorage(str(STEREO / "intrinsics.yml"), cv2.FILE_STORAGE_READ)
    M1, D1, M2, D2 = (fs.getNode(k).mat() for k in ("M1", "D1", "M2", "D2"))
    fs.release()
    _, obj, left, right = _real_pairs()
    *_, R, T, _, _ = cv2.stereoCalibrate(obj, left, right, M1, D1, M2, D2, (640, 480), flags=cv2.CALIB_FIX_INTRINSIC)
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("R", R)
    fs.write("T", T)
    fs.release()
    for given in ("intrinsics.yml", "extrinsics.yml"):
        cal = read_stereo_calibration(tmp_path / given, ["left", "right"], {"left": (480, 640), "right": (480, 640)})
        assert np.allclose(cal["views"]["left"]["camera_matrix"], M1) and np.allclose(cal["views"]["right"]["camera_matrix"], M2)
        assert np.allclose(cal["views"]["left"]["dist_coeffs"], D1.ravel()) and cal["views"]["left"]["image_size"] == [640, 480]
        assert np.allclose(cal["stereo"]["R"], R) and np.allclose(cal["stereo"]["T_mm"], T.ravel())
        assert cal["source"]["format"] == "opencv-filestorage" and len(cal["source"]["files"]) == 2


def test_an_opencv_stereo_file_triangulates_the_real_chessboard(tmp_path):
    """The real pair calibrated by OpenCV (each camera, then the pair with them fixed: RMS 0.408,
    0.458, 0.447 px, baseline 83.6 mm, the reference's), written in one FileStorage file (M1 D1
    M2 D2 R T, as cv::FileStorage writes them) and read back: pair 1's board, triangulated
    linearly and by the reprojection-minimising refinement, has neighbouring corners 25 mm
    apart (the reference: 24.95 +- 0.53 mm).  The linear triangulation in plain millimetres had
    given 28.5 +- 6.0 mm (3.96 px off in the right view): its coordinates are now conditioned."""
    boards, obj, left, right = _real_pairs()
    _, K1, d1, _, _ = cv2.calibrateCamera(obj, left, (640, 480), None, None)
    _, K2, d2, _, _ = cv2.calibrateCamera(obj, right, (640, 480), None, None)
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(obj, left, right, K1, d1, K2, d2, (640, 480), flags=cv2.CALIB_FIX_INTRINSIC)
    assert rms == pytest.approx(0.447, abs=0.01) and np.linalg.norm(T) == pytest.approx(83.6, abs=0.1)
    fs = cv2.FileStorage(str(tmp_path / "stereo.xml"), cv2.FILE_STORAGE_WRITE)
    for k, v in (("M1", K1), ("D1", d1), ("M2", K2), ("D2", d2), ("R", R), ("T", T), ("image_size", np.array([640, 480]))):
        fs.write(k, v)
    fs.release()
    cal = read_stereo_calibration(tmp_path / "stereo.xml", ["left", "right"])
    assert cal["views"]["right"]["image_size"] == [640, 480]
    views = views_from_calibration(cal, ("left", "right"))
    va, vb = views["left"], views["right"]
    a, b = boards[0]
    o = a.object_points.reshape(-1, 3)
    i, j = np.nonzero(np.isclose(np.linalg.norm(o[:, None] - o[None], axis=2), 25.0))
    assert len(i) == 2 * (8 * 6 + 9 * 5)
    linear = triangulate_dlt([va, vb], [va.to_normalized(a.image_points), vb.to_normalized(b.image_points)])
    refined = triangulate((va, vb), a.image_points, b.image_points)["X_mm"]
    for X in (linear, refined):
        d = np.linalg.norm(X[i] - X[j], axis=1)
        assert abs(np.mean(d) - 25.0) < 0.1 and np.std(d) < 0.53
    assert np.abs(linear - refined).max() < 0.05


@pytest.mark.parametrize("unit, scale", [("metres", 1e-3), ("squares of 25 mm", 1 / 25.0)])
def test_a_pair_calibrated_in_metres_or_board_squares_is_refused(tmp_path, unit, scale):
    """The real pair's calibration (baseline 83.6 mm) written as it would be had the board been
    given in metres (0.0836) or in squares (3.34, OpenCV's stereo_calib sample's default square
    size of 1): refused, naming the file, the baseline and the fix, in FileStorage, Bouguet and
    JSON form alike; in millimetres it is read as before.  It had been read as millimetres: every
    3-D point and ray gap 1000 or 25 times too small, labelled mm."""
    _, obj, left, right = _real_pairs()
    _, K1, d1, _, _ = cv2.calibrateCamera(obj, left, (640, 480), None, None)
    _, K2, d2, _, _ = cv2.calibrateCamera(obj, right, (640, 480), None, None)
    *_, R, T, _, _ = cv2.stereoCalibrate(obj, left, right, K1, d1, K2, d2, (640, 480), flags=cv2.CALIB_FIX_INTRINSIC)
    sizes = {"left": (480, 640), "right": (480, 640)}

    def files(t, folder: Path) -> list[Path]:
        folder.mkdir()
        fs = cv2.FileStorage(str(folder / "stereo.yml"), cv2.FILE_STORAGE_WRITE)
        for k, v in (("M1", K1), ("D1", d1), ("M2", K2), ("D2", d2), ("R", R), ("T", t)):
            fs.write(k, v)
        fs.release()
        js = folder / "calibration.json"
        js.write_text(json.dumps({"views": {"left": {"image_size": [640, 480], "camera_matrix": K1.tolist(),
                                                      "dist_coeffs": d1.ravel().tolist()},
                                             "right": {"image_size": [640, 480], "camera_matrix": K2.tolist(),
                                                       "dist_coeffs": d2.ravel().tolist()}},
                                  "stereo": {"views": ["left", "right"], "R": R.tolist(), "T_mm": t.ravel().tolist()}}))
        return [folder / "stereo.yml", _bouguet(folder / "Calib_Results_stereo.mat", T=t.reshape(3, 1).tolist()), js]

    for path in files(T, tmp_path / "mm"):
        cal = read_stereo_calibration(path, ["left", "right"], sizes)
        assert np.linalg.norm(cal["stereo"]["T_mm"]) == pytest.approx(83.6, abs=0.1), path
    for path in files(T * scale, tmp_path / "scaled"):
        with pytest.raises(InputError, match="millimetres") as e:
            read_stereo_calibration(path, ["left", "right"], sizes)
        msg = str(e.value)
        assert str(path) in msg and f"{83.6 * scale:.3g}"[:-1] in msg and "metres" in msg and "square" in msg, msg


def test_a_calibration_whose_cameras_stand_in_one_place_is_refused(tmp_path):
    p = _bouguet(tmp_path / "Calib_Results_stereo.mat", T=[[0.0], [0.0], [0.0]])
    with pytest.raises(InputError, match="T is zero"):
        read_stereo_calibration(p, ["cam1", "cam2"])


def _bouguet(path: Path, **over):
    m = {"fc_left": [[3300.0], [3302.0]], "cc_left": [[511.5], [510.0]], "kc_left": [[-0.1], [0.02], [0.001], [-0.002], [0.0]],
         "alpha_c_left": 0.0, "fc_right": [[3290.0], [3291.0]], "cc_right": [[515.0], [509.0]],
         "kc_right": [[-0.09], [0.01], [0.0], [0.0], [0.0]], "alpha_c_right": 0.0,
         "om": [[0.0], [1.5707963], [0.0]], "T": [[-640.0], [0.0], [640.0]], "nx": 1024.0, "ny": 1024.0}
    m.update(over)
    savemat(str(path), {k: v for k, v in m.items() if v is not None})
    return path


def test_bouguet_stereo_results_map_onto_opencvs_model(tmp_path):
    """fc, cc, kc of each side become the camera matrix and OpenCV's five coefficients term for
    term, om the rotation (Rodrigues) and T the translation, nx x ny the image size."""
    cal = read_stereo_calibration(_bouguet(tmp_path / "Calib_Results_stereo.mat"), ["cam1", "cam2"])
    c1 = cal["views"]["cam1"]
    assert c1["camera_matrix"] == [[3300.0, 0.0, 511.5], [0.0, 3302.0, 510.0], [0.0, 0.0, 1.0]]
    assert c1["dist_coeffs"] == [-0.1, 0.02, 0.001, -0.002, 0.0] and c1["image_size"] == [1024, 1024]
    R = np.asarray(cal["stereo"]["R"])
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], atol=1e-6)      # 90 degrees about y
    assert cal["stereo"]["T_mm"] == [-640.0, 0.0, 640.0] and cal["stereo"]["views"] == ["cam1", "cam2"]


@pytest.mark.parametrize("case, message", [
    ("single", "a single camera's results (Calib_Results.mat)"),
    ("truncated", "not a MATLAB .mat file"),
    ("skew", "a skew of 0.01"),
    ("kc", "7 distortion coefficients"),
])
def test_bouguet_files_that_cannot_serve_are_refused(tmp_path, case, message):
    p = tmp_path / "x.mat"
    if case == "single":
        savemat(str(p), {"fc": [[1.0], [1.0]], "cc": [[0.0], [0.0]], "kc": [[0.0]] * 5})
    elif case == "truncated":
        _bouguet(p)
        p.write_bytes(p.read_bytes()[:300])
    elif case == "skew":
        _bouguet(p, alpha_c_left=0.01)
    else:
        _bouguet(p, kc_right=[[0.0]] * 7)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")) as e:
        read_stereo_calibration(p, ["cam1", "cam2"])
    assert str(p) in str(e.value)


def test_opencv_file_without_the_extrinsics_says_what_it_needs(tmp_path):
    shutil.copy(STEREO / "intrinsics.yml", tmp_path / "intrinsics.yml")
    with pytest.raises(InputError, match="no R, T in intrinsics.yml"):
        read_stereo_calibration(tmp_path / "intrinsics.yml", ["a", "b"], {})
