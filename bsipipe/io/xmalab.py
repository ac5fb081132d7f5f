"""XMALab's 2-D and 3-D point CSV files (read and write).

The layout is XMALab's own "export 2D points" / "export 3D points" (one file, header row,
``src/core/Trial.cpp`` ``save2dPoints`` / ``save3dPoints`` / ``load2dPoints``):

- 2-D: one column pair per marker and camera, markers outer, cameras inner,
  ``<marker>_cam1_X,<marker>_cam1_Y,<marker>_cam2_X,<marker>_cam2_Y,...``; one row per frame
  (no frame column; row *i* is frame *i*); a missing point is ``NaN`` in both columns.
- 3-D: ``<marker>_X,<marker>_Y,<marker>_Z`` per marker, one row per frame, ``NaN`` if missing.

XMALab numbers its cameras ``cam1, cam2, ...`` in the order they were loaded, whatever
they are called elsewhere; the writers take the views in a given order and map them to
``cam1..camN`` (:func:`xmalab_cameras`, recorded by the caller), except views that are all
called ``camN`` themselves, which keep their names whatever order they are given in.
Pixel coordinates are XMALab's default export ("distorted", not offset by 1, y not
inverted), which is bsipipe's convention: x to the right, y down, the centre of the top-left
pixel at (0, 0).  XMALab writes `` , `` between
fields and 12 significant digits; it reads a file by splitting each line at commas and
trimming the names, so plain commas (written here, as deepxromm and DeepLabCut's
``xrommtools`` do) load in XMALab and in pandas alike.  Empty fields are read as missing.
"""

from __future__ import annotations

import os
import re
from typing import Sequence

import numpy as np
import pandas as pd

from ..errors import InputError

_CAM_RE = re.compile(r"^(?P<marker>.+)_cam(?P<cam>\d+)_(?P<axis>[XY])$")
_3D_RE = re.compile(r"^(?P<marker>.+)_(?P<axis>[XYZ])$")


def _write(header: list[str], arr: np.ndarray) -> str:
    """Header and one line per row of ``arr``: 12 significant digits, ``NaN`` where not finite
    (formatted a column at a time: a long sequence has hundreds of thousands of values)."""
    cols = []
    for c in np.asarray(arr, float).T:
        s = [f"{v:.12g}" for v in c.tolist()]
        for i in np.flatnonzero(~np.isfinite(c)).tolist():
            s[i] = "NaN"
        cols.append(s)
    rows = (",".join(r) + "\n" for r in zip(*cols)) if cols else ("\n" for _ in range(len(arr)))
    return ",".join(header) + "\n" + "".join(rows)


def _positions(keys, order) -> np.ndarray:
    """Index of each key in ``order`` (-1 where it is not there)."""
    pos = {k: i for i, k in enumerate(order)}
    return np.array([pos.get(k, -1) for k in keys], dtype=np.int64)


def xmalab_cameras(views: Sequence[str]) -> dict[str, str]:
    """XMALab's camera name of each view, in XMALab's column order (``{"cam1": view, ...}``).

    The N-th view given is ``camN``, except when every view is called ``camN`` itself (in
    any order, numbers distinct): each is then its own camera, so ``--view cam2=... --view
    cam1=...`` reads and writes ``cam1`` as the view called ``cam1``, and a lone view called
    ``cam2`` takes an XMALab file's ``cam2`` columns.

    >>> xmalab_cameras(["lateral", "dorsal"])
    {'cam1': 'lateral', 'cam2': 'dorsal'}
    >>> xmalab_cameras(["cam2", "cam1"])
    {'cam1': 'cam1', 'cam2': 'cam2'}
    >>> xmalab_cameras(["cam2"])
    {'cam2': 'cam2'}
    """
    views = list(views)
    nums = [int(m.group(1)) if (m := re.fullmatch(r"cam(\d+)", v)) else None for v in views]
    if views and None not in nums and len(set(nums)) == len(nums) and min(nums) >= 1:
        return {f"cam{n}": v for n, v in sorted(zip(nums, views))}
    return {f"cam{i + 1}": v for i, v in enumerate(views)}


