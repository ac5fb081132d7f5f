r"""The registration stage's loop: its model spec, its fit, and its five effects.

Declared model: the references are fixed to the skull, and the X-ray frame maps to the CT
frame rigidly (``--scale``: with a uniform scale).  The fit uses the references' X-ray
positions in the registration frame F; its residual is the 3N coordinates of
:math:`\mathbf y_i - s R \mathbf x_i - \mathbf t` (mm).  Effects (CONTRACTS.md names):

``scale``
    A magnification the C-arm calibration did not capture (source-to-object distance off,
    a detector pixel size taken from the wrong header) scales every X-ray length.  Signature:
    the residual grows with the distance from the references' centroid, pointing along it:
    it correlates with the centred CT coordinates (the ``centred_position_mm`` covariate of
    :func:`~bsipipe.loop.residual_structure`).  One parameter, :math:`\ln s`.
``moving-reference``
    A reference marker that is on the brain surface rather than the skull (or was knocked)
    moves with the tissue.  Signature: in frame F, a residual at that reference far larger
    than the others' (its held-out prediction by a fit of the others fails); over the trial,
    its position relative to the other references changes.  Parameters: a free displacement
    of that reference (3), i.e. it no longer constrains the transform.  Outside evidence:
    (a) its smooth motion over the trial while the other references stay still
    (:func:`~bsipipe.geometry.registration.reference_motion`, against the others' rigid
    motion where they turn; not counted when another reference's motion explains the tracks
    as well, :func:`motion_rivals`), and (b) the held-out test
    at frame F (:func:`~bsipipe.geometry.registration.leave_one_out`: the reference predicted
    by a fit that never saw it), expressed as :math:`\chi^2_3` of equal tail probability
    minus :math:`3 \ln 3N`.  Evidence of no motion is not evidence that the CT position is
    right, so these two are never negative; (c) the implanted-marker check below.
``label-swap``
    References whose labels are mixed up between the CT file and the X-ray tracks (a click
    order mixed up in Slicer or in the tracking seeds): two exchanged, or more in a cycle
    (clicking the corners of a craniotomy from another corner turns every label by one).
    Signature: the same as a moved reference at the registration frame (two references, or
    more, fail their held-out prediction) but no motion over the trial; giving the CT labels
    back makes every reference consistent.  No continuous parameter: the loop tries every
    relabelling of the references in use (:func:`relabellings`: every permutation of up to
    :data:`MAX_PERMUTED` references, else those changing at most four labels, three beyond
    twelve references) and keeps the one with
    the strongest outside evidence, then the best fit (reported as ``label_swaps``, one
    cycle each: a pair, or ``[a, b, c]`` for X-ray a = CT b, b = c, c = a; ties to the
    fewest labels changed).  Outside evidence: the held-out evidence the moving-reference
    effect would claim for the worst of the references free to be relabelled, plus
    :math:`3 \ln 3N` (the three parameters a moved reference costs and a relabelling does
    not) minus :math:`2 \ln K` (the choice among the :math:`K` relabellings tried that
    change as many labels or fewer: an exchange competes with the :math:`N(N-1)/2`
    exchanges only), counted only when after it no reference fails its held-out test
    (Bonferroni 1 %) and the best moved-reference fit is not significantly better (an F
    test with the moved reference's three parameters, 1 %); and (c).  With four
    references at the corners of a square, an exchange across a diagonal and a moved
    reference fit the references about equally (a turn by 180 degrees about the other
    diagonal); only (c) tells them apart.

``ct-axis-scale``
    The CT's lengths along one of its axes are off: a slice spacing (reconstruction interval)
    that is not the header's slice thickness, or a tilted gantry's table increment taken for
    the spacing (off by :math:`1/\cos` of the tilt: 5 % at 18 degrees).  Every CT position is
    stretched along that axis, so no rigid (or uniformly scaled) transform fits: the
    references' residuals grow with their spread along the axis, and markers far from the
    references along it (implanted markers below a craniotomy, on an axial CT) are off by
    :math:`(k - 1)` times that distance while the references fit well.  One parameter,
    :math:`\ln k`, along the CT axis with the strongest outside evidence (below; then the best
    fit; the slice axis, z, on a tie); the
    transform is :class:`~bsipipe.geometry.registration.AxisScaledSimilarity` about the
    references' CT centroid.  Tried with four references or more, on the axes along which they
    determine a stretch (:func:`~bsipipe.geometry.registration.axis_scale_lever` above zero).
    Outside evidence: the references' own F test of the added parameter,
    :math:`F = (\mathrm{RSS}_0 - \mathrm{RSS}_1)/(\mathrm{RSS}_1/(3N - p - 1))` on (1, 3N - p - 1)
    degrees of freedom, as :math:`\chi^2_1` of equal tail probability minus :math:`\ln 3N` (the
    parameter) minus :math:`2 \ln K` (the choice among the :math:`K` axes tried): as for the
    held-out test, twelve numbers are too few for the Gaussian BIC, whose noise variance is
    known to 5 degrees of freedom; plus (c), which can be negative.  With a 5 dof F test the
    references alone need a stretch residual several times their noise; the implanted
    markers (c) carry most of the evidence where the CT localises the references coarsely.
``ct-gantry-shear``
    The CT was acquired with the gantry tilted (10-25 degrees for a head, to spare the eyes) and
    read without its tilt (DICOM's GantryDetectorTilt ignored): the slices are stacked without
    their in-plane shift, so every CT position is sheared, its y (anterior-posterior; less
    often x) off by :math:`k = \tan` of the tilt times its z (the slice position) from the
    references' centroid.  No rigid (or uniformly scaled) transform fits: on the square of
    four references of ``tests/test_register_checks.py`` (noise 0.005 mm) 5 degrees had left
    FRE 0.31 mm and the implanted markers 0.43 mm RMS off, no warning; 15 degrees 0.95 and
    1.32 mm with only ``large-fre``.  One parameter, :math:`k` (a tilt either way), of the
    in-plane axis (:data:`SHEAR_ORDER`: y, then x; y on a tie) with the strongest outside
    evidence, by the slice axis z (:data:`SHEAR_BY`), fitted jointly with the transform
    (:class:`~bsipipe.geometry.registration.ShearedSimilarity`, about the references' CT
    centroid).  Tried as ``ct-axis-scale`` is: with four references or more, on the axes whose
    shear they determine (:func:`~bsipipe.geometry.registration.shear_lever` above zero), with
    the same outside evidence (the references' F test of the parameter, minus :math:`\ln 3N`
    and :math:`2 \ln K` for the :math:`K` axes tried, plus (c)).  A fitted tilt beyond
    :data:`MAX_GANTRY_TILT_DEG` is vetoed.  One of ``ct-axis-scale`` and ``ct-gantry-shear``
    per registration (:func:`_axis_candidates`): both compete in one round and the one kept
    shuts the other out (a pure shear's stretch candidate had outside evidence -4.6 to 0.8, a
    pure stretch's shear candidate -5.1 to 2.9, the right one 69 to 187, at 1-20 degrees and
    2-10 %).

(c) Markers localised in CT that are not references (implanted markers: the same check
``registration.json`` reports as ``ct_check_mm``) were not fitted, so they judge any
transform from the outside: with :math:`m` of them at their X-ray positions at rest,
:math:`3m \ln(\mathrm{RSS}_{before}/\mathrm{RSS}_{after})` (Gaussian, variance unknown, no
parameter fitted) is added to the outside evidence of ``moving-reference`` and
``label-swap``; it can be negative.  This is what tells a label swap of two references at
opposite corners of a square (which a 180-degree turn about the other diagonal fits as well
as a moved reference) from a moved reference.

Why the held-out test is outside evidence: with N = 4 references the residual has 12
numbers, too few for the generic structure tests to see one displaced marker, and the
Gaussian BIC on 12 numbers with 3 added parameters is not strong evidence either (the
noise variance is known only to 3 degrees of freedom); the F test accounts for that
uncertainty exactly.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from itertools import combinations, permutations

import numpy as np

from ..distributions import chi2_isf, f_sf
from ..loop import Effect, LoopReport, run_loop
from .registration import (CT_AXES, AxisScaledSimilarity, ShearedSimilarity, Similarity, axis_scale_lever,
                           fit_axis_scaled, fit_sheared, fit_similarity, leave_one_out, n_params, reference_motion,
                           rounding_rss, shear_lever)

__all__ = ["RegistrationSpec", "RegistrationData", "RegistrationFit", "fit_registration",
           "registration_covariates", "registration_effects", "close_registration_loop",
           "reference_checks", "ct_positions", "motion_rivals", "unresolved_motion", "axis_scale_identification",
           "shear_identification"]

#: Fewest references that determine the transform.
MIN_REFERENCES = 3


@dataclass(frozen=True)
class RegistrationSpec:
    """The registration model: ``scale`` on/off, the references taken as moved, and the
    cycles of references whose CT labels are mixed up (``swapped``, X-ray names: in a cycle
    ``(c0, c1, ..., ck)`` the CT file's ``c1`` is the X-ray ``c0``, its ``c2`` the X-ray
    ``c1``, ..., its ``c0`` the X-ray ``ck``; a pair is an exchange); ``ct_axis``: the CT axis
    (0, 1, 2: x, y, z of the CT file) along which the CT's lengths are scaled, or None;
    ``ct_shear``: the in-plane CT axis (1 or 0: y or x) sheared by the slice axis
    (:data:`SHEAR_BY`, z: a gantry tilt read without it), or None."""

    scale: bool = False
    moved: tuple[str, ...] = ()
    swapped: tuple[tuple[str, ...], ...] = ()
    ct_axis: int | None = None
    ct_shear: int | None = None

    def describe(self) -> str:
        s = "similarity (rigid + uniform scale)" if self.scale else "rigid"
        if self.ct_axis is not None:
            s += f", then a scale along the CT's {CT_AXES[self.ct_axis]} axis"
        if self.ct_shear is not None:
            s += f", then a shear of the CT's {CT_AXES[self.ct_shear]} axis by its {CT_AXES[SHEAR_BY]} (gantry tilt)"
        if self.swapped:
            s += "; CT labels " + ", ".join(describe_cycle(c) for c in self.swapped) + " given back"
        if self.moved:
            s += f"; moved reference{'s' if len(self.moved) > 1 else ''} {', '.join(self.moved)} not used"
        return s


@dataclass
class RegistrationData:
    """What the fit needs: references at frame F in both frames, and their tracks.

    ``names`` (N,), ``x_mm`` (N, 3) X-ray positions in frame F, ``y_mm`` (N, 3) CT positions
    (as the CT file labels them), ``tracks_mm`` (n_frames, N, 3) X-ray positions in every frame
    (NaN where not found), ``time_s`` (n_frames,); ``check_x_mm``, ``check_y_mm`` (m, 3):
    markers localised in CT that are not references (X-ray position at rest: ``bsipipe
    register`` takes the first frame each is found in; CT position), the outside check of a
    transform.
    """

    names: list[str]
    x_mm: np.ndarray
    y_mm: np.ndarray
    tracks_mm: np.ndarray | None = None
    time_s: np.ndarray | None = None
    check_x_mm: np.ndarray | None = None
    check_y_mm: np.ndarray | None = None
    _motion: dict = field(default_factory=dict, repr=False)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def _motion_test(self, name: str, model: str) -> dict | None:
        key = (name, model)
        if key not in self._motion:
            if self.tracks_mm is None or len(self.names) < MIN_REFERENCES + 1:
                self._motion[key] = None
            else:
                k = self.index(name)
                others = [j for j in range(len(self.names)) if j != k]
                self._motion[key] = reference_motion(self.tracks_mm[:, k], self.tracks_mm[:, others],
                                                     time=self.time_s, model=model)
        return self._motion[key]

    def motion(self, name: str) -> dict | None:
        """:func:`reference_motion` of reference ``name`` against the others (cached).

        Against the others' rigid motion where they turn (``model="auto"``), except where
        another reference's motion, judged against its others' translation only, explains
        their turn (it moves out of their plane, and a rigid fit of a set holding it tilts):
        then against the others' translation, as though the head did not turn."""
        m = self._motion_test(name, "auto")
        if m is None or m["model"] != "rigid":
            return m
        by = [n for n in self.names if n != name and _flagged(self._motion_test(n, "auto"))
              and self._motion_test(n, "auto")["model"] == "translation"]
        if not by:
            return m
        return {**self._motion_test(name, "translation"), "others_turn_explained_by": by}


