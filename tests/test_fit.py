"""The fit engine on synthetic logs with known truth and on Treloar's real rubber data."""

import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bsipipe.mechanics.contact import detect_contact
from bsipipe.mechanics.fit import (ForceModelSpec, LogData, fit_logs, fit_tables, median_relative_errors,
                                   parameter_names, predict_force)
from bsipipe.mechanics.hyperelastic import get_law, ogden_nominal_stress
from bsipipe.synth.machine_log import synth_compression_log

TRELOAR = Path(__file__).parent / "data" / "real" / "treloar1944"


def _log(frame, truth, name="log", contact_mm=None):
    """The log as fit-ogden prepares it: the detected contact with its standard deviation and the
    load noise (so the fit refines the contact), or ``contact_mm`` given exactly (held)."""
    sd = noise = None
    if contact_mm is None:
        c = detect_contact(frame["time_s"], frame["extension_mm"], frame["load_n"])
        contact_mm, sd, noise = c.displacement_mm, c.displacement_sd_mm, c.force_noise_n
    return LogData(name, frame["time_s"], frame["extension_mm"], frame["load_n"], truth["diameter_mm"],
                   truth["height_mm"], contact_mm, truth["speed_mm_s"], sd, noise)


# --- (a) the sheep-brain log: accuracy and interval coverage --------------------------------

def test_sheep_brain_log_recovers_mu_and_alpha_with_covering_intervals():
    """mu = 720 Pa, alpha = -4.7; 18 x 12 mm, 4 mm/min, 0.5 mm gap, 1 mN noise, 10 Hz (616 samples).

    The default model, as ``fit-ogden`` runs it: the contact refined within the detector's
    standard deviation (a Gaussian prior): the detector's scatter (about 7 um here) alone
    moves mu by about 0.7 %, so an interval that ignores it cannot claim 95 %.  Printed for
    comparison: the same fits with the contact held at the detected point
    (``refine_contact=False``).
    """
    n_rep = 50
    hits = {"mu_pa": 0, "alpha": 0}
    hits_fixed = {"mu_pa": 0, "alpha": 0}
    errs, errs_fixed = [], []
    truth_p = {"mu_pa": 720.0, "alpha": -4.7}
    for seed in range(n_rep):
        frame, truth = synth_compression_log(mu_pa=720.0, alpha=-4.7, seed=1000 + seed)
        assert len(frame) == 616
        lg = _log(frame, truth)
        res = fit_logs([lg], ForceModelSpec())
        fixed = fit_logs([lg], ForceModelSpec(refine_contact=False))
        assert res.success and "contact_offset_mm" in res.params and "contact_offset_mm" not in fixed.params
        errs_fixed.append(fixed.params["mu_pa"] / 720.0 - 1.0)
        for k, v in truth_p.items():
            hits[k] += res.ci95[k][0] <= v <= res.ci95[k][1]
            hits_fixed[k] += fixed.ci95[k][0] <= v <= fixed.ci95[k][1]
        errs.append((res.params["mu_pa"] / 720.0 - 1.0, res.params["alpha"] + 4.7))
    errs = np.array(errs)
    print(f"\nsheep-brain log, {n_rep} seeds: max |mu error| {100 * np.abs(errs[:, 0]).max():.2f} %, "
          f"max |alpha error| {np.abs(errs[:, 1]).max():.4f}; 95 % CI coverage mu {hits['mu_pa']}/{n_rep}, "
          f"alpha {hits['alpha']}/{n_rep} (contact held at the detected point: mu {hits_fixed['mu_pa']}/{n_rep}, "
          f"alpha {hits_fixed['alpha']}/{n_rep}, max |mu error| {100 * np.abs(errs_fixed).max():.2f} %)")
    assert np.all(np.abs(errs[:, 0]) < 0.01)
    assert np.all(np.abs(errs[:, 1]) < 0.05)
    assert hits["mu_pa"] >= 45 and hits["alpha"] >= 45


