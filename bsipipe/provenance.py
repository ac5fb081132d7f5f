"""Provenance blocks, content hashes and atomic, all-or-nothing result writing."""

from __future__ import annotations

import datetime as _dt
import hashlib
import io
import json
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from . import __version__


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, read in chunks (large image stacks stay out of memory)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def _version(mod: str) -> str | None:
    try:
        from importlib.metadata import version
        return version(mod)
    except Exception:  # a package that is not installed has no version to report
        return None


def library_versions() -> dict[str, str | None]:
    """The versions a result was computed with, and which sub-pixel fits marker measurements
    run with here: the compiled kernels (``bsipipe.imaging._kernels``, with their version) or
    NumPy's (the same values to 1e-9 px).  Every command says it, whatever it measured and
    whatever ran before it in the process: a stage rerun alone writes what the whole study
    wrote (:mod:`bsipipe.imaging.compiled`, a few microseconds: the detector is not loaded)."""
    import cv2

    from .imaging.compiled import subpixel_fits
    return {
        "bsipipe": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": _version("scipy"),
        "opencv": cv2.__version__,
        "scikit-image": _version("scikit-image"),
        "pandas": _version("pandas"),
        "subpixel_fits": subpixel_fits(),
    }


def input_hashes(paths: Iterable[str | os.PathLike], known: dict[str, str] | None = None) -> dict[str, str]:
    """sha256 of every input file; a folder contributes each file below it.  ``known``: hashes
    already taken (e.g. by :func:`bsipipe.io.images.iter_frames` from the bytes it decoded),
    keyed by ``str(path)``; the other files are read here."""
    known = known or {}
    out: dict[str, str] = {}
    for p in paths:
        p = Path(p)
        files = sorted(x for x in p.rglob("*") if x.is_file()) if p.is_dir() else [p] if p.is_file() else []
        for q in files:
            out[str(q)] = known.get(str(q)) or sha256_file(q)
    return out


