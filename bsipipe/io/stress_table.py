"""Stress-stretch tables: ``stretch`` and nominal stress, optionally per loading mode.

The layout of ``bsipipe fit-ogden TABLE.csv --stress-stretch`` (CONTRACTS.md): a header
row with a ``stretch`` column and exactly one of ``nominal_stress_pa``,
``nominal_stress_kpa``, ``nominal_stress_mpa`` (``Nominal stress (kPa)`` also reads), and
an optional ``mode`` column (``uniaxial``, ``equibiaxial``, ``pure-shear``,
``simple-shear``; for simple shear ``stretch`` holds the amount of shear gamma).  The
separator (``,``, ``;``, tab or spaces) and a decimal comma are detected; lines starting
with ``#`` are comments.  Every problem is an :class:`~bsipipe.errors.InputError` naming the
file and the line.
"""

from __future__ import annotations

import os

import numpy as np
import pandas as pd

from ..errors import InputError
from ..mechanics.hyperelastic import MODES
from ._units import UnknownUnit, normalise_name, split_name_unit, unit_factor
from .machine_log import _DELIMITERS, _cells, _detect_decimal, _number_column, _read_lines, _rows

__all__ = ["read_stress_table", "normalise_mode"]

_MODE_ALIASES = {
    "uniaxial": "uniaxial", "ut": "uniaxial", "uniaxial tension": "uniaxial",
    "uniaxial compression": "uniaxial", "tension": "uniaxial", "compression": "uniaxial",
    "equibiaxial": "equibiaxial", "et": "equibiaxial", "biaxial": "equibiaxial",
    "equibiaxial tension": "equibiaxial",
    "pure shear": "pure-shear", "ps": "pure-shear", "planar": "pure-shear",
    "planar tension": "pure-shear",
    "simple shear": "simple-shear", "ss": "simple-shear", "shear": "simple-shear",
}


def normalise_mode(text: str) -> str | None:
    """``"Pure shear"``, ``"pure_shear"``, ``"PS"`` -> ``"pure-shear"``; None if unknown.

    >>> normalise_mode("Pure_Shear"), normalise_mode("UT"), normalise_mode("torsion")
    ('pure-shear', 'uniaxial', None)
    """
    return _MODE_ALIASES.get(normalise_name(text.replace("-", " ")))


def read_stress_table(path: str | os.PathLike, mode: str | None = None) -> pd.DataFrame:
    """Read a stress-stretch table.

    Parameters
    ----------
    path : str or path-like
    mode : str, optional
        The loading mode of every row when the table has no ``mode`` column (default
        ``"uniaxial"``); a ``mode`` column wins where present.

    Returns
    -------
    pandas.DataFrame
        Columns ``stretch`` (gamma for simple shear), ``nominal_stress_pa`` (Pa) and
        ``mode``; ``attrs`` holds ``path``, ``lines`` (the file line of each row) and
        ``stress_unit`` (as written).

    Raises
    ------
    InputError
        No header, no ``stretch`` or stress column, two stress columns, an unknown mode
        or unit, text, NaN or inf in a number, a stretch that is not positive, no rows.
    """
    path = os.fspath(path)
    default_mode = "uniaxial"
    if mode is not None:
        default_mode = normalise_mode(mode)
        if default_mode is None:
            raise InputError(f"unknown loading mode {mode!r}; expected one of {', '.join(MODES)}",
                             path=path)
    lines, _ = _read_lines(path)
    body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise InputError("the file has no header and no data", path=path, line=len(lines) or 1)
    h = body[0]
    delim, cells = _header_delimiter(lines[h])
    if delim is False:
        raise InputError(f"no 'stretch' column in the header {lines[h].strip()!r} (expected "
                         f"stretch and one of nominal_stress_pa, nominal_stress_kpa, "
                         f"nominal_stress_mpa)", path=path, line=h + 1)
    names = [normalise_name(c) for c in cells]
    j_stretch = names.index("stretch")
    stress_cols = []
    for j, cell in enumerate(cells):
        base, unit = split_name_unit(cell, {"nominal stress"})
        if normalise_name(base) == "nominal stress":
            stress_cols.append((j, cell, unit))
    if not stress_cols:
        raise InputError("no nominal stress column (expected one of nominal_stress_pa, "
                         "nominal_stress_kpa, nominal_stress_mpa)", path=path, line=h + 1)
    if len(stress_cols) > 1:
        raise InputError(f"two stress columns ({', '.join(c for _, c, _ in stress_cols)}); give "
                         f"exactly one", path=path, line=h + 1)
    j_stress, stress_name, stress_unit = stress_cols[0]
    if not stress_unit:
        raise InputError(f"column {stress_name!r} has no unit (expected nominal_stress_pa, _kpa "
                         f"or _mpa)", path=path, line=h + 1)
    try:
        factor = unit_factor(stress_unit, "stress")
    except UnknownUnit as e:
        raise InputError(f"{e} in column {stress_name!r}", path=path, line=h + 1) from None
    j_mode = names.index("mode") if "mode" in names else None

    idx = body[1:]
    rows = _rows([lines[i] for i in idx], delim)
    keep = [k for k, r in enumerate(rows) if any(r)]
    idx, rows = [idx[k] for k in keep], [rows[k] for k in keep]
    if not rows:
        raise InputError(f"no data rows after the header at line {h + 1} (empty or truncated file)",
                         path=path, line=len(lines) + 1)
    need = max(j_stretch, j_stress, -1 if j_mode is None else j_mode) + 1
    for k, r in enumerate(rows):
        if len(r) < need:
            raise InputError(f"the row has {len(r)} fields but the header has {len(cells)}; the "
                             f"line looks truncated", path=path, line=idx[k] + 1)
    line_no = np.asarray(idx, dtype=int) + 1
    decimal = _detect_decimal(rows, [j_stretch, j_stress], delim)
    stretch = _number_column(rows, j_stretch, cells[j_stretch], decimal, line_no, path)
    stress = _number_column(rows, j_stress, stress_name, decimal, line_no, path) * factor
    if j_mode is None:
        modes = [default_mode] * len(rows)
    else:
        modes = []
        for k, r in enumerate(rows):
            m = normalise_mode(r[j_mode]) if r[j_mode] else None
            if m is None:
                raise InputError(f"unknown loading mode {r[j_mode]!r}; expected one of "
                                 f"{', '.join(MODES)}", path=path, line=int(line_no[k]))
            modes.append(m)
    for k, (lam, m) in enumerate(zip(stretch, modes)):
        if m != "simple-shear" and lam <= 0:
            raise InputError(f"stretch {rows[k][j_stretch]!r} is not positive ({m} needs a "
                             f"stretch > 0)", path=path, line=int(line_no[k]))
    # strains in the stretch column (0.02, 0.05, ...): every stretch near 0 is a specimen
    # compressed to a sliver; they had been fitted (mu 53 Pa, alpha 0.27, errors of 100 %)
    lam_ns = np.asarray([lam for lam, m in zip(stretch, modes) if m != "simple-shear"], float)
    if len(lam_ns) and lam_ns.min() < MIN_STRETCH:
        raise InputError(f"the stretch column looks like strains: it runs from {lam_ns.min():.3g} to "
                         f"{lam_ns.max():.3g}, and a stretch of {lam_ns.min():.3g} is a specimen compressed to "
                         f"{100 * lam_ns.min():.2g} % of its length (a stretch is length / original length, 1 "
                         "unloaded): give stretch = 1 + strain (1 - the compressive strain in compression)", path=path)
    stress, turned, magnitudes = _stress_sign(stretch, stress, np.asarray(modes))
    out = pd.DataFrame({"stretch": stretch, "nominal_stress_pa": stress, "mode": modes})
    out.attrs.update(path=path, lines=line_no.tolist(), stress_unit=stress_unit, sign_turned=turned,
                     magnitudes=magnitudes)
    return out


