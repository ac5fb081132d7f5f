r"""The loop: fit the declared model, look at what is left, add an effect only on strong evidence.

::

    state = fit(spec0)
    repeat:
        test state's residual for structure                      (residual_structure)
        if it is noise: try only effects with outside evidence   (none added on the residual alone)
        for each candidate effect that can augment the spec: fit it, weigh the evidence in sample
        in order of preference, check those that pass on held-out data; keep the first that
        passes that too; if none, stop

Selection rule (:class:`SelectionRule`, defaults):

- **Information criterion.**  :math:`\Delta\mathrm{BIC} = \mathrm{BIC}_{before} - \mathrm{BIC}_{after} > 10`,
  "very strong" evidence on Kass & Raftery's (1995) scale.  BIC is the stage's own when the
  fit reports one, else the Gaussian :math:`n \ln(\mathrm{RSS}/n) + k \ln n`.  For one extra
  parameter in 5,000 white-noise samples this is a likelihood-ratio test at
  :math:`p \approx 2 \times 10^{-5}`.
  Where the stage's richer fit has a ``serial_data_term`` (fit-ogden: a log's residual
  serially correlated, each log's samples counted as :math:`(1-\rho)/(1+\rho)` of them), the
  BIC is taken on the effective samples, for both models.
- **Practical significance.**  The fitted RMSE must also drop by more than
  ``rmse_gain_min`` (5 %): the part of the error the effect removes,
  :math:`\sqrt{\mathrm{RMSE}_{before}^2 - \mathrm{RMSE}_{after}^2}`, is then about a third or more of
  what is left.  BIC alone, over thousands of samples, accepts corrections far below the
  noise (a contact detector's few-micrometre scatter, the remainder of an effect the model
  represents only approximately), and each such step invites the next.  Or, where the stage's
  fits report their parameters' 95 % intervals (``values``, ``ci95``): the effect moves a
  declared parameter by more than ``param_shift_min`` (3) times the larger half-width.  On a
  long quiet record a bias can be small against the noise and large against the intervals
  (a load cell's slow drift, 1.3 % of the peak force: the RMSE 2.1 % lower, mu 1.4 % off, six
  half-widths); that is practical significance too.
- **Held-out error** (when the stage passes ``heldout``; fit-ogden does where there are
  several logs, over interleaved blocks of every log): the candidate must also lower the held-out RMSE by more than
  ``heldout_gain_min`` (5 %) of its value before.  An effect that only fits the training
  logs' noise does not predict a log it has not seen.
- **Outside evidence** (an :class:`Effect` with ``evidence``, e.g. a side-camera width series
  for the platen boundary): the candidate passes when that evidence has
  :math:`\Delta\mathrm{BIC} > 10` and the fitted residual does not get very strongly worse
  (:math:`\Delta\mathrm{BIC} > -10`).  Outside evidence that is there and says no
  (:math:`\Delta\mathrm{BIC} < -10`) vetoes the candidate whatever the residual says.
- A catch-all effect (:class:`Effect` ``catch_all``: a model-free correction fitted to the
  residual, which can absorb a physical effect and the parameters it identifies) is kept only
  in a round where no other candidate passes.
- Among passing candidates the loop keeps, first, the one with the strongest outside
  evidence (direct evidence of the mechanism, from data the model was not fitted to), else
  the one with the largest :math:`\Delta\mathrm{BIC}`; the held-out error is a check, not a
  ranking.  Candidates within ``tie_delta_bic`` (10) of the best are not told apart by the
  data; the one that adds the fewest parameters is kept, then the one the stage lists first
  (its most common mechanism), and the runner-up is reported.
- The loop stops when no candidate passes; when the residual is already noise
  (:func:`~bsipipe.loop.residual_structure` at family-wise level 1 %, or, where the stage
  measures its noise level independently of any model, an RMSE at or below it), only effects
  with outside evidence are tried, so data without a hidden effect gets none.  An RMSE a
  few per cent above the measured noise does not by itself end the loop: a residual whose
  pattern is structured (a second relaxation time, a machine's compliance) can be that
  small and still bias the parameters far outside their intervals.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .effect import Effect
from .structure import ALPHA, residual_structure

log = logging.getLogger(__name__)

#: A residual at or below the measured noise level is taken for noise unless its structure
#: test's smallest p-value is below this (overwhelming structure: it is looked at).
STRUCTURE_OVER_FLOOR_P = 1e-6


@dataclass(frozen=True)
class SelectionRule:
    """Thresholds of the evidence an effect needs (see the module docstring)."""

    delta_bic_min: float = 10.0          # Kass & Raftery "very strong"
    rmse_gain_min: float = 0.05          # relative drop of the fitted RMSE (practical significance)
    param_shift_min: float = 3.0         # or a declared parameter moved by this many 95 % half-widths
    heldout_gain_min: float = 0.05       # relative drop of the held-out RMSE
    evidence_delta_bic_min: float = 10.0  # outside evidence, same scale
    residual_delta_bic_floor: float = -10.0  # an outside-evidence effect may not make the fit very strongly worse
    alpha: float = ALPHA                 # family-wise level of the residual-is-noise verdict
    tie_delta_bic: float = 10.0          # candidates closer than this are not told apart by the data

    def as_dict(self) -> dict:
        d = asdict(self)
        d["description"] = (
            f"keep an effect when delta BIC > {self.delta_bic_min:g} (Kass-Raftery 'very strong'), the fitted RMSE "
            f"drops by more than {100 * self.rmse_gain_min:g} % (or a declared parameter moves by more than "
            f"{self.param_shift_min:g} times its 95 % half-width) and, where held-out data exist, the held-out RMSE "
            f"drops by more than {100 * self.heldout_gain_min:g} %; "
            f"or when outside evidence has delta BIC > {self.evidence_delta_bic_min:g} and the fit's delta BIC "
            f"> {self.residual_delta_bic_floor:g}; the strongest passing effect is kept, one per step (within "
            f"delta BIC {self.tie_delta_bic:g} of the strongest, the one adding the fewest parameters, then the "
            f"one the stage lists first); only "
            f"outside-evidence effects are tried once the residual is noise (family-wise alpha {self.alpha:g}) "
            f"or its RMSE is within {100 * self.rmse_gain_min:g} % of the measured noise level")
        return d


@dataclass
class LoopState:
    """One fitted model: its spec, the stage's fit result, and what its residual looks like."""

    spec: Any
    fit: Any
    model: str
    params: dict
    rmse: float
    bic: float
    n_obs: int
    n_params: int
    structure: dict
    heldout_rmse: float | None = None

    def summary(self, unit: str) -> dict:
        d = {"model": self.model, "params": self.params, f"rmse_{unit}": self.rmse, "bic": self.bic,
             "n_obs": self.n_obs, "n_params": self.n_params}
        if self.heldout_rmse is not None:
            d[f"heldout_rmse_{unit}"] = self.heldout_rmse
        return d


