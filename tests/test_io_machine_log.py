"""Reading testing-machine logs and stress-stretch tables.

The fixtures in ``tests/data/logs`` hold one small compression record written in each
layout the reader knows (Bluehill 2, 3 and Universal, plain CSV in several dialects), with
its own units, separator, decimal mark and sign convention, plus malformed variants.  The
record is the one below; each layout must give it back to within half a unit of the last
digit the file wrote, converted to s, mm and N.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bsipipe.errors import InputError
from bsipipe.io._units import unit_factor
from bsipipe.io.machine_log import read_machine_log
from bsipipe.io.stress_table import read_stress_table

DATA = Path(__file__).parent / "data"
LOGS = DATA / "logs"
REAL = DATA / "real" / "instron_bluehill" / "bluehill2_compression_cyclic_Specimen_RawData_6.csv"

# The record every fixture holds (positive in compression): 30 samples at 10 Hz, the
# platen 0.05 mm further each sample, a 1 mN alternating load-cell ripple, and contact at
# sample 10 with the force growing as (k - 10)^1.5.
K = np.arange(30)
TIME_S = 0.1 * K
DISP_MM = 0.05 * K
FORCE_N = np.where(K >= 10, 0.02 * np.clip(K - 10, 0, None) ** 1.5, 0.0) + 0.001 * (-1.0) ** K

LBF, GF = 4.4482216152605, 9.80665e-3

# file: layout, units as written (time, extension, load), load sign and extension sign of
# compression, geometry, and the tolerances (half the last written digit, in s, mm, N).
LAYOUTS = {
    "bluehill2_metadata.csv": ("bluehill2", ("sec", "mm", "N"), -1, -1,
                               {"diameter_mm": 18.0, "height_mm": 12.0}, (5e-6, 5e-6, 5e-6)),
    "bluehill3_results_table.csv": ("bluehill3", ("s", "mm", "kN"), -1, -1,
                                    {"diameter_mm": 18.0, "height_mm": 12.0}, (5e-4, 5e-5, 5e-6)),
    "bluehill3_european.csv": ("bluehill3", ("s", "mm", "N"), -1, -1,
                               {"diameter_mm": 18.0, "height_mm": 12.0}, (5e-3, 5e-5, 5e-6)),
    "bluehill3_raw_data_marker.csv": ("bluehill3", ("s", "mm", "N"), -1, -1,
                                      {"diameter_mm": 18.0, "height_mm": 12.0}, (5e-5, 5e-6, 5e-7)),
    "bluehill3_utf16.csv": ("bluehill3", ("s", "mm", "gf"), -1, -1, {}, (5e-3, 5e-5, 5e-5 * GF)),
    "bluehill_universal.csv": ("bluehill-universal", ("s", "mm", "N"), 1, 1,
                               {"diameter_mm": 0.708661 * 25.4, "height_mm": 0.472441 * 25.4},
                               (5e-3, 5e-6, 5e-6)),
    "plain_snake_case.csv": ("plain-csv", ("s", "mm", "n"), 1, 1, {}, (5e-3, 5e-5, 5e-7)),
    "plain_units_in_names.csv": ("plain-csv", ("ms", "µm", "mN"), 1, 1, {}, (5e-4, 5e-5, 5e-7)),
    "plain_imperial.tsv": ("plain-csv", ("min", "in", "lbf"), -1, -1, {},
                           (5e-9 * 60, 5e-9 * 25.4, 5e-9 * LBF)),
    "plain_mixed_signs.csv": ("plain-csv", ("s", "mm", "n"), -1, 1, {}, (5e-3, 5e-5, 5e-7)),
}


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_each_layout_gives_back_the_record(name):
    layout, units, load_sign, disp_sign, geometry, (tol_t, tol_d, tol_f) = LAYOUTS[name]
    log = read_machine_log(LOGS / name)
    assert log.layout == layout
    assert len(log) == K.size
    assert tuple(log.units[k] for k in list(log.units)[:3]) == units
    assert (log.compression_sign, log.displacement_sign) == (load_sign, disp_sign)
    # Values come back converted, with the file's own signs (half a written digit, plus
    # the float rounding of the conversion factor).
    np.testing.assert_allclose(log.time_s, TIME_S, rtol=0, atol=tol_t * 1.0001)
    displacement_mm, force_n = log.compression()
    np.testing.assert_allclose(displacement_mm, DISP_MM, rtol=0, atol=2 * tol_d * 1.0001)
    np.testing.assert_allclose(force_n, FORCE_N, rtol=0, atol=tol_f * 1.0001)
    np.testing.assert_allclose(log.load_n, load_sign * FORCE_N, rtol=0, atol=tol_f * 1.0001)
    assert set(log.geometry) == set(geometry)
    for key, value in geometry.items():
        assert log.geometry[key] == pytest.approx(value, abs=1e-9)


def test_bluehill2_metadata_segment_and_lines():
    log = read_machine_log(LOGS / "bluehill2_metadata.csv")
    assert log.metadata["Specimen label"] == "brain 1"
    assert log.metadata["Start Date"] == "13/11/2018 5:14 PM"
    assert log.metadata["Diameter"] == "18.00 mm"
    np.testing.assert_array_equal(log.segment, np.where(K < 20, 22476, 22412))
    np.testing.assert_array_equal(log.extra["Total Cycle Count"], np.zeros(30))
    assert log.data_lines[0] == 8 and log.data_lines[-1] == 37
    assert log.dialect["newline"] == "CRLF"


def test_results_table_and_european_metadata():
    log = read_machine_log(LOGS / "bluehill3_results_table.csv")
    assert log.metadata["Results Table 1: Specimen label"] == "brain 2"
    assert log.metadata["Results Table 1: Maximum Load"] == "0.00166 kN"
    eu = read_machine_log(LOGS / "bluehill3_european.csv")
    assert (eu.dialect["delimiter"], eu.dialect["decimal"]) == (";", ",")
    assert eu.metadata["Specimen label"] == "Hirn 3"
    assert eu.geometry["height_mm"] == pytest.approx(12.0)  # written "1,2" cm
    uni = read_machine_log(LOGS / "bluehill_universal.csv")
    assert uni.metadata["Sample name"] == "brain_A"
    assert uni.metadata["Results Table 1: Maximum Force"] == "1.656 N"


def test_real_bluehill2_export():
    """The real Instron Bluehill 2 export (yadbor/bluer, CC0): 18,011 rows at 50 Hz."""
    log = read_machine_log(REAL)
    assert log.layout == "bluehill2"
    assert len(log) == 18011
    assert log.units == {"Time": "sec", "Extension": "mm", "Load": "N", "Segment ID": "",
                         "Total Cycle Count": ""}
    assert log.metadata == {"Specimen label": "22L.3", "Start Date": "13/11/2018 5:14 PM"}
    assert log.compression_sign == -1 and log.displacement_sign == -1
    assert log.dialect["newline"] == "CRLF"
    # First and last rows exactly as written (lines 6 and 18016 of the file).
    assert (log.time_s[0], log.extension_mm[0], log.load_n[0]) == (0.0, -2.04726, -4.319)
    assert (log.time_s[-1], log.extension_mm[-1], log.load_n[-1]) == (360.06, -2.04555, 0.28068)
    assert (log.data_lines[0], log.data_lines[-1]) == (6, 18016)
    assert set(np.unique(log.segment)) == {22412, 22476}
    np.testing.assert_array_equal(np.unique(log.extra["Total Cycle Count"]), [0, 1, 2])
    displacement_mm, force_n = log.compression()
    # The platen travels 10.0 mm into the sample and back three times; peak force 53 N.
    assert displacement_mm[0] == 0.0
    assert displacement_mm.max() == pytest.approx(12.04865 - 2.04726, abs=1e-9)
    assert force_n.max() == pytest.approx(53.0, abs=0.5)
    assert np.median(np.diff(log.time_s)) == pytest.approx(0.02, abs=1e-9)


# file, line, words the message must contain
MALFORMED = {
    "bad_missing_units_row.csv": (4, "expected a units row"),
    "bad_text_in_number.csv": (8, "text 'abc' in number column 'Load'"),
    "bad_nan.csv": (6, "NaN value"),
    "bad_inf.csv": (10, "infinite value"),
    "bad_time_backwards.csv": (7, "time goes back"),
    "bad_time_repeated.csv": (7, "repeats"),
    "bad_empty_data.csv": (5, "no data rows"),
    "bad_empty_file.csv": (1, "empty"),
    "bad_truncated_row.csv": (11, "truncated"),
    "bad_missing_column.csv": (1, "no extension column"),
    "bad_unknown_unit.csv": (2, "unknown force unit 'stone'"),
    "bad_unknown_unit_in_name.csv": (1, "unknown force unit 'furlong'"),
    "bad_no_header.csv": (1, "no header"),
    "bad_geometry_unit.csv": (1, "unknown length unit 'cubits'"),
}


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_variants_name_file_and_line(name):
    line, words = MALFORMED[name]
    with pytest.raises(InputError) as info:
        read_machine_log(LOGS / name)
    message = str(info.value)
    assert info.value.exit_code == 2
    assert name in message and f"line {line}:" in message and words in message, message
    assert "\n" not in message


def test_quoted_values_with_thousands_separators(tmp_path):
    p = tmp_path / "thousands.csv"
    p.write_text('"Time","Extension","Load"\n"(s)","(mm)","(N)"\n"0.0","-0.5","-1,234.5"\n'
                 '"1.0","-1.0","-2,000.25"\n')
    log = read_machine_log(p)
    np.testing.assert_array_equal(log.load_n, [-1234.5, -2000.25])


@pytest.mark.parametrize("preamble", [
    # results tables whose names, read word by word, name the channels (Bluehill 3, Universal)
    '"Results Table 1"\n"Extension at Maximum Load (mm)","Maximum Load (N)","Specimen label"\n"4.100","0.547","s1"\n\n'
    '"Raw Data"\n',
    "Results Table 1\nSpecimen label,Maximum Compressive load (N),Compressive extension at Maximum (mm)\n"
    "s1,0.547,4.1\n\nRaw Data\n",
    # free text naming them
    "Test end: Extension limit or Load drop 40 %\n\n",
])
def test_lines_naming_the_channels_without_data_under_them_are_not_the_header(tmp_path, preamble):
    p = tmp_path / "results_first.csv"
    p.write_text(preamble + '"Time","Extension","Load"\n"(s)","(mm)","(N)"\n'
                 + "".join(f'"{0.1 * k:.1f}","{-0.01 * k:.2f}","{-0.02 * k:.3f}"\n' for k in range(12)))
    log = read_machine_log(p)
    np.testing.assert_allclose(log.time_s, 0.1 * np.arange(12))
    np.testing.assert_allclose(log.load_n, -0.02 * np.arange(12))


def test_missing_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        read_machine_log(tmp_path / "absent.csv")


def test_compression_positive_file_with_compressive_names(tmp_path):
    """A method that names its channels 'Compressive ...' writes compression positive,
    even before the record shows any load."""
    p = tmp_path / "compressive.csv"
    p.write_text("Time,Compressive extension,Compressive load\n(s),(mm),(N)\n"
                 + "".join(f"{0.1 * k:.1f},{0.01 * k:.2f},0.0\n" for k in range(10)))
    log = read_machine_log(p)
    assert (log.compression_sign, log.displacement_sign) == (1, 1)
    assert log.dialect["sign_from"] == "column name"


def test_compressive_names_with_negative_values_follow_the_data(tmp_path):
    """A template that names its channels 'Compressive ...' but writes Instron's negative values:
    the data decide the sign (the name alone would make the ramp a retreat), and say so."""
    p = tmp_path / "compressive_neg.csv"
    force = [0.0] * 5 + [-0.1 * k for k in range(1, 16)]
    p.write_text("Time,Compressive extension,Compressive load\n(s),(mm),(N)\n"
                 + "".join(f"{0.1 * k:.1f},{-0.01 * k:.2f},{fk:.2f}\n" for k, fk in enumerate(force)))
    log = read_machine_log(p)
    assert (log.compression_sign, log.displacement_sign) == (-1, -1)
    assert "named compressive" in log.dialect["sign_from"]
    disp, f = log.compression()
    assert disp[-1] > 0 and f[-1] > 0


@pytest.mark.parametrize("magic, kind", [(b"PK\x03\x04\x14\x00\x06\x00", ".xlsx"),
                                         (b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1\x00\x00", ".xls")])
def test_excel_workbook_is_named_not_decoded(tmp_path, magic, kind):
    p = tmp_path / f"log{kind}"
    p.write_bytes(magic + b"\x00" * 64 + b"xl/worksheets/sheet1.xml")
    with pytest.raises(InputError, match="Excel workbooks are not read: export the raw data as CSV from Bluehill") as e:
        read_machine_log(p)
    assert kind in str(e.value) and "utf-16" not in str(e.value)


def test_geometry_unit_inside_the_key_and_thickness(tmp_path):
    """``Specimen diameter (mm),18`` (the unit in the key) and ``Dimensions : Thickness``."""
    rows = "Time,Extension,Load\n(s),(mm),(N)\n0.0,0.0,0.0\n0.1,-0.1,-0.5\n"
    p = tmp_path / "unit_in_key.csv"
    p.write_text("Specimen diameter (mm),18\nSpecimen height [cm],1.2\n\n" + rows)
    assert read_machine_log(p).geometry == pytest.approx({"diameter_mm": 18.0, "height_mm": 12.0})
    q = tmp_path / "thickness.csv"
    q.write_text("Dimensions : Diameter,18,mm\nDimensions : Thickness,12,mm\n\n" + rows)
    assert read_machine_log(q).geometry == pytest.approx({"diameter_mm": 18.0, "thickness_mm": 12.0})


# ----------------------------------------------------------------- property: plain CSV

TIME_UNITS = ["s", "sec", "ms", "min"]
LENGTH_UNITS = ["mm", "m", "µm", "um", "in"]
FORCE_UNITS = ["N", "kN", "mN", "lbf", "gf", "kgf"]
finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(data=st.data(), n=st.integers(min_value=1, max_value=25),
       units=st.tuples(st.sampled_from(TIME_UNITS), st.sampled_from(LENGTH_UNITS),
                       st.sampled_from(FORCE_UNITS)),
       style=st.sampled_from(["snake", "paren", "bracket"]),
       dialect=st.sampled_from([(",", "."), (";", ","), ("\t", "."), (";", ".")]))
def test_plain_csv_round_trips(tmp_path_factory, data, n, units, style, dialect):
    """Random finite columns written with random units, name styles, separators and
    decimal marks come back exactly (repr round-trips a float), times the unit factor."""
    steps = data.draw(st.lists(st.floats(min_value=1e-3, max_value=1e3), min_size=n, max_size=n))
    time = np.cumsum(steps) - 5.0
    ext = np.array(data.draw(st.lists(finite, min_size=n, max_size=n)))
    load = np.array(data.draw(st.lists(finite, min_size=n, max_size=n)))
    names = ["time", "displacement", "force"]
    header = [{"snake": f"{a}_{u}", "paren": f"{a.title()} ({u})",
               "bracket": f"{a.title()} [{u}]"}[style] for a, u in zip(names, units)]
    sep, decimal = dialect
    fmt = (lambda v: repr(float(v)).replace(".", ",")) if decimal == "," else (lambda v: repr(float(v)))
    text = sep.join(header) + "\n" + "".join(
        sep.join(fmt(v) for v in row) + "\n" for row in zip(time, ext, load))
    path = tmp_path_factory.mktemp("rt") / "log.csv"
    path.write_text(text, encoding="utf-8")
    log = read_machine_log(path)
    assert log.layout == "plain-csv"
    np.testing.assert_array_equal(log.time_s, time * unit_factor(units[0], "time"))
    np.testing.assert_array_equal(log.extension_mm, ext * unit_factor(units[1], "length"))
    np.testing.assert_array_equal(log.load_n, load * unit_factor(units[2], "force"))


# ----------------------------------------------------------------- stress tables


def _table(tmp_path, text, name="table.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_stress_table_units_and_modes(tmp_path):
    p = _table(tmp_path, "stretch,nominal_stress_kpa,mode\n1.1,0.5,uniaxial\n1.2,1.0,pure shear\n"
                         "0.3,0.2,simple-shear\n1.05,2.5,Equibiaxial\n")
    df = read_stress_table(p)
    assert list(df.columns) == ["stretch", "nominal_stress_pa", "mode"]
    np.testing.assert_allclose(df["nominal_stress_pa"], [500.0, 1000.0, 200.0, 2500.0], rtol=1e-15)
    assert list(df["mode"]) == ["uniaxial", "pure-shear", "simple-shear", "equibiaxial"]
    assert df.attrs["lines"] == [2, 3, 4, 5]


def test_stress_table_mode_argument_and_european_dialect(tmp_path):
    p = _table(tmp_path, "# Treloar 1944, equibiaxial\nStretch;Nominal stress (MPa)\n1,02;0,0255\n"
                         "1,125;0,1344\n")
    df = read_stress_table(p, mode="ET")
    np.testing.assert_allclose(df["stretch"], [1.02, 1.125], rtol=1e-15)
    np.testing.assert_allclose(df["nominal_stress_pa"], [25500.0, 134400.0], rtol=1e-12)
    assert set(df["mode"]) == {"equibiaxial"}
    assert set(read_stress_table(p)["mode"]) == {"uniaxial"}


@pytest.mark.parametrize("text, line, words", [
    ("stretch,nominal_stress_pa\n1.1,abc\n", 2, "text 'abc'"),
    ("stretch,nominal_stress_pa\n1.1,10\n1.2,nan\n", 3, "NaN value"),
    ("stretch,nominal_stress_pa\n1.1,10\n-0.5,3\n", 3, "not positive"),
    ("stretch,nominal_stress_pa,mode\n1.1,10,torsion\n", 2, "unknown loading mode 'torsion'"),
    ("stretch,nominal_stress_psi\n1.1,10\n", 1, "unknown stress unit 'psi'"),
    ("stretch,nominal_stress_pa,nominal_stress_kpa\n1.1,10,0.01\n", 1, "two stress columns"),
    ("stretch,stress\n1.1,10\n", 1, "no nominal stress column"),
    ("lambda,nominal_stress_pa\n1.1,10\n", 1, "no 'stretch' column"),
    ("stretch,nominal_stress_pa\n", 2, "no data rows"),
    ("", 1, "empty"),
])
def test_stress_table_errors_name_file_and_line(tmp_path, text, line, words):
    p = _table(tmp_path, text, name="bad_table.csv")
    with pytest.raises(InputError) as info:
        read_stress_table(p)
    message = str(info.value)
    assert "bad_table.csv" in message and f"line {line}:" in message and words in message, message


def test_stress_table_simple_shear_allows_any_gamma(tmp_path):
    p = _table(tmp_path, "stretch,nominal_stress_pa\n-0.2,-40\n0.0,0\n0.2,40\n")
    df = read_stress_table(p, mode="simple-shear")
    np.testing.assert_array_equal(df["stretch"], [-0.2, 0.0, 0.2])
    with pytest.raises(InputError, match="unknown loading mode"):
        read_stress_table(p, mode="torsion")


def test_fixture_files_are_small():
    """Fixtures stay a few dozen rows (the real export is the one large file)."""
    for f in LOGS.glob("*.[ct]sv"):
        assert os.path.getsize(f) < 4000, f


def test_a_compression_table_written_positive_is_turned_and_said(tmp_path):
    """Stress positive in compression (stretch < 1) had been fitted as written: mu = 0 Pa and
    exit 0; the sign is the laws' now, and the modes turned are named."""
    from bsipipe.mechanics.hyperelastic import ogden_nominal_stress
    lam = np.linspace(1.0, 0.7, 16)
    p_true = ogden_nominal_stress(lam, [720.0], [-4.7])               # negative in compression
    text = "stretch,nominal_stress_pa\n" + "".join(f"{a:.4f},{-b:.6f}\n" for a, b in zip(lam, p_true))
    t = read_stress_table(_table(tmp_path, text))
    np.testing.assert_allclose(t["nominal_stress_pa"], p_true, atol=1e-6)
    assert t.attrs["sign_turned"] == ["uniaxial"]
    mixed = "stretch,nominal_stress_pa\n1.0,0\n0.9,-5\n1.1,-3\n"       # rows disagree: left as written
    mixed_t = read_stress_table(_table(tmp_path, mixed, "mixed.csv"))
    assert mixed_t.attrs["sign_turned"] == [] and mixed_t.attrs["magnitudes"] == []
    # tension and compression written as magnitudes (every stress positive): had been fitted as
    # written, mu 123 Pa, alpha +8.8, exit 0; the compression rows take the laws' sign
    lam2 = np.r_[np.linspace(0.7, 1.0, 16), np.linspace(1.02, 1.3, 15)]
    p2 = ogden_nominal_stress(lam2, [720.0], [-4.7])
    text2 = "stretch,nominal_stress_pa\n" + "".join(f"{a:.4f},{abs(b):.6f}\n" for a, b in zip(lam2, p2))
    t2 = read_stress_table(_table(tmp_path, text2, "magnitudes.csv"))
    np.testing.assert_allclose(t2["nominal_stress_pa"], p2, atol=1e-6)
    assert t2.attrs["sign_turned"] == [] and t2.attrs["magnitudes"] == ["uniaxial"]


