"""``bsipipe fit-ogden``: machine logs or stress-stretch tables -> fit.json, FE cards, fit.png, loop.md, loop.png.

The command reads its inputs, merges options over the config (options > config > a log's
metadata for the geometry), calls the fitting stage (:mod:`bsipipe.mechanics.fit`) through
the loop (:func:`_close_loop`), and writes every result file at once through
:class:`~bsipipe.provenance.ResultSet` (``fit.json`` last).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pydantic import Field, PositiveFloat

from ..config import FitConfig, load_config, validate
from ..errors import InputError, ProcessingError
from ..io.machine_log import RESOLUTION_REFUSE_SHARE, clipped_top, load_resolution
from ..quality import listed

log = logging.getLogger(__name__)

#: What fit.json says about how several logs / modes are weighted (fit.py's docstring).
WEIGHTING_LOGS = ("residuals in N; log i with n_i fitted samples weighted sqrt(N / (L n_i)) so every "
                  "log counts equally whatever its length (a single log is unweighted)")
WEIGHTING_TABLES = ("residual / sqrt(|P| * mean |P| of its mode) (stress error variance proportional to stress), "
                    "every mode weighted equally, soft-L1 loss with f = 0.03")


class FitOgdenConfig(FitConfig):
    """:class:`~bsipipe.config.FitConfig` with the keys only this command reads."""

    contact_mm: float | list[float] | None = Field(
        None, description="given contact: crosshead displacement (mm) past the record's first sample, positive in "
                          "compression (fit.json's contact_mm frame; negative: before the first sample); one for "
                          "every log or one per log")
    diameter_mm: PositiveFloat | list[PositiveFloat] | None = Field(
        None, description="specimen diameter (cylinder); one for every log or one per log")
    height_mm: PositiveFloat | list[PositiveFloat] | None = Field(
        None, description="specimen height before contact; one for every log or one per log")


def _merge_config(config_path, options: dict) -> tuple[FitOgdenConfig, set]:
    """Options (not None) over the config file over FitConfig's defaults; the keys set explicitly."""
    base = load_config(FitOgdenConfig, config_path) if config_path is not None else FitOgdenConfig()
    data = base.model_dump()
    explicit = set(base.model_fields_set)
    for k, v in options.items():
        if v is not None:
            data[k] = v
            explicit.add(k)
    cfg = validate(FitOgdenConfig, data, source=config_path or "command line")
    return cfg, explicit


#: The keys given once for every log or once per log, and what one value is.
PER_LOG = {"contact_mm": "contacts", "diameter_mm": "diameters", "height_mm": "heights"}


def _per_log(cfg: FitOgdenConfig, key: str, paths: Sequence[str]) -> list[float | None]:
    """Each log's value of ``key`` (:data:`PER_LOG`: one for all, or one per log in order;
    ``None``: not given)."""
    given = getattr(cfg, key)
    if given is None:
        return [None] * len(paths)
    if isinstance(given, (int, float)):
        return [float(given)] * len(paths)
    if len(given) == 1:
        return [float(given[0])] * len(paths)
    if len(given) != len(paths):
        opt = "--" + key.replace("_", "-")
        raise InputError(f"{len(given)} {PER_LOG[key]} ({opt} / {key}) for {len(paths)} logs: give one for "
                         f"every log, or one for all", path=paths[0], key=key)
    return [float(g) for g in given]


def _loading_speed(time_s: np.ndarray, disp_mm: np.ndarray, start: int) -> float | None:
    """Crosshead speed (mm/s) on the first loading ramp from ``start`` (up to the largest
    displacement): its travel over its time, less the holds in it (runs of 10 or more steps
    slower than a quarter of the 95th percentile step speed), so a pause within the ramp does
    not count: a least-squares slope over a ramp-hold-ramp had halved a 4 mm/min ramp's speed."""
    stop = int(np.argmax(disp_mm)) + 1
    if stop - start < 3:
        start = 0
    t, d = time_s[start:stop], disp_mm[start:stop]
    if len(t) < 3 or np.ptp(t) <= 0:
        return None
    dt = np.diff(t)
    ok = dt > 0
    if ok.sum() < 2:
        return None
    dd = np.diff(d)[ok]
    dt = dt[ok]
    still = dd / dt <= 0.25 * np.percentile(dd / dt, 95)
    # a hold is a run of 10 or more still steps (a quantised encoder's single still steps
    # between counts are part of the ramp)
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(np.int8), 0]))
    hold = np.zeros(len(still), bool)
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a >= 10:
            hold[a:b] = True
    if dt[~hold].sum() <= 0:
        return float(np.polyfit(t, d, 1)[0])
    return float(dd[~hold].sum() / dt[~hold].sum())


def _geometry(name: str, given: dict, logfile) -> tuple[dict, dict, dict]:
    """Diameter and height for one log: options/config first (``given``: this log's value of
    each, None where not given), then the log's metadata.  Returns the sizes, where each came
    from, and the metadata's sizes that a given one contradicts by more than
    :data:`GEOMETRY_DISAGREE` (options win; :func:`_geometry_disagrees` says so).

    A cylinder's height is its ``Thickness`` in Bluehill's compression templates
    (``Dimensions : Thickness``): the metadata's thickness is the height where the log
    states no height."""
    out, source, disagree = {}, {}, {}
    for key in ("diameter_mm", "height_mm"):
        v = given[key]
        if v is not None:
            out[key], source[key] = float(v), "option or config"
            meta = logfile.geometry.get(key, logfile.geometry.get("thickness_mm") if key == "height_mm" else None)
            if meta is not None and abs(float(v) / float(meta) - 1.0) > GEOMETRY_DISAGREE:
                disagree[key] = float(meta)
                source[key] += f" (the log's metadata says {float(meta):g} mm)"
        elif key in logfile.geometry:
            out[key], source[key] = float(logfile.geometry[key]), "log metadata"
        elif key == "height_mm" and "thickness_mm" in logfile.geometry:
            out[key] = float(logfile.geometry["thickness_mm"])
            source[key] = "log metadata: Thickness (a cylinder's height in Bluehill's compression templates)"
    missing = [k for k in ("diameter_mm", "height_mm") if k not in out]
    bad = logfile.geometry_invalid
    for k in missing:
        # the dimension the log's metadata states wrongly (an empty or zero Diameter), and no
        # option gives it: said with the line, not as missing
        for key in ((k, "thickness_mm") if k == "height_mm" else (k,)):
            if key in bad:
                why, line = bad[key]
                raise InputError(f"{why}: give --{k.replace('_', '-')} (or {k} in --config)", path=name, line=line)
    if missing:
        opts = " and ".join(f"--{k.replace('_', '-')}" for k in missing)
        raise InputError(f"specimen {' and '.join(missing)} missing: give {opts}, set "
                         f"{' and '.join(missing)} in --config, or state it in the log's metadata",
                         path=name)
    return out, source, disagree


#: Relative difference between a size given as an option (or config) and the log's own
#: metadata beyond which a ``geometry-disagrees`` warning is raised (options win).
GEOMETRY_DISAGREE = 0.02


#: Least number of samples past the contact (and within max_strain) a log must hold to be fitted.
MIN_LOADED_SAMPLES = 10


def _check_distinct(paths: Sequence[str]) -> None:
    """The same record given twice (the same path, or a copy: identical bytes) would be fitted
    as two independent logs, its weight doubled and the intervals narrowed: refused, naming both."""
    import hashlib
    seen: dict[str, str] = {}
    for p in paths:
        try:
            digest = hashlib.sha256(Path(p).read_bytes()).hexdigest()
        except OSError:
            continue                      # the reader names a missing or unreadable file
        if digest in seen:
            raise InputError(f"the same record as {seen[digest]} (identical content): each log is one independent "
                             "test; give it once", path=p)
        seen[digest] = p


