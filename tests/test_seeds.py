"""seeds.csv as labs write it: a European spreadsheet's ';', names XMALab's layouts can hold."""

from pathlib import Path

import pandas as pd
import pytest

from bsipipe.errors import InputError
from bsipipe.io.seeds import read_seeds

XRAY = Path(__file__).parent / "data" / "real" / "xray_frame_deepxromm"


@pytest.mark.parametrize("sep", [",", ";", "\t"])
def test_separator_is_read_from_the_header(tmp_path, sep):
    """A ';' export had been refused as 'missing column(s) view, marker, x_px, y_px'."""
    p = tmp_path / "seeds.csv"
    p.write_text(sep.join(["view", "marker", "x_px", "y_px"]) + "\n"
                 + sep.join(["cam1", "M1", "12.5", "40.25"]) + "\n" + sep.join(["cam1", "M2", "30", "41"]) + "\n",
                 encoding="utf-8-sig")
    df = read_seeds(p, ["cam1"])
    assert list(df["marker"]) == ["M1", "M2"] and df["x_px"].tolist() == [12.5, 30.0]


def test_a_name_with_a_comma_is_refused_naming_its_line(tmp_path):
    """xmalab_2d.csv and xmalab_3d.csv had been written with more header fields than data fields."""
    p = tmp_path / "seeds.csv"
    p.write_text('view,marker,x_px,y_px\ncam1,M1,1,2\ncam1,"M2,a",3,4\n')
    with pytest.raises(InputError, match="comma") as e:
        read_seeds(p, ["cam1"])
    assert e.value.line == 3


def test_xmalab_seeds_views_called_camN_match_by_name():
    """Views called cam1 and cam2 keep their names whatever order they are given in: an
    XMALab seeds file's cam1 columns seed the view called cam1 (it had seeded the first view
    given, here cam2), and the XMALab 2-D file written back holds cam1 first; a lone view
    called cam2 is the file's cam2."""
    from bsipipe.io.xmalab import format_xmalab_2d, read_xmalab_2d, xmalab_cameras
    src = XRAY / "sample_frame_input.csv"
    ref = read_xmalab_2d(src)
    ref = ref[(ref["frame"] == 0) & ref["x_px"].notna()]
    for order in (["cam1", "cam2"], ["cam2", "cam1"]):
        assert xmalab_cameras(order) == {"cam1": "cam1", "cam2": "cam2"}
        s = read_seeds(src, order)
        for v in ("cam1", "cam2"):
            a = s[s["view"] == v].set_index("marker")[["x_px", "y_px"]].sort_index()
            b = ref[ref["view"] == v].set_index("marker")[["x_px", "y_px"]].sort_index()
            pd.testing.assert_frame_equal(a, b, check_dtype=False)
    # a lone view called cam2 takes the file's cam2 columns (it had taken cam1's)
    s = read_seeds(src, ["cam2"])
    assert set(s["view"]) == {"cam2"}
    pd.testing.assert_frame_equal(s.set_index("marker")[["x_px", "y_px"]].sort_index(),
                                  ref[ref["view"] == "cam2"].set_index("marker")[["x_px", "y_px"]].sort_index(),
                                  check_dtype=False)
    # other names: the N-th view given is camN, as XMALab numbers the cameras it loads
    assert xmalab_cameras(["lateral", "dorsal"]) == {"cam1": "lateral", "cam2": "dorsal"}
    assert xmalab_cameras(["cam2", "dorsal"]) == {"cam1": "cam2", "cam2": "dorsal"}
    pts = pd.DataFrame({"view": ["cam1", "cam2"], "frame": [0, 0], "marker": ["A", "A"], "x_px": [1.0, 2.0],
                        "y_px": [3.0, 4.0]})
    text = format_xmalab_2d(pts, ["cam2", "cam1"])
    assert text.splitlines()[:2] == ["A_cam1_X,A_cam1_Y,A_cam2_X,A_cam2_Y", "1,3,2,4"]


