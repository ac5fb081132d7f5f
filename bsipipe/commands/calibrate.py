"""``bsipipe calibrate``: calibration views of a target -> calibration.json, MayaCam files and
residual figures.

Forms (CONTRACTS.md)::

    bsipipe calibrate --images GLOB_OR_DIR --pattern P --grid COLSxROWS --spacing-mm S [--view NAME] -o DIR
    bsipipe calibrate --view NAME=DIR [--view NAME=DIR ...] [--stereo NAME=DIR --stereo NAME=DIR] ... -o DIR
    bsipipe calibrate CONFIG.yaml -o DIR

Each camera (C-arm, "view" in the contract) is calibrated from its own views plus its
``--stereo`` frames; a view whose target is not found, or whose reprojection RMS is an
outlier, is left out and listed with the reason under ``rejected_views``.  The loop
(:mod:`bsipipe.imaging.calibration_effects`) may grow each camera's distortion model.  Two
``--stereo`` folders give the extrinsics from frames with the same file name.

Exit 2 (besides invalid options): an image whose size or pixel type differs from the one
most of a camera's images have (named); a ``--grid`` smaller than the chessboard when that
leaves fewer than 3 views (the board's size named).  ``warnings``: ``poor-coverage`` and
``large-rms`` (a camera's or the stereo pair's RMS over
:data:`bsipipe.imaging.calibrate.LARGE_RMS_PX`, 2 px).

Writes ``DIR/calibration.json`` (last), ``DIR/mayacam_<NAME>.txt`` (MayaCam 2.0, world frame =
the target in the first shared stereo frame, else in the camera's first view) and
``DIR/residuals_<NAME>.png`` (the residual field over the detector, all views pooled).
"""

from __future__ import annotations

import copy
import logging
import math
import os
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
from pydantic import Field, PositiveFloat, ValidationInfo, field_validator

from ..config import StrictModel, load_config, validate
from ..errors import InputError, ProcessingError
from ..quality import listed

log = logging.getLogger(__name__)


class CalibrateConfig(StrictModel):
    """``bsipipe calibrate CONFIG.yaml``; paths are relative to the config file's folder."""

    pattern: Literal["chessboard", "circles", "asymmetric-circles", "charuco"]
    grid: str = Field(description="COLSxROWS: inner corners (chessboard), circles, or squares (ChArUco)")
    spacing_mm: PositiveFloat = Field(description="square size or circle spacing, mm")
    images: str | None = Field(None, description="one camera's views: a folder, glob, video or stack")
    view_name: str = Field("cam1", description="name of the camera given by `images`")
    views: dict[str, str] = Field(default_factory=dict, description="camera name -> its own calibration views")
    stereo: dict[str, str] = Field(default_factory=dict, description="camera name -> frames shared with the other camera")
    loop: bool = True
    polarity: Literal["dark", "bright"] = Field("dark", description="circle grids: beads dark (X-ray) or bright")
    diameter_px: PositiveFloat | None = Field(None, description="circle grids: bead diameter (estimated if omitted)")
    marker_mm: PositiveFloat | None = Field(None, description="ChArUco: marker side (default 0.75 x square)")
    dictionary: str = Field("DICT_4X4_50", description="ChArUco: ArUco dictionary name")
    fix_aspect_ratio: bool = False
    principal_point: Literal["fitted", "field-centre"] = Field(
        "fitted", description="'fitted': cx, cy fitted; 'field-centre': fixed at the image intensifier's circular "
                              "field centre (physical cx, cy when the views leave them loose; a worse fit)")
    subpix_window_px: int | Literal["auto"] = Field(11, description="chessboard: cornerSubPix half window in px "
                                                   "(2-30; default 11 as OpenCV's sample and Bouguet; 'auto': up to 11, "
                                                   "shrunk below half the corner spacing)")
    reject_outliers: bool = True

    @field_validator("subpix_window_px")
    @classmethod
    def _subpix(cls, v):
        if v != "auto" and not 2 <= v <= 30:
            raise ValueError("must be 2 to 30 px, or 'auto'")
        return v

    @field_validator("grid", mode="before")
    @classmethod
    def _grid_list(cls, v):
        # [COLS, ROWS], as synth's config writes the plate's grid, is COLSxROWS
        if isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool)
                                                                 for x in v):
            return f"{v[0]}x{v[1]}"
        return v

    @field_validator("grid")
    @classmethod
    def _grid(cls, v: str) -> str:
        from ..imaging.gridfind import parse_grid
        parse_grid(v)
        return v

    @field_validator("dictionary")
    @classmethod
    def _dictionary(cls, v: str) -> str:
        # checked whatever the pattern: a misspelt key is an error, not something ignored
        from ..imaging.gridfind import aruco_dictionaries
        names = aruco_dictionaries()
        if v not in names:
            raise ValueError(f"unknown ArUco dictionary {v!r}; OpenCV's are: {', '.join(names)}")
        return v

    @field_validator("marker_mm")
    @classmethod
    def _marker_in_square(cls, v, info: ValidationInfo):
        spacing = info.data.get("spacing_mm")  # validated before (field order)
        if v is not None and spacing is not None and v >= spacing:
            raise ValueError(f"the marker ({v:g} mm) must be smaller than the ChArUco square, spacing_mm "
                             f"({spacing:g} mm): the marker sits inside a white square")
        return v


def _parse_pairs(values: Sequence[str], option: str) -> tuple[dict[str, str], list[str]]:
    """``NAME=PATH`` pairs and bare names of a repeated option."""
    pairs: dict[str, str] = {}
    bare: list[str] = []
    for v in values:
        if "=" in v:
            name, path = v.split("=", 1)
            if not name or not path:
                raise InputError(f"{option} expects NAME=DIR, got {v!r}")
            if name in pairs:
                raise InputError(f"{option} names {name!r} twice")
            pairs[name] = path
        else:
            bare.append(v)
    return pairs, bare