def _check_travel(path, disp, contact_mm: float, geo: dict, given: bool, geo_source: dict,
                  max_strain: float | None) -> None:
    """The contact and the specimen's height against the record: a contact past the record's
    travel leaves nothing loaded to fit; a travel past the contact as long as the height
    (nominal strain 1 or more) cannot be a compression of this specimen -- a contact or a
    height that is wrong, not a material (such fits had run to the parameters' bounds, mu
    0.01 Pa, and written material cards with exit 0)."""
    where = "--contact-mm (contact_mm)" if given else "the detected contact"
    h = float(geo["height_mm"])
    end = float(np.max(disp))
    loaded = np.count_nonzero(disp > contact_mm)
    if loaded < MIN_LOADED_SAMPLES:
        raise InputError(f"{where} at {contact_mm:.4g} mm leaves {loaded} samples loaded (the record's travel ends at "
                         f"{end:.4g} mm past its first sample; at least {MIN_LOADED_SAMPLES} are needed)", path=path)
    strain = (end - contact_mm) / h
    if strain >= 1.0:
        raise InputError(f"the travel past {where} ({end - contact_mm:.4g} mm) is "
                         f"{strain:.3g} times the specimen's height ({h:.4g} mm, {geo_source.get('height_mm', '')}): "
                         "a compression cannot exceed the height; check the contact and the height", path=path)
    if max_strain is not None:
        within = np.count_nonzero((disp > contact_mm) & (disp - contact_mm <= max_strain * h))
        if within < MIN_LOADED_SAMPLES:
            raise InputError(f"max_strain {max_strain:g} keeps {within} loaded samples (at least "
                             f"{MIN_LOADED_SAMPLES} are needed: {max_strain * h:.3g} mm of travel past the contact)",
                             path=path)


#: More spikes than this (and than 1 % of the record) is no glitch: the channel is broken or
#: the column is not a load.
def _residual_correlated(final, loop_dict: dict, paths) -> list[dict]:
    """``residual-correlated``: a log's final residual is serially correlated (the load noise
    is not white, or the model misses something smooth), with the effects the loop turned
    down only because its samples are not independent (their delta BIC over 10 counted as
    independent, not on the effective samples).  On AR(1) 0.9 noise a true relaxation (g 0.3,
    tau 5 s) had been turned down so in 6 of 6 logs, mu 531 Pa for 720, unsaid."""
    from ..quality import warning
    f = list(getattr(final, "serial_factors", []) or [])
    lag = final.metrics.get("residual_lag1") or []
    # warned at 3 / sqrt(m) (white noise passes 2 / sqrt(m), where the covariance already
    # changes, in about 2 % of logs; this in about 0.1 %)
    serial = [(Path(str(p)).name, r) for p, r, fi, u in zip(paths, lag, f, final.used)
              if fi < 1.0 and r > 3.0 / np.sqrt(max(int(np.sum(u)), 1))]
    if not serial:
        return []
    rounds = loop_dict.get("tried") or []
    # those the effective samples turned down; not those passing there that a veto turned down
    # (the real Bluehill 2 record's periodic-disturbance, 12.9 on them, no line in the spectrum)
    masked = [c for c in (rounds[-1] if rounds else [])
              if c.get("delta_bic_white", -np.inf) > 10.0 and c.get("delta_bic", np.inf) <= 10.0
              and not c.get("passes")]
    msg = ("fit-ogden: the residual of " + ", ".join(f"{n} (lag-1 {r:.2f})" for n, r in serial)
           + " is serially correlated: the load noise is not white (a filtered load channel, a vibration), or the "
             "model misses something smooth (relaxation, drift, compliance) that cannot be told from such noise; "
             "the intervals allow for the correlation (Newey-West), not for a missing effect")
    if masked:
        msg += ("; turned down only because the samples are not independent: "
                + ", ".join(f"{c['effect']} (delta BIC {c['delta_bic_white']:.3g} counted as independent, "
                            f"{c['delta_bic']:.3g} on the effective samples)" for c in masked)
                + ": fit with each given (--prony, --model) and compare")
    return [warning("residual-correlated", msg, log, logs={n: r for n, r in serial},
                    turned_down=[{"effect": c["effect"], "delta_bic_white": c["delta_bic_white"],
                                  "delta_bic": c["delta_bic"]} for c in masked])]


def _other_optima(final, data, max_strain) -> list[dict]:
    """``another-optimum``: another set of the law's parameters, outside the reported
    intervals, that fits as well within the noise (:func:`~bsipipe.mechanics.fit.other_optima`:
    a law with several Ogden terms, or a one-term law's exponent of the other sign).  The
    intervals describe one basin; the warning gives each parameter's span over both
    (``params_span``: the reported interval and the other optimum's own)."""
    from ..mechanics.fit import other_optima
    from ..quality import warning
    alts = other_optima(data, final, max_strain=max_strain)
    if not alts:
        return []
    a = alts[0]
    span = {k: [min(final.ci95[k][0], v, *a["ci95"].get(k, [v])), max(final.ci95[k][1], v, *a["ci95"].get(k, [v]))]
            for k, v in a["params"].items() if k in final.ci95}
    exps = [k for k in a["params"] if k.startswith("alpha")]
    what = (f"the sign of {exps[0]} is not determined by these logs" if len(exps) == 1
            else f"the {final.spec.law} law's parameters are not determined by these logs")
    return [warning(
        "another-optimum",
        f"fit-ogden: {what}: "
        + ", ".join(f"{k} {v:.4g}" for k, v in a["params"].items())
        + f" fits as well within the noise (its weighted sum of squares {a['delta_sse_over_s2']:.2g} noise variances "
          "above the best, inside the parameters' joint 95 % region), outside the reported intervals, which "
          "describe one basin only; over both, "
        + ", ".join(f"{k} spans [{lo:.4g}, {hi:.4g}]" for k, (lo, hi) in span.items())
        + ("; a longer ramp, or another speed or mode, would tell them apart" if len(exps) == 1
           else "; another test (speed, mode) or a law with fewer terms would tell them apart"),
        log, alternatives=alts, params_span=span)]


MAX_SPIKES = 5


