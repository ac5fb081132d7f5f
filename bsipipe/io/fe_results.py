"""FE meshes and nodal displacement results, as ``bsipipe compare`` reads them.

Meshes
    ABAQUS / CalculiX input (``.inp``): ``*NODE`` (and ``*NGEN``) and ``*ELEMENT, TYPE=C3D4 |
    C3D10 | C3D6 | C3D15 | C3D8 | C3D20`` (and their variants: ``C3D8R``, ``C3D10M``, ...),
    ``*INCLUDE`` followed, keyword lines continued after a comma; other element types
    (springs, shells, ...) are counted and skipped; keywords that generate nodes or elements
    otherwise (``*NFILL``, ``*ELGEN``, ...) are refused.  Any other format through meshio
    (``tetra``, ``tetra10``, ``wedge``, ``wedge15``, ``hexahedron``, ``hexahedron20`` cells);
    its nodes are numbered 1..n in file order.
Displacements
    - CSV ``node,ux_mm,uy_mm,uz_mm`` (an optional ``time_s`` or ``step`` column holds several
      results; the last is taken unless one is chosen);
    - an ABAQUS report file (``.rpt``, Report > Field Output, ``U.U1 U.U2 U.U3`` at nodes,
      one or more frames);
    - a CalculiX ``.dat`` file (``*NODE PRINT`` of ``U``) or ``.frd`` file (``*NODE FILE`` of
      ``U``, ASCII), one or more increments;
    - any file meshio reads whose point data holds ``U``/``displacement`` (matched to the
      mesh's nodes by position, since such files carry no node labels the .inp would share).

Lengths are in the files' unit, mm unless ``length_unit="m"`` is given (then converted).
Errors name the file and, where it applies, the line.
"""

from __future__ import annotations

import csv
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

log = logging.getLogger(__name__)

__all__ = ["CellBlock", "FEMesh", "NodalDisplacements", "read_mesh", "read_abaqus_mesh",
           "read_displacements", "read_displacement_csv", "read_abaqus_report", "read_ccx_dat",
           "read_frd", "read_meshio_displacements", "displacements_on_mesh", "LENGTH_UNITS"]

#: Length unit -> factor to mm.
LENGTH_UNITS = {"mm": 1.0, "m": 1000.0}


@dataclass
class CellBlock:
    """Elements of one type: ``element_type`` (C3D4, C3D10, C3D6, C3D15, C3D8, C3D20), ``type_as_written``,
    ``element_ids`` (ne,), ``connectivity`` (ne, n): 0-based indices into the mesh's nodes."""

    element_type: str
    type_as_written: str
    element_ids: np.ndarray
    connectivity: np.ndarray