#: A stretch (tension and compression rows) below this is a strain: no specimen is compressed
#: to a tenth of its length.
MIN_STRETCH = 0.1


def _stress_sign(stretch: np.ndarray, stress: np.ndarray,
                 modes: np.ndarray) -> tuple[np.ndarray, list[str], list[str]]:
    """The stress with the sign the laws use -- positive in tension (stretch > 1, or gamma >
    0 in simple shear), negative in compression -- and the modes whose table wrote every
    loaded row with the other sign (compression positive, as many compression rigs and papers
    do), which are turned; a mode with both tension and compression rows whose every stress
    is positive gives magnitudes, and its compression rows are turned.  A mode whose rows
    disagree among themselves otherwise is left as written.  Returns the stress, the modes
    turned whole and the modes whose compression rows were turned (magnitudes).

    >>> _stress_sign(np.array([1.0, 0.9, 0.8]), np.array([0.0, 10.0, 25.0]), np.array(["uniaxial"] * 3))
    (array([  0., -10., -25.]), ['uniaxial'], [])
    """
    out = stress.copy()
    turned, magnitudes = [], []
    for m in dict.fromkeys(modes.tolist()):
        rows = modes == m
        strain = stretch[rows] - (0.0 if m == "simple-shear" else 1.0)
        agree = np.sign(strain) * np.sign(stress[rows])
        loaded = agree != 0
        if loaded.any() and np.all(agree[loaded] < 0):
            out[rows] = 0.0 - stress[rows]            # (an unloaded 0 stays 0, not -0)
            turned.append(m)
        elif m != "simple-shear" and (strain < 0).any() and (strain > 0).any() and np.all(stress[rows] >= 0) \
                and np.all(agree[loaded & (strain < 0)] < 0) and (loaded & (strain < 0)).any():
            # every stress positive, tension and compression alike: magnitudes (as a rig that
            # reports |F| writes them); the compression rows take the laws' sign
            idx = np.flatnonzero(rows)[strain < 0]
            out[idx] = 0.0 - stress[idx]
            magnitudes.append(m)
    return out, turned, magnitudes


def _header_delimiter(line: str):
    """``(delimiter, cells)`` of the header line: the separator that yields a ``stretch``
    cell; ``(False, [])`` when none does."""
    for delim in _DELIMITERS:
        cells = _cells(line, delim)
        if "stretch" in (normalise_name(c) for c in cells):
            return delim, cells
    return False, []
