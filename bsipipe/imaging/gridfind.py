r"""Find calibration targets in images: chessboards, symmetric and asymmetric circle (bead)
grids, ChArUco boards, and dense dot grids of unknown extent.

Every finder returns a :class:`GridDetection` (image points in pixels, the matching target
points in mm and their ids) or raises :class:`DetectionFailed` with the reason, so the caller
can report a view it leaves out instead of dropping it silently.

Pixel convention: 0-based, x right, y down, centre of the top-left pixel at (0, 0)
(OpenCV's).

Beads (circles)
---------------
X-ray beads are dark on a bright background (they absorb); printed circle grids may be
either.  :func:`detect_blobs` flattens the background with a morphological top-hat (black-hat
for dark blobs: :math:`s = \mathrm{close}_B(I) - I`, with a square :math:`B` 2.5 bead
diameters wide, the diameter itself measured first by a scale-space search,
:func:`estimate_blob_diameter`), thresholds :math:`s` at its
median + 5 robust (MAD) standard deviations, keeps components whose area and elongation
match the median bead, and places each centre at the iterated, background-subtracted
intensity centroid

.. math::  \mathbf{c} \leftarrow \frac{\sum_{|\mathbf{x}-\mathbf{c}| \le R} w(\mathbf{x})\,\mathbf{x}}
                                       {\sum_{|\mathbf{x}-\mathbf{c}| \le R} w(\mathbf{x})},
           \qquad w = \max(s - t, 0),

with a window radius :math:`R` a little over the bead radius and :math:`t` a noise floor,
repeated until the centre moves by less than 0.001 px.  The window is a soft disk (each
pixel weighted by its covered fraction) so the estimate is continuous in
:math:`\mathbf{c}` and free of the integer-window bias.

Ordering (:func:`lattice_indices`) grows the grid from a seed bead by predicting each
neighbour from the local lattice steps, so it copes with strong distortion, missing beads
and stray blobs; :func:`fit_to_target` then maps lattice indices onto the target's
``COLSxROWS`` layout (for a grid seen whole).  ``cv2.findCirclesGrid`` is not used for the
ordering because it needs the whole grid in view and no stray blobs; the lattice growth
handles the circular field of an image intensifier that cuts off corners of the plate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

log = logging.getLogger(__name__)

Pattern = Literal["chessboard", "circles", "asymmetric-circles", "charuco", "dots"]
PATTERNS = ("chessboard", "circles", "asymmetric-circles", "charuco")


class DetectionFailed(Exception):
    """The target was not found in a view; ``str(e)`` says why."""


class GridMismatch(DetectionFailed):
    """The view shows a board of another size than the grid asked for (``found``: its
    ``(cols, rows)`` in the orientation of the grid asked for, None when not measured;
    ``pattern``: the layout it shows, when that is what differs or was measured)."""

    def __init__(self, message: str, found: tuple[int, int] | None, pattern: str | None = None):
        super().__init__(message)
        self.found = None if found is None else tuple(int(x) for x in found)
        self.pattern = pattern


@dataclass
class GridDetection:
    """A target found in one image.

    image_points : ndarray (n, 2) float64, pixels
    object_points : ndarray (n, 3) float64, mm, target plane z = 0
    ids : ndarray (n,) int, target point ids (row-major ``row * cols + col``)
    grid_ij : ndarray (n, 2) int, (col, row) of each point on the target
    complete : bool, every target point was found
    ambiguous : bool, the target is symmetric, so its orientation (which point is id 0) is
        not fixed by the image alone (stereo pairs resolve it, see ``calibrate``)
    info : dict, what the finder did (method, counts, bead diameter)
    """

    image_points: np.ndarray
    object_points: np.ndarray
    ids: np.ndarray
    grid_ij: np.ndarray
    complete: bool = True
    ambiguous: bool = False
    info: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.ids)


def parse_grid(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6) (columns, rows).

    >>> parse_grid("9x6")
    (9, 6)
    """
    parts = str(text).lower().replace(" ", "").split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts) or min(int(p) for p in parts) < 2:
        raise ValueError(f"grid must be COLSxROWS with two integers >= 2, got {text!r}")
    return int(parts[0]), int(parts[1])


def target_points(pattern: str, grid: tuple[int, int], spacing_mm: float) -> np.ndarray:
    """Target points (cols*rows, 3) in mm, id = row * cols + col, z = 0.

    Chessboard / ChArUco: inner corners; circles: centres on a square grid; asymmetric
    circles: OpenCV's layout, centre of (row i, col j) at ((2 j + i mod 2) s, i s).

    >>> target_points("asymmetric-circles", (2, 2), 1.0)[:, :2].tolist()
    [[0.0, 0.0], [2.0, 0.0], [1.0, 1.0], [3.0, 1.0]]
    """
    cols, rows = grid
    j, i = np.meshgrid(np.arange(cols), np.arange(rows))
    j, i = j.ravel(), i.ravel()
    if pattern == "asymmetric-circles":
        x, y = (2 * j + i % 2) * spacing_mm, i * spacing_mm
    else:
        x, y = j * spacing_mm, i * spacing_mm
    return np.column_stack([x, y, np.zeros_like(x)]).astype(np.float64)


# --- blobs ---------------------------------------------------------------------------------

@dataclass
class Blobs:
    """Blob centres in one image: ``xy`` (n, 2) px, ``area_px`` (n,), ``diameter_px`` (median)."""

    xy: np.ndarray
    area_px: np.ndarray
    diameter_px: float
    polarity: str
    n_rejected: int = 0


def _signal(img: np.ndarray, polarity: str, se_px: int) -> np.ndarray:
    """Background-flattened blob signal (positive on blobs): black-hat or top-hat with a square
    (separable, so fast even when wide) structuring element of side ``se_px``."""
    import cv2
    op = cv2.MORPH_BLACKHAT if polarity == "dark" else cv2.MORPH_TOPHAT
    se = max(3, int(se_px) | 1)
    return cv2.morphologyEx(img, op, cv2.getStructuringElement(cv2.MORPH_RECT, (se, se)))


def _smoothed(sig: np.ndarray, sigma_px: float) -> np.ndarray:
    """``sig`` smoothed by a Gaussian of ``sigma_px`` (0: as it is): a matched filter for faint,
    blurred blobs, whose pixels are each near the noise while their sum is well above it."""
    if not sigma_px > 0:
        return sig
    import cv2
    return cv2.GaussianBlur(sig, (0, 0), float(sigma_px))


def _components(sig: np.ndarray, thresh: float):
    import cv2
    mask = (sig > thresh).astype(np.uint8)
    n, lab, stats, cent = cv2.connectedComponentsWithStats(mask, connectivity=8)
    return n, lab, stats, cent


