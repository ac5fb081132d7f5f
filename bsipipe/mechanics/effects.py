r"""The effects fit-ogden's loop may add to a force model, and the loop's wiring for machine logs.

Each effect switches one part of :class:`~bsipipe.mechanics.fit.ForceModelSpec` on (the
force model itself is in :mod:`bsipipe.mechanics.fit`); the names are the contract's:

============================ ================================================================
``viscoelastic-relaxation``  one more quasi-linear viscoelastic Prony term (up to 3; relaxation
                             times bounded by the logs' sampling and span, 0.1-100 s for the
                             seeds' tests), one set over every log and segment
``contact-offset``           the true contact differs from the detected one beyond the detector's
                             uncertainty: a free contact shift and an uneven-top toe (per log)
``load-baseline-drift``      load-cell offset and linear drift in time (per log)
``machine-compliance``       the crosshead extension includes frame deflection ``C F`` (shared)
``model-order``              one more Ogden term (ogden -> ogden2 -> ogden3)
``periodic-disturbance``     a sinusoid on the load reading (per log): mains pick-up aliased by
                             the sampling, a pump's or fan's vibration; its frequency starts
                             from the residual's periodogram
``no-slip-platens``          the specimen is bonded to the platens (axisymmetric FE force,
                             :mod:`bsipipe.mechanics.noslip`); offered only when the boundary is
                             not declared; evidence from a side-camera width series
                             (:func:`width_evidence`) or from specimens of different aspect
============================ ================================================================

:func:`close_loop_logs` runs :func:`bsipipe.loop.run_loop` on machine logs: warm-started fits,
held-out error over interleaved blocks of every log where there are several logs, the
load-cell noise level measured from the logs (:func:`force_noise_rms`), and residual
covariates (time, nominal strain, crosshead rate, load phase, force).  :func:`close_loop_tables` does
the same for stress-stretch tables (``model-order`` only: a table has no time).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np

from ..loop import Effect, LoopReport, SelectionRule, run_loop
from .contact import force_noise
from .fit import (FLAT_TOE, MIN_UNLOADED_SAMPLES, ForceModelSpec, LogData, contact_compression, disturbance_line_test,
                  fit_logs, fit_tables, parameter_names, predict_force, toe_params)

log = logging.getLogger(__name__)

_LAW_ORDER = ("ogden", "ogden2", "ogden3")
_MAX_PRONY = 3


# --- the effects -------------------------------------------------------------------------------

def _more_prony(spec: ForceModelSpec):
    return replace(spec, prony=spec.prony + 1) if spec.prony < _MAX_PRONY else None


def _more_terms(spec: ForceModelSpec):
    if spec.law in _LAW_ORDER[:-1] and spec.boundary == "frictionless":
        return replace(spec, law=_LAW_ORDER[_LAW_ORDER.index(spec.law) + 1])
    return None


VISCOELASTIC = Effect(
    "viscoelastic-relaxation",
    "Brain tissue relaxes: the force at a given stretch depends on the loading history, higher at "
    "1 mm/s than at 0.01 mm/s and falling during a hold. Quasi-linear viscoelastic Prony terms "
    "G(t) = g_inf + sum g_i exp(-t/tau_i) on the elastic force, one set over every log and segment.",
    "Residual differs between speeds (per-log means, crosshead rate) and between ramp and hold "
    "(load phase); during a hold the data relax below a hyperelastic model's constant force; long "
    "runs of one sign (lag-1 autocorrelation).",
    _more_prony, ("g{i}", "tau{i}_s"))

CONTACT_OFFSET = Effect(
    "contact-offset",
    "The true contact differs from the detected one by more than the detector's uncertainty: an "
    "uneven top surface the platen meets at its highest point first and flattens over 2 c of travel, "
    "the contact area growing as a power p of the indentation (1: a dome or a tilted face), the "
    "touching part carrying between its own compression (spread s = 0, a bed of independent columns) "
    "and the whole travel (s = 1) (contact_compression), so the force rises early and slowly. "
    "Frees each log's contact shift (the declared model holds it within the detector's standard "
    "deviation) and fits the toe's half-width c, exponent p and spread s.",
    "Residual concentrated just after contact and changing sign there (correlates with nominal "
    "strain at small strain), smaller at large strain; a contact shift many detector standard "
    "deviations from the detected contact.",
    lambda s: None if s.contact_offset else replace(s, contact_offset=True), ("contact_offset_mm", "contact_toe_mm", "contact_toe_exponent", "contact_toe_spread"))

BASELINE_DRIFT = Effect(
    "load-baseline-drift",
    "The load cell's zero is offset and drifts in time (temperature, creep of the cell).",
    "Non-zero residual before contact and after unloading; residual linear in time across the "
    "whole log.",
    lambda s: None if s.baseline_drift else replace(s, baseline_drift=True), ("baseline_n", "drift_n_per_s"))

COMPLIANCE = Effect(
    "machine-compliance",
    "The recorded crosshead extension includes the frame's and load cell's deflection, "
    "proportional to the load: the specimen is compressed less than the log says.",
    "Model too stiff where the force is high: residual grows with force and strain, following "
    "the force curve's shape.",
    lambda s: None if s.compliance else replace(s, compliance=True), ("compliance_mm_per_n",))

MODEL_ORDER = Effect(
    "model-order",
    "One Ogden term cannot follow the tissue's stiffening over the strain range tested.",
    "Smooth residual against stretch with sign changes in mid-range, the same in every log and "
    "segment (no dependence on rate or time beyond stretch).",
    _more_terms, ("mu{i}_pa", "alpha{i}"))


SPECIMEN_SCATTER = Effect(
    "specimen-scatter",
    "Specimens differ: brain tissue from different animals, regions or post-mortem times is "
    "tens of per cent stiffer or softer.  Each log's moduli are the law's times its own factor "
    "exp(z_i), the factors' geometric mean 1 (the law is the geometric-mean specimen's); the "
    "exponents and every other effect stay shared.",
    "Per-log residual means of opposite signs, growing with the force (one log's model too "
    "soft all along, another's too stiff); held out, each log's blocks predicted as badly.",
    lambda s: None if s.specimen_scatter else replace(s, specimen_scatter=True), ("stiffness_log_factor[i]",))


PERIODIC_DISTURBANCE = Effect(
    "periodic-disturbance",
    "The load channel carries a periodic signal that is no force on the specimen: mains hum "
    "picked up by the load cell's cable or amplifier (50 or 60 Hz and harmonics; sampled at "
    "tens of Hz it shows at its alias, |f - k f_s|, 50.5 Hz at 50 Hz as a 0.5 Hz swing) or the "
    "vibration of a pump, fan or the frame.  A sinusoid A sin(2 pi f (t - t0) + phi) added to "
    "each log's model force, its frequency started from the residual's periodogram "
    "(disturbance_frequencies) and refined with A and phi in the fit; f at least 1.5 cycles over "
    "the log and at most its Nyquist frequency.",
    "A narrow peak in the residual's periodogram (most of the misfit at one frequency, its "
    "harmonics perhaps), a residual that swings about zero with a constant period through "
    "approach, ramp and hold alike, unrelated to stretch or force; lag-1 autocorrelation high "
    "for a slow (aliased) swing, runs alternating for a fast one.",
    lambda s: None if s.periodic_disturbance else replace(s, periodic_disturbance=True),
    ("disturbance_n", "disturbance_hz", "disturbance_phase_rad"))


def no_slip_effect(evidence=None) -> Effect:
    """``no-slip-platens``, with outside evidence (e.g. :func:`width_evidence`) when there is any."""
    return Effect(
        "no-slip-platens",
        "The specimen is bonded to the platens (sandpaper, glue): its ends cannot spread, it barrels, "
        "and the homogeneous formula overestimates mu (about 20-35 % at height/diameter 1, 60-130 % "
        "at 0.5). Modelled by an axisymmetric nearly incompressible FE cylinder.",
        "In the force of one specimen almost none (a homogeneous law with a larger mu mimics it); "
        "specimens of different height/diameter disagree (per-specimen residual means); a side "
        "camera sees mid-height width grow faster than D * stretch^-1/2.",
        lambda s: replace(s, boundary="no-slip") if s.boundary == "frictionless" and s.law == "ogden" else None,
        ("mu_pa", "alpha"), evidence)


def mechanics_effects(*, boundary_declared: bool, width: "WidthSeries | None" = None,
                      logs: Sequence[LogData] = ()) -> list[Effect]:
    """fit-ogden's candidate effects for machine logs, in the order they are tried.

    ``load-baseline-drift`` is not a candidate when a log has no samples before its contact
    (:func:`baseline_measurable`): its load cell's zero is then taken as 0 N.
    ``no-slip-platens`` is a candidate only when the command line did not declare the
    boundary and the data can show it: a width series (of ``logs[width.log_index]``, whose
    evidence :func:`width_evidence` then carries), or specimens whose height/diameter
    differ by at least :data:`NO_SLIP_MIN_ASPECT_SPREAD` (the barrelling factor then differs
    between them).  In the force of one shape alone a homogeneous law with a larger mu
    mimics bonded platens, so the candidate would only be fitted, never decided (and a
    new shape costs minutes of FE to tabulate): declare ``--boundary`` instead.
    ``periodic-disturbance`` is listed after the force's and the load cell's own effects (the
    rarer mechanism); with its three parameters it must beat them by the tie margin, and
    :func:`disturbance_veto` turns it down where its sinusoid is no line in the spectrum.
    """
    effects = [VISCOELASTIC, CONTACT_OFFSET, BASELINE_DRIFT, COMPLIANCE, MODEL_ORDER]
    if len(logs) > 1:
        # two specimens of 600 and 850 Pa fitted together: with nothing to take their difference
        # the loop had kept a drift, a compliance and 1 mm toes, mu 1397 Pa, alpha +13.8
        effects.append(SPECIMEN_SCATTER)
    # 2 mN of 50.5 Hz hum on a 1 mm/s log sampled at 50 Hz (a 0.5 Hz swing): with nothing to
    # take it the loop had kept a contact offset, a drift and a compliance, alpha +13.4 for -4.7
    effects.append(PERIODIC_DISTURBANCE)
    unzeroed = [lg.name for lg in logs if not baseline_measurable(lg)]
    if unzeroed:
        # On a ramp at constant speed an offset and a drift in time are a force linear in the
        # displacement: with no unloaded sample they would take the tissue's response.
        effects.remove(BASELINE_DRIFT)
        log.info("loop: load-baseline-drift is not tried: %s ha%s fewer than %d samples before the contact, so "
                 "the load cell's zero cannot be measured (taken as 0 N)", ", ".join(unzeroed),
                 "s" if len(unzeroed) == 1 else "ve", MIN_UNLOADED_SAMPLES)
    if not boundary_declared:
        aspects = [lg.aspect for lg in logs]
        spread = max(aspects) / min(aspects) if aspects else 1.0
        if width is not None or spread >= NO_SLIP_MIN_ASPECT_SPREAD:
            effects.append(no_slip_effect(width_evidence(width, logs) if width is not None else None))
        else:
            log.info("loop: no-slip-platens is not tried: no width series and the specimens' height/diameter "
                     "differ by %.1f %% (< %.0f %%); declare --boundary no-slip if the platens held the specimen",
                     100 * (spread - 1), 100 * (NO_SLIP_MIN_ASPECT_SPREAD - 1))
    return effects


def baseline_measurable(lg: LogData) -> bool:
    """Whether ``lg`` has samples before its contact (:data:`MIN_UNLOADED_SAMPLES`) to measure the load
    cell's zero: not so for a record that starts loaded, its contact given before the first sample."""
    return int(np.count_nonzero(lg.displacement_mm < lg.contact_mm)) >= MIN_UNLOADED_SAMPLES


