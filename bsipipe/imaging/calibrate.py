r"""Camera (C-arm) calibration: Zhang's method through OpenCV, a distortion model that can
grow, held-out error, parameter uncertainties and stereo extrinsics.

Pure functions over arrays: nothing here reads a file.

Camera model (pixels, OpenCV's convention: 0-based, x right, y down)
--------------------------------------------------------------------
A target point :math:`\mathbf X` (mm) seen in a view with pose :math:`(R, \mathbf t)` projects to

.. math::
    \mathbf p_{cv} = K\, D(\pi(R \mathbf X + \mathbf t)), \qquad
    \mathbf p_{tw} = \mathbf c + \mathcal R\big(\theta(\rho)\big)(\mathbf p_{cv} - \mathbf c), \qquad
    \mathbf p = \mathbf p_{tw} + \mathbf f(\mathbf p_{tw}),

- :math:`K, D`: OpenCV's pinhole and distortion (``k1 k2 p1 p2 k3`` by default; ``k4 k5 k6``
  with the rational model, ``s1..s4`` thin prism), :math:`\pi` the perspective division;
- **S-distortion** of an image intensifier (the earth's and stray magnetic fields turn the
  electron paths, more at larger radius): a rotation about the intensifier's axis
  :math:`\mathbf c` (the centre of its circular field, measured in the images by
  :func:`bsipipe.imaging.gridfind.field_centre`; the image centre without one), by
  :math:`\theta(\rho) = t_1 \rho^2 + t_2 \rho^3` rad, :math:`\rho = \lVert \mathbf p_{cv} -
  \mathbf c \rVert / s`, :math:`s` half the image diagonal;
- **local distortion**: a smooth residual field :math:`\mathbf f` (thin-plate spline of the
  pooled grid residuals, XMALab's idea of a local correction), in pixels.

Fitting alternates OpenCV's ``calibrateCameraExtended`` on observations with the current
twist and field removed, and least-squares refits of the twist and field on what is left,
until the RMS changes by less than 1e-6 px.  Standard deviations of the OpenCV parameters are
OpenCV's (conditional on the twist and field); the twist's from its own Jacobian.

Errors: ``rms_px`` is OpenCV's definition, :math:`\sqrt{\sum_i \lVert \mathbf e_i \rVert^2 / N}`
over all points.  The held-out error is leave-one-view-out: calibrate without view *i*,
find its pose with the intrinsics fixed (``solvePnP``), and take the RMS over the held-out
points of all views.

Outlier views (:func:`calibrate_with_rejection`): a view is judged held out, against a fit
without it: when its held-out RMS exceeds ``max(median + 5 * 1.4826 * MAD, 3 * median)`` of the
other views' RMS in that fit, and leaving it out lowers the others' RMS by 5 % or more, it is
left out (the furthest over first, refitting after each) and reported with its reason.  A
view from another camera or with a mis-ordered grid shows up here; a blurred one that is
merely noisier is kept and flagged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

log = logging.getLogger(__name__)

#: OpenCV's distortion coefficient order (the first n of them are used).
OPENCV_COEFF_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
#: ``stdDeviationsIntrinsics`` order of ``cv2.calibrateCameraExtended``.
OPENCV_STD_NAMES = ("fx", "fy", "cx", "cy") + OPENCV_COEFF_NAMES

#: Outlier view rule: RMS above max(median + MAD_SIGMAS * 1.4826 * MAD, MEDIAN_FACTOR * median).
OUTLIER_MAD_SIGMAS = 5.0
OUTLIER_MEDIAN_FACTOR = 3.0
# A view whose RMS is an outlier is left out only when it also pulls the model: leaving it
# out must lower the other views' reprojection RMS by at least this fraction.  A view whose
# corners are merely noisier (blur, a steep angle) but consistent with the others is kept
# and flagged, as OpenCV and Bouguet would keep it.
OUTLIER_MIN_INFLUENCE = 0.05
#: The views with the largest RMS that are judged held out, each round.
OUTLIER_CANDIDATES = 3
#: A calibration whose reprojection RMS exceeds this (px) is not to be trusted: a chessboard's
#: corners or a bead grid's centres are located to a few tenths of a pixel (OpenCV's sample
#: views: 0.41 px; blurred or steep views about 1 px), so an RMS of several pixels means a
#: wrong --grid, views from two cameras or mis-ordered points, not detection noise.
LARGE_RMS_PX = 2.0


@dataclass(frozen=True)
class ModelSpec:
    """Which parts of the camera model are on (the loop's spec; hashable)."""

    rational: bool = False       # k4, k5, k6 (cv2.CALIB_RATIONAL_MODEL)
    thin_prism: bool = False     # s1..s4 (cv2.CALIB_THIN_PRISM_MODEL)
    s_distortion: bool = False   # twist theta(rho) = t1 rho + t2 rho^2 about the principal point
    local: bool = False          # smooth residual field (thin-plate spline)
    fix_aspect_ratio: bool = False
    fix_principal_point: bool = False   # cx, cy kept where the starting camera has them

    @property
    def n_coeffs(self) -> int:
        return 12 if self.thin_prism else 8 if self.rational else 5

    def flags(self) -> int:
        import cv2
        f = 0
        if self.rational:
            f |= cv2.CALIB_RATIONAL_MODEL
        if self.thin_prism:
            f |= cv2.CALIB_THIN_PRISM_MODEL
            if not self.rational:
                f |= cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6
        if self.fix_aspect_ratio:
            f |= cv2.CALIB_FIX_ASPECT_RATIO
        if self.fix_principal_point:
            f |= cv2.CALIB_FIX_PRINCIPAL_POINT
        return f

    def coeff_names(self) -> list[str]:
        return list(OPENCV_COEFF_NAMES[: self.n_coeffs])

    def describe(self) -> str:
        s = f"opencv-{self.n_coeffs}"
        if self.thin_prism and not self.rational:
            s += "(k4-k6 fixed at 0)"
        if self.fix_aspect_ratio:
            s += "+fixed-aspect"
        if self.fix_principal_point:
            s += "+fixed-principal-point"
        if self.s_distortion:
            s += "+s-distortion"
        if self.local:
            s += "+local-distortion"
        return s


@dataclass
class ViewData:
    """One calibration view: target points seen in one image."""

    name: str
    image_points: np.ndarray   # (n, 2) px
    object_points: np.ndarray  # (n, 3) mm
    ids: np.ndarray            # (n,) target point ids


# --- the extra (non-OpenCV) parts of the model ------------------------------------------------

@dataclass
class LocalField:
    r"""Smooth displacement field :math:`\mathbf f(\mathbf p)` in pixels: a thin-plate spline
    (``scipy.interpolate.RBFInterpolator``, linear polynomial part) through residuals pooled
    in square cells of ``cell_px``, each cell weighted by its count (smoothing
    ``smoothing / count``), less its own affine part (``affine``, fitted over the cells by
    :func:`fit_local_field`).

    The field owns no affine part: a shift, scale or shear of the image is the pinhole's
    (cx, cy, fx, fy and the views' poses).  A spline that kept one would hold a share of them,
    split with the pinhole by where the alternation of the two fits happened to stop.  (On the
    S-distortion twin the fit is unchanged by it: held-out 0.0921 and 0.0821 px, stereo RMS
    0.0728 -> 0.0722 px, triangulated shape 0.0048 mm.)"""

    centres_px: np.ndarray   # (m, 2) cell mean positions
    values_px: np.ndarray    # (m, 2) cell mean residuals
    counts: np.ndarray       # (m,)
    smoothing: float
    cell_px: float
    dof: float = 0.0         # effective degrees of freedom (trace of the smoother, both components)
    affine: np.ndarray | None = None   # (3, 2): subtracted [x/scale, y/scale, 1] @ affine
    _rbf: object = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        from scipy.interpolate import RBFInterpolator
        self._rbf = RBFInterpolator(self.centres_px / self.scale_px, self.values_px, kernel="thin_plate_spline",
                                    smoothing=self.smoothing / np.maximum(self.counts, 1), degree=1)

    @property
    def scale_px(self) -> float:
        """Positions are divided by this (24 cells) so the smoothing does not depend on the image size."""
        return 24.0 * self.cell_px

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if not len(xy):
            return np.zeros((0, 2))
        u = xy / self.scale_px
        f = self._rbf(u)
        if self.affine is not None:
            f -= u @ self.affine[:2] + self.affine[2]
        return f

    def without_affine(self) -> "LocalField":
        """This field less its affine part, least squares over the cells weighted by their counts."""
        u = self.centres_px / self.scale_px
        w = np.sqrt(np.maximum(self.counts, 1.0))[:, None]
        A = np.column_stack([u, np.ones(len(u))])
        aff, *_ = np.linalg.lstsq(A * w, self._rbf(u) * w, rcond=None)
        return LocalField(self.centres_px, self.values_px, self.counts, self.smoothing, self.cell_px, self.dof, aff)

    def to_dict(self) -> dict:
        return {"kind": "thin-plate-spline", "cell_px": self.cell_px, "smoothing": self.smoothing,
                "dof": self.dof, "centres_px": self.centres_px.tolist(), "values_px": self.values_px.tolist(),
                "counts": self.counts.tolist(),
                "affine_removed": None if self.affine is None else self.affine.tolist(),
                "formula": "p = p_tw + f(p_tw); f(p) = s(p / L) - [p / L, 1] affine_removed, L = 24 * cell_px; s = "
                           "thin-plate spline through the cell means (scipy RBFInterpolator, degree 1, smoothing / "
                           "count per cell)"}

    @classmethod
    def from_dict(cls, ld: dict) -> "LocalField":
        aff = ld.get("affine_removed")
        return cls(np.asarray(ld["centres_px"], float).reshape(-1, 2), np.asarray(ld["values_px"], float).reshape(-1, 2),
                   np.asarray(ld["counts"], float), float(ld["smoothing"]), float(ld["cell_px"]),
                   float(ld.get("dof", 0.0)), None if aff is None else np.asarray(aff, float).reshape(3, 2))


def _bin_residuals(pos: np.ndarray, res: np.ndarray, cell_px: float):
    key = np.floor(pos / cell_px).astype(int)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    m = len(counts)
    c = np.zeros((m, 2))
    v = np.zeros((m, 2))
    np.add.at(c, inv, pos)
    np.add.at(v, inv, res)
    return c / counts[:, None], v / counts[:, None], counts.astype(float)


def fit_local_field(pos: np.ndarray, res: np.ndarray, groups: np.ndarray, image_size: tuple[int, int],
                    smoothings: Sequence[float] = tuple(10.0 ** np.arange(-6, 2.1, 1.0)), n_folds: int = 5,
                    smoothing: float | None = None) -> LocalField:
    """Thin-plate spline of residuals ``res`` (n, 2) at ``pos`` (n, 2); smoothing by view-wise
    cross-validation (``groups`` = view index; folds of whole views, so the field must predict
    views it has not seen), unless ``smoothing`` is given."""
    w, h = image_size
    cell = max(w, h) / 24.0
    ug = np.unique(groups)
    folds = [ug[k::n_folds] for k in range(min(n_folds, len(ug)))]
    best, best_err = smoothings[-1], np.inf
    if smoothing is not None:
        best, folds = float(smoothing), []
    if len(folds) >= 2:
        for sm in smoothings:
            sse = 0.0
            for fold in folds:
                test = np.isin(groups, fold)
                c, v, n = _bin_residuals(pos[~test], res[~test], cell)
                if len(c) < 6:
                    continue
                f = LocalField(c, v, n, sm, cell)
                sse += float(np.sum((res[test] - f(pos[test])) ** 2))
            if sse < best_err:
                best, best_err = sm, sse
    c, v, n = _bin_residuals(pos, res, cell)
    f = LocalField(c, v, n, best, cell).without_affine()
    # effective dof: trace of the cell smoother (the interpolant is linear in the data)
    from scipy.interpolate import RBFInterpolator
    m = len(c)
    if m <= 800:
        cs = c / f.scale_px
        S = RBFInterpolator(cs, np.eye(m), kernel="thin_plate_spline", smoothing=best / n, degree=1)(cs)
        f.dof = 2.0 * float(np.trace(S))
    else:
        f.dof = 2.0 * m
    f.dof = max(f.dof - 6.0, 0.0)        # less the affine part (3 per component) the pinhole owns
    return f


def twist(xy: np.ndarray, centre: np.ndarray, t: np.ndarray, norm_radius: float, inverse: bool = False) -> np.ndarray:
    r"""Rotate pixels about ``centre`` by :math:`\theta(\rho) = t_1 \rho^2 + t_2 \rho^3` rad,
    :math:`\rho = \lVert \mathbf p - \mathbf c \rVert / s` (radius kept, so the inverse is the
    rotation by :math:`-\theta`)."""
    d = np.asarray(xy, float) - centre
    rho = np.hypot(d[:, 0], d[:, 1]) / norm_radius
    th = t[0] * rho ** 2 + t[1] * rho ** 3
    if inverse:
        th = -th
    c, s = np.cos(th), np.sin(th)
    return centre + np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])


