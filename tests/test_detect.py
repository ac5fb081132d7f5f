"""Marker detection on synthetic beads with known centres, a real X-ray frame against
XMALab-style refined positions, real microscopy against trackpy, and the per-frame fast paths against the plain formulas."""

import math
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

import bsipipe.imaging.detect as D
from bsipipe.imaging.camera import Camera
from bsipipe.imaging.detect import (FieldOfView, detect_markers, find_field_of_view, pixel_noise, refine_at,
                                    structuring_size, tophat)
from bsipipe.io.images import read_image
from bsipipe.synth.xray import Detector, RayField, apply_patch, sphere_patch

REAL = Path(__file__).parent / "data" / "real"
XRAY = REAL / "xray_frame_deepxromm"
WATER = REAL / "trackpy_bulk_water"

F_PX = 3355.0      # the twin's C-arm: SID 1000 mm imaged on 1024 px of a 305 mm intensifier
Z_MM = 640.0       # source-object distance
#: The twin's noise before it was set from real C-arm frames (SNR 19 for a 4 px bead, against
#: 12 at today's default, bsipipe.synth.config.NoiseConfig): the absolute accuracies and the
#: ranking of the centre methods below were measured there and are checked there.
QUANTA_SNR19 = 1000.0


# --- synthetic beads: H6's X-ray renderer (exact chord lengths, detector chain) -------------------

def bead_camera(size: int) -> Camera:
    return Camera(np.array([[F_PX, 0, (size - 1) / 2], [0, F_PX, (size - 1) / 2], [0, 0, 1]]), np.zeros(5),
                  np.eye(3), np.zeros(3), (size, size))


def render_beads(centres_px: np.ndarray, diameter_px: float, size: int, rng, *, field=None, noise: bool = True,
                 bright: bool = False, skip=(), detector: Detector | None = None, quantize: bool = True,
                 quanta_per_px: float | None = None, background: np.ndarray | None = None) -> np.ndarray:
    """Steel spheres whose centres project to ``centres_px`` (N, 2), ``diameter_px`` across,
    through the twin's detector chain with its defaults (blur, veiling glare, heel effect,
    vignetting, video gamma, quantum and read noise, 8 bits; ``quanta_per_px`` other than
    the default).  ``skip``: indices not drawn; ``noise=False`` and ``quantize=False`` give
    the expected image itself; ``background`` (size, size): the transmission of what lies
    behind the beads (bone, an instrument), 1 where nothing does."""
    cam = bead_camera(size) if field is None else field.camera
    field = RayField(cam) if field is None else field
    r_mm = diameter_px * Z_MM / F_PX / 2
    T = np.ones((size, size), np.float32)
    for k, (u, v) in enumerate(np.asarray(centres_px, float).reshape(-1, 2)):
        if k in skip:
            continue
        X = [(u - (size - 1) / 2) * Z_MM / F_PX, (v - (size - 1) / 2) * Z_MM / F_PX, Z_MM]
        apply_patch(T, sphere_patch(field, X, r_mm, 1.5, ss=8))
    if background is not None:
        T *= np.asarray(background, np.float32)
    det = detector or Detector((size, size), ((size - 1) / 2, (size - 1) / 2), 0.49 * size)
    if quanta_per_px is not None:
        det.quanta_per_px = quanta_per_px
    det.noise = noise
    img, _ = det.expose(T, rng if noise else None, quantize=quantize)
    if bright:
        return (det.full_scale - img).astype(img.dtype)
    return img


def cramer_rao_px(centres_px: np.ndarray, diameter_px: float, size: int, quanta_per_px: float | None = None) -> float:
    """RMS (px, both axes) of the Cramer-Rao bound on the centres of these beads at the
    detector's default noise (or ``quanta_per_px``): the Fisher information of each centre
    from the derivative of the expected image (rendered at +-0.05 px) and the pixel noise,
    which under the video chain's gamma 1/2 is the same everywhere (``Detector.expose``),
    plus 8-bit quantisation (1/12 grey level^2)."""
    det = Detector((size, size), ((size - 1) / 2, (size - 1) / 2), 0.49 * size)
    if quanta_per_px is not None:
        det.quanta_per_px = quanta_per_px
    top = det.level * det.full_scale
    read = det.read_noise_dn * det.full_scale / 255.0
    var = 0.25 * top * top / det.quanta_per_px + read * read + 1.0 / 12.0
    h = 0.05
    c = np.asarray(centres_px, float)
    field = RayField(bead_camera(size))
    grads = []
    for ax in (0, 1):
        d = np.zeros(2)
        d[ax] = h
        hi = render_beads(c + d, diameter_px, size, None, field=field, noise=False, quantize=False)
        lo = render_beads(c - d, diameter_px, size, None, field=field, noise=False, quantize=False)
        grads.append((hi.astype(float) - lo.astype(float)) / (2 * h))
    gx, gy = grads
    bound = []
    r = int(np.ceil(diameter_px + 4))
    for u, v in c:
        ys, xs = slice(int(v) - r, int(v) + r + 1), slice(int(u) - r, int(u) + r + 1)
        a, b = gx[ys, xs].ravel(), gy[ys, xs].ravel()
        F = np.array([[a @ a, a @ b], [a @ b, b @ b]]) / var
        bound.append(np.trace(np.linalg.inv(F)))
    return float(np.sqrt(np.mean(bound)))


def bead_grid(n_side: int, size: int, rng, margin: int = 90) -> np.ndarray:
    """Bead centres on a jittered grid inside the circular field, sub-pixel phases uniform."""
    sp = (size - 2 * margin) / (n_side - 1)
    g = np.array([(margin + i * sp, margin + j * sp) for i in range(n_side) for j in range(n_side)])
    g += rng.uniform(-0.5, 0.5, g.shape)
    c = (size - 1) / 2
    return g[np.hypot(g[:, 0] - c, g[:, 1] - c) < 0.49 * size - 25]


def match(found: pd.DataFrame, truth: np.ndarray, tol: float = 2.0):
    """Nearest detection of every true centre (KD-tree, as trackpy's tests do): errors (N, 2)
    with NaN rows where none is within ``tol``."""
    xy = found[["x_px", "y_px"]].to_numpy()
    if len(xy) == 0:
        return np.full(truth.shape, np.nan)
    d, j = cKDTree(xy).query(truth)
    e = xy[j] - truth
    e[d > tol] = np.nan
    return e


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(np.sum(e ** 2, axis=1))))


