"""``bsipipe register``: CT marker coordinates + X-ray marker tracks -> registration.json, markers_ct.csv.

::

    bsipipe register --ct CT_MARKERS --xray markers3d.csv --reference NAME [--reference NAME ...] \\
                     [--frame F] [--scale/--no-scale] [--loop/--no-loop] -o DIR

The reference markers (skull-fixed, e.g. at the craniotomy corners) give the transform from
the X-ray frame to the CT frame in the registration frame F (default: the first frame in
which every reference is found): ``x_ct = scale * R @ x_xray + t_mm`` (geometry in
:mod:`bsipipe.geometry.registration`, loop in :mod:`bsipipe.geometry.registration_effects`).
Coordinates stay in the CT file's own system (LPS or RAS, as the file says).

Writes ``DIR/markers_ct.csv`` (every marker of ``markers3d.csv`` in every frame in the CT
frame, and its displacement from frame F, with the CT file's ``coordinate_system``),
``DIR/loop.md`` and ``DIR/registration.json`` (last, with its ``warnings``).  Exit 2 when
fewer than three references are found in both files (naming which and where they are
missing), or when the references coincide or lie on one line in either file.

Warnings (``registration.json`` ``warnings``, also logged; codes):

``references-missing``, ``no-frame-with-all-references``
    Some requested references are not used (named, with where they are missing).
``ill-conditioned-references``
    The references are nearly collinear (lateral spread under :data:`LINE_RATIO_MIN` of their
    length): the rotation about their line is poorly determined.
``label-swap``
    The loop exchanged two CT labels (the ``label-swap`` effect): the file's labels are wrong.
``large-fre``
    The final FRE is more than the tracking noise (times :data:`NOISE_FACTOR`) and a CT
    localisation error of :data:`CT_FLE_MAX_MM` can give together, and no effect explains it
    (with three references the moving-reference test cannot run).
``ct-check``
    Markers localised in CT that are not references lie more than :data:`NOISE_FACTOR` times
    the larger of the tracking noise and the estimated FLE, and more than
    :data:`CHECK_FLOOR_MM`, from where the transform puts them: a wrong transform (swapped
    or moved references), mislabelled markers or brain shift.
``ambiguous-reference-error``
    The loop kept ``label-swap`` (or ``moving-reference``) while the other explains the
    references about as well (within the loop's tie margin).
``late-registration-frame``
    The registration frame is not the table's first and markers other than the references
    had moved by then (more than :data:`NOISE_FACTOR` times the tracking noise) from where
    they were first found: markers_ct.csv's displacements, from the registration frame, miss
    that motion (``--frame`` of the first frame, where three references are found there).
``head-motion``
    The references move together over the trial (more than :data:`HEAD_MOTION_FACTOR` times
    their per-axis tracking noise with each frame's rigid motion taken out,
    ``skull_motion.tracking_noise_mm``; three references suffice): the head moved relative
    to the C-arms.  Every frame with three references or more is
    brought back onto the skull (:func:`_skull_fixed`: the references' rigid motion from the
    registration frame taken out of all its markers; ``markers_ct.csv`` column
    ``head_motion_mm``, ``skull_motion.compensation`` with the references' RMS motion before
    and after); frames with fewer are listed and left as they were.
``reference-motion-unresolved``
    References in use move relative to each other over the trial, but each one's motion is
    explained as well by another's (the head turned and a reference moved out of the plane
    of four nearly coplanar ones, which looks like a tilt moving any of them; or two moved):
    none is left out, and the head-motion compensation and the displacements carry part of
    that motion.
``marker-missing-in-registration-frame``
    A marker not found in the registration frame (found in others): its displacements are
    from a frame-F position estimated from its nearest frames (linear in time between the
    nearest before and after, else the nearest one), named with the frames used and how far
    it moved between them.
``ct-axis-scale``
    The loop kept ``ct-axis-scale``: the CT's lengths along one of its axes are off (slice
    spacing); the transform maps into the CT file's frame as it is, stretched
    (``ct_axis_scale``, ``matrix``); R, t_mm and scale alone leave the stretch out.
``ct-gantry-shear``
    The loop kept ``ct-gantry-shear``: the CT was acquired with the gantry tilted and read
    without its tilt (its y, or x, sheared by z); the transform maps into the CT file's frame
    as it is, sheared (``ct_gantry_shear``, ``matrix``), and markers_ct.csv's positions and
    displacements are in that frame; R, t_mm and scale alone leave the shear out.
``tre-not-estimated``
    No degrees of freedom left for the FLE.
``tre-unbounded``
    The FLE is estimated on two degrees of freedom (three references and a scale): the
    expected TRE is unbounded (``tre_mm`` empty); the perturbation's p95 still bounds it.

The tracking noise and the references' motion test use the raw 3-D points
(``x_mm_raw, y_mm_raw, z_mm_raw``) where ``markers3d.csv`` has them (decided per reference: one
without a raw point uses its smoothed ones, ``tracking_noise.smoothed_references``), the fit
the smoothed.  A reference's motion test takes out the other references' translation, or
their rigid motion where they turn (:func:`~bsipipe.geometry.registration.reference_motion`).
"""

from __future__ import annotations

import logging
import math
import os
from typing import Sequence

import numpy as np
import pandas as pd
from pydantic import Field

from ..config import StrictModel, validate
from ..errors import InputError, ProcessingError

log = logging.getLogger(__name__)

MARKERS3D_COLUMNS = ("frame", "marker", "x_mm", "y_mm", "z_mm")

#: A FRE or an implanted-marker check error more than this many times the expected error
#: (the tracking noise, 3-D RMS; for the check also the estimated FLE) is a warning.
NOISE_FACTOR = 10.0
#: ... and an implanted-marker check error is a warning only above this (mm): about a CT voxel,
#: which bounds how well a marker is localised in CT, and a brain shift between CT and trial of
#: this size is common.
CHECK_FLOOR_MM = 0.5
#: The largest 3-D RMS error of a reference's CT localisation (mm): about a CT voxel.  With the
#: tracking noise it bounds the FRE noise can give: :data:`NOISE_FACTOR` times their root sum
#: of squares is the loop's noise ceiling (per coordinate, over sqrt 3); a FRE above it is not
#: noise, however few references there are to show a pattern (four: twelve numbers).
CT_FLE_MAX_MM = 0.5
#: References whose X-ray lateral spread (off their best line) is under this many times their
#: 3-D tracking noise lie on one line as far as the data can tell: exit 2 (a spread of 0.02 mm
#: at 0.017 mm of noise had registered with a rotation 10.5 degrees off, exit 0).
LINE_NOISE_FACTOR = 5.0
#: The references moving together by more than this many times their per-axis tracking noise
#: (each frame's rigid motion taken out: :func:`~bsipipe.geometry.registration.rigid_tracking_noise`)
#: is head motion (``head-motion``).
HEAD_MOTION_FACTOR = 5.0
#: Lateral spread of the references over their length (``line_ratio`` of
#: :func:`~bsipipe.geometry.registration.point_configuration`) below which they are nearly collinear.
LINE_RATIO_MIN = 0.1


class RegisterConfig(StrictModel):
    """The settings of ``bsipipe register`` (written into provenance as validated)."""

    references: list[str] = Field(min_length=1, description="reference marker names (skull-fixed)")
    frame: int | None = Field(None, description="registration frame; default the first with every reference found")
    scale: bool = Field(False, description="fit a uniform scale as part of the declared model")
    loop: bool = True
    perturbation_draws: int = Field(2000, ge=0, description="re-fits of the perturbation TRE estimate (0: none)")
    seed: int = 0


def read_table(path, required: Sequence[str], *, expected: str, integer: Sequence[str] = ("frame",),
               text: Sequence[str] = ("marker",), optional_numeric: Sequence[str] = ()) -> pd.DataFrame:
    """One of bsipipe's own CSV tables (``markers3d.csv``, ``markers_ct.csv``), checked.

    ``required`` columns must be there (``expected`` says what the header should be);
    ``integer`` columns must hold integers, ``text`` columns non-empty names, the other
    required and ``optional_numeric`` columns numbers or nothing (NaN).  Errors name the file
    and the line (blank lines count, the header is line 1).
    """
    try:
        df = pd.read_csv(path, dtype={c: str for c in text}, skip_blank_lines=False)
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, ValueError, pd.errors.ParserError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read the table: {e}", path=path) from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}; expected {expected}", path=path, line=1)
    _not_cut(path, len(df.columns), len(df) + 1)
    df = df[~df.isna().all(axis=1)].copy()

    def line(k: int) -> int:
        return int(df.index[k]) + 2

    for c in text:
        if c in df.columns:
            empty = np.flatnonzero(df[c].isna().to_numpy())
            if len(empty):
                raise InputError(f"empty {c}", path=path, line=line(empty[0]))
            df[c] = df[c].astype(str).str.strip()
    numeric = [c for c in required if c not in text] + [c for c in optional_numeric if c in df.columns]
    for c in numeric:
        v = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(v.isna().to_numpy() & df[c].notna().to_numpy())
        if c in integer:
            vf = v.to_numpy(float)
            bad = np.flatnonzero(~np.isfinite(vf) | (np.nan_to_num(vf) % 1 != 0))
        if len(bad):
            kind = "an integer" if c in integer else "a number"
            raise InputError(f"{c} is not {kind}: {df[c].iloc[bad[0]]!r}", path=path, line=line(bad[0]))
        df[c] = v.astype(np.int64) if c in integer else v.astype(float)
    if df.empty:
        raise InputError("no data rows", path=path)
    return df