#: Least ratio of the largest to the smallest height/diameter over the logs for which the
#: loop tries ``no-slip-platens`` from the force alone.  The bonded/homogeneous force ratio
#: at 20 % compression (alpha -4.7) is 1.68, 1.40 and 1.22 at H/D 0.5, 2/3 and 1 (the shipped
#: tables), so shapes 1.25x apart differ by more than 10 % in it.
NO_SLIP_MIN_ASPECT_SPREAD = 1.25


# --- outside evidence: the lateral width series ------------------------------------------------

@dataclass(frozen=True, eq=False)
class WidthSeries:
    """Mid-height width of the specimen over time (side camera), for one log.

    ``time_s`` on the log's clock, ``width_mm`` the measured width; ``log_index`` the log it
    belongs to (``--width-csv`` names the first log's).
    """

    time_s: np.ndarray
    width_mm: np.ndarray
    log_index: int = 0

    def __post_init__(self):
        t = np.asarray(self.time_s, dtype=float)
        w = np.asarray(self.width_mm, dtype=float)
        if t.ndim != 1 or t.shape != w.shape or len(t) < 3:
            raise ValueError("a width series needs at least 3 samples of time_s and width_mm of one length")
        if not np.all(np.isfinite(t)) or not np.all(np.isfinite(w)):
            raise ValueError("the width series has non-finite values")
        object.__setattr__(self, "time_s", t)
        object.__setattr__(self, "width_mm", w)


