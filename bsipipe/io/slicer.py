"""3D Slicer markups: point lists as ``.fcsv`` (Slicer 4.x/5.x) and ``.mrk.json`` (Slicer 5).

Writers return the file's text, so a command can hand it to its all-or-nothing
:class:`~bsipipe.provenance.ResultSet`. Coordinates are written as given, in the
coordinate system named (``LPS``, Slicer's file default since 4.11, or ``RAS``).

``.fcsv`` layout::

    # Markups fiducial file version = 4.11
    # CoordinateSystem = LPS
    # columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID
    vtkMRMLMarkupsFiducialNode_0,x,y,z,0,0,0,1,1,1,0,M1,,

``.mrk.json`` follows Slicer's markups schema v1.0.3 (one ``Fiducial`` markup with
``controlPoints``, each with ``label`` and ``position``).

Readers (:func:`read_markups` and the per-format functions below) take CT marker
coordinates from a ``.fcsv`` of any version, a ``.mrk.json`` or bsipipe's plain CSV
``marker,x_mm,y_mm,z_mm``, in the file's own coordinate system (:class:`MarkupPoints`;
:meth:`MarkupPoints.to` converts); a bad file is an :class:`~bsipipe.errors.InputError`
naming the file and line.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..errors import InputError

FCSV_VERSION = "4.11"
MRK_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
              "Schema/markups-schema-v1.0.3.json#")
_SYSTEMS = ("LPS", "RAS")


def _check(labels: Sequence[str], points_mm, coordinate_system: str) -> np.ndarray:
    if coordinate_system not in _SYSTEMS:
        raise InputError(f"coordinate system must be LPS or RAS, got {coordinate_system!r}")
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(p) != len(labels):
        raise InputError(f"{len(labels)} labels for {len(p)} points")
    for lab in labels:
        if any(c in str(lab) for c in ",\n\r"):
            raise InputError(f"a markup label cannot hold a comma or a line break: {lab!r}")
    if not np.all(np.isfinite(p)):
        raise InputError("markup coordinates must be finite")
    return p


def _num(v: float) -> str:
    return repr(float(v))  # shortest text that reads back to the same double


def format_fcsv(labels: Sequence[str], points_mm, coordinate_system: str = "LPS",
                descriptions: Iterable[str] | None = None) -> str:
    """A Slicer ``.fcsv`` point list.

    >>> print(format_fcsv(["R1"], [[1.5, -2.0, 30.25]]), end="")
    # Markups fiducial file version = 4.11
    # CoordinateSystem = LPS
    # columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID
    vtkMRMLMarkupsFiducialNode_0,1.5,-2.0,30.25,0,0,0,1,1,1,0,R1,,
    """
    p = _check(labels, points_mm, coordinate_system)
    desc = list(descriptions) if descriptions is not None else [""] * len(p)
    lines = [f"# Markups fiducial file version = {FCSV_VERSION}",
             f"# CoordinateSystem = {coordinate_system}",
             "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"]
    for i, (lab, xyz, d) in enumerate(zip(labels, p, desc)):
        d = str(d).replace(",", ";").replace("\n", " ")
        lines.append(f"vtkMRMLMarkupsFiducialNode_{i},{_num(xyz[0])},{_num(xyz[1])},{_num(xyz[2])},"
                     f"0,0,0,1,1,1,0,{lab},{d},")
    return "\n".join(lines) + "\n"


def format_mrk_json(labels: Sequence[str], points_mm, coordinate_system: str = "LPS",
                    descriptions: Iterable[str] | None = None, name: str = "markers") -> str:
    """A Slicer ``.mrk.json`` point list (markups schema v1.0.3)."""
    p = _check(labels, points_mm, coordinate_system)
    desc = list(descriptions) if descriptions is not None else [""] * len(p)
    cps = [{"id": str(i + 1), "label": str(lab), "description": str(d), "associatedNodeID": "",
            "position": [float(v) for v in xyz], "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
            "selected": True, "locked": False, "visibility": True, "positionStatus": "defined"}
           for i, (lab, xyz, d) in enumerate(zip(labels, p, desc))]
    doc = {"@schema": MRK_SCHEMA,
           "markups": [{"type": "Fiducial", "name": name, "coordinateSystem": coordinate_system,
                        "coordinateUnits": "mm", "locked": False, "fixedNumberOfControlPoints": False,
                        "labelFormat": "%N-%d", "lastUsedControlPointNumber": len(cps),
                        "controlPoints": cps, "measurements": []}]}
    return json.dumps(doc, indent=4) + "\n"


# --- readers (CT marker coordinates) ------------------------------------------------------------
#
# Read as 3D Slicer reads them (Modules/Loadable/Markups/MRML/vtkMRMLMarkupsFiducialStorageNode.cxx,
# vtkMRMLMarkupsJsonStorageNode.cxx):
#
# .fcsv   '#' lines hold "name = value" pairs: "Markups fiducial file version" (absent in Slicer 3
#         files), "CoordinateSystem" (RAS, LPS, or 0 = RAS / 1 = LPS in files before Slicer 4.11;
#         RAS when absent), "columns".  Data rows are CSV with Slicer's quoting (a field that
#         starts with '"' runs to the closing quote; '""' is a quote).  Versioned rows:
#         id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID[,positionStatus,autoCreated]
#         (Slicer 5.x appends the last two unlabelled fields; positionStatus 0 = undefined,
#         1 = preview, 2 = defined, 3 = missing).  Unversioned (Slicer 3) rows: label,x,y,z,sel,vis.
#         A "# columns" line naming label, x, y, z is honoured (other writers use other columns).
# .mrk.json  {"markups": [{"coordinateSystem": "LPS"|"RAS", "coordinateUnits": "mm"|"um",
#         "controlPoints": [{"label": .., "position": [x, y, z], "positionStatus": ..}, ..]}, ..]}
# .csv    marker,x_mm,y_mm,z_mm (bsipipe's plain table); an optional "# CoordinateSystem = LPS"
#         comment line before the header states the system.
#
# Coordinates are returned in the file's own system (never converted on reading);
# MarkupPoints.to(system) converts (LPS = RAS with x and y negated).


_SYSTEM_CODES = {"0": "RAS", "1": "LPS", "RAS": "RAS", "LPS": "LPS"}
_FCSV4_COLUMNS = ("id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc",
                  "associatedNodeID", "positionStatus", "autoCreated")
_SLICER3_COLUMNS = ("label", "x", "y", "z", "sel", "vis")
_POSITION_STATUS = {0: "undefined", 1: "preview", 2: "defined", 3: "missing"}


@dataclass
class MarkupPoints:
    """Named 3-D points read from a markups file, in the file's own coordinate system.

    ``names`` (n,), ``positions_mm`` (n, 3), ``lines`` (n,): the 1-based source line of each
    point (None where the format has no lines, e.g. a JSON file written on one line);
    ``coordinate_system``: ``"LPS"``, ``"RAS"`` or None (a plain CSV that does not say);
    ``skipped``: label -> why a point was not read (position undefined or missing).
    """

    path: str
    format: str
    names: list[str]
    positions_mm: np.ndarray
    coordinate_system: str | None
    version: str | None = None
    lines: list[int | None] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict[str, np.ndarray]:
        return {n: p for n, p in zip(self.names, self.positions_mm)}

    def to(self, system: str) -> "MarkupPoints":
        """The same points in ``system`` (``"LPS"`` or ``"RAS"``): x and y change sign between them."""
        system = system.upper()
        if system not in ("LPS", "RAS"):
            raise ValueError(f"unknown coordinate system {system!r}; expected LPS or RAS")
        if self.coordinate_system is None:
            raise ValueError(f"{self.path}: the file does not state its coordinate system")
        pos = self.positions_mm.copy()
        if system != self.coordinate_system:
            pos[:, :2] *= -1.0
        return replace(self, positions_mm=pos, coordinate_system=system)


def lps_ras(xyz) -> np.ndarray:
    """Convert between LPS and RAS (the map is its own inverse: x and y change sign).

    >>> lps_ras([[1.0, 2.0, 3.0]]).tolist()
    [[-1.0, -2.0, 3.0]]
    """
    out = np.array(xyz, dtype=float)
    out[..., :2] *= -1.0
    return out


def _split_slicer_csv(row: str) -> list[str]:
    """One row split as Slicer's CsvCodec does (quotes only open a field at its start)."""
    fields, cur, state = [], [], 0   # 0 unquoted, 1 quoted, 2 quote inside a quoted field
    for c in row:
        if state == 0:
            if c == ",":
                fields.append("".join(cur))
                cur = []
            elif c == '"' and not cur:
                state = 1
            else:
                cur.append(c)
        elif state == 1:
            if c == '"':
                state = 2
            else:
                cur.append(c)
        else:
            if c == ",":
                fields.append("".join(cur))
                cur = []
                state = 0
            elif c == '"':
                cur.append('"')
                state = 1
            else:
                cur.append(c)
                state = 0
    fields.append("".join(cur))
    return fields


