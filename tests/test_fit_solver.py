"""The compliance solver of the log fit: its closed-form slope, its warm start, the QLV operator.

A fit with a machine compliance solves F = QLV[F_e(x - C F)] by a Jacobi iteration at every
residual evaluation.  The slope that scales each step is the Ogden law's own derivative, the
iteration starts from the force last solved for the same log (the optimiser's finite
differences ask for nearby parameters one after another), and the QLV operator prepares its
time grid once.  None of them may move the fixed point beyond the iteration's tolerance.
"""

import numpy as np

from bsipipe.mechanics import fit as F
from bsipipe.mechanics.hyperelastic import ogden_nominal_stress, ogden_uniaxial_stress_slope
from bsipipe.mechanics.viscoelastic import QLV, qlv_response


def test_ogden_slope_is_the_derivative_and_the_stress_is_the_same_numbers():
    lam = np.linspace(0.3, 1.0, 300)
    for mus, alphas in (([720.0], [-4.7]), ([0.398e6, 1400.0, 7500.0], [1.31, 5.47, -2.18]), ([5.0], [2.0])):
        p, k = ogden_uniaxial_stress_slope(lam, mus, alphas)
        assert np.array_equal(p, ogden_nominal_stress(lam, mus, alphas, "uniaxial"))
        h = 1e-6
        fd = (ogden_nominal_stress(lam + h, mus, alphas) - ogden_nominal_stress(lam - h, mus, alphas)) / (2 * h)
        np.testing.assert_allclose(k, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_qlv_operator_gives_qlv_response_bit_for_bit():
    rng = np.random.default_rng(5)
    for _ in range(50):
        n = int(rng.integers(1, 3000))
        t = np.cumsum(rng.choice([0.0, 0.02, 0.5, 400.0], size=n, p=[0.05, 0.6, 0.3, 0.05]))
        k = int(rng.integers(0, 4))
        g, tau = rng.uniform(0, 0.3, k), 10 ** rng.uniform(-2, 3, k)
        op = QLV(t, g, tau)
        for _ in range(2):                      # one operator, several histories
            se = rng.normal(size=n).cumsum()
            assert np.array_equal(op(se), qlv_response(t, se, g, tau))


def _stiff_log_case():
    """A cyclic ramp on a compliant machine with a strongly viscous specimen: the slow case
    (the Jacobi iteration needs about 60 steps from zero)."""
    t = np.linspace(0.0, 360.0, 3005)
    x = 2.5 * (1 - np.cos(2 * np.pi * t / 40.0)) + 0.5
    stress = F._OgdenStress(np.array([1.0e6]), np.array([1.44]))
    args = dict(height_mm=20.0, area_m2=np.pi * 0.01 ** 2, stress=stress, g=np.array([0.89]), tau=np.array([1.86]),
                compliance=0.0994)
    return t, x, args


def test_warm_start_reaches_the_same_force_in_fewer_steps(monkeypatch):
    t, x, args = _stiff_log_case()
    calls = []
    real = F._elastic_force

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(F, "_elastic_force", counted)
    f_cold = F._tissue_force(t, x, max_iter=1000, **args)
    n_cold = len(calls)
    nearby = {**args, "compliance": args["compliance"] * (1 + 1.5e-8)}    # a finite-difference step
    calls.clear()
    f_ref = F._tissue_force(t, x, max_iter=1000, **nearby)
    n_ref = len(calls)
    calls.clear()
    f_warm = F._tissue_force(t, x, max_iter=1000, f0=f_cold, **nearby)
    n_warm = len(calls)
    scale = np.abs(f_ref).max()
    assert np.abs(f_warm - f_ref).max() <= 1e-10 * scale
    assert n_warm <= 0.7 * n_ref, (n_cold, n_ref, n_warm)
    # the fixed point itself: the residual of the equation is at the tolerance
    fe, _ = F._elastic_force(args["stress"], x - nearby["compliance"] * f_warm, 20.0, args["area_m2"])
    assert np.abs(f_warm - qlv_response(t, fe, args["g"], args["tau"])).max() <= 1e-10 * scale


def test_problem_predictions_do_not_depend_on_the_calls_before():
    t, x, args = _stiff_log_case()
    force = F._tissue_force(t, x, max_iter=1000, **args)
    log = F.LogData("stiff", t, x, force, 2 * np.sqrt(args["area_m2"] / np.pi) * 1e3, 20.0, 0.0)
    spec = F.ForceModelSpec(law="ogden", prony=1, compliance=True)
    prob = F._LogProblem([log], spec, None)
    base = {"mu_pa": 1.0e6, "alpha": 1.44, "g1": 0.89, "tau1_s": 1.86, "compliance_mm_per_n": 0.0994}
    values = {k: base.get(k, 0.0) for k in prob.names}
    for c in (0.05, 0.2, 0.0994 * (1 + 1e-6)):            # earlier evaluations elsewhere
        prob.predict({**values, "compliance_mm_per_n": c})
    warm = prob.predict(values)[0]
    # the converged force (from zero, 60 steps are not always enough on this log: the
    # default cap leaves about 5e-8 of it, which is why a warm start helps the Jacobian)
    assert np.abs(warm - force).max() <= 1e-10 * np.abs(force).max()
    assert np.abs(F.predict_force(log, spec, values) - force).max() <= 1e-6 * np.abs(force).max()
