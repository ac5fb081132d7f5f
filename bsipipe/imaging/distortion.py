r"""Single-image radial distortion from the straightness of a dot grid (discorpy-style).

A flat plate of dots in a regular square grid is imaged once.  Without distortion every row
and column of dots lies on a straight line (a perspective view keeps lines straight), so
the distortion is the radial map that makes them straight again.  Model (forward:
distorted pixel :math:`\mathbf d` to undistorted :math:`\mathbf u`, about the centre of
distortion :math:`\mathbf c`):

.. math::  \mathbf u = \mathbf c + (\mathbf d - \mathbf c)\, F(\rho), \qquad
           F(\rho) = 1 + \sum_{k=1}^{K} a_k \rho^k, \qquad
           \rho = \lVert \mathbf d - \mathbf c \rVert / s,

with :math:`s` half the image diagonal (so the :math:`a_k` are dimensionless and of
similar size) and :math:`F(0) = 1` (magnification at the centre unchanged; it cannot be
told from straightness).

The centre :math:`\mathbf c` is where the grid's rows and columns stop bending
(:func:`centre_of_distortion`): the one row and the one column that radial distortion
leaves straight, found from the zero crossing of the lines' parabola curvatures, a
geometric definition that does not depend on the polynomial, the lines' extent or the
perspective, reported with an uncertainty (noise and split halves).  With :math:`\mathbf
c` held there, :math:`a_1 \ldots a_K` minimise the sum of squared perpendicular distances
of the corrected dots from the total-least-squares line of their row or column (each
line's fit eliminated in closed form: its normal is the eigenvector of the smallest
eigenvalue of the points' scatter matrix), by ``scipy.optimize.least_squares``.  Dots
whose line residual is an outlier (over :data:`OUTLIER_SIGMAS` robust standard
deviations) are dropped and the fit repeated once: a damaged dot or one at the edge of an
object must not bend the map.

Why not fit :math:`\mathbf c` with the coefficients (``centre="joint"``, kept as a check):
the straightness of the lines hardly depends on it.  To first order a shift of the centre
is the same distortion as decentring (tangential) terms, and what is left trades against
the polynomial's high orders at the edge of the grid, where the distortion is largest; on
discorpy's ``dot_pattern_05`` the joint optimum sits 10 px from the curvature centre (its
Jacobian standard deviation says 0.3 px) and straightens the lines by 0.003 px RMS more
(0.015 against 0.018 px).  The joint fit's centre and its straightness are reported next
to the fixed-centre fit as the identifiability check.

"Off a straight grid": the straight grid is the homography of the grid indices that best
matches the *corrected* dots; before correction the raw dots are compared with it (this
is the distortion displacement, at the central magnification), after correction the
corrected dots.

This is the same model family as discorpy's (Vo et al. 2015, Opt. Express 23, 32859),
which writes the backward map :math:`\mathbf d = \mathbf c + (\mathbf u - \mathbf c)
\sum_k f_k r_u^k` and takes its centre (``find_cod_coarse``) between the first two lines
whose parabola curvatures differ in sign; :func:`centre_of_distortion` interpolates the
same zero crossing from a fit over many lines.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

#: Line residuals further than this many robust standard deviations from the median are outliers.
OUTLIER_SIGMAS = 6.0


@dataclass(frozen=True)
class RadialDistortion:
    """Forward radial map about ``centre_px`` (see the module docstring)."""

    centre_px: tuple[float, float]
    coeffs: tuple[float, ...]
    norm_radius_px: float

    def _F(self, rho: np.ndarray) -> np.ndarray:
        return 1.0 + sum(a * rho ** (k + 1) for k, a in enumerate(self.coeffs))

    def undistort(self, xy: np.ndarray) -> np.ndarray:
        """Distorted pixels (n, 2) -> undistorted pixels (n, 2)."""
        xy = np.asarray(xy, dtype=float)
        d = xy - np.asarray(self.centre_px)
        rho = np.hypot(d[:, 0], d[:, 1]) / self.norm_radius_px
        return np.asarray(self.centre_px) + d * self._F(rho)[:, None]

    def distort(self, xy_undist: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Inverse map by Newton's method on the radius: undistorted (n, 2) -> distorted (n, 2)."""
        u = np.asarray(xy_undist, dtype=float) - np.asarray(self.centre_px)
        ru = np.hypot(u[:, 0], u[:, 1]) / self.norm_radius_px
        rd = ru.copy()
        for _ in range(iterations):
            F = self._F(rd)
            dF = sum((k + 1) * a * rd ** k for k, a in enumerate(self.coeffs))
            step = (rd * F - ru) / (F + rd * dF)
            rd = rd - step
            if np.max(np.abs(step), initial=0.0) < 1e-12:
                break
        scale = np.divide(rd, ru, out=np.ones_like(ru), where=ru > 0)
        return np.asarray(self.centre_px) + u * scale[:, None]

    def to_dict(self) -> dict:
        return {"model": "radial-forward", "centre_px": list(self.centre_px), "coeffs": list(self.coeffs),
                "norm_radius_px": self.norm_radius_px,
                "formula": "u = c + (d - c) * (1 + sum_k a_k rho^k), rho = |d - c| / norm_radius_px"}


