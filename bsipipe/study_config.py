"""The study's config (``configs/study.yaml``) and the plan it makes: one command per stage and trial.

A study chains the commands ``synth -> calibrate -> track -> register``, ``fit-ogden``,
``export-fe -> fe-solve -> compare`` for every trial (specimen).  The config holds one
section per stage; each section takes the keys of its command's own config (validated by
that command's model, so an unknown key is an error naming ``<stage>.<key>``) plus the
study's input paths.  Paths are relative to the study config's folder.

With a ``synth`` section the study runs on the seeded X-ray twin: ``synth`` renders the
calibration views, the sequence, the CT markers and the seeds, and the later stages default
their inputs, pattern, frame rate and reference names to the twin's.  Without it the
sections name the recorded data (``calibrate.views``/``stereo``, ``track.views``/``seeds``,
``register.ct``/``references``, ...).

``trials:`` lists the specimens: each has a ``name`` and may override any key of any
section (deep-merged), e.g. ``{name: sheep2, synth: {seed: 2}}``.  Results go to
``<out>/<trial>/<stage>/``; the command configs the study writes for ``synth``,
``calibrate``, ``track``, ``fit-ogden`` and ``export-fe`` go to ``<out>/<trial>/config/``.

:func:`plan_study` turns the config into :class:`StagePlan` objects, each holding the
command line (``argv``, what the Snakemake workflow runs) and the equivalent in-process
call of the command's ``run`` (what ``bsipipe study`` runs), built from the same values.
"""

from __future__ import annotations

import copy
import glob
import json
import os
import re
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Callable, Literal

import yaml
from pydantic import Field, field_validator

from .config import StrictModel, load_yaml, validate
from .errors import InputError

STAGES = ("synth", "calibrate", "track", "register", "fit-ogden", "export-fe", "fe-solve", "compare")

#: The bsipipe modules that compute each stage (their transitive imports enter the stage's key).
STAGE_CODE = {
    "synth": ("bsipipe.commands.synth", "bsipipe.synth.twin", "bsipipe.synth.config", "bsipipe.synth.machine_log"),
    "calibrate": ("bsipipe.commands.calibrate",),
    "track": ("bsipipe.commands.track",),
    "register": ("bsipipe.commands.register",),
    "fit-ogden": ("bsipipe.commands.fit_ogden",),
    "export-fe": ("bsipipe.commands.export_fe",),
    "fe-solve": ("bsipipe.commands.study:fe_solve",),
    "compare": ("bsipipe.commands.compare",),
}

#: The file a stage writes last (its command's "run is complete" result).
PRIMARY = {"synth": "synth.json", "calibrate": "calibration.json", "track": "track.json",
           "register": "registration.json", "fit-ogden": "fit.json", "export-fe": "manifest.json",
           "fe-solve": "fe_solve.json", "compare": "compare.json"}

#: The environment every stage's command runs in: one thread for OpenCV and the BLAS, so that
#: sums are taken in one order and a stage gives the same bytes on every run (OpenCV's
#: calibrateCamera and OpenBLAS reduce in a thread-dependent order).  The study parallelises
#: across stages and trials instead; the Snakemake workflow runs its commands under it too.
SINGLE_THREAD_ENV = {"OPENCV_FOR_THREADS_NUM": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                     "MKL_NUM_THREADS": "1", "GOTO_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1",
                     "NUMEXPR_NUM_THREADS": "1"}

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# --- the config model ---------------------------------------------------------------------------

class RegisterSection(StrictModel):
    """``register``: ``bsipipe register``'s settings and its two inputs."""

    ct: str | None = Field(None, description="CT markers (.fcsv, .mrk.json, CSV); default the twin's ct_markers.fcsv")
    references: list[str] | None = Field(None, description="reference markers; default the twin's R1..Rn")
    frame: int | None = None
    scale: bool = False
    loop: bool = True
    perturbation_draws: int = Field(2000, ge=0)
    seed: int = 0