def _not_cut(path, n_fields: int, last_line: int) -> None:
    """Error where the table's last row has fewer fields than its header: the file was cut
    short mid-row (a copy interrupted, a disk full).  pandas reads the missing fields as
    empty: compare had picked another registration frame from a markers_ct.csv cut at 40 %,
    sigma 1.119 mm for 1.542, exit 0."""
    import csv
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(size - 65536, 0))
        tail = f.read().decode("utf-8", errors="replace")
    lines = [ln for ln in tail.splitlines() if ln.strip()]
    if len(lines) < 2 and size > 65536:
        return
    if not lines:
        return
    row = next(csv.reader([lines[-1]]))
    if len(row) < n_fields:
        raise InputError(f"the last row has {len(row)} of the header's {n_fields} fields: the file was cut short "
                         "(copy it again from the run that wrote it)", path=path, line=last_line)


def read_markers3d(path) -> pd.DataFrame:
    """``markers3d.csv`` (``frame,time_s,marker,x_mm,y_mm,z_mm[,...]``): positions may be empty (NaN).

    Returns columns ``frame`` (int), ``time_s`` (float, NaN when the file has none),
    ``marker`` (str), ``x_mm, y_mm, z_mm`` (float) plus the file's other columns.
    """
    df = read_table(path, MARKERS3D_COLUMNS, expected="frame,time_s,marker,x_mm,y_mm,z_mm",
                    optional_numeric=("time_s",))
    if "time_s" not in df.columns:
        df["time_s"] = np.nan
    _once_per_frame(df, path)
    return df.reset_index(drop=True)


def read_markers_ct(path) -> pd.DataFrame:
    """``markers_ct.csv`` as :func:`run` writes it (``frame,time_s,marker,x_mm,..,dz_mm[,role]``),
    for ``compare`` and ``export-fe``: one row per marker and frame (a second row of a marker
    in a frame, the same or not, is an error naming both lines); ``time_s`` NaN when the
    file has none."""
    from ..fe.compare import MARKERS_CT_COLUMNS

    df = read_table(path, MARKERS_CT_COLUMNS, expected="frame,time_s,marker,x_mm,y_mm,z_mm,dx_mm,dy_mm,dz_mm",
                    optional_numeric=("time_s", "fe_time_s"))
    if "time_s" not in df.columns:
        df["time_s"] = np.nan
    _once_per_frame(df, path)
    return df.reset_index(drop=True)


def _once_per_frame(df: pd.DataFrame, path) -> None:
    """Error (naming the line and the line of the first row) where a marker has two rows in
    one frame; ``df`` as :func:`read_table` returns it (index: data row number)."""
    dup = df.duplicated(["frame", "marker"], keep=False)
    if dup.any():
        rows = df[dup]
        first = rows.groupby(["frame", "marker"], sort=False).head(1)
        again = rows.drop(first.index)
        k = again.index[0]
        f = first[(first["frame"] == again.at[k, "frame"]) & (first["marker"] == again.at[k, "marker"])].index[0]
        raise InputError(f"marker {again.at[k, 'marker']!r} appears twice in frame {again.at[k, 'frame']} "
                         f"(also line {int(f) + 2}): one row per marker and frame",
                         path=path, line=int(k) + 2)


def _found(df: pd.DataFrame) -> pd.Series:
    return df[["x_mm", "y_mm", "z_mm"]].notna().all(axis=1)


def choose_frame(tracks: pd.DataFrame, references: Sequence[str], frame: int | None, *, xray_path=None
                 ) -> tuple[int, list[str], dict[str, str]]:
    """The registration frame, the references found in it, and why the others are missing.

    ``references`` are those present in the CT file.  Default frame: the first in which all
    are found; failing that, the first with the most found (the caller warns).
    """
    ok = tracks[_found(tracks) & tracks["marker"].isin(list(references))]
    frames = sorted(tracks["frame"].unique())
    if frame is not None:
        if frame not in set(frames):
            raise InputError(f"frame {frame} is not in the marker table (frames {frames[0]}..{frames[-1]})",
                             path=xray_path, frame=frame)
        chosen = int(frame)
    else:
        counts = ok.groupby("frame")["marker"].nunique().reindex(frames, fill_value=0)
        best = int(counts.max()) if len(counts) else 0
        chosen = int(counts.index[np.argmax(counts.to_numpy() == best)]) if best else int(frames[0])
    here = set(ok.loc[ok["frame"] == chosen, "marker"])
    found = [r for r in references if r in here]
    tracked = set(tracks.loc[_found(tracks), "marker"])
    missing = {}
    for r in references:
        if r in here:
            continue
        if r not in set(tracks["marker"]):
            missing[r] = "not in the X-ray marker table"
        elif r not in tracked:
            missing[r] = "never found in the X-ray marker table"
        else:
            missing[r] = f"not found in frame {chosen}"
    return chosen, found, missing


#: ``markers3d.csv``'s columns of the raw (unsmoothed) 3-D points, which ``bsipipe track``
#: writes beside the smoothed ``x_mm, y_mm, z_mm``.
RAW_COLUMNS = ("x_mm_raw", "y_mm_raw", "z_mm_raw")


def _tracks_array(tracks: pd.DataFrame, names: Sequence[str], *column_sets: Sequence[str]) -> tuple:
    """``(frames (F,), time_s (F,), positions (F, len(names), 3), ...)`` with NaN where
    missing: one positions array for each of ``column_sets`` (three position columns each;
    default ``x_mm, y_mm, z_mm``)."""
    frames = np.array(sorted(tracks["frame"].unique()), dtype=np.int64)
    sub = tracks[tracks["marker"].isin(list(names))]
    fi = np.searchsorted(frames, sub["frame"].to_numpy(np.int64))
    mi = sub["marker"].map({n: j for j, n in enumerate(names)}).to_numpy(np.int64)
    out = []
    for cols in column_sets or (("x_mm", "y_mm", "z_mm"),):
        pos = np.full((len(frames), len(names), 3), np.nan)
        pos[fi, mi] = sub[list(cols)].to_numpy(float)
        out.append(pos)
    time = tracks.groupby("frame")["time_s"].first().reindex(frames).to_numpy(float)
    return (frames, time, *out)


def estimate_frame_positions(tracks: pd.DataFrame, frame: int) -> dict[str, dict]:
    """X-ray positions in ``frame`` of the markers not found there but found in other frames.

    Linear in time between the nearest frames found before and after ``frame``; with frames on
    one side only, the nearest one's position.  Returns ``{marker: {"xyz": (3,), "frames":
    [frames used], "change_mm": ..}}``, ``change_mm`` the marker's motion between the two
    frames used (one side only: between the nearest frame and the next found beyond it), the
    scale of the estimate's error; markers never found are left out."""
    ok = tracks[_found(tracks)]
    here = set(ok.loc[ok["frame"] == frame, "marker"])
    t_of = tracks.groupby("frame")["time_s"].first()
    t_of = pd.Series(np.where(np.isfinite(t_of.to_numpy(float)), t_of.to_numpy(float),
                              t_of.index.to_numpy(float)), index=t_of.index)
    out = {}
    for m, g in ok[~ok["marker"].isin(here)].groupby("marker", sort=True):
        g = g.sort_values("frame")
        f = g["frame"].to_numpy(np.int64)
        x = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        before, after = np.flatnonzero(f < frame), np.flatnonzero(f > frame)
        if len(before) and len(after):
            a, b = before[-1], after[0]
            ta, tb, tF = t_of[f[a]], t_of[f[b]], t_of[frame]
            w = (tF - ta) / (tb - ta) if tb != ta else 0.5
            xyz, used, change = (1 - w) * x[a] + w * x[b], [int(f[a]), int(f[b])], np.linalg.norm(x[b] - x[a])
        else:
            side = before[::-1] if len(before) else after          # nearest first
            xyz, used = x[side[0]], [int(f[side[0]])]
            change = np.linalg.norm(x[side[1]] - x[side[0]]) if len(side) > 1 else float("nan")
        out[str(m)] = {"xyz": xyz, "frames": used, "change_mm": float(change)}
    return out