def test_joint_fit_of_a_long_and_a_short_log_has_calibrated_intervals():
    """A 616-sample and a 100-sample log fitted jointly: the short one is weighted up (weight
    squared 3.6) to count as much, but its samples are no less noisy, so the intervals are the
    weighted estimator's sandwich (module docstring).  Over 40 seeds the mean standard error of
    mu must match mu's scatter (measured 2.07 vs 2.06 Pa; the plain s^2 (J^T J)^-1 gives 1.43
    and covers 33/40) to 25 % (the scatter of 40 draws is known to about 11 %), and the 95 %
    intervals cover 720 Pa at least 35 times (expected 38, binomial sd 1.4)."""
    mus, ses, hits = [], [], 0
    for seed in range(40):
        logs = []
        for name, kw in (("long", {"seed": 500 + seed}), ("short", {"n_points": 100, "seed": 900 + seed})):
            frame, truth = synth_compression_log(**kw)
            logs.append(_log(frame, truth, name))
        res = fit_logs(logs, ForceModelSpec())
        lo, hi = res.ci95["mu_pa"]
        mus.append(res.params["mu_pa"])
        ses.append((hi - lo) / 2 / 1.96)
        hits += lo <= 720.0 <= hi
    scatter = float(np.std(mus, ddof=1))
    print(f"\nlong + short log, 40 seeds: mu scatter {scatter:.2f} Pa, mean standard error {np.mean(ses):.2f} Pa, "
          f"coverage {hits}/40")
    assert abs(np.mean(ses) / scatter - 1.0) < 0.25
    assert hits >= 35


def test_bootstrap_intervals_agree_with_the_jacobian_on_a_5000_point_log():
    frame, truth = synth_compression_log(n_points=5000, seed=7)
    lg = _log(frame, truth, contact_mm=truth["contact_mm"])
    t0 = time.perf_counter()
    res = fit_logs([lg], ForceModelSpec())
    elapsed = time.perf_counter() - t0
    print(f"\n5000-point log, one-term Ogden: fit {elapsed:.3f} s, mu {res.params['mu_pa']:.2f} Pa, "
          f"alpha {res.params['alpha']:.4f}")
    boot = fit_logs([lg], ForceModelSpec(), bootstrap=200, seed=3)
    assert boot.bootstrap["n_ok"] == 200
    for k in ("mu_pa", "alpha"):
        w_jac = np.diff(boot.ci95[k])[0]
        w_boot = np.diff(boot.ci95_bootstrap[k])[0]
        print(f"  {k}: Jacobian {boot.ci95[k]}, bootstrap {boot.ci95_bootstrap[k]}")
        # 200 resamples estimate a 95 % width to about +-10 %; the two must agree to +-30 %.
        assert 0.7 < w_boot / w_jac < 1.3
    assert abs(res.params["mu_pa"] / 720 - 1) < 0.01 and abs(res.params["alpha"] + 4.7) < 0.05


# --- (b) Treloar 1944 ---------------------------------------------------------------------------

def _treloar_tables():
    out = []
    for tag, mode in (("UT", "uniaxial"), ("ET", "equibiaxial"), ("PS", "pure-shear")):
        a = np.loadtxt(TRELOAR / f"treloar1944_{tag}_stress_stretch_ChongranZhao.txt")
        out.append(pd.DataFrame({"stretch": a[:, 1], "nominal_stress_pa": a[:, 0] * 1e6, "mode": mode}))
    return out


def test_treloar_joint_ogden3_beats_ogden_1972_in_every_mode():
    tables = _treloar_tables()
    res = fit_tables(tables, "ogden3")
    assert res.success
    ours = median_relative_errors(res)
    # Ogden (1972) in W = sum mu_p / alpha_p (...); in 2 mu / alpha^2 (...) mu = mu_p alpha_p / 2.
    mu_p = np.array([0.63, 0.0012, -0.01]) * 1e6
    alpha = np.array([1.3, 5.0, -2.0])
    mus = mu_p * alpha / 2
    ogden = {}
    for t in tables:
        mode = t["mode"].iloc[0]
        p = ogden_nominal_stress(t["stretch"], mus, alpha, mode)
        ogden[mode] = float(np.median(np.abs(p - t["nominal_stress_pa"]) / t["nominal_stress_pa"]))
    print("\nTreloar 1944, median |relative error|:   this fit   Ogden 1972 (README: 3.2 / 4.5 / 2.8 %)")
    for mode in ours:
        print(f"  {mode:12s}                          {100 * ours[mode]:5.2f} %    {100 * ogden[mode]:5.2f} %")
    print("  params:", {k: round(v, 4) for k, v in res.params.items()})
    # Our reproduction of Ogden's errors matches the README's to its rounding.
    np.testing.assert_allclose([ogden[m] for m in ("uniaxial", "equibiaxial", "pure-shear")],
                               [0.032, 0.045, 0.028], atol=0.0006)
    for mode in ours:
        assert ours[mode] <= ogden[mode]