def _read_logs(paths: Sequence[str], cfg: FitOgdenConfig, per_log: dict[str, list]):
    """The logs and their inputs records; ``per_log``: each :data:`PER_LOG` key's value per
    log (:func:`_per_log`)."""
    from ..io.machine_log import read_machine_log
    from ..mechanics.contact import (ContactNotInRecord, NoLoadingRamp, detect_contact, force_noise, lift_off,
                                     loading_ramps)
    from ..mechanics.fit import MIN_UNLOADED_SAMPLES, LogData

    logs, inputs = [], []
    dims = {k: per_log[k] for k in ("diameter_mm", "height_mm")}
    for i, (p, given) in enumerate(zip(paths, per_log["contact_mm"])):
        ml = read_machine_log(p)
        geo, geo_source, geo_disagree = _geometry(str(p), {k: v[i] for k, v in dims.items()}, ml)
        disp, force = ml.compression()
        time_s = ml.time_s
        rows = np.arange(len(ml))                # the record's sample of each one kept
        record: dict = {"n_record": int(len(ml))}
        for key, spikes, what, values, unit in (
                ("spikes_left_out", ml.spikes, "load samples are over-range codes (|F| >= 1e30) or glitches",
                 ml.load_n, "load_n"),
                ("extension_spikes_left_out", ml.extension_spikes, "extension samples are glitches",
                 ml.extension_mm, "extension_mm")):
            if spikes.any():
                lines = [ml.line_of(k) for k in np.flatnonzero(spikes)]
                if spikes.sum() > max(MAX_SPIKES, 0.01 * len(ml)):
                    raise InputError(f"{int(spikes.sum())} {what} (runs of 1 to 3 samples that jump away and "
                                     f"back; lines {listed(lines, 8)}): the channel did not record the test "
                                     "there; check the export", path=p)
                record[key] = {"lines": lines, unit: [float(v) for v in values[spikes]]}
        bad = ml.spikes | ml.extension_spikes
        if bad.any():
            keep = ~bad
            rows, time_s, disp, force = rows[keep], time_s[keep], disp[keep], force[keep]
        ramps = loading_ramps(disp)
        record["loading_ramps"] = len(ramps)
        if len(ramps) > 1:
            # A cyclic record: later cycles follow a loading history (preconditioning, set) that
            # the first loading does not have; the first loading ramp is what is fitted.
            stop = ramps[0][1]
            time_s, disp, force = time_s[:stop], disp[:stop], force[:stop]
            record["fitted_part"] = (f"first loading ramp only: samples 0-{rows[stop - 1]} of {len(ml)} "
                                     f"(lines {ml.line_of(rows[0])}-{ml.line_of(rows[stop - 1])}; the record has "
                                     f"{len(ramps)} loading ramps)")
        else:
            record["fitted_part"] = "whole record"
        clip = clipped_top(disp, force)
        if clip is not None:
            # the load cell (or the export's range) clipped: the samples from the first at the
            # clip level on are no measurement of the tissue; the fit stops before them
            first = clip["first"]
            record["load_clipped"] = {**{k: v for k, v in clip.items() if k != "first"},
                                      "first_line": ml.line_of(rows[first]),
                                      "displacement_mm": float(disp[first])}
            time_s, disp, force = time_s[:first], disp[:first], force[:first]
            record["fitted_part"] += (f"; up to line {ml.line_of(rows[first - 1])}, the last sample before the load "
                                      f"clipped at {clip['level_n']:.6g} N")
        coarse = load_resolution(disp, force)
        if coarse is not None:
            said = (f"the load is written in steps of {coarse['quantum_n']:.4g} N (the smallest step between its "
                    f"values; {coarse['levels']:.0f} steps over its range; its noise, {1e3 * coarse['noise_n']:.2g} mN, "
                    f"under half a step, does not dither them): its first step past the start of the loading spans "
                    f"{coarse['first_step_mm']:.3g} mm of the {coarse['travel_mm']:.3g} mm of travel after it")
            if coarse["share"] > RESOLUTION_REFUSE_SHARE:
                raise InputError(f"{said}, more than {RESOLUTION_REFUSE_SHARE:.0%}: the record cannot locate the "
                                 "contact or the low-strain stiffness (the staircase is no noise a fit can average); "
                                 "export the load with more decimals (in N rather than kN)", path=p)
            record["load_resolution"] = {**coarse, "message": said}
        name = Path(p).stem
        tared = False
        if given is None:
            try:
                contact = detect_contact(time_s, disp, force)
            except ContactNotInRecord as e:
                # exit 1, as the acceptance check takes it for the real preloaded Bluehill 2 file
                # (a probe had asked for 2: the record is valid, the fit needs what it cannot show)
                raise ProcessingError(
                    f"contact detection: {e.message}: give it with --contact-mm D (config key contact_mm), the "
                    f"displacement in mm past the first sample, positive in compression, at which the platen "
                    f"touched (negative: before the record began)", path=p) from None
            except NoLoadingRamp as e:      # the record cannot hold a contact: bad input
                raise InputError(f"contact detection: {e.message}", path=p) from None
            except ProcessingError as e:
                raise ProcessingError(f"contact detection: {e.message}", path=p) from None
            except ValueError as e:
                raise InputError(f"contact detection: {e}", path=p) from None
            contact_mm, contact_info, start = contact.displacement_mm, contact.to_dict(), contact.index
            # The detector's standard deviation and noise make the contact a refined nuisance
            # parameter of every fit (bsipipe.mechanics.fit, "Contact").
            sd, noise = contact.displacement_sd_mm, contact.force_noise_n
            baseline = {"level_n": contact.baseline_n,
                        "source": "the hinge fit's level before the detected contact"}
        else:
            contact_mm, sd, noise = given, None, None
            start = int(np.argmax(disp >= given)) if np.any(disp >= given) else len(disp)
            before = disp < given
            contact_info = {"method": "given (--contact-mm / contact_mm)", "displacement_mm": given,
                            "before_first_sample": bool(given < disp[0]),
                            "extension_mm": float(ml.extension_mm[0] + ml.displacement_sign * given)}
            if before.sum() >= MIN_UNLOADED_SAMPLES:
                baseline = {"level_n": float(np.median(force[before])),
                            "source": f"median of the {int(before.sum())} samples before the given contact"}
            elif given < disp[0] and _zeroed_loaded(force):
                # the record starts compressed (the contact before it) yet reads no force: the
                # cell was zeroed there, and the law's own force at the first sample is taken out
                tared = True
                baseline = {"level_n": 0.0,
                            "source": "the record starts compressed (the given contact is before its first sample) "
                                      "yet reads about 0 N: the load cell was zeroed at the first sample; the "
                                      "model's force there is taken out of every sample (tared_at_start), and the "
                                      "zero's error, that sample's noise, is fitted (tare_n)"}
            else:
                baseline = {"level_n": 0.0,
                            "source": "assumed 0 N (the load cell zeroed unloaded): the record has "
                                      f"{int(before.sum())} samples before the given contact, too few to measure it"}
        off = lift_off(disp, force, baseline["level_n"], noise if noise else force_noise(force))
        if off is not None:
            # the platen left the specimen while retracting: the force at the cell's zero from
            # there on measures no tissue (the model would pull on it); the fit stops before it
            record["lift_off"] = {"line": ml.line_of(rows[off]), "time_s": float(time_s[off]),
                                  "extension_mm": float(ml.extension_mm[rows[off]]),
                                  "displacement_mm": float(disp[off]), "n_left_out": int(len(disp) - off),
                                  "floor_n": float(baseline["level_n"])}
            time_s, disp, force = time_s[:off], disp[:off], force[:off]
            record["fitted_part"] += (f"; up to line {ml.line_of(rows[off - 1])}, the last sample before the platen "
                                      f"left the specimen on unloading (at {record['lift_off']['time_s']:.4g} s, "
                                      f"extension {record['lift_off']['extension_mm']:.4g} mm)")
        _check_travel(p, disp, contact_mm, geo, given is not None, geo_source, cfg.max_strain)
        speed = _loading_speed(time_s, disp, start)
        logs.append(LogData(name, time_s, disp, force, geo["diameter_mm"], geo["height_mm"],
                            contact_mm, speed, sd, noise, tared_at_start=tared))
        inputs.append({"path": str(p), "layout": ml.layout, "speed_mm_s": speed,
                       "contact_mm": contact_mm, "n_points": int(len(disp)), **record,
                       "diameter_mm": geo["diameter_mm"], "height_mm": geo["height_mm"],
                       "geometry_source": geo_source, "geometry_metadata_disagrees": geo_disagree,
                       "contact": contact_info, "force_baseline": baseline,
                       "sign_from": ml.dialect.get("sign_from"),
                       "specimen_label": ml.metadata.get("Specimen label")})
    return logs, inputs


def _zeroed_loaded(force: np.ndarray, n: int = 10) -> bool:
    """Whether a record that starts compressed reads about zero force at its start: a line
    through its first ``n`` samples (the force already rising) meets the first sample within
    3 of their scatter about it and 1 % of the record's force range.  A cell left unzeroed
    reads the preload there (a 0.22 mm preload of an 18 x 12 mm brain cylinder: about 10 mN,
    twenty times the noise)."""
    head = np.asarray(force[:n], float)
    if len(head) < 4:
        return False
    k = np.arange(len(head), dtype=float)
    slope, level = np.polyfit(k, head, 1)
    scatter = float(np.std(head - (level + slope * k), ddof=2))
    return abs(level) <= 3.0 * max(scatter, 1e-12) and abs(level) <= 0.01 * float(np.ptp(force))


def _read_tables(paths: Sequence[str], modes: Sequence[str], cfg: FitConfig):
    from ..io.stress_table import read_stress_table

    if modes and len(modes) not in (1, len(paths)):
        raise InputError(f"{len(modes)} --mode options for {len(paths)} tables: give one --mode for every "
                         f"table, or one for all", path=paths[0])
    tables, inputs = [], []
    for i, p in enumerate(paths):
        mode = modes[i] if len(modes) == len(paths) else (modes[0] if modes else cfg.mode)
        t = read_stress_table(p, mode)
        strain = t["stretch"] - np.where(t["mode"] == "simple-shear", 0.0, 1.0)     # gamma in simple shear
        if not ((t["nominal_stress_pa"] != 0) & (strain != 0)).any():
            raise InputError("no loaded row: every row has zero stress or zero strain (stretch 1, or gamma 0 in "
                             "simple shear), so no law can be fitted", path=p)
        if cfg.max_strain is not None:
            t = t[np.abs(strain) <= cfg.max_strain]
            if t.empty:
                raise InputError(f"no row within --max-strain {cfg.max_strain}", path=p)
        tables.append(t)
        inputs.append({"path": str(p), "speed_mm_s": None, "contact_mm": None, "n_points": int(len(t)),
                       "modes": sorted(set(t["mode"])), "stress_sign_turned": t.attrs.get("sign_turned", []),
                       "stress_magnitudes": t.attrs.get("magnitudes", [])})
    return tables, inputs