class FitSection(StrictModel):
    """``fit-ogden``: the machine logs (files or globs) and ``bsipipe fit-ogden --config``'s keys."""

    logs: list[str] = Field(min_length=1, description="testing-machine logs, files or glob patterns")
    width_csv: str | None = None
    config: dict[str, Any] = Field(default_factory=dict, description="FitConfig keys (model, prony, loop, ...)")


class FeSolveSection(StrictModel):
    """``fe-solve``: run the exported ABAQUS deck in CalculiX."""

    enabled: Literal["auto", True, False] = Field(
        "auto", description="auto: run when `ccx` is on PATH, else skip fe-solve and compare with a message")
    deck: str = Field("abaqus/model.inp", description="the deck inside export-fe's folder")
    timeout_s: float = Field(1800.0, gt=0)


class CompareSection(StrictModel):
    """``compare``: ``bsipipe compare``'s settings; FE result and mesh default to fe-solve's and export-fe's."""

    fe_displacements: str | None = None
    mesh: str | None = None
    frame: int | None = None
    markers: list[str] = Field(default_factory=list)
    fe_result: int | None = None
    length_unit: Literal["mm", "m"] = "mm"
    outside_tol_mm: float = Field(0.0, ge=0)


class Sections(StrictModel):
    """Every stage's section, as one trial sees them (after its overrides)."""

    synth: dict[str, Any] | None = Field(None, description="bsipipe synth's config: the twin (omit for real data)")
    calibrate: dict[str, Any] = Field(default_factory=dict, description="bsipipe calibrate's config keys")
    track: dict[str, Any] = Field(default_factory=dict, description="bsipipe track's config keys")
    register_: RegisterSection = Field(RegisterSection(), alias="register")
    fit_ogden: FitSection = Field(alias="fit-ogden")
    export_fe: dict[str, Any] = Field(default_factory=dict, alias="export-fe",
                                      description="bsipipe export-fe's config keys")
    fe_solve: FeSolveSection = Field(FeSolveSection(), alias="fe-solve")
    compare: CompareSection = CompareSection()


class TrialSpec(StrictModel):
    name: str

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not _NAME.match(v) or v == "config":
            raise ValueError("a trial name is letters, digits, '_', '-', '.' (and not 'config')")
        return v


@dataclass
class Trial:
    name: str
    sections: Sections
    index: int = 0
    overridden: frozenset = frozenset()

    def key(self, section: str) -> str:
        """Where a section's key is written: ``trials.i.<section>`` when this trial overrides it."""
        return f"trials.{self.index}.{section}" if section in self.overridden else section


@dataclass
class StudyConfig:
    """A validated study: where its config lives (``base``), its output folder and its trials."""

    path: Path
    base: Path
    out: Path
    trials: list[Trial]
    raw: dict

    def as_dict(self) -> dict:
        return {"out": str(self.out), "trials": [{"name": t.name, **t.sections.model_dump(mode="json", by_alias=True)}
                                                 for t in self.trials]}


def _deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def load_study(path: str | os.PathLike, out: str | os.PathLike | None = None) -> StudyConfig:
    """Read and validate a study config; ``out`` (e.g. ``-o``) wins over its ``out`` key."""
    path = Path(path)
    raw = load_yaml(path)
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise InputError("expected a mapping of keys to values", path=path)
    base = path.resolve().parent
    top_keys = {"out", "trials", *(f.alias or n for n, f in Sections.model_fields.items())}
    for k in raw:
        if k not in top_keys:
            raise InputError("unknown key", path=path, key=str(k))
    out_value = raw.get("out", "results")
    if not isinstance(out_value, str) or not out_value:
        raise InputError("expected a folder name", path=path, key="out")
    out_dir = Path(out) if out is not None else Path(out_value)
    if not out_dir.is_absolute():
        out_dir = (Path.cwd() if out is not None else base) / out_dir
    sections_raw = {k: v for k, v in raw.items() if k not in ("out", "trials")}
    trials_raw = raw.get("trials")
    if trials_raw is None:
        trials_raw = [{"name": "main"}]
    if not isinstance(trials_raw, list) or not trials_raw:
        raise InputError("expected a list of trials, each with a name", path=path, key="trials")
    _validate_prefixed(Sections, sections_raw, path, None)
    trials: list[Trial] = []
    for i, t in enumerate(trials_raw):
        if not isinstance(t, dict):
            raise InputError("expected a mapping with a name", path=path, key=f"trials.{i}")
        overrides = {k: v for k, v in t.items() if k != "name"}
        for k in overrides:
            if k not in top_keys or k in ("out", "trials"):
                raise InputError("unknown key", path=path, key=f"trials.{i}.{k}")
        spec = _validate_prefixed(TrialSpec, {"name": t.get("name")}, path, f"trials.{i}")
        merged = _deep_merge(sections_raw, overrides)
        prefix = f"trials.{i}" if overrides else None
        sections = _validate_prefixed(Sections, merged, path, prefix)
        trials.append(Trial(spec.name, sections, i, frozenset(overrides)))
    names = [t.name for t in trials]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise InputError(f"trial {dupes[0]!r} is listed twice", path=path, key="trials")
    study = StudyConfig(path=path, base=base, out=out_dir.resolve(), trials=trials, raw=raw)
    plan_study(study)   # every stage's own config is validated before anything runs
    return study