@dataclass
class FEMesh:
    """Nodes (``node_ids`` (n,), ``coords_mm`` (n, 3)) and solid element blocks."""

    path: str
    format: str
    node_ids: np.ndarray
    coords_mm: np.ndarray
    blocks: list[CellBlock]
    skipped: dict[str, int] = field(default_factory=dict)

    @property
    def n_elements(self) -> int:
        return int(sum(len(b.element_ids) for b in self.blocks))

    def element_types(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for b in self.blocks:
            out[b.type_as_written] = out.get(b.type_as_written, 0) + len(b.element_ids)
        return out

    def locator(self):
        from ..geometry.shape_functions import PointLocator
        return PointLocator(self.coords_mm, [(b.element_type, b.connectivity) for b in self.blocks])


@dataclass
class NodalDisplacements:
    """Nodal displacements of one result (step/frame/increment) of an FE run.

    ``node_ids`` (n,) labels (None for meshio files, which are matched by ``coords_mm``),
    ``u_mm`` (n, 3), ``coords_mm`` (n, 3) or None, ``step`` (a description of the chosen
    result), ``time`` (its step time, None where the file has none), ``n_results`` (results
    in the file), ``results`` (their descriptions, in file order).
    """

    path: str
    format: str
    node_ids: np.ndarray | None
    u_mm: np.ndarray
    coords_mm: np.ndarray | None = None
    step: str | None = None
    time: float | None = None
    n_results: int = 1
    results: list[str] = field(default_factory=list)
    coords_resolution_mm: float = 0.0     # the spacing of ``coords_mm``'s stored numbers (float32 files)


def _unit_factor(length_unit: str) -> float:
    try:
        return LENGTH_UNITS[length_unit]
    except KeyError:
        raise InputError(f"unknown length unit {length_unit!r}; expected one of {sorted(LENGTH_UNITS)}") from None


def _read_lines(path) -> list[str]:
    try:
        # utf-8-sig: Excel's "CSV UTF-8" starts with a byte-order mark, which had made the
        # first column "\ufeffnode" ("missing column(s) node" under a header that shows it)
        return Path(path).read_text(encoding="utf-8-sig", errors="replace").splitlines()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except OSError as e:
        raise InputError(f"cannot read the file: {e}", path=path) from None


def _choose(results: list, choose: int | None, path, what: str):
    """The chosen result (default: the last); ``choose`` is 0-based, negative from the end."""
    if not results:
        raise InputError(f"no {what} in the file", path=path)
    if choose is None:
        return results[-1]
    try:
        return results[choose]
    except IndexError:
        raise InputError(f"result {choose} requested, the file holds {len(results)} ({what})",
                         path=path) from None


# --- ABAQUS input -------------------------------------------------------------------------------

#: ABAQUS keywords that generate nodes or elements compare does not generate.
_GENERATED = {"NFILL": "nodes", "NCOPY": "nodes", "NMAP": "node coordinates", "ELGEN": "elements",
              "ELCOPY": "elements"}

def _keyword(line: str) -> tuple[str, dict[str, str]]:
    parts = [p.strip() for p in line[1:].split(",")]
    params = {}
    for p in parts[1:]:
        if not p:
            continue
        k, _, v = p.partition("=")
        params[k.strip().upper()] = v.strip()
    return parts[0].upper(), params


def element_line_continues(line: str, values) -> bool:
    """Whether an ``*ELEMENT`` data line goes on on the next: it ends in a comma, or it is full
    (16 entries, ABAQUS's maximum)."""
    return line.rstrip().endswith(",") or len(values) >= 16


def _inp_lines(path, seen=None):
    """(path, line number, text) of an ABAQUS input file with ``*INCLUDE`` expanded."""
    path = Path(path)
    seen = set() if seen is None else seen
    key = path.resolve()
    if key in seen:
        raise InputError("*INCLUDE loop", path=path)
    seen = seen | {key}
    lines = _read_lines(path)
    i = 0
    while i < len(lines):
        no, raw = i + 1, lines[i]
        i += 1
        s = raw.strip()
        if s.startswith("*") and not s.startswith("**"):
            # a keyword line ending in a comma continues on the next line (ABAQUS's rule):
            # "*ELEMENT, TYPE=C3D8," then "ELSET=E" had been read as a node line
            while s.endswith(",") and i < len(lines):
                nxt = lines[i].strip()
                i += 1
                if not nxt or nxt.startswith("**"):
                    continue
                s = s + " " + nxt
            raw = s
            kw, params = _keyword(s)
            if kw == "INCLUDE":
                inc = params.get("INPUT")
                if not inc:
                    raise InputError("*INCLUDE without INPUT=", path=path, line=no)
                inc_path = (path.parent / inc.strip('"')) if not os.path.isabs(inc) else Path(inc)
                if not inc_path.exists():
                    raise InputError(f"included file {inc} not found", path=path, line=no)
                yield from _inp_lines(inc_path, seen)
                continue
        yield path, no, raw


def read_abaqus_mesh(path, *, length_unit: str = "mm") -> FEMesh:
    """Nodes and solid elements of an ABAQUS/CalculiX input deck (see the module docstring)."""
    from ..geometry.shape_functions import element_type

    factor = _unit_factor(length_unit)
    ids: list[int] = []
    xyz: list[list[float]] = []
    where_node: dict[int, tuple] = {}
    elements: dict[str, tuple[list, list, str]] = {}   # base type -> (ids, conn labels, written)
    where_elem: dict[int, tuple] = {}
    skipped: dict[str, int] = {}
    mode = None            # "node", "element" or None
    etype = None           # ElementType or None (skipped type)
    written = ""
    pending: list[str] = []
    pending_at = None
    part = None                 # the *PART being read (its nodes are placed by its instance)
    node_part: list = []        # each node's part (None outside parts)
    instances: dict = {}        # part -> [(instance name, data lines, (file, line))]
    inst = None                 # the *INSTANCE being read: its positioning lines
    assembly_nodes: list = []   # nodes of the assembly (after an *INSTANCE, outside parts): left out

    def flush_element():
        nonlocal pending, pending_at
        if not pending:
            return
        f, no = pending_at
        try:
            vals = [int(v) for v in pending]
        except ValueError:
            raise InputError(f"element data must be integers: {','.join(pending)}", path=f, line=no) from None
        if len(vals) != etype.n_nodes + 1:
            raise InputError(f"a {written} element needs {etype.n_nodes} nodes, got {len(vals) - 1}",
                             path=f, line=no)
        if vals[0] in where_elem:
            raise InputError(f"element {vals[0]} defined twice (also {where_elem[vals[0]][0]} line "
                             f"{where_elem[vals[0]][1]})", path=f, line=no)
        where_elem[vals[0]] = (f, no)
        store = elements.setdefault(etype.name, ([], [], set()))
        store[0].append(vals[0])
        store[1].append(vals[1:])
        store[2].add(written)
        pending, pending_at = [], None

    for f, no, raw in _inp_lines(path):
        s = raw.strip()
        if not s or s.startswith("**"):
            continue
        if s.startswith("*"):
            if mode == "element" and etype is not None and pending:
                flush_element()
            pending, pending_at = [], None
            kw, params = _keyword(s)
            mode, etype = None, None
            if kw == "PART":
                part = params.get("NAME", "")
            elif kw == "END PART":
                part = None
            elif kw == "INSTANCE":
                inst = (params.get("NAME", ""), [], (f, no))
                instances.setdefault(params.get("PART", "").upper(), []).append(inst)
                mode = "instance"
                continue
            elif kw == "END INSTANCE":
                inst = None
            if kw in _GENERATED:
                # nodes or elements the solver generates: had been skipped unsaid, every marker
                # then "outside the mesh"
                raise InputError(f"*{kw} generates {_GENERATED[kw]}, which compare does not do: write them out "
                                 "(Abaqus/CAE and most preprocessors do; in Abaqus, the .inp of a datacheck run)",
                                 path=f, line=no)
            if kw == "NGEN":
                if params.get("LINE", "L").upper() not in ("L", ""):
                    raise InputError(f"*NGEN, LINE={params['LINE']} is not supported (straight lines only)",
                                     path=f, line=no)
                mode = "ngen"
                continue
            if kw == "NODE":
                if params.get("SYSTEM", "R").upper() not in ("R", ""):
                    raise InputError(f"*NODE, SYSTEM={params['SYSTEM']} is not supported (rectangular only)",
                                     path=f, line=no)
                mode = "node"
            elif kw == "ELEMENT":
                written = params.get("TYPE", "").upper()
                if not written:
                    raise InputError("*ELEMENT without TYPE=", path=f, line=no)
                mode = "element"
                try:
                    etype = element_type(written)
                except KeyError:
                    etype = None
                    skipped.setdefault(written, 0)
            continue
        if mode == "ngen":
            try:
                a, b, *inc = [int(v) for v in s.split(",") if v.strip() != ""][:3]
            except ValueError:
                raise InputError(f"an *NGEN line needs 'first, last[, increment]', got {s!r}", path=f, line=no) from None
            step = inc[0] if inc and inc[0] else 1
            for end in (a, b):
                if end not in where_node:
                    raise InputError(f"*NGEN from node {a} to {b}: node {end} is not defined before", path=f, line=no)
            if step <= 0 or (b - a) % step:
                raise InputError(f"*NGEN from node {a} to {b} by {step}: not a whole number of steps", path=f, line=no)
            pa, pb = np.array(xyz[ids.index(a)]), np.array(xyz[ids.index(b)])
            n = (b - a) // step
            for k in range(1, n):
                nid = a + k * step
                if nid in where_node:
                    raise InputError(f"node {nid} defined twice (also {where_node[nid][0]} line "
                                     f"{where_node[nid][1]}), here by *NGEN", path=f, line=no)
                where_node[nid] = (f, no)
                ids.append(nid)
                xyz.append(list(pa + (pb - pa) * k / n))
                node_part.append(part)
            continue
        if mode == "node":
            parts = [p for p in (v.strip() for v in s.split(",")) if p != ""]
            try:
                nid = int(parts[0])
                c = [float(v) for v in parts[1:4]]
            except (ValueError, IndexError):
                raise InputError(f"a node line needs 'id, x, y[, z]', got {s!r}", path=f, line=no) from None
            if len(c) < 2:
                raise InputError(f"a node line needs 'id, x, y[, z]', got {s!r}", path=f, line=no)
            if part is None and instances:
                # a node of the assembly (Abaqus/CAE writes a rigid indentor's reference point
                # there): its own namespace, no solid element's; it had clashed with a part's
                # node of the same label ("node 1 defined twice")
                assembly_nodes.append(nid)
                continue
            if nid in where_node:
                raise InputError(f"node {nid} defined twice (also {where_node[nid][0]} line {where_node[nid][1]}); "
                                 f"several parts or instances are not supported", path=f, line=no)
            where_node[nid] = (f, no)
            ids.append(nid)
            xyz.append((c + [0.0, 0.0])[:3])
            node_part.append(part)
        elif mode == "instance":
            inst[1].append((s, f, no))
        elif mode == "element":
            vals = [v for v in (v.strip() for v in s.split(",")) if v != ""]
            cont = element_line_continues(s, vals)
            if etype is None:
                if not pending:
                    skipped[written] = skipped.get(written, 0) + 1
                pending = ["..."] if cont else []
                continue
            if not pending:
                pending_at = (f, no)
            pending.extend(vals)
            if len(pending) >= etype.n_nodes + 1 or not cont:
                flush_element()
    if mode == "element" and etype is not None and pending:
        flush_element()
    if not ids:
        raise InputError("no *NODE data in the deck", path=path)
    if assembly_nodes:
        log.info("%s: %d node(s) of the assembly (reference points) left out: %s", path, len(assembly_nodes),
                 ", ".join(str(n) for n in assembly_nodes[:5]))
    xyz = _instances_placed(np.array(xyz, dtype=float), node_part, instances, path)
    node_ids = np.array(ids, dtype=np.int64)
    order = {n: i for i, n in enumerate(ids)}
    blocks = []
    for base, (eids, conn, wr) in elements.items():
        idx = np.empty((len(conn), len(conn[0])), dtype=np.int64)
        for r, (e, row) in enumerate(zip(eids, conn)):
            for c, nid in enumerate(row):
                if nid not in order:
                    fpath, no = where_elem[e]
                    raise InputError(f"element {e} uses node {nid}, which no *NODE defines", path=fpath, line=no)
                idx[r, c] = order[nid]
        blocks.append(CellBlock(base, "/".join(sorted(wr)), np.array(eids, dtype=np.int64), idx))
    if not blocks:
        raise InputError("no solid elements (C3D4, C3D10, C3D6, C3D15, C3D8, C3D20) in the deck"
                         + (f"; found {', '.join(sorted(skipped))}" if skipped else ""), path=path)
    return FEMesh(str(path), "abaqus", node_ids, xyz * factor, blocks, skipped)


def _instances_placed(xyz: np.ndarray, node_part: list, instances: dict, path) -> np.ndarray:
    """The nodes of each ``*PART`` where its ``*INSTANCE`` puts them in the assembly (an
    Abaqus/CAE input file): the first data line a translation, the optional second a rotation
    by an angle (degrees, right-handed) about the axis from point a to point b, applied after
    the translation (Abaqus Keywords Reference, ``*INSTANCE``).  A part instanced more than
    once has two places for one node label: an InputError."""
    parts = {p for p in node_part if p is not None}
    if not parts:
        return xyz
    from scipy.spatial.transform import Rotation
    out = xyz.copy()
    owner = np.array([p if p is not None else "" for p in node_part], dtype=object)
    for p in parts:
        inst = instances.get(p.upper(), [])
        if len(inst) > 1:
            raise InputError(f"part {p} is instanced {len(inst)} times ({', '.join(i[0] for i in inst)}): its node "
                             "labels would stand for several places; give compare one instance per part",
                             path=inst[1][2][0], line=inst[1][2][1])
        if not inst:
            continue
        sel = owner == p
        lines = inst[0][1]
        for k, (text, f, no) in enumerate(lines[:2]):
            try:
                v = [float(x) for x in text.split(",") if x.strip() != ""]
            except ValueError:
                raise InputError(f"an *INSTANCE line needs numbers, got {text!r}", path=f, line=no) from None
            if k == 0:
                if len(v) != 3:
                    raise InputError(f"an *INSTANCE translation needs 3 numbers, got {len(v)}", path=f, line=no)
                out[sel] += np.array(v)
            else:
                if len(v) != 7:
                    raise InputError(f"an *INSTANCE rotation needs 7 numbers (point a, point b, angle), got {len(v)}",
                                     path=f, line=no)
                a, b = np.array(v[:3]), np.array(v[3:6])
                axis = b - a
                if not np.linalg.norm(axis) > 0:
                    raise InputError("an *INSTANCE rotation axis from a point to itself", path=f, line=no)
                R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(v[6])).as_matrix()
                out[sel] = a + (out[sel] - a) @ R.T
    return out