def markers_to_ct(tracks: pd.DataFrame, T, frame: int, roles: dict[str, str],
                  coordinate_system: str | None = None, estimated: dict[str, dict] | None = None) -> pd.DataFrame:
    """Every row of ``tracks`` mapped to the CT frame, with its displacement from ``frame``.

    ``dx_mm, dy_mm, dz_mm = T(x_f) - T(x_F)`` (NaN where the marker is missing in frame f, or
    in frame F and not in ``estimated``, :func:`estimate_frame_positions`, whose ``xyz`` then
    stands for ``x_F``); ``role`` from ``roles`` (default ``marker``); ``coordinate_system``
    is the CT file's (``LPS``, ``RAS``, or ``unstated`` for a plain CSV that does not say).
    """
    xyz = tracks[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    ct = T.apply(xyz)
    ref = tracks[(tracks["frame"] == frame) & _found(tracks)].set_index("marker")[["x_mm", "y_mm", "z_mm"]]
    ref_ct = {m: T.apply(v.to_numpy(float)) for m, v in ref.iterrows()}
    for m, e in (estimated or {}).items():
        ref_ct.setdefault(m, T.apply(np.asarray(e["xyz"], float)))
    d = np.array([ct[i] - ref_ct.get(m, np.full(3, np.nan)) for i, m in enumerate(tracks["marker"])]).reshape(-1, 3)
    out = pd.DataFrame({"frame": tracks["frame"].to_numpy(), "time_s": tracks["time_s"].to_numpy(float),
                        "marker": tracks["marker"].to_numpy(), "x_mm": ct[:, 0], "y_mm": ct[:, 1], "z_mm": ct[:, 2],
                        "dx_mm": d[:, 0], "dy_mm": d[:, 1], "dz_mm": d[:, 2],
                        "role": [roles.get(m, "marker") for m in tracks["marker"]],
                        "coordinate_system": coordinate_system or "unstated"})
    if "head_motion_mm" in tracks:      # the head's motion taken out of the frame (:func:`_skull_fixed`)
        out["head_motion_mm"] = tracks["head_motion_mm"].to_numpy(float)
    return out.sort_values(["frame", "marker"], kind="stable").reset_index(drop=True)


def coordinate_system_of(table: pd.DataFrame, path) -> str | None:
    """The CT coordinate system (``LPS`` or ``RAS``) a ``markers_ct.csv`` states in its
    ``coordinate_system`` column (:func:`markers_to_ct`), None where it does not say (no
    column, ``unstated``); rows that state both are an InputError naming the file."""
    if "coordinate_system" not in table.columns:
        return None
    said = {str(v).strip().upper() for v in table["coordinate_system"].dropna()} - {"", "UNSTATED"}
    if len(said) > 1:
        raise InputError(f"the coordinate_system column states {' and '.join(sorted(said))}: one table holds "
                         "markers of one CT frame", path=path)
    return next(iter(said)) if said else None


def check_same_coordinate_system(a: str | None, path_a, b: str | None, path_b) -> None:
    """Two files that both state the CT frame's coordinate system must state the same one: an
    LPS and an RAS description of one CT differ by the sign of x and y, and set against each
    other they would give wrong numbers without an error."""
    if a and b and a.upper() != b.upper():
        raise InputError(f"its CT coordinates are {a.upper()}, those of {path_b} are {b.upper()} (x and y of "
                         "opposite signs): register, export-fe and compare must work in one CT frame; rerun register "
                         "with the CT markups file of the frame the FE model is in", path=path_a)


def _rest_positions(tracks: pd.DataFrame) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Each marker's X-ray position in the first frame it is found in (the trial's start: at
    rest, as the CT saw it, whatever frame the references register in), and that frame."""
    ok = tracks[_found(tracks)].sort_values("frame", kind="stable")
    first = ok.groupby("marker", sort=False).head(1)
    pos = {str(m): np.array([x, y, z], float) for m, x, y, z in first[["marker", "x_mm", "y_mm", "z_mm"]]
           .itertuples(index=False)}
    return pos, {str(m): int(f) for m, f in first[["marker", "frame"]].itertuples(index=False)}


def _late_frame_warning(tracks: pd.DataFrame, F: int, rest: dict, rest_frame: dict, references: Sequence[str],
                        limit_mm: float, in_ct: Sequence[str], given: bool = False) -> dict | None:
    """``late-registration-frame`` when the registration frame ``F`` is not the table's first
    and markers other than the references had moved by then more than ``limit_mm``: the
    displacements in markers_ct.csv are from ``F``, so they miss that motion (``given``: F
    came from ``--frame``)."""
    from ..quality import warning

    f0 = int(tracks["frame"].min())
    if F == f0 or not np.isfinite(limit_mm):
        return None
    at = tracks[(tracks["frame"] == F) & _found(tracks)].set_index("marker")[["x_mm", "y_mm", "z_mm"]]
    moved = {}
    for m, x in at.iterrows():
        if m in references or m not in rest or rest_frame[m] >= F:
            continue
        d = float(np.linalg.norm(x.to_numpy(float) - rest[m]))
        if d > limit_mm:
            moved[str(m)] = d
    if not moved:
        return None
    here = sorted(set(tracks.loc[(tracks["frame"] == f0) & _found(tracks), "marker"]) & set(in_ct))
    hint = (f"; --frame {f0} registers there with the references found in it ({', '.join(here)})"
            if len(here) >= 3 else "")
    worst = sorted(moved.items(), key=lambda kv: -kv[1])
    return warning("late-registration-frame",
                   f"register: displacements in markers_ct.csv are from the registration frame {F} "
                   + ("(--frame)" if given else "(the first with every reference found)")
                   + f", not from frame {f0}: by frame {F} "
                   + ", ".join(f"{m} had moved {d:.3g} mm" for m, d in worst[:5])
                   + (f" and {len(worst) - 5} more" if len(worst) > 5 else "")
                   + f" (more than {limit_mm:.2g} mm) from where each was first found{hint}", log,
                   frame=int(F), first_frame=f0, moved_mm=moved, limit_mm=limit_mm)


def _check_handedness(xray: dict, ct: dict, *, scale: bool, ct_path, system, references: Sequence[str] = ()) -> None:
    """Refuse a CT file that matches the X-ray markers only as a mirror image.

    A file whose coordinates are mirrored relative to what it states (one axis flipped, a
    left-handed frame) cannot be mapped by a rotation.  Over every marker in both files (at
    least four, not coplanar: a planar set and its mirror image are congruent), the mirrored
    fit ``y ~ s R diag(-1, 1, 1) x + t`` is compared with the rigid one; mirrored RMS below a
    fifth of the rigid RMS, the rigid RMS above 1 % of the markers' spread, is an InputError,
    unless exchanging the CT labels of two ``references`` fits rigidly as well (within five
    times the mirrored RMS): four references with two equal pairs of distances (a square's
    corners) exchanged across a diagonal are a mirror image of themselves, and the loop's
    ``label-swap`` effect is the one to judge that.
    """
    from ..geometry.registration import fit_similarity, fre

    names = [n for n in xray if n in ct]
    if len(names) < 4:
        return
    x = np.array([xray[n] for n in names], dtype=float)
    y = np.array([ct[n] for n in names], dtype=float)
    xm = x * np.array([-1.0, 1.0, 1.0])
    try:
        e_rigid = float(np.sqrt(np.mean(fre(fit_similarity(x, y, scale=scale), x, y) ** 2)))
        e_mirror = float(np.sqrt(np.mean(fre(fit_similarity(xm, y, scale=scale), xm, y) ** 2)))
    except ValueError:  # collinear markers: the reference check reports them
        return
    spread = float(np.sqrt(np.mean(np.sum((y - y.mean(axis=0)) ** 2, axis=1))))
    if e_mirror < 0.2 * e_rigid and e_rigid > 0.01 * spread:
        refs = [names.index(r) for r in references if r in names]
        for i, a in enumerate(refs):
            for b in refs[i + 1:]:
                ys = y.copy()
                ys[[a, b]] = ys[[b, a]]
                try:
                    e_swap = float(np.sqrt(np.mean(fre(fit_similarity(x, ys, scale=scale), x, ys) ** 2)))
                except ValueError:
                    continue
                if e_swap < 5.0 * e_mirror:
                    return
        raise InputError(f"the CT markers match the X-ray markers only as a mirror image (RMS {e_mirror:.3g} mm "
                         f"mirrored vs {e_rigid:.3g} mm rigid over {len(names)} markers): the file's coordinates "
                         f"are flipped relative to the coordinate system it states ({system or 'none stated'})",
                         path=ct_path)


#: The largest ratio of the references' spreads in the two files (either way) taken for a
#: magnification error (a C-arm's source distance or pixel size off by tens of per cent at
#: most); beyond it the files' lengths are in different units.
MAX_SPREAD_RATIO = 2.0
#: A fitted scale further than this from 1 is warned (``large-scale``): a C-arm calibration's
#: magnification error is a few per cent; CT coordinates in voxel indices of 0.8 mm voxels had
#: been registered with scale 1.25 and FRE 0.007 mm, every displacement 25 % too large, unsaid.
MAX_PLAUSIBLE_SCALE_ERROR = 0.05
#: RMS distance (mm) of reference markers from their centroid that a skull's craniotomy can
#: hold (beads millimetres to centimetres apart); beyond it, in one file and not the other,
#: that file's coordinates are in other units.
PLAUSIBLE_SPREAD_MM = (0.5, 500.0)


def _check_length_units(x_mm, y_mm, *, ct_path, xray_path) -> None:
    """Refuse a CT file whose references span a very different size from the X-ray's (RMS
    distance from their centroid, ratio beyond :data:`MAX_SPREAD_RATIO`): its coordinates are
    in other units than millimetres (a CT exported in metres is 1000 times smaller, and the
    loop's ``scale`` would absorb it and write every ``_mm`` value in metres)."""
    def spread(p):
        p = np.asarray(p, float)
        return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))

    sx, sy = spread(x_mm), spread(y_mm)
    if not (sx > 0 and sy > 0):
        return
    r = sy / sx
    if 1.0 / MAX_SPREAD_RATIO <= r <= MAX_SPREAD_RATIO:
        return
    # which file is off: reference markers around a craniotomy lie millimetres to centimetres
    # apart, so a spread far outside PLAUSIBLE_SPREAD_MM names the file in other units
    lo, hi = PLAUSIBLE_SPREAD_MM
    xray_off = not lo <= sx <= hi and lo <= sy <= hi
    ratio = 1.0 / r if xray_off else r
    units = {1e-3: "metres", 1e-2: "centimetres", 1e3: "micrometres"}
    near = min(units, key=lambda u: abs(np.log10(ratio / u)))
    hint = (f": its coordinates look like {units[near]} (give them in mm, or convert)"
            if abs(np.log10(ratio / near)) < np.log10(MAX_SPREAD_RATIO) else
            ": its coordinates are in other units than millimetres, or not of these markers")
    if xray_off:
        raise InputError(f"the reference markers span {sx:.4g} (RMS from their centroid) in the X-ray markers and "
                         f"{sy:.4g} mm in the CT file ({ct_path}), {ratio:.3g} times as much, beyond any C-arm "
                         f"magnification error{hint}", path=xray_path)
    raise InputError(f"the reference markers span {sy:.4g} (RMS from their centroid) in the CT file and {sx:.4g} mm "
                     f"in the X-ray markers ({xray_path}), {r:.3g} times as much, beyond any C-arm magnification "
                     f"error{hint}", path=ct_path)


