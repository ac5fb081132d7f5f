r"""Marker detection: region of interest, top-hat, noise threshold, blobs, sub-pixel centres.

The chain (:func:`detect_markers`), for markers of diameter ``d`` pixels:

1. **Region of interest.**  An image intensifier images a circular field and leaves the rest
   black; :func:`find_field_of_view` thresholds the dark surround (a quarter of the way from its
   level to the field's, on a reduced copy; the dark pixels connected to the image border),
   fits a circle to the field's edge (robustly, points on the image border and on dark
   objects inside the field left out, so a field cut by the frame is still found) and
   detection keeps away from its edge.  Or give ``roi``.
2. **Top-hat** with a disk larger than a marker (OpenCV ``morphologyEx``; black-hat for dark
   markers, white top-hat for bright ones): the background, anything wider than the disk,
   is removed and markers become positive bumps ``T`` on a flat floor.
3. **Threshold from the noise.**  ``T`` is lightly smoothed (a Gaussian of about the
   marker's blur, the matched filter of a small blob) to ``T_s``, and the threshold is
   :math:`\mathrm{median}(T_s) + k\,\hat\sigma`, :math:`\hat\sigma = 1.4826\,\mathrm{MAD}(T_s)`
   over the region of interest: a robust estimate that the sparse markers do not move.  The
   statistics (and the pixel noise, step 6) are taken on a sampling grid of about 16,000
   pixels or more (:func:`_grid_step`); the region is tested on that grid and at the
   candidate pixels only, so the whole-frame work per frame is the top-hat, its smoothing
   (:func:`smoothed_tophat`) and one comparison with the threshold.
4. **Blobs.**  Local maxima of ``T_s`` above the threshold, at least about a diameter
   apart (two touching markers give two), are the candidates; each blob is measured at
   half its peak height (``area_px``), which does not depend on the threshold: noise specks
   are too small, instrument edges too large, elongated blobs are dropped.  Where
   connected components are wanted, ``cv2.connectedComponentsWithStats`` merges plateaus.
5. **Sub-pixel centre** on a patch around each candidate, after subtracting a plane fitted
   robustly to the patch's outer ring, with the pixels nearer to a neighbouring marker left
   out, or, where the ring shows an edge the plane cannot follow (a bone's, the skull rim's,
   an instrument's, a line), a profile across the edge (:func:`_edge_background`): the
   intensity-weighted centroid (iterated, soft-edged window), then refined by a
   2-D Gaussian fit (default, batched Levenberg-Marquardt), or Parthasarathy's (2012)
   radial-symmetry centre.  On synthetic chord-law beads (steel spheres 2.6-5 px across,
   0.7 px blur, fluoroscopy noise; ``tests/test_detect.py``) the Gaussian refinement has the
   smallest error (RMS 0.09 px at 2.6 px, 0.04 px at 4 px, against 0.12/0.06 px for the
   centroid and 0.11/0.05 px for radial symmetry).
6. **Signal-to-noise.**  ``snr`` = fitted amplitude / the pixel noise, the noise from the MAD
   of Immerkaer's (1996) Laplacian-like high-pass, which the sparse markers do not move.

Pixel convention (CONTRACTS.md): x to the right, y down, the centre of the top-left pixel
is (0, 0); array element ``[i, j]`` is centred at ``x = j, y = i``.
"""

from __future__ import annotations

import functools
import math
import sys
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import cv2
import numpy as np
import pandas as pd

Polarity = Literal["dark", "bright"]
CentreMethod = Literal["gaussian", "centroid", "radial"]
Background = Literal["edge", "plane"]

#: Columns of :func:`detect_markers` and :func:`refine_at` (in this order).
COLUMNS = ["x_px", "y_px", "snr", "amplitude", "area_px", "mass", "sigma_px", "elongation",
           "x_centroid_px", "y_centroid_px"]

_EYE3 = np.eye(3)
_EYE3_TINY = 1e-9 * _EYE3
_LITTLE_ENDIAN = sys.byteorder == "little"
_MAD = 1.482602218505602   # sd of a normal distribution / its median absolute deviation
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_SECOND_DIFF = np.array([1, -2, 1], np.float32)      # Immerkaer's kernel is its outer square
_CROSS_DY, _CROSS_DX = np.array([-1, 0, 0, 1]), np.array([0, -1, 1, 0])   # the four neighbours


# --- region of interest ---------------------------------------------------------------------

@dataclass(frozen=True)
class FieldOfView:
    """The image intensifier's circular field (``found``), else the whole image; and, when
    ``region`` is given, only its pixels.

    ``centre_px`` (x, y) and ``radius_px`` in the frame's pixels; ``shape`` (h, w).
    ``region``: a bool (h, w) mask of the pixels to search (a region of interest the user
    drew, e.g. to leave out an instrument or a label), else None.  ``given``: the circle or
    the region came from the user, not from the frames (:func:`find_field_of_view`).
    """

    shape: tuple[int, int]
    centre_px: tuple[float, float] | None = None
    radius_px: float | None = None
    found: bool = False
    region: np.ndarray | None = field(default=None, compare=False, repr=False)
    given: bool = False

    def _region_within(self, margin_px: float) -> np.ndarray:
        """``region`` shrunk by ``margin_px`` (a disk erosion; the image border is outside)."""
        r = np.asarray(self.region, bool)
        k = int(math.ceil(margin_px))
        if k <= 0:
            return r
        se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
        return cv2.erode(np.ascontiguousarray(r, dtype=np.uint8), se, borderType=cv2.BORDER_CONSTANT,
                         borderValue=0) > 0

    def mask(self, margin_px: float = 0.0) -> np.ndarray:
        """Boolean (h, w) mask of the pixels at least ``margin_px`` inside the field."""
        h, w = self.shape
        if not self.found:
            m = np.zeros((h, w), bool)
            b = int(math.ceil(margin_px))
            m[b:h - b, b:w - b] = True
        else:
            ys, xs = np.ogrid[:h, :w]
            cx, cy = self.centre_px
            m = (xs - cx) ** 2 + (ys - cy) ** 2 <= (self.radius_px - margin_px) ** 2
        if self.region is not None:
            m &= self._region_within(margin_px)
        return m

    def contains(self, xy, margin_px: float = 0.0) -> np.ndarray:
        """Which points (N, 2) lie at least ``margin_px`` inside the field (and the image)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        h, w = self.shape
        ok = (xy[:, 0] >= margin_px - 0.5) & (xy[:, 1] >= margin_px - 0.5) & \
             (xy[:, 0] <= w - 0.5 - margin_px) & (xy[:, 1] <= h - 0.5 - margin_px)
        if self.found:
            cx, cy = self.centre_px
            ok &= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) <= self.radius_px - margin_px
        if self.region is not None and ok.any():
            r = self._region_within(margin_px)
            xi = np.clip(np.rint(np.nan_to_num(xy[:, 0])).astype(int), 0, w - 1)
            yi = np.clip(np.rint(np.nan_to_num(xy[:, 1])).astype(int), 0, h - 1)
            ok &= r[yi, xi]
        return ok

    def to_dict(self) -> dict:
        d = {"found": self.found, "centre_px": None if self.centre_px is None else list(self.centre_px),
             "radius_px": self.radius_px, "shape": list(self.shape)}
        if self.given:
            d["given"] = True
        if self.region is not None:
            d["region_px"] = int(np.count_nonzero(self.region))
        return d


def _fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Algebraic (Kasa) least-squares circle through points: centre x, y and radius."""
    A = np.column_stack([x, y, np.ones_like(x)])
    (p, q, c), *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    cx, cy = p / 2, q / 2
    return float(cx), float(cy), float(np.sqrt(max(c + cx * cx + cy * cy, 0.0)))


