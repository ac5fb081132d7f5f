"""Property-based tests (hypothesis; issue 7, item 2): parsers, geometry and mechanics.

Every property is an identity that holds exactly (or to the stated numerical tolerance) for
any input in its domain, so hypothesis searches the domain for a counterexample:

* parsers: machine logs written in the plain-CSV, Bluehill 2, Bluehill 3 and European
  layouts read back to the values written; stress tables in Pa, kPa and MPa with modes;
  3D Slicer ``.fcsv`` / ``.mrk.json`` point lists in LPS and RAS;
* geometry: a random similarity transform is recovered from its points; random points
  seen by two random C-arms are triangulated back; OpenCV distortion and its inverse round
  trip over physically sensible coefficients;
* mechanics: the Ogden nominal stress of every law and mode is the derivative of the
  strain energy along the mode's deformation; the QLV response to a held input is the input
  times G(t), and it is linear in the input.

``max_examples`` is bounded per test (the whole file runs in well under a minute) and
``derandomize=True`` keeps the suite deterministic; ``BSIPIPE_HYPOTHESIS=search`` runs a
ten times longer randomised search.
"""

from __future__ import annotations

import os
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

#: Examples per property; ``BSIPIPE_HYPOTHESIS=search`` runs ten times as many, not derandomised.
N_PARSER, N_GEOMETRY, N_MECHANICS = 60, 80, 100
_SEARCH = os.environ.get("BSIPIPE_HYPOTHESIS") == "search"


def examples(n: int):
    return settings(max_examples=n * (10 if _SEARCH else 1), derandomize=not _SEARCH, deadline=None,
                    print_blob=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much,
                                                            HealthCheck.function_scoped_fixture])


# --------------------------------------------------------------------------- strategies

#: Finite numbers of any sign from 1e-12 to 1e7 in magnitude, and zero (a record's numbers;
#: near the bottom of the double range, v / 1000 would be subnormal and lose digits).
finite = st.one_of(st.just(0.0), st.floats(min_value=1e-12, max_value=1e7).flatmap(lambda v: st.sampled_from([-v, v])))


@st.composite
def machine_records(draw, min_size=3, max_size=40):
    """(time_s strictly increasing, extension_mm, load_n), each finite."""
    n = draw(st.integers(min_size, max_size))
    # steps of at least a microsecond: a unit conversion (x 0.001) must not merge two samples
    t0 = draw(st.floats(min_value=0.0, max_value=1e3))
    steps = draw(st.lists(st.floats(min_value=1e-6, max_value=1e3), min_size=n - 1, max_size=n - 1))
    ext = draw(st.lists(finite, min_size=n, max_size=n))
    load = draw(st.lists(finite, min_size=n, max_size=n))
    return t0 + np.concatenate([[0.0], np.cumsum(steps)]), np.array(ext), np.array(load)


def _rows(*cols):
    """Rows of Python floats (``repr`` gives the shortest text that reads back to the same double)."""
    return zip(*(np.asarray(c, float).tolist() for c in cols))


def _write(path, lines, newline="\n", encoding="utf-8"):
    path.write_bytes((newline.join(lines) + newline).encode(encoding))
    return path


def _plain(path, t, x, f):
    return _write(path, ["time_s,extension_mm,load_n"] + [f"{a!r},{b!r},{c!r}" for a, b, c in _rows(t, x, f)])


def _bluehill2(path, t, x, f):
    head = ["Text Inputs : Specimen label,prop", "Specimen : Diameter,18.0,mm", "", "Time,Extension,Load,Segment ID",
            "(sec),(mm),(N),"]
    return _write(path, head + [f"{a!r},{b!r},{c!r},1" for a, b, c in _rows(t, x, f)], newline="\r\n")


def _bluehill3(path, t, x, f):
    q = lambda v: f'"{v!r}"'   # noqa: E731
    head = ['"Results Table 1"', '"Specimen label","Height"', '"","(mm)"', '"prop","12.0"', "", '"Raw Data"',
            '"Time","Extension","Load"', '"(s)","(mm)","(N)"']
    return _write(path, head + [",".join(q(v) for v in r) for r in _rows(t, x, f)])


