"""scripts/kill_rerun_trials.py (issue 7): SIGKILL `bsipipe study` at random moments, rerun,
compare with a clean run.

- its normaliser removes the run's clock and nothing else: a changed number anywhere else, a
  stale input hash, a leftover temporary file or an unfinished stage stamp is a difference;
- three kill-and-rerun trials of the tiny study (configs/study_tiny.yaml) pass;
- a study killed between creating a stage folder and renaming its first stamp into place is
  redone on the next run (the stamp's temporary file alone does not make the folder foreign).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "kill_rerun_trials.py"


@pytest.fixture(scope="module")
def kr():
    spec = importlib.util.spec_from_file_location("kill_rerun_trials", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod          # its dataclasses look their module up there
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop(spec.name, None)


def _sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


def _tree(root: Path, *, stamp_time: str = "2026-01-01T00:00:00+00:00", solve_s: float = 1.5,
          sigma: float = 0.125, draws: int = 200, upstream_time: str | None = None, stale_hash: bool = False,
          frd_time: str = "10:00:00", frd_value: str = "1.23456E+00", ccx_time: str = "0.48",
          status: str = "ran", detail: str = "sigma 0.125 mm") -> Path:
    """A study output folder as the run at logical path ``<root>`` would write it."""
    up = root / "t" / "register"
    up.mkdir(parents=True)
    upstream = {"fre_rms_mm": 0.02, "provenance": {"utc_time": upstream_time or stamp_time}}
    (up / "registration.json").write_text(json.dumps(upstream, indent=2) + "\n")
    up_sha = "0" * 64 if stale_hash else _sha((up / "registration.json").read_bytes())
    cmp_ = root / "t" / "compare"
    cmp_.mkdir(parents=True)
    result = {"sigma_mm": sigma, "n_markers": 5, "timing": {"solve_s": solve_s},
              "provenance": {"config": {"perturbation_draws": draws}, "utc_time": stamp_time,
                             "inputs_sha256": {str(up / "registration.json"): up_sha}}}
    (cmp_ / "compare.json").write_text(json.dumps(result, indent=2) + "\n")
    (cmp_ / "table.csv").write_text("marker,err_mm\nM1,0.125\n")
    (cmp_ / "job.frd").write_text(f"    1C\n    1UDATE              1.january.2026\n"
                                  f"    1UTIME              {frd_time}\n -1         1 {frd_value}\n")
    (cmp_ / "ccx.log").write_text(f"Job finished\n\nTotal CalculiX Time: {ccx_time}\n")
    for folder in (up, cmp_):
        outputs = {p.name: _sha(p.read_bytes()) for p in sorted(folder.iterdir())}
        (folder / ".stage.json").write_text(json.dumps({"state": "done", "key": folder.name * 4,
                                                        "finished_utc": stamp_time, "outputs": outputs}))
    study = {"config": "c.yaml", "wall_s": 12.5, "counts": {"ran": 2, "up to date": 0},
             "stages": [{"stage": "t/register", "status": status, "seconds": 1.0, "key": "register" * 4,
                         "detail": "FRE"},
                        {"stage": "t/compare", "status": "ran", "seconds": 2.0, "key": "compare" * 4,
                         "detail": detail}],
             "provenance": {"utc_time": stamp_time}}
    if status == "up to date":
        study["counts"] = {"ran": 1, "up to date": 1}
    (root / "study.json").write_text(json.dumps(study, indent=2) + "\n")
    return root


def _compare(kr, tmp_path, **changes):
    """(files compared, problems) between a reference tree and one with ``changes``, both
    written at the same logical path (the second is moved aside, as the script does)."""
    logical = tmp_path / "run"
    _tree(logical)
    (tmp_path / "run").rename(tmp_path / "clean")
    _tree(logical, **changes)
    return kr.compare_trees(logical, tmp_path / "clean", logical)


def test_normaliser_strips_only_the_clock(kr, tmp_path):
    # the clock: time stamps, durations, CalculiX's date and time, ran vs up to date
    n, problems = _compare(kr, tmp_path, stamp_time="2026-11-21T13:00:00+00:00", solve_s=9.75,
                           frd_time="13:00:01", ccx_time="12.5", status="up to date")
    assert problems == [] and n == 6


def test_upstream_time_stamp_changes_an_input_hash_but_not_the_result(kr, tmp_path):
    # registration.json got a new time stamp, so compare.json's recorded hash of it changed too
    n, problems = _compare(kr, tmp_path, upstream_time="2026-11-21T13:00:00+00:00")
    assert problems == []


@pytest.mark.parametrize("change, file", [
    ({"sigma": 0.126}, "t/compare/compare.json"),                 # a result number
    ({"draws": 150}, "t/compare/compare.json"),                   # a config value inside provenance
    ({"stale_hash": True}, "t/compare/compare.json"),             # an input hash that matches no file
    ({"frd_value": "1.23457E+00"}, "t/compare/job.frd"),          # a solver result
    ({"detail": "sigma 0.126 mm"}, "study.json"),                 # a key output in the summary
])
def test_normaliser_keeps_everything_else(kr, tmp_path, change, file):
    n, problems = _compare(kr, tmp_path, **change)
    assert problems == [f"differs {file}"]


def test_one_byte_of_a_csv_and_leftovers_and_unfinished_stamps(kr, tmp_path):
    logical = tmp_path / "run"
    _tree(logical)
    (tmp_path / "run").rename(tmp_path / "clean")
    _tree(logical)
    csv = logical / "t" / "compare" / "table.csv"
    csv.write_text(csv.read_text().replace("0.125", "0.124"))
    (logical / "t" / "compare" / ".table.csv.ab12.tmp").write_text("half")
    stamp = logical / "t" / "register" / ".stage.json"
    stamp.write_text(json.dumps({**json.loads(stamp.read_text()), "state": "running"}))
    (logical / "t" / "extra.txt").write_text("x")
    _, problems = kr.compare_trees(logical, tmp_path / "clean", logical)
    assert set(problems) == {"differs t/compare/table.csv", "leftover t/compare/.table.csv.ab12.tmp",
                             "t/register: stamp state 'running'",
                             "t/compare: stamp does not list the files its folder holds", "extra t/extra.txt"}


def test_running_stages_from_the_log(kr):
    lines = [(0.1, "[study] x: 1 trial(s)"), (1.0, "[study] t/synth: running (never run)"),
             (1.1, "[study] t/fit-ogden: running (never run)"), (5.0, "[study] t/synth: done in 4.0 s (...)"),
             (5.1, "[study] t/calibrate: running (never run)")]
    assert kr._running_stages(lines, 4.0) == ["t/synth", "t/fit-ogden"]
    assert kr._running_stages(lines, 6.0) == ["t/fit-ogden", "t/calibrate"]
    assert kr._running_stages(lines, 0.5) == []


@pytest.mark.slow
def test_three_kill_and_rerun_trials_of_the_tiny_study(tmp_path):
    """About 80 s on an idle 2-core machine (a clean tiny study is ~17 s; each trial is about one)."""
    work = tmp_path / "w"
    p = subprocess.run([sys.executable, str(SCRIPT), "--config", str(ROOT / "configs" / "study_tiny.yaml"),
                        "--trials", "3", "--seed", "1", "--workdir", str(work)],
                       capture_output=True, text=True, timeout=900)
    print(p.stdout[-3000:], p.stderr[-3000:])
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    report = json.loads((work / "trials.json").read_text())
    assert len(report["trials"]) == 3
    for t in report["trials"]:
        assert t["identical"] and not t["problems"]
        assert t["kill_s"] is not None and t["files"] >= 40       # killed, then every result compared
    assert "3/3 trials identical to the clean run" in p.stdout
    assert not (work / "run").exists() and (work / "clean" / "study.json").is_file()


def _write_out(folder: Path) -> None:
    (Path(folder) / "out.txt").write_text("a\n")


def test_a_run_killed_while_writing_its_first_stamp_is_redone(tmp_path):
    """SIGKILL between creating a stage's folder and renaming its first ``running`` stamp into
    place leaves only that stamp's temporary file: the next run redoes the stage (it does
    not refuse the folder as one the study did not write) and removes the file."""
    from bsipipe.study import STAMP, Stage, read_stamp, run_stages

    folder = tmp_path / "out" / "a"
    folder.mkdir(parents=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{STAMP}.", suffix=".tmp", dir=folder)   # as atomic_write_bytes names it
    os.write(fd, b'{"state": "runn')
    os.close(fd)
    st = run_stages([Stage("a", _write_out)], tmp_path / "out", echo=lambda s: None, isolate=False)
    assert [(o.name, o.status) for o in st] == [("a", "ran")], st[0].detail
    assert sorted(p.name for p in folder.iterdir()) == [STAMP, "out.txt"]
    assert read_stamp(folder)["state"] == "done"
    (folder / STAMP).unlink()                      # a folder with a file of someone else's is still refused
    st = run_stages([Stage("a", _write_out)], tmp_path / "out", echo=lambda s: None, isolate=False)
    assert st[0].status == "failed" and "not written by bsipipe study" in st[0].detail


def test_unfinished_stages_after_a_kill(kr, tmp_path):
    _tree(tmp_path)
    stamp = tmp_path / "t" / "register" / ".stage.json"
    stamp.write_text(json.dumps({"state": "running"}))        # killed while writing its results
    (tmp_path / "t" / "fit").mkdir()
    (tmp_path / "t" / "fit" / "..stage.json.x1y2.tmp").write_text("{")   # killed writing its first stamp
    assert kr.unfinished_stages(tmp_path) == {"t/fit": 0, "t/register": 1}
