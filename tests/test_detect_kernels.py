"""The compiled sub-pixel fits (``bsipipe.imaging._kernels``, built by ``setup.py``) against their
NumPy versions in :mod:`bsipipe.imaging.detect`: the same values to rounding on random patches
(beads on planes and edges, noise, integer and float pixels, masks, NaN), and the same centres
on the real X-ray frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import bsipipe.imaging.detect as D
from bsipipe.imaging.detect import refine_at
from bsipipe.io.images import read_image

XRAY = Path(__file__).parent / "data" / "real" / "xray_frame_deepxromm"


def test_the_kernels_are_built():
    """``pip install -e .`` (the Makefile's install step) compiles them; without them every fit
    still runs, in NumPy, about a fifth slower per tracked frame -- a build that silently failed
    would only show in ``make bench``, so it fails here."""
    from bsipipe.imaging import _kernels
    assert D._kernels is _kernels
    assert {"centroid", "gaussian_fit", "plane_removed", "edge_fit"} <= set(dir(_kernels))
    from bsipipe.provenance import library_versions
    assert library_versions()["subpixel_fits"] == f"compiled (bsipipe.imaging._kernels {D.KERNELS_VERSION})"


def _patches(rng, geo, n, *, integer=False, edge=False):
    """``n`` raw patches: a dark Gaussian bead near the centre on a tilted background, maybe
    on an edge, with noise; pixels rounded to integers where asked."""
    h = geo.half
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    c0 = rng.uniform(-1, 1, (n, 2))
    amp = rng.uniform(0, 60, n)
    sig = rng.uniform(0.8, 3, n)
    bg = rng.uniform(50, 200, (n, 1, 1)) + rng.uniform(-3, 3, (n, 1, 1)) * xx + rng.uniform(-3, 3, (n, 1, 1)) * yy
    if edge:
        side = xx * rng.uniform(-1, 1, (n, 1, 1)) + yy * rng.uniform(-1, 1, (n, 1, 1)) > rng.uniform(-5, 5, (n, 1, 1))
        bg = bg + side * rng.uniform(0, 80, (n, 1, 1))
    bead = amp[:, None, None] * np.exp(-((xx - c0[:, 0, None, None]) ** 2 + (yy - c0[:, 1, None, None]) ** 2)
                                       / (2 * sig[:, None, None] ** 2))
    p = bg - bead + rng.normal(0, 1, (n, 1, 1)) * rng.uniform(0.1, 10, (n, 1, 1)) * rng.normal(0, 1, bead.shape)
    if integer:
        p = np.round(p)
    return p.reshape(n, -1)


def _geos():
    st = D.DetectionSettings()
    return [D._geo(d, st.smooth_px(d), st.window_px(d)) for d in (4.0, 9.0)]


@pytest.mark.parametrize("geo", _geos(), ids=["4px", "9px"])
def test_kernels_agree_with_numpy_on_random_patches(geo):
    rng = np.random.default_rng(11)
    worst = {"plane": 0.0, "centroid": 0.0, "mass": 0.0, "fit_xy": 0.0, "fit_amp": 0.0, "fit_sigma": 0.0}
    n_ok = n_flag = 0
    for trial in range(150):
        n = int(rng.integers(1, 14))
        p = _patches(rng, geo, n, integer=trial % 3 == 0, edge=trial % 4 == 0)
        valid = None if trial % 2 else rng.random(p.shape) > rng.uniform(0, 0.6)
        s = D._plane_removed(p, geo, 1.0, valid)
        s_ref = D._plane_removed_numpy(p, geo, 1.0, valid)
        worst["plane"] = max(worst["plane"], float(np.abs(s - s_ref).max()))
        for n_iter in (3, 6):
            c, m, e = D._centroid(s_ref, geo, n_iter)
            c_ref, m_ref, e_ref = D._centroid_numpy(s_ref, geo, n_iter)
            worst["centroid"] = max(worst["centroid"], float(np.abs(c - c_ref).max()))
            worst["mass"] = max(worst["mass"], float((np.abs(m - m_ref) / np.maximum(np.abs(m_ref), 1.0)).max()))
            np.testing.assert_allclose(e, e_ref, rtol=1e-9)
        start = rng.uniform(-1, 1, (n, 2))
        xy, amp, sg, ok = D._gaussian_fit(s_ref, geo, start, 1.5, valid)
        xy_r, amp_r, sg_r, ok_r = D._gaussian_fit_numpy(s_ref, geo, start, 1.5, valid)
        n_flag += int((ok != ok_r).sum())
        both = ok & ok_r
        n_ok += int(both.sum())
        if both.any():
            worst["fit_xy"] = max(worst["fit_xy"], float(np.abs(xy[both] - xy_r[both]).max()))
            worst["fit_amp"] = max(worst["fit_amp"], float((np.abs(amp[both] - amp_r[both]) / amp_r[both]).max()))
            worst["fit_sigma"] = max(worst["fit_sigma"], float(np.abs(sg[both] - sg_r[both]).max()))
    print(f"{n_ok} converged fits; worst differences {worst}")
    assert n_flag == 0 and n_ok > 500
    assert worst["plane"] < 1e-9 and worst["centroid"] < 1e-12 and worst["mass"] < 1e-12
    assert worst["fit_xy"] < 1e-9 and worst["fit_amp"] < 1e-9 and worst["fit_sigma"] < 1e-9


def _edge_patches(rng, geo, n):
    """``n`` raw patches of a bead beside a blurred step edge (any direction, up to 4 px off the
    centre), the case the edge background is for."""
    h = geo.half
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    th = rng.uniform(0, np.pi, (n, 1, 1))
    u = xx * np.cos(th) + yy * np.sin(th) - rng.uniform(-4, 4, (n, 1, 1))
    step = rng.uniform(5, 40, (n, 1, 1)) / (1 + np.exp(-u / rng.uniform(0.5, 2, (n, 1, 1))))
    c0 = rng.uniform(-1, 1, (n, 2))
    bead = rng.uniform(5, 40, (n, 1, 1)) * np.exp(-((xx - c0[:, 0, None, None]) ** 2
                                                    + (yy - c0[:, 1, None, None]) ** 2) / (2 * 1.3 ** 2))
    p = 120 + step - bead + rng.uniform(0.3, 2, (n, 1, 1)) * rng.normal(0, 1, bead.shape)
    return p.reshape(n, -1)


@pytest.mark.parametrize("geo", _geos(), ids=["4px", "9px"])
def test_edge_kernel_agrees_with_numpy(geo, monkeypatch):
    """The edge background: the same rows looked at and chosen, the same fits (plane, profile,
    residuals, depth, range) and backgrounds to rounding, compiled or in NumPy."""
    rng = np.random.default_rng(5)
    n_look = n_chosen = 0
    worst_fit = worst_bg = 0.0
    for trial in range(150):
        n = int(rng.integers(1, 14))
        p = _edge_patches(rng, geo, n)
        if trial % 3 == 0:
            p = np.round(p)
        valid = None if trial % 2 else rng.random(p.shape) > rng.uniform(0, 0.3)
        xy = rng.uniform(0, 80, (n, 2)).round()
        noise = rng.uniform(0.3, 2, n)
        w = np.ones((n, len(geo.ring_idx))) if valid is None else valid[:, geo.ring_idx].astype(float)
        crowded = rng.random(n) < 0.1
        fast = D._edge_fit_compiled(p, geo, valid, w, crowded, noise)
        plain = D._edge_fit_numpy(p, geo, valid, w, p[:, geo.ring_idx], crowded, noise)
        np.testing.assert_array_equal(fast[0], plain[0])
        n_look += len(plain[0])
        for a, b in zip(fast[1:], plain[1:]):
            if b.size:
                worst_fit = max(worst_fit, float(np.max(np.abs(a - b) / np.maximum(1.0, np.abs(b)))))
        bg, chosen = D._edge_background(p, geo, valid, xy, xy, noise)
        monkeypatch.setattr(D, "_kernels", None)
        bg_ref, chosen_ref = D._edge_background(p, geo, valid, xy, xy, noise)
        monkeypatch.undo()
        np.testing.assert_array_equal(chosen, chosen_ref)
        n_chosen += int(chosen.sum())
        worst_bg = max(worst_bg, float(np.abs(bg - bg_ref).max()))
    print(f"{n_look} rows looked at, {n_chosen} chosen; worst relative fit difference {worst_fit:.2g}, "
          f"background {worst_bg:.2g}")
    assert n_look > 800 and n_chosen > 50
    assert worst_fit < 1e-9 and worst_bg < 1e-9


def test_kernels_propagate_nan_as_numpy_does():
    """A float frame with a NaN pixel: the same NaN pattern (a plane's NaN ring median drops
    the NaN rows' limits, a centroid NaN stays NaN)."""
    geo = _geos()[0]
    rng = np.random.default_rng(3)
    p = _patches(rng, geo, 6)
    p[1, geo.ring_idx[4]] = np.nan         # in the ring: the plane's fit
    p[3, geo.support[0]] = np.nan          # in the support: the centroid and the fit
    s, s_ref = D._plane_removed(p, geo, 1.0, None), D._plane_removed_numpy(p, geo, 1.0, None)
    np.testing.assert_array_equal(np.isnan(s), np.isnan(s_ref))
    np.testing.assert_allclose(s, s_ref, rtol=0, atol=1e-9)
    for a, b in zip(D._centroid(s_ref, geo, 3), D._centroid_numpy(s_ref, geo, 3)):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    start = np.zeros((6, 2))
    a, b = D._gaussian_fit(s_ref, geo, start, 1.5), D._gaussian_fit_numpy(s_ref, geo, start, 1.5)
    np.testing.assert_array_equal(a[3], b[3])
    np.testing.assert_allclose(a[0][a[3]], b[0][b[3]], rtol=0, atol=1e-9)


def test_real_xray_frame_same_centres_compiled_or_not(monkeypatch):
    """The 24 seeded beads of the real X-ray frame (XMALab's rough positions): the same centres,
    amplitudes and widths with the kernels as with NumPy alone."""
    img = read_image(XRAY / "sample_frame.jpg")
    inp = pd.read_csv(XRAY / "sample_frame_input.csv")
    names = [c[:-7] for c in inp.columns if c.endswith("_cam1_X")]
    xy = np.array([[inp[n + "_cam1_X"][0], inp[n + "_cam1_Y"][0]] for n in names])
    xy = xy[np.isfinite(xy).all(axis=1)]
    assert len(xy) >= 20
    fast = refine_at(img, xy, 4.0, "dark")
    monkeypatch.setattr(D, "_kernels", None)
    plain = refine_at(img, xy, 4.0, "dark")
    assert fast["found"].sum() >= 20
    np.testing.assert_array_equal(fast["found"].to_numpy(), plain["found"].to_numpy())
    for col in ("x_px", "y_px", "sigma_px"):
        np.testing.assert_allclose(fast[col].to_numpy(float), plain[col].to_numpy(float), rtol=0, atol=1e-9,
                                   equal_nan=True)
    np.testing.assert_allclose(fast["amplitude"].to_numpy(float), plain["amplitude"].to_numpy(float), rtol=1e-9,
                               equal_nan=True)