def _read_width(path) -> Any:
    """The side camera's width series ``time_s,width_mm`` (for the boundary evidence)."""
    import pandas as pd

    from ..mechanics.effects import WidthSeries

    try:
        df = pd.read_csv(path, comment="#")
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, ValueError, pd.errors.ParserError) as e:
        raise InputError(f"cannot read the width series: {e}", path=path) from None
    cols = {c.strip().lower(): c for c in df.columns}
    missing = [c for c in ("time_s", "width_mm") if c not in cols]
    if missing:
        raise InputError(f"missing column(s) {missing}; expected time_s,width_mm", path=path, line=1)
    out = {}
    for c in ("time_s", "width_mm"):
        v = pd.to_numeric(df[cols[c]], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(v.to_numpy(float)))
        if len(bad):
            raise InputError(f"column {c} is not a finite number", path=path, line=int(bad[0]) + 2)
        out[c] = v.to_numpy(float)
    try:
        return WidthSeries(out["time_s"], out["width_mm"], 0)
    except ValueError as e:
        raise InputError(str(e), path=path) from None


def _close_loop(kind: str, data, spec0, *, loop: bool, boundary_declared: bool, width=None,
                max_strain: float | None = None, law: str | None = None):
    """Fit the declared model and, with ``loop``, close the loop; returns ``(baseline, final, loop_dict)``.

    The one place the command meets the loop framework (:mod:`bsipipe.loop`,
    :mod:`bsipipe.mechanics.effects`): machine logs try every effect of
    :func:`~bsipipe.mechanics.effects.mechanics_effects` (``no-slip-platens`` only when
    ``--boundary`` was not given, with the ``--width-csv`` series as its evidence), stress
    tables ``model-order``.  ``--no-loop`` fits the declared model only and still reports the
    loop section in the contract's shape (``baseline`` = ``final``, no steps) with the
    residual-structure tests of the declared model.
    """
    from ..loop import run_loop
    from ..mechanics import effects
    from ..mechanics.fit import fit_logs, fit_tables

    if kind == "logs":
        if loop:
            report = effects.close_loop_logs(data, spec0, boundary_declared=boundary_declared, width=width,
                                             max_strain=max_strain)
        else:
            res = fit_logs(data, spec0, max_strain=max_strain)
            report = run_loop(lambda s: res, spec0, [],
                              covariates=lambda r: effects.log_covariates(data, r.used),
                              describe=lambda s: s.describe(), unit="n")
            report.stopped_because = "--no-loop: the declared model only"
    else:
        if loop:
            report = effects.close_loop_tables(data, law)
        else:
            res = fit_tables(data, law)
            report = run_loop(lambda s: res, law, [], covariates=effects.table_covariates, describe=str, unit="pa")
            report.stopped_because = "--no-loop: the declared model only"
    return report.baseline.fit, report.final.fit, report.to_dict()


def _loop_files(loop_dict: dict, baseline, final, labels) -> tuple[str, Any]:
    """``loop.md`` (the steps' table) and ``loop.png`` (data, fits and residuals before and after)."""
    from ..report.loop_report import fit_loop_series, loop_figure, loop_markdown

    title = "fit-ogden: closing the loop"
    unit = "N" if getattr(final, "kind", "logs") == "logs" else "Pa"
    fig = loop_figure(fit_loop_series(baseline, final, labels),
                      title=f"{loop_dict['baseline']['model']} -> {loop_dict['final']['model']}", unit_label=f"({unit})")
    return loop_markdown(loop_dict, title=title), fig


def _cards(result) -> dict[str, str]:
    """ABAQUS, LS-DYNA and FEBio material cards of the final model (Prony terms with g = 0 dropped)."""
    from ..io.abaqus import abaqus_material
    from ..io.febio import febio_material
    from ..io.lsdyna import lsdyna_material

    tissue = result.tissue_params()
    prony = [t for t in tissue.pop("prony", []) if t["g"] > 0.0]
    law = result.spec.law
    try:
        return {"material.inp": abaqus_material(law, tissue, prony or None),
                "material.k": lsdyna_material(law, tissue, prony or None),
                "material.feb.xml": febio_material(law, tissue, prony or None)}
    except ValueError as e:
        raise ProcessingError(f"the fitted parameters make no valid FE material: {e}") from None


#: A measured unloaded force the model leaves out is warned about beyond this share of the
#: log's force range (and 5 times the load noise where measured).
BASELINE_WARN_FRACTION = 0.01


#: The largest share of a log's travel past the contact that a fitted machine compliance may
#: take as the frame's deflection at the peak force before it is warned about.
COMPLIANCE_MAX_SHARE = 0.2


#: A fitted load-cell drift over a log may move the zero by at most this share of its peak force.
DRIFT_MAX_SHARE = 0.05


def _disturbance_lines(final, data) -> dict | None:
    """With ``periodic-disturbance`` in the final model, which logs carry it: each log's fitted
    sinusoid and its line test (:func:`~bsipipe.mechanics.fit.disturbance_line_test`, p times
    the number of logs), a ``line`` where p is below the loop's level.  With several logs fitted
    together one line keeps the effect, and the others' sinusoids fit their own noise (a hum of
    2 mN on one of two logs: 1.97 mN at 0.498 Hz there, p below 1e-12; 0.26 mN at 14.95 Hz on
    the clean one, no line): this says which is which."""
    if not getattr(final.spec, "periodic_disturbance", False):
        return None
    from ..mechanics.effects import DISTURBANCE_LINE_P, disturbance_lines
    keys = ("log", "amplitude_n", "hz", "phase_rad", "line_ratio", "p", "line")
    logs = [{k: t[k] for k in keys} for t in disturbance_lines(data, final)]
    lines = [x["log"] for x in logs if x["line"]]
    log.info("fit-ogden: periodic disturbance a line in %s%s", ", ".join(lines) or "no log",
             "" if len(lines) == len(logs) else
             f"; its sinusoid fits noise in {', '.join(x['log'] for x in logs if not x['line'])}")
    return {"logs": logs, "with_line": lines,
            "rule": f"a line where the sinusoid's periodogram power over the mean of its neighbours has family-wise "
                    f"p (frequencies searched, times the logs) below {DISTURBANCE_LINE_P:g}"}


def _drift_implausible(final, data) -> list[dict]:
    """An ``implausible-drift`` warning where the fitted ``load-baseline-drift`` moves a log's
    load-cell zero over its record by more than :data:`DRIFT_MAX_SHARE` of its peak force: a
    cell's zero drifts by a fraction of a per cent of its range, so the residual the effect
    took is another one's (three specimens fitted together, one 10 % shorter than declared:
    -1.1 mN/s, 70 mN over the log, a tenth of its peak force, and alpha -4.92 [-4.97, -4.87]
    for -4.7, with nothing said)."""
    from ..quality import warning
    out = []
    for i, lg in enumerate(data):
        b1 = float(final.log_params(i).get("drift_n_per_s", 0.0))
        span = float(lg.time_s[-1] - lg.time_s[0])
        peak = float(np.max(np.abs(lg.force_n))) if len(lg.force_n) else 0.0
        moved = abs(b1) * span
        if peak > 0 and moved > DRIFT_MAX_SHARE * peak:
            out.append(warning(
                "implausible-drift",
                f"fit-ogden: {lg.name}: the fitted load-cell drift {1e3 * b1:.3g} mN/s moves the zero by "
                f"{1e3 * moved:.3g} mN over the {span:.4g} s record, {100 * moved / peak:.0f} % of its peak force: "
                "no load cell drifts so; the residual it took is likely another effect's (a specimen's size given "
                "wrong, specimens that differ, a contact placed wrong): check the sizes, or fit the logs one by one",
                log, log_name=lg.name, drift_n_per_s=b1, moved_n=moved, peak_n=peak))
    return out