def build_config(config_path=None, *, images=None, pattern=None, grid=None, spacing_mm=None, view=(), stereo=(),
                 loop=None, **options) -> CalibrateConfig:
    """Options over the config file; the command-line forms mapped onto one config."""
    data: dict = {}
    base_dir = None
    if config_path is not None:
        cfg0 = load_config(CalibrateConfig, config_path)
        data = cfg0.model_dump()
        base_dir = Path(config_path).resolve().parent
    view_pairs, view_bare = _parse_pairs(view, "--view")
    stereo_pairs, stereo_bare = _parse_pairs(stereo, "--stereo")
    if stereo_bare:
        raise InputError(f"--stereo expects NAME=DIR, got {stereo_bare[0]!r}")
    if len(view_bare) > 1:
        raise InputError("--view NAME (without =DIR) names the camera of --images and may be given once")
    if view_bare and images is None:
        raise InputError(f"--view {view_bare[0]} without =DIR needs --images")
    if images is not None:
        data["images"] = images
        if view_bare:
            data["view_name"] = view_bare[0]
    if view_pairs:
        data["views"] = {**data.get("views", {}), **view_pairs}
    if stereo_pairs:
        data["stereo"] = {**data.get("stereo", {}), **stereo_pairs}
    for k, v in (("pattern", pattern), ("grid", grid), ("spacing_mm", spacing_mm), ("loop", loop)):
        if v is not None:
            data[k] = v
    for k, v in options.items():
        if v is not None:
            data[k] = v
    cfg = validate(CalibrateConfig, data, source=config_path or "command line")
    if base_dir is not None:  # config paths are relative to the config's folder
        def fix(p):
            return p if p is None or os.path.isabs(p) else str(base_dir / p)
        cfg = cfg.model_copy(update={"images": fix(cfg.images),
                                     "views": {k: fix(v) for k, v in cfg.views.items()},
                                     "stereo": {k: fix(v) for k, v in cfg.stereo.items()}})
    if cfg.images is None and not cfg.views and not cfg.stereo:
        raise InputError("nothing to calibrate: give --images, --view NAME=DIR or --stereo NAME=DIR")
    if cfg.images is not None and cfg.view_name in cfg.views:
        raise InputError(f"camera {cfg.view_name!r} is given both by --images and --view")
    if cfg.stereo and len(cfg.stereo) != 2:
        raise InputError(f"--stereo needs exactly two cameras (NAME=DIR twice, or two entries under the config's "
                         f"'stereo'), got {len(cfg.stereo)}: {', '.join(cfg.stereo)}", path=config_path,
                         key="stereo" if config_path else None)
    for name in [cfg.view_name, *cfg.views, *cfg.stereo]:
        # a camera's name names its files (mayacam_NAME.txt, residuals_NAME.png)
        if not name or any(c in name for c in "/\\") or name in (".", ".."):
            raise InputError(f"camera name {name!r} cannot name a file (mayacam_<name>.txt): no / or \\",
                             path=config_path)
    return cfg


def _detect_source(path: str, cfg: CalibrateConfig, kind: str, size: list, views: dict, rejected: dict,
                   frames: dict | None, sizes: dict, mismatches: dict, seen: dict, copies: dict, spacings: dict):
    """Detect the target in every frame of one source; fill ``views`` / ``rejected`` / ``frames``,
    ``sizes`` (key -> ((w, h), file, frame index)) and ``mismatches`` (key -> the board size a
    view shows when ``--grid`` does not fit it, or None).  ``seen`` (digest of the pixels ->
    key) holds the camera's images so far: an image identical to an earlier one (a file copied,
    a folder given as --view and --stereo) is one view, not two; it is left out of the
    camera's views (rejected, and in ``copies``: key -> the first's key) and still pairs as a
    stereo frame.  ``spacings`` (key -> (cornerSubPix half window, least corner spacing)) for
    chessboards."""
    import glob
    import hashlib
    from ..imaging.gridfind import DetectionFailed, GridDetection, GridMismatch, find_target, parse_grid
    from ..imaging.calibrate import ViewData
    from ..io.images import iter_frames, list_image_files

    grid = parse_grid(cfg.grid)
    kw = {}
    if cfg.pattern in ("circles", "asymmetric-circles"):
        kw = {"polarity": cfg.polarity, "diameter_px": cfg.diameter_px}
    elif cfg.pattern == "charuco":
        kw = {"marker_mm": cfg.marker_mm, "dictionary": cfg.dictionary}
    ambiguous = False
    from ..imaging.gridfind import field_centre
    # the file each frame came from, for messages: a folder's or a glob's own file, else the
    # source itself (a stack, a video, a multi-frame DICOM)
    files = {f.name: str(f) for f in list_image_files(path)} if os.path.isdir(path) or glob.has_magic(str(path)) \
        else {}
    for fr in iter_frames(path, check_size=False):  # sizes checked over the whole camera: _check_sizes
        if size[2] is None:
            size[2] = field_centre(fr.image) or "none"
        h, w = fr.image.shape
        key = fr.name if kind == "view" else f"stereo/{fr.name}"
        sizes[key] = ((w, h), files.get(fr.name, path), fr.index, fr.image.dtype)
        if size[0] is None:
            size[0], size[1] = (w, h), f"{path}: {fr.name}"
        digest = hashlib.sha1(np.ascontiguousarray(fr.image).tobytes()).hexdigest()
        first = seen.setdefault(digest, key)
        if first != key:               # the first is in views, or rejected: detected already
            rejected[key] = f"the same image as {first} (identical pixels): counted once"
            copies[key] = first
            if frames is not None and first in views:
                frames[fr.name] = views[first]
            continue
        try:
            if cfg.pattern == "chessboard":
                from ..imaging.gridfind import find_chessboard
                det: GridDetection = find_chessboard(fr.image, grid, cfg.spacing_mm, subpix_half_window=cfg.subpix_window_px)
            else:
                det = find_target(fr.image, cfg.pattern, grid, cfg.spacing_mm, **kw)
        except DetectionFailed as e:
            if isinstance(e, GridMismatch):
                mismatches[key] = None if e.found is None else (e.pattern or cfg.pattern, e.found)
            rejected[key] = f"detection failed: {e}"
            log.info("calibrate: %s: %s", key, rejected[key])
            continue
        ambiguous |= det.ambiguous
        if "corner_spacing_min_px" in det.info:
            spacings[key] = (det.info["subpix_half_window_px"], det.info["corner_spacing_min_px"])
        v = ViewData(key, det.image_points, det.object_points, det.ids)
        views[key] = v
        if frames is not None:
            frames[fr.name] = v
    return ambiguous


def _coverage(name: str, sources, points_px):
    """Coverage of the field of view by one camera's detected points, and its warning (or None)
    (:func:`bsipipe.quality.coverage_warning`); the field is found in the camera's first image."""
    from ..io.images import iter_frames
    from ..quality import coverage_warning

    first = next(iter(iter_frames(sources[0][1])))
    return coverage_warning(name, points_px, first.image, logger=log)


#: A local-distortion field is warned about where the target's points cover less of the field.
LOCAL_COVERAGE_MIN = 0.9