@dataclass
class RegistrationFit:
    """One fitted registration (the object the loop framework handles)."""

    spec: RegistrationSpec
    transform: Similarity
    used: np.ndarray            # (N,) bool: references that constrain the transform
    residual_vectors: np.ndarray  # (N, 3): y - T(x) for every reference, moved ones included
    residuals: np.ndarray       # (3N,): the loop's residual; zero for moved references
    params: dict
    n_params: int
    success: bool = True


def describe_cycle(c) -> str:
    """``a <-> b`` for a pair; ``a = CT b, b = CT c, c = CT a`` for a longer cycle."""
    if len(c) == 2:
        return f"{c[0]} <-> {c[1]}"
    return ", ".join(f"{a} = CT {b}" for a, b in zip(c, c[1:] + c[:1]))


def ct_labels(spec: RegistrationSpec) -> dict[str, str]:
    """X-ray name -> the CT file's label of that marker, for the references ``spec`` relabels."""
    return {a: b for c in spec.swapped for a, b in zip(c, c[1:] + c[:1])}


def ct_positions(data: RegistrationData, spec: RegistrationSpec) -> np.ndarray:
    """The CT positions (N, 3) of ``data.names`` once the labels are given back (``spec.swapped``)."""
    y = data.y_mm.copy()
    for a, b in ct_labels(spec).items():
        y[data.index(a)] = data.y_mm[data.index(b)]
    return y