def _read_meshio(path):
    import meshio
    try:
        return meshio.read(str(path))
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except Exception as e:   # meshio raises many kinds of errors for unreadable files
        raise InputError(f"meshio cannot read the file: {type(e).__name__}: {e}", path=path) from None
    except SystemExit as e:  # and some of its readers call sys.exit (a cut VTU: exit 1, "Couldn't read file")
        raise InputError(f"meshio cannot read the file (damaged, cut off, or not the format its suffix says)"
                         + (f": {e.code}" if isinstance(e.code, str) else ""), path=path) from None


def read_mesh(path, *, length_unit: str = "mm") -> FEMesh:
    """A mesh from an ABAQUS ``.inp`` or any format meshio reads."""
    if str(path).lower().endswith(".inp"):
        return read_abaqus_mesh(path, length_unit=length_unit)
    from ..geometry.shape_functions import MESHIO_TO_ABAQUS

    m = _read_meshio(path)
    pts = np.asarray(m.points, dtype=float)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    blocks, skipped = [], {}
    next_id = 1
    for cb in m.cells:
        if cb.type in MESHIO_TO_ABAQUS:
            conn = np.asarray(cb.data, dtype=np.int64)
            blocks.append(CellBlock(MESHIO_TO_ABAQUS[cb.type], cb.type,
                                    np.arange(next_id, next_id + len(conn)), conn))
        else:
            skipped[cb.type] = skipped.get(cb.type, 0) + len(cb.data)
        next_id += len(cb.data)
    if not blocks:
        raise InputError("no solid cells (tetra, tetra10, wedge, wedge15, hexahedron, hexahedron20) in the mesh"
                         + (f"; found {', '.join(sorted(skipped))}" if skipped else ""), path=path)
    return FEMesh(str(path), "meshio", np.arange(1, len(pts) + 1), pts * _unit_factor(length_unit),
                  blocks, skipped)