def test_results_table_of_two_specimens_leaves_a_differing_dimension_unknown(tmp_path):
    """A Bluehill 3 export whose results table lists two specimens: the first row's diameter
    had been taken for the log without a word.  Where the rows agree (height 12 mm) the
    dimension stands; where they differ (18 and 20 mm) it is unknown, and fit-ogden without
    --diameter-mm says so naming the line (exit 2); with the option the log fits.  A log that
    states its specimen's label takes the table's row of that label."""
    text = (LOGS / "bluehill3_results_table.csv").read_text()
    two = text.replace('"1","brain 2","18.00","12.00","0.00166"\n',
                       '"1","brain 2","18.00","12.00","0.00166"\n"2","brain 3","20.00","12.00","0.00170"\n')
    assert two != text
    p = tmp_path / "two.csv"
    p.write_text(two)
    log = read_machine_log(p)
    assert log.geometry["height_mm"] == pytest.approx(12.0) and "diameter_mm" not in log.geometry
    why, line = log.geometry_invalid["diameter_mm"]
    assert "18 and 20 mm" in why and line == 5
    one = read_machine_log(LOGS / "bluehill3_results_table.csv")
    assert one.geometry["diameter_mm"] == pytest.approx(18.0) and not one.geometry_invalid
    # the log stating its own specimen's label (Bluehill's "Text Inputs : Specimen label"):
    # the results table's row of that label is the log's, whichever row it is
    for label, d in (("brain 3", 20.0), ("brain 2", 18.0)):
        p2 = tmp_path / f"labelled_{d:g}.csv"
        p2.write_text(f'"Text Inputs : Specimen label","{label}"\n\n' + two)
        lab = read_machine_log(p2)
        assert lab.geometry["diameter_mm"] == pytest.approx(d) and not lab.geometry_invalid, lab.geometry_invalid
        assert lab.geometry["height_mm"] == pytest.approx(12.0)
    p3 = tmp_path / "other_label.csv"
    p3.write_text('"Text Inputs : Specimen label","brain 9"\n\n' + two)       # no such row: still unknown
    assert "diameter_mm" in read_machine_log(p3).geometry_invalid

    from click.testing import CliRunner

    from bsipipe.cli import cli
    r = CliRunner().invoke(cli, ["fit-ogden", str(p), "-o", str(tmp_path / "out"), "--bootstrap", "0"])
    assert r.exit_code == 2 and "18 and 20 mm" in r.output and "line 5" in r.output and "--diameter-mm" in r.output
    r = CliRunner().invoke(cli, ["fit-ogden", str(p), "--diameter-mm", "18", "-o", str(tmp_path / "out"),
                                 "--bootstrap", "0", "--no-loop"])
    assert r.exit_code == 0, r.output


