"""The study: content-hashed reruns, interruption, parallel trials, on a graph of small stages and
on the whole chain of commands on a tiny twin (``configs/study_tiny.yaml``).

What is asserted (issue 6, issue 7 item 3):

- a second run redoes nothing; changing one value redoes exactly the stages downstream of it;
- a deleted or edited result file, a stage that raises half-way and a real SIGKILL of
  ``bsipipe study`` each make the next run redo the stage, and the results are then the same as
  a clean run's: JSON equal without ``provenance``/``timing`` (paths under the output folder
  written relative to it), every other file byte for byte.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from bsipipe.errors import InputError, ProcessingError
from bsipipe.study import Stage, code_version, module_closure, read_stamp, run_stages
from bsipipe.study import run_stages as _run_stages

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "study_tiny.yaml"
BSIPIPE = str(Path(sys.executable).parent / "bsipipe")


# --- comparing result trees ---------------------------------------------------------------------

#: Files that carry the solver's or the run's clock (CalculiX writes the date into .frd/.log).
VOLATILE = {"ccx.log", "study.json"}


def _norm(o, roots: tuple[str, ...]):
    if isinstance(o, dict):
        return {k: _norm(v, roots) for k, v in o.items() if k not in ("provenance", "timing")}
    if isinstance(o, list):
        return [_norm(v, roots) for v in o]
    if isinstance(o, str):
        return _norm_text(o, roots)
    return o


def _norm_text(text: str, roots: tuple[str, ...]) -> str:
    for r in roots:
        text = text.replace(r, "<out>")
    return text


def result_tree(root: Path, *others: Path) -> dict[str, object]:
    """Every result file of a study folder, comparable across runs and folders.

    Paths under ``root`` (and under ``others``: a folder the results were copied from keeps
    its name in the files of the stages that did not rerun) are written ``<out>``.
    """
    root = Path(root).resolve()
    roots = tuple(sorted({str(root), *(str(Path(o).resolve()) for o in others)}, key=len, reverse=True))
    out: dict[str, object] = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if not p.is_file() or any(x.startswith(".") for x in rel.parts) or p.name in VOLATILE:
            continue
        if p.suffix == ".json":
            out[rel.as_posix()] = _norm(json.loads(p.read_text()), roots)
        elif p.suffix in (".yaml", ".frd"):
            text = _norm_text(p.read_text(), roots)
            if p.suffix == ".frd":   # CalculiX's header records the date and time of the run
                text = "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith(("1UDATE", "1UTIME")))
            out[rel.as_posix()] = text
        else:
            out[rel.as_posix()] = p.read_bytes()
    return out


def assert_same_results(a: Path, b: Path) -> None:
    ta, tb = result_tree(a, b), result_tree(b, a)
    assert sorted(ta) == sorted(tb), (sorted(set(ta) ^ set(tb)))
    differ = [k for k in ta if ta[k] != tb[k]]
    assert not differ, f"results differ from the clean run: {differ}"


# --- the engine on small stages -----------------------------------------------------------------

def _write(name: str, inputs: list[str], value, folder: Path) -> None:
    """A stage: its value and the content of what it reads, into ``out.txt``."""
    folder = Path(folder)
    text = f"{name} {value}\n" + "".join(Path(i).read_text() for i in inputs)
    (folder / "out.txt").write_text(text)


def _fail_after_partial(folder: Path) -> None:
    (Path(folder) / "out.txt").write_text("half")
    raise ProcessingError("simulated failure half-way")


def _graph(tmp: Path, values: dict[str, int], fail: str | None = None) -> list[Stage]:
    """a -> b -> d, c -> d; ``a`` reads an input file, each writes out.txt."""
    out = tmp / "out"
    src = tmp / "input.txt"
    spec = {"a": ([], [str(src)]), "b": (["a"], []), "c": ([], []), "d": (["b", "c"], [])}
    stages = []
    for n, (after, inputs) in spec.items():
        reads = inputs + [str(out / a / "out.txt") for a in after]
        run = _fail_after_partial if n == fail else partial(_write, n, reads, values[n])
        stages.append(Stage(n, run, inputs=[Path(i) for i in inputs], after=after, config={"value": values[n]},
                            code=("bsipipe.study",)))
    return stages


def _status(outcomes) -> dict[str, str]:
    return {o.name: o.status for o in outcomes}


def test_engine_reruns_only_what_changed(tmp_path):
    from functools import partial as _p
    (tmp_path / "input.txt").write_text("raw data\n")
    values = {"a": 1, "b": 1, "c": 1, "d": 1}
    quiet = lambda s: None                                              # noqa: E731
    out = tmp_path / "out"
    jobs = 1
    run_stages = _p(_run_stages, isolate=False)                         # in this process: fast
    assert set(_status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet)).values()) == {"ran"}
    assert set(_status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet)).values()) == {"up to date"}

    values["b"] = 2                                       # a config value: b and what reads b
    assert _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet)) == {
        "a": "up to date", "b": "ran", "c": "up to date", "d": "ran"}

    (tmp_path / "input.txt").write_text("new data\n")     # an input file's content
    assert _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet)) == {
        "a": "ran", "b": "ran", "c": "up to date", "d": "ran"}
    os.utime(tmp_path / "input.txt", (1, 1))              # only its time: nothing to redo
    assert set(_status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet)).values()) == {"up to date"}

    (out / "c" / "out.txt").write_text("edited by hand\n")   # a result edited: that stage again
    assert _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet)) == {
        "a": "up to date", "b": "up to date", "c": "ran", "d": "up to date"}
    assert (out / "c" / "out.txt").read_text() == "c 1\n"
    (out / "b" / "out.txt").unlink()                         # deleted: again, and d reads it
    st = _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet))
    assert st == {"a": "up to date", "b": "ran", "c": "up to date", "d": "up to date"}
    (out / "d" / "stray.txt").write_text("x")                # a file that is not one of its results
    assert _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet))["d"] == "ran"
    assert not (out / "d" / "stray.txt").exists()

    st = _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet, force=True))
    assert set(st.values()) == {"ran"}
    st = _status(run_stages(_graph(tmp_path, values), out, jobs=jobs, echo=quiet, only=["d"], force=True))
    assert st == {"d": "ran"}


def test_engine_parallel_workers(tmp_path):
    """Two worker processes (spawned, with the given environment) give what one process gives."""
    (tmp_path / "input.txt").write_text("raw data\n")
    values = {"a": 1, "b": 1, "c": 1, "d": 1}
    quiet = lambda s: None                                              # noqa: E731
    st = run_stages(_graph(tmp_path, values), tmp_path / "out", jobs=2, echo=quiet, env={"BSIPIPE_TEST_ENV": "1"})
    assert set(_status(st).values()) == {"ran"} and "BSIPIPE_TEST_ENV" not in os.environ
    one = {p.name: p.read_text() for p in (tmp_path / "out").glob("*/out.txt")}
    values["c"] = 2
    st = run_stages(_graph(tmp_path, values), tmp_path / "out", jobs=2, echo=quiet)
    assert _status(st) == {"a": "up to date", "b": "up to date", "c": "ran", "d": "ran"}
    shutil.rmtree(tmp_path / "out")
    values["c"] = 1
    run_stages(_graph(tmp_path, values), tmp_path / "out", echo=quiet, isolate=False)
    assert one == {p.name: p.read_text() for p in (tmp_path / "out").glob("*/out.txt")}


def test_engine_failure_half_way_is_redone(tmp_path):
    (tmp_path / "input.txt").write_text("raw data\n")
    values = {"a": 1, "b": 1, "c": 1, "d": 1}
    quiet = lambda s: None                                              # noqa: E731
    out = tmp_path / "out"
    run_stages(_graph(tmp_path, values), out, echo=quiet, isolate=False)
    clean = (out / "b" / "out.txt").read_text()
    values["b"] = 2
    st = run_stages(_graph(tmp_path, values, fail="b"), out, echo=quiet)   # in a worker process
    assert _status(st) == {"a": "up to date", "b": "failed", "c": "up to date", "d": "not run"}
    assert st[1].exit_code == 1 and "half-way" in st[1].detail
    # d's folder keeps the earlier run's results, but its stamp no longer passes them off as
    # this run's (the probe had read a stale export-fe stamped done)
    assert read_stamp(out / "d")["state"] == "stale" and "b failed" in read_stamp(out / "d")["stale_because"]
    assert (out / "b" / "out.txt").read_text() == "half"           # the half-written file is there ...
    assert read_stamp(out / "b")["state"] == "running"              # ... and not taken as done
    values["b"] = 1                                                 # back to the clean run's config
    # b is redone; its result is the clean one again, so d (which reads only that) is up to date
    assert _status(run_stages(_graph(tmp_path, values), out, echo=quiet, isolate=False)) == {
        "a": "up to date", "b": "ran", "c": "up to date", "d": "up to date"}
    assert (out / "b" / "out.txt").read_text() == clean
    assert read_stamp(out / "d")["state"] == "done"                 # this run's results again


def test_engine_refuses_a_folder_it_did_not_write(tmp_path):
    (tmp_path / "input.txt").write_text("x\n")
    (tmp_path / "out" / "a").mkdir(parents=True)
    (tmp_path / "out" / "a" / "precious.txt").write_text("user data")
    st = run_stages(_graph(tmp_path, dict.fromkeys("abcd", 1)), tmp_path / "out", echo=lambda s: None,
                    isolate=False)
    assert st[0].status == "failed" and st[0].exit_code == 2 and "not written by bsipipe study" in st[0].detail
    assert (tmp_path / "out" / "a" / "precious.txt").read_text() == "user data"


def test_code_version_follows_imports():
    files = {p.relative_to(ROOT / "bsipipe").as_posix() for p in module_closure(("bsipipe.commands.register",))}
    # the command, what it imports at the top and inside run(), and their packages
    assert {"commands/register.py", "geometry/registration.py", "io/slicer.py", "provenance.py", "__init__.py",
            "geometry/__init__.py"} <= files
    assert "commands/track.py" not in files and "synth/twin.py" not in files
    assert code_version(["bsipipe.commands.register"]) != code_version(["bsipipe.commands.track"])
    # one function of a module: what it imports, not what the rest of the module does
    fe = {p.relative_to(ROOT / "bsipipe").as_posix() for p in module_closure(("bsipipe.commands.study:fe_solve",))}
    assert {"fe/_calculix.py", "io/fe_results.py", "commands/__init__.py"} <= fe
    assert "study_config.py" not in fe and "commands/track.py" not in fe


# --- the whole chain on the tiny twin ----------------------------------------------------------

def _study(config: Path, out: Path, **kw):
    from bsipipe.commands import study
    lines: list[str] = []
    kw.setdefault("jobs", 2)
    res = study.run(config, out=out, echo=lines.append, **kw)
    return {s["stage"].split("/", 1)[1]: s["status"] for s in res["stages"]}, lines


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """One clean run of the tiny study (shared by the tests below, which work on copies)."""
    out = tmp_path_factory.mktemp("study") / "clean"
    t0 = time.perf_counter()
    status, lines = _study(TINY, out)
    print(f"\nclean tiny study: {time.perf_counter() - t0:.1f} s\n" + "\n".join(lines))
    return out, status


def _copy(clean_out: Path, dest: Path) -> Path:
    shutil.copytree(clean_out, dest, symlinks=True)
    return dest


def test_tiny_study_end_to_end(clean):
    out, status = clean
    from bsipipe.fe._calculix import ccx_executable
    expect_fe = ccx_executable() is not None
    assert status == {"synth": "ran", "calibrate": "ran", "track": "ran", "register": "ran", "fit-ogden": "ran",
                      "export-fe": "ran", "fe-solve": "ran" if expect_fe else "skipped",
                      "compare": "ran" if expect_fe else "skipped"}
    t = out / "tiny"
    for f in ("synth/synth.json", "calibrate/calibration.json", "track/markers3d.csv", "register/markers_ct.csv",
              "fit-ogden/fit.json", "export-fe/manifest.json", "config/calibrate.yaml"):
        assert (t / f).is_file(), f
    assert read_stamp(t / "track")["state"] == "done"
    # each two-view point's standard deviation per axis, propagated from its centres' (the
    # Monte Carlo check is tests/test_triangulate.py); none for single-view points
    p3 = pd.read_csv(t / "track" / "markers3d.csv")
    two = p3["n_views"] == 2
    sds = p3[["sd_x_mm", "sd_y_mm", "sd_z_mm", "sd_x_mm_raw", "sd_y_mm_raw", "sd_z_mm_raw"]]
    assert two.any() and (sds[two] > 0).all().all() and (sds[two] < 1.0).all().all()
    assert sds[~two].isna().all().all()
    # the tracking loop's steps, each with the ray gap before and after
    md = (t / "track" / "loop.md").read_text()
    assert md.startswith("# Tracking and triangulation: closing the loop") and "| 0 | declared model `stereo`" in md
    if expect_fe:
        cmp = json.loads((t / "compare" / "compare.json").read_text())
        assert cmp["n_markers"] >= 1 and cmp["sigma_mm"] >= 0
        # the indentor's force, the FE stage's other target, in N beside the log's (the .dat
        # holds it in the deck's force unit, mN here; no output had shown it)
        fs = json.loads((t / "fe-solve" / "fe_solve.json").read_text())
        f = fs["indentor_force"]
        from bsipipe.fe._calculix import parse_dat
        tot = [b for b in parse_dat((t / "fe-solve" / "job.dat").read_text()) if b.title.startswith("total force")]
        assert len(f["magnitude_n"]) == len(tot)
        assert f["peak"]["magnitude_n"] == pytest.approx(max(np.linalg.norm(b.values) for b in tot) / 1e3, rel=1e-6)
        assert 0 < f["peak"]["log_force_n"] < 1.0 and f["peak"]["ratio"] == pytest.approx(
            f["peak"]["magnitude_n"] / f["peak"]["log_force_n"])
    summary = json.loads((out / "study.json").read_text())
    assert summary["counts"]["failed"] == 0 and "provenance" in summary


def test_tiny_study_against_the_twins_truth(clean):
    """The chain from rendered frames to the FE hand-off scored on the tiny (256 px) twin:
    the sample study's own figures come from ``scripts/twin_check.py results/sheep1``."""
    from bsipipe.synth.check import format_check, twin_check
    out, status = clean
    c = twin_check(out / "tiny")
    print(format_check(c))
    assert c["registration"]["rms_mm"] < 0.1
    assert c["indentor"]["source"].startswith("markers3d.csv")      # tracked on its beads
    assert c["indentor"]["trajectory"]["n"] >= 5 and c["indentor"]["trajectory"]["max_mm"] < 0.1
    assert c["markers_fe"]["displacement"]["n"] >= 30 and c["markers_fe"]["displacement"]["rms_mm"] < 0.1
    assert abs(c["indentor"]["depth_mm"] - c["indentor"]["depth_true_mm"]) < 0.2
    # the points' stated 3-D sds against their errors in the FE frame, which also carry the
    # registration's and the calibration's (1.64 here, 1.16 on the sample study; 1.72 and 1.41 with a
    # plane under every marker, before the edge background; 0.94 in the
    # X-ray frame itself): within a factor of 3 either way
    z = c["markers_fe"]["position_over_stated_sd"]
    assert z["n"] >= 30 and 1 / 3 < z["z_rms"] < 3


