r"""Quasi-linear viscoelasticity (Fung): a Prony relaxation function applied to an elastic response.

The stress (or force) is the hereditary integral of the elastic response
:math:`\sigma_e(t)` against a normalised relaxation function,

.. math::

    \sigma(t) = \int_{-\infty}^{t} G(t - s)\, \frac{d\sigma_e}{ds}\, ds, \qquad
    G(t) = g_\infty + \sum_{i=1}^{N} g_i\, e^{-t/\tau_i}, \qquad g_\infty = 1 - \sum_i g_i,

so :math:`G(0) = 1`: the elastic law is the *instantaneous* response and
:math:`g_\infty \sigma_e` the fully relaxed one.  This is the hyperviscoelastic form of
ABAQUS's ``*VISCOELASTIC, TIME=PRONY`` with instantaneous moduli.
"""

from __future__ import annotations

import numpy as np

#: Largest decay exponent spanned by one vectorised block of the recursion; e^300 ~ 2e130
#: keeps every intermediate term finite (forces of any physical size stay far from over- and underflow).
_BLOCK_EXPONENT = 300.0


class _PronyTerm:
    r"""One Prony term's recursion on a fixed time grid, its coefficients computed once.

    The state obeys :math:`h_{k+1} = e^{-\Delta x_k} h_k + \Delta\sigma_k (1 - e^{-\Delta x_k}) / \Delta x_k`,
    ``x`` being time in units of the relaxation time (non-decreasing).  The first-order
    recursion is summed in closed form, block by block:

    .. math::

        h_n = e^{x_e - x_n}\Big(h_s e^{x_s - x_e} + \sum_{k=s}^{n-1} b_k e^{x_{k+1} - x_e}\Big),
        \quad s \le n \le e,

    with the block end ``e`` chosen so that :math:`x_e - x_s \le 300` (no overflow; every
    exponent in the sum is :math:`\le 0`).  A single step longer than that is its own block.
    Everything but the increments (the blocks and their exponentials) depends on the grid
    alone: a fit that applies the operator to many elastic histories on one grid
    (:class:`QLV`) prepares it once.
    """

    def __init__(self, x: np.ndarray):
        self.n = n = len(x)
        if n == 1:
            return
        dx = np.diff(x)
        # (1 - e^{-dx}) / dx, with its limit 1 at dx = 0 (repeated time stamps).
        with np.errstate(invalid="ignore", divide="ignore"):
            self.frac = np.where(dx > 0, -np.expm1(-dx) / np.where(dx > 0, dx, 1.0), 1.0)
        self.blocks = []
        s = 0
        while s < n - 1:
            e = int(np.searchsorted(x, x[s] + _BLOCK_EXPONENT, side="right")) - 1
            e = min(max(e, s + 1), n - 1)
            xe = x[e]
            # e^{x_{k+1} - x_e} (k = s..e-1), e^{x_s - x_e}, e^{x_e - x_n} (n = s+1..e)
            self.blocks.append((s, e, np.exp(x[s + 1:e + 1] - xe), np.exp(x[s] - xe), np.exp(xe - x[s + 1:e + 1])))
            s = e

    def state(self, d_elastic: np.ndarray, h0: float) -> np.ndarray:
        """The state at every sample from the (already ``g_i``-scaled) elastic increments and
        the state ``h0`` at the first sample."""
        h = np.empty(self.n)
        h[0] = h0
        if self.n == 1:
            return h
        # worked in units of a power of two near the largest input (exact): the weights reach
        # e^-300, and a history of 1e-230 N had underflowed in their products, off by 4e-8
        # relative where twice the history is exact (the property test of linearity)
        m = max(float(np.max(np.abs(d_elastic), initial=0.0)), abs(float(h0)))
        k = int(np.frexp(m)[1]) if np.isfinite(m) and m > 0 else 0
        h[0] = np.ldexp(h0, -k)
        b = np.ldexp(d_elastic * self.frac, -k)
        for s, e, w, first, back in self.blocks:
            acc = h[s] * first + np.cumsum(b[s:e] * w)
            h[s + 1:e + 1] = acc * back
        return np.ldexp(h, k)


class QLV:
    """The quasi-linear viscoelastic operator of a Prony series on one time grid:
    ``QLV(time_s, g, tau_s)(elastic)`` is :func:`qlv_response` ``(time_s, elastic, g, tau_s)``,
    the same numbers, with the grid's coefficients computed once for every history applied.
    ``terms``: a :class:`PronyTerms` of this grid, which keeps each relaxation time's
    coefficients from one operator to the next (a fit builds one per evaluation).

    >>> t = np.array([0.0, 0.5, 1.0, 10.0])
    >>> op = QLV(t, [0.5], [1.0])
    >>> bool(np.array_equal(op(np.ones(4)), qlv_response(t, np.ones(4), [0.5], [1.0])))
    True
    """

    def __init__(self, time_s, g, tau_s, terms: "PronyTerms | None" = None):
        t = np.asarray(time_s, dtype=float)
        g = np.atleast_1d(np.asarray(g, dtype=float))
        tau = np.atleast_1d(np.asarray(tau_s, dtype=float))
        if t.ndim != 1:
            raise ValueError(f"time_s must be 1-D, got shape {t.shape}")
        if g.shape != tau.shape:
            raise ValueError(f"g and tau_s must have one length, got {g.shape} and {tau.shape}")
        if np.any(tau <= 0):
            raise ValueError("relaxation times must be positive")
        if len(t) > 1 and np.any(np.diff(t) < 0):
            raise ValueError("time_s must be non-decreasing")
        self.n = len(t)
        self.g_inf = 1.0 - g.sum()
        if not len(t):
            self.terms = []
        elif terms is None:
            self.terms = [(gi, _PronyTerm((t - t[0]) / ti)) for gi, ti in zip(g, tau) if gi != 0.0]
        else:
            self.terms = [(gi, terms.term(t, ti)) for gi, ti in zip(g, tau) if gi != 0.0]

    def __call__(self, elastic) -> np.ndarray:
        se = np.asarray(elastic, dtype=float)
        if se.shape != (self.n,):
            raise ValueError(f"time_s and elastic must be 1-D of one length, got ({self.n},) and {se.shape}")
        if self.n == 0:
            return np.zeros(0)
        out = self.g_inf * se
        d_se = np.diff(se)
        for gi, term in self.terms:
            out = out + term.state(gi * d_se, gi * se[0])
        return out


