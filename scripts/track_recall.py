"""Score ``bsipipe track`` against a twin's truth, per trial and per marker.

    python scripts/track_recall.py results/sheep1 [TRIAL_DIR ...] [--mp4 WORKDIR | --retrack WORKDIR] [--no-seeds]

Each TRIAL_DIR is a study trial (``synth/`` with ``truth_markers.csv``, ``track/`` with
``markers2d.csv`` and ``markers3d.csv``).  Printed per trial: the visible positions (truth
``visible``) found within 1 px of the truth, the positions more than 1 px off their marker
(on another marker: an identity swap; elsewhere: clutter), the two-view 3-D points, the
RMS of each position's error over its stated sd (``sd_px``, ``sd_px_smooth``; 1 when the
stated errors are honest), and the markers that miss the most.  ``--mp4 WORKDIR``: the trial's frames are first written to MP4
(OpenCV ``mp4v`` at its default quality, the trial's frame rate) in ``WORKDIR/<trial>`` and
tracked there with the trial's own track config: the same score on compressed video.
``--retrack WORKDIR``: the trial's own frames are tracked again with its track config into
``WORKDIR/<trial>/track`` (the current code on the study's frames, its outputs left alone).
``--no-seeds`` (with ``--mp4`` or ``--retrack``): tracked without the seeds (automatic mode);
each track then takes the name of the true marker it lies within 1 px of most often (a
track on none, or a second track on one marker, keeps its own name and counts as off).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd


def name_by_truth(tk: pd.DataFrame, tr: pd.DataFrame) -> pd.DataFrame:
    """Automatic tracks renamed, per view, after the true marker each lies within 1 px of most
    often (the track with the most such positions wins a marker; the others keep their
    names, prefixed ``auto:``)."""
    out = []
    for v, t in tk.groupby("view"):
        m = t[t["found"].astype(bool)].merge(tr[tr["view"] == v], on="frame", suffixes=("", "_t"))
        m = m[np.hypot(m["x_px"] - m["x_px_t"], m["y_px"] - m["y_px_t"]) <= 1.0]
        votes = m.groupby(["marker", "marker_t"]).size().sort_values(ascending=False)
        names, used = {}, set()
        for (trk, true), _ in votes.items():
            if trk not in names and true not in used:
                names[trk] = true
                used.add(true)
        out.append(t.assign(marker=t["marker"].map(lambda k: names.get(k, f"auto:{k}"))))
    return pd.concat(out, ignore_index=True)


def score(synth_dir: Path, track_dir: Path, auto: bool = False) -> dict:
    tr = pd.read_csv(synth_dir / "truth_markers.csv", dtype={"marker": str, "view": str})
    tk = pd.read_csv(track_dir / "markers2d.csv", dtype={"marker": str, "view": str})
    if auto:
        tk = name_by_truth(tk, tr)
    if "shift_x_px" in tk:
        # the smoothed centres have the loop's frame shifts taken out; the truth's 2-D
        # positions carry the jolts (they are where the markers' images are): put them back
        for a in ("x", "y"):
            tk[f"{a}_px_smooth"] = tk[f"{a}_px_smooth"] + tk[f"shift_{a}_px"].fillna(0.0)
    extra = [c for c in ("sd_px", "x_px_smooth", "y_px_smooth", "sd_px_smooth") if c in tk]
    m = tr.merge(tk[["view", "frame", "marker", "x_px", "y_px", "found", *extra]], on=["view", "frame", "marker"],
                 suffixes=("_t", ""), how="left")
    unowned = tk[tk["marker"].str.startswith("auto:") & tk["found"].astype(bool)]
    m["found"] = m["found"].astype("boolean").fillna(False).astype(bool)
    m["err"] = np.hypot(m["x_px"] - m["x_px_t"], m["y_px"] - m["y_px_t"])
    vis = m["visible"].astype(bool)
    hit = vis & m["found"] & (m["err"] <= 1.0)
    off = m[m["found"] & ~(m["err"] <= 1.0)]
    n_unowned = int(len(unowned))
    swap = 0
    for r in off.itertuples():
        o = tr[(tr["view"] == r.view) & (tr["frame"] == r.frame) & (tr["marker"] != r.marker)]
        swap += int(np.hypot(o["x_px"] - r.x_px, o["y_px"] - r.y_px).min() < 1.5) if len(o) else 0
    p3 = pd.read_csv(track_dir / "markers3d.csv") if (track_dir / "markers3d.csv").exists() else None
    per = (m.assign(vis=vis, hit=hit).groupby(["view", "marker"])[["vis", "hit"]].sum()
           .assign(missed=lambda d: d["vis"] - d["hit"]).sort_values("missed", ascending=False))
    # the stated errors against the truth: z = error / sd per axis, RMS over the visible found positions
    z_rms = {}
    for name, (x, y, sd) in {"raw": ("x_px", "y_px", "sd_px"),
                             "smoothed": ("x_px_smooth", "y_px_smooth", "sd_px_smooth")}.items():
        if sd in m:
            f = m[vis & m["found"]]
            z = np.r_[(f[x] - f["x_px_t"]) / f[sd], (f[y] - f["y_px_t"]) / f[sd]]
            z = z[np.isfinite(z)]
            z_rms[name] = float(np.sqrt(np.mean(z ** 2))) if len(z) else float("nan")
    return {"visible": int(vis.sum()), "found_1px": int(hit.sum()), "off_1px": int(len(off)) + n_unowned,
            "swaps": swap, "z_rms": z_rms,
            "clutter": int(len(off)) - swap + n_unowned,
            "two_view": None if p3 is None else int((p3["n_views"] == 2).sum()),
            "worst": [(v, mk, int(r.hit), int(r.vis)) for (v, mk), r in per.head(3).iterrows() if r.missed > 0]}


def retrack(trial: Path, work: Path, seeds: bool = True, mp4: bool = False) -> Path:
    """Track the trial's frames again with its own track config into ``work/track``
    (``seeds`` False: without its seeds; ``mp4``: from its frames written as MP4, OpenCV's
    ``mp4v`` at its default quality and the trial's frame rate); returns the track output."""
    import yaml

    work.mkdir(parents=True, exist_ok=True)
    cfg = yaml.safe_load((trial / "config" / "track.yaml").read_text())
    if mp4:
        import cv2

        fps = float(cfg.get("fps") or 2.0)
        for v, src in cfg["views"].items():
            frames = sorted(Path(src).glob("*.png"), key=lambda p: [int(t) if t.isdigit() else t
                                                                   for t in re.split(r"(\d+)", p.name)])
            first = cv2.imread(str(frames[0]), cv2.IMREAD_GRAYSCALE)
            out = cv2.VideoWriter(str(work / f"{v}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                  first.shape[::-1], isColor=False)
            for f in frames:
                out.write(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))
            out.release()
            cfg["views"][v] = str(work / f"{v}.mp4")
    if not seeds:
        cfg["seeds"] = None
    (work / "track.yaml").write_text(yaml.safe_dump(cfg))
    subprocess.run([sys.executable, "-m", "bsipipe.cli", "-q", "track", str(work / "track.yaml"),
                    "-o", str(work / "track")], check=True, stdout=subprocess.DEVNULL)
    return work / "track"


if __name__ == "__main__":
    args = sys.argv[1:]
    if not args or args[0] in ("-h", "--help"):
        sys.exit(__doc__)
    mp4 = again = None
    if "--mp4" in args:
        i = args.index("--mp4")
        mp4 = Path(args[i + 1])
        del args[i:i + 2]
    auto = "--no-seeds" in args
    args = [a for a in args if a != "--no-seeds"]
    if "--retrack" in args:
        i = args.index("--retrack")
        again = Path(args[i + 1])
        del args[i:i + 2]
    total = {"visible": 0, "found_1px": 0, "off_1px": 0}
    for d in (Path(a) for a in args if (Path(a) / "synth" / "truth_markers.csv").exists()):
        track = (retrack(d, mp4 / d.name, not auto, mp4=True) if mp4 is not None else
                 retrack(d, again / d.name, not auto) if again is not None else d / "track")
        s = score(d / "synth", track, auto)
        for k in total:
            total[k] += s[k]
        print(f"{d}{' (MP4)' if mp4 else ''}{' (no seeds)' if auto else ''}: found within 1 px {s['found_1px']}/{s['visible']} "
              f"({100 * s['found_1px'] / s['visible']:.2f} %); off > 1 px {s['off_1px']} (swaps {s['swaps']}, "
              f"clutter {s['clutter']}); two-view points {s['two_view']}; error / stated sd, z RMS "
              + (", ".join(f"{k} {v:.2f}" for k, v in s["z_rms"].items()) or "n/a") + "; most missed "
              + ", ".join(f"{v} {mk} {h}/{n}" for v, mk, h, n in s["worst"]))
    if total["visible"] and len(args) > 1:
        print(f"all: found within 1 px {total['found_1px']}/{total['visible']} "
              f"({100 * total['found_1px'] / total['visible']:.2f} %); off > 1 px {total['off_1px']}")
