r"""Point-based registration of the X-ray (calibration) frame to the CT frame, and its errors.

Transform (CONTRACTS.md, ``bsipipe register``): an X-ray point :math:`\mathbf x` maps to the
CT point

.. math::

   \mathbf y = s\,R\,\mathbf x + \mathbf t,

with :math:`R` a rotation, :math:`\mathbf t` in mm and :math:`s = 1` for a rigid transform.
Where the CT's lengths along one of its own axes are off (a slice spacing or reconstruction
interval not the header's, a tilted gantry's table increment taken for the slice spacing), the
CT file's frame is that of a correct CT stretched along the axis, and
:class:`AxisScaledSimilarity` maps into it: :math:`\mathbf y = \mathbf c + D(sR\mathbf x + \mathbf t - \mathbf c)`,
:math:`D = I + (k - 1)\,\mathbf e_a \mathbf e_a^T` (:func:`fit_axis_scaled`).  Where the CT was
acquired with the gantry tilted and read without its tilt (DICOM's GantryDetectorTilt ignored:
the slices stacked without their in-plane shift), the file's frame is a correct CT sheared, an
in-plane axis by the slice axis, and :class:`ShearedSimilarity` maps into it:
:math:`\mathbf y = \mathbf c + H(sR\mathbf x + \mathbf t - \mathbf c)`,
:math:`H = I + k\,\mathbf e_a \mathbf e_b^T`, :math:`k = \tan` of the tilt (:func:`fit_sheared`).
:func:`fit_similarity` solves the least-squares problem
:math:`\min \sum_i w_i |\mathbf y_i - s R \mathbf x_i - \mathbf t|^2` in closed form: the
rotation by Kabsch's SVD of the centred points (scipy ``Rotation.align_vectors``), the scale
by Umeyama (1991), :math:`s = \sum_i w_i\, \bar{\mathbf y}_i \cdot R \bar{\mathbf x}_i / \sum_i w_i |\bar{\mathbf x}_i|^2`
(bars: centred on the weighted centroids), and :math:`\mathbf t = \bar{\mathbf y} - s R \bar{\mathbf x}`.

Errors (Fitzpatrick, West & Maurer 1998, IEEE TMI 17:694; Fitzpatrick & West 2001):

- **FRE** (fiducial registration error) of marker *i*: :math:`|\mathbf y_i - s R \mathbf x_i - \mathbf t|`.
- **FLE** (fiducial localisation error, RMS 3-D, combined over both frames), estimated from
  the residual sum of squares with :math:`3N - p` degrees of freedom (:math:`p` = 6 rigid,
  7 with scale): :math:`\widehat{\mathrm{FLE}}^2 = 3\,\mathrm{RSS} / (3N - p)`; for a rigid
  fit this is :math:`N\,\mathrm{FRE}_{rms}^2/(N-2)`, Fitzpatrick's
  :math:`\langle\mathrm{FRE}^2\rangle = (1 - 2/N)\,\mathrm{FLE}^2` turned round.
- **TRE** (target registration error) at a point :math:`\mathbf r`, first order in FLE:

  .. math::

     \mathrm{TRE}^2(\mathbf r) \approx \frac{\mathrm{FLE}^2}{N}
        \Big(1 + \frac13 \sum_{k=1}^{3} \frac{d_k^2}{f_k^2}\Big)

  with :math:`d_k` the distance of the target from principal axis *k* of the fiducial
  configuration and :math:`f_k` the RMS distance of the fiducials from that axis
  (:func:`tre_fitzpatrick`).  :func:`tre_linearized` propagates the same isotropic FLE through
  the fit's Jacobian, which reproduces the formula for a rigid fit and also covers the
  scale; :func:`tre_perturbation` re-fits perturbed fiducials (a parametric bootstrap) and
  needs no linearisation.

Robustness to a reference that moved: :func:`leave_one_out` (the held-out prediction of each
reference by a fit of the others, with an F test) and :func:`reference_motion` (a reference's
motion over the trial while the others stay still); :func:`skull_motion` reports the
references moving together (the head moving relative to the C-arms).  :func:`tracking_noise`
is the references' tracking noise over the trial, the scale that FRE and the implanted-marker
check are judged against; :func:`point_configuration` tells a usable reference configuration
from a degenerate one (coincident, collinear) and measures how close to collinear it is.

Shapes: points are ``(n, 3)`` arrays in mm; rows with any NaN are the caller's to drop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..distributions import chi2_sf, f_sf

__all__ = ["Similarity", "AxisScaledSimilarity", "ShearedSimilarity", "fit_similarity", "fit_axis_scaled",
           "fit_sheared", "axis_scale_lever", "shear_lever", "axis_scale_se", "factor_se",
           "registration_transform", "n_params", "residual_vectors", "fre", "estimate_fle", "tre_fitzpatrick",
           "tre_linearized", "tre_perturbation", "leave_one_out", "reference_motion", "tracking_noise",
           "rigid_tracking_noise", "skull_tracking_noise", "reference_motions", "skull_motion",
           "rotation_angle_deg", "point_configuration"]

#: Relative size of the second singular value of the centred points below which they are
#: taken as collinear (a rotation about their line is then undetermined).
_COLLINEAR_RTOL = 1e-9


@dataclass(frozen=True)
class Similarity:
    """``y = scale * R @ x + t_mm``; ``R`` (3, 3) a rotation, ``t_mm`` (3,), ``scale`` > 0.

    >>> T = Similarity(np.eye(3), np.array([1.0, 2.0, 3.0]), 2.0)
    >>> T.apply([[1.0, 0.0, 0.0]]).tolist()
    [[3.0, 2.0, 3.0]]
    >>> np.allclose(T.inverse().apply(T.apply([[0.3, -1.0, 2.0]])), [[0.3, -1.0, 2.0]])
    True
    """

    R: np.ndarray
    t_mm: np.ndarray
    scale: float = 1.0

    def apply(self, x) -> np.ndarray:
        """Map points ``x`` (n, 3) or (3,) from the X-ray to the CT frame."""
        x = np.asarray(x, dtype=float)
        return self.scale * x @ self.R.T + self.t_mm

    def apply_vector(self, v) -> np.ndarray:
        """Map displacement vectors (no translation): ``scale * R @ v``."""
        return self.scale * np.asarray(v, dtype=float) @ self.R.T

    def inverse(self) -> "Similarity":
        Rt = self.R.T
        return Similarity(Rt, -(Rt @ self.t_mm) / self.scale, 1.0 / self.scale)

    def matrix(self) -> np.ndarray:
        """The 4 x 4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t_mm
        return m

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t_mm": self.t_mm.tolist(), "scale": float(self.scale)}


