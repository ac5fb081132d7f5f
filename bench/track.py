"""Benchmark ``track``: marker detection + tracking on the X-ray twin (issues 5 and 7).

Data: a ``bsipipe synth`` sequence rendered once into ``results/bench_cache/twin200``
(:data:`TWIN_CONFIG`: 1024 x 1024 8-bit PNG frames, two C-arm views, 10 markers = 6 implanted
+ 4 references, 200 frames per view at 4 frames/s over the indentation, two markers hidden
by the indentor for a while), its ``seeds.csv`` (clicks 0.5 px off) and a
``calibration.json`` holding the twin's true cameras.  The 2,000-frame case reuses those
frames: ``results/bench_cache/twin2000`` holds symlinks that play the 200 frames forwards,
backwards, forwards... (the motion stays continuous), 2,000 per view.

Rows
----
1. **detection + tracking vs trackpy** on the same frames, decoded beforehand (decode is in
   neither time): the first :data:`N_PEER` frames of each view (``--quick``:
   :data:`N_PEER_QUICK`).  bsipipe: :func:`bsipipe.imaging.track.track_view` from the seeds
   (what ``bsipipe track`` does) and, second row, without seeds (whole-frame detection and
   linking, the like-for-like job).  trackpy: ``trackpy.locate`` on every frame
   (``diameter=5``, the smallest odd size over bsipipe's 4 px; ``invert=True``: the beads are
   dark; ``minmass`` 0.8 x the faintest seeded marker's mass in frame 0, tuned as a user
   would, not timed) then ``trackpy.link`` (``search_range=5``, ``memory=5``), with trackpy's
   fast numba engine when numba is installed (the row says which engine ran; the pure-Python
   one is about 7x slower on these frames).  Both are checked against the twin's truth
   (visible markers found within 1 px).  Each side's fastest timed run counts: bsipipe's seeded
   tracker, its automatic mode and trackpy run three times each (``--quick``: once), after a
   warm-up, in turn (seeded, automatic, trackpy, seeded, ...: :func:`bench.common.interleaved`),
   so each ratio compares runs made under the same machine state.  Target: bsipipe at least 30x trackpy's frames per second.  The automatic mode searches the whole frame for new markers only every
   ``sweep_every_frames`` frames (default 20, and in the first and last frames) and each
   track in its own window in between; its row's note also gives the speed and recall with a
   whole-frame search in every frame (``sweep_every_frames=1``), as trackpy does.
2. **whole command vs decode**: ``bsipipe track --view cam1=.. --view cam2=.. --seeds ..
   --calibration .. --fps 4 -o ..`` (tracking, triangulation, the loop, CSVs, figures) and a
   child that only decodes the same frames with :func:`bsipipe.io.images.iter_frames`
   (``bench/decode_frames.py``), both as fresh processes (start-up included), interleaved,
   twice each (``--quick``: once), at 200 frames per view and (not with ``--quick``) 2,000.
   Target: command <= 1.5x decode, judged two ways, one row each: **wall time** (what a user
   waits; the command decodes on reader threads while it tracks, so it takes about the longer
   of decoding, spread over the cores, and tracking, plus its start-up; the decode child
   reads on one thread, as a plain frame reader does) and **CPU time** (user + system: the work
   done in all, the stricter measure and the one load cannot skew).  The fastest run of each
   counts (load only adds time).  From the two lengths the CPU time is split into a fixed
   part (start-up, imports, the loop, figures) and a per-frame part, for the command and for
   decoding; the Kalman/RTS smoother's share is timed on each command's own 2-D table
   (:func:`bsipipe.imaging.smooth.smooth_tracks`, in this process).  The 200-frame CPU row
   also gives the floor no tracking speed can lower (:func:`_floor`): the CPU to import what
   the command needs and the decode child does not (pandas, ``scipy.optimize`` for
   ``linear_sum_assignment``, matplotlib's Agg canvas) and to draw its two figures, against
   the room the target leaves beyond decoding (0.5 x decode's CPU).
3. **peak memory** of ``bsipipe track`` at 200 and 2,000 frames per view: the child's own
   high-water mark (``VmHWM``, :func:`bench.common.run_child`).  Target: flat within 20 %,
   and under 1 GiB at 2,000.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from .common import CACHE, OUT, ROOT, Row, bsipipe_exe, fmt_bytes, fmt_s, interleaved, run_child, timed

VIEWS = ("cam1", "cam2")
N_FRAMES = 200
N_LONG = 2000
FPS = 4.0
N_PEER = 50
N_PEER_QUICK = 16
DIAMETER_PX = 4.0
TP_DIAMETER = 5
TP_SEARCH_RANGE = 5.0
TP_MEMORY = 5
TARGET_SPEEDUP = 30.0
TARGET_CMD_OVER_DECODE = 1.5
TARGET_RSS_GROWTH = 1.2
TARGET_RSS_BYTES = 2**30

TWIN_CONFIG = f"""\
# bench/track.py: the twin sequence of the tracking benchmark (1024 x 1024, 10 markers, 2 views)
seed: 0
image: {{size_px: 1024}}
calibration: {{views: 0, stereo_views: 0}}
sequence: {{n_frames: {N_FRAMES}, fps: {FPS}, n_markers: 6, n_references: 4}}
"""


# --- the cached sequences ----------------------------------------------------------------------

def twin_sequence(say=print) -> Path:
    """``results/bench_cache/twin200``: rendered by ``bsipipe synth`` once (about a minute)."""
    cfg = CACHE / "twin_seq.yaml"
    out = CACHE / f"twin{N_FRAMES}"
    if not (cfg.exists() and cfg.read_text() == TWIN_CONFIG and (out / "synth.json").exists()):
        CACHE.mkdir(parents=True, exist_ok=True)
        cfg.write_text(TWIN_CONFIG)
        shutil.rmtree(out, ignore_errors=True)
        say(f"track: rendering the twin sequence into {out} (once)")
        r = run_child([bsipipe_exe(), "synth", str(cfg), "-o", str(out)], timeout_s=3600)
        if not r.ok:
            raise RuntimeError(f"bsipipe synth failed (exit {r.returncode}):\n{r.tail()}")
    cal = out / "calibration.json"
    if not cal.exists():
        cal.write_text(json.dumps(truth_calibration(json.loads((out / "truth.json").read_text()))))
    return out


def truth_calibration(truth: dict) -> dict:
    """The twin's true cameras in ``bsipipe calibrate``'s calibration.json layout."""
    views = {}
    for v in VIEWS:
        c = truth["cameras"][v]
        views[v] = {"image_size": c["image_size"], "camera_matrix": c["camera_matrix"], "dist_model": "opencv-5",
                    "dist_coeffs": c["dist_coeffs"][:5], "dist_coeff_names": ["k1", "k2", "p1", "p2", "k3"]}
    st = truth["stereo_extrinsics"]
    return {"views": views, "stereo": {"views": st["views"], "R": st["R"], "T_mm": st["T_mm"]}}


def pingpong(n: int, period: int) -> np.ndarray:
    """Frame ``i`` of a sequence that plays ``period`` frames forwards, backwards, forwards...

    >>> pingpong(9, 4).tolist()
    [0, 1, 2, 3, 2, 1, 0, 1, 2]
    """
    cycle = np.concatenate([np.arange(period), np.arange(period - 2, 0, -1)])
    return cycle[np.arange(n) % len(cycle)]


def long_sequence(src: Path) -> Path:
    """``twin2000``: symlinks to ``src``'s frames, :func:`pingpong` order, per view."""
    out = CACHE / f"twin{N_LONG}"
    idx = pingpong(N_LONG, N_FRAMES)
    for v in VIEWS:
        d = out / "sequence" / v
        last = d / f"frame_{N_LONG - 1:04d}.png"
        if last.is_symlink() and len(os.listdir(d)) == N_LONG:
            continue
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        for i, j in enumerate(idx):
            os.symlink(os.path.relpath(src / "sequence" / v / f"frame_{j:04d}.png", d), d / f"frame_{i:04d}.png")
    return out


