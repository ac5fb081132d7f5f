"""What every benchmark shares: timing, child processes with their peak memory, rows, the table.

A row compares bsipipe with a named peer measured in the same run.  ``ratio`` is stated with
its definition (``ratio_def``) because the natural direction differs between rows (a speed-up
for timings, bsipipe over the peer for a budget like "the command within 1.5x the decode").
Every row carries the 1-minute load average when it was measured: on a loaded machine the
absolute numbers are inflated, the ratios much less so.  Absolute targets, and ratios of
runs made at different moments, are judged on CPU time (user + system, all threads), which
for these single-threaded programs is what an idle machine's wall time would be; wall
times are printed beside them.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "results"
#: Generated inputs (twin frames, logs) and the commands' scratch outputs (``CACHE / "out"``);
#: ``BSIPIPE_BENCH_CACHE`` moves them (e.g. out of a ``results/`` that other runs clean).
CACHE = Path(os.environ.get("BSIPIPE_BENCH_CACHE") or RESULTS / "bench_cache").resolve()
OUT = CACHE / "out"


def load_average() -> list[float]:
    """1-, 5- and 15-minute load averages (``os.getloadavg``), rounded."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:  # not available on this platform
        return [float("nan")] * 3


@dataclass
class Row:
    """One line of the table.

    ``bsipipe`` and ``peer`` are display strings (value and unit); ``ratio`` is the number
    ``ratio_def`` defines; ``passed`` is None where there is no target (or it could not be
    judged, e.g. a peer that could not run: ``note`` says why).
    """

    benchmark: str
    bsipipe: str
    peer: str
    ratio: float | None
    ratio_def: str
    target: str
    passed: bool | None
    note: str = ""
    load: list[float] = field(default_factory=load_average)
    values: dict = field(default_factory=dict)        # raw numbers for results/bench.json

    def to_dict(self) -> dict:
        return asdict(self)


def timed(fn: Callable[[], Any], repeats: int = 1, warmup: int = 0) -> tuple[dict, Any]:
    """Run ``fn`` ``warmup`` + ``repeats`` times; ``({"min_s", "median_s", "all_s", "cpu_min_s"}, last result)``.

    The minimum wall time is the figure to compare (load only ever adds time); the median
    is kept too, and the process CPU time (all threads), which load inflates far less.
    """
    tm, out = interleaved({"fn": fn}, repeats, {"fn": warmup})
    return tm["fn"], out["fn"]


