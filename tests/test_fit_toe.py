"""The ``contact-offset`` effect's toe on uneven tops it was not written from.

``bsipipe.synth.machine_log`` makes its toe with the fit's own quadratic form (a bed of
columns whose heights are spread evenly), so no test of the loop met another toe shape.  The
logs here are made from the contact area alone, written out in this file: the platen meets
the top first at the gap and the area in contact grows as a power of the indentation ``u``
(linearly for a dome or a tilted face) until the whole face touches ``toe_mm`` later,

- ``area``: the touching part carries the whole travel, F = a(u) F_flat(u) (the stress
  test's uneven top, phys/toe_0.csv: mu came out 1497 [1255, 1739] Pa, blamed on
  viscoelastic relaxation);
- ``winkler``: every point of the face carries only its own compression (independent
  columns), F = E_flat applied to the integral of a(u).

Truth: one-term Ogden mu = 720 Pa, alpha = -4.7, 18 x 12 mm, 1 mN load noise, 10 mm/min.
"""

from __future__ import annotations

import numpy as np
import pytest

from bsipipe.mechanics.contact import detect_contact
from bsipipe.mechanics.effects import close_loop_logs
from bsipipe.mechanics.fit import ForceModelSpec, LogData, contact_compression

MU, ALPHA = 720.0, -4.7
D_MM, H_MM = 18.0, 12.0
AREA_M2 = np.pi * (D_MM / 2) ** 2 * 1e-6
NOISE_N = 1e-3


def _flat_force(u_mm):
    """Force (N, compression +) of a flat-topped cylinder compressed by ``u`` (homogeneous, uniaxial)."""
    lam = 1.0 - np.clip(u_mm, 0.0, None) / H_MM
    return -(2 * MU / ALPHA) * (lam ** (ALPHA - 1) - lam ** (-ALPHA / 2 - 1)) * AREA_M2


def _toe_log(kind: str, toe_mm: float, power: float, *, gap_mm=0.5, speed_mm_s=10 / 60, rate_hz=10.0,
             strain=0.3, seed=1, noise_n=NOISE_N):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, (gap_mm + strain * H_MM) / speed_mm_s + 1e-12, 1.0 / rate_hz)
    x = speed_mm_s * t
    u = np.clip(x - gap_mm, 0.0, None)
    area = np.clip(u / toe_mm, 0.0, 1.0) ** power
    if kind == "area":
        f = area * _flat_force(u)
    else:  # winkler: compression = integral of the contact fraction over the travel
        fine = np.linspace(0.0, u.max(), 20001)
        frac = np.clip(fine / toe_mm, 0.0, 1.0) ** power
        integral = np.concatenate([[0.0], np.cumsum(0.5 * (frac[1:] + frac[:-1]) * np.diff(fine))])
        f = _flat_force(np.interp(u, fine, integral))
    return t, x, f + noise_n * rng.standard_normal(t.size)


def _detected(t, x, f):
    c = detect_contact(t, x, f)
    return LogData("toe", t, x, f, D_MM, H_MM, c.displacement_mm, None, c.displacement_sd_mm, c.force_noise_n)