@dataclass
class LoopStep:
    effect: Effect
    evidence: dict
    before: LoopState
    after: LoopState

    def effect_params(self) -> dict:
        """The parameters this step added or grew (a longer Prony list), and the effect's named ones."""
        out = {}
        for k, v in self.after.params.items():
            b = self.before.params.get(k)
            grew = isinstance(v, list) and isinstance(b, list) and len(v) != len(b)
            if k not in self.before.params or grew or k in self.effect.param_names:
                out[k] = v
        return out

    def to_dict(self, unit: str) -> dict:
        added = self.effect_params()
        return {
            "effect": self.effect.name,
            "explanation": self.effect.explanation,
            "signature": self.effect.signature,
            "model": self.after.model,
            "evidence": self.evidence,
            f"rmse_{unit}_before": self.before.rmse,
            f"rmse_{unit}_after": self.after.rmse,
            "params": self.after.params,
            "effect_params": added,
            "residual_before": _compact(self.before.structure),
            "residual_after": _compact(self.after.structure),
        }


def _compact(structure: dict) -> dict:
    return {k: structure[k] for k in ("noise", "p_min", "worst", "n_tests", "rms")}


@dataclass
class LoopReport:
    """Everything the loop did: the baseline, each kept effect, every candidate tried, the end."""

    unit: str
    rule: SelectionRule
    baseline: LoopState
    steps: list[LoopStep] = field(default_factory=list)
    tried: list[list[dict]] = field(default_factory=list)
    stopped_because: str = ""
    noise_rms: float | None = None
    noise_ceiling: float | None = None

    @property
    def final(self) -> LoopState:
        return self.steps[-1].after if self.steps else self.baseline

    @property
    def effects(self) -> list[str]:
        return [s.effect.name for s in self.steps]

    def to_dict(self) -> dict:
        """The contract's shape: ``baseline``, ``steps``, ``final``, ``residual_structure`` (and more)."""
        u = self.unit
        base = self.baseline.summary(u)
        base["residual_structure"] = self.baseline.structure
        rs = dict(self.final.structure)
        if self.noise_rms:
            rs.update({f"noise_rms_{u}": self.noise_rms, "rmse_over_noise": self.final.rmse / self.noise_rms})
        if self.noise_ceiling:
            rs[f"noise_ceiling_{u}"] = self.noise_ceiling
            if self.final.rmse > self.noise_ceiling:
                # the structure tests saw no pattern, but noise cannot be this large
                rs.update(noise=False, above_noise_ceiling=True)
        return {
            "baseline": base,
            "steps": [s.to_dict(u) for s in self.steps],
            "final": self.final.summary(u),
            "residual_structure": rs,
            "rule": self.rule.as_dict(),
            "tried": self.tried,
            "stopped_because": self.stopped_because,
        }