def _local_field_extrapolated(name: str, camera, points_px, coverage: dict) -> dict | None:
    """A ``local-distortion-extrapolated`` warning where the camera's model holds a
    local-distortion field (a spline through the residuals, :class:`LocalField`) and the
    target's points cover under :data:`LOCAL_COVERAGE_MIN` of the field: beyond them the spline
    only extrapolates (on the probe's local-distortion twin, 74 % covered, the model was 3.0 px
    off at the field's edge, unsaid).  Gives the field's largest displacement inside the points'
    hull and on the field's rim beyond it."""
    local = getattr(camera, "local", None)
    frac = coverage.get("hull_fraction", 1.0)
    if local is None or not frac < LOCAL_COVERAGE_MIN:
        return None
    from matplotlib.path import Path as _Path
    from scipy.spatial import ConvexHull, QhullError

    from ..quality import warning

    fov = coverage.get("field_of_view") or {}
    centre, radius = fov.get("centre_px"), fov.get("radius_px")
    if not (centre and radius):
        w, h = camera.image_size
        centre, radius = (0.5 * (w - 1), 0.5 * (h - 1)), 0.5 * min(w, h)
    a = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
    rim = np.column_stack([centre[0] + 0.97 * radius * np.cos(a), centre[1] + 0.97 * radius * np.sin(a)])
    pts = np.asarray(points_px, float)
    try:
        hull = _Path(pts[ConvexHull(pts).vertices])
    except QhullError:
        return None
    out = rim[~hull.contains_points(rim)]
    if not len(out):
        return None
    inside = float(np.hypot(*local(pts).T).max())
    beyond = float(np.hypot(*local(out).T).max())
    return warning(
        "local-distortion-extrapolated",
        f"calibrate: {name}: the local-distortion field is fitted where the target's points are ({100 * frac:.0f} % "
        f"of the field): up to {inside:.2g} px there, and {beyond:.2g} px on the field's rim beyond them, where the "
        "spline only extrapolates: points tracked there carry the model's error; views with the plate out to the "
        "field's edge pin it down", logger=log, view=name, hull_fraction=frac, local_max_inside_px=inside,
        local_max_rim_px=beyond)


def _check_sizes(sizes: dict) -> tuple[int, int]:
    """The image size of one camera: the size (and pixel type) most of its images have, the
    first seen on a tie; an image of another is an error that names it, not the majority.

    ``sizes``: view key -> ((w, h), file, frame index, dtype)."""
    from collections import Counter

    from ..io.images import _depth

    def odd_one(values, what):
        count = Counter(values)
        ref = max(count, key=lambda v: count[v])  # Counter keeps insertion order: ties go to the first seen
        for (wh, path, index, dt), v in zip(sizes.values(), values):
            if v != ref:
                same = [os.path.basename(p) for (_, p, _, _), u in zip(sizes.values(), values) if u == ref]
                like = listed(same, 3)
                got, want = ((f"is {wh[0]}x{wh[1]} px", f"{ref[0]}x{ref[1]} px") if what == "size" else
                             (f"has {_depth(dt)} pixels", _depth(ref)))
                raise InputError(f"image {got}, expected {want} like the camera's other {len(same)} image(s) "
                                 f"({like})", path=path, frame=index)
        return ref

    ref = odd_one([wh for wh, _, _, _ in sizes.values()], "size")
    odd_one([np.dtype(dt) for _, _, _, dt in sizes.values()], "depth")
    return ref


#: :func:`_subpix_window_warning`'s limits: the half window against the corners' typical least
#: spacing, and the camera's reprojection RMS (px) that shows the corners pulled off.
SUBPIX_WINDOW_SPACING_RATIO = 0.5
SUBPIX_WINDOW_RMS_PX = 0.5


def _subpix_window_warning(name: str, cfg: CalibrateConfig, spacings: dict, rms_px: float):
    """A ``subpix-window-large`` warning (or None) where a fixed ``cornerSubPix`` half window
    reaches past half the corners' typical spacing (the median over views of each one's least
    spacing) and the camera's reprojection RMS is over :data:`SUBPIX_WINDOW_RMS_PX`: the window
    holds the neighbouring squares' edges, which pull each corner off.  Measured: OpenCV's left
    views at half size (least spacing 16 px, ratio 0.69) calibrated with RMS 1.36 px and fx
    276 without a word (``auto``: 0.193 px, 269.8); at full size (30 px) 0.408 px; sharp
    rendered boards with 18.6 px (ratio 0.59) fit to 0.277 px with 11 and 0.302 px with auto,
    so a wide window alone is no fault."""
    from ..quality import warning
    if not spacings or cfg.subpix_window_px == "auto" or not rms_px > SUBPIX_WINDOW_RMS_PX:
        return None
    half = max(h for h, _ in spacings.values())
    typical = float(np.median([s for _, s in spacings.values()]))
    if half <= SUBPIX_WINDOW_SPACING_RATIO * typical:
        return None
    return warning("subpix-window-large",
                   f"calibrate: {name}: reprojection RMS {rms_px:.3g} px with a cornerSubPix half window ({half} px) "
                   f"that reaches past half the corners' spacing (typically {typical:.1f} px at the closest in a "
                   "view): neighbouring squares' edges fall in it and pull each corner off; give "
                   "--subpix-window-px auto (just under half the spacing)",
                   logger=log, view=name, half_window_px=half, corner_spacing_px=typical, rms_px=rms_px)


def _rejected_images(sizes: dict, rejected: dict, n: int):
    """``(file, image)`` of the first ``n`` rejected views that can be read again (a still
    image; a stack or video: its first frame), for naming what the user's options miss."""
    from ..io.images import read_image
    for key in [k for k in rejected if k in sizes][:n]:
        _, path, _, _ = sizes[key]
        try:
            img = read_image(path)
        except InputError:
            continue
        yield path, img


def _chessboard_named(name: str, cfg: CalibrateConfig, sizes: dict, rejected: dict, n_probe: int = 3) -> None:
    """No image of a camera shows a ``--grid`` chessboard: the board the first few show, found
    whatever its size (:func:`~bsipipe.imaging.gridfind.chessboard_size`, about a second an
    image), is named in an InputError (exit 2): ``--grid 10x7`` for a board of 10 x 7 squares,
    9 x 6 inner corners, had been exit 1, 'no 10x7 chessboard found'."""
    from ..imaging.gridfind import chessboard_size, parse_grid
    grid = parse_grid(cfg.grid)
    for path, img in _rejected_images(sizes, rejected, n_probe):
        # OpenCV finds a board at least as large as the size it is asked for: asked for the
        # squares (one more than the corners each way) it finds nothing; the corners of the
        # squares counted, then a small board, find the whole board
        found = None
        for probe in ((grid[0] - 1, grid[1] - 1), (3, 3)):
            if min(probe) >= 3:
                found = chessboard_size(img, probe)
                if found is not None:
                    break
        if found is not None and tuple(found) != tuple(grid):
            raise InputError(f"camera {name}: no image shows a {cfg.grid} chessboard; this one's has {found[0]}x"
                             f"{found[1]} inner corners: is it --grid {found[0]}x{found[1]}? (a chessboard's --grid "
                             "counts inner corners, COLSxROWS: one less than its squares)", path=path)