def test_a_tension_record_is_refused_naming_its_peak_line(tmp_path):
    """Channels named tensile whose load rises: the specimen was pulled.  It had been fitted
    as a compression (the data's sign taken for compression's).  It is now exit 2 naming the
    most loaded line; the same channels falling (Instron's compression negative) read as a
    compression test."""
    t = np.arange(60) * 0.1
    x = np.where(t < 1.0, 0.0, 0.12 * (t - 1.0))
    f = np.where(t < 1.0, 0.0, 0.05 * (t - 1.0) ** 2) + 1e-4 * np.cos(7 * t)
    for sign in (1, -1):
        p = tmp_path / f"tensile{sign}.csv"
        rows = "".join(f"{a:.2f},{sign * b:.4f},{sign * c:.5f}\n" for a, b, c in zip(t, x, f))
        p.write_text("Time (s),Tensile extension (mm),Tensile load (N)\n" + rows)
        if sign == 1:
            with pytest.raises(InputError, match=r"tension test") as e:
                read_machine_log(p)
            assert e.value.line == 2 + int(np.argmax(f)) and "Tensile load" in str(e.value)
        else:
            log = read_machine_log(p)
            u, force = log.compression()
            assert log.compression_sign == -1 and force.max() == pytest.approx(f.max(), rel=1e-3) and u.max() > 0


