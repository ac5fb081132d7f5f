"""Testing-machine logs: Instron Bluehill 2, 3 and Universal exports and plain CSV.

:func:`read_machine_log` returns a :class:`MachineLog` with time in s, extension in mm and
load in N, whatever units the file wrote, and the file's own sign convention recorded so
:meth:`MachineLog.compression` can give displacement and force positive in compression.

Layouts recognised (``MachineLog.layout``):

``bluehill2``
    Optional metadata rows ``Key : Sub,value[,unit]`` and a blank line, then a names row
    (``Time,Extension,Load,...``) and a units row whose time unit is written ``(sec)``.
``bluehill3``
    The same two header rows with ``(s)``; values may be quoted; a ``Results Table`` block
    may come before the data; in a European locale the separator is ``;`` and the decimal
    mark ``,`` (the reader detects both).
``bluehill-universal``
    Section titles (``Method Parameters``, ``Results Table 1``, ...) and a ``Raw Data``
    marker line before the names row, units either in the names (``Time (s)``) or in a
    units row.
``plain-csv``
    One header row with the unit in each name: ``time_s``, ``Time (s)``, ``Load [kN]``,
    ``Displacement (µm)``.

Column names: time (``Time``), extension (``Extension``, ``Displacement``, ``Position``,
``Crosshead``, ...), load (``Load``, ``Force``, ...), all case-insensitive, German names
too; a ``Segment ID`` column becomes ``segment``.  Units: s, ms, min; mm, m, µm, in; N, kN,
mN, lbf, gf, kgf.  Any problem in the file raises :class:`~bsipipe.errors.InputError`
naming the file and the line.
"""

from __future__ import annotations

import codecs
import csv
import os
import re
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ._units import (UnknownUnit, clean_unit, is_known_unit, looks_numeric, normalise_name,
                     parse_number, split_name_unit, unit_factor)

__all__ = ["MachineLog", "read_machine_log", "LAYOUTS", "load_quantum", "load_resolution"]

LAYOUTS = ("bluehill2", "bluehill3", "bluehill-universal", "plain-csv")

# Normalised column names (see _units.normalise_name) of each channel.
ROLE_NAMES: dict[str, set[str]] = {
    "time": {"time", "t", "zeit", "test time", "elapsed time", "total time", "prüfzeit"},
    "extension": {"extension", "displacement", "position", "crosshead", "crosshead extension",
                  "crosshead displacement", "crosshead position", "compressive extension",
                  "tensile extension", "deformation", "stroke", "weg", "verfahrweg",
                  "traversenweg", "standardweg"},
    "load": {"load", "force", "compressive load", "tensile load", "compressive force",
             "tensile force", "kraft", "standardkraft"},
    "segment": {"segment id", "segment", "segment number", "step", "step id"},
}
_REQUIRED = ("time", "extension", "load")
_KIND = {"time": "time", "extension": "length", "load": "force"}
_EXAMPLE = {"time": "Time", "extension": "Extension, Displacement, Position or Crosshead",
            "load": "Load or Force"}
_ALL_ROLE_NAMES = set().union(*ROLE_NAMES.values())
_DELIMITERS = (",", ";", "\t", None)  # None: runs of white space
_META = re.compile(r"^(?P<key>[^:]+?)\s+:\s+(?P<sub>.+)$")
_GEOMETRY = re.compile(r"^(?:specimen |sample |initial |original |gauge )?"
                       r"(?P<what>diameter|height|thickness|width|length)$")
#: A results table's column naming each row's specimen.
_LABEL_NAMES = ("specimen label", "sample label", "specimen name", "sample name", "specimen id")
_ZIP_MAGIC = b"PK\x03\x04"                            # .xlsx (and any zip archive)
_OLE2_MAGIC = b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1"      # .xls
_HEADER_SEARCH_LINES = 5000  # the names row comes after at most a preamble and results tables
_SECTION_TABLES = ("results table", "results statistics", "test results", "statistics")


