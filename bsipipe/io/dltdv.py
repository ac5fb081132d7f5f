"""DLTdv's 2-D point CSV (``<prefix>xypts.csv``, Hedrick's DLTdv8; read and write).

The flat layout DLTdv writes (``DLTdv7.m``/DLTdv8a "export points", one file, header row):
one column pair per point and camera, points outer, cameras inner,
``pt1_cam1_X,pt1_cam1_Y,pt1_cam2_X,pt1_cam2_Y,pt2_cam1_X,...``; one row per frame (no frame
column; row *i* is frame *i + 1* in DLTdv, frame *i* here); ``NaN`` where a point is
missing.  It is XMALab's 2-D layout (:mod:`bsipipe.io.xmalab`) with the points numbered
``ptN`` instead of named, and in DLTdv8's pixel convention: MATLAB's, origin at the top-left
corner, the centre of the top-left pixel at (1, 1) (DLTdv8 turned the older versions' lower-left
origin into the image's own; ``DLTdv8a_internal/dlt_invert.m``), so each coordinate is
bsipipe's plus 1.  DLTdv names its cameras ``cam1, cam2, ...`` in the order the videos were
loaded, mapped to views as XMALab's are (:func:`bsipipe.io.xmalab.xmalab_cameras`); the
points' names are not in the file (the writer returns the ``ptN`` -> marker map for the
caller to record).  DLTdv's sparse export (a title line, then ``rows cols nnz`` and
``i j value`` triplets, tab-separated) is refused with a message: export the points flat.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Sequence

import pandas as pd

from ..errors import InputError
from .xmalab import _write, camera_columns, read_xmalab_2d

#: DLTdv8's pixel coordinates minus bsipipe's (MATLAB's pixel centres start at 1).
DLTDV_OFFSET_PX = 1.0

_PT_RE = re.compile(r"^pt(?P<point>\d+)_cam(?P<cam>\d+)_(?P<axis>[XY])$")


def _head(path) -> list[str]:
    try:
        with open(path, encoding="utf-8-sig") as f:
            return [f.readline(), f.readline()]
    except (OSError, UnicodeDecodeError):
        return ["", ""]


def is_dltdv_xypts(path: str | os.PathLike) -> bool:
    """Whether a file is a DLTdv points export: its name ends in ``xypts.csv`` (DLTdv's own
    suffix; an XMALab file may name its markers ``pt1`` too) and every header column is
    ``pt<N>_cam<M>_X/Y``, or it is DLTdv's sparse export (refused by :func:`read_dltdv_xypts`)."""
    if not Path(path).name.lower().endswith("xypts.csv"):
        return False
    first, second = _head(path)
    cols = [h.strip() for h in first.split(",") if h.strip()]
    if cols and all(_PT_RE.match(c) for c in cols):
        return True
    return _is_sparse(second)


def _is_sparse(line: str) -> bool:
    f = line.strip().split("\t")
    return len(f) == 3 and all(x.strip().isdigit() for x in f)


def read_dltdv_xypts(path: str | os.PathLike) -> pd.DataFrame:
    """A DLTdv flat ``xypts.csv`` as a tidy table ``view, frame, marker, x_px, y_px`` in
    bsipipe's pixel convention (views ``cam1, cam2, ...``, markers ``pt1, pt2, ...``, frame 0
    the file's first row; missing points NaN)."""
    if _is_sparse(_head(path)[1]):
        raise InputError("a DLTdv sparse export (a title line, then tab-separated counts and triplets): export the "
                         "points in DLTdv's flat format (one column per point, camera and axis)", path=path)
    df = read_xmalab_2d(path)
    df["x_px"] = df["x_px"] - DLTDV_OFFSET_PX
    df["y_px"] = df["y_px"] - DLTDV_OFFSET_PX
    return df


def format_dltdv_xypts(points: pd.DataFrame, views: Sequence[str], markers: Sequence[str] | None = None,
                       frames: Sequence[int] | None = None) -> tuple[str, dict[str, str]]:
    """DLTdv flat ``xypts.csv`` text from a tidy table ``view, frame, marker, x_px, y_px``, and
    the map ``{"pt1": marker, ...}``.  ``views`` in DLTdv's camera order (as
    :func:`~bsipipe.io.xmalab.format_xmalab_2d`); ``markers`` (default: in order of first
    appearance) become ``pt1, pt2, ...``; ``frames`` (default ``0..max``) the rows."""
    cams, markers, arr = camera_columns(points, views, markers, frames)
    arr = arr + DLTDV_OFFSET_PX
    header = [f"pt{j + 1}_{c}_{a}" for j in range(len(markers)) for c in cams for a in "XY"]
    return _write(header, arr), {f"pt{j + 1}": m for j, m in enumerate(markers)}