# --- displacement results -----------------------------------------------------------------------

def read_displacement_csv(path, *, choose: int | None = None, length_unit: str = "mm") -> NodalDisplacements:
    """CSV ``node,ux_mm,uy_mm,uz_mm`` (``ux_m``, ... with ``length_unit='m'``), optional ``time_s``/``step``."""
    import pandas as pd

    lines = _read_lines(path)
    body = [(i + 1, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise InputError("empty file; expected a header node,ux_mm,uy_mm,uz_mm", path=path, line=1)
    head_line, head = body[0]
    cols = [c.strip().lower() for c in next(csv.reader([head]))]
    _unit_factor(length_unit)
    unit = length_unit
    want = ["node"] + [f"u{a}_{unit}" for a in "xyz"]
    missing = [c for c in want if c not in cols]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}; expected {','.join(want)}",
                         path=path, line=head_line)
    rows = list(csv.reader([ln for _, ln in body[1:]]))
    linenos = [no for no, _ in body[1:]]
    sel = "time_s" if "time_s" in cols else ("step" if "step" in cols else None)
    data = {c: [] for c in want + ([sel] if sel else [])}
    for no, r in zip(linenos, rows):
        if len(r) < len(cols):
            raise InputError(f"{len(r)} fields, expected {len(cols)}", path=path, line=no)
        for c in data:
            v = r[cols.index(c)].strip()
            try:
                data[c].append(_label(v) if c == "node" else float(v))
            except ValueError:
                what = "a node label (a whole number)" if c == "node" else "a number"
                raise InputError(f"{c} is not {what}: {v!r}", path=path, line=no) from None
    df = pd.DataFrame(data)
    if df.empty:
        raise InputError("no data rows", path=path)
    factor = _unit_factor(length_unit)
    groups = [(None, df)] if sel is None else list(df.groupby(sel, sort=False))
    labels = [f"{sel} = {k:g}" if sel else "single result" for k, _ in groups]

    def build(k: int) -> NodalDisplacements:
        key, g = groups[k]
        if g["node"].duplicated().any():
            dup = int(g["node"][g["node"].duplicated()].iloc[0])
            raise InputError(f"node {dup} appears twice in one result", path=path)
        u = g[[f"u{a}_{unit}" for a in "xyz"]].to_numpy(float) * factor
        return NodalDisplacements(str(path), "csv", g["node"].to_numpy(np.int64), u, None, labels[k],
                                  None if sel != "time_s" else float(key), len(groups), labels)

    if choose == "all":
        return [build(k) for k in range(len(groups))]
    return build(_choose(list(range(len(groups))), choose, path, "results"))


