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

Grids cover :math:`\log_{10} q \in [-6, 6]` (steps of 0.25) and :math:`s \in [0.5, 4]` (13
steps), searched coarse to fine (every 4th q and 2nd s, then the full grid near each track's
best); every track and grid point of a pass is filtered at once with vectorised NumPy (each track's measurements shared by its
grid models, not copied per model), so a 2,000-frame view of 10 markers takes under a
second and little memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

#: The Cramer-Rao factor: per-axis sd of a Gaussian spot's centre = CRB_FACTOR / SNR.
CRB_FACTOR = float(np.sqrt(2.0 / np.pi))
LOG_Q_GRID = np.arange(-6.0, 6.0001, 0.25)
SCALE_GRID = np.geomspace(0.5, 4.0, 13)


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


def _filter(t: np.ndarray, z: np.ndarray, r: np.ndarray, q: np.ndarray, keep: bool = False,
            scale2: np.ndarray | None = None):
    """Kalman filter of lanes in lockstep.

    ``t`` (n,) times; ``z`` (n, R) measurements (NaN: none); ``r`` (n, R) measurement
    variances.  Without ``scale2`` there is one lane per column: ``q`` (R,) process noise.
    With ``scale2`` (G,) every column is filtered under G models at once, lane (i, g) with
    variance ``r[:, i] * scale2[g]`` and process noise ``q[g]`` (G,): the lanes of a column
    share its measurements and its clock, so these are not copied G times.  Returns the
    log-likelihood per lane ((R,) or (R, G)) and, with ``keep`` (no ``scale2``), the
    filtered and predicted states for the smoother.
    """
    n, R = z.shape
    grid = scale2 is not None
    shape = (R, len(scale2)) if grid else (R,)
    qq = np.asarray(q, float)[None, :] if grid else np.asarray(q, float)
    x = np.zeros(shape)
    v = np.zeros(shape)
    p00 = np.zeros(shape)
    p01 = np.zeros(shape)
    p11 = np.zeros(shape)
    # which lanes have started and their last time depend on the measurements only: per column
    started = np.zeros(R, bool)
    last_t = np.zeros(R)
    ll = np.zeros(shape)
    if keep:
        F = np.zeros((n, 5, R))      # filtered x, v, p00, p01, p11
        Pr = np.zeros((n, 5, R))     # predicted, the same
        dts = np.zeros((n, R))
    obs = np.isfinite(z)

    def col(a):                      # a per-column array against the lanes
        return a[:, None] if grid else a
    for k in range(n):
        dt = np.where(started, t[k] - last_t, 0.0)
        dt2, dt3 = dt * dt, dt * dt * dt
        if grid and R and (dt == dt[0]).all():
            # one step for every lane (the usual case): the process-noise terms are computed
            # once per model instead of once per lane (the same values)
            dtc, dt2c, dt3c = dt[0], dt2[0], dt3[0]
        else:
            dtc, dt2c, dt3c = col(dt), col(dt2), col(dt3)
        # predict (only lanes already started move; others stay zero)
        x = x + dtc * v
        n00 = p00 + 2 * dtc * p01 + dt2c * p11 + qq * dt3c / 3
        n01 = p01 + dtc * p11 + qq * dt2c / 2
        n11 = p11 + qq * dtc
        p00, p01, p11 = n00, n01, n11
        if keep:
            Pr[k] = (x, v, p00, p01, p11)
            dts[k] = dt
        o = obs[k]
        upd = o & started
        if upd.all():
            # every lane measured (the usual frame): the masked update below without its masks
            rk = col(r[k]) * scale2[None, :] if grid else r[k]
            S = p00 + rk
            innov = col(z[k]) - x
            ll += -0.5 * (np.log(2 * np.pi * S) + innov * innov / S)
            k0 = p00 / S
            k1 = p01 / S
            x = x + k0 * innov
            v = v + k1 * innov
            p00, p01, p11 = p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01
        elif upd.any():
            u = col(upd)
            zk = np.where(upd, z[k], 0.0)
            rk = col(r[k]) * scale2[None, :] if grid else r[k]
            S = p00 + rk
            innov = col(zk) - x
            ll += np.where(u, -0.5 * (np.log(2 * np.pi * S) + innov * innov / S), 0.0)
            k0 = np.where(u, p00 / S, 0.0)
            k1 = np.where(u, p01 / S, 0.0)
            x = x + k0 * innov
            v = v + k1 * innov
            p00, p01, p11 = p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01
        new = o & ~started
        if new.any():
            # a diffuse start: position from the first measurement, velocity unknown
            u = col(new)
            x = np.where(u, col(z[k]), x)
            v = np.where(u, 0.0, v)
            p00 = np.where(u, col(r[k]) * scale2[None, :] if grid else r[k], p00)
            p01 = np.where(u, 0.0, p01)
            p11 = np.where(u, 1e6, p11)
            started |= new
        last_t = np.where(started, t[k], last_t)
        if keep:
            F[k] = (x, v, p00, p01, p11)
    return (ll, F, Pr, dts) if keep else (ll,)


