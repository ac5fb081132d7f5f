"""``bsipipe register`` on a CT read without its gantry tilt (the ``ct-gantry-shear`` effect).

A head CT acquired with the gantry tilted (10-25 degrees, to spare the eyes) and read without
DICOM's GantryDetectorTilt has its slices stacked without their in-plane shift: every CT
position is sheared, y (or x) off by tan(tilt) times its z.  On the square of four references
of ``tests/test_register_checks.py`` (CT and tracking noise 0.005 mm, five implanted markers
1.5-7.5 mm below the references), sheared about the CT origin's z, the loop had kept nothing:
5 degrees left FRE 0.31 mm, the implanted markers 0.43 mm RMS off and markers_ct.csv's
positions up to 0.75 mm from where the sheared CT has them, no warning; 10 degrees FRE 0.62,
implanted 0.87 mm RMS, positions 1.52 mm; 20 degrees 1.30, 1.80 and 3.17 mm, with only
``large-fre``.  The loop's ``ct-gantry-shear`` effect now finds the shear (y by z, or x by z)
and maps into the CT file's own (sheared) frame, where a mesh made from that CT lies.

Tolerances (measured on seeds 0-2 at 5-25 degrees, y and x): the tilt within 0.11 degrees of
the truth (its stated standard error 0.03-0.07), FRE 0.003-0.008 mm, implanted markers
0.006-0.020 mm RMS, markers_ct.csv positions within 0.027 mm of the sheared truth.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from bsipipe.geometry.registration import (ShearedSimilarity, Similarity, factor_se, fit_sheared, fit_similarity,
                                           registration_transform, shear_lever, tre_linearized)
from bsipipe.geometry.registration_effects import SHEAR_SE_MAX, RegistrationSpec, close_registration_loop
from test_register_checks import IMPLANTED, NOISE_MM, T_TRUE, _codes, _register, _trial
from test_register_ct_scale import ORIGIN, _flat_trial, _stretched
from test_registration import _trial as _loop_trial


def _shear(p, k, axis):
    """Positions ``p`` of a correct CT as a reader without the gantry tilt has them: ``axis``
    (0 x, 1 y) off by ``k`` times z from the CT origin's."""
    p = np.array(p, float)
    out = p.copy()
    out[..., axis] += k * (p[..., 2] - ORIGIN[2])
    return out


def _sheared(k, axis):
    def edit(ct):
        for n in ct:
            ct[n] = _shear(ct[n], k, axis)
    return edit


def _steps(res):
    return [s["effect"] for s in res["loop"]["steps"]]


def _tried(res, effect):
    return [c for rnd in res["loop"]["tried"] for c in rnd if c["effect"] == effect]


