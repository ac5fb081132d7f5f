"""Quality warnings: results that were computed but should not be trusted blindly.

A command still writes its result; each warning goes into the JSON result's ``warnings``
list (always present, empty when nothing is flagged) and to the console as a logging
WARNING.  A warning is a dict ``{"code": ..., "message": ..., **details}``; the codes:

``parameter-correlation``
    Two fitted parameters with a correlation :math:`|r| > 0.99` (from the covariance of the
    fit): the data pin down a combination of them, not each one.
``interval-spans-zero``
    A material parameter whose 95 % interval contains zero: the data cannot tell it from
    zero (the model may be too rich for the data).
``parameter-undetermined``
    A parameter without a finite standard error (the Jacobian is singular in its direction).
``poor-coverage``
    The calibration target's detected points, pooled over the views used, span a convex hull
    covering less than half of the field of view (the intensifier's circle where the images
    show one, else the image): the distortion model is extrapolated over the rest.
``lossy-frames``
    ``track``: a view's frames come lossily compressed (JPEG files, a video codec other than
    a raw or lossless one, a lossy DICOM transfer syntax): the codec removes the pixel noise
    the detection thresholds, SNR and ``sd_px`` are set from, and smears small beads.
``frame-shifts``
    ``track``: the whole picture jolted between frames in a view (``frame-shift`` events: a
    C-arm's vibration, the head moving): the tracks follow the jolts, but the positions carry
    them, and so do the 3-D points triangulated from them unless the stereo loop's
    ``frame-shift`` takes them out (then ``corrected_by_loop`` is true).
``missing-frames``
    ``track``: numbers missing from a view's frame files (``frame_0057.png`` absent among
    ``frame_0000.png`` ... ``frame_0199.png``, or a gap in a DICOM series' InstanceNumbers):
    the recorder dropped them.  Their indices are left empty, so the later frames keep their
    numbers and still pair with the other view's frames by index (counting the files would
    pair every later frame with the other view's next one, a time offset from there on).
``large-ray-gap``
    Triangulated points whose two back-projected rays pass further apart than five times the
    median ray gap of their marker (and at least :data:`RAY_GAP_FLOOR_MM`) or than a stated
    limit (``track``'s ``max_ray_gap_mm``, default 0.5 mm): a wrong match, an
    identity swap or a bad detection.  Such points are also marked in ``markers3d.csv``'s
    ``flag`` column.
"""

from __future__ import annotations

import logging
from typing import Iterable, Sequence

import numpy as np

log = logging.getLogger(__name__)

#: |r| above which two parameters are reported as not separately identifiable.
CORRELATION_MAX = 0.99
#: Fraction of the field of view the calibration points must span.
COVERAGE_MIN = 0.5
#: Ray gaps above this multiple of the sequence's median are flagged.
RAY_GAP_FACTOR = 5.0
#: ... and never below this (mm): the localisation precision of X-ray marker tracking (RSA,
#: XROMM: 0.1 mm or better), under which a gap is no evidence of a bad point (a calibration
#: leaves a few hundredths of a mm of systematic gap at some markers).
RAY_GAP_FLOOR_MM = 0.1


def warning(code: str, message: str, logger: logging.Logger | None = None, **details) -> dict:
    """Log ``message`` at WARNING and return the warning's dict for the JSON result."""
    (logger or log).warning("%s", message)
    return {"code": code, "message": message, **details}


# --------------------------------------------------------------------------- fits


def listed(items: Sequence, most: int, sep: str = ", ") -> str:
    """The first ``most`` items for a message, and how many more.

    >>> listed([4, 9, 12, 30], 2)
    '4, 9 and 2 more'
    """
    return sep.join(map(str, items[:most])) + (f" and {len(items) - most} more" if len(items) > most else "")


def correlation_matrix(cov) -> np.ndarray:
    """:math:`r_{ij} = C_{ij} / \\sqrt{C_{ii} C_{jj}}` (NaN where a variance is not positive)."""
    c = np.asarray(cov, float)
    d = np.sqrt(np.where(np.diag(c) > 0, np.diag(c), np.nan))
    with np.errstate(invalid="ignore", divide="ignore"):
        return c / np.outer(d, d)


