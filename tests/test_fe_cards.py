"""FE material cards: parse each card back and check its convention numerically.

For every format the uniaxial nominal stress is rebuilt from the numbers on the card
*as the target code defines its strain energy* (written out here independently of the
writers) and compared with :func:`ogden_nominal_stress`.  The stress is the derivative of
the energy along the incompressible uniaxial path, taken by complex step (exact to
rounding), so a wrong factor in a convention shows up at order one while a right one
agrees to the card's printed precision: 1e-10 where the format allows 14 digits
(ABAQUS, FEBio), and the half-unit of the last printed digit of each 10-character field
for LS-DYNA (checked field by field, and propagated to the stress).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from bsipipe.io._fe_material import UNIT_SYSTEMS, poisson_ratio, prepare_material, unit_system
from bsipipe.io.abaqus import abaqus_material
from bsipipe.io.febio import febio_material, febio_ogden_terms
from bsipipe.io.lsdyna import (
    FIELD_WIDTH,
    field10,
    field_rounding_bound,
    lsdyna_material,
    lsdyna_ogden_terms,
    parse_fixed_card,
)
from bsipipe.mechanics.hyperelastic import get_law, ogden_nominal_stress

# brain-like laws (Pa); the 3-term one exercises ABAQUS's continuation data line
CASES = {
    "ogden": {"mu_pa": 720.0, "alpha": -4.7},
    "ogden2": {"mu1_pa": 500.0, "alpha1": -6.0, "mu2_pa": 220.0, "alpha2": 4.0},
    "ogden3": {"mu1_pa": 400.0, "alpha1": -6.0, "mu2_pa": 200.0, "alpha2": 4.0,
               "mu3_pa": 120.0, "alpha3": -2.0},
    "neo-hookean": {"mu_pa": 720.0},
    "mooney-rivlin": {"c10_pa": 300.0, "c01_pa": 60.0},
}
PRONY = [{"g": 0.45, "tau_s": 0.02}, {"g": 0.25, "tau_s": 1.5}]
STRETCH = np.r_[np.linspace(0.55, 0.98, 12), np.linspace(1.02, 1.6, 12)]
REL_TOL = 1e-10  # 14 printed digits leave ~1e-14; complex step is exact to rounding


def uniaxial_stress(energy, stretch):
    """dW/dlambda along lambda_2 = lambda_3 = lambda^-1/2 (complex step)."""
    h = 1e-30
    z = np.asarray(stretch, dtype=complex) + 1j * h
    return energy(z, z ** -0.5, z ** -0.5).imag / h


def reference(law_name):
    mus, alphas = get_law(law_name).ogden_terms([CASES[law_name][k]
                                                 for k in get_law(law_name).param_names])
    return ogden_nominal_stress(STRETCH, mus, alphas)


def assert_rel(actual, expected, tol):
    err = np.max(np.abs(actual / expected - 1.0))
    assert err < tol, f"max relative error {err:.3g} > {tol:g}"


# ---------------------------------------------------------------- ABAQUS


def parse_abaqus(card: str):
    """``{keyword: (params, [data values])}`` of an ABAQUS card, comments dropped."""
    out: dict[str, tuple[dict[str, str], list[float]]] = {}
    key = None
    for line in card.splitlines():
        if not line.strip() or line.startswith("**"):
            continue
        if line.startswith("*"):
            head, *opts = [p.strip() for p in line[1:].split(",")]
            params = {}
            for o in opts:
                k, _, v = o.partition("=")
                params[k.strip().upper()] = v.strip()
            key = head.upper()
            out[key] = (params, [])
        else:
            out[key][1].extend(float(v) for v in line.split(","))
    return out


def abaqus_energy(params, values):
    """ABAQUS's deviatoric energies (User's Guide, hyperelastic behavior)."""
    if "OGDEN" in params:
        n = int(params["N"])
        mus, alphas = values[0:2 * n:2], values[1:2 * n:2]
        return lambda l1, l2, l3: sum(2 * m / a ** 2 * (l1 ** a + l2 ** a + l3 ** a - 3)
                                      for m, a in zip(mus, alphas))
    i1 = lambda l1, l2, l3: l1 ** 2 + l2 ** 2 + l3 ** 2  # noqa: E731
    i2 = lambda l1, l2, l3: (l1 * l2) ** 2 + (l2 * l3) ** 2 + (l3 * l1) ** 2  # noqa: E731
    if "NEO HOOKE" in params:
        return lambda *l: values[0] * (i1(*l) - 3)
    if "MOONEY-RIVLIN" in params:
        return lambda *l: values[0] * (i1(*l) - 3) + values[1] * (i2(*l) - 3)
    raise AssertionError(f"unexpected *HYPERELASTIC options {params}")


@pytest.mark.parametrize("units", sorted(UNIT_SYSTEMS))
@pytest.mark.parametrize("law_name", sorted(CASES))
def test_abaqus_card_convention(law_name, units):
    u = unit_system(units)
    kw = parse_abaqus(abaqus_material(law_name, CASES[law_name], units=units))
    params, values = kw["HYPERELASTIC"]
    assert kw["MATERIAL"][0]["NAME"] == "BRAIN"
    card = abaqus_material(law_name, CASES[law_name], units=units, prony=PRONY)
    assert max(len(line) for line in card.splitlines()) <= 256  # ABAQUS's line limit
    stress_pa = uniaxial_stress(abaqus_energy(params, values), STRETCH) / u.per_pa
    assert_rel(stress_pa, reference(law_name), REL_TOL)
    # D1 = 2/K0 with K0 = 1000 G0 (the documented near-incompressible default)
    n = int(params.get("N", 1))
    d = values[-n:]
    g0 = prepare_material(law_name, CASES[law_name]).shear_modulus_pa
    assert d[0] == pytest.approx(2.0 / (1000.0 * g0 * u.per_pa), rel=1e-13)
    assert all(di == 0.0 for di in d[1:])
    assert kw["DENSITY"][1][0] == pytest.approx(1040.0 * u.per_kg_m3, rel=1e-13)
    assert "MODULI" not in params  # no viscoelasticity, nothing to state


def test_abaqus_layout_eight_values_a_line():
    card = abaqus_material("ogden3", CASES["ogden3"])
    lines = card.splitlines()
    i = next(k for k, l in enumerate(lines) if l.startswith("*HYPERELASTIC"))
    assert lines[i] == "*HYPERELASTIC, OGDEN, N=3"
    assert len(lines[i + 1].split(",")) == 8 and len(lines[i + 2].split(",")) == 1
    # CalculiX reads each field as f20.0
    assert all(len(v.strip()) <= 20 for v in lines[i + 1].split(","))


@pytest.mark.parametrize("moduli", ["instantaneous", "long-term"])
def test_abaqus_viscoelastic_moduli_stated_and_consistent(moduli):
    u = unit_system("mm-g-ms-MPa")  # a time unit other than s, to see tau converted
    kw = parse_abaqus(abaqus_material("ogden", CASES["ogden"], prony=PRONY, units=u.name,
                                      moduli=moduli))
    params, values = kw["HYPERELASTIC"]
    assert params["MODULI"] == {"instantaneous": "INSTANTANEOUS", "long-term": "LONG TERM"}[moduli]
    assert kw["VISCOELASTIC"][0] == {"TIME": "PRONY"}
    prony = np.reshape(kw["VISCOELASTIC"][1], (-1, 3))
    np.testing.assert_allclose(prony[:, 0], [p["g"] for p in PRONY], rtol=1e-14)
    np.testing.assert_array_equal(prony[:, 1], 0.0)  # bulk does not relax
    np.testing.assert_allclose(prony[:, 2], [p["tau_s"] * 1e3 for p in PRONY], rtol=1e-14)
    factor = 1.0 if moduli == "instantaneous" else 1.0 - sum(p["g"] for p in PRONY)
    assert values[0] / u.per_pa == pytest.approx(720.0 * factor, rel=1e-13)
    assert values[1] == -4.7


def test_params_may_be_long_term_and_come_from_fit_json():
    """A fit.json ``params`` mapping (with a Prony list and a non-material loop parameter)
    works as is; long-term input moduli are converted to instantaneous ones."""
    g_sum = sum(p["g"] for p in PRONY)
    fit_params = {"mu_pa": 720.0 * (1 - g_sum), "alpha": -4.7, "prony": PRONY,
                  "contact_offset_mm": 0.01}
    kw = parse_abaqus(abaqus_material("ogden", fit_params, params_moduli="long-term"))
    assert kw["HYPERELASTIC"][1][0] == pytest.approx(720e-6, rel=1e-13)
    assert kw["HYPERELASTIC"][0]["MODULI"] == "INSTANTANEOUS"
    kw = parse_abaqus(abaqus_material("ogden", fit_params, params_moduli="long-term",
                                      moduli="long-term"))
    assert kw["HYPERELASTIC"][1][0] == pytest.approx(720e-6 * (1 - g_sum), rel=1e-13)


def test_flat_prony_keys_are_read():
    flat = {"mu_pa": 720.0, "alpha": -4.7, "g1": 0.45, "tau1_s": 0.02, "g2": 0.25, "tau2_s": 1.5}
    assert prepare_material("ogden", flat).prony == ((0.45, 0.02), (0.25, 1.5))


def test_explicit_d1_and_bulk_modulus():
    kw = parse_abaqus(abaqus_material("ogden", CASES["ogden"], d1=0.05))
    assert kw["HYPERELASTIC"][1][2] == 0.05
    kw = parse_abaqus(abaqus_material("ogden", CASES["ogden"], bulk_modulus_pa=2.1e9))
    assert kw["HYPERELASTIC"][1][2] == pytest.approx(2.0 / 2.1e3, rel=1e-13)


@pytest.mark.parametrize("bad, match", [
    ({"mu_pa": 720.0}, "needs parameters"),
    ({"mu_pa": -1.0, "alpha": 2.0}, "must be positive"),
    # Infinity (Python's json writes inf so) had reached the writers: "nan cannot be written", exit 1
    ({"mu_pa": float("inf"), "alpha": -4.7}, "must be finite numbers, got mu_pa = inf"),
    ({"mu_pa": 720.0, "alpha": float("nan")}, "must be finite numbers, got alpha = nan"),
])
def test_bad_parameters_rejected(bad, match):
    with pytest.raises(ValueError, match=match):
        abaqus_material("ogden", bad)


def test_bad_prony_and_units_rejected():
    with pytest.raises(ValueError, match="sum to less than 1"):
        abaqus_material("ogden", CASES["ogden"], prony=[(0.6, 1.0), (0.5, 2.0)])
    with pytest.raises(ValueError, match="unknown unit system"):
        abaqus_material("ogden", CASES["ogden"], units="furlong")


# ---------------------------------------------------------------- units


@pytest.mark.parametrize("units", sorted(UNIT_SYSTEMS))
def test_unit_systems_are_consistent(units):
    """force = mass x length / time^2 and stress = force / length^2 in every system."""
    u = unit_system(units)
    per_kg = u.per_kg_m3 * u.per_m ** 3
    assert u.per_n == pytest.approx(per_kg * u.per_m / u.per_s ** 2, rel=1e-12)
    assert u.per_pa == pytest.approx(u.per_n / u.per_m ** 2, rel=1e-12)


# ---------------------------------------------------------------- LS-DYNA


def lsdyna_energy(mus, alphas):
    """*MAT_OGDEN_RUBBER: W = sum_j mu_j/alpha_j (l1^a + l2^a + l3^a - 3)."""
    return lambda l1, l2, l3: sum(m / a * (l1 ** a + l2 ** a + l3 ** a - 3)
                                  for m, a in zip(mus, alphas))


def parse_lsdyna(card: str):
    lines = [l for l in card.splitlines() if l.strip() and not l.startswith("$")]
    assert lines[0] == "*MAT_OGDEN_RUBBER_TITLE"
    title, cards = lines[1], lines[2:]
    assert all(len(c) <= 8 * FIELD_WIDTH for c in cards)
    return title, cards


def fields(line):
    return [line[i:i + FIELD_WIDTH] for i in range(0, len(line), FIELD_WIDTH)]


@pytest.mark.parametrize("law_name", sorted(CASES))
def test_lsdyna_conversion_is_exact(law_name):
    mat = prepare_material(law_name, CASES[law_name])
    mus_dyna, alphas = lsdyna_ogden_terms(mat.mus_pa, mat.alphas)
    assert_rel(uniaxial_stress(lsdyna_energy(mus_dyna, alphas), STRETCH), reference(law_name),
               REL_TOL)
    # LS-DYNA's initial shear modulus, (1/2) sum mu_j alpha_j, is bsipipe's sum mu_j
    assert 0.5 * np.sum(mus_dyna * alphas) == pytest.approx(mat.shear_modulus_pa, rel=1e-14)


@pytest.mark.parametrize("units", sorted(UNIT_SYSTEMS))
@pytest.mark.parametrize("law_name", sorted(CASES))
def test_lsdyna_card_fields(law_name, units):
    u = unit_system(units)
    mat = prepare_material(law_name, CASES[law_name])
    card = lsdyna_material(law_name, CASES[law_name], units=units, mid=7)
    assert max(len(line) for line in card.splitlines()) <= 80  # LS-DYNA reads 80 columns
    title, cards = parse_lsdyna(card)
    assert title == "BRAIN"
    c1 = fields(cards[0])
    assert c1[0] == f"{7:>10d}" and c1[3] == f"{0:>10d}"  # MID, N=0: right-justified ints
    n = len(mat.mus_pa)
    mu_text, alpha_text = fields(cards[1]), fields(cards[2])
    assert len(mu_text) == len(alpha_text) == n and len(cards) == 3
    exact_mu, exact_alpha = lsdyna_ogden_terms(mat.mus_pa * u.per_pa, mat.alphas)
    for text, exact in [*zip(mu_text, exact_mu), *zip(alpha_text, exact_alpha)]:
        assert abs(float(text) - exact) <= field_rounding_bound(text) * (1 + 1e-12), text
    # the stress from the printed card, within the printed fields' rounding
    mus = np.array([float(t) for t in mu_text])
    alphas = np.array([float(t) for t in alpha_text])
    stress_pa = uniaxial_stress(lsdyna_energy(mus, alphas), STRETCH) / u.per_pa
    bound = np.zeros_like(STRETCH)
    for j, (mt, at) in enumerate(zip(mu_text, alpha_text)):
        for vec, text in ((mus, mt), (alphas, at)):
            bumped_m, bumped_a = mus.copy(), alphas.copy()
            (bumped_m if vec is mus else bumped_a)[j] += field_rounding_bound(text)
            bumped = uniaxial_stress(lsdyna_energy(bumped_m, bumped_a), STRETCH) / u.per_pa
            bound += np.abs(bumped - stress_pa)
    ref = reference(law_name)
    # first-order propagation of the printed rounding; 1 % covers the second-order terms
    assert np.all(np.abs(stress_pa - ref) <= bound * 1.01 + 1e-12 * np.abs(ref))
    # PR: LS-DYNA's K = 2G(1+nu)/(3(1-2nu)) with G = (1/2) sum mu alpha gives K0
    pr_text = c1[2]
    pr = float(pr_text)
    g_card = 0.5 * np.sum(mus * alphas)
    k_card = 2 * g_card * (1 + pr) / (3 * (1 - 2 * pr))
    dk_dnu = 2 * g_card / 3 * (3 / (1 - 2 * pr) ** 2)
    k0 = mat.bulk_modulus_pa * u.per_pa
    assert abs(k_card - k0) <= dk_dnu * field_rounding_bound(pr_text) + 1e-4 * k0
    assert 0.499 < pr < 0.5
    assert float(c1[1]) == pytest.approx(1040.0 * u.per_kg_m3, rel=1e-4)


def test_lsdyna_viscoelastic_cards():
    u = unit_system("mm-g-ms-MPa")
    mat = prepare_material("ogden", CASES["ogden"], PRONY)
    _, cards = parse_lsdyna(lsdyna_material("ogden", CASES["ogden"], prony=PRONY, units=u.name))
    g_sum = sum(p["g"] for p in PRONY)
    # hyperelastic part is the long-term response
    mu_text = fields(cards[1])[0]
    expected_mu = 2 * 720.0 * (1 - g_sum) / -4.7 * u.per_pa
    assert abs(float(mu_text) - expected_mu) <= field_rounding_bound(mu_text)
    prony = [parse_fixed_card(c, 2) for c in cards[3:]]
    assert len(prony) == len(PRONY)
    for (gi, beta), term, line in zip(prony, PRONY, cards[3:]):
        gi_text, beta_text = fields(line)[:2]
        expected_gi = term["g"] * mat.shear_modulus_pa * u.per_pa
        assert abs(gi - expected_gi) <= field_rounding_bound(gi_text)
        assert abs(beta - 1.0 / (term["tau_s"] * u.per_s)) <= field_rounding_bound(beta_text)
    # PR is computed against the long-term shear modulus on the card
    pr = parse_fixed_card(cards[0])[2]
    assert pr == pytest.approx(poisson_ratio(mat.bulk_modulus_pa,
                                             mat.shear_modulus_pa * (1 - g_sum)), abs=1e-8)


@pytest.mark.parametrize("x", [720.0, -306.38297872340425, 3.0638297872e-4, -2.7777777777777e-12,
                               0.49950016655, 1.04e-9, 123456.789, 9.99999999999e20])
def test_field10_rounds_to_nearest_within_width(x):
    text = field10(x)
    assert len(text) == FIELD_WIDTH
    assert abs(float(text) - x) <= field_rounding_bound(text) * (1 + 1e-12)
    assert abs(float(text) / x - 1) < 1e-4  # at least 5 significant digits in 10 characters


# ---------------------------------------------------------------- FEBio


def febio_energy(elastic):
    """FEBio's uncoupled deviatoric energies: Ogden sum c/m^2 (...), Mooney-Rivlin."""
    p = {e.tag: float(e.text) for e in elastic if isinstance(e.tag, str)}
    if elastic.get("type") == "Ogden":
        terms = [(p[f"c{i}"], p[f"m{i}"]) for i in range(1, 7) if f"c{i}" in p]
        return lambda l1, l2, l3: sum(c / m ** 2 * (l1 ** m + l2 ** m + l3 ** m - 3)
                                      for c, m in terms)
    assert elastic.get("type") == "Mooney-Rivlin"
    return lambda l1, l2, l3: (p["c1"] * (l1 ** 2 + l2 ** 2 + l3 ** 2 - 3)
                               + p["c2"] * ((l1 * l2) ** 2 + (l2 * l3) ** 2 + (l3 * l1) ** 2 - 3))