def _european(path, t, x, f):
    c = lambda v: repr(v).replace(".", ",")   # noqa: E731
    head = ["Text Inputs : Specimen label;Hirn", "", "Time;Extension;Load", "(s);(mm);(N)"]
    return _write(path, head + [f"{c(a)};{c(b)};{c(cc)}" for a, b, cc in _rows(t, x, f)], newline="\r\n")


def _scaled(path, t, x, f):
    """ms, µm and kN in the names: the reader converts back (to within rounding of the scaling)."""
    return _write(path, ["Time (ms),Displacement (µm),Force [kN]"]
                  + [f"{a * 1e3!r},{b * 1e3!r},{c / 1e3!r}" for a, b, c in _rows(t, x, f)])


LAYOUTS = {"plain-csv": _plain, "bluehill2": _bluehill2, "bluehill3": _bluehill3, "european": _european}


# --------------------------------------------------------------------------- parsers


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@examples(N_PARSER)
@given(rec=machine_records())
def test_machine_log_round_trip(tmp_path, layout, rec):
    from bsipipe.io.machine_log import read_machine_log

    t, x, f = rec
    m = read_machine_log(LAYOUTS[layout](tmp_path / f"{layout}.csv", t, x, f))
    assert m.layout == {"european": "bluehill3"}.get(layout, layout)
    np.testing.assert_array_equal(m.time_s, t)
    np.testing.assert_array_equal(m.extension_mm, x)
    np.testing.assert_array_equal(m.load_n, f)
    assert m.compression_sign in (-1, 1) and m.displacement_sign in (-1, 1)
    d, force = m.compression()
    np.testing.assert_array_equal(force, m.compression_sign * f)
    assert d[0] == 0.0


@examples(N_PARSER)
@given(rec=machine_records())
def test_machine_log_units_converted(tmp_path, rec):
    from bsipipe.io.machine_log import read_machine_log

    t, x, f = rec
    m = read_machine_log(_scaled(tmp_path / "scaled.csv", t, x, f))
    # written as v * s and read back as (v * s) / s: two roundings, each half an ulp
    for got, want in ((m.time_s, t), (m.extension_mm, x), (m.load_n, f)):
        np.testing.assert_allclose(got, want, rtol=4e-16 * 2, atol=0)


@examples(N_PARSER)
# stretches from 0.1 (below it a stretch column holds strains: exit 2, tests/test_bad_input_matrix.py)
@given(stretch=st.lists(st.floats(min_value=0.1, max_value=10.0, allow_subnormal=False), min_size=1, max_size=30),
       data=st.data(), unit=st.sampled_from([("pa", 1.0), ("kpa", 1e3), ("mpa", 1e6)]), with_mode=st.booleans())
def test_stress_table_round_trip(tmp_path, stretch, data, unit, with_mode):
    from bsipipe.io.stress_table import read_stress_table
    from bsipipe.mechanics.hyperelastic import MODES

    n = len(stretch)
    stress = data.draw(st.lists(finite, min_size=n, max_size=n))
    modes = data.draw(st.lists(st.sampled_from(MODES), min_size=n, max_size=n))
    # stresses with the laws' sign (that of the strain: a table written the other way round is
    # turned, test_io_machine_log.py::test_a_compression_table_written_positive_is_turned_and_said)
    row_modes = modes if with_mode else ["pure-shear"] * n
    stress = [abs(b) * (np.sign(a - (0.0 if m == "simple-shear" else 1.0)) or 1.0)
              for a, b, m in zip(stretch, stress, row_modes)]
    name, factor = unit
    head = f"stretch,nominal_stress_{name}" + (",mode" if with_mode else "")
    rows = [f"{a!r},{b!r}" + (f",{m}" if with_mode else "") for (a, b), m in zip(_rows(stretch, stress), modes)]
    (tmp_path / "t.csv").write_text("# a comment line\n" + head + "\n" + "\n".join(rows) + "\n")
    df = read_stress_table(tmp_path / "t.csv", None if with_mode else "pure-shear")
    np.testing.assert_array_equal(df["stretch"].to_numpy(), stretch)
    np.testing.assert_allclose(df["nominal_stress_pa"].to_numpy(), np.array(stress) * factor, rtol=0, atol=0)
    assert list(df["mode"]) == (modes if with_mode else ["pure-shear"] * n)
    assert df.attrs["lines"] == list(range(3, 3 + n))