def _residual_vector(fit) -> list[np.ndarray]:
    r = fit.residuals
    if isinstance(r, (list, tuple)):
        return [np.asarray(x, dtype=float).ravel() for x in r]
    return [np.asarray(r, dtype=float).ravel()]


def gaussian_bic(rss: float, n: int, k: int) -> float:
    r"""BIC of a least-squares fit with Gaussian errors of unknown variance, :math:`n \ln(RSS/n) + k \ln n`.

    >>> round(gaussian_bic(100.0, 100, 2) - gaussian_bic(100.0, 100, 1), 4) == round(float(np.log(100)), 4)
    True
    """
    return float(n * np.log(max(rss, np.finfo(float).tiny) / n) + k * np.log(n))


class _Fitter:
    """Fits each spec once; turns fit results into loop states."""

    def __init__(self, fit, heldout, covariates, groups, describe, alpha):
        self._fit, self._heldout = fit, heldout
        self._covariates, self._groups = covariates, groups
        self._describe, self._alpha = describe, alpha
        self._cache: dict = {}
        self._heldout_cache: dict = {}

    def state(self, spec) -> LoopState:
        if spec in self._cache:
            return self._cache[spec]
        res = self._fit(spec)
        parts = _residual_vector(res)
        e = np.concatenate(parts)
        n = len(e)
        k = int(getattr(res, "n_params", 0) or 0)
        rss = float(np.dot(e, e))
        bic = getattr(res, "bic", None)
        bic = gaussian_bic(rss, n, k) if bic is None or not np.isfinite(bic) else float(bic)
        cov = self._covariates(res) if callable(self._covariates) else (self._covariates or {})
        groups = self._groups(res) if callable(self._groups) else self._groups
        if groups is None and len(parts) > 1:
            groups = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)])
        st = LoopState(spec=spec, fit=res, model=self._describe(spec), params=dict(getattr(res, "params", {}) or {}),
                       rmse=float(np.sqrt(rss / n)), bic=bic, n_obs=n, n_params=k,
                       structure=residual_structure(e, cov, groups, alpha=self._alpha))
        self._cache[spec] = st
        return st

    def heldout(self, state: LoopState) -> float | None:
        if self._heldout is None:
            return None
        if state.spec not in self._heldout_cache:
            h = self._heldout(state.spec)
            if isinstance(h, Mapping):
                h = h.get("rmse")
            self._heldout_cache[state.spec] = None if h is None else float(h)
        state.heldout_rmse = self._heldout_cache[state.spec]
        return state.heldout_rmse


#: Failures of a candidate fit that reject the candidate instead of ending the loop.
_CANDIDATE_FAILURES = (ArithmeticError, ValueError, np.linalg.LinAlgError, RuntimeError)