@dataclass
class StraightnessFit:
    """Result of :func:`fit_straightness`.

    distortion : RadialDistortion
    centre_std_px : (2,) standard uncertainty of the centre: :attr:`CentreEstimate.std_px` for
        the curvature centre, the Jacobian's (noise only) for a joint fit, 0 for a given one
    line_residual_before_px, line_residual_after_px : (n,) signed distance of each dot from
        its line's straight fit, raw and corrected (each dot counted in its row and column)
    grid_offset_before_px, grid_offset_after_px : (n,) distance of each dot from the straight
        grid, raw and corrected
    inlier : (n,) bool, dots used in the final fit
    centre : CentreEstimate, when the centre came from :func:`centre_of_distortion`
    info : the fit's details; ``joint_fit``: the identifiability check of a fixed centre
    """

    distortion: RadialDistortion
    centre_std_px: np.ndarray
    line_residual_before_px: np.ndarray
    line_residual_after_px: np.ndarray
    grid_offset_before_px: np.ndarray
    grid_offset_after_px: np.ndarray
    inlier: np.ndarray
    n_lines: int
    centre: CentreEstimate | None = None
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        inl = self.inlier
        gb, ga = self.grid_offset_before_px, self.grid_offset_after_px
        lb, la = np.abs(self.line_residual_before_px), np.abs(self.line_residual_after_px)
        return {
            "centre_px": list(self.distortion.centre_px),
            "centre_std_px": self.centre_std_px.tolist(),
            "centre_method": self.info.get("centre_method", "joint"),
            "centre": self.centre.to_dict() if self.centre is not None else None,
            "joint_fit": self.info.get("joint_fit"),
            "coeffs": list(self.distortion.coeffs),
            "n_dots": int(len(inl)), "n_outlier_dots": int((~inl).sum()), "n_lines": self.n_lines,
            "grid_offset_before_max_px": float(gb.max()), "grid_offset_before_rms_px": _rms(gb),
            "grid_offset_after_max_px": float(ga.max()), "grid_offset_after_rms_px": _rms(ga),
            "grid_offset_after_max_inliers_px": float(ga[inl].max()),
            "line_residual_before_max_px": float(lb.max()), "line_residual_before_rms_px": _rms(lb),
            "line_residual_after_max_px": float(la.max()), "line_residual_after_rms_px": _rms(la),
        }


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def grid_lines(ij: np.ndarray, min_points: int = 5) -> list[np.ndarray]:
    """Index arrays of the rows (same ``ij[:, 1]``) and columns (same ``ij[:, 0]``) of a grid."""
    ij = np.asarray(ij)
    out = []
    for axis in (1, 0):
        for v in np.unique(ij[:, axis]):
            idx = np.flatnonzero(ij[:, axis] == v)
            if len(idx) >= min_points:
                out.append(idx)
    return out