@dataclass
class CameraModel:
    """A calibrated camera: OpenCV intrinsics and distortion, optional twist and local field."""

    image_size: tuple[int, int]
    camera_matrix: np.ndarray        # (3, 3)
    dist_coeffs: np.ndarray          # (n,) OpenCV order
    spec: ModelSpec
    twist_rad: np.ndarray | None = None   # (t1, t2)
    local: LocalField | None = None
    twist_centre_px: np.ndarray | None = None  # the intensifier axis; defaults to the image centre

    @property
    def norm_radius_px(self) -> float:
        return 0.5 * float(np.hypot(*self.image_size))

    @property
    def principal_point(self) -> np.ndarray:
        return self.camera_matrix[:2, 2].copy()

    @property
    def twist_centre(self) -> np.ndarray:
        if self.twist_centre_px is None:
            return 0.5 * (np.asarray(self.image_size, float) - 1.0)
        return np.asarray(self.twist_centre_px, float)

    def extras(self, p_cv: np.ndarray) -> np.ndarray:
        """OpenCV-model pixels -> full-model pixels (twist, then local field)."""
        p = p_cv
        if self.twist_rad is not None:
            p = twist(p, self.twist_centre, self.twist_rad, self.norm_radius_px)
        if self.local is not None:
            p = p + self.local(p)
        return p

    def remove_extras(self, p: np.ndarray, iterations: int = 4) -> np.ndarray:
        """Observed pixels -> the pixels the OpenCV part alone would give (inverse of :meth:`extras`)."""
        q = np.asarray(p, dtype=float).reshape(-1, 2)
        if self.local is not None:
            tw = q.copy()
            for _ in range(iterations):  # fixed point of tw + f(tw) = q
                tw = q - self.local(tw)
            q = tw
        if self.twist_rad is not None:
            q = twist(q, self.twist_centre, self.twist_rad, self.norm_radius_px, inverse=True)
        return q

    def project(self, object_points: np.ndarray, rvec, tvec) -> np.ndarray:
        """Target points (n, 3) mm in a view with pose (rvec, tvec) -> pixels (n, 2)."""
        import cv2
        p, _ = cv2.projectPoints(np.asarray(object_points, np.float64).reshape(-1, 1, 3),
                                 np.asarray(rvec, np.float64), np.asarray(tvec, np.float64),
                                 self.camera_matrix, self.dist_coeffs)
        return self.extras(p.reshape(-1, 2))

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """Observed pixels (n, 2) -> normalised, undistorted image coordinates (n, 2) (z = 1)."""
        from .camera import opencv_undistort  # Newton's inverse of OpenCV's model (the twin's)
        q = self.remove_extras(pixels)
        K = self.camera_matrix
        xyd = (q - K[:2, 2]) / [K[0, 0], K[1, 1]]
        return opencv_undistort(xyd, self.dist_coeffs)

    def solve_pose(self, object_points: np.ndarray, image_points: np.ndarray, rvec=None, tvec=None):
        """Pose of a view with the intrinsics fixed (``cv2.solvePnP`` on extras-removed pixels)."""
        import cv2
        q = self.remove_extras(image_points).reshape(-1, 1, 2)
        obj = np.asarray(object_points, np.float64).reshape(-1, 1, 3)
        if rvec is not None:
            ok, r, t = cv2.solvePnP(obj, q, self.camera_matrix, self.dist_coeffs,
                                    np.array(rvec, np.float64).reshape(3, 1), np.array(tvec, np.float64).reshape(3, 1),
                                    useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        else:
            ok, r, t = cv2.solvePnP(obj, q, self.camera_matrix, self.dist_coeffs, flags=cv2.SOLVEPNP_ITERATIVE)
        return r.ravel(), t.ravel()

    def distortion_map(self, xy_ideal: np.ndarray) -> np.ndarray:
        """Distorted pixels of ideal (pinhole, undistorted) pixels: the full distortion as a map."""
        import cv2
        K = self.camera_matrix
        n = (np.asarray(xy_ideal, float) - K[:2, 2]) / [K[0, 0], K[1, 1]]
        obj = np.column_stack([n, np.ones(len(n))])
        p, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, self.dist_coeffs)
        return self.extras(p.reshape(-1, 2))

    @classmethod
    def from_dict(cls, d: dict) -> "CameraModel":
        """The camera of one ``calibration.json`` ``views`` entry (inverse of :meth:`to_dict`)."""
        n = len(d["dist_coeffs"])
        names = list(d.get("dist_coeff_names") or OPENCV_COEFF_NAMES[:n])
        desc = str(d.get("dist_model", ""))
        spec = ModelSpec(rational=n >= 8 and "k4-k6 fixed" not in desc, thin_prism="s1" in names,
                         s_distortion=d.get("s_distortion") is not None,
                         local=d.get("local_distortion") is not None, fix_aspect_ratio="fixed-aspect" in desc,
                         fix_principal_point="fixed-principal-point" in desc)
        twist = centre = local = None
        if d.get("s_distortion"):
            sd = d["s_distortion"]
            twist = np.array([sd["t1_rad"], sd["t2_rad"]], float)
            centre = np.asarray(sd["centre_px"], float) if sd.get("centre_px") is not None else None
        if d.get("local_distortion"):
            local = LocalField.from_dict(d["local_distortion"])
        return cls(tuple(int(v) for v in d["image_size"]), np.asarray(d["camera_matrix"], float).reshape(3, 3),
                   np.asarray(d["dist_coeffs"], float).ravel(), spec, twist, local, centre)

    def to_dict(self) -> dict:
        K = self.camera_matrix
        d = {"image_size": list(self.image_size), "camera_matrix": K.tolist(),
             "dist_model": self.spec.describe(), "dist_coeffs": self.dist_coeffs.ravel().tolist(),
             "dist_coeff_names": self.spec.coeff_names()}
        if self.twist_rad is not None:
            d["s_distortion"] = {"t1_rad": float(self.twist_rad[0]), "t2_rad": float(self.twist_rad[1]),
                                 "edge_rotation_deg_at_norm_radius": float(np.degrees(sum(self.twist_rad))),
                                 "norm_radius_px": self.norm_radius_px, "centre_px": self.twist_centre.tolist(),
                                 "formula": "p = c + Rot(t1 rho^2 + t2 rho^3) (p_cv - c), rho = |p_cv - c| / norm_radius_px"}
        if self.local is not None:
            d["local_distortion"] = self.local.to_dict()
        return d


