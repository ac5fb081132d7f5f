r"""The FE hand-off (``bsipipe export-fe``): pure numerics over plain arrays.

What is computed here, from values the command has read:

**Indentor trajectory, two ways.**  *From the X-ray*: the indentor's tracked points mapped
into the CT (FE) frame by the registration, :math:`\mathbf y = sR\mathbf x + \mathbf t`; their
centroid :math:`\mathbf c_i` in frame *i*, the tip :math:`\mathbf p_i = \mathbf c_i + o\,\mathbf a`
(``tip_offset_mm`` *o* along the unit direction of indentation :math:`\mathbf a`).  *From the
machine*: the crosshead travel :math:`e(t)` (positive in compression, from the log's first
sample) places the tip at :math:`\mathbf p(t) = \mathbf P_0 + e(t)\,\mathbf a`, the indentor
being a rigid body driven along a straight line.  The two are tied by the model

.. math::

    \mathbf c_i \approx \mathbf C_0 + e(t_i - \Delta)\,\mathbf a,

with :math:`\Delta` the clock offset (X-ray time = log time + :math:`\Delta`).  For a given
:math:`\Delta` the model is linear: :math:`\mathbf a` is the least-squares slope of the
centroids on the travel (its length, :math:`|\mathbf a|`, is the X-ray travel per log
millimetre, 1 when registration scale and machine agree) and :math:`\mathbf C_0` the mean of
:math:`\mathbf c_i - e_i \hat{\mathbf a}`; :math:`\Delta` minimises the residual sum of squares
(a grid of a quarter of the finer sampling interval, at most 4000 points, over every
overlap, then a bounded scalar search), unless the config gives it.  The travel is held at its first/last value
outside the log (the machine at rest).  The difference between the two trajectories,
:math:`|\mathbf p_i - \mathbf P_0 - e(t_i - \Delta)\hat{\mathbf a}|`, is reported (RMS and
maximum, mm) over the frames during contact and over the whole log.

**Contact and the FE amplitude.**  Contact is detected on the log
(:func:`bsipipe.mechanics.contact.detect_contact`) at travel :math:`e_c`, time :math:`t_c`;
FE time starts there.  The amplitude is the depth after contact
:math:`d(\tau) = e(t_c + \tau) - e_c` until the indentor leaves the surface again
(:math:`e \le e_c`) or the log ends, reduced to the knots needed to stay within a tolerance
(Ramer-Douglas-Peucker on the vertical distance).  The contact point (the centre of the
indentor's flat end on the brain surface, CT frame) is :math:`\mathbf P_0 + e_c\hat{\mathbf a}`.

**Springs.**  Stiffness per spring :math:`k_s = k\,A / n` (``k`` in N/mm per mm^2, the area
in mm^2, ``n`` springs).

:func:`build_handoff` computes all of it in mm, s and N (CT frame) from values already read;
:func:`render_files` converts to the decks' unit system and calls the ABAQUS, LS-DYNA and FEBio
writers of :mod:`bsipipe.io`.  Neither reads or writes a file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

__all__ = ["spring_stiffness_n_per_mm", "LogRecord", "ContactWindow", "contact_window", "Alignment",
           "fit_alignment", "trajectory_difference", "simplify_polyline", "amplitude_from_log",
           "amplitude_from_xray", "force_target", "ramp_holds", "ramp_speed_mm_per_min", "indentor_centroids",
           "marker_table", "marker_element_nodes", "sliding_anchor_equations", "DifferenceStats",
           "turning_points", "HandoffError", "Handoff", "build_handoff", "OutputFile", "render_files", "deck_increments"]


def spring_stiffness_n_per_mm(stiffness_n_per_mm_per_mm2: float, area_mm2: float, n_springs: int) -> float:
    """Stiffness of one spring, ``k x A / n`` (N/mm).

    >>> round(spring_stiffness_n_per_mm(11.45, 5240.0, 5240), 12)
    11.45
    """
    if not (stiffness_n_per_mm_per_mm2 > 0 and area_mm2 > 0 and n_springs > 0):
        raise ValueError("interface stiffness, area and number of springs must be positive")
    return float(stiffness_n_per_mm_per_mm2) * float(area_mm2) / int(n_springs)


@dataclass(frozen=True)
class LogRecord:
    """A machine record as the hand-off needs it: ``time_s`` (n,), ``travel_mm`` (n,) from
    the first sample, positive in compression, ``force_n`` (n,) positive in compression."""

    time_s: np.ndarray
    travel_mm: np.ndarray
    force_n: np.ndarray
    segment: np.ndarray | None = None


@dataclass(frozen=True)
class ContactWindow:
    """Contact at ``time_s``/``travel_mm`` (sample ``index``), lost at ``end_time_s`` (the log's
    last time when it is not lost: ``lost`` False); ``baseline_n`` the force before contact;
    ``method`` how the contact was found; ``peak_index`` the deepest sample;
    ``travel_sd_mm`` the contact travel's standard deviation (0 when given)."""

    index: int
    time_s: float
    travel_mm: float
    end_time_s: float
    lost: bool
    baseline_n: float
    method: str
    peak_index: int
    travel_sd_mm: float = 0.0

    @property
    def duration_s(self) -> float:
        return self.end_time_s - self.time_s


def contact_window(log: LogRecord, *, contact_mm: float | None = None) -> ContactWindow:
    """Where the indentor meets the brain and where it leaves it again.

    Contact from :func:`~bsipipe.mechanics.contact.detect_contact` unless ``contact_mm`` is
    given (then at the first crossing of that travel, baseline from the samples before).
    """
    from ..mechanics.contact import detect_contact

    t, e, f = log.time_s, log.travel_mm, log.force_n
    if contact_mm is None:
        c = detect_contact(t, e, f)
        idx, tc, ec, base, method = c.index, c.time_s, c.displacement_mm, c.baseline_n, c.method
        sd = float(c.displacement_sd_mm)
    else:
        sd = 0.0
        above = np.flatnonzero(e >= contact_mm)
        if not above.size:
            raise ValueError(f"the travel never reaches contact_mm = {contact_mm} mm")
        idx = int(above[0])
        ec = float(contact_mm)
        tc = float(t[idx]) if idx == 0 else float(np.interp(ec, [e[idx - 1], e[idx]], [t[idx - 1], t[idx]]))
        base = float(np.median(f[:idx])) if idx > 0 else 0.0
        method = "given (config log.contact_mm)"
    peak = int(np.argmax(e))
    after = np.flatnonzero(e[peak:] <= ec)
    if after.size:
        k = peak + int(after[0])
        t_end = float(np.interp(ec, [e[k], e[k - 1]], [t[k], t[k - 1]])) if e[k - 1] != e[k] else float(t[k])
        lost = True
    else:
        t_end, lost = float(t[-1]), False
    return ContactWindow(int(idx), float(tc), float(ec), t_end, lost, float(base), method, peak, sd)


#: A stretch of the loading ramp where the crosshead moves at less than this fraction of its
#: median speed, for at least :data:`HOLD_MIN_S`, is a hold (:func:`ramp_holds`).
HOLD_SPEED_FRACTION = 0.2
HOLD_MIN_S = 1.0


def ramp_holds(log: LogRecord, window: ContactWindow) -> list[dict]:
    """Holds between contact and the deepest point: runs of samples where the crosshead moves
    at less than :data:`HOLD_SPEED_FRACTION` of its median loading speed for at least
    :data:`HOLD_MIN_S` s (``start_s``, ``duration_s``, ``travel_mm`` past contact)."""
    sl = slice(window.index, window.peak_index + 1)
    t, e = log.time_s[sl], log.travel_mm[sl]
    if len(t) < 3:
        return []
    dt, de = np.diff(t), np.diff(e)
    v = np.divide(de, dt, out=np.zeros_like(de), where=dt > 0)
    pos = v[v > 0]
    if not len(pos):
        return []
    slow = v < HOLD_SPEED_FRACTION * float(np.median(pos))
    # runs of slow steps: step a..b-1 spans samples a..b (as fit-ogden's _loading_speed finds
    # its holds, there by step count)
    edges = np.flatnonzero(np.diff(np.r_[0, slow.astype(np.int8), 0]))
    return [{"start_s": float(t[a]), "duration_s": float(t[b] - t[a]), "travel_mm": float(e[a] - window.travel_mm)}
            for a, b in zip(edges[::2], edges[1::2]) if t[b] - t[a] >= HOLD_MIN_S]


