"""Distribution functions the stages' tests need, from :mod:`scipy.special`.

Each is the function :mod:`scipy.stats` itself evaluates for that distribution, so the
numbers are the same bit for bit (``tests/test_distributions.py``), without importing
:mod:`scipy.stats`: its import builds the docstrings of a hundred distributions and costs
most of a second of every command's start-up (``fit-ogden``, ``register``).
"""

from __future__ import annotations

import numpy as np


def norm_sf2(z: float) -> float:
    """Two-sided normal p-value of ``z``: ``2 * scipy.stats.norm.sf(abs(z))``."""
    from scipy.special import ndtr
    return float(2 * ndtr(-abs(z)))


def chi2_sf(q: float, dof: int) -> float:
    """``scipy.stats.chi2.sf(q, dof)``."""
    from scipy.special import chdtrc
    if np.isnan(q):
        return float("nan")
    return float(chdtrc(dof, q)) if q > 0 else 1.0


def f_sf(f: float, d1: int, d2: int) -> float:
    """``scipy.stats.f.sf(f, d1, d2)``."""
    from scipy.special import fdtrc
    if np.isnan(f):
        return float("nan")
    return float(fdtrc(d1, d2, f)) if f > 0 else 1.0


def pearsonr(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``scipy.stats.pearsonr(x, y)`` (two-sided) for 1-D float arrays of length >= 2, computed
    as it computes it: r of the centred, scaled vectors; p from the beta distribution of r
    under independence.  A constant input gives NaN, NaN (scipy warns)."""
    from scipy.special import betaincc
    n = float(len(x))
    if np.all(x == x[0]) or np.all(y == y[0]):
        import warnings
        warnings.warn("An input array is constant; the correlation coefficient is not defined.",
                      RuntimeWarning, stacklevel=3)
        return float("nan"), float("nan")
    xm = x - np.mean(x, keepdims=True)
    ym = y - np.mean(y, keepdims=True)
    xmax = np.max(np.abs(xm), keepdims=True)
    ymax = np.max(np.abs(ym), keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normxm = xmax * np.linalg.norm(xm / xmax, axis=-1, keepdims=True)
        normym = ymax * np.linalg.norm(ym / ymax, axis=-1, keepdims=True)
        r = np.vecdot(xm / normxm, ym / normym, axis=-1)
    r = np.clip(r, -1.0, 1.0)
    if n == 2:
        return float(np.round(r)), 1.0
    ab = np.asarray(n / 2 - 1, dtype=np.float64)
    p = 2 * betaincc(ab, ab, (np.abs(r) - (-1)) / 2)
    return float(r), float(p)


def chi2_isf(p: float, dof: int) -> float:
    """``scipy.stats.chi2.isf(p, dof)``: the value exceeded with probability ``p``."""
    from scipy.special import chdtri
    return float(chdtri(dof, p))


def t_ppf(q: float, dof: float) -> float:
    """``scipy.stats.t.ppf(q, dof)``: Student's t quantile."""
    from scipy.special import stdtrit
    return float(stdtrit(dof, q))