def _boundary_undeclared(data) -> list[dict]:
    """A ``boundary-undeclared`` warning for logs fitted frictionless without ``--boundary``
    where nothing could decide it (no width series, one height/diameter): bonded (sandpaper)
    platens make the homogeneous formula overestimate mu by about 20-35 % at H/D 1 and
    60-130 % at 0.5, and the force of one shape cannot show it (a no-slip 18 x 6 mm specimen
    had been fitted at 2.2 times its modulus, exit 0, the hint only an INFO log line)."""
    from ..mechanics.effects import NO_SLIP_MIN_ASPECT_SPREAD
    from ..quality import warning
    aspects = sorted({round(lg.aspect, 3) for lg in data})
    if aspects[-1] / aspects[0] >= NO_SLIP_MIN_ASPECT_SPREAD:
        return []                          # the loop tried no-slip-platens on the shapes and kept frictionless
    return [warning(
        "boundary-undeclared",
        "fit-ogden: the platens' boundary was not declared and the logs cannot show it (one height/diameter, "
        f"{', '.join(f'{a:g}' for a in aspects)}, no --width-csv): fitted as frictionless (free to spread); if "
        "the specimen was bonded or on sandpaper (no-slip), give --boundary no-slip: the frictionless formula "
        "overestimates mu by about 20-35 % at height/diameter 1 and 60-130 % at 0.5", log, aspect=aspects)]


def _compliance_implausible(c_mm_per_n: float, data) -> list[dict]:
    """An ``implausible-compliance`` warning where the fitted ``machine-compliance`` makes the
    frame deflect, at a log's peak force, by more than :data:`COMPLIANCE_MAX_SHARE` of its
    travel past the contact: no testing frame is that soft next to its specimen, so the
    residual the effect took is another one's (a record that starts loaded, a contact placed
    wrong, a specimen that is no hyperelastic solid).  The real Bluehill export: 0.108 mm/N,
    5.7 mm of 10 mm at 53 N, a modulus of 4.1 MPa for 53 kPa."""
    from ..quality import warning
    out = []
    c = float(c_mm_per_n)
    for lg in data:
        loaded = lg.displacement_mm > lg.contact_mm
        if not loaded.any() or c <= 0:
            continue
        travel = float(np.max(lg.displacement_mm[loaded]) - lg.contact_mm)
        deflection = c * float(np.max(lg.force_n[loaded]))
        if travel > 0 and deflection > COMPLIANCE_MAX_SHARE * travel:
            out.append(warning(
                "implausible-compliance",
                f"fit-ogden: {lg.name}: the fitted machine compliance {c:.3g} mm/N deflects the frame by "
                f"{deflection:.3g} mm at the peak force, {100 * deflection / travel:.0f} % of the {travel:.3g} mm "
                "travel past the contact: no testing frame is that soft beside its specimen; the residual it took "
                "is likely another effect's (a record that starts loaded, the contact placed wrong, a specimen that "
                "is no hyperelastic solid): check the contact, or fit with --no-loop and read the residual",
                log, log_name=lg.name, compliance_mm_per_n=c, deflection_mm=deflection, travel_mm=travel))
    return out


def _softening_hint(data) -> tuple[int, str] | None:
    """Why a fit failed, where a log's force rises ever more slowly past the contact (the
    second half of its travel adds less than 0.8 of the first's force per millimetre): brain
    tissue in unconfined compression stiffens, so such a record is a tension test (or its
    channels' signs read the wrong way), which the compression law cannot fit.  Returns the
    log's index and the words, or None."""
    for i, lg in enumerate(data):
        past = lg.displacement_mm > lg.contact_mm
        x = lg.displacement_mm[past] - lg.contact_mm
        f = np.abs(lg.force_n[past])
        if len(x) < 20 or np.ptp(x) <= 0:
            continue
        half = x <= 0.5 * x.max()
        if half.sum() < 5 or (~half).sum() < 5:
            continue
        k1 = np.polyfit(x[half], f[half], 1)[0]
        k2 = np.polyfit(x[~half], f[~half], 1)[0]
        if k1 > 0 and k2 < 0.8 * k1:
            return i, (f"{lg.name}'s force rises ever more slowly past the contact (slope {k2:.3g} N/mm over the "
                       f"second half of its travel, {k1:.3g} over the first): brain tissue in unconfined compression "
                       "stiffens, so this looks like a tension test, or its extension or load read with the wrong "
                       "sign (fit-ogden fits compression; name the columns, e.g. 'Compressive extension', or give a "
                       "stress-stretch table with --stress-stretch)")
    return None


def _raise_if_softening(what: str, kind: str, data, paths) -> None:
    """Exit 2 for a failed fit (``what`` went wrong) of a log :func:`_softening_hint` names."""
    hint = _softening_hint(data) if kind == "logs" else None
    if hint is not None:
        raise InputError(f"{what}, and {hint[1]}", path=paths[hint[0]]) from None


def _geometry_disagrees(input_info: list[dict]) -> list[dict]:
    """A ``geometry-disagrees`` warning for each log whose size given as an option or in the
    config differs from its own metadata by more than :data:`GEOMETRY_DISAGREE` (the option is
    used: 20 x 10 mm given for an 18 x 12 mm specimen fits mu 486 Pa for 720)."""
    from ..quality import warning
    out = []
    for info in input_info:
        said = info.get("geometry_metadata_disagrees") or {}
        if said:
            out.append(warning(
                "geometry-disagrees",
                f"fit-ogden: {Path(info['path']).name}: " + "; ".join(
                    f"{k} {info[k]:g} given, {meta:g} mm in the log's metadata" for k, meta in said.items())
                + ": the size given is used (options win); stress and stretch scale with it, so check which is "
                  "the specimen's", log, log_name=info["path"], given={k: info[k] for k in said}))
    return out


def _several_ramps(input_info: list[dict]) -> list[dict]:
    """A ``first-ramp-only`` warning for each log with more than one loading ramp: the first is
    fitted (the tissue before any preconditioning), which the usual protocol does not (it fits
    the response after preconditioning cycles); the fitted part had been said only in
    ``inputs[].fitted_part`` (the probe: two preconditioning cycles to 10 % strain, the first
    of them fitted, mu 729, alpha -4.22 for -4.70, with no warning)."""
    from ..quality import warning
    return [warning(
        "first-ramp-only",
        f"fit-ogden: {Path(info['path']).name}: the record has {info['loading_ramps']} loading ramps and only the "
        "first is fitted (the tissue before any preconditioning); to fit the response after preconditioning "
        "cycles, cut the record to the ramp wanted", log, log_name=info["path"], loading_ramps=info["loading_ramps"])
        for info in input_info if int(info.get("loading_ramps", 1) or 1) > 1]


def _log_warnings(input_info: list[dict], key: str, code: str, text, fields) -> list[dict]:
    """A ``code`` warning for each log whose ``input_info`` entry holds ``key`` (``c``): ``text(c)``
    its message after the log's name, ``fields(c)`` its keys beside ``log_name``."""
    from ..quality import warning
    return [warning(code, f"fit-ogden: {Path(info['path']).name}: {text(info[key])}", log, log_name=info["path"],
                    **fields(info[key]))
            for info in input_info if info.get(key)]


def _load_clipped(input_info: list[dict]) -> list[dict]:
    """A ``load-clipped`` warning for each log whose force stops at a ceiling
    (:func:`clipped_top`): the fit ends before it."""
    return _log_warnings(
        input_info, "load_clipped", "load-clipped",
        lambda c: (f"the load reads {c['level_n']:.6g} N, exactly, on {c['n_samples']} samples from line "
                   f"{c['first_line']} while the platen travels {c['travel_mm']:.3g} mm on, over which the samples "
                   f"before rise {c['expected_rise_n']:.3g} N: the load cell (or the export) clipped at the end of "
                   f"its range; the fit stops before it, at {c['displacement_mm']:.4g} mm; use a larger cell or a "
                   "shallower test to fit the rest"),
        lambda c: {"level_n": c["level_n"], "n_samples": c["n_samples"], "first_line": c["first_line"]})


