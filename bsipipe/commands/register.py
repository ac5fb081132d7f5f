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
frame, and its displacement from frame F), ``DIR/loop.md`` and ``DIR/registration.json``
(last).  Exit 2 when fewer than three references are found in both files (naming which
and where they are missing).
"""

from __future__ import annotations

import logging
import os
from typing import Sequence

import numpy as np
import pandas as pd
from pydantic import Field

from ..config import StrictModel, validate
from ..errors import InputError, ProcessingError

log = logging.getLogger(__name__)

MARKERS3D_COLUMNS = ("frame", "marker", "x_mm", "y_mm", "z_mm")


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


def read_markers3d(path) -> pd.DataFrame:
    """``markers3d.csv`` (``frame,time_s,marker,x_mm,y_mm,z_mm[,...]``): positions may be empty (NaN).

    Returns columns ``frame`` (int), ``time_s`` (float, NaN when the file has none),
    ``marker`` (str), ``x_mm, y_mm, z_mm`` (float) plus the file's other columns.
    """
    df = read_table(path, MARKERS3D_COLUMNS, expected="frame,time_s,marker,x_mm,y_mm,z_mm",
                    optional_numeric=("time_s",))
    if "time_s" not in df.columns:
        df["time_s"] = np.nan
    dup = df.duplicated(["frame", "marker"], keep="first")
    if dup.any():
        i = int(np.flatnonzero(dup.to_numpy())[0])
        raise InputError(f"marker {df['marker'].iloc[i]!r} appears twice in frame {df['frame'].iloc[i]}",
                         path=path, line=int(df.index[i]) + 2)
    return df.reset_index(drop=True)


def _found(df: pd.DataFrame) -> pd.Series:
    return df[["x_mm", "y_mm", "z_mm"]].notna().all(axis=1)


def choose_frame(tracks: pd.DataFrame, references: Sequence[str], frame: int | None, *, xray_path=None
                 ) -> tuple[int, list[str], dict[str, str]]:
    """The registration frame, the references found in it, and why the others are missing.

    ``references`` are those present in the CT file.  Default frame: the first in which all
    are found; failing that, the first with the most found (a warning).
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
        if best < len(references):
            log.warning("register: no frame has all %d references; frame %d has %d", len(references), chosen, best)
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


def _tracks_array(tracks: pd.DataFrame, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames (F,), time_s (F,), positions (F, len(names), 3)) with NaN where missing."""
    frames = np.array(sorted(tracks["frame"].unique()), dtype=np.int64)
    pos = np.full((len(frames), len(names), 3), np.nan)
    fidx = {f: i for i, f in enumerate(frames)}
    sub = tracks[tracks["marker"].isin(list(names))]
    col = {n: j for j, n in enumerate(names)}
    for f, m, x, y, z in sub[["frame", "marker", "x_mm", "y_mm", "z_mm"]].itertuples(index=False):
        pos[fidx[f], col[m]] = (x, y, z)
    time = tracks.groupby("frame")["time_s"].first().reindex(frames).to_numpy(float)
    return frames, time, pos


def markers_to_ct(tracks: pd.DataFrame, T, frame: int, roles: dict[str, str]) -> pd.DataFrame:
    """Every row of ``tracks`` mapped to the CT frame, with its displacement from ``frame``.

    ``dx_mm, dy_mm, dz_mm = T(x_f) - T(x_F)`` (NaN where the marker is missing in either frame).
    """
    xyz = tracks[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    ct = T.apply(xyz)
    ref = tracks[tracks["frame"] == frame].set_index("marker")[["x_mm", "y_mm", "z_mm"]]
    ref_ct = {m: T.apply(v.to_numpy(float)) for m, v in ref.iterrows()}
    d = np.array([ct[i] - ref_ct.get(m, np.full(3, np.nan)) for i, m in enumerate(tracks["marker"])]).reshape(-1, 3)
    out = pd.DataFrame({"frame": tracks["frame"].to_numpy(), "time_s": tracks["time_s"].to_numpy(float),
                        "marker": tracks["marker"].to_numpy(), "x_mm": ct[:, 0], "y_mm": ct[:, 1], "z_mm": ct[:, 2],
                        "dx_mm": d[:, 0], "dy_mm": d[:, 1], "dz_mm": d[:, 2],
                        "role": [roles.get(m, "marker") for m in tracks["marker"]]})
    return out.sort_values(["frame", "marker"], kind="stable").reset_index(drop=True)


def _target_positions(tracks: pd.DataFrame, frame: int) -> dict[str, np.ndarray]:
    """Each marker's X-ray position in ``frame``, else its mean over the frames where it is found."""
    ok = tracks[_found(tracks)]
    out = {}
    for m, g in ok.groupby("marker", sort=False):
        at = g[g["frame"] == frame]
        src = at if len(at) else g
        out[str(m)] = src[["x_mm", "y_mm", "z_mm"]].to_numpy(float).mean(axis=0)
    return out


