"""Stereo calibrations made by other tools, read as ``bsipipe calibrate``'s ``calibration.json``
(a dict), so ``bsipipe track --calibration`` triangulates through them.

OpenCV (``.yml``, ``.yaml``, ``.xml``: ``cv::FileStorage``)
    ``M1``, ``D1``, ``M2``, ``D2`` (camera matrices, distortion in OpenCV's order ``k1 k2 p1
    p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]``) and ``R``, ``T`` (``x_2 = R x_1 + T``), in one file or,
    as OpenCV's ``stereo_calib`` sample writes them, ``intrinsics.yml`` and ``extrinsics.yml``
    side by side (either may be given; the other is read from the same folder).  An
    ``image_size`` / ``imageSize`` entry (w, h) is used where present.
Bouguet's Camera Calibration Toolbox for MATLAB (``.mat``: ``Calib_Results_stereo.mat``)
    ``fc_left``, ``cc_left``, ``kc_left``, ``alpha_c_left``, the same ``_right``, ``om``
    (Rodrigues vector) and ``T`` (``X_right = R X_left + T``), ``nx``, ``ny``.  The toolbox's
    distortion ``kc = [k1 k2 p1 p2 k3]`` is OpenCV's five-coefficient model term for term, and
    its pixel convention is OpenCV's (the upper-left pixel's centre at [0; 0]: its initial
    principal point is ``[nx; ny] / 2 - 0.5``).  A skew ``alpha_c`` other than 0 is refused
    (OpenCV's undistortion has no skew; the toolbox leaves it 0 unless ``est_alpha`` is set).

Camera 1 / left is the first ``--view`` of the calibrated pair, camera 2 / right the second.
``T`` is in the units the tool was given the target in: millimetres expected (bsipipe's
``T_mm``); a baseline under :data:`MIN_BASELINE_MM` (a pair calibrated in metres, or in squares
of its board) is refused, in any format.  Image sizes missing from the file are taken from the
frames (``shapes``).  The files carry no reprojection RMS: ``stereo.rms_px`` is None (``track``
then assumes one).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import InputError

__all__ = ["read_stereo_calibration", "check_baseline", "MIN_BASELINE_MM", "OPENCV_SUFFIXES", "BOUGUET_SUFFIXES"]

OPENCV_SUFFIXES = (".yml", ".yaml", ".xml")
BOUGUET_SUFFIXES = (".mat",)
#: The partner file of OpenCV's stereo_calib sample pair, by the name of the one given.
_PARTNER = {"intrinsics": "extrinsics", "extrinsics": "intrinsics"}


def read_stereo_calibration(path: str | os.PathLike, views: Sequence[str],
                            shapes: Mapping[str, tuple] | None = None) -> dict:
    """The stereo calibration in ``path`` as a ``calibration.json`` dict for the two ``views``
    (camera 1 / left first); ``shapes``: view -> the frames' (h, w), for a file without image
    sizes.  JSON files are read as they are.  Any problem raises
    :class:`~bsipipe.errors.InputError` naming the file."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in OPENCV_SUFFIXES:
        cal = _opencv(p, views, shapes or {})
    elif suffix in BOUGUET_SUFFIXES:
        cal = _bouguet(p, views)
    else:
        try:
            with open(p, encoding="utf-8") as f:
                cal = json.load(f)
        except FileNotFoundError:
            raise InputError("file not found", path=p) from None
        except (OSError, ValueError) as e:
            raise InputError(f"cannot read the calibration: {e}", path=p) from None
    check_baseline(cal, p)
    return cal


#: The shortest stereo baseline (|T|) read as millimetres.  Two C-arms stand about a metre
#: apart (the study's twin: 896 mm), a desktop camera pair several centimetres (OpenCV's real
#: chessboard pair: 83.6 mm); a pair calibrated in metres reads 0.05-1.5, and one calibrated in
#: squares of its board (OpenCV's stereo_calib sample takes a square size of 1 unless told)
#: 2-8 for such a desktop pair.  Below this, every 3-D point, ray gap and displacement would
#: come out 25 to 1000 times too small, labelled mm.
MIN_BASELINE_MM = 10.0


