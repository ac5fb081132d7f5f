"""The Micro Tester twin: every effect does what its truth says, and H1's reader reads it back."""

import numpy as np
import pytest

from bsipipe.io.machine_log import read_machine_log
from bsipipe.mechanics.hyperelastic import ogden_nominal_stress
from bsipipe.mechanics.viscoelastic import relaxation_function
from bsipipe.synth.machine_log import (indentation_equivalent_cylinder, synth_compression_log,
                                       synth_indentation_log, write_bluehill2, write_bluehill3)

AREA_M2 = np.pi * 18.0**2 / 4 * 1e-6


def _ogden_force(delta_mm, mu=720.0, alpha=-4.7, height=12.0, area=AREA_M2):
    lam = 1 - np.maximum(delta_mm, 0) / height
    return -ogden_nominal_stress(lam, [mu], [alpha]) * area


def test_default_log_is_the_homogeneous_ogden_force_plus_seeded_noise():
    frame, truth = synth_compression_log(seed=5)
    assert truth["params"] == {"mu_pa": 720.0, "alpha": -4.7} and truth["contact_mm"] == 0.5
    np.testing.assert_allclose(np.diff(frame["time_s"]), 0.1, atol=1e-9)            # 10 Hz
    np.testing.assert_allclose(frame["extension_mm"], 4.0 / 60 * frame["time_s"], atol=1e-12)
    np.testing.assert_allclose(truth["force_true_n"], _ogden_force(frame["extension_mm"] - 0.5), atol=1e-12)
    noise = frame["load_n"] - truth["force_true_n"]
    assert abs(noise.std() / 1e-3 - 1) < 0.15                                     # 616 samples of 1 mN
    again, _ = synth_compression_log(seed=5)
    other, _ = synth_compression_log(seed=6)
    assert again.equals(frame) and not other["load_n"].equals(frame["load_n"])
    assert len(synth_compression_log(n_points=5000)[0]) == 5000


def test_compliance_baseline_and_drift():
    c, b0, b1 = 0.4, 0.02, 3e-4
    frame, truth = synth_compression_log(compliance_mm_per_n=c, baseline_n=b0, drift_n_per_s=b1, noise_n=0.0, seed=1)
    f = truth["force_true_n"]
    # The frame's deflection C F is taken off the crosshead travel: F = F_e(e - gap - C F).
    np.testing.assert_allclose(f, _ogden_force(frame["extension_mm"] - 0.5 - c * f), atol=1e-9)
    assert np.max(c * f) > 0.15                                                    # 0.19 mm of deflection
    np.testing.assert_allclose(frame["load_n"] - f, b0 + b1 * frame["time_s"], atol=1e-15)
    assert truth["effects"]["machine-compliance"] and truth["effects"]["load-baseline-drift"]


def test_uneven_top_touches_early_and_behaves_as_a_flat_top_at_the_true_contact():
    cofs = 0.2
    frame, truth = synth_compression_log(contact_offset_mm=cofs, noise_n=0.0)
    e = frame["extension_mm"].to_numpy()
    f = truth["force_true_n"]
    assert truth["contact_mm"] == pytest.approx(0.5 + cofs)
    far = e > 0.5 + 2 * cofs
    np.testing.assert_allclose(f[far], _ogden_force(e[far] - truth["contact_mm"]), atol=1e-12)
    toe = (e > 0.5) & (e < 0.5 + cofs)
    assert np.all(f[toe] > 0)                         # force rises before the true contact
    assert np.all(f[e <= 0.5] == 0)


def test_ramp_hold_unload_relaxes_along_the_prony_series():
    g, tau = [0.5, 0.2], [2.0, 20.0]
    frame, truth = synth_compression_log(prony=list(zip(g, tau)), protocol="ramp-hold-unload", hold_s=100.0,
                                         speed_mm_min=240.0, rate_hz=20.0, noise_n=0.0)
    assert list(np.unique(frame["segment"])) == [1, 2, 3]
    assert frame["extension_mm"].iloc[-1] == pytest.approx(0.0, abs=1e-9)
    hold = frame["segment"].to_numpy() == 2
    t_hold = frame["time_s"].to_numpy()[hold]
    f_hold = truth["force_true_n"][hold]
    # Independent check: the hereditary integral of the ramp's elastic force by quadrature.
    speed = truth["speed_mm_s"]
    t_ramp = (0.5 + truth["depth_mm"]) / speed
    s_grid = np.linspace(0.5 / speed, t_ramp, 200001)
    dfe = np.gradient(_ogden_force(speed * s_grid - 0.5), s_grid)
    expected = [np.trapezoid(relaxation_function(t - s_grid, g, tau) * dfe, s_grid) for t in t_hold[::50]]
    np.testing.assert_allclose(f_hold[::50], expected, rtol=2e-4)
    assert np.all(np.diff(f_hold) < 0)
    fe = _ogden_force(truth["depth_mm"])
    assert f_hold[-1] == pytest.approx((1 - sum(g)) * fe, rel=0.02)   # the slow term nearly relaxed too
    assert relaxation_function(0.0, g, tau) == 1.0
    assert truth["params"]["prony"] == [{"g": 0.5, "tau_s": 2.0}, {"g": 0.2, "tau_s": 20.0}]