@pytest.mark.parametrize("quanta_per_px", [None, QUANTA_SNR19], ids=["default-noise", "snr19-noise"])
@pytest.mark.parametrize("diameter_px", [2.6, 4.0, 5.2])
def test_synthetic_beads_centre_rms(diameter_px, quanta_per_px):
    """Every bead is found, nothing else, and the centres are unbiased and close to the best
    any estimator can do (the Cramer-Rao bound): within 15 % of it, at the twin's default
    noise (real C-arm SNR) and at its former one.  At the former (SNR 19 for 4 px) that is
    under 0.1 px RMS for 0.75 and 1 mm beads (4 and 5.2 px); at the default the bound is
    0.09 px for 4 px, 0.19 px for 0.5 mm beads (2.6 px, SNR ~ 6): no detector reaches
    0.1 px on 0.5 mm beads at the noise of real C-arm frames."""
    rng = np.random.default_rng(11)
    truth = bead_grid(8, 512, rng)
    img = render_beads(truth, diameter_px, 512, rng, quanta_per_px=quanta_per_px)
    found = detect_markers(img, diameter_px, "dark")
    e = match(found, truth)
    crb = cramer_rao_px(truth, diameter_px, 512, quanta_per_px)
    print(f"{diameter_px} px beads, {quanta_per_px or 'default'} quanta/px: {np.isfinite(e[:, 0]).sum()}/{len(truth)} "
          f"found, {len(found)} detections, centre RMS {rms(e):.4f} px, Cramer-Rao bound {crb:.4f} px "
          f"(ratio {rms(e) / crb:.3f}), SNR median {found['snr'].median():.1f}")
    assert np.isfinite(e).all()
    assert len(found) == len(truth)
    assert rms(e) < 1.15 * crb
    if diameter_px >= 4.0 and quanta_per_px == QUANTA_SNR19:
        assert rms(e) < 0.1
    assert abs(np.mean(e[:, 0])) < 0.03 and abs(np.mean(e[:, 1])) < 0.03


def test_centre_methods_compared():
    """The measurement behind the default: on 2.6 px and 4 px beads the Gaussian refinement
    has a smaller error than the intensity-weighted centroid (pixel locking) and than
    radial symmetry (noisier on beads only 2-4 px across), at SNR 19 for 4 px beads."""
    rng = np.random.default_rng(12)
    out = {}
    for d in (2.6, 4.0):
        truth = bead_grid(8, 512, rng)
        img = render_beads(truth, d, 512, rng, quanta_per_px=QUANTA_SNR19)
        for m in ("gaussian", "centroid", "radial"):
            out[d, m] = rms(match(refine_at(img, truth, d, "dark", method=m), truth))
    print({f"{d} px {m}": round(v, 4) for (d, m), v in out.items()})
    for d in (2.6, 4.0):
        assert out[d, "gaussian"] < out[d, "centroid"]
        assert out[d, "gaussian"] < out[d, "radial"]


def test_bright_polarity_and_no_signal():
    """Bright beads (4 px, SNR 19) found as well as dark ones; pure noise gives nothing."""
    rng = np.random.default_rng(13)
    truth = bead_grid(5, 256, rng, margin=60)
    img = render_beads(truth, 4.0, 256, rng, bright=True, quanta_per_px=QUANTA_SNR19)
    found = detect_markers(img, 4.0, "bright", roi="none")
    e = match(found, truth)
    assert np.isfinite(e).all() and rms(e) < 0.1
    # pure noise: nothing is a marker
    flat = np.clip(rng.normal(120, 3, (256, 256)), 0, 255).astype(np.uint8)
    assert len(detect_markers(flat, 4.0, "dark", roi="none")) == 0


def test_pixel_noise_and_tophat():
    rng = np.random.default_rng(14)
    ramp = np.add.outer(np.linspace(0, 60, 300), np.linspace(0, 40, 300))
    img = ramp + rng.normal(0, 2.5, ramp.shape)
    assert abs(pixel_noise(img) - 2.5) < 0.1                 # the ramp does not count
    assert structuring_size(2.6) == 7
    t = tophat(img.astype(np.float32), 4.0, "dark")
    assert t.min() >= 0 and np.median(t) < 10                # background removed


def test_field_of_view_cut_by_the_frame():
    """A circular field wider than the frame (cut at top and bottom) with a dark instrument
    biting into it: the circle is found to a pixel."""
    h, w = 512, 1024
    yy, xx = np.mgrid[:h, :w]
    img = np.where((xx - 500.3) ** 2 + (yy - 270.6) ** 2 <= 420.2 ** 2, 120, 3).astype(np.uint8)
    img[100:300, 60:110] = 10
    fov = find_field_of_view(img)
    assert fov.found
    assert abs(fov.centre_px[0] - 500.3) < 1.5 and abs(fov.centre_px[1] - 270.6) < 1.5
    assert abs(fov.radius_px - 420.2) < 1.5
    assert not FieldOfView((h, w)).found and FieldOfView((h, w)).mask().all()
    flat = np.full((200, 200), 100, np.uint8)
    assert not find_field_of_view(flat).found


def test_field_of_view_of_the_twin_both_views():
    """The twin's frames (bsipipe synth, default configuration, one frame per C-arm): a bright
    field nearly as wide as the frame, a black surround, a large mid-grey head and a dark
    indentor rod inside it.  Otsu's threshold split white from grey there and the field was
    not found in cam1; both views' circles are now found within 1 px of the truth."""
    from bsipipe.synth.config import SynthConfig
    from bsipipe.synth.twin import Twin
    tw = Twin(SynthConfig.model_validate({"calibration": {"views": 0, "stereo_views": 0},
                                          "sequence": {"n_frames": 1}}))
    seen = set()
    for rel, img in tw.sequence_frames():
        v = rel.split("/")[1]
        det = tw.arms[v].detector
        fov = find_field_of_view(img)
        print(v, fov.to_dict(), "truth", det.fov_centre_px, det.fov_radius_px)
        assert fov.found, v
        assert np.hypot(fov.centre_px[0] - det.fov_centre_px[0], fov.centre_px[1] - det.fov_centre_px[1]) < 1.0
        assert abs(fov.radius_px - det.fov_radius_px) < 1.0
        seen.add(v)
    assert seen == {"cam1", "cam2"}