def test_second_run_redoes_nothing_and_one_value_redoes_downstream(clean, tmp_path):
    out = _copy(clean[0], tmp_path / "out")
    t0 = time.perf_counter()
    status, lines = _study(TINY, out)
    assert set(status.values()) <= {"up to date", "skipped"}, status
    assert time.perf_counter() - t0 < 20
    assert any("stage" in ln and "status" in ln for ln in lines)          # the summary table

    cfg = yaml.safe_load(TINY.read_text())
    cfg["register"]["perturbation_draws"] = 150                          # one value of one stage
    changed = tmp_path / "configs" / "study_tiny.yaml"
    changed.parent.mkdir()
    changed.write_text(yaml.safe_dump(cfg))
    shutil.copytree(ROOT / "configs", tmp_path / "configs", dirs_exist_ok=True,
                    ignore=lambda d, names: [n for n in names if n == "study_tiny.yaml"])
    (tmp_path / "sample_data").symlink_to(ROOT / "sample_data")
    status, _ = _study(changed, out, jobs=1)
    ran = {k for k, v in status.items() if v == "ran"}
    assert ran == {"register", "export-fe"} | ({"fe-solve", "compare"} & {k for k, v in clean[1].items() if v == "ran"})
    assert {"synth", "calibrate", "track", "fit-ogden"} <= {k for k, v in status.items() if v == "up to date"}


