"""The study: a graph of stages, each a command run on files, rerun only when something changed.

A stage owns one folder, ``<out>/<stage dir>/``, and is *done* when its stamp
``<stage dir>/.stage.json`` says ``"state": "done"``, records the same *key* as the stage
would have now, and lists exactly the result files the folder holds, with the same sha256.
The key is the sha256 of

- the stage's kind and validated config (paths under the study's base folder and its output
  folder written relative to them, so a moved checkout keeps its keys),
- the code version of the stage: the source of every bsipipe module its command imports,
  followed transitively (:func:`code_version`), and the versions of the libraries that
  compute (numpy, scipy, OpenCV, scikit-image, pandas, Python),
- the content (not the name or modification time) of every input file, and of every result
  file of the stages it reads from.

Running a stage first replaces its stamp by ``"state": "running"`` and empties its folder,
then calls the command, then hashes the results and writes the ``done`` stamp atomically.
A run killed at any point therefore leaves a stage without a matching ``done`` stamp, and the
next run redoes it from an empty folder: a half-written file never passes as done, and a
result file deleted or edited afterwards makes its stage run again.  Because a stage's key
holds its upstream results' content, a stage runs again when what it read has changed (a
JSON result carries the time of its run, so a redone stage normally changes it), and not
when its upstream stage was redone to the same bytes.

Stages whose upstream stages are done run concurrently in ``jobs`` worker processes
(:mod:`concurrent.futures`), so a study of many trials uses every core.  Each worker is a
fresh interpreter started with the study's environment (one BLAS and OpenCV thread), so a
stage gives the same bytes whichever way it is run.
"""

from __future__ import annotations

import ast
import concurrent.futures as cf
import datetime as _dt
import hashlib
import json
import logging
import os
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable

from . import __version__
from .errors import BsipipeError, InputError
from .provenance import atomic_write_bytes, dumps_json, sha256_file

log = logging.getLogger("bsipipe.study")

STAMP = ".stage.json"
#: Bumped when the key's recipe changes, so every stage of an older study reruns once.
KEY_SCHEMA = "bsipipe-study-key/1"

__all__ = ["Stage", "StageOutcome", "run_stages", "stage_key", "code_version", "module_closure",
           "read_stamp", "result_files", "summary_table", "STAMP"]


@dataclass
class Stage:
    """One node of the study graph.

    ``run(out_dir)`` writes the stage's results into ``out_dir`` (through a ResultSet); it
    must be picklable (a module-level function or a :func:`functools.partial` of one) for
    ``jobs > 1``.  ``inputs`` are the files or folders it reads from outside the study,
    ``after`` the names of the stages whose results it reads (their whole result folders
    enter the key), ``config`` the validated settings that change its result (JSON-able or a
    pydantic model), ``code`` the bsipipe modules that compute it (their transitive imports
    are hashed into the key).  ``dir`` is the stage's folder relative to the study's output
    folder (default ``name``).  A stage with ``skip`` set is not run and neither are the
    stages after it (the reason is reported).  ``summary(out_dir)`` returns the key outputs
    for the final table.
    """

    name: str
    run: Callable[[Path], Any]
    inputs: list[Path] = field(default_factory=list)
    after: list[str] = field(default_factory=list)
    config: Any = None
    code: tuple[str, ...] = ()
    dir: str | None = None
    skip: str | None = None
    summary: Callable[[Path], str] | None = None

    @property
    def folder(self) -> str:
        return self.dir or self.name


@dataclass
class StageOutcome:
    """What happened to one stage in a run: ``status`` is ``ran``, ``up to date``, ``failed``,
    ``skipped`` or ``not run`` (an upstream stage failed or was skipped)."""

    name: str
    status: str
    seconds: float = 0.0
    key: str | None = None
    detail: str = ""
    exit_code: int = 0
    traceback: str | None = None
    outputs: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"stage": self.name, "status": self.status, "seconds": round(self.seconds, 3), "key": self.key,
                "detail": self.detail, **({"exit_code": self.exit_code} if self.exit_code else {})}


# --- hashing ----------------------------------------------------------------------------------