# --- calibration -----------------------------------------------------------------------------

@dataclass
class Calibration:
    """The result of :func:`calibrate_camera` for one camera."""

    camera: CameraModel
    views: list[ViewData]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]
    residuals: dict[str, np.ndarray]          # view -> (n, 2) observed - projected, px
    per_view_rms_px: dict[str, float]
    rms_px: float
    std: dict[str, float]
    n_params: int
    rejected: dict[str, str] = field(default_factory=dict)
    flagged: dict[str, str] = field(default_factory=dict)
    heldout_rms_px: float | None = None
    heldout_per_view_rms_px: dict[str, float] = field(default_factory=dict)
    std_jackknife: dict[str, float] = field(default_factory=dict)   # :func:`jackknife_std`, params' names
    iterations: int = 1
    success: bool = True

    @property
    def params(self) -> dict:
        K = self.camera.camera_matrix
        p = {"fx_px": K[0, 0], "fy_px": K[1, 1], "cx_px": K[0, 2], "cy_px": K[1, 2]}
        p.update({n: float(v) for n, v in zip(self.camera.spec.coeff_names(), self.camera.dist_coeffs.ravel())})
        if self.camera.twist_rad is not None:
            p["s_t1_rad"], p["s_t2_rad"] = (float(x) for x in self.camera.twist_rad)
        if self.camera.local is not None:
            p["local_dof"] = self.camera.local.dof
            p["local_smoothing"] = self.camera.local.smoothing
        return {k: float(v) for k, v in p.items()}

    def to_dict(self) -> dict:
        d = self.camera.to_dict()
        d.update({
            "rms_px": self.rms_px,
            "per_image_rms_px": dict(self.per_view_rms_px),
            "heldout_rms_px": self.heldout_rms_px,
            "heldout_per_image_rms_px": dict(self.heldout_per_view_rms_px),
            "std": dict(self.std),
            "std_jackknife": {_STD_NAME.get(k, k): v for k, v in self.std_jackknife.items()},
            "n_views": len(self.views),
            "n_points": int(sum(len(v.ids) for v in self.views)),
            "rejected_views": dict(self.rejected),
            "flagged_views": dict(self.flagged),
            "poses": {v.name: {"rvec": r.tolist(), "tvec_mm": t.tolist()}
                      for v, r, t in zip(self.views, self.rvecs, self.tvecs)},
        })
        return d


