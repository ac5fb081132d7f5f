"""Figure of ``bsipipe export-fe`` (``handoff.png``): the FE set-up at a glance, so a person can see
that the indentor, the markers and the interface springs sit where they should before a solver
runs: the mesh from above and from the side (CT frame), and the indentor's depth and the force
target against FE time."""

from __future__ import annotations

import numpy as np


def handoff_figure(h, title: str = ""):
    """Four panels from a :class:`~bsipipe.fe.export.Handoff`: the mesh's nodes (grey), the
    interface springs' brain nodes (blue), the markers at rest (names), the indentor's contact
    point and axis (red) seen along the CT's z and y; the indentor's depth on the FE clock (the
    deck's amplitude, and the X-ray track and the Micro Tester log where the trajectory has
    them); the force target.  Returns a matplotlib Figure."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(16.0, 4.4))
    axes = fig.subplots(1, 4, gridspec_kw={"width_ratios": [1.0, 1.0, 1.15, 1.15], "wspace": 0.32})
    xyz = np.asarray(h.mesh.coords_mm, float)
    rng = np.random.default_rng(0)
    show = xyz if len(xyz) <= 4000 else xyz[rng.choice(len(xyz), 4000, replace=False)]
    brain = h.mesh.coords_of(np.unique(h.springs.brain_nodes)) if h.springs is not None else np.zeros((0, 3))
    m = h.markers
    rest = m[m["frame"] == m["frame"].min()].drop_duplicates("marker") if len(m) else m
    tip, axis = np.asarray(h.contact_point_mm, float), np.asarray(h.axis, float)
    for ax, (i, j) in zip(axes[:2], ((0, 1), (0, 2))):
        ax.plot(show[:, i], show[:, j], ".", ms=1.0, color="0.75", label="mesh nodes")
        if len(brain):
            ax.plot(brain[:, i], brain[:, j], ".", ms=2.0, color="tab:blue", label="spring (brain) nodes")
        cols = ["x0_mm", "y0_mm", "z0_mm"]
        for _, r in rest.iterrows():
            ax.plot(r[cols[i]], r[cols[j]], "o", mfc="none", color="tab:green", ms=5)
            ax.annotate(str(r["marker"]), (r[cols[i]], r[cols[j]]), xytext=(3, 2), textcoords="offset points",
                        fontsize=7, color="tab:green")
        ax.plot(tip[i], tip[j], "x", color="tab:red", ms=8, mew=2, label="indentor contact point")
        d = float(h.depth_mm) if np.isfinite(h.depth_mm) else 5.0
        ax.annotate("", xy=(tip[i] + d * axis[i], tip[j] + d * axis[j]), xytext=(tip[i], tip[j]),
                    arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.5})
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{'xyz'[i]} (mm)", fontsize=8)
        ax.set_ylabel(f"{'xyz'[j]} (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"CT frame, seen along {'z' if j == 1 else 'y'}", fontsize=9)
    axes[0].legend(fontsize=7, loc="best", title=f"red arrow: the indentor's {d:.3g} mm", title_fontsize=7)

    ax = axes[2]
    ax.plot(h.amplitude_time_s, h.amplitude_depth_mm, "-", color="k", lw=1.5, label="deck amplitude")
    tr = h.trajectory
    if tr is not None and len(tr) and "fe_time_s" in tr:
        if "depth_log_mm" in tr:
            ax.plot(tr["fe_time_s"], tr["depth_log_mm"], "-", lw=0.8, color="tab:orange", label="Micro Tester log")
        if all(c in tr for c in ("xray_x_mm", "xray_y_mm", "xray_z_mm")):
            # the tracked tip's advance along the axis past the contact point
            depth = (tr[["xray_x_mm", "xray_y_mm", "xray_z_mm"]].to_numpy(float) - tip) @ axis
            ax.plot(tr["fe_time_s"], np.maximum(depth, 0.0), ".", ms=3, color="tab:red", label="X-ray (tracked tip)")
    ax.set_xlabel("FE time (s)", fontsize=8)
    ax.set_ylabel("indentation depth (mm)", fontsize=8)
    ax.set_title(f"indentor: {h.speed_mm_per_min:.3g} mm/min to {h.depth_mm:.3g} mm", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    ax.tick_params(labelsize=7)

    ax = axes[3]
    t = h.target
    if len(t):
        ax.plot(t["time_s"], t["force_n"], "-", color="tab:purple", lw=1.0)
    ax.set_xlabel("FE time (s)", fontsize=8)
    ax.set_ylabel("force (N)", fontsize=8)
    ax.set_title("force target (the log, contact-zeroed)", fontsize=9)
    ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig
