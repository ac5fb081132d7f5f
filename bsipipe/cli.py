"""The ``bsipipe`` command line: a click group, one small function per command.

Heavy modules are imported inside the commands so ``bsipipe --help`` stays instant.
Errors: :class:`~bsipipe.errors.InputError` exits 2, :class:`~bsipipe.errors.ProcessingError`
exits 1, each with one message on stderr and no traceback unless ``-v`` is given.
"""

from __future__ import annotations

import os

# numpy's OpenBLAS starts a thread per core that spins between calls; bsipipe's linear algebra
# is many small systems, where the extra threads only burn CPU (``bsipipe track``: 10-15 % of
# its CPU time). Set before numpy is imported; a value the user set is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import functools  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import click

from . import __version__
from .errors import BsipipeError

log = logging.getLogger("bsipipe")


def _setup_logging(verbose: int, quiet: int) -> None:
    level = logging.INFO - 10 * verbose + 10 * quiet
    logging.basicConfig(level=max(level, logging.DEBUG), format="%(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr, force=True)
    # numpy's and pandas' RuntimeWarnings (an all-NaN slice in a frame where a marker is
    # hidden, ...) are the code's business, not the user's: logged at DEBUG (-v shows them),
    # not printed raw among the command's lines
    logging.captureWarnings(True)
    logging.getLogger("py.warnings").setLevel(logging.DEBUG if verbose else logging.ERROR)


def handle_errors(fn):
    """Turn bsipipe's errors into one stderr line and the contract's exit status."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        ctx = click.get_current_context()
        verbose = (ctx.find_root().obj or {}).get("verbose", 0)
        try:
            if kwargs.get("out"):
                from .provenance import check_output_folder
                check_output_folder(kwargs["out"])
            return fn(*args, **kwargs)
        except BsipipeError as e:
            if verbose:
                # the traceback, and still the contract's exit status (a re-raise had made a
                # user's error exit 1)
                import traceback
                traceback.print_exc(file=sys.stderr)
            click.echo(f"bsipipe {ctx.info_name}: error: {e}", err=True)
            sys.exit(e.exit_code)
        except KeyboardInterrupt:
            # Ctrl-C: the shell's 128 + SIGINT, not click's "Aborted!" with exit 1, a processing
            # failure by the contract; nothing half-written is left (results are committed whole)
            click.echo(f"bsipipe {ctx.info_name}: interrupted", err=True)
            sys.exit(130)
        except (click.exceptions.Exit, click.ClickException):
            raise
        except MemoryError:
            click.echo(f"bsipipe {ctx.info_name}: error: out of memory", err=True)
            sys.exit(1)
        except Exception as e:  # an unexpected failure is still a failure: exit 1, never 0
            if verbose:
                raise
            click.echo(f"bsipipe {ctx.info_name}: internal error: {type(e).__name__}: {e} "
                       f"(rerun with -v for the traceback)", err=True)
            sys.exit(1)

    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="bsipipe")
@click.option("-v", "--verbose", count=True, help="More log output; -v also shows tracebacks.")
@click.option("-q", "--quiet", count=True, help="Less log output.")
@click.pass_context
def cli(ctx: click.Context, verbose: int, quiet: int) -> None:
    """Brain-skull interface experiments: calibrate C-arms, track markers, register CT,
    fit constitutive models and hand off to FE."""
    ctx.obj = {"verbose": verbose, "quiet": quiet}
    _setup_logging(verbose, quiet)


@cli.command("fit-ogden")
@click.argument("inputs", metavar="LOG... | TABLE.csv...", nargs=-1, required=True,
                type=click.Path(dir_okay=False))
@click.option("--diameter-mm", multiple=True, type=click.FloatRange(min=0, min_open=True),
              help="Specimen diameter (mm). Once for all logs or once per log (over the logs' metadata).")
@click.option("--height-mm", multiple=True, type=click.FloatRange(min=0, min_open=True),
              help="Specimen height before contact (mm). Once for all logs or once per log.")
@click.option("--stress-stretch", is_flag=True, help="Inputs are stress-stretch tables, not machine logs.")
@click.option("--mode", "modes", multiple=True,
              type=click.Choice(["uniaxial", "equibiaxial", "pure-shear", "simple-shear"]),
              help="Loading mode of each table (repeat per table, or once for all).")
@click.option("--model", type=click.Choice(["ogden", "ogden2", "ogden3", "neo-hookean", "mooney-rivlin"]),
              help="Hyperelastic law (default ogden, one term).")
@click.option("--prony", type=click.IntRange(0, 3), help="Prony terms of a hyperviscoelastic form (QLV).")
@click.option("--boundary", type=click.Choice(["frictionless", "no-slip"]),
              help="Platen boundary (default frictionless: the homogeneous formula).")
@click.option("--loop/--no-loop", default=None, help="Close the loop: find and add missing effects (default on).")
@click.option("--width-csv", type=click.Path(dir_okay=False),
              help="Lateral width at mid-height over time (time_s,width_mm), evidence for the boundary.")
@click.option("--config", type=click.Path(dir_okay=False), help="YAML config (options win over it).")
@click.option("--max-strain", type=click.FloatRange(0, 1, min_open=True, max_open=True),
              help="Fit only up to this nominal strain past contact.")
@click.option("--bootstrap", type=click.IntRange(min=0), help="Residual-bootstrap resamples checking the CIs.")
@click.option("--seed", type=click.IntRange(min=0), help="Seed of the bootstrap (a non-negative integer).")
@click.option("--contact-mm", "contact_mm", multiple=True, type=float,
              help="Contact, not detected: displacement (mm) past the log's first sample, positive in compression, "
                   "at which the platen touched (negative: before the record began). Once for all logs or once per log.")
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def fit_ogden(inputs, out, **opts) -> None:
    """Fit Ogden-family (hyper)viscoelastic laws to machine logs or stress-stretch tables."""
    from .commands import fit_ogden as command

    obj = click.get_current_context().find_root().obj or {}
    res = command.run(inputs, out=out, progress=sys.stderr.isatty() and not obj.get("quiet", 0), **opts)
    p = res["params"]
    # the loop's final model (its Prony terms and effects), as fit.json's loop.final has it
    model = ((res.get("loop") or {}).get("final") or {}).get("model") or res["model"]
    prony = "".join(f", g{i + 1} = {t['g']:.3g} at tau{i + 1} = {t['tau_s']:.3g} s"
                    for i, t in enumerate(p.get("prony") or []))
    click.echo(f"{model}: " + ", ".join(f"{k} = {v:.5g}" for k, v in p.items() if isinstance(v, float)) + prony
               + f"; rmse {res['metrics'].get('rmse_n', res['metrics'].get('rmse_pa')):.4g}; wrote {Path(out) / 'fit.json'}")


@cli.command("calibrate")
@click.argument("config", required=False, type=click.Path(dir_okay=False))
@click.option("--images", help="One camera's calibration views: a folder, a glob, a video or an image stack.")
@click.option("--pattern", type=click.Choice(["chessboard", "circles", "asymmetric-circles", "charuco"]),
              help="Calibration target.")
@click.option("--grid", help="COLSxROWS: inner corners (chessboard), circles (grids), squares (ChArUco).")
@click.option("--spacing-mm", type=click.FloatRange(min=0, min_open=True), help="Square size or circle spacing (mm).")
@click.option("--view", "view", multiple=True,
              help="NAME=DIR: a camera's own views (repeat per C-arm); or NAME alone to name the --images camera.")
@click.option("--stereo", "stereo", multiple=True,
              help="NAME=DIR twice: frames seen by both cameras at once (same file names).")
@click.option("--loop/--no-loop", default=None, help="Grow the distortion model where the residual asks (default on).")
@click.option("--polarity", type=click.Choice(["dark", "bright"]), help="Circle grids: beads dark (X-ray, default) or bright.")
@click.option("--diameter-px", type=click.FloatRange(min=0, min_open=True), help="Circle grids: bead diameter (px).")
@click.option("--marker-mm", type=click.FloatRange(min=0, min_open=True), help="ChArUco: marker side (mm).")
@click.option("--dictionary", help="ChArUco: ArUco dictionary (default DICT_4X4_50).")
@click.option("--fix-aspect-ratio", is_flag=True, default=None, help="Keep fx/fy at its initial value 1.")
@click.option("--principal-point", type=click.Choice(["fitted", "field-centre"]),
              help="cx, cy fitted (default), or fixed at the image intensifier's circular field centre.")
@click.option("--subpix-window-px", help="Chessboard: cornerSubPix half window in px, 2-30 (default 11, as "
              "OpenCV's sample), or 'auto' (shrunk below half the corner spacing: more accurate on small boards).")
@click.option("--keep-outlier-views", "reject_outliers", flag_value=False, default=None,
              help="Keep views whose reprojection RMS is an outlier (default: leave them out and report).")
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def calibrate(config, out, **opts) -> None:
    """Calibrate C-arms (cameras) from views of a chessboard, circle/bead grid or ChArUco board."""
    from .commands import calibrate as command

    res = command.run(config, out=out, **opts)
    for name, v in res["views"].items():
        held = (f"held-out {v['heldout_rms_px']:.4f} px (declared model {v['heldout_rms_px_declared_model']:.4f} px)"
                if math.isfinite(v["heldout_rms_px"]) else "no view held out (too few)")
        click.echo(f"{name}: {v['dist_model']}, RMS {v['rms_px']:.4f} px, {held}, {v['n_views']} views"
                   + (f", {len(v['rejected_views'])} left out" if v["rejected_views"] else ""))
        for step in (v.get("loop") or {}).get("steps", []):
            ev = step["evidence"]
            click.echo(f"  loop: {step['effect']}: held-out {ev.get('heldout_rmse_before', float('nan')):.4f} -> "
                       f"{ev.get('heldout_rmse_after', float('nan')):.4f} px")
    if res.get("stereo"):
        s = res["stereo"]
        click.echo(f"stereo {s['views'][0]}-{s['views'][1]}: baseline {s['baseline_mm']:.3f} mm, "
                   f"rotation {s['rotation_deg']:.3f} deg, RMS {s['rms_px']:.4f} px")
    click.echo(f"wrote {Path(out) / 'calibration.json'}")


@cli.command("register")
@click.option("--ct", "ct", required=True, type=click.Path(dir_okay=False),
              help="CT marker coordinates: 3D Slicer .fcsv / .mrk.json, or CSV marker,x_mm,y_mm,z_mm.")
@click.option("--xray", required=True, type=click.Path(dir_okay=False),
              help="X-ray marker positions over time (markers3d.csv from `bsipipe track`).")
@click.option("--reference", "references", multiple=True, required=True,
              help="A skull-fixed reference marker (repeat; at least three).")
@click.option("--frame", type=int, help="Registration frame (default: the first with every reference found).")
@click.option("--scale/--no-scale", default=False, help="Fit a uniform scale as well (default: rigid).")
@click.option("--loop/--no-loop", default=True, help="Close the loop: effects scale, moving-reference, label-swap (default on).")
@click.option("--perturbation-draws", type=click.IntRange(min=0), default=2000, show_default=True,
              help="Re-fits of the perturbation TRE estimate (0: skip).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the perturbation estimate.")
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def register(ct, xray, references, out, **opts) -> None:
    """Register the X-ray frame to the CT frame with reference markers; markers in the CT frame."""
    from .commands import register as command

    res = command.run(ct, xray, references, out=out, **opts)
    moved = f"; moved: {', '.join(res['references']['moved'])}" if res["references"]["moved"] else ""
    click.echo(f"register: {res['model']}, frame {res['frame']}, FRE rms {res['fre_rms_mm']:.4f} mm, "
               f"scale {res['scale']:.6f}{moved}; wrote {Path(out) / 'registration.json'}")


@cli.command("compare")
@click.option("--fe-displacements", required=True, type=click.Path(dir_okay=False),
              help="FE nodal displacements: CSV node,ux_mm,uy_mm,uz_mm, ABAQUS .rpt, CalculiX .dat/.frd, "
                   "or a file meshio reads.")
@click.option("--mesh", required=True, type=click.Path(dir_okay=False),
              help="The FE mesh: ABAQUS .inp or any meshio format (CT/FE frame).")
@click.option("--markers", required=True, type=click.Path(dir_okay=False),
              help="markers_ct.csv from `bsipipe register`.")
@click.option("--frame", type=int, help="Compared frame (default: the frame of peak mean marker displacement).")
@click.option("--marker", "marker_names", multiple=True,
              help="Compare only this marker (repeat; default every marker that is not a reference).")
@click.option("--fe-result", type=int, help="0-based index of the FE result in the file (default: the one at the measured frame's time, from export-fe's deck header or an fe_time_s column; else the largest marker displacement when the frame is the peak; else the last, with a warning).")
@click.option("--length-unit", type=click.Choice(["mm", "m"]), default="mm", show_default=True,
              help="Length unit of the mesh and the FE displacements.")
@click.option("--outside-tol-mm", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Accept markers this far outside the mesh (nearest element surface).")
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def compare(fe_displacements, mesh, markers, out, **opts) -> None:
    """FE displacements at the markers vs measured: Table 1, Table 2, sigma, figure."""
    from .commands import compare as command

    res = command.run(fe_displacements, mesh, markers, out=out, **opts)
    ts = res.get("time_series")
    click.echo(f"compare: {res['n_markers']} markers, frame {res['frame']}, sigma {res['sigma_mm']:.4f} mm"
               + (f"; over the loading history {ts['n_results']} FE results, {len(ts['per_marker'])} markers, sigma "
                  f"{ts['sigma_mm']:.4f} mm" if ts else "") + f"; wrote {Path(out) / 'compare.json'}")


@cli.command("synth")
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def synth(config, out) -> None:
    """Write a seeded twin of the two-C-arm indentation study: calibration views, the
    sequence, the Micro Tester log, CT markers, seeds and the truth (truth.json)."""
    from .commands import synth as command

    res = command.run(config, out=out)
    c, t = res["counts"], res["timing"]
    click.echo(f"{c['calibration_images']} calibration images, {c['sequence_frames']} sequence frames"
               + (f" ({t['render_ms_per_frame']:.0f} ms/frame to render)" if "render_ms_per_frame" in t else "")
               + f"; wrote {Path(out) / 'truth.json'} and {Path(out) / 'synth.json'}")


@cli.command("track")
@click.argument("config", required=False, type=click.Path(dir_okay=False))
@click.option("--view", "view", multiple=True,
              help="NAME=PATH: a view's frames (folder of PNG/TIFF/JPEG, multi-page TIFF, AVI/MP4, DICOM); repeat.")
@click.option("--calibration", type=click.Path(dir_okay=False), help="calibration.json of bsipipe calibrate, or OpenCV's (intrinsics.yml + extrinsics.yml, or one FileStorage file with M1 D1 M2 D2 R T) or Bouguet's toolbox's Calib_Results_stereo.mat; the first --view is camera 1 / left (stereo: 3-D and the loop).")
@click.option("--polarity", type=click.Choice(["dark", "bright", "auto"]),
              help="Markers darker or brighter; auto (default): from the seeds, else from the first frames.")
@click.option("--diameter-px", "diameter_px", multiple=True, metavar="D|NAME=D",
              help="Marker diameter on screen in px, or NAME=D for one view (repeat for each view: C-arms at "
                   "different magnifications); default: estimated per view from the seeds, else the first frames.")
@click.option("--seeds", type=click.Path(dir_okay=False),
              help="seeds.csv view,marker,x_px,y_px in frame 0 (or an XMALab 2-D CSV); default: automatic.")
@click.option("--fps", multiple=True, metavar="F|NAME=F",
              help="Frame rate where frames have no time stamps, or NAME=F for one view (repeat for each view: "
                   "C-arms filming at different rates).")
@click.option("--fps-over-stamps", "fps_over_stamps", is_flag=True, default=None,
              help="Use --fps even where the source has time stamps (a video exported at a container rate that "
                   "is not the acquisition's).")
@click.option("--loop/--no-loop", default=None, help="Close the loop on the triangulation (default on).")
@click.option("--method", type=click.Choice(["gaussian", "centroid", "radial"]), help="Sub-pixel centre (default gaussian; centroid with --parity trackpy).")
@click.option("--parity", type=click.Choice(["none", "trackpy"]),
              help="trackpy: detect exactly as trackpy.locate(diameter, invert=dark) does, to reproduce a trackpy "
                   "user's features (odd --diameter-px, no --seeds; implies --method centroid).")
@click.option("--minmass", type=click.FloatRange(min=0), help="With --parity trackpy: trackpy's minmass (default 0).")
@click.option("--background", type=click.Choice(["edge", "plane"]),
              help="Taken from under a marker before its centre is measured: edge (default: a plane, or a profile "
                   "across a bone's or an instrument's edge where the plane leaves structure) or plane.")
@click.option("--roi", "roi", multiple=True, metavar="REGION|NAME=REGION",
              help="Where markers are looked for: auto (the intensifier's circular field, default), none (the "
                   "whole frame), a circle X,Y,R in px, or a mask image (its non-zero pixels); NAME=REGION for "
                   "one view (repeat; views not named keep auto).")
@click.option("--channel", type=click.IntRange(0, 2), help="Colour frames: use this channel (0 R, 1 G, 2 B).")
@click.option("--lowpass-hz", type=click.FloatRange(min=0, min_open=True),
              help="Also write zero-phase low-passed 3-D trajectories (*_filt columns).")
@click.option("--smooth/--no-smooth", default=None,
              help="Kalman/RTS-smooth the 2-D tracks and triangulate the smoothed centres (default on; raw "
                   "values kept in x_px, y_px and the *_raw 3-D columns).")
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def track(config, out, **opts) -> None:
    """Track markers through X-ray frame sequences; triangulate with a calibration."""
    from .commands import track as command

    obj = click.get_current_context().find_root().obj or {}
    progress = sys.stderr.isatty() and not obj.get("quiet", 0)
    res = command.run(config, out=out, progress=progress, **opts)
    for v, i in res["views"].items():
        n_ev = sum(1 for e in res["events"] if e["view"] == v)
        click.echo(f"{v}: {i['n_frames']} frames, {sum(1 for m in res['markers'].values() if v in m)} markers, "
                   f"{n_ev} events")
    lp = res.get("loop")
    if lp:
        b, f = lp["baseline"], lp["final"]
        click.echo(f"ray gap RMS {b['ray_gap_rms_mm']:.4f} mm, reprojection RMS {b['reprojection_rms_px']:.3f} px "
                   f"({b['model']})")
        for s in lp.get("steps", []):
            extra = ""
            if s["effect"] == "view-time-offset":
                extra = f", offset {s['params'].get('view_time_offset_s', float('nan')):+.4f} s"
            elif s["effect"] == "frame-shift":
                fs = s["params"].get("frame_shifts") or {}
                extra = ", " + ", ".join(f"{v} {i.get('n_frames', 0)} frames shifted ({i.get('rms_px', 0.0):.2f} px RMS)"
                                         for v, i in fs.items())
            elif s["effect"] == "view-clock-drift":
                extra = (f", offset {s['params'].get('view_time_offset_s', float('nan')):+.4f} s at the first frame, "
                         f"B's frame interval {100 * s['params'].get('view_clock_drift', float('nan')):+.3f} % "
                         f"against A's")
            click.echo(f"  loop: {s['effect']}{extra}: ray gap RMS {s['ray_gap_rms_mm_before']:.4f} -> "
                       f"{s['ray_gap_rms_mm_after']:.4f} mm, reprojection RMS {s['reprojection_rms_px_before']:.3f} -> "
                       f"{s['reprojection_rms_px_after']:.3f} px")
        click.echo(f"final: {f['model']}, ray gap RMS {f['ray_gap_rms_mm']:.4f} mm, reprojection RMS "
                   f"{f['reprojection_rms_px']:.3f} px")
    sm = res.get("smoothing")
    if sm and sm["tracks"]:
        import numpy as np
        raw = np.median([t["raw_sd_px"] for t in sm["tracks"]])
        smo = np.median([t["smooth_sd_px"] for t in sm["tracks"]])
        gap = (f"; ray gap RMS {sm['ray_gap_rms_mm']:.4f} mm (raw {sm['ray_gap_rms_mm_raw']:.4f})"
               if sm.get("ray_gap_rms_mm") is not None else "")
        sc = (sm.get("stereo_check") or {}).get("markers") or {}
        up = [m for m, r in sc.items() if r["scale_smooth"] > 1.0]
        chk = (f"; stereo check: sd scaled up for {len(up)} of {len(sc)} markers "
               f"(up to x{max(r['scale_smooth'] for r in sc.values()):.3g})" if up else
               ("; stereo check: sd consistent with the ray gaps" if sc else ""))
        click.echo(f"smoothed {len(sm['tracks'])} tracks: median centre sd {raw:.3f} -> {smo:.3f} px{gap}{chk}")
    click.echo(f"wrote {Path(out) / 'track.json'}")


@cli.command("study")
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("-o", "--out", type=click.Path(file_okay=False), help="Output folder (default: the config's `out`).")
@click.option("--force", is_flag=True, help="Redo the selected stages even when they are up to date.")
@click.option("--stage", "stages", multiple=True,
              help="Run only this stage (NAME, or TRIAL/NAME; repeat); the stages it reads must have run.")
@click.option("--trial", "trials", multiple=True, help="Run only this trial (repeat).")
@click.option("-j", "--jobs", type=click.IntRange(min=1), help="Stages run at once (default: the usable cores).")
@handle_errors
def study(config, out, force, stages, trials, jobs) -> None:
    """Run a study (every stage of every trial): only what changed since its last complete run."""
    from .commands import study as command

    obj = click.get_current_context().find_root().obj or {}
    command.run(config, out=out, force=force, stages=stages, trials=trials, jobs=jobs,
                echo=lambda s: click.echo(s), tracebacks=bool(obj.get("verbose")))


@cli.command("export-fe")
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@handle_errors
def export_fe(config, out) -> None:
    """Write the FE hand-off for ABAQUS (runs in CalculiX), LS-DYNA and FEBio: material, indentor
    trajectory (log and X-ray), interface springs, force target, markers and a manifest."""
    from .commands import export_fe as command

    res = command.run(config, out=out)
    d = res["trajectory"]["difference"]["during_contact"]
    s = res["springs"]["deck"]
    click.echo(f"indentor: contact at log {res['indentor']['contact']['log_time_s']:.3f} s, depth "
               f"{res['indentor']['depth_mm']:.3f} mm, {res['indentor']['speed_mm_per_min']:.3f} mm/min; "
               + ("log vs X-ray n/a" if d is None
                  else f"log vs X-ray RMS {d['rms_mm']:.4f} mm, max {d['max_mm']:.4f} mm")
               + (f"; {s['n_springs']} springs of {s['per_spring_n_per_mm']:.5g} N/mm"
                  if res["springs"]["lumping"] == "uniform" else
                  f"; {s['n_springs']} springs of {s['in_decks_n_per_mm']['min']:.5g}-{s['in_decks_n_per_mm']['max']:.5g} "
                  "N/mm (tributary areas)")
               + f"; wrote {Path(out) / 'manifest.json'}")


#: First threshold of the cyclic garbage collector in a command's process (Python's default: 700).
GC_FIRST_THRESHOLD = 20_000


def main() -> None:
    """The ``bsipipe`` executable.

    The cyclic garbage collector is tuned for a short-lived process that imports a lot:
    importing numpy, pandas, scipy and matplotlib creates about a million objects that live
    to the end, and with the default first threshold (a collection every 700 new container
    objects) the collector walks them again and again, then once more at exit.  A first
    threshold of :data:`GC_FIRST_THRESHOLD` collects as surely (cyclic garbage is still
    freed, every 20,000 allocations instead of 700), and freezing what is alive when the
    command returns spares the exit's walks (the process ends; the system takes the memory
    back).  Measured on ``bsipipe track``, 2 x 200 frames of the bench twin: about 0.5 s of
    4.4 s wall time, the same share of CPU.  Tests calling :data:`cli` directly keep
    Python's defaults."""
    import gc

    gc.set_threshold(GC_FIRST_THRESHOLD, *gc.get_threshold()[1:])
    try:
        cli(prog_name="bsipipe")
    finally:
        gc.freeze()


if __name__ == "__main__":
    main()
