"""The calibration stage's loop: candidate effects that grow the distortion model, and the
glue between :func:`bsipipe.imaging.calibrate.calibrate_camera` and
:func:`bsipipe.loop.run_loop`.

The loop fits the declared model, tests the reprojection residual for structure (radial and
tangential components about the principal point, view by view in grid order, against the
radius), and adds an effect only when the BIC drops by more than 10, the fitted RMS drops by
more than 5 % *and* the leave-one-view-out held-out RMS drops by more than 5 %
(:class:`bsipipe.loop.SelectionRule`'s defaults, ``rmse_gain_min`` and
``heldout_gain_min``): an effect that only fits the detection noise of the views it saw does
not predict a view it has not seen.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..loop import Effect, LoopReport, run_loop
from .calibrate import (MIN_HELDOUT_VIEWS, Calibration, ModelSpec, ViewData, calibrate_camera, heldout_error,
                        residual_components)


def _higher(spec: ModelSpec):
    if not spec.rational:
        return replace(spec, rational=True)
    if not spec.thin_prism:
        return replace(spec, thin_prism=True)
    return None


HIGHER_ORDER = Effect(
    "higher-order-distortion",
    "An image intensifier's pincushion (its curved input phosphor) and a wide-angle lens bend rays more "
    "than OpenCV's k1, k2, k3 describe; the rational terms k4-k6 and then the thin-prism terms s1-s4 "
    "(a tilted sensor or intensifier output screen) are added in turn.",
    "A radial residual that changes sign with the radius (few runs, a binned ANOVA over the radius), the "
    "same in every view; thin prism: a residual that is a fixed shift growing as r^2 in one direction.",
    _higher, ("k4", "k5", "k6", "s1", "s2", "s3", "s4"))

S_DISTORTION = Effect(
    "s-distortion",
    "The earth's (and stray) magnetic field turns the electron paths in an image intensifier, more at "
    "larger radius: the image is twisted, a straight line through the centre becomes an S.",
    "A tangential residual (perpendicular to the radius) that grows with the radius and has the same "
    "sign in every view: the runs and lag-1 tests and a correlation of the residual with the radius.",
    lambda s: None if s.s_distortion else replace(s, s_distortion=True), ("s_t1_rad", "s_t2_rad"))

LOCAL_DISTORTION = Effect(
    "local-distortion",
    "Irregular, smooth warps of a real intensifier (phosphor and electron-optics imperfections, "
    "magnetic fields that are not uniform) that no global model captures; XMALab corrects them with a "
    "local weighted mean over a bead grid.  Here a thin-plate spline of the pooled residuals, its "
    "smoothing chosen by view-wise cross-validation.",
    "A residual that is spatially coherent over the detector and repeats from view to view: neighbouring "
    "beads agree (few runs, lag-1 autocorrelation) without a purely radial or tangential pattern.",
    lambda s: None if s.local else replace(s, local=True), ("local_dof",),
    # a spline of the residual absorbs an S-distortion (and, with it, the principal point) as
    # readily as a warp: it takes what the physical terms leave, never their place
    catch_all=True)

#: The candidates in the order the loop tries them.
CANDIDATES = (HIGHER_ORDER, S_DISTORTION, LOCAL_DISTORTION)


@dataclass
class _LoopFit:
    """What :func:`bsipipe.loop.run_loop` needs from one fit."""

    cal: Calibration
    residuals: list
    radius_px: np.ndarray
    params: dict
    n_params: int
    success: bool


#: The terms an effect switches on (a model with more of them contains one with fewer).
_TERMS = ("rational", "thin_prism", "s_distortion", "local")


def _contains(big: ModelSpec, small: ModelSpec) -> bool:
    """Whether ``big`` has every term ``small`` has (and the same fixed parameters)."""
    return (all(getattr(small, f) <= getattr(big, f) for f in _TERMS)
            and (small.fix_aspect_ratio, small.fix_principal_point) == (big.fix_aspect_ratio, big.fix_principal_point))


class CalibrationLoop:
    """Fits and held-out errors of camera models on a fixed set of views, cached by spec."""

    def __init__(self, views: Sequence[ViewData], image_size: tuple[int, int], base: Calibration):
        self.views = list(views)
        self.image_size = tuple(image_size)
        self.base = base
        self._cals: dict[ModelSpec, Calibration] = {base.camera.spec: base}
        self._heldout: dict[ModelSpec, tuple[float, dict]] = {}
        self._folds: dict[ModelSpec, list[dict]] = {}

    def calibration(self, spec: ModelSpec) -> Calibration:
        """The fit of ``spec``, started from the richest model fitted so far that it contains
        (the loop's current model, which it augments by one effect), else the declared one.
        From the declared camera, S-distortion plus a local correction had run off to fx 3014,
        fy 2762, cy -70 px (truth 3300, 3300, 500), its leave-one-view-out refits to a held-out
        RMS of 65 px, and the loop turned down the correction the data needed."""
        if spec not in self._cals:
            init = max((c for k, c in self._cals.items() if _contains(spec, k)),
                       key=lambda c: sum(getattr(c.camera.spec, f) for f in _TERMS), default=self.base)
            self._cals[spec] = calibrate_camera(self.views, self.image_size, spec, init=init.camera,
                                                twist_centre_px=self.base.camera.twist_centre_px)
        return self._cals[spec]

    def fit(self, spec: ModelSpec) -> _LoopFit:
        cal = self.calibration(spec)
        parts, radius = residual_components(cal)
        return _LoopFit(cal, parts, radius, cal.params, cal.n_params, cal.success)

    def heldout(self, spec: ModelSpec) -> float:
        return self.heldout_detail(spec)[0]

    def heldout_detail(self, spec: ModelSpec) -> tuple[float, dict]:
        if spec not in self._heldout:
            folds: list[dict] = []
            self._heldout[spec] = heldout_error(self.calibration(spec), spec, folds=folds)
            self._folds[spec] = folds
        return self._heldout[spec]

    def folds(self, spec: ModelSpec) -> list[dict]:
        """The leave-one-view-out refits' parameters of ``spec`` (:func:`heldout_error`)."""
        self.heldout_detail(spec)
        return self._folds[spec]


def close_loop(views: Sequence[ViewData], image_size: tuple[int, int], base: Calibration,
               candidates: Sequence[Effect] = CANDIDATES) -> tuple[LoopReport, Calibration, CalibrationLoop]:
    """Run the loop from the declared model ``base``; return the report, the final calibration
    (its held-out error filled in) and the fitter (for the baseline's held-out error)."""
    lp = CalibrationLoop(views, image_size, base)
    # with too few views to hold one out, effects are weighed by BIC alone
    report = run_loop(lp.fit, base.camera.spec, candidates,
                      heldout=lp.heldout if len(views) >= MIN_HELDOUT_VIEWS else None,
                      covariates=lambda res: {"radius_px": res.radius_px}, describe=lambda s: s.describe(),
                      unit="px")
    final = lp.calibration(report.final.spec)
    return report, final, lp
