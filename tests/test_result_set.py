"""``ResultSet.commit``: a command's result files written all-or-nothing.

A failure while the files are written (a disk full at the second run's ``material.k``) had
left the first run's ``fit.json`` beside the second run's ``material.inp`` and the first
run's ``material.k``: the renames came file by file.  Every file is now written in full
before anything is renamed, and the earlier run's primary result goes first; files of an
earlier run that this one does not write (``outputs``, names or glob patterns) go too.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bsipipe import provenance
from bsipipe.provenance import ResultSet


def _run(out, tag: str, *, cards=("material.inp", "material.k"), outputs=()):
    rs = ResultSet(out, primary="fit.json", outputs=outputs)
    for c in cards:
        rs.add_text(c, f"{tag} {c}\n")
    rs.add_json("fit.json", {"run": tag})
    return rs


def _contents(out):
    return {p.name: p.read_text() for p in sorted(out.iterdir())}


def test_a_failure_while_writing_leaves_the_earlier_run_whole(tmp_path, monkeypatch):
    out = tmp_path / "fit"
    _run(out, "first").commit()
    before = _contents(out)
    real = provenance.write_temporary

    def disk_full(path, data):
        if path.name == "material.k":
            raise OSError(28, "No space left on device")
        return real(path, data)
    monkeypatch.setattr(provenance, "write_temporary", disk_full)
    with pytest.raises(OSError):
        _run(out, "second").commit()
    assert _contents(out) == before          # the first run, whole; no temporary file left
    monkeypatch.setattr(provenance, "write_temporary", real)
    _run(out, "second").commit()
    assert json.loads((out / "fit.json").read_text()) == {"run": "second"}
    assert all(v.startswith("second") for k, v in _contents(out).items() if k != "fit.json")


def test_a_failure_while_renaming_leaves_no_primary_result(tmp_path, monkeypatch):
    """Killed between the renames: the earlier run's fit.json is already gone, so nothing in
    the folder looks like a complete run."""
    out = tmp_path / "fit"
    _run(out, "first").commit()
    import os
    real = os.replace
    calls = []

    def killed(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(src, dst)
    monkeypatch.setattr(provenance.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        _run(out, "second").commit()
    monkeypatch.setattr(provenance.os, "replace", real)
    left = _contents(out)
    assert "fit.json" not in left and not any(k.startswith(".") for k in left), left


def test_an_earlier_runs_files_this_run_does_not_write_are_removed(tmp_path):
    """calibrate --view left, then --view right into one folder: mayacam_left.txt had stayed
    beside a calibration.json without left."""
    out = tmp_path / "cal"
    pats = ("mayacam_*.txt", "residuals_*.png")
    _run(out, "first", cards=("mayacam_left.txt", "residuals_left.png"), outputs=pats).commit()
    (out / "notes.txt").write_text("mine\n")
    _run(out, "second", cards=("mayacam_right.txt", "residuals_right.png"), outputs=pats).commit()
    assert sorted(_contents(out)) == ["fit.json", "mayacam_right.txt", "notes.txt", "residuals_right.png"]


def test_an_existing_output_folder_the_file_system_will_not_write_is_refused_first(tmp_path, monkeypatch):
    """-o naming an existing folder on a read-only mount: the whole fit had run and then
    failed to write (internal error, exit 1); the folder itself is now tried before any work
    (its parents had been, for a folder still to make)."""
    import errno
    import tempfile

    from bsipipe.errors import InputError
    from bsipipe.provenance import check_output_folder
    ro = tmp_path / "ro"
    ro.mkdir()
    real = tempfile.mkdtemp

    def mkdtemp(*a, dir=None, **k):
        if dir is not None and Path(dir) == ro:
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*a, dir=dir, **k)
    monkeypatch.setattr(tempfile, "mkdtemp", mkdtemp)
    with pytest.raises(InputError, match="cannot write in the output folder.*Read-only file system"):
        check_output_folder(ro)
    check_output_folder(tmp_path / "other")           # a writable parent: fine
