r"""Stereo triangulation of markers seen by two calibrated C-arms, with per-point errors.

Each view is a :class:`ViewGeometry`: world-to-camera pose ``x_c = R X + t`` (mm), the
intrinsic matrix ``K`` and two maps between raw (distorted) pixels and undistorted
normalised image coordinates, taken from whichever camera model calibrated it (the
OpenCV model with twist and local field of ``bsipipe calibrate``, or the twin's
:class:`~bsipipe.imaging.camera.Camera`).  With ``calibration.json`` the world frame is
camera A's (the first of ``stereo.views``): A has ``R = I, t = 0``, B has the stereo
``R, T_mm`` (``x_B = R x_A + T``).

For a marker seen at raw pixels ``u_A``, ``u_B``:

1. **Undistort** both to normalised coordinates ``m = (x, y, 1)``.
2. **Linear (DLT)** estimate: the null vector of the 4x4 system
   :math:`[x P_3 - P_1;\ y P_3 - P_2]` of both views, :math:`P = [R | t]`.
3. **Reprojection-minimising** refinement: Gauss-Newton on :math:`X` minimising
   :math:`\sum_v \lVert K_v\,\pi(R_v X + t_v) - K_v m_v \rVert^2` (ideal-pinhole pixels, so
   the residual is in pixels), batched over all points.
4. **Errors**: the *ray gap* :math:`g = (C_B - C_A) \cdot \hat n`,
   :math:`\hat n = (d_A \times d_B)/\lVert d_A \times d_B\rVert`, the closest distance between
   the two back-projected rays (signed: the sign says on which side B's ray passes A's);
   ``ray_gap_mm`` is :math:`|g|`.  The *reprojection error* per view is the distance between
   the observed raw pixel and the raw projection of :math:`X` through the full model.

:func:`lowpass_trajectories` adds a zero-phase Butterworth low-pass (``scipy.signal.filtfilt``)
of the 3-D trajectories in ``*_filt`` columns; the raw values stay.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import pandas as pd


@dataclass
class ViewGeometry:
    """One calibrated view: pose (world -> camera), ``K`` and the pixel maps.

    ``to_normalized(u)`` raw pixels (n, 2) -> undistorted normalised (n, 2);
    ``to_pixels(m)`` the inverse.
    """

    name: str
    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    to_normalized: Callable[[np.ndarray], np.ndarray]
    to_pixels: Callable[[np.ndarray], np.ndarray]
    image_size: tuple[int, int] | None = None

    def __post_init__(self):
        self.R = np.asarray(self.R, float).reshape(3, 3)
        self.t = np.asarray(self.t, float).ravel()
        self.K = np.asarray(self.K, float).reshape(3, 3)

    @property
    def centre_mm(self) -> np.ndarray:
        """Camera centre (the X-ray focal spot) in world coordinates."""
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """Normalised projection matrix ``[R | t]`` (3, 4)."""
        return np.hstack([self.R, self.t[:, None]])

    def ray_directions(self, pixels: np.ndarray) -> np.ndarray:
        """Unit world directions (n, 2 -> n, 3) of the rays through raw pixels."""
        return self.rays_from_normalized(self.to_normalized(np.asarray(pixels, float).reshape(-1, 2)))

    def rays_from_normalized(self, m: np.ndarray) -> np.ndarray:
        """Unit world directions (n, 3) of the rays through undistorted normalised points (n, 2)."""
        d = np.column_stack([m, np.ones(len(m))]) @ self.R      # R^T (x, y, 1) for each row
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (n, 3) -> raw pixels (n, 2) through the full camera model (a point in
        the camera's own plane, z = 0, has no image: inf or NaN, without a warning)."""
        Xc = np.asarray(X, float).reshape(-1, 3) @ self.R.T + self.t
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.to_pixels(Xc[:, :2] / Xc[:, 2:3])


# --- building views ----------------------------------------------------------------------------

def _calibrate_camera_model(d: Mapping):
    """``bsipipe calibrate``'s camera model from its ``calibration.json`` entry."""
    from .calibrate import CameraModel
    return CameraModel.from_dict(d)


