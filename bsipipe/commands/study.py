"""``bsipipe study CONFIG``: run every stage of a study that is not up to date.

::

    bsipipe study CONFIG [-o OUT] [--force] [--stage NAME ...] [--trial NAME ...] [-j N]

The config (``configs/study.yaml``, :mod:`bsipipe.study_config`) chains ``synth ->
calibrate -> track -> register``, ``fit-ogden`` and ``export-fe -> fe-solve -> compare`` for
each trial; :mod:`bsipipe.study` decides from content hashes which stages to redo and runs
independent stages (of one trial, or of many trials) in ``-j`` worker processes.  Each stage
calls the same ``run`` function as its command.  Prints a progress line per stage and a
summary table (stage, status, time, key outputs), and, after a run of the whole study (no
``--stage``/``--trial``), writes ``OUT/study.json`` (the table and the provenance).

``fe-solve`` is the one stage without a command of its own: it runs export-fe's ABAQUS deck
in CalculiX (``ccx``) and keeps the result files (``job.frd``, ``job.dat``) that ``compare``
reads, with ``fe_solve.json``.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path
from typing import Callable, Sequence

from ..errors import InputError, ProcessingError

log = logging.getLogger(__name__)


class StudyFailed(ProcessingError):
    """One or more stages failed; ``report`` is the study's summary, ``exit_code`` the first failure's."""

    def __init__(self, message: str, report: dict, exit_code: int):
        super().__init__(message)
        self.report = report
        self.exit_code = exit_code


def default_jobs() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def run(config: str | os.PathLike, *, out: str | os.PathLike | None = None, force: bool = False,
        stages: Sequence[str] = (), trials: Sequence[str] = (), jobs: int | None = None,
        echo: Callable[[str], None] = print, tracebacks: bool = False) -> dict:
    """Run the study; returns the ``study.json`` dict.

    ``stages`` (``NAME`` for that stage in every trial, or ``TRIAL/NAME``) runs only those
    stages, taking the results of the others as they are; ``trials`` restricts the run to
    those trials.  ``jobs`` worker processes (default: the usable cores).

    Raises
    ------
    InputError
        Invalid config, unknown stage or trial (exit 2).
    StudyFailed
        A stage failed (exit status of its error); the other trials' stages still ran.
    """
    from ..provenance import ResultSet, provenance
    from ..study import run_stages, summary_table
    from ..study_config import SINGLE_THREAD_ENV, STAGES, load_study, plan_study, to_stages, write_config_file

    t0 = time.perf_counter()
    study = load_study(config, out)
    plans = plan_study(study)
    names = [t.name for t in study.trials]
    for t in trials:
        if t not in names:
            raise InputError(f"no trial named {t!r}; trials: {', '.join(names)}", path=config)
    if trials:
        plans = [p for p in plans if p.trial in trials]
    only = None
    if stages:
        only = set()
        for s in stages:
            if "/" in s:
                if s not in {p.name for p in plans}:
                    raise InputError(f"no stage {s!r} (TRIAL/STAGE); stages: {', '.join(STAGES)}", path=config)
                only.add(s)
            elif s in STAGES:
                only.update(p.name for p in plans if p.stage == s)
            else:
                raise InputError(f"no stage named {s!r}; stages: {', '.join(STAGES)}", path=config)
    for p in plans:   # every command config as the study now says (a stage up to date keeps its bytes)
        write_config_file(p.config_file)
    jobs = default_jobs() if jobs is None else max(1, int(jobs))
    echo(f"[study] {study.path}: {len(study.trials)} trial(s), {len(plans)} stages, output {study.out}, "
         f"{jobs} worker(s)")
    outcomes = run_stages(to_stages(plans, study), study.out, force=force, only=only, jobs=jobs, echo=echo,
                          env=SINGLE_THREAD_ENV)
    wall = time.perf_counter() - t0
    echo("")
    echo(summary_table(outcomes))
    counts = {st: sum(o.status == st for o in outcomes) for st in ("ran", "up to date", "failed", "skipped", "not run")}
    echo(f"[study] {', '.join(f'{v} {k}' for k, v in counts.items() if v)}; {wall:.1f} s")
    report = {"config": str(study.path), "out": str(study.out), "jobs": jobs, "wall_s": wall, "counts": counts,
              "stages": [o.to_dict() for o in outcomes],
              # every JSON result has a warnings list: here the stages that failed
              "warnings": [{"code": "stage-failed", "message": f"study: {o.name} failed: {o.detail}", "stage": o.name}
                           for o in outcomes if o.status == "failed"],
              "provenance": provenance(study.as_dict(), [study.path], command="study")}
    if not stages and not trials:   # the summary of the whole study (a partial run leaves it as it was)
        rs = ResultSet(study.out, primary="study.json")
        rs.add_json("study.json", report)
        rs.commit()
    failed = [o for o in outcomes if o.status == "failed"]
    if failed:
        if tracebacks:
            for o in failed:
                if o.traceback:
                    echo(f"[study] {o.name} traceback:\n{o.traceback}")
        first = failed[0]
        more = f" (and {len(failed) - 1} more failed stage(s))" if len(failed) > 1 else ""
        raise StudyFailed(f"stage {first.name} failed: {first.detail}{more}", report, first.exit_code)
    return report


#: The FE indentor force at the deepest result is said to differ from the log's when their
#: ratio is outside this range.
FORCE_RATIO_RANGE = (0.5, 2.0)


def _indentor_force(deck: Path, dat: bytes | None, peak_time: float | None) -> dict | None:
    """The indentor's reaction force from the solver's ``.dat`` (``*NODE PRINT, NSET=INDENTOR,
    TOTALS=ONLY`` of RF, which export-fe's decks ask for), in N (the deck's force unit from its
    ``** bsipipe: fe_force_per_n`` header), its magnitude at each result time, and, where
    export-fe's ``target_force.csv`` (the log's contact-zeroed force against time from contact)
    sits beside the deck's folder, the log's force at the same times and the ratio at the
    deepest result: the match the FE stage tunes the interface stiffness for, which no output
    had shown (the study's first run: 1.05 N for a log's 0.23 N, unsaid).  None where the deck
    is not export-fe's or the file holds no such totals."""
    import numpy as np
    import pandas as pd

    from ..fe._calculix import parse_dat
    from ..io.abaqus import abaqus_header_values

    if dat is None:
        return None
    head = abaqus_header_values(deck)
    try:
        per_n = float(head["fe_force_per_n"])
    except (KeyError, ValueError):
        return None
    blocks = [b for b in parse_dat(dat.decode("utf-8", "replace"))
              if b.title.startswith("total force") and b.set_name.upper() == "INDENTOR" and b.values.size >= 3]
    if not blocks:
        return None
    t = np.array([b.time for b in blocks])
    f = np.array([np.asarray(b.values, float).reshape(-1)[:3] for b in blocks]) / per_n
    mag = np.linalg.norm(f, axis=1)
    out = {"unit": "N", "time": t.tolist(), "force_n": f.tolist(), "magnitude_n": mag.tolist()}
    k = int(np.argmin(np.abs(t - peak_time))) if peak_time is not None else int(np.argmax(mag))
    out["peak"] = {"time": float(t[k]), "magnitude_n": float(mag[k])}
    target = deck.parent.parent / "target_force.csv"
    if target.is_file():
        tf = pd.read_csv(target)
        if {"time_s", "force_n"} <= set(tf.columns) and len(tf) >= 2:
            # the log's force at the FE times (its loading part up to the deepest point: the FE
            # step time runs from contact, as the target's time_s does)
            log_f = np.interp(t, tf["time_s"].to_numpy(float), tf["force_n"].to_numpy(float),
                              left=np.nan, right=np.nan)
            out["log_force_n"] = [None if not np.isfinite(v) else float(v) for v in log_f]
            lf = float(log_f[k])
            if np.isfinite(lf) and lf > 0:
                ratio = float(mag[k]) / lf
                out["peak"].update(log_force_n=lf, ratio=ratio)
                lo, hi = FORCE_RATIO_RANGE
                if not lo <= ratio <= hi:
                    out["warning"] = (f"the FE indentor force at the deepest result (t = {t[k]:.4g}) is {mag[k]:.3g} N, "
                                      f"{ratio:.2g} times the log's {lf:.3g} N there: the model's stiffness (the "
                                      "material, the interface springs, the mesh and its boundaries) does not match "
                                      "the in situ test; it is what the interface stiffness is tuned on")
    return out


