"""``bsipipe compare``: FE displacements interpolated at the markers, Table 1/2 and sigma.

1. Synthetic FE results built from a known displacement field: a linear field on a C3D8
   mesh with moved interior nodes and on a C3D4 mesh is recovered exactly (within 1e-9 mm
   in compare.json, 1e-6 mm in the CSV tables); a quadratic field is recovered exactly by
   C3D10 elements (straight edges, any mesh) and C3D20 elements (undistorted bricks: the
   serendipity space holds every quadratic only for an affine map).  Every result format
   (CSV, ABAQUS .rpt, meshio .vtu; .inp or .vtu mesh) gives the same numbers.
2. A small constructed case whose Table 1, Table 2 and sigma were computed by hand.
3. A real CalculiX run (C3D8, mm-kg-s-kPa, the project's Ogden card, NLGEOM): a brick whose
   boundary nodes are all displaced by u = (F - I) X deforms homogeneously for any
   homogeneous material, so the computed interior nodes, read back from the .dat and .frd
   files and interpolated at interior points, must equal (F - I) X to the files' printed
   precision.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.errors import InputError
from bsipipe.fe._calculix import ccx_executable, run_ccx
from bsipipe.fe.compare import compare_displacements, model_at_points
from bsipipe.io.abaqus import abaqus_elements, abaqus_material, abaqus_nodes
from bsipipe.io.fe_results import (displacements_on_mesh, read_abaqus_mesh, read_abaqus_report, read_ccx_dat,
                                   read_displacements, read_frd, read_mesh)
from test_shape_functions import (add_midside, brick_hex, hex_to_tet, hex_to_wedge, linear_field, points_inside,
                                  quadratic_field)

SIZE = (10.0, 8.0, 6.0)


def _invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def write_inp(path, coords, blocks, extra=""):
    ids = np.arange(1, len(coords) + 1) + 100          # labels that are not row numbers
    parts = ["** bsipipe test mesh", abaqus_nodes(ids, coords, nset="NALL")]
    first = 1
    for kind, conn in blocks:
        parts.append(abaqus_elements(kind, np.arange(first, first + len(conn)), ids[conn], elset="EALL"))
        first += len(conn)
    parts.append(extra)
    path.write_text("\n".join(p.rstrip("\n") for p in parts) + "\n")
    return ids


def write_disp_csv(path, ids, u):
    pd.DataFrame({"node": ids, "ux_mm": u[:, 0], "uy_mm": u[:, 1], "uz_mm": u[:, 2]}).to_csv(
        path, index=False, float_format="%.17g")


def write_rpt(path, ids, u, frames=((0.5, 0.5), (1.0, 1.0))):
    """An ABAQUS field-output report in Abaqus/CAE's layout: one table per frame (u scaled)."""
    out = []
    for k, (t, s) in enumerate(frames, start=1):
        out += ["*" * 80, "Field Output Report, written Mon Jan  1 00:00:00 2024", "", "Source 1", "---------", "",
                "   ODB: /tmp/job.odb", "   Step: Step-1", f"   Frame: Increment {k:6d}: Step Time = {t:8.3f}", "",
                "Loc 1 : Nodal values from source 1", "", 'Output sorted by column "Node Label".', "",
                "Field Output reported at nodes for part: PART-1-1", "",
                "            Node            U.U1            U.U2            U.U3",
                "           Label          @Loc 1          @Loc 1          @Loc 1",
                "-" * 65]
        out += [f"{i:16d} {s * a:17.10E} {s * b:17.10E} {s * c:17.10E}" for i, (a, b, c) in zip(ids, u)]
        out += ["", f"  Minimum {0.0:17.10E}", "", "    At Node 1", "  Maximum 0.0", "", ""]
    path.write_text("\n".join(out) + "\n")


def write_markers_ct(path, names, X, d, roles=None, frame_ref=0, frame=3):
    """markers_ct.csv with the registration frame (d = 0) and one displaced frame."""
    rows = []
    for f, dd in ((frame_ref, np.zeros_like(d)), (frame, d)):
        for i, n in enumerate(names):
            x = X[i] + dd[i]
            rows.append({"frame": f, "time_s": 0.1 * f, "marker": n, "x_mm": x[0], "y_mm": x[1], "z_mm": x[2],
                         "dx_mm": dd[i, 0], "dy_mm": dd[i, 1], "dz_mm": dd[i, 2],
                         "role": (roles or {}).get(n, "marker")})
    pd.DataFrame(rows).to_csv(path, index=False, float_format="%.17g")