# --- detection + tracking: bsipipe vs trackpy ------------------------------------------------------

def _truth_table(src: Path):
    import pandas as pd
    return pd.read_csv(src / "truth_markers.csv")


def _found_within(table_xy, truth, tol=1.0) -> float:
    """Fraction of visible true positions with a reported position within ``tol`` px."""
    from scipy.spatial import cKDTree
    hits, total = 0, 0
    for f, g in truth.groupby("frame"):
        vis = g[g["visible"]]
        pts = table_xy.get(f)
        total += len(vis)
        if pts is None or len(pts) == 0 or len(vis) == 0:
            continue
        d, _ = cKDTree(pts).query(vis[["x_px", "y_px"]].to_numpy())
        hits += int(np.sum(d <= tol))
    return hits / total if total else float("nan")


def _bsipipe_track(frames: dict, seeds, auto: bool, **settings):
    from bsipipe.imaging.track import TrackSettings, track_view
    out = {}
    for v in VIEWS:
        s = None if auto else seeds[seeds["view"] == v]
        out[v] = track_view(frames[v], s, DIAMETER_PX, "dark", view=v, fps=FPS, settings=TrackSettings(**settings))
    return out


def _recall(res: dict, truth) -> float:
    """Mean over the views of the visible true positions found within 1 px."""
    hits = []
    for v in VIEWS:
        t = res[v].table
        t = t[t["found"]]
        xy = {f: g[["x_px", "y_px"]].to_numpy() for f, g in t.groupby("frame")}
        hits.append(_found_within(xy, truth[truth["view"] == v]))
    return float(np.mean(hits))


