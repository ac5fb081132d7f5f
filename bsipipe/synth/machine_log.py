r"""A seeded digital twin of the Micro Tester: compression and indentation logs with known truth.

The generator simulates what the machine records when a platen driven at constant crosshead
speed meets a brain-tissue specimen, with every effect the fit's loop knows about switchable
and recorded in the returned truth:

- **tissue**: one- or two-term (any N) Ogden, :math:`W = \sum 2\mu_i/\alpha_i^2
  (\lambda_1^{\alpha_i} + \lambda_2^{\alpha_i} + \lambda_3^{\alpha_i} - 3)`, homogeneous
  uniaxial compression (frictionless platens), or bonded (``boundary='no-slip'``) platens
  through :func:`bsipipe.mechanics.noslip.noslip_nominal_stress` (one-term);
- **viscoelastic-relaxation**: a Prony series applied quasi-linearly to the elastic force
  (:func:`~bsipipe.mechanics.viscoelastic.qlv_response`, instantaneous moduli);
- **contact-offset**: an uneven top surface.  The platen meets the highest point at
  ``gap_mm`` but full contact needs ``2 c`` more travel (``c = contact_offset_mm``); the
  bulk compression is :math:`\delta = u^2 / (4c)` for :math:`0 \le u \le 2c` (``u`` travel
  past first touch) and :math:`u - c` beyond, so the log behaves as a flat specimen touched
  at ``gap_mm + c`` (the truth ``contact_mm``) while a detector sees the force rise earlier;
- **load-baseline-drift**: load-cell offset ``baseline_n`` plus ``drift_n_per_s`` times time;
- **machine-compliance**: the frame deflects ``compliance_mm_per_n`` times the load, so the
  platen lags the recorded crosshead extension: :math:`\delta = \delta(e - C F)`, solved by
  fixed-point iteration (an independent route from the fit's Newton solve);
- **periodic-disturbance**: a sinusoid on the load reading, ``disturbance_n`` amplitude at
  ``disturbance_hz`` (the source's frequency: mains hum at 50.5 Hz recorded at 50 Hz shows as
  a 0.5 Hz swing, the sampling aliases it) and phase ``disturbance_phase_rad`` at time 0;
- load noise: independent Gaussian, ``noise_n`` standard deviation.

The simulation runs on a time grid ``oversample`` times finer than the recorded one (the
hereditary integral of a nonlinear response is then accurate to far below the noise) and
is sampled at ``rate_hz`` (or ``n_points`` evenly spaced samples).

Protocols: ``ramp`` (approach and load to ``max_strain`` or ``depth_mm`` past contact),
``ramp-hold`` (then hold ``hold_s``), ``ramp-unload`` (then back to the start at the same
speed), ``ramp-hold-unload``.  The ``segment`` column numbers the segments from 1.

Writers produce the Instron layouts documented in ``data/real/README.md``: Bluehill 2
(metadata rows ``Key : Sub,value,unit``, a blank line, ``Time,Extension,Load,Segment ID``,
units ``(sec),(mm),(N)``, CRLF, compression negative) and Bluehill 3 (a quoted
``Results Table`` block with the geometry, a ``Raw Data`` marker, ``"Time","Extension","Load"``
with ``(s)``).
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from bsipipe.mechanics.hyperelastic import ogden_nominal_stress
from bsipipe.mechanics.viscoelastic import qlv_response

PROTOCOLS = ("ramp", "ramp-hold", "ramp-unload", "ramp-hold-unload")


def _crosshead_schedule(gap_mm, depth_mm, speed_mm_s, protocol, hold_s):
    """Knots (time_s, extension_mm, segment) of the piecewise-linear crosshead path."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; expected one of {PROTOCOLS}")
    e_max = gap_mm + depth_mm
    t = [0.0, e_max / speed_mm_s]
    e = [0.0, e_max]
    seg = [1]
    if "hold" in protocol:
        t.append(t[-1] + hold_s)
        e.append(e_max)
        seg.append(2)
    if "unload" in protocol:
        t.append(t[-1] + e_max / speed_mm_s)
        e.append(0.0)
        seg.append(seg[-1] + 1)
    return np.array(t), np.array(e), seg