# --- each effect of the forward model, declared ------------------------------------------------

def test_baseline_drift_and_compliance_are_recovered_when_declared():
    """12 mN offset, 0.2 mN/s drift, 0.4 mm/N frame (0.2 mm of deflection at the peak load)."""
    truth_p = {"mu_pa": 720.0, "alpha": -4.7, "baseline_n": 0.012, "drift_n_per_s": 2e-4, "compliance_mm_per_n": 0.4}
    frame, truth = synth_compression_log(baseline_n=0.012, drift_n_per_s=2e-4, compliance_mm_per_n=0.4, seed=11)
    lg = _log(frame, truth, contact_mm=truth["contact_mm"])
    res = fit_logs([lg], ForceModelSpec(baseline_drift=True, compliance=True))
    p = res.params
    for k, v in truth_p.items():
        assert res.ci95[k][0] <= v <= res.ci95[k][1], k
    assert abs(p["mu_pa"] / 720 - 1) < 0.03 and abs(p["alpha"] + 4.7) < 0.15
    assert abs(p["compliance_mm_per_n"] / 0.4 - 1) < 0.25
    assert res.metrics["rmse_n"] < 1.1e-3                     # the noise, 1 mN
    # The model's implicit compliance relation holds at the solution: F = F_e(x - C F).
    f = predict_force(lg, res.spec, res.log_params(0)) - p["baseline_n"] - p["drift_n_per_s"] * lg.time_s
    delta = np.maximum(lg.displacement_mm - lg.contact_mm - p["compliance_mm_per_n"] * f, 0) / lg.height_mm
    fe = -ogden_nominal_stress(1 - delta, [p["mu_pa"]], [p["alpha"]]) * lg.area_m2
    np.testing.assert_allclose(f, fe, atol=1e-12)


def test_contact_offset_is_recovered_from_an_uneven_top():
    """An uneven top (the twin's toe: first touch at 0.5 mm, flat from 0.8 mm, true contact
    0.65 mm): ``contact_offset`` frees the contact and fits the toe's half-width c."""
    frame, truth = synth_compression_log(contact_offset_mm=0.15, noise_n=1e-3, seed=12)
    lg = _log(frame, truth)
    res = fit_logs([lg], ForceModelSpec(contact_offset=True))
    true_offset = truth["contact_mm"] - lg.contact_mm
    print(f"\nuneven top c = 0.15 mm: detected {lg.contact_mm:.4f} mm, shift {res.params['contact_offset_mm']:.4f} "
          f"(true {true_offset:.4f}), toe {res.params['contact_toe_mm']:.4f} mm {res.ci95['contact_toe_mm']}, "
          f"mu {res.params['mu_pa']:.1f} Pa, alpha {res.params['alpha']:.3f}")
    assert abs(res.params["contact_offset_mm"] - true_offset) < 0.02
    lo, hi = res.ci95["contact_toe_mm"]
    assert lo <= 0.15 <= hi
    assert abs(res.params["mu_pa"] / 720 - 1) < 0.02 and abs(res.params["alpha"] + 4.7) < 0.1


def test_contact_prior_is_a_pseudo_observation_of_the_shift():
    """The declared model's contact shift is held by one residual row w sigma r(shift / sd_c), so
    the cost is the data's plus sigma^2 rho(shift / sd_c), rho = 2 (sqrt(1 + z^2) - 1); a contact
    given exactly is not refined."""
    frame, truth = synth_compression_log(seed=16)
    lg = _log(frame, truth)
    res = fit_logs([lg], ForceModelSpec())
    shift = res.params["contact_offset_mm"]
    sse_data = float(np.sum(res.residuals[0] ** 2))
    z = shift / lg.contact_sd_mm
    prior = lg.force_noise_n ** 2 * 2.0 * (np.sqrt(1.0 + z * z) - 1.0)
    assert res.metrics["sse_weighted"] == pytest.approx(sse_data + prior, rel=1e-9)
    assert res.n_obs == len(res.residuals[0]) and res.n_params == 3
    assert parameter_names(ForceModelSpec(), [lg]) == ["mu_pa", "alpha", "contact_offset_mm"]
    known = _log(frame, truth, contact_mm=truth["contact_mm"])
    assert parameter_names(ForceModelSpec(), [known]) == ["mu_pa", "alpha"]
    assert "contact_offset_mm" not in fit_logs([known], ForceModelSpec()).params
    with pytest.raises(ValueError):
        LogData("x", lg.time_s, lg.displacement_mm, lg.force_n, 18.0, 12.0, 0.5, None, 0.01, None)