def line_residuals(xy: np.ndarray, lines: list[np.ndarray]) -> np.ndarray:
    """Signed perpendicular distance of each point from its line's total-least-squares fit,
    concatenated line by line (a point on a row and a column appears twice)."""
    out = []
    for idx in lines:
        p = xy[idx]
        q = p - p.mean(axis=0)
        _, vec = np.linalg.eigh(q.T @ q)
        out.append(q @ vec[:, 0])
    return np.concatenate(out) if out else np.zeros(0)


def _per_dot(values: np.ndarray, lines: list[np.ndarray], n: int) -> np.ndarray:
    """Largest |line residual| of each dot over its row and column."""
    worst = np.zeros(n)
    k = 0
    for idx in lines:
        v = np.abs(values[k:k + len(idx)])
        worst[idx] = np.maximum(worst[idx], v)
        k += len(idx)
    return worst


def straight_grid_offsets(xy: np.ndarray, ij: np.ndarray, reference_xy: np.ndarray | None = None) -> np.ndarray:
    """Distance of each point from the straight grid: the least-squares homography
    ``ij -> reference_xy`` (``reference_xy`` defaults to ``xy``) evaluated at ``ij``."""
    import cv2
    ref = xy if reference_xy is None else reference_xy
    H, _ = cv2.findHomography(np.asarray(ij, np.float64), np.asarray(ref, np.float64), 0)
    q = np.column_stack([ij, np.ones(len(ij))]) @ H.T
    g = q[:, :2] / q[:, 2:]
    return np.hypot(*(np.asarray(xy) - g).T)


