"""Perturb a rendered twin's frames with an effect the twin does not render, track, score.

    python scripts/track_probe.py EFFECT [--no-seeds] [--old]      (after ``make bench``)

EFFECT: ``none``, ``dust`` (25 static specks per view, 10 of them within a few px of the
markers' paths, 35 % darker than the background: harsher than a bead), ``dust2`` (40 static
bead-like specks per view scattered over the markers' region), ``lag05`` (cam2's
intensifier lag: each frame half the previous), ``lag03both`` (both views averaged, y = 0.7 x
+ 0.3 y_prev: a lag they share), ``flicker`` (15 % frame-to-frame gain),
``interlace`` (odd lines from the previous frame), ``saltpepper`` (2,000 impulse pixels per
frame), ``late`` (cam2 starts 6 frames late), ``invert`` (bright beads), ``vignette``
(brightness falling to 35 % at the field's edge; applied to the recorded frames, so the air
clipped at 255 becomes a flat grey without noise, which no detector would see in a real
frame: automatic mode's whole-frame noise statistics are misled by it), ``noise2`` (extra pixel noise, sd 4),
``bits16`` (10-bit data in 16-bit files), ``blur`` (a further Gaussian blur of 1.2 px),
``dup`` (cam2 repeats every 7th frame and drops the next), ``log`` (log-converted 16-bit
frames), ``grid`` (anti-scatter grid stripes, period 3.3 px, +-3 grey levels), ``glare``
(veiling glare: 30 % of the light spread over ~50 px), ``abc`` (automatic brightness control:
gain -30 % and offset +20 over the middle third), ``jpeg`` (JPEG files, OpenCV's default
quality 95), ``mp4`` (an MPEG-4 part 2 video per view, lossy), ``mjpg`` (a Motion-JPEG AVI per view), ``blank`` (missed exposures: every 23rd frame
of cam2 dark noise only), ``burnin`` (text burned in by the C-arm's video output: a frame
counter and clock in the corners outside the field, a patient line, kV/mA, a laterality
letter "L" inside the field).  The twin is the track benchmark's
(``results/bench_cache/twin200``: 200 frames per view at 4 frames/s, its seeds and true
cameras); the perturbed frames go to ``/tmp/bsipipe_probe/EFFECT`` and are tracked by the
current code with ``bsipipe track`` (``--old``: the output goes to ``track_old``, for a
run with another checkout first on PYTHONPATH).  Printed: ``scripts/track_recall.py``'s
score, the loop's named effects and the 3-D error against the twin's truth (raw and
smoothed, and rigidly aligned).
"""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
sys.path.insert(0, str(Path(__file__).resolve().parent))
from track_recall import score
SRC = Path(__file__).resolve().parents[1] / "results" / "bench_cache" / "twin200"
def frames(v): return sorted((SRC / "sequence" / v).glob("*.png"))
rng = np.random.default_rng(1)

def dust(v, imgs):
    # static dark specks (intensifier dust / dead pixels) of marker size, 25 per view, some on marker paths
    tr = pd.read_csv(SRC / "truth_markers.csv"); t = tr[tr.view == v]
    pts = t[["x_px", "y_px"]].to_numpy()[rng.choice(len(t), 10)] + rng.normal(0, 3, (10, 2))
    pts = np.r_[pts, rng.uniform(200, 800, (15, 2))]
    out = []
    for im in imgs:
        f = im.astype(np.float32)
        yy, xx = np.mgrid[:f.shape[0], :f.shape[1]]
        for x, y in pts:
            sl = (slice(int(y) - 6, int(y) + 7), slice(int(x) - 6, int(x) + 7))
            d2 = (xx[sl] - x) ** 2 + (yy[sl] - y) ** 2
            f[sl] *= 1 - 0.35 * np.exp(-d2 / (2 * 1.3 ** 2))
        out.append(np.clip(f, 0, 255).astype(np.uint8))
    return out

def lag(a, views=("cam2",)):
    def fx(v, imgs):
        if v not in views: return imgs
        out, acc = [], None
        for im in imgs:
            acc = im.astype(np.float32) if acc is None else (1 - a) * im + a * acc
            out.append(np.clip(np.rint(acc), 0, 255).astype(np.uint8))
        return out
    return fx