def _polarity_named(name: str, cfg: CalibrateConfig, sizes: dict, rejected: dict, n_probe: int = 3) -> None:
    """No image of a camera shows its bead grid with ``--polarity``: where most of the first
    few show it with the other polarity, an InputError (exit 2) says so; a wrong polarity had
    been exit 1, 'no bright blobs found ... give --diameter-px'."""
    from ..imaging.gridfind import DetectionFailed, find_target, parse_grid
    other = "bright" if cfg.polarity == "dark" else "dark"
    probed = found = 0
    path = None
    for p, img in _rejected_images(sizes, rejected, n_probe):
        probed += 1
        try:
            find_target(img, cfg.pattern, parse_grid(cfg.grid), cfg.spacing_mm, polarity=other,
                        diameter_px=cfg.diameter_px)
        except DetectionFailed:
            continue
        found += 1
        path = path or p
    if probed and 2 * found > probed:
        raise InputError(f"camera {name}: no image shows the {cfg.grid} grid of {cfg.polarity} beads; {found} of the "
                         f"first {probed} show it with {other} beads: is it --polarity {other}?", path=path)


def _grid_mismatch_error(name: str, cfg: CalibrateConfig, mismatches: dict, path: str) -> InputError:
    """Too few views, most of them rejected because ``--grid`` does not fit the board (the
    others not found at all): exit 2 with the board's size most views show."""
    from collections import Counter
    sizes = Counter(f for f in mismatches.values() if f is not None)
    if cfg.pattern != "chessboard":
        (p, (c, r)), n = sizes.most_common(1)[0] if sizes else ((cfg.pattern, (0, 0)), 0)
        hint = (f": {n} of {len(mismatches)} views show a complete {c}x{r} {p} grid: is it --pattern {p} --grid "
                f"{c}x{r}? (circles per row x rows)" if n else "")
        return InputError(f"camera {name}: --pattern {cfg.pattern} --grid {cfg.grid} does not fit the target{hint}",
                          path=path)
    hint = ""
    if sizes:
        (_, (c, r)), n = sizes.most_common(1)[0]
        hint = (f"; the board has {c}x{r} inner corners ({n} of {len(mismatches)} views): is it --grid {c}x{r}? "
                "(a chessboard's --grid counts inner corners, COLSxROWS)")
    else:
        hint = "; the corners found are not a chessboard's of that size (a chessboard's --grid counts inner corners)"
    return InputError(f"camera {name}: --grid {cfg.grid} does not fit the {cfg.pattern}: {len(mismatches)} "
                      f"view(s) show a part of a larger board{hint}", path=path)


#: With ``principal_point: field-centre`` a held-out RMS over this factor of the fitted
#: principal point's is warned about: the C-arm's central ray misses the field centre (on the
#: warped twin it rose 4-12 % at the true centre; a field centre 80 px off tripled it).
ANCHOR_MAX_HELDOUT_RATIO = 1.5


def _principal_point(name: str, free, hf, image_size, centre, cfg: CalibrateConfig, path: str, warnings: list):
    """The principal point's source (config ``principal_point``); returns the calibration kept,
    its held-out error, the ``principal_point`` section and the weak parameters of the fit
    with cx, cy free (:func:`bsipipe.imaging.calibrate.weak_intrinsics`, warned about).

    A narrow field (a C-arm: f about 3,300 px for 1,024) is nearly affine: a shift of the
    principal point is, to first order, a turn of the camera (with the tangential terms taking
    the second-order rest), so a distortion the model lacks (an intensifier's local warp of a
    pixel) moves cx by up to hundreds of pixels and fx by a few per cent while the
    reprojection stays as good.  The two cameras turn together, so the triangulated shape is
    not hurt: measured on the S-distortion twin (cam1 cx 235 px off), 0.0048 mm RMS over a
    50 mm cube after a rigid fit; the camera frame is turned by atan(shift / f), 4.1 deg
    there, which the CT registration takes up.  'fitted' (the default) keeps that;
    'field-centre' fixes cx, cy at the intensifier's circular field centre, where an aligned
    C-arm's central ray meets it, for parameters with their physical meaning (on the twin:
    cx 3.6 px off, frame turned 0.15 deg, at the cost of a worse fit: held-out +4 to +12 %,
    stereo RMS 0.073 -> 0.113 px, shape 0.0067 mm)."""
    from dataclasses import replace as dc_replace

    from ..imaging.calibrate import calibrate_camera, heldout_error, jackknife_std, weak_intrinsics
    from ..quality import warning

    weak = weak_intrinsics(free)
    K = free.camera.camera_matrix
    info: dict = {"source": "fitted", "fitted_px": [float(K[0, 2]), float(K[1, 2])],
                  "field_centre_px": None if centre is None else [float(c) for c in centre]}
    kept, hk = free, hf
    if cfg.principal_point == "field-centre":
        if centre is None:
            raise InputError(f"camera {name}: principal_point 'field-centre' needs an image intensifier's circular "
                             "field, and none was found in the first image", path=path, key="principal_point")
        init = copy.copy(free.camera)
        init.camera_matrix = K.copy()
        init.camera_matrix[0, 2], init.camera_matrix[1, 2] = centre
        spec = dc_replace(free.camera.spec, fix_principal_point=True)
        kept = calibrate_camera(free.views, image_size, spec, init=init, twist_centre_px=free.camera.twist_centre_px)
        kept.flagged = dict(free.flagged)
        folds: list = []
        hk = heldout_error(kept, folds=folds)
        kept.heldout_rms_px, kept.heldout_per_view_rms_px = hk
        kept.std_jackknife = jackknife_std(folds)
        # the parameters of the model delivered: cx, cy are fixed there (the free fit's spread
        # of cx had been warned about, "cx 447.0 moves by +/-4.9 px", for a cx held at 509.1)
        weak = weak_intrinsics(kept)
        info.update(source="field-centre", rms_px={"fitted": free.rms_px, "field_centre": kept.rms_px},
                    heldout_rms_px={"fitted": hf[0], "field_centre": hk[0]},
                    focal_px={"fitted": [float(K[0, 0]), float(K[1, 1])],
                              "field_centre": [float(kept.camera.camera_matrix[0, 0]),
                                               float(kept.camera.camera_matrix[1, 1])]})
        log.info("calibrate: %s: principal point fixed at the field centre (%.1f, %.1f) px (fitted: (%.1f, %.1f)); "
                 "held-out RMS %.4f -> %.4f px", name, centre[0], centre[1], K[0, 2], K[1, 2], hf[0], hk[0])
        if hk[0] > ANCHOR_MAX_HELDOUT_RATIO * hf[0]:
            warnings.append(warning(
                "principal-point-not-at-field-centre",
                f"calibrate: {name}: with cx, cy fixed at the field centre ({centre[0]:.1f}, {centre[1]:.1f}) px the "
                f"held-out RMS rises from {hf[0]:.4f} to {hk[0]:.4f} px, over {ANCHOR_MAX_HELDOUT_RATIO:g}x: the "
                f"C-arm's central ray misses the field centre (fitted: ({K[0, 2]:.1f}, {K[1, 2]:.1f}) px); "
                "principal_point: fitted fits it", logger=log, view=name,
                heldout_rms_px={"fitted": hf[0], "field_centre": hk[0]}))
    if weak:
        f = float(K[0, 0])
        what = ", ".join(f"{k} {w['value_px']:.1f} px moves by +/-{w['std_jackknife_px']:.1f} px when one view is left "
                         f"out (the fit's own std says +/-{w['std_px']:.2f})" for k, w in weak.items())
        pp = {"cx", "cy"} & set(weak)
        shift = math.hypot(*(w["std_jackknife_px"] for k, w in weak.items() if k in pp)) if pp else 0.0
        then = (f"the parameters are uncertain (std_jackknife gives their spread, and a distortion the model lacks or a "
                f"local-distortion field can hold them further off: 60-70 px for cx on the probe's local-distortion "
                f"twin, jackknife 5-10 px), not the 3-D: a shift of the principal point is a turn "
                f"of the camera (here about {np.degrees(np.arctan(shift / f)):.2f} deg per jackknife sd), both cameras "
                "turn together and the triangulated shape is kept; the camera frame turns, which the registration "
                "to CT takes up." if pp else
                "the focal length trades with the views' distances; a stereo baseline calibrated with it takes "
                "the same scale.")
        if cfg.principal_point == "field-centre":
            then += f" cx, cy are fixed at the intensifier's field centre (held-out RMS {hf[0]:.4f} -> {hk[0]:.4f} px)."
        elif pp and centre is not None:
            then += (" For cx, cy with their physical meaning, principal_point: field-centre fixes them at the "
                     "intensifier's field centre (a worse fit).")
        half = float(np.degrees(np.arctan(0.5 * max(image_size) / f)))
        why = (f"a narrow field, f = {f:.0f} px, {half:.1f} deg half-angle, and a distortion the model lacks" if half < 15
               else f"f = {f:.0f} px, {half:.1f} deg half-angle: too few or too alike views, or a distortion the "
                    "model lacks")
        warnings.append(warning(
            "weak-intrinsics", f"calibrate: {name}: {what}: the views do not pin "
            f"{'it' if len(weak) == 1 else 'them'} down ({why}).  {then}", logger=log, view=name, parameters=weak,
            principal_point=info["source"]))
    return kept, hk, info, weak


