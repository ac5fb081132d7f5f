"""A twin study's results against the twin's truth: what the pipeline got right, in mm.

``bsipipe study`` on the twin (``make study``) writes, per trial, the twin's ``truth.json``
beside every stage's results, so the whole chain from the rendered frames to the FE
hand-off can be scored:

- **registration**: the registered reference markers against their true CT positions
  (``register/markers_ct.csv`` at the registration frame vs ``truth.ct.markers_mm``);
- **markers in the FE frame**: position and displacement of every implanted marker in
  ``export-fe/markers_fe.csv`` against the truth mapped into the CT frame, frame by frame;
- **indentor trajectory**: the flat end's path that export-fe hands to the FE model (its
  ``amplitude.csv`` knots, on the FE clock, mapped back to the X-ray clock with the clock
  offset and contact time of ``manifest.json``) against the true tip, at every X-ray frame
  between contact and the end of the amplitude.

``python scripts/twin_check.py results/sheep1`` prints it; :func:`twin_check` returns it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd


def _rms(v) -> float:
    v = np.asarray(v, float)
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")


def _stats(v) -> dict:
    v = np.asarray(v, float)
    if not v.size:
        return {"n": 0, "rms_mm": None, "max_mm": None, "p95_mm": None}
    return {"n": int(v.size), "rms_mm": _rms(v), "max_mm": float(v.max()), "p95_mm": float(np.quantile(v, 0.95))}


def twin_check(trial_dir) -> dict:
    """Errors (mm) of a twin trial's registration, FE-frame markers and indentor trajectory."""
    d = Path(trial_dir)
    truth = json.loads((d / "synth" / "truth.json").read_text())
    seq, ct = truth["sequence"], truth["ct"]
    kinds = {n: m["kind"] for n, m in seq["markers"].items()}
    per_frame = {n: np.asarray(v, float) for n, v in ct["markers_ct_mm_per_frame"].items()}
    out: dict = {"trial": str(d)}

    # registration: references at the registration frame
    reg = json.loads((d / "register" / "registration.json").read_text())
    mct = pd.read_csv(d / "register" / "markers_ct.csv")
    F = int(reg["frame"])
    at = mct[mct["frame"] == F].set_index("marker")
    ref_err = {n: float(np.linalg.norm(at.loc[n, ["x_mm", "y_mm", "z_mm"]].to_numpy(float) - per_frame[n][F]))
               for n in reg["references"]["used"] if n in at.index}
    out["registration"] = {"frame": F, "reference_error_mm": ref_err, **_stats(list(ref_err.values()))}

    # markers in the FE frame
    fe = pd.read_csv(d / "export-fe" / "markers_fe.csv")
    fe = fe[np.isfinite(fe["x_mm"])]
    pos, disp = {}, {}
    for name, g in fe.groupby("marker"):
        if kinds.get(name) != "implanted":
            continue
        T = per_frame[name][g["frame"].to_numpy(int)]
        X = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        D = g[["dx_mm", "dy_mm", "dz_mm"]].to_numpy(float)
        pos[name] = np.linalg.norm(X - T, axis=1)
        # a displacement needs the marker at the registration frame (one hidden there has none)
        ok = np.isfinite(D).all(axis=1)
        if ok.any():
            disp[name] = np.linalg.norm(D[ok] - (T[ok] - per_frame[name][0]), axis=1)
    allp = np.concatenate(list(pos.values())) if pos else np.array([])
    alld = np.concatenate(list(disp.values())) if disp else np.array([])
    out["markers_fe"] = {"position": _stats(allp), "displacement": _stats(alld),
                         "displacement_rms_per_marker_mm": {n: _rms(v) for n, v in disp.items()}}
    # the position errors over the sds track states for the same points (a rigid map keeps
    # lengths: |error| over sqrt(sd_x^2 + sd_y^2 + sd_z^2), RMS 1 when the sds hold)
    p3 = pd.read_csv(d / "track" / "markers3d.csv")
    if {"sd_x_mm", "sd_y_mm", "sd_z_mm"} <= set(p3.columns):
        sd = p3.set_index(["frame", "marker"])[["sd_x_mm", "sd_y_mm", "sd_z_mm"]]
        z = []
        for name, g in fe.groupby("marker"):
            if name not in pos:
                continue
            s3 = sd.reindex(pd.MultiIndex.from_arrays([g["frame"].to_numpy(int), [name] * len(g)])).to_numpy(float)
            z.append(pos[name] / np.sqrt((s3 ** 2).sum(axis=1)))
        z = np.concatenate(z) if z else np.array([])
        z = z[np.isfinite(z)]
        out["markers_fe"]["position_over_stated_sd"] = {"n": int(z.size), "z_rms": _rms(z) if z.size else None}

    # indentor trajectory handed to the FE model
    man = json.loads((d / "export-fe" / "manifest.json").read_text())
    amp = pd.read_csv(d / "export-fe" / "amplitude.csv")
    tip = np.asarray(seq["indentor"]["tip_ct_mm"], float)
    t_x = np.asarray(seq["times_s"]["cam1"], float)
    t_fe = t_x - float(man["trajectory"]["clock_offset_s"]) - float(man["indentor"]["contact"]["log_time_s"])
    inside = (t_fe >= 0) & (t_fe <= amp["time_s"].max())
    est = np.column_stack([np.interp(t_fe, amp["time_s"], amp[c]) for c in ("tip_x_mm", "tip_y_mm", "tip_z_mm")])
    err = np.linalg.norm(est - tip, axis=1)[inside]
    depth_true = float(seq["indentor"]["depth_mm"])           # the log's whole indentation
    out["indentor"] = {"source": man["indentor"]["source"], "trajectory": _stats(err),
                       "depth_mm": float(man["indentor"]["depth_mm"]), "depth_true_mm": depth_true,
                       "contact_point_error_mm": float(np.linalg.norm(
                           np.asarray(man["indentor"]["contact_point_ct_mm"], float)
                           - (tip[0] + float(seq["indentor"]["gap_mm"]) * _ct_direction(truth))))}
    return out


def _ct_direction(truth: dict) -> np.ndarray:
    R = np.asarray(truth["ct"]["R"], float)
    n = R @ np.asarray(truth["sequence"]["indentor"]["direction"], float)
    return n / np.linalg.norm(n)


def format_check(c: dict) -> str:
    r, m, i = c["registration"], c["markers_fe"], c["indentor"]
    f = lambda s: "n/a" if s["n"] == 0 else f"RMS {s['rms_mm']:.4f} mm, max {s['max_mm']:.4f} mm (n = {s['n']})"  # noqa: E731
    return "\n".join([
        f"registration (references at frame {r['frame']}): {f(r)}",
        f"implanted markers, FE frame: position {f(m['position'])}",
        f"implanted markers, FE frame: displacement {f(m['displacement'])}",
        *([f"implanted markers, FE frame: position error over the stated 3-D sd, RMS "
           f"{m['position_over_stated_sd']['z_rms']:.2f} (n = {m['position_over_stated_sd']['n']})"]
          if m.get("position_over_stated_sd", {}).get("z_rms") is not None else []),
        f"indentor trajectory ({i['source']}): {f(i['trajectory'])}",
        f"indentor depth {i['depth_mm']:.4f} mm (true {i['depth_true_mm']:.4f}); contact point error "
        f"{i['contact_point_error_mm']:.4f} mm",
    ])