@dataclass(frozen=True, eq=False)
class MachineLog:
    """One testing-machine record, units converted.

    Attributes
    ----------
    path : str
    layout : str
        One of :data:`LAYOUTS`.
    time_s, extension_mm, load_n : ndarray, shape (n,)
        As the file wrote them (signs unchanged), converted to s, mm and N.
    segment : ndarray of int, shape (n,), or None
        The ``Segment ID`` column where the file has one.
    metadata : dict str -> str
        Header rows (``'Specimen label': '22L.3'``), a unit appended to the value where the
        row gives one; ``Results Table`` cells as ``'Results Table 1: Maximum Load'``.
    geometry : dict str -> float
        ``diameter_mm``, ``height_mm``, ``length_mm``, ``width_mm``, ``thickness_mm`` where
        the metadata states them with a length unit.
    geometry_invalid : dict str -> (str, int)
        The same keys where the metadata's value is empty, zero, negative or not finite (a
        template's unused dimensions are often left at 0): the reason and the line, raised
        only by a caller that needs that dimension and is given it no other way.
    units : dict str -> str
        Column name (without unit) -> unit as written, ``''`` for unitless columns.
    compression_sign : int
        +1 or -1: the sign of the load in compression in this file (Bluehill: -1).
    displacement_sign : int
        The same for the extension channel; equal to ``compression_sign`` unless the file
        mixes conventions.
    extra : dict str -> ndarray
        Every other numeric column, as written (units in ``units``).
    data_lines : ndarray of int, shape (n,)
        The 1-based line of the file each sample came from.
    dialect : dict str -> str
        ``delimiter``, ``decimal``, ``encoding``, ``newline`` and ``sign_from`` (how the
        sign convention was decided).
    spikes : ndarray of bool, shape (n,)
        Load samples that are no force (:func:`load_spikes`): they decided no sign, and a
        fit leaves them out.
    extension_spikes : ndarray of bool, shape (n,)
        Extension samples that are glitches (:func:`channel_spikes`: an encoder's miscount
        of one to three samples); a fit leaves them out.
    """

    path: str
    layout: str
    time_s: np.ndarray
    extension_mm: np.ndarray
    load_n: np.ndarray
    segment: np.ndarray | None
    metadata: dict[str, str]
    geometry: dict[str, float]
    units: dict[str, str]
    compression_sign: int
    displacement_sign: int = 0
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    data_lines: np.ndarray | None = None
    dialect: dict[str, str] = field(default_factory=dict)
    geometry_invalid: dict[str, tuple[str, int]] = field(default_factory=dict)
    spikes: np.ndarray | None = None
    extension_spikes: np.ndarray | None = None

    def __post_init__(self):
        if self.displacement_sign == 0:
            object.__setattr__(self, "displacement_sign", self.compression_sign)
        if self.spikes is None:
            object.__setattr__(self, "spikes", load_spikes(self.load_n))
        if self.extension_spikes is None:
            object.__setattr__(self, "extension_spikes", channel_spikes(self.extension_mm))

    def __len__(self) -> int:
        return int(self.time_s.size)

    def compression(self) -> tuple[np.ndarray, np.ndarray]:
        """``(displacement_mm, force_n)``, both positive in compression; the displacement
        is measured from the first sample, the force keeps the load cell's zero."""
        displacement_mm = self.displacement_sign * (self.extension_mm - self.extension_mm[0])
        force_n = self.compression_sign * self.load_n
        return displacement_mm, force_n

    def line_of(self, index: int) -> int:
        """The file line of sample ``index``, for messages about a sample."""
        return int(self.data_lines[index])


# --------------------------------------------------------------------------- text


def _read_lines(path) -> tuple[list[str], dict[str, str]]:
    """The file's lines (without line ends) and how it was written (encoding, newline).

    Raises :class:`InputError` for an unreadable or empty file.
    """
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as e:
        raise InputError(f"cannot read the file: {e.strerror or e}", path=path) from None
    if not raw.strip(b" \t\r\n\x00" + codecs.BOM_UTF8):
        raise InputError("the file is empty", path=path, line=1)
    if raw.startswith((_ZIP_MAGIC, _OLE2_MAGIC)):
        # An .xlsx is a zip archive, an .xls an OLE2 compound file: no text encoding reads them.
        raise InputError(f"this is an Excel workbook ({'.xlsx' if raw.startswith(_ZIP_MAGIC) else '.xls'}), "
                         f"not a text export: Excel workbooks are not read: export the raw data as CSV "
                         f"from Bluehill", path=path)
    if raw.startswith(codecs.BOM_UTF8):
        encodings = ["utf-8-sig"]
    elif raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        encodings = ["utf-16"]
    elif b"\x00" in raw[:4096]:  # UTF-16 without a byte order mark (Bluehill's option)
        encodings = ["utf-16-le" if raw[1:2] == b"\x00" else "utf-16-be"]
    else:
        encodings = ["utf-8", "cp1252"]
    for enc in encodings:
        try:
            text = raw.decode(enc)
            break
        except UnicodeDecodeError:
            continue
    else:
        raise InputError(f"cannot decode the file as {' or '.join(encodings)}", path=path, line=1)
    newline = "CRLF" if "\r\n" in text else ("CR" if "\r" in text else "LF")
    lines = re.split(r"\r\n|\r|\n", text)
    if lines and lines[-1] == "":
        lines.pop()
    return lines, {"encoding": enc, "newline": newline}


def _cells(line: str, delimiter: str | None) -> list[str]:
    """Fields of one line, quotes removed, surrounding space stripped."""
    if delimiter is None:
        return line.split()
    return [c.strip() for c in next(csv.reader([line], delimiter=delimiter, quotechar='"',
                                               skipinitialspace=True), [])]


def _rows(lines: list[str], delimiter: str | None) -> list[list[str]]:
    """:func:`_cells` for many lines at once (one row per line)."""
    if delimiter is None:
        return [ln.split() for ln in lines]
    rows = list(csv.reader(lines, delimiter=delimiter, quotechar='"', skipinitialspace=True))
    if len(rows) != len(lines):  # a quote opened on one line and closed on another
        return [_cells(ln, delimiter) for ln in lines]
    return [[c.strip() for c in r] for r in rows]


def _role_columns(names: list[str]) -> dict[str, list[int]]:
    """Column indices of each channel a names row names (every match, in order)."""
    found: dict[str, list[int]] = {}
    for j, cell in enumerate(names):
        base, _ = split_name_unit(cell, _ALL_ROLE_NAMES)
        key = normalise_name(base)
        for role, names_ in ROLE_NAMES.items():
            if key in names_:
                found.setdefault(role, []).append(j)
    return found


def _roles(names: list[str]) -> dict[str, int]:
    """Column index of each channel found in a names row (first match wins)."""
    return {role: cols[0] for role, cols in _role_columns(names).items()}


def _one_specimen(path, names: list[str], h: int) -> None:
    """A names row that holds every channel twice or more is several specimens side by side
    (a Bluehill export of all specimens): one record per file (exit 2) -- the first
    match of each channel would have fitted the first specimen and dropped the others."""
    found = _role_columns(names)
    cols = {r: [j + 1 for j in found.get(r, [])] for r in _REQUIRED}
    n = min(len(c) for c in cols.values())
    if n >= 2:
        raise InputError(f"the header names every channel {n} times ("
                         + "; ".join(f"{r} in columns {', '.join(map(str, c))}" for r, c in cols.items())
                         + f"): {n} specimens side by side; one record per file is supported: export each "
                           "specimen to its own file", path=path, line=h + 1)