def _weigh(effect: Effect, before: LoopState, after: LoopState, rule: SelectionRule,
           residual_is_noise: bool) -> dict:
    """In-sample and outside evidence for one candidate, and whether it passes that far.

    A candidate that passes here on the residual still needs the held-out check
    (:func:`_heldout_check`) when the stage has held-out data.
    """
    ev: dict = {"delta_bic": before.bic - after.bic, "bic_before": before.bic, "bic_after": after.bic,
                "rmse_before": before.rmse, "rmse_after": after.rmse,
                "added_params": after.n_params - before.n_params}
    if getattr(after.fit, "success", True) is False:
        ev.update(passes=False, criterion="fit", reason="the augmented fit did not converge")
        return ev
    hook = getattr(after.fit, "serial_data_term", None)
    term = hook(before.fit) if callable(hook) else None
    if term is not None:
        # serially correlated noise (the richer model's residual still correlated): the
        # Gaussian BIC on each series' effective samples, n (1 - rho) / (1 + rho); counted as
        # independent, AR(1) 0.9 load noise had had drift, compliance or a contact offset
        # kept on 6 of 16 elastic logs
        data, n_eff = term
        dp = after.n_params - before.n_params
        ev.update(delta_bic_white=ev["delta_bic"], n_effective=n_eff,
                  delta_bic=data - dp * np.log(max(n_eff, 2.0)))
    outside = effect.evidence(before, after) if effect.evidence is not None else None
    if outside is not None:
        ev["outside"] = outside
        d = float(outside["delta_bic"])
        if d < -rule.evidence_delta_bic_min:
            ev.update(passes=False, criterion="outside", reason=f"outside evidence against the effect (delta BIC {d:.1f})")
            return ev
        if d > rule.evidence_delta_bic_min and ev["delta_bic"] > rule.residual_delta_bic_floor:
            ev.update(passes=True, criterion="outside",
                      reason=f"outside evidence delta BIC {d:.1f} > {rule.evidence_delta_bic_min:g}, "
                             f"fit delta BIC {ev['delta_bic']:.1f} > {rule.residual_delta_bic_floor:g}")
            return ev
    if residual_is_noise:
        ev.update(passes=False, criterion="residual", reason="the residual is already noise")
        return ev
    if ev["delta_bic"] <= rule.delta_bic_min:
        ev.update(passes=False, criterion="bic", reason=f"delta BIC {ev['delta_bic']:.1f} <= {rule.delta_bic_min:g}")
        return ev
    gain = (before.rmse - after.rmse) / before.rmse if before.rmse > 0 else 0.0
    ev["rmse_gain"] = gain
    shift = _param_shift(before, after)
    if shift is not None:
        ev["param_shift"] = shift
    if gain <= rule.rmse_gain_min and shift is not None and shift["half_widths"] > rule.param_shift_min:
        ev.update(passes=True, criterion="params",
                  reason=f"delta BIC {ev['delta_bic']:.1f} > {rule.delta_bic_min:g}; the RMSE drops only "
                         f"{100 * gain:.1f} % but {shift['name']} moves {shift['half_widths']:.1f} times its 95 % "
                         f"half-width (> {rule.param_shift_min:g})")
        return ev
    if gain <= rule.rmse_gain_min:
        ev.update(passes=False, criterion="rmse",
                  reason=f"delta BIC {ev['delta_bic']:.1f} but the RMSE drops only {100 * gain:.1f} % "
                         f"(<= {100 * rule.rmse_gain_min:g} %)")
        return ev
    ev.update(passes=True, criterion="bic", reason=f"delta BIC {ev['delta_bic']:.1f} > {rule.delta_bic_min:g}, "
                                                    f"RMSE {100 * gain:.1f} % lower")
    return ev


def _param_shift(before: LoopState, after: LoopState) -> dict | None:
    """The declared parameter the candidate moves most, in 95 % half-widths (the larger of the
    two fits'), where the stage's fits report ``values`` and ``ci95`` (flat name -> value,
    [low, high]); None otherwise.  Where the fit names its ``declared_params`` (the quantities
    the stage reports: a tissue's law, not the nuisance parameters of the effects already in
    the model), only those count."""
    vb, va = getattr(before.fit, "values", None), getattr(after.fit, "values", None)
    cb, ca = getattr(before.fit, "ci95", None), getattr(after.fit, "ci95", None)
    if not (isinstance(vb, Mapping) and isinstance(va, Mapping) and isinstance(cb, Mapping) and isinstance(ca, Mapping)):
        return None
    declared = getattr(before.fit, "declared_params", None)
    best = None
    for k, x0 in vb.items():
        if k not in va or k not in cb or k not in ca or (declared is not None and k not in declared):
            continue
        try:
            hw = max(0.5 * (float(cb[k][1]) - float(cb[k][0])), 0.5 * (float(ca[k][1]) - float(ca[k][0])))
            d = abs(float(va[k]) - float(x0))
        except (TypeError, ValueError, IndexError):
            continue
        if not (np.isfinite(hw) and hw > 0 and np.isfinite(d)):
            continue
        if best is None or d / hw > best["half_widths"]:
            best = {"name": k, "before": float(x0), "after": float(va[k]), "half_widths": d / hw}
    return best


