"""``bsipipe synth CONFIG -o DIR``: write the seeded C-arm twin of the indentation study.

Layout of ``DIR`` (see :mod:`bsipipe.synth.twin` for what each file holds)::

    calibration/<view>/cal_NNN.png          each C-arm's own views of the calibration plate
    calibration/stereo/<view>/stereo_NNN.png  views seen by both C-arms at once (same names)
    sequence/<view>/frame_NNNN.png          the indentation sequence, views cam1 and cam2
    indentation_log.csv                     Micro Tester log (Bluehill 3 layout)
    ct_markers.fcsv, ct_markers.mrk.json    CT marker coordinates (3D Slicer, LPS)
    calibration.yaml                        a ready config: ``bsipipe calibrate DIR/calibration.yaml -o CAL``
    seeds.csv                               view,marker,x_px,y_px in frame 0
    truth_markers.csv                       true 2-D/3-D marker positions per view and frame
    truth.json                              every true value
    synth.json                              what was written, timing, provenance (last)

Frames are rendered into a hidden staging folder inside ``DIR`` and moved into place only
when everything has been produced; ``synth.json`` is written last, so a run that fails
leaves no folder that looks complete.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from ..config import load_config
from ..errors import InputError
from ..io.slicer import format_fcsv, format_mrk_json
from ..provenance import ResultSet, provenance

log = logging.getLogger("bsipipe.synth")

_OWNED = ("calibration", "sequence")
_STAGING = ".synth-staging-"
#: truth_markers.csv's columns, written even when the scene has no markers
TRUTH_MARKERS_COLUMNS = ["view", "frame", "time_s", "marker", "x_px", "y_px", "x_mm", "y_mm", "z_mm", "occluded",
                         "visible"]
_FILES = ("indentation_log.csv", "ct_markers.fcsv", "ct_markers.mrk.json", "seeds.csv", "truth_markers.csv",
          "calibration.yaml", "truth.json", "synth.json")


def calibrate_config(cfg) -> dict | None:
    """``bsipipe calibrate``'s config for the calibration views the twin ``cfg`` writes (the
    keys of :class:`bsipipe.commands.calibrate.CalibrateConfig`, folders relative to the
    output folder, where ``calibration.yaml`` is written), or None when it writes none.

    The target is the twin's plate as OpenCV names it (``grid`` = circles per row x rows,
    or inner corners / squares), so a user or ``bsipipe study`` need not work it out."""
    from ..synth.twin import VIEWS
    c = cfg.calibration
    if c.views == 0 and c.stereo_views == 0:
        return None
    d: dict = {"pattern": c.pattern, "grid": f"{c.grid[0]}x{c.grid[1]}", "spacing_mm": float(c.spacing_mm)}
    if c.views > 0:
        d["views"] = {v: f"calibration/{v}" for v in VIEWS}
    if c.stereo_views > 0:
        d["stereo"] = {v: f"calibration/stereo/{v}" for v in VIEWS}
    if c.pattern in ("circles", "asymmetric-circles"):
        d["polarity"] = "dark"            # steel beads absorb: dark in raw C-arm frames
    elif c.pattern == "charuco":
        d["marker_mm"] = float(c.spacing_mm * c.charuco_marker_fraction)
        d["dictionary"] = c.charuco_dictionary
    return d


def encode_png(img: np.ndarray) -> bytes:
    import cv2
    # level 1: noisy frames compress no better at higher levels, which take twice as long
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV only fails here on an invalid array
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def run(config: str | os.PathLike, out: str | os.PathLike) -> dict:
    """Generate the twin described by ``config`` into ``out``; returns ``synth.json``'s content."""
    from ..synth.config import SynthConfig
    from ..synth.machine_log import write_bluehill3
    from ..synth.twin import Twin, TwinError

    cfg = load_config(SynthConfig, config)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output path exists and is not a folder", path=out)
    if not (out / "synth.json").exists():
        for name in _OWNED:
            if (out / name).exists():
                raise InputError(f"'{name}' exists and was not written by bsipipe synth (no synth.json); "
                                 "choose another output folder", path=out)
    t_start = time.perf_counter()
    try:
        twin = Twin(cfg)
    except TwinError as e:
        raise InputError(str(e), path=config, key=e.key) from None
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(out)
    stage = Path(tempfile.mkdtemp(prefix=f"{_STAGING}{os.getpid()}-", dir=out))
    timing: dict[str, float] = {}
    counts: dict[str, int] = {}
    try:
        t0 = time.perf_counter()
        n = 0
        try:
            for rel, img in twin.calibration_images():
                _write(stage / rel, encode_png(img))
                n += 1
        except TwinError as e:
            raise InputError(str(e), path=config, key=e.key) from None
        counts["calibration_images"] = n
        timing["calibration_s"] = time.perf_counter() - t0
        log.info("wrote %d calibration images", n)

        t0 = time.perf_counter()
        n, render_s = 0, 0.0
        gen = twin.sequence_frames()
        while True:
            tr = time.perf_counter()
            try:
                rel, img = next(gen)
            except StopIteration:
                break
            render_s += time.perf_counter() - tr
            _write(stage / rel, encode_png(img))
            n += 1
        counts["sequence_frames"] = n
        timing["sequence_s"] = time.perf_counter() - t0
        if n:
            timing["render_ms_per_frame"] = 1000 * render_s / n
            timing["ms_per_frame_with_png"] = 1000 * timing["sequence_s"] / n
        log.info("wrote %d sequence frames", n)

        rs = ResultSet(out, primary="synth.json")
        prov = provenance(cfg, [config], command="synth")
        truth = twin.truth()
        truth["provenance"] = prov
        if twin.scene is not None:
            frame, log_truth = twin.machine_log()
            d_eq, h_eq = log_truth["diameter_mm"], log_truth["height_mm"]
            write_bluehill3(frame, stage / "indentation_log.csv", label=f"bsipipe synth seed {cfg.seed}",
                            geometry={"diameter_mm": d_eq, "height_mm": h_eq},
                            metadata={"Test": "in situ indentation (equivalent cylinder geometry)",
                                      "Indenter diameter (mm)": f"{cfg.sequence.indentor_diameter_mm:g}"})
            ct = twin.ct_markers()
            kind = {m.name: m.kind for m in twin.scene.markers}
            desc = [kind[n] for n in ct["names"]]
            rs.add_text("ct_markers.fcsv", format_fcsv(ct["names"], ct["written_mm"], "LPS", desc))
            rs.add_text("ct_markers.mrk.json", format_mrk_json(ct["names"], ct["written_mm"], "LPS", desc,
                                                               name="ct_markers"))
            rs.add_csv("seeds.csv", pd.DataFrame(twin.seeds(), columns=["view", "marker", "x_px", "y_px"]))
            rs.add_csv("truth_markers.csv", pd.DataFrame(twin.truth_markers_rows(), columns=TRUTH_MARKERS_COLUMNS))
        cal_cfg = calibrate_config(cfg)
        if cal_cfg is not None:
            import yaml
            rs.add_text("calibration.yaml",
                        "# bsipipe calibrate's config for these calibration views, written by bsipipe synth:\n"
                        "#   bsipipe calibrate calibration.yaml -o CAL    (folders are relative to this file)\n"
                        + yaml.safe_dump(cal_cfg, sort_keys=False))
        rs.add_json("truth.json", truth)
        timing["total_s"] = time.perf_counter() - t_start
        written = sorted(str(p.relative_to(stage)) for p in stage.rglob("*") if p.is_file()) + sorted(rs.files)
        result = {"out": str(out), "views": list(twin.arms), "counts": counts, "timing": timing,
                  "files": [f for f in written if Path(f).parts[0] not in _OWNED] + [f"{d}/..." for d in _OWNED
                                                                              if (stage / d).exists()],
                  "truth": "truth.json", "warnings": [], "provenance": prov}
        rs.add_json("synth.json", result)

        # commit: the previous run stops looking complete first, then everything moves in
        for name in _FILES:
            if (out / name).exists():
                (out / name).unlink()
        for name in _OWNED:
            if (out / name).exists():
                shutil.rmtree(out / name)
            if (stage / name).exists():
                os.replace(stage / name, out / name)
        if (stage / "indentation_log.csv").exists():
            os.replace(stage / "indentation_log.csv", out / "indentation_log.csv")
        rs.commit()
        return result
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:      # someone else's process
        return True
    except (OverflowError, ValueError):
        return False
    return True


def remove_stale_staging(out: Path, legacy_age_s: float = 3600.0) -> list[Path]:
    """Remove the staging folders in ``out`` that no running synth owns: a run killed
    outright (SIGKILL, power loss) cannot clean up after itself. A folder's name holds its
    run's process id (``.synth-staging-<pid>-<random>``); one without (written by an older
    version) is removed once untouched for ``legacy_age_s``. Returns the folders removed."""
    removed = []
    for d in out.glob(_STAGING + "*"):
        if not d.is_dir():
            continue
        pid = d.name[len(_STAGING):].split("-", 1)[0]
        if pid.isdigit() and "-" in d.name[len(_STAGING):]:
            stale = int(pid) != os.getpid() and not _pid_alive(int(pid))
        else:
            try:
                stale = time.time() - d.stat().st_mtime > legacy_age_s
            except OSError:
                continue
        if stale:
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
            log.info("removed %s, left by a synth run that no longer runs", d)
    return removed


def _write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