def fit_registration(data: RegistrationData, spec: RegistrationSpec) -> RegistrationFit:
    """Fit ``spec`` to ``data`` (references in ``spec.moved`` do not constrain the transform;
    the CT labels in ``spec.swapped`` are exchanged first)."""
    used = np.array([n not in spec.moved for n in data.names])
    if used.sum() < MIN_REFERENCES:
        raise ValueError(f"{int(used.sum())} references left, the transform needs {MIN_REFERENCES}")
    y = ct_positions(data, spec)
    if spec.ct_axis is not None:
        T = fit_axis_scaled(data.x_mm[used], y[used], spec.ct_axis, scale=spec.scale)
    elif spec.ct_shear is not None:
        T = fit_sheared(data.x_mm[used], y[used], spec.ct_shear, by=SHEAR_BY, scale=spec.scale)
    else:
        T = fit_similarity(data.x_mm[used], y[used], scale=spec.scale)
    rv = y - T.apply(data.x_mm)
    res = rv.copy()
    res[~used] = 0.0   # absorbed by the moved reference's free displacement
    params = {"rotation_vector_rad": _rotvec(T.R), "t_mm": T.t_mm.tolist(), "scale": float(T.scale)}
    if spec.ct_axis is not None:
        params.update(ct_axis=CT_AXES[spec.ct_axis], ct_axis_scale=float(T.factor))
    if spec.ct_shear is not None:
        params.update(ct_shear_axis=CT_AXES[spec.ct_shear], ct_shear_by=CT_AXES[SHEAR_BY],
                      ct_gantry_shear=float(T.factor), ct_gantry_tilt_deg=T.tilt_deg)
    if spec.swapped:
        params["label_swaps"] = [list(p) for p in spec.swapped]
    for n in spec.moved:
        params[f"displacement_{n}_mm"] = rv[data.index(n)].tolist()
    return RegistrationFit(spec, T, used, rv, res.ravel(),
                           params, n_params(spec.scale, _mapped(spec)) + 3 * len(spec.moved))


def _mapped(spec: RegistrationSpec) -> bool:
    """``spec`` has a CT-geometry effect (``ct-axis-scale`` or ``ct-gantry-shear``)."""
    return spec.ct_axis is not None or spec.ct_shear is not None


def _distortion(spec: RegistrationSpec, y: np.ndarray):
    """A transform of ``spec``'s CT-geometry effect (its kind and axes; :func:`leave_one_out`'s
    ``like``), about the centroid of the CT positions ``y``; None without one."""
    c = np.asarray(y, float).mean(axis=0)
    if spec.ct_axis is not None:
        return AxisScaledSimilarity(np.eye(3), np.zeros(3), 1.0, spec.ct_axis, 1.0, c)
    if spec.ct_shear is not None:
        return ShearedSimilarity(np.eye(3), np.zeros(3), 1.0, spec.ct_shear, 0.0, c, SHEAR_BY)
    return None


def _rotvec(R) -> list[float]:
    from scipy.spatial.transform import Rotation
    return Rotation.from_matrix(R).as_rotvec().tolist()


def registration_covariates(data: RegistrationData) -> dict:
    """Covariates of the 3N residual: the centred CT coordinate of each component (scale's signature)."""
    return {"centred_position_mm": (data.y_mm - data.y_mm.mean(axis=0)).ravel()}


def _heldout(data: RegistrationData, spec: RegistrationSpec, name: str) -> dict | None:
    """Leave-one-out test of reference ``name`` among the references ``spec`` uses."""
    used = [n for n in data.names if n not in spec.moved]
    if name not in used or len(used) < MIN_REFERENCES + 1:
        return None
    idx = [data.index(n) for n in used]
    y = ct_positions(data, spec)[idx]
    loo = leave_one_out(data.x_mm[idx], y, scale=spec.scale, like=_distortion(spec, y))[used.index(name)]
    if not np.isfinite(loo["p"]):
        return None
    n = len(used)
    chi2_equiv = chi2_isf(max(loo["p"], 1e-300), 3)
    return {**loo, "chi2_equivalent": chi2_equiv, "delta_bic": chi2_equiv - 3 * np.log(3 * n),
            "in_sample_delta_bic": loo["delta_bic"]}


#: Delta BIC above which a reference counts as moving over the trial (Kass-Raftery "very strong").
MOTION_DELTA_BIC = 10.0


def _check_evidence(data: RegistrationData, before, after) -> dict | None:
    """(c) in the module docstring: the markers localised in CT that are not references, before
    and after an effect (fit results); None when there are none."""
    if data.check_x_mm is None or not len(data.check_x_mm):
        return None
    rss = [float(np.sum((data.check_y_mm - f.transform.apply(data.check_x_mm)) ** 2)) for f in (before, after)]
    m = len(data.check_x_mm)
    tiny = rounding_rss(3 * m, data.check_x_mm, data.check_y_mm)     # below it: rounding, no evidence
    return {"n_markers": int(m), "rms_before_mm": float(np.sqrt(rss[0] / m)),
            "rms_after_mm": float(np.sqrt(rss[1] / m)),
            "delta_bic": float(3 * m * np.log(max(rss[0], tiny) / max(rss[1], tiny)))}


