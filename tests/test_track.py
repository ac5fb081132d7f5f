"""Tracking: crossing markers, occlusion and re-finding, automatic linking against trackpy,
the ``bsipipe track`` command on the real X-ray frame, XMALab files."""

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.imaging.track import TrackSettings, link_detections, track_view
from bsipipe.io.xmalab import format_xmalab_2d, format_xmalab_3d, is_xmalab_2d, read_xmalab_2d, read_xmalab_3d
from bsipipe.synth.xray import RayField
from test_detect import REAL, WATER, bead_camera, render_beads

XRAY = REAL / "xray_frame_deepxromm"


def crossing_sequence(n: int = 40, size: int = 160, seed: int = 0):
    """Two 4 px beads crossing head-on (2.2 px per frame each, their images merge for a
    frame or two) and a third passing 5 px from the crossing point, rendered through the
    twin's detector chain."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    A = np.column_stack([36 + 2.2 * t, 80 + 0.4 * np.sin(t / 6)])
    B = np.column_stack([124 - 2.2 * t, 81 + 0 * t])
    C = np.column_stack([80 + 5 + 0 * t, 30 + 2.0 * t])
    field = RayField(bead_camera(size))
    truth = np.stack([A, B, C], axis=1)
    frames = [render_beads(truth[i], 4.0, size, rng, field=field) for i in range(n)]
    return frames, truth


def test_crossing_markers_keep_their_names():
    """Constant-velocity prediction and global assignment: zero identity swaps, every found
    position on its own marker, the merged frames reported (merged, lost or ambiguous), and
    each marker found again right after."""
    frames, truth = crossing_sequence()
    seeds = {"A": truth[0, 0] + [1.0, -0.8], "B": truth[0, 1] + [-0.7, 1.0], "C": truth[0, 2] + [0.5, 0.5]}
    res = track_view(frames, seeds, 4.0, "dark", roi="none")
    tab = res.table
    swaps = 0
    for j, m in enumerate("ABC"):
        s = tab[tab["marker"] == m].sort_values("frame")
        xy = s[["x_px", "y_px"]].to_numpy()
        own = np.hypot(*(xy - truth[:, j]).T)
        others = [np.hypot(*(xy - truth[:, k]).T) for k in range(3) if k != j]
        swaps += int(np.sum(np.isfinite(own) & np.any([o < own for o in others], axis=0) & (own > 2.0)))
        assert s["found"].mean() > 0.9
        # away from the frames where the beads overlap, the centres are exact to noise
        sep = np.min([np.hypot(*(truth[:, j] - truth[:, k]).T) for k in range(3) if k != j], axis=0)
        clear = np.isfinite(own) & (sep > 8)
        assert np.sqrt(np.mean(own[clear] ** 2)) < 0.15
    print("events:", [(e["frame"], e["marker"], e["kind"]) for e in res.events])
    assert swaps == 0
    kinds = {e["kind"] for e in res.events}
    assert kinds & {"lost", "ambiguous", "merged"}          # the crossing is reported, not hidden
    for e in res.events:
        if e["kind"] in ("lost", "merged"):
            back = [f for f in res.events if f["kind"] == "refound" and f["marker"] == e["marker"]
                    and f["frame"] > e["frame"]]
            # found again right after a loss, and once the merged images part
            assert back and back[0]["frame"] - e["frame"] <= (3 if e["kind"] == "lost" else 10)


@pytest.mark.parametrize("miss_px", [1.0, 2.0, 3.0])
def test_slow_markers_passing_close_keep_their_names(miss_px):
    """Two 4 px beads at right angles, 0.5 px per frame each, passing ``miss_px`` apart (the
    probe's case, where their images merge for several frames): the merged image's centre had
    been taken as a measurement, which turned both tracks onto one path, and they parted
    swapped for the rest of the sequence (about 95 positions each, up to 69 px off, status
    found).  Now neither is measured while merged (status ``merged``, a ``merged`` event),
    both move on at their velocities from before, and each takes its own image where they
    part: no position off its marker by more than 1 px."""
    n, size = 60, 120
    rng = np.random.default_rng(7)
    t = np.arange(n, dtype=float)
    A = np.column_stack([45 + 0.5 * t, 60 + 0 * t])
    B = np.column_stack([60 + miss_px + 0 * t, 45 + 0.5 * t])          # closest at frame 30
    truth = np.stack([A, B], axis=1)
    field = RayField(bead_camera(size))
    frames = [render_beads(truth[i], 4.0, size, rng, field=field) for i in range(n)]
    res = track_view(frames, {"A": truth[0, 0], "B": truth[0, 1]}, 4.0, "dark", roi="none")
    tab = res.table
    for j, m in enumerate("AB"):
        s = tab[tab["marker"] == m].sort_values("frame")
        own = np.hypot(*(s[["x_px", "y_px"]].to_numpy() - truth[:, j]).T)
        print(m, "found", int(s["found"].sum()), "max error", np.nanmax(own), s["status"].value_counts().to_dict())
        assert np.nanmax(own) < 1.0
        assert s["found"].sum() >= n - 12 and (s["status"] == "merged").any()
    assert any(e["kind"] == "merged" for e in res.events)


def test_seeds_clicked_off_alike_still_start_their_tracks():
    """Every seed 6-8 px off its 4 px bead (clicks on a scaled display): within the seed
    radius (6 px) one or two found a marker, the first frame was empty for the rest.  Where
    most seeds find none, those are searched 2.5 times as far (the global assignment keeps
    each on its own bead): every marker is found in the first frame, on its own bead."""
    n, size = 6, 200
    rng = np.random.default_rng(3)
    truth = np.array([[40.0 + 30 * i, 60.0 + 25 * (i % 3)] for i in range(6)])
    field = RayField(bead_camera(size))
    frames = [render_beads(truth + [0.3 * k, 0.2 * k], 4.0, size, rng, field=field) for k in range(n)]
    ang = rng.uniform(0, 2 * np.pi, len(truth))
    off = np.column_stack([np.cos(ang), np.sin(ang)]) * rng.uniform(6.1, 7.9, (len(truth), 1))
    seeds = {f"M{i}": truth[i] + off[i] for i in range(len(truth))}
    res = track_view(frames, seeds, 4.0, "dark", roi="none")
    t0 = res.table[res.table["frame"] == 0].set_index("marker")
    for i in range(len(truth)):
        assert t0.loc[f"M{i}", "found"], f"M{i}"
        assert np.hypot(*(t0.loc[f"M{i}", ["x_px", "y_px"]].to_numpy(float) - truth[i])) < 0.5
    # seeds within the radius are not searched further: a seed 9 px from the nearest bead
    # among seeds on their beads finds nothing in the first frame
    seeds2 = {f"M{i}": truth[i] for i in range(len(truth))}
    seeds2["X"] = truth[0] + [0.0, 9.0]
    res2 = track_view(frames, seeds2, 4.0, "dark", roi="none")
    assert not res2.table[(res2.table["frame"] == 0) & (res2.table["marker"] == "X")]["found"].any()


def test_nearest_neighbour_without_prediction_is_worse():
    """The same crossing with the seeds' method (static nearest neighbour, no prediction):
    the prediction is what keeps the names -- without it a marker is lost for longer or
    swapped."""
    frames, truth = crossing_sequence()
    seeds = {"A": truth[0, 0], "B": truth[0, 1], "C": truth[0, 2]}
    static = track_view(frames, seeds, 4.0, "dark", roi="none", settings=TrackSettings(motion="static"))
    cv = track_view(frames, seeds, 4.0, "dark", roi="none")

    def bad(res):
        n = 0
        for j, m in enumerate("ABC"):
            s = res.table[res.table["marker"] == m].sort_values("frame")
            e = np.hypot(*(s[["x_px", "y_px"]].to_numpy() - truth[:, j]).T)
            n += int(np.sum(~np.isfinite(e) | (e > 2.0)))
        return n

    print(f"frames lost or wrong: static {bad(static)}, constant velocity {bad(cv)}")
    assert bad(cv) < bad(static)


def _hidden_marker_frames(M, hidden, size, rng, *, extra=None, background=None):
    """Frames of one 4 px bead at ``M[i]`` (none in the ``hidden`` frames), on ``extra`` (an
    image added, its median taken out) or over ``background`` (a transmission), with noise of
    sd 1.7."""
    field = RayField(bead_camera(size))
    frames = []
    for i in range(len(M)):
        img = render_beads(M[i:i + 1], 4.0, size, None, field=field, skip={0} if i in hidden else set(),
                           noise=False, quantize=False, background=background)
        if extra is not None:
            img = img + extra - np.median(extra)
        frames.append(np.clip(np.rint(img + rng.normal(0, 1.7, img.shape)), 0, 255).astype(np.uint8))
    return frames


def test_occluded_marker_found_again():
    """A marker hidden for 8 frames (behind an instrument) while it keeps moving: lost when
    it disappears, found again within a frame of reappearing (the gate grows along its
    predicted path), and a larger bead passing near its last position is not taken for it."""
    rng = np.random.default_rng(1)
    n, size = 40, 160
    t = np.arange(n, dtype=float)
    M = np.column_stack([40 + 1.5 * t, 60 + 0.8 * t])
    hidden = set(range(14, 22))
    # an 8 px bead sits 6 px from the hidden marker's path, inside its growing search window
    big = render_beads(np.array([[63.0, 79.5]]), 8.0, size, None, field=RayField(bead_camera(size)), noise=False,
                       quantize=False)
    frames = _hidden_marker_frames(M, hidden, size, rng, extra=big)
    res = track_view(frames, {"M": M[0]}, 4.0, "dark", roi="none")
    s = res.table.sort_values("frame")
    found = s["found"].to_numpy()
    assert not found[sorted(hidden)].any()
    lost = [e for e in res.events if e["kind"] == "lost"]
    ref = [e for e in res.events if e["kind"] == "refound"]
    assert lost and lost[0]["frame"] == min(hidden)
    assert ref and ref[0]["frame"] <= max(hidden) + 2
    after = s[s["frame"] > max(hidden) + 2]
    e = np.hypot(after["x_px"] - M[after["frame"], 0], after["y_px"] - M[after["frame"], 1])
    assert after["found"].all() and e.max() < 0.5


def test_a_lookalike_met_while_the_marker_is_hidden_is_left_out():
    """A marker hidden for 15 frames while a bead like it shows for one frame 8 px from its
    path, inside the gate grown since it was last seen: the tracker takes the bead, and the
    track's positions on either side (0.1 px a frame apart) show it was not the marker.  That
    frame is left out (status ``excursion``, an ``excursion`` event with where it was) instead
    of a position 8 px off with status ``found``."""
    rng = np.random.default_rng(3)
    n, size = 40, 160
    t = np.arange(n, dtype=float)
    M = np.column_stack([60 + 0.1 * t, 70 + 0.05 * t])
    hidden = set(range(10, 25))
    frames = _hidden_marker_frames(M, hidden, size, rng)
    look = render_beads(np.array([[M[16, 0] + 8.0, M[16, 1]]]), 4.0, size, None, field=RayField(bead_camera(size)),
                        noise=False, quantize=False)
    frames[16] = np.clip(frames[16].astype(float) + look - np.median(look), 0, 255).astype(np.uint8)
    res = track_view(frames, {"M": M[0]}, 4.0, "dark", roi="none")
    s = res.table.sort_values("frame").set_index("frame")
    assert not s.loc[sorted(hidden), "found"].any()
    assert s.loc[16, "status"] == "excursion" and np.isnan(s.loc[16, "x_px"])
    exc = [e for e in res.events if e["kind"] == "excursion"]
    assert len(exc) == 1 and exc[0]["frame"] == 16 and abs(exc[0]["x_px"] - (M[16, 0] + 8.0)) < 0.5
    assert exc[0]["distance_px"] > 7.0
    # the stale events of the excursion are gone: lost at 10, found again once the marker shows
    assert [(e["kind"], e["frame"]) for e in res.events if e["kind"] in ("lost", "refound")] == [("lost", 10),
                                                                                               ("refound", 25)]
    e = np.hypot(s["x_px"] - M[s.index, 0], s["y_px"] - M[s.index, 1])
    assert s["found"].sum() == n - len(hidden) and e[s["found"]].max() < 0.5


def test_excursions_only_where_the_track_on_both_sides_disagrees():
    """``reject_excursions`` on tables: a short run between gaps on the line between its
    neighbours, or on a curve the neighbours' distance allows, is kept; one off both is not;
    a run at either end of the track (no neighbour on one side) is never judged."""
    from bsipipe.imaging.track import reject_excursions

    def table(xy, found):
        n = len(xy)
        return pd.DataFrame({"view": "v", "frame": np.arange(n), "time_s": np.arange(n) / 2.0, "marker": "M",
                             "x_px": np.where(found, xy[:, 0], np.nan), "y_px": np.where(found, xy[:, 1], np.nan),
                             "found": found, "snr": 10.0, "amplitude": 5.0, "area_px": 12.0, "sigma_px": 1.3,
                             "pred_x_px": np.nan, "pred_y_px": np.nan, "gate_px": 6.0,
                             "status": np.where(found, "found", "lost")})

    n = 30
    xy = np.column_stack([50 + 0.5 * np.arange(n), np.full(n, 40.0)])
    found = np.ones(n, bool)
    found[[5, 6, 7, 9, 10, 11]] = False          # a one-frame run at 8 between gaps
    kept, ev = reject_excursions(table(xy, found), [], 6.0, "v")
    assert kept["found"].sum() == found.sum() and not ev
    off = xy.copy()
    off[8] += [0.0, 9.0]                          # 9 px off the line, its neighbours 4 px apart: out
    out, ev = reject_excursions(table(off, found), [], 6.0, "v")
    assert not out.loc[8, "found"] and out.loc[8, "status"] == "excursion" and [e["frame"] for e in ev] == [8]
    # a track that moved 20 px between the neighbours may have curved 9 px: kept
    bend = xy.copy()
    bend[12:, 1] += 20.0
    bend[8] += [0.0, 9.0]
    kept, ev = reject_excursions(table(bend, found), [], 6.0, "v")
    assert kept.loc[8, "found"] and not ev
    # the run at the start (frames 0-1, then a gap) has no neighbour before it: not judged
    f2 = np.ones(n, bool)
    f2[2:6] = False
    off2 = xy.copy()
    off2[:2] += [0.0, 9.0]
    kept, ev = reject_excursions(table(off2, f2), [], 6.0, "v")
    assert kept["found"].sum() == f2.sum() and not ev


def test_hidden_marker_is_not_taken_onto_a_wire():
    """A marker that crosses a thin wire (a line 30 % darker across the field) while hidden for
    16 frames: its growing search window took peaks of the wire's top-hat ridge (here 2
    positions while hidden, 2.2 px off, status found; on the probe's twin it was followed along
    the wire, 7-50 px off, 3-D error up to 4.9 mm).  A ridge away from a window's centre is no
    marker: lost while hidden, found again on its own bead (0.18 px)."""
    rng = np.random.default_rng(2)
    n, size = 50, 160
    t = np.arange(n, dtype=float)
    M = np.column_stack([50 + 0.6 * t, 70 + 0.3 * t])
    hidden = set(range(14, 30))
    yy = np.arange(size, dtype=np.float32)[:, None] * np.ones((1, size), np.float32)
    wire = 1.0 - 0.3 * np.exp(-0.5 * ((yy - 76) / 0.7) ** 2)
    frames = _hidden_marker_frames(M, hidden, size, rng, background=wire)
    res = track_view(frames, {"M": M[0]}, 4.0, "dark", roi="none")
    s = res.table.sort_values("frame").set_index("frame")
    e = np.hypot(s["x_px"] - M[s.index, 0], s["y_px"] - M[s.index, 1])
    print("found while hidden:", s.loc[sorted(hidden), "found"].sum(), "max error found:", e[s["found"]].max())
    assert not s.loc[sorted(hidden), "found"].any()
    after = s.loc[max(hidden) + 3:]
    assert after["found"].all() and e[after.index].max() < 0.5


def jolted_sequence(n: int = 30, size: int = 160, seed: int = 5):
    """Six 4 px beads 14-16 px apart, drifting 0.3 px per frame, the whole picture shifted
    in every frame by a common random offset of up to 3 px per axis (a C-arm's or a head's
    jolts)."""
    rng = np.random.default_rng(seed)
    base = np.array([[60, 60], [75, 62], [90, 60], [60, 76], [76, 77], [91, 75]], float)
    jolt = rng.integers(-3, 4, (n, 2)).astype(float)
    jolt[0] = 0
    truth = np.stack([base + [0.3 * k, 0.2 * k] + jolt[k] for k in range(n)])
    field = RayField(bead_camera(size))
    return [render_beads(truth[k], 4.0, size, rng, field=field) for k in range(n)], truth


def test_a_jolt_of_the_whole_picture_does_not_swap_markers():
    """Seeded, the whole picture jolting by up to 3 px per axis in every frame (up to 6 px
    between frames, beyond the gate's reach once the velocity takes a jolt in): the common
    offset is found from the markers and every prediction moved by it, so every marker
    is found in every frame, on its own bead, and the frames are reported (frame-shift
    events).  Without it (``frame_shift=False``) markers are lost or swapped."""
    frames, truth = jolted_sequence()
    seeds = {f"B{j}": truth[0, j] for j in range(truth.shape[1])}
    errs = {}
    for on in (True, False):
        res = track_view(frames, seeds, 4.0, "dark", roi="none", settings=TrackSettings(frame_shift=on))
        t = res.table
        j = t["marker"].str[1:].astype(int).to_numpy()
        e = np.hypot(t["x_px"] - truth[t["frame"], j, 0], t["y_px"] - truth[t["frame"], j, 1])
        errs[on] = (float(t["found"].mean()), float(np.nanmax(e)))
        if on:
            assert t["found"].all() and e.max() < 0.3
            shifts = [x for x in res.events if x["kind"] == "frame-shift"]
            assert len(shifts) >= 5 and all(x["marker"] is None for x in shifts)
    print(f"found, worst error: with the frame shift {errs[True]}, without {errs[False]}")
    assert errs[False][0] < 0.95 or errs[False][1] > 3.0


def test_cli_warns_of_a_jolting_picture(tmp_path):
    """``bsipipe track`` on frames whose whole picture jolts: a ``frame-shifts`` warning
    naming the view, how many frames and the largest jolt; the markers are all found.  The
    crossing sequence, which does not jolt, has no such warning."""
    import cv2
    for name, (frames, truth) in (("jolted", jolted_sequence()), ("steady", crossing_sequence(n=12))):
        d = tmp_path / name
        d.mkdir()
        for k, img in enumerate(frames):
            cv2.imwrite(str(d / f"f{k:03d}.png"), img)
        seeds = tmp_path / f"{name}_seeds.csv"
        pd.DataFrame([("cam1", f"B{j}", *truth[0, j]) for j in range(truth.shape[1])],
                     columns=["view", "marker", "x_px", "y_px"]).to_csv(seeds, index=False)
        out = tmp_path / f"{name}_out"
        r = CliRunner().invoke(cli, ["-q", "track", "--view", f"cam1={d}", "--seeds", str(seeds),
                                     "--diameter-px", "4", "--fps", "2", "-o", str(out)])
        assert r.exit_code == 0, r.output
        j = json.loads((out / "track.json").read_text())
        codes = [w["code"] for w in j["warnings"]]
        if name == "jolted":
            w = next(w for w in j["warnings"] if w["code"] == "frame-shifts")
            assert w["views"]["cam1"]["n_frames"] >= 5 and 2.0 < w["views"]["cam1"]["max_px"] < 9.0
            assert pd.read_csv(out / "markers2d.csv")["found"].all()
        else:
            assert "frame-shifts" not in codes


def _track_crossing(tmp_path, frames, truth, skip=()) -> Path:
    """``bsipipe track`` on the crossing sequence's frames as PNG files (those in ``skip``
    not written), seeded at the truth's first positions (markers A, B, C), 2 frames/s;
    returns the output folder."""
    d = tmp_path / "frames"
    d.mkdir()
    for k, img in enumerate(frames):
        if k not in skip:
            cv2.imwrite(str(d / f"f{k:03d}.png"), img)
    seeds = tmp_path / "seeds.csv"
    pd.DataFrame([("cam1", m, *truth[0, j]) for j, m in enumerate("ABC")],
                 columns=["view", "marker", "x_px", "y_px"]).to_csv(seeds, index=False)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["-q", "track", "--view", f"cam1={d}", "--seeds", str(seeds), "--diameter-px", "4",
                                 "--fps", "2", "-o", str(out)])
    assert r.exit_code == 0, r.output
    return out


def test_cli_a_dropped_frame_file_keeps_the_numbering(tmp_path):
    """``bsipipe track`` on frames f000..f011 with f005.png missing (the recorder dropped it):
    frame 5's rows are empty (status missing-frame), the later frames keep their numbers and
    times (frame 6 at 3 s at 2 frames/s), the markers are followed across the gap, a
    ``missing-frames`` warning names the frame, and XMALab's 2-D file keeps a blank row for
    it."""
    frames, truth = crossing_sequence(n=12)
    out = _track_crossing(tmp_path, frames, truth, skip=(5,))
    t = pd.read_csv(out / "markers2d.csv")
    assert t["frame"].tolist() == [k for k in range(12) for _ in range(3)]
    gone = t[t["frame"] == 5]
    assert (gone["status"] == "missing-frame").all() and not gone["found"].any() and gone["x_px"].isna().all()
    assert (t.loc[t["frame"] != 5, "status"] != "missing-frame").all()
    assert t.loc[t["frame"] == 6, "time_s"].eq(3.0).all() and t.loc[t["frame"] == 5, "time_s"].eq(2.5).all()
    j = t["marker"].map({"A": 0, "B": 1, "C": 2}).to_numpy()
    err = np.hypot(t["x_px"] - truth[t["frame"], j, 0], t["y_px"] - truth[t["frame"], j, 1])
    late = (t["frame"] > 5).to_numpy() & t["found"].to_numpy()
    assert late.sum() >= 15 and err[late].max() < 0.5
    w = [w for w in json.loads((out / "track.json").read_text())["warnings"] if w["code"] == "missing-frames"]
    assert len(w) == 1 and w[0]["frames"] == {"cam1": [5]}
    x2 = read_xmalab_2d(out / "xmalab_2d.csv")
    assert sorted(x2["frame"].unique()) == list(range(12))
    assert x2.loc[x2["frame"] == 5, ["x_px", "y_px"]].isna().all().all()
    # DLTdv8's points file: the same positions in DLTdv's pixels (1 more), points named in track.json
    from bsipipe.io.dltdv import read_dltdv_xypts
    dl = read_dltdv_xypts(out / "dltdv_xypts.csv")
    names = json.loads((out / "track.json").read_text())["dltdv"]["points"]
    dl["marker"] = dl["marker"].map(names)
    both = x2.merge(dl, on=["view", "frame", "marker"], suffixes=("", "_dl"))
    assert len(both) == len(x2) and np.allclose(both["x_px"], both["x_px_dl"], equal_nan=True)
    assert np.allclose(both["y_px"], both["y_px_dl"], equal_nan=True)
    raw = pd.read_csv(out / "dltdv_xypts.csv")
    assert list(raw.columns[:2]) == ["pt1_cam1_X", "pt1_cam1_Y"]
    first = both[(both["frame"] == 0) & (both["marker"] == names["pt1"])]
    assert raw["pt1_cam1_X"].iloc[0] == pytest.approx(first["x_px"].iloc[0] + 1.0)


def test_automatic_mode_names_tracks():
    """Without seeds the whole frame is searched for new markers (here in frames 0 and 11,
    the last) and each track in its window between; the three beads become three tracks
    M1..M3 that follow them."""
    frames, truth = crossing_sequence(n=12)
    res = track_view(frames, None, 4.0, "dark", roi="none")
    names = sorted(res.table["marker"].unique())
    assert names == ["M1", "M2", "M3"]
    last = res.table[res.table["frame"] == 5]
    for j in range(3):
        d = np.hypot(last["x_px"] - truth[5, j, 0], last["y_px"] - truth[5, j, 1])
        assert d.min() < 0.5


def test_automatic_mode_follows_a_new_marker_back_to_where_it_appeared():
    """Without seeds, the whole frame is searched only every ``sweep_every_frames`` frames
    (and in the last); a marker that comes into view between two sweeps is found by the
    next one and followed backwards through the frames since the previous sweep, so its
    track starts where it appeared, with the positions a sweep of every frame gives; a
    marker that stays in view for fewer frames than the sweeps are apart, between two of
    them, is the price."""
    size, n, appear = 160, 24, 7
    rng = np.random.default_rng(3)
    t = np.arange(n, dtype=float)
    A = np.column_stack([50 + 0.5 * t, 60 + 0 * t])
    N = np.column_stack([100 + 0 * t, 40 + 1.5 * t])          # comes into view at frame 7
    field = RayField(bead_camera(size))
    frames = [render_beads(np.vstack([A[i], N[i]]), 4.0, size, rng, field=field, skip=(1,) if i < appear else ())
              for i in range(n)]
    tabs = {}
    for every in (1, 10):
        res = track_view(frames, None, 4.0, "dark", roi="none", settings=TrackSettings(sweep_every_frames=every))
        tab = res.table[res.table["found"]]
        assert sorted(tab["marker"].unique()) == ["M1", "M2"]
        new = tab[tab["marker"] == "M2"].set_index("frame")
        assert new.index.min() == appear and len(new) == n - appear
        e = np.hypot(new["x_px"] - N[new.index, 0], new["y_px"] - N[new.index, 1])
        assert e.max() < 0.3
        tabs[every] = new
    # frames 7-9: followed back from the sweep of frame 10 in search windows, against the
    # whole-frame detections of a sweep in every frame
    d = np.hypot(tabs[1]["x_px"] - tabs[10]["x_px"], tabs[1]["y_px"] - tabs[10]["y_px"])
    assert d.max() < 0.02


def test_automatic_mode_follows_a_new_marker_back_across_a_gap():
    """A marker that comes into view at frame 3 and is hidden in frames 12-13 is first found
    by the sweep of frame 20; followed backwards as tracks are followed forwards (a gap of
    up to ``memory`` frames is crossed, the gate growing), its track starts at frame 3, not
    after the gap."""
    size, n, appear, hidden = 160, 24, 3, (12, 13)
    rng = np.random.default_rng(8)
    t = np.arange(n, dtype=float)
    A = np.column_stack([50 + 0.5 * t, 60 + 0 * t])
    N = np.column_stack([100 + 0.3 * t, 40 + 1.2 * t])
    field = RayField(bead_camera(size))
    frames = [render_beads(np.vstack([A[i], N[i]]), 4.0, size, rng, field=field,
                           skip=(1,) if i < appear or i in hidden else ()) for i in range(n)]
    res = track_view(frames, None, 4.0, "dark", roi="none", settings=TrackSettings(sweep_every_frames=20))
    tab = res.table[res.table["found"]]
    assert sorted(tab["marker"].unique()) == ["M1", "M2"]
    new = tab[tab["marker"] == "M2"].set_index("frame")
    assert new.index.min() == appear
    assert sorted(new.index) == [i for i in range(appear, n) if i not in hidden]
    e = np.hypot(new["x_px"] - N[new.index, 0], new["y_px"] - N[new.index, 1])
    assert e.max() < 0.3


def test_automatic_mode_in_a_dense_field():
    """120 beads in a 200 x 200 frame (12.5 px apart), each moving 0.6 px per frame in its own direction:
    their search windows would hold more pixels than the frame, so each frame is searched
    whole and the tracks take their beads from it (the window search's prediction,
    assignment and appearance tests, on the whole frame's candidates); every bead keeps one
    track, every position within 0.5 px of its bead (two beads that close in bias each
    other's centres by a few tenths)."""
    from bsipipe.imaging.detect import window_strip_px
    size, n, nb = 200, 8, 120
    rng = np.random.default_rng(4)
    g = np.stack(np.meshgrid(np.arange(-7, 8), np.arange(-7, 8)), -1).reshape(-1, 2) * 12.5
    g = g[np.argsort(np.hypot(g[:, 0], g[:, 1]), kind="stable")][:nb]       # inside the intensifier's circle
    p0 = 99.5 + g + rng.uniform(-2, 2, (nb, 2))
    ang = rng.uniform(0, 2 * np.pi, nb)
    v = 0.6 * np.column_stack([np.cos(ang), np.sin(ang)])
    truth = np.stack([p0 + k * v for k in range(n)])
    assert window_strip_px(nb, 6.0, 4.0) > 0.5 * size * size
    frames = [render_beads(truth[k], 4.0, size, rng) for k in range(n)]
    res = track_view(frames, None, 4.0, "dark", roi="none")
    tab = res.table[res.table["found"]]
    assert tab["marker"].nunique() == nb
    for m, grp in tab.groupby("marker"):
        d = np.hypot(truth[grp["frame"].to_numpy(), :, 0] - grp["x_px"].to_numpy()[:, None],
                     truth[grp["frame"].to_numpy(), :, 1] - grp["y_px"].to_numpy()[:, None])
        owner = d.argmin(axis=1)
        assert (owner == owner[0]).all() and d.min(axis=1).max() < 0.5
    assert len(tab) >= 0.98 * nb * n


# --- linking against trackpy on real microscopy --------------------------------------------------------

def trackpy_30():
    """trackpy 0.7's features of frames 0-29 (``batch(green, 11, invert=True, minmass=20)``,
    stored: ``_make_trackpy_reference.py``; frame 29 is checked live in test_detect) and
    their ``link(search_range=5, memory=3)``: live if trackpy is installed, else stored."""
    feats = pd.read_csv(WATER / "trackpy_features_30.csv")
    try:
        import trackpy as tp
    except ImportError:
        return feats, pd.read_csv(WATER / "trackpy_link_30.csv")
    tp.quiet()
    return feats, tp.link(feats, 5, memory=3)


def _links(df: pd.DataFrame, x="x", y="y") -> set:
    """Every link of a linked table: (frame, x, y) of a detection and of the next one of
    its trajectory."""
    d = df.sort_values(["particle", "frame"])
    p = d["particle"].to_numpy()
    key = list(zip(d["frame"].to_numpy(), np.round(d[x].to_numpy(), 4), np.round(d[y].to_numpy(), 4)))
    same = np.flatnonzero(p[1:] == p[:-1])
    return {(key[i], key[i + 1]) for i in same}


def test_linking_vs_trackpy_30_frames():
    """The same 30 frames, the same detections (trackpy's), the same search range (5 px) and
    memory (3 frames).

    - ``static``: trackpy's criterion (the matching of minimum total squared displacement
      within the search range), solved exactly by linear_sum_assignment: every one of
      trackpy's links is reproduced and there are no others.
    - ``constant-velocity`` (the default, for markers carried by tissue): on Brownian
      particles the velocity of the last step does not predict the next, so predictions are
      slightly worse than "no motion" and about 1 % of the links differ -- the prediction is
      for directed motion, which is why ``static`` exists.
    """
    feats, linked = trackpy_30()
    tp_links = _links(linked)
    det = feats.rename(columns={"x": "x_px", "y": "y_px"})
    st, _ = link_detections(det, 5.0, memory=3, motion="static")
    cv, _ = link_detections(det, 5.0, memory=3, motion="constant-velocity")
    ls = _links(st, "x_px", "y_px")
    lc = _links(cv, "x_px", "y_px")
    print(f"trackpy: {linked['particle'].nunique()} trajectories, {len(tp_links)} links; static: "
          f"{st['particle'].nunique()} trajectories, {len(ls & tp_links)} common links, {len(ls - tp_links)} others; "
          f"constant velocity: {len(lc & tp_links) / len(tp_links):.4f} of trackpy's links")
    assert ls == tp_links
    assert st["particle"].nunique() == linked["particle"].nunique()
    assert 0.97 < len(lc & tp_links) / len(tp_links) < 1.0


# --- the command ----------------------------------------------------------------------------------

def _xray_seeds(tmp_path) -> Path:
    inp = pd.read_csv(XRAY / "sample_frame_input.csv")
    rows = [("cam1", c[:-7], inp[c][0], inp[c[:-7] + "_cam1_Y"][0]) for c in inp.columns if c.endswith("_cam1_X")]
    p = tmp_path / "seeds.csv"
    pd.DataFrame(rows, columns=["view", "marker", "x_px", "y_px"]).to_csv(p, index=False)
    return p


@pytest.mark.parametrize("given", ["--diameter-px", "--polarity"])
def test_a_diameter_wider_than_a_sixteenth_of_the_frame_is_refused_at_once(tmp_path, given):
    """--diameter-px 100 on 1024 px frames had run for minutes without a word (a top-hat that
    wide on whole frames); it is exit 2 naming the limit, before any frame is tracked (also
    with the polarity given, where the first frames had not been read)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "sample_frame.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    extra = ["--polarity", "dark"] if given == "--polarity" else []
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--diameter-px", "100", *extra,
                                 "-o", str(tmp_path / "out")])
    assert r.exit_code == 2 and "1/16" in r.output and "diameter" in r.output, r.output
    assert not (tmp_path / "out").exists()


def test_cli_track_real_frame(tmp_path):
    """The contract's 2-D form on the real X-ray frame: markers2d.csv, XMALab 2-D file that
    reads back, track.json with per-marker SNR, events and provenance, the figures."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "sample_frame.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    seeds = _xray_seeds(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--polarity", "dark", "--diameter-px", "4",
                                 "--seeds", str(seeds), "-o", str(out)])
    assert r.exit_code == 0, r.output
    m2 = pd.read_csv(out / "markers2d.csv")
    assert list(m2.columns[:5]) == ["view", "frame", "marker", "x_px", "y_px"]
    assert len(m2) == 24 and m2["found"].all()
    x = read_xmalab_2d(out / "xmalab_2d.csv")
    assert len(x) == 24 and np.allclose(x.sort_values("marker")["x_px"], m2.sort_values("marker")["x_px"], atol=1e-6)
    j = json.loads((out / "track.json").read_text())
    assert j["loop"] is None and j["provenance"]["command"] == "track"
    assert all(v["cam1"]["median_snr"] > 10 for v in j["markers"].values())
    assert (out / "track.png").stat().st_size > 0 and (out / "overlay.png").stat().st_size > 0
    assert not (out / "markers3d.csv").exists()
    # the frame is a JPEG: its SNR and sd_px come from noise the codec partly removed
    assert [(w["code"], w["views"]) for w in j["warnings"]] == [("lossy-frames", {"cam1": "JPEG files"})]
    assert j["warnings"][0]["seeds"] and "give seeds" not in j["warnings"][0]["message"]
    # without seeds the warning adds that the codec's artefacts start tracks of their own
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "-o", str(tmp_path / "auto")])
    assert r.exit_code == 0, r.output
    w = [w for w in json.loads((tmp_path / "auto" / "track.json").read_text())["warnings"] if w["code"] == "lossy-frames"]
    assert len(w) == 1 and not w[0]["seeds"] and w[0]["message"].endswith("give seeds")