def ramp_speed_mm_per_min(log: LogRecord, window: ContactWindow, holds: list[dict] | None = None) -> float:
    """Crosshead speed while loading after contact: the least-squares slope of travel on time,
    over the moving samples only where the ramp holds (:func:`ramp_holds`): each moving stretch
    its own intercept, one common slope (a 3 s pause had been averaged in: 9.995 mm/min for a
    12 mm/min ramp, a failed speed check that never named the pause).  ``holds``: the ramp's
    holds where the caller has them already."""
    sl = slice(window.index, window.peak_index + 1)
    t, e = log.time_s[sl], log.travel_mm[sl]
    if len(t) < 2:
        raise ValueError("fewer than two samples between contact and the deepest point")
    holds = ramp_holds(log, window) if holds is None else holds
    if not holds:
        return float(np.polyfit(t, e, 1)[0] * 60.0)
    seg = np.zeros(len(t), int)
    held = np.zeros(len(t), bool)
    for h in holds:
        inside = (t > h["start_s"]) & (t < h["start_s"] + h["duration_s"])
        held |= inside
        seg[t >= h["start_s"] + h["duration_s"]] += 1
    keep = ~held
    tk, ek, sk = t[keep], e[keep], seg[keep]
    # one slope, an intercept per moving stretch: centre each stretch and pool
    num = den = 0.0
    for g in np.unique(sk):
        m = sk == g
        if m.sum() < 2:
            continue
        tc, ec = tk[m] - tk[m].mean(), ek[m] - ek[m].mean()
        num += float(tc @ ec)
        den += float(tc @ tc)
    if not den > 0:
        return float(np.polyfit(t, e, 1)[0] * 60.0)
    return num / den * 60.0


# --- the X-ray indentor and the alignment -----------------------------------------------------

