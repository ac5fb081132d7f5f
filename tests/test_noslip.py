"""No-slip platens: the axisymmetric felupe model, its tables, and the published ratios.

The published numbers (``../shared/data/real/README.md``, the study this project serves):
axisymmetric FE on a 32 x 32 mesh, one-term Ogden, alpha = -4.7; force over the homogeneous
force about 1.21 (10 % strain) and 1.25 (30 %) at height/diameter 1, about 1.6 and 1.9 at
0.5; at 1 % strain near the bonded-cylinder factor 1 + 2 S^2, S = D / (4 H).
"""

from __future__ import annotations

import numpy as np
import pytest

from bsipipe.mechanics import noslip as ns
from bsipipe.mechanics.hyperelastic import ogden_nominal_stress

ALPHA = -4.7
ASPECT_SEED = 12.0 / 18.0   # the seeds' 18 mm x 12 mm sheep-brain cylinder


def _ratio(stretch, aspect, alpha=ALPHA):
    s = np.atleast_1d(np.asarray(stretch, dtype=float))
    return ns.noslip_nominal_stress(s, 1.0, alpha, aspect) / ogden_nominal_stress(s, [1.0], [alpha])


@pytest.fixture
def no_fe(monkeypatch):
    """Fail if a table would be computed (the shipped tables must serve these aspects)."""
    def refuse(*args, **kwargs):
        raise AssertionError("a shipped no-slip table is missing or stale: FE would run")
    monkeypatch.setattr(ns, "build_table", refuse)
    ns._load_table.cache_clear()
    yield
    ns._load_table.cache_clear()


# --- the material and the FE model --------------------------------------------------------

def test_closed_form_ogden_equals_felupe_ogden_and_its_own_derivative():
    """Stress and tangent of :class:`OgdenIsochoric` vs felupe's automatic-differentiation Ogden.

    tensortrax perturbs equal eigenvalues (relative 1e-7 level), so the comparison is at
    1e-6 on moderate deformations; the tangent is also checked against central differences
    of the stress at the undeformed state and at repeated eigenvalues, where the closed form
    switches to its limit.
    """
    import felupe as fem

    rng = np.random.default_rng(0)
    F = np.eye(3)[:, :, None, None] + 0.15 * rng.standard_normal((3, 3, 4, 50))
    F[2, :2] = F[:2, 2] = 0.0                      # axisymmetric structure
    F[2, 2] = np.abs(F[2, 2]) + 0.3
    sv = np.zeros((0, 4, 50))
    for alpha in (-12.0, -4.7, 1.0, 2.0, 7.5):
        ref = fem.Hyperelastic(fem.ogden, mu=[1.3], alpha=[alpha])
        mine = ns.OgdenIsochoric(1.3, alpha)
        P0, A0 = ref.gradient([F, sv])[0], ref.hessian([F, sv])[0]
        P1, A1 = mine.gradient([F, sv])[0], mine.hessian([F, sv])[0]
        assert np.abs(P1 - P0).max() <= 1e-6 * np.abs(P0).max()
        assert np.abs(A1 - A0).max() <= 1e-6 * np.abs(A0).max()
        for Fi in (np.eye(3), np.diag([1.2, 1.2, 1 / 1.44]), np.diag([0.8, 1.1, 1.1 + 1e-7])):
            Fa, s1 = Fi[:, :, None, None], np.zeros((0, 1, 1))
            A = mine.hessian([Fa, s1])[0][..., 0, 0]
            h = 1e-6
            Afd = np.zeros((3, 3, 3, 3))
            for k in range(3):
                for m in range(3):
                    E = np.zeros((3, 3, 1, 1))
                    E[k, m] = h
                    dP = mine.gradient([Fa + E, s1])[0] - mine.gradient([Fa - E, s1])[0]
                    Afd[:, :, k, m] = dP[..., 0, 0] / (2 * h)
            assert np.abs(A - Afd).max() <= 1e-7 * np.abs(A).max()