def test_cli_track_polarity_from_the_seeds(tmp_path):
    """The real X-ray frame inverted (a processed radiograph: beads bright) and tracked
    without --polarity: the seeds show bright markers, so they are tracked as bright, with a
    warning, at the centres of the frame as recorded (within 0.01 px; the Gaussian fit sees
    the same pixels mirrored in grey level).  As recorded, without --polarity: dark, no
    warning.  With --polarity dark on the inverted frame: the seeds find nothing, exit 1
    naming --polarity, nothing written."""
    import cv2
    seeds = _xray_seeds(tmp_path)
    img = cv2.imread(str(XRAY / "sample_frame.jpg"), cv2.IMREAD_GRAYSCALE)
    res = {}
    for name, im in (("raw", img), ("inverted", 255 - img)):
        d = tmp_path / name
        d.mkdir()
        cv2.imwrite(str(d / "frame.png"), im)
        out = tmp_path / f"out_{name}"
        r = CliRunner().invoke(cli, ["track", "--view", f"cam1={d}", "--diameter-px", "4", "--seeds", str(seeds),
                                     "-o", str(out)])
        assert r.exit_code == 0, r.output
        j = json.loads((out / "track.json").read_text())
        res[name] = pd.read_csv(out / "markers2d.csv").sort_values("marker")
        assert res[name]["found"].all()
        assert j["polarity"] == ("dark" if name == "raw" else "bright")
        assert j["polarity_source"].startswith("auto: from the seeds")
        assert ("bright-markers" in [w["code"] for w in j["warnings"]]) == (name == "inverted")
    e = np.hypot(res["raw"]["x_px"].to_numpy() - res["inverted"]["x_px"].to_numpy(),
                 res["raw"]["y_px"].to_numpy() - res["inverted"]["y_px"].to_numpy())
    assert e.max() < 0.01
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={tmp_path / 'inverted'}", "--diameter-px", "4",
                                 "--polarity", "dark", "--seeds", str(seeds), "-o", str(tmp_path / "out_dark")])
    assert r.exit_code == 1 and "--polarity" in r.output       # a ProcessingError: the seeds found nothing
    assert not (tmp_path / "out_dark").exists()


