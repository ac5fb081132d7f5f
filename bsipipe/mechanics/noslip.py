r"""No-slip (bonded) platens: an axisymmetric FE model of a compressed one-term Ogden cylinder.

A cylinder of diameter :math:`D` and height :math:`H` compressed between sandpaper platens
does not slide on them: it barrels, and the platen force exceeds the homogeneous
(frictionless) one,

.. math::

    P_{\text{hom}}(\lambda) = \frac{2\mu}{\alpha}
        \left(\lambda^{\alpha - 1} - \lambda^{-\alpha/2 - 1}\right),

by a factor that grows with the shape factor :math:`S = D / (4H)` (loaded area over free
area) and with the compression.  For small strains the factor tends to the bonded-cylinder
value :math:`1 + 2S^2` of the thin-layer (lubrication) solution, exact for :math:`S \gg 1`.

The FE model
------------
felupe, axisymmetric (:class:`felupe.FieldAxisymmetric`: axis :math:`x_1`, radius
:math:`x_2`), four-node quads with a mean-dilatation volume constraint
(:class:`felupe.SolidBodyNearlyIncompressible`, bulk modulus :math:`K = 5000\,\mu`), and the
isochoric Ogden energy of :func:`felupe.ogden`, :math:`W = \sum 2\mu_i/\alpha_i^2
(\bar\lambda_1^{\alpha_i} + \bar\lambda_2^{\alpha_i} + \bar\lambda_3^{\alpha_i} - 3)`, the
convention of :mod:`bsipipe.mechanics.hyperelastic` (the frictionless test checks it).  The
material is evaluated in closed form (:class:`OgdenIsochoric`, equal to felupe's
automatic-differentiation ``Hyperelastic(ogden)`` to 1e-6 and several times faster).
A quarter of the meridian section is modelled: mid-height plane symmetric, the axis
radially fixed, the top face bonded (radially fixed) and moved axially.

At large compression the free surface next to the bonded edge folds over onto the platen.
A frictionless penalty contact (:class:`felupe.MultiPointContact`, :math:`10^4\,\mu D`)
keeps it out, and Newton steps use a backtracking line search (without it the folded layer
can trap a pocket whose tangent turns singular).  Without the contact the folded layer
passes through the platen and the force keeps falling on refinement (about 1 % per halving
of the cells at 30 % compression); with it the force converges.  A step that does not
converge even at the smallest increment is an error, never patched over: every run of the
shipped tables converges (``scripts/build_noslip_tables.py`` builds them and fails loudly
otherwise).
Bonding the folded layer from the moment it touches (sandpaper gripping it) instead of
letting it slide raises the force by about 1 % at 30 % and 2-3 % at 40 % compression at
H/D 2/3 (``scripts/build_noslip_tables.py --study``): the model's uncertainty where it folds.
The mesh is graded geometrically towards the bonded edge (the singular corner), the
smallest cell ``grading`` times smaller than the largest along each edge.  Halving every
cell of the default mesh (``scripts/build_noslip_tables.py --refine``) changes the force by
about 0.1 % at 1 % compression and, for :math:`|\alpha| \le 6` (measured: -4.7 at the three
shipped aspects, 1 at H/D 2/3, 6 at 1/2), by under 1 % over the whole stretch range
(largest 0.87 % at H/D 1/2, alpha -4.7, 20 % compression, where the surface has just
folded over).  Not so at the ends of the alpha
grid: alpha -12 changes by 0.6-1.4 % at 20 % and 1.4-2.6 % at 30 % compression (H/D 1 to
1/2), alpha 12 by 1.3-1.4 % at 30-40 % at H/D 1/2 (0.9 % at 2/3); there the tables are
that much stiff.  The change is systematic (finer meshes are softer) and larger than a
1 mN load noise on a 0.5 N force: data made by a different discretisation leave a
residual a fit can mistake for a mechanism.

The problem is solved once in units :math:`\mu = 1`, :math:`D = 1`; a hyperelastic force
scales with :math:`\mu D^2`, so only :math:`\alpha` and :math:`H/D` need new runs.

Tables
------
For each aspect :math:`H/D` the ratio :math:`g(\lambda, \alpha) = P_{\text{FE}} /
P_{\text{hom}}` (smooth, and finite at :math:`\lambda = 1`) and the mid-height bulge width
over :math:`D` are tabulated on a grid of stretch (1 to 0.6) and of exponent
(:data:`ALPHA_GRID`, both signs, :math:`1 \le |\alpha| \le 12`), and interpolated with
not-a-knot cubic splines in :math:`\alpha` (each sign separately) and PCHIP in
:math:`\lambda`.  Tables ship with the package for common aspects
(``_data/noslip_*.npz``); any other aspect is computed on first use (minutes, with a
progress bar) and cached in ``$BSIPIPE_CACHE/noslip`` (default ``~/.cache/bsipipe/noslip``),
keyed by aspect, grid, mesh and :data:`TABLE_VERSION`.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from .hyperelastic import ogden_nominal_stress

# Bump when the FE model or the table layout changes: cached and shipped tables of another
# version are ignored (shipped ones must then be rebuilt by scripts/build_noslip_tables.py).
# 2: frictionless fold-over contact with line search; no bonding rescue.
TABLE_VERSION = 2

#: Exponents tabulated (each sign interpolated separately; ``|alpha| < 1`` is not covered).
ALPHA_GRID = np.concatenate([np.arange(-12.0, -0.5, 1.0), np.arange(1.0, 12.5, 1.0)])
#: Stretches tabulated; 1.0 holds the small-strain limit of the force ratio.
STRETCH_GRID = np.concatenate([
    [1.0, 0.999, 0.998, 0.995],
    np.round(np.arange(0.99, 0.8999, -0.01), 4),
    np.round(np.arange(0.88, 0.5999, -0.02), 4),
])
#: Bulk modulus over shear modulus of the nearly incompressible FE model.
BULK_RATIO = 5000.0
#: What keeps the folded-over free surface out of the platen (see :func:`_solve_unit`).
FOLD_OVER = "slide"
#: Penalty stiffness of the frictionless fold-over contact, in units of mu * D.
CONTACT_PENALTY = 1e4
#: Stretches above 1 accepted (a linear continuation of the force ratio; finite-difference
#: derivatives of a fit evaluate just past the contact point).
MAX_STRETCH = 1.01
#: Aspects whose tables ship with the package (1/2, the seeds' 18 mm wide x 12 mm high
#: specimen, 1).
SHIPPED_ASPECTS = (0.5, 12.0 / 18.0, 1.0)


@dataclass(frozen=True)
class FEMesh:
    """Structured quad mesh of the quarter meridian section (height/2 x radius).

    ``n_radial`` cells along the radius, ``round(n_radial * aspect)`` (at least 4) along
    the half height, so that cells are square on average; each edge is graded
    geometrically towards the bonded top-outer edge, its largest cell ``grading`` times its
    smallest.
    """

    n_radial: int = 32
    grading: float = 8.0

    def n_axial(self, aspect: float) -> int:
        return max(4, int(round(self.n_radial * aspect)))


DEFAULT_MESH = FEMesh()


@dataclass
class NoSlipRun:
    """Result of :func:`noslip_simulate`; arrays have one entry per requested stretch.

    ``force_n`` is the platen force (N, negative in compression), ``nominal_stress_pa`` the
    force over the undeformed area, ``homogeneous_stress_pa`` the frictionless formula,
    ``bulge_width_mm`` the lateral width at mid-height, ``iterations`` the Newton iterations
    spent reaching each stretch (including sub-steps).
    """

    stretch: np.ndarray
    force_n: np.ndarray
    nominal_stress_pa: np.ndarray
    homogeneous_stress_pa: np.ndarray
    bulge_width_mm: np.ndarray
    iterations: np.ndarray
    seconds: float
    boundary: str
    mesh: FEMesh = field(default_factory=FEMesh)

    @property
    def force_ratio(self) -> np.ndarray:
        """FE force over the homogeneous-compression force."""
        return self.nominal_stress_pa / self.homogeneous_stress_pa


# --- the FE model ------------------------------------------------------------------------

class OgdenIsochoric:
    r"""Closed-form isochoric one-term Ogden material for felupe (a ``umat``).

    The energy of :func:`felupe.ogden` (tensortrax, automatic differentiation) written in
    the eigenvalues :math:`c_a` of :math:`\boldsymbol{C}`, with :math:`p = \alpha/2`,
    :math:`q = -\alpha/6`, :math:`f = \sum_a c_a^p`, :math:`I_3 = c_1 c_2 c_3`:

    .. math::

        W = \frac{2\mu}{\alpha^2}\left(f I_3^{q} - 3\right), \quad
        \boldsymbol{S} = 2 \sum_a W_a \boldsymbol{N}_a \otimes \boldsymbol{N}_a, \quad
        \boldsymbol{P} = \boldsymbol{F}\boldsymbol{S}

    and the tangent
    :math:`\mathbb{A} = \boldsymbol{I} \overset{ik}{\otimes} \boldsymbol{S}
    + 4 \sum_{ab} W_{ab}\, \boldsymbol{G}_{aa} \otimes \boldsymbol{G}_{bb}
    + 2 \sum_{a<b} \theta_{ab}\, \boldsymbol{H}_{ab} \otimes \boldsymbol{H}_{ab}`, with
    :math:`\boldsymbol{G}_{ab} = \boldsymbol{F}\boldsymbol{N}_a \otimes \boldsymbol{N}_b`,
    :math:`\boldsymbol{H}_{ab} = \boldsymbol{G}_{ab} + \boldsymbol{G}_{ba}` and
    :math:`\theta_{ab} = (W_a - W_b)/(c_a - c_b)`, replaced by its limit
    :math:`W_{aa} - W_{ab}` for (nearly) equal eigenvalues (the undeformed state, the axis).
    It agrees with the automatic-differentiation material to 1e-6 (that one perturbs
    repeated eigenvalues; this tangent matches central differences of this stress to 1e-7,
    ``tests/test_noslip.py``) and is about eight times faster.  The stress needs no
    eigenvalue differences, so the converged solution does not depend on the limit switch.
    """

    def __init__(self, mu: float, alpha: float):
        if alpha == 0:
            raise ValueError("alpha must not be 0")
        self.mu, self.alpha = float(mu), float(alpha)
        self.x = [np.eye(3), np.zeros(0)]   # felupe reads the state-variable shape from x[-1]

    def _spectral(self, F):
        shape = F.shape[2:]
        Fn = F.reshape(3, 3, -1)
        C = np.einsum("kin,kjn->nij", Fn, Fn)
        c, N = np.linalg.eigh(C)             # c: (n, 3) ascending, N[n, :, a] eigenvectors
        c = np.ascontiguousarray(c.T)        # (a, n)
        N = np.ascontiguousarray(N.transpose(2, 1, 0))   # (a, I, n)
        k = 2.0 * self.mu / self.alpha**2
        p, q = self.alpha / 2.0, -self.alpha / 6.0
        cp = c**p
        f = cp.sum(axis=0)
        i3q = (c[0] * c[1] * c[2]) ** q
        Wa = k * i3q * (p * cp + q * f) / c                           # (a, n)
        S = 2.0 * np.einsum("an,ain,ajn->ijn", Wa, N, N, optimize=False)
        return shape, Fn, c, N, k, p, q, cp, f, i3q, Wa, S

    def gradient(self, x):
        F, statevars = x[0], x[-1]
        shape, Fn, *_, S = self._spectral(F)
        P = np.einsum("ikn,kjn->ijn", Fn, S)
        return [P.reshape(3, 3, *shape), statevars]

    def hessian(self, x):
        F = x[0]
        shape, Fn, c, N, k, p, q, cp, f, i3q, Wa, S = self._spectral(F)
        # W_ab = k I3^q [ q/c_b (p c_a^(p-1) + q f/c_a) + q p c_b^(p-1)/c_a
        #                 + delta_ab (p (p-1) c_a^(p-2) - q f / c_a^2) ]
        ca, cb = c[:, None, :], c[None, :, :]
        Wab = k * i3q * (q * (p * cp[:, None, :] + q * f) + q * p * cp[None, :, :]) / (ca * cb)
        Wab[[0, 1, 2], [0, 1, 2]] += k * i3q * (p * (p - 1.0) * cp - q * f) / c**2
        m = np.einsum("iIn,aIn->ain", Fn, N)                            # F N_a
        G = m[:, None, :, None, :] * N[None, :, None, :, :]              # G_ab = F N_a x N_b
        Gd = G[[0, 1, 2], [0, 1, 2]]                                     # (a, i, J, n)
        U = np.einsum("abn,bkln->akln", Wab, Gd)
        A = np.zeros((3, 3, 3, 3, Fn.shape[-1]))
        for i in range(3):
            A[i, :, i] = S                   # A_iJiL = S_JL
        for a in range(3):
            A += 4.0 * Gd[a][:, :, None, None] * U[a][None, None]
        for a, b in ((0, 1), (0, 2), (1, 2)):
            dc = c[a] - c[b]
            close = np.abs(dc) <= 1e-6 * np.maximum(np.abs(c[a]), np.abs(c[b]))
            limit = 0.5 * (Wab[a, a] - Wab[a, b] + Wab[b, b] - Wab[b, a])
            theta = np.where(close, limit, (Wa[a] - Wa[b]) / np.where(close, 1.0, dc))
            H = G[a, b] + G[b, a]
            A += (2.0 * theta * H)[:, :, None, None] * H[None, None]
        return [A.reshape(3, 3, 3, 3, *shape)]


def _graded_edge(n: int, length: float, grading: float) -> np.ndarray:
    """``n + 1`` coordinates on ``[0, length]``, cells shrinking geometrically towards the end."""
    if n == 1 or grading == 1.0:
        return np.linspace(0.0, length, n + 1)
    q = grading ** (-1.0 / (n - 1))
    h = q ** np.arange(n)
    x = np.concatenate([[0.0], np.cumsum(h)]) / h.sum() * length
    x[-1] = length
    return x


def _finite_spsolve(A, b):
    """``spsolve`` that refuses a non-finite system (an inverted cell), so the step is cut."""
    from scipy.sparse.linalg import spsolve

    if not (np.all(np.isfinite(A.data)) and np.all(np.isfinite(np.asarray(b)))):
        raise FloatingPointError("non-finite tangent or residual")
    return spsolve(A, b)


def _platen_dofs(bounds) -> np.ndarray:
    """Axial degrees of freedom the platen drives: the top face and the side points bonded
    after folding over (their reactions sum to the platen force)."""
    dofs = [bounds["move"].dof]
    if "folded" in bounds:
        b = bounds["folded"]
        dofs.append(b.field.indices.dof[b.points, 0])
    return np.concatenate(dofs)


def _solve_unit(stretches, alpha: float, aspect: float, mesh: FEMesh = DEFAULT_MESH,
                boundary: str = "no-slip", bulk_ratio: float = BULK_RATIO,
                max_step: float = 0.02, min_step: float = 1e-4, tol: float = 1e-8,
                material: str = "closed-form", fold_over: str = FOLD_OVER,
                bond_gap: float = 0.5, fold_tolerance: float = 0.1, linesearch: bool = True):
    """FE compression of a cylinder with ``mu = 1``, ``D = 1``, ``H = aspect``.

    Returns ``(nominal, width, iterations)``, each of shape (n,) in the order of
    ``stretches`` (which must decrease from at most 1): the platen force over the undeformed
    area (negative), the mid-height width over ``D``, and Newton iterations per stretch.
    Increments are at most ``max_step`` in stretch.  Newton steps use felupe's
    backtracking line search (``linesearch``; without it the folded layer can trap a pocket
    whose tangent turns singular); a failed solve is retried (state restored) with the line
    search, then with halved increments down to ``min_step``, below which it raises
    ``RuntimeError``.  Stretches closer than ``min_step / 2`` to the previous one share its
    solution (no increment is shorter than that).

    ``fold_over`` says what stops the free surface from passing through the platen where it
    folds over the bonded edge: ``"slide"`` (the model of the tables) a frictionless penalty
    contact, the folded layer slides out on the platen; ``"bond"`` (the study's bound on
    this modelling choice: sandpaper gripping the folded layer) bonds the side points within
    ``bond_gap`` smallest cells of the platen, and all points between them and the bonded
    edge, where they are as soon as they come that close (increments cut while a point would
    pass through by more than ``fold_tolerance`` smallest cells); ``"none"`` lets the
    surface pass through (the published reference's model; for the mesh study only).
    ``material`` is ``"closed-form"`` (:class:`OgdenIsochoric`) or ``"tensortrax"``
    (:func:`felupe.ogden` by automatic differentiation, the reference it is checked against).
    """
    import felupe as fem  # heavy import: only where FE runs

    stretches = np.asarray(stretches, dtype=float)
    if np.any(np.diff(stretches) >= 0) or stretches[0] > 1.0 or stretches[-1] <= 0.0:
        raise ValueError("stretches must decrease strictly within (0, 1]")
    if boundary not in ("no-slip", "frictionless"):
        raise ValueError(f"unknown boundary {boundary!r}; expected 'no-slip' or 'frictionless'")
    if fold_over not in ("slide", "bond", "none"):
        raise ValueError(f"unknown fold_over {fold_over!r}; expected 'slide', 'bond' or 'none'")
    if boundary == "frictionless":
        fold_over = "none"

    radius, half_h = 0.5, aspect / 2.0
    xa = _graded_edge(mesh.n_axial(aspect), half_h, mesh.grading)
    xr = _graded_edge(mesh.n_radial, radius, mesh.grading)
    grid = fem.Grid(xa, xr)   # x1 axial (the axisymmetric axis), x2 radial
    points = grid.points
    side = np.flatnonzero(np.isclose(points[:, 1], radius) & ~np.isclose(points[:, 0], half_h))
    side = side[np.argsort(points[side, 0])]      # free surface, mid-height up to the platen
    mid = int(np.flatnonzero(np.isclose(points[:, 0], 0.0) & np.isclose(points[:, 1], radius))[0])
    h_min = min(np.diff(xa).min(), np.diff(xr).min())
    fold_tol, bond_gap = fold_tolerance * h_min, bond_gap * h_min
    if fold_over == "slide":
        # The contact's rigid plane is a point without cells on the bonded edge; it lies on
        # the top face, so the 'move' and 'clamp' boundaries drive it with the platen.
        grid.update(points=np.vstack([points, [half_h, radius]]))
        points = grid.points

    region = fem.RegionQuad(grid)
    u = fem.FieldAxisymmetric(region, dim=2)
    field_ = fem.FieldContainer([u])
    if material == "closed-form":
        umat = OgdenIsochoric(1.0, float(alpha))
    elif material == "tensortrax":  # felupe's own Ogden, by automatic differentiation
        umat = fem.Hyperelastic(fem.ogden, mu=[1.0], alpha=[float(alpha)])
    else:
        raise ValueError(f"unknown material {material!r}")
    solid = fem.SolidBodyNearlyIncompressible(umat, field_, bulk=bulk_ratio)
    items = [solid]
    if fold_over == "slide":
        contact = fem.MultiPointContact(field_, side, grid.npoints - 1, skip=(False, True),
                                        multiplier=CONTACT_PENALTY)
        items.append(contact)
    bounds = {
        "symmetry": fem.Boundary(u, fx=0.0, skip=(0, 1)),
        "axis": fem.Boundary(u, fy=0.0, skip=(1, 0)),
        "move": fem.Boundary(u, fx=half_h, skip=(0, 1)),
    }
    if boundary == "no-slip":
        bounds["clamp"] = fem.Boundary(u, fx=half_h, skip=(1, 0))
    folded = np.zeros(grid.npoints, dtype=bool)     # side points bonded to the platen
    folded_at = np.zeros((grid.npoints, 2))         # (height over the platen, radial displacement)

    def gaps(values, s_platen):
        """Height of each side point over the platen plane (-inf for bonded ones)."""
        return np.where(folded[side], -np.inf, points[side, 0] + values[side, 0] - s_platen * half_h)

    def bond(over):
        """Bond the side points within ``bond_gap`` of the platen and all between them and
        the edge (points trapped between bonded ones have no stiffness left) where they
        are; from then on they move with the platen.  Returns whether any were new."""
        if not np.any(over >= -bond_gap):
            return False
        new = side[np.argmax(over >= -bond_gap):]
        new = new[~folded[new]]
        folded[new] = True
        folded_at[new, 0] = points[new, 0] + u.values[new, 0] - s_done * half_h
        folded_at[new, 1] = u.values[new, 1]
        return new.size > 0

    def set_folded(s_platen):
        pts = np.flatnonzero(folded)
        value = np.column_stack([s_platen * half_h + folded_at[pts, 0] - points[pts, 0],
                                 folded_at[pts, 1]]).ravel()
        bounds["folded"] = fem.Boundary(u, mask=folded, value=value)

    dof0, dof1 = fem.dof.partition(field_, bounds)

    n = len(stretches)
    nominal, width, iters = np.empty(n), np.empty(n), np.zeros(n, dtype=int)
    s_done, u_prev, s_prev, force = 1.0, None, None, 0.0
    step, search = max_step, linesearch
    # A target closer than this to the reached stretch counts as reached, and a step never
    # leaves less than it to go: a step of rounding size (0.75 reached as 0.7499999999999999
    # on the way to 0.7499999999999998) would feed the linear predictor a 1e-16 increment,
    # whose extrapolation then wrecks every later start, whatever the step size.
    reach = 0.5 * min_step
    for k, target in enumerate(stretches):
        while s_done - target > reach:
            s_try = s_done - step if s_done - step - target > reach else target
            checkpoint = solid.checkpoint()
            u_done = u.values.copy()
            if u_prev is not None:  # linear predictor from the last two converged states
                u.values[:] = u_done + (u_done - u_prev) * (s_done - s_try) / (s_prev - s_done)
            bounds["move"].value = -(1.0 - s_try) * half_h
            if folded.any():
                set_folded(s_try)
            ext0 = fem.dof.apply(field_, bounds, dof0)
            try:
                with np.errstate(all="ignore"):
                    res = fem.newtonraphson(items=items, x0=field_, dof1=dof1, dof0=dof0,
                                            ext0=ext0, verbose=0, tol=tol, maxiter=12,
                                            solver=_finite_spsolve,
                                            plugins=[fem.LinesearchPlugin()] if search else None)
                ok = bool(res.success) and np.all(np.isfinite(res.x[0].values))
            except (ValueError, FloatingPointError, np.linalg.LinAlgError, RuntimeError):
                ok = False
            if ok and fold_over == "bond" and step > min_step:
                ok = gaps(res.x[0].values, s_try).max() <= fold_tol
            if not ok:
                solid.restore(checkpoint)
                u.values[:] = u_done
                # Retry with a backtracking line search first (it gets the folded layer
                # past the configurations where plain Newton steps overshoot), then
                # with halved increments.
                if not search:
                    search = True
                    continue
                step /= 2.0
                if step < min_step:
                    raise RuntimeError(
                        f"no-slip FE did not converge at stretch {s_try:.4f} (alpha={alpha}, "
                        f"aspect={aspect}, boundary={boundary})")
                continue
            field_.link(res.x)
            iters[k] += res.iterations
            search = linesearch
            u_prev, s_prev, s_done = u_done, s_done, s_try
            if res.iterations <= 4:
                step = min(max_step, step * 1.5)
            force = float(np.sum(np.asarray(res.fun).ravel()[_platen_dofs(bounds)]))
            if fold_over == "bond" and bond(gaps(u.values, s_done)):
                set_folded(s_done)
                dof0, dof1 = fem.dof.partition(field_, bounds)
        nominal[k] = force / (np.pi * radius**2)
        width[k] = 2.0 * (radius + u.values[mid, 1])
    return nominal, width, iters


def noslip_simulate(stretches, mu_pa: float, alpha: float, diameter_mm: float, height_mm: float,
                    mesh: FEMesh = DEFAULT_MESH, boundary: str = "no-slip",
                    bulk_ratio: float = BULK_RATIO) -> NoSlipRun:
    """Run the axisymmetric FE model of a compressed one-term Ogden cylinder.

    Parameters
    ----------
    stretches : array_like, shape (n,)
        Nominal stretches ``1 - delta / H``, distinct, in (0, 1] (solved in decreasing
        order along one loading path, returned in the given order).
    mu_pa, alpha : float
        Ogden modulus (Pa) and exponent, ``W = 2 mu / alpha^2 (l1^a + l2^a + l3^a - 3)``.
    diameter_mm, height_mm : float
        Undeformed specimen size.
    mesh : FEMesh
    boundary : {"no-slip", "frictionless"}
        Bonded platens, or a top face free to slide radially (homogeneous compression:
        the FE then reproduces :func:`~bsipipe.mechanics.hyperelastic.ogden_nominal_stress`).
    bulk_ratio : float
        Bulk modulus over ``mu``.

    Returns
    -------
    NoSlipRun
        Forces (N) from ``P * pi D^2 / 4`` with ``D`` in m; widths (mm).
    """
    if mu_pa <= 0 or diameter_mm <= 0 or height_mm <= 0:
        raise ValueError("mu_pa, diameter_mm and height_mm must be positive")
    t0 = time.perf_counter()
    stretches = np.atleast_1d(np.asarray(stretches, dtype=float))
    order = np.argsort(-stretches, kind="stable")
    if np.any(np.diff(stretches[order]) == 0):
        raise ValueError("stretches must be distinct")
    nominal, width, iters = np.empty_like(stretches), np.empty_like(stretches), np.empty(len(stretches), int)
    nominal[order], width[order], iters[order] = _solve_unit(
        stretches[order], alpha, height_mm / diameter_mm, mesh, boundary, bulk_ratio)
    area_m2 = np.pi * (diameter_mm * 1e-3) ** 2 / 4.0
    stress = mu_pa * nominal
    return NoSlipRun(
        stretch=stretches, force_n=stress * area_m2, nominal_stress_pa=stress,
        homogeneous_stress_pa=ogden_nominal_stress(stretches, [mu_pa], [alpha]),
        bulge_width_mm=diameter_mm * width, iterations=iters,
        seconds=time.perf_counter() - t0, boundary=boundary, mesh=mesh)


# --- tables ------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class NoSlipTable:
    """Tabulated FE results for one aspect.

    ``ratio[i, j]`` is the force over the homogeneous force at ``alphas[i]``,
    ``stretches[j]`` (``stretches[0] == 1`` holds the small-strain limit), ``width[i, j]``
    the mid-height bulge width over the diameter.
    """

    aspect: float
    alphas: np.ndarray
    stretches: np.ndarray
    ratio: np.ndarray
    width: np.ndarray
    meta: dict

    def __post_init__(self):
        from scipy.interpolate import CubicSpline

        splines = {}
        for sign in (-1.0, 1.0):
            sel = np.flatnonzero(np.sign(self.alphas) == sign)
            if sel.size < 2:
                continue
            sel = sel[np.argsort(self.alphas[sel])]
            both = np.concatenate([self.ratio[sel], self.width[sel]], axis=1)
            bc = "not-a-knot" if sel.size >= 4 else "natural"
            splines[sign] = (self.alphas[sel].min(), self.alphas[sel].max(),
                             CubicSpline(self.alphas[sel], both, axis=0, bc_type=bc))
        object.__setattr__(self, "_splines", splines)

    def alpha_range(self) -> list[tuple[float, float]]:
        """The intervals of alpha the table covers (one per sign)."""
        return [(float(lo), float(hi)) for lo, hi, _ in self._splines.values()]

    def _columns(self, alpha: float):
        """``(ratio, width)`` over the stretch grid at ``alpha`` (cubic spline in alpha)."""
        alpha = float(alpha)
        for lo, hi, spline in self._splines.values():
            if lo - 1e-9 <= alpha <= hi + 1e-9:
                v = spline(alpha)
                n = self.stretches.size
                return v[:n], v[n:]
        ranges = " or ".join(f"[{lo:g}, {hi:g}]" for lo, hi in self.alpha_range())
        raise ValueError(f"alpha={alpha} is outside the no-slip table ({ranges})")

    def _check_stretch(self, lam: np.ndarray):
        s_min = float(self.stretches.min())
        if np.any(~np.isfinite(lam)) or np.any(lam < s_min - 1e-12) or np.any(lam > MAX_STRETCH):
            raise ValueError(f"stretch outside the no-slip table [{s_min:g}, {MAX_STRETCH:g}]")

    def force_ratio(self, stretch, alpha: float) -> np.ndarray:
        """FE force over homogeneous force at ``stretch`` (shape (n,))."""
        lam = np.asarray(stretch, dtype=float)
        self._check_stretch(lam)
        ratio, _ = self._columns(alpha)
        return _along_stretch(self.stretches, ratio, lam)

    def bulge_width(self, stretch, alpha: float) -> np.ndarray:
        """Mid-height width over the undeformed diameter."""
        lam = np.asarray(stretch, dtype=float)
        self._check_stretch(lam)
        _, width = self._columns(alpha)
        return _along_stretch(self.stretches, width, lam)

    def to_bytes(self) -> bytes:
        buf = io.BytesIO()
        np.savez_compressed(buf, aspect=np.float64(self.aspect), alphas=self.alphas,
                            stretches=self.stretches, ratio=self.ratio, width=self.width,
                            meta=np.array(json.dumps(self.meta, sort_keys=True)))
        return buf.getvalue()

    @classmethod
    def from_file(cls, path) -> "NoSlipTable":
        with np.load(path, allow_pickle=False) as z:
            return cls(aspect=float(z["aspect"]), alphas=z["alphas"], stretches=z["stretches"],
                       ratio=z["ratio"], width=z["width"], meta=json.loads(str(z["meta"])))


def _along_stretch(s_grid: np.ndarray, values: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """PCHIP in stretch; above 1 the linear continuation with the slope at 1."""
    from scipy.interpolate import PchipInterpolator

    order = np.argsort(s_grid)
    p = PchipInterpolator(s_grid[order], values[order], extrapolate=True)
    out = p(np.minimum(lam, 1.0))
    above = lam > 1.0
    if np.any(above):
        out = np.where(above, p(1.0) + p.derivative()(1.0) * (lam - 1.0), out)
    return out


def _grid_key(aspect: float, alphas, stretches, mesh: FEMesh) -> str:
    spec = {"aspect": round(float(aspect), 4), "alphas": [round(float(a), 6) for a in alphas],
            "stretches": [round(float(s), 6) for s in stretches], "mesh": asdict(mesh),
            "bulk_ratio": BULK_RATIO, "fold_over": FOLD_OVER, "contact_penalty": CONTACT_PENALTY,
            "version": TABLE_VERSION}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:12]


def table_filename(aspect: float, alphas=ALPHA_GRID, stretches=STRETCH_GRID,
                   mesh: FEMesh = DEFAULT_MESH) -> str:
    """File name of a table: aspect, a hash of grid, mesh and model, and the version."""
    return (f"noslip_a{round(float(aspect), 4):.4f}_{_grid_key(aspect, alphas, stretches, mesh)}"
            f"_v{TABLE_VERSION}.npz")


def cache_dir() -> Path:
    """``$BSIPIPE_CACHE/noslip``, else ``$XDG_CACHE_HOME/bsipipe/noslip`` or ``~/.cache/...``."""
    root = os.environ.get("BSIPIPE_CACHE")
    if root:
        return Path(root) / "noslip"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "bsipipe" / "noslip"


def shipped_dir() -> Path:
    return Path(__file__).resolve().parent / "_data"


def _table_column(alpha: float, aspect: float, stretches, mesh: FEMesh):
    """One alpha of a table: the ratio to the homogeneous force and the width over D."""
    s = np.asarray(stretches, dtype=float)
    run = s[s < 1.0]
    t0 = time.perf_counter()
    nominal, width, iters = _solve_unit(run, alpha, aspect, mesh)
    ratio = nominal / ogden_nominal_stress(run, [1.0], [alpha])
    # The small-strain limit: the ratio is linear in the stretch near 1; extrapolate from
    # the two smallest strains (0.1 % and 0.2 % on the default grid).
    r1 = ratio[0] + (ratio[0] - ratio[1]) * (1.0 - run[0]) / (run[0] - run[1])
    return (float(alpha), np.concatenate([[r1], ratio]), np.concatenate([[1.0], width]),
            int(iters.sum()), time.perf_counter() - t0)


def build_table(aspect: float, alphas=ALPHA_GRID, stretches=STRETCH_GRID,
                mesh: FEMesh = DEFAULT_MESH, workers: int | None = None,
                progress: bool = True) -> NoSlipTable:
    """Run the FE model for every alpha (in parallel processes) and return the table."""
    alphas = np.asarray(alphas, dtype=float)
    stretches = np.asarray(stretches, dtype=float)
    if stretches[0] != 1.0 or np.any(np.diff(stretches) >= 0):
        raise ValueError("the stretch grid must start at 1.0 and decrease")
    if np.any(np.abs(alphas) < 1e-9):
        raise ValueError("alpha = 0 is not an Ogden exponent")
    workers = workers or min(len(alphas), os.cpu_count() or 1)
    t0 = time.perf_counter()
    results, failures = {}, []
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(alphas), file=sys.stderr, unit="alpha",
                   desc=f"no-slip FE table, H/D = {aspect:.4g}")
    try:
        if workers == 1:
            for a in alphas:
                try:
                    results[float(a)] = _table_column(a, aspect, stretches, mesh)
                except RuntimeError as exc:
                    failures.append(str(exc))
                if bar is not None:
                    bar.update()
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures = [pool.submit(_table_column, float(a), aspect, stretches, mesh) for a in alphas]
                for fut in as_completed(futures):
                    try:
                        col = fut.result()
                        results[col[0]] = col
                    except RuntimeError as exc:
                        failures.append(str(exc))
                    if bar is not None:
                        bar.update()
    finally:
        if bar is not None:
            bar.close()
    if failures:  # every failure at once: one rerun to see them all is expensive enough
        raise RuntimeError(f"{len(failures)} of {len(alphas)} FE runs failed:\n" + "\n".join(failures))
    cols = [results[float(a)] for a in alphas]
    import felupe
    meta = {"table_version": TABLE_VERSION, "mesh": asdict(mesh), "bulk_ratio": BULK_RATIO,
            "fold_over": FOLD_OVER, "contact_penalty": CONTACT_PENALTY, "felupe": felupe.__version__,
            "newton_iterations": [c[3] for c in cols], "seconds_per_alpha": [round(c[4], 2) for c in cols],
            "wall_seconds": round(time.perf_counter() - t0, 1), "workers": workers,
            "key": _grid_key(aspect, alphas, stretches, mesh)}
    return NoSlipTable(aspect=float(aspect), alphas=alphas, stretches=stretches,
                       ratio=np.array([c[1] for c in cols]), width=np.array([c[2] for c in cols]),
                       meta=meta)


def save_table(table: NoSlipTable, folder) -> Path:
    """Write ``table`` atomically into ``folder`` under :func:`table_filename`."""
    from ..provenance import atomic_write_bytes

    mesh = FEMesh(**table.meta["mesh"])
    path = Path(folder) / table_filename(table.aspect, table.alphas, table.stretches, mesh)
    atomic_write_bytes(path, table.to_bytes())
    return path


@lru_cache(maxsize=32)
def _load_table(aspect_key: float, mesh: FEMesh) -> NoSlipTable:
    name = table_filename(aspect_key, ALPHA_GRID, STRETCH_GRID, mesh)
    for folder in (shipped_dir(), cache_dir()):
        path = folder / name
        if path.is_file():
            try:
                return NoSlipTable.from_file(path)
            except (OSError, ValueError, KeyError) as exc:  # a damaged cache file: recompute
                print(f"bsipipe: ignoring unreadable no-slip table {path}: {exc}", file=sys.stderr)
    print(f"bsipipe: no no-slip FE table for H/D = {aspect_key:.4f}; computing it "
          f"({len(ALPHA_GRID)} FE runs, a few minutes) into {cache_dir()}", file=sys.stderr)
    table = build_table(aspect_key, ALPHA_GRID, STRETCH_GRID, mesh=mesh)
    try:
        save_table(table, cache_dir())
    except OSError as exc:  # a read-only home still gets the table for this process
        print(f"bsipipe: could not cache the no-slip table: {exc}", file=sys.stderr)
    return table


def noslip_table(aspect: float, mesh: FEMesh = DEFAULT_MESH) -> NoSlipTable:
    """The table for ``aspect = height / diameter`` (shipped, cached, or computed now)."""
    aspect = float(aspect)
    if not np.isfinite(aspect) or aspect <= 0:
        raise ValueError(f"aspect (height / diameter) must be positive, got {aspect}")
    return _load_table(round(aspect, 4), mesh)


def noslip_nominal_stress(stretch, mu_pa: float, alpha: float, aspect: float) -> np.ndarray:
    r"""Nominal stress (mean platen force / undeformed area, Pa) of a bonded Ogden cylinder.

    .. math::

        P(\lambda) = g(\lambda; \alpha, H/D)\, \frac{2\mu}{\alpha}
            \left(\lambda^{\alpha - 1} - \lambda^{-\alpha/2 - 1}\right)

    with :math:`g` the FE force ratio, interpolated from the table of ``aspect``.

    Parameters
    ----------
    stretch : array_like, shape (n,)
        ``1 - delta / H``, in ``[0.6, 1.01]`` (above 1: linear continuation).
    mu_pa, alpha : float
        One-term Ogden modulus (Pa) and exponent, ``1 <= |alpha| <= 12``.
    aspect : float
        Height / diameter.

    Returns
    -------
    ndarray, shape (n,)
        Negative in compression, like :func:`~bsipipe.mechanics.hyperelastic.ogden_nominal_stress`.

    Examples
    --------
    >>> p = noslip_nominal_stress([0.9, 0.7], 720.0, -4.7, 12 / 18)
    >>> bool(np.all(p < ogden_nominal_stress([0.9, 0.7], [720.0], [-4.7])))  # stiffer
    True
    """
    lam = np.asarray(stretch, dtype=float)
    ratio = noslip_table(aspect).force_ratio(lam, alpha)
    return ratio * ogden_nominal_stress(lam, [mu_pa], [alpha])


def noslip_bulge_width(stretch, alpha: float, diameter_mm: float, aspect: float) -> np.ndarray:
    """Lateral width (mm) of the bonded cylinder at mid-height, interpolated from the table.

    >>> round(float(noslip_bulge_width(1.0, -4.7, 18.0, 12 / 18)), 9)  # ends bonded: width D at contact
    18.0
    """
    lam = np.asarray(stretch, dtype=float)
    return diameter_mm * noslip_table(aspect).bulge_width(lam, alpha)