def test_frictionless_fe_equals_homogeneous_formula():
    """A top face free to slide: the FE is the homogeneous Ogden formula (convention check).

    The 0.2 % tolerance covers the bulk modulus (K = 5000 mu: J - 1 ~ P / K).
    """
    s = np.array([0.95, 0.8, 0.7])
    for alpha in (-4.7, 3.0):
        run = ns.noslip_simulate(s, 720.0, alpha, 18.0, 12.0, mesh=ns.FEMesh(6, 1.0),
                                 boundary="frictionless")
        ratio = run.force_ratio
        print(f"\nfrictionless FE / homogeneous formula, alpha {alpha}: {np.round(ratio, 5)}")
        assert np.all(np.abs(ratio - 1.0) < 2e-3)
        # homogeneous compression: the width is D / sqrt(stretch) everywhere
        np.testing.assert_allclose(run.bulge_width_mm, 18.0 / np.sqrt(s), rtol=2e-3)


def test_table_interpolation_matches_a_direct_fe_run():
    """Off-grid alpha and stretches on the seeds' aspect: table vs a direct FE run, 0.5 %.

    Also the units of :func:`noslip_simulate`: force = stress x pi D^2 / 4 in m^2.
    """
    s = np.array([0.97, 0.85, 0.75, 0.65])
    alpha = -5.3
    run = ns.noslip_simulate(s, 720.0, alpha, 18.0, 12.0)
    table = ns.noslip_nominal_stress(s, 720.0, alpha, ASPECT_SEED)
    err = table / run.nominal_stress_pa - 1.0
    werr = ns.noslip_bulge_width(s, alpha, 18.0, ASPECT_SEED) / run.bulge_width_mm - 1.0
    print(f"\ntable vs direct FE (alpha {alpha}, H/D 2/3) at {s}: force {np.round(100 * err, 3)} %, "
          f"width {np.round(100 * werr, 3)} %; FE {run.seconds:.1f} s, {run.iterations.sum()} Newton iterations")
    assert np.all(np.abs(err) < 5e-3)
    assert np.all(np.abs(werr) < 5e-3)
    np.testing.assert_allclose(run.force_n, run.nominal_stress_pa * np.pi * 0.018**2 / 4, rtol=1e-12)
    assert np.all(run.force_n < 0)


def test_force_changes_under_one_percent_when_every_cell_is_halved():
    """Mesh refinement: the default mesh (the tables') against every cell halved, at
    H/D 1/2 (the largest barrelling of the shipped aspects) and the seeds' alpha, at 10 and
    20 % compression; 20 % is where the free surface has just folded onto the platen and
    the change is largest (0.87 % here; 0.48 % at 30 %).  The issue asks for under 1 %;
    ``scripts/build_noslip_tables.py --refine`` measures other alphas, aspects and 30-40 %.
    """
    s = np.array([0.9, 0.8])
    fine = ns.FEMesh(2 * ns.DEFAULT_MESH.n_radial, ns.DEFAULT_MESH.grading)
    nominal, _, _ = ns._solve_unit(s, ALPHA, 0.5, fine)
    ratio_fine = nominal / ogden_nominal_stress(s, [1.0], [ALPHA])
    nominal, _, _ = ns._solve_unit(s, ALPHA, 0.5)
    ratio = nominal / ogden_nominal_stress(s, [1.0], [ALPHA])
    change = ratio_fine / ratio - 1.0
    print(f"\nH/D 0.5, alpha {ALPHA}: ratio {np.round(ratio, 4)} ({ns.DEFAULT_MESH.n_radial} radial cells), "
          f"{np.round(ratio_fine, 4)} ({fine.n_radial}); change {np.round(100 * change, 3)} % at stretch {s}")
    assert np.all(np.abs(change) < 0.01)
    # the tables are the default mesh: the same numbers, up to interpolation in alpha
    np.testing.assert_allclose(_ratio(s, 0.5), ratio, rtol=1e-3)


def test_fe_with_the_published_mesh_reproduces_the_published_ratios():
    """The published discretisation (uniform 32 x 32 quarter mesh, no fold-over contact)
    gives the published ratios to their quoted precision (+-0.005 at H/D 1, +-0.05 at 0.5)
    """
    s = np.array([0.9, 0.7])
    for aspect, published, tol in ((1.0, (1.21, 1.25), 0.005), (0.5, (1.6, 1.9), 0.05)):
        nominal, _, _ = ns._solve_unit(s, ALPHA, aspect, ns.FEMesh(32, 1.0), fold_over="none")
        ratio = nominal / ogden_nominal_stress(s, [1.0], [ALPHA])
        print(f"\nuniform 32x32, no fold-over contact, H/D {aspect}: ratios {np.round(ratio, 4)} (published {published})")
        assert np.all(np.abs(ratio - np.array(published)) <= tol)