def _stretch_at(log_: LogData, values: Mapping, spec: ForceModelSpec, time_s: np.ndarray) -> np.ndarray:
    """Specimen stretch at ``time_s`` under a fitted model (its contact offset and compliance)."""
    d = np.interp(time_s, log_.time_s, log_.displacement_mm)
    f = np.interp(time_s, log_.time_s, log_.force_n)
    off = float(values.get("contact_offset_mm", 0.0))       # present where the fit refined the contact
    c_toe, p_toe, s_toe = toe_params(values) if spec.contact_offset else FLAT_TOE
    c = float(values.get("compliance_mm_per_n", 0.0)) if spec.compliance else 0.0
    delta = contact_compression(d - log_.contact_mm - off - c * f, c_toe, exponent=p_toe, spread=s_toe)
    return np.clip(1.0 - delta / log_.height_mm, 0.05, 1.0)


def _scaled_fit(w: np.ndarray, shape: np.ndarray) -> tuple[float, float]:
    """Least-squares scale ``s`` of ``w ~ s * shape`` and the residual sum of squares."""
    s = float(np.dot(w, shape) / np.dot(shape, shape))
    r = w - s * shape
    return s, float(np.dot(r, r))


def width_evidence(width: WidthSeries, logs: Sequence[LogData]):
    r"""Evidence for bonded platens from the specimen's mid-height width.

    Homogeneous incompressible compression keeps the cylinder straight:
    :math:`w = s D \lambda^{-1/2}`.  Bonded ends make it barrel: :math:`w = s D\, b(\lambda;
    \alpha, H/D)`, the FE mid-height bulge (:func:`bsipipe.mechanics.noslip.noslip_bulge_width`).
    The stretch comes from the log and each model's fit (contact offset, compliance); ``s``
    absorbs the camera's scale and the specimen's true diameter, one free parameter in both
    models, so :math:`\Delta\mathrm{BIC} = n \ln(\mathrm{RSS}_{hom} / \mathrm{RSS}_{no-slip})`.
    """
    from . import noslip

    def evidence(before, after) -> dict | None:
        i = width.log_index
        if i >= len(logs):
            return None
        lg = logs[i]
        vb = before.fit.log_params(i) if hasattr(before.fit, "log_params") else {}
        va = after.fit.log_params(i) if hasattr(after.fit, "log_params") else {}
        lam_h = _stretch_at(lg, vb, before.spec, width.time_s)
        lam_b = _stretch_at(lg, va, after.spec, width.time_s)
        # The FE tables cover stretches down to their grid's smallest; samples beyond are left out.
        keep = (lam_h >= noslip.STRETCH_GRID.min()) & (lam_b >= noslip.STRETCH_GRID.min())
        if keep.sum() < 3:
            return None
        w, d = width.width_mm[keep], lg.diameter_mm
        hom = d * lam_h[keep] ** -0.5
        bulge = np.asarray(noslip.noslip_bulge_width(lam_b[keep], float(va["alpha"]), d, lg.aspect), dtype=float)
        s_h, rss_h = _scaled_fit(w, hom)
        s_b, rss_b = _scaled_fit(w, bulge)
        n = len(w)
        tiny = np.finfo(float).tiny
        return {"source": "width series (mid-height, side camera)", "n": n,
                "delta_bic": float(n * np.log(max(rss_h, tiny) / max(rss_b, tiny))),
                "rmse_width_homogeneous_mm": float(np.sqrt(rss_h / n)),
                "rmse_width_no_slip_mm": float(np.sqrt(rss_b / n)),
                "scale_homogeneous": s_h, "scale_no_slip": s_b,
                "n_left_out": int(len(keep) - n),
                "width_range_mm": [float(w.min()), float(w.max())]}

    return evidence


