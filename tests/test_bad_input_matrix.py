"""The bad-input matrix (issue 7, item 1): every reader and command, refused cleanly.

Each case feeds one command a broken input through the real command line (click's
``CliRunner`` with ``catch_exceptions=False``; a few through a real ``bsipipe`` process) and
checks the contract (CONTRACTS.md, General):

* the exit status: 2 for bad usage, an invalid config or an unreadable/invalid input, 1 for a
  processing failure on valid input;
* exactly one ``error:`` message on stderr naming the file (the option or the config key
  where no file is involved) and, where it applies, the line, frame or key;
* no Python traceback and no ``internal error`` (an exception no reader anticipated);
* no result file written or changed: the output folder is pre-populated with a complete
  result of a previous good run of the same command and must be byte-identical afterwards
  (no new, changed, removed or temporary file), and a fresh output folder must stay empty.

The good inputs and the previous good results come from one small chain run once per module
(``bsipipe synth`` of a 256-px twin, ``calibrate``, ``track``, ``register``, ``fit-ogden``,
``export-fe``, ``compare``).  ``test_matrix_summary`` prints the matrix (``pytest -s``) and
writes it to its tmp folder as ``bad_input_matrix.txt``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from bsipipe.cli import cli

ROOT = Path(__file__).resolve().parents[1]
LOGS = ROOT / "tests" / "data" / "logs"
GOOD_LOG = ROOT / "sample_data" / "logs" / "sheep_s3_100mm_min.csv"
REFS = ["R1", "R2", "R3", "R4"]
EXE = Path(sys.executable).parent / "bsipipe"

# The twin of configs/study_tiny.yaml (256 px frames, 4 + 3 calibration views, 8 frames).
SYNTH_TINY = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs" / "study_tiny.yaml").read_text())["synth"]


# --------------------------------------------------------------------------- the good chain


def _invoke(args) -> tuple[int, str, str, BaseException | None]:
    """Run the CLI in-process; an exception that escapes the command is returned, not raised."""
    runner = CliRunner()
    try:
        r = runner.invoke(cli, [str(a) for a in args], catch_exceptions=False)
    except BaseException as e:  # noqa: BLE001 - the matrix records it as a traceback
        return -1, "", traceback.format_exc(), e
    return r.exit_code, r.stdout, r.stderr, None


def _ok(args):
    code, out, err, exc = _invoke(args)
    assert exc is None and code == 0, f"{args}: exit {code}\n{out}\n{err}"


def _write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _brick_mesh(folder: Path, lo, hi) -> tuple[Path, Path]:
    """One C3D8 brick spanning ``lo``..``hi`` (CT frame) and a linear displacement field on it."""
    from bsipipe.io.abaqus import abaqus_elements, abaqus_nodes

    (x0, y0, z0), (x1, y1, z1) = lo, hi
    coords = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                       [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
    ids = np.arange(1, 9)
    mesh = folder / "mesh.inp"
    mesh.write_text(abaqus_nodes(ids, coords, nset="NALL") + abaqus_elements("C3D8", [1], ids[None, :], elset="EALL"))
    u = 0.01 * (coords - coords.mean(axis=0))
    disp = folder / "u.csv"
    pd.DataFrame({"node": ids, "ux_mm": u[:, 0], "uy_mm": u[:, 1], "uz_mm": u[:, 2]}).to_csv(disp, index=False)
    return mesh, disp


@dataclass
class Base:
    """Good inputs and good results of every command."""

    root: Path
    synth: Path
    calibrate: Path
    track: Path
    register: Path
    fit: Path
    export: Path
    compare: Path
    configs: dict[str, Path]
    mesh: Path
    disp: Path
    good: dict[str, Path] = field(default_factory=dict)   # command -> folder of its previous good result


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Base:
    root = tmp_path_factory.mktemp("matrix_base")
    cfg = root / "configs"
    cfg.mkdir()
    configs = {}
    configs["synth"] = _write_yaml(cfg / "synth.yaml", SYNTH_TINY)
    _ok(["synth", configs["synth"], "-o", root / "synth"])
    s = root / "synth"
    configs["calibrate"] = _write_yaml(cfg / "calibrate.yaml", {
        "pattern": "asymmetric-circles", "grid": "4x9", "spacing_mm": 3.0, "loop": False,
        "views": {"cam1": str(s / "calibration/cam1"), "cam2": str(s / "calibration/cam2")},
        "stereo": {"cam1": str(s / "calibration/stereo/cam1"), "cam2": str(s / "calibration/stereo/cam2")}})
    _ok(["calibrate", configs["calibrate"], "-o", root / "calibrate"])
    configs["track"] = _write_yaml(cfg / "track.yaml", {
        "views": {"cam1": str(s / "sequence/cam1"), "cam2": str(s / "sequence/cam2")},
        "calibration": str(root / "calibrate/calibration.json"), "seeds": str(s / "seeds.csv"), "fps": 0.5})
    _ok(["track", configs["track"], "-o", root / "track"])
    _ok(["register", "--ct", s / "ct_markers.fcsv", "--xray", root / "track/markers3d.csv",
         *[a for r in REFS for a in ("--reference", r)], "--perturbation-draws", "50", "-o", root / "register"])
    configs["fit"] = _write_yaml(cfg / "fit.yaml", {"loop": False, "bootstrap": 0})
    _ok(["fit-ogden", GOOD_LOG, "--config", configs["fit"], "-o", root / "fit"])
    export = yaml.safe_load((ROOT / "configs" / "study_tiny.yaml").read_text())["export-fe"]
    truth = json.loads((s / "truth.json").read_text())
    configs["export"] = _write_yaml(cfg / "export.yaml", {
        "inputs": {"fit": str(root / "fit/fit.json"), "registration": str(root / "register/registration.json"),
                   "markers_ct": str(root / "register/markers_ct.csv"), "log": str(s / "indentation_log.csv")},
        "indentor": {"diameter_mm": 5.0, "pose_xray": _indentor_pose(truth)},
        "log": {"clock_offset_s": float(truth["log"]["clock_offset_s"])}, **export})
    _ok(["export-fe", configs["export"], "-o", root / "export"])
    mct = pd.read_csv(root / "register/markers_ct.csv")
    p0 = mct[["x_mm", "y_mm", "z_mm"]].to_numpy() - mct[["dx_mm", "dy_mm", "dz_mm"]].to_numpy()
    p0 = p0[np.all(np.isfinite(p0), axis=1)]
    mesh, disp = _brick_mesh(cfg, p0.min(axis=0) - 5.0, p0.max(axis=0) + 5.0)
    _ok(["compare", "--fe-displacements", disp, "--mesh", mesh, "--markers", root / "register/markers_ct.csv",
         "-o", root / "compare"])
    b = Base(root, s, root / "calibrate", root / "track", root / "register", root / "fit", root / "export",
             root / "compare", configs, mesh, disp)
    b.good = {"synth": b.synth, "calibrate": b.calibrate, "track": b.track, "register": b.register,
              "fit-ogden": b.fit, "export-fe": b.export, "compare": b.compare, "study": root}
    return b


def _indentor_pose(truth: dict) -> dict:
    """The indentor at rest in cam1's camera frame (the X-ray frame of ``track``), from the twin's truth."""
    cam = truth["cameras"]["cam1"]
    R, t = np.asarray(cam["R"], float), np.asarray(cam["t_mm"], float)
    ind = truth["sequence"]["indentor"]
    return {"tip_mm": (R @ np.asarray(ind["tip_mm"][0], float) + t).tolist(),
            "axis": (R @ np.asarray(ind["direction"], float)).tolist()}



# --------------------------------------------------------------------------- making bad inputs


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


def _put(path: Path, lines) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _copy_dir(src: Path, dst: Path, n: int | None = None) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.iterdir())[:n]:
        shutil.copy2(f, dst / f.name)
    return dst


def _good_log_edit(d: Path, name: str, edit: Callable[[list[str]], None]) -> Path:
    lines = _lines(GOOD_LOG)
    edit(lines)
    return _put(d / name, lines)


def _no_contact(lines):
    """Load that never rises: the platen never reaches the sample (noise only)."""
    rng = np.random.default_rng(5)
    for i in range(15, len(lines)):
        t, x, _ = [c.strip('"') for c in lines[i].split(",")]
        lines[i] = f'"{t}","{x}","{rng.normal(0, 0.001):.6f}"'


def _set_line(k: int, text: str):
    def edit(lines):
        lines[k - 1] = text
    return edit


def _edits(*edits):
    def edit(lines):
        for e in edits:
            e(lines)
    return edit


FIT = ["fit-ogden", "--diameter-mm", "18", "--height-mm", "12"]


def _fit_log(name: str, line: int | None, code: int = 2):
    """fit-ogden on one of tests/data/logs/bad_*.csv (the line each error is on: _make_fixtures.py)."""
    def build(b, d):
        return [*FIT, LOGS / name], LOGS / name, None if line is None else f"line {line}"
    return build


def _calib_args(folder: Path, grid: str = "4x9") -> list:
    return ["calibrate", "--view", f"cam1={folder}", "--pattern", "asymmetric-circles", "--grid", grid,
            "--spacing-mm", "3", "--no-loop"]


def _calib_folder(b: Base, d: Path, n: int | None = None) -> Path:
    return _copy_dir(b.synth / "calibration" / "cam1", d / "cam1", n)


def _png_16bit(src: Path, dst: Path) -> None:
    import cv2
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8
    cv2.imwrite(str(dst), img.astype(np.uint16) * 257)


def _png_resized(src: Path, dst: Path) -> None:
    import cv2
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(dst), img[:200, :220])


def _truncate(path: Path, keep: float = 0.4) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _dicom_from_png(src: Path, dst: Path) -> None:
    import cv2
    import pydicom
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.12.1"   # X-ray angiographic image
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(dst), {}, file_meta=meta, preamble=b"\0" * 128)
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Rows, ds.Columns = img.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = 8
    ds.HighBit, ds.PixelRepresentation = 7, 0
    ds.PixelData = img.tobytes()
    ds.save_as(str(dst), enforce_file_format=True)
    assert pydicom.dcmread(str(dst)).pixel_array.shape == img.shape


def _zero_frame_video(path: Path) -> Path:
    import cv2
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (256, 256), False)
    w.release()
    assert path.exists()
    return path


def _track_args(b: Base, *, cam1=None, cam2=None, seeds=None, calibration=None) -> list:
    return ["track", "--view", f"cam1={cam1 or b.synth / 'sequence/cam1'}",
            "--view", f"cam2={cam2 or b.synth / 'sequence/cam2'}",
            "--calibration", calibration or b.calibrate / "calibration.json",
            "--seeds", seeds or b.synth / "seeds.csv", "--fps", "0.5"]


def _seeds_edit(b: Base, d: Path, edit) -> Path:
    df = pd.read_csv(b.synth / "seeds.csv")
    edit(df)
    df.to_csv(d / "seeds.csv", index=False)
    return d / "seeds.csv"


def _register_args(b: Base, *, ct=None, xray=None, refs=REFS) -> list:
    return ["register", "--ct", ct or b.synth / "ct_markers.fcsv", "--xray", xray or b.track / "markers3d.csv",
            *[a for r in refs for a in ("--reference", r)], "--perturbation-draws", "20"]


def _compare_args(b: Base, *, disp=None, mesh=None, markers=None) -> list:
    return ["compare", "--fe-displacements", disp or b.disp, "--mesh", mesh or b.mesh,
            "--markers", markers or b.register / "markers_ct.csv"]


def _config_edit(src: Path, dst: Path, edit) -> Path:
    data = yaml.safe_load(src.read_text())
    edit(data)
    return _write_yaml(dst, data)


def _study_config(b: Base, d: Path, edit=None) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "study_tiny.yaml").read_text())
    data["out"] = str(d / "unused-out")
    data["fit-ogden"]["logs"] = [str(GOOD_LOG)]
    if edit:
        edit(data)
    return _write_yaml(d / "study.yaml", data)


# --------------------------------------------------------------------------- the cases


@dataclass
class Case:
    id: str
    command: str                  # whose previous good result pre-populates the output folder
    what: str                     # the bad input, in words
    build: Callable               # (base, folder) -> (args without -o, the file (or option) named, where)
    expect: int = 2
    subprocess: bool = False      # through a real `bsipipe` process instead of CliRunner


def _c(id, command, what, build, expect=2, sub=False) -> Case:
    return Case(id, command, what, build, expect, sub)


CASES: list[Case] = [
    # --- machine logs (bsipipe/io/machine_log.py) through fit-ogden
    _c("log-empty-file", "fit-ogden", "empty log file", _fit_log("bad_empty_file.csv", 1), sub=True),
    _c("log-truncated-row", "fit-ogden", "log cut off in the middle of a row", _fit_log("bad_truncated_row.csv", 11)),
    _c("log-no-data-rows", "fit-ogden", "log truncated after the header", _fit_log("bad_empty_data.csv", 5)),
    _c("log-units-row-missing", "fit-ogden", "units row missing", _fit_log("bad_missing_units_row.csv", 4)),
    _c("log-unknown-unit", "fit-ogden", "unknown unit (stone) in the units row", _fit_log("bad_unknown_unit.csv", 2)),
    _c("log-unknown-unit-in-name", "fit-ogden", "unknown unit in a column name",
       _fit_log("bad_unknown_unit_in_name.csv", 1)),
    _c("log-text-in-number", "fit-ogden", "text in the load column", _fit_log("bad_text_in_number.csv", 8)),
    _c("log-nan", "fit-ogden", "NaN load", _fit_log("bad_nan.csv", 6)),
    _c("log-inf", "fit-ogden", "infinite load", _fit_log("bad_inf.csv", 10)),
    _c("log-time-backwards", "fit-ogden", "time goes back", _fit_log("bad_time_backwards.csv", 7)),
    _c("log-time-repeated", "fit-ogden", "time repeats", _fit_log("bad_time_repeated.csv", 7)),
    _c("log-no-header", "fit-ogden", "data without a names row", _fit_log("bad_no_header.csv", 1)),
    _c("log-missing-column", "fit-ogden", "no extension column", _fit_log("bad_missing_column.csv", 1)),
    _c("log-geometry-unit", "fit-ogden", "diameter in cubits", _fit_log("bad_geometry_unit.csv", 1)),
    _c("log-no-contact", "fit-ogden", "force never rises (no contact)",
       lambda b, d: ([*FIT, p := _good_log_edit(d, "flat.csv", _no_contact)], p, None), expect=1, sub=True),
    # the sample log states its dimensions twice (Dimensions rows and Results Table 1): a
    # dimension is bad input where every statement of it is invalid (a valid one is taken)
    _c("log-zero-diameter", "fit-ogden", "metadata diameter 0 mm",
       lambda b, d: (["fit-ogden", p := _good_log_edit(d, "d0.csv", _edits(
           _set_line(3, '"Dimensions : Diameter","0.0000","mm"'),
           _set_line(11, '"sheep brain sheep_s3_100mm_min","0.0000","12.2000"')))], p, "line 3")),
    _c("log-negative-height", "fit-ogden", "metadata height -12.2 mm",
       lambda b, d: (["fit-ogden", p := _good_log_edit(d, "hneg.csv", _edits(
           _set_line(4, '"Dimensions : Height","-12.2000","mm"'),
           _set_line(11, '"sheep brain sheep_s3_100mm_min","18.3000",""')))], p, "line 4")),
    _c("option-negative-height", "fit-ogden", "--height-mm -5 (no file involved: the option is named)",
       lambda b, d: (["fit-ogden", GOOD_LOG, "--height-mm", "-5"], "--height-mm", None)),
    _c("log-missing-file", "fit-ogden", "log file does not exist",
       lambda b, d: ([*FIT, d / "nope.csv"], d / "nope.csv", None)),
    _c("fit-config-unknown-key", "fit-ogden", "config typo 'bootstap'",
       lambda b, d: (["fit-ogden", GOOD_LOG, "--config", p := _write_yaml(d / "fit.yaml", {"bootstap": 10})],
                     p, "key 'bootstap'")),
    _c("fit-config-wrong-type", "fit-ogden", "config prony: two",
       lambda b, d: (["fit-ogden", GOOD_LOG, "--config", p := _write_yaml(d / "fit.yaml", {"prony": "two"})],
                     p, "key 'prony'")),
    _c("fit-config-zero-geometry", "fit-ogden", "config diameter_mm: 0",
       lambda b, d: (["fit-ogden", GOOD_LOG, "--config", p := _write_yaml(d / "fit.yaml", {"diameter_mm": 0})],
                     p, "key 'diameter_mm'")),
    _c("fit-config-duplicate-key", "fit-ogden", "config diameter_mm given twice (PyYAML kept the last)",
       lambda b, d: (["fit-ogden", GOOD_LOG, "--config", p := _put(d / "fit.yaml", [
           "diameter_mm: 18", "height_mm: 12", "diameter_mm: 20"])], p, "line 3")),
    _c("width-csv-missing-column", "fit-ogden", "--width-csv without width_mm",
       lambda b, d: ([*FIT, GOOD_LOG, "--width-csv", p := _put(d / "w.csv", ["time_s,w", "0,18", "1,18.2"])],
                     p, "line 1")),
    # --- stress-stretch tables (bsipipe/io/stress_table.py)
    _c("table-text-in-number", "fit-ogden", "text in a stress column",
       lambda b, d: (["fit-ogden", "--stress-stretch", p := _put(d / "t.csv", [
           "stretch,nominal_stress_pa", "1.0,0", "1.1,120", "1.2,abc", "1.3,400"])], p, "line 4")),
    _c("table-no-stress-column", "fit-ogden", "no nominal_stress_* column",
       lambda b, d: (["fit-ogden", "--stress-stretch", p := _put(d / "t.csv", [
           "stretch,stress", "1.0,0", "1.1,120"])], p, "line 1")),
    _c("table-nan", "fit-ogden", "NaN stretch",
       lambda b, d: (["fit-ogden", "--stress-stretch", p := _put(d / "t.csv", [
           "stretch,nominal_stress_kpa", "1.0,0", "nan,0.12", "1.2,0.25"])], p, "line 3")),
    # strains in the stretch column: had been fitted (mu 53 Pa, alpha 0.27), exit 0
    _c("table-strain-as-stretch", "fit-ogden", "strains 0.02-6.6 in the stretch column",
       lambda b, d: (["fit-ogden", "--stress-stretch", p := _put(d / "t.csv", [
           "stretch,nominal_stress_pa", "0.02,25500", "0.125,134400", "0.24,225600", "0.39,316900", "1.5,700000",
           "3.0,1500000"])], p, "looks like strains")),
    # --- images (bsipipe/io/images.py) through calibrate
    _c("png-corrupt", "calibrate", "truncated PNG among the views",
       lambda b, d: (_calib_args(f := _calib_folder(b, d)), (_truncate(f / "cal_002.png"), f / "cal_002.png")[1],
                     None), sub=True),
    _c("tiff-corrupt", "calibrate", "a TIFF with a broken header",
       lambda b, d: (_calib_args(f := _calib_folder(b, d)),
                     (((f / "cal_009.tif").write_bytes(b"II*\x00\x08\x00\x00\x00\xff\xff garbage")),
                      f / "cal_009.tif")[1], None), sub=True),
    _c("dicom-corrupt", "calibrate", "a DICOM whose pixel data are cut off",
       lambda b, d: (_calib_args(f := _dicom_views(b, d)), f / "cal_001.dcm", None), sub=True),
    _c("images-mixed-sizes", "calibrate", "one view 220x200 among 256x256",
       lambda b, d: (_calib_args(f := _calib_folder(b, d)),
                     (_png_resized(f / "cal_001.png", f / "cal_001.png"), f / "cal_001.png")[1], "frame 1")),
    _c("images-mixed-bit-depths", "calibrate", "one 16-bit view among 8-bit views",
       lambda b, d: (_calib_args(f := _calib_folder(b, d)),
                     (_png_16bit(f / "cal_002.png", f / "cal_002.png"), f / "cal_002.png")[1], "frame 2"), sub=True),
    _c("video-zero-frames", "calibrate", "a video with no frame",
       lambda b, d: (["calibrate", "--images", p := _zero_frame_video(d / "empty.avi"), "--pattern",
                      "asymmetric-circles", "--grid", "4x9", "--spacing-mm", "3"], p, None), sub=True),
    _c("images-folder-empty", "calibrate", "a views folder without images",
       lambda b, d: (_calib_args(p := _put(d / "v" / "notes.txt", ["x"]).parent), p, None)),
    _c("images-missing", "calibrate", "views folder does not exist",
       lambda b, d: (_calib_args(d / "nothing"), d / "nothing", None)),
    # two images given: the input's fault (exit 2; exit 1 until session 21); the target found in
    # fewer than three of three or more is the calibration's (exit 1, tests/test_calibrate_checks.py)
    _c("calib-too-few-views", "calibrate", "two images given (at least three needed)",
       lambda b, d: (_calib_args(f := _calib_folder(b, d, 2)), f, None), expect=2, sub=True),
    # a grid larger than the board is a partly seen target (X-ray grids run past the field) and
    # calibrates; a grid smaller than the board cannot be placed on it: bad input (exit 2, as a
    # chessboard's; exit 1 until session 5), naming the grid the views show
    _c("calib-pattern-size", "calibrate", "--grid 3x9 for a 4x9 board",
       lambda b, d: (_calib_args(f := _calib_folder(b, d), "3x9"), f, "--grid 4x9"), expect=2),
    _c("calib-config-unknown-key", "calibrate", "config typo 'spacing'",
       lambda b, d: (["calibrate", p := _config_edit(b.configs["calibrate"], d / "c.yaml",
                                                      lambda c: c.update(spacing=3.0))], p, "key 'spacing'")),
    _c("calib-config-wrong-type", "calibrate", "config spacing_mm: three",
       lambda b, d: (["calibrate", p := _config_edit(b.configs["calibrate"], d / "c.yaml",
                                                      lambda c: c.update(spacing_mm="three"))], p,
                     "key 'spacing_mm'")),
    # --- track (images, seeds, calibration)
    _c("track-seeds-outside", "track", "a seed at x = 5000 px in a 256 px frame",
       lambda b, d: (_track_args(b, seeds=(p := _seeds_edit(b, d, lambda s: s.__setitem__(
           "x_px", np.where(np.arange(len(s)) == 2, 5000.0, s["x_px"])))), ), p, "line 4")),
    _c("track-marker-lost", "track", "a seeded marker that is not in any frame",
       lambda b, d: (_track_args(b, seeds=(p := _seeds_edit(b, d, _seed_on_background)), ), p,
                     "'M1' was not found in any of the 8 frames of view 'cam1'"), expect=1),
    _c("track-seeds-text", "track", "text in x_px of seeds.csv",
       lambda b, d: (_track_args(b, seeds=(p := _seeds_edit(b, d, lambda s: s.__setitem__(
           "x_px", s["x_px"].astype(object).where(np.arange(len(s)) != 4, "left")))), ), p, "line 6")),
    _c("xmalab-seeds-text", "track", "XMALab 2-D CSV seeds with text in a coordinate",
       lambda b, d: (_track_args(b, seeds=(p := _put(d / "xmalab_2d.csv", [
           ln if i != 1 else "abc" + ln[ln.index(","):] for i, ln in enumerate(_lines(b.track / "xmalab_2d.csv"))]))),
                     p, "line 2")),
    _c("xmalab-seeds-outside", "track", "XMALab 2-D CSV seeds with a point off the image",
       lambda b, d: (_track_args(b, seeds=(p := _put(d / "xmalab_2d.csv", [
           ln if i != 1 else "-40" + ln[ln.index(","):] for i, ln in enumerate(_lines(b.track / "xmalab_2d.csv"))]))),
                     p, "outside the 256x256 px image")),
    _c("track-frames-mixed-sizes", "track", "one sequence frame of another size",
       lambda b, d: (_track_args(b, cam1=(f := _copy_dir(b.synth / "sequence/cam1", d / "cam1"))),
                     (_png_resized(f / "frame_0003.png", f / "frame_0003.png"), f / "frame_0003.png")[1],
                     "frame 3")),
    _c("track-video-zero-frames", "track", "cam2 is a video with no frame",
       lambda b, d: (_track_args(b, cam2=(p := _zero_frame_video(d / "cam2.avi"))), p, None), sub=True),
    _c("track-view-missing", "track", "cam1 folder does not exist",
       lambda b, d: (_track_args(b, cam1=d / "gone"), d / "gone", None)),
    _c("track-calibration-corrupt", "track", "calibration.json cut off",
       lambda b, d: (_track_args(b, calibration=(p := _put(d / "calibration.json", _lines(
           b.calibrate / "calibration.json")[:40]))), p, None)),
    _c("track-config-unknown-key", "track", "config typo detection.k_sgima",
       lambda b, d: (["track", p := _config_edit(b.configs["track"], d / "t.yaml",
                                                  lambda c: c.update(detection={"k_sgima": 4}))],
                     p, "key 'detection.k_sgima'"), sub=True),
    _c("track-config-wrong-type", "track", "config fps: fast",
       lambda b, d: (["track", p := _config_edit(b.configs["track"], d / "t.yaml", lambda c: c.update(fps="fast"))],
                     p, "key 'fps'")),
    _c("track-config-fps-inf", "track", "config fps: .inf (a frame rate must be finite)",
       lambda b, d: (["track", p := _config_edit(b.configs["track"], d / "t.yaml",
                                                  lambda c: c.update(fps=float("inf")))], p, "key 'fps'")),
    _c("track-config-fps-1e300", "track", "config fps: 1e300 (the clock fits had overflowed: exit 1)",
       lambda b, d: (["track", p := _config_edit(b.configs["track"], d / "t.yaml",
                                                  lambda c: c.update(fps=1e300))], p, "key 'fps'")),
    # --- register (bsipipe/io/slicer.py, markers3d.csv)
    _c("register-two-references", "register", "two reference markers (three needed)",
       lambda b, d: (_register_args(b, refs=["R1", "R2"]), b.track / "markers3d.csv", None)),
    _c("register-reference-unknown", "register", "references R1, R2 and a name not in either file",
       lambda b, d: (_register_args(b, refs=["R1", "R2", "R9"]), b.track / "markers3d.csv", None)),
    _c("register-ct-mirrored", "register", "CT file says LPS but its x axis is flipped (mirror image)",
       lambda b, d: (_register_args(b, ct=(p := _ct_mirrored(b, d))), p, None), sub=True),
    _c("register-ct-unknown-system", "register", "fcsv CoordinateSystem = XYZ",
       lambda b, d: (_register_args(b, ct=(p := _put(d / "ct.fcsv", [
           ln.replace("= LPS", "= XYZ") for ln in _lines(b.synth / "ct_markers.fcsv")]))), p, "line 2")),
    _c("register-ct-text", "register", "text coordinate in the fcsv",
       lambda b, d: (_register_args(b, ct=(p := _put(d / "ct.fcsv", [
           re.sub(r"^(vtkMRMLMarkupsFiducialNode_1),[^,]+,", r"\1,abc,", ln)
           for ln in _lines(b.synth / "ct_markers.fcsv")]))), p, "line 5")),
    _c("register-ct-mrk-json-cut", "register", ".mrk.json cut off",
       lambda b, d: (_register_args(b, ct=(p := _put(d / "ct.mrk.json", _lines(b.synth / "ct_markers.mrk.json")[:30]))),
                     p, "line 31")),
    _c("register-ct-csv-text", "register", "CT marker CSV with text in z_mm",
       lambda b, d: (_register_args(b, ct=(p := _put(d / "ct.csv", ["marker,x_mm,y_mm,z_mm", "R1,1,2,3", "R2,4,5,6",
                                                                   "R3,7,8,nine", "R4,1,1,1"]))), p, "line 4")),
    _c("register-markers3d-text", "register", "text in x_mm of markers3d.csv",
       lambda b, d: (_register_args(b, xray=(p := _put(d / "m3.csv", [
           ln if i != 3 else re.sub(r"^(\d+,[^,]*,[^,]+),[^,]+,", r"\1,oops,", ln)
           for i, ln in enumerate(_lines(b.track / "markers3d.csv"))]))), p, "line 4")),
    _c("register-ct-missing", "register", "CT file does not exist",
       lambda b, d: (_register_args(b, ct=d / "ct.fcsv"), d / "ct.fcsv", None)),
    # --- compare (bsipipe/io/fe_results.py)
    _c("compare-markers-ras", "compare", "markers_ct.csv in RAS, mesh in LPS (no marker inside the mesh)",
       lambda b, d: (_compare_args(b, markers=_markers_ras(b, d)), b.mesh, None), expect=1),
    # a second, different row of one marker in one frame (hand-edited, or two files pasted)
    _c("compare-markers-duplicate", "compare", "markers_ct.csv with a second, different row of a marker in a frame",
       lambda b, d: (_compare_args(b, markers=(p := _marker_row_twice(b, d))), p, "line 3")),
    _c("compare-disp-text", "compare", "text in a displacement",
       lambda b, d: (_compare_args(b, disp=(p := _put(d / "u.csv", [
           ln if i != 3 else ln.split(",")[0] + ",x,0,0" for i, ln in enumerate(_lines(b.disp))]))), p, "line 4")),
    # 30 % of the nodes' rows dropped (a result written for a node set): had been exit 1 naming the mesh
    _c("compare-disp-nodes-missing", "compare", "displacement CSV without every third node (the markers' too)",
       lambda b, d: (_compare_args(b, disp=(p := _put(d / "u.csv", [
           ln for i, ln in enumerate(_lines(b.disp)) if i == 0 or i % 3]))), p, "have no displacement in this file")),
    _c("compare-mesh-truncated", "compare", "mesh element line cut short",
       lambda b, d: (_compare_args(b, mesh=(p := _put(d / "mesh.inp", _lines(b.mesh)[:-1] + ["1, 1, 2, 3"]))),
                     p, None)),
    # --- export-fe (bsipipe/fe/config.py and its inputs)
    _c("export-config-unknown-key", "export-fe", "config typo deck.max_incremnt_mm",
       lambda b, d: (["export-fe", p := _config_edit(b.configs["export"], d / "e.yaml",
                                                      lambda c: c["deck"].update(max_incremnt_mm=1.0))],
                     p, "key 'deck.max_incremnt_mm'")),
    _c("export-config-wrong-type", "export-fe", "config indentor.diameter_mm: five",
       lambda b, d: (["export-fe", p := _config_edit(b.configs["export"], d / "e.yaml",
                                                      lambda c: c["indentor"].update(diameter_mm="five"))],
                     p, "key 'indentor.diameter_mm'")),
    _c("export-fit-missing", "export-fe", "inputs.fit names a missing file",
       lambda b, d: (["export-fe", _config_edit(b.configs["export"], d / "e.yaml",
                                                 lambda c: c["inputs"].update(fit=str(d / "fit.json")))],
                     d / "fit.json", None)),
    _c("export-fit-corrupt", "export-fe", "fit.json cut off",
       lambda b, d: (["export-fe", _config_edit(b.configs["export"], d / "e.yaml", lambda c: c["inputs"].update(
           fit=str(_put(d / "fit.json", _lines(b.fit / "fit.json")[:5]))))], d / "fit.json", None)),
    _c("export-markers-duplicate", "export-fe", "markers_ct.csv with a second, different row of a marker in a frame",
       lambda b, d: (["export-fe", _config_edit(b.configs["export"], d / "e.yaml", lambda c: c["inputs"].update(
           markers_ct=str(_marker_row_twice(b, d))))], d / "markers_ct_twice.csv", "line 3")),
    # registration.json of another register run (another CT: everything 60 mm along x), with
    # this run's markers_ct.csv: exit 0 had placed the indentor 60 mm off (800 mm in the probe)
    _c("export-registration-other-run", "export-fe", "registration.json of another run than markers_ct.csv",
       lambda b, d: (["export-fe", _config_edit(b.configs["export"], d / "e.yaml", lambda c: c["inputs"].update(
           registration=str(_registration_moved(b, d))))], b.register / "markers_ct.csv", "different register runs")),
    _c("export-markers3d-other-trial", "export-fe", "inputs.markers3d of another trial than the registration",
       lambda b, d: (["export-fe", _config_edit(b.configs["export"], d / "e.yaml", lambda c: c["inputs"].update(
           markers3d=str(_markers3d_moved(b, d))))], d / "markers3d.csv", "registration is of another trial")),
    _c("export-log-no-contact", "export-fe", "the indentation log never loads the tissue",
       lambda b, d: (["export-fe", _config_edit(b.configs["export"], d / "e.yaml", lambda c: c["inputs"].update(
           log=str(_flat_indentation_log(b, d))))], d / "log.csv", None), expect=1),
    # --- synth
    _c("synth-config-unknown-key", "synth", "config typo image.size",
       lambda b, d: (["synth", p := _config_edit(b.configs["synth"], d / "s.yaml",
                                                  lambda c: c["image"].update(size=256))], p, "key 'image.size'")),
    _c("synth-config-wrong-type", "synth", "config seed: three",
       lambda b, d: (["synth", p := _config_edit(b.configs["synth"], d / "s.yaml", lambda c: c.update(seed="three"))],
                     p, "key 'seed'")),
    _c("synth-out-is-file", "synth", "-o names an existing file", "out-is-file"),
    _c("fit-out-is-file", "fit-ogden", "-o names an existing file", "out-is-file", sub=True),
    # --- study
    _c("study-config-unknown-key", "study", "config typo 'trails'",
       lambda b, d: (["study", p := _study_config(b, d, lambda c: c.update(trails=c.pop("trials")))],
                     p, "key 'trails'")),
    _c("study-config-wrong-type", "study", "config register.perturbation_draws: many",
       lambda b, d: (["study", p := _study_config(b, d, lambda c: c["register"].update(perturbation_draws="many"))],
                     p, "perturbation_draws")),
    _c("study-config-stage-typo", "study", "config typo in a stage section (fit-ogden.config.bootstap)",
       lambda b, d: (["study", p := _study_config(b, d, lambda c: c["fit-ogden"]["config"].update(bootstap=3))],
                     p, "bootstap")),
    _c("study-config-missing", "study", "config file does not exist",
       lambda b, d: (["study", d / "study.yaml"], d / "study.yaml", None)),
]


def _dicom_views(b: Base, d: Path) -> Path:
    f = d / "dcm"
    f.mkdir()
    for i, png in enumerate(sorted((b.synth / "calibration" / "cam1").glob("*.png"))):
        _dicom_from_png(png, f / f"cal_{i:03d}.dcm")
    _truncate(f / "cal_001.dcm", 0.6)
    return f


def _seed_on_background(s: pd.DataFrame) -> None:
    """Move cam1's seed of M1 to a place with no marker (the field's centre region, 30 px away)."""
    i = int(np.flatnonzero((s["view"] == "cam1") & (s["marker"] == "M1"))[0])
    s.loc[i, "y_px"] = s.loc[i, "y_px"] - 30.0


def _ct_mirrored(b: Base, d: Path) -> Path:
    from bsipipe.io.slicer import format_fcsv, read_markups
    m = read_markups(b.synth / "ct_markers.fcsv")
    p = m.positions_mm.copy()
    p[:, 0] *= -1.0
    return _put(d / "ct_mirrored.fcsv", format_fcsv(m.names, p, "LPS").splitlines())


def _markers_ras(b: Base, d: Path) -> Path:
    df = pd.read_csv(b.register / "markers_ct.csv")
    for c in ("x_mm", "y_mm", "dx_mm", "dy_mm"):
        df[c] = -df[c]
    df.to_csv(d / "markers_ct_ras.csv", index=False)
    return d / "markers_ct_ras.csv"


def _marker_row_twice(b: Base, d: Path) -> Path:
    """markers_ct.csv with its first row again as the second, 3 mm deeper."""
    lines = _lines(b.register / "markers_ct.csv")
    df = pd.read_csv(b.register / "markers_ct.csv", nrows=1)
    df["z_mm"] += 3.0
    df["dz_mm"] += 3.0
    return _put(d / "markers_ct_twice.csv", [lines[0], lines[1], *df.to_csv(index=False).splitlines()[1:], *lines[2:]])


def _registration_moved(b: Base, d: Path) -> Path:
    """The run's registration.json as a registration to a CT 60 mm along x would be."""
    reg = json.loads((b.register / "registration.json").read_text())
    reg["t_mm"][0] += 60.0
    reg["reference_ct_mm"] = {n: [x + 60.0, y, z] for n, (x, y, z) in reg["reference_ct_mm"].items()}
    (d / "registration.json").write_text(json.dumps(reg))
    return d / "registration.json"