#: :attr:`Calibration.params`' names as ``std`` names them.
_STD_NAME = {"fx_px": "fx", "fy_px": "fy", "cx_px": "cx", "cy_px": "cy"}


def weak_intrinsics(cal: Calibration, ratio: float = 3.0, floor_px: float = 1.0) -> dict[str, dict]:
    """The pinhole parameters (fx, fy, cx, cy) whose leave-one-view-out spread
    (:attr:`Calibration.std_jackknife`) is over ``ratio`` times the fit's own std and over
    ``floor_px``: the views do not pin them down as closely as the fit's std says (with
    independent errors and a right model the two agree).  Name -> value, std, jackknife
    std (px)."""
    p = cal.params
    out = {}
    for k, short in _STD_NAME.items():
        jk = cal.std_jackknife.get(k)
        sd = cal.std.get(short)
        if jk is None or sd is None or not np.isfinite(jk):
            continue
        if jk > ratio * sd and jk > floor_px:
            out[short] = {"value_px": p[k], "std_px": sd, "std_jackknife_px": jk}
    return out


def _rms(e: np.ndarray) -> float:
    e = np.asarray(e).reshape(-1, 2)
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))) if len(e) else float("nan")


def _opencv_calibrate(obj, img, image_size, spec: ModelSpec, K0=None, D0=None):
    import cv2
    flags = spec.flags()
    K = np.eye(3) if K0 is None else np.array(K0, np.float64)
    if K0 is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    D = np.zeros(spec.n_coeffs) if D0 is None else np.resize(np.asarray(D0, np.float64).ravel(), spec.n_coeffs)
    if D0 is not None and len(np.ravel(D0)) < spec.n_coeffs:
        D[len(np.ravel(D0)):] = 0.0
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    size = tuple(int(x) for x in image_size)
    try:
        out = cv2.calibrateCameraExtended(obj, img, size, K, D, flags=flags, criteria=crit)
    except cv2.error as e:
        if K0 is None:
            raise ValueError(f"OpenCV calibration failed: {str(e).strip().splitlines()[-1]}") from None
        # a starting guess from another model can lead OpenCV astray; start afresh
        try:
            out = cv2.calibrateCameraExtended(obj, img, size, np.eye(3), np.zeros(spec.n_coeffs),
                                              flags=spec.flags(), criteria=crit)
        except cv2.error as e2:
            raise ValueError(f"OpenCV calibration failed: {str(e2).strip().splitlines()[-1]}") from None
    rms, K, D, rvecs, tvecs, std_i, _std_e, per_view = out
    return K, D.ravel()[: spec.n_coeffs], [r.ravel() for r in rvecs], [t.ravel() for t in tvecs], std_i.ravel()


def calibrate_camera(views: Sequence[ViewData], image_size: tuple[int, int], spec: ModelSpec = ModelSpec(), *,
                     init: CameraModel | None = None, max_iter: int = 30, tol_px: float = 1e-4,
                     twist_centre_px=None) -> Calibration:
    """Fit the camera model ``spec`` to ``views`` (all used; see :func:`calibrate_with_rejection`).

    Raises ValueError with fewer than 3 views (Zhang's method needs at least 3 for a full
    pinhole with principal point).
    """
    views = list(views)
    if len(views) < 3:
        raise ValueError(f"{len(views)} usable view(s); calibration needs at least 3")
    obj = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in views]
    K0 = D0 = None
    cam = CameraModel(tuple(image_size), np.eye(3), np.zeros(spec.n_coeffs), spec,
                      np.zeros(2) if spec.s_distortion else None, None)
    if twist_centre_px is None and init is not None:
        twist_centre_px = init.twist_centre_px
    cam.twist_centre_px = None if twist_centre_px is None else np.asarray(twist_centre_px, float)
    if init is not None:
        K0, D0 = init.camera_matrix, init.dist_coeffs
        if spec.s_distortion and init.twist_rad is not None:
            cam.twist_rad = init.twist_rad.copy()
    extras = spec.s_distortion or spec.local
    smoothing = init.local.smoothing if (init is not None and init.local is not None and spec.local) else None
    prev = np.inf
    it = 0
    std_i = np.zeros(18)
    for it in range(1, (max_iter if extras else 1) + 1):
        img = [cam.remove_extras(v.image_points).astype(np.float32).reshape(-1, 1, 2) for v in views]
        K, D, rvecs, tvecs, std_i = _opencv_calibrate(obj, img, image_size, spec, K0, D0)
        K0, D0 = K, D
        cam.camera_matrix, cam.dist_coeffs = K, D
        if extras:
            import cv2
            p_cv = [cv2.projectPoints(o.astype(np.float64), r, t, K, D)[0].reshape(-1, 2)
                    for o, r, t in zip(obj, rvecs, tvecs)]
            P = np.concatenate(p_cv)
            Y = np.concatenate([v.image_points for v in views])
            if spec.s_distortion:
                _fit_twist(cam, p_cv, [v.image_points for v in views])
            if spec.local:
                cam.local = None
                base = twist(P, cam.twist_centre, cam.twist_rad, cam.norm_radius_px) if spec.s_distortion else P
                groups = np.concatenate([np.full(len(v.ids), k) for k, v in enumerate(views)])
                cam.local = fit_local_field(base, Y - base, groups, image_size, smoothing=smoothing)
                smoothing = cam.local.smoothing
        resid = {v.name: v.image_points - cam.project(v.object_points, r, t)
                 for v, r, t in zip(views, rvecs, tvecs)}
        rms = _rms(np.concatenate(list(resid.values())))
        if not extras or abs(prev - rms) < tol_px:
            break
        prev = rms
    std = {n: float(s) for n, s in zip(OPENCV_STD_NAMES, std_i)
           if n in ("fx", "fy", "cx", "cy") or n in spec.coeff_names()}
    if spec.fix_aspect_ratio and std.get("fx", 0.0) == 0.0:
        std["fx"] = std["fy"] * K[0, 0] / K[1, 1]  # OpenCV fits fy and keeps fx = aspect * fy
    n_params = ((3 if spec.fix_aspect_ratio else 4) - (2 if spec.fix_principal_point else 0) + spec.n_coeffs
                - (3 if spec.thin_prism and not spec.rational else 0))
    n_params += 6 * len(views)
    if spec.s_distortion:
        n_params += 2
        J = _twist_jacobian(cam, views, rvecs, tvecs)
        e = np.concatenate([r.ravel() for r in resid.values()])
        s2 = float(e @ e) / max(len(e) - n_params, 1)
        try:
            cov = np.linalg.inv(J.T @ J) * s2
            std["s_t1_rad"], std["s_t2_rad"] = (float(x) for x in np.sqrt(np.diag(cov)))
        except np.linalg.LinAlgError:
            pass
    if spec.local and cam.local is not None:
        n_params += int(round(cam.local.dof))
    return Calibration(cam, views, rvecs, tvecs, resid, {k: _rms(v) for k, v in resid.items()}, rms, std,
                       n_params, iterations=it, success=bool(np.isfinite(rms)))