#: A focal length whose leave-one-view-out spread (std_jackknife) is more than this fraction of
#: it is not determined by the views: a failed calibration (exit 1).  Calibrations of C-arms
#: and of the real chessboard pair spread 0.01-5 %; ten views tilted 1.5 degrees, 26 %.
MAX_FOCAL_SPREAD = 0.15
#: Views whose target planes all lie within this angle of each other leave the focal length
#: undetermined (Zhang's method needs planes that are not parallel).
MIN_PLATE_TURN_DEG = 1.0


def _focal_length_determined(name: str, cal, path: str) -> None:
    """ProcessingError where the views do not determine the focal length: they are too alike
    (nearly parallel to each other, at one distance), so f trades with their distances (ten
    views tilted 1.5 degrees had given fx 1,862 px against a true 3,300, exit 0, the fit's own
    std 0.17 px)."""
    from ..imaging.calibrate import _STD_NAME, LARGE_RMS_PX
    K = np.asarray(cal.camera.camera_matrix, float)
    j = {_STD_NAME.get(k, k): v for k, v in (cal.std_jackknife or {}).items()}
    spread = {k: j[k] / K[i, i] for i, k in ((0, "fx"), (1, "fy")) if k in j and K[i, i] > 0}
    # the plates' normals: all parallel (within MIN_PLATE_TURN_DEG) and f is not determined at
    # all, whatever the leave-one-out spread says (exactly fronto-parallel views: every subset
    # lands on the same wrong f, fx 1674 px for a true 3385, spread 2 %, exit 0)
    import cv2
    normals = [cv2.Rodrigues(np.asarray(r, float).reshape(3, 1))[0][:, 2] for r in (cal.rvecs or [])]
    if len(normals) >= 2 and cal.rms_px <= LARGE_RMS_PX:
        N = np.array(normals)
        turn = float(np.degrees(np.arccos(np.clip(np.abs(N @ N.T), -1.0, 1.0))).max())
        if turn < MIN_PLATE_TURN_DEG:
            raise ProcessingError(f"camera {name}: the views do not determine the focal length: the target's plane "
                                  f"turns by at most {turn:.2g} degrees between the {len(normals)} views (all "
                                  f"parallel: the focal length trades with the distances, fx {K[0, 0]:.0f} px is "
                                  "arbitrary); give views of the target tilted 20-40 degrees in different "
                                  "directions", path=path)
    # views that fit one camera well but do not pin its focal length down; views that do not
    # fit one camera (a large RMS: views of two cameras) are the large-rms warning's
    if spread and max(spread.values()) > MAX_FOCAL_SPREAD and cal.rms_px <= LARGE_RMS_PX:
        k = max(spread, key=spread.get)
        raise ProcessingError(f"camera {name}: the views do not determine the focal length: {k} "
                              f"{K[0, 0] if k == 'fx' else K[1, 1]:.0f} px moves by +/-{j[k]:.0f} px "
                              f"({100 * spread[k]:.0f} %) when one view is left out: the views are too alike (nearly "
                              "parallel to each other, at one distance); give views of the target tilted 20-40 "
                              "degrees in different directions", path=path)


def _same_part_everywhere(name: str, cfg: CalibrateConfig, views: dict):
    """A ``grid-never-whole`` warning (or None) when every view of a bead grid shows the same
    number of points, fewer than ``--grid`` holds: a grid cut off by the field is read as such
    and calibrates, but one cut off the same way in every view is more likely a plate smaller
    than ``--grid`` (its ids are then relative to the corner seen, which stereo pairs rely on)."""
    from ..imaging.gridfind import parse_grid
    from ..quality import warning
    if cfg.pattern not in ("circles", "asymmetric-circles") or len(views) < 3:
        return None
    cols, rows = parse_grid(cfg.grid)
    counts = {len(v.ids) for v in views.values()}
    if len(counts) != 1 or next(iter(counts)) >= cols * rows:
        return None
    n = next(iter(counts))
    return warning("grid-never-whole",
                   f"calibrate: {name}: every one of the {len(views)} views shows {n} of the {cols * rows} points of "
                   f"the {cfg.grid} {cfg.pattern} grid: a grid cut off by the field differs from view to view, so the "
                   "plate is likely smaller than --grid; give its own grid (circles per row x rows)",
                   logger=log, view=name, n_points=n, grid_points=cols * rows)


