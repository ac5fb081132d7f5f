"""Kill `bsipipe study` with SIGKILL at random moments, rerun it, and check the results (issue 7).

::

    python scripts/kill_rerun_trials.py [--config configs/study.yaml] [--trials 20] [--seed 0]
                                        [--workdir DIR] [--keep]

Runs the study (``bsipipe study CONFIG -o WORKDIR/run``, what ``make study`` runs, into a
scratch folder: the repository's ``results/`` is never touched) once cleanly and keeps that
as ``WORKDIR/clean``.  Every run uses a copy of ``bsipipe/``, ``configs/`` and ``sample_data/``
taken at the start (``WORKDIR/src``, first on ``PYTHONPATH``), so edits to the working tree
during the trials do not change the stages' code.  Then, for each trial, from an empty ``WORKDIR/run``:

1. starts the study in its own process group (session) and SIGKILLs the whole group (the
   study, its worker processes and a CalculiX child) at a random moment: uniform within the
   clean run's duration, or, for every fourth trial (3, 7, 11, ...), at a uniform moment
   within the clean run's CalculiX solve after ``ccx`` has started, so the solver is hit too;
2. checks that no process of the killed group survives, and notes the stages the kill left
   unfinished (no ``done`` stamp; "w/ files": their folder held half-written results);
3. reruns the study to completion (exit status 0), which must redo every unfinished stage;
4. compares every file of ``WORKDIR/run`` with the clean run after :func:`normalise`, which
   removes only the run's clock (provenance time stamps, ``timing`` durations, CalculiX's
   date/time lines) and run history (``study.json``'s per-stage seconds and ran/up-to-date
   status); anything else that differs, a missing or extra file, a hidden temporary or
   partial file left in the output, a stage stamp that is not ``done`` or does not list the
   files its folder holds, or a temporary file the *rerun* left in ``TMPDIR`` fails the trial.

Prints one row per trial (kill time, the stages running when killed, whether ``ccx`` was
alive, unfinished stages, files compared, identical) and a summary line, and writes
``WORKDIR/trials.json``; exits 1 when any trial fails.  A passing trial's output is removed
(``--keep`` keeps it); a failing one's is kept as ``WORKDIR/trial-NN``.
The runs share one output path, so paths written into the results are the same in every run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
BSIPIPE = str(Path(sys.executable).parent / "bsipipe")
STAMP = ".stage.json"
#: Copied into the work folder and run from there (``PYTHONPATH``), so that every run of a
#: series sees the same code and data.
SNAPSHOT = ("bsipipe", "configs", "sample_data")
#: Draws of a trial's kill time before a study that keeps finishing first fails the trial.
MAX_ATTEMPTS = 3

#: Keys holding the run's clock, wherever they are in a JSON result.
CLOCK_KEYS = {"utc_time"}
#: Keys whose value is a block of durations (every leaf is a time measured during the run).
DURATION_BLOCKS = {"timing"}
#: CalculiX writes the date and time of the run into these lines.
CCX_CLOCK_LINES = {".frd": ("1UDATE", "1UTIME"), ".log": ("Total CalculiX Time:",)}


# --- normalising one result file -----------------------------------------------------------------

def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for b in iter(lambda: f.read(1 << 20), b""):
            h.update(b)
    return h.hexdigest()


def _strip_clock(o, resolve: Callable[[str], str | None], where: tuple = ()):
    if isinstance(o, dict):
        out = {}
        for k, v in o.items():
            if k in CLOCK_KEYS and isinstance(v, str):
                out[k] = "<time stamp>"
            elif k in DURATION_BLOCKS and isinstance(v, dict):
                out[k] = {d: "<duration>" for d in v}
            elif k == "inputs_sha256" and where and where[-1] == "provenance" and isinstance(v, dict):
                # An input that is a result of this run (an upstream JSON carries its own time
                # stamp) is compared by content elsewhere; here its hash must be the hash of the
                # file that is there now.  A hash that matches nothing in the tree stays as it is.
                out[k] = {p: (f"<sha256 of {p}>" if resolve(p) == h else h) for p, h in v.items()}
            else:
                out[k] = _strip_clock(v, resolve, where + (k,))
        return out
    if isinstance(o, list):
        return [_strip_clock(v, resolve, where) for v in o]
    return o


def _study_summary(d: dict, stamp_key: Callable[[str], str | None]) -> dict:
    """``study.json`` without its run history: wall time, per-stage seconds, and whether a
    complete stage ran in this invocation or was up to date from the killed one."""
    d = dict(d)
    d.pop("wall_s", None)
    counts = dict(d.get("counts") or {})
    counts["complete"] = counts.pop("ran", 0) + counts.pop("up to date", 0)
    d["counts"] = counts
    stages = []
    for s in d.get("stages", []):
        s = dict(s)
        s.pop("seconds", None)
        if s.get("status") in ("ran", "up to date"):
            s["status"] = "complete"
        if s.get("key") is not None and s["key"] == stamp_key(s.get("stage", "")):
            s["key"] = "<the key in its stage stamp>"
        stages.append(s)
    d["stages"] = stages
    return d


def normalise(rel: str, data: bytes, tree: Path, logical_root: Path | None = None) -> bytes:
    """The bytes of result file ``rel`` (relative to ``tree``) with the run's clock removed.

    ``logical_root`` is the folder the run wrote into (paths in the results start with it);
    ``tree`` is where the files are now (default: the same).  Removed, and only these:

    - JSON: every ``utc_time`` string; the values (not the keys) of every ``timing`` block;
      in ``provenance.inputs_sha256``, the hash of an input that matches the file now at
      that path in ``tree`` (an upstream result whose own time stamp changed its hash);
      in ``study.json`` also ``wall_s``, each stage's ``seconds``, the split of complete
      stages into ``ran``/``up to date``, and a stage key equal to its stamp's key.
    - ``.frd``: CalculiX's ``1UDATE``/``1UTIME`` header lines; ``ccx.log``: its total time.

    Every other byte is kept: a changed number anywhere else is a difference.
    """
    tree = Path(tree)
    logical_root = Path(logical_root or tree)
    name = Path(rel).name
    suffix = Path(rel).suffix

    def resolve(p: str) -> str | None:
        try:
            q = Path(p)
            inside = q.relative_to(logical_root)
        except ValueError:
            inside = None
        target = tree / inside if inside is not None else Path(p)
        return _sha256(target) if target.is_file() else None

    def stamp_key(stage: str) -> str | None:
        try:
            return json.loads((tree / stage / STAMP).read_text()).get("key")
        except (OSError, ValueError):
            return None

    if suffix == ".json":
        obj = json.loads(data)
        obj = _strip_clock(obj, resolve)
        if rel == "study.json":
            obj = _study_summary(obj, stamp_key)
        return (json.dumps(obj, indent=2) + "\n").encode()
    if suffix == ".frd" or (suffix == ".log" and name == "ccx.log"):
        prefixes = CCX_CLOCK_LINES[suffix]
        lines = data.split(b"\n")
        keep = [ln for ln in lines if not ln.lstrip().decode("latin-1").startswith(prefixes)]
        return b"\n".join(keep)
    return data


# --- comparing a run with the clean run ----------------------------------------------------------

def list_files(tree: Path) -> tuple[list[str], list[str]]:
    """(result files, leftover hidden files) of a study output folder, relative paths.

    A stage's stamp is the one hidden file a complete study holds; any other file or folder
    whose name starts with ``.`` (an atomic write's ``.name.XXXX.tmp``, a staging folder) is
    a leftover of an interrupted run.
    """
    results, leftovers = [], []
    for p in sorted(Path(tree).rglob("*")):
        rel = p.relative_to(tree)
        hidden = [x for x in rel.parts if x.startswith(".")]
        if hidden:
            if not (p.is_file() and rel.name == STAMP and len(hidden) == 1):
                if p.is_file() or not any(p.iterdir()):
                    leftovers.append(rel.as_posix())
            continue
        if p.is_file():
            results.append(rel.as_posix())
        elif p.is_dir() and not any(p.iterdir()):
            results.append(rel.as_posix() + "/")     # an empty folder is compared by name
    return results, leftovers


def check_stamps(tree: Path) -> list[str]:
    """Problems with the stage stamps: not ``done``, or not listing exactly the files there."""
    problems = []
    for stamp in sorted(Path(tree).rglob(STAMP)):
        folder = stamp.parent
        rel = folder.relative_to(tree).as_posix()
        try:
            d = json.loads(stamp.read_text())
        except (OSError, ValueError):
            problems.append(f"{rel}: stamp unreadable")
            continue
        if d.get("state") != "done":
            problems.append(f"{rel}: stamp state {d.get('state')!r}")
            continue
        now = {}
        for p in sorted(folder.rglob("*")):
            r = p.relative_to(folder)
            if p.is_file() and not any(x.startswith(".") for x in r.parts):
                now[r.as_posix()] = _sha256(p)
        if now != d.get("outputs"):
            problems.append(f"{rel}: stamp does not list the files its folder holds")
    return problems


def unfinished_stages(tree: Path) -> dict[str, int]:
    """``{stage folder: result files in it}`` of the stage folders without a ``done`` stamp:
    what a killed run left half-done (a stage with files here held half-written results)."""
    out = {}
    for folder in sorted({p.parent for p in Path(tree).rglob("*") if p.name == STAMP or
                          (p.name.startswith(f".{STAMP}.") and p.name.endswith(".tmp"))}):
        try:
            state = json.loads((folder / STAMP).read_text()).get("state")
        except (OSError, ValueError):
            state = None
        if state != "done":
            out[folder.relative_to(tree).as_posix()] = sum(
                1 for p in folder.rglob("*") if p.is_file() and not any(
                    x.startswith(".") for x in p.relative_to(folder).parts))
    return out


def compare_trees(run: Path, clean: Path, logical_root: Path) -> tuple[int, list[str]]:
    """(files compared, problems) between a rerun's output and the clean run's."""
    problems: list[str] = []
    files, leftovers = list_files(run)
    clean_files, _ = list_files(clean)
    problems += [f"leftover {x}" for x in leftovers]
    problems += [f"missing {x}" for x in sorted(set(clean_files) - set(files))]
    problems += [f"extra {x}" for x in sorted(set(files) - set(clean_files))]
    stamps_run = sorted(p.relative_to(run).as_posix() for p in run.rglob(STAMP))
    stamps_clean = sorted(p.relative_to(clean).as_posix() for p in clean.rglob(STAMP))
    if stamps_run != stamps_clean:
        problems.append(f"stage stamps differ: {sorted(set(stamps_run) ^ set(stamps_clean))}")
    problems += check_stamps(run)
    n = 0
    for rel in sorted(set(files) & set(clean_files)):
        if rel.endswith("/"):
            continue
        n += 1
        a = normalise(rel, (run / rel).read_bytes(), run, logical_root)
        b = normalise(rel, (clean / rel).read_bytes(), clean, logical_root)
        if a != b:
            problems.append(f"differs {rel}")
    return n, problems


# --- running and killing the study ---------------------------------------------------------------

def _session_processes(sid: int) -> list[tuple[int, str]]:
    """(pid, command name) of the live processes of session ``sid`` (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        state, session = fields[0], int(fields[3])
        if session == sid and state != "Z":
            out.append((int(d.name), comm))
    return out


@dataclass
class Run:
    """One invocation of the study: its output lines (with the time each arrived) and exit."""

    returncode: int | None = None
    seconds: float = 0.0
    lines: list[tuple[float, str]] = field(default_factory=list)
    killed_at: float | None = None
    running_at_kill: list[str] = field(default_factory=list)
    ccx_at_kill: bool = False
    ccx_window: tuple[float, float] | None = None    # first and last moment a ccx process was seen
    survivors: list[tuple[int, str]] = field(default_factory=list)


_RUNNING = re.compile(r"^\[study\] (\S+): running")
_ENDED = re.compile(r"^\[study\] (\S+): (done in|FAILED|up to date|not run|skipped)")


def _running_stages(lines: list[tuple[float, str]], t: float) -> list[str]:
    running: list[str] = []
    for when, ln in lines:
        if when > t:
            break
        if m := _RUNNING.match(ln):
            running.append(m.group(1))
        elif (m := _ENDED.match(ln)) and m.group(1) in running:
            running.remove(m.group(1))
    return running


def run_study(config: Path, out: Path, env: dict, log: Path, *, kill_after: float | None = None,
              kill_in_ccx: tuple[float, float] | None = None, poll_s: float = 0.02) -> Run:
    """Run ``bsipipe study CONFIG -o OUT`` in a new session; optionally SIGKILL the session.

    ``kill_after``: seconds after the start.  ``kill_in_ccx=(fallback_s, delay_s)``: ``delay_s``
    after a ``ccx`` process of the session is first seen, or at ``fallback_s`` if none has
    appeared by then.
    """
    r = Run()
    t0 = time.perf_counter()
    proc = subprocess.Popen([BSIPIPE, "study", str(config), "-o", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env=env, start_new_session=True, cwd=ROOT)
    sid = proc.pid

    def reader():
        with open(log, "w") as f:
            for raw in proc.stdout:
                ln = raw.decode(errors="replace").rstrip("\n")
                r.lines.append((time.perf_counter() - t0, ln))
                f.write(ln + "\n")
                f.flush()

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    ccx_seen: list[float] = []
    deadline = kill_after
    while proc.poll() is None:
        now = time.perf_counter() - t0
        if any(c == "ccx" for _, c in _session_processes(sid)):
            ccx_seen.append(now)
            if kill_in_ccx is not None and deadline is None:
                deadline = now + kill_in_ccx[1]
        if kill_in_ccx is not None and deadline is None and now >= kill_in_ccx[0]:
            deadline = now
        if deadline is not None and now >= deadline:
            r.ccx_at_kill = any(c == "ccx" for _, c in _session_processes(sid))
            os.killpg(sid, signal.SIGKILL)
            r.killed_at = now
            break
        time.sleep(poll_s)
    proc.wait()
    for _ in range(250):      # workers and the solver die with the group; give the kernel a moment
        r.survivors = _session_processes(sid)
        if not r.survivors:
            break
        time.sleep(0.02)
    th.join(timeout=10)
    r.returncode = proc.returncode
    r.seconds = time.perf_counter() - t0
    if ccx_seen:
        r.ccx_window = (ccx_seen[0], ccx_seen[-1])
    if r.killed_at is not None:
        r.running_at_kill = _running_stages(r.lines, r.killed_at)
    return r


def _phase(r: Run) -> str:
    """What the study was doing when killed with no stage running: by the lines printed before."""
    seen = [ln for t, ln in r.lines if r.killed_at is not None and t <= r.killed_at]
    if any(ln.startswith("stage ") for ln in seen):
        return "(summary, study.json)"
    if any(_RUNNING.match(ln) for ln in seen):
        return "(between stages)"
    return "(starting)"


def _short(stage: str) -> str:
    return stage.split("/", 1)[-1]


# --- the trials ----------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "study.yaml",
                    help="study config (default: the sample study, configs/study.yaml)")
    ap.add_argument("--trials", type=int, default=20, help="kill-and-rerun trials (default 20)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the kill times (default 0)")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="scratch folder (new or empty; default: a new temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep every trial's output, not only failed ones")
    a = ap.parse_args(argv)
    if a.trials < 1:
        ap.error("--trials must be at least 1")
    config = a.config.resolve()
    if not config.is_file():
        ap.error(f"no study config {config}")
    if a.workdir is None:
        work = Path(tempfile.mkdtemp(prefix="bsipipe-kill-trials-"))
    else:
        work = a.workdir.resolve()
        if work.exists() and any(work.iterdir()):
            ap.error(f"--workdir {work} is not empty")
        work.mkdir(parents=True, exist_ok=True)
    run_dir, clean_dir, logs, tmp_root = work / "run", work / "clean", work / "logs", work / "tmp"
    logs.mkdir()
    # Every run uses one copy of the code and of the sample data: other people editing the
    # working tree during the trials would otherwise change stages' keys and results under us.
    src = work / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for d in SNAPSHOT:
        shutil.copytree(ROOT / d, src / d, ignore=ignore)
    if config.is_relative_to(ROOT) and config.relative_to(ROOT).parts[0] in SNAPSHOT:
        config = src / config.relative_to(ROOT)
    rng = random.Random(a.seed)
    t_start = time.perf_counter()

    def env_for(name: str) -> dict:
        tmp = tmp_root / name
        tmp.mkdir(parents=True, exist_ok=True)
        path = os.pathsep.join([str(src), *filter(None, [os.environ.get("PYTHONPATH")])])
        return {**os.environ, "PYTHONUNBUFFERED": "1", "TMPDIR": str(tmp), "PYTHONPATH": path}

    print(f"kill-and-rerun trials of {config} in {work}", flush=True)
    clean = run_study(config, run_dir, env_for("clean"), logs / "clean.log")
    if clean.returncode != 0:
        print(f"the clean run failed (exit {clean.returncode}); see {logs / 'clean.log'}", flush=True)
        return 2
    run_dir.rename(clean_dir)
    ccx_s = (clean.ccx_window[1] - clean.ccx_window[0]) if clean.ccx_window else None
    print(f"clean run: {clean.seconds:.1f} s" + (f"; CalculiX ran {ccx_s:.2f} s from {clean.ccx_window[0]:.1f} s"
                                                   if ccx_s is not None else "; no CalculiX process seen"),
          flush=True)

    head = f"{'trial':>5}  {'mode':<7}  {'kill s':>7}  {'running when killed':<28}  {'ccx':<3}  " \
           f"{'unfinished':>10}  {'w/ files':>8}  {'rerun s':>7}  {'redone':>6}  {'files':>5}  identical"
    print(head, flush=True)
    rows = []
    for i in range(1, a.trials + 1):
        name = f"trial-{i:02d}"
        in_ccx = i % 4 == 3 and ccx_s is not None
        for attempt in range(1, MAX_ATTEMPTS + 1):
            # A run can be faster than the clean one (the machine's load varies); a study that
            # finishes before its kill time was not interrupted, so that trial draws again.
            if in_ccx:   # a moment within the solve (or at 3x the clean time if ccx never starts)
                delay = rng.uniform(0.0, max(ccx_s, 0.05))
                killed = run_study(config, run_dir, env_for(name), logs / f"{name}-killed.log",
                                   kill_in_ccx=(3 * clean.seconds, delay))
            else:
                killed = run_study(config, run_dir, env_for(name), logs / f"{name}-killed.log",
                                   kill_after=rng.uniform(0.0, clean.seconds))
            if killed.killed_at is not None or attempt == MAX_ATTEMPTS:
                break
            print(f"       (trial {i}: the study finished in {killed.seconds:.1f} s, before its kill time; "
                  f"drawing again)", flush=True)
            shutil.rmtree(run_dir)
            shutil.rmtree(tmp_root / name)
        tmp_after_kill = set(os.listdir(tmp_root / name))
        unfinished = unfinished_stages(run_dir)
        rerun = run_study(config, run_dir, env_for(name), logs / f"{name}-rerun.log")
        problems = []
        if killed.killed_at is None:
            problems.append(f"the study ended (exit {killed.returncode}) before the kill, {MAX_ATTEMPTS} times")
        if killed.survivors:
            problems.append(f"processes survived the kill: {killed.survivors}")
        if rerun.returncode != 0:
            problems.append(f"rerun exit status {rerun.returncode}")
        tmp_leaks = sorted(set(os.listdir(tmp_root / name)) - tmp_after_kill)
        if tmp_leaks:
            problems.append(f"the rerun left temporary files in TMPDIR: {tmp_leaks}")
        rerun_ran = {m.group(1) for _, ln in rerun.lines if (m := _RUNNING.match(ln))}
        not_redone = sorted(set(unfinished) - rerun_ran)
        if not_redone:
            problems.append(f"stages the kill left unfinished that the rerun did not redo: {not_redone}")
        n, diff = compare_trees(run_dir, clean_dir, run_dir)
        problems += diff
        redone = len(rerun_ran)
        partial = sum(1 for files in unfinished.values() if files)
        ok = not problems
        stages = ",".join(_short(s) for s in killed.running_at_kill) or _phase(killed)
        row = {"trial": i, "mode": "ccx" if in_ccx else "uniform", "kill_s": killed.killed_at,
               "running": stages, "ccx_alive": killed.ccx_at_kill, "rerun_s": rerun.seconds, "redone": redone,
               "files": n, "identical": ok, "problems": problems, "attempts": attempt,
               "tmp_left_by_kill": sorted(tmp_after_kill), "unfinished_at_kill": unfinished,
               "partial_at_kill": partial}
        rows.append(row)
        kill = f"{killed.killed_at:7.2f}" if killed.killed_at is not None else "    n/a"
        print(f"{i:>5}  {row['mode']:<7}  {kill}  {stages[:28]:<28}  {'yes' if killed.ccx_at_kill else 'no':<3}  "
              f"{len(unfinished):>10}  {partial:>8}  {rerun.seconds:7.1f}  {redone:>6}  {n:>5}  "
              f"{'yes' if ok else 'NO'}", flush=True)
        for p in problems[:20]:
            print(f"       {p}", flush=True)
        if ok and not a.keep:
            shutil.rmtree(run_dir)
        else:
            run_dir.rename(work / name)
        shutil.rmtree(tmp_root / name, ignore_errors=True)

    n_ok = sum(r["identical"] for r in rows)
    kills = [r["kill_s"] for r in rows if r["kill_s"] is not None]
    hit = sorted({s for r in rows for s in r["running"].split(",")})
    total = time.perf_counter() - t_start
    (work / "trials.json").write_text(json.dumps({"config": str(config), "seed": a.seed,
                                                  "clean_s": clean.seconds, "ccx_window_s": clean.ccx_window,
                                                  "total_s": total, "trials": rows}, indent=2) + "\n")
    print(f"{n_ok}/{len(rows)} trials identical to the clean run; kill times "
          f"{min(kills, default=0):.1f}-{max(kills, default=0):.1f} s of a {clean.seconds:.1f} s clean run; "
          f"stages hit: {', '.join(hit)}; ccx alive at {sum(r['ccx_alive'] for r in rows)} kill(s); "
          f"{sum(r['partial_at_kill'] for r in rows)} half-written stage folder(s) redone; "
          f"{sum(bool(r['tmp_left_by_kill']) for r in rows)} killed run(s) left files in TMPDIR; "
          f"{total:.0f} s in all; details in {work / 'trials.json'}", flush=True)
    return 0 if n_ok == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