def _load_resolution(input_info: list[dict]) -> list[dict]:
    """A ``load-resolution`` warning for each log whose load is written so coarsely that its
    first step spans over a tenth of the loading travel
    (:func:`~bsipipe.io.machine_log.load_resolution`; over a fifth is exit 2)."""
    return _log_warnings(
        input_info, "load_resolution", "load-resolution",
        lambda c: (f"{c['message']}: the contact and the low-strain stiffness are located no better than that "
                   "step, and the staircase is no random error (the intervals do not allow for it); export the "
                   "load with more decimals"),
        lambda c: {"quantum_n": c["quantum_n"], "share": c["share"]})


def _lift_off(input_info: list[dict]) -> list[dict]:
    """A ``platen-lift-off`` warning for each log whose force sits at the load cell's zero on
    unloading while the crosshead still retracts (:func:`~bsipipe.mechanics.contact.lift_off`):
    the platen left the specimen there, and the fit stops before it."""
    return _log_warnings(
        input_info, "lift_off", "platen-lift-off",
        lambda c: (f"on unloading the load sits at its unloaded level ({c['floor_n']:.3g} N) from line {c['line']} "
                   f"(time {c['time_s']:.4g} s, extension {c['extension_mm']:.4g} mm) while the crosshead still "
                   "retracts, where loading had pressed the specimen well above the noise: the platen left the "
                   "specimen there (it recovers more slowly than the platen retracts); its "
                   f"{c['n_left_out']} samples from there on measure no tissue and are left out of the fit"),
        lambda c: {"line": c["line"], "time_s": c["time_s"], "extension_mm": c["extension_mm"],
                   "n_left_out": c["n_left_out"]})


def _spikes_left_out(input_info: list[dict]) -> list[dict]:
    """``load-spikes`` and ``extension-spikes`` warnings: the samples of a log left out of the
    fit as over-range codes or glitches (:func:`bsipipe.io.machine_log.load_spikes`,
    :func:`~bsipipe.io.machine_log.channel_spikes`), by line."""
    from ..quality import warning
    out = []
    for info in input_info:
        for key, code, what, unit, u in (("spikes_left_out", "load-spikes", "load", "load_n", "N"),
                                         ("extension_spikes_left_out", "extension-spikes", "extension",
                                          "extension_mm", "mm")):
            sp = info.get(key)
            if sp:
                kind = "over-range codes or glitches" if code == "load-spikes" else "glitches"
                out.append(warning(
                    code,
                    f"fit-ogden: {Path(info['path']).name}: {len(sp['lines'])} {what} sample(s) left out of the "
                    f"fit, {kind} (runs of 1 to 3 samples that jump away and back; line(s) "
                    f"{listed(sp['lines'], 8)}: " + ", ".join(f"{v:.4g} {u}" for v in sp[unit][:8]) + ")",
                    log, path=str(info["path"]), lines=sp["lines"]))
    return out


#: A fitted shear modulus below this (Pa) is no modulus: the fit ran to its bound.
MIN_MODULUS_PA = 1e-6


def _moduli(params: dict) -> list[float]:
    """The fit's Ogden, neo-Hookean or Mooney-Rivlin moduli (``mu*_pa``, ``c*_pa``)."""
    import re
    return [float(v) for k, v in params.items() if re.fullmatch(r"(mu\d*|c\d+)_pa", k) and isinstance(v, (int, float))]


def _all_moduli_zero(params: dict) -> bool:
    """Every modulus below :data:`MIN_MODULUS_PA`: the fit failed (:func:`_no_modulus`)."""
    mus = _moduli(params)
    return bool(mus) and max(abs(m) for m in mus) < MIN_MODULUS_PA


def _no_modulus(params: dict, warnings: list[dict], path) -> None:
    """A fit whose every Ogden (or neo-Hookean, Mooney-Rivlin) modulus ran to zero is a failed
    fit (exit 1), not a material card: an untared 2.5 N load-cell offset with --no-loop had
    written mu = 6.7e-14 Pa with exit 0 (its warnings said why; they are the message now)."""
    if _all_moduli_zero(params):
        mus = _moduli(params)
        why = "; ".join(w["message"] for w in warnings if w["code"] not in ("parameter-undetermined",
                                                                           "interval-spans-zero",
                                                                           "parameter-correlation"))
        raise ProcessingError(f"the fit ran every modulus to zero ({', '.join(f'{m:.3g}' for m in mus)} Pa): the "
                              "force is not the law's at these settings" + (f"; {why}" if why else ""), path=path)


def _declared_boundary_check(final, data, width, width_csv) -> dict | None:
    """A declared ``--boundary`` weighed against the ``--width-csv`` series (the loop tries
    ``no-slip-platens`` only where the boundary is not declared): the width's evidence for
    bonded platens (:func:`bsipipe.mechanics.effects.width_evidence`, both shapes from the
    final fit's stretch), and a ``boundary-contradicted`` warning where it says the other
    boundary with delta BIC over 10.  A frictionless record declared no-slip, its width
    exactly D / sqrt(stretch), had given mu 527 Pa (truth 720) and a spurious compliance
    without a word."""
    from types import SimpleNamespace

    from ..mechanics.effects import width_evidence
    from ..quality import warning
    st = SimpleNamespace(fit=final, spec=final.spec)
    try:
        ev = width_evidence(width, data)(st, st)
    except (ValueError, KeyError, ArithmeticError):
        return None
    if ev is None:
        return None
    declared = final.spec.boundary
    out = {"evidence": {**ev, "declared": declared,
                        "note": "delta BIC > 0 favours bonded (no-slip) platens, < 0 a homogeneous (frictionless) "
                                "compression"}}
    d = ev["delta_bic"]
    other = "frictionless" if declared == "no-slip" else "no-slip"
    if (declared == "no-slip" and d < -10) or (declared != "no-slip" and d > 10):
        out["warning"] = warning(
            "boundary-contradicted",
            f"fit-ogden: the width series {Path(str(width_csv)).name} contradicts --boundary {declared}: it fits the "
            f"{other} shape (width RMSE {ev['rmse_width_homogeneous_mm']:.3g} mm homogeneous, "
            f"{ev['rmse_width_no_slip_mm']:.3g} mm barrelled; delta BIC {d:.1f}); the parameters assume "
            f"{declared}: refit with --boundary {other}, or leave --boundary out and let the loop weigh it",
            log, delta_bic=d, declared=declared)
    return out


def _contacts_moved(input_info: list[dict]) -> list[dict]:
    """``contact-moved`` warnings: a fit that moved a detected contact more than
    :data:`CONTACT_MOVED_SD` of the detector's standard deviations (the data and the detector
    disagree: a wrong diameter or height, given for another log, or a force the law does not
    follow near the contact)."""
    from ..quality import warning
    out = []
    for info in input_info:
        z = info.get("contact_shift_sd")
        if z is not None and abs(z) > CONTACT_MOVED_SD:
            out.append(warning(
                "contact-moved",
                f"fit-ogden: {Path(info['path']).name}: the fit moved the detected contact by "
                f"{info['contact_shift_mm']:+.4g} mm, {abs(z):.0f} times the detector's standard deviation "
                f"({info['contact_mm']:.4g} -> {info['contact_refined_mm']:.4g} mm): the force data and the detector "
                "disagree; check the specimen's diameter and height for this log, or give the contact "
                "(--contact-mm)", log, path=str(info["path"]), shift_mm=info["contact_shift_mm"], shift_sd=z))
    return out


def _stress_sign_turned(input_info: list[dict]) -> list[dict]:
    """``stress-sign`` warnings: a table that wrote its loaded rows with the sign opposite to the
    laws' (compression positive) is fitted with its sign turned, and said so; one that gives
    magnitudes (every stress positive) with its compression rows turned."""
    from ..quality import warning
    out = []
    for info in input_info:
        whole = info.get("stress_sign_turned") or []
        parts = info.get("stress_magnitudes") or []
        said = []
        if whole:
            said.append(f"every loaded {', '.join(whole)} row has the stress's sign opposite to its strain's "
                        "(compression written positive): fitted with the sign turned")
        if parts:
            said.append(f"every stress of {', '.join(parts)} is positive, in tension and "
                        "compression alike (magnitudes): the compression rows fitted with the sign turned")
        if said:
            out.append(warning("stress-sign", f"fit-ogden: {Path(info['path']).name}: " + "; ".join(said)
                               + " (tension positive, compression negative)", log, path=str(info["path"]),
                               modes=whole, magnitudes=parts))
    return out


