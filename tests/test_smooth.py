"""Kalman/RTS smoothing of 2-D tracks (``bsipipe.imaging.smooth``)."""

import numpy as np
import pandas as pd
import pytest

from bsipipe.imaging.smooth import CRB_FACTOR, smooth_tracks


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
