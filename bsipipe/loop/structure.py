r"""Is a residual noise?  Tests for structure, shared by every stage's loop.

A model that lacks an effect leaves a residual that is not white noise: neighbouring
samples agree in sign (few runs, positive lag-1 autocorrelation), or the residual follows a
covariate (time, rate, stretch) or differs between groups (segments, specimens, views).
:func:`residual_structure` runs one test per kind of structure and says whether what is left
is consistent with independent noise.

Tests (``n`` samples, residual ``e``, each series taken in its own order within a group):

- **Runs** (Wald-Wolfowitz) of the sign of ``e`` about each group's median.  With
  :math:`n_+, n_-` samples above and below, :math:`E[R] = 1 + 2 n_+ n_- / n` and
  :math:`\operatorname{Var}[R] = 2 n_+ n_- (2 n_+ n_- - n) / (n^2 (n - 1))`, summed over
  groups; two-sided normal p-value.
- **Lag-1 autocorrelation** :math:`r_1 = \sum_t (e_t - \bar e)(e_{t+1} - \bar e) / \sum_t (e_t - \bar e)^2`,
  pooled within groups; under noise :math:`r_1 \sim N(0, 1/n)`.
- **Ljung-Box** :math:`Q = n (n + 2) \sum_{k=1}^{h} r_k^2 / (n - k)`, per group, summed;
  :math:`\chi^2` with ``h`` degrees of freedom per group.
- **Covariates**: for a numeric covariate, the Pearson correlation (t test) and a binned
  one-way ANOVA of ``e`` over ``n_bins`` quantile bins (catches a U-shaped dependence that a
  correlation misses); for a categorical one (segment, specimen), the ANOVA over its levels.
- **Group means**: one-way ANOVA of ``e`` over ``groups``.

The verdict ``noise`` is true when no test rejects at level ``alpha`` after a Bonferroni
correction over the tests run (``p_min >= alpha / n_tests``).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

# The p-values come from scipy.special (bsipipe.distributions), the functions scipy.stats
# evaluates for these distributions: the same numbers without importing scipy.stats.
from ..distributions import chi2_sf, f_sf, norm_sf2, pearsonr

#: Family-wise level of the noise verdict (Bonferroni over the tests run).
ALPHA = 0.01


def _as_series(residual, groups):
    """Flatten a residual (array or list of per-group arrays) and its group labels."""
    if isinstance(residual, (list, tuple)):
        parts = [np.asarray(r, dtype=float).ravel() for r in residual]
        e = np.concatenate(parts) if parts else np.zeros(0)
        if groups is None:
            groups = np.concatenate([np.full(len(p), i) for i, p in enumerate(parts)]) if parts else np.zeros(0, int)
    else:
        e = np.asarray(residual, dtype=float).ravel()
    if groups is None:
        groups = np.zeros(len(e), dtype=int)
    groups = np.asarray(groups)
    if groups.shape != e.shape:
        raise ValueError(f"groups has shape {groups.shape}, residual {e.shape}")
    return e, groups


def _group_slices(groups: np.ndarray) -> list[np.ndarray]:
    """Indices of each group's samples, in their original order (labels need not be contiguous)."""
    _, inv = np.unique(groups, return_inverse=True)
    return [np.flatnonzero(inv == k) for k in range(inv.max() + 1)] if len(groups) else []


def runs_test(e: np.ndarray, groups: np.ndarray) -> dict:
    """Wald-Wolfowitz runs of sign about each group's median, pooled over groups."""
    runs = expected = var = 0.0
    n_total = 0
    for idx in _group_slices(groups):
        x = e[idx]
        s = x > np.median(x)
        n1 = int(s.sum())
        n2 = len(s) - n1
        n = n1 + n2
        if n1 == 0 or n2 == 0 or n < 3:
            continue
        runs += 1 + int(np.count_nonzero(s[1:] != s[:-1]))
        expected += 1.0 + 2.0 * n1 * n2 / n
        var += 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
        n_total += n
    if var <= 0:
        return {"runs": int(runs), "expected": expected, "z": 0.0, "p": 1.0}
    z = (runs - expected) / np.sqrt(var)
    return {"runs": int(runs), "expected": float(expected), "z": float(z), "p": norm_sf2(z)}


def _autocorr(x: np.ndarray, max_lag: int) -> np.ndarray:
    x = x - x.mean()
    den = float(np.dot(x, x))
    if den == 0.0:
        return np.zeros(max_lag)
    return np.array([np.dot(x[:-k], x[k:]) / den for k in range(1, max_lag + 1)])


