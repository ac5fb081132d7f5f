r"""Marker tracking through a frame sequence: prediction, global assignment, gap closing.

Each marker keeps its last measured position :math:`p`, the frame :math:`f_0` it was
measured in, and a velocity :math:`v` (px per frame, from its last two measurements).  In
frame :math:`f` it is expected at

.. math::  \hat p = p + v\,\min(f - f_0, n_x) \qquad \text{(constant velocity; } v = 0 \text{ for ``static``)}

within a gate of radius :math:`g = g_0 + g_1 (f - f_0 - 1)`, capped at :math:`g_{max}`: the
gate grows while a marker is hidden, so a marker that reappears is found again near where
its motion carried it (the velocity is carried at most :math:`n_x` =
``max_extrapolation_frames`` frames).  Candidates are detected only inside the gates
(:func:`~bsipipe.imaging.detect.window_candidates`), and markers and candidates are matched
all at once by :func:`scipy.optimize.linear_sum_assignment` on the cost
:math:`\|c - \hat p\|^2 / g^2` (pairs outside a gate are not allowed), so two markers that
pass close to each other keep their names: the assignment that fits both predictions wins,
not the nearest neighbour of whichever marker is looked at first.

Every change is reported as an event (``events``: view, frame, marker, kind, detail):

- ``lost``: no candidate in the marker's gate (or the only one was a better match for
  another marker); its position is NaN until it is found again.
- ``refound``: found again after ``gap_frames`` frames, ``distance_px`` from the prediction.
- ``ambiguous``: two markers whose gates share candidates could be matched the other way
  round at a cost less than ``ambiguity_px**2`` higher: an identity swap is possible here.
- ``partial``: the marker's amplitude fell below ``partial_fraction`` of its median (it is
  partly hidden, e.g. entering the shadow of an instrument): its centre may be biased.
- ``appeared`` (automatic tracks): first found after the view's first frame (hidden,
  outside the field or too faint before it).
- ``frame-shift`` (``marker`` None): the whole picture moved between two frames (the C-arm
  or the head jolted; ``dx_px``, ``dy_px``): the markers seen in the frame before were
  missed, or found off their predictions by a common offset, and the offset most of them
  agree on (:func:`_frame_shift`) was added to every prediction (and left out of the
  velocities).  ``frame_shift=False`` in the settings switches this off.

Without seeds (:func:`_track_swept`) the whole frame is searched
(:func:`~bsipipe.imaging.detect.detect_arrays`, the intensifier's field found once, in the
first frame, as with seeds) in the first frame, every ``sweep_every_frames``-th and the last;
a detection that no track holds starts a new track, which is first followed backwards through
the last ``back_frames`` frames (as tracks are followed forwards), then forwards with the
others.  In between, every track
is searched for in its own window exactly as a seeded marker is (the per-frame work is that of
the seeded mode, not a whole-frame detection); where the windows would hold more pixels than
half the frame, the frame is searched whole instead (and swept).  A track not seen for more than ``memory``
frames ends, a new one not yet seen in ``min_track_frames`` frames at its first miss; a new
track that starts where an ended one would have been found had it still been searched for
(within the gate grown since its last position, looking like it) continues it, under its
name (gap closing across an occlusion, as with seeds).  With
trackpy parity every frame is detected whole as ``trackpy.locate`` does and the detections are
linked (:func:`link_detections`).
"""

from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass, field
from typing import Iterable, Literal

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from .detect import COLUMNS as DETECT_COLUMNS
from .detect import (DetectionSettings, FieldOfView, Polarity, detect_arrays, detect_markers, find_field_of_view,
                     window_arrays, window_strip_px)
from .detect import _DarkObjects

log = logging.getLogger(__name__)

Motion = Literal["constant-velocity", "static"]

#: Columns of the tidy 2-D table, one row per view, frame and marker.
TRACK_COLUMNS = ["view", "frame", "time_s", "marker", "x_px", "y_px", "found", "snr", "amplitude",
                 "area_px", "sigma_px", "pred_x_px", "pred_y_px", "gate_px", "status"]


@dataclass(frozen=True)
class TrackSettings:
    """Knobs of the tracker (defaults in units of the marker diameter ``d``).

    ``gate_px`` (default ``max(3, 1.5 d)``): search radius one frame after a measurement;
    ``gate_growth_px`` (default ``0.25 d``) added per missed frame, up to ``max_gate_px``
    (default ``4 d``); ``seed_radius_px`` (default ``max(4, 1.5 d)``): how far a marker may
    be from its seed (a click) in the first frame; ``motion``: ``constant-velocity`` or
    ``static``; ``max_extrapolation_frames``: a hidden marker is predicted to move on at its
    last velocity for at most this many frames, then to stay (a velocity measured as the
    marker slid behind an instrument, or from one noisy centre, carried through a long
    occlusion would put the prediction far from where it reappears; the growing gate
    covers what it really moved); ``ambiguity_px`` (default ``d/2``); ``partial_fraction``; ``appearance``:
    (min, max) factors of a marker's median amplitude and (min, max) of its median fitted
    width a candidate must lie within to be taken for it (an instrument's edge or a larger
    bead is not the marker that vanished behind it); ``memory``:
    frames a track may miss before it ends (automatic mode only; seeded markers are looked
    for until the end; a new automatic track ends at its first miss until it has been
    found in ``min_track_frames`` frames); ``min_track_frames``: shorter automatic tracks are
    dropped; ``sweep_every_frames``: automatic mode searches the whole frame for new markers
    in the first frame, every this many frames and the last; ``back_frames``: it follows a
    new one back through at most this many frames (held in memory);
    ``second_look_k_sigma``: a seeded marker that nothing in its gate matched, measured in
    the last ``max_extrapolation_frames`` frames, is looked for once more within
    ``second_look_radius_px`` (default ``max(1, d/4)``) of its prediction with this lower
    window threshold (robust sd of the window's smoothed top-hat, instead of the detector's
    ``window_k_sigma``); a candidate is taken only if it also passes ``second_look_min_snr``
    (2; the detector's ``min_snr`` where that is lower) and looks
    like the whole marker (``appearance`` once the marker has 3 measurements, amplitude at
    least ``partial_fraction`` of its median).  A threshold over a whole search window must
    hold its false alarms down over every pixel of it, and an instrument's edge or bone
    texture in the window inflates the spread it is set from; near the prediction of a
    marker seen a frame or two ago the area is a few pixels and the marker's own amplitude
    and width are the stronger test (None: no second look).  Such positions have status
    ``weak``.  ``frame_shift``: when the markers seen a frame before are missed or found off
    their predictions by a common offset, the offset of the whole picture is looked for
    (:func:`_frame_shift`) and every prediction moved by it (a ``frame-shift`` event).
    ``merge_px`` (default ``1.5 d``): two markers predicted closer than this whose images
    merge into one (one of them finds nothing in its gate but what a neighbour took) are
    ``merged`` until they part: the merged image's centre is neither's, so neither is
    measured (status ``merged``, position left empty) and both move on at their velocities
    from before, for at most ``merge_extrapolation_frames`` frames; where they part, the
    assignment on those predictions gives each its own image (a merged centre taken as a
    measurement had turned both tracks onto one path, and they parted swapped).
    """

    gate_px: float | None = None
    gate_growth_px: float | None = None
    max_gate_px: float | None = None
    seed_radius_px: float | None = None
    motion: Motion = "constant-velocity"
    ambiguity_px: float | None = None
    partial_fraction: float = 0.6
    memory: int = 5
    max_extrapolation_frames: int = 3
    min_track_frames: int = 3
    appearance: tuple[float, float, float, float] = (0.3, 2.5, 0.6, 1.6)
    second_look_k_sigma: float | None = 2.5
    second_look_radius_px: float | None = None
    second_look_min_snr: float = 2.0
    frame_shift: bool = True
    sweep_every_frames: int = 20
    back_frames: int = 60
    merge_px: float | None = None
    merge_extrapolation_frames: int = 20

    def resolved(self, d: float) -> dict:
        return {"gate_px": self.gate_px if self.gate_px is not None else max(3.0, 1.5 * d),
                "gate_growth_px": self.gate_growth_px if self.gate_growth_px is not None else 0.25 * d,
                "max_gate_px": self.max_gate_px if self.max_gate_px is not None else 4.0 * d,
                "seed_radius_px": self.seed_radius_px if self.seed_radius_px is not None else max(4.0, 1.5 * d),
                "ambiguity_px": self.ambiguity_px if self.ambiguity_px is not None else 0.5 * d,
                "second_look_radius_px": (self.second_look_radius_px if self.second_look_radius_px is not None
                                          else max(1.0, 0.25 * d)),
                "merge_px": self.merge_px if self.merge_px is not None else 1.5 * d}