MESHES = {
    "C3D8": lambda: (lambda c, h: (c, [("C3D8", h)]))(*brick_hex(5, 4, 3, size=SIZE, jitter=0.15, seed=11)),
    "C3D4": lambda: (lambda c, h: (c, [("C3D4", hex_to_tet(h))]))(*brick_hex(5, 4, 3, size=SIZE, jitter=0.15, seed=12)),
    # half the brick as C3D6 wedges, half C3D8 (a prism layer beside bricks): the wedges had been
    # skipped and the markers in them called "outside the mesh"
    "C3D6+C3D8": lambda: (lambda c, h: (c, [("C3D6", hex_to_wedge(h[: len(h) // 2])), ("C3D8", h[len(h) // 2:])]))(
        *brick_hex(5, 4, 3, size=SIZE, jitter=0.15, seed=14)),
}


def _quadratic_mesh(kind):
    if kind == "C3D10":       # straight-edged tetrahedra are affine whatever the corner positions
        c, h = brick_hex(4, 3, 3, size=SIZE, jitter=0.15, seed=13)
        c, q = add_midside(c, hex_to_tet(h), "C3D10")
    elif kind == "C3D15":     # straight-edged wedges on an undistorted brick
        c, h = brick_hex(4, 3, 3, size=SIZE, jitter=0.0)
        c, q = add_midside(c, hex_to_wedge(h), "C3D15")
    else:                     # C3D20 holds every quadratic only on an affine (undistorted) brick
        c, h = brick_hex(4, 3, 3, size=SIZE, jitter=0.0)
        c, q = add_midside(c, h, "C3D20")
    return c, [(kind, q)]


def _run_compare(tmp_path, coords, blocks, field, n_markers=12, seed=21, fmt="csv", mesh_fmt="inp"):
    X = points_inside(n_markers, size=SIZE, margin=0.3, seed=seed)
    names = [f"M{i + 1}" for i in range(n_markers)]
    u_nodes = field(coords)
    u_true = field(X)
    rng = np.random.default_rng(seed)
    measured = u_true + rng.normal(0, 0.05, u_true.shape)
    markers = tmp_path / "markers_ct.csv"
    write_markers_ct(markers, names, X, measured)
    if mesh_fmt == "inp":
        mesh = tmp_path / "mesh.inp"
        ids = write_inp(mesh, coords, blocks)
    else:
        import meshio
        mesh = tmp_path / "mesh.vtu"
        cells = [({"C3D8": "hexahedron", "C3D4": "tetra", "C3D10": "tetra10", "C3D20": "hexahedron20",
                   "C3D6": "wedge", "C3D15": "wedge15"}[k], c)
                 for k, c in blocks]
        meshio.write(mesh, meshio.Mesh(coords, cells, point_data={"U": u_nodes}))
        ids = np.arange(1, len(coords) + 1)
    if fmt == "csv":
        disp = tmp_path / "u.csv"
        write_disp_csv(disp, ids, u_nodes)
    elif fmt == "rpt":
        disp = tmp_path / "u.rpt"
        write_rpt(disp, ids, u_nodes)
    else:
        disp = mesh                   # meshio: displacements are point data of the mesh file
    out = tmp_path / f"out_{fmt}_{mesh_fmt}"
    r = _invoke("compare", "--fe-displacements", disp, "--mesh", mesh, "--markers", markers, "-o", out)
    assert r.exit_code == 0, r.output
    res = json.loads((out / "compare.json").read_text())
    model = np.array([res["markers"][n]["model_mm"] for n in names])
    t1 = pd.read_csv(out / "table1.csv")
    return res, model, u_true, measured, t1, names, out


@pytest.mark.parametrize("kind", ["C3D8", "C3D4", "C3D6+C3D8"])
def test_linear_field_is_recovered_at_the_markers(tmp_path, kind):
    coords, blocks = MESHES[kind]()
    res, model, truth, measured, t1, names, out = _run_compare(tmp_path, coords, blocks, linear_field)
    assert res["n_markers"] == len(names) and not res["skipped"]
    assert np.abs(model - truth).max() < 1e-9
    piv = t1.pivot(index="marker", columns="axis", values="model_mm").loc[names, ["x", "y", "z"]].to_numpy()
    assert np.abs(piv - truth).max() < 1e-6
    meas = t1.pivot(index="marker", columns="axis", values="measured_mm").loc[names, ["x", "y", "z"]].to_numpy()
    assert np.abs(meas - measured).max() < 1e-9
    assert set(t1.columns) >= {"marker", "axis", "model_mm", "measured_mm", "diff_mm"}
    t2 = pd.read_csv(out / "table2.csv")
    assert t2["quantity"].tolist() == ["x", "y", "z", "magnitude"]
    assert set(t2.columns) >= {"quantity", "max_mm", "min_mm", "mean_mm"}
    e = np.linalg.norm(model - measured, axis=1)
    assert res["sigma_mm"] == pytest.approx(np.sqrt(np.mean(e ** 2)), rel=1e-12)
    assert (out / "compare.png").stat().st_size > 10_000
    prov = res["provenance"]
    assert len(prov["inputs_sha256"]) == 3 and prov["config"]["length_unit"] == "mm"


def _model_at(mesh_path, disp_path, points, **kw):
    """The compare stage without the command: read, match nodes, interpolate."""
    mesh = read_mesh(mesh_path)
    disp = read_displacements(disp_path, **kw)
    nodal, _ = displacements_on_mesh(mesh, disp)
    u, loc = model_at_points(mesh.locator(), nodal, points)
    assert loc.inside.all()
    return u, disp


@pytest.mark.parametrize("kind", ["C3D10", "C3D15", "C3D20"])
def test_quadratic_field_is_recovered_by_quadratic_elements(tmp_path, kind):
    coords, blocks = _quadratic_mesh(kind)
    ids = write_inp(tmp_path / "mesh.inp", coords, blocks)
    write_disp_csv(tmp_path / "u.csv", ids, quadratic_field(coords))
    X = points_inside(20, size=SIZE, margin=0.3, seed=22)
    u, _ = _model_at(tmp_path / "mesh.inp", tmp_path / "u.csv", X)
    assert np.abs(u - quadratic_field(X)).max() < 1e-9


@pytest.mark.parametrize("fmt,mesh_fmt", [("rpt", "inp"), ("meshio", "vtu"), ("csv", "vtu")])
def test_result_formats_agree(tmp_path, fmt, mesh_fmt):
    import meshio

    coords, blocks = MESHES["C3D8"]()
    u_nodes = linear_field(coords)
    if mesh_fmt == "inp":
        mesh = tmp_path / "mesh.inp"
        ids = write_inp(mesh, coords, blocks)
    else:
        mesh = tmp_path / "mesh.vtu"
        meshio.write(mesh, meshio.Mesh(coords, [("hexahedron", blocks[0][1])], point_data={"U": u_nodes}))
        ids = np.arange(1, len(coords) + 1)
    disp = {"rpt": tmp_path / "u.rpt", "csv": tmp_path / "u.csv", "meshio": mesh}[fmt]
    if fmt == "rpt":
        write_rpt(disp, ids, u_nodes)
    elif fmt == "csv":
        write_disp_csv(disp, ids, u_nodes)
    X = points_inside(20, size=SIZE, margin=0.3, seed=23)
    u, d = _model_at(mesh, disp, X)
    assert np.abs(u - linear_field(X)).max() < 1e-9     # the .rpt holds 11 significant digits
    if fmt == "rpt":
        assert d.n_results == 2 and "1.000" in d.step
    if fmt == "meshio":                                 # and once through the command
        write_markers_ct(tmp_path / "m.csv", [f"M{i}" for i in range(20)], X, linear_field(X))
        r = _invoke("compare", "--fe-displacements", disp, "--mesh", mesh, "--markers", tmp_path / "m.csv",
                    "-o", tmp_path / "out")
        assert r.exit_code == 0, r.output
        res = json.loads((tmp_path / "out" / "compare.json").read_text())
        assert res["sigma_mm"] < 1e-9 and res["fe"]["node_matching"]["matched_by"].startswith("node position")


def test_rpt_reader_chooses_frames(tmp_path):
    ids = np.array([5, 7, 9])
    u = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.25], [0.0, 0.0, -2.0]])
    p = tmp_path / "u.rpt"
    write_rpt(p, ids, u)
    first = read_displacements(p, choose=0)
    last = read_displacements(p)
    assert first.node_ids.tolist() == [5, 7, 9]
    assert np.allclose(first.u_mm, 0.5 * u, atol=0) and np.allclose(last.u_mm, u, atol=0)
    assert last.time == 1.0 and first.time == 0.5
    # every result at once (compare's default, to choose by time): the same as one at a time
    every = read_displacements(p, choose="all")
    assert len(every) == last.n_results == 2
    for k, d in enumerate(every):
        one = read_displacements(p, choose=k)
        assert d.time == one.time and d.step == one.step and np.array_equal(d.u_mm, one.u_mm)


def test_rpt_with_magnitude_and_instance_labels_and_csv_with_times(tmp_path):
    p = tmp_path / "u.rpt"
    p.write_text("Field Output reported at nodes for part: PART-1-1\n\n"
                 "  Node Label   U.Magnitude        U.U1        U.U2        U.U3\n"
                 "                   @Loc 1      @Loc 1      @Loc 1      @Loc 1\n"
                 "-" * 60 + "\n"
                 "  PART-1-1.3     5.     3.     0.     -4.\n"
                 "  PART-1-1.4     1.     -0.    1.     0.\n\n"
                 "  Minimum        1.     -0.    0.     -4.\n")
    d = read_displacements(p)
    assert d.node_ids.tolist() == [3, 4] and d.u_mm.tolist() == [[3.0, 0.0, -4.0], [0.0, 1.0, 0.0]]
    q = tmp_path / "u.csv"
    q.write_text("node,time_s,ux_mm,uy_mm,uz_mm\n1,0.5,1,2,3\n2,0.5,4,5,6\n1,1.0,10,20,30\n2,1.0,40,50,60\n")
    d = read_displacements(q)
    assert d.time == 1.0 and d.n_results == 2 and d.u_mm[1].tolist() == [40, 50, 60]
    assert read_displacements(q, choose=0).u_mm[0].tolist() == [1, 2, 3]
    assert [x.time for x in read_displacements(q, choose="all")] == [0.5, 1.0]
    m = tmp_path / "u_m.csv"
    m.write_text("node,ux_m,uy_m,uz_m\n1,0.001,0,0\n")
    assert read_displacements(m, length_unit="m").u_mm.tolist() == [[1.0, 0.0, 0.0]]


def test_hand_computed_tables_and_sigma(tmp_path):
    """Field u = (0.1 x, -0.05 y, 0.02 z) mm; markers A (1, 2, 3), B (4, 2, 5), C (5, 4, 1) give
    model displacements (0.1, -0.1, 0.06), (0.4, -0.1, 0.1), (0.5, -0.2, 0.02); the measured
    ones (0.2, -0.1, 0.0), (0.4, 0.0, 0.1), (0.3, -0.2, 0.1) differ by (-0.1, 0, 0.06),
    (0, -0.1, 0), (0.2, 0, -0.08).  By hand: |dx| max 0.2, min 0, mean 0.1; |dy| 0.1, 0,
    0.1/3; |dz| 0.08, 0, 0.14/3; magnitudes sqrt(0.0136), 0.1, sqrt(0.0464): max 0.2154066,
    min 0.1, mean 0.1440085; sigma = sqrt((0.0136 + 0.01 + 0.0464) / 3) = sqrt(0.07 / 3)."""
    coords, conn = brick_hex(3, 3, 3, size=SIZE, jitter=0.1, seed=5)
    grad = np.diag([0.1, -0.05, 0.02])
    X = np.array([[1.0, 2.0, 3.0], [4.0, 2.0, 5.0], [5.0, 4.0, 1.0], [0.5, 0.5, 0.5]])
    measured = np.array([[0.2, -0.1, 0.0], [0.4, 0.0, 0.1], [0.3, -0.2, 0.1], [0.0, 0.0, 0.0]])
    write_markers_ct(tmp_path / "m.csv", ["A", "B", "C", "R1"], X, measured, roles={"R1": "reference"})
    ids = write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn)])
    write_disp_csv(tmp_path / "u.csv", ids, coords @ grad.T)
    out = tmp_path / "out"
    r = _invoke("compare", "--fe-displacements", tmp_path / "u.csv", "--mesh", tmp_path / "mesh.inp",
                "--markers", tmp_path / "m.csv", "-o", out)
    assert r.exit_code == 0, r.output
    t1 = pd.read_csv(out / "table1.csv")
    assert t1["marker"].tolist() == ["A"] * 3 + ["B"] * 3 + ["C"] * 3       # the reference R1 is left out
    assert t1["axis"].tolist() == ["x", "y", "z"] * 3
    assert np.allclose(t1["model_mm"], [0.1, -0.1, 0.06, 0.4, -0.1, 0.1, 0.5, -0.2, 0.02], atol=1e-12)
    assert np.allclose(t1["measured_mm"], measured[:3].ravel(), atol=1e-12)
    assert np.allclose(t1["diff_mm"], [-0.1, 0, 0.06, 0, -0.1, 0, 0.2, 0, -0.08], atol=1e-12)
    t2 = pd.read_csv(out / "table2.csv").set_index("quantity")
    expect = {"x": (0.2, 0.0, 0.1), "y": (0.1, 0.0, 0.1 / 3), "z": (0.08, 0.0, 0.14 / 3),
              "magnitude": (np.sqrt(0.0464), 0.1, (np.sqrt(0.0136) + 0.1 + np.sqrt(0.0464)) / 3)}
    for q, (mx, mn, mean) in expect.items():
        assert t2.loc[q, ["max_mm", "min_mm", "mean_mm"]].tolist() == pytest.approx([mx, mn, mean], abs=1e-12)
    assert t2.loc["magnitude", "max_mm"] == pytest.approx(0.2154066, abs=1e-7)
    assert t2.loc["magnitude", "mean_mm"] == pytest.approx(0.1440085, abs=1e-7)
    res = json.loads((out / "compare.json").read_text())
    assert res["sigma_mm"] == pytest.approx(np.sqrt(0.07 / 3), abs=1e-12)
    assert res["sigma_mm"] == pytest.approx(0.1527525, abs=1e-7)
    assert res["frame"] == 3 and res["n_markers"] == 3


