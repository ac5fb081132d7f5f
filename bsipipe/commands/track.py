"""``bsipipe track``: X-ray frame sequences -> 2-D marker tracks, 3-D trajectories, loop.

Forms (CONTRACTS.md)::

    bsipipe track CONFIG.yaml -o DIR
    bsipipe track --view NAME=PATH [--view NAME=PATH ...] [--calibration calibration.json] \\
                  [--polarity dark|bright] [--diameter-px D] [--seeds seeds.csv] [--fps F] -o DIR

Each view's frames are streamed once (:func:`bsipipe.io.images.iter_frames`; twice without seeds
where the first frames' average shows markers too faint for one frame), detected in
search windows around each marker's prediction and matched globally
(:mod:`bsipipe.imaging.track`); without seeds every frame is searched whole and the
detections are linked.  With a calibration the two stereo views are triangulated
(:mod:`bsipipe.imaging.triangulate`) and the loop (:mod:`bsipipe.imaging.track_effects`)
looks for a view time offset or clock drift, a jolting picture, identity swaps, a track held
by a static spot (the only case where frames are read a second time, in windows) and partial
occlusion.

Writes ``DIR/markers2d.csv``, ``DIR/xmalab_2d.csv``, ``DIR/dltdv_xypts.csv``, with a calibration
``DIR/markers3d.csv``, ``DIR/xmalab_3d.csv`` and ``DIR/loop.md``, the figures ``DIR/track.png`` (trajectories)
and ``DIR/overlay.png`` (a frame with the detections), and ``DIR/track.json`` (last).
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Annotated, Literal, Sequence, Union

import numpy as np
import pandas as pd
from pydantic import Field, PositiveFloat, field_validator, model_validator

from ..config import StrictModel, load_yaml, validate
from ..errors import InputError, ProcessingError

log = logging.getLogger(__name__)


class RoiCircle(StrictModel):
    """A circular region of interest in a view's pixels (the keys of track.json's
    ``field_of_view``, so the field an earlier run found can be pasted in and adjusted)."""

    centre_px: tuple[float, float] = Field(description="centre x, y (px)")
    radius_px: PositiveFloat = Field(description="radius (px)")


#: A region of interest: found in the frames ("auto"), none, a circle, or a mask image's path
#: (non-zero pixels are searched; the frames' size).
RoiSpec = Union[Literal["auto", "none"], RoiCircle, str]


class DetectionConfig(StrictModel):
    """Marker detection (see :class:`bsipipe.imaging.detect.DetectionSettings`)."""

    k_sigma: PositiveFloat = Field(5.0, description="threshold in robust sd of the smoothed top-hat (whole frames)")
    window_k_sigma: PositiveFloat = Field(4.0, description="the same in the search windows around seeded markers")
    min_snr: float = Field(3.0, ge=0, description="amplitude / pixel noise a marker needs")
    method: Literal["gaussian", "centroid", "radial"] = Field(
        "gaussian", description="sub-pixel centre; default centroid when parity is trackpy, else gaussian")
    parity: Literal["none", "trackpy"] = Field("none", description="trackpy: detect exactly as trackpy.locate does "
                                               "(method centroid, no seeds; for comparisons with trackpy results)")
    minmass: float = Field(0.0, ge=0, description="parity trackpy: trackpy's minmass")
    max_elongation: float = Field(2.5, ge=1)
    max_sigma_factor: PositiveFloat | None = Field(0.75, description="a fitted Gaussian width above this times the "
                                                   "diameter is not a marker (null: no limit)")
    blur_px: PositiveFloat | None = Field(None, description="marker blur sigma (default max(0.6, d/5))")
    background: Literal["edge", "plane"] = Field(
        "edge", description="what is taken from under a marker before its centre is measured: plane (fitted to the "
                            "ring of pixels around it) or edge (the plane, or where an F test finds structure the "
                            "plane leaves, a profile across one direction: a bone's or an instrument's edge, a line)")
    roi: Union[RoiSpec, dict[str, RoiSpec]] = Field(
        "auto", description="where markers are looked for: auto (the intensifier's circular field, found in the "
                            "first frame), none (the whole frame), a circle {centre_px: [x, y], radius_px: r}, or "
                            "a mask image (its non-zero pixels; the frames' size); or one of these per view "
                            "({cam1: auto, cam2: {centre_px: [512, 500], radius_px: 470}})")

    @model_validator(mode="before")
    @classmethod
    def _parity_method(cls, data):
        # trackpy parity is trackpy's centroid: it is the method unless one is named
        if isinstance(data, dict) and data.get("parity") == "trackpy" and data.get("method") is None:
            data = {**data, "method": "centroid"}
        return data


class TrackingConfig(StrictModel):
    """Tracker (see :class:`bsipipe.imaging.track.TrackSettings`); lengths in px."""

    gate_px: PositiveFloat | None = None
    gate_growth_px: float | None = Field(None, ge=0)
    max_gate_px: PositiveFloat | None = None
    seed_radius_px: PositiveFloat | None = None
    motion: Literal["constant-velocity", "static"] = "constant-velocity"
    memory: int = Field(5, ge=0, description="automatic mode: frames a track may miss")
    max_extrapolation_frames: int = Field(3, ge=0, description="a hidden marker moves on at its last velocity "
                                          "for at most this many frames")
    min_track_frames: int = Field(3, ge=1, description="automatic mode: shorter tracks are dropped")
    frame_shift: bool = Field(True, description="a shift of the whole picture between frames (a jolt of the "
                              "C-arm or the head) is found from the markers and every prediction moved with it "
                              "(a frame-shift event)")
    sweep_every_frames: int = Field(20, ge=1, description="automatic mode: the whole frame is searched for new "
                                    "markers in the first frame, every this many frames and the last (a new one "
                                    "is followed back to where it appeared); in between each track is searched "
                                    "for in its own window")
    back_frames: int = Field(60, ge=0, description="automatic mode: a new marker is followed back through at most "
                             "this many frames (held in memory)")
    merge_px: PositiveFloat | None = Field(None, description="two markers predicted closer than this whose images "
                                           "merge are not measured until they part (status 'merged'); default "
                                           "1.5 diameters")
    merge_extrapolation_frames: int = Field(20, ge=0, description="merged markers move on at their velocities from "
                                            "before for at most this many frames")
    second_look_k_sigma: PositiveFloat | None = Field(
        2.5, description="seeded mode: a marker nothing matched is looked for again in its gate with this window "
                         "threshold (robust sd), taken only if it passes min_snr and has the marker's own amplitude "
                         "and width (status 'weak'); null: no second look")
    second_look_min_snr: PositiveFloat = Field(
        2.0, description="seeded mode: the SNR (amplitude / pixel noise) a second look's candidate needs, at most "
                         "the detector's min_snr: within a pixel of the prediction, with the marker's own amplitude "
                         "and width as the test, a fainter find is safe")


#: A frame rate bsipipe can use (frames/s): a frame in 11 days to a megahertz camera.
FrameRate = Annotated[float, Field(ge=1e-6, le=1e6)]


class TrackConfig(StrictModel):
    """``bsipipe track CONFIG.yaml``; paths are relative to the config file's folder."""

    views: dict[str, str] = Field(min_length=1, description="view name -> frames (folder, TIFF, video, DICOM)")
    calibration: str | None = Field(None, description="calibration.json of `bsipipe calibrate` (stereo for 3-D)")
    seeds: str | None = Field(None, description="seeds.csv view,marker,x_px,y_px (or an XMALab 2-D CSV)")
    polarity: Literal["dark", "bright", "auto"] | dict[str, Literal["dark", "bright", "auto"]] = Field(
        "auto", description="markers darker or brighter than their surroundings, or one per view ({cam1: dark, "
                            "cam2: bright}: one C-arm's video inverted); auto: with seeds, the polarity in which "
                            "more seeded markers are found in the first frame (dark on a tie); without seeds, "
                            "bright only where the first frames hold at least 3 bright markers of SNR 6 or more "
                            "and twice as many as dark ones (beads are dark in raw X-ray frames); a view whose "
                            "own seeds or frames say clearly otherwise keeps its own")
    diameter_px: PositiveFloat | dict[str, PositiveFloat] | None = Field(
        None, description="marker diameter in px, or one per view ({cam1: 4, cam2: 7}: C-arms at different "
                          "magnifications); default estimated per view from the seeds (else from the first frames)")
    fps: FrameRate | dict[str, FrameRate] | None = Field(
        None, description="frame rate where the source has no time stamps (frames/s, 1e-6 to 1e6: a frame in 11 days "
                          "to a megahertz camera; beyond, times in seconds under- or overflow in the clock fits), or "
                          "one per view ({cam1: 2, cam2: 4}: C-arms filming at different rates)")
    fps_over_stamps: bool = Field(False, description="use fps even where the source has time stamps (a video "
                                                     "exported at a container rate of 25 frames/s for a 4 frames/s "
                                                     "acquisition)")
    channel: int | None = Field(None, ge=0, le=2, description="colour frames: use this channel (default luma)")
    loop: bool = True
    lowpass_hz: PositiveFloat | None = Field(None, description="zero-phase low-pass of the 3-D trajectories")
    smooth: bool = Field(True, description="Kalman/RTS-smooth each 2-D track (process noise and error scale by "
                                           "maximum likelihood) and triangulate the smoothed centres; the raw "
                                           "values stay (x_px, y_px; x_mm_raw, ...)")
    max_offset_s: PositiveFloat | None = Field(None, description="search range of the view time offset")
    correct_lag: bool = Field(True, description="frames averaged over time (frames-averaged: image-intensifier lag, "
                                                "a recursive noise filter) in losslessly stored views: markers3d.csv's "
                                                "time_s moved back by the average's lag, rho / (1 - rho) frames")
    max_ray_gap_mm: PositiveFloat | None = Field(0.5, description="flag two-view points whose rays pass further "
                                                 "apart (also any above 5x the sequence's median ray gap)")
    detection: DetectionConfig = DetectionConfig()
    tracking: TrackingConfig = TrackingConfig()
    figures: bool = True

    @field_validator("diameter_px", "fps", "polarity")
    @classmethod
    def _one_per_view(cls, v, info):
        if isinstance(v, dict) and info.data.get("views") is not None:
            views = info.data["views"]
            if info.field_name == "polarity":
                _every_view("a polarity", "polarities", v, views)
            elif info.field_name == "fps":
                # a rate for the views without time stamps only (a stamped video beside a
                # folder of PNGs): the others keep their own times
                unknown = [k for k in v if k not in views]
                if unknown:
                    raise ValueError(f"a frame rate per view names views {', '.join(views)}; {', '.join(unknown)} "
                                     "is none of them")
            else:
                _every_view("a diameter", "diameters", v, views)
        return v

    def polarity_of(self, view: str) -> str:
        """The polarity of ``view`` (one for every view, or its own)."""
        return self.polarity[view] if isinstance(self.polarity, dict) else self.polarity

    def fps_of(self, view: str) -> float | None:
        """The frame rate given for ``view`` (one for every view, or its own)."""
        return self.fps.get(view) if isinstance(self.fps, dict) else self.fps

    @model_validator(mode="after")
    def _rois_per_view(self):
        if isinstance(self.detection.roi, dict):
            _every_view("detection.roi: a region of interest", "regions", self.detection.roi, self.views)
        return self

    @field_validator("views")
    @classmethod
    def _names(cls, v: dict) -> dict:
        for k in v:
            if not k or "," in k or "=" in k:
                raise ValueError(f"bad view name {k!r}")
        return v


def _every_view(what: str, plural: str, given: dict, views) -> None:
    """A value per view (a config's dict) must name every view and only them."""
    if set(given) != set(views):
        raise ValueError(f"{what} per view must give every view and only them: views {', '.join(views)}; "
                         f"{plural} for {', '.join(given)}")


def _parse_views(values: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for s in values:
        if "=" not in s:
            raise InputError(f"--view {s!r}: expected NAME=PATH", key="view")
        k, p = s.split("=", 1)
        k, p = k.strip(), p.strip()
        if not k or not p:
            raise InputError(f"--view {s!r}: expected NAME=PATH", key="view")
        if k in out:
            raise InputError(f"--view {k!r} given twice", key="view")
        out[k] = p
    return out


def _per_view_option(option: str, key: str, form: str, values: Sequence[str], parse, name_of):
    """A command-line option given once for every view (given more than once, the last counts)
    or as ``NAME=FORM`` per view (repeated): ``(value for every view or None, {view: value})``.
    ``name_of(s)``: the view ``s`` names (None: a value for every view); ``parse(text, s)``
    reads a value.  A view given twice, an empty name, or both forms mixed: an error naming
    the option."""
    named: dict = {}
    plain = []
    for s in values:
        k = name_of(s)
        if k is None:
            plain.append(s)
            continue
        if not k:
            raise InputError(f"{option} {s!r}: expected NAME={form}", key=key)
        if k in named:
            raise InputError(f"{option} {k!r} given twice", key=key)
        named[k] = parse(s.split("=", 1)[1].strip(), s)
    if named and plain:
        raise InputError(f"{option}: give one {form} for every view, or NAME={form} for each view, not both",
                         key=key)
    return (parse(plain[-1].strip(), plain[-1]) if plain else None), named


def _parse_positive_per_view(values: Sequence[str], option: str, key: str, form: str, unit: str):
    """``option``: one positive ``form`` for every view, or ``NAME=form`` per view
    (:func:`_per_view_option`); None when not given.  A value that is not a positive number is
    an error naming the option."""
    if not values:
        return None

    def number(text: str, given: str) -> float:
        try:
            x = float(text)
        except ValueError:
            x = math.nan
        if not (math.isfinite(x) and x > 0):
            raise InputError(f"{option} {given!r}: expected a positive number of {unit} ({form}, or NAME={form} for "
                             "one view)", key=key)
        return x

    one, named = _per_view_option(option, key, form, values, number,
                                  lambda s: s.split("=", 1)[0].strip() if "=" in s else None)
    return named or one


def _parse_diameters(values: Sequence[str]) -> float | dict[str, float] | None:
    """``--diameter-px``: one ``D`` for every view, or ``NAME=D`` per view."""
    return _parse_positive_per_view(values, "--diameter-px", "diameter_px", "D", "px")


def _parse_fps(values: Sequence[str]) -> float | dict[str, float] | None:
    """``--fps``: one ``F`` for every view, or ``NAME=F`` per view."""
    return _parse_positive_per_view(values, "--fps", "fps", "F", "frames/s")


def _parse_roi(text: str):
    """One ``--roi`` value: ``auto``, ``none``, a circle ``X,Y,R`` (px) or a mask image's path."""
    t = text.strip()
    if t in ("auto", "none"):
        return t
    parts = t.split(",")
    if len(parts) == 3:
        try:
            x, y, r = (float(a) for a in parts)
        except ValueError:
            pass
        else:
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(r) and r > 0):
                raise InputError(f"--roi {text!r}: a circle is X,Y,R with a positive radius (px)", key="roi")
            return {"centre_px": [x, y], "radius_px": r}
    if not t:
        raise InputError("--roi: empty value (auto, none, X,Y,R or a mask image)", key="roi")
    return t


def _parse_rois(values: Sequence[str], views: dict):
    """``--roi``: one region for every view, or ``NAME=REGION`` per view
    (:func:`_per_view_option`; NAME a view's name: a mask's path may hold an ``=``)."""
    def name_of(s: str) -> str | None:
        k, _, rest = s.partition("=")
        return k.strip() if rest and k.strip() in views else None

    one, named = _per_view_option("--roi", "roi", "REGION", values, lambda text, s: _parse_roi(text), name_of)
    # views not named keep the automatic field
    return {v: named.get(v, "auto") for v in views} if named else one