def test_specimens_side_by_side_are_one_record_per_file(tmp_path):
    """A Bluehill export of two specimens side by side (Time, Extension, Load twice): the first
    match of each channel had fitted specimen 1 and dropped specimen 2 without a word.  It is
    exit 2 naming the header's line and the columns; one channel named twice (a load and a
    compressive load) is not several specimens."""
    rows = "\n".join(f"{0.1 * k:.1f},{-0.01 * k:.3f},{-0.001 * k:.4f},{0.1 * k:.1f},{-0.01 * k:.3f},"
                     f"{-0.002 * k:.4f}" for k in range(30))
    p = tmp_path / "side.csv"
    p.write_text("Specimen 1,,,Specimen 2,,\nTime,Extension,Load,Time,Extension,Load\n(s),(mm),(N),(s),(mm),(N)\n"
                 + rows + "\n")
    with pytest.raises(InputError) as e:
        read_machine_log(p)
    assert e.value.line == 2 and "2 specimens side by side" in str(e.value)
    assert "load in columns 3, 6" in str(e.value)
    q = tmp_path / "two_loads.csv"
    q.write_text("Time,Extension,Load,Load\n(s),(mm),(N),(N)\n" + "\n".join(
        f"{0.1 * k:.1f},{-0.01 * k:.3f},{-0.001 * k:.4f},{-0.001 * k:.4f}" for k in range(30)) + "\n")
    assert len(read_machine_log(q)) == 30