def test_compare_displacements_directly():
    r = compare_displacements(["A"], [[0.3, 0.0, -0.4]], [[0.0, 0.0, 0.0]])
    assert r.sigma_mm == pytest.approx(0.5, abs=1e-15)
    assert r.table2.set_index("quantity").loc["z", "mean_signed_mm"] == pytest.approx(-0.4)


def test_markers_outside_the_mesh_are_skipped_and_named(tmp_path):
    coords, conn = brick_hex(2, 2, 2, size=SIZE)
    X = np.array([[5.0, 4.0, 3.0], [5.0, 4.0, 6.4], [12.0, 4.0, 3.0]])
    write_markers_ct(tmp_path / "m.csv", ["IN", "NEAR", "FAR"], X, np.full((3, 3), 0.01))
    ids = write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn)])
    write_disp_csv(tmp_path / "u.csv", ids, linear_field(coords))
    base = ["compare", "--fe-displacements", tmp_path / "u.csv", "--mesh", tmp_path / "mesh.inp",
            "--markers", tmp_path / "m.csv"]
    r = _invoke(*base, "-o", tmp_path / "a")
    assert r.exit_code == 0
    res = json.loads((tmp_path / "a" / "compare.json").read_text())
    assert list(res["markers"]) == ["IN"] and set(res["skipped"]) == {"NEAR", "FAR"}
    r = _invoke(*base, "--outside-tol-mm", "0.5", "-o", tmp_path / "b")
    res = json.loads((tmp_path / "b" / "compare.json").read_text())
    assert set(res["markers"]) == {"IN", "NEAR"} and not res["markers"]["NEAR"]["inside"]
    assert res["markers"]["NEAR"]["distance_mm"] == pytest.approx(0.4, abs=1e-9)
    # nothing inside: a processing failure (exit 1) naming the mesh
    r = _invoke(*base, "--marker", "FAR", "-o", tmp_path / "c")
    assert r.exit_code == 1 and "mesh.inp" in r.output and "outside the mesh" in r.output
    assert not (tmp_path / "c" / "compare.json").exists()