def _check_configuration(points, *, path, frame: int | None = None, names: Sequence[str], what: str) -> dict:
    """Refuse references that coincide or lie on one line (InputError naming ``path``); returns
    :func:`~bsipipe.geometry.registration.point_configuration` of ``points`` (n, 3)."""
    from ..geometry.registration import point_configuration

    conf = point_configuration(points)
    if conf["degenerate"] == "coincide":
        raise InputError(f"the {what} positions of the references {', '.join(names)} coincide (all within "
                         f"{conf['spread_mm']:.2g} mm of one point): they cannot define a transform",
                         path=path, frame=frame)
    if conf["degenerate"] == "collinear":
        raise InputError(f"the {what} positions of the references {', '.join(names)} lie on one line (lateral "
                         f"spread {conf['lateral_mm']:.2g} mm over {conf['spread_mm']:.3g} mm): a rotation about "
                         f"the line is undetermined; use references that span a plane", path=path, frame=frame)
    return conf


def _fre_rms(fit) -> float:
    """RMS over the used references of a :class:`~bsipipe.geometry.registration_effects.RegistrationFit`'s FRE."""
    return float(np.sqrt(np.mean(np.sum(fit.residual_vectors[fit.used] ** 2, axis=1))))


def _relabel_note(c) -> str:
    """What a relabelling cycle of the label-swap effect says about the CT file."""
    if len(c) == 2:
        return f"the CT file's {c[0]} is the marker the X-ray tracks call {c[1]}, and its {c[1]} is their {c[0]}"
    return "the CT file's " + ", its ".join(f"{b} is the marker the X-ray tracks call {a}"
                                           for a, b in zip(c, c[1:] + c[:1]))


def _reference_effect_warnings(report, *, has_check: bool) -> list[dict]:
    """``label-swap`` when the loop exchanged CT labels, ``moving-reference`` when it left a
    reference out; ``ambiguous-reference-error`` when the loop kept label-swap or
    moving-reference with the other within its tie margin."""
    from ..geometry.registration_effects import describe_cycle
    from ..quality import warning

    out = []
    for i, step in enumerate(report.steps):
        name = step.effect.name
        if name in ("label-swap", "moving-reference"):
            fre = f"loop effect {name}: FRE RMS {_fre_rms(step.before.fit):.4g} -> {_fre_rms(step.after.fit):.4g} mm"
            if name == "label-swap":
                new = [list(c) for c in step.after.spec.swapped if c not in step.before.spec.swapped]
                how = "exchanged" if all(len(c) == 2 for c in new) else "mixed up"
                what = (f"the CT labels {', '.join(describe_cycle(c) for c in new)} are {how} relative to the "
                        f"X-ray markers ({fre}); registered with the labels corrected: fix the CT file")
                details = {"pairs": [c for c in new if len(c) == 2], "cycles": new}
            else:
                new = [n for n in step.after.spec.moved if n not in step.before.spec.moved]
                what = (f"reference(s) {', '.join(new)} moved relative to the others (on the brain rather than the "
                        f"skull, or knocked) and were left out of the transform ({fre}); their role in "
                        "markers_ct.csv is moved-reference")
                details = {"references": new}
            out.append(warning(name, f"register: {what}", log, **details))
        rival = {"label-swap": "moving-reference", "moving-reference": "label-swap"}.get(step.effect.name)
        runner = step.evidence.get("runner_up") or {}
        if rival is None or runner.get("effect") != rival:
            continue
        if step.evidence.get("criterion") == "outside":
            what = "outside evidence"
            mine = (step.evidence.get("outside") or {}).get("delta_bic", 0.0)
            other = next(((c.get("outside") or {}).get("delta_bic", 0.0) for c in report.tried[i]
                          if c["effect"] == rival), 0.0)
        else:       # kept on the fit (a FRE above what noise can give): the runner-up's fit
            what = "delta BIC of the fit"
            mine, other = step.evidence["delta_bic"], runner.get("delta_bic", 0.0)
        if abs(mine - other) <= report.rule.tie_delta_bic:
            out.append(warning(
                "ambiguous-reference-error",
                f"register: {step.effect.name} and {rival} explain the references about equally ({what} "
                f"{mine:.1f} vs {other:.1f}); the loop kept {step.effect.name}"
                + ("" if has_check else "; no marker localised in CT besides the references could tell them "
                                        "apart: check the CT labels and the references by eye"), log,
                kept=step.effect.name, runner_up=rival))
    return out


def _skull_fixed(tracks: pd.DataFrame, frames: np.ndarray, refs: np.ndarray, fi: int,
                 motions: list) -> tuple[pd.DataFrame, dict]:
    """Every frame's X-ray positions moved back onto the skull: in each frame with at least
    three of the references ``refs`` (F, N, 3) found, the rigid transform taking them onto
    their registration-frame positions (frame index ``fi``; ``motions``: those transforms,
    :func:`~bsipipe.geometry.registration.reference_motions`) is applied to every marker of
    that frame.  Returns the moved table (a copy, column ``head_motion_mm``: how far the
    transform moved the references' centroid, NaN where not compensated) and a report: the
    references' RMS distance from their registration-frame positions before and after, and
    the frames left as they were."""
    out = tracks.copy()
    out["head_motion_mm"] = np.nan
    ref = refs[fi]
    before, after, left = [], [], []
    xyz = out[["x_mm", "y_mm", "z_mm"]].to_numpy(float, copy=True)
    for k, (f, m) in enumerate(zip(frames, motions)):
        if m is None:                   # fewer than three references, or on a line
            left.append(int(f))
            continue
        M, ok = m
        before.extend(np.linalg.norm(refs[k][ok] - ref[ok], axis=1) ** 2)
        after.extend(np.linalg.norm(M.apply(refs[k][ok]) - ref[ok], axis=1) ** 2)
        rows = (out["frame"] == f).to_numpy()
        xyz[rows] = M.apply(xyz[rows])
        c = refs[k][ok].mean(axis=0)
        out.loc[rows, "head_motion_mm"] = float(np.linalg.norm(M.apply(c) - c))
    out[["x_mm", "y_mm", "z_mm"]] = xyz
    report = {"method": "per frame, the rigid transform taking the used references onto their registration-frame "
                        "positions, applied to every marker of that frame (markers_ct.csv column head_motion_mm)",
              "reference_rms_mm_before": float(np.sqrt(np.mean(before))) if before else None,
              "reference_rms_mm_after": float(np.sqrt(np.mean(after))) if after else None,
              "n_frames_compensated": int(len(frames) - len(left)), "frames_not_compensated": left}
    return out, report