def _opencv_maps(model) -> tuple[Callable, Callable]:
    import cv2

    def to_norm(u):
        u = np.asarray(u, float).reshape(-1, 2)
        if len(u) == 0:
            return np.zeros((0, 2))
        return model.undistort_points(u)

    def to_pix(m):
        m = np.asarray(m, float).reshape(-1, 2)
        if len(m) == 0:
            return np.zeros((0, 2))
        obj = np.column_stack([m, np.ones(len(m))]).reshape(-1, 1, 3)
        p, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), model.camera_matrix, model.dist_coeffs)
        return model.extras(p.reshape(-1, 2))

    return to_norm, to_pix


def views_from_calibration(cal: Mapping, names: tuple[str, str] | None = None) -> dict[str, ViewGeometry]:
    """The two stereo views of a ``calibration.json`` (dict).

    The world frame is always the calibration's: the camera frame of ``stereo.views[0]``
    (``x_B = R x_A + T``).  ``names`` only orders the returned dict (default
    ``stereo.views``).  A calibration without a ``stereo`` block cannot triangulate:
    ValueError.
    """
    st = cal.get("stereo")
    if not st:
        raise ValueError("the calibration has no 'stereo' block (two views calibrated together)")
    a, b = st["views"]
    if names is not None and set(names) != {a, b}:
        raise ValueError(f"the calibration's stereo views are {a!r}, {b!r}, not {names[0]!r}, {names[1]!r}")
    R, T = np.asarray(st["R"], float).reshape(3, 3), np.asarray(st["T_mm"], float).ravel()
    out = {}
    for n, Rv, tv in ((a, np.eye(3), np.zeros(3)), (b, R, T)):
        if n not in cal["views"]:
            raise ValueError(f"the calibration has no view {n!r}")
        model = _calibrate_camera_model(cal["views"][n])
        to_norm, to_pix = _opencv_maps(model)
        out[n] = ViewGeometry(n, Rv, tv, model.camera_matrix, to_norm, to_pix, model.image_size)
    return {n: out[n] for n in (names or (a, b))}


def views_from_cameras(cameras: Mapping) -> dict[str, ViewGeometry]:
    """Views from :class:`~bsipipe.imaging.camera.Camera` objects (e.g. the twin's truth),
    in their common world frame."""
    return {n: ViewGeometry(n, c.R, c.t, c.K, c.pixels_to_normalized, c.normalized_to_pixels, tuple(c.image_size))
            for n, c in cameras.items()}


# --- triangulation -----------------------------------------------------------------------------

def triangulate_dlt(views: list[ViewGeometry], normalized: list[np.ndarray]) -> np.ndarray:
    """Linear triangulation (n, 3) from normalised coordinates (n, 2) in each view: the right
    singular vector of the stacked :math:`x P_3 - P_1, y P_3 - P_2` rows, batched, in world
    coordinates conditioned as Hartley and Zisserman advise: centred on the cameras' centres
    and scaled by their spread, so the homogeneous coordinate weighs as much as the others.
    In millimetres as they are (OpenCV's real stereo pair, 84 mm apart, a board 390 mm away) the
    point came out 3.96 px off in the second view and the board's 25 mm squares 28.5 +- 6.0 mm;
    conditioned, 0.10 px in both and 25.02 +- 0.44 mm, the reprojection-minimising point's."""
    C = np.array([v.centre_mm for v in views])
    c = C.mean(axis=0)
    s = max(float(np.linalg.norm(C - c, axis=1).max()), 1e-12)
    Tn = np.eye(4)
    Tn[:3, :3] *= s
    Tn[:3, 3] = c
    rows = []
    for v, m in zip(views, normalized):
        P = v.P @ Tn
        m = np.asarray(m, float).reshape(-1, 2)
        rows.append(m[:, 0, None] * P[2][None] - P[0][None])
        rows.append(m[:, 1, None] * P[2][None] - P[1][None])
    A = np.stack(rows, axis=1)                                   # (n, 2V, 4)
    A = A / np.linalg.norm(A, axis=2, keepdims=True)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    return c + s * Xh[:, :3] / Xh[:, 3:4]