def fit_warnings(names: Sequence[str], cov, ci95: dict, *, zero_checked: Iterable[str] = (),
                 r_max: float = CORRELATION_MAX, logger: logging.Logger | None = None) -> list[dict]:
    """Identifiability warnings of a least-squares fit.

    Parameters
    ----------
    names : sequence of str, length p
        The fitted parameters in the order of ``cov``.
    cov : array_like, shape (p, p)
        Their covariance (in the fitted parametrisation; a correlation does not depend on a
        monotonic reparametrisation to first order).
    ci95 : dict name -> [lo, hi]
    zero_checked : names whose interval must not contain zero (material parameters: an
        offset or drift of zero is a finding, not a failure).
    """
    names = list(names)
    out: list[dict] = []
    c = np.asarray(cov, float).reshape(len(names), len(names)) if len(names) else np.zeros((0, 0))
    var = np.diag(c) if len(names) else np.zeros(0)
    for j, n in enumerate(names):
        if not (np.isfinite(var[j]) and var[j] > 0):
            out.append(warning("parameter-undetermined", f"fit: parameter {n} has no finite standard error (the "
                                                         f"data do not determine it)", logger, param=n))
    r = correlation_matrix(c) if len(names) else c
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if np.isfinite(r[i, j]) and abs(r[i, j]) > r_max:
                out.append(warning("parameter-correlation",
                                   f"fit: parameters {names[i]} and {names[j]} are correlated (r = {r[i, j]:+.4f}, "
                                   f"|r| > {r_max}): the data determine a combination of them, not each one",
                                   logger, params=[names[i], names[j]], r=float(r[i, j]), r_max=r_max))
    for n in zero_checked:
        lo, hi = (ci95.get(n) or [np.nan, np.nan])[:2]
        if lo is not None and hi is not None and np.isfinite(lo) and np.isfinite(hi) and lo <= 0.0 <= hi:
            out.append(warning("interval-spans-zero", f"fit: the 95 % interval of {n}, [{lo:.4g}, {hi:.4g}], contains "
                                                      f"zero: the data cannot tell it from zero", logger,
                               param=n, ci95=[float(lo), float(hi)]))
    return out


# --------------------------------------------------------------------------- calibration


def hull_coverage(points_px, field_mask: np.ndarray, step_px: int | None = None) -> float:
    """Fraction of the ``field_mask`` pixels (h, w) inside the convex hull of ``points_px`` (n, 2).

    Pixel centres are sampled every ``step_px`` (default: about 256 samples a side).
    """
    from matplotlib.path import Path as _Path
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points_px, float).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    h, w = field_mask.shape
    step = step_px or max(1, int(max(h, w) // 256))
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    inside_field = field_mask[ys, xs]
    n_field = int(inside_field.sum())
    if n_field == 0 or len(pts) < 3:
        return 0.0
    try:
        hull = ConvexHull(pts)
    except QhullError:  # collinear points span no area
        return 0.0
    poly = _Path(pts[hull.vertices])
    grid = np.column_stack([xs[inside_field], ys[inside_field]]).astype(float)
    return float(poly.contains_points(grid).sum() / n_field)


def coverage_warning(view: str, points_px, image: np.ndarray, *, min_fraction: float = COVERAGE_MIN,
                     logger: logging.Logger | None = None) -> tuple[dict, dict | None]:
    """``(coverage summary, warning or None)`` of one camera's calibration points.

    The field is the intensifier's circle found in ``image`` (one of the camera's views),
    else the whole image.
    """
    from .imaging.detect import find_field_of_view

    fov = find_field_of_view(np.asarray(image))
    frac = hull_coverage(points_px, fov.mask())
    field = "intensifier circle" if fov.found else "image"
    summary = {"hull_fraction": frac, "field": field, "min_fraction": min_fraction, "field_of_view": fov.to_dict()}
    if frac >= min_fraction:
        return summary, None
    return summary, warning("poor-coverage", f"calibrate: {view}: the target's points cover {100 * frac:.0f} % of the "
                                             f"{field} (convex hull of every view used; at least "
                                             f"{100 * min_fraction:.0f} % wanted): the distortion model is "
                                             f"extrapolated over the rest", logger, view=view, hull_fraction=frac,
                            field=field, min_fraction=min_fraction)


# --------------------------------------------------------------------------- triangulation


def ray_gap_flags(ray_gap_mm, markers=None, *, factor: float = RAY_GAP_FACTOR, floor_mm: float = RAY_GAP_FLOOR_MM,
                  max_mm: float | None = None) -> tuple[np.ndarray, dict]:
    """Which ray gaps are large.

    A gap is large above ``max(factor x median of its marker's gaps, floor_mm)``, or above
    ``max_mm`` when given.  The marker's own median absorbs the steady gap a calibration leaves
    at some markers (a bias, not a bad point); the floor keeps a marker with tiny gaps from
    flagging ordinary ones.

    ``ray_gap_mm`` (n,), NaN where a point has no two-view gap (never flagged); ``markers``
    (n,) the marker of each point (None: all one marker).  Returns the boolean mask and
    ``{"median_mm" (all markers), "factor", "floor_mm", "max_mm", "threshold_mm": {marker: mm}}``.
    """
    g = np.asarray(ray_gap_mm, float)
    names = np.full(len(g), "", dtype=object) if markers is None else np.asarray(markers, dtype=object)
    ok = np.isfinite(g)
    med = float(np.median(g[ok])) if ok.any() else float("nan")
    flag = np.zeros(len(g), bool)
    thresholds: dict[str, float] = {}
    for m in dict.fromkeys(names[ok]):
        sel = ok & (names == m)
        thr = max(factor * float(np.median(g[sel])), floor_mm)
        thresholds[str(m)] = thr
        flag |= sel & (g > thr)
    if max_mm is not None:
        flag |= ok & (g > max_mm)
    return flag, {"median_mm": med, "factor": factor, "floor_mm": floor_mm, "max_mm": max_mm,
                  "threshold_mm": thresholds}