def _intensifier_frame(shape, centre, radius, rng, *, head=True, rod=True, bright=240.0, noise=2.0):
    """A field (2 px soft edge, video gamma 1/2) with an elliptical mid-grey region and a
    dark rod entering from the top, on a black surround."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    m = np.clip((radius - np.hypot(xx - centre[0], yy - centre[1])) / 2 + 0.5, 0, 1)
    lev = np.full((h, w), bright)
    if head:
        lev[np.hypot((xx - centre[0] + 20) / 1.6, yy - centre[1] - 70) < 200] = 90
    if rod:
        lev[:int(centre[1]), int(centre[0]) - 10:int(centre[0]) + 20] = 40
    return (np.sqrt(m) * lev + rng.normal(0, noise, (h, w))).clip(0, 255).astype(np.uint8)


def test_field_of_view_cut_by_three_edges():
    """A field cut by the left, right and top edges of the frame, with a large grey head and
    a rod inside it: found within a pixel (the old Otsu threshold did not find it)."""
    rng = np.random.default_rng(3)
    img = _intensifier_frame((900, 800), (401.7, 380.2), 430.5, rng)
    assert img[0, 0] < 10 and img[-1, 400] < 10 and min(img[0, 300], img[400, 0], img[400, -1]) > 100   # 3 edges cut
    fov = find_field_of_view(img)
    assert fov.found
    assert abs(fov.centre_px[0] - 401.7) < 1.0 and abs(fov.centre_px[1] - 380.2) < 1.0
    assert abs(fov.radius_px - 430.5) < 1.0


def test_field_of_view_without_surround():
    """No surround, so no field: noise, a smooth gradient, and a dark round region at the
    border of a frame (its edge is a circle, but the bright rest lies outside it)."""
    rng = np.random.default_rng(4)
    assert not find_field_of_view(rng.normal(100, 10, (512, 512)).clip(0, 255).astype(np.uint8)).found
    yy, xx = np.mgrid[:600, :800]
    assert not find_field_of_view((60 + 0.2 * xx + rng.normal(0, 3, xx.shape)).clip(0, 255).astype(np.uint8)).found
    anatomy = 150 - 60 * np.exp(-((xx - 100) ** 2 + (yy - 300) ** 2) / (2 * 150 ** 2)) + rng.normal(0, 3, xx.shape)
    assert not find_field_of_view(anatomy.clip(0, 255).astype(np.uint8)).found


# --- the real X-ray frame ----------------------------------------------------------------------

def _xray():
    img = read_image(XRAY / "sample_frame.jpg")
    inp = pd.read_csv(XRAY / "sample_frame_input.csv")
    ref = pd.read_csv(XRAY / "sample_autocorrect_output.csv")
    names = [c[:-7] for c in ref.columns if c.endswith("_cam1_X")]
    seeds = np.array([[inp[n + "_cam1_X"][0], inp[n + "_cam1_Y"][0]] for n in names])
    refined = np.array([[ref[n + "_cam1_X"][0], ref[n + "_cam1_Y"][0]] for n in names])
    return img, names, seeds, refined, inp


def reference_kind(seeds: np.ndarray, refined: np.ndarray) -> np.ndarray:
    """What the XMALab-style reference did with each seed, from the CSVs alone.

    The port cuts a 31 x 31 window ``[int(s - 15.5), int(s + 15.5))`` around each seed and
    returns the centre of the minimum enclosing circle of the contour nearest to the seed.
    When its threshold swallows the whole window, that contour is the window's border and
    the "refined" position is exactly the window's centre (``window``); when the seeded bead
    is not segmented, the nearest contour is a neighbouring bead, over 5 px away (``jump``).
    Only the rest (``refined``) are refinements of the seeded bead.
    """
    lo = (seeds - 15.5).astype(int)
    hi = (seeds + 15.5).astype(int)
    centre = (lo + hi - 1) / 2.0
    kind = np.full(len(seeds), "refined", dtype=object)
    kind[np.hypot(*(refined - centre).T) < 1e-6] = "window"
    kind[(kind == "refined") & (np.hypot(*(refined - seeds).T) > 5.0)] = "jump"
    return kind


def test_real_xray_frame_vs_xmalab_refinement():
    """From the rough positions as seeds, our centres are within 0.3 px (median) of the
    XMALab-style refined positions of every marker the reference refines (17 of 24, cam1:
    this frame is camera 1's).  The other 7 are not refinements: 5 times the reference
    returned its search window's centre, 2 times it jumped to a neighbouring bead; there
    our detector finds the seeded bead itself."""
    img, names, seeds, refined, _ = _xray()
    kind = reference_kind(seeds, refined)
    assert sorted(np.array(names)[kind == "window"]) == ["BHa", "BHc", "GHa", "HPa", "LJla"]
    assert sorted(np.array(names)[kind == "jump"]) == ["GHc", "HPc"]
    r = refine_at(img, seeds, 4.0, "dark")
    assert r["found"].all()
    d = np.hypot(r["x_px"] - refined[:, 0], r["y_px"] - refined[:, 1]).to_numpy()
    ok = kind == "refined"
    print(f"median distance to the XMALab-style refinement: {np.median(d[ok]):.3f} px over {ok.sum()} markers "
          f"(max {d[ok].max():.2f}); all 24: {np.median(d):.3f} px")
    assert np.median(d[ok]) <= 0.3
    # where the reference did not refine, ours is still on the seeded bead (a rough click is
    # within ~2.5 px of its bead), with a clear signal
    assert (r["distance_px"][~ok] < 2.6).all()
    assert (r["snr"][~ok] > 10).all()
    assert (d[kind == "jump"] > 10).all()


def test_real_xray_frame_as_the_reference_saw_it():
    """The reference positions were computed on the frame after a DIVX AVI round trip; on
    those same pixels (OpenCV's MPEG-4 encoder, when available) our median distance over the
    refined markers is smaller still."""
    img, names, seeds, refined, _ = _xray()
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        p = str(Path(tmp) / "f.avi")
        bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        wr = cv2.VideoWriter(p, cv2.VideoWriter_fourcc(*"DIVX"), 30, (img.shape[1], img.shape[0]))
        if not wr.isOpened():
            pytest.skip("this OpenCV build cannot write DIVX AVI")
        wr.write(bgr)
        wr.release()
        ok, fr = cv2.VideoCapture(p).read()
    if not ok:
        pytest.skip("this OpenCV build cannot read back DIVX AVI")
    divx = cv2.cvtColor(fr, cv2.COLOR_BGR2GRAY)
    kind = reference_kind(seeds, refined)
    r = refine_at(divx, seeds, 4.0, "dark")
    d = np.hypot(r["x_px"] - refined[:, 0], r["y_px"] - refined[:, 1]).to_numpy()[kind == "refined"]
    print(f"DIVX round trip: median {np.median(d):.3f} px")
    assert np.median(d) <= 0.3


def test_real_xray_frame_is_camera_1_only():
    """The input CSV also has cam2 columns, but this 1024 x 512 frame is one C-arm's circular
    field (camera 1): no bead lies at any cam2 position, every cam1 seed has one."""
    img, names, seeds, refined, inp = _xray()
    s2 = np.array([[inp[n + "_cam2_X"][0], inp[n + "_cam2_Y"][0]] for n in names])
    assert refine_at(img, s2, 4.0, "dark")["found"].sum() == 0
    assert refine_at(img, seeds, 4.0, "dark")["found"].all()
    fov = find_field_of_view(img)
    assert fov.found and 350 < fov.radius_px < 500


def test_real_xray_frame_automatic_detection():
    """Without seeds, the full-frame detector finds the seeded beads among its detections
    (inside the circular field, away from the rod and the lead letter)."""
    img, names, seeds, refined, _ = _xray()
    found = detect_markers(img, 4.0, "dark")
    d, _ = cKDTree(found[["x_px", "y_px"]].to_numpy()).query(seeds)
    assert np.mean(d < 2.6) >= 0.9


# --- real microscopy: trackpy's bulk_water -----------------------------------------------------------

def trackpy_frame29():
    """trackpy 0.7 on frame 29: ``locate(green, 11, invert=True, minmass=20)`` and the same
    frame given as float; live when trackpy is installed, else the stored tables
    (``_make_trackpy_reference.py``)."""
    try:
        import trackpy as tp
    except ImportError:
        return (pd.read_csv(WATER / "trackpy_frame029.csv"), pd.read_csv(WATER / "trackpy_frame029_float.csv"),
                "stored")
    tp.quiet()
    g = read_image(WATER / "bulk_water_029.png", channel=1)
    f = tp.locate(g, 11, invert=True, minmass=20)
    ff = tp.locate((255 - g).astype(float) / 255, 11, minmass=20 / 255)
    return f, ff, f"live (trackpy {tp.__version__})"


#: Detection settings for these frames: spots about 5 px across blurred by ~1 px, so the
#: centroid window is 4 px (trackpy's mask is 5 px for diameter 11); the same 11 px
#: background scale as trackpy's boxcar; a low threshold, like trackpy's minmass 20; no
#: roundness test (out-of-focus features are irregular, unlike a steel bead's shadow).
WATER_SETTINGS = dict(roi="none", k_sigma=2.0, min_snr=0.0, method="centroid", blur_px=1.0, window_radius_px=4.0,
                      structuring_px=11, min_roundness=None)


def test_microscopy_frame29_vs_trackpy():
    """Real microscopy (dark features, diameter 11, green channel) against trackpy's 599
    frame-29 features.

    trackpy's positions of faint, out-of-focus features depend on its own details: given the
    very same frame as float instead of uint8 it reproduces only ~68 % of its features
    within 0.5 px (its background is an integer boxcar on uint8 input, its mask moves in
    whole pixels).  So the comparison is split: on the features trackpy itself places
    reproducibly (within 0.25 px either way) we find every one and >= 95 % within 0.5 px;
    over all 599 we agree with trackpy at least as often as trackpy agrees with itself.
    With the default settings the 0.5 px agreement on all 599 that was asked for is not
    reached (~74 %): the missing ones are faint (median mass ~70 vs 210) and their centre is
    a matter of definition.  In the trackpy parity mode (``method="centroid",
    parity="trackpy"``: trackpy's band pass, maxima and whole-pixel-shifting centroid,
    :func:`bsipipe.imaging.detect.locate_trackpy`) at least 95 % of all 599 agree within
    0.5 px (in fact every one, to rounding).
    """
    f, ff, how = trackpy_frame29()
    F = f[["x", "y"]].to_numpy()
    assert len(F) == 599                      # data/real/README.md's reference
    d_self, _ = cKDTree(ff[["x", "y"]].to_numpy()).query(F)
    stable = d_self < 0.25
    self_agreement = float(np.mean(d_self < 0.5))
    g = read_image(WATER / "bulk_water_029.png", channel=1)
    found = detect_markers(g, 11, "dark", **WATER_SETTINGS)
    d, _ = cKDTree(found[["x_px", "y_px"]].to_numpy()).query(F)
    frac_stable = float(np.mean(d[stable] < 0.5))
    frac_all = float(np.mean(d < 0.5))
    print(f"trackpy {how}: {len(F)} features, {stable.sum()} reproducible; trackpy uint8 vs float agreement "
          f"{self_agreement:.3f}; ours: {len(found)} detections, within 0.5 px: {frac_stable:.3f} of the "
          f"reproducible, {frac_all:.3f} of all; within 3 px: {np.mean(d < 3):.3f} of all")
    assert (d[stable] < 3.0).all()
    assert frac_stable >= 0.95
    assert frac_all >= self_agreement
    # trackpy parity mode: trackpy's own definition of a feature's centre
    par = detect_markers(g, 11, "dark", method="centroid", parity="trackpy", minmass=20)
    d_par, j_par = cKDTree(par[["x_px", "y_px"]].to_numpy()).query(F)
    frac_par = float(np.mean(d_par < 0.5))
    dmass = np.abs(par["mass"].to_numpy()[j_par] - f["mass"].to_numpy()).max()
    print(f"parity mode: {len(par)} features, {frac_par:.3f} of trackpy's within 0.5 px (max distance "
          f"{d_par.max():.2g} px, max mass difference {dmass:.2g})")
    assert frac_par >= 0.95
    assert abs(len(par) - len(F)) <= 0.05 * len(F)


# --- the per-frame fast paths against the plain formulas they replace ----------------------------
#
# detect.py's per-frame path (window_arrays, detect_arrays, _measure) is written for few numpy
# calls; each shortcut must give the values of the straightforward computation.  The references
# below are those computations, written plainly.

def _ref_unclipped(a):
    top = np.iinfo(a.dtype).max
    return cv2.erode(cv2.inRange(a, 1, top - 1), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0


def _ref_immerkaer(a, step):
    r = cv2.filter2D(a.astype(np.float64), cv2.CV_64F, D._IMMERKAER.astype(np.float64),
                     borderType=cv2.BORDER_REPLICATE)[1:-1:step, 1:-1:step]
    return np.rint(r).astype(np.int64)


def _test_images(rng):
    """8/16-bit frames with clipped regions (black and saturated), odd sizes."""
    out = []
    for shape, dtype in (((203, 317), np.uint8), ((64, 64), np.uint8), ((257, 128), np.uint16),
                         ((1024, 1024), np.uint8)):
        top = np.iinfo(dtype).max
        a = rng.normal(0.5 * top, 0.1 * top, shape)
        a[: shape[0] // 5] = 0                                  # a black band
        a[:, -shape[1] // 6:] = top                             # a saturated band
        a[rng.random(shape) < 0.01] = top                       # specks
        out.append(np.clip(a, 0, top).astype(dtype))
    return out


def test_area_reduction_is_opencv_inter_area():
    rng = np.random.default_rng(0)
    for f in (2, 3, 4, 5, 8, 16):
        for shape in ((f * 17, f * 23), (f * 5 + 3, f * 9 + 1), (256, 512)):
            a = rng.integers(0, 256, shape).astype(np.uint8)
            a[: shape[0] // 3] = 255                            # all-saturated blocks: sums at the top
            ref = cv2.resize(a, (shape[1] // f, shape[0] // f), interpolation=cv2.INTER_AREA)
            assert np.array_equal(D._area_reduced(a, f), ref), (f, shape)


def test_grid_pixels_are_the_full_frame_tests_sampled():
    rng = np.random.default_rng(1)
    for a in _test_images(rng):
        for g in (2, 3, 8):
            unc0, unc1, hp = D._grid_pixels(a, g)
            full = _ref_unclipped(a)
            assert np.array_equal(unc0, full[::g, ::g]) and np.array_equal(unc1, full[1:-1:g, 1:-1:g])
            assert hp.dtype == np.int32 and np.array_equal(hp, _ref_immerkaer(a, g))
            assert np.array_equal(hp, D._immerkaer(a, g))


def test_median_is_numpys():
    rng = np.random.default_rng(2)
    for shape in ((1,), (2,), (7,), (7221,), (12, 1), (12, 144), (12, 201), (3, 324), (5, 9)):
        for dtype in (np.float32, np.float64, np.int32):
            v = (rng.normal(size=shape) * 7).astype(dtype)
            for axis in ((None, 0) if len(shape) == 1 else (None, 0, 1)):
                assert np.array_equal(np.asarray(D._median(v, axis), float), np.median(v, axis=axis))


def _ref_neighbour_valid(xy, others, ix, iy, geo):
    reach = geo.radius + 1.0
    px = ix[:, None] + geo.dx[None]
    py = iy[:, None] + geo.dy[None]
    valid = np.ones(px.shape, bool)
    for o in others:
        far = (np.abs(o[0] - xy[:, 0]) >= 0.5) | (np.abs(o[1] - xy[:, 1]) >= 0.5)
        d2_o = (px - o[0]) ** 2 + (py - o[1]) ** 2
        d2_s = (px - xy[:, 0, None]) ** 2 + (py - xy[:, 1, None]) ** 2
        valid &= ~(far[:, None] & (d2_o < d2_s) & (d2_o <= reach * reach))
    return valid


@pytest.mark.parametrize("n", [12, 90])
def test_neighbour_masks_tabulated_and_plain_agree(n):
    """Integer neighbours (a frame's candidates) use a table, others the formula; with many
    points the pairs come from KD-trees, unsorted."""
    rng = np.random.default_rng(3)
    st = D.DetectionSettings()
    geo = D._geo(4.0, st.smooth_px(4.0), st.window_px(4.0))
    pts = np.rint(rng.uniform(0, 60, (n, 2)))
    ix, iy = pts[:, 0].astype(int), pts[:, 1].astype(int)
    for others in (pts, pts + rng.uniform(-0.5, 0.5, pts.shape)):
        got = D._neighbour_valid(pts, others, ix, iy, geo)
        ref = _ref_neighbour_valid(pts, others, ix, iy, geo)
        assert got is not None and np.array_equal(got, ref)


def _ref_dark_objects(img, diameter_px, grow_px=2):
    a = np.asarray(img)
    h, w = a.shape
    f = max(1, int(diameter_px))
    small = cv2.resize(a, (max(w // f, 1), max(h // f, 1)), interpolation=cv2.INTER_AREA)
    k = max(3, int(round(16 * diameter_px / f)) | 1)
    bg = cv2.morphologyEx(small, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)),
                          borderType=cv2.BORDER_REPLICATE)
    dark = ((2 * small.astype(np.int32) < bg) & (bg > 0)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] * f * f > math.pi * (2 * diameter_px) ** 2
    keep[0] = False
    return keep[lab] if keep.any() else None


def test_dark_objects_as_plainly_computed():
    rng = np.random.default_rng(4)
    for d in (4.0, 5.0, 8.0):
        img = rng.normal(180, 4, (512, 640))
        img[100:300, 200:230] = 60                              # an instrument
        img[400:404, 500:504] = 50                              # a bead: too small to count
        for x, y in rng.uniform(20, 480, (30, 2)):              # dark specks
            img[int(y):int(y) + 3, int(x):int(x) + 3] = 70
        img = np.clip(img, 0, 255).astype(np.uint8)
        got, ref = D._DarkObjects.find(img, d), _ref_dark_objects(img, d)
        assert (got is None) == (ref is None)
        if ref is not None:
            assert np.array_equal(got.small, ref)
    assert D._DarkObjects.find(np.full((200, 200), 90, np.uint8), 4.0) is None


def _ref_centroid(s, geo, n_iter):
    sp = np.maximum(s[:, geo.support], 0.0)
    X, Y = geo.dx[geo.support][None], geo.dy[geo.support][None]
    cx, cy = np.zeros(len(s)), np.zeros(len(s))
    for _ in range(n_iter + 1):
        ddx, ddy = X - cx[:, None], Y - cy[:, None]
        w = sp * np.clip(geo.radius + 1.0 - np.sqrt(ddx * ddx + ddy * ddy), 0.0, 1.0)
        m = w.sum(axis=1)
        mm = np.where(m > 0, m, 1.0)
        nx = np.where(m > 0, cx + (w * ddx).sum(axis=1) / mm, cx)
        ny = np.where(m > 0, cy + (w * ddy).sum(axis=1) / mm, cy)
        cx, cy = np.clip(nx, -1.5, 1.5), np.clip(ny, -1.5, 1.5)
    return np.column_stack([cx, cy]), m


def _ref_gaussian_fit(s, geo, start, sigma0, valid, n_iter=5):
    """The batched Levenberg-Marquardt fit, written plainly."""
    reach = geo.radius + 1.0 + np.hypot(start[:, 0], start[:, 1]).max()
    sup = geo.support[geo.support_r <= reach + 1e-9]
    X, Y = geo.dx[sup][None], geo.dy[sup][None]
    S = s[:, sup]
    dist = np.hypot(X - start[:, 0, None], Y - start[:, 1, None])
    win = (dist <= geo.radius + 1.0) * (1.0 if valid is None else valid[:, sup])
    P = np.column_stack([start, np.full(len(S), sigma0), np.maximum((S * (dist <= 1.0)).max(axis=1), 1e-6),
                         np.zeros(len(S))])
    lam = np.full(len(S), 1e-3)

    def model(P):
        ex, ey = X - P[:, 0:1], Y - P[:, 1:2]
        g = np.exp(-(ex ** 2 + ey ** 2) / (2 * P[:, 2:3] ** 2))
        return g, ex, ey, P[:, 3:4] * g + P[:, 4:5]

    g, ex, ey, m = model(P)
    cost = (win * (m - S) ** 2).sum(axis=1)
    for _ in range(n_iter):
        a = P[:, 3:4] * g / P[:, 2:3] ** 2
        J = np.stack([a * ex, a * ey, a * (ex ** 2 + ey ** 2) / P[:, 2:3], g, np.ones_like(g)], axis=1)
        H = (J * win[:, None]) @ J.transpose(0, 2, 1)
        H = H + lam[:, None, None] * (H + 1e-12) * np.eye(5)
        step = np.linalg.solve(H, ((J * win[:, None]) @ (S - m)[..., None]))[..., 0]
        cand = P + step
        cand[:, 2] = np.clip(cand[:, 2], 0.3, geo.half)
        g1, ex1, ey1, m1 = model(cand)
        c1 = (win * (m1 - S) ** 2).sum(axis=1)
        b = c1 < cost
        P = np.where(b[:, None], cand, P)
        g, ex, ey, m = (np.where(b[:, None], u, v) for u, v in ((g1, g), (ex1, ex), (ey1, ey), (m1, m)))
        cost = np.where(b, c1, cost)
        lam = np.where(b, lam * 0.3, lam * 10.0)
        if ((np.abs(step[:, :2]).max(axis=1) < 1e-3) | ~b).all() and (lam < 1e3).all():
            break
    return P


def test_patch_measurement_as_plainly_computed():
    """Plane, centroid and Gaussian fit of real X-ray beads (twin-like synthetic frame, touching
    neighbours included) against the plain formulas: to rounding."""
    rng = np.random.default_rng(6)
    centres = np.array([[60.3, 60.8], [66.1, 61.2], [120.4, 90.6], [40.2, 130.7], [150.5, 150.5], [100.0, 40.0]])
    img = render_beads(centres, 4.0, 192, rng)
    st = D.DetectionSettings()
    blur, radius = st.smooth_px(4.0), st.window_px(4.0)
    geo = D._geo(4.0, blur, radius)
    pts = np.rint(centres)
    ix, iy = pts[:, 0].astype(int), pts[:, 1].astype(int)
    valid = D._neighbour_valid(pts, pts, ix, iy, geo)
    assert valid is not None and not valid.all()                 # the touching pair masks each other
    s = D._plane_removed(D._gather(img, ix, iy, geo.half), geo, 1.0, valid)
    sv = s * valid
    c, m, _ = D._centroid(sv, geo, 3)
    c_ref, m_ref = _ref_centroid(sv, geo, 3)
    np.testing.assert_allclose(c, c_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(m, m_ref, rtol=1e-12)
    sig0 = math.hypot(1.0, blur)
    xy, amp, sig, ok = D._gaussian_fit(s, geo, c, sig0, valid)
    P = _ref_gaussian_fit(s, geo, c, sig0, valid)
    assert ok.all()
    np.testing.assert_allclose(xy, P[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(sig, P[:, 2], rtol=1e-9)
    np.testing.assert_allclose(amp, P[:, 3], rtol=1e-9)
    # and the centres are the beads'
    assert np.abs(pts + xy - centres).max() < 0.15


def test_peak_tests_agree():
    """A maximum is a pixel no lower than any in the disk of side max(3, d) around it, the edge
    replicated: the per-pixel test on the pixels above a threshold (:func:`_peaks_at`, with its
    four-neighbour pre-test; detect_arrays) and one dilation (window_arrays) find the same."""
    rng = np.random.default_rng(7)
    ts = cv2.GaussianBlur(rng.normal(0, 1, (120, 333)).astype(np.float32), (0, 0), 1.2)
    ts[50:52, 80:83] = ts.max() + 1                             # a plateau
    ts[0, 5] = ts[119, 332] = ts.max() + 2                      # maxima at the edge
    st = D.DetectionSettings(min_area_px=0, max_area_factor=100.0)
    for d in (2.6, 4.0, 7.0):
        k = max(3, int(round(d)) | 1)
        thr = float(np.percentile(ts, 80))
        ys, xs = np.nonzero(ts > thr)
        px, py, _ = D._peaks_at(ts, xs, ys, d, 0.0, st)
        peak = (ts >= cv2.dilate(ts, D._ellipse(k), borderType=cv2.BORDER_REPLICATE)) & (ts > thr)
        qy, qx = np.nonzero(peak)
        qx, qy, _ = D._peak_areas(ts, qx, qy, d, 0.0, st)
        assert np.array_equal(px, qx) and np.array_equal(py, qy)
        assert len(px) > 5


def test_window_candidates_do_not_depend_on_the_other_windows():
    """Seeded tracking searches every marker's window in one strip; a window's candidates
    must be what the window alone gives.  Here a faint bead's window ends on a dark rod (an
    instrument's edge).  When the windows were laid side by side at their own width, the
    window beside another one saw the rod as a valley between bright pixels across the seam
    while the window alone saw a replicated edge: the bead was found in 2 of these 12 frames
    beside the other window and in 8 alone.  Each window is now cut wider by the reach of
    the top-hat and the smoothing, so both see the frame's own top-hat there."""
    size = 128
    bead = np.array([[40.3, 63.6]])
    clean = render_beads(bead, 3.0, size, None, field=RayField(bead_camera(size)), noise=False, quantize=False)
    clean[:, 53:58] *= 0.4                              # the rod along the window's right edge
    rng = np.random.default_rng(3)
    found = {1: 0, 2: 0}
    for _ in range(12):
        f = np.clip(np.rint(clean + rng.normal(0, 7.0, clean.shape)), 0, 255).astype(np.uint8)
        alone = D.window_arrays(f, bead, 5.0, 4.0, "dark")
        both = D.window_arrays(f, np.vstack([bead, [[90.0, 64.0]]]), 5.0, 4.0, "dark")
        a = np.column_stack([alone["x_px"], alone["y_px"]])
        b = np.column_stack([both["x_px"], both["y_px"]])
        b = b[np.hypot(b[:, 0] - bead[0, 0], b[:, 1] - bead[0, 1]) <= 6.5]   # window 1's (radius + 1.5)
        assert len(a) == len(b)
        if len(a):
            # the same candidates; the batched Gaussian fit may iterate once more for a patch
            assert np.abs(np.sort(a, axis=0) - np.sort(b, axis=0)).max() < 0.02
        found[1] += int((np.hypot(*(a - bead[0]).T) < 1).any())
        found[2] += int((np.hypot(*(b - bead[0]).T) < 1).any())
    print(f"bead found in {found[1]} of 12 frames with its window alone, {found[2]} beside another window")
    assert found[1] == found[2] >= 4


def test_detect_arrays_skip_leaves_the_other_markers_as_they_were():
    """``skip`` (a tracker's sweep for new markers) drops the candidates inside the given
    circles before they are measured; every other marker comes out bit for bit as without
    ``skip`` (the skipped ones are still masked out of their neighbours' fits)."""
    size = 256
    rng = np.random.default_rng(5)
    pts = bead_grid(4, size, rng)
    pts[1] = pts[0] + [5.0, 0.5]                   # a close pair: each masked from the other's fit
    img = render_beads(pts, 4.0, size, rng)
    full = D.detect_arrays(img, 4.0, "dark", "none")
    xy = np.column_stack([full["x_px"], full["y_px"]])
    assert len(xy) == len(pts)
    near = [int(np.argmin(np.hypot(*(xy - p).T))) for p in (pts[0], pts[-1])]
    held = xy[near]                                # one of the close pair, one far from it
    part = D.detect_arrays(img, 4.0, "dark", "none", skip=(held, np.full(2, 2.0)))
    pxy = np.column_stack([part["x_px"], part["y_px"]])
    assert len(pxy) == len(xy) - 2
    keep = ~(((xy[:, None, :] - held[None, :, :]) ** 2).sum(-1) <= 4.0).any(axis=1)
    for c in D.COLUMNS:
        np.testing.assert_array_equal(part[c], full[c][keep])


def test_a_blob_far_wider_than_the_marker_is_not_taken_for_one():
    """``max_sigma_factor`` (0.75 d): a dark Gaussian smudge of sigma 3.5 px (what a video
    codec leaves of a faint bead, or a corner of bone) beside a 4 px bead is not reported as a
    marker; the bead is.  (Six tracking twins written to mp4v: the visible positions found
    within 1 px rose from 91.5 % to 93.3 % with this limit, their PNG frames' 99.44 % unchanged.)"""
    size = 160
    rng = np.random.default_rng(2)
    img = render_beads(np.array([[50.3, 80.6]]), 4.0, size, rng).astype(float)
    yy, xx = np.mgrid[:size, :size]
    img -= 14.0 * np.exp(-((xx - 110.0) ** 2 + (yy - 78.0) ** 2) / (2 * 3.5 ** 2))
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    got = D.detect_arrays(img, 4.0, "dark", "none")
    assert len(got["x_px"]) == 1 and abs(got["x_px"][0] - 50.3) < 0.3
    loose = D.detect_arrays(img, 4.0, "dark", "none", D.DetectionSettings(max_sigma_factor=None))
    wide = np.hypot(loose["x_px"] - 110.0, loose["y_px"] - 78.0) < 1.5
    assert wide.sum() == 1 and loose["sigma_px"][wide][0] > 3.0


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_constant_fill_region_is_left_out_of_the_noise_statistics(dtype):
    """Two thirds of the frame a constant grey that is neither black nor saturated (a blanked
    region, a saturated one mapped to a grey by post-processing, as an automatic brightness
    control applied to recorded frames does), the rest noisy with eight beads.  The fill has
    no noise to measure: counted as background it sets the threshold near zero and the noise
    of the rest and its structure pass for markers (20 detections); left out, the eight beads
    are found, nothing else, as in the noisy part alone."""
    rng = np.random.default_rng(4)
    h, w = 240, 360
    beads = np.array([[260.3, 40.2], [300.7, 80.5], [250.1, 120.9], [330.4, 150.2], [280.8, 190.6],
                      [320.2, 215.3], [262.6, 170.1], [305.5, 30.7]])
    yy, xx = np.mgrid[:h, :w].astype(float)
    scale = 1 if dtype == np.uint8 else 64
    # background: smooth structure (sd 8 grey levels over ~8 px, as anatomy) and pixel noise
    s = cv2.GaussianBlur(rng.normal(0, 1, (h, w)), (0, 0), 8.0)
    img = 150.0 + 8.0 * s / s.std()
    for x, y in beads:
        img -= 25 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2 ** 2))
    img = (img + rng.normal(0, 2.0, img.shape)) * scale
    img[:, :240] = 60 * scale
    img = np.clip(np.rint(img), 0, np.iinfo(dtype).max).astype(dtype)
    found = detect_markers(img, 4.0, "dark", roi="none")
    xy = found[["x_px", "y_px"]].to_numpy()
    d = cKDTree(beads).query(xy)[0] if len(xy) else np.zeros(0)
    near = cKDTree(xy).query(beads)[0]
    # the noisy part alone (no fill): what the detector finds there, fill or not
    alone = detect_markers(img[:, 240:], 4.0, "dark", roi="none")
    print(f"{np.dtype(dtype).name}: {len(found)} detections ({len(alone)} in the noisy part alone), "
          f"{int((near < 0.5).sum())} of 8 beads within 0.5 px")
    assert (near < 0.5).all()
    assert len(found) == len(alone) == 8
    np.testing.assert_allclose(np.sort(alone["x_px"].to_numpy() + 240), np.sort(found["x_px"].to_numpy()), atol=1e-3)


def _edge_scene(kind: str, c, size: int = 64, angle_deg: float = 20.0, off_px: float = 2.0) -> np.ndarray:
    """The transmission behind a bead centred at ``c``: ``step``, a bone's edge (30 % less
    light beyond it, over about 2 px) or ``line``, a dark line 1.2 px sd wide (25 %), running
    at ``angle_deg`` ``off_px`` from the bead's centre; ``flat``: nothing."""
    yy, xx = np.mgrid[:size, :size].astype(float)
    a = math.radians(angle_deg)
    u = (xx - c[0]) * -math.sin(a) + (yy - c[1]) * math.cos(a) - off_px
    if kind == "step":
        return 1 - 0.3 * (0.5 + 0.5 * np.tanh(u))
    if kind == "line":
        return 1 - 0.25 * np.exp(-u ** 2 / (2 * 1.2 ** 2))
    return np.ones_like(xx)


def test_edge_background_as_plainly_computed():
    """The edge background's knots (normal equations summed pixel by pixel) against a plain
    dense least-squares fit of the same piecewise-linear profile, on a bead beside a bone's
    edge: to rounding; the F test takes it there and not on a flat background."""
    rng = np.random.default_rng(3)
    st = D.DetectionSettings()
    blur, radius = st.smooth_px(8.0), st.window_px(8.0)
    geo = D._geo(8.0, blur, radius)
    c = np.array([32.2, 31.7])
    pts = np.array([[32, 32]])
    raw = {k: D._gather(render_beads(c[None], 8.0, 64, rng, background=_edge_scene(k, c)), pts[:, 0], pts[:, 1],
                        geo.half) for k in ("step", "flat")}
    bg, chosen = D._edge_background(raw["step"], geo, None)
    assert chosen.all()
    _, chosen_flat = D._edge_background(raw["flat"], geo, None)
    assert not chosen_flat.any()
    # the plain formula: the direction from the ring's gradients, dense hat functions, the
    # penalised normal equations
    p = raw["step"][0]
    P = 2 * geo.half + 1
    gi, K, nk, pen = D._edge_geo(geo.key)[:4]
    g = p.reshape(P, P)
    ys, xs = np.divmod(gi, P)
    gx, gy = g[ys, xs + 1] - g[ys, xs - 1], g[ys + 1, xs] - g[ys - 1, xs]
    J = np.array([[gx @ gx, gx @ gy], [gx @ gy, gy @ gy]])
    n = np.linalg.eigh(J)[1][:, -1]
    u = (geo.dx * n[0] + geo.dy * n[1]) / D._EDGE_KNOT_PX
    H = np.maximum(0.0, 1.0 - np.abs(u[:, None] - (np.arange(nk) - K)[None, :]))
    ring = geo.ring_idx

    def solve(sel):
        Hr = H[sel]
        return H @ np.linalg.solve(Hr.T @ Hr + pen, Hr.T @ p[sel])

    np.testing.assert_allclose(bg[0], solve(ring), rtol=0, atol=1e-8)


@pytest.mark.parametrize("kind", ["step", "line"])
def test_marker_on_an_edge_is_not_pulled_off_by_it(kind):
    """A 1 mm reference bead (8 px) seated beside a bone's edge or a dark line 2 px from its
    centre, through the twin's detector chain (100 noise draws, sub-pixel positions, rough
    seeds): with the plane under it the centre is pulled across the edge; with the edge
    background (the default) the bias falls to less than half (step 0.23 -> 0.05 px, line 0.18 ->
    0.07 px) and the error RMS by more than a tenth.
    On a flat background the two give the same centres (the F test never takes the edge)."""
    rng = np.random.default_rng(11)
    err = {m: [] for m in ("plane", "edge")}
    flat_same = []
    for _ in range(100):
        c = np.array([32.0, 32.0]) + rng.uniform(-0.5, 0.5, 2)
        seed = c[None] + rng.normal(0, 0.3, 2)
        img = render_beads(c[None], 8.0, 64, rng, background=_edge_scene(kind, c))
        for m in err:
            r = D.refine_at(img, seed, 8.0, settings=D.DetectionSettings(background=m))
            err[m].append([r.x_px[0] - c[0], r.y_px[0] - c[1]])
        flat = render_beads(c[None], 8.0, 64, rng)
        a, b = (D.refine_at(flat, seed, 8.0, settings=D.DetectionSettings(background=m)) for m in ("plane", "edge"))
        flat_same.append(a.x_px[0] == b.x_px[0] and a.y_px[0] == b.y_px[0])
    bias = {m: float(np.hypot(*np.mean(e, axis=0))) for m, e in err.items()}
    rms = {m: float(np.sqrt(np.mean(np.sum(np.square(e), axis=1)))) for m, e in err.items()}
    print(f"{kind}: bias plane {bias['plane']:.3f} px, edge {bias['edge']:.3f} px; "
          f"RMS plane {rms['plane']:.3f} px, edge {rms['edge']:.3f} px")
    assert np.isfinite(np.array(err["edge"])).all()
    assert bias["plane"] > 0.15 and bias["edge"] < bias["plane"] / 2 and rms["edge"] < 0.9 * rms["plane"]
    assert all(flat_same)


def test_snr_of_blurred_noise_is_measured_against_the_noise_it_has():
    """Noise the imaging chain has blurred (sigma 1 px: an intensifier's unsharpness) moves
    Immerkaer's high-pass, the pixel-noise estimate, to a tenth of the noise: the blobs of a
    frame of blurred noise alone came out at SNR 29-38, as strong as markers.  The noise
    measured at twice the pixel size too (the larger counts) gives them SNR under 10, and
    leaves white noise's estimate where it was."""
    from bsipipe.imaging.detect import _coarse_noise, pixel_noise
    rng = np.random.default_rng(1)
    white = 120 + rng.normal(0, 6, (512, 512))
    blurred = np.clip(cv2.GaussianBlur(white, (0, 0), 1.0), 0, 255).astype(np.uint8)
    true_sd = float(np.std(cv2.GaussianBlur(white, (0, 0), 1.0)[20:-20, 20:-20]))
    assert pixel_noise(blurred) < 0.15 * true_sd < 0.6 * true_sd < _coarse_noise(blurred, 1) < 1.2 * true_sd
    d = detect_markers(blurred, 4.0, "dark")
    assert len(d) == 0 or d["snr"].max() < 10, d["snr"].tolist()
    w8 = np.clip(white, 0, 255).astype(np.uint8)
    assert _coarse_noise(w8, 1) == pytest.approx(pixel_noise(w8), rel=0.03)


def _rim_frame(rng, centre=(200.0, 200.0), radius=150.0, beads=(), sigma=1.8, depth=50.0, noise=1.5):
    """A field of level 180 inside a circle (edge blurred, sigma 1 px) on a black (3) surround,
    with dark Gaussian beads ``(x, y)``."""
    yy, xx = np.mgrid[:400, :400].astype(float)
    m = (np.hypot(xx - centre[0], yy - centre[1]) <= radius).astype(np.float32)
    m = cv2.GaussianBlur(m, (0, 0), 1.0)
    img = 180.0 * m + 3.0 * (1 - m)
    for x, y in beads:
        img -= depth * m * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma ** 2))
    return (img + rng.normal(0, noise, img.shape)).clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize("gap_px", [3.0, 5.0])