@pytest.mark.parametrize("kind, toe_mm, power", [("area", 0.4, 1.0), ("winkler", 0.6, 2.0)])
def test_loop_names_contact_offset_for_an_uneven_top(kind, toe_mm, power):
    lg = _detected(*_toe_log(kind, toe_mm, power))
    rep = close_loop_logs([lg], ForceModelSpec())
    p, ci = rep.final.params, rep.final.fit.ci95
    print(f"\n{kind} toe {toe_mm} mm, area ~ u^{power:g}: effects {rep.effects}, mu {p['mu_pa']:.1f} "
          f"{np.round(ci['mu_pa'], 1)}, alpha {p['alpha']:.3f} {np.round(ci['alpha'], 3)}, "
          f"toe c {p.get('contact_toe_mm', 0):.3f} p {p.get('contact_toe_exponent', 0):.2f} "
          f"s {p.get('contact_toe_spread', 0):.2f}, rmse {1e3 * rep.final.rmse:.3f} mN")
    assert rep.effects == ["contact-offset"]
    assert ci["mu_pa"][0] <= MU <= ci["mu_pa"][1]
    assert ci["alpha"][0] <= ALPHA <= ci["alpha"][1]
    assert rep.final.rmse < 1.1 * NOISE_N
    # The toe found is the one made (its 95 % intervals): full contact 2c = toe_mm after the
    # first touch, the area growing as u^power.
    print(f"  c {np.round(ci['contact_toe_mm'], 3)}, p {np.round(ci['contact_toe_exponent'], 2)}, "
          f"s {np.round(ci['contact_toe_spread'], 2)}")
    assert ci["contact_toe_mm"][0] <= toe_mm / 2 <= ci["contact_toe_mm"][1]
    assert ci["contact_toe_exponent"][0] <= power <= ci["contact_toe_exponent"][1]


@pytest.mark.parametrize("seed", [4, 101])
def test_a_nuisance_parameter_moving_is_no_evidence(seed):
    """The probe's toe at 3 mN noise and 4 mm/min (area growing linearly over 0.4 mm): the
    residual is within a few per cent of the noise, contact-offset (delta BIC 43.5) lowers the
    RMSE by 4.6 %, under the 5 % bar, and viscoelastic-relaxation (delta BIC 28.5, RMSE 2.9 %)
    had been kept on the parameter-shift rule because it moved contact_offset_mm, the contact
    already in the model, 3.5 half-widths: mu 1238 Pa for a true 720.  Only the tissue's own
    parameters count now; no Prony term is invented."""
    lg = _detected(*_toe_log("area", 0.4, 1.0, speed_mm_s=4 / 60, noise_n=3e-3, strain=0.3, seed=seed))
    rep = close_loop_logs([lg], ForceModelSpec())
    p = rep.final.params
    shifts = [t.get("param_shift", {}).get("name") for rnd in rep.tried for t in rnd
              if t.get("criterion") == "params" and t.get("passes")]
    print(f"\nseed {seed}: effects {rep.effects}, mu {p['mu_pa']:.1f}, alpha {p['alpha']:.3f}, kept on shifts of {shifts}")
    assert "viscoelastic-relaxation" not in rep.effects
    assert all(n in ("mu_pa", "alpha") for n in shifts)
    assert abs(p["mu_pa"] - MU) < 0.06 * MU and abs(p["alpha"] - ALPHA) < 0.1


def test_contact_compression_family():
    """p = 1, s = 0 is the quadratic toe; s = 1 is the contact fraction times the travel; the
    slope is the derivative; past full contact it is the flat top's travel x."""
    x = np.linspace(-0.5, 0.8, 1301)
    c = 0.2
    np.testing.assert_allclose(contact_compression(x, c),
                               np.where(x <= -c, 0, np.where(x >= c, x, (x + c) ** 2 / (4 * c))), atol=1e-15)
    for p in (0.5, 1.0, 2.0, 4.0):
        for s in (0.0, 0.4, 1.0):
            delta, slope = contact_compression(x, c, with_derivative=True, exponent=p, spread=s)
            gamma = 1 - (1 - s) * p / (p + 1)
            v = x + (1 - gamma) * 2 * c                      # travel past the first touch
            if s == 1.0:
                np.testing.assert_allclose(delta, np.clip(v / (2 * c), 0, 1) ** p * np.clip(v, 0, None), atol=1e-14)
            assert np.all(np.diff(delta) >= -1e-15)
            np.testing.assert_allclose(delta[x >= gamma * 2 * c], x[x >= gamma * 2 * c])
            # Away from the first touch and full contact (where s > 0 leaves a kink):
            smooth = (np.abs(v) > 0.005) & (np.abs(v - 2 * c) > 0.005)
            np.testing.assert_allclose(np.gradient(delta, x)[smooth], slope[smooth], atol=0.02 * (p + 1))