def indentor_centroids(table: pd.DataFrame, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames where every named point is found: ``(frames (F,), time_s (F,), centroid (F, 3))``.

    ``table`` has columns ``frame, time_s, marker, x_mm, y_mm, z_mm`` (one frame of reference).
    """
    names = list(names)
    sub = table[table["marker"].isin(names)]
    sub = sub[sub[["x_mm", "y_mm", "z_mm"]].notna().all(axis=1)]
    counts = sub.groupby("frame")["marker"].nunique()
    full = counts.index[counts.to_numpy() == len(names)]
    sub = sub[sub["frame"].isin(full)]
    g = sub.groupby("frame")
    xyz = g[["x_mm", "y_mm", "z_mm"]].mean().sort_index()
    time = g["time_s"].first().reindex(xyz.index)
    return xyz.index.to_numpy(np.int64), time.to_numpy(float), xyz.to_numpy(float)


@dataclass(frozen=True)
class Alignment:
    """The X-ray indentor track tied to the log (module docstring).

    ``clock_offset_s`` (X-ray time = log time + offset) and how it was found
    (``clock_offset_source``), ``axis`` unit direction of indentation (CT frame) and where
    it came from, ``rest_centroid_mm`` :math:`\\mathbf C_0`, ``travel_ratio`` :math:`|\\mathbf a|`
    along ``axis`` (X-ray mm per log mm), ``rms_residual_mm`` of the fit.
    """

    clock_offset_s: float
    clock_offset_source: str
    axis: np.ndarray
    axis_source: str
    rest_centroid_mm: np.ndarray
    travel_ratio: float
    rms_residual_mm: float
    n_frames: int
    #: other clock offsets that fit the X-ray motion as well (within 2 noise sd of chi^2), e.g. a
    #: record that sees only a stretch of a ramp-unload log that the unloading mirrors: each
    #: ``{"clock_offset_s", "rms_residual_mm", "brain_ahead_mm"}``; empty when the fit is unique
    alternatives: tuple = ()
    #: how the offset was chosen among equally good ones (None when it was unique)
    choice: str | None = None


def _travel_at(t_xray, offset, log: LogRecord) -> np.ndarray:
    return np.interp(np.asarray(t_xray, float) - offset, log.time_s, log.travel_mm)


def _regress(P: np.ndarray, e: np.ndarray, axis: np.ndarray | None):
    """Slope vector ``a`` (3,), intercept ``C0`` (3,) and SSE of ``P ~ C0 + e a``."""
    eb = e.mean()
    de = e - eb
    var = float(de @ de)
    if axis is None:
        a = (de @ (P - P.mean(axis=0))) / var if var > 0 else np.zeros(3)
    else:
        a = axis
    C0 = (P - e[:, None] * a).mean(axis=0)
    r = P - C0 - e[:, None] * a
    return a, C0, float(np.sum(r * r))


def _local_minima(costs: np.ndarray, within: float) -> list[int]:
    """Indices of the grid's local minima (one per flat run) whose cost is within ``within`` of
    the lowest."""
    best = float(np.min(costs))
    out, k, n = [], 0, len(costs)
    while k < n:
        j = k
        while j + 1 < n and costs[j + 1] == costs[k]:
            j += 1
        left = costs[k - 1] if k > 0 else np.inf
        right = costs[j + 1] if j + 1 < n else np.inf
        if costs[k] <= left and costs[k] <= right and costs[k] <= best + within:
            out.append((k + j) // 2)
        k = j + 1
    return out


def fit_alignment(t_xray, centroids_mm, log: LogRecord, *, clock_offset_s: float | None = None,
                  axis=None, ahead_mm=None) -> Alignment:
    """Fit the clock offset, the direction of indentation and the rest position (module
    docstring) to the X-ray centroids ``centroids_mm`` (F, 3) at ``t_xray`` (F,).

    ``axis`` (CT frame, any length) fixes the direction; ``clock_offset_s`` the offset.
    ``ahead_mm`` (k, 3): points that lie ahead of the indentor along its direction of travel
    (the implanted markers, inside the brain it presses).  Where several offsets fit the
    motion equally well (a ramp and the unloading that mirrors it, seen over a stretch that
    holds no asymmetric part of the log), the direction of indentation flips between them;
    the one that has ``ahead_mm`` in front of the indentor is taken (``choice``), and the
    others are kept in ``alternatives``.
    """
    t = np.asarray(t_xray, float)
    P = np.asarray(centroids_mm, float)
    if len(t) < 3 or not np.all(np.isfinite(t)):
        raise ValueError("the X-ray track needs at least three frames with finite times")
    fixed_axis = None if axis is None else np.asarray(axis, float) / np.linalg.norm(axis)

    def sse(off: float) -> float:
        return _regress(P, _travel_at(t, off, log), fixed_axis)[2]

    if clock_offset_s is None:
        dt_log = float(np.median(np.diff(log.time_s)))
        dt_x = float(np.median(np.diff(t))) if len(t) > 1 else dt_log
        lo, hi = t.min() - log.time_s.max(), t.max() - log.time_s.min()
        # a quarter of the finer sampling, coarsened for long records (then refined locally)
        h = max(min(dt_log, dt_x) / 4.0, (hi - lo) / 4000.0)
        grid = np.arange(lo, hi + h, h)
        costs = np.array([sse(o) for o in grid])

        def refine(g0: float) -> tuple[float, float]:
            res = minimize_scalar(sse, bounds=(g0 - h, g0 + h), method="bounded",
                                  options={"xatol": 1e-6 * max(h, 1e-9)})
            return (float(res.x), float(res.fun)) if res.fun <= sse(g0) else (g0, sse(g0))

        # every minimum as good as the best within 2 noise sd of chi^2 (noise from the best fit:
        # 3F residuals, 7 parameters), each refined
        s2 = float(np.min(costs)) / max(3 * len(t) - 7, 1)
        cands = sorted((refine(float(grid[k])) for k in _local_minima(costs, 4.0 * s2)), key=lambda c: c[1])
        cands = [c for c in cands if c[1] <= cands[0][1] + 4.0 * s2]
        offset = cands[0][0]
        source = "fitted to the X-ray motion"
        if fixed_axis is None and len(cands) > 1:
            def ahead(off: float) -> float:
                if ahead_mm is None or not len(ahead_mm):
                    return float("nan")
                a, C0, _ = _regress(P, _travel_at(t, off, log), None)
                n = np.linalg.norm(a)
                return float(np.median((np.asarray(ahead_mm, float) - C0) @ (a / n))) if n > 0 else float("nan")
            scored = [(o, f, ahead(o)) for o, f in cands]
            front = [c for c in scored if c[2] > 0]
            if len(front) == 1:
                offset = front[0][0]
                choice = ("the only one of the offsets that fit equally well with the implanted markers ahead of "
                          "the indentor (the others reverse its direction of travel)")
            else:
                choice = ("ambiguous: offsets that fit equally well, the lowest residual taken; give "
                          "log.clock_offset_s (the markers ahead of the indentor do not tell them apart)")
            alternatives = tuple({"clock_offset_s": o, "rms_residual_mm": float(np.sqrt(f / len(t))),
                                  "brain_ahead_mm": b} for o, f, b in scored if o != offset)
        else:
            choice, alternatives = None, ()
    else:
        offset, source = float(clock_offset_s), "given (config log.clock_offset_s)"
        choice, alternatives = None, ()
    e = _travel_at(t, offset, log)
    if float(np.ptp(e)) <= 0:
        raise ValueError("the log does not move while the X-ray frames are recorded (check the clock offset)")
    a_free, _, _ = _regress(P, e, None)
    if fixed_axis is None:
        if not np.linalg.norm(a_free) > 0:
            raise ValueError("the indentor does not move in the X-ray frames")
        unit = a_free / np.linalg.norm(a_free)
        axis_source = "fitted to the X-ray motion (slope of the indentor's position on the log travel)"
    else:
        unit = fixed_axis
        axis_source = "given (config indentor.axis_xray / pose_xray.axis, rotated into the CT frame)"
    _, C0, s = _regress(P, e, unit)
    return Alignment(offset, source, unit, axis_source, C0, float(a_free @ unit),
                     float(np.sqrt(s / len(t))), int(len(t)), alternatives, choice)


@dataclass(frozen=True)
class DifferenceStats:
    """``|p_xray - p_log|`` over ``n_frames`` frames: ``rms_mm``, ``max_mm``, the RMS of the
    part along the axis and across it, and the frame of the maximum."""

    n_frames: int
    rms_mm: float
    max_mm: float
    along_axis_rms_mm: float
    across_axis_rms_mm: float
    frame_of_max: int | None

    def to_dict(self) -> dict:
        return {"n_frames": self.n_frames, "rms_mm": self.rms_mm, "max_mm": self.max_mm,
                "along_axis_rms_mm": self.along_axis_rms_mm, "across_axis_rms_mm": self.across_axis_rms_mm,
                "frame_of_max": self.frame_of_max}


def trajectory_difference(frames, diff_mm: np.ndarray, axis: np.ndarray, mask: np.ndarray) -> DifferenceStats:
    """Statistics of the difference vectors ``diff_mm`` (F, 3) over the frames in ``mask``."""
    d = np.asarray(diff_mm, float)[mask]
    if not len(d):
        return DifferenceStats(0, float("nan"), float("nan"), float("nan"), float("nan"), None)
    mag = np.linalg.norm(d, axis=1)
    along = d @ axis
    across = np.linalg.norm(d - along[:, None] * axis, axis=1)
    k = int(np.argmax(mag))
    return DifferenceStats(int(len(d)), float(np.sqrt(np.mean(mag ** 2))), float(mag.max()),
                           float(np.sqrt(np.mean(along ** 2))), float(np.sqrt(np.mean(across ** 2))),
                           int(np.asarray(frames)[mask][k]))


# --- amplitude, target, markers ---------------------------------------------------------------

def simplify_polyline(x, y, tol: float) -> np.ndarray:
    """Indices of the points of ``(x, y)`` that keep the piecewise-linear curve within
    ``tol`` (vertical distance) of every dropped point (Ramer-Douglas-Peucker).

    >>> simplify_polyline([0, 1, 2, 3, 4], [0, 1, 2, 1, 0], 1e-9).tolist()
    [0, 2, 4]
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    keep = np.zeros(len(x), bool)
    keep[[0, -1]] = True
    stack = [(0, len(x) - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        xs, ys = x[i + 1:j], y[i + 1:j]
        chord = y[i] + (y[j] - y[i]) * (xs - x[i]) / (x[j] - x[i])
        err = np.abs(ys - chord)
        k = int(np.argmax(err))
        if err[k] > tol:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return np.flatnonzero(keep)


def _knots(tau: np.ndarray, depth: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(tau, kind="stable")
    tau, depth = tau[order], depth[order]
    _, first = np.unique(tau, return_index=True)
    tau, depth = tau[first], depth[first]
    keep = simplify_polyline(tau, depth, tol)
    return tau[keep], depth[keep]


def amplitude_from_log(log: LogRecord, window: ContactWindow, tol_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """``(tau_s, depth_mm)``: depth after contact from the log, FE time from contact."""
    t, e = log.time_s, log.travel_mm
    inside = (t > window.time_s) & (t < window.end_time_s)
    tau = np.concatenate([[0.0], t[inside] - window.time_s, [window.duration_s]])
    end_depth = 0.0 if window.lost else float(e[-1] - window.travel_mm)
    depth = np.concatenate([[0.0], e[inside] - window.travel_mm, [end_depth]])
    return _knots(tau, np.maximum(depth, 0.0), tol_mm)


def amplitude_from_xray(t_xray, tip_mm, contact_point_mm, axis, clock_offset_s: float, window: ContactWindow,
                        tol_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """``(tau_s, depth_mm)``: depth after contact from the X-ray tip positions (F, 3)."""
    tau_all = np.asarray(t_xray, float) - clock_offset_s - window.time_s
    depth_all = (np.asarray(tip_mm, float) - contact_point_mm) @ axis
    inside = (tau_all > 0) & (tau_all < window.duration_s)
    end_depth = 0.0 if window.lost else float(np.interp(window.duration_s, tau_all, depth_all))
    tau = np.concatenate([[0.0], tau_all[inside], [window.duration_s]])
    depth = np.concatenate([[0.0], depth_all[inside], [end_depth]])
    return _knots(tau, np.maximum(depth, 0.0), tol_mm)


def turning_points(value) -> np.ndarray:
    """Indices of the knots where a piecewise-linear curve changes direction (rising,
    flat, falling), and of its last knot: where FE steps end so the solver meets every
    extreme of the amplitude.

    >>> turning_points([0.0, 1.0, 2.0, 2.0, 0.5, 0.0]).tolist()
    [2, 3, 5]
    """
    v = np.asarray(value, float)
    sign = np.sign(np.diff(v))
    change = np.flatnonzero(sign[1:] != sign[:-1]) + 1
    return np.append(change, len(v) - 1)


def force_target(log: LogRecord, window: ContactWindow) -> pd.DataFrame:
    """The contact-zeroed force-displacement curve over the contact window:
    ``log_time_s, time_s`` (from contact), ``indentation_mm`` (travel - contact travel),
    ``force_n`` (force - baseline before contact) and ``segment`` where the log has one."""
    t = log.time_s
    sel = (np.arange(len(t)) >= window.index) & (t <= window.end_time_s + 1e-12)
    out = pd.DataFrame({"log_time_s": t[sel], "time_s": t[sel] - window.time_s,
                        "indentation_mm": log.travel_mm[sel] - window.travel_mm,
                        "force_n": log.force_n[sel] - window.baseline_n})
    if log.segment is not None:
        out["segment"] = np.asarray(log.segment)[sel]
    return out


def marker_table(markers_ct: pd.DataFrame, exclude, contact_time_xray_s: float) -> pd.DataFrame:
    """Markers in the FE frame: initial positions (``x0_mm`` = ``x_mm - dx_mm`` ...: the
    registration frame), positions and displacements per frame, and ``fe_time_s`` (X-ray time
    minus the time of contact on the X-ray clock)."""
    t = markers_ct[~markers_ct["marker"].isin(list(exclude))].copy()
    out = pd.DataFrame({"frame": t["frame"].to_numpy(), "time_s": t["time_s"].to_numpy(float),
                        "fe_time_s": t["time_s"].to_numpy(float) - contact_time_xray_s,
                        "marker": t["marker"].to_numpy(),
                        "role": t["role"].to_numpy() if "role" in t.columns else "marker"})
    for ax in "xyz":
        out[f"{ax}0_mm"] = (t[f"{ax}_mm"] - t[f"d{ax}_mm"]).to_numpy(float)
    for ax in "xyz":
        out[f"{ax}_mm"] = t[f"{ax}_mm"].to_numpy(float)
    for ax in "xyz":
        out[f"d{ax}_mm"] = t[f"d{ax}_mm"].to_numpy(float)
    return out.sort_values(["frame", "marker"], kind="stable").reset_index(drop=True)


def marker_element_nodes(mesh, markers: pd.DataFrame, *, outside_tol_mm: float = 1.0
                         ) -> tuple[np.ndarray, list[str], list[str]]:
    """The nodes (labels, sorted) of the elements that hold the markers' initial positions
    (``x0_mm, y0_mm, z0_mm`` of :func:`marker_table`; rows of role ``reference`` or
    ``xray-only`` are left out), or of the nearest element within ``outside_tol_mm``: what
    ``bsipipe compare`` interpolates, so the deck prints their displacements.  Returns
    ``(node labels, markers in the mesh, markers outside it)``."""
    from ..geometry.shape_functions import PointLocator

    t = markers[~markers["role"].astype(str).isin(["reference", "xray-only"])]
    t = t[t[["x0_mm", "y0_mm", "z0_mm"]].notna().all(axis=1)]
    first = t.groupby("marker", sort=True)[["x0_mm", "y0_mm", "z0_mm"]].first()
    if first.empty:
        return np.array([], dtype=np.int64), [], []
    order = np.argsort(mesh.node_ids)
    corners = {"C3D8": 8, "C3D4": 4}
    blocks = [(b.base, order[np.searchsorted(mesh.node_ids, np.asarray(b.connectivity)[:, :corners[b.base]],
                                             sorter=order)]) for b in mesh.blocks]
    loc = PointLocator(mesh.coords_mm, blocks).locate(first.to_numpy(float), outside_tol_mm=outside_tol_mm)
    rows = [blocks[loc.block[i]][1][loc.element[i]] for i in np.flatnonzero(loc.found)]
    nodes = np.unique(mesh.node_ids[np.concatenate(rows)]) if rows else np.array([], dtype=np.int64)
    names = [str(m) for m in first.index]
    return (nodes.astype(np.int64), [n for n, ok in zip(names, loc.found) if ok],
            [n for n, ok in zip(names, loc.found) if not ok])


def sliding_anchor_equations(brain_nodes, skull_nodes, normals,
                             tol: float = 1e-13) -> list[list[tuple[int, int, float]]]:
    r"""Linear constraints that make a spring's skull end follow its brain node along the skull:
    :math:`\mathbf u_s = (I - \mathbf n\mathbf n^T)\,\mathbf u_b` (three equations per spring,
    each ``[(skull, i, 1), (brain, j, -P_ij), ...]``, the skull dof first so a solver eliminates
    it).  The spring then stays along its normal ``n``: it resists the normal motion only
    (frictionless sliding), however far the node slides, and a compressed spring cannot
    swing sideways."""
    rows = []
    for b, s, n in zip(brain_nodes, skull_nodes, np.asarray(normals, float)):
        P = np.eye(3) - np.outer(n, n)
        for i in range(3):
            rows.append([(int(s), i + 1, 1.0)] + [(int(b), j + 1, -float(P[i, j])) for j in range(3)
                                                   if abs(P[i, j]) > tol])
    return rows


# --- the hand-off as a whole ----------------------------------------------------------------

class HandoffError(ValueError):
    """The inputs cannot make a hand-off; ``key`` names the config key (or None), ``source``
    the input it concerns (a key of the ``sources`` mapping, or None)."""

    def __init__(self, message: str, key: str | None = None, source: str | None = None,
                 failed_check: bool = False, processing: bool = False):
        super().__init__(message)
        self.key = key
        self.source = source
        self.failed_check = failed_check
        self.processing = processing   # valid input on which processing failed (exit 1, as in fit-ogden)


@dataclass
class Handoff:
    """Everything the writers need, in mm, s, N (CT frame); see :func:`build_handoff`."""

    law: str
    params: dict
    prony: list
    window: ContactWindow
    axis: np.ndarray
    rest_tip_mm: np.ndarray
    contact_point_mm: np.ndarray
    clock_offset_s: float
    clock_offset_source: str
    alignment: Alignment | None
    trajectory: pd.DataFrame | None
    difference_contact: DifferenceStats | None
    difference_record: DifferenceStats | None
    amplitude_time_s: np.ndarray
    amplitude_depth_mm: np.ndarray
    amplitude_source: str
    target: pd.DataFrame
    markers: pd.DataFrame
    mesh: Any
    springs: Any
    spring_nominal_n_per_mm: float
    spring_deck_n_per_mm: float
    spring_k_n_per_mm: np.ndarray                 # (n_springs,) each spring's stiffness in the decks
    nominal_area_mm2: float
    nominal_area_source: str
    skull_ids: np.ndarray
    anchor_equations: list | None
    marker_nodes: np.ndarray
    markers_in_mesh: list[str]
    markers_outside_mesh: list[str]
    speed_mm_per_min: float
    depth_mm: float
    checks: list[dict]
    warnings: list[str]
    indentor_source: str
    indentor_names: list[str]


def _check(checks, warnings, name, value, expected, tol, unit, ok, on_fail, **extra):
    entry = {"check": name, "value": value, "expected": expected, "tolerance": tol, "unit": unit, "passed": bool(ok),
             **extra}
    checks.append(entry)
    if not ok:
        msg = (f"{name}: {value:.4g} {unit}, expected {expected:g} +- {tol:g} {unit}" if expected is not None
               else f"{name}: {value:.4g} {unit}, limit {tol:g} {unit}")
        if on_fail == "error":
            raise HandoffError(msg, key=f"checks.{name}", failed_check=True)
        warnings.append(msg)


def _ct_direction(transform, v) -> np.ndarray:
    """A direction ``v`` (X-ray frame) in the CT frame, its length kept: ``R v`` for a
    similarity; along the image of ``v`` by the transform's linear part (``apply_vector``) for a
    CT stretched along one of its axes or sheared by a gantry tilt read without it
    (:class:`~bsipipe.geometry.registration.AxisScaledSimilarity`,
    :class:`~bsipipe.geometry.registration.ShearedSimilarity`: both have a ``factor``)."""
    v = np.asarray(v, float)
    if not hasattr(transform, "factor"):
        return transform.R @ v
    u = transform.apply_vector(v)
    return u * (np.linalg.norm(v) / np.linalg.norm(u))


def build_handoff(cfg, *, fit: dict, transform, markers_ct: pd.DataFrame, log: LogRecord,
                  indentor_xray: pd.DataFrame | None = None, mesh=None) -> Handoff:
    """Compute the hand-off from values already read.

    Parameters
    ----------
    cfg : bsipipe.fe.config.ExportConfig
    fit : dict
        ``fit.json`` (``model``, ``params`` with an optional ``prony`` list).
    transform : bsipipe.geometry.registration.Similarity (or AxisScaledSimilarity, ShearedSimilarity)
        X-ray -> CT (``registration.json``).
    markers_ct : DataFrame
        ``markers_ct.csv``.
    log : LogRecord
        The machine record (compression positive).
    indentor_xray : DataFrame, optional
        The indentor's points in the X-ray frame (``markers3d.csv`` rows); without it they
        are taken from ``markers_ct``.
    mesh : bsipipe.fe.mesh.SolidMesh, optional
        A mesh in the CT frame with the node sets of ``cfg.mesh_sets``; default: the
        demonstration brick under the indentor.

    Raises
    ------
    HandoffError
        Inputs that cannot make a hand-off (with the config key or input concerned), or a
        failed check when ``checks.on_fail`` is ``error``.
    """
    from ..io._fe_material import prepare_material
    from ..io.machine_log import clipped_top
    from ..errors import ProcessingError
    from .mesh import demo_block_mesh, interface_springs

    warnings: list[str] = []
    checks: list[dict] = []
    ind = cfg.indentor

    law = str(fit.get("model", ""))
    params = dict(fit.get("params") or {})
    prony = params.get("prony") or []
    try:
        prepare_material(law, params, prony or None)
    except (ValueError, KeyError, TypeError) as e:
        raise HandoffError(f"the fitted material cannot be written: {e}", source="fit") from None

    try:
        window = contact_window(log, contact_mm=cfg.log.contact_mm)
    except ProcessingError as e:
        raise HandoffError(f"contact: {e.message}", source="log", processing=True) from None
    except ValueError as e:
        raise HandoffError(str(e), key="log.contact_mm") from None

    alignment = None
    trajectory = None
    diff_contact = diff_record = None
    names = list(ind.markers)
    if names:
        if indentor_xray is not None:
            table = indentor_xray.copy()
            src = "markers3d"
            missing = [n for n in names if n not in set(table["marker"])]
            if not missing:
                xyz = transform.apply(table[["x_mm", "y_mm", "z_mm"]].to_numpy(float))
                table[["x_mm", "y_mm", "z_mm"]] = xyz
        else:
            table, src = markers_ct, "markers_ct"
            missing = [n for n in names if n not in set(table["marker"])]
        if missing:
            raise HandoffError(f"indentor marker(s) {', '.join(missing)} not in the table", key="indentor.markers",
                               source=src)
        frames, t_x, C = indentor_centroids(table, names)
        if len(frames) < 3:
            raise HandoffError(f"the indentor's markers are found together in {len(frames)} frame(s); need 3",
                               key="indentor.markers", source=src)
        if not np.all(np.isfinite(t_x)):
            raise HandoffError("the X-ray table has no time_s for the indentor's frames", source=src)
        axis_ct = None if ind.axis_xray is None else _ct_direction(transform, ind.axis_xray)
        # the implanted markers lie in the brain, ahead of the indentor: they tell a fitted
        # direction of indentation from its reverse where the motion alone cannot
        brain = markers_ct[~markers_ct["marker"].isin(names)]
        if "role" in brain.columns:
            brain = brain[brain["role"].astype(str) == "marker"]
        ahead = brain[["x_mm", "y_mm", "z_mm"]].dropna().to_numpy(float)
        try:
            alignment = fit_alignment(t_x, C, log, clock_offset_s=cfg.log.clock_offset_s, axis=axis_ct,
                                      ahead_mm=ahead)
        except ValueError as e:
            raise HandoffError(f"cannot tie the X-ray indentor to the log: {e}", key="log.clock_offset_s") from None
        if alignment.alternatives:
            alt = ", ".join(f"{a['clock_offset_s']:+.3f} s" for a in alignment.alternatives)
            msg = (f"the X-ray motion of the indentor fits the log equally well at clock offsets "
                   f"{alignment.clock_offset_s:+.3f} s and {alt} (its direction reversed between them)")
            if alignment.choice and alignment.choice.startswith("ambiguous"):
                warnings.append(msg + ": the lowest residual is taken, but the X-ray record alone cannot tell "
                                      "them apart; give log.clock_offset_s")
            else:
                log_msg = msg + f": {alignment.clock_offset_s:+.3f} s taken, {alignment.choice}"
                warnings.append(log_msg)
        axis = alignment.axis
        offset = alignment.clock_offset_s
        offset_source = alignment.clock_offset_source
        tip_x = C + ind.tip_offset_mm * axis
        rest_tip = alignment.rest_centroid_mm + ind.tip_offset_mm * axis
        log_t = t_x - offset
        travel = np.interp(log_t, log.time_s, log.travel_mm)
        tip_log = rest_tip + travel[:, None] * axis
        diff = tip_x - tip_log
        in_log = (log_t >= log.time_s[0]) & (log_t <= log.time_s[-1])
        in_contact = (log_t >= window.time_s) & (log_t <= window.end_time_s)
        diff_contact = trajectory_difference(frames, diff, axis, in_contact)
        diff_record = trajectory_difference(frames, diff, axis, in_log)
        trajectory = pd.DataFrame({"frame": frames, "time_s": t_x, "log_time_s": log_t,
                                   "fe_time_s": log_t - window.time_s, "travel_mm": travel,
                                   "depth_log_mm": np.maximum(travel - window.travel_mm, 0.0)})
        for k, ax in enumerate("xyz"):
            trajectory[f"xray_{ax}_mm"] = tip_x[:, k]
        for k, ax in enumerate("xyz"):
            trajectory[f"log_{ax}_mm"] = tip_log[:, k]
        trajectory["difference_mm"] = np.linalg.norm(diff, axis=1)
        trajectory["in_log"] = in_log
        trajectory["in_contact"] = in_contact
        indentor_source = ("markers3d.csv mapped by the registration" if src == "markers3d"
                           else "markers_ct.csv (already in the CT frame)")
    else:
        pose = ind.pose_xray
        axis = _ct_direction(transform, pose.axis)
        axis = axis / np.linalg.norm(axis)
        rest_tip = transform.apply(np.asarray(pose.tip_mm, float))
        if cfg.log.clock_offset_s is None:
            raise HandoffError("without indentor markers the clock offset between the log and the X-ray "
                               "frames must be given", key="log.clock_offset_s")
        offset = float(cfg.log.clock_offset_s)
        offset_source = "given (config log.clock_offset_s)"
        indentor_source = "config indentor.pose_xray mapped by the registration (no X-ray track)"
        warnings.append("no X-ray indentor track: the log-vs-X-ray trajectory difference is not available")
    contact_point = rest_tip + window.travel_mm * axis

    if cfg.deck.amplitude_source == "xray":
        if trajectory is None:
            raise HandoffError("amplitude_source 'xray' needs indentor markers", key="deck.amplitude_source")
        tau, depth = amplitude_from_xray(trajectory["time_s"].to_numpy(), tip_x, contact_point, axis, offset,
                                         window, cfg.deck.amplitude_tolerance_mm)
        amp_source = "X-ray indentor track"
    else:
        tau, depth = amplitude_from_log(log, window, cfg.deck.amplitude_tolerance_mm)
        amp_source = "machine log travel after contact"
    if not depth.max() > 0:
        raise HandoffError("the indentor does not go into the brain after contact", source="log")

    target = force_target(log, window)
    clip = clipped_top(target["indentation_mm"].to_numpy(), target["force_n"].to_numpy())
    if clip is not None:
        warnings.append(
            f"the log's force stops at {clip['level_n']:.6g} N (after the contact baseline) on {clip['n_samples']} "
            f"samples over {clip['travel_mm']:.3g} mm of travel, where the {clip['n_before']} samples before rose "
            f"{clip['expected_rise_n']:.3g} N over as much: a load cell at the end of its range; target_force.csv "
            "there is the cell's limit, not the brain's force")
    markers = marker_table(markers_ct, names, window.time_s + offset)

    holds = ramp_holds(log, window)
    speed = ramp_speed_mm_per_min(log, window, holds)
    if holds:
        warnings.append(
            "the log's crosshead stood still during loading: "
            + "; ".join(f"{h['duration_s']:.3g} s from log time {h['start_s']:.4g} s at {h['travel_mm']:.3g} mm past "
                        "contact" for h in holds)
            + " (a hold in the test method, or a pause); the speed check uses the moving samples, and the FE "
              "amplitude holds too: check that the X-ray frames show the same hold (the log-vs-X-ray difference)")
    depth_max = float(log.travel_mm[window.peak_index] - window.travel_mm)
    ch = cfg.checks
    if ch.speed_mm_per_min is not None:
        tol = ch.speed_rel_tol * ch.speed_mm_per_min
        _check(checks, warnings, "speed_mm_per_min", speed, ch.speed_mm_per_min, tol, "mm/min",
               abs(speed - ch.speed_mm_per_min) <= tol, ch.on_fail)
    if ch.depth_mm is not None:
        # the depth is counted from the contact the log shows, which the force's noise blurs
        # (a soft brain under a 5 mm indentor: millinewtons at the first tenth of a millimetre):
        # the check allows the contact's own uncertainty (2 sd) on top of depth_tol_mm
        tol = ch.depth_tol_mm + 2.0 * window.travel_sd_mm
        _check(checks, warnings, "depth_mm", depth_max, ch.depth_mm, tol, "mm",
               abs(depth_max - ch.depth_mm) <= tol, ch.on_fail, depth_tol_mm=ch.depth_tol_mm,
               contact_sd_mm=window.travel_sd_mm, rule="|depth - expected| <= depth_tol_mm + 2 x contact sd")
    if ch.max_trajectory_difference_mm is not None and diff_contact is not None and diff_contact.n_frames:
        _check(checks, warnings, "max_trajectory_difference_mm", diff_contact.max_mm, None,
               ch.max_trajectory_difference_mm, "mm", diff_contact.max_mm <= ch.max_trajectory_difference_mm,
               ch.on_fail)

    if mesh is None:
        dm = cfg.demo_mesh
        try:
            mesh = demo_block_mesh(contact_point, axis, indentor_radius_mm=ind.diameter_mm / 2,
                                   craniotomy_mm=dm.craniotomy_mm, half_width_mm=dm.half_width_mm,
                                   depth_mm=dm.depth_mm, n_footprint=dm.n_footprint, n_ring=dm.n_ring,
                                   n_outer=dm.n_outer, n_depth=dm.n_depth)
        except ValueError as e:
            raise HandoffError(str(e), key="demo_mesh") from None
        iface, indentor_set = "INTERFACE", "INDENTOR"
    else:
        iface, indentor_set = cfg.mesh_sets.interface.upper(), cfg.mesh_sets.indentor.upper()
        for key, nm in (("mesh_sets.interface", iface), ("mesh_sets.indentor", indentor_set)):
            if nm not in mesh.nsets or not len(mesh.nsets[nm]):
                why = "is empty" if nm in mesh.nsets else f"is not in the mesh (it has {sorted(mesh.nsets)})"
                raise HandoffError(f"node set {nm} {why}", key=key,
                                   source="mesh")
        mesh.nsets["INDENTOR"] = mesh.nsets[indentor_set]
        mesh.nsets["INTERFACE"] = mesh.nsets[iface]
        centre = mesh.coords_of(mesh.nsets[indentor_set]).mean(axis=0)
        off = float(np.linalg.norm(centre - contact_point))
        if off > ind.diameter_mm / 2:
            warnings.append(f"the mesh's indentor nodes are centred {off:.3g} mm from the contact point "
                            f"{np.round(contact_point, 3).tolist()} (more than the indentor's radius)")
    try:
        springs = interface_springs(mesh, "INTERFACE", cfg.interface.spring_length_mm)
    except ValueError as e:
        raise HandoffError(str(e), key="mesh_sets.interface") from None
    overlap = np.intersect1d(springs.brain_nodes, mesh.nsets["INDENTOR"])
    if len(overlap):
        warnings.append(f"{len(overlap)} indentor node(s) also carry an interface spring")
    k_area = cfg.interface.stiffness_n_per_mm_per_mm2
    deck_k = spring_stiffness_n_per_mm(k_area, springs.area_mm2, springs.n_springs)
    if cfg.interface.area_mm2 is not None:
        nominal_area, area_source = float(cfg.interface.area_mm2), "config interface.area_mm2"
    else:
        nominal_area, area_source = springs.area_mm2, "the deck mesh's interface area"
    nominal_k = spring_stiffness_n_per_mm(k_area, nominal_area, cfg.interface.n_springs)
    if springs.n_springs != cfg.interface.n_springs:
        n_nodes = len(np.unique(springs.brain_nodes))
        warnings.append(f"the deck mesh has {springs.n_springs} interface springs"
                        + (f" ({n_nodes} nodes, one per side at edges and corners)" if n_nodes != springs.n_springs
                           else "") + ", the study "
                        f"{cfg.interface.n_springs} springs: the deck's springs carry k x A_mesh / n_mesh = "
                        f"{deck_k:.6g} N/mm each (the study's k x A / n = {nominal_k:.6g} N/mm)")
    trib = np.asarray(springs.tributary_area_mm2, dtype=float)
    if cfg.interface.lumping == "tributary":
        spring_k = k_area * trib
    else:
        spring_k = np.full(springs.n_springs, deck_k)
        lo, hi = float(trib.min()), float(trib.max())
        if lo > 0 and hi / lo > 2.0:
            # the uniform rule is exact on equal cells only: on this mesh it gives some nodes
            # several times, others a fraction of, the stiffness of their share of the surface
            mean = float(trib.mean())
            warnings.append(f"the interface springs' tributary areas range {lo:.3g}-{hi:.3g} mm^2 (mean {mean:.3g}): "
                            f"the uniform springs k x A / n carry {mean / hi:.2f}-{mean / lo:.2f} times the "
                            "stiffness of each node's share of the surface; interface.lumping: tributary gives "
                            "each spring k x its tributary area (springs.csv lumped_stiffness_n_per_mm)")
    skull_base = 10 ** int(np.ceil(np.log10(int(mesh.node_ids.max()) + 1)))
    skull_ids = skull_base + np.arange(1, springs.n_springs + 1)
    equations = (sliding_anchor_equations(springs.brain_nodes, skull_ids, springs.normals)
                 if cfg.interface.anchors == "sliding" else None)
    if equations is not None:
        warnings.append("interface.anchors 'sliding' is modelled in the ABAQUS deck (*EQUATION: the skull end follows "
                        "its brain node along the skull) and in LS-DYNA (springs along their fixed normal), not in "
                        "FEBio: the FEBio model's skull nodes are fixed (zero displacement), its springs act along "
                        "their nodes' line (fixed anchors), so its interface is stiffer sideways")
    marker_nodes, in_mesh, outside = marker_element_nodes(mesh, markers)
    if outside:
        warnings.append(f"marker(s) {', '.join(outside)} lie outside the deck mesh: compare cannot set them against "
                        f"the FE result")
    if prony:
        warnings.append("the material has a Prony series: the ABAQUS deck's steps are *VISCO (ABAQUS relaxes; "
                        "*STATIC would use the instantaneous moduli only); CalculiX has no *VISCOELASTIC, it warns "
                        "and solves with the instantaneous moduli, so its result is the elastic response")

    return Handoff(law=law, params={k: v for k, v in params.items() if k != "prony"}, prony=list(prony),
                   window=window, axis=axis, rest_tip_mm=rest_tip, contact_point_mm=contact_point,
                   clock_offset_s=offset, clock_offset_source=offset_source, alignment=alignment,
                   trajectory=trajectory, difference_contact=diff_contact, difference_record=diff_record,
                   amplitude_time_s=tau, amplitude_depth_mm=depth, amplitude_source=amp_source, target=target,
                   markers=markers, mesh=mesh, springs=springs, spring_nominal_n_per_mm=nominal_k,
                   spring_deck_n_per_mm=deck_k, spring_k_n_per_mm=spring_k, nominal_area_mm2=nominal_area, nominal_area_source=area_source,
                   skull_ids=skull_ids, anchor_equations=equations, marker_nodes=marker_nodes,
                   markers_in_mesh=in_mesh, markers_outside_mesh=outside, speed_mm_per_min=speed, depth_mm=depth_max,
                   checks=checks,
                   warnings=warnings, indentor_source=indentor_source, indentor_names=names)


# --- files --------------------------------------------------------------------------------------

@dataclass
class OutputFile:
    """One file of the hand-off: ``path`` (relative to the output folder), ``text``, what it
    is, its format and units, and where its numbers come from (``sources``: ``quantity``,
    ``from`` (an input file, the config or a computation), ``key``)."""

    path: str
    text: str
    what: str
    format: str
    units: str
    sources: list[dict]


def _src(quantity: str, origin: str, key: str | None = None) -> dict:
    return {"quantity": quantity, "from": origin, "key": key}


def _csv(df: pd.DataFrame) -> str:
    # -0 (a travel of -0.0 before the log starts) written as 0
    df = df.apply(lambda c: c + 0.0 if c.dtype.kind == "f" else c)
    return df.to_csv(index=False, lineterminator="\n", float_format="%.12g")


def deck_increments(h: Handoff, max_increment_mm: float) -> tuple[float, float]:
    """``(step_time_s, max_increment_s)``: the FE step spans the contact window; an increment
    moves the indentor by at most ``max_increment_mm`` at the amplitude's mean rate."""
    step = float(h.amplitude_time_s[-1])
    path_mm = float(np.sum(np.abs(np.diff(h.amplitude_depth_mm))))
    n = max(1, int(np.ceil(path_mm / max_increment_mm)))
    return step, step / n


#: ``*VISCO, CETOL=``: ABAQUS keeps the change of the viscous strain rate over an increment below
#: this, a 0.1 % strain error against the indentation's strains of order 0.1-1.
VISCO_CETOL = 1e-3


def render_files(h: Handoff, cfg, sources: dict[str, str | None], *,
                 coordinate_system: str | None = None) -> list[OutputFile]:
    """Every file of the hand-off (decks in ``cfg.deck.units``, tables in mm, s, N).

    ``coordinate_system`` (the CT frame's, e.g. ``LPS``) is stated in the decks' header with
    the marker-table (X-ray) time of FE time 0, for ``bsipipe compare``."""
    from ..io._fe_material import unit_system
    from ..io.abaqus import abaqus_amplitude, abaqus_equations, abaqus_header_line, abaqus_indentation_deck, \
        abaqus_material, abaqus_nodes, abaqus_springa
    from ..io.febio import febio_indentation_model, febio_material
    from ..io.lsdyna import lsdyna_curve, lsdyna_discrete_springs, lsdyna_indentation_deck, lsdyna_material

    u = unit_system(cfg.deck.units)
    per_mm = u.per_m / 1000.0
    per_s = u.per_s
    per_n_per_mm = u.per_n / per_mm
    src_fit, src_reg, src_log = sources.get("fit"), sources.get("registration"), sources.get("log")
    src_mct, src_m3d, src_mesh = sources.get("markers_ct"), sources.get("markers3d"), sources.get("mesh")
    src_cfg = sources.get("config")
    mesh, sp = h.mesh, h.springs
    mat_kw = dict(bulk_modulus_pa=cfg.deck.bulk_modulus_pa, density_kg_m3=cfg.deck.density_kg_m3)
    prony = h.prony or None
    step_s, dt_s = deck_increments(h, cfg.deck.max_increment_mm)
    t_deck = h.amplitude_time_s * per_s
    a_deck = h.amplitude_depth_mm * per_mm
    k_deck = h.spring_k_n_per_mm * per_n_per_mm
    xyz = mesh.coords_mm * per_mm
    skull_xyz = sp.skull_xyz_mm * per_mm
    ne_max = max(int(b.element_ids.max()) for b in mesh.blocks)
    spring_ids = 10 ** int(np.ceil(np.log10(ne_max + 1))) + np.arange(1, sp.n_springs + 1)
    pairs = np.column_stack([sp.brain_nodes, h.skull_ids])
    indentor_nodes = mesh.nsets["INDENTOR"]
    etype = cfg.deck.element_type
    blocks = []
    for b in mesh.blocks:
        written = etype or b.element_type
        if "/" in written:
            raise HandoffError(f"the mesh mixes element types {written}; name one", key="deck.element_type")
        if etype:
            # a variant of the mesh's own element (C3D8R, C3D8H for a C3D8 mesh): the same nodes
            from ..geometry.shape_functions import element_type
            try:
                given, own = element_type(etype), element_type(b.element_type.split("/")[0])
            except KeyError as e:
                raise HandoffError(str(e).strip("'\""), key="deck.element_type") from None
            if given.name != own.name:
                raise HandoffError(f"{etype} is a {given.name} element ({given.n_nodes} nodes), the mesh's are "
                                   f"{b.element_type} ({own.n_nodes} nodes): give a variant of {own.name} "
                                   f"({own.name}R, {own.name}H, ...)", key="deck.element_type")
        blocks.append((written, b.element_ids, b.connectivity))
    fixed_dir = cfg.interface.anchors == "sliding"
    where = (f"indentor contact point {np.round(h.contact_point_mm, 4).tolist()} mm, direction of "
             f"indentation {np.round(h.axis, 6).tolist()} (CT frame)")
    comments = [
        "bsipipe export-fe: in situ indentation of the brain, CT (FE) frame",
        u.describe(),
        where,
        f"FE time 0 = contact (log time {h.window.time_s:.6g} s); the analysis spans {step_s:.6g} s"
        + (f" ({step_s * per_s:.6g} {u.time})" if u.time != "s" else "") + ", contact to release",
        (f"interface springs: {cfg.interface.stiffness_n_per_mm_per_mm2:g} N/mm per mm^2 x {sp.area_mm2:.6g} mm^2 / "
         f"{sp.n_springs} springs = {h.spring_deck_n_per_mm:.6g} N/mm each"
         if cfg.interface.lumping == "uniform" else
         f"interface springs: {cfg.interface.stiffness_n_per_mm_per_mm2:g} N/mm per mm^2 x each node's tributary "
         f"area = {h.spring_k_n_per_mm.min():.6g}-{h.spring_k_n_per_mm.max():.6g} N/mm ({sp.n_springs} springs, "
         f"{sp.area_mm2:.6g} mm^2)")
        + f", {cfg.interface.spring_length_mm:g} mm long, anchors {cfg.interface.anchors}",
        f"FE time 0 on the marker tables' (X-ray) clock: contact log time + clock offset {h.clock_offset_s:g} s",
        abaqus_header_line("fe_time_zero_xray_s", repr(float(h.window.time_s + h.clock_offset_s))),
        abaqus_header_line("fe_time_unit", u.time),
        abaqus_header_line("fe_force_per_n", repr(float(u.per_n))),
        abaqus_header_line("fe_force_unit", u.force),
        abaqus_header_line("frame", "CT (FE) frame of registration.json"),
    ] + ([abaqus_header_line("ct_coordinate_system", coordinate_system)] if coordinate_system else [])
    mat_sources = [_src("hyperelastic law and parameters (Pa)", src_fit, "model, params"),
                   _src("Prony terms", src_fit, "params.prony"),
                   _src("bulk modulus", src_cfg, "deck.bulk_modulus_pa (null: 1000 x G0)"),
                   _src("density", src_cfg, "deck.density_kg_m3")]
    mesh_sources = ([_src("nodes, elements, node sets", src_mesh, "mesh")] if src_mesh else
                    [_src("demonstration brick geometry", src_cfg, "demo_mesh.*, indentor.diameter_mm"),
                     _src("brick placement: contact point and direction of indentation", "computed",
                          "indentor pose (registration R, t_mm; X-ray indentor track; log contact)")])
    pose_sources = [_src("registration", src_reg, "R, t_mm, scale"),
                    _src("indentor track", src_m3d or src_mct, ", ".join(h.indentor_names) or "indentor.pose_xray"),
                    _src("contact travel and time", src_log, f"Extension, Load ({h.window.method})")]
    spring_sources = [_src("interface stiffness per area", src_cfg, "interface.stiffness_n_per_mm_per_mm2"),
                      _src("spring length", src_cfg, "interface.spring_length_mm"),
                      _src("interface area and nodes", "computed", "the mesh's interface faces"),
                      _src("anchors", src_cfg, "interface.anchors")]
    from_log = h.amplitude_source.startswith("machine")
    amp_sources = [_src("depth after contact", src_log if from_log else src_m3d or src_mct,
                        "Extension" if from_log else ", ".join(h.indentor_names)),
                   _src("knot tolerance", src_cfg, "deck.amplitude_tolerance_mm")]

    deck_nsets = {k: mesh.nsets[k] for k in ("INDENTOR", "INTERFACE", "OPENING") if k in mesh.nsets}
    if len(h.marker_nodes):
        deck_nsets["MARKERS"] = h.marker_nodes
    files: list[OutputFile] = []
    # ---- ABAQUS / CalculiX
    mat_abq = abaqus_material(h.law, h.params, prony, units=u.name, **mat_kw)
    files.append(OutputFile("abaqus/material.inp", mat_abq, "*MATERIAL BRAIN from fit.json", "ABAQUS input",
                            f"{u.name} (stress {u.stress}, time {u.time})", mat_sources))
    amp = abaqus_amplitude("INDENT", t_deck, a_deck, time_kind="TOTAL TIME")
    files.append(OutputFile("abaqus/amplitude.inp", amp,
                            "*AMPLITUDE INDENT: the indentor's depth after contact (multiply by the unit direction "
                            "of indentation for the displacement)", "ABAQUS input",
                            f"time {u.time} (total time from contact), value {u.length}", amp_sources))
    spring_text = (abaqus_nodes(h.skull_ids, skull_xyz, nset="SKULL")
                   + abaqus_springa(spring_ids, pairs, k_deck, "SPRINGS")
                   + (abaqus_equations(h.anchor_equations) if h.anchor_equations is not None else
                      "*BOUNDARY\nSKULL, 1, 3\n"))
    files.append(OutputFile("abaqus/springs.inp", spring_text,
                            "skull nodes, SPRINGA brain-skull springs with their *SPRING card, and the skull "
                            "nodes' constraints (sliding: *EQUATION; fixed: *BOUNDARY); node ids of model.inp",
                            "ABAQUS input", f"length {u.length}, stiffness {u.force}/{u.length}", spring_sources))
    deck = abaqus_indentation_deck(
        comments=comments, node_ids=mesh.node_ids, node_xyz=xyz, blocks=blocks,
        nsets=deck_nsets, print_nsets=[k for k in ("MARKERS",) if k in deck_nsets],
        visco_cetol=VISCO_CETOL if prony else None, material_card=mat_abq, material_name="BRAIN",
        spring_ids=spring_ids, spring_pairs=pairs, skull_ids=h.skull_ids, skull_xyz=skull_xyz,
        spring_stiffness=k_deck, axis=h.axis, amplitude_time=t_deck, amplitude_value=a_deck,
        initial_increment=dt_s * per_s, max_increment=dt_s * per_s, anchor_equations=h.anchor_equations,
        step_ends=t_deck[turning_points(a_deck)], file_frequency=1)
    files.append(OutputFile("abaqus/model.inp", deck,
                            "complete deck: mesh, material, springs to the skull, amplitude, displacement-driven "
                            f"indentor nodes (INDENTOR), *STEP NLGEOM {'*VISCO' if prony else '*STATIC'}, output "
                            "(U, RF to .frd; indentor U and total RF, and U of the nodes of the elements holding "
                            "the markers (MARKERS), to .dat); runs in CalculiX (ccx -i model)",
                            "ABAQUS / CalculiX input",
                            f"{u.name}: length {u.length}, time {u.time}, force {u.force}, stress {u.stress}",
                            mat_sources + mesh_sources + pose_sources + spring_sources + amp_sources))
    # ---- LS-DYNA
    mat_k = lsdyna_material(h.law, h.params, prony, mid=1, units=u.name, **mat_kw)
    files.append(OutputFile("lsdyna/material.k", mat_k, "*MAT_OGDEN_RUBBER (MID 1) from fit.json",
                            "LS-DYNA keyword (include)", f"{u.name}", mat_sources))
    curve = "*KEYWORD\n" + lsdyna_curve(1, t_deck, a_deck, "indentor depth after contact") + "*END\n"
    files.append(OutputFile("lsdyna/curve.k", curve, "*DEFINE_CURVE 1: the indentor's depth after contact",
                            "LS-DYNA keyword", f"abscissa {u.time}, ordinate {u.length}", amp_sources))
    springs_k = ("*KEYWORD\n" + lsdyna_discrete_springs(spring_ids, pairs, sp.normals, k_deck, pid=2, secid=2, mid=2,
                                                        fixed_direction=fixed_dir) + "*END\n")
    files.append(OutputFile("lsdyna/springs.k", springs_k,
                            "*MAT_SPRING_ELASTIC, *SECTION_DISCRETE, *PART 2, *DEFINE_SD_ORIENTATION (interface "
                            "normals) and *ELEMENT_DISCRETE brain-skull springs; node ids of model.k",
                            "LS-DYNA keyword", f"stiffness {u.force}/{u.length}", spring_sources))
    blocks_dyna = [(b.base, b.element_ids, b.connectivity) for b in mesh.blocks]
    model_k = lsdyna_indentation_deck(
        comments=comments, node_ids=mesh.node_ids, node_xyz=xyz, blocks=blocks_dyna, material_card=mat_k, mid=1,
        anchor_ids=h.skull_ids, anchor_xyz=skull_xyz, spring_ids=spring_ids, spring_pairs=pairs,
        spring_normals=sp.normals, spring_stiffness=k_deck, indentor_nodes=indentor_nodes, axis=h.axis,
        curve_time=t_deck, curve_value=a_deck, end_time=step_s * per_s, dt_initial=dt_s * per_s,
        dt_max=dt_s * per_s, output_dt=dt_s * per_s, fixed_direction=fixed_dir)
    files.append(OutputFile("lsdyna/model.k", model_k,
                            "complete implicit static deck: mesh (PART 1), material, springs (PART 2) to fixed "
                            "skull nodes (each along its fixed interface normal when anchors are 'sliding'), "
                            "curve, prescribed indentor nodes (SET 1), fixed skull (SET 2); not run here",
                            "LS-DYNA keyword", f"{u.name}", mat_sources + mesh_sources + pose_sources
                            + spring_sources + amp_sources))
    # ---- FEBio
    mat_feb = febio_material(h.law, h.params, prony, units=u.name, **mat_kw)
    files.append(OutputFile("febio/material.feb.xml", mat_feb, "<Material> BRAIN from fit.json", "FEBio 4 XML",
                            f"{u.name}", mat_sources))
    feb_comments = comments + (["interface.anchors 'sliding' is not modelled here: the skull nodes are fixed and "
                                "the springs act along their nodes' line (fixed anchors); the ABAQUS and LS-DYNA "
                                "decks slide"] if fixed_dir else [])
    model_feb = febio_indentation_model(
        comments=feb_comments, node_ids=mesh.node_ids, node_xyz=xyz, blocks=blocks_dyna, material_xml=mat_feb,
        anchor_ids=h.skull_ids, anchor_xyz=skull_xyz, spring_pairs=pairs, spring_stiffness=k_deck,
        indentor_nodes=indentor_nodes, axis=h.axis, curve_time=t_deck, curve_value=a_deck,
        time_steps=int(round(step_s / dt_s)), step_size=dt_s * per_s, dt_max=dt_s * per_s)
    files.append(OutputFile("febio/model.feb", model_feb,
                            "complete FEBio 4 model: mesh, material, linear springs to fixed skull nodes (along "
                            "the line of their nodes: fixed anchors, whatever interface.anchors says), load curve "
                            "1, prescribed indentor nodes; not run here",
                            "FEBio 4 XML", f"{u.name}", mat_sources + mesh_sources + pose_sources + spring_sources
                            + amp_sources))
    # ---- tables (mm, s, N)
    amp_df = pd.DataFrame({"time_s": h.amplitude_time_s, "depth_mm": h.amplitude_depth_mm})
    tip = h.contact_point_mm + h.amplitude_depth_mm[:, None] * h.axis
    for k, ax in enumerate("xyz"):
        amp_df[f"tip_{ax}_mm"] = tip[:, k]
    files.append(OutputFile("amplitude.csv", _csv(amp_df),
                            "the decks' indentor amplitude: FE time from contact, depth after contact, and the "
                            "centre of the indentor's flat end in the CT frame", "CSV", "s, mm (CT frame)",
                            amp_sources + pose_sources))
    if h.trajectory is not None:
        files.append(OutputFile("indentor_trajectory.csv", _csv(h.trajectory),
                                "the indentor tip at every X-ray frame, from the X-ray (xray_*) and from the log "
                                "(log_*), their distance (difference_mm), clocks (time_s X-ray, log_time_s, "
                                "fe_time_s from contact)", "CSV", "mm (CT frame), s",
                                pose_sources + [_src("clock offset", "computed" if h.alignment and
                                                     h.alignment.clock_offset_source.startswith("fitted")
                                                     else src_cfg, "log.clock_offset_s")]))
    files.append(OutputFile("target_force.csv", _csv(h.target),
                            "the FE target: contact-zeroed indentor force against indentation over the contact "
                            "window (time_s from contact, log_time_s on the log's clock)", "CSV", "s, mm, N",
                            [_src("time, travel, force", src_log, "Time, Extension, Load"),
                             _src("contact (travel, time, force baseline)", "computed", h.window.method)]))
    files.append(OutputFile("markers_fe.csv", _csv(h.markers),
                            "markers in the FE (CT) frame: initial positions (x0_mm..: registration frame), "
                            "positions and displacements per frame, fe_time_s from contact", "CSV", "mm, s",
                            [_src("positions and displacements", src_mct, "x_mm, y_mm, z_mm, dx_mm, dy_mm, dz_mm"),
                             _src("time of contact on the X-ray clock", "computed",
                                  "log contact time + clock offset")]))
    sp_df = pd.DataFrame({"spring": spring_ids, "brain_node": sp.brain_nodes, "skull_node": h.skull_ids})
    bxyz = mesh.coords_of(sp.brain_nodes)
    for k, ax in enumerate("xyz"):
        sp_df[f"{ax}_mm"] = bxyz[:, k]
    for k, ax in enumerate("xyz"):
        sp_df[f"n{ax}"] = sp.normals[:, k]
    for k, ax in enumerate("xyz"):
        sp_df[f"skull_{ax}_mm"] = sp.skull_xyz_mm[:, k]
    sp_df["tributary_area_mm2"] = sp.tributary_area_mm2
    sp_df["stiffness_n_per_mm"] = h.spring_k_n_per_mm
    sp_df["lumped_stiffness_n_per_mm"] = cfg.interface.stiffness_n_per_mm_per_mm2 * sp.tributary_area_mm2
    files.append(OutputFile("springs.csv", _csv(sp_df),
                            "per-node interface springs of the deck mesh: brain and skull node, outward normal, "
                            "tributary area, the decks' stiffness (interface.lumping: uniform k A / n, or "
                            "tributary) and the lumped k x tributary area", "CSV", "mm, mm^2, N/mm",
                            spring_sources))
    return files
