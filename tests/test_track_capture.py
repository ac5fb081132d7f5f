"""The loop's ``track-capture``: a marker's track held by a static spot in one view.

Two C-arms film six beads on smooth 3-D paths; cam1's intensifier carries a static dark
speck (dust, a defect) beside one bead's first position, darker than the bead.  Seeded on
the bead, cam1's tracker follows the merged blob and, as the bead moves off, stays on the
speck: the bead's rays pass far apart for the rest of the sequence.  The loop must name
``track-capture``, find the bead again along cam2's rays, and bring its 2-D and 3-D errors
back to the other beads'; without the speck it must name nothing.
"""

import json

import cv2
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.imaging.camera import Camera, look_at

SIZE = 512
F_PX = 1677.5
FPS = 10.0
N = 80


def _cams():
    cams = {}
    for name, src in (("cam1", [-640.0, 0, 0]), ("cam2", [0, -640.0, 0])):
        R, t = look_at(src, [0, 0, 0])
        K = np.array([[F_PX, 0, 255.5], [0, F_PX, 256.2], [0, 0, 1]])
        cams[name] = Camera(K, np.array([0.03, -0.005, 0.0005, -0.0003, 0.0]), R, t, (SIZE, SIZE), name=name)
    return cams


def _calibration(cams) -> dict:
    a, b = cams["cam1"], cams["cam2"]
    R = b.R @ a.R.T
    views = {n: {"image_size": list(c.image_size), "camera_matrix": c.K.tolist(), "dist_model": "opencv-5",
                 "dist_coeffs": c.dist.tolist(), "dist_coeff_names": ["k1", "k2", "p1", "p2", "k3"]}
             for n, c in cams.items()}
    return {"views": views, "stereo": {"views": ["cam1", "cam2"], "R": R.tolist(), "T_mm": (b.t - R @ a.t).tolist()}}


def _scene(cams, seed=5):
    """The beads' 3-D paths (N, 6, 3) mm and their projections {view: (N, 6, 2)} px."""
    rng = np.random.default_rng(seed)
    P0 = rng.uniform(-25, 25, (6, 3))
    amp = rng.uniform(1.5, 3.0, (6, 3))
    ph = rng.uniform(0, 2 * np.pi, (6, 3))
    t = np.arange(N) / FPS
    X = P0[None] + amp[None] * np.sin(2 * np.pi * 0.12 * t[:, None, None] + ph[None])
    return X, {v: np.stack([c.project(x) for x in X]) for v, c in cams.items()}