def test_bad_inputs_exit_2_naming_file_and_line(tmp_path):
    coords, conn = brick_hex(1, 1, 1, size=SIZE)
    ids = write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn)])
    write_disp_csv(tmp_path / "u.csv", ids, linear_field(coords))
    write_markers_ct(tmp_path / "m.csv", ["A"], np.array([[5.0, 4.0, 3.0]]), np.zeros((1, 3)))
    good = {"--fe-displacements": tmp_path / "u.csv", "--mesh": tmp_path / "mesh.inp", "--markers": tmp_path / "m.csv"}

    def run(**over):
        args = dict(good, **over)
        return _invoke("compare", *[x for kv in args.items() for x in kv], "-o", tmp_path / "o")

    (tmp_path / "bad.csv").write_text("node,ux_mm,uy_mm,uz_mm\n1,0,0,0\n2,0,abc,0\n")
    r = run(**{"--fe-displacements": tmp_path / "bad.csv"})
    assert r.exit_code == 2 and "bad.csv" in r.output and "line 3" in r.output
    (tmp_path / "cols.csv").write_text("node,ux,uy,uz\n1,0,0,0\n")
    r = run(**{"--fe-displacements": tmp_path / "cols.csv"})
    assert r.exit_code == 2 and "ux_mm" in r.output and "line 1" in r.output
    (tmp_path / "bad.inp").write_text("*NODE\n1, 0, 0, 0\n*ELEMENT, TYPE=C3D8\n1, 1, 2, 3\n")
    r = run(**{"--mesh": tmp_path / "bad.inp"})
    assert r.exit_code == 2 and "bad.inp" in r.output and "line 4" in r.output
    (tmp_path / "mk.csv").write_text("frame,marker,x_mm,y_mm,z_mm\n0,A,1,2,3\n")
    r = run(**{"--markers": tmp_path / "mk.csv"})
    assert r.exit_code == 2 and "dx_mm" in r.output
    r = _invoke("compare", *[x for kv in good.items() for x in kv], "--frame", "9", "-o", tmp_path / "o")
    assert r.exit_code == 2 and "frame 9" in r.output
    assert "Traceback" not in r.output


def test_abaqus_mesh_reader_details(tmp_path):
    """Node labels kept, *INCLUDE followed, C3D20 continuation lines, springs skipped."""
    coords, conn = brick_hex(1, 1, 1, size=(1.0, 1.0, 1.0))
    c20, q = add_midside(coords, conn, "C3D20")
    ids = np.arange(1, len(c20) + 1) * 10
    (tmp_path / "nodes.inp").write_text(abaqus_nodes(ids, c20))
    row = [7] + list(ids[q[0]])
    lines = ["*INCLUDE, INPUT=nodes.inp", "*ELEMENT, TYPE=C3D20R, ELSET=E",
             ", ".join(map(str, row[:16])) + ",", ", ".join(map(str, row[16:])),
             "*ELEMENT, TYPE=SPRINGA, ELSET=S", f"100, {ids[0]}, {ids[1]}", f"101, {ids[2]}, {ids[3]}",
             "** a comment", "*NSET, NSET=N1", f"{ids[0]}"]
    (tmp_path / "m.inp").write_text("\n".join(lines) + "\n")
    m = read_abaqus_mesh(tmp_path / "m.inp")
    assert m.node_ids.tolist() == ids.tolist()
    assert len(m.blocks) == 1 and m.blocks[0].element_type == "C3D20"
    assert m.blocks[0].element_ids.tolist() == [7]
    assert m.skipped == {"SPRINGA": 2}
    assert np.array_equal(m.node_ids[m.blocks[0].connectivity[0]], ids[q[0]])
    assert read_mesh(tmp_path / "m.inp", length_unit="m").coords_mm.max() == pytest.approx(1000.0)


# --- CalculiX --------------------------------------------------------------------------------------

# Rounding bounds of the printed numbers for |u| < 10 mm: the .dat prints 7 significant digits
# (d.dddddd E+xx, half a unit in the last place <= 5e-7 mm), the .frd 6 (E12.5, <= 5e-6 mm);
# the tolerances are twice these.  CalculiX's Newton iterations converge far below them.
DAT_TOL_MM = 1e-6
FRD_TOL_MM = 1e-5