def _bulk_compression(u_mm, contact_offset_mm):
    """Bulk compression for travel ``u`` past first touch (the uneven-top model above)."""
    u = np.maximum(u_mm, 0.0)
    c = float(contact_offset_mm)
    if c <= 0.0:
        return u
    return np.where(u <= 2 * c, u**2 / (4 * c), u - c)


#: The generator's own no-slip FE mesh: finer than the fit's tables (32 radial cells), so a
#: fit with ``boundary='no-slip'`` meets discretisation and interpolation error it did not make.
NOSLIP_MESH_RADIAL = 40


@lru_cache(maxsize=16)
def _noslip_ratio(alpha: float, aspect: float, lam_min: float, n_radial: int):
    """PCHIP of the FE force ratio (bonded / homogeneous) over ``[lam_min, 1]``, unit mu and D."""
    from scipy.interpolate import PchipInterpolator

    from bsipipe.mechanics.noslip import FEMesh, noslip_simulate
    grid = np.unique(np.concatenate([[0.999, 0.998, 0.995], np.arange(0.99, lam_min - 0.02, -0.02)]))[::-1]
    grid = grid[grid >= lam_min - 0.02]
    run = noslip_simulate(grid, 1.0, alpha, 1.0, aspect, mesh=FEMesh(n_radial=n_radial))
    ratio = np.asarray(run.force_ratio, dtype=float)
    # The ratio is linear in the stretch near 1: extrapolate the small-strain limit.
    r1 = ratio[0] + (ratio[0] - ratio[1]) * (1.0 - grid[0]) / (grid[0] - grid[1])
    lam = np.concatenate([[1.0], grid])[::-1]
    return PchipInterpolator(lam, np.concatenate([[r1], ratio])[::-1], extrapolate=False)


def _stress_function(mus, alphas, boundary, aspect, lam_floor, noslip_mesh_radial):
    """``stretch -> nominal stress (Pa)`` of the simulated specimen."""
    if boundary == "frictionless":
        return lambda lam: ogden_nominal_stress(lam, mus, alphas, "uniaxial")
    if boundary != "no-slip":
        raise ValueError(f"unknown boundary {boundary!r}")
    if len(mus) != 1:
        raise ValueError("the no-slip platen model is a one-term Ogden law")
    if noslip_mesh_radial is None:
        from bsipipe.mechanics.noslip import noslip_nominal_stress
        return lambda lam: np.asarray(noslip_nominal_stress(lam, mus[0], alphas[0], aspect), dtype=float)
    lam_min = float(np.floor(lam_floor * 50.0) / 50.0)                 # one FE run per 0.02 of depth
    ratio = _noslip_ratio(float(alphas[0]), round(float(aspect), 6), lam_min, int(noslip_mesh_radial))
    return lambda lam: ratio(np.clip(lam, lam_min, 1.0)) * ogden_nominal_stress(lam, mus, alphas, "uniaxial")