def test_two_speeds_fitted_jointly_with_two_prony_terms():
    """alpha = -6.3, Prony (0.4, 0.5 s), (0.3, 50 s), at 1 mm/s and 0.01 mm/s (411 samples each)."""
    prony = [(0.4, 0.5), (0.3, 50.0)]
    logs = []
    for i, (speed, hz) in enumerate(((60.0, 100.0), (0.6, 1.0))):
        frame, truth = synth_compression_log(mu_pa=1000.0, alpha=-6.3, prony=prony, speed_mm_min=speed,
                                             rate_hz=hz, seed=20 + i)
        logs.append(_log(frame, truth, f"v{i}", contact_mm=truth["contact_mm"]))
    res = fit_logs(logs, ForceModelSpec(prony=2))
    p = res.params
    assert res.success
    assert abs(p["mu_pa"] / 1000 - 1) < 0.03 and abs(p["alpha"] + 6.3) < 0.1
    terms = sorted(p["prony"], key=lambda t: t["tau_s"])
    assert abs(terms[0]["g"] - 0.4) < 0.03 and abs(terms[1]["g"] - 0.3) < 0.03
    assert abs(np.log(terms[0]["tau_s"] / 0.5)) < 0.2 and abs(np.log(terms[1]["tau_s"] / 50)) < 0.2
    assert res.metrics["rmse_n"] < 1.1e-3
    # Each log counts equally: w_i^2 n_i is the same for both.
    totals = [fr["weight"].iloc[0] ** 2 * fr["fitted"].sum() for fr in res.fitted]
    assert totals[0] == pytest.approx(totals[1])


def test_two_term_truth_needs_two_terms():
    frame, truth = synth_compression_log(mus_pa=[500.0, 300.0], alphas=[-8.0, 4.0], seed=13)
    lg = _log(frame, truth, contact_mm=truth["contact_mm"])
    one = fit_logs([lg], ForceModelSpec())
    two = fit_logs([lg], ForceModelSpec(law="ogden2"))
    assert two.bic < one.bic - 10
    # Compression to 30 % alone does not pin both terms (other pairs fit as well); the fit
    # must reach the noise and the model's force must follow the truth's.
    assert two.metrics["rmse_n"] < 1.1e-3 < one.metrics["rmse_n"]
    f = predict_force(lg, two.spec, two.log_params(0))
    assert np.sqrt(np.mean((f - truth["force_true_n"]) ** 2)) < 3e-4
    assert two.params["mu1_pa"] >= two.params["mu2_pa"]             # terms in canonical order


def test_max_strain_cut_and_names():
    frame, truth = synth_compression_log(seed=14)
    lg = _log(frame, truth, contact_mm=truth["contact_mm"])
    res = fit_logs([lg], ForceModelSpec(), max_strain=0.15)
    assert np.all(lg.nominal_strain()[res.used[0]] <= 0.15)
    assert res.n_obs == int(res.used[0].sum()) < len(frame)
    assert abs(res.params["mu_pa"] / 720 - 1) < 0.02
    assert parameter_names(ForceModelSpec(baseline_drift=True, compliance=True), 2) == [
        "mu_pa", "alpha", "baseline_n[0]", "drift_n_per_s[0]", "baseline_n[1]", "drift_n_per_s[1]",
        "compliance_mm_per_n"]
    assert set(res.metrics) >= {"rmse_n", "nrmse", "max_rel_err", "aic", "bic"}
    with pytest.raises(ValueError):
        ForceModelSpec(law="ogden2", boundary="no-slip")


