r"""Optimal smoothing of 2-D marker tracks: a Kalman filter and Rauch-Tung-Striebel smoother.

A detected centre is the true image position plus noise whose size the detector knows: a
Gaussian spot of peak amplitude :math:`A` in white pixel noise :math:`\sigma_n` cannot be
located better than the Cramer-Rao bound

.. math::

    \sigma_x = \sigma_y = \sqrt{2/\pi}\,\sigma_n / A = 0.798 / \mathrm{SNR}

per axis, whatever the spot's width, and the Gaussian fit of
:mod:`bsipipe.imaging.detect` reaches it.  A marker in tissue moves smoothly between
frames, so the positions of neighbouring frames carry information about this one.  Each
axis of each track is modelled as a particle with white-noise acceleration (the "nearly
constant velocity" model of tracking),

.. math::

    \begin{aligned}
    x_{k+1} &= x_k + \Delta t\,v_k + w_{x}, &
    v_{k+1} &= v_k + w_{v}, &
    \operatorname{cov}(w) &= q \begin{pmatrix}\Delta t^3/3 & \Delta t^2/2\\
                                               \Delta t^2/2 & \Delta t\end{pmatrix},\\
    z_k &= x_k + e_k, & e_k &\sim N\!\left(0, (s\,\sigma_{x,k})^2\right),
    \end{aligned}

and smoothed by the Kalman filter forwards and the RTS smoother backwards: the
minimum-variance estimate of each position from the whole track, with its standard
deviation.  Nothing is tuned by hand: the process noise :math:`q` (px^2/s^3) and the scale
:math:`s` of the detector's error model are chosen per track by maximum likelihood (the
prediction-error decomposition, evaluated on a grid of both at once).  :math:`s` is itself a
check of the detector's error model (about 1 when the model is right, above 1 when the
background is not white noise); :math:`q` is large where the motion is abrupt, and the
smoother then follows the data.  A frame where the marker was not found is bridged by the
model but keeps no smoothed value (the table says where the marker was seen).

Grids cover :math:`\log_{10} q \in [-6, 6]` (steps of 0.25; px^2/s^3 at 2 frames/s, the
time rescaled to that rate for any other, so the same frames are smoothed alike at any rate)
and :math:`s \in [0.5, 32]` (25 steps of :math:`2^{1/4}`; a lossy codec's frames have lost
the pixel noise the SNR is measured from, and their centres scatter up to about 20 times
:math:`0.798/\mathrm{SNR}`), searched coarse to fine (every 4th q and 2nd s, then the full
grid near each track's best).  Each pass is one Kalman recursion over time whose every step is a few vectorised
NumPy operations on all tracks under all their grid models at once (and on all views that
share a clock): tracks' measurements are shared by their models, not copied per model, so a
2,000-frame stereo pair of 12 markers per view takes about half a second and little memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pandas as pd

#: The Cramer-Rao factor: per-axis sd of a Gaussian spot's centre = CRB_FACTOR / SNR.
CRB_FACTOR = float(np.sqrt(2.0 / np.pi))
LOG_Q_GRID = np.arange(-6.0, 6.0001, 0.25)
#: The grid of q is in px^2/s^3 for frames this far apart (the C-arms' 2 frames/s); other
#: rates are searched on the same grid with time rescaled to it (q reported in px^2/s^3).
REFERENCE_INTERVAL_S = 0.5
SCALE_GRID = np.geomspace(0.5, 32.0, 25)


@dataclass(frozen=True)
class TrackSmoothing:
    """Per-track maximum-likelihood model: process noise ``q`` (px^2/s^3), error scale."""

    view: str
    marker: str
    n_points: int
    q_px2_per_s3: float
    error_scale: float
    raw_sd_px: float          # median per-axis sd of a raw centre (scaled error model)
    smooth_sd_px: float       # median per-axis sd of a smoothed centre
    n_outliers: int = 0       # detections left out as too far off the track

    def to_dict(self) -> dict:
        return {"view": self.view, "marker": self.marker, "n_points": self.n_points,
                "q_px2_per_s3": self.q_px2_per_s3, "error_scale": self.error_scale,
                "raw_sd_px": self.raw_sd_px, "smooth_sd_px": self.smooth_sd_px, "n_outliers": self.n_outliers}


def centre_sd_px(snr) -> np.ndarray:
    """Per-axis standard deviation (px) of a detected centre from its SNR (Cramer-Rao)."""
    return CRB_FACTOR / np.asarray(snr, float)


def _block_loglik(S: np.ndarray, e: np.ndarray, upd: np.ndarray) -> np.ndarray:
    r"""Log-likelihood terms of a block of filter steps, summed over the steps and both axes.

    ``S`` (b, m, G) innovation variances, ``e`` (b, 2, m, G) innovations per axis, ``upd``
    (b, m, 1) where a measurement entered.  The prediction-error decomposition
    :math:`-\tfrac12\sum(\log 2\pi S + e^2/S)` per axis; the log is taken once per block, of
    the product of the block's ``S`` (``np.log`` costs several times another operation), or
    as a sum of logs where that product could leave the normal range.  ``S`` is infinite where
    no measurement entered, which takes those steps' ``e^2/S`` out.
    """
    prod = np.multiply.reduce(S, axis=0, where=upd, initial=1.0)
    normal = (prod > 1e-300) & (prod < 1e300)
    log_s = np.log(np.where(normal, prod, 1.0))
    if not normal.all():
        log_s = np.where(normal, log_s, np.log(np.where(upd, S, 1.0)).sum(axis=0))
    return -(log_s + upd.sum(axis=0) * np.log(2 * np.pi)) - 0.5 * ((e * e).sum(axis=1) / S).sum(axis=0)


def _filter(t: np.ndarray, z: np.ndarray, r: np.ndarray, q, s2, keep: bool = False):
    r"""Kalman filter of many lanes in lockstep: one vectorised step per time index.

    ``t`` (n,) times of a view; ``z`` (n, m, 2) positions of its m tracks (NaN: not found,
    both axes together); ``r`` (n, m) the detector's variance of each position (finite);
    ``q`` and ``s2`` (process noise, squared error scale) broadcastable to (m, G).  Lane
    (i, g) filters track i under model g: process noise ``q[i, g]``, measurement variance
    ``r[:, i] * s2[i, g]``.  Returns the log-likelihood (m, G), summed over both axes; with
    ``keep`` instead the predicted and filtered states of every step, for :func:`_rts`.

    The recursion is written for all lanes at once, in place, without a branch per lane:

    * both axes of a track share its clock, variances and gaps, so they share the covariance
      (p00, p01, p11): one per lane, and a mean (position, velocity) per lane and axis;
    * where a track has no measurement (a gap, after its end) its variance is infinite: the
      gain is 0 and the prediction passes through unchanged;
    * a track starts (diffuse: position from its first detection, velocity variance 1e6) at its
      first detection; its lanes run on the same clock before that, from zero, but are overwritten
      at the start and take in no measurement, so nothing of them reaches the result;
    * the process noise's terms and the measurement variances are computed per block of steps, and
      the log-likelihood's terms buffered and summed per block (:func:`_block_loglik`).

    The arithmetic is that of the textbook step, term by term and in its order (no fused or
    reordered products): the diffuse start makes the second measurement's update cancel most
    digits of p00, so another grouping would change the results beyond rounding.
    """
    n, m = r.shape
    shape = np.broadcast_shapes(np.shape(q), np.shape(s2), (m, 1))
    q = np.atleast_2d(np.asarray(q, float))
    s2 = np.broadcast_to(np.asarray(s2, float), shape)
    seen = np.isfinite(z[:, :, 0])
    first = np.where(seen.any(axis=0), seen.argmax(axis=0), n)
    starts = {int(k): np.flatnonzero(first == k) for k in np.unique(first[first < n])}
    upd = seen & (np.arange(n)[:, None] > first[None, :])       # a measurement updates the lane
    r_upd = np.where(upd, r, np.inf)
    z_upd = np.where(upd[:, :, None], z, 0.0).transpose(0, 2, 1)[..., None]     # (n, 2, m, 1)
    dt = np.diff(np.asarray(t, float), prepend=t[0])
    dt_pair = np.stack([2 * dt, dt], axis=1).reshape(n, 2, 1, 1)     # p00 += 2 dt p01, p01 += dt p11 at once
    X = np.zeros((2, 2) + shape)                 # (position, velocity) x axis: predicted, then filtered
    pos, vel = X
    P = np.zeros((3,) + shape)                   # p00, p01, p11: predicted, then filtered
    p00, p01, p11 = P
    if keep:
        XP, XF = np.empty((n, 2, 2) + shape), np.empty((n, 2, 2) + shape)
        PP, PF = np.empty((n, 3) + shape), np.empty((n, 3) + shape)
    ll = np.zeros(shape)
    block = 32
    SB = np.empty((block,) + shape)              # a block's measurement, then innovation variances
    EB = np.empty((block, 2) + shape)            # ... its innovations
    QB = np.empty((block, 3) + q.shape)          # ... and process noise terms (per model)
    for k in range(n):
        b = k % block
        if b == 0:
            kb = min(k + block, n)
            np.multiply(r_upd[k:kb, :, None], s2, out=SB[:kb - k])
            d = dt[k:kb, None, None]
            QB[:kb - k] = np.stack([q * (d * d * d) / 3, q * (d * d) / 2, q * d], axis=1)
        pos += dt[k] * vel
        P[:2] += dt_pair[k] * P[1:]
        p00 += dt[k] * dt[k] * p11
        P += QB[b]
        if keep:
            XP[k], PP[k] = X, P
        S = np.add(SB[b], p00, out=SB[b])
        K = P[:2] / S                                            # gains of position, velocity
        e = np.subtract(z_upd[k], pos, out=EB[b])
        X += K[:, None] * e
        p11 -= K[1] * p01
        P[:2] -= K[0] * P[:2]
        if k in starts:
            c = starts[k]
            pos[:, c] = z[k, c].T[:, :, None]
            vel[:, c] = 0.0
            p00[c] = r[k, c][:, None] * s2[c]
            p01[c] = 0.0
            p11[c] = 1e6
        if keep:
            XF[k], PF[k] = X, P
        elif b == block - 1 or k == n - 1:
            ll += _block_loglik(SB[:b + 1], EB[:b + 1], upd[k - b:k + 1, :, None])
    if keep:
        return dt, XF[..., 0], XP[..., 0], PF[..., 0], PP[..., 0]
    return ll


def _rts(dt: np.ndarray, XF: np.ndarray, XP: np.ndarray, PF: np.ndarray, PP: np.ndarray):
    r"""Rauch-Tung-Striebel backward pass over the states of :func:`_filter` with ``keep``
    (one model per track): smoothed positions (n, m, 2) and their per-axis variance (n, m).

    ``XF``, ``XP`` (n, 2, 2, m) filtered and predicted (position, velocity) x axis, ``PF``,
    ``PP`` (n, 3, m) their (p00, p01, p11).  The smoother gain
    :math:`C_k = P_{f,k} F_{k+1}^T P_{p,k+1}^{-1}` (0 where the prediction is singular) depends
    on the filter's covariances only and is computed for every step at once; the backward
    recursion :math:`x_{s,k} = x_{f,k} + C_k (x_{s,k+1} - x_{p,k+1})`,
    :math:`P_{s,k} = P_{f,k} + C_k (P_{s,k+1} - P_{p,k+1}) C_k^T` then takes a few operations
    per step, for every track and both axes.  Its terms are grouped as written out for one
    lane (a track's first smoothed variance, under a velocity variance of 1e6, is ill-conditioned
    and would show another grouping's rounding).
    """
    d = dt[1:, None]
    f00, f01, f11 = PF[:-1, 0], PF[:-1, 1], PF[:-1, 2]
    q00, q01, q11 = PP[1:, 0], PP[1:, 1], PP[1:, 2]
    a00, a01, a10, a11 = f00 + d * f01, f01, f01 + d * f11, f11        # P_f F^T
    det = q00 * q11 - q01 * q01
    ok = det > 0
    det = np.where(ok, det, 1.0)
    i00, i01, i11 = q11 / det, -q01 / det, q00 / det
    c00, c01 = a00 * i00 + a01 * i01, a00 * i01 + a01 * i11
    c10, c11 = a10 * i00 + a11 * i01, a10 * i01 + a11 * i11
    c00, c01, c10, c11 = (np.where(ok, c, 0.0) for c in (c00, c01, c10, c11))
    col0 = np.stack([c00, c10, c10], axis=1)          # C's columns at rows (0, 1, 1) ...
    col1 = np.stack([c01, c11, c11], axis=1)
    row0 = np.stack([c00, c00, c10], axis=1)          # ... and its rows 0, 0, 1
    row1 = np.stack([c01, c01, c11], axis=1)
    xs, ps = XF.copy(), PF.copy()
    for k in range(len(dt) - 2, -1, -1):
        dx = xs[k + 1] - XP[k + 1]                     # (position, velocity) x axis
        xs[k] += col0[k, :2, None] * dx[0]
        xs[k] += col1[k, :2, None] * dx[1]
        dp = ps[k + 1] - PP[k + 1]                     # (p00, p01, p11)
        v0 = col0[k] * dp[0] + col1[k] * dp[1]         # D C^T at (0, 0), (0, 1), (0, 1)
        v1 = col0[k] * dp[1] + col1[k] * dp[2]         # ... (1, 0), (1, 1), (1, 1)
        ps[k] += row0[k] * v0 + row1[k] * v1           # C D C^T at (0, 0), (0, 1), (1, 1)
    return xs[:, 0].transpose(0, 2, 1), ps[:, 0]


def _spike(times: np.ndarray, Zu: np.ndarray, sd: np.ndarray, k_sigma: float = 3.0) -> np.ndarray:
    """(n, m) True where a detection is off the straight-line extrapolations of the two
    detections before it and of the two after it, each by more than ``k_sigma`` times the
    extrapolation's sd (sqrt(1 + (1 + r)^2 + r^2) sd, 2.45 sd at a constant frame rate).
    A detection without two on each side (a track's first two and last two) is never a
    spike: a marker that starts or stops moving there looks the same."""
    def off(times, Zu, sd):
        # every detection against the line through the two detections of its track before it
        n, m = sd.shape
        seen = np.isfinite(Zu[:, :, 0])
        upto = np.maximum.accumulate(np.where(seen, np.arange(n)[:, None], -1), axis=0)
        b = np.vstack([np.full((1, m), -1), upto[:-1]])                  # the last detection before
        a = np.where(b >= 0, np.take_along_axis(b, np.maximum(b, 0), axis=0), -1)   # and the one before it
        cells = np.flatnonzero(seen & (a >= 0))                          # (frame, track), flat
        k, j = np.divmod(cells, m)
        a, b = a.ravel()[cells], b.ravel()[cells]
        r = (times[k] - times[b]) / (times[b] - times[a])
        dev = []
        for axis in (0, 1):
            z = Zu[:, :, axis].ravel()
            zb = z[b * m + j]
            dev.append(np.abs(z[cells] - (zb + r * (zb - z[a * m + j]))))
        e = np.zeros(n * m)
        e[cells] = np.maximum(*dev) / (sd.ravel()[cells] * np.sqrt(1.0 + (1 + r) ** 2 + r ** 2))
        return e.reshape(n, m) > k_sigma
    return off(times, Zu, sd) & off(times[::-1], Zu[::-1], sd[::-1])[::-1]


def _fit_view(times, Zu, SDu, qs, scales):
    """Maximum-likelihood (q, scale) per track, then the RTS smoother with them.

    The grid ``qs`` x ``scales`` is searched coarse to fine: every 4th q and every 2nd scale
    first, then the full grid's points within a coarse step of each track's best.  Each pass
    filters every track under every one of its models at once (:func:`_filter`); in the fine
    pass each track has its own window, clipped at the grid's edges (a clipped window repeats
    its edge's models, next to them in the search order: the choice is the same).  The tracks
    are independent: a track's result does not depend on the others fitted with it.  ``Zu``
    (n, m, 2) positions (NaN: none), ``SDu`` (n, m) raw per-axis sd.  Returns ``q``,
    ``scale`` (m,), smoothed positions (n, m, 2) and their per-axis variance (n, m)."""
    m = Zu.shape[1]
    r = SDu ** 2
    cq, cs = np.arange(0, len(qs), 4), np.arange(0, len(scales), 2)
    Q, S = (a.ravel() for a in np.meshgrid(qs[cq], scales[cs], indexing="ij"))
    ll = _filter(times, Zu, r, Q[None, :], (S ** 2)[None, :])
    b = np.argmax(ll, axis=1)
    bq, bs = cq[b // len(cs)], cs[b % len(cs)]
    iq, js = np.broadcast_arrays(np.clip(bq[:, None, None] + np.arange(-3, 4)[None, :, None], 0, len(qs) - 1),
                                 np.clip(bs[:, None, None] + np.arange(-2, 3)[None, None, :], 0, len(scales) - 1))
    Q, S = qs[iq].reshape(m, -1), scales[js].reshape(m, -1)      # (m, 35), q-major as in the coarse pass
    b = np.argmax(_filter(times, Zu, r, Q, S ** 2), axis=1)
    q_best, s_best = Q[np.arange(m), b], S[np.arange(m), b]
    xs, var = _rts(*_filter(times, Zu, r, q_best[:, None], (s_best ** 2)[:, None], keep=True))
    return q_best, s_best, xs, var


def _fit_views(times, Zs, SDs, qs, scales):
    """:func:`_fit_view` of the tracks of several views on one clock at once (lanes of one
    filter, so that each step's operations serve them all); the results split per view."""
    cuts = np.cumsum([Z.shape[1] for Z in Zs])[:-1]
    q, s, xs, var = _fit_view(times, np.concatenate(Zs, axis=1), np.concatenate(SDs, axis=1), qs, scales)
    return list(zip(np.split(q, cuts), np.split(s, cuts), np.split(xs, cuts, axis=1), np.split(var, cuts, axis=1)))


def _outliers(times, Zu, SDu, xs, outlier_sigma):
    """(n, m) True at a detection far off its smoothed track (a bad centre) and a spike.

    Far off is judged on a robust scale of the residuals (the likelihood's scale grows to take
    in an outlier); a spike is off the straight-line extrapolation from both sides (a sudden
    turn, such as the indentor's reversal, lies on both and is kept)."""
    resid = np.abs(Zu - xs) / SDu[:, :, None]
    fin = np.where(np.isfinite(resid), resid, np.nan)
    robust = np.maximum(1.4826 * np.nanmedian(fin.transpose(1, 0, 2).reshape(Zu.shape[1], -1), axis=1), 1.0)
    outlier = np.nanmax(np.where(np.isfinite(fin), fin, 0.0), axis=2) > outlier_sigma * robust[None, :]
    return outlier & _spike(times, Zu, SDu * robust[None, :])


def smooth_tracks(table: pd.DataFrame, *, log_q_grid=LOG_Q_GRID, scale_grid=SCALE_GRID,
                  min_points: int = 5, outlier_sigma: float = 5.0) -> tuple[pd.DataFrame, list[TrackSmoothing]]:
    """Smooth every (view, marker) track of a ``markers2d`` table.

    ``table`` needs ``view, frame, time_s, marker, x_px, y_px, snr`` (rows where the marker
    was not found have NaN positions).  Returns a copy with ``sd_px`` (the raw centre's
    per-axis sd, scaled error model), ``x_px_smooth``, ``y_px_smooth``, ``sd_px_smooth`` and
    ``smooth_outlier`` added (NaN where the marker was not found, and, but for ``sd_px`` (the
    detector's own, unscaled), for tracks with fewer than ``min_points`` found points), and
    the per-track model.  A detection more than
    ``outlier_sigma`` robust sd (1.4826 MAD of the track's residuals over the detector's sd, at
    least the detector's sd) off its smoothed track on either axis is a bad centre: it
    is left out, the track refitted, and its smoothed value is the track's there
    (``smooth_outlier`` True).
    """
    need = {"view", "frame", "time_s", "marker", "x_px", "y_px", "snr"}
    missing = need - set(table.columns)
    if missing:
        raise ValueError(f"track table lacks columns {sorted(missing)}")
    out = table.copy()
    # the new columns, by row position; written into the table at the end
    new = {c: np.full(len(out), np.nan) for c in ("sd_px", "x_px_smooth", "y_px_smooth", "sd_px_smooth")}
    new["smooth_outlier"] = np.zeros(len(out), bool)
    models: list[TrackSmoothing] = []
    qs = 10.0 ** np.asarray(log_q_grid, float)
    scales = np.asarray(scale_grid, float)
    views = out.groupby("view", sort=False)
    fits = []                       # per view with tracks to smooth: its arrays and, below, its fit
    for view, vt in views:
        frames = np.sort(vt["frame"].unique())
        times = vt.groupby("frame")["time_s"].first().reindex(frames).to_numpy(float)
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise ValueError(f"view {view}: time stamps must be finite and increasing to smooth tracks")
        markers = list(pd.unique(vt["marker"]))
        n, M = len(frames), len(markers)
        Z = np.full((n, 2, M), np.nan)
        SD = np.full((n, M), np.nan)
        fi = np.searchsorted(frames, vt["frame"].to_numpy())
        mi = pd.Index(markers).get_indexer(vt["marker"])
        sd = centre_sd_px(vt["snr"].to_numpy(float))
        found = np.isfinite(vt["x_px"].to_numpy(float)) & np.isfinite(vt["y_px"].to_numpy(float)) & np.isfinite(sd) & (sd > 0)
        Z[fi[found], 0, mi[found]] = vt["x_px"].to_numpy(float)[found]
        Z[fi[found], 1, mi[found]] = vt["y_px"].to_numpy(float)[found]
        SD[fi[found], mi[found]] = sd[found]
        n_found = np.isfinite(SD).sum(axis=0)
        use = np.flatnonzero(n_found >= min_points)
        # a track too short to smooth keeps its detections' own sd (the detector's model,
        # unscaled): its raw centres are what is triangulated
        short = found & ~np.isin(mi, use)
        new["sd_px"][views.indices[view][short]] = sd[short]
        if use.size == 0:
            continue
        fits.append(SimpleNamespace(
            view=view, pos=views.indices[view], times=times, markers=markers, fi=fi, mi=mi, found=found, SD=SD,
            use=use, Zu=Z[:, :, use].transpose(0, 2, 1),          # (n, m, 2): track, axis
            SDu=np.where(np.isfinite(SD[:, use]), SD[:, use], 1.0)))
    # views on one clock (a synchronised stereo pair) are fitted together
    clocks: dict[bytes, list] = {}
    for f in fits:
        clocks.setdefault(f.times.tobytes(), []).append(f)
    for group in clocks.values():
        # time in units of REFERENCE_INTERVAL_S per frame interval: the q grid is searched in
        # those units, so the same frames are smoothed the same whatever their rate (a grid
        # fixed in px^2/s^3 had covered no useful q at 0.001 or 10,000 frames/s)
        dts = np.diff(group[0].times)
        unit = REFERENCE_INTERVAL_S / float(np.median(dts)) if dts.size else 1.0
        times = group[0].times * unit
        for f in group:
            f.unit = unit
        for f, fit in zip(group, _fit_views(times, [f.Zu for f in group], [f.SDu for f in group], qs, scales)):
            f.q, f.s, f.xs, f.var = fit
            # a bad centre is left out and its track refitted
            f.outlier = _outliers(times, f.Zu, f.SDu, f.xs, outlier_sigma)
            f.Zu = np.where(f.outlier[:, :, None], np.nan, f.Zu)
            f.redo = np.flatnonzero(f.outlier.any(axis=0))
        # tracks are fitted independently: only those that lost a detection change
        redo = [f for f in group if f.redo.size]
        if redo:
            for f, fit in zip(redo, _fit_views(times, [f.Zu[:, f.redo] for f in redo],
                                               [f.SDu[:, f.redo] for f in redo], qs, scales)):
                f.q[f.redo], f.s[f.redo], f.xs[:, f.redo], f.var[:, f.redo] = fit
    for f in fits:
        seen = np.isfinite(f.Zu[:, :, 0])
        has = seen.any(axis=0)
        first = seen.argmax(axis=0)
        last = len(f.times) - 1 - seen[::-1].argmax(axis=0)
        a_of = np.full(len(f.markers), -1)
        a_of[f.use] = np.arange(f.use.size)
        a = a_of[f.mi]
        rel = f.found & (a >= 0)
        rel[rel] = has[a[rel]]                      # rows of the smoothed tracks
        new["smooth_outlier"][f.pos[rel]] = f.outlier[f.fi[rel], a[rel]]
        rel[rel] = (f.fi[rel] >= first[a[rel]]) & (f.fi[rel] <= last[a[rel]])
        k, j, a = f.fi[rel], f.mi[rel], a[rel]
        new["sd_px"][f.pos[rel]] = f.SD[k, j] * f.s[a]
        new["x_px_smooth"][f.pos[rel]] = f.xs[k, a, 0]
        new["y_px_smooth"][f.pos[rel]] = f.xs[k, a, 1]
        new["sd_px_smooth"][f.pos[rel]] = np.sqrt(f.var[k, a])
        for a, j in enumerate(f.use):
            if has[a]:
                models.append(TrackSmoothing(
                    view=str(f.view), marker=str(f.markers[j]), n_points=int(seen[:, a].sum()),
                    q_px2_per_s3=float(f.q[a] * f.unit ** 3), error_scale=float(f.s[a]),
                    raw_sd_px=float(np.median(f.SD[seen[:, a], j]) * f.s[a]),
                    smooth_sd_px=float(np.median(np.sqrt(f.var[seen[:, a], a]))),
                    n_outliers=int(f.outlier[:, a].sum())))
    for c, v in new.items():
        out[c] = v
    return out, models


def stereo_error_check(points3d: pd.DataFrame, table: pd.DataFrame, views, pair: tuple[str, str], *,
                       min_points: int = 10) -> dict:
    """Check the 2-D error model against the stereo ray gaps, per marker.

    Two rays through a marker's centres in two views miss each other by the part of each
    view's centre error that is perpendicular to the epipolar plane, times the view's
    millimetres per pixel at the marker (its depth over the focal length).  With per-axis
    errors of ``sd`` px the signed gap's standard deviation is

    .. math::  \\sigma_g = \\sqrt{(s_a\\,Z_a/f_a)^2 + (s_b\\,Z_b/f_b)^2}

    so ``z = gap / sigma_g`` is N(0, 1) when the error model is right.  Its RMS over a
    marker's two-view points (``ray_gap_signed_mm`` with ``sd_px_smooth``; ``ray_gap_mm_raw``
    with ``sd_px``) is what the model misses: an error that the smoother cannot average away
    (a bias that changes slowly, as the fit's mismatch to a large bead's shape, or residual
    calibration error), or a noise model too optimistic.  The scale returned for each marker
    with ``min_points`` two-view points is ``max(1, z RMS)``: applied to both views' ``sd``,
    the model then accounts for what the two views disagree by (never made tighter).

    ``views`` are the pair's :class:`~bsipipe.imaging.triangulate.ViewGeometry` (``R``,
    ``t``, ``K``) in ``pair`` order; ``table`` the 2-D table with ``sd_px`` and
    ``sd_px_smooth``; ``points3d`` the triangulated smoothed centres with ``ray_gap_mm_raw``.
    Returns ``{marker: {n_points, z_rms_raw, z_rms_smooth, scale_raw, scale_smooth}}``.
    """
    two = points3d[points3d["n_views"] == 2]
    if two.empty:
        return {}
    X = two[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    idx = pd.MultiIndex.from_frame(two[["frame", "marker"]])
    var_s = np.zeros(len(two))
    var_r = np.zeros(len(two))
    for name, g in zip(pair, views):
        mm_per_px = (X @ np.asarray(g.R).T + np.asarray(g.t))[:, 2] / float(np.asarray(g.K)[0, 0])
        s = table[table["view"] == name].set_index(["frame", "marker"])
        var_s += (s["sd_px_smooth"].reindex(idx).to_numpy(float) * mm_per_px) ** 2
        var_r += (s["sd_px"].reindex(idx).to_numpy(float) * mm_per_px) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        z = pd.DataFrame({"marker": two["marker"].to_numpy(),
                          "smooth": two["ray_gap_signed_mm"].to_numpy(float) / np.sqrt(var_s),
                          "raw": two["ray_gap_mm_raw"].to_numpy(float) / np.sqrt(var_r)})
    out = {}
    for m, g in z.groupby("marker", sort=False):
        zs, zr = g["smooth"].to_numpy(), g["raw"].to_numpy()
        zs, zr = zs[np.isfinite(zs)], zr[np.isfinite(zr)]
        n = int(min(len(zs), len(zr)))
        rs = float(np.sqrt(np.mean(zs ** 2))) if len(zs) else float("nan")
        rr = float(np.sqrt(np.mean(zr ** 2))) if len(zr) else float("nan")
        enough = n >= min_points
        out[str(m)] = {"n_points": n, "z_rms_raw": rr, "z_rms_smooth": rs,
                       "scale_raw": max(1.0, rr) if enough and np.isfinite(rr) else 1.0,
                       "scale_smooth": max(1.0, rs) if enough and np.isfinite(rs) else 1.0}
    return out