def synth_compression_log(*, mu_pa: float = 720.0, alpha: float = -4.7,
                          mus_pa: Sequence[float] | None = None, alphas: Sequence[float] | None = None,
                          prony: Sequence[tuple[float, float]] = (),
                          diameter_mm: float = 18.0, height_mm: float = 12.0,
                          speed_mm_min: float = 4.0, gap_mm: float = 0.5,
                          max_strain: float = 0.3, depth_mm: float | None = None,
                          protocol: str = "ramp", hold_s: float = 60.0,
                          noise_n: float = 1e-3, rate_hz: float = 10.0, n_points: int | None = None,
                          contact_offset_mm: float = 0.0, baseline_n: float = 0.0, drift_n_per_s: float = 0.0,
                          compliance_mm_per_n: float = 0.0, disturbance_n: float = 0.0,
                          disturbance_hz: float = 50.5, disturbance_phase_rad: float = 0.0,
                          boundary: str = "frictionless",
                          noslip_mesh_radial: int | None = NOSLIP_MESH_RADIAL,
                          oversample: int = 10, seed: int = 0) -> tuple[pd.DataFrame, dict]:
    """Simulate a Micro Tester cylinder-compression log.

    Parameters
    ----------
    mu_pa, alpha : float
        One-term Ogden truth (ignored when ``mus_pa``/``alphas`` are given).
    mus_pa, alphas : sequence of float, optional
        N-term Ogden truth (e.g. two terms).
    prony : sequence of (g, tau_s)
        Prony terms of the QLV relaxation (instantaneous moduli); empty for hyperelastic.
    diameter_mm, height_mm : float
        Specimen geometry (default 18 x 12 mm, the sheep-brain samples).
    speed_mm_min : float
        Crosshead speed (default 4 mm/min).
    gap_mm : float
        Platen travel before it first touches the specimen (default 0.5 mm).
    max_strain, depth_mm : float
        Crosshead travel past the (true) contact: ``depth_mm`` if given, else
        ``max_strain * height_mm`` (with machine compliance the specimen itself is
        compressed less, by the frame's deflection).
    protocol : {"ramp", "ramp-hold", "ramp-unload", "ramp-hold-unload"}
    hold_s : float
        Hold duration of the hold protocols.
    noise_n : float
        Load-cell noise standard deviation, N (default 1 mN).
    rate_hz, n_points : float, int
        Recording rate (default 10 Hz), or a fixed number of evenly spaced samples.
    contact_offset_mm, baseline_n, drift_n_per_s, compliance_mm_per_n, disturbance_n : float
        Effects (module docstring); 0 switches each off.
    disturbance_hz, disturbance_phase_rad : float
        The periodic disturbance's frequency at its source (sampled at the recording's times,
        so aliased where it is above the Nyquist frequency) and its phase at time 0.
    boundary : {"frictionless", "no-slip"}
    noslip_mesh_radial : int or None
        For ``no-slip``: radial cells of the generator's own FE run
        (:func:`bsipipe.mechanics.noslip.noslip_simulate`, once per alpha, aspect and depth in a
        process; tens of seconds), finer than the fit's tables; ``None`` uses the tables
        (:func:`~bsipipe.mechanics.noslip.noslip_nominal_stress`, fast, but the very model a
        no-slip fit uses).
    oversample : int
        Simulation steps per recorded sample.
    seed : int
        Seeds the noise.

    Returns
    -------
    frame : DataFrame
        ``time_s, extension_mm, load_n, segment``; extension and load positive in
        compression (the writers flip them to the machine's sign).
    truth : dict
        Every parameter used, the tissue in ``fit.json``'s naming (``mu_pa``/``alpha`` or
        ``mu1_pa``, ``alpha1``, ...; ``prony`` as ``[{"g", "tau_s"}]``), the true contact
        displacement ``contact_mm`` and the noise-free force ``force_true_n`` (array).

    Examples
    --------
    >>> df, truth = synth_compression_log(seed=1)
    >>> len(df), truth["contact_mm"], round(float(df["load_n"].max()), 2)
    (616, 0.5, 0.55)
    """
    if mus_pa is None:
        mus, als = np.array([float(mu_pa)]), np.array([float(alpha)])
    else:
        mus, als = np.asarray(mus_pa, dtype=float), np.asarray(alphas, dtype=float)
        if mus.shape != als.shape or mus.ndim != 1 or len(mus) == 0:
            raise ValueError("mus_pa and alphas must be sequences of one length")
    g = np.array([float(p[0]) for p in prony])
    tau = np.array([float(p[1]) for p in prony])
    if g.sum() >= 1 or np.any(g < 0) or np.any(tau <= 0):
        raise ValueError("Prony terms need g >= 0, sum(g) < 1 and tau_s > 0")
    depth = float(depth_mm) if depth_mm is not None else float(max_strain) * height_mm
    speed = speed_mm_min / 60.0
    contact_true = gap_mm + max(contact_offset_mm, 0.0)
    knots_t, knots_e, segs = _crosshead_schedule(gap_mm, depth + max(contact_offset_mm, 0.0), speed, protocol, hold_s)
    duration = knots_t[-1]
    if n_points is not None:
        t_rec = np.linspace(0.0, duration, int(n_points))
    else:
        t_rec = np.arange(0.0, duration + 0.5 / rate_hz, 1.0 / rate_hz)
        t_rec = t_rec[t_rec <= duration + 1e-9]
    # Fine simulation grid: every recorded time, every knot, and oversample steps between.
    fine = np.union1d(np.concatenate([np.linspace(a, b, oversample + 1) for a, b in zip(t_rec[:-1], t_rec[1:])])
                      if len(t_rec) > 1 else t_rec, knots_t)
    e_fine = np.interp(fine, knots_t, knots_e)
    area_m2 = np.pi * diameter_mm**2 / 4.0 * 1e-6
    aspect = height_mm / diameter_mm

    # The deepest stretch (compliance only makes the specimen's compression smaller).
    lam_floor = 1.0 - min(float(_bulk_compression(np.max(e_fine) - gap_mm, contact_offset_mm)),
                          0.95 * height_mm) / height_mm
    stress = _stress_function(mus, als, boundary, aspect, lam_floor, noslip_mesh_radial)

    def tissue_force(platen_mm):
        delta = _bulk_compression(platen_mm - gap_mm, contact_offset_mm)
        lam = 1.0 - np.minimum(delta, 0.95 * height_mm) / height_mm
        fe = -stress(lam) * area_m2
        return qlv_response(fine, fe, g, tau) if len(g) else fe

    f = tissue_force(e_fine)
    if compliance_mm_per_n > 0:
        for it in range(1000):
            f_new = tissue_force(e_fine - compliance_mm_per_n * f)
            step = float(np.max(np.abs(f_new - f)))
            f = f_new
            if step <= 1e-13 * max(float(np.max(np.abs(f))), 1e-12):
                break
        else:
            raise ValueError("the compliance iteration did not converge: the frame is softer than the specimen")
    f_rec = np.interp(t_rec, fine, f)
    rng = np.random.default_rng(seed)
    load = f_rec + baseline_n + drift_n_per_s * t_rec + rng.normal(0.0, noise_n, len(t_rec))
    if disturbance_n:
        load = load + disturbance_n * np.sin(2.0 * np.pi * disturbance_hz * t_rec + disturbance_phase_rad)
    extension = np.interp(t_rec, knots_t, knots_e)
    segment = np.searchsorted(knots_t[1:-1], t_rec, side="right") + 1
    segment = np.asarray(segs)[np.minimum(segment - 1, len(segs) - 1)]
    frame = pd.DataFrame({"time_s": t_rec, "extension_mm": extension, "load_n": load, "segment": segment})
    if len(mus) == 1:
        tissue = {"mu_pa": float(mus[0]), "alpha": float(als[0])}
    else:
        tissue = {k: float(v) for i, (m, a) in enumerate(zip(mus, als), start=1)
                  for k, v in ((f"mu{i}_pa", m), (f"alpha{i}", a))}
    truth = {
        "model": "ogden" if len(mus) == 1 else f"ogden{len(mus)}",
        "params": {**tissue, **({"prony": [{"g": float(a), "tau_s": float(b)} for a, b in zip(g, tau)]} if len(g) else {})},
        "shear_modulus_pa": float(mus.sum()),
        "boundary": boundary,
        "noslip_model": (None if boundary != "no-slip" else
                         "tables" if noslip_mesh_radial is None else f"FE, {noslip_mesh_radial} radial cells"),
        "diameter_mm": float(diameter_mm), "height_mm": float(height_mm),
        "speed_mm_s": float(speed), "speed_mm_min": float(speed_mm_min),
        "gap_mm": float(gap_mm), "contact_mm": float(contact_true), "depth_mm": depth,
        "protocol": protocol, "hold_s": float(hold_s) if "hold" in protocol else 0.0,
        "noise_n": float(noise_n), "n_points": int(len(t_rec)),
        "effects": {
            "viscoelastic-relaxation": bool(len(g)),
            "contact-offset": float(contact_offset_mm) != 0.0,
            "load-baseline-drift": bool(baseline_n or drift_n_per_s),
            "machine-compliance": compliance_mm_per_n > 0,
            "no-slip-platens": boundary == "no-slip",
            "periodic-disturbance": bool(disturbance_n),
        },
        "contact_offset_mm": float(contact_offset_mm), "baseline_n": float(baseline_n),
        "drift_n_per_s": float(drift_n_per_s), "compliance_mm_per_n": float(compliance_mm_per_n),
        "disturbance_n": float(disturbance_n), "disturbance_hz": float(disturbance_hz),
        "disturbance_phase_rad": float(disturbance_phase_rad),
        "seed": int(seed),
        "force_true_n": f_rec,
    }
    return frame, truth