class PronyTerms:
    """The Prony recursions of one time grid by relaxation time, the ``size`` last used kept.

    Building a term's coefficients (the blocks' exponentials) costs about twice applying it.
    A fit evaluates its model thousands of times on one grid with a handful of relaxation
    times (each finite-difference step but the one on ``tau`` keeps them): with this cache
    each evaluation builds only the terms whose time changed; the numbers are the same.

    >>> t = np.linspace(0.0, 10.0, 101)
    >>> cache = PronyTerms()
    >>> a = QLV(t, [0.3], [2.0], cache)(np.sin(t))
    >>> bool(np.array_equal(a, qlv_response(t, np.sin(t), [0.3], [2.0]))), len(cache)
    (True, 1)
    """

    def __init__(self, size: int = 8):
        from collections import OrderedDict
        self.size = size
        self._grid: np.ndarray | None = None
        self._terms: "OrderedDict[float, _PronyTerm]" = OrderedDict()

    def __len__(self) -> int:
        return len(self._terms)

    def term(self, t: np.ndarray, tau: float) -> _PronyTerm:
        if self._grid is None:
            self._grid = t
        elif t is not self._grid and not np.array_equal(t, self._grid):
            raise ValueError("a PronyTerms cache serves one time grid")
        key = float(tau)
        hit = self._terms.get(key)
        if hit is not None:
            self._terms.move_to_end(key)
            return hit
        term = self._terms[key] = _PronyTerm((t - t[0]) / tau)
        if len(self._terms) > self.size:
            self._terms.popitem(last=False)
        return term


def qlv_response(time_s, elastic, g, tau_s) -> np.ndarray:
    r"""Quasi-linear viscoelastic response to an elastic history sampled on any time grid.

    The elastic response is taken as piecewise linear between samples and as zero before
    ``time_s[0]``, so ``elastic[0]`` is applied as a step at the first sample (zero for a
    log that starts unloaded).  For each Prony term the state
    :math:`h_i(t) = \int g_i e^{-(t-s)/\tau_i} \dot\sigma_e(s)\, ds` follows the exact
    recursion for a linear segment of length :math:`\Delta t_k`,

    .. math::

        h_i(t_{k+1}) = e^{-\Delta t_k/\tau_i} h_i(t_k)
            + g_i \frac{\Delta\sigma_{e,k}\, \tau_i}{\Delta t_k}\left(1 - e^{-\Delta t_k/\tau_i}\right),
        \qquad h_i(t_0) = g_i\, \sigma_e(t_0),

    and :math:`\sigma(t_k) = g_\infty \sigma_e(t_k) + \sum_i h_i(t_k)`,
    :math:`g_\infty = 1 - \sum_i g_i`.  No time-step restriction: the grid may be
    non-uniform and may repeat a time stamp (a jump).

    Parameters
    ----------
    time_s : array_like, shape (n,)
        Sample times, non-decreasing.
    elastic : array_like, shape (n,)
        Elastic (instantaneous) response at those times, any unit (force or stress).
    g : sequence of float, length N
        Prony fractions, each in [0, 1), their sum below 1.
    tau_s : sequence of float, length N
        Relaxation times, s, positive.

    Returns
    -------
    ndarray, shape (n,), the unit of ``elastic``.

    Examples
    --------
    A step held in time relaxes along :math:`G(t)`:

    >>> t = np.array([0.0, 0.5, 1.0, 10.0])
    >>> np.round(qlv_response(t, np.ones(4), [0.5], [1.0]), 6)
    array([1.      , 0.803265, 0.68394 , 0.500023])
    >>> bool(np.allclose(qlv_response(t, np.ones(4), [0.5], [1.0]), 0.5 + 0.5 * np.exp(-t)))
    True
    """
    t = np.asarray(time_s, dtype=float)
    se = np.asarray(elastic, dtype=float)
    if t.ndim != 1 or se.shape != t.shape:
        raise ValueError(f"time_s and elastic must be 1-D of one length, got {t.shape} and {se.shape}")
    return QLV(t, g, tau_s)(se)


def relaxation_function(time_s, g, tau_s) -> np.ndarray:
    r"""The normalised relaxation function :math:`G(t) = g_\infty + \sum_i g_i e^{-t/\tau_i}`.

    >>> float(relaxation_function(0.0, [0.3, 0.2], [0.5, 50.0]))
    1.0
    """
    t = np.asarray(time_s, dtype=float)
    g = np.atleast_1d(np.asarray(g, dtype=float))
    tau = np.atleast_1d(np.asarray(tau_s, dtype=float))
    out = np.full_like(t, 1.0 - g.sum())
    for gi, ti in zip(g, tau):
        out = out + gi * np.exp(-t / ti)
    return out