_hash_cache: dict[tuple, str] = {}


def _sha(path: Path) -> str:
    """sha256 of a file, cached on (path, size, mtime, inode) for the life of the process."""
    st = path.stat()
    k = (str(path), st.st_size, st.st_mtime_ns, st.st_ino)
    h = _hash_cache.get(k)
    if h is None:
        h = _hash_cache[k] = sha256_file(path)
    return h


def _hidden(rel: Path) -> bool:
    return any(part.startswith(".") for part in rel.parts)


def result_files(folder: Path) -> dict[str, str]:
    """``{relative path: sha256}`` of the result files in a stage folder.

    Files and folders whose name starts with ``.`` (the stamp, a command's temporary files,
    a staging folder a killed run left behind) are not results.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return {}
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder)
        if p.is_file() and not _hidden(rel):
            out[rel.as_posix()] = _sha(p)
    return out


def _hash_input(h, p: Path) -> None:
    if p.is_dir():
        for rel, sha in result_files(p).items():
            h.update(f"  {rel} {sha}\n".encode())
    elif p.is_file():
        h.update(f"  {_sha(p)}\n".encode())
    else:
        h.update(b"  <missing>\n")


_PKG_ROOT = Path(__file__).resolve().parent


def _module_path(name: str) -> Path | None:
    """Source file of bsipipe module ``name`` (dotted, from ``bsipipe``), or None."""
    parts = name.split(".")
    if parts[0] != "bsipipe":
        return None
    base = _PKG_ROOT.joinpath(*parts[1:])
    for cand in (base.with_suffix(".py"), base / "__init__.py"):
        if cand.is_file():
            return cand
    return None


def _imports(name: str, path: Path, nodes: Iterable[ast.AST] | None = None) -> set[str]:
    """bsipipe modules imported anywhere in a module (top level and inside functions), or in ``nodes`` of it."""
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    found: set[str] = set()
    if nodes is None:
        nodes = [ast.parse(path.read_text(encoding="utf-8"), filename=str(path))]
    for node in (n for top in nodes for n in ast.walk(top)):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)   # `from pkg import submodule`
    return {m for m in found if m.split(".")[0] == "bsipipe"}


def _function_part(name: str, func: str) -> tuple[str, set[str]]:
    """Source of function ``func`` of module ``name`` with the module's top-level imports,
    and the bsipipe modules those import: the code of a stage that is one function of a
    module that also holds other things."""
    path = _module_path(name)
    if path is None:
        raise ValueError(f"no bsipipe module {name}")
    text = path.read_text(encoding="utf-8")
    tree = ast.parse(text, filename=str(path))
    tops = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    fn = [n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name == func]
    if not fn:
        raise ValueError(f"no function {func} in {name}")
    part = "\n".join(ast.get_source_segment(text, n) or "" for n in [*tops, fn[0]])
    return part, _imports(name, path, [*tops, fn[0]])


@lru_cache(maxsize=None)
def module_closure(modules: tuple[str, ...]) -> tuple[Path, ...]:
    """Source files of ``modules`` and every bsipipe module they import, transitively.

    Parent packages' ``__init__.py`` are included (importing ``a.b`` runs ``a/__init__``).
    An entry ``module:function`` stands for what that function imports (its own source
    is hashed by :func:`code_version`).
    """
    seen: dict[str, Path] = {}
    todo = []
    for m in modules:
        if ":" in m:
            mod, func = m.split(":", 1)
            todo.extend(_function_part(mod, func)[1])
            todo.extend(".".join(mod.split(".")[:i]) for i in range(1, len(mod.split("."))))
        else:
            todo.append(m)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_path(name)
        if path is None:
            continue
        seen[name] = path
        parts = name.split(".")
        todo.extend(".".join(parts[:i]) for i in range(1, len(parts)))
        todo.extend(_imports(name, path))
    return tuple(sorted(set(seen.values())))


def _package_data(files: Iterable[Path]) -> list[Path]:
    """Data files shipped beside the modules (``_data/`` and ``data/`` folders of their packages)."""
    out: set[Path] = set()
    for d in {p.parent for p in files}:
        for sub in ("_data", "data"):
            if (d / sub).is_dir():
                out.update(q for q in (d / sub).rglob("*") if q.is_file() and not _hidden(q.relative_to(d))
                           and q.suffix != ".pyc")
    return sorted(out)


def code_version(modules: Iterable[str]) -> str:
    """sha256 of the source of ``modules`` (or of one function, ``module:function``), of the
    bsipipe modules they import and of the package data beside them (e.g. tabulated no-slip
    factors).

    Editing any of them changes the key of the stages computed by them.
    """
    h = hashlib.sha256()
    modules = tuple(sorted(modules))
    for m in modules:
        if ":" in m:
            h.update(f"{m} {hashlib.sha256(_function_part(*m.split(':', 1))[0].encode()).hexdigest()}\n".encode())
    files = module_closure(modules)
    for p in [*files, *_package_data(files)]:
        h.update(f"{p.relative_to(_PKG_ROOT).as_posix()} {_sha(p)}\n".encode())
    return h.hexdigest()


@lru_cache(maxsize=1)
def _library_versions() -> str:
    from .provenance import library_versions
    return json.dumps(library_versions(), sort_keys=True)


def _config_json(config: Any) -> str:
    if hasattr(config, "model_dump"):
        config = config.model_dump(mode="json")
    return json.dumps(config, sort_keys=True, default=str)


def stage_key(stage: Stage, upstream: dict[str, dict[str, str]]) -> str:
    """The stage's key: kind, config, code version, library versions, input and upstream content.

    ``upstream`` maps each name in ``stage.after`` to its result files ``{rel: sha256}``.
    """
    h = hashlib.sha256()
    h.update(f"{KEY_SCHEMA}\nbsipipe {__version__}\n{_library_versions()}\n".encode())
    h.update(f"config {_config_json(stage.config)}\n".encode())
    h.update(f"code {code_version(stage.code)}\n".encode())
    for p in stage.inputs:
        h.update(b"input\n")
        _hash_input(h, Path(p))
    for a in stage.after:
        h.update(f"after {a}\n".encode())
        for rel, sha in sorted(upstream[a].items()):
            h.update(f"  {rel} {sha}\n".encode())
    return h.hexdigest()


# --- stamps -----------------------------------------------------------------------------------

def _stamp_path(folder: Path) -> Path:
    return folder / STAMP


def read_stamp(folder: Path) -> dict | None:
    """The stage folder's stamp, or None when it has none or it cannot be read."""
    try:
        d = json.loads(_stamp_path(folder).read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def _utc() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _mark_stale(folder: Path, why: str) -> bool:
    """A stage not run because an upstream stage failed keeps its folder (a user's earlier
    results are not deleted), but a ``done`` stamp there would pass its files off as this
    run's: the stamp becomes ``"state": "stale"`` with the reason.  The next run redoes the
    stage unless the upstream stage comes back to the very results it had read (its key
    holds them), and then stamps it done again.  True where a done stamp was so marked."""
    stamp = read_stamp(folder)
    if not stamp or stamp.get("state") != "done":
        return False
    atomic_write_bytes(_stamp_path(folder), dumps_json({**stamp, "state": "stale", "stale_since_utc": _utc(),
                                                         "stale_because": why}).encode())
    return True


def _is_done(folder: Path, key: str) -> tuple[bool, str]:
    """Whether the folder holds a complete run with ``key``; else why not."""
    stamp = read_stamp(folder)
    if stamp is None:
        return False, "never run" if not folder.exists() else "no complete run"
    if stamp.get("state") not in ("done", "stale"):
        return False, "the last run did not finish"
    if stamp.get("key") != key:
        return False, "inputs, config or code changed"
    now = result_files(folder)
    recorded = stamp.get("outputs") or {}
    if now != recorded:
        missing = sorted(set(recorded) - set(now))
        changed = sorted(k for k in set(recorded) & set(now) if recorded[k] != now[k])
        extra = sorted(set(now) - set(recorded))
        what = (f"{missing[0]} is missing" if missing else f"{changed[0]} was changed" if changed
                else f"{extra[0]} is not one of its results")
        return False, what
    return True, ""


def _stamp_temp(p: Path) -> bool:
    """Whether ``p`` is the temporary file of an unfinished write of the stage stamp."""
    return p.is_file() and p.name.startswith(f".{STAMP}.") and p.name.endswith(".tmp")


def _prepare_folder(folder: Path) -> None:
    """Mark the folder as running (the previous run stops counting as done), then empty it."""
    if folder.exists() and not folder.is_dir():
        raise InputError("exists and is not a folder; choose another study output folder", path=folder)
    # A run killed while writing its first stamp leaves only that write's temporary file
    # (``..stage.json.XXXX.tmp``, atomic_write_bytes): the folder is still the study's.
    if folder.is_dir() and read_stamp(folder) is None and any(not _stamp_temp(p) for p in folder.iterdir()):
        raise InputError("folder exists and was not written by bsipipe study (no .stage.json); "
                         "choose another study output folder", path=folder)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(_stamp_path(folder), dumps_json({"state": "running", "started_utc": _utc(),
                                                        "pid": os.getpid()}).encode())
    for p in folder.iterdir():
        if p.name == STAMP:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def execute_stage(name: str, run: Callable[[Path], Any], folder: Path, key: str) -> dict:
    """Run one stage into ``folder`` and stamp it; returns a picklable outcome dict.

    This is what a worker process runs.  Errors are returned, not raised, so that a failing
    stage of one trial does not stop the others.
    """
    t0 = time.perf_counter()
    folder = Path(folder)
    try:
        _prepare_folder(folder)
        run(folder)
        outputs = result_files(folder)
        atomic_write_bytes(_stamp_path(folder), dumps_json({
            "state": "done", "stage": name, "key": key, "bsipipe": __version__,
            "finished_utc": _utc(), "seconds": round(time.perf_counter() - t0, 3), "outputs": outputs}).encode())
        return {"ok": True, "seconds": time.perf_counter() - t0, "outputs": outputs}
    except BsipipeError as e:
        return {"ok": False, "seconds": time.perf_counter() - t0, "exit_code": e.exit_code, "message": str(e),
                "traceback": traceback.format_exc()}
    except MemoryError:
        return {"ok": False, "seconds": time.perf_counter() - t0, "exit_code": 1, "message": "out of memory",
                "traceback": traceback.format_exc()}
    except Exception as e:  # an unexpected failure of one stage is that stage's failure (exit 1)
        return {"ok": False, "seconds": time.perf_counter() - t0, "exit_code": 1,
                "message": f"internal error: {type(e).__name__}: {e}", "traceback": traceback.format_exc()}


# --- the scheduler ----------------------------------------------------------------------------

def _order(stages: list[Stage]) -> list[Stage]:
    """Stages in an order where each comes after those it reads from; rejects cycles and unknown names."""
    by_name = {s.name: s for s in stages}
    if len(by_name) != len(stages):
        raise ValueError("two study stages have the same name")
    order: list[Stage] = []
    state: dict[str, int] = {}

    def visit(s: Stage, trail: tuple[str, ...]) -> None:
        if state.get(s.name) == 2:
            return
        if state.get(s.name) == 1:
            raise ValueError(f"study stages form a cycle: {' -> '.join(trail + (s.name,))}")
        state[s.name] = 1
        for a in s.after:
            if a not in by_name:
                raise ValueError(f"stage {s.name} reads from unknown stage {a}")
            visit(by_name[a], trail + (s.name,))
        state[s.name] = 2
        order.append(s)

    for s in stages:
        visit(s, ())
    return order


def run_stages(stages: list[Stage], out: Path, *, force: bool = False, only: Iterable[str] | None = None,
               jobs: int = 1, echo: Callable[[str], None] = print, isolate: bool = True,
               env: dict[str, str] | None = None) -> list[StageOutcome]:
    """Run the stages that are not up to date, each after those it reads from.

    ``force`` reruns every selected stage.  ``only`` (stage names) runs just those stages and
    takes the others' result folders as they are (they must exist): a cluster job that runs
    one stage, or a user redoing one.  ``jobs`` worker processes run independent stages at
    once.  With ``isolate`` (default) every stage runs in a fresh worker process (``spawn``)
    whose environment is this process's plus ``env``: thread counts of BLAS and OpenCV, which
    must be set before those libraries load, fix the order of floating-point sums and so the
    bytes of a result.  ``isolate=False`` with ``jobs=1`` runs the stages in this process.
    Returns one :class:`StageOutcome` per selected stage, in graph order.
    """
    out = Path(out)
    order = _order(stages)
    by_name = {s.name: s for s in order}
    selected = set(by_name) if only is None else set(only)
    unknown = selected - set(by_name)
    if unknown:
        raise InputError(f"no stage named {sorted(unknown)[0]!r}; stages: {', '.join(by_name)}")

    results: dict[str, dict[str, str]] = {}      # finished stage -> its result files
    outcomes: dict[str, StageOutcome] = {}
    blocked: dict[str, str] = {}                  # stage -> why it cannot run
    pending = [s for s in order if s.name in selected]
    running: dict[cf.Future, tuple[Stage, str, float]] = {}
    checked: dict[str, tuple[str, bool, str]] = {}   # stage -> (key, done, why not), once its inputs are final

    def upstream_files(s: Stage) -> dict[str, dict[str, str]] | None:
        ups = {}
        for a in s.after:
            if a in results:
                ups[a] = results[a]
            elif a in selected:
                return None                       # not finished yet (or failed)
            else:                                 # not part of this run: its folder as it is
                folder = out / by_name[a].folder
                files = result_files(folder)
                if not files:
                    raise InputError(f"stage {s.name} reads the results of stage {a}, which has none; "
                                     f"run stage {a} first", path=folder)
                ups[a] = files
        return ups

    def finish(s: Stage, o: StageOutcome) -> None:
        outcomes[s.name] = o
        if o.status in ("ran", "up to date"):
            results[s.name] = o.outputs
        else:
            for t in order:
                if t.name in selected and t.name not in outcomes and _depends_on(t, s.name, by_name):
                    blocked.setdefault(t.name, f"{s.name} {o.status}")

    def summary(s: Stage) -> str:
        if s.summary is None:
            return ""
        try:
            return s.summary(out / s.folder)
        except Exception as e:  # a summary that cannot be read is not a failed stage
            return f"(no summary: {type(e).__name__})"

    pool = None
    saved_env = {k: os.environ.get(k) for k in (env or {})}
    if isolate or jobs > 1:
        import multiprocessing

        os.environ.update(env or {})      # read by each worker when it starts
        pool = cf.ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=_die_with_parent)
    try:
        while pending or running:
            progressed = False
            for s in list(pending):
                if s.skip:
                    pending.remove(s)
                    finish(s, StageOutcome(s.name, "skipped", detail=s.skip))
                    echo(f"[study] {s.name}: skipped: {s.skip}")
                    progressed = True
                    continue
                if s.name in blocked:
                    pending.remove(s)
                    finish(s, StageOutcome(s.name, "not run", detail=blocked[s.name]))
                    stale = _mark_stale(out / s.folder, blocked[s.name])
                    echo(f"[study] {s.name}: not run ({blocked[s.name]})"
                         + ("; its folder holds an earlier run's results, stamped stale" if stale else ""))
                    progressed = True
                    continue
                ups = upstream_files(s)
                if ups is None:
                    continue
                if s.name not in checked:
                    key = stage_key(s, ups)
                    checked[s.name] = (key, *_is_done(out / s.folder, key))
                key, done, why = checked[s.name]
                folder = out / s.folder
                if done and not force:
                    pending.remove(s)
                    progressed = True
                    stamp = read_stamp(folder)
                    if stamp.get("state") == "stale":
                        # marked when an upstream stage failed; that stage is back to the same
                        # results, so these are this run's again
                        stamp = {k: v for k, v in stamp.items() if not k.startswith("stale_")}
                        atomic_write_bytes(_stamp_path(folder), dumps_json({**stamp, "state": "done"}).encode())
                    o = StageOutcome(s.name, "up to date", key=key, outputs=stamp["outputs"])
                    o.detail = summary(s)
                    finish(s, o)
                    echo(f"[study] {s.name}: up to date" + (f" ({o.detail})" if o.detail else ""))
                    continue
                if pool is not None and len(running) >= jobs:
                    continue                      # every worker is busy: it waits, and is reported when it starts
                pending.remove(s)
                progressed = True
                echo(f"[study] {s.name}: running ({'--force' if done else why})")
                if pool is None:
                    _collect(s, key, execute_stage(s.name, s.run, folder, key), finish, summary, echo)
                else:
                    fut = pool.submit(execute_stage, s.name, s.run, folder, key)
                    running[fut] = (s, key, time.perf_counter())
            if running and not progressed:
                finished, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
                for fut in finished:
                    s, key, _t0 = running.pop(fut)
                    try:
                        res = fut.result()
                    except Exception as e:  # the worker process died (killed, out of memory)
                        res = {"ok": False, "seconds": time.perf_counter() - _t0, "exit_code": 1,
                               "message": f"worker process failed: {type(e).__name__}: {e}", "traceback": None}
                    _collect(s, key, res, finish, summary, echo)
            elif not running and not progressed and pending:  # pragma: no cover - guarded by _order
                raise RuntimeError(f"study scheduler stalled on {[s.name for s in pending]}")
    except BaseException:
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
            pool = None
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return [outcomes[s.name] for s in order if s.name in outcomes]


