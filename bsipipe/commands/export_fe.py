"""``bsipipe export-fe CONFIG.yaml -o DIR``: the FE hand-off package for ABAQUS, LS-DYNA and FEBio.

Reads the files named in the config (``fit.json``, ``registration.json``, ``markers_ct.csv``,
the indentation machine log, optionally ``markers3d.csv`` and a mesh), builds the hand-off
(:func:`bsipipe.fe.export.build_handoff`) and writes::

    DIR/abaqus/model.inp        complete deck (runs in CalculiX: ccx -i model)
    DIR/abaqus/material.inp, amplitude.inp, springs.inp     the same pieces as includes
    DIR/lsdyna/model.k          complete implicit deck; material.k, curve.k, springs.k
    DIR/febio/model.feb         complete FEBio 4 model; material.feb.xml
    DIR/amplitude.csv           the indentor's depth after contact (FE time) and tip position
    DIR/indentor_trajectory.csv the tip from the X-ray and from the log at every X-ray frame
    DIR/target_force.csv        the contact-zeroed force-indentation curve (the FE target)
    DIR/markers_fe.csv          markers in the FE frame: initial positions, displacements
    DIR/springs.csv             per-node interface springs (normals, tributary areas, stiffness)
    DIR/manifest.json           what each file is, its units and where its numbers come from (last)

Exit 2 for an invalid config or input (the message names the key or file); exit 1 when a
check of ``checks`` fails with ``on_fail: error``.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pandas as pd

from ..config import load_yaml, validate
from ..errors import InputError, ProcessingError

log = logging.getLogger("bsipipe.export_fe")

def load_export_config(path):
    """The validated config with its paths made absolute (relative to the config's folder)."""
    from ..fe.config import ExportConfig

    cfg = validate(ExportConfig, load_yaml(path), source=path)
    base = Path(path).resolve().parent

    def fix(p):
        return None if p is None else str(p if os.path.isabs(p) else base / p)

    inputs = cfg.inputs.model_copy(update={k: fix(getattr(cfg.inputs, k))
                                           for k in ("fit", "registration", "markers_ct", "log", "markers3d")})
    return cfg.model_copy(update={"inputs": inputs, "mesh": fix(cfg.mesh)})


def _read_json(path, key: str) -> dict:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("file not found", path=path, key=key) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot read JSON: {e}", path=path) from None
    if not isinstance(data, dict):
        raise InputError("expected a JSON object", path=path)
    return data


def read_fit(path) -> dict:
    """``fit.json`` by its contract: ``model`` and ``params`` (Pa; ``prony`` a list)."""
    fit = _read_json(path, "inputs.fit")
    for k in ("model", "params"):
        if k not in fit:
            raise InputError(f"no '{k}' (expected fit-ogden's fit.json)", path=path)
    if not isinstance(fit["params"], dict):
        raise InputError("'params' must be an object of parameter values", path=path)
    return fit


def read_registration(path):
    """``registration.json``: ``R`` (3 x 3 rotation), ``t_mm``, ``scale`` -> Similarity; with
    ``ct_axis_scale`` (the register loop found the CT stretched along one of its axes: a slice
    spacing off) the :class:`~bsipipe.geometry.registration.AxisScaledSimilarity` into the CT
    file's frame as it is (``R``, ``t_mm`` and ``scale`` alone leave the stretch out: the
    indentor 15 mm from the references along the axis had been placed 0.75 mm off at 5 %); with
    ``ct_gantry_shear`` (the CT read without its gantry tilt) the
    :class:`~bsipipe.geometry.registration.ShearedSimilarity` likewise (R, t_mm and scale alone
    had placed the indentor 15 mm from the references along z 2.6 mm off at 10 degrees)
    (:func:`~bsipipe.geometry.registration.registration_transform`; its errors name the file)."""
    from ..geometry.registration import registration_transform

    reg = _read_json(path, "inputs.registration")
    try:
        return registration_transform(reg), reg
    except ValueError as e:
        raise InputError(str(e), path=path) from None


#: markers_ct.csv's references at the registration frame may lie this far from registration.json's
#: CT positions of them (mm) -- their FRE is hundredths; another run's files are metres apart.
SAME_RUN_TOL_MM = 1.0


def _reference_offsets(reg: dict, table: pd.DataFrame, mapping=None) -> dict[str, float] | None:
    """Distance (mm) of each registration reference's row of ``table`` at the registration
    frame (mapped by ``mapping``, X-ray to CT, where given) from its CT position in
    ``registration.json`` (``reference_ct_mm``); None for a registration.json without them."""
    ref = reg.get("reference_ct_mm")
    frame = reg.get("frame")
    if not isinstance(ref, dict) or frame is None:
        return None
    at = table[table["frame"] == frame].set_index("marker")
    off = {}
    for name, xyz in ref.items():
        if name in at.index:
            p = at.loc[name, ["x_mm", "y_mm", "z_mm"]].to_numpy(float)
            if np.all(np.isfinite(p)):
                p = p if mapping is None else mapping.apply(p[None])[0]
                off[name] = float(np.linalg.norm(p - np.asarray(xyz, float)))
    return off


def _same_run(reg: dict, reg_path, markers_ct: pd.DataFrame, markers_path) -> None:
    """``markers_ct.csv`` and ``registration.json`` must come from one ``register`` run: the
    references' rows at the registration frame lie where the registration put their CT
    positions (within their FRE; :data:`SAME_RUN_TOL_MM`).  A registration.json written
    before it recorded those positions is not checked."""
    off = _reference_offsets(reg, markers_ct)
    if off is None:
        return
    if not off:
        raise InputError(f"holds none of the registration's references ({', '.join(reg['reference_ct_mm'])}) at "
                         f"its frame {reg['frame']}: it and {reg_path} come from different register runs",
                         path=markers_path)
    worst = max(off, key=off.get)
    if off[worst] > SAME_RUN_TOL_MM:
        raise InputError(f"reference {worst} at the registration frame {reg['frame']} lies {off[worst]:.4g} mm from "
                         f"where {reg_path} has it in CT (more than {SAME_RUN_TOL_MM:g} mm): the two files come from "
                         "different register runs", path=markers_path)


def _same_trial(reg: dict, reg_path, transform, tracks: pd.DataFrame, tracks_path) -> None:
    """``markers3d.csv`` must be the trial ``registration.json`` registered: its references at
    the registration frame, mapped by the registration, lie at their CT positions (within
    :data:`SAME_RUN_TOL_MM`; unchecked for a registration.json without them)."""
    off = _reference_offsets(reg, tracks, transform)
    if off and max(off.values()) > SAME_RUN_TOL_MM:
        worst = max(off, key=off.get)
        raise InputError(f"reference {worst} at the registration frame {reg['frame']}, mapped by {reg_path}, lies "
                         f"{off[worst]:.4g} mm from its CT position there (more than {SAME_RUN_TOL_MM:g} mm): the "
                         "registration is of another trial", path=tracks_path)


def read_log(path):
    from ..fe.export import LogRecord
    from ..io.machine_log import read_machine_log

    if not Path(path).exists():
        raise InputError("file not found", path=path, key="inputs.log")
    m = read_machine_log(path)
    disp, force = m.compression()
    return LogRecord(np.asarray(m.time_s, float), np.asarray(disp, float), np.asarray(force, float),
                     None if m.segment is None else np.asarray(m.segment)), m


def read_mesh(path, names):
    """A user's ABAQUS mesh as a :class:`~bsipipe.fe.mesh.SolidMesh` (labels, node sets)."""
    from ..fe.mesh import ElementBlock, SolidMesh
    from ..io.abaqus import abaqus_node_sets
    from ..io.fe_results import read_abaqus_mesh

    if not Path(path).exists():
        raise InputError("file not found", path=path, key="mesh")
    m = read_abaqus_mesh(path)
    blocks = []
    for b in m.blocks:
        if b.element_type not in ("C3D8", "C3D4"):
            raise InputError(f"the hand-off's interface needs C3D8 or C3D4 elements, the mesh has {b.element_type}",
                             path=path, key="mesh")
        blocks.append(ElementBlock(b.type_as_written, b.element_type, b.element_ids, m.node_ids[b.connectivity]))
    nsets = abaqus_node_sets(path)
    nsets["NALL"] = m.node_ids
    return SolidMesh(m.node_ids, m.coords_mm, blocks, nsets, source=str(path),
                     info={"kind": "user mesh", "path": str(path), "element_types": m.element_types(),
                           "n_nodes": int(len(m.node_ids)), "n_elements": m.n_elements,
                           "interface_set": names[0], "indentor_set": names[1]})


def run(config: str | os.PathLike, *, out: str | os.PathLike) -> dict:
    """Build and write the hand-off; returns ``manifest.json``'s content."""
    from ..commands.register import check_same_coordinate_system, coordinate_system_of, read_markers3d, read_markers_ct
    from ..fe.export import HandoffError, build_handoff, render_files
    from ..io._fe_material import unit_system
    from ..provenance import ResultSet, provenance

    cfg = load_export_config(config)
    inp = cfg.inputs
    fit = read_fit(inp.fit)
    transform, reg = read_registration(inp.registration)
    if not Path(inp.markers_ct).exists():
        raise InputError("file not found", path=inp.markers_ct, key="inputs.markers_ct")
    markers_ct = read_markers_ct(inp.markers_ct)
    check_same_coordinate_system(coordinate_system_of(markers_ct, inp.markers_ct), inp.markers_ct,
                                 reg.get("ct_coordinate_system"), inp.registration)
    _same_run(reg, inp.registration, markers_ct, inp.markers_ct)
    log_record, machine_log = read_log(inp.log)
    indentor_xray = None
    if inp.markers3d is not None:
        if not Path(inp.markers3d).exists():
            raise InputError("file not found", path=inp.markers3d, key="inputs.markers3d")
        indentor_xray = read_markers3d(inp.markers3d)
        _same_trial(reg, inp.registration, transform, indentor_xray, inp.markers3d)
    mesh = None
    if cfg.mesh is not None:
        mesh = read_mesh(cfg.mesh, (cfg.mesh_sets.interface, cfg.mesh_sets.indentor))

    sources = {"fit": inp.fit, "registration": inp.registration, "markers_ct": inp.markers_ct, "log": inp.log,
               "markers3d": inp.markers3d, "mesh": cfg.mesh, "config": str(config)}
    try:
        h = build_handoff(cfg, fit=fit, transform=transform, markers_ct=markers_ct, log=log_record,
                          indentor_xray=indentor_xray, mesh=mesh)
        files = render_files(h, cfg, sources, coordinate_system=reg.get("ct_coordinate_system"))
    except HandoffError as e:
        where = sources.get(e.source) if e.source else str(config)
        if e.failed_check:
            raise ProcessingError(f"check failed: {e}", path=where, key=e.key) from None
        if e.processing:
            raise ProcessingError(str(e), path=where, key=e.key) from None
        raise InputError(str(e), path=where, key=e.key) from None
    for w in h.warnings:
        log.warning("export-fe: %s", w)

    inputs = [p for p in (config, inp.fit, inp.registration, inp.markers_ct, inp.log, inp.markers3d, cfg.mesh) if p]
    u = unit_system(cfg.deck.units)
    manifest = _manifest(h, cfg, files, sources, reg, machine_log, u)
    figure = _handoff_png(h)
    import hashlib
    manifest["files"].append({
        "path": "handoff.png", "what": "the set-up at a glance: the mesh, the interface springs' brain nodes, the "
        "markers and the indentor (contact point, axis) in two views of the CT frame; the indentor's depth on the FE "
        "clock (deck amplitude, log, tracked tip) and the force target", "format": "PNG image",
        "units": "mm, s (FE clock), N", "sha256": hashlib.sha256(figure).hexdigest(),
        "sources": [{"quantity": "what the other files hold", "from": "this hand-off", "key": None}]})
    manifest["provenance"] = provenance(cfg, inputs, command="export-fe")
    # an earlier hand-off's files this one does not write go (another solver's deck, springs)
    rs = ResultSet(out, primary="manifest.json", outputs=(
        "amplitude.csv", "indentor_trajectory.csv", "markers_fe.csv", "springs.csv", "target_force.csv", "handoff.png",
        "abaqus/*.inp", "febio/*.feb", "febio/*.feb.xml", "lsdyna/*.k"))
    for f in files:
        rs.add_text(f.path, f.text)
    rs.add_bytes("handoff.png", figure)
    rs.add_json("manifest.json", manifest)
    rs.commit()
    d = h.difference_contact
    log.info("export-fe: %d files; indentor log vs X-ray during contact: %s", len(files),
             "n/a" if d is None else f"rms {d.rms_mm:.4f} mm, max {d.max_mm:.4f} mm")
    return manifest


def _handoff_png(h) -> bytes:
    """``handoff.png`` (:func:`~bsipipe.report.handoff_figure.handoff_figure`) as PNG bytes: listed in
    the manifest with its sha256 like every other file."""
    import io

    from ..report.handoff_figure import handoff_figure
    buf = io.BytesIO()
    handoff_figure(h, title=f"bsipipe export-fe: {len(h.markers_in_mesh)} markers in the mesh, "
                            f"{len(h.spring_k_n_per_mm)} interface springs").savefig(buf, format="png", dpi=120)
    return buf.getvalue()


def _manifest(h, cfg, files, sources, reg, machine_log, u) -> dict:
    import hashlib

    from ..fe.export import VISCO_CETOL, deck_increments

    step_s, dt_s = deck_increments(h, cfg.deck.max_increment_mm)
    al = h.alignment
    first_tip = None
    if h.trajectory is not None:
        first_tip = h.trajectory.iloc[0][["xray_x_mm", "xray_y_mm", "xray_z_mm"]].to_numpy(float).tolist()
    sp = h.springs
    return {
        "schema": "bsipipe-export-fe/1",
        "frame": {"name": "CT (FE) frame of registration.json",
                  "coordinate_system": reg.get("ct_coordinate_system"),
                  "maps": "x_ct = scale * R @ x_xray + t_mm", "length": "mm"},
        "units": {
            "tables": "names carry units: _mm millimetres, _s seconds, _n newtons, _mm2 square millimetres, "
                      "_n_per_mm newtons per millimetre",
            "decks": {"system": u.name, "length": u.length, "mass": u.mass, "time": u.time, "force": u.force,
                      "stress": u.stress,
                      "why": "brain-soft forces in mN stay above CalculiX's absolute residual floor (~1e-5 deck "
                             "force units); in N they fall below it" if u.name == "mm-kg-s-kPa" else None},
        },
        "files": [{"path": f.path, "what": f.what, "format": f.format, "units": f.units,
                   "sha256": hashlib.sha256(f.text.encode("utf-8")).hexdigest(), "sources": f.sources}
                  for f in files],
        "material": {"model": h.law, "params": h.params, "prony": h.prony, "from": sources["fit"],
                     "bulk_modulus_pa": cfg.deck.bulk_modulus_pa, "density_kg_m3": cfg.deck.density_kg_m3,
                     "note": ("the ABAQUS deck's steps are *VISCO, so ABAQUS includes the relaxation; CalculiX "
                              "has no *VISCOELASTIC (it warns and solves with the instantaneous moduli)")
                     if h.prony else None},
        "indentor": {
            "diameter_mm": cfg.indentor.diameter_mm,
            "source": h.indentor_source, "markers": h.indentor_names, "tip_offset_mm": cfg.indentor.tip_offset_mm,
            "axis_ct": h.axis.tolist(), "axis_source": al.axis_source if al else "config indentor.pose_xray.axis",
            "rest_tip_ct_mm": h.rest_tip_mm.tolist(),
            "first_frame_tip_ct_mm": first_tip,
            "contact_point_ct_mm": h.contact_point_mm.tolist(),
            "contact": {"log_time_s": h.window.time_s, "travel_mm": h.window.travel_mm,
                        "force_baseline_n": h.window.baseline_n, "method": h.window.method,
                        "lost_log_time_s": h.window.end_time_s if h.window.lost else None,
                        "xray_time_s": h.window.time_s + h.clock_offset_s},
            "speed_mm_per_min": h.speed_mm_per_min, "depth_mm": h.depth_mm,
            "log": {"path": sources["log"], "layout": machine_log.layout},
        },
        "trajectory": {
            "clock_offset_s": h.clock_offset_s, "clock_offset_source": h.clock_offset_source,
            "clock": "X-ray time = log time + clock_offset_s; FE time = log time - contact log time",
            "xray_to_log_travel_ratio": al.travel_ratio if al else None,
            "alignment_rms_residual_mm": al.rms_residual_mm if al else None,
            "clock_offset_alternatives": list(al.alternatives) if al else [],
            "clock_offset_choice": al.choice if al else None,
            "difference": {
                "what": "|tip from the X-ray - tip from the log| at the X-ray frames, CT frame",
                "during_contact": h.difference_contact.to_dict() if h.difference_contact else None,
                "whole_log": h.difference_record.to_dict() if h.difference_record else None,
            },
            "amplitude": {"source": h.amplitude_source, "n_knots": int(len(h.amplitude_time_s)),
                          "step_time_s": step_s, "max_depth_mm": float(h.amplitude_depth_mm.max()),
                          "tolerance_mm": cfg.deck.amplitude_tolerance_mm},
        },
        "springs": {
            "formula": ("stiffness per spring = interface stiffness x interface area / number of springs"
                        if cfg.interface.lumping == "uniform" else
                        "stiffness per spring = interface stiffness x the node's tributary area"),
            "lumping": cfg.interface.lumping,
            "stiffness_n_per_mm_per_mm2": cfg.interface.stiffness_n_per_mm_per_mm2,
            "study": {"area_mm2": h.nominal_area_mm2, "area_source": h.nominal_area_source,
                      "n_springs": cfg.interface.n_springs, "per_spring_n_per_mm": h.spring_nominal_n_per_mm},
            "deck": {"area_mm2": sp.area_mm2, "n_springs": sp.n_springs, "n_faces": sp.n_faces,
                     "per_spring_n_per_mm": h.spring_deck_n_per_mm,
                     "per_spring_deck_units": h.spring_deck_n_per_mm * u.per_n / (u.per_m / 1000.0),
                     "in_decks_n_per_mm": {"min": float(h.spring_k_n_per_mm.min()),
                                           "max": float(h.spring_k_n_per_mm.max()),
                                           "sum": float(h.spring_k_n_per_mm.sum())},
                     "deck_unit": f"{u.force}/{u.length}"},
            "length_mm": cfg.interface.spring_length_mm,
            "anchors": cfg.interface.anchors,
            "anchors_note": (
                "sliding: each skull node follows its brain node along the skull (u_s = (I - n n^T) u_b, "
                "*EQUATION; LS-DYNA: springs along their fixed normal), so a spring resists only the normal "
                "motion and a compressed 0.3 mm spring cannot swing sideways under NLGEOM. With fixed anchors "
                "CalculiX stopped at 2.4 mm of the demonstration indentation (compressed SPRINGA springs "
                "buckle). FEBio's linear springs always act along their nodes' line and its skull nodes are "
                "fixed (fixed anchors, whatever 'anchors' says; a warning when it says sliding)."),
        },
        "mesh": {**{k: v for k, v in h.mesh.info.items()}, "interface_area_mm2": sp.area_mm2,
                 "n_interface_nodes": sp.n_springs, "n_indentor_nodes": int(len(h.mesh.nsets["INDENTOR"])),
                 "source": sources["mesh"] or "generated (demo_mesh)",
                 "note": None if sources["mesh"] else (
                     "a demonstration that makes the decks complete and runnable, not a model of the specimen: "
                     "full-integration C3D8 with K0 = 1000 G0 on this coarse brick over-predicts the force "
                     "(measured in CalculiX on the twin: 1.7x at 0.5 mm and 1.4x at 4.75 mm depth for the "
                     "default 400-element brick against a 2048-element one); give the specimen's mesh in 'mesh'")},
        "deck": {"units": u.name, "step_time_s": step_s, "max_increment_s": dt_s,
                 "max_increment_mm": cfg.deck.max_increment_mm,
                 "analysis": "*STEP, NLGEOM; " + ("*VISCO, CETOL=%g" % VISCO_CETOL if h.prony else "*STATIC"),
                 "indentor": "nodes of INDENTOR prescribed u = depth(t) x axis (bonded flat punch)",
                 "dat_output": "U of INDENTOR and of MARKERS (the nodes of the elements holding the markers, what "
                               "compare interpolates), total RF of INDENTOR, every increment; U and RF of every "
                               "node in the .frd",
                 "markers_in_mesh": h.markers_in_mesh, "markers_outside_mesh": h.markers_outside_mesh,
                 "n_marker_nodes": int(len(h.marker_nodes)),
                 "fe_time_zero_xray_s": h.window.time_s + h.clock_offset_s},
        "checks": h.checks,
        "warnings": h.warnings,
        "inputs": sources,
    }
