"""3D Slicer markups readers (CT marker coordinates): every .fcsv version, .mrk.json, plain CSV.

Round trips through the writers (``format_fcsv``, ``format_mrk_json``) in LPS and RAS give the
numbers back exactly, in the file's own system; converting between systems negates x and y.
Files as older and newer Slicer versions write them (4.x with ``CoordinateSystem = 0/1``,
unversioned Slicer 3 files, 5.x rows with position status fields, quoted labels) read as
Slicer reads them.  Bad files fail with the file and line named, and ``bsipipe register``
exits 2 on them.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from bsipipe.cli import cli
from bsipipe.errors import InputError
from bsipipe.io.slicer import (format_fcsv, format_mrk_json, lps_ras, read_fcsv, read_marker_csv, read_markups,
                               read_mrk_json)

LABELS = ["R1", "R2", "R3", "M1"]
POINTS = np.array([[12.25, -30.5, 101.125], [-7.1, 0.3, 99.9], [1e-3, 1.0 / 3.0, -2.5], [4.0, 5.0, 6.0]])


@pytest.mark.parametrize("system", ["LPS", "RAS"])
@pytest.mark.parametrize("fmt", ["fcsv", "mrk.json"])
def test_round_trip_in_the_files_own_system(tmp_path, system, fmt):
    text = (format_fcsv if fmt == "fcsv" else format_mrk_json)(LABELS, POINTS, system)
    path = tmp_path / f"ct.{fmt}"
    path.write_text(text)
    m = read_markups(path)
    assert m.names == LABELS and m.coordinate_system == system and m.format == fmt
    assert np.array_equal(m.positions_mm, POINTS)             # exactly: the writer keeps every digit
    other = "RAS" if system == "LPS" else "LPS"
    conv = m.to(other)
    assert conv.coordinate_system == other
    assert np.array_equal(conv.positions_mm, POINTS * [-1, -1, 1])
    assert np.array_equal(conv.to(system).positions_mm, POINTS)
    assert np.array_equal(m.to(system).positions_mm, POINTS)
    assert np.array_equal(lps_ras(lps_ras(POINTS)), POINTS)


def test_lps_and_ras_files_of_one_scene_agree(tmp_path):
    (tmp_path / "a.fcsv").write_text(format_fcsv(LABELS, POINTS, "LPS"))
    (tmp_path / "b.mrk.json").write_text(format_mrk_json(LABELS, lps_ras(POINTS), "RAS"))
    a = read_markups(tmp_path / "a.fcsv")
    b = read_markups(tmp_path / "b.mrk.json")
    assert np.array_equal(b.to("LPS").positions_mm, a.positions_mm)
    assert np.array_equal(a.to("RAS").positions_mm, b.positions_mm)


def test_fcsv_slicer_4_numeric_coordinate_systems(tmp_path):
    for code, system in (("0", "RAS"), ("1", "LPS")):
        p = tmp_path / f"old{code}.fcsv"
        p.write_text("# Markups fiducial file version = 4.4\n"
                     f"# CoordinateSystem = {code}\n"
                     "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                     "vtkMRMLMarkupsFiducialNode_0,1.5,-2,3e1,0,0,0,1,1,1,0,R1,skull rim,vtkMRMLScalarVolumeNode1\n"
                     "vtkMRMLMarkupsFiducialNode_1,4,5,6,0,0,0,1,1,1,0,R2,,\n")
        m = read_fcsv(p)
        assert m.coordinate_system == system and m.version == "4.4"
        assert m.names == ["R1", "R2"] and m.positions_mm.tolist() == [[1.5, -2.0, 30.0], [4.0, 5.0, 6.0]]
        assert m.lines == [4, 5]


def test_fcsv_without_coordinate_system_is_ras(tmp_path):
    p = tmp_path / "noscs.fcsv"
    p.write_text("# Markups fiducial file version = 4.6\n"
                 "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                 "1,1,2,3,0,0,0,1,1,1,0,A,,\n")
    assert read_fcsv(p).coordinate_system == "RAS"


def test_fcsv_slicer_5_position_status_and_quoted_labels(tmp_path):
    p = tmp_path / "new.fcsv"
    p.write_text("# Markups fiducial file version = 5.6\n"
                 "# CoordinateSystem = LPS\n"
                 "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                 "1,1.0,2.0,3.0,0,0,0,1,1,1,1,R1,,,2,0\n"
                 '2,4.0,5.0,6.0,0,0,0,1,1,1,1,"R,2","a ""quoted"" note",,2,0\n'
                 "3,0,0,0,0,0,0,1,1,1,1,R3,,,0,0\n"          # position undefined: not a point
                 "4,0,0,0,0,0,0,1,1,1,1,R4,,,3,0\n")         # position missing
    m = read_fcsv(p)
    assert m.names == ["R1", "R,2"] and m.positions_mm.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert set(m.skipped) == {"R3", "R4"} and "undefined" in m.skipped["R3"] and "missing" in m.skipped["R4"]


def test_fcsv_slicer_3_and_other_columns(tmp_path):
    p = tmp_path / "s3.fcsv"
    p.write_text("# Fiducial List file s3.fcsv\n# numPoints = 2\n# symbolScale = 5\n"
                 "# columns = label,x,y,z,sel,vis\nR1,1,2,3,1,1\nR2,-4,-5,-6,1,1\n")
    m = read_fcsv(p)
    assert m.version is None and m.coordinate_system == "RAS"
    assert m.names == ["R1", "R2"] and m.positions_mm[1].tolist() == [-4, -5, -6]
    q = tmp_path / "short.fcsv"
    q.write_text("# Markups fiducial file version = 4.10.2\n# CoordinateSystem = 0\n# columns = id,x,y,z,label\n"
                 "0,1.1,1.2,1.3,10\n1,2.1,2.2,2.3,20\n")
    m = read_fcsv(q)
    assert m.names == ["10", "20"] and m.positions_mm[0].tolist() == [1.1, 1.2, 1.3]


def test_mrk_json_units_status_and_several_nodes(tmp_path):
    doc = {"@schema": "x", "markups": [
        {"type": "Fiducial", "coordinateSystem": "RAS", "coordinateUnits": "um",
         "controlPoints": [{"label": "R1", "position": [1000.0, -2000.0, 3500.0]},
                           {"label": "R2", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"}]},
        {"type": "Fiducial", "coordinateSystem": "RAS",
         "controlPoints": [{"label": "M1", "position": [1.0, 2.0, 3.0], "positionStatus": "defined"}]}]}
    p = tmp_path / "m.mrk.json"
    p.write_text(json.dumps(doc, indent=2))
    m = read_mrk_json(p)
    assert m.coordinate_system == "RAS" and m.names == ["R1", "M1"]
    assert m.positions_mm.tolist() == [[1.0, -2.0, 3.5], [1.0, 2.0, 3.0]]
    assert "undefined" in m.skipped["R2"]
    doc["markups"][1]["coordinateSystem"] = "LPS"
    p.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="different coordinate systems"):
        read_mrk_json(p)


def test_plain_csv(tmp_path):
    p = tmp_path / "ct.csv"
    p.write_text("# CoordinateSystem = LPS\nmarker,x_mm,y_mm,z_mm\nR1,1,2,3\nR2,4,5,6\n")
    m = read_marker_csv(p)
    assert m.coordinate_system == "LPS" and m.names == ["R1", "R2"] and m.lines == [3, 4]
    q = tmp_path / "ct2.csv"
    q.write_text("z_mm,marker,y_mm,x_mm\n3,R1,2,1\n")
    m = read_markups(q)
    assert m.coordinate_system is None and m.positions_mm.tolist() == [[1, 2, 3]]
    with pytest.raises(ValueError, match="does not state"):
        m.to("RAS")


@pytest.mark.parametrize("name,text,line,what", [
    ("a.fcsv", "# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n1,1,2,x,0,0,0,1,1,1,0,R1,,\n",
     3, "z is not a number"),
    ("b.fcsv", "# Markups fiducial file version = 4.11\n# CoordinateSystem = XYZ\n", 2, "unknown coordinate system"),
    ("c.fcsv", "# Markups fiducial file version = 4.11\n1,1,2,3,0,0,0,1,1,1,0,R1,,\n2,1,2,3,0,0,0,1,1,1,0,R1,,\n",
     3, "appears twice (also line 2)"),
    ("d.fcsv", "# Markups fiducial file version = 4.11\n1,1,2\n", 2, "fields"),
    ("e.mrk.json", '{"markups": [\n  {"controlPoints": [\n    {"label": "R1", "position": [1, 2]}]}]}', 3,
     "position"),
    ("f.mrk.json", '{"markups": [\n  {"controlPoints": [\n    {"label": "R1", "position": [1, 2, 3]},]}]}', 3,
     "invalid JSON"),
    ("g.csv", "marker,x_mm,y_mm\nR1,1,2\n", 1, "z_mm"),
    ("h.csv", "marker,x_mm,y_mm,z_mm\nR1,1,2,3\nR2,1,nan,3\n", 3, "y_mm is not finite"),
    ("i.csv", "marker,x_mm,y_mm,z_mm\n,1,2,3\n", 2, "empty label"),
    # a label in two markups lists: each named by its own line (both had been "line 3 ... (also line 3)")
    ("j.mrk.json", '{"markups": [\n  {"controlPoints": [\n    {"label": "R1", "position": [1, 2, 3]}]},\n'
                   '  {"controlPoints": [\n    {"label": "R1", "position": [4, 5, 6]}]}]}', 5,
     "appears twice (also line 3)"),
])
def test_bad_files_name_file_and_line(tmp_path, name, text, line, what):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(InputError) as e:
        read_markups(p)
    msg = str(e.value)
    assert name in msg and f"line {line}" in msg and what in msg


def test_register_exits_2_on_a_bad_ct_file(tmp_path):
    ct = tmp_path / "ct.fcsv"
    ct.write_text("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n1,1,2,abc,0,0,0,1,1,1,0,R1,,\n")
    xr = tmp_path / "markers3d.csv"
    xr.write_text("frame,time_s,marker,x_mm,y_mm,z_mm\n0,0,R1,1,2,3\n")
    r = CliRunner().invoke(cli, ["register", "--ct", str(ct), "--xray", str(xr), "--reference", "R1",
                                 "-o", str(tmp_path / "out")])
    assert r.exit_code == 2
    assert "ct.fcsv" in r.output and "line 3" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "out").exists()


def test_a_latin1_markups_file_is_read(tmp_path):
    """A Windows tool's .fcsv with a micro sign in a description, in Latin-1: it had been
    refused with Python's raw codec message."""
    from bsipipe.io.slicer import read_markups
    p = tmp_path / "l1.fcsv"
    p.write_bytes(b"# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
                  b"# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                  b"vtkMRMLMarkupsFiducialNode_0,1,2,3,0,0,0,1,1,1,0,R1,\xb5 marker,\n")
    assert read_markups(p).as_dict()["R1"].tolist() == [1.0, 2.0, 3.0]