def _robust_threshold(sig: np.ndarray, valid: np.ndarray, k: float) -> tuple[float, float]:
    """``median + k sigma`` of the signal over ``valid`` pixels, sigma from the MAD (blobs are a
    small fraction of the pixels, so the median and MAD are the background's)."""
    v = sig[valid]
    med = float(np.median(v))
    sigma = float(1.4826 * np.median(np.abs(v - med))) or 1e-3 * (float(v.max()) - med + 1e-12)
    return med + k * sigma, sigma


def refine_centroid(sig: np.ndarray, xy0, radius_px: float, floor: float = 0.0,
                    max_iter: int = 30, tol_px: float = 1e-3) -> tuple[float, float, float]:
    """Iterated soft-disk intensity centroid of ``max(sig - floor, 0)`` around ``xy0``.

    Returns (x, y, mass); NaNs when the window holds no signal.
    """
    h, w = sig.shape
    cx, cy = float(xy0[0]), float(xy0[1])
    r = float(radius_px)
    m = 0.0
    for _ in range(max_iter):
        x0, x1 = int(np.floor(cx - r - 1)), int(np.ceil(cx + r + 1)) + 1
        y0, y1 = int(np.floor(cy - r - 1)), int(np.ceil(cy + r + 1)) + 1
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            return np.nan, np.nan, 0.0
        patch = np.maximum(sig[y0:y1, x0:x1].astype(np.float64) - floor, 0.0)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        d = np.hypot(xx - cx, yy - cy)
        cover = np.clip(r + 0.5 - d, 0.0, 1.0)  # soft edge: fraction of the pixel inside
        wgt = patch * cover
        m = float(wgt.sum())
        if m <= 0:
            return np.nan, np.nan, 0.0
        nx, ny = float((wgt * xx).sum() / m), float((wgt * yy).sum() / m)
        moved = np.hypot(nx - cx, ny - cy)
        cx, cy = nx, ny
        if moved < tol_px:
            break
    return cx, cy, m


