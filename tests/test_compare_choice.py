"""``bsipipe compare``: which measured frame and which FE result are compared, and what
``compare.json`` says about it.

An FE file often holds many results (a CalculiX ``.frd`` one per increment, to the release of
the indentor); the markers are taken at their peak.  The cases here are exact: the FE field
is a linear field (which C3D8 interpolation recovers to round-off) scaled by an amplitude
per result, and the measured displacements are the same field scaled by the amplitude at the
measured frame, so the right pairing gives sigma at round-off (< 1e-9 mm) and any other
pairing an error of the order of the field (> 0.1 mm).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.fe.compare import choose_fe_result, peak_frame, peak_frame_info
from bsipipe.io.abaqus import abaqus_header_line, abaqus_header_values
from test_compare import MESHES, SIZE, write_inp
from test_shape_functions import linear_field, points_inside

EXACT_MM = 1e-9          # linear field in C3D8: interpolation is exact up to round-off
WRONG_MM = 0.1           # a wrong pairing is off by a fraction of the field (~1 mm)

#: FE results at FE times 1, 2, 3, 4 s: loading to the peak at 2 s, then unloading.
FE_TIMES = np.array([1.0, 2.0, 3.0, 4.0])
FE_AMPLITUDE = np.array([0.5, 1.0, 0.6, 0.1])


def _invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def _setup(tmp_path, *, header: str = "", fe_time_col: bool = False, time_zero_s: float = 10.0,
           frame_times=None, drop=()):
    """Mesh, a CSV of four FE results (``time_s``), and a marker table whose frame k is at
    X-ray time ``time_zero_s + frame_times[k]`` with the FE field's amplitude there."""
    coords, blocks = MESHES["C3D8"]()
    mesh = tmp_path / "mesh.inp"
    ids = write_inp(mesh, coords, blocks)
    if header:
        text = mesh.read_text()
        mesh.write_text(header + text)
    u = linear_field(coords)
    rows = [{"node": n, "time_s": t, "ux_mm": a * v[0], "uy_mm": a * v[1], "uz_mm": a * v[2]}
            for t, a in zip(FE_TIMES, FE_AMPLITUDE) for n, v in zip(ids, u)]
    fe = tmp_path / "fe.csv"
    pd.DataFrame(rows).to_csv(fe, index=False, float_format="%.17g")
    X = points_inside(6, size=SIZE, margin=0.5, seed=5)
    names = [f"M{i}" for i in range(len(X))]
    frame_times = np.array([0.0, 1.0, 2.0, 3.0, 4.0] if frame_times is None else frame_times)
    amp = np.interp(frame_times, np.r_[0.0, FE_TIMES], np.r_[0.0, FE_AMPLITUDE])
    rows = []
    for f, (t, a) in enumerate(zip(frame_times, amp)):
        d = a * linear_field(X)
        for i, n in enumerate(names):
            if (n, f) in drop:
                continue
            r = {"frame": f, "time_s": time_zero_s + t, "marker": n, "x_mm": X[i, 0] + d[i, 0],
                 "y_mm": X[i, 1] + d[i, 1], "z_mm": X[i, 2] + d[i, 2], "dx_mm": d[i, 0], "dy_mm": d[i, 1],
                 "dz_mm": d[i, 2], "role": "marker"}
            if fe_time_col:
                r["fe_time_s"] = t
            rows.append(r)
    markers = tmp_path / "markers.csv"
    pd.DataFrame(rows).to_csv(markers, index=False, float_format="%.17g")
    return mesh, fe, markers


def _compare(tmp_path, mesh, fe, markers, *extra):
    out = tmp_path / "cmp"
    r = _invoke("compare", "--fe-displacements", fe, "--mesh", mesh, "--markers", markers, "-o", out, *extra)
    assert r.exit_code == 0, r.output
    return json.loads((out / "compare.json").read_text())


def test_default_pairs_the_peak_frame_with_the_peak_fe_result(tmp_path):
    """No clock ties the FE times to the markers: the measured peak (frame 2) is set against
    the FE result of the largest displacement at the markers (FE time 2), not the last
    (after the release), which the old default took."""
    mesh, fe, markers = _setup(tmp_path)
    res = _compare(tmp_path, mesh, fe, markers)
    assert res["frame"] == 2
    assert res["fe_result"]["index"] == 1 and res["fe"]["time"] == 2.0
    assert "peak" in res["fe_result"]["why"]
    assert res["sigma_mm"] < EXACT_MM
    assert res["warnings"] == []


