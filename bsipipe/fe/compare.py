r"""FE model against measured marker displacements: the seeds' Table 1, Table 2 and sigma.

Positions: a marker's reference position (where the FE field is evaluated, on the undeformed
mesh) is its position in the registration frame, :math:`\mathbf X = \mathbf x_F - \mathbf d_F`
from any row of ``markers_ct.csv`` (``x_mm - dx_mm`` etc.), and its measured displacement in
the compared frame F is :math:`\mathbf d_F` (``dx_mm, dy_mm, dz_mm``).  The model displacement
is the FE nodal field interpolated at :math:`\mathbf X` with the element shape functions
(:class:`~bsipipe.geometry.shape_functions.PointLocator`).

Per marker *n* and axis: :math:`E_{n,a} = u^{model}_{n,a} - u^{measured}_{n,a}` (``diff_mm``),
and :math:`E_n = |\mathbf E_n|`.  Table 2 gives, for x, y and z, the maximum, minimum and mean of
:math:`|E_{n,a}|` and, for the magnitude, of :math:`E_n` (plus the signed mean, the bias, and the
RMS); :math:`\sigma = \sqrt{\sum_n E_n^2 / n}` (``sigma_mm``), the seeds' standard error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

__all__ = ["MarkerFrame", "markers_at_frame", "peak_frame", "model_at_points", "CompareResult",
           "compare_displacements"]

AXES = ("x", "y", "z")
MARKERS_CT_COLUMNS = ("frame", "marker", "x_mm", "y_mm", "z_mm", "dx_mm", "dy_mm", "dz_mm")


@dataclass
class MarkerFrame:
    """Markers in one frame: ``names`` (n,), reference positions ``position_mm`` (n, 3),
    measured displacements ``measured_mm`` (n, 3), ``time_s``, and markers skipped (name -> why)."""

    frame: int
    time_s: float | None
    names: list[str]
    position_mm: np.ndarray
    measured_mm: np.ndarray
    skipped: dict[str, str] = field(default_factory=dict)


def peak_frame(table: pd.DataFrame, markers=None) -> int:
    """The frame with the largest mean displacement magnitude over ``markers`` (default: all
    non-reference markers): where an FE run to the peak of the indentation is compared."""
    t = _select(table, markers)
    mag = np.sqrt(t["dx_mm"] ** 2 + t["dy_mm"] ** 2 + t["dz_mm"] ** 2)
    per = mag.groupby(t["frame"]).mean().dropna()
    if per.empty:
        raise ValueError("no frame has a finite displacement")
    return int(per.idxmax())


def _select(table: pd.DataFrame, markers):
    if markers:
        return table[table["marker"].isin(list(markers))]
    if "role" in table.columns:
        return table[~table["role"].astype(str).isin(["reference", "xray-only"])]
    return table


def markers_at_frame(table: pd.DataFrame, frame: int, markers=None) -> MarkerFrame:
    """The markers of ``table`` (``markers_ct.csv``) in ``frame``: reference positions and
    measured displacements.  ``markers`` (names) selects; by default every marker whose
    ``role`` is neither ``reference`` (skull-fixed references do not move with the tissue)
    nor ``xray-only`` (a point the CT does not hold, such as a bead on the indentor)."""
    t = _select(table, markers)
    rows = t[t["frame"] == frame]
    skipped = {}
    if markers:
        for m in markers:
            if m not in set(table["marker"]):
                skipped[m] = "not in the markers table"
            elif m not in set(rows["marker"]):
                skipped[m] = f"no row in frame {frame}"
    names, X, d = [], [], []
    for _, r in rows.iterrows():
        xyz = np.array([r["x_mm"], r["y_mm"], r["z_mm"]], dtype=float)
        dis = np.array([r["dx_mm"], r["dy_mm"], r["dz_mm"]], dtype=float)
        if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(dis))):
            skipped[str(r["marker"])] = f"not found in frame {frame} or in the registration frame"
            continue
        names.append(str(r["marker"]))
        X.append(xyz - dis)
        d.append(dis)
    time_s = None
    if "time_s" in rows.columns and len(rows):
        v = pd.to_numeric(rows["time_s"], errors="coerce").dropna()
        time_s = float(v.iloc[0]) if len(v) else None
    return MarkerFrame(int(frame), time_s, names, np.array(X, dtype=float).reshape(-1, 3),
                       np.array(d, dtype=float).reshape(-1, 3), skipped)


def model_at_points(locator, nodal_u_mm, points_mm, *, outside_tol_mm: float = 0.0):
    """FE displacements (p, 3) at ``points_mm`` (p, 3) and where each point lies.

    ``nodal_u_mm`` (n_nodes, 3) in the locator's node order (NaN for nodes without a result:
    a point in an element with such a node gets NaN).  Returns ``(u, location)``.
    """
    loc = locator.locate(points_mm, outside_tol_mm=outside_tol_mm)
    return locator.interpolate(nodal_u_mm, loc), loc


@dataclass
class CompareResult:
    """Table 1 (``marker, axis, model_mm, measured_mm, diff_mm``), Table 2 (``quantity, max_mm,
    min_mm, mean_mm, mean_signed_mm, rms_mm``), ``sigma_mm`` and per-marker errors."""

    table1: pd.DataFrame
    table2: pd.DataFrame
    sigma_mm: float
    sigma_axis_mm: dict
    error_mm: dict
    n: int


def compare_displacements(names, model_mm, measured_mm) -> CompareResult:
    """Tables 1 and 2 and sigma for markers ``names`` with model and measured displacements (n, 3).

    >>> r = compare_displacements(["A", "B"], [[1.0, 0, 0], [0, 2.0, 0]], [[0.5, 0, 0], [0, 2.0, 1.0]])
    >>> r.table2.set_index("quantity").loc["magnitude", ["max_mm", "min_mm", "mean_mm"]].tolist()
    [1.0, 0.5, 0.75]
    >>> round(r.sigma_mm, 12) == round(float(np.sqrt((0.25 + 1.0) / 2)), 12)
    True
    """
    names = [str(n) for n in names]
    model = np.asarray(model_mm, dtype=float).reshape(-1, 3)
    meas = np.asarray(measured_mm, dtype=float).reshape(-1, 3)
    if not (len(names) == len(model) == len(meas)):
        raise ValueError("names, model and measured differ in length")
    if len(names) == 0:
        raise ValueError("no marker to compare")
    diff = model - meas
    rows = [{"marker": n, "axis": a, "model_mm": model[i, k], "measured_mm": meas[i, k], "diff_mm": diff[i, k]}
            for i, n in enumerate(names) for k, a in enumerate(AXES)]
    table1 = pd.DataFrame(rows, columns=["marker", "axis", "model_mm", "measured_mm", "diff_mm"])
    mag = np.linalg.norm(diff, axis=1)
    t2 = []
    for k, a in enumerate(AXES):
        e = np.abs(diff[:, k])
        t2.append({"quantity": a, "max_mm": e.max(), "min_mm": e.min(), "mean_mm": e.mean(),
                   "mean_signed_mm": diff[:, k].mean(), "rms_mm": float(np.sqrt(np.mean(diff[:, k] ** 2)))})
    t2.append({"quantity": "magnitude", "max_mm": mag.max(), "min_mm": mag.min(), "mean_mm": mag.mean(),
               "mean_signed_mm": mag.mean(), "rms_mm": float(np.sqrt(np.mean(mag ** 2)))})
    table2 = pd.DataFrame(t2, columns=["quantity", "max_mm", "min_mm", "mean_mm", "mean_signed_mm", "rms_mm"])
    sigma = float(np.sqrt(np.sum(mag ** 2) / len(mag)))
    sig_axis = {a: float(np.sqrt(np.mean(diff[:, k] ** 2))) for k, a in enumerate(AXES)}
    return CompareResult(table1, table2, sigma, sig_axis, {n: float(e) for n, e in zip(names, mag)}, len(names))