def _find_header(lines: list[str]) -> tuple[int, str | None, list[str], dict[str, int]] | None:
    """The first line naming at least two of time, extension and load, with its delimiter,
    that data rows follow.

    A names row is followed, after at most a units row, by numbers in its columns.  A line
    that names the channels without data under it is a results table's names (``Extension
    at Maximum Load (mm)`` read word by word) or the preamble's text (``Test end: Extension
    limit or Load drop``), not the data's header; where no candidate has data under it, the
    first is taken (its missing data is then the error)."""
    first = None
    for i, line in enumerate(lines[:_HEADER_SEARCH_LINES]):
        if not line.strip():
            continue
        best = None
        for delim in _DELIMITERS:
            cells = _cells(line, delim)
            roles = _roles(cells)
            n = sum(r in roles for r in _REQUIRED)
            if n >= 2 and (best is None or n > best[0]):  # ties: the earlier, stricter delimiter
                best = (n, delim, cells, roles)
        if best is None:
            continue
        found = (i, best[1], best[2], best[3])
        if _data_follows(lines, i, best[1], max(best[3].values())):
            return found
        first = first or found
    return first


def _data_follows(lines: list[str], i: int, delimiter: str | None, last_col: int, look: int = 3) -> bool:
    """Whether a row of numbers reaching column ``last_col`` comes within ``look`` non-empty
    lines after line ``i`` (a units row may come between)."""
    seen = 0
    for line in lines[i + 1:]:
        if not line.strip():
            continue
        cells = _cells(line, delimiter)
        if len(cells) > last_col and _is_numeric_row(cells):
            return True
        seen += 1
        if seen >= look:
            return False
    return False


def _is_numeric_row(cells: list[str]) -> bool:
    filled = [c for c in cells if c]
    return bool(filled) and sum(looks_numeric(c) for c in filled) >= max(2, len(filled) - 1)


def _detect_decimal(rows: list[list[str]], cols: list[int], delimiter: str | None) -> str:
    """``','`` when the numbers use a decimal comma, else ``'.'``."""
    comma = point = False
    for r in rows[:200]:
        for j in cols:
            if j < len(r):
                c = r[j]
                comma |= bool(re.fullmatch(r"[+-]?\d*,\d+([eE][+-]?\d+)?", c))
                point |= bool(re.fullmatch(r"[+-]?\d*\.\d+([eE][+-]?\d+)?", c))
    # With a "," separator a decimal comma only survives inside quotes; either way a file
    # that writes "1,5" and never "1.5" uses the comma.
    return "," if comma and not point else "."


# --------------------------------------------------------------------------- reader


