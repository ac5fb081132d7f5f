"""Figures of ``bsipipe track``: the trajectories (``track.png``) and one frame of each view
with the detections overlaid (``overlay.png``)."""

from __future__ import annotations

import numpy as np
import pandas as pd

#: Tracks named in the trajectory figure's legend (the first ones, by first appearance).
MAX_LEGEND = 20


def _figure(figsize):
    """A :class:`matplotlib.figure.Figure` of its own (no pyplot: its import and global state
    cost a command about a quarter of a second and buy nothing when writing files)."""
    from matplotlib.figure import Figure
    return Figure(figsize=figsize)


def trajectories_figure(table2d: pd.DataFrame, points3d: pd.DataFrame | None = None, title: str = ""):
    """2-D tracks of every view (x_px, y_px per marker; lost frames left as gaps, losses and
    re-finds marked) and, with 3-D points, x/y/z in mm against time (raw lines, filtered
    dashed where present).  Returns a matplotlib Figure."""
    import matplotlib
    views = list(pd.unique(table2d["view"]))
    n3 = 0 if points3d is None or points3d.empty else 1
    fig = _figure((5.2 * (len(views) + n3), 4.8))
    axes = fig.subplots(1, len(views) + n3, squeeze=False)
    cmap = matplotlib.colormaps["tab10"]
    markers = list(pd.unique(table2d["marker"]))
    colour = {m: cmap(i % 10) for i, m in enumerate(markers)}
    for ax, v in zip(axes[0], views):
        t = table2d[table2d["view"] == v]
        for m, g in t.groupby("marker", sort=False):
            g = g.sort_values("frame")
            ax.plot(g["x_px"], g["y_px"], "-", lw=1.0, color=colour[m], label=m)
            lost = g[~g["found"].astype(bool)]
            if len(lost):
                last = g["x_px"].ffill(), g["y_px"].ffill()
                ax.plot(last[0][lost.index], last[1][lost.index], "x", ms=4, color=colour[m])
        ax.invert_yaxis()
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        ax.set_title(f"{v}: 2-D tracks (x: last position while lost)", fontsize=9)
    if n3:
        ax = axes[0][-1]
        p = points3d.sort_values("frame")
        tcol = "time_s" if p["time_s"].notna().any() else "frame"
        for m, g in p.groupby("marker", sort=False):
            for c, ls in (("x_mm", "-"), ("y_mm", "--"), ("z_mm", ":")):
                y = g[c] - g[c].dropna().iloc[0] if g[c].notna().any() else g[c]
                ax.plot(g[tcol], y, ls, lw=1.0, color=colour.get(m, "k"))
        ax.set_xlabel("time (s)" if tcol == "time_s" else "frame")
        ax.set_ylabel("displacement from the first position (mm)")
        ax.set_title("3-D: x solid, y dashed, z dotted", fontsize=9)
    h, lab = axes[0][0].get_legend_handles_labels()
    if h:
        # a legend names up to MAX_LEGEND tracks (an automatic run can have hundreds: the
        # legend would cost more than the plot and say nothing); colours repeat every 10
        more = len(lab) - MAX_LEGEND
        h, lab = h[:MAX_LEGEND], lab[:MAX_LEGEND]
        if more > 0:
            lab[-1] = f"{lab[-1]} (+{more} more)"
        fig.legend(h, lab, loc="lower center", ncol=min(len(lab), 10), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    # fixed margins instead of tight_layout (a full draw of every line just to measure the
    # labels); the saved figure is cropped to its content anyway (bbox_inches="tight")
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.2, top=0.88, wspace=0.3)
    return fig


def overlay_figure(images: dict[str, np.ndarray], table2d: pd.DataFrame, frame: dict[str, int],
                   seeds: pd.DataFrame | None = None, diameter_px: float | dict = 4.0, regions: dict | None = None):
    """One frame per view with the tracked markers (circles, names) and the seeds (+).
    Each panel is cropped to the markers with a margin, so small beads stay visible.
    ``regions``: view -> :class:`~bsipipe.imaging.detect.FieldOfView` searched (its circle,
    and a given mask's outline, drawn dashed where they cross the panel)."""
    from matplotlib.patches import Circle
    views = [v for v in images]
    fig = _figure((6.0 * len(views), 6.0))
    axes = fig.subplots(1, len(views), squeeze=False)
    for ax, v in zip(axes[0], views):
        img = np.asarray(images[v])
        t = table2d[(table2d["view"] == v) & (table2d["frame"] == frame[v])]
        ok = t[t["found"].astype(bool)]
        lo, hi = (float(q) for q in np.percentile(img, [1, 99.5]))
        r = max(2.0 * (diameter_px[v] if isinstance(diameter_px, dict) else diameter_px), 6.0)
        pts = ok[["x_px", "y_px"]].to_numpy()
        h, w = img.shape
        # only the pixels the cropped panel shows are drawn (resampling a whole 1024 x 1024
        # frame costs more than the rest of the figure); extent keeps pixel coordinates
        x0, x1, y0, y1 = 0, w, 0, h
        if len(pts):
            m = 8 * r
            x0 = int(np.clip(np.floor(pts[:, 0].min() - m), 0, w - 1))
            x1 = int(np.clip(np.ceil(pts[:, 0].max() + m) + 1, x0 + 1, w))
            y0 = int(np.clip(np.floor(pts[:, 1].min() - m), 0, h - 1))
            y1 = int(np.clip(np.ceil(pts[:, 1].max() + m) + 1, y0 + 1, h))
        ax.imshow(img[y0:y1, x0:x1], cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1, interpolation="nearest",
                  extent=(x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5))
        for rr in ok.itertuples():
            ax.add_patch(Circle((rr.x_px, rr.y_px), r, fill=False, color="tab:orange", lw=0.8))
            ax.annotate(str(rr.marker), (rr.x_px + r, rr.y_px - r), color="tab:orange", fontsize=7)
        fov = (regions or {}).get(v)
        if fov is not None and fov.found:
            ax.add_patch(Circle(tuple(fov.centre_px), fov.radius_px, fill=False, color="tab:green", lw=0.8, ls="--"))
        if fov is not None and fov.region is not None:
            part = np.asarray(fov.region[y0:y1, x0:x1], float)
            if 0.0 < part.mean() < 1.0:               # the mask's edge crosses the panel
                ax.contour(np.arange(x0, x1), np.arange(y0, y1), part, levels=[0.5], colors="tab:green",
                           linewidths=0.8, linestyles="--")
        if seeds is not None and len(seeds):
            s = seeds[seeds["view"] == v]
            ax.plot(s["x_px"], s["y_px"], "+", color="tab:cyan", ms=6, mew=0.8, label="seeds")
        if len(pts):
            ax.set_xlim(max(pts[:, 0].min() - m, -0.5), min(pts[:, 0].max() + m, w - 0.5))
            ax.set_ylim(min(pts[:, 1].max() + m, h - 0.5), max(pts[:, 1].min() - m, -0.5))
        given = " (dashed: the region of interest given)" if fov is not None and fov.given else ""
        ax.set_title(f"{v}, frame {frame[v]}: {len(ok)} of {len(t)} markers found{given}", fontsize=9)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.08, top=0.94, wspace=0.25)
    return fig