label_text = st.text(alphabet=string.ascii_letters + string.digits + "_-.:()[]/+ ", min_size=1, max_size=12).map(
    str.strip).filter(bool)


@st.composite
def markups(draw):
    n = draw(st.integers(1, 12))
    labels = draw(st.lists(label_text, min_size=n, max_size=n, unique=True))
    pts = np.array(draw(st.lists(st.tuples(finite, finite, finite), min_size=n, max_size=n)), float).reshape(n, 3)
    return labels, pts, draw(st.sampled_from(["LPS", "RAS"]))


@pytest.mark.parametrize("fmt", ["fcsv", "mrk.json"])
@examples(N_PARSER)
@given(m=markups())
def test_slicer_markups_round_trip(tmp_path, fmt, m):
    from bsipipe.io.slicer import format_fcsv, format_mrk_json, read_markups

    labels, pts, system = m
    text = format_fcsv(labels, pts, system) if fmt == "fcsv" else format_mrk_json(labels, pts, system)
    path = tmp_path / f"points.{fmt}"
    path.write_text(text)
    got = read_markups(path)
    assert got.names == labels
    assert got.coordinate_system == system
    np.testing.assert_array_equal(got.positions_mm, pts)
    other = "RAS" if system == "LPS" else "LPS"
    flipped = got.to(other)
    np.testing.assert_array_equal(flipped.positions_mm, pts * [-1.0, -1.0, 1.0])
    np.testing.assert_array_equal(flipped.to(system).positions_mm, pts)


# --------------------------------------------------------------------------- geometry


@st.composite
def similarity(draw, with_scale=True):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(3, 12))
    x = rng.normal(0.0, 30.0, (n, 3)) + rng.uniform(-200, 200, 3)
    # not collinear: the second singular value of the centred points at least 5 % of the first
    sv = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    assume(sv[1] > 0.05 * sv[0])
    R = Rotation.random(random_state=seed).as_matrix()
    t = rng.uniform(-500, 500, 3)
    s = draw(st.floats(0.5, 2.0)) if with_scale else 1.0
    return x, R, t, s


@examples(N_GEOMETRY)
@given(case=similarity(), scale=st.booleans())
def test_registration_recovers_random_transforms(case, scale):
    from bsipipe.geometry.registration import fit_similarity

    x, R, t, s = case
    if not scale:
        s = 1.0
    y = s * x @ R.T + t
    T = fit_similarity(x, y, scale=scale)
    np.testing.assert_allclose(T.R, R, atol=1e-9)
    assert abs(np.linalg.det(T.R) - 1.0) < 1e-12
    assert T.scale == pytest.approx(s, rel=1e-10)
    np.testing.assert_allclose(T.t_mm, t, atol=1e-7 * (1 + np.abs(x).max()))
    np.testing.assert_allclose(T.apply(x), y, atol=1e-8 * (1 + np.abs(y).max()))
    # the inverse maps back
    np.testing.assert_allclose(T.inverse().apply(y), x, atol=1e-8 * (1 + np.abs(x).max()))


def _c_arm(rng, source_mm, K_scale, dist):
    from bsipipe.imaging.camera import Camera, look_at
    R, t = look_at(source_mm, np.zeros(3))
    f = K_scale
    K = np.array([[f, 0, 512.0 + rng.uniform(-20, 20)], [0, f * rng.uniform(0.98, 1.02), 512.0 + rng.uniform(-20, 20)],
                  [0, 0, 1]])
    return Camera(K, dist, R, t, (1024, 1024))