def _heldout_check(ev: dict, before: LoopState, after: LoopState, fitter: "_Fitter", rule: SelectionRule) -> bool:
    """Add the held-out error to a candidate that passed in sample; does it pass that too?"""
    h0 = fitter.heldout(before)
    if h0 is None or ev["criterion"] == "outside":
        return True
    h1 = fitter.heldout(after)
    hgain = (h0 - h1) / h0 if h0 > 0 else 0.0
    ok = hgain > rule.heldout_gain_min
    ev.update(heldout_rmse_before=h0, heldout_rmse_after=h1, heldout_gain=hgain, passes=bool(ok), criterion="heldout",
              reason=(f"held-out RMSE {h0:.4g} -> {h1:.4g} ({-100 * hgain:+.1f} %), "
                      f"{'more' if ok else 'not more'} than {100 * rule.heldout_gain_min:g} % lower; "
                      f"delta BIC {ev['delta_bic']:.1f}, RMSE {100 * ev['rmse_gain']:.1f} % lower"))
    return ok


def _preference(passing: list, tie: float) -> list:
    """Candidates in the order the loop prefers them: outside evidence first, then by
    delta BIC; among candidates within ``tie`` of the strongest, the one that adds the fewest
    parameters (the data cannot tell them apart: the simpler explanation), then the one listed
    first.  A two-term Ogden truth had model-order (2 parameters, delta BIC 74.6) and
    contact-offset (a toe: 4, 70.7) tied; the stage's order kept the toe, and it turned alpha
    from -7.2 to +16.2 (mu 1656 Pa for 720)."""
    rest, order = list(passing), []
    while rest:
        best = max(rest, key=lambda t: t[0])
        outside, score, _ = best[0]
        close = [t for t in rest if t[0][0] == outside and t[0][1] >= score - tie]
        # fewest added parameters, then the earliest in the stage's order
        chosen = max(close, key=lambda t: (-int(t[3].get("added_params", 0) or 0), t[0][2]))
        order.append(chosen)
        rest.remove(chosen)
    return order


