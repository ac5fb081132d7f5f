"""``bsipipe export-fe`` decks as ``bsipipe compare`` and the solvers use them, on the twin.

* The ABAQUS deck prints (``*NODE PRINT``) the displacements of the nodes of the elements
  that hold the markers, so the documented ``compare --fe-displacements model.dat`` works,
  and states the FE clock and the CT coordinate system in its header, so compare pairs the
  measured peak frame with the FE result at the same time.  Run in CalculiX, the ``.dat``
  (7 printed digits) and the ``.frd`` (6 digits, E12.5) give the same model displacements at
  the markers to 2e-5 mm (twice the ``.frd``'s rounding of displacements below 10 mm).
* A fitted Prony series makes the steps ``*VISCO`` (ABAQUS's ``*STATIC`` would ignore the
  relaxation); CalculiX still runs the deck.
* The FEBio model does not slide on the skull: with ``interface.anchors: sliding`` the
  manifest's ``warnings`` and the model's comments say so.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from bsipipe.fe._calculix import ccx_executable, run_ccx
from bsipipe.io.abaqus import abaqus_header_values, abaqus_node_sets
from bsipipe.io.fe_results import read_abaqus_mesh
from test_export_fe import _invoke, build_inputs

PRONY = [{"g": 0.45, "tau_s": 2.1}]
DAT_FRD_TOL_MM = 2e-5


@pytest.fixture(scope="module")
def prony_case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("export_fe_prony")
    build_inputs(folder)
    (folder / "fit.json").write_text(json.dumps({"model": "ogden",
                                                 "params": {"mu_pa": 720.0, "alpha": -4.7, "prony": PRONY}}))
    res = _invoke("export-fe", folder / "export.yaml", "-o", folder / "out")
    assert res.exit_code == 0, res.output
    return folder, folder / "out", json.loads((folder / "out" / "manifest.json").read_text())


def _steps(deck: str) -> list[list[str]]:
    blocks, cur = [], None
    for line in deck.splitlines():
        if line.upper().startswith("*STEP"):
            cur = []
        elif line.upper().startswith("*END STEP"):
            blocks.append(cur)
            cur = None
        elif cur is not None:
            cur.append(line)
    return blocks


def test_deck_prints_the_nodes_of_the_marker_elements(prony_case):
    _, out, man = prony_case
    deck = out / "abaqus" / "model.inp"
    mesh = read_abaqus_mesh(deck)
    sets = abaqus_node_sets(deck)
    fe = pd.read_csv(out / "markers_fe.csv")
    fe = fe[fe["role"] == "marker"].groupby("marker")[["x0_mm", "y0_mm", "z0_mm"]].first()
    loc = mesh.locator().locate(fe.to_numpy(float))
    assert loc.found.any(), "no marker in the demonstration brick: the test needs one"
    assert sorted(man["deck"]["markers_in_mesh"]) == sorted(fe.index[loc.found])
    want = set()
    for i in np.flatnonzero(loc.found):
        want |= set(mesh.node_ids[mesh.blocks[loc.block[i]].connectivity[loc.element[i]]].tolist())
    assert set(sets["MARKERS"].tolist()) == want
    steps = _steps(deck.read_text())
    assert steps and all("*NODE PRINT, NSET=MARKERS" in s for s in steps)


def test_prony_steps_are_visco_and_febio_anchors_are_warned(prony_case):
    _, out, man = prony_case
    deck = (out / "abaqus" / "model.inp").read_text()
    for s in _steps(deck):
        procedures = [ln for ln in s if ln.upper().startswith(("*STATIC", "*VISCO"))]
        assert len(procedures) == 1 and procedures[0].startswith("*VISCO, CETOL=")
    assert man["deck"]["analysis"].startswith("*STEP, NLGEOM; *VISCO")
    assert any("*VISCO" in w for w in man["warnings"])
    assert any("FEBio" in w and "sliding" in w for w in man["warnings"])
    assert "'sliding' is not modelled here" in (out / "febio" / "model.feb").read_text()
    header = abaqus_header_values(out / "abaqus" / "model.inp")
    assert float(header["fe_time_zero_xray_s"]) == pytest.approx(man["indentor"]["contact"]["xray_time_s"])
    assert header["fe_time_unit"] == "s" and header["ct_coordinate_system"] == man["frame"]["coordinate_system"]


def test_fixed_anchors_have_no_febio_warning(tmp_path):
    build_inputs(tmp_path, extra={"interface": {"anchors": "fixed"}})
    res = _invoke("export-fe", tmp_path / "export.yaml", "-o", tmp_path / "out")
    assert res.exit_code == 0, res.output
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert not any("FEBio" in w for w in man["warnings"])
    assert man["deck"]["analysis"] == "*STEP, NLGEOM; *STATIC"


@pytest.mark.skipif(ccx_executable() is None, reason="CalculiX 'ccx' is not on PATH (`make ccx`)")
def test_calculix_runs_the_visco_deck_and_compare_reads_dat_and_frd_alike(prony_case, tmp_path):
    folder, out, man = prony_case
    run_ccx((out / "abaqus" / "model.inp").read_text(), jobname="model", keep_dir=tmp_path)
    amp = pd.read_csv(out / "amplitude.csv")
    t_peak = float(amp["time_s"].iloc[int(np.argmax(amp["depth_mm"]))])
    res = {}
    for ext in ("dat", "frd"):
        cmp = tmp_path / f"cmp_{ext}"
        r = _invoke("compare", "--fe-displacements", tmp_path / f"model.{ext}", "--mesh", out / "abaqus" / "model.inp",
                    "--markers", folder / "reg" / "markers_ct.csv", "-o", cmp)
        assert r.exit_code == 0, r.output
        res[ext] = json.loads((cmp / "compare.json").read_text())
    for d in res.values():
        assert d["fe_result"]["time"] == pytest.approx(t_peak, rel=1e-5)       # not the last (the release)
        assert d["fe_result"]["n_results"] > 2 and "nearest in time" in d["fe_result"]["why"]
        assert d["frame_choice"]["why"].startswith("the peak")
        assert d["coordinate_system"]["ct_coordinate_system"] == man["frame"]["coordinate_system"]
    assert res["dat"]["markers"].keys() == res["frd"]["markers"].keys()
    for m in res["dat"]["markers"]:
        a, b = (np.array(res[k]["markers"][m]["model_mm"]) for k in ("dat", "frd"))
        assert np.abs(a - b).max() < DAT_FRD_TOL_MM


def _abaqus_spring_stiffness(deck: str) -> dict[int, float]:
    """Element id -> stiffness from the deck's SPRINGA blocks and their *SPRING cards."""
    lines = deck.splitlines()
    members, k_of = {}, {}
    i = 0
    while i < len(lines):
        up = lines[i].upper()
        if up.startswith("*ELEMENT") and "SPRINGA" in up:
            name = up.split("ELSET=")[1].strip()
            i += 1
            while i < len(lines) and not lines[i].startswith("*"):
                members.setdefault(name, []).append(int(lines[i].split(",")[0]))
                i += 1
            continue
        if up.startswith("*SPRING,"):
            k_of[up.split("ELSET=")[1].strip()] = float(lines[i + 2])
            i += 3
            continue
        i += 1
    return {e: k_of[name] for name, ids in members.items() for e in ids}