def _validate_prefixed(model, data, path, prefix: str | None):
    try:
        return validate(model, data, source=path)
    except InputError as e:
        if prefix:
            e.key = f"{prefix}.{e.key}" if e.key else prefix
            e.args = (str(e),)
        raise


# --- the plan -----------------------------------------------------------------------------------

@dataclass
class StagePlan:
    """One stage of one trial: the command line and the same call in process.

    ``argv`` are the arguments of ``bsipipe`` (``["calibrate", CONFIG, "-o", DIR]``);
    ``call(out_dir)`` runs the same command in this process.  ``config_file`` is the command
    config the stage reads (path, text), written by :func:`write_config_file` before the
    command runs.  ``key_config`` is what enters the stage's key: the command line and the
    config text with the study's folders written as ``<base>`` and ``<out>``.
    """

    trial: str
    stage: str
    folder: str
    after: list[str]
    inputs: list[str]
    argv: list[str]
    call: Callable[[Path], Any]
    config_file: tuple[str, str] | None = None
    skip: str | None = None
    extra: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.trial}/{self.stage}"

    @property
    def primary(self) -> str:
        return f"{self.folder}/{PRIMARY[self.stage]}"


def _tokenise(text: str, study: StudyConfig) -> str:
    pairs = sorted([(str(study.out), "<out>"), (str(study.base), "<base>")], key=lambda p: -len(p[0]))
    for a, b in pairs:
        text = text.replace(a, b)
    return text


def key_config(plan: StagePlan, study: StudyConfig) -> dict:
    return {"stage": plan.stage, "argv": [_tokenise(a, study) for a in plan.argv],
            "config_file": None if plan.config_file is None else _tokenise(plan.config_file[1], study)}


def write_config_file(config_file: tuple[str, str] | None) -> None:
    """Write a stage's command config, only when its text changed (a rerun keeps its mtime)."""
    if config_file is None:
        return
    path, text = Path(config_file[0]), config_file[1]
    try:
        if path.read_text(encoding="utf-8") == text:
            return
    except OSError:
        pass
    from .provenance import atomic_write_bytes
    atomic_write_bytes(path, text.encode("utf-8"))


def _yaml_text(header: str, data: dict) -> str:
    return f"# {header}\n# Written by bsipipe study from the study config; edit that, not this file.\n" + \
        yaml.safe_dump(data, sort_keys=False, default_flow_style=False)


def _abs(p: str, base: Path) -> str:
    return str(Path(p) if os.path.isabs(p) else (base / p))


def _run_command(stage: str, args: tuple, kwargs: dict, config_file, out_dir: Path):
    """Write the stage's config, then call ``bsipipe.commands.<stage>.run(*args, out=out_dir, **kwargs)``."""
    import importlib

    write_config_file(config_file)
    mod = importlib.import_module(f"bsipipe.commands.{stage.replace('-', '_')}")
    return mod.run(*args, out=str(out_dir), **kwargs)