def _fit_twist(cam: CameraModel, p_cv: list[np.ndarray], obs: list[np.ndarray], iterations: int = 3) -> None:
    r"""Twist (t1, t2) on OpenCV-model pixels ``p_cv`` against ``obs`` by linear least squares
    in the small angle, :math:`\mathbf r \approx (t_1 \rho^2 + t_2 \rho^3 + \phi_v) J \mathbf d`,
    with a roll :math:`\phi_v` of each view about the principal point (a camera roll, which the
    next OpenCV step takes into the view's pose) so the twist is not confounded with the poses;
    repeated about the current estimate."""
    c, s, loc = cam.twist_centre, cam.norm_radius_px, cam.local
    t = np.asarray(cam.twist_rad, float).copy()
    for _ in range(iterations):
        rows, rhs = [], []
        for k, (p, y) in enumerate(zip(p_cv, obs)):
            q = twist(p, c, t, s)
            if loc is not None:
                y = y - loc(q)
            d = q - c
            jd = np.column_stack([-d[:, 1], d[:, 0]])  # J d: the direction a small rotation moves d
            rho = np.hypot(d[:, 0], d[:, 1]) / s
            A = np.zeros((2 * len(p), 2 + len(p_cv)))
            A[:, 0] = (jd * (rho ** 2)[:, None]).ravel()
            A[:, 1] = (jd * (rho ** 3)[:, None]).ravel()
            A[:, 2 + k] = jd.ravel()
            rows.append(A)
            rhs.append((y - q).ravel())
        x, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
        t = t + x[:2]
    cam.twist_rad = t


def _twist_jacobian(cam: CameraModel, views, rvecs, tvecs, h: float = 1e-7) -> np.ndarray:
    def proj(t):
        c = replace(cam, twist_rad=np.asarray(t))
        return np.concatenate([c.project(v.object_points, r, tv).ravel() for v, r, tv in zip(views, rvecs, tvecs)])
    t0 = np.asarray(cam.twist_rad, float)
    cols = []
    for k in range(2):
        dt = np.zeros(2)
        dt[k] = h
        cols.append((proj(t0 + dt) - proj(t0 - dt)) / (2 * h))
    return np.column_stack(cols)


def outlier_threshold_px(rms: Sequence[float]) -> float:
    """``max(median + 5 * 1.4826 * MAD, 3 * median)`` of per-view RMS values.

    >>> round(outlier_threshold_px([0.2, 0.2, 0.2, 0.25, 0.3]), 3)
    0.6
    """
    r = np.asarray(rms, float)
    med = float(np.median(r))
    mad = float(np.median(np.abs(r - med)))
    return max(med + OUTLIER_MAD_SIGMAS * 1.4826 * mad, OUTLIER_MEDIAN_FACTOR * med)


def calibrate_with_rejection(views: Sequence[ViewData], image_size: tuple[int, int], spec: ModelSpec = ModelSpec(),
                             *, reject_outliers: bool = True, min_views: int = 3, twist_centre_px=None,
                             n_candidates: int = OUTLIER_CANDIDATES) -> Calibration:
    """:func:`calibrate_camera`, leaving out outlier views one at a time.

    A view that does not belong (another camera, a mis-ordered board) pulls the fit towards
    itself, so its own RMS looks milder and the others' worse, and the median and MAD of the
    contaminated fit hide it.  So each of the ``n_candidates`` views with the largest RMS is
    judged held out: the camera is calibrated without it, its pose found with those
    intrinsics (``solvePnP``), and its held-out RMS compared with
    :func:`outlier_threshold_px` of the other views' RMS in that fit.  The candidate furthest
    over its threshold is left out when leaving it out also lowers the other views' RMS by at
    least ``OUTLIER_MIN_INFLUENCE`` (it pulls the model); a view over the threshold that does
    not pull the model is kept and listed in ``Calibration.flagged`` (noisier but consistent:
    blur, a steep angle).  Repeated until no candidate is over its threshold.  Every view
    left out is in ``Calibration.rejected`` with its RMS, held-out RMS, threshold and influence.
    """
    views = list(views)
    rejected: dict[str, str] = {}
    flagged: dict[str, str] = {}
    cal = calibrate_camera(views, image_size, spec, twist_centre_px=twist_centre_px)
    while reject_outliers and len(cal.views) > min_views:
        names = [v.name for v in cal.views]
        rms = np.array([cal.per_view_rms_px[n] for n in names])
        judged = []
        for k in np.argsort(-rms, kind="stable")[: max(1, n_candidates)]:
            v = cal.views[k]
            keep = [u for u in cal.views if u.name != v.name]
            try:
                cal_wo = calibrate_camera(keep, image_size, spec, init=cal.camera, twist_centre_px=twist_centre_px)
            except ValueError:
                continue
            held = _held_out_rms(cal_wo, cal, k)
            thr = outlier_threshold_px([cal_wo.per_view_rms_px[u.name] for u in keep])
            influence = _influence(cal, cal_wo, keep)
            why = (f"reprojection RMS {rms[k]:.3f} px, held out {held:.3f} px > threshold {thr:.3f} px "
                   f"(max(median + {OUTLIER_MAD_SIGMAS:g} x 1.4826 MAD, {OUTLIER_MEDIAN_FACTOR:g} x median) of the "
                   f"other views, fitted without it); leaving it out changes the other views' RMS by "
                   f"{-100 * influence:+.1f} %")
            if held > thr:
                judged.append((held / thr, influence, v.name, why, cal_wo))
        if not judged:
            break
        pulling = [j for j in judged if j[1] >= OUTLIER_MIN_INFLUENCE]
        if not pulling and len(judged) > 1:
            group = _outliers_together(cal, judged, image_size, spec, twist_centre_px, min_views)
            if group:
                for name, why in group.items():
                    rejected[name] = f"outlier: {why}"
                    flagged.pop(name, None)
                    log.info("calibrate: leaving out %s: %s", name, rejected[name])
                cal = calibrate_camera([u for u in cal.views if u.name not in group], image_size, spec,
                                       init=cal.camera, twist_centre_px=twist_centre_px)
                continue
        if not pulling:
            for _, _, name, why, _ in judged:
                if name not in flagged:
                    flagged[name] = f"kept: {why} (< {100 * OUTLIER_MIN_INFLUENCE:g} %: consistent with the others)"
                    log.warning("calibrate: %s is noisier than the other views but consistent with them: %s",
                                name, why)
            break
        _, _, name, why, cal_wo = max(pulling, key=lambda j: j[0])
        rejected[name] = f"outlier: {why}"
        flagged.pop(name, None)
        log.info("calibrate: leaving out %s: %s", name, rejected[name])
        cal = cal_wo
    cal.rejected = rejected
    cal.flagged = flagged
    return cal