#: The largest compression of the equivalent cylinder at full depth (:func:`indentation_equivalent_cylinder`).
INDENTATION_MAX_STRAIN = 0.3


def indentation_equivalent_cylinder(indenter_diameter_mm: float, depth_mm: float | None = None,
                                    max_strain: float = INDENTATION_MAX_STRAIN) -> tuple[float, float]:
    r"""Equivalent homogeneous cylinder ``(diameter_mm, height_mm)`` of a flat-punch indentation.

    Sneddon's flat punch of radius :math:`a` on an incompressible half-space has stiffness
    :math:`8 \mu a`; a cylinder of area :math:`A` and height :math:`L` compressed
    homogeneously has :math:`3 \mu A / L`, so :math:`A = 8 a L / 3` matches them for any
    :math:`L`.  The stressed zone is taken one punch diameter deep, :math:`L = 2a`, or deeper
    where an indentation ``depth_mm`` would compress it by more than ``max_strain``: a punch
    sunk deep loads tissue deeper than a diameter, and a zone of :math:`2a` would be squeezed
    to nothing (a 5 mm punch 4.8 mm deep: a stretch of 0.04, and the twin's log read 266 kN
    for an Ogden brain of 720 Pa).  Beyond small depths this is a model of the in situ test,
    not its solution: the generator uses it so that the indentation log has a known answer
    that ``fit-ogden`` can recover with this geometry.

    >>> d, h = indentation_equivalent_cylinder(16.0)
    >>> round(d, 3), h
    (20.847, 16.0)
    >>> d, h = indentation_equivalent_cylinder(5.0, depth_mm=4.8)
    >>> round(d, 3), h
    (11.654, 16.0)
    """
    a = indenter_diameter_mm / 2.0
    height = 2.0 * a
    if depth_mm is not None:
        height = max(height, float(depth_mm) / float(max_strain))
    area = 8.0 * a * height / 3.0
    return float(np.sqrt(4.0 * area / np.pi)), float(height)