@dataclass
class _Marker:
    name: str
    pos: np.ndarray                  # last measured position (2,)
    frame: int                       # frame of that measurement
    vel: np.ndarray = field(default_factory=lambda: np.zeros(2))
    n_meas: int = 0
    lost_since: int | None = None
    amps: list = field(default_factory=list)
    sigmas: list = field(default_factory=list)
    ended: bool = False
    merged_with: tuple = ()          # names of the markers whose image this one's merged with
    merged_since: int | None = None
    amp_median: float = np.nan
    sigma_median: float = np.nan
    _amps_sorted: list = field(default_factory=list, repr=False)
    _sigmas_sorted: list = field(default_factory=list, repr=False)

    def predict(self, f: int, motion: Motion, max_frames: int | None = None) -> np.ndarray:
        """Expected position in frame ``f``: the last one moved on at the last velocity, for
        at most ``max_frames`` frames (None: all the way)."""
        if motion == "static" or self.n_meas < 2:
            return self.pos.copy()
        df = f - self.frame                     # negative when followed backwards
        if max_frames is not None:
            df = max(-max_frames, min(df, max_frames))
        return self.pos + self.vel * df

    def gate(self, f: int, g0: float, g1: float, gmax: float) -> float:
        return float(min(g0 + g1 * max(abs(f - self.frame) - 1, 0), gmax))

    def update(self, f: int, xy: np.ndarray, amp: float, sigma: float = np.nan, offset=None) -> None:
        """Take the measurement ``xy`` in frame ``f``; ``offset``: a shift of the whole frame
        found in this frame (:func:`_frame_shift`), left out of the velocity."""
        x, y = float(xy[0]), float(xy[1])
        if self.n_meas >= 1:
            dt = f - self.frame
            ox, oy = (0.0, 0.0) if offset is None else (float(offset[0]), float(offset[1]))
            vx, vy = (x - ox - float(self.pos[0])) / dt, (y - oy - float(self.pos[1])) / dt
            # a fresh velocity after a gap, else a light smoothing of the last two
            if not (self.n_meas < 2 or abs(dt) > 1):
                vx, vy = 0.7 * vx + 0.3 * float(self.vel[0]), 0.7 * vy + 0.3 * float(self.vel[1])
            self.vel = np.array([vx, vy])
        self.pos = np.array([x, y])
        self.frame = f
        self.n_meas += 1
        # the last 50 amplitudes and widths, also kept sorted: the medians without a sort
        for v, lst, srt in ((amp, self.amps, self._amps_sorted), (sigma, self.sigmas, self._sigmas_sorted)):
            if math.isfinite(v):
                v = float(v)
                lst.append(v)
                bisect.insort(srt, v)
                if len(lst) > 50:
                    del srt[bisect.bisect_left(srt, lst.pop(0))]
        self.amp_median = _sorted_median(self._amps_sorted) if len(self.amps) >= 3 else np.nan
        self.sigma_median = _sorted_median(self._sigmas_sorted) if len(self.sigmas) >= 3 else np.nan