def _held_out_rms(cal_wo: Calibration, cal: Calibration, k: int) -> float:
    """The reprojection RMS of ``cal``'s view ``k`` under ``cal_wo``, a calibration without it:
    its pose found with those intrinsics (``solvePnP`` from its pose in ``cal``)."""
    v = cal.views[k]
    r, t = cal_wo.camera.solve_pose(v.object_points, v.image_points, cal.rvecs[k], cal.tvecs[k])
    return _rms(v.image_points - cal_wo.camera.project(v.object_points, r, t))


def posed_rms(camera, views: Sequence[ViewData]) -> np.ndarray:
    """Each view's reprojection RMS (px) under ``camera``'s intrinsics, its pose fitted alone
    (``solvePnP``): how well views that took no part in a calibration fit it."""
    out = []
    for v in views:
        r, t = camera.solve_pose(v.object_points, v.image_points)
        out.append(_rms(v.image_points - camera.project(v.object_points, r, t)))
    return np.asarray(out, float)


def _influence(cal: Calibration, cal_wo: Calibration, keep: Sequence[ViewData]) -> float:
    """How much leaving views out of ``cal`` lowers the RMS of the views ``keep`` (``cal_wo``
    is the calibration on ``keep`` alone): 1 - RMS without / RMS with them."""
    others_with = _rms(np.concatenate([cal.residuals[u.name] for u in keep]))
    return 1.0 - cal_wo.rms_px / others_with if others_with > 0 else 0.0


def _outliers_together(cal: Calibration, judged: list, image_size, spec: ModelSpec, twist_centre_px,
                       min_views: int) -> dict[str, str]:
    """Views over their threshold that do not pull the model alone may pull it together: two
    bad views (a wire across the plate in both) each keep the other views' RMS up when the
    other is left out, so neither is judged an outlier one at a time.  Left out together, if
    the other views' RMS falls by ``OUTLIER_MIN_INFLUENCE`` or more, each is judged again held
    out against that cleaner fit; those over its threshold are the outliers (name -> why)."""
    names = {j[2] for j in judged}
    keep = [u for u in cal.views if u.name not in names]
    if len(keep) < max(min_views, 3):
        return {}
    try:
        cal_wo = calibrate_camera(keep, image_size, spec, init=cal.camera, twist_centre_px=twist_centre_px)
    except ValueError:
        return {}
    influence = _influence(cal, cal_wo, keep)
    if influence < OUTLIER_MIN_INFLUENCE:
        return {}
    thr = outlier_threshold_px([cal_wo.per_view_rms_px[u.name] for u in keep])
    out = {}
    index = {v.name: k for k, v in enumerate(cal.views)}
    for name in sorted(names, key=index.get):
        held = _held_out_rms(cal_wo, cal, index[name])
        if held > thr:
            out[name] = (f"held out {held:.3f} px > threshold {thr:.3f} px against a fit without "
                         f"{', '.join(sorted(names))}, which together pull the model: leaving them out changes the "
                         f"other views' RMS by {-100 * influence:+.1f} % (one at a time each hid the other)")
    return out


#: Views a leave-one-view-out error needs: each refit keeps the 3 a calibration needs.
MIN_HELDOUT_VIEWS = 4


def heldout_error(cal: Calibration, spec: ModelSpec | None = None,
                  folds: list | None = None) -> tuple[float, dict[str, float]]:
    """Leave-one-view-out reprojection RMS (px) over all held-out points, and per view.
    ``folds``: a list that receives each refit's :attr:`Calibration.params` (for
    :func:`jackknife_std`).  A refit needs the 3 views a calibration needs: with fewer than
    :data:`MIN_HELDOUT_VIEWS` views there is nothing to hold out, and the error is NaN (no
    folds, no per-view values)."""
    spec = spec or cal.camera.spec
    views = cal.views
    if len(views) < MIN_HELDOUT_VIEWS:
        return math.nan, {}
    sse = 0.0
    n = 0
    per: dict[str, float] = {}
    for i, v in enumerate(views):
        train = views[:i] + views[i + 1:]
        c = calibrate_camera(train, cal.camera.image_size, spec, init=cal.camera)
        if folds is not None:
            folds.append(c.params)
        r, t = c.camera.solve_pose(v.object_points, v.image_points, cal.rvecs[i], cal.tvecs[i])
        e = v.image_points - c.camera.project(v.object_points, r, t)
        per[v.name] = _rms(e)
        sse += float(np.sum(e ** 2))
        n += len(e)
    return float(np.sqrt(sse / n)), per


def jackknife_std(folds: Sequence[dict]) -> dict[str, float]:
    r"""Leave-one-view-out (jackknife) standard deviation of each parameter the ``folds``
    (:func:`heldout_error`'s refits, one per left-out view) share:
    :math:`\sqrt{(n-1)/n \sum_i (\theta_i - \bar\theta)^2}`.

    Unlike OpenCV's ``stdDeviationsIntrinsics`` (the residual variance times the inverse
    normal matrix: independent errors and a right model assumed), it follows what moves a
    parameter from view to view: a systematic residual the model lacks, a parameter that
    trades with others (a narrow field's principal point against the views' tilts and the
    tangential terms).  Empty with fewer than 3 folds.

    >>> jackknife_std([{"cx_px": 1.0}, {"cx_px": 2.0}, {"cx_px": 3.0}])["cx_px"]   # sqrt(2/3 * 2)
    1.1547005383792515
    """
    if len(folds) < 3:
        return {}
    names = [k for k in folds[0] if all(k in f for f in folds)]
    n = len(folds)
    out = {}
    for k in names:
        a = np.array([f[k] for f in folds], float)
        if np.all(np.isfinite(a)):
            # a parameter held fixed (a principal point at the field centre) does not move: 0,
            # not the 1e-13 its rounding would give
            still = np.ptp(a) <= 1e-9 * max(1.0, float(np.abs(a).max()))
            out[k] = 0.0 if still else float(np.sqrt((n - 1) / n * np.sum((a - a.mean()) ** 2)))
    return out


