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

Which frame, which FE result: the measured frame defaults to the peak of the indentation
(:func:`peak_frame_info`: the largest mean displacement over the markers tracked with at
most short gaps, so one marker lost in one frame does not move it), and the FE result is the
one at the same time on the FE clock when both clocks are known, else, for the peak frame,
the FE result of the largest mean model displacement at the compared markers
(:func:`choose_fe_result`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

__all__ = ["MarkerFrame", "markers_at_frame", "PeakFrame", "peak_frame_info", "peak_frame", "model_at_points",
           "FEResultChoice", "choose_fe_result", "CompareResult", "compare_displacements"]

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


@dataclass
class PeakFrame:
    """The peak frame and how it was found: ``markers`` whose displacements picked it,
    ``filled`` (marker -> frames where it was missing, filled by linear interpolation in
    frame), ``left_out`` (marker -> why it did not take part) and ``method``."""

    frame: int
    markers: list[str]
    filled: dict[str, list[int]]
    left_out: dict[str, str]
    method: str

    def to_dict(self) -> dict:
        return {"frame": self.frame, "markers": self.markers, "filled_frames": self.filled,
                "left_out": self.left_out, "method": self.method}


def _runs(missing: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` index ranges of the True runs of ``missing``."""
    edges = np.diff(np.concatenate([[0], missing.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def peak_frame_info(table: pd.DataFrame, markers=None, *, max_gap_frames: int = 2) -> PeakFrame:
    """The frame with the largest mean displacement magnitude over ``markers`` (default: all
    non-reference markers): where an FE run to the peak of the indentation is compared.

    The mean is taken over the same markers in every frame, so a marker lost in the peak
    frame does not move the peak: the markers found in every frame, and those whose gaps
    are at most ``max_gap_frames`` consecutive frames long (filled by linear interpolation
    of the magnitude in frame, held at the ends).  A marker with a longer gap takes no part.
    Only when no marker qualifies is the mean taken over the markers present in each frame
    (``method`` says so).

    >>> t = pd.DataFrame({"frame": [0, 0, 1, 1, 2, 2], "marker": list("ABABAB"),
    ...                   "dx_mm": [0, 0, 1.0, np.nan, 0.5, 3.0], "dy_mm": 0.0, "dz_mm": 0.0})
    >>> info = peak_frame_info(t)
    >>> info.frame, info.filled
    (2, {'B': [1]})
    """
    t = _select(table, markers)
    mag = np.sqrt(t["dx_mm"] ** 2 + t["dy_mm"] ** 2 + t["dz_mm"] ** 2)
    wide = mag.groupby([t["frame"], t["marker"].astype(str)]).mean().unstack()
    frames = np.array(sorted(table["frame"].unique()))
    wide = wide.reindex(frames)
    if not np.isfinite(wide.to_numpy(float)).any():
        raise ValueError("no frame has a finite displacement")
    used, filled, left_out, columns = [], {}, {}, []
    for m in wide.columns:
        v = wide[m].to_numpy(float)
        missing = ~np.isfinite(v)
        if missing.all():
            seen = int(np.isfinite(pd.to_numeric(t.loc[t["marker"].astype(str) == m, "x_mm"], errors="coerce")).sum()) \
                if "x_mm" in t.columns else 0
            left_out[m] = ("never found" if not seen else
                           f"found in {seen} frames but not in the registration frame, which its displacements are "
                           "measured from: none in any frame")
            continue
        longest = max((b - a for a, b in _runs(missing)), default=0)
        if longest > max_gap_frames:
            left_out[m] = f"missing in {int(missing.sum())} frames, up to {longest} in a row"
            continue
        if missing.any():
            v = v.copy()
            v[missing] = np.interp(frames[missing], frames[~missing], v[~missing])
            filled[m] = [int(f) for f in frames[missing]]
        used.append(m)
        columns.append(v)
    if used:
        mean = np.mean(columns, axis=0)
        method = (f"largest mean displacement over the markers found in every frame or with gaps of at most "
                  f"{max_gap_frames} frames (filled by linear interpolation in frame)")
        return PeakFrame(int(frames[int(np.argmax(mean))]), used, filled, left_out, method)
    per = wide.mean(axis=1, skipna=True).dropna()
    method = (f"largest mean displacement over the markers present in each frame (every marker has a gap longer "
              f"than {max_gap_frames} frames)")
    return PeakFrame(int(per.idxmax()), [], {}, left_out, method)


def peak_frame(table: pd.DataFrame, markers=None) -> int:
    """The frame of :func:`peak_frame_info`."""
    return peak_frame_info(table, markers).frame


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
    else:
        for m in sorted(set(t["marker"].astype(str)) - set(rows["marker"].astype(str))):
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
class FEResultChoice:
    """The FE result compared with the measured frame: its 0-based ``index``, ``why``, the
    FE time it should have had (``target_fe_time``, None when the clocks are not tied) and
    ``warnings`` (the two could not be matched, or only roughly)."""

    index: int
    why: str
    target_fe_time: float | None = None
    warnings: list[str] = field(default_factory=list)


def choose_fe_result(n_results: int, *, given: int | None = None, fe_times=None,
                     target_fe_time: float | None = None, time_tol: float = 0.0,
                     peak_values=None, frame_is_peak: bool = False,
                     clock_zero: float | None = None) -> FEResultChoice:
    """Which of ``n_results`` FE results (file order) to set against the measured frame.

    In order: ``given`` (0-based, negative from the end); the only one (with a warning when
    nothing ties it to a measured frame other than the peak); the FE result whose
    time ``fe_times`` (n,) is nearest ``target_fe_time`` (the measured frame's time on the FE
    clock), with a warning when it is more than ``time_tol`` away or outside the results'
    span; for the peak frame (``frame_is_peak``), the result of the largest ``peak_values``
    (n,: the mean model displacement at the compared markers); else the last, with a warning.
    A result chosen by time for the peak frame that is not the FE results' peak (more than 10 %
    less mean displacement, the peak more than ``time_tol`` away) is warned: the FE times run
    on another clock; ``clock_zero`` (the marker clock's time of FE time 0, FE units), when the
    offset matches it, names the marker clock.

    >>> choose_fe_result(3, fe_times=[1.0, 2.0, 3.0], target_fe_time=2.1, time_tol=0.25).index
    1
    >>> choose_fe_result(3, peak_values=[1.0, 4.0, 0.5], frame_is_peak=True).index
    1
    """
    times = None if fe_times is None else np.asarray(fe_times, dtype=float)
    timed = times is not None and target_fe_time is not None and bool(np.all(np.isfinite(times)))
    if given is not None:
        if not -n_results <= int(given) < n_results:
            raise ValueError(f"FE result {given} asked for; the file holds {n_results} (0..{n_results - 1}, or "
                             f"-1..-{n_results} from the end)")
        k = int(given) % n_results
        # every result's time, or only the given one's (the caller read that result alone)
        t = np.nan if times is None else times[k] if len(times) == n_results else times[0] if len(times) == 1 \
            else np.nan
        warnings = []
        if target_fe_time is not None and np.isfinite(t) and abs(t - target_fe_time) > time_tol:
            warnings.append(_gap_warning("the FE result given", t, target_fe_time, time_tol))
        return FEResultChoice(k, "given (--fe-result)", target_fe_time, warnings)
    elif n_results == 1:
        k, why = 0, "the file holds one result"
    elif timed:
        k = int(np.argmin(np.abs(times - target_fe_time)))
        why = f"nearest in time to the measured frame (FE time {target_fe_time:.6g})"
    elif frame_is_peak and peak_values is not None and np.isfinite(np.asarray(peak_values, dtype=float)).any():
        k = int(np.nanargmax(np.asarray(peak_values, dtype=float)))
        why = ("the measured frame is the peak: the FE result of the largest mean model displacement at the "
               "compared markers")
    else:
        return FEResultChoice(n_results - 1, "the last (the FE results cannot be matched to the measured frame)",
                              target_fe_time,
                              [f"cannot tell which of the {n_results} FE results belongs to the measured frame "
                               f"(no FE time tied to the marker clock, and the frame is not the peak); compared "
                               f"the last: choose one with --fe-result"])
    warnings = []
    if n_results == 1 and given is None and not timed and not frame_is_peak:
        warnings.append("the FE file holds one result without a time tied to the marker clock, and the measured "
                        "frame is not the peak: nothing shows that they belong together")
    if timed:
        gap = abs(float(times[k]) - target_fe_time)
        if target_fe_time < times.min() - time_tol or target_fe_time > times.max() + time_tol:
            warnings.append(f"the measured frame's FE time {target_fe_time:.6g} is outside the FE results' "
                            f"{times.min():.6g}..{times.max():.6g}; compared the FE result at {times[k]:.6g}")
        elif gap > time_tol:
            warnings.append(_gap_warning("the compared FE result", float(times[k]), target_fe_time, time_tol)
                            + ": write FE results more often or choose another frame")
        pv = None if peak_values is None else np.asarray(peak_values, dtype=float)
        if frame_is_peak and pv is not None and len(pv) == len(times) and np.isfinite(pv).any():
            # the measured frame is the markers' peak: the FE result at its time should be the
            # model's.  FE times written on the X-ray clock had been matched to the wrong result
            # (0.82 of the peak's displacement, sigma 1.20 mm against 1.54), unsaid
            p = int(np.nanargmax(pv))
            off = float(times[p]) - target_fe_time
            if p != k and pv[k] < 0.9 * pv[p] and abs(off) > time_tol:
                hint = ""
                if clock_zero is not None and abs(off - clock_zero) <= max(time_tol, 1e-9 * abs(clock_zero)):
                    hint = (f"; the offset is the X-ray time of FE time 0 in the deck's header ({clock_zero:.6g}): "
                            "the FE results' times look counted on the X-ray clock")
                warnings.append(
                    f"the FE result at the measured (peak) frame's FE time ({times[k]:.6g}, mean model displacement "
                    f"{pv[k]:.3g} mm) is not the FE results' peak (FE time {times[p]:.6g}, {pv[p]:.3g} mm), "
                    f"{abs(off):.3g} {'later' if off > 0 else 'earlier'}: the FE results' times do not follow the "
                    f"deck's clock (shifted or scaled){hint}; compare result {p} with --fe-result {p} if so")
    return FEResultChoice(k, why, target_fe_time, warnings)


def _gap_warning(what: str, fe_time: float, target_fe_time: float, time_tol: float) -> str:
    return (f"{what} (FE time {fe_time:.6g}) is {abs(fe_time - target_fe_time):.3g} from the measured frame's FE "
            f"time {target_fe_time:.6g} (tolerance {time_tol:.3g}, half a frame interval)")


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