def _baseline_ignored(input_info: list[dict], data) -> list[dict]:
    """``force-baseline-ignored`` warnings: a log whose samples before the contact measure an
    unloaded force away from zero (a load cell not tared, an offset) fitted by a model that
    takes the load cell's zero as the unloaded force (the declared model, ``--no-loop``, or a
    loop that did not take ``load-baseline-drift``): every force is then off by that level,
    and the fitted parameters and contact with it."""
    from ..quality import warning
    out = []
    for info, lg in zip(input_info, data):
        b = info.get("force_baseline") or {}
        level = float(b.get("level_n", 0.0))
        if b.get("source", "").startswith("assumed") or level == 0.0:
            continue
        span = float(np.ptp(lg.force_n)) if len(lg.force_n) else 0.0
        noise = lg.force_noise_n
        if abs(level) > BASELINE_WARN_FRACTION * span and (noise is None or abs(level) > 5.0 * noise):
            out.append(warning(
                "force-baseline-ignored",
                f"fit-ogden: {Path(info['path']).name}: the samples before the contact measure an unloaded force of "
                f"{level:.4g} N ({100 * abs(level) / span:.2g} % of the log's force range), which the model takes as "
                "0 N (the load cell's zero): every force of the fit is off by it; tare the load cell, or let the loop "
                "fit it (load-baseline-drift; not with --no-loop)", log, path=str(info["path"]), level_n=level,
                force_range_n=span))
    return out


def _fit_quality(final) -> list[dict]:
    """Identifiability warnings of the final fit (:func:`bsipipe.quality.fit_warnings`): the
    material parameters (the law's and the Prony fractions) must not have an interval
    spanning zero; no two fitted parameters may be correlated beyond |r| = 0.99."""
    import re

    from ..mechanics.hyperelastic import get_law
    from ..quality import fit_warnings

    material = set(get_law(final.spec.law).param_names)
    zero = [n for n in final.param_names if n in material or re.fullmatch(r"g\d+", n)]
    return fit_warnings(final.param_names, final.cov, final.ci95, zero_checked=zero, logger=log)


#: A contact the fit moves more than this many of the detector's standard deviations from the
#: detected one, under the prior, is a warning (``contact-moved``): the force data and the
#: detector disagree far beyond a viscoelastic onset's bias (4.3 sd on the sample study's
#: 1 mm/min log).
CONTACT_MOVED_SD = 10.0


def _refined_contact(final, i: int, n_logs: int, detected_mm: float, given: bool = False,
                     sd_mm: float | None = None) -> dict:
    """Log ``i``'s contact after the fit: the detected one plus the fitted shift, its 95 % interval,
    how it was refined (under the detector's prior of standard deviation ``sd_mm``, and by how
    many of them it moved; or free: the ``contact-offset`` effect) and the fitted toe
    half-width where there is one."""
    from ..mechanics.fit import log_suffix
    sfx = log_suffix(n_logs)(i)
    name = f"contact_offset_mm{sfx}"
    if name not in final.values:
        return {"contact_refined_mm": detected_mm,
                "contact_refinement": f"held at the {'given' if given else 'detected'} contact"}
    shift = float(final.values[name])
    lo, hi = final.ci95[name]
    out = {"contact_refined_mm": detected_mm + shift, "contact_refined_ci95_mm": [detected_mm + lo, detected_mm + hi],
           "contact_shift_mm": shift,
           "contact_refinement": "free, with an uneven-top toe (contact-offset)" if final.spec.contact_offset
           else "under the detector's prior (its standard deviation; heavier tails than Gaussian)"}
    if not final.spec.contact_offset and sd_mm is not None and np.isfinite(sd_mm) and sd_mm > 0:
        out["contact_shift_sd"] = shift / sd_mm
        out["contact_refinement"] += f": moved {abs(shift) / sd_mm:.1f} sd of {sd_mm:.3g} mm"
    for key, ci_key in (("contact_toe_mm", "contact_toe_ci95_mm"), ("contact_toe_exponent", "contact_toe_exponent_ci95"),
                        ("contact_toe_spread", "contact_toe_spread_ci95")):
        if f"{key}{sfx}" in final.values:
            out[key] = float(final.values[f"{key}{sfx}"])
            out[ci_key] = list(final.ci95[f"{key}{sfx}"])
    return out