def test_fe_result_matched_by_the_deck_clock(tmp_path):
    """export-fe states the X-ray time of FE time 0 in the deck header; a chosen frame
    (frame 3: X-ray 13 s = FE 3 s) is set against the FE result at 3 s."""
    header = f"** {abaqus_header_line('fe_time_zero_xray_s', 10.0)}\n** {abaqus_header_line('fe_time_unit', 's')}\n"
    mesh, fe, markers = _setup(tmp_path, header=header)
    res = _compare(tmp_path, mesh, fe, markers, "--frame", 3)
    assert res["fe_result"]["index"] == 2 and res["fe_result"]["measured_frame_fe_time"] == pytest.approx(3.0)
    assert "nearest in time" in res["fe_result"]["why"] and "header" in res["fe_result"]["clock"]
    assert res["sigma_mm"] < EXACT_MM and res["warnings"] == []


def test_fe_result_matched_by_the_marker_tables_fe_time(tmp_path):
    """markers_fe.csv (export-fe) carries fe_time_s: frame 1 (FE 1 s) pairs with result 0."""
    mesh, fe, markers = _setup(tmp_path, fe_time_col=True)
    res = _compare(tmp_path, mesh, fe, markers, "--frame", 1)
    assert res["fe_result"]["index"] == 0 and res["fe_result"]["clock"] == "the marker table's fe_time_s"
    assert res["sigma_mm"] < EXACT_MM


@pytest.mark.parametrize("given, index", [(1, 1), (3, 3), (-2, 2), (0, 0)])
def test_fe_result_given(tmp_path, given, index):
    """--fe-result picks the result whatever the clocks say (only that one is read): with the
    marker table's FE times, a given result other than the frame's is compared and its time
    gap warned about; it had ended in an internal error (IndexError) for any index but 0."""
    mesh, fe, markers = _setup(tmp_path, fe_time_col=True)
    res = _compare(tmp_path, mesh, fe, markers, "--frame", 2, "--fe-result", given)
    assert res["fe_result"]["index"] == index and res["fe"]["time"] == FE_TIMES[index]
    assert "given" in res["fe_result"]["why"]
    if index == 1:                      # frame 2 is at FE time 2 s: the right result
        assert res["sigma_mm"] < EXACT_MM and res["warnings"] == []
    else:
        assert res["sigma_mm"] > WRONG_MM
        assert any(f"FE time {FE_TIMES[index]:g}) is {abs(FE_TIMES[index] - 2.0):.3g} from" in w
                   for w in res["warnings"])
    r = _invoke("compare", "--fe-displacements", fe, "--mesh", mesh, "--markers", markers, "--fe-result", 4,
                "-o", tmp_path / "bad")
    assert r.exit_code == 2 and "holds 4" in r.output and not (tmp_path / "bad").exists()


@pytest.mark.parametrize("table_cs, ok", [("LPS", True), ("unstated", True), ("RAS", False), ("LPS|RAS", False)])
def test_marker_table_and_mesh_must_share_the_ct_frame(tmp_path, table_cs, ok):
    """A deck written in an LPS CT frame (export-fe's header) against markers_ct.csv of an RAS
    registration (x and y of opposite signs) is exit 2 naming both files, with nothing
    written: it had been compared without a word (the sample study's files: sigma 0.994 mm
    for 1.542).  A table that states nothing is compared as before; one that states both is
    refused too."""
    header = f"** {abaqus_header_line('ct_coordinate_system', 'LPS')}\n"
    mesh, fe, markers = _setup(tmp_path, header=header)
    t = pd.read_csv(markers)
    cs = table_cs.split("|")
    t["coordinate_system"] = [cs[i % len(cs)] for i in range(len(t))]
    t.to_csv(markers, index=False, float_format="%.17g")
    out = tmp_path / "cmp"
    r = _invoke("compare", "--fe-displacements", fe, "--mesh", mesh, "--markers", markers, "-o", out)
    if ok:
        assert r.exit_code == 0, r.output
        assert json.loads((out / "compare.json").read_text())["sigma_mm"] < EXACT_MM
    else:
        assert r.exit_code == 2 and str(markers) in r.output and not out.exists()
        assert ("RAS, those of" in r.output and str(mesh) in r.output) if table_cs == "RAS" else "LPS and RAS" in r.output