@pytest.mark.skipif(ccx_executable() is None, reason="CalculiX 'ccx' is not on PATH (`make ccx`)")
def test_calculix_homogeneous_brick_read_back_and_interpolated(tmp_path):
    """A 4 x 3 x 3 C3D8 brick (20 x 12 x 10 mm, interior nodes moved up to 15 % of the spacing),
    Ogden mu = 720 Pa, alpha = -4.7 in mm-kg-s-kPa, NLGEOM; every boundary node displaced by
    (F - I) X with F an isochoric stretch 1.1 plus shear 0.05.  The exact solution is the
    homogeneous field, in the FE space, so the 12 computed interior nodes and every
    interpolated interior point must carry (F - I) X."""
    size = (20.0, 12.0, 10.0)
    coords, conn = brick_hex(4, 3, 3, size=size, jitter=0.15, seed=3)
    a = 1 / np.sqrt(1.1)
    F = np.array([[1.1, 0.05, 0.0], [0.0, a, 0.0], [0.0, 0.0, a]])
    U = coords @ (F - np.eye(3)).T
    ids = np.arange(1, len(coords) + 1)
    boundary = np.any(np.isclose(coords, 0.0) | np.isclose(coords, size), axis=1)
    bc = [f"{ids[i]}, {d + 1}, {d + 1}, {float(U[i, d])!r}" for i in np.flatnonzero(boundary) for d in range(3)]
    deck = "\n".join([
        abaqus_nodes(ids, coords, nset="NALL").rstrip(),
        abaqus_elements("C3D8", np.arange(1, len(conn) + 1), ids[conn], elset="EALL").rstrip(),
        abaqus_material("ogden", {"mu_pa": 720.0, "alpha": -4.7}, units="mm-kg-s-kPa").rstrip(),
        "*SOLID SECTION, ELSET=EALL, MATERIAL=BRAIN",
        "*STEP, NLGEOM, INC=100", "*STATIC", "0.25, 1.0, 1e-5, 1.0", "*BOUNDARY", *bc,
        "*NODE PRINT, NSET=NALL", "U", "*NODE FILE", "U", "*END STEP"]) + "\n"
    run_ccx(deck, jobname="brick", keep_dir=tmp_path)
    (tmp_path / "mesh.inp").write_text(deck)

    dat = read_ccx_dat(tmp_path / "brick.dat")
    frd = read_frd(tmp_path / "brick.frd")
    assert dat.time == 1.0 and frd.time == 1.0 and dat.n_results == frd.n_results == 4
    interior = ~boundary
    assert interior.sum() == 12
    for res, tol in ((dat, DAT_TOL_MM), (frd, FRD_TOL_MM)):
        u = np.full_like(U, np.nan)
        u[res.node_ids - 1] = res.u_mm
        assert np.abs(u[interior] - U[interior]).max() < tol
    assert np.abs(frd.coords_mm - coords[frd.node_ids - 1]).max() < 5e-5   # E12.5 coordinates

    # markers at interior points of the elements around the computed nodes
    X = points_inside(15, size=size, margin=3.0, seed=4)
    u_true = X @ (F - np.eye(3)).T
    u_dat, _ = _model_at(tmp_path / "mesh.inp", tmp_path / "brick.dat", X)
    assert np.abs(u_dat - u_true).max() < DAT_TOL_MM
    write_markers_ct(tmp_path / "m.csv", [f"M{i}" for i in range(15)], X, u_true)
    out = tmp_path / "cmp"
    r = _invoke("compare", "--fe-displacements", tmp_path / "brick.frd", "--mesh", tmp_path / "mesh.inp",
                "--markers", tmp_path / "m.csv", "-o", out)
    assert r.exit_code == 0, r.output
    res = json.loads((out / "compare.json").read_text())
    model = np.array([res["markers"][f"M{i}"]["model_mm"] for i in range(15)])
    assert np.abs(model - u_true).max() < FRD_TOL_MM
    assert res["sigma_mm"] < FRD_TOL_MM
    assert res["fe"]["element_types"] == {"C3D8": 36} and res["fe"]["format"] == "calculix-frd"


def _frd_text(n_nodes: int, times=(0.5, 1.0)) -> str:
    """A small CalculiX ASCII .frd (long format): the node block and one DISP block per time."""
    out = [f"    2C{n_nodes:>30d}{'':37s}1"]
    out += [f" -1{k:>10d}{float(k):12.5E}{0.0:12.5E}{0.0:12.5E}" for k in range(1, n_nodes + 1)]
    out.append(" -3")
    for t in times:
        out += [f"  100CL  101{t:12.5E}{n_nodes:12d}                     0    1           1",
                " -4  DISP        4    1", " -5  D1          1    2    1    0"]
        out += [f" -1{k:>10d}{t * k:12.5E}{0.0:12.5E}{0.0:12.5E}" for k in range(1, n_nodes + 1)]
        out.append(" -3")
    return "\n".join(out + ["9999"]) + "\n"


def _dat_text(n_nodes: int, times=(0.5, 1.0)) -> str:
    out = []
    for t in times:
        out += ["", f" displacements (vx,vy,vz) for set NALL and time  {t:.7E}", ""]
        out += [f"{k:>10d} {t * k: .6E} {0.0: .6E} {0.0: .6E}" for k in range(1, n_nodes + 1)]
    return "\n".join(out) + "\n"


def test_calculix_results_cut_off_are_invalid_input(tmp_path):
    """A .frd that ends inside a block (no -3 record), or whose DISP block holds fewer nodes
    than its header says, and a .dat whose last block is shorter than the set's earlier ones,
    are InputErrors naming the file: a run stopped while writing, or a copy cut short, had been
    read as complete (a partial last result: 'its element has a node without an FE
    displacement' for markers the file simply did not reach, or the file's last result taken
    as the peak's)."""
    frd, dat = tmp_path / "job.frd", tmp_path / "job.dat"
    frd.write_text(_frd_text(10))
    dat.write_text(_dat_text(10))
    for r in (read_frd(frd), read_ccx_dat(dat)):          # the whole files read
        assert r.n_results == 2 and r.time == 1.0 and len(r.node_ids) == 10
        assert np.allclose(r.u_mm[:, 0], np.arange(1, 11))
    lines = _frd_text(10).splitlines()
    frd.write_text("\n".join(lines[:-6]) + "\n")          # cut inside the last DISP block
    with pytest.raises(InputError, match=r"ends inside the DISP block that starts at line 27"):
        read_frd(frd)
    frd.write_text("\n".join(lines[:-4] + lines[-3:]) + "\n")   # a node record gone
    with pytest.raises(InputError, match=r"holds 9 nodes, its header says 10"):
        read_frd(frd)
    lines = _dat_text(10).splitlines()
    dat.write_text("\n".join(lines[:-4]) + "\n")
    with pytest.raises(InputError, match=r"set NALL, time 1\) holds 6 nodes, the set's earlier ones 10"):
        read_ccx_dat(dat)


def test_results_cut_at_a_line_or_block_edge_are_invalid_input(tmp_path):
    """A report cut inside its last table at a line's end, and a .dat cut just before the last
    time's block of one of its sets: the report had been read with the rows it had (a table cut
    at 30 % gave 1 marker of 8 and sigma from it, exit 0), the .dat as a result of another mesh
    ("933 of the mesh's 942 nodes have no displacement").  Both are InputErrors saying the file
    was cut off; the whole files read."""
    from bsipipe.io.fe_results import read_abaqus_report
    ids = np.arange(1, 21)
    u = np.column_stack([ids * 0.01, np.zeros(20), np.zeros(20)])
    rpt = tmp_path / "u.rpt"
    write_rpt(rpt, ids, u)
    assert read_abaqus_report(rpt).n_results == 2
    lines = rpt.read_text().splitlines()
    dashes = [k for k, ln in enumerate(lines) if ln.startswith("-" * 60)]
    rpt.write_text("\n".join(lines[:dashes[-1] + 1 + 6]) + "\n")        # 6 of the last table's 20 rows
    with pytest.raises(InputError, match=r"ends inside its last table .*6 rows, the part's earlier tables 20"):
        read_abaqus_report(rpt)
    def block(name, t, n):
        return _dat_text(n, times=(t,)).replace("set NALL", f"set {name}")

    dat = tmp_path / "job.dat"
    head = block("NALL", 0.5, 10) + block("MARKERS", 0.5, 4) + block("NALL", 1.0, 10)
    dat.write_text(head)                                   # cut before time 1's MARKERS block
    with pytest.raises(InputError, match=r"last time \(1\) has no displacement block for set\(s\) MARKERS"):
        read_ccx_dat(dat)
    dat.write_text(head + block("MARKERS", 1.0, 4))
    assert read_ccx_dat(dat).n_results == 2