def _label(v: str) -> int:
    """A node label as a spreadsheet or pandas may write it: ``601`` or ``601.0``."""
    try:
        return int(v)
    except ValueError:
        f = float(v)
        if not f.is_integer():
            raise
        return int(f)


_RPT_FRAME = re.compile(r"Step Time\s*=\s*(\S+)")


def _rpt_parts_merged(tables: list[tuple], path) -> list[tuple]:
    """One result per frame from a report's tables ``(desc, time, ids, values, part, line)``:
    Abaqus/CAE reports a model of several part instances as one table per instance and frame
    ("Field Output reported at nodes for part: BRAIN-1", then INDENTOR-1, ...).  Tables of one
    frame are merged where their node labels are distinct (one label space); where they
    overlap (each instance numbering its own nodes from 1) the labels cannot be told apart and
    the report is refused: report the brain's instance alone."""
    out: list[tuple] = []
    k = 0
    while k < len(tables):
        j = k + 1
        while j < len(tables) and tables[j][0] == tables[k][0] and tables[j][4] != tables[k][4]:
            j += 1
        group = tables[k:j]
        if len(group) > 1:
            ids = np.concatenate([g[2] for g in group])
            if len(np.unique(ids)) != len(ids):
                names = ", ".join(str(g[4]) for g in group)
                raise InputError(f"{group[0][0]} is reported as one table per part instance ({names}), whose node "
                                 "labels overlap (each instance numbers its own nodes): report the brain's instance "
                                 "alone (Report > Field Output, Setup: the instance's nodes), the one the mesh given "
                                 "to compare describes", path=path, line=group[0][5])
            out.append((group[0][0], group[0][1], ids, np.vstack([g[3] for g in group])))
        else:
            out.append(group[0][:4])
        k = j
    return out