def _run_fe_solve(deck: str, timeout_s: float, length_unit: str, out_dir: Path):
    from .commands.study import fe_solve
    return fe_solve(deck, out=out_dir, timeout_s=timeout_s, length_unit=length_unit)


def _opts(pairs) -> list[str]:
    """``--flag value`` pairs (None dropped, lists repeated, booleans as given)."""
    out: list[str] = []
    for flag, v in pairs:
        if v is None:
            continue
        if isinstance(v, (list, tuple)):
            for x in v:
                out += [flag, str(x)]
        elif isinstance(v, bool):
            out.append(flag if v else "--no-" + flag[2:])
        else:
            out += [flag, repr(v) if isinstance(v, float) else str(v)]
    return out


def _expand_logs(patterns: list[str], base: Path, source: Path, key: str) -> list[str]:
    files: list[str] = []
    for i, pat in enumerate(patterns):
        p = _abs(pat, base)
        hits = sorted(glob.glob(p)) if any(c in p for c in "*?[") else ([p] if os.path.exists(p) else [])
        if not hits:
            raise InputError(f"no file matches {pat!r}", path=source, key=f"{key}.{i}")
        files += [h for h in hits if h not in files]
    return files


def plan_study(study: StudyConfig) -> list[StagePlan]:
    """Every stage of every trial, in order; validates each command's config."""
    plans: list[StagePlan] = []
    for trial in study.trials:
        plans += _plan_trial(study, trial)
    return plans


