"""The stereo loop's fast paths give the numbers of the straightforward code they replace.

``track_effects`` builds and evaluates PCHIP, smooths tracks (Savitzky-Golay) and arranges the
2-D table with whole-array operations; each is checked here against the library call it
stands in for (the same numbers, bit for bit; the p-values of ``bsipipe.distributions`` in
``test_distributions.py``), and the loop's path is checked not to import ``scipy.stats`` or
``scipy.signal`` (about a second of start-up).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pandas as pd
import pytest

from bsipipe.imaging import track_effects as te
from bsipipe.imaging.triangulate import refine_points, triangulate_dlt, views_from_cameras

from test_triangulate import _moving_tracks, two_carms


def _runs_of(ok):
    run_id = np.cumsum(np.r_[True, ~(ok[1:] & ok[:-1])])
    return [np.flatnonzero((run_id == r) & ok) for r in np.unique(run_id[ok])]


def _pchip_reference(t_src, y, t_query):
    """One PchipInterpolator per marker and run, NaN outside the runs (what _Interp does)."""
    from scipy.interpolate import PchipInterpolator
    out = np.full((len(t_query),) + y.shape[1:], np.nan)
    for j in range(y.shape[1]):
        ok = np.isfinite(y[:, j]).reshape(len(y), -1).all(axis=1) & np.isfinite(t_src)
        for idx in _runs_of(ok):
            if len(idx) >= 2:
                ts = t_src[idx]
                q = (t_query >= ts[0]) & (t_query <= ts[-1])
                if q.any():
                    out[q, j] = PchipInterpolator(ts, y[idx, j], axis=0)(t_query[q])
    return out


def test_interp_is_scipy_pchip_bit_for_bit():
    """Runs of every length (2 samples: linear), flat and sign-changing pieces, gaps in the
    clock, queries at breakpoints, at run ends and outside the runs (NaN)."""
    rng = np.random.default_rng(11)
    n = 0
    for trial in range(120):
        F, M = int(rng.integers(1, 60)), int(rng.integers(1, 5))
        t = np.arange(F) * 0.25 + rng.normal()
        if trial % 3 == 0:
            t = t + rng.uniform(-0.1, 0.1, F)
        if trial % 5 == 0:
            t[rng.random(F) < 0.1] = np.nan
        y = rng.normal(size=(F, M, 2)) * 10
        if trial % 4 == 0:
            y = np.cumsum(y, axis=0)
        if trial % 6 == 0:
            y = np.round(y)
        y[rng.random((F, M)) < rng.choice([0.0, 0.1, 0.3])] = np.nan
        fin = t[np.isfinite(t)]
        q = np.r_[rng.uniform(fin.min() - 1, fin.max() + 1, 40) if len(fin) else [], t, np.nan]
        it = te._Interp(t, y)
        ref = _pchip_reference(t, y, q)
        assert np.array_equal(it(q), ref, equal_nan=True), trial
        cols = rng.integers(0, M, 50)
        at = rng.integers(0, len(q), 50)
        assert np.array_equal(it.at_points(q, cols, at=at), ref[at, cols], equal_nan=True), trial
        assert np.array_equal(it.at_points(q[at], cols), ref[at, cols], equal_nan=True), trial
        n += np.isfinite(ref).any()
    assert n > 60


def test_interp_with_a_clock_that_goes_back_uses_scipy_per_run():
    t = np.array([0.0, 1.0, 2.0, 3.0, 2.5, 5.0, 6.0, 7.0])
    y = np.arange(16.0).reshape(8, 1, 2) ** 1.5
    y[3:5] = np.nan                              # the runs themselves are increasing
    it = te._Interp(t, y)
    assert not it._fast
    q = np.linspace(-1, 8, 37)
    assert np.array_equal(it(q), _pchip_reference(t, y, q), equal_nan=True)


def test_smooth_runs_is_savgol_filter_per_run_bit_for_bit():
    from scipy.signal import savgol_filter
    rng = np.random.default_rng(12)
    for trial in range(15):
        F, M = int(rng.integers(3, 200)), int(rng.integers(1, 5))
        x = np.cumsum(rng.normal(size=(F, M, 2)), axis=0) * 3 + 500
        x[rng.random((F, M)) < 0.05] = np.nan
        for w in (3, 8, 9, 11):
            ref = x.copy()
            for j in range(M):
                for idx in _runs_of(np.isfinite(x[:, j]).all(axis=1)):
                    if len(idx) >= (w | 1):
                        ref[idx, j] = savgol_filter(x[idx, j], w | 1, 2, axis=0)
            assert np.array_equal(te._smooth_runs(x, w), ref, equal_nan=True), (trial, w)


def _view_arrays_reference(table, view, markers, frames):
    """The row-by-row arrangement (the last row of a cell counts, its position only if found)."""
    t = table[table["view"] == view]
    F, M = len(frames), len(markers)
    xy = np.full((F, M, 2), np.nan)
    times = np.full(F, np.nan)
    status = np.full((F, M), "", dtype=object)
    fpos = {f: i for i, f in enumerate(frames)}
    mpos = {m: j for j, m in enumerate(markers)}
    for r in t.itertuples(index=False):
        i, j = fpos.get(r.frame), mpos.get(r.marker)
        if i is None or j is None:
            continue
        times[i] = r.time_s
        status[i, j] = r.status
        if r.found:
            xy[i, j] = (r.x_px, r.y_px)
    found = np.isfinite(xy).all(axis=2)
    edge = np.zeros_like(found)
    ch = found[1:] != found[:-1]
    edge[1:] |= ch
    edge[:-1] |= ch
    return xy, times, found & (edge | (status == "partial"))


def test_stereo_data_matches_the_row_by_row_arrangement():
    """Shuffled rows, missing rows, repeated cells, unknown frames and markers, lost and
    partial flags."""
    cams = two_carms()
    V = views_from_cameras(cams)
    tab, _ = _moving_tracks(cams, seed=14)
    rng = np.random.default_rng(14)
    lost = rng.random(len(tab)) < 0.05
    tab.loc[lost, "found"] = False
    tab.loc[lost, "status"] = "lost"
    tab.loc[(~lost) & (rng.random(len(tab)) < 0.05), "status"] = "partial"
    tab.loc[rng.random(len(tab)) < 0.02, "status"] = np.nan
    dup = tab.sample(60, random_state=1).copy()
    dup["x_px"] += 0.5
    dup["time_s"] += 0.001
    dup.loc[dup.index[:20], "found"] = False
    extra = tab.sample(10, random_state=2).copy()
    extra["marker"] = "B-only"
    extra["view"] = "cam2"
    tab = pd.concat([tab.sample(frac=0.95, random_state=3), dup, extra])
    d = te.stereo_data(tab, (V["cam1"], V["cam2"]))
    assert "B-only" not in d.markers and all(type(m) is str for m in d.markers)
    for view, xy, times, sus in (("cam1", d.xa, d.ta, d.suspect_a), ("cam2", d.xb, d.tb, d.suspect_b)):
        rx, rt, rs = _view_arrays_reference(tab, view, d.markers, d.frames)
        assert np.array_equal(xy, rx, equal_nan=True)
        assert np.array_equal(times, rt, equal_nan=True)
        assert np.array_equal(sus, rs)


def test_refinement_from_the_midpoint_reaches_the_dlt_start_optimum():
    """Gauss-Newton from the rays' midpoints (the fast start) lands where it lands from the
    linear (DLT) point, to rounding."""
    rng = np.random.default_rng(15)
    cams = two_carms()
    V = views_from_cameras(cams)
    va, vb = V["cam1"], V["cam2"]
    X = rng.uniform(-40, 40, (3000, 3))
    ua = cams["cam1"].project(X) + rng.normal(0, 0.5, (len(X), 2))
    ub = cams["cam2"].project(X) + rng.normal(0, 0.5, (len(X), 2))
    ub[:30] += 25.0                                    # a few far-off pairs (large gaps)
    ma, mb = va.to_normalized(ua), vb.to_normalized(ub)
    from bsipipe.imaging.triangulate import _midpoints
    Xm = refine_points([va, vb], [ma, mb], _midpoints((va, vb), ma, mb))
    Xd = refine_points([va, vb], [ma, mb], triangulate_dlt([va, vb], [ma, mb]))
    assert np.abs(Xm - Xd).max() < 1e-9


def test_find_swaps_matches_the_pair_by_pair_search():
    cams = two_carms()
    V = views_from_cameras(cams)
    tab, _ = _moving_tracks(cams, swap=(30, [1, 4]), seed=16)
    sel = (tab["view"] == "cam2") & tab["frame"].between(50, 60)
    a, b = sel & (tab["marker"] == "M1"), sel & (tab["marker"] == "M3")
    tab.loc[a, "marker"], tab.loc[b, "marker"] = "M3", "M1"
    d = te.stereo_data(tab, (V["cam1"], V["cam2"]))
    got = te.find_swaps(d, d.xb)
    # reference: each pair on its own
    da, db = te._ray_dirs(d.views[0], d.xa), te._ray_dirs(d.views[1], d.xb)
    base = d.views[1].centre_mm - d.views[0].centre_mm
    g = te._gaps_from_dirs(da, db, base)
    fin = g[np.isfinite(g)]
    s = max(1.4826 * np.median(np.abs(fin - np.median(fin))), 1e-9)
    ref = []
    M = len(d.markers)
    for i in range(M):
        for j in range(i + 1, M):
            cur = np.abs(g[:, i]) + np.abs(g[:, j])
            alt = np.abs(te._gaps_from_dirs(da[:, i], db[:, j], base)) + np.abs(te._gaps_from_dirs(da[:, j], db[:, i], base))
            hit = np.isfinite(cur) & np.isfinite(alt) & (alt < 0.25 * cur) & (cur > 10 * s)
            for idx in _runs_of(hit):
                ref.append((d.markers[i], d.markers[j], int(d.frames[idx[0]]), int(d.frames[idx[-1]]),
                            float(np.nanmean(cur[idx]) / 2), float(np.nanmean(alt[idx]) / 2)))
    assert [(*s_["markers"], s_["first_frame"], s_["last_frame"], s_["gap_before_mm"], s_["gap_after_mm"])
            for s_ in got] == ref
    assert {tuple(sorted(s_["markers"])) for s_ in got} == {("M2", "M5"), ("M1", "M3")}


def test_the_loop_imports_neither_scipy_stats_nor_scipy_signal():
    code = textwrap.dedent("""
        import sys
        sys.path.insert(0, "tests")
        from test_triangulate import _moving_tracks, two_carms
        from bsipipe.imaging.track_effects import close_stereo_loop, stereo_data
        from bsipipe.imaging.triangulate import views_from_cameras
        cams = two_carms()
        V = views_from_cameras(cams)
        tab, _ = _moving_tracks(cams, offset_s=0.12)
        loop, fit, _ = close_stereo_loop(stereo_data(tab, (V["cam1"], V["cam2"])))
        assert loop["steps"][0]["effect"] == "view-time-offset"
        print(sorted(m for m in ("scipy.stats", "scipy.signal") if m in sys.modules))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    assert out.stdout.strip().splitlines()[-1] == "[]"
