"""seeds.csv as labs write it: a European spreadsheet's ';', names XMALab's layouts can hold."""

import pytest

from bsipipe.errors import InputError
from bsipipe.io.seeds import read_seeds


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