@st.composite
def two_c_arms(draw):
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    angle = np.radians(draw(st.floats(30.0, 150.0)))
    dist_a, dist_b = (draw(st.floats(500.0, 1200.0)) for _ in range(2))
    tilt = rng.uniform(-0.3, 0.3, 2)
    a = dist_a * np.array([np.cos(tilt[0]), 0.0, np.sin(tilt[0])])
    b = dist_b * np.array([np.cos(angle) * np.cos(tilt[1]), np.sin(angle) * np.cos(tilt[1]), np.sin(tilt[1])])
    k = [draw(st.floats(-0.2, 0.2)), draw(st.floats(-0.05, 0.05)), draw(st.floats(-2e-3, 2e-3)),
         draw(st.floats(-2e-3, 2e-3)), 0.0]
    kb = [draw(st.floats(-0.2, 0.2)), draw(st.floats(-0.05, 0.05)), draw(st.floats(-2e-3, 2e-3)),
          draw(st.floats(-2e-3, 2e-3)), 0.0]
    cams = {"A": _c_arm(rng, a, rng.uniform(1500, 3000), k), "B": _c_arm(rng, b, rng.uniform(1500, 3000), kb)}
    X = rng.uniform(-40.0, 40.0, (draw(st.integers(1, 20)), 3))
    return cams, X


@examples(N_GEOMETRY)
@given(case=two_c_arms())
def test_triangulation_recovers_random_points(case):
    from bsipipe.imaging.triangulate import triangulate, views_from_cameras

    cams, X = case
    views = views_from_cameras(cams)
    ua, ub = cams["A"].project(X), cams["B"].project(X)
    res = triangulate((views["A"], views["B"]), ua, ub)
    np.testing.assert_allclose(res["X_mm"], X, atol=1e-6)
    assert np.all(res["ray_gap_mm"] < 1e-6)
    assert np.all(res["reproj_rms_px"] < 1e-6)


@st.composite
def opencv_camera(draw):
    """A C-arm/optical camera with OpenCV coefficients of the sizes calibration finds in practice."""
    from bsipipe.imaging.camera import Camera

    n = draw(st.sampled_from([4, 5, 8, 12]))
    d = [draw(st.floats(-0.3, 0.3)), draw(st.floats(-0.1, 0.1)), draw(st.floats(-5e-3, 5e-3)),
         draw(st.floats(-5e-3, 5e-3))]
    if n >= 5:
        d.append(draw(st.floats(-0.05, 0.05)))
    if n >= 8:
        d += [draw(st.floats(-0.05, 0.05)), draw(st.floats(-0.02, 0.02)), draw(st.floats(-0.01, 0.01))]
    if n == 12:
        d += [draw(st.floats(-2e-3, 2e-3)) for _ in range(4)]
    w, h = draw(st.sampled_from([(640, 480), (1024, 1024), (1920, 1080)]))
    f = draw(st.floats(1.2, 3.0)) * max(w, h) / 2   # half field of view ~ 18-40 degrees
    K = np.array([[f, 0, w / 2 + draw(st.floats(-20, 20))], [0, f * draw(st.floats(0.98, 1.02)), h / 2], [0, 0, 1]])
    cam = Camera(K, d, np.eye(3), np.zeros(3), (w, h))
    # the model must be a one-to-one map over the image: monotonic in the radius out to the
    # corners, and reaching past them, so that every raw pixel has an ideal one (a barrel
    # model can top out inside the image: k2 = -0.094 at f = 400 px on 640 x 480 maps no ideal
    # radius to the corners' raw one, and undistorting them has no answer)
    corner = np.hypot(w, h) / 2 / f
    r = np.linspace(0.0, 2.0 * corner, 400)
    xy = np.column_stack([r, np.zeros_like(r)])
    from bsipipe.imaging.camera import opencv_distort
    rd = opencv_distort(xy, d)[:, 0]
    reach = np.flatnonzero(rd >= 1.05 * corner)
    assume(len(reach) > 0)
    upto = max(int(reach[0]), int(np.searchsorted(r, 1.05 * corner)))
    assume(np.all(np.diff(rd[:upto + 1]) > 0))
    return cam