def _rpt_two_parts(path, ids_a, ids_b, frames=((0.5, 0.5), (1.0, 1.0))):
    """Abaqus/CAE's report of a model of two part instances: per frame a table for BRAIN-1,
    then one for INDENTOR-1 (u of node k = (k, 0, 0) times the frame's scale)."""
    out = []
    for k, (t, s) in enumerate(frames, start=1):
        out += ["Source 1", "---------", "   ODB: /tmp/job.odb", "   Step: Step-1",
                f"   Frame: Increment {k:6d}: Step Time = {t:8.3f}", ""]
        for part, ids in (("BRAIN-1", ids_a), ("INDENTOR-1", ids_b)):
            out += [f"Field Output reported at nodes for part: {part}", "",
                    "            Node            U.U1            U.U2            U.U3",
                    "           Label          @Loc 1          @Loc 1          @Loc 1", "-" * 65]
            out += [f"{i:16d} {s * i:17.10E} {0.0:17.10E} {0.0:17.10E}" for i in ids]
            out += ["", f"  Minimum {0.0:17.10E}", ""]
    path.write_text("\n".join(out) + "\n")


def test_report_of_several_part_instances(tmp_path):
    """A report of two part instances (one table per instance and frame) is one result per
    frame, the tables merged where their labels are distinct; where they overlap (each
    instance numbering its nodes from 1) it is an InputError naming the parts: the indentor's
    labels had been read as brain nodes, and each frame counted twice (23 frames as 46 results)."""
    p = tmp_path / "two.rpt"
    _rpt_two_parts(p, np.arange(1, 21), np.arange(101, 106))
    r = read_abaqus_report(p, choose="all")
    assert len(r) == 2 and [x.time for x in r] == [0.5, 1.0]
    assert list(r[1].node_ids) == list(range(1, 21)) + list(range(101, 106))
    assert np.allclose(r[1].u_mm[:, 0], r[1].node_ids)
    _rpt_two_parts(p, np.arange(1, 21), np.arange(1, 6))
    with pytest.raises(InputError, match=r"one table per part instance \(BRAIN-1, INDENTOR-1\), whose node labels "
                                         r"overlap"):
        read_abaqus_report(p)


def test_abaqus_cae_parts_are_placed_by_their_instances(tmp_path):
    """An Abaqus/CAE input file holds each part's nodes in the part's own frame and places the
    part by its *INSTANCE (a translation, then a rotation about an axis through two points):
    the mesh read is the assembly's, as the flat deck of the same model.  The instance had
    been ignored (a mesh 10 mm off, compared and exported without an error).  A part
    instanced twice is an InputError."""
    from scipy.spatial.transform import Rotation
    coords, conn = brick_hex(2, 2, 2, size=(4.0, 4.0, 4.0))
    ids = np.arange(1, len(coords) + 1)
    a, b, angle = np.array([1.0, 2.0, 3.0]), np.array([1.0, 3.0, 5.0]), 30.0
    shift = np.array([10.0, -5.0, 2.5])
    R = Rotation.from_rotvec((b - a) / np.linalg.norm(b - a) * np.radians(angle)).as_matrix()
    placed = a + (coords + shift - a) @ R.T
    body = abaqus_nodes(ids, coords).rstrip() + "\n" + abaqus_elements("C3D8", np.arange(1, len(conn) + 1),
                                                                          ids[conn]).rstrip()
    instance = (f"*Instance, name=BRAIN-1, part=BRAIN\n{', '.join(repr(float(x)) for x in shift)}\n"
                f"{', '.join(repr(float(x)) for x in (*a, *b, angle))}\n*End Instance\n")
    cae = tmp_path / "cae.inp"
    cae.write_text(f"*Heading\n*Part, name=BRAIN\n{body}\n*End Part\n*Assembly, name=Assembly\n{instance}"
                   "*End Assembly\n")
    m = read_abaqus_mesh(cae)
    assert np.abs(m.coords_mm[np.argsort(m.node_ids)] - placed).max() < 1e-9
    twice = instance + instance.replace("BRAIN-1", "BRAIN-2")
    cae.write_text(f"*Part, name=BRAIN\n{body}\n*End Part\n*Assembly, name=Assembly\n{twice}*End Assembly\n")
    with pytest.raises(InputError, match="part BRAIN is instanced 2 times"):
        read_abaqus_mesh(cae)


def test_abaqus_keyword_forms_compare_had_misread(tmp_path):
    """Valid ABAQUS input compare had refused or misread: a keyword line continued after a comma
    ("*ELEMENT, TYPE=C3D8," then "ELSET=E": read as a node line), nodes generated by *NGEN
    ("uses node 2, which no *NODE defines"), and an Abaqus/CAE assembly's own node (a rigid
    indentor's reference point, label 1 as the part's first node: "node 1 defined twice").
    *ELGEN, which it had skipped unsaid (every marker "outside the mesh"), is refused naming
    the line."""
    coords, conn = brick_hex(1, 1, 1, size=(2.0, 2.0, 2.0))
    ids = np.arange(1, 9)
    nodes = "\n".join(f"{i}, {float(x)!r}, {float(y)!r}, {float(z)!r}" for i, (x, y, z) in zip(ids, coords))
    elem = ", ".join(str(int(n)) for n in ids[conn[0]])
    cont = tmp_path / "cont.inp"
    cont.write_text(f"*NODE,\n NSET=ALL\n{nodes}\n*ELEMENT, TYPE=C3D8,\n** a comment\nELSET=E\n1, {elem}\n")
    m = read_abaqus_mesh(cont)
    assert m.n_elements == 1 and len(m.node_ids) == 8
    # *NGEN: nodes 1 and 3 given, 2 between them
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    full = np.vstack([line, line + [0, 2, 0], line + [0, 0, 2], line + [0, 2, 2]])
    def ngen_block(base):
        return (f"*NODE\n{base}, {float(full[base - 1][0])!r}, {float(full[base - 1][1])!r}, {float(full[base - 1][2])!r}\n"
                f"{base + 2}, {float(full[base + 1][0])!r}, {float(full[base + 1][1])!r}, {float(full[base + 1][2])!r}\n"
                f"*NGEN\n{base}, {base + 2}, 1\n")
    deck = "".join(ngen_block(b) for b in (1, 4, 7, 10))
    deck += "*ELEMENT, TYPE=C3D8\n1, 1, 2, 5, 4, 7, 8, 11, 10\n2, 2, 3, 6, 5, 8, 9, 12, 11\n"
    (tmp_path / "ngen.inp").write_text(deck)
    m = read_abaqus_mesh(tmp_path / "ngen.inp")
    got = m.coords_mm[np.argsort(m.node_ids)]
    assert np.abs(got - full).max() < 1e-12 and m.n_elements == 2
    # an assembly's reference point with the label of a part's node
    body = abaqus_nodes(ids, coords).rstrip() + "\n" + abaqus_elements("C3D8", [1], ids[conn]).rstrip()
    cae = tmp_path / "rp.inp"
    cae.write_text(f"*Part, name=BRAIN\n{body}\n*End Part\n*Assembly, name=Assembly\n"
                   "*Instance, name=BRAIN-1, part=BRAIN\n*End Instance\n*Node\n1, 1.0, 1.0, 9.0\n"
                   "*Nset, nset=RP\n1,\n*End Assembly\n")
    m = read_abaqus_mesh(cae)
    assert len(m.node_ids) == 8 and np.abs(m.coords_mm[np.argsort(m.node_ids)] - coords).max() < 1e-12
    (tmp_path / "elgen.inp").write_text(f"*NODE\n{nodes}\n*ELEMENT, TYPE=C3D8\n1, {elem}\n*ELGEN\n1, 3, 1, 1\n")
    with pytest.raises(InputError, match=r"line \d+.*\*ELGEN generates elements"):
        read_abaqus_mesh(tmp_path / "elgen.inp")