def run(inputs: Sequence[str | os.PathLike], *, out: str | os.PathLike, stress_stretch: bool = False,
        modes: Sequence[str] = (), diameter_mm: float | Sequence[float] | None = None,
        height_mm: float | Sequence[float] | None = None,
        model: str | None = None, prony: int | None = None, boundary: str | None = None,
        loop: bool | None = None, width_csv: str | os.PathLike | None = None,
        config: str | os.PathLike | None = None, max_strain: float | None = None,
        bootstrap: int | None = None, seed: int | None = None,
        contact_mm: float | Sequence[float] | None = None, progress: bool = False) -> dict:
    """Run fit-ogden; returns the ``fit.json`` dict (also written to ``out``).

    ``None`` means "not given": the config's value, else FitConfig's default.
    ``diameter_mm`` and ``height_mm`` are one value for all logs or one per log (over the
    logs' metadata).  ``contact_mm`` gives each log's contact (one value for all or one per
    log; :class:`FitOgdenConfig`) instead of detecting it; the fit then holds it there (the
    loop's ``contact-offset`` may still free it).

    Raises
    ------
    InputError
        Unreadable or invalid input, config or options; missing geometry (exit 2).
    ProcessingError
        No contact in a log, a fit that does not converge, parameters no FE card can hold (exit 1).
    """
    from ..mechanics.effects import baseline_measurable
    from ..mechanics.fit import ForceModelSpec, TooFewRows, add_bootstrap
    from ..provenance import ResultSet, provenance
    from ..report.fit_figure import fit_figure

    paths = [str(p) for p in inputs]
    if not paths:
        raise InputError("no input file given (LOG ... or TABLE.csv --stress-stretch)")
    _check_distinct(paths)
    # click's repeated options: () is "not given"; one diameter or height is one number
    contact_mm, diameter_mm, height_mm = ([float(c) for c in v] or None if isinstance(v, (list, tuple)) else v
                                          for v in (contact_mm, diameter_mm, height_mm))
    diameter_mm, height_mm = (v[0] if isinstance(v, list) and len(v) == 1 else v for v in (diameter_mm, height_mm))
    cfg, explicit = _merge_config(config, {"diameter_mm": diameter_mm, "height_mm": height_mm, "model": model,
                                           "prony": prony, "boundary": boundary, "loop": loop,
                                           "max_strain": max_strain, "bootstrap": bootstrap, "seed": seed,
                                           "contact_mm": contact_mm})
    if stress_stretch:
        for opt, bad in (("--prony", cfg.prony), ("--boundary no-slip", cfg.boundary == "no-slip"),
                         ("--width-csv", width_csv is not None), ("--contact-mm", cfg.contact_mm is not None),
                         ("--diameter-mm", diameter_mm is not None), ("--height-mm", height_mm is not None)):
            if bad:
                raise InputError(f"{opt} does not apply to a stress-stretch table (it has no time, platens or "
                                 "specimen size)", path=paths[0])
        data, input_info = _read_tables(paths, list(modes), cfg)
        kind = "tables"
        spec0 = ForceModelSpec(law=cfg.model)
    else:
        if modes:
            raise InputError("--mode applies to stress-stretch tables (--stress-stretch)", path=paths[0])
        if "mode" in explicit and cfg.mode != "uniaxial":
            # a testing machine's log is fitted as the unconfined compression it records
            raise InputError(f"mode {cfg.mode!r} applies to stress-stretch tables; a machine log is fitted as "
                             "uniaxial compression", path=config, key="mode")
        try:
            spec0 = ForceModelSpec(law=cfg.model, prony=cfg.prony, boundary=cfg.boundary)
        except ValueError as e:
            raise InputError(str(e), path=config) from None
        given = {"contact_mm": contact_mm, "diameter_mm": diameter_mm, "height_mm": height_mm}
        per_log = {}
        for key in PER_LOG:
            try:
                per_log[key] = _per_log(cfg, key, paths)
            except InputError as e:
                # a count the config gives names the config (it had named the first log)
                raise InputError(e.message, path=paths[0] if given[key] is not None or config is None else config,
                                 key=key) from None
        data, input_info = _read_logs(paths, cfg, per_log)
        kind = "logs"
    width = _read_width(width_csv) if width_csv is not None else None

    try:
        baseline, final, loop_dict = _close_loop(kind, data, spec0, loop=cfg.loop,
                                                 boundary_declared="boundary" in explicit, width=width,
                                                 max_strain=cfg.max_strain if kind == "logs" else None,
                                                 law=cfg.model)
        if not final.success:
            _raise_if_softening(f"the {final.spec.describe()} fit did not converge", kind, data, paths)
            raise ProcessingError(f"the {final.spec.describe()} fit did not converge: {final.message}",
                                  path=paths[0])
        boundary_said = (_declared_boundary_check(final, data, width, width_csv)
                         if width is not None and "boundary" in explicit and kind == "logs" else None)
        if cfg.bootstrap and not _all_moduli_zero(final.params):
            # (a fit whose every modulus ran to zero fails below, with its warnings: its 200
            # refits had cost a tension test 17 s of 27 before the error)
            # one refit per resample: seconds on a short log, many minutes on a long record with
            # a Prony series and compliance; a bar on a terminal says where it is
            from tqdm import tqdm
            with tqdm(total=cfg.bootstrap, desc="bootstrap", unit="refit", file=sys.stderr, leave=False,
                      disable=not progress, mininterval=0.5) as bar:
                final_boot = add_bootstrap(final, data, n=cfg.bootstrap, seed=cfg.seed,
                                           max_strain=cfg.max_strain if kind == "logs" else None,
                                           progress=bar.update)
        else:
            final_boot = final
    except TooFewRows as e:             # the table cannot determine the model: bad input
        raise InputError(f"{e}: give more rows or a model with fewer parameters", path=paths[0]) from None
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as e:
        raise ProcessingError(f"the fit failed: {e}", path=paths[0]) from None
    changed = bool(loop_dict.get("steps"))
    figure = fit_figure(final, baseline if changed else None, labels=[Path(p).stem for p in paths]
                        if kind == "logs" else None)
    loop_md, loop_png = _loop_files(loop_dict, baseline, final, [Path(p).stem for p in paths] if kind == "logs" else None)
    final = final_boot

    if kind == "logs":
        from ..mechanics.fit import log_suffix, scatter_factors
        factors = scatter_factors(final.values, len(input_info)) if final.spec.specimen_scatter else None
        for i, (info, used) in enumerate(zip(input_info, final.used)):
            info["n_fitted"] = int(used.sum())
            if factors is not None:
                # specimen-scatter: this specimen's moduli, the law's times its factor
                info["specimen_stiffness_factor"] = float(factors[i])
                info["specimen_params"] = {k: float(v) * (float(factors[i]) if k.endswith("_pa") else 1.0)
                                           for k, v in final.tissue_params().items() if not isinstance(v, list)}
            given = info["contact"].get("method", "").startswith("given")
            info.update(_refined_contact(final, i, len(input_info), info["contact_mm"], given,
                                         info["contact"].get("displacement_sd_mm")))
            if final.spec.baseline_drift:
                sfx = log_suffix(len(input_info))(i)
                info["force_baseline"]["model"] = (f"fitted (load-baseline-drift): {final.values['baseline_n' + sfx]:.4g} N "
                                                   f"+ {final.values['drift_n_per_s' + sfx]:.3g} N/s")
            else:
                info["force_baseline"]["model"] = "0 N: the model takes the load cell's zero as the unloaded force"
            tare_key = "tare_n" + log_suffix(len(input_info))(i)
            if tare_key in final.values:
                info["force_baseline"]["tare_n"] = float(final.values[tare_key])
            if not baseline_measurable(data[i]):
                info["force_baseline"]["model"] += (" (load-baseline-drift not tried: no sample before the contact "
                                                    "measures the zero)")
    spec = final.spec
    result = {
        "model": spec.law,
        "params": final.params,
        "ci95": final.ci95,
        "metrics": {k: v for k, v in final.metrics.items() if k not in ("n_obs", "n_params", "sse_weighted")},
        "inputs": input_info,
        "loop": loop_dict,
        "spec": {"law": spec.law, "prony": spec.prony, "boundary": spec.boundary,
                 "contact_offset": spec.contact_offset, "baseline_drift": spec.baseline_drift,
                 "compliance": spec.compliance, "periodic_disturbance": spec.periodic_disturbance,
                 "refine_contact": spec.refine_contact,
                 "description": spec.describe()},
        "moduli": "instantaneous (G(0) = 1; long-term = mu * (1 - sum g))" if spec.prony else "elastic",
        "ci95_method": ("Jacobian at the optimum, t quantile, covariance scaled by the residual variance"
                        + ("; each detected contact refined within the detector's standard deviation "
                           "(a Gaussian prior), so its uncertainty is in every interval"
                           if kind == "logs" else "")),
        "ci95_bootstrap": final.ci95_bootstrap,
        "bootstrap": final.bootstrap,
        "n_obs": final.n_obs, "n_params": final.n_params, "aic": final.aic, "bic": final.bic,
        "weighting": WEIGHTING_LOGS if kind == "logs" else WEIGHTING_TABLES,
        "units": {"params": "mu in Pa (W = 2 mu / alpha^2 (l1^a + l2^a + l3^a - 3)); tau in s",
                  "rmse": "N" if kind == "logs" else "Pa"},
    }
    if kind == "logs":
        result["periodic_disturbance"] = _disturbance_lines(final, data)
    result["warnings"] = _fit_quality(final)
    if kind == "logs":
        result["warnings"] += (_spikes_left_out(input_info) + _load_clipped(input_info) + _lift_off(input_info)
                               + _load_resolution(input_info)
                               + _several_ramps(input_info) + _contacts_moved(input_info) + _geometry_disagrees(input_info))
        if boundary_said is not None:
            result["boundary_check"] = boundary_said["evidence"]
            if boundary_said.get("warning"):
                result["warnings"].append(boundary_said["warning"])
    else:
        result["warnings"] += _stress_sign_turned(input_info)
    if kind == "logs" and not spec.baseline_drift:
        result["warnings"] += _baseline_ignored(input_info, data)
    if kind == "logs" and spec.compliance:
        result["warnings"] += _compliance_implausible(final.values.get("compliance_mm_per_n", 0.0), data)
    if kind == "logs" and spec.baseline_drift:
        result["warnings"] += _drift_implausible(final, data)
    if kind == "logs" and "boundary" not in explicit and width is None and final.spec.boundary == "frictionless":
        result["warnings"] += _boundary_undeclared(data)
    if kind == "logs":
        result["warnings"] += _other_optima(final, data, cfg.max_strain)
        result["warnings"] += _residual_correlated(final, loop_dict, paths)
    try:
        _no_modulus(final.params, result["warnings"], paths[0])
    except ProcessingError:
        _raise_if_softening("the fit ran every modulus to zero", kind, data, paths)
        raise
    prov_inputs = paths + ([str(width_csv)] if width_csv is not None else []) + ([str(config)] if config else [])
    result["provenance"] = provenance(cfg, prov_inputs, command="fit-ogden")

    rs = ResultSet(out, primary="fit.json")
    for name, text in _cards(final).items():
        rs.add_text(name, text)
    rs.add_figure("fit.png", figure)
    rs.add_text("loop.md", loop_md)
    rs.add_figure("loop.png", loop_png)
    rs.add_json("fit.json", result)
    rs.commit()
    log.info("fit-ogden: %s, %s", spec.describe(),
             ", ".join(f"{k} = {v:.4g}" for k, v in final.values.items()))
    return result