def read_machine_log(path: str | os.PathLike) -> MachineLog:
    """Read a testing-machine export (layouts in the module docstring).

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    MachineLog

    Raises
    ------
    InputError
        Naming the file and the line: no header, a missing column, no or unknown units,
        text, NaN or inf in a number column, time that does not increase, no data rows.
    """
    path = os.fspath(path)
    lines, dialect = _read_lines(path)
    found = _find_header(lines)
    if found is None:
        _raise_no_header(path, lines)
    h, delim, names_row, roles = found
    missing = [r for r in _REQUIRED if r not in roles]
    if missing:
        raise InputError(f"the header has no {missing[0]} column (found {', '.join(names_row)}; "
                         f"expected {_EXAMPLE[missing[0]]})", path=path, line=h + 1)

    _one_specimen(path, names_row, h)

    metadata, geometry_rows, raw_marker = _read_preamble(lines[:h], delim)

    u = h + 1
    while u < len(lines) and not lines[u].strip():
        u += 1
    if u >= len(lines):
        raise InputError(f"no data rows after the header at line {h + 1} (empty or truncated file)",
                         path=path, line=len(lines) + 1)
    names, units, factors, units_row = _column_units(path, names_row, roles, h, u,
                                                     _cells(lines[u], delim))

    # Data rows.
    first = u + 1 if units_row is not None else u
    data_idx = [i for i in range(first, len(lines)) if lines[i].strip()]
    rows = _rows([lines[i] for i in data_idx], delim)
    keep = [k for k, r in enumerate(rows) if any(r)]  # ",,,," is a blank line too
    data_idx = [data_idx[k] for k in keep]
    rows = [rows[k] for k in keep]
    if not rows:
        raise InputError(f"no data rows after the header at line {h + 1} (empty or truncated file)",
                         path=path, line=first + 1)
    need = max(roles[r] for r in _REQUIRED) + 1
    header = [normalise_name(c) for c in names_row]
    for k, r in enumerate(rows):
        # another export's rows after the data (two files joined): its metadata ("Key : Sub",
        # a "Results Table"/"Raw Data" title) or its own names row had read as a truncated line
        # or as text in a number column
        first_cell = r[0].strip() if r else ""
        if k and first_cell and not looks_numeric(first_cell) and (
                " : " in first_cell or normalise_name(first_cell) in ("resultstable1", "rawdata")
                or [normalise_name(c) for c in r[:len(header)]] == header):
            raise InputError(f"a second record starts inside the data ('{first_cell}', after "
                             f"{k} data rows): one record per file is supported; split the file", path=path,
                             line=data_idx[k] + 1)
        if len(r) < need:
            if r and not looks_numeric(r[0]) and sum(bool(c) for c in r) == 1:
                raise InputError(f"a second block '{r[0]}' starts inside the data; one record "
                                 f"per file is supported", path=path, line=data_idx[k] + 1)
            raise InputError(f"the row has {len(r)} fields but the header at line {h + 1} has "
                             f"{len(names_row)}; the line looks truncated", path=path,
                             line=data_idx[k] + 1)
    line_no = np.asarray(data_idx, dtype=int) + 1
    decimal = _detect_decimal(rows, [roles[r] for r in _REQUIRED], delim)
    values = {}
    for role in _REQUIRED:
        j = roles[role]
        values[role] = _number_column(rows, j, names[j], decimal, line_no, path) * factors[role]

    t = values["time"]
    dt = np.diff(t)
    bad = np.flatnonzero(~(dt > 0))
    if bad.size:
        k = int(bad[0]) + 1
        if dt[k - 1] == 0:
            msg = (f"time {rows[k][roles['time']]} repeats the previous sample's (line "
                   f"{line_no[k - 1]}); time must increase")
        else:
            msg = (f"time goes back from {rows[k - 1][roles['time']]} (line {line_no[k - 1]}) to "
                   f"{rows[k][roles['time']]}; time must increase")
        raise InputError(msg, path=path, line=int(line_no[k]))

    extra: dict[str, np.ndarray] = {}
    segment = None
    for j, name in enumerate(names):
        if j in (roles[r] for r in _REQUIRED) or not name:
            continue
        col = _optional_column(rows, j, decimal)
        if col is None:
            continue
        extra[name] = col
        if roles.get("segment") == j and np.all(np.isfinite(col)) and np.all(col == np.round(col)):
            segment = col.astype(np.int64)

    label = next((str(metadata[k]).strip() for k in metadata if normalise_name(k) in _LABEL_NAMES), None)
    geometry, geometry_invalid = _geometry(_rows_of(geometry_rows, label), decimal, path)
    spikes = load_spikes(values["load"])
    load_sign, disp_sign, sign_from = _compression_signs(
        values["extension"], values["load"], normalise_name(names[roles["load"]]),
        normalise_name(names[roles["extension"]]), spikes)
    if sign_from == _TENSION:
        k = int(np.argmax(np.abs(_load_change(values["load"], spikes))))
        raise InputError(f"'{names[roles['load']]}' rises to {values['load'][k]:.4g} N: the specimen was pulled, a "
                         "tension test; machine logs are fitted as compression between platens (a tension test can "
                         "be fitted as a stress-stretch table, mode uniaxial)", path=path, line=int(line_no[k]))

    if units_row is not None:
        # Bluehill 2 writes seconds "(sec)", Bluehill 3 "(s)"; another time unit (an export in
        # minutes, which had been called Bluehill 3 whatever its layout): Bluehill 3 marks its
        # table "Raw Data"
        t_unit = units[names[roles["time"]]].lower()
        layout = ("bluehill2" if t_unit == "sec" else "bluehill3" if t_unit == "s" or raw_marker else "bluehill2")
    elif raw_marker or metadata or any(ln.strip() for ln in lines[:h]):
        layout = "bluehill-universal"
    else:
        layout = "plain-csv"
    dialect.update({"delimiter": "whitespace" if delim is None else delim, "decimal": decimal,
                    "sign_from": sign_from})
    return MachineLog(path=path, layout=layout, time_s=t, extension_mm=values["extension"],
                      load_n=values["load"], segment=segment, metadata=metadata,
                      geometry=geometry, geometry_invalid=geometry_invalid, units=units, compression_sign=load_sign,
                      displacement_sign=disp_sign, extra=extra, data_lines=line_no,
                      dialect=dialect, spikes=spikes)


def _column_units(path, names_row, roles, h, u, next_cells):
    """Column names without units, the unit of each column as written, the conversion
    factor of each channel, and the units row (None when the names carry the units).

    Units come from the names (``Time (s)``, ``time_s``) and/or a units row at line
    ``u`` below the names; the row wins where it gives one.
    """
    names, name_units = [], []
    for cell in names_row:
        base, unit = split_name_unit(cell, _ALL_ROLE_NAMES)
        names.append(base)
        name_units.append(unit)
    req = [next_cells[roles[r]] if roles[r] < len(next_cells) else "" for r in _REQUIRED]
    units_row = next_cells if any(req) and not any(looks_numeric(c) for c in req) else None
    units: dict[str, str] = {}
    for j, name in enumerate(names):
        from_row = clean_unit(units_row[j]) if units_row is not None and j < len(units_row) else ""
        units[name or f"column {j + 1}"] = from_row or (name_units[j] or "")
    factors = {}
    for role in _REQUIRED:
        j = roles[role]
        unit = units[names[j]]
        if not unit:
            if units_row is None:
                raise InputError(f"no units for column '{names[j]}': expected a units row such as "
                                 f"(s),(mm),(N) below the header at line {h + 1}, or units in the "
                                 f"names such as 'Time (s)'", path=path, line=u + 1)
            raise InputError(f"the units row has no unit for column '{names[j]}'", path=path,
                             line=u + 1)
        try:
            factors[role] = unit_factor(unit, _KIND[role])
        except UnknownUnit as e:
            in_row = units_row is not None and j < len(units_row) and clean_unit(units_row[j])
            raise InputError(f"{e} for column '{names[j]}'", path=path,
                             line=(u if in_row else h) + 1) from None
    return names, units, factors, units_row


def _is_units_row(cells: list[str]) -> bool:
    """Every non-empty cell a unit in parentheses, ``(s)``, ``(mm/mm)``: Bluehill's units row."""
    full = [c for c in cells if c]
    return bool(full) and all(re.fullmatch(r"\(.*\)", c) for c in full)