@pytest.mark.parametrize("lumping", ["uniform", "tributary"])
def test_interface_springs_uniform_or_by_tributary_area(tmp_path, lumping):
    """interface.lumping: uniform gives every spring k x A / n (the published rule) and, on the
    demonstration mesh whose interface nodes' tributary areas differ more than twofold, a
    warning with the range; tributary gives each spring k x its node's tributary area, in
    all three decks (ABAQUS: a *SPRING card per stiffness; LS-DYNA: each element's scale
    factor S on one material; FEBio: a discrete set and material per stiffness), the same
    total stiffness, and CalculiX runs the deck (a whole-number stiffness is written with a
    decimal point: CalculiX had read such a line as degrees of freedom and stopped)."""
    build_inputs(tmp_path, extra={"interface": {"lumping": lumping}})
    res = _invoke("export-fe", tmp_path / "export.yaml", "-o", tmp_path / "out")
    assert res.exit_code == 0, res.output
    out = tmp_path / "out"
    man = json.loads((out / "manifest.json").read_text())
    sp = pd.read_csv(out / "springs.csv")
    k_area = man["springs"]["stiffness_n_per_mm_per_mm2"]
    lumped = k_area * sp["tributary_area_mm2"].to_numpy()
    uniform = k_area * man["springs"]["deck"]["area_mm2"] / len(sp)
    want = lumped if lumping == "tributary" else np.full(len(sp), uniform)
    np.testing.assert_allclose(sp["stiffness_n_per_mm"], want, rtol=1e-9)          # springs.csv's digits
    np.testing.assert_allclose(sp["stiffness_n_per_mm"].sum(), k_area * man["springs"]["deck"]["area_mm2"], rtol=1e-9)
    warned = any("tributary areas range" in w for w in man["warnings"])
    assert warned == (lumping == "uniform" and lumped.max() / lumped.min() > 2)
    # ABAQUS: each spring element's stiffness, in deck units (a common factor from N/mm)
    k_abq = _abaqus_spring_stiffness((out / "abaqus" / "model.inp").read_text())
    k_abq = np.array([k_abq[int(e)] for e in sp["spring"]])
    factor = k_abq / want
    np.testing.assert_allclose(factor, factor[0], rtol=1e-9)
    # LS-DYNA: material K times each element's S
    text = "\n".join(p.read_text() for p in sorted((out / "lsdyna").glob("*.k")))
    lines = text.splitlines()
    k_mat = float(lines[lines.index("$#     mid         k") + 1][10:20])
    at = lines.index("*ELEMENT_DISCRETE") + 2
    rows = {}
    for ln in lines[at:]:
        if ln.startswith("*") or ln.startswith("$"):
            break
        rows[int(ln[:8])] = float(ln[40:56])
    k_dyna = np.array([k_mat * rows[int(e)] for e in sp["spring"]])
    np.testing.assert_allclose(k_dyna / want, (k_dyna / want)[0], rtol=1e-6)
    # FEBio: the springs' materials hold the same stiffnesses
    feb = (out / "febio" / "model.feb").read_text()
    n_mats = feb.count('type="linear spring"')
    assert n_mats == len(np.unique(np.round(sp["tributary_area_mm2"], 6))) if lumping == "tributary" else n_mats == 1
    if ccx_executable() is not None:
        run_ccx((out / "abaqus" / "model.inp").read_text(), jobname="model", keep_dir=tmp_path / "ccx")
        assert (tmp_path / "ccx" / "model.dat").stat().st_size > 0


