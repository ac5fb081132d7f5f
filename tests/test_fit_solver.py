"""The compliance solver of the log fit and its QLV operator.

A fit with a machine compliance solves F = QLV[F_e(x - C F)] by a Jacobi iteration at every
residual evaluation, the QLV operator's time grid prepared once; the iteration reaches the
fixed point, and the force is a function of the parameters alone (no state carried between
calls).
"""

import numpy as np
import pytest

from bsipipe.mechanics import fit as F
from bsipipe.mechanics.hyperelastic import ogden_nominal_stress
from bsipipe.mechanics.viscoelastic import QLV, qlv_response


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

    def stress(lam):
        return ogden_nominal_stress(lam, [1.0e6], [1.44])

    args = dict(height_mm=20.0, area_m2=np.pi * 0.01 ** 2, stress=stress, g=np.array([0.89]), tau=np.array([1.86]),
                compliance=0.0994)
    return t, x, args


def test_the_iteration_reaches_the_fixed_point():
    t, x, args = _stiff_log_case()
    f = F._tissue_force(t, x, max_iter=1000, **args)
    fe, _ = F._elastic_force(args["stress"], x - args["compliance"] * f, args["height_mm"], args["area_m2"])
    assert np.abs(f - qlv_response(t, fe, args["g"], args["tau"])).max() <= 1e-10 * np.abs(f).max()


def test_predictions_do_not_depend_on_the_calls_before():
    """The optimiser's finite differences need the residual to be a function of the
    parameters alone: a solver warm-started from its last solution made the real Bluehill 2
    fit take 4x the evaluations and end at a worse minimum."""
    t, x, args = _stiff_log_case()
    force = F._tissue_force(t, x, max_iter=1000, **args)
    log = F.LogData("stiff", t, x, force, 2 * np.sqrt(args["area_m2"] / np.pi) * 1e3, 20.0, 0.0)
    spec = F.ForceModelSpec(law="ogden", prony=1, compliance=True)
    prob = F._LogProblem([log], spec, None)
    values = {"mu_pa": 1.0e6, "alpha": 1.44, "g1": 0.89, "tau1_s": 1.86, "compliance_mm_per_n": 0.0994}
    assert set(values) == set(prob.names)
    first = prob.predict(values)[0]
    for c in (0.05, 0.2, 0.0994 * (1 + 1e-6)):            # evaluations elsewhere in between
        prob.predict({**values, "compliance_mm_per_n": c})
    assert np.array_equal(prob.predict(values)[0], first)
    assert np.array_equal(F.predict_force(log, spec, values), first)


def test_prony_terms_cache_serves_one_grid_and_keeps_the_last_few():
    from bsipipe.mechanics.viscoelastic import PronyTerms
    t = np.linspace(0.0, 10.0, 50)
    cache = PronyTerms(size=3)
    se = np.sin(t)
    for tau in (1.0, 2.0, 3.0, 4.0, 1.0):
        assert np.array_equal(QLV(t, [0.2], [tau], cache)(se), qlv_response(t, se, [0.2], [tau]))
    assert len(cache) == 3
    with pytest.raises(ValueError, match="one time grid"):
        QLV(t * 2, [0.2], [1.0], cache)