def _with_check(ev: dict, check: dict | None) -> dict:
    if check is not None:
        ev["check"] = check
        ev["delta_bic"] = float(ev["delta_bic"] + check["delta_bic"])
        ev["note"] += "; plus the implanted-marker check (markers localised in CT, not fitted), which can be negative"
    return ev


def _outside_evidence(data: RegistrationData, spec: RegistrationSpec, name: str) -> dict:
    motion = data.motion(name)
    held = _heldout(data, spec, name)
    parts = {"motion": motion, "heldout": held}
    scores = {"heldout": None if held is None else float(held["delta_bic"]),
              "motion": None if motion is None else float(motion["delta_bic"])}
    note = ("largest of the motion test over the trial and the held-out test at the registration frame; "
            "never negative (no motion does not show the CT position is right)")
    if scores["motion"] is not None and scores["motion"] > MOTION_DELTA_BIC:
        also = motion_rivals(data, spec, name)
        if also:
            # another reference explains the motion as well: several moved, or the head turned
            # and which one moved out of the others' plane cannot be told; this says nothing
            # about this one reference
            scores["motion"] = None
            note += (f"; motion not counted: {', '.join(also)} move as well relative to the others "
                     f"({'the head turned: ' if motion['model'] == 'rigid' else ''}which moved cannot be told)")
    d = max([0.0] + [v for v in scores.values() if v is not None])
    return {"delta_bic": d, "reference": name, **parts, "note": note}


def _flagged(motion: dict | None) -> bool:
    return motion is not None and motion.get("delta_bic", 0.0) > MOTION_DELTA_BIC


def motion_rivals(data: RegistrationData, spec: RegistrationSpec, name: str) -> list[str]:
    """The references in use other than ``name`` whose motion test (:meth:`RegistrationData.motion`)
    explains the trial's tracks as well as ``name``'s.

    A reference judged against the others' translation only (``model`` ``"translation"``: the
    others do not turn) is the simpler explanation: a flag judged against the others' rigid
    motion does not rival it (one reference moving out of the others' plane tilts a rigid fit
    of a set that holds it, and every other reference then looks moved).  Two flags judged
    alike rival each other, except that a rigid-motion flag whose others scatter
    significantly more (F test, p < 1 %) than ``name``'s does not: its others are not rigid,
    they hold the reference that moved.  With four nearly coplanar references and the head
    turning, all four flag alike: which one moved cannot be told from the tracks."""
    me = data.motion(name)
    if not _flagged(me):
        return []
    out = []
    for n in data.names:
        if n == name or n in spec.moved:
            continue
        other = data.motion(n)
        if not _flagged(other):
            continue
        if not _dominates(me, other):
            out.append(n)
    return out


def _dominates(a: dict, b: dict) -> bool:
    """Motion test ``a`` explains flag ``b`` away: ``a`` judged against the others' translation
    and ``b`` against their rigid motion, or both against rigid motion and ``b``'s others
    scattering significantly more (F test, p < 1 %)."""
    if a["model"] == "translation":
        return b["model"] == "rigid"
    if b["model"] != "rigid" or not (a["others_dof"] and b["others_dof"]):
        return False
    return f_sf((b["others_sigma_mm"] / a["others_sigma_mm"]) ** 2, b["others_dof"], a["others_dof"]) < HELDOUT_P


def motion_explainers(data: RegistrationData, name: str) -> list[str]:
    """The references whose flagged motion explains ``name``'s flag away (:func:`motion_rivals`)."""
    me = data.motion(name)
    if not _flagged(me):
        return []
    return [n for n in data.names if n != name and _flagged(data.motion(n)) and _dominates(data.motion(n), me)]


def unresolved_motion(data: RegistrationData, spec: RegistrationSpec) -> list[str]:
    """References in use whose motion over the trial is flagged together with a rival's
    (:func:`motion_rivals`) while the loop left out neither: one of them (or more) moved
    relative to the skull, and the tracks cannot tell which."""
    used = [n for n in data.names if n not in spec.moved]
    out = []
    for n in used:
        rivals = motion_rivals(data, replace(spec, moved=()), n)
        if rivals and not any(r in spec.moved for r in rivals):
            out.append(n)
    return out


def _candidate(data: RegistrationData, spec: RegistrationSpec) -> str | None:
    """The reference the moving-reference effect would free next: strongest outside evidence.

    None where it would leave fewer references than :data:`MIN_REFERENCES`, or, with a CT-geometry
    effect in ``spec``, fewer than the four that effect needs (the ct-axis-scale and
    ct-gantry-shear effects' rule, whichever comes first): three references and a shear are 7
    parameters on 9 numbers, and the implanted markers' RSS ratio at their noise (0.014 against
    0.009 mm RMS) had kept a moved reference after a shear of x by z on 2 of 3 seeds
    (tre-unbounded)."""
    used = [n for n in data.names if n not in spec.moved]
    if len(used) <= MIN_REFERENCES + int(_mapped(spec)):
        return None
    scores = {n: _outside_evidence(data, spec, n)["delta_bic"] for n in used}
    # ties (no evidence anywhere): the largest residual in the current fit
    rv = fit_registration(data, spec).residual_vectors
    res = {n: float(np.linalg.norm(rv[data.index(n)])) for n in used}
    return max(used, key=lambda n: (scores[n], res[n]))


#: Every permutation of up to this many free references is a relabelling the loop tries
#: (7! - 1 = 5,039 fits); with more, those that change at most :func:`_most_changed` labels.
MAX_PERMUTED = 7


def _most_changed(n: int) -> int:
    """Labels a relabelling of ``n`` > :data:`MAX_PERMUTED` references changes at most: 4 up
    to 12 references (2,175 relabellings of 10), else 3."""
    return 4 if n <= 12 else 3

#: Relabellings whose references fit within this factor of the best one's RSS get the full
#: evidence (held-out tests, F test, implanted markers): the symmetric alternatives of a
#: square of references fit alike, and the implanted markers choose among them.
SHORTLIST_RSS_FACTOR = 10.0
SHORTLIST_MAX = 24