#: The slice-spacing error (relative) ``ct_axis_scale_check`` weighs: a reconstruction interval
#: or an uncorrected gantry tilt (18 degrees) gives 5 % or more.
UNSEEN_AXIS_SCALE = 0.05


def _mapped_offsets(T, x_targets, unseen=None, *, fiducials=None, scale: bool = False) -> list[float]:
    """How far (mm) a CT stretched along one axis, or sheared, puts each target ``x_targets``
    (X-ray frame) from where a transform without that stretch or shear maps it.

    With ``unseen`` (``centre -> `` the map of ``T`` into a CT stretched or sheared about
    ``centre``) and ``fiducials`` (the references' X-ray positions): the CT file's frame is that,
    about the references' centroid, and the transform is refitted to the distorted references
    (rigid, or with ``scale``), as the loop without the effect would: the error a distortion
    that size leaves unseen.  Without: ``T`` is the
    :class:`~bsipipe.geometry.registration.AxisScaledSimilarity` or
    :class:`~bsipipe.geometry.registration.ShearedSimilarity` the loop fitted, and the offset is
    that of its similarity part (the stretch or shear taken out) against ``T``."""
    from ..geometry.registration import fit_similarity

    x = np.asarray(x_targets, dtype=float).reshape(-1, 3)
    if not len(x):
        return []
    if unseen is None:
        return [float(v) for v in np.linalg.norm(T.apply(x) - T.similarity.apply(x), axis=1)]
    f = np.asarray(fiducials, dtype=float)
    S = unseen(T.apply(f).mean(axis=0))
    refit = fit_similarity(f, S.apply(f), scale=scale)
    return [float(v) for v in np.linalg.norm(refit.apply(x) - S.apply(x), axis=1)]


def _unseen_check(ident: dict, offsets: dict[str, float], tre: dict[str, float], size: dict, what: str) -> dict:
    """What the references can tell of a CT distortion they might not show (``ct_axis_scale_check``,
    ``ct_gantry_shear_check`` in registration.json): ``ident``
    (:func:`~bsipipe.geometry.registration_effects.axis_scale_identification` or
    :func:`~bsipipe.geometry.registration_effects.shear_identification`), the targets' offsets
    under a distortion of ``size`` (:func:`_mapped_offsets`) and their stated TRE; ``what``
    names the distortion in the note.  Logged (not a warning: it is the reference layout's
    limit, the same whether the CT is right or not; a warning had been given on 5 of 5 correct
    CTs of the twin at 0.15 mm CT noise) when not identified and a target moves beyond its TRE."""
    worse = {n: (o, tre[n]) for n, o in offsets.items() if not o <= tre[n]}
    out = {"identified": bool(ident["identified"]), "axis": ident["axis"],
           **({"by": ident["by"]} if "by" in ident else {}), "n_references": ident["n_references"],
           "lever_mm": ident["lever_mm"], "factor_se": ident["factor_se"], **size,
           "beyond_tre_mm": {n: v[0] for n, v in worse.items()},
           "note": (f"{what}, which these references " + ("could show" if ident["identified"] else "cannot show")
                    + ", would move the points in beyond_tre_mm further than their stated TRE (tre_mm does not "
                      "include it)")}
    if not ident["identified"] and worse:
        worst = max(worse, key=lambda n: worse[n][0])
        log.info("register: the references cannot show %s (%d references, lever %.2g mm, factor known to +- %.2g): "
                 "it would move %s %.2g mm against its TRE %.2g mm", what, ident["n_references"], ident["lever_mm"],
                 ident["factor_se"], worst, worse[worst][0], worse[worst][1])
    return out


def _mapped_effect_warning(report, name: str, T, x_targets, factor_se: float, what: str, cause: str,
                           fix: str) -> dict:
    """The warning of a kept ``ct-axis-scale`` or ``ct-gantry-shear`` (``name``): ``what`` the CT
    file shows (with the loop's FRE and implanted-marker figures), its ``cause``, how far the
    stretch or shear moves the markers ``x_targets`` and ``fix``."""
    from ..quality import warning
    from ..geometry.registration import CT_AXES

    step = next(s for s in report.steps if s.effect.name == name)
    chk = (step.evidence.get("outside") or {}).get("check")
    off = _mapped_offsets(T, x_targets)
    kind = "sheared" if name == "ct-gantry-shear" else "stretched"
    return warning(
        name,
        f"register: {what} (loop effect {name}: FRE RMS {_fre_rms(step.before.fit):.3g} -> "
        f"{_fre_rms(step.after.fit):.3g} mm"
        + (f", markers localised in CT {chk['rms_before_mm']:.3g} -> {chk['rms_after_mm']:.3g} mm RMS" if chk else "")
        + f"): {cause}; registered into the CT file's frame as it is, {kind}"
        + (f" (the {kind[:-2]} moves the markers up to {max(off):.2g} mm from where the same transform without "
           "it puts them)" if off else "")
        + f", as any mesh made from this CT is: {fix}; registration.json's R, t_mm and scale alone leave the "
          f"{kind[:-2]} out (matrix and {name.replace('-', '_')} hold it)",
        log, axis=CT_AXES[T.axis], factor=float(T.factor), factor_se=factor_se,
        **({"by": CT_AXES[T.by], "tilt_deg": T.tilt_deg} if name == "ct-gantry-shear" else {}))


def _noise_ceiling(noise: dict) -> float:
    """The loop's noise ceiling (mm, per coordinate) from the references' tracking noise
    (:func:`~bsipipe.geometry.registration.tracking_noise`; none measured: CT alone)."""
    track_3d = math.sqrt(3.0) * noise["sigma_mm"] if math.isfinite(noise["sigma_mm"]) else 0.0
    return NOISE_FACTOR * math.hypot(track_3d, CT_FLE_MAX_MM) / math.sqrt(3.0)