@pytest.mark.parametrize("units", sorted(UNIT_SYSTEMS))
@pytest.mark.parametrize("law_name", sorted(CASES))
def test_febio_xml_convention(law_name, units):
    u = unit_system(units)
    root = ET.fromstring(febio_material(law_name, CASES[law_name], units=units, mat_id=3))
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    (material,) = root.findall("Material/material")
    assert material.get("id") == "3" and material.get("name") == "BRAIN"
    assert material.get("type") == ("Ogden" if law_name.startswith("ogden") else "Mooney-Rivlin")
    stress_pa = uniaxial_stress(febio_energy(material), STRETCH) / u.per_pa
    assert_rel(stress_pa, reference(law_name), REL_TOL)
    mat = prepare_material(law_name, CASES[law_name])
    k = float(material.find("k").text)
    assert k == pytest.approx(mat.bulk_modulus_pa * u.per_pa, rel=1e-13)
    assert float(material.find("density").text) == pytest.approx(1040 * u.per_kg_m3, rel=1e-13)


def test_febio_ogden_c_is_twice_mu():
    c, m = febio_ogden_terms([720.0, 100.0], [-4.7, 3.0])
    np.testing.assert_array_equal(c, [1440.0, 200.0])
    np.testing.assert_array_equal(m, [-4.7, 3.0])