def _read_text(path) -> str:
    """The file's text: UTF-8 (a byte-order mark dropped), else Latin-1 (Windows tools'
    files with a description in an accented word or a micro sign had been refused with a
    raw codec message)."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except OSError as e:
        raise InputError(f"cannot read the file: {e.strerror or e}", path=path) from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        if b"\x00" in data:
            raise InputError("not a text file (it holds NUL bytes): expected a Slicer markups or CSV file",
                             path=path) from None
        return data.decode("latin-1")


def _coordinate_system(value: str, path, line: int | None) -> str:
    v = value.strip().upper()
    if v not in _SYSTEM_CODES:
        raise InputError(f"unknown coordinate system {value.strip()!r}; expected LPS, RAS, 0 (RAS) or 1 (LPS)",
                         path=path, line=line)
    return _SYSTEM_CODES[v]


def _float(text: str, what: str, path, line: int | None) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"{what} is not a number: {text.strip()!r}", path=path, line=line) from None
    if not np.isfinite(v):
        raise InputError(f"{what} is not finite: {text.strip()!r}", path=path, line=line)
    return v


class _Points:
    """Collects points; a repeated label is an error naming both lines."""

    def __init__(self, path):
        self.path = path
        self.names: list[str] = []
        self.xyz: list[list[float]] = []
        self.lines: list[int | None] = []
        self.skipped: dict[str, str] = {}
        self._where: dict[str, int | None] = {}

    def add(self, label: str, xyz, line: int | None) -> None:
        label = label.strip()
        if not label:
            raise InputError("a point has an empty label; every marker needs a name", path=self.path, line=line)
        if label in self._where:
            prev = self._where[label]
            raise InputError(f"label {label!r} appears twice" + (f" (also line {prev})" if prev else ""),
                             path=self.path, line=line)
        self._where[label] = line
        self.names.append(label)
        self.xyz.append(list(xyz))
        self.lines.append(line)

    def skip(self, label: str, why: str, line: int | None) -> None:
        label = label.strip()
        if label in self._where:
            raise InputError(f"label {label!r} appears twice", path=self.path, line=line)
        self._where[label] = line
        self.skipped[label] = why

    def result(self, fmt, system, version) -> MarkupPoints:
        if not self.names:
            raise InputError("no point with a defined position in the file", path=self.path)
        return MarkupPoints(str(self.path), fmt, self.names, np.array(self.xyz, dtype=float).reshape(-1, 3),
                            system, version, self.lines, self.skipped)


def read_fcsv(path) -> MarkupPoints:
    """A 3D Slicer ``.fcsv`` markups file of any version (Slicer 3, 4.x, 5.x)."""
    text = _read_text(path)
    version = None
    system = None
    columns = None
    pts = _Points(path)
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.rstrip("\r\n")
        if not line.strip():
            continue
        if line.startswith("#"):
            body = line[1:]
            if "=" not in body:
                continue
            name, value = (s.strip() for s in body.split("=", 1))
            low = name.lower()
            if low == "markups fiducial file version":
                version = value
            elif low == "coordinatesystem":
                system = _coordinate_system(value, path, lineno)
            elif low == "columns":
                columns = [c.strip() for c in value.split(",")]
            continue
        fields = _split_slicer_csv(line)
        std = list(_FCSV4_COLUMNS)
        if columns and {"label", "x", "y", "z"} <= set(columns):
            # Slicer's own header lists 14 columns; 5.x rows carry two more unlabelled fields
            cols = std if len(columns) >= 14 and columns[:14] == std[:14] else columns
        else:
            cols = std if version is not None else list(_SLICER3_COLUMNS)
        where = {c: i for i, c in enumerate(cols)}
        need = max(where[c] for c in ("x", "y", "z", "label")) + 1   # up to the last field read
        if len(fields) < need:
            raise InputError(f"{len(fields)} fields, expected at least {need} ({','.join(cols[:need])})",
                             path=path, line=lineno)
        label = fields[where["label"]]
        status = where.get("positionStatus")
        if status is not None and status < len(fields) and fields[status].strip():
            try:
                code = int(fields[status])
            except ValueError:
                raise InputError(f"position status is not an integer: {fields[status]!r}",
                                 path=path, line=lineno) from None
            if code in (0, 3):
                pts.skip(label, f"position {_POSITION_STATUS[code]} (line {lineno})", lineno)
                continue
        xyz = [_float(fields[where[c]], c, path, lineno) for c in ("x", "y", "z")]
        pts.add(label, xyz, lineno)
    return pts.result("fcsv", system or "RAS", version)


def _json_line(text: str, needle: str, nth: int = 0) -> int | None:
    """1-based line of the ``nth`` occurrence (0: the first) of ``needle`` (for messages), or None."""
    i = -1
    for _ in range(nth + 1):
        i = text.find(needle, i + 1)
        if i < 0:
            return None
    return text.count("\n", 0, i) + 1


def read_mrk_json(path) -> MarkupPoints:
    """A 3D Slicer markups JSON file (``.mrk.json``): the control points of every markups node.

    Every node must use the same coordinate system; units ``mm`` (default) or ``um``.
    """
    text = _read_text(path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"invalid JSON: {e.msg}", path=path, line=e.lineno) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("markups"), list) or not doc["markups"]:
        raise InputError("not a markups file: expected a top-level 'markups' list", path=path, key="markups")
    pts = _Points(path)
    system = None
    seen: dict[str, int] = {}       # label -> how many times met so far (its line: that occurrence's)
    for m, node in enumerate(doc["markups"]):
        key = f"markups[{m}]"
        if not isinstance(node, dict):
            raise InputError("expected an object", path=path, key=key)
        cs = node.get("coordinateSystem", "LPS")
        this = _coordinate_system(str(cs), path, _json_line(text, '"coordinateSystem"'))
        if system is not None and this != system:
            raise InputError(f"markups nodes use different coordinate systems ({system} and {this})",
                             path=path, key=f"{key}.coordinateSystem")
        system = this
        units = str(node.get("coordinateUnits", "mm"))
        if units not in ("mm", "um"):
            raise InputError(f"unknown coordinate units {units!r}; expected mm or um", path=path,
                             key=f"{key}.coordinateUnits")
        factor = 1e-3 if units == "um" else 1.0
        cps = node.get("controlPoints", [])
        if not isinstance(cps, list):
            raise InputError("expected a list", path=path, key=f"{key}.controlPoints")
        for c, cp in enumerate(cps):
            ck = f"{key}.controlPoints[{c}]"
            if not isinstance(cp, dict):
                raise InputError("expected an object", path=path, key=ck)
            label = str(cp.get("label", ""))
            line = _json_line(text, json.dumps(label), seen.get(label, 0)) if label else None
            seen[label] = seen.get(label, 0) + 1
            status = str(cp.get("positionStatus", "defined"))
            if status in ("undefined", "missing"):
                pts.skip(label, f"position {status} ({ck})", line)
                continue
            pos = cp.get("position")
            if not isinstance(pos, list) or len(pos) != 3:
                raise InputError("expected 'position': [x, y, z]", path=path, line=line, key=f"{ck}.position")
            xyz = []
            for a, v in zip("xyz", pos):
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                    raise InputError(f"{a} is not a finite number: {v!r}", path=path, line=line,
                                     key=f"{ck}.position")
                xyz.append(float(v) * factor)
            pts.add(label, xyz, line)
    return pts.result("mrk.json", system or "LPS", str(doc.get("@schema", "")) or None)


def read_marker_csv(path) -> MarkupPoints:
    """bsipipe's plain table ``marker,x_mm,y_mm,z_mm`` (an optional ``# CoordinateSystem = ..`` line)."""
    text = _read_text(path)
    system = None
    header = None
    pts = _Points(path)
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            body = line[1:]
            if "=" in body:
                name, value = (s.strip() for s in body.split("=", 1))
                if name.lower() == "coordinatesystem":
                    system = _coordinate_system(value, path, lineno)
            continue
        fields = next(csv.reader([line]))
        if header is None:
            header = {c.strip().lower(): i for i, c in enumerate(fields)}
            missing = [c for c in ("marker", "x_mm", "y_mm", "z_mm") if c not in header]
            if missing:
                raise InputError(f"missing column(s) {', '.join(missing)}; expected marker,x_mm,y_mm,z_mm",
                                 path=path, line=lineno)
            continue
        if len(fields) < len(header):
            raise InputError(f"{len(fields)} fields, expected {len(header)}", path=path, line=lineno)
        xyz = [_float(fields[header[c]], c, path, lineno) for c in ("x_mm", "y_mm", "z_mm")]
        pts.add(fields[header["marker"]], xyz, lineno)
    if header is None:
        raise InputError("empty file; expected a header marker,x_mm,y_mm,z_mm", path=path, line=1)
    return pts.result("csv", system, None)


def read_markups(path) -> MarkupPoints:
    """CT marker coordinates from ``.fcsv``, ``.mrk.json`` (or ``.json``) or a plain ``.csv``."""
    name = Path(path).name.lower()
    if name.endswith(".fcsv"):
        return read_fcsv(path)
    if name.endswith(".json"):
        return read_mrk_json(path)
    if name.endswith(".csv") or name.endswith(".txt"):
        return read_marker_csv(path)
    raise InputError("unknown marker file type; expected .fcsv, .mrk.json or .csv", path=path)