def fit_straightness(xy: np.ndarray, ij: np.ndarray, image_size: tuple[int, int], n_coeffs: int = 4,
                     min_line_points: int = 5,
                     centre: Literal["curvature", "joint"] | tuple[float, float] = "curvature") -> StraightnessFit:
    """Radial coefficients (and, with ``centre="joint"``, the centre) that make the grid's rows
    and columns straight.

    Parameters
    ----------
    xy : ndarray (n, 2) dot centres, px
    ij : ndarray (n, 2) int, grid (column, row) index of each dot (any origin)
    image_size : (width, height) px, sets the normalising radius (half the diagonal) and the
        starting centre of a joint fit (the image centre)
    n_coeffs : number K of polynomial terms
    centre : ``"curvature"`` (default): the centre where the rows and columns stop bending
        (:func:`centre_of_distortion`, with its uncertainty), held fixed while the
        coefficients are fitted; ``"joint"``: the centre fitted with the coefficients; or an
        (x, y) px held fixed.

    Identifiability check: with a fixed centre the joint fit is run as well, from that
    centre, and its centre, its Jacobian standard deviation and its straightness are in
    ``info["joint_fit"]``.  The joint fit's centre is a weak optimum: it trades against the
    polynomial at the edge of the grid, where the distortion is largest, and first-order
    shifts of it are the same distortion as decentring terms (see
    :func:`centre_of_distortion`).
    """
    from scipy.optimize import least_squares

    xy = np.asarray(xy, dtype=float)
    ij = np.asarray(ij)
    w, h = image_size
    s = 0.5 * float(np.hypot(w, h))
    inlier = np.ones(len(xy), dtype=bool)
    estimate = None
    if isinstance(centre, str) and centre == "curvature":
        estimate = centre_of_distortion(xy, ij, min_line_points)
        fixed = estimate.centre_px
    elif isinstance(centre, str) and centre == "joint":
        fixed = None
    elif isinstance(centre, str):
        raise ValueError(f"centre must be 'curvature', 'joint' or (x, y) px, got {centre!r}")
    else:
        fixed = np.asarray(centre, dtype=float).reshape(2)

    def run(fixed_c, inlier, p0):
        def model(p):
            c = fixed_c if fixed_c is not None else p[:2]
            a = p if fixed_c is not None else p[2:]
            return RadialDistortion((float(c[0]), float(c[1])), tuple(float(v) for v in a), s)

        def fit(mask, p0):
            idx_map = np.flatnonzero(mask)
            lines = grid_lines(ij[mask], min_line_points)
            pts = xy[mask]

            def res(p):
                return line_residuals(model(p).undistort(pts), lines)

            return least_squares(res, p0, x_scale="jac", method="lm"), lines, idx_map

        r, lines, idx_map = fit(inlier, p0)
        if inlier.all():
            # robust pass: drop dots whose line residual is an outlier, refit once
            e = r.fun
            sig = 1.4826 * np.median(np.abs(e - np.median(e)))
            worst = _per_dot(e, lines, len(idx_map))
            bad = worst > OUTLIER_SIGMAS * max(sig, 1e-6)
            if bad.any():
                inlier = inlier.copy()
                inlier[idx_map[bad]] = False
                r, lines, idx_map = fit(inlier, r.x)
        # noise-only standard deviations from the Jacobian at the optimum
        s2 = float(r.fun @ r.fun) / max(len(r.fun) - len(r.x), 1)
        try:
            std = np.sqrt(np.diag(np.linalg.inv(r.jac.T @ r.jac) * s2))
        except np.linalg.LinAlgError:
            std = np.full(len(r.x), np.nan)
        return model(r.x), r, std, inlier

    a0 = np.zeros(n_coeffs)
    start = np.array([0.5 * (w - 1), 0.5 * (h - 1)]) if fixed is None else fixed
    dist, r, std, inlier = run(fixed, inlier, a0 if fixed is not None else np.concatenate([start, a0]))
    info = {"n_coeffs": n_coeffs, "success": bool(r.success), "nfev": int(r.nfev)}
    if fixed is None:
        centre_std = std[:2]
        info["centre_method"] = "joint"
    else:
        centre_std = estimate.std_px if estimate is not None else np.zeros(2)
        info["centre_method"] = "curvature-zero-crossing" if estimate is not None else "given"
        jd, _, jstd, _ = run(None, inlier, np.concatenate([fixed, r.x]))
        lines_in = grid_lines(ij[inlier], min_line_points)
        info["joint_fit"] = {
            "centre_px": list(jd.centre_px), "centre_std_px": jstd[:2].tolist(),
            "centre_shift_px": float(np.hypot(*(np.asarray(jd.centre_px) - fixed))),
            "line_residual_rms_px": _rms(line_residuals(jd.undistort(xy[inlier]), lines_in)),
            "line_residual_rms_px_fixed_centre": _rms(line_residuals(dist.undistort(xy[inlier]), lines_in))}
    all_lines = grid_lines(ij, min_line_points)
    und = dist.undistort(xy)
    lb = line_residuals(xy, all_lines)
    la = line_residuals(und, all_lines)
    gb = straight_grid_offsets(xy, ij, reference_xy=und)
    ga = straight_grid_offsets(und, ij)
    return StraightnessFit(dist, np.asarray(centre_std, float), lb, la, gb, ga, inlier, len(all_lines),
                           centre=estimate, info=info)


# --- the centre of distortion --------------------------------------------------------------------

#: Lines each side of the zero crossing used in the local fit of curvature against position.
CROSSING_WINDOW_LINES = 6


@dataclass
class CentreEstimate:
    """Result of :func:`centre_of_distortion` (pixels).

    centre_px : (2,) the centre of distortion
    std_px : (2,) standard uncertainty, ``hypot(noise_std_px, split_half_std_px)``
    noise_std_px : (2,) from the scatter of the lines' curvatures about the local fit
    split_half_px : dict, the centre from half-lines: ``rows_left``/``rows_right`` (the rows
        cut at the centre, all columns), ``cols_top``/``cols_bottom`` (the columns cut)
    split_half_std_px : (2,) RMS deviation of the row halves' centres from ``centre_px`` and
        that of the column halves' added in quadrature
    n_rows, n_cols : lines used
    """

    centre_px: np.ndarray
    std_px: np.ndarray
    noise_std_px: np.ndarray
    split_half_px: dict
    split_half_std_px: np.ndarray
    n_rows: int
    n_cols: int

    def to_dict(self) -> dict:
        return {"method": "curvature-zero-crossing", "centre_px": self.centre_px.tolist(),
                "std_px": self.std_px.tolist(), "noise_std_px": self.noise_std_px.tolist(),
                "split_half_px": {k: v.tolist() for k, v in self.split_half_px.items()},
                "split_half_std_px": self.split_half_std_px.tolist(), "n_rows": self.n_rows, "n_cols": self.n_cols}


