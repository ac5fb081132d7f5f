"""The markers' polarity and diameter, from the first frame of each view.

``bsipipe track`` without ``--polarity`` or ``--diameter-px`` asks these: the seeds, where
there are some, are searched for dark and for bright markers and measured
(:func:`polarity_from_seeds`, :func:`diameter_from_seeds`); without seeds the first frames
are searched whole (:func:`polarity_from_frames`, :func:`diameter_without_seeds`).  A
diameter comes from the fitted Gaussian widths (:func:`diameter_from_sigmas`); views that see
the markers at different sizes keep one each (:func:`view_diameters`).  Markers much larger
than the 4 px tried first are not seen by a top-hat that small, so 8 and 16 px are tried
where 4 px finds too few.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .detect import DetectionSettings, detect_arrays, refine_at

#: The polarity and diameter probes measure with the plane background: their thresholds and
#: the two-size test of :func:`diameter_from_seeds` were set on it, and a run's choice of
#: background (for its centres) does not move its diameter (the edge background had moved the
#: grid probe's from 4.60 to 3.24 px: 4524 of 4628 positions within 1 px at 4.60, 4259 at 3.24).
PROBE = {"background": "plane"}


def polarity_from_seeds(firsts: dict, seeds: pd.DataFrame, diameter_px: float | None) -> tuple[str, str, dict]:
    """Dark or bright markers, from the seeds: each seeded view's first frame is searched
    around every seed (:func:`~bsipipe.imaging.detect.refine_at`, 6 px) for a dark and for a
    bright marker; the polarity that finds more of them wins, dark on a tie (raw X-ray frames
    show beads dark; an inverted export or a processed radiograph shows them bright).
    ``firsts``: each view's first frame (decoded by the caller).  Returns the polarity, a
    note for track.json and the counts per polarity, and under ``"per_view"`` each view's own
    (:func:`view_polarities`)."""
    seeded = [(v, firsts[v], g[["x_px", "y_px"]].to_numpy()) for v, g in seeds.groupby("view", sort=False)
              if firsts.get(v) is not None]
    total = sum(len(xy) for _, _, xy in seeded)
    # beads larger than 4 px may need a larger diameter to be found at all
    for d in ([diameter_px] if diameter_px else [4.0, 8.0, 16.0]):
        per = {v: {p: int(refine_at(img, xy, d, p, search_radius_px=max(6.0, 0.5 * d), **PROBE)["found"].sum())
                   for p in ("dark", "bright")} for v, img, xy in seeded}
        n = {p: sum(c[p] for c in per.values()) for p in ("dark", "bright")}
        if n["dark"] or n["bright"]:
            break
    pol = "bright" if n["bright"] > n["dark"] else "dark"
    return pol, (f"auto: from the seeds, {n['dark']} of {total} seeded markers found dark and {n['bright']} "
                 f"bright in the first frame"), {**n, "per_view": per}


def polarity_from_frames(firsts: dict, diameter_px: float | None, rois: dict | None = None
                          ) -> tuple[str, str, dict]:
    """Dark or bright markers without seeds: every view's first frame is searched whole
    (:func:`~bsipipe.imaging.detect.detect_arrays`) for dark and for bright markers, and
    those of SNR 6 or more are counted.  Steel beads in a raw frame give a dozen such dark
    spots and hardly any bright ones; bright is taken only where it finds at least 3 and
    twice as many as dark.  ``firsts``: each view's first frame (decoded by the caller);
    ``rois``: each view's region of interest (default: its field, found).  The counts come
    with each view's own under ``"per_view"`` (:func:`view_polarities`)."""
    # without a diameter, at 4 px, then 8 and 16 px where 4 px finds fewer than 3 of either
    # (markers much larger than 4 px are not seen by a top-hat that small)
    for d in ([diameter_px] if diameter_px else [4.0, 8.0, 16.0]):
        per = {v: {p: int((detect_arrays(img, d, p, (rois or {}).get(v), DetectionSettings(**PROBE))["snr"]
                           >= 6.0).sum()) for p in ("dark", "bright")}
               for v, img in firsts.items() if img is not None}
        n = {p: sum(c[p] for c in per.values()) for p in ("dark", "bright")}
        if max(n.values()) >= 3:
            break
    pol = "bright" if n["bright"] >= 3 and n["bright"] >= 2 * n["dark"] else "dark"
    return pol, (f"auto: no seeds; {n['dark']} dark and {n['bright']} bright markers of SNR 6 or more in the first "
                 f"frames{'' if d == 4.0 or diameter_px else f' at {d:g} px'}"), {**n, "per_view": per}