@examples(N_GEOMETRY)
@given(cam=opencv_camera(), seed=st.integers(0, 2**32 - 1))
def test_distort_undistort_round_trip(cam, seed):
    rng = np.random.default_rng(seed)
    w, h = cam.image_size
    u = rng.uniform([0, 0], [w - 1, h - 1], (50, 2))
    u = np.vstack([u, [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [cam.cx, cam.cy]]])
    np.testing.assert_allclose(cam.distort_pixels(cam.undistort_pixels(u)), u, atol=1e-7)
    np.testing.assert_allclose(cam.undistort_pixels(cam.distort_pixels(u)), u, atol=1e-7)


@examples(N_GEOMETRY)
@given(cam=opencv_camera(), seed=st.integers(0, 2**32 - 1))
def test_camera_distortion_matches_opencv(cam, seed):
    import cv2

    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-0.4, 0.4, (30, 2)), np.ones(30)]) * rng.uniform(100, 1000)
    mine = cam.project_opencv(X)
    ref = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(mine, ref, atol=1e-6)


# --------------------------------------------------------------------------- mechanics


def _principal(mode: str, s: float) -> np.ndarray:
    """Principal stretches along each mode's deformation path (s = stretch, or gamma in simple shear)."""
    if mode == "uniaxial":
        return np.array([s, s ** -0.5, s ** -0.5])
    if mode == "equibiaxial":
        return np.array([s, s, s ** -2.0])
    if mode == "pure-shear":
        return np.array([s, 1.0, 1.0 / s])
    lam = s / 2.0 + np.sqrt(1.0 + s * s / 4.0)
    return np.array([lam, 1.0 / lam, 1.0])


#: Loaded directions that share the work: P = (1 / n) dW/ds.
_LOADED = {"uniaxial": 1, "equibiaxial": 2, "pure-shear": 1, "simple-shear": 1}


@st.composite
def ogden_terms(draw):
    n = draw(st.integers(1, 3))
    mus = [draw(st.floats(1.0, 1e4)) * draw(st.sampled_from([-1.0, 1.0])) for _ in range(n)]
    alphas = [draw(st.floats(0.2, 25.0)) * draw(st.sampled_from([-1.0, 1.0])) for _ in range(n)]
    return mus, alphas


@pytest.mark.parametrize("mode", ["uniaxial", "equibiaxial", "pure-shear", "simple-shear"])
@examples(N_MECHANICS)
@given(terms=ogden_terms(), s=st.floats(0.6, 1.6))
def test_ogden_stress_is_the_energy_derivative(mode, terms, s):
    from bsipipe.mechanics.hyperelastic import ogden_energy, ogden_nominal_stress

    mus, alphas = terms
    if mode == "simple-shear":
        s = s - 1.1   # gamma in [-0.5, 0.5]
    h = 1e-5
    # fourth-order central difference: error ~ h^4 W'''''; well below the tolerance here
    W = lambda v: float(ogden_energy(_principal(mode, v), mus, alphas))   # noqa: E731
    dW = (-W(s + 2 * h) + 8 * W(s + h) - 8 * W(s - h) + W(s - 2 * h)) / (12 * h)
    P = float(ogden_nominal_stress(np.array([s]), mus, alphas, mode)[0])
    # scale: the size of the individual terms (they may cancel)
    lam = _principal(mode, s)
    scale = sum(abs(2 * m / a) * np.sum(lam ** a + lam ** -abs(a)) for m, a in zip(mus, alphas))
    assert P == pytest.approx(dW / _LOADED[mode], abs=1e-7 * scale)