def format_xmalab_2d(points: pd.DataFrame, views: Sequence[str], markers: Sequence[str] | None = None,
                     frames: Sequence[int] | None = None) -> str:
    """XMALab 2-D CSV text from a tidy table ``view, frame, marker, x_px, y_px``.

    ``views`` in XMALab's camera order (``views[0]`` is ``cam1``); ``markers`` (default: in
    order of first appearance) and ``frames`` (default ``0..max``; row *i* is frame *i*, as
    XMALab assumes) fix the layout.
    """
    cams, markers, arr = camera_columns(points, views, markers, frames)
    header = [f"{m}_{c}_{a}" for m in markers for c in cams for a in "XY"]
    return _write(header, arr)


def camera_columns(points: pd.DataFrame, views: Sequence[str], markers: Sequence[str] | None = None,
                   frames: Sequence[int] | None = None) -> tuple[dict[str, str], list[str], np.ndarray]:
    """The (frames, 2 x markers x cameras) array of XMALab's (and DLTdv's) 2-D layout, markers
    outer, cameras inner, X then Y; a point missing in either coordinate is NaN in both (as
    XMALab sets it).  Returns the cameras (:func:`xmalab_cameras`), the markers and the array."""
    cams = xmalab_cameras(views)
    views = list(cams.values())             # the files' column order
    p = points[points["view"].isin(views)]
    markers = list(pd.unique(p["marker"])) if markers is None else list(markers)
    if frames is None:
        n = int(p["frame"].max()) + 1 if len(p) else 0
        frames = range(n)
    frames = list(frames)
    pairs = [(m, v) for m in markers for v in views]
    arr = np.full((len(frames), 2 * len(pairs)), np.nan)
    i = _positions(p["frame"].tolist(), frames)
    k = _positions(zip(p["marker"].tolist(), p["view"].tolist()), pairs)
    ok = (i >= 0) & (k >= 0)
    arr[i[ok], 2 * k[ok]] = p["x_px"].to_numpy(float)[ok]
    arr[i[ok], 2 * k[ok] + 1] = p["y_px"].to_numpy(float)[ok]
    miss = ~np.isfinite(arr[:, 0::2]) | ~np.isfinite(arr[:, 1::2])
    arr[:, 0::2][miss] = np.nan
    arr[:, 1::2][miss] = np.nan
    return cams, markers, arr


def format_xmalab_3d(points: pd.DataFrame, markers: Sequence[str] | None = None,
                     frames: Sequence[int] | None = None) -> str:
    """XMALab 3-D CSV text from a table ``frame, marker, x_mm, y_mm, z_mm``."""
    markers = list(pd.unique(points["marker"])) if markers is None else list(markers)
    if frames is None:
        n = int(points["frame"].max()) + 1 if len(points) else 0
        frames = range(n)
    frames = list(frames)
    arr = np.full((len(frames), 3 * len(markers)), np.nan)
    i = _positions(points["frame"].tolist(), frames)
    j = _positions(points["marker"].tolist(), markers)
    ok = (i >= 0) & (j >= 0)
    for a, c in enumerate(("x_mm", "y_mm", "z_mm")):
        arr[i[ok], 3 * j[ok] + a] = points[c].to_numpy(float)[ok]
    miss = ~np.isfinite(arr.reshape(len(frames), -1, 3)).all(axis=2)
    arr.reshape(len(frames), -1, 3)[miss] = np.nan
    header = [f"{m}_{a}" for m in markers for a in "XYZ"]
    return _write(header, arr)