def test_an_unknown_marker_is_named(tmp_path):
    """--marker M9 that the table does not hold is exit 2 naming it (it had been 'no frame has
    a finite displacement', as if the data were at fault)."""
    mesh, fe, markers = _setup(tmp_path)
    r = _invoke("compare", "--fe-displacements", fe, "--mesh", mesh, "--markers", markers, "--marker", "M9",
                "-o", tmp_path / "cmp")
    assert r.exit_code == 2 and "marker(s) M9 not in the marker table" in r.output and str(markers) in r.output


def test_unmatched_fe_time_and_unknown_clock_are_warned(tmp_path):
    """A frame between FE results (FE 2.5 s, results at 2 and 3 s, frames 0.5 s apart) is compared with the
    nearest and warned about; without any clock a non-peak frame cannot be matched: the
    last result, with a warning that names --fe-result."""
    mesh, fe, markers = _setup(tmp_path, fe_time_col=True, frame_times=[0.0, 0.5, 1.0, 2.5, 3.0])
    res = _compare(tmp_path, mesh, fe, markers, "--frame", 3)
    assert res["fe_result"]["index"] in (1, 2)
    assert any("from the measured frame's FE time 2.5" in w for w in res["warnings"])
    mesh, fe, markers = _setup(tmp_path)
    res = _compare(tmp_path, mesh, fe, markers, "--frame", 1)
    assert res["fe_result"]["index"] == 3 and res["sigma_mm"] > WRONG_MM
    assert any("--fe-result" in w for w in res["warnings"])


def test_peak_frame_does_not_move_when_a_marker_is_lost_in_it(tmp_path):
    """Markers of very different displacement (a marker near the indentor moves 10x the
    others): losing it in the peak frame used to move the peak (the mean of the rest is
    smaller there); the mean is now over the same markers in every frame, the gap filled."""
    frames = np.arange(11)
    amp = 1.0 - np.abs(frames - 5) / 5.0
    rows = []
    for name, scale in (("A", 10.0), ("B", 1.0), ("C", 1.0)):
        for f, a in zip(frames, amp):
            if (name, f) == ("A", 5):
                continue
            rows.append({"frame": f, "marker": name, "dx_mm": scale * a, "dy_mm": 0.0, "dz_mm": 0.0})
    t = pd.DataFrame(rows)
    info = peak_frame_info(t)
    assert info.frame == peak_frame(t) == 5
    assert info.markers == ["A", "B", "C"] and info.filled == {"A": [5]}
    # a marker with a long gap takes no part
    long_gap = t[~((t["marker"] == "B") & t["frame"].between(2, 8))]
    info = peak_frame_info(long_gap)
    assert info.frame == 5 and "B" in info.left_out and info.markers == ["A", "C"]


def test_compare_reports_the_frame_choice_and_skipped_marker(tmp_path):
    """Through the command: M0 lost in the peak frame 2 leaves the frame at 2 and is named in
    ``skipped`` and ``warnings``; the CT coordinate system comes from the deck header."""
    header = f"** {abaqus_header_line('ct_coordinate_system', 'LPS')}\n"
    mesh, fe, markers = _setup(tmp_path, header=header, drop={("M0", 2)})
    res = _compare(tmp_path, mesh, fe, markers)
    assert res["frame"] == 2 and res["frame_choice"]["peak"]["filled_frames"] == {"M0": [2]}
    assert res["skipped"] == {"M0": "no row in frame 2"} and any("M0" in w for w in res["warnings"])
    assert res["coordinate_system"]["ct_coordinate_system"] == "LPS"
    assert res["sigma_mm"] < EXACT_MM


def test_choose_fe_result_rules():
    assert choose_fe_result(4, given=-1).index == 3
    c = choose_fe_result(1, fe_times=[5.0], target_fe_time=2.0, time_tol=0.25)
    assert c.index == 0 and c.warnings                                   # one result, far in time
    c = choose_fe_result(3, fe_times=[1.0, 2.0, 3.0], target_fe_time=9.0, time_tol=0.25)
    assert c.index == 2 and "outside" in c.warnings[0]
    c = choose_fe_result(3, peak_values=[np.nan, np.nan, np.nan], frame_is_peak=True)
    assert c.index == 2 and c.warnings
    assert choose_fe_result(1, frame_is_peak=True).warnings == []
    assert choose_fe_result(1, frame_is_peak=False).warnings                # one untimed result, another frame