def residual_components(cal: Calibration) -> tuple[list[np.ndarray], np.ndarray]:
    r"""Per view, the radial then the tangential residual (about the principal point) in grid
    order, times :math:`\sqrt 2` so that their RMS equals the per-point RMS (OpenCV's
    definition); and the radius (px) of each sample, for the loop's structure tests."""
    c = cal.camera.principal_point
    parts, radii = [], []
    for v in cal.views:
        e = cal.residuals[v.name]
        d = v.image_points - c
        rad = np.hypot(d[:, 0], d[:, 1])
        u = d / np.maximum(rad, 1e-9)[:, None]
        er = np.sum(e * u, axis=1)
        et = u[:, 0] * e[:, 1] - u[:, 1] * e[:, 0]
        parts.append(np.sqrt(2.0) * np.concatenate([er, et]))
        radii.append(np.concatenate([rad, rad]))
    return parts, np.concatenate(radii)


# --- stereo ----------------------------------------------------------------------------------

def target_symmetries(object_points_all: np.ndarray) -> list[np.ndarray]:
    """Id permutations under which the target looks the same (its in-plane symmetries,
    mirrors included: a planar target seen from behind, as in X-ray, is mirrored).

    ``object_points_all`` (N, 3): every target point, indexed by id.  Returns a list of
    index arrays ``perm`` with ``perm[id]`` the id the point is relabelled to; the identity first.
    """
    P = np.asarray(object_points_all, float)[:, :2]
    ctr = 0.5 * (P.min(axis=0) + P.max(axis=0))
    Q = P - ctr
    scale = np.max(np.abs(Q)) or 1.0
    key = {tuple(np.round(q / scale * 1e6).astype(int)): k for k, q in enumerate(Q)}
    mats = [np.array(m, float) for m in ([[1, 0], [0, 1]], [[-1, 0], [0, -1]], [[-1, 0], [0, 1]], [[1, 0], [0, -1]],
                                         [[0, 1], [1, 0]], [[0, -1], [-1, 0]], [[0, -1], [1, 0]], [[0, 1], [-1, 0]])]
    out = []
    for m in mats:
        perm = []
        for q in Q @ m.T:
            k = key.get(tuple(np.round(q / scale * 1e6).astype(int)))
            if k is None:
                break
            perm.append(k)
        if len(perm) == len(Q):
            out.append(np.array(perm))
    return out


