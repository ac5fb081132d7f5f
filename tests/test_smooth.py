"""Kalman/RTS smoothing of 2-D tracks (``bsipipe.imaging.smooth``)."""

import math

import numpy as np
import pandas as pd
import pytest

from bsipipe.imaging.smooth import CRB_FACTOR, LOG_Q_GRID, REFERENCE_INTERVAL_S, SCALE_GRID, smooth_tracks


def _track(x, y, snr, t, marker="M1", view="cam1"):
    return pd.DataFrame({"view": view, "frame": np.arange(len(t)), "time_s": t, "marker": marker,
                         "x_px": x, "y_px": y, "snr": snr})


def _smooth_motion(n=200, fps=2.0, seed=0, noise_scale=1.0, snr=6.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fps
    # indentation-like: a ramp down, a turn-around, a ramp back, plus a slow sway
    xt = 500 + 3.0 * np.sin(2 * np.pi * t / 60)
    yt = 400 + np.where(t < t[-1] / 2, 0.2 * t, 0.2 * (t[-1] - t)) + 0.5 * np.sin(2 * np.pi * t / 23)
    s = np.full(n, snr)
    sd = noise_scale * CRB_FACTOR / s
    return _track(xt + rng.normal(0, sd), yt + rng.normal(0, sd), s, t), xt, yt, sd


def test_smoothing_beats_raw_and_its_sd_is_honest():
    raw_rms, sm_rms, zs = [], [], []
    for seed in range(5):
        tab, xt, yt, sd = _smooth_motion(seed=seed)
        out, models = smooth_tracks(tab)
        raw_rms.append(np.sqrt(np.mean((out.x_px - xt) ** 2 + (out.y_px - yt) ** 2)))
        sm_rms.append(np.sqrt(np.mean((out.x_px_smooth - xt) ** 2 + (out.y_px_smooth - yt) ** 2)))
        zs.append(np.concatenate([(out.x_px_smooth - xt) / out.sd_px_smooth, (out.y_px_smooth - yt) / out.sd_px_smooth]))
        assert 0.7 < models[0].error_scale < 1.45
    raw, sm = float(np.mean(raw_rms)), float(np.mean(sm_rms))
    z_sd = float(np.std(np.concatenate(zs)))
    print(f"2-D RMS raw {raw:.4f} px, smoothed {sm:.4f} px (x{sm / raw:.2f}); smoothed z sd {z_sd:.2f}")
    assert sm < 0.5 * raw
    assert 0.75 < z_sd < 1.35


def test_error_scale_is_measured_when_the_detector_underestimates_its_error():
    tab, *_ = _smooth_motion(seed=3, noise_scale=2.0)
    _, models = smooth_tracks(tab)
    assert 1.6 < models[0].error_scale < 2.5


def test_error_scale_reaches_the_errors_of_lossy_video():
    """Frames from a lossy codec (OpenCV's mp4v) lose the pixel noise the SNR is measured
    from: on the twin's mp4v frames the centres scatter 6-19 times the detector's
    0.798 / SNR.  The scale's grid reaches 32 (it stopped at 4, which left the stated errors
    of every such track several times too small); the smoothed sd stays honest."""
    tab, xt, yt, _ = _smooth_motion(seed=4, noise_scale=10.0, snr=60.0)
    out, models = smooth_tracks(tab)
    assert 7.0 < models[0].error_scale < 14.0
    z = np.concatenate([(out.x_px_smooth - xt) / out.sd_px_smooth, (out.y_px_smooth - yt) / out.sd_px_smooth])
    assert 0.7 < float(np.std(z)) < 1.4


def test_static_marker_gets_the_smallest_process_noise_and_averages_down():
    n = 100
    t = np.arange(n) / 2.0
    rng = np.random.default_rng(1)
    sd = CRB_FACTOR / 10.0
    tab = _track(300 + rng.normal(0, sd, n), 200 + rng.normal(0, sd, n), np.full(n, 10.0), t)
    out, models = smooth_tracks(tab)
    assert models[0].q_px2_per_s3 <= 1e-5
    err = np.hypot(out.x_px_smooth - 300, out.y_px_smooth - 200)
    assert np.sqrt(np.mean(err ** 2)) < 0.35 * np.sqrt(2) * sd


def test_abrupt_motion_is_followed_not_averaged_away():
    n = 120
    t = np.arange(n) / 2.0
    rng = np.random.default_rng(2)
    xt = 100 + np.where(np.arange(n) < 60, 0.0, 8.0)       # a jump of 8 px (a slip)
    sd = CRB_FACTOR / 8.0
    tab = _track(xt + rng.normal(0, sd, n), 50 + rng.normal(0, sd, n), np.full(n, 8.0), t)
    out, _ = smooth_tracks(tab)
    far = np.abs(np.arange(n) - 59.5) > 3
    assert np.max(np.abs(out.x_px_smooth - xt)[far]) < 0.5


def test_missing_frames_stay_missing_and_tracks_are_independent():
    tab, xt, yt, _ = _smooth_motion(n=80, seed=4)
    tab.loc[30:35, ["x_px", "y_px", "snr"]] = np.nan
    other, *_ = _smooth_motion(n=80, seed=5)
    other["marker"] = "M2"
    other["x_px"] += 100
    both = pd.concat([tab, other], ignore_index=True)
    out, models = smooth_tracks(both)
    assert {m.marker for m in models} == {"M1", "M2"}
    m1 = out[out.marker == "M1"]
    assert m1.loc[30:35, "x_px_smooth"].isna().all()
    assert m1.drop(index=range(30, 36))["x_px_smooth"].notna().all()
    assert (out[out.marker == "M2"]["x_px_smooth"] > 550).all()


def test_too_short_tracks_are_left_unsmoothed_and_bad_times_refused():
    tab, *_ = _smooth_motion(n=4)
    out, models = smooth_tracks(tab)
    assert models == [] and out["x_px_smooth"].isna().all()
    bad, *_ = _smooth_motion(n=20)
    bad.loc[5, "time_s"] = bad.loc[4, "time_s"]
    with pytest.raises(ValueError, match="increasing"):
        smooth_tracks(bad)


@pytest.mark.slow
def test_twin_at_default_noise_smoothed_implanted_markers_under_a_tenth_of_a_pixel():
    """The twin's 0.5 mm markers at real-frame noise: raw at the Cramer-Rao bound, smoothed below 0.1 px."""
    from test_track_twin import _errors_2d, _tracked_twin
    tw = _tracked_twin(None)
    for view in ("cam1", "cam2"):
        out, models = smooth_tracks(_errors_2d(tw, view))
        ok = out.found.astype(bool) & out.visible.astype(bool) & out.marker.str.startswith("M")
        e_raw = np.hypot(out.x_px - out.x_px_true, out.y_px - out.y_px_true)[ok]
        e_sm = np.hypot(out.x_px_smooth - out.x_px_true, out.y_px_smooth - out.y_px_true)[ok]
        z = ((out.x_px - out.x_px_true) / out.sd_px)[ok]
        raw, sm = float(np.sqrt(np.mean(e_raw ** 2))), float(np.sqrt(np.mean(e_sm ** 2)))
        print(f"{view}: 0.5 mm markers 2-D RMS raw {raw:.4f} px, smoothed {sm:.4f} px; raw error model z sd "
              f"{np.std(z):.2f}; error scales {[round(m.error_scale, 2) for m in models if m.marker.startswith('M')]}")
        assert sm < 0.1
        assert 0.8 < np.std(z) < 1.25


def test_a_bad_detection_is_left_out_not_followed():
    tab, xt, yt, sd = _smooth_motion(n=40, seed=6)
    tab.loc[17, "y_px"] += 2.0                      # a centre pulled 2 px off (about 15 sd)
    out, models = smooth_tracks(tab)
    assert out["smooth_outlier"].tolist() == [i == 17 for i in range(40)]
    assert models[0].n_outliers == 1
    assert abs(out.loc[17, "y_px_smooth"] - yt[17]) < 0.3


def test_a_marker_that_starts_moving_after_the_first_frame_is_not_an_outlier():
    n = 12
    t = np.arange(n) * 2.0
    y = 50 + np.where(np.arange(n) >= 1, 1.0 * (np.arange(n) - 0.5), 0.0)   # at rest, then 1 px/frame
    tab = _track(np.full(n, 100.0), y, np.full(n, 30.0), t)
    out, models = smooth_tracks(tab)
    assert not out["smooth_outlier"].any()
    assert out["y_px_smooth"].notna().all()


# --- the batched filter against a one-track, one-step-at-a-time reference ---------------------

def _ref_filter(t, z, r, q):
    """Textbook Kalman filter of one axis of one track under one model, a step at a time
    (white-noise acceleration; diffuse start at the first measurement).  Returns the
    log-likelihood and, per step, the predicted and filtered (x, v, p00, p01, p11)."""
    started = False
    x = v = p00 = p01 = p11 = 0.0
    ll, pred, filt = 0.0, [], []
    for k in range(len(t)):
        if started:
            dt = t[k] - t[k - 1]
            x = x + dt * v
            p00, p01, p11 = (p00 + 2 * dt * p01 + dt * dt * p11 + q * dt ** 3 / 3,
                             p01 + dt * p11 + q * dt * dt / 2, p11 + q * dt)
        pred.append((x, v, p00, p01, p11))
        if not math.isnan(z[k]):
            if started:
                S = p00 + r[k]
                e = z[k] - x
                ll -= 0.5 * (math.log(2 * math.pi * S) + e * e / S)
                k0, k1 = p00 / S, p01 / S
                x, v = x + k0 * e, v + k1 * e
                p00, p01, p11 = p00 - k0 * p00, p01 - k0 * p01, p11 - k1 * p01
            else:
                x, v, p00, p01, p11, started = z[k], 0.0, r[k], 0.0, 1e6, True
        filt.append((x, v, p00, p01, p11))
    return ll, pred, filt


def _ref_smooth(t, z, r, q):
    """Rauch-Tung-Striebel smoother of one axis over :func:`_ref_filter`: positions and variances
    (NaN before the first measurement)."""
    _, pred, filt = _ref_filter(t, z, r, q)
    n = len(t)
    first = int(np.flatnonzero(~np.isnan(z))[0])
    mean = [np.array(s[:2]) for s in filt], [np.array(s[:2]) for s in pred]
    cov = [[np.array([[s[2], s[3]], [s[3], s[4]]]) for s in a] for a in (filt, pred)]
    xs, ps = [None] * n, [None] * n
    xs[-1], ps[-1] = mean[0][-1], cov[0][-1]
    for k in range(n - 2, first - 1, -1):
        F = np.array([[1.0, t[k + 1] - t[k]], [0.0, 1.0]])
        C = cov[0][k] @ F.T @ np.linalg.inv(cov[1][k + 1])
        xs[k] = mean[0][k] + C @ (xs[k + 1] - mean[1][k + 1])
        ps[k] = cov[0][k] + C @ (ps[k + 1] - cov[1][k + 1]) @ C.T
    x = np.array([np.nan if k < first else xs[k][0] for k in range(n)])
    var = np.array([np.nan if k < first else ps[k][0, 0] for k in range(n)])
    return x, var


def _assert_variances_close(var, var_ref):
    """Smoothed variances from a track's first detection on: at the first, under the diffuse
    start's velocity variance of 1e6, most digits cancel (the reference's matrix inverse and the
    module's written-out terms round differently there)."""
    np.testing.assert_allclose(var[0], var_ref[0], rtol=1e-5)
    np.testing.assert_allclose(var[1:], var_ref[1:], rtol=1e-11)


def _ref_loglik(t, z, r, q, s):
    """Both axes of a track (z (n, 2)) under (q, scale s)."""
    return sum(_ref_filter(t, z[:, a], r * s ** 2, q)[0] for a in (0, 1))


def _ref_fit(t, z, r):
    """The maximum-likelihood grid point of one track, coarse to fine as documented: every 4th q
    and 2nd scale, then the full grid within a coarse step of the best (first best in q-major order)."""
    qs, scales = 10.0 ** LOG_Q_GRID, SCALE_GRID

    def best(cands):
        return max(cands, key=lambda c: _ref_loglik(t, z, r, qs[c[0]], scales[c[1]]))
    bq, bs = best([(i, j) for i in range(0, len(qs), 4) for j in range(0, len(scales), 2)])
    iq, js = best([(i, j) for i in range(max(0, bq - 3), min(len(qs), bq + 4))
                   for j in range(max(0, bs - 2), min(len(scales), bs + 3))])
    return qs[iq], scales[js]


def _gappy_tracks(t, rng):
    """Four tracks on clock ``t``: (n, 4, 2) positions with gaps, a late start, an early end and
    a spike, (n, 4) detector variances."""
    n = len(t)
    z = np.empty((n, 4, 2))
    z[:, 0] = np.stack([300 + 4 * np.sin(t / 3), 200 + 0.5 * t], axis=1)       # moving
    z[:, 1] = np.stack([350 + 0.3 * t, 260 - 2 * np.cos(t / 5)], axis=1)       # late start, early end
    z[:, 2] = [420.0, 180.0]                                                   # static
    z[:, 3] = np.stack([380 + 0.1 * t ** 1.5, 300 + np.where(t > t[n // 2], 3.0, 0.0)], axis=1)   # a slip
    snr = rng.uniform(8, 20, (n, 4))
    r = (CRB_FACTOR / snr) ** 2
    z += rng.normal(0, 1, z.shape) * np.sqrt(r)[:, :, None]
    missing = rng.random((n, 4)) < 0.1
    missing[n // 2:n // 2 + 5, 0] = True
    missing[:6, 1] = missing[n - 6:, 1] = True
    missing[n // 4 - 2:n // 4 + 3, 0] = False
    z[missing] = np.nan
    z[n // 4, 0, 0] += 3.0                                                     # a bad centre (~40 sd)
    return z, r


def test_batched_filter_and_smoother_match_a_one_track_reference():
    from bsipipe.imaging.smooth import _filter, _rts
    rng = np.random.default_rng(11)
    t = np.cumsum(rng.uniform(0.3, 0.7, 40))              # an irregular clock
    z, r = _gappy_tracks(t, rng)
    qs = np.array([1e-5, 1e-2, 1.0, 1e2, 1e5])
    ss = np.array([0.5, 1.0, 1.3, 2.0, 4.0])
    ll = _filter(t, z, r, qs[None, :], (ss ** 2)[None, :])   # every track under every model
    ref = [[_ref_loglik(t, z[:, i], r[:, i], q, s) for q, s in zip(qs, ss)] for i in range(4)]
    np.testing.assert_allclose(ll, ref, rtol=1e-12)
    qi, si = qs[[0, 2, 3, 4]], ss[[1, 2, 0, 3]]             # a model per track
    xs, var = _rts(*_filter(t, z, r, qi[:, None], (si ** 2)[:, None], keep=True))
    for i in range(4):
        first = np.flatnonzero(~np.isnan(z[:, i, 0]))[0]          # (no smoothed value before)
        for a in (0, 1):
            x_ref, var_ref = _ref_smooth(t, z[:, i, a], r[:, i] * si[i] ** 2, qi[i])
            np.testing.assert_allclose(xs[first:, i, a], x_ref[first:], rtol=1e-10)
            _assert_variances_close(var[first:, i], var_ref[first:])


def test_smooth_tracks_matches_the_reference_fit_per_track():
    """Views on one clock fitted together, a view on its own clock, a refit after a spike, a
    static track at the grid's edge, a too-short track: each track's model and smoothed values
    are those of the one-track reference on its data (the spike left out)."""
    rng = np.random.default_rng(12)
    tabs = []
    for view, t in (("cam1", np.arange(36) * 0.5), ("cam2", np.arange(36) * 0.5),
                    ("cam3", np.cumsum(rng.uniform(0.3, 0.7, 30)))):
        z, r = _gappy_tracks(t, rng)
        for j in range(4):
            snr = CRB_FACTOR / np.sqrt(r[:, j])
            tab = _track(z[:, j, 0], z[:, j, 1], np.where(np.isnan(z[:, j, 0]), np.nan, snr), t, f"M{j}", view)
            tabs.append(tab)
    short = tabs[-1].copy()
    short.loc[4:, ["x_px", "y_px", "snr"]] = np.nan          # 4 points: left unsmoothed
    short["marker"] = "short"
    table = pd.concat(tabs + [short], ignore_index=True)
    out, models = smooth_tracks(table)
    assert [(m.view, m.marker) for m in models] == [(v, f"M{j}") for v in ("cam1", "cam2", "cam3") for j in range(4)]
    assert out.loc[out.marker == "short", "x_px_smooth"].isna().all()
    assert sum(m.n_outliers for m in models) >= 3           # the spikes were left out, their tracks refitted
    assert min(m.q_px2_per_s3 for m in models) == 10.0 ** LOG_Q_GRID[0]     # the static track (cam1/2, 2 frames/s): fine window clipped
    for m in models:
        tr = out[(out.view == m.view) & (out.marker == m.marker)].sort_values("frame")
        # the grid is searched with time rescaled to REFERENCE_INTERVAL_S per median frame interval
        u = REFERENCE_INTERVAL_S / float(np.median(np.diff(tr.time_s.to_numpy())))
        t = tr.time_s.to_numpy() * u
        use = tr.x_px.notna() & ~tr.smooth_outlier
        z = np.where(use.to_numpy()[:, None], tr[["x_px", "y_px"]].to_numpy(), np.nan)
        r = np.where(use, CRB_FACTOR / tr.snr.to_numpy(), 1.0) ** 2
        q, s = _ref_fit(t, z, r)
        assert (m.q_px2_per_s3, m.error_scale) == (q * u ** 3, s), (m.view, m.marker)
        seen = np.flatnonzero(use)
        rows = tr.x_px.notna().to_numpy() & (np.arange(len(tr)) >= seen[0]) & (np.arange(len(tr)) <= seen[-1])
        for a, col in enumerate(("x_px_smooth", "y_px_smooth")):
            x_ref, var_ref = _ref_smooth(t, z[:, a], r * s ** 2, q)
            np.testing.assert_allclose(tr[col].to_numpy()[rows], x_ref[rows], rtol=1e-10)
        _assert_variances_close(tr.sd_px_smooth.to_numpy()[rows] ** 2, var_ref[rows])
        assert tr.x_px_smooth.notna().sum() == rows.sum()


def _pinhole(name: str, R: np.ndarray, centre_mm: np.ndarray, f_px: float = 5000.0, c_px: float = 512.0):
    from bsipipe.imaging.triangulate import ViewGeometry
    K = np.array([[f_px, 0, c_px], [0, f_px, c_px], [0, 0, 1.0]])
    t = -R @ centre_mm
    return ViewGeometry(name, R, t, K, to_normalized=lambda u: (np.asarray(u, float).reshape(-1, 2) - c_px) / f_px,
                        to_pixels=lambda m: np.asarray(m, float).reshape(-1, 2) * f_px + c_px)


def test_stereo_error_check_finds_what_the_error_model_misses():
    """Two C-arms at 90 degrees (1 m from the isocentre, f = 5000 px: 0.2 mm per px there).
    Marker A's centres err 5x their stated sd_px_smooth (a bias the smoother cannot average
    away), B's as stated, C's as stated but seen in only 6 frames: the ray gaps give A a
    scale near 5 (its z RMS), B none to speak of, C none (too few points)."""
    from bsipipe.imaging.smooth import stereo_error_check
    from bsipipe.imaging.triangulate import triangulate
    a = _pinhole("cam1", np.eye(3), np.array([0.0, 0.0, -1000.0]))
    rb = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])      # looks along +x
    b = _pinhole("cam2", rb, np.array([-1000.0, 0.0, 0.0]))
    rng = np.random.default_rng(4)
    rows2, rows3 = [], []
    sd_stated = 0.02
    for m, n, factor in (("A", 200, 5.0), ("B", 200, 1.0), ("C", 6, 1.0)):
        X = rng.normal(0, 10.0, (n, 3))
        uv = {}
        for v in (a, b):
            Xc = X @ v.R.T + v.t
            uv[v.name] = v.to_pixels(Xc[:, :2] / Xc[:, 2:3]) + rng.normal(0, factor * sd_stated, (n, 2))
        r = triangulate((a, b), uv["cam1"], uv["cam2"], refine=False)
        for k in range(n):
            rows3.append({"frame": k, "marker": m, "n_views": 2, "x_mm": r["X_mm"][k, 0], "y_mm": r["X_mm"][k, 1],
                          "z_mm": r["X_mm"][k, 2], "ray_gap_signed_mm": r["ray_gap_signed_mm"][k],
                          "ray_gap_mm_raw": r["ray_gap_mm"][k]})
            for v in ("cam1", "cam2"):
                rows2.append({"view": v, "frame": k, "marker": m, "sd_px": sd_stated, "sd_px_smooth": sd_stated})
    out = stereo_error_check(pd.DataFrame(rows3), pd.DataFrame(rows2), (a, b), ("cam1", "cam2"))
    print({m: (r["n_points"], round(r["z_rms_smooth"], 2), round(r["scale_smooth"], 2)) for m, r in out.items()})
    assert out["A"]["scale_smooth"] == pytest.approx(5.0, rel=0.15)
    assert out["A"]["scale_raw"] == pytest.approx(5.0, rel=0.15)
    assert 1.0 <= out["B"]["scale_smooth"] < 1.2
    assert out["C"]["n_points"] == 6 and out["C"]["scale_smooth"] == 1.0


def test_the_same_frames_are_smoothed_alike_at_any_frame_rate():
    """The q grid had been fixed in px^2/s^3: at 0.001 frames/s nothing was smoothed (and an
    overflow warning leaked), at 10,000 frames/s the track was over-smoothed with too small an
    sd.  Time is now rescaled to 2 frames/s for the search: the smoothed track is the same at
    any rate, and q is reported in px^2/s^3 of the real rate."""
    import warnings
    tab, xt, yt, sd = _smooth_motion(seed=1)
    ref, ref_models = smooth_tracks(tab)
    for fps in (0.001, 0.01, 30.0, 10000.0):
        t2 = tab.copy()
        t2["time_s"] = tab["time_s"] * (2.0 / fps)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            out, models = smooth_tracks(t2)
        for c in ("x_px_smooth", "y_px_smooth", "sd_px_smooth"):
            np.testing.assert_allclose(out[c], ref[c], rtol=1e-9, atol=1e-9)
        assert models[0].q_px2_per_s3 == pytest.approx(ref_models[0].q_px2_per_s3 * (fps / 2.0) ** 3, rel=1e-9)


def test_a_track_too_short_to_smooth_keeps_its_detections_sd():
    """A sequence of 3 frames: no track can be smoothed (5 points needed), and every stated
    error had been left empty (sd_px too, though it is the detection's own, 0.798 / SNR).
    sd_px is now the detector's model there; the smoothed columns stay empty."""
    from bsipipe.imaging.smooth import centre_sd_px, smooth_tracks
    rows = [{"view": "cam1", "frame": f, "time_s": 0.5 * f, "marker": m, "x_px": 10.0 + f + k, "y_px": 20.0,
             "snr": 10.0 + k, "found": True} for f in range(3) for k, m in enumerate(("A", "B"))]
    out, models = smooth_tracks(pd.DataFrame(rows))
    assert models == []
    np.testing.assert_allclose(out["sd_px"], centre_sd_px(out["snr"].to_numpy(float)))
    assert out["x_px_smooth"].isna().all() and out["sd_px_smooth"].isna().all()
