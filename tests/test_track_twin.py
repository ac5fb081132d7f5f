"""The twin's Must-show checks (``bsipipe synth``'s C-arm twin, rendered in memory).

One twin sequence with an undeclared view time offset of 1 s (cam2's clock ahead), tracked
from its seeds (a user's clicks, 0.5 px off) and triangulated with the twin's true cameras
written as a ``calibration.json`` (world = cam1's camera), rendered twice:

- at the twin's former noise (1000 quanta per pixel, SNR 19 for a 4 px bead), where the
  issue's numbers were first met and are still checked as they were written;
- at the twin's default noise, set from real C-arm frames (SNR 12 for a 4 px bead; a
  0.5 mm marker, 2.6 px, has SNR ~6 there): what holds at the noise of real frames.  The
  2-D error of the 0.5 mm markers is then at the Cramer-Rao bound (~0.19 px), so the
  issue's "under 0.1 px" cannot be met by any estimator; a marker that faint is also
  missed in the odd frame (about 1 % of them).
"""

from itertools import groupby

import numpy as np
import pandas as pd
import pytest

from bsipipe.imaging.track import track_view
from bsipipe.imaging.track_effects import close_stereo_loop, stereo_data
from bsipipe.imaging.triangulate import views_from_calibration

pytestmark = pytest.mark.slow

OFFSET_S = 1.0
QUANTA_SNR19 = 1000.0     # the twin's noise before it was set from real frames


def truth_calibration(truth: dict) -> dict:
    """The twin's true cameras in ``bsipipe calibrate``'s calibration.json layout."""
    views = {}
    for v in ("cam1", "cam2"):
        c = truth["cameras"][v]
        views[v] = {"image_size": c["image_size"], "camera_matrix": c["camera_matrix"], "dist_model": "opencv-5",
                    "dist_coeffs": c["dist_coeffs"][:5], "dist_coeff_names": ["k1", "k2", "p1", "p2", "k3"]}
    st = truth["stereo_extrinsics"]
    return {"views": views, "stereo": {"views": st["views"], "R": st["R"], "T_mm": st["T_mm"]}}


def _tracked_twin(quanta_per_px: float | None, auto: bool = False) -> dict:
    from bsipipe.synth.config import SynthConfig
    from bsipipe.synth.twin import Twin
    over = {"calibration": {"views": 0, "stereo_views": 0}, "effects": {"view_time_offset_s": OFFSET_S}}
    if quanta_per_px is not None:
        over["noise"] = {"quanta_per_px": quanta_per_px}
    cfg = SynthConfig.model_validate(over)
    tw = Twin(cfg)
    seeds = pd.DataFrame(tw.seeds())
    fps = cfg.sequence.fps
    results = {}
    # frames come view after view; each view's are streamed straight into its tracker
    automatic = {}
    for view, grp in groupby(tw.sequence_frames(), key=lambda p: p[0].split("/")[1]):
        frames = [img for _, img in grp] if auto else (img for _, img in grp)
        results[view] = track_view(frames, seeds[seeds["view"] == view], 4.0, "dark", view=view, fps=fps)
        if auto:
            automatic[view] = track_view(frames, None, 4.0, "dark", view=view, fps=fps)
    truth = tw.truth()
    rows = pd.DataFrame(tw.truth_markers_rows())
    return {"results": results, "truth": truth, "rows": rows, "seeds": seeds, "automatic": automatic}


@pytest.fixture(scope="module")
def twin():
    """At the twin's former noise (SNR 19 for a 4 px bead)."""
    return _tracked_twin(QUANTA_SNR19)


@pytest.fixture(scope="module")
def twin_default_noise():
    """At the twin's default noise (the real C-arm frames' SNR); also tracked without seeds."""
    return _tracked_twin(None, auto=True)


def _errors_2d(twin: dict, view: str) -> pd.DataFrame:
    rows = twin["rows"]
    tab = twin["results"][view].table.merge(
        rows[rows["view"] == view][["frame", "marker", "x_px", "y_px", "visible", "occluded"]],
        on=["frame", "marker"], suffixes=("", "_true"))
    tab["err_px"] = np.hypot(tab["x_px"] - tab["x_px_true"], tab["y_px"] - tab["y_px_true"])
    return tab


def _loop_and_3d(twin: dict):
    """The stereo loop on both views' tracks; returns (view-time-offset step, 3-D errors mm)."""
    truth = twin["truth"]
    V = views_from_calibration(truth_calibration(truth))
    table = pd.concat([r.table for r in twin["results"].values()], ignore_index=True)
    loop, fit, _ = close_stereo_loop(stereo_data(table, (V["cam1"], V["cam2"])))
    steps = loop["steps"]
    R1 = np.asarray(truth["cameras"]["cam1"]["R"])
    t1 = np.asarray(truth["cameras"]["cam1"]["t_mm"])
    traj = truth["sequence"]["trajectories_mm"]
    p = fit.points.dropna(subset=["x_mm"])
    X = p[["x_mm", "y_mm", "z_mm"]].to_numpy()
    T = np.array([traj[m][f] for m, f in zip(p["marker"], p["frame"])]) @ R1.T + t1
    return steps, np.linalg.norm(X - T, axis=1)