def _own_views_fit(name: str, views: dict, image_size, spec, centre=None) -> dict | None:
    """For a camera given both --view and --stereo frames (3 or more each): its --view frames'
    intrinsics (the camera's final model, ``spec``, calibrated on them alone), the threshold a
    view of its own keeps under (:func:`outlier_threshold_px` of their RMS) and the median RMS
    of its --stereo frames posed under them (:func:`posed_rms`); else None.  The stereo frames
    disagree with the camera's own where that median is over the threshold: a whole set of
    frames held to the test a single outlier view is held to (the right way round, 0.063-0.072
    px against thresholds of 0.20 on 8 twins; swapped, 0.39-1.01)."""
    import cv2

    from ..imaging.calibrate import calibrate_camera, outlier_threshold_px, posed_rms
    own = [v for k, v in views.items() if not k.startswith("stereo/")]
    shared = [v for k, v in views.items() if k.startswith("stereo/")]
    if len(own) < 3 or len(shared) < 3:
        return None
    try:
        cal = calibrate_camera(own, image_size, spec, twist_centre_px=centre)
    except (ValueError, cv2.error):
        return None
    thr = outlier_threshold_px(list(cal.per_view_rms_px.values()))
    return {"camera": cal.camera, "threshold_px": thr, "stereo_views": shared,
            "stereo_rms_px": float(np.median(posed_rms(cal.camera, shared)))}


def _stereo_frames_belong(name: str, fit: dict, fits: dict, cfg, warnings: list) -> None:
    """The check of :func:`_own_views_fit`: --stereo frames that do not fit the camera's own
    --view frames are another camera's (exit 2 where they fit the other --stereo camera's own
    frames: the two --stereo folders given the wrong way round), or a warning.  Swapped, each
    camera had calibrated with 6 of its 18 views from the other C-arm: fx 39 px off, the stereo
    rotation 177 degrees off, its RMS 0.27 px, exit 0."""
    from ..imaging.calibrate import posed_rms
    from ..quality import warning
    if fit["stereo_rms_px"] <= fit["threshold_px"]:
        return
    for o in [o for o in cfg.stereo if o != name and o in fits]:
        theirs = fits[o]
        mine_there = float(np.median(posed_rms(theirs["camera"], fit["stereo_views"])))
        theirs_here = float(np.median(posed_rms(fit["camera"], theirs["stereo_views"])))
        if (theirs["stereo_rms_px"] > theirs["threshold_px"] and mine_there <= theirs["threshold_px"]
                and theirs_here <= fit["threshold_px"]):
            raise InputError(
                f"the --stereo folders look swapped: the frames given for {name} ({cfg.stereo[name]}) fit {o}'s own "
                f"views (median RMS {mine_there:.3g} px posed with {o}'s intrinsics) and not {name}'s "
                f"({fit['stereo_rms_px']:.3g} px), and those given for {o} fit {name}'s ({theirs_here:.3g} px) and not "
                f"{o}'s ({theirs['stereo_rms_px']:.3g} px): give --stereo {name}=<{name}'s folder> "
                f"--stereo {o}=<{o}'s folder>", path=cfg.stereo[name])
    warnings.append(warning(
        "stereo-frames-disagree",
        f"calibrate: {name}: its --stereo frames do not fit the intrinsics of its --view frames (median RMS "
        f"{fit['stereo_rms_px']:.3g} px posed with them, against {fit['threshold_px']:.3g} px for a view of its own): "
        "frames of another C-arm, or the C-arm moved or was set up otherwise between the two sets; the camera is "
        "calibrated on both, and the outlier test sees only single views", logger=log, view=name,
        stereo_rms_px=fit["stereo_rms_px"], own_threshold_px=fit["threshold_px"]))


def _stereo_names_shared(cfg) -> None:
    """Two --stereo folders of image files whose names have none in common: exit 2 before any
    calibration (frames are paired by file name; it had been exit 1, "no frame seen by both",
    after both cameras were calibrated)."""
    if len(cfg.stereo) != 2:
        return
    from ..io.images import list_image_files
    (a, pa), (b, pb) = cfg.stereo.items()
    if not (os.path.isdir(pa) and os.path.isdir(pb)):
        return
    na, nb = ({q.name for q in list_image_files(p)} for p in (pa, pb))
    if len(na) > 1 and len(nb) > 1 and not na & nb:
        ex = lambda names: ", ".join(sorted(names)[:2])          # noqa: E731
        raise InputError(f"--stereo {a} and {b}: no file name is in both folders ({a}: {ex(na)}, ...; {b}: "
                         f"{ex(nb)}, ...): the frames the two C-arms took at one instant must have the same file "
                         "name in each", path=pb)


def _failures(rejected: dict[str, str], max_reasons: int = 3) -> str:
    """The reasons views failed, each once with the views it applies to (the same wrong
    ``--grid`` fails every view alike)."""
    by: dict[str, list[str]] = {}
    for k, why in rejected.items():
        by.setdefault(why, []).append(k)
    parts = []
    for why, keys in list(by.items())[:max_reasons]:
        names = listed(keys, 3)
        parts.append(f"{names}: {why}")
    if len(by) > max_reasons:
        parts.append(f"{len(by) - max_reasons} other reason(s)")
    return "; ".join(parts)


