"""The loop framework on a toy problem whose answer is known (no mechanics).

Toy stage: two "logs" of a signal ``y = a + b x`` sampled along a triangular sweep ``x(t)``
with Gaussian noise (sigma 0.05).  Hidden effects a declared straight line lacks:
``curvature`` (``c x^2``), ``drift`` (``k t``, the sweep goes up and down so ``t`` and ``x``
differ), ``kink`` (a slope change above x = 0.6).  The fit is linear least squares.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, replace

import numpy as np
import pytest

from bsipipe.loop import Effect, SelectionRule, residual_structure, run_loop
from bsipipe.report.loop_report import LoopSeries, loop_figure, loop_markdown

SIGMA = 0.05
N_PER_LOG = 800


@dataclass(frozen=True)
class ToySpec:
    curvature: bool = False
    drift: bool = False
    kink: bool = False


@dataclass
class ToyFit:
    residuals: list
    params: dict
    n_params: int
    coef: np.ndarray


def make_logs(seed, curvature=0.0, drift=0.0, kink=0.0, n_logs=2):
    rng = np.random.default_rng(seed)
    logs = []
    for i in range(n_logs):
        t = np.linspace(0.0, 1.0, N_PER_LOG)
        x = 1.0 - np.abs(2.0 * t - 1.0) + 0.1 * i      # up then down; logs a little apart
        y = 0.3 + 1.2 * x + curvature * x**2 + drift * t + kink * np.clip(x - 0.6, 0, None)
        logs.append({"t": t, "x": x, "y": y + rng.normal(0.0, SIGMA, len(t))})
    return logs


def design(spec: ToySpec, log):
    cols, names = [np.ones_like(log["x"]), log["x"]], ["a", "b"]
    if spec.curvature:
        cols.append(log["x"] ** 2); names.append("c")
    if spec.drift:
        cols.append(log["t"]); names.append("k")
    if spec.kink:
        cols.append(np.clip(log["x"] - 0.6, 0, None)); names.append("kink")
    return np.column_stack(cols), names


def fit_toy(logs, spec: ToySpec) -> ToyFit:
    a = np.vstack([design(spec, lg)[0] for lg in logs])
    y = np.concatenate([lg["y"] for lg in logs])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    names = design(spec, logs[0])[1]
    res = [lg["y"] - design(spec, lg)[0] @ coef for lg in logs]
    return ToyFit(res, {k: float(v) for k, v in zip(names, coef)}, len(coef), coef)


def heldout_toy(logs, spec):
    """Leave-one-log-out RMSE."""
    sq = []
    for i in range(len(logs)):
        f = fit_toy([lg for j, lg in enumerate(logs) if j != i], spec)
        sq.append((logs[i]["y"] - design(spec, logs[i])[0] @ f.coef) ** 2)
    return float(np.sqrt(np.mean(np.concatenate(sq))))


EFFECTS = [
    Effect("curvature", "the response stiffens with x", "U-shaped residual against x",
           lambda s: replace(s, curvature=True), ("c",)),
    Effect("drift", "the sensor drifts in time", "residual correlates with time, not with x",
           lambda s: replace(s, drift=True), ("k",)),
    Effect("kink", "a second mechanism engages at x = 0.6", "residual bends above x = 0.6",
           lambda s: replace(s, kink=True), ("kink",)),
]


def covariates(logs):
    return {"time": np.concatenate([lg["t"] for lg in logs]), "x": np.concatenate([lg["x"] for lg in logs])}


def loop_on(logs, heldout=False, candidates=EFFECTS, **kw):
    return run_loop(lambda s: fit_toy(logs, s), ToySpec(), candidates,
                    heldout=(lambda s: heldout_toy(logs, s)) if heldout else None,
                    covariates=covariates(logs), unit="y", **kw)


# --- residual_structure ------------------------------------------------------------------


def test_white_noise_is_noise_across_seeds():
    verdicts = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        e = [rng.normal(size=600), rng.normal(size=600)]
        t = np.tile(np.arange(600.0), 2)
        verdicts.append(residual_structure(e, {"time": t, "segment": np.repeat([0, 1, 2], 400)})["noise"])
    print(f"white noise judged structured in {20 - sum(verdicts)} of 20 seeds")
    assert all(verdicts)


def test_autocorrelated_residual_is_structure():
    rng = np.random.default_rng(1)
    e = np.zeros(3000)
    w = rng.normal(size=3000)
    for i in range(1, 3000):
        e[i] = 0.3 * e[i - 1] + w[i]
    rs = residual_structure(e)
    print(f"AR(1) rho=0.3: r1 = {rs['tests']['lag1_autocorrelation']['r1']:.3f}, p_min = {rs['p_min']:.2g}")
    assert not rs["noise"]
    # r1 has standard error 1/sqrt(3000) = 0.018 about rho
    assert abs(rs["tests"]["lag1_autocorrelation"]["r1"] - 0.3) < 3 / np.sqrt(3000)


def test_u_shaped_dependence_found_by_binned_test_not_correlation():
    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, 4000)                       # shuffled order: no serial structure
    e = 0.5 * (x**2 - 1 / 3) + rng.normal(size=4000)
    t = residual_structure(e, {"x": x})["tests"]["covariate:x"]
    print(f"U shape: Pearson p = {t['p_r']:.2f}, binned ANOVA p = {t['p_bins']:.2g}")
    assert t["p_r"] > 0.01 and t["p_bins"] < 1e-6


def test_group_means_and_categorical_covariate():
    rng = np.random.default_rng(3)
    e = [rng.normal(size=500) + 0.3, rng.normal(size=500)]
    rs = residual_structure(e, {"specimen": np.repeat(np.array(["A", "B"]), 500)})
    assert rs["tests"]["group_means"]["p"] < 1e-6
    assert rs["tests"]["covariate:specimen"]["kind"] == "categorical" and not rs["noise"]


# --- run_loop ----------------------------------------------------------------------------


def test_no_hidden_effect_no_effect_added_20_seeds():
    added = {}
    for seed in range(20):
        rep = loop_on(make_logs(seed))
        if rep.effects:
            added[seed] = rep.effects
        assert rep.final.spec == ToySpec()
    print(f"false positives: {len(added)} of 20 seeds {added}")
    assert not added


@pytest.mark.parametrize("effect,kw,truth", [
    ("curvature", {"curvature": 0.4}, ("c", 0.4)),
    ("drift", {"drift": 0.15}, ("k", 0.15)),
    ("kink", {"kink": 0.8}, ("kink", 0.8)),
])
def test_hidden_effect_is_named_and_recovered(effect, kw, truth):
    rep = loop_on(make_logs(10, **kw))
    d = rep.to_dict()
    print(f"{effect}: effects {rep.effects}, rmse before {d['baseline']['rmse_y']:.4f}, "
          f"after {d['final']['rmse_y']:.4f}, noise {SIGMA}, {truth[0]} = {rep.final.params[truth[0]]:.4f} "
          f"(true {truth[1]})")
    assert rep.effects == [effect]
    assert d["final"]["rmse_y"] < min(1.5 * SIGMA, d["baseline"]["rmse_y"])
    assert rep.final.structure["noise"]
    # least-squares standard error of each coefficient here is below 0.02
    assert abs(rep.final.params[truth[0]] - truth[1]) < 0.06
    assert abs(rep.final.params["b"] - 1.2) < 0.06


def test_two_hidden_effects_both_found_with_heldout():
    logs = make_logs(11, curvature=0.4, drift=0.15)
    rep = loop_on(logs, heldout=True)
    steps = rep.to_dict()["steps"]
    for s in steps:
        ev = s["evidence"]
        print(f"{s['effect']}: rmse {s['rmse_y_before']:.4f} -> {s['rmse_y_after']:.4f}, "
              f"held-out {ev['heldout_rmse_before']:.4f} -> {ev['heldout_rmse_after']:.4f}")
        assert ev["criterion"] == "heldout" and ev["passes"]
    assert sorted(rep.effects) == ["curvature", "drift"]
    assert rep.final.rmse < 1.5 * SIGMA


def test_heldout_rejects_an_effect_that_only_fits_one_log():
    # Drift present in log 0 only, opposite in log 1: the joint fit gains nothing a held-out log confirms.
    logs = make_logs(12)
    logs[0]["y"] = logs[0]["y"] + 0.05 * logs[0]["t"]
    logs[1]["y"] = logs[1]["y"] - 0.05 * logs[1]["t"]
    rep = loop_on(logs, heldout=True)
    assert "drift" not in rep.effects


def test_outside_evidence_adds_and_vetoes():
    logs = make_logs(13)                        # residual is noise
    for delta, expect in ((40.0, ["kink"]), (-40.0, [])):
        kink = replace(EFFECTS[2], evidence=lambda b, a, d=delta: {"delta_bic": d, "source": "camera"})
        rep = loop_on(logs, candidates=[EFFECTS[0], kink])
        assert rep.effects == expect
    # with a hidden kink, evidence against it vetoes it whatever the residual says
    kink = replace(EFFECTS[2], evidence=lambda b, a: {"delta_bic": -40.0})
    rep = loop_on(make_logs(14, kink=0.8), candidates=[kink])
    assert rep.effects == [] and not rep.final.structure["noise"]
    assert "no candidate" in rep.stopped_because


def test_threshold_is_the_stated_rule():
    assert SelectionRule().delta_bic_min == 10.0
    # a rule that demands more evidence than the data hold keeps nothing
    rep = loop_on(make_logs(15, curvature=0.4), rule=SelectionRule(delta_bic_min=1e9))
    assert rep.effects == []


def test_report_shape_and_renderers():
    logs = make_logs(16, curvature=0.4, drift=0.15)
    rep = loop_on(logs)
    d = rep.to_dict()
    assert set(d) >= {"baseline", "steps", "final", "residual_structure"}
    for s in d["steps"]:
        assert {"effect", "evidence", "rmse_y_before", "rmse_y_after", "params"} <= set(s)
    assert d["final"]["rmse_y"] == pytest.approx(d["steps"][-1]["rmse_y_after"])
    md = loop_markdown(d, title="toy")
    assert "| step | effect | parameters | RMSE before (y) | RMSE after (y) | evidence |" in md
    assert all(f"`{e}`" in md for e in rep.effects)
    series = []
    for i, lg in enumerate(logs):
        before = lg["y"] - rep.baseline.fit.residuals[i]
        after = lg["y"] - rep.final.fit.residuals[i]
        series.append(LoopSeries(f"log {i}", lg["t"], lg["y"], before, after, "t", "y"))
    fig = loop_figure(series, title="toy")
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    assert buf.getvalue()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ties_go_to_the_effect_listed_first_and_the_runner_up_is_reported():
    logs = make_logs(17, curvature=0.4)
    alias = replace(EFFECTS[0], name="curvature-alias")          # the same augmentation, listed second
    for order in ([EFFECTS[0], alias], [alias, EFFECTS[0]]):
        rep = loop_on(logs, candidates=order)
        assert rep.effects == [order[0].name]
        assert rep.to_dict()["steps"][0]["evidence"]["runner_up"]["effect"] == order[1].name


def test_a_catch_all_yields_to_a_physical_effect_that_passes():
    """A model-free correction listed first, explaining as much: the physical effect is kept
    (the catch-all would take its place, and with it what the physical model identifies)."""
    logs = make_logs(17, curvature=0.4)
    spline = replace(EFFECTS[0], name="spline", catch_all=True)
    rep = loop_on(logs, candidates=[spline, EFFECTS[0]])
    assert rep.effects == [EFFECTS[0].name]
    # alone, the catch-all is kept
    assert loop_on(logs, candidates=[spline]).effects == ["spline"]


def test_a_residual_at_the_measured_noise_level_stops_the_loop():
    logs = make_logs(18, curvature=0.4)
    # noise_rms is the measurement noise, known independently of any model
    rep = run_loop(lambda s: fit_toy(logs, s), ToySpec(), EFFECTS, covariates=covariates(logs), unit="y",
                   noise_rms=SIGMA)
    assert rep.effects == ["curvature"]
    assert rep.stopped_because.startswith("the residual is noise")
    assert all(t["reason"] == "the residual is already noise" for t in rep.tried[-1])
    assert rep.to_dict()["residual_structure"]["rmse_over_noise"] < 1.05
    # a residual at or below the measured noise is noise whatever its tests say: nothing is
    # tried on the residual alone
    floor = 1.001 * rep.final.rmse
    rep = run_loop(lambda s: fit_toy(logs, s), ToySpec(), EFFECTS, covariates=covariates(logs), unit="y",
                   noise_rms=floor)
    assert rep.effects == ["curvature"]
    assert "at or below the measured noise level" in rep.stopped_because
    assert all(t["reason"] == "the residual is already noise" for t in rep.tried[-1])
