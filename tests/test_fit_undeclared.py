"""fit-ogden's loop on logs with an effect nobody declared, made by a generator independent of
bsipipe's own (``bsipipe.synth.machine_log`` shares the fit's toe and QLV forms; this one is
written from the textbook forms alone): one-term Ogden in uniaxial stress, a QLV Prony
series integrated sample by sample, a machine compliance solved by fixed point, noise.

Both effects here change the fitted RMSE by only a few per cent at the load cell's noise
(the residual is at the noise floor in size) while biasing the parameters far outside their
intervals; the loop must go on while its structure tests see a pattern.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli

pytestmark = pytest.mark.slow

MU, ALPHA = 720.0, -4.7
D_MM, H_MM = 18.0, 12.0
AREA_M2 = np.pi * (D_MM / 2) ** 2 * 1e-6


def _nominal_stress(lam):
    """Uniaxial nominal stress of W = 2 mu / alpha^2 (l1^a + l2^a + l3^a - 3), incompressible."""
    return (2 * MU / ALPHA) * (lam ** (ALPHA - 1) - lam ** (-ALPHA / 2 - 1))


def _log(speed_mm_s, rate_hz, *, prony=(), compliance_mm_n=0.0, gap_mm=0.5, strain=0.3, noise_n=0.001, seed=1,
         unload=False, lift_off=False):
    """Time (s), crosshead (mm, compression positive), force (N, compression positive).
    ``unload``: the crosshead returns to its start at the same speed; ``lift_off``: the
    platen cannot pull, so where the QLV force would be negative the load reads 0."""
    rng = np.random.default_rng(seed)
    top = (gap_mm + strain * H_MM) / speed_mm_s
    t = np.arange(0.0, (2 if unload else 1) * top + 1e-12, 1.0 / rate_hz)
    x = speed_mm_s * (np.minimum(t, 2 * top - t) if unload else t)

    def elastic(u):
        return -_nominal_stress(1.0 - np.clip(u, 0.0, None) / H_MM) * AREA_M2

    def qlv(fe):
        out = fe * (1.0 - sum(g for g, _ in prony))
        dfe = np.diff(fe, prepend=0.0)
        for g, tau in prony:
            h, acc = np.zeros_like(fe), g * dfe[0]
            h[0] = acc
            for i in range(1, len(t)):
                r = (t[i] - t[i - 1]) / tau
                acc = acc * np.exp(-r) + g * dfe[i] * (1.0 - np.exp(-r)) / r
                h[i] = acc
            out = out + h
        return out

    f = qlv(elastic(x - gap_mm))
    for _ in range(100 if compliance_mm_n else 0):
        f = qlv(elastic(x - gap_mm - compliance_mm_n * f))
    if lift_off:
        f = np.maximum(f, 0.0)
    return t, x, f + noise_n * rng.standard_normal(t.size)


def _bluehill(path, t, x, f, load_unit="N", load_decimals=5):
    """A Bluehill 2 raw-data export (compression negative, CRLF); the load in N or kN with
    ``load_decimals`` decimals."""
    scale = {"N": 1.0, "kN": 1e-3}[load_unit]
    rows = [f"{a:.5f},{-b:.5f},{-c * scale:.{load_decimals}f},1,0" for a, b, c in zip(t, x, f)]
    path.write_bytes(("\r\n".join(['Text Inputs : Specimen label,"S1"', "", "Time,Extension,Load,Segment ID,"
                                   "Total Cycle Count", f"(sec),(mm),({load_unit}),,", *rows]) + "\r\n").encode())
    return path


def _fit(tmp_path, logs, exit_code=0):
    out = tmp_path / "fit"
    r = CliRunner().invoke(cli, ["fit-ogden", *map(str, logs), "--diameter-mm", str(D_MM), "--height-mm", str(H_MM),
                                 "-o", str(out)], catch_exceptions=False)
    assert r.exit_code == exit_code, r.output
    return json.loads((out / "fit.json").read_text()) if exit_code == 0 else r.output


def _steps(fit):
    return [s["effect"] for s in fit["loop"]["steps"]]


def test_two_relaxation_times_at_two_rates(tmp_path):
    """Relaxation at 0.5 s and 50 s (the times the rate effect of brain tissue needs), logs at
    1 and 0.01 mm/s: one Prony term leaves a structured residual (Ljung-Box p ~ 1e-52) with
    an RMSE within 5 % of the noise, and mu at 549 [545, 553] Pa; the loop, which stopped
    there at the noise floor, adds the second term (RMSE 1.06 -> 0.97 mN) and the interval
    holds 720 Pa (739 [682, 796])."""
    prony = ((0.3, 0.5), (0.3, 50.0))
    logs = [_bluehill(tmp_path / "fast.csv", *_log(1.0, 100.0, prony=prony, seed=1)),
            _bluehill(tmp_path / "slow.csv", *_log(0.01, 1.0, prony=prony, seed=2))]
    fit = _fit(tmp_path, logs)
    assert _steps(fit) == ["viscoelastic-relaxation", "viscoelastic-relaxation"]
    lo, hi = fit["ci95"]["mu_pa"]
    assert lo <= MU <= hi, (lo, hi)
    lo, hi = fit["ci95"]["alpha"]
    assert lo <= ALPHA <= hi, (lo, hi)
    taus = sorted(p["tau_s"] for p in fit["params"]["prony"])
    assert 0.2 < taus[0] < 1.5 and 20 < taus[1] < 150, taus


def test_machine_compliance(tmp_path):
    """0.3 mm/N between crosshead and sample: without the loop alpha comes out -4.07
    [-4.09, -4.06] and mu 738 [734, 742] Pa; the loop names machine-compliance and both
    intervals hold the truth (-4.75 [-4.85, -4.64], 719 [714, 724] Pa)."""
    fit = _fit(tmp_path, [_bluehill(tmp_path / "c.csv", *_log(10 / 60, 20.0, compliance_mm_n=0.3))])
    assert _steps(fit) == ["machine-compliance"]
    lo, hi = fit["ci95"]["alpha"]
    assert lo <= ALPHA <= hi, (lo, hi)
    lo, hi = fit["ci95"]["mu_pa"]
    assert lo <= MU <= hi, (lo, hi)


def test_load_cell_clipping(tmp_path):
    """The load flattened at 0.5 N by the cell's range (the probe's log: 4 mm/min, 3 mN noise,
    the last 18 of 616 samples clipped): the loop had kept machine-compliance at 1.39 mm/N
    with alpha turned to +19.4 and mu 1179 Pa, no warning.  The clipped top is found (the
    same value to the last digit while the platen moves on), the fit stops before it with a
    load-clipped warning, and both intervals hold the truth (probe: 719.5 [710, 729] Pa,
    -4.72 [-4.76, -4.68])."""
    t, x, f = _log(4 / 60, 10.0, strain=0.3, noise_n=0.003, seed=3)
    f = np.minimum(f, 0.5)
    assert 10 < (f == 0.5).sum() < 40
    fit = _fit(tmp_path, [_bluehill(tmp_path / "clip.csv", t, x, f)])
    w = [w for w in fit["warnings"] if w["code"] == "load-clipped"]
    assert len(w) == 1 and w[0]["level_n"] == pytest.approx(0.5), fit["warnings"]
    assert fit["inputs"][0]["load_clipped"]["n_samples"] == int((f == 0.5).sum())
    for k, truth in (("mu_pa", MU), ("alpha", ALPHA)):
        lo, hi = fit["ci95"][k]
        assert lo <= truth <= hi, (k, lo, hi, _steps(fit))
    assert fit["params"]["alpha"] < 0


def test_two_term_truth_keeps_model_order_not_a_sign_flipping_toe(tmp_path):
    """A two-term Ogden truth (mu 500 / 220 Pa, alpha -8 / +2; the probe's log, 4 mm/min, 3 mN):
    model-order (delta BIC 74.6) and contact-offset (70.7) were within the tie margin, the
    stage's order kept contact-offset, and its 1 mm toe turned alpha from -7.19 to +16.2 (mu
    1656 Pa); on this log viscoelastic-relaxation also passes, with g = 0.98, the edge of its
    range.  A tie goes to the fewer added parameters, and an added parameter on a refused edge
    is turned down (effect_veto); the loop keeps model-order: 489 / 242 Pa, -8.10 / +1.80."""
    rng = np.random.default_rng(7)
    speed, gap = 4 / 60, 0.5
    t = np.arange(0.0, (gap + 3.6) / speed + 1e-9, 0.1)
    x = speed * t
    lam = 1.0 - np.clip(x - gap, 0.0, None) / H_MM
    s = sum((2 * m / a) * (lam ** (a - 1) - lam ** (-a / 2 - 1)) for m, a in ((500.0, -8.0), (220.0, 2.0)))
    f = -s * AREA_M2 + 0.003 * rng.standard_normal(t.size)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "o2.csv", t, x, f)])
    tried = [(e["effect"], e.get("criterion"), e.get("reason")) for e in fit["loop"]["tried"][0]]
    print(_steps(fit), fit["params"], tried)
    assert _steps(fit) == ["model-order"]
    p = fit["params"]
    assert abs(p["alpha1"] + 8.0) < 0.5 and abs(p["alpha2"] - 2.0) < 0.5, p
    assert abs(p["mu1_pa"] + p["mu2_pa"] - 720.0) < 0.05 * 720.0, p


def test_two_specimens_of_different_stiffness_fitted_together(tmp_path):
    """Specimens of 600 and 850 Pa (alpha -4.7 both, the probe's logs: 4 mm/min, 3 mN) fitted in
    one run: with nothing to take their difference the loop had kept a load drift, a frame
    compliance and 1 mm toes (mu 1397 Pa, alpha +13.8; before the toe-length veto, mu 1626,
    alpha +11.5).  specimen-scatter gives each log its own factor on the moduli (their
    geometric mean 1): mu is the geometric-mean specimen's (714 Pa), each log's own is in
    inputs[].specimen_params (probe: 608 and 858 Pa, mu 722.5 [716, 729], alpha -4.683)."""
    rng = np.random.default_rng(11)
    logs = []
    for name, mu in (("a600", 600.0), ("b850", 850.0)):
        t, x, f = _log(4 / 60, 10.0, strain=0.3, noise_n=0.0)
        f = f * mu / MU + 0.003 * rng.standard_normal(f.size)
        logs.append(_bluehill(tmp_path / f"{name}.csv", t, x, f))
    fit = _fit(tmp_path, logs)
    assert _steps(fit) == ["specimen-scatter"], _steps(fit)
    own = [i["specimen_params"]["mu_pa"] for i in fit["inputs"]]
    print(fit["params"]["mu_pa"], fit["ci95"]["mu_pa"], fit["params"]["alpha"], own)
    assert own[0] == pytest.approx(600.0, rel=0.03) and own[1] == pytest.approx(850.0, rel=0.03)
    assert fit["params"]["mu_pa"] == pytest.approx(np.sqrt(600.0 * 850.0), rel=0.03)
    assert abs(fit["params"]["alpha"] - ALPHA) < 0.1


def test_unloading_lift_off_left_out(tmp_path):
    """A viscoelastic specimen (QLV g 0.3, tau 1 s) loaded to 30 % at 1 mm/s and unloaded: the
    QLV force would pull below 0 from 6.96 s (crosshead 1.24 mm, 0.74 mm before the contact),
    so the load reads 0 N there (the platen leaves the tissue).  The clamped samples had been
    fitted too: mu 672 [607, 737] Pa, alpha -4.945 [-5.081, -4.809], g 0.377, tau 1.61 s,
    with a false load-baseline-drift and contact-offset kept.  The lift-off is found (the
    load at its zero while the crosshead retracts, where loading had pressed 40 noise levels),
    the fit stops before it with a platen-lift-off warning naming the time, and both
    intervals hold the truth (probe: 719.6 [713.5, 725.7] Pa, -4.701 [-4.718, -4.684])."""
    t, x, f = _log(1.0, 50.0, prony=[(0.3, 1.0)], seed=12, unload=True, lift_off=True)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "off.csv", t, x, f)])
    w = [w for w in fit["warnings"] if w["code"] == "platen-lift-off"]
    assert len(w) == 1, fit["warnings"]
    # the first sample at the zero comes a few samples (3 mN of force) before the true 6.96 s
    assert 6.8 <= w[0]["time_s"] <= 6.97 and "6.9" in w[0]["message"], w[0]
    inp = fit["inputs"][0]
    assert "platen left the specimen" in inp["fitted_part"] and inp["lift_off"]["n_left_out"] >= 63
    assert not {"load-baseline-drift", "contact-offset"} & set(_steps(fit)), _steps(fit)
    for k, truth in (("mu_pa", MU), ("alpha", ALPHA)):
        lo, hi = fit["ci95"][k]
        assert lo <= truth <= hi, (k, lo, hi, _steps(fit))
    assert fit["params"]["prony"][0]["g"] == pytest.approx(0.3, abs=0.03)


@pytest.mark.parametrize("prony", [(), ((0.3, 1.0),)], ids=["elastic", "glued"])
def test_unloading_without_lift_off_fitted_whole(tmp_path, prony):
    """No lift-off where there is none: an elastic specimen's unloading reaches the load's zero
    at the contact (where loading was at the zero too), and a glued viscoelastic one reads
    tension (down to -22 mN) instead of sitting at the zero; both are fitted whole, no
    platen-lift-off warning."""
    t, x, f = _log(1.0, 50.0, prony=list(prony), seed=12, unload=True)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "un.csv", t, x, f)])
    assert not [w for w in fit["warnings"] if w["code"] == "platen-lift-off"], fit["warnings"]
    assert "lift_off" not in fit["inputs"][0] and fit["inputs"][0]["fitted_part"] == "whole record"
    for k, truth in (("mu_pa", MU), ("alpha", ALPHA)):
        lo, hi = fit["ci95"][k]
        assert lo <= truth <= hi, (k, lo, hi, _steps(fit))


def test_a_load_too_coarse_for_the_record_is_refused(tmp_path):
    """The load written in kN with 4 decimals: 0.1 N steps, 6 levels over the 0.55 N peak of a
    30 % ramp (1 mN noise, so every step is exact).  It had been fitted at mu 1668 Pa, alpha
    +11.2, the contact at 1.06 mm (truth 0.5), with only residual-correlated said.  Its first
    step past the onset spans 1.04 of the 2.7 mm after it (over a fifth): exit 2 naming the
    file and the step; the same log with 5 decimals (10 mN, 55 levels) is fitted as before,
    unwarned (probe: 717.8 [703.9, 731.7] Pa, -4.703 [-4.755, -4.651])."""
    t, x, f = _log(1.0, 50.0, seed=11)
    said = _fit(tmp_path, [_bluehill(tmp_path / "kN4.csv", t, x, f, "kN", 4)], exit_code=2)
    assert "kN4.csv" in said and "steps of 0.1 N" in said, said
    fit = _fit(tmp_path, [_bluehill(tmp_path / "kN5.csv", t, x, f, "kN", 5)])
    assert not [w for w in fit["warnings"] if w["code"] == "load-resolution"], fit["warnings"]
    for k, truth in (("mu_pa", MU), ("alpha", ALPHA)):
        lo, hi = fit["ci95"][k]
        assert lo <= truth <= hi, (k, lo, hi, _steps(fit))


def test_a_coarse_load_that_still_carries_a_fit_is_warned_about(tmp_path):
    """A 10 % ramp written in kN with 5 decimals: 10 mN steps, 7 levels over its 0.06 N; the
    first step past the onset spans 0.18 of the 1.1 mm after it (a sixth): fitted, with a
    load-resolution warning giving the step (nothing had been said)."""
    t, x, f = _log(1.0, 50.0, seed=11, strain=0.1)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "kN5.csv", t, x, f, "kN", 5)])
    w = [w for w in fit["warnings"] if w["code"] == "load-resolution"]
    assert len(w) == 1 and w[0]["quantum_n"] == pytest.approx(0.01) and 0.1 < w[0]["share"] <= 0.2, w


def test_a_short_ramp_whose_exponent_sign_the_record_does_not_fix(tmp_path):
    """A ramp to 10 % strain (1 mm/s, 50 Hz, 1 mN): the noise of this seed makes alpha's other
    sign fit best: mu 969 [949, 989] Pa, alpha +23.7 [22.4, 25.0] for 720 / -4.7, and a
    one-term law was never given the another-optimum check (other_optima returned nothing for
    fewer than two exponents).  The other sign's basin (740 Pa, -4.13) is 7.2 noise variances
    worse, inside the joint 95 % region of mu, alpha and the contact (3 F(3, 83) = 8.15):
    another-optimum names it, and the span over both basins holds the truth.  On the 30 %
    ramp of the same noise the other sign is far outside: nothing is said."""
    t, x, f = _log(1.0, 50.0, strain=0.1, seed=25)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "short.csv", t, x, f)])
    assert fit["params"]["alpha"] > 0            # the chosen basin: the record does not fix the sign
    w = [w for w in fit["warnings"] if w["code"] == "another-optimum"]
    assert len(w) == 1, fit["warnings"]
    alt = w[0]["alternatives"][0]
    assert alt["params"]["alpha"] < 0 and abs(alt["params"]["alpha"] - ALPHA) < 1.0, alt
    assert abs(alt["params"]["mu_pa"] / MU - 1.0) < 0.05 and alt["delta_sse_over_s2"] < 8.15, alt
    span = w[0]["params_span"]
    assert span["alpha"][0] <= ALPHA <= span["alpha"][1] and span["mu_pa"][0] <= MU <= span["mu_pa"][1], span
    assert "sign of alpha is not determined" in w[0]["message"]
    t, x, f = _log(1.0, 50.0, strain=0.3, seed=25)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "long.csv", t, x, f)])
    assert not [w for w in fit["warnings"] if w["code"] == "another-optimum"], fit["warnings"]
    assert abs(fit["params"]["alpha"] - ALPHA) < 0.1


#: The hum cases: (source frequency Hz, noise seed, phase rad) on a 1 mm/s ramp sampled at 50 Hz.
HUM_CASES = {"50.5Hz-seed1": (50.5, 1, 1.0), "50.5Hz-seed2": (50.5, 2, 0.0), "60.3Hz": (60.3, 1, 1.0),
             "3.3Hz-resolved": (3.3, 2, 1.0)}


@pytest.mark.parametrize("case", list(HUM_CASES))
def test_a_periodic_disturbance_of_the_load(tmp_path, case):
    """2 mN of hum on the load of a 1 mm/s ramp sampled at 50 Hz (1 mN noise): mains at 50.5 Hz
    shows as a 0.5 Hz swing, two cycles over the 4.1 s record; 60.3 Hz as 10.3 Hz; a 3.3 Hz
    vibration as itself.  With nothing to take it the loop had kept a contact offset, a drift
    and a compliance and turned alpha to +13.4 [12.8, 13.9], mu 1352 Pa, for -4.7 / 720 (50.5
    Hz, seed 1; seed 2: a contact offset, alpha +11.7, mu 1585 Pa), the final residual white,
    exit 0; the faster ones had been left in the residual, unnamed (mu 719-721 Pa, intervals
    of +-6-17 Pa).  periodic-disturbance, its frequency from the residual's periodogram, is
    kept alone, finds the frequency the log shows and the amplitude, and both intervals hold
    the truth (mu 718-721 Pa, +-5-7 Pa)."""
    hum_hz, seed, phase = HUM_CASES[case]
    t, x, f = _log(1.0, 50.0, seed=seed)
    f = f + 0.002 * np.sin(2 * np.pi * hum_hz * t + phase)
    fit = _fit(tmp_path, [_bluehill(tmp_path / "hum.csv", t, x, f)])
    p, ci = fit["params"], fit["ci95"]
    print(case, _steps(fit), {k: (p[k], ci[k]) for k in ci if k in ("mu_pa", "alpha") or k.startswith("disturbance")})
    assert _steps(fit) == ["periodic-disturbance"], (_steps(fit), p["mu_pa"], p["alpha"])
    shown_hz = abs(hum_hz - 50.0 * round(hum_hz / 50.0))
    # the frequency within its interval and 1/(10 T) of the truth; the amplitude within 3
    # standard errors, noise sqrt(2 / n) = 0.1 mN
    lo, hi = ci["disturbance_hz"]
    assert lo <= shown_hz <= hi and abs(p["disturbance_hz"] - shown_hz) < 0.025, (p["disturbance_hz"], lo, hi)
    assert abs(p["disturbance_n"] - 0.002) < 3e-4
    for k, truth in (("mu_pa", MU), ("alpha", ALPHA)):
        lo, hi = ci[k]
        assert lo <= truth <= hi, (k, lo, hi)


def test_a_periodic_disturbance_on_one_of_two_logs(tmp_path):
    """2 mN of 50.5 Hz hum on the 1 mm/s log only, a clean 0.5 mm/s log fitted with it: the
    clean log's sinusoid (its noise's largest peak, 0.26 mN at 14.95 Hz, 7 times its neighbours)
    was no line, so the loop had turned the effect down and kept nothing, the hum left in the
    residual.  One line is enough now (p times the number of logs); fit.json's
    ``periodic_disturbance`` says which log carries it."""
    paths = []
    for i, (speed, hum) in enumerate(((1.0, 0.002), (0.5, 0.0))):
        t, x, f = _log(speed, 50.0, seed=1 + i)
        paths.append(_bluehill(tmp_path / f"log{i}.csv", t, x, f + hum * np.sin(2 * np.pi * 50.5 * t + 0.3)))
    fit = _fit(tmp_path, paths)
    assert _steps(fit) == ["periodic-disturbance"], _steps(fit)
    pd_ = fit["periodic_disturbance"]
    assert pd_["with_line"] == ["log0"] and [x["line"] for x in pd_["logs"]] == [True, False]
    assert abs(pd_["logs"][0]["amplitude_n"] - 0.002) < 3e-4 and abs(pd_["logs"][0]["hz"] - 0.5) < 0.025
    for k, truth in (("mu_pa", MU), ("alpha", ALPHA)):
        lo, hi = fit["ci95"][k]
        assert lo <= truth <= hi, (k, lo, hi)


@pytest.mark.parametrize("seed", [1, 2])
def test_no_periodic_disturbance_on_a_clean_log(tmp_path, seed):
    """The hum cases' logs without the hum: nothing is kept, periodic-disturbance included."""
    fit = _fit(tmp_path, [_bluehill(tmp_path / "clean.csv", *_log(1.0, 50.0, seed=seed))])
    assert _steps(fit) == [], _steps(fit)
    assert not any(k.startswith("disturbance") for k in fit["params"])