def _raise_no_header(path: str, lines: list[str]):
    """No names row: say where the data starts without one, or that there is no table."""
    for i, line in enumerate(lines):
        for delim in _DELIMITERS:
            cells = _cells(line, delim)
            if len(cells) >= 2 and _is_numeric_row(cells):
                prev = i - 1
                while prev >= 0 and not lines[prev].strip():
                    prev -= 1
                if prev >= 0 and _is_units_row(_cells(lines[prev], delim)):
                    # a units row: the names are the line above it
                    up = prev - 1
                    while up >= 0 and not lines[up].strip():
                        up -= 1
                    prev = up if up >= 0 else prev
                if prev >= 0:
                    names = [c for c in _cells(lines[prev], delim) if c]
                    said = [c for c in names if re.search(r"stress|strain", c, re.I)]
                    if said:
                        raise InputError(f"the header names {', '.join(repr(c) for c in said)}: the file holds "
                                         "stress and strain, not the extension and load fit-ogden fits a log by; "
                                         "export Extension and Load, or give a table of stretch and nominal "
                                         "stress with --stress-stretch", path=path, line=prev + 1)
                    raise InputError(f"the header before the data ({lines[prev].strip()!r}) does not "
                                     f"name time, extension and load columns (expected e.g. "
                                     f"Time,Extension,Load)", path=path, line=prev + 1)
                raise InputError("the data has no header row naming the time, extension and load "
                                 "columns (expected e.g. Time,Extension,Load)", path=path, line=i + 1)
    last = max(i for i, ln in enumerate(lines) if ln.strip()) if any(ln.strip() for ln in lines) else 0
    raise InputError("no data table: the file ends without a header row naming Time, Extension "
                     "and Load and the rows below it", path=path, line=last + 1)


def _number_column(rows, j, name, decimal, line_no, path) -> np.ndarray:
    """Column ``j`` as floats; text, an empty cell, NaN or inf is an InputError at its line."""
    cells = [r[j] for r in rows]
    try:
        if decimal != ".":
            raise ValueError
        col = np.asarray(cells, dtype=float)
    except ValueError:
        col = np.empty(len(cells))
        for k, c in enumerate(cells):
            if not c:
                raise InputError(f"empty value in number column '{name}'", path=path,
                                 line=int(line_no[k])) from None
            try:
                col[k] = parse_number(c, decimal)
            except ValueError:
                raise InputError(f"text {c!r} in number column '{name}' (expected a number"
                                 f"{' with a decimal comma' if decimal == ',' else ''})",
                                 path=path, line=int(line_no[k])) from None
    bad = np.flatnonzero(~np.isfinite(col))
    if bad.size:
        k = int(bad[0])
        what = "NaN" if np.isnan(col[k]) else "infinite"
        raise InputError(f"{what} value {cells[k]!r} in column '{name}' (expected a finite number)",
                         path=path, line=int(line_no[k]))
    return col


def _optional_column(rows, j, decimal) -> np.ndarray | None:
    """An extra column as floats (NaN where empty or text); None when nothing is numeric."""
    out = np.full(len(rows), np.nan)
    any_number = False
    for k, r in enumerate(rows):
        if j < len(r) and r[j]:
            try:
                out[k] = parse_number(r[j], decimal)
                any_number = True
            except ValueError:
                pass
    return out if any_number else None


class _GeometryRow(NamedTuple):
    """A dimension the preamble states, converted once the decimal mark is known: ``row`` is
    its results table row (0: the first, or a metadata row: the log's own; later rows are
    other specimens'), ``label`` that row's specimen label where the table names it."""

    what: str
    value: str
    unit: str
    line: int
    row: int = 0
    label: str | None = None


def _read_preamble(lines: list[str], delim):
    """Metadata rows, Results Table blocks and section titles before the names row.

    Returns ``(metadata, geometry_rows, raw_marker)``; ``geometry_rows`` are
    :class:`_GeometryRow`.
    """
    metadata: dict[str, str] = {}
    geometry_rows: list[_GeometryRow] = []
    raw_marker = False
    table = None  # {'title', 'names', 'units', 'n'}

    def put(key: str, value: str, unit: str, line: int, full_key: str | None = None):
        k = key if key not in metadata or full_key is None else full_key
        metadata[k] = f"{value} {unit}".strip() if unit else value
        base = key
        if not unit:
            # The unit inside the key: ``Specimen diameter (mm),18``.
            base, key_unit = split_name_unit(key)
            unit = key_unit or ""
        m = _GEOMETRY.match(normalise_name(base))
        if m and unit:
            geometry_rows.append(_GeometryRow(m.group("what"), value, unit, line))

    for i, line in enumerate(lines):
        cells = _cells(line, delim)
        filled = [c for c in cells if c]
        if not filled:
            table = None
            continue
        m = _META.match(cells[0]) if cells[0] else None
        if m:
            table = None
            value = cells[1] if len(cells) > 1 else ""
            unit = cells[2] if len(cells) > 2 else ""
            put(m.group("sub").strip(), value, unit, i + 1, full_key=cells[0])
            continue
        if len(filled) == 1 and cells[0] and not looks_numeric(cells[0]):
            title = cells[0]
            low = normalise_name(title)
            raw_marker |= low.startswith("raw data")
            table = ({"title": title, "names": None, "units": None, "n": 0}
                     if low.startswith(_SECTION_TABLES) else None)
            continue
        if table is not None:
            if table["names"] is None:
                table["names"] = cells
            elif (table["units"] is None and table["n"] == 0
                  and not any(looks_numeric(c) for c in filled)
                  and all(c.startswith(("(", "[")) or is_known_unit(c) for c in filled)):
                table["units"] = [clean_unit(c) for c in cells]
            else:
                # the row's specimen, where the table names it (to match the log's own label)
                lab = next((j for j, nm in enumerate(table["names"]) if normalise_name(nm) in _LABEL_NAMES), None)
                row_label = cells[lab].strip() if lab is not None and lab < len(cells) and cells[lab] else None
                for j, name in enumerate(table["names"]):
                    if not name or j >= len(cells) or not cells[j]:
                        continue
                    unit = table["units"][j] if table["units"] and j < len(table["units"]) else ""
                    suffix = f" [{table['n'] + 1}]" if table["n"] else ""
                    metadata[f"{table['title']}: {name}{suffix}"] = (
                        f"{cells[j]} {unit}".strip() if unit else cells[j])
                    m = _GEOMETRY.match(normalise_name(name))
                    if m and unit:
                        # a later row is another specimen's: kept to tell whether it agrees
                        geometry_rows.append(_GeometryRow(m.group("what"), cells[j], unit, i + 1, table["n"],
                                                          row_label))
                table["n"] += 1
            continue
        if 2 <= len(filled) <= 3 and cells[0] and not looks_numeric(cells[0]):
            put(cells[0], cells[1] if len(cells) > 1 else "", cells[2] if len(cells) > 2 else "",
                i + 1)
    return metadata, geometry_rows, raw_marker