def refine_points(views: list[ViewGeometry], normalized: list[np.ndarray], X0: np.ndarray,
                  n_iter: int = 10) -> np.ndarray:
    r"""Gauss-Newton minimisation of the ideal-pixel reprojection error over ``X`` (n, 3).

    Batched in closed form: each view adds the outer products of its two Jacobian rows
    :math:`K_{ii}/z\,(R_i - u_i R_3)` to the 3x3 normal matrix, which is solved by its adjugate.
    """
    X = np.array(X0, float)
    geo = []
    for v, m in zip(views, normalized):
        m = np.asarray(m, float).reshape(-1, 2)
        geo.append((v.R, v.t, v.K[0, 0], v.K[1, 1], m[:, 0], m[:, 1]))
    for _ in range(n_iter):
        a00 = a01 = a02 = a11 = a12 = a22 = g0 = g1 = g2 = 0.0
        for R, t, fx, fy, mx, my in geo:
            Xc = X @ R.T + t
            iz = 1 / Xc[:, 2]
            ux, uy = Xc[:, 0] * iz, Xc[:, 1] * iz
            rx, ry = (mx - ux) * fx, (my - uy) * fy
            # rows of the Jacobian of K pi(R X + t): K_ii / z (R_i - u_i R_3)
            sx, sy = fx * iz, fy * iz
            x0, x1, x2 = sx * (R[0, 0] - ux * R[2, 0]), sx * (R[0, 1] - ux * R[2, 1]), sx * (R[0, 2] - ux * R[2, 2])
            y0, y1, y2 = sy * (R[1, 0] - uy * R[2, 0]), sy * (R[1, 1] - uy * R[2, 1]), sy * (R[1, 2] - uy * R[2, 2])
            a00 = a00 + (x0 * x0 + y0 * y0)
            a01 = a01 + (x0 * x1 + y0 * y1)
            a02 = a02 + (x0 * x2 + y0 * y2)
            a11 = a11 + (x1 * x1 + y1 * y1)
            a12 = a12 + (x1 * x2 + y1 * y2)
            a22 = a22 + (x2 * x2 + y2 * y2)
            g0 = g0 + (x0 * rx + y0 * ry)
            g1 = g1 + (x1 * rx + y1 * ry)
            g2 = g2 + (x2 * rx + y2 * ry)
        # the 3x3 normal equations by the adjugate
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a11 * a02
        c11 = a00 * a22 - a02 * a02
        c12 = a01 * a02 - a00 * a12
        c22 = a00 * a11 - a01 * a01
        det = a00 * c00 + a01 * c01 + a02 * c02
        ok = np.isfinite(det) & (np.abs(det) > 1e-300) & np.isfinite(g0) & np.isfinite(g1) & np.isfinite(g2)
        with np.errstate(invalid="ignore", divide="ignore"):
            step = np.column_stack([c00 * g0 + c01 * g1 + c02 * g2,
                                    c01 * g0 + c11 * g1 + c12 * g2,
                                    c02 * g0 + c12 * g1 + c22 * g2]) / det[:, None]
        step[~ok] = 0.0
        X = X + step
        if np.max(np.abs(step), initial=0.0) < 1e-13 * max(1.0, float(np.max(np.abs(X), initial=1.0))):
            break
    return X


def _midpoints(views: tuple[ViewGeometry, ViewGeometry], ma: np.ndarray, mb: np.ndarray) -> np.ndarray:
    """Starting points (n, 3) for :func:`refine_points`: the midpoints of the common
    perpendiculars of the two rays (closed form); nearly parallel rays get the linear
    (:func:`triangulate_dlt`) point."""
    va, vb = views
    da, db = va.rays_from_normalized(ma), vb.rays_from_normalized(mb)
    ca, cb = va.centre_mm, vb.centre_mm
    w = ca - cb
    b = np.einsum("ij,ij->i", da, db)
    d, e = da @ w, db @ w
    den = 1.0 - b * b
    par = ~(den > 1e-9)
    with np.errstate(invalid="ignore", divide="ignore"):
        sa = (b * e - d) / den
        sb = (e - b * d) / den
    X = 0.5 * ((ca + sa[:, None] * da) + (cb + sb[:, None] * db))
    if par.any():
        X[par] = triangulate_dlt([va, vb], [ma[par], mb[par]])
    return X