def build_config(config_path=None, *, view=(), calibration=None, polarity=None, diameter_px=None, seeds=None,
                 fps=None, loop=None, **extra) -> TrackConfig:
    """The validated config: the YAML file (paths relative to it), command-line options win."""
    data: dict = {}
    base = None
    if config_path is not None:
        data = load_yaml(config_path) or {}
        if not isinstance(data, dict):
            raise InputError("expected a mapping of keys to values", path=config_path)
        base = Path(config_path).resolve().parent
    if view:
        data["views"] = _parse_views(view)
    if isinstance(diameter_px, (tuple, list)):           # the command line's --diameter-px values
        diameter_px = _parse_diameters(diameter_px)
    if isinstance(fps, (tuple, list)):                   # the command line's --fps values
        fps = _parse_fps(fps)
    roi = extra.pop("roi", None)
    if isinstance(roi, (tuple, list)):                   # the command line's --roi values
        roi = _parse_rois(roi, data.get("views") or {}) if roi else None
    if roi is not None:
        data.setdefault("detection", {})["roi"] = roi
    for k, v in (("calibration", calibration), ("polarity", polarity), ("diameter_px", diameter_px),
                 ("seeds", seeds), ("fps", fps), ("loop", loop)):
        if v is not None:
            data[k] = v
    for k, v in extra.items():
        if v is None:
            continue
        if k in ("method", "parity", "minmass", "k_sigma", "min_snr", "background"):
            data.setdefault("detection", {})[k] = v
        else:
            data[k] = v
    if "views" not in data:
        raise InputError("no views: give --view NAME=PATH (or a config with 'views')", path=config_path, key="views")
    cfg = validate(TrackConfig, data, source=config_path)
    if base is not None:
        def fix(p):
            return None if p is None else str(p if os.path.isabs(p) else base / p)
        roi = map_roi_masks(cfg.detection.roi, fix)
        cfg = cfg.model_copy(update={"views": {k: fix(v) for k, v in cfg.views.items()},
                                     "calibration": fix(cfg.calibration), "seeds": fix(cfg.seeds),
                                     "detection": cfg.detection.model_copy(update={"roi": roi})})
    return cfg


def _is_mask(r) -> bool:
    """Whether a region of interest is a mask image's path (any string but auto and none)."""
    return isinstance(r, str) and r not in ("auto", "none")


def map_roi_masks(roi, fn):
    """A ``detection.roi`` value (validated or as read from YAML) with each mask image's path
    passed through ``fn``: one region for every view, or a dict of them per view."""
    if isinstance(roi, dict) and "radius_px" not in roi:          # per view (not a circle's keys)
        return {k: map_roi_masks(r, fn) for k, r in roi.items()}
    return fn(roi) if _is_mask(roi) else roi


def roi_masks(roi) -> list[str]:
    """The mask images' paths a ``detection.roi`` value names."""
    vals = roi.values() if isinstance(roi, dict) and "radius_px" not in roi else [roi]
    return [r for r in vals if _is_mask(r)]


def _roi_per_view(cfg) -> dict:
    """``detection.roi`` per view (the same for every view unless given per view)."""
    r = cfg.detection.roi
    return dict(r) if isinstance(r, dict) else {v: r for v in cfg.views}


def _given_roi(cfg) -> bool:
    """Whether some view's region of interest is given (a circle or a mask), not auto or none."""
    return any(not isinstance(r, str) or r not in ("auto", "none") for r in _roi_per_view(cfg).values())


def _resolve_rois(cfg, shapes: dict, config_path) -> dict:
    """Each view's region of interest for the tracker: "auto", "none", or a
    :class:`~bsipipe.imaging.detect.FieldOfView` built from a given circle or mask image (the
    config names every view: :meth:`TrackConfig._rois_per_view`).  A circle outside the frame,
    a mask of another size than the frames or with no pixel set: an error naming the file or
    key."""
    from ..imaging.detect import FieldOfView
    from ..io.images import iter_frames
    out = {}
    for v, r in _roi_per_view(cfg).items():
        shape = shapes.get(v)
        if isinstance(r, str) and r in ("auto", "none"):
            out[v] = r
            continue
        if shape is None:             # a view without frames: reported later
            out[v] = "none"
            continue
        h, w = int(shape[0]), int(shape[1])
        if isinstance(r, RoiCircle):
            cx, cy = (float(a) for a in r.centre_px)
            # the frame's nearest pixel to the centre must lie inside the circle
            nx, ny = min(max(cx, 0.0), w - 1.0), min(max(cy, 0.0), h - 1.0)
            if not (math.isfinite(cx) and math.isfinite(cy)) or math.hypot(nx - cx, ny - cy) >= r.radius_px:
                raise InputError(f"view {v!r}: the region of interest (circle at {cx:g}, {cy:g}, radius "
                                 f"{r.radius_px:g} px) holds no pixel of its {w}x{h} px frames", path=config_path,
                                 key="detection.roi")
            out[v] = FieldOfView((h, w), (cx, cy), float(r.radius_px), found=True, given=True)
            continue
        if not os.path.isfile(r):
            raise InputError(f"view {v!r}: region of interest mask: no such file", path=r, key="detection.roi")
        fr = next(iter(iter_frames(r)), None)
        if fr is None:
            raise InputError(f"view {v!r}: region of interest mask: no image in the file", path=r)
        m = np.asarray(fr.image) != 0
        if m.shape != (h, w):
            raise InputError(f"view {v!r}: the region of interest mask is {m.shape[1]}x{m.shape[0]} px, the "
                             f"view's frames {w}x{h} px", path=r)
        if not m.any():
            raise InputError(f"view {v!r}: the region of interest mask selects no pixel (non-zero pixels are "
                             "searched)", path=r)
        out[v] = FieldOfView((h, w), region=m, given=True)
    return out


def _seeds_outside(seed_df: pd.DataFrame, rois: dict) -> list[tuple[str, str, float, float]]:
    """Seeds outside their view's given region of interest, as ``(view, marker, x, y)``."""
    from ..imaging.detect import FieldOfView
    out = []
    for v, g in seed_df.groupby("view", sort=False):
        fov = rois.get(v)
        if not isinstance(fov, FieldOfView):
            continue
        xy = g[["x_px", "y_px"]].to_numpy(float)
        for name, (x, y), ok in zip(g["marker"], xy, fov.contains(xy)):
            if not ok:
                out.append((v, str(name), float(x), float(y)))
    return out


#: Frames read past a blank first frame for one with a picture (:func:`_first_frames`).
BLANK_LOOKAHEAD = 10


def _first_frames(views: dict, channel) -> tuple[dict, dict]:
    """Each view's first frame with a picture, decoded once for the seeds' check, the
    polarity and the diameter (None when it has no frame: reported later), and the views
    whose first frame was blank (:func:`~bsipipe.imaging.detect.is_blank`): view -> the frame
    used instead, the first of the next :data:`BLANK_LOOKAHEAD` with a picture (frame 0 when
    none has one)."""
    from itertools import chain, islice

    from ..imaging.detect import is_blank
    from ..io.images import iter_frames
    out, blank = {}, {}
    for v, p in views.items():
        it = iter(iter_frames(p, channel=channel))
        fr = next(it, None)
        out[v] = None if fr is None else fr.image
        # the second frame too: a first file of another size (a thumbnail that sorts first) is
        # named as such here, before the calibration or the seeds are checked against it
        second = next(it, None)
        if fr is not None and is_blank(fr.image):
            it = chain([second], it) if second is not None else it
            for k, nxt in enumerate(islice(it, BLANK_LOOKAHEAD), start=1):
                if not is_blank(nxt.image):
                    out[v], blank[v] = nxt.image, k
                    break
            else:
                blank[v] = 0
    return out, blank


def _seeds_together(seeds: pd.DataFrame, diameters: dict) -> list[tuple]:
    """Pairs of seeds of one view within half a marker diameter of each other, as
    ``(view, marker, marker, distance_px, limit_px)``: one marker clicked twice under two
    names, or two markers whose images overlap in that view's first frame."""
    out = []
    for v, g in seeds.groupby("view", sort=False):
        xy = g[["x_px", "y_px"]].to_numpy(float)
        if len(xy) < 2:
            continue
        lim = 0.5 * float(diameters.get(v) or 4.0)
        dd = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        for i, j in zip(*np.nonzero(np.triu(dd < lim, 1))):
            out.append((v, str(g["marker"].iloc[i]), str(g["marker"].iloc[j]), float(dd[i, j]), lim))
    return out


def _read_calibration(path, views: Sequence[str], shapes: dict | None = None):
    """The calibrated pair's view geometries, its two views (in ``views``' order) and the
    calibration's own stereo reprojection RMS (px; None where the file has none).  ``path``:
    ``bsipipe calibrate``'s calibration.json, or OpenCV's or Bouguet's toolbox's stereo results
    (:func:`~bsipipe.io.stereo_calibration.read_stereo_calibration`; ``shapes``, the frames'
    (h, w) per view, give the image sizes such files lack)."""
    from ..imaging.triangulate import views_from_calibration
    from ..io.stereo_calibration import read_stereo_calibration
    cal = read_stereo_calibration(path, views, shapes)
    if isinstance(cal, dict) and cal.get("source"):
        log.info("track: calibration read from %s (%s), cameras %s", path, cal["source"]["format"],
                 ", ".join(f"{k} = {v}" for k, v in cal["source"]["views"].items()))
    st = cal.get("stereo") if isinstance(cal, dict) else None
    if not st or "views" not in st:
        cams = cal.get("views") if isinstance(cal, dict) else None
        named = sorted(cams) if isinstance(cams, dict) else []
        missing = [v for v in views if v not in named]
        if named and missing:
            raise InputError(f"the calibration has camera(s) {', '.join(named)} and no {', '.join(missing)} (nor a "
                             "'stereo' block): 3-D needs the views calibrated together (bsipipe calibrate --stereo)",
                             path=path)
        raise InputError("the calibration has no 'stereo' block: 3-D needs two views calibrated together", path=path)
    pair = tuple(st["views"])
    if not set(pair) <= set(views):
        raise InputError(f"the calibration's stereo views are {pair[0]!r}, {pair[1]!r}; --view gives "
                         f"{', '.join(views)}", path=path)
    order = tuple(v for v in views if v in pair)
    try:
        rms = float(st["rms_px"])
    except (KeyError, TypeError, ValueError):
        rms = None          # no stereo RMS: the calibration-mismatch check assumes one
    try:
        return views_from_calibration(cal, order), order, rms if rms is not None and math.isfinite(rms) else None
    except (KeyError, ValueError, TypeError) as e:
        raise InputError(f"invalid calibration: {e}", path=path) from None


#: The triangulated points' reprojection RMS may be this many times what the calibration's own
#: stereo RMS and the markers' measured noise explain before the calibration is said not to
#: fit the frames (the twin: 0.59 times, jolting frames with the loop's frame-shift 1.6; a C-arm
#: moved 5 mm since the calibration: 4.1, turned 3 degrees 5.8; turned 1 degree, 1.9, passes).
CALIBRATION_FIT_FACTOR = 2.0
#: The same where the loop took jolts out (frame-shift): each frame's shift is an estimate from
#: that frame's few markers, and its error stays in the reprojection (the study's twin with 5 px
#: jolts: 2.0 times, its 3-D error 0.02 mm; the moved and turned C-arms above are 4.1 and 5.8).
CALIBRATION_FIT_FACTOR_JOLTS = 3.0
#: The stereo RMS taken for a calibration that gives none (another tool's, or a rig's true
#: cameras): the upper end of a usable C-arm calibration (the study's twin calibrates to 0.066
#: px, OpenCV's real chessboard pair to 0.41).  The check had been left out for such a file: a
#: view whose frames were cropped 15 px since its calibration gave 3-D points 3 mm off with no
#: word; with 0.5 px assumed it reprojects 7 times what that explains.
ASSUMED_CALIBRATION_RMS_PX = 0.5


def _calibration_fit_warning(loop: dict, table: pd.DataFrame, cal_rms: float | None, pair) -> dict | None:
    """``calibration-mismatch`` when the two-view points reproject more than
    :data:`CALIBRATION_FIT_FACTOR` times the root sum of squares of the calibration's stereo
    RMS and the markers' own centre error (0.798 / SNR per axis, RMS over the found
    positions, times sqrt 2 for the two axes): the C-arms moved since they were calibrated, or
    the calibration is another setup's.  The ray-gap flags compare points with the sequence's
    own median, so an error common to every point passes them.  ``cal_rms``: the
    calibration's stereo RMS (px; None: the file gives none, and
    :data:`ASSUMED_CALIBRATION_RMS_PX` is taken)."""
    from ..quality import warning
    assumed = cal_rms is None
    if assumed:
        cal_rms = ASSUMED_CALIBRATION_RMS_PX
    final = (loop or {}).get("final") or {}
    rms = final.get("reprojection_rms_px")
    found = table[table["found"] & table["view"].isin(pair)]
    snr = found["snr"].to_numpy(float) if "snr" in found else np.zeros(0)
    snr = snr[np.isfinite(snr) & (snr > 0)]
    if rms is None or not len(snr):
        return None
    centre = float(np.sqrt(2.0 * np.mean((0.798 / snr) ** 2)))
    expected = math.hypot(cal_rms, centre)
    jolts = "frame-shift" in str(final.get("model", ""))
    if rms <= (CALIBRATION_FIT_FACTOR_JOLTS if jolts else CALIBRATION_FIT_FACTOR) * expected:
        return None
    return warning(
        "calibration-mismatch",
        f"track: the two-view points reproject {rms:.3g} px RMS, {rms / expected:.1f} times what the calibration's "
        f"own stereo RMS ({cal_rms:.3g} px{', assumed: the file gives none' if assumed else ''}) and the markers' "
        f"centre error ({centre:.3g} px) explain; ray gap RMS "
        f"{final.get('ray_gap_rms_mm', float('nan')):.3g} mm: the C-arms moved since they were calibrated, or the "
        "calibration is another setup's; every 3-D point is off by about the ray gap", log,
        reprojection_rms_px=rms, expected_px=expected, calibration_rms_px=cal_rms, calibration_rms_assumed=assumed,
        centre_error_px=centre)


def _progress(total: int | None, desc: str, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, disable=not enabled, leave=False)


#: Without seeds, a marker whose median ray gap is this many times the sequence's (and over
#: PAIRING_SUSPECT_FLOOR_MM) was likely paired across the views with another marker's track.
PAIRING_SUSPECT_FACTOR = 5.0
PAIRING_SUSPECT_FLOOR_MM = 0.1


def _pairing_suspects(points3d: pd.DataFrame) -> list[dict]:
    """``cross-view-pairing-suspect`` (automatic tracks only): markers whose median ray gap is
    :data:`PAIRING_SUSPECT_FACTOR` times the sequence's median, and over
    :data:`PAIRING_SUSPECT_FLOOR_MM`.  The large-ray-gap flags judge each point against its own
    marker's median, so a whole track paired with the wrong one in the other view passes them
    (a track split at a bone edge had its second half paired with another marker: 20 points
    2 mm off, gaps 0.11-0.24 mm against a 0.02 mm median, unflagged)."""
    from ..quality import warning
    col = "ray_gap_mm_raw" if "ray_gap_mm_raw" in points3d else "ray_gap_mm"
    two = points3d[points3d["n_views"] == 2]
    g = two[col].to_numpy(float)
    if not np.isfinite(g).any():
        return []
    overall = float(np.nanmedian(g))
    per = two.groupby("marker", sort=False)[col].median()
    bad = per[(per > PAIRING_SUSPECT_FACTOR * overall) & (per > PAIRING_SUSPECT_FLOOR_MM)]
    if bad.empty:
        return []
    return [warning("cross-view-pairing-suspect",
                    "track: without seeds, these markers' rays pass far apart all along (median ray gap "
                    + ", ".join(f"{m} {v:.3g} mm" for m, v in bad.items())
                    + f", against {overall:.3g} mm over the sequence): their tracks in the two views are likely "
                      "different markers paired together (their 3-D points are off by millimetres); give seeds, "
                      "or check the 2-D tracks", log, markers={str(m): float(v) for m, v in bad.items()},
                    median_mm=overall)]


def _ray_gap_warnings(points3d: pd.DataFrame, max_mm: float | None) -> list[dict]:
    """Flag two-view points with a large ray gap (:func:`bsipipe.quality.ray_gap_flags`): sets the
    ``flag`` column of ``points3d`` (``large-ray-gap`` or empty) and returns track.json's warning.
    With smoothing the raw detections' gaps are judged (``ray_gap_mm_raw``): a bad detection
    shows there, while the smoother has already left it out."""
    from ..quality import ray_gap_flags, warning

    col = "ray_gap_mm_raw" if "ray_gap_mm_raw" in points3d else "ray_gap_mm"
    gaps = points3d[col].where(points3d["n_views"] == 2).to_numpy(float)
    flag, rule = ray_gap_flags(gaps, points3d["marker"].to_numpy(), max_mm=max_mm)
    points3d["flag"] = np.where(flag, "large-ray-gap", "")
    if not flag.any():
        return []
    bad = points3d[flag]
    frames = bad.groupby("marker", sort=False)["frame"].apply(list).to_dict()
    where = "; ".join(f"{m}: frame{'s' if len(f) > 1 else ''} {', '.join(map(str, f[:8]))}{', ...' if len(f) > 8 else ''}"
                      for m, f in frames.items())
    return [warning("large-ray-gap",
                    f"track: {len(bad)} triangulated point(s) whose rays pass further apart than {rule['factor']:g}x "
                    f"their marker's median ray gap and {rule['floor_mm']:g} mm"
                    + (f", or than {max_mm:g} mm" if max_mm is not None else "")
                    + f" (flag column of markers3d.csv): {where}",
                    log, n_points=int(len(bad)), **rule,
                    points=[{"frame": int(f), "marker": str(m), "ray_gap_mm": float(g)}
                            for f, m, g in bad[["frame", "marker", col]].itertuples(index=False)][:200])]