def test_a_stress_strain_export_is_named_as_such(tmp_path):
    """A Bluehill export of time, strain and stress only: the message had quoted its units row
    '(s),(mm/mm),(MPa)' at line 2 as "the header"; it names the header's stress and strain
    columns at line 1."""
    p = tmp_path / "ss.csv"
    p.write_text("Time,Compressive strain,Compressive stress\n(s),(mm/mm),(MPa)\n"
                 + "".join(f"{0.01 * k:.2f},{0.001 * k:.4f},{1e-6 * k:.3g}\n" for k in range(30)))
    with pytest.raises(InputError) as e:
        read_machine_log(p)
    assert e.value.line == 1 and "'Compressive strain', 'Compressive stress'" in str(e.value)
    assert "--stress-stretch" in str(e.value)


def test_a_bluehill2_export_in_minutes_is_bluehill2(tmp_path):
    """The layout had been told by the time unit alone: a Bluehill 2 file with "(min)" read as
    Bluehill 3.  Its times are read in minutes."""
    from bsipipe.synth.machine_log import synth_compression_log, write_bluehill2
    frame, _ = synth_compression_log(seed=2)
    frame["time_s"] = frame["time_s"] / 60.0
    p = write_bluehill2(frame, tmp_path / "min.csv")
    p.write_text(p.read_text().replace("(sec)", "(min)"))
    ml = read_machine_log(p)
    assert ml.layout == "bluehill2"
    assert ml.time_s[-1] == pytest.approx(60.0 * frame["time_s"].iloc[-1], rel=1e-6)


@pytest.mark.parametrize("how", ["bluehill2", "bluehill3", "names-row"])
def test_two_exports_joined_in_one_file_are_named(tmp_path, how):
    """Two Bluehill exports joined: the second's metadata had read as "the row has 2 fields ...
    the line looks truncated", or its names row as text in a number column.  The message now
    says a second record starts there (exit 2 at its line either way)."""
    from bsipipe.synth.machine_log import synth_compression_log, write_bluehill2, write_bluehill3
    frame, _ = synth_compression_log(seed=4)
    writer = write_bluehill3 if how == "bluehill3" else write_bluehill2
    a = writer(frame, tmp_path / "a.csv").read_text()
    if how == "names-row":
        lines = a.splitlines()
        k = next(i for i, ln in enumerate(lines) if ln.startswith("Time"))
        joined = a + "\n".join(lines[k:]) + "\n"
    else:
        joined = a + a
    p = tmp_path / "joined.csv"
    p.write_text(joined)
    with pytest.raises(InputError, match=r"a second record starts inside the data"):
        read_machine_log(p)