def run_loop(fit: Callable[[Any], Any], spec0, candidates: Sequence[Effect], *,
             heldout: Callable[[Any], float | Mapping] | None = None,
             covariates: Callable[[Any], Mapping] | Mapping | None = None,
             groups: Callable[[Any], Any] | Any = None,
             describe: Callable[[Any], str] = str,
             unit: str = "n",
             rule: SelectionRule = SelectionRule(),
             noise_rms: float | None = None,
             noise_ceiling: float | None = None,
             veto: Callable[[LoopState, LoopState], str | None] | None = None,
             max_steps: int = 10) -> LoopReport:
    """Close the loop on one stage's model (the rule is in the module docstring).

    Parameters
    ----------
    fit : callable ``spec -> result``
        Fits the model ``spec`` describes.  ``result`` has ``residuals`` (an array or a list
        of arrays, one per log / view, each in its natural order, in the stage's unit),
        ``params`` (a JSON-ready dict) and optionally ``n_params``, ``bic``, ``success``.
    spec0 : hashable
        The declared model.
    candidates : sequence of Effect
        The effects this stage may add, in the order they are tried.
    heldout : callable ``spec -> float | {"rmse": float, ...}``, optional
        Held-out RMSE of a model (e.g. over held-out blocks, or leaving one series out); when
        given it is part of the rule.
    covariates : mapping or callable ``result -> mapping``, optional
        Name -> array (same length as the concatenated residual) for the structure tests.
    groups : array or callable ``result -> array``, optional
        Series labels for the structure tests; default: the index of each residual array.
    describe : callable ``spec -> str``
        The model's name in the report.
    unit : str
        Unit suffix of the error names (``rmse_n``, ``rmse_px``).
    noise_rms : float, optional
        The measurement noise level, estimated independently of any model (e.g. from
        sample-to-sample differences), reported with the loop; a residual whose RMSE is at or
        below it is noise (only effects with outside evidence are tried); above it, only the
        residual's structure tests decide.
    noise_ceiling : float, optional
        The largest RMSE the measurement noise can plausibly give (from known bounds on each
        source of error); a residual whose RMSE is above it is not noise, whatever its
        structure tests say (a dozen numbers show no pattern: four references at a
        registration frame), so the candidates are weighed on the fit (delta BIC and the
        RMSE gain) as well as on outside evidence.
    veto : callable ``(before, after) -> str | None``, optional
        The stage's physical plausibility check of a candidate's fit: a reason (the candidate
        is turned down whatever its evidence) or None.  For what no amount of residual can
        justify: an added effect whose own parameter ends at the edge of its physical range
        (fit-ogden: a Prony g of 0.98) is standing in for something else.

    Returns
    -------
    LoopReport
    """
    fitter = _Fitter(fit, heldout, covariates, groups, describe, rule.alpha)
    state = fitter.state(spec0)
    report = LoopReport(unit=unit, rule=rule, baseline=state, noise_rms=noise_rms, noise_ceiling=noise_ceiling)
    for _ in range(max_steps):
        # Below the measured noise level there is nothing left to explain.  Just above it the
        # residual is noise only if its pattern says so too: a structured residual (a second
        # relaxation time, a machine's compliance) can be a few % of the RMSE and still bias
        # the parameters far outside their intervals; the candidates still need delta BIC,
        # the RMSE gain and the held-out check.
        # (at the noise level, a residual whose pattern is overwhelmingly not noise, p below
        # STRUCTURE_OVER_FLOOR_P, is still looked at: the noise level is itself an estimate, and
        # a load cell's slow drift of 1 % of the peak force fits within it)
        at_floor = (noise_rms is not None and state.rmse <= noise_rms
                    and not float(state.structure.get("p_min", 1.0)) < STRUCTURE_OVER_FLOOR_P)
        above_ceiling = noise_ceiling is not None and state.rmse > noise_ceiling
        noise = (state.structure["noise"] or at_floor) and not above_ceiling
        round_: list[dict] = []
        passing: list[tuple[tuple, Effect, LoopState, dict]] = []
        for eff in candidates:
            spec1 = eff.augment(state.spec)
            if spec1 is None:
                continue
            if noise and eff.evidence is None:
                round_.append({"effect": eff.name, "passes": False, "reason": "the residual is already noise"})
                continue
            try:
                cand = fitter.state(spec1)
            except _CANDIDATE_FAILURES as exc:
                log.warning("loop: fitting %s failed: %s", eff.name, exc)
                round_.append({"effect": eff.name, "passes": False, "reason": f"fit failed: {exc}"})
                continue
            ev = _weigh(eff, state, cand, rule, noise)
            if ev["passes"] and veto is not None:
                why = veto(state, cand)
                if why:
                    ev.update(passes=False, criterion="veto", reason=f"{ev['reason']}; turned down: {why}")
            round_.append({"effect": eff.name, **ev})
            if ev["passes"]:
                outside = ev["criterion"] == "outside"
                score = ev["outside"]["delta_bic"] if outside else ev["delta_bic"]
                passing.append(((outside, score, -len(passing)), eff, cand, round_[-1]))
            else:
                log.info("loop: %s: %s", eff.name, ev["reason"])
        # The held-out check, costly, runs in order of preference until a candidate passes.
        kept = None
        # physical effects first; a catch-all correction only where none of them passes
        order = (_preference([t for t in passing if not t[1].catch_all], rule.tie_delta_bic)
                 + _preference([t for t in passing if t[1].catch_all], rule.tie_delta_bic))
        for j, (_, eff, cand, entry) in enumerate(order):
            if kept is not None:
                entry.update(passes=None, reason=entry["reason"] + f"; not weighed further: {kept[0].name} was kept")
                continue
            try:
                ok = _heldout_check(entry, state, cand, fitter, rule)
            except _CANDIDATE_FAILURES as exc:      # the held-out refits can fail too
                entry.update(passes=False, reason=f"held-out fit failed: {exc}")
                ok = False
            log.info("loop: %s: %s", eff.name, entry["reason"])
            if ok:
                kept = (eff, cand, entry)
                if j + 1 < len(order):
                    nxt = order[j + 1]
                    entry["runner_up"] = {"effect": nxt[1].name, "delta_bic": nxt[3]["delta_bic"]}
        report.tried.append(round_)
        if kept is None:
            floor = (" (its RMSE at or below the measured noise level)" if at_floor
                     else f" (its RMSE above the {noise_ceiling:.3g} noise can give)" if above_ceiling else "")
            report.stopped_because = (f"the residual is noise{floor} and no effect has outside evidence" if noise
                                      else f"the residual has structure no candidate explains with strong evidence{floor}"
                                      if round_ else "no candidate can augment the model further")
            break
        eff, cand, entry = kept
        ev = {k: v for k, v in entry.items() if k != "effect"}
        report.steps.append(LoopStep(effect=eff, evidence=ev, before=state, after=cand))
        state = cand
    else:
        report.stopped_because = f"reached max_steps={max_steps}"
    return report