def _angle_deg(Ra, Rb) -> float:
    """The angle (deg) of the rotation between ``Ra`` and ``Rb``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def _pose_distance(Ra, ta, Rb, tb) -> float:
    return float(_angle_deg(Ra, Rb) + np.linalg.norm(ta - tb) / 10.0)  # 1 deg ~ 10 mm


@dataclass
class StereoResult:
    views: tuple[str, str]
    R: np.ndarray
    T_mm: np.ndarray
    rms_px: float
    frames: list[str]
    n_points: int
    relabelled: dict[str, int] = field(default_factory=dict)
    note: str = ""
    pair_deviation: dict[str, dict] = field(default_factory=dict)   # frame -> {"deg", "mm"}
    rejected: dict[str, str] = field(default_factory=dict)          # frame -> why it was left out
    unpaired: dict[str, list[str]] = field(default_factory=dict)    # camera -> its frames the other lacks

    def to_dict(self) -> dict:
        import cv2
        rvec = cv2.Rodrigues(self.R)[0].ravel()
        return {"views": list(self.views), "R": self.R.tolist(), "T_mm": self.T_mm.ravel().tolist(),
                "rms_px": self.rms_px, "baseline_mm": float(np.linalg.norm(self.T_mm)),
                "rotation_deg": float(np.degrees(np.linalg.norm(rvec))),
                "frames": list(self.frames), "n_points": self.n_points,
                "pair_deviation": {k: dict(v) for k, v in self.pair_deviation.items()},
                "rejected_frames": dict(self.rejected), "unpaired_frames": {k: list(v) for k, v in self.unpaired.items()},
                "relabelled_frames": dict(self.relabelled), "note": self.note,
                "convention": "x_B = R x_A + T_mm (points in camera A's frame to camera B's)"}


def stereo_calibrate(cam_a: CameraModel, cam_b: CameraModel, names: tuple[str, str],
                     frames_a: dict[str, ViewData], frames_b: dict[str, ViewData],
                     target_all: np.ndarray | None = None, ambiguous: bool = False) -> StereoResult:
    """Extrinsics between two calibrated cameras from frames both saw (same file name).

    ``cv2.stereoCalibrate`` with both cameras' intrinsics fixed, on observations with each
    camera's twist and local field removed.  When the target is symmetric (``ambiguous``),
    camera B's labelling of each frame is chosen among the target's symmetries so that the
    relative pose agrees across frames (needs at least two frames in different poses).
    """
    import cv2
    common = sorted(set(frames_a) & set(frames_b))
    if not common:
        raise ValueError(f"no frame seen by both {names[0]} and {names[1]} (same file name in both folders)")
    relabelled: dict[str, int] = {}
    note = ""
    fb = dict(frames_b)
    if ambiguous and target_all is not None:
        perms = target_symmetries(target_all)
        if len(perms) > 1:
            fb, relabelled, note = _resolve_symmetry(cam_a, cam_b, common, frames_a, frames_b, perms, target_all)
    unpaired = {names[0]: sorted(set(frames_a) - set(frames_b)), names[1]: sorted(set(frames_b) - set(frames_a))}
    unpaired = {k: v for k, v in unpaired.items() if v}
    # A grid cut off by the field is numbered from the first row and column seen, which need not
    # be the other camera's: such a pair would match different dots (the probe: cam1's stereo
    # images cut by 30 %, stereo RMS 17.3 px, 3-D error 0.87 mm, exit 0).  Left out where at
    # least MIN_WHOLE_PAIRS pairs show the whole grid in both cameras; else said (``note``).
    cut: dict[str, str] = {}
    if target_all is not None:
        full = len(target_all)
        for n in common:
            short = [nm for nm, v in ((names[0], frames_a[n]), (names[1], fb[n])) if len(v.ids) < full]
            if short:
                seen = ", ".join(str(len(v.ids)) for v in (frames_a[n], fb[n]))
                cut[n] = (f"the grid is cut off in {' and '.join(short)}'s image ({seen} of {full} points): numbered "
                          "from the first row and column seen, its dots need not be the other camera's")
    cut_note = ""
    if cut and len(common) - len(cut) >= MIN_WHOLE_PAIRS:
        common = [n for n in common if n not in cut]
    elif cut:
        cut_note = (f"{len(cut)} of {len(common)} shared frames show the grid cut off in a camera: a cut-off grid is "
                    "numbered from the first row and column seen, so the two cameras may number the same dots "
                    f"differently; give at least {MIN_WHOLE_PAIRS} stereo pairs with the whole grid in both images")
        note = (note + "; " if note else "") + cut_note
        cut = {}
    obj, pa, pb, used = [], [], [], []
    for n in common:
        va, vb = frames_a[n], fb[n]
        ids = np.intersect1d(va.ids, vb.ids)
        if len(ids) < 6:
            continue
        ia = np.searchsorted(va.ids, ids)
        ib = np.searchsorted(vb.ids, ids)
        obj.append(va.object_points[ia].astype(np.float32).reshape(-1, 1, 3))
        pa.append(cam_a.remove_extras(va.image_points[ia]).astype(np.float32).reshape(-1, 1, 2))
        pb.append(cam_b.remove_extras(vb.image_points[ib]).astype(np.float32).reshape(-1, 1, 2))
        used.append(n)
    if not obj:
        raise ValueError("no shared frame has 6 or more target points seen by both cameras")
    try:
        deviation, rejected = _pair_consistency(cam_a, cam_b, names, used, frames_a, fb)
    except ValueError as e:
        if cut_note:
            raise ValueError(f"{e}; or {cut_note}") from None
        raise
    keep = [k for k, n in enumerate(used) if n not in rejected]
    rejected = {**cut, **rejected}
    obj, pa, pb = [obj[k] for k in keep], [pa[k] for k in keep], [pb[k] for k in keep]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    out = cv2.stereoCalibrate(obj, pa, pb, cam_a.camera_matrix, cam_a.dist_coeffs, cam_b.camera_matrix,
                              cam_b.dist_coeffs, tuple(cam_a.image_size), flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    rms, R, T = out[0], out[5], out[6]
    return StereoResult(names, np.asarray(R), np.asarray(T).ravel(), float(rms), [used[k] for k in keep],
                        int(sum(len(o) for o in obj)), relabelled, note, deviation, rejected, unpaired)


#: Stereo pairs with the whole grid in both images enough to leave out those with a grid cut off.
MIN_WHOLE_PAIRS = 3

#: A shared frame's relative pose (camera A to B) may differ from the others' by this much
#: (median over them) before the pair is left out: 5 times the frames' typical deviation, and
#: at least 2 degrees and a tenth of the baseline (the real chessboard pair: 0.16-0.51 deg and
#: 0.9-3.3 mm on an 84 mm baseline; two right images exchanged: 16 deg and 108 mm).
PAIR_DEV_FACTOR = 5.0
PAIR_DEV_MIN_DEG = 2.0
PAIR_DEV_MIN_BASELINE = 0.1


def _pair_consistency(cam_a: CameraModel, cam_b: CameraModel, names: tuple[str, str], frames: list[str],
                      frames_a: dict[str, ViewData], frames_b: dict[str, ViewData]) -> tuple[dict, dict]:
    """Each shared frame's relative pose (``R_b R_a^T``, ``t_b - R t_a`` from the two cameras'
    own poses of the target) against the other frames': the median rotation angle (deg) and
    translation (mm) between it and each of them.  Both cameras see one rigid rig, so every
    pair of images taken together gives the same relative pose; a pair that does not (file
    names exchanged or shifted between the folders, an image of another moment) is left out,
    beyond :data:`PAIR_DEV_FACTOR` times the median deviation, :data:`PAIR_DEV_MIN_DEG` and
    :data:`PAIR_DEV_MIN_BASELINE` of the baseline.  Where the median frame itself is beyond
    those floors, the pairs do not agree at all: a ValueError.  Returns ``({frame: {"deg",
    "mm"}}, {frame: why left out})``; with fewer than 3 frames nothing can be judged."""
    import cv2
    if len(frames) < 3:
        return {}, {}
    rel = {}
    for n in frames:
        ra, ta = cam_a.solve_pose(frames_a[n].object_points, frames_a[n].image_points)
        rb, tb = cam_b.solve_pose(frames_b[n].object_points, frames_b[n].image_points)
        R = cv2.Rodrigues(np.asarray(rb, float))[0] @ cv2.Rodrigues(np.asarray(ra, float))[0].T
        rel[n] = (R, np.ravel(tb) - R @ np.ravel(ta))
    dev = {}
    for n, (R, t) in rel.items():
        ang = [_angle_deg(R2, R) for m, (R2, _) in rel.items() if m != n]
        mm = [float(np.linalg.norm(t - t2)) for m, (_, t2) in rel.items() if m != n]
        dev[n] = {"deg": float(np.median(ang)), "mm": float(np.median(mm))}
    baseline = float(np.median([np.linalg.norm(t) for _, t in rel.values()]))
    typ_deg = float(np.median([d["deg"] for d in dev.values()]))
    typ_mm = float(np.median([d["mm"] for d in dev.values()]))
    lim_deg = max(PAIR_DEV_FACTOR * typ_deg, PAIR_DEV_MIN_DEG)
    lim_mm = max(PAIR_DEV_FACTOR * typ_mm, PAIR_DEV_MIN_BASELINE * baseline)
    if typ_deg > PAIR_DEV_MIN_DEG or typ_mm > PAIR_DEV_MIN_BASELINE * baseline:
        raise ValueError(f"the shared frames' relative poses of {names[0]} and {names[1]} disagree (median "
                         f"{typ_deg:.3g} deg and {typ_mm:.3g} mm between frames, on a {baseline:.3g} mm baseline): "
                         "the files of one name are not images taken together (names shifted or mismatched "
                         "between the two folders?)")
    rejected = {n: (f"its relative pose differs from the other pairs' by {d['deg']:.3g} deg and {d['mm']:.3g} mm "
                    f"(median; limits {lim_deg:.3g} deg, {lim_mm:.3g} mm): not images taken together")
                for n, d in dev.items() if d["deg"] > lim_deg or d["mm"] > lim_mm}
    if len(frames) - len(rejected) < 2:
        raise ValueError(f"{len(rejected)} of the {len(frames)} shared frames have relative poses unlike the others': "
                         "the files of one name are not images taken together")
    return dev, rejected


def _resolve_symmetry(cam_a, cam_b, common, frames_a, frames_b, perms, target_all):
    import cv2
    cands = {}
    for n in common:
        va, vb = frames_a[n], frames_b[n]
        ra, ta = cam_a.solve_pose(va.object_points, va.image_points)
        Ra = cv2.Rodrigues(ra)[0]
        lst = []
        for k, perm in enumerate(perms):
            ids = perm[vb.ids]
            rb, tb = cam_b.solve_pose(target_all[ids], vb.image_points)
            Rb = cv2.Rodrigues(rb)[0]
            R = Rb @ Ra.T
            lst.append((k, R, tb - R @ ta))
        cands[n] = lst
    best = None
    for n0 in common:
        for k0, R0, t0 in cands[n0]:
            score, choice = 0.0, {}
            for n in common:
                d = [(_pose_distance(R0, t0, R, t), k) for k, R, t in cands[n]]
                dm, km = min(d)
                score += dm
                choice[n] = km
            if best is None or score < best[0]:
                best = (score, choice)
    choice = best[1]
    fb = {}
    for n in common:
        vb = frames_b[n]
        perm = perms[choice[n]]
        ids = perm[vb.ids]
        order = np.argsort(ids)
        fb[n] = ViewData(vb.name, vb.image_points[order], target_all[ids[order]], ids[order])
    relabelled = {n: int(k) for n, k in choice.items() if k != 0}
    note = ("symmetric target: camera B's labelling chosen per frame for a consistent relative pose"
            if len(common) > 1 else
            "symmetric target seen in one shared frame only: the labelling (and so R, T) is ambiguous")
    return fb, relabelled, note