@pytest.mark.parametrize("cell, said", [("", "x_px is empty"), ("abc", "x_px is not a number: 'abc'")])
def test_a_seed_without_a_number_is_named_by_line(tmp_path, cell, said):
    """An empty coordinate had been reported as "x_px is not a number: np.float64(nan)"."""
    p = tmp_path / "seeds.csv"
    p.write_text(f"view,marker,x_px,y_px\ncam1,M1,10,12\ncam1,M2,{cell},14\n")
    with pytest.raises(InputError) as e:
        read_seeds(p, ["cam1"])
    assert e.value.line == 3 and str(e.value).endswith(said)


def test_latin1_seeds_are_read(tmp_path):
    """Marker names with accents in a Windows spreadsheet's Latin-1 export."""
    from bsipipe.io.seeds import read_seeds
    p = tmp_path / "seeds.csv"
    p.write_bytes(b"view,marker,x_px,y_px\ncam1,M\xe9,10.5,20.5\n")
    assert read_seeds(p, ["cam1"])["marker"].tolist() == ["M\u00e9"]


def test_dltdv_xypts_seeds_and_round_trip(tmp_path):
    """DLTdv8's flat points file (``<prefix>xypts.csv``: ``pt1_cam1_X,...``, MATLAB pixels, the
    top-left pixel's centre at (1, 1)) seeds a run as an XMALab file does, its coordinates
    taken to bsipipe's (1 less); read as an XMALab file it had seeded every marker 1.4 px off.
    The writer's text reads back to the same positions; a file so named whose header names its
    markers is XMALab's; DLTdv's sparse export is refused with what to do."""
    from bsipipe.io.dltdv import format_dltdv_xypts, is_dltdv_xypts, read_dltdv_xypts
    p = tmp_path / "trial1xypts.csv"
    p.write_text("pt1_cam1_X,pt1_cam1_Y,pt1_cam2_X,pt1_cam2_Y,pt2_cam1_X,pt2_cam1_Y,pt2_cam2_X,pt2_cam2_Y\n"
                 "101.5,201.25,NaN,NaN,31,41,51,61\n"
                 "102.5,202.25,11,21,NaN,NaN,52,62\n")
    assert is_dltdv_xypts(p)
    s = read_seeds(p, ["lateral", "dorsal"])
    got = {(r.view, r.marker): (r.x_px, r.y_px) for r in s.itertuples()}
    assert got == {("lateral", "pt1"): (100.5, 200.25), ("lateral", "pt2"): (30.0, 40.0),
                   ("dorsal", "pt2"): (50.0, 60.0)}
    assert s.attrs["later"] == {"dorsal": {"pt1": 1}}
    back = read_dltdv_xypts(p)
    text, names = format_dltdv_xypts(back.assign(view=back["view"].map({"cam1": "lateral", "cam2": "dorsal"})),
                                     ["lateral", "dorsal"], ["pt1", "pt2"], range(2))
    assert names == {"pt1": "pt1", "pt2": "pt2"}
    assert [ln.split(",") for ln in text.splitlines()] == [ln.split(",") for ln in p.read_text().splitlines()]
    # the same header in a file not so named, and a file so named with named markers: XMALab's
    q = tmp_path / "clicks.csv"
    q.write_text(p.read_text())
    assert not is_dltdv_xypts(q) and read_seeds(q, ["a", "b"])["x_px"].iloc[0] == 101.5
    r = tmp_path / "namedxypts.csv"
    r.write_text("R1_cam1_X,R1_cam1_Y\n5,6\n")
    assert not is_dltdv_xypts(r) and read_seeds(r, ["a"])["x_px"].iloc[0] == 5.0
    sp = tmp_path / "sparsexypts.csv"
    sp.write_text("xypts\n2\t8\t3\n1\t1\t101.5\n1\t2\t201.25\n2\t1\t102.5\n")
    with pytest.raises(InputError, match="sparse") as e:
        read_seeds(sp, ["a", "b"])
    assert e.value.path is not None and "sparsexypts.csv" in str(e.value.path)