def run(ct: str | os.PathLike, xray: str | os.PathLike, references: Sequence[str], *,
        out: str | os.PathLike, frame: int | None = None, scale: bool = False, loop: bool = True,
        perturbation_draws: int = 2000, seed: int = 0) -> dict:
    """Run ``bsipipe register``; returns the ``registration.json`` dict (also written to ``out``).

    Raises
    ------
    InputError
        Unreadable files; fewer than three references in both files; references that
        coincide or lie on one line in either file (exit 2).
    ProcessingError
        The fit failed on valid input (exit 1).
    """
    from ..geometry import registration as reg
    from ..geometry.registration_effects import (MIN_REFERENCES, SHEAR_BY, UNSEEN_GANTRY_TILT_DEG, RegistrationData,
                                                 RegistrationSpec, axis_scale_identification,
                                                 close_registration_loop, ct_positions, reference_checks,
                                                 shear_identification, unresolved_motion)
    from ..io.slicer import read_markups
    from ..provenance import ResultSet, provenance
    from ..quality import warning
    from ..report.loop_report import loop_markdown

    warnings: list[dict] = []

    cfg = validate(RegisterConfig, {"references": list(references), "frame": frame, "scale": scale,
                                    "loop": loop, "perturbation_draws": perturbation_draws, "seed": seed},
                   source="command line")
    dupes = sorted({r for r in cfg.references if cfg.references.count(r) > 1})
    if dupes:
        raise InputError(f"reference {', '.join(dupes)} given twice")
    markups = read_markups(ct)
    tracks = read_markers3d(xray)
    ct_pos = markups.as_dict()

    missing: dict[str, str] = {}
    in_ct = []
    for r in cfg.references:
        if r in ct_pos:
            in_ct.append(r)
        elif r in markups.skipped:
            missing[r] = f"in {ct} but {markups.skipped[r]}"
        else:
            alike = [k for k in ct_pos if k.strip().casefold() == r.strip().casefold()]
            missing[r] = f"not in {ct}" + (f" (it has {', '.join(alike)}: names match as written, case "
                                           "included)" if alike else "")
    F, found, miss_x = choose_frame(tracks, in_ct, cfg.frame, xray_path=xray)
    missing.update({r: f"{why} ({xray})" for r, why in miss_x.items()})
    if len(found) < MIN_REFERENCES:
        detail = "; ".join(f"{r}: {why}" for r, why in missing.items())
        given = "" if len(cfg.references) >= MIN_REFERENCES else \
            f"only {len(cfg.references)} given (--reference {' --reference '.join(cfg.references)})"
        raise InputError(f"{len(found)} of {len(cfg.references)} reference markers found in both files "
                         f"(frame {F}), at least {MIN_REFERENCES} are needed: "
                         + "; ".join(x for x in (given, detail) if x), path=xray, frame=F)
    if missing:
        warnings.append(warning("references-missing", "register: references missing: " + "; ".join(
            f"{r}: {w}" for r, w in missing.items()), log, references=dict(missing)))
    # the frame-to-frame statistics (the tracking noise, the motion test) read the raw 3-D
    # points where the file has them: smoothed points wander slowly, not frame by frame, so a
    # noise taken from their scatter is several times too small and any wander is "motion"
    # (a static reference of the clean twin, 0.013 mm of wander within its stated sd, had
    # been dropped as moved, delta BIC 2917, in 6 of 13 tracked twins)
    # decided per reference: a reference with no raw point at all (the others have them) had
    # made the whole file's switch fail the other way round, the tracking noise NaN and with it
    # the motion tests, large-fre and the head-motion check (displacements off by 1.23 mm, unsaid)
    has_raw = all(c in tracks.columns for c in RAW_COLUMNS)
    frames, time, pos, *pos_raw = _tracks_array(tracks, found, ("x_mm", "y_mm", "z_mm"),
                                                *([RAW_COLUMNS] if has_raw else []))
    raw_refs = ([r for j, r in enumerate(found) if np.all(np.isfinite(pos_raw[0][:, j]), axis=1).any()]
                if has_raw else [])
    raw = bool(raw_refs)
    pos_stat = pos.copy()
    for j, r in enumerate(found):
        if r in raw_refs:
            pos_stat[:, j] = pos_raw[0][:, j]
    smoothed_refs = [r for r in found if r not in raw_refs] if raw else []
    fi = int(np.flatnonzero(frames == F)[0])
    if cfg.frame is None and len(found) < len(in_ct):
        warnings.append(warning("no-frame-with-all-references",
                                f"register: no frame has all {len(in_ct)} references found in the CT file; "
                                f"frame {F} has {len(found)}", log, frame=int(F)))
    y_refs = np.array([ct_pos[r] for r in found])
    conf = _check_configuration(y_refs, path=ct, names=found, what="CT")
    conf_x = _check_configuration(pos[fi], path=xray, frame=F, names=found, what="X-ray")
    ref_noise = reg.skull_tracking_noise(pos)
    noise_line = LINE_NOISE_FACTOR * math.sqrt(3.0) * ref_noise["sigma_mm"]
    if math.isfinite(noise_line) and conf_x["lateral_mm"] < noise_line:
        raise InputError(f"the X-ray positions of the references {', '.join(found)} lie on one line within their "
                         f"tracking noise (lateral spread {conf_x['lateral_mm']:.2g} mm over {conf_x['spread_mm']:.3g} "
                         f"mm, under {LINE_NOISE_FACTOR:g} x their 3-D noise, {noise_line:.2g} mm): a rotation about "
                         "the line is undetermined; use references that span a plane", path=xray, frame=F)
    worst = min((conf, "CT"), (conf_x, "X-ray"), key=lambda c: c[0]["line_ratio"])
    if worst[0]["line_ratio"] < LINE_RATIO_MIN:
        c = worst[0]
        warnings.append(warning(
            "ill-conditioned-references",
            f"register: the references {', '.join(found)} are nearly collinear in the {worst[1]} file (lateral "
            f"spread {c['lateral_mm']:.3g} mm over {c['spread_mm']:.3g} mm, ratio {c['line_ratio']:.3g} < "
            f"{LINE_RATIO_MIN:g}): the rotation about their line is poorly determined (about FLE / "
            f"{c['lateral_mm']:.3g} mm rad), and so is every point away from it", log,
            line_ratio=c["line_ratio"], lateral_mm=c["lateral_mm"], spread_mm=c["spread_mm"], file=worst[1]))
    _check_length_units(pos[fi], y_refs, ct_path=ct, xray_path=xray)
    targets, target_frames = _rest_positions(tracks)
    _check_handedness(targets, ct_pos, scale=cfg.scale, ct_path=ct,
                      system=markups.coordinate_system, references=found)

    t_names = list(targets)
    # Markers localised in CT that are not references: an independent check of any transform
    c_names = [n for n in t_names if n in ct_pos and n not in found]
    data = RegistrationData(names=list(found), x_mm=pos[fi].copy(), y_mm=y_refs,
                            tracks_mm=pos_stat, time_s=np.where(np.isfinite(time), time, frames.astype(float)),
                            check_x_mm=np.array([targets[n] for n in c_names]).reshape(-1, 3),
                            check_y_mm=np.array([ct_pos[n] for n in c_names]).reshape(-1, 3))
    spec0 = RegistrationSpec(scale=cfg.scale)
    ceiling = _noise_ceiling(ref_noise)
    try:
        report = close_registration_loop(data, spec0, loop=cfg.loop, noise_ceiling=ceiling)
    except ValueError as e:
        raise ProcessingError(f"registration failed: {e}", path=xray, frame=F) from None
    fit = report.final.fit
    spec = report.final.spec
    T = fit.transform
    used = [n for n, u in zip(found, fit.used) if u]
    fre = np.linalg.norm(fit.residual_vectors, axis=1)
    fre_rms = float(np.sqrt(np.mean(fre[fit.used] ** 2)))
    axis_scaled = spec.ct_axis is not None
    sheared = spec.ct_shear is not None
    mapped = axis_scaled or sheared         # the CT file's frame a correct CT's, stretched or sheared
    fle, fle_dof = reg.estimate_fle(fit.residual_vectors[fit.used], scale=spec.scale, axis_scale=mapped)
    noise = reg.skull_tracking_noise(pos_stat[:, fit.used])
    noise_3d = float(np.sqrt(3.0) * noise["sigma_mm"])
    # the FRE noise can give: the tracking noise and the CT localisation, at most about a voxel
    # (Fitzpatrick: <FRE^2> = (3N - p) / 3N FLE^2, 1 - 2/N for a rigid fit)
    n_fit = 3 * len(used)
    ct_fre = CT_FLE_MAX_MM * math.sqrt(max(n_fit - reg.n_params(spec.scale, mapped), 0) / n_fit)
    fre_limit = math.hypot(NOISE_FACTOR * noise_3d, ct_fre) if np.isfinite(noise_3d) else float("nan")
    swaps = [{"references": list(c), "note": _relabel_note(c)} for c in spec.swapped]
    warnings += _reference_effect_warnings(report, has_check=bool(c_names))
    unresolved = unresolved_motion(data, spec) if cfg.loop else []
    if unresolved:
        mo = {n: data.motion(n) for n in unresolved}
        turned = any(m["model"] == "rigid" for m in mo.values())
        warnings.append(warning(
            "reference-motion-unresolved",
            f"register: the references {', '.join(unresolved)} do not stay rigid relative to each other over the "
            f"trial (motion tests: " + ", ".join(f"{n} up to {m['max_displacement_mm']:.2g} mm" for n, m in mo.items())
            + "), but each one's motion is explained as well by another's "
            + ("(the head turned, and a reference moving out of the others' plane looks like a tilt that moves "
               "any of them) " if turned else "(more than one moved) ")
            + "so none was left out: a reference moved relative to the skull (on the brain, or knocked) and the "
              "tracks cannot tell which; the head-motion compensation and every displacement carry part of its "
              "motion: check the references by eye, or register with --reference naming only those on the bone",
            log, references=unresolved, head_turned=turned,
            max_displacement_mm={n: m["max_displacement_mm"] for n, m in mo.items()}))
    late = _late_frame_warning(tracks, F, targets, target_frames, found, NOISE_FACTOR * noise_3d, in_ct,
                               given=cfg.frame is not None)
    if late is not None:
        warnings.append(late)
    if np.isfinite(fre_limit) and fre_rms > fre_limit:
        # against the tracking noise alone (10 x 0.0016 mm from smoothed points) every
        # registration of a tracked twin at CT noise 0.1-0.5 mm had been warned
        why = ("with three references the moving-reference test cannot run, so a moved or mislabelled reference "
               "cannot be told from the others" if len(used) <= MIN_REFERENCES
               else "no loop effect explains it" if cfg.loop else "the loop was off (--no-loop)")
        warnings.append(warning(
            "large-fre", f"register: FRE RMS {fre_rms:.3g} mm is more than the references' tracking noise "
                         f"({noise_3d:.2g} mm, 3-D RMS, times {NOISE_FACTOR:g}) and a CT localisation error of "
                         f"{CT_FLE_MAX_MM:g} mm (about a voxel; {ct_fre:.2g} mm of FRE with {len(used)} references) "
                         f"can give ({fre_limit:.3g} mm), and {why}: a reference "
                         f"moved or is mislabelled, or the CT localisation is poor; the transform may be wrong", log,
            fre_rms_mm=fre_rms, tracking_noise_mm=noise_3d, limit_mm=fre_limit, n_used=len(used)))
    t_xyz = np.array([targets[n] for n in t_names]).reshape(-1, 3)
    x_used = data.x_mm[fit.used]
    if np.isfinite(fle) and len(t_names):
        # the FLE is estimated on fle_dof degrees of freedom (6 with four references): the
        # expected squared TRE is the plug-in one times E[nu / chi2_nu] = nu / (nu - 2), finite
        # only for nu > 2 (the probe's true / stated TRE had RMS 1.13-1.32 with four references,
        # 1.25-2.5 with three); the perturbation draws the FLE likewise
        tre = reg.tre_linearized(T, x_used, t_xyz, fle, scale=spec.scale) * (
            math.sqrt(fle_dof / (fle_dof - 2.0)) if fle_dof > 2 else float("nan"))
        pert = (reg.tre_perturbation(T, x_used, t_xyz, fle, scale=spec.scale, n_draws=cfg.perturbation_draws,
                                     seed=cfg.seed, fle_dof=fle_dof) if cfg.perturbation_draws > 0 else None)
        if pert is not None and fle_dof <= 2:
            pert["rms_mm"] = np.full(len(t_names), np.nan)
        if fle_dof <= 2:
            warnings.append(warning(
                "tre-unbounded", f"register: the FLE is estimated on {fle_dof} degree(s) of freedom only (three "
                                 "references and a scale): the expected TRE is unbounded, tre_mm is empty; "
                                 "tre_perturbation_p95_mm still bounds it (one more reference would give a TRE)",
                log, fle_dof=int(fle_dof)))
    else:
        tre = np.full(len(t_names), np.nan)
        pert = None
        warnings.append(warning("tre-not-estimated", "register: no degrees of freedom left to estimate the "
                                                     "localisation error; TRE not estimated", log))

    motions = reg.reference_motions(pos[:, fit.used], fi)
    skull = reg.skull_motion(pos[:, fit.used], fi, motions)
    skull["note"] = ("rigid motion of the used references as a whole relative to the registration frame; the "
                     "declared model has the head fixed relative to the C-arms (one transform for every frame)")
    # judged against the used references' tracking noise with each frame's rigid motion taken
    # out (a turn of the head does not inflate it), whatever their number: it had been the
    # motion tests' noise, which needs four references, so with three a head that turned 1.9
    # degrees and slid 1 mm was never compensated (displacements off by 1.28 mm, unsaid)
    head_noise = reg.rigid_tracking_noise(pos_stat[:, fit.used])
    skull["tracking_noise_mm"] = head_noise["sigma_mm"]
    head = None
    if np.isfinite(head_noise["sigma_mm"]) and skull["max_translation_mm"] > HEAD_MOTION_FACTOR * head_noise["sigma_mm"]:
        # the head moved relative to the C-arms: each frame is brought back onto the skull
        # (the used references' rigid motion from the registration frame taken out), so the
        # displacements are the tissue's relative to the skull, as the FE model's are
        tracks, head = _skull_fixed(tracks, frames, pos[:, fit.used], fi, motions)
        warnings.append(warning(
            "head-motion", f"register: the references move together by up to {skull['max_translation_mm']:.3g} mm "
                           f"(frame {int(frames[skull['frame_of_max']])}): the head moved relative to the C-arms; "
                           f"each frame was brought back onto the skull by the references' own rigid motion "
                           f"(references' RMS motion {head['reference_rms_mm_before']:.3g} -> "
                           f"{head['reference_rms_mm_after']:.3g} mm; {len(head['frames_not_compensated'])} frame(s) "
                           f"with fewer than 3 references left as they were)", log,
            max_translation_mm=skull["max_translation_mm"], compensated=True,
            frames_not_compensated=head["frames_not_compensated"]))
    skull["frame_of_max"] = int(frames[skull["frame_of_max"]])
    skull["compensation"] = head

    # A tracked point the CT does not hold (e.g. a bead on the indentor) is "xray-only"; an
    # implanted marker the CT file lists without a position (Slicer: undefined or missing) is
    # still a marker, it only has no CT check.
    roles = {n: "marker" if n in ct_pos or n in markups.skipped else "xray-only" for n in t_names}
    for r in found:
        roles[r] = "moved-reference" if r in spec.moved else "reference"
    # a marker hidden in the registration frame only had NaN displacements in every frame
    # (50 of 50 rows of the probe's M3), unsaid: its frame-F position is estimated from its
    # nearest frames, and a warning names it
    at_F = estimate_frame_positions(tracks, F)
    table = markers_to_ct(tracks, T, F, roles, markups.coordinate_system, estimated=at_F)
    if at_F:
        def how(m, e):
            fr = e["frames"]
            src = (f"interpolated between frames {fr[0]} and {fr[1]}, between which it moved "
                   f"{e['change_mm']:.3g} mm" if len(fr) == 2 else
                   f"taken from frame {fr[0]}, the nearest it is found in" + (
                       f" (it moves {e['change_mm']:.3g} mm over the next frame found)"
                       if np.isfinite(e["change_mm"]) else ""))
            return f"{m} ({src})"
        warnings.append(warning(
            "marker-missing-in-registration-frame",
            f"register: {len(at_F)} marker(s) not found in the registration frame {F}: their displacements in "
            f"markers_ct.csv are from an estimated frame-{F} position: "
            + "; ".join(how(m, e) for m, e in at_F.items())
            + "; an error of that estimate is in every displacement of the marker", log,
            frame=int(F), markers={m: {"frames": e["frames"], "change_mm": e["change_mm"],
                                       "xray_mm": [float(c) for c in e["xyz"]]} for m, e in at_F.items()}))
    no_ct = {n: markups.skipped[n] for n in t_names if n in markups.skipped and n not in cfg.references}

    check = {n: float(np.linalg.norm(T.apply(targets[n]) - ct_pos[n])) for n in c_names}
    check_scale = max([v for v in (noise_3d, fle) if np.isfinite(v)], default=float("nan"))
    check_limit = max(NOISE_FACTOR * check_scale, CHECK_FLOOR_MM) if np.isfinite(check_scale) else CHECK_FLOOR_MM
    bad = {n: e for n, e in check.items() if e > check_limit}
    if bad:
        warnings.append(warning(
            "ct-check", f"register: {len(bad)} of {len(check)} markers localised in CT lie far from where the "
                        f"transform puts them ({', '.join(f'{n} {e:.3g} mm' for n, e in bad.items())}; more than "
                        f"{check_limit:.2g} mm: {NOISE_FACTOR:g} x the larger of the tracking noise and the FLE, "
                        f"{check_scale:.2g} mm, and at least {CHECK_FLOOR_MM:g} mm): "
                        f"the transform is wrong (references swapped or moved), those markers are mislabelled, "
                        f"or the brain shifted since the CT", log,
            markers=bad, expected_mm=check_scale, limit_mm=check_limit))

    mapped_se = float("nan")
    axis_scale_check = shear_check = None
    not_refs = [targets[n] for n in t_names if n not in found]
    if mapped:
        # the FLE's own uncertainty as for the TRE (nu / (nu - 2) in the mean square)
        mapped_se = reg.factor_se(T, x_used, fle, scale=spec.scale) * (
            math.sqrt(fle_dof / (fle_dof - 2.0)) if fle_dof > 2 else float("nan"))
    # the tilt's standard error: d atan(k) = dk / (1 + k^2)
    tilt_se = float(np.degrees(mapped_se / (1.0 + T.factor ** 2))) if sheared else float("nan")
    if axis_scaled:
        warnings.append(_mapped_effect_warning(
            report, "ct-axis-scale", T, not_refs, mapped_se,
            f"the CT file's lengths along its {reg.CT_AXES[T.axis]} axis are {T.factor:.4g} (+- {mapped_se:.2g}) "
            "times those the X-ray markers show",
            "its slice spacing (reconstruction interval) is not what its header says, or a tilted gantry's table "
            "increment was taken for it", "correct the CT's spacing and segment and register again"))
    elif sheared:
        warnings.append(_mapped_effect_warning(
            report, "ct-gantry-shear", T, not_refs, mapped_se,
            f"the CT file's {reg.CT_AXES[T.axis]} coordinates are sheared by its {reg.CT_AXES[T.by]}: "
            f"{T.factor:.4g} (+- {mapped_se:.2g}) mm per mm, a gantry tilt of {T.tilt_deg:.3g} (+- {tilt_se:.2g}) "
            "degrees",
            "the CT was acquired with the gantry tilted and read without its tilt (DICOM's GantryDetectorTilt "
            "ignored: the slices stacked without their in-plane shift)",
            "read the CT with its gantry tilt corrected (a reader that applies GantryDetectorTilt, or resample "
            "it) and segment and register again"))
    elif cfg.loop and np.isfinite(fle):
        tgt = [n for n in t_names if n not in found]
        tre_of = {n: float(tre[t_names.index(n)]) for n in tgt}
        x_tgt = [targets[n] for n in tgt]
        k_unseen = float(np.tan(np.radians(UNSEEN_GANTRY_TILT_DEG)))
        axis_scale_check = _unseen_check(
            axis_scale_identification(data, spec, fle),
            dict(zip(tgt, _mapped_offsets(T, x_tgt, lambda c: reg.AxisScaledSimilarity(
                T.R, T.t_mm, float(T.scale), 2, 1.0 + UNSEEN_AXIS_SCALE, c), fiducials=x_used, scale=spec.scale))),
            tre_of, {"scale_error": UNSEEN_AXIS_SCALE}, f"a slice spacing {100 * UNSEEN_AXIS_SCALE:g} % off")
        shear_check = _unseen_check(
            shear_identification(data, spec, fle),
            dict(zip(tgt, _mapped_offsets(T, x_tgt, lambda c: reg.ShearedSimilarity(
                T.R, T.t_mm, float(T.scale), 1, k_unseen, c, SHEAR_BY), fiducials=x_used, scale=spec.scale))),
            tre_of, {"tilt_deg": UNSEEN_GANTRY_TILT_DEG, "factor": k_unseen},
            f"a gantry tilt of {UNSEEN_GANTRY_TILT_DEG:g} degrees read without it (y sheared by z)")

    if abs(float(T.scale) - 1.0) > MAX_PLAUSIBLE_SCALE_ERROR:
        warnings.append(warning(
            "large-scale",
            f"register: the registration's scale is {T.scale:.4g}: the CT and X-ray lengths differ by "
            f"{100 * abs(T.scale - 1):.0f} %, more than a C-arm calibration's magnification error (a few per cent); "
            f"are the CT coordinates ({ct}) voxel indices (isotropic voxels of {1 / T.scale:.3g} mm would give "
            f"this), or the CT's voxel size or the calibration target's spacing given wrong?  markers_ct.csv is in "
            "the CT file's units", log, scale=float(T.scale), limit=MAX_PLAUSIBLE_SCALE_ERROR))

    axis_scale_json = shear_json = None
    maps = "x_ct = scale * R @ x_xray + t_mm (X-ray/calibration frame to the CT frame)"
    if axis_scaled:
        axis_scale_json = {"axis": reg.CT_AXES[T.axis], "axis_index": int(T.axis), "factor": float(T.factor),
                           "factor_se": mapped_se, "centre_mm": T.centre_mm.tolist(),
                           "note": "the CT file's lengths along this axis are factor times those the X-ray "
                                   "markers show (the loop's ct-axis-scale effect): its slice spacing or "
                                   "reconstruction interval is off; factor_se from the fit at the estimated FLE"}
        maps = ("x_ct = c + D (scale * R @ x_xray + t_mm - c), D = I + (factor - 1) e e^T along ct_axis_scale.axis "
                "about c = ct_axis_scale.centre_mm (X-ray/calibration frame to the CT file's frame; matrix is the "
                "whole affine map; R, t_mm and scale alone map into a CT whose lengths along that axis are "
                "corrected, coinciding with the file's at c)")
    elif sheared:
        shear_json = {"axis": reg.CT_AXES[T.axis], "axis_index": int(T.axis), "by": reg.CT_AXES[T.by],
                      "factor": float(T.factor), "factor_se": mapped_se, "tilt_deg": T.tilt_deg,
                      "tilt_deg_se": tilt_se,
                      "centre_mm": T.centre_mm.tolist(),
                      "note": "the CT file's coordinate along axis is off by factor times its coordinate along by "
                              "(from centre_mm), factor = tan(tilt_deg) (the loop's ct-gantry-shear effect): the CT "
                              "was acquired with the gantry tilted and read without its tilt (GantryDetectorTilt "
                              "ignored); factor_se from the fit at the estimated FLE"}
        maps = ("x_ct = c + H (scale * R @ x_xray + t_mm - c), H = I + factor e_axis e_by^T "
                "(ct_gantry_shear.axis sheared by ct_gantry_shear.by) about c = ct_gantry_shear.centre_mm "
                "(X-ray/calibration frame to the CT file's frame, sheared as the file is: markers_ct.csv's positions "
                "and displacements are in it, where a mesh made from this CT lies; matrix is the whole affine map; "
                "R, t_mm and scale alone map into the CT read with its tilt corrected, coinciding with the file's "
                "at c)")
    result = {
        "R": T.R.tolist(), "t_mm": T.t_mm.tolist(), "scale": float(T.scale),
        "maps": maps,
        "matrix": T.matrix().tolist(),
        "ct_axis_scale": axis_scale_json,
        "ct_axis_scale_check": axis_scale_check,
        "ct_gantry_shear": shear_json,
        "ct_gantry_shear_check": shear_check,
        "rotation_deg": reg.rotation_angle_deg(T.R),
        "frame": int(F), "time_s": None if not np.isfinite(time[fi]) else float(time[fi]),
        "ct_coordinate_system": markups.coordinate_system,
        "ct_file": {"path": str(ct), "format": markups.format, "version": markups.version,
                    "coordinate_system": markups.coordinate_system or "not stated (coordinates used as written)"},
        "references": {"requested": list(cfg.references), "found": found, "used": used,
                       "moved": list(spec.moved), "swapped": [list(p) for p in spec.swapped], "missing": missing},
        "label_swaps": swaps,
        "reference_configuration": {"ct": conf, "xray": conf_x},
        "tracking_noise": {**noise, "rms_3d_mm": noise_3d,
                           "note": "per-axis scatter of the used references about their mean positions over "
                                   "the trial, their common translation taken out" + (
                                       " and, the head having turned (F test of the rotation, p "
                                       f"{noise['rotation']['p']:.2g} < {reg.ROTATION_P:g}), their rotation"
                                       if noise["model"] == "rigid" else "") + (
                                       "; of the raw 3-D points (x_mm_raw, ..), as the motion test" if raw else
                                       "") + (f"; {', '.join(smoothed_refs)}: no raw point, smoothed points used"
                                              if smoothed_refs else ""),
                           "smoothed_references": smoothed_refs},
        "model": spec.describe(),
        "fre_mm": {n: float(e) for n, e in zip(found, fre)},
        # the references' CT positions (labels given back where the loop found them mixed up):
        # with "frame", what markers_ct.csv's reference rows of that frame must be near
        # (export-fe checks that the two files come from one run)
        "reference_ct_mm": {n: [float(c) for c in y] for n, y in zip(found, ct_positions(data, spec))
                            if n not in spec.moved},
        "fre_rms_mm": fre_rms,
        "fle_mm": fle, "fle_dof": int(fle_dof),
        "fle_method": "3 RSS / (3N - p) over the used references (N - 2 for rigid: Fitzpatrick's <FRE^2> = (1 - 2/N) FLE^2)",
        "tre_mm": {n: float(e) for n, e in zip(t_names, tre)},
        "tre_method": ("first-order propagation of the estimated FLE through the fit (equals Fitzpatrick, West & "
                       "Maurer 1998 for a rigid fit), in the CT frame at each marker's X-ray position in the "
                       "first frame it is found in, times sqrt(nu / (nu - 2)) for the FLE's estimation on nu = "
                       "fle_dof degrees of freedom (the expected squared TRE; none for nu <= 2)"),
        "tre_perturbation_mm": None if pert is None else {n: float(e) for n, e in zip(t_names, pert["rms_mm"])},
        "tre_perturbation_p95_mm": None if pert is None else {n: float(e) for n, e in zip(t_names, pert["p95_mm"])},
        "tre_perturbation": None if pert is None else {"n_draws": pert["n_draws"], "seed": pert["seed"],
                                                        "method": "refit after isotropic Gaussian FLE added to the "
                                                                  "fitted CT references, each draw's FLE from its "
                                                                  "estimate's distribution (FLE^2 nu / chi2_nu)"},
        "ct_check_mm": check,
        "ct_check_rms_mm": float(np.sqrt(np.mean(np.square(list(check.values()))))) if check else None,
        "ct_check_note": "markers localised in CT that are not references: |T(x) - x_ct|, x their X-ray "
                         "position in the first frame each is found in (at rest, as the CT saw them; their own "
                         "localisation errors included)",
        "ct_position_undefined": no_ct,
        "reference_checks": reference_checks(data, spec),
        "skull_motion": skull,
        "loop": report.to_dict(),
        "n_frames": int(len(frames)),
        "warnings": warnings,
    }
    result["provenance"] = provenance(cfg, [ct, xray], command="register")

    rs = ResultSet(out, primary="registration.json")
    rs.add_csv("markers_ct.csv", table, float_format="%.12g")
    rs.add_text("loop.md", loop_markdown(result["loop"], title="Registration: closing the loop"))
    from ..report.register_figure import registration_figure
    ct_shown = {**{n: ct_pos[n] for n in ct_pos}, **(result.get("reference_ct_mm") or {})}
    rs.add_figure("registration.png", registration_figure(
        table, ct_shown, int(F), fre_mm=result["fre_mm"], check_mm=check, check_limit_mm=check_limit,
        system=markups.coordinate_system, title=f"bsipipe register: {spec.describe()}, FRE RMS {fre_rms:.3g} mm"),
        tight=False)
    rs.add_json("registration.json", result)
    rs.commit()
    log.info("register: %s, frame %d, FRE rms %.4f mm, moved %s", spec.describe(), F, fre_rms, list(spec.moved))
    return result