def flicker(v, imgs):
    g = 1 + 0.15 * rng.standard_normal(len(imgs))
    return [np.clip(im.astype(np.float32) * k, 0, 255).astype(np.uint8) for im, k in zip(imgs, g)]

def interlace(v, imgs):
    # each frame's odd lines from the previous frame (field capture)
    out = [imgs[0]]
    for a, b in zip(imgs, imgs[1:]):
        c = b.copy(); c[1::2] = a[1::2]; out.append(c)
    return out

def saltpepper(v, imgs):
    out = []
    for im in imgs:
        c = im.copy(); n = 2000
        ys, xs = rng.integers(0, 1024, n), rng.integers(0, 1024, n)
        c[ys[:n//2], xs[:n//2]] = 0; c[ys[n//2:], xs[n//2:]] = 255
        out.append(c)
    return out

def late(v, imgs):
    return imgs if v == "cam1" else imgs[6:]

def dust2(v, imgs):
    # 40 static specks per view, marker-like (8-25 % darker, sigma 1-1.8 px), uniform over the markers' region
    tr = pd.read_csv(SRC / "truth_markers.csv"); t = tr[tr.view == v]
    lo, hi = t[["x_px", "y_px"]].min().to_numpy() - 30, t[["x_px", "y_px"]].max().to_numpy() + 30
    r = np.random.default_rng(7 if v == "cam1" else 8)
    pts = r.uniform(lo, hi, (40, 2)); depth = r.uniform(0.08, 0.25, 40); sig = r.uniform(1.0, 1.8, 40)
    yy, xx = np.mgrid[:1024, :1024].astype(np.float32)
    m = np.ones((1024, 1024), np.float32)
    for (x, y), a, sg in zip(pts, depth, sig):
        sl = (slice(int(y) - 8, int(y) + 9), slice(int(x) - 8, int(x) + 9))
        m[sl] *= 1 - a * np.exp(-((xx[sl] - x) ** 2 + (yy[sl] - y) ** 2) / (2 * sg ** 2))
    return [np.clip(np.rint(im.astype(np.float32) * m), 0, 255).astype(np.uint8) for im in imgs]

def invert(v, imgs):
    # frames exported inverted (a processed radiograph): the beads are bright
    return [255 - im for im in imgs]

def vignette(v, imgs):
    # an intensifier's brightness falling to 35 % at the field's edge
    yy, xx = np.mgrid[:1024, :1024].astype(np.float32)
    g = 1 - 0.65 * np.clip(((xx - 512) ** 2 + (yy - 512) ** 2) / 512 ** 2, 0, 1)
    return [np.clip(np.rint(im * g), 0, 255).astype(np.uint8) for im in imgs]

def noise2(v, imgs):
    # extra Gaussian pixel noise of sd 4 grey levels (about twice the twin's)
    return [np.clip(np.rint(im + rng.normal(0, 4, im.shape)), 0, 255).astype(np.uint8) for im in imgs]

def bits16(v, imgs):
    # 10-bit data in 16-bit files, scaled by 4 with 2 bits of fresh noise, offset 100
    return [(im.astype(np.uint16) * 4 + 100 + rng.integers(0, 4, im.shape)).astype(np.uint16) for im in imgs]

def blur(v, imgs):
    # intensifier unsharpness: a Gaussian blur of sigma 1.2 px
    return [cv2.GaussianBlur(im, (0, 0), 1.2) for im in imgs]

def dup(v, imgs):
    # cam2's frame grabber repeats every 7th frame and drops the next (the count stays the same)
    if v != "cam2": return imgs
    out = list(imgs)
    for k in range(7, len(imgs) - 1, 7):
        out[k] = imgs[k - 1]
    return out

def logimg(v, imgs):
    # the log of the intensity (line integrals of attenuation, as a log-converted radiograph), 16-bit
    return [np.rint(np.log(im.astype(np.float64) + 1) / np.log(256) * 65535).astype(np.uint16) for im in imgs]

def grid(v, imgs):
    # an anti-scatter grid's lines: horizontal stripes of period 3.3 px, +-3 grey levels
    yy = np.arange(1024, dtype=np.float32)[:, None]
    g = 3.0 * np.sin(2 * np.pi * yy / 3.3)
    return [np.clip(np.rint(im + g), 0, 255).astype(np.uint8) for im in imgs]

def glare(v, imgs):
    # veiling glare of the intensifier: 30 % of the light spread over ~50 px (contrast down)
    return [np.clip(np.rint(0.7 * im + 0.3 * cv2.GaussianBlur(im.astype(np.float32), (0, 0), 50)), 0, 255)
            .astype(np.uint8) for im in imgs]

def abc(v, imgs):
    # automatic brightness control: gain falls 30 % and the offset rises 20 grey levels over the
    # middle of the sequence (the instrument enters the field), smoothly
    n = len(imgs)
    out = []
    for k, im in enumerate(imgs):
        a = 0.5 - 0.5 * np.cos(np.pi * min(max((k - n / 3) / (n / 3), 0), 1))
        out.append(np.clip(np.rint(im * (1 - 0.3 * a) + 20 * a), 0, 255).astype(np.uint8))
    return out

def blank(v, imgs):
    # missed exposures (pulsed fluoroscopy): every 23rd frame of cam2 only dark noise, no picture
    if v != "cam2": return imgs
    out = list(imgs)
    for k in range(11, len(imgs), 23):
        out[k] = np.clip(np.rint(rng.normal(12, 2, imgs[k].shape)), 0, 255).astype(np.uint8)
    return out

def burnin(v, imgs):
    # text burned into the frames by the C-arm's video output, as its monitor shows it: a frame
    # counter and a clock in the corners outside the circular field (white and dark), a patient
    # line, and the letter "L" over the picture (where the field's edge is, in the twin at about 95 px)
    out = []
    for k, im in enumerate(imgs):
        c = im.copy()
        cv2.putText(c, f"FR {k:04d}", (12, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 255, 2, cv2.LINE_AA)
        cv2.putText(c, f"T {k / 4:07.2f}s", (860, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 255, 1, cv2.LINE_AA)
        cv2.putText(c, "SHEEP-1  2026-11-22", (12, 1010), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 200, 1, cv2.LINE_AA)
        cv2.putText(c, "kV 70 mA 2.1", (860, 1010), cv2.FONT_HERSHEY_SIMPLEX, 0.5, 40, 1, cv2.LINE_AA)
        cv2.putText(c, "L", (200, 300), cv2.FONT_HERSHEY_SIMPLEX, 1.0, 255, 2, cv2.LINE_AA)
        out.append(c)
    return out

def same(v, imgs):
    return imgs

#: effects written in another file format than PNG: the extension (a folder of JPEG files) or a
#: video container (one file per view)
FORMATS = {"jpeg": ".jpg", "mp4": ".mp4", "mjpg": ".avi"}

EFFECTS = {"grid": grid, "glare": glare, "abc": abc, "jpeg": same, "mp4": same, "mjpg": same, "log": logimg, "invert": invert, "vignette": vignette, "noise2": noise2, "bits16": bits16, "blur": blur, "dup": dup,
           "dust2": dust2, "late": late, "none": lambda v, i: i, "dust": dust, "lag05": lag(0.5), "lag03both": lag(0.3, ("cam1", "cam2")), "flicker": flicker, "interlace": interlace,
           "saltpepper": saltpepper, "blank": blank, "burnin": burnin}


def err3d(synth: Path, track: Path) -> None:
    """3-D RMS error of the raw and smoothed points against the twin's truth (cam1's frame),
    as written and rigidly aligned."""
    t = json.loads((synth / "truth.json").read_text())
    p = pd.read_csv(track / "markers3d.csv")
    R1, t1 = np.asarray(t["cameras"]["cam1"]["R"]), np.asarray(t["cameras"]["cam1"]["t_mm"])
    traj = t["sequence"]["trajectories_mm"]
    for cols in (["x_mm_raw", "y_mm_raw", "z_mm_raw"], ["x_mm", "y_mm", "z_mm"]):
        q = p.dropna(subset=cols)
        q = q[q["marker"].isin(traj)]
        T = np.array([traj[m][f] for m, f in zip(q["marker"], q["frame"])]) @ R1.T + t1
        if q["time_s"].notna().all():
            # the truth where the points are dated (time_s, frames at 4 frames/s): a lag put right
            fq = q["time_s"].to_numpy() * 4.0
            Tt = np.array([[np.interp(fk, np.arange(len(traj[m])), np.asarray(traj[m])[:, k]) for k in range(3)]
                           for m, fk in zip(q["marker"], fq)]) @ R1.T + t1
            et = np.linalg.norm(q[cols].to_numpy() - Tt, axis=1)
            print(f"{cols[0]}: 3-D RMS against the truth at time_s {np.sqrt(np.mean(et ** 2)):.4f} mm "
                  f"(max {et.max():.4f})")
        X = q[cols].to_numpy()
        e0 = np.linalg.norm(X - T, axis=1)
        mx, mt = X.mean(0), T.mean(0)
        U, _, Vt = np.linalg.svd((X - mx).T @ (T - mt))
        R = (U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt).T
        e = np.linalg.norm((X - mx) @ R.T + mt - T, axis=1)
        print(f"{cols[0]}: 3-D RMS {np.sqrt(np.mean(e0 ** 2)):.4f} mm, rigidly aligned {np.sqrt(np.mean(e ** 2)):.4f} "
              f"(max {e.max():.4f}) over {len(e)} points")


if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
    sys.exit(__doc__)
name, extra = sys.argv[1], sys.argv[2:]
work = Path("/tmp/bsipipe_probe") / name
if not (work / "synth" / "truth_markers.csv").exists():
    shutil.rmtree(work, ignore_errors=True)
    for v in ("cam1", "cam2"):
        imgs = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in frames(v)]
        imgs = EFFECTS[name](v, imgs)
        ext = FORMATS.get(name, ".png")
        if ext in (".mp4", ".avi"):
            (work / "sequence").mkdir(parents=True, exist_ok=True)
            wr = cv2.VideoWriter(str(work / "sequence" / f"{v}{ext}"),
                                 cv2.VideoWriter_fourcc(*("mp4v" if ext == ".mp4" else "MJPG")), 4.0,
                                 imgs[0].shape[::-1], False)
            for im in imgs: wr.write(im)
            wr.release()
        else:
            d = work / "sequence" / v; d.mkdir(parents=True)
            for k, im in enumerate(imgs): cv2.imwrite(str(d / f"frame_{k:04d}{ext}"), im)
    (work / "synth").mkdir()
    for f in ("truth_markers.csv", "truth.json"): shutil.copy(SRC / f, work / "synth" / f)
out = work / ("track" + ("_auto" if "--no-seeds" in extra else "") + ("_old" if "--old" in extra else ""))
shutil.rmtree(out, ignore_errors=True)
src = {v: work / "sequence" / (v + (FORMATS.get(name, "") if FORMATS.get(name) in (".mp4", ".avi") else ""))
       for v in ("cam1", "cam2")}
cmd = [sys.executable, "-m", "bsipipe.cli", "-q", "track", "--view", f"cam1={src['cam1']}", "--view", f"cam2={src['cam2']}",
       "--calibration", str(SRC / "calibration.json"), "--fps", "4", "-o", str(out)]
if "--no-seeds" not in extra: cmd += ["--seeds", str(SRC / "seeds.csv")]
r = subprocess.run(cmd, capture_output=True, text=True)
print(r.stdout[-1500:], r.stderr[-1500:] if r.returncode else "")
s = score(work / "synth", out, auto="--no-seeds" in extra)
print(name, {k: s[k] for k in ("visible", "found_1px", "off_1px", "swaps", "clutter", "z_rms", "worst")})
j = json.load(open(out / "track.json"))
print("loop:", j["loop"]["final"]["model"], "ray gap RMS", round(j["loop"]["baseline"]["ray_gap_rms_mm"], 4), "->",
      round(j["loop"]["final"]["ray_gap_rms_mm"], 4))
err3d(work / "synth", out)