def test_a_marker_near_the_fields_rim_is_measured_on_the_field_only(gap_px):
    """A 1 mm reference bead (sigma 1.8 px) whose centre lies 3-5 px inside the intensifier
    field's edge: the black surround had entered its background plane and its fit, and pulled
    the centre towards the rim (the track probe's off-centre field: 0.63 px RMS against a
    stated 0.08, the registration reference 0.12-0.23 mm off in 3-D).  The pixels within
    FIELD_RIM_PX of the field's edge and beyond it are left out: bias under 0.15 px, and a bead
    far from the rim measured as before (within 0.005 px: the fits of a batch stop together, at
    steps under 1e-3 px)."""
    rng = np.random.default_rng(11)
    xs = []
    for _ in range(12):
        x0 = 200.0 + 150.0 - gap_px + rng.uniform(-0.5, 0.5)
        y0 = 200.0 + rng.uniform(-0.5, 0.5)
        far = (150.3, 180.6)
        img = _rim_frame(rng, beads=[(x0, y0), far])
        fov = find_field_of_view(img)
        assert fov.found and abs(fov.radius_px - 150.0) < 1.0
        c = D.window_arrays(img, [[x0, y0], far], 6.0, 4.0, "dark", fov=fov)
        got = np.column_stack([c["x_px"], c["y_px"]])
        d, i = cKDTree(got).query([[x0, y0], far])
        assert (d < 1.0).all(), d
        xs.append(got[i[0]] - [x0, y0])
        # far from the rim nothing changes: the same centre as without the field
        c0 = D.window_arrays(img, [far], 6.0, 4.0, "dark")
        assert np.hypot(*(got[i[1]] - [c0["x_px"][0], c0["y_px"][0]])) < 0.005
    bias = np.mean(xs, axis=0)
    print(f"gap {gap_px} px: bias ({bias[0]:+.3f}, {bias[1]:+.3f}) px, RMS {np.sqrt(np.mean(np.square(xs))):.3f}")
    assert np.hypot(*bias) < 0.15