def provenance(config: Any, inputs: Iterable[str | os.PathLike], command: str | None = None,
               known_hashes: dict[str, str] | None = None) -> dict:
    """The ``provenance`` block every JSON result carries (CONTRACTS.md); ``known_hashes`` as
    in :func:`input_hashes`."""
    if hasattr(config, "model_dump"):
        config = config.model_dump(mode="json")
    vers = library_versions()
    return {
        "bsipipe_version": vers["bsipipe"],
        "command": command,
        "config": config,
        "inputs_sha256": input_hashes(inputs, known_hashes),
        "versions": vers,
        "utc_time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def _json_default(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _clean_nan(o: Any):
    """JSON has no NaN/inf: write them as null so every reader can load the file."""
    if isinstance(o, float) and not np.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _clean_nan(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean_nan(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean_nan(o.tolist())
    if isinstance(o, np.floating):
        return _clean_nan(float(o))
    return o


def dumps_json(obj: Any) -> str:
    return json.dumps(_clean_nan(obj), indent=2, default=_json_default, allow_nan=False) + "\n"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_temporary(path: str | os.PathLike, data) -> Path:
    """Write ``data`` in full to a new temporary file beside ``path`` (fsync'd, with the
    permissions an ordinary file would get) and return its path, for the caller to rename
    over ``path``; nothing is left on failure.  ``data`` is bytes, or a binary file object
    read from its start (copied in blocks)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if isinstance(data, (bytes, bytearray, memoryview)):
                f.write(data)
            else:
                data.seek(0)
                shutil.copyfileobj(data, f, 1 << 20)
            f.flush()
            os.fsync(f.fileno())
        # mkstemp creates 0600; a result file gets the permissions an ordinary file would.
        os.chmod(tmp, 0o666 & ~_umask())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def atomic_write_bytes(path: str | os.PathLike, data) -> None:
    """Write to a temporary file in the same folder, fsync, then rename over ``path``.

    ``data`` is bytes, or a binary file object read from its start (copied in blocks)."""
    tmp = write_temporary(path, data)
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check_output_folder(out: str | os.PathLike) -> None:
    """Refuse, before any work, an output folder that cannot be made: the path or one of its
    parents is a file, or the nearest existing folder is not writable or takes no new folder
    (an InputError naming
    it; found only when the results are written, after the work, it had been an internal
    error)."""
    from .errors import InputError
    p = Path(out).absolute()
    if p.exists() and not p.is_dir():
        raise InputError("the output folder is a file", path=p)
    # the folder itself where it exists (a read-only mount given as -o had run the whole fit
    # and then failed to write, exit 1), else its nearest existing parent
    for parent in (p, *p.parents):
        if parent.exists():
            what = f"cannot write in the output folder {p}" if parent == p else f"cannot make the output folder {p}"
            if not parent.is_dir():
                raise InputError(f"{what}: {parent} is a file", path=parent)
            if not os.access(parent, os.W_OK | os.X_OK):
                raise InputError(f"{what}: {parent} is not writable", path=parent)
            # the permission bits can say yes where the file system says no (/proc, a read-only
            # mount, a full disk): a folder is made there and removed again
            try:
                os.rmdir(tempfile.mkdtemp(prefix=".bsipipe-probe-", dir=parent))
            except OSError as e:
                raise InputError(f"{what}: {e.strerror or e}", path=parent) from None
            return


class ResultSet:
    """Collects a command's result files and writes them all-or-nothing.

    Nothing touches ``out`` until :meth:`commit`.  Then every file is first written in full
    to a temporary file beside its target (a failure there, a full disk, removes them all
    and leaves an earlier run's results as they were); only then is the earlier run's
    primary result removed, the files it wrote that this run does not (``outputs``, names
    or glob patterns relative to ``out``) with it, and each temporary file renamed over its
    target, the JSON result named ``primary`` (the file that says a run is complete, e.g.
    ``fit.json``) last.  A run killed part-way so never leaves a primary result next to
    stale or missing companions.  (Renaming each file as it was written had left, on a
    disk full at the second run's ``material.k``, the first run's ``fit.json`` beside the
    second run's ``material.inp``.)

    >>> rs = ResultSet("unused", primary="a.json")
    >>> rs.add_text("b.txt", "x"); sorted(rs.files)
    ['b.txt']
    """

    def __init__(self, out: str | os.PathLike, primary: str | None = None, outputs: Sequence[str] = ()):
        self.out = Path(out)
        self.primary = primary
        # every file the command can write: one an earlier run left that this run does not
        # write is removed at commit (a 2-D run into a folder that holds a 3-D run's
        # markers3d.csv must not leave it beside its own results; calibrate's per-view
        # mayacam_<view>.txt of another view beside a calibration.json without it)
        self.outputs = tuple(outputs)
        # bytes, or (for tables) an anonymous temporary file: a long sequence's CSV tables
        # then wait on disk, not in memory (unlinked at creation, so a kill leaves nothing)
        self.files: dict[str, Any] = {}

    def add_bytes(self, name: str, data: bytes) -> None:
        self.files[name] = data

    def add_text(self, name: str, text: str) -> None:
        self.files[name] = text.encode("utf-8")

    def add_json(self, name: str, obj: Any) -> None:
        self.add_text(name, dumps_json(obj))

    def add_csv(self, name: str, df, **kw) -> None:
        kw.setdefault("index", False)
        kw.setdefault("lineterminator", "\n")
        from .io.csvtable import write_csv
        f = tempfile.TemporaryFile()
        write_csv(df, f, encoding="utf-8", **kw)
        self.files[name] = f

    def add_figure(self, name: str, fig, dpi: int = 120, tight: bool = True) -> None:
        """Render ``fig`` (then closed).  ``tight``: crop to the drawn content
        (``bbox_inches="tight"``, which draws the figure twice); a figure laid out with fixed
        margins that fit passes False and is drawn once."""
        buf = io.BytesIO()
        fig.savefig(buf, format=Path(name).suffix.lstrip(".") or "png", dpi=dpi,
                    bbox_inches="tight" if tight else None)
        if "matplotlib.pyplot" in sys.modules:      # a pyplot figure is closed (ours are not pyplot's)
            sys.modules["matplotlib.pyplot"].close(fig)
        self.add_bytes(name, buf.getvalue())

    def _stale(self) -> list[Path]:
        """The files in ``out`` an earlier run wrote (``outputs``) that this run does not."""
        out = []
        for pat in self.outputs:                     # a plain name globs to itself
            for p in self.out.glob(pat):
                if p.is_file() and p.relative_to(self.out).as_posix() not in self.files:
                    out.append(p)
        return out

    def commit(self) -> list[Path]:
        self.out.mkdir(parents=True, exist_ok=True)
        names = sorted(self.files, key=lambda n: (n == self.primary, n))
        staged: list[tuple[str, Path]] = []
        try:
            for n in names:                           # every file in full first ...
                staged.append((n, write_temporary(self.out / n, self.files[n])))
            if self.primary is not None:              # ... then the earlier run's primary goes
                (self.out / self.primary).unlink(missing_ok=True)
            for p in self._stale():
                p.unlink()
            for n, tmp in staged:
                os.replace(tmp, self.out / n)
        except BaseException:
            for _, tmp in staged:                     # a renamed one is gone already
                tmp.unlink(missing_ok=True)
            raise
        finally:
            for f in self.files.values():
                if hasattr(f, "close"):
                    f.close()
        return [self.out / n for n in names]
