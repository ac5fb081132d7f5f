"""The C-arm twin: camera model, X-ray image formation, scene truth, writers and the CLI.

Every check compares against a value known independently of the code under test
(cv2.projectPoints, the chord-length law, the projection of the 3-D truth, json/csv
parsers), with a tolerance taken from floating point or from the physics stated beside it.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.imaging.camera import Camera, LocalDistortion, SDistortion, look_at
from bsipipe.io.slicer import format_fcsv, format_mrk_json
from bsipipe.synth.config import SynthConfig
from bsipipe.synth.twin import Twin, build_carms, indentation_displacement
from bsipipe.synth.xray import (Detector, RodShadow, apply_patch, cylinder_chord_mm,
                                ellipsoid_chord_mm, sphere_chord_mm, sphere_patch)

ALL_DISTORTIONS = {"distortion": {"pincushion_edge_px": 15.0, "tangential_edge_px": 2.0,
                                  "s_distortion_deg": 1.0, "local_rms_px": 1.5}}


def _cfg(**over) -> SynthConfig:
    return SynthConfig.model_validate(over)


@pytest.fixture(scope="module")
def carm_all():
    """A 1024 px C-arm with every distortion switched on."""
    return build_carms(_cfg(**ALL_DISTORTIONS))["cam1"]


def _world_at_pixel(cam: Camera, u, depth_mm: float) -> np.ndarray:
    xy = cam.pixels_to_normalized(np.asarray(u, float))[0]
    return cam.R.T @ (np.array([xy[0], xy[1], 1.0]) * depth_mm - cam.t)


# --- camera model ------------------------------------------------------------------------------

@pytest.mark.parametrize("n_coef", [4, 5, 8, 12])
def test_projection_equals_cv2_projectpoints(n_coef):
    rng = np.random.default_rng(n_coef)
    R, t = look_at([-640.0, 10.0, 5.0], [0.0, 0.0, 0.0])
    K = np.array([[3357.0, 0, 515.2], [0, 3361.5, 508.7], [0, 0, 1]])
    d = np.array([1.2, 0.5, 0.004, -0.003, 2.0, 0.1, 0.05, 0.02, 0.001, -0.002, 0.003, 0.001])[:n_coef]
    cam = Camera(K, d, R, t, (1024, 1024))
    X = rng.uniform(-90, 90, (400, 3))
    ref = cv2.projectPoints(X, cam.rvec, cam.t, K, d)[0].reshape(-1, 2)
    assert np.abs(cam.project(X) - ref).max() < 1e-9
    assert np.abs(cam.project_opencv(X) - ref).max() < 1e-9
    # and its inverse equals cv2.undistortPoints run to convergence
    und = cv2.undistortPoints(ref.reshape(-1, 1, 2), K, d, P=K,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)).reshape(-1, 2)
    assert np.abs(cam.undistort_pixels(ref) - und).max() < 1e-9


def test_distort_undistort_round_trip_all_distortions(carm_all):
    cam = carm_all.camera
    assert cam.s_distortion is not None and cam.local_distortion is not None
    rng = np.random.default_rng(0)
    u = rng.uniform(0, 1023, (20000, 2))
    ideal = cam.undistort_pixels(u)
    assert np.abs(cam.distort_pixels(ideal) - u).max() < 1e-6
    assert np.abs(cam.undistort_pixels(cam.distort_pixels(ideal)) - ideal).max() < 1e-6
    # world -> pixel -> ray -> the same world point at its depth
    X = rng.uniform(-60, 60, (500, 3))
    Xc = cam.to_camera(X)
    rays = cam.rays(cam.project(X))
    assert np.abs(rays * Xc[:, 2:3] - Xc).max() < 1e-9


def test_camera_serialisation_round_trip(carm_all):
    cam = carm_all.camera
    back = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    X = np.random.default_rng(1).uniform(-50, 50, (100, 3))
    assert np.abs(back.project(X) - cam.project(X)).max() < 1e-9


def test_s_distortion_is_a_rotation_growing_with_radius():
    sd = SDistortion(np.deg2rad(1.0), 500.0, (512.0, 512.0))
    u = np.array([[1012.0, 512.0], [762.0, 512.0], [512.0, 512.0]])
    v = sd.apply(u) - 512.0
    r = np.hypot(*(u - 512.0).T)
    assert np.allclose(np.hypot(*v.T), r)                                # radius kept
    ang = np.arctan2(v[:2, 1], v[:2, 0])
    assert np.allclose(ang, np.deg2rad(1.0) * (r[:2] / 500.0) ** 2)     # theta = s (r/r_ref)^2


def test_local_distortion_amplitude_and_smoothness():
    rng = np.random.default_rng(3)
    ld = LocalDistortion.random(rng, (1024, 1024), 1.5, 8, 3, (512, 512), 500)
    g = np.stack(np.meshgrid(np.linspace(12, 1012, 60), np.linspace(12, 1012, 60)), -1).reshape(-1, 2)
    g = g[np.hypot(*(g - 512).T) <= 500]
    d = ld.displacement(g)
    assert np.sqrt(np.mean(np.sum(d ** 2, axis=1))) == pytest.approx(1.5, rel=0.05)   # 64x64 vs 60x60 grid
    # wavelengths >= 1024/3 px: the field changes by at most 2 pi A / lambda per pixel
    assert np.abs(np.diff(ld.displacement(np.column_stack([np.arange(1024.0), np.full(1024, 300.0)])), axis=0)).max() < 0.2


def test_distortion_map_truth(carm_all):
    cam, arm = carm_all.camera, carm_all
    m = cam.distortion_map(32.0, arm.fov_centre_px, arm.fov_radius_px)
    assert np.abs(cam.distort_pixels(m.undist_px) - m.raw_px).max() < 1e-6
    r = np.hypot(*(m.raw_px - np.asarray(arm.fov_centre_px)).T)
    edge = r > 0.9 * arm.fov_radius_px
    # pincushion sized to move the field edge by ~15 px (seeded +-15 %), plus S and local
    assert 10 < np.abs(np.hypot(*m.displacement_px[edge].T)).max() < 30


# --- rays and chords ---------------------------------------------------------------------------

def test_rayfield_matches_exact_inverse(carm_all):
    f, cam = carm_all.field, carm_all.camera
    rng = np.random.default_rng(5)
    for _ in range(10):
        x0, y0 = (int(v) for v in rng.integers(0, 1000, 2))
        b = f.block(x0, y0, 12, 9, 4)
        off = (np.arange(4) + 0.5) / 4 - 0.5
        gx, gy = np.meshgrid((np.arange(x0, x0 + 12)[:, None] + off).ravel(), (np.arange(y0, y0 + 9)[:, None] + off).ravel())
        exact = cam.pixels_to_normalized(np.stack([gx.ravel(), gy.ravel()], -1)).reshape(b.shape)
        assert np.abs(b - exact).max() * cam.fx < 1e-5       # in pixels


def test_chords_against_geometry():
    # rays along the optical axis through objects centred on it: chords are diameters
    xy = np.zeros((1, 2))
    assert sphere_chord_mm(xy, [0, 0, 600.0], 0.5)[0] == pytest.approx(1.0)
    assert ellipsoid_chord_mm(xy, [0, 0, 600.0], np.eye(3), [3.0, 4.0, 5.0])[0] == pytest.approx(10.0)
    # a rod lying across the beam: chord = diameter; along the beam: its length
    assert cylinder_chord_mm(xy, [0, -50, 600.0], [0, 1.0, 0], 2.5, 100.0)[0] == pytest.approx(5.0)
    assert cylinder_chord_mm(xy, [0, 0, 550.0], [0, 0, 1.0], 2.5, 80.0)[0] == pytest.approx(80.0)
    # off-axis ray at normalised x: distance from the sphere centre is 600 x / sqrt(1 + x^2)
    x = 0.0003
    D = 600 * x / np.sqrt(1 + x * x)
    assert sphere_chord_mm(np.array([[x, 0.0]]), [0, 0, 600.0], 0.5)[0] == pytest.approx(2 * np.sqrt(0.25 - D * D), rel=1e-12)
    # the sliding rod equals the direct chord at every shift
    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.02, 0.02, (2000, 2))
    tip0, axis = np.array([1.0, -3.0, 640.0]), np.array([0.05, -1.0, 0.02])
    axis /= np.linalg.norm(axis)
    rod = RodShadow(xy, tip0, axis, 2.5, 200.0)
    for shift in (0.0, -2.4, -5.3):
        assert np.abs(rod.chord(shift) - cylinder_chord_mm(xy, tip0 + shift * axis, axis, 2.5, 200.0)).max() < 1e-9


# --- X-ray image formation ---------------------------------------------------------------------

def _plain_detector(arm, blur=0.7) -> Detector:
    return Detector(arm.camera.image_size, arm.fov_centre_px, arm.fov_radius_px, heel_gradient=0.0, vignetting=0.0,
                    veiling_glare=0.0, blur_sigma_px=blur, noise=False, gamma=1.0)


@pytest.mark.parametrize("diameter_mm", [0.5, 1.0])
def test_bead_centroid_at_projected_centre(carm_all, diameter_mm):
    """Noise-free, every distortion on, beads anywhere out to 0.9 of the field radius: the
    intensity-weighted centroid is within 0.05 px of the projected centre. (What is left,
    up to ~0.025 px for a 2.6 px bead, is the pixel-locking of centroids of sampled spots.)"""
    arm, cam = carm_all, carm_all.camera
    det = _plain_detector(arm)
    rng = np.random.default_rng(int(diameter_mm * 10))
    for _ in range(12):
        ang, rr = rng.uniform(0, 2 * np.pi), rng.uniform(0, 0.9) * arm.fov_radius_px
        u = np.asarray(arm.fov_centre_px) + rr * np.array([np.cos(ang), np.sin(ang)])
        X = _world_at_pixel(cam, u, rng.uniform(560, 720))
        T = np.ones((1024, 1024), np.float32)
        apply_patch(T, sphere_patch(arm.field, X, diameter_mm / 2, 1.5, 4))
        img, _ = det.expose(T, None, reference=1.0, quantize=False)
        c0 = cam.project(X)[0]
        x0, y0 = int(c0[0]) - 8, int(c0[1]) - 8
        w = 1.0 - img[y0:y0 + 17, x0:x0 + 17] / (det.level * 255)
        gy, gx = np.mgrid[y0:y0 + 17, x0:x0 + 17]
        c = np.array([(w * gx).sum(), (w * gy).sum()]) / w.sum()
        assert np.linalg.norm(c - c0) < 0.05


def test_bead_contrast_follows_chord_length_law():
    """A 3 mm bead (8 px radius), no blur: each pixel holds the pixel mean of exp(-mu L),
    L the exact chord of each ray through the sphere. Reference: 32 x 32 rays per pixel
    from the camera's exact inverse; the patch's 8 x 8 midpoint rule differs from it by
    (p/8)^2/24 * |lap f|/f, below 1e-3 relative for these pixels."""
    arm = build_carms(_cfg(**ALL_DISTORTIONS))["cam1"]
    cam = arm.camera
    rng = np.random.default_rng(9)
    for mu in (0.5, 1.5):
        X = _world_at_pixel(cam, [730.3, 298.6], 640.0)
        p = sphere_patch(arm.field, X, 1.5, mu, 8)
        h, w = p.transmission.shape
        c = cam.to_camera(X)[0]
        L0 = sphere_chord_mm(arm.field.block(p.x0, p.y0, w, h, 1), c, 1.5)
        iy, ix = np.nonzero(L0 > 2 * 1.5 * np.sqrt(1 - 0.8 ** 2))
        assert len(iy) > 100
        off = (np.arange(32) + 0.5) / 32 - 0.5
        for k in rng.choice(len(iy), 25, replace=False):
            u = np.stack(np.meshgrid(p.x0 + ix[k] + off, p.y0 + iy[k] + off), -1).reshape(-1, 2)
            ref = np.mean(np.exp(-mu * sphere_chord_mm(cam.pixels_to_normalized(u), c, 1.5)))
            assert p.transmission[iy[k], ix[k]] == pytest.approx(ref, rel=1e-3)
        # the darkest pixel sees (nearly) the whole diameter: -ln T / mu close to 2a
        assert -np.log(p.transmission.min()) / mu == pytest.approx(3.0, rel=0.01)


def test_detector_noise_level_and_field():
    """Noise: with gamma 1/2 the Poisson variance becomes uniform, sd = level*255/(2 sqrt(q))
    (+ read noise); the image is black outside the circular field."""
    arm = build_carms(_cfg(image={"size_px": 256}))["cam1"]
    det = Detector(arm.camera.image_size, arm.fov_centre_px, arm.fov_radius_px, heel_gradient=0.0, vignetting=0.0,
                   veiling_glare=0.0, blur_sigma_px=0.0, noise=True, quanta_per_px=500.0, read_noise_dn=0.5, gamma=0.5)
    T = np.ones((256, 256), np.float32)
    rng = np.random.default_rng(0)
    clean, _ = det.expose(T, None, reference=1.0, quantize=False)
    noisy, _ = det.expose(T, rng, reference=1.0, quantize=False)
    inside = det.mask >= 1
    sd = np.std((noisy - clean)[inside])
    expected = np.sqrt((0.5 * det.level * 255) ** 2 / 500 + 0.25)
    assert sd == pytest.approx(expected, rel=0.03)   # ~40k pixels: 1/sqrt(2N) = 0.4 %
    q, _ = det.expose(T, rng, reference=1.0)
    assert q.dtype == np.uint8 and np.all(q[det.mask == 0] == 0)


# --- the twin ------------------------------------------------------------------------------------

SMALL = {"seed": 7, "image": {"size_px": 512}, "calibration": {"views": 2, "stereo_views": 1},
         "sequence": {"n_frames": 8}}


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("synth")
    cfgp = d / "small.yaml"
    import yaml
    cfgp.write_text(yaml.safe_dump(SMALL))
    out = d / "out"
    res = CliRunner().invoke(cli, ["synth", str(cfgp), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return cfgp, out


def test_cli_writes_every_file(small_run):
    _, out = small_run
    for name in ("indentation_log.csv", "ct_markers.fcsv", "ct_markers.mrk.json", "seeds.csv", "truth_markers.csv",
                 "truth.json", "synth.json"):
        assert (out / name).is_file(), name
    for v in ("cam1", "cam2"):
        assert sorted(p.name for p in (out / "calibration" / v).glob("*.png")) == ["cal_000.png", "cal_001.png"]
        assert [p.name for p in (out / "calibration" / "stereo" / v).glob("*.png")] == ["stereo_000.png"]
        assert sorted(p.name for p in (out / "sequence" / v).glob("*.png")) == [f"frame_{i:04d}.png" for i in range(8)]
    img = cv2.imread(str(out / "sequence" / "cam1" / "frame_0000.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (512, 512) and img.dtype == np.uint8
    assert not any(p.name.startswith(".synth-staging") for p in out.iterdir())
    s = json.loads((out / "synth.json").read_text())
    assert s["provenance"]["config"]["seed"] == 7 and s["counts"]["sequence_frames"] == 16
    assert "inputs_sha256" in s["provenance"]


def test_determinism_same_seed_identical_bytes(small_run, tmp_path):
    cfgp, out = small_run
    out2 = tmp_path / "again"
    assert CliRunner().invoke(cli, ["synth", str(cfgp), "-o", str(out2)]).exit_code == 0
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(out2) for p in out2.rglob("*") if p.is_file())
    for rel in files:
        a, b = (out / rel).read_bytes(), (out2 / rel).read_bytes()
        if rel.suffix == ".json" and rel.name != "ct_markers.mrk.json":
            ja, jb = json.loads(a), json.loads(b)
            for j in (ja, jb):   # the run's own time and duration are the only differences
                j.pop("provenance", None)
                j.pop("timing", None)
                j.pop("out", None)
            assert ja == jb, rel
        else:
            assert a == b, rel


def test_truth_is_consistent_with_frames(small_run):
    _, out = small_run
    truth = json.loads((out / "truth.json").read_text())
    cams = {v: Camera.from_dict(truth["cameras"][v]) for v in ("cam1", "cam2")}
    seq = truth["sequence"]
    # 2-D truth = projection of the 3-D truth, per view at that view's own times
    for v, cam in cams.items():
        for m, p2 in seq["projections_px"][v].items():
            p3 = np.asarray(seq["positions_mm_per_view"][v][m])
            assert np.abs(cam.project(p3) - np.asarray(p2)).max() < 1e-9
    rows = list(csv.DictReader(io.StringIO((out / "truth_markers.csv").read_text())))
    r = next(x for x in rows if x["view"] == "cam2" and x["frame"] == "3" and x["marker"] == "M1")
    assert float(r["x_px"]) == pytest.approx(seq["projections_px"]["cam2"]["M1"][3][0], abs=1e-9)
    # calibration truth = projection of the plate's object points
    cal = truth["calibration"]
    P = np.asarray(cal["object_points_mm"])
    for v, recs in cal["views"].items():
        for rec in recs:
            X = P @ np.asarray(rec["R_plate"]).T + np.asarray(rec["t_plate_mm"])
            assert np.abs(cams[v].project(X) - np.asarray(rec["image_points_px"])).max() < 1e-9


def test_frames_show_the_markers_where_the_truth_says():
    """Noise and tissue off, 16-bit, a frame every 5 s, cam2 0.4 s behind cam1 (markers move
    up to 0.3 mm/s x 0.4 s = 0.6 px between the views): in every frame of both views each
    visible marker's dark blob is centred within 0.05 px of its 2-D truth (as for a single
    bead), so frames, times and views are matched to the truth without slip."""
    tw = Twin(_cfg(seed=3, image={"bit_depth": 16}, noise={"enabled": False}, xray={"tissue": False},
                   calibration={"views": 0, "stereo_views": 0},
                   sequence={"fps": 0.2, "n_frames": 6, "start_s": 0.0, "gap_mm": 0.0},
                   effects={"view_time_offset_s": 0.4}))
    frames = dict(tw.sequence_frames())
    seq = tw.truth()["sequence"]
    assert max(seq["max_displacement_mm"].values()) > 0.3
    from bsipipe.synth.twin import rod_cover
    n = 0
    for v in ("cam1", "cam2"):
        # markers whose surround (the centroid's background ring, ~6 px = 1.2 mm) the rod's
        # shadow reaches are left out: the plane fitted to the ring would be biased
        P = tw.scene.positions_mm(tw.times[v])
        tips = tw.scene.tip_mm(tw.times[v])
        far = {m.name: rod_cover(tw.scene, tw.arms[v], P[:, j], tips, m.diameter_mm / 2, 1.2)[0]
               for j, m in enumerate(tw.scene.markers)}
        for i in range(6):
            img = frames[f"sequence/{v}/frame_{i:04d}.png"].astype(float)
            assert img.dtype == float and frames[f"sequence/{v}/frame_{i:04d}.png"].dtype == np.uint16
            for m, p2 in seq["projections_px"][v].items():
                if not (seq["visible"][v][m][i] and far[m][i]):
                    continue
                u = np.asarray(p2[i])
                c = _local_centroid(img, u, 3.5 if m.startswith("R") else 2.0)
                assert np.linalg.norm(c - u) < 0.05, (v, i, m)
                n += 1
    assert n >= 80    # of 2 x 6 x 9 = 108


def _local_centroid(img, u, radius_px):
    """Dark-blob centroid after removing a plane fitted to the ring around it."""
    x0, y0 = int(round(u[0])), int(round(u[1]))
    R = int(np.ceil(radius_px + 4))
    sub = img[y0 - R:y0 + R + 1, x0 - R:x0 + R + 1]
    gy, gx = np.mgrid[y0 - R:y0 + R + 1, x0 - R:x0 + R + 1].astype(float)
    r = np.hypot(gx - u[0], gy - u[1])
    ring = (r > radius_px + 1.5) & (r <= R)
    A = np.column_stack([np.ones(ring.sum()), gx[ring], gy[ring]])
    coef = np.linalg.lstsq(A, sub[ring], rcond=None)[0]
    w = np.clip(coef[0] + coef[1] * gx + coef[2] * gy - sub, 0, None) * (r <= radius_px + 1.0)
    return np.array([(w * gx).sum(), (w * gy).sum()]) / w.sum()


def test_scene_matches_the_study():
    tw = Twin(_cfg(seed=11, image={"size_px": 512}, calibration={"views": 0, "stereo_views": 0}))
    truth = tw.truth()
    seq = truth["sequence"]
    disp = seq["max_displacement_mm"]
    implanted = [m for m in seq["markers"] if m.startswith("M")]
    assert len(implanted) == 5 and len([m for m in seq["markers"] if m.startswith("R")]) == 4
    assert all(0.3 <= disp[m] <= 1.9 for m in implanted)          # the study's 0.3-1.8 mm
    assert all(disp[m] == 0 for m in seq["markers"] if m.startswith("R"))
    ind = seq["indentor"]
    assert max(ind["indentation_mm"]) == pytest.approx(4.8)
    assert ind["speed_mm_s"] == pytest.approx(0.2)                # 12 mm/min
    assert seq["fps"] == 2 and seq["n_frames"] == tw.n_frames
    # a steel rod hides M2 in cam1 and M4 in cam2 for a while, visible at both ends
    for m, v in (("M2", "cam1"), ("M4", "cam2")):
        occ = _occluded_by_geometry(tw, v, m)
        assert occ.sum() >= 3 and not occ[0] and not occ[-1]
    # the displacement field moves the surface point under the indentor with it
    u = indentation_displacement(np.asarray(ind["surface_point_mm"]), ind["surface_point_mm"], ind["direction"], 4.8, 2.5)
    assert np.allclose(u[0], 4.8 * np.asarray(ind["direction"]))


def _occluded_by_geometry(tw, view, marker):
    from bsipipe.synth.twin import rod_cover
    j = [m.name for m in tw.scene.markers].index(marker)
    P = tw.scene.positions_mm(tw.times[view])[:, j]
    clear, _ = rod_cover(tw.scene, tw.arms[view], P, tw.scene.tip_mm(tw.times[view]), 0.25, 0.0)
    return ~clear


def test_effects_switch():
    base = Twin(_cfg(seed=5, image={"size_px": 512}, calibration={"views": 0, "stereo_views": 0},
                     effects={"occlusion": False}))
    off = Twin(_cfg(seed=5, image={"size_px": 512}, calibration={"views": 0, "stereo_views": 0},
                    effects={"occlusion": False, "view_time_offset_s": 0.4, "moving_reference": True}))
    assert np.allclose(off.times["cam2"] - off.times["cam1"], 0.4)
    for m in ("M2", "M4"):
        assert not _occluded_by_geometry(base, "cam1", m).any() and not _occluded_by_geometry(base, "cam2", m).any()
    d = off.truth()["sequence"]["max_displacement_mm"]
    assert d["R2"] > 0.1 and d["R1"] == 0.0
    # switching the effects leaves the cameras as they were
    assert np.array_equal(base.arms["cam1"].camera.K, off.arms["cam1"].camera.K)


def test_log_consistent_with_motion():
    tw = Twin(_cfg(seed=2, image={"size_px": 256}, calibration={"views": 0, "stereo_views": 0}))
    frame, lt = tw.machine_log()
    t_cam1 = frame["time_s"].to_numpy() + lt["clock_offset_s"]
    assert np.abs(frame["extension_mm"].to_numpy() - tw.scene.travel_mm(t_cam1)).max() < 1e-9
    assert lt["depth_mm"] == pytest.approx(4.8) and lt["gap_mm"] == pytest.approx(0.5)


def test_stereo_extrinsics_and_plate_views():
    tw = Twin(_cfg(seed=4, image={"size_px": 512}, calibration={"views": 1, "stereo_views": 1},
                   sequence={"enabled": False}))
    images = dict(tw.calibration_images())
    assert set(images) == {"calibration/cam1/cal_000.png", "calibration/cam2/cal_000.png",
                           "calibration/stereo/cam1/stereo_000.png", "calibration/stereo/cam2/stereo_000.png"}
    t = tw.truth()
    st = t["stereo_extrinsics"]
    a, b = tw.arms["cam1"].camera, tw.arms["cam2"].camera
    X = np.random.default_rng(0).uniform(-30, 30, (10, 3))
    assert np.abs(a.to_camera(X) @ np.asarray(st["R"]).T + st["T_mm"] - b.to_camera(X)).max() < 1e-9
    assert 85 < st["angle_deg"] < 95
    rec = t["calibration"]["stereo"][0]["views"]
    assert all(all(rec[v]["inside_fov"]) for v in ("cam1", "cam2"))


@pytest.mark.parametrize("pattern,grid,spacing", [("chessboard", (9, 6), 10.0), ("charuco", (7, 5), 14.0)])
def test_optical_boards_are_detected_where_the_truth_says(pattern, grid, spacing):
    """OpenCV's own detectors find the rendered corners within 0.15 px of the truth (their
    sub-pixel precision on blurred, noisy 8-bit images is a few hundredths of a pixel)."""
    tw = Twin(_cfg(seed=1, calibration={"views": 1, "stereo_views": 0, "pattern": pattern, "grid": list(grid),
                                        "spacing_mm": spacing}, sequence={"enabled": False}))
    rel, img = next(iter(tw.calibration_images()))
    truth = np.asarray(tw.truth()["calibration"]["views"]["cam1"][0]["image_points_px"])
    if pattern == "chessboard":
        ok, c = cv2.findChessboardCorners(img, grid)
        assert ok
        c = cv2.cornerSubPix(img, c, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
        c = c.reshape(-1, 2)
        if np.linalg.norm(c[0] - truth[0]) > np.linalg.norm(c[0] - truth[-1]):
            c = c[::-1]
        err = np.linalg.norm(c - truth, axis=1)
    else:
        board = cv2.aruco.CharucoBoard(grid, spacing, spacing * 0.7, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250))
        cc, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(img)
        assert ids is not None and len(ids) == (grid[0] - 1) * (grid[1] - 1)
        err = np.linalg.norm(cc.reshape(-1, 2) - truth[ids.ravel()], axis=1)
    assert err.max() < 0.15


def test_bead_grid_found_by_opencv_in_truth_order():
    tw = Twin(_cfg(seed=1, calibration={"views": 1, "stereo_views": 0}, sequence={"enabled": False}))
    rel, img = next(iter(tw.calibration_images()))
    truth = np.asarray(tw.truth()["calibration"]["views"]["cam1"][0]["image_points_px"])
    p = cv2.SimpleBlobDetector_Params()
    p.minArea, p.maxArea, p.minThreshold, p.maxThreshold, p.thresholdStep = 8, 400, 40, 120, 4
    p.filterByConvexity = p.filterByInertia = False
    p.filterByCircularity, p.minCircularity = True, 0.6
    p.minRepeatability, p.minDistBetweenBlobs = 3, 3
    ok, c = cv2.findCirclesGrid(img, (8, 17), flags=cv2.CALIB_CB_ASYMMETRIC_GRID, blobDetector=cv2.SimpleBlobDetector_create(p))
    assert ok
    # the blob detector's centres are coarse (~0.1 px); the order is OpenCV's object-point order
    assert np.sqrt(np.mean(np.sum((c.reshape(-1, 2) - truth) ** 2, axis=1))) < 0.2


# --- Slicer markups --------------------------------------------------------------------------------

def test_slicer_files_parse_back(small_run):
    _, out = small_run
    truth = json.loads((out / "truth.json").read_text())
    written = truth["ct"]["markers_written_mm"]
    lines = (out / "ct_markers.fcsv").read_text().splitlines()
    assert lines[0].startswith("# Markups fiducial file version = ")
    assert "# CoordinateSystem = LPS" in lines
    cols = lines[2].split("=", 1)[1].strip().split(",")
    rows = list(csv.DictReader(io.StringIO("\n".join(lines[3:])), fieldnames=cols))
    assert [r["label"] for r in rows] == list(written)
    for r in rows:
        assert [float(r["x"]), float(r["y"]), float(r["z"])] == written[r["label"]]
    doc = json.loads((out / "ct_markers.mrk.json").read_text())
    mk = doc["markups"][0]
    assert mk["type"] == "Fiducial" and mk["coordinateSystem"] == "LPS"
    assert {p["label"]: p["position"] for p in mk["controlPoints"]} == written
    # the written coordinates are the world positions moved by the CT transform
    R, t = np.asarray(truth["ct"]["R"]), np.asarray(truth["ct"]["t_mm"])
    for name, rec in truth["sequence"]["markers"].items():
        if rec["kind"] == "indentor":      # mounted after the CT: not in the CT's markups
            assert name not in written
            continue
        assert np.allclose(R @ np.asarray(rec["position0_mm"]) + t, written[name], atol=1e-9)


def test_slicer_writers_reject_bad_input():
    from bsipipe.errors import InputError
    with pytest.raises(InputError):
        format_fcsv(["a,b"], [[0, 0, 0]])
    with pytest.raises(InputError):
        format_mrk_json(["a"], [[0, 0, 0]], coordinate_system="XYZ")
    txt = format_fcsv(["M1"], [[0.1, 1e-17, -3.0]], "RAS")
    assert "# CoordinateSystem = RAS" in txt and ",0.1,1e-17,-3.0," in txt


# --- CLI errors ----------------------------------------------------------------------------------

@pytest.mark.parametrize("text,key", [("sequence:\n  fps: -2\n", "sequence.fps"),
                                      ("image:\n  bit_depth: 12\n", "image.bit_depth"),
                                      ("effects:\n  occlusions: true\n", "effects.occlusions")])
def test_bad_config_exits_2_naming_the_key(tmp_path, text, key):
    cfgp = tmp_path / "bad.yaml"
    cfgp.write_text(text)
    res = CliRunner().invoke(cli, ["synth", str(cfgp), "-o", str(tmp_path / "out")])
    assert res.exit_code == 2
    assert key in res.output and "bad.yaml" in res.output
    assert not (tmp_path / "out" / "synth.json").exists()


def test_impossible_plate_exits_2(tmp_path):
    cfgp = tmp_path / "big.yaml"
    cfgp.write_text("image: {size_px: 256}\ncalibration: {grid: [30, 30], spacing_mm: 10}\nsequence: {enabled: false}\n")
    res = CliRunner().invoke(cli, ["synth", str(cfgp), "-o", str(tmp_path / "out")])
    assert res.exit_code == 2 and "calibration.grid" in res.output
    assert not (tmp_path / "out" / "calibration").exists()


def test_sample_configs_validate():
    from bsipipe.config import load_config
    root = Path(__file__).resolve().parents[1] / "configs"
    for name in ("synth_default.yaml", "synth_sdistortion.yaml", "synth_offset.yaml"):
        load_config(SynthConfig, root / name)


def test_indentor_beads_ride_the_indentor_and_stay_clear_of_the_rod():
    """The indentor's two beads (I1, I2) move with its flat end, their midpoint on its axis
    ``indentor_marker_height_mm`` above it, and each C-arm sees both outside the rod's shadow."""
    from bsipipe.synth.config import SynthConfig
    from bsipipe.synth.twin import Twin

    cfg = SynthConfig.model_validate({"calibration": {"views": 0, "stereo_views": 0}, "sequence": {"n_frames": 60}})
    tw = Twin(cfg)
    for _ in tw.sequence_frames():
        pass
    truth = tw.truth()
    seq = truth["sequence"]
    tip = np.asarray(seq["indentor"]["tip_mm"])
    into = np.asarray(seq["indentor"]["direction"])
    I = {n: np.asarray(seq["trajectories_mm"][n]) for n in ("I1", "I2")}
    mid = 0.5 * (I["I1"] + I["I2"])
    assert np.allclose(mid, tip - cfg.sequence.indentor_marker_height_mm * into, atol=1e-9)
    assert np.ptp(np.linalg.norm(I["I1"] - tip, axis=1)) < 1e-9          # rigid with the indentor
    assert np.ptp(tip @ into) > 4.0                                       # and the indentor moves
    for v in ("cam1", "cam2"):
        assert all(seq["visible"][v]["I1"]) and all(seq["visible"][v]["I2"])
    assert {s["marker"] for s in tw.seeds()} >= {"I1", "I2"}