def find_field_of_view(frame: np.ndarray, *, min_dark_fraction: float = 0.03,
                       max_side_px: int = 256, level_fraction: float = 0.25) -> FieldOfView:
    """Find the intensifier's circular field by thresholding the dark surround.

    The frame is reduced to at most ``max_side_px`` a side.  The surround is the darkest
    class and lies outside the field, so it touches the image border: its level ``s`` is a
    low percentile of the reduced frame (the middle of its darkest ``min_dark_fraction``),
    the field's ``f`` the median of the frame or of its central region, whichever is higher
    (dense anatomy or an instrument may fill the centre), and the threshold is
    ``s + level_fraction (f - s)``: low, because the field may be darker at its edge
    (vignetting, dense tissue) than in its middle, and an image intensifier's surround is
    close to black.  (Otsu's threshold splits bright from grey when the field holds a large
    mid-grey region, e.g. a head.)  The dark pixels connected to the image border are the
    surround, the rest (dark objects inside the field included) the field; its largest
    component's contour points that are not on the image border are fitted with a circle,
    refitted to the points within 2 reduced pixels of it (dark instruments or tissue at
    the field's edge bite into the contour, the circle is what remains), and the circle is
    refined on the full frame (:func:`_refine_circle`).  When the surround covers less than
    ``min_dark_fraction`` of the frame, fewer than half the contour points lie on the
    circle, or the field does not lie inside it, the whole frame is the field.
    """
    img = np.asarray(frame)
    h, w = img.shape[:2]
    f = max(1, int(math.ceil(max(h, w) / max_side_px)))
    small = cv2.resize(img.astype(np.float32), (max(w // f, 1), max(h // f, 1)), interpolation=cv2.INTER_AREA)
    lo, hi = float(small.min()), float(small.max())
    if hi <= lo:
        return FieldOfView((h, w))
    hs, ws = small.shape
    flat = small.ravel()
    k = min(int(0.5 * min_dark_fraction * flat.size), flat.size - 1)
    if np.count_nonzero(flat <= lo) > k:
        # a black surround: the k-th smallest is the minimum itself (np.partition takes 2.5 ms
        # on a 256 x 256 frame whose darkest 20 % tie, 50 times this test)
        surround = lo
    else:
        surround = float(np.partition(flat, k)[k])
    yy, xx = np.ogrid[:hs, :ws]
    central = (xx - (ws - 1) / 2) ** 2 + (yy - (hs - 1) / 2) ** 2 <= (0.25 * min(hs, ws)) ** 2
    field = max(float(np.median(small[central])), float(np.median(flat)))
    if field <= surround:
        return FieldOfView((h, w))
    dark = (small <= surround + level_fraction * (field - surround)).astype(np.uint8)
    # the surround: the dark components that touch the image border
    n, labels = cv2.connectedComponents(dark, connectivity=8)
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    outer = np.unique(edge[edge > 0])
    if len(outer) == 0:
        return FieldOfView((h, w))
    lut = np.zeros(n, np.uint8)
    lut[outer] = 1
    outside = lut[labels]
    if np.count_nonzero(outside) < min_dark_fraction * outside.size:
        return FieldOfView((h, w))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(1 - outside, connectivity=4)
    if n < 2:
        return FieldOfView((h, w))
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    comp = (labels == k).astype(np.uint8)
    contours, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = max(contours, key=len).reshape(-1, 2).astype(float)
    pts = pts[(pts[:, 0] > 1) & (pts[:, 1] > 1) & (pts[:, 0] < ws - 2) & (pts[:, 1] < hs - 2)]
    if len(pts) < 20:
        return FieldOfView((h, w))
    use = np.ones(len(pts), bool)
    for _ in range(5):
        cx, cy, r = _fit_circle(pts[use, 0], pts[use, 1])
        off = np.abs(np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - r)
        new = off <= 2.0
        if new.sum() < 10 or np.array_equal(new, use):
            break
        use = new
    if np.mean(off <= 2.0) < 0.5 or r < 0.2 * min(hs, ws):
        return FieldOfView((h, w))
    # the field lies inside its circle (a dark round region at the border of a frame without
    # surround has a circular edge too, but the bright rest lies outside it)
    inside = (xx - cx) ** 2 + (yy - cy) ** 2 <= (r + 2.0) ** 2
    if np.count_nonzero(comp & inside) < 0.9 * np.count_nonzero(comp):
        return FieldOfView((h, w))
    # reduced pixel i covers full pixels [i f, (i + 1) f); the contour runs on the field's
    # outermost pixels, so the edge itself is about half a reduced pixel further out
    cx, cy, r = (cx + 0.5) * f - 0.5, (cy + 0.5) * f - 0.5, (r + 0.5) * f
    if f > 1:
        theta = np.arctan2(pts[use, 1] - (cy + 0.5) / f + 0.5, pts[use, 0] - (cx + 0.5) / f + 0.5)
        cx, cy, r = _refine_circle(img, cx, cy, r, theta, surround, 2.0 * f)
    return FieldOfView((h, w), (cx, cy), r, True)


def _refine_circle(img: np.ndarray, cx: float, cy: float, r: float, theta: np.ndarray, surround: float,
                   reach: float) -> tuple[float, float, float]:
    """The field's circle refined on the full-resolution frame: along the radius at each
    angle ``theta`` (the coarse fit's inlying contour points), the edge is where the profile
    last crosses halfway between the field's level just inside (median of the profile's
    inner part) and the surround's; a circle is fitted to these edge points, refitted to
    those within 1.5 px.  Profiles without contrast (an instrument across the edge) or
    reaching off the frame are left out; with too few edge points the coarse circle stays."""
    h, w = img.shape[:2]
    c, s = np.cos(theta), np.sin(theta)
    far = np.hypot(np.maximum(np.abs(cx + c * (r + reach) - (w - 1) / 2) - (w - 1) / 2, 0),
                   np.maximum(np.abs(cy + s * (r + reach) - (h - 1) / 2) - (h - 1) / 2, 0))
    keep = far == 0
    c, s = c[keep], s[keep]
    if len(c) < 20:
        return cx, cy, r
    step = 0.5
    d = np.arange(-2 * reach, reach + step / 2, step, dtype=np.float32)
    X = (cx + c[:, None] * (r + d[None])).astype(np.float32)
    Y = (cy + s[:, None] * (r + d[None])).astype(np.float32)
    src = img if img.dtype == np.float32 else img.astype(np.float32)
    prof = cv2.remap(src, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    inner = np.median(prof[:, :int(reach / step)], axis=1)
    half = 0.5 * (inner + surround)
    above = prof >= half[:, None]
    j = len(d) - 1 - np.argmax(above[:, ::-1], axis=1)          # the last sample above half
    ok = above.any(axis=1) & (j < len(d) - 1) & (inner - surround > 0.1 * (np.median(inner) - surround))
    if ok.sum() < 20:
        return cx, cy, r
    rows = np.nonzero(ok)[0]
    j = j[ok]
    a, b = prof[rows, j], prof[rows, j + 1]
    t = np.clip((a - half[ok]) / np.maximum(a - b, 1e-6), 0, 1)
    rad = r + d[j] + t * step
    ex, ey = cx + c[ok] * rad, cy + s[ok] * rad
    use = np.ones(len(ex), bool)
    fx, fy, fr = cx, cy, r
    for _ in range(5):
        fx, fy, fr = _fit_circle(ex[use], ey[use])
        new = np.abs(np.hypot(ex - fx, ey - fy) - fr) <= 1.5
        if new.sum() < 20:
            return cx, cy, r
        if np.array_equal(new, use):
            break
        use = new
    return fx, fy, fr


# --- top-hat and noise -----------------------------------------------------------------------

def structuring_size(diameter_px: float) -> int:
    """Side (odd) of the disk structuring element for markers of ``diameter_px``: wide
    enough that a blurred marker never fits inside it (about twice the diameter, at least 5).

    >>> structuring_size(4), structuring_size(11)
    (9, 23)
    """
    return max(5, (int(round(2.0 * diameter_px)) + 1) | 1)


def tophat(frame: np.ndarray, diameter_px: float, polarity: Polarity = "dark",
           structuring_px: int | None = None) -> np.ndarray:
    """Black-hat (dark markers) or white top-hat (bright markers) with a disk, float32 (h, w).

    Computed by ``cv2.morphologyEx`` in the frame's own dtype when OpenCV supports it
    (uint8, uint16, float32), so no precision is lost and 8-bit frames take the fast path.
    """
    img = np.asarray(frame)
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    k = structuring_size(diameter_px) if structuring_px is None else int(structuring_px) | 1
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    op = cv2.MORPH_BLACKHAT if polarity == "dark" else cv2.MORPH_TOPHAT
    return cv2.morphologyEx(img, op, se, borderType=cv2.BORDER_REPLICATE).astype(np.float32, copy=False)


def smoothed_tophat(frame: np.ndarray, diameter_px: float, polarity: Polarity, structuring_px: int,
                    sigma_px: float) -> np.ndarray:
    """:func:`tophat` smoothed by a Gaussian of ``sigma_px``, float32 (h, w): the same values as
    ``cv2.GaussianBlur(tophat(...), (0, 0), sigma_px)`` (kernel to 4 sigma, reflected border),
    but the morphology stays in the frame's dtype and the conversion to float32 is fused into
    the separable filter: no full-frame float copy of the top-hat."""
    img = np.asarray(frame)
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    op = cv2.MORPH_BLACKHAT if polarity == "dark" else cv2.MORPH_TOPHAT
    t = cv2.morphologyEx(img, op, _ellipse(int(structuring_px)), borderType=cv2.BORDER_REPLICATE)
    g = _gauss_kernel(float(sigma_px))
    return cv2.sepFilter2D(t, cv2.CV_32F, g, g, borderType=cv2.BORDER_REFLECT_101)


@functools.lru_cache(maxsize=16)
def _gauss_kernel(sigma_px: float) -> np.ndarray:
    """The kernel ``cv2.GaussianBlur`` uses on float images for ``sigma_px`` (size round(8 sigma + 1), odd)."""
    return cv2.getGaussianKernel(int(round(sigma_px * 8 + 1)) | 1, sigma_px, cv2.CV_32F)


# the compiled sub-pixel fits (setup.py builds them; optional): None where they are not built
from .compiled import KERNELS_VERSION  # noqa: E402, F401 - the version the calls below are written for
from .compiled import kernels as _kernels  # noqa: E402

try:                                   # the batched LAPACK solver np.linalg.solve wraps
    from numpy.linalg._umath_linalg import solve as _gesv
except ImportError:                    # pragma: no cover - a NumPy without it
    _gesv = None


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(a, b)`` for stacks of small systems (a (N, k, k), b (N, k, 1)): the
    same LAPACK routine and values without the wrapper's checks and error-state context
    (three times the solve itself on a frame's few 5 x 5 systems).  Where a result is not
    finite (a singular or non-finite system) ``np.linalg.solve`` is called, so a singular
    matrix still raises ``LinAlgError`` as before."""
    if _gesv is not None:
        with np.errstate(all="ignore"):
            x = _gesv(a, b)
        if np.isfinite(x).all():
            return x
    return np.linalg.solve(a, b)


def _clamp(x, lo, hi):
    """``np.clip`` for the per-frame path: the same values from two ufunc calls, without
    ``np.clip``'s Python-level dispatch (a dozen microseconds a call, dozens of calls a frame)."""
    return np.minimum(np.maximum(x, lo), hi)


def _median(v: np.ndarray, axis: int | None = None) -> np.ndarray:
    """``np.median`` of NaN-free data (the same values): one partition (or a sort) and the
    mean of the middle pair.  ``np.median``'s own checks (NaN, keepdims, overwrite) cost several times
    the partition on the small arrays of the per-frame path (search windows, patches)."""
    v = np.asarray(v)
    if axis is None:
        v, axis = v.ravel(), 0
    n = v.shape[axis]
    lo, hi = (n - 1) // 2, n // 2
    if v.ndim == 2 and axis in (1, -1):
        # rows: a sort for short ones; else one partition at the upper middle, the lower
        # middle being the largest value before it
        if n <= 200:
            p = np.sort(v, axis=1)
            return p[:, hi] if hi == lo else (p[:, lo] + p[:, hi]) / 2
        p = np.partition(v, hi, axis=1)
        return p[:, hi] if hi == lo else (p[:, :hi].max(axis=1) + p[:, hi]) / 2
    if v.ndim == 1 and n > 1:
        p = np.partition(v, hi)
        return p[hi] if hi == lo else (p[:hi].max() + p[hi]) / 2
    p = np.partition(v, (lo, hi) if hi != lo else lo, axis=axis)
    a = np.take(p, lo, axis=axis)
    return a if hi == lo else (a + np.take(p, hi, axis=axis)) / 2


def _robust_sd(v: np.ndarray, axis=None, med: np.ndarray | None = None) -> np.ndarray:
    """1.4826 MAD along ``axis`` (``med``: the median, if already known); where the MAD is 0
    (coarsely quantised or codec-smoothed images) the mean absolute deviation times
    sqrt(pi/2) stands in."""
    if med is None:
        med = _median(v, axis)
    a = np.abs(v - (med if axis is None else med[:, None] if (axis == 1 and v.ndim == 2)
                    else np.expand_dims(med, axis)))
    sd = _MAD * _median(a, axis)
    if np.all(sd > 0):
        return sd
    mean_ad = np.mean(a, axis=axis) * math.sqrt(math.pi / 2)
    return np.where(sd > 0, sd, mean_ad)


def pixel_noise(frame: np.ndarray, mask: np.ndarray | None = None, step: int = 1) -> float:
    r"""Robust standard deviation of the pixel noise (grey levels).

    The frame is filtered with Immerkaer's kernel
    :math:`N = [[1,-2,1],[-2,4,-2],[1,-2,1]]`, which removes any locally linear intensity
    (background, gradients); for white noise of sd :math:`\sigma` the output has sd
    :math:`6\sigma`.  The MAD of the output (within ``mask``, every ``step``-th row and
    column) makes the markers and edges, a small fraction of the pixels, irrelevant.
    """
    img = np.asarray(frame)
    r = _immerkaer(img, step)
    if mask is not None:
        r = r[np.asarray(mask)[1:-1:step, 1:-1:step]]
    return _noise_from_highpass(r)


def _trimmed_power(x: np.ndarray) -> float:
    """Mean square of ``x`` over its entries within 4 robust sd (at least 4 grey levels) of 0:
    markers moving and edges are a small share of a difference image and are left out; the
    cut is wide enough that noise is not (a MAD alone is too coarse on integer frames)."""
    x = x.ravel()
    s0 = _MAD * float(np.median(np.abs(x - np.median(x)))) if x.size else 0.0
    k = np.abs(x) < 4.0 * max(s0, 1.0)
    return float(np.mean(np.square(x[k], dtype=np.float64))) if k.any() else 0.0


def temporal_noise_correlation(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float | None:
    r"""Lag-1 correlation :math:`\rho` of the pixel noise of three consecutive frames ``a, b, c``
    (same shape), or None where the frames hold no noise (identical, or flat).

    A frame the C-arm averaged over time (image-intensifier lag, phosphor persistence, the
    recursive noise filter fluoroscopy units apply), :math:`y_t = (1-a)\,x_t + a\,y_{t-1}`,
    carries noise that is an AR(1) sequence in time with :math:`\rho = a`; the scene's static
    part cancels in frame differences, whose powers are :math:`2\sigma^2(1-\rho)` one frame
    apart and :math:`2\sigma^2(1-\rho^2)` two apart, so

    .. math::  \rho = \frac{P(c - a)}{P(c - b)} - 1

    on the differences high-passed along rows (``[1, -2, 1]``: a change of the picture's gain
    or level between the frames is not noise) and trimmed (:func:`_trimmed_power`).  About 0 for
    independent frames (|rho| < 0.02 on the bench twin, with flicker, drift, clipping, 20 grey
    levels or a repeated frame); 0.32 for a twin averaged with a = 0.3.  Pixels at the three
    frames' lowest or highest level in any of them (clipped: black, or saturated air) are left
    out, with the high-pass values they enter: they carry no noise, and one clipped in one
    frame only breaks the average's linear model (the bench twin's cam2, a third of its
    central quarter saturated, averaged with a = 0.3, had read 0.11; 0.30 without them)."""
    lo = min(float(np.min(x)) for x in (a, b, c))
    hi = max(float(np.max(x)) for x in (a, b, c))
    clip = None
    if hi > lo:
        clip = (a <= lo) | (a >= hi) | (b <= lo) | (b >= hi) | (c <= lo) | (c >= hi)
        clip = clip[:, 2:] | clip[:, 1:-1] | clip[:, :-2]
        if clip.all():
            return None
        if not clip.any():
            clip = None
    a, b, c = (np.asarray(x, np.float32) for x in (a, b, c))

    def hp(d):
        h = d[:, 2:] - 2.0 * d[:, 1:-1] + d[:, :-2]
        return h if clip is None else h[~clip]

    p1 = _trimmed_power(hp(c - b))
    p2 = _trimmed_power(hp(c - a))
    if not (p1 > 0 and p2 > 0):
        return None
    return p2 / p1 - 1.0


def is_blank(frame: np.ndarray) -> bool:
    """A frame without a picture: its whole range of grey levels (max - min) is within 16
    sd of its own pixel noise (1.4826 MAD of Immerkaer's high-pass / 6, on every 4th row
    and column), plus one grey level of an integer frame: a black or saturated frame (range
    0) or dark noise only (about 10 sd over a megapixel).  A frame with any marker, edge or
    field border spans far more; a noiseless one (a rendering: MAD 0) is blank only if flat.

    >>> is_blank(np.zeros((64, 64), np.uint8)), is_blank(np.eye(64, dtype=np.uint8) * 200)
    (True, False)
    >>> is_blank(np.eye(64, dtype=np.float32) * 0.8), is_blank(np.full((64, 64), 0.5, np.float32))
    (False, True)
    """
    a = np.asarray(frame)
    r = _immerkaer(a, 4).ravel().astype(np.float64)
    sd = _MAD * float(np.median(np.abs(r - np.median(r)))) / 6.0 if r.size else 0.0
    hi, lo = float(a.max()), float(a.min())
    # one grey level of an integer frame; a float frame has no levels (scaled 0-1, a floor of
    # 1.0 had called every frame blank): its rounding only
    floor = 1.0 if np.issubdtype(a.dtype, np.integer) else 1e-9 * max(abs(hi), abs(lo))
    return hi - lo <= 16.0 * sd + floor


def _immerkaer(img: np.ndarray, step: int = 1) -> np.ndarray:
    """Immerkaer's high-pass at pixels ``[1:-1:step, 1:-1:step]`` (float32; int32 for 8/16-bit
    frames with ``step`` > 1, exact)."""
    if step == 1:
        return cv2.filter2D(img.astype(np.float32, copy=False), cv2.CV_32F, _IMMERKAER,
                            borderType=cv2.BORDER_REPLICATE)[1:-1, 1:-1]
    # the filter at the sampled pixels only: nine strided views, 1/step^2 of the work
    h, w = img.shape
    ny, nx = len(range(1, h - 1, step)), len(range(1, w - 1, step))
    if ny == 0 or nx == 0:
        return np.zeros((ny, nx), np.float32)

    # 8/16-bit frames: exact integer arithmetic (the statistics then use a histogram)
    dt = np.int32 if img.dtype in (np.uint8, np.uint16, np.int8, np.int16) else np.float32

    def at(dy, dx):
        return img[1 + dy:2 + dy + (ny - 1) * step:step, 1 + dx:2 + dx + (nx - 1) * step:step].astype(dt)
    return 4 * at(0, 0) - 2 * (at(-1, 0) + at(1, 0) + at(0, -1) + at(0, 1)) + \
        (at(-1, -1) + at(-1, 1) + at(1, -1) + at(1, 1))


def _coarse_noise(img: np.ndarray, step: int, use: np.ndarray | None = None) -> float:
    r"""The pixel noise measured at twice the pixel size: Immerkaer's high-pass of the frame's
    2 x 2 box sums two pixels apart, at the grid ``[3:-3:step, 3:-3:step]`` (``use``: the
    pixels of :func:`pixel_noise`'s grid ``[1:-1:step, 1:-1:step]`` to count, taken two pixels
    over), halved: for white noise of sd :math:`\sigma` the sums have sd :math:`2\sigma` and
    the high-pass :math:`12\sigma`.  It equals :func:`pixel_noise` for white noise; for
    noise the imaging chain has blurred (an intensifier's unsharpness, a camera's filter, JPEG)
    it is larger, as the noise is: a blur of 0.8 px left Immerkaer's estimate at 0.18 grey
    levels on a twin frame whose noise was 1.34, and the noise blobs came out at SNR 6 and more
    (thousands of tracks in automatic mode).  Strided views at the grid only: no full-frame
    filter."""
    h, w = img.shape
    ny, nx = len(range(3, h - 3, step)), len(range(3, w - 3, step))
    if ny == 0 or nx == 0:
        return float("nan")
    dt = np.int32 if img.dtype in (np.uint8, np.uint16, np.int8, np.int16) else np.float32

    def box(dy, dx):            # the 2 x 2 sums with top-left corner at the grid + (dy, dx)
        out = None
        for a, b in ((0, 0), (1, 0), (0, 1), (1, 1)):
            y0, x0 = 3 + dy + a, 3 + dx + b
            v = img[y0:y0 + (ny - 1) * step + 1:step, x0:x0 + (nx - 1) * step + 1:step].astype(dt)
            out = v if out is None else out + v
        return out
    hp = 4 * box(0, 0) - 2 * (box(-2, 0) + box(2, 0) + box(0, -2) + box(0, 2)) + \
        (box(-2, -2) + box(-2, 2) + box(2, -2) + box(2, 2))
    if use is not None:
        u = use[1:1 + ny, 1:1 + nx] if step == 1 else use[:ny, :nx]
        hp = hp[:u.shape[0], :u.shape[1]][u]
    return 0.5 * _noise_from_highpass(hp)


def _noise_from_highpass(r: np.ndarray) -> float:
    """Pixel noise sd from Immerkaer's high-pass values: 1.4826 MAD / 6 (:func:`_robust_sd`)."""
    r = r.ravel()
    if r.size == 0:
        return float("nan")
    if r.dtype.kind == "i" and r.size > 4096:
        return float(max(_robust_sd_int(r), 1e-3) / 6.0)
    return float(max(float(_robust_sd(r)), 1e-3) / 6.0)


def _median_hist(counts: np.ndarray, n: int) -> float:
    """Median (mean of the middle pair) of ``n`` integers 0, 1, ... from their histogram."""
    c = np.cumsum(counts)
    lo = int(np.searchsorted(c, (n - 1) // 2, side="right"))
    hi = int(np.searchsorted(c, n // 2, side="right"))
    return 0.5 * (lo + hi)


def _robust_sd_int(v: np.ndarray) -> float:
    """:func:`_robust_sd` of integers, by histograms instead of partitions (the same value)."""
    lo = int(v.min())
    n = v.size
    med = lo + _median_hist(np.bincount(v - lo), n)
    dev2 = np.abs(2 * v - int(round(2 * med)))           # twice |v - med|: integers
    mad = 0.5 * _median_hist(np.bincount(dev2), n)
    if mad > 0:
        return _MAD * mad
    return float(np.mean(dev2)) * 0.5 * math.sqrt(math.pi / 2)


def robust_threshold(values: np.ndarray, k_sigma: float) -> tuple[float, float]:
    """``median + k_sigma * 1.4826 * MAD`` of ``values``; returns (threshold, sigma)."""
    v = np.asarray(values, np.float32).ravel()
    med = _median(v)
    sd = max(float(_robust_sd(v, med=med)), 1e-6)
    return float(med) + k_sigma * sd, sd


def _smooth_sigma(diameter_px: float) -> float:
    return max(0.6, 0.2 * diameter_px)


# --- settings --------------------------------------------------------------------------------

@dataclass(frozen=True)
class DetectionSettings:
    """Knobs of :func:`detect_markers` (defaults suit C-arm frames and beads of 2-12 px).

    ``k_sigma``: threshold in robust sd of the smoothed top-hat over a whole frame;
    ``window_k_sigma``: the same in the small search windows of seeded tracking
    (:func:`window_arrays`).  A threshold sets the false alarms per pixel searched: 5 sd on
    a 1024 x 1024 frame and 4 sd on a window of ~1,000 pixels both give about one noise
    peak in a hundred searches (normal tails 3e-7 and 3e-5 per pixel), and 4 sd keeps a
    0.5 mm bead at the real C-arm noise (amplitude SNR ~6, 2.6 px) where 5 sd loses it in
    a few percent of frames; ``min_area_px`` /
    ``max_area_factor``: limits of a blob's half-maximum area (the upper one times the area
    of a disc twice the marker's diameter); ``max_elongation``: axis ratio of a blob's
    second moments; ``min_snr``: amplitude / pixel noise a kept marker needs;
    ``edge_margin_px``: distance a marker keeps from the field's edge (default: the
    structuring element's radius + 2); ``method``: sub-pixel centre (``gaussian``,
    ``centroid``, ``radial``); ``blur_px``: the marker's blur sigma, which sets the top-hat's
    smoothing and the patch sizes (default ``max(0.6, d/5)``); ``window_radius_px``:
    centroid and fit window (default ``d/2 + 1.5 blur``); ``structuring_px``: side of the
    top-hat's disk (default :func:`structuring_size`); ``max_sigma_factor``: a fitted Gaussian
    width above this times the diameter is not a marker (None: no limit); ``parity``: ``"trackpy"`` replaces the
    whole chain by trackpy's (:func:`locate_trackpy`, for comparisons with trackpy users'
    results; needs ``method="centroid"``), ``minmass`` its mass threshold; ``background``: what
    is taken from under a marker before its centre is measured, ``"plane"`` (fitted to the
    ring of pixels around it) or ``"edge"`` (the plane, or, where the plane leaves structure
    an F test finds, a profile that varies across one direction: the edge of a bone or an
    instrument, a line; :func:`_edge_background`).
    """

    k_sigma: float = 5.0
    window_k_sigma: float = 4.0
    min_area_px: int = 2
    max_area_factor: float = 1.0
    max_elongation: float = 2.5
    min_snr: float = 3.0
    edge_margin_px: float | None = None
    method: CentreMethod = "gaussian"
    blur_px: float | None = None
    window_radius_px: float | None = None
    structuring_px: int | None = None
    min_roundness: float | None = 0.5
    max_sigma_factor: float | None = 0.75
    parity: Literal["none", "trackpy"] = "none"
    minmass: float = 0.0
    background: Background = "edge"

    def smooth_px(self, diameter_px: float) -> float:
        return _smooth_sigma(diameter_px) if self.blur_px is None else float(self.blur_px)

    def se_px(self, diameter_px: float) -> int:
        return structuring_size(diameter_px) if self.structuring_px is None else int(self.structuring_px) | 1

    def window_px(self, diameter_px: float) -> float:
        if self.window_radius_px is not None:
            return float(self.window_radius_px)
        return 0.5 * diameter_px + 1.5 * self.smooth_px(diameter_px)

    def updated(self, **kw) -> "DetectionSettings":
        names = {f.name for f in fields(self)}
        bad = sorted(set(kw) - names)
        if bad:
            raise TypeError(f"unknown detection setting(s): {', '.join(bad)}")
        return replace(self, **kw)


# --- sub-pixel centres (array core) ------------------------------------------------------------
#
# The per-frame path measures a dozen small patches; its cost is the number of numpy calls,
# not their size.  Everything that depends on the patch geometry alone is computed once per
# geometry (:func:`_geo`, :func:`_neighbour_table`), and the routines below are written to
# give the same values as the straightforward formulas with as few calls as possible
# (order statistics from one sort per row set, neighbour masks from a table, the model's cost
# with the model, ...); the tests in ``tests/test_detect.py`` hold them to those formulas.

@dataclass(frozen=True)
class _Geo:
    half: int
    dx: np.ndarray          # (P*P,) x offset of each patch pixel from the patch centre
    dy: np.ndarray
    ring: np.ndarray        # (P*P,) bool: pixels for the background plane
    A: np.ndarray           # (P*P, 3) plane design [1, dx, dy]
    radius: float           # centroid / fit window radius
    support: np.ndarray     # (K,) indices of pixels a fit may use (near the patch centre)
    support_r: np.ndarray   # (K,) their distance from the patch centre
    A_ring: np.ndarray      # (R, 3) the plane design on the ring
    AA_ring: np.ndarray     # (R, 9) each ring row's outer product A_r A_r^T, flattened
    ring_idx: np.ndarray    # (R,) indices of the ring pixels
    near1: np.ndarray       # indices of the pixels within 1 px of the patch centre
    sup_xy: np.ndarray      # (2, K) x and y offsets of the support pixels
    sup_w0: np.ndarray      # (K,) the centroid's soft-disc weights about the patch centre
    key: tuple              # the arguments of :func:`_geo`
    ring_r_signal: float = 0.0  # the ring's inner radius: how far a marker's signal reaches


@functools.lru_cache(maxsize=32)
def _geo(diameter_px: float, blur_px: float, radius: float) -> _Geo:
    r_signal = max(0.5 * diameter_px + 2.5 * blur_px + 1.0, radius + 1.0)
    half = int(math.ceil(r_signal + 2.0))
    ax = np.arange(-half, half + 1, dtype=np.float64)
    gx, gy = np.meshgrid(ax, ax)
    dx, dy = gx.ravel(), gy.ravel()
    rr = np.hypot(dx, dy)
    A = np.column_stack([np.ones_like(dx), dx, dy])
    support = np.flatnonzero(rr <= radius + 3.0)
    A_ring = A[rr > r_signal]
    AA_ring = (A_ring[:, :, None] * A_ring[:, None, :]).reshape(-1, 9)
    sup_xy = np.ascontiguousarray(np.vstack([dx[support], dy[support]]))
    X, Y = sup_xy
    w0 = _clamp(radius + 1.0 - np.sqrt(X * X + Y * Y), 0.0, 1.0)   # :func:`_centroid`'s first pass
    return _Geo(half, dx, dy, rr > r_signal, A, float(radius), support, rr[support], A_ring, AA_ring,
                np.flatnonzero(rr > r_signal), np.flatnonzero(rr <= 1.0), sup_xy, w0,
                (diameter_px, blur_px, radius), float(r_signal))


def _gather(img: np.ndarray, ix: np.ndarray, iy: np.ndarray, half: int) -> np.ndarray:
    """Patches (N, P*P) centred on integer pixels; indices clipped (edge replicated)."""
    h, w = img.shape
    off = np.arange(-half, half + 1)
    rows = _clamp(iy[:, None] + off[None, :], 0, h - 1)
    cols = _clamp(ix[:, None] + off[None, :], 0, w - 1)
    return img[rows[:, :, None], cols[:, None, :]].reshape(len(ix), -1).astype(np.float64)


_NEIGHBOUR_TABLE_MAX = 8 << 20       # bytes: beads up to ~12 px across (larger ones: the formula)


def _neighbour_table_size(geo: _Geo) -> int:
    R = int(math.ceil(geo.half * math.sqrt(2) + geo.radius + 1.0))
    return (2 * R + 1) ** 2 * len(geo.dx)


@functools.lru_cache(maxsize=4)
def _neighbour_table(key: tuple) -> tuple[int, np.ndarray]:
    """For the geometry ``_geo(*key)``: (R, table (2R+1, 2R+1, P*P) bool), ``table[R + oy, R + ox]``
    True on the pixels (offsets from the patch centre) that a neighbour at the integer
    offset (ox, oy) leaves valid, i.e. not nearer to it than to the centre or farther than
    the window radius + 1 from it (:func:`_neighbour_valid`'s test, tabulated: the
    candidates of a frame are integer pixels)."""
    geo = _geo(*key)
    reach = geo.radius + 1.0
    R = int(math.ceil(geo.half * math.sqrt(2) + reach))
    o = np.arange(-R, R + 1, dtype=np.float64)
    ox = geo.dx[None, None, :] - o[None, :, None]
    oy = geo.dy[None, None, :] - o[:, None, None]
    d2_o = ox * ox + oy * oy
    bad = (d2_o < (geo.dx * geo.dx + geo.dy * geo.dy)[None, None, :]) & (d2_o <= reach * reach)
    good = ~bad
    good.setflags(write=False)
    return R, good


def _neighbour_valid(xy: np.ndarray, others: np.ndarray | None, ix, iy, geo: _Geo) -> np.ndarray | None:
    """Per patch (N, P*P), False on the pixels nearer to another marker than to this one and
    within the window radius + 1 of it: a neighbour is neither fitted nor background.
    ``xy`` are the patch centres (``ix, iy`` as floats)."""
    if others is None or len(others) < 2:
        return None
    others = np.asarray(others, float).reshape(-1, 2)
    reach = geo.radius + 1.0
    k, j = _pairs_within(xy, others, geo.half * math.sqrt(2) + reach)
    if len(k) == 0:
        return None
    o = others[j] - xy[k]                          # the neighbours' offsets
    other = np.abs(o).max(axis=1) >= 0.5           # not the marker itself
    if not other.all():
        k, j, o = k[other], j[other], o[other]
        if len(k) == 0:
            return None
    oi = np.rint(o)
    if (oi == o).all() and _neighbour_table_size(geo) <= _NEIGHBOUR_TABLE_MAX:
        # integer offsets (the candidates of a frame): the masks are tabulated; one AND over
        # each marker's run of neighbours (k sorted: the dense pairs are; the KD-tree's not)
        R, table = _neighbour_table(geo.key)
        oi = oi.astype(np.intp) + R
        if len(k) > 1 and (k[1:] < k[:-1]).any():
            order = np.argsort(k, kind="stable")
            k, oi = k[order], oi[order]
        good = table[oi[:, 1], oi[:, 0]]
        first = np.flatnonzero(np.concatenate(([True], k[1:] != k[:-1])))
        out = np.ones((len(xy), len(geo.dx)), bool)
        out[k[first]] = np.logical_and.reduceat(good, first, axis=0)
        return out
    px = ix[k, None] + geo.dx[None]
    py = iy[k, None] + geo.dy[None]
    ox, oy = px - others[j, 0, None], py - others[j, 1, None]
    sx, sy = px - xy[k, 0, None], py - xy[k, 1, None]
    d2_o = ox * ox + oy * oy                      # squared distances: the same comparisons, no roots
    bad = (d2_o < sx * sx + sy * sy) & (d2_o <= reach * reach)
    acc = np.zeros((len(xy), len(geo.dx)), bool)
    np.logical_or.at(acc, k, bad)
    return ~acc


def _pairs_within(a: np.ndarray, b: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) with ``|a[i] - b[j]| <= r``: a dense distance matrix for the few
    points of a frame's windows (far cheaper than building KD-trees), KD-trees for many."""
    if len(a) * len(b) <= 4096:
        d = a[:, None, :] - b[None, :, :]
        d *= d
        return np.nonzero(d.sum(axis=-1) <= r * r)
    from scipy.spatial import cKDTree
    pairs = cKDTree(a).sparse_distance_matrix(cKDTree(b), r, output_type="ndarray")
    return pairs["i"], pairs["j"]


def _masked_median(v: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median of each row of ``v`` over its ``mask`` entries (NaN for an empty row); a sort
    instead of ``np.nanmedian``, which loops in Python."""
    return _row_median(v, _median_rows(mask, v.shape))


def _median_rows(mask: np.ndarray | None, shape) -> tuple | None:
    """Where the middle pair of each row's ``mask`` entries lies once the row is sorted with
    the other entries (+inf) last: flat indices (lo, hi) and the empty rows (None if none);
    None for a mask that keeps everything.  Shared by the medians over one mask."""
    if mask is None or mask.all():
        return None
    n, m = shape
    k = mask.sum(axis=1)
    base = np.arange(0, n * m, m)
    hi = base + k // 2
    lo = base + np.maximum(k - 1, 0) // 2
    return mask, lo, hi, (k == 0) if k.min() == 0 else None


def _row_median(v: np.ndarray, rows: tuple | None) -> np.ndarray:
    """Median of each row of ``v`` (N, M) over the entries :func:`_median_rows` describes (the
    values of ``np.median``: the mean of the middle pair)."""
    if rows is None:
        m = v.shape[1]
        srt = np.sort(v, axis=1)
        return 0.5 * (srt[:, (m - 1) // 2] + srt[:, m // 2])
    mask, lo, hi, empty = rows
    srt = np.sort(np.where(mask, v, np.inf), axis=1).ravel()
    out = 0.5 * (srt[lo] + srt[hi])
    if empty is not None:
        out[empty] = np.nan
    return out


def _plane_removed(p: np.ndarray, geo: _Geo, sign: float, valid: np.ndarray | None) -> np.ndarray:
    """Patches with a background plane removed, markers positive (N, P*P).

    The plane is fitted to the pixels of the outer ring (``valid`` ones only) that are
    background: first those within 3 robust sd of the ring's median level (a dark
    instrument or a bone edge reaching into the ring is left out from the start), then,
    once more, those within 3 robust sd of the fitted plane.  The compiled kernel where it
    is built (:data:`_kernels`), else (and for a singular system) :func:`_plane_removed_numpy`.
    """
    if _kernels is not None:
        p = np.ascontiguousarray(p, dtype=np.float64)
        out = np.empty_like(p)
        singular = _kernels.plane_removed(p, p.shape[0], p.shape[1], geo.ring_idx, geo.dx, geo.dy,
                                          None if valid is None else np.ascontiguousarray(valid, dtype=np.uint8),
                                          float(sign), _MAD, float(_EYE3_TINY[0, 0]), out)
        if not singular:
            return out
    return _plane_removed_numpy(p, geo, sign, valid)


def _plane_removed_numpy(p: np.ndarray, geo: _Geo, sign: float, valid: np.ndarray | None) -> np.ndarray:
    """:func:`_plane_removed` in NumPy (the reference the compiled kernel is tested against)."""
    A = geo.A_ring                                                     # (R, 3)
    r = p[:, geo.ring_idx]                                             # (N, R)
    w0 = None if valid is None else valid[:, geo.ring_idx]
    if w0 is not None and w0.all():
        w0 = None
    rows = _median_rows(w0, r.shape)
    med = _row_median(r, rows)
    dev = np.abs(r - med[:, None])
    mad = _MAD * _row_median(dev, rows)
    mad = np.where(mad > 0, mad, np.inf)                               # 0 or NaN: no limit
    w = dev <= (3 * mad + 1e-9)[:, None]
    if w0 is not None:
        w &= w0
    for it in range(2):
        # normal equations A^T W A and A^T W r as two plain matrix products: the weights are 0/1
        # and A holds small integers, so for 8/16-bit pixels every product and sum is exact
        # and the values do not depend on the order of summation (float frames: to rounding)
        wf = w.astype(np.float64)
        M = (wf @ geo.AA_ring).reshape(-1, 3, 3) + _EYE3_TINY
        b = ((wf * r) @ A)[:, :, None]
        coef = _solve(M, b)[..., 0]
        if it == 1:
            break
        res = r - coef @ A.T
        rows = _median_rows(w, r.shape)
        sd = _MAD * _row_median(np.abs(res - _row_median(res, rows)[:, None]), rows)
        sd = np.where(sd > 0, sd, np.inf)
        new = np.abs(res) <= (3 * sd + 1e-9)[:, None]
        if w0 is not None:
            new &= w0
        # keep at least the pixels of the first selection if the new one collapses
        enough = new.sum(axis=1) >= 6
        w = new if enough.all() else np.where(enough[:, None], new, w)
    return sign * (coef @ geo.A.T - p)


#: The edge background (:func:`_edge_background`): its knots' spacing (px, across the edge),
#: the weight of their second-difference penalty (it ties knots the ring
#: hardly reaches and keeps a profile from following the noise), the F test's false-alarm rate
#: per marker on a background a plane describes, how far beyond a neighbour's signal its pixels
#: are left out of the ring (px), the share of the ring a neighbour may take before the plane is
#: kept, how far above the ring's pixel noise the profile's residual may be (sd), and the
#: profile's range over the ring against the marker's own depth.
_EDGE_KNOT_PX = 1.5
_EDGE_SMOOTH = 0.3
_EDGE_ALPHA = 1e-4
_EDGE_NEIGHBOUR_PAD_PX = 2.0
_EDGE_MAX_CROWDED = 0.2
_EDGE_MAX_RESIDUAL = 1.5
_EDGE_MAX_RANGE = 1.0


@functools.lru_cache(maxsize=8)
def _edge_geo(key: tuple) -> tuple:
    """For the geometry ``_geo(*key)``: the ring pixels whose four neighbours are ring pixels
    too (where the ring's gradients and noise are taken), the knots' half count ``K`` (knots
    at ``-K..K`` times :data:`_EDGE_KNOT_PX` across the edge, reaching the patch's corners),
    their number and the penalty matrix."""
    geo = _geo(*key)
    P = 2 * geo.half + 1
    r = geo.ring.reshape(P, P)
    ok = np.zeros((P, P), bool)
    ok[1:-1, 1:-1] = r[1:-1, 1:-1] & r[1:-1, 2:] & r[1:-1, :-2] & r[2:, 1:-1] & r[:-2, 1:-1]
    K = int(math.ceil(geo.half * math.sqrt(2.0) / _EDGE_KNOT_PX)) + 1
    nk = 2 * K + 1
    d2 = np.diff(np.eye(nk), 2, axis=0)
    out = (np.flatnonzero(ok.ravel()), K, nk, _EDGE_SMOOTH * (d2.T @ d2) + 1e-6 * np.eye(nk))
    for x in out:
        if isinstance(x, np.ndarray):
            x.setflags(write=False)
    return out


def _hat_fit(k: np.ndarray, f: np.ndarray, w: np.ndarray, v: np.ndarray, nk: int, pen: np.ndarray):
    """Penalised least squares of piecewise-linear profiles, one per row: pixel ``j`` of row
    ``i`` lies between knots ``k[i, j]`` (flat over the rows' ``nk`` knots each) and
    ``k[i, j] + 1``, a fraction ``f`` of the way, with weight ``w``; ``v`` its value.  The
    normal equations are tridiagonal plus the penalty ``pen``, summed pixel by pixel
    (``np.bincount``).  Returns the knots (flat) and the weight each knot got (rows, nk)."""
    kk = np.arange(nk)
    size = len(k) * nk
    kf, fr = k.ravel(), f.ravel()
    a, b = (w * (1.0 - f)).ravel(), (w * f).ravel()
    d = np.bincount(kf, a * (1.0 - fr), size) + np.bincount(kf + 1, b * fr, size)
    off = np.bincount(kf, a * fr, size).reshape(-1, nk)
    rhs = np.bincount(kf, a * v.ravel(), size) + np.bincount(kf + 1, b * v.ravel(), size)
    M = np.repeat(pen[None], len(k), axis=0)
    M[:, kk, kk] += d.reshape(-1, nk)
    M[:, kk[:-1], kk[1:]] += off[:, :-1]
    M[:, kk[1:], kk[:-1]] += off[:, :-1]
    reach = (np.bincount(kf, a, size) + np.bincount(kf + 1, b, size)).reshape(-1, nk)
    return _solve(M, rhs.reshape(-1, nk, 1)).reshape(-1), reach


def _hat_value(c: np.ndarray, k: np.ndarray, f: np.ndarray) -> np.ndarray:
    return c[k] * (1.0 - f) + c[k + 1] * f


def _edge_background(p: np.ndarray, geo: _Geo, valid: np.ndarray | None, xy: np.ndarray | None = None,
                     others: np.ndarray | None = None,
                     noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A background under each marker that varies across one direction only, where it
    explains the ring of pixels around the marker and a plane does not.

    A marker on the edge of a bone, of the skull's rim or of an instrument, or beside a thin
    line, sits on a background no plane describes: what the plane leaves under the marker is
    darker on one side and pulls its centre that way (the twin's 1 mm reference markers, in
    the skull's rim: 0.14 px RMS, across the rim).  Locally such a background is constant
    along the edge, a profile ``b(u)`` of the distance ``u`` across it: the edge's direction is
    the main axis of the ring's gradients (their structure tensor), and ``b`` is piecewise
    linear on knots :data:`_EDGE_KNOT_PX` apart with a second-difference penalty, fitted to
    the ring's valid pixels (the ring holds every ``u`` the marker covers, at both ends of its
    chord along the edge: ``b`` under the marker is interpolated, not extrapolated).

    Only markers whose ring the least-squares plane leaves with more than its pixel noise
    (``noise``, per marker, else a Laplacian's robust sd over the ring; by more than 3 sd of a
    variance from that many pixels) are looked at, and the profile replaces the plane where
    (1) an F test on the ring's residuals (the knots the ring reaches plus the angle, against
    the plane's three parameters) rejects the plane at :data:`_EDGE_ALPHA`, (2) the profile
    leaves no more than :data:`_EDGE_MAX_RESIDUAL` times the pixel noise (a blob leaves more:
    it is no edge), (3) other markers (``others``; ``xy`` the patches' centres) hold at
    most :data:`_EDGE_MAX_CROWDED` of the ring within their signal's reach plus
    :data:`_EDGE_NEIGHBOUR_PAD_PX` (those pixels are left out of the fits), and (4) the
    profile's range over the ring is at most :data:`_EDGE_MAX_RANGE` times the marker's own
    depth (an instrument's edge that dwarfs the marker stays the plane's: on the bench twin a
    bead hidden by the indentor's rod had been taken 3.3 px off, on the rod's edge).  On a flat
    background the plane's centres are kept to the bit.

    ``p`` (N, P*P): the raw patches.  Returns (background (N, P*P), chosen (N,) bool); rows not
    chosen are zero."""
    from scipy.special import fdtrc

    n, PP = p.shape
    P = 2 * geo.half + 1
    gi, K, nk, pen = _edge_geo(geo.key)
    ri = geo.ring_idx
    pr = p[:, ri]                                          # the ring's pixels (N, R)
    w = np.ones(pr.shape) if valid is None else valid[:, ri].astype(np.float64)
    crowded = np.zeros(n, bool)
    if others is not None and xy is not None and len(others) > 1:
        # a neighbour's pixels are its, not the background's
        o = np.asarray(others, float).reshape(-1, 2)
        reach = geo.ring_r_signal + _EDGE_NEIGHBOUR_PAD_PX
        i, j = _pairs_within(xy, o, reach + geo.half * math.sqrt(2.0))
        off = o[j] - xy[i]
        keep = np.abs(off).max(axis=1) >= 0.5             # not the marker itself
        if keep.any():
            i, off = i[keep], off[keep]
            near = (geo.dx[ri][None] - off[:, :1]) ** 2 + (geo.dy[ri][None] - off[:, 1:]) ** 2 <= reach * reach
            R = pr.shape[1]
            cell = (i[:, None] * R + np.arange(R)[None, :])[near]
            hit = np.bincount(cell, minlength=n * R).reshape(n, R) > 0
            crowded = hit.mean(axis=1) > _EDGE_MAX_CROWDED
            w = w * ~hit
    if noise is None:
        # a Laplacian's robust sd over the ring: smooth structure does not enter it
        lap = p[:, gi - 1] + p[:, gi + 1] + p[:, gi - P] + p[:, gi + P] - 4.0 * p[:, gi]
        sig = _MAD * _row_median(np.abs(lap - _row_median(lap, None)[:, None]), None) / math.sqrt(20.0)
    else:
        sig = noise
    sig = np.ascontiguousarray(np.broadcast_to(np.asarray(sig, np.float64), (n,)))
    fit = _edge_fit_compiled(p, geo, valid, w, crowded, sig) if _kernels is not None else None
    if fit is None:
        fit = _edge_fit_numpy(p, geo, valid, w, pr, crowded, sig)
    i, m, rssp, sig, c, cs, sn, rss1, k1, depth, span = fit
    out = np.zeros_like(p)
    chosen = np.zeros(n, bool)
    if len(i) == 0:
        return out, chosen
    d1, d2 = np.maximum(k1 - 3.0, 1.0), np.maximum(m - k1, 1.0)
    with np.errstate(all="ignore"):
        F = ((rssp - rss1) / d1) / (rss1 / d2)
        ok = np.isfinite(F) & (F > 0) & (m - k1 >= 10) & (fdtrc(d1, d2, F) < _EDGE_ALPHA)
        # (2) the profile leaves the ring's pixel noise only
        ok &= rss1 / d2 <= (_EDGE_MAX_RESIDUAL * sig) ** 2
        # (4) the edge is no deeper across the ring than the marker itself (its plane-removed
        # depth within 1 px of the centre): an instrument's edge that dwarfs the marker is left
        # to the plane, as a profile of it could carve a marker-like blob out of the edge
        ok &= span <= _EDGE_MAX_RANGE * depth
    if not ok.any():
        return out, chosen
    sel = np.flatnonzero(ok)
    chosen[i[sel]] = True
    k, f = _edge_knots(geo.dx, geo.dy, cs[sel], sn[sel], K, nk)
    out[i[sel]] = _hat_value(c[sel].reshape(-1), k, f)
    return out, chosen


def _edge_knots(dx: np.ndarray, dy: np.ndarray, cs: np.ndarray, sn: np.ndarray, K: int, nk: int):
    """Each pixel's knot to its left (flat over the rows' knots) and its share of the next, for
    rows whose edge normals are (``cs``, ``sn``) (N, 1), pixels at offsets ``dx, dy``."""
    us = (dx[None] * cs + dy[None] * sn) * (1.0 / _EDGE_KNOT_PX) + K
    k0 = np.floor(us)
    return k0.astype(np.intp) + (np.arange(len(us)) * nk)[:, None], us - k0


def _edge_fit_compiled(p, geo: _Geo, valid, w, crowded, sig):
    """:func:`_edge_fit_numpy`'s values from the compiled kernel (None where a system was
    singular or an angle not a number: then NumPy's path, which raises or goes on as before)."""
    gi, K, nk, pen = _edge_geo(geo.key)
    p = np.ascontiguousarray(p, dtype=np.float64)
    n = len(p)
    look = np.empty(n, np.uint8)
    coef, c = np.empty((n, 3)), np.empty((n, nk))
    m, rssp, cs, sn, rss1, k1, depth, span = (np.empty(n) for _ in range(8))
    singular = _kernels.edge_fit(
        p, n, p.shape[1], 2 * geo.half + 1, geo.ring_idx, gi, geo.near1, geo.dx, geo.dy,
        np.ascontiguousarray(w, dtype=np.float64), crowded.astype(np.uint8),
        None if valid is None else np.ascontiguousarray(valid, dtype=np.uint8), sig, K, nk,
        np.ascontiguousarray(pen, dtype=np.float64), _EDGE_KNOT_PX, float(_EYE3_TINY[0, 0]),
        look, coef, m, rssp, c, cs, sn, rss1, k1, depth, span)
    if singular:
        return None
    i = np.flatnonzero(look)
    return (i, m[i], rssp[i], sig[i], c[i], cs[i, None], sn[i, None], rss1[i], k1[i], depth[i], span[i])


def _edge_fit_numpy(p, geo: _Geo, valid, w, pr, crowded, sig):
    """The arithmetic of :func:`_edge_background` between its set-up and its decision, in NumPy
    (the reference the compiled kernel is tested against): the rows ``i`` looked at and, for
    them, the ring's weight ``m`` and plane residual ``rssp``, the noise, the profile's knots
    ``c`` (rows, nk), the edge's normal (``cs``, ``sn``), the profile's residual ``rss1``, the
    knots it reaches plus the angle ``k1``, the marker's depth under the plane and the
    profile's range over the ring."""
    n, PP = p.shape
    P = 2 * geo.half + 1
    gi, K, nk, pen = _edge_geo(geo.key)
    ri = geo.ring_idx
    # the least-squares plane on the ring's pixels against their noise: where it leaves no
    # more than noise (within 3 sd of a variance from this many pixels), nothing to look at
    A = geo.A_ring
    coef = _solve((w @ geo.AA_ring).reshape(-1, 3, 3) + _EYE3_TINY, ((w * pr) @ A)[:, :, None])[..., 0]
    plane = coef @ A.T
    m = w.sum(axis=1)
    rssp = (w * (pr - plane) ** 2).sum(axis=1)
    dfp = np.maximum(m - 3.0, 1.0)
    with np.errstate(all="ignore"):
        look = (rssp / dfp > sig ** 2 * (1.0 + 3.0 * np.sqrt(2.0 / dfp))) & ~crowded & (m >= 20)
    i = np.flatnonzero(look)
    if len(i) == 0:
        e = np.zeros(0)
        return i, e, e, e, np.zeros((0, nk)), e[:, None], e[:, None], e, e, e, e
    pi, pr, w, m, rssp, sig = p[i], pr[i], w[i], m[i], rssp[i], sig[i]
    # the edge's normal: the main axis of the ring's gradients
    gx = pi[:, gi + 1] - pi[:, gi - 1]
    gy = pi[:, gi + P] - pi[:, gi - P]
    wg = 1.0 if valid is None else valid[i][:, gi]
    jxx = (wg * gx * gx).sum(axis=1)
    jyy = (wg * gy * gy).sum(axis=1)
    jxy = (wg * gx * gy).sum(axis=1)
    th = 0.5 * np.arctan2(2.0 * jxy, jxx - jyy)
    cs, sn = np.cos(th)[:, None], np.sin(th)[:, None]
    k, f = _edge_knots(geo.dx[ri], geo.dy[ri], cs, sn, K, nk)
    c, reach_k = _hat_fit(k, f, w, pr, nk, pen)
    bg = _hat_value(c, k, f)
    rss1 = (w * (pr - bg) ** 2).sum(axis=1)
    k1 = (reach_k > 0.5).sum(axis=1) + 1.0            # the knots the ring reaches, and the angle
    with np.errstate(all="ignore"):
        depth = np.abs(coef[i] @ geo.A[geo.near1].T - pi[:, geo.near1]).max(axis=1)
        on = w > 0
        span = np.where(on, bg, -np.inf).max(axis=1) - np.where(on, bg, np.inf).min(axis=1)
    return i, m, rssp, sig, c.reshape(-1, nk), cs, sn, rss1, k1, depth, span


def _above_peak_excluded(s: np.ndarray, geo: _Geo, valid: np.ndarray | None) -> np.ndarray | None:
    """Leave out of a marker's fit the pixels whose signal rises well above the marker's own
    peak (within 1 px of the patch centre): they belong to something larger -- the shadow
    of an instrument the marker is passing, a bigger bead -- and would pull the centre.
    "Well above": by more than 3 robust sd of the ring's residual; one pixel of margin."""
    P = 2 * geo.half + 1
    peak = s[:, geo.near1].max(axis=1)
    above = s > peak[:, None]
    if not above.any():                # nothing above the peak at all: no noise estimate needed
        return valid
    noise = _robust_sd(s[:, geo.ring_idx], axis=1)
    hot = above & (s > (peak + 3 * noise)[:, None])
    if not hot.any():
        return valid
    h = hot.reshape(-1, P, P)
    g = h.copy()
    g[:, 1:, :] |= h[:, :-1, :]
    g[:, :-1, :] |= h[:, 1:, :]
    g[:, :, 1:] |= h[:, :, :-1]
    g[:, :, :-1] |= h[:, :, 1:]
    g = g.reshape(len(s), -1)
    g[:, geo.near1] = False
    return ~g if valid is None else valid & ~g


def _centroid(s: np.ndarray, geo: _Geo, n_iter: int = 6):
    """Iterated intensity-weighted centroid in a soft disc (1 inside ``radius``, 0 beyond
    ``radius + 1``: less pixel locking than a hard edge), on the pixels near the patch
    centre.  Returns offsets (N, 2) from the patch centre, the mass (sum of positive signal
    in the disc) and the axis ratio of the second moments.  The compiled kernel where it is
    built (:data:`_kernels`), else :func:`_centroid_numpy`: the same values to rounding."""
    if _kernels is None:
        return _centroid_numpy(s, geo, n_iter)
    s = np.ascontiguousarray(s, dtype=np.float64)
    n = s.shape[0]
    c, m, elong = np.empty((n, 2)), np.empty(n), np.empty(n)
    _kernels.centroid(s, n, s.shape[1], geo.support, geo.sup_xy[0], geo.sup_xy[1], geo.sup_w0, geo.radius,
                      n_iter, c, m, elong)
    return c, m, elong


def _centroid_numpy(s: np.ndarray, geo: _Geo, n_iter: int = 6):
    """:func:`_centroid` in NumPy (the reference the compiled kernel is tested against)."""
    sp = np.maximum(s[:, geo.support], 0.0)
    X, Y = geo.sup_xy[0], geo.sup_xy[1]
    n = s.shape[0]
    c = np.zeros((n, 2))
    r1 = geo.radius + 1.0
    lim = 1.5
    sh = np.empty((n, 2))                                  # the weighted offsets' sums
    for it in range(n_iter + 1):
        if it == 0:                                        # about the patch centre: weights known
            ddx = np.broadcast_to(X, sp.shape)
            ddy = np.broadcast_to(Y, sp.shape)
            w = np.multiply(sp, geo.sup_w0, order="C")     # (sp is column-major: C order as below)
        else:
            ddx = X - c[:, 0:1]
            ddy = Y - c[:, 1:2]
            dist = ddx * ddx
            dist += ddy * ddy
            np.sqrt(dist, out=dist)
            np.subtract(r1, dist, out=dist)
            w = _clamp(dist, 0.0, 1.0)
            w *= sp
        m = w.sum(axis=1)
        wdx = w * ddx
        wdx.sum(axis=1, out=sh[:, 0])
        wdy = w * ddy
        wdy.sum(axis=1, out=sh[:, 1])
        if (m > 0).all():
            mm = m
            nc = c + sh / m[:, None]
        else:
            pos = m > 0
            mm = np.where(pos, m, 1.0)
            nc = np.where(pos[:, None], c + sh / mm[:, None], c)
        # the window stays within the pixels kept (a marker is at most ~1 px off its peak pixel)
        c = _clamp(nc, -lim, lim)
    ixx = (wdx * ddx).sum(axis=1) / mm
    iyy = (wdy * ddy).sum(axis=1) / mm
    ixy = (wdx * ddy).sum(axis=1) / mm
    tr, det = ixx + iyy, ixx * iyy - ixy * ixy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    elong = np.sqrt((tr / 2 + disc) / np.maximum(tr / 2 - disc, 1e-12))
    return c, m, elong


def _radial_symmetry(s: np.ndarray, geo: _Geo, start: np.ndarray) -> np.ndarray:
    """Parthasarathy's (2012) radial-symmetry centre, offsets (N, 2) from the patch centre.

    Gradients at the pixel corners (2x2 differences, 3x3 smoothed) define lines through
    each corner; the centre minimises the weighted squared distance to them, weights
    ``|grad|^2 / distance to the centroid``, inside the marker's window.
    """
    n = s.shape[0]
    P = 2 * geo.half + 1
    q = s.reshape(n, P, P)
    gx = 0.5 * ((q[:, :-1, 1:] - q[:, :-1, :-1]) + (q[:, 1:, 1:] - q[:, 1:, :-1]))
    gy = 0.5 * ((q[:, 1:, :-1] - q[:, :-1, :-1]) + (q[:, 1:, 1:] - q[:, :-1, 1:]))
    k = np.ones((3, 3), np.float64) / 9.0
    gx = np.stack([cv2.filter2D(a, -1, k, borderType=cv2.BORDER_REPLICATE) for a in gx])
    gy = np.stack([cv2.filter2D(a, -1, k, borderType=cv2.BORDER_REPLICATE) for a in gy])
    ax = np.arange(-geo.half, geo.half, dtype=np.float64) + 0.5
    mx, my = np.meshgrid(ax, ax)
    g2 = gx * gx + gy * gy
    gn = np.sqrt(np.where(g2 > 0, g2, 1.0))
    nx, ny = np.where(g2 > 0, gx / gn, 0.0), np.where(g2 > 0, gy / gn, 0.0)
    dist = np.hypot(mx[None] - start[:, 0, None, None], my[None] - start[:, 1, None, None])
    w = np.where(dist <= geo.radius + 1.0, g2 / np.maximum(dist, 0.5), 0.0)
    # minimise sum w |(p - m) x n|^2: normal equations with the projector I - n n^T
    a11 = (w * (1 - nx * nx)).sum(axis=(1, 2))
    a12 = (w * (-nx * ny)).sum(axis=(1, 2))
    a22 = (w * (1 - ny * ny)).sum(axis=(1, 2))
    b1 = (w * (mx[None] * (1 - nx * nx) - my[None] * nx * ny)).sum(axis=(1, 2))
    b2 = (w * (-mx[None] * nx * ny + my[None] * (1 - ny * ny))).sum(axis=(1, 2))
    det = a11 * a22 - a12 * a12
    ok = det > 1e-12
    x = np.where(ok, (a22 * b1 - a12 * b2) / np.where(ok, det, 1), start[:, 0])
    y = np.where(ok, (a11 * b2 - a12 * b1) / np.where(ok, det, 1), start[:, 1])
    lim = geo.half - 1.0
    return np.column_stack([np.clip(x, -lim, lim), np.clip(y, -lim, lim)])


def _gaussian_fit(s: np.ndarray, geo: _Geo, start: np.ndarray, sigma0: float,
                  valid: np.ndarray | None = None, n_iter: int = 5):
    r"""Levenberg-Marquardt fit of :math:`A \exp(-((x-x_0)^2+(y-y_0)^2)/(2\sigma^2)) + c`
    to every patch, on the pixels within ``radius + 1`` of the start.  Returns (offsets
    (N, 2), amplitude, sigma, converged).  The compiled kernel where it is built
    (:data:`_kernels`), else :func:`_gaussian_fit_numpy`: the same values to rounding (the
    same steps, and the same stopping rule, taken over the whole batch)."""
    if _kernels is None:
        return _gaussian_fit_numpy(s, geo, start, sigma0, valid, n_iter)
    n = len(start)
    start = np.ascontiguousarray(start, dtype=np.float64)
    sup, X, Y = _fit_support(geo, start)
    P = np.empty((n, 5))
    _kernels.gaussian_fit(np.ascontiguousarray(s, dtype=np.float64), n, s.shape[1], sup, X, Y, start,
                          None if valid is None else np.ascontiguousarray(valid, dtype=np.uint8),
                          geo.radius, float(sigma0), float(geo.half), n_iter, P)
    return _gaussian_result(P, geo, start)


def _fit_support(geo: _Geo, start: np.ndarray):
    """The support pixels some patch's fit window reaches (within ``radius + 1`` of a start,
    ``start`` (N, 2) offsets from the patch centres; the others weigh nothing): their indices
    and x, y offsets (contiguous)."""
    reach = geo.radius + 1.0 + (float(np.hypot(start[:, 0], start[:, 1]).max()) if len(start) else 0.0)
    sel = geo.support_r <= reach + 1e-9
    return geo.support[sel], np.ascontiguousarray(geo.sup_xy[0, sel]), np.ascontiguousarray(geo.sup_xy[1, sel])


def _gaussian_result(P: np.ndarray, geo: _Geo, start: np.ndarray):
    """(offsets, amplitude, sigma, converged) from the fitted parameters ``P`` (N, 5)."""
    x0, y0, sig, amp = P[:, 0], P[:, 1], P[:, 2], P[:, 3]
    # a width that ran into its bound (the patch's half side) is no marker's: the fit spread
    # over something larger (an instrument's edge, a bone), whose "centre" means nothing
    ok = (np.hypot(x0 - start[:, 0], y0 - start[:, 1]) < max(1.5, 0.5 * geo.radius)) & (amp > 0) & np.isfinite(x0) \
        & (sig < geo.half)
    return P[:, :2], amp, sig, ok


def _gaussian_fit_numpy(s: np.ndarray, geo: _Geo, start: np.ndarray, sigma0: float,
                        valid: np.ndarray | None = None, n_iter: int = 5):
    r""":func:`_gaussian_fit` in NumPy (the reference the compiled kernel is tested against):
    every patch at once, batched 5x5 normal equations.

    Every patch's model, residual and Jacobian are kept between iterations and written in
    place; a step's cost comes with its model (one pass), so an iteration is about thirty
    small array operations."""
    n = len(start)
    sup, X, Y = _fit_support(geo, start)
    S = s[:, sup]
    K = S.shape[1]
    ex0 = X - start[:, 0:1]
    ey0 = Y - start[:, 1:2]
    dist = np.hypot(ex0, ey0)
    win = (dist <= geo.radius + 1.0).astype(np.float64)
    if valid is not None:
        win *= valid[:, sup]
    amp0 = np.maximum((S * (dist <= 1.0)).max(axis=1), 1e-6)
    P = np.empty((n, 5))
    P[:, :2] = start
    P[:, 2] = sigma0
    P[:, 3] = amp0
    P[:, 4] = 0.0
    lam = np.full(n, 1e-3)
    # the Jacobian's rows (N, 5, K), filled in place each iteration
    J = np.empty((n, 5, K))
    J[:, 4] = 1.0
    JT = J.transpose(0, 2, 1)
    W = win[:, None, :]

    def model(P, ex, ey):
        r2 = ex * ex
        r2 += ey * ey
        g = np.exp(r2 * (-0.5 / P[:, 2:3] ** 2))
        res = P[:, 3:4] * g
        res += P[:, 4:5]
        np.subtract(S, res, out=res)                   # data - model
        rw = win * res
        rw *= res
        return g, ex, ey, r2, res, rw.sum(axis=1)

    g, ex, ey, r2, res, cost = model(P, ex0, ey0)
    lim_sig = float(geo.half)
    with np.errstate(all="ignore"):
        for _ in range(n_iter):
            sig = P[:, 2:3]
            ags = P[:, 3:4] * g / sig ** 2
            np.multiply(ags, ex, out=J[:, 0])
            np.multiply(ags, ey, out=J[:, 1])
            np.multiply(ags / sig, r2, out=J[:, 2])
            J[:, 3] = g
            Jw = J * W
            H = Jw @ JT
            gv = Jw @ res[:, :, None]
            dg = H.reshape(n, 25)[:, ::6]                   # H + lam diag(H): Levenberg-Marquardt
            dg += lam[:, None] * (dg + 1e-12)
            step = _gesv(H, gv) if _gesv is not None else np.full(gv.shape, np.nan)
            if not math.isfinite(step.sum()):           # singular: np.linalg.solve raises
                try:
                    step = np.linalg.solve(H, gv)
                except np.linalg.LinAlgError:
                    break
            step = step[..., 0]
            cand = P + step
            cand[:, 2] = _clamp(cand[:, 2], 0.3, lim_sig)
            new = model(cand, X - cand[:, 0:1], Y - cand[:, 1:2])
            better = new[5] < cost
            if better.all():
                P = cand
                g, ex, ey, r2, res, cost = new
                lam *= 0.3
                if np.abs(step[:, :2]).max() < 1e-3 and (lam < 1e3).all():
                    break
            else:
                b1 = better[:, None]
                P = np.where(b1, cand, P)
                g, ex, ey, r2, res = (np.where(b1, a, o) for a, o in zip(new, (g, ex, ey, r2, res)))
                cost = np.where(better, new[5], cost)
                lam = np.where(better, lam * 0.3, lam * 10.0)
                if ((np.abs(step[:, :2]).max(axis=1) < 1e-3) | ~better).all() and (lam < 1e3).all():
                    break
    return _gaussian_result(P, geo, start)


#: Pixels this close to the intensifier field's edge (its half-level circle) or beyond are left
#: out of a marker's fits: the rim's fall to the dark surround is no marker's background.
FIELD_RIM_PX = 2.5


def _field_circle(fov: "FieldOfView | None") -> tuple[float, float, float] | None:
    """The circle (cx, cy, r) of the pixels a fit may use in ``fov``'s field (None: no field)."""
    if fov is None or not fov.found:
        return None
    return float(fov.centre_px[0]), float(fov.centre_px[1]), float(fov.radius_px) - FIELD_RIM_PX


def _in_field(ix: np.ndarray, iy: np.ndarray, geo: "_Geo", field) -> np.ndarray | None:
    """Per patch (N, P*P), False on the pixels outside the field's circle ``field``; None
    where every patch lies inside it."""
    if field is None or len(ix) == 0:
        return None
    cx, cy, r = field
    reach = geo.half * math.sqrt(2.0)
    if (np.hypot(ix - cx, iy - cy) + reach <= r).all():
        return None
    px = ix[:, None] + geo.dx[None, :] - cx
    py = iy[:, None] + geo.dy[None, :] - cy
    return px * px + py * py <= r * r


def _measure(img: np.ndarray, pts: np.ndarray, diameter_px: float, sign: float, st: DetectionSettings,
             others: np.ndarray | None, noise: np.ndarray | None = None, field=None) -> dict:
    """Sub-pixel measurement of candidates near the pixels ``pts`` (N, 2); arrays of
    :data:`COLUMNS` except ``snr`` and ``area_px``.  ``field``: the circle (cx, cy, r) of the
    intensifier's field (:func:`_field_circle`); pixels beyond it are neither the marker nor
    its background (a marker near the rim had been pulled towards the dark surround)."""
    blur = st.smooth_px(diameter_px)
    radius = st.window_px(diameter_px)
    geo = _geo(float(diameter_px), float(blur), float(radius))
    h, w = img.shape
    ixy = _clamp(np.rint(pts).astype(np.intp), 0, (w - 1, h - 1))
    ix, iy = ixy[:, 0], ixy[:, 1]
    xy = ixy.astype(float)
    valid = _neighbour_valid(xy, others, ix, iy, geo)
    inside = _in_field(ix, iy, geo, field)
    if inside is not None:
        valid = inside if valid is None else valid & inside
    raw = _gather(img, ix, iy, geo.half)
    s = _plane_removed(raw, geo, sign, valid)
    if st.background == "edge":
        bg, edge = _edge_background(raw, geo, valid, xy, others, noise)
        if edge.any():
            s = np.where(edge[:, None], sign * (bg - raw), s)
    valid = _above_peak_excluded(s, geo, valid)
    sv = s if valid is None else s * valid
    c, mass, elong = _centroid(sv, geo, 6 if st.method == "centroid" else 3)
    cen = ixy + c

    def disc_peak():
        # the peak of the signal within 1 px of the centroid (the support holds that disc and more)
        d = geo.sup_xy[None] - c[:, :, None]
        return (sv[:, geo.support] * (np.hypot(d[:, 0], d[:, 1]) <= 1.0)).max(axis=1)

    if st.method == "centroid":
        fin, amp, sigma = cen, disc_peak(), np.full(len(pts), np.nan)
    elif st.method == "radial":
        fin, amp, sigma = ixy + _radial_symmetry(sv, geo, c), disc_peak(), np.full(len(pts), np.nan)
    elif st.method == "gaussian":
        sig0 = math.sqrt((diameter_px / 4.0) ** 2 + blur ** 2)
        g, a, sg, ok = _gaussian_fit(s, geo, c, sig0, valid)
        if ok.all():
            fin, amp, sigma = ixy + g, a, sg
        else:
            fin = np.where(ok[:, None], ixy + g, np.nan)
            amp = np.where(ok, a, disc_peak())
            sigma = np.where(ok, sg, np.nan)
    else:
        raise ValueError(f"unknown centre method {st.method!r}")
    return {"x_px": fin[:, 0], "y_px": fin[:, 1], "amplitude": amp, "mass": mass,
            "sigma_px": sigma, "elongation": elong, "x_centroid_px": cen[:, 0], "y_centroid_px": cen[:, 1]}


def subpixel_centres(frame: np.ndarray, xy, diameter_px: float, polarity: Polarity = "dark",
                     settings: DetectionSettings = DetectionSettings(), others_xy=None, **kw) -> pd.DataFrame:
    """Sub-pixel centres of the markers nearest to the positions ``xy`` (N, 2).

    Measures on a patch around each rounded position (see the module docstring);
    ``others_xy`` (M, 2) are neighbouring markers whose pixels are left out.  Returns the
    :data:`COLUMNS` (``snr`` and ``area_px`` NaN: they need the noise and the blob);
    ``x_px``/``y_px`` are NaN where the Gaussian fit did not converge near its start.
    """
    st = settings.updated(**kw) if kw else settings
    pts = np.asarray(xy, float).reshape(-1, 2)
    if len(pts) == 0:
        return pd.DataFrame(columns=COLUMNS, dtype=float)
    m = _measure(np.asarray(frame), pts, diameter_px, 1.0 if polarity == "dark" else -1.0, st,
                 None if others_xy is None else np.asarray(others_xy, float).reshape(-1, 2))
    m["snr"] = np.full(len(pts), np.nan)
    m["area_px"] = np.full(len(pts), np.nan)
    return pd.DataFrame(m, columns=COLUMNS)


# --- candidates --------------------------------------------------------------------------------

@functools.lru_cache(maxsize=8)
def _quadric_design(radius: float):
    """For :func:`curvature_ratio`: the offsets (dy, dx) of the pixels within ``radius`` (row
    by row) and the transposed pseudo-inverse of the quadric design on them (read-only)."""
    R = int(math.ceil(radius))
    off = np.arange(-R, R + 1)
    X, Y = np.meshgrid(off.astype(float), off.astype(float))
    sel = np.hypot(X, Y) <= radius
    x, y = X[sel], Y[sel]
    pinv_t = np.linalg.pinv(np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])).T.copy()
    dy, dx = np.nonzero(sel)
    out = (dy - R, dx - R, pinv_t)
    for a in out:
        a.setflags(write=False)
    return out


def curvature_ratio(ts: np.ndarray, xs: np.ndarray, ys: np.ndarray, radius: float) -> np.ndarray:
    r"""How round each peak of ``ts`` is: the ratio of the smaller to the larger principal
    curvature (Hessian eigenvalue) of a quadratic surface fitted to the pixels within
    ``radius`` of the peak; 1 for a round blob, near 0 for a ridge.  The projection of a
    sphere is round; the top-hat's response along the edge of a bone or an instrument is a
    ridge.  0 where the peak is not a maximum of the fitted surface."""
    dy, dx, pinv_t = _quadric_design(float(radius))
    h, w = ts.shape
    c = ts[_clamp(ys[:, None] + dy, 0, h - 1), _clamp(xs[:, None] + dx, 0, w - 1)] @ pinv_t
    a, b, cc = c[:, 3], c[:, 4], c[:, 5]
    tr, det = 2 * a + 2 * cc, 4 * a * cc - b * b
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))
    l1, l2 = tr / 2 - disc, tr / 2 + disc            # l1 <= l2; a maximum has both < 0
    return np.where(l1 < 0, np.maximum(-l2, 0.0) / np.where(l1 < 0, -l1, 1.0), 0.0)


def _peaks(ts: np.ndarray, above: np.ndarray, diameter_px: float, floor: np.ndarray | float,
           st: DetectionSettings):
    """Local maxima of ``ts`` where ``above`` (one per plateau) and their half-maximum area
    (pixels within one diameter of the peak above half its height over ``floor``).
    ``floor`` may be an image (per-window floors).  Returns (x, y, area) arrays of the
    peaks whose area is plausible for a marker."""
    i = np.flatnonzero(above)
    ys, xs = np.divmod(i, ts.shape[1])
    return _peaks_at(ts, xs, ys, diameter_px, floor, st)


@functools.lru_cache(maxsize=8)
def _offsets_within(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (dy, dx) of the pixels within ``radius`` of a pixel, row by row (read-only)."""
    R = int(math.ceil(radius))
    off = np.arange(-R, R + 1)
    dy, dx = np.nonzero(np.hypot(off[None, :], off[:, None]) <= radius)
    dy, dx = dy - R, dx - R
    dy.setflags(write=False)
    dx.setflags(write=False)
    return dy, dx


def _peaks_at(ts: np.ndarray, xs: np.ndarray, ys: np.ndarray, diameter_px: float, floor: np.ndarray | float,
              st: DetectionSettings, region: "_Region | None" = None):
    """:func:`_peaks` on the pixels ``xs, ys`` (raster order) above the threshold: a pixel is a
    maximum when no pixel of the disk of side ``max(3, d)`` around it is higher (the test of
    ``ts >= cv2.dilate(ts, disk)``, made only where it can pass: no full-frame dilation), and
    in ``region`` (tested on the maxima only)."""
    k = max(3, int(round(diameter_px)) | 1)
    if len(xs):
        h, w = ts.shape
        dy, dx = _disk_offsets(k)
        # a maximum of the disk is one of its four neighbours' too (they are in the disk): that
        # cheap test first, the disk's on the few that pass.  Edge pixels clamp to the image: a
        # clamped neighbour is still inside the disk
        v = ts[ys, xs]
        pk = v >= ts[_clamp(ys[:, None] + _CROSS_DY, 0, h - 1), _clamp(xs[:, None] + _CROSS_DX, 0, w - 1)].max(axis=1)
        xs, ys, v = xs[pk], ys[pk], v[pk]
        nb = ts[_clamp(ys[:, None] + dy, 0, h - 1), _clamp(xs[:, None] + dx, 0, w - 1)]
        pk = v >= nb.max(axis=1)
        xs, ys = xs[pk], ys[pk]
        if region is not None and not region.everywhere and len(xs):
            ok = region.at(xs, ys)
            xs, ys = xs[ok], ys[ok]
    return _peak_areas(ts, xs, ys, diameter_px, floor, st)


def _peak_areas(ts: np.ndarray, xs: np.ndarray, ys: np.ndarray, diameter_px: float, floor: np.ndarray | float,
                st: DetectionSettings):
    """The maxima ``xs, ys`` (raster order) of :func:`_peaks_at`, one per plateau, with their
    half-maximum areas; those whose area is plausible for a marker.  ``floor``: a number,
    an image like ``ts``, or one value per column of ``ts`` (1-D)."""
    if len(xs) > 1:
        pts = np.column_stack([xs, ys]).astype(float)
        i, j = _pairs_within(pts, pts, 1.5)
        if len(i) > len(xs):                   # pairs besides each point with itself
            # a plateau of equal maxima gives several (touching) pixels: keep the first of each
            from scipy.sparse import coo_matrix
            from scipy.sparse.csgraph import connected_components
            _, lab = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(len(xs), len(xs))),
                                          directed=False)
            _, first = np.unique(lab, return_index=True)
            first.sort()
            xs, ys = xs[first], ys[first]
    if len(xs) == 0:
        return xs, ys, np.zeros(0)
    h, w = ts.shape
    dy, dx = _offsets_within(float(diameter_px))
    disc = ts[_clamp(ys[:, None] + dy, 0, h - 1), _clamp(xs[:, None] + dx, 0, w - 1)]
    fl = (floor[xs] if floor.ndim == 1 else floor[ys, xs]) if isinstance(floor, np.ndarray) else floor
    half = fl + 0.5 * (ts[ys, xs] - fl)
    area = (disc > half[:, None]).sum(axis=1).astype(float)
    max_area = st.max_area_factor * math.pi * diameter_px ** 2 + 12.0
    keep = (area >= st.min_area_px) & (area <= max_area)
    return xs[keep], ys[keep], area[keep]


def _finish(img, xs, ys, area, noise, diameter_px, polarity, st, mask=None, neighbours=None, field=None) -> dict:
    """Measure candidates, keep the good ones, merge duplicates.  Arrays of COLUMNS.
    ``neighbours`` (default: the candidates) are the markers masked out of each fit;
    ``field`` the circle of the intensifier's field (:func:`_measure`)."""
    pts = np.column_stack([xs, ys]).astype(float)
    if len(pts) == 0:
        return {c: np.zeros(0) for c in COLUMNS}
    noise = np.asarray(noise, float)
    m = _measure(img, pts, diameter_px, 1.0 if polarity == "dark" else -1.0, st,
                 pts if neighbours is None else neighbours, noise, field)
    m["area_px"] = np.asarray(area, float)
    m["snr"] = m["amplitude"] / np.maximum(noise, 1e-9)
    keep = np.isfinite(m["x_px"]) & (m["snr"] >= st.min_snr) & (m["elongation"] <= st.max_elongation)
    if st.max_sigma_factor is not None:
        # a Gaussian this wide (half-maximum width 1.8 d at the default 0.75) is not a bead of
        # diameter d seen through the blur, but something larger the fit spread over (the
        # smear a video codec leaves of a faint bead, an instrument's corner, bone)
        with np.errstate(invalid="ignore"):
            keep &= ~(m["sigma_px"] > st.max_sigma_factor * diameter_px)
    # a marker cut by the image border has no trustworthy centre
    h, w = img.shape
    b = min(0.5 * diameter_px, st.window_px(diameter_px))
    with np.errstate(invalid="ignore"):
        keep &= (m["x_px"] >= b - 0.5) & (m["x_px"] <= w - 0.5 - b) & (m["y_px"] >= b - 0.5) & (m["y_px"] <= h - 0.5 - b)
    if mask is not None and keep.any():
        h, w = img.shape
        xi = np.clip(np.rint(np.nan_to_num(m["x_px"])).astype(int), 0, w - 1)
        yi = np.clip(np.rint(np.nan_to_num(m["y_px"])).astype(int), 0, h - 1)
        keep &= mask.at(xi, yi) if isinstance(mask, _Region) else mask[yi, xi]
    if not keep.all():
        m = {k: v[keep] for k, v in m.items()}
    return _dedupe(m, 0.5 * diameter_px)


def _dedupe(m: dict, min_sep_px: float) -> dict:
    """Two candidates that converged on one marker: keep the stronger."""
    n = len(m["x_px"])
    if n < 2:
        return m
    xy = np.column_stack([m["x_px"], m["y_px"]])
    i, j = _pairs_within(xy, xy, min_sep_px)
    if len(i) == n:                    # each candidate with itself only
        return m
    pairs = np.column_stack([i, j])[i < j]
    if len(pairs) == 0:
        return m
    amp = m["amplitude"]
    drop = np.zeros(n, bool)
    for i, j in pairs:
        drop[j if amp[i] >= amp[j] else i] = True
    return {k: v[~drop] for k, v in m.items()}


def dark_objects(img: np.ndarray, diameter_px: float, grow_px: int = 2) -> np.ndarray:
    """Mask (h, w) of large radio-opaque objects -- instruments, lead letters -- grown by
    ``grow_px`` (their blurred edge): regions darker than half their surroundings (a grey
    closing with a disk 16 marker diameters wide, on a copy reduced by about a diameter)
    and larger than a disc twice the marker's diameter.  A steel bead is far smaller; the
    top-hat's responses in such objects' texture are not markers.  A marker next to an
    instrument is kept (the blob-shape and above-peak rules deal with the edge itself).
    (Detection itself tests the objects at points, :class:`_DarkObjects`, without this mask.)"""
    d = _DarkObjects.find(img, diameter_px, grow_px)
    h, w = np.asarray(img).shape
    if d is None:
        return np.zeros((h, w), bool)
    m = cv2.resize(d.small.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
    return cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d.kk, d.kk))) > 0


@functools.lru_cache(maxsize=16)
def _ellipse(k: int) -> np.ndarray:
    """``cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))`` (read-only)."""
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    se.setflags(write=False)
    return se


@functools.lru_cache(maxsize=16)
def _disk_offsets(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (dy, dx) of the pixels of :func:`_ellipse` ``(k)`` from its centre (read-only)."""
    dy, dx = np.nonzero(_ellipse(k))
    dy, dx = dy - k // 2, dx - k // 2
    dy.setflags(write=False)
    dx.setflags(write=False)
    return dy, dx


def _area_reduced(a: np.ndarray, f: int) -> np.ndarray:
    """``cv2.resize(a, (w // f, h // f), interpolation=cv2.INTER_AREA)``.  For 8-bit frames whose
    sides are multiples of ``f`` = 4, 8 or 16 the same values from block sums (OpenCV's area
    reduction by an integer factor rounds sum / f^2 to the nearest integer, ties to even,
    exactly what ``cv2.multiply`` does to the sums; ``f^2`` a power of two, no rounding
    before that), a quarter cheaper than OpenCV's scalar loop."""
    h, w = a.shape
    if a.dtype == np.uint8 and f in (4, 8, 16) and h % f == 0 and w % f == 0:
        r = a.reshape(h // f, f, w).sum(axis=1, dtype=np.uint16)          # column sums of each block row
        if f == 4 and _LITTLE_ENDIAN:
            # four 16-bit sums a 64-bit word (little-endian lanes): add them into the lowest lane
            q = r.view(np.uint64)
            q = q + (q >> 32)
            q += q >> 16
            c = np.ascontiguousarray(q.view(np.uint16)[:, ::4])
        else:
            c = r[:, 0::f] + r[:, 1::f]
            for i in range(2, f):
                c += r[:, i::f]
        return cv2.multiply(c, 1.0 / (f * f), dtype=cv2.CV_8U)
    return cv2.resize(a, (max(w // f, 1), max(h // f, 1)), interpolation=cv2.INTER_AREA)


class _DarkObjects:
    """:func:`dark_objects` kept at the reduced size: ``small`` (hs, ws) bool, reduced pixel
    (i, j) standing for full pixels [i f, (i + 1) f) x [j f, (j + 1) f), grown at full size by
    a disk of side ``kk``.  :meth:`at` is exact at full-size points; :meth:`grid` is a
    slightly wider (never narrower) mask for sampling statistics."""

    def __init__(self, small: np.ndarray, f: int, kk: int, shape):
        self.small, self.f, self.kk, self.shape = small, f, kk, shape
        reach = kk // 2
        rr = -(-reach // f)                          # the growth in reduced pixels, rounded up
        self.coarse = cv2.dilate(small.view(np.uint8), np.ones((2 * rr + 1, 2 * rr + 1), np.uint8)) > 0
        self.dy, self.dx = _disk_offsets(kk)

    @classmethod
    def find(cls, img: np.ndarray, diameter_px: float, grow_px: int = 2,
             depth: float | None = None) -> "_DarkObjects | None":
        """The objects of a frame (None when there are none).  The reduced copy is made in the
        frame's own dtype (8/16-bit: area means rounded to whole grey levels).  ``depth``:
        dark where more than this below the surroundings (grey levels) or below half of them,
        instead of the latter alone (a log-converted frame's instrument is not darker than
        half its surroundings, but far deeper than a bead)."""
        a = np.asarray(img)
        if a.dtype not in (np.uint8, np.uint16, np.float32):
            a = a.astype(np.float32)
        h, w = a.shape
        f = max(1, int(diameter_px))
        small = _area_reduced(a, f)
        k = max(3, int(round(16 * diameter_px / f)) | 1)
        bg = cv2.morphologyEx(small, cv2.MORPH_CLOSE, _ellipse(k), borderType=cv2.BORDER_REPLICATE)
        if small.dtype == np.float32:
            dark = (small < 0.5 * bg) & (bg > 0)
        else:                                        # integers: 2 small < bg, exactly (so bg > 0)
            dark = 2 * small.astype(np.int16 if small.dtype == np.uint8 else np.int32) < bg
        if depth is not None:
            dark |= (bg.astype(np.float32) - small.astype(np.float32)) > depth
        dark = dark.view(np.uint8)
        # the components within the dark pixels' bounding box (labels and areas as in the whole)
        x0, y0, bw, bh = cv2.boundingRect(dark)
        if bw == 0:
            return None
        box = dark[y0:y0 + bh, x0:x0 + bw]
        # 16-bit labels when they cannot run out (8-connected components: at most one per 2 x 2
        # block): three times faster than 32-bit ones in OpenCV
        ltype = cv2.CV_16U if ((bh + 1) // 2) * ((bw + 1) // 2) < 65535 else cv2.CV_32S
        n, lab, stats, _ = cv2.connectedComponentsWithStats(box, connectivity=8, ltype=ltype)
        big = stats[:, cv2.CC_STAT_AREA] * f * f > math.pi * (2 * diameter_px) ** 2
        big[0] = False
        if not big.any():
            return None
        if big[1:].all():              # every component big (the usual case): the dark pixels
            small = dark.view(bool)
        else:
            small = np.zeros(dark.shape, bool)
            small[y0:y0 + bh, x0:x0 + bw] = np.take(big, lab)
        return cls(small, f, 2 * (grow_px + f // 2) + 1, (h, w))

    def _block(self, xs, ys):
        hs, ws = self.small.shape
        h, w = self.shape
        # the reduced pixel of full pixels 0 ... h - 1 (0 ... w - 1); when the sides are whole
        # multiples of f that is a plain division
        by = ys // self.f if h == hs * self.f else np.minimum(ys * hs // h, hs - 1)
        bx = xs // self.f if w == ws * self.f else np.minimum(xs * ws // w, ws - 1)
        return by, bx

    def core_at(self, xs, ys) -> np.ndarray:
        """Whether full-size pixels (xs, ys) (integer arrays) lie in an object itself (its
        reduced pixel dark; not grown)."""
        by, bx = self._block(np.asarray(xs), np.asarray(ys))
        return self.small[by, bx]

    def at(self, xs, ys) -> np.ndarray:
        """Whether full-size pixels (xs, ys) (integer arrays that broadcast) are in a grown object."""
        xs, ys = np.asarray(xs), np.asarray(ys)
        if xs.shape != ys.shape:
            xs, ys = np.broadcast_arrays(xs, ys)
        by, bx = self._block(xs, ys)
        near = self.coarse[by, bx]
        if not near.any():
            return near
        out = np.zeros(xs.shape, bool)
        x, y = xs[near].ravel(), ys[near].ravel()
        h, w = self.shape
        px, py = x[:, None] + self.dx[None], y[:, None] + self.dy[None]
        r = self.kk // 2
        if x.min() >= r and y.min() >= r and x.max() < w - r and y.max() < h - r:
            by, bx = self._block(px, py)                 # every disk inside the image
            out[near] = self.small[by, bx].any(axis=1)
            return out
        inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
        by, bx = self._block(_clamp(px, 0, w - 1), _clamp(py, 0, h - 1))
        out[near] = (self.small[by, bx] & inside).any(axis=1)
        return out

    def grid(self, ys, xs) -> np.ndarray:
        by, bx = self._block(xs, ys)
        if by.ndim == 2 and by.shape[1] == 1 and bx.ndim == 2 and bx.shape[0] == 1:
            # a grid (a column of ys, a row of xs): rows, then columns (no 2-D index arrays)
            return np.take(np.take(self.coarse, by[:, 0], axis=0), bx[0], axis=1)
        return self.coarse[by, bx]


class _Region:
    """Where markers are looked for in a frame: inside the field of view (``margin`` from its
    edge, or from the image border when no field was found and ``border`` is set), inside a
    given mask, and outside dark objects.  Tested on a sampling grid (for the statistics) and
    at points (for the candidates); no full-size mask is built for a field of view.
    ``None`` parts impose nothing."""

    def __init__(self, shape, fov: FieldOfView | None = None, margin: float = 0.0, border: bool = False,
                 mask: np.ndarray | None = None, dark: np.ndarray | None = None):
        self.shape, self.fov, self.margin, self.border = shape, fov, float(margin), border
        if fov is not None and fov.region is not None:
            # a region drawn by the user: its pixels only (the field's circle and border as well)
            r = np.asarray(fov.region, bool)
            mask = r if mask is None else (np.asarray(mask, bool) & r)
        self.mask, self.dark = mask, dark

    @property
    def everywhere(self) -> bool:
        return ((self.fov is None or (not self.fov.found and not self.border)) and self.mask is None
                and self.dark is None)

    def grid(self, y0: int, x0: int, step: int) -> np.ndarray | None:
        """Bool mask of pixels ``[y0::step, x0::step]`` (None: all).  The field-of-view part is
        the same in every frame of a sequence: kept (read-only) between calls."""
        if self.everywhere:
            return None
        h, w = self.shape
        ys = np.arange(y0, h, step)[:, None]
        xs = np.arange(x0, w, step)[None, :]
        if self.mask is None:
            try:
                ok = _fov_grid(tuple(self.shape), self.fov, self.margin, self.border, y0, x0, step)
            except TypeError:                        # a FieldOfView built with lists: not hashable
                ok = _Region(self.shape, self.fov, self.margin, self.border).at(xs, ys)
        else:
            ok = self.at(xs, ys, coarse=True) if self.dark is None else \
                _Region(self.shape, self.fov, self.margin, self.border, self.mask).at(xs, ys)
        if self.dark is not None:
            ok = ok & ~self.dark.grid(ys, xs)
        return ok

    def at(self, xs, ys, coarse: bool = False) -> np.ndarray:
        """Whether the pixels (xs, ys) (integer arrays that broadcast) are in the region
        (``coarse``: dark objects grown a little wider, for sampling statistics)."""
        sx, sy = np.shape(xs), np.shape(ys)
        ok = np.ones(sx if sx == sy else np.broadcast_shapes(sx, sy), bool)
        if self.fov is not None:
            h, w = self.shape
            if self.fov.found:
                cx, cy = self.fov.centre_px
                ok &= (xs - cx) ** 2 + (ys - cy) ** 2 <= (self.fov.radius_px - self.margin) ** 2
            elif self.border:
                b = int(math.ceil(self.margin))
                ok &= (xs >= b) & (xs < w - b) & (ys >= b) & (ys < h - b)
        if self.mask is not None:
            ok &= self.mask[ys, xs]
        if self.dark is not None:
            ok &= ~(self.dark.grid(ys, xs) if coarse else self.dark.at(xs, ys))
        return ok


@functools.lru_cache(maxsize=8)
def _fov_grid(shape, fov, margin, border, y0, x0, step) -> np.ndarray:
    """The field-of-view and border part of :meth:`_Region.grid` (read-only)."""
    h, w = shape
    ok = _Region(shape, fov, margin, border).at(np.arange(x0, w, step)[None, :], np.arange(y0, h, step)[:, None])
    ok.setflags(write=False)
    return ok


def _region(img: np.ndarray, roi, margin: float, diameter_px: float = 4.0, polarity: Polarity = "dark",
            dark: bool | None = None) -> _Region:
    """The :class:`_Region` ``roi`` names (see :func:`detect_markers`); ``dark``: leave out
    :func:`dark_objects` (default: for dark markers when the field is found automatically)."""
    if isinstance(roi, str):
        if roi not in ("auto", "none"):
            raise ValueError(f"roi must be 'auto', 'none', a FieldOfView or a mask, got {roi!r}")
        if roi == "none":
            return _Region(img.shape, dark=_DarkObjects.find(img, diameter_px) if dark else None)
    if dark is None:
        dark = polarity == "dark" and (roi is None or isinstance(roi, str))
    dk = _DarkObjects.find(img, diameter_px) if dark else None
    if roi is None or isinstance(roi, str):
        return _Region(img.shape, find_field_of_view(img), margin, border=False, dark=dk)
    if isinstance(roi, FieldOfView):
        return _Region(img.shape, roi, margin, border=True, dark=dk)
    m = np.asarray(roi, bool)
    if m.shape != img.shape:
        raise ValueError(f"roi mask has shape {m.shape}, frame {img.shape}")
    if margin > 0:
        k = 2 * int(math.ceil(margin)) + 1
        m = cv2.erode(m.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
    return _Region(img.shape, mask=m, dark=dk)


# --- trackpy parity ------------------------------------------------------------------------------

def _trackpy_gaussian_kernel(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """trackpy's 1-D discretised Gaussian: ``exp(-x^2 / 2 sigma^2)`` on
    ``|x| <= int(truncate sigma + 0.5)``, normalised to sum 1."""
    lw = int(truncate * sigma + 0.5)
    x = np.arange(-lw, lw + 1)
    k = np.exp(x ** 2 / (-2 * sigma ** 2))
    return k / k.sum()


def locate_trackpy(frame: np.ndarray, diameter_px: int, polarity: Polarity = "dark", *, minmass: float = 0.0,
                   separation: int | None = None, noise_size: float = 1.0, smoothing_size: int | None = None,
                   threshold: float | None = None, percentile: float = 64.0, max_iterations: int = 10,
                   shift_thresh: float = 0.6) -> pd.DataFrame:
    r"""trackpy's ``locate`` (v0.7, 2-D, its Python engine), step for step: bsipipe's
    centroid parity mode, to reproduce a trackpy user's positions (``DetectionSettings(parity=
    "trackpy", method="centroid")``).

    1. Dark features (``polarity="dark"``, trackpy's ``invert=True``): integer images become
       ``max XOR image`` (``max - image``), floats ``1 - image``.
    2. Band pass: a Gaussian (``noise_size``, kernel to ``int(4 sigma + 0.5)``, zero outside)
       of the image minus its boxcar mean over ``smoothing_size`` (default the diameter;
       computed in the image's own dtype, so an 8-bit boxcar is an integer), values below
       ``threshold`` (1, or 1/255 for floats) set to 0.
    3. Rescaled to the integer range of the input's dtype (uint8 for floats) and truncated.
    4. Local maxima: pixels equal to their grey dilation over a square of side
       ``int(2 separation / sqrt 2)`` (``separation`` default diameter + 1), above the
       ``percentile`` of the non-zero pixels, at least ``max(r, separation // 2 - 1,
       smoothing_size // 2)`` from the edge (``r = diameter // 2``).
    5. Centre: the centre of mass of the rescaled band pass in a disc of radius ``r`` around
       the integer position, the disc moved by one pixel along each axis where the centre is
       more than ``shift_thresh`` off, up to ``max_iterations`` times; ``mass`` the sum in
       the last disc.
    6. Of two features closer than ``separation`` the one of lower mass is dropped; ``mass``
       is divided by the rescaling factor and features with ``mass <= minmass`` dropped.

    Returns :data:`COLUMNS` (``amplitude`` = the disc's peak, ``mass``, the rest NaN) sorted
    by y then x.  Unlike :func:`detect_markers` there is no noise model: the positions are
    trackpy's, estimator quirks included (pixel locking of the integer disc).
    """
    from scipy import ndimage

    img = np.asarray(frame)
    if img.ndim != 2:
        raise ValueError(f"frame must be 2-D grayscale, got shape {img.shape}")
    d = int(round(diameter_px))
    if d % 2 == 0:
        raise ValueError(f"trackpy parity needs an odd diameter, got {diameter_px}")
    r = d // 2
    integer = np.issubdtype(img.dtype, np.integer)
    if polarity == "dark":
        raw = img ^ np.iinfo(img.dtype).max if integer else 1.0 - img
    else:
        raw = img
    sep = d + 1 if separation is None else int(separation)
    smooth = d if smoothing_size is None else int(smoothing_size)
    thr = (1 if integer else 1 / 255.0) if threshold is None else threshold
    # band pass (trackpy.preprocessing.bandpass): boxcar in the image's dtype, Gaussian in float
    background = raw.copy()
    for axis in (0, 1):
        ndimage.uniform_filter1d(background, smooth, axis, output=background, mode="nearest", cval=0)
    low = np.array(raw, dtype=float)
    k = _trackpy_gaussian_kernel(noise_size)
    for axis in (0, 1):
        ndimage.correlate1d(low, k, axis, output=low, mode="constant", cval=0.0)
    bp = low - background
    bp = np.where(bp >= thr, bp, 0)
    dtype = img.dtype if integer else np.uint8
    top = bp.max()
    scale = np.iinfo(dtype).max / top if top != 0 else 1.0
    im = (scale * bp.clip(min=0.0)).astype(dtype)
    # local maxima (trackpy.find.grey_dilation, precise=False)
    margin = max(r, sep // 2 - 1, smooth // 2)
    nz = im[np.nonzero(im)]
    if len(nz) == 0:
        return pd.DataFrame(columns=COLUMNS, dtype=float)
    level = np.percentile(nz, percentile)
    size = int(2 * sep / np.sqrt(2))
    dil = ndimage.grey_dilation(im, (size, size), mode="constant")
    pos = np.argwhere((im == dil) & (im > level))
    h, w = im.shape
    pos = pos[~np.any((pos < margin) | (pos > np.array([h, w]) - margin - 1), axis=1)]
    # centre of mass in a disc that moves by whole pixels (trackpy.refine.center_of_mass._refine),
    # every feature at once: each stops moving when its centre is within shift_thresh
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = ((yy / r) ** 2 + (xx / r) ** 2 <= 1).astype(np.int64)
    gy = np.arange(2 * r + 1)[None, :, None]
    gx = np.arange(2 * r + 1)[None, None, :]
    off_px = np.arange(-r, r + 1)
    c = pos.astype(np.int64)
    hi = np.array([h, w]) - 1 - r
    out = np.empty((len(pos), 4))
    todo = np.arange(len(pos))
    for _ in range(max(int(max_iterations), 1)):
        if len(todo) == 0:
            break
        cc = c[todo]
        nb = disc[None] * im[(cc[:, 0, None] + off_px)[:, :, None], (cc[:, 1, None] + off_px)[:, None, :]]
        m = nb.sum(axis=(1, 2))
        ok = m != 0
        mm = np.where(ok, m, 1)
        cm = np.where(ok[:, None], np.column_stack([(nb * gy).sum(axis=(1, 2)) / mm, (nb * gx).sum(axis=(1, 2)) / mm]),
                      float(r))
        out[todo] = np.column_stack([cm[:, 1] - r + cc[:, 1], cm[:, 0] - r + cc[:, 0], m, nb.max(axis=(1, 2))])
        off = cm - r
        done = np.all(np.abs(off) < shift_thresh, axis=1)
        moved = np.clip(cc + (off > shift_thresh) - (off < -shift_thresh), r, hi)
        c[todo[~done]] = moved[~done]
        todo = todo[~done]
    # of two features closer than the separation keep the brighter (trackpy.find.where_close)
    if len(out) > 1:
        from scipy.spatial import cKDTree
        resc = out[:, [1, 0]] / sep
        pairs = cKDTree(resc, 30).query_pairs(1 - 1e-7, output_type="ndarray")
        if len(pairs):
            i0, i1 = pairs[:, 0], pairs[:, 1]
            m0, m1 = out[i0, 2], out[i1, 2]
            drop = np.where(m0 > m1, i1, i0)
            tie = m0 == m1
            drop[tie] = np.where(resc[i0[tie]].sum(axis=1) > resc[i1[tie]].sum(axis=1), i1[tie], i0[tie])
            out = np.delete(out, np.unique(drop), axis=0)
    out[:, 2] /= scale
    out = out[out[:, 2] > minmass]
    res = {c: np.full(len(out), np.nan) for c in COLUMNS}
    res.update(x_px=out[:, 0], y_px=out[:, 1], mass=out[:, 2], amplitude=out[:, 3] / scale,
               x_centroid_px=out[:, 0], y_centroid_px=out[:, 1])
    return pd.DataFrame(res, columns=COLUMNS).sort_values(["y_px", "x_px"]).reset_index(drop=True)


def detect_markers(frame: np.ndarray, diameter_px: float, polarity: Polarity = "dark",
                   roi: FieldOfView | np.ndarray | str | None = None,
                   settings: DetectionSettings = DetectionSettings(), **kw) -> pd.DataFrame:
    """Find every marker in a frame.

    Parameters
    ----------
    frame : ndarray (h, w)
        Grayscale pixels, any numeric dtype.
    diameter_px : float
        Marker diameter on screen (pixels).
    polarity : ``"dark"`` | ``"bright"``
        Markers darker (steel beads in raw X-ray frames) or brighter than the background.
    roi : None | ``"auto"`` | ``"none"`` | FieldOfView | bool ndarray (h, w)
        Region searched: None/``"auto"`` finds the intensifier's circular field
        (:func:`find_field_of_view`) and, for dark markers, leaves out large radio-opaque
        objects (:func:`dark_objects`); ``"none"`` the whole frame; or a given field or mask.
    settings : DetectionSettings
        Thresholds and the centre method; keyword arguments override single fields.

    Returns
    -------
    DataFrame
        One row per marker, :data:`COLUMNS`: ``x_px, y_px`` (sub-pixel, OpenCV convention),
        ``snr`` (amplitude / pixel noise), ``amplitude`` (grey levels above the local
        background), ``area_px`` (pixels of the blob above half its peak), ``mass`` (sum of
        the signal in the marker's window), ``sigma_px`` (fitted Gaussian width),
        ``elongation`` (axis ratio), ``x_centroid_px, y_centroid_px`` (before refinement).
        Sorted by y then x.
    """
    st = settings.updated(**kw) if kw else settings
    img = np.asarray(frame)
    if img.ndim != 2:
        raise ValueError(f"frame must be 2-D grayscale, got shape {img.shape}")
    if st.parity == "trackpy":
        if st.method != "centroid":
            raise ValueError("parity='trackpy' is trackpy's centroid: use it with method='centroid'")
        return locate_trackpy(img, diameter_px, polarity, minmass=st.minmass)
    return pd.DataFrame(detect_arrays(img, diameter_px, polarity, roi, st), columns=COLUMNS)


def _nonzero_sparse(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.nonzero`` of a sparse 2-D bool mask (rows ys, columns xs in raster order): the
    rows holding any first, then the nonzero entries of those rows only."""
    rows = np.flatnonzero(m.any(axis=1))
    if len(rows) * 4 > len(m):
        return np.nonzero(m)
    ys, xs = np.nonzero(m[rows])
    return rows[ys], xs


def _grid_step(shape) -> int:
    """Sampling step of the whole-frame statistics: about 16,000 samples or more (every 2nd
    pixel of each axis up to 512 x 512, every 8th at 1024 x 1024), which give the median and
    the robust sd to about 1 %."""
    return max(2, int(math.sqrt(shape[0] * shape[1] / 16384)))


def _grid_pixels(img: np.ndarray, g: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For an 8/16-bit frame: whether the pixels ``[::g, ::g]`` and ``[1:-1:g, 1:-1:g]`` are
    unclipped (the values of ``_unclipped(img)[...] > 0``; all True when nothing is clipped)
    and Immerkaer's high-pass at ``[1:-1:g, 1:-1:g]`` (``_immerkaer(img, g)``, int32), from
    the rows and columns of those grids and their neighbours only: no full-frame erosion or
    filter.  The high-pass is separable, [1, -2, 1] down the rows, then across."""
    h, w = img.shape
    top = np.iinfo(img.dtype).max
    m = cv2.inRange(img, 1, top - 1)                     # 255 where the pixel is not clipped
    # the grid [::g, ::g]: rows and columns at -1, 0, +1 (edge replicated)
    y0 = np.arange(0, h, g)
    x0 = np.arange(0, w, g)
    v = None
    for d in (-1, 0, 1):
        r = np.take(m, np.clip(y0 + d, 0, h - 1), axis=0)
        v = r if v is None else np.minimum(v, r, out=v)
    u0 = None
    for d in (-1, 0, 1):
        c = np.take(v, np.clip(x0 + d, 0, w - 1), axis=1)
        u0 = c if u0 is None else np.minimum(u0, c, out=u0)
    # the grid [1:-1:g, 1:-1:g]: never at the edge
    ny, nx = len(range(1, h - 1, g)), len(range(1, w - 1, g))
    v = np.minimum(m[0::g][:ny], m[1::g][:ny])
    np.minimum(v, m[2::g][:ny], out=v)
    u1 = np.minimum(v[:, 0::g][:, :nx], v[:, 1::g][:, :nx])
    np.minimum(u1, v[:, 2::g][:, :nx], out=u1)
    dt = np.int16 if img.dtype == np.uint8 else np.int32
    a1 = img[1::g][:ny]
    v2 = np.add(img[0::g][:ny], img[2::g][:ny], dtype=dt)
    v2 -= a1
    v2 -= a1
    hp = np.add(v2[:, 0::g][:, :nx], v2[:, 2::g][:, :nx], dtype=np.int32)
    hp -= v2[:, 1::g][:, :nx]
    hp -= v2[:, 1::g][:, :nx]
    u0, u1 = u0 > 0, u1 > 0
    # a fill region (a constant value outside the field, a saturated region mapped to a grey)
    # carries no noise either: where more than a fifth of the unclipped grid pixels sit in
    # constant 5 x 5 patches, those are left out too.  Noisy frames hold few such patches
    # (0-13 % in the real frames of the tests), so they keep every pixel.  A pixel of such a
    # patch has a zero high-pass, so the patch test runs only where more than a fifth of the
    # high-pass samples are zero (never on a usual noisy frame).  (A test for any patch
    # without noise, a smooth ramp as well, would take 60 % of a real microscopy frame of low
    # noise for one: not used.)
    n1 = int(np.count_nonzero(u1))
    if n1 and 5 * int(np.count_nonzero((hp == 0) & u1)) > n1:
        for u, ys, xs in ((u0, y0, x0), (u1, np.arange(1, h - 1, g)[:ny], np.arange(1, w - 1, g)[:nx])):
            flat = _flat_at(img, ys, xs)
            n = int(np.count_nonzero(u))
            if n and 5 * int(np.count_nonzero(flat & u)) > n:
                u &= ~flat
    return u0, u1, hp


def _flat_at(img: np.ndarray, ys: np.ndarray, xs: np.ndarray, r: int = 2) -> np.ndarray:
    """(len(ys), len(xs)) bool: whether the (2r+1)-square around each grid pixel is one value
    (edges replicated), from those rows and columns only."""
    h, w = img.shape
    hi = lo = None
    for d in range(-r, r + 1):
        row = np.take(img, np.clip(ys + d, 0, h - 1), axis=0)
        hi = row.copy() if hi is None else np.maximum(hi, row, out=hi)
        lo = row.copy() if lo is None else np.minimum(lo, row, out=lo)
    chi = clo = None
    for d in range(-r, r + 1):
        cx = np.clip(xs + d, 0, w - 1)
        a, b = np.take(hi, cx, axis=1), np.take(lo, cx, axis=1)
        chi = a if chi is None else np.maximum(chi, a, out=chi)
        clo = b if clo is None else np.minimum(clo, b, out=clo)
    return chi == clo


def _unclipped(img: np.ndarray) -> np.ndarray | None:
    """Pixels strictly between the lowest and highest value the dtype (integers) or the
    image (floats) holds, grown away from clipped ones by a pixel (saturated or black regions
    have no noise to measure): a uint8 mask, nonzero where unclipped; None when no pixel is
    clipped.  Sample it on a grid (``m[y0::step, x0::step] > 0``)."""
    a = np.asarray(img)
    if a.dtype in (np.uint8, np.uint16):
        hi = np.iinfo(a.dtype).max
        mn, mx, _, _ = cv2.minMaxLoc(a)
        if 0 < mn and mx < hi:
            return None
        # 255 strictly inside (0, max), eroded by a 3x3 square: away from clipped pixels by one
        return cv2.erode(cv2.inRange(a, 1, hi - 1), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    if np.issubdtype(a.dtype, np.integer):
        info = np.iinfo(a.dtype)
        lo, hi = info.min, info.max
    else:
        lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
    clipped = ((a <= lo) | (a >= hi)).astype(np.uint8)
    if not clipped.any():
        return None
    return (cv2.dilate(clipped, np.ones((3, 3), np.uint8)) == 0).view(np.uint8)


def detect_arrays(frame: np.ndarray, diameter_px: float, polarity: Polarity = "dark",
                  roi: FieldOfView | np.ndarray | str | None = None,
                  settings: DetectionSettings = DetectionSettings(), *, dark: bool | None = None,
                  skip: tuple | None = None) -> dict:
    """:func:`detect_markers` as a dict of :data:`COLUMNS` arrays, sorted by y then x (the
    per-frame path of automatic tracking: no DataFrame per frame).  ``dark``: leave out
    :func:`dark_objects` (default: for dark markers when ``roi`` is None or ``"auto"``; a
    tracker that finds the field of view once passes it as ``roi`` with ``dark=True``).
    ``skip``: ``(centres (n, 2), radii (n,))``, circles whose candidates are not measured nor
    returned (a tracker's sweep for new markers skips the ones it already holds; they are
    still masked out of their neighbours' fits).

    Whole-frame work is the smoothed top-hat (:func:`smoothed_tophat`), one comparison with
    the threshold, and Immerkaer's filter and the statistics on a sampling grid
    (:func:`_grid_step`); masks are tested on that grid and at the candidate pixels only."""
    st = settings
    img = np.asarray(frame)
    if img.ndim != 2:
        raise ValueError(f"frame must be 2-D grayscale, got shape {img.shape}")
    if st.parity != "none":
        raise ValueError(f"parity {st.parity!r} is detect_markers' (trackpy's locate), not detect_arrays'")
    se = st.se_px(diameter_px)
    margin = st.edge_margin_px if st.edge_margin_px is not None else se // 2 + 2.0
    region = _region(img, roi, margin, diameter_px, polarity, dark)
    ts = smoothed_tophat(img, diameter_px, polarity, se, st.smooth_px(diameter_px))
    # the noise statistics come from pixels that carry noise: not clipped (saturated or black)
    g = _grid_step(img.shape)
    inside = region.grid(0, 0, g)
    if img.dtype in (np.uint8, np.uint16) and min(img.shape) >= 3:
        # 8/16-bit: the unclipped test and the high-pass at the grid's pixels only
        unc, unc1, hp = _grid_pixels(img, g)
    else:
        unclipped = _unclipped(img)
        unc = None if unclipped is None else unclipped[::g, ::g] > 0
        unc1 = None if unclipped is None else unclipped[1:-1:g, 1:-1:g] > 0
        hp = None
    stat = unc if inside is None else inside if unc is None else unc & inside
    sample = ts[::g, ::g] if stat is None else ts[::g, ::g][stat]
    if sample.size < 100:
        sample = ts[::g, ::g] if inside is None else ts[::g, ::g][inside]
    thr, sd = robust_threshold(sample, st.k_sigma)
    ys, xs = _nonzero_sparse(ts > thr)
    xs, ys, area = _peaks_at(ts, xs, ys, diameter_px, thr - st.k_sigma * sd, st, region)
    if st.min_roundness is not None and len(xs):
        rnd = curvature_ratio(ts, xs, ys, max(3.0, 0.75 * diameter_px)) >= st.min_roundness
        xs, ys, area = xs[rnd], ys[rnd], area[rnd]
    if len(xs) == 0:
        return {c: np.zeros(0) for c in COLUMNS}
    if hp is None:
        hp = _immerkaer(img, g)
    inside1 = region.grid(1, 1, g)
    inside1 = None if inside1 is None else inside1[:hp.shape[0], :hp.shape[1]]
    use = unc1
    if inside1 is not None:
        use = inside1 if use is None else use & inside1
    if use is not None and not use.any():
        use = inside1
    noise = max(_noise_from_highpass(hp if use is None else hp[use]), _coarse_noise(img, g, use))
    neighbours = None
    if skip is not None and len(skip[0]):
        c = np.asarray(skip[0], float).reshape(-1, 2)
        r = np.broadcast_to(np.asarray(skip[1], float), (len(c),))
        d2 = (xs[:, None] - c[None, :, 0]) ** 2 + (ys[:, None] - c[None, :, 1]) ** 2
        new = ~(d2 <= r[None, :] ** 2).any(axis=1)
        if not new.all():
            neighbours = np.column_stack([xs, ys]).astype(float)
            xs, ys, area = xs[new], ys[new], area[new]
            if len(xs) == 0:
                return {c: np.zeros(0) for c in COLUMNS}
    m = _finish(img, xs, ys, area, np.full(len(xs), noise), diameter_px, polarity, st, region, neighbours,
                _field_circle(region.fov))
    order = np.lexsort((m["x_px"], m["y_px"]))
    return {c: m[c][order] for c in COLUMNS}


# --- windows (seeded refinement and tracking) ----------------------------------------------------

def _window_geometry(radius_px: float, diameter_px: float, st: DetectionSettings) -> tuple[int, int, int]:
    """(half side, pad, border) of :func:`window_arrays`' windows for search radius
    ``radius_px``: a window is ``2 half + 1`` square, cut ``pad`` columns wider on both sides;
    ``border``, the reach of the top-hat and its smoothing, is kept out of its core."""
    k = st.se_px(diameter_px)
    sg = st.smooth_px(diameter_px)
    b = k // 2 + int(math.ceil(3 * sg)) + 1
    half = int(math.ceil(radius_px)) + b + int(math.ceil(diameter_px))
    return half, 2 * (k // 2) + len(_gauss_kernel(float(sg))) // 2, b


def window_strip_px(n: int, radius_px: float, diameter_px: float,
                    settings: DetectionSettings = DetectionSettings()) -> int:
    """Pixels :func:`window_arrays` filters for ``n`` windows of largest radius
    ``radius_px``: against a frame's, the cost of searching the windows instead of the whole
    frame."""
    half, pad, _ = _window_geometry(radius_px, diameter_px, settings)
    return (2 * half + 1) * n * (2 * half + 1 + 2 * pad)


def window_arrays(frame: np.ndarray, centres_xy, radii_px, diameter_px: float, polarity: Polarity = "dark",
                  settings: DetectionSettings = DetectionSettings(),
                  fov: FieldOfView | None = None) -> dict:
    """Candidates in circular search windows of one frame, as arrays (fast path).

    All windows are cut out to the same size and laid side by side in one strip, so the
    top-hat, smoothing and peak search are one OpenCV call each whatever the number of
    windows; each window is cut wider by the reach of the top-hat and the smoothing, so its
    top-hat does not see its neighbours in the strip; threshold and noise are each window's
    own (robust statistics per window): a window's candidates do not depend on the other
    windows searched with it.
    Returns a dict of :data:`COLUMNS` arrays for every candidate in the windows (duplicates
    from overlapping windows merged).
    """
    img = np.asarray(frame)
    h, w = img.shape
    st = settings
    if st.parity != "none":
        raise ValueError(f"parity {st.parity!r} detects whole frames (detect_markers), not search windows")
    c = np.asarray(centres_xy, float).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radii_px, float), (len(c),))
    ok = np.isfinite(c).all(axis=1) & np.isfinite(radii)
    if not ok.all():
        c, radii = c[ok], radii[ok]
    if len(c) == 0:
        return {k: np.zeros(0) for k in COLUMNS}
    k = st.se_px(diameter_px)
    sg = st.smooth_px(diameter_px)
    half, pad, b = _window_geometry(float(radii.max()), diameter_px, st)
    W = 2 * half + 1
    n = len(c)
    icx = np.rint(c[:, 0]).astype(int)
    icy = np.rint(c[:, 1]).astype(int)
    xl, yl = icx.tolist(), icy.tolist()
    # the windows side by side, each cut ``pad`` columns wider on both sides than the W x W
    # window (the reach of the closing and the smoothing): the window's top-hat is then the
    # frame's own there, whatever window sits next to it in the strip -- side by side, a
    # window would see its neighbour across the seam, the seam's response would enter its
    # statistics, and its threshold would depend on which other markers are searched in the
    # same frame.  ``wide`` (W, n Wp); window i is wide[:, i Wp + pad:i Wp + pad + W].  ``use``
    # (n, W, W): the pixels searched (inside the image)
    Wp = W + 2 * pad
    if (min(xl) >= half + pad and min(yl) >= half and max(xl) < w - half - pad and max(yl) < h - half):
        # every window inside the image (the usual case): slices, no index arrays
        wide = np.empty((W, n * Wp), img.dtype)
        for i, (x, y) in enumerate(zip(xl, yl)):
            wide[:, i * Wp:(i + 1) * Wp] = img[y - half:y + half + 1, x - half - pad:x + half + pad + 1]
        use = None
    else:
        offy = np.arange(-half, half + 1)
        offx = np.arange(-half - pad, half + pad + 1)
        rows = icy[:, None] + offy[None, :]                 # (n, W)
        cols = icx[:, None] + offx[None, :]                 # (n, Wp)
        win = img[_clamp(rows, 0, h - 1)[:, :, None], _clamp(cols, 0, w - 1)[:, None, :]]        # (n, W, Wp)
        wide = np.ascontiguousarray(win.transpose(1, 0, 2).reshape(W, n * Wp))
        cw = cols[:, pad:pad + W]
        use = ((rows >= 0) & (rows < h))[:, :, None] & ((cw >= 0) & (cw < w))[:, None, :]       # (n, W, W)
    if fov is not None and fov.found:
        fx, fy = fov.centre_px
        # only windows that reach beyond the field's edge need the per-pixel test
        if np.any(np.hypot(icx - fx, icy - fy) + half * math.sqrt(2) > fov.radius_px):
            off = np.arange(-half, half + 1)
            rows = icy[:, None] + off[None, :]
            cols = icx[:, None] + off[None, :]
            inf = ((cols[:, None, :] - fx) ** 2 + (rows[:, :, None] - fy) ** 2) <= fov.radius_px ** 2
            use = inf if use is None else use & inf
    if fov is not None and fov.region is not None:
        # a region of interest the user gave: its pixels only (outside the image: not in it)
        off = np.arange(-half, half + 1)
        rows = icy[:, None] + off[None, :]
        cols = icx[:, None] + off[None, :]
        inr = np.asarray(fov.region, bool)[_clamp(rows, 0, h - 1)[:, :, None], _clamp(cols, 0, w - 1)[:, None, :]]
        use = inr if use is None else use & inr
    core = _strip_core(W, n, b)
    use = core if use is None else core & use.transpose(1, 0, 2).reshape(W, n * W)
    ts = smoothed_tophat(wide, diameter_px, polarity, k, sg).reshape(W, n, Wp)
    ts = np.ascontiguousarray(ts[:, :, pad:pad + W]).reshape(W, n * W)
    tsw = ts.reshape(W, n, W).transpose(1, 0, 2)        # (n, W, W)
    # per-window robust statistics (a window cut by the image edge repeats its edge pixels;
    # every other pixel of each axis is plenty for a median)
    vals = tsw[:, ::2, ::2].reshape(n, -1)
    med = _median(vals, axis=1)
    sd = np.maximum(_robust_sd(vals, axis=1, med=med), 1e-6)
    thr = med + st.window_k_sigma * sd
    # the local maxima above each window's threshold: one dilation of the strip (its edge
    # replicated, as a peak test clamped to the strip)
    kp = max(3, int(round(diameter_px)) | 1)
    peak = ts >= cv2.dilate(ts, _ellipse(kp), borderType=cv2.BORDER_REPLICATE)
    peak &= ts > np.repeat(thr, W)
    peak &= use
    ys, xs = np.divmod(np.flatnonzero(peak), n * W)
    floor = np.repeat(med.astype(np.float32), W)        # each window's floor, by strip column
    xs, ys, area = _peak_areas(ts, xs, ys, diameter_px, floor, st)
    if st.min_roundness is not None and len(xs):
        # a ridge away from the window's centre is no marker (the whole-frame search's test): a
        # thin wire crossing a window gives peaks along its top-hat ridge, and a marker hidden
        # 7 px from one had been taken onto it and followed along it, 7-50 px off, as "found".
        # Within a diameter of the centre (the prediction) a candidate stays whatever its
        # shape: two markers passing close merge into one elongated image, and a marker on a
        # line is still that marker
        far = (xs % W - half) ** 2 + (ys - half) ** 2 > max(diameter_px, 3.0) ** 2
        if far.any():
            rnd = ~far
            rnd[far] = curvature_ratio(ts, xs[far], ys[far], max(3.0, 0.75 * diameter_px)) >= st.min_roundness
            xs, ys, area = xs[rnd], ys[rnd], area[rnd]
    if len(xs) == 0:
        return {k: np.zeros(0) for k in COLUMNS}
    # pixel noise of each window (Immerkaer; exact integers from 8/16-bit pixels), for the SNR
    if wide.dtype in (np.uint8, np.uint16):         # separable [1, -2, 1] x [1, -2, 1]: exact integers
        lap = cv2.sepFilter2D(wide, cv2.CV_32F, _SECOND_DIFF, _SECOND_DIFF, borderType=cv2.BORDER_REPLICATE)
    else:
        lap = cv2.filter2D(wide.astype(np.float32), cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REPLICATE)
    lapw = lap.reshape(W, n, Wp).transpose(1, 0, 2)[:, b:W - b:2, pad + b:pad + W - b:2].reshape(n, -1)
    noise = np.maximum(_robust_sd(lapw, axis=1) / 6.0, 1e-3)
    wi = xs // W
    px = icx[wi] - half + xs % W
    py = icy[wi] - half + ys
    _, first = np.unique(px.astype(np.int64) * (h + 1) + py, return_index=True)
    px, py, area, wi = px[first], py[first], area[first], wi[first]
    # measure the candidates inside a search radius (+ 1 px); all of them are neighbours
    d2 = (px[:, None] - c[None, :, 0]) ** 2 + (py[:, None] - c[None, :, 1]) ** 2
    near = (d2 <= (radii[None, :] + 1.5) ** 2).any(axis=1)
    allpts = np.column_stack([px, py]).astype(float)
    if not near.all():
        px, py, area, wi = px[near], py[near], area[near], wi[near]
    return _finish(img, px, py, area, noise[wi], diameter_px, polarity, st, neighbours=allpts,
                   field=_field_circle(fov))


@functools.lru_cache(maxsize=16)
def _strip_core(W: int, n: int, b: int) -> np.ndarray:
    """(W, n W) bool: each window's pixels at least ``b`` from its border (read-only)."""
    core = np.zeros((W, n, W), bool)
    core[b:W - b, :, b:W - b] = True
    core = core.reshape(W, n * W)
    core.setflags(write=False)
    return core


def window_candidates(frame: np.ndarray, centres_xy, radii_px, diameter_px: float, polarity: Polarity = "dark",
                      settings: DetectionSettings = DetectionSettings(),
                      fov: FieldOfView | None = None) -> tuple[pd.DataFrame, list[np.ndarray]]:
    """Markers in circular search windows (centre, radius) of one frame.

    Returns every candidate found in the windows (:data:`COLUMNS`) and, per window, the
    indices of the candidates within its radius.  See :func:`window_arrays`.
    """
    m = window_arrays(frame, centres_xy, radii_px, diameter_px, polarity, settings, fov)
    df = pd.DataFrame(m, columns=COLUMNS)
    c = np.asarray(centres_xy, float).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(radii_px, float), (len(c),))
    xy = df[["x_px", "y_px"]].to_numpy()
    members = [np.flatnonzero(np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) <= r) for (cx, cy), r in zip(c, radii)]
    return df, members


def refine_at(frame: np.ndarray, seeds_xy, diameter_px: float, polarity: Polarity = "dark",
              search_radius_px: float | None = None, settings: DetectionSettings = DetectionSettings(),
              **kw) -> pd.DataFrame:
    """Refine seeded positions (N, 2) to the nearest marker within ``search_radius_px``.

    The seed is a rough click (as in XMALab); the marker nearest to it inside the search
    window (default ``max(3, diameter_px)`` px) is measured as in :func:`detect_markers`.
    Returns one row per seed in order: :data:`COLUMNS` plus ``found`` (bool) and
    ``distance_px`` (from the seed); NaN coordinates where no marker is in the window.
    """
    st = settings.updated(**kw) if kw else settings
    seeds = np.asarray(seeds_xy, float).reshape(-1, 2)
    r = float(search_radius_px) if search_radius_px is not None else max(3.0, float(diameter_px))
    cand, members = window_candidates(frame, seeds, r, diameter_px, polarity, st)
    xy = cand[["x_px", "y_px"]].to_numpy()
    rows = []
    for i, (sx, sy) in enumerate(seeds):
        idx = members[i]
        if len(idx) == 0:
            rows.append({**{c: np.nan for c in COLUMNS}, "found": False, "distance_px": np.nan})
            continue
        d = np.hypot(xy[idx, 0] - sx, xy[idx, 1] - sy)
        j = idx[int(np.argmin(d))]
        rows.append({**cand.iloc[j][COLUMNS].to_dict(), "found": True, "distance_px": float(d.min())})
    return pd.DataFrame(rows, columns=COLUMNS + ["found", "distance_px"])