def _quiet_interrupt(signum, frame) -> None:  # pragma: no cover - runs in a worker on Ctrl-C
    """A worker's SIGINT (Ctrl-C reaches the whole process group): end at once, as a kill
    would (the stage is redone by the next run), without a traceback of its own; the study
    process reports the interruption."""
    os._exit(128 + int(signum))


def _die_with_parent() -> None:
    """Worker initializer: end with the study process (Linux), so that a study killed with
    SIGKILL leaves no worker finishing a stage behind the next run's back; on Ctrl-C end
    quietly (:func:`_quiet_interrupt`)."""
    import signal

    signal.signal(signal.SIGINT, _quiet_interrupt)
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))   # PR_SET_PDEATHSIG
        except (OSError, AttributeError):  # pragma: no cover - no prctl: the worker may outlive a killed study
            pass
        import multiprocessing

        parent = multiprocessing.parent_process()
        if parent is not None and os.getppid() != parent.pid:  # the study died before the request took effect
            os._exit(1)


def _depends_on(t: Stage, name: str, by_name: dict[str, Stage]) -> bool:
    todo, seen = list(t.after), set()
    while todo:
        a = todo.pop()
        if a == name:
            return True
        if a not in seen:
            seen.add(a)
            todo.extend(by_name[a].after)
    return False