def check_baseline(cal, path: Path) -> None:
    """Refuse a calibration whose stereo translation cannot be in millimetres
    (:data:`MIN_BASELINE_MM`), naming the file, the baseline and the fix; a calibration
    without a readable stereo block is left to the caller's own checks."""
    st = cal.get("stereo") if isinstance(cal, dict) else None
    try:
        T = np.asarray(st["T_mm"], float).ravel()
    except (TypeError, KeyError, ValueError):
        return
    if T.size != 3 or not np.all(np.isfinite(T)):
        return
    b = float(np.linalg.norm(T))
    if b == 0.0:
        raise InputError("the stereo translation T is zero: the two cameras stand in one place, and rays from one "
                         "point cannot be triangulated", path=path)
    if b < MIN_BASELINE_MM:
        raise InputError(
            f"the two cameras are {b:.4g} apart in the calibration's units (|T|): bsipipe reads T in millimetres, "
            f"and no C-arm or camera pair stands {b:.4g} mm apart (under {MIN_BASELINE_MM:g} mm): the calibration "
            f"was made in metres (multiply T by 1000) or in squares of the board (multiply T by the square's size "
            f"in mm; OpenCV's stereo_calib sample takes a square size of 1 unless told); every 3-D point and ray "
            f"gap would come out that many times too small, labelled mm", path=path)


def _pair(views: Sequence[str], path: Path, tool: str) -> tuple[str, str]:
    if len(views) < 2:
        raise InputError(f"a {tool} stereo calibration needs two --view (camera 1 / left, then camera 2 / right)",
                         path=path)
    return views[0], views[1]


def _view(K, dist, size, path: Path, which: str) -> dict:
    K = np.asarray(K, float).reshape(3, 3)
    d = np.asarray(dist, float).ravel()
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1])):
        raise InputError(f"camera {which}: not a camera matrix: {K.tolist()}", path=path)
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise InputError(f"camera {which}: a skew of {K[0, 1] / K[0, 0]:.3g} (K[0][1] / fx): OpenCV's model, which "
                         "bsipipe undistorts with, has none; calibrate without skew", path=path)
    if d.size not in (4, 5, 8, 12) or not np.all(np.isfinite(d)):
        raise InputError(f"camera {which}: {d.size} distortion coefficients: OpenCV's 4, 5, 8 or 12 expected "
                         "(k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]])", path=path)
    if d.size == 4:
        d = np.append(d, 0.0)
    from ..imaging.calibrate import OPENCV_COEFF_NAMES
    out = {"camera_matrix": K.tolist(), "dist_model": f"opencv-{d.size}", "dist_coeffs": d.tolist(),
           "dist_coeff_names": list(OPENCV_COEFF_NAMES[:d.size])}
    if size is not None:
        out["image_size"] = [int(size[0]), int(size[1])]
    return out


def _stereo(R, T, a: str, b: str, path: Path) -> dict:
    R = np.asarray(R, float).reshape(3, 3)
    T = np.asarray(T, float).ravel()
    if T.size != 3 or not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        raise InputError("R is not a rotation or T not a 3-vector", path=path)
    return {"views": [a, b], "R": R.tolist(), "T_mm": T.tolist(), "rms_px": None}


def _frame_size(shapes: Mapping, v: str):
    s = shapes.get(v)
    return None if s is None else (int(s[1]), int(s[0]))