#: The CT file's axes by index (an axial CT's slice axis is z, the third).
CT_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class _MappedSimilarity:
    r"""A similarity followed by a linear map :math:`L` of the CT file's frame about ``centre_mm``:
    :math:`\mathbf y = \mathbf c + L(sR\mathbf x + \mathbf t - \mathbf c)`, with one parameter of
    its own (``factor``) along CT axis ``axis``.  Subclasses give ``_linear()`` (:math:`L`),
    ``_dparam(x)`` (the derivative of the mapped points by that parameter), ``_dfactor``
    (d factor / d parameter) and ``refit``."""

    R: np.ndarray
    t_mm: np.ndarray
    scale: float
    axis: int
    factor: float
    centre_mm: np.ndarray

    @property
    def similarity(self) -> Similarity:
        """The map into a correct CT, coinciding with the file's at ``centre_mm``."""
        return Similarity(self.R, self.t_mm, self.scale)

    def apply(self, x) -> np.ndarray:
        """Map points ``x`` (n, 3) or (3,) from the X-ray to the CT file's frame."""
        return self.centre_mm + (self.similarity.apply(x) - self.centre_mm) @ self._linear().T

    def apply_vector(self, v) -> np.ndarray:
        """Map displacement vectors (no translation): ``L scale R v``."""
        return self.similarity.apply_vector(v) @ self._linear().T

    def matrix(self) -> np.ndarray:
        """The 4 x 4 homogeneous (affine) matrix: the whole map into the CT file's frame."""
        L = self._linear()
        m = np.eye(4)
        m[:3, :3] = L @ (self.scale * self.R)
        m[:3, 3] = L @ self.t_mm + (np.eye(3) - L) @ self.centre_mm
        return m


@dataclass(frozen=True)
class AxisScaledSimilarity(_MappedSimilarity):
    r"""A similarity followed by a stretch by ``factor`` along CT axis ``axis`` about ``centre_mm``:
    :math:`\mathbf y = \mathbf c + D(sR\mathbf x + \mathbf t - \mathbf c)`, :math:`D = I + (k - 1)\,\mathbf e_a \mathbf e_a^T`.

    The CT file's frame where its lengths along one axis are ``factor`` times the true ones (a
    slice spacing off); ``similarity`` (``R``, ``t_mm``, ``scale``) is the map into a correct CT
    that coincides with the file's at ``centre_mm`` (the references' CT centroid), so it is off by
    :math:`(k - 1)` times a point's distance from ``centre_mm`` along the axis.  Its parameter
    is :math:`\ln k`.

    >>> T = AxisScaledSimilarity(np.eye(3), np.zeros(3), 1.0, 2, 1.1, np.array([0.0, 0.0, 10.0]))
    >>> T.apply([[1.0, 2.0, 20.0]]).tolist()
    [[1.0, 2.0, 21.0]]
    >>> bool(np.allclose(T.matrix()[:3, :3] @ [1.0, 2.0, 20.0] + T.matrix()[:3, 3], [1.0, 2.0, 21.0]))
    True
    """

    def _d(self) -> np.ndarray:
        d = np.ones(3)
        d[self.axis] = self.factor
        return d

    def _linear(self) -> np.ndarray:
        return np.diag(self._d())

    def _dparam(self, x) -> np.ndarray:
        """d T(x) / d ln k: ``e (e . (T(x) - c))``."""
        out = np.zeros((len(x), 3))
        out[:, self.axis] = (self.apply(x) - self.centre_mm)[:, self.axis]
        return out

    @property
    def _dfactor(self) -> float:
        return float(self.factor)

    def refit(self, x, y, *, scale: bool) -> "AxisScaledSimilarity":
        """:func:`fit_axis_scaled` of ``x``, ``y`` along the same axis, about the same centre."""
        return fit_axis_scaled(x, y, self.axis, scale=scale, centre=self.centre_mm)

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t_mm": self.t_mm.tolist(), "scale": float(self.scale),
                "axis": CT_AXES[self.axis], "factor": float(self.factor), "centre_mm": self.centre_mm.tolist()}


@dataclass(frozen=True)
class ShearedSimilarity(_MappedSimilarity):
    r"""A similarity followed by a shear of CT axis ``axis`` by CT axis ``by`` (the slice axis, z)
    about ``centre_mm``: :math:`\mathbf y = \mathbf c + H(sR\mathbf x + \mathbf t - \mathbf c)`,
    :math:`H = I + k\,\mathbf e_a \mathbf e_b^T`, ``factor`` :math:`= k`.

    The CT file's frame of a CT acquired with the gantry tilted by :math:`\arctan k` and read
    without the tilt (DICOM's GantryDetectorTilt ignored): each slice keeps its in-plane
    coordinates, so a point's coordinate along ``axis`` (y for a tilt about the patient's
    left-right axis) is off by :math:`k` times its distance from ``centre_mm`` along ``by``.
    ``similarity`` is the map into the correct CT that coincides with the file's at the centre
    (the references' CT centroid); the parameter is :math:`k` itself (a tilt either way).

    >>> T = ShearedSimilarity(np.eye(3), np.zeros(3), 1.0, 1, 0.2, np.array([0.0, 0.0, 10.0]))
    >>> T.apply([[1.0, 2.0, 20.0]]).tolist()
    [[1.0, 4.0, 20.0]]
    >>> round(T.tilt_deg, 4)
    11.3099
    >>> bool(np.allclose(T.matrix()[:3, :3] @ [1.0, 2.0, 20.0] + T.matrix()[:3, 3], [1.0, 4.0, 20.0]))
    True
    """

    by: int = 2

    @property
    def tilt_deg(self) -> float:
        """The gantry tilt the shear stands for, :math:`\\arctan k` in degrees."""
        return float(np.degrees(np.arctan(self.factor)))

    def _linear(self) -> np.ndarray:
        H = np.eye(3)
        H[self.axis, self.by] = self.factor
        return H

    def _dparam(self, x) -> np.ndarray:
        """d T(x) / d k: ``e_a ((sRx + t - c) . e_b)``."""
        out = np.zeros((len(x), 3))
        out[:, self.axis] = (self.similarity.apply(x) - self.centre_mm)[:, self.by]
        return out

    _dfactor = 1.0

    def refit(self, x, y, *, scale: bool) -> "ShearedSimilarity":
        """:func:`fit_sheared` of ``x``, ``y``: the same axes, about the same centre."""
        return fit_sheared(x, y, self.axis, by=self.by, scale=scale, centre=self.centre_mm)

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t_mm": self.t_mm.tolist(), "scale": float(self.scale),
                "axis": CT_AXES[self.axis], "by": CT_AXES[self.by], "factor": float(self.factor),
                "centre_mm": self.centre_mm.tolist()}


def registration_transform(reg: dict):
    """The X-ray -> CT file transform a ``registration.json`` dict describes: a
    :class:`Similarity` from ``R``, ``t_mm``, ``scale``; with ``ct_axis_scale`` an
    :class:`AxisScaledSimilarity`, with ``ct_gantry_shear`` a :class:`ShearedSimilarity` (``R``,
    ``t_mm`` and ``scale`` alone leave the stretch or the shear out).  ValueError names the key
    that is wrong."""
    try:
        R = np.asarray(reg["R"], dtype=float)
        t = np.asarray(reg["t_mm"], dtype=float)
        scale = float(reg.get("scale", 1.0))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"needs R (3 x 3), t_mm (3) and scale: {e}") from None
    if R.shape != (3, 3) or t.shape != (3,) or not np.all(np.isfinite(R)) or not np.all(np.isfinite(t)):
        raise ValueError("R must be 3 x 3 and t_mm 3 finite numbers")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0 or not scale > 0:
        raise ValueError("R is not a rotation or scale is not positive")
    kinds = [k for k in ("ct_axis_scale", "ct_gantry_shear") if reg.get(k) is not None]
    if len(kinds) > 1:
        raise ValueError("ct_axis_scale and ct_gantry_shear both set: a registration has one of them at most")
    if not kinds:
        return Similarity(R, t, scale)
    key, st = kinds[0], reg[kinds[0]]
    try:
        axis = CT_AXES.index(st["axis"]) if "axis_index" not in st else int(st["axis_index"])
        by = CT_AXES.index(st.get("by", "z"))
        factor = float(st["factor"])
        centre = np.asarray(st["centre_mm"], dtype=float)
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"{key} needs axis, factor and centre_mm: {e}") from None
    shear = key == "ct_gantry_shear"
    if not (0 <= axis < 3 and np.isfinite(factor) and (shear or factor > 0) and centre.shape == (3,)
            and np.all(np.isfinite(centre)) and (not shear or by != axis)):
        raise ValueError(f"{key}: axis must be x, y or z" + (" (by another)" if shear else "") + ", factor "
                         + ("finite" if shear else "positive") + " and centre_mm 3 finite numbers")
    if shear:
        return ShearedSimilarity(R, t, scale, axis, factor, centre, by)
    return AxisScaledSimilarity(R, t, scale, axis, factor, centre)