def run(config_path=None, *, out, images=None, pattern=None, grid=None, spacing_mm=None, view=(), stereo=(),
        loop=None, figures: bool = True, **options) -> dict:
    """The whole command; returns the calibration.json content (already written to ``out``)."""
    import cv2

    from ..imaging.calibrate import (LARGE_RMS_PX, MIN_HELDOUT_VIEWS, ModelSpec, calibrate_with_rejection,
                                     heldout_error, jackknife_std, stereo_calibrate)
    from ..imaging.calibration_effects import close_loop
    from ..imaging.gridfind import parse_grid, target_points
    from ..io.mayacam import format_mayacam
    from ..provenance import ResultSet, provenance
    from ..quality import warning

    cfg = build_config(config_path, images=images, pattern=pattern, grid=grid, spacing_mm=spacing_mm, view=view,
                       stereo=stereo, loop=loop, **options)
    _stereo_names_shared(cfg)
    cameras: dict[str, list[tuple[str, str]]] = {}
    if cfg.images is not None:
        cameras.setdefault(cfg.view_name, []).append(("view", cfg.images))
    for n, p in cfg.views.items():
        cameras.setdefault(n, []).append(("view", p))
    for n, p in cfg.stereo.items():
        cameras.setdefault(n, []).append(("stereo", p))

    spec0 = ModelSpec(fix_aspect_ratio=cfg.fix_aspect_ratio)
    result_views: dict[str, dict] = {}
    loops: dict[str, dict] = {}
    cals: dict = {}
    stereo_frames: dict[str, dict] = {}
    ambiguous_any = False
    warnings: list[dict] = []
    # a view's files of an earlier run into this folder that this run does not calibrate go
    # (calibrate --view left, then --view right: mayacam_left.txt had stayed beside a
    # calibration.json without left)
    rs = ResultSet(out, primary="calibration.json", outputs=("mayacam_*.txt", "residuals_*.png", "opencv_stereo.yml"))
    inputs: list[str] = []
    camera_pixels: dict[str, set] = {}     # camera -> the digests of its images' pixels
    own_fits: dict[str, dict] = {}         # camera -> its --view frames' fit (:func:`_own_views_fit`)
    for name, sources in cameras.items():
        views: dict = {}
        rejected: dict[str, str] = {}
        size: list = [None, None, None]  # (w, h), first image, intensifier field centre
        sizes: dict = {}
        mismatches: dict = {}
        seen: dict = {}         # digest of an image's pixels -> its key
        copies: dict = {}       # an image identical to an earlier one -> that one's key
        spacings: dict = {}     # chessboard view -> (cornerSubPix half window, least corner spacing), px
        for kind, path in sources:
            from ..io.images import list_image_files
            inputs.extend([path] if os.path.isfile(path) else [str(q) for q in list_image_files(path)])
            frames = stereo_frames.setdefault(name, {}) if kind == "stereo" else None
            ambiguous_any |= _detect_source(path, cfg, kind, size, views, rejected, frames, sizes, mismatches, seen,
                                            copies, spacings)
        mine = set(seen)
        for other, theirs in camera_pixels.items():
            if mine and mine <= theirs:
                raise InputError(f"every image of camera {name} is one of camera {other}'s, pixel for pixel (the "
                                 "same folder, or copies of it, given for both): each C-arm needs its own views",
                                 path=sources[0][1])
        camera_pixels[name] = mine

        if copies:
            warnings.append(warning(
                "duplicate-views",
                f"calibrate: {name}: {len(copies)} image(s) identical to another of the camera's (a copied file, or one "
                "folder given twice): each counted once, else they would weigh double and shrink the parameters' "
                "spread: " + listed([f"{k}: {first}" for k, first in copies.items()], 6, sep="; "), logger=log,
                view=name,
                images={k: rejected[k] for k in copies}))
        if sizes:
            size[0] = _check_sizes(sizes)
        if len(views) < 3:
            if not views and not mismatches and cfg.pattern == "chessboard":
                _chessboard_named(name, cfg, sizes, rejected)
            if not views and cfg.pattern in ("circles", "asymmetric-circles"):
                _polarity_named(name, cfg, sizes, rejected)
            if mismatches and 2 * len(mismatches) >= len(rejected):  # --grid does not fit the board
                raise _grid_mismatch_error(name, cfg, mismatches, sources[0][1])
            why = f" ({len(rejected)} failed: {_failures(rejected)})" if rejected else ""
            if len(sizes) - len(copies) < 3:
                # too few images given is the input's fault, not the calibration's
                raise InputError(f"camera {name}: {len(sizes) - len(copies)} image(s) given, calibration needs views "
                                 f"of the target in at least 3 (10 or more at different tilts){why}",
                                 path=sources[0][1])
            raise ProcessingError(f"camera {name}: the target was found in {len(views)} image(s), calibration needs "
                                  f"at least 3{why}", path=sources[0][1])
        image_size = size[0]
        warn = _same_part_everywhere(name, cfg, views)
        if warn:
            warnings.append(warn)
        try:
            centre = None if size[2] == "none" else size[2]
            base = calibrate_with_rejection(list(views.values()), image_size, spec0,
                                            reject_outliers=cfg.reject_outliers, twist_centre_px=centre)
        except (ValueError, cv2.error) as e:
            raise ProcessingError(f"camera {name}: calibration failed: {e}", path=sources[0][1]) from None
        rejected.update(base.rejected)
        if cfg.loop:
            report, final, lp = close_loop(base.views, image_size, base)
            h0 = lp.heldout_detail(spec0)
            hf = lp.heldout_detail(final.camera.spec)
            folds = lp.folds(final.camera.spec)
            loop_dict = report.to_dict()
            loop_dict["baseline"]["heldout_rms_px"] = h0[0]
            loop_dict["final"]["heldout_rms_px"] = hf[0]
            loops[name] = loop_dict
        else:
            final = base
            folds = []
            hf = heldout_error(final, folds=folds)
            h0 = hf
        final.heldout_rms_px, final.heldout_per_view_rms_px = hf
        fit = _own_views_fit(name, views, image_size, final.camera.spec, None if size[2] == "none" else size[2])
        if fit is not None:
            own_fits[name] = fit
            _stereo_frames_belong(name, fit, own_fits, cfg, warnings)
        final.std_jackknife = jackknife_std(folds)
        _focal_length_determined(name, final, sources[0][1])
        if len(final.views) < MIN_HELDOUT_VIEWS:
            warnings.append(warning(
                "few-views",
                f"calibrate: {name}: {len(final.views)} views calibrated, the fewest a camera needs: none can be held "
                "out, so there is no held-out error, no leave-one-view-out spread of the parameters (std_jackknife), "
                "no test for an outlier view, and the loop weighed effects by BIC alone; give 10 or more views of the "
                "target at different tilts and positions", logger=log, view=name, n_views=len(final.views)))
        centre = None if size[2] in (None, "none") else tuple(size[2])
        final, hf, pp_info, _ = _principal_point(name, final, hf, image_size, centre, cfg, sources[0][1],
                                                    warnings)
        final.rejected = rejected
        cals[name] = final
        d = final.to_dict()
        d["heldout_rms_px_declared_model"] = h0[0]
        d["field_centre_px"] = None if size[2] == "none" else list(size[2])
        d["image_size"] = list(image_size)
        if name in loops:
            d["loop"] = loops[name]
            if pp_info["source"] == "field-centre":
                # the loop chose the model with cx, cy free; what is delivered has them fixed
                d["loop"]["final"]["delivered"] = {
                    "principal_point": "field-centre", "rms_px": final.rms_px, "heldout_rms_px": hf[0],
                    "note": "the loop's model with cx, cy fixed at the intensifier's field centre: the numbers above "
                            "are its fit with them free"}
        result_views[name] = d
        log.info("calibrate: %s: %s, RMS %.4f px, held-out %.4f px (declared model %.4f px), %d views, %d left out",
                 name, final.camera.spec.describe(), final.rms_px, hf[0], h0[0], len(final.views), len(rejected))
        warn = _subpix_window_warning(name, cfg, spacings, final.rms_px)
        if warn:
            warnings.append(warn)
        if final.rms_px > LARGE_RMS_PX:
            warnings.append(warning(
                "large-rms", f"calibrate: {name}: reprojection RMS {final.rms_px:.2f} px is over {LARGE_RMS_PX:g} px; "
                "a calibration target is located to a few tenths of a pixel, so the views do not fit one camera "
                "(a wrong --grid or --pattern, views from another camera, mis-ordered points)", logger=log,
                view=name, rms_px=final.rms_px, limit_px=LARGE_RMS_PX))
        d["principal_point"] = pp_info
        pts = np.concatenate([v.image_points for v in final.views])
        d["coverage"], warn = _coverage(name, sources, pts)
        if warn:
            warnings.append(warn)
        warn = _local_field_extrapolated(name, final.camera, pts, d["coverage"])
        if warn:
            warnings.append(warn)
        if figures:
            from ..report.calibration_figure import residual_figure
            res = np.concatenate([final.residuals[v.name] for v in final.views])
            fig = residual_figure(f"{name}: {final.camera.spec.describe()}, {len(final.views)} views", pts, res,
                                  image_size, final.rms_px, hf[0])
            rs.add_figure(f"residuals_{name}.png", fig)

    result: dict = {"views": result_views, "warnings": warnings}
    world: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if len(stereo_frames) == 2:
        a, b = list(cfg.stereo)
        tgt = target_points(cfg.pattern, parse_grid(cfg.grid), cfg.spacing_mm) if cfg.pattern != "charuco" else None
        try:
            st = stereo_calibrate(cals[a].camera, cals[b].camera, (a, b), stereo_frames.get(a, {}),
                                  stereo_frames.get(b, {}), target_all=tgt, ambiguous=ambiguous_any)
        except ValueError as e:
            raise ProcessingError(f"stereo {a}-{b}: {e}", path=cfg.stereo[b]) from None
        result["stereo"] = st.to_dict()
        if st.rejected:
            warnings.append(warning(
                "stereo-pairs-left-out",
                f"calibrate: stereo {a}-{b}: {len(st.rejected)} of the {len(st.rejected) + len(st.frames)} shared "
                "frames left out (a relative pose unlike the other pairs': images not taken together, file names "
                "exchanged or shifted between the folders; or a grid cut off in one image): "
                + "; ".join(f"{n}: {why}" for n, why in st.rejected.items()), logger=log, view=f"{a}-{b}",
                frames=dict(st.rejected)))
        if st.unpaired:
            warnings.append(warning(
                "stereo-unpaired-frames",
                f"calibrate: stereo {a}-{b}: frames without a partner in the other camera are not used for the "
                "stereo extrinsics: " + "; ".join(
                    f"{v}: " + ", ".join(f + (f" (in {o}'s folder, its target not found: "
                                              f"{cals[o].rejected[f'stereo/{f}']})" if f"stereo/{f}" in
                                              (cals[o].rejected or {}) else f" (no {o} file of that name)")
                                         for f in fs)
                    for v, fs in st.unpaired.items() for o in [b if v == a else a]),
                logger=log, view=f"{a}-{b}", frames=dict(st.unpaired)))
        if st.rms_px > LARGE_RMS_PX:
            warnings.append(warning(
                "large-rms", f"calibrate: stereo {a}-{b}: reprojection RMS {st.rms_px:.2f} px is over "
                f"{LARGE_RMS_PX:g} px: the shared frames do not fit the two cameras (frames that were not taken at "
                "the same instant, or a wrong --grid)" + (f"; {st.note}" if st.note else ""), logger=log,
                view=f"{a}-{b}", rms_px=st.rms_px,
                limit_px=LARGE_RMS_PX))
        # world = the target in the first shared frame, seen by camera a
        f0 = st.frames[0]
        va = stereo_frames[a][f0]
        ra, ta = cals[a].camera.solve_pose(va.object_points, va.image_points)
        Ra = cv2.Rodrigues(ra)[0]
        world[a] = (Ra, ta)
        world[b] = (st.R @ Ra, st.R @ ta + st.T_mm)
        result["stereo"]["world_frame"] = f"target in shared frame {f0}"
        result["stereo"]["opencv"] = _opencv_stereo(rs, cals[a].camera, cals[b].camera, st)
    for name, cal in cals.items():
        if name not in world:
            world[name] = (cv2.Rodrigues(cal.rvecs[0])[0], cal.tvecs[0])
            result_views[name]["world_frame"] = f"target in view {cal.views[0].name}"
        R, t = world[name]
        rs.add_text(f"mayacam_{name}.txt", format_mayacam(cal.camera.image_size, cal.camera.camera_matrix, R, t))
        result_views[name]["mayacam"] = f"mayacam_{name}.txt"
    if len(loops) == 1:
        result["loop"] = next(iter(loops.values()))
    elif loops:
        result["loop"] = {"baseline": {n: l["baseline"] for n, l in loops.items()},
                          "steps": [{"view": n, **s} for n, l in loops.items() for s in l["steps"]],
                          "final": {n: l["final"] for n, l in loops.items()},
                          "residual_structure": {n: l["residual_structure"] for n, l in loops.items()}}
    else:
        result["loop"] = None
    result["provenance"] = provenance(cfg, inputs, command="calibrate")
    rs.add_json("calibration.json", result)
    rs.commit()
    return result