def interleaved(fns: dict[str, Callable[[], Any]], repeats: int = 1,
                warmup: dict[str, int] | None = None) -> tuple[dict[str, dict], dict[str, Any]]:
    """:func:`timed` (which is this for one function) for several functions whose speeds are
    compared, their timed runs taken in turn (``a b c a b c ...``) after each one's ``warmup``
    runs: a ratio of two minima is then taken under the same machine state, where timing one
    side's runs minutes after the other's let the machine's drift between them enter the ratio
    (on this VM the same code ran 250 and 400 frames/s an hour apart).  Returns (name -> timing
    dict, name -> last result)."""
    for name, fn in fns.items():
        for _ in range((warmup or {}).get(name, 0)):
            fn()
    times: dict[str, list] = {k: [] for k in fns}
    cpus: dict[str, list] = {k: [] for k in fns}
    out: dict[str, Any] = {}
    for _ in range(max(1, repeats)):
        for name, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            out[name] = fn()
            times[name].append(time.perf_counter() - t0)
            cpus[name].append(time.process_time() - c0)
    res = {}
    for name in fns:
        s = sorted(times[name])
        res[name] = {"min_s": s[0], "median_s": s[len(s) // 2], "all_s": times[name], "cpu_min_s": min(cpus[name])}
    return res, out


@dataclass
class ChildRun:
    """A finished child process: wall time, CPU time, peak resident memory, exit status, output."""

    args: list[str]
    wall_s: float
    peak_rss_bytes: int
    returncode: int
    stdout: str
    stderr: str
    cpu_s: float = float("nan")          # user + system, all threads of the child

    @property
    def ok(self) -> bool:
        return self.returncode == 0

    def tail(self, n: int = 15) -> str:
        return "\n".join((self.stderr or self.stdout).strip().splitlines()[-n:])


def _vm_hwm_bytes(pid: int) -> int | None:
    """``VmHWM`` (peak resident set of the current program image) of a live process, Linux."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def run_child(args: Sequence[str], *, timeout_s: float = 3600.0, env: dict | None = None,
              cwd: str | os.PathLike | None = None, poll_s: float = 0.01) -> ChildRun:
    """Run ``args`` and measure its wall time, CPU time and peak RSS.

    The peak is the child's ``VmHWM`` (``/proc/PID/status``), read every ``poll_s`` while it
    runs: a high-water mark of the program the child executes, so only growth within the
    last poll before exit can be missed.  ``ru_maxrss`` (``os.wait4``) is not used where
    VmHWM is available: Linux carries it across ``exec``, so it would include the memory of
    the forked copy of this (large) bench process.  Processes the child starts are not
    included.  On timeout the child is killed (its pid only) and the return code is -9.
    """
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        p = subprocess.Popen(list(args), stdout=out, stderr=err, env=env, cwd=cwd)
        status, usage, hwm = None, None, None
        while True:
            h = _vm_hwm_bytes(p.pid)
            if h is not None:
                hwm = h if hwm is None else max(hwm, h)
            pid, st, ru = os.wait4(p.pid, os.WNOHANG)
            if pid == p.pid:
                status, usage = st, ru
                break
            if time.perf_counter() - t0 > timeout_s:
                p.kill()
                _, status, usage = os.wait4(p.pid, 0)
                break
            time.sleep(poll_s)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)      # reaped here: keep Popen from waiting again
        out.seek(0)
        err.seek(0)
        rss = hwm if hwm is not None else int(usage.ru_maxrss) * (1 if sys.platform == "darwin" else 1024)
        return ChildRun(list(map(str, args)), wall, rss, p.returncode, out.read(), err.read(),
                        float(usage.ru_utime + usage.ru_stime))


def bsipipe_exe() -> str:
    """The console script of the interpreter running the bench (the venv's ``bsipipe``)."""
    exe = Path(sys.executable).with_name("bsipipe")
    return str(exe) if exe.exists() else "bsipipe"


def fmt_s(x: float | None) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    if x < 1e-2:
        return f"{1e3 * x:.2f} ms"
    if x < 1:
        return f"{1e3 * x:.0f} ms"
    return f"{x:.2f} s"


def fmt_ratio(x: float | None) -> str:
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x:.3g}x" if x < 100 else f"{x:.0f}x"


def fmt_bytes(n: float | None) -> str:
    if n is None:
        return "n/a"
    return f"{n / 2**20:.0f} MiB"


def verdict(passed: bool | None) -> str:
    return "n/a" if passed is None else ("PASS" if passed else "FAIL")


def print_table(rows: Sequence[Row], file=sys.stdout) -> None:
    """The table: benchmark, bsipipe, peer, ratio (with its definition), target, result, load."""
    head = ["benchmark", "bsipipe", "peer", "ratio", "target", "result", "load(1m)"]
    body = [[r.benchmark, r.bsipipe, r.peer, f"{fmt_ratio(r.ratio)} {r.ratio_def}".strip(), r.target,
             verdict(r.passed), f"{r.load[0]:.1f}"] for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(head)]
    line = "  ".join("-" * w for w in widths)
    print("  ".join(h.ljust(w) for h, w in zip(head, widths)), file=file)
    print(line, file=file)
    for b in body:
        print("  ".join(c.ljust(w) for c, w in zip(b, widths)), file=file)
    notes = [(r.benchmark, r.note) for r in rows if r.note]
    if notes:
        print(file=file)
        for name, note in notes:
            print(f"  {name}: {note}", file=file)


def versions() -> dict[str, str | None]:
    from importlib.metadata import PackageNotFoundError, version
    out: dict[str, str | None] = {"python": sys.version.split()[0]}
    for pkg in ("bsipipe", "numpy", "scipy", "opencv-contrib-python-headless", "pandas", "lmfit", "trackpy",
                "felupe", "tensortrax", "numba"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out