@pytest.mark.parametrize("deg, axis", [(10.0, 1), (20.0, 1), (15.0, 0)])
def test_a_ct_read_without_its_gantry_tilt_is_found_and_mapped_into(tmp_path, deg, axis):
    k = math.tan(math.radians(deg))
    _trial(tmp_path, ct_edit=_sheared(k, axis))
    r, res = _register(tmp_path)
    assert r.exit_code == 0, r.output
    assert _steps(res) == ["ct-gantry-shear"] and res["ct_axis_scale"] is None
    assert not any(c["passes"] for c in _tried(res, "ct-axis-scale"))
    sh = res["ct_gantry_shear"]
    assert sh["axis"] == "xyz"[axis] and sh["by"] == "z" and sh["axis_index"] == axis
    assert sh["tilt_deg"] == pytest.approx(deg, abs=0.2)
    assert sh["factor"] == pytest.approx(math.tan(math.radians(sh["tilt_deg"])))
    assert 0 < sh["factor_se"] < 0.002 and abs(sh["factor"] - k) < 4 * sh["factor_se"]
    assert "ct-gantry-shear" in _codes(res) and not {"large-fre", "ct-check"} & set(_codes(res))
    # FRE and the implanted markers at the noise, not 0.6-1.3 and 0.9-2.0 mm
    assert res["fre_rms_mm"] < 2 * math.sqrt(3) * NOISE_MM and res["ct_check_rms_mm"] < 0.03
    # matrix is the whole map into the sheared file: the implanted markers where that CT has them
    M = np.array(res["matrix"])
    err = np.linalg.norm(IMPLANTED @ M[:3, :3].T + M[:3, 3] - _shear(T_TRUE.apply(IMPLANTED), k, axis), axis=1)
    assert err.max() < 0.03
    # markers_ct.csv in the CT file's (sheared) frame: every row where the sheared truth has it
    mct = pd.read_csv(tmp_path / "out" / "markers_ct.csv")
    m = mct.merge(pd.read_csv(tmp_path / "markers3d.csv"), on=["frame", "marker"], suffixes=("", "_xray"))
    truth = _shear(T_TRUE.apply(m[["x_mm_xray", "y_mm_xray", "z_mm_xray"]].to_numpy()), k, axis)
    assert np.linalg.norm(m[["x_mm", "y_mm", "z_mm"]].to_numpy() - truth, axis=1).max() < 0.05
    # displacements in the same frame: the tissue's motion, sheared (H T_TRUE d), from frame F
    ramp = np.clip((m["frame"].to_numpy() - 5) / 10.0, 0, 1)
    H = np.eye(3)
    H[axis, 2] = k
    want = np.where(m["marker"].str.startswith("M").to_numpy()[:, None],
                    T_TRUE.apply_vector(np.outer(ramp, [0.1, -0.1, -0.8])) @ H.T, 0.0)
    d = m[["dx_mm", "dy_mm", "dz_mm"]].to_numpy()
    assert np.linalg.norm(d - want, axis=1).max() < 0.05
    # R, t_mm and scale alone map into the CT read with its tilt corrected (about the centre)
    c = np.array(sh["centre_mm"])
    S = Similarity(np.array(res["R"]), np.array(res["t_mm"]), res["scale"])
    assert np.linalg.norm(c + (S.apply(IMPLANTED) - c) @ H.T - _shear(T_TRUE.apply(IMPLANTED), k, axis),
                          axis=1).max() < 0.03
    assert registration_transform(res).tilt_deg == pytest.approx(sh["tilt_deg"])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_correct_ct_keeps_no_gantry_shear(tmp_path, seed):
    _trial(tmp_path, seed=seed)
    r, res = _register(tmp_path)
    assert r.exit_code == 0, r.output
    assert "ct-gantry-shear" not in _steps(res) and res["ct_gantry_shear"] is None
    assert "ct-gantry-shear" not in _codes(res)
    tried = _tried(res, "ct-gantry-shear")
    assert tried and not any(c["passes"] for c in tried)
    # what these references can tell of a tilt they might not show: they could show 10 degrees
    chk = res["ct_gantry_shear_check"]
    assert chk["identified"] and chk["axis"] == "y" and chk["by"] == "z" and chk["factor_se"] < SHEAR_SE_MAX
    assert chk["tilt_deg"] == 10.0 and max(chk["beyond_tre_mm"].values()) > 1.0


def test_correct_cts_of_the_loop_trials_keep_no_gantry_shear():
    """30 seeded trials of tests/test_registration.py (CT FLE 0.05 mm, tracking 0.02 mm): none
    keeps the shear (none of 500-559 did; of 1000-1299 one did, tilt -0.36 degrees, on the fit's
    delta BIC 27.2 where the residual's structure test said it was not noise, as ct-axis-scale
    did on one other; its outside evidence was at most 7.9 on all 300)."""
    kept = sum("ct-gantry-shear" in close_registration_loop(_loop_trial(seed=500 + s), RegistrationSpec()).effects
               for s in range(30))
    assert kept == 0


