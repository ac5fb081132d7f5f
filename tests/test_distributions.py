"""bsipipe.distributions gives scipy.stats's numbers bit for bit without importing it."""

import subprocess
import sys

import numpy as np
import pytest

from bsipipe import distributions as D


def test_p_values_are_scipy_stats_bit_for_bit():
    from scipy import stats
    rng = np.random.default_rng(13)
    for _ in range(300):
        n = int(rng.integers(4, 3000))
        x = rng.normal(size=n) * rng.uniform(1e-3, 1e3)
        y = rng.uniform(-1, 1) * x + rng.normal(size=n) + rng.choice([0.0, 1e6])
        r, p = stats.pearsonr(x, y)
        assert D.pearsonr(x, y) == (float(r), float(p))
        z = rng.normal() * rng.choice([0.1, 1.0, 10.0, 40.0])
        assert D.norm_sf2(z) == float(2 * stats.norm.sf(abs(z)))
        q, dof = float(rng.uniform(0, 3) * rng.integers(1, 300)), int(rng.integers(1, 300))
        assert D.chi2_sf(q, dof) == float(stats.chi2.sf(q, dof))
        f, k, m = float(rng.uniform(0, 5) ** 2), int(rng.integers(2, 30)), int(rng.integers(31, 30000))
        assert D.f_sf(f, k - 1, m - k) == float(stats.f.sf(f, k - 1, m - k))
        pv = float(10.0 ** rng.uniform(-300, 0))
        assert D.chi2_isf(pv, 3) == float(stats.chi2.isf(pv, 3))
        assert D.t_ppf(0.975, dof) == float(stats.t.ppf(0.975, dof))
    for v in (0.0, -1.0, np.inf, np.nan):
        assert np.array_equal(D.chi2_sf(v, 5), stats.chi2.sf(v, 5), equal_nan=True)
        assert np.array_equal(D.f_sf(v, 3, 10), stats.f.sf(v, 3, 10), equal_nan=True)
    with pytest.warns(RuntimeWarning):
        assert np.isnan(D.pearsonr(np.ones(5), np.arange(5.0))).all()


@pytest.mark.parametrize("module", ["bsipipe.mechanics.fit", "bsipipe.mechanics.effects", "bsipipe.geometry.registration",
                                    "bsipipe.geometry.registration_effects", "bsipipe.commands.fit_ogden",
                                    "bsipipe.commands.register", "bsipipe.commands.track"])
def test_commands_do_not_import_scipy_stats(module):
    """Importing scipy.stats costs most of a second of a command's start-up: none needs it."""
    code = f"import sys, {module}; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