def read_abaqus_report(path, *, choose: int | None = None, length_unit: str = "mm") -> NodalDisplacements:
    """An ABAQUS field-output report (``.rpt``) with ``U.U1 U.U2 U.U3`` at nodes.

    The layout (Abaqus/CAE, Report > Field Output, position Unique Nodal)::

        Source 1
        ---------
           ODB: job.odb
           Step: Step-1
           Frame: Increment      6: Step Time =    1.000
        ...
                    Node            U.U1            U.U2            U.U3
                   Label          @Loc 1          @Loc 1          @Loc 1
        -----------------------------------------------------------------
                     601    -2.68589E-03    -746.369E-06    -49.4577E-03

    Every table with the three components is one result (frames in file order; the last is
    taken unless ``choose`` says otherwise).  Rows may carry instance-qualified labels
    (``PART-1-1.601``); the summary rows (Minimum, Maximum, Total, At Node) are ignored.
    """
    lines = _read_lines(path)
    results = []
    endings: list[bool] = []           # each table ended by a blank line or summary rows
    step = frame = part = None
    i = 0
    while i < len(lines):
        s = lines[i].strip()
        if s.startswith("Step:"):
            step = s.split(":", 1)[1].strip()
        elif s.startswith("Frame:"):
            frame = s.split(":", 1)[1].strip()
            part = None
        elif s.lower().startswith("field output reported at nodes for part:"):
            part = s.split(":", 1)[1].strip()
        toks = s.split()
        if toks and toks[0] == "Node" and any(t.startswith("U.U") for t in toks):
            names = toks[2:] if len(toks) > 1 and toks[1] == "Label" else toks[1:]
            head_no = i + 1
            i += 1
            while i < len(lines) and not (lines[i].strip() and set(lines[i].strip()) <= {"-"}):
                i += 1            # the "Label @Loc 1" line(s) up to the dashes
            i += 1
            comps = []
            for c in ("U.U1", "U.U2", "U.U3"):
                if c not in names:
                    raise InputError(f"the table has no {c} column (columns: {' '.join(names)}); "
                                     f"report U at nodes for a 3-D model", path=path, line=head_no)
                comps.append(names.index(c))
            ids, vals, inst = [], [], set()
            ended = False                     # by a blank line or the summary rows, not the file's end
            while i < len(lines):
                row = lines[i].split()
                if not row:
                    if ids:
                        ended = True
                        break
                    i += 1
                    continue
                if row[0] in ("Minimum", "Maximum", "Total", "At"):
                    ended = True
                    break
                label = row[0]
                if "." in label:
                    pre, _, label = label.rpartition(".")
                    inst.add(pre)
                try:
                    nid = int(label)
                    v = [float(row[1 + c]) for c in comps]
                except (ValueError, IndexError):
                    raise InputError(f"expected a node label and {len(names)} numbers, got {lines[i].strip()!r}",
                                     path=path, line=i + 1) from None
                ids.append(nid)
                vals.append(v)
                i += 1
            if len(inst) > 1:
                raise InputError(f"labels from several instances ({', '.join(sorted(inst))}); report one "
                                 f"instance (compare supports one part)", path=path, line=head_no)
            m = _RPT_FRAME.search(frame or "")
            t = None
            if m:
                try:
                    t = float(m.group(1))
                except ValueError:
                    t = None
            desc = f"step {step}, frame {frame}" if step or frame else f"table at line {head_no}"
            results.append((desc, t, np.array(ids, dtype=np.int64), np.array(vals, dtype=float), part, head_no))
            endings.append(ended)
            continue
        i += 1
    if results and not endings[-1]:
        # the file ends inside its last table: cut off where the other tables end properly or
        # hold more rows for the same part (a table cut at 30 % had given 1 marker of 8, exit 0)
        last = results[-1]
        same = [len(r[2]) for r in results[:-1] if r[4] == last[4]]
        if any(endings[:-1]) or (same and len(last[2]) < max(same)):
            more = f", the part's earlier tables {max(same)}" if same else ""
            raise InputError(f"the report ends inside its last table ({last[0]}: {len(last[2])} rows{more}), "
                             "without the blank line and summary rows the others end with: the file was cut off "
                             "(a report written while the job ran, or a copy cut short)", path=path,
                             line=len(lines))
    results = _rpt_parts_merged(results, path)

    def build(r) -> NodalDisplacements:
        desc, t, ids, u = r
        if len(np.unique(ids)) != len(ids):
            raise InputError(f"node labels repeat in the table ({desc}); report unique nodal values", path=path)
        return NodalDisplacements(str(path), "abaqus-rpt", ids, u * _unit_factor(length_unit), None, desc, t,
                                  len(results), [r[0] for r in results])

    what = "U.U1 U.U2 U.U3 tables"
    if choose == "all":
        _choose(results, None, path, what)            # none at all: the error
        return [build(r) for r in results]
    return build(_choose(results, choose, path, what))


