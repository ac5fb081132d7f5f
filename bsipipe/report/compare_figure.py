"""``compare.png``: FE model against measured marker displacements, per axis (Table 1 drawn).

Built on :class:`matplotlib.figure.Figure` directly (no pyplot state, no GUI backend)."""

from __future__ import annotations

import numpy as np


def compare_figure(table1, sigma_mm: float | None = None, title: str | None = None):
    """Three bar panels (x, y, z: model and measured per marker, mm) and one scatter of model
    against measured over all axes with the line of equality.  ``table1`` is
    :attr:`bsipipe.fe.compare.CompareResult.table1`.  Returns the matplotlib figure."""
    from matplotlib.figure import Figure

    markers = list(dict.fromkeys(table1["marker"]))
    fig = Figure(figsize=(15, 3.8))
    axes = fig.subplots(1, 4, gridspec_kw={"width_ratios": [1, 1, 1, 1.1], "wspace": 0.35})
    x = np.arange(len(markers))
    w = 0.38
    for ax, axis in zip(axes[:3], ("x", "y", "z")):
        t = table1[table1["axis"] == axis].set_index("marker").reindex(markers)
        ax.bar(x - w / 2, t["model_mm"], w, label="FE model", color="tab:blue")
        ax.bar(x + w / 2, t["measured_mm"], w, label="measured", color="tab:orange")
        ax.axhline(0.0, color="0.4", lw=0.6)
        ax.set_xticks(x, markers, rotation=45 if len(markers) > 6 else 0)
        ax.set_title(f"{axis} displacement")
        ax.set_ylabel("mm")
    axes[0].legend(fontsize=8)
    ax = axes[3]
    colours = {"x": "tab:red", "y": "tab:green", "z": "tab:purple"}
    for axis, c in colours.items():
        t = table1[table1["axis"] == axis]
        ax.scatter(t["measured_mm"], t["model_mm"], s=18, color=c, label=axis)
    vals = np.concatenate([table1["measured_mm"].to_numpy(float), table1["model_mm"].to_numpy(float)])
    vals = vals[np.isfinite(vals)]
    lo, hi = (float(vals.min()), float(vals.max())) if len(vals) else (-1.0, 1.0)
    pad = 0.05 * (hi - lo or 1.0)
    ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="0.3", lw=0.8, ls="--")
    ax.set_xlabel("measured (mm)")
    ax.set_ylabel("FE model (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8, title="axis")
    ax.set_title("model vs measured" + (f", sigma = {sigma_mm:.3g} mm" if sigma_mm is not None else ""))
    if title:
        fig.suptitle(title)
    return fig


def compare_time_figure(table, series: dict, markers=None):
    """``compare_time.png``: each marker's measured displacement (x, y, z; lines, every frame of
    ``markers_ct.csv``) and the FE model's at the FE results' times (circles), one panel per
    axis, and sigma of each FE result against time.  ``series``: compare.json's
    ``time_series``.  Returns the matplotlib figure."""
    import matplotlib
    from matplotlib.figure import Figure

    names = list(series["per_marker"])
    cmap = matplotlib.colormaps["tab10"]
    colour = {n: cmap(k % 10) for k, n in enumerate(names)}
    fig = Figure(figsize=(15, 3.8))
    axes = fig.subplots(1, 4, gridspec_kw={"wspace": 0.3})
    t = table[table["marker"].astype(str).isin(names)]
    for j, (ax, axis) in enumerate(zip(axes[:3], ("x", "y", "z"))):
        for n, g in t.groupby("marker", sort=False):
            g = g.sort_values("frame")
            ax.plot(g["time_s"], g[f"d{axis}_mm"], "-", lw=1.0, color=colour[str(n)], label=str(n))
        for r in series["results"]:
            for n, m in r["markers"].items():
                ax.plot(r["time_s"], m["model_mm"][j], "o", ms=4, mfc="none", color=colour[n])
        ax.axhline(0.0, color="0.4", lw=0.6)
        ax.set_title(f"{axis} displacement: measured (line), FE (o)", fontsize=9)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("mm")
    axes[0].legend(fontsize=7, ncol=2)
    ax = axes[3]
    ts = [r["time_s"] for r in series["results"]]
    ax.plot(ts, [r["sigma_mm"] for r in series["results"]], "o-", color="k", ms=4)
    for x, r in zip(ts, series["results"]):
        ax.annotate(str(r["n_markers"]), (x, r["sigma_mm"]), xytext=(0, 4), textcoords="offset points",
                    fontsize=6, ha="center")
    ax.set_title(f"sigma per FE result (n markers above); all: {series['sigma_mm']:.3g} mm", fontsize=9)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("sigma (mm)")
    return fig