def test_a_stretched_ct_still_keeps_the_axis_scale_not_the_shear(tmp_path):
    """A slice spacing 5 % off (tests/test_register_ct_scale.py): the stretch is kept (outside
    evidence 107), the shear candidate does not pass (2.1), and none is kept after it."""
    _trial(tmp_path, ct_edit=_stretched(1.05, 2))
    r, res = _register(tmp_path)
    assert r.exit_code == 0, r.output
    assert _steps(res) == ["ct-axis-scale"] and res["ct_gantry_shear"] is None
    assert not any(c["passes"] for c in _tried(res, "ct-gantry-shear"))
    assert res["ct_axis_scale"]["factor"] == pytest.approx(1.05, abs=0.005)


def test_a_shear_beyond_any_gantry_tilt_is_turned_down(tmp_path):
    """35 degrees is beyond the 30 a CT gantry tilts by: the shear fits (outside evidence 211)
    but stands for something else; the loop turns it down and large-fre says the fit is poor."""
    _trial(tmp_path, ct_edit=_sheared(math.tan(math.radians(35.0)), 1))
    r, res = _register(tmp_path)
    assert r.exit_code == 0, r.output
    assert _steps(res) == [] and res["ct_gantry_shear"] is None
    (c,) = [c for c in _tried(res, "ct-gantry-shear")]
    assert c["criterion"] == "veto" and "gantry tilt of 35.0 degrees" in c["reason"]
    assert "large-fre" in _codes(res)


def test_references_that_cannot_show_a_gantry_shear_say_so(tmp_path):
    """References in a plane across z (tests/test_register_ct_scale.py's flat trial, a correct
    CT): a shear by z only moves them (their lever is the CT noise's, 0.005 mm), so the shear
    tried does not pass, and ct_gantry_shear_check says a tilt of 10 degrees could not be seen
    (factor known to +- 2) and would move the implanted markers (7.5 mm below) 1.3 mm, far
    beyond their stated TRE.  Not a warning, as ct_axis_scale_check is not."""
    _flat_trial(tmp_path, ct_noise=0.005)
    r, res = _register(tmp_path)
    assert r.exit_code == 0, r.output
    assert not any(c["passes"] for c in _tried(res, "ct-gantry-shear")) and res["ct_gantry_shear"] is None
    chk = res["ct_gantry_shear_check"]
    assert not chk["identified"] and chk["lever_mm"] < 0.01 and chk["n_references"] == 4
    assert "ct-gantry-shear" not in _codes(res)
    assert max(chk["beyond_tre_mm"].values()) == pytest.approx(math.tan(math.radians(10.0)) * 7.5, rel=0.1)


def test_fit_sheared_recovers_an_exact_shear_and_its_tre_matches_monte_carlo():
    """Exact first: a known shear of y by z is recovered to 1e-9.  Then noisy: the first-order
    TRE with the shear's uncertainty (tre_linearized of a ShearedSimilarity) matches the RMS of
    the actual target errors over 1000 draws at FLE 0.2 mm within 4 Monte-Carlo standard errors
    plus 3 %, and factor_se the spread of the fitted factor within 10 %."""
    rng = np.random.default_rng(7)
    x = np.array([[10.0, 10.0, 0.5], [-10.0, 10.0, -0.3], [-10.0, -10.0, 0.8], [10.0, -10.0, 0.0], [0.0, 3.0, 6.0]])
    R = Rotation.from_rotvec([0.2, -0.4, 0.9]).as_matrix()
    T = ShearedSimilarity(R, np.array([-5.0, 10.0, -90.0]), 1.0, 1, 0.27, np.array([0.0, 0.0, -90.0]))
    Te = fit_sheared(x, T.apply(x), 1)
    tgt = np.array([[-3.0, 3.0, -5.0], [5.0, 1.5, -7.5], [-9.5, 4.0, -6.5]])
    assert np.abs(Te.apply(tgt) - T.apply(tgt)).max() < 1e-9 and Te.factor == pytest.approx(0.27, abs=1e-9)
    assert shear_lever(fit_similarity(x, T.apply(x)), x, 1) > 1.0
    fle = 0.2
    err2, ks = [], []
    for _ in range(1000):
        Tk = fit_sheared(x, T.apply(x) + rng.normal(0, fle / math.sqrt(3), x.shape), 1)
        err2.append(np.sum((Tk.apply(tgt) - T.apply(tgt)) ** 2, axis=1))
        ks.append(Tk.factor)
    err2 = np.array(err2)
    stated = tre_linearized(T, x, tgt, fle, scale=False) ** 2
    se = err2.std(axis=0) / math.sqrt(len(err2))
    assert np.all(np.abs(err2.mean(axis=0) - stated) < 4 * se + 0.03 * stated), (err2.mean(axis=0), stated)
    assert factor_se(T, x, fle, scale=False) == pytest.approx(np.std(ks), rel=0.1)
    rigid = tre_linearized(fit_similarity(x, T.apply(x)), x, tgt, fle, scale=False) ** 2
    assert np.all(stated > rigid)