def _cycles(names: list[str], perm: tuple[int, ...]) -> tuple[tuple[str, ...], ...]:
    """The cycles (length >= 2) of ``perm`` (X-ray ``names[i]`` is CT ``names[perm[i]]``),
    each from its first name in ``names``' order."""
    seen, out = set(), []
    for i in range(len(perm)):
        if i in seen or perm[i] == i:
            continue
        c, j = [], i
        while j not in seen:
            seen.add(j)
            c.append(names[j])
            j = perm[j]
        out.append(tuple(c))
    return tuple(out)


def relabellings(free: list[str]) -> list[tuple[tuple[str, ...], ...]]:
    """Every relabelling of the references ``free`` the label-swap effect tries, as cycles:
    every permutation but the identity of up to :data:`MAX_PERMUTED` references, else those
    changing at most :func:`_most_changed` labels (exchanges, cycles of three, two exchanges,
    cycles of four).

    >>> relabellings(["a", "b", "c"])
    [(('b', 'c'),), (('a', 'b'),), (('a', 'b', 'c'),), (('a', 'c', 'b'),), (('a', 'c'),)]
    """
    return list(_relabellings(tuple(free)))


@functools.lru_cache(maxsize=8)
def _relabellings(free: tuple[str, ...]) -> tuple[tuple[tuple[str, ...], ...], ...]:
    """:func:`relabellings`, kept: the effect asks for the same references' again and again."""
    n = len(free)
    if n <= MAX_PERMUTED:
        return tuple(_cycles(list(free), p) for p in permutations(range(n)) if any(i != j for i, j in enumerate(p)))
    out = []
    for k in range(2, _most_changed(n) + 1):
        for sub in combinations(free, k):
            out += [_cycles(list(sub), p) for p in permutations(range(k)) if all(i != j for i, j in enumerate(p))]
    return tuple(out)


@functools.lru_cache(maxsize=64)
def _n_relabellings(free: tuple[str, ...], size: int) -> int:
    """How many of :func:`relabellings` of ``free`` change ``size`` labels or fewer (at least 1)."""
    return max(sum(1 for r in _relabellings(free) if sum(len(c) for c in r) <= size), 1)


def _free(data: RegistrationData, spec: RegistrationSpec) -> list[str]:
    """The references in use whose labels no earlier step gave back."""
    done = {n for c in spec.swapped for n in c}
    return [n for n in data.names if n not in spec.moved and n not in done]


def _swap_candidate(data: RegistrationData, spec: RegistrationSpec) -> tuple[tuple[str, ...], ...] | None:
    """The relabelling the label-swap effect would make next: among those whose references
    fit within :data:`SHORTLIST_RSS_FACTOR` of the best, the strongest outside evidence
    (:func:`_swap_evidence` and the implanted-marker check), ties to the fewest labels
    changed, then the best fit.

    By the references alone, exchanging the labels at both ends of one diagonal of a square
    fits as well as exchanging those of the other (a turn by 180 degrees about the square's
    normal), and turning every label by one corner as well as by three; the implanted
    markers tell them apart."""
    try:
        before = fit_registration(data, spec)
    except ValueError:
        return None
    free = _free(data, spec)
    rss = []
    for cyc in _relabellings(tuple(free)):
        try:
            after = fit_registration(data, replace(spec, swapped=spec.swapped + cyc))
        except ValueError:      # the relabelling leaves a degenerate configuration
            continue
        rss.append((float(np.sum(after.residuals ** 2)), cyc, after))
    if not rss:
        return None
    rss.sort(key=lambda r: r[0])
    floor = rss[0][0] * SHORTLIST_RSS_FACTOR + np.finfo(float).tiny
    held = {n: _heldout(data, spec, n) for n in free}        # the same for every relabelling
    best, best_key = None, None
    for r, cyc, after in [x for x in rss if x[0] <= floor][:SHORTLIST_MAX]:
        ev = _with_check(_swap_evidence(data, spec, cyc, held), _check_evidence(data, before, after))
        key = (ev["delta_bic"], -sum(len(c) for c in cyc), -r)
        if best_key is None or key > best_key:
            best, best_key = cyc, key
    return best


#: Bonferroni-corrected p below which a reference fails its held-out test (as in reference_checks).
HELDOUT_P = 0.01


def _versus_moved(data: RegistrationData, spec: RegistrationSpec, after_spec: RegistrationSpec) -> dict | None:
    r"""F test of the exchanged labels (``after_spec``) against the best moved-reference fit of ``spec``.

    :math:`F = \frac{(\mathrm{RSS}_{swap} - \mathrm{RSS}_{-k})/3}{\mathrm{RSS}_{-k}/(3(N-1) - p)}`
    with :math:`\mathrm{RSS}_{-k}` the smallest residual sum of squares with one reference
    left out: a small p says a moved reference fits significantly better than the exchange
    despite its three more parameters.  None with fewer than four references in use.
    """
    used = [n for n in data.names if n not in spec.moved]
    if len(used) < MIN_REFERENCES + 1:
        return None
    idx = [data.index(n) for n in used]
    y = ct_positions(data, spec)[idx]
    loo = leave_one_out(data.x_mm[idx], y, scale=spec.scale, like=_distortion(spec, y))
    rss_moved = min(d["rss_without_mm2"] for d in loo if np.isfinite(d["rss_without_mm2"]))
    rss_swap = float(np.sum(fit_registration(data, after_spec).residuals ** 2))
    dof = 3 * (len(used) - 1) - n_params(spec.scale, _mapped(spec))
    f = ((rss_swap - rss_moved) / 3.0) / max(rss_moved / dof, np.finfo(float).tiny)
    return {"rss_swap_mm2": rss_swap, "rss_moved_mm2": float(rss_moved), "f": float(f), "dof": [3, int(dof)],
            "p": f_sf(f, 3, dof)}