def _sorted_median(srt: list) -> float:
    """Median of a sorted list (``statistics.median``'s value)."""
    n = len(srt)
    return float(srt[n // 2]) if n % 2 else float((srt[n // 2 - 1] + srt[n // 2]) / 2)


def _looks_like(markers: list[_Marker], amp: np.ndarray, sigma: np.ndarray, settings: "TrackSettings",
                whole=None) -> np.ndarray:
    """Which candidates (amplitudes, widths) could be each marker, (n_markers, n_candidates)
    bool: within the factors of ``settings.appearance`` of the marker's median amplitude and
    width (once it has 3 measurements; a candidate without a fitted width passes that test).
    ``whole`` (n_markers,) bool: those markers must look whole, an amplitude of at least
    ``partial_fraction`` of their median (not a partly hidden one)."""
    lo_a, hi_a, lo_s, hi_s = settings.appearance
    lo_a = np.full((len(markers), 1), lo_a)
    if whole is not None:
        lo_a[np.asarray(whole, bool)] = max(settings.appearance[0], settings.partial_fraction)
    ma = np.array([m.amp_median for m in markers], float)[:, None]
    ms = np.array([m.sigma_median for m in markers], float)[:, None]
    amp = np.asarray(amp, float)[None, :]
    sigma = np.asarray(sigma, float)[None, :]
    sg = np.where(np.isfinite(sigma), sigma, ms)
    with np.errstate(invalid="ignore"):
        ok_a = ~np.isfinite(ma) | ((amp >= lo_a * ma) & (amp <= hi_a * ma))
        ok_s = ~np.isfinite(ms) | ((sg >= lo_s * ms) & (sg <= hi_s * ms))
    return ok_a & ok_s


@dataclass
class TrackResult:
    """A view's tracks: the tidy table (:data:`TRACK_COLUMNS`) and the events."""

    table: pd.DataFrame
    events: list[dict]
    fov: dict | None = None
    settings: dict | None = None
    faint: list[dict] | None = None     # automatic mode: spots the first frames' average shows, no track holds


def _assign(markers: list[_Marker], pred: np.ndarray, gates: np.ndarray, cand_xy: np.ndarray,
            compatible: np.ndarray | None = None, miss_cost: float | None = None):
    """Optimal one-to-one matching of markers to candidates inside the gates (and, where
    given, ``compatible`` (n, m): candidates that look like the marker).

    The cost of a pair is ``d^2 / gate^2`` (1 at the gate's edge).  ``miss_cost``: each
    marker may also stay unmatched at this cost, so a marker is not pushed onto a poor
    candidate (one a neighbour fits far better, say, or one at the edge of a gate grown while
    it was hidden) only because every marker must take something; None: every marker takes
    a candidate whenever one is allowed (trackpy's linking).

    Returns ``match`` (marker index -> candidate index or -1) and the squared distances
    (inf where a pair is not allowed).
    """
    n, m = len(markers), len(cand_xy)
    match = np.full(n, -1)
    if n == 0 or m == 0:
        return match, np.full((n, m), np.inf)
    d2 = ((pred[:, None, :] - cand_xy[None, :, :]) ** 2).sum(axis=-1)
    cost = d2 / gates[:, None] ** 2
    allowed = d2 <= gates[:, None] ** 2
    if compatible is not None:
        allowed &= compatible
    big = 1e6
    c = np.where(allowed, cost, big)
    if miss_cost is not None:
        # one "unmatched" column per marker, its own only
        miss = np.full((n, n), big)
        np.fill_diagonal(miss, miss_cost)
        c = np.hstack([c, miss])
    r, k = linear_sum_assignment(c)
    keep = k < m
    r, k = r[keep], k[keep]
    ok = allowed[r, k]
    match[r[ok]] = k[ok]
    return match, np.where(allowed, d2, np.inf)


def _apart(xy: np.ndarray, points, radius) -> np.ndarray:
    """(n,) True for each of ``xy`` (n, 2) farther than ``radius`` (a number, or one per
    point) from every one of ``points`` (k, 2; none: all True)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    if len(pts) == 0 or len(xy) == 0:
        return np.ones(len(xy), bool)
    r = np.broadcast_to(np.asarray(radius, float), (len(pts),))
    return (((xy[:, None, :] - pts[None, :, :]) ** 2).sum(-1) > r[None, :] ** 2).all(axis=1)


def _ambiguous_pairs(match: np.ndarray, d2: np.ndarray, margin2: float) -> list[tuple[int, int]]:
    """Pairs of matched markers whose swapped matching costs less than ``margin2`` more."""
    idx = np.flatnonzero(match >= 0)
    if len(idx) < 2 or np.isfinite(d2).sum(axis=1).max() < 2:   # no gate holds two candidates
        return []
    D = d2[np.ix_(idx, match[idx])]            # D[a, b]: marker idx[a] to the candidate of idx[b]
    own = np.diag(D)
    swap = D + D.T
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(swap) & (swap - (own[:, None] + own[None, :]) < margin2)
    a, b = np.nonzero(np.triu(hit, 1))
    return [(int(idx[p]), int(idx[q])) for p, q in zip(a, b)]


def track_view(frames: Iterable, seeds: pd.DataFrame | dict | None, diameter_px: float,
               polarity: Polarity = "dark", *, view: str = "view", fps: float | None = None,
               roi: FieldOfView | np.ndarray | str | None = None,
               detection: DetectionSettings = DetectionSettings(),
               settings: TrackSettings = TrackSettings(),
               on_frame=None) -> TrackResult:
    """Track the markers of one view through a stream of frames.

    Parameters
    ----------
    frames : iterable
        Frames in order: 2-D arrays, or objects with ``image``, ``index`` and ``time_s``
        (:class:`bsipipe.io.images.Frame`); consumed once, one at a time.
    seeds : DataFrame ``marker, x_px, y_px`` | dict name -> (x, y) | None
        Positions in the first frame (rough clicks are fine: each is refined to the marker
        within ``seed_radius_px``).  None: markers are detected in every frame and linked
        (:func:`link_detections` semantics), named ``M1, M2, ...`` by first appearance.
    diameter_px, polarity, roi, detection
        As in :func:`~bsipipe.imaging.detect.detect_markers`.
    fps : float, optional
        Frame rate for ``time_s`` where a frame has no time stamp (frame i at i / fps).
    on_frame : callable ``(index, image) -> None``, optional
        Called with each frame (e.g. to keep one for a figure, or to advance a progress bar).

    Returns
    -------
    TrackResult
        ``table`` with :data:`TRACK_COLUMNS` (NaN positions where a marker was not found)
        and ``events``.
    """
    if seeds is None:
        return _track_auto(frames, diameter_px, polarity, view=view, fps=fps, roi=roi, detection=detection,
                           settings=settings, on_frame=on_frame)
    S = settings.resolved(diameter_px)
    names, xy0 = _seed_arrays(seeds)
    markers = [_Marker(n, p.copy(), -1) for n, p in zip(names, xy0)]
    # the table is kept as one small array per frame and column (a dict per row would hold
    # about a kilobyte per marker and frame: tens of MB over a long sequence)
    cols: dict[str, list] = {c: [] for c in ("frame", "time_s", "x_px", "y_px", "found", "snr", "amplitude",
                                             "area_px", "sigma_px", "pred", "gate_px", "status")}
    events: list[dict] = []
    fov_info = None
    fov = None
    for k, fr in enumerate(frames):
        img, f, t = _unpack(fr, k, fps)
        if on_frame is not None:
            on_frame(f, img)
        if fov is None:
            fov = _resolve_roi(img, roi)
            fov_info = fov.to_dict() if fov is not None else {"found": False}
        if k == 0:
            pred = np.array([m.pos for m in markers]).reshape(-1, 2)
            gates = _seed_gates(img, markers, pred, diameter_px, polarity, detection, fov, settings, S, view)
        else:
            pred, gates = _predictions(markers, f, S, settings)
        r = _search_frame(img, f, markers, pred, gates, diameter_px, polarity, detection, fov, settings, S,
                          view, events, second_look=k > 0)
        for name in ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px", "found", "gate_px"):
            cols[name].append(r[name])
        cols["frame"].append(f)
        cols["time_s"].append(t)
        cols["status"].extend(r["status"])
        cols["pred"].append(r["pred"])
    table, events = reject_excursions(_seeded_table(view, names, cols), events, S["gate_px"], view,
                                      settings.min_track_frames - 1)
    return TrackResult(table, events, fov_info, {**settings.__dict__, **S})


#: Where most seeds find no marker within ``seed_radius_px`` (clicks systematically off, e.g.
#: on a scaled display), the seeds that find none are searched this many times as far.
SEED_REACH_FACTOR = 2.5


def _seed_gates(img, markers: list[_Marker], pred: np.ndarray, diameter_px: float, polarity, detection, fov,
                settings: TrackSettings, S: dict, view: str) -> np.ndarray:
    """The first frame's search radius per seed: ``seed_radius_px``, or, where more than half
    the seeds find no marker within it (a trial search on copies of the markers), that times
    :data:`SEED_REACH_FACTOR` for the seeds that found none (the global assignment keeps a
    seed off a marker a nearer seed takes).  Seeds 6-8 px off 4 px beads had found 1 of 12:
    the frame was empty and the diameter, from that one, too small to find the rest."""
    import copy
    r0 = S["seed_radius_px"]
    gates = np.full(len(markers), r0)
    if len(markers) < 2:
        return gates
    trial = _search_frame(img, 0, copy.deepcopy(markers), pred, gates, diameter_px, polarity, detection, fov,
                          settings, S, view, [], second_look=False)
    missed = ~np.asarray(trial["found"], bool)
    if 2 * missed.sum() > len(markers):
        gates[missed] = SEED_REACH_FACTOR * r0
    return gates


def _predictions(markers: list[_Marker], f: int, S: dict, settings: TrackSettings):
    """Each marker's predicted position in frame ``f`` and its gate radius."""
    pred = np.array([m.predict(f, settings.motion, settings.merge_extrapolation_frames if m.merged_with
                               else settings.max_extrapolation_frames) for m in markers])
    gates = np.array([m.gate(f, S["gate_px"], S["gate_growth_px"], S["max_gate_px"]) for m in markers])
    return pred.reshape(-1, 2), gates


def _search_frame(img, f: int, live: list[_Marker], pred, gates, diameter_px: float, polarity: Polarity,
                  detection: DetectionSettings, fov, settings: TrackSettings, S: dict, view: str,
                  events: list[dict], *, second_look: bool = True, cand: dict | None = None,
                  taken: np.ndarray | None = None) -> dict:
    """One frame of the window search: candidates in each marker's gate around its
    prediction, the global assignment, the second look, and each marker's update and events
    (appended to ``events``).  ``cand``: the frame's candidates when they are already known (a
    whole-frame detection), instead of a search in the windows; ``taken`` (k, 2): positions
    other markers hold in this frame (a candidate within a diameter of one is not taken).
    Returns per-marker arrays ``x_px, y_px, snr, amplitude,
    area_px, sigma_px, found, gate_px``, ``pred`` (n, 2) and the ``status`` list."""
    whole = cand
    objects: dict = {}

    def first_pass(pred):
        c = whole if whole is not None else window_arrays(img, pred, gates, diameter_px, polarity, detection, fov)
        cxy = np.column_stack([c["x_px"], c["y_px"]])
        # a marker being found again after a gap must look whole: a partial candidate at the
        # edge of a gate grown while it was hidden is more likely clutter, or the edge of the
        # instrument that hid it, than the marker (it is taken a frame later, whole)
        compat = _looks_like(live, c["amplitude"], c["sigma_px"], settings,
                             whole=[m.lost_since is not None for m in live])
        if taken is not None:
            # candidates other markers already hold in this frame (within a diameter) are not free
            compat &= _apart(cxy, taken, max(1.0, diameter_px))[None, :]
        # a candidate within a diameter of the prediction of a marker measured in the last
        # few frames (its prediction still holds) is that marker, even one its own appearance
        # test turns down in this frame, noise having widened it: it is not free for the
        # grown gate of a marker lost for longer
        recent = np.array([abs(f - m.frame) <= settings.max_extrapolation_frames + 1 for m in live], bool)
        if recent.any() and not recent.all() and len(cxy):
            compat[~recent] &= _apart(cxy, pred[recent], max(1.0, diameter_px))[None, :]
        if polarity == "dark" and len(cxy):
            _not_in_objects(img, diameter_px, live, cxy, compat, objects)
        return c, cxy, *_assign(live, pred, gates, cxy, compat, miss_cost=1.0)

    cand, cxy, match, d2 = first_pass(pred)
    shift = np.zeros(2)
    if settings.frame_shift and len(live) >= 3:
        found = _frame_shift(img, f, live, pred, match, cxy, whole, diameter_px, polarity, detection, fov,
                             settings, S)
        if found is not None:
            # the whole picture moved (the C-arm or the head jolted): the predictions move with it
            again = first_pass(pred + found)
            n0, n1 = (match >= 0).sum(), (again[2] >= 0).sum()
            # taken when it finds more markers, or as many nearer their predictions
            if n1 > n0 or (n1 == n0 and n1 and _matched_d2(again[3], again[2]) < _matched_d2(d2, match)):
                shift = found
                pred = pred + found
                cand, cxy, match, d2 = again
                events.append({"view": view, "frame": f, "marker": None, "kind": "frame-shift",
                               "dx_px": float(found[0]), "dy_px": float(found[1]),
                               "detail": "the whole picture moved: every prediction moved with it"})
    weak = np.zeros(len(live), bool)
    if settings.second_look_k_sigma is not None and second_look:
        near = np.minimum(gates, S["second_look_radius_px"])
        cand, match, d2, weak = _second_look(f, img, live, pred, near, cand, match, d2, diameter_px, polarity,
                                             detection, fov, settings)
    amb = _ambiguous_pairs(match, d2, S["ambiguity_px"] ** 2)
    for i, j in amb:
        events.append({"view": view, "frame": f, "marker": live[i].name, "kind": "ambiguous",
                       "other": live[j].name, "detail": "the two markers could be matched the other way round"})
        events.append({"view": view, "frame": f, "marker": live[j].name, "kind": "ambiguous",
                       "other": live[i].name, "detail": "the two markers could be matched the other way round"})
    nm = len(live)
    merged = _merged(f, live, pred, match, cand, S["merge_px"], diameter_px, settings, view, events)
    if merged.any():
        match = np.where(merged, -1, match)
    hit = match >= 0
    val = {}
    for name in ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px"):
        arr = np.full(nm, np.nan)
        arr[hit] = cand[name][match[hit]]
        val[name] = arr
    status = ["merged" if mg else "lost" for mg in merged]
    xs, ys, amps, sigs = (val[c].tolist() for c in ("x_px", "y_px", "amplitude", "sigma_px"))
    for i, m in enumerate(live):
        j = match[i]
        if j < 0 and merged[i]:
            if m.lost_since is None:
                m.lost_since = f
        elif j < 0:
            if m.lost_since is None:
                m.lost_since = f
                in_gate = np.flatnonzero(np.isfinite(d2[i])) if d2.size else []
                why = ("no marker in the search window" if len(in_gate) == 0 else
                       "the only candidates were better matches for other markers")
                events.append({"view": view, "frame": f, "marker": m.name, "kind": "lost",
                               "last_x_px": float(m.pos[0]), "last_y_px": float(m.pos[1]),
                               "gate_px": float(gates[i]), "detail": why})
        else:
            amp = amps[i]
            med = m.amp_median
            partial = bool(np.isfinite(med) and amp < settings.partial_fraction * med)
            status[i] = "partial" if partial else "weak" if weak[i] else "found"
            if m.lost_since is not None:
                events.append({"view": view, "frame": f, "marker": m.name, "kind": "refound",
                               "gap_frames": int(f - m.lost_since),
                               "distance_px": float(math.sqrt(d2[i, j])),
                               "detail": f"found again after {f - m.lost_since} frame(s)"})
                m.lost_since = None
            if partial:
                events.append({"view": view, "frame": f, "marker": m.name, "kind": "partial",
                               "amplitude_ratio": amp / med,
                               "detail": "amplitude below its median: partly hidden, centre may be biased"})
            m.update(f, (xs[i], ys[i]), amp if not partial else np.nan, sigs[i] if not partial else np.nan,
                     offset=shift)
    val["found"] = hit.copy()
    val["shift"] = shift
    val["gate_px"] = np.asarray(gates, float)
    val["pred"] = np.asarray(pred, float).reshape(nm, 2)
    val["status"] = status
    return val


def _merged(f: int, live: list[_Marker], pred: np.ndarray, match: np.ndarray, cand: dict, merge_px: float,
            diameter_px: float, settings: TrackSettings, view: str, events: list[dict]) -> np.ndarray:
    """Which markers' images are merged with a neighbour's in frame ``f`` (n,) bool, and each
    marker's merge state updated (see :class:`TrackSettings` ``merge_px``).

    A merge starts where a marker measured a frame before is not matched, another marker's
    prediction is within ``merge_px`` of its own, and a candidate lies within ``merge_px`` of
    both predictions (the one image of both, taken by the other marker, or by neither when
    its size or depth are no single marker's).
    It lasts, for the markers in it, until each is matched to a candidate of its own at least
    a diameter from the others' (they have parted), or ``merge_extrapolation_frames`` frames
    have passed (then they are tracked as before)."""
    n = len(live)
    out = np.zeros(n, bool)
    if n < 2:
        return out
    P = np.asarray(pred, float).reshape(n, 2)
    close = ((P[:, None, :] - P[None, :, :]) ** 2).sum(axis=-1) < merge_px ** 2
    np.fill_diagonal(close, False)
    idx = {m.name: i for i, m in enumerate(live)}
    # merges that go on: until every marker in one holds a candidate of its own, apart
    cxy = np.column_stack([np.asarray(cand["x_px"], float), np.asarray(cand["y_px"], float)]).reshape(-1, 2)
    for i, m in enumerate(live):
        if not m.merged_with:
            continue
        group = [i] + [idx[o] for o in m.merged_with if o in idx]
        own = all(match[k] >= 0 for k in group) and len({int(match[k]) for k in group}) == len(group)
        apart = own and all(np.hypot(*(cxy[match[a]] - cxy[match[b]])) >= diameter_px
                            for a in group for b in group if a < b)
        if apart or abs(f - m.merged_since) > settings.merge_extrapolation_frames:
            m.merged_with, m.merged_since = (), None
        else:
            out[i] = True
    # merges that start: a marker just seen, not matched, beside a close neighbour with one
    # image near both
    near = ((cxy[None, :, :] - P[:, None, :]) ** 2).sum(axis=-1) < merge_px ** 2 if len(cxy) else \
        np.zeros((n, 0), bool)

    def recent(m):
        return m.lost_since is None or m.lost_since >= f - 1 or m.frame >= f - 2

    for i, m in enumerate(live):
        if match[i] >= 0 or out[i] or not recent(m):
            continue
        took = [j for j in np.flatnonzero(close[i]) if recent(live[j]) and (near[i] & near[j]).any()]
        if not took:
            continue
        group = [i] + took
        for k in group:
            mk = live[k]
            others = tuple(live[o].name for o in group if o != k)
            if not mk.merged_with:
                mk.merged_since = f
                events.append({"view": view, "frame": f, "marker": mk.name, "kind": "merged",
                               "other": ", ".join(others),
                               "detail": "passing close: one image for both; left empty, each moves on at its "
                                         "velocity from before until they part"})
            mk.merged_with = tuple(dict.fromkeys(mk.merged_with + others))
            out[k] = True
    return out


def _not_in_objects(img, diameter_px: float, live: list[_Marker], cxy: np.ndarray, compat: np.ndarray,
                    objects: dict) -> None:
    """A lost marker is not found again inside a large dark object (an instrument's shadow,
    :func:`~bsipipe.imaging.detect.dark_objects`, the object itself, not grown): a bead hidden
    behind the indentor is not seen through it, and the top-hat's responses along the rod's
    blurred edges or in its noise look like beads.  ``compat`` (markers, candidates) is
    updated in place; the objects are found once per frame (``objects``), and only when a
    lost marker has a candidate."""
    lost = np.array([m.lost_since is not None for m in live], bool)
    if not lost.any():
        return
    test = compat[lost].any(axis=0)
    if not test.any():
        return
    h, w = np.shape(img)
    xi = np.clip(np.rint(cxy[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.rint(cxy[:, 1]).astype(int), 0, h - 1)
    # the objects in a crop around the candidates, wider than the reach of the closing that
    # finds them (a disk 16 diameters across): about a hundredth of a frame
    f = max(1, int(diameter_px))
    pad = int(math.ceil(10 * diameter_px)) + 2 * f
    x0 = max(0, (int(xi[test].min()) - pad) // f * f)
    y0 = max(0, (int(yi[test].min()) - pad) // f * f)
    x1 = min(w, int(xi[test].max()) + pad + 1)
    y1 = min(h, int(yi[test].max()) + pad + 1)
    # an object is also far deeper than the lost markers (5 times their amplitude), whatever
    # its ratio to its surroundings (log-converted frames)
    amps = [m.amp_median for m, lo in zip(live, lost) if lo and math.isfinite(m.amp_median)]
    depth = 5.0 * max(amps) if amps else None
    key = (x0, y0, x1, y1, depth)
    if key not in objects:
        objects[key] = _DarkObjects.find(np.asarray(img)[y0:y1, x0:x1], diameter_px, depth=depth)
    dk = objects[key]
    if dk is None:
        return
    inside = np.zeros(len(cxy), bool)
    # the object itself, not grown: a bead coming out beside it is whole
    inside[test] = dk.core_at(xi[test] - x0, yi[test] - y0)
    if inside.any():
        compat[np.ix_(lost, inside)] = False


def _matched_d2(d2: np.ndarray, match: np.ndarray) -> float:
    """Mean squared distance of the matched markers from their predictions."""
    hit = np.flatnonzero(match >= 0)
    return float(d2[hit, match[hit]].mean()) if len(hit) else np.inf


def _frame_shift(img, f: int, live: list[_Marker], pred, match, cxy, whole, diameter_px: float, polarity: Polarity,
                 detection: DetectionSettings, fov, settings: TrackSettings, S: dict):
    """A shift of the whole picture in frame ``f``, or None.

    Looked for only when the first pass suggests one: of the markers measured in the frame
    before (at least 3), under 70 % matched, or the matched ones off their predictions by a
    common offset (the median residual) larger than ``max(1, gate/4)``.  Then each of those
    markers' candidates within ``max_gate_px`` of its prediction (that look like it) votes with
    its offset from the prediction; the offset most markers agree on (within ``max(1, d/4)``)
    wins if at least 3 markers and half of them agree, and it is the median of their offsets."""
    # markers measured in the frame before: a seed is a click, not a measurement (seeds clicked
    # 3 px off, all alike, had been taken for the picture jolting in frame 0)
    recent = np.array([f - m.frame == 1 and m.n_meas > 0 for m in live])
    if recent.sum() < 3:
        return None
    hit = recent & (match >= 0)
    tol = max(1.0, 0.25 * diameter_px)
    if hit.sum() >= 0.7 * recent.sum():
        res = cxy[match[hit]] - pred[hit]
        common = np.median(res, axis=0)
        if hit.sum() < 3 or np.hypot(*common) <= max(1.0, 0.25 * S["gate_px"]):
            return None
    idx = np.flatnonzero(recent)
    R = S["max_gate_px"]
    c = whole if whole is not None else window_arrays(img, pred[idx], np.full(len(idx), R), diameter_px, polarity,
                                                      detection, fov)
    xy = np.column_stack([c["x_px"], c["y_px"]])
    if len(xy) == 0:
        return None
    ok = _looks_like([live[i] for i in idx], c["amplitude"], c["sigma_px"], settings, whole=np.ones(len(idx), bool))
    off = xy[None, :, :] - pred[idx][:, None, :]                        # (markers, candidates, 2)
    ok &= (off ** 2).sum(-1) <= R * R
    mi, cj = np.nonzero(ok)
    if len(mi) < 3:
        return None
    o = off[mi, cj]                                                   # every vote
    close = ((o[:, None, :] - o[None, :, :]) ** 2).sum(-1) <= tol * tol
    # support of each vote: the markers with a vote near it
    support = np.array([len(set(mi[close[k]])) for k in range(len(o))])
    best = support.max()
    if best < max(3, 0.5 * len(idx)):
        return None
    k = int(np.flatnonzero(support == best)[np.argmin(np.hypot(*o[support == best].T))])
    near = close[k]
    # one offset per supporting marker (its vote nearest the winner), then their median
    per = {}
    for v, i in zip(np.flatnonzero(near), mi[near]):
        if i not in per or np.hypot(*(o[v] - o[k])) < np.hypot(*(o[per[i]] - o[k])):
            per[i] = v
    shift = np.median(o[list(per.values())], axis=0)
    return shift if np.hypot(*shift) > tol else None


def _second_look(frame: int, img, live: list[_Marker], pred, gates, cand: dict, match, d2, diameter_px: float,
                 polarity: Polarity, detection: DetectionSettings, fov, settings: TrackSettings):
    """Look once more, in ``frame``, for the markers nothing matched (``match`` -1) that have a
    known appearance (3 measurements) and were measured in the last
    ``max_extrapolation_frames`` frames (at least the last one: their prediction still follows
    their motion; a marker hidden for longer is the first pass's to find again).

    Candidates in ``gates`` (the caller passes ``second_look_radius_px``, not the search
    gate: a low threshold is only safe over a small area) with the window
    threshold lowered to ``settings.second_look_k_sigma``, away (half a diameter) from every
    candidate already matched, that pass the detector's other tests (SNR, shape) and look like
    the whole marker, are assigned as in the first pass.  Returns the candidates (the first
    pass's, then the new ones), ``match`` and ``d2`` over them, and which markers the second
    look found."""
    n_x = max(settings.max_extrapolation_frames, 1)
    recent = np.array([np.isfinite(m.amp_median) and abs(frame - m.frame) <= n_x for m in live], bool)
    miss = np.flatnonzero((match < 0) & recent)
    weak = np.zeros(len(live), bool)
    if len(miss) == 0 or settings.second_look_k_sigma >= detection.window_k_sigma:
        return cand, match, d2, weak
    low = detection.updated(window_k_sigma=float(settings.second_look_k_sigma),
                            min_snr=min(detection.min_snr, float(settings.second_look_min_snr)))
    more = window_arrays(img, pred[miss], gates[miss], diameter_px, polarity, low, fov)
    xy = np.column_stack([more["x_px"], more["y_px"]])
    if len(xy) == 0:
        return cand, match, d2, weak
    taken = np.column_stack([cand["x_px"], cand["y_px"]])[match[match >= 0]]
    if len(taken):
        free = _apart(xy, taken, 0.5 * diameter_px)
        if not free.all():
            more = {c: v[free] for c, v in more.items()}
            xy = xy[free]
            if len(xy) == 0:
                return cand, match, d2, weak
    ms = [live[i] for i in miss]
    # a weak find must look like the whole marker: not a partly hidden one (amplitude at least
    # ``partial_fraction`` of its median), which is the first pass's to take or not
    compat = _looks_like(ms, more["amplitude"], more["sigma_px"], settings, whole=np.ones(len(ms), bool))
    m2, dd2 = _assign(ms, pred[miss], gates[miss], xy, compat, miss_cost=1.0)
    hit = m2 >= 0
    if not hit.any():
        return cand, match, d2, weak
    n0 = len(cand["x_px"])
    cand = {c: np.concatenate([cand[c], more[c]]) for c in cand}
    match = match.copy()
    match[miss[hit]] = n0 + m2[hit]
    d2 = np.hstack([d2.reshape(len(live), n0), np.full((len(live), len(xy)), np.inf)])
    d2[miss[:, None], n0 + np.arange(len(xy))[None, :]] = dd2
    weak[miss[hit]] = True
    return cand, match, d2, weak


def _seeded_table(view: str, names: list[str], cols: dict) -> pd.DataFrame:
    """The tidy table (:data:`TRACK_COLUMNS`, one row per frame and marker, markers in seed
    order within each frame) from :func:`track_view`'s per-frame column arrays."""
    nf, nm = len(cols["frame"]), len(names)
    if nf == 0 or nm == 0:
        table = pd.DataFrame([], columns=TRACK_COLUMNS)
        table["found"] = table["found"].astype(bool)
        return table
    pred = np.concatenate(cols["pred"])
    data = {"view": [view] * (nf * nm), "frame": np.repeat(np.asarray(cols["frame"], np.int64), nm),
            "time_s": np.repeat(np.asarray(cols["time_s"], float), nm), "marker": names * nf,
            "pred_x_px": pred[:, 0], "pred_y_px": pred[:, 1], "gate_px": np.concatenate(cols["gate_px"]),
            "found": np.concatenate(cols["found"]), "status": cols["status"]}
    for c in ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px"):
        data[c] = np.concatenate(cols[c])
    return pd.DataFrame(data, columns=TRACK_COLUMNS)


def _seed_arrays(seeds) -> tuple[list[str], np.ndarray]:
    if isinstance(seeds, dict):
        names = [str(k) for k in seeds]
        xy = np.array([seeds[k] for k in seeds], float).reshape(-1, 2)
    else:
        names = [str(x) for x in seeds["marker"]]
        xy = seeds[["x_px", "y_px"]].to_numpy(float)
    if len(set(names)) != len(names):
        raise ValueError("seed marker names must be unique within a view")
    return names, xy


def _unpack(fr, k: int, fps: float | None):
    if hasattr(fr, "image"):
        img, f, t = fr.image, int(fr.index), fr.time_s
    else:
        img, f, t = fr, k, None
    if t is None:
        t = f / fps if fps else np.nan
    return np.asarray(img), f, float(t)


def _resolve_roi(img, roi):
    """The :class:`FieldOfView` a view is searched in: ``roi`` itself (given), the field found
    in ``img`` (None or "auto"), a bool mask (h, w) of the pixels to search, or None ("none")."""
    if isinstance(roi, FieldOfView):
        return roi
    if roi is None or (isinstance(roi, str) and roi == "auto"):
        return find_field_of_view(img)
    if isinstance(roi, np.ndarray):
        m = np.asarray(roi, bool)
        if m.shape != np.shape(img)[:2]:
            raise ValueError(f"the region of interest is {m.shape[1]}x{m.shape[0]} px, the frames "
                             f"{np.shape(img)[1]}x{np.shape(img)[0]}")
        return FieldOfView(tuple(m.shape), region=m, given=True)
    return None


def _track_swept(frames, diameter_px, polarity, *, view, fps, roi, detection, settings, on_frame) -> TrackResult:
    """Automatic mode: whole-frame sweeps for new markers, search windows in between.

    The first frame, then every ``settings.sweep_every_frames``-th frame and the last one,
    are searched whole (:func:`~bsipipe.imaging.detect.detect_arrays`); a detection that no
    track holds (none found within a diameter, no lost track's gate around it) starts a new
    track, which is first followed backwards through the last ``back_frames`` frames (kept in
    memory) as tracks are followed forwards, then forwards with the other tracks.  Every
    frame in between is searched only in each live track's window, as with seeds
    (:func:`_search_frame`: prediction, global assignment, second look); where the windows
    would hold more pixels than half the frame, the frame is searched whole (and swept)
    instead.  A track lost for more than ``memory`` frames ends (a new one at its first miss
    until it has ``min_track_frames`` positions); a new track that starts where an ended one
    would have been found continues it; tracks with fewer than ``min_track_frames`` positions
    are dropped; the others are named ``M1, M2, ...`` by first appearance."""
    S = settings.resolved(diameter_px)
    every = max(1, int(settings.sweep_every_frames))
    markers: list[_Marker] = []
    n_back: list[int] = []                # each track's positions found backwards from its sweep
    first: dict[int, tuple] = {}          # a new track's earliest position: (frame, xy, amplitude, sigma)
    dormant: list[int] = []               # confirmed tracks ended by ``memory``: a new track may continue one
    alias: dict[int, int] = {}            # new track -> the ended track it continues
    events: list[dict] = []
    # per frame: (frame, marker indices, column arrays); backwards finds as single rows
    recs: list[tuple[int, np.ndarray, dict]] = []
    back: list[tuple[int, int, dict]] = []
    times: dict[int, float] = {}
    buf: list[list] = []                  # the last back_frames frames: [frame, image, found xy (list)]
    fov = fov_info = where = dark = None
    stacked = None                        # spots in the average of the first STACK_FRAMES frames
    excl = max(1.0, float(diameter_px))

    def sweep(f: int, img, found_xy: np.ndarray, lost: list[int], lost_pred, lost_gate, d=None) -> None:
        if d is None:
            # the tracks' own markers are not measured again: a found one's centre, a lost one's gate
            d = detect_arrays(img, diameter_px, polarity, where, detection, dark=dark,
                              skip=(np.vstack([found_xy, lost_pred]),
                                    np.concatenate([np.full(len(found_xy), excl), lost_gate])))
        xy = np.column_stack([d["x_px"], d["y_px"]])
        if len(xy) == 0:
            return
        free = _apart(xy, found_xy, excl) & _apart(xy, lost_pred, lost_gate)
        idx = []
        for j in np.flatnonzero(free):
            m = _Marker(str(len(markers)), xy[j].copy(), f)
            m.update(f, xy[j], float(d["amplitude"][j]), float(d["sigma_px"][j]))
            markers.append(m)
            n_back.append(0)
            idx.append(len(markers) - 1)
            first[idx[-1]] = (f, xy[j].copy(), float(d["amplitude"][j]), float(d["sigma_px"][j]))
        if not idx:
            return
        idx = np.array(idx)
        vals = {c: np.asarray(d[c], float)[free] for c in ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px")}
        vals.update(found=np.ones(len(idx), bool), gate_px=np.full(len(idx), np.nan),
                    pred=np.full((len(idx), 2), np.nan), status=["found"] * len(idx))
        recs.append((f, idx, vals))
        _follow_back(idx)
        _continue_ended(idx)

    def _continue_ended(idx) -> None:
        """A new track that starts where an ended (confirmed) one would have been found had
        it still been searched for -- within the gate grown since its last position, looking
        like it -- continues it (the same name; a ``refound`` event): the gap closing of the
        seeded mode, for tracks that ``memory`` ended."""
        if not dormant:
            return
        pairs = []
        ms = [markers[j] for j in dormant]
        last = np.array([m.frame for m in ms])
        for i in idx:
            fb, pb, amp, sig = first[int(i)]
            # the ended tracks' predictions and gates in frame fb, all at once (a dense field
            # ends many tracks), then the appearance test for those near enough
            pred, gates = _predictions(ms, fb, S, settings)
            d2 = ((pred - pb) ** 2).sum(axis=1)
            for k in np.flatnonzero((last < fb) & (d2 <= gates ** 2)):
                if _looks_like([ms[k]], [amp], [sig], settings, whole=[True])[0, 0]:
                    pairs.append((d2[k] / gates[k] ** 2, int(i), dormant[k], fb, math.sqrt(d2[k])))
        taken_i, taken_j = set(), set()
        for _, i, j, fb, dist in sorted(pairs):
            if i in taken_i or j in taken_j:
                continue
            taken_i.add(i)
            taken_j.add(j)
            alias[i] = j
            dormant.remove(j)
            mj = markers[j]
            gap = int(fb - (mj.lost_since if mj.lost_since is not None else mj.frame + 1))
            events.append({"view": view, "frame": int(fb), "marker": mj.name, "kind": "refound", "gap_frames": gap,
                           "distance_px": dist, "detail": f"found again after {gap} frame(s) (its track had ended)"})

    def _follow_back(idx) -> None:
        """Follow the new markers ``idx`` backwards through the buffered frames (the sweep's
        own frame, the last one in the buffer, excluded) as they are followed forwards
        (:func:`_search_frame`: prediction, gates, assignment, second look), away from the
        markers already found in each frame; each until it has been missed for more than
        ``memory`` frames (at its first miss while it has fewer than ``min_track_frames``
        positions)."""
        bs = []
        for i in idx:
            m = markers[i]
            b = _Marker(m.name, m.pos.copy(), m.frame)
            b.update(m.frame, m.pos, m.amps[0] if m.amps else np.nan, m.sigmas[0] if m.sigmas else np.nan)
            bs.append((int(i), b))
        scratch: list[dict] = []                 # backwards losses and re-finds are not events
        for f, img, taken in reversed(buf[:-1]):
            # followed back until missed for more than ``memory`` frames; not yet confirmed
            # (fewer than min_track_frames positions), until its first miss, as forwards
            bs = [(i, b) for i, b in bs if abs(b.frame - f) - 1 <= (settings.memory if b.n_meas >=
                                                                    settings.min_track_frames else 0)]
            if not bs:
                return
            ms = [b for _, b in bs]
            pred, gates = _predictions(ms, f, S, settings)
            r = _search_frame(img, f, ms, pred, gates, diameter_px, polarity, detection, fov, settings, S, view,
                              scratch, taken=np.asarray(taken, float).reshape(-1, 2))
            for k in np.flatnonzero(r["found"]):
                i = bs[k][0]
                vals = {c: float(r[c][k]) for c in ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px",
                                                    "gate_px")}
                vals.update(pred_x_px=float(r["pred"][k, 0]), pred_y_px=float(r["pred"][k, 1]),
                            status=r["status"][k])
                back.append((f, i, vals))
                n_back[i] += 1
                xy = np.array([vals["x_px"], vals["y_px"]])
                first[i] = (f, xy, vals["amplitude"], vals["sigma_px"])
                taken.append(xy)

    k = -1
    for k, fr in enumerate(frames):
        img, f, t = _unpack(fr, k, fps)
        if on_frame is not None:
            on_frame(f, img)
        times[f] = t
        if k == 0:
            # the intensifier's field does not move: found once, in the first frame; dark
            # objects (instruments) do move, so a sweep looks for them in its own frame
            fov = _resolve_roi(img, roi)
            fov_info = fov.to_dict() if fov is not None else {"found": False}
            auto = roi is None or (isinstance(roi, str) and roi == "auto")
            # a field found or given (a circle or a drawn region); dark objects are left out of
            # both (a given region says where to look, not that no instrument is there)
            where = fov if (fov is not None and (fov.found or fov.region is not None)) else "none"
            dark = True if ((auto or (fov is not None and fov.given)) and polarity == "dark") else None
        live = [i for i, m in enumerate(markers) if not m.ended]
        found_xy = np.zeros((0, 2))
        lost, lost_pred, lost_gate = [], np.zeros((0, 2)), np.zeros(0)
        whole = None
        if live:
            ms = [markers[i] for i in live]
            pred, gates = _predictions(ms, f, S, settings)
            if window_strip_px(len(ms), float(gates.max()), diameter_px, detection) > 0.5 * img.size:
                # so many tracks that their windows hold more pixels than half the frame:
                # the whole frame is searched instead (it is cheaper), and swept as well
                whole = detect_arrays(img, diameter_px, polarity, where, detection, dark=dark)
            r = _search_frame(img, f, ms, pred, gates, diameter_px, polarity, detection, fov, settings, S,
                              view, events, cand=whole)
            recs.append((f, np.array(live), {c: r[c] for c in ("x_px", "y_px", "snr", "amplitude", "area_px",
                                                                 "sigma_px", "found", "gate_px", "pred", "status")}))
            hit = r["found"]
            found_xy = np.column_stack([r["x_px"], r["y_px"]])[hit]
            lost = [i for i, h in zip(live, hit) if not h]
            lost_pred, lost_gate = r["pred"][~hit], r["gate_px"][~hit]
            for i in lost:
                # a track not yet confirmed (fewer than min_track_frames positions, those
                # found backwards included) ends at its first miss: noise peaks come and go,
                # and a wide gate kept open for them would only gather more noise
                m = markers[i]
                confirmed = m.n_meas + n_back[i] >= settings.min_track_frames
                # a track merged with a neighbour's image waits for them to part (at most
                # merge_extrapolation_frames), however long that takes
                if (f - m.frame > settings.memory and not m.merged_with) or not confirmed:
                    m.ended = True
                    if confirmed:
                        dormant.append(i)
        buf.append([f, img, [p for p in found_xy]])
        if k == STACK_FRAMES - 1 and len(buf) >= STACK_FRAMES:
            # the tracks' own markers are not measured again (their centres now, a lost one's gate)
            stacked = _stacked_spots([b[1] for b in buf[-STACK_FRAMES:]], diameter_px, polarity, where, detection,
                                     dark, skip=(np.vstack([found_xy, lost_pred]),
                                                 np.concatenate([np.full(len(found_xy), excl), lost_gate])))
        swept = k % every == 0 or whole is not None
        if swept:
            sweep(f, img, found_xy, lost, lost_pred, lost_gate, whole)
        if len(buf) > max(0, settings.back_frames) + 1:
            del buf[0]
        pending = (found_xy, lost, lost_pred, lost_gate)
    if k >= 0 and not swept:
        # the last frame is swept too: a marker that came into view since the last sweep
        # is followed back from there
        sweep(buf[-1][0], buf[-1][1], *pending)
    buf = []
    res = _swept_result(view, markers, recs, back, times, events, settings, S, fov_info, alias)
    if stacked is not None:
        res.faint = _untracked_spots(stacked, res.table, diameter_px)
    return res


#: Automatic mode averages its first frames to look for markers too faint for a single frame,
#: and takes a spot there with at least this SNR for one (the average's noise is the frames'
#: over sqrt(STACK_FRAMES): SNR 8 there is about 2.8 in a frame, where seeded tracking still
#: follows a marker).  On the bench twin with Poisson noise, the untracked 0.5 mm markers had
#: SNR 10.6-13.2 in the average of 8 frames and the other spots at most 7.0; on the clean twin
#: nothing reached 5.
STACK_FRAMES = 8
FAINT_MIN_SNR = 8.0


def _stacked_spots(images: list, diameter_px: float, polarity, where, detection, dark, skip=None) -> dict:
    """The whole-frame detections (:func:`~bsipipe.imaging.detect.detect_arrays`) in the mean
    of ``images`` (the first :data:`STACK_FRAMES` frames): the pixel noise falls by the square
    root of their number, so a marker of single-frame SNR 2-4 (a 0.5 mm bead in a noisy C-arm
    frame, below the sweep's threshold) stands out there if it moves less than its size.  The
    sum of 8- or 12-bit frames is taken in 16-bit integers (exact, and the detector's integer
    path: 16 ms a view where the float mean took 38), else the float mean.  ``skip``: as
    :func:`~bsipipe.imaging.detect.detect_arrays`' (the tracks' markers, not measured again)."""
    ims = [np.asarray(im) for im in images]
    n = len(ims)
    if all(im.dtype == np.uint8 for im in ims) or (
            all(im.dtype == np.uint16 for im in ims) and max(int(im.max()) for im in ims) * n <= 65535):
        acc = np.zeros(ims[0].shape, np.uint16)
        for im in ims:
            np.add(acc, im, out=acc, casting="unsafe")
    else:
        acc = np.mean(np.stack([im.astype(np.float32) for im in ims]), axis=0)
    return detect_arrays(acc, diameter_px, polarity, where, detection, dark=dark, skip=skip)


def _untracked_spots(d: dict, table: pd.DataFrame, diameter_px: float) -> list[dict]:
    """The spots of :func:`_stacked_spots` of SNR :data:`FAINT_MIN_SNR` or more farther than a
    diameter from every position of every track in the averaged frames (and the next as many):
    markers the automatic search did not follow (too faint in single frames), or static
    marker-like structure; strongest first, with their SNR in the average and what it means for
    one frame."""
    if not len(d["x_px"]):
        return []
    t = table[table["found"] & (table["frame"] < table["frame"].min() + 2 * STACK_FRAMES)] if len(table) else table
    xy = np.column_stack([d["x_px"], d["y_px"]])
    free = _apart(xy, t[["x_px", "y_px"]].to_numpy(float), max(1.0, float(diameter_px)))
    out = [{"x_px": float(x), "y_px": float(y), "snr_average": float(snr),
            "snr_one_frame": float(snr / math.sqrt(STACK_FRAMES))}
           for x, y, snr, ok in zip(d["x_px"], d["y_px"], d["snr"], free) if ok and snr >= FAINT_MIN_SNR]
    return sorted(out, key=lambda r: -r["snr_average"])


def _swept_result(view, markers, recs, back, times, events, settings, S, fov_info, alias=None) -> TrackResult:
    """The tidy table of :func:`_track_swept`: kept tracks named by first appearance, a row
    per frame and track (``lost`` where it was not found); ``alias``: a track that continues
    another (ended) one takes its place."""
    num = ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px", "gate_px", "pred_x_px", "pred_y_px")
    fr = [np.full(len(idx), f, np.int64) for f, idx, _ in recs] + [np.array([f for f, _, _ in back], np.int64)]
    ii = [np.asarray(idx, np.int64) for _, idx, _ in recs] + [np.array([i for _, i, _ in back], np.int64)]
    col = {c: [v[c] for _, _, v in recs] for c in num[:7]}
    col["pred_x_px"] = [v["pred"][:, 0] for _, _, v in recs]
    col["pred_y_px"] = [v["pred"][:, 1] for _, _, v in recs]
    for c in num:
        col[c].append(np.array([v[c] for _, _, v in back], float))
    fr, ii = np.concatenate(fr), np.concatenate(ii)
    found = np.concatenate([v["found"] for _, _, v in recs] + [np.ones(len(back), bool)])
    status = np.array([x for _, _, v in recs for x in v["status"]] + [v.get("status", "found") for _, _, v in back],
                      dtype=object)
    root = np.arange(len(markers))
    for i, j in (alias or {}).items():
        while j in alias:
            j = alias[j]
        root[i] = j
    if len(ii):
        ii = root[ii]
        # a continued track's last "lost" rows may share frames with its continuation's first
        # rows (followed back): the found row stands
        order = np.lexsort((~found, ii, fr))
        key = fr[order] * len(markers) + ii[order]
        keep = order[np.unique(key, return_index=True)[1]]
        fr, ii, found, status = fr[keep], ii[keep], found[keep], status[keep]
        col = {c: [np.concatenate(v).astype(float)[keep]] for c, v in col.items()}
    # kept: tracks found in at least min_track_frames frames; named by their first frame
    n_found = np.bincount(ii[found], minlength=len(markers))
    first = np.full(len(markers), np.iinfo(np.int64).max)
    np.minimum.at(first, ii[found], fr[found])
    need = min(settings.min_track_frames, max(len(times), 1))
    kept = [int(i) for i in np.argsort(first, kind="stable") if n_found[i] >= need and n_found[i] > 0]
    names = {i: f"M{n + 1}" for n, i in enumerate(kept)}
    by_name = {markers[i].name: names[int(root[i])] for i in range(len(markers)) if int(root[i]) in names}
    frames_all = np.array(sorted(times), np.int64)
    F, M = len(frames_all), len(kept)
    pos = np.full(len(markers), -1)
    pos[kept] = np.arange(M)
    sel = pos[ii] >= 0 if len(ii) else np.zeros(0, bool)
    at = np.searchsorted(frames_all, fr[sel]) * M + pos[ii[sel]]
    data = {"view": [view] * (F * M), "frame": np.repeat(frames_all, M),
            "time_s": np.repeat(np.array([times[f] for f in frames_all], float), M),
            "marker": [names[i] for i in kept] * F}
    for c in num:
        arr = np.full(F * M, np.nan)
        arr[at] = np.concatenate(col[c]).astype(float)[sel]
        data[c] = arr
    data["found"] = np.zeros(F * M, bool)
    data["found"][at] = found[sel]
    st = np.full(F * M, "lost", dtype=object)
    st[at] = status[sel]
    data["status"] = st.tolist()
    table = pd.DataFrame(data, columns=TRACK_COLUMNS)
    out_events = []
    for e in events:
        if e["marker"] is None:                   # an event of the frame, not of a track
            out_events.append(e)
            continue
        if e["marker"] not in by_name or ("other" in e and e["other"] not in by_name):
            continue
        e = dict(e, marker=by_name[e["marker"]])
        if "other" in e:
            e["other"] = by_name[e["other"]]
        out_events.append(e)
    table, out_events = reject_excursions(table, out_events, S["gate_px"], view, settings.min_track_frames - 1)
    out_events = _gap_events(table, out_events, view)
    return TrackResult(table, out_events, fov_info, {**settings.__dict__, **S})


def true_runs(ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and one-past-last index of each run of consecutive True in ``ok`` (1-D)."""
    e = np.flatnonzero(np.diff(np.r_[0, np.asarray(ok).astype(np.int8), 0]))
    return e[::2], e[1::2]


def reject_excursions(table: pd.DataFrame, events: list[dict], gate_px: float, view: str,
                      max_run: int = 2) -> tuple[pd.DataFrame, list[dict]]:
    """Positions a track took from something else for a frame or two while its marker was not
    found, left out (status ``excursion``, ``found`` False, position empty; an ``excursion``
    event holds what was measured).

    A run of at most ``max_run`` found frames between two gaps of a track is an excursion when
    each of its positions lies further from the line between the track's positions on either
    side (the last one before the run and the first one after, at the run's frame by linear
    interpolation) than the gate one frame after a measurement (``gate_px``, the farthest the
    tracker lets a marker move in a frame) plus half the distance between those two positions
    (a track that moved between them may have curved).  The tracker's gate grows while a marker
    is hidden, and a noise peak or a quantisation plateau it then meets is taken for it: on the
    bench twin with its frames reduced to 20 grey levels, cam2's faint M5 was found 10.4 px off
    in one frame between gaps, status ``found``, its positions 7 frames before and 10 frames after
    0.9 px apart.  The stale ``refound`` and ``lost`` events of such a run are dropped."""
    if table.empty or not table["found"].any():
        return table, events
    rows, new_events, stale = [], [], set()
    for m, g in table.groupby("marker", sort=False):
        ok = g["found"].to_numpy(bool)
        starts, ends = true_runs(ok)
        if len(starts) < 3:
            continue
        fr = g["frame"].to_numpy(np.float64)
        x, y = g["x_px"].to_numpy(np.float64), g["y_px"].to_numpy(np.float64)
        for k in range(1, len(starts) - 1):
            s, e = int(starts[k]), int(ends[k])
            if e - s > max_run:
                continue
            ia, ib = int(ends[k - 1]) - 1, int(starts[k + 1])
            t = (fr[s:e] - fr[ia]) / (fr[ib] - fr[ia])
            qx, qy = x[ia] + t * (x[ib] - x[ia]), y[ia] + t * (y[ib] - y[ia])
            dev = np.hypot(x[s:e] - qx, y[s:e] - qy)
            apart = float(np.hypot(x[ib] - x[ia], y[ib] - y[ia]))
            limit = gate_px + 0.5 * apart
            if not (dev > limit).all():
                continue
            rows.extend(g.index[s:e])
            stale.add((m, int(fr[s]), "refound"))
            stale.add((m, int(fr[e]), "lost"))
            for j in range(s, e):
                new_events.append({
                    "view": view, "frame": int(fr[j]), "marker": m, "kind": "excursion",
                    "x_px": float(x[j]), "y_px": float(y[j]), "distance_px": float(dev[j - s]),
                    "detail": f"found {dev[j - s]:.1f} px off the line between its positions in frames "
                              f"{int(fr[ia])} and {int(fr[ib])} ({apart:.1f} px apart), more than the "
                              f"one-frame gate {gate_px:.1f} px + half that: taken for something else, left out"})
    if not rows:
        return table, events
    table = table.copy()
    table.loc[rows, "found"] = False
    table.loc[rows, "status"] = "excursion"
    for c in ("x_px", "y_px", "snr", "amplitude", "area_px", "sigma_px"):
        table.loc[rows, c] = np.nan
    kept = [ev for ev in events if (ev.get("marker"), int(ev.get("frame", -1)), ev.get("kind")) not in stale]
    return table, sorted(kept + new_events, key=lambda ev: ev["frame"])


def _gap_events(table: pd.DataFrame, events: list[dict], view: str) -> list[dict]:
    """``events`` with a ``lost`` / ``refound`` pair for every run of ``lost`` rows of an
    automatic track that has none (a track followed back past a gap reports nothing on its
    way, and the forward sweep never saw the frames before the track began), an ``appeared``
    event where a track is first found after the view's first frame, and a ``lost`` event
    where it is last found before the view's last frame with none after it; in frame order.

    A band of bone crossing two markers of a twin's second view had hidden one for its first
    12 frames and the other for 18 with gaps, with 0 events in that view."""
    if table.empty:
        return events
    have = {(e["marker"], e["frame"], e["kind"]) for e in events if e.get("marker") is not None}
    lost_at: dict[str, list[int]] = {}
    for e in events:
        if e.get("marker") is not None and e["kind"] == "lost":
            lost_at.setdefault(e["marker"], []).append(int(e["frame"]))
    added = []
    for m, g in table.groupby("marker", sort=False):
        fr = g["frame"].to_numpy(np.int64)
        st = g["status"].to_numpy(object)
        seen = np.flatnonzero(g["found"].to_numpy(bool) | (st == "merged"))
        if not len(seen):
            continue
        a, b = int(seen[0]), int(seen[-1])
        if a > 0:
            added.append({"view": view, "frame": int(fr[a]), "marker": m, "kind": "appeared",
                          "frames_before": int(a),
                          "detail": f"first found in frame {int(fr[a])}, not in the {a} frame(s) before it (hidden, "
                                    "outside the field or too faint)"})
        # the runs of lost rows between the first and the last found row (each ends before one)
        for k, e in zip(*(i + a for i in true_runs(np.isin(st[a:b + 1], ("lost", "excursion"))))):
            f0, f1 = int(fr[k]), int(fr[e])
            if not any(f0 <= x < f1 for x in lost_at.get(m, ())):
                added.append({"view": view, "frame": f0, "marker": m, "kind": "lost",
                              "detail": "not found; followed across the gap"})
                if (m, f1, "refound") not in have:
                    added.append({"view": view, "frame": f1, "marker": m, "kind": "refound", "gap_frames": int(e - k),
                                  "detail": f"found again after {e - k} frame(s)"})
        if b < len(fr) - 1 and not any(x > int(fr[b]) for x in lost_at.get(m, ())):
            added.append({"view": view, "frame": int(fr[b + 1]), "marker": m, "kind": "lost",
                          "detail": "not found again to the end of the sequence"})
    if not added:
        return events
    return sorted(events + added, key=lambda e: e["frame"])


def _track_auto(frames, diameter_px, polarity, *, view, fps, roi, detection, settings, on_frame) -> TrackResult:
    if detection.parity == "none":
        return _track_swept(frames, diameter_px, polarity, view=view, fps=fps, roi=roi, detection=detection,
                            settings=settings, on_frame=on_frame)
    # trackpy parity: every frame detected whole as trackpy's locate does, then linked
    dets: list[dict] = []
    times = {}
    for k, fr in enumerate(frames):
        img, f, t = _unpack(fr, k, fps)
        if on_frame is not None:
            on_frame(f, img)
        d = {c: v.to_numpy(float) for c, v in detect_markers(img, diameter_px, polarity, roi, detection).items()}
        d["frame"] = np.full(len(d["x_px"]), f)
        times[f] = t
        dets.append(d)
    if dets:
        det = pd.DataFrame({c: np.concatenate([d[c] for d in dets]) for c in DETECT_COLUMNS + ["frame"]})
    else:
        det = pd.DataFrame(columns=DETECT_COLUMNS + ["frame"])
    S = settings.resolved(diameter_px)
    linked, events = link_detections(det, S["gate_px"], memory=settings.memory, motion=settings.motion,
                                     gate_growth_px=S["gate_growth_px"], max_gate_px=S["max_gate_px"],
                                     ambiguity_px=S["ambiguity_px"], view=view)
    # drop stubs, name tracks by first appearance
    counts = linked.groupby("particle")["frame"].count()
    keep = counts.index[counts >= min(settings.min_track_frames, max(len(times), 1))]
    linked = linked[linked["particle"].isin(keep)]
    order = linked.groupby("particle")["frame"].min().sort_values(kind="stable")
    names = {p: f"M{i + 1}" for i, p in enumerate(order.index)}
    linked = linked.assign(marker=linked["particle"].map(names))
    events = [dict(e, marker=names[e["particle"]]) for e in events if e["particle"] in names]
    for e in events:
        e.pop("particle", None)
    frames_all = sorted(times)
    rows = []
    by = {(r.marker, r.frame): r for r in linked.itertuples(index=False)}
    for f in frames_all:
        for p, n in sorted(names.items(), key=lambda t: int(t[1][1:])):
            r = by.get((n, f))
            if r is None:
                rows.append({"view": view, "frame": f, "time_s": times[f], "marker": n, "x_px": np.nan,
                             "y_px": np.nan, "found": False, "snr": np.nan, "amplitude": np.nan, "area_px": np.nan,
                             "sigma_px": np.nan, "pred_x_px": np.nan, "pred_y_px": np.nan, "gate_px": np.nan,
                             "status": "lost"})
            else:
                rows.append({"view": view, "frame": f, "time_s": times[f], "marker": n, "x_px": r.x_px,
                             "y_px": r.y_px, "found": True, "snr": r.snr, "amplitude": r.amplitude,
                             "area_px": r.area_px, "sigma_px": r.sigma_px, "pred_x_px": r.pred_x_px,
                             "pred_y_px": r.pred_y_px, "gate_px": r.gate_px, "status": "found"})
    table = pd.DataFrame(rows, columns=TRACK_COLUMNS)
    table["found"] = table["found"].astype(bool)
    return TrackResult(table, events, None, {**settings.__dict__, **S})


def link_detections(detections: pd.DataFrame, search_range_px: float, *, memory: int = 0,
                    motion: Motion = "static", gate_growth_px: float = 0.0, max_gate_px: float | None = None,
                    ambiguity_px: float = 0.0, view: str = "view",
                    x: str = "x_px", y: str = "y_px") -> tuple[pd.DataFrame, list[dict]]:
    """Link per-frame detections into trajectories (trackpy's ``link``, with prediction).

    ``detections`` has columns ``frame`` and the positions ``x``/``y``.  Within each frame
    the live tracks and the detections are matched by :func:`linear_sum_assignment` on the
    squared distance to each track's prediction, inside ``search_range_px`` (+
    ``gate_growth_px`` per missed frame); a track may miss up to ``memory`` frames.  With
    ``motion="static"`` and no gate growth this is trackpy's criterion (the matching that
    minimises the total squared displacement), solved exactly rather than by trackpy's
    subnetwork search.

    Returns the detections with ``particle`` (int), ``pred_x_px``, ``pred_y_px``, ``gate_px``
    and the events (``lost``, ``refound``, ``ambiguous``; each with ``particle``).
    """
    det = detections.reset_index(drop=True)
    gmax = max_gate_px if max_gate_px is not None else search_range_px + gate_growth_px * memory
    particle = np.full(len(det), -1)
    pred_out = np.full((len(det), 2), np.nan)
    gate_out = np.full(len(det), np.nan)
    tracks: list[_Marker] = []
    ids: list[int] = []
    events: list[dict] = []
    frames = np.sort(det["frame"].unique())
    groups = det.groupby("frame").indices
    xy_all = det[[x, y]].to_numpy(float)
    nxt = 0
    for f in frames:
        idx = np.asarray(groups[f])
        xy = xy_all[idx]
        live = [i for i, t in enumerate(tracks) if not t.ended]
        for i in live:
            if f - tracks[i].frame - 1 > memory:
                tracks[i].ended = True
        live = [i for i in live if not tracks[i].ended]
        ms = [tracks[i] for i in live]
        pred = np.array([m.predict(f, motion) for m in ms]).reshape(-1, 2)
        gates = np.array([m.gate(f, search_range_px, gate_growth_px, gmax) for m in ms])
        match, d2 = _assign(ms, pred, gates, xy)
        if ambiguity_px > 0:
            for a, b in _ambiguous_pairs(match, d2, ambiguity_px ** 2):
                for u, w in ((a, b), (b, a)):
                    events.append({"view": view, "frame": int(f), "particle": ids[live[u]], "kind": "ambiguous",
                                   "other_particle": ids[live[w]]})
        taken = np.zeros(len(xy), bool)
        for k, i in enumerate(live):
            t = tracks[i]
            j = match[k]
            if j < 0:
                if t.lost_since is None:
                    t.lost_since = int(f)
                    events.append({"view": view, "frame": int(f), "particle": ids[i], "kind": "lost",
                                   "last_x_px": float(t.pos[0]), "last_y_px": float(t.pos[1])})
                continue
            taken[j] = True
            particle[idx[j]] = ids[i]
            pred_out[idx[j]] = pred[k]
            gate_out[idx[j]] = gates[k]
            if t.lost_since is not None:
                events.append({"view": view, "frame": int(f), "particle": ids[i], "kind": "refound",
                               "gap_frames": int(f - t.lost_since), "distance_px": float(math.sqrt(d2[k, j]))})
                t.lost_since = None
            t.update(int(f), xy[j], np.nan)
        for j in np.flatnonzero(~taken):
            tracks.append(_Marker(str(nxt), xy[j].copy(), int(f), n_meas=1))
            ids.append(nxt)
            particle[idx[j]] = nxt
            nxt += 1
    out = det.copy()
    out["particle"] = particle
    out["pred_x_px"] = pred_out[:, 0]
    out["pred_y_px"] = pred_out[:, 1]
    out["gate_px"] = gate_out
    # a lost event of a track that never came back and ended is still a loss; keep it
    return out, events


def track_views(sources: dict, seeds: pd.DataFrame | None, diameter_px: float, polarity: Polarity = "dark",
                **kw) -> tuple[pd.DataFrame, list[dict], dict]:
    """Track several views (name -> iterable of frames), one after the other (each view's
    frames are streamed once).  ``seeds`` has a ``view`` column; returns the concatenated
    table, all events and per-view information (field of view, settings)."""
    tables, events, info = [], [], {}
    for v, frames in sources.items():
        s = None
        if seeds is not None:
            s = seeds[seeds["view"] == v]
            if len(s) == 0:
                raise ValueError(f"no seeds for view {v!r}")
        res = track_view(frames, s, diameter_px, polarity, view=v, **kw)
        tables.append(res.table)
        events.extend(res.events)
        info[v] = {"fov": res.fov, "settings": res.settings}
    return pd.concat(tables, ignore_index=True), events, info