def _trackpy_minmass(tp, img, seeds_xy) -> float:
    from scipy.spatial import cKDTree
    f = tp.locate(img, TP_DIAMETER, invert=True, minmass=0)
    d, i = cKDTree(f[["x", "y"]].to_numpy()).query(seeds_xy)
    return 0.8 * float(f["mass"].to_numpy()[i[d <= 2.0]].min())


def _trackpy_track(tp, frames: dict, minmass: dict):
    import pandas as pd
    out = {}
    for v in VIEWS:
        feats = [tp.locate(img, TP_DIAMETER, invert=True, minmass=minmass[v]).assign(frame=k)
                 for k, img in enumerate(frames[v])]
        out[v] = tp.link(pd.concat(feats, ignore_index=True), TP_SEARCH_RANGE, memory=TP_MEMORY)
    return out


def bench_detect_track(src: Path, quick: bool, say=print) -> tuple[list[Row], dict]:
    import pandas as pd

    from bsipipe.io.images import iter_frames

    n = N_PEER_QUICK if quick else N_PEER
    frames = {v: [fr.image for _, fr in zip(range(n), iter_frames(src / "sequence" / v))] for v in VIEWS}
    n_total = sum(len(x) for x in frames.values())
    seeds = pd.read_csv(src / "seeds.csv")
    truth = _truth_table(src)
    truth = truth[truth["frame"] < n]
    det: dict = {"n_frames_per_view": n, "frame_shape": list(frames[VIEWS[0]][0].shape)}

    rows = []
    reps = 1 if quick else 3
    runs = {"seeded": lambda: _bsipipe_track(frames, seeds, auto=False),
            "auto": lambda: _bsipipe_track(frames, seeds, auto=True)}
    # both modes warmed up (a mode's first run in a process pays one-time costs: the automatic
    # mode's 1.08 s against 0.44 s after it)
    warm = {"seeded": 1, "auto": 1}
    try:
        import trackpy as tp
    except ImportError as e:
        tp, tp_missing = None, e
    if tp is not None:
        tp.quiet()
        minmass = {v: _trackpy_minmass(tp, frames[v][0], seeds[seeds["view"] == v][["x_px", "y_px"]].to_numpy())
                   for v in VIEWS}
        # trackpy's fast engine: locate's engine="auto" takes numba when it is installed
        if importlib.util.find_spec("numba") is not None:
            engine = "numba"
        else:
            engine = "python: numba not installed, trackpy's slow engine (about 7x slower here)"
        # warm-up, not timed: numba compiles locate's kernels on the first call (done above by
        # the minmass tuning) and link's on the first link
        tp.link(pd.concat([tp.locate(frames[VIEWS[0]][k], TP_DIAMETER, invert=True, minmass=minmass[VIEWS[0]])
                           .assign(frame=k) for k in range(2)], ignore_index=True), TP_SEARCH_RANGE, memory=TP_MEMORY)
        runs["trackpy"] = lambda: _trackpy_track(tp, frames, minmass)
    # the timed runs of bsipipe's two modes and trackpy's in turn, the fastest of each counting
    # (load only adds time): the ratios compare runs made under the same machine state
    tm, res = interleaved(runs, repeats=reps, warmup=warm)
    t_seed, t_auto = tm["seeded"], tm["auto"]
    res_seed, res_auto = res["seeded"], res["auto"]
    acc = {"seeded": _recall(res_seed, truth), "auto": _recall(res_auto, truth)}
    fps_seed = n_total / t_seed["min_s"]
    fps_auto = n_total / t_auto["min_s"]
    say(f"  bsipipe track_view: seeded {fps_seed:.1f} frames/s, no seeds {fps_auto:.1f} frames/s "
        f"({n} frames x {len(VIEWS)} views; found within 1 px: {100 * acc['seeded']:.1f} % / "
        f"{100 * acc['auto']:.1f} %)")
    det["bsipipe"] = {"seeded": {"time": t_seed, "fps": fps_seed, "found_1px": acc["seeded"]},
                      "auto": {"time": t_auto, "fps": fps_auto, "found_1px": acc["auto"]}}
    # the automatic mode with a whole-frame search in every frame (trackpy's way), for scale
    t_every, res_every = timed(lambda: _bsipipe_track(frames, seeds, auto=True, sweep_every_frames=1),
                               repeats=1 if quick else 2)
    det["bsipipe"]["auto_sweep_every_frame"] = {"time": t_every, "fps": n_total / t_every["min_s"],
                                                "found_1px": _recall(res_every, truth)}
    say(f"  no seeds, whole frame searched in every frame: {n_total / t_every['min_s']:.1f} frames/s (found within "
        f"1 px: {100 * det['bsipipe']['auto_sweep_every_frame']['found_1px']:.1f} %)")
    if not quick:
        # the seeded tracker's steady state: every frame of the sequence (the per-view set-up,
        # field of view and seed refinement, weighs on 50 frames)
        every = {v: [fr.image for fr in iter_frames(src / "sequence" / v)] for v in VIEWS}
        t_all, _ = timed(lambda: _bsipipe_track(every, seeds, auto=False), repeats=2)
        n_all = sum(len(x) for x in every.values())
        det["bsipipe"]["seeded_all_frames"] = {"time": t_all, "fps": n_all / t_all["min_s"], "n_frames": n_all}
        say(f"  bsipipe seeded on all {n_all} frames: {n_all / t_all['min_s']:.1f} frames/s")
        del every

    if tp is None:
        note = f"trackpy cannot run ({tp_missing}): pip install trackpy"
        for name, fps in (("seeded", fps_seed), ("no seeds", fps_auto)):
            rows.append(Row(f"track {name}: detect+track vs trackpy", f"{fps:.1f} frames/s", "trackpy: not installed",
                            None, "", ">= 30x", None, note=note))
        return rows, det
    t_tp, res_tp = tm["trackpy"], res["trackpy"]
    fps_tp = n_total / t_tp["min_s"]
    hits, per_frame = [], []
    for v in VIEWS:
        df = res_tp[v]
        xy = {f: g[["x", "y"]].to_numpy() for f, g in df.groupby("frame")}
        hits.append(_found_within(xy, truth[truth["view"] == v]))
        per_frame.append(len(df) / n)
    acc_tp = float(np.mean(hits))
    say(f"  trackpy {tp.__version__} locate+link ({engine}): {fps_tp:.2f} frames/s, {np.mean(per_frame):.0f} features "
        f"per frame (minmass {', '.join(f'{m:.0f}' for m in minmass.values())}), found within 1 px: "
        f"{100 * acc_tp:.1f} %")
    det["trackpy"] = {"time": t_tp, "fps": fps_tp, "found_1px": acc_tp, "features_per_frame": per_frame,
                      "minmass": minmass, "engine": engine, "version": tp.__version__,
                      "diameter": TP_DIAMETER, "search_range": TP_SEARCH_RANGE, "memory": TP_MEMORY}
    common = (f"{n} frames/view in memory; visible markers found within 1 px: bsipipe {{acc:.1f}} %, trackpy "
              f"{100 * acc_tp:.1f} % ({np.mean(per_frame):.0f} features/frame); CPU-time ratio {{cpu:.3g}}x; "
              f"trackpy engine {engine}")
    for name, fps, a, t in (("seeded", fps_seed, acc["seeded"], t_seed), ("no seeds", fps_auto, acc["auto"], t_auto)):
        r = fps / fps_tp
        cpu = t_tp["cpu_min_s"] / t["cpu_min_s"]
        note = common.format(acc=100 * a, cpu=cpu)
        if name == "no seeds":
            from bsipipe.imaging.track import TrackSettings
            ev = det["bsipipe"]["auto_sweep_every_frame"]
            note += (f"; the whole frame searched every {TrackSettings().sweep_every_frames} frames (and the first "
                     f"and last), each track in its window between; searched whole in every frame instead: "
                     f"{ev['fps'] / fps_tp:.1f}x trackpy, found within 1 px {100 * ev['found_1px']:.1f} %")
        rows.append(Row(f"track {name}: detect+track vs trackpy", f"{fps:.1f} frames/s",
                        f"trackpy {fps_tp:.2f} frames/s", r, "bsipipe/peer fps", ">= 30x", r >= TARGET_SPEEDUP,
                        note=note, values={"bsipipe_fps": fps, "peer_fps": fps_tp, "cpu_ratio": cpu}))
    return rows, det