def _collect(s: Stage, key: str, res: dict, finish, summary, echo) -> None:
    if res["ok"]:
        o = StageOutcome(s.name, "ran", seconds=res["seconds"], key=key, outputs=res["outputs"])
        o.detail = summary(s)
        echo(f"[study] {s.name}: done in {o.seconds:.1f} s" + (f" ({o.detail})" if o.detail else ""))
    else:
        o = StageOutcome(s.name, "failed", seconds=res["seconds"], key=key, detail=res["message"],
                         exit_code=res["exit_code"], traceback=res.get("traceback"))
        echo(f"[study] {s.name}: FAILED after {o.seconds:.1f} s: {res['message']}")
    finish(s, o)


def summary_table(outcomes: list[StageOutcome]) -> str:
    """The final table: stage, status, time, key outputs."""
    rows = [("stage", "status", "time", "key outputs")]
    for o in outcomes:
        t = f"{o.seconds:.1f} s" if o.status in ("ran", "failed") else "-"
        rows.append((o.name, o.status, t, o.detail))
    w = [max(len(r[i]) for r in rows) for i in range(3)]
    lines = [f"{r[0]:<{w[0]}}  {r[1]:<{w[1]}}  {r[2]:>{w[2]}}  {r[3]}".rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * x for x in w) + "  " + "-" * 11)
    return "\n".join(lines)
