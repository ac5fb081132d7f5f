"""fit-ogden's loop on synthetic machine logs that hide an effect the command line does not declare.

Every log comes from the seeded twin (:func:`bsipipe.synth.machine_log.synth_compression_log`):
an 18 x 12 mm cylinder at 4 mm/min unless stated, 0.5 mm pre-contact gap, load noise
``NOISE_N`` = 1 mN, the contact found by the detector (as the command does).  The declared
model is always one-term Ogden, frictionless, no effects.

Tolerances (from the noise: at 1 mN on these logs the fits' 95 % intervals are about
+-0.5 % on mu and +-0.02 on alpha; the bounds below leave room for the detector's contact
scatter and the effects' correlation with the tissue parameters):

- the error after the loop within 1.5x the noise RMS;
- mu within 2 %, alpha within 0.1 (one-term truths);
- Prony fractions g within 0.03, relaxation times within 20 %;
- two-term truth (terms are not identifiable one by one from one uniaxial ramp): the fitted
  nominal stress within 1 % of the true one over strains 5-30 %.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from bsipipe.mechanics.contact import detect_contact
from bsipipe.mechanics.effects import WidthSeries, close_loop_logs
from bsipipe.mechanics.fit import ForceModelSpec, LogData, fit_logs
from bsipipe.mechanics.hyperelastic import get_law, ogden_nominal_stress
from bsipipe.synth.machine_log import synth_compression_log

NOISE_N = 1e-3
DECLARED = ForceModelSpec()


def make_log(name="log", **kw):
    frame, truth = synth_compression_log(noise_n=NOISE_N, **kw)
    t, d, f = (frame[c].to_numpy(float) for c in ("time_s", "extension_mm", "load_n"))
    contact = detect_contact(t, d, f)
    # As the command: the detector's standard deviation and noise, so every fit refines the contact.
    return LogData(name, t, d, f, truth["diameter_mm"], truth["height_mm"], contact.displacement_mm,
                   truth["speed_mm_s"], contact.displacement_sd_mm, contact.force_noise_n), truth


def summary(rep) -> str:
    d = rep.to_dict()
    b = d["baseline"]["params"]
    lines = [f"effects {rep.effects}; rmse_n before {d['baseline']['rmse_n']:.3e}, after {d['final']['rmse_n']:.3e} "
             f"(noise {NOISE_N:.1e}; before/noise {d['baseline']['rmse_n'] / NOISE_N:.2f}, "
             f"after/noise {d['final']['rmse_n'] / NOISE_N:.2f}); declared model alone: mu {b['mu_pa']:.1f} Pa, "
             f"alpha {b['alpha']:.3f}"]
    for s in d["steps"]:
        lines.append(f"  + {s['effect']}: {s['rmse_n_before']:.3e} -> {s['rmse_n_after']:.3e} N, "
                     f"delta BIC {s['evidence']['delta_bic']:.1f} ({s['evidence']['criterion']})")
    return "\n".join(lines)


def check_one_term(params, truth, tol_mu=0.02, tol_alpha=0.1):
    e_mu = params["mu_pa"] / truth["params"]["mu_pa"] - 1.0
    e_a = params["alpha"] - truth["params"]["alpha"]
    print(f"  mu {params['mu_pa']:.1f} Pa (true {truth['params']['mu_pa']:.0f}, {100 * e_mu:+.2f} %), "
          f"alpha {params['alpha']:.3f} (true {truth['params']['alpha']}, {e_a:+.3f})")
    assert abs(e_mu) < tol_mu and abs(e_a) < tol_alpha


def check_prony(params, truth):
    fit = sorted(params["prony"], key=lambda p: p["tau_s"])
    true = sorted(truth["params"]["prony"], key=lambda p: p["tau_s"])
    assert len(fit) == len(true)
    for f, t in zip(fit, true):
        print(f"  g {f['g']:.3f} (true {t['g']}), tau {f['tau_s']:.2f} s (true {t['tau_s']})")
        assert abs(f["g"] - t["g"]) < 0.03
        assert abs(f["tau_s"] / t["tau_s"] - 1.0) < 0.2


# --- one hidden effect at a time -------------------------------------------------------------

@pytest.mark.slow
def test_hidden_viscoelastic_relaxation():
    lg, truth = make_log(prony=[(0.3, 2.0), (0.2, 30.0)], protocol="ramp-hold", hold_s=120.0, rate_hz=2.0, seed=1)
    rep = close_loop_logs([lg], DECLARED)
    print("\nviscoelastic-relaxation (ramp + 120 s hold):", summary(rep))
    assert rep.effects[:2] == ["viscoelastic-relaxation"] * 2
    assert rep.final.rmse < 1.5 * NOISE_N and rep.final.rmse < rep.baseline.rmse
    check_one_term(rep.final.params, truth)
    check_prony(rep.final.params, truth)


@pytest.mark.parametrize("seed", [2, 3])
def test_hidden_contact_offset(seed):
    """Uneven top, c = 0.5 mm: first touch at the gap, flat 1 mm of travel later, the true
    contact 0.5 mm past the gap.  The detector sees the force start early (about 0.08 mm past
    the gap); the declared model's contact prior cannot reach 0.4 mm, so the loop names
    ``contact-offset`` (a free contact and the toe)."""
    lg, truth = make_log(contact_offset_mm=0.5, rate_hz=5.0, seed=seed)
    rep = close_loop_logs([lg], DECLARED)
    print(f"\ncontact-offset c = 0.5 mm (detected {lg.contact_mm:.3f} +- {lg.contact_sd_mm:.3f} mm, "
          f"true {truth['contact_mm']:.3f} mm):", summary(rep))
    assert rep.effects == ["contact-offset"]
    assert rep.final.rmse < 1.5 * NOISE_N and rep.final.rmse < rep.baseline.rmse
    off, toe = rep.final.params["contact_offset_mm"], rep.final.params["contact_toe_mm"]
    true_off = truth["contact_mm"] - lg.contact_mm
    print(f"  shift {off:.4f} mm (true contact - detected {true_off:.4f} mm), toe {toe:.3f} mm (true 0.5)")
    # 0.02 mm: 0.17 % strain, where the force is below the noise (test_contact.py).
    assert abs(off - true_off) < 0.02
    check_one_term(rep.final.params, truth)


def test_small_toe_is_named_or_absorbed_by_the_contact_prior():
    """c = 0.2 mm: the declared model's refined contact (a prior of a few detector standard
    deviations' reach) takes most of the 0.02-0.07 mm between the detected and the true
    contact, so on some seeds the residual is at the noise already (its tests say noise, or
    no candidate lowers it by the rule's 5 %); where it is not, ``contact-offset`` is named.
    Either way mu and alpha are within the stated tolerance and nothing else is added."""
    named = 0
    for seed in range(4):
        lg, truth = make_log(contact_offset_mm=0.2, rate_hz=5.0, seed=seed)
        rep = close_loop_logs([lg], DECLARED)
        print(f"\nc = 0.2 mm, seed {seed} (detected {lg.contact_mm:.3f} +- {lg.contact_sd_mm:.3f} mm, "
              f"true {truth['contact_mm']:.3f}):", summary(rep))
        assert rep.effects in ([], ["contact-offset"])
        if not rep.effects:
            assert ("noise" in rep.stopped_because
                    or all(t["passes"] is False for t in rep.tried[-1])), rep.stopped_because
        named += bool(rep.effects)
        assert rep.final.rmse < 1.5 * NOISE_N
        check_one_term(rep.final.params, truth)
    assert named >= 1


def test_hidden_load_baseline_drift():
    lg, truth = make_log(baseline_n=0.01, drift_n_per_s=1e-4, protocol="ramp-unload", rate_hz=5.0, seed=3)
    rep = close_loop_logs([lg], DECLARED)
    print("\nload-baseline-drift (10 mN + 0.1 mN/s, ramp-unload):", summary(rep))
    assert rep.effects[0] == "load-baseline-drift"
    assert set(rep.effects) <= {"load-baseline-drift", "contact-offset"}
    assert rep.final.rmse < 1.5 * NOISE_N and rep.final.rmse < rep.baseline.rmse
    p = rep.final.params
    print(f"  baseline {1e3 * p['baseline_n']:.2f} mN (true 10), drift {1e3 * p['drift_n_per_s']:.4f} mN/s (true 0.1)")
    assert abs(p["baseline_n"] - 0.01) < 1e-3 and abs(p["drift_n_per_s"] - 1e-4) < 1e-5
    check_one_term(p, truth)


def test_hidden_machine_compliance():
    lg, truth = make_log(compliance_mm_per_n=1.0, rate_hz=5.0, seed=4)
    rep = close_loop_logs([lg], DECLARED)
    print("\nmachine-compliance (1 mm/N):", summary(rep))
    assert rep.effects == ["machine-compliance"]
    assert rep.final.rmse < 1.5 * NOISE_N and rep.final.rmse < rep.baseline.rmse
    c = rep.final.params["compliance_mm_per_n"]
    print(f"  compliance {c:.3f} mm/N (true 1.0)")
    assert abs(c - 1.0) < 0.2
    # On one ramp the compliance trades off against alpha: the fit's own 95 % interval of
    # alpha is +-0.19 here (+-0.02 without compliance), so alpha is held to 0.2.
    print(f"  95 % intervals: alpha {rep.final.fit.ci95['alpha']}, compliance {rep.final.fit.ci95['compliance_mm_per_n']}")
    check_one_term(rep.final.params, truth, tol_alpha=0.2)


def test_hidden_model_order():
    lg, truth = make_log(mus_pa=[500.0, 300.0], alphas=[-8.0, 4.0], rate_hz=5.0, seed=5)
    rep = close_loop_logs([lg], DECLARED)
    print("\nmodel-order (two-term truth mu = 500/300 Pa, alpha = -8/4):", summary(rep))
    assert rep.effects == ["model-order"]
    assert rep.final.rmse < 1.5 * NOISE_N and rep.final.rmse < rep.baseline.rmse
    lam = 1.0 - np.linspace(0.05, 0.3, 26)
    true = ogden_nominal_stress(lam, [500.0, 300.0], [-8.0, 4.0])
    law = get_law(rep.final.spec.law)
    fit = law.nominal_stress(lam, [rep.final.params[k] for k in law.param_names])
    base = ogden_nominal_stress(lam, [rep.baseline.params["mu_pa"]], [rep.baseline.params["alpha"]])
    err, err0 = np.max(np.abs(fit / true - 1.0)), np.max(np.abs(base / true - 1.0))
    print(f"  stress error over 5-30 % strain: one term {100 * err0:.2f} %, after the loop {100 * err:.2f} %; "
          f"params {rep.final.params}")
    assert err < 0.01


def make_bonded_log(name="log", **kw):
    """A twin log of a specimen bonded to the platens.

    The twin runs its own FE (at the exact alpha, on its own stretch grid) on the fit tables'
    mesh: the fit then meets the tables' interpolation error (about 0.01 %) but not a
    different discretisation.  A different mesh moves the force by 0.3-0.4 % (40 against 32
    radial cells, near 20 % compression where the free surface folds onto the platen): the
    tables' discretisation error, under the 1 % the model promises but 1-2 mN here, above
    the 1 mN noise.  The loop cannot tell that from a mechanism: it shifts mu by about 1 %
    and, on the bench's logs, was absorbed by a spurious Prony term.
    """
    from bsipipe.mechanics.noslip import DEFAULT_MESH

    return make_log(name, boundary="no-slip", noslip_mesh_radial=DEFAULT_MESH.n_radial, **kw)


@pytest.mark.slow
def test_declared_no_slip_boundary_recovers_mu():
    """Semi-confined 18 x 12 mm cylinder bonded to the platens, fitted with ``--boundary
    no-slip`` from the start: the homogeneous formula's mu bias, and mu recovered within 2 %
    with nothing added by the loop."""
    lg, truth = make_bonded_log(rate_hz=5.0, seed=7)
    hom = fit_logs([lg], DECLARED)
    bias = hom.params["mu_pa"] / truth["params"]["mu_pa"] - 1.0
    rep = close_loop_logs([lg], ForceModelSpec(boundary="no-slip"))
    print(f"\nbonded 18 x 12 mm: homogeneous fit mu {hom.params['mu_pa']:.1f} Pa (bias {100 * bias:+.1f} %), "
          f"alpha {hom.params['alpha']:.3f}; declared no-slip:", summary(rep))
    assert 0.2 < bias < 1.3   # the published 20-35 % at H/D 1 and 60-130 % at 1/2 bracket H/D 2/3
    assert rep.effects == []
    assert rep.final.rmse < 1.5 * NOISE_N
    check_one_term(rep.final.params, truth, tol_mu=0.02)


@pytest.mark.slow
def test_hidden_no_slip_platens_from_width_series():
    """Semi-confined 18 x 12 mm cylinder bonded to the platens (the twin's own FE run).

    The side camera's width series: mid-height width of the bonded cylinder (the package's FE
    tables) at the true stretch, 1 Hz, 0.03 mm noise.
    """
    from bsipipe.mechanics.noslip import noslip_bulge_width

    lg, truth = make_bonded_log(rate_hz=5.0, seed=6)
    rng = np.random.default_rng(60)
    t = np.arange(0.0, lg.time_s[-1], 1.0)
    lam = 1.0 - np.maximum(np.interp(t, lg.time_s, lg.displacement_mm) - truth["contact_mm"], 0.0) / 12.0
    width = noslip_bulge_width(lam, truth["params"]["alpha"], 18.0, 12.0 / 18.0) + rng.normal(0.0, 0.03, len(t))
    rep = close_loop_logs([lg], DECLARED, boundary_declared=False, width=WidthSeries(t, width))
    print(f"\nno-slip-platens (width {width[0]:.2f} -> {width[-1]:.2f} mm):", summary(rep))
    mu0 = rep.baseline.params["mu_pa"]
    print(f"  homogeneous fit: mu {mu0:.1f} Pa, bias {100 * (mu0 / 720.0 - 1):+.1f} % "
          f"(alpha {rep.baseline.params['alpha']:.2f})")
    steps = {s["effect"]: s for s in rep.to_dict()["steps"]}
    assert "no-slip-platens" in steps, rep.to_dict()["tried"][0]
    ev = steps["no-slip-platens"]["evidence"]["outside"]
    print(f"  width rmse: homogeneous {ev['rmse_width_homogeneous_mm']:.3f} mm, no-slip "
          f"{ev['rmse_width_no_slip_mm']:.3f} mm, delta BIC {ev['delta_bic']:.0f}")
    assert rep.effects == ["no-slip-platens"]
    assert rep.final.spec.boundary == "no-slip"
    assert rep.final.rmse < 1.5 * NOISE_N
    check_one_term(rep.final.params, truth, tol_mu=0.02)


@pytest.mark.slow
def test_hidden_no_slip_platens_from_two_aspects():
    """No width series: two bonded specimens, 18 x 12 and 18 x 9 mm, fitted jointly.  One
    homogeneous law cannot serve both (their apparent mu differ); the bonded FE model can."""
    a, truth = make_bonded_log("18x12", rate_hz=5.0, seed=6)
    b, _ = make_bonded_log("18x9", height_mm=9.0, rate_hz=5.0, seed=16)
    per = {lg.name: fit_logs([lg], DECLARED).params["mu_pa"] for lg in (a, b)}
    print(f"\nno-slip-platens from two aspects: homogeneous mu 18x12 {per['18x12']:.0f} Pa "
          f"({100 * (per['18x12'] / 720 - 1):+.0f} %), 18x9 {per['18x9']:.0f} Pa ({100 * (per['18x9'] / 720 - 1):+.0f} %)")
    rep = close_loop_logs([a, b], DECLARED, boundary_declared=False)
    print(summary(rep))
    ev = rep.to_dict()["steps"][0]["evidence"]
    print(f"  held-out rmse {ev['heldout_rmse_before']:.3e} -> {ev['heldout_rmse_after']:.3e} N")
    assert rep.effects == ["no-slip-platens"] and rep.final.spec.boundary == "no-slip"
    assert all(p["rmse_n"] < 1.5 * NOISE_N for p in rep.final.fit.metrics["per_log"])
    check_one_term(rep.final.params, truth, tol_mu=0.02)


@pytest.mark.parametrize("seed", [21, 22])
def test_hidden_periodic_disturbance(seed):
    """Mains hum on the load, 2 mN at 50.5 Hz, recorded at 10 Hz: a 0.5 Hz swing, 30 cycles
    over the 61 s ramp.  Without the effect nothing had been named (mu 722.3 and 721.1 Pa on
    seeds 21 and 22, their Newey-West intervals +-11 and +-10 Pa, the RMSE 1.7 times the
    noise); periodic-disturbance is named from the periodogram's peak, at the alias the log
    shows, the error drops to the noise and the intervals to +-3 Pa."""
    hum = dict(disturbance_n=2e-3, disturbance_hz=50.5, disturbance_phase_rad=1.0)
    lg, truth = make_log(rate_hz=10.0, seed=seed, **hum)
    rep = close_loop_logs([lg], DECLARED)
    p = rep.final.params
    print(f"\nperiodic-disturbance (2 mN at 50.5 Hz, 10 Hz samples), seed {seed}:", summary(rep))
    print(f"  amplitude {1e3 * p.get('disturbance_n', 0):.2f} mN (true 2), frequency {p.get('disturbance_hz')} Hz "
          f"(true alias 0.5)")
    assert rep.effects == ["periodic-disturbance"]
    assert rep.final.rmse < 1.5 * NOISE_N and rep.final.rmse < rep.baseline.rmse
    # frequency within a tenth of 1/T (61 s; its standard error 0.3 mHz), amplitude within 3.5 standard
    # errors (noise sqrt(2 / n), 0.057 mN)
    assert abs(p["disturbance_hz"] - 0.5) < 0.0016 and abs(p["disturbance_n"] - 2e-3) < 2e-4
    check_one_term(p, truth)


# --- no hidden effect: nothing is added ------------------------------------------------------

def test_no_hidden_effect_20_seeds_no_false_positive():
    added, t0 = {}, time.perf_counter()
    structured = 0
    for seed in range(20):
        lg, truth = make_log(rate_hz=5.0, seed=100 + seed)
        rep = close_loop_logs([lg], DECLARED)
        structured += not rep.baseline.structure["noise"]
        if rep.effects:
            added[seed] = rep.effects
    print(f"\nno hidden effect, 20 seeds: false positives {len(added)} {added}; baseline residual judged "
          f"structured in {structured}; {time.perf_counter() - t0:.1f} s")
    assert not added


# --- the rate effect: two speeds, one tissue ---------------------------------------------------

@pytest.mark.slow
def test_two_speeds_one_parameter_set():
    """Hyperviscoelastic Ogden (alpha -6.3, Prony tau 0.5 s and 50 s) at 1 mm/s and 0.01 mm/s."""
    prony = [(0.25, 0.5), (0.22, 50.0)]
    kw = dict(mu_pa=1000.0, alpha=-6.3, prony=prony, n_points=600, max_strain=0.3)
    fast, truth = make_log("1 mm/s", speed_mm_min=60.0, seed=7, **kw)
    slow, _ = make_log("0.01 mm/s", speed_mm_min=0.6, seed=8, **kw)
    per_speed = {lg.name: fit_logs([lg], DECLARED).params["mu_pa"] for lg in (fast, slow)}
    print(f"\nhyperelastic mu per speed: 1 mm/s {per_speed['1 mm/s']:.0f} Pa, "
          f"0.01 mm/s {per_speed['0.01 mm/s']:.0f} Pa (seeds: 790 vs 600)")
    assert per_speed["1 mm/s"] > 1.15 * per_speed["0.01 mm/s"]
    rep = close_loop_logs([fast, slow], DECLARED)
    print("joint loop:", summary(rep))
    d = rep.to_dict()
    for s in d["steps"]:
        ev = s["evidence"]
        if "heldout_rmse_before" in ev:
            print(f"  {s['effect']}: held-out rmse (interleaved blocks) {ev['heldout_rmse_before']:.3e} -> "
                  f"{ev['heldout_rmse_after']:.3e} N")
    assert rep.effects[0] == "viscoelastic-relaxation"
    per_log = rep.final.fit.metrics["per_log"]
    print("  per-log rmse after:", [f"{p['rmse_n']:.2e}" for p in per_log])
    assert all(p["rmse_n"] < 1.5 * NOISE_N for p in per_log)
    p = rep.final.params
    fit_terms = sorted(p["prony"], key=lambda x: x["tau_s"])
    long_term = p["mu_pa"] * (1.0 - sum(x["g"] for x in fit_terms))
    print(f"  one parameter set: mu {p['mu_pa']:.1f} Pa (true 1000), alpha {p['alpha']:.3f} (true -6.3), "
          f"long-term modulus {long_term:.1f} Pa (true 530), Prony {fit_terms} (true {prony})")
    # The contact the detector finds on the 1 mm/s log is ~8 um early; the instantaneous modulus
    # and the 0.5 s term trade off against it (with the true contact: mu 990 Pa, tau 0.53 s), so
    # they are held to 6 % and a factor 1.5; alpha, the long-term modulus and the slow term are
    # what two ramps determine well.
    assert abs(p["alpha"] + 6.3) < 0.1
    assert abs(long_term / 530.0 - 1.0) < 0.03
    assert abs(p["mu_pa"] / 1000.0 - 1.0) < 0.06
    (g1, t1), (g2, t2) = ((x["g"], x["tau_s"]) for x in fit_terms)
    assert abs(g1 - 0.25) < 0.03 and 0.5 / 1.5 < t1 < 0.5 * 1.5
    assert abs(g2 - 0.22) < 0.03 and abs(t2 / 50.0 - 1.0) < 0.2


# --- two effects at once -----------------------------------------------------------------------

@pytest.mark.slow
def test_viscoelastic_and_baseline_drift_both_found():
    lg, truth = make_log(prony=[(0.3, 2.0), (0.2, 30.0)], protocol="ramp-hold-unload", hold_s=60.0,
                         baseline_n=0.01, drift_n_per_s=1e-4, rate_hz=2.0, seed=9)
    rep = close_loop_logs([lg], DECLARED)
    print("\nviscoelastic + baseline drift:", summary(rep))
    assert {"viscoelastic-relaxation", "load-baseline-drift"} <= set(rep.effects)
    assert rep.final.rmse < 1.5 * NOISE_N
    check_one_term(rep.final.params, truth)
    check_prony(rep.final.params, truth)


# --- through the command line: fit.json's loop section, loop.md, loop.png ---------------------------

def test_fit_ogden_writes_the_loop(tmp_path):
    import json

    from click.testing import CliRunner

    from bsipipe.cli import cli
    from bsipipe.synth.machine_log import write_bluehill2

    frame, truth = synth_compression_log(compliance_mm_per_n=1.0, rate_hz=5.0, seed=4, noise_n=NOISE_N)
    path = write_bluehill2(frame, tmp_path / "compliant.csv", label="C1", geometry={"diameter_mm": 18.0, "height_mm": 12.0})
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["fit-ogden", str(path), "--boundary", "frictionless", "--bootstrap", "0", "-o", str(out)],
                           catch_exceptions=False)
    assert r.exit_code == 0, r.output
    loop = json.loads((out / "fit.json").read_text())["loop"]
    assert [s["effect"] for s in loop["steps"]] == ["machine-compliance"]
    assert loop["steps"][0]["rmse_n_before"] > loop["steps"][0]["rmse_n_after"] == pytest.approx(loop["final"]["rmse_n"])
    # --boundary was declared: the platen boundary is not a candidate
    assert "no-slip-platens" not in {t["effect"] for rnd in loop["tried"] for t in rnd}
    md = (out / "loop.md").read_text()
    assert "| step | effect | parameters | RMSE before (N) | RMSE after (N) | evidence |" in md
    assert "| 1 | `machine-compliance` | compliance_mm_per_n=" in md
    assert (out / "loop.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("seed", [51, 52])
def test_a_slow_drift_small_against_the_noise_is_taken_out(seed):
    """A 1 mm/min ramp at 10 Hz with a load-cell drift of 3e-5 N/s (7.4 mN over the ramp,
    1.3 % of the peak force): the probe's case.  The drift moves mu by about 1.4 % and alpha
    by 2 %, six or more times their 95 % intervals, but lowers the RMSE by only about 2 %, and
    the residual's RMSE sits at the measured noise level: the loop had kept nothing (mu 730-731
    Pa, intervals of +-1.6 Pa, truth outside).  Now an effect that moves a declared parameter
    by more than 3 half-widths is practically significant, and a residual at the noise level
    whose structure test is overwhelming (p < 1e-6) is still looked at: load-baseline-drift
    is kept and the truth lies in the intervals."""
    lg, truth = make_log(speed_mm_min=1.0, rate_hz=10.0, drift_n_per_s=3e-5, seed=seed)
    rep = close_loop_logs([lg], DECLARED)
    p, ci = rep.final.params, rep.final.fit.ci95
    print(summary(rep), ci["mu_pa"], ci["alpha"])
    assert "load-baseline-drift" in rep.effects
    assert ci["mu_pa"][0] <= truth["params"]["mu_pa"] <= ci["mu_pa"][1]
    assert ci["alpha"][0] <= truth["params"]["alpha"] <= ci["alpha"][1]
    # without the drift nothing is named
    lg0, _ = make_log(speed_mm_min=1.0, rate_hz=10.0, seed=seed)
    assert close_loop_logs([lg0], DECLARED).effects == []