# --- the whole command vs decoding, and its memory ---------------------------------------------------

def _run_command(seq: Path, src: Path, tag: str, calibration: bool = True):
    out = OUT / f"track{tag}"
    shutil.rmtree(out, ignore_errors=True)
    args = [bsipipe_exe(), "-q", "track"]
    for v in VIEWS:
        args += ["--view", f"{v}={seq / 'sequence' / v}"]
    args += ["--seeds", str(src / "seeds.csv"), "--fps", str(FPS), "-o", str(out)]
    if calibration:
        args += ["--calibration", str(src / "calibration.json")]
    return run_child(args, timeout_s=3600), out


def _run_decode(seq: Path):
    r = run_child([sys.executable, str(ROOT / "bench" / "decode_frames.py"),
                   *[str(seq / "sequence" / v) for v in VIEWS]], timeout_s=3600)
    info = json.loads(r.stdout.strip().splitlines()[-1]) if r.ok else {}
    return r, info


def _time_smoothing(markers2d_csv: Path) -> dict:
    """CPU and wall time of :func:`bsipipe.imaging.smooth.smooth_tracks` on a command's 2-D
    table (time stamps and SNR as ``bsipipe track`` passes them)."""
    import pandas as pd

    from bsipipe.imaging.smooth import smooth_tracks
    t = pd.read_csv(markers2d_csv, dtype={"view": str, "marker": str})
    t = t[["view", "frame", "time_s", "marker", "x_px", "y_px", "snr", "found"]].copy()
    t["snr"] = t["snr"].where(t["found"].astype(bool))
    if t["time_s"].isna().any():
        t["time_s"] = t["frame"].astype(float)
    tm, _ = timed(lambda: smooth_tracks(t), repeats=1)
    return {"cpu_s": tm["cpu_min_s"], "wall_s": tm["min_s"], "n_rows": int(len(t))}