def _rts(F: np.ndarray, Pr: np.ndarray, dts: np.ndarray):
    """Rauch-Tung-Striebel backward pass; returns smoothed position and its variance."""
    n = F.shape[0]
    xs = F[:, 0].copy()
    vs = F[:, 1].copy()
    s00 = F[:, 2].copy()
    s01 = F[:, 3].copy()
    s11 = F[:, 4].copy()
    for k in range(n - 2, -1, -1):
        dt = dts[k + 1]
        f00, f01, f11 = F[k, 2], F[k, 3], F[k, 4]
        # P_f F^T, F = [[1, dt], [0, 1]]
        a00, a01 = f00 + dt * f01, f01
        a10, a11 = f01 + dt * f11, f11
        q00, q01, q11 = Pr[k + 1, 2], Pr[k + 1, 3], Pr[k + 1, 4]
        det = q00 * q11 - q01 * q01
        ok = det > 0
        det = np.where(ok, det, 1.0)
        i00, i01, i11 = q11 / det, -q01 / det, q00 / det
        c00, c01 = a00 * i00 + a01 * i01, a00 * i01 + a01 * i11
        c10, c11 = a10 * i00 + a11 * i01, a10 * i01 + a11 * i11
        c00, c01, c10, c11 = (np.where(ok, c, 0.0) for c in (c00, c01, c10, c11))
        dx, dv = xs[k + 1] - Pr[k + 1, 0], vs[k + 1] - Pr[k + 1, 1]
        xs[k] = F[k, 0] + c00 * dx + c01 * dv
        vs[k] = F[k, 1] + c10 * dx + c11 * dv
        d00, d01, d11 = s00[k + 1] - q00, s01[k + 1] - q01, s11[k + 1] - q11
        # C D C^T
        e00 = c00 * (c00 * d00 + c01 * d01) + c01 * (c00 * d01 + c01 * d11)
        e01 = c00 * (c10 * d00 + c11 * d01) + c01 * (c10 * d01 + c11 * d11)
        e11 = c10 * (c10 * d00 + c11 * d01) + c11 * (c10 * d01 + c11 * d11)
        s00[k], s01[k], s11[k] = f00 + e00, f01 + e01, f11 + e11
    return xs, s00


def _spike(times: np.ndarray, Zu: np.ndarray, sd: np.ndarray, k_sigma: float = 3.0) -> np.ndarray:
    """(n, m) True where a detection is off the straight-line extrapolations of the two
    detections before it and of the two after it, each by more than ``k_sigma`` times the
    extrapolation's sd (sqrt(1 + (1 + r)^2 + r^2) sd, 2.45 sd at a constant frame rate).
    A detection without two on each side (a track's first two and last two) is never a
    spike: a marker that starts or stops moving there looks the same."""
    n, m = Zu.shape[:2]
    off = np.ones((n, m), bool)
    for step in (1, -1):
        e = np.zeros((n, m))
        for j in range(m):
            idx = np.flatnonzero(np.isfinite(Zu[:, j, 0]))
            if step == -1:
                idx = idx[::-1]
            if len(idx) < 3:
                continue
            # every consecutive triple (a, b, k) of the marker's detections at once
            a, b, k = idx[:-2], idx[1:-1], idx[2:]
            r = (times[k] - times[b]) / (times[b] - times[a])
            pred = Zu[b, j] + r[:, None] * (Zu[b, j] - Zu[a, j])
            s = sd[k, j] * np.sqrt(1.0 + (1 + r) ** 2 + r ** 2)
            e[k, j] = np.max(np.abs(Zu[k, j] - pred), axis=1) / s
        off &= e > k_sigma
    return off