def _plan_trial(study: StudyConfig, trial: Trial) -> list[StagePlan]:
    from .commands.calibrate import CalibrateConfig
    from .commands.track import TrackConfig, map_roi_masks, roi_masks
    from .config import FitConfig

    s, base, src = trial.sections, study.base, study.path
    tdir = study.out / trial.name
    cfgdir = tdir / "config"
    folder = {st: f"{trial.name}/{st}" for st in STAGES}
    sdir = {st: tdir / st for st in STAGES}
    plans: list[StagePlan] = []

    def add(stage, after, inputs, argv, call, config_file=None, skip=None, **extra):
        plans.append(StagePlan(trial.name, stage, folder[stage], [f"{trial.name}/{a}" for a in after], inputs,
                               argv, call, config_file, skip, extra))

    def command(stage, args, kwargs, opts, config_file=None, positional=None):
        argv = [stage, *(positional if positional is not None else [str(a) for a in args]), *opts,
                "-o", str(sdir[stage])]
        return argv, partial(_run_command, stage, tuple(args), kwargs, config_file)

    # synth ----------------------------------------------------------------------------------------
    twin = None
    if s.synth is not None:
        from .synth.config import SynthConfig
        from .synth.twin import VIEWS
        twin = _validate_prefixed(SynthConfig, s.synth, src, trial.key("synth"))
        cf = (str(cfgdir / "synth.yaml"), _yaml_text("bsipipe synth config", twin.model_dump(mode="json")))
        argv, call = command("synth", [cf[0]], {}, [], cf)
        add("synth", [], [], argv, call, cf)
        views = list(VIEWS)

    # calibrate ------------------------------------------------------------------------------------
    cal = dict(s.calibrate)
    for k in ("views", "stereo"):
        if k in cal and isinstance(cal[k], dict):
            cal[k] = {n: _abs(p, base) for n, p in cal[k].items()}
    if isinstance(cal.get("images"), str):
        cal["images"] = _abs(cal["images"], base)
    if twin is not None:
        c = twin.calibration
        d: dict[str, Any] = {"pattern": c.pattern, "grid": f"{c.grid[0]}x{c.grid[1]}", "spacing_mm": c.spacing_mm}
        if c.views > 0:
            d["views"] = {v: str(sdir["synth"] / "calibration" / v) for v in views}
        if c.stereo_views > 0:
            d["stereo"] = {v: str(sdir["synth"] / "calibration" / "stereo" / v) for v in views}
        if c.pattern == "charuco":
            d["marker_mm"] = c.spacing_mm * c.charuco_marker_fraction
            d["dictionary"] = c.charuco_dictionary
        cal = {**d, **cal}
    cal_cfg = _validate_prefixed(CalibrateConfig, cal, src, trial.key("calibrate"))
    if cal_cfg.images is None and not cal_cfg.views and not cal_cfg.stereo:
        raise InputError("nothing to calibrate: give views, stereo or images", path=src, key=trial.key("calibrate"))
    cf = (str(cfgdir / "calibrate.yaml"), _yaml_text("bsipipe calibrate config", cal_cfg.model_dump(mode="json")))
    argv, call = command("calibrate", [cf[0]], {}, [], cf)
    cal_inputs = [] if twin is not None else [p for p in [cal_cfg.images, *cal_cfg.views.values(),
                                                          *cal_cfg.stereo.values()] if p]
    add("calibrate", ["synth"] if twin is not None else [], cal_inputs, argv, call, cf)

    # track ----------------------------------------------------------------------------------------
    trk = dict(s.track)
    if isinstance(trk.get("views"), dict):
        trk["views"] = {n: _abs(p, base) for n, p in trk["views"].items()}
    if isinstance(trk.get("seeds"), str):
        trk["seeds"] = _abs(trk["seeds"], base)
    if isinstance(trk.get("detection"), dict) and "roi" in trk["detection"]:
        # mask images' paths, relative to the study config
        trk["detection"] = {**trk["detection"],
                            "roi": map_roi_masks(trk["detection"]["roi"], lambda p: _abs(p, base))}
    if "calibration" in trk:
        raise InputError("the study's track stage reads calibrate's calibration.json; remove this key",
                         path=src, key=f"{trial.key('track')}.calibration")
    trk["calibration"] = str(sdir["calibrate"] / "calibration.json")
    if twin is not None:
        trk = {"views": {v: str(sdir["synth"] / "sequence" / v) for v in views},
               "seeds": str(sdir["synth"] / "seeds.csv"), "fps": twin.sequence.fps, **trk}
    trk_cfg = _validate_prefixed(TrackConfig, trk, src, trial.key("track"))
    cf = (str(cfgdir / "track.yaml"), _yaml_text("bsipipe track config", trk_cfg.model_dump(mode="json")))
    argv, call = command("track", [cf[0]], {}, [], cf)
    trk_inputs = [] if twin is not None else [*trk_cfg.views.values(), *([trk_cfg.seeds] if trk_cfg.seeds else [])]
    trk_inputs += roi_masks(trk_cfg.detection.roi)
    add("track", ["synth", "calibrate"] if twin is not None else ["calibrate"], trk_inputs, argv, call, cf)

    # register -------------------------------------------------------------------------------------
    r = s.register_
    ct = _abs(r.ct, base) if r.ct else (str(sdir["synth"] / "ct_markers.fcsv") if twin is not None else None)
    refs = r.references if r.references is not None else (
        [f"R{i}" for i in range(1, twin.sequence.n_references + 1)] if twin is not None else None)
    if ct is None:
        raise InputError("required key is missing (the CT marker file)", path=src, key=f"{trial.key('register')}.ct")
    if not refs:
        raise InputError("required key is missing (the reference markers)", path=src,
                         key=f"{trial.key('register')}.references")
    xray = str(sdir["track"] / "markers3d.csv")
    kw = {"frame": r.frame, "scale": r.scale, "loop": r.loop, "perturbation_draws": r.perturbation_draws,
          "seed": r.seed}
    opts = _opts([("--ct", ct), ("--xray", xray), ("--reference", refs), ("--frame", r.frame),
                  ("--scale", r.scale), ("--loop", r.loop), ("--perturbation-draws", r.perturbation_draws),
                  ("--seed", r.seed)])
    argv, call = command("register", [ct, xray, tuple(refs)], kw, opts, positional=[])
    add("register", ["track", "synth"] if (twin is not None and r.ct is None) else ["track"],
        [ct] if r.ct else [], argv, call)

    # fit-ogden ------------------------------------------------------------------------------------
    f = s.fit_ogden
    logs = _expand_logs(f.logs, base, src, f"{trial.key('fit-ogden')}.logs")
    fit_cfg = _validate_prefixed(FitConfig, f.config, src, f"{trial.key('fit-ogden')}.config")
    cf = (str(cfgdir / "fit-ogden.yaml"), _yaml_text("bsipipe fit-ogden config", fit_cfg.model_dump(mode="json")))
    width = _abs(f.width_csv, base) if f.width_csv else None
    kw = {"config": cf[0], "width_csv": width}
    opts = _opts([("--config", cf[0]), ("--width-csv", width)])
    argv, call = command("fit-ogden", [logs], kw, opts, cf, positional=logs)
    add("fit-ogden", [], logs + ([width] if width else []), argv, call, cf)

    # export-fe, fe-solve, compare -----------------------------------------------------------------
    _plan_fe(study, trial, twin, sdir, cfgdir, add, command)
    return plans