def _render(xy, speck=None, seed=0):
    """Dark Gaussian beads (sigma 1.1 px, depth 60) on grey 170 with noise sd 3; ``speck``
    (x, y, depth, sigma): a static dark spot in every frame."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:SIZE, :SIZE].astype(np.float32)
    spots = [(x, y, 60.0, 1.1) for x, y in xy] + ([speck] if speck is not None else [])
    img = np.full((SIZE, SIZE), 170.0, np.float32)
    for x, y, a, s in spots:
        x0, y0 = int(x), int(y)
        sl = (slice(y0 - 8, y0 + 9), slice(x0 - 8, x0 + 9))
        img[sl] -= a * np.exp(-((xx[sl] - x) ** 2 + (yy[sl] - y) ** 2) / (2 * s * s))
    img += rng.normal(0, 3.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _track(tmp_path, cams, proj, speck, loop=True):
    for v in cams:
        d = tmp_path / v
        d.mkdir()
        for i in range(N):
            cv2.imwrite(str(d / f"f{i:03d}.png"), _render(proj[v][i], speck if v == "cam1" else None,
                                                           seed=i + (0 if v == "cam1" else 1000)))
    (tmp_path / "calibration.json").write_text(json.dumps(_calibration(cams)))
    pd.DataFrame([(v, f"M{j + 1}", *proj[v][0, j]) for v in cams for j in range(6)],
                 columns=["view", "marker", "x_px", "y_px"]).to_csv(tmp_path / "seeds.csv", index=False)
    outs = []
    for on in ((True, False) if not loop else (True,)):
        out = tmp_path / ("out" if on else "out_noloop")
        r = CliRunner().invoke(cli, ["-q", "track", "--view", f"cam1={tmp_path / 'cam1'}", "--view",
                                     f"cam2={tmp_path / 'cam2'}", "--seeds", str(tmp_path / "seeds.csv"),
                                     "--calibration", str(tmp_path / "calibration.json"), "--diameter-px", "4",
                                     "--fps", str(FPS), "--loop" if on else "--no-loop", "-o", str(out)])
        assert r.exit_code == 0, r.output
        outs.append(out)
    return outs[0] if loop else outs


def _errors(out, cams, X, proj, marker):
    t = pd.read_csv(out / "markers2d.csv")
    j = int(marker[1:]) - 1
    m = t[(t["view"] == "cam1") & (t["marker"] == marker) & t["found"]]
    e2 = np.hypot(m["x_px"] - proj["cam1"][m["frame"], j, 0], m["y_px"] - proj["cam1"][m["frame"], j, 1])
    p = pd.read_csv(out / "markers3d.csv").dropna(subset=["x_mm_raw"])
    R1, t1 = cams["cam1"].R, cams["cam1"].t
    T = X[p["frame"].to_numpy(), p["marker"].str[1:].astype(int).to_numpy() - 1] @ R1.T + t1
    e3 = np.linalg.norm(p[["x_mm_raw", "y_mm_raw", "z_mm_raw"]].to_numpy() - T, axis=1)
    mine = (p["marker"] == marker).to_numpy()
    return e2.to_numpy(), e3[mine], e3[~mine]


@pytest.mark.slow
def test_a_track_held_by_a_static_speck_is_found_again(tmp_path):
    cams = _cams()
    X, proj = _scene(cams)
    # the bead that moves furthest in cam1, a speck 1.5 px from its first position, darker than it
    j = int(np.argmax(np.ptp(proj["cam1"], axis=0).max(axis=1)))
    marker = f"M{j + 1}"
    x0, y0 = proj["cam1"][0, j]
    speck = (x0 + 1.2, y0 - 0.9, 110.0, 1.3)
    clean = _track(tmp_path / "clean", cams, proj, None) if (tmp_path / "clean").mkdir() is None else None
    dusty, declared = (_track(tmp_path / "dusty", cams, proj, speck, loop=False)
                       if (tmp_path / "dusty").mkdir() is None else None)
    loops = {k: json.loads((o / "track.json").read_text())["loop"] for k, o in (("clean", clean), ("dusty", dusty))}
    named = {k: [s["effect"] for s in lp["steps"]] for k, lp in loops.items()}
    e2, e3, e3_other = _errors(dusty, cams, X, proj, marker)
    e2_0, e3_0, _ = _errors(declared, cams, X, proj, marker)
    print(f"{marker} without the loop: 2-D error median {np.median(e2_0):.3f} px, 3-D RMS "
          f"{np.sqrt(np.mean(e3_0 ** 2)):.4f} mm")
    print(named, loops["dusty"]["final"]["params"].get("track_captures"))
    print(f"{marker}: 2-D error median {np.median(e2):.3f} px, 3-D RMS {np.sqrt(np.mean(e3 ** 2)):.4f} mm "
          f"(other beads {np.sqrt(np.mean(e3_other ** 2)):.4f} mm, {len(e3)} points)")
    assert "track-capture" not in named["clean"]
    assert "track-capture" in named["dusty"]
    caps = loops["dusty"]["final"]["params"]["track_captures"]
    assert [(c["marker"], c["view"]) for c in caps] == [(marker, "cam1")]
    # the captured stretch comes back: the track's frames in cam1 are on the bead again
    assert np.median(e2) < 0.3
    assert np.sqrt(np.mean(e3 ** 2)) < 2.0 * np.sqrt(np.mean(e3_other ** 2))
    # and without the loop the track stays on the speck
    assert np.median(e2_0) > 1.0 and np.sqrt(np.mean(e3_0 ** 2)) > 5 * np.sqrt(np.mean(e3 ** 2))
    t = pd.read_csv(dusty / "markers2d.csv")
    merged = t[(t["status"] == "merged")]
    assert set(merged["marker"]) <= {marker} and merged["x_px"].isna().all()
    ev = [e for e in json.loads((dusty / "track.json").read_text())["events"] if e["kind"] == "track-capture"]
    assert len(ev) == 1 and ev[0]["marker"] == marker


def test_window_source_reads_a_view_once_per_new_set_of_windows(tmp_path):
    """:class:`WindowSource` searches each window once: asking again for the same windows reads
    no frame; a new window reads the view again, up to the last frame asked for only; every
    window holds the beads inside it (and none outside)."""
    from bsipipe.imaging.track_effects import WindowSource
    d = tmp_path / "v"
    d.mkdir()
    xy = np.array([[100.3, 120.6], [300.2, 310.7]])
    for i in range(6):
        cv2.imwrite(str(d / f"f{i}.png"), _render(xy + [0.5 * i, 0.0], seed=i))
    src = WindowSource({"cam1": str(d)}, 4.0)
    wa, wb, wc = ("a", 100, 120, 10), ("b", 300, 311, 10), ("c", 200, 200, 10)
    got = src.candidates("cam1", {f: [wa, wb] for f in (1, 3)})
    assert src.n_reads == 1
    for f in (1, 3):
        for w, (x, y) in ((wa, xy[0]), (wb, xy[1])):
            c = got[(f, w)]
            assert len(c["x_px"]) == 1
            assert abs(c["x_px"][0] - (x + 0.5 * f)) < 0.2 and abs(c["y_px"][0] - y) < 0.2
    assert src.candidates("cam1", {3: [wa]})[(3, wa)] is got[(3, wa)]
    assert src.n_reads == 1
    src.candidates("cam1", {4: [wc]})
    assert src.n_reads == 2 and len(src.candidates("cam1", {4: [wc]})[(4, wc)]["x_px"]) == 0
    assert src.candidates("cam1", {9: [wa]})[(9, wa)] is None and src.n_reads == 3


def test_window_source_keeps_to_a_given_region(tmp_path):
    """With a view's given region of interest (a mask), track-capture's re-search finds only
    the beads inside it: the bead outside the region is not a candidate, the one inside is."""
    from bsipipe.imaging.detect import FieldOfView
    from bsipipe.imaging.track_effects import WindowSource
    d = tmp_path / "v"
    d.mkdir()
    xy = np.array([[100.3, 120.6], [300.2, 310.7]])
    img = _render(xy, seed=1)
    cv2.imwrite(str(d / "f0.png"), img)
    mask = np.zeros(img.shape[:2], bool)
    mask[:, :200] = True                         # the left part: the first bead only
    wa, wb = ("a", 100, 120, 10), ("b", 300, 311, 10)
    got = WindowSource({"cam1": str(d)}, 4.0).candidates("cam1", {0: [wa, wb]})
    assert len(got[(0, wa)]["x_px"]) == 1 and len(got[(0, wb)]["x_px"]) == 1
    roi = {"cam1": FieldOfView(img.shape[:2], region=mask, given=True)}
    got = WindowSource({"cam1": str(d)}, 4.0, rois=roi).candidates("cam1", {0: [wa, wb]})
    assert len(got[(0, wa)]["x_px"]) == 1 and len(got[(0, wb)]["x_px"]) == 0


def test_capture_windows_reach_no_farther_than_a_marker_moves():
    """One C-arm's picture panning 5 px a frame for 90 frames (the other still): the marker's
    motion in the other view, 450 px, had set windows of 467 px, the loop "found" static
    references 261 px from where they were, and the run took 13 minutes instead of 9 s.  The
    window's reach beyond its own 4 diameters is at most CAPTURE_REACH diameters."""
    from types import SimpleNamespace

    from bsipipe.imaging.track_effects import CAPTURE_REACH, _refind_windows
    F = 90
    own = np.full((F, 1, 2), 500.0)                                 # the track stands still
    other = np.stack([500.0 + 5.0 * np.arange(F), np.full(F, 400.0)], axis=1)[:, None, :]
    d = SimpleNamespace(frames=np.arange(F))
    req, radius = _refind_windows(d, own, other, np.zeros((F, 2)), 0, np.arange(F), 4.0)
    assert radius == np.ceil(4.0 * 4.0 + CAPTURE_REACH * 4.0) and len(req) == F
    # a marker's own motion (40 px in the other view) is searched in full
    other_small = np.stack([500.0 + 0.5 * np.arange(F) * 40 / 44.5, np.full(F, 400.0)], axis=1)[:, None, :]
    _, r_small = _refind_windows(d, own, other_small, np.zeros((F, 2)), 0, np.arange(F), 4.0)
    assert r_small == np.ceil(16.0 + 0.5 * (F - 1) * 40 / 44.5)