@pytest.mark.parametrize("law", ["ogden", "ogden2", "ogden3", "neo-hookean", "mooney-rivlin"])
@examples(N_MECHANICS // 2)
@given(data=st.data(), s=st.floats(0.6, 1.6))
def test_every_law_is_its_ogden_series(law, data, s):
    from bsipipe.mechanics.hyperelastic import get_law, ogden_energy

    L = get_law(law)
    p = []
    for name in L.param_names:
        p.append(data.draw(st.floats(1.0, 1e4)) if name.endswith("_pa") else
                 data.draw(st.floats(0.2, 25.0)) * data.draw(st.sampled_from([-1.0, 1.0])))
    mus, alphas = L.ogden_terms(p)
    if law == "neo-hookean":   # W = mu/2 (I1 - 3)
        lam = _principal("uniaxial", s)
        assert float(ogden_energy(lam, mus, alphas)) == pytest.approx(p[0] / 2 * (np.sum(lam ** 2) - 3), rel=1e-12,
                                                                      abs=1e-9)
    if law == "mooney-rivlin":   # W = C10 (I1 - 3) + C01 (I2 - 3)
        lam = _principal("uniaxial", s)
        I1, I2 = np.sum(lam ** 2), np.sum(lam ** -2.0)
        assert float(ogden_energy(lam, mus, alphas)) == pytest.approx(p[0] * (I1 - 3) + p[1] * (I2 - 3), rel=1e-12,
                                                                      abs=1e-9)
    # small-strain limit: the initial shear modulus is the sum of the mu_i
    g = 1e-6
    # (error ~ alpha^2 g^2 from the neglected terms, ~ eps / g from rounding: both below 1e-8)
    assert float(L.nominal_stress(np.array([g]), p, "simple-shear")[0]) / g == pytest.approx(L.shear_modulus(p),
                                                                                            rel=1e-7)


@st.composite
def prony(draw):
    n = draw(st.integers(1, 3))
    g = np.array([draw(st.floats(0.0, 1.0)) for _ in range(n)])
    g = 0.95 * g / max(1.0, g.sum())
    tau = np.array([draw(st.floats(1e-3, 1e3)) for _ in range(n)])
    return g, tau


@st.composite
def time_grids(draw):
    """Non-decreasing times: any spacing, repeated stamps allowed."""
    n = draw(st.integers(1, 60))
    steps = draw(st.lists(st.one_of(st.just(0.0), st.floats(1e-4, 50.0)), min_size=n - 1, max_size=n - 1))
    t0 = draw(st.floats(-100.0, 100.0))
    return t0 + np.concatenate([[0.0], np.cumsum(steps)])


@examples(N_MECHANICS)
@given(p=prony(), t=time_grids(), c=st.one_of(st.just(0.0), st.floats(1e-6, 1e4).flatmap(
    lambda v: st.sampled_from([-v, v]))))
def test_qlv_held_input_relaxes_along_G(p, t, c):
    from bsipipe.mechanics.viscoelastic import qlv_response, relaxation_function

    g, tau = p
    out = qlv_response(t, np.full(len(t), c), g, tau)
    np.testing.assert_allclose(out, c * relaxation_function(t - t[0], g, tau), rtol=1e-12, atol=1e-12 * abs(c))


@examples(N_MECHANICS)
@given(p=prony(), t=time_grids(), data=st.data(), a=st.floats(-10, 10), b=st.floats(-10, 10))
def test_qlv_is_linear_in_the_input(p, t, data, a, b):
    from bsipipe.mechanics.viscoelastic import qlv_response

    g, tau = p
    n = len(t)
    e1 = np.array(data.draw(st.lists(st.floats(-1e3, 1e3), min_size=n, max_size=n)))
    e2 = np.array(data.draw(st.lists(st.floats(-1e3, 1e3), min_size=n, max_size=n)))
    lhs = qlv_response(t, a * e1 + b * e2, g, tau)
    rhs = a * qlv_response(t, e1, g, tau) + b * qlv_response(t, e2, g, tau)
    scale = (abs(a) + abs(b)) * 1e3 * max(1, n)
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-12 * scale)
    # no relaxation: the elastic response itself
    np.testing.assert_array_equal(qlv_response(t, e1, np.zeros_like(g), tau), e1)