def test_node_set_from_an_element_set(tmp_path):
    """``*NSET, NSET=S, ELSET=E`` (the nodes of E's elements), as Abaqus/CAE writes a surface's
    nodes: it had read as an empty set, and export-fe said "node set INTERFACE is not in the
    mesh (it has [..., 'INTERFACE', ...])".  Elements whose lines continue, ``*ELSET,
    GENERATE`` and a keyword line continued after a comma are read."""
    deck = tmp_path / "m.inp"
    deck.write_text("*NODE\n" + "".join(f"{i}, {i}.0, 0.0, 0.0\n" for i in range(1, 31))
                    + "*ELEMENT, TYPE=C3D20, ELSET=ALL\n"
                    + "1, " + ", ".join(str(i) for i in range(1, 16)) + ",\n"
                    + ", ".join(str(i) for i in range(16, 21)) + "\n"
                    + "2, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25,\n26, 27, 28, 29, 30\n"
                    + "*Elset, elset=SKIN, generate\n2, 2, 1\n*Nset, nset=INTERFACE,\n elset=SKIN\n"
                    + "*Nset, nset=BOTH, elset=ALL\n")
    sets = abaqus_node_sets(deck)
    assert sets["INTERFACE"].tolist() == list(range(11, 31))
    assert sets["BOTH"].tolist() == list(range(1, 31))