def test_mesh_or_displacements_in_metres_read_as_mm(tmp_path):
    """A mesh written in metres without --length-unit m had been exit 1 "no marker lies in the
    mesh ... outside the mesh", as if the markers were wrong: it is exit 2 saying the mesh's
    coordinates look like metres.  Displacements in metres on a mesh in mm had given exit 0
    with sigma the size of the measured motion and no word (a CSV whose ux_mm columns hold
    metres): a warning now gives the ratio."""
    coords, conn = brick_hex(3, 3, 3, size=SIZE)
    X = points_inside(6, size=SIZE, margin=0.3, seed=3)
    names = [f"M{i + 1}" for i in range(6)]
    u = linear_field(coords)
    write_markers_ct(tmp_path / "m.csv", names, X, linear_field(X))
    ids = write_inp(tmp_path / "mesh_m.inp", coords / 1000.0, [("C3D8", conn)])
    write_disp_csv(tmp_path / "u_m.csv", ids, u / 1000.0)
    r = _invoke("compare", "--fe-displacements", tmp_path / "u_m.csv", "--mesh", tmp_path / "mesh_m.inp",
                "--markers", tmp_path / "m.csv", "-o", tmp_path / "a")
    assert r.exit_code == 2 and "mesh_m.inp" in r.output and "--length-unit m" in r.output, r.output
    pd.DataFrame({"node": ids, "ux_m": u[:, 0] / 1000.0, "uy_m": u[:, 1] / 1000.0, "uz_m": u[:, 2] / 1000.0}
                 ).to_csv(tmp_path / "u_metres.csv", index=False, float_format="%.17g")
    r = _invoke("compare", "--fe-displacements", tmp_path / "u_metres.csv", "--mesh", tmp_path / "mesh_m.inp",
                "--markers", tmp_path / "m.csv", "--length-unit", "m", "-o", tmp_path / "b")
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "b" / "compare.json").read_text())
    assert res["sigma_mm"] < 1e-6 and not any("length unit" in w for w in res["warnings"])
    ids = write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn)])
    r = _invoke("compare", "--fe-displacements", tmp_path / "u_m.csv", "--mesh", tmp_path / "mesh.inp",
                "--markers", tmp_path / "m.csv", "-o", tmp_path / "c")
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "c" / "compare.json").read_text())
    assert any("0.001 times the measured ones" in w for w in res["warnings"]), res["warnings"]


def test_result_node_labels_the_mesh_lacks(tmp_path):
    """A CSV numbered from 0 against a mesh numbered from 1 had put every displacement on its
    neighbour's node, exit 0 with a wrong sigma and no word (the probe: the study's 1.542 mm
    read as 1.862 mm): every label is in the mesh once shifted by one, so it is exit 2 naming
    the file.  A result with an extra node the mesh lacks (a solver's reference node) is
    compared, with a warning naming it."""
    coords, conn = brick_hex(3, 3, 3, size=SIZE)
    X = points_inside(6, size=SIZE, margin=0.3, seed=3)
    names = [f"M{i + 1}" for i in range(6)]
    u = linear_field(coords)
    write_markers_ct(tmp_path / "m.csv", names, X, linear_field(X))
    ids = write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn)])
    write_disp_csv(tmp_path / "u0.csv", ids - 1, u)
    r = _invoke("compare", "--fe-displacements", tmp_path / "u0.csv", "--mesh", tmp_path / "mesh.inp",
                "--markers", tmp_path / "m.csv", "-o", tmp_path / "a")
    assert r.exit_code == 2 and "u0.csv" in r.output and "numbered from 0" in r.output, r.output
    assert not (tmp_path / "a").exists()
    extra_ids = np.concatenate([ids, [ids.max() + 100]])
    write_disp_csv(tmp_path / "u_extra.csv", extra_ids, np.vstack([u, [[9.0, 9.0, 9.0]]]))
    r = _invoke("compare", "--fe-displacements", tmp_path / "u_extra.csv", "--mesh", tmp_path / "mesh.inp",
                "--markers", tmp_path / "m.csv", "-o", tmp_path / "b")
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "b" / "compare.json").read_text())
    assert res["sigma_mm"] < 1e-6
    assert any(f"e.g. {ids.max() + 100})" in w for w in res["warnings"]), res["warnings"]


def test_fe_times_on_the_xray_clock_are_warned():
    """FE result times written on the X-ray clock (every time + 3.7448 s, the X-ray time of
    FE time 0 in the deck header): the result nearest the peak frame's FE time had been
    compared, 0.82 of the model's peak displacement (the probe: sigma 1.20 mm against the
    true 1.54), with no warning.  The peak frame's result must be the model's peak; when it
    is not, the offset is named, and the X-ray clock when it matches the header's zero."""
    from bsipipe.fe.compare import choose_fe_result
    t = np.arange(23) * 1.25
    pv = np.minimum(t, 11.9) * 0.15 - np.maximum(t - 11.9, 0) * 0.08
    xray = t + 3.7448
    # the peak frame's FE time on the deck's clock: the model's peak, FE time 12.5
    c = choose_fe_result(len(t), fe_times=xray, target_fe_time=12.51, time_tol=0.25, peak_values=pv,
                         frame_is_peak=True, clock_zero=3.7448)
    assert int(np.argmax(pv)) == 10 and c.index == 7
    assert len(c.warnings) == 1 and "X-ray clock" in c.warnings[0] and f"--fe-result {int(np.argmax(pv))}" in c.warnings[0]
    # the same times on the right clock: the chosen result is the peak, nothing said
    ok = choose_fe_result(len(t), fe_times=t, target_fe_time=12.51, time_tol=0.25, peak_values=pv,
                          frame_is_peak=True, clock_zero=3.7448)
    assert ok.index == int(np.argmax(pv)) and ok.warnings == []
    # shifted by something else: the shift is named, not the X-ray clock
    c2 = choose_fe_result(len(t), fe_times=t + 6.0, target_fe_time=12.51, time_tol=0.25, peak_values=pv,
                          frame_is_peak=True, clock_zero=3.7448)
    assert any("not the FE results' peak" in w and "X-ray clock" not in w for w in c2.warnings), c2.warnings