# --- the loop on machine logs ------------------------------------------------------------------

def _nested(a: ForceModelSpec, b: ForceModelSpec) -> bool:
    """Is ``b`` ``a`` with effects added (so ``a``'s fit is a fair start for ``b``)?"""
    la = _LAW_ORDER.index(a.law) if a.law in _LAW_ORDER else -1
    lb = _LAW_ORDER.index(b.law) if b.law in _LAW_ORDER else -1
    law_ok = a.law == b.law or (la >= 0 and lb >= la)
    return (law_ok and a.prony <= b.prony and a.boundary in (b.boundary, "frictionless")
            and a.contact_offset <= b.contact_offset and a.baseline_drift <= b.baseline_drift
            and a.compliance <= b.compliance and a.periodic_disturbance <= b.periodic_disturbance)


def _carry(values: Mapping, a: ForceModelSpec, b: ForceModelSpec) -> dict:
    """``a``'s fitted values renamed for ``b`` (one-term ``mu_pa`` becomes ``mu1_pa``...)."""
    v = dict(values)
    if a.law == "ogden" and b.law != "ogden" and "mu_pa" in v:
        v["mu1_pa"], v["alpha1"] = v.pop("mu_pa"), v.pop("alpha")
    return v


#: Held-out error with several logs: folds, and consecutive blocks per log dealt to them in turn.
HELDOUT_FOLDS = 3
HELDOUT_BLOCKS = 21


