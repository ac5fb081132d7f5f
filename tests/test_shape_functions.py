"""Element shape functions, inverse isoparametric mapping and point location.

Exact checks first (Kronecker property, partition of unity, derivatives against central
differences, the inverse map recovering known natural coordinates of distorted elements to
1e-12), then completeness (the fields each element reproduces exactly: linear fields for
all four, complete quadratics for C3D10 and C3D20 with straight edges; C3D4/C3D8
interpolating a quadratic converge at second order), then point location in hexahedral and
tetrahedral meshes with moved interior nodes.

The mesh helpers here (``brick_hex``, ``hex_to_tet``, ``add_midside``) are shared with
``test_compare.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from bsipipe.geometry.shape_functions import (ELEMENTS, PointLocator, _HEX20_EDGES, _TET10_EDGES, _WEDGE15_EDGES,
                                              element_type, interpolate, inverse_map, shape_functions)

# Six tetrahedra of a brick around its diagonal node 0 - node 6 (0-based C3D8 order).
KUHN = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]


def brick_hex(nx, ny, nz, size=(10.0, 8.0, 6.0), origin=(0.0, 0.0, 0.0), jitter=0.0, seed=0):
    """Coordinates (n, 3) and C3D8 connectivity (ne, 8), 0-based."""
    xs = [np.linspace(0.0, size[a], n + 1) + origin[a] for a, n in enumerate((nx, ny, nz))]
    I, J, K = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    coords = np.column_stack([xs[0][I.ravel()], xs[1][J.ravel()], xs[2][K.ravel()]])
    if jitter:
        rng = np.random.default_rng(seed)
        h = np.array([size[0] / nx, size[1] / ny, size[2] / nz])
        interior = ((I > 0) & (I < nx) & (J > 0) & (J < ny) & (K > 0) & (K < nz)).ravel()
        coords[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 3)) * h

    def nid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    conn = []
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                conn.append([nid(i, j, k), nid(i + 1, j, k), nid(i + 1, j + 1, k), nid(i, j + 1, k),
                             nid(i, j, k + 1), nid(i + 1, j, k + 1), nid(i + 1, j + 1, k + 1), nid(i, j + 1, k + 1)])
    return coords, np.array(conn, dtype=np.int64)


def hex_to_tet(conn):
    return np.array([[h[a] for a in t] for h in conn for t in KUHN], dtype=np.int64)


def hex_to_wedge(conn):
    """Two C3D6 wedges per C3D8 brick, split across its diagonal 1-3 (0-based 0-2)."""
    return np.array([[h[a] for a in w] for h in conn for w in ((0, 1, 2, 4, 5, 6), (0, 2, 3, 4, 6, 7))],
                    dtype=np.int64)


def add_midside(coords, conn, kind):
    """Quadratic elements from linear ones: ``kind`` "C3D10" (from C3D4), "C3D15" (from C3D6) or
    "C3D20" (from C3D8)."""
    edges = {"C3D10": _TET10_EDGES, "C3D15": _WEDGE15_EDGES, "C3D20": _HEX20_EDGES}[kind]
    coords = [tuple(c) for c in coords]
    index: dict = {}
    out = []
    for el in conn:
        row = list(el)
        for a, b in edges:
            key = tuple(sorted((int(el[a]), int(el[b]))))
            if key not in index:
                index[key] = len(coords)
                coords.append(tuple((np.asarray(coords[key[0]]) + np.asarray(coords[key[1]])) / 2))
            row.append(index[key])
        out.append(row)
    return np.array(coords, dtype=float), np.array(out, dtype=np.int64)


def points_inside(n, size=(10.0, 8.0, 6.0), margin=0.5, seed=1):
    rng = np.random.default_rng(seed)
    lo = np.full(3, margin)
    hi = np.asarray(size) - margin
    return rng.uniform(lo, hi, (n, 3))


def random_natural(et, n, rng, inside=True):
    if et.family == "hex":
        return rng.uniform(-1, 1, (n, 3)) if inside else rng.uniform(-1.5, 1.5, (n, 3))
    if et.family == "wedge":
        return np.column_stack([rng.dirichlet(np.ones(3), n)[:, :2], rng.uniform(-1, 1, n)])
    return rng.dirichlet(np.ones(4), n)[:, :3]


def distorted_nodes(et, rng, noise=0.06):
    """A general element: an affine map of the reference element plus a random node perturbation
    (curved edges for the quadratic elements), far from degenerate."""
    A = rng.normal(size=(3, 3)) * 0.4 + np.diag([4.0, 3.0, 2.5])
    return et.natural_nodes @ A.T + rng.normal(0, noise * 2.5, (et.n_nodes, 3)) + rng.normal(0, 5, 3)


# --- shape functions ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(ELEMENTS))
def test_kronecker_and_partition_of_unity(name):
    et = ELEMENTS[name]
    N = shape_functions(name, et.natural_nodes)
    assert np.abs(N - np.eye(et.n_nodes)).max() < 1e-15
    xi = random_natural(et, 200, np.random.default_rng(0))
    assert np.abs(shape_functions(name, xi).sum(axis=1) - 1.0).max() < 1e-14
    # derivatives of a partition of unity sum to zero
    assert np.abs(et.dshape(xi).sum(axis=1)).max() < 1e-13


@pytest.mark.parametrize("name", sorted(ELEMENTS))
def test_derivatives_match_central_differences(name):
    et = ELEMENTS[name]
    xi = random_natural(et, 50, np.random.default_rng(1))
    h = 1e-6
    fd = np.stack([(et.shape(xi + h * e) - et.shape(xi - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    # the shape functions are polynomials of degree <= 3 in each variable: central differences
    # are exact up to h^2 * f''' / 6 ~ 1e-12, plus rounding eps / h ~ 1e-10
    assert np.abs(et.dshape(xi) - fd).max() < 1e-9


def test_element_names():
    assert element_type("C3D8R").name == "C3D8"
    assert element_type("c3d10m").name == "C3D10"
    assert element_type("hexahedron20").name == "C3D20"
    assert element_type("C3D6H").name == "C3D6" and element_type("wedge15").name == "C3D15"
    with pytest.raises(KeyError):
        element_type("C3D27")
    with pytest.raises(KeyError):
        element_type("C3D8X1")


# --- inverse mapping ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(ELEMENTS))
def test_inverse_map_recovers_natural_coordinates(name):
    rng = np.random.default_rng(2)
    et = ELEMENTS[name]
    for _ in range(5):
        X = distorted_nodes(et, rng)
        xi = random_natural(et, 40, rng)
        x = shape_functions(name, xi) @ X
        xi2, conv = inverse_map(name, X, x)
        assert conv.all()
        assert np.abs(xi2 - xi).max() < 1e-12
        assert et.contains(xi2, 1e-9).all()


def test_inverse_map_outside_points_are_not_contained():
    rng = np.random.default_rng(3)
    et = ELEMENTS["C3D8"]
    X = distorted_nodes(et, rng, noise=0.0)        # affine hexahedron: the map is exact everywhere
    xi = rng.uniform(-3, 3, (200, 3))
    x = shape_functions("C3D8", xi) @ X
    xi2, conv = inverse_map("C3D8", X, x)
    assert conv.all()
    assert np.abs(xi2 - xi).max() < 1e-10
    inside = np.all(np.abs(xi) <= 1, axis=1)
    assert np.array_equal(et.contains(xi2, 1e-9), inside)


# --- completeness --------------------------------------------------------------------------------

def linear_field(x):
    A = np.array([[0.02, -0.01, 0.03], [0.005, 0.04, -0.02], [-0.03, 0.01, 0.015]])
    return x @ A.T + np.array([0.1, -0.2, 0.05])


def quadratic_field(x):
    x0, y, z = x[:, 0], x[:, 1], x[:, 2]
    return np.column_stack([0.01 * x0 ** 2 - 0.02 * x0 * y + 0.003 * z ** 2,
                            0.004 * y ** 2 + 0.01 * y * z - 0.002 * x0,
                            -0.006 * z ** 2 + 0.005 * x0 * z + 0.001 * y ** 2 + 0.3])


@pytest.mark.parametrize("name", sorted(ELEMENTS))
def test_linear_fields_are_reproduced_exactly(name):
    rng = np.random.default_rng(4)
    et = ELEMENTS[name]
    X = distorted_nodes(et, rng)
    xi = random_natural(et, 30, rng)
    x = shape_functions(name, xi) @ X
    assert np.abs(interpolate(name, linear_field(X), xi) - linear_field(x)).max() < 1e-13


@pytest.mark.parametrize("name", ["C3D10", "C3D15", "C3D20"])
def test_quadratic_fields_are_reproduced_by_straight_edged_quadratic_elements(name):
    rng = np.random.default_rng(5)
    et = ELEMENTS[name]
    X = distorted_nodes(et, rng, noise=0.0)        # affine: straight edges, mid-side nodes at midpoints
    xi = random_natural(et, 30, rng)
    x = shape_functions(name, xi) @ X
    assert np.abs(interpolate(name, quadratic_field(X), xi) - quadratic_field(x)).max() < 1e-12


@pytest.mark.parametrize("kind", ["hex", "tet"])
def test_linear_elements_converge_at_second_order_on_a_quadratic(kind):
    pts = points_inside(60, seed=6)
    errs = []
    for n in (2, 4, 8):
        coords, conn = brick_hex(n, n, n)
        blocks = [("C3D8", conn)] if kind == "hex" else [("C3D4", hex_to_tet(conn))]
        loc = PointLocator(coords, blocks)
        where = loc.locate(pts)
        assert where.inside.all()
        errs.append(np.abs(loc.interpolate(quadratic_field(coords), where) - quadratic_field(pts)).max())
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    # halving h divides the interpolation error by 4 (O(h^2)); 3 allows for where the points fall
    assert np.all(ratios > 3.0), ratios


# --- point location -------------------------------------------------------------------------------

def _mesh(kind, jitter=0.15):
    coords, conn = brick_hex(5, 4, 3, jitter=jitter, seed=7)
    if kind == "C3D8":
        return coords, [("C3D8", conn)]
    if kind == "C3D6":
        return coords, [("C3D6", hex_to_wedge(conn))]
    if kind == "C3D15":
        c, q = add_midside(coords, hex_to_wedge(conn), "C3D15")
        return c, [("C3D15", q)]
    if kind == "C3D20":
        c, q = add_midside(coords, conn, "C3D20")
        return c, [("C3D20", q)]
    tets = hex_to_tet(conn)
    if kind == "C3D4":
        return coords, [("C3D4", tets)]
    c, q = add_midside(coords, tets, "C3D10")
    return c, [("C3D10", q)]


@pytest.mark.parametrize("kind", ["C3D8", "C3D4", "C3D10", "C3D20", "C3D6", "C3D15"])
def test_locate_points_in_meshes_with_moved_interior_nodes(kind):
    coords, blocks = _mesh(kind)
    loc = PointLocator(coords, blocks)
    pts = points_inside(300, margin=0.05, seed=8)
    where = loc.locate(pts)
    assert where.inside.all() and where.found.all()
    et = ELEMENTS[kind]
    conn = blocks[0][1]
    back = np.array([shape_functions(kind, where.xi[i]) @ coords[conn[where.element[i]]] for i in range(len(pts))])
    assert np.abs(back[:, 0, :] - pts).max() < 1e-10
    assert et.contains(where.xi, 1e-8).all()
    # a linear field through the located elements is exact
    assert np.abs(loc.interpolate(linear_field(coords), where) - linear_field(pts)).max() < 1e-12


def test_points_outside_the_mesh():
    coords, blocks = _mesh("C3D8", jitter=0.0)
    loc = PointLocator(coords, blocks)
    pts = np.array([[-0.3, 4.0, 3.0], [10.2, 4.0, 3.0], [5.0, 4.0, 9.0], [5.0, 4.0, 3.0]])
    where = loc.locate(pts)
    assert where.found.tolist() == [False, False, False, True]
    where = loc.locate(pts, outside_tol_mm=0.5)
    assert where.found.tolist() == [True, True, False, True]
    assert where.inside.tolist() == [False, False, False, True]
    assert np.allclose(where.distance_mm[:2], [0.3, 0.2], atol=1e-10)
    # a point outside takes the value at the nearest surface point
    u = loc.interpolate(linear_field(coords), where)
    assert np.allclose(u[0], linear_field(np.array([[0.0, 4.0, 3.0]]))[0], atol=1e-12)
    assert np.isnan(u[2]).all()


@pytest.mark.parametrize("kind", ["C3D8", "C3D4", "C3D10", "C3D20", "C3D6", "C3D15"])
def test_distance_outside_is_the_nearest_surface_point_in_space(kind):
    """120 points 0.3 mm outside the brick's faces: the distance is 0.3 mm for every element
    type.  The nearest point had been the projection in natural coordinates, a point of the
    surface but not the nearest: 0.31-0.57 mm for tetrahedra (median 0.37), so with
    ``outside_tol_mm`` 0.5, 16 of 120 markers were refused."""
    coords, blocks = _mesh(kind, jitter=0.0)
    loc = PointLocator(coords, blocks)
    rng = np.random.default_rng(3)
    size = np.array([10.0, 8.0, 6.0])
    pts = []
    for ax in range(3):
        for side in (0, 1):
            for _ in range(20):
                q = rng.uniform(0.1, 0.9, 3) * size
                q[ax] = side * size[ax] + (0.3 if side else -0.3)
                pts.append(q)
    pts = np.array(pts)
    where = loc.locate(pts, outside_tol_mm=0.5)
    assert where.found.all() and not where.inside.any()
    assert np.abs(where.distance_mm - 0.3).max() < 1e-6
    # the value taken is the field's at the nearest surface point (the point moved onto the face)
    foot = pts.copy()
    for ax in range(3):
        foot[:, ax] = np.clip(foot[:, ax], 0.0, size[ax])
    assert np.abs(loc.interpolate(linear_field(coords), where) - linear_field(foot)).max() < 1e-5


def test_shared_faces_give_one_value():
    """A point on a face, edge or node shared by several elements has the same interpolated
    value in each of them (the interpolation is continuous), so which element the locator
    picks does not matter."""
    coords, conn = brick_hex(2, 2, 2, size=(2.0, 2.0, 2.0), jitter=0.0)
    field = quadratic_field(coords)
    pts = np.array([[1.0, 1.0, 1.0], [1.0, 0.5, 0.5], [0.3, 1.0, 1.7], [1.0, 1.0, 0.2]])
    for p in pts:
        values = []
        for el in conn:
            xi, conv = inverse_map("C3D8", coords[el], p[None])
            if conv[0] and ELEMENTS["C3D8"].contains(xi, 1e-12)[0]:
                values.append(interpolate("C3D8", field[el], xi)[0])
        assert len(values) >= 2
        assert np.abs(np.array(values) - values[0]).max() < 1e-15