def _check_handedness(xray: dict, ct: dict, *, scale: bool, ct_path, system) -> None:
    """Refuse a CT file that matches the X-ray markers only as a mirror image.

    A file whose coordinates are mirrored relative to what it states (one axis flipped, a
    left-handed frame) cannot be mapped by a rotation.  Over every marker in both files (at
    least four, not coplanar: a planar set and its mirror image are congruent), the mirrored
    fit ``y ~ s R diag(-1, 1, 1) x + t`` is compared with the rigid one; mirrored RMS below a
    fifth of the rigid RMS, the rigid RMS above 1 % of the markers' spread, is an InputError.
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
        raise InputError(f"the CT markers match the X-ray markers only as a mirror image (RMS {e_mirror:.3g} mm "
                         f"mirrored vs {e_rigid:.3g} mm rigid over {len(names)} markers): the file's coordinates "
                         f"are flipped relative to the coordinate system it states ({system or 'none stated'})",
                         path=ct_path)


def run(ct: str | os.PathLike, xray: str | os.PathLike, references: Sequence[str], *,
        out: str | os.PathLike, frame: int | None = None, scale: bool = False, loop: bool = True,
        perturbation_draws: int = 2000, seed: int = 0) -> dict:
    """Run ``bsipipe register``; returns the ``registration.json`` dict (also written to ``out``).

    Raises
    ------
    InputError
        Unreadable files; fewer than three references in both files (exit 2).
    ProcessingError
        Degenerate reference geometry (collinear references) (exit 1).
    """
    from ..geometry import registration as reg
    from ..geometry.registration_effects import (MIN_REFERENCES, RegistrationData, RegistrationSpec,
                                                 close_registration_loop, reference_checks)
    from ..io.slicer import read_markups
    from ..provenance import ResultSet, provenance
    from ..report.loop_report import loop_markdown

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
            missing[r] = f"not in {ct}"
    F, found, miss_x = choose_frame(tracks, in_ct, cfg.frame, xray_path=xray)
    missing.update({r: f"{why} ({xray})" for r, why in miss_x.items()})
    if len(found) < MIN_REFERENCES:
        detail = "; ".join(f"{r}: {why}" for r, why in missing.items())
        raise InputError(f"{len(found)} of {len(cfg.references)} reference markers found in both files "
                         f"(frame {F}), at least {MIN_REFERENCES} are needed: {detail}", path=xray, frame=F)
    if missing:
        log.warning("register: references missing: %s", "; ".join(f"{r}: {w}" for r, w in missing.items()))
    _check_handedness(_target_positions(tracks, F), ct_pos, scale=cfg.scale, ct_path=ct,
                      system=markups.coordinate_system)

    frames, time, pos = _tracks_array(tracks, found)
    fi = int(np.flatnonzero(frames == F)[0])
    data = RegistrationData(names=list(found), x_mm=pos[fi].copy(), y_mm=np.array([ct_pos[r] for r in found]),
                            tracks_mm=pos, time_s=np.where(np.isfinite(time), time, frames.astype(float)))
    spec0 = RegistrationSpec(scale=cfg.scale)
    try:
        report = close_registration_loop(data, spec0, loop=cfg.loop)
    except ValueError as e:
        raise ProcessingError(f"registration failed: {e}", path=xray, frame=F) from None
    fit = report.final.fit
    spec = report.final.spec
    T = fit.transform
    used = [n for n, u in zip(found, fit.used) if u]
    fre = np.linalg.norm(fit.residual_vectors, axis=1)
    fre_rms = float(np.sqrt(np.mean(fre[fit.used] ** 2)))
    fle, fle_dof = reg.estimate_fle(fit.residual_vectors[fit.used], scale=spec.scale)

    targets = _target_positions(tracks, F)
    t_names = list(targets)
    t_xyz = np.array([targets[n] for n in t_names]).reshape(-1, 3)
    x_used = data.x_mm[fit.used]
    if np.isfinite(fle) and len(t_names):
        tre = reg.tre_linearized(T, x_used, t_xyz, fle, scale=spec.scale)
        pert = (reg.tre_perturbation(T, x_used, t_xyz, fle, scale=spec.scale, n_draws=cfg.perturbation_draws,
                                     seed=cfg.seed) if cfg.perturbation_draws > 0 else None)
    else:
        tre = np.full(len(t_names), np.nan)
        pert = None
        log.warning("register: no degrees of freedom left to estimate the localisation error; TRE not estimated")

    skull = reg.skull_motion(pos[:, fit.used], fi)
    skull["note"] = ("rigid motion of the used references as a whole relative to the registration frame; the "
                     "declared model has the head fixed relative to the C-arms (one transform for every frame)")
    noise = [m["sigma_mm"] for m in (data.motion(n) for n in used) if m and np.isfinite(m["sigma_mm"])]
    if noise and skull["max_translation_mm"] > 5 * np.median(noise):
        log.warning("register: the references move together by up to %.3g mm (frame %d): the head moved "
                    "relative to the C-arms; one transform does not serve every frame",
                    skull["max_translation_mm"], int(frames[skull["frame_of_max"]]))
    skull["frame_of_max"] = int(frames[skull["frame_of_max"]])

    # a tracked point the CT does not hold (e.g. a bead on the indentor) is "xray-only"
    roles = {n: "marker" if n in ct_pos else "xray-only" for n in t_names}
    for r in found:
        roles[r] = "moved-reference" if r in spec.moved else "reference"
    table = markers_to_ct(tracks, T, F, roles)

    # Markers localised in CT that are not references: an independent check of the transform
    check = {}
    for n in t_names:
        if n in ct_pos and n not in found:
            check[n] = float(np.linalg.norm(T.apply(targets[n]) - ct_pos[n]))

    result = {
        "R": T.R.tolist(), "t_mm": T.t_mm.tolist(), "scale": float(T.scale),
        "maps": "x_ct = scale * R @ x_xray + t_mm (X-ray/calibration frame to the CT frame)",
        "matrix": T.matrix().tolist(),
        "rotation_deg": reg.rotation_angle_deg(T.R),
        "frame": int(F), "time_s": None if not np.isfinite(time[fi]) else float(time[fi]),
        "ct_coordinate_system": markups.coordinate_system,
        "ct_file": {"path": str(ct), "format": markups.format, "version": markups.version,
                    "coordinate_system": markups.coordinate_system or "not stated (coordinates used as written)"},
        "references": {"requested": list(cfg.references), "found": found, "used": used,
                       "moved": list(spec.moved), "missing": missing},
        "model": spec.describe(),
        "fre_mm": {n: float(e) for n, e in zip(found, fre)},
        "fre_rms_mm": fre_rms,
        "fle_mm": fle, "fle_dof": int(fle_dof),
        "fle_method": "3 RSS / (3N - p) over the used references (N - 2 for rigid: Fitzpatrick's <FRE^2> = (1 - 2/N) FLE^2)",
        "tre_mm": {n: float(e) for n, e in zip(t_names, tre)},
        "tre_method": ("first-order propagation of the estimated FLE through the fit (equals Fitzpatrick, West & "
                       "Maurer 1998 for a rigid fit), in the CT frame at each marker's X-ray position in the "
                       "registration frame (else its mean position)"),
        "tre_perturbation_mm": None if pert is None else {n: float(e) for n, e in zip(t_names, pert["rms_mm"])},
        "tre_perturbation_p95_mm": None if pert is None else {n: float(e) for n, e in zip(t_names, pert["p95_mm"])},
        "tre_perturbation": None if pert is None else {"n_draws": pert["n_draws"], "seed": pert["seed"],
                                                        "method": "refit after isotropic Gaussian FLE added to the "
                                                                  "fitted CT references"},
        "ct_check_mm": check,
        "ct_check_rms_mm": float(np.sqrt(np.mean(np.square(list(check.values()))))) if check else None,
        "ct_check_note": "markers localised in CT that are not references: |T(x) - x_ct| (their own "
                         "localisation errors included)",
        "reference_checks": reference_checks(data, spec),
        "skull_motion": skull,
        "loop": report.to_dict(),
        "n_frames": int(len(frames)),
    }
    result["provenance"] = provenance(cfg, [ct, xray], command="register")

    rs = ResultSet(out, primary="registration.json")
    rs.add_csv("markers_ct.csv", table, float_format="%.12g")
    rs.add_text("loop.md", loop_markdown(result["loop"], title="Registration: closing the loop"))
    rs.add_json("registration.json", result)
    rs.commit()
    log.info("register: %s, frame %d, FRE rms %.4f mm, moved %s", spec.describe(), F, fre_rms, list(spec.moved))
    return result