def synth_indentation_log(*, indenter_diameter_mm: float = 16.0, speed_mm_min: float = 12.0,
                          depth_mm: float = 4.8, gap_mm: float = 0.5, **kw) -> tuple[pd.DataFrame, dict]:
    """An in situ indentation log (12 mm/min to 4.8 mm past contact, the seeds' protocol).

    The brain under a flat punch is simulated as its equivalent cylinder
    (:func:`indentation_equivalent_cylinder`, deep enough for ``depth_mm``); every other option is
    :func:`synth_compression_log`'s.  The truth records the punch and the equivalent
    geometry (``diameter_mm``, ``height_mm``) a fit needs.
    """
    d_eq, h_eq = indentation_equivalent_cylinder(indenter_diameter_mm, depth_mm)
    frame, truth = synth_compression_log(diameter_mm=d_eq, height_mm=h_eq, speed_mm_min=speed_mm_min,
                                         depth_mm=depth_mm, gap_mm=gap_mm, **kw)
    truth.update(test="in-situ-indentation", indenter_diameter_mm=float(indenter_diameter_mm))
    return frame, truth


# --- writers ---------------------------------------------------------------------------------

def _metadata_rows(label: str, geometry: Mapping[str, float] | None, extra: Mapping[str, str] | None):
    rows = [("Text Inputs : Specimen label", f'"{label}"', None),
            ("General : Start Date", "01/02/2024 9:30 AM", None)]
    for key, value in (geometry or {}).items():
        name = {"diameter_mm": "Diameter", "height_mm": "Height"}.get(key, key)
        rows.append((f"Dimensions : {name}", f"{float(value):.4f}", "mm"))
    for key, value in (extra or {}).items():
        rows.append((f"Text Inputs : {key}", f'"{value}"', None))
    return rows