@pytest.mark.parametrize("law,params,modes", [
    ("neo-hookean", {"mu_pa": 5e5}, ("uniaxial", "simple-shear")),
    ("mooney-rivlin", {"c10_pa": 2e5, "c01_pa": 5e4}, ("uniaxial", "equibiaxial")),
    ("ogden2", {"mu1_pa": 3e5, "alpha1": 1.5, "mu2_pa": 2e4, "alpha2": -3.0}, ("uniaxial", "pure-shear", "equibiaxial")),
])
def test_tables_recover_exact_parameters(law, params, modes):
    lw = get_law(law)
    vec = [params[k] for k in lw.param_names]
    tables = []
    for m in modes:
        s = np.linspace(0.3, 1.0, 12) if m == "simple-shear" else np.linspace(1.05, 3.0, 15)
        tables.append(pd.DataFrame({"stretch": s, "nominal_stress_pa": lw.nominal_stress(s, vec, m), "mode": m}))
    res = fit_tables(tables, law)
    for k, v in params.items():
        assert res.params[k] == pytest.approx(v, rel=1e-5)
    assert res.metrics["rmse_pa"] < 1e-4 * max(abs(t["nominal_stress_pa"]).max() for t in tables)


def test_no_slip_boundary_is_fitted_through_the_fe_tables():
    """A bonded 18 x 12 mm cylinder (the FE tables themselves, so exact up to noise): the
    homogeneous formula overstates mu; the no-slip model recovers it."""
    frame, truth = synth_compression_log(boundary="no-slip", noslip_mesh_radial=None, seed=15)
    lg = _log(frame, truth, contact_mm=truth["contact_mm"])
    hom = fit_logs([lg], ForceModelSpec())
    bonded = fit_logs([lg], ForceModelSpec(boundary="no-slip"))
    bias = hom.params["mu_pa"] / 720 - 1
    print(f"\nno-slip data, homogeneous fit: mu {hom.params['mu_pa']:.1f} Pa ({100 * bias:+.1f} %), "
          f"alpha {hom.params['alpha']:.3f}; no-slip fit: mu {bonded.params['mu_pa']:.2f} Pa, "
          f"alpha {bonded.params['alpha']:.4f}")
    assert bias > 0.2                                   # README: force ratio 1.2-1.9 for H/D 0.5-1
    assert abs(bonded.params["mu_pa"] / 720 - 1) < 0.01 and abs(bonded.params["alpha"] + 4.7) < 0.05
    assert bonded.metrics["rmse_n"] < 1.1e-3 < hom.metrics["rmse_n"]


def _ogden2_mixed(noise_n: float, seed: int):
    from bsipipe.synth.machine_log import synth_compression_log
    frame, truth = synth_compression_log(mus_pa=[500.0, 220.0], alphas=[-8.0, 2.0], max_strain=0.4,
                                         noise_n=noise_n, seed=seed)
    t, d, f = (frame[c].to_numpy(float) for c in ("time_s", "extension_mm", "load_n"))
    c = detect_contact(t, d, f)
    lg = LogData("o2", t, d, f, truth["diameter_mm"], truth["height_mm"], c.displacement_mm, truth["speed_mm_s"],
                 c.displacement_sd_mm, c.force_noise_n)
    return fit_logs([lg], ForceModelSpec(law="ogden2"))


def test_two_term_ogden_with_exponents_of_opposite_signs():
    """mu 500 / 220 Pa, alpha -8 / +2 to 40 % strain (the probe's case): each exponent keeps
    the sign it starts with, and the grid's mixed-sign starts (-6.5 / +20, -9 / +13) led
    elsewhere, so the fit had ended at -8.03 / -0.05 (the second exponent at the small end of
    its range, wanting to cross zero), RMSE 17 times the noise; over 16 noise seeds the 95 %
    intervals held the truth 0-6 times.  An exponent stuck there is now tried with its sign
    turned: at 0.01 mN noise the truth is found to 0.3 %, and at 1 mN over 6 seeds the
    intervals hold every parameter at least 5 times (10 of 10 over seeds 100-109)."""
    r = _ogden2_mixed(1e-5, 1)
    v = r.values
    print({k: round(x, 4) for k, x in v.items()}, r.metrics["rmse_n"])
    assert r.metrics["rmse_n"] < 1.2e-5 and abs(v["alpha2"] - 2.0) < 0.02 and abs(v["mu2_pa"] - 220.0) < 1.0
    truth = {"mu1_pa": 500.0, "alpha1": -8.0, "mu2_pa": 220.0, "alpha2": 2.0}
    hits = dict.fromkeys(truth, 0)
    for seed in range(100, 106):
        r = _ogden2_mixed(1e-3, seed)
        assert r.values["alpha2"] > 0 and r.metrics["rmse_n"] < 1.1e-3
        for k, x in truth.items():
            hits[k] += r.ci95[k][0] <= x <= r.ci95[k][1]
    print(hits)
    assert min(hits.values()) >= 5