def test_twin_2d_no_swaps_and_occlusion_refound(twin):
    """Zero identity swaps; the two markers that pass behind the indentor (M2 in cam1, M4 in
    cam2) are lost while hidden and found again after they reappear; nothing is found
    where the truth says a marker is hidden."""
    rows = twin["rows"]
    for view, res in twin["results"].items():
        tab = res.table.merge(rows[rows["view"] == view][["frame", "marker", "x_px", "y_px", "visible", "occluded"]],
                              on=["frame", "marker"], suffixes=("", "_true"))
        e = np.hypot(tab["x_px"] - tab["x_px_true"], tab["y_px"] - tab["y_px_true"])
        found = tab["found"]
        vis = tab["visible"].astype(bool)
        print(f"{view}: 2-D RMS {np.sqrt(np.mean(e[found & vis] ** 2)):.4f} px over {int((found & vis).sum())} points "
              f"({int(vis.sum())} visible); per marker "
              + ", ".join(f"{m} {np.sqrt(np.mean(e[found & vis & (tab['marker'] == m)] ** 2)):.3f}"
                          for m in tab["marker"].unique()))
        assert (e[found] < 1.0).all()                      # no swaps, no wrong marker anywhere
        assert found[vis].mean() > 0.95
        hidden_marker = {"cam1": "M2", "cam2": "M4"}[view]
        h = tab[tab["marker"] == hidden_marker].sort_values("frame")
        occ = h["occluded"].to_numpy(bool)
        assert occ.any()
        last_hidden = int(h["frame"].to_numpy()[occ].max())
        ev = [x for x in res.events if x["marker"] == hidden_marker]
        assert any(x["kind"] == "lost" for x in ev)
        assert any(x["kind"] == "refound" and x["frame"] > last_hidden - 3 for x in ev)
        after = h[h["frame"] > last_hidden + 2]
        assert after["found"].all()


def test_twin_3d_error_and_view_time_offset(twin):
    """3-D error RMS under 0.05 mm against the true trajectories; the loop names
    view-time-offset, estimates it within 10 % and the ray gap falls."""
    steps, err = _loop_and_3d(twin)
    assert steps and steps[0]["effect"] == "view-time-offset"
    s = steps[0]
    est = s["params"]["view_time_offset_s"]
    print(f"view-time-offset: estimated {est:.4f} s (true {OFFSET_S} s, {100 * (est / OFFSET_S - 1):+.1f} %); "
          f"ray gap RMS {s['ray_gap_rms_mm_before']:.4f} -> {s['ray_gap_rms_mm_after']:.4f} mm; reprojection RMS "
          f"{s['reprojection_rms_px_before']:.3f} -> {s['reprojection_rms_px_after']:.3f} px")
    assert abs(est - OFFSET_S) < 0.1 * OFFSET_S
    assert s["ray_gap_rms_mm_after"] < s["ray_gap_rms_mm_before"]
    assert "identity-swap" not in [x["effect"] for x in steps]
    # 3-D points (cam1's camera frame) against the truth (world -> cam1)
    rms = float(np.sqrt(np.mean(err ** 2)))
    print(f"3-D error RMS {rms:.4f} mm over {len(err)} points (max {err.max():.3f} mm)")
    assert rms < 0.05


