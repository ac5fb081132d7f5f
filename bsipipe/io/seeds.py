"""Seeds: each marker's position in the first frame of each view, as a user clicks them.

Two forms are read (:func:`read_seeds`):

- ``seeds.csv``: one row per view and marker, columns ``view,marker,x_px,y_px`` (pixels,
  x to the right, y down, the centre of the top-left pixel at (0, 0));
- an XMALab 2-D point CSV (:mod:`bsipipe.io.xmalab`), as a user clicks markers in XMALab:
  its first row (frame 0), ``camN`` the N-th view given (views all called ``camN``
  themselves are matched by name: :func:`bsipipe.io.xmalab.xmalab_cameras`).  Markers the file places only in
  later frames are not seeds; they are listed in ``attrs["later"]``, for a warning;
- a DLTdv points file (``<prefix>xypts.csv``, :mod:`bsipipe.io.dltdv`), as a user clicks
  markers in DLTdv8: the same, its points named ``pt1, pt2, ...`` and its pixel coordinates
  (1 at the top-left pixel's centre) taken to bsipipe's.

Errors are :class:`~bsipipe.errors.InputError` naming the file and, where there is one, the
line.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from ..errors import InputError


def _separator(path) -> str:
    """The seeds file's field separator: ``,``, or the ``;`` (a European spreadsheet's export)
    or tab its header uses instead."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            head = f.readline()
    except OSError:
        return ","          # read_csv says what is wrong with the file
    for sep in (";", "\t"):
        if sep in head and "," not in head:
            return sep
    return ","


def read_seeds(path, views: Sequence[str], frame_shapes: dict | None = None) -> pd.DataFrame:
    """``seeds.csv`` (``view,marker,x_px,y_px``), an XMALab 2-D CSV or a DLTdv ``xypts.csv``
    (first row; ``camN`` is the N-th view, or the view called ``camN``).  Errors name the file
    and line.  ``frame_shapes`` (view -> (h, w)): a seed outside its view's image is an error."""
    from .dltdv import is_dltdv_xypts, read_dltdv_xypts
    from .xmalab import is_xmalab_2d, read_xmalab_2d, xmalab_cameras
    dltdv = is_dltdv_xypts(path)
    if dltdv or is_xmalab_2d(path):
        allx = read_dltdv_xypts(path) if dltdv else read_xmalab_2d(path)
        cams = xmalab_cameras(views)
        allx = allx[allx["view"].isin(list(cams)) & np.isfinite(allx["x_px"]) & np.isfinite(allx["y_px"])].copy()
        allx["view"] = allx["view"].map(cams)
        x = allx[allx["frame"] == 0]
        x = x[["view", "marker", "x_px", "y_px"]].reset_index(drop=True)
        # markers the file places only in later frames (clicked where they were visible): the
        # seeds are frame 0's, so these are not followed in that view -- said, not dropped
        # silently (``attrs["later"]``: view -> {marker: first frame}, for track.json's warning)
        held = set(zip(x["view"], x["marker"]))
        later: dict = {}
        for (v, m), g in allx.groupby(["view", "marker"], sort=False):
            if (v, m) not in held:
                later.setdefault(v, {})[m] = int(g["frame"].min())
        _check_seeds_inside(x, frame_shapes, path, lines=None)
        if x.empty:
            raise InputError("no marker has a position in frame 0 (the first row): the seeds are the markers' "
                             "positions in the first frame", path=path)
        x.attrs["later"] = later
        return x
    try:
        try:
            df = pd.read_csv(path, dtype={"view": str, "marker": str}, sep=_separator(path), encoding="utf-8-sig")
        except UnicodeDecodeError:
            # a Windows spreadsheet's export, marker names with accents: Latin-1 (it had been
            # refused with a raw codec message)
            df = pd.read_csv(path, dtype={"view": str, "marker": str}, sep=_separator(path), encoding="latin-1")
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, ValueError, pd.errors.ParserError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read seeds: {e}", path=path) from None
    df.columns = [str(c).strip() for c in df.columns]
    miss = [c for c in ("view", "marker", "x_px", "y_px") if c not in df.columns]
    if miss:
        raise InputError(f"missing column(s) {', '.join(miss)}; expected view,marker,x_px,y_px", path=path, line=1)
    if df.empty:
        raise InputError("no seeds", path=path)
    for c in ("x_px", "y_px"):
        v = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(v.to_numpy(float)))
        if len(bad):
            cell = df[c].iloc[bad[0]]
            what = "is empty" if pd.isna(cell) or str(cell).strip() == "" else f"is not a number: {str(cell)!r}"
            raise InputError(f"{c} {what}", path=path, line=int(bad[0]) + 2)
        df[c] = v.astype(float)
    for c in ("view", "marker"):
        if df[c].isna().any():
            i = int(np.flatnonzero(df[c].isna().to_numpy())[0])
            raise InputError(f"empty {c}", path=path, line=i + 2)
        df[c] = df[c].astype(str).str.strip()
    odd = np.flatnonzero(df["marker"].str.contains('[,"]', regex=True).to_numpy())
    if len(odd):
        raise InputError(f"marker name {df['marker'].iloc[odd[0]]!r} holds a comma or a quote, which XMALab's "
                         "CSV layouts (xmalab_2d.csv, xmalab_3d.csv) cannot hold: rename it", path=path,
                         line=int(odd[0]) + 2)
    unknown = sorted(set(df["view"]) - set(views))
    if unknown:
        raise InputError(f"seeds for unknown view(s) {', '.join(unknown)}; the views are {', '.join(views)}",
                         path=path)
    dup = df.duplicated(["view", "marker"])
    if dup.any():
        i = int(np.flatnonzero(dup.to_numpy())[0])
        raise InputError(f"marker {df['marker'].iloc[i]!r} seeded twice in view {df['view'].iloc[i]!r}",
                         path=path, line=i + 2)
    _check_seeds_inside(df, frame_shapes, path, lines=np.arange(len(df)) + 2)
    return df[["view", "marker", "x_px", "y_px"]].reset_index(drop=True)


def _check_seeds_inside(df: pd.DataFrame, frame_shapes: dict | None, path, lines) -> None:
    """A seed must lie on its view's image (pixel centres 0..w-1, 0..h-1, half a pixel of edge)."""
    for k, (v, m, x, y) in enumerate(df[["view", "marker", "x_px", "y_px"]].itertuples(index=False)):
        shape = (frame_shapes or {}).get(v)
        if shape is None:
            continue
        h, w = shape[:2]
        if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
            raise InputError(f"seed {m!r} of view {v!r} at ({x:g}, {y:g}) px is outside the {w}x{h} px image",
                             path=path, line=None if lines is None else int(lines[k]))