def _opencv_stereo(rs, ca, cb, st) -> dict:
    """``opencv_stereo.yml``: the pair in OpenCV's ``cv::FileStorage`` layout (``M1 D1 M2 D2 R T``
    as OpenCV's stereo_calib sample writes them, and ``image_size`` where the two cameras share
    one), for OpenCV-based tools and
    for ``bsipipe track --calibration``; written where both cameras are OpenCV's own model (an
    S-distortion twist or a local field has no place in it: what ``calibration.json`` says
    instead).  Returns the calibration.json note."""
    import cv2
    extra = [n for n, c in (("1", ca), ("2", cb)) if c.twist_rad is not None or c.local is not None]
    if extra:
        return {"written": None, "why": f"camera {' and '.join(extra)} has an S-distortion twist or a local field "
                                         "beyond OpenCV's model: use calibration.json"}
    fs = cv2.FileStorage("opencv_stereo.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    if tuple(ca.image_size) == tuple(cb.image_size):      # one size for the pair, as OpenCV's sample has it
        fs.write("image_size", np.asarray(ca.image_size, np.int32))
    for key, val in (("M1", ca.camera_matrix),
                     ("D1", np.asarray(ca.dist_coeffs, float).reshape(1, -1)), ("M2", cb.camera_matrix),
                     ("D2", np.asarray(cb.dist_coeffs, float).reshape(1, -1)), ("R", np.asarray(st.R, float)),
                     ("T", np.asarray(st.T_mm, float).reshape(3, 1))):
        fs.write(key, np.asarray(val))
    rs.add_text("opencv_stereo.yml", fs.releaseAndGetString())
    return {"written": "opencv_stereo.yml", "layout": "cv::FileStorage: M1 D1 (camera 1), M2 D2 (camera 2), R, T "
                                                       "(x_2 = R x_1 + T, mm), image_size (w, h)"}