def _swap_evidence(data: RegistrationData, spec: RegistrationSpec, cycles: tuple[tuple[str, ...], ...],
                   before: dict | None = None) -> dict:
    """Outside evidence for giving back the CT labels of ``cycles`` (``label-swap`` in the
    module docstring).  ``before``: the held-out tests of the free references under
    ``spec``, where the caller has them already."""
    n_used = len([n for n in data.names if n not in spec.moved])
    free = tuple(_free(data, spec))
    # the choice among the relabellings that change as many labels as this one or fewer: an
    # exchange competes with the other exchanges only (as when pairs were all the effect
    # tried), a cycle of three with those and the other cycles of three, ...
    n_pairs = _n_relabellings(free, sum(len(c) for c in cycles))
    # the worst held-out failure among the references free to be relabelled: the same for
    # every relabelling, so the evidence does not grow with the number of labels a
    # relabelling touches (a cycle of four is not favoured over the exchange it ties with)
    if before is None:
        before = {n: _heldout(data, spec, n) for n in free}
    after_spec = replace(spec, swapped=spec.swapped + tuple(cycles))
    after = {n: _heldout(data, after_spec, n) for n in data.names if n not in spec.moved}
    failing = sorted(n for n, h in after.items() if h is not None and h["p_bonferroni"] < HELDOUT_P)
    versus = _versus_moved(data, spec, after_spec)
    held = [h["delta_bic"] for h in before.values() if h is not None]
    note = ("held-out evidence of the worst of the references free to be relabelled, as moving-reference would "
            "claim it, "
            "+ 3 ln 3N (no displacement parameters) - 2 ln K (K relabellings changing as many labels or fewer "
            "to choose from); counted only when "
            "after it every reference passes its held-out test and a moved reference does not fit "
            f"significantly better (F test, p >= {HELDOUT_P:g})")
    d = 0.0
    if failing:
        note += f"; not counted: {', '.join(failing)} still fail{'s' if len(failing) == 1 else ''} the held-out test"
    elif versus is not None and versus["p"] < HELDOUT_P:
        note += f"; not counted: a moved reference fits significantly better (p = {versus['p']:.2g})"
    elif held:
        d = max(0.0, max(held) + 3 * np.log(3 * n_used) - 2 * np.log(n_pairs))
    return {"delta_bic": float(d), "cycles": [list(c) for c in cycles], "n_relabellings": int(n_pairs),
            "heldout_before": before,
            "heldout_failing_after": failing, "versus_moved_reference": versus, "note": note}


#: The CT axes the ct-axis-scale effect tries, the slice axis (z) first: it is kept on a tie.
AXIS_ORDER = (2, 0, 1)
#: The in-plane CT axes the ct-gantry-shear effect shears by the slice axis, y first (a gantry
#: tilts about the patient's left-right axis, shifting each slice anterior-posterior): it is
#: kept on a tie.
SHEAR_ORDER = (1, 0)
#: The CT axis the ct-gantry-shear effect shears by: the slice axis, z.
SHEAR_BY = 2


def _axis_levers(data: RegistrationData, spec: RegistrationSpec, T: Similarity | None = None,
                 shear: bool = False) -> dict[int, float]:
    """Per CT axis, :func:`~bsipipe.geometry.registration.axis_scale_lever` (mm) of the references
    ``spec`` uses, at its fitted transform (``T``, where the caller has it); with ``shear``, per
    in-plane axis of :data:`SHEAR_ORDER`, :func:`~bsipipe.geometry.registration.shear_lever` by
    the slice axis."""
    used = np.array([n not in spec.moved for n in data.names])
    if T is None:
        y = ct_positions(data, spec)
        T = fit_similarity(data.x_mm[used], y[used], scale=spec.scale)
    if shear:
        return {a: shear_lever(T, data.x_mm[used], a, by=SHEAR_BY, scale=spec.scale) for a in SHEAR_ORDER}
    return {a: axis_scale_lever(T, data.x_mm[used], a, scale=spec.scale) for a in AXIS_ORDER}


def _axis_candidates(data: RegistrationData, spec: RegistrationSpec, T: Similarity | None = None,
                     shear: bool = False) -> list[int]:
    """The CT axes the ct-axis-scale effect (``shear``: the ct-gantry-shear effect) may try: none
    with fewer than four references in use (its F test would have two degrees of freedom, or
    none) or where ``spec`` has either effect already (one CT-geometry effect per registration:
    below), else those along which the references determine a stretch (a shear by the slice
    axis): a lever above a millionth of their spread; ``T``: ``spec``'s fitted transform, where
    the caller has it.

    Why one of the two at most: each is one parameter more on the twelve numbers of four
    references (5 degrees of freedom left, 4 with both), and a pure stretch or a pure shear is
    told from the other by a wide margin (outside evidence 69-187 for the right one at 1-20
    degrees or 2-10 %, under 3 for the other).  A CT both read without its tilt and with its
    slices' spacing taken perpendicular to them (z times cos tilt) keeps the shear only: at 20
    degrees FRE 0.066 mm and the implanted markers 0.37 mm RMS off after it (10 degrees: 0.019
    and 0.087 mm), left to the ``ct-gantry-shear`` warning's advice (read the CT with its tilt
    corrected).
    """
    used = [n for n in data.names if n not in spec.moved]
    if spec.ct_axis is not None or spec.ct_shear is not None or len(used) < MIN_REFERENCES + 1:
        return []
    spread = float(np.sqrt(np.sum((data.y_mm - data.y_mm.mean(axis=0)) ** 2)))
    return [a for a, lev in _axis_levers(data, spec, T, shear).items() if lev > 1e-6 * spread]


def _with_ct_axis(spec: RegistrationSpec, axis: int, shear: bool) -> RegistrationSpec:
    return replace(spec, ct_shear=axis) if shear else replace(spec, ct_axis=axis)


def _axis_choice(data: RegistrationData, spec: RegistrationSpec, shear: bool = False) -> int | None:
    """The CT axis the ct-axis-scale effect would scale (``shear``: the one the ct-gantry-shear
    effect would shear by the slice axis): the strongest outside evidence (:func:`_axis_evidence`:
    the references' F test and the implanted markers), then the best fit, then the first of
    :data:`AXIS_ORDER` (the slice axis; :data:`SHEAR_ORDER`: y)."""
    try:
        before = fit_registration(data, spec)
    except ValueError:
        return None
    if float(np.sum(before.residuals ** 2)) <= rounding_rss(len(before.residuals), data.x_mm, data.y_mm):
        return None         # the references fit to rounding: there is no misfit a stretch could explain
    best, best_key = None, None
    axes = _axis_candidates(data, spec, before.transform, shear)
    for j, a in enumerate(axes):
        try:
            after = fit_registration(data, _with_ct_axis(spec, a, shear))
        except ValueError:
            continue
        ev = _axis_evidence(data, spec, before, after, n_axes=len(axes))
        key = (ev["delta_bic"], -ev["rss_after_mm2"], -j)
        if best_key is None or key > best_key:
            best, best_key = a, key
    return best