def n_params(scale: bool, axis_scale: bool = False) -> int:
    """Parameters of the transform: 6 rigid, 7 with a uniform scale; one more with a scale along a
    CT axis or a shear of one (``axis_scale``: either)."""
    return 6 + int(scale) + int(axis_scale)


def _as_points(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or infinite coordinates")
    return a


def fit_similarity(x, y, *, scale: bool = False, weights=None) -> Similarity:
    """Least-squares rigid (or, with ``scale``, similarity) transform with ``y ~ s R x + t``.

    Parameters
    ----------
    x, y : array_like, shape (n, 3)
        Corresponding points (X-ray and CT frame), n >= 3, not collinear.
    scale : bool
        Fit a uniform scale (Umeyama) as well.
    weights : array_like, shape (n,), optional
        Non-negative weights (default: equal).

    Raises
    ------
    ValueError
        Fewer than three points, mismatched shapes, or collinear points.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> x = rng.normal(size=(5, 3))
    >>> R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    >>> T = fit_similarity(x, 1.5 * x @ R.T + [1.0, 2.0, 3.0], scale=True)
    >>> bool(np.allclose(T.R, R)), round(T.scale, 12)
    (True, 1.5)
    """
    x, y = _point_pairs(x, y)
    n = len(x)
    if n < 3:
        raise ValueError(f"a 3-D transform needs at least 3 points, got {n}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (n,) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be n non-negative numbers, not all zero")
    w = w / w.sum()
    xm, ym = w @ x, w @ y
    xc, yc = x - xm, y - ym
    sv = np.linalg.svd(xc * np.sqrt(w)[:, None], compute_uv=False)
    if sv[0] == 0.0 or sv[1] <= _COLLINEAR_RTOL * sv[0]:
        raise ValueError("the points are collinear (or coincide): a rotation about their line is undetermined")
    rot, _ = Rotation.align_vectors(yc, xc, weights=w)
    R = rot.as_matrix()
    s = 1.0
    if scale:
        s = float(np.sum(w[:, None] * yc * (xc @ R.T)) / np.sum(w[:, None] * xc * xc))
        if not s > 0:
            raise ValueError(f"the fitted scale is not positive ({s:g}): the points do not correspond")
    return Similarity(R, ym - s * R @ xm, s)


def _point_pairs(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Corresponding point sets ``x``, ``y`` as (n, 3) float arrays of one shape."""
    x = _as_points(x, "x")
    y = _as_points(y, "y")
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in shape: {x.shape} vs {y.shape}")
    return x, y


def fit_axis_scaled(x, y, axis: int, *, scale: bool = False, centre=None) -> AxisScaledSimilarity:
    r"""Least-squares :class:`AxisScaledSimilarity` with ``y ~ c + D(sRx + t - c)``, the stretch
    along CT axis ``axis`` (0, 1, 2: x, y, z of the CT file) about ``centre`` (default: the
    centroid of ``y``).

    Gauss-Newton (scipy ``least_squares``, Levenberg-Marquardt) in a small rotation after the
    similarity fit's, the translation, :math:`\ln s` (``scale``) and :math:`\ln k`, from the
    similarity fit and :math:`k = 1` (:func:`_fit_mapped`).  Needs :math:`3n \ge` the
    parameters (7, 8 with ``scale``).

    >>> rng = np.random.default_rng(1)
    >>> x = rng.normal(size=(5, 3)) * 10
    >>> R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    >>> T = fit_axis_scaled(x, (x @ R.T + [1.0, 2.0, 3.0]) * [1.0, 1.0, 1.07], 2)
    >>> bool(np.allclose(T.R, R)), round(T.factor, 10)
    (True, 1.07)
    """
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2, not {axis!r}")
    T = _fit_mapped(x, y, lambda R, t, s, v, c: AxisScaledSimilarity(R, t, s, axis, float(np.exp(v)), c),
                    scale=scale, centre=centre, what="a scale along a CT axis")
    if not (np.isfinite(T.factor) and T.factor > 0):
        raise ValueError(f"the fitted scale along CT axis {CT_AXES[axis]} is not positive ({T.factor:g})")
    return T


def fit_sheared(x, y, axis: int, *, by: int = 2, scale: bool = False, centre=None) -> ShearedSimilarity:
    r"""Least-squares :class:`ShearedSimilarity` with ``y ~ c + H(sRx + t - c)``, CT axis ``axis``
    sheared by CT axis ``by`` (default the slice axis, z) about ``centre`` (default: the centroid
    of ``y``): a CT acquired with the gantry tilted and read without the tilt.

    Jointly in the rotation, translation, :math:`\ln s` (``scale``) and :math:`k`, from the
    similarity fit and :math:`k = 0` (:func:`_fit_mapped`, Levenberg-Marquardt).  Needs
    :math:`3n \ge` the parameters (7, 8 with ``scale``).

    >>> rng = np.random.default_rng(1)
    >>> x = rng.normal(size=(5, 3)) * 10
    >>> R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    >>> y = x @ R.T + [1.0, 2.0, 3.0]
    >>> y[:, 1] += 0.3 * (y[:, 2] - y[:, 2].mean())
    >>> T = fit_sheared(x, y, 1)
    >>> bool(np.allclose(T.R, R)), round(T.factor, 10)
    (True, 0.3)
    """
    if axis not in (0, 1, 2) or by not in (0, 1, 2) or axis == by:
        raise ValueError(f"axis and by must be two different CT axes (0, 1, 2), not {axis!r} and {by!r}")
    T = _fit_mapped(x, y, lambda R, t, s, v, c: ShearedSimilarity(R, t, s, axis, float(v), c, by),
                    scale=scale, centre=centre, what="a shear of a CT axis")
    if not np.isfinite(T.factor):
        raise ValueError(f"the fitted shear of CT axis {CT_AXES[axis]} by {CT_AXES[by]} is not finite")
    return T


def _fit_mapped(x, y, make, *, scale: bool, centre, what: str):
    """Least squares of a :class:`_MappedSimilarity` ``make(R, t, s, v, c)`` (``v`` its own
    parameter, 0 for the identity map) to ``x``, ``y``: a rotation vector after the similarity
    fit's rotation, the translation, :math:`\\ln s` (``scale``) and ``v``, from the similarity
    fit, with the analytic Jacobian (:func:`_jacobian`, its rotation columns through the
    rotation vector's left Jacobian): by finite differences the loop's fits of a sheared CT had
    taken 2.3 of the 3.7 s of a registration (now 0.7 s in all)."""
    from scipy.optimize import least_squares

    x, y = _point_pairs(x, y)
    p = n_params(scale, True)
    if 3 * len(x) < p:
        raise ValueError(f"{what} needs at least {-(-p // 3)} points, got {len(x)}")
    c = y.mean(axis=0) if centre is None else np.asarray(centre, dtype=float)
    T0 = fit_similarity(x, y, scale=scale)
    R0 = Rotation.from_matrix(T0.R)

    def unpack(v):
        s = float(T0.scale * np.exp(v[6])) if scale else 1.0
        return make((Rotation.from_rotvec(v[:3]) * R0).as_matrix(), np.asarray(v[3:6], float), s, v[-1], c)

    def resid(v):
        return (unpack(v).apply(x) - y).ravel()

    def jac(v):
        J = _jacobian(unpack(v), x, scale)
        J[:, :, :3] = J[:, :, :3] @ _so3_left_jacobian(v[:3])
        return J.reshape(-1, p)

    v0 = np.concatenate([np.zeros(3), T0.t_mm, [0.0] * int(scale), [0.0]])
    sol = least_squares(resid, v0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return unpack(sol.x)


def _so3_left_jacobian(w) -> np.ndarray:
    r"""The left Jacobian of SO(3) at rotation vector ``w``: :math:`d\,\exp([\mathbf w]_	imes) =
    [J_l(\mathbf w)\, d\mathbf w]_	imes \exp([\mathbf w]_	imes)`."""
    w = np.asarray(w, dtype=float)
    th = float(np.linalg.norm(w))
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-6:
        return np.eye(3) + W / 2 + W @ W / 6
    return np.eye(3) + (1 - np.cos(th)) / th ** 2 * W + (th - np.sin(th)) / th ** 3 * (W @ W)


def axis_scale_lever(T, x, axis: int, *, scale: bool = False) -> float:
    r"""How well points determine a scale along CT axis ``axis``: the lever (mm) of :math:`\ln k`.

    With :math:`J` the Jacobian of the mapped points ``T(x)`` (n, 3) with respect to the
    transform's parameters and :math:`\ln k` (at :math:`k = 1`), ``lever`` :math:`=
    1/\sqrt{[(J^TJ)^{-1}]_{kk}}`: the root sum of squares of the points' offsets along the axis
    (from their centroid) that no rotation, translation (or uniform scale) can mimic.  A least-squares :math:`k` from those points has standard error
    :math:`\sigma/\mathrm{lever}` for a per-axis localisation error :math:`\sigma`; 0 where the
    points lie in a plane across the axis (a stretch along it is then a translation).

    >>> sq = np.array([[10.0, 10, 0], [-10, 10, 0], [-10, -10, 0], [10, -10, 0]])
    >>> axis_scale_lever(Similarity(np.eye(3), np.zeros(3)), sq, 2)
    0.0
    >>> round(axis_scale_lever(Similarity(np.eye(3), np.zeros(3)), sq, 0), 6)
    20.0
    """
    x = _as_points(x, "x")
    return _lever(AxisScaledSimilarity(T.R, T.t_mm, float(T.scale), axis, 1.0, T.apply(x).mean(axis=0)), x, scale)


def shear_lever(T, x, axis: int, *, by: int = 2, scale: bool = False) -> float:
    r"""How well points determine a shear of CT axis ``axis`` by ``by``: the lever (mm) of
    :math:`k`, as :func:`axis_scale_lever` (standard error of :math:`k` :math:`\sigma/\mathrm{lever}`);
    0 where the points lie in a plane across ``by`` (the shear is then a translation).

    >>> sq = np.array([[10.0, 10, 0], [-10, 10, 0], [-10, -10, 0], [10, -10, 0]])
    >>> shear_lever(Similarity(np.eye(3), np.zeros(3)), sq, 1)
    0.0
    """
    x = _as_points(x, "x")
    return _lever(ShearedSimilarity(T.R, T.t_mm, float(T.scale), axis, 0.0, T.apply(x).mean(axis=0), by), x, scale)


def _lever(Tm, x: np.ndarray, scale: bool) -> float:
    """:math:`1/\\sqrt{[(J^TJ)^{-1}]_{vv}}` of a :class:`_MappedSimilarity` ``Tm`` at its identity
    map, ``v`` its own parameter (0 where the points do not determine it)."""
    J = _jacobian(Tm, x, scale).reshape(-1, n_params(scale, True))
    try:
        u = np.linalg.svd(J, compute_uv=False)
        if u[-1] <= 1e-9 * u[0]:
            return 0.0
        return float(1.0 / np.sqrt(np.linalg.inv(J.T @ J)[-1, -1]))
    except np.linalg.LinAlgError:
        return 0.0


def factor_se(T, x_fiducials, fle_mm: float, *, scale: bool) -> float:
    r"""Standard error of ``T.factor`` (first order) of an :class:`AxisScaledSimilarity` or a
    :class:`ShearedSimilarity` from fiducials ``x_fiducials`` (n, 3, X-ray frame) with isotropic
    localisation errors of RMS ``fle_mm``: d factor / d parameter (``factor`` for a stretch's
    :math:`\ln k`, 1 for a shear's :math:`k`) times the square root of the parameter's entry of
    :math:`(\mathrm{FLE}^2/3)(J^TJ)^{-1}`."""
    J = _jacobian(T, _as_points(x_fiducials, "x_fiducials"), scale)
    J = J.reshape(-1, J.shape[-1])
    try:
        var = float(np.linalg.inv(J.T @ J)[-1, -1])
    except np.linalg.LinAlgError:
        return float("inf")
    return float(T._dfactor * fle_mm / np.sqrt(3.0) * np.sqrt(max(var, 0.0)))


#: The standard error of an :class:`AxisScaledSimilarity`'s factor (:func:`factor_se`).
axis_scale_se = factor_se


#: RMS distance from their centroid (mm) below which points are taken to coincide (far below
#: any localisation precision: a file that repeats one point).
_COINCIDE_MM = 1e-6


def point_configuration(points) -> dict:
    r"""How well a point set determines a rotation: its spread and how close it is to a line.

    With :math:`s_1 \ge s_2 \ge s_3` the singular values of the centred points (n, 3),
    ``spread_mm`` :math:`= s_1/\sqrt n` (the RMS distance from the centroid along the points'
    main direction; the RMS distance itself is :math:`\sqrt{(s_1^2 + s_2^2 + s_3^2)/n}`), ``lateral_mm``
    :math:`= s_2/\sqrt n` (RMS distance from the best-fitting line) and ``line_ratio``
    :math:`= s_2/s_1`.  A rotation about the points' line is determined by the lateral spread
    only: its error is about FLE / ``lateral_mm`` (rad), so a small ``line_ratio`` (nearly
    collinear) leaves the transform ill-conditioned.  ``degenerate`` is ``"coincide"`` (spread
    below 1e-6 mm), ``"collinear"`` (``line_ratio`` at or below the tolerance of
    :func:`fit_similarity`), or None.

    >>> point_configuration([[0, 0, 0], [1, 0, 0], [2, 0, 0]])["degenerate"]
    'collinear'
    >>> c = point_configuration([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]])
    >>> c["degenerate"], round(c["line_ratio"], 6)
    (None, 1.0)
    """
    p = _as_points(points, "points")
    n = len(p)
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False) if n else np.zeros(3)
    sv = np.concatenate([sv, np.zeros(3 - len(sv))])
    spread = float(sv[0] / np.sqrt(max(n, 1)))
    ratio = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
    degenerate = ("coincide" if spread < _COINCIDE_MM
                  else "collinear" if n < 3 or sv[1] <= _COLLINEAR_RTOL * sv[0] else None)
    return {"n": int(n), "spread_mm": spread, "lateral_mm": float(sv[1] / np.sqrt(max(n, 1))),
            "line_ratio": ratio, "degenerate": degenerate}


def residual_vectors(T: Similarity, x, y) -> np.ndarray:
    """``y - T(x)``, shape (n, 3)."""
    return np.asarray(y, dtype=float) - T.apply(x)


def fre(T: Similarity, x, y) -> np.ndarray:
    """Fiducial registration error per point, ``|y - T(x)|`` (n,) in mm."""
    return np.linalg.norm(residual_vectors(T, x, y), axis=1)


def estimate_fle(residuals, *, scale: bool, axis_scale: bool = False) -> tuple[float, int]:
    """RMS 3-D fiducial localisation error from a fit's residual vectors (n, 3).

    :math:`\\widehat{\\mathrm{FLE}}^2 = 3\\,\\mathrm{RSS}/(3n - p)`, unbiased for isotropic
    Gaussian errors to first order; returns ``(fle_mm, dof)``.  With no degrees of freedom
    left (three points and a scale) the estimate is NaN.  ``axis_scale``: the fit has a scale
    along a CT axis, or a shear of one, too (one parameter more).

    >>> r = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0, 0.1, 0], [0, -0.1, 0]])
    >>> fle, dof = estimate_fle(r, scale=False); dof, round(fle, 6)
    (6, 0.141421)
    """
    r = np.asarray(residuals, dtype=float)
    dof = 3 * len(r) - n_params(scale, axis_scale)
    if dof <= 0:
        return float("nan"), dof
    return float(np.sqrt(3.0 * np.sum(r * r) / dof)), dof


def tre_fitzpatrick(fiducials, targets, fle_mm: float) -> np.ndarray:
    """Expected RMS target registration error (mm) at ``targets`` (m, 3), rigid registration.

    Fitzpatrick, West & Maurer (1998), eq. 46:
    :math:`\\mathrm{TRE}^2(\\mathbf r) = \\frac{\\mathrm{FLE}^2}{N}(1 + \\frac13\\sum_k d_k^2/f_k^2)`,
    principal axes of the fiducial configuration ``fiducials`` (N, 3) about its centroid.
    ``fiducials`` and ``targets`` in one frame (the CT frame for errors in CT mm).

    >>> f = np.array([[10.0, 0, 0], [-10, 0, 0], [0, 10, 0], [0, -10, 0]])
    >>> float(tre_fitzpatrick(f, [[0.0, 0.0, 0.0]], 0.2)[0]) == 0.2 / 2
    True
    """
    f = _as_points(fiducials, "fiducials")
    r = np.atleast_2d(np.asarray(targets, dtype=float))
    c = f.mean(axis=0)
    F = f - c
    _, axes = np.linalg.eigh(F.T @ F)
    n = len(f)
    total = np.zeros(len(r))
    rc = r - c
    for k in range(3):
        e = axes[:, k]
        fk2 = np.mean(np.sum(F * F, axis=1) - (F @ e) ** 2)
        dk2 = np.sum(rc * rc, axis=1) - (rc @ e) ** 2
        total += dk2 / fk2
    return np.sqrt(fle_mm ** 2 / n * (1.0 + total / 3.0))


def _jacobian(T, x: np.ndarray, scale: bool) -> np.ndarray:
    """d T(x) / d(params) at X-ray points ``x`` (m, 3): rows (m, 3, p).

    Parameters: a small rotation ``w`` applied after R (``d(sRx) = w x q = -[q]x w`` with
    ``q = s R x``), the translation, ``d ln s`` (``d(sRx) = q d ln s``, with ``scale``) and, for an
    :class:`AxisScaledSimilarity`, ``d ln k`` (``e (e . (T(x) - c))``), for a
    :class:`ShearedSimilarity` ``d k`` (``e_a ((sRx + t - c) . e_b)``); their linear map (``D``,
    ``H``) multiplies the similarity's columns (the same span for the translation)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    q = T.scale * x @ T.R.T
    mapped = isinstance(T, _MappedSimilarity)
    m = len(q)
    J = np.zeros((m, 3, n_params(scale, mapped)))
    qx, qy, qz = q[:, 0], q[:, 1], q[:, 2]
    zero = np.zeros(m)
    J[:, :, :3] = -np.stack([np.stack([zero, -qz, qy], -1),
                             np.stack([qz, zero, -qx], -1),
                             np.stack([-qy, qx, zero], -1)], axis=1)
    J[:, :, 3:6] = np.eye(3)
    if scale:
        J[:, :, 6] = q
    if mapped:
        J[:, :, :-1] = np.einsum("ij,mjp->mip", T._linear(), J[:, :, :-1])
        J[:, :, -1] = T._dparam(x)
    return J


def tre_linearized(T: Similarity, x_fiducials, x_targets, fle_mm: float, *, scale: bool) -> np.ndarray:
    """Expected RMS TRE (mm, CT frame) at ``x_targets`` (m, 3, X-ray frame), first order.

    The CT fiducials carry isotropic errors of RMS ``fle_mm`` (per-axis variance
    ``fle_mm**2 / 3``); the least-squares parameters then have covariance
    :math:`\\sigma^2 (J^T J)^{-1}` and the error at a target :math:`\\mathbf r` is
    :math:`\\mathrm{TRE}^2 = \\operatorname{tr}(J_r \\operatorname{Cov} J_r^T)`.  For a rigid
    fit this equals :func:`tre_fitzpatrick`.  An :class:`AxisScaledSimilarity` ``T`` carries its
    scale along the CT axis as one parameter more (its uncertainty is in the TRE), a
    :class:`ShearedSimilarity` its shear.
    """
    xf = _as_points(x_fiducials, "x_fiducials")
    xt = np.atleast_2d(np.asarray(x_targets, dtype=float))
    Jf = _jacobian(T, xf, scale)
    Jf = Jf.reshape(-1, Jf.shape[-1])
    cov = (fle_mm ** 2 / 3.0) * np.linalg.inv(Jf.T @ Jf)
    Jt = _jacobian(T, xt, scale)
    return np.sqrt(np.einsum("mip,pq,miq->m", Jt, cov, Jt))


def tre_perturbation(T: Similarity, x_fiducials, x_targets, fle_mm: float, *, scale: bool,
                     n_draws: int = 2000, seed: int = 0, fle_dof: int | None = None) -> dict:
    r"""TRE at ``x_targets`` by re-fitting perturbed fiducials (parametric bootstrap).

    Each draw moves the fitted CT fiducials ``T(x_i)`` by isotropic Gaussian errors of RMS
    ``fle_mm``, re-fits, and measures ``|T*(r) - T(r)|`` at every target.  ``fle_dof``: the
    FLE is itself estimated on that many degrees of freedom (:func:`estimate_fle`), and each
    draw takes its own :math:`\mathrm{FLE}^2 = \widehat{\mathrm{FLE}}^2\,\nu/\chi^2_\nu`
    (the predictive distribution: with four references, 6 degrees of freedom, the true TRE had
    exceeded the plug-in p95 in 8-20 % of trials instead of 5 %).  Returns
    ``{"rms_mm": (m,), "p95_mm": (m,), "n_draws": n, "seed": seed}``; the RMS has a relative
    Monte-Carlo standard error of about ``1 / sqrt(6 n)`` (about 1 % for n = 2000; more with
    ``fle_dof``).  An :class:`AxisScaledSimilarity` ``T`` is refitted with its scale along the CT
    axis (:func:`fit_axis_scaled`, about the same centre), a :class:`ShearedSimilarity` with its
    shear (:func:`fit_sheared`).
    """
    xf = _as_points(x_fiducials, "x_fiducials")
    xt = np.atleast_2d(np.asarray(x_targets, dtype=float))
    rng = np.random.default_rng(seed)
    y0 = T.apply(xf)
    t0 = T.apply(xt)
    sigma = fle_mm / np.sqrt(3.0)
    err = np.empty((n_draws, len(xt)))
    for k in range(n_draws):
        s_k = sigma if fle_dof is None else sigma * math.sqrt(fle_dof / rng.chisquare(fle_dof))
        yk = y0 + rng.normal(0.0, s_k, y0.shape)
        Tk = T.refit(xf, yk, scale=scale) if isinstance(T, _MappedSimilarity) else fit_similarity(xf, yk, scale=scale)
        err[k] = np.linalg.norm(Tk.apply(xt) - t0, axis=1)
    return {"rms_mm": np.sqrt(np.mean(err ** 2, axis=0)), "p95_mm": np.quantile(err, 0.95, axis=0),
            "n_draws": int(n_draws), "seed": int(seed)}


def rounding_rss(n_values: int, *coords) -> float:
    """The residual sum of squares of ``n_values`` residuals that floating-point rounding alone
    gives for points of the magnitude of ``coords`` (a thousand units in the last place of
    the largest coordinate each): sums below it hold no evidence, their ratios only rounding."""
    big = max((float(np.max(np.abs(c))) for c in coords if np.size(c)), default=1.0)
    return float(n_values) * (1e3 * np.finfo(float).eps * max(big, 1.0)) ** 2


def leave_one_out(x, y, *, scale: bool, like=None) -> list[dict]:
    r"""Each point predicted by a fit of the others: the test for one reference that moved.

    For point *k*: the fit without it has residual sum of squares :math:`\mathrm{RSS}_{-k}`;
    :math:`F_k = \frac{(\mathrm{RSS} - \mathrm{RSS}_{-k})/3}{\mathrm{RSS}_{-k}/(3(N-1) - p)}`
    is F-distributed with (3, 3(N-1) - p) degrees of freedom when nothing moved (exactly so
    for a linear model; to first order here).  Returned per point: ``error_mm`` (the held-out
    prediction error :math:`|\mathbf y_k - T_{-k}(\mathbf x_k)|`), ``rss_without_mm2``,
    ``f``, ``p`` (one-sided), ``p_bonferroni`` (times N), ``delta_bic`` (of the model in
    which point *k* is displaced by three free parameters, Gaussian BIC on the 3N residuals).

    Needs N >= 4 (so that 3(N-1) - p > 0, rigid or with scale).  ``like``: an
    :class:`AxisScaledSimilarity` or :class:`ShearedSimilarity` whose CT distortion every fit
    takes too (``like.refit``; one parameter more): the CT file's frame stretched or sheared, where
    a plain fit's misfit would be the distortion's (a gantry tilt of 15 degrees had given every
    reference a held-out error of 2.0 mm, at 0.005 mm of noise).
    """
    x = _as_points(x, "x")
    y = _as_points(y, "y")
    n = len(x)
    p = n_params(scale, like is not None)
    dof2 = 3 * (n - 1) - p
    if dof2 <= 0:
        raise ValueError(f"leave-one-out needs at least 4 points, got {n}")

    def fit(a, b):
        return fit_similarity(a, b, scale=scale) if like is None else like.refit(a, b, scale=scale)
    # sums of squares at the level of rounding are exact fits (a moved point cannot show there)
    floor = rounding_rss(3 * n, x, y)
    rss = max(float(np.sum(residual_vectors(fit(x, y), x, y) ** 2)), floor)
    out = []
    for k in range(n):
        keep = np.arange(n) != k
        try:
            Tk = fit(x[keep], y[keep])
        except ValueError:
            out.append({"error_mm": float("nan"), "rss_without_mm2": float("nan"), "f": float("nan"),
                        "p": float("nan"), "p_bonferroni": float("nan"), "delta_bic": float("nan"),
                        "note": "the other points are collinear"})
            continue
        rss_k = max(float(np.sum(residual_vectors(Tk, x[keep], y[keep]) ** 2)), floor)
        err = float(np.linalg.norm(y[k] - Tk.apply(x[k])))
        tiny = np.finfo(float).tiny
        f = ((rss - rss_k) / 3.0) / max(rss_k / dof2, tiny)
        pv = f_sf(f, 3, dof2)
        dbic = 3 * n * np.log(max(rss, tiny) / max(rss_k, tiny)) - 3 * np.log(3 * n)
        out.append({"error_mm": err, "rss_without_mm2": rss_k, "f": float(f), "p": pv,
                    "p_bonferroni": min(1.0, pv * n), "delta_bic": float(dbic)})
    return out


def _hat_basis(t: np.ndarray, n_knots: int) -> np.ndarray:
    """Piecewise-linear (hat) functions on ``n_knots`` evenly spaced knots over ``t``; rows sum to 1."""
    knots = np.linspace(t.min(), t.max(), n_knots)
    B = np.zeros((len(t), n_knots))
    for j in range(n_knots):
        e = np.zeros(n_knots)
        e[j] = 1.0
        B[:, j] = np.interp(t, knots, e)
    return B


def _common_scatter(O: np.ndarray) -> tuple[np.ndarray, float, int]:
    """Points (F, M, 3) found in every frame: their common translation (F, 3) and the residual
    sum of squares and degrees of freedom, :math:`3(M-1)(F-1)`, of their scatter about their
    mean positions once it is taken out."""
    common = O.mean(axis=1) - O.mean(axis=(0, 1))
    dev = O - O.mean(axis=0) - common[:, None, :]
    return common, float(np.sum(dev ** 2)), 3 * (O.shape[1] - 1) * (O.shape[0] - 1)


def _rigid_scatter(O: np.ndarray, n_iter: int = 3) -> tuple[list, np.ndarray, float, int]:
    """Points (F, M, 3), M >= 3 not on a line, found in every frame: the rigid transform of each
    frame onto their mean shape (generalised Procrustes, ``n_iter`` rounds), the mean shape
    (M, 3), and the residual sum of squares and degrees of freedom, :math:`(3M-6)(F-1)`, of
    their scatter about it once each frame's rigid motion is taken out."""
    mean = O.mean(axis=0)
    for _ in range(n_iter):
        Ts = [fit_similarity(o, mean) for o in O]
        aligned = np.stack([T.apply(o) for T, o in zip(Ts, O)])
        mean = aligned.mean(axis=0)
    return Ts, mean, float(np.sum((aligned - mean) ** 2)), (3 * O.shape[1] - 6) * (O.shape[0] - 1)


def rigid_tracking_noise(tracks) -> dict:
    r"""Per-axis tracking noise :math:`\sigma` (mm) of references fixed to one rigid body that
    may turn as well as slide (the head relative to the C-arms).

    As :func:`tracking_noise`, but each frame's rigid motion (not only its translation) is
    taken out (:math:`\hat\sigma^2 = \mathrm{RSS}/((3M-6)(F-1))`, generalised Procrustes on
    the frames where all M >= 3 are found): a turn of the head does not inflate it.  Returns
    ``{"sigma_mm", "dof", "n_frames", "n_references"}`` (``sigma_mm`` NaN with no degrees of
    freedom or references on a line)."""
    tracks, ok, out = _noise_frames(tracks)
    if out["n_references"] < 3 or ok.sum() < 2:
        return out
    try:
        _, _, rss, dof = _rigid_scatter(tracks[ok])
    except ValueError:          # on a line
        return out
    return _with_sigma(out, rss, dof)


def _noise_frames(tracks):
    """``tracks`` as a float array (F, M, 3), the frames where all are found, and the result
    of the noise estimates before any degree of freedom is counted."""
    tracks = np.asarray(tracks, dtype=float)
    ok = np.all(np.isfinite(tracks), axis=(1, 2))
    return tracks, ok, {"sigma_mm": float("nan"), "dof": 0, "n_frames": int(ok.sum()),
                        "n_references": int(tracks.shape[1])}


def _with_sigma(out: dict, rss: float, dof: int) -> dict:
    if dof > 0:
        out.update(sigma_mm=float(np.sqrt(rss / dof)), dof=int(dof))
    return out


def tracking_noise(tracks) -> dict:
    r"""Per-axis tracking noise :math:`\sigma` (mm) of references that stay fixed to the skull.

    ``tracks`` (F, M, 3), NaN where not found; the frames where all M >= 2 are found are used.
    Their common translation in each frame (the head slipping) is taken out and
    :math:`\hat\sigma^2 = \mathrm{RSS}/(3(M-1)(F-1))` is the scatter left about their mean
    positions, the estimate :func:`reference_motion` uses for its noise.  A reference that moves
    inflates it.  The expected 3-D RMS of a tracking error is :math:`\sqrt3\,\sigma`.
    Returns ``{"sigma_mm", "dof", "n_frames", "n_references"}`` (``sigma_mm`` NaN with no
    degrees of freedom: one frame, or one reference).
    """
    tracks, ok, out = _noise_frames(tracks)
    if out["n_references"] < 2 or ok.sum() < 2:
        return out
    _, rss, dof = _common_scatter(tracks[ok])
    return _with_sigma(out, rss, dof)


#: p of the F test (the others' scatter with their translation taken out against that with
#: their rigid motion taken out) below which the other references turn as well as slide, and
#: :func:`reference_motion` takes their rigid motion out of the candidate.
ROTATION_P = 0.01


def skull_tracking_noise(tracks) -> dict:
    r"""The references' per-axis tracking noise :math:`\sigma` (mm), with their rigid motion
    taken out where the head turned: :func:`rigid_tracking_noise` where the F test of their
    scatter with each frame's translation taken out against that with its rigid motion taken
    out has p below :data:`ROTATION_P` (the test :func:`reference_motion` makes of the others),
    else :func:`tracking_noise`.  A turn of the head had been counted as noise: 2 degrees about
    references 20 mm apart gave 0.164 mm for a true 0.005, and every check judged against it
    (a CT marker 0.8 mm off) was silent.  Returns :func:`tracking_noise`'s dict with ``model``
    (``translation`` or ``rigid``) and ``rotation`` (``f``, ``dof``, ``p``; None where not
    tested: fewer than 3 references, on a line, or no scatter)."""
    tracks, ok, out = _noise_frames(tracks)
    out = {**out, "model": "translation", "rotation": None}
    if out["n_references"] < 2 or ok.sum() < 2:
        return out
    O = tracks[ok]
    _, rss_t, dof_t = _common_scatter(O)
    if out["n_references"] >= 3:
        rigid, out["rotation"] = _rotation_test(O, rss_t, dof_t)
        if out["rotation"] is not None and out["rotation"]["p"] < ROTATION_P:
            out["model"] = "rigid"
            return _with_sigma(out, rigid[2], rigid[3])
    return _with_sigma(out, rss_t, dof_t)


def _rotation_test(O: np.ndarray, rss_t: float, dof_t: int) -> tuple[tuple | None, dict | None]:
    """Points (F >= 2, M >= 3, 3) found in every frame, with the residual sum of squares and
    degrees of freedom of their scatter once each frame's translation is taken out
    (:func:`_common_scatter`): their :func:`_rigid_scatter` and the F test of what taking each
    frame's rotation out as well removes (``f``, ``dof``, ``p``); ``(None, None)`` for points
    on a line (their rotation about it is undetermined), the test None where no scatter is left."""
    try:
        rigid = _rigid_scatter(O)
    except ValueError:
        return None, None
    rss_r, dof_r = rigid[2], rigid[3]
    if not (dof_r > 0 and rss_r > 0):
        return rigid, None
    d1 = dof_t - dof_r
    f = ((rss_t - rss_r) / d1) / (rss_r / dof_r)
    return rigid, {"f": float(f), "dof": [int(d1), int(dof_r)], "p": f_sf(f, d1, dof_r)}


def reference_motion(track, others, *, time=None, max_knots: int = 12, model: str = "auto") -> dict:
    r"""Did a reference move over the trial, while the others stayed still?

    Parameters
    ----------
    track : array_like, shape (F, 3)
        The candidate's X-ray positions in every frame (NaN where not found).
    others : array_like, shape (F, M, 3)
        The other references' positions, M >= 2: their common translation and the tracking noise.
    time : array_like, shape (F,), optional
        Frame times (default: the frame index).

    The registration's declared model has the skull, so every reference, fixed relative to
    the C-arms for the whole trial (one transform serves every frame).  The others' common
    translation in each frame (their mean position's change: the head slipping in its frame)
    is taken out of every track; a reference then stays where it is up to tracking noise of
    per-axis variance :math:`\sigma^2`, estimated from the others' remaining scatter
    (:math:`3(M-1)(F-1)` degrees of freedom, times :math:`1 + 1/M` for the noise of their mean;
    a moving one among them only inflates it, which makes the test more conservative).  The
    alternative is a smooth motion: piecewise-linear in time on K knots (K = F/4, 2..``max_knots``)
    per axis, 3(K - 1) more parameters.  With
    :math:`\chi^2 = (\mathrm{RSS}_{const} - \mathrm{RSS}_{smooth})/\sigma^2`, ``delta_bic``
    :math:`= \chi^2 - 3(K-1)\ln(3F)` (Gaussian BIC, known noise); positive favours motion.  A
    smooth alternative makes the test insensitive to a reference that is merely tracked with
    more noise than the others.  (Aligning the others frame by frame instead would make the
    test blind to which of four references moved: with three others a rigid tilt absorbs one
    of them moving out of their plane.)

    But when the others turn as well as slide (``model="auto"``: the F test of their scatter
    with the translation taken out against that with their rigid motion taken out, at p <
    :data:`ROTATION_P`; ``model="rigid"``: always), a turn of the head makes a reference
    away from the axis look as if it moved (a static corner reference had been left out for
    a moving one, displacements off by 0.3-0.5 mm).  Then each frame's rigid motion of the
    others (generalised Procrustes onto their mean shape) is taken out of the candidate, and
    :math:`\sigma^2` is their remaining scatter (:math:`(3M-6)(F-1)` degrees of freedom)
    times :math:`1 + \mathrm{TRE}^2/(3\sigma^2)` at the candidate (the alignment's error
    there, :func:`tre_fitzpatrick`).  With the others turning, a reference moving out of
    their plane cannot be told from a tilt that moves another (``"model": "rigid"`` results
    of several references flag together: the caller's to judge).

    Returns ``{"n_frames", "sigma_mm", "max_displacement_mm", "rms_displacement_mm",
    "chi2", "dof", "p", "delta_bic", "n_knots", "model", "others_rotation", "others_sigma_mm",
    "others_dof"}`` (``n_frames`` < 3: no test, delta_bic 0); the displacements are those of
    the smooth fit since the first usable frame; ``model`` ``"translation"`` or ``"rigid"``
    (what was taken out), ``others_rotation`` the F test (``{"f", "dof", "p"}``, None with
    fewer than three others), ``others_sigma_mm`` and ``others_dof`` the others' scatter
    with it taken out.
    """
    if model not in ("auto", "translation", "rigid"):
        raise ValueError(f"model must be auto, translation or rigid, not {model!r}")
    track = np.asarray(track, dtype=float)
    others = np.asarray(others, dtype=float)
    nf = len(track)
    t = np.arange(nf, dtype=float) if time is None else np.asarray(time, dtype=float)
    ok = np.all(np.isfinite(track), axis=1) & np.all(np.isfinite(others), axis=(1, 2)) & np.isfinite(t)
    idx = np.flatnonzero(ok)
    m = others.shape[1]
    empty = {"n_frames": int(len(idx)), "sigma_mm": float("nan"), "max_displacement_mm": float("nan"),
             "rms_displacement_mm": float("nan"), "chi2": 0.0, "dof": 0, "p": 1.0, "delta_bic": 0.0,
             "n_knots": 0, "model": "translation", "others_rotation": None, "others_sigma_mm": float("nan"),
             "others_dof": 0}
    tt = t[idx]
    if m < 2 or len(idx) < 3 or np.ptp(tt) <= 0:
        return empty
    O = others[idx]
    common, rss_o, dof_o = _common_scatter(O)
    if dof_o <= 0 or rss_o <= 0:
        return empty
    rotation, rigid = None, None
    if m >= 3 and model != "translation":
        rigid, rotation = _rotation_test(O, rss_o, dof_o)
    if rigid is not None and rotation is not None and (model == "rigid" or rotation["p"] < ROTATION_P):
        Ts, shape, rss_r, dof_r = rigid
        a = np.stack([T.apply(x) for T, x in zip(Ts, track[idx])])
        # the alignment's per-axis error variance at the candidate, in units of sigma^2
        lever = float(tre_fitzpatrick(shape, a.mean(axis=0)[None], math.sqrt(3.0))[0] ** 2 / 3.0)
        s2_o, d_o, used_model = rss_r / dof_r, dof_r, "rigid"
        sigma2 = s2_o * (1.0 + lever)
    else:
        s2_o, d_o, used_model = rss_o / dof_o, dof_o, "translation"
        sigma2 = s2_o * (1.0 + 1.0 / m)                     # a_f carries the noise of the others' mean
        a = track[idx] - common
    rss_const = float(np.sum((a - a.mean(axis=0)) ** 2))
    n_knots = int(np.clip(len(idx) // 4, 2, max_knots))
    B = _hat_basis(tt, n_knots)
    coef, *_ = np.linalg.lstsq(B, a, rcond=None)
    smooth = B @ coef
    rss_smooth = float(np.sum((a - smooth) ** 2))
    chi2 = (rss_const - rss_smooth) / sigma2
    k = 3 * (n_knots - 1)
    disp = np.linalg.norm(smooth - smooth[0], axis=1)     # motion since the first usable frame
    return {"n_frames": int(len(idx)), "sigma_mm": float(np.sqrt(sigma2)),
            "max_displacement_mm": float(disp.max()), "rms_displacement_mm": float(np.sqrt(np.mean(disp ** 2))),
            "chi2": float(chi2), "dof": int(k), "p": chi2_sf(chi2, k),
            "delta_bic": float(chi2 - k * np.log(3 * len(idx))), "n_knots": n_knots, "model": used_model,
            "others_rotation": rotation, "others_sigma_mm": float(np.sqrt(s2_o)), "others_dof": int(d_o)}


def reference_motions(tracks, frame_index: int) -> list[tuple["Similarity", np.ndarray] | None]:
    """Per frame of ``tracks`` (F, N, 3), the rigid transform taking the references found in
    it onto their positions in frame ``frame_index``, and which references (N,) it used; None
    where fewer than three are found in both frames or they lie on a line."""
    tracks = np.asarray(tracks, dtype=float)
    ref = tracks[frame_index]
    out: list = []
    for f in range(len(tracks)):
        ok = np.all(np.isfinite(tracks[f]), axis=1) & np.all(np.isfinite(ref), axis=1)
        T = None
        if ok.sum() >= 3:
            try:
                T = fit_similarity(tracks[f][ok], ref[ok])
            except ValueError:
                pass
        out.append(None if T is None else (T, ok))
    return out


def skull_motion(tracks, frame_index: int, motions: list | None = None) -> dict:
    """Rigid motion of the references as a whole, frame by frame, relative to frame ``frame_index``.

    ``tracks`` (F, N, 3), N >= 3.  In each frame where at least three references are found,
    the rigid transform taking their positions onto those in the registration frame gives a
    translation (at their centroid) and a rotation angle.  The declared model has both near
    zero (head fixed relative to the C-arms); returns ``{"n_frames", "max_translation_mm",
    "max_rotation_deg", "frame_of_max"}`` (frame indices into ``tracks``).  ``motions``:
    :func:`reference_motions` of the same arguments, where the caller has them.
    """
    tracks = np.asarray(tracks, dtype=float)
    motions = reference_motions(tracks, frame_index) if motions is None else motions
    best = (0.0, 0.0, int(frame_index))
    n = 0
    for f, m in enumerate(motions):
        if m is None:
            continue
        T, ok = m
        n += 1
        c = tracks[f][ok].mean(axis=0)
        tr = float(np.linalg.norm(T.apply(c) - c))
        ang = rotation_angle_deg(T.R)
        if tr > best[0]:
            best = (tr, max(best[1], ang), f)
        else:
            best = (best[0], max(best[1], ang), best[2])
    return {"n_frames": n, "max_translation_mm": best[0], "max_rotation_deg": best[1], "frame_of_max": best[2]}


def rotation_angle_deg(R) -> float:
    """Angle of the rotation ``R`` in degrees."""
    return float(np.degrees(Rotation.from_matrix(np.asarray(R, dtype=float)).magnitude()))