def test_frame_jolt_moves_the_anatomy_and_its_truth_together():
    """``effects.frame_jolt_px``: every sequence frame after the first has the anatomy
    shifted by whole pixels (up to 3 per axis here) on the detector; the detections stay
    within 0.3 px (median) of the truth that shifted with them, the shifts are recorded in
    the truth, and the intensifier's field does not move."""
    from scipy.spatial import cKDTree

    from bsipipe.imaging.detect import detect_arrays, find_field_of_view
    cfg = SynthConfig.model_validate({"calibration": {"views": 0, "stereo_views": 0}, "sequence": {"n_frames": 4},
                                      "effects": {"frame_jolt_px": 3}})
    tw = Twin(cfg)
    frames = dict(tw.sequence_frames())
    rows = [r for r in tw.truth_markers_rows() if r["view"] == "cam1" and r["visible"]]
    jolt = tw.truth()["sequence"]["frame_jolt_px"]["cam1"]
    assert jolt[0] == [0, 0] and any(any(j) for j in jolt[1:])
    fov0 = find_field_of_view(frames["sequence/cam1/frame_0000.png"])
    for k in range(4):
        img = frames[f"sequence/cam1/frame_{k:04d}.png"]
        assert np.allclose(find_field_of_view(img).centre_px, fov0.centre_px, atol=0.5)
        d = detect_arrays(img, 4.0, "dark")
        truth = np.array([[r["x_px"], r["y_px"]] for r in rows if r["frame"] == k])
        dist, _ = cKDTree(np.column_stack([d["x_px"], d["y_px"]])).query(truth)
        assert np.median(dist) < 0.3