def test_deleted_and_edited_results_are_redone(clean, tmp_path):
    out = _copy(clean[0], tmp_path / "out")
    (out / "tiny" / "register" / "markers_ct.csv").unlink()
    status, lines = _study(TINY, out, jobs=1, stages=["register"])
    assert status == {"register": "ran"} and any("markers_ct.csv is missing" in ln for ln in lines)
    trk = out / "tiny" / "track" / "track.json"
    trk.write_bytes(trk.read_bytes()[:-200])                         # truncated
    status, lines = _study(TINY, out, jobs=1)
    assert {k for k, v in status.items() if v == "ran"} == {"track", "register", "export-fe", "fe-solve",
                                                            "compare"} & set(status)
    assert any("track: running (track.json was changed)" in ln for ln in lines)
    assert {status[s] for s in ("synth", "calibrate", "fit-ogden")} == {"up to date"}
    assert_same_results(out, clean[0])


def _half_then_raise(folder: Path) -> None:
    """A register stage that dies half-way: part of a result file written, then an error."""
    (Path(folder) / "markers_ct.csv").write_text("frame,time_s,marker\n0,0,")
    raise RuntimeError("killed half-way (simulated)")


def test_stage_raising_half_way_is_redone(clean, tmp_path):
    from bsipipe.study_config import SINGLE_THREAD_ENV, load_study, plan_study, to_stages

    out = _copy(clean[0], tmp_path / "out")
    study = load_study(TINY, out)
    stages = to_stages(plan_study(study), study)
    for s in stages:
        if s.name == "tiny/register":
            s.run = _half_then_raise
    st = run_stages(stages, study.out, force=True, only=["tiny/register"], env=SINGLE_THREAD_ENV,
                    echo=lambda s: None)
    assert [(o.name, o.status, o.exit_code) for o in st] == [("tiny/register", "failed", 1)]
    assert "killed half-way" in st[0].detail
    assert read_stamp(out / "tiny" / "register")["state"] == "running"
    status, lines = _study(TINY, out, jobs=1)
    assert status["register"] == "ran" and status["track"] == "up to date"
    assert any("register: running (the last run did not finish)" in ln for ln in lines)
    assert_same_results(out, clean[0])


