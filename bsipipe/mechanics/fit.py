r"""Fitting hyperelastic and hyperviscoelastic laws to machine logs and stress-stretch tables.

Force model of a cylinder log
-----------------------------
Compression is positive.  For a log with crosshead displacement :math:`d(t)` (from the first
sample), detected contact :math:`d_c`, height :math:`H` and diameter :math:`D`:

.. math::

    x &= d - d_c - \Delta_c - C F_t                         &\text{(platen travel past contact, mm)} \\
    \delta &= \delta(x; c)                                  &\text{(tissue compression, mm)} \\
    \lambda &= 1 - \delta / H \\
    F_e &= -P(\lambda)\, \pi D^2 / 4                         &\text{(elastic force, N; mm}^2 \to \text{m}^2) \\
    F_t &= \mathrm{QLV}[F_e](t)                             &\text{(Prony terms, when any)} \\
    F &= F_t + b_0 + b_1 (t - t_0) + A \sin(2 \pi f (t - t_0) + \varphi)

:math:`P` is the law's homogeneous uniaxial nominal stress (Pa, negative in compression), or
the bonded-platen FE force per area of :mod:`bsipipe.mechanics.noslip` for
``boundary='no-slip'`` (one-term Ogden only).  :math:`\delta(x; c, p, s)` is
:func:`contact_compression`: an uneven top face met over :math:`2c` of travel, its contact
area growing as the power :math:`p` of the indentation, the touching part carrying between
its own compression (:math:`s = 0`) and the whole travel (:math:`s = 1`).  The effects of
:class:`ForceModelSpec` switch on the free contact shift and the toe (``contact_offset``:
:math:`\Delta_c` = ``contact_offset_mm``, :math:`c` = ``contact_toe_mm``, :math:`p` =
``contact_toe_exponent``, :math:`s` = ``contact_toe_spread``, per log), the load-cell baseline and drift :math:`b_0, b_1`
(``baseline_n``, ``drift_n_per_s``, per log) and the machine compliance :math:`C`
(``compliance_mm_per_n``, shared: one frame) and a periodic disturbance of the load reading
(``periodic_disturbance``: :math:`A` = ``disturbance_n``, :math:`f` = ``disturbance_hz``, the
frequency the log shows, aliased by its sampling where the source is faster,
:math:`\varphi` = ``disturbance_phase_rad`` at the first sample, per log; its frequency starts
from the periodogram of the residual, :func:`disturbance_frequencies`).  Compliance makes the
model implicit in :math:`F_t`; it is solved by Newton's method per sample (exact without Prony terms; with them
the instantaneous derivative, :math:`G(0) = 1`, preconditions a fixed-point iteration over
the whole history).

Contact
-------
A detected contact is an estimate: :func:`bsipipe.mechanics.contact.detect_contact` gives
its standard deviation :math:`s_c` (``LogData.contact_sd_mm``), about 7 um on the
sheep-brain log at 10 Hz, where 7 um moves mu by 0.7 %.  Holding the contact there would put
that error into mu without its interval knowing.  So every fit of a log with a detected
contact (``refine_contact``, the default) refines the shift :math:`\Delta_c` as a nuisance
parameter under the detector's Gaussian prior :math:`\Delta_c \sim N(0, s_c^2)`: one
pseudo-observation :math:`w_i \sigma_i \Delta_c / s_c` joins the residuals, with
:math:`\sigma_i` the load noise the detector measured (``LogData.force_noise_n``, N) and
:math:`w_i` the log's weight, so that against the data's residuals (noise :math:`w_i
\sigma_i`) it weighs as :math:`(\Delta_c / s_c)^2`.  The Jacobian intervals below then carry
the contact's uncertainty.  The force data pin the contact about three times better than the
detector (the Ogden shape is known, the detector's polynomial is not), so the refined contact
is mostly the data's and the prior only keeps it near the detector where the data do not
decide (it is a statistic of the same samples, so it is not independent information; its
weight is a tenth of the data's on the sheep-brain log, and the 95 % intervals cover the
truth in 46/50 seeded repeats, ``tests/test_fit.py``).

The prior's tails are heavier than Gaussian: the pseudo-observation is
:func:`contact_prior_residual`, :math:`\rho(z) = 2(\sqrt{1 + z^2} - 1)` of
:math:`z = \Delta_c / s_c` (a density :math:`\propto e^{-\rho/2}`), :math:`z^2` within about one
standard deviation, :math:`2|z|` beyond.  The detector's standard deviation cannot see a bias
its hinge polynomial shares over every window, as at a viscoelastic onset (the force first
rises with the instantaneous modulus and relaxes within :math:`v\tau` of contact: on the
sample study's 1 mm/min log the detector is 21 um, 4.3 sd, early).  A Gaussian prior would
then hold the contact partway between the detector and the data (mu 1 % low there); with
these tails the data win a conflict of several standard deviations, and the interval widens
as the prior's curvature falls, while a calibrated detector (:math:`|z| \lesssim 1`) keeps
the Gaussian prior's weight.  ``contact_offset`` (the loop's
``contact-offset`` effect) frees the shift and adds the toe: the true contact is not where the
detector and a flat top say.  A log whose contact is given exactly (no ``contact_sd_mm``) is
held there.

The data fitted are every sample from the first (the pre-contact part pins the baseline and
the contact) up to ``max_strain`` of nominal strain past the *detected* contact; the model is
always evaluated over the whole history (the hereditary integral needs it).

Objective and weights
---------------------
Residuals are model minus data.  Several logs are fitted jointly with one tissue parameter
set; log :math:`i` with :math:`n_i` fitted samples gets the weight
:math:`w_i = \sqrt{N / (L\, n_i)}` (:math:`L` logs, :math:`N = \sum n_i`) on its residuals,
so every log contributes equally to the objective whatever its sampling rate or duration,
and the weights average to one (a single log is unweighted).

Stress tables (:func:`fit_tables`) weight every loading mode equally (the same
:math:`\sqrt{N / (M n_m)}` over :math:`M` modes) and scale each residual by
:math:`\sqrt{|P|\, \overline{|P|}_m}`: a stress error whose variance grows in proportion to
the stress, between absolute residuals (which fit only the large-stretch end: Treloar's
stresses span two decades) and relative ones (which let the smallest stresses dominate).
The scaled residual :math:`z` enters through a soft-L1 loss,
:math:`\rho(z) = 2 f^2 (\sqrt{1 + z^2/f^2} - 1)`, :math:`f = 0.03` (about 3 % at the mode's
mean stress): quadratic for small misfits, absolute for large ones, so the fit is close to a
least-absolute-deviation one and is judged consistently by median errors.  It is solved as
least squares on :math:`\tilde r = \operatorname{sign}(z) \sqrt{\rho(z)}`, so the Jacobian
intervals below apply unchanged.  On Treloar's UT/ET/PS data a plain least-squares fit of
relative residuals leaves a 4.3 % median error in uniaxial tension, worse than Ogden's 1972
parameters (3.2 %); this objective beats them in every mode (``tests/test_fit.py``).

Starts, optimiser, uncertainty
------------------------------
A coarse global stage first: the force is linear in the moduli for fixed exponents (the
QLV operator is linear too), so for every exponent (combination) on a grid that spans both
signs, the moduli and baseline terms come from a bounded linear least-squares solve.  The
best grid points of each exponent sign pattern start ``scipy.optimize.least_squares``
(``trf``, bounds: moduli >= 0, each exponent keeps its start's sign with
:math:`0.05 \le |\alpha| \le 40` (no-slip: the FE tables' range, :math:`1 \le |\alpha| \le 12`),
:math:`0 \le g_i \le 0.98`, relaxation times fitted as :math:`\log_{10}\tau`); every start
runs 12 iterations, the best two run to convergence, the lowest cost wins.  Ogden terms are
reported in decreasing order of :math:`\mu_i`.  The 95 %
intervals come from the Jacobian at the optimum (central differences, the contact priors'
rows included), :math:`\mathrm{cov} = s^2 (J^T J)^{-1}`, :math:`s^2 = \mathrm{SSE}/(n - p)`
(the priors' rows and the shifts they hold leave :math:`n - p` of the data as it is);
where a log's residuals are serially correlated (lag-1 above :math:`2/\sqrt m`: a load
channel low-pass filtered, or sampled faster than its noise changes) the covariance is
Newey-West's instead (:func:`_serial_covariance`; the white form had made the intervals 4.5
times too narrow on AR(1) 0.9 noise); with several logs the weights balance the logs, they are not the noise (every sample has
the load cell's), so the covariance is the weighted estimator's sandwich,
:math:`s^2 (J^T J)^{-1} J^T W J (J^T J)^{-1}` (:math:`J` the weighted residual's Jacobian,
:math:`W` the rows' squared weights, :math:`s^2` from the unweighted residuals): a short log
weighted up does not make its noise smaller (on the sample study's 125-sample 100 mm/min
log, weight squared 7.5, the plain form made the contact's and mu's intervals 2.5 times too
narrow), and a prior row counts with its log's weight.  Half-width
:math:`t_{0.975, n-p} \sqrt{\mathrm{cov}_{jj}}` (relaxation times: in :math:`\log_{10}`, then
mapped back).  ``bootstrap=B`` checks them with a seeded residual bootstrap (residuals
resampled within each log, refitted from the optimum, 2.5/97.5 percentiles).

Metrics: ``rmse_n`` (``rmse_pa`` for tables, unweighted over the fitted samples), ``nrmse``
(rmse over the data's range), ``max_rel_err`` (max :math:`|F_{model} - F| / |F|` over samples
with :math:`|F|` above 10 % of the maximum), ``median_rel_err``, and AIC/BIC from the
weighted SSE (with the contact priors' terms, a penalised likelihood; :math:`n` the data's
samples): :math:`n \ln(\mathrm{SSE}/n) + 2p` and :math:`n \ln(\mathrm{SSE}/n) + p \ln n`.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy import optimize

from ..distributions import t_ppf
from .hyperelastic import MODES, Law, get_law, ogden_nominal_stress
from .viscoelastic import QLV, PronyTerms

log = logging.getLogger(__name__)

BOUNDARIES = ("frictionless", "no-slip")
#: Exponent grid of the global stage (both signs); multi-term laws use the coarser one.
_ALPHA_GRID_1 = np.array([0.25, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 9.0, 11.0, 14.0, 18.0, 24.0])
_ALPHA_GRID_N = np.array([0.5, 1.0, 2.0, 3.0, 4.5, 6.5, 9.0, 13.0, 20.0])
_ALPHA_ABS_BOUNDS = (0.05, 40.0)
_G_MAX = 0.98
#: f of the soft-L1 loss of stress-table fits (module docstring).
TABLE_LOSS_SCALE = 0.03
_MIN_STRETCH = 0.05          # the model clips the stretch here (a 95 % compression is no log's range)
_TOE_START_MM = 0.05         # start of the uneven-top half-width c (contact_offset)
#: The toe's parameters (:func:`contact_compression`'s c, p, s), per log under ``contact_offset``.
TOE_NAMES = ("contact_toe_mm", "contact_toe_exponent", "contact_toe_spread")
#: Bounds of the area exponent p: contact area from nearly all at once (0.25) to a narrow ridge (6).
TOE_EXPONENT_BOUNDS = (0.25, 6.0)
_TOE_START = {"contact_toe_mm": _TOE_START_MM, "contact_toe_exponent": 1.0, "contact_toe_spread": 0.5}


def toe_params(values: Mapping) -> tuple[float, float, float]:
    """``(c, p, s)`` of :func:`contact_compression` from plain names (a flat top where absent)."""
    return (float(values.get("contact_toe_mm", 0.0)), float(values.get("contact_toe_exponent", 1.0)),
            float(values.get("contact_toe_spread", 0.0)))


def contact_prior_residual(z) -> np.ndarray:
    r"""The contact prior's residual at ``z`` = shift / detector sd: soft-L1 with ``f = 1``.

    Its square :math:`2(\sqrt{1 + z^2} - 1)` is :math:`z^2` (a Gaussian prior) within about
    one standard deviation and :math:`2|z|` (Laplace tails) far out (module docstring,
    "Contact").

    >>> [round(float(r), 4) for r in contact_prior_residual(np.array([0.1, 4.0]))]
    [0.0999, 2.4992]
    """
    return soft_l1_residual(z, 1.0)


def soft_l1_residual(z, f: float) -> np.ndarray:
    r"""Residual whose square is the soft-L1 loss: :math:`\operatorname{sign}(z)\sqrt{2f^2(\sqrt{1+z^2/f^2}-1)}`.

    Least squares on it minimises :math:`\sum \rho(z)`; it is :math:`z` for :math:`|z| \ll f`
    and grows like :math:`\sqrt{2 f |z|}` for :math:`|z| \gg f`.

    >>> [round(float(r), 6) for r in soft_l1_residual(np.array([1e-4, -1.0]), 0.03)]
    [0.0001, -0.241303]
    """
    z = np.asarray(z, dtype=float)
    u = z / f
    # 2 f^2 (sqrt(1 + u^2) - 1) = 2 f^2 u^2 / (sqrt(1 + u^2) + 1), free of cancellation near 0.
    return z * np.sqrt(2.0 / (np.sqrt(1.0 + u * u) + 1.0))


# --- data and model descriptions -------------------------------------------------------

@dataclass(frozen=True, eq=False)
class LogData:
    """One machine log prepared for fitting (plain arrays, units in the names).

    ``displacement_mm`` and ``force_n`` are positive in compression, displacement from the
    first sample (:meth:`bsipipe.io.machine_log.MachineLog.compression`); ``contact_mm`` is
    the detected contact displacement; ``speed_mm_s`` the loading speed (reported only).

    ``contact_sd_mm`` and ``force_noise_n`` are the contact detector's standard deviation of
    ``contact_mm`` and the load noise it measured
    (:class:`bsipipe.mechanics.contact.Contact`'s ``displacement_sd_mm`` and
    ``force_noise_n``): with them the fit refines the contact within that uncertainty (the
    module docstring's contact prior).  Without them (``None``) the contact is taken as known
    exactly and held, unless the spec frees it (``contact_offset``).

    ``tared_at_start``: the load cell was zeroed at the first sample with the specimen already
    compressed (a contact before the record): the model's force at the first sample is taken
    out of every sample, as the cell took it out (no parameter: the law gives it).
    """

    name: str
    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_n: np.ndarray
    diameter_mm: float
    height_mm: float
    contact_mm: float
    speed_mm_s: float | None = None
    contact_sd_mm: float | None = None
    force_noise_n: float | None = None
    tared_at_start: bool = False

    def __post_init__(self):
        for k in ("time_s", "displacement_mm", "force_n"):
            object.__setattr__(self, k, np.asarray(getattr(self, k), dtype=float))
        n = len(self.time_s)
        if self.displacement_mm.shape != (n,) or self.force_n.shape != (n,):
            raise ValueError(f"log {self.name}: time, displacement and force must be 1-D of one length")
        if not (self.diameter_mm > 0 and self.height_mm > 0):
            raise ValueError(f"log {self.name}: diameter and height must be positive")
        if (self.contact_sd_mm is None) != (self.force_noise_n is None):
            raise ValueError(f"log {self.name}: give the contact's standard deviation and the load noise together")
        if self.contact_sd_mm is not None and not (np.isfinite(self.contact_sd_mm) and self.contact_sd_mm > 0
                                                   and np.isfinite(self.force_noise_n) and self.force_noise_n > 0):
            raise ValueError(f"log {self.name}: contact_sd_mm and force_noise_n must be positive and finite")

    @property
    def contact_prior(self) -> bool:
        """Whether the contact is a detector's estimate with a standard deviation."""
        return self.contact_sd_mm is not None

    @property
    def area_m2(self) -> float:
        return float(np.pi * self.diameter_mm**2 / 4.0 * 1e-6)

    @property
    def aspect(self) -> float:
        """height / diameter."""
        return float(self.height_mm / self.diameter_mm)

    def nominal_strain(self) -> np.ndarray:
        """Compression past the detected contact over the height (0 before contact)."""
        return np.maximum(self.displacement_mm - self.contact_mm, 0.0) / self.height_mm


@dataclass(frozen=True)
class ForceModelSpec:
    """The force model: a law, its Prony order, the platen boundary and the effects switched on.

    ``refine_contact`` (default) refines each detected contact within the detector's standard
    deviation (module docstring, "Contact"); ``False`` holds it at the detected point.
    ``contact_offset`` frees it and fits an uneven-top toe (the ``contact-offset`` effect).

    Frozen and hashable: the loop (``bsipipe.loop``) augments a spec with
    :func:`dataclasses.replace` and caches fits by spec.
    """

    law: str = "ogden"
    prony: int = 0
    boundary: str = "frictionless"
    contact_offset: bool = False
    baseline_drift: bool = False
    compliance: bool = False
    refine_contact: bool = True
    specimen_scatter: bool = False
    periodic_disturbance: bool = False

    def __post_init__(self):
        get_law(self.law)
        if not 0 <= int(self.prony) <= 3:
            raise ValueError(f"prony must be 0..3, got {self.prony}")
        if self.boundary not in BOUNDARIES:
            raise ValueError(f"unknown boundary {self.boundary!r}; expected one of {BOUNDARIES}")
        if self.boundary == "no-slip" and self.law != "ogden":
            raise ValueError("the no-slip platen model is a one-term Ogden law (model 'ogden')")

    def describe(self) -> str:
        """A short name for reports, e.g. ``ogden+prony2 (no-slip, contact-offset)``."""
        s = self.law + (f"+prony{self.prony}" if self.prony else "")
        extra = [self.boundary] if self.boundary != "frictionless" else []
        extra += [n for n, on in (("contact-offset", self.contact_offset), ("load-baseline-drift", self.baseline_drift),
                                  ("machine-compliance", self.compliance), ("specimen-scatter", self.specimen_scatter),
                                  ("periodic-disturbance", self.periodic_disturbance))
                  if on]
        return s + (f" ({', '.join(extra)})" if extra else "")


@dataclass
class FitResult:
    """What a fit returns (``bsipipe.commands.fit_ogden`` writes it as ``fit.json``).

    ``params`` is JSON-ready in the contract's shape: the law's parameters (``mu_pa``,
    ``alpha``; ``mu1_pa``, ``alpha1``, ...; ``c10_pa``, ``c01_pa``), ``"prony": [{"g", "tau_s"}]``
    when there are Prony terms, then the effects' parameters (per-log names carry ``[i]``
    when several logs are fitted).  ``ci95`` maps every fitted parameter's flat name
    (``g1``, ``tau1_s`` for Prony terms) to ``[lo, hi]``.
    """

    spec: ForceModelSpec
    params: dict
    ci95: dict
    metrics: dict
    residuals: list
    n_obs: int
    n_params: int
    aic: float
    bic: float
    cov: np.ndarray
    success: bool
    param_names: list = field(default_factory=list)
    values: dict = field(default_factory=dict)          # flat name -> value
    ci95_bootstrap: dict | None = None
    bootstrap: dict | None = None
    fitted: list = field(default_factory=list)           # one DataFrame per log / mode
    used: list = field(default_factory=list)             # boolean masks of the fitted samples per log
    message: str = ""
    n_starts: int = 0
    kind: str = "logs"                                   # "logs" | "tables"
    at_bound: dict = field(default_factory=dict)         # flat name -> "lower" | "upper": ended on its range's edge
    #: per log, the effective share of independent samples, (1 - rho) / (1 + rho) of its
    #: residual's lag-1 autocorrelation where that is significant, else 1
    #: (:meth:`serial_data_term`: the loop weighs an effect's evidence on them)
    serial_factors: list = field(default_factory=list)
    log_weights: list = field(default_factory=list)      # the logs' balancing weights

    def serial_data_term(self, before: "FitResult") -> tuple[float, float] | None:
        r"""The loop's data term of an effect's delta BIC on the effective samples, this fit
        the richer one: :math:`n \ln(1 + \sum_i f_i \Delta\mathrm{SSE}_i / \mathrm{SSE})`
        (:math:`f_i` each log's :attr:`serial_factors`, :math:`\Delta\mathrm{SSE}_i` the
        fall of its weighted sum of squares; with every :math:`f_i = 1` this is
        :math:`n \ln(\mathrm{SSE}_{before}/\mathrm{SSE}_{after})`), and the effective number
        of samples :math:`\sum_i f_i m_i`; None where every log is white.  Per log: one log of
        three with correlated noise had had a pooled factor of 0.5-0.7 against its own 0.03,
        and a false drift kept in 3 of 10 seeds."""
        f = np.asarray(self.serial_factors, float)
        if self.kind != "logs" or not len(f) or np.all(f >= 1.0) or len(before.residuals) != len(self.residuals):
            return None
        w2 = np.asarray(self.log_weights, float) ** 2
        sse_a = np.array([w * float(np.dot(r, r)) for w, r in zip(w2, self.residuals)])
        sse_b = np.array([w * float(np.dot(r, r)) for w, r in zip(w2, before.residuals)])
        if sse_a.sum() <= 0:
            return None
        x = 1.0 + float(np.sum(f * (sse_b - sse_a))) / float(sse_a.sum())
        m = np.array([len(r) for r in self.residuals], float)
        return float(self.n_obs * np.log(max(x, 1e-300))), float(np.sum(f * m))

    @property
    def declared_params(self) -> list[str]:
        """The tissue's own parameters (the law's and the Prony terms'), the ones the loop's
        parameter-shift criterion weighs: an effect's nuisance parameters (a contact offset, a
        baseline) moving says nothing of the material (the toe probe: viscoelastic relaxation
        kept because it moved contact_offset_mm 3.5 half-widths, mu 1238 Pa for a true 720)."""
        return list(get_law(self.spec.law).param_names) + prony_names(self.spec.prony)

    def tissue_params(self) -> dict:
        """The law's parameters and the Prony list only (what an FE card needs)."""
        law = get_law(self.spec.law)
        out = {k: self.params[k] for k in law.param_names}
        if self.spec.prony:
            out["prony"] = self.params["prony"]
        return out

    def log_params(self, i: int) -> dict:
        """Flat parameters of log ``i`` with plain effect names (what :func:`predict_force` takes)."""
        out = {}
        for k, v in self.values.items():
            if k.endswith("]"):
                base, idx = k[:-1].split("[")
                if int(idx) == i:
                    out[base] = v
            else:
                out[k] = v
        if getattr(self.spec, "specimen_scatter", False) and SCATTER_NAME not in out:
            # the last log's factor (minus the others' logarithms: scatter_factors)
            n = sum(k.startswith(SCATTER_NAME + "[") for k in self.values) + 1
            if n > 1:
                out[SCATTER_NAME] = float(np.log(scatter_factors(self.values, n)[i]))
        return out


# --- parameters --------------------------------------------------------------------------

@dataclass(frozen=True)
class _Par:
    name: str
    lo: float
    hi: float
    scale: float
    log10: bool = False          # fitted as log10(value)


def _tared(lg) -> bool:
    """Whether a log was zeroed in contact (``tared_at_start``): its zero, one loaded sample's
    reading, is off the force there by that sample's noise, a constant in every sample that the
    fit takes as a parameter (``tare_n``).  Taken as exact, a zero 1.8 mN off had put mu at 706
    Pa [704, 708] for a true 720 with no warning, and the loop's stand-ins further off."""
    return lg is not None and bool(getattr(lg, "tared_at_start", False))


def prony_names(n: int) -> list[str]:
    return [x for i in range(1, n + 1) for x in (f"g{i}", f"tau{i}_s")]


def _shifted(spec: ForceModelSpec, log_: "LogData | None") -> bool:
    """Is the contact of ``log_`` a fitted parameter under ``spec`` (free, or within its prior)?"""
    return spec.contact_offset or (spec.refine_contact and log_ is not None and log_.contact_prior)


def _has_prior(spec: ForceModelSpec, log_: "LogData | None") -> bool:
    """Is the contact shift of ``log_`` held by the detector's Gaussian prior?"""
    return not spec.contact_offset and spec.refine_contact and log_ is not None and log_.contact_prior


def parameter_names(spec: ForceModelSpec, logs: "int | Sequence[LogData]" = 1) -> list[str]:
    """Flat names of every fitted parameter of ``spec`` over ``logs``, in fit order.

    ``logs`` is the logs themselves or their number; a number stands for logs whose contact
    is known exactly (no detector uncertainty, so no contact shift unless ``contact_offset``).

    >>> parameter_names(ForceModelSpec(prony=1, contact_offset=True), 2)[2:]
    ['g1', 'tau1_s', 'contact_offset_mm[0]', 'contact_offset_mm[1]', 'contact_toe_mm[0]', 'contact_toe_mm[1]', 'contact_toe_exponent[0]', 'contact_toe_exponent[1]', 'contact_toe_spread[0]', 'contact_toe_spread[1]']
    """
    seq = [None] * logs if isinstance(logs, (int, np.integer)) else list(logs)
    n_logs = len(seq)
    names = list(get_law(spec.law).param_names) + prony_names(spec.prony)
    sfx = log_suffix(n_logs)
    names += [f"contact_offset_mm{sfx(i)}" for i, lg in enumerate(seq) if _shifted(spec, lg)]
    names += [f"tare_n{sfx(i)}" for i, lg in enumerate(seq) if _tared(lg)]
    if spec.contact_offset:
        names += [f"{k}{sfx(i)}" for k in TOE_NAMES for i in range(n_logs)]
    if spec.baseline_drift:
        names += [x for i in range(n_logs) for x in (f"baseline_n{sfx(i)}", f"drift_n_per_s{sfx(i)}")]
    if spec.compliance:
        names.append("compliance_mm_per_n")
    if spec.specimen_scatter and n_logs > 1:
        names += [f"{SCATTER_NAME}[{i}]" for i in range(n_logs - 1)]
    if spec.periodic_disturbance:
        names += [f"{k}{sfx(i)}" for i in range(n_logs) for k in DISTURBANCE_NAMES]
    return names


def log_suffix(n_logs: int):
    """The suffix of log ``i``'s own parameters in a fit of ``n_logs`` logs, as a function of
    ``i``: ``[i]`` with several logs, nothing with one.

    >>> log_suffix(2)(1), log_suffix(1)(0)
    ('[1]', '')
    """
    return (lambda i: f"[{i}]") if n_logs > 1 else (lambda i: "")


#: ``periodic-disturbance``'s parameters per log: amplitude (N), frequency as the log shows it
#: (Hz, aliased by the sampling where the source is faster) and phase at the first sample (rad).
DISTURBANCE_NAMES = ("disturbance_n", "disturbance_hz", "disturbance_phase_rad")
#: The fewest cycles a periodic disturbance completes over a log's fitted samples: slower, a
#: sinusoid is a trend (a drift, a relaxation, a stiffer law) and not told from one.
DISTURBANCE_MIN_CYCLES = 1.5
#: Frequencies of the residual's periodogram each fit of a periodic disturbance starts from.
DISTURBANCE_PEAKS = 3


def disturbance_band(time_s: np.ndarray) -> tuple[float, float]:
    """The frequencies (Hz) a periodic disturbance of samples at ``time_s`` may have: at least
    :data:`DISTURBANCE_MIN_CYCLES` over their span, at most the Nyquist frequency of their median
    spacing (a faster source shows at its alias below it).

    >>> [round(f, 4) for f in disturbance_band(np.arange(0.0, 10.0, 0.02))]
    [0.1503, 25.0]
    """
    t = np.asarray(time_s, dtype=float)
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    dt = np.diff(t)
    dt = dt[dt > 0]
    if span <= 0 or not len(dt):
        return 1.0, 2.0
    lo, hi = DISTURBANCE_MIN_CYCLES / span, 0.5 / float(np.median(dt))
    return float(lo), float(max(hi, 1.01 * lo))


def disturbance_frequencies(time_s, residual, band: tuple[float, float] | None = None,
                            n_peaks: int = DISTURBANCE_PEAKS, oversample: int = 8) -> list[float]:
    r"""The frequencies (Hz) of the largest narrow peaks of a residual's periodogram, largest first.

    The residual (its least-squares line taken out, so a trend does not leak into the band) is
    interpolated onto a uniform grid of its median spacing and its power :math:`|\mathrm{FFT}|^2`
    computed on a grid ``oversample`` times finer than :math:`1/T` (zero padding); the highest
    local maximum inside ``band`` (default :func:`disturbance_band`) is taken, its sinusoid
    (least squares at that frequency) taken out, and the next peak sought in what is left, so the
    sidelobes of a strong peak are not returned as peaks of their own.  A sinusoid of
    frequency :math:`f` is found within a fraction of :math:`1/T`; the fit refines it.

    >>> t = np.arange(0.0, 8.0, 0.02)
    >>> r = 2e-3 * np.sin(2 * np.pi * 0.5 * t + 1.0) + 1e-4 * np.cos(2 * np.pi * 7.0 * t)
    >>> [round(f, 1) for f in disturbance_frequencies(t, r, n_peaks=2)]
    [0.5, 7.0]
    """
    t = np.asarray(time_s, dtype=float)
    if len(t) < 8:
        return []
    lo, hi = band if band is not None else disturbance_band(t)
    tu, eu, dt = _uniform(t, residual)
    n_fft = int(2 ** np.ceil(np.log2(oversample * len(tu))))
    freq = np.fft.rfftfreq(n_fft, dt)
    inside = (freq >= lo) & (freq <= hi)
    cols = [np.ones_like(tu), tu]
    out: list[float] = []
    for _ in range(n_peaks):
        a = np.column_stack(cols)
        left = eu - a @ np.linalg.lstsq(a, eu, rcond=None)[0]
        power = np.abs(np.fft.rfft(left, n_fft)) ** 2
        k = np.flatnonzero((power[1:-1] >= power[:-2]) & (power[1:-1] > power[2:])) + 1
        k = k[inside[k]]
        if not len(k):
            break
        f = float(freq[k[np.argmax(power[k])]])
        out.append(f)
        cols += [np.sin(2 * np.pi * f * tu), np.cos(2 * np.pi * f * tu)]
    return out


def _uniform(time_s, values) -> tuple[np.ndarray, np.ndarray, float]:
    """``values`` at ``time_s`` interpolated onto a uniform grid of their median spacing from
    the first sample (times from 0), and that spacing."""
    t = np.asarray(time_s, dtype=float)
    dt = np.diff(t)
    dt = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    tu = np.arange(t[0], t[-1] + 0.5 * dt, dt) - t[0]
    return tu, np.interp(tu, t - t[0], np.asarray(values, dtype=float)), dt


#: Ordinates of the periodogram on either side of a disturbance's frequency (spaced 1/T) over
#: which :func:`disturbance_line_test` measures the continuum.
DISTURBANCE_CONTINUUM_BINS = 10


def disturbance_line_test(time_s, residual, amplitude_n: float, hz: float,
                          band: tuple[float, float] | None = None, bins: int = DISTURBANCE_CONTINUUM_BINS) -> dict:
    r"""Is a fitted sinusoid a line in the spectrum, or a piece of a broad misfit or of red noise?

    The sinusoid's power in the periodogram, :math:`n A^2 / 4`, over the mean of the :math:`k`
    ordinates of the residual left beside it (``residual``: the fit's with the sinusoid, its line
    taken out) at the independent frequencies :math:`f_j = j/T` within ``bins`` of :math:`f` but
    outside its main lobe (:math:`1.5 \le |f_j - f|\,T \le` ``bins``).  Where the spectrum is
    smooth over that window (any colour: white noise, red noise, a slow misfit) each ordinate
    is its level times an exponential variable, so the ratio :math:`R` of a chance peak is
    :math:`F(2, 2k)`, :math:`P(R > x) = (1 + x/k)^{-k}`; searched over the :math:`M` independent
    frequencies of ``band`` (default :func:`disturbance_band`; :math:`M` its width times
    :math:`T`), its family-wise p-value is :math:`\min(1, M (1 + R/k)^{-k})` (Fisher's test of a
    periodogram peak against a local continuum).  On white noise a sinusoid that passes delta
    BIC 10 stands about 13-17 times above it; one cut from a red residual stands little above
    its neighbours.  Returns ``ratio``, ``n_neighbours``, ``n_frequencies`` and ``p`` (1 with
    fewer than 4 neighbours: nothing to compare).

    >>> rng = np.random.default_rng(0)
    >>> t = np.arange(0.0, 60.0, 0.1)
    >>> noise = rng.normal(0.0, 1e-3, t.size)        # 1 mN against 1 mN of noise: n / 4 = 150
    >>> test = disturbance_line_test(t, noise, 1e-3, 0.5)
    >>> 75 < test["ratio"] < 300, test["n_neighbours"], test["p"] < 1e-9
    (True, 17, True)
    """
    tu, eu, dt = _uniform(time_s, residual)
    n = len(tu)
    span = n * dt
    lo, hi = band if band is not None else disturbance_band(np.asarray(time_s, dtype=float))
    m_freq = max((hi - lo) * span, 1.0)
    out = {"ratio": float("nan"), "n_neighbours": 0, "n_frequencies": float(m_freq), "p": 1.0}
    if n < 8:
        return out
    a = np.column_stack([np.ones_like(tu), tu])
    eu = eu - a @ np.linalg.lstsq(a, eu, rcond=None)[0]
    power = np.abs(np.fft.rfft(eu)) ** 2 / n
    freq = np.fft.rfftfreq(n, dt)
    gap = np.abs(freq - hz) * span
    near = (gap >= 1.5) & (gap <= bins) & (freq > 0) & (freq < 0.5 / dt)
    k = int(near.sum())
    out["n_neighbours"] = k
    if k < 4:
        return out
    ratio = n * amplitude_n ** 2 / 4.0 / max(float(np.mean(power[near])), np.finfo(float).tiny)
    out.update(ratio=float(ratio), p=float(min(1.0, m_freq * (1.0 + ratio / k) ** (-k))))
    return out


def _sinusoid_of(t, y, hz: float) -> tuple[float, float]:
    r"""Amplitude and phase of the least-squares :math:`A \sin(2 \pi f t + \varphi)` (with a constant) in ``y(t)``.

    >>> t = np.linspace(0.0, 4.0, 201)
    >>> [round(x, 3) for x in _sinusoid_of(t, 0.5 + 2.0 * np.sin(2 * np.pi * 0.7 * t - 1.0), 0.7)]
    [2.0, -1.0]
    """
    arg = 2.0 * np.pi * hz * np.asarray(t, dtype=float)
    a = np.column_stack([np.sin(arg), np.cos(arg), np.ones_like(arg)])
    c = np.linalg.lstsq(a, np.asarray(y, dtype=float), rcond=None)[0]
    return float(np.hypot(c[0], c[1])), float(np.arctan2(c[1], c[0]))


#: ``specimen-scatter``: log ``i``'s moduli are the law's times ``exp(z_i)``; ``z_i`` is fitted
#: for every log but the last, whose ``z`` is minus their sum (the law's moduli are the
#: geometric-mean specimen's).
SCATTER_NAME = "stiffness_log_factor"


def scatter_factors(values: Mapping, n_logs: int) -> np.ndarray:
    """Each log's stiffness factor ``exp(z_i)`` (ones without ``specimen-scatter``)."""
    z = [float(values[f"{SCATTER_NAME}[{i}]"]) for i in range(n_logs - 1) if f"{SCATTER_NAME}[{i}]" in values]
    if len(z) != n_logs - 1 or n_logs < 2:
        return np.ones(n_logs)
    return np.exp(np.array(z + [-sum(z)]))


def _scaled_tissue(law: Law, tissue: np.ndarray, factor: float) -> np.ndarray:
    """The law's parameters with its moduli (names ending ``_pa``) times ``factor``."""
    if factor == 1.0:
        return tissue
    out = np.array(tissue, dtype=float)
    for j, k in enumerate(law.param_names):
        if k.endswith("_pa"):
            out[j] *= factor
    return out


def _flat_prony(params: Mapping) -> dict:
    """Accept Prony terms as ``"prony": [{"g", "tau_s"}]`` or flat ``g1``/``tau1_s``."""
    out = dict(params)
    if "prony" in out:
        for i, term in enumerate(out.pop("prony") or [], start=1):
            out[f"g{i}"], out[f"tau{i}_s"] = float(term["g"]), float(term["tau_s"])
    return out


def _contract_params(spec: ForceModelSpec, values: Mapping[str, float]) -> dict:
    law = get_law(spec.law)
    out = {k: float(values[k]) for k in law.param_names}
    if spec.prony:
        out["prony"] = [{"g": float(values[f"g{i}"]), "tau_s": float(values[f"tau{i}_s"])}
                        for i in range(1, spec.prony + 1)]
    for k, v in values.items():
        if k not in out and k not in prony_names(spec.prony):
            out[k] = float(v)
    return out


# --- the force model ---------------------------------------------------------------------

def noslip_limits() -> tuple[float, float, float]:
    """``(|alpha| min, |alpha| max, smallest stretch)`` the no-slip FE tables cover."""
    from . import noslip
    a = np.abs(np.asarray(noslip.ALPHA_GRID, dtype=float))
    return float(a.min()), float(a.max()), float(np.min(noslip.STRETCH_GRID))


def _stress_function(spec: ForceModelSpec, law: Law, tissue: np.ndarray, aspect: float):
    """``stretch -> nominal stress (Pa)`` of the specimen under the spec's boundary."""
    if spec.boundary == "no-slip":
        from .noslip import noslip_nominal_stress
        mu, alpha = float(tissue[0]), float(tissue[1])
        lam_min = noslip_limits()[2]
        # Fitted samples stay inside the table (checked in fit_logs); the clip only guards
        # trial points of the optimiser (a contact offset) and finite differences.
        return lambda lam: np.asarray(noslip_nominal_stress(np.maximum(lam, lam_min), mu, alpha, aspect), dtype=float)
    mus, alphas = law.ogden_terms(tissue)
    return lambda lam: ogden_nominal_stress(lam, mus, alphas, "uniaxial")


def contact_compression(x_mm, toe_mm: float = 0.0, with_derivative: bool = False, exponent: float = 1.0,
                        spread: float = 0.0):
    r"""Bulk compression (mm) of a specimen with an uneven top, at platen travel ``x`` past contact.

    The top face is met over a travel :math:`w = 2c` (``toe_mm`` is :math:`c`): at travel
    :math:`v` past the first touch the fraction of the face in contact is
    :math:`a(v) = (v / w)^p` (``exponent`` :math:`p`: 1 for a dome or a tilted face, whose
    contact area grows linearly with the indentation; 2 for a cone; large for a face flat but
    for a narrow ridge), and the force is that of a flat specimen compressed by

    .. math::

        \delta(v) = \gamma\, w\, (v / w)^{p + 1} \quad (0 \le v \le w), \qquad
        \delta(v) = v - (1 - \gamma)\, w \quad (v \ge w), \qquad
        \gamma = 1 - (1 - s) \frac{p}{p + 1},

    :math:`a(v)` times the compression the touching part carries.  ``spread`` :math:`s` says
    how much of the travel that is: :math:`s = 0`, each touching column carries only its own
    compression :math:`v - h` (a Winkler bed, :math:`\delta = \int_0^v a`, smooth at full
    contact); :math:`s = 1`, the touching part carries the whole travel :math:`v` (the
    tissue around it is drawn down with it, :math:`\delta = a v`; the force meets a flat
    top's touched at first contact).  The travel ``x`` is measured from the flat-equivalent
    contact, where the large-strain part extrapolates to zero: :math:`v = x + (1 - \gamma) w`.
    ``p = 1, s = 0`` is the quadratic toe :math:`(x + c)^2 / 4c` for :math:`|x| < c`;
    ``c = 0`` is a flat top, :math:`\max(x, 0)`.  With ``with_derivative`` also
    :math:`d\delta / dx`.

    >>> [round(float(v), 6) for v in contact_compression(np.array([-0.3, 0.0, 0.1, 0.3]), 0.2)]
    [0.0, 0.05, 0.1125, 0.3]
    >>> [round(float(v), 6) for v in contact_compression(np.array([0.0, 0.2, 0.4, 0.5]), 0.2, spread=1.0)]
    [0.0, 0.1, 0.4, 0.5]
    """
    x = np.asarray(x_mm, dtype=float)
    c = float(toe_mm)
    if c <= 0.0:
        delta, slope = np.maximum(x, 0.0), (x > 0).astype(float)
    else:
        w, p = 2.0 * c, float(exponent)
        gamma = 1.0 - (1.0 - float(spread)) * p / (p + 1.0)
        s = np.clip((x + (1.0 - gamma) * w) / w, 0.0, 1.0)        # v / w in the toe
        full = s >= 1.0
        delta = np.where(full, x, gamma * w * s ** (p + 1.0))
        slope = np.where(full, 1.0, gamma * (p + 1.0) * s ** p)
    return (delta, slope) if with_derivative else delta


#: A flat top: no toe (``(contact_toe_mm, contact_toe_exponent, contact_toe_spread)``).
FLAT_TOE = (0.0, 1.0, 0.0)


def _elastic_force(stress, x_mm, height_mm, area_m2, toe=FLAT_TOE, with_derivative=False):
    """Elastic force (N, + in compression) at platen travel ``x`` past contact, optionally dF/dx (N/mm).

    ``toe`` is ``(c, p, s)`` of :func:`contact_compression`."""
    c, p, s = toe
    delta, slope = contact_compression(x_mm, c, with_derivative=True, exponent=p, spread=s)
    lam = np.clip(1.0 - delta / height_mm, _MIN_STRETCH, 1.0)
    f = -stress(lam) * area_m2
    if not with_derivative:
        return f, None
    h = 1e-6
    dp = (stress(np.minimum(lam + h, 1.0 + h)) - stress(lam - h)) / (2 * h)   # dP/dlambda
    return f, dp * area_m2 / height_mm * slope


def _tissue_force(time_s, x_mm, height_mm, area_m2, stress, g, tau, compliance, toe=FLAT_TOE, max_iter=60,
                  terms: PronyTerms | None = None):
    """QLV[F_e(delta(x - C F))] solved for F (see the module docstring).

    With a machine compliance the force is the fixed point of a Jacobi iteration, always
    started from zero: the result is then a deterministic, smooth function of the
    parameters even where ``max_iter`` steps stop short of the tolerance, which the
    optimiser's finite differences need.  (Started from the force last solved, the
    iteration took half the steps per call, but the residual then depended on the calls
    before: on the real Bluehill 2 export the optimiser needed 4x the evaluations and found
    a worse minimum, BIC -10284 against -10445.)  ``terms``: the log's cache of Prony
    recursions (:class:`~bsipipe.mechanics.viscoelastic.PronyTerms`; the same numbers)."""
    qlv = QLV(time_s, g, tau, terms) if len(g) else None
    if compliance <= 0.0:
        fe, _ = _elastic_force(stress, x_mm, height_mm, area_m2, toe)
        return qlv(fe) if qlv is not None else fe
    f = np.zeros_like(x_mm)
    scale = None
    for _ in range(max_iter):
        fe, dfe = _elastic_force(stress, x_mm - compliance * f, height_mm, area_m2, toe, with_derivative=True)
        target = qlv(fe) if qlv is not None else fe
        r = f - target
        f = f - r / (1.0 + compliance * np.maximum(dfe, 0.0))
        scale = max(float(np.max(np.abs(f))), 1e-12) if scale is None else scale
        if float(np.max(np.abs(r))) <= 1e-11 * scale:
            break
    return f


def _log_force(log_: LogData, spec: ForceModelSpec, law: Law, tissue, g, tau, offset, compliance, b0, b1,
               toe=FLAT_TOE, tare: float = 0.0, disturbance=None, *, terms: PronyTerms | None = None):
    stress = _stress_function(spec, law, tissue, log_.aspect)
    x = log_.displacement_mm - log_.contact_mm - offset
    f = _tissue_force(log_.time_s, x, log_.height_mm, log_.area_m2, stress, g, tau, compliance, toe, terms=terms)
    if log_.tared_at_start:
        # the load cell was zeroed at the first sample, the specimen already compressed (a
        # contact before the record): what the cell reads is the force less the force there,
        # less that sample's noise (``tare``: the zero's error, the same in every sample)
        f = f - f[0] - tare
    if b0 or b1:
        f = f + b0 + b1 * (log_.time_s - log_.time_s[0])
    if disturbance is not None:
        # in the load reading, not the specimen: mains pick-up or a vibration the cell senses
        amp, hz, phase = disturbance
        f = f + amp * np.sin(2.0 * np.pi * hz * (log_.time_s - log_.time_s[0]) + phase)
    return f


def predict_force(log: LogData, spec: ForceModelSpec, params: Mapping) -> np.ndarray:
    """Model force (N, + in compression) at every sample of ``log``.

    ``params`` holds the law's parameters, the Prony terms (``"prony"`` list or flat
    ``g1``/``tau1_s``) and the effects' parameters under their plain names
    (``contact_offset_mm``, ``contact_toe_mm``, ``contact_toe_exponent``, ``contact_toe_spread``,
    ``baseline_n``, ``drift_n_per_s``,
    ``compliance_mm_per_n``, ``disturbance_n``, ``disturbance_hz``, ``disturbance_phase_rad``;
    :meth:`FitResult.log_params` gives them for one log of a joint fit).  Effects the spec does
    not switch on are ignored; the contact shift applies where the fit refines it
    (``contact_offset``, or a detected contact with ``refine_contact``).
    """
    p = _flat_prony(params)
    law = get_law(spec.law)
    tissue = np.array([p[k] for k in law.param_names], dtype=float)
    g = np.array([p[f"g{i}"] for i in range(1, spec.prony + 1)], dtype=float)
    tau = np.array([p[f"tau{i}_s"] for i in range(1, spec.prony + 1)], dtype=float)
    offset = float(p.get("contact_offset_mm", 0.0)) if _shifted(spec, log) else 0.0
    toe = toe_params(p) if spec.contact_offset else FLAT_TOE
    c = float(p.get("compliance_mm_per_n", 0.0)) if spec.compliance else 0.0
    b0 = float(p.get("baseline_n", 0.0)) if spec.baseline_drift else 0.0
    b1 = float(p.get("drift_n_per_s", 0.0)) if spec.baseline_drift else 0.0
    if spec.specimen_scatter:
        tissue = _scaled_tissue(law, tissue, float(np.exp(p.get(SCATTER_NAME, 0.0))))
    tare = float(p.get("tare_n", 0.0)) if _tared(log) else 0.0
    dist = tuple(float(p.get(k, 0.0)) for k in DISTURBANCE_NAMES) if spec.periodic_disturbance else None
    return _log_force(log, spec, law, tissue, g, tau, offset, c, b0, b1, toe, tare, dist)


# --- problems: a residual function over an internal parameter vector ---------------------

class _Problem:
    """Shared machinery: parameter layout, internal <-> natural values, residuals."""

    pars: list[_Par]
    kind: str
    unit: str
    alpha_abs_bounds: tuple[float, float] = _ALPHA_ABS_BOUNDS

    def to_values(self, theta) -> dict:
        return {p.name: (10.0 ** t if p.log10 else float(t)) for p, t in zip(self.pars, theta)}

    def to_theta(self, values: Mapping) -> np.ndarray:
        return np.array([np.log10(values[p.name]) if p.log10 else values[p.name] for p in self.pars], dtype=float)

    def bounds(self, theta0):
        lo = np.array([p.lo for p in self.pars], dtype=float)
        hi = np.array([p.hi for p in self.pars], dtype=float)
        # Each exponent keeps the sign it starts with (the force is singular at alpha = 0).
        for j, p in enumerate(self.pars):
            if p.name.startswith("alpha"):
                a_lo, a_hi = self.alpha_abs_bounds
                if theta0[j] > 0:
                    lo[j], hi[j] = a_lo, a_hi
                else:
                    lo[j], hi[j] = -a_hi, -a_lo
        return lo, hi

    def canonical(self, theta) -> np.ndarray:
        """The same model with its Ogden terms ordered by decreasing modulus (mu1 the largest) and
        each periodic disturbance's phase in [-pi, pi)."""
        names = self.law.param_names
        n = self.law.n_terms
        phases = [j for j, k in enumerate(getattr(self, "names", ())) if k.startswith("disturbance_phase_rad")]
        if phases:
            theta = np.array(theta, dtype=float)
            theta[phases] = np.mod(theta[phases] + np.pi, 2.0 * np.pi) - np.pi
        if self.law.name not in ("ogden2", "ogden3"):
            return theta
        idx = [self.names.index(k) for k in names]
        blocks = np.array(idx).reshape(n, 2)
        order = np.argsort(-theta[blocks[:, 0]], kind="stable")
        out = theta.copy()
        out[blocks.ravel()] = theta[blocks[order].ravel()]
        return out

    def residual(self, theta, data=None) -> np.ndarray:       # weighted, concatenated
        raise NotImplementedError

    def safe_residual(self, theta, data=None) -> np.ndarray:
        r = self.residual(theta, data)
        bad = ~np.isfinite(r)
        if bad.any():
            r = np.where(bad, 1e6 * (1.0 + np.nanmax(np.abs(np.where(bad, 0.0, r)), initial=1.0)), r)
        return r


class _LogProblem(_Problem):
    kind = "logs"
    unit = "n"

    def __init__(self, logs: Sequence[LogData], spec: ForceModelSpec, max_strain: float | None,
                 sample_mask: Sequence[np.ndarray] | None = None):
        self.logs = list(logs)
        self.spec = spec
        self.law = get_law(spec.law)
        self._prony_terms = [PronyTerms() for _ in self.logs]    # each log's Prony recursions, by tau
        self.used = []
        for i, lg in enumerate(self.logs):
            m = np.ones(len(lg.time_s), dtype=bool)
            if max_strain is not None:
                m &= lg.nominal_strain() <= max_strain
            if sample_mask is not None:
                m &= np.asarray(sample_mask[i], dtype=bool)
            self.used.append(m)
        if spec.boundary == "no-slip":
            a_lo, a_hi, lam_min = noslip_limits()
            self.alpha_abs_bounds = (a_lo, a_hi)
            for lg, m in zip(self.logs, self.used):
                worst = float(np.max(lg.nominal_strain()[m], initial=0.0))
                if worst > 1.0 - lam_min:
                    raise ValueError(f"log {lg.name} reaches {100 * worst:.1f} % strain; the no-slip FE model covers "
                                     f"up to {100 * (1 - lam_min):.0f} % (give max_strain)")
        counts = np.array([m.sum() for m in self.used], dtype=float)
        self.n_obs = int(counts.sum())
        self.weights = np.sqrt(self.n_obs / (len(self.logs) * np.maximum(counts, 1.0)))
        self.data = [lg.force_n[m] for lg, m in zip(self.logs, self.used)]
        self._build_pars()

    def _build_pars(self):
        spec, logs = self.spec, self.logs
        fmax = max(float(np.max(np.abs(d))) if len(d) else 0.0 for d in self.data) or 1.0
        # A modulus scale from the data: the homogeneous small-strain estimate E = 3 mu.
        mu_scale = 100.0
        for lg, d, m in zip(logs, self.data, self.used):
            strain = lg.nominal_strain()[m]
            k = strain > 0
            if k.sum() > 2 and np.max(strain[k]) > 0:
                s = float(np.max(d[k])) / lg.area_m2 / max(float(np.max(strain[k])), 1e-3) / 3.0
                mu_scale = max(mu_scale, abs(s) * 0.2)
        self.mu_scale = mu_scale
        pars: list[_Par] = []
        if spec.law == "mooney-rivlin":
            pars += [_Par("c10_pa", 0.0, np.inf, mu_scale / 2), _Par("c01_pa", 0.0, np.inf, mu_scale / 2)]
        else:
            for name in self.law.param_names:
                if name.startswith("mu"):
                    pars.append(_Par(name, 0.0, np.inf, mu_scale))
                else:
                    pars.append(_Par(name, -_ALPHA_ABS_BOUNDS[1], _ALPHA_ABS_BOUNDS[1], 1.0))
        dts = np.concatenate([np.diff(lg.time_s) for lg in logs])
        dts = dts[dts > 0]
        dt = float(np.median(dts)) if len(dts) else 1.0
        span = max(float(lg.time_s[-1] - lg.time_s[0]) for lg in logs)
        self.tau_bounds = (max(1e-3, 0.5 * dt), max(20.0 * span, 1.0))
        for i in range(1, spec.prony + 1):
            pars += [_Par(f"g{i}", 0.0, _G_MAX, 0.1),
                     _Par(f"tau{i}_s", np.log10(self.tau_bounds[0]), np.log10(self.tau_bounds[1]), 0.5, log10=True)]
        n = len(logs)
        sfx = log_suffix(n)
        # The contact shift: free under contact_offset, else held by the detector's prior.
        # Its pseudo-observation (module docstring) is w_i sigma_i r(shift / sd_i), so it
        # weighs against log i's data residuals (weight w_i, noise sigma_i N) as a prior of
        # scale sd_i mm.
        self.prior_rows = []                      # (parameter index, w_i sigma_i (N), sd_i (mm))
        self.prior_log = []                       # the log of each prior row
        for i, lg in enumerate(logs):
            if _shifted(spec, lg):
                if _has_prior(spec, lg):
                    self.prior_log.append(i)
                    self.prior_rows.append((len(pars), float(self.weights[i] * lg.force_noise_n),
                                            float(lg.contact_sd_mm)))
                lim = 0.2 * lg.height_mm
                scale = min(0.02, 2.0 * lg.contact_sd_mm) if _has_prior(spec, lg) else 0.02
                pars.append(_Par(f"contact_offset_mm{sfx(i)}", -lim, lim, scale))
        for i, lg in enumerate(logs):
            if _tared(lg):
                pars.append(_Par(f"tare_n{sfx(i)}", -np.inf, np.inf, max(1e-3 * fmax, 1e-6)))
        if spec.contact_offset:
            for i, lg in enumerate(logs):
                pars.append(_Par(f"contact_toe_mm{sfx(i)}", 0.0, 0.1 * lg.height_mm, 0.02))
            for i, lg in enumerate(logs):
                pars.append(_Par(f"contact_toe_exponent{sfx(i)}", *TOE_EXPONENT_BOUNDS, 0.3))
            for i, lg in enumerate(logs):
                pars.append(_Par(f"contact_toe_spread{sfx(i)}", 0.0, 1.0, 0.2))
        if spec.baseline_drift:
            for i, (lg, d) in enumerate(zip(logs, self.data)):
                span_i = max(float(lg.time_s[-1] - lg.time_s[0]), 1e-9)
                fs = max(1e-3 * fmax, 1e-6)
                pars += [_Par(f"baseline_n{sfx(i)}", -np.inf, np.inf, fs),
                         _Par(f"drift_n_per_s{sfx(i)}", -np.inf, np.inf, fs / span_i)]
        if spec.compliance:
            hmin = min(lg.height_mm for lg in logs)
            pars.append(_Par("compliance_mm_per_n", 0.0, 0.5 * hmin / fmax, 0.01 * hmin / fmax))
        if spec.specimen_scatter and n > 1:
            # specimens a factor of 5 stiffer or softer than the geometric mean at most
            pars += [_Par(f"{SCATTER_NAME}[{i}]", -np.log(5.0), np.log(5.0), 0.05) for i in range(n - 1)]
        self.disturbance_bands = [disturbance_band(lg.time_s[m]) for lg, m in zip(logs, self.used)]
        if spec.periodic_disturbance:
            fs = max(1e-3 * fmax, 1e-6)
            for i, (lo, hi) in enumerate(self.disturbance_bands):
                pars += [_Par(f"disturbance_n{sfx(i)}", 0.0, np.inf, fs),
                         _Par(f"disturbance_hz{sfx(i)}", lo, hi, 0.1 * lo / DISTURBANCE_MIN_CYCLES),
                         _Par(f"disturbance_phase_rad{sfx(i)}", -np.inf, np.inf, 0.3)]
        self.pars = pars
        self.names = [p.name for p in pars]
        if self.names != parameter_names(spec, logs):    # the layout and the public names must agree
            raise RuntimeError(f"parameter layout {self.names} differs from {parameter_names(spec, logs)}")

    def _split(self, values: Mapping, i: int):
        spec = self.spec
        sfx = log_suffix(len(self.logs))(i)
        tissue = np.array([values[k] for k in self.law.param_names])
        g = np.array([values[f"g{j}"] for j in range(1, spec.prony + 1)])
        tau = np.array([values[f"tau{j}_s"] for j in range(1, spec.prony + 1)])
        off = values[f"contact_offset_mm{sfx}"] if _shifted(spec, self.logs[i]) else 0.0
        toe = (values[f"contact_toe_mm{sfx}"], values[f"contact_toe_exponent{sfx}"],
               values[f"contact_toe_spread{sfx}"]) if spec.contact_offset else FLAT_TOE
        b0 = values[f"baseline_n{sfx}"] if spec.baseline_drift else 0.0
        b1 = values[f"drift_n_per_s{sfx}"] if spec.baseline_drift else 0.0
        c = values["compliance_mm_per_n"] if spec.compliance else 0.0
        if spec.specimen_scatter and len(self.logs) > 1:
            tissue = _scaled_tissue(self.law, tissue, float(scatter_factors(values, len(self.logs))[i]))
        tare = values[f"tare_n{sfx}"] if _tared(self.logs[i]) else 0.0
        dist = tuple(values[k + sfx] for k in DISTURBANCE_NAMES) if spec.periodic_disturbance else None
        return tissue, g, tau, off, c, b0, b1, toe, tare, dist

    def predict(self, values: Mapping) -> list[np.ndarray]:
        return [_log_force(lg, self.spec, self.law, *self._split(values, i), terms=c)
                for i, (lg, c) in enumerate(zip(self.logs, self._prony_terms))]

    def residual(self, theta, data=None):
        values = self.to_values(theta)
        data = self.data if data is None else data
        pred = self.predict(values)
        prior = [np.array([scale * contact_prior_residual(theta[j] / sd) for j, scale, sd in self.prior_rows])]
        return np.concatenate([w * (p[m] - d) for w, p, m, d in zip(self.weights, pred, self.used, data)] + prior)

    def raw_residuals(self, values, data=None) -> list[np.ndarray]:
        data = self.data if data is None else data
        return [p[m] - d for p, m, d in zip(self.predict(values), self.used, data)]

    def row_weights(self) -> np.ndarray:
        """The weight of every row of :meth:`residual`: its log's (the priors' rows too)."""
        rows = [np.full(int(m.sum()), w) for w, m in zip(self.weights, self.used)]
        prior_w = [self.weights[i] for i in self.prior_log]
        return np.concatenate(rows + [np.array(prior_w, dtype=float)])

    # -- global stage -------------------------------------------------------------------

    def _unit_columns(self, alpha: float, defaults: Mapping) -> np.ndarray:
        """Weighted force of each log for mu = 1 at exponent ``alpha`` (no offset, no compliance)."""
        g = np.array([defaults[f"g{j}"] for j in range(1, self.spec.prony + 1)])
        tau = np.array([defaults[f"tau{j}_s"] for j in range(1, self.spec.prony + 1)])
        spec = replace(self.spec, boundary="frictionless") if self.spec.boundary == "no-slip" else self.spec
        law = get_law("ogden")
        cols = []
        for w, lg, m in zip(self.weights, self.logs, self.used):
            f = _log_force(lg, spec, law, np.array([1.0, alpha]), g, tau, 0.0, 0.0, 0.0, 0.0)
            cols.append(w * f[m])
        return np.concatenate(cols)

    def _nuisance_columns(self, disturbance_hz: Sequence[float] | None = None) -> np.ndarray:
        """Weighted baseline and drift columns (per log), when the spec has them; then, given
        each log's disturbance frequency, its sine and cosine columns (per log)."""
        blocks = []
        if self.spec.baseline_drift:
            blocks.append(self._log_column_pairs(lambda i, t: (np.ones_like(t), t)))
        if disturbance_hz is not None:
            blocks.append(self._log_column_pairs(
                lambda i, t: (np.sin(2.0 * np.pi * disturbance_hz[i] * t), np.cos(2.0 * np.pi * disturbance_hz[i] * t))))
        return np.column_stack(blocks) if blocks else np.zeros((self.n_obs, 0))

    def _log_column_pairs(self, pair) -> np.ndarray:
        """Two weighted columns per log, nonzero on its own fitted samples: ``pair(i, t)`` of log
        ``i``'s times from its first sample."""
        out = np.zeros((self.n_obs, 2 * len(self.logs)))
        row = 0
        for i, (w, lg, m) in enumerate(zip(self.weights, self.logs, self.used)):
            k = int(m.sum())
            a, b = pair(i, lg.time_s[m] - lg.time_s[0])
            out[row:row + k, 2 * i] = w * a
            out[row:row + k, 2 * i + 1] = w * b
            row += k
        return out

    def default_values(self) -> dict:
        v = {}
        spec = self.spec
        if spec.prony:
            lo, hi = self.tau_bounds
            taus = np.geomspace(max(0.1, 2 * lo), min(100.0, hi / 4), spec.prony) if spec.prony > 1 else \
                [float(np.sqrt(max(0.1, 2 * lo) * min(100.0, hi / 4)))]
            for j, t in enumerate(taus, start=1):
                v[f"g{j}"] = 0.5 / (spec.prony + 1)
                v[f"tau{j}_s"] = float(t)
        for p in self.pars:
            if p.name.startswith(("contact_offset_mm", "tare_n")):
                v[p.name] = 0.0
            elif p.name.startswith(TOE_NAMES):
                # c not 0: at a flat top the force is flat in c to first order, so a fit started
                # there would stay; p and s start mid-range (a dome, half the load spread).
                v[p.name] = _TOE_START[p.name.split("[")[0]]
            elif p.name.startswith(("baseline_n", "drift_n_per_s")):
                v[p.name] = 0.0
            elif p.name == "compliance_mm_per_n":
                v[p.name] = 1e-3 * p.hi
            elif p.name.startswith(SCATTER_NAME):
                v[p.name] = 0.0
            elif p.name.startswith(("disturbance_n", "disturbance_phase_rad")):
                v[p.name] = 0.0
            elif p.name.startswith("disturbance_hz"):
                v[p.name] = float(np.sqrt(p.lo * p.hi))
        return v

    def global_starts(self, n_keep: int = 4, disturbance_peaks: Sequence[Sequence[float]] | None = None) -> list[dict]:
        """Starts of the local fits from the global stage (module docstring).

        With a periodic disturbance, each log's candidate frequencies are ``disturbance_peaks``
        (from the residual of the model before the disturbance: :func:`fit_logs`), else those
        of the periodogram (:func:`disturbance_frequencies`) of the stage's own best residual
        without the disturbance; the stage is run at each (the k-th of every log), with the
        disturbance's sine and cosine as linear columns: the starts of the best frequency, then
        the best start of each other one."""
        if not self.spec.periodic_disturbance:
            return self._grid_starts(n_keep)[0]
        peaks = disturbance_peaks
        if peaks is None:
            _, _, resid = self._grid_starts(1)
            peaks = self.disturbance_peaks(resid)
        if not any(peaks):
            return self._grid_starts(n_keep)[0]
        runs = []
        for k in range(max(len(p) for p in peaks)):
            hz = [p[min(k, len(p) - 1)] if p else float(np.sqrt(lo * hi))
                  for p, (lo, hi) in zip(peaks, self.disturbance_bands)]
            starts, sse, _ = self._grid_starts(n_keep, hz)
            runs.append((sse, starts))
        runs.sort(key=lambda r: r[0])
        return list(runs[0][1]) + [r[1][0] for r in runs[1:]]

    def disturbance_peaks(self, residuals: Sequence[np.ndarray]) -> list[list[float]]:
        """Each log's candidate disturbance frequencies: its fitted residual's periodogram peaks."""
        return [disturbance_frequencies(lg.time_s[m], r, band)
                for lg, m, r, band in zip(self.logs, self.used, residuals, self.disturbance_bands)]

    def _grid_starts(self, n_keep: int, disturbance_hz: Sequence[float] | None = None):
        """The global stage: ``(starts, the best grid point's weighted sum of squares, its
        unweighted residual per log)``; with ``disturbance_hz`` (one frequency per log) the
        disturbance's sine and cosine are linear columns at those frequencies."""
        defaults = self.default_values()
        y = np.concatenate([w * d for w, d in zip(self.weights, self.data)])
        nuis = self._nuisance_columns(disturbance_hz)
        law = self.law
        if law.name in ("neo-hookean", "mooney-rivlin"):
            a_set = [2.0] if law.name == "neo-hookean" else [2.0, -2.0]
            cols = np.column_stack([self._unit_columns(a, defaults) for a in a_set])
            coef, sse, nu = _bounded_linear(cols, nuis, y)
            v = dict(defaults)
            if law.name == "neo-hookean":
                v["mu_pa"] = max(coef[0], 1e-6 * self.mu_scale)
            else:
                v["c10_pa"], v["c01_pa"] = (max(c / 2.0, 1e-6 * self.mu_scale) for c in coef)
            _put_nuisance(self, v, nu, disturbance_hz)
            return [v], sse, self._grid_residual(y, cols, coef, nuis, nu)
        nterm = law.n_terms
        grid = _ALPHA_GRID_1 if nterm == 1 else _ALPHA_GRID_N
        grid = grid[(grid >= self.alpha_abs_bounds[0]) & (grid <= self.alpha_abs_bounds[1])]
        alphas = np.concatenate([-grid[::-1], grid])
        basis = {a: self._unit_columns(a, defaults) for a in alphas}
        scored = []
        for combo in itertools.combinations(alphas, nterm):
            cols = np.column_stack([basis[a] for a in combo])
            coef, sse, nu = _bounded_linear(cols, nuis, y)
            scored.append((sse, combo, coef, nu))
        scored.sort(key=lambda s: s[0])
        picks, seen = [], {}
        # The best of every sign pattern first (alpha's sign matters), then the best overall.
        # Several terms: the best two of every pattern, because the grid's best of a pattern
        # can sit in another basin than the pattern's optimum (a two-term truth with alpha
        # -8 / +4: the grid's best mixed pair is (-6.5, 20), its second (-9, 0.5) leads to it).
        per_pattern = 1 if nterm == 1 else 2
        for s in scored:
            pat = tuple(np.sign(s[1]))
            if seen.get(pat, 0) < per_pattern:
                seen[pat] = seen.get(pat, 0) + 1
                picks.append(s)
        picks = sorted(picks, key=lambda s: s[0])
        if nterm == 1:
            picks = picks[:max(2, n_keep // 2 + 1)]
        for s in scored:
            if len(picks) >= n_keep:
                break
            if not any(s[1] == p[1] for p in picks):
                picks.append(s)
        starts = []
        for sse, combo, coef, nu in picks:
            v = dict(defaults)
            for j, (a, c) in enumerate(zip(combo, coef), start=1):
                mu = max(float(c), 1e-4 * self.mu_scale)
                if nterm == 1:
                    v["mu_pa"], v["alpha"] = mu, float(a)
                else:
                    v[f"mu{j}_pa"], v[f"alpha{j}"] = mu, float(a)
            _put_nuisance(self, v, nu, disturbance_hz)
            if self.spec.boundary == "no-slip":
                v = self._rescale_noslip(v, y, nuis, disturbance_hz)
            starts.append(v)
        sse, combo, coef, nu = scored[0]
        best = self._grid_residual(y, np.column_stack([basis[a] for a in combo]), coef, nuis, nu)
        return starts, sse, best

    def _grid_residual(self, y, cols, coef, nuis, nu) -> list[np.ndarray]:
        """A global-stage point's residual (data minus model, N) per log, unweighted."""
        r = y - cols @ coef - (nuis @ nu if nuis.shape[1] else 0.0)
        ends = np.cumsum([int(m.sum()) for m in self.used])
        return [r[a:b] / w for a, b, w in zip(np.r_[0, ends[:-1]], ends, self.weights)]

    def _rescale_noslip(self, v: dict, y, nuis, disturbance_hz=None) -> dict:
        """The global stage ran the homogeneous formula; rescale mu with the no-slip force."""
        cols = []
        tissue = np.array([1.0, v["alpha"]])
        g = np.array([v[f"g{j}"] for j in range(1, self.spec.prony + 1)])
        tau = np.array([v[f"tau{j}_s"] for j in range(1, self.spec.prony + 1)])
        for w, lg, m in zip(self.weights, self.logs, self.used):
            f = _log_force(lg, self.spec, self.law, tissue, g, tau, 0.0, 0.0, 0.0, 0.0)
            cols.append(w * f[m])
        coef, _, nu = _bounded_linear(np.concatenate(cols)[:, None], nuis, y)
        v = dict(v)
        v["mu_pa"] = max(float(coef[0]), 1e-4 * self.mu_scale)
        _put_nuisance(self, v, nu, disturbance_hz)
        return v


def _put_nuisance(problem: "_LogProblem", v: dict, nu: np.ndarray, disturbance_hz=None) -> None:
    r"""The global stage's linear nuisance coefficients (:meth:`_LogProblem._nuisance_columns`)
    as parameters: baseline and drift; a disturbance's sine and cosine as amplitude and phase,
    :math:`a \sin x + b \cos x = A \sin(x + \varphi)`."""
    n = len(problem.logs)
    sfx = log_suffix(n)
    j = 0
    if problem.spec.baseline_drift:
        for i in range(n):
            v[f"baseline_n{sfx(i)}"] = float(nu[2 * i])
            v[f"drift_n_per_s{sfx(i)}"] = float(nu[2 * i + 1])
        j = 2 * n
    if problem.spec.periodic_disturbance and disturbance_hz is not None:
        for i, hz in enumerate(disturbance_hz):
            a, b = float(nu[j + 2 * i]), float(nu[j + 2 * i + 1])
            v[f"disturbance_n{sfx(i)}"] = float(np.hypot(a, b))
            v[f"disturbance_hz{sfx(i)}"] = float(hz)
            v[f"disturbance_phase_rad{sfx(i)}"] = float(np.arctan2(b, a))


def _bounded_linear(cols: np.ndarray, nuis: np.ndarray, y: np.ndarray):
    """min ||cols a + nuis b - y|| with a >= 0, b free (NNLS on [cols, nuis, -nuis])."""
    a = np.column_stack([cols, nuis, -nuis]) if nuis.shape[1] else cols
    ok = np.all(np.isfinite(a), axis=0)
    if not ok.all():
        return np.zeros(cols.shape[1]), np.inf, np.zeros(nuis.shape[1])
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    x, rnorm = optimize.nnls(a / scale, y, maxiter=50 * a.shape[1])
    x = x / scale
    k = cols.shape[1]
    m = nuis.shape[1]
    nu = x[k:k + m] - x[k + m:] if m else np.zeros(0)
    return x[:k], float(rnorm**2), nu


class _TableProblem(_Problem):
    kind = "tables"
    unit = "pa"

    def __init__(self, table: pd.DataFrame, law_name: str):
        self.law = get_law(law_name)
        self.spec = ForceModelSpec(law=law_name)
        self.table = table.reset_index(drop=True)
        self.modes = list(dict.fromkeys(self.table["mode"]))
        self.groups = [np.flatnonzero(self.table["mode"].to_numpy() == m) for m in self.modes]
        self.stretch = [self.table["stretch"].to_numpy(float)[g] for g in self.groups]
        self.data = [self.table["nominal_stress_pa"].to_numpy(float)[g] for g in self.groups]
        self.n_obs = len(self.table)
        counts = np.array([len(g) for g in self.groups], dtype=float)
        self.weights = np.sqrt(self.n_obs / (len(self.groups) * counts))
        # Residual scale sqrt(|P| mean|P|) per mode (module docstring); a stress near zero is
        # measured against 1 % of its mode's largest.
        self.denoms = [np.sqrt(np.maximum(np.abs(d), 0.01 * np.max(np.abs(d))) * np.mean(np.abs(d)))
                       for d in self.data]
        smax = max(float(np.max(np.abs(d))) for d in self.data)
        self.mu_scale = max(smax / 10.0, 1e-9)
        pars = []
        for name in self.law.param_names:
            if name.startswith(("mu", "c10", "c01")):
                pars.append(_Par(name, 0.0, np.inf, self.mu_scale))
            else:
                pars.append(_Par(name, -_ALPHA_ABS_BOUNDS[1], _ALPHA_ABS_BOUNDS[1], 1.0))
        self.pars = pars
        self.names = [p.name for p in pars]
        self.used = [np.ones(len(g), dtype=bool) for g in self.groups]

    def predict(self, values: Mapping) -> list[np.ndarray]:
        tissue = np.array([values[k] for k in self.law.param_names])
        return [self.law.nominal_stress(s, tissue, m) for s, m in zip(self.stretch, self.modes)]

    def residual(self, theta, data=None):
        data = self.data if data is None else data
        pred = self.predict(self.to_values(theta))
        z = np.concatenate([w * (p - d) / q for w, p, d, q in zip(self.weights, pred, data, self.denoms)])
        return soft_l1_residual(z, TABLE_LOSS_SCALE)

    def raw_residuals(self, values, data=None):
        data = self.data if data is None else data
        return [p - d for p, d in zip(self.predict(values), data)]

    def _unit_columns(self, alpha: float) -> np.ndarray:
        return np.concatenate([w * ogden_nominal_stress(s, [1.0], [alpha], m) / q
                               for w, s, m, q in zip(self.weights, self.stretch, self.modes, self.denoms)])

    def global_starts(self, n_keep: int = 6) -> list[dict]:
        y = np.concatenate([w * d / q for w, d, q in zip(self.weights, self.data, self.denoms)])
        nuis = np.zeros((len(y), 0))
        law = self.law
        if law.name in ("neo-hookean", "mooney-rivlin"):
            a_set = [2.0] if law.name == "neo-hookean" else [2.0, -2.0]
            coef, _, _ = _bounded_linear(np.column_stack([self._unit_columns(a) for a in a_set]), nuis, y)
            if law.name == "neo-hookean":
                return [{"mu_pa": max(coef[0], 1e-6 * self.mu_scale)}]
            return [{"c10_pa": max(coef[0] / 2, 1e-6 * self.mu_scale), "c01_pa": max(coef[1] / 2, 1e-6 * self.mu_scale)}]
        nterm = law.n_terms
        grid = _ALPHA_GRID_1 if nterm == 1 else _ALPHA_GRID_N
        alphas = np.concatenate([-grid[::-1], grid])
        basis = {a: self._unit_columns(a) for a in alphas}
        scored = []
        for combo in itertools.combinations(alphas, nterm):
            coef, sse, _ = _bounded_linear(np.column_stack([basis[a] for a in combo]), nuis, y)
            scored.append((sse, combo, coef))
        scored.sort(key=lambda s: s[0])
        picks, seen = [], set()
        for s in scored:
            pat = tuple(np.sign(s[1]))
            if pat not in seen:
                seen.add(pat)
                picks.append(s)
        picks = sorted(picks, key=lambda s: s[0])[:max(2, n_keep // 2)]
        for s in scored:
            if len(picks) >= n_keep:
                break
            if not any(s[1] == p[1] for p in picks):
                picks.append(s)
        starts = []
        for _, combo, coef in picks:
            v = {}
            for j, (a, c) in enumerate(zip(combo, coef), start=1):
                mu = max(float(c), 1e-4 * self.mu_scale)
                if nterm == 1:
                    v["mu_pa"], v["alpha"] = mu, float(a)
                else:
                    v[f"mu{j}_pa"], v[f"alpha{j}"] = mu, float(a)
            starts.append(v)
        return starts


# --- the optimiser and the uncertainty ------------------------------------------------------

def _local_fit(problem: _Problem, start: Mapping, data=None, max_nfev: int | None = None):
    theta0 = problem.to_theta({**start})
    lo, hi = problem.bounds(theta0)
    theta0 = np.clip(theta0, np.where(np.isfinite(lo), lo, -np.inf), np.where(np.isfinite(hi), hi, np.inf))
    x_scale = np.array([p.scale for p in problem.pars], dtype=float)
    for j, p in enumerate(problem.pars):
        if p.name.startswith(("mu", "c10", "c01")):
            x_scale[j] = max(abs(theta0[j]), 1e-3 * problem.mu_scale)
    res = optimize.least_squares(problem.safe_residual, theta0, bounds=(lo, hi), x_scale=x_scale,
                                 method="trf", args=(data,), max_nfev=max_nfev or 200 * (len(theta0) + 1),
                                 ftol=1e-10, xtol=1e-10, gtol=1e-10)
    return res, (lo, hi)


def _central_jacobian(problem: _Problem, theta, bounds) -> np.ndarray:
    lo, hi = bounds
    r0 = problem.residual(theta)
    jac = np.empty((len(r0), len(theta)))
    for j, p in enumerate(problem.pars):
        h = 1e-6 * max(abs(theta[j]), p.scale if not p.name.startswith(("mu", "c10", "c01")) else 1e-3 * problem.mu_scale)
        up, dn = theta.copy(), theta.copy()
        up[j] = min(theta[j] + h, hi[j])
        dn[j] = max(theta[j] - h, lo[j])
        if up[j] == dn[j]:
            jac[:, j] = 0.0
            continue
        jac[:, j] = (problem.residual(up) - problem.residual(dn)) / (up[j] - dn[j])
    return jac


def _covariance(jac: np.ndarray, sse: float, n: int, p: int, row_weights: np.ndarray | None = None) -> np.ndarray:
    """``s^2 (J^T J)^{-1}``; with ``row_weights`` the sandwich form (module docstring).

    ``jac`` is the weighted residual's Jacobian; ``sse`` the weighted sum of squares, or with
    ``row_weights`` the sum of squares of the residuals divided by their weights.
    """
    if n <= p:
        return np.full((p, p), np.nan)
    meat = None
    if row_weights is not None:
        jw = jac * np.asarray(row_weights, dtype=float)[:, None]
        meat = jw.T @ jw
    return _sandwich(jac, sse / (n - p), meat)


def _sandwich(jac: np.ndarray, scale: float, meat: np.ndarray | None = None) -> np.ndarray:
    """``scale (J^T J)^{-1}``, or with ``meat`` ``scale (J^T J)^{-1} meat (J^T J)^{-1}``
    (pseudo-inverse by SVD); NaN in the rows and columns of parameters the null space of
    ``J`` touches."""
    p = jac.shape[1]
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    tol = np.finfo(float).eps * max(jac.shape) * (sv[0] if len(sv) else 0.0)
    good = sv > tol
    inv = (vt[good].T / sv[good] ** 2) @ vt[good]
    if meat is not None:
        inv = inv @ meat @ inv
    if not good.all():
        cov = np.full((p, p), np.nan)
        ok = np.all(np.abs(vt[~good]) < 1e-8, axis=0)     # directions untouched by the null space
        cov[np.ix_(ok, ok)] = scale * inv[np.ix_(ok, ok)]
        return cov
    return scale * inv


#: Andrews' (1991) AR(1) plug-in bandwidth constant for the Bartlett kernel.
_ANDREWS_BARTLETT = 1.1447


def _serial(e: np.ndarray) -> tuple[float, int]:
    """Lag-1 autocorrelation of one log's residuals (clipped to [0, 0.97]) and the Bartlett
    kernel's bandwidth for it (Andrews' AR(1) plug-in, at most a quarter of the samples)."""
    m = len(e)
    ss = float(np.dot(e, e))
    if m < 8 or ss <= 0:
        return 0.0, 0
    rho = min(max(float(np.dot(e[1:], e[:-1]) / ss), 0.0), 0.97)
    a = 4 * rho ** 2 / ((1 - rho) ** 2 * (1 + rho) ** 2)
    return rho, int(min(np.ceil(_ANDREWS_BARTLETT * (a * m) ** (1 / 3)), m // 4))


def _is_serial(rho: float, bandwidth: int, m: int) -> bool:
    r"""A log's residuals are serially correlated: lag-1 above :math:`2/\sqrt m` (about the
    5 % level for white noise) and a bandwidth of a sample or more."""
    return rho > 2.0 / np.sqrt(max(m, 1)) and bandwidth >= 1


def _serial_logs(r: np.ndarray, segments: Sequence[tuple[int, int]]) -> dict:
    """Per log (``segments``: its rows of the residual ``r``): the lag-1 autocorrelation, the
    Bartlett bandwidth (:func:`_serial`) and whether it is serially correlated
    (:func:`_is_serial`)."""
    lag, bw = zip(*(_serial(r[a:b]) for a, b in segments)) if len(segments) else ((), ())
    return {"lag1": list(lag), "bandwidth": list(bw),
            "serial": [_is_serial(rho, L, b - a) for (a, b), rho, L in zip(segments, lag, bw)]}


def _serial_covariance(jac: np.ndarray, r: np.ndarray, segments: Sequence[tuple[int, int]], n: int, p: int,
                       lag1: Sequence[float]) -> np.ndarray:
    r"""The covariance with the noise's serial correlation: Newey-West's, AR(1)-prewhitened
    per log, :math:`\frac{n}{n-p} B^{-1} \hat S B^{-1}`, :math:`B = J^T J`,
    :math:`\hat S = \sum_{logs} (1-\rho)^{-2} \sum_l w_l \sum_t g_t g_{t-l}^T`,
    :math:`g_t = J_t (r_t - \rho r_{t-1})` (Bartlett weights :math:`w_l`, Andrews' bandwidth)
    within each log (``segments``: its rows, ``lag1`` their :math:`\rho`; the rows outside,
    the contact priors', count alone); for logs whose residuals are serially correlated
    (:func:`_serial_logs`).  A load channel low-pass filtered, or sampled faster than its
    noise changes, has correlated noise: the white-noise covariance had made 95 % intervals
    4.5 times too narrow (AR(1) 0.9: mu covered in 6 of 29 seeds)."""
    inside = np.zeros(len(r), bool)
    meat = np.zeros((p, p))
    for (a, b), rho in zip(segments, lag1):
        inside[a:b] = True
        # prewhitened (Andrews & Monahan 1992): the AR(1) taken out, the rest's Bartlett
        # sum, recoloured by 1 / (1 - rho)^2; the kernel alone, on rho 0.9, had left the
        # intervals 1.6 times too narrow
        e = r[a:b]
        w = np.r_[e[0] * np.sqrt(max(1.0 - rho ** 2, 0.0)), e[1:] - rho * e[:-1]]
        gi = jac[a:b] * w[:, None]
        _, L = _serial(w)
        S = gi.T @ gi
        for lag in range(1, L + 1):
            c = gi[lag:].T @ gi[:-lag]
            S += (1.0 - lag / (L + 1.0)) * (c + c.T)
        meat += S / (1.0 - rho) ** 2
    g = jac[~inside] * r[~inside, None]
    meat += g.T @ g
    return _sandwich(jac, n / (n - p), meat)


def _intervals(problem: _Problem, theta, cov, n, p) -> dict:
    q = t_ppf(0.975, max(n - p, 1))
    out = {}
    for j, par in enumerate(problem.pars):
        se = np.sqrt(cov[j, j]) if np.isfinite(cov[j, j]) and cov[j, j] >= 0 else np.nan
        lo, hi = theta[j] - q * se, theta[j] + q * se
        if par.log10:
            # An unidentified relaxation time has an interval over decades; cap it short of overflow.
            lo, hi = 10.0 ** np.clip(lo, -300, 300), 10.0 ** np.clip(hi, -300, 300)
        out[par.name] = [float(lo), float(hi)]
    return out


#: Fewest samples before the contact that measure the load cell's zero (``load-baseline-drift``,
#: the relative errors' unloaded level, a given contact's baseline).
MIN_UNLOADED_SAMPLES = 5


def _unloaded_level(lg) -> float:
    """A log's unloaded force: the median of its samples before the contact (0 N where fewer
    than :data:`MIN_UNLOADED_SAMPLES` measure it)."""
    before = lg.force_n[lg.displacement_mm < lg.contact_mm]
    return float(np.median(before)) if len(before) >= MIN_UNLOADED_SAMPLES else 0.0


def _metrics(problem: _Problem, values: Mapping) -> dict:
    """RMSE, NRMSE and the relative errors, these against the force the specimen carries (a
    log's force above its unloaded level, :func:`_unloaded_level`: a load cell's offset would
    otherwise shrink them, 0.00074 with +5 N for 0.053 without)."""
    raw = problem.raw_residuals(values)
    if problem.kind == "tables":
        carried = list(problem.data)
    else:
        carried = [d - _unloaded_level(lg) for d, lg in zip(problem.data, problem.logs)]
    r = np.concatenate(raw)
    y = np.concatenate(problem.data)
    yc = np.concatenate(carried)
    rmse = float(np.sqrt(np.mean(r**2)))
    rng = float(np.ptp(y)) if len(y) else 0.0
    big = np.abs(yc) > 0.1 * np.max(np.abs(yc))
    rel = np.abs(r[big]) / np.abs(yc[big])
    u = problem.unit
    m = {f"rmse_{u}": rmse, "nrmse": rmse / rng if rng > 0 else float("nan"),
         "max_rel_err": float(np.max(rel)) if len(rel) else float("nan"),
         "median_rel_err": float(np.median(rel)) if len(rel) else float("nan")}
    per = []
    for k, (rr, d) in enumerate(zip(raw, carried)):
        bigk = np.abs(d) > 0.1 * np.max(np.abs(d)) if len(d) else np.zeros(0, bool)
        relk = np.abs(rr[bigk]) / np.abs(d[bigk])
        entry = {f"rmse_{u}": float(np.sqrt(np.mean(rr**2))) if len(rr) else float("nan"), "n_points": int(len(rr)),
                 "max_rel_err": float(np.max(relk)) if len(relk) else float("nan"),
                 "median_rel_err": float(np.median(relk)) if len(relk) else float("nan")}
        if problem.kind == "tables":
            entry["mode"] = problem.modes[k]
        else:
            entry["log"] = problem.logs[k].name
        per.append(entry)
    m["per_mode" if problem.kind == "tables" else "per_log"] = per
    return m


def _fitted_frames(problem: _Problem, values: Mapping) -> list[pd.DataFrame]:
    frames = []
    if problem.kind == "tables":
        for s, d, p, m in zip(problem.stretch, problem.data, problem.predict(values), problem.modes):
            frames.append(pd.DataFrame({"stretch": s, "nominal_stress_pa": d, "model_pa": p,
                                        "residual_pa": p - d, "mode": m}))
        return frames
    for lg, m, p, w in zip(problem.logs, problem.used, problem.predict(values), problem.weights):
        frames.append(pd.DataFrame({"time_s": lg.time_s, "displacement_mm": lg.displacement_mm,
                                    "nominal_strain": lg.nominal_strain(), "force_n": lg.force_n,
                                    "model_n": p, "residual_n": p - lg.force_n, "fitted": m, "weight": w}))
    return frames


#: Multi-start screening: every start gets this many iterations, the best few run to convergence.
_SCREEN_NFEV = 12
_FINALISTS = 2


def _across_zero(problem: _Problem, res, max_rounds: int = 2):
    """An Ogden exponent that ran into the small end of its range (|alpha| at
    ``alpha_abs_bounds[0]``) wants to cross zero, which its sign, fixed by its start, forbids
    (the force is singular there): the fit is run again from there with that exponent's sign
    turned (|alpha| 0.5 and 2), and the better fit kept.  A two-term law with exponents of
    opposite signs (-8 and +2) had ended at -8 / -0.05, RMSE 17 times the noise, with intervals
    that missed the truth."""
    a_lo = problem.alpha_abs_bounds[0]
    for _ in range(max_rounds):
        values = problem.to_values(res.x)
        stuck = [k for k, v in values.items() if k.startswith("alpha") and abs(abs(v) - a_lo) <= 1e-6 + 1e-3 * a_lo]
        if not stuck:
            return res
        better = None
        for k in stuck:
            for mag in (0.5, 2.0):
                start = dict(values)
                start[k] = -np.sign(values[k]) * mag
                try:
                    r, _ = _local_fit(problem, start)
                except (ValueError, np.linalg.LinAlgError):
                    continue
                if np.isfinite(r.cost) and r.cost < (better or res).cost:
                    better = r
        if better is None:
            return res
        res = better
    return res


def _solve(problem: _Problem, starts: list[dict], *, seed: int, bootstrap: int) -> FitResult:
    screened = []
    for s in starts:
        try:
            res, _ = _local_fit(problem, s, max_nfev=_SCREEN_NFEV if len(starts) > _FINALISTS else None)
        except (ValueError, np.linalg.LinAlgError) as exc:
            log.debug("start %s failed: %s", s, exc)
            continue
        if np.isfinite(res.cost):
            screened.append(res)
    if not screened:
        raise ArithmeticError("no start of the fit could be evaluated")
    n_ok = len(screened)
    screened.sort(key=lambda r: r.cost)
    best = None
    for r in screened[:_FINALISTS]:
        res = r if r.status != 0 or len(starts) <= _FINALISTS else _local_fit(problem, problem.to_values(r.x))[0]
        if best is None or res.cost < best[0].cost:
            best = (res, None)
    res, _ = best
    res = _across_zero(problem, res)
    theta = problem.canonical(res.x)
    bnds = problem.bounds(theta)
    values = problem.to_values(theta)
    r = problem.residual(theta)
    # Rows: the data's residuals and the contact priors' pseudo-observations (one per prior,
    # with its parameter: they leave the residual degrees of freedom n - p of the data).
    rows, n, p = len(r), int(problem.n_obs), len(theta)
    sse = float(np.dot(r, r))
    finite = bool(np.all(np.isfinite(theta)) and np.isfinite(sse))
    success = bool(res.status > 0 and finite and n > p)
    jac = _central_jacobian(problem, theta, bnds) if finite else np.full((rows, p), np.nan)
    row_w = problem.row_weights() if problem.kind == "logs" and len(problem.logs) > 1 else None
    sse_cov = float(np.sum((r / row_w) ** 2)) if row_w is not None else sse
    serial = None
    if problem.kind == "logs" and finite:
        ends = np.cumsum([int(m.sum()) for m in problem.used])
        segments = list(zip(np.r_[0, ends[:-1]], ends))
        serial = _serial_logs(r, segments)
        serial["method"] = "white"
    if not finite:
        cov = np.full((p, p), np.nan)
    elif serial is not None and any(serial["serial"]) and rows > p and np.all(np.isfinite(jac)):
        cov = _serial_covariance(jac, r, segments, rows, p, serial["lag1"])
        serial["method"] = "newey-west, AR(1)-prewhitened per log (Bartlett kernel, Andrews bandwidth)"
    else:
        cov = _covariance(jac, sse_cov, rows, p, row_w)
    ci = _intervals(problem, theta, cov, rows, p)
    sse_n = max(sse, np.finfo(float).tiny) / max(n, 1)
    aic = float(n * np.log(sse_n) + 2 * p)
    bic = float(n * np.log(sse_n) + p * np.log(max(n, 1)))
    metrics = _metrics(problem, values)
    metrics.update(aic=aic, bic=bic, n_obs=n, n_params=p, sse_weighted=sse)
    factors: list[float] = []
    if serial is not None:
        metrics.update(residual_lag1=serial["lag1"], covariance=serial["method"])
        factors = [(1.0 - rho) / (1.0 + rho) if ser else 1.0 for rho, ser in zip(serial["lag1"], serial["serial"])]
    out = FitResult(spec=problem.spec, params=_contract_params(problem.spec, values), ci95=ci, metrics=metrics,
                    residuals=problem.raw_residuals(values), n_obs=n, n_params=p, aic=aic, bic=bic, cov=cov,
                    success=success, param_names=list(problem.names), values=values,
                    fitted=_fitted_frames(problem, values), used=list(problem.used),
                    message=str(res.message), n_starts=n_ok, kind=problem.kind,
                    at_bound=_at_bound(problem.names, theta, bnds), serial_factors=factors,
                    log_weights=[float(w) for w in getattr(problem, "weights", [])])
    if bootstrap and success:
        out.ci95_bootstrap, out.bootstrap = _bootstrap(problem, values, bootstrap, seed)
    return out


def _at_bound(names, theta, bnds, rel: float = 1e-6) -> dict:
    """The parameters that ended on an edge of their range (within ``rel`` of its width, or of
    the value where the range is unbounded on that side): ``name -> "lower" | "upper"``."""
    out = {}
    for k, t, lo, hi in zip(names, theta, *bnds):
        width = hi - lo if np.isfinite(hi - lo) else max(abs(t), 1.0)
        tol = rel * width
        if np.isfinite(lo) and t <= lo + tol:
            out[k] = "lower"
        elif np.isfinite(hi) and t >= hi - tol:
            out[k] = "upper"
    return out


def _bootstrap(problem: _Problem, values: Mapping, n_boot: int, seed: int, progress=None):
    """Residual bootstrap: data* = model + residuals resampled within each log / mode
    (``progress``: called once per refit, e.g. a progress bar's ``update``).  A log whose
    residuals are serially correlated (:func:`_serial`) is resampled in moving blocks of its
    Bartlett bandwidth, so the draws keep the correlation (single samples shuffled had made
    the bootstrap's intervals as narrow as the white-noise Jacobian's on AR(1) 0.9 noise)."""
    rng = np.random.default_rng(seed)
    pred = [p[m] if problem.kind == "logs" else p for p, m in zip(problem.predict(values), problem.used)]
    raw = problem.raw_residuals(values)
    blocks = []
    for rk in raw:
        rho, L = _serial(rk) if problem.kind == "logs" else (0.0, 0)
        blocks.append(L if _is_serial(rho, L, len(rk)) else 1)

    def resample(rk, b):
        if b <= 1:
            return rng.choice(rk, size=len(rk), replace=True)
        starts = rng.integers(0, len(rk) - b + 1, size=-(-len(rk) // b))
        return np.concatenate([rk[s0:s0 + b] for s0 in starts])[:len(rk)]

    draws = []
    for _ in range(n_boot):
        data = [pk - resample(rk, b) for pk, rk, b in zip(pred, raw, blocks)]
        try:
            res, _ = _local_fit(problem, values, data=data)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if res.status > 0:
            draws.append(problem.canonical(res.x))
        if progress is not None:
            progress()
    if len(draws) < max(10, n_boot // 2):
        return None, {"n": n_boot, "n_ok": len(draws), "seed": seed}
    d = np.array(draws)
    ci = {}
    for j, par in enumerate(problem.pars):
        lo, hi = np.percentile(d[:, j], [2.5, 97.5])
        if par.log10:
            lo, hi = 10.0**lo, 10.0**hi
        ci[par.name] = [float(lo), float(hi)]
    return ci, {"n": n_boot, "n_ok": len(draws), "seed": seed, "method": "residual resampling within each series"}


# --- public entry points ---------------------------------------------------------------------

def fit_logs(logs: Sequence[LogData], spec: ForceModelSpec = ForceModelSpec(), *, max_strain: float | None = None,
             seed: int = 0, bootstrap: int = 0, start: Mapping | None = None,
             sample_mask: Sequence[np.ndarray] | None = None) -> FitResult:
    """Fit ``spec`` jointly to machine logs (one tissue parameter set, per-log effects).

    Parameters
    ----------
    logs : sequence of LogData
    spec : ForceModelSpec
    max_strain : float, optional
        Fit only samples up to this nominal strain past each log's detected contact.
    seed : int
        Seeds the bootstrap.
    bootstrap : int
        Number of residual-bootstrap refits that check the Jacobian intervals (0: none).
    start : mapping, optional
        An extra start (e.g. the previous fit's values, flat names); names it lacks take the
        global stage's values.
    sample_mask : sequence of bool arrays, optional
        One per log: fit only the samples where it is True (and within ``max_strain``); the
        model is still evaluated over each whole log.  The loop's held-out error uses it.

    Returns
    -------
    FitResult (``success`` False when the optimiser did not converge; the caller decides).

    Raises
    ------
    ValueError
        When there are fewer fitted samples than parameters.
    """
    if not logs:
        raise ValueError("no logs to fit")
    problem = _LogProblem(logs, spec, max_strain, sample_mask)
    if problem.n_obs <= len(problem.pars):
        raise ValueError(f"{problem.n_obs} samples to fit but the model has {len(problem.pars)} parameters")
    peaks = before = None
    if spec.periodic_disturbance and start is not None and not any(k.startswith("disturbance_hz") for k in start):
        # the disturbance is being added to the model ``start`` fitted: the periodogram of that
        # model's residual says where it is (the global stage's coarse law leaves its own misfit
        # there, at the frequencies of the record's shape: 0.8-1.2 Hz on a 4 s ramp for a 0.5 Hz hum)
        before = {**problem.default_values(), **{k: v for k, v in _flat_prony(start).items() if k in problem.names}}
        if set(problem.names) <= set(before):
            peaks = problem.disturbance_peaks(problem.raw_residuals(before))
        else:
            before = None
    starts = problem.global_starts(disturbance_peaks=peaks)
    if start is not None:
        extra = dict(starts[0])
        extra.update({k: v for k, v in _flat_prony(start).items() if k in problem.names})
        if before is not None and any(peaks):
            # ``start`` and, at each of its residual's peaks, the sinusoid that residual has there
            resid = problem.raw_residuals(before)
            sfx = log_suffix(len(logs))
            ahead = []
            for k in range(max(len(p) for p in peaks)):
                v = dict(extra)
                for i, (lg, m, r, p) in enumerate(zip(problem.logs, problem.used, resid, peaks)):
                    if p:
                        hz = p[min(k, len(p) - 1)]
                        amp, phase = _sinusoid_of(lg.time_s[m] - lg.time_s[0], -r, hz)
                        v.update({f"disturbance_n{sfx(i)}": amp, f"disturbance_hz{sfx(i)}": hz,
                                  f"disturbance_phase_rad{sfx(i)}": phase})
                ahead.append(v)
            starts = ahead + starts
        else:
            starts = [extra] + starts
    if spec.prony:
        # A second set of relaxation-time starts, a decade apart from the first.
        alt = []
        for s in starts[:2]:
            v = dict(s)
            for j in range(1, spec.prony + 1):
                v[f"tau{j}_s"] = float(np.clip(v[f"tau{j}_s"] * (10.0 if j % 2 else 0.1), *problem.tau_bounds))
            alt.append(v)
        starts = starts + alt
    return _solve(problem, starts, seed=seed, bootstrap=bootstrap)


def other_optima(logs: Sequence[LogData], result: FitResult, *, max_strain: float | None = None,
                 level: float = 0.95) -> list[dict]:
    r"""Other fits of a law with several Ogden terms as good as ``result`` within the noise.

    Every global start of ``result``'s model is run to convergence (the fit itself refines
    only the best few); an optimum whose weighted sum of squares lies within
    :math:`k\,F_{k,n-p}(level)\,s^2` of the best (``k`` the law's parameters and the refined
    contacts: inside their joint confidence region) and whose law parameters fall outside ``result``'s 95 % intervals is
    returned (``params``, ``delta_sse_over_s2``, and its own 95 % intervals ``ci95``).  The
    intervals describe one basin: on a
    two-term log (truth 500 Pa / -8, 300 Pa / +4) the fit had ended at -5.5 / +20.2 with
    tight intervals while the truth's basin fitted 0.89 s^2 worse, nothing said.

    A one-term Ogden law has its exponent's other sign tried (the fit keeps the sign it starts
    with): the global stage's best start of that sign, and |alpha| 2, 5 and 10, each from the
    fit's own nuisance values and from the start's, run to convergence; an optimum of that
    sign inside the joint region is returned.  A short ramp (to 10 % strain, 1 mN noise) had
    been fitted at alpha +24.2 [23.0, 25.5], mu 975 [955, 995] Pa for -4.7 / 720, the truth's
    basin 5.6 noise variances worse, nothing said."""
    law = get_law(result.spec.law)
    names = list(law.param_names)
    exponents = [k for k in names if k.startswith("alpha")]
    if not exponents or (len(exponents) < 2 and law.n_terms != 1) or not result.success:
        return []
    problem = _LogProblem(logs, result.spec, max_strain)
    n, p = problem.n_obs, len(problem.pars)
    best = float(result.metrics.get("sse_weighted", np.nan))
    if not np.isfinite(best) or n <= p:
        return []
    s2 = best / (n - p)
    # The joint region of the law's parameters and the contacts the fit refines (the basins
    # trade an exponent against the contact: a stiff +alpha curve starts later), with s^2
    # estimated on n - p degrees of freedom: sum of squares within k F(k, n - p) s^2 of the
    # best (Bates & Watts 1988, 6.1.1).
    from scipy.special import fdtri
    k = len(names) + sum(1 for q in problem.names if q.startswith("contact_offset_mm"))
    limit = k * float(fdtri(k, n - p, level))
    out: list[dict] = []
    if len(exponents) == 1:
        a_name = exponents[0]
        sign = float(np.sign(result.values[a_name]))
        starts = []
        turned = [st for st in problem.global_starts(n_keep=8) if np.sign(st[a_name]) == -sign][:1]
        for mag in (2.0, 5.0, 10.0):
            st = dict(turned[0]) if turned else problem.default_values()
            st[a_name] = -sign * mag
            st.setdefault("mu_pa", float(result.values["mu_pa"]))
            turned.append(st)
        for st in turned:
            own = dict(result.values)
            own.update({k: st[k] for k in names if k in st})
            starts += [own, {**result.values, **st}]
    else:
        starts = []
        for st in problem.global_starts():
            start = dict(result.values)
            start.update({k: st[k] for k in names if k in st})
            starts.append(start)
    for start in starts:
        try:
            r, _ = _local_fit(problem, start)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if not np.isfinite(r.cost) or r.status <= 0:
            continue
        v = problem.to_values(problem.canonical(r.x))
        d = (2.0 * r.cost - best) / s2
        ci = result.ci95
        if d > limit or all(k in ci and ci[k][0] <= v[k] <= ci[k][1] for k in names):
            continue
        if len(exponents) == 1 and np.sign(v[exponents[0]]) == np.sign(result.values[exponents[0]]):
            continue
        if any(all(abs(v[k] - o["params"][k]) <= 1e-3 * max(1.0, abs(o["params"][k])) for k in names) for o in out):
            continue
        # its own 95 % intervals (Jacobian, the best fit's s^2): what the basin spans
        theta = problem.canonical(r.x)
        try:
            jac = _central_jacobian(problem, theta, problem.bounds(theta))
            own = _intervals(problem, theta, _sandwich(jac, s2), n, p)
        except (ValueError, np.linalg.LinAlgError):
            own = {}
        out.append({"params": {k: float(v[k]) for k in names}, "delta_sse_over_s2": float(max(d, 0.0)),
                    "ci95": {k: own[k] for k in names if k in own}})
    return sorted(out, key=lambda o: o["delta_sse_over_s2"])


class TooFewRows(ValueError):
    """A stress-stretch table with no more rows than the model has parameters."""


def fit_tables(tables, law: str = "ogden", *, seed: int = 0, bootstrap: int = 0) -> FitResult:
    """Fit a law jointly to stress-stretch tables of one or several loading modes.

    Parameters
    ----------
    tables : DataFrame or sequence of DataFrames
        Columns ``stretch``, ``nominal_stress_pa``, ``mode`` (as ``read_stress_table``
        returns); simple-shear rows hold the amount of shear in ``stretch``.
    law : str
        A name of :data:`bsipipe.mechanics.hyperelastic.LAWS`.

    Returns
    -------
    FitResult with ``kind='tables'``; metrics in Pa (``rmse_pa``) and per mode.
    """
    if isinstance(tables, pd.DataFrame):
        tables = [tables]
    table = pd.concat(list(tables), ignore_index=True)
    missing = {"stretch", "nominal_stress_pa", "mode"} - set(table.columns)
    if missing:
        raise ValueError(f"stress table lacks columns {sorted(missing)}")
    bad = set(table["mode"]) - set(MODES)
    if bad:
        raise ValueError(f"unknown loading modes {sorted(bad)}; expected {MODES}")
    problem = _TableProblem(table, law)
    if problem.n_obs <= len(problem.pars):
        raise TooFewRows(f"{problem.n_obs} table rows to fit but the model has {len(problem.pars)} parameters")
    return _solve(problem, problem.global_starts(), seed=seed, bootstrap=bootstrap)


def add_bootstrap(result: FitResult, data, *, n: int, seed: int = 0, max_strain: float | None = None,
                  progress=None) -> FitResult:
    """``result`` with its residual-bootstrap check added (``ci95_bootstrap``, ``bootstrap``).

    ``data`` is what ``result`` was fitted to: the logs (with the same ``max_strain``) or the
    tables.  The point estimate is not refitted, so the parameters stay those given.
    ``progress`` is called after each of the ``n`` refits.
    """
    if result.kind == "tables":
        table = pd.concat([data] if isinstance(data, pd.DataFrame) else list(data), ignore_index=True)
        problem: _Problem = _TableProblem(table, result.spec.law)
    else:
        problem = _LogProblem(data, result.spec, max_strain)
    ci, info = _bootstrap(problem, result.values, n, seed, progress) if n and result.success else (None, None)
    return replace(result, ci95_bootstrap=ci, bootstrap=info)


def median_relative_errors(result: FitResult) -> dict:
    """Median |model - data| / |data| per mode (tables) or per log, over every fitted point."""
    out = {}
    for k, fr in enumerate(result.fitted):
        if result.kind == "tables":
            out[fr["mode"].iloc[0]] = float(np.median(np.abs(fr["residual_pa"]) / np.abs(fr["nominal_stress_pa"])))
        else:
            f = fr[fr["fitted"]]
            big = np.abs(f["force_n"]) > 0.1 * np.max(np.abs(f["force_n"]))
            out[k] = float(np.median(np.abs(f["residual_n"][big]) / np.abs(f["force_n"][big])))
    return out