def autocorrelation_tests(e: np.ndarray, groups: np.ndarray, max_lag: int | None = None) -> tuple[dict, dict]:
    """Pooled lag-1 autocorrelation (normal test) and Ljung-Box over ``h`` lags (summed over groups)."""
    num = den = 0.0
    n_pairs = 0
    q = 0.0
    dof = 0
    for idx in _group_slices(groups):
        x = e[idx]
        n = len(x)
        if n < 4:
            continue
        xc = x - x.mean()
        num += float(np.dot(xc[:-1], xc[1:]))
        den += float(np.dot(xc, xc))
        n_pairs += n
        h = max_lag or int(min(10, max(1, n // 5)))
        r = _autocorr(x, h)
        k = np.arange(1, h + 1)
        q += float(n * (n + 2) * np.sum(r**2 / (n - k)))
        dof += h
    r1 = num / den if den > 0 else 0.0
    z = r1 * np.sqrt(max(n_pairs, 1))
    lag1 = {"r1": float(r1), "z": float(z), "p": norm_sf2(z)}
    lb = {"q": q, "dof": int(dof), "p": chi2_sf(q, dof) if dof else 1.0}
    return lag1, lb


def _anova(e: np.ndarray, labels: np.ndarray) -> dict:
    levels, inv = np.unique(labels, return_inverse=True)
    k = len(levels)
    n = len(e)
    if k < 2 or n <= k:
        return {"levels": int(k), "f": 0.0, "p": 1.0}
    counts = np.bincount(inv, minlength=k).astype(float)
    means = np.bincount(inv, weights=e, minlength=k) / counts
    grand = e.mean()
    ss_between = float(np.sum(counts * (means - grand) ** 2))
    ss_within = float(np.sum((e - means[inv]) ** 2))
    if ss_within <= 0:
        return {"levels": int(k), "f": float("inf"), "p": 0.0}
    f = (ss_between / (k - 1)) / (ss_within / (n - k))
    return {"levels": int(k), "f": float(f), "p": f_sf(f, k - 1, n - k)}


def _is_categorical(x: np.ndarray) -> bool:
    if x.dtype.kind in "OUSb":
        return True
    if x.dtype.kind in "iu":
        return len(np.unique(x)) <= 50
    return False


def covariate_tests(e: np.ndarray, x: np.ndarray, n_bins: int = 10) -> dict:
    """Dependence of the residual on one covariate: correlation + binned ANOVA, or ANOVA over levels."""
    x = np.asarray(x)
    if x.shape != e.shape:
        raise ValueError(f"covariate has shape {x.shape}, residual {e.shape}")
    if _is_categorical(x):
        a = _anova(e, x)
        return {"kind": "categorical", "anova_f": a["f"], "levels": a["levels"], "p": a["p"]}
    xf = x.astype(float)
    ok = np.isfinite(xf)
    xf, ef = xf[ok], e[ok]
    if len(ef) < 4 or np.ptp(xf) == 0:
        return {"kind": "numeric", "r": 0.0, "p_r": 1.0, "anova_f": 0.0, "p_bins": 1.0, "p": 1.0}
    r, p_r = pearsonr(xf.astype(float), ef.astype(float))
    edges = np.unique(np.quantile(xf, np.linspace(0, 1, n_bins + 1)))
    bins = np.clip(np.searchsorted(edges, xf, side="right") - 1, 0, max(len(edges) - 2, 0))
    a = _anova(ef, bins)
    # Two tests on one covariate: the smaller p, doubled (Bonferroni within the covariate).
    p = min(1.0, 2.0 * min(float(p_r), a["p"]))
    return {"kind": "numeric", "r": float(r), "p_r": float(p_r), "anova_f": a["f"], "p_bins": a["p"], "p": p}


def residual_structure(residual, covariates: Mapping[str, Sequence] | None = None, groups=None, *,
                       alpha: float = ALPHA, n_bins: int = 10, max_lag: int | None = None) -> dict:
    """Test a residual for structure; say whether it is consistent with independent noise.

    Parameters
    ----------
    residual : array_like, shape (n,), or list of arrays (one per group, e.g. per log)
        Residual in the stage's unit, each group's samples in their natural (time) order.
    covariates : dict name -> array_like, shape (n,), optional
        Quantities the residual may follow: numeric (time, rate, stretch) or categorical
        (segment, specimen).
    groups : array_like, shape (n,), optional
        Series labels (log, view); serial tests run within each group, and the group means
        are compared.  Defaults to the list index when ``residual`` is a list.
    alpha : float
        Family-wise level of the verdict (Bonferroni over the tests run).

    Returns
    -------
    dict with ``n``, ``rms``, ``tests`` (name -> statistics and ``p``), ``n_tests``,
    ``p_min``, ``worst`` (the test with the smallest p), ``alpha``, ``noise`` (bool).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> residual_structure(rng.normal(size=2000), {"time_s": np.arange(2000.0)})["noise"]
    True
    >>> residual_structure(np.sin(np.linspace(0, 6, 2000)) + rng.normal(size=2000))["noise"]
    False
    """
    e, g = _as_series(residual, groups)
    tests: dict[str, dict] = {}
    tests["runs"] = runs_test(e, g)
    tests["lag1_autocorrelation"], tests["ljung_box"] = autocorrelation_tests(e, g, max_lag)
    if len(np.unique(g)) > 1:
        a = _anova(e, g)
        tests["group_means"] = {"levels": a["levels"], "anova_f": a["f"], "p": a["p"],
                                "means": {str(k): float(e[g == k].mean()) for k in np.unique(g)}}
    for name, x in (covariates or {}).items():
        tests[f"covariate:{name}"] = covariate_tests(e, np.asarray(x), n_bins)
    ps = {k: v["p"] for k, v in tests.items()}
    worst = min(ps, key=ps.get)
    n_tests = len(ps)
    return {
        "n": int(len(e)),
        "rms": float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
        "tests": tests,
        "n_tests": n_tests,
        "p_min": float(ps[worst]),
        "worst": worst,
        "alpha": alpha,
        "noise": bool(ps[worst] >= alpha / n_tests),
    }