#: What ``bsipipe track`` must load beyond the decode child's reader (numpy and OpenCV): pandas
#: for its tables, ``scipy.optimize`` for the global assignment the issue names
#: (``linear_sum_assignment``), matplotlib's Agg canvas for the figures the contract writes.
_COMMAND_LIBS = "import numpy, cv2, pandas, scipy.optimize, matplotlib.figure, matplotlib.backends.backend_agg"
_DECODE_LIBS = "import numpy, cv2, bsipipe.io.images"


def _floor(out: Path, src: Path, repeats: int = 2) -> dict:
    """The CPU the command cannot avoid beyond decoding, whatever tracking costs: importing the
    libraries it needs that the decode child does not (fresh children, the fastest of
    ``repeats`` each), and drawing and saving its two figures (timed in this process on the
    command's own ``markers2d.csv`` / ``markers3d.csv``, the first frames decoded untimed)."""
    import io

    import pandas as pd

    from bsipipe.io.images import iter_frames
    from bsipipe.report.track_figure import overlay_figure, trajectories_figure

    def child_cpu(code: str) -> float:
        return min(run_child([sys.executable, "-c", code], timeout_s=600).cpu_s for _ in range(repeats))

    imports = child_cpu(_COMMAND_LIBS) - child_cpu(_DECODE_LIBS)
    t2 = pd.read_csv(out / "markers2d.csv", dtype={"view": str, "marker": str})
    p3 = pd.read_csv(out / "markers3d.csv", dtype={"marker": str})
    first = {v: next(iter(iter_frames(src / "sequence" / v))).image for v in VIEWS}

    def draw():
        for fig in (trajectories_figure(t2, p3), overlay_figure(first, t2, {v: 0 for v in VIEWS})):
            fig.savefig(io.BytesIO(), format="png", dpi=120, bbox_inches="tight")

    tm, _ = timed(draw, repeats=repeats, warmup=1)
    return {"imports_cpu_s": imports, "figures_cpu_s": tm["cpu_min_s"]}