def _opencv(path: Path, views: Sequence[str], shapes: Mapping) -> dict:
    import cv2
    a, b = _pair(views, path, "OpenCV")
    if not path.exists():
        raise InputError("file not found", path=path)
    nodes: dict = {}
    files = [path]
    partner = _PARTNER.get(path.stem.lower())
    if partner:
        files += [path.with_name(partner + s) for s in OPENCV_SUFFIXES if path.with_name(partner + s).exists()][:1]
    for f in files:
        try:
            fs = cv2.FileStorage(str(f), cv2.FILE_STORAGE_READ)
        except cv2.error as e:
            raise InputError(f"not an OpenCV FileStorage file: {str(e).strip().splitlines()[-1]}", path=f) from None
        if not fs.isOpened():
            raise InputError("not an OpenCV FileStorage file (YAML or XML)", path=f)
        try:
            for key in ("M1", "D1", "M2", "D2", "R", "T", "image_size", "imageSize"):
                node = fs.getNode(key)
                if key not in nodes and not node.empty():
                    m = node.mat()
                    nodes[key] = np.asarray(m if m is not None else [node.at(i).real() for i in range(node.size())],
                                            float)
        finally:
            fs.release()
    missing = [k for k in ("M1", "D1", "M2", "D2", "R", "T") if k not in nodes]
    if missing:
        where = " or ".join(str(f.name) for f in files)
        raise InputError(f"no {', '.join(missing)} in {where}: an OpenCV stereo calibration holds M1, D1, M2, D2 "
                         "(intrinsics.yml of OpenCV's stereo_calib sample) and R, T (extrinsics.yml beside it)",
                         path=path)
    size = nodes.get("image_size", nodes.get("imageSize"))
    sizes = {v: (tuple(np.asarray(size).ravel()[:2]) if size is not None else _frame_size(shapes, v))
             for v in (a, b)}
    return {"views": {a: _view(nodes["M1"], nodes["D1"], sizes[a], path, "1"),
                      b: _view(nodes["M2"], nodes["D2"], sizes[b], path, "2")},
            "stereo": _stereo(nodes["R"], nodes["T"], a, b, path),
            "source": {"format": "opencv-filestorage", "files": [str(f) for f in files],
                       "views": {"1": a, "2": b}, "T_units": "as given to OpenCV (mm expected)"}}


def _bouguet(path: Path, views: Sequence[str]) -> dict:
    import cv2
    from scipy.io import loadmat
    a, b = _pair(views, path, "Bouguet toolbox")
    if not path.exists():
        raise InputError("file not found", path=path)
    try:
        m = loadmat(str(path))
    except NotImplementedError:
        raise InputError("a MATLAB v7.3 (HDF5) file: save it with save(..., '-v7') to read it", path=path) from None
    except Exception as e:  # noqa: BLE001 - scipy's MatReadError and the rest: an unreadable file
        raise InputError(f"not a MATLAB .mat file: {e}", path=path) from None
    need = [f"{k}_{s}" for s in ("left", "right") for k in ("fc", "cc", "kc")] + ["om", "T"]
    missing = [k for k in need if k not in m]
    if missing:
        single = all(k in m for k in ("fc", "cc", "kc"))
        raise InputError(f"no {', '.join(missing)}: " + (
            "a single camera's results (Calib_Results.mat); 3-D needs the stereo toolbox's Calib_Results_stereo.mat"
            if single else "Bouguet's stereo results (Calib_Results_stereo.mat) hold fc_left, cc_left, kc_left, the "
                           "same _right, om and T"), path=path)

    def vec(k, n=None):
        v = np.asarray(m[k], float).ravel()
        if n is not None and v.size != n:
            raise InputError(f"{k} has {v.size} values, {n} expected", path=path)
        return v

    out = {}
    for v, side, which in ((a, "left", "left"), (b, "right", "right")):
        fc, cc, kc = vec(f"fc_{side}", 2), vec(f"cc_{side}", 2), vec(f"kc_{side}")
        alpha = float(vec(f"alpha_c_{side}", 1)[0]) if f"alpha_c_{side}" in m else 0.0
        K = [[fc[0], alpha * fc[0], cc[0]], [0.0, fc[1], cc[1]], [0.0, 0.0, 1.0]]
        size = None
        if "nx" in m and "ny" in m:
            size = (int(vec("nx", 1)[0]), int(vec("ny", 1)[0]))
        out[v] = _view(K, kc, size, path, which)
    R, _ = cv2.Rodrigues(vec("om", 3).reshape(3, 1))
    return {"views": out, "stereo": _stereo(R, vec("T", 3), a, b, path),
            "source": {"format": "bouguet-toolbox", "files": [str(path)], "views": {"left": a, "right": b},
                       "T_units": "as the toolbox was given the grid (dX, dY; mm expected)"}}