def _axis_evidence(data: RegistrationData, spec: RegistrationSpec, before: RegistrationFit,
                   after: RegistrationFit, n_axes: int | None = None) -> dict:
    """Outside evidence for ``ct-axis-scale`` or ``ct-gantry-shear`` (module docstring; which one:
    ``after.spec``'s): the references' F test of the added parameter, minus its cost and the
    choice of axis, plus the implanted-marker check (``before``, ``after``: the fits of ``spec``
    and of ``spec`` with the scale along the axis, or the shear; ``n_axes``: the axes tried,
    where the caller has counted them)."""
    shear = after.spec.ct_shear is not None
    n_used = int(np.sum(after.used))
    floor = rounding_rss(3 * n_used, data.x_mm, data.y_mm)
    rss0 = max(float(np.sum(np.asarray(before.residuals) ** 2)), floor)
    rss1 = max(float(np.sum(np.asarray(after.residuals) ** 2)), floor)
    dof = 3 * n_used - n_params(after.spec.scale, True)
    f = (rss0 - rss1) / max(rss1 / dof, np.finfo(float).tiny)
    p = f_sf(max(f, 0.0), 1, dof)
    k = max(len(_axis_candidates(data, spec, before.transform, shear)) if n_axes is None else n_axes, 1)
    chi2_equiv = chi2_isf(max(p, 1e-300), 1)
    T = after.transform
    what = (f"shear of the CT's {CT_AXES[T.axis]} axis by its {CT_AXES[T.by]} axis" if shear
            else "scale along the CT axis")
    ev = {"delta_bic": float(chi2_equiv - np.log(3 * n_used) - 2 * np.log(k)),
          "axis": CT_AXES[T.axis], **({"by": CT_AXES[T.by]} if shear else {}), "factor": float(T.factor),
          **({"tilt_deg": T.tilt_deg} if shear else {}),
          "f": float(f), "dof": [1, int(dof)], "p": float(p), "chi2_equivalent": float(chi2_equiv),
          "n_axes": int(k), "rss_before_mm2": rss0, "rss_after_mm2": rss1,
          "note": f"the references' F test of the {what}, as chi2_1 of equal tail probability, "
                  "- ln 3N (the parameter) - 2 ln K (K CT axes tried: the one with the strongest evidence is taken)"}
    return _with_check(ev, _check_evidence(data, before, after))


#: Standard error of a CT axis's scale factor above which the references cannot show a
#: slice-spacing error of 5 % (the size a wrong reconstruction interval or an uncorrected
#: gantry tilt of 18 degrees gives) at three standard errors.
AXIS_SCALE_SE_MAX = 0.05 / 3
#: The gantry tilt (degrees) registration.json's ``ct_gantry_shear_check`` weighs: the low end
#: of the 10-25 degrees a head CT is tilted by to spare the eyes.
UNSEEN_GANTRY_TILT_DEG = 10.0
#: Standard error of a shear factor above which the references cannot show a gantry tilt of
#: :data:`UNSEEN_GANTRY_TILT_DEG` read without its tilt, at three standard errors.
SHEAR_SE_MAX = float(np.tan(np.radians(UNSEEN_GANTRY_TILT_DEG))) / 3
#: A fitted gantry tilt beyond this (degrees) is turned down: CT gantries tilt by 30 degrees at
#: most, so a larger shear stands for something else (a wrong file, mixed-up markers).
MAX_GANTRY_TILT_DEG = 30.0


def axis_scale_identification(data: RegistrationData, spec: RegistrationSpec, fle_mm: float,
                              axis: int = 2) -> dict:
    """How well the references ``spec`` uses determine a scale along CT ``axis`` (default the
    slice axis, z): their lever (:func:`~bsipipe.geometry.registration.axis_scale_lever`, mm)
    and the standard error of the factor at the per-axis localisation error ``fle_mm / sqrt 3``;
    ``identified`` when there are four references or more and that standard error is at most
    :data:`AXIS_SCALE_SE_MAX`."""
    return _identification(data, spec, fle_mm, axis, False)


def shear_identification(data: RegistrationData, spec: RegistrationSpec, fle_mm: float, axis: int = 1) -> dict:
    """How well the references ``spec`` uses determine a shear of CT ``axis`` (default y) by the
    slice axis (a gantry tilt read without it), as :func:`axis_scale_identification`:
    ``identified`` when there are four references or more and the shear factor's standard error
    is at most :data:`SHEAR_SE_MAX` (a tilt of :data:`UNSEEN_GANTRY_TILT_DEG` at three of them)."""
    return _identification(data, spec, fle_mm, axis, True)


def _identification(data: RegistrationData, spec: RegistrationSpec, fle_mm: float, axis: int, shear: bool) -> dict:
    used = [n for n in data.names if n not in spec.moved]
    lever = _axis_levers(data, replace(spec, ct_axis=None, ct_shear=None), shear=shear)[axis]
    se = float(fle_mm / np.sqrt(3.0) / lever) if lever > 0 and np.isfinite(fle_mm) else float("inf")
    se_max = SHEAR_SE_MAX if shear else AXIS_SCALE_SE_MAX
    return {"axis": CT_AXES[axis], **({"by": CT_AXES[SHEAR_BY]} if shear else {}), "n_references": len(used),
            "lever_mm": float(lever), "factor_se": se,
            "identified": bool(len(used) >= MIN_REFERENCES + 1 and se <= se_max), "se_max": se_max}


def _implausible_tilt(before, after) -> str | None:
    """The loop's veto: a ct-gantry-shear whose tilt is beyond :data:`MAX_GANTRY_TILT_DEG`."""
    if after.spec.ct_shear is None or before.spec.ct_shear is not None:
        return None
    tilt = after.fit.transform.tilt_deg
    if abs(tilt) <= MAX_GANTRY_TILT_DEG:
        return None
    return (f"a gantry tilt of {tilt:.1f} degrees, beyond the {MAX_GANTRY_TILT_DEG:g} a CT gantry tilts by: "
            "the shear stands for something else")


