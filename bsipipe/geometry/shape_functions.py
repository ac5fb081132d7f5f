r"""Isoparametric solid elements: shape functions, inverse mapping, point location.

Elements and node orders are ABAQUS's (also VTK's and meshio's for these six):

========  =====================  ==========================================================
name      reference element      shape functions :math:`N_i(\xi, \eta, \zeta)`
========  =====================  ==========================================================
C3D4      tetrahedron            :math:`L_1 = 1 - \xi - \eta - \zeta,\ L_2 = \xi,\ L_3 = \eta,\ L_4 = \zeta`
C3D10     tetrahedron            corners :math:`L_i (2 L_i - 1)`; mid-edge nodes 5..10 on edges
                                 1-2, 2-3, 3-1, 1-4, 2-4, 3-4: :math:`4 L_i L_j`
C3D6      wedge (triangle        :math:`L_i (1 \mp \zeta) / 2` (nodes 1-3 at :math:`\zeta = -1`, 4-6 above them)
          :math:`\times [-1, 1]`)
C3D15     wedge                  corners :math:`\frac12 L_i (2 L_i - 1)(1 \mp \zeta) - \frac12 L_i (1 - \zeta^2)`;
                                 nodes 7-12 on the triangles' edges 1-2, 2-3, 3-1, 4-5, 5-6, 6-4:
                                 :math:`2 L_i L_j (1 \mp \zeta)`; 13-15 on the sides 1-4, 2-5, 3-6:
                                 :math:`L_i (1 - \zeta^2)`
C3D8      cube :math:`[-1, 1]^3`   :math:`\frac18 (1 + \xi\xi_i)(1 + \eta\eta_i)(1 + \zeta\zeta_i)`
C3D20     cube :math:`[-1, 1]^3`   corners :math:`\frac18 (1+\xi\xi_i)(1+\eta\eta_i)(1+\zeta\zeta_i)(\xi\xi_i+\eta\eta_i+\zeta\zeta_i-2)`;
                                 mid-edge nodes 9..20 (edges 1-2, 2-3, 3-4, 4-1, 5-6, 6-7,
                                 7-8, 8-5, 1-5, 2-6, 3-7, 4-8), e.g. :math:`\xi_i = 0`:
                                 :math:`\frac14 (1-\xi^2)(1+\eta\eta_i)(1+\zeta\zeta_i)`
========  =====================  ==========================================================

C3D8 nodes 1-4 are the face :math:`\zeta = -1` counter-clockwise seen from :math:`+\zeta`,
5-8 the face :math:`\zeta = +1`.  A point :math:`\mathbf x` inside an element has natural
coordinates :math:`\boldsymbol\xi` with :math:`\mathbf x = \sum_i N_i(\boldsymbol\xi)\mathbf X_i`,
found by Newton's method (:func:`inverse_map`; one step for C3D4, whose map is affine), and a
nodal field interpolates as :math:`u(\mathbf x) = \sum_i N_i(\boldsymbol\xi) u_i`.
:class:`PointLocator` finds the element holding each point: candidates from a KD-tree on the
element centroids (every element whose centroid lies within the largest element radius),
then the containment test on the natural coordinates within a tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["ElementType", "ELEMENTS", "MESHIO_TO_ABAQUS", "element_type", "shape_functions",
           "shape_derivatives", "inverse_map", "interpolate", "nearest_point", "Location", "PointLocator"]


# --- element definitions --------------------------------------------------------------------

_HEX8_NODES = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                        [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
_HEX20_EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
                (0, 4), (1, 5), (2, 6), (3, 7)]
_HEX20_NODES = np.vstack([_HEX8_NODES] + [(_HEX8_NODES[a] + _HEX8_NODES[b]) / 2 for a, b in _HEX20_EDGES])
_TET4_NODES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
_TET10_EDGES = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
_TET10_NODES = np.vstack([_TET4_NODES] + [(_TET4_NODES[a] + _TET4_NODES[b]) / 2 for a, b in _TET10_EDGES])
# dL_i/dxi for the tetrahedron's volume coordinates
_DL = np.array([[-1, -1, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)


def _hex8(xi):
    xi = np.atleast_2d(xi)
    a = 1 + xi[:, None, :] * _HEX8_NODES[None]          # (m, 8, 3)
    return np.prod(a, axis=2) / 8.0


def _hex8_d(xi):
    xi = np.atleast_2d(xi)
    a = 1 + xi[:, None, :] * _HEX8_NODES[None]
    d = np.empty_like(a)
    d[..., 0] = _HEX8_NODES[None, :, 0] * a[..., 1] * a[..., 2]
    d[..., 1] = _HEX8_NODES[None, :, 1] * a[..., 0] * a[..., 2]
    d[..., 2] = _HEX8_NODES[None, :, 2] * a[..., 0] * a[..., 1]
    return d / 8.0


_HEX20_EDGE_AXIS = _HEX20_NODES[8:] == 0                  # (12, 3): the axis along each edge


def _hex20_factors(xi):
    """Corner terms a = 1 + xi xi_i (m, 8, 3); edge factors f and their derivatives df (m, 12, 3)."""
    c = _HEX20_NODES
    a = 1 + xi[:, None, :] * c[None, :8]
    f = np.where(_HEX20_EDGE_AXIS[None], 1 - xi[:, None, :] ** 2, 1 + xi[:, None, :] * c[None, 8:])
    df = np.where(_HEX20_EDGE_AXIS[None], -2 * xi[:, None, :], np.broadcast_to(c[None, 8:], f.shape))
    return a, f, df


def _hex20(xi):
    xi = np.atleast_2d(xi)
    a, f, _ = _hex20_factors(xi)
    s = xi @ _HEX20_NODES[:8].T - 2.0                   # (m, 8)
    return np.concatenate([np.prod(a, axis=2) * s / 8.0, np.prod(f, axis=2) / 4.0], axis=1)


def _hex20_d(xi):
    xi = np.atleast_2d(xi)
    c = _HEX20_NODES
    a, f, df = _hex20_factors(xi)
    s = xi @ c[:8].T - 2.0
    d = np.empty((len(xi), 20, 3))
    for ax in range(3):
        o1, o2 = [b for b in range(3) if b != ax]
        d[:, :8, ax] = c[None, :8, ax] * a[..., o1] * a[..., o2] * (s + a[..., ax]) / 8.0
        d[:, 8:, ax] = df[..., ax] * f[..., o1] * f[..., o2] / 4.0
    return d


def _volume_coords(xi):
    xi = np.atleast_2d(xi)
    return np.column_stack([1.0 - xi.sum(axis=1), xi])


def _tet4(xi):
    return _volume_coords(xi)


def _tet4_d(xi):
    xi = np.atleast_2d(xi)
    return np.broadcast_to(_DL, (len(xi), 4, 3)).copy()


def _tet10(xi):
    L = _volume_coords(xi)
    mids = [4 * L[:, a] * L[:, b] for a, b in _TET10_EDGES]
    return np.column_stack([L * (2 * L - 1)] + mids)


def _tet10_d(xi):
    L = _volume_coords(xi)
    m = len(L)
    d = np.empty((m, 10, 3))
    d[:, :4, :] = (4 * L - 1)[:, :, None] * _DL[None]
    for j, (a, b) in enumerate(_TET10_EDGES, start=4):
        d[:, j, :] = 4 * (L[:, a, None] * _DL[b] + L[:, b, None] * _DL[a])
    return d


# Wedges (triangular prisms): triangle coordinates (g, h) with L1 = 1 - g - h, L2 = g, L3 = h,
# and r in [-1, 1] along the prism; nodes 1-3 at r = -1, 4-6 above them at r = +1.
_WEDGE6_NODES = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1], [0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=float)
_WEDGE_TRI_EDGES = [(0, 1), (1, 2), (2, 0)]
_WEDGE15_NODES = np.vstack([_WEDGE6_NODES]
                           + [(_WEDGE6_NODES[a] + _WEDGE6_NODES[b]) / 2 for a, b in _WEDGE_TRI_EDGES]
                           + [(_WEDGE6_NODES[a + 3] + _WEDGE6_NODES[b + 3]) / 2 for a, b in _WEDGE_TRI_EDGES]
                           + [(_WEDGE6_NODES[a] + _WEDGE6_NODES[a + 3]) / 2 for a in range(3)])
_DL_TRI = np.array([[-1, -1], [1, 0], [0, 1]], dtype=float)      # dL_i/d(g, h)
#: C3D15's mid-edge nodes 7-15 (0-based corners): the lower triangle's edges, the upper's, the sides.
_WEDGE15_EDGES = [(0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)]


def _wedge_parts(xi):
    xi = np.atleast_2d(xi)
    L = np.column_stack([1.0 - xi[:, 0] - xi[:, 1], xi[:, 0], xi[:, 1]])
    return L, xi[:, 2]


def _wedge6(xi):
    L, r = _wedge_parts(xi)
    return np.column_stack([L * (0.5 * (1 - r))[:, None], L * (0.5 * (1 + r))[:, None]])


def _wedge6_d(xi):
    L, r = _wedge_parts(xi)
    d = np.empty((len(L), 6, 3))
    for k, sgn in ((0, -1.0), (3, 1.0)):
        d[:, k:k + 3, :2] = _DL_TRI[None] * (0.5 * (1 + sgn * r))[:, None, None]
        d[:, k:k + 3, 2] = 0.5 * sgn * L
    return d


def _wedge15(xi):
    L, r = _wedge_parts(xi)
    lo, hi, b = (1 - r)[:, None], (1 + r)[:, None], (1 - r * r)[:, None]
    corner = 0.5 * L * (2 * L - 1)
    tri = np.column_stack([2 * L[:, a] * L[:, c] for a, c in _WEDGE_TRI_EDGES])
    return np.column_stack([corner * lo - 0.5 * L * b, corner * hi - 0.5 * L * b, tri * lo, tri * hi, L * b])


def _wedge15_d(xi):
    L, r = _wedge_parts(xi)
    m = len(L)
    lo, hi, b = 1 - r, 1 + r, 1 - r * r
    d = np.empty((m, 15, 3))
    dcorner = 0.5 * (4 * L - 1)                                    # d[L (2L - 1) / 2]/dL
    corner = 0.5 * L * (2 * L - 1)
    for i in range(3):
        for k, f, df in ((i, lo, -1.0), (i + 3, hi, 1.0)):
            d[:, k, :2] = (dcorner[:, i] * f - 0.5 * b)[:, None] * _DL_TRI[i]
            d[:, k, 2] = df * corner[:, i] + L[:, i] * r
        d[:, 12 + i, :2] = b[:, None] * _DL_TRI[i]
        d[:, 12 + i, 2] = -2 * r * L[:, i]
    for j, (a, c) in enumerate(_WEDGE_TRI_EDGES):
        g = 2 * (L[:, a, None] * _DL_TRI[c] + L[:, c, None] * _DL_TRI[a])
        t = 2 * L[:, a] * L[:, c]
        d[:, 6 + j, :2], d[:, 6 + j, 2] = g * lo[:, None], -t
        d[:, 9 + j, :2], d[:, 9 + j, 2] = g * hi[:, None], t
    return d


def _wedge_contains(xi, tol):
    return _tet_contains(xi[:, :2], tol) & (np.abs(xi[:, 2]) <= 1.0 + tol)


def _wedge_clamp(xi):
    out = np.empty_like(xi)
    out[:, :2] = _simplex_clamp(xi[:, :2])
    out[:, 2] = np.clip(xi[:, 2], -1.0, 1.0)
    return out


def _hex_contains(xi, tol):
    return np.all(np.abs(xi) <= 1.0 + tol, axis=1)


def _tet_contains(xi, tol):
    return np.all(xi >= -tol, axis=1) & (xi.sum(axis=1) <= 1.0 + tol)


def _hex_clamp(xi):
    return np.clip(xi, -1.0, 1.0)


def _simplex_clamp(xi):
    """Nearest point of the reference simplex {xi >= 0, sum <= 1} (the tetrahedron's, or the
    wedge's triangle in its first two coordinates), by Euclidean projection in natural
    coordinates."""
    out = np.clip(xi, 0.0, None)
    over = out.sum(axis=1) > 1.0
    if np.any(over):
        # projection onto the face sum = 1 with xi >= 0 (Held, Wolfe & Crowder's sort method)
        v = xi[over]
        u = -np.sort(-v, axis=1)
        css = np.cumsum(u, axis=1) - 1.0
        k = np.arange(1, v.shape[1] + 1)
        rho = np.sum(u - css / k > 0, axis=1)
        theta = css[np.arange(len(v)), rho - 1] / rho
        out[over] = np.clip(v - theta[:, None], 0.0, None)
    return out


@dataclass(frozen=True)
class ElementType:
    """One isoparametric element: shape functions (m, n) and their natural derivatives (m, n, 3)."""

    name: str
    n_nodes: int
    family: str                       # "hex" or "tet"
    natural_nodes: np.ndarray         # (n, 3)
    centre: np.ndarray                # (3,) natural coordinates of the centroid
    shape: Callable[[np.ndarray], np.ndarray]
    dshape: Callable[[np.ndarray], np.ndarray]
    order: int

    def contains(self, xi, tol: float = 1e-8) -> np.ndarray:
        """Whether natural coordinates ``xi`` (m, 3) lie in the reference element (within ``tol``)."""
        xi = np.atleast_2d(xi)
        return {"hex": _hex_contains, "tet": _tet_contains, "wedge": _wedge_contains}[self.family](xi, tol)

    def clamp(self, xi) -> np.ndarray:
        """The nearest natural coordinates inside the reference element."""
        xi = np.atleast_2d(np.asarray(xi, dtype=float))
        return {"hex": _hex_clamp, "tet": _simplex_clamp, "wedge": _wedge_clamp}[self.family](xi)


ELEMENTS: dict[str, ElementType] = {
    "C3D4": ElementType("C3D4", 4, "tet", _TET4_NODES, np.full(3, 0.25), _tet4, _tet4_d, 1),
    "C3D10": ElementType("C3D10", 10, "tet", _TET10_NODES, np.full(3, 0.25), _tet10, _tet10_d, 2),
    "C3D8": ElementType("C3D8", 8, "hex", _HEX8_NODES, np.zeros(3), _hex8, _hex8_d, 1),
    "C3D20": ElementType("C3D20", 20, "hex", _HEX20_NODES, np.zeros(3), _hex20, _hex20_d, 2),
    "C3D6": ElementType("C3D6", 6, "wedge", _WEDGE6_NODES, np.array([1 / 3, 1 / 3, 0.0]), _wedge6, _wedge6_d, 1),
    "C3D15": ElementType("C3D15", 15, "wedge", _WEDGE15_NODES, np.array([1 / 3, 1 / 3, 0.0]), _wedge15, _wedge15_d,
                         2),
}

#: meshio cell type -> element name (same node order).
MESHIO_TO_ABAQUS = {"tetra": "C3D4", "tetra10": "C3D10", "hexahedron": "C3D8", "hexahedron20": "C3D20",
                    "wedge": "C3D6", "wedge15": "C3D15"}


_ABAQUS_SUFFIXES = set("RHIMTPS")


def element_type(name: str) -> ElementType:
    """The element for an ABAQUS type (``C3D8``, ``C3D8R``, ``C3D10M``, ...) or a meshio cell type.

    >>> element_type("C3D8R").name, element_type("tetra10").name
    ('C3D8', 'C3D10')
    """
    key = MESHIO_TO_ABAQUS.get(name, name).upper()
    for base in ("C3D20", "C3D15", "C3D10", "C3D8", "C3D6", "C3D4"):
        # C3D8R, C3D8H, C3D8I, C3D10M, C3D20R, C3D8RT, ...: same nodes, same interpolation
        # (ABAQUS's suffixes: Reduced integration, Hybrid, Incompatible modes, Modified,
        # Temperature, Pore pressure, S for C3D10HS); another letter is no ABAQUS element
        if key == base or (key.startswith(base) and set(key[len(base):]) <= _ABAQUS_SUFFIXES and key[len(base):]):
            return ELEMENTS[base]
    raise KeyError(f"element type {name!r} is not supported (C3D4, C3D10, C3D6, C3D15, C3D8, C3D20 and variants)")


def shape_functions(name: str, xi) -> np.ndarray:
    """``N_i(xi)``, shape (m, n) for natural coordinates ``xi`` (m, 3) or (3,).

    >>> shape_functions("C3D8", [0.0, 0.0, 0.0]).round(3).tolist()
    [[0.125, 0.125, 0.125, 0.125, 0.125, 0.125, 0.125, 0.125]]
    """
    return element_type(name).shape(np.asarray(xi, dtype=float))


def shape_derivatives(name: str, xi) -> np.ndarray:
    """``dN_i/dxi_j``, shape (m, n, 3)."""
    return element_type(name).dshape(np.asarray(xi, dtype=float))


def inverse_map(name: str, nodes_xyz, x, *, tol: float = 1e-12, max_iter: int = 50
                ) -> tuple[np.ndarray, np.ndarray]:
    """Natural coordinates of points ``x`` (m, 3) in elements with node coordinates ``nodes_xyz``.

    ``nodes_xyz`` is (m, n, 3) (one element per point) or (n, 3) (one element for all).
    Newton's method from the element centre:
    :math:`\\boldsymbol\\xi \\leftarrow \\boldsymbol\\xi - J^{-1}(\\mathbf x(\\boldsymbol\\xi) - \\mathbf x)`,
    :math:`J_{ij} = \\partial x_i / \\partial \\xi_j`, until the step is below ``tol``.  Steps
    are limited so a point far outside cannot send the iterate to infinity.

    Returns ``(xi, converged)``: (m, 3) and (m,) bool (False where J is singular or Newton
    did not converge; a point far outside a curved element may not converge, and is not in it).
    """
    et = element_type(name)
    x = np.atleast_2d(np.asarray(x, dtype=float))
    X = np.asarray(nodes_xyz, dtype=float)
    if X.ndim == 2:
        X = np.broadcast_to(X, (len(x),) + X.shape)
    m = len(x)
    xi = np.tile(et.centre, (m, 1))
    active = np.ones(m, dtype=bool)
    converged = np.zeros(m, dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        xa = xi[idx]
        r = np.einsum("mn,mni->mi", et.shape(xa), X[idx]) - x[idx]
        J = np.einsum("mnj,mni->mij", et.dshape(xa), X[idx])
        det = np.linalg.det(J)
        scale = np.abs(J).max(axis=(1, 2)) ** 3
        ok = np.abs(det) > 1e-14 * np.maximum(scale, np.finfo(float).tiny)
        step = np.zeros_like(xa)
        if ok.any():
            step[ok] = -np.linalg.solve(J[ok], r[ok][..., None])[..., 0]
        big = np.abs(step).max(axis=1)
        step *= np.minimum(1.0, 2.0 / np.maximum(big, 1e-300))[:, None]
        xi[idx] = np.clip(xa + step, -10.0, 10.0)
        done = ok & (np.abs(step).max(axis=1) <= tol)
        converged[idx[done]] = True
        active[idx[done | ~ok]] = False
        if et.order == 1 and et.family == "tet":
            converged[idx[ok]] = True
            active[idx] = False
    return xi, converged


def interpolate(name: str, nodal_values, xi) -> np.ndarray:
    """``sum_i N_i(xi) v_i``: ``nodal_values`` (m, n, k) or (n, k), ``xi`` (m, 3) -> (m, k)."""
    N = shape_functions(name, xi)
    v = np.asarray(nodal_values, dtype=float)
    if v.ndim == 2:
        return N @ v
    return np.einsum("mn,mnk->mk", N, v)


def nearest_point(et: ElementType, nodes_xyz, x, xi0=None) -> tuple[np.ndarray, float]:
    """The point of one element nearest to ``x`` (3,): its natural coordinates and distance.

    Minimises :math:`|\\mathbf x(\\boldsymbol\\xi) - \\mathbf x|^2` over the reference element
    (bounds for the cube, L-BFGS-B; the simplex's or the triangle's constraint for the tetrahedron
    and the wedge, SLSQP) from
    ``xi0`` (default the centre), with the exact gradient :math:`2 J^T r`; the start is kept if
    the search ends farther.  Exact for the affine C3D4 (a quadratic problem), to the solver's
    tolerance for curved elements (a local minimum of a strongly curved face is possible).
    """
    from scipy.optimize import minimize

    X = np.asarray(nodes_xyz, dtype=float)
    x = np.asarray(x, dtype=float)
    xi0 = et.centre if xi0 is None else et.clamp(xi0)[0]

    def dist(z):
        return float(np.linalg.norm(et.shape(z[None])[0] @ X - x))

    def f(z):
        r = et.shape(z[None])[0] @ X - x
        J = et.dshape(z[None])[0].T @ X                  # (3, 3): dx_i/dxi_j transposed
        return float(r @ r), 2.0 * (J @ r)

    if et.family == "hex":
        res = minimize(f, xi0, jac=True, method="L-BFGS-B", bounds=[(-1.0, 1.0)] * 3,
                       options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 200})
    else:
        # the tetrahedron's simplex, or the wedge's triangle (its third coordinate a bound)
        wedge = et.family == "wedge"
        lead = np.array([1.0, 1.0, 0.0 if wedge else 1.0])
        res = minimize(f, xi0, jac=True, method="SLSQP",
                       bounds=[(0.0, 1.0), (0.0, 1.0), (-1.0, 1.0) if wedge else (0.0, 1.0)],
                       constraints=[{"type": "ineq", "fun": lambda z: 1.0 - lead @ z, "jac": lambda z: -lead}],
                       options={"ftol": 1e-16, "maxiter": 200})
    best = et.clamp(res.x)[0]
    d_best, d0 = dist(best), dist(xi0)
    return (best, d_best) if d_best <= d0 else (xi0, d0)


# --- point location ---------------------------------------------------------------------------

@dataclass
class Location:
    """Where each of p points lies: ``block`` and ``element`` (index within the block; -1 when
    not found), natural coordinates ``xi`` (p, 3), ``inside`` (within the natural-coordinate
    tolerance), ``distance_mm`` (0 inside; else the distance to the nearest element surface
    point found), ``found`` (inside, or outside by at most the allowed distance)."""

    block: np.ndarray
    element: np.ndarray
    xi: np.ndarray
    inside: np.ndarray
    distance_mm: np.ndarray
    found: np.ndarray


class PointLocator:
    """Find the element that holds a point, in a mesh of C3D4/C3D10/C3D8/C3D20 blocks.

    Parameters
    ----------
    coords : array_like, shape (n_nodes, 3)
        Node coordinates (mm).
    blocks : sequence of ``(element_name, connectivity)``
        ``connectivity`` (n_elements, n_nodes_per_element): 0-based row indices into ``coords``.
    """

    def __init__(self, coords, blocks: Sequence[tuple[str, np.ndarray]]):
        self.coords = np.asarray(coords, dtype=float)
        self.blocks = [(element_type(n), np.asarray(c, dtype=np.int64)) for n, c in blocks]
        cents, radii, owner, boxes = [], [], [], []
        for b, (et, conn) in enumerate(self.blocks):
            if conn.size == 0:
                continue
            X = self.coords[conn]                          # (ne, n, 3)
            c = X[:, : (8 if et.family == "hex" else 4)].mean(axis=1)
            cents.append(c)
            radii.append(np.linalg.norm(X - c[:, None], axis=2).max(axis=1))
            lo, hi = X.min(axis=1), X.max(axis=1)
            # quadratic elements may bulge a little beyond their nodes' box
            pad = (0.1 if et.order > 1 else 1e-9) * (hi - lo).max(axis=1, keepdims=True)
            boxes.append(np.hstack([lo - pad, hi + pad]))
            owner.append(np.column_stack([np.full(len(conn), b), np.arange(len(conn))]))
        if not cents:
            raise ValueError("the mesh has no solid elements")
        self.centroids = np.vstack(cents)
        self.radii = np.concatenate(radii)
        self.owner = np.vstack(owner)
        self.boxes = np.vstack(boxes)
        self.max_radius = float(self.radii.max())
        self.tree = cKDTree(self.centroids)

    def locate(self, points, *, tol: float = 1e-8, outside_tol_mm: float = 0.0) -> Location:
        """Locate ``points`` (p, 3); an element containing a point within ``tol`` (natural
        coordinates) wins, nearest centroid first.  A point in no element is ``found`` only
        when an element surface is within ``outside_tol_mm``; its ``xi`` then is the nearest
        point of that element (the field is extended constantly from the surface)."""
        P = np.atleast_2d(np.asarray(points, dtype=float))
        p = len(P)
        out = Location(np.full(p, -1), np.full(p, -1), np.full((p, 3), np.nan), np.zeros(p, bool),
                       np.full(p, np.inf), np.zeros(p, bool))
        for i, x in enumerate(P):
            if not np.all(np.isfinite(x)):
                continue
            cand = np.array(self.tree.query_ball_point(x, self.max_radius * (1 + 1e-9) + outside_tol_mm),
                            dtype=np.int64)
            if cand.size == 0:
                continue
            dist_c = np.linalg.norm(self.centroids[cand] - x, axis=1)
            box = self.boxes[cand]
            keep = ((dist_c <= self.radii[cand] * (1 + 1e-9) + outside_tol_mm)
                    & np.all(x >= box[:, :3] - outside_tol_mm, axis=1)
                    & np.all(x <= box[:, 3:] + outside_tol_mm, axis=1))
            cand, dist_c = cand[keep], dist_c[keep]
            cand = cand[np.argsort(dist_c, kind="stable")]
            rank = {int(c): r for r, c in enumerate(cand)}
            inside_best = None      # (rank, block, element, xi)
            near_best = None        # (distance, block, element, xi)
            for b in np.unique(self.owner[cand, 0]):
                et, conn = self.blocks[b]
                sel = cand[self.owner[cand, 0] == b]
                els = self.owner[sel, 1]
                X = self.coords[conn[els]]
                xi, conv = inverse_map(et.name, X, np.repeat(x[None], len(els), axis=0))
                ins = conv & et.contains(xi, tol)
                for k in np.flatnonzero(ins):
                    r = rank[int(sel[k])]
                    if inside_best is None or r < inside_best[0]:
                        inside_best = (r, b, els[k], xi[k])
                if inside_best is None and outside_tol_mm > 0:
                    # the nearest point of each element, in space (a projection in natural
                    # coordinates is a point of the surface, not the nearest: 0.37 mm for a
                    # point 0.30 mm off a tetrahedron's face); elements that cannot beat the
                    # best so far (their centroid farther than their radius plus it) are skipped
                    start = np.where(conv[:, None], et.clamp(np.where(np.isfinite(xi), xi, 0.0)), et.centre)
                    lower = np.linalg.norm(self.centroids[sel] - x, axis=1) - self.radii[sel]
                    for k in np.argsort(lower, kind="stable"):
                        if near_best is not None and lower[k] >= near_best[0]:
                            break
                        xc, d = nearest_point(et, X[k], x, start[k])
                        if near_best is None or d < near_best[0]:
                            near_best = (d, b, els[k], xc)
            if inside_best is not None:
                _, b, e, xi_ = inside_best
                out.block[i], out.element[i], out.xi[i] = b, e, xi_
                out.inside[i] = out.found[i] = True
                out.distance_mm[i] = 0.0
            elif near_best is not None:
                d, b, e, xi_ = near_best
                out.distance_mm[i] = d
                if d <= outside_tol_mm:
                    out.block[i], out.element[i], out.xi[i] = b, e, xi_
                    out.found[i] = True
        return out

    def interpolate(self, nodal_values, loc: Location) -> np.ndarray:
        """Values (p, k) at located points from ``nodal_values`` (n_nodes, k); NaN where not found."""
        v = np.asarray(nodal_values, dtype=float)
        v2 = v.reshape(len(v), -1)
        out = np.full((len(loc.block), v2.shape[1]), np.nan)
        for i in np.flatnonzero(loc.found):
            et, conn = self.blocks[loc.block[i]]
            out[i] = shape_functions(et.name, loc.xi[i]) @ v2[conn[loc.element[i]]]
        return out