def _plan_fe(study, trial, twin, sdir, cfgdir, add, command) -> None:
    """export-fe, fe-solve and compare (added through ``add``)."""
    from .fe._calculix import ccx_executable
    from .io._fe_material import unit_system

    s, base, src = trial.sections, study.base, study.path
    exp, exp_after, exp_inputs = _export_fe_config(s.export_fe, twin, sdir, base, src, trial.key("export-fe"))
    cf = (str(cfgdir / "export-fe.yaml"), _yaml_text("bsipipe export-fe config", exp))
    argv, call = command("export-fe", [cf[0]], {}, [], cf)
    add("export-fe", exp_after, exp_inputs, argv, call, cf)

    fs = s.fe_solve
    skip = None
    if fs.enabled is False:
        skip = "disabled in the study config (fe-solve.enabled: false)"
    elif ccx_executable() is None:
        if fs.enabled is True:
            raise InputError("CalculiX 'ccx' is not on PATH (apt-get install calculix-ccx, or `make ccx`)",
                             path=src, key=f"{trial.key('fe-solve')}.enabled")
        skip = "CalculiX 'ccx' is not on PATH (apt-get install calculix-ccx, or `make ccx`)"
    deck = str(sdir["export-fe"] / fs.deck)
    length_unit = unit_system(exp["deck"]["units"]).length
    argv = ["study", str(study.path.resolve()), "-o", str(study.out), "--trial", trial.name, "--stage", "fe-solve",
            "-j", "1"]
    add("fe-solve", ["export-fe"], [], argv, partial(_run_fe_solve, deck, fs.timeout_s, length_unit), skip=skip,
        key_argv=["fe-solve", deck, repr(fs.timeout_s), length_unit])

    c = s.compare
    # fe-solve's whole result file: compare pairs the peak frame with the FE result at its time
    # (the deck's clock) and sets every other result against its frame (the loading history)
    fe_disp = _abs(c.fe_displacements, base) if c.fe_displacements else str(sdir["fe-solve"] / "job.frd")
    mesh = _abs(c.mesh, base) if c.mesh else deck
    unit = c.length_unit if (c.fe_displacements or c.mesh) else length_unit
    markers = str(sdir["register"] / "markers_ct.csv")
    kw = {"frame": c.frame, "marker_names": tuple(c.markers), "fe_result": c.fe_result,
          "length_unit": unit, "outside_tol_mm": c.outside_tol_mm}
    opts = _opts([("--fe-displacements", fe_disp), ("--mesh", mesh), ("--markers", markers), ("--frame", c.frame),
                  ("--marker", list(c.markers)), ("--fe-result", c.fe_result), ("--length-unit", unit),
                  ("--outside-tol-mm", c.outside_tol_mm)])
    argv, call = command("compare", [fe_disp, mesh, markers], kw, opts, positional=[])
    after = ["register"] + ([] if c.fe_displacements else ["fe-solve"]) + ([] if c.mesh else ["export-fe"])
    cskip = None
    if skip and not c.fe_displacements:
        cskip = f"no FE displacements: fe-solve is skipped ({skip})"
    add("compare", after, [p for p, given in ((fe_disp, c.fe_displacements), (mesh, c.mesh)) if given],
        argv, call, skip=cskip)