def view_polarities(pooled: str, per_view: dict, *, seeded: bool) -> dict[str, str]:
    """Each view's polarity: its own where its counts decide it clearly, else ``pooled`` (the
    views' counts together).  Two C-arms need not show the markers alike: one whose video is
    inverted (bone dark, steel bright) beside one that is not had found 12 seeded markers
    dark and 12 bright, dark won the tie, and the bright view's first seed was not found in
    any frame (exit 1), with no single ``--polarity`` to give.  Clearly: with seeds, one
    polarity finding at least 2 of the view's seeded markers and twice as many as the other;
    without, at least 3 strong markers and twice as many as the other (the rule
    :func:`polarity_from_frames` applies to the views together)."""
    least = 2 if seeded else 3
    out = {}
    for v, c in per_view.items():
        own = None
        for p, q in (("dark", "bright"), ("bright", "dark")):
            if c[p] >= least and c[p] >= 2 * c[q]:
                own = p
        out[v] = own or pooled
    return out


def diameter_from_sigmas(sigmas) -> float:
    """Marker diameter from fitted Gaussian sigmas: 2.5 times their median (a bead of
    diameter d blurred by sigma_b gives sigma ~ sqrt((d/4)^2 + sigma_b^2)), clipped to 2..40 px.

    Markers of two sizes (widths more than 1.6 times apart; split at the geometric mean of the
    smallest and largest) are tracked at one diameter between them: at least 2.5 times the
    geometric mean of the two groups' medians, which the median is where the groups are about
    as many, and is not where the small ones outnumber the large (eight 0.5 mm beads and six
    1 mm ones had given 2.62 px, at which the references were found in 9-28 of 221 frames)."""
    s = np.asarray(sigmas, float)
    s = s[np.isfinite(s) & (s > 0)]
    if not len(s):
        return 4.0
    d = 2.5 * float(np.median(s))
    lo, hi = float(s.min()), float(s.max())
    if hi > 1.6 * lo:
        cut = math.sqrt(lo * hi)
        small, large = s[s < cut], s[s >= cut]
        if len(small) and len(large):
            d = max(d, 2.5 * math.sqrt(float(np.median(small)) * float(np.median(large))))
    return float(np.clip(d, 2.0, 40.0))


def view_diameters(est: dict, views) -> tuple[float, dict, str]:
    """The diameter (the first estimated view's), one per view and the note, from each view's
    estimate ``est`` (view -> (diameter, note)).  Where the estimates differ by more than 25 %
    the views see the markers at different sizes (C-arms at different magnifications, an
    intensifier in another field mode) and each keeps its own; within 25 % all take the first
    view's, so one noisy estimate does not split them.  No estimate: 4 px."""
    if not est:
        return 4.0, {v: 4.0 for v in views}, "default (no --diameter-px, no seeds)"
    v0 = next(iter(est))
    d, how = est[v0]
    per_view = {v: d for v in views}
    ds = [e[0] for e in est.values()]
    if max(ds) > 1.25 * min(ds):
        per_view.update({v: e[0] for v, e in est.items()})
        return d, per_view, "; ".join(f"{v}: {e[1]}" for v, e in est.items()) + " (a diameter per view)"
    return d, per_view, f"{v0}: {how}"


