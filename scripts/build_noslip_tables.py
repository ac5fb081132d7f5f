"""Regenerate the shipped no-slip FE tables, check their interpolation, and run the mesh study.

Usage (from the repository root, with the project's venv)::

    .venv/bin/python scripts/build_noslip_tables.py                 # build + verify shipped tables
    .venv/bin/python scripts/build_noslip_tables.py --aspects 0.75  # another aspect
    .venv/bin/python scripts/build_noslip_tables.py --study         # mesh, bulk, fold-over study
    .venv/bin/python scripts/build_noslip_tables.py --refine -4.7 --aspects 0.5  # refinement only
    .venv/bin/python scripts/build_noslip_tables.py --no-verify     # build only ...
    .venv/bin/python scripts/build_noslip_tables.py --verify-only   # ... and verify later

Tables go to ``bsipipe/mechanics/_data/`` (``--out``), written atomically.  ``--verify``
(on by default) runs the FE at the midpoints of the alpha grid, on a stretch grid that
also holds the midpoints of the stretch grid, and stores the largest interpolation errors
of the force ratio and of the bulge width in the table's metadata.  ``--study`` writes
``noslip_study.json`` next to the tables: the refinement study (the default mesh against
every cell halved at six alphas, a mesh sequence at alpha = -4.7), the bulk
modulus check, the folded layer bonded instead of sliding, uniform 32 x 32 and 64 x 64
meshes without fold-over contact (the published reference's discretisation) and the
frictionless check.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from bsipipe.mechanics import noslip as ns
from bsipipe.mechanics.hyperelastic import ogden_nominal_stress
from bsipipe.provenance import atomic_write_bytes, dumps_json


def _ratio_run(args):
    """(alpha, aspect, stretches, mesh, kwargs) -> (ratio, width, iterations, seconds)."""
    alpha, aspect, stretches, mesh, kwargs = args
    t0 = time.perf_counter()
    try:
        nominal, width, iters = ns._solve_unit(np.asarray(stretches), alpha, aspect, mesh, **kwargs)
    except RuntimeError as exc:  # recorded, not hidden: the study prints it
        print(f"FE failed: {exc}", file=sys.stderr)
        nan = np.full(len(stretches), np.nan)
        return nan, nan, np.zeros(len(stretches), int), time.perf_counter() - t0
    ratio = nominal / ogden_nominal_stress(np.asarray(stretches), [1.0], [alpha])
    return ratio, width, iters, time.perf_counter() - t0


def _pool_map(jobs, workers):
    if workers == 1:
        return [_ratio_run(j) for j in jobs]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(_ratio_run, jobs))


def verify_table(table: ns.NoSlipTable, workers: int) -> dict:
    """FE at alpha midpoints (and stretch midpoints) against the table's interpolation."""
    a = table.alphas
    mids = np.array([(x + y) / 2 for x, y in zip(a[:-1], a[1:]) if np.sign(x) == np.sign(y)])
    s = table.stretches[table.stretches < 1.0]
    s_mid = (s[:-1] + s[1:]) / 2
    s_all = np.sort(np.concatenate([s, s_mid]))[::-1]
    mesh = ns.FEMesh(**table.meta["mesh"])
    t0 = time.perf_counter()
    runs = _pool_map([(float(al), table.aspect, s_all, mesh, {}) for al in mids], workers)
    err_r, err_w = [], []
    worst = {"ratio": (0.0, None, None), "width": (0.0, None, None)}
    for al, (ratio, width, _, _) in zip(mids, runs):
        er = np.abs(table.force_ratio(s_all, al) / ratio - 1.0)
        ew = np.abs(table.bulge_width(s_all, al) / width - 1.0)
        err_r.append(er)
        err_w.append(ew)
        j = int(np.argmax(er))
        if er[j] > worst["ratio"][0]:
            worst["ratio"] = (float(er[j]), float(al), float(s_all[j]))
        j = int(np.argmax(ew))
        if ew[j] > worst["width"][0]:
            worst["width"] = (float(ew[j]), float(al), float(s_all[j]))
    err_r, err_w = np.array(err_r), np.array(err_w)
    on_grid = np.isin(s_all, s)
    out = {
        "alphas": mids.tolist(),
        "max_rel_err_force": float(err_r.max()),
        "max_rel_err_force_alpha_midpoints_grid_stretches": float(err_r[:, on_grid].max()),
        "max_rel_err_force_both_midpoints": float(err_r[:, ~on_grid].max()),
        "max_rel_err_width": float(err_w.max()),
        "worst_force": {"err": worst["ratio"][0], "alpha": worst["ratio"][1], "stretch": worst["ratio"][2]},
        "worst_width": {"err": worst["width"][0], "alpha": worst["width"][1], "stretch": worst["width"][2]},
        "max_rel_err_force_per_alpha": dict(zip(map(float, mids), map(float, err_r.max(axis=1)))),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    return out


#: Exponents of the refinement study: the tables' ends, the seeds' -4.7, both signs.
REFINE_ALPHAS = (-12.0, -4.7, -1.0, 1.0, 4.0, 12.0)
#: Radial cells of the refinement study (the default mesh and its halving of every cell).
REFINE_SIZES = (ns.DEFAULT_MESH.n_radial, 2 * ns.DEFAULT_MESH.n_radial)


def refine(aspects, alphas, workers: int) -> list[dict]:
    """Force change (%) from the default mesh to every cell halved, each (aspect, alpha)
    printed as it finishes (the ``--refine`` option: the study's refinement part alone)."""
    st = np.array([0.99, 0.9, 0.8, 0.7, 0.6])
    out = []
    for asp in aspects:
        for al in alphas:
            jobs = [(float(al), asp, st, ns.FEMesh(n, ns.DEFAULT_MESH.grading), {}) for n in REFINE_SIZES[::-1]]
            (fine, _, _, t_fine), (coarse, _, _, t_coarse) = _pool_map(jobs, workers)
            change = 100 * (fine / coarse - 1)
            out.append({"aspect": round(asp, 4), "alpha": float(al), "stretch": st.tolist(),
                        "force_ratio": {str(n): r.tolist() for n, r in zip(REFINE_SIZES, (coarse, fine))},
                        "change_pct": change.tolist(), "seconds": [round(t_coarse, 1), round(t_fine, 1)]})
            print(f"H/D={asp:.4f} alpha={al:<5g} ratio ({REFINE_SIZES[0]} cells) "
                  + " ".join(f"{x:.4f}" for x in coarse) + f"; change on halving every cell (%) at stretch "
                  f"{st.tolist()}: " + " ".join(f"{x:+.3f}" for x in change)
                  + f"  ({t_coarse:.0f} s, {t_fine:.0f} s)", flush=True)
    return out


def study(workers: int) -> dict:
    """Refinement (default mesh vs every cell halved, several alphas; a mesh sequence at
    -4.7), the bulk modulus, the folded layer bonded instead of sliding, the published
    discretisation, and the frictionless check."""
    st = np.array([0.99, 0.9, 0.8, 0.7, 0.6])
    alpha = -4.7
    aspects = (12.0 / 18.0, 0.5, 1.0)
    jobs, tags = [], []

    def add(kind, al, asp, mesh, **kw):
        jobs.append((al, asp, st, mesh, kw))
        tags.append((kind, al, asp, mesh.n_radial))

    for asp in aspects:
        for al in REFINE_ALPHAS:
            for n in REFINE_SIZES:
                add("refine", al, asp, ns.FEMesh(n, ns.DEFAULT_MESH.grading))
        for n in (16, 24, 48):
            add("refine", alpha, asp, ns.FEMesh(n, ns.DEFAULT_MESH.grading))
        add("published-mesh", alpha, asp, ns.FEMesh(32, 1.0), fold_over="none")
        add("bulk x10", alpha, asp, ns.DEFAULT_MESH, bulk_ratio=10 * ns.BULK_RATIO)
        add("fold-over bonded", alpha, asp, ns.DEFAULT_MESH, fold_over="bond")
        add("uniform, no fold", alpha, asp, ns.FEMesh(64, 1.0), fold_over="none")
        add("frictionless", alpha, asp, ns.DEFAULT_MESH, boundary="frictionless")
    # The largest jobs first keep both workers busy to the end.
    cost = [j[3].n_radial ** 2 * max(j[1], 0.25) for j in jobs]
    order = np.argsort(cost)[::-1]
    results = dict(zip(order, _pool_map([jobs[i] for i in order], workers)))
    rows = []
    for i, (kind, al, asp, n) in enumerate(tags):
        ratio, width, iters, sec = results[i]
        rows.append({"kind": kind, "alpha": al, "aspect": round(asp, 4), "n_radial": n,
                     "n_axial": jobs[i][3].n_axial(asp), "grading": jobs[i][3].grading,
                     "stretch": st.tolist(), "force_ratio": ratio.tolist(),
                     "width_over_d": width.tolist(), "newton_iterations": int(iters.sum()),
                     "seconds": round(sec, 1)})
    return {"alpha": alpha, "refine_alphas": list(REFINE_ALPHAS), "default_mesh": asdict(ns.DEFAULT_MESH),
            "bulk_ratio": ns.BULK_RATIO, "fold_over": ns.FOLD_OVER, "contact_penalty": ns.CONTACT_PENALTY,
            "table_version": ns.TABLE_VERSION, "rows": rows}


def refinement_changes(res: dict) -> list[dict]:
    """Force change (%) from the default mesh to every cell halved, per aspect and alpha."""
    out = []
    coarse, fine = REFINE_SIZES
    st = res["rows"][0]["stretch"]
    for asp in sorted({r["aspect"] for r in res["rows"]}):
        for al in res["refine_alphas"]:
            pick = {r["n_radial"]: r for r in res["rows"]
                    if r["kind"] == "refine" and r["aspect"] == asp and r["alpha"] == al}
            a, b = np.array(pick[coarse]["force_ratio"]), np.array(pick[fine]["force_ratio"])
            out.append({"aspect": asp, "alpha": al, "stretch": st,
                        "change_pct": (100 * (b / a - 1)).tolist()})
    return out


def print_study(res: dict) -> None:
    st = res["rows"][0]["stretch"]
    print(f"force ratio FE / homogeneous at stretch {st}")
    for r in res["rows"]:
        print(f"  {r['kind']:16s} H/D={r['aspect']:.4f} alpha={r['alpha']:<5g} mesh {r['n_axial']:3d}x{r['n_radial']:<3d} "
              f"g={r['grading']:<4g} " + " ".join(f"{x:.4f}" for x in r["force_ratio"])
              + f"  ({r['newton_iterations']} it, {r['seconds']} s)")
    coarse, fine = REFINE_SIZES
    print(f"change on refinement {coarse} -> {fine} radial cells (%), at stretch {st}:")
    for c in refinement_changes(res):
        print(f"  H/D={c['aspect']:.4f} alpha={c['alpha']:<5g} " + " ".join(f"{x:+.3f}" for x in c["change_pct"]))
    worst = max(abs(x) for c in refinement_changes(res) for x in c["change_pct"])
    print(f"  largest |change|: {worst:.3f} %")
    for asp in sorted({r["aspect"] for r in res["rows"]}):
        ref = sorted((r for r in res["rows"] if r["kind"] == "refine" and r["aspect"] == asp
                      and r["alpha"] == res["alpha"]), key=lambda r: r["n_radial"])
        print(f"  H/D={asp}, alpha {res['alpha']}: change on refinement at 20 % / 30 % compression:")
        for a, b in zip(ref[:-1], ref[1:]):
            d20 = b["force_ratio"][2] / a["force_ratio"][2] - 1
            d30 = b["force_ratio"][3] / a["force_ratio"][3] - 1
            print(f"    {a['n_radial']:>3d} -> {b['n_radial']:<3d}: {100 * d20:+.2f} %  {100 * d30:+.2f} %")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--aspects", type=float, nargs="*", default=list(ns.SHIPPED_ASPECTS))
    ap.add_argument("--out", type=Path, default=ns.shipped_dir())
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-verify", dest="verify", action="store_false")
    ap.add_argument("--study", action="store_true", help="run the mesh study instead of building")
    ap.add_argument("--refine", type=float, nargs="*", metavar="ALPHA",
                    help="only the refinement study, at these alphas (default: the study's) and --aspects")
    ap.add_argument("--verify-only", action="store_true",
                    help="verify the tables already in --out (current key) instead of building them")
    args = ap.parse_args(argv)

    if args.refine is not None:
        res = refine(args.aspects, args.refine or REFINE_ALPHAS, args.workers)
        worst = max(abs(x) for r in res for x in r["change_pct"])
        print(f"largest |change| on refinement: {worst:.3f} %")
        return 0

    if args.study:
        res = study(args.workers)
        res["refinement_changes_pct"] = refinement_changes(res)
        atomic_write_bytes(args.out / "noslip_study.json", dumps_json(res).encode())
        print_study(res)
        return 0

    for asp in args.aspects:
        if args.verify_only:
            table = ns.NoSlipTable.from_file(args.out / ns.table_filename(asp))
        else:
            table = ns.build_table(asp, workers=args.workers)
            print(f"H/D = {asp:.4f}: {table.meta['wall_seconds']} s wall, "
                  f"{np.mean(table.meta['seconds_per_alpha']):.1f} s per alpha run, "
                  f"{sum(table.meta['newton_iterations'])} Newton iterations", flush=True)
        if args.verify or args.verify_only:
            check = verify_table(table, args.workers)
            table = replace(table, meta={**table.meta, "interpolation_check": check})
            print(f"  interpolation vs FE at alpha midpoints: force {100 * check['max_rel_err_force']:.3f} % "
                  f"(worst at alpha {check['worst_force']['alpha']}, stretch {check['worst_force']['stretch']}), "
                  f"width {100 * check['max_rel_err_width']:.3f} %", flush=True)
        path = ns.save_table(table, args.out)
        print(f"  wrote {path} ({path.stat().st_size} bytes)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