def test_view_clock_drift_times_cam2s_frames():
    """``effects.view_clock_drift``: cam2's frame i is taken at i / fps (1 + drift) + offset
    (cam1's at i / fps); the truth states both, and its per-view positions follow those times."""
    tw = Twin(_cfg(calibration={"views": 0, "stereo_views": 0}, sequence={"fps": 2.0, "n_frames": 7},
                   effects={"view_time_offset_s": 0.1, "view_clock_drift": 0.01}))
    i = np.arange(7)
    assert np.allclose(tw.times["cam1"], i / 2.0)
    assert np.allclose(tw.times["cam2"], i / 2.0 * 1.01 + 0.1)
    seq = tw.truth()["sequence"]
    assert seq["view_clock_drift"] == 0.01 and seq["view_time_offset_s"] == 0.1
    assert np.allclose(seq["times_s"]["cam2"], tw.times["cam2"])


def test_static_specks_darken_the_same_pixels_in_every_frame():
    """``effects.static_specks``: dark spots fixed on each intensifier, recorded in the truth.
    Against the same twin without specks (the same scene, the same noise drawn), every frame is
    darker at each speck's centre and unchanged far from the specks."""
    base = {"calibration": {"views": 0, "stereo_views": 0}, "sequence": {"n_frames": 3}}
    plain = dict(Twin(SynthConfig.model_validate(base)).sequence_frames())
    tw = Twin(SynthConfig.model_validate({**base, "effects": {"static_specks": 6}}))
    dusty = dict(tw.sequence_frames())
    specks = tw.truth()["sequence"]["static_specks"]
    assert set(specks) == {"cam1", "cam2"} and all(len(s) == 6 for s in specks.values())
    for v, sp in specks.items():
        far = np.ones(plain[f"sequence/{v}/frame_0000.png"].shape, bool)
        for s in sp:
            assert 0.08 <= s["depth"] <= 0.25 and 1.0 <= s["sigma_px"] <= 1.8
            x, y = int(round(s["x_px"])), int(round(s["y_px"]))
            far[max(y - 12, 0):y + 13, max(x - 12, 0):x + 13] = False
        for k in range(3):
            name = f"sequence/{v}/frame_{k:04d}.png"
            diff = plain[name].astype(float) - dusty[name].astype(float)
            assert np.abs(diff[far]).mean() < 0.05
            for s in sp:
                x, y = int(round(s["x_px"])), int(round(s["y_px"]))
                assert diff[y - 1:y + 2, x - 1:x + 2].mean() > 0.015 * plain[name][y, x], (v, s, k)