def sheared_registration(deg: float, scale: float = 1.0):
    """A registration into a CT whose y is sheared by z (``deg`` of gantry tilt) about (1, 2, 70)
    mm: its rotation, transform and registration.json dict (shared with tests/test_export_fe.py)."""
    R = Rotation.from_rotvec([0.1, -0.3, 0.5]).as_matrix()
    k = math.tan(math.radians(deg))
    T = ShearedSimilarity(R, np.array([3.0, -4.0, 80.0]), scale, 1, k, np.array([1.0, 2.0, 70.0]))
    reg = {"R": R.tolist(), "t_mm": T.t_mm.tolist(), "scale": scale, "matrix": T.matrix().tolist(),
           "ct_axis_scale": None,
           "ct_gantry_shear": {"axis": "y", "axis_index": 1, "by": "z", "factor": k, "centre_mm": [1.0, 2.0, 70.0]}}
    return R, T, reg


def test_export_fe_directions_and_registration_json_through_a_shear():
    """export-fe maps an indentor direction through the registration: for a sheared CT along the
    image of the direction by the whole linear part (normalised to its length), not by R alone
    (19.9 degrees off, for a direction near the CT's z at 20 degrees of tilt);
    registration_transform rebuilds the sheared map from registration.json (export-fe's
    read_registration reads it so: tests/test_export_fe.py), and a bad ct_gantry_shear is an
    error naming the key."""
    from bsipipe.fe.export import _ct_direction

    R, T, reg = sheared_registration(20.0, 1.01)
    k = reg["ct_gantry_shear"]["factor"]
    got = registration_transform(reg)
    x = np.array([[0.0, 0.0, 0.0], [5.0, -3.0, 15.0], [-7.0, 2.0, -9.0]])
    M = np.asarray(reg["matrix"])
    assert isinstance(got, ShearedSimilarity)
    assert np.allclose(got.apply(x), x @ M[:3, :3].T + M[:3, 3], atol=1e-12)
    v = np.array([0.0, 0.0, 2.0])
    d = _ct_direction(got, v)
    assert np.isclose(np.linalg.norm(d), 2.0) and np.allclose(np.cross(d, M[:3, :3] @ v), 0, atol=1e-12)
    angle = math.degrees(math.acos(np.clip(d @ (R @ v) / 4.0, -1, 1)))
    assert angle == pytest.approx(19.9, abs=0.1)
    for bad, what in [({"axis": "y", "by": "y", "factor": k, "centre_mm": [0, 0, 0]}, "ct_gantry_shear"),
                      ({"axis": "y", "factor": float("nan"), "centre_mm": [0, 0, 0]}, "ct_gantry_shear"),
                      ({"axis": "y", "factor": k}, "ct_gantry_shear needs")]:
        with pytest.raises(ValueError, match=what):
            registration_transform({**reg, "ct_gantry_shear": bad})
    with pytest.raises(ValueError, match="both set"):
        registration_transform({**reg, "ct_axis_scale": {"axis": "z", "factor": 1.05, "centre_mm": [0, 0, 0]}})