def bench_command(src: Path, quick: bool, say=print) -> tuple[list[Row], dict]:
    cases = [(N_FRAMES, src)]
    if not quick:
        cases.append((N_LONG, long_sequence(src)))
    rows, det, rss = [], {}, {}
    for n, seq in cases:
        # interleaved, the fastest of each (load only adds time), wall and CPU each their own minimum
        dec = cmd = None
        cpu = {"decode": math.inf, "command": math.inf}
        for _ in range(1 if quick else 2):
            d_, i_ = _run_decode(seq)
            c_, o_ = _run_command(seq, src, str(n))
            if dec is None or (d_.ok and d_.wall_s < dec.wall_s):
                dec, info = d_, i_
            if cmd is None or (c_.ok and c_.wall_s < cmd.wall_s):
                cmd, out = c_, o_
            if d_.ok:
                cpu["decode"] = min(cpu["decode"], d_.cpu_s)
            if c_.ok:
                cpu["command"] = min(cpu["command"], c_.cpu_s)
        d = {"decode": {"wall_s": dec.wall_s, "cpu_s": cpu["decode"], "in_process_s": info.get("seconds"),
                        "n_frames": info.get("n_frames"), "peak_rss_bytes": dec.peak_rss_bytes, "exit": dec.returncode},
             "command": {"wall_s": cmd.wall_s, "cpu_s": cpu["command"], "peak_rss_bytes": cmd.peak_rss_bytes,
                         "exit": cmd.returncode, "args": cmd.args}}
        if cmd.ok:
            tj = json.loads((out / "track.json").read_text())
            d["command"]["loop_effects"] = [s.get("effect") for s in (tj.get("loop") or {}).get("steps", [])]
            d["command"]["summary"] = tj.get("summary")
        else:
            d["command"]["stderr_tail"] = cmd.tail()
        det[str(n)] = d
        if cmd.ok:
            rss[n] = cmd.peak_rss_bytes
        say(f"  {n} frames/view: decode {fmt_s(dec.wall_s)} (CPU {fmt_s(cpu['decode'])}, in-process "
            f"{fmt_s(info.get('seconds'))}, peak {fmt_bytes(dec.peak_rss_bytes)}), bsipipe track "
            f"{fmt_s(cmd.wall_s) if cmd.ok else 'FAILED'} (CPU {fmt_s(cpu['command'])}, "
            f"peak {fmt_bytes(cmd.peak_rss_bytes)})")
        if not cmd.ok:
            say(cmd.tail())
        ok_both = cmd.ok and dec.ok
        rw = cmd.wall_s / dec.wall_s if ok_both else None
        rc = cpu["command"] / cpu["decode"] if ok_both else None
        why = (f"track exited {cmd.returncode}: {cmd.tail(3)}" if not cmd.ok else
               f"decode exited {dec.returncode}" if not dec.ok else "")
        note_w = (f"2 views x {n} frames, the faster of {1 if quick else 2} interleaved runs each; the command "
                  f"decodes on reader threads (one per core, at most 4) while it tracks, so it takes about the longer of "
                  f"decoding (spread over the cores) and tracking, plus its start-up; the peer decodes on one thread; decode child peak {fmt_bytes(dec.peak_rss_bytes)}" if ok_both else why)
        note_c = (f"CPU time (user + system) of the same runs, the smaller of each: what the command costs in all, "
                  f"whatever the cores; decoding is {100 * cpu['decode'] / cpu['command']:.0f} % of it at best"
                  if ok_both else why)
        vals = {"bsipipe_s": cmd.wall_s, "decode_s": dec.wall_s, "bsipipe_cpu_s": cpu["command"],
                "decode_cpu_s": cpu["decode"]}
        rows.append(Row(f"track command vs decode, {n} frames/view (wall)",
                        fmt_s(cmd.wall_s) if cmd.ok else "failed", f"decode {fmt_s(dec.wall_s)}", rw,
                        "bsipipe/peer wall time", "<= 1.5x", (rw <= TARGET_CMD_OVER_DECODE) if rw is not None else None,
                        note=note_w, values=vals))
        rows.append(Row(f"track command vs decode, {n} frames/view (CPU)",
                        f"CPU {fmt_s(cpu['command'])}" if cmd.ok else "failed", f"decode CPU {fmt_s(cpu['decode'])}",
                        rc, "bsipipe/peer CPU time", "<= 1.5x (CPU)",
                        (rc <= TARGET_CMD_OVER_DECODE) if rc is not None else None, note=note_c, values=vals))
    # the Kalman/RTS smoother's share (on by default): smooth_tracks timed in this process on
    # each command's own 2-D table, as the command calls it
    for n in (N_FRAMES, N_LONG):
        d = det.get(str(n))
        if d is None or d["command"]["exit"] != 0:
            continue
        t_sm = _time_smoothing(OUT / f"track{n}" / "markers2d.csv")
        d["smoothing"] = t_sm
        say(f"  {n} frames/view: Kalman/RTS smoothing (smooth_tracks on the command's markers2d.csv) CPU "
            f"{fmt_s(t_sm['cpu_s'])} ({1e3 * t_sm['cpu_s'] / (len(VIEWS) * n):.2f} ms/frame), "
            f"{100 * t_sm['cpu_s'] / d['command']['cpu_s']:.0f} % of the command's CPU")
        for r in rows:
            if r.benchmark == f"track command vs decode, {n} frames/view (CPU)":
                r.note += f"; of the command's CPU, Kalman/RTS smoothing {fmt_s(t_sm['cpu_s'])}"
    # the floor: at 200 frames the target leaves 0.5 x decode's CPU for everything else; what the
    # command must load and draw whatever tracking costs is set against it
    d = det.get(str(N_FRAMES))
    if d is not None and d["command"]["exit"] == 0:
        fl = _floor(OUT / f"track{N_FRAMES}", src, repeats=1 if quick else 2)
        room = (TARGET_CMD_OVER_DECODE - 1.0) * d["decode"]["cpu_s"]
        need = fl["imports_cpu_s"] + fl["figures_cpu_s"]
        d["floor"] = {**fl, "room_cpu_s": room}
        say(f"  {N_FRAMES} frames/view: the target leaves {fmt_s(room)} CPU beyond decoding; the libraries the "
            f"command needs and the decode child does not cost {fmt_s(fl['imports_cpu_s'])} to import and its two "
            f"figures {fmt_s(fl['figures_cpu_s'])} to draw: {fmt_s(need)} before one frame is tracked")
        for r in rows:
            if r.benchmark == f"track command vs decode, {N_FRAMES} frames/view (CPU)":
                r.note += (f"; floor without any tracking: imports {fmt_s(fl['imports_cpu_s'])} + figures "
                           f"{fmt_s(fl['figures_cpu_s'])} = {fmt_s(need)} against {fmt_s(room)} of room "
                           f"({'unreachable at this length' if need > room else 'reachable'})")
    # the 2-D-only command at 200 frames: what triangulation + loop add
    cmd2d, _ = _run_command(src, src, f"{N_FRAMES}_2d", calibration=False)
    det["command_2d_only_200"] = {"wall_s": cmd2d.wall_s, "cpu_s": cmd2d.cpu_s,
                                  "peak_rss_bytes": cmd2d.peak_rss_bytes, "exit": cmd2d.returncode}
    say(f"  {N_FRAMES} frames/view without --calibration (2-D only): {fmt_s(cmd2d.wall_s)} (CPU {fmt_s(cmd2d.cpu_s)})")
    if rows and cmd2d.ok:
        rows[0].note += f"; without --calibration (2-D only) CPU {fmt_s(cmd2d.cpu_s)}"

    # where the command's time goes: CPU = fixed (start-up, imports, loop, figures) + per frame,
    # from the two lengths (decode likewise); the per-frame parts are what 2,000 frames approach
    if not quick and all(str(n) in det and det[str(n)]["command"]["exit"] == 0 for n in (N_FRAMES, N_LONG)):
        per, fixed = {}, {}
        for k in ("command", "decode"):
            c0, c1 = det[str(N_FRAMES)][k]["cpu_s"], det[str(N_LONG)][k]["cpu_s"]
            per[k] = (c1 - c0) / (len(VIEWS) * (N_LONG - N_FRAMES))
            fixed[k] = c0 - per[k] * len(VIEWS) * N_FRAMES
        det["cpu_split"] = {"per_frame_s": per, "fixed_s": fixed}
        say(f"  CPU split: command {1e3 * per['command']:.2f} ms/frame + {fixed['command']:.2f} s fixed; decode "
            f"{1e3 * per['decode']:.2f} ms/frame + {fixed['decode']:.2f} s fixed; tracking adds "
            f"{1e3 * (per['command'] - per['decode']):.2f} ms/frame ({per['command'] / per['decode']:.2f}x decode "
            f"per frame)")
        rows[-1].note += (f"; CPU split from the two lengths: command {1e3 * per['command']:.2f} ms/frame + "
                          f"{fixed['command']:.1f} s fixed, decode {1e3 * per['decode']:.2f} ms/frame + "
                          f"{fixed['decode']:.1f} s fixed (per-frame ratio {per['command'] / per['decode']:.2f}x)")
    if quick or N_LONG not in rss or N_FRAMES not in rss:
        why = "skipped (--quick)" if quick else "a track run failed"
        rows.append(Row("track peak RSS, 2000 vs 200 frames/view",
                        fmt_bytes(rss.get(N_LONG)), f"200 frames: {fmt_bytes(rss.get(N_FRAMES))}", None,
                        "", "<= 1.2x, < 1 GiB", None, note=why))
    else:
        g = rss[N_LONG] / rss[N_FRAMES]
        rows.append(Row("track peak RSS, 2000 vs 200 frames/view", fmt_bytes(rss[N_LONG]),
                        f"200 frames: {fmt_bytes(rss[N_FRAMES])}", g, "2000/200 frames", "<= 1.2x, < 1 GiB",
                        g <= TARGET_RSS_GROWTH and rss[N_LONG] < TARGET_RSS_BYTES,
                        note="the same command at 200 frames is the reference; peak RSS = the child's VmHWM "
                             "(polled /proc)",
                        values={"rss_2000": rss[N_LONG], "rss_200": rss[N_FRAMES]}))
    return rows, det


def run(quick: bool = False, say=print) -> tuple[list[Row], dict]:
    t0 = time.perf_counter()
    src = twin_sequence(say)
    rows1, det1 = bench_detect_track(src, quick, say)
    rows2, det2 = bench_command(src, quick, say)
    return rows1 + rows2, {"source": str(src), "detect_track": det1, "command": det2,
                           "seconds": time.perf_counter() - t0}