def test_sigkill_at_a_random_point_then_rerun(clean, tmp_path):
    """One real SIGKILL of `bsipipe study` while it redoes the last stages, at a random moment."""
    out = _copy(clean[0], tmp_path / "out")
    rng = random.Random(int(os.environ.get("BSIPIPE_KILL_SEED", "6")))
    delay = rng.uniform(1.0, 8.0)
    proc = subprocess.Popen([BSIPIPE, "study", str(TINY), "-o", str(out), "--force", "-j", "1",
                             "--stage", "register", "--stage", "export-fe", "--stage", "fe-solve",
                             "--stage", "compare"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    time.sleep(delay)
    os.killpg(proc.pid, signal.SIGKILL)     # the study and any solver it started
    log = proc.communicate()[0].decode()
    print(f"killed after {delay:.2f} s; its output:\n{log}")
    status, _ = _study(TINY, out, jobs=1)
    assert {status[s] for s in ("synth", "calibrate", "track")} == {"up to date"}
    assert_same_results(out, clean[0])
    status, _ = _study(TINY, out, jobs=1)
    assert set(status.values()) <= {"up to date", "skipped"}


def test_cli_exit_status_and_messages(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(TINY.read_text().replace("register:", "registr:", 1))
    p = subprocess.run([BSIPIPE, "study", str(bad)], capture_output=True, text=True)
    assert p.returncode == 2 and "registr" in p.stderr and "unknown key" in p.stderr and "Traceback" not in p.stderr
    cfg = yaml.safe_load(TINY.read_text())
    cfg["trials"] = [{"name": "x", "track": {"polarity": "grey"}}]
    bad.write_text(yaml.safe_dump(cfg))
    p = subprocess.run([BSIPIPE, "study", str(bad)], capture_output=True, text=True)
    assert p.returncode == 2 and "trials.0.track.polarity" in p.stderr
    p = subprocess.run([BSIPIPE, "study", str(TINY), "-o", str(tmp_path / "o"), "--stage", "nope"],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "no stage named 'nope'" in p.stderr
    # a stage whose input is invalid: that stage fails with its command's status and message
    cfg = yaml.safe_load(TINY.read_text())
    cfg["fit-ogden"]["logs"] = [str(ROOT / "tests" / "data" / "logs" / "bad_text_in_number.csv")]
    bad.write_text(yaml.safe_dump(cfg))
    p = subprocess.run([BSIPIPE, "study", str(bad), "-o", str(tmp_path / "o"), "--stage", "fit-ogden", "-j", "1"],
                       capture_output=True, text=True)
    assert p.returncode == 2, p.stderr
    assert "stage tiny/fit-ogden failed" in p.stderr and "bad_text_in_number.csv" in p.stderr
    assert "FAILED" in p.stdout and "Traceback" not in p.stderr + p.stdout
    assert read_stamp(tmp_path / "o" / "tiny" / "fit-ogden")["state"] == "running"


def test_trials_are_validated_and_planned(tmp_path):
    from bsipipe.study_config import load_study, plan_study
    cfg = yaml.safe_load(TINY.read_text())
    cfg["trials"] = [{"name": "s1"}, {"name": "s2", "synth": {"seed": 9}}]
    p = tmp_path / "configs" / "t.yaml"
    p.parent.mkdir()
    p.write_text(yaml.safe_dump(cfg))
    (tmp_path / "sample_data").symlink_to(ROOT / "sample_data")
    study = load_study(p, tmp_path / "o")
    plans = plan_study(study)
    assert [x.name for x in plans[:2]] == ["s1/synth", "s1/calibrate"]
    synth = {x.trial: x.config_file[1] for x in plans if x.stage == "synth"}
    assert "seed: 9" in synth["s2"] and "seed: 9" not in synth["s1"]
    cfg["trials"] = [{"name": "s1"}, {"name": "s1"}]
    p.write_text(yaml.safe_dump(cfg))
    with pytest.raises(InputError, match="listed twice"):
        load_study(p)


def test_track_region_of_interest_in_a_study(tmp_path):
    """A mask image named in the study's track section: its path is taken relative to the
    study config (as the other inputs), written absolute into the stage's track config, and
    the mask is one of the stage's inputs (a changed mask redoes the stage); a circle passes
    through as it is."""
    from bsipipe.study_config import load_study, plan_study
    cfg = yaml.safe_load(TINY.read_text())
    cfg["track"] = {"detection": {"roi": "masks/m.png"}}
    p = tmp_path / "configs" / "t.yaml"
    (tmp_path / "configs" / "masks").mkdir(parents=True)
    (tmp_path / "sample_data").symlink_to(ROOT / "sample_data")
    p.write_text(yaml.safe_dump(cfg))
    mask = str(tmp_path / "configs" / "masks" / "m.png")
    track = next(x for x in plan_study(load_study(p, tmp_path / "o")) if x.stage == "track")
    assert yaml.safe_load(track.config_file[1])["detection"]["roi"] == mask and mask in track.inputs
    cfg["track"] = {"detection": {"roi": {"cam1": {"centre_px": [128, 128], "radius_px": 100}, "cam2": "auto"}}}
    p.write_text(yaml.safe_dump(cfg))
    track = next(x for x in plan_study(load_study(p, tmp_path / "o")) if x.stage == "track")
    assert yaml.safe_load(track.config_file[1])["detection"]["roi"] == {
        "cam1": {"centre_px": [128.0, 128.0], "radius_px": 100.0}, "cam2": "auto"}


def test_sample_logs_regenerate_byte_for_byte(tmp_path):
    """sample_data/logs is what scripts/make_sample_data.py makes, byte for byte."""
    p = subprocess.run([sys.executable, str(ROOT / "scripts" / "make_sample_data.py"), "--check"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr
    truth = json.loads((ROOT / "sample_data" / "logs" / "truth.json").read_text())
    assert len(truth["logs"]) == 3 and truth["tissue"]["params"]["mu_pa"] == 720.0


def test_export_fe_checks_follow_the_twins_design(tmp_path):
    """On a twin indenting 3 mm at 30 mm/min, export-fe's checks expect the twin's speed and
    depth (its defaults, the sheep study's 12 mm/min and 4.8 mm, had stopped the study at
    export-fe: "check failed: 30 mm/min, expected 12 +- 0.6"); checks the study config gives
    are kept."""
    from bsipipe.study_config import load_study, plan_study
    cfg = yaml.safe_load(TINY.read_text())
    cfg.setdefault("synth", {}).setdefault("sequence", {}).update(speed_mm_per_min=30.0, depth_mm=3.0)
    p = tmp_path / "configs" / "t.yaml"
    p.parent.mkdir()
    (tmp_path / "sample_data").symlink_to(ROOT / "sample_data")
    p.write_text(yaml.safe_dump(cfg))

    def checks():
        exp = next(x for x in plan_study(load_study(p, tmp_path / "o")) if x.stage == "export-fe")
        return yaml.safe_load(exp.config_file[1])["checks"]

    c = checks()
    assert c["speed_mm_per_min"] == 30.0 and c["depth_mm"] == 3.0
    cfg.setdefault("export-fe", {})["checks"] = {"depth_mm": 2.9}
    p.write_text(yaml.safe_dump(cfg))
    c = checks()
    assert c["speed_mm_per_min"] == 30.0 and c["depth_mm"] == 2.9