def _export_fe_config(section: dict, twin, sdir, base: Path, src: Path, where: str = "export-fe"
                      ) -> tuple[dict, list[str], list[str]]:
    """export-fe's config (validated by export-fe's model), the stages it reads and its outside inputs.

    Inputs default to the study's own results (fit-ogden's fit.json, register's
    registration.json and markers_ct.csv, the twin's indentation log).  On the twin, the
    indentor's beads (I1, I2 on a collar, ``synth.sequence.indentor_markers``) are its tracked
    markers, their midpoint ``indentor_marker_height_mm`` above the flat end; a twin
    indentor without beads gets the twin's rig geometry instead: the flat end's rest
    position and direction in the X-ray frame (cam1's camera frame, where ``track``
    triangulates) and the clock offset between the log and the X-ray frames, as a user would
    measure them on the rig (``indentor.pose_xray``, ``log.clock_offset_s``).
    """
    from .fe.config import ExportConfig

    d = copy.deepcopy(section)
    given = dict(d.get("inputs") or {})
    for k in ("fit", "registration", "markers_ct", "log", "markers3d"):
        if isinstance(given.get(k), str):
            given[k] = _abs(given[k], base)
    if isinstance(d.get("mesh"), str):
        d["mesh"] = _abs(d["mesh"], base)
    after, outside = ["fit-ogden", "register"], []
    inputs = {"fit": str(sdir["fit-ogden"] / "fit.json"),
              "registration": str(sdir["register"] / "registration.json"),
              "markers_ct": str(sdir["register"] / "markers_ct.csv")}
    if twin is not None:
        inputs["log"] = str(sdir["synth"] / "indentation_log.csv")
        after.append("synth")
    if twin is not None and d.get("indentor") is None and twin.sequence.indentor_markers:
        # the twin's indentor carries beads: track it like a user would (clock offset fitted)
        d["indentor"] = {"diameter_mm": twin.sequence.indentor_diameter_mm,
                         "markers": [f"I{k + 1}" for k in range(twin.sequence.indentor_markers)],
                         "tip_offset_mm": twin.sequence.indentor_marker_height_mm}
    indentor = d.get("indentor")
    if isinstance(indentor, dict) and indentor.get("markers"):
        inputs["markers3d"] = str(sdir["track"] / "markers3d.csv")
        after.append("track")
    for k in ("fit", "registration", "markers_ct", "log", "markers3d"):
        if k in given:
            inputs[k] = given[k]
            if given[k] is not None:
                outside.append(given[k])
    d["inputs"] = inputs
    if twin is not None and isinstance(d.get("checks", {}), dict):
        # the checks' expected speed and depth are the experiment's design: on a twin, the
        # twin's (export-fe's defaults are the sheep study's 12 mm/min and 4.8 mm; a twin
        # indenting 3 mm at 30 mm/min had stopped the study at export-fe, "check failed")
        checks = d.setdefault("checks", {})
        checks.setdefault("speed_mm_per_min", twin.sequence.speed_mm_per_min)
        checks.setdefault("depth_mm", twin.sequence.depth_mm)
    if twin is not None and indentor is None:
        pose, offset = _twin_indentor(twin)
        d["indentor"] = {"diameter_mm": twin.sequence.indentor_diameter_mm, "pose_xray": pose}
        d.setdefault("log", {})
        if isinstance(d["log"], dict):
            d["log"].setdefault("clock_offset_s", offset)
    cfg = _validate_prefixed(ExportConfig, d, src, where)
    return cfg.model_dump(mode="json"), after, outside


def _twin_indentor(twin) -> tuple[dict, float]:
    """The twin's indentor at rest in cam1's camera frame, and its log-to-X-ray clock offset."""
    import numpy as np

    from .synth.twin import Twin

    truth = Twin(twin).truth()
    cam = truth["cameras"]["cam1"]
    R, t = np.asarray(cam["R"], float), np.asarray(cam["t_mm"], float)
    ind = truth["sequence"]["indentor"]
    tip = R @ np.asarray(ind["tip_mm"][0], float) + t
    axis = R @ np.asarray(ind["direction"], float)
    return ({"tip_mm": [round(float(v), 9) for v in tip], "axis": [round(float(v), 12) for v in axis]},
            float(truth["log"]["clock_offset_s"]))