def _rows_of(rows: list[_GeometryRow], label: str | None) -> list[_GeometryRow]:
    """The geometry rows of the log's own specimen: where the log states its label (``Text
    Inputs : Specimen label``) and a results table labels its rows, that row (as the log's
    own) and no other table row; else every row as read."""
    if label is None or not any(r.label == label for r in rows):
        return rows
    return [r._replace(row=0) if r.label == label else r for r in rows if r.label in (None, label)]


def _length_or_none(value, unit, decimal) -> float | None:
    """A length in mm, or None where the value or unit is not one."""
    try:
        v = parse_number(value, decimal) * unit_factor(unit, "length")
    except (ValueError, UnknownUnit):
        return None
    return float(v) if np.isfinite(v) and v > 0 else None


def _geometry(rows, decimal, path) -> tuple[dict[str, float], dict[str, tuple[str, int]]]:
    """``{what}_mm`` from the metadata rows that give a length with a unit, and the rows whose
    value is empty or not a positive finite number (``key -> (reason, line)``: a template's
    unused dimensions, left at 0; an error only where a caller needs that dimension)."""
    out: dict[str, float] = {}
    invalid: dict[str, tuple[str, int]] = {}
    ambiguous: set[str] = set()
    for what, value, unit, line, row, _ in rows:
        key = f"{what}_mm"
        if row > 0:
            # a results table's later row: another specimen of the same test file.  Its
            # dimension differing from the first row's leaves this log's unknown
            v = _length_or_none(value, unit, decimal)
            if key in out and v is not None and not np.isclose(v, out[key], rtol=1e-6) and key not in ambiguous:
                ambiguous.add(key)
                invalid[key] = (f"the results table lists specimens of different {what} ({out.pop(key):g} and "
                                f"{v:g} mm): which is this log's is not known", line)
            continue
        if key in out or key in ambiguous:
            continue
        if not str(value).strip():
            invalid.setdefault(key, (f"the {what} is empty", line))
            continue
        try:
            factor = unit_factor(unit, "length")
        except UnknownUnit as e:
            if is_known_unit(unit):  # a force or a time under a geometric name: not geometry
                continue
            raise InputError(f"{e} for '{what}'", path=path, line=line) from None
        try:
            v = parse_number(value, decimal)
        except ValueError:
            raise InputError(f"text {value!r} where the {what} should be a number", path=path,
                             line=line) from None
        if not np.isfinite(v) or v <= 0:
            invalid.setdefault(key, (f"the {what} must be a positive finite number, not {value!r}", line))
            continue
        out[key] = v * factor
        invalid.pop(key, None)
    return out, invalid


#: A load sample whose magnitude reaches this is a channel's over-range code (Bluehill writes
#: 9.9E+37), not a force.
OVERRANGE_N = 1e30
#: A sample is a spike when its jumps in and out are both this many times the larger of the
#: neighbouring steps (and of the channel's resolution).
SPIKE_RATIO = 10.0


#: The longest burst (consecutive samples away from the signal and back) taken for a glitch.
MAX_BURST = 3


def load_spikes(load) -> np.ndarray:
    """Samples of a load channel that are no force: over-range codes (``|F| >= 1e30``) and
    glitches (:func:`channel_spikes`), as a bool mask.

    >>> bool(load_spikes([0.0, 0.1, 0.2, 0.3, 5.0, 0.5, 0.6, 0.7, 0.8])[4])
    True
    >>> int(load_spikes([0.0, 0.1, 0.2, 0.3, 0.4, 0.3, 0.2, 0.1, 0.0]).sum())     # a turning point
    0
    >>> load_spikes([0.0, 0.1, 0.2, 0.3, 9.9e37, 0.5, 0.6]).nonzero()[0].tolist()
    [4]
    """
    f = np.asarray(load, dtype=float)
    bad = ~np.isfinite(f) | (np.abs(f) >= OVERRANGE_N)
    if f.size < 5:
        return bad
    g = f.copy()
    if bad.any():
        good = np.flatnonzero(~bad)
        if good.size == 0:
            return bad
        g[bad] = np.interp(np.flatnonzero(bad), good, f[good])
    return bad | channel_spikes(g)