def _markers3d_moved(b: Base, d: Path) -> Path:
    """The run's markers3d.csv 25 mm along x: another trial, the head placed elsewhere."""
    m3 = pd.read_csv(b.track / "markers3d.csv")
    m3["x_mm"] += 25.0
    m3.to_csv(d / "markers3d.csv", index=False)
    return d / "markers3d.csv"


def _flat_indentation_log(b: Base, d: Path) -> Path:
    lines = _lines(b.synth / "indentation_log.csv")
    k = next(i for i, ln in enumerate(lines) if ln.startswith('"(s)"')) + 1
    rng = np.random.default_rng(2)
    for i in range(k, len(lines)):
        cells = [c.strip('"') for c in lines[i].split(",")]
        cells[2] = f"{rng.normal(0, 0.001):.6f}"
        lines[i] = ",".join(f'"{c}"' for c in cells)
    return _put(d / "log.csv", lines)


# --------------------------------------------------------------------------- running a case


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _snapshot(folder: Path) -> dict[str, str] | None:
    """Every file below ``folder`` (hidden and temporary ones too) with its sha256; None if absent."""
    if not folder.exists():
        return None
    if folder.is_file():
        return {".": _sha(folder)}
    return {str(p.relative_to(folder)): _sha(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def _run(args: list, via_subprocess: bool) -> tuple[int, str, str, BaseException | None]:
    if not via_subprocess:
        return _invoke(args)
    p = subprocess.run([str(EXE), *[str(a) for a in args]], capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout, p.stderr, None


_MESSAGE = re.compile(r"^(bsipipe [\w-]+: (internal )?error:|Error:)")
#: What else stderr may hold: log records (bsipipe's format), click's usage lines, blank lines.
_EXPECTED_LINE = re.compile(r"^((DEBUG|INFO|WARNING|ERROR|CRITICAL) [\w.]+: |Usage: |Try '|\s*$)")


@dataclass
class Outcome:
    case: Case
    observed: int
    message: str
    n_messages: int
    traceback: bool
    internal: bool
    partial: list[str]            # files written, changed or removed in the output folders
    names_file: bool
    where_ok: bool
    stray: list[str] = field(default_factory=list)   # other stderr lines (a library printing its own)

    @property
    def ok(self) -> bool:
        return (self.observed == self.case.expect and self.n_messages == 1 and not self.traceback
                and not self.internal and not self.partial and self.names_file and self.where_ok
                and not self.stray)


def run_case(case: Case, base: Base, tmp: Path) -> Outcome:
    d = tmp / "inputs"
    d.mkdir(parents=True, exist_ok=True)
    out = tmp / "out"
    if case.build == "out-is-file":
        args = (["synth", base.configs["synth"]] if case.command == "synth"
                else ["fit-ogden", GOOD_LOG, "--config", base.configs["fit"]])
        out.write_text("a file where the output folder should go\n")
        named, where, fresh = out, None, None
    else:
        args, named, where = case.build(base, d)
        src = base.good[case.command]
        if case.command == "study":   # a previous study's stage folders
            for name in ("register", "fit", "compare"):
                shutil.copytree(getattr(base, name), out / "trial" / name)
        else:
            shutil.copytree(src, out)
        fresh = tmp / "fresh" / "out"
    before = _snapshot(out)
    code, stdout, stderr, exc = _run([*args, "-o", out], case.subprocess)
    after = _snapshot(out)
    partial = sorted({k for k in set(before or {}) | set(after or {}) if (before or {}).get(k) != (after or {}).get(k)})
    if fresh is not None:   # the same run into a new folder leaves no file there
        code2, _, stderr2, exc2 = _run([*args, "-o", fresh], case.subprocess)
        partial += [f"fresh:{k}" for k in (_snapshot(fresh) or {})]
        exc = exc or exc2
        if code2 != code:
            partial.append(f"fresh run exited {code2}, first run {code}")
    messages = [ln for ln in stderr.splitlines() if _MESSAGE.match(ln)]
    msg = messages[0] if messages else (stderr.strip().splitlines() or [""])[-1]
    text = stdout + stderr
    stray = [ln for ln in stderr.splitlines() if not (_MESSAGE.match(ln) or _EXPECTED_LINE.match(ln))]
    return Outcome(case=case, observed=code, message=msg, n_messages=len(messages),
                   traceback=exc is not None or "Traceback (most recent call last)" in text,
                   internal="internal error" in text, partial=partial,
                   names_file=str(named) in msg, where_ok=where is None or where in msg, stray=stray)


RESULTS: dict[str, Outcome] = {}


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case, base, tmp_path):
    o = run_case(case, base, tmp_path)
    RESULTS[case.id] = o
    assert not o.traceback, o.message
    assert not o.internal, o.message
    assert o.observed == case.expect, f"exit {o.observed}, expected {case.expect}: {o.message}"
    assert o.n_messages == 1, f"{o.n_messages} error messages"
    assert o.names_file, f"the message does not name the file: {o.message}"
    assert o.where_ok, f"the message does not say where: {o.message}"
    assert not o.partial, f"output written or changed: {o.partial}"
    assert not o.stray, f"other lines on stderr: {o.stray}"


def _fmt_table(outcomes: list[Outcome]) -> str:
    """case, command, bad input, expected and observed exit status, verdict, the message (cut at 150)."""
    rows = [("case", "command", "bad input", "expected", "observed", "verdict", "message")]
    for o in outcomes:
        verdict = "ok" if o.ok else ",".join(f for f, bad in (
            ("exit", o.observed != o.case.expect), ("n_msg", o.n_messages != 1), ("traceback", o.traceback),
            ("internal", o.internal), ("partial", bool(o.partial)), ("file", not o.names_file),
            ("where", not o.where_ok), ("stray", bool(o.stray))) if bad)
        msg = o.message if len(o.message) <= 150 else o.message[:147] + "..."
        rows.append((o.case.id, o.case.command, o.case.what, str(o.case.expect), str(o.observed), verdict, msg))
    k = len(rows[0]) - 1
    w = [max(len(r[i]) for r in rows) for i in range(k)]
    lines = ["  ".join(r[i].ljust(w[i]) for i in range(k)) + "  " + r[k] for r in rows]
    lines.insert(1, "  ".join("-" * w[i] for i in range(k)) + "  " + "-" * 7)
    return "\n".join(lines)


def test_matrix_summary(base, tmp_path):
    """The matrix: every case (run here if the parametrised test did not), printed and written."""
    outcomes = []
    for c in CASES:
        if c.id not in RESULTS:
            RESULTS[c.id] = run_case(c, base, tmp_path / c.id)
        outcomes.append(RESULTS[c.id])
    n = len(outcomes)
    tracebacks = sum(o.traceback or o.internal for o in outcomes)
    partial = sum(bool(o.partial) for o in outcomes)
    named = sum(o.names_file for o in outcomes)
    exits = sum(o.observed == o.case.expect for o in outcomes)
    commands = sorted({o.case.command for o in outcomes})
    n_sub = sum(o.case.subprocess for o in outcomes)
    stray = sum(bool(o.stray) for o in outcomes)
    summary = (f"{n} cases over {len(commands)} commands ({', '.join(commands)}): {exits}/{n} expected exit "
               f"status, {tracebacks} tracebacks, {partial} partial outputs, {named}/{n} messages name the file, "
               f"{sum(o.where_ok for o in outcomes)}/{n} say where; {n_sub} cases through a real bsipipe process, "
               f"{stray} with other lines on stderr")
    table = _fmt_table(outcomes) + "\n\n" + summary + "\n"
    (tmp_path / "bad_input_matrix.txt").write_text(table)
    print("\n" + table)
    assert n >= 40
    assert tracebacks == 0 and partial == 0 and named == n and exits == n and stray == 0
    assert all(o.ok for o in outcomes), [o.case.id for o in outcomes if not o.ok]


def test_views_of_different_lengths_are_a_warning(base, tmp_path):
    """Not an error (a video's header count may be an estimate, a file may be missing at the
    end), but never silent: track.json's warnings name both views' frame counts."""
    n = len(list((base.synth / "sequence/cam2").iterdir()))
    cam2 = _copy_dir(base.synth / "sequence/cam2", tmp_path / "cam2", n - 1)
    out = tmp_path / "out"
    code, _, err, exc = _invoke(_track_args(base, cam2=cam2) + ["-o", out])
    assert exc is None and code == 0, err
    w = [x for x in json.loads((out / "track.json").read_text())["warnings"] if x["code"] == "frame-count-mismatch"]
    assert len(w) == 1 and w[0]["n_frames"] == {"cam1": n, "cam2": n - 1}
    assert f"cam1 {n}, cam2 {n - 1}" in w[0]["message"]


@pytest.mark.parametrize("value,ok", [(True, False), (False, False), ("12", True), (float("inf"), False), (12, True)])
def test_config_numbers_are_numbers(value, ok):
    """A config number is a finite number: YAML's true/false (lax pydantic: 1 and 0) and .inf
    are refused naming the key; a number quoted as a string (PyYAML reads ``1e-3`` so) is read."""
    from bsipipe.config import FitConfig, validate
    from bsipipe.errors import InputError
    if ok:
        assert validate(FitConfig, {"diameter_mm": 18, "height_mm": value}, "c.yaml").height_mm == 12.0
    else:
        with pytest.raises(InputError, match=r"c.yaml, key 'height_mm': .*(not true/false|finite)"):
            validate(FitConfig, {"diameter_mm": 18, "height_mm": value}, "c.yaml")


@pytest.mark.parametrize("value", [True, False, "auto"])
def test_config_literal_with_true_false_takes_them(value):
    """A key whose values include true and false (``fe-solve.enabled: auto | true | false``)
    takes YAML's true/false: the numbers-are-numbers rule refused them (session 5: the
    documented ``fe-solve: {enabled: false}`` was exit 2)."""
    from bsipipe.config import validate
    from bsipipe.study_config import FeSolveSection
    assert validate(FeSolveSection, {"enabled": value}, "s.yaml").enabled == value


def test_views_at_different_frame_rates_are_a_warning(tmp_path):
    """Two lossless videos whose time stamps give 4 and 2 frames/s: frame k of one is not
    taken at frame k's time in the other.  Not an error (the loop's view-time-offset can pair
    them by time), but never silent: a frame-rate-mismatch warning with both rates; videos at
    the same rate raise none."""
    import cv2
    rng = np.random.default_rng(6)
    yy, xx = np.mgrid[:96, :96].astype(float)
    beads = {"A": (30.3, 40.6), "B": (60.2, 55.1)}
    seeds = tmp_path / "seeds.csv"
    pd.DataFrame([{"view": v, "marker": m, "x_px": x + 0.4, "y_px": y - 0.3} for v in ("cam1", "cam2")
                  for m, (x, y) in beads.items()]).to_csv(seeds, index=False)
    outs = {}
    for rates in ((4.0, 2.0), (4.0, 4.0)):
        for v, fps in zip(("cam1", "cam2"), rates):
            w = cv2.VideoWriter(str(tmp_path / f"{v}_{fps:g}.avi"), cv2.VideoWriter_fourcc(*"FFV1"), fps, (96, 96), False)
            assert w.isOpened()
            for k in range(8):
                img = np.full((96, 96), 150.0)
                for x, y in beads.values():
                    img -= 40 * np.exp(-((xx - x - 0.2 * k) ** 2 + (yy - y) ** 2) / (2 * 1.1 ** 2))
                w.write(np.clip(np.rint(img + rng.normal(0, 1.5, img.shape)), 0, 255).astype(np.uint8))
            w.release()
        out = tmp_path / f"out_{rates[1]:g}"
        r = CliRunner().invoke(cli, ["track", "--view", f"cam1={tmp_path / 'cam1_4.avi'}",
                                     "--view", f"cam2={tmp_path / f'cam2_{rates[1]:g}.avi'}",
                                     "--seeds", str(seeds), "-o", str(out)])
        assert r.exit_code == 0, r.output
        outs[rates] = [x for x in json.loads((out / "track.json").read_text())["warnings"]
                       if x["code"] == "frame-rate-mismatch"]
    w = outs[(4.0, 2.0)]
    assert len(w) == 1 and w[0]["frames_per_s"] == pytest.approx({"cam1": 4.0, "cam2": 2.0})
    assert "cam1 4, cam2 2 frames/s" in w[0]["message"]
    assert outs[(4.0, 4.0)] == []


def test_frames_of_another_size_than_the_calibration_are_refused(base, tmp_path):
    """cam1's frames binned 2x2 (an export at half size) against a calibration made at full
    size: the camera matrix would send every ray wrong (the ray gaps were 8.5 mm on the bench
    twin, with only a large-ray-gap warning).  Refused before any tracking: exit 2, the
    message names the calibration file and both sizes, nothing written."""
    import cv2
    src = base.synth / "sequence/cam1"
    cam1 = tmp_path / "cam1"
    cam1.mkdir()
    for f in sorted(src.iterdir())[:4]:
        im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(cam1 / f.name), cv2.resize(im, (im.shape[1] // 2, im.shape[0] // 2), interpolation=cv2.INTER_AREA))
    h, w = im.shape[:2]
    out = tmp_path / "out"
    code, _, err, exc = _invoke(_track_args(base, cam1=cam1) + ["-o", out])
    assert exc is None and code == 2, err
    assert "calibration.json" in err and f"{w // 2}x{h // 2} px" in err and f"{w}x{h} px" in err, err
    assert not out.exists()


def test_a_marker_seeded_in_one_view_only_is_a_warning(base, tmp_path):
    """A marker seeded in cam1 and not in cam2: tracked in 2-D in cam1, no 3-D point -- not
    an error, but said (single-view-markers, naming it and its view), where it used to be
    left out of markers3d.csv without a word."""
    df = pd.read_csv(base.synth / "seeds.csv")
    name = str(df.loc[df["view"] == "cam2", "marker"].iloc[-1])
    seeds = tmp_path / "seeds.csv"
    df[~((df["view"] == "cam2") & (df["marker"] == name))].to_csv(seeds, index=False)
    out = tmp_path / "out"
    code, _, err, exc = _invoke(_track_args(base, seeds=seeds) + ["-o", out])
    assert exc is None and code == 0, err
    w = [x for x in json.loads((out / "track.json").read_text())["warnings"] if x["code"] == "single-view-markers"]
    assert len(w) == 1 and w[0]["markers"] == {"cam1": [name]}
    p3 = pd.read_csv(out / "markers3d.csv")
    assert name not in set(p3["marker"]) and name in set(pd.read_csv(out / "markers2d.csv")["marker"])


@pytest.mark.parametrize("command", ["fit-ogden", "register"])
def test_output_folder_under_a_file_is_refused_before_the_work(tmp_path, command):
    """-o a/b where a is a file: exit 2 naming a, before any work (it had been an internal
    error, exit 1, once the fit was done and its results were written)."""
    from click.testing import CliRunner

    from bsipipe.cli import cli
    (tmp_path / "afile").write_text("a file, not a folder\n")
    args = ([*FIT, str(GOOD_LOG)] if command == "fit-ogden" else
            ["register", "--ct", str(tmp_path / "none.fcsv"), "--xray", str(tmp_path / "none.csv"),
             "--reference", "R1"])
    r = CliRunner().invoke(cli, [*args, "-o", str(tmp_path / "afile" / "sub")])
    assert r.exit_code == 2 and f"{tmp_path / 'afile'} is a file" in r.output, r.output
    assert "internal error" not in r.output and (tmp_path / "afile").read_text() == "a file, not a folder\n"


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_output_folder_the_file_system_refuses_is_exit_2(tmp_path):
    """-o /proc/x: the permission bits say writable (as root) but no folder can be made there;
    it had been an internal error, exit 1."""
    from click.testing import CliRunner

    from bsipipe.cli import cli
    r = CliRunner().invoke(cli, [*FIT, str(GOOD_LOG), "-o", "/proc/bsipipe-test-out"])
    assert r.exit_code == 2 and "cannot make the output folder" in r.output, r.output
    assert "internal error" not in r.output and not list(tmp_path.iterdir())
