"""When is a match real?  The a contrario false-alarm model of the fast matcher.

The null hypothesis is that the image objects have nothing to do with the map
around the hypothesised position: projected into the map, each lands at a random
place.  Under it, the chance that the nearest map object of its own label lies
within ``r`` is ``1 - exp(-lambda * pi * r^2)`` for a label density ``lambda``
(objects per square metre) - the Poisson void probability.  Expressing every
residual as ``u = lambda_label * pi * r^2`` makes that chance ``1 - exp(-u)``
whatever the label, so one binomial tail covers images that mix labels.

A hypothesis built from ``s`` correspondences (the quad it came from) that
brings ``k`` of the ``n`` image objects within their ``k``-th smallest ``u``
would do so by chance with probability at most
``P(Binomial(n - s, 1 - exp(-u_(k))) >= k - s)``.  The number of false alarms
multiplies that by the number of tests: every hypothesis tried, and every
choice of ``k`` (``n - s`` of them) - the tolerance is picked after looking,
as in AC-RANSAC (Moisan and Stival 2004; Moisan, Moulon and Monasse 2012).
An answer is accepted when the NFA is below a threshold ``10**log10_epsilon``.

Objects extracted from masks also carry their pixel area: :mod:`mapdb.match.evidence.areas` thins the null's
process to the map objects of a compatible area (``u`` computed with ``lambda q``), which leaves this
model unchanged; objects without an area keep ``q = 1``.

Everything is in log10 and vectorised over hypotheses.
"""

from __future__ import annotations

import numpy as np

from .._scipy import betainc
from ._kernel import nfa_curve
from .arrays import contiguous_to

__all__ = ["LOG10_FLOOR", "log10_binomial_tail", "log10_nfa_curve", "log10_trials"]

# Probabilities below this are reported as this: they are far beyond any threshold we use.
LOG10_FLOOR = -300.0


def log10_binomial_tail(
    n: float | np.ndarray, k: float | np.ndarray, p: float | np.ndarray
) -> np.ndarray:
    """``log10 P(Binomial(n, p) >= k)``, elementwise with broadcasting.

    Uses the regularised incomplete beta function ``I_p(k, n - k + 1)``: exact, and
    accurate for tails far smaller than floating-point differences of CDFs could give.

    Examples
    --------
    >>> bool(np.isclose(log10_binomial_tail(10, 10, 0.5), 10 * np.log10(0.5)))
    True
    >>> float(log10_binomial_tail(10, 0, 0.1)), float(log10_binomial_tail(3, 4, 0.9))
    (0.0, -inf)
    """
    n = np.asarray(n, dtype=np.float64)
    k = np.asarray(k, dtype=np.float64)
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0)
    n, k, p = np.broadcast_arrays(n, k, p)
    out = np.zeros(n.shape)
    out[k > n] = -np.inf
    inner = (k >= 1) & (k <= n)
    if np.any(inner):
        tail = betainc(k[inner], n[inner] - k[inner] + 1.0, p[inner])
        with np.errstate(divide="ignore"):
            out[inner] = np.maximum(np.log10(tail), LOG10_FLOOR)
    return out


def log10_nfa_curve(
    u: np.ndarray,
    n_sample: int,
    log10_tests: float,
    shape: np.ndarray | None = None,
    sample: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Best (smallest) log10 NFA of each hypothesis over the number of inliers ``k``.

    Parameters
    ----------
    u : array of shape (H, n)
        Normalised residuals ``lambda * pi * r^2`` of the ``n`` image objects under each of ``H``
        hypotheses (``inf`` where an object has no map object of its label in reach).
    n_sample : int
        Correspondences that built each hypothesis; they are not counted as evidence.
    log10_tests : float
        log10 of the number of hypotheses tried.
    shape : array of shape (H, n), optional
        Relative tolerance area per object (> 0): how much farther from its prediction a true object
        may lie, e.g. ``1 + prediction variance factor`` of the hypothesis.  Objects are then ranked by
        ``u / shape`` and a threshold ``tau`` admits ``u_i <= tau * shape_i``; the chance of that differs
        per object, and the binomial with their mean chance bounds the tail (Hoeffding 1956: the
        binomial with the same mean has the heavier upper tail beyond its mean plus one).  Default: all 1.
    sample : bool array of shape (H, n), optional
        The ``n_sample`` objects that built each hypothesis (exactly ``n_sample`` per row): neither
        evidence nor trials.  Default: the ``n_sample`` with the smallest ``u / shape``.

    Returns
    -------
    log10_nfa : array (H,)
        ``min_k`` of ``log10_tests + log10(n - s) + log10 P(Bin(n - s, 1 - e^-u_(k)) >= k - s)``;
        ``+inf`` where ``n <= s``.
    k_best : array (H,) of int
        The minimising ``k`` (0 where undefined): the inliers are the ``k_best`` smallest ``u``.

    Examples
    --------
    Ten objects within a tiny normalised residual are overwhelming evidence; ten far ones are none:

    >>> nfa, k = log10_nfa_curve(np.array([[1e-4] * 10, [3.0] * 10]), 4, 3.0)
    >>> bool(nfa[0] < -10), bool(nfa[1] > 0), int(k[0])
    (True, True, 10)
    """
    u = np.ascontiguousarray(u, dtype=np.float64)
    if u.ndim != 2:
        raise ValueError(f"u must be 2-D (hypotheses x objects), got shape {u.shape}")
    h, n = u.shape
    trials = n - n_sample
    if h == 0 or trials <= 0:
        return np.full(h, np.inf), np.zeros(h, dtype=np.int64)
    if shape is not None:
        shape = contiguous_to(np.asarray(shape, dtype=np.float64), u.shape)
    if sample is not None:
        sample = contiguous_to(np.asarray(sample, dtype=bool), u.shape)
    # The compiled kernel sorts each row, forms the chances, the binomial tails, the curve and its minimum.  Its
    # tail (a sum of the binomial's terms from the largest) agrees with scipy's incomplete beta function (boost's
    # ibeta) to 1.4e-13 in log10 down to tails of 1e-275 and is exact below, where betainc underflows early (to 0,
    # read as the floor, for a tail of 1e-299.07; tests/test_kernel.py).
    nfa = np.empty(h)
    best = np.empty(h, dtype=np.int64)
    nfa_curve(u, shape, sample, n_sample, log10_tests + log10_trials(trials), LOG10_FLOOR, nfa, best)
    return nfa, best + 1 + n_sample


_LOG10_TRIALS: dict[int, float] = {}


def log10_trials(trials: int) -> float:
    """``log10(trials)``, the count of choices of ``k`` in the curve: the same few dozen values for every image,
    made once."""
    found = _LOG10_TRIALS.get(trials)
    if found is None:
        found = _LOG10_TRIALS[trials] = float(np.log10(trials))
    return found