def estimate_blob_diameter(img: np.ndarray, polarity: str, valid: np.ndarray, se0: int = 15,
                           rel_tol: float = 0.15, max_steps: int = 8, smooth_px: float = 0.0) -> float:
    r"""Blob diameter (px) from the image, whatever the blob size: a scale-space search.

    The top-hat of width :math:`w` (:func:`_signal`) keeps only features narrower than
    :math:`w`: a blob wider than that leaves fragments of its rim, whose equivalent diameter
    :math:`d(w) = 2\sqrt{	ilde A / \pi}` (:math:`	ilde A` the median component area above
    a 6-sigma threshold) grows with :math:`w`; once :math:`w` exceeds the blobs, :math:`d(w)`
    stops changing.  So :math:`w` is widened from ``se0`` to :math:`\max(2w, 3d + 2)` until
    :math:`d` changes by less than ``rel_tol``.  (A single width fails both ways: 15 px finds
    rim fragments of a 50 px bead and takes them for 7 px blobs.)
    """
    import cv2
    se, d_prev = int(se0), None
    se_max = max(se0, min(img.shape) // 2)
    for _ in range(max_steps):
        sig0 = _smoothed(_signal(img, polarity, se), smooth_px)
        thr0, _ = _robust_threshold(sig0, valid, 6.0)
        _, _, stats, _ = _components(np.where(valid, sig0, 0), thr0)
        areas = stats[1:, cv2.CC_STAT_AREA].astype(float)
        areas = areas[areas >= 4]
        if areas.size == 0:
            if d_prev is not None:
                return d_prev
            raise DetectionFailed(f"no {polarity} blobs found: the blob diameter could not be estimated from the "
                                  "image (give --diameter-px)")
        d = float(2.0 * np.sqrt(np.median(areas) / np.pi))
        if d_prev is not None and abs(d - d_prev) <= rel_tol * d_prev:
            return d
        d_prev = d
        if se >= se_max:
            break
        se = min(se_max, max(2 * se, int(3 * d) + 2))
    return d_prev


def detect_blobs(image: np.ndarray, polarity: Literal["dark", "bright"] = "dark",
                 diameter_px: float | None = None, mask: np.ndarray | None = None,
                 area_range: tuple[float, float] = (0.4, 2.5), max_elongation: float = 2.0,
                 smooth_px: float = 0.0) -> Blobs:
    """Centres of round blobs (beads, dots) to sub-pixel accuracy.

    Parameters
    ----------
    image : ndarray (h, w), any dtype
    polarity : "dark" (X-ray beads, absorbing) or "bright"
    diameter_px : float, optional
        Expected blob diameter; estimated from the image when omitted.
    mask : ndarray (h, w) bool, optional
        Where blobs may be (e.g. inside an image intensifier's circular field).
    area_range : (lo, hi)
        Accepted component area as a multiple of the median component area.
    max_elongation : float
        Largest accepted ratio of the principal axes of a component.
    smooth_px : float
        Gaussian smoothing (sigma, px) of the blob signal before the threshold and the
        components (the centres are refined on the signal unsmoothed): for faint, blurred
        blobs (:func:`find_circles` retries with it).
    """
    import cv2
    if polarity not in ("dark", "bright"):
        raise ValueError(f"polarity must be 'dark' or 'bright', got {polarity!r}")
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    # pixels outside a collimator / intensifier field (near-black background) carry no blobs;
    # the background is the closing of the image (dark blobs filled in)
    if polarity == "dark":
        import cv2 as _cv2
        k = max(15, min(img.shape) // 16) | 1
        bg = _cv2.morphologyEx(img, _cv2.MORPH_CLOSE, _cv2.getStructuringElement(_cv2.MORPH_RECT, (k, k)))
        valid = bg > 0.2 * float(np.median(bg))
    else:
        valid = np.ones(img.shape, bool)
    if mask is not None:
        valid &= mask
    if diameter_px is None:
        diameter_px = estimate_blob_diameter(img, polarity, valid, smooth_px=smooth_px)
    d = float(diameter_px)
    sig = _signal(img, polarity, int(round(2.5 * d)) + 2)
    sig = np.where(valid, sig, 0).astype(np.float32)
    det = np.where(valid, _smoothed(sig, smooth_px), 0).astype(np.float32)
    thr, noise_det = _robust_threshold(det, valid, 5.0)
    noise = _robust_threshold(sig, valid, 5.0)[1] if smooth_px > 0 else noise_det
    n, lab, stats, cent = _components(det, thr)
    if n <= 1:
        raise DetectionFailed(f"no {polarity} blobs above the noise")
    area = stats[1:, cv2.CC_STAT_AREA].astype(float)
    big = area >= max(4.0, 0.1 * np.pi * d * d / 4)
    med_area = float(np.median(area[big])) if big.any() else float(np.median(area))
    keep = (area >= area_range[0] * med_area) & (area <= area_range[1] * med_area)
    # elongation from second moments of each component's bounding box content
    xs, ys = [], []
    h, w = img.shape
    radius = 0.5 * d + 1.0
    floor = float(np.median(sig[valid])) + 2.0 * noise
    masses = []
    rejected = 0
    for k in np.flatnonzero(keep) + 1:
        x, y, bw, bh, a = stats[k]
        if x == 0 or y == 0 or x + bw >= w or y + bh >= h:
            rejected += 1
            continue
        comp = (lab[y:y + bh, x:x + bw] == k)
        yy, xx = np.nonzero(comp)
        if len(xx) >= 3:
            cov = np.cov(np.vstack([xx, yy]))
            ev = np.linalg.eigvalsh(cov)
            if ev[0] <= 0 or np.sqrt(ev[1] / ev[0]) > max_elongation:
                rejected += 1
                continue
        cx, cy, m = refine_centroid(sig, cent[k], radius, floor)
        if not np.isfinite(cx):
            rejected += 1
            continue
        xs.append(cx)
        ys.append(cy)
        masses.append(a)
    rejected += int((~keep).sum())
    xy = np.column_stack([xs, ys]) if xs else np.zeros((0, 2))
    return Blobs(xy=xy, area_px=np.asarray(masses, float), diameter_px=d, polarity=polarity, n_rejected=rejected)


# --- lattice ordering ------------------------------------------------------------------------

def lattice_indices(xy: np.ndarray, tol: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice coordinates of points on a (distorted) square lattice.

    Grows from the point nearest the centroid that has four neighbours; each neighbour of
    an indexed point is predicted by extrapolating the local lattice step (the step to the
    neighbour it was reached from, so the prediction follows the distortion) and accepted
    when a point lies within ``tol`` steps of the prediction.

    Returns
    -------
    ij : ndarray (n, 2) int
        (a, b): ``a`` counts along the lattice direction nearest image +x, ``b`` nearest +y.
    ok : ndarray (n,) bool
        Points reached by the growth (stray blobs are not).
    """
    from collections import deque

    from scipy.spatial import cKDTree

    xy = np.asarray(xy, dtype=np.float64)
    n = len(xy)
    ij = np.zeros((n, 2), dtype=int)
    ok = np.zeros(n, dtype=bool)
    if n < 5:
        return ij, ok
    tree = cKDTree(xy)
    _, nn = tree.query(xy, k=min(9, n))
    centre = np.median(xy, axis=0)
    order = np.argsort(np.hypot(*(xy - centre).T))
    # the seed: a point near the centre with a lattice step u (its nearest neighbour) and a
    # second step v (the nearest neighbour at least 30 degrees off u's line) whose four points
    # s +- u, s +- v are all there.  The seed had to have four neighbours within 1.4 times the
    # median spacing: a plate tilted 45 degrees or more (stereo frames of C-arms 90 degrees
    # apart) foreshortens one axis so its second neighbours fall beyond, and the view was
    # rejected with every bead detected ("0 of 136 grid points found")
    seed = None
    for s in order[: max(50, n // 4)]:
        vecs = xy[nn[s, 1:]] - xy[s]
        lens = np.hypot(*vecs.T)
        u = vecs[int(np.argmin(lens))]
        sin = np.abs(u[0] * vecs[:, 1] - u[1] * vecs[:, 0]) / np.maximum(lens * np.hypot(*u), 1e-300)
        off = np.flatnonzero(sin > 0.5)
        if not len(off):
            continue
        v = vecs[off[int(np.argmin(lens[off]))]]
        if all(tree.query(xy[s] + w)[0] <= tol * np.hypot(*w) for w in (u, -u, v, -v)):
            seed = s
            break
    if seed is None:
        return ij, ok
    steps = {(1, 0): u, (-1, 0): -u, (0, 1): v, (0, -1): -v}
    local = np.zeros((n, 2, 2))  # per point: step along a, step along b
    local[seed] = [u, v]
    ok[seed] = True
    taken: dict[tuple[int, int], int] = {(0, 0): seed}
    queue = deque([seed])
    while queue:
        p = queue.popleft()
        up, vp = local[p]
        for (da, db) in steps:
            key = (ij[p, 0] + da, ij[p, 1] + db)
            if key in taken:
                continue
            step = da * up + db * vp
            pred = xy[p] + step
            dq, q = tree.query(pred)
            if dq > tol * np.hypot(*step) or ok[q]:
                continue
            ok[q] = True
            ij[q] = key
            taken[key] = q
            obs = xy[q] - xy[p]
            local[q] = [obs * da if da else up, obs * db if db else vp]
            queue.append(q)
    if ok.sum() >= 3:
        ij[ok] = _reduce_lattice(ij[ok], xy[ok])
    return ij, ok


def _reduce_lattice(ij: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Re-express lattice coordinates in the reduced basis (the two shortest independent
    steps, Lagrange-Gauss), oriented so ``a`` runs nearest image +x and ``b`` nearest +y.

    The growth may start from a skewed pair of steps (a side and a diagonal generate the same
    lattice); the target layouts are defined in the reduced basis.
    """
    A = np.column_stack([ij, np.ones(len(ij))])
    coef, *_ = np.linalg.lstsq(A, xy, rcond=None)
    B = coef[:2].T.copy()  # columns: image step of a, of b (global mean)
    U = np.eye(2, dtype=int)
    for _ in range(50):
        u, v = B[:, 0], B[:, 1]
        if v @ v < u @ u:
            B = B[:, ::-1].copy()
            U = U[:, ::-1].copy()
            continue
        m = int(np.round((u @ v) / (u @ u)))
        if m == 0:
            break
        B[:, 1] -= m * B[:, 0]
        U[:, 1] -= m * U[:, 0]
    # orientation: a nearest +x, b nearest +y (a symmetry of the lattice, not a shear)
    best = None
    for S in _dihedral():
        Bs = B @ S
        score = Bs[0, 0] / np.hypot(*Bs[:, 0]) + Bs[1, 1] / np.hypot(*Bs[:, 1])
        if best is None or score > best[0] + 1e-9:
            best = (score, S)
    U = U @ best[1]
    # xy = B_old ij = B_old U ij'  ->  ij' = U^-1 ij
    Uinv = np.round(np.linalg.inv(U)).astype(int)
    return ij @ Uinv.T


def _dihedral() -> list[np.ndarray]:
    """The 8 symmetries of the square lattice (proper ones first)."""
    rots = [np.array([[1, 0], [0, 1]]), np.array([[0, -1], [1, 0]]),
            np.array([[-1, 0], [0, -1]]), np.array([[0, 1], [-1, 0]])]
    flip = np.array([[1, 0], [0, -1]])
    return rots + [r @ flip for r in rots]


def _unimodular(max_entry: int = 2) -> list[np.ndarray]:
    """Integer 2x2 matrices with det +-1 and entries in [-max_entry, max_entry] (the changes of
    basis of a lattice with short steps), identity first."""
    r = range(-max_entry, max_entry + 1)
    out = [np.array([[p, q], [t, u]]) for p in r for q in r for t in r for u in r if abs(p * u - q * t) == 1]
    out.sort(key=lambda m: (np.abs(m - np.eye(2, dtype=int)).sum(), tuple(m.ravel())))
    return out


_UNIMODULAR = _unimodular()


def fit_to_target(ij: np.ndarray, pattern: str, grid: tuple[int, int],
                  xy: np.ndarray | None = None) -> tuple[np.ndarray, bool, bool]:
    """Map lattice coordinates onto the target's (col, row) layout.

    Tries the changes of lattice basis with short steps (which include the 8 symmetries of a
    square lattice; an asymmetric grid seen obliquely can make a side as short as a diagonal);
    one fits when it puts every point on a target position (the bounding box anchored at the
    first row and column).  Among those that fit, keeps the one whose target x and y axes point
    closest to image +x and +y (measured with ``xy``, else taking lattice ``a``/``b`` as
    image x/y), then a proper rotation (the target keeps its handedness in the image).

    Returns
    -------
    colrow : ndarray (n, 2) int
    complete : bool, every target position is occupied
    ambiguous : bool, more than one map fits (a symmetric grid, or a partial view), so which
        physical point is id 0 is not fixed by this image alone

    Raises DetectionFailed when the points do not fit in the target.

    >>> ij = np.array([[a, b] for b in range(2) for a in range(3)])
    >>> colrow, complete, ambiguous = fit_to_target(ij, "circles", (3, 2))
    >>> colrow.tolist() == ij.tolist(), complete, ambiguous
    (True, True, True)
    """
    cols, rows = grid
    tgt = target_points(pattern, grid, 1.0)[:, :2].round().astype(int)  # integer (X, Y)
    id_of = {tuple(t): k for k, t in enumerate(tgt)}
    conv = np.array([[1, 1], [-1, 1]]) if pattern == "asymmetric-circles" else np.eye(2, dtype=int)
    span_t = tgt.max(axis=0) - tgt.min(axis=0)
    if xy is not None and len(ij) >= 3:
        coef, *_ = np.linalg.lstsq(np.column_stack([ij, np.ones(len(ij))]), np.asarray(xy, float), rcond=None)
        B = coef[:2].T  # image step of lattice a, b
    else:
        B = np.eye(2)
    fits = []
    seen = set()
    for m in _UNIMODULAR:
        a = conv @ m  # lattice (a, b) -> target (X, Y)
        XY = ij @ a.T
        lo = XY.min(axis=0)
        if np.any(XY.max(axis=0) - lo > span_t):
            continue
        for off in (lo, lo - [1, 0], lo - [0, 1], lo - [1, 1]):  # parity of the asymmetric layout
            P = XY - off
            ids = [id_of.get(tuple(p)) for p in P]
            if None not in ids:
                key = tuple(ids)
                if key in seen:
                    break
                seen.add(key)
                inv = np.linalg.inv(a)
                xdir, ydir = B @ inv[:, 0], B @ inv[:, 1]
                score = xdir[0] / np.hypot(*xdir) + ydir[1] / np.hypot(*ydir)
                fits.append((round(float(score), 6), float(np.linalg.det(B @ inv)) > 0, np.asarray(ids)))
                break
    if not fits:
        raise DetectionFailed(f"the {len(ij)} points found do not fit a {cols}x{rows} {pattern} grid")
    fits.sort(key=lambda f: (f[0], f[1]), reverse=True)
    ids = fits[0][2]
    complete = len(set(ids.tolist())) == len(tgt)
    return np.column_stack([ids % cols, ids // cols]), complete, len(fits) > 1


def field_centre(image: np.ndarray) -> tuple[float, float] | None:
    """Centre (x, y) px of an image intensifier's circular field: the bright disc inside the
    dark surround, from a least-squares circle through its boundary.  None when the image has
    no such disc (an optical camera, or a field wider than the frame)."""
    import cv2
    a = np.asarray(image, dtype=np.float32)
    lo = float(np.percentile(a, 1))
    med = float(np.median(a))
    if med <= lo:
        return None
    mask = (a > lo + 0.3 * (med - lo)).astype(np.uint8)
    n, lab, st, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return None
    k = 1 + int(np.argmax(st[1:, cv2.CC_STAT_AREA]))
    comp = (lab == k).astype(np.uint8)
    if comp.mean() > 0.97:  # no dark surround
        return None
    cnts, _ = cv2.findContours(comp, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(cnts, key=len).reshape(-1, 2).astype(float)
    h, w = a.shape
    c = c[(c[:, 0] > 0) & (c[:, 1] > 0) & (c[:, 0] < w - 1) & (c[:, 1] < h - 1)]  # drop frame edges
    if len(c) < 20:
        return None
    # algebraic circle fit: x^2 + y^2 + D x + E y + F = 0
    A = np.column_stack([c[:, 0], c[:, 1], np.ones(len(c))])
    sol, *_ = np.linalg.lstsq(A, -(c[:, 0] ** 2 + c[:, 1] ** 2), rcond=None)
    cx, cy = -sol[0] / 2, -sol[1] / 2
    r = np.sqrt(max(cx * cx + cy * cy - sol[2], 0.0))
    resid = np.abs(np.hypot(c[:, 0] - cx, c[:, 1] - cy) - r)
    if r <= 0 or np.median(resid) > 0.02 * r:
        return None
    return float(cx), float(cy)


# --- finders -------------------------------------------------------------------------------

def _to_u8(image: np.ndarray) -> np.ndarray:
    """8-bit copy for OpenCV finders that need it (contrast stretched over the 0.1-99.9 %)."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    lo, hi = np.percentile(a, [0.1, 99.9])
    if hi <= lo:
        hi = lo + 1
    return np.clip((a.astype(np.float64) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def find_chessboard(image: np.ndarray, grid: tuple[int, int], spacing_mm: float,
                    subpix_half_window: int | str | None = 11) -> GridDetection:
    """Inner corners of a ``COLSxROWS`` chessboard (COLS, ROWS count inner corners).

    ``cv2.findChessboardCorners`` (adaptive threshold, normalised image) refined with
    ``cv2.cornerSubPix``, falling back to ``cv2.findChessboardCornersSB``.  The refinement's
    half window is ``subpix_half_window``: 11 by default, as OpenCV's calibration sample and
    Bouguet's toolbox use (so results compare with theirs), or ``"auto"``: 11 shrunk to just
    under half the smallest corner spacing, so the window never reaches a neighbouring
    corner (a window that does pulls the corner off by tenths of a pixel; on OpenCV's
    left-camera views ``auto`` lowers the RMS from 0.408 to 0.245 px).
    """
    import cv2
    g = _to_u8(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, c = cv2.findChessboardCorners(g, grid, flags=flags)
    method = "findChessboardCorners+cornerSubPix"
    if ok:
        pts = c.reshape(-1, 2)
        sp = np.hypot(*np.diff(pts.reshape(grid[1], grid[0], 2), axis=1).reshape(-1, 2).T).min()
        auto = subpix_half_window in (None, "auto")
        half = int(max(2, min(11, np.floor(sp / 2) - 1)) if auto else subpix_half_window)
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        c = cv2.cornerSubPix(g, c, (half, half), (-1, -1), crit)
    else:
        ok, c = cv2.findChessboardCornersSB(g, grid, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        method = "findChessboardCornersSB"
        if not ok:
            raise DetectionFailed(f"no {grid[0]}x{grid[1]} chessboard found")
    pts = c.reshape(-1, 2).astype(np.float64)
    # a finder asked for fewer corners than the board has returns a part of it, or a sheared
    # lattice of its corners: both calibrate silently to nonsense
    cells = chessboard_cells(g, pts, grid)
    found = None
    if cells.mean() < CHESS_CELL_FRACTION:
        found = chessboard_size(g, grid)
        if found is None or found == tuple(grid):
            raise GridMismatch(f"the {grid[0]}x{grid[1]} corners {method} found are not a chessboard's (only "
                               f"{100 * cells.mean():.0f} % of the cells between them are single squares): "
                               "is --grid the board's inner corners, COLSxROWS?", None)
    else:
        extra = chessboard_extension(g, pts, grid)
        if any(extra):
            found = (grid[0] + extra[0] + extra[1], grid[1] + extra[2] + extra[3])
        else:
            # a grid larger than the board can be found with a line of "corners" along the
            # board's edge (the outer squares' vertices on the margin): calibrated, every
            # point of the view is a square off
            left, right, top, bottom = chessboard_edge_lines(g, pts, grid)
            if left or right or top or bottom:
                found = (grid[0] - left - right, grid[1] - top - bottom)
    if found is not None:
        how = ("a part of it" if found[0] * found[1] > grid[0] * grid[1] else
               "a line of corners along the board's edge, beyond its inner corners")
        raise GridMismatch(f"the board has {found[0]}x{found[1]} inner corners, --grid says {grid[0]}x{grid[1]} "
                           f"({method} found {how})", found)
    obj = target_points("chessboard", grid, spacing_mm)
    ids = np.arange(len(pts))
    colrow = np.column_stack([ids % grid[0], ids // grid[0]])
    info = {"method": method}
    if method.endswith("cornerSubPix"):
        info.update(subpix_half_window_px=half, corner_spacing_min_px=float(sp))
    return GridDetection(pts, obj, ids, colrow, complete=True,
                         ambiguous=(grid[0] % 2 == grid[1] % 2), info=info)


def _sample_cells(img: np.ndarray, H: np.ndarray, cells: np.ndarray, half: float = 0.25) -> np.ndarray:
    """Mean intensity of ``img`` over the middle of chessboard cells: 3x3 bilinear samples
    within +-``half`` cell of each cell centre ``cells`` (m, 2) in grid units (col, row),
    mapped to the image by the homography ``H``.  NaN where a sample falls outside the image."""
    import cv2
    o = np.linspace(-half, half, 3)
    du, dv = np.meshgrid(o, o)
    g = (cells[:, None, :] + np.column_stack([du.ravel(), dv.ravel()])[None]).reshape(-1, 1, 2)
    xy = cv2.perspectiveTransform(g.astype(np.float64), H).reshape(-1, 2).astype(np.float32)
    v = cv2.remap(img, xy[:, 0].reshape(1, -1), xy[:, 1].reshape(1, -1), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    return v.reshape(len(cells), -1).mean(axis=1)


#: A corner grid is a chessboard's when at least this fraction of the cells between its
#: corners are single squares (uniform, of the colour their parity predicts); a finder asked
#: for a grid smaller than the board can return a sheared lattice of its corners instead.
CHESS_CELL_FRACTION = 0.8
#: A line of cells beyond a found board continues the chessboard when its colours alternate
#: as the cells just inside do, each step by more than this fraction of theirs (a white
#: margin does not alternate; a cluttered background does so by chance, in about half)...
CHESS_EXTEND_RATIO = 0.3
#: ... in at least this fraction of the steps (2 or more) that are in the image.
CHESS_EXTEND_FRACTION = 0.75


def _cell_samples(img: np.ndarray, P: np.ndarray, uv=(0.3, 0.7)) -> np.ndarray:
    """Intensities at the points ``(u, v)``, ``u, v`` in ``uv``, of every cell of the corner
    array ``P`` (R, C, 2) (bilinear in the cell's four corners): (R-1, C-1, len(uv)**2)."""
    import cv2
    P = np.asarray(P, np.float64)
    p00, p10, p01, p11 = P[:-1, :-1], P[:-1, 1:], P[1:, :-1], P[1:, 1:]
    pts = [(1 - u) * (1 - v) * p00 + u * (1 - v) * p10 + (1 - u) * v * p01 + u * v * p11 for v in uv for u in uv]
    xy = np.stack(pts, axis=2).astype(np.float32)  # (R-1, C-1, k, 2)
    flat = xy.reshape(1, -1, 2)
    out = cv2.remap(img, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=float("nan"))
    return out.reshape(xy.shape[:3])


def chessboard_cells(image: np.ndarray, corners_px: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """Per cell between the corners (``(rows-1, cols-1)`` bool): the cell is one square of the
    chessboard, i.e. its four sample points (at 0.3 and 0.7 of its sides) all lie on the side of
    the mid-grey that its colour parity predicts, by over a quarter of the contrast."""
    C, R = grid
    g = np.asarray(image, np.float32)
    S = _cell_samples(g, np.asarray(corners_px, np.float64).reshape(R, C, 2))
    par = np.add.outer(np.arange(R - 1), np.arange(C - 1)) % 2
    m = np.median(S, axis=2)
    if not np.isfinite(m).any() or (par == 0).all():
        return np.isfinite(m)
    e0, e1 = np.nanmedian(m[par == 0]), np.nanmedian(m[par == 1])
    mid, con = 0.5 * (e0 + e1), abs(e0 - e1)
    sgn = np.where(par == 0, np.sign(e0 - mid), np.sign(e1 - mid))
    with np.errstate(invalid="ignore"):
        return np.all((S - mid) * sgn[..., None] > 0.25 * con, axis=2) & (con > 0)


def chessboard_extension(image: np.ndarray, corners_px: np.ndarray, grid: tuple[int, int],
                         max_extra: int = 30) -> tuple[int, int, int, int]:
    r"""How many lines of inner corners the chessboard in ``image`` has beyond the ``grid`` of
    ``corners_px`` found: ``(left, right, top, bottom)`` in the grid's own directions (all 0
    for a board found whole).

    ``findChessboardCorners`` asked for 8x6 finds 8x6 of a 9x6 board.  Beyond the outermost
    corners of a whole board lie one line of the board's squares and then its margin; beyond
    those of a part of it, two lines of squares.  So, side by side, the next corner line out
    is predicted (homography of the three outermost lines) and refined (``cornerSubPix``), and
    the cells half a square beyond it are sampled (:func:`_sample_cells`): their intensities
    :math:`v_k` along the line continue the board when their steps :math:`v_{k+1} - v_k`
    repeat those of the cells just inside the board (two cells in, the same colour parity),
    each by more than ``CHESS_EXTEND_RATIO`` of theirs, in ``CHESS_EXTEND_FRACTION`` of the
    steps.  Then the line is added and the next one tried.
    """
    import cv2
    C, R = grid
    if R < 3 or C < 3:
        return (0, 0, 0, 0)
    g = np.asarray(image, np.float32)
    P = np.asarray(corners_px, np.float64).reshape(R, C, 2)
    known = {(c, r): P[r, c] for r in range(R) for c in range(C)}
    lo, hi = [0, 0], [C - 1, R - 1]  # extent (col, row) of the known corners
    extra = [0, 0, 0, 0]
    u8 = _to_u8(g)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    h, w = g.shape

    def line_homography(axis, lines):
        src = np.array([k for k in known if k[axis] in lines], np.float64)
        return cv2.findHomography(src, np.array([known[(int(a), int(b))] for a, b in src]))[0]

    for side, (axis, sgn) in enumerate(((0, -1), (0, 1), (1, -1), (1, 1))):
        other = 1 - axis
        for _ in range(max_extra):
            edge = lo[axis] if sgn < 0 else hi[axis]
            H = line_homography(axis, [edge - sgn * k for k in range(3)])
            if H is None:
                break
            # the next corner line out, where the three outermost lines put it, refined: on a
            # whole board these are the outer squares' vertices on the margin
            new = edge + sgn
            span = range(lo[other], hi[other] + 1)
            keys = [(new, r) if axis == 0 else (r, new) for r in span]
            pred = cv2.perspectiveTransform(np.array(keys, np.float64).reshape(-1, 1, 2), H).reshape(-1, 2)
            last = np.array([known[(edge, r) if axis == 0 else (r, edge)] for r in span])
            for k, (p, d) in enumerate(zip(pred, np.hypot(*(pred - last).T))):
                hw = int(max(2, min(11, np.floor(0.35 * d))))  # the window must not reach the next line
                if not (hw + 1 < p[0] < w - hw - 2 and hw + 1 < p[1] < h - hw - 2):
                    continue
                ref = cv2.cornerSubPix(u8, p.astype(np.float32).reshape(1, 1, 2), (hw, hw), (-1, -1), crit)
                ref = ref.reshape(2).astype(np.float64)
                if np.hypot(*(ref - p)) < 0.3 * d:
                    pred[k] = ref
            added = dict(zip(keys, pred))
            known.update(added)
            H = line_homography(axis, [new, edge, edge - sgn])
            ratio = _cell_step_ratio(g, H, axis, lo[other], hi[other], new + 0.5 * sgn, edge - 0.5 * sgn)
            seen = np.isfinite(ratio)
            if (seen.sum() < max(2, 0.75 * len(ratio))
                    or np.mean(ratio[seen] > CHESS_EXTEND_RATIO) < CHESS_EXTEND_FRACTION):
                for k in added:
                    del known[k]
                break
            if sgn < 0:
                lo[axis] = new
            else:
                hi[axis] = new
            extra[side] += 1
    return tuple(extra)


def _cell_step_ratio(g: np.ndarray, H, axis: int, lo: int, hi: int, beyond: float, inside: float) -> np.ndarray:
    """The steps of intensity between neighbouring cells along a line of cells at ``beyond``
    (grid units along ``axis``), over those of the line at ``inside``, for the cells ``lo`` to
    ``hi`` across (:func:`_sample_cells` through the homography ``H``; NaN where ``H`` is None
    or a cell is outside the image): about +1 where the board continues in step, -1 where it
    continues a square further, 0 where the line ``beyond`` is the margin."""
    other = 1 - axis
    cells = np.zeros((hi - lo, 2))
    cells[:, other] = np.arange(lo, hi) + 0.5
    rows = []
    for at in (beyond, inside):
        cells[:, axis] = at
        rows.append(_sample_cells(g, H, cells) if H is not None else np.full(len(cells), np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.diff(rows[0]) / np.diff(rows[1])


def chessboard_edge_lines(image: np.ndarray, corners_px: np.ndarray, grid: tuple[int, int]) -> tuple[bool, ...]:
    """Which outermost corner lines ``(left, right, top, bottom)`` of a found grid lie on the
    board's edge, not inside it.  Beyond the outermost inner corners of a board lies a line of
    its squares, whose colours alternate as the cells just inside do (each the opposite
    colour); beyond a line on the board's edge lies its margin, which does not alternate.  An
    edge line is one where the cells half a square out change by less than
    ``CHESS_EXTEND_RATIO`` of the cells inside in at least ``CHESS_EXTEND_FRACTION`` of the
    steps.  OpenCV's finder asked for 10x6 on a 9x6 board returned one (OpenCV's left13.jpg):
    its cells are all squares, so the cell test passes it."""
    import cv2
    C, R = grid
    if R < 3 or C < 3:
        return (False, False, False, False)
    g = np.asarray(image, np.float32)
    P = np.asarray(corners_px, np.float64).reshape(R, C, 2)
    out = []
    for axis, sgn in ((0, -1), (0, 1), (1, -1), (1, 1)):
        n_ax, n_other = (C, R) if axis == 0 else (R, C)
        edge = 0 if sgn < 0 else n_ax - 1
        lines = [edge - sgn * k for k in range(3)]
        src = np.array([(a, b) for a in range(C) for b in range(R) if (a, b)[axis] in lines], np.float64)
        H = cv2.findHomography(src, np.array([P[int(b), int(a)] for a, b in src]))[0]     # None: no ratio
        ratio = np.abs(_cell_step_ratio(g, H, axis, 0, n_other - 1, edge + 0.5 * sgn, edge - 0.5 * sgn))
        seen = np.isfinite(ratio)
        out.append(bool(seen.sum() >= max(2, 0.75 * len(ratio))
                        and np.mean(ratio[seen] < CHESS_EXTEND_RATIO) >= CHESS_EXTEND_FRACTION))
    return tuple(out)


def chessboard_size(image: np.ndarray, grid: tuple[int, int]) -> tuple[int, int] | None:
    """The inner corners ``(cols, rows)`` of the chessboard in ``image`` whatever its size, in
    the orientation of ``grid`` (the longer side first when ``grid``'s is): OpenCV's
    ``findChessboardCornersSBWithMeta`` with ``CALIB_CB_LARGER``, less the lines along its
    border whose cells are not single squares (it takes a board's outer squares' vertices on
    the margin for corners) and its outermost lines, grown again by
    :func:`chessboard_extension` (which stops at the margin).  None when no board
    is found or its cells are not single squares.  About a second per image: used
    only to name the board when ``grid`` does not fit it."""
    import cv2
    u8 = _to_u8(image)
    try:
        ok, c, meta = cv2.findChessboardCornersSBWithMeta(
            u8, tuple(grid), cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_LARGER)
    except cv2.error:
        return None
    if not ok or meta is None:
        return None
    rows, cols = meta.shape[:2]
    if rows * cols != len(c):
        return None
    P = c.reshape(rows, cols, 2).astype(np.float64)
    while P.shape[0] >= 3 and P.shape[1] >= 3:
        good = chessboard_cells(u8, P.reshape(-1, 2), (P.shape[1], P.shape[0]))
        bad = {"top": 1 - good[0].mean(), "bottom": 1 - good[-1].mean(),
               "left": 1 - good[:, 0].mean(), "right": 1 - good[:, -1].mean()}
        worst = max(bad, key=bad.get)
        if bad[worst] <= 0.5:
            break
        P = {"top": P[1:], "bottom": P[:-1], "left": P[:, 1:], "right": P[:, :-1]}[worst]
    size = (P.shape[1], P.shape[0])
    if min(size) < 3 or chessboard_cells(u8, P.reshape(-1, 2), size).mean() < CHESS_CELL_FRACTION:
        return None
    if min(size) >= 5:  # the outermost lines may be the margin's vertices: grow back from inside
        P, size = P[1:-1, 1:-1], (size[0] - 2, size[1] - 2)
    extra = chessboard_extension(u8, P.reshape(-1, 2), size)
    size = (size[0] + extra[0] + extra[1], size[1] + extra[2] + extra[3])
    return (max(size), min(size)) if grid[0] >= grid[1] else (min(size), max(size))


#: The Gaussian smoothing (sigma, px) of the blob signal :func:`find_circles` tries in turn
#: until the lattice holds the whole grid (0: none).
BLOB_SMOOTH_RETRIES_PX = (0.0, 1.0, 2.0)


def find_circles(image: np.ndarray, grid: tuple[int, int], spacing_mm: float, *,
                 asymmetric: bool = False, polarity: Literal["dark", "bright"] = "dark",
                 diameter_px: float | None = None, mask: np.ndarray | None = None,
                 allow_partial: bool = True) -> GridDetection:
    """Circle / bead grid: sub-pixel blob centres (:func:`detect_blobs`) ordered by lattice growth.

    With ``allow_partial`` a grid cut off by the field of view is accepted (at least half
    of its points, in a connected lattice); its ids are then relative to the first row and
    column seen (fine for intrinsics; ``complete`` is False).
    """
    pattern = "asymmetric-circles" if asymmetric else "circles"
    n_target = grid[0] * grid[1]
    # blobs as they are, then, where the lattice falls short of the grid, with the signal
    # smoothed (a matched filter): beads blurred to a sigma of 2 px were plainly visible but
    # their pixels each near the noise, 63 of 136 found, and every view was lost (exit 1)
    best, first_error = None, None
    for smooth in BLOB_SMOOTH_RETRIES_PX:
        try:
            b = detect_blobs(image, polarity=polarity, diameter_px=diameter_px, mask=mask, smooth_px=smooth)
        except DetectionFailed as e:
            first_error = first_error or e
            continue
        ij_b, ok_b = lattice_indices(b.xy) if len(b.xy) >= 6 else (np.zeros((len(b.xy), 2), int),
                                                                    np.zeros(len(b.xy), bool))
        if best is None or ok_b.sum() > best[2].sum():
            best = (b, ij_b, ok_b, smooth)
        if ok_b.sum() >= n_target:
            break
    if best is None:
        raise first_error
    blobs, ij, ok, smooth = best
    if len(blobs.xy) < 6:
        raise DetectionFailed(f"only {len(blobs.xy)} {polarity} blobs found" + (
            "" if diameter_px is not None else
            f" with the blob diameter estimated from the image at {blobs.diameter_px:.1f} px: if the estimate "
            "failed, give --diameter-px"))
    xy = blobs.xy[ok]
    ij = ij[ok]
    info = {"method": "blobs+lattice", "polarity": polarity, "diameter_px": blobs.diameter_px,
            "n_blobs": int(len(blobs.xy)), "n_on_lattice": int(ok.sum()), "smooth_px": smooth}
    if len(xy) > n_target:
        # a speck of dust (or a bead) on a lattice site just beyond the grid: a lone point or two
        # on an outer row or column of the lattice; kept out where the rest is the whole grid
        # (one such speck had lost 3 of 12 views, "137 blobs on the lattice, more than the 8x17
        # grid holds", with nothing said)
        def whole(mask):
            try:
                return fit_to_target(ij[mask], pattern, grid, xy[mask])[1]
            except DetectionFailed:
                return False

        keep = _without_stray_edges(ij, len(xy) - n_target, whole) if len(xy) - n_target <= 4 else None
        if keep is not None:
            info["stray_points_px"] = xy[~keep].round(2).tolist()
            xy, ij = xy[keep], ij[keep]
    if len(xy) > n_target:
        _raise_other_grid(f"{len(xy)} blobs on the lattice, more than the {grid[0]}x{grid[1]} grid holds",
                          ij, xy, pattern, grid)
    if len(xy) < n_target and (not allow_partial or len(xy) < n_target // 2):
        _raise_other_grid(f"only {len(xy)} of {n_target} grid points found", ij, xy, pattern, grid)
    try:
        colrow, complete, ambiguous = fit_to_target(ij, pattern, grid, xy)
    except DetectionFailed as e:
        _raise_other_grid(str(e), ij, xy, pattern, grid)
    ids = colrow[:, 1] * grid[0] + colrow[:, 0]
    order = np.argsort(ids)
    obj = target_points(pattern, grid, spacing_mm)[ids[order]]
    return GridDetection(xy[order], obj, ids[order], colrow[order], complete=complete,
                         ambiguous=ambiguous, info=info)


def _without_stray_edges(ij: np.ndarray, excess: int, whole=None, max_lines: int = 2) -> np.ndarray | None:
    """A mask leaving out ``excess`` points that lie on outer lattice lines (rows or columns in
    either lattice direction, or the diagonals, an asymmetric grid's rows), one line or two,
    for which ``whole(mask)`` says the rest is the whole grid (every candidate tried: a grid's
    own corner is a lone point on an outer diagonal too); None where none does."""
    from itertools import combinations

    if excess <= 0:
        return None
    lines = []
    for coord in (ij[:, 0], ij[:, 1], ij[:, 0] + ij[:, 1], ij[:, 0] - ij[:, 1]):
        for edge in (coord.min(), coord.max()):
            on = coord == edge
            if on.sum() <= excess:
                lines.append(on)
    for r in range(1, max_lines + 1):
        for combo in combinations(lines, r):
            drop = np.logical_or.reduce(combo)
            if drop.sum() == excess and (whole is None or whole(~drop)):
                return ~drop
    return None


def lattice_grids(ij: np.ndarray, xy: np.ndarray | None = None) -> list[tuple[str, tuple[int, int]]]:
    """The complete circle grids that points on a lattice form: ``[(pattern, (cols, rows))]``.

    For each layout (``asymmetric-circles``, ``circles``) and each short change of lattice
    basis, the bounding box of the points in target units gives the only grid they could
    fill; it is kept when every one of its positions is occupied (:func:`fit_to_target`).
    Used to tell a user which ``--pattern``/``--grid`` the views show when the one asked
    for does not fit.  The first is the reading closest to the image axes (a symmetric grid
    seen turned by 90 degrees also fits its transpose).

    >>> ij = np.array([[a, b] for b in range(3) for a in range(4)])
    >>> lattice_grids(ij)
    [('circles', (4, 3)), ('circles', (3, 4))]
    """
    ij = np.asarray(ij, int)
    n = len(ij)
    out: list[tuple[str, tuple[int, int]]] = []
    if n < 4:
        return out
    for pattern in ("asymmetric-circles", "circles"):
        conv = np.array([[1, 1], [-1, 1]]) if pattern == "asymmetric-circles" else np.eye(2, dtype=int)
        for m in _UNIMODULAR:
            XY = ij @ (conv @ m).T
            span = XY.max(axis=0) - XY.min(axis=0)
            if pattern == "asymmetric-circles":
                cols, rows = (int(span[0]) + 2) // 2, int(span[1]) + 1
            else:
                cols, rows = int(span[0]) + 1, int(span[1]) + 1
            if cols < 2 or rows < 2 or cols * rows != n or (pattern, (cols, rows)) in out:
                continue
            try:
                _, complete, _ = fit_to_target(ij, pattern, (cols, rows), xy)
            except DetectionFailed:
                continue
            if complete:
                out.append((pattern, (cols, rows)))
    return out


def _raise_other_grid(message: str, ij: np.ndarray, xy: np.ndarray, pattern: str, grid: tuple[int, int]):
    """Raise :class:`GridMismatch` (the view fills a complete grid of another size or layout:
    ``"...; the 136 points form a complete 8x17 asymmetric-circles grid: is it --pattern ...
    --grid 8x17 ...?"``), else :class:`DetectionFailed` with ``message``."""
    grids = [g for g in lattice_grids(ij, xy) if g != (pattern, tuple(grid))]
    if not grids:
        raise DetectionFailed(message)
    p, (c, r) = grids[0]
    raise GridMismatch(f"{message}; the {len(ij)} points form a complete {c}x{r} {p} grid: is it --pattern {p} "
                       f"--grid {c}x{r} (OpenCV's convention: circles per row x rows)?", (c, r), p)


def aruco_dictionaries() -> list[str]:
    """The names of OpenCV's predefined ArUco dictionaries (``cv2.aruco.DICT_*``)."""
    import cv2
    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and isinstance(getattr(cv2.aruco, n), int))


def check_charuco(spacing_mm: float, marker_mm: float | None, dictionary: str) -> None:
    """ValueError unless ``dictionary`` names a predefined ArUco dictionary and the marker
    (if given) is smaller than the square it sits in."""
    names = aruco_dictionaries()
    if dictionary not in names:
        raise ValueError(f"unknown ArUco dictionary {dictionary!r}; OpenCV's are: {', '.join(names)}")
    if marker_mm is not None and not 0 < float(marker_mm) < float(spacing_mm):
        raise ValueError(f"the ChArUco marker ({marker_mm:g} mm) must be smaller than the square it sits in "
                         f"(--spacing-mm {spacing_mm:g})")


def find_charuco(image: np.ndarray, grid: tuple[int, int], spacing_mm: float, *,
                 marker_mm: float | None = None, dictionary: str = "DICT_4X4_50",
                 min_corners: int = 6) -> GridDetection:
    """ChArUco board with ``COLSxROWS`` *squares* (so (COLS-1)x(ROWS-1) inner corners).

    ``marker_mm`` defaults to 0.75 of the square (OpenCV's tutorials use 0.5-0.8).  The
    board's ArUco ids fix its orientation, so the detection is never ambiguous.
    """
    import cv2
    check_charuco(spacing_mm, marker_mm, dictionary)
    aruco = cv2.aruco
    d = aruco.getPredefinedDictionary(getattr(aruco, dictionary))
    board = aruco.CharucoBoard(grid, float(spacing_mm), float(marker_mm or 0.75 * spacing_mm), d)
    det = aruco.CharucoDetector(board)
    corners, ids, _, _ = det.detectBoard(_to_u8(image))
    if ids is None or len(ids) < min_corners:
        raise DetectionFailed(f"ChArUco board: {0 if ids is None else len(ids)} corners found, "
                              f"need at least {min_corners}")
    ids = ids.ravel().astype(int)
    allc = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    cols_inner = grid[0] - 1
    order = np.argsort(ids)
    ids = ids[order]
    pts = corners.reshape(-1, 2)[order].astype(np.float64)
    colrow = np.column_stack([ids % cols_inner, ids // cols_inner])
    return GridDetection(pts, allc[ids], ids, colrow, complete=len(ids) == len(allc),
                         ambiguous=False, info={"method": "CharucoDetector", "dictionary": dictionary})


def find_target(image: np.ndarray, pattern: str, grid: tuple[int, int], spacing_mm: float,
                **kw) -> GridDetection:
    """Dispatch to the finder for ``pattern`` (one of :data:`PATTERNS`)."""
    if pattern == "chessboard":
        return find_chessboard(image, grid, spacing_mm)
    if pattern in ("circles", "asymmetric-circles"):
        return find_circles(image, grid, spacing_mm, asymmetric=pattern == "asymmetric-circles", **kw)
    if pattern == "charuco":
        return find_charuco(image, grid, spacing_mm, **{k: v for k, v in kw.items()
                                                         if k in ("marker_mm", "dictionary")})
    raise ValueError(f"pattern must be one of {', '.join(PATTERNS)}, got {pattern!r}")