def diameter_without_seeds(first: np.ndarray, polarity: str, roi=None) -> tuple[float, str]:
    """Marker diameter of a view without seeds, from its first frame searched whole
    (:func:`~bsipipe.imaging.detect.detect_arrays`): 4 px (the default) where that finds 3 or
    more markers of SNR 6 or more; else the first of 8 and 16 px that does, refined to 2.5
    times the median fitted width of what it finds (markers much larger than 4 px are not
    seen by a top-hat that small, and the command would find nothing)."""

    def strong(d):
        r = detect_arrays(first, d, polarity, roi, DetectionSettings(**PROBE))
        ok = (r["snr"] >= 6.0) & np.isfinite(r["sigma_px"])
        return int(ok.sum()), r["sigma_px"][ok]

    n4, _ = strong(4.0)
    if n4 >= 3:
        return 4.0, f"default 4 px (no --diameter-px, no seeds; {n4} markers of SNR 6 or more in the first frame)"
    for d0 in (8.0, 16.0):
        n, sig = strong(d0)
        if n >= 3:
            d = diameter_from_sigmas(sig)
            return d, (f"estimated without seeds: 4 px found {n4} markers of SNR 6 or more in the first frame, "
                       f"{d0:g} px {n}; 2.5 x their median fitted sigma")
    return 4.0, "default 4 px (no --diameter-px, no seeds; no size tried finds 3 markers of SNR 6 or more)"


#: How far under the width test's limit (``DetectionSettings.max_sigma_factor`` x the diameter) the
#: widest seeded marker's fitted sigma must stay (:func:`width_floor`).
WIDTH_MARGIN = 1.25


def width_floor(sigmas, max_sigma_factor: float | None = DetectionSettings().max_sigma_factor) -> float:
    """The smallest diameter at which every one of the seeded markers' fitted widths
    ``sigmas`` (px) passes the width test (a fit wider than ``max_sigma_factor`` x the
    diameter is no marker) with :data:`WIDTH_MARGIN` to spare; 0 without a test.

    The diameter of markers of two sizes lies between them (:func:`diameter_from_sigmas`), and
    where a few large ones are measured narrower (clipped in a saturated frame, cut by the
    field's rim) the median falls towards the small: on a twin of six 0.5 mm and six 1 mm beads
    with its frames' bright parts clipped, the diameter fell from 3.51 to 3.07 px, and the
    references, sigma up to 2.08 px against a limit of 2.30, failed it in 7.5 % of their
    frames, unsaid (this floor: 3.47 px).  The margin covers about 3.5 sd of a fitted width's
    scatter at an SNR of 30 (7 % of it) over a bead 5 % wider than in the first frame."""
    s = np.asarray(sigmas, float)
    s = s[np.isfinite(s) & (s > 0)]
    if not len(s) or not max_sigma_factor:
        return 0.0
    return float(min(40.0, WIDTH_MARGIN * float(s.max()) / max_sigma_factor))


#: Where most seeds find no marker within the diameter probe's reach, how many times as far
#: they are searched (as the tracker's first frame does, ``track.SEED_REACH_FACTOR``).
SEED_REACH = 2.5