def test_febio_viscoelastic_wrapper():
    u = unit_system("mm-g-ms-MPa")
    root = ET.fromstring(febio_material("ogden2", CASES["ogden2"], prony=PRONY, units=u.name))
    (material,) = root.findall("Material/material")
    assert material.get("type") == "uncoupled viscoelastic"
    p = {e.tag: float(e.text) for e in material if isinstance(e.tag, str) and e.tag != "elastic"}
    gs = [p[f"g{i}"] for i in range(1, len(PRONY) + 1)]
    np.testing.assert_allclose(gs, [t["g"] for t in PRONY], rtol=1e-14)
    np.testing.assert_allclose([p[f"t{i}"] for i in range(1, len(PRONY) + 1)],
                               [t["tau_s"] * 1e3 for t in PRONY], rtol=1e-14)
    # instantaneous response = (g0 + sum g_i) x elastic: the elastic part is instantaneous
    assert p["g0"] + sum(gs) == pytest.approx(1.0, abs=1e-14)
    elastic = material.find("elastic")
    assert elastic.get("type") == "Ogden"
    stress_pa = uniaxial_stress(febio_energy(elastic), STRETCH) / u.per_pa
    assert_rel(stress_pa, reference("ogden2"), REL_TOL)


def test_lsdyna_curve_fields_keep_a_blank_between_numbers():
    """Reals that need every digit of their field (23.749827027260117 s, 24.749965405452024 mm)
    had been written edge to edge, ``23.749827027260117524.749965405452023504``: legal for
    LS-DYNA's column reader, unreadable to a person or a free-format reader.  Each real now
    leaves a blank before it, and the columns still parse to the values."""
    from bsipipe.io.lsdyna import lsdyna_curve

    t = np.array([0.0, 23.749827027260117, 47.49965405452023504])
    d = np.array([0.0, 24.749965405452023504, 0.0])
    lines = lsdyna_curve(1, t, d).splitlines()[4:]
    assert len(lines) == 3
    for line, a, o in zip(lines, t, d):
        assert line[0] == " " and (len(line) <= 20 or line[20] == " "), line
        assert len(line.split()) == 2, line
        x, y = float(line[:20]), float(line[20:40])          # the 20-column fields of the curve
        assert x == pytest.approx(a, rel=1e-12) and y == pytest.approx(o, rel=1e-12, abs=0)