def _gaps_of_rays(da: np.ndarray, db: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed ray gaps (n,) of unit directions ``da``, ``db`` (n, 3) from centres ``base`` apart
    (B's minus A's) and the rays' unit common normals (n, 3; NaN for parallel rays)."""
    n = np.cross(da, db)
    nn = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = n / nn[:, None]
    return (n / np.where(nn > 0, nn, 1)[:, None]) @ base, unit


def ray_gaps(views: tuple[ViewGeometry, ViewGeometry], uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """Signed closest distance (n,) mm between the rays through raw pixels of two views."""
    va, vb = views
    return _gaps_of_rays(va.ray_directions(uv_a), vb.ray_directions(uv_b), vb.centre_mm - va.centre_mm)[0]


def triangulate(views: tuple[ViewGeometry, ViewGeometry], uv_a, uv_b, *, refine: bool = True) -> dict:
    """Triangulate points seen at raw pixels ``uv_a``, ``uv_b`` (n, 2; NaN rows stay NaN).

    Returns a dict of arrays: ``X_mm`` (n, 3), ``ray_gap_mm`` (n,, >= 0), ``ray_gap_signed_mm``,
    ``reproj_px`` (n, 2: per view, raw pixels) and ``reproj_rms_px`` (n,).
    """
    r = _triangulate(views, uv_a, uv_b, refine=refine)
    del r["normal"]
    return r


def _triangulate(views: tuple[ViewGeometry, ViewGeometry], uv_a, uv_b, *, refine: bool = True) -> dict:
    """:func:`triangulate`, and ``normal`` (n, 3): the rays' unit common normals.  Each view's
    pixels are undistorted once (for the points, the gaps and the normals)."""
    uv_a = np.asarray(uv_a, float).reshape(-1, 2)
    uv_b = np.asarray(uv_b, float).reshape(-1, 2)
    n = len(uv_a)
    X = np.full((n, 3), np.nan)
    gap = np.full(n, np.nan)
    rep = np.full((n, 2), np.nan)
    nrm = np.full((n, 3), np.nan)
    ok = np.isfinite(uv_a).all(axis=1) & np.isfinite(uv_b).all(axis=1)
    if ok.any():
        va, vb = views
        ma, mb = va.to_normalized(uv_a[ok]), vb.to_normalized(uv_b[ok])
        # the linear point without refinement; refined, any point near the optimum will do
        Xo = refine_points([va, vb], [ma, mb], _midpoints(views, ma, mb)) if refine else \
            triangulate_dlt([va, vb], [ma, mb])
        X[ok] = Xo
        gap[ok], nrm[ok] = _gaps_of_rays(va.rays_from_normalized(ma), vb.rays_from_normalized(mb),
                                         vb.centre_mm - va.centre_mm)
        rep[ok, 0] = np.linalg.norm(va.project(Xo) - uv_a[ok], axis=1)
        rep[ok, 1] = np.linalg.norm(vb.project(Xo) - uv_b[ok], axis=1)
    return {"X_mm": X, "ray_gap_mm": np.abs(gap), "ray_gap_signed_mm": gap, "reproj_px": rep,
            "reproj_rms_px": np.sqrt(np.mean(rep ** 2, axis=1)), "normal": nrm}


def point_covariance(views, X: np.ndarray, sd_px) -> np.ndarray:
    r"""First-order covariance (N, 3, 3) mm^2 of points ``X`` (N, 3) triangulated from views
    whose centres each have per-axis standard deviations ``sd_px`` (one (N,) array per view,
    px).  :func:`triangulate` minimises the plain sum of squared reprojection errors, so the
    covariance is the sandwich :math:`A^{-1} B A^{-1}`, :math:`A = \sum_v J_v^T J_v`,
    :math:`B = \sum_v s_v^2 J_v^T J_v`, :math:`J_v` the Jacobian (2 x 3) of view ``v``'s
    full projection (distortion included, by central differences) at the point.  Along a
    view's rays the depth is set by the other view only.  NaN where a view's sd is missing
    or not positive, or the point is not finite."""
    X = np.asarray(X, float).reshape(-1, 3)
    n = len(X)
    A = np.zeros((n, 3, 3))
    B = np.zeros((n, 3, 3))
    bad = ~np.isfinite(X).all(axis=1)
    h = 1e-3                                                       # mm
    Xs = np.where(bad[:, None], 0.0, X)
    for view, sd in zip(views, sd_px):
        sd = np.asarray(sd, float).reshape(-1)
        ok = np.isfinite(sd) & (sd > 0)
        bad |= ~ok
        J = np.empty((n, 2, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            J[:, :, k] = (view.project(Xs + e) - view.project(Xs - e)) / (2 * h)
        JJ = np.einsum("nik,nil->nkl", J, J)
        A += JJ
        B += np.where(ok, sd, 0.0)[:, None, None] ** 2 * JJ
    cov = np.full((n, 3, 3), np.nan)
    good = ~bad
    if good.any():
        Ai = np.linalg.inv(A[good])
        cov[good] = Ai @ B[good] @ Ai
    return cov


def single_view_covariance(view: ViewGeometry, X: np.ndarray, sd_px, sd_along_mm) -> np.ndarray:
    r"""First-order covariance (N, 3, 3) mm^2 of points ``X`` (N, 3) placed on one view's rays
    (:func:`closest_point_on_ray`: the depth along the ray from a trajectory the two-view
    points give).  Across the ray, the centre's per-axis sd ``sd_px`` (N,) through the
    pseudo-inverse of the projection's Jacobian, :math:`s^2 J^+ J^{+T}`; along it,
    ``sd_along_mm`` (N,), the sd the trajectory has there.  NaN where either is missing."""
    X = np.asarray(X, float).reshape(-1, 3)
    n = len(X)
    sd = np.asarray(sd_px, float).reshape(-1)
    sa = np.asarray(sd_along_mm, float).reshape(-1)
    cov = np.full((n, 3, 3), np.nan)
    ok = np.isfinite(X).all(axis=1) & np.isfinite(sd) & (sd > 0) & np.isfinite(sa) & (sa >= 0)
    if not ok.any():
        return cov
    Xs = X[ok]
    h = 1e-3
    J = np.empty((len(Xs), 2, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        J[:, :, k] = (view.project(Xs + e) - view.project(Xs - e)) / (2 * h)
    Jp = np.linalg.pinv(J)                                   # (m, 3, 2), across the ray
    r = Xs - view.centre_mm
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    cov[ok] = (sd[ok, None, None] ** 2 * Jp @ Jp.transpose(0, 2, 1)
               + sa[ok, None, None] ** 2 * r[:, :, None] * r[:, None, :])
    return cov


def closest_point_on_ray(view: ViewGeometry, uv: np.ndarray, target_mm: np.ndarray) -> np.ndarray:
    """The point (n, 3) on each ray through raw pixels ``uv`` nearest to ``target_mm`` (n, 3):
    a single-view reconstruction constrained by a predicted 3-D position."""
    d = view.ray_directions(uv)
    c = view.centre_mm
    s = np.einsum("ij,ij->i", np.asarray(target_mm, float) - c, d)
    return c + s[:, None] * d


# --- filtering -----------------------------------------------------------------------------------

def lowpass_trajectories(points: pd.DataFrame, cutoff_hz: float, fps: float, order: int = 4,
                         columns=("x_mm", "y_mm", "z_mm")) -> pd.DataFrame:
    """Zero-phase Butterworth low-pass of each marker's trajectory (``scipy.signal.filtfilt``).

    ``points`` has ``marker``, ``frame`` and ``columns``; each contiguous run of frames with
    a position is filtered on its own (no filtering across gaps).  Adds ``<col>_filt``
    columns (the raw columns stay); runs too short for ``filtfilt``'s padding keep their raw
    values there, flagged ``filtered = False``.
    """
    from scipy.signal import butter, filtfilt
    if not 0 < cutoff_hz < fps / 2:
        raise ValueError(f"cutoff {cutoff_hz} Hz must lie between 0 and the Nyquist frequency {fps / 2} Hz")
    b, a = butter(order, cutoff_hz / (fps / 2))
    pad = 3 * max(len(a), len(b))
    out = points.copy()
    for c in columns:
        out[c + "_filt"] = out[c].astype(float)
    out["filtered"] = False
    for _, g in out.sort_values("frame").groupby("marker", sort=False):
        idx = g.index.to_numpy()
        fin = np.isfinite(g[list(columns)].to_numpy()).all(axis=1)
        fr = g["frame"].to_numpy()
        # contiguous runs of consecutive frames with finite positions
        cont = np.r_[False, fin[1:] & fin[:-1] & (np.diff(fr) == 1)]
        run_id = np.cumsum(~cont)
        for r in np.unique(run_id[fin]):
            run = np.flatnonzero((run_id == r) & fin)
            if len(run) > pad:
                for c in columns:
                    out.loc[idx[run], c + "_filt"] = filtfilt(b, a, g[c].to_numpy()[run])
                out.loc[idx[run], "filtered"] = True
    return out