def to_stages(plans: list[StagePlan], study: StudyConfig) -> list:
    """The plans as :class:`bsipipe.study.Stage` objects for :func:`bsipipe.study.run_stages`."""
    from .study import Stage

    stages = []
    for p in plans:
        kc = key_config(p, study)
        if "key_argv" in p.extra:   # a stage without a command of its own: its key is its call
            kc["argv"] = [_tokenise(a, study) for a in p.extra["key_argv"]]
        stages.append(Stage(name=p.name, run=p.call, inputs=[Path(i) for i in p.inputs], after=p.after,
                            config=kc, code=STAGE_CODE[p.stage], dir=p.folder, skip=p.skip,
                            summary=partial(summarise, p.stage)))
    return stages


# --- key outputs for the summary table ---------------------------------------------------------

def summarise(stage: str, folder: Path) -> str:
    """One line of key outputs read from a stage's primary result."""
    d = json.loads((Path(folder) / PRIMARY[stage]).read_text())
    g = lambda v, f=".4g": "n/a" if v is None else format(v, f)          # noqa: E731
    if stage == "synth":
        c = d.get("counts", {})
        return f"{c.get('calibration_images', 0)} calibration images, {c.get('sequence_frames', 0)} frames"
    if stage == "calibrate":
        parts = [f"{n} RMS {g(v.get('rms_px'), '.3f')} px" for n, v in d.get("views", {}).items()]
        if d.get("stereo"):
            parts.append(f"stereo RMS {g(d['stereo'].get('rms_px'), '.3f')} px")
        return ", ".join(parts)
    if stage == "track":
        lp = d.get("loop") or {}
        fin = lp.get("final") or {}
        n = len(d.get("markers", {}))
        return (f"{n} markers, ray gap RMS {g(fin.get('ray_gap_rms_mm'), '.4f')} mm ({fin.get('model', '2-D')})"
                if fin else f"{n} markers")
    if stage == "register":
        return f"FRE RMS {g(d.get('fre_rms_mm'), '.4f')} mm, scale {g(d.get('scale'), '.6f')}"
    if stage == "fit-ogden":
        p = d.get("params", {})
        ps = ", ".join(f"{k} {g(v)}" for k, v in p.items() if isinstance(v, (int, float)))
        ps += "".join(f", g{i} {g(t.get('g'))} tau{i}_s {g(t.get('tau_s'))}"
                      for i, t in enumerate(p.get("prony") or [], start=1))
        m = d.get("metrics", {})
        return f"{d.get('model')}: {ps}; RMSE {g(m.get('rmse_n', m.get('rmse_pa')))}"
    if stage == "export-fe":
        return ", ".join(sorted(k for k in ("abaqus", "lsdyna", "febio") if (Path(folder) / k).is_dir()))
    if stage == "fe-solve":
        pk = d.get("peak_result") or {}
        fp = (d.get("indentor_force") or {}).get("peak") or {}
        force = (f"; indentor {g(fp.get('magnitude_n'), '.3g')} N" + (
            f" (log {g(fp.get('log_force_n'), '.3g')} N, x{g(fp.get('ratio'), '.2g')})" if "ratio" in fp else "")
                 if fp else "")
        return (f"CalculiX: {d.get('n_results', '?')} results; deepest at t = {g(pk.get('time'))}: "
                f"max |u| {g(pk.get('max_displacement_mm'), '.4f')} mm" + force)
    if stage == "compare":
        ts = d.get("time_series") or {}
        return (f"sigma {g(d.get('sigma_mm'), '.4f')} mm over {d.get('n_markers')} markers, frame {d.get('frame')}"
                + (f"; over the history {g(ts.get('sigma_mm'), '.4f')} mm, {ts.get('n_results')} FE results, "
                   f"{len(ts.get('per_marker') or {})} markers" if ts else ""))
    return ""
