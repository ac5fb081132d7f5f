"""Figure of ``bsipipe register`` (``registration.png``): where the markers are in the CT frame,
how well the transform puts them there, and how they move from the registration frame."""

from __future__ import annotations

import numpy as np
import pandas as pd



def registration_figure(table: pd.DataFrame, ct_mm: dict, frame: int, *, fre_mm: dict | None = None,
                        check_mm: dict | None = None, check_limit_mm: float | None = None,
                        system: str | None = None, title: str = ""):
    """Three panels.  Left: the markers in the CT frame seen from two sides (x-y, x-z): each
    one's CT position (circle) and its tracked position at the registration ``frame`` mapped
    through the transform (cross), named; a marker has one colour in every panel.  Middle: the error of each, the
    references' FRE and the implanted markers' CT check (mapped against their CT position),
    with the check's limit dashed.  Right: each marker's displacement magnitude from the
    registration frame against time (references dashed: they should stay at zero).

    ``table``: ``markers_ct.csv`` (``frame``, ``time_s``, ``marker``, ``x_mm``.., ``dx_mm``..,
    ``role``); ``ct_mm``: marker -> CT position (mm, the file's frame).  Returns a matplotlib
    Figure."""
    from matplotlib.figure import Figure
    from matplotlib.gridspec import GridSpec

    fig = Figure(figsize=(15.0, 5.2))
    gs = GridSpec(2, 3, figure=fig, width_ratios=[1.1, 0.9, 1.3], hspace=0.35, wspace=0.3,
                  left=0.05, right=0.98, bottom=0.12, top=0.86)
    top, side = fig.add_subplot(gs[0, 0]), fig.add_subplot(gs[1, 0])
    err_ax, mot_ax = fig.add_subplot(gs[:, 1]), fig.add_subplot(gs[:, 2])
    at = table[table["frame"] == frame].drop_duplicates("marker").set_index("marker")
    role = table.drop_duplicates("marker").set_index("marker")["role"] if "role" in table else pd.Series(dtype=str)
    names = list(dict.fromkeys(list(ct_mm) + list(at.index) + list(pd.unique(table["marker"]))))
    import matplotlib
    cmap = matplotlib.colormaps["tab10"]
    colour = {n: cmap(k % 10) for k, n in enumerate(names)}
    axis_name = ["x", "y", "z"]
    for ax, (i, j) in ((top, (0, 1)), (side, (0, 2))):
        for n in names:
            c = colour[n]
            if n in ct_mm:
                p = np.asarray(ct_mm[n], float)
                ax.plot(p[i], p[j], "o", mfc="none", mec=c, ms=8)
            if n in at.index and np.isfinite(at.loc[n, ["x_mm", "y_mm", "z_mm"]].to_numpy(float)).all():
                q = at.loc[n, ["x_mm", "y_mm", "z_mm"]].to_numpy(float)
                ax.plot(q[i], q[j], "x", color=c, ms=6)
                ax.annotate(n, (q[i], q[j]), xytext=(4, 3), textcoords="offset points", fontsize=7, color=c)
        ax.set_xlabel(f"{axis_name[i]} (mm)", fontsize=8)
        ax.set_ylabel(f"{axis_name[j]} (mm)", fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=7)
    sysname = f" ({system})" if system else ""
    top.set_title(f"CT frame{sysname}: o CT position, x tracked (frame {frame}) mapped", fontsize=9)

    bars = [(n, v, "reference") for n, v in (fre_mm or {}).items()] + \
           [(n, v, "marker") for n, v in (check_mm or {}).items()]
    if bars:
        y = np.arange(len(bars))
        err_ax.barh(y, [v for _, v, _ in bars], color=[colour.get(n, "0.4") for n, _, _ in bars])
        err_ax.set_yticks(y, [f"{n} ({'FRE' if r == 'reference' else 'CT check'})" for n, _, r in bars], fontsize=7)
        err_ax.invert_yaxis()
        if check_limit_mm is not None and np.isfinite(check_limit_mm) and check_mm:
            err_ax.axvline(check_limit_mm, ls="--", color="k", lw=0.8, label=f"check limit {check_limit_mm:.2g} mm")
            err_ax.legend(fontsize=7, loc="lower right")
    err_ax.set_xlabel("distance, mapped to CT (mm)", fontsize=8)
    err_ax.set_title("references' FRE and implanted markers' CT check", fontsize=9)
    err_ax.tick_params(labelsize=7)

    tcol = "time_s" if "time_s" in table and table["time_s"].notna().any() else "frame"
    for n, g in table.groupby("marker", sort=False):
        g = g.sort_values("frame")
        d = np.linalg.norm(g[["dx_mm", "dy_mm", "dz_mm"]].to_numpy(float), axis=1)
        r = str(role.get(n, "marker"))
        mot_ax.plot(g[tcol], d, "--" if "reference" in r else "-", lw=1.0, color=colour.get(n, "0.4"),
                    label=n + (" (ref.)" if "reference" in r else ""))
    mot_ax.set_xlabel("time (s)" if tcol == "time_s" else "frame", fontsize=8)
    mot_ax.set_ylabel("|displacement| from the registration frame (mm)", fontsize=8)
    mot_ax.set_title("motion in the CT frame (references dashed)", fontsize=9)
    mot_ax.tick_params(labelsize=7)
    h, lab = mot_ax.get_legend_handles_labels()
    if h:
        mot_ax.legend(h[:20], lab[:20], fontsize=7, ncol=2, loc="upper left", frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig
