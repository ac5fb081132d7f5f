"""``bsipipe compare``: FE nodal displacements vs the markers' measured displacements.

::

    bsipipe compare --fe-displacements FILE --mesh MESH --markers markers_ct.csv [--frame F] -o DIR

Reads the FE result (:mod:`bsipipe.io.fe_results`: CSV ``node,ux_mm,uy_mm,uz_mm``, ABAQUS
``.rpt``, CalculiX ``.dat``/``.frd``, or any file meshio reads) and its mesh (ABAQUS ``.inp``
or any meshio format, in the CT/FE frame), interpolates the displacements at each marker's
registration-frame position with the element shape functions, and writes the seeds'
Table 1 (``DIR/table1.csv``), Table 2 (``DIR/table2.csv``), ``DIR/compare.png`` and
``DIR/compare.json`` (last; with ``sigma_mm``).  Stage: :mod:`bsipipe.fe.compare`.

The compared frame F defaults to the frame of the largest mean marker displacement (the
peak of the indentation), over the markers tracked in every frame or with short gaps
(:func:`bsipipe.fe.compare.peak_frame_info`).  The compared FE result (a ``.frd``/``.dat``/
``.rpt``/CSV may hold many) defaults to the one at F's time on the FE clock when both clocks
are known: ``fe_time_s`` in the marker table (export-fe's ``markers_fe.csv``) or the X-ray time
of FE time 0 that export-fe states in its deck's header (``** bsipipe: fe_time_zero_xray_s``);
else, when F is the peak, the FE result of the largest mean model displacement at the markers;
else the last, with a warning (:func:`bsipipe.fe.compare.choose_fe_result`).  ``compare.json``
says which frame and which FE result were compared and why.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
from pydantic import Field

from ..config import StrictModel, validate
from ..errors import InputError, ProcessingError

log = logging.getLogger(__name__)


class CompareConfig(StrictModel):
    """The settings of ``bsipipe compare`` (written into provenance as validated)."""

    frame: int | None = Field(None, description="compared frame; default the frame of peak mean displacement")
    markers: list[str] = Field(default_factory=list, description="markers to compare; default every non-reference")
    fe_result: int | None = Field(None, description="0-based index of the FE result (step/frame) in the file; "
                                                    "default the one of the compared frame's time, or the peak")
    length_unit: str = Field("mm", pattern="^(mm|m)$", description="length unit of the mesh and the FE result")
    outside_tol_mm: float = Field(0.0, ge=0.0, description="a marker this close outside the mesh takes the "
                                                           "displacement of the nearest element surface point")


#: Length units a mesh may be written in, and their size in mm.
_UNIT_MM = {"m": 1000.0, "cm": 10.0, "mm": 1.0, "um": 1e-3}


def _unmatched_labels(fe_mesh, disp, match: dict, mesh, path) -> str | None:
    """Node labels of the FE result that the mesh lacks.  All of them found in the mesh once
    shifted by one (a result numbered from 0 against a mesh numbered from 1, or the reverse)
    would put every displacement on its neighbour's node: exit 2.  Otherwise a warning (extra
    nodes of the solver's model, such as a reference node, are left out; a result of another
    mesh would be compared wrongly)."""
    if disp.node_ids is None or not match.get("n_unmatched_result_nodes"):
        return None
    have = np.asarray(fe_mesh.node_ids, dtype=np.int64)
    got = np.asarray(disp.node_ids, dtype=np.int64)
    out = got[~np.isin(got, have)]
    for shift in (1, -1):
        if np.isin(got + shift, have).all():
            raise InputError(
                f"{len(out)} node label(s) of the FE result are not in the mesh {mesh} (e.g. {', '.join(map(str, out[:3]))}), "
                f"and every label {'+' if shift > 0 else '-'} 1 is: the result looks numbered from "
                f"{'0' if shift > 0 else '2'} against the mesh's labels; write the result with the mesh's node labels",
                path=path)
    return (f"compare: {len(out)} node(s) of the FE result are not in the mesh {mesh} (e.g. "
            f"{', '.join(map(str, out[:5]))}) and are left out; a result of another mesh would be compared wrongly")


def _units_hint(nodes_mm: np.ndarray, markers_mm: np.ndarray, length_unit: str) -> str | None:
    """Why no marker is in the mesh, where the mesh's coordinates are in other units than
    ``length_unit`` says: as read, the markers lie more than twice the mesh's size away from
    its bounding box, and scaled by another unit's size the box (grown by a tenth) holds most
    of them.  None when no unit explains it."""
    lo, hi = nodes_mm.min(axis=0), nodes_mm.max(axis=0)
    read_mm = _UNIT_MM[length_unit]

    def inside(k: float) -> float:
        a, b = lo * k, hi * k
        pad = 0.1 * (b - a)
        return float(np.mean(np.all((markers_mm >= a - pad) & (markers_mm <= b + pad), axis=1)))

    span = float(np.max(hi - lo))
    # as read, the markers lie well away from the mesh (not just past its surface)
    away = float(np.median(np.linalg.norm(np.maximum(lo - markers_mm, 0) + np.maximum(markers_mm - hi, 0), axis=1)))
    if not away > 2 * span:
        return None
    for unit, mm in _UNIT_MM.items():
        k = mm / read_mm
        if unit != length_unit and inside(k) >= 0.5 > inside(1.0):
            hint = ("--length-unit m, which reads the displacement file in metres too: one unit for both files; "
                    "a mesh in metres with displacements in mm needs one of them converted"
                    if unit == "m" else f"in {unit}, which compare does not read (mm or m)")
            return (f"its nodes span {span:.3g} {length_unit} while the markers lie about "
                    f"{float(np.median(np.linalg.norm(markers_mm - 0.5 * (lo + hi), axis=1))):.3g} mm from its centre; "
                    f"read as {unit} the mesh holds {100 * inside(k):.0f} % of them: its coordinates look like {unit} "
                    f"({hint})")
    return None


def _scale_warning(model_mm: np.ndarray, measured_mm: np.ndarray, peak_values=None) -> str | None:
    """A warning where the model's displacements at the markers are a hundredth of the
    measured ones or less (or a hundred times or more), median over the markers: a length
    unit the FE result was written in other than the mesh's (metres read as mm), not a model
    that is merely stiff or soft -- unless another of the FE results (``peak_values``: each
    one's mean displacement at the markers) is within that range: then the result compared is
    the wrong one (FE result times halved had picked the unloaded state, and the warning had
    blamed the length unit)."""
    m = float(np.median(np.linalg.norm(model_mm, axis=1)))
    d = float(np.median(np.linalg.norm(measured_mm, axis=1)))
    if not (m > 0 and d > 0):
        return None
    r = m / d
    if 0.01 < r < 100:
        return None
    said = (f"the model's displacements at the markers are {r:.3g} times the measured ones (medians {m:.3g} and "
            f"{d:.3g} mm)")
    pv = np.asarray(peak_values if peak_values is not None else [], dtype=float)
    pv = pv[np.isfinite(pv) & (pv > 0)]
    if len(pv) and np.any((pv / d > 0.01) & (pv / d < 100)):
        return (f"{said}, while other FE results in the file reach {pv.max():.3g} mm: the result compared is not "
                "the measured frame's (its time, or the frame, is off; see --fe-result)")
    return (f"{said}: the FE result is likely in another length unit than the mesh (metres read as mm?); sigma is "
            "not meaningful until they agree")


def _axis_sign_warning(model_mm: np.ndarray, measured_mm: np.ndarray) -> str | None:
    """A warning where one axis of the model's displacements runs opposite to the measured one
    at the markers (the cosine of the two columns below -0.7, the axis carrying at least a fifth
    of the measured motion) and turning its sign would halve sigma or better: the FE result or
    the marker table uses another sign for that axis (another coordinate convention, a
    post-processor's axis flipped), not a model that is merely off.  uz negated in the FE
    result had given sigma 3.34 mm for 1.54, unsaid."""
    m = np.asarray(model_mm, float).reshape(-1, 3)
    d = np.asarray(measured_mm, float).reshape(-1, 3)
    if len(m) < 2:
        return None
    sigma = float(np.sqrt(np.mean(np.sum((m - d) ** 2, axis=1))))
    total = float(np.sqrt(np.sum(d ** 2)))
    for a, name in enumerate("xyz"):
        nm, nd = float(np.linalg.norm(m[:, a])), float(np.linalg.norm(d[:, a]))
        if not (nm > 0 and nd > 0.2 * total):
            continue
        cos = float(m[:, a] @ d[:, a]) / (nm * nd)
        if cos >= -0.7:
            continue
        f = m.copy()
        f[:, a] *= -1.0
        turned = float(np.sqrt(np.mean(np.sum((f - d) ** 2, axis=1))))
        if turned <= 0.5 * sigma:
            return (f"the model's {name} displacements run opposite to the measured ones at the markers (cosine "
                    f"{cos:.2f}); with their sign turned sigma would be {turned:.3g} mm instead of {sigma:.3g}: does "
                    f"the FE result (or the marker table) use the other sign for {name} (another coordinate "
                    "convention, an axis flipped on export)?")
    return None


def run(fe_displacements: str | os.PathLike, mesh: str | os.PathLike, markers: str | os.PathLike, *,
        out: str | os.PathLike, frame: int | None = None, marker_names: Sequence[str] = (),
        fe_result: int | None = None, length_unit: str = "mm", outside_tol_mm: float = 0.0) -> dict:
    """Run ``bsipipe compare``; returns the ``compare.json`` dict (also written to ``out``).

    Raises
    ------
    InputError
        Unreadable files, an unknown frame or marker (exit 2).
    ProcessingError
        No marker inside the mesh with a displacement (exit 1).
    """
    from ..fe.compare import choose_fe_result, compare_displacements, markers_at_frame, peak_frame_info
    from ..io.abaqus import abaqus_header_values
    from ..io.fe_results import displacements_on_mesh, read_displacements, read_mesh
    from .register import check_same_coordinate_system, coordinate_system_of, read_markers_ct
    from ..provenance import ResultSet, provenance
    from ..report.compare_figure import compare_figure

    cfg = validate(CompareConfig, {"frame": frame, "markers": list(marker_names), "fe_result": fe_result,
                                   "length_unit": length_unit, "outside_tol_mm": outside_tol_mm},
                   source="command line")
    warnings: list[str] = []
    table = read_markers_ct(markers)
    fe_mesh = read_mesh(mesh, length_unit=cfg.length_unit)
    header = abaqus_header_values(mesh) if str(mesh).lower().endswith(".inp") else {}
    check_same_coordinate_system(coordinate_system_of(table, markers), markers, header.get("ct_coordinate_system"),
                                 mesh)
    if cfg.fe_result is None:          # every result (the file parsed once), to choose from below
        results = read_displacements(fe_displacements, choose="all", length_unit=cfg.length_unit)
        last = results[-1]
    else:
        last = read_displacements(fe_displacements, choose=cfg.fe_result, length_unit=cfg.length_unit)
        results = [last]

    frames = sorted(table["frame"].unique())
    unknown = [m for m in dict.fromkeys(cfg.markers) if m not in set(table["marker"].astype(str))]
    if unknown:
        raise InputError(f"marker(s) {', '.join(unknown)} not in the marker table", path=markers)
    try:
        peak = peak_frame_info(table, cfg.markers or None)
    except ValueError as e:
        if cfg.frame is None:
            raise InputError(str(e), path=markers) from None
        peak = None
    if cfg.frame is None:
        F = peak.frame
        frame_why = "the peak: " + peak.method
        if not peak.markers:
            warnings.append(f"the peak frame {F} is the largest mean over the markers present in each frame: every "
                            f"marker has a long gap ({'; '.join(f'{k}: {v}' for k, v in peak.left_out.items())})")
    else:
        if cfg.frame not in set(frames):
            raise InputError(f"frame {cfg.frame} is not in the marker table (frames {frames[0]}..{frames[-1]})",
                             path=markers, frame=cfg.frame)
        F = int(cfg.frame)
        frame_why = "given (--frame)"
    mf = markers_at_frame(table, F, cfg.markers or None)
    unknown = [m for m, why in mf.skipped.items() if why == "not in the markers table"]
    if unknown:
        raise InputError(f"marker(s) {', '.join(unknown)} not in the marker table", path=markers)
    if not mf.names:
        raise ProcessingError(f"no marker with a position and a displacement in frame {F}", path=markers, frame=F)

    locator = fe_mesh.locator()
    loc = locator.locate(mf.position_mm, outside_tol_mm=cfg.outside_tol_mm)
    clock = _fe_clock(table, F, mf.time_s, header, last.format)
    peak_values = None
    if len(results) > 1:
        peak_values = []
        for r in results:
            u_r = locator.interpolate(displacements_on_mesh(fe_mesh, r)[0], loc)
            ok = np.all(np.isfinite(u_r), axis=1)
            peak_values.append(float(np.linalg.norm(u_r[ok], axis=1).mean()) if ok.any() else np.nan)
    _time_units_check(clock, [r.time for r in results], table, header, fe_displacements, markers, mesh)
    choice = choose_fe_result(last.n_results, given=cfg.fe_result,
                              fe_times=[r.time for r in results] if clock["target_fe_time"] is not None else None,
                              target_fe_time=clock["target_fe_time"], time_tol=clock["time_tol"],
                              peak_values=peak_values, frame_is_peak=peak is not None and F == peak.frame,
                              clock_zero=clock["clock_zero"])
    if clock["warning"]:
        warnings.append(clock["warning"])
    warnings += choice.warnings
    disp = results[choice.index] if len(results) > 1 else last
    nodal, match = displacements_on_mesh(fe_mesh, disp)
    if match["n_matched"] == 0:
        raise InputError(f"no node of the FE result matches a node of the mesh {mesh} ({match['matched_by']})",
                         path=fe_displacements)
    w = _unmatched_labels(fe_mesh, disp, match, mesh, fe_displacements)
    if w:
        warnings.append(w)
    u_model = locator.interpolate(nodal, loc)
    skipped = dict(mf.skipped)
    keep = []
    for i, n in enumerate(mf.names):
        if not loc.found[i]:
            skipped[n] = (f"outside the mesh (nearest element surface {loc.distance_mm[i]:.3g} mm away)"
                          if np.isfinite(loc.distance_mm[i]) else "outside the mesh")
        elif not np.all(np.isfinite(u_model[i])):
            skipped[n] = f"its element has a node without a displacement in {Path(fe_displacements).name}"
        else:
            keep.append(i)
    solid_skipped = {t: c for t, c in fe_mesh.skipped.items() if t.upper().startswith("C3D")}
    if solid_skipped and not loc.found.all():
        # a marker in an element of a type compare does not interpolate reads as outside
        what = ", ".join(f"{c} {t}" for t, c in sorted(solid_skipped.items()))
        for i, n in enumerate(mf.names):
            if not loc.found[i]:
                skipped[n] += f", or inside one of the mesh's solid elements compare does not interpolate ({what})"
    if skipped:
        warnings.append("skipped " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    if not keep:
        units = _units_hint(fe_mesh.coords_mm, mf.position_mm, cfg.length_unit) if not loc.found.any() else None
        if units is not None:
            raise InputError(f"no marker lies in the mesh: {units}", path=mesh)
        no_u = [i for i in range(len(mf.names)) if loc.found[i] and not np.all(np.isfinite(u_model[i]))]
        if no_u:
            # the markers are in the mesh; the displacement file lacks their elements' nodes
            missing = int((~np.all(np.isfinite(nodal), axis=1)).sum())
            others = [f"{k}: {v}" for k, v in skipped.items() if k not in {mf.names[i] for i in no_u}]
            raise InputError(f"{missing} of the mesh's {len(nodal)} nodes have no displacement in this file, among "
                             f"them nodes of the elements holding {', '.join(mf.names[i] for i in no_u)} in frame {F} "
                             f"(is it the result of this mesh, {Path(mesh).name}, written for every node?)"
                             + (f"; the other markers: {'; '.join(others)}" if others else ""),
                             path=fe_displacements, frame=F)
        raise ProcessingError(f"no marker lies in the mesh with FE displacements in frame {F}: "
                              + "; ".join(f"{k}: {v}" for k, v in skipped.items()), path=mesh, frame=F)
    names = [mf.names[i] for i in keep]
    res = compare_displacements(names, u_model[keep], mf.measured_mm[keep])
    scale = _scale_warning(u_model[keep], mf.measured_mm[keep], peak_values)
    if scale:
        warnings.append(scale)
    flip = _axis_sign_warning(u_model[keep], mf.measured_mm[keep])
    if flip:
        warnings.append(flip)

    per_marker = {}
    for i in keep:
        n = mf.names[i]
        blk = fe_mesh.blocks[loc.block[i]]
        per_marker[n] = {
            "position_mm": mf.position_mm[i].tolist(),
            "model_mm": u_model[i].tolist(), "measured_mm": mf.measured_mm[i].tolist(),
            "diff_mm": (u_model[i] - mf.measured_mm[i]).tolist(), "error_mm": res.error_mm[n],
            "element": int(blk.element_ids[loc.element[i]]), "element_type": blk.type_as_written,
            "xi": loc.xi[i].tolist(), "inside": bool(loc.inside[i]), "distance_mm": float(loc.distance_mm[i]),
        }
    result = {
        "sigma_mm": res.sigma_mm,
        "sigma_definition": "sqrt(sum_n E_n^2 / n), E_n = |model - measured| displacement of marker n",
        "sigma_axis_mm": res.sigma_axis_mm,
        "n_markers": res.n,
        "frame": F, "time_s": mf.time_s,
        "frame_choice": {"frame": F, "time_s": mf.time_s, "why": frame_why,
                         "peak": peak.to_dict() if peak is not None else None},
        "fe_result": {"index": choice.index, "description": disp.step, "time": disp.time, "why": choice.why,
                      "n_results": disp.n_results, "measured_frame_fe_time": choice.target_fe_time,
                      "clock": clock["source"],
                      "peak_index": (int(np.nanargmax(peak_values)) if peak_values is not None
                                     and np.isfinite(peak_values).any() else None),
                      "mean_model_displacement_mm": None if peak_values is None else
                      [v if np.isfinite(v) else None for v in peak_values]},
        "coordinate_system": {
            "frame": header.get("frame", "the CT (FE) frame of registration.json (markers_ct.csv)"),
            "ct_coordinate_system": header.get("ct_coordinate_system"),
            "source": ("the deck header written by export-fe" if "ct_coordinate_system" in header else
                       "not stated in the mesh file; markers and mesh must share the CT frame"),
            "length": cfg.length_unit},
        "positions": "marker positions in the registration frame (x_mm - dx_mm, ...), where the FE mesh is undeformed",
        "table2": res.table2.to_dict(orient="records"),
        "markers": per_marker,
        "skipped": skipped,
        "fe": {"displacements": str(fe_displacements), "format": disp.format, "result": disp.step,
               "time": disp.time, "n_results": disp.n_results, "mesh": str(mesh), "mesh_format": fe_mesh.format,
               "n_nodes": int(len(fe_mesh.node_ids)), "n_elements": fe_mesh.n_elements,
               "element_types": fe_mesh.element_types(), "skipped_element_types": fe_mesh.skipped,
               "node_matching": match, "length_unit": cfg.length_unit},
    }
    series = _time_series(results, table, clock, header, fe_mesh, locator, cfg) if cfg.fe_result is None else None
    result["time_series"] = series
    result["warnings"] = warnings
    for w in warnings:
        log.warning("compare: %s", w)
    result["provenance"] = provenance(cfg, [fe_displacements, mesh, markers], command="compare")

    rs = ResultSet(out, primary="compare.json")
    rs.add_csv("table1.csv", res.table1, float_format="%.12g")
    rs.add_csv("table2.csv", res.table2, float_format="%.12g")
    rs.add_figure("compare.png", compare_figure(res.table1, res.sigma_mm,
                                                title=f"FE vs markers, frame {F}, FE {disp.step}"))
    if series is not None:
        from ..report.compare_figure import compare_time_figure
        rs.add_figure("compare_time.png", compare_time_figure(table, series, cfg.markers or None))
    rs.add_json("compare.json", result)
    rs.commit()
    log.info("compare: %d markers, frame %d, FE result %d (%s), sigma %.4f mm", res.n, F, choice.index, disp.step,
             res.sigma_mm)
    if series is not None:
        log.info("compare: over the loading history, %d FE results on frames, %d marker positions, sigma %.4f mm",
                 series["n_results"], series["n_pairs"], series["sigma_mm"])
    return result


def _time_series(results, table: pd.DataFrame, clock: dict, header: dict, fe_mesh, locator, cfg) -> dict | None:
    """Every FE result whose time falls on a frame of the marker table (the clock that matched
    the compared frame: the table's ``fe_time_s`` or the deck's X-ray time of FE time 0; within
    half a frame interval) set against the markers found in that frame: the loading history, not
    one frame.  A marker hidden at the peak (behind the indentor) is compared where it is seen:
    on the sample study 3 markers were compared at the peak, all 5 over the history.  Returns
    ``results`` (per FE result: its index and time, the frame and its time, each marker's
    model and measured displacement, sigma), ``sigma_mm`` over every (result, marker) pair,
    ``per_marker`` (each marker's count and RMS error), or None (one result, or no clock)."""
    from ..fe.compare import markers_at_frame
    from ..io.fe_results import displacements_on_mesh
    if len(results) < 2 or clock.get("target_fe_time") is None or "time_s" not in table.columns:
        return None
    per_s = _PER_S.get(header.get("fe_time_unit", "s"), 1.0)
    frames = table.groupby("frame")
    if clock.get("clock_zero") is not None:
        fe_t = frames["time_s"].first().astype(float) * per_s - clock["clock_zero"]
    elif "fe_time_s" in table.columns:
        fe_t = pd.to_numeric(frames["fe_time_s"].first(), errors="coerce") * per_s
    else:
        return None
    fe_t = fe_t.dropna()
    if fe_t.empty:
        return None
    tol = max(float(clock.get("time_tol") or 0.0), 1e-9)
    rows, pairs = [], []
    for i, r in enumerate(results):
        if r.time is None or not np.isfinite(r.time):
            continue
        k = int(np.argmin(np.abs(fe_t.to_numpy() - r.time)))
        if abs(float(fe_t.iloc[k]) - r.time) > tol:
            continue
        f = int(fe_t.index[k])
        mf = markers_at_frame(table, f, cfg.markers or None)
        if not mf.names:
            continue
        loc = locator.locate(mf.position_mm, outside_tol_mm=cfg.outside_tol_mm)
        u = locator.interpolate(displacements_on_mesh(fe_mesh, r)[0], loc)
        ok = loc.found & np.all(np.isfinite(u), axis=1)
        if not ok.any():
            continue
        keep = np.flatnonzero(ok)
        e = np.linalg.norm(u[keep] - mf.measured_mm[keep], axis=1)
        pairs += [(mf.names[j], float(ej)) for j, ej in zip(keep, e)]
        rows.append({"fe_result": i, "fe_time": float(r.time), "frame": f, "time_s": mf.time_s,
                     "n_markers": len(keep), "sigma_mm": float(np.sqrt(np.mean(e ** 2))),
                     "markers": {mf.names[j]: {"model_mm": u[j].tolist(), "measured_mm": mf.measured_mm[j].tolist(),
                                               "error_mm": float(ej)} for j, ej in zip(keep, e)}})
    if not rows:
        return None
    err = np.array([e for _, e in pairs])
    per = {}
    for n, e in pairs:
        per.setdefault(n, []).append(e)
    return {"sigma_mm": float(np.sqrt(np.mean(err ** 2))), "n_results": len(rows), "n_pairs": int(len(err)),
            "sigma_definition": "sqrt(mean E^2) over every (FE result, marker) pair: E = |model - measured| "
                                "displacement of a marker found in the frame at the FE result's time",
            "per_marker": {n: {"n_results": len(v), "rms_error_mm": float(np.sqrt(np.mean(np.square(v))))}
                           for n, v in per.items()},
            "results": rows}


#: FE time units a deck states (``** bsipipe: fe_time_unit``) -> per second.
_PER_S = {"s": 1.0, "ms": 1000.0}


def _time_units_check(clock: dict, fe_times, table: pd.DataFrame, header: dict, fe_path, markers_path,
                      mesh_path) -> None:
    """Exit 2 where the measured frame's FE time lies outside the FE results' span, 1000 times
    it (or a thousandth) inside, and the FE results span about 1000 times the marker table's
    time (or a thousandth; within a factor 3): the FE results, the deck's header and the
    marker table do not count time in the same unit (ms against s), and the result nearest in
    time would be the wrong one.  (An FE run of part of the experiment spans a fraction of the
    table's time, not a thousand times it.)"""
    t = clock.get("target_fe_time")
    times = np.asarray([x for x in fe_times if x is not None], dtype=float)
    if t is None or len(times) < 2 or not np.all(np.isfinite(times)) or "time_s" not in table.columns:
        return
    lo, hi = float(times.min()), float(times.max())
    tol = float(clock.get("time_tol") or 0.0)
    ts = pd.to_numeric(table["time_s"], errors="coerce").dropna()
    per_s = _PER_S.get(header.get("fe_time_unit", "s"), 1.0)
    span_table = (float(ts.max()) - float(ts.min())) * per_s if len(ts) > 1 else 0.0
    if lo - tol <= t <= hi + tol or span_table <= 0 or hi <= lo:
        return
    ratio = (hi - lo) / span_table
    for f in (1000.0, 1e-3):
        if f / 3 < ratio < 3 * f and lo - tol * f <= t * f <= hi + tol * f:
            raise InputError(
                f"the measured frame's FE time ({t:.6g} {header.get('fe_time_unit', 's')}, from {clock['source']}) "
                f"lies outside the FE results' times {lo:.6g}..{hi:.6g}, and {f:g} times it inside: the FE results, "
                f"the deck {mesh_path} (header: FE time unit {header.get('fe_time_unit', 's')!r}) and the marker "
                f"table {markers_path} (time_s in s) do not count time in the same unit; give the deck the results "
                "were solved with, or the markers' times in seconds", path=fe_path)


def _fe_clock(table: pd.DataFrame, frame: int, time_s: float | None, header: dict, fe_format: str) -> dict:
    """Frame ``frame``'s time on the FE clock (``target_fe_time``, None when not known), the
    tolerance of a match (half the marker table's frame interval, FE time units), where the
    clock came from (``source``) and a ``warning`` when the FE file's times cannot be used."""
    out = {"target_fe_time": None, "time_tol": 0.0, "source": None, "warning": None, "clock_zero": None}
    per_s = _PER_S.get(header.get("fe_time_unit", "s"))
    if per_s is None:
        out["warning"] = f"the deck's FE time unit {header['fe_time_unit']!r} is unknown: FE times not matched"
        return out
    if fe_format == "abaqus-rpt":
        out["source"] = "not used: an ABAQUS report gives step times, not the total time the deck's clock counts"
        return out
    if "time_s" in table.columns:
        per_frame = table.groupby("frame")["time_s"].first().dropna().sort_index()
        if len(per_frame) > 1:
            out["time_tol"] = 0.5 * float(np.median(np.diff(per_frame.to_numpy(float)))) * per_s
    rows = table[table["frame"] == frame]
    fe_t = pd.to_numeric(rows["fe_time_s"], errors="coerce").dropna() if "fe_time_s" in rows.columns else []
    if len(fe_t):
        out["target_fe_time"] = float(fe_t.iloc[0]) * per_s
        out["source"] = "the marker table's fe_time_s"
    elif "fe_time_zero_xray_s" in header and time_s is not None:
        try:
            t0 = float(header["fe_time_zero_xray_s"])
        except ValueError:
            out["warning"] = f"the deck's fe_time_zero_xray_s {header['fe_time_zero_xray_s']!r} is not a number"
            return out
        out["target_fe_time"] = (time_s - t0) * per_s
        out["clock_zero"] = t0 * per_s
        out["source"] = (f"the marker table's time_s minus the X-ray time of FE time 0 in the deck's header "
                         f"({t0:.6g} s)")
    return out