def _parabolas(t: np.ndarray, s: np.ndarray, groups: list[np.ndarray]) -> np.ndarray:
    """Least-squares :math:`s = a t^2 + b t + c` of each group: (m, 3) rows (a, b, c)."""
    out = np.empty((len(groups), 3))
    for k, idx in enumerate(groups):
        A = np.column_stack([t[idx] ** 2, t[idx], np.ones(len(idx))])
        out[k] = np.linalg.lstsq(A, s[idx], rcond=None)[0]
    return out


def _zero_curvature_line(abc: np.ndarray, window: int) -> tuple[float, float, float]:
    """Position ``c0``, slope ``b0`` and noise standard deviation of ``c0`` of the straight line
    where the curvature ``a`` of a family of lines crosses zero (see :func:`centre_of_distortion`)."""
    a, b, c = abc[:, 0], abc[:, 1], abc[:, 2]
    if len(c) < 4:
        raise ValueError(f"{len(c)} lines: at least 4 are needed to find where their curvature changes sign")
    # the crossing nearest the middle of the lines, from a cubic through all the curvatures ...
    P = np.polyfit(c, a, min(3, len(c) - 2))
    r = np.roots(P)
    r = r[(np.abs(r.imag) < 1e-9 * (1 + np.abs(r.real))) & (r.real >= c.min()) & (r.real <= c.max())].real
    if not len(r):
        raise ValueError("the lines' curvature does not change sign across the grid: the centre of distortion "
                         "is not inside it (fit_straightness(..., centre='joint') fits one instead)")
    c0 = float(r[np.argmin(np.abs(r - np.median(c)))])
    # ... refined by a straight line through the curvatures of the nearest lines, twice
    for _ in range(2):
        near = np.argsort(np.abs(c - c0))[: 2 * window]
        X = np.column_stack([c[near] - c0, np.ones(len(near))])
        (slope, icpt), *_ = np.linalg.lstsq(X, a[near], rcond=None)
        if slope == 0:
            raise ValueError("the lines' curvature does not change with their position: no distortion to centre")
        c0 = c0 - icpt / slope
    X = np.column_stack([c[near] - c0, np.ones(len(near))])
    coef, *_ = np.linalg.lstsq(X, a[near], rcond=None)
    e = a[near] - X @ coef
    cov = np.linalg.inv(X.T @ X) * float(e @ e) / max(len(near) - 2, 1)
    std = float(np.sqrt(cov[1, 1])) / abs(coef[0])  # root c0 - icpt / slope, icpt ~ 0 at the root
    bcoef = np.polyfit(c[near] - c0, b[near], 1)
    return c0, float(bcoef[1]), std