def _read_table(path: str | os.PathLike) -> tuple[list[str], np.ndarray]:
    try:
        with open(path, encoding="utf-8-sig") as f:
            lines = [ln for ln in f.read().splitlines() if ln.strip()]
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read: {e}", path=path) from None
    if not lines:
        raise InputError("file is empty", path=path)
    header = [h.strip() for h in lines[0].split(",")]
    rows = []
    for k, ln in enumerate(lines[1:], start=2):
        fields = [x.strip() for x in ln.split(",")]
        if len(fields) != len(header):
            raise InputError(f"{len(fields)} fields, the header has {len(header)}", path=path, line=k)
        vals = []
        for x in fields:
            if x == "" or x.lower() == "nan":
                vals.append(np.nan)
                continue
            try:
                vals.append(float(x))
            except ValueError:
                raise InputError(f"not a number: {x!r}", path=path, line=k) from None
        rows.append(vals)
    return header, np.array(rows, float).reshape(len(rows), len(header))


def read_xmalab_2d(path: str | os.PathLike) -> pd.DataFrame:
    """Read an XMALab 2-D points CSV into a tidy table ``view, frame, marker, x_px, y_px``
    (views named ``cam1, cam2, ...``; missing points are NaN rows)."""
    header, arr = _read_table(path)
    keys = []
    for k, h in enumerate(header):
        m = _CAM_RE.match(h)
        if m is None:
            if h.endswith("_offset"):       # XMALab's optional offset columns
                keys.append(None)
                continue
            raise InputError(f"column {h!r} is not <marker>_cam<N>_X/Y (XMALab 2-D layout)", path=path, line=1)
        keys.append((m["marker"], int(m["cam"]), m["axis"]))
    pairs: dict[tuple[str, int], dict[str, int]] = {}
    for k, key in enumerate(keys):
        if key is not None:
            pairs.setdefault(key[:2], {})[key[2]] = k
    rows = []
    for (marker, cam), ax in pairs.items():
        if set(ax) != {"X", "Y"}:
            raise InputError(f"marker {marker!r} cam{cam} lacks its X or Y column", path=path, line=1)
        for f in range(arr.shape[0]):
            x, y = arr[f, ax["X"]], arr[f, ax["Y"]]
            if not (np.isfinite(x) and np.isfinite(y)):     # XMALab sets a point only when both are numbers
                x = y = np.nan
            rows.append({"view": f"cam{cam}", "frame": f, "marker": marker, "x_px": x, "y_px": y})
    return pd.DataFrame(rows, columns=["view", "frame", "marker", "x_px", "y_px"])


def read_xmalab_3d(path: str | os.PathLike) -> pd.DataFrame:
    """Read an XMALab 3-D points CSV into ``frame, marker, x_mm, y_mm, z_mm``."""
    header, arr = _read_table(path)
    cols: dict[str, dict[str, int]] = {}
    for k, h in enumerate(header):
        m = _3D_RE.match(h)
        if m is None:
            raise InputError(f"column {h!r} is not <marker>_X/Y/Z (XMALab 3-D layout)", path=path, line=1)
        cols.setdefault(m["marker"], {})[m["axis"]] = k
    rows = []
    for marker, ax in cols.items():
        if set(ax) != {"X", "Y", "Z"}:
            raise InputError(f"marker {marker!r} lacks one of its X, Y, Z columns", path=path, line=1)
        for f in range(arr.shape[0]):
            rows.append({"frame": f, "marker": marker, "x_mm": arr[f, ax["X"]], "y_mm": arr[f, ax["Y"]],
                         "z_mm": arr[f, ax["Z"]]})
    return pd.DataFrame(rows, columns=["frame", "marker", "x_mm", "y_mm", "z_mm"])


def is_xmalab_2d(path: str | os.PathLike) -> bool:
    """Whether a CSV's header is XMALab's 2-D layout (``<marker>_cam<N>_X`` columns)."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            head = f.readline()
    except (OSError, UnicodeDecodeError):
        return False
    cols = [h.strip() for h in head.split(",") if h.strip()]
    return bool(cols) and all(_CAM_RE.match(c) or c.endswith("_offset") for c in cols)