@pytest.mark.parametrize("bright", [False, True])
def test_cli_track_polarity_without_seeds(tmp_path, bright):
    """Automatic mode (no seeds) on five beads rendered dark (raw) and bright (inverted):
    the first frame's whole-frame detections of SNR 6 or more in each polarity decide, and
    every bead is tracked in every frame within 0.3 px either way."""
    n = 4
    frames, truth = _five_beads(tmp_path, 160, n, 5.0, (0.5, 0.3), seed=4, bright=bright)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--diameter-px", "5", "-o", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    assert j["polarity"] == ("bright" if bright else "dark") and j["polarity_source"].startswith("auto: no seeds")
    _assert_on_the_beads(out, truth, range(n))


def _five_beads(tmp_path, size: int, n: int, dia: float, step, *, seed: int, bright: bool = False,
                blank_first: bool = False):
    """Five beads of ``dia`` px moving ``step`` px a frame over ``n`` frames of ``size`` px
    (PNG files in ``tmp_path/frames``; frame 0 black with ``blank_first``); returns the
    folder and the true positions per frame."""
    import cv2
    rng = np.random.default_rng(seed)
    B = np.array([[0.25, 0.31], [0.69, 0.29], [0.5, 0.5], [0.32, 0.75], [0.75, 0.73]]) * size + [0.3, 0.2]
    field = RayField(bead_camera(size))
    frames = tmp_path / "frames"
    frames.mkdir()
    truth = [B + np.multiply(step, i) for i in range(n)]
    for i in range(n):
        img = render_beads(truth[i], dia, size, rng, field=field, bright=bright)
        cv2.imwrite(str(frames / f"f{i}.png"), np.zeros_like(img) if blank_first and i == 0 else img)
    return frames, truth


def _assert_on_the_beads(out, truth, frames) -> None:
    """Every bead found in each of ``frames`` (and no other), each within 0.3 px of a bead."""
    m2 = pd.read_csv(out / "markers2d.csv")
    m2 = m2[m2["found"]]
    assert sorted(set(m2["frame"])) == list(frames) and len(m2) == 5 * len(frames)
    for _, row in m2.iterrows():
        assert np.hypot(*(truth[row["frame"]] - [row["x_px"], row["y_px"]]).T).min() < 0.3


@pytest.mark.parametrize("seeded", [False, True])
def test_cli_track_blank_first_frame(tmp_path, seeded):
    """Five 9 px beads over six frames, the first frame black (the grabber started before
    the X-rays).  The polarity and the diameter had been probed on it: nothing found, so the
    4 px default, a third of the beads.  They are now probed on frame 1, a blank-first-frame
    warning says so, and every bead is tracked from frame 1 within 0.3 px.  Seeded, frame 0
    is also named by frames-without-markers (the seeds put every marker there)."""
    n, dia = 6, 9.0
    frames, truth = _five_beads(tmp_path, 200, n, dia, (0.6, 0.4), seed=7, blank_first=True)
    out = tmp_path / "out"
    args = ["track", "--view", f"cam1={frames}", "--fps", "2", "-o", str(out)]
    if seeded:
        seeds = tmp_path / "seeds.csv"
        pd.DataFrame([("cam1", f"M{j}", *truth[0][j]) for j in range(5)],
                     columns=["view", "marker", "x_px", "y_px"]).to_csv(seeds, index=False)
        args += ["--seeds", str(seeds)]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    w = {w["code"]: w for w in j["warnings"]}
    assert w["blank-first-frame"]["views"] == {"cam1": 1}
    assert 0.75 * dia < j["diameter_px"] < 1.25 * dia, j["diameter_source"]
    if seeded:
        assert w["frames-without-markers"]["frames"] == {"cam1": [0]}
    else:
        assert "frames-without-markers" not in w
    _assert_on_the_beads(out, truth, range(1, n))