def write_bluehill2(frame: pd.DataFrame, path: str | os.PathLike, *, label: str = "synthetic",
                    geometry: Mapping[str, float] | None = None, metadata: Mapping[str, str] | None = None) -> Path:
    """Write ``frame`` (compression positive) as an Instron Bluehill 2 raw-data CSV.

    Layout of the real export in ``data/real/instron_bluehill``: metadata rows
    ``Key : Sub,value[,unit]``, a blank line, ``Time,Extension,Load,Segment ID``, the units
    row ``(sec),(mm),(N),``, CRLF line endings, compression negative.
    """
    lines = [",".join(x for x in row if x is not None) for row in _metadata_rows(label, geometry, metadata)]
    lines += ["", "Time,Extension,Load,Segment ID", "(sec),(mm),(N),"]
    t, e, f = frame["time_s"].to_numpy(), -frame["extension_mm"].to_numpy(), -frame["load_n"].to_numpy()
    seg = frame["segment"].to_numpy() if "segment" in frame else np.ones(len(frame), int)
    lines += [f"{a:.5f},{b:.5f},{c:.6f},{int(s)}" for a, b, c, s in zip(t, e, f, seg)]
    path = Path(path)
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode("utf-8"))
    return path


def write_bluehill3(frame: pd.DataFrame, path: str | os.PathLike, *, label: str = "synthetic",
                    geometry: Mapping[str, float] | None = None, metadata: Mapping[str, str] | None = None) -> Path:
    """Write ``frame`` (compression positive) in the Bluehill 3 layout.

    Quoted metadata rows, a ``Results Table 1`` block (specimen label and geometry with a
    units row), a blank line, a ``Raw Data`` marker, ``"Time","Extension","Load"`` with
    units ``"(s)","(mm)","(N)"``, quoted values, LF line endings, compression negative.
    """
    q = lambda s: f'"{s}"'                                            # noqa: E731
    lines = []
    for key, value, unit in _metadata_rows(label, geometry, metadata):
        lines.append(",".join([q(key), value if value.startswith('"') else q(value)] + ([q(unit)] if unit else [])))
    geo = dict(geometry or {})
    names = ["Specimen label"] + [{"diameter_mm": "Diameter", "height_mm": "Height"}.get(k, k) for k in geo]
    lines += ["", q("Results Table 1"), ",".join(q(n) for n in names),
              ",".join([q("")] + [q("(mm)") for _ in geo]),
              ",".join([q(label)] + [q(f"{float(v):.4f}") for v in geo.values()]), "", q("Raw Data"),
              ",".join(q(n) for n in ("Time", "Extension", "Load")), ",".join(q(u) for u in ("(s)", "(mm)", "(N)"))]
    t, e, f = frame["time_s"].to_numpy(), -frame["extension_mm"].to_numpy(), -frame["load_n"].to_numpy()
    lines += [f'"{a:.4f}","{b:.5f}","{c:.6f}"' for a, b, c in zip(t, e, f)]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