def registration_effects(data: RegistrationData) -> list[Effect]:
    """The candidate effects, in the order the loop tries them."""

    def add_scale(spec: RegistrationSpec):
        return None if spec.scale else replace(spec, scale=True)

    def add_moved(spec: RegistrationSpec):
        name = _candidate(data, spec)
        return None if name is None else replace(spec, moved=spec.moved + (name,))

    def moved_evidence(before, after) -> dict | None:
        new = [n for n in after.spec.moved if n not in before.spec.moved]
        if not new:
            return None
        return _with_check(_outside_evidence(data, before.spec, new[0]), _check_evidence(data, before.fit, after.fit))

    def add_swap(spec: RegistrationSpec):
        cyc = _swap_candidate(data, spec)
        return None if cyc is None else replace(spec, swapped=spec.swapped + cyc)

    def swap_evidence(before, after) -> dict | None:
        new = tuple(c for c in after.spec.swapped if c not in before.spec.swapped)
        if not new:
            return None
        ev = _swap_evidence(data, before.spec, new)
        rss0 = float(np.sum(np.asarray(before.fit.residuals) ** 2))
        rss1 = float(np.sum(np.asarray(after.fit.residuals) ** 2))
        if rss1 >= rss0:
            # a true exchange makes the references consistent: their misfit falls by orders of
            # magnitude.  One that leaves them fitting no better is no label swap (three labels
            # in a cycle: exchanging two of them had been kept on the implanted markers alone,
            # FRE 13.61 -> 14.15 mm), and nothing outside it is counted for it
            ev.update(delta_bic=0.0, rss_before_mm2=rss0, rss_after_mm2=rss1,
                      note=ev["note"] + f"; not counted: the references fit no better after the exchange "
                                        f"(RSS {rss0:.4g} -> {rss1:.4g} mm^2)")
            return ev
        return _with_check(ev, _check_evidence(data, before.fit, after.fit))

    def add_axis(spec: RegistrationSpec):
        a = _axis_choice(data, spec)
        return None if a is None else replace(spec, ct_axis=a)

    def axis_evidence(before, after) -> dict | None:
        if after.spec.ct_axis is None or before.spec.ct_axis is not None:
            return None
        return _axis_evidence(data, before.spec, before.fit, after.fit)

    def add_shear(spec: RegistrationSpec):
        a = _axis_choice(data, spec, shear=True)
        return None if a is None else replace(spec, ct_shear=a)

    def shear_evidence(before, after) -> dict | None:
        if after.spec.ct_shear is None or before.spec.ct_shear is not None:
            return None
        return _axis_evidence(data, before.spec, before.fit, after.fit)

    return [
        Effect("scale",
               "magnification the C-arm calibration did not capture (source distance or pixel size off) "
               "scales every X-ray length by the same factor",
               "residual pointing away from (or towards) the references' centroid, growing with the distance "
               "from it: correlation with the centred CT coordinates",
               add_scale, ("scale",)),
        # before moving-reference: when an exchange makes every reference consistent it is the
        # simpler explanation (no displacement parameters), and it wins a tie
        Effect("label-swap",
               "references carry each other's labels in the CT file (or in the tracking seeds): two exchanged, or "
               "more in a cycle; a click order mixed up",
               "two (or more) references fail their held-out prediction at the registration frame without "
               "moving over the trial; giving the CT labels back (an exchange or a cycle) makes every reference "
               "consistent",
               add_swap, ("label_swaps",), evidence=swap_evidence),
        Effect("moving-reference",
               "a reference marker on the brain surface rather than the skull moves with the tissue "
               "(or was displaced between the CT and the trial)",
               "one reference's residual far above the others' at the registration frame (its held-out "
               "prediction fails), or its motion relative to the other references over the trial",
               add_moved, ("displacement_<reference>_mm",), evidence=moved_evidence),
        Effect("ct-axis-scale",
               "the CT's lengths along one of its axes are off: a slice spacing (reconstruction interval) that "
               "is not the header's slice thickness, or a tilted gantry's table increment taken for the spacing",
               "the references' residuals grow with their spread along that CT axis; markers far from them "
               "along it (implanted markers below a craniotomy on an axial CT) are off by (k - 1) times that "
               "distance while the references fit well",
               add_axis, ("ct_axis", "ct_axis_scale"), evidence=axis_evidence),
        Effect("ct-gantry-shear",
               "the CT was acquired with the gantry tilted (10-25 degrees for a head, to spare the eyes) and read "
               "without its tilt (DICOM's GantryDetectorTilt ignored): the slices are stacked without their "
               "in-plane shift, so every CT position is sheared, y (or x) off by tan(tilt) times its z",
               "the references' residuals grow with their spread along z, along y (or x); markers far from them "
               "along z are off along y by tan(tilt) times that distance while the references fit well",
               add_shear, ("ct_shear_axis", "ct_gantry_shear"), evidence=shear_evidence),
    ]


def close_registration_loop(data: RegistrationData, spec0: RegistrationSpec, *, loop: bool = True,
                            noise_ceiling: float | None = None) -> LoopReport:
    """Fit ``spec0`` and, with ``loop``, try ``scale``, ``label-swap``, ``moving-reference``, ``ct-axis-scale``
    and ``ct-gantry-shear`` (bsipipe.loop's rule, a shear beyond :data:`MAX_GANTRY_TILT_DEG` vetoed;
    ``noise_ceiling``, mm per coordinate: :func:`bsipipe.loop.run_loop`'s)."""
    cands = registration_effects(data) if loop else []

    def fit(spec):
        return fit_registration(data, spec)

    report = run_loop(fit, spec0, cands, covariates=registration_covariates(data),
                      describe=lambda s: s.describe(), unit="mm", noise_ceiling=noise_ceiling,
                      veto=_implausible_tilt)
    if not loop:
        report.stopped_because = "--no-loop: the declared model only"
    return report


def reference_checks(data: RegistrationData, spec: RegistrationSpec) -> dict:
    """Per reference: the held-out test at frame F and the motion test over the trial (for the report).

    ``flagged`` when the held-out test rejects at Bonferroni-corrected 1 % or the motion test
    has delta BIC > 10 (very strong) and no other reference's motion explains it
    (``motion_explained_by``, :func:`motion_explainers`).  The held-out test uses every reference, with the CT
    labels exchanged as ``spec`` has them.
    """
    out = {}
    swapped = ct_labels(spec)
    for n in data.names:
        held = _heldout(data, replace(spec, moved=()), n)
        motion = data.motion(n)
        explained = motion_explainers(data, n)
        flag = bool((held is not None and held["p_bonferroni"] < HELDOUT_P) or (_flagged(motion) and not explained))
        out[n] = {"heldout": held, "motion": motion, "motion_explained_by": explained, "flagged": flag,
                  "moved": n in spec.moved, "ct_label": swapped.get(n, n)}
    return out