def read_ccx_dat(path, *, choose: int | None = None, length_unit: str = "mm") -> NodalDisplacements:
    """CalculiX ``.dat``: ``displacements (vx,vy,vz) for set S and time t`` blocks (``*NODE PRINT`` U).

    Blocks of one time (several node sets) are merged; times in file order, the last taken
    unless ``choose`` says otherwise.
    """
    from ..fe._calculix import parse_dat

    text = "\n".join(_read_lines(path))
    try:
        blocks = [b for b in parse_dat(text) if b.title.startswith("displacements")]
    except ValueError as e:
        raise InputError(f"cannot parse the .dat file: {e}", path=path) from None
    times: list[float] = []
    for b in blocks:
        if b.time not in times:
            times.append(b.time)
    # a file cut off (a run stopped while writing, a copy cut short) ends with a partial block:
    # fewer nodes than the same set's block at every earlier time
    if blocks:
        last = blocks[-1]
        before = [len(b.ids) for b in blocks[:-1] if b.set_name == last.set_name]
        if before and len(last.ids) < min(before):
            raise InputError(f"the last displacement block (set {last.set_name}, time {last.time:g}) holds "
                             f"{len(last.ids)} nodes, the set's earlier ones {min(before)}: the file was cut off "
                             "(a run stopped while writing, or a copy cut short)", path=path)
        # cut at a block's edge: the last time lacks a set every earlier time printed (it had
        # read as a result of another mesh, "933 of the mesh's 942 nodes have no displacement")
        sets_at = {t: {b.set_name for b in blocks if b.time == t} for t in times}
        if len(times) > 1:
            every = set.intersection(*(sets_at[t] for t in times[:-1]))
            gone = sorted(every - sets_at[times[-1]])
            if gone:
                raise InputError(f"the last time ({times[-1]:g}) has no displacement block for set(s) "
                                 f"{', '.join(gone)}, which every earlier time has: the file was cut off (a run "
                                 "stopped while writing, or a copy cut short)", path=path)

    def build(t: float) -> NodalDisplacements:
        merged: dict[int, np.ndarray] = {}
        for b in blocks:
            if b.time != t:
                continue
            if b.values.shape[1] < 3:
                raise InputError(f"a displacement block of set {b.set_name} has {b.values.shape[1]} columns",
                                 path=path)
            for nid, v in zip(b.ids, b.values[:, :3]):
                merged[int(nid)] = v
        ids = np.array(sorted(merged), dtype=np.int64)
        u = np.array([merged[n] for n in ids], dtype=float)
        return NodalDisplacements(str(path), "calculix-dat", ids, u * _unit_factor(length_unit), None,
                                  f"time {t:g}", float(t), len(times), [f"time {x:g}" for x in times])

    what = "displacement blocks (*NODE PRINT ... U)"
    if choose == "all":
        _choose(times, None, path, what)              # none at all: the error
        return [build(t) for t in times]
    return build(_choose(times, choose, path, what))


def _frd_values(line: str, start: int, n: int) -> list[float]:
    return [float(line[start + 12 * k: start + 12 * (k + 1)]) for k in range(n)]


def _frd_block_end(lines: list[str], i: int, head_no: int, what: str, path) -> None:
    """A block of an ``.frd`` ends with a `` -3`` record: a file that ends first was cut off
    (a run stopped while writing, a copy cut short) and its last result is partial."""
    if i >= len(lines):
        raise InputError(f"the file ends inside the {what} block that starts at line {head_no} (no -3 record): "
                         "a run cut short or a file cut off; its last result would be partial", path=path,
                         line=head_no)


def read_frd(path, *, choose: int | None = None, length_unit: str = "mm") -> NodalDisplacements:
    """CalculiX ASCII ``.frd``: node coordinates (block ``2C``) and ``DISP`` result blocks (``100C``).

    Fixed-width records: `` -1`` + node number (I10 long format, I5 short) + values (E12.5).
    """
    lines = _read_lines(path)
    coords: dict[int, list[float]] = {}
    results = []
    i = 0
    while i < len(lines):
        ln = lines[i]
        s = ln.strip()
        if s.startswith("2C"):
            fmt = int(s.split()[-1]) if s.split()[-1].isdigit() else 1
            if fmt not in (0, 1):
                raise InputError("a binary .frd file; write it in ASCII (CalculiX's default)", path=path, line=i + 1)
            w = 10 if fmt == 1 else 5
            head_no = i + 1
            i += 1
            while i < len(lines) and not lines[i].startswith(" -3"):
                r = lines[i]
                if r.startswith(" -1"):
                    try:
                        coords[int(r[3:3 + w])] = _frd_values(r, 3 + w, 3)
                    except ValueError:
                        raise InputError("bad node record", path=path, line=i + 1) from None
                i += 1
            _frd_block_end(lines, i, head_no, "node", path)
        elif s.startswith("100C"):
            head_no = i + 1
            try:
                t = float(ln[12:24])
            except ValueError:
                t = float("nan")
            toks = s.split()
            fmt = int(toks[-1]) if toks[-1].isdigit() else 1
            w = 10 if fmt == 1 else 5
            i += 1
            name = lines[i][5:13].strip() if i < len(lines) and lines[i].startswith(" -4") else ""
            ids, vals = [], []
            while i < len(lines) and not lines[i].startswith(" -3"):
                r = lines[i]
                if r.startswith(" -1") and name == "DISP":
                    try:
                        ids.append(int(r[3:3 + w]))
                        vals.append(_frd_values(r, 3 + w, 3))
                    except ValueError:
                        raise InputError("bad DISP record", path=path, line=i + 1) from None
                i += 1
            _frd_block_end(lines, i, head_no, name or "result", path)
            if name == "DISP":
                try:
                    stated = int(ln[24:36])
                except ValueError:
                    stated = None
                if stated is not None and stated != len(ids):
                    raise InputError(f"the DISP block holds {len(ids)} nodes, its header says {stated}: the file was "
                                     "cut off or edited", path=path, line=head_no)
                results.append((f"DISP at time {t:g} (line {head_no})", t, np.array(ids, dtype=np.int64),
                                np.array(vals, dtype=float)))
        i += 1
    f = _unit_factor(length_unit)

    def build(r) -> NodalDisplacements:
        desc, t, ids, u = r
        xyz = np.array([coords.get(int(n), [np.nan] * 3) for n in ids], dtype=float) * f if coords else None
        return NodalDisplacements(str(path), "calculix-frd", ids, u * f, xyz, desc, t, len(results),
                                  [r[0] for r in results])

    what = "DISP blocks (*NODE FILE ... U)"
    if choose == "all":
        _choose(results, None, path, what)            # none at all: the error
        return [build(r) for r in results]
    return build(_choose(results, choose, path, what))