def _fit_view(times, Zu, SDu, qs, scales):
    """Maximum-likelihood (q, scale) per marker, then the RTS smoother with them.

    The grid ``qs`` x ``scales`` is searched coarse to fine: every 4th q and every 2nd scale
    first, then the full grid's points within a coarse step of each marker's best (markers
    sharing a best share the fine pass).  ``Zu`` (n, m, 2) positions (NaN: none), ``SDu``
    (n, m) raw per-axis sd.  Returns ``q``, ``scale`` (m,), smoothed positions and variances
    (n, 2 m; lane 2 marker + axis)."""
    n, m = Zu.shape[:2]
    Z2 = Zu.reshape(n, 2 * m)
    R2 = np.repeat(SDu, 2, axis=1) ** 2

    def loglik(markers, iq, js):
        Q, S = (a.ravel() for a in np.meshgrid(qs[iq], scales[js], indexing="ij"))
        cols = np.stack([2 * markers, 2 * markers + 1], axis=1).ravel()
        # every (marker, axis) under every model (q, scale) at once: lanes (2 m, G)
        (ll,) = _filter(times, Z2[:, cols], R2[:, cols], Q, scale2=S ** 2)
        return ll.reshape(len(markers), 2, -1).sum(axis=1), Q, S      # both axes

    cq, cs = np.arange(0, len(qs), 4), np.arange(0, len(scales), 2)
    ll, _, _ = loglik(np.arange(m), cq, cs)
    b = np.argmax(ll, axis=1)
    bq, bs = cq[b // len(cs)], cs[b % len(cs)]
    q_best, s_best = np.empty(m), np.empty(m)
    for key in sorted(set(zip(bq.tolist(), bs.tolist()))):
        mk = np.flatnonzero((bq == key[0]) & (bs == key[1]))
        fq = np.arange(max(0, key[0] - 3), min(len(qs), key[0] + 4))
        fs = np.arange(max(0, key[1] - 2), min(len(scales), key[1] + 3))
        ll, Q, S = loglik(mk, fq, fs)
        b2 = np.argmax(ll, axis=1)
        q_best[mk], s_best[mk] = Q[b2], S[b2]
    r2 = np.repeat(SDu ** 2 * s_best ** 2, 2, axis=1)
    _, F, Pr, dts = _filter(times, Z2, r2, np.repeat(q_best, 2), keep=True)
    xs, var = _rts(F, Pr, dts)
    return q_best, s_best, xs, var


def smooth_tracks(table: pd.DataFrame, *, log_q_grid=LOG_Q_GRID, scale_grid=SCALE_GRID,
                  min_points: int = 5, outlier_sigma: float = 5.0) -> tuple[pd.DataFrame, list[TrackSmoothing]]:
    """Smooth every (view, marker) track of a ``markers2d`` table.

    ``table`` needs ``view, frame, time_s, marker, x_px, y_px, snr`` (rows where the marker
    was not found have NaN positions).  Returns a copy with ``sd_px`` (the raw centre's
    per-axis sd, scaled error model), ``x_px_smooth``, ``y_px_smooth``, ``sd_px_smooth`` and
    ``smooth_outlier`` added (NaN where the marker was not found, and for tracks with fewer
    than ``min_points`` found points), and the per-track model.  A detection more than
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
    for c in ("sd_px", "x_px_smooth", "y_px_smooth", "sd_px_smooth"):
        out[c] = np.nan
    out["smooth_outlier"] = False
    models: list[TrackSmoothing] = []
    qs = 10.0 ** np.asarray(log_q_grid, float)
    scales = np.asarray(scale_grid, float)
    for view, vt in out.groupby("view", sort=False):
        frames = np.sort(vt["frame"].unique())
        times = vt.groupby("frame")["time_s"].first().reindex(frames).to_numpy(float)
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise ValueError(f"view {view}: time stamps must be finite and increasing to smooth tracks")
        markers = list(pd.unique(vt["marker"]))
        n, M = len(frames), len(markers)
        Z = np.full((n, 2, M), np.nan)
        SD = np.full((n, M), np.nan)
        fidx = {f: i for i, f in enumerate(frames)}
        midx = {m: j for j, m in enumerate(markers)}
        rows = vt.index.to_numpy()
        fi = vt["frame"].map(fidx).to_numpy()
        mi = vt["marker"].map(midx).to_numpy()
        sd = centre_sd_px(vt["snr"].to_numpy(float))
        found = np.isfinite(vt["x_px"].to_numpy(float)) & np.isfinite(vt["y_px"].to_numpy(float)) & np.isfinite(sd) & (sd > 0)
        Z[fi[found], 0, mi[found]] = vt["x_px"].to_numpy(float)[found]
        Z[fi[found], 1, mi[found]] = vt["y_px"].to_numpy(float)[found]
        SD[fi[found], mi[found]] = sd[found]
        n_found = np.isfinite(SD).sum(axis=0)
        use = np.flatnonzero(n_found >= min_points)
        if use.size == 0:
            continue
        Zu = Z[:, :, use].transpose(0, 2, 1)                # (n, m, 2): lane = 2 * marker + axis
        SDu = np.where(np.isfinite(SD[:, use]), SD[:, use], 1.0)
        q_best, s_best, xs, var = _fit_view(times, Zu, SDu, qs, scales)
        # a detection far off its smoothed track (a bad centre) is left out and the track refitted
        # (judged on a robust scale of the residuals: the likelihood's scale grows to take in an outlier)
        resid = np.abs(Zu - xs.reshape(n, use.size, 2)) / SDu[:, :, None]
        fin = np.where(np.isfinite(resid), resid, np.nan)
        robust = np.maximum(1.4826 * np.nanmedian(fin.transpose(1, 0, 2).reshape(use.size, -1), axis=1), 1.0)
        outlier = np.nanmax(np.where(np.isfinite(fin), fin, 0.0), axis=2) > outlier_sigma * robust[None, :]
        # ... and only a spike: off the straight-line extrapolation from both sides (a sudden turn,
        # such as the indentor's reversal, lies on both and is kept)
        outlier &= _spike(times, Zu, SDu * robust[None, :])
        if outlier.any():
            Zu = np.where(outlier[:, :, None], np.nan, Zu)
            q_best, s_best, xs, var = _fit_view(times, Zu, SDu, qs, scales)
        out_rows = np.zeros(len(vt), bool)
        for a, j in enumerate(use):
            seen = np.isfinite(Zu[:, a, 0])
            if not seen.any():
                continue
            first, last = np.flatnonzero(seen)[[0, -1]]
            sel = (mi == j) & found & (fi >= first) & (fi <= last)
            k = fi[sel]
            r_idx = rows[sel]
            out.loc[r_idx, "sd_px"] = SD[k, j] * s_best[a]
            out.loc[r_idx, "x_px_smooth"] = xs[k, 2 * a]
            out.loc[r_idx, "y_px_smooth"] = xs[k, 2 * a + 1]
            out.loc[r_idx, "sd_px_smooth"] = np.sqrt(0.5 * (var[k, 2 * a] + var[k, 2 * a + 1]))
            out_rows |= (mi == j) & found & outlier[fi, a]
            models.append(TrackSmoothing(
                view=str(view), marker=str(markers[j]), n_points=int(seen.sum()),
                q_px2_per_s3=float(q_best[a]), error_scale=float(s_best[a]),
                raw_sd_px=float(np.median(SD[seen, j]) * s_best[a]),
                smooth_sd_px=float(np.median(np.sqrt(0.5 * (var[seen, 2 * a] + var[seen, 2 * a + 1])))),
                n_outliers=int(outlier[:, a].sum())))
        out.loc[rows[out_rows], "smooth_outlier"] = True
    return out, models