def test_deck_header_values_round_trip(tmp_path):
    p = tmp_path / "d.inp"
    p.write_text(f"** a comment\n** {abaqus_header_line('fe_time_zero_xray_s', 3.75)}\n*NODE\n"
                 f"** {abaqus_header_line('late', 1)}\n")
    assert abaqus_header_values(p) == {"fe_time_zero_xray_s": "3.75"}


@pytest.mark.parametrize("which", ["fe results in ms", "marker times in ms"])
def test_fe_and_marker_clocks_in_different_units_are_invalid_input(tmp_path, which):
    """FE results solved with a deck in ms set against a deck header in s (or a marker table
    whose time_s holds ms) had been exit 0: the measured frame's FE time fell outside the
    results' span, the nearest result (the first, or the last) was compared, and only a
    warning said the time was outside (the probe: the study's sigma 1.542 mm read as 0.905 or
    1.087 mm).  The FE results span about 1000 times the table's time and 1000 times the
    frame's FE time lies inside them: exit 2 naming the units."""
    header = f"** {abaqus_header_line('fe_time_zero_xray_s', 10.0)}\n** {abaqus_header_line('fe_time_unit', 's')}\n"
    mesh, fe, markers = _setup(tmp_path, header=header)
    if which == "fe results in ms":
        t = pd.read_csv(fe)
        t["time_s"] *= 1000.0
        t.to_csv(fe, index=False, float_format="%.17g")
    else:
        m = pd.read_csv(markers)
        m["time_s"] = (m["time_s"] - 10.0) * 1000.0 + 10.0
        m.to_csv(markers, index=False, float_format="%.17g")
    r = _invoke("compare", "--fe-displacements", fe, "--mesh", mesh, "--markers", markers, "--frame", 3,
                "-o", tmp_path / "cmp")
    assert r.exit_code == 2 and "same unit" in r.output and "fe.csv" in r.output, r.output
    assert not (tmp_path / "cmp").exists()


def test_a_marker_missing_at_the_registration_frame_is_not_called_never_found():
    """A marker found in many frames but not in the registration frame has no displacement
    in any frame; the peak-frame note had called it "never found" (the probe: M1 in 43 frames,
    M3 in 55)."""
    from bsipipe.fe.compare import peak_frame_info
    t = pd.DataFrame({"frame": [0, 0, 1, 1, 2, 2], "marker": list("ABABAB"),
                      "x_mm": [0.0, np.nan, 0.1, 1.0, 0.2, 1.1],
                      "dx_mm": [0.0, np.nan, 0.1, np.nan, 0.2, np.nan], "dy_mm": 0.0, "dz_mm": 0.0})
    info = peak_frame_info(t)
    assert "found in 2 frames but not in the registration frame" in info.left_out["B"]


def test_the_loading_history_is_compared_at_every_fe_result(tmp_path):
    """With the deck's clock, every FE result falls on a frame (FE 1..4 s on frames 1..4) and is
    set against the markers found there: M0, lost in the peak frame (behind the indentor, say),
    is compared in the other three, where it had been left out of the comparison altogether.
    Exact pairings: every result's sigma at round-off.  No clock, or --fe-result: no history."""
    header = f"** {abaqus_header_line('fe_time_zero_xray_s', 10.0)}\n** {abaqus_header_line('fe_time_unit', 's')}\n"
    mesh, fe, markers = _setup(tmp_path, header=header, drop=[("M0", 2)])
    res = _compare(tmp_path, mesh, fe, markers)
    assert res["frame"] == 2 and "M0" in res["skipped"]
    ts = res["time_series"]
    assert [r["frame"] for r in ts["results"]] == [1, 2, 3, 4] and [r["fe_result"] for r in ts["results"]] == [0, 1, 2, 3]
    assert all(r["sigma_mm"] < EXACT_MM for r in ts["results"]) and ts["sigma_mm"] < EXACT_MM
    assert ts["per_marker"]["M0"]["n_results"] == 3 and ts["n_pairs"] == 6 * 4 - 1
    assert "M0" not in ts["results"][1]["markers"]
    assert (tmp_path / "cmp" / "compare_time.png").stat().st_size > 20000
    no_clock = tmp_path / "no_clock"
    no_clock.mkdir()
    mesh, fe, markers = _setup(no_clock)
    assert _compare(no_clock, mesh, fe, markers)["time_series"] is None
    mesh, fe, markers = _setup(tmp_path, header=header)
    assert _compare(tmp_path, mesh, fe, markers, "--fe-result", 1)["time_series"] is None