# --- the shipped tables -------------------------------------------------------------------

def test_shipped_tables_cover_the_common_aspects_without_fe(no_fe):
    for aspect in ns.SHIPPED_ASPECTS:
        table = ns.noslip_table(aspect)
        assert table.meta["table_version"] == ns.TABLE_VERSION
        # built by the current model on the current grid (the key covers both)
        assert table.meta["key"] == ns._grid_key(aspect, ns.ALPHA_GRID, ns.STRETCH_GRID, ns.DEFAULT_MESH)
        path = ns.shipped_dir() / ns.table_filename(aspect)
        assert path.is_file() and path.stat().st_size < 50_000
        assert table.alpha_range() == [(-12.0, -1.0), (1.0, 12.0)]
        check = table.meta["interpolation_check"]
        print(f"\nH/D {aspect:.4f}: interpolation vs FE at {len(check['alphas'])} alpha midpoints: "
              f"force {100 * check['max_rel_err_force']:.3f} % (worst alpha {check['worst_force']['alpha']}, "
              f"stretch {check['worst_force']['stretch']}), width {100 * check['max_rel_err_width']:.3f} %")
        assert check["max_rel_err_force"] < 3e-3
        assert check["max_rel_err_width"] < 3e-3


def test_ratios_against_the_published_values(no_fe):
    """Mesh-converged ratios vs the published 32 x 32 values.

    At 10 % strain they agree to the published precision.  At 30 % the converged ratio is
    lower: the study in ``scripts/build_noslip_tables.py --study`` shows the uniform 32 x 32
    mesh 2 % stiff at 30 % at H/D 1 (and its folded layer passing through the platen); the
    tolerance, 3 %, is that discretisation difference plus the quoted precision.
    """
    published = {1.0: {0.9: 1.21, 0.7: 1.25}, 0.5: {0.9: 1.6, 0.7: 1.9}}
    for aspect, pairs in published.items():
        s = np.array(sorted(pairs, reverse=True))
        ratio = _ratio(s, aspect)
        ref = np.array([pairs[x] for x in s])
        print(f"\nH/D {aspect}: no-slip / homogeneous at 10 %, 30 % strain: {np.round(ratio, 4)} "
              f"(published {ref})")
        assert np.all(np.abs(ratio / ref - 1.0) < 0.03)
    # the seeds' aspect lies between
    r_seed = _ratio([0.9, 0.7], ASPECT_SEED)
    print(f"H/D 2/3: {np.round(r_seed, 4)}")
    assert np.all(_ratio([0.9, 0.7], 1.0) < r_seed) and np.all(r_seed < _ratio([0.9, 0.7], 0.5))


def test_small_strain_ratio_is_the_bonded_cylinder_factor(no_fe):
    """At 1 % strain the ratio is a property of the geometry only (the same for every
    alpha: linear elasticity) and approaches 1 + 2 S^2 as S grows (the thin-layer limit).
    """
    excess = []
    for aspect in sorted(ns.SHIPPED_ASPECTS, reverse=True):   # S increasing
        S = 1.0 / (4.0 * aspect)
        r = np.array([_ratio(0.99, aspect, a)[0] for a in (-12.0, -4.7, -1.0, 1.0, 2.0, 12.0)])
        gent = 1.0 + 2.0 * S**2
        print(f"\nH/D {aspect:.4f}, S {S:.3f}: ratio at 1 % strain {r.mean():.4f} "
              f"(spread over alpha {np.ptp(r):.1e}), 1 + 2 S^2 = {gent:.4f}, excess {100 * (r.mean() / gent - 1):.1f} %")
        assert np.ptp(r) < 0.01 * r.mean()
        excess.append(r.mean() / gent - 1.0)
    assert all(e > 0 for e in excess)
    assert all(b < a for a, b in zip(excess[:-1], excess[1:]))
    # A thinner disc, S = 1, by a direct FE step of 0.1 %: the excess falls roughly as
    # 1.6 % / S (6.4 % at S = 1/4, 3.1 % at S = 1/2), so it must be under 2 % here.
    nominal, _, _ = ns._solve_unit([0.999], ALPHA, 0.25)
    r = nominal[0] / ogden_nominal_stress(0.999, [1.0], [ALPHA])
    print(f"H/D 0.25, S 1: ratio at 0.1 % strain {r:.4f}, 1 + 2 S^2 = 3")
    assert abs(r / 3.0 - 1.0) < 0.02