def heldout_folds(n: int, folds: int = HELDOUT_FOLDS, blocks: int = HELDOUT_BLOCKS) -> np.ndarray:
    """Fold of each of ``n`` samples: ``blocks`` consecutive blocks, block ``j`` in fold ``j mod folds``.

    >>> heldout_folds(12, folds=2, blocks=4).tolist()
    [0, 0, 0, 1, 1, 1, 0, 0, 0, 1, 1, 1]
    """
    return (np.arange(n) * blocks // max(n, 1)) % folds


class LogFitter:
    """Fits specs to a fixed set of logs, warm-starting each from its closest fitted ancestor."""

    def __init__(self, logs: Sequence[LogData], max_strain: float | None = None):
        self.logs = list(logs)
        self.max_strain = max_strain
        self.fits: dict[ForceModelSpec, object] = {}

    def _start(self, spec, fits, names):
        anc = [(r.bic, s) for s, r in fits.items() if s != spec and _nested(s, spec) and r.success]
        if not anc:
            return None
        _, s = min(anc, key=lambda t: t[0])
        v = _carry(fits[s].values, s, spec)
        return {k: x for k, x in v.items() if k in names}

    def fit(self, spec: ForceModelSpec):
        if spec not in self.fits:
            start = self._start(spec, self.fits, set(parameter_names(spec, self.logs)))
            self.fits[spec] = fit_logs(self.logs, spec, max_strain=self.max_strain, start=start)
        return self.fits[spec]

    def heldout_rmse(self, spec: ForceModelSpec) -> dict | None:
        r"""Held-out RMSE (N) over interleaved blocks of every log (several logs only).

        Each log's samples are cut into :data:`HELDOUT_BLOCKS` consecutive blocks, block
        ``j`` going to fold ``j mod HELDOUT_FOLDS``; for each fold the model is fitted to
        every log without that fold's blocks (warm-started from the full fit) and predicts
        them.  Every log keeps its own parameters in every fold, so a shared effect (Prony
        terms that need both speeds, compliance, the platen boundary) is judged on samples
        it was not fitted to, and a per-log effect cannot adapt to the samples it is judged
        on.  Each log's mean square counts equally.

        Leaving a whole log out instead would ask one log to identify what only the logs
        together can (a 1 mm/s ramp cannot see a 50 s relaxation time, a 0.01 mm/s one a
        0.5 s one): on the two-speed twin the true two-term Prony model predicts a left-out
        log 4x worse than the one-term one.
        """
        n = len(self.logs)
        if n < 2:
            return None
        full = self.fit(spec)
        folds = [heldout_folds(len(lg.time_s)) for lg in self.logs]
        used = [self._used(lg) for lg in self.logs]
        sq: list[list[np.ndarray]] = [[] for _ in range(n)]
        for k in range(HELDOUT_FOLDS):
            res = fit_logs(self.logs, spec, max_strain=self.max_strain, start=full.values,
                           sample_mask=[f != k for f in folds])
            for i, lg in enumerate(self.logs):
                m = (folds[i] == k) & used[i]
                sq[i].append((predict_force(lg, spec, res.log_params(i)) - lg.force_n)[m] ** 2)
        per_log = [float(np.mean(np.concatenate(x))) for x in sq]
        return {"rmse": float(np.sqrt(np.mean(per_log))), "per_log_rmse": [float(np.sqrt(x)) for x in per_log],
                "method": f"{HELDOUT_FOLDS} folds of interleaved blocks, {HELDOUT_BLOCKS} blocks per log"}

    def _used(self, lg: LogData) -> np.ndarray:
        m = np.ones(len(lg.time_s), dtype=bool)
        if self.max_strain is not None:
            m &= lg.nominal_strain() <= self.max_strain
        return m


def _crosshead_rate(lg: LogData) -> np.ndarray:
    """Crosshead speed (mm/s) at each sample; 0 where the time stamps do not separate samples."""
    if len(lg.time_s) < 2:
        return np.zeros(len(lg.time_s))
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.gradient(lg.displacement_mm, lg.time_s)
    return np.where(np.isfinite(v), v, 0.0)


def _phase(lg: LogData) -> np.ndarray:
    """Load phase of each sample from the crosshead motion: 'load', 'hold' or 'unload'."""
    v = _crosshead_rate(lg)
    vmax = max(float(np.max(np.abs(v), initial=0.0)), 1e-12)
    return np.where(v > 0.05 * vmax, "load", np.where(v < -0.05 * vmax, "unload", "hold"))


def log_covariates(logs: Sequence[LogData], used: Sequence[np.ndarray]) -> dict:
    """Residual covariates of fitted samples: time, nominal strain, crosshead rate, phase, force."""
    out: dict[str, list] = {"time_s": [], "nominal_strain": [], "rate_mm_s": [], "phase": [], "force_n": []}
    for lg, m in zip(logs, used):
        rate = _crosshead_rate(lg)
        out["time_s"].append(lg.time_s[m])
        out["nominal_strain"].append(lg.nominal_strain()[m])
        out["rate_mm_s"].append(np.round(rate[m], 6))
        out["phase"].append(_phase(lg)[m])
        out["force_n"].append(lg.force_n[m])
    return {k: np.concatenate(v) for k, v in out.items()}


def force_noise_rms(logs: Sequence[LogData]) -> float | None:
    r"""Load-cell noise (N) of the logs, independent of any model: robust second differences.

    For white noise :math:`\sigma`, :math:`F_{k+1} - 2F_k + F_{k-1}` has standard deviation
    :math:`\sqrt 6\,\sigma` while a force curve sampled finely contributes little, so
    :math:`\hat\sigma = 1.4826\,\mathrm{MAD}(\Delta^2 F) / \sqrt 6` per log, pooled over logs.
    A load signal filtered by the machine (correlated noise) gives a low estimate: the loop
    then simply does not stop early on it.

    >>> rng = np.random.default_rng(0)
    >>> t = np.linspace(0, 10, 4000)
    >>> lg = LogData("a", t, t, 0.1 * t**2 + rng.normal(0, 1e-3, t.size), 18.0, 12.0, 0.0)
    >>> round(force_noise_rms([lg]) * 1e3, 1)
    1.0
    """
    var, n = 0.0, 0
    for lg in logs:
        if len(lg.force_n) < 5:
            continue
        s = force_noise(lg.force_n)
        var += s * s * (len(lg.force_n) - 2)
        n += len(lg.force_n) - 2
    return float(np.sqrt(var / n)) if n else None


#: An effect's parameters that may not end on these edges of their ranges (name prefix ->
#: edges): a toe as long as a tenth of the specimen, a relaxation of g = 0.98, a compliance
#: whose deflection is half the specimen, a relaxation time at the record's bounds, a
#: disturbance slower than 1.5 cycles over the log (a trend) or at its Nyquist frequency -- the
#: mechanism asked for more than it can be, so it is standing in for something else.
_EDGES_REFUSED = {r"contact_toe_mm": ("upper",), r"g\d+": ("upper",), r"compliance_mm_per_n": ("upper",),
                  r"tau\d+_s": ("lower", "upper"), r"disturbance_hz": ("lower", "upper")}


def _refused_edge(name: str, edge: str) -> bool:
    """Whether parameter ``name`` (per-log names carry ``[i]``) may not end on ``edge``."""
    base = name.split("[")[0]
    return any(edge in edges and re.fullmatch(pattern, base) for pattern, edges in _EDGES_REFUSED.items())


def effect_veto(before, after) -> str | None:
    """fit-ogden's veto (:func:`~bsipipe.loop.run_loop` ``veto``): a parameter the candidate adds
    that ended on a refused edge of its range (:data:`_EDGES_REFUSED`): an elastic two-term
    truth (mu 500 / 220 Pa, alpha -8 / +2, the probe's log) had been given a relaxation of
    g = 0.98 at tau 66 s, mu 776 Pa.  (The sign of an Ogden exponent is no such test: a toe
    fitted as a flat top bends the curve to alpha +11.8, and contact-offset rightly turns it
    to -4.69; a two-term truth's sign turned by a toe is a tie the data cannot break, which
    :func:`~bsipipe.loop.run._preference` gives to the fewer parameters.)"""
    new = set(getattr(after.fit, "values", {}) or {}) - set(getattr(before.fit, "values", {}) or {})
    edges = getattr(after.fit, "at_bound", {}) or {}
    hit = sorted(k for k in new if k in edges and _refused_edge(k, edges[k]))
    if hit:
        va = after.fit.values
        return ("its " + ", ".join(f"{k} = {va[k]:.3g} ({edges[k]} end of its range)" for k in hit)
                + ": the mechanism asked for more than it can be, standing in for something it does not describe")
    return None


def tared_contact_veto(logs: Sequence[LogData], after) -> str | None:
    """A candidate that moves the contact of a record zeroed in contact (``tared_at_start``:
    the specimen already compressed at its first sample, where the load cell was zeroed)
    past that first sample: the record's own premise undone, the zero then standing at a
    loaded sample the model calls unloaded.  On a record pressed 0.22 mm and zeroed, the
    loop had freed the given contact by 0.263 mm, mu 822 Pa [819, 826] for a true 720, with
    only a parameter-correlation warning."""
    vals = getattr(after.fit, "values", {}) or {}
    for i, lg in enumerate(logs):
        if not getattr(lg, "tared_at_start", False):
            continue
        off = vals.get(f"contact_offset_mm[{i}]" if len(logs) > 1 else "contact_offset_mm")
        if off is None:
            continue
        contact = float(lg.contact_mm) + float(off)
        first = float(lg.displacement_mm[0])
        if contact > first + 1e-9:
            return (f"it moves the contact of log {i} to {contact:.3g} mm, past its first sample ({first:.3g} mm), where "
                    "the load cell was zeroed with the specimen already compressed")
    return None


#: Family-wise level of the line test of ``periodic-disturbance`` (:func:`disturbance_veto`).
DISTURBANCE_LINE_P = 1e-3


def disturbance_veto(logs: Sequence[LogData], before, after) -> str | None:
    r"""``periodic-disturbance`` must be a line in the spectrum: each log's fitted sinusoid must
    stand above the residual's periodogram around it by more than a chance peak of a smooth
    spectrum does over the frequencies searched, family-wise p below :data:`DISTURBANCE_LINE_P`
    (:func:`~bsipipe.mechanics.fit.disturbance_line_test`: 17-20 times the mean of its
    neighbours on a 4 s log at 50 Hz).  The fit's delta BIC counts the frequency as one
    parameter, but it was searched over hundreds of independent frequencies, and a serially
    correlated residual has a peak somewhere: on AR(1) noise of rho 0.9 (``tests/test_fit_serial.py``)
    one log of 8 had had a 0.032 Hz sinusoid of 0.77 mN kept (1.95 cycles, delta BIC 11.5 on
    the effective samples), and on the real Bluehill 2 record (a 4-53 N specimen, its residual
    of ogden+prony1 with compliance 0.17 N, red) a 0.045 Hz sinusoid of 0.17 N (2.7 cycles,
    12.9); 2 mN of hum on 1 mN of noise stands 140-850 times above its neighbours.  With several
    logs fitted together one line is enough (each log's p times the number of logs, family-wise
    over them too): the others' sinusoids then fit their noise, a fraction of a millinewton.  A
    hum of 2 mN on one of two logs had been turned down because the clean log's sinusoid (0.26
    mN at 14.95 Hz, 7.1 times its neighbours) was no line, and the loop kept nothing."""
    if not getattr(after.spec, "periodic_disturbance", False) or getattr(before.spec, "periodic_disturbance", False):
        return None
    tests = disturbance_lines(logs, after.fit)
    if any(t["line"] for t in tests):
        return None
    t = min(tests, key=lambda t: t["p_log"])
    which = f"log {t['index']}" if len(logs) > 1 else "the log"
    return (f"the sinusoid of {which} ({t['amplitude_n']:.3g} N at {t['hz']:.4g} Hz"
            + (", the strongest line of the logs" if len(logs) > 1 else "") + f") stands "
            f"{t['line_ratio']:.1f} times above the mean of the {t['n_neighbours']} periodogram ordinates "
            f"around it: as a chance peak of a smooth spectrum over the {t['n_frequencies']:.0f} frequencies "
            f"searched" + (f" and {len(logs)} logs" if len(logs) > 1 else "")
            + f", p = {t['p']:.2g} (not below {DISTURBANCE_LINE_P:g}): a broad misfit or red noise, not a periodic "
              "disturbance")


def disturbance_lines(logs: Sequence[LogData], fit) -> list[dict]:
    """Each log's fitted ``periodic-disturbance`` sinusoid and its line test
    (:func:`~bsipipe.mechanics.fit.disturbance_line_test`) in a fit of ``logs``: ``index``,
    ``log``, ``amplitude_n``, ``hz``, ``phase_rad``, ``line_ratio``, ``n_neighbours``,
    ``n_frequencies``, ``p_log`` (the log's own), ``p`` (family-wise: times the number of logs)
    and ``line`` (``p`` below :data:`DISTURBANCE_LINE_P`): what :func:`disturbance_veto` decides
    on and fit.json reports."""
    out = []
    for i, lg in enumerate(logs):
        v = fit.log_params(i)
        t = disturbance_line_test(lg.time_s[fit.used[i]], fit.residuals[i], v["disturbance_n"], v["disturbance_hz"])
        p = min(1.0, t["p"] * len(logs))
        out.append({"index": i, "log": lg.name, "amplitude_n": float(v["disturbance_n"]),
                    "hz": float(v["disturbance_hz"]), "phase_rad": float(v["disturbance_phase_rad"]),
                    "line_ratio": float(t["ratio"]), "n_neighbours": int(t["n_neighbours"]),
                    "n_frequencies": float(t["n_frequencies"]), "p_log": float(t["p"]), "p": float(p),
                    "line": bool(p < DISTURBANCE_LINE_P)})
    return out


def close_loop_logs(logs: Sequence[LogData], spec0: ForceModelSpec, *, boundary_declared: bool = True,
                    width: WidthSeries | None = None, max_strain: float | None = None,
                    rule: SelectionRule = SelectionRule(), candidates: Sequence[Effect] | None = None,
                    fitter: LogFitter | None = None) -> LoopReport:
    """fit-ogden's loop on machine logs (see :mod:`bsipipe.loop.run` for the rule).

    Parameters
    ----------
    logs : sequence of LogData
    spec0 : ForceModelSpec
        The model the command line declares.
    boundary_declared : bool
        Whether ``--boundary`` was given; if not, ``no-slip-platens`` is a candidate.
    width : WidthSeries, optional
        Side-camera width series, evidence for the boundary.
    max_strain : float, optional
        As :func:`~bsipipe.mechanics.fit.fit_logs`.
    candidates : sequence of Effect, optional
        Defaults to :func:`mechanics_effects`.

    Returns
    -------
    LoopReport with errors in N (``rmse_n``); ``report.final.fit`` is the final FitResult.
    """
    fitter = fitter or LogFitter(logs, max_strain)
    if candidates is None:
        candidates = mechanics_effects(boundary_declared=boundary_declared, width=width, logs=logs)
    return run_loop(fitter.fit, spec0, candidates,
                    heldout=fitter.heldout_rmse if len(fitter.logs) > 1 else None,
                    covariates=lambda res: log_covariates(fitter.logs, res.used),
                    describe=lambda s: s.describe(), unit="n", rule=rule, noise_rms=force_noise_rms(fitter.logs),
                    veto=lambda before, after: (effect_veto(before, after) or tared_contact_veto(fitter.logs, after)
                                                or disturbance_veto(fitter.logs, before, after)))


# --- the loop on stress-stretch tables ---------------------------------------------------------

@dataclass(frozen=True)
class _TableSpec:
    law: str


MODEL_ORDER_TABLE = Effect(
    MODEL_ORDER.name, MODEL_ORDER.explanation, MODEL_ORDER.signature,
    lambda s: _TableSpec(_LAW_ORDER[_LAW_ORDER.index(s.law) + 1])
    if s.law in _LAW_ORDER[:-1] else None, MODEL_ORDER.param_names)


def table_covariates(res) -> dict:
    """Residual covariates of a stress-table fit: stretch and loading mode."""
    import pandas as pd

    fr = pd.concat(res.fitted, ignore_index=True)
    return {"stretch": fr["stretch"].to_numpy(float), "mode": fr["mode"].to_numpy(str)}


def close_loop_tables(tables, law: str, *, rule: SelectionRule = SelectionRule()) -> LoopReport:
    """The loop on stress-stretch tables: ``model-order`` (a table has no time, rate or load
    cell), errors in Pa (``rmse_pa``), residual covariates stretch and mode."""
    import pandas as pd

    table = pd.concat(list(tables), ignore_index=True) if not isinstance(tables, pd.DataFrame) else tables
    return run_loop(lambda s: fit_tables(table, s.law), _TableSpec(law), [MODEL_ORDER_TABLE],
                    covariates=table_covariates, describe=lambda s: s.law, unit="pa", rule=rule)
