"""Figure of the reprojection residual field of one calibration view (``residuals_<view>.png``)."""

from __future__ import annotations

import numpy as np


def residual_figure(title: str, image_points: np.ndarray, residuals: np.ndarray, image_size: tuple[int, int],
                    rms_px: float | None = None, heldout_rms_px: float | None = None):
    """Arrows from each detected point along its residual (observed - projected), magnified so
    the 90th-percentile arrow is 4 % of the image width; colour = |residual| px.

    image_points : (n, 2) px; residuals : (n, 2) px.  Returns a matplotlib Figure.
    """
    from matplotlib.figure import Figure

    p = np.asarray(image_points, float).reshape(-1, 2)
    e = np.asarray(residuals, float).reshape(-1, 2)
    mag = np.hypot(e[:, 0], e[:, 1])
    w, h = image_size
    med = float(np.percentile(mag, 90)) if len(mag) else 0.0
    scale = 0.04 * w / med if med > 0 else 1.0
    fig = Figure(figsize=(6.4, 6.4 * h / w + 0.6))
    ax = fig.subplots()
    q = ax.quiver(p[:, 0], p[:, 1], e[:, 0] * scale, e[:, 1] * scale, mag, angles="xy", scale_units="xy",
                  scale=1.0, cmap="viridis", width=0.003)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)  # y down, as in the image
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    sub = [f"arrows x{scale:.0f}"]
    if rms_px is not None:
        sub.append(f"RMS {rms_px:.3f} px")
    if heldout_rms_px is not None and np.isfinite(heldout_rms_px):
        sub.append(f"held-out {heldout_rms_px:.3f} px")
    ax.set_title(f"{title}\n" + ", ".join(sub), fontsize=10)
    fig.colorbar(q, ax=ax, label="|residual| (px)", shrink=0.8)
    return fig