def sigmas_at(first: np.ndarray, xy, d: float, polarity: str, reach: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Whether each of the points ``xy`` (n, 2) finds a marker at diameter ``d`` within
    ``reach`` times the probe's radius (``max(6, d/2)``) with a fitted width, and that width
    (sigma, px) (:func:`~bsipipe.imaging.detect.refine_at`, plane background)."""
    r = refine_at(first, xy, d, polarity, search_radius_px=reach * max(6.0, 0.5 * d), **PROBE)
    return r["found"].to_numpy(bool) & np.isfinite(r["sigma_px"].to_numpy()), r["sigma_px"].to_numpy()


def larger_sigmas(first: np.ndarray, xy, d: float, polarity: str,
                  factors=(1.5, 2.0, 3.0, 4.0)) -> np.ndarray:
    """Each point's fitted width (sigma, px) at the first of ``factors`` times ``d`` (at most
    40 px) that finds a marker there, NaN where none does: markers larger than ``d``."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    out = np.full(len(xy), np.nan)
    miss = np.arange(len(xy))
    for f in factors:
        if not len(miss):
            break
        big, sb = sigmas_at(first, xy[miss], min(40.0, f * d), polarity)
        out[miss[big]] = sb[big]
        miss = miss[~big]
    return out


def diameter_from_seeds(first: np.ndarray, seeds: pd.DataFrame, polarity: str) -> tuple[float, str]:
    """Marker diameter from the seeds of one view, and a note: from the fitted Gaussian sigmas
    of the seeded markers in the first frame (:func:`diameter_from_sigmas`).

    Markers of two sizes (the deep 0.5 mm beads and the 1 mm references) are found at one
    diameter near the larger size, not near the smaller: where seeds find no marker at the
    median's diameter, they are looked for at 1.5, 2, 3 and 4 times it, and if the diameter
    of those found (2.5 x their median sigma) finds at least half the seeds missed, and every
    seed found before, it is taken.  (A bead fitted with a diameter over about twice its own is
    measured less well: beads of more than two sizes apart need --diameter-px or separate
    runs.)  ``first``: the view's first frame."""
    xy = seeds[["x_px", "y_px"]].to_numpy()

    def found_at(d, pts, reach=1.0):
        return sigmas_at(first, pts, d, polarity, reach)

    # first probed at 4 px, then 8 and 16 px (markers much larger than 4 px are not seen by a
    # top-hat that small)
    for d0 in (4.0, 8.0, 16.0):
        ok, s = found_at(d0, xy)
        if ok.any():
            break
    far = ""
    if 2 * ok.sum() < len(xy):
        # most seeds find no marker within the probe's reach: clicks systematically off (a
        # scaled display); the diameter is measured on what a wider search finds, not on the
        # one or two seeds that happened to lie near a marker
        ok2, s2 = found_at(d0, xy, SEED_REACH)
        if ok2.sum() > ok.sum():
            ok, s = ok2, s2
            far = f"; most seeds far from their markers, searched {SEED_REACH:g} x as far"
    if not ok.any():
        return 4.0, "default: no seeded marker measured in the first frame"
    d = diameter_from_sigmas(s[ok])
    note = f"estimated from the seeds ({ok.sum()} of {len(xy)}; 2.5 x median fitted sigma{far})"
    d_wide = width_floor(s[ok])
    if d_wide > d:
        note += (f"; raised from {d:.2f} px so that the widest seeded marker (sigma {np.max(s[ok]):.2f} px) passes "
                 f"the width test with {100 * (WIDTH_MARGIN - 1):.0f} % to spare")
        d = d_wide
    hit, _ = found_at(d, xy)
    if hit.all():
        return d, note
    sig = larger_sigmas(first, xy[~hit], d, polarity)
    sig = sig[np.isfinite(sig)]
    if len(sig):
        d2 = diameter_from_sigmas(sig)
        hit2, _ = found_at(d2, xy)
        # a second size of marker, not one stray find: at least half the seeds missed at d
        # found (a lossy video's faint beads, lost at every size, must not make one blur or
        # block artefact found at 2-4 d set the diameter of every marker)
        gain = int(hit2.sum() - hit.sum())
        if gain > 0 and 2 * gain >= int((~hit).sum()) and hit2[hit].all():
            return d2, (f"{note}: {d:.2f} px found {hit.sum()} of {len(xy)} seeded markers; {d2:.2f} px, from the "
                        f"{len(sig)} larger ones, finds {hit2.sum()}")
    return d, note