@pytest.mark.parametrize("seeded", [True, False])
def test_cli_track_one_view_inverted(tmp_path, seeded):
    """Two views of five beads, the second view's video inverted (steel bright, as a C-arm set
    to show bone dark gives it): the views' seeds had found 5 dark and 5 bright markers, dark
    won the tie, and view b's first seed was found in no frame (exit 1; no single --polarity
    could do).  Each view now keeps the polarity its own seeds (or, without seeds, its own
    first frame) show clearly: both tracked, said in a bright-markers warning naming view b,
    ``polarity_per_view`` in track.json; a config's polarity per view is taken as given."""
    n = 5
    a, truth = _five_beads(tmp_path, 160, n, 4.0, (0.5, 0.3), seed=11)
    (tmp_path / "b").mkdir()
    b = tmp_path / "b" / "frames"
    b.mkdir()
    for f in sorted(a.iterdir()):
        cv2.imwrite(str(b / f.name), 255 - cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
    out = tmp_path / "out"
    args = ["track", "--view", f"a={a}", "--view", f"b={b}", "--fps", "2", "--diameter-px", "4", "-o", str(out)]
    if seeded:
        seeds = tmp_path / "seeds.csv"
        pd.DataFrame([(v, f"M{j}", *truth[0][j]) for v in ("a", "b") for j in range(5)],
                     columns=["view", "marker", "x_px", "y_px"]).to_csv(seeds, index=False)
        args += ["--seeds", str(seeds)]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    assert j["polarity"] == "per view" and j["polarity_per_view"] == {"a": "dark", "b": "bright"}
    w = {w["code"]: w for w in j["warnings"]}
    assert w["bright-markers"]["views"] == ["b"]
    m2 = pd.read_csv(out / "markers2d.csv")
    for v in ("a", "b"):
        got = m2[(m2["view"] == v) & m2["found"]]
        assert len(got) == 5 * n, (v, len(got))
        for _, row in got.iterrows():
            assert np.hypot(*(truth[row["frame"]] - [row["x_px"], row["y_px"]]).T).min() < 0.3
    # a polarity per view in a config: taken as given (here the right ones), every view named
    cfg = tmp_path / "track.yaml"
    cfg.write_text(f"views: {{a: {a}, b: {b}}}\nfps: 2\ndiameter_px: 4\npolarity: {{a: dark, b: bright}}\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "-o", str(tmp_path / "out2")])
    assert r.exit_code == 0, r.output
    j2 = json.loads((tmp_path / "out2" / "track.json").read_text())
    assert j2["polarity_per_view"] == {"a": "dark", "b": "bright"} and j2["polarity_source"] == "given"
    cfg.write_text(f"views: {{a: {a}, b: {b}}}\nfps: 2\npolarity: {{a: dark}}\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "-o", str(tmp_path / "out3")])
    assert r.exit_code == 2 and "polarity" in r.output and not (tmp_path / "out3").exists(), r.output


def test_view_polarities_keep_the_pooled_one_unless_a_view_says_clearly():
    from bsipipe.imaging.marker_size import view_polarities
    per = {"a": {"dark": 12, "bright": 0}, "b": {"dark": 0, "bright": 12}, "c": {"dark": 1, "bright": 1},
           "d": {"dark": 2, "bright": 1}, "e": {"dark": 0, "bright": 0}}
    assert view_polarities("dark", per, seeded=True) == {"a": "dark", "b": "bright", "c": "dark", "d": "dark",
                                                          "e": "dark"}
    # without seeds a view needs 3 strong markers of its polarity to keep its own
    per["f"] = {"dark": 0, "bright": 2}
    assert view_polarities("dark", per, seeded=False)["f"] == "dark"
    assert view_polarities("dark", per, seeded=True)["f"] == "bright"
    assert view_polarities("bright", {"g": {"dark": 1, "bright": 1}}, seeded=True) == {"g": "bright"}


def test_cli_track_polarity_given_without_seeds_is_checked(tmp_path):
    """The real X-ray frame (dark steel beads), three copies, no seeds: --polarity bright
    tracked the bright clutter around the beads without a word; it is now a
    polarity-mismatch warning naming the counts of the first frame's strong detections of
    each kind (35 dark against 8 bright here).  --polarity dark: no such warning."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        (frames / f"f{k}.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    for given in ("bright", "dark"):
        o = tmp_path / f"given_{given}"
        r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--diameter-px", "4", "--polarity", given,
                                     "-o", str(o)])
        assert r.exit_code == 0, r.output
        j = json.loads((o / "track.json").read_text())
        assert j["polarity"] == given and j["polarity_source"] == "given"
        w = [w for w in j["warnings"] if w["code"] == "polarity-mismatch"]
        if given == "dark":
            assert not w, w
        else:
            assert len(w) == 1 and w[0]["given"] == "bright" and w[0]["dark"] >= 3 * w[0]["bright"] >= 3, w
            assert "--polarity dark" in w[0]["message"]


def test_cli_track_xmalab_seeds_and_config(tmp_path):
    """Seeds straight from XMALab's 2-D CSV (camN = the N-th view), and the YAML form."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "f.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    cfg = tmp_path / "track.yaml"
    cfg.write_text(f"views:\n  cam1: frames\nseeds: {XRAY / 'sample_frame_input.csv'}\ndiameter_px: 4\nfigures: false\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    m2 = pd.read_csv(tmp_path / "out" / "markers2d.csv")
    assert set(m2["marker"]) >= {"F1", "TP", "EPa"} and m2["found"].all()


def test_cli_track_xmalab_seeds_placed_only_later_are_named(tmp_path):
    """An XMALab 2-D file whose TP and F1 points are empty in the first row and set in the
    second (clicked where they were visible): the seeds are the first frame's, so those two
    are not followed -- a seeds-after-first-frame warning names them with the frame where the
    file first places them; the other markers are tracked as from the whole file."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(2):
        (frames / f"f{k}.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    x = pd.read_csv(XRAY / "sample_frame_input.csv")
    row = x.iloc[[0]].copy()
    two = pd.concat([row, row], ignore_index=True)
    for c in ("TP_cam1_X", "TP_cam1_Y", "F1_cam1_X", "F1_cam1_Y"):
        two.loc[0, c] = np.nan
    seeds = tmp_path / "xma.csv"
    two.to_csv(seeds, index=False, na_rep="NaN")
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--seeds", str(seeds), "--diameter-px", "4",
                                 "-o", str(out)])
    assert r.exit_code == 0, r.output
    w = [w for w in json.loads((out / "track.json").read_text())["warnings"] if w["code"] == "seeds-after-first-frame"]
    assert len(w) == 1 and w[0]["markers"] == {"cam1": {"TP": 1, "F1": 1}}, w
    assert "TP (first at frame 1)" in w[0]["message"]
    m2 = pd.read_csv(out / "markers2d.csv")
    assert {"TP", "F1"}.isdisjoint(m2["marker"]) and {"EPa", "GHa"} <= set(m2["marker"])


@pytest.mark.parametrize("case", ["missing-view", "bad-seeds", "unknown-view-seed", "no-stereo", "bad-key"])
def test_cli_track_errors(tmp_path, case):
    """Bad input exits 2 with one message naming the file (and line), no traceback, no result."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "f.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    out = tmp_path / "out"
    args = ["track", "--view", f"cam1={frames}", "-o", str(out)]
    expect = None
    if case == "missing-view":
        args[2] = f"cam1={tmp_path / 'nope'}"
        expect = "nope"
    elif case == "bad-seeds":
        p = tmp_path / "seeds.csv"
        p.write_text("view,marker,x_px,y_px\ncam1,A,10,20\ncam1,B,abc,3\n")
        args += ["--seeds", str(p)]
        expect = "line 3"
    elif case == "unknown-view-seed":
        p = tmp_path / "seeds.csv"
        p.write_text("view,marker,x_px,y_px\ncam9,A,10,20\n")
        args += ["--seeds", str(p)]
        expect = "cam9"
    elif case == "no-stereo":
        p = tmp_path / "cal.json"
        p.write_text(json.dumps({"views": {}}))
        args += ["--calibration", str(p)]
        expect = "stereo"
    elif case == "bad-key":
        cfg = tmp_path / "t.yaml"
        cfg.write_text("views:\n  cam1: frames\nspeed: 3\n")
        args = ["track", str(cfg), "-o", str(out)]
        expect = "speed"
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2, r.output
    assert expect in r.output and "Traceback" not in r.output
    assert not (out / "track.json").exists()


# --- XMALab files -----------------------------------------------------------------------------------

def test_xmalab_2d_3d_round_trip(tmp_path):
    pts = pd.DataFrame({"view": ["left", "left", "right", "right", "left"], "frame": [0, 1, 0, 1, 2],
                        "marker": ["A", "A", "A", "A", "B"], "x_px": [1.5, 2.25, 3.0, np.nan, 7.0],
                        "y_px": [4.0, 5.0, 6.0, 1.0, 8.0]})
    text = format_xmalab_2d(pts, ["left", "right"])
    assert text.splitlines()[0] == "A_cam1_X,A_cam1_Y,A_cam2_X,A_cam2_Y,B_cam1_X,B_cam1_Y,B_cam2_X,B_cam2_Y"
    assert text.splitlines()[2].split(",")[2:4] == ["NaN", "NaN"]      # a point missing in one axis is missing
    p = tmp_path / "x2.csv"
    p.write_text(text)
    assert is_xmalab_2d(p)
    back = read_xmalab_2d(p)
    a = back[(back["marker"] == "A") & (back["view"] == "cam1")]
    assert np.allclose(a["x_px"], [1.5, 2.25, np.nan], equal_nan=True)
    p3 = tmp_path / "x3.csv"
    p3.write_text(format_xmalab_3d(pd.DataFrame({"frame": [0, 2], "marker": ["A", "A"], "x_mm": [1.0, 2.0],
                                                 "y_mm": [3.0, np.nan], "z_mm": [5.0, 6.0]})))
    assert p3.read_text().splitlines()[0] == "A_X,A_Y,A_Z"
    b3 = read_xmalab_3d(p3)
    assert np.isnan(b3["x_mm"].iloc[1]) and np.isnan(b3["x_mm"].iloc[2]) and b3["z_mm"].iloc[0] == 5.0
    # XMALab's own spacing (" , ") and the reference files read too
    (tmp_path / "sp.csv").write_text("A_cam1_X , A_cam1_Y\n1.5 , NaN\n")
    assert read_xmalab_2d(tmp_path / "sp.csv")["x_px"].isna().all()
    ref = read_xmalab_2d(XRAY / "sample_frame_input.csv")
    assert set(ref["view"]) == {"cam1", "cam2"} and ref["marker"].nunique() == 24


def test_cli_track_trackpy_parity_mode(tmp_path):
    """``detection: {method: centroid, parity: trackpy}`` without seeds (and every track kept,
    however short): every frame is
    detected as ``trackpy.locate(green, 11, invert=True, minmass=20)`` detects it (trackpy's
    stored features of frames 0-2, ``trackpy_features_30.csv``), at least 95 % of them within
    0.5 px; with seeds the mode is refused (exit 2): search windows are not trackpy's."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        (frames / f"bulk_water_{i:03d}.png").write_bytes((WATER / f"bulk_water_{i:03d}.png").read_bytes())
    cfg = tmp_path / "track.yaml"
    cfg.write_text("views: {cam1: frames}\ndiameter_px: 11\nchannel: 1\nfigures: false\nfps: 1\n"
                   "detection: {method: centroid, parity: trackpy, minmass: 20, roi: none}\n"
                   "tracking: {min_track_frames: 1}\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    m2 = pd.read_csv(tmp_path / "out" / "markers2d.csv")
    ref = pd.read_csv(WATER / "trackpy_features_30.csv")
    from scipy.spatial import cKDTree
    for f in range(3):
        ours = m2[(m2["frame"] == f) & m2["found"]][["x_px", "y_px"]].to_numpy()
        theirs = ref[ref["frame"] == f][["x", "y"]].to_numpy()
        d, _ = cKDTree(ours).query(theirs)
        print(f"frame {f}: trackpy {len(theirs)} features, ours {len(ours)}, within 0.5 px {np.mean(d < 0.5):.3f}")
        assert np.mean(d < 0.5) >= 0.95
    seeds = tmp_path / "seeds.csv"
    seeds.write_text(f"view,marker,x_px,y_px\ncam1,A,{ref['x'][0]},{ref['y'][0]}\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "--seeds", str(seeds), "-o", str(tmp_path / "out2")])
    assert r.exit_code == 2 and "parity" in r.output


def test_cli_parity_flag_reproduces_trackpy_frame29(tmp_path):
    """The command-line form of the parity mode, ``--parity trackpy --minmass 20`` (the method
    follows: trackpy's centroid), on frames 27-29 of the real microscopy: frame 29 holds
    every one of trackpy's 599 features (``locate(green, 11, invert=True, minmass=20)``,
    live when trackpy is installed) to rounding, nothing else.  Given with another method,
    or with a diameter trackpy would refuse (even), the flag is an error (exit 2).  The
    config only turns the figures off and keeps one-frame tracks (a feature seen in frame 29
    alone is still trackpy's feature)."""
    from test_detect import trackpy_frame29
    from scipy.spatial import cKDTree
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in (27, 28, 29):
        (frames / f"bulk_water_{i:03d}.png").write_bytes((WATER / f"bulk_water_{i:03d}.png").read_bytes())
    cfg = tmp_path / "quiet.yaml"
    cfg.write_text("views: {water: frames}\nfigures: false\ntracking: {min_track_frames: 1}\n")
    args = ["track", str(cfg), "--channel", "1", "--diameter-px", "11", "--parity", "trackpy", "--minmass", "20"]
    r = CliRunner().invoke(cli, args + ["-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    j = json.loads((tmp_path / "out" / "track.json").read_text())
    assert j["provenance"]["config"]["detection"]["method"] == "centroid"
    assert j["provenance"]["config"]["detection"]["parity"] == "trackpy"
    m2 = pd.read_csv(tmp_path / "out" / "markers2d.csv")
    ours = m2[(m2["frame"] == 2) & m2["found"]][["x_px", "y_px"]].to_numpy()
    f, _, how = trackpy_frame29()
    theirs = f[["x", "y"]].to_numpy()
    d, _ = cKDTree(ours).query(theirs)
    print(f"trackpy {how}: {len(theirs)} features in frame 29; --parity trackpy: {len(ours)}, within 0.5 px "
          f"{np.mean(d < 0.5):.3f}, max distance {d.max():.2g} px")
    assert np.mean(d < 0.5) >= 0.95
    assert d.max() < 1e-5 and len(ours) == len(theirs)          # markers2d.csv keeps 6 decimals
    for extra, word in ((["--method", "gaussian"], "centroid"), (["--diameter-px", "10"], "odd")):
        r = CliRunner().invoke(cli, args + extra + ["-o", str(tmp_path / "bad")])
        assert r.exit_code == 2 and word in r.output, r.output
        assert not (tmp_path / "bad" / "track.json").exists()


def test_cli_parity_and_trackpy_linking_30_frames(tmp_path):
    """The whole trackpy workflow from the command line: ``--parity trackpy --minmass 20`` on
    the 30 frames of real microscopy, linked with trackpy's rule and numbers (``tracking:
    {gate_px: 5, gate_growth_px: 0, motion: static, memory: 3, min_track_frames: 1}`` =
    ``link(search_range=5, memory=3)``, every trajectory kept), gives trackpy's features of
    every frame and every one of its links, no others (trackpy's stored ``batch`` features
    and their ``link``, live when trackpy is installed)."""
    cfg = tmp_path / "trackpy.yaml"
    cfg.write_text(f"views: {{water: {WATER}}}\nfigures: false\n"
                   "tracking: {gate_px: 5, gate_growth_px: 0, motion: static, memory: 3, min_track_frames: 1}\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "--channel", "1", "--diameter-px", "11", "--parity", "trackpy",
                                 "--minmass", "20", "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    feats, linked = trackpy_30()
    m2 = pd.read_csv(tmp_path / "out" / "markers2d.csv")
    m2 = m2[m2["found"]]
    ours, theirs = _links(m2.assign(particle=m2["marker"]), "x_px", "y_px"), _links(linked)
    print(f"trackpy: {len(feats)} features, {linked['particle'].nunique()} trajectories, {len(theirs)} links; "
          f"bsipipe track: {len(m2)} positions, {m2['marker'].nunique()} tracks, {len(ours & theirs)} common links, "
          f"{len(ours - theirs)} others")
    assert len(m2) == len(feats) and m2["marker"].nunique() == linked["particle"].nunique()
    assert ours == theirs


def _faint_bead_sequence(seed: int, n: int = 60, size: int = 128, quanta_per_px: float = 120.0):
    """A 2.6 px bead drifting 0.5 px per frame on a flat background at a quarter of the
    default X-ray dose (amplitude SNR about 4-6): near the window threshold, as the deep
    0.5 mm markers are."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    M = np.column_stack([50 + 0.4 * t, 60 + 0.3 * t])
    field = RayField(bead_camera(size))
    frames = [np.clip(np.rint(render_beads(M[i:i + 1], 2.6, size, rng, field=field, quanta_per_px=quanta_per_px,
                                           quantize=False)), 0, 255).astype(np.uint8) for i in range(n)]
    return frames, M


def _track_faint(frames, M, **settings):
    """The faint bead tracked from its first position with these tracker settings: the table,
    each frame's centre error and which frames were found (none of them off the bead)."""
    s = track_view(frames, {"M": M[0]}, 4.0, "dark", roi="none",
                   settings=TrackSettings(**settings)).table.sort_values("frame")
    e = np.hypot(s["x_px"] - M[:, 0], s["y_px"] - M[:, 1]).to_numpy()
    ok = s["found"].to_numpy()
    assert (e[ok] < 1.0).all()                     # nothing off the bead
    return s, e, ok


def test_automatic_mode_finds_markers_too_faint_for_one_frame(tmp_path):
    """Without seeds: two 4 px beads and three 2.6 px ones at a dose that puts the small ones
    below the whole-frame search's threshold in single frames (amplitude SNR about 3).  The
    sweeps had found the two large ones only, unsaid.  The average of the first 8 frames shows
    the small ones (SNR 8 or more there); they are tracked from there as seeds, in a second pass,
    every position found on its bead, and a faint-markers warning says so."""
    import bsipipe.imaging.track as T
    rng = np.random.default_rng(0)
    n, size = 30, 160
    big = np.array([[40.0, 40.0], [120.0, 45.0]])
    faint = np.array([[50.0, 110.0], [100.0, 100.0], [80.0, 70.0]])
    field = RayField(bead_camera(size))
    frames, truth = [], []
    for i in range(n):
        b, f = big + [0.2 * i, 0.1 * i], faint + [0.08 * i, -0.05 * i]
        img = (render_beads(b, 4.0, size, None, field=field, noise=False, quantize=False)
               + render_beads(f, 2.6, size, None, field=field, noise=False, quantize=False))
        img = img - np.median(img) + 150.0
        frames.append(np.clip(np.rint(img + rng.normal(0, 5.5, img.shape)), 0, 255).astype(np.uint8))
        truth.append(np.vstack([b, f]))
    a = tmp_path / "frames"
    a.mkdir()
    for i, im in enumerate(frames):
        cv2.imwrite(str(a / f"f{i:03d}.png"), im)
    before = track_view(frames, None, 4.0, "dark", roi="none", settings=TrackSettings())
    assert before.table["marker"].nunique() == 2 and len(before.faint) >= 2
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={a}", "--fps", "2", "--diameter-px", "4", "--polarity",
                                 "dark", "-o", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    w = {w["code"]: w for w in j["warnings"]}
    added = w["faint-markers"]["markers"]["cam1"]
    assert len(added) >= 2 and all(sp["snr_average"] >= T.FAINT_MIN_SNR for sp in added.values())
    m2 = pd.read_csv(out / "markers2d.csv")
    got = m2[m2["found"]]
    assert got["marker"].nunique() >= 4
    # every position on a bead: within 1.5 px (a 2.6 px bead's radius) at SNR 3, 0.5 px RMS
    on = np.array([np.hypot(*(truth[r.frame] - [r.x_px, r.y_px]).T).min() for r in got.itertuples()])
    assert on.max() < 1.5 and np.sqrt(np.mean(on ** 2)) < 0.5
    faint_rows = got[got["marker"].isin(list(added))]
    near_faint = np.array([np.hypot(*(truth[r.frame][2:] - [r.x_px, r.y_px]).T).min()
                           for r in faint_rows.itertuples()])
    assert len(faint_rows) >= 0.5 * n * len(added) and near_faint.max() < 1.5
    print(f"faint beads: {len(faint_rows)} positions of {n * len(added)}, error RMS "
          f"{np.sqrt(np.mean(near_faint ** 2)):.2f} px (max {near_faint.max():.2f})")


def test_second_look_finds_faint_marker_near_its_prediction():
    """A marker the window threshold misses in some frames is found there by the second look
    (a lower threshold within a pixel of its prediction, the marker's own amplitude and
    width as the test): more frames found, every one of them on the bead, the added ones
    marked ``weak``; without the second look those frames are lost."""
    found = {None: 0, 2.5: 0}
    weak_err = []
    for seed in range(3):
        frames, M = _faint_bead_sequence(seed)
        for k in found:
            s, e, ok = _track_faint(frames, M, second_look_k_sigma=k)
            found[k] += int(ok.sum())
            weak = (s["status"] == "weak").to_numpy()
            if k is None:
                assert not weak.any()
            else:
                assert weak.any() and ok[weak].all()
                weak_err.extend(e[weak])
    print(f"frames found of 180: without the second look {found[None]}, with {found[2.5]}; weak finds' error "
          f"RMS {np.sqrt(np.mean(np.square(weak_err))):.3f} px (max {np.max(weak_err):.3f})")
    assert found[2.5] >= found[None] + 10
    assert np.sqrt(np.mean(np.square(weak_err))) < 0.5


def test_assignment_may_leave_a_hidden_marker_unmatched():
    """The situation that swapped two markers on compressed (MP4) frames: A is tracked (gate
    7 px) and finds its bead 0.45 px from its prediction (c1) and a partial blob 5 px away
    (c2); B, hidden for a while, has a gate grown to 19 px that reaches c1 (15 px) and C's
    bead (c3, 17.8 px); C finds c3 at 0.3 px.  When every marker must take a candidate, the
    cheapest complete matching gives c1 to B and the blob to A: a swap.  With the option to
    stay unmatched (at the cost of a match at the gate's edge) A keeps c1 and B stays lost."""
    from bsipipe.imaging.track import _assign, _Marker
    ms = [_Marker(n, np.zeros(2), 0) for n in "ABC"]
    pred = np.array([[491.91, 508.90], [492.52, 493.84], [478.2, 504.4]])
    gates = np.array([7.15, 19.08, 7.15])
    cand = np.array([[492.35, 508.83], [492.95, 503.84], [478.02, 504.17]])
    compat = np.array([[True, True, False], [True, False, True], [False, False, True]])
    forced, _ = _assign(ms, pred, gates, cand, compat)
    free, _ = _assign(ms, pred, gates, cand, compat, miss_cost=1.0)
    assert forced.tolist() == [1, 0, 2]                 # the swap
    assert free.tolist() == [0, -1, 2]


def test_marker_found_again_must_look_whole():
    """A marker being found again after a gap takes only a candidate of at least
    ``partial_fraction`` of its median amplitude; one tracked without a gap may take a
    partial one (it is passing behind something)."""
    from bsipipe.imaging.track import _looks_like, _Marker
    tracked, hidden = _Marker("T", np.zeros(2), 0), _Marker("H", np.zeros(2), 0)
    for m in (tracked, hidden):
        for f in range(1, 4):
            m.update(f, np.zeros(2), 10.0, 1.0)
    hidden.lost_since = 4
    amp = np.array([4.0, 8.0])              # a partial candidate (0.4 of the median) and a whole one
    ok = _looks_like([tracked, hidden], amp, np.array([1.0, 1.0]), TrackSettings(),
                     whole=[m.lost_since is not None for m in (tracked, hidden)])
    assert ok.tolist() == [[True, True], [False, True]]


def test_second_look_takes_a_faint_marker_below_the_detector_snr():
    """At two thirds of the dose of the test above (amplitude SNR about 3-4, as the deep markers in a
    noisier recording) the second look keeps the candidates of SNR 2-3 near the marker's
    prediction that pass its appearance test (``second_look_min_snr``): more frames found
    than with the detector's own ``min_snr`` of 3, and none of them off the bead."""
    found = {3.0: 0, 2.0: 0}
    for seed in range(4):
        frames, M = _faint_bead_sequence(seed, quanta_per_px=80.0)
        for k in found:
            found[k] += int(_track_faint(frames, M, second_look_min_snr=k)[2].sum())
    print(f"frames found of 240 at SNR 3-4: second look at min SNR 3 {found[3.0]}, at 2 {found[2.0]}")
    assert found[2.0] >= found[3.0] + 10


def _rod_sequence(n: int = 80, size: int = 160, seed: int = 3, levels=(140.0, 35.0, 40.0, 30.0, 2.0),
                  dtype=np.uint8):
    """A bead moving right at 1 px per frame passes behind an opaque rod (x 80-92, blurred
    edges) from frame 40 to 56 and comes out on the other side; inside the rod, 10 px ahead
    of where the bead vanished and on its path, a bead-sized dip (rod texture, a hole).
    ``levels``: background, rod, the bead's depth, the dip's depth, noise sd (default a raw
    8-bit frame: the rod a quarter of the background's brightness, the dip 3/4 of the bead's
    depth)."""
    bg, rod_level, amp, dip, sd = levels
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size].astype(float)
    rod = (xx >= 80) & (xx <= 92) & (yy <= 110)
    base = np.where(rod, rod_level, bg)
    base = cv2.GaussianBlur(base, (0, 0), 1.0)
    spot = dip * np.exp(-((xx - 88.0) ** 2 + (yy - 90.4) ** 2) / (2 * 1.4 ** 2))
    t = np.arange(n, dtype=float)
    M = np.column_stack([38 + 1.0 * t, 90 + 0.0 * t])
    hidden = (M[:, 0] > 77) & (M[:, 0] < 95)
    frames = []
    top = np.iinfo(dtype).max
    for i in range(n):
        img = base - spot
        if not hidden[i]:
            img = img - amp * np.exp(-((xx - M[i, 0]) ** 2 + (yy - M[i, 1]) ** 2) / (2 * 1.4 ** 2))
        frames.append(np.clip(np.rint(img + rng.normal(0, sd, img.shape)), 0, top).astype(dtype))
    return frames, M, hidden


@pytest.mark.parametrize("kw", [{}, {"levels": (40000.0, 30000.0, 1500.0, 1500.0, 150.0), "dtype": np.uint16}],
                         ids=["raw", "log"])
def test_lost_marker_is_not_found_again_inside_a_dark_object(kw):
    """A marker lost behind an instrument is not found again on a bead-like dip inside the
    instrument's shadow while its gate grows along its predicted path (the dip lies on that
    path): no position of it inside the rod, and it is found again on the bead after it comes
    out.  Without the rule (the dark-object test patched out) the dip is taken for it.  Raw
    8-bit frames (the rod a quarter of the background), and 16-bit log-converted ones, where
    the rod is 3/4 of the background's level (not darker than half) but 6.7 times deeper than
    the bead."""
    import bsipipe.imaging.track as T
    frames, M, hidden = _rod_sequence(**kw)

    def run():
        s = track_view(frames, {"M": M[0]}, 4.0, "dark", roi="none").table.sort_values("frame")
        return s, np.hypot(s["x_px"] - M[:, 0], s["y_px"] - M[:, 1]).to_numpy(), s["found"].to_numpy()

    s, e, ok = run()
    assert not ok[hidden].any()
    back = np.flatnonzero(ok & ~hidden & (np.arange(len(M)) > np.flatnonzero(hidden).max()))
    assert len(back) and back[0] <= np.flatnonzero(hidden).max() + 3
    assert (e[ok] < 1.0).all()
    orig = T._not_in_objects
    try:
        T._not_in_objects = lambda *a, **k: None
        s0, _, ok0 = run()
    finally:
        T._not_in_objects = orig
    on_dip = np.hypot(s0["x_px"] - 88.0, s0["y_px"] - 90.4).to_numpy() < 1.0
    assert ok0[hidden].sum() >= 5 and on_dip[ok0 & hidden].all()
    print(f"positions found inside the rod: {int(ok0[hidden].sum())} without the rule, {int(ok[hidden].sum())} with")


def _track_clicked(tmp_path, images, names, xy):
    """``bsipipe track`` on one view of these frames (8-bit PNG files) from seeds clicked
    (0.8, -0.6) px off ``xy``, no diameter given; returns track.json and markers2d.csv."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, img in enumerate(images):
        cv2.imwrite(str(frames / f"f{i}.png"), np.clip(np.rint(img), 0, 255).astype(np.uint8))
    seeds = tmp_path / "seeds.csv"
    pd.DataFrame({"view": "cam1", "marker": names, "x_px": xy[:, 0] + 0.8, "y_px": xy[:, 1] - 0.6}).to_csv(
        seeds, index=False)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--seeds", str(seeds), "-o", str(out)])
    assert r.exit_code == 0, r.output
    return json.loads((out / "track.json").read_text()), pd.read_csv(out / "markers2d.csv")


def test_cli_track_markers_of_two_sizes_without_a_diameter(tmp_path):
    """Seeds on beads of two sizes (four 5 px ones, three 10 px ones, as deep beads and
    larger reference markers at a higher magnification) and no --diameter-px: the diameter
    from the median of the seeds' fitted widths (the small beads') finds none of the large
    ones, so they are looked for at larger diameters and the diameter they give, which still
    finds the small ones, is taken: every marker found in every frame, within 0.3 px."""
    rng = np.random.default_rng(2)
    size = 200
    small = np.array([[50.3, 60.7], [140.2, 55.1], [60.6, 140.4], [100.5, 100.2]])
    large = np.array([[150.4, 140.6], [40.2, 100.8], [105.7, 160.3]])
    field = RayField(bead_camera(size))
    base_s = render_beads(small, 5.0, size, None, field=field, noise=False, quantize=False)
    base_l = render_beads(large, 10.0, size, None, field=field, noise=False, quantize=False)
    truth = np.vstack([small, large])
    names = [f"S{k}" for k in range(len(small))] + [f"L{k}" for k in range(len(large))]
    j, m2 = _track_clicked(tmp_path, [base_s + base_l - np.median(base_l) + rng.normal(0, 1.7, base_s.shape)
                                      for _ in range(3)], names, truth)
    assert "from the 3 larger ones, finds 7" in j["diameter_source"], j["diameter_source"]
    assert m2["found"].all() and len(m2) == 21
    t = dict(zip(names, truth))
    e = np.hypot(m2["x_px"] - [t[m][0] for m in m2["marker"]], m2["y_px"] - [t[m][1] for m in m2["marker"]])
    print(f"diameter {j['diameter_px']:.2f} px ({j['diameter_source']}); centre error max {e.max():.3f} px")
    assert e.max() < 0.3


def test_cli_track_one_stray_find_does_not_set_the_diameter(tmp_path):
    """Eight 5 px beads seeded; in the first frame (as a lossy codec's key frame) three of
    them are erased and one is smeared into a 10 px blob.  The larger diameters find the blob
    only, one of the four seeds missed, so the diameter stays the beads' (taken from the blob,
    as before, it was ~9 px) and every bead is found within 0.3 px in the later frames."""
    rng = np.random.default_rng(3)
    size = 200
    beads = np.array([[50.3, 60.7], [140.2, 55.1], [60.6, 140.4], [100.5, 100.2],
                      [150.4, 140.6], [40.2, 100.8], [105.7, 160.3], [160.1, 95.4]])
    field = RayField(bead_camera(size))
    first = render_beads(beads[:4], 5.0, size, None, field=field, noise=False, quantize=False)
    blob = render_beads(beads[4:5], 10.0, size, None, field=field, noise=False, quantize=False)
    first = first + blob - np.median(blob)
    later = render_beads(beads, 5.0, size, None, field=field, noise=False, quantize=False)
    names = [f"S{k}" for k in range(len(beads))]
    j, m2 = _track_clicked(tmp_path, [(first if i == 0 else later) + rng.normal(0, 1.7, later.shape)
                                      for i in range(5)], names, beads)
    print(f"diameter {j['diameter_px']:.2f} px ({j['diameter_source']})")
    assert "larger ones" not in j["diameter_source"], j["diameter_source"]
    assert 4.0 < j["diameter_px"] < 6.5
    s = m2[m2["frame"] > 0]
    assert s["found"].all() and len(s) == 32
    t = dict(zip(names, beads))
    e = np.hypot(s["x_px"] - [t[m][0] for m in s["marker"]], s["y_px"] - [t[m][1] for m in s["marker"]])
    print(f"centre error max {e.max():.3f} px")
    assert e.max() < 0.3


def test_a_bead_another_marker_just_held_is_not_free_for_a_long_lost_one():
    """A is tracked on its bead; B (a wider bead 12 px away) vanishes after frame 9, and its
    gate grows over A's bead.  For three frames noise widens A's bead beyond A's own width
    test (as anti-scatter grid stripes did on the bench twin), though not beyond B's.  Without
    the rule B takes A's bead in those frames and then keeps it, 12 px from where B was; with
    it the bead stays A's (A lost for those frames only) and B is never found again."""
    rng = np.random.default_rng(5)
    size = 128
    yy, xx = np.mgrid[:size, :size].astype(float)

    def spot(x, y, sigma, depth=30.0):
        return depth * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma ** 2))

    A, B = (50.3, 60.2), (62.4, 60.5)
    frames = []
    for k in range(50):
        img = 120.0 - spot(*A, 1.75 if 30 <= k <= 32 else 1.0)
        if k < 10:
            img -= spot(*B, 1.3)
        frames.append(np.clip(np.rint(img + rng.normal(0, 1.5, img.shape)), 0, 255).astype(np.uint8))
    r = track_view(frames, {"A": A, "B": B}, 4.0)
    t = r.table.set_index(["marker", "frame"])
    b_late = t.loc["B"].loc[10:]
    a = t.loc["A"]
    print(f"B found after it vanished: {int(b_late['found'].sum())} frames; A found {int(a['found'].sum())} of 50")
    assert not b_late["found"].any()
    assert a["found"].drop(index=[30, 31, 32]).all()
    e = np.hypot(a["x_px"] - A[0], a["y_px"] - A[1])[a["found"].to_numpy(bool)]
    assert e.max() < 0.5


def test_cli_track_views_at_different_magnifications_get_their_own_diameter(tmp_path):
    """The same five beads seen 5 px across in one view and 9 px in the other (C-arms at
    different magnifications), seeds in both, no --diameter-px: each view's diameter is
    estimated from its own seeds (they differ by more than 25 %) and every bead is found
    within 0.3 px in both views (with one diameter for both, the larger view's beads were
    measured with a top-hat sized for the smaller)."""
    rng = np.random.default_rng(8)
    size = 200
    beads = np.array([[50.3, 60.7], [140.2, 55.1], [60.6, 140.4], [100.5, 100.2], [150.4, 140.6]])
    field = RayField(bead_camera(size))
    seeds, truth = [], {}
    for v, dia in (("cam1", 5.0), ("cam2", 9.0)):
        base = render_beads(beads, dia, size, None, field=field, noise=False, quantize=False)
        d = tmp_path / v
        d.mkdir()
        for i in range(3):
            cv2.imwrite(str(d / f"f{i}.png"),
                        np.clip(np.rint(base + rng.normal(0, 1.7, base.shape)), 0, 255).astype(np.uint8))
        for k, (x, y) in enumerate(beads):
            seeds.append({"view": v, "marker": f"B{k}", "x_px": x + 0.8, "y_px": y - 0.6})
            truth[(v, f"B{k}")] = (x, y)
    pd.DataFrame(seeds).to_csv(tmp_path / "seeds.csv", index=False)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={tmp_path / 'cam1'}", "--view", f"cam2={tmp_path / 'cam2'}",
                                 "--seeds", str(tmp_path / "seeds.csv"), "-o", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    dv = j["diameter_px_per_view"]
    print(f"diameters {dv} ({j['diameter_source']})")
    assert dv["cam2"] > 1.25 * dv["cam1"]
    m2 = pd.read_csv(out / "markers2d.csv")
    assert m2["found"].all() and len(m2) == 30
    e = np.hypot(*(m2[["x_px", "y_px"]].to_numpy() - np.array([truth[(v, m)] for v, m in zip(m2["view"], m2["marker"])])).T)
    print(f"centre error max {e.max():.3f} px")
    assert e.max() < 0.3


def test_cli_track_one_marker_seeded_twice_is_named(tmp_path):
    """The real X-ray frame's TP seeded a second time, 0.3 px off, as "TP2": the run ends as
    before (one of the two "was not found in any frame": the bead goes to the other), but a
    seeds-together warning comes first and the error says why."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "f.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    s = pd.read_csv(_xray_seeds(tmp_path))
    tp = s[s["marker"] == "TP"].copy()
    tp["marker"], tp["x_px"] = "TP2", tp["x_px"] + 0.3
    pd.concat([s, tp]).to_csv(tmp_path / "seeds2.csv", index=False)
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--seeds", str(tmp_path / "seeds2.csv"),
                                 "--diameter-px", "4", "-o", str(tmp_path / "out")])
    assert r.exit_code == 1, r.output
    assert "seeds within half a marker diameter" in r.output and "TP and TP2 in cam1, 0.3 px" in r.output
    assert ("within half a diameter of the seed of 'TP': one marker seeded twice" in r.output
            or "within half a diameter of the seed of 'TP2': one marker seeded twice" in r.output), r.output


def test_config_gives_a_diameter_per_view(tmp_path):
    """``diameter_px: {cam1: 5, cam2: 9}`` in a track config: each view tracked at its own
    diameter (track.json ``diameter_px_per_view``, source "given per view"), every bead within
    0.3 px; a per-view diameter that leaves out a view is refused naming the key (exit 2)."""
    rng = np.random.default_rng(9)
    size = 200
    beads = np.array([[50.3, 60.7], [140.2, 55.1], [60.6, 140.4], [100.5, 100.2], [150.4, 140.6]])
    field = RayField(bead_camera(size))
    seeds = []
    for v, dia in (("cam1", 5.0), ("cam2", 9.0)):
        base = render_beads(beads, dia, size, None, field=field, noise=False, quantize=False)
        (tmp_path / v).mkdir()
        for i in range(2):
            cv2.imwrite(str(tmp_path / v / f"f{i}.png"),
                        np.clip(np.rint(base + rng.normal(0, 1.7, base.shape)), 0, 255).astype(np.uint8))
        seeds += [{"view": v, "marker": f"B{k}", "x_px": x + 0.8, "y_px": y - 0.6} for k, (x, y) in enumerate(beads)]
    pd.DataFrame(seeds).to_csv(tmp_path / "seeds.csv", index=False)
    cfg = tmp_path / "track.yaml"
    cfg.write_text("views: {cam1: cam1, cam2: cam2}\nseeds: seeds.csv\ndiameter_px: {cam1: 5, cam2: 9}\nfigures: false\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    j = json.loads((tmp_path / "out" / "track.json").read_text())
    assert j["diameter_px_per_view"] == {"cam1": 5.0, "cam2": 9.0} and j["diameter_source"] == "given per view"
    m2 = pd.read_csv(tmp_path / "out" / "markers2d.csv")
    assert m2["found"].all() and len(m2) == 20
    t = dict(zip([f"B{k}" for k in range(len(beads))], beads))
    e = np.hypot(m2["x_px"] - [t[m][0] for m in m2["marker"]], m2["y_px"] - [t[m][1] for m in m2["marker"]])
    assert e.max() < 0.3
    cfg.write_text("views: {cam1: cam1, cam2: cam2}\nseeds: seeds.csv\ndiameter_px: {cam1: 5}\n")
    r = CliRunner().invoke(cli, ["track", str(cfg), "-o", str(tmp_path / "bad")])
    assert r.exit_code == 2 and "diameter_px" in r.output and not (tmp_path / "bad").exists(), r.output
    # the same on the command line: --diameter-px NAME=D per view, the same tracks
    args = ["track", "--view", f"cam1={tmp_path / 'cam1'}", "--view", f"cam2={tmp_path / 'cam2'}", "--seeds",
            str(tmp_path / "seeds.csv")]
    r = CliRunner().invoke(cli, [*args, "--diameter-px", "cam1=5", "--diameter-px", "cam2=9", "-o",
                                 str(tmp_path / "cli")])
    assert r.exit_code == 0, r.output
    j = json.loads((tmp_path / "cli" / "track.json").read_text())
    assert j["diameter_px_per_view"] == {"cam1": 5.0, "cam2": 9.0} and j["diameter_source"] == "given per view"
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "cli" / "markers2d.csv"), m2)
    # bad values: exit 2 naming the option, nothing written
    for bad, word in ((["cam1=5"], "every view"), (["cam1=5", "cam1=6"], "given twice"), (["4", "cam2=9"], "not both"),
                      (["cam1=-1", "cam2=9"], "positive number"),
                      (["wide"], "positive number"), (["=5", "cam2=9"], "NAME=D")):
        out = tmp_path / f"bad{len(word)}{len(bad)}"
        r = CliRunner().invoke(cli, [*args, *[a for b in bad for a in ("--diameter-px", b)], "-o", str(out)])
        assert r.exit_code == 2 and word in r.output and "diameter" in r.output and not out.exists(), (bad, r.output)


@pytest.mark.parametrize("dia,bright", [(9.0, False), (14.0, False), (9.0, True)])
def test_cli_track_without_seeds_or_diameter_finds_large_beads(tmp_path, dia, bright):
    """No seeds and no --diameter-px, beads 9 or 14 px across (dark, or bright as in an
    inverted export): the default 4 px top-hat finds none of them (the command used to stop:
    "no marker was found in any frame"), so the polarity and the diameter are looked for at
    8 and 16 px as well, the diameter taken from what they find; every bead in every frame
    within 0.3 px."""
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(8)
    size = 200
    beads = np.array([[50.3, 60.7], [140.2, 55.1], [60.6, 140.4], [100.5, 100.2], [150.4, 140.6]])
    base = render_beads(beads, dia, size, None, field=RayField(bead_camera(size)), noise=False, quantize=False)
    frames = tmp_path / "cam1"
    frames.mkdir()
    for i in range(3):
        img = np.clip(np.rint(base + rng.normal(0, 1.7, base.shape)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(frames / f"f{i}.png"), 255 - img if bright else img)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "-o", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    print(f"{dia:g} px {'bright' if bright else 'dark'} beads: diameter {j['diameter_px']:.2f} px "
          f"({j['diameter_source']}); {j['polarity']} ({j['polarity_source']})")
    assert "estimated without seeds" in j["diameter_source"]
    assert j["polarity"] == ("bright" if bright else "dark")
    m2 = pd.read_csv(out / "markers2d.csv")
    assert m2["marker"].nunique() == 5 and m2["found"].all() and len(m2) == 15
    assert cKDTree(beads).query(m2[["x_px", "y_px"]].to_numpy())[0].max() < 0.3


def _roi_views(tmp_path, n_frames=12, moving=None, seed=11):
    """Two views of five dark beads (5 px) on 200 px frames, pixel noise 1.7; ``moving``: a
    sixth bead's x per frame (y 100), in both views.  Returns the folders and the beads."""
    rng = np.random.default_rng(seed)
    size = 200
    beads = np.array([[40.3, 40.7], [160.2, 45.1], [60.6, 150.4], [100.5, 60.2], [150.4, 160.6]])
    field = RayField(bead_camera(size))
    dirs = {}
    for v in ("cam1", "cam2"):
        d = tmp_path / v
        d.mkdir()
        for i in range(n_frames):
            b = beads if moving is None else np.vstack([beads, [[moving[i], 100.3]]])
            img = render_beads(b, 5.0, size, None, field=field, noise=False, quantize=False)
            cv2.imwrite(str(d / f"f{i:02d}.png"), np.clip(np.rint(img + rng.normal(0, 1.7, img.shape)), 0, 255)
                        .astype(np.uint8))
        dirs[v] = d
    return dirs, beads


def test_cli_track_given_region_of_interest(tmp_path):
    """``--roi``: a circle X,Y,R, a mask image, one per view (NAME=REGION), or the same in a
    config (``detection.roi``, a mask path relative to it): without seeds only the beads
    inside are tracked (5 with the automatic field), and track.json says the region was
    given."""
    dirs, beads = _roi_views(tmp_path, n_frames=4)
    base = ["-q", "track", "--view", f"cam1={dirs['cam1']}", "--view", f"cam2={dirs['cam2']}", "--diameter-px", "5",
            "--fps", "2"]

    def run(*extra, name):
        out = tmp_path / name
        r = CliRunner().invoke(cli, [*base, *extra, "-o", str(out)])
        assert r.exit_code == 0, r.output
        t = pd.read_csv(out / "markers2d.csv")
        t = t[t["found"].astype(bool)]
        return {v: np.unique(np.rint(g[["x_px", "y_px"]].to_numpy() / 10).astype(int), axis=0).tolist()
                for v, g in t.groupby("view")}, json.loads((out / "track.json").read_text())

    def near(found, pts):
        return sorted(np.rint(np.asarray(pts) / 10).astype(int).tolist()) == sorted(found)

    auto, _ = run(name="auto")
    assert near(auto["cam1"], beads) and near(auto["cam2"], beads)
    # a circle around three of the beads (centre 70, 90, radius 70: beads 0, 2 and 3)
    circ, j = run("--roi", "70,90,70", name="circle")
    inside = beads[np.hypot(beads[:, 0] - 70, beads[:, 1] - 90) <= 70]
    assert len(inside) == 3 and near(circ["cam1"], inside) and near(circ["cam2"], inside)
    assert j["views"]["cam1"]["field_of_view"] == {"found": True, "centre_px": [70.0, 90.0], "radius_px": 70.0,
                                                    "shape": [200, 200], "given": True}
    # a mask image (the left half) for cam2 only: cam1 keeps the automatic field
    m = np.zeros((200, 200), np.uint8)
    m[:, :110] = 255
    cv2.imwrite(str(tmp_path / "left.png"), m)
    per, j = run("--roi", f"cam2={tmp_path / 'left.png'}", name="mask")
    assert near(per["cam1"], beads) and near(per["cam2"], beads[beads[:, 0] < 110])
    assert j["views"]["cam2"]["field_of_view"]["region_px"] == 200 * 110
    assert str(tmp_path / "left.png") in j["provenance"]["inputs_sha256"]       # the mask is an input
    assert "given" not in j["views"]["cam1"]["field_of_view"]
    # the same in a config: per view, the mask's path relative to the config's folder
    (tmp_path / "cfg").mkdir()
    cv2.imwrite(str(tmp_path / "cfg" / "left.png"), m)
    cfg = tmp_path / "cfg" / "track.yaml"
    cfg.write_text(f"views: {{cam1: {dirs['cam1']}, cam2: {dirs['cam2']}}}\ndiameter_px: 5\nfps: 2\nfigures: false\n"
                   "detection: {roi: {cam1: {centre_px: [70, 90], radius_px: 70}, cam2: left.png}}\n")
    r = CliRunner().invoke(cli, ["-q", "track", str(cfg), "-o", str(tmp_path / "cfgout")])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(tmp_path / "cfgout" / "markers2d.csv")
    t = t[t["found"].astype(bool)]
    for v, want in (("cam1", inside), ("cam2", beads[beads[:, 0] < 110])):
        g = t[t["view"] == v]
        assert near(np.unique(np.rint(g[["x_px", "y_px"]].to_numpy() / 10).astype(int), axis=0).tolist(), want)


def test_cli_track_seeded_marker_leaving_the_region_is_lost(tmp_path):
    """A seeded bead moving right across the edge of a given mask (x < 120 searched) is
    followed while inside and reported lost once outside (the search windows see only the
    region), where the automatic field follows it all the way."""
    xs = np.linspace(95.2, 145.7, 12)
    dirs, beads = _roi_views(tmp_path, moving=xs)
    left = beads[beads[:, 0] < 120]            # the still beads inside the region, and the moving one
    seeds = pd.DataFrame([{"view": "cam1", "marker": f"B{k}", "x_px": x + 0.6, "y_px": y - 0.4}
                          for k, (x, y) in enumerate(left)]
                         + [{"view": "cam1", "marker": "MV", "x_px": xs[0] + 0.6, "y_px": 100.3 - 0.4}])
    seeds.to_csv(tmp_path / "seeds.csv", index=False)
    m = np.zeros((200, 200), np.uint8)
    m[:, :120] = 1
    cv2.imwrite(str(tmp_path / "m.png"), m)
    args = ["-q", "track", "--view", f"cam1={dirs['cam1']}", "--seeds", str(tmp_path / "seeds.csv"),
            "--diameter-px", "5", "--fps", "2"]
    for roi, name in ((None, "auto"), (str(tmp_path / "m.png"), "mask")):
        out = tmp_path / name
        r = CliRunner().invoke(cli, [*args, *(["--roi", roi] if roi else []), "-o", str(out)])
        assert r.exit_code == 0, r.output
        t = pd.read_csv(out / "markers2d.csv")
        b5 = t[t["marker"] == "MV"].sort_values("frame")
        e = np.hypot(b5["x_px"] - xs, b5["y_px"] - 100.3)
        if roi is None:
            assert b5["found"].all() and e.max() < 0.3
            continue
        inside = xs < 120 - 3          # the bead's peak pixel and its fit within the region
        assert b5["found"].to_numpy()[inside].all() and (e[inside] < 0.3).all()
        assert not b5["found"].to_numpy()[xs > 120 + 3].any()
        ev = json.loads((out / "track.json").read_text())["events"]
        assert any(x["marker"] == "MV" and x["kind"] == "lost" for x in ev)
        # the other beads, all inside, are unaffected
        assert t[t["marker"] != "MV"]["found"].all()


def test_cli_track_bad_region_of_interest(tmp_path):
    """A mask of another size than the frames, a circle holding no pixel, a seed outside the
    region, a per-view region that leaves out a view, a mask with no pixel set, both --roi
    forms mixed: exit 2 naming the file or key, nothing written."""
    dirs, beads = _roi_views(tmp_path, n_frames=2)
    seeds = pd.DataFrame([{"view": "cam1", "marker": f"B{k}", "x_px": x, "y_px": y} for k, (x, y) in enumerate(beads)])
    seeds.to_csv(tmp_path / "seeds.csv", index=False)
    cv2.imwrite(str(tmp_path / "small.png"), np.full((100, 200), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "empty.png"), np.zeros((200, 200), np.uint8))
    one = ["track", "--view", f"cam1={dirs['cam1']}", "--diameter-px", "5"]
    two = ["track", "--view", f"cam1={dirs['cam1']}", "--view", f"cam2={dirs['cam2']}", "--diameter-px", "5"]
    cases = [(one + ["--roi", str(tmp_path / "small.png")], "small.png"),
             (one + ["--roi", str(tmp_path / "empty.png")], "selects no pixel"),
             (one + ["--roi", "900,900,50"], "holds no pixel"),
             (one + ["--roi", "70,70,75", "--seeds", str(tmp_path / "seeds.csv")], "B1 in cam1 at (160.2, 45.1)"),
             (two + ["--roi", "auto", "--roi", "cam1=none"], "not both"),
             (two + ["--roi", "cam1=none", "--roi", "cam1=auto"], "given twice")]
    cfg = tmp_path / "t.yaml"
    cfg.write_text(f"views: {{cam1: {dirs['cam1']}, cam2: {dirs['cam2']}}}\ndetection: {{roi: {{cam1: none}}}}\n")
    cases.append((["track", str(cfg)], "every view"))
    for k, (args, word) in enumerate(cases):
        out = tmp_path / f"out{k}"
        r = CliRunner().invoke(cli, [*args, "-o", str(out)])
        assert r.exit_code == 2 and word in r.output and not out.exists(), (args, r.output)


def test_overlay_draws_the_region_searched():
    """The overlay figure outlines each view's region of interest: a given circle (dashed
    patch) and a given mask's edge where it crosses the panel (a contour); the title says so."""
    from matplotlib.patches import Circle

    from bsipipe.imaging.detect import FieldOfView
    from bsipipe.report.track_figure import overlay_figure
    img = np.full((200, 200), 120, np.uint8)
    table = pd.DataFrame({"view": ["a", "b"], "frame": [0, 0], "marker": ["M1", "M1"], "x_px": [100.0, 100.0],
                          "y_px": [100.0, 100.0], "found": [True, True]})
    mask = np.zeros((200, 200), bool)
    mask[:, :110] = True
    regions = {"a": FieldOfView((200, 200), (100.0, 100.0), 30.0, found=True, given=True),
               "b": FieldOfView((200, 200), region=mask, given=True)}
    fig = overlay_figure({"a": img, "b": img}, table, {"a": 0, "b": 0}, None, 4.0, regions)
    ax_a, ax_b = fig.axes[:2]
    circ = [p for p in ax_a.patches if isinstance(p, Circle) and p.get_radius() == 30.0]
    assert len(circ) == 1 and circ[0].get_linestyle() == "--"
    assert len(ax_b.collections) >= 1 and "region of interest given" in ax_b.get_title()
    fig = overlay_figure({"a": img, "b": img}, table, {"a": 0, "b": 0}, None, 4.0)
    assert not [p for p in fig.axes[0].patches if isinstance(p, Circle) and p.get_radius() == 30.0]
    assert "region of interest" not in fig.axes[1].get_title()


def test_cli_names_frames_without_their_picture(tmp_path):
    """``bsipipe track`` on frames where two frames are dark noise only (missed exposures of
    pulsed fluoroscopy) and one has its picture but no bead (everything lost at once, as in
    a jolt): a ``frames-without-markers`` warning names the three, the markers are followed
    across them, and it tells the two without a picture (``without_picture``) from the one
    with (``with_picture``: every marker lost at once; it had been worded as a missed
    exposure too); a marker hidden in one frame while the others are seen is not such a
    frame, nor are frames before the first or after the last in which markers were found."""
    frames, truth = crossing_sequence(n=14)
    rng = np.random.default_rng(3)
    for k in (4, 9):
        frames[k] = np.clip(np.rint(rng.normal(12, 2, frames[k].shape)), 0, 255).astype(frames[k].dtype)
    frames[7] = render_beads(np.full((3, 2), -60.0), 4.0, frames[7].shape[0], rng,
                             field=RayField(bead_camera(frames[7].shape[0])))
    out = _track_crossing(tmp_path, frames, truth)
    j = json.loads((out / "track.json").read_text())
    w = [w for w in j["warnings"] if w["code"] == "frames-without-markers"]
    assert len(w) == 1 and w[0]["frames"] == {"cam1": [4, 7, 9]}
    assert w[0]["without_picture"] == {"cam1": [4, 9]} and w[0]["with_picture"] == {"cam1": [7]}
    assert "every marker was lost at once" in w[0]["message"] and "without their picture" in w[0]["message"]
    assert j["views"]["cam1"]["frames_without_picture"] == [4, 9]
    t = pd.read_csv(out / "markers2d.csv")
    j = t["marker"].map({"A": 0, "B": 1, "C": 2}).to_numpy()
    err = np.hypot(t["x_px"] - truth[t["frame"], j, 0], t["y_px"] - truth[t["frame"], j, 1])
    assert not t.loc[t["frame"].isin([4, 7, 9]), "found"].any()
    assert t.loc[t["frame"] > 9, "found"].sum() >= 10 and err[t["found"].to_numpy()].max() < 0.5

    from bsipipe.commands.track import _frames_without_markers
    tab = pd.DataFrame({"view": "cam1", "frame": np.repeat(np.arange(6), 2), "marker": ["A", "B"] * 6,
                        "status": "found",
                        "found": [False, False, True, True, True, False, False, False, True, True, False, False]})
    # frame 0 before any marker, frame 5 after the last: not counted; frame 2 one marker seen
    assert _frames_without_markers(tab) == {"cam1": [3]}
    tab.loc[tab["frame"] == 3, "status"] = "missing-frame"
    assert _frames_without_markers(tab) == {}


def test_a_rerun_removes_what_an_earlier_run_left_and_it_does_not_write(tmp_path):
    """A 2-D run into a folder holding a 3-D run's markers3d.csv, xmalab_3d.csv and loop.md had
    left them beside its own results (register would read them as this run's)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "sample_frame.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    out = tmp_path / "out"
    out.mkdir()
    for n in ("markers3d.csv", "xmalab_3d.csv", "loop.md", "notes.txt"):
        (out / n).write_text("from an earlier run\n")
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--polarity", "dark", "--diameter-px", "4",
                                 "--seeds", str(_xray_seeds(tmp_path)), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert not any((out / n).exists() for n in ("markers3d.csv", "xmalab_3d.csv", "loop.md"))
    assert (out / "notes.txt").exists() and (out / "markers2d.csv").exists()      # a user's own file stays


def test_a_calibration_of_one_camera_for_two_views_names_the_missing_one(tmp_path):
    """It had said only that the calibration has no 'stereo' block."""
    for v in ("cam1", "cam2"):
        (tmp_path / v).mkdir()
        (tmp_path / v / "sample_frame.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps({"views": {"cam1": {}}}))
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={tmp_path / 'cam1'}", "--view", f"cam2={tmp_path / 'cam2'}",
                                 "--polarity", "dark", "--diameter-px", "4", "--calibration", str(cal),
                                 "-o", str(tmp_path / "out")])
    assert r.exit_code == 2 and "no cam2" in r.output and "calibration.json" in r.output, r.output


def test_a_calibration_in_metres_stops_track_before_anything_is_written(tmp_path):
    """The bench twin's true cameras (baseline 895 mm) with T given in metres: exit 2 naming the
    file and the fix, no output folder; it had triangulated 1000 times too small, labelled mm."""
    for v in ("cam1", "cam2"):
        (tmp_path / v).mkdir()
        (tmp_path / v / "sample_frame.jpg").write_bytes((XRAY / "sample_frame.jpg").read_bytes())
    K = [[2000.0, 0, 512], [0, 2000.0, 512], [0, 0, 1]]
    cam = {"image_size": [1024, 1024], "camera_matrix": K, "dist_model": "opencv-5", "dist_coeffs": [0] * 5,
           "dist_coeff_names": ["k1", "k2", "p1", "p2", "k3"]}
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps({"views": {"cam1": cam, "cam2": cam},
                               "stereo": {"views": ["cam1", "cam2"], "R": np.eye(3).tolist(), "T_mm": [0.633, 0.0, 0.633]}}))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={tmp_path / 'cam1'}", "--view", f"cam2={tmp_path / 'cam2'}",
                                 "--polarity", "dark", "--diameter-px", "4", "--calibration", str(cal), "-o", str(out)])
    assert r.exit_code == 2 and "calibration.json" in r.output and "0.8952 apart" in r.output, r.output
    assert "multiply T by 1000" in r.output and not out.exists(), r.output


def test_where_the_times_come_from_is_said(tmp_path):
    """--fps on a source with its own time stamps had been ignored without a word, and frames
    with neither had left time_s empty without one."""
    import cv2
    img = cv2.imread(str(XRAY / "sample_frame.jpg"), cv2.IMREAD_GRAYSCALE)
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(3):
        cv2.imwrite(str(frames / f"f{k}.png"), img)
    seeds = str(_xray_seeds(tmp_path))
    base = ["track", "--polarity", "dark", "--diameter-px", "4", "--seeds", seeds]
    r = CliRunner().invoke(cli, [*base, "--view", f"cam1={frames}", "-o", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    j = json.loads((tmp_path / "a" / "track.json").read_text())
    assert "no-frame-times" in [w["code"] for w in j["warnings"]]
    assert j["views"]["cam1"]["time_source"].startswith("none")
    video = tmp_path / "seq.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 2.0, (img.shape[1], img.shape[0]), False)
    for _ in range(3):
        w.write(img)
    w.release()
    r = CliRunner().invoke(cli, [*base, "--view", f"cam1={video}", "--fps", "10", "-o", str(tmp_path / "b")])
    assert r.exit_code == 0, r.output
    j = json.loads((tmp_path / "b" / "track.json").read_text())
    fw = [w for w in j["warnings"] if w["code"] == "fps-ignored"]
    assert len(fw) == 1 and fw[0]["frames_per_s"]["cam1"] == pytest.approx(2.0, rel=0.01)
    assert j["views"]["cam1"]["time_source"] == "the source's time stamps"


def test_diameter_of_two_sizes_when_the_small_ones_outnumber_the_large():
    """Eight 0.5 mm beads and six 1 mm ones seeded (fitted widths about 0.9 and 1.8 px): the
    median of the widths is a small bead's, and the diameter came out 2.62 px, at which the
    probe's references were found in 9-28 of 221 frames and the study stopped at register.
    With two sizes the diameter is at least 2.5 times the geometric mean of the two groups'
    medians: the same as the median where the groups are about as many (the study's twin:
    unchanged), between them where the small ones outnumber the large."""
    from bsipipe.imaging.marker_size import diameter_from_sigmas
    small, large = [0.89, 0.92, 0.93, 0.94, 0.97, 1.0, 1.0, 1.1], [1.71, 1.75, 1.77, 1.78, 1.97, 2.06]
    assert diameter_from_sigmas(small + large) == pytest.approx(2.5 * np.sqrt(np.median(small) * np.median(large)))
    assert 3.2 < diameter_from_sigmas(small + large) < 3.3
    balanced = [0.75, 0.81, 0.84, 0.85, 1.01, 1.15, 1.65, 1.69, 1.7, 1.77, 1.82, 2.08]
    assert diameter_from_sigmas(balanced) == pytest.approx(2.5 * np.median(balanced))
    assert diameter_from_sigmas([1.0, 1.1, 1.2, 1.05]) == pytest.approx(2.5 * np.median([1.0, 1.1, 1.2, 1.05]))


def test_tracks_on_one_epipolar_line_are_said_to_pair_ambiguously():
    """Without seeds the views' tracks are paired by their ray gaps; two static markers on one
    epipolar plane pair almost as well crosswise (two references so placed had been paired
    crosswise on the probe's twin, 4 mm off, unsaid).  Such pairs are returned as ambiguous;
    markers off each other's epipolar planes are not."""
    import cv2

    from bsipipe.imaging.track_effects import match_tracks_across_views
    from bsipipe.imaging.triangulate import views_from_calibration
    K = [[2000.0, 0, 512], [0, 2000.0, 512], [0, 0, 1]]
    view = {"image_size": [1024, 1024], "camera_matrix": K, "dist_model": "opencv-5", "dist_coeffs": [0] * 5,
            "dist_coeff_names": ["k1", "k2", "p1", "p2", "k3"]}
    R = cv2.Rodrigues(np.array([0.0, -0.6, 0.0]))[0]
    T = np.array([300.0, 0.0, 100.0])
    vg = views_from_calibration({"views": {"a": view, "b": view}, "stereo": {"views": ["a", "b"], "R": R.tolist(),
                                                                              "T_mm": T.tolist()}})
    rng = np.random.default_rng(0)

    def table(points):
        rows = []
        for f in range(8):
            for name, P in points.items():
                for v, (Rv, tv) in (("a", (np.eye(3), np.zeros(3))), ("b", (R, T))):
                    p = cv2.projectPoints(np.asarray(P, float)[None], cv2.Rodrigues(Rv)[0], tv, np.asarray(K), None)[0]
                    x, y = p.ravel() + rng.normal(0, 0.05, 2)
                    rows.append({"view": v, "frame": f, "marker": name, "x_px": x, "y_px": y, "found": True})
        return pd.DataFrame(rows)

    crossed: list = []
    names = match_tracks_across_views(table({"P": [0.0, 0.0, 600.0], "Q": [15.0, 0.0, 640.0]}),
                                      (vg["a"], vg["b"]), ambiguous=crossed)
    assert len(crossed) == 1 and set(names.values()) == {"P", "Q"}, (crossed, names)
    apart: list = []
    match_tracks_across_views(table({"P": [0.0, 0.0, 600.0], "Q": [40.0, 30.0, 700.0]}), (vg["a"], vg["b"]),
                              ambiguous=apart)
    assert apart == []


def test_a_track_paired_with_another_marker_is_suspected():
    """A whole track whose median ray gap is 5 times the sequence's (and over 0.1 mm) passes the
    large-ray-gap flags, which judge each point against its own marker's median; without seeds
    it is named (cross-view-pairing-suspect)."""
    from bsipipe.commands.track import _pairing_suspects
    rng = np.random.default_rng(1)
    # the probe's edge twin: 10 well-paired markers at ~0.02 mm, M12 at 0.13 mm all along
    rows = [{"marker": m, "frame": f, "n_views": 2, "ray_gap_mm": g * (1 + 0.2 * rng.standard_normal())}
            for m, g in [(f"M{i}", 0.02) for i in range(1, 11)] + [("M12", 0.13)] for f in range(20)]
    w = _pairing_suspects(pd.DataFrame(rows))
    assert len(w) == 1 and set(w[0]["markers"]) == {"M12"}
    assert _pairing_suspects(pd.DataFrame([r for r in rows if r["marker"] != "M12"])) == []


def test_a_track_that_begins_late_or_has_gaps_is_reported_without_seeds(tmp_path):
    """Without seeds, a marker hidden for the first 4 of 24 frames and again in frame 8 (the
    probe's dark band of bone over two markers of a second view: 18 of 40 frames lost, no
    event, no warning) is reported: an ``appeared`` event where its track begins, a
    ``lost`` / ``refound`` pair around the gap (a track followed back across a gap had
    reported nothing), and the ``tracks-incomplete`` warning naming the frames it was not
    found in.  The four markers seen throughout are neither."""
    n, size, dia = 24, 160, 5.0
    rng = np.random.default_rng(3)
    B = np.array([[0.25, 0.31], [0.69, 0.29], [0.5, 0.5], [0.32, 0.75], [0.75, 0.73]]) * size
    field = RayField(bead_camera(size))
    frames = tmp_path / "frames"
    frames.mkdir()
    hidden = set(range(4)) | {8}
    for i in range(n):
        P = B + [0.4 * i, 0.25 * i]
        if i in hidden:
            P = P[:4]
        cv2.imwrite(str(frames / f"f{i:02d}.png"), render_beads(P, dia, size, rng, field=field))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["track", "--view", f"cam1={frames}", "--diameter-px", "5", "--fps", "2",
                                 "-o", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads((out / "track.json").read_text())
    m2 = pd.read_csv(out / "markers2d.csv")
    last = m2[m2["frame"] == n - 1].set_index("marker")
    late = last.index[np.hypot(last["x_px"] - (B[4, 0] + 0.4 * (n - 1)),
                               last["y_px"] - (B[4, 1] + 0.25 * (n - 1))) < 1][0]
    found = m2[m2["marker"] == late].set_index("frame")["found"]
    assert sorted(found.index[~found]) == sorted(hidden)
    ev = {(e["marker"], e["kind"], e["frame"]) for e in j["events"]}
    assert {(late, "appeared", 4), (late, "lost", 8), (late, "refound", 9)} <= ev, ev
    assert {e["marker"] for e in j["events"]} == {late}
    w = {w["code"]: w for w in j["warnings"]}
    assert set(w["tracks-incomplete"]["markers"]["cam1"]) == {late}
    assert w["tracks-incomplete"]["markers"]["cam1"][late]["not_found_frames"] == sorted(hidden)
    assert "not in 0-3, 8" in w["tracks-incomplete"]["message"]


def test_gaps_of_automatic_tracks_without_events_get_them():
    """The probe's band twin: a track followed back across a gap (found in frame 12, lost in
    13-17, found 18-19, lost 20, found from 21) had no event at all in its view.  Every run
    of lost rows between found ones now has a lost / refound pair (an existing pair is not
    doubled), a late start an ``appeared`` event and an early end a ``lost`` event."""
    from bsipipe.imaging.track import _gap_events
    pattern = "............x.....xx.xxxxxxxxxxxxxxx..."
    table = pd.DataFrame({"frame": np.arange(len(pattern)), "marker": "M11",
                          "found": [c == "x" for c in pattern],
                          "status": ["found" if c == "x" else "lost" for c in pattern]})
    have = [{"view": "cam2", "frame": 20, "marker": "M11", "kind": "lost"},
            {"view": "cam2", "frame": 21, "marker": "M11", "kind": "refound"}]
    ev = _gap_events(table, have, "cam2")
    assert [(e["kind"], e["frame"]) for e in ev] == [("appeared", 12), ("lost", 13), ("refound", 18),
                                                     ("lost", 20), ("refound", 21), ("lost", 36)]
    assert ev[2]["gap_frames"] == 5
    whole = table.assign(found=True, status="found")
    assert _gap_events(whole, [], "cam2") == []


def test_cli_track_widest_seeded_marker_keeps_room_under_the_width_test(tmp_path):
    """Six small beads (fitted sigma 0.75-1.15 px) and six large ones, two of the large measured
    narrower in the first frame (clipped in a saturated frame, or cut by the field's rim: 1.29
    and 1.34 px for 1.7): the diameter from the median fell to 3.05 px, and the widest bead
    (sigma 1.95 px, 2.05 later, nearer the source) against the width test's limit of
    0.75 x 3.06 = 2.30 px failed it in some later frames (the track probe's clipped twin: 7.5 %
    of the positions lost, unsaid).  The diameter is now at least the width floor
    (1.25 x 2.01 / 0.75 = 3.35 px, from the widest fitted sigma): every marker found in every
    frame."""
    from bsipipe.imaging.marker_size import WIDTH_MARGIN, diameter_from_sigmas, width_floor
    sig = np.array([0.75, 0.81, 0.84, 0.85, 1.01, 1.15, 1.29, 1.34, 1.65, 1.77, 1.82, 1.95])
    assert diameter_from_sigmas(sig) < 3.1                       # the median's diameter, as before
    assert width_floor(sig) == pytest.approx(WIDTH_MARGIN * 1.95 / 0.75)
    rng = np.random.default_rng(5)
    size = 240
    yy, xx = np.mgrid[:size, :size].astype(float)
    xy = np.array([[30.3 + 60 * (k % 4), 40.6 + 70 * (k // 4)] for k in range(12)]) + rng.uniform(-0.5, 0.5, (12, 2))
    first = np.full((size, size), 180.0)
    for (x, y), s in zip(xy, sig):
        first -= 60.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s * s))
    # the later frames: the two narrowed beads at their own width (1.7 px), the widest 5 % wider
    # (nearer the source as it moves; about the scatter of a fitted width at this noise)
    later = first.copy()
    for (x, y), s, s1 in zip(xy[[6, 7, 11]], sig[[6, 7, 11]], (1.7, 1.7, 2.05)):
        later += 60.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s * s))
        later -= 60.0 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s1 * s1))
    images = [first + rng.normal(0, 2.0, first.shape)] + [later + rng.normal(0, 2.0, first.shape) for _ in range(39)]
    names = [f"S{k}" for k in range(6)] + [f"L{k}" for k in range(6)]
    j, m2 = _track_clicked(tmp_path, images, names, xy)
    t = dict(zip(names, xy))
    e = np.hypot(m2["x_px"] - [t[m][0] for m in m2["marker"]], m2["y_px"] - [t[m][1] for m in m2["marker"]])
    small = m2["marker"].str.startswith("S").to_numpy()
    rms_s, rms_l = np.sqrt(np.nanmean(e[small] ** 2)), np.sqrt(np.nanmean(e[~small] ** 2))
    print(f"diameter {j['diameter_px']:.2f} px ({j['diameter_source']}); found {int(m2['found'].sum())} of {len(m2)}; "
          f"centre RMS small {rms_s:.3f} px, large {rms_l:.3f} px")
    assert WIDTH_MARGIN * 1.9 / 0.75 <= j["diameter_px"] <= WIDTH_MARGIN * 2.3 / 0.75
    assert "passes the width test" in j["diameter_source"]
    assert m2["found"].all(), m2[~m2["found"]].groupby("marker").size().to_dict()


@pytest.mark.parametrize("a", [0.0, 0.4])
def test_cli_track_frames_averaged_over_time_are_said(tmp_path, a):
    """Frames the C-arm averaged with the ones before (y_t = (1 - a) x_t + a y_{t-1}: image-
    intensifier lag or a recursive noise filter) make a moving bead's image trail it, by
    a / (1 - a) frames, in every view alike, so the ray gaps cannot show it (the track probe's
    twin averaged with a = 0.3: the indentor's beads 0.35 px and 0.068 mm off at 1 px a frame,
    8-11 times their stated sds, exit 0 and nothing said).  The noise of consecutive frames is
    then correlated: measured (a = 0.4 read 0.4 +/- 0.05) and said (``frames-averaged``, with
    the lag in frames); independent frames (a = 0) are not."""
    rng = np.random.default_rng(8)
    size = 160
    yy, xx = np.mgrid[:size, :size].astype(float)
    scene = 150 + 10 * np.sin(xx / 9.0) * np.cos(yy / 13.0)
    xy0 = np.array([[40.3, 50.6], [90.2, 110.4], [120.7, 60.1]])
    images, y = [], None
    for t in range(40):
        x = scene.copy()
        for bx, by in xy0 + [0.8 * t, 0.0]:
            x -= 50.0 * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * 1.2 ** 2))
        x += rng.normal(0, 3.0, x.shape)
        y = x if y is None else (1 - a) * x + a * y
        images.append(y)
    j, _ = _track_clicked(tmp_path, images, ["A", "B", "C"], xy0)
    tn = j["views"]["cam1"]["temporal_noise"]
    codes = [w["code"] for w in j["warnings"]]
    print(f"a {a}: {tn}, warnings {codes}")
    assert tn["n_triples"] >= 3 and tn["rho"] == pytest.approx(a, abs=0.05)
    assert ("frames-averaged" in codes) == (a > 0)


def _averaged_pair(tmp_path, a: float, n: int = 46, step_mm: float = 0.15):
    """Two calibrated views (f 800 px, 200 px frames, cam2 turned 40 degrees about y) of four
    beads 300 mm away moving ``step_mm`` a frame along x (0.15 mm: 0.4 px, about what the
    indentation gives at 2 frames/s), each view's frames averaged over time,
    y_t = (1 - a) x_t + a y_{t-1}; written as PNG folders with seeds.csv and calibration.json.
    Returns the folder and the beads' true positions (n, 4, 3) in cam1's frame."""
    from scipy.spatial.transform import Rotation
    size, f = 200, 800.0
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    R = Rotation.from_euler("y", 40, degrees=True).as_matrix()
    centre = np.array([0.0, 0.0, 300.0])
    T = centre - R @ centre
    start = centre + np.array([[-12.0, -6.0, 4.0], [-8.0, 7.0, -5.0], [-14.0, 3.0, 9.0], [-6.0, -9.0, -3.0]])
    X = start[None] + np.arange(n)[:, None, None] * np.array([step_mm, 0.0, 0.0])
    rng = np.random.default_rng(12)
    yy, xx = np.mgrid[:size, :size].astype(float)
    names = ["A", "B", "C", "D"]
    seeds = []
    for v, (Rv, tv) in {"cam1": (np.eye(3), np.zeros(3)), "cam2": (R, T)}.items():
        d = tmp_path / v
        d.mkdir()
        scene = 150 + 10 * np.sin(xx / 9.0) * np.cos(yy / 13.0)
        y = None
        for k in range(n):
            p = (X[k] @ Rv.T + tv) @ K.T
            uv = p[:, :2] / p[:, 2:]
            img = scene.copy()
            for bx, by in uv:
                img -= 50.0 * np.exp(-((xx - bx) ** 2 + (yy - by) ** 2) / (2 * 1.2 ** 2))
            img += rng.normal(0, 3.0, img.shape)
            y = img if y is None else (1 - a) * img + a * y
            cv2.imwrite(str(d / f"f{k:03d}.png"), np.clip(np.rint(y), 0, 255).astype(np.uint8))
            if k == 0:
                seeds += [{"view": v, "marker": m, "x_px": u + 0.4, "y_px": w - 0.3} for m, (u, w) in zip(names, uv)]
    pd.DataFrame(seeds).to_csv(tmp_path / "seeds.csv", index=False)
    cam = {"image_size": [size, size], "camera_matrix": K.tolist(), "dist_model": "opencv-5",
           "dist_coeffs": [0.0] * 5, "dist_coeff_names": ["k1", "k2", "p1", "p2", "k3"]}
    (tmp_path / "calibration.json").write_text(json.dumps(
        {"views": {"cam1": cam, "cam2": cam}, "stereo": {"views": ["cam1", "cam2"], "R": R.tolist(),
                                                          "T_mm": T.tolist()}}))
    return tmp_path, X, names


def test_cli_track_frames_averaged_in_both_views_are_dated_by_their_lag(tmp_path):
    """Both C-arms average their frames over time (a = 0.4): every marker is imaged where it
    was a / (1 - a) = 0.67 frames before, in both views alike, which the ray gaps cannot show
    (against the truth at the frames' times the points are 0.1 mm behind).  The noise
    correlation measures it per view (``frames-averaged``) and markers3d.csv's time_s is moved
    back by the lag: against the truth at those times the 3-D error falls to about that of
    frames not averaged.  Without averaging nothing is moved.  (The model is the average's
    delay for a marker that moves little in a frame against its size, as in the indentation;
    at 1.2 px a frame, the width of these beads, the fit keeps nearer the newest image and the
    shift overshoots: 3-D RMS 0.19 mm at the frames' times, 0.12 mm at the moved ones.)"""
    err = {}
    for a in (0.0, 0.4):
        (tmp_path / f"a{a}").mkdir()
        root, X, names = _averaged_pair(tmp_path / f"a{a}", a)
        out = root / "out"
        r = CliRunner().invoke(cli, ["track", "--view", f"cam1={root / 'cam1'}", "--view", f"cam2={root / 'cam2'}",
                                     "--seeds", str(root / "seeds.csv"), "--calibration",
                                     str(root / "calibration.json"), "--fps", "2", "-o", str(out)])
        assert r.exit_code == 0, r.output
        j = json.loads((out / "track.json").read_text())
        p = pd.read_csv(out / "markers3d.csv").dropna(subset=["x_mm"])
        p = p[p["frame"] >= 8]                       # after the average's start (it begins with y_0 = x_0)
        got = p[["x_mm", "y_mm", "z_mm"]].to_numpy()
        idx = [names.index(m) for m in p["marker"]]
        at_frame = X[p["frame"].to_numpy(), idx]
        tf = p["time_s"].to_numpy() * 2.0           # the frame the point is dated at
        at_time = np.stack([np.array([np.interp(t, np.arange(len(X)), X[:, i, k]) for k in range(3)])
                            for t, i in zip(tf, idx)])
        err[a] = {"by_frame": float(np.sqrt(np.mean(np.sum((got - at_frame) ** 2, axis=1)))),
                  "by_time": float(np.sqrt(np.mean(np.sum((got - at_time) ** 2, axis=1)))),
                  "lag": j.get("lag_correction"), "codes": [w["code"] for w in j["warnings"]]}
        print(a, err[a])
    assert err[0.0]["lag"] is None and "frames-averaged" not in err[0.0]["codes"]
    assert err[0.0]["by_time"] == pytest.approx(err[0.0]["by_frame"])
    lag = err[0.4]["lag"]
    assert "frames-averaged" in err[0.4]["codes"] and lag["applied"]
    assert lag["lag_frames"] == pytest.approx(0.4 / 0.6, abs=0.1)
    assert lag["shift_s"] == pytest.approx(lag["lag_frames"] * 0.5)
    assert err[0.4]["by_frame"] > 0.07                # 0.15 mm a frame x 0.67 frame behind
    assert err[0.4]["by_time"] < 0.3 * err[0.4]["by_frame"]
    assert err[0.4]["by_time"] < 2.0 * err[0.0]["by_time"]


def test_frames_averaged_is_not_said_where_motion_sets_the_frame_differences():
    """trackpy's bulk-water frames (real microscopy: particles moving everywhere) give triples
    whose noise-correlation estimates scatter about 1.17 (interquartile range 0.67): motion,
    not noise, sets their frame differences, and nothing is said of averaged frames; the
    probe's averaged twin's estimates agree within 0.02 and are said."""
    from bsipipe.commands.track import _lag_warning, _temporal_noise
    from bsipipe.imaging.detect import temporal_noise_correlation
    from bsipipe.io.images import iter_frames
    imgs = [fr.image for fr in iter_frames(str(WATER / "bulk_water_*.png"))]
    crop = [x[x.shape[0] // 4:3 * x.shape[0] // 4:2, x.shape[1] // 4:3 * x.shape[1] // 4:2] for x in imgs]
    tn = _temporal_noise([temporal_noise_correlation(*crop[k:k + 3]) for k in range(0, len(crop) - 2, 3)])
    print(tn)
    assert tn["n_triples"] >= 9 and not tn["consistent"] and tn["iqr"] > 0.3
    assert _lag_warning({"water": {"temporal_noise": tn}}, ["water"]) is None
    agree = _temporal_noise([0.315, 0.324, 0.33, 0.32, 0.31, 0.335])
    assert agree["consistent"] and _lag_warning({"cam1": {"temporal_noise": agree}}, ["cam1"]) is not None


def test_markers_merged_in_both_views_are_said():
    """Two markers whose images merged in both calibrated views over the same frames and then
    parted may have crossed or turned back, which the images cannot tell, and an exchange made
    alike in both views leaves the ray gaps small (the automatic-mode probe's bead that came
    within 0.5 mm of a fixed reference and went back: both 3-D tracks 3.5 mm RMS off, 7.8 mm at
    most, exit 0, unsaid): ``merged-in-both-views`` names them with the frames.  Merged in one
    view only (the other tells them apart), or in the two views at different times, nothing is
    said.  Renaming a view's tracks to the paired names renames the merge partners too (they had
    kept the view's own names, another marker's in the paired table)."""
    from bsipipe.commands.track import _merged_in_both_views, _rename_markers

    def table(merged: dict):
        rows = []
        for v in ("cam1", "cam2"):
            for f in range(30):
                for m in ("A", "B", "C"):
                    st = "merged" if m in ("A", "B") and f in merged.get(v, ()) else "found"
                    rows.append({"view": v, "frame": f, "marker": m, "status": st, "found": st == "found"})
        return pd.DataFrame(rows)

    def events(merged: dict):
        return [{"view": v, "frame": min(fr), "marker": m, "kind": "merged", "other": o}
                for v, fr in merged.items() for m, o in (("A", "B"), ("B", "A"))]

    both = {"cam1": range(10, 16), "cam2": range(11, 17)}
    w = _merged_in_both_views(table(both), events(both), ("cam1", "cam2"))
    assert len(w) == 1 and w[0]["code"] == "merged-in-both-views"
    assert w[0]["pairs"] == [{"markers": ["A", "B"], "first_frame": 11, "last_frame": 15, "parted_frame": 17}]
    one = {"cam1": range(10, 16)}
    assert _merged_in_both_views(table(one), events(one), ("cam1", "cam2")) == []
    apart = {"cam1": range(2, 6), "cam2": range(20, 24)}
    assert _merged_in_both_views(table(apart), events(apart), ("cam1", "cam2")) == []
    t, ev = table(both), events(both)
    _rename_markers(t, ev, "cam2", {"A": "M1", "B": "M2", "C": "M3"})
    assert [(e["marker"], e["other"]) for e in ev if e["view"] == "cam2"] == [("M1", "M2"), ("M2", "M1")]
    assert [(e["marker"], e["other"]) for e in ev if e["view"] == "cam1"] == [("A", "B"), ("B", "A")]


def test_merged_frames_count_as_not_found_in_tracks_incomplete():
    """A frame where a track's image merged with a neighbour's has no position and no 3-D
    point: ``tracks-incomplete`` counts it as not found and says so (the automatic-mode probe's
    bead measured in 21 of 80 frames had been said "57 of 80", two markers measured in 54 of
    80 not named at all)."""
    from bsipipe.commands.track import _tracks_incomplete
    rows = []
    for f in range(40):
        for m in ("A", "B"):
            st = "merged" if m == "A" and 10 <= f < 22 else "found"
            rows.append({"view": "cam1", "frame": f, "marker": m, "status": st, "found": st == "found"})
    w = _tracks_incomplete(pd.DataFrame(rows))
    assert len(w) == 1 and set(w[0]["markers"]["cam1"]) == {"A"}
    a = w[0]["markers"]["cam1"]["A"]
    assert a["found"] == 28 and a["merged_frames"] == list(range(10, 22)) and "merged in 10-21" in w[0]["message"]