def centre_of_distortion(xy: np.ndarray, ij: np.ndarray, min_line_points: int = 5,
                         window: int = CROSSING_WINDOW_LINES) -> CentreEstimate:
    r"""Centre of distortion of a dot grid: where its rows and its columns stop bending.

    Radial distortion about :math:`\mathbf c` bends a straight line one way on one side of
    :math:`\mathbf c` and the other way on the other, and leaves the line through
    :math:`\mathbf c` straight, whatever the polynomial, the line's extent and any
    perspective (a homography keeps lines straight).  So, in a frame turned to the grid's
    rows, each row is fitted with a parabola :math:`y = a x^2 + b x + c`; the curvature
    :math:`a` against the row's position :math:`c` crosses zero at the one row that is
    straight: a cubic through all :math:`(c, a)` finds the crossing nearest the middle, a
    straight line through the ``2 * window`` nearest rows places it,
    :math:`c_0 = -\alpha_0 / \alpha_1`, and the slope :math:`b` at :math:`c_0` gives the
    straight row :math:`y = c_0 + b_0 x`.  The same for the columns (:math:`x` as a
    parabola in :math:`y`); the centre is where the straight row and column meet.  This is
    discorpy's ``find_cod_coarse`` idea (Vo et al. 2015), with the crossing interpolated
    from a fit over many lines instead of taken between the first two lines whose
    curvatures differ in sign, which makes it robust to the lines' scatter.

    Decentring (tangential) distortion adds a constant to the curvature of every row and
    column and so moves the crossing: to first order a centre shift and decentring terms
    are the same distortion (radial about :math:`\mathbf c + \boldsymbol\delta` equals radial
    about :math:`\mathbf c` plus decentring :math:`p_1 = -k_1 \delta_y, p_2 = -k_1 \delta_x`),
    so straightness alone cannot separate them; this is the centre of the distortion that
    the lines show, decentring included.

    Uncertainty: the noise part from the scatter of the curvatures about the local straight
    line (delta method on the root); the model part from split halves, the rows cut at the
    centre (left and right halves give two estimates of the row crossing) and likewise the
    columns (top and bottom): the RMS deviation of the two row-half centres from the centre
    and that of the two column-half centres, added in quadrature, per coordinate (NaN when
    both halves have too few lines).  A distortion that is not radial about one point
    (S-distortion, a tilted lens) shows up there.

    Parameters
    ----------
    xy : ndarray (n, 2) dot centres, px
    ij : ndarray (n, 2) int, grid (column, row) index of each dot
    min_line_points : lines (and half-lines) with fewer dots are not used
    window : lines each side of the crossing in the local fit
    """
    xy = np.asarray(xy, dtype=float)
    ij = np.asarray(ij)
    coef, *_ = np.linalg.lstsq(np.column_stack([ij, np.ones(len(ij))]), xy, rcond=None)
    th = float(np.arctan2(coef[0, 1], coef[0, 0]))  # direction of a row (ij[:, 0] increasing)
    rot = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])  # image -> grid frame
    origin = xy.mean(axis=0)
    q = (xy - origin) @ rot.T

    def groups(axis: int, mask: np.ndarray) -> list[np.ndarray]:
        out = []
        for v in np.unique(ij[mask, axis]):
            idx = np.flatnonzero(mask & (ij[:, axis] == v))
            if len(idx) >= min_line_points:
                out.append(idx)
        return out

    def crossing(mask_rows, mask_cols):
        rows, cols = groups(1, mask_rows), groups(0, mask_cols)
        yr, br, sy = _zero_curvature_line(_parabolas(q[:, 0], q[:, 1], rows), window)  # y = yr + br x
        xc, bc, sx = _zero_curvature_line(_parabolas(q[:, 1], q[:, 0], cols), window)  # x = xc + bc y
        x = (xc + bc * yr) / (1.0 - br * bc)
        y = yr + br * x
        return np.array([x, y]), np.array([sx, sy]), len(rows), len(cols)

    allm = np.ones(len(xy), bool)
    cq, sq, n_rows, n_cols = crossing(allm, allm)
    centre = origin + cq @ rot
    # noise std in the grid frame -> image frame (a rotation of independent errors)
    noise = np.sqrt((rot.T ** 2) @ (sq ** 2))
    halves = {}
    for name, mr, mc in (("rows_left", q[:, 0] < cq[0], allm), ("rows_right", q[:, 0] >= cq[0], allm),
                         ("cols_top", allm, q[:, 1] < cq[1]), ("cols_bottom", allm, q[:, 1] >= cq[1])):
        try:
            halves[name] = origin + crossing(mr, mc)[0] @ rot
        except ValueError:
            continue  # too few lines or no crossing in that half: it gives no check
    # rows cut in half move the centre along the columns, columns cut along the rows
    split = np.zeros(2)
    for pair in (("rows_left", "rows_right"), ("cols_top", "cols_bottom")):
        dev = np.array([halves[k] - centre for k in pair if k in halves]).reshape(-1, 2)
        split = split + (np.mean(dev ** 2, axis=0) if len(dev) else np.nan)
    split = np.sqrt(split)
    return CentreEstimate(centre, np.hypot(noise, split), noise, halves, split, n_rows, n_cols)
