r"""Closing the loop on tracking and triangulation: effects that leave a mark in the ray gap.

The declared model pairs frame *i* of view A with frame *i* of view B, trusts every
tracked position and every marker name, and triangulates.  Its residual is the signed ray
gap :math:`g` of each point (mm; :func:`~bsipipe.imaging.triangulate.triangulate`): for
markers measured without error through exact cameras it is zero, and measurement noise
leaves independent values of either sign.  These effects leave structure instead:

``view-time-offset``
    The two C-arms are not synchronised: view B's frame *i* is taken at
    :math:`t_i + \delta`.  A marker moving with velocity :math:`v` is then seen by B
    :math:`v\delta` away from where A saw it, and the gap is
    :math:`g \approx \delta\,(v \cdot \hat n)`, :math:`\hat n` the rays' common normal: it
    grows with the marker's speed and follows the covariate ``v_perp_mm_s``.  Fix:
    interpolate B's 2-D tracks in time (PCHIP through each contiguous run) to A's frame
    times, :math:`\delta` chosen to minimise the (robust) sum of squared gaps.  Parameter
    ``view_time_offset_s`` (B's clock minus A's).
``view-clock-drift``
    The two C-arms' frame clocks also run at slightly different rates: B's frame *i*,
    nominally at :math:`t_i`, is taken at :math:`t_i (1 + \varepsilon) + \delta` on A's
    clock, so the offset grows through the sequence (0.1 % is 0.1 s over 100 s).  The gap
    then follows ``v_perp_mm_s`` with a slope that changes with time.  Fix: B interpolated
    at :math:`(t - \delta)/(1 + \varepsilon)`, both chosen to minimise the (robust) sum
    of squared gaps.  Parameters ``view_time_offset_s`` (at B's first frame) and
    ``view_clock_drift`` (:math:`\varepsilon`, B's frame interval over A's, minus one).
``dropped-frames``
    One view lost frames partway through (a capture that skipped them, frame files deleted
    and the rest renumbered) or repeated one: from there on its frame *i* pairs with the
    other view's taken whole periods apart, a step in the offset that no constant offset or
    rate fits.  Fix (:func:`estimate_frame_steps`): the per-frame gaps at offsets a whole
    number of periods apart, the path with a BIC penalty per step (dynamic programming); a
    step is a repeat where a view's frames there are identical to the frame before, else
    frames lost; the view's times put right (:func:`stepped_times`; B's tracks interpolated
    across a gap, a repeat's copies left out) and the clock offset estimated on those times.
    Parameters ``view_time_offset_s`` and ``frame_steps`` (view, lost or repeated, frame,
    how many).
``frame-shift``
    A view's whole picture jolts from frame to frame (a C-arm's vibration: the source and
    detector move, the head does not): every marker of that view's frame is shifted by a
    common offset, which the other view does not see, so the gaps of a frame's markers move
    together.  Fix: each view's offset in each frame, the median over its markers of their
    departures from their own smooth tracks (Savitzky-Golay, the offsets taken out and the
    tracks smoothed again until they settle), kept where it stands out of the markers'
    scatter, subtracted before triangulating.  Only the part that is not smooth in time is
    seen: a jolt's slow part is the markers' common motion.  Refined by a rank-1 motion model
    (:func:`low_rank_frame_shifts`) or read off the still markers (:func:`still_frame_shifts`),
    whichever leaves the smaller ray gaps, judged after the clock where the spec has one.
    Outside evidence: the 2-D tracks
    themselves (BIC of a common offset per frame against none, on the markers' departures
    from their smooth tracks), and the ray gaps must fall too (a shift that both views see
    alike is the head moving, not a jolt).  Parameters: ``frame_shifts`` (per view, how many
    frames, the RMS and largest offset).
``identity-swap``
    Two markers' names are exchanged in one view from some frame on: both get gaps of many
    times the noise, for a run of frames (runs test, group means).  Fix: for every frame,
    the pairing of A's and B's markers that makes the gaps small; every run of frames
    where exchanging two of B's names lowers both gaps below a quarter is one swap
    (one parameter each).
``track-capture``
    A marker's track in one view was held by something else in its search window (a static
    spot: dust or a defect on the intensifier, darker than the bead) while the marker moved
    off: from then on one marker's gaps are many times the noise for a run of frames (group
    means, runs test).  Fix (:func:`find_captures`): runs of at least 3 frames where a
    marker's gap exceeds 10 times the gaps' noise (from their frame-to-frame changes, which a
    slowly growing bias does not enter); the frames of both views searched again
    (:class:`WindowSource`, the tracker's window search) in windows around the track wide
    enough for the marker's motion in the other view; per frame the pair of candidates, one
    per view and held by no other marker, whose rays pass within 4 noise sd, nearest the pair
    taken a frame before.  A view where that finds the marker elsewhere in at least 3 frames
    (and a pair in at least half the run's) takes the re-found positions; what held the track,
    if it stood still, is a spot: every frame the track stood on it is searched again with
    the spot's candidates left out (its error may lie along the rays there, unseen by the
    gap), and a frame with no pair left is left out (the marker's image merged with the
    spot).  One parameter per re-found run.  The views' frames are paired as recorded: with a
    clock offset between them uncorrected, a moving marker's true pair does not pass the test.
``occlusion``
    A marker partly hidden (entering or leaving an instrument's shadow) is measured off
    centre: its gaps at the frames next to a loss, or where the tracker saw its amplitude
    fall (``partial``), are outliers.  Fix: those measurements are left out, and the frames
    where only one view sees the marker get a single-view point (on the visible ray,
    nearest to the trajectory interpolated through the gap).  Outside evidence: the
    tracker's flags, i.e. whether the gaps of the flagged points have a larger spread
    than the others (BIC of two variances against one).

:func:`close_stereo_loop` runs :func:`bsipipe.loop.run_loop` over these candidates and
reports the ray gap and reprojection error before and after each step.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import pandas as pd

from ..loop import Effect, LoopReport, run_loop
from .track import true_runs as _runs
from .triangulate import ViewGeometry, _triangulate, closest_point_on_ray

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StereoSpec:
    """Which effects the stereo model includes (the loop's spec)."""

    time_offset: bool = False
    swaps: bool = False
    occlusion: bool = False
    clock_drift: bool = False        # with time_offset: B's clock also runs at its own rate
    frame_shift: bool = False        # each view's picture shifted by a common offset per frame
    capture: bool = False            # a view's track held by another spot: re-found along the other view's ray
    frame_steps: bool = False        # with time_offset: the offset steps by whole frames (a view lost frames)
    rig_mismatch: bool = False       # the rays miss each other by a steady field over the points (the rig moved)

    def describe(self) -> str:
        parts = [n for n, on in (("view-time-offset", self.time_offset and not (self.clock_drift or self.frame_steps)),
                                 ("view-clock-drift", self.clock_drift), ("dropped-frames", self.frame_steps),
                                 ("frame-shift", self.frame_shift),
                                 ("identity-swap", self.swaps), ("track-capture", self.capture),
                                 ("occlusion", self.occlusion), ("rig-mismatch", self.rig_mismatch)) if on]
        return "stereo" + ("+" + "+".join(parts) if parts else "")


@dataclass
class StereoData:
    """Two views' 2-D tracks on a common grid of A's frames and the markers both track.

    ``xa``, ``xb`` (F, M, 2) raw pixels (NaN where not found); ``ta``, ``tb`` (F,) each
    view's frame times (s; B's nominal clock); ``suspect_a``, ``suspect_b`` (F, M) bool:
    partial detections and the frames next to a loss (the tracker's flags).  ``windows``: where
    the frames can be searched again (:class:`WindowSource`, for ``track-capture``); None: they
    cannot (the effect then finds nothing to re-measure).
    """

    views: tuple[ViewGeometry, ViewGeometry]
    frames: np.ndarray
    markers: list[str]
    xa: np.ndarray
    xb: np.ndarray
    ta: np.ndarray
    tb: np.ndarray
    suspect_a: np.ndarray
    suspect_b: np.ndarray
    windows: "WindowSource | None" = field(default=None, repr=False, compare=False)
    #: the model has a rig's steady misfit (rig-mismatch): each marker's mean 3-D position
    #: (M, 3), and the clock searches judge the gaps about the linear field of the markers'
    #: mean gaps over them, so the misfit does not pull the clock
    steady_field: np.ndarray | None = field(default=None, repr=False, compare=False)


def _view_arrays(cols: dict, markers: list[str], frames: np.ndarray):
    """One view's positions (F, M, 2), frame times (F,) and suspect flags (F, M) from its rows
    (``cols``: the table's columns as arrays)."""
    F, M = len(frames), len(markers)
    xy = np.full((F, M, 2), np.nan)
    times = np.full(F, np.nan)
    partial = np.zeros((F, M), bool)
    # rows -> (frame, marker) cells, all at once; where a cell (or a frame's time) has more
    # than one row, the last one counts (and, for the position, the last found one)
    i = pd.Index(frames).get_indexer(cols["frame"])
    j = pd.Index(markers).get_indexer(cols["marker"])
    keep = (i >= 0) & (j >= 0)
    i, j = i[keep], j[keep]
    cell = i * M + j
    last_i = len(i) - 1 - np.unique(i[::-1], return_index=True)[1]
    times[i[last_i]] = cols["time_s"][keep][last_i]
    last = len(cell) - 1 - np.unique(cell[::-1], return_index=True)[1]
    partial.ravel()[cell[last]] = cols["partial"][keep][last]
    found = cols["found"][keep]
    if found.any():
        cf = cell[found]
        lf = len(cf) - 1 - np.unique(cf[::-1], return_index=True)[1]
        xy.reshape(-1, 2)[cf[lf]] = np.column_stack([cols["x_px"][keep][found][lf], cols["y_px"][keep][found][lf]])
    found = np.isfinite(xy).all(axis=2)
    # the frames next to a change between found and lost: partly hidden there (a frame the
    # recorder dropped, status missing-frame, hides nothing)
    edge = np.zeros_like(found)
    ch = found[1:] != found[:-1]
    if "missing" in cols and cols["missing"].any():
        gone = np.zeros(F, bool)
        gone[i[cols["missing"][keep]]] = True
        ch &= ~(gone[1:] | gone[:-1])[:, None]
    edge[1:] |= ch
    edge[:-1] |= ch
    suspect = found & (edge | partial)
    return xy, times, suspect


def stereo_data(table: pd.DataFrame, views: tuple[ViewGeometry, ViewGeometry]) -> StereoData:
    """Arrange a tidy 2-D table (``view, frame, time_s, marker, x_px, y_px, found, status``)
    for the two views: A's frames, the markers present in both views."""
    a, b = views[0].name, views[1].name
    view = table["view"]
    cols = {"frame": table["frame"].to_numpy(), "marker": table["marker"].to_numpy(),
            "time_s": table["time_s"].to_numpy(dtype=float), "x_px": table["x_px"].to_numpy(dtype=float),
            "y_px": table["y_px"].to_numpy(dtype=float),
            "found": np.asarray(table["found"].to_numpy(), dtype=bool),
            "partial": (table["status"] == "partial").to_numpy(dtype=bool),
            "missing": (table["status"] == "missing-frame").to_numpy(dtype=bool)}
    in_a, in_b = (view == a).to_numpy(), (view == b).to_numpy()
    ma = list(pd.unique(cols["marker"][in_a]))            # in order of appearance
    mb = set(pd.unique(cols["marker"][in_b]))
    markers = [m for m in ma if m in mb]
    fa = np.sort(pd.unique(cols["frame"][in_a]))
    fb = np.sort(pd.unique(cols["frame"][in_b]))
    col_a = {k: v[in_a] for k, v in cols.items()}
    col_b = {k: v[in_b] for k, v in cols.items()}
    resampled = _other_rate(col_a, col_b, fa, fb, markers)
    if resampled is not None:
        xa, ta, sa = _view_arrays(col_a, markers, fa)
        xb, sb = resampled(ta)
        return StereoData(views, fa, markers, xa, xb, ta, ta.copy(), sa, sb)
    frames = fa[np.isin(fa, fb)] if len(fb) else fa
    xa, ta, sa = _view_arrays(col_a, markers, frames)
    xb, tb, sb = _view_arrays(col_b, markers, frames)
    return StereoData(views, frames, markers, xa, xb, ta, tb, sa, sb)


#: Two views whose median frame intervals differ by more than this fraction run at their own
#: frame rates (frame k of one is not taken with frame k of the other).
OTHER_RATE = 0.01


def frame_period(frames, times) -> float:
    """A view's median frame interval from its rows' frame numbers and times (the first time
    of each frame, in frame order); NaN where fewer than two frames have one."""
    t = pd.Series(np.asarray(times, float)).groupby(np.asarray(frames)).first().sort_index().to_numpy(float)
    d = np.diff(t[np.isfinite(t)])
    return float(np.median(d)) if len(d) else np.nan


def rates_differ(pa: float, pb: float) -> bool:
    """Whether two views' frame periods (:func:`frame_period`) are more than :data:`OTHER_RATE`
    apart (both known)."""
    return bool(np.isfinite(pa) and np.isfinite(pb) and pa > 0 and pb > 0 and abs(pa / pb - 1.0) > OTHER_RATE)


def _flags_near(t_src: np.ndarray, flags: np.ndarray, t_query: np.ndarray, reach: float) -> np.ndarray:
    """(len(t_query), M): a flagged sample (``flags`` (F, M) at times ``t_src``) taints the
    points interpolated within ``reach`` of it."""
    out = np.zeros((len(t_query), flags.shape[1]), bool)
    for j in range(flags.shape[1]):
        ts = t_src[flags[:, j] & np.isfinite(t_src)]
        if len(ts):
            out[:, j] = np.abs(t_query[:, None] - ts[None, :]).min(axis=1) < reach
    return out


def _other_rate(col_a: dict, col_b: dict, fa: np.ndarray, fb: np.ndarray, markers: list[str]):
    """Where both views' frames carry times at different rates (median intervals more than
    1 % apart: a DICOM, TIFF or video of each C-arm at its own frame rate), frame k of one is
    not taken with frame k of the other, and the frames both number cover only the shorter
    count: B's tracks are then interpolated (PCHIP through each run of found frames, as the
    clock effects do) at every one of A's frame times.  Returns ``at(ta) -> (xb, suspect_b)``
    on A's frames, or None where the rates agree (frames pair by number)."""
    pb = frame_period(col_b["frame"], col_b["time_s"])
    if not rates_differ(frame_period(col_a["frame"], col_a["time_s"]), pb):
        return None
    xb_own, tb_own, sb_own = _view_arrays(col_b, markers, fb)

    def at(ta):
        xb = _Interp(tb_own, xb_own)(ta)
        # a point interpolated within one of B's periods of a suspect B sample is suspect
        return xb, _flags_near(tb_own, sb_own, ta, pb) & np.isfinite(xb).all(axis=2)

    return at


# --- the fit of one spec ---------------------------------------------------------------------

@dataclass
class StereoFit:
    """Triangulated points of one spec and everything the loop needs."""

    spec: StereoSpec
    points: pd.DataFrame
    residuals: np.ndarray            # signed ray gaps (mm) of the two-view points
    params: dict
    n_params: int
    covariates: dict
    groups: np.ndarray               # marker index of each residual
    frame_index: np.ndarray          # frame index (into StereoData.frames) of each residual
    swaps: list = field(default_factory=list)
    xb_used: np.ndarray | None = None
    success: bool = True
    frame_shifts: dict | None = None  # view -> (F, 2) px each frame's common shift taken out (frame-shift)
    captures: list = field(default_factory=list)  # track-capture: re-found runs (find_captures)
    gap_bias: np.ndarray | None = None  # rig-mismatch: the field's value at each residual (mm), taken out
    rig: dict | None = None           # rig-mismatch: each marker's count and mean position (its evidence)

    @property
    def ray_gap_rms_mm(self) -> float:
        """RMS of the ray gaps themselves (a rig-mismatch field the model explains included)."""
        if not len(self.residuals):
            return float("nan")
        g = self.residuals if self.gap_bias is None else self.residuals + self.gap_bias
        return float(np.sqrt(np.mean(g ** 2)))

    @property
    def reproj_rms_px(self) -> float:
        p = self.points[self.points["n_views"] == 2]
        return float(np.sqrt(np.mean(p["reproj_err_px"] ** 2))) if len(p) else float("nan")


def _pchip_slopes(h: np.ndarray, m: np.ndarray, first: np.ndarray, last: np.ndarray, two: np.ndarray) -> np.ndarray:
    """PCHIP's derivatives (F, ...) at samples whose intervals have widths ``h`` (F-1,) and
    slopes ``m`` (F-1, ...), as :class:`scipy.interpolate.PchipInterpolator` finds them for each
    run (the same operations): the weighted harmonic mean of the slopes inside a run (zero
    where they change sign or one is zero), the shape-preserving three-point estimate at
    its ends, the slope itself in a run of two samples.  ``first``, ``last``, ``two`` (F, ...)
    mark each run's first and last samples and the runs of two."""
    F = len(m) + 1
    hb = h.reshape((-1,) + (1,) * (m.ndim - 1))
    d = np.zeros((F,) + m.shape[1:])
    if F < 3:
        d[:-1] = np.where(two[:-1], m, 0.0)
        d[1:] = np.where(two[1:], m, d[1:])
        return d
    with np.errstate(divide="ignore", invalid="ignore"):
        # inside: samples 1..F-2, slopes m[:-1] before and m[1:] after
        w1 = 2 * hb[1:] + hb[:-1]
        w2 = hb[1:] + 2 * hb[:-1]
        whmean = (w1 / m[:-1] + w2 / m[1:]) / (w1 + w2)
        cond = (np.sign(m[1:]) != np.sign(m[:-1])) | (m[1:] == 0) | (m[:-1] == 0)
        d[1:-1] = np.where(cond, 0.0, 1.0 / whmean)

        def edge(h0, h1, m0, m1):
            e = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
            mask = np.sign(e) != np.sign(m0)
            mask2 = (np.sign(m0) != np.sign(m1)) & (np.abs(e) > 3. * np.abs(m0))
            e = np.where(mask, 0., e)
            return np.where(~mask & mask2, 3. * m0, e)

        # a run's first sample i: intervals i, i+1; its last sample i: intervals i-1, i-2
        d[:-2] = np.where(first[:-2], edge(hb[:-1], hb[1:], m[:-1], m[1:]), d[:-2])
        d[2:] = np.where(last[2:], edge(hb[1:], hb[:-1], m[1:], m[:-1]), d[2:])
    d[:-1] = np.where(two[:-1] & first[:-1], m, d[:-1])
    d[1:] = np.where(two[1:] & last[1:], m, d[1:])
    return d


class _Interp:
    """PCHIP through each marker's contiguous runs of found frames, built once and evaluated
    at any times (NaN outside a run: gaps are not bridged).

    The cubics are built and evaluated here for every marker and run at once, with the same
    operations :class:`scipy.interpolate.PchipInterpolator` (derivatives, Hermite
    coefficients) and :class:`~scipy.interpolate.PPoly` (interval by binary search, the local
    power series summed in the same order) apply to each run: the same numbers without one
    interpolator per run.  That needs the finite source times in increasing order; otherwise
    each run gets its own ``PchipInterpolator`` (markers whose runs span the same frames
    share one).
    """

    def __init__(self, t_src: np.ndarray, y: np.ndarray):
        self.shape = y.shape[1:]
        self.t_src = t_src = np.asarray(t_src, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        F, M = y.shape[:2]
        tfin = np.isfinite(t_src)
        ok = np.isfinite(y).reshape(F, M, -1).all(axis=2) & tfin[:, None]
        spans: dict[tuple[int, int], list[int]] = {}
        first = np.zeros((F, M), bool)
        last = np.zeros((F, M), bool)
        two = np.zeros((F, M), bool)
        for j in range(M):
            for i0, i1 in zip(*_runs(ok[:, j])):
                if i1 - i0 >= 2:
                    spans.setdefault((int(i0), int(i1) - 1), []).append(j)
                    first[i0, j] = last[i1 - 1, j] = True
                    two[i0:i1, j] = i1 - i0 == 2
                else:
                    ok[i0, j] = False                 # a single sample: no interpolant
        # (cols, first time, last time) of each run, markers with the same frames together
        self.runs: list[tuple[np.ndarray, float, float]] = [
            (np.asarray(cols), t_src[i0], t_src[i1]) for (i0, i1), cols in spans.items()]
        self._fast = bool(np.all(np.diff(t_src[tfin]) > 0))
        self._pchip: list = []
        if not self._fast:
            from scipy.interpolate import PchipInterpolator
            self._pchip = [PchipInterpolator(t_src[i0:i1 + 1], y[i0:i1 + 1][:, cols], axis=0)
                           for (i0, i1), cols in spans.items()]
            return
        # interval i (samples i, i+1) of marker j is a piece when both samples are in one run
        self._valid = ok[1:] & ok[:-1]
        tail = (1,) * (y.ndim - 2)
        h = t_src[1:] - t_src[:-1]
        with np.errstate(invalid="ignore", divide="ignore"):
            m = (y[1:] - y[:-1]) / h.reshape((-1, 1) + tail)
            d = _pchip_slopes(h, m, first.reshape(first.shape + tail), last.reshape(last.shape + tail),
                              two.reshape(two.shape + tail))
            hr = h.reshape((-1, 1) + tail)
            t = (d[:-1] + d[1:] - 2 * m) / hr
            # the local power series of each piece, highest power first (PPoly's c): for each
            # power and each component, entry i * M + j is interval i of marker j
            n_tail = int(np.prod(self.shape[1:], dtype=int))
            self._coef = [np.ascontiguousarray(np.moveaxis(c.reshape(max(F - 1, 0) * M, n_tail), 1, 0))
                          for c in (t / hr, (m - d[:-1]) / hr - t, d[:-1], y[:-1])]
        # t_src with its gaps filled by the time before (-inf at the start): non-decreasing,
        # so one binary search finds every point's interval
        self._t_ff = np.maximum.accumulate(np.where(tfin, t_src, -np.inf)) if F else t_src

    def covers(self, t_lo: np.ndarray, t_hi: np.ndarray) -> np.ndarray:
        """(F, M) bool: marker j has one run spanning [t_lo[i], t_hi[i]]."""
        out = np.zeros((len(t_lo), self.shape[0]), bool)
        for cols, t0, t1 in self.runs:
            out[:, cols] |= ((t_lo >= t0) & (t_hi <= t1))[:, None]
        return out

    def at_points(self, t: np.ndarray, cols: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
        """Values (P, ...) of markers ``cols`` (P,) at times ``t`` (P,), or at ``t[at]`` where
        ``at`` (P,) is given (a few times shared by many points): NaN outside their runs."""
        P = len(cols)
        out = np.full((P,) + self.shape[1:], np.nan)
        F = len(self.t_src)
        if not self._fast:
            if at is not None:
                t = t[at]
            for (c, t0, t1), f in zip(self.runs, self._pchip):
                q = np.flatnonzero((t >= t0) & (t <= t1) & np.isin(cols, c))
                if len(q):
                    out[q] = f(t[q])[np.arange(len(q)), np.searchsorted(c, cols[q])]
            return out
        if F < 2 or P == 0:
            return out
        g = np.searchsorted(self._t_ff, t, side="right") - 1
        if at is not None:
            t, g = t[at], g[at]
        gc = np.clip(g, 0, F - 2)
        hit = (g >= 0) & (g <= F - 2) & self._valid[gc, cols]
        if not hit.all():
            # exactly at a run's last sample: the end of its last interval
            miss = np.flatnonzero(~hit)
            g0 = np.searchsorted(self._t_ff, t[miss], side="left")
            g0c = np.clip(g0, 1, F - 1)
            end = (g0 >= 1) & (g0 <= F - 1) & (self.t_src[g0c] == t[miss]) & self._valid[g0c - 1, cols[miss]]
            gc[miss] = np.where(end, g0c - 1, gc[miss])
            hit[miss] = end
            idx = np.flatnonzero(hit)
            gc, t, cols = gc[idx], t[idx], cols[idx]
        else:
            idx = slice(None)
        s = t - self.t_src[gc]
        z2 = s * s
        z3 = z2 * s
        row = gc * self.shape[0] + cols
        o = out.reshape(P, -1)
        for k in range(o.shape[1]):
            c0, c1, c2, c3 = (c[k][row] for c in self._coef)
            # PPoly's sum: c_3 + c_2 s + c_1 s^2 + c_0 s^3, the powers by repeated products
            o[idx, k] = ((c3 + c2 * s) + c1 * z2) + c0 * z3
        return out

    def __call__(self, t_query: np.ndarray) -> np.ndarray:
        if not self._fast:
            out = np.full((len(t_query),) + self.shape, np.nan)
            for (cols, t0, t1), f in zip(self.runs, self._pchip):
                q = (t_query >= t0) & (t_query <= t1)
                if q.any():
                    out[np.ix_(q, cols)] = f(t_query[q])
            return out
        M = self.shape[0]
        v = self.at_points(t_query, np.tile(np.arange(M), len(t_query)), at=np.repeat(np.arange(len(t_query)), M))
        return v.reshape((len(t_query),) + self.shape)


def _pchip_at(t_src: np.ndarray, y: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Interpolate (F, M, 2) samples at times ``t_src`` to ``t_query`` (see :class:`_Interp`)."""
    return _Interp(t_src, y)(t_query)


def _gaps(d: StereoData, xb: np.ndarray, ok: np.ndarray | None = None) -> np.ndarray:
    """Signed ray gaps (F, M) of A's and the given B positions (NaN where either is missing)."""
    F, M = d.xa.shape[:2]
    ua, ub = d.xa.reshape(-1, 2), xb.reshape(-1, 2)
    good = np.isfinite(ua).all(axis=1) & np.isfinite(ub).all(axis=1)
    if ok is not None:
        good &= ok.ravel()
    g = np.full(F * M, np.nan)
    if good.any():
        from .triangulate import ray_gaps
        g[good] = ray_gaps(d.views, ua[good], ub[good])
    return g.reshape(F, M)


def _ray_dirs(view: ViewGeometry, x: np.ndarray) -> np.ndarray:
    """Unit ray directions (..., 3) of raw pixels x (..., 2); NaN where x is NaN."""
    u = x.reshape(-1, 2)
    out = np.full((len(u), 3), np.nan)
    ok = np.isfinite(u).all(axis=1)
    if ok.any():
        out[ok] = view.ray_directions(u[ok])
    return out.reshape(x.shape[:-1] + (3,))


def _gaps_from_dirs(da: np.ndarray, db: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Signed ray gaps (mm) of rays with directions da, db (..., 3) from centres ``base``
    apart: :func:`~bsipipe.imaging.triangulate.ray_gaps` for rays already found."""
    n = np.cross(da, db)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    return (n / np.where(nn > 0, nn, 1)) @ base


@functools.lru_cache(maxsize=8)
def _savgol2(window: int):
    """The pieces of ``scipy.signal.savgol_filter(x, window, 2, mode="interp")``, computed as
    it computes them: the convolution coefficients (``savgol_coeffs``), and the least-squares
    solver and column scale of its edge fits (``polyfit`` of a quadratic to ``window``
    samples, two columns at a time)."""
    from scipy.linalg import lstsq
    eps = np.finfo(np.float64).eps
    half = window // 2
    x = np.flip(np.arange(-half, window - half, dtype=np.float64))
    A = x ** np.reshape(np.arange(3, dtype=np.float64), (-1, 1))
    y = np.zeros(3, dtype=np.float64)
    y[0] = 1.0
    coeffs = lstsq(A, y, cond=eps * max(A.shape))[0]
    xe = np.arange(0, window, dtype=np.float64)
    lhs = xe[:, None] ** np.flip(np.arange(3, dtype=np.float64))[None, :]
    scale = np.sqrt(np.sum(lhs * lhs, axis=0))
    lhs /= scale
    rcond = window * eps

    # the edge fits' least squares (two columns: x, y), LAPACK's gelsd called as
    # scipy.linalg.lstsq calls it, its workspace sized once
    from scipy.linalg import get_lapack_funcs
    gelsd, gelsd_lwork = get_lapack_funcs(("gelsd", "gelsd_lwork"), (lhs, np.zeros((window, 2))))
    work, iwork, info = gelsd_lwork(window, 3, 2, rcond)
    if info != 0:
        raise ValueError(f"gelsd workspace query failed: {info}")
    lwork, liwork = int(work.real), int(iwork.real)

    def solve(b):
        if b.shape != (window, 2):
            return lstsq(lhs, b, cond=rcond)[0]
        x, _, _, info = gelsd(lhs, b, lwork, liwork, rcond, False, False)
        if info != 0:
            return lstsq(lhs, b, cond=rcond)[0]           # let lstsq raise as it does
        return x[:3]

    return coeffs, solve, scale


def _smooth_runs(x: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay (quadratic, ``window`` frames, zero phase) along each marker's
    contiguous runs; shorter runs are left as they are.

    The same numbers as ``scipy.signal.savgol_filter(run, window, 2, axis=0)`` on each run
    (mode ``interp``: the convolution inside, a quadratic fitted to the first and last
    ``window`` samples at the ends), without importing :mod:`scipy.signal` (which imports
    :mod:`scipy.stats`, most of a second of start-up): one convolution of all tracks (inside
    a run it only sees that run's samples), then the two end fits of each run.
    """
    out = x.copy()
    if window < 3:
        return out
    window |= 1
    if len(x) < window:
        return out
    from scipy.ndimage import convolve1d
    coeffs, solve, scale = _savgol2(window)
    half = window // 2
    conv = None
    i_lo = np.arange(0, half, dtype=np.float64).reshape(-1, 1)
    i_hi = np.arange(window - half, window, dtype=np.float64).reshape(-1, 1)

    def edge(xw, i):
        c = solve(xw)
        c = (c.T / scale).T
        y = np.zeros_like(i)
        for j in range(c.shape[0]):
            y = y * i + c[j, ...]
        return y

    for j in range(x.shape[1]):
        ok = np.isfinite(x[:, j]).all(axis=1)
        for a, b in zip(*_runs(ok)):
            if b - a < window:
                continue
            if conv is None:
                conv = convolve1d(x, coeffs, axis=0, mode="constant")
            out[a + half:b - half, j] = conv[a + half:b - half, j]
            out[a:a + half, j] = edge(x[a:a + window, j], i_lo)
            out[b - half:b, j] = edge(x[b - window:b, j], i_hi)
    return out


def estimate_frame_shifts(x: np.ndarray, window: int = 11, n_iter: int = 30, min_markers: int = 3,
                          z: float = 3.0) -> tuple[np.ndarray, dict]:
    """The common shift of one view's picture in each frame (F, 2) px, from its tracks ``x``
    (F, M, 2), NaN where not found.

    A shift common to a frame's markers is what their departures from their own smooth
    tracks (quadratic Savitzky-Golay over ``window`` frames) share: the median over the
    markers (at least ``min_markers``) of each frame's departures.  The shifts are taken out
    and the tracks smoothed again, ``n_iter`` times or until they settle; a frame's shift is
    kept where it exceeds ``z`` standard errors of that median (1.4826 MAD of the markers'
    departures over the square root of their number), else 0.  Only the part of the shifts
    that is not smooth over the window is found (the smooth part is the markers' common
    motion).

    Returns the shifts and ``{"n_frames", "rms_px", "max_px", "delta_bic", ...}``:
    ``delta_bic`` weighs a common offset per shifted frame (2 parameters each) against none,
    on the markers' departures from their smooth tracks (capped at 5 robust sd)."""
    F, M = x.shape[:2]
    found = np.isfinite(x).all(axis=2)
    n = found.sum(axis=1)
    enough = n >= min_markers
    o = np.zeros((F, 2))

    def departures(o):
        return x - _smooth_runs(x - o[:, None, :], window) - o[:, None, :]

    def median_over_markers(r):
        out = np.zeros((F, 2))
        if enough.any():
            out[enough] = np.nanmedian(r[enough], axis=1)
        return out

    v0 = (x - _smooth_runs(x, window))[found].ravel()       # departures without any shift
    nobs = len(v0)
    cap = (5 * max(1.4826 * float(np.median(np.abs(v0 - np.median(v0)))) if nobs else 0.0, 1e-12)) ** 2
    rss0 = float(np.sum(np.minimum(v0 ** 2, cap)))

    def kept(o):
        """The shifts that stand out of their frame's scatter (others 0), and the evidence."""
        r = departures(o)
        med = median_over_markers(r)
        sd = np.full((F, 2), np.inf)
        if enough.any():
            sd[enough] = 1.4826 * np.nanmedian(np.abs(r[enough] - med[enough][:, None, :]), axis=1)
        se = sd / np.sqrt(np.maximum(n, 1))[:, None]
        keep = enough & (np.abs(o) > z * se).any(axis=1)
        o = np.where(keep[:, None], o, 0.0)
        k = 2 * int(keep.sum())
        info = {"n_frames": int(keep.sum()), "n_frames_seen": int(enough.sum()),
                "rms_px": float(np.sqrt(np.mean(np.sum(o[keep] ** 2, axis=1)))) if keep.any() else 0.0,
                "max_px": float(np.hypot(o[:, 0], o[:, 1]).max()) if F else 0.0, "window_frames": int(window),
                "n_obs": nobs, "n_params": k, "delta_bic": 0.0}
        if nobs > k + 2:
            rss1 = float(np.sum(np.minimum(departures(o)[found].ravel() ** 2, cap)))
            info.update(rss0_px2=rss0, rss1_px2=rss1,
                        delta_bic=float(nobs * math.log(max(rss0, 1e-300) / max(rss1, 1e-300)) - k * math.log(nobs)))
        return o, info

    for it in range(max(1, int(n_iter))):
        new = o + median_over_markers(departures(o))
        done = float(np.abs(new - o).max()) < 1e-4 if F else True
        o = new
        if it == 0:
            first = kept(o)
            if first[1]["delta_bic"] <= 0:
                return first    # no shift that the first pass finds is worth its parameters
        if done:
            break
    return kept(o)


def low_rank_frame_shifts(x: np.ndarray, start: np.ndarray, n_iter: int = 50, min_markers: int = 3) -> np.ndarray:
    """Refine a view's frame shifts (F, 2) px with a motion model instead of smoothness: the
    markers' tracks ``x`` (F, M, 2) are a fixed position each, plus one shared time course
    times each marker's own displacement (rank 1: every marker moved by the indentor, each
    as far as it goes and in its own direction; a reference not at all), plus the frame's
    shift.  A shift cannot pose as that motion unless every marker moved alike, so most of
    its slow part, which smoothness cannot tell from the markers' common motion, is found
    too; what stays is a multiple of the time course (a shift along it and a common
    displacement of every marker fit alike), which the largest group of markers that move
    alike, the references, fixes by standing still (:func:`_still_group`).

    Alternating least squares from ``start`` (:func:`estimate_frame_shifts`): the rank-1
    fit (SVD, a missing position filled with the model's) of the tracks less the shifts,
    then each frame's shift as the median over its markers of what that fit leaves.  The
    shifts' mean is 0 (a constant is the markers')."""
    F, M = x.shape[:2]
    X = x.reshape(F, 2 * M)
    W = np.isfinite(X)
    ax = np.tile([0, 1], M)                       # the axis of each column: x0, y0, x1, y1, ...
    enough = np.isfinite(x).all(axis=2).sum(axis=1) >= min_markers
    o = np.array(start, float, copy=True)
    model = None
    with np.errstate(all="ignore"):
        for _ in range(max(1, int(n_iter))):
            Y = X - o[:, ax]
            c = np.nanmean(Y, axis=0)
            c = np.where(np.isfinite(c), c, 0.0)
            Yc = np.where(W, Y - c, 0.0 if model is None else model)
            U, S, Vt = np.linalg.svd(Yc, full_matrices=False)
            model = np.outer(U[:, 0] * S[0], Vt[0])
            R = np.where(W, X - c - model, np.nan)
            new = np.zeros((F, 2))
            for a in (0, 1):
                if enough.any():
                    new[enough, a] = np.nanmedian(R[enough][:, ax == a], axis=1)
            done = float(np.abs(new - o).max()) < 1e-5
            o = new
            if done:
                break
    if not enough.any():
        return o
    o = o - o[enough].mean(axis=0)
    return o + _still_group(x, o, enough, min_markers)


def still_frame_shifts(x: np.ndarray, start: np.ndarray, min_markers: int = 3) -> np.ndarray:
    """A view's frame shifts (F, 2) px read off the markers that stand still: the references
    fixed to the skull move only with the picture, so a frame's shift is the median over them
    of their departures from their own median positions, whatever the others do (a motion no
    model fits, a clock offset between the views, cannot leak in).  Still markers: with the
    shifts ``start`` taken out, those whose median distance from their median position is at
    most twice the ``min_markers``-th smallest such spread, or 0.15 px (at least
    ``min_markers``; else ``start`` is returned).  Frames where fewer than 2 of them are seen
    keep ``start``."""
    F, M = x.shape[:2]
    with np.errstate(all="ignore"):
        r = x - start[:, None, :]
        spread = np.nanmedian(np.hypot(*(r - np.nanmedian(r, axis=0)).transpose(2, 0, 1)), axis=0)
    ok = np.isfinite(spread)
    if ok.sum() < min_markers:
        return np.array(start, float, copy=True)
    s_k = np.sort(spread[ok])[min_markers - 1]
    still = ok & (spread <= max(2.0 * s_k, 0.15))
    dep = x[:, still] - np.nanmedian(x[:, still], axis=0)
    n = np.isfinite(dep).all(axis=2).sum(axis=1)
    with np.errstate(all="ignore"):
        o = np.nanmedian(dep, axis=1)
    return np.where((n >= 2)[:, None] & np.isfinite(o), o, start)


def _still_group(x: np.ndarray, o: np.ndarray, enough: np.ndarray, min_group: int = 3) -> np.ndarray:
    """What to add to a view's frame shifts ``o`` so that the largest group of markers that
    move alike stands still: the part of a jolt that follows the motion's time course fits
    as well as a common displacement of every marker, and references fixed to the skull are
    the markers whose displacement is that common one alone.  The tracks less ``o`` are
    fitted at rank 1 (time course ``u`` of unit RMS, each marker's displacement ``a_m`` in px);
    the group is the most markers (at least ``min_group``) whose displacements lie within
    ``max(0.05, 4 se)`` px of one of theirs (``se`` the displacement's standard error from the
    fit's residual); its mean displacement times ``u`` is returned (0 where there is none)."""
    F, M = x.shape[:2]
    y = x - o[:, None, :]
    with np.errstate(all="ignore"):
        c = np.nanmean(y[enough], axis=0)
    seen = np.isfinite(y).all(axis=2) & enough[:, None]
    if M < min_group or seen.sum() < 3 * M:
        return np.zeros_like(o)
    Yc = np.where(seen[..., None], y - c, 0.0).reshape(F, 2 * M)
    U, S, Vt = np.linalg.svd(Yc, full_matrices=False)
    n_u = max(int(enough.sum()), 1)
    u = U[:, 0] * np.sqrt(n_u)
    a = (Vt[0] * S[0] / np.sqrt(n_u)).reshape(M, 2)
    res = (Yc - np.outer(U[:, 0] * S[0], Vt[0])).reshape(F, M, 2)[seen]
    sd = 1.4826 * float(np.median(np.abs(res - np.median(res)))) if len(res) else 0.0
    tol = max(0.05, 4.0 * sd / np.sqrt(max(float(seen.sum(axis=0).min()), 1.0)))
    near = np.hypot(*(a[:, None, :] - a[None, :, :]).transpose(2, 0, 1)) <= tol
    best = int(np.argmax(near.sum(axis=1)))
    group = near[best]
    if group.sum() < min_group:
        return np.zeros_like(o)
    return np.outer(np.where(enough, u, 0.0), a[group].mean(axis=0))


def _gap_problem(d: StereoData, xb: np.ndarray | None, smooth_frames: int, reach_s: float):
    """What the clock searches share: both views' tracks smoothed alike (Savitzky-Golay,
    quadratic, ``smooth_frames``), the points both see that the tracker did not flag and
    whose B track covers A's time +- ``reach_s``, and ``gaps(tq)``: the signed ray gaps of
    those points with B interpolated (PCHIP) at its nominal times ``tq`` (one per frame of A);
    with ``d.steady_field`` the linear field of the markers' mean gaps over their positions
    taken out (:func:`_field_of_means`).  None where fewer than 3 points are left."""
    xb = _smooth_runs(d.xb if xb is None else xb, smooth_frames)
    xa_s = _smooth_runs(d.xa, smooth_frames)
    va, vb = d.views
    # B's tracks are undistorted once and interpolated in normalised image coordinates (the
    # distortion is smooth over a frame-to-frame step, so this is the same to ~1e-4 px):
    # undistorting afresh at every trial offset would cost more than everything else
    ub_all = xb.reshape(-1, 2)
    nb = np.full(ub_all.shape, np.nan)
    okb = np.isfinite(ub_all).all(axis=1)
    if okb.any():
        nb[okb] = vb.to_normalized(ub_all[okb])
    interp = _Interp(d.tb, nb.reshape(xb.shape))
    ua = xa_s.reshape(-1, 2)
    use = np.isfinite(ua).all(axis=1) & ~(d.suspect_a | d.suspect_b).ravel()
    use &= interp.covers(d.ta - reach_s, d.ta + reach_s).ravel()
    if use.sum() < 3:
        return None
    da = va.ray_directions(ua[use])
    base = vb.centre_mm - va.centre_mm
    Rb = vb.R
    # B is interpolated at the used points only (each in the one run that covers it)
    fi, mi = np.divmod(np.flatnonzero(use), xb.shape[1])
    a0, a1, a2 = da[:, 0].copy(), da[:, 1].copy(), da[:, 2].copy()
    un = np.empty_like(da)

    def gaps(tq: np.ndarray) -> np.ndarray:
        mb = interp.at_points(tq, mi, at=fi)
        db = mb @ Rb[:2] + Rb[2]                   # R^T (x, y, 1), as ray_directions
        # (n / |n|) @ base, n = da x db: np.cross and np.linalg.norm's operations, by column
        b0, b1, b2 = db[:, 0], db[:, 1], db[:, 2]
        n0, n1, n2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        nn = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
        np.divide(n0, nn, out=un[:, 0])
        np.divide(n1, nn, out=un[:, 1])
        np.divide(n2, nn, out=un[:, 2])
        g = un @ base
        if d.steady_field is not None:
            g = g - _field_of_means(g, mi, d.steady_field)[mi]
        return g

    return SimpleNamespace(gaps=gaps, fi=fi, mi=mi)


def _field_of_means(g: np.ndarray, mi: np.ndarray, pos: np.ndarray) -> np.ndarray:
    r"""Per marker (M,), the linear field :math:`c_0 + \mathbf c \cdot (\bar{\mathbf X}_m -
    \bar{\mathbf X})` fitted (weighted by their counts) to the markers' mean gaps ``g``
    (grouped by ``mi``) over their mean positions ``pos`` (M, 3); zero where fewer than five
    markers have positions."""
    M = len(pos)
    n = np.bincount(mi, minlength=M).astype(float)
    ok = (n > 0) & np.isfinite(pos).all(axis=1)
    out = np.zeros(M)
    if ok.sum() < 5:
        return out
    mean = np.bincount(mi, weights=g, minlength=M)[ok] / n[ok]
    P = pos[ok] - np.average(pos[ok], axis=0, weights=n[ok])
    A = np.column_stack([np.ones(int(ok.sum())), P])
    w = np.sqrt(n[ok])
    c, *_ = np.linalg.lstsq(A * w[:, None], mean * w, rcond=None)
    out[ok] = A @ c
    return out


def _minimise(cost, lo: float, hi: float, grid_n: int, xatol: float) -> tuple[float, float]:
    """The minimum of ``cost`` over [lo, hi]: a grid finds the basin, Brent's method (bounded)
    the minimum within the grid cell either side of the best node."""
    from scipy.optimize import minimize_scalar
    grid = np.linspace(lo, hi, grid_n)
    vals = np.array([cost(x) for x in grid])
    k = int(np.argmin(vals))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    res = minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": xatol})
    return (float(res.x), float(res.fun)) if res.fun <= vals[k] else (float(grid[k]), float(vals[k]))


def _held_out(even: np.ndarray, gain_all: float, one_half, key: str, at: str, against: str = "") -> tuple[dict, str | None]:
    """The even/odd check of a clock estimate: ``one_half(fit_on, other)`` finds it on the
    points ``fit_on`` and returns (the estimate, the gain it brings the ``other`` points);
    each half's must be at least half ``gain_all``, the gain on all points at ``at``.
    Returns the ``held_out`` record and why the estimate fails (None if it holds)."""
    held = {}
    for name, fit_on in (("even", even), ("odd", ~even)):
        est, gain = one_half(fit_on, ~fit_on)
        held[name] = {key: est, "gain_on_the_other_half": gain}
    worst = min(h["gain_on_the_other_half"] for h in held.values())
    why = None
    if worst < 0.5 * gain_all:
        why = (f"found on the even frames ({held['even'][key]:.4g}) or the odd ones ({held['odd'][key]:.4g}), it lowers "
               f"the other half's mean squared gap {against}by as little as {100 * worst:.1f} %, against "
               f"{100 * gain_all:.1f} % on all frames at {at}")
    return {"gain_all": gain_all, "fit_on": held}, why


def estimate_time_offset(d: StereoData, max_offset_s: float | None = None, xb: np.ndarray | None = None,
                         smooth_frames: int = 9) -> dict:
    r"""B's clock minus A's (s) that minimises the sum of squared ray gaps.

    Both views' 2-D tracks are first smoothed alike (Savitzky-Golay, quadratic,
    ``smooth_frames``; a shift in time commutes with the same filter, so this lowers the
    noise without biasing the offset), then B's (sampled at its nominal times ``tb``) are
    interpolated (PCHIP) to ``ta - delta``.  Every offset is judged on the same points: those both views see at both
    ends of the search range (so also in between) and that the tracker did not flag as
    partly hidden.  A grid over :math:`\pm` ``max_offset_s`` (default the larger of 3 frame
    periods and a tenth of the sequence) finds the basin and Brent's method the minimum of
    :math:`\sum g^2`; a second pass caps each term at :math:`(5 s)^2`, ``s`` the robust sd
    of the gaps there, so that a few wrong points cannot pull the estimate.

    The estimate is rejected (0, with ``offset_rejected_s`` and why in ``note``) unless it
    acts like a clock: it lowers the mean squared gap (outliers capped) by 2 % or more; B
    moved the other way by as much must fit worse than no offset
    (interpolating B between its frames averages noise that is not smooth in time, such as
    a jolt of its whole picture, alike either way), and the offset found on the even frames
    must lower the odd frames' mean squared gap, and the one found on the odd frames the even
    frames', by at least half the gain on all frames (noise shared by a frame's markers can
    line up with the motion by chance in one half, not in both; ``held_out``).
    """
    dt = float(np.nanmedian(np.diff(d.ta))) if len(d.ta) > 1 else 1.0
    duration = float(np.nanmax(d.ta) - np.nanmin(d.ta)) if len(d.ta) > 1 else dt
    lim = max(3.0 * dt, 0.1 * duration) if max_offset_s is None else float(max_offset_s)
    prob = _gap_problem(d, xb, smooth_frames, lim)
    if prob is None:
        return {"view_time_offset_s": 0.0, "search_s": [-lim, lim], "n_points": 0,
                "note": "too few points seen by both views over the whole search range"}
    fi = prob.fi

    def gaps(delta: float) -> np.ndarray:
        return prob.gaps(d.ta - delta)

    def minimise(cost, lo, hi, grid_n):
        return _minimise(cost, lo, hi, grid_n, 1e-7 * max(dt, 1e-3))

    d1, _ = minimise(lambda x: float(np.mean(gaps(x) ** 2)), -lim, lim, 81)
    g1 = gaps(d1)
    s1 = max(1.4826 * float(np.median(np.abs(g1 - np.median(g1)))), 1e-12)
    cap = (5 * s1) ** 2
    step = 2 * lim / 80
    d2, c2 = minimise(lambda x: float(np.mean(np.minimum(gaps(x) ** 2, cap))), d1 - 2 * step, d1 + 2 * step, 21)
    g0, gb = gaps(0.0), gaps(d2)
    out = {"view_time_offset_s": d2, "search_s": [float(-lim), float(lim)], "n_points": int(len(fi)),
           "rms_gap_mm_at_zero": float(np.sqrt(np.mean(g0 ** 2))),
           "rms_gap_mm_at_best": float(np.sqrt(np.mean(gb ** 2))), "robust_sd_mm": s1,
           "frame_period_s": dt, "smooth_frames": int(smooth_frames),
           "note": "gaps of the smoothed tracks, the points both views see over the whole search range"}
    # a clock offset is a direction in time: moving B the other way by as much must make the
    # gaps worse than no offset at all.  Interpolating B between its frames also averages
    # noise that is not smooth in time (a jolt of one view's whole picture, say), and does
    # so alike either way: an "offset" that gains only that is no evidence of a clock offset
    if d2 != 0.0:
        # outliers capped as in the search, on the scale of the gaps without an offset (at the
        # best offset the gaps of exact tracks are nothing, and would cap everything)
        s0 = 1.4826 * float(np.median(np.abs(g0 - np.median(g0))))
        cap0 = (5 * max(s0, s1)) ** 2
        m0, mb, mo = (float(np.mean(np.minimum(g ** 2, cap0))) for g in (g0, gb, gaps(-d2)))
        out["mean_sq_gap_mm2"] = {"zero": m0, "best": mb, "opposite": mo}
        gain_all = 1.0 - mb / m0 if m0 > 0 else 0.0
        why = None
        even = (fi % 2) == 0
        if not mo > m0:
            why = (f"B moved the other way by as much fits as well as or better than no offset (mean squared gap "
                   f"{mo:.3g} against {m0:.3g} mm^2; {mb:.3g} at the best): interpolation averaging noise, not a clock")
        elif gain_all < 0.02:
            # under 2 % of the typical squared gap (outliers capped): no evidence of a clock,
            # whatever a few large gaps make of the RMSE (as for the rate, see estimate_clock_drift)
            why = f"it lowers the mean squared gap (outliers capped) by only {100 * gain_all:.2f} %"
        elif even.sum() >= 10 and (~even).sum() >= 10:
            # a clock holds for every frame: the offset found on the even frames must also lower
            # the odd frames' gaps (noise shared by a frame's markers, such as a jolt, can
            # line up with the motion by chance in one half, not in both)
            def one_half(fit_on, other):
                dh, _ = minimise(lambda x: float(np.mean(np.minimum(gaps(x)[fit_on] ** 2, cap0))), -lim, lim, 81)
                h0 = float(np.mean(np.minimum(g0[other] ** 2, cap0)))
                return dh, 1.0 - float(np.mean(np.minimum(gaps(dh)[other] ** 2, cap0))) / h0

            out["held_out"], why = _held_out(even, gain_all, one_half, "offset_s", f"{d2:.4g} s")
        if why is not None:
            out.update(view_time_offset_s=0.0, offset_rejected_s=d2)
            out["note"] += "; offset rejected: " + why
    return out


#: The largest clock rate difference searched (2 %: frame clocks differ by parts per
#: thousand, video standards by 0.1 %; a twin rendered at 1 % had found its best at the old 1 %
#: bound, rejected there, and kept a constant offset 0.26-0.29 s off at the sequence's ends).
MAX_CLOCK_DRIFT = 0.02


def estimate_clock_drift(d: StereoData, max_offset_s: float | None = None, xb: np.ndarray | None = None,
                         smooth_frames: int = 9, max_drift: float | None = None) -> dict:
    r"""B's clock offset :math:`\delta` and rate :math:`\varepsilon` (B's frame at nominal
    time :math:`t` taken at :math:`t(1+\varepsilon)+\delta` on A's clock) that minimise the
    sum of squared ray gaps, capped at :math:`(5 s)^2` as in :func:`estimate_time_offset`
    (whose best constant offset is the start, and the model the drift must beat).

    Searched as the offset at mid-sequence :math:`t_m` (:math:`\delta + \varepsilon t_m`,
    nearly independent of the rate) and the rate: for every rate on a grid over
    :math:`\pm` ``max_drift`` (default: the rate that moves the offset by the offset search's
    range over the sequence, at most :data:`MAX_CLOCK_DRIFT`: frame clocks differ by parts per thousand), the best
    offset within 2 frame periods of the constant one; then Nelder-Mead from the best node.
    The rate is rejected (0, the constant offset kept, ``drift_rejected`` and why in
    ``note``) unless it acts like a clock: its minimum lies inside the range; it lowers the
    mean squared gap (outliers capped) below the constant offset's by 2 % or more; B's times moved
    the other way from the constant offset's by as much fit worse than the constant offset
    (interpolation between B's frames averages noise that is not smooth in time alike either
    way); and the rate found on the even frames lowers the odd frames' mean squared gap below
    the constant offset's, and the one found on the odd frames the even frames', by at least
    half the gain on all frames (``held_out``)."""
    from scipy.optimize import minimize
    const = estimate_time_offset(d, max_offset_s, xb, smooth_frames)
    dt = const.get("frame_period_s") or (float(np.nanmedian(np.diff(d.ta))) if len(d.ta) > 1 else 1.0)
    lim = float(const["search_s"][1])
    t0, t1 = (float(np.nanmin(d.ta)), float(np.nanmax(d.ta))) if len(d.ta) else (0.0, 0.0)
    duration = max(t1 - t0, dt)
    tm = 0.5 * (t0 + t1)
    eps_max = float(max_drift) if max_drift is not None else min(MAX_CLOCK_DRIFT, lim / duration)
    delta0 = float(const.get("offset_rejected_s", const["view_time_offset_s"]) or 0.0)
    out = {"view_time_offset_s": const["view_time_offset_s"], "view_clock_drift": 0.0, "constant": const,
           "drift_search": [-eps_max, eps_max], "mid_time_s": tm}
    # B's query times move by up to eps_max * |t| beyond the constant offset's
    prob = _gap_problem(d, xb, smooth_frames, lim + 2 * dt + eps_max * max(abs(t0), abs(t1)))
    if prob is None or len(prob.fi) < 10:
        out["note"] = "too few points seen by both views over the whole search range"
        return out
    fi = prob.fi

    def gaps(off_m: float, eps: float) -> np.ndarray:
        return prob.gaps((d.ta - (off_m - eps * tm)) / (1.0 + eps))

    g1 = gaps(delta0, 0.0)
    s1 = max(1.4826 * float(np.median(np.abs(g1 - np.median(g1)))), 1e-12)
    cap = (5 * s1) ** 2

    def cost(off_m, eps, sel=None):
        g = gaps(off_m, eps)
        return float(np.mean(np.minimum((g if sel is None else g[sel]) ** 2, cap)))

    def fit(sel=None):
        """(offset at mid-sequence, rate, cost) minimising the capped cost on the points ``sel``."""
        best = None
        for eps in np.linspace(-eps_max, eps_max, 21):
            om, c = _minimise(lambda x: cost(x, eps, sel), delta0 - 2 * dt, delta0 + 2 * dt, 7, 1e-6 * dt)
            if best is None or c < best[2]:
                best = (om, float(eps), c)
        res = minimize(lambda v: cost(v[0], v[1], sel), np.array(best[:2]), method="Nelder-Mead",
                       options={"xatol": 1e-7, "fatol": 1e-12 * max(best[2], 1e-30), "maxiter": 400})
        if res.fun < best[2] and abs(res.x[1]) <= eps_max:
            best = (float(res.x[0]), float(res.x[1]), float(res.fun))
        return best

    def const_cost(sel=None):
        om, c = _minimise(lambda x: cost(x, 0.0, sel), delta0 - 2 * dt, delta0 + 2 * dt, 21, 1e-6 * dt)
        return om, c

    om, eps, c_best = fit()
    _, c_const = const_cost()
    out.update({"view_time_offset_s": om - eps * tm, "view_clock_drift": eps, "offset_at_mid_s": om,
                "mean_sq_gap_mm2": {"constant": c_const, "best": c_best}, "n_points": int(len(fi)),
                "note": "capped squared gaps of the smoothed tracks; offset at mid-sequence and rate searched"})
    # a rate is a direction in time too: B's times moved the other way from the constant
    # offset's by as much must fit worse than the constant offset.  Interpolating B at
    # times between its frames averages noise that is not smooth in time (a jolt of its whole
    # picture), alike either way, and a rate that sweeps the offset over a frame period or
    # more gains that everywhere
    tq_c = d.ta - (delta0 if const["view_time_offset_s"] != 0.0 else 0.0)
    tq_b = (d.ta - (om - eps * tm)) / (1.0 + eps)
    c_zero = float(np.mean(np.minimum(prob.gaps(tq_c) ** 2, cap)))
    c_mirror = float(np.mean(np.minimum(prob.gaps(2 * tq_c - tq_b) ** 2, cap)))
    out["mean_sq_gap_mm2"].update({"without_rate": c_zero, "opposite_rate": c_mirror})
    even = (fi % 2) == 0
    gain_all = 1.0 - c_best / c_const if c_const > 0 else 0.0
    why = None
    if abs(eps) >= 0.98 * eps_max:
        # no minimum inside the range: what pulls the rate to its bound is not a clock (frame
        # clocks differ by parts per thousand, video standards by 0.1 %)
        why = f"at the bound of its search range (+-{eps_max:.3g}), no minimum inside it"
    elif not c_mirror > c_zero:
        why = (f"B's times moved the other way by as much fit as well or better (mean squared gap {c_mirror:.3g} "
               f"against {c_zero:.3g} mm^2 without the rate; {c_best:.3g} at the best): interpolation averaging "
               "noise, not a clock")
    elif gain_all < 0.02:
        # under 2 % of the typical squared gap (outliers capped) is no evidence of a rate,
        # whatever a few large gaps make of the RMSE (as for the offset)
        why = f"it lowers the mean squared gap (outliers capped) below the constant offset's by only {100 * gain_all:.2f} %"
    elif even.sum() >= 10 and (~even).sum() >= 10:
        def one_half(fit_on, other):
            # both models (with and without the rate) found on one half, judged on the other
            hm, he, _ = fit(fit_on)
            c0 = cost(const_cost(fit_on)[0], 0.0, other)
            return he, 1.0 - cost(hm, he, other) / c0 if c0 > 0 else 0.0

        out["held_out"], why = _held_out(even, gain_all, one_half, "drift", f"{eps:.3g}",
                                         against="below the constant offset's ")
    if why is not None:
        # the rate is no clock's: the constant offset (as estimate_time_offset judged it) stands
        out.update(drift_rejected=eps, view_clock_drift=0.0, view_time_offset_s=const["view_time_offset_s"])
        out["note"] += "; rate rejected: " + why
    return out


def _step_segments(C: np.ndarray, penalty: float) -> np.ndarray:
    """The piecewise-constant state path through the frames of least ``C[state, frame]``
    summed plus ``penalty`` per change of state (dynamic programming); (F,) state indices."""
    S, F = C.shape
    if F == 0:
        return np.zeros(0, int)
    cost = C[:, 0].copy()
    back = np.zeros((S, F), int)
    for f in range(1, F):
        k = int(np.argmin(cost))
        jump = cost[k] + penalty
        stay = cost <= jump
        back[:, f] = np.where(stay, np.arange(S), k)
        cost = np.where(stay, cost, jump) + C[:, f]
    path = np.empty(F, int)
    path[-1] = int(np.argmin(cost))
    for f in range(F - 1, 0, -1):
        path[f - 1] = back[path[f], f]
    return path


def stepped_times(d: StereoData, steps: list[dict] | None) -> tuple[np.ndarray, np.ndarray]:
    """Each view's frame times (``ta``, ``tb``) with its steps (:func:`estimate_frame_steps`)
    put right: where the ``view`` ``lost`` ``n_frames`` frames, its frames from ``frame`` on
    were taken that many periods later than their numbers say; where it ``repeated`` a frame
    ``n_frames`` times, the copies (``frame`` on, ``n_frames`` of them) get no time (they
    hold nothing new: A's have no 3-D point, B's are not interpolated) and the frames after
    them were taken that many periods earlier."""
    ta, tb = d.ta.astype(float), d.tb.astype(float)
    for st in steps or ():
        n, dt = int(st["n_frames"]), float(st["frame_period_s"])
        t = ta if st["view"] == d.views[0].name else tb
        if st["kind"] == "lost":
            t = t + np.where(d.frames >= st["frame"], n * dt, 0.0)
        else:
            copies = (d.frames >= st["frame"]) & (d.frames < st["frame"] + n)
            t = np.where(copies, np.nan, t - np.where(d.frames >= st["frame"] + n, n * dt, 0.0))
        if st["view"] == d.views[0].name:
            ta = t
        else:
            tb = t
    return ta, tb


def _repeated_run(x: np.ndarray, lo: int, hi: int, n: int) -> int | None:
    """The first index ``i`` in [lo, hi] where frames ``i .. i+n-1`` of the tracks ``x``
    (F, M, 2) repeat frame ``i - 1`` exactly (every marker found in both, at least 2):
    a repeated picture gives the tracker the same pixels, so the same centres to the bit."""
    F = len(x)

    def same(i):
        a, b = x[i], x[i - 1]
        ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        return ok.sum() >= 2 and np.array_equal(a[ok], b[ok])

    for i in range(max(lo, 1), min(hi, F - n) + 1):
        if all(same(i + r) for r in range(n)) and not (i + n < F and same(i + n)):
            return i
    return None


def estimate_frame_steps(d: StereoData, max_offset_s: float | None = None, xb: np.ndarray | None = None,
                         smooth_frames: int = 9, max_step_frames: int | None = None) -> dict:
    r"""Frames missing from one view (or repeated in it) partway through: B's clock minus A's
    is :math:`\delta + j_f\,\Delta t` at A's frame :math:`f`, :math:`\Delta t` the frame
    period and :math:`j_f` a whole number of frames, constant between steps.

    A view that drops :math:`k` frames (a recorder that skips frames, files deleted and the
    rest renumbered) pairs its later frames with the other view's taken :math:`k` periods
    earlier: a step in the offset that no constant offset or clock rate fits.  The capped
    squared gaps (as in :func:`estimate_time_offset`, of the smoothed tracks, over the points
    both views see) are summed per frame for every :math:`j` within
    :math:`\pm` ``max_step_frames`` of the constant offset (default: enough to reach the
    constant offset's search range from it, at least 5 and at most 30); the path of :math:`j` with the
    least sum plus a BIC penalty per step (its frame and size: :math:`2 \ln n`, on gaps in
    units of their robust variance) is found by dynamic programming; :math:`\delta` is then
    refined (Brent) on that path and the path found again.  Steps of
    :math:`k < 0` frames mean A's frames from there on were taken later than their index
    says (A lost :math:`|k|` frames, or B repeated some); :math:`k > 0`, the reverse.

    Returns ``view_time_offset_s`` (:math:`\delta` before the first step), ``frame_steps``
    (each: the ``view``, ``kind`` ``lost`` -- its first ``frame`` number taken ``n_frames``
    periods later than the number says; for B, which of its frames follows the gap is chosen
    on the gaps with its times put back -- or ``repeated`` -- the first of ``n_frames``
    copies of the frame before, found as frames identical to it in the view whose repeat
    makes the same step; ``frame_period_s``; see :func:`stepped_times`), ``gain`` of the
    capped mean squared gap, and the search's record; no steps where the path has none."""
    const = estimate_time_offset(d, max_offset_s, xb, smooth_frames)
    dt = float(const.get("frame_period_s") or (np.nanmedian(np.diff(d.ta)) if len(d.ta) > 1 else 1.0))
    delta0 = float(const["view_time_offset_s"])
    out = {"view_time_offset_s": delta0, "frame_steps": [], "constant": const, "frame_period_s": dt}
    if max_step_frames is None:
        lim = float(const["search_s"][1])
        max_step_frames = min(max(5, math.ceil((lim + abs(delta0)) / dt - 1e-9)), 30) if dt > 0 else 5
    out["max_step_frames"] = K = int(max_step_frames)
    prob = _gap_problem(d, xb, smooth_frames, abs(delta0) + (K + 1) * dt)
    if prob is None or len(prob.fi) < 10 or not np.isfinite(dt) or dt <= 0:
        out["note"] = "too few points seen by both views over the whole search range"
        return out
    fi = prob.fi
    F = len(d.ta)
    J = np.arange(-K, K + 1)
    g1 = prob.gaps(d.ta - delta0)
    s1 = max(1.4826 * float(np.median(np.abs(g1 - np.median(g1)))), 1e-12)
    cap = (5 * s1) ** 2
    penalty = 2.0 * math.log(len(fi))

    def frame_costs(delta: float) -> np.ndarray:
        """(2K+1, F): each frame's capped squared gaps at offset delta + j dt, in units of s1^2."""
        C = np.empty((len(J), F))
        for r, j in enumerate(J):
            g = prob.gaps(d.ta - (delta + j * dt))
            C[r] = np.bincount(fi, np.minimum(g * g, cap), minlength=F)
        return C / (s1 * s1)

    def total(delta: float, path: np.ndarray) -> float:
        g = prob.gaps(d.ta - (delta + J[path] * dt))
        return float(np.mean(np.minimum(g * g, cap)))

    path = _step_segments(frame_costs(delta0), penalty)
    delta = delta0
    if np.any(path != path[0]):
        delta, _ = _minimise(lambda x: total(x, path), delta0 - dt, delta0 + dt, 21, 1e-6 * dt)
        path = _step_segments(frame_costs(delta), penalty)
    c_const = float(np.mean(np.minimum(g1 * g1, cap)))
    c_path = total(delta, path)
    out["mean_sq_gap_mm2"] = {"constant": c_const, "steps": c_path}
    out["n_points"] = int(len(fi))
    out["note"] = ("capped squared gaps of the smoothed tracks per frame, offsets a whole number of frame periods "
                   "apart; path by dynamic programming, BIC penalty per step")
    change = np.flatnonzero(np.diff(path)) + 1
    if len(change) > 1:
        # the tracks are smoothed across a step (A's positions jump in time there), so the path
        # can take one step as several within the smoothing window: steps of one sign that close
        # are one, placed where it leaves the least cost
        groups = [[int(change[0])]]
        for c in change[1:]:
            p0, c0 = groups[-1][-1], groups[-1][0]
            same = np.sign(J[path[c]] - J[path[c - 1]]) == np.sign(J[path[c0]] - J[path[c0 - 1]])
            if c - p0 < smooth_frames and same:
                groups[-1].append(int(c))
            else:
                groups.append([int(c)])
        for grp in groups:
            if len(grp) == 1:
                continue
            lo, hi = grp[0], grp[-1]
            before, after = path[lo - 1], path[hi]
            best = None
            for c in range(lo, hi + 1):
                trial = path.copy()
                trial[lo:c] = before
                trial[c:hi + 1] = after
                t = total(delta, trial)
                if best is None or t < best[0]:
                    best = (t, trial)
            path = best[1]
        c_path = total(delta, path)
        out["mean_sq_gap_mm2"]["steps"] = c_path
        change = np.flatnonzero(np.diff(path)) + 1
    if len(change) == 0:
        # no step: the constant offset, as estimate_time_offset judged it
        out["note"] += "; no step"
        return out
    va, vb = d.views
    offset = float(delta + J[path[0]] * dt)
    steps = []
    for c in change:
        k = int(J[path[c]] - J[path[c - 1]])
        # the same step is one view losing |k| frames or the other repeating one |k| times: a
        # repeat shows as frames identical to the one before
        rep_view, x_rep = (va, d.xa) if k > 0 else (vb, d.xb)
        i = _repeated_run(x_rep, c - abs(k) - 2, c + 2, abs(k))
        if i is not None:
            steps.append({"view": rep_view.name, "kind": "repeated", "frame": int(d.frames[i]), "n_frames": abs(k),
                          "frame_period_s": dt, "found_at_frame": int(d.frames[c])})
            continue
        st = {"view": va.name if k < 0 else vb.name, "kind": "lost", "frame": int(d.frames[c]), "n_frames": abs(k),
              "frame_period_s": dt, "found_at_frame": int(d.frames[c])}
        if k > 0:
            # B lost frames: its frame paired with A's frame c is about c - k; which of B's
            # frames comes first after the gap is decided on the gaps with B's times put back
            # (A's frame in the gap is then interpolated across it)
            best = None
            for i in range(max(c - k - 1, 1), min(c - k + 3, F)):
                trial = steps + [{**st, "frame": int(d.frames[i])}]
                ta_s, tb_s = stepped_times(d, trial)
                pr = _gap_problem(replace(d, ta=ta_s, tb=tb_s), xb, smooth_frames, abs(offset) + dt)
                if pr is None:
                    continue
                g = pr.gaps(ta_s - offset)
                cst = float(np.mean(np.minimum(g * g, cap)))
                if best is None or cst < best[0]:
                    best = (cst, trial[-1])
            if best is not None:
                st = best[1]
        steps.append(st)
    # the clock offset itself as estimate_time_offset judges one (with its checks that it acts
    # like a clock), on the times with the lost frames put back
    ta_s, tb_s = stepped_times(d, steps)
    clock = estimate_time_offset(replace(d, ta=ta_s, tb=tb_s), max_offset_s, xb, smooth_frames)
    out.update(view_time_offset_s=float(clock["view_time_offset_s"]), frame_steps=steps, offset_search=clock,
               gain=1.0 - c_path / c_const if c_const > 0 else 0.0)
    return out


class WindowSource:
    """Search windows in a view's frames, read again on request (``track-capture``).

    ``sources``: view name -> frame source (what :func:`~bsipipe.io.images.iter_frames`
    reads).  :meth:`candidates` searches each asked window
    (:func:`~bsipipe.imaging.detect.window_arrays`, the tracker's own search) and keeps what it
    found, so a window asked for again is not searched again; a view's frames are read once
    per call that asks for new windows, up to the last frame asked for.  ``n_reads`` counts
    those reads.
    """

    def __init__(self, sources: dict, diameter_px: float | dict, polarity: str | dict = "dark", detection=None, *,
                 channel: int | None = None, workers: int = 1, rois: dict | None = None):
        self.sources = dict(sources)
        # view -> the FieldOfView a region of interest the user gave (its windows search it only)
        self.rois = dict(rois or {})
        # one diameter, or one per view (views at different magnifications)
        self.diameters = ({v: float(diameter_px[v]) for v in self.sources} if isinstance(diameter_px, dict)
                          else {v: float(diameter_px) for v in self.sources})
        self.polarity = polarity
        self.detection = detection
        self.channel = channel
        self.workers = workers
        self.n_reads = 0
        self._found: dict = {}

    def candidates(self, view: str, requests: dict) -> dict:
        """``requests``: frame -> list of windows ``(key, x_px, y_px, radius_px)``; returns
        ``{(frame, window): {column: array}}``, the candidates within each window (None where
        the source has no such frame)."""
        new = {f: [q for q in qs if (view, f, q) not in self._found] for f, qs in requests.items()}
        new = {f: qs for f, qs in new.items() if qs}
        if new:
            from ..io.images import iter_frames
            from .detect import DetectionSettings, window_arrays
            det = self.detection if self.detection is not None else DetectionSettings()
            self.n_reads += 1
            log.info("track-capture: reading %s's frames again for %d search window(s) in %d frame(s)", view,
                     sum(len(q) for q in new.values()), len(new))
            last = max(new)
            for fr in iter_frames(self.sources[view], channel=self.channel, workers=self.workers):
                if fr.index > last:
                    break
                qs = new.get(fr.index)
                if not qs:
                    continue
                c = np.array([[q[1], q[2]] for q in qs], float)
                r = np.array([q[3] for q in qs], float)
                pol = self.polarity[view] if isinstance(self.polarity, dict) else self.polarity
                cand = window_arrays(fr.image, c, r, self.diameters[view], pol, det, self.rois.get(view))
                xy = np.column_stack([cand["x_px"], cand["y_px"]])
                for q, cc, rr in zip(qs, c, r):
                    inside = np.hypot(xy[:, 0] - cc[0], xy[:, 1] - cc[1]) <= rr
                    self._found[(view, fr.index, q)] = {k: np.asarray(v)[inside] for k, v in cand.items()}
        return {(f, q): self._found.get((view, f, q)) for f, qs in requests.items() for q in qs}


#: The candidate columns a re-found position carries into the 2-D table.
CAPTURE_COLUMNS = ("x_px", "y_px", "amplitude", "sigma_px", "snr", "area_px")


def _capture_runs(g: np.ndarray, s: float, factor: float, min_run: int) -> list[tuple[int, int, int]]:
    """``(marker, first, stop)`` index runs where a marker's gap exceeds ``factor`` x ``s`` for
    at least ``min_run`` frames (runs less than ``min_run`` frames apart joined)."""
    big = np.isfinite(g) & (np.abs(g) > factor * s)
    out = []
    for j in np.flatnonzero(big.any(axis=0)):
        r0, r1 = _runs(big[:, j])
        runs: list[list[int]] = []
        for a, b in zip(r0.tolist(), r1.tolist()):
            if runs and a - runs[-1][1] < min_run:
                runs[-1][1] = b
            else:
                runs.append([a, b])
        out += [(int(j), a, b) for a, b in runs if big[a:b, j].sum() >= min_run]
    return out


#: The farthest the loop's track-capture looks for a marker from where its track was, in
#: marker diameters beyond its window's own 4 (the other view's motion over the run, up to this).
CAPTURE_REACH = 20.0


def _refind_windows(d: StereoData, own: np.ndarray, other: np.ndarray, shift: np.ndarray, j: int, idx: np.ndarray,
                    diameter_px: float) -> tuple[dict, float]:
    """The windows :func:`_refind` searches: ``{frame: [(key, x, y, radius)]}`` and the radius."""
    oth = other[idx, j]
    fin = np.isfinite(oth).all(axis=1)
    if fin.sum() < 2:
        return {}, 0.0
    ext = float(np.hypot(*(np.nanmax(oth[fin], axis=0) - np.nanmin(oth[fin], axis=0))))
    # the other view's motion bounds this one's only roughly (another angle, another scale);
    # beyond CAPTURE_REACH diameters it is no marker's motion but a picture that moved (one
    # C-arm panning: 450 px had made windows of 467 px, and static references were "found"
    # 261 px away along rays that met by chance)
    ext = min(ext, CAPTURE_REACH * diameter_px)
    radius = float(np.ceil(max(4.0 * diameter_px, 12.0) + ext))
    centre = pd.DataFrame(own[idx, j] + shift[idx]).ffill().bfill().to_numpy()
    if not np.isfinite(centre).all():
        return {}, 0.0
    req = {}
    for i, f in enumerate(d.frames[idx].tolist()):
        if fin[i]:
            req[f] = [(j, int(round(centre[i, 0])), int(round(centre[i, 1])), int(radius))]
    return req, radius


def _refind(d: StereoData, x: tuple, shifts: tuple, j: int, idx: np.ndarray, tol_mm: float,
            exclude: dict | None = None) -> dict | None:
    """Marker ``j`` searched again in both views over the frames ``idx``: in each view a window
    around where its track was (the tracker's pixels: the loop's ``x`` plus the view's frame
    ``shifts``) wide enough for the marker's motion in the other view, every candidate not held
    by another marker of that view; of the pairs whose rays pass within ``tol_mm`` of each other,
    the one nearest the pair taken last (the first: the nearest rays).  ``exclude``: view index ->
    ``(x, y, radius)``, a spot whose candidates are not taken (what held the track).  Returns
    the picks (index into ``idx``; per view the positions and the candidates' columns) or None."""
    from .track import _apart
    src = d.windows
    per_view = []
    for k in (0, 1):
        own, other = x[k], x[1 - k]
        dpx = src.diameters[d.views[k].name]
        req, radius = _refind_windows(d, own, other, shifts[k], j, idx, dpx)
        got = src.candidates(d.views[k].name, req) if req else {}
        raw_own = own + shifts[k][:, None, :]
        frames = []
        for i, f in enumerate(d.frames[idx].tolist()):
            c = got.get((f, req[f][0])) if f in req else None
            if c is None or len(c["x_px"]) == 0:
                frames.append(None)
                continue
            xy = np.column_stack([c["x_px"], c["y_px"]])
            others = np.delete(raw_own[idx[i]], j, axis=0)
            free = _apart(xy, others[np.isfinite(others).all(axis=1)], max(1.0, dpx))
            if exclude and k in exclude:
                ex, ey, er = exclude[k]
                free &= np.hypot(xy[:, 0] - shifts[k][idx[i], 0] - ex, xy[:, 1] - shifts[k][idx[i], 1] - ey) > er
            cols = {name: np.asarray(c[name], float)[free] for name in CAPTURE_COLUMNS}
            frames.append((xy[free] - shifts[k][idx[i]], cols))
        per_view.append((frames, radius))
    va, vb = d.views
    base = vb.centre_mm - va.centre_mm
    picks = []
    prev = None
    for i in range(len(idx)):
        fa, fb = per_view[0][0][i], per_view[1][0][i]
        if fa is None or fb is None or len(fa[0]) == 0 or len(fb[0]) == 0:
            continue
        g = np.abs(_gaps_from_dirs(va.ray_directions(fa[0])[:, None, :], vb.ray_directions(fb[0])[None, :, :], base))
        ok = np.isfinite(g) & (g < tol_mm)
        if not ok.any():
            continue
        a, b = np.nonzero(ok)
        if prev is None:
            q = int(np.argmin(g[a, b]))
        else:
            q = int(np.argmin(np.hypot(*(fa[0][a] - prev[0]).T) + np.hypot(*(fb[0][b] - prev[1]).T)))
        a, b = int(a[q]), int(b[q])
        prev = (fa[0][a], fb[0][b])
        picks.append((i, a, b, float(g[a, b])))
    if not picks:
        return None
    out = {"i": np.array([p[0] for p in picks]), "gap_mm": np.array([p[3] for p in picks]),
           "radius_px": [per_view[0][1], per_view[1][1]]}
    for k in (0, 1):
        sel = [(per_view[k][0][p[0]], p[1 + k]) for p in picks]
        out[f"xy{k}"] = np.array([fr[0][q] for fr, q in sel])
        out[f"cols{k}"] = {c: np.array([fr[1][c][q] for fr, q in sel]) for c in CAPTURE_COLUMNS}
    return out


def _gap_noise(g: np.ndarray) -> float:
    """The gaps' noise (mm) from their frame-to-frame changes: the median over the markers of
    the robust sd of each one's successive differences, over sqrt 2.  A bias that changes
    slowly (a track held off its marker) does not enter it, however many markers carry one."""
    sds = []
    for j in range(g.shape[1]):
        dg = np.diff(g[:, j])
        dg = dg[np.isfinite(dg)]
        if len(dg) >= 5:
            sds.append(1.4826 * float(np.median(np.abs(dg - np.median(dg)))) / math.sqrt(2))
    return max(float(np.median(sds)), 1e-9) if sds else float("nan")


def _moved_views(r: dict | None, x: tuple, j: int, idx: np.ndarray, min_run: int, moved_px: float,
                 n_run: int) -> list:
    """The views whose re-found positions (:func:`_refind`) lie elsewhere than the track in
    at least ``min_run`` frames, with the picks' mask of those frames; none unless the re-find
    took a pair in at least half of ``n_run`` frames."""
    if r is None or 2 * len(r["i"]) < n_run:
        return []
    out = []
    for k in (0, 1):
        moved = np.hypot(*(r[f"xy{k}"] - x[k][idx[r["i"]], j]).T)
        moved = ~(np.where(np.isfinite(moved), moved, np.inf) <= moved_px)
        if moved.sum() >= min_run:
            out.append((k, moved))
    return out


def find_captures(d: StereoData, xa: np.ndarray, xb: np.ndarray, shifts: tuple | None = None, *,
                  factor: float = 10.0, tol_factor: float = 4.0, min_run: int = 3,
                  moved_px: float = 0.5) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """``track-capture``: runs of frames where a marker's rays pass far apart (more than
    ``factor`` times their noise, :func:`_gap_noise`, at least ``min_run`` frames), its track searched again in
    each view along the other view's ray (:func:`_refind`, within ``tol_factor`` sd), and the
    view where that re-finds the marker somewhere else in at least ``min_run`` frames and
    agrees with the other view in at least half the run's frames taken: there the re-found
    positions replace the track's, and the run's frames where no candidate agrees are left out
    (the marker's image merged with what held its track).  Returns the new ``xa, xb`` and one
    dict per capture (``_frames``, ``_columns``, ``_dropped``: for the 2-D table).  ``shifts``:
    each view's common shift per frame (F, 2) already taken out of ``xa``, ``xb`` (frame-shift)."""
    if d.windows is None:
        return xa, xb, []
    F = len(d.frames)
    shifts = shifts if shifts is not None else (np.zeros((F, 2)), np.zeros((F, 2)))
    g = _gaps(replace(d, xa=xa), xb)
    s = _gap_noise(g)
    if not np.isfinite(s):
        return xa, xb, []
    xa, xb = xa.copy(), xb.copy()
    out = []
    runs = _capture_runs(g, s, factor, min_run)
    # every window of every run searched first, one read of each view's frames
    for k in (0, 1):
        own, other = (xa, xb) if k == 0 else (xb, xa)
        req: dict = {}
        for j, r0, r1 in runs:
            for f, q in _refind_windows(d, own, other, shifts[k], j, np.arange(r0, r1),
                                        d.windows.diameters[d.views[k].name])[0].items():
                req.setdefault(f, []).extend(q)
        if req:
            d.windows.candidates(d.views[k].name, req)
    done: dict[int, set] = {}
    near = {k: max(1.5, 0.5 * d.windows.diameters[d.views[k].name]) for k in (0, 1)}
    for j, r0, r1 in runs:
        idx = np.arange(r0, r1)
        if done.get(j, set()) >= set(idx.tolist()):
            continue
        r = _refind(d, (xa, xb), shifts, j, idx, tol_factor * s)
        changed = _moved_views(r, (xa, xb), j, idx, min_run, moved_px, len(idx))
        if not changed:
            continue
        # what held the track: where it stood in the frames the marker was found elsewhere.  A
        # static spot holds it wherever the marker passes close, inside the run or not (its
        # error may lie along the rays there, where the gap does not see it): every frame the
        # track stood on the spot is searched again, the spot's own candidates left out
        exclude = {}
        for k, moved in changed:
            held = (xa, xb)[k][idx[r["i"][moved]], j]
            c = np.median(held, axis=0)
            if np.median(np.hypot(*(held - c).T)) < 0.5:
                exclude[k] = (float(c[0]), float(c[1]), near[k])
        if exclude:
            on = np.zeros(len(d.frames), bool)
            on[idx] = True
            for k, (ex, ey, er) in exclude.items():
                own = (xa, xb)[k][:, j]
                on |= np.hypot(own[:, 0] - ex, own[:, 1] - ey) <= er
            idx2 = np.flatnonzero(on)
            r2 = _refind(d, (xa, xb), shifts, j, idx2, tol_factor * s, exclude)
            ch2 = _moved_views(r2, (xa, xb), j, idx2, min_run, moved_px, len(idx))
            if ch2:
                idx, r, changed = idx2, r2, ch2
        done.setdefault(j, set()).update(idx.tolist())
        cells = np.zeros(g.shape, bool)
        cells[idx, j] = True
        before = _gaps(replace(d, xa=xa), xb, cells)[idx, j]
        drop = np.setdiff1d(np.arange(len(idx)), r["i"])
        for k, moved in changed:
            own = (xa, xb)[k]
            own[idx[r["i"]], j] = r[f"xy{k}"]
            own[idx[drop], j] = np.nan
        after = _gaps(replace(d, xa=xa), xb, cells)[idx, j]
        for k, moved in changed:
            out.append({"marker": d.markers[j], "view": d.views[k].name, "first_frame": int(d.frames[idx[0]]),
                        "last_frame": int(d.frames[idx[-1]]), "n_refound": int(moved.sum()),
                        "n_left_out": int(len(drop)), "search_radius_px": r["radius_px"][k],
                        "held_at_px": list(exclude[k][:2]) if k in exclude else None,
                        "gap_rms_before_mm": float(np.sqrt(np.nanmean(before ** 2))),
                        "gap_rms_after_mm": (float(np.sqrt(np.nanmean(after ** 2))) if np.isfinite(after).any()
                                             else None),
                        "_frames": d.frames[idx[r["i"]]], "_columns": r[f"cols{k}"], "_dropped": d.frames[idx[drop]]})
    return xa, xb, out


def _one_sided(g, da, db, base, i: int, j: int, s: float, min_ratio: float, min_noise_factor: float):
    """Per frame, for a pair (i, j) where A sees one of the two and B both: whether B's other
    name fits A's marker far better (``yes``) or B's own does within the noise (``no``)."""
    yes = np.zeros(len(g), bool)
    no = np.zeros(len(g), bool)
    for a, b in ((i, j), (j, i)):
        own = np.abs(g[:, a])
        other = np.abs(_gaps_from_dirs(da[:, a], db[:, b], base))
        only = np.isfinite(own) & np.isfinite(other) & ~np.isfinite(g[:, b])
        yes |= only & (other < min_ratio * own) & (own > 0.5 * min_noise_factor * s)
        no |= only & (own < 3.0 * s)
    return yes, no


def _swap_runs(hit: np.ndarray, one_yes: np.ndarray, one_no: np.ndarray, cur: np.ndarray, alt: np.ndarray,
               s: float) -> list[tuple[int, int]]:
    """The frames of one swap: runs of two-sided evidence (``hit``) joined, with the frames
    between them, wherever no frame between shows the names right (both gaps within 3 sd of
    the noise as they are, or the one-sided test ``one_no``): a tracker keeps a name through
    the frames a marker is hidden in one view, so B's names stay exchanged until something
    shows them right.  A run then reaches on, either side, over frames of one-sided evidence
    (``one_yes``) and frames that show nothing."""
    F = len(hit)
    right = (np.isfinite(cur) & (cur < 3.0 * s) & ~(np.isfinite(alt) & (alt < cur))) | one_no
    out = []
    for r0, r1 in zip(*_runs(hit)):
        if out and not right[out[-1][1]:r0].any():
            out[-1] = (out[-1][0], int(r1))
        else:
            out.append((int(r0), int(r1)))
    grown = []
    for r0, r1 in out:
        while r0 > 0 and not right[r0 - 1] and (one_yes[r0 - 1] or not np.isfinite(cur[r0 - 1])):
            r0 -= 1
        while r1 < F and not right[r1] and (one_yes[r1] or not np.isfinite(cur[r1])):
            r1 += 1
        if grown and r0 <= grown[-1][1]:
            grown[-1] = (grown[-1][0], max(grown[-1][1], r1))
        else:
            grown.append((r0, r1))
    return grown


def find_swaps(d: StereoData, xb: np.ndarray, min_ratio: float = 0.25, min_noise_factor: float = 10.0) -> list[dict]:
    """Runs of frames where exchanging two of B's marker names makes both gaps small.

    A pair (i, j) is swapped in a frame when ``|g(A_i,B_j)| + |g(A_j,B_i)|`` is below
    ``min_ratio`` times ``|g(A_i,B_i)| + |g(A_j,B_j)|`` and the latter exceeds
    ``min_noise_factor`` robust sd of all gaps.  Such frames make one swap with the frames
    between them that show nothing against it, and it reaches on over frames where A sees
    one of the two and B's other name fits it (:func:`_swap_runs`): names exchanged in B's
    seeds stay exchanged through the frames one marker is hidden in A.
    """
    F, M = d.xa.shape[:2]
    # each view's rays are found once (undistortion is the costly part); a swap of two of
    # B's names only pairs A's rays of markers i, j with B's of j, i
    da, db = _ray_dirs(d.views[0], d.xa), _ray_dirs(d.views[1], xb)
    base = d.views[1].centre_mm - d.views[0].centre_mm
    g = _gaps_from_dirs(da, db, base)
    fin = g[np.isfinite(g)]
    if len(fin) < 3 or M < 2:
        return []
    s = 1.4826 * np.median(np.abs(fin - np.median(fin)))
    s = max(s, 1e-9)
    out = []
    # every pair (i < j) at once, in chunks of pairs (memory): the gaps with B's names exchanged
    I, J = np.triu_indices(M, 1)
    step = max(1, 2_000_000 // max(F, 1))
    for k0 in range(0, len(I), step):
        i_, j_ = I[k0:k0 + step], J[k0:k0 + step]
        cur_all = np.abs(g[:, i_]) + np.abs(g[:, j_])
        alt_all = np.abs(_gaps_from_dirs(da[:, i_], db[:, j_], base)) + np.abs(_gaps_from_dirs(da[:, j_], db[:, i_], base))
        hit_all = (np.isfinite(cur_all) & np.isfinite(alt_all) & (alt_all < min_ratio * cur_all)
                   & (cur_all > min_noise_factor * s))
        for k in np.flatnonzero(hit_all.any(axis=0)):
            i, j = int(i_[k]), int(j_[k])
            cur, alt, hit = cur_all[:, k], alt_all[:, k], hit_all[:, k]
            for r0, r1 in _swap_runs(hit, *_one_sided(g, da, db, base, i, j, s, min_ratio, min_noise_factor),
                                     cur, alt, s):
                idx = np.arange(r0, r1)
                out.append({"markers": [d.markers[i], d.markers[j]], "first_frame": int(d.frames[idx[0]]),
                            "last_frame": int(d.frames[idx[-1]]), "view": d.views[1].name,
                            "gap_before_mm": float(np.nanmean(cur[idx]) / 2),
                            "gap_after_mm": float(np.nanmean(alt[idx]) / 2), "_idx": (idx, i, j)})
    return out


def stereo_fit(d: StereoData, spec: StereoSpec, *, max_offset_s: float | None = None,
               fixed_offset_s: float | None = None, fixed_drift: float | None = None,
               fixed_steps: list[dict] | None = None) -> StereoFit:
    """Triangulate under ``spec`` (see the module docstring); ``fixed_offset_s`` (and
    ``fixed_drift`` or ``fixed_steps``) apply a known clock instead of estimating it."""
    va, vb = d.views
    F, M = d.xa.shape[:2]
    params: dict = {}
    n_params = 0
    xb = d.xb.copy()
    xa = d.xa.copy()
    swaps: list = []
    if spec.swaps:
        swaps = find_swaps(d, xb)
        for s in swaps:
            idx, i, j = s.pop("_idx")
            xb[np.ix_(idx, [i, j])] = xb[np.ix_(idx, [j, i])]
        params["identity_swaps"] = swaps
        n_params += len(swaps)
    shifts = None
    if spec.frame_shift:
        # each view's common shift per frame, taken out of its tracks before anything else
        # (the clock searches below see the corrected tracks)
        oa, ia = estimate_frame_shifts(xa)
        ob, ib = estimate_frame_shifts(xb)
        # a view whose tracks show no shifts worth their parameters keeps its positions
        oa = oa if ia["delta_bic"] > 10 else np.zeros_like(oa)
        ob = ob if ib["delta_bic"] > 10 else np.zeros_like(ob)
        # refined by the motion model where that makes the views agree better (the ray gaps
        # are the judge: the model assumes the markers moved together in time)
        # (not tried where the 2-D tracks show no shifts: the effect is vetoed there anyway)
        cand = {"smooth tracks": (oa, ob)}
        rss = {}
        if ia["delta_bic"] + ib["delta_bic"] > 0:
            la, lb = low_rank_frame_shifts(xa, oa), low_rank_frame_shifts(xb, ob)
            cand["rank-1 motion"] = (np.where((oa != 0).any(axis=1)[:, None], la, 0.0),
                                     np.where((ob != 0).any(axis=1)[:, None], lb, 0.0))
            cand["still markers"] = (np.where((oa != 0).any(axis=1)[:, None], still_frame_shifts(xa, la), 0.0),
                                     np.where((ob != 0).any(axis=1)[:, None], still_frame_shifts(xb, lb), 0.0))
            clock = spec.time_offset or spec.clock_drift or fixed_offset_s is not None
            for k, (sa, sb) in cand.items():
                ua, ub = xa - sa[:, None, :], xb - sb[:, None, :]
                if clock:
                    # with a clock in the model the shifts are judged after it: a set of shifts
                    # that soaks up part of the clock's gaps must not win for that (a motion no
                    # one time course fits leaks into the rank-1 shifts, and with it the offset)
                    dd = replace(d, xa=ua, xb=ub)
                    off = (float(fixed_offset_s) if fixed_offset_s is not None else
                           estimate_time_offset(dd, max_offset_s, ub)["view_time_offset_s"])
                    ub = _pchip_at(d.tb, ub, (d.ta - off) / (1.0 + float(fixed_drift or 0.0)))
                g = _triangulate(d.views, ua.reshape(-1, 2), ub.reshape(-1, 2))["ray_gap_signed_mm"]
                rss[k] = float(np.nansum(g ** 2))
        how = min(rss, key=rss.get) if rss else "smooth tracks"
        oa, ob = cand[how]
        xa = xa - oa[:, None, :]
        xb = xb - ob[:, None, :]
        d = replace(d, xa=xa, xb=xb)
        for info, o in ((ia, oa), (ib, ob)):
            keep = (o != 0).any(axis=1)
            info.update(method=how, rms_px=float(np.sqrt(np.mean(np.sum(o[keep] ** 2, axis=1)))) if keep.any() else 0.0,
                        max_px=float(np.hypot(o[:, 0], o[:, 1]).max()) if len(o) else 0.0)
        params["frame_shifts"] = {va.name: ia, vb.name: ib}
        params["frame_shift_ray_gap_ss_mm2"] = rss
        shifts = {va.name: oa, vb.name: ob}
    captures: list = []
    if spec.capture:
        # a view's track held by something else in its window: searched again along the other view's rays
        sh = (shifts[va.name], shifts[vb.name]) if shifts is not None else None
        xa, xb, captures = find_captures(d, xa, xb, sh)
        d = replace(d, xa=xa, xb=xb)
        params["track_captures"] = [{k: v for k, v in c.items() if not k.startswith("_")} for c in captures]
        n_params += len(captures)
    if spec.rig_mismatch:
        # the markers' mean positions, for the clock searches' field (as the views stand)
        r0 = _triangulate(d.views, xa.reshape(-1, 2), xb.reshape(-1, 2))["X_mm"].reshape(F, M, 3)
        with np.errstate(invalid="ignore"):
            d = replace(d, steady_field=np.nanmean(r0, axis=0) if np.isfinite(r0).any() else None)
    offset, drift = 0.0, 0.0
    tq = None                                       # B's (time-corrected) times paired with A's frames
    ta_s = d.ta                                     # A's times, the frames it lost put back
    if spec.time_offset or spec.clock_drift or spec.frame_steps or fixed_offset_s is not None:
        if fixed_offset_s is not None:
            offset = float(fixed_offset_s)
            drift = float(fixed_drift or 0.0)
            params["view_time_offset_s"] = offset
            if fixed_drift is not None:
                params["view_clock_drift"] = drift
            if fixed_steps:
                params["frame_steps"] = fixed_steps
        elif spec.frame_steps:
            est = estimate_frame_steps(d, max_offset_s, xb)
            offset = est["view_time_offset_s"]
            params["view_time_offset_s"] = offset
            params["frame_steps"] = est["frame_steps"]
            params["frame_steps_search"] = {k: v for k, v in est.items() if k != "frame_steps"}
            n_params += 1 + 2 * len(est["frame_steps"])
        elif spec.clock_drift:
            est = estimate_clock_drift(d, max_offset_s, xb)
            offset, drift = est["view_time_offset_s"], est["view_clock_drift"]
            params["view_time_offset_s"] = offset
            params["view_clock_drift"] = drift
            params["clock_drift_search"] = est
            n_params += 2
        else:
            est = estimate_time_offset(d, max_offset_s, xb)
            offset = est["view_time_offset_s"]
            params["view_time_offset_s"] = offset
            params["time_offset_search"] = est
            n_params += 1
        ta_s, tb_s = stepped_times(d, params.get("frame_steps"))
        tq = (ta_s - offset) / (1.0 + drift)
        xb = _pchip_at(tb_s, xb, tq)
    sus_a, sus_b = d.suspect_a.copy(), d.suspect_b.copy()
    if (spec.time_offset or spec.clock_drift or spec.frame_steps) and tq is not None and np.any(tq != d.ta):
        # B's flags move with its samples: a suspect sample taints the interpolated points near it
        sus_b = _flags_near(tb_s, sus_b, tq, np.nanmedian(np.diff(d.tb)))
    drop = np.zeros((F, M), bool)
    if spec.occlusion:
        drop = sus_a | sus_b
        params["excluded_partly_hidden"] = int((drop & np.isfinite(xa).all(axis=2) & np.isfinite(xb).all(axis=2)).sum())
    ua = np.where(drop[..., None], np.nan, xa)
    ub = np.where(drop[..., None], np.nan, xb)
    r = _triangulate(d.views, ua.reshape(-1, 2), ub.reshape(-1, 2))
    X = r["X_mm"].reshape(F, M, 3)
    g = r["ray_gap_signed_mm"].reshape(F, M)
    rep = r["reproj_px"].reshape(F, M, 2)
    n_views = np.where(np.isfinite(X).all(axis=2), 2, 0)
    source = np.where(n_views == 2, "two-view", "").astype(object)     # room for "single-view:NAME"
    if spec.occlusion:
        n_single = 0
        Xi = _interp_trajectory(d.ta, X)
        for view, u, tag in ((va, ua, va.name), (vb, ub, vb.name)):
            one = (n_views == 0) & np.isfinite(u).all(axis=2) & np.isfinite(Xi).all(axis=2)
            if one.any():
                X[one] = closest_point_on_ray(view, u[one], Xi[one])
                n_views[one] = 1
                source[one] = f"single-view:{tag}"
                n_single += int(one.sum())
        params["single_view_points"] = n_single
    # covariates: the 3-D velocity projected on the rays' common normal
    # (ta_s: A's frames after frames A lost were taken later than their nominal times say)
    vel = _velocity(ta_s, X)
    nrm = r["normal"].reshape(F, M, 3)          # the rays' common normals (NaN where a view is missing)
    v_perp = np.einsum("fmk,fmk->fm", vel, nrm)
    speed = np.linalg.norm(vel, axis=2)
    two = (n_views == 2) & np.isfinite(g)
    order = np.argwhere(two.T)                       # marker-major, frames in order
    mi, fi = order[:, 0], order[:, 1]
    res = g[fi, mi]
    rows = {"frame": np.repeat(d.frames[:, None], M, axis=1), "time_s": np.repeat(ta_s[:, None], M, axis=1),
            "marker": np.tile(np.array(d.markers, dtype=object)[None, :], (F, 1))}
    pts = pd.DataFrame({k: v.ravel() for k, v in rows.items()})
    pts["x_mm"], pts["y_mm"], pts["z_mm"] = X[..., 0].ravel(), X[..., 1].ravel(), X[..., 2].ravel()
    pts["ray_gap_mm"] = np.where(n_views == 2, np.abs(g), np.nan).ravel()
    pts["ray_gap_signed_mm"] = np.where(n_views == 2, g, np.nan).ravel()
    pts["reproj_err_px"] = np.where(n_views == 2, np.sqrt(0.5 * np.sum(np.nan_to_num(rep) ** 2, axis=2)), np.nan).ravel()
    pts[f"reproj_{va.name}_px"] = np.where(n_views == 2, rep[..., 0], np.nan).ravel()
    pts[f"reproj_{vb.name}_px"] = np.where(n_views == 2, rep[..., 1], np.nan).ravel()
    pts["n_views"] = n_views.ravel()
    pts["source"] = source.ravel()
    pts["speed_mm_s"] = speed.ravel()
    if not (len(d.frames) < 2 or np.all(np.diff(d.frames) > 0)) or len(set(d.markers)) < M:
        # rows by frame, then the markers' order (already so for increasing frames, distinct markers)
        pts = pts.sort_values(["frame", "marker"], kind="stable").reset_index(drop=True)
        pts["marker"] = pd.Categorical(pts["marker"], categories=d.markers)
        pts = pts.sort_values(["frame", "marker"], kind="stable").reset_index(drop=True)
    pts["marker"] = pts["marker"].astype(str)
    cov = {"v_perp_mm_s": np.nan_to_num(v_perp[fi, mi]), "speed_mm_s": np.nan_to_num(speed[fi, mi]),
           "time_s": ta_s[fi]}
    bias = None
    if spec.rig_mismatch:
        res, bias, info, rig = _rig_mismatch(res, mi, X[fi, mi], d.markers)
        params["rig_mismatch"] = info
        n_params += 4
    return StereoFit(spec, pts, res, params, n_params, cov, mi, fi, swaps, xb, frame_shifts=shifts,
                     captures=captures, gap_bias=bias, rig=rig if spec.rig_mismatch else None)


def _rig_mismatch(res: np.ndarray, mi: np.ndarray, X: np.ndarray, markers: list[str]
                  ) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    r"""The ``rig-mismatch`` effect: a linear field of the signed ray gap over the points' 3-D
    positions ``X`` (n, 3), :math:`g = c_0 + \mathbf c \cdot (\mathbf X - \bar{\mathbf X})`,
    taken out of the residuals (four parameters).  A rig whose views no longer match the
    calibration (a C-arm moved or turned since, a focal length off, a calibration of another
    session) makes the rays miss each other by an amount that changes smoothly with where
    the point is, over a field of a few centimetres about linearly, so steadily over
    millimetres of motion; with the markers moving at a steady speed, a time offset between
    the views fits part of it (a view turned 0.3 degrees: an offset of 0.25 s kept on a twin
    that has none; 1 % on the focal length 0.53 s; 2 mm across the baseline -0.72 s).  A
    marker's own steady bias (a speck beside it) is not such a field.  The 3-D points are
    left as they are: the gap shows the error across the rays, not along them.  Returns the
    residuals, the field's value at each residual, the parameters, and each marker's count
    and mean position (for the evidence)."""
    M = len(markers)
    ok = np.isfinite(X).all(axis=1)
    field_ = np.zeros(len(res))
    info = {"n_markers": int(len(np.unique(mi[ok]))) if ok.any() else 0}
    if ok.sum() >= 5:
        c0 = X[ok].mean(axis=0)
        A = np.column_stack([np.ones(int(ok.sum())), X[ok] - c0])
        c, *_ = np.linalg.lstsq(A, res[ok], rcond=None)
        field_[ok] = A @ c
        info.update(offset_mm=float(c[0]), gradient_mm_per_mm=[float(x) for x in c[1:]],
                    centre_mm=[float(x) for x in c0])
    n = np.bincount(mi, minlength=M)
    mean_pos = np.full((M, 3), np.nan)
    for k in range(3):
        mean_pos[:, k] = np.bincount(mi[ok], weights=X[ok, k], minlength=M) / np.maximum(
            np.bincount(mi[ok], minlength=M), 1)
    b = np.bincount(mi, weights=field_, minlength=M) / np.maximum(n, 1)
    used = n >= 1
    info.update(bias_mm={markers[j]: float(b[j]) for j in np.flatnonzero(used)},
                rms_bias_mm=float(np.sqrt(np.average(b[used] ** 2, weights=n[used]))) if used.any() else 0.0)
    return res - field_, field_, info, {"mean_pos": mean_pos, "n": n}


def _interp_trajectory(t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Each marker's 3-D trajectory interpolated (PCHIP) through its gaps, NaN outside."""
    out = X.copy()
    for j in range(X.shape[1]):
        ok = np.isfinite(X[:, j]).all(axis=1)
        if ok.sum() < 2:
            continue
        q = ~ok & (t > t[ok][0]) & (t < t[ok][-1])
        if q.any():
            out[q, j] = _Interp(t[ok], X[ok, j][:, None, :]).at_points(t[q], np.zeros(int(q.sum()), int))
    return out


def _velocity(t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Velocity (F, M, 3) mm/s: central differences, one-sided at the ends of each run."""
    v = np.full_like(X, np.nan)
    if len(t) < 2:
        return v
    fwd = (X[1:] - X[:-1]) / (t[1:] - t[:-1])[:, None, None]
    back = np.full_like(X, np.nan)
    forw = np.full_like(X, np.nan)
    back[1:] = fwd
    forw[:-1] = fwd
    v = 0.5 * (back + forw)
    return np.where(np.isfinite(v), v, np.where(np.isfinite(back), back, forw))


# --- effects and the loop --------------------------------------------------------------------------

def _occlusion_evidence(before, after) -> dict | None:
    """Do the tracker-flagged points' gaps spread more than the others'?  BIC of two
    variances against one (positive favours the effect)."""
    fit: StereoFit = before.fit
    flagged = fit.covariates.get("_suspect")
    if flagged is None or not flagged.any() or flagged.all():
        return None
    e = fit.residuals
    n, n1 = len(e), int(flagged.sum())
    n0 = n - n1
    if n1 < 1 or n0 < 2:
        return None
    v = max(float(np.mean(e ** 2)), 1e-300)
    v1 = max(float(np.mean(e[flagged] ** 2)), 1e-300)
    v0 = max(float(np.mean(e[~flagged] ** 2)), 1e-300)
    bic1 = n * math.log(v) + math.log(n)
    bic2 = n1 * math.log(v1) + n0 * math.log(v0) + 2 * math.log(n)
    return {"delta_bic": bic1 - bic2, "n_flagged": n1, "rms_flagged_mm": math.sqrt(v1), "rms_other_mm": math.sqrt(v0),
            "test": "Gaussian likelihood of the gaps: one variance vs a separate variance for the tracker-flagged points"}


def _frame_shift_evidence(before, after) -> dict | None:
    """A common shift per frame, from the 2-D tracks (each view's BIC of a common offset per
    shifted frame against none, :func:`estimate_frame_shifts`), and the ray gaps it must
    lower: the smaller of the two delta BICs (a shift both views see alike is the head
    moving: it leaves the gaps as they were)."""
    fs = after.fit.params.get("frame_shifts")
    if not fs:
        return None
    tracks = float(sum(v.get("delta_bic", 0.0) for v in fs.values()))
    gaps = float(before.bic - after.bic)
    return {"delta_bic": min(tracks, gaps), "tracks_2d_delta_bic": tracks, "ray_gap_delta_bic": gaps,
            "views": {k: {kk: v[kk] for kk in ("n_frames", "rms_px", "max_px", "delta_bic") if kk in v}
                      for k, v in fs.items()},
            "test": "Gaussian likelihood of the markers' departures from their smooth tracks with a common offset "
                    "per shifted frame against none (per view, summed), and of the ray gaps after against before; "
                    "the smaller"}


def _rig_mismatch_evidence(before, after) -> dict | None:
    r"""Are the markers' steady gaps a rig's field rather than a clock's?  A time offset gives
    marker m a mean gap :math:`\Delta t\,\bar v_m` (its mean velocity across the rays): the
    means line up with the velocities, and a still marker's is nothing.  A rig that no
    longer matches its calibration gives a field over the markers' positions, static
    references' included.  On the M markers' mean gaps: the clock alone (one parameter)
    against the clock and the linear field (five), an F test whose error is the means'
    scatter about the richer model (so a marker's own steady bias, a speck beside it,
    counts as noise, as it should), as :math:`\chi^2_4` of equal tail probability, shifted so
    that the loop's threshold of 10 falls at p = :data:`RIG_MISMATCH_P`.  Over a steady ramp
    either model fits the gaps; this is what tells them apart."""
    from ..distributions import chi2_isf, f_sf
    rig = after.fit.rig
    if rig is None:
        return None
    bf = before.fit
    n = rig["n"]
    M = len(n)
    nb = np.bincount(bf.groups, minlength=M)
    v = np.bincount(bf.groups, weights=bf.covariates["v_perp_mm_s"], minlength=M) / np.maximum(nb, 1)
    b = np.bincount(bf.groups, weights=bf.residuals, minlength=M) / np.maximum(nb, 1)
    pos = rig["mean_pos"]
    ok = (n >= 2) & np.isfinite(pos).all(axis=1) & (nb >= 2)
    m = int(ok.sum())
    if m < 8:
        return None
    w = np.sqrt(n[ok].astype(float))
    P = pos[ok] - np.average(pos[ok], axis=0, weights=n[ok])
    A1 = v[ok][:, None]
    A2 = np.column_stack([v[ok], np.ones(m), P])
    rss = []
    for A in (A1, A2):
        c, *_ = np.linalg.lstsq(A * w[:, None], b[ok] * w, rcond=None)
        rss.append(float(np.sum((w * (b[ok] - A @ c)) ** 2)))
    dof2 = m - A2.shape[1]
    if rss[1] <= 0:
        return None
    F = ((rss[0] - rss[1]) / 4.0) / (rss[1] / dof2)
    p = f_sf(max(F, 0.0), 4, dof2)
    chi2 = chi2_isf(max(p, 1e-300), 4)
    # on the loop's scale, with its threshold of 10 at p = RIG_MISMATCH_P: passing evidence
    # ranks the effect first, so the clock is then judged about the field (cam2 turned 0.3
    # degrees with a true 1 s offset: the offset kept first had ended 14 % off)
    return {"delta_bic": float(chi2 - chi2_isf(RIG_MISMATCH_P, 4) + 10.0), "f": float(F), "p": float(p),
            "dof": [4, dof2], "n_markers": m,
            "test": "the markers' mean ray gaps: a clock alone (time offset x mean velocity across the rays) against "
                    "the clock and a linear field over their positions, F test on the means' scatter, as chi-square "
                    f"of equal tail probability on the loop's scale (10 at p = {RIG_MISMATCH_P:g})"}


#: ``rig-mismatch`` is turned down unless its F test (:func:`_rig_mismatch_evidence`) has p
#: below this.  The test has only M - 5 degrees of freedom for its error (6 with the twin's 11
#: markers): its delta BIC, which needs F > 26 there, had turned down cam2 turned 0.3 degrees
#: (F 10.9), 0.2 degrees about x (17.5), its principal point 10 px off (13.9) and, with a
#: true 1 s offset, the 0.3 degrees (F 8.0, the offset then 25 % off).  Twelve twins with
#: their true cameras had F 0.15-5.1 (p 0.04 and above).
RIG_MISMATCH_P = 0.02


def _rig_mismatch_veto(before, after) -> str | None:
    """``rig-mismatch`` is kept only where its outside evidence says so
    (:func:`_rig_mismatch_evidence`, p below :data:`RIG_MISMATCH_P`): a marker's own steady
    bias (a speck, its rendering) is correlated over hundreds of frames, so the fit's delta
    BIC, counting them as independent, takes any such biases for a field (a twin with a true
    1 s offset and its true calibration: delta BIC 95, the offset then pulled to 0.91 s)."""
    if not after.spec.rig_mismatch or before.spec.rig_mismatch:
        return None
    ev = _rig_mismatch_evidence(before, after)
    if ev is None:
        return "too few markers (8 at least) to tell a rig's field from the markers' own steady biases"
    if ev["p"] >= RIG_MISMATCH_P:
        return (f"the markers' mean gaps need no field beyond a clock (F {ev['f']:.3g}, p {ev['p']:.3g}): their "
                "steady gaps are the markers' own biases")
    return None


def _switch(name: str):
    """An effect's ``apply``: the spec with its switch ``name`` on (None where it already is)."""
    return lambda s: None if getattr(s, name) else replace(s, **{name: True})


EFFECTS = (
    Effect("view-time-offset",
           "the two C-arms are not synchronised: view B's frames are taken a fixed time after (or before) A's",
           "the signed ray gap grows with the marker's velocity across the rays (covariate v_perp_mm_s): "
           "correlation test and runs of the residual",
           _switch("time_offset"), ("view_time_offset_s",)),
    Effect("view-clock-drift",
           "the two C-arms' frame clocks run at slightly different rates: the time between the views' frames "
           "grows (or shrinks) through the sequence",
           "the signed ray gap follows the marker's velocity across the rays, with a slope that changes with "
           "time (covariates v_perp_mm_s and time_s)",
           lambda s: None if s.clock_drift else replace(s, time_offset=True, clock_drift=True, frame_steps=False),
           ("view_time_offset_s", "view_clock_drift")),
    Effect("dropped-frames",
           "one view lost frames partway through (a recorder that skipped them, files deleted and the rest "
           "renumbered) or repeated some: from there on its frames are paired with the other view's taken whole "
           "frame periods apart",
           "the signed ray gap follows the marker's velocity across the rays from some frame on, or with a slope "
           "that changes there by a whole frame period (covariates v_perp_mm_s and time_s)",
           lambda s: None if s.frame_steps else replace(s, time_offset=True, clock_drift=False, frame_steps=True),
           ("view_time_offset_s", "frame_steps")),
    Effect("frame-shift",
           "a view's whole picture jolts from frame to frame (a C-arm's vibration): every marker of the frame is "
           "shifted by a common offset the other view does not see",
           "the gaps of a frame's markers move together, frame to frame; the markers' 2-D departures from their "
           "smooth tracks share an offset per frame",
           _switch("frame_shift"), ("frame_shifts",),
           evidence=_frame_shift_evidence),
    Effect("identity-swap",
           "two markers' names were exchanged in one view (they passed close and the tracker swapped them)",
           "two markers' gaps jump to many times the noise for a run of frames (group means, runs test)",
           _switch("swaps"), ("identity_swaps",)),
    Effect("track-capture",
           "a marker's track in one view was held by something else in its search window (a static spot: dust "
           "or a defect of the intensifier, another object) while the marker moved away",
           "one marker's gaps grow far beyond the noise for a run of frames (group means, runs test); the "
           "marker is found again along the other view's ray",
           _switch("capture"), ("track_captures",)),
    Effect("occlusion",
           "a marker partly hidden by an instrument is measured off centre at the frames next to its loss",
           "outlying gaps at the frames the tracker flagged (next to a loss, amplitude drop)",
           _switch("occlusion"), ("excluded_partly_hidden",),
           evidence=_occlusion_evidence),
    Effect("rig-mismatch",
           "the views no longer match the calibration (a C-arm moved or turned since it was calibrated, or the "
           "calibration is another session's): the rays miss each other by a steady amount that changes smoothly "
           "with where the point is",
           "the markers' mean signed gaps follow their positions, static markers' too, not their velocities "
           "across the rays (group means of the residual)",
           _switch("rig_mismatch"), ("rig_mismatch",),
           evidence=_rig_mismatch_evidence),
)


def close_stereo_loop(d: StereoData, *, loop: bool = True, max_offset_s: float | None = None,
                      candidates=EFFECTS) -> tuple[dict, StereoFit, LoopReport | None]:
    """Fit the declared stereo model, run the loop over :data:`EFFECTS`, and return the
    loop's dict (contract shape, with ray gap and reprojection error before/after each step),
    the final fit and the report (None with ``loop=False``)."""
    cache: dict = {}

    def fit(spec):
        if spec not in cache:
            f = stereo_fit(d, spec, max_offset_s=max_offset_s)
            # which residuals the tracker flagged (for the occlusion evidence)
            f.covariates["_suspect"] = (d.suspect_a | d.suspect_b)[f.frame_index, f.groups]
            cache[spec] = f
        return cache[spec]

    base = fit(StereoSpec())
    if not loop:
        return {"baseline": _summary(base), "steps": [], "final": _summary(base), "residual_structure": None,
                "enabled": False}, base, None

    def cov(res):
        return {k: v for k, v in res.covariates.items() if not k.startswith("_")}

    report = run_loop(fit, StereoSpec(), candidates, covariates=cov, groups=lambda r: r.groups,
                      describe=lambda s: s.describe(), unit="mm", veto=_rig_mismatch_veto)
    out = report.to_dict()
    for step, sd in zip(report.steps, out["steps"]):
        b, a = step.before.fit, step.after.fit
        sd["ray_gap_rms_mm_before"], sd["ray_gap_rms_mm_after"] = b.ray_gap_rms_mm, a.ray_gap_rms_mm
        sd["reprojection_rms_px_before"], sd["reprojection_rms_px_after"] = b.reproj_rms_px, a.reproj_rms_px
    for key, st in (("baseline", report.baseline), ("final", report.final)):
        out[key].update(_summary(st.fit))
    out["enabled"] = True
    return out, report.final.fit, report


def _summary(f: StereoFit) -> dict:
    p = f.points
    return {"model": f.spec.describe(), "params": f.params, "ray_gap_rms_mm": f.ray_gap_rms_mm,
            "ray_gap_median_mm": float(np.nanmedian(p["ray_gap_mm"])) if p["ray_gap_mm"].notna().any() else None,
            "reprojection_rms_px": f.reproj_rms_px, "n_two_view": int((p["n_views"] == 2).sum()),
            "n_single_view": int((p["n_views"] == 1).sum())}


def match_tracks_across_views(table: pd.DataFrame, views: tuple[ViewGeometry, ViewGeometry],
                              max_gap_mm: float = 1.0, min_gap_mm: float = 0.3, min_common: int = 3,
                              max_shift_frames: int = 3, ambiguous: list | None = None,
                              paired_costs: list | None = None) -> dict[str, str]:
    """Names for view B's automatic tracks that make them the same markers as view A's.

    Without seeds each view names its tracks on its own; the epipolar geometry pairs them.
    The cost of pairing track a (view A) with track b (view B) is the median absolute ray gap
    over the frames both see (at least ``min_common``), the least of it over whole-frame
    shifts of B's frames up to ``max_shift_frames`` (a clock offset between the views, not yet
    found, widens a moving marker's true gaps; the nearest whole-frame shift takes most of it
    out).  The pairing is the one of least total cost (``linear_sum_assignment``) in which
    every B track may also stay unpaired at cost ``tau``: a track does not take a poor partner,
    nor push another track off its good one, only because every track must take something
    (static spots seen in both views, a speck of dust or a bone edge, would otherwise pair
    with anything near their rays, and with the markers).  ``tau`` is five times the median
    over B's tracks of their cheapest cost (its lower quartile: the pairs that fit best, whatever
    the clutter), within ``[min_gap_mm, max_gap_mm]``: the noise of true pairs sets it, a
    calibration with large gaps widens it.  Returns ``{B name: A
    name}``; an unpaired B track keeps its name, prefixed with B's view.

    ``ambiguous`` (a list), where given, receives each two pairs whose crossed pairing costs
    within :data:`PAIRING_AMBIGUITY` good pairs' costs of theirs (markers on nearly one
    epipolar line in both views, static ones above all: two references so placed had been
    paired crosswise, 4 mm off, unsaid): ``(A name, B name, A name, B name, cost, crossed
    cost)``.  ``paired_costs`` (a list), where given, receives the cost (mm) of each pair made.
    """
    from scipy.optimize import linear_sum_assignment
    va, vb = views
    ta = table[(table["view"] == va.name) & table["found"]]
    tb = table[(table["view"] == vb.name) & table["found"]]
    na, nb = list(pd.unique(ta["marker"])), list(pd.unique(tb["marker"]))
    out = {b: f"{vb.name}:{b}" for b in nb}
    if not (na and nb):
        return out
    frames = np.union1d(ta["frame"].to_numpy(), tb["frame"].to_numpy())
    F = len(frames)

    def rays(t, view, names):
        # (F, n, 3) ray directions on the common frame grid, NaN where a track is not seen
        d = np.full((F, len(names), 3), np.nan)
        fi = np.searchsorted(frames, t["frame"].to_numpy())
        mi = pd.Index(names).get_indexer(t["marker"])
        d[fi, mi] = _ray_dirs(view, t[["x_px", "y_px"]].to_numpy(float))
        return d

    da, db = rays(ta, va, na), rays(tb, vb, nb)
    base = vb.centre_mm - va.centre_mm
    cost = np.full((len(nb), len(na)), np.inf)
    with np.errstate(all="ignore"):
        for k in range(-max_shift_frames, max_shift_frames + 1):
            # A's frame f with B's frame f + k (whole frames of the common grid)
            a_sl = slice(max(0, -k), F - max(0, k))
            b_sl = slice(max(0, k), F - max(0, -k))
            if a_sl.stop - a_sl.start < min_common:
                continue
            for j0 in range(0, len(na), 16):       # chunks of A's tracks: memory stays (F, 16, nB)
                g = np.abs(_gaps_from_dirs(da[a_sl, j0:j0 + 16, None, :], db[b_sl, None, :, :], base))
                n = np.isfinite(g).sum(axis=0)
                med = np.where(n >= min_common, np.nanmedian(g, axis=0), np.inf)      # (16, nB)
                cost[:, j0:j0 + 16] = np.minimum(cost[:, j0:j0 + 16], med.T)
    best = cost.min(axis=1)
    best = best[np.isfinite(best)]
    if not len(best):
        return out
    q25 = float(np.percentile(best, 25))
    tau = float(np.clip(5.0 * q25, min_gap_mm, max_gap_mm))
    log.debug("cross-view pairing: best costs %s, tau %.3f", np.round(np.sort(best), 3).tolist(), tau)
    big = 1e9
    miss = np.full((len(nb), len(nb)), big)
    np.fill_diagonal(miss, tau)
    r, c = linear_sum_assignment(np.hstack([np.where(cost < tau, cost, big), miss]))
    pairs = []
    for i, j in zip(r, c):
        if j < len(na) and cost[i, j] < tau:
            out[nb[i]] = na[j]
            pairs.append((i, j))
            if paired_costs is not None:
                paired_costs.append(float(cost[i, j]))
    if ambiguous is not None:
        for x in range(len(pairs)):
            for y in range(x + 1, len(pairs)):
                (i, j), (k, m) = pairs[x], pairs[y]
                now, crossed = cost[i, j] + cost[k, m], cost[i, m] + cost[k, j]
                if (cost[i, m] < tau and cost[k, j] < tau
                        and crossed <= now + PAIRING_AMBIGUITY * max(q25, 1e-6)):
                    ambiguous.append((na[j], nb[i], na[m], nb[k], float(now), float(crossed)))
    return out


#: Two pairs of tracks are ambiguous across the views when pairing them crosswise costs (sum of
#: median |ray gaps|) at most this many times a good pair's cost (the lower quartile of the
#: tracks' best costs) more than their own pairing, each crossed pair under the pairing limit.
PAIRING_AMBIGUITY = 2.0


#: The eight orientations of a picture (the square's symmetries), as (name, map) with the map
#: taking pixel coordinates (n, 2) of a w x h frame to those of the frame so turned; turns by
#: a quarter only for square frames.
def _orientations(w: int, h: int) -> list[tuple[str, callable]]:
    X, Y = w - 1.0, h - 1.0
    out = [("mirrored left-right", lambda p: np.column_stack([X - p[:, 0], p[:, 1]])),
           ("mirrored top-bottom", lambda p: np.column_stack([p[:, 0], Y - p[:, 1]])),
           ("turned 180 degrees", lambda p: np.column_stack([X - p[:, 0], Y - p[:, 1]]))]
    if w == h:
        out += [("turned 90 degrees clockwise", lambda p: np.column_stack([Y - p[:, 1], p[:, 0]])),
                ("turned 90 degrees anticlockwise", lambda p: np.column_stack([p[:, 1], X - p[:, 0]])),
                ("transposed", lambda p: np.column_stack([p[:, 1], p[:, 0]])),
                ("transposed the other way", lambda p: np.column_stack([Y - p[:, 1], X - p[:, 0]]))]
    return out


_INVERSE = {"turned 90 degrees clockwise": "turned 90 degrees anticlockwise",
            "turned 90 degrees anticlockwise": "turned 90 degrees clockwise"}


def orientation_check(d: StereoData, shapes: dict, *, factor: float = 4.0, min_markers: int = 4) -> dict | None:
    """Whether one view's frames look turned or mirrored against the calibration (an export
    that flips the picture, the calibration taken from frames oriented otherwise), or the two
    views' frames given the other way round: the two-view points' median |ray gap| as the
    frames are, with each view's positions mirrored or turned (:func:`_orientations`) in
    turn, and with the views exchanged (frames of one size).  Returns the orientation the frames
    look to have (view, the name of the turn that, undone, fits best, median gaps) where it brings the median gap down ``factor`` times or more,
    with at least ``min_markers`` markers seen in both views; else None.  ``shapes``: view
    name -> (h, w) of its frames."""
    from .triangulate import ray_gaps
    both = np.isfinite(d.xa).all(axis=2) & np.isfinite(d.xb).all(axis=2)
    if int(both.any(axis=0).sum()) < min_markers:
        return None
    ua, ub = d.xa[both], d.xb[both]
    as_is = float(np.median(np.abs(ray_gaps(d.views, ua, ub))))
    best = None
    for cand, views in _orientation_candidates(d.views, shapes):
        m = float(np.median(np.abs(ray_gaps(views, ua, ub))))
        if best is None or m < best["median_gap_mm"]:
            best = {**cand, "median_gap_mm": m}
    if best is None or not best["median_gap_mm"] * factor <= as_is:
        return None
    return {**best, "median_gap_as_is_mm": as_is, "n_points": int(both.sum())}


def _orientation_candidates(views: tuple[ViewGeometry, ViewGeometry], shapes: dict):
    """The ways two views' frames may be oriented against their calibration, in the order
    :func:`orientation_check` and :func:`pairing_orientation` try them: each view's frames
    mirrored or turned (:func:`_orientations`; a view without a shape is skipped), then the two
    views' frames exchanged (frames of one size).  Yields ``({"view", "orientation",
    "map_back"}, views as they would then be)``: the orientation the frames look to have is the
    inverse of the map that brings them back."""
    for k, v in enumerate(views):
        shape = shapes.get(v.name)
        if shape is None:
            continue
        h, w = int(shape[0]), int(shape[1])
        for name, _ in _orientations(w, h):
            yield ({"view": v.name, "orientation": _INVERSE.get(name, name), "map_back": name},
                   tuple(reoriented_view(g, name, shape) if i == k else g for i, g in enumerate(views)))
    if all(shapes.get(v.name) is not None for v in views) and \
            tuple(shapes[views[0].name]) == tuple(shapes[views[1].name]):
        yield ({"view": f"{views[0].name} and {views[1].name}", "orientation": "swapped", "map_back": "swapped"},
               swapped_views(views))


#: Frames of the automatic tracks the trial pairings of :func:`pairing_orientation` use at most
#: (evenly spaced): fifteen pairings of a long sequence cost what a few of its frames do.
PAIRING_TRIAL_FRAMES = 100


def pairing_orientation(table: pd.DataFrame, views: tuple[ViewGeometry, ViewGeometry], shapes: dict, *,
                        factor: float = 4.0, min_pairs: int = 4, unpaired_mm: float = 1.0) -> dict | None:
    """:func:`orientation_check` for automatic tracks, which are not yet named across the views:
    the views' tracks paired (:func:`match_tracks_across_views`) as the frames are, and with each
    view's positions mirrored or turned back in turn (:func:`reoriented_view`), on at most
    :data:`PAIRING_TRIAL_FRAMES` frames.  Each pairing's cost is the mean over the smaller view's
    tracks of their pair's cost (median |ray gap|), an unpaired track counting ``unpaired_mm``
    (the pairing's largest cost): the frames as they are pair few tracks where a view's are
    mirrored, some of them well by chance (the bench twin with cam2 mirrored: 6 of 12 tracks at a
    median of 0.044 mm, 12 at 0.023 mirrored back).  A view's frames look turned where that
    pairing makes at least ``min_pairs`` pairs at a cost ``factor`` times lower or more.  Returns
    :func:`orientation_check`'s dict with these costs for ``median_gap_mm`` and
    ``median_gap_as_is_mm``, ``n_points`` the pairs made (``n_points_as_is`` as the frames are),
    or None."""
    frames = np.unique(table["frame"].to_numpy())
    if len(frames) > PAIRING_TRIAL_FRAMES:
        keep = frames[np.linspace(0, len(frames) - 1, PAIRING_TRIAL_FRAMES).round().astype(int)]
        table = table[table["frame"].isin(keep)]
    found = table[table["found"]]
    m = min(found.loc[found["view"] == v.name, "marker"].nunique() for v in views)
    if m < min_pairs:
        return None

    def trial(vpair):
        costs: list = []
        match_tracks_across_views(table, vpair, max_gap_mm=unpaired_mm, paired_costs=costs)
        return len(costs), (float(np.sum(costs)) + (m - len(costs)) * unpaired_mm) / m

    n0, c0 = trial(views)
    best = None
    for cand, turned in _orientation_candidates(views, shapes):
        n, c = trial(turned)
        if n >= min_pairs and (best is None or c < best["median_gap_mm"]):
            best = {**cand, "median_gap_mm": c, "n_points": n}
    if best is None or not best["median_gap_mm"] * factor <= c0:
        return None
    return {**best, "median_gap_as_is_mm": c0, "n_points_as_is": n0,
            "measure": f"the mean pair cost (median |ray gap|, an unpaired track counted {unpaired_mm:g} mm)"}


def swapped_views(views: tuple[ViewGeometry, ViewGeometry]) -> tuple[ViewGeometry, ViewGeometry]:
    """Each view's name on the other's geometry: two views' frames given the other way round
    against the calibration's cameras (``--view cam1=<cam2's frames>``), each triangulated
    through the camera that took it; the world frame stays the calibration's."""
    a, b = views
    return replace(b, name=a.name), replace(a, name=b.name)


def reoriented_view(view: ViewGeometry, map_back: str, shape) -> ViewGeometry:
    """``view``'s geometry for frames turned or mirrored against its calibration: pixels of the
    frames (``shape`` (h, w)) go to the calibration's pixels by ``map_back`` (a name of
    :func:`_orientations`, as :func:`orientation_check` gives it) before the calibrated model
    undistorts them, and projections come back the other way.  Everything that works in the
    frames' own pixels (triangulation, reprojection errors, the loop's search in the frames)
    then agrees with the calibration, with no frame or position rewritten.

    >>> from bsipipe.imaging.triangulate import ViewGeometry
    >>> v = ViewGeometry("a", np.eye(3), np.zeros(3), np.eye(3), lambda u: u / 100.0, lambda m: m * 100.0, (8, 8))
    >>> w = reoriented_view(v, "turned 90 degrees clockwise", (8, 8))
    >>> w.to_normalized(np.array([[1.0, 2.0]])).tolist(), w.to_pixels(w.to_normalized(np.array([[1.0, 2.0]]))).tolist()
    ([[0.05, 0.01]], [[1.0, 2.0]])
    """
    h, w = int(shape[0]), int(shape[1])
    maps = dict(_orientations(w, h))
    back, fwd = maps[map_back], maps[_INVERSE.get(map_back, map_back)]
    return ViewGeometry(view.name, view.R, view.t, view.K,
                        lambda u: view.to_normalized(back(np.asarray(u, float).reshape(-1, 2))),
                        lambda m: fwd(np.asarray(view.to_pixels(m), float).reshape(-1, 2)), (w, h))