def channel_spikes(values) -> np.ndarray:
    """Glitches of a channel (a dropped bit, an encoder's miscount, a burst of interference),
    as a bool mask: runs of 1 to :data:`MAX_BURST` samples that jump away from the signal and
    back.

    A run of ``w`` samples ``i .. i+w-1`` is a glitch when the jumps into it and out of it are
    both more than :data:`SPIKE_RATIO` times the steps around it (``|v[i-1] - v[i-2]|``,
    ``|v[i+w+1] - v[i+w]|``) and the channel's resolution (the median nonzero step); a run of
    two or three must also jump out the way it jumped in, back to within ``2 (w + 1)`` such
    steps of where it left (a ramp's turning point moves in steps like its neighbours'; a
    step change stays).

    >>> channel_spikes([0.0, 0.1, 0.2, 0.3, 5.0, 0.5, 0.6, 0.7, 0.8]).nonzero()[0].tolist()
    [4]
    >>> channel_spikes([0.0, 0.1, 0.2, 0.3, 5.0, 5.1, 0.6, 0.7, 0.8]).nonzero()[0].tolist()
    [4, 5]
    >>> int(channel_spikes([0.0, 0.1, 0.2, 0.3, 5.0, 5.1, 5.2, 5.3, 5.4]).sum())   # a step stays
    0
    """
    g = np.asarray(values, dtype=float)
    n = g.size
    spike = np.zeros(n, bool)
    if n < 5:
        return spike
    d = np.abs(np.diff(g))                       # d[i] = |g[i+1] - g[i]|
    nz = d[d > 0]
    resolution = float(np.median(nz)) if nz.size else 0.0
    # one sample (i = 2 .. n-3): |g[i] - g[i-1]|, |g[i+1] - g[i]| against the steps either side
    jump_in, jump_out = d[1:-2], d[2:-1]
    around = np.maximum(np.maximum(d[:-3], d[3:]), resolution)
    spike[2:-2] = (jump_in > SPIKE_RATIO * around) & (jump_out > SPIKE_RATIO * around)
    s = np.diff(g)                                # signed steps
    for w in range(2, MAX_BURST + 1):
        i = np.arange(2, n - w - 1)               # the run i .. i+w-1, with i-2 and i+w+1 in the record
        if i.size == 0:
            break
        into, out = s[i - 1], s[i + w - 1]
        around = np.maximum(np.maximum(d[i - 2], d[i + w]), resolution)
        back = np.abs(g[i + w] - g[i - 1]) <= 2 * (w + 1) * around
        hit = ((np.abs(into) > SPIKE_RATIO * around) & (np.abs(out) > SPIKE_RATIO * around)
               & (np.sign(into) == -np.sign(out)) & back)
        for k in range(w):
            spike[i[hit] + k] = True
    return spike


#: ``sign_from`` of a record whose channel named tensile rises: a tension test.
_TENSION = "tension"


def _load_change(load, spikes) -> np.ndarray:
    """Each sample's load less the start's (the median of the first ten samples); 0 at the
    ``spikes``, which decide nothing."""
    ok = ~spikes
    start = float(np.median(load[ok][: min(10, int(ok.sum()))])) if ok.any() else 0.0
    return np.where(ok, load - start, 0.0)


def _compression_signs(extension, load, load_name, extension_name, spikes) -> tuple[int, int, str]:
    """The sign of compression on the load and extension channels.

    The record decides: the sample most loaded away from the start,
    ``k = argmax |F - F_start|`` (the ``spikes`` of :func:`load_spikes` left out), is where
    the machine compressed hardest, so the sign of ``F_k - F_start`` is the load's sign of
    compression and that of ``x_k - x_0`` the extension's.  A name saying ``compressive``
    (Bluehill's ``Compressive load``, ``Compressive extension``) means +1; where the data are
    clear and say the opposite (a template that names the channel compressive but writes
    Instron's negative values), the data win and ``sign_from`` says so.  A name saying
    ``tensile`` (``Tensile load``) whose data rise is a tension test: ``sign_from`` is
    :data:`_TENSION` (the reader refuses it).  A record with no load change keeps the name's
    sign, else Instron's convention (compression negative).
    """
    dev = _load_change(load, spikes)        # a glitch or an over-range code decides nothing
    k = int(np.argmax(np.abs(dev)))
    scale = float(np.median(np.abs(np.diff(load)))) if load.size > 2 else 0.0
    clear = abs(dev[k]) > 10 * scale and dev[k] != 0
    data_load = int(np.sign(dev[k])) if clear else 0
    step = extension[k] - extension[0]
    data_disp = int(np.sign(step)) if clear and step != 0 else 0
    notes = []
    if load_name.startswith("tensile") and data_load == 1:
        return 1, data_disp or 1, _TENSION
    if load_name.startswith("compressive"):
        load_sign, how = 1, "column name"
        if data_load == -1:
            load_sign, how = -1, "data"
            notes.append(f"'{load_name}' falls in compression")
    elif data_load:
        load_sign, how = data_load, "data"
    else:
        load_sign, how = -1, "default (no load change in the record)"
    if extension_name.startswith("compressive"):
        disp_sign = 1
        if data_disp == -1:
            disp_sign = -1
            notes.append(f"'{extension_name}' falls in compression")
    else:
        disp_sign = data_disp or load_sign
    if notes:
        how = f"data (the column is named compressive but {' and '.join(notes)}: the data's sign is used)"
    return load_sign, disp_sign, how


#: A clipped top needs at least this many samples at the record's largest force, exactly.
CLIP_MIN_SAMPLES = 3