def _smooth(table: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    """:func:`bsipipe.imaging.smooth.smooth_tracks` on the 2-D table (frames as the clock
    where there are no time stamps) and the ``smoothing`` section of ``track.json``."""
    from ..imaging.smooth import smooth_tracks
    t = table[["view", "frame", "time_s", "marker", "x_px", "y_px", "snr", "found"]].copy()
    if "shift_x_px" in table:
        # the loop's frame shifts (a jolting picture) are taken out before smoothing
        t["x_px"] -= table["shift_x_px"].fillna(0.0)
        t["y_px"] -= table["shift_y_px"].fillna(0.0)
    clock = "s"
    if t["time_s"].isna().any():
        t["time_s"] = t["frame"].astype(float)
        clock = "frame"
    t["snr"] = t["snr"].where(t["found"].astype(bool))
    try:
        sm, models = smooth_tracks(t)
    except ValueError:          # time stamps that repeat or go back: smooth on the frame clock
        t["time_s"] = t["frame"].astype(float)
        clock = "frame"
        sm, models = smooth_tracks(t)
    out = table        # the caller's own table: columns added, not copied
    for c in ("sd_px", "x_px_smooth", "y_px_smooth", "sd_px_smooth", "smooth_outlier"):
        out[c] = sm[c].to_numpy()
    del sm, t
    return out, {
        "method": "Kalman filter + Rauch-Tung-Striebel smoother per track and axis, white-noise acceleration; "
                  "process noise q and the scale of the detector's error model (sd = 0.798 / SNR per axis, "
                  "the Cramer-Rao bound of a Gaussian spot) chosen per track by maximum likelihood",
        "clock": clock, "units": {"q": f"px^2/{clock}^3"},
        "tracks": [m.to_dict() for m in models]}


def _stereo_check(table: pd.DataFrame, points3d: pd.DataFrame, vpair, pair, tracks: list[dict]) -> dict:
    """:func:`bsipipe.imaging.smooth.stereo_error_check` on the smoothed centres, and each
    marker's ``sd_px`` and ``sd_px_smooth`` scaled (in ``table``, both views) by what the ray
    gaps show the error model misses, as are the medians in its ``tracks`` entries (the
    ``smoothing`` section's, which gain ``stereo_scale_raw`` / ``_smooth``); returns the
    ``stereo_check`` section of ``track.json``."""
    from ..imaging.smooth import stereo_error_check
    per = stereo_error_check(points3d, table, vpair, pair)
    before = {c: float(table[c].median()) for c in ("sd_px", "sd_px_smooth")}
    for m, r in per.items():
        sel = (table["marker"] == m) & table["view"].isin(pair)
        table.loc[sel, "sd_px"] *= r["scale_raw"]
        table.loc[sel, "sd_px_smooth"] *= r["scale_smooth"]
    for t in tracks:
        r = per.get(str(t["marker"])) if t["view"] in pair else None
        if r is not None:
            t["raw_sd_px"] *= r["scale_raw"]
            t["smooth_sd_px"] *= r["scale_smooth"]
            t["stereo_scale_raw"], t["stereo_scale_smooth"] = r["scale_raw"], r["scale_smooth"]
    scaled = {m: round(r["scale_smooth"], 2) for m, r in per.items() if r["scale_smooth"] > 1.0}
    zs = [r["z_rms_smooth"] for r in per.values() if r["n_points"]]
    if zs:
        log.info("track: stereo check of the error model: ray-gap z RMS of the smoothed centres %.2f-%.2f over %d "
                 "markers; sd scaled where above 1 (%s)", min(zs), max(zs), len(zs),
                 ", ".join(f"{m} x{k:g}" for m, k in scaled.items()) or "none")
    return {"rule": "per marker with >= 10 two-view points: z = signed ray gap / its sd from both views' sd_px "
                    "(sd x depth / focal length); sd_px and sd_px_smooth of both views scaled by max(1, z RMS)",
            "median_sd_px_before": before["sd_px"], "median_sd_px_smooth_before": before["sd_px_smooth"],
            "median_sd_px_after": float(table["sd_px"].median()),
            "median_sd_px_smooth_after": float(table["sd_px_smooth"].median()),
            "markers": per}


def _centre_sd(t: pd.DataFrame, idx, sd_col: str) -> np.ndarray:
    """One view's centre sd (px) at the ``(frame, marker)`` cells ``idx`` of its table ``t``:
    ``sd_col``, and for the smoothed one (``sd_px_smooth``) the raw ``sd_px`` where the track
    was too short to smooth (its raw centres are what is triangulated)."""
    sd = t[sd_col].reindex(idx).to_numpy(float, copy=True)
    if sd_col == "sd_px_smooth":
        unsmoothed = ~np.isfinite(sd) & ~np.isfinite(t["x_px_smooth"].reindex(idx).to_numpy(float))
        sd[unsmoothed] = t["sd_px"].reindex(idx).to_numpy(float)[unsmoothed]
    return sd


def _sd_at_times(t: pd.DataFrame, idx, names: np.ndarray, tq: np.ndarray, sd_col: str, sd: np.ndarray) -> None:
    """In place: where a point's ``sd`` is missing, or its view's row of that frame number is
    another time (a view at its own frame rate, interpolated to the other's frame times), the
    view's ``sd_col`` at the point's time ``tq``, linear between its own frames."""
    row_t = t["time_s"].reindex(idx).to_numpy(float)
    gap = ~np.isfinite(sd) | ~(np.abs(row_t - tq) <= 1e-6 * max(1.0, float(np.nanmax(np.abs(tq)))))
    gap &= np.isfinite(tq)
    for m in pd.unique(names[gap]):
        if m not in t.index.get_level_values("marker"):
            continue
        own = t.xs(m, level="marker")
        own = own[np.isfinite(own["time_s"]) & np.isfinite(own[sd_col])].sort_values("time_s")
        sel = gap & (names == m)
        if len(own) >= 2 and sel.any():
            tt = own["time_s"].to_numpy(float)
            inside = sel & (tq >= tt[0]) & (tq <= tt[-1])
            sd[inside] = np.interp(tq[inside], tt, own[sd_col].to_numpy(float))


def _point_sds(points3d: pd.DataFrame, table: pd.DataFrame, vpair, pair) -> None:
    """Each two-view point's standard deviation per axis (mm), propagated from its two
    centres' (:func:`bsipipe.imaging.triangulate.point_covariance`): ``sd_x_mm, sd_y_mm,
    sd_z_mm`` of the smoothed point from ``sd_px_smooth``, ``sd_x_mm_raw`` ... of the raw one
    from ``sd_px`` (both as the stereo check left them); single-view points' from
    :func:`_single_view_sds`."""
    from ..imaging.track_effects import frame_period, rates_differ
    from ..imaging.triangulate import point_covariance
    two = (points3d["n_views"] == 2).to_numpy()
    idx = pd.MultiIndex.from_frame(points3d.loc[two, ["frame", "marker"]])
    per_view = [table[table["view"] == v].set_index(["frame", "marker"]) for v in pair]
    # views at their own frame rates: the second was interpolated to the first's frame times
    # (track_effects.stereo_data), so its sd is taken at each point's time
    other_rate = rates_differ(*(frame_period(t.index.get_level_values("frame"), t["time_s"]) for t in per_view))
    tq = points3d.loc[two, "time_s"].to_numpy(float) if other_rate and "time_s" in points3d else None
    names = points3d.loc[two, "marker"].to_numpy()
    for suffix, cols, sd_col in (("", ("x_mm", "y_mm", "z_mm"), "sd_px_smooth"),
                                 ("_raw", ("x_mm_raw", "y_mm_raw", "z_mm_raw"), "sd_px")):
        out = np.full((len(points3d), 3), np.nan)
        if two.any():
            sds = [_centre_sd(t, idx, sd_col) for t in per_view]
            if tq is not None:
                for t, sd in zip(per_view, sds):
                    if t["time_s"].notna().any():
                        _sd_at_times(t, idx, names, tq, sd_col, sd)
            cov = point_covariance(vpair, points3d.loc[two, list(cols)].to_numpy(float), sds)
            out[two] = np.sqrt(np.einsum("nkk->nk", cov))
        _single_view_sds(points3d, table, vpair, pair, cols, sd_col, out)
        for k, a in enumerate("xyz"):
            points3d[f"sd_{a}_mm{suffix}"] = out[:, k]


def _single_view_sds(points3d: pd.DataFrame, table: pd.DataFrame, vpair, pair, cols, sd_col: str,
                     out: np.ndarray) -> None:
    """Each single-view point's sd per axis into ``out`` (rows of ``points3d``): across its
    view's ray from that view's centre sd (:func:`_centre_sd`), along it the sd the marker's
    two-view points have there (each axis's sd interpolated in time, projected on the ray)
    (:func:`~bsipipe.imaging.triangulate.single_view_covariance`).  They had none: a quarter
    of the points of a twin with jolts and specks."""
    from ..imaging.triangulate import single_view_covariance
    src = points3d["source"].astype(str) if "source" in points3d else pd.Series("", index=points3d.index)
    tcol = "time_s" if "time_s" in points3d and points3d["time_s"].notna().any() else "frame"
    markers = points3d["marker"].to_numpy()
    times = points3d[tcol].to_numpy(float)
    two = (points3d["n_views"] == 2).to_numpy() & np.isfinite(out).all(axis=1) & np.isfinite(times)
    for view, name in zip(vpair, pair):
        one = (points3d["n_views"] == 1).to_numpy() & (src == f"single-view:{name}").to_numpy()
        if not one.any():
            continue
        rows = points3d.loc[one]
        t = table[table["view"] == name].set_index(["frame", "marker"])
        sd = _centre_sd(t, pd.MultiIndex.from_frame(rows[["frame", "marker"]]), sd_col)
        X = rows[list(cols)].to_numpy(float)
        ray = X - view.centre_mm
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        along = np.full(len(rows), np.nan)
        tq = rows[tcol].to_numpy(float)
        for m in pd.unique(rows["marker"]):
            k2 = np.flatnonzero(two & (markers == m))                  # positions of its two-view points
            sel = (rows["marker"] == m).to_numpy()
            if not len(k2):
                continue
            k2 = k2[np.argsort(times[k2], kind="stable")]
            at = np.column_stack([np.interp(tq[sel], times[k2], out[k2, k]) for k in range(3)])
            along[sel] = np.sqrt(np.sum((ray[sel] * at) ** 2, axis=1))
        cov = single_view_covariance(view, X, sd, along)
        out[np.flatnonzero(one)] = np.sqrt(np.einsum("nkk->nk", cov))


def _frames_listed(frames: dict[str, list[int]]) -> str:
    """``cam1: 2 frame(s), 4, 9; cam2: ...`` (the first ten of each view) for a warning."""
    return "; ".join(f"{v}: {len(m)} frame(s), {', '.join(map(str, m[:10]))}{', ...' if len(m) > 10 else ''}"
                     for v, m in frames.items())


def _frames_without_markers(table: pd.DataFrame, seeded: bool = False) -> dict[str, list[int]]:
    """Per view, the frames in which no marker was found although at least two were found in
    an earlier and in a later frame: a frame without its picture (a missed exposure of pulsed
    fluoroscopy, a black or flashed frame from the grabber) rather than markers hidden one by
    one.  ``seeded``: the seeds place the markers in the first frame, so the frames before
    the first in which two were found count too.  Frames missing from the numbering (status
    ``missing-frame``) are not counted."""
    out = {}
    for v, g in table.groupby("view", sort=False):
        g = g[g["status"] != "missing-frame"]
        if g["marker"].nunique() < 2:
            continue
        n = g.groupby("frame")["found"].sum()
        seen = n.index[n.to_numpy() >= 2]
        if len(seen) < 2:
            continue
        empty = n.index[(n.to_numpy() == 0) & ((n.index > seen[0]) | seeded) & (n.index < seen[-1])]
        if len(empty):
            out[str(v)] = [int(f) for f in empty]
    return out


def _missing_frame_rows(table: pd.DataFrame, missing: dict[str, list[int]], cfg,
                        views: list[str]) -> pd.DataFrame:
    """``table`` with a row for every marker of a view in each of its ``missing`` frames (not
    found, status ``missing-frame``, timed at frame / the view's ``fps`` where a rate is
    given), in view and frame order."""
    add = []
    for v, fr in missing.items():
        fps = cfg.fps_of(v)
        ms = pd.unique(table.loc[table["view"] == v, "marker"])
        f = np.repeat(np.asarray(fr, np.int64), len(ms))
        add.append(pd.DataFrame({"view": v, "frame": f, "marker": np.tile(ms, len(fr)),
                                 "time_s": f / fps if fps else np.nan, "found": False, "status": "missing-frame"}))
    out = pd.concat([table, *add], ignore_index=True)
    out["found"] = out["found"].astype(bool)
    rank = out["view"].map({v: i for i, v in enumerate(views)})
    return out.iloc[np.lexsort((out["frame"].to_numpy(), rank.to_numpy()))].reset_index(drop=True)


def _noting_stamps(frames, state: dict):
    """``frames`` as they come, ``state["stamped"]`` set when one carries its source's own time."""
    for fr in frames:
        if fr.time_s is not None:
            state["stamped"] = True
        yield fr


def _rates_for_unstamped_views(cfg, views) -> None:
    """A per-view ``--fps`` may leave out views whose sources have their own time stamps (a
    stamped video beside a folder of PNGs); one left out whose frames have none is exit 2
    naming it (it had been refused whatever the source: "a frame rate per view must give
    every view")."""
    if not isinstance(cfg.fps, dict):
        return
    from ..io.images import iter_frames
    for v in views:
        if v in cfg.fps:
            continue
        first = next(iter(iter_frames(cfg.views[v], channel=cfg.channel)), None)
        if first is not None and first.time_s is None:
            raise InputError(f"--fps gives rates for {', '.join(cfg.fps)} but none for {v}, whose frames have no "
                             f"time stamps: give --fps {v}=F too", path=cfg.views[v], key="fps")


def _track_views(cfg, views, seed_df, d: dict, det, tk, progress: bool, rois: dict):
    """Track every view (:func:`bsipipe.imaging.track.track_view`), frames decoded ahead on
    threads (a pool for a folder of frames, :func:`~bsipipe.io.images.decode_workers`;
    :func:`~bsipipe.io.images.prefetched` for every source, so videos and stacks overlap too);
    returns the per-view tables, the events, the per-view info, each view's first frame (for
    the overlay figure) and the sha256 of every frame file (from the bytes decoded)."""
    from ..imaging.detect import is_blank, temporal_noise_correlation
    from ..imaging.track import track_view
    from ..io.images import count_frames, prefetched

    tables, events, info = [], [], {}
    first_images: dict[str, np.ndarray] = {}
    frame_hashes: dict[str, str] = {}     # sha256 of each frame file, from the bytes decoded (provenance)
    for v in views:
        path = cfg.views[v]
        s = None
        if seed_df is not None:
            s = seed_df[seed_df["view"] == v]
            if s.empty:
                raise InputError(f"no seeds for view {v!r}", path=cfg.seeds)
        try:
            n = count_frames(path)
        except InputError:
            raise
        except Exception:  # a count is only for the progress bar
            n = None
        bar = _progress(n, v, progress)
        state = {"n": 0, "shape": None, "range": 0.0, "blank": [], "lag": []}
        lag_every = LAG_EVERY if not n else max(3, n // LAG_TRIPLES)
        crops: list = []

        def on_frame(i, img, v=v, bar=bar, state=state, crops=crops):
            if state["n"] == 0:
                first_images[v] = np.array(img, copy=True)
                state["shape"] = list(img.shape)
            # frames averaged over time (intensifier lag, a recursive noise filter): the noise
            # of three consecutive frames, every lag_every-th, from the central quarter's pixels
            k = state["n"] % lag_every
            if k >= lag_every - 3 or lag_every <= 3:
                h, w = img.shape[:2]
                crops.append(np.array(img[h // 4:3 * h // 4:2, w // 4:3 * w // 4:2], copy=True))
                if len(crops) == 3:
                    rho = temporal_noise_correlation(*crops)
                    if rho is not None:
                        state["lag"].append(rho)
                    crops.clear()
            else:
                crops.clear()
            state["n"] += 1
            # frames without a picture, for the frames-without-markers warning: only a frame
            # whose sampled range falls to a quarter of the widest seen so far is tested whole.
            # The sample is whole rows, every 32nd: the frame was decoded on another core, and a
            # strided sample of every 8th row and column touched all its 256 pages (0.28 ms a
            # frame on the main thread, in 2 x 2,000 frames of the bench twin), this one 32
            sub = img[::32]
            r = float(sub.max()) - float(sub.min())
            if r <= 0.25 * state["range"] or state["range"] == 0.0:
                if is_blank(img):
                    state["blank"].append(int(i))
            state["range"] = max(state["range"], r)
            bar.update(1)

        try:
            frames = _view_frames(cfg, v, hashes=frame_hashes, state=state)
            res = track_view(prefetched(frames), s, d[v], cfg.polarity_of(v), view=v,
                             fps=cfg.fps_of(v), roi=rois[v], detection=det, settings=tk, on_frame=on_frame)
        except ValueError as e:
            raise InputError(str(e), path=path) from None
        finally:
            bar.close()
        if state["n"] == 0:
            raise InputError("no frames", path=path)
        try:
            faint = _faint_pass(res, cfg, v, d[v], det, tk, rois[v], progress=progress) if s is None else None
        except ValueError as e:
            raise InputError(str(e), path=path) from None
        tables.append(res.table)
        events.extend(res.events)
        info[v] = {"path": path, "n_frames": state["n"], "frame_shape_px": state["shape"], "field_of_view": res.fov,
                   "settings": res.settings, "frames_without_picture": state["blank"],
                   "temporal_noise": _temporal_noise(state["lag"]),
                   "source_stamped": state.get("stamped", False)}
        if faint:
            info[v]["faint_markers"] = faint
        nf = int(res.table["found"].sum())
        log.info("track: %s: %d frames, %d markers, %d of %d positions found, %d events", v, state["n"],
                 res.table["marker"].nunique(), nf, len(res.table), len(res.events))
    return tables, events, info, first_images, frame_hashes


#: The noise correlation of consecutive frames is measured on three consecutive frames out of
#: every so many that the view gives LAG_TRIPLES triples (every LAG_EVERY where its length is
#: unknown); at LAG_RHO or more (median of at least LAG_MIN_TRIPLES triples) the frames are said
#: to be averaged over time.
LAG_EVERY = 10
LAG_TRIPLES = 30
LAG_RHO = 0.1
LAG_MIN_TRIPLES = 5
#: The triples' estimates agree within this interquartile range where noise sets them (0.012-
#: 0.018 on the probe's twins, averaged or not); motion or flicker that the differences do not
#: cancel spreads them (trackpy's bulk-water frames, particles moving everywhere: 0.67 about a
#: median of 1.17, no correlation at all), and then nothing is said.
LAG_SPREAD = 0.15


def _temporal_noise(rhos: list[float]) -> dict:
    r"""A view's lag-1 noise correlation (median over its frame triples,
    :func:`~bsipipe.imaging.detect.temporal_noise_correlation`), the triples' interquartile
    range, whether they agree as noise-set estimates do (:data:`LAG_SPREAD`, and a
    correlation under 1), and the delay it implies: a recursive average
    :math:`y_t = (1-\rho) x_t + \rho y_{t-1}` shows a marker moving at a steady speed
    :math:`\rho/(1-\rho)` frames behind where it is."""
    if not rhos:
        return {"rho": None, "n_triples": 0, "iqr": None, "consistent": False, "lag_frames": None}
    q25, rho, q75 = (float(v) for v in np.percentile(rhos, [25, 50, 75]))
    ok = (q75 - q25) <= LAG_SPREAD and rho < 1.0
    return {"rho": rho, "n_triples": len(rhos), "iqr": q75 - q25, "consistent": bool(ok),
            "lag_frames": rho / (1.0 - rho) if ok and rho > 0.0 else 0.0}


def _view_frames(cfg, v: str, *, hashes: dict | None = None, state: dict | None = None):
    """View ``v``'s frames as ``track`` reads them: decoded on reader threads, the source's
    time stamps noted in ``state`` (where given, :func:`_noting_stamps`), and dropped where the
    config's rate wins over them (``fps_over_stamps``: a container's default rate)."""
    from ..io.images import decode_workers, iter_frames
    frames = iter_frames(cfg.views[v], channel=cfg.channel, hashes=hashes, workers=decode_workers())
    if state is not None:
        frames = _noting_stamps(frames, state)
    if cfg.fps_over_stamps and cfg.fps_of(v) is not None:
        frames = (fr._replace(time_s=None) for fr in frames)
    return frames


def _faint_pass(res, cfg, v: str, d: float, det, tk, roi, *, progress: bool = False) -> dict | None:
    """Automatic mode: the spots the average of the view's first frames shows where no track is
    (:attr:`~bsipipe.imaging.track.TrackResult.faint`: markers too faint for the whole-frame
    search in single frames, SNR 8 or more in the average), tracked as seeded markers are, in a
    second pass over the view's frames; their tracks (named on from the automatic ones) and
    events join ``res`` (in place).  Returns what was added, for track.json and the
    ``faint-markers`` warning, or None.  On the bench twin with Poisson noise the automatic
    mode had tracked 9 and 7 of the 12 markers of the two views, unsaid."""
    from ..imaging.track import track_view
    from ..io.images import prefetched
    spots = res.faint or []
    if not spots:
        return None
    taken = [int(m[1:]) for m in res.table["marker"].unique() if str(m)[:1] == "M" and str(m)[1:].isdigit()]
    first = max(taken, default=0) + 1
    names = [f"M{first + i}" for i in range(len(spots))]
    seeds = pd.DataFrame({"view": v, "marker": names, "x_px": [sp["x_px"] for sp in spots],
                          "y_px": [sp["y_px"] for sp in spots]})
    log.info("track: %s: %d spot(s) in the average of the first frames no automatic track holds (SNR %.3g-%.3g "
             "there): tracked from there as seeds (%s)", v, len(spots), spots[-1]["snr_average"],
             spots[0]["snr_average"], ", ".join(names))
    n_frames = int(res.table["frame"].nunique()) if len(res.table) else None
    bar = _progress(n_frames, f"{v} (faint markers)", progress)
    try:
        more = track_view(prefetched(_view_frames(cfg, v)), seeds, d, cfg.polarity_of(v), view=v, fps=cfg.fps_of(v), roi=roi,
                          detection=det, settings=tk, on_frame=lambda i, img: bar.update(1))
    finally:
        bar.close()
    # a spot an automatic track holds only in later frames (a sweep found it after the averaged
    # frames) is that track's marker: its frames the track misses are filled from the seeded
    # pass, and no second track is kept (the Poisson twin's M5 had been tracked twice)
    table, extra = res.table, more.table
    merged = {}
    for n in names:
        g = extra[(extra["marker"] == n) & extra["found"]]
        for m in table["marker"].unique():
            h = table[(table["marker"] == m) & table["found"]]
            both = g.merge(h, on="frame", suffixes=("", "_a"))
            if len(both) and (np.hypot(both["x_px"] - both["x_px_a"], both["y_px"] - both["y_px_a"])
                              <= max(1.0, d)).any():
                merged[n] = m
                break
    for n, m in merged.items():
        fill = extra[(extra["marker"] == n) & extra["found"]].set_index("frame")
        rows = table.index[(table["marker"] == m) & ~table["found"] & table["frame"].isin(fill.index)]
        cols = [c for c in table.columns if c not in ("view", "frame", "time_s", "marker")]
        table.loc[rows, cols] = fill.loc[table.loc[rows, "frame"], cols].to_numpy()
    keep = ~extra["marker"].isin(list(merged))
    res.table = pd.concat([table, extra[keep]], ignore_index=True).sort_values("frame", kind="stable",
                                                                               ignore_index=True)
    res.table["found"] = res.table["found"].astype(bool)
    res.events = sorted(res.events + [e for e in more.events if e.get("marker") not in merged],
                        key=lambda e: e["frame"])
    found = res.table.groupby("marker", sort=False)["found"].agg(["sum", "size"])
    return {"markers": {merged.get(n, n): {**sp, "found": int(found.loc[merged.get(n, n), "sum"]),
                                           "frames": int(found.loc[merged.get(n, n), "size"]),
                                           **({"joined": merged[n]} if n in merged else {})}
                        for n, sp in zip(names, spots)}}


def _faint_warning(info: dict, views) -> dict | None:
    """``faint-markers``: automatic tracks started from the average of the first frames."""
    from ..quality import warning
    hit = {v: info[v]["faint_markers"]["markers"] for v in views if info[v].get("faint_markers")}
    if not hit:
        return None
    return warning(
        "faint-markers",
        "track: without seeds, spots too faint for the whole-frame search in single frames showed in the average "
        "of the first frames, where no automatic track was, and were tracked from there as seeds (" + "; ".join(
            f"{v}: " + ", ".join(f"{m} SNR {sp['snr_average']:.3g} there, about {sp['snr_one_frame']:.2g} a frame, "
                                  f"found in {sp['found']} of {sp['frames']} frames"
                                  + (" (its automatic track began later: the frames before filled)"
                                     if sp.get("joined") else "") for m, sp in ms.items())
            for v, ms in hit.items())
        + "): faint markers (their positions are noisier, and some frames miss them) or static marker-like "
          "structure; seeds name and place them for certain", log, markers=hit)


def _averaged(temporal_noise: dict | None) -> bool:
    """Whether a view's frames are averaged over time (:func:`_temporal_noise`'s finding): its
    triples agree, on a lag-1 noise correlation of :data:`LAG_RHO` or more, over at least
    :data:`LAG_MIN_TRIPLES` of them."""
    t = temporal_noise or {}
    return bool(t.get("consistent")) and t["rho"] >= LAG_RHO and t["n_triples"] >= LAG_MIN_TRIPLES


def _lag_warning(info: dict, views) -> dict | None:
    """``frames-averaged``: views whose consecutive frames share their noise (:data:`LAG_RHO`)."""
    from ..quality import warning
    hit = {v: info[v]["temporal_noise"] for v in views if _averaged(info[v].get("temporal_noise"))}
    if not hit:
        return None
    return warning(
        "frames-averaged",
        "track: consecutive frames share their noise ("
        + "; ".join(f"{v}: lag-1 correlation {t['rho']:.2f} over {t['n_triples']} frame triples" for v, t in hit.items())
        + "): each frame is partly the ones before (image-intensifier lag, the C-arm's recursive noise filter, or a "
          "lossy video codec's prediction between frames). A moving marker's image trails it: its centre lags the "
          "motion by about "
        + ", ".join(f"{t['lag_frames']:.2f} frame" for t in hit.values())
        + " (speed x that: ray gaps cannot show a lag both views share), and the errors of consecutive centres are "
          "correlated, so the stated sds, smoothed ones most, are too small. Switch the temporal filter off "
          "(or record the last-image-hold frames without it) for motion measurements",
        log, views={v: t for v, t in hit.items()})


def _lag_correction(info: dict, table: pd.DataFrame, pair, points3d: pd.DataFrame, fit, cfg,
                    lossy: dict) -> dict | None:
    r"""``frames-averaged`` put right in time: where a calibrated view's frames are a recursive
    average :math:`y_t = (1-\rho) x_t + \rho y_{t-1}` of what the C-arm saw (its noise correlated
    from frame to frame, :func:`_temporal_noise`), a marker moving at a steady speed is imaged
    where it was :math:`\rho/(1-\rho)` frames before (the average's delay), in both views alike,
    where the ray gaps cannot see it.  The 3-D points keep their positions and are dated by when
    the marker was there: ``time_s`` moved back by that lag -- the lag of the first view where
    the loop paired the views through a view-time-offset (the second view then follows the
    first's clock, its own lag in the offset), else the views' mean.  Not where the frames were
    stored lossily (a codec's prediction between frames correlates their noise without delaying
    the picture; ``lossy``: view -> what the ``lossy-frames`` warning found), without a clock, or
    with ``correct_lag: false``.  Changes ``points3d`` in place; returns what was done for
    track.json (None where no view is averaged)."""
    noise = {v: (info.get(v) or {}).get("temporal_noise") for v in pair}
    lags = {v: float(noise[v]["lag_frames"]) if _averaged(noise[v]) else 0.0 for v in pair}
    if not any(lags.values()):
        return None
    out = {"views": {v: {"rho": (noise[v] or {}).get("rho"), "lag_frames": lags[v]} for v in pair}}
    offset = (fit.params.get("view_time_offset_s") if fit is not None else None) is not None
    lag = lags[pair[0]] if offset else float(np.mean([lags[v] for v in pair]))
    out["lag_frames"] = lag
    out["rule"] = (f"the first view's lag ({pair[0]}: the loop paired the views through a view-time-offset)" if offset
                   else "the mean of the views' lags")
    lossy = {v: c for v, c in lossy.items() if lags.get(v)}
    from ..imaging.track_effects import frame_period
    a = table[table["view"] == pair[0]]
    period = frame_period(a["frame"], a["time_s"])
    why = ("correct_lag is false" if not cfg.correct_lag else
           f"only {', '.join(v for v in pair if lags[v])}'s frames are averaged: the loop's view-time-offset holds "
           f"that lag, and the points follow {pair[0]}'s clock" if lag == 0.0 else
           "frames stored lossily (" + ", ".join(f"{v}: {c}" for v, c in lossy.items()) + "): a codec's prediction "
           "between frames correlates their noise without delaying the picture" if lossy else
           "no clock (neither time stamps nor a frame rate): the points are dated by frame only"
           if not period > 0 else None)
    if why is not None:
        out.update(applied=False, shift_s=0.0, why_not=why)
        return out
    shift = lag * period
    points3d["time_s"] = points3d["time_s"] - shift
    out.update(applied=True, frame_period_s=period, shift_s=shift)
    log.info("track: frames averaged over time put right: markers3d.csv's time_s moved back by %.4g s (%.3g frame: %s)",
             shift, lag, out["rule"])
    return out


def _rename_markers(table: pd.DataFrame, events: list[dict], view: str, names: dict) -> None:
    """Rename ``view``'s markers in ``table`` and its ``events`` (in place) by ``names``, which
    holds every marker of the view."""
    sel = table["view"] == view
    table.loc[sel, "marker"] = table.loc[sel, "marker"].map(names)
    for e in events:
        if e["view"] != view:
            continue
        if e.get("marker") in names:
            e["marker"] = names[e["marker"]]
        if e.get("other"):
            # the other markers of a merge or an ambiguity, by their new names too (they had kept
            # the view's own, another marker's name in the paired table)
            e["other"] = ", ".join(names.get(o, o) for o in str(e["other"]).split(", "))


def _check_frame_sizes(rig, pair, shapes: dict, path) -> None:
    """Each calibrated view's frames must have the size of the image its camera was
    calibrated on: the camera matrix holds for that image, and frames binned, cropped or
    exported at another size would be triangulated through the wrong rays."""
    for v in pair:
        size, shape = rig[v].image_size, shapes.get(v)
        if size and shape is not None and (int(shape[1]), int(shape[0])) != (int(size[0]), int(size[1])):
            raise InputError(f"view {v!r}: its frames are {shape[1]}x{shape[0]} px, the calibration's camera "
                             f"{v!r} is {size[0]}x{size[1]} px (frames binned, cropped or exported at another "
                             "size): calibrate from frames of this size, or track frames of the calibrated size",
                             path=path)


#: The widest marker tracked, as a share of the frame's shorter side: a top-hat that wide on
#: a whole frame takes minutes (a 100 px diameter on 1024 x 1024 frames ran for more than 3)
#: and finds regions, not markers.
MAX_DIAMETER_SHARE = 1.0 / 16.0


def _check_diameter(cfg, shapes: dict, config_path) -> None:
    """A given marker diameter wider than :data:`MAX_DIAMETER_SHARE` of a view's frame is
    exit 2, before any frame is tracked."""
    d = cfg.diameter_px
    if d is None:
        return
    for v, shape in shapes.items():
        dv = float(d[v]) if isinstance(d, dict) else float(d)
        if shape is not None and dv > MAX_DIAMETER_SHARE * min(shape[:2]):
            raise InputError(f"view {v}: a marker diameter of {dv:g} px is more than 1/16 of its "
                             f"{shape[1]} x {shape[0]} frames ({MAX_DIAMETER_SHARE * min(shape[:2]):g} px): give the "
                             "markers' diameter in px (X-ray beads are a few px), or leave it out to have it "
                             "measured", path=config_path, key="diameter_px")


def _marker_size(cfg, views, firsts: dict, seed_df, rois: dict):
    """The markers' polarity and diameter, given or estimated from the first frames.  Returns
    ``(cfg with the polarity, (polarity source, counts or None), (diameter, per view, source))``.
    A diameter per view (config) is probed as no diameter: 4, 8 and 16 px."""
    from ..imaging.marker_size import (diameter_from_seeds, diameter_without_seeds, polarity_from_frames,
                                       polarity_from_seeds, view_diameters, view_polarities)
    one_d = cfg.diameter_px if not isinstance(cfg.diameter_px, dict) else None
    polarity = ("given", None)
    auto = [v for v in views if cfg.polarity_of(v) == "auto"]
    if auto:
        if seed_df is not None:
            pol, note, counts = polarity_from_seeds({v: firsts.get(v) for v in auto},
                                                    seed_df[seed_df["view"].isin(auto)], one_d)
        else:
            pol, note, counts = polarity_from_frames({v: firsts.get(v) for v in auto}, one_d, rois)
        own = view_polarities(pol, counts.pop("per_view"), seeded=seed_df is not None)
        per = {v: own.get(v, pol) if v in auto else cfg.polarity_of(v) for v in views}
        cfg = cfg.model_copy(update={"polarity": per[views[0]] if len(set(per.values())) == 1 else per})
        if isinstance(cfg.polarity, dict):
            note += "; each view its own: " + ", ".join(f"{v} {p}" for v, p in per.items())
        polarity = (note, counts)
        log.info("track: markers %s (%s)", per[views[0]] if len(set(per.values())) == 1 else "dark or bright by view",
                 note)
    elif seed_df is None and not isinstance(cfg.polarity, dict):
        # a polarity given without seeds is checked as the automatic one would be chosen: the
        # wrong one tracks clutter (the seeds' own check is that they are found)
        counts = polarity_from_frames(firsts, one_d, rois)[2]
        counts.pop("per_view")
        polarity = ("given", counts)
    d = cfg.diameter_px
    note = "given"
    if isinstance(d, dict):
        per_view_d = {v: float(d[v]) for v in views}
        d = per_view_d[views[0]]
        note = "given per view"
    else:
        per_view_d = {v: d for v in views}
    if d is None:
        if seed_df is not None:
            est = {v: diameter_from_seeds(firsts[v], seed_df[seed_df["view"] == v], cfg.polarity_of(v))
                   for v in dict.fromkeys(seed_df["view"]) if firsts.get(v) is not None}
        else:
            est = {v: diameter_without_seeds(im, cfg.polarity_of(v), rois.get(v)) for v, im in firsts.items()
                   if im is not None}
        d, per_view_d, note = view_diameters(est, views)
        log.info("track: marker diameter %s (%s)", ", ".join(f"{v} {x:.2f} px" for v, x in per_view_d.items())
                 if len(set(per_view_d.values())) > 1 else f"{d:.2f} px", note)
    return cfg, polarity, (d, per_view_d, note)


def _detection_settings(cfg, d: float, diameter_note: str, seeded: bool, config_path):
    """The :class:`~bsipipe.imaging.detect.DetectionSettings` of the config's ``detection``,
    trackpy parity checked against the method, the seeds and the diameter."""
    from ..imaging.detect import DetectionSettings
    c = cfg.detection
    det = DetectionSettings(k_sigma=c.k_sigma, window_k_sigma=c.window_k_sigma, min_snr=c.min_snr, method=c.method,
                            max_elongation=c.max_elongation, blur_px=c.blur_px, max_sigma_factor=c.max_sigma_factor,
                            parity=c.parity, minmass=c.minmass, background=c.background)
    if det.parity == "trackpy" and (det.method != "centroid" or seeded):
        raise InputError("detection.parity 'trackpy' is trackpy's locate: it needs method 'centroid' and "
                         "automatic detection (no seeds)", path=config_path, key="detection.parity")
    if det.parity == "trackpy" and not (float(d).is_integer() and int(d) % 2 == 1):
        raise InputError(f"detection.parity 'trackpy' needs an odd whole diameter, as trackpy.locate does; the "
                         f"diameter is {d:g} px ({diameter_note}): give --diameter-px", path=config_path,
                         key="diameter_px")
    return det


def _check_seeds_found(table: pd.DataFrame, seed_df, together: list, info: dict, path) -> None:
    """A seed that finds nothing in any frame is a wrong seed, not a result."""
    found_any = table.groupby(["view", "marker"])["found"].any()
    for v, m, x, y in seed_df[["view", "marker", "x_px", "y_px"]].itertuples(index=False):
        if not found_any.get((v, m), False):
            twin = [b if a == m else a for vv, a, b, _, _ in together if vv == v and m in (a, b)]
            hint = (f"; its seed lies within half a diameter of the seed of {twin[0]!r}: one marker seeded "
                    "twice under two names?" if twin else "")
            raise ProcessingError(f"marker {m!r} was not found in any of the {info[v]['n_frames']} frames of "
                                  f"view {v!r} (seeded at ({x:g}, {y:g}) px): check the seed, --polarity and "
                                  f"--diameter-px{hint}", path=path)


def _larger_markers_said(warnings: list[dict], firsts: dict, seed_df, per_view_d: dict, polarity: str | dict) -> None:
    """Where the ``markers-rarely-found`` warning names a seeded marker that the first frame
    shows at a diameter 2-4 times the one tracked (a much larger bead among small ones, which
    the diameter estimate from the seeds leaves to the majority), say so in that warning
    instead of leaving "too faint" as the likely reason."""
    from ..imaging.marker_size import diameter_from_sigmas, larger_sigmas
    for w in warnings:
        if w.get("code") != "markers-rarely-found":
            continue
        bigger = {}
        for v, ms in w["markers"].items():
            img, d = firsts.get(v), float(per_view_d.get(v, 4.0))
            if img is None:
                continue
            for m in ms:
                row = seed_df[(seed_df["view"] == v) & (seed_df["marker"] == m)]
                if row.empty:
                    continue
                sig = larger_sigmas(img, row[["x_px", "y_px"]].to_numpy(float)[:1], d,
                                    polarity[v] if isinstance(polarity, dict) else polarity, (2.0, 3.0, 4.0))
                if np.isfinite(sig[0]) and (size := diameter_from_sigmas(sig)) >= 2.0 * d:
                    bigger.setdefault(v, {})[m] = round(float(size), 1)
        if bigger:
            said = ("; ".join(f"{v}: " + ", ".join(f"{m} looks {s:g} px across" for m, s in ms.items())
                              for v, ms in bigger.items())
                    + " in the first frame, more than twice the diameter tracked: markers of such different sizes "
                      "need separate runs, each with its own --diameter-px (and seeds)")
            w["message"] += "; " + said
            w["larger_markers_px"] = bigger
            log.warning("track: %s", said)


def _seeds_far(table: pd.DataFrame, seed_df, per_view_d: dict, tk) -> list[dict]:
    """A warning naming the seeds whose markers were found in the first frame farther from
    them than the tracker's seed radius (where most seeds miss their markers, the first frame
    searches further: clicks systematically off, say on a scaled display, still start the
    tracks, and the user should know)."""
    from ..quality import warning
    first = table.loc[table.groupby("view")["frame"].transform("min") == table["frame"]]
    first = first[first["found"].astype(bool)].set_index(["view", "marker"])
    far = {}
    for v, m, x, y in seed_df[["view", "marker", "x_px", "y_px"]].itertuples(index=False):
        if (v, m) not in first.index:
            continue
        r0 = tk.resolved(per_view_d.get(v, 4.0))["seed_radius_px"]
        d = float(np.hypot(first.loc[(v, m), "x_px"] - x, first.loc[(v, m), "y_px"] - y))
        if d > r0:
            far.setdefault(v, {})[m] = round(d, 2)
    if not far:
        return []
    return [warning("seeds-far", "track: seeds farther from the markers found for them in the first frame than the "
                    "seed radius (most seeds were off, so the first frame was searched further): "
                    + "; ".join(f"{v}: " + ", ".join(f"{m} {d:g} px" for m, d in ms.items()) for v, ms in far.items())
                    + "; check that each took its own marker (the overlay figure)", log, distances_px=far)]


def _seed_warnings(seed_df, polarity_of: dict, polarity_note: str, polarity_counts) -> list[dict]:
    """Warnings about the seeds and the markers' polarity (``polarity_of``: view -> dark or
    bright), known before the tracks are."""
    from ..quality import warning
    out = []
    later = seed_df.attrs.get("later") if seed_df is not None else None
    if later:
        out.append(warning(
            "seeds-after-first-frame",
            "track: the XMALab seeds file places these markers only in later frames, so they are not followed "
            "in that view: " + "; ".join(f"{v}: " + ", ".join(f"{m} (first at frame {f})" for m, f in ms.items())
                                        for v, ms in later.items())
            + " (seeds are the markers' positions in the first frame: click them there, where they would be)",
            log, markers=later))
    pols = set(polarity_of.values())
    if polarity_note == "given" and polarity_counts is not None and len(pols) == 1:
        polarity = pols.pop()
        other = "bright" if polarity == "dark" else "dark"
        n = polarity_counts
        if n[other] >= 3 and n[other] >= 2 * n[polarity]:
            out.append(warning(
                "polarity-mismatch",
                f"track: --polarity {polarity} given, but the first frames hold {n[other]} {other} and {n[polarity]} "
                f"{polarity} markers of SNR 6 or more: the tracks may follow clutter (--polarity {other}, or auto, "
                "or seeds)", log, given=polarity, **n))
    elif polarity_counts is not None and "bright" in pols:
        bright = [v for v, p in polarity_of.items() if p == "bright"]
        which = "the markers are" if len(bright) == len(polarity_of) else f"{', '.join(bright)}'s markers are"
        out.append(warning(
            "bright-markers", f"track: {which} brighter than their surroundings ({polarity_note}; "
            "raw X-ray frames show steel beads dark: inverted or processed frames?): tracked as bright markers "
            "(--polarity dark, or a polarity per view in a config, to override)", log, views=bright,
            **polarity_counts))
    return out


def _frame_rates(table: pd.DataFrame) -> dict[str, float]:
    """Each view's frame rate from its time stamps: the slope of time on frame number (a
    container's time stamps rounded to its time base, intervals of 0.24 and 0.28 s for 0.25 s
    frames, do not bias it, as a median of the intervals is)."""
    rates = {}
    for v, g in table.groupby("view", sort=False):
        t = g.drop_duplicates("frame").sort_values("frame")
        ts, fs = t["time_s"].to_numpy(float), t["frame"].to_numpy(float)
        ok = np.isfinite(ts)
        if ok.sum() >= 2 and np.ptp(fs[ok]) > 0:
            slope = float(np.polyfit(fs[ok], ts[ok], 1)[0])
            if slope > 0:
                rates[v] = 1.0 / slope
    return rates


#: What the frame-shifts warning says of the positions, and what it says instead where the
#: loop's frame-shift took the jolts out (:func:`_stereo`).
_JOLTS_CARRIED = ("but their 2-D positions, and any 3-D point triangulated from them, carry the jolts (nothing "
                  "corrects them)")
_JOLTS_TAKEN_OUT = ("their raw 2-D positions carry the jolts, and the loop's frame-shift took each view's common "
                    "shift per frame out of the 3-D points and the smoothed 2-D centres (columns shift_x_px, "
                    "shift_y_px)")

#: A seeded marker found in fewer than this fraction of its view's frames is a warning: the
#: indentor hides a marker for a while (the twin's two hidden ones are found in 53 and 64 % of
#: the frames), but one found in a few frames was mostly too faint to find.
RARELY_FOUND = 0.25


def _rarely_found(table: pd.DataFrame) -> dict[str, dict[str, tuple[int, int]]]:
    """View -> marker -> (frames found, frames) for the markers found in fewer than
    :data:`RARELY_FOUND` of their view's frames (rows of missing frames not counted)."""
    out: dict[str, dict[str, tuple[int, int]]] = {}
    t = table[table["status"] != "missing-frame"] if "status" in table.columns else table
    for (v, m), g in t.groupby(["view", "marker"], sort=False):
        k, n = int(g["found"].sum()), int(g["frame"].nunique())
        if n and k < RARELY_FOUND * n:
            out.setdefault(str(v), {})[str(m)] = (k, n)
    return out


#: Automatic tracks found in fewer than this fraction of their view's frames are warned
#: (``tracks-incomplete``).
INCOMPLETE = 0.9


def _runs(frames) -> str:
    """``0-17, 20, 31-33``: the frame numbers ``frames`` (sorted) as runs."""
    fr = np.asarray(frames, np.int64)
    runs = np.split(fr, np.flatnonzero(np.diff(fr) != 1) + 1) if len(fr) else []
    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs)


def _merge_spans(table: pd.DataFrame, events: list[dict], view: str) -> dict[frozenset, list[tuple[int, int]]]:
    """``view``'s merges by pair of markers: the frames ``(first, last)`` the two were one image
    (``merged`` events; a merge lasts while a marker's status is ``merged``)."""
    t = table[table["view"] == view]
    status = {m: g.set_index("frame")["status"] for m, g in t.groupby("marker", sort=False)}
    out: dict[frozenset, list[tuple[int, int]]] = {}
    for e in events:
        if e.get("view") != view or e.get("kind") != "merged" or e.get("marker") not in status:
            continue
        st = status[e["marker"]]
        f0 = int(e["frame"])
        after = st.loc[st.index >= f0]
        end = after.index[after.to_numpy(object) != "merged"]
        f1 = int(end[0]) - 1 if len(end) else int(after.index.max())
        for o in str(e.get("other") or "").split(", "):
            if o:
                out.setdefault(frozenset((e["marker"], o)), []).append((f0, f1))
    return out


def _merged_in_both_views(table: pd.DataFrame, events: list[dict], pair) -> list[dict]:
    """``merged-in-both-views``: two markers whose images merged in both calibrated views over
    the same frames and then parted.  Where they part they may have crossed or turned back,
    which neither view's images can tell (one image for both, then two that look alike), and
    an exchange made alike in both views leaves the ray gaps small: the loop's identity-swap
    test cannot see it.  A bead that came within 0.5 mm of a fixed reference and went back
    had been taken, in both views, for the reference moving off while the bead stayed, both
    3-D tracks 3.5 mm RMS off (7.8 mm at most), exit 0 and nothing said (the automatic-mode
    probe's bounce twins).  Where the pair merged in one view only, the other view tells them
    apart and the identity-swap test can judge."""
    from ..quality import warning
    if not pair or len(pair) < 2:
        return []
    a, b = (_merge_spans(table, events, v) for v in pair[:2])
    found = []
    for key, spans in a.items():
        for f0, f1 in spans:
            for g0, g1 in b.get(key, []):
                if f0 <= g1 and g0 <= f1:
                    found.append((sorted(key), max(f0, g0), min(f1, g1), max(f1, g1) + 1))
    if not found:
        return []
    found = sorted({(tuple(k), s, e, p) for k, s, e, p in found}, key=lambda x: x[1])
    return [warning(
        "merged-in-both-views",
        "track: markers whose images merged in both views over the same frames ("
        + "; ".join(f"{k[0]} and {k[1]}, frames {s}-{e}, parted by frame {p}" for k, s, e, p in found)
        + "): where they parted they may have crossed or turned back, which the images cannot tell apart, and an "
          "exchange made alike in both views leaves the ray gaps small: from the parting on, the two may carry "
          "each other's names (both 3-D tracks then off by their separation); check the frames around the parting",
        log, pairs=[{"markers": list(k), "first_frame": s, "last_frame": e, "parted_frame": p} for k, s, e, p in found])]


def _tracks_incomplete(table: pd.DataFrame) -> list[dict]:
    """Without seeds, the ``tracks-incomplete`` warning: tracks found in fewer than
    :data:`INCOMPLETE` of their view's frames (rows of missing frames not counted), with the
    frames they were not found in.  A seeded marker the tracker cannot find is searched for
    where it should be and its losses are events; an automatic track that begins late or
    ends early was simply not there for the tracker.  A dark band of bone across a twin's
    second view had hidden two markers for 18 of 40 frames with no word."""
    from ..quality import warning
    t = table[table["status"] != "missing-frame"] if "status" in table.columns else table
    bad: dict[str, dict[str, dict]] = {}
    for (v, m), g in t.groupby(["view", "marker"], sort=False):
        # a frame where the marker's image merged with a neighbour's has no position and no 3-D
        # point: not found (the probe's bead measured in 21 of 80 frames had been said 57 of 80)
        ok = g["found"].to_numpy(bool)
        merged = g["frame"].to_numpy()[g["status"].to_numpy(object) == "merged"].tolist() if "status" in g else []
        n = len(ok)
        if n and ok.sum() < INCOMPLETE * n:
            bad.setdefault(str(v), {})[str(m)] = {"found": int(ok.sum()), "frames": n,
                                                  "not_found": g["frame"].to_numpy()[~ok].tolist(), "merged": merged}
    if not bad:
        return []

    def why(d):
        merged = set(d["merged"])
        gone = [f for f in d["not_found"] if f not in merged]
        parts = ([f"not in {_runs(gone)}"] if gone else []) + ([f"merged in {_runs(d['merged'])}"] if d["merged"] else [])
        return "; ".join(parts)

    listed = "; ".join(f"{v}: " + ", ".join(f"{m} {d['found']} of {d['frames']} ({why(d)})" for m, d in ms.items())
                       for v, ms in bad.items())
    return [warning(
        "tracks-incomplete",
        f"track: without seeds, tracks found in fewer than {100 * INCOMPLETE:.0f} % of their view's frames ({listed}): "
        "hidden for part of the sequence (something over the field, bone, the edge of the field) or too faint; "
        "their 3-D points are missing there, and a track that begins late may be a marker lost earlier under "
        "another name: look at those frames, or give seeds (each seeded marker is searched for where it should "
        "be, and its losses are events)",
        log, markers={v: {m: {k: d[k] for k in ("found", "frames")} | {"not_found_frames": d["not_found"],
                                                                      "merged_frames": d["merged"]}
                          for m, d in ms.items()} for v, ms in bad.items()})]


def _sequence_warnings(table: pd.DataFrame, events: list[dict], cfg, views, info: dict, seeded: bool):
    """What the frames themselves tell against the tracks: frames missing from the numbering
    (their rows added to the table, status missing-frame), frames without any marker, views
    of different lengths or frame rates, lossy compression, a jolting picture.  Returns
    ``(table, warnings)``."""
    from ..io.images import lossy_compression
    from ..quality import warning
    out = []
    missing = {}
    for v, g in table.groupby("view", sort=False):
        fr = np.unique(g["frame"].to_numpy())
        if len(fr) and fr[-1] - fr[0] + 1 > len(fr):
            missing[v] = sorted(set(range(int(fr[0]), int(fr[-1]) + 1)) - set(fr.tolist()))
    if missing:
        # a frame the recorder dropped (its number missing from the files' names): its index
        # stays empty, so the frames after it still pair with the other view's by index; the
        # 2-D table keeps a row per frame and marker (not found, status missing-frame)
        out.append(warning(
            "missing-frames",
            "track: frames missing from the numbering of the files or the source's time stamps ("
            + _frames_listed(missing) + "): their rows are empty (status missing-frame, no 3-D point), and the later frames keep their "
              "numbers and pair with the other view's frames of the same number",
            log, frames={v: m for v, m in missing.items()}))
        table = _missing_frame_rows(table, missing, cfg, views)
    empty = _frames_without_markers(table, seeded)
    if empty:
        # which of them have no picture at all (black, flashed, dark noise: tested while tracking)
        dark: dict[str, list[int]] = {}
        lit: dict[str, list[int]] = {}
        for v, fr in empty.items():
            no_picture = set(info[v].get("frames_without_picture") or ())
            for f in fr:
                (dark if f in no_picture else lit).setdefault(v, []).append(f)
        why = []
        if dark:
            why.append(("" if not lit else _frames_listed(dark) + ": ") + "frames without their picture (a missed "
                       "exposure, a black or flashed frame)")
        if lit:
            why.append(("" if not dark else _frames_listed(lit) + ": ") + "frames with a picture in which every "
                       "marker was lost at once (a jolt of the head or the C-arm, motion blur, or something over the "
                       "field: look at them)")
        out.append(warning(
            "frames-without-markers",
            "track: frames in which no marker was found, between frames where they were"
            + (" or where the seeds put them" if seeded else "") + " ("
            + _frames_listed(empty) + "): " + "; ".join(why) + "; the markers were followed across them (lost and "
              "refound events), the frames have no 3-D point from that view",
            log, frames=empty, without_picture=dark, with_picture=lit))
    lag = _lag_warning(info, views)
    if lag is not None:
        out.append(lag)
    faint = _faint_warning(info, views)
    if faint is not None:
        out.append(faint)
    rare = _rarely_found(table) if seeded else {}
    if rare:
        out.append(warning(
            "markers-rarely-found",
            f"track: seeded markers found in fewer than {100 * RARELY_FOUND:.0f} % of their view's frames ("
            + "; ".join(f"{v}: " + ", ".join(f"{m} {k} of {n}" for m, (k, n) in ms.items()) for v, ms in rare.items())
            + "): too faint for the noise, or hidden; their tracks and 3-D points are mostly missing and what was "
              "found may be noise: look at the frames (a config's detection.window_k_sigma lowers the search "
              "threshold)",
            log, markers={v: {m: {"found": k, "frames": n} for m, (k, n) in ms.items()} for v, ms in rare.items()}))
    counts = {v: info[v]["n_frames"] for v in views}
    last = {v: int(table.loc[table["view"] == v, "frame"].max()) for v in views}
    rates = _frame_rates(table)
    other_rates = len(rates) > 1 and max(rates.values()) > 1.01 * min(rates.values())
    if len(set(counts.values())) > 1 and len(set(last.values())) > 1 and not other_rates:
        # e.g. a video cut short within its header's tolerance, or a frame file missing: the
        # views' frames are paired by index (and time stamps), so the shorter view's end is
        # where stereo stops
        # a whole-number ratio of the counts: one C-arm filming at a fraction of the other's rate
        # (cam1 at half the rate, one --fps for both: 3-D points 0.33 mm RMS off, only this
        # warning; with --fps cam1=1 --fps cam2=2, 0.017 mm)
        lo_v, hi_v = min(counts, key=counts.get), max(counts, key=counts.get)
        ratio = counts[hi_v] / max(counts[lo_v], 1)
        hint = ""
        if ratio >= 1.9 and abs(ratio - round(ratio)) <= 0.05 * ratio:
            f = cfg.fps_of(hi_v) or cfg.fps_of(lo_v)
            rate = (f"--fps {lo_v}={f / round(ratio):g} --fps {hi_v}={f:g}" if f
                    else f"--fps {lo_v}=F/{round(ratio)} --fps {hi_v}=F")
            hint = (f"; {hi_v} holds {ratio:.2f} times {lo_v}'s frames: if {lo_v} filmed at 1/{round(ratio)} of the "
                    f"rate over the same time, give each view its rate ({rate})")
        out.append(warning("frame-count-mismatch",
                           "track: the views hold different numbers of frames ("
                           + ", ".join(f"{v} {n}" for v, n in counts.items())
                           + "); frames are paired by index and time, the longer views' last frames "
                             "have no partner" + hint, log, n_frames=counts))
    if other_rates:
        # time stamps from the sources (video, DICOM) at different rates: frame k of one view
        # is not taken at frame k's time in the other.  Stereo pairs frames by index; the
        # loop's view-time-offset interpolates one view's tracks to the other's times (offset
        # 0 if the clocks agree), over the frames both views hold
        out.append(warning(
            "frame-rate-mismatch",
            "track: the views' time stamps give different frame rates ("
            + ", ".join(f"{v} {r:.3g}" for v, r in rates.items())
            + " frames/s): frame k of one is not taken with frame k of the other, so the second view's tracks are "
              "interpolated (PCHIP) at the first view's frame times for the 3-D points, over the whole time both "
              "views cover", log, frames_per_s=rates))
    # where each view's times come from: --fps is only for sources without time stamps
    by_view = table.groupby("view", sort=False)
    timed, n_frames = by_view["time_s"].count() > 0, by_view["frame"].nunique()
    untimed = [v for v in views if not timed.get(v, False)]
    given = {v: cfg.fps_of(v) for v in views}
    stamped = {v: r for v, r in rates.items() if not cfg.fps_over_stamps and given.get(v) is not None
               and abs(r - given[v]) > 1e-3 * given[v]}
    for v in views:
        own = info.get(v, {}).get("source_stamped", False)
        info.get(v, {})["time_source"] = (
            "none: no time stamps and no --fps" if v in untimed else
            f"--fps {given[v]:g} (over the source's own stamps: --fps-over-stamps)" if cfg.fps_over_stamps
            and given[v] is not None else
            "the source's time stamps" if given[v] is None or v in stamped or own else f"--fps {given[v]:g}")
    if stamped:
        out.append(warning(
            "fps-ignored",
            "track: --fps is not used for " + ", ".join(f"{v} ({r:.4g} frames/s in the source, {given[v]:g} given)"
                                                         for v, r in stamped.items())
            + ": the source's own time stamps are (give --fps only for frames without them, or --fps-over-stamps "
              "where the source's rate is an export's default, not the acquisition's)", log,
            fps=cfg.fps, frames_per_s=stamped))
    untimed = [v for v in untimed if n_frames.get(v, 0) > 1]      # one frame has no time to lose
    if untimed:
        out.append(warning(
            "no-frame-times",
            f"track: {', '.join(untimed)} {'has' if len(untimed) == 1 else 'have'} no time stamps and no --fps "
            "was given: time_s is left empty, and the smoothing and the loop's view-time-offset work in frames; "
            "give --fps for times in seconds", log,
            views=untimed))
    lossy = {v: c for v in views if (c := lossy_compression(cfg.views[v])) is not None}
    if lossy:
        out.append(warning(
            "lossy-frames",
            "track: " + ", ".join(f"{v}'s frames are lossily compressed ({c})" for v, c in lossy.items())
            + ": the codec removes the pixel noise the detector sets its thresholds and each marker's SNR and "
              "sd_px from, and smears small beads, so expect markers lost or taken for clutter and errors larger "
              "than sd_px (six twins written with OpenCV's mp4v: 93.2 % of the visible positions found within "
              "1 px, 99.4 % from their PNG frames); record lossless frames (PNG, TIFF, FFV1) where you can"
            + ("; without seeds the codec's block artefacts start tracks of their own (the bench twin as an mp4v "
               "video: 39,958 positions of clutter without seeds, 94 % of the markers within 1 px with them): "
               "give seeds" if not seeded else ""),
            log, views=lossy, seeds=seeded))
    shifts: dict[str, list] = {}
    for e in events:
        if e["kind"] == "frame-shift":
            shifts.setdefault(e["view"], []).append(float(np.hypot(e["dx_px"], e["dy_px"])))
    if shifts:
        out.append(warning(
            "frame-shifts",
            "track: the whole picture jolted (a C-arm's vibration, the head moving) in "
            + ", ".join(f"{len(s)} frame(s) of {v} (up to {max(s):.1f} px)" for v, s in shifts.items())
            + " (frame-shift events): the markers were followed across the jolts, " + _JOLTS_CARRIED,
            log, views={v: {"n_frames": len(s), "max_px": max(s)} for v, s in shifts.items()}))
    return table, out


#: One view's frames are turned back to the calibration's orientation (the loop's first step,
#: ``view-orientation``) where that brings the two-view points' median ray gap down this many
#: times or more; between :func:`~bsipipe.imaging.track_effects.orientation_check`'s 4 and this,
#: exit 2 (the frames fit neither well).  The bench twin (80 frames) with cam2 mirrored: 23.3
#: times, turned 90 degrees: 338.
ORIENTATION_FACTOR = 10.0


def _two_view_rows(table: pd.DataFrame, pair) -> tuple[pd.DataFrame, str]:
    """The calibrated pair's rows of ``table`` (a copy) and the unit of their ``time_s``: in
    frames where no view has a clock."""
    sub = table[table["view"].isin(pair)].copy()
    if sub["time_s"].isna().all():
        sub["time_s"] = sub["frame"].astype(float)     # no clock: time in frames
        return sub, "frame"
    return sub, "s"


def _turned_back(turned: dict, vpair: tuple, shapes: dict, cfg) -> tuple:
    """``vpair`` with the view whose frames look turned (``turned``, of
    :func:`~bsipipe.imaging.track_effects.orientation_check` or ``pairing_orientation``) taking
    its frames' pixels back to the calibration's (the loop's view-orientation), where the
    evidence is overwhelming (:data:`ORIENTATION_FACTOR`) and the loop is on; else exit 2 naming
    the view and how its frames look: every 3-D point would be off by about the ray gap as the
    frames are (the bench twin with cam2 mirrored: 0.46 mm, turned 90 degrees: 9.7 mm)."""
    from ..imaging.track_effects import reoriented_view, swapped_views
    ratio = turned["median_gap_as_is_mm"] / max(turned["median_gap_mm"], 1e-12)
    turned["ratio"] = ratio
    what = turned.get("measure", "the rays' median gap")
    swapped = turned["orientation"] == "swapped"
    if not cfg.loop or ratio < ORIENTATION_FACTOR:
        if swapped:
            how, given, act, path = ("with the views exchanged", "as given", "exchange them", cfg.views[vpair[0].name])
            fix = "give each --view its own camera's frames (and the seeds their view's names)"
        else:
            how, given, act, path = ("with its positions so turned back", "as the frames are", "turn a view back",
                                     cfg.views[turned["view"]])
            fix = ("export the frames as the calibration images were, or calibrate from frames oriented as these "
                   "(without --calibration the 2-D tracks are written as the frames are)")
        raise InputError(
            f"{_orientation_said(turned)}: {what} is {turned['median_gap_mm']:.3g} mm {how}, "
            f"{turned['median_gap_as_is_mm']:.3g} mm {given} "
            f"({turned['n_points']} two-view " + ("pairs" if "measure" in turned else "points")
            + (f", {ratio:.3g} times: under {ORIENTATION_FACTOR:g} the loop does not {act}" if cfg.loop
               else f"; the loop, off here, would {act}") + f"); {fix}", path=path)
    if swapped:
        return swapped_views(vpair)
    return tuple(reoriented_view(g, turned["map_back"], shapes[g.name]) if g.name == turned["view"] else g
                 for g in vpair)


def _orientation_said(turned: dict) -> str:
    """How the frames look against the calibration (``turned``: :func:`_turned_back`'s), for the
    refusal and the warning alike."""
    if turned["orientation"] == "swapped":
        return (f"the frames of {turned['view']} look swapped against the calibration (each view's frames are the "
                "other camera's)")
    return f"{turned['view']}'s frames look {turned['orientation']} against the calibration"


def _orientation_warning(turned: dict) -> dict:
    """The ``view-orientation`` warning of a view (or pair) the loop turned back or exchanged."""
    from ..quality import warning
    swapped = turned["orientation"] == "swapped"
    done = ("each view was triangulated through the other's camera" if swapped else
            "its positions were taken back to the calibration's orientation before triangulating")
    return warning(
        "view-orientation",
        f"track: {_orientation_said(turned)} ({turned.get('measure', 'the median ray gap')} "
        f"{turned['median_gap_as_is_mm']:.3g} mm as the frames are, {turned['median_gap_mm']:.3g} mm "
        + ("with the views exchanged" if swapped else "with its positions turned back")
        + f", over {turned['n_points']} two-view " + ("pairs" if "measure" in turned else "points")
        + f"): {done} (the loop's view-orientation step); markers2d.csv and the XMALab/DLTdv files keep the "
          "frames' own pixels and the views' names as given. Check that the frames were exported and named as "
          "intended", log, view=turned["view"], orientation=turned["orientation"],
        median_gap_as_is_mm=turned["median_gap_as_is_mm"], median_gap_mm=turned["median_gap_mm"])


def _orientation_step(loop_dict: dict, turned: dict, as_is) -> None:
    """Put the view-orientation correction in front of the loop's steps (in place): the
    declared model's fit on the frames as they are becomes the baseline, the step takes it to
    the loop's own baseline (the view turned back).  ``as_is``: that fit
    (:class:`~bsipipe.imaging.track_effects.StereoFit`; None where no track paired as the frames
    are)."""
    from ..imaging.track_effects import _summary
    from ..loop import gaussian_bic
    after = loop_dict["baseline"]
    if as_is is not None and len(as_is.residuals):
        e = np.asarray(as_is.residuals, float)
        n, rss = len(e), float(np.dot(e, e))
        before = {"model": as_is.spec.describe(), "params": as_is.params, "rmse_mm": float(np.sqrt(rss / n)),
                  "bic": gaussian_bic(rss, n, as_is.n_params), "n_obs": n, "n_params": as_is.n_params,
                  **_summary(as_is)}
    else:
        nan = float("nan")
        before = {"model": after["model"], "params": {}, "rmse_mm": nan, "ray_gap_rms_mm": nan,
                  "ray_gap_median_mm": None, "reprojection_rms_px": nan, "n_two_view": 0, "n_single_view": 0}
    params = {"view": turned["view"], "orientation": turned["orientation"], "map_back": turned["map_back"]}
    step = {"effect": "view-orientation",
            "explanation": "one view's frames are mirrored or turned against the calibration (a display or "
                           "export setting that flips the picture, a calibration taken from frames oriented "
                           "otherwise), or the two views' frames are given the other way round",
            "signature": "ray gaps many times the calibration's, which fall to its level with that view's "
                         "positions mirrored or turned back, or with the views exchanged",
            "model": after["model"],
            "evidence": {"criterion": ("median-pair-cost-ratio" if "measure" in turned else "median-ray-gap-ratio"),
                         "median_gap_as_is_mm": turned["median_gap_as_is_mm"],
                         "median_gap_turned_back_mm": turned["median_gap_mm"], "ratio": turned["ratio"],
                         "threshold": ORIENTATION_FACTOR, "n_points": turned["n_points"],
                         **({"n_pairs_as_is": turned["n_points_as_is"]} if "n_points_as_is" in turned else {})},
            "rmse_mm_before": before["rmse_mm"], "rmse_mm_after": after.get("rmse_mm", after["ray_gap_rms_mm"]),
            "ray_gap_rms_mm_before": before["ray_gap_rms_mm"], "ray_gap_rms_mm_after": after["ray_gap_rms_mm"],
            "reprojection_rms_px_before": before["reprojection_rms_px"],
            "reprojection_rms_px_after": after["reprojection_rms_px"],
            "params": {**after["params"], **params}, "effect_params": params}
    # every model after the step has the view turned back: "stereo+view-orientation+..."
    for d in (step, loop_dict["final"], *loop_dict["steps"]):
        head, _, rest = d["model"].partition("+")
        d["model"] = head + "+view-orientation" + ("+" + rest if rest else "")
    loop_dict["baseline"] = before
    loop_dict["steps"].insert(0, step)


def _stereo(table: pd.DataFrame, events: list[dict], warnings: list[dict], cfg, rig, pair, seed_df,
            per_view_d: dict, det, rois: dict, info: dict) -> dict:
    """Triangulate the calibrated pair and close the loop on it
    (:func:`~bsipipe.imaging.track_effects.close_stereo_loop`); what the loop finds (identity
    swaps, a track held by something else, the frames' common shifts) is corrected in the 2-D
    ``table`` too.  Automatic tracks are first named across the views.  Appends to ``events``
    and ``warnings``; returns ``table``, ``points3d``, ``loop``, ``fit``, ``data``,
    ``time_unit``, ``vpair`` and ``cross_view`` (the renaming, or None)."""
    from ..imaging.detect import FieldOfView
    from ..imaging.track_effects import (CAPTURE_COLUMNS, StereoSpec, WindowSource, close_stereo_loop,
                                         match_tracks_across_views, orientation_check, pairing_orientation,
                                         stereo_data, stereo_fit)
    from ..io.images import decode_workers
    from ..quality import warning
    vpair = (rig[pair[0]], rig[pair[1]])
    shapes = {v: info[v]["frame_shape_px"] for v in pair}
    cross_view = None
    # the view-orientation step: how the frames look (or None) and the two-view data as they are
    oriented = as_is_data = None
    if seed_df is None:
        # automatic tracks are named per view: pair them across the views by their ray gaps, with
        # a view's frames turned back first where they pair only so (pairing_orientation)
        oriented = pairing_orientation(table, vpair, shapes)
        as_is_vpair = vpair
        if oriented is not None:
            vpair = _turned_back(oriented, vpair, shapes, cfg)
        crossed: list = []
        names = match_tracks_across_views(table, vpair, ambiguous=crossed)
        if oriented is not None:
            # the step's "before": the frames as they are, their tracks paired as they were
            t0 = table.copy()
            _rename_markers(t0, [], pair[1], match_tracks_across_views(table, as_is_vpair))
            as_is_data = stereo_data(_two_view_rows(t0, pair)[0], as_is_vpair)
            del t0
        if crossed:
            warnings.append(warning(
                "cross-view-ambiguous",
                "track: without seeds, these tracks pair across the views almost as well crosswise (markers on "
                "nearly one epipolar line in both views: the geometry cannot tell them apart, and a crossed pair "
                "is millimetres off): " + "; ".join(
                    f"{a1}+{pair[1]}:{b1} and {a2}+{pair[1]}:{b2} (median |ray gap| sums {c0:.3g} mm paired so, "
                    f"{c1:.3g} crosswise)" for a1, b1, a2, b2, c0, c1 in crossed)
                + "; give seeds that name them in both views", log,
                pairs=[{"a": [a1, a2], "b": [b1, b2], "cost_mm": c0, "crossed_cost_mm": c1}
                       for a1, b1, a2, b2, c0, c1 in crossed]))
        _rename_markers(table, events, pair[1], names)
        cross_view = {"view": pair[1], "renamed": names,
                      "rule": "median |ray gap| (least over whole-frame shifts of up to 3 frames), pairing of least "
                               "total cost, a track left unpaired above 5x the lower quartile of the best costs "
                               "(0.3-1 mm)"}
    sub, time_unit = _two_view_rows(table, pair)
    data = stereo_data(sub, vpair)
    if oriented is None:
        oriented = orientation_check(data, shapes)
        if oriented is not None:
            as_is_data = data
            vpair = _turned_back(oriented, vpair, shapes, cfg)
            data = stereo_data(sub, vpair)
    as_is = (stereo_fit(as_is_data, StereoSpec(), max_offset_s=cfg.max_offset_s)
             if as_is_data is not None and as_is_data.markers else None)
    del sub, as_is_data
    if det.parity == "none":
        # the frames can be searched again in windows, for the loop's track-capture
        data.windows = WindowSource({v: cfg.views[v] for v in pair}, {v: per_view_d[v] for v in pair},
                                    {v: cfg.polarity_of(v) for v in pair}, det, channel=cfg.channel,
                                    workers=decode_workers(),
                                    rois={v: rois[v] for v in pair if isinstance(rois.get(v), FieldOfView)})
    if not data.markers:
        if seed_df is not None:
            raise InputError(f"no marker is tracked in both {pair[0]} and {pair[1]} (the seeds must use the same "
                             "marker names in both views)", path=cfg.seeds)
        n = int(table["frame"].nunique())
        raise ProcessingError(f"no automatic track of {pair[0]} was paired with one of {pair[1]} by their ray gaps"
                              + (f": {n} frame(s); automatic tracks need at least "
                                 f"{cfg.tracking.min_track_frames} (give seeds for shorter sequences)"
                                 if n < cfg.tracking.min_track_frames else
                                 " (check the calibration's camera names and the views)"),
                              path=cfg.views[pair[0]])
    if seed_df is not None:
        # a marker seeded in one of the two views has no 3-D point: said, not left out silently
        names = {v: list(dict.fromkeys(seed_df.loc[seed_df["view"] == v, "marker"])) for v in pair}
        alone = {v: [m for m in names[v] if m not in set(names[o])] for v, o in (pair, pair[::-1])}
        alone = {v: ms for v, ms in alone.items() if ms}
        if alone:
            warnings.append(warning(
                "single-view-markers",
                "track: markers seeded in only one of the calibrated views are tracked in 2-D there with no "
                "3-D point: " + "; ".join(f"{', '.join(ms)} ({v} only)" for v, ms in alone.items())
                + " (seed each in both views under the same name to triangulate it)", log, markers=alone))
    loop_dict, fit, _ = close_stereo_loop(data, loop=cfg.loop, max_offset_s=cfg.max_offset_s)
    if oriented is not None:
        _orientation_step(loop_dict, oriented, as_is)
        warnings.append(_orientation_warning(oriented))
    loop_dict["time_unit"] = time_unit
    if fit.spec.occlusion:
        # the loop's occlusion effect left these samples out of the 3-D points (a marker at the
        # edge of what hides it, its centre pulled): said in the 2-D table too (status)
        for v, sus in ((pair[0], data.suspect_a), (pair[1], data.suspect_b)):
            fi, mi = np.nonzero(sus)
            if len(fi):
                cells = pd.MultiIndex.from_arrays([data.frames[fi], np.asarray(data.markers, dtype=object)[mi]])
                at = pd.MultiIndex.from_arrays([table["frame"].to_numpy(), table["marker"].to_numpy()])
                hit = (table["view"] == v).to_numpy() & at.isin(cells) & (table["status"] == "found").to_numpy()
                table.loc[hit, "status"] = "partly-hidden"
    if fit.params.get("frame_steps"):
        # frames lost or repeated by one view partway through (the loop's dropped-frames):
        # said, with where, so the user can check the recording
        steps = fit.params["frame_steps"]
        warnings.append(warning(
            "dropped-frames",
            "track: the loop found the views' frames out of step partway through: "
            + "; ".join(f"{st['view']} lost {st['n_frames']} frame{'s' if st['n_frames'] > 1 else ''} before its frame "
                        f"{st['frame']}" if st["kind"] == "lost" else
                        f"{st['view']} repeated its frame {st['frame'] - 1} {st['n_frames']} time"
                        f"{'s' if st['n_frames'] > 1 else ''} (frame {st['frame']} on)" for st in steps)
            + ". The frames are paired by their times put right (the other view's tracks interpolated across a "
              "gap; a repeated frame's copies hold nothing new and have no 3-D point); markers3d.csv's time_s has "
              "the times put right, markers2d.csv keeps each view's own count. Check the recording (a capture "
              "that skipped or repeated frames, frame files deleted and the rest renumbered)", log, steps=steps))
    mis = fit.params.get("rig_mismatch")
    if mis:
        # the loop's rig-mismatch: the rays miss each other by a steady field over the markers
        scatter = float(np.sqrt(np.mean(fit.residuals ** 2))) if len(fit.residuals) else float("nan")
        worst = sorted(mis["bias_mm"].items(), key=lambda kv: -abs(kv[1]))[:5]
        warnings.append(warning(
            "rig-mismatch",
            f"track: the loop found the views' rays missing each other by a steady amount that changes with where "
            f"the marker is (rig-mismatch: RMS {mis['rms_bias_mm']:.3g} mm over {mis['n_markers']} markers, e.g. "
            + ", ".join(f"{m} {b:+.3g}" for m, b in worst)
            + f" mm, against {scatter:.2g} mm of ray-gap scatter about it): the views no longer match the "
              "calibration (a C-arm moved or turned since it was calibrated, or the calibration is another "
              "session's"
            + ("; or, with the loop's frame-shift, the mean of a view's jolts, which shifts its picture as a whole"
               if fit.spec.frame_shift else "")
            + "). The 3-D points carry an error that their sds do not show, across the rays at least this size "
              "and along them, where the gaps cannot see it, possibly many times more (cam2 turned 0.3 degrees "
              "about its own centre: gaps 0.039 mm, points 3.3 mm off): calibrate again with the C-arms as they "
              "stood for this trial",
            log, rms_bias_mm=mis["rms_bias_mm"], bias_mm=mis["bias_mm"], ray_gap_scatter_mm=scatter))
    points3d = fit.points.copy()
    if time_unit == "frame":
        points3d["time_s"] = np.nan
    # identity swaps found by the loop are corrected in the 2-D table too
    for sw in fit.swaps:
        a, b = sw["markers"]
        sel = (table["view"] == sw["view"]) & table["frame"].between(sw["first_frame"], sw["last_frame"])
        ia, ib = sel & (table["marker"] == a), sel & (table["marker"] == b)
        table.loc[ia, "marker"], table.loc[ib, "marker"] = b, a
        events.append({"view": sw["view"], "frame": sw["first_frame"], "marker": a, "kind": "identity-swap",
                       "other": b, "last_frame": sw["last_frame"],
                       "detail": "names exchanged by the loop (ray gaps)"})
    # a track the loop found held by something else (track-capture): the re-found positions
    # replace it in the 2-D table; the frames where the marker's image merged with what held
    # it are left empty (status merged)
    for cp in fit.captures:
        key = (table["view"] == cp["view"]) & (table["marker"] == cp["marker"])
        new = pd.DataFrame({"frame": cp["_frames"], **cp["_columns"]}).set_index("frame")
        rows = table.index[key & table["frame"].isin(cp["_frames"])]
        at = table.loc[rows, "frame"].to_numpy()
        for c in CAPTURE_COLUMNS:
            table.loc[rows, c] = new[c].reindex(at).to_numpy()
        table.loc[rows, "found"] = True
        table.loc[rows, "status"] = "found"
        gone = table.index[key & table["frame"].isin(cp["_dropped"])]
        table.loc[gone, ["x_px", "y_px"]] = np.nan
        table.loc[gone, "found"] = False
        table.loc[gone, "status"] = "merged"
        events.append({"view": cp["view"], "frame": cp["first_frame"], "marker": cp["marker"],
                       "kind": "track-capture", "last_frame": cp["last_frame"], "n_refound": cp["n_refound"],
                       "n_left_out": cp["n_left_out"],
                       "detail": "the track was held by something else in its window: the marker was found "
                                 "again along the other view's rays by the loop"})
    if fit.frame_shifts:
        # each view's common shift per frame (frame-shift): a column of the 2-D table, taken
        # out of the smoothed centres and of the 3-D points
        sh = pd.concat([pd.DataFrame({"view": v, "frame": data.frames, "shift_x_px": o[:, 0], "shift_y_px": o[:, 1]})
                        for v, o in fit.frame_shifts.items()]).set_index(["view", "frame"])
        idx = pd.MultiIndex.from_arrays([table["view"].astype(str), table["frame"]])
        for c in ("shift_x_px", "shift_y_px"):
            table[c] = sh[c].reindex(idx).to_numpy()
        n_sh = {v: int((o != 0).any(axis=1).sum()) for v, o in fit.frame_shifts.items()}
        for w in warnings:
            if w["code"] == "frame-shifts":
                w["message"] = w["message"].replace(_JOLTS_CARRIED, _JOLTS_TAKEN_OUT)
                w["corrected_by_loop"] = True
                # the warning was logged before the loop ran, saying nothing corrects the jolts
                log.warning("track: frame-shifts, after the loop: %s", _JOLTS_TAKEN_OUT)
        log.info("track: frame-shift: %s", ", ".join(f"{v} {n} frames" for v, n in n_sh.items()))
    table = table.sort_values(["view", "frame", "marker"], kind="stable")
    table["view"] = pd.Categorical(table["view"], categories=list(cfg.views))
    table = table.sort_values(["view", "frame"], kind="stable")
    table["view"] = table["view"].astype(str)
    return {"table": table, "points3d": points3d, "loop": loop_dict, "fit": fit, "data": data,
            "time_unit": time_unit, "vpair": vpair, "cross_view": cross_view}


def _smoothed_points(table: pd.DataFrame, st: dict, smoothing: dict, max_offset_s: float | None, pair):
    """The smoothed centres triangulated with the loop's final model (its offset and drift as
    estimated), the raw points kept as ``*_raw`` columns; the stereo check of the error model
    (``smoothing['stereo_check']``, ``sd_px`` scaled in ``table``) and each point's sd.  Returns
    the points and that fit."""
    from ..imaging.track_effects import StereoSpec, stereo_data, stereo_fit
    fit, vpair = st["fit"], st["vpair"]
    sub = table[table["view"].isin(pair)].copy()
    ok = sub["x_px_smooth"].notna() & sub["y_px_smooth"].notna()
    # a track too short to smooth (fewer than smooth_tracks' min_points) keeps its raw centres:
    # with under 5 frames no track is smoothed, and the 3-D table had been left empty
    smoothed = ok.groupby([sub["view"], sub["marker"]]).transform("any")
    sub["x_px"] = sub["x_px_smooth"].where(smoothed, sub["x_px"])
    sub["y_px"] = sub["y_px_smooth"].where(smoothed, sub["y_px"])
    sub["found"] = sub["found"].astype(bool) & (ok | ~smoothed)
    smoothing["raw_tracks_triangulated"] = sorted({f"{v}:{m}" for v, m in sub.loc[~smoothed, ["view", "marker"]]
                                                   .itertuples(index=False)})
    if st["time_unit"] == "frame":
        sub["time_s"] = sub["frame"].astype(float)
    sdata = stereo_data(sub, vpair)
    del sub
    fit = stereo_fit(sdata, StereoSpec(occlusion=fit.spec.occlusion),
                     fixed_offset_s=fit.params.get("view_time_offset_s"),
                     fixed_drift=fit.params.get("view_clock_drift"), fixed_steps=fit.params.get("frame_steps"),
                     max_offset_s=max_offset_s)
    raw = st["points3d"].set_index(["frame", "marker"])[["x_mm", "y_mm", "z_mm", "ray_gap_mm"]]
    points3d = fit.points.copy()
    if st["time_unit"] == "frame":
        points3d["time_s"] = np.nan
    raw = raw.reindex(pd.MultiIndex.from_frame(points3d[["frame", "marker"]]))
    for c in ("x_mm", "y_mm", "z_mm", "ray_gap_mm"):
        points3d[c + "_raw"] = raw[c].to_numpy()
    two = points3d["n_views"] == 2
    smoothing["ray_gap_rms_mm"] = (float(np.sqrt(np.mean(points3d.loc[two, "ray_gap_mm"] ** 2)))
                                   if two.any() else None)
    smoothing["ray_gap_rms_mm_raw"] = st["loop"]["final"]["ray_gap_rms_mm"]
    smoothing["stereo_check"] = _stereo_check(table, points3d, vpair, pair, smoothing["tracks"])
    _point_sds(points3d, table, vpair, pair)
    return points3d, fit


def _marker_summary(table: pd.DataFrame, events: list[dict], fit) -> dict:
    """track.json's ``markers``: per marker and view its found frames, signal-to-noise and
    events; per marker its 3-D points' counts, ray gap and reprojection error."""
    markers: dict = {}
    kinds = Counter((e.get("view"), e.get("marker"), e.get("kind")) for e in events)
    for (v, m), g in table.groupby(["view", "marker"], sort=False):
        snr = g.loc[g["found"], "snr"]
        markers.setdefault(m, {})[v] = {
            "found_frames": int(g["found"].sum()), "n_frames": int(len(g)),
            "median_snr": float(snr.median()) if len(snr) else None,
            "min_snr": float(snr.min()) if len(snr) else None,
            **{k: int(kinds[(v, m, k)]) for k in ("lost", "refound", "ambiguous", "partial")},
            "excursions": int(kinds[(v, m, "excursion")])}
    if fit is not None:
        for m, g in fit.points.groupby("marker"):
            two = g[g["n_views"] == 2]
            markers.setdefault(m, {})["3d"] = {
                "n_points": int(np.isfinite(g["x_mm"]).sum()), "n_two_view": int(len(two)),
                "ray_gap_rms_mm": float(np.sqrt(np.mean(two["ray_gap_mm"] ** 2))) if len(two) else None,
                "reprojection_rms_px": float(np.sqrt(np.mean(two["reproj_err_px"] ** 2))) if len(two) else None}
    return markers


def _add_figures(rs, table: pd.DataFrame, points3d, first_images: dict, info: dict, rois: dict, seed_df,
                 per_view_d: dict) -> None:
    """``track.png`` (the trajectories) and ``overlay.png`` (each view's first frame with the
    detections and the region searched), both laid out with fixed margins: drawn once, not
    twice for a tight crop."""
    from ..imaging.detect import FieldOfView
    from ..report.track_figure import overlay_figure, trajectories_figure
    rs.add_figure("track.png", trajectories_figure(table, points3d, title="bsipipe track"), tight=False)
    # the region each view was searched in: a given one, else the field found in its frames
    regions = {}
    for v in first_images:
        fi = info.get(v, {}).get("field_of_view") or {}
        if isinstance(rois.get(v), FieldOfView):
            regions[v] = rois[v]
        elif fi.get("found"):
            regions[v] = FieldOfView(tuple(fi["shape"]), tuple(fi["centre_px"]), float(fi["radius_px"]), True)
    first = {v: int(table.loc[table["view"] == v, "frame"].min()) for v in first_images}
    rs.add_figure("overlay.png", overlay_figure(first_images, table, first, seed_df, per_view_d, regions), tight=False)


#: Every file track writes (one an earlier run left in the folder that this run does not
#: write is removed: a 2-D run does not write markers3d.csv, xmalab_3d.csv, loop.md).
TRACK_OUTPUTS = ("markers2d.csv", "xmalab_2d.csv", "dltdv_xypts.csv", "markers3d.csv", "xmalab_3d.csv", "loop.md", "track.png",
                 "overlay.png", "track.json")


def run(config_path=None, *, out, view=(), calibration=None, polarity=None, diameter_px=None, seeds=None,
        fps=None, loop=None, progress: bool = False, **extra) -> dict:
    """The whole command; returns the ``track.json`` content (already written to ``out``).

    Everything that can be checked before the frames are tracked is (the sources, the
    calibration against the frames' size, the seeds, the markers' polarity and diameter);
    then each view is tracked, the frames are checked against the tracks, the calibrated pair
    is triangulated and the loop closed on it, the tracks are smoothed, and the results are
    written together (:class:`~bsipipe.provenance.ResultSet`), ``track.json`` last."""
    from ..imaging.track import TrackSettings
    from ..io.seeds import read_seeds
    from ..provenance import ResultSet, provenance
    from ..quality import warning

    cfg = build_config(config_path, view=view, calibration=calibration, polarity=polarity,
                       diameter_px=diameter_px, seeds=seeds, fps=fps, loop=loop, **extra)
    views = list(cfg.views)
    for v, p in cfg.views.items():
        if not (os.path.exists(p) or any(c in p for c in "*?[")):
            raise InputError(f"view {v}: no such file or folder", path=p)
        if os.path.isdir(p) and Path(out).resolve().is_relative_to(Path(p).resolve()):
            # the figures (PNG) would be read as frames by the next run on that folder
            raise InputError(f"the output folder {out} is inside view {v}'s folder of frames: its figures would be "
                             "read as frames; write the results elsewhere", path=p)

    # each view's first frame, for the seeds' check, the polarity and the diameter (then let go)
    given_roi = _given_roi(cfg)
    firsts, blank_firsts = _first_frames(cfg.views, cfg.channel)
    shapes = {v: None if im is None else im.shape for v, im in firsts.items()}
    rois = _resolve_rois(cfg, shapes, config_path) if given_roi else _roi_per_view(cfg)
    _check_diameter(cfg, shapes, config_path)
    _rates_for_unstamped_views(cfg, views)
    rig = pair = cal_rms = None
    if cfg.calibration:
        rig, pair, cal_rms = _read_calibration(cfg.calibration, views, shapes)
        _check_frame_sizes(rig, pair, shapes, cfg.calibration)
    seed_df = read_seeds(cfg.seeds, views, shapes) if cfg.seeds else None
    if seed_df is not None:
        outside = _seeds_outside(seed_df, rois)
        if outside:
            raise InputError("seeds outside their view's given region of interest (detection.roi): "
                             + "; ".join(f"{m} in {v} at ({x:.1f}, {y:.1f})" for v, m, x, y in outside),
                             path=cfg.seeds)
    cfg, (polarity_note, polarity_counts), (d, per_view_d, diameter_note) = _marker_size(
        cfg, views, firsts, seed_df, rois)
    del firsts
    together = _seeds_together(seed_df, per_view_d) if seed_df is not None else []
    warnings: list[dict] = []
    if blank_firsts:
        warnings.append(warning(
            "blank-first-frame",
            "track: first frame without a picture (a missed exposure, or the grabber started before the X-rays): "
            + "; ".join(f"{v}: the polarity and diameter probed on frame {k}" if k else
                        f"{v}: so are the next {BLANK_LOOKAHEAD}, probed on frame 0" for v, k in blank_firsts.items())
            + (" (the seeds are still positions in frame 0: the markers are looked for there in the next frames)"
               if seed_df is not None else ""), log, views=blank_firsts))
    if together:
        # said (logged) before the run: a marker seeded twice ends "not found in any frame" after it
        warnings.append(warning(
            "seeds-together",
            "track: seeds within half a marker diameter of each other (one marker seeded twice under two names, "
            "or two markers overlapping in the first frame): "
            + "; ".join(f"{a} and {b} in {v}, {dist:.2g} px" for v, a, b, dist, _ in together), log,
            pairs=[{"view": v, "markers": [a, b], "distance_px": dist} for v, a, b, dist, _ in together]))
    det = _detection_settings(cfg, d, diameter_note, seed_df is not None, config_path)
    tk = TrackSettings(**cfg.tracking.model_dump())

    # frames decode on other threads while the tracker works: the other cores are taken, and
    # OpenCV's own thread pool on whole-frame morphology would compete with the readers
    # (measured with one reader: about 15 % more CPU for no shorter wall time on two cores)
    import cv2
    cv2_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        tables, events, info, first_images, frame_hashes = _track_views(
            cfg, views, seed_df, per_view_d, det, tk, progress, rois)
    finally:
        cv2.setNumThreads(cv2_threads)
    table = pd.concat(tables, ignore_index=True)
    del tables          # the per-view tables: a second copy of the 2-D table for the rest of the run
    if seed_df is not None:
        _check_seeds_found(table, seed_df, together, info, cfg.seeds)
    if table.empty or not table["found"].any():
        raise ProcessingError("no marker was found in any frame (check --polarity and --diameter-px)",
                              path=next(iter(cfg.views.values())))
    warnings += _seed_warnings(seed_df, {v: cfg.polarity_of(v) for v in views}, polarity_note, polarity_counts)
    if seed_df is not None:
        warnings += _seeds_far(table, seed_df, per_view_d, tk)
    table, more = _sequence_warnings(table, events, cfg, views, info, seed_df is not None)
    if seed_df is not None:
        _larger_markers_said(more, first_images, seed_df, per_view_d, {v: cfg.polarity_of(v) for v in views})
    warnings += more

    st = None
    points3d = fit = lag_fix = None
    unpaired_names = None
    if rig is None and seed_df is None and len(views) > 1:
        # automatic tracks without a calibration: each view names its own, and nothing pairs
        # them; the names of the views after the first carry their view, so the XMALab 2-D
        # file (marker-major columns) does not put unrelated tracks under one marker
        renamed = {}
        for v in views[1:]:
            renamed[v] = {m: f"{v}:{m}" for m in pd.unique(table.loc[table["view"] == v, "marker"])}
            _rename_markers(table, events, v, renamed[v])
        unpaired_names = {"renamed": renamed,
                          "rule": "no calibration and no seeds: the views' tracks are not paired; the names of the "
                                  "views after the first carry their view"}
    if rig is not None:
        st = _stereo(table, events, warnings, cfg, rig, pair, seed_df, per_view_d, det, rois, info)
        table, points3d, fit = st["table"], st["points3d"], st["fit"]
        w = _calibration_fit_warning(st["loop"], table, cal_rms, pair)
        if w is not None:
            warnings.append(w)
    if seed_df is None:
        warnings += _tracks_incomplete(table)      # after the views' tracks are named alike
    if rig is not None:
        warnings += _merged_in_both_views(table, events, pair)
    smoothing = None
    if cfg.smooth:
        table, smoothing = _smooth(table)
        if st is not None:
            points3d, fit = _smoothed_points(table, st, smoothing, cfg.max_offset_s, pair)
    if points3d is not None:
        if cfg.lowpass_hz is not None:
            rate = cfg.fps_of(pair[0]) if pair else None
            rate = rate or (1.0 / np.nanmedian(np.diff(st["data"].ta)) if st["time_unit"] == "s" else None)
            if rate is None:
                raise InputError("--lowpass-hz needs a frame rate (--fps or time stamps)", path=config_path,
                                 key="lowpass_hz")
            from ..imaging.triangulate import lowpass_trajectories
            try:
                points3d = lowpass_trajectories(points3d, cfg.lowpass_hz, rate)
            except ValueError as e:
                raise InputError(str(e), path=config_path, key="lowpass_hz") from None
        warnings += _ray_gap_warnings(points3d, cfg.max_ray_gap_mm)
        if seed_df is None:
            warnings += _pairing_suspects(points3d)
        lossy = next((w["views"] for w in warnings if w["code"] == "lossy-frames"), {})
        lag_fix = _lag_correction(info, table, pair, points3d, fit, cfg, lossy)
        if lag_fix is not None:
            for w in warnings:
                if w["code"] == "frames-averaged":
                    w["message"] += (f"; markers3d.csv's time_s is moved back by {lag_fix['shift_s']:.4g} s "
                                     f"({lag_fix['lag_frames']:.3g} frame), to when the markers were where the "
                                     f"frames show them (correct_lag)" if lag_fix["applied"] else
                                     f"; markers3d.csv's time_s is left as stamped: {lag_fix['why_not']}")
                    w["lag_correction"] = lag_fix

    rs = ResultSet(out, primary="track.json", outputs=TRACK_OUTPUTS)
    cols2d = ["view", "frame", "marker", "x_px", "y_px", "time_s", "found", "status", "snr", "amplitude",
              "area_px", "sigma_px", "pred_x_px", "pred_y_px", "gate_px"]
    if "shift_x_px" in table:
        cols2d += ["shift_x_px", "shift_y_px"]
    if smoothing is not None:
        cols2d += ["sd_px", "x_px_smooth", "y_px_smooth", "sd_px_smooth", "smooth_outlier"]
    rs.add_csv("markers2d.csv", table[cols2d], float_format="%.6f", na_rep="")
    from ..io.dltdv import format_dltdv_xypts
    from ..io.xmalab import format_xmalab_2d, format_xmalab_3d, xmalab_cameras
    marker_order = list(pd.unique(table["marker"]))
    n_frames = int(table["frame"].max()) + 1
    rs.add_text("xmalab_2d.csv", format_xmalab_2d(table[table["found"]], views, marker_order, range(n_frames)))
    text, points = format_dltdv_xypts(table[table["found"]], views, marker_order, range(n_frames))
    rs.add_text("dltdv_xypts.csv", text)
    result: dict = {
        "views": info,
        "xmalab_cameras": xmalab_cameras(views),
        "dltdv": {"file": "dltdv_xypts.csv", "cameras": xmalab_cameras(views), "points": points,
                  "pixels": "DLTdv8's: origin at the top-left corner, the top-left pixel's centre at (1, 1)"},
        "diameter_px": d, "diameter_px_per_view": per_view_d, "diameter_source": diameter_note, "polarity": cfg.polarity if isinstance(cfg.polarity, str) else "per view",
        "polarity_per_view": {v: cfg.polarity_of(v) for v in views}, "polarity_source": polarity_note,
        "markers": _marker_summary(table, events, fit),
        "events": events,
        "warnings": warnings,
    }
    if st is not None and st["cross_view"] is not None:
        result["cross_view_names"] = st["cross_view"]
    elif unpaired_names is not None:
        result["cross_view_names"] = unpaired_names
    if smoothing is not None:
        result["smoothing"] = smoothing
    if points3d is not None and lag_fix is not None:
        result["lag_correction"] = lag_fix
    if points3d is not None:
        loop_dict = st["loop"]
        cols3d = ["frame", "time_s", "marker", "x_mm", "y_mm", "z_mm", "ray_gap_mm", "ray_gap_signed_mm",
                  "reproj_err_px", f"reproj_{pair[0]}_px", f"reproj_{pair[1]}_px", "n_views", "source", "flag"]
        cols3d += [c for c in ("sd_x_mm", "sd_y_mm", "sd_z_mm") if c in points3d]
        cols3d += [c for c in points3d.columns if c.endswith("_raw")]
        cols3d += [c for c in points3d.columns if c.endswith("_filt")] + (["filtered"] if "filtered" in points3d else [])
        rs.add_csv("markers3d.csv", points3d[cols3d], float_format="%.6f", na_rep="")
        rs.add_text("xmalab_3d.csv", format_xmalab_3d(points3d[points3d["n_views"] > 0], marker_order,
                                                      range(n_frames)))
        result["stereo"] = {"views": list(pair), "world_frame": f"camera {pair[0]} (calibration.json stereo)"}
        result["summary"] = {k: loop_dict["final"][k] for k in ("ray_gap_rms_mm", "ray_gap_median_mm",
                                                                 "reprojection_rms_px", "n_two_view", "n_single_view")}
        result["loop"] = loop_dict
        if loop_dict.get("enabled"):
            from ..report.loop_report import loop_markdown
            rs.add_text("loop.md", loop_markdown(loop_dict, title="Tracking and triangulation: closing the loop "
                                                                "(RMSE = ray gap RMS)"))
    else:
        result["loop"] = None
        result["loop_note"] = "no calibration: 2-D tracking only, nothing to triangulate or close the loop on"
    if cfg.figures:
        _add_figures(rs, table, points3d, first_images, info, rois, seed_df, per_view_d)
    inputs = ([p for p in cfg.views.values()] + [p for p in (cfg.calibration, cfg.seeds) if p]
              + roi_masks(cfg.detection.roi))
    result["provenance"] = provenance(cfg, inputs, command="track", known_hashes=frame_hashes)
    rs.add_json("track.json", result)
    rs.commit()
    return result