def test_twin_at_the_noise_of_real_carm_frames(twin_default_noise):
    """At the default (real C-arm) noise: no identity swap, at least 95 % of the visible
    positions found, the hidden markers re-found after they reappear, the 2-D error of the
    0.5 mm markers within 1.3x the Cramer-Rao bound of a 2.6 px bead at this noise (the
    bound on a flat background: the markers here are 2.5-2.7 px, on tissue, and tracked
    with the 4 px settings of a mixed bead set), the 3-D error RMS under 0.05 mm and the
    view time offset within 10 %."""
    from test_detect import bead_grid, cramer_rao_px
    tw = twin_default_noise
    crb = cramer_rao_px(bead_grid(8, 512, np.random.default_rng(11)), 2.6, 512)
    for view, hidden_marker in (("cam1", "M2"), ("cam2", "M4")):
        tab = _errors_2d(tw, view)
        found, vis = tab["found"], tab["visible"].astype(bool)
        implanted = tab["marker"].str.startswith("M")
        rms_imp = float(np.sqrt(np.mean(tab["err_px"][found & vis & implanted] ** 2)))
        rms_ref = float(np.sqrt(np.mean(tab["err_px"][found & vis & ~implanted] ** 2)))
        print(f"{view} at the default noise: 2-D RMS 0.5 mm markers {rms_imp:.4f} px (Cramer-Rao bound {crb:.4f} px, "
              f"ratio {rms_imp / crb:.2f}), 1 mm references {rms_ref:.4f} px; found {found[vis].mean():.4f} of "
              f"{int(vis.sum())} visible positions")
        assert (tab["err_px"][found] < 1.0).all()
        assert found[vis].mean() > 0.95
        assert rms_imp < 1.3 * crb
        h = tab[tab["marker"] == hidden_marker]
        last_hidden = int(h["frame"][h["occluded"].astype(bool)].max())
        ev = [x for x in tw["results"][view].events if x["marker"] == hidden_marker]
        assert any(x["kind"] == "refound" and x["frame"] > last_hidden - 3 for x in ev)
    steps, err = _loop_and_3d(tw)
    assert steps and steps[0]["effect"] == "view-time-offset"
    est = steps[0]["params"]["view_time_offset_s"]
    rms3 = float(np.sqrt(np.mean(err ** 2)))
    print(f"view-time-offset {est:.4f} s ({100 * (est / OFFSET_S - 1):+.1f} %); 3-D error RMS {rms3:.4f} mm over "
          f"{len(err)} points")
    assert abs(est - OFFSET_S) < 0.1 * OFFSET_S
    assert rms3 < 0.05


def test_twin_without_seeds(twin_default_noise):
    """Automatic mode (no seeds) at the real frames' noise: every track follows one true
    marker (no found position more than 1 px off it: no swap, no track of noise), every
    marker visible in the first frame has a track, at least 98 % of the visible positions
    are found within 1 px, and the marker hidden by the indentor keeps its track across the
    gap (a new track that starts where the ended one would have been found continues it).  Tracking the tracks in search windows between
    whole-frame sweeps (with the seeded mode's prediction, assignment and second look)
    raised this from the per-frame detection and linking it replaced (measured on this
    twin: see the printout)."""
    from scipy.spatial import cKDTree
    tw = twin_default_noise
    rows = tw["rows"]
    for view, res in tw["automatic"].items():
        t = res.table
        tv = rows[rows["view"] == view]
        vis = tv[tv["visible"].astype(bool)]
        hits = 0
        for f, g in vis.groupby("frame"):
            got = t[(t["frame"] == f) & t["found"]]
            if len(got):
                d, _ = cKDTree(got[["x_px", "y_px"]].to_numpy()).query(g[["x_px", "y_px"]].to_numpy())
                hits += int((d <= 1.0).sum())
        owners = {}
        for m, g in t[t["found"]].groupby("marker"):
            tt = tv.set_index("frame").loc[g["frame"]]
            ids = []
            for (x, y), (_, row) in zip(g[["x_px", "y_px"]].to_numpy(), tt.groupby(level=0)):
                d = np.hypot(row["x_px"] - x, row["y_px"] - y).to_numpy()
                ids.append(row["marker"].to_numpy()[int(np.argmin(d))] if d.min() <= 1.0 else None)
            owners[m] = ids
        frac = hits / len(vis)
        n_off = sum(sum(1 for i in ids if i is None or i != ids[0]) for ids in owners.values())
        print(f"{view} without seeds: {len(owners)} tracks, {100 * frac:.2f} % of {len(vis)} visible positions found "
              f"within 1 px, {n_off} found positions off their track's marker")
        assert n_off == 0
        first = {ids[0] for ids in owners.values()}
        assert set(vis[vis["frame"] == vis["frame"].min()]["marker"]) <= first
        assert frac >= 0.98
        # the marker hidden by the indentor keeps its track: one track per marker, its name
        # re-found after the gap (the track had ended after ``memory`` frames)
        assert len(owners) == tv["marker"].nunique()
        hidden = {"cam1": "M2", "cam2": "M4"}[view]
        name = next(m for m, ids in owners.items() if ids[0] == hidden)
        last_hidden = int(tv[(tv["marker"] == hidden) & tv["occluded"].astype(bool)]["frame"].max())
        assert any(e["kind"] == "refound" and e["marker"] == name and e["frame"] > last_hidden - 3
                   for e in res.events)