def clipped_top(disp: np.ndarray, force: np.ndarray, n_before: int = 20) -> dict | None:
    """Where a log's force stops at a ceiling: a load cell at the end of its range (or an
    export's) reads one value, exactly, while the platen goes on compressing.  The test: at
    least :data:`CLIP_MIN_SAMPLES` samples at the record's largest force to the last digit,
    spread over a travel along which the ``n_before`` samples before the first of them rise by
    more than 3 times the larger of their scatter and the log's force resolution (so a coarse
    log whose top few samples round alike, or a hold, is not called clipped).  Returns the
    first such sample's index, the level (N), the count, that expected rise and ``n_before``,
    or None.

    A 0.5 N ceiling on 18 of 616 samples (the last 3 %) of the probe's log had been fitted as
    a machine compliance of 1.39 mm/N with alpha turned to +19.4, unsaid.

    >>> d = np.linspace(0, 3, 301); f = np.minimum(0.05 * d ** 3, 1.0)
    >>> c = clipped_top(d, f); c["first"], c["n_samples"]
    (272, 29)
    >>> clipped_top(d, 0.05 * d ** 3) is None
    True
    """
    f = np.asarray(force, float)
    x = np.asarray(disp, float)
    if len(f) < n_before + CLIP_MIN_SAMPLES:
        return None
    top = float(np.max(f))
    at = f >= top - 1e-12 * abs(top)
    idx = np.flatnonzero(at)
    first = int(idx[0])
    if len(idx) < CLIP_MIN_SAMPLES or first < n_before:
        return None
    span = float(np.ptp(x[idx]))
    if not span > 0:                      # a hold at one displacement is no clipping
        return None
    pre = slice(first - n_before, first)
    xp, fp = x[pre], f[pre]
    if not np.ptp(xp) > 0:
        return None
    slope, icpt = np.polyfit(xp, fp, 1)
    scatter = float(np.std(fp - (slope * xp + icpt), ddof=2))
    levels = np.unique(f)
    steps = np.diff(levels)
    resolution = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
    rise = float(slope) * span
    if not rise > 3.0 * max(scatter, resolution):
        return None
    return {"first": first, "level_n": top, "n_samples": int(len(idx)), "travel_mm": span,
            "expected_rise_n": rise, "n_before": n_before}


#: The load's quantum (:func:`load_resolution`): a first step past the loading's start that
#: spans more than this share of the loading travel cannot locate the contact or the
#: low-strain stiffness (exit 2 in fit-ogden) ...
RESOLUTION_REFUSE_SHARE = 0.2
#: ... more than this share is warned about (``load-resolution``).
RESOLUTION_WARN_SHARE = 0.1


def load_quantum(force) -> float:
    """The load's quantum: the smallest step between its distinct values (the export's last
    digit, or the cell's resolution), less differences below 1e-9 of its range that a unit's
    conversion leaves (0.3 kN written as 300.00000000000006 N).  0 for fewer than 2 values.

    >>> round(load_quantum(np.array([0.0, 0.1, 0.1, 0.3, 0.2]) * 1000.0 / 1000.0), 12)
    0.1
    """
    f = np.asarray(force, float)
    f = f[np.isfinite(f)]
    if f.size < 2 or not np.ptp(f) > 0:
        return 0.0
    steps = np.diff(np.unique(f))
    steps = steps[steps > 1e-9 * float(np.ptp(f))]
    return float(steps.min()) if steps.size else 0.0


def load_resolution(disp: np.ndarray, force: np.ndarray) -> dict | None:
    """How coarsely the load is written against the loading it records, or None where the
    quantum does not matter.

    On a loading ramp (up to its largest displacement) the force climbs from its first
    samples' level; the travel between the first sample one quantum above that level and the
    first two quanta above it is the travel one step of the load spans at the onset, where the
    contact and the low-strain stiffness are read.  Returned where that step spans more than
    :data:`RESOLUTION_WARN_SHARE` of the travel left from its start to the largest displacement
    and the load's noise (from its second differences) is under half a quantum, so the
    staircase is no random error the fit can average (a noisier load dithers it):
    ``quantum_n``, ``levels`` (the force's range in quanta), ``first_step_mm``,
    ``travel_mm``, ``share`` and ``noise_n``.

    A load written in kN with 4 decimals (0.1 N steps, 6 levels over a 0.55 N peak, the
    first step spanning 1.04 of the 2.7 mm after it) had been fitted at mu 1668 Pa, alpha +11.2 for 720 Pa,
    -4.7, its contact 0.56 mm late, with no word of the resolution.
    """
    d = np.asarray(disp, float)
    f = np.asarray(force, float)
    q = load_quantum(f)
    if not q > 0 or d.size < 10:
        return None
    stop = int(np.argmax(d)) + 1
    d, f = d[:stop], f[:stop]
    from ..mechanics.contact import force_noise
    noise = force_noise(f)
    if noise >= 0.5 * q:
        return None
    start = float(np.median(f[:min(10, f.size)]))
    one = np.flatnonzero(f >= start + q * (1 - 1e-6))
    two = np.flatnonzero(f >= start + 2 * q * (1 - 1e-6))
    if not (one.size and two.size):
        step, travel = float(np.ptp(d)), float(np.ptp(d))
    else:
        step, travel = float(d[two[0]] - d[one[0]]), float(d[-1] - d[one[0]])
    if not travel > 0:
        return None
    share = step / travel
    if share <= RESOLUTION_WARN_SHARE:
        return None
    return {"quantum_n": q, "levels": float(np.ptp(f)) / q, "first_step_mm": step, "travel_mm": travel,
            "share": share, "noise_n": noise}