def test_indentation_log_has_sneddon_stiffness_at_small_depth():
    frame, truth = synth_indentation_log(noise_n=0.0, n_points=4000)
    assert truth["test"] == "in-situ-indentation" and truth["depth_mm"] == 4.8
    assert truth["speed_mm_s"] == pytest.approx(0.2)
    d, h = indentation_equivalent_cylinder(16.0)
    assert (truth["diameter_mm"], truth["height_mm"]) == (d, h)
    e = frame["extension_mm"].to_numpy()
    small = (e > 0.5) & (e < 0.52)
    k = np.polyfit(e[small] - 0.5, truth["force_true_n"][small], 1)[0]              # N/mm
    sneddon = 8 * 720.0 * 8e-3 * 1e-3                                               # 8 mu a, N/mm
    assert k == pytest.approx(sneddon, rel=0.01)


@pytest.mark.parametrize("writer,layout", [(write_bluehill2, "bluehill2"), (write_bluehill3, "bluehill3")])
def test_bluehill_files_read_back(tmp_path, writer, layout):
    frame, truth = synth_compression_log(protocol="ramp-unload", seed=3)
    path = writer(frame, tmp_path / f"{layout}.csv", label="S7", geometry={"diameter_mm": 18.0, "height_mm": 12.0})
    ml = read_machine_log(path)
    assert ml.layout == layout and ml.compression_sign == -1
    assert ml.geometry == {"diameter_mm": 18.0, "height_mm": 12.0}
    assert ml.metadata["Specimen label"] == "S7"
    d, f = ml.compression()
    np.testing.assert_allclose(ml.time_s, frame["time_s"], atol=1e-4)
    np.testing.assert_allclose(d, frame["extension_mm"], atol=1e-5)
    np.testing.assert_allclose(f, frame["load_n"], atol=1e-6)
    if layout == "bluehill2":
        np.testing.assert_array_equal(ml.segment, frame["segment"])
        assert path.read_bytes().count(b"\r\n") == path.read_bytes().count(b"\n")


def test_no_slip_generator_runs_its_own_fe_and_agrees_with_the_tables():
    """The generator's own FE run (coarse here, 16 radial cells, for speed) against the fit's
    tables (32 cells): the mesh changes the force by about 1.5 % at 30 % strain."""
    own, truth = synth_compression_log(boundary="no-slip", noslip_mesh_radial=16, noise_n=0.0)
    tab, _ = synth_compression_log(boundary="no-slip", noslip_mesh_radial=None, noise_n=0.0)
    assert truth["noslip_model"] == "FE, 16 radial cells"
    loaded = truth["force_true_n"] > 0.01
    np.testing.assert_allclose(truth["force_true_n"][loaded], tab["load_n"][loaded], rtol=0.025)
    hom = _ogden_force(own["extension_mm"] - 0.5)
    assert np.all(truth["force_true_n"][loaded] / hom[loaded] > 1.3)                # bonded is stiffer


def test_deep_indentation_log_stays_physical():
    """A 5 mm punch 4.8 mm deep (the study twin's protocol): the equivalent cylinder had been
    one punch diameter high, squeezed to a stretch of 0.04 at full depth, and the log's load
    read 266 kN, flat where the stretch was clipped; now the cylinder is deep enough to keep
    the compression at 30 %, the force stays a fraction of a newton and still has Sneddon's
    stiffness at small depth."""
    frame, truth = synth_indentation_log(indenter_diameter_mm=5.0, depth_mm=4.8, noise_n=0.0, n_points=4000)
    assert truth["depth_mm"] / truth["height_mm"] == pytest.approx(0.3)
    f = truth["force_true_n"]
    assert 0.1 < f.max() < 1.0                              # 8 mu a d = 0.069 N, stiffened by alpha -4.7
    e = frame["extension_mm"].to_numpy()
    small = (e > 0.5) & (e < 0.52)
    k = np.polyfit(e[small] - 0.5, f[small], 1)[0]
    assert k == pytest.approx(8 * 720.0 * 2.5e-3 * 1e-3, rel=0.01)