_MESHIO_KEYS = ("u", "displacement", "displacements", "disp", "displacement_mm")


def read_meshio_displacements(path, *, length_unit: str = "mm") -> NodalDisplacements:
    """Point data ``U`` (or ``displacement``, ...) of a file meshio reads, with the point coordinates."""
    m = _read_meshio(path)
    for k, v in m.point_data.items():
        if k.lower() in _MESHIO_KEYS:
            v = np.asarray(v, dtype=float)
            if v.ndim == 2 and v.shape[1] >= 2:
                if v.shape[1] == 2:
                    v = np.column_stack([v, np.zeros(len(v))])
                f = _unit_factor(length_unit)
                raw = np.asarray(m.points)
                pts = raw.astype(float)
                if pts.shape[1] == 2:
                    pts = np.column_stack([pts, np.zeros(len(pts))])
                # coordinates stored as float32 are rounded to 6e-8 of their size (3e-5 mm at
                # 850 mm, a CT frame's): matching them to the mesh must allow that
                eps = float(np.finfo(raw.dtype).eps) if np.issubdtype(raw.dtype, np.floating) else 0.0
                res = eps * float(np.abs(pts).max()) * f if len(pts) else 0.0
                return NodalDisplacements(str(path), "meshio", None, v[:, :3] * f, pts * f, f"point data {k!r}",
                                          coords_resolution_mm=res)
    raise InputError(f"no displacement point data (looked for {', '.join(_MESHIO_KEYS)}, any case); "
                     f"found: {', '.join(m.point_data) or 'none'}", path=path)


def read_displacements(path, *, choose: int | str | None = None, length_unit: str = "mm"):
    """Nodal displacements from any supported result file (by extension: .csv, .rpt, .dat, .frd, else meshio).
    ``choose``: a result's 0-based index (negative from the end; default the last), or ``"all"``
    for the list of every result, the file parsed once."""
    low = str(path).lower()
    if low.endswith(".csv"):
        return read_displacement_csv(path, choose=choose, length_unit=length_unit)
    if low.endswith(".rpt"):
        return read_abaqus_report(path, choose=choose, length_unit=length_unit)
    if low.endswith(".dat"):
        return read_ccx_dat(path, choose=choose, length_unit=length_unit)
    if low.endswith(".frd"):
        return read_frd(path, choose=choose, length_unit=length_unit)
    if choose == "all":
        return [read_meshio_displacements(path, length_unit=length_unit)]
    if choose is not None:
        raise InputError("this file holds one result; --fe-result does not apply", path=path)
    return read_meshio_displacements(path, length_unit=length_unit)


def displacements_on_mesh(mesh: FEMesh, disp: NodalDisplacements, *, match_tol_mm: float | None = None
                          ) -> tuple[np.ndarray, dict]:
    """Displacements (n_nodes, 3) in the mesh's node order, NaN where the result has none.

    Labels are matched where the result has them; a meshio result (no labels) is matched by
    node position within ``match_tol_mm`` (default 1e-6 of the mesh's bounding-box diagonal, or
    4 times the spacing of the result's stored coordinates where that is larger: float32).
    Returns ``(u, info)`` with ``info`` = ``{"matched_by", "n_matched", "n_unmatched_result_nodes"}``.
    """
    n = len(mesh.node_ids)
    u = np.full((n, 3), np.nan)
    if disp.node_ids is not None:
        pos = {int(k): i for i, k in enumerate(mesh.node_ids)}
        idx = np.array([pos.get(int(k), -1) for k in disp.node_ids], dtype=np.int64)
        ok = idx >= 0
        u[idx[ok]] = disp.u_mm[ok]
        return u, {"matched_by": "node label", "n_matched": int(ok.sum()),
                   "n_unmatched_result_nodes": int((~ok).sum())}
    from scipy.spatial import cKDTree

    diag = float(np.linalg.norm(np.ptp(mesh.coords_mm, axis=0)))
    tol = max(1e-6 * diag, 4.0 * disp.coords_resolution_mm) if match_tol_mm is None else match_tol_mm
    d, j = cKDTree(disp.coords_mm).query(mesh.coords_mm, distance_upper_bound=tol)
    ok = np.isfinite(d)
    u[ok] = disp.u_mm[j[ok]]
    return u, {"matched_by": f"node position (within {tol:.3g} mm)", "n_matched": int(ok.sum()),
               "n_unmatched_result_nodes": int(len(disp.u_mm) - len(np.unique(j[ok])))}
