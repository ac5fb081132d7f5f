"""Benchmark ``loop``: the whole fit-ogden loop on two 5,000-point logs, FE effect included (issue 3).

Data (generated once into ``results/bench_cache/loop_logs``): two sheep-brain-like cylinders
bonded to the platens (``boundary='no-slip'``: the machine-log twin runs its own axisymmetric
felupe FE at the exact alpha, on the fit tables' mesh), 18 x 12 mm and 18 x 9 mm, one-term
Ogden mu 720 Pa, alpha -4.7, 4 mm/min to 30 % strain, 5,000 samples each, 1 mN load noise,
written in the Bluehill 3 layout with the geometry in the metadata.  The twin shares the
tables' mesh because a different one moves the force by 0.25-0.4 % where the free surface
folds onto the platen (40 against 32 radial cells, near 20 % compression, up to 1.75 mN,
RMS 0.6-0.7 mN): within the model's 1 % refinement bound but above the 1 mN load noise, so
the loop finds structure it cannot attribute.  With 40-cell logs the fit of HEAD 4e59307
added ``viscoelastic-relaxation`` (g 0.023, tau 9 s) beside ``no-slip-platens`` to absorb it;
with the refined contact the residual sits at the 5 % noise threshold and mu is 1.2 % low.
The logs are regenerated when the no-slip model (its table version) or the twin's mesh
changes.

- **bsipipe**: the command a user runs, ``bsipipe fit-ogden A.csv B.csv -o DIR`` with no
  ``--boundary`` (so ``no-slip-platens`` is a candidate beside the five other effects), in a
  child process: reading, contact detection, the loop (every candidate fitted jointly to both
  logs, held-out error over interleaved blocks, the FE tables), figures and FE cards.  Judged
  with ``--bootstrap 0`` (the loop; target within 60 s on 2 cores, judged on the child's CPU
  time, which load inflates far less than its wall time); the default command, which
  adds a 200-resample bootstrap of the final model, is timed too (full runs, no target).
- **peer**: felupe, one axisymmetric FE compression of the 18 x 12 mm cylinder to 30 %
  (:func:`bsipipe.mechanics.noslip.noslip_simulate`, the package's default 32-cell mesh, the
  stretches of the FE tables): what a single no-slip force curve costs when it is solved
  instead of read from the tables.  The ratio says how many such solves the whole loop costs.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

from .common import CACHE, OUT, Row, bsipipe_exe, fmt_bytes, fmt_s, run_child, timed

N_POINTS = 5000
TARGET_S = 60.0
SPECIMENS = (("bonded_18x12", 12.0, 21), ("bonded_18x9", 9.0, 22))
TRUTH = {"mu_pa": 720.0, "alpha": -4.7}
LOG_KW = dict(n_points=N_POINTS, diameter_mm=18.0, max_strain=0.3, boundary="no-slip", noise_n=1e-3,
              mu_pa=TRUTH["mu_pa"], alpha=TRUTH["alpha"])
CACHE_VERSION = 2


def make_logs(say=print) -> list[Path]:
    """The two Bluehill 3 logs (cached: the twin's FE takes tens of seconds per specimen)."""
    from bsipipe.mechanics.noslip import DEFAULT_MESH, TABLE_VERSION
    from bsipipe.synth.machine_log import synth_compression_log, write_bluehill3

    folder = CACHE / "loop_logs"
    stamp = folder / "stamp.json"
    kw = {**LOG_KW, "noslip_mesh_radial": DEFAULT_MESH.n_radial}
    want = json.loads(json.dumps({"version": CACHE_VERSION, "specimens": SPECIMENS, "kw": kw,
                                  "noslip_table_version": TABLE_VERSION}))
    paths = [folder / f"{name}.csv" for name, _, _ in SPECIMENS]
    if stamp.exists() and all(p.exists() for p in paths):
        have = json.loads(stamp.read_text())
        if {k: have.get(k) for k in want} == want:
            return paths
    folder.mkdir(parents=True, exist_ok=True)
    models = []
    for (name, h, seed), p in zip(SPECIMENS, paths):
        say(f"loop: generating {p.name} (the twin's FE, once)")
        frame, truth = synth_compression_log(height_mm=h, seed=seed, **kw)
        models.append(truth["noslip_model"])
        write_bluehill3(frame, p, label=name, geometry={"diameter_mm": 18.0, "height_mm": h})
    stamp.write_text(json.dumps({**want, "noslip_model": models}))
    return paths


def logs_noslip_model() -> list | None:
    """How the cached logs' bonded-platen force was made (e.g. ``FE, 32 radial cells``)."""
    stamp = CACHE / "loop_logs" / "stamp.json"
    return json.loads(stamp.read_text()).get("noslip_model") if stamp.exists() else None


def read_logs(paths):
    """LogData as the command builds them (reader, detected contact, geometry from the file)."""
    from bsipipe.io.machine_log import read_machine_log
    from bsipipe.mechanics.contact import detect_contact
    from bsipipe.mechanics.fit import LogData

    logs = []
    for p in paths:
        ml = read_machine_log(p)
        disp, force = ml.compression()
        c = detect_contact(ml.time_s, disp, force)
        logs.append(LogData(Path(p).stem, ml.time_s, disp, force, ml.geometry["diameter_mm"],
                            ml.geometry["height_mm"], c.displacement_mm))
    return logs


def _command(paths, tag: str, extra=()):
    out = OUT / f"fit_ogden{tag}"
    shutil.rmtree(out, ignore_errors=True)
    cmd = run_child([bsipipe_exe(), "-q", "fit-ogden", *map(str, paths), "-o", str(out), *extra], timeout_s=1800)
    fit = json.loads((out / "fit.json").read_text()) if cmd.ok else {}
    info = {"wall_s": cmd.wall_s, "cpu_s": cmd.cpu_s, "peak_rss_bytes": cmd.peak_rss_bytes, "exit": cmd.returncode,
            "args": cmd.args,
            "effects": [s["effect"] for s in fit.get("loop", {}).get("steps", [])],
            "final": fit.get("spec", {}).get("description"), "params": fit.get("params")}
    if not cmd.ok:
        info["stderr_tail"] = cmd.tail()
    return cmd, info


def _say_command(say, label, cmd, info):
    if cmd.ok:
        p = info["params"]
        say(f"  {label}: {fmt_s(cmd.wall_s)} (CPU {fmt_s(cmd.cpu_s)}), peak RSS {fmt_bytes(cmd.peak_rss_bytes)}, "
            f"effects {info['effects']}, {info['final']}: mu {p['mu_pa']:.1f} Pa, alpha {p['alpha']:.3f} "
            "(truth 720, -4.7)")
    else:
        say(f"  {label} FAILED (exit {cmd.returncode}):\n{cmd.tail()}")


def run(quick: bool = False, say=print) -> tuple[list[Row], dict]:
    paths = make_logs(say)
    details: dict = {"logs": [str(p) for p in paths], "truth": TRUTH, "n_points": N_POINTS,
                     "noslip_model": logs_noslip_model()}

    # The FE tables ship with the package for these aspects; where they do not (a table
    # version bumped and not rebuilt yet), the first use builds and caches them (minutes): a
    # one-time cost, done here untimed so that it does not count as the loop's.
    from bsipipe.mechanics.noslip import noslip_table
    for _, h, _ in SPECIMENS:
        t0 = time.perf_counter()
        noslip_table(h / 18.0)
        if time.perf_counter() - t0 > 2.0:
            say(f"  (no-slip FE table for H/D = {h / 18.0:.4f} was not shipped: built and cached in "
                f"{fmt_s(time.perf_counter() - t0)}, untimed)")
            details.setdefault("tables_built", []).append(h / 18.0)

    # --- the loop end to end (reading, contact, loop, figures, cards), no bootstrap -----------------
    cmd, info = _command(paths, "_loop", ["--bootstrap", "0"])
    _say_command(say, "bsipipe fit-ogden --bootstrap 0", cmd, info)
    details["command_loop"] = info
    # --- what a user gets by default: the loop plus the 200-resample bootstrap of the final model ---
    if not quick:
        cmd_b, info_b = _command(paths, "_default", [])
        _say_command(say, "bsipipe fit-ogden (default: + 200-resample bootstrap)", cmd_b, info_b)
        details["command_default"] = info_b

    # --- peer: one felupe FE solve of the same specimen --------------------------------------------
    from bsipipe.mechanics.noslip import STRETCH_GRID, noslip_simulate
    grid = STRETCH_GRID[(STRETCH_GRID >= 0.7) & (STRETCH_GRID < 1.0)]
    try:
        t_fe, _ = timed(lambda: noslip_simulate(grid, TRUTH["mu_pa"], TRUTH["alpha"], 18.0, 12.0))
        fe_s, fe_cpu = t_fe["min_s"], t_fe["cpu_min_s"]
        say(f"  felupe FE, one no-slip compression to 30 % ({len(grid)} stretches, 32 radial cells): {fmt_s(fe_s)} "
            f"(CPU {fmt_s(fe_cpu)})")
        details["peer_fe"] = {"time": t_fe, "n_stretches": int(len(grid))}
        peer_txt, note_fe = f"felupe 1 FE solve {fmt_s(fe_s)} (CPU {fmt_s(fe_cpu)})", ""
    except Exception as e:  # the peer's failure is reported, not hidden
        fe_s, fe_cpu, peer_txt = None, None, "felupe FE: failed"
        note_fe = f"; the FE peer raised {type(e).__name__}: {e}"

    rows = []
    for label, c, inf, judged in (("fit-ogden loop (--bootstrap 0), 2x5000 pts", cmd, info, True),
                                  ("fit-ogden default (+200 bootstrap), 2x5000", *(
                                      (cmd_b, info_b) if not quick else (None, None)), False)):
        if c is None:
            rows.append(Row(label, "skipped", peer_txt, None, "", "info (no target)", None, note="skipped (--quick)"))
            continue
        found = "no-slip-platens" in inf["effects"]
        extra = [e for e in inf["effects"] if e != "no-slip-platens"]
        note = (f"{'found' if found else 'DID NOT FIND'} no-slip-platens"
                + (f"; ALSO ADDED {extra} (truth: no-slip only)" if extra else "")
                + f"; final {inf['final']}; peak RSS {fmt_bytes(c.peak_rss_bytes)}; logs' bonded-platen force: "
                + ", ".join(sorted(set(details["noslip_model"] or ["unknown"]))) + note_fe)
        if not c.ok:
            note = f"fit-ogden exited {c.returncode}: {c.tail(3)}" + note_fe
        rows.append(Row(label, f"{fmt_s(c.wall_s)} (CPU {fmt_s(c.cpu_s)})" if c.ok else "failed", peer_txt,
                        (c.cpu_s / fe_cpu) if (fe_s and c.ok) else None, "bsipipe/peer CPU time",
                        "< 60 s (CPU)" if judged else "info (no target)",
                        (c.ok and c.cpu_s < TARGET_S) if judged else None, note=note,
                        values={"bsipipe_s": c.wall_s, "bsipipe_cpu_s": c.cpu_s, "peer_s": fe_s,
                                "peer_cpu_s": fe_cpu}))
    return rows, details