@pytest.mark.parametrize("a", [0.0, 0.3, 0.6])
def test_temporal_noise_correlation_of_frames_averaged_over_time(a):
    """Frames a C-arm averaged recursively, y_t = (1 - a) x_t + a y_{t-1} (intensifier lag, a
    fluoroscopy noise filter), over a static textured scene whose gain flickers by 10 %: the
    noise's lag-1 correlation is a, measured within 0.03 from three frames (the scene and the
    gain changes cancel in the row-high-passed differences)."""
    rng = np.random.default_rng(int(10 * a) + 1)
    yy, xx = np.mgrid[:300, :300].astype(float)
    scene = 120 + 30 * np.sin(xx / 7.0) * np.cos(yy / 11.0) + 20 * (xx > 150)
    y = None
    frames = []
    for _ in range(8):
        x = scene * rng.uniform(0.9, 1.1) + rng.normal(0, 3.0, scene.shape)
        y = x if y is None else (1 - a) * x + a * y
        frames.append(y.astype(np.float32))
    rho = D.temporal_noise_correlation(*frames[-3:])
    print(f"a {a}: rho {rho:.3f}")
    assert rho == pytest.approx(a, abs=0.03)
    assert D.temporal_noise_correlation(frames[-1], frames[-1], frames[-1]) is None