def test_scale_warning_blames_the_result_not_the_unit_when_another_result_fits():
    """FE times halved picked the unloaded result (model displacement ~1e-10 mm) and the
    warning had blamed a length unit (metres read as mm); with another result in the file
    reaching the measured size it names the choice of result instead.  Metres throughout
    still get the unit warning."""
    from bsipipe.commands.compare import _scale_warning
    meas = np.array([[0.0, 0.0, -0.9], [0.1, 0.0, -0.8]])
    w = _scale_warning(meas * 1e-10, meas, peak_values=[0.2, 0.9, 1e-10])
    assert w is not None and "not the measured frame's" in w and "length unit" not in w
    w = _scale_warning(meas * 1e-3, meas, peak_values=[2e-4, 9e-4, 1e-13])
    assert w is not None and "length unit" in w


def test_an_axis_with_its_sign_turned_is_warned():
    """uz negated in the FE displacements (another convention, an axis flipped on export):
    sigma 3.34 mm for 1.54 on the probe's study, unsaid.  An axis that runs opposite at the
    markers, whose turning would halve sigma, is named; a model merely off is not."""
    from bsipipe.commands.compare import _axis_sign_warning
    meas = np.array([[0.84, -0.21, -4.0], [0.54, -0.07, -0.40], [-0.17, -0.01, -0.56]])
    model = meas * [1.0, 1.0, -1.0] + 0.05
    w = _axis_sign_warning(model, meas)
    assert w is not None and "z displacements run opposite" in w
    assert _axis_sign_warning(meas * 0.7 + 0.1, meas) is None           # a stiffer model: no word
    assert "x displacements" in _axis_sign_warning(meas * [-1.0, 1.0, 1.0], meas)
    assert _axis_sign_warning(meas * [1.0, -1.0, 1.0], meas) is None     # y carries too little to tell


def test_float32_meshio_results_at_ct_coordinates_and_damaged_files(tmp_path):
    """A VTU result whose points are float32, 850 mm from the origin (a CT frame's): rounded to
    3e-5 mm, finer than the position match's 1e-6 of the mesh diagonal, 18 of 120 nodes had
    gone unmatched and the mesh was blamed (exit 2).  The match allows the stored precision.  A
    damaged VTU had exited 1 with meshio's bare message (it calls sys.exit): exit 2 naming it."""
    import meshio
    coords, conn = brick_hex(4, 3, 3, size=SIZE)
    coords = coords + np.array([-120.0, 210.0, -850.0])
    write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn)])
    u = linear_field(coords - coords.mean(axis=0))
    vtu = tmp_path / "u.vtu"
    meshio.write(vtu, meshio.Mesh(coords.astype(np.float32), [("hexahedron", conn)], point_data={"U": u}))
    mesh = read_mesh(tmp_path / "mesh.inp")
    nodal, info = displacements_on_mesh(mesh, read_displacements(vtu))
    assert info["n_matched"] == len(coords) and np.isfinite(nodal).all()
    vtu.write_bytes(vtu.read_bytes()[:200])
    X = coords.mean(axis=0)[None] + 0.5
    write_markers_ct(tmp_path / "m.csv", ["M1"], X, np.zeros((1, 3)))
    r = _invoke("compare", "--fe-displacements", vtu, "--mesh", tmp_path / "mesh.inp", "--markers",
                tmp_path / "m.csv", "-o", tmp_path / "out")
    assert r.exit_code == 2 and "u.vtu" in r.output and "meshio cannot read the file" in r.output, r.output


def test_displacement_csv_as_spreadsheets_write_it(tmp_path):
    """Excel's "CSV UTF-8" (a byte-order mark before the header) had given "missing column(s)
    node" under a header that shows it, and labels written 601.0 (pandas' float column) "node
    is not a number: '1.0'".  Both read; a label that is no whole number is refused naming it."""
    from bsipipe.io.fe_results import read_displacement_csv
    p = tmp_path / "u.csv"
    p.write_bytes("\ufeffnode,ux_mm,uy_mm,uz_mm\r\n1.0,0.1,0.2,0.3\r\n2.0,0.4,0.5,0.6\r\n".encode("utf-8"))
    r = read_displacement_csv(p)
    assert r.node_ids.tolist() == [1, 2] and r.u_mm[1].tolist() == [0.4, 0.5, 0.6]
    p.write_text("node,ux_mm,uy_mm,uz_mm\n1.5,0,0,0\n")
    with pytest.raises(InputError, match=r"line 2: node is not a node label \(a whole number\): '1.5'"):
        read_displacement_csv(p)


def test_a_marker_in_an_element_type_compare_skips_is_not_only_outside(tmp_path):
    """Half a mesh of 27-node bricks (C3D27, which compare does not interpolate): the markers in
    them had been reported "outside the mesh"; the reason now names the skipped solid type."""
    coords, conn = brick_hex(4, 2, 2, size=SIZE)
    half = len(conn) // 2
    X = np.array([coords[conn[0]].mean(axis=0), coords[conn[-1]].mean(axis=0)])
    labels = np.arange(1, len(coords) + 1) + 100                  # write_inp's node labels

    def c3d27(k, row):                                           # 16 entries a line at most
        vals = [1000 + k] + [int(labels[n]) for n in row] + [int(labels[row[0]])] * 19
        return ", ".join(map(str, vals[:16])) + ",\n" + ", ".join(map(str, vals[16:])) + "\n"

    extra = "*ELEMENT, TYPE=C3D27\n" + "".join(c3d27(k, row) for k, row in enumerate(conn[:half]))
    ids = write_inp(tmp_path / "mesh.inp", coords, [("C3D8", conn[half:])], extra=extra)
    write_disp_csv(tmp_path / "u.csv", ids, linear_field(coords))
    write_markers_ct(tmp_path / "m.csv", ["IN_C3D27", "IN_C3D8"], X, linear_field(X))
    r = _invoke("compare", "--fe-displacements", tmp_path / "u.csv", "--mesh", tmp_path / "mesh.inp",
                "--markers", tmp_path / "m.csv", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "out" / "compare.json").read_text())
    assert res["n_markers"] == 1
    assert "solid elements compare does not interpolate" in res["skipped"]["IN_C3D27"]
    assert "C3D27" in res["skipped"]["IN_C3D27"]