def test_twin_with_frames_lost_from_one_view(twin):
    """An effect nobody declared, on top of the undeclared 1 s offset: cam1's frames 30-32
    deleted and the rest renumbered (a capture that skipped them), so from frame 30 on cam1's
    frame k is the twin's k + 3.  The loop names ``dropped-frames``: cam1 lost 3 frames before
    its frame 30, cam2's clock 1 s ahead within 10 %; the 3-D points, compared with the twin at
    the times put back, are as good as the complete sequence's; and the ray gap falls to the
    complete sequence's.  (Before the effect the loop had a constant offset or a clock drift to
    offer: a step is neither.)"""
    truth = twin["truth"]
    V = views_from_calibration(truth_calibration(truth))
    full = pd.concat([r.table for r in twin["results"].values()], ignore_index=True)
    t1 = full[full["view"] == "cam1"]
    t1 = t1[~t1["frame"].between(30, 32)].copy()
    later = t1["frame"] > 32
    period = float(np.median(np.diff(np.unique(full["time_s"].dropna()))))
    t1.loc[later, "frame"] -= 3
    t1.loc[later, "time_s"] = t1.loc[later, "frame"] * period
    cut = pd.concat([t1, full[full["view"] == "cam2"]], ignore_index=True)
    loop, fit, _ = close_stereo_loop(stereo_data(cut, (V["cam1"], V["cam2"])))
    names = [s["effect"] for s in loop["steps"]]
    steps = [{k: st[k] for k in ("view", "kind", "frame", "n_frames")} for st in fit.params.get("frame_steps", [])]
    _, err_full = _loop_and_3d(twin)
    R1 = np.asarray(truth["cameras"]["cam1"]["R"])
    tr1 = np.asarray(truth["cameras"]["cam1"]["t_mm"])
    traj = truth["sequence"]["trajectories_mm"]
    p = fit.points.dropna(subset=["x_mm"])
    real = p["frame"].to_numpy() + 3 * (p["frame"].to_numpy() >= 30)        # the twin's frame of each point
    T = np.array([traj[m][f] for m, f in zip(p["marker"], real)]) @ R1.T + tr1
    err = np.linalg.norm(p[["x_mm", "y_mm", "z_mm"]].to_numpy() - T, axis=1)
    rms, rms_full = float(np.sqrt(np.mean(err ** 2))), float(np.sqrt(np.mean(err_full ** 2)))
    print(names, steps, fit.params.get("view_time_offset_s"), loop["baseline"]["ray_gap_rms_mm"],
          loop["final"]["ray_gap_rms_mm"], rms, rms_full)
    assert "dropped-frames" in names
    assert steps == [{"view": "cam1", "kind": "lost", "frame": 30, "n_frames": 3}]
    assert abs(fit.params["view_time_offset_s"] - OFFSET_S) < 0.1 * OFFSET_S
    assert rms < 1.1 * rms_full
    np.testing.assert_allclose(p["time_s"].to_numpy(), real * period, atol=1e-9)


def test_twin_with_a_calibration_the_views_no_longer_match(twin):
    """An effect nobody declared, on top of the undeclared 1 s offset: cam2 turned 0.3 degrees
    since its calibration (a C-arm bumped).  Each marker's rays then miss each other by a
    steady amount, static references' too, and with the markers moving at a steady speed a
    time offset fitted part of it: on the probe's twin without an offset the loop had kept
    one of 0.25 s (0.53 s for 1 % on the focal length, -0.72 s for 2 mm across the
    baseline).  The loop names ``rig-mismatch`` beside ``view-time-offset``, the offset stays
    within 10 % of the truth, the ray gap about the markers' steady gaps is back near the
    true calibration's, and the run's warnings say so (``rig-mismatch``)."""
    from scipy.spatial.transform import Rotation
    truth = twin["truth"]
    cal = truth_calibration(truth)
    cal["stereo"]["R"] = (Rotation.from_euler("y", 0.3, degrees=True).as_matrix() @ np.asarray(cal["stereo"]["R"])).tolist()
    full = pd.concat([r.table for r in twin["results"].values()], ignore_index=True)
    V = views_from_calibration(cal)
    loop, fit, _ = close_stereo_loop(stereo_data(full, (V["cam1"], V["cam2"])))
    names = [s["effect"] for s in loop["steps"]]
    V0 = views_from_calibration(truth_calibration(truth))
    loop0, fit0, _ = close_stereo_loop(stereo_data(full, (V0["cam1"], V0["cam2"])))
    scatter = float(np.sqrt(np.mean(fit.residuals ** 2)))
    print(names, fit.params.get("view_time_offset_s"), fit.params["rig_mismatch"]["rms_bias_mm"],
          loop["baseline"]["ray_gap_rms_mm"], scatter, loop0["final"]["ray_gap_rms_mm"])
    assert set(names) == {"view-time-offset", "rig-mismatch"}, names
    assert abs(fit.params["view_time_offset_s"] - OFFSET_S) < 0.1 * OFFSET_S
    assert scatter < 1.5 * loop0["final"]["ray_gap_rms_mm"]
    assert "rig-mismatch" not in [s["effect"] for s in loop0["steps"]]