def fe_solve(deck: str | os.PathLike, *, out: str | os.PathLike, timeout_s: float = 1800.0,
             length_unit: str = "mm") -> dict:
    """Run an ABAQUS deck (and the files it includes, from its folder) in CalculiX.

    Writes ``out/job.frd`` and ``out/job.dat`` (the solver's results), ``out/ccx.log`` (its
    console output), ``out/displacements_peak.csv`` (``node,ux_<unit>,uy_<unit>,uz_<unit>``,
    ``<unit>`` the deck's ``length_unit``: the nodal displacements of the result with the
    largest displacement, i.e. the deepest indentation, for tools that take one result; the
    study's ``compare`` reads ``job.frd`` whole, its peak and its loading history) and ``out/fe_solve.json`` (last): the results in the ``.frd`` file,
    which one is the peak, the largest displacement, the solver's warnings, timing and
    provenance.
    """
    import numpy as np
    import pandas as pd

    from ..fe._calculix import CcxError, ccx_executable, run_ccx
    from ..io.fe_results import read_frd
    from ..provenance import ResultSet, provenance

    deck = Path(deck)
    if not deck.is_file():
        raise InputError("the ABAQUS deck to solve is not there (did export-fe write it?)", path=deck)
    if length_unit not in ("mm", "m"):
        raise InputError(f"length unit {length_unit!r}: expected mm or m", key="length_unit")
    exe = ccx_executable()
    if exe is None:
        raise ProcessingError("CalculiX 'ccx' is not on PATH (apt-get install calculix-ccx)", path=deck)
    rs = ResultSet(out, primary="fe_solve.json")
    t0 = time.perf_counter()
    # CalculiX runs in a hidden folder inside the stage's own: a run killed mid-solve leaves it
    # there, and the rerun empties the stage folder (a system temp folder would be left behind)
    work = Path(out) / ".ccx-work"
    if work.exists():
        shutil.rmtree(work)
    work.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(deck.parent, work)   # the deck's *INCLUDE files sit beside it
    try:
        try:
            res = run_ccx(deck.read_text(encoding="utf-8"), jobname="job", timeout_s=timeout_s, keep_dir=work)
        except CcxError as e:
            raise ProcessingError(str(e), path=deck) from None
        solve_s = time.perf_counter() - t0
        frd = work / "job.frd"
        if not frd.is_file():
            raise ProcessingError("CalculiX wrote no .frd file: the deck needs a *NODE FILE request for U", path=deck)
        written = {name: (work / name).read_bytes() for name in ("job.frd", "job.dat") if (work / name).is_file()}
        for name, data in written.items():
            rs.add_bytes(name, data)
        dat = written.get("job.dat")
        rs.add_text("ccx.log", res.stdout)
        first = read_frd(frd)   # the last result; tells how many there are
        peaks = []
        for i in range(first.n_results):
            d = first if i == first.n_results - 1 else read_frd(frd, choose=i)
            peaks.append(float(np.sqrt((d.u_mm ** 2).sum(axis=1)).max()) if len(d.u_mm) else 0.0)
        k = int(np.argmax(peaks))
        peak = read_frd(frd, choose=k)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    # read_frd gives mm; the table is in the deck's length unit, as compare reads it with the mesh
    scale = 1e-3 if length_unit == "m" else 1.0
    table = pd.DataFrame({"node": peak.node_ids.astype(int)})
    for j, a in enumerate("xyz"):
        table[f"u{a}_{length_unit}"] = peak.u_mm[:, j] * scale
    rs.add_csv("displacements_peak.csv", table, float_format="%.9g")
    force = _indentor_force(deck, dat, peak.time)
    summary = {"deck": str(deck), "ccx": exe, "n_results": first.n_results, "results": list(first.results),
               "peak_result": {"index": k, "description": peak.step, "time": peak.time,
                               "max_displacement_mm": peaks[k]},
               "max_displacement_mm": max(peaks), "length_unit": length_unit,
               "warnings": res.warnings[:50], "n_warnings": len(res.warnings),
               "timing": {"solve_s": solve_s}}
    if force is not None:
        summary["indentor_force"] = force
        if force.get("warning"):
            summary["warnings"] = [force["warning"]] + summary["warnings"]
            log.warning("fe-solve: %s", force["warning"])
    summary["provenance"] = provenance({"deck": str(deck), "timeout_s": timeout_s, "length_unit": length_unit},
                                       [deck], command="fe-solve")
    rs.add_json("fe_solve.json", summary)
    rs.commit()
    return summary