def test_mid_height_bulge_exceeds_the_homogeneous_width(no_fe):
    """Volume is conserved and the bonded ends stay at D, so the mid-height width must
    exceed the homogeneous D / sqrt(stretch); at stretch 1 it is D.
    """
    s = np.linspace(0.6, 0.99, 12)
    for aspect in ns.SHIPPED_ASPECTS:
        w = ns.noslip_bulge_width(s, -6.3, 18.99, aspect)
        assert np.all(w > 18.99 / np.sqrt(s))
        assert np.all(np.diff(w) < 0)
    assert float(ns.noslip_bulge_width(1.0, -6.3, 18.99, ASPECT_SEED)) == pytest.approx(18.99, rel=1e-12)
    # the seeds' width series (1 mm/s): 18.99 -> 20.65 mm
    s_fine = np.linspace(0.6, 1.0, 401)
    w = ns.noslip_bulge_width(s_fine, -6.3, 18.99, ASPECT_SEED)
    s_at = s_fine[np.argmin(np.abs(w - 20.65))]
    print(f"\nwidth 18.99 -> 20.65 mm (H/D 2/3, alpha -6.3): no-slip at stretch {s_at:.3f}, "
          f"homogeneous at {(18.99 / 20.65) ** 2:.3f}")


def test_input_checks(no_fe):
    with pytest.raises(ValueError, match="alpha"):
        ns.noslip_nominal_stress([0.9], 720.0, -0.5, ASPECT_SEED)
    with pytest.raises(ValueError, match="alpha"):
        ns.noslip_nominal_stress([0.9], 720.0, -20.0, ASPECT_SEED)
    with pytest.raises(ValueError, match="stretch"):
        ns.noslip_nominal_stress([0.5], 720.0, -4.7, ASPECT_SEED)
    with pytest.raises(ValueError, match="aspect"):
        ns.noslip_nominal_stress([0.9], 720.0, -4.7, 0.0)
    # just past contact (finite differences of a fit): a smooth linear continuation
    p = ns.noslip_nominal_stress([1.0, 1.0 + 1e-6, 1.0 - 1e-6], 720.0, -4.7, ASPECT_SEED)
    assert p[0] == 0.0 and p[1] > 0.0 > p[2]
    assert p[1] == pytest.approx(-p[2], rel=1e-3)


# --- the cache ------------------------------------------------------------------------------

def test_new_aspect_is_computed_once_then_read_from_the_cache(tmp_path, monkeypatch):
    """A small grid and mesh stand in for the real ones: computed, cached atomically, reused."""
    monkeypatch.setenv("BSIPIPE_CACHE", str(tmp_path))
    monkeypatch.setattr(ns, "ALPHA_GRID", np.array([-6.0, -5.0, -4.0, -3.0]))
    monkeypatch.setattr(ns, "STRETCH_GRID", np.array([1.0, 0.999, 0.998, 0.98, 0.95]))
    mesh = ns.FEMesh(6, 4.0)
    ns._load_table.cache_clear()
    try:
        table = ns.noslip_table(0.8, mesh=mesh)
        files = list((tmp_path / "noslip").glob("noslip_a0.8000_*.npz"))
        assert len(files) == 1 and not list((tmp_path / "noslip").glob(".*tmp"))
        ns._load_table.cache_clear()
        monkeypatch.setattr(ns, "build_table", lambda *a, **k: pytest.fail("recomputed a cached table"))
        again = ns.noslip_table(0.8, mesh=mesh)
        np.testing.assert_array_equal(again.ratio, table.ratio)
        # a different mesh is a different key
        assert ns.table_filename(0.8, mesh=ns.FEMesh(8, 4.0)) != files[0].name
    finally:
        ns._load_table.cache_clear()
