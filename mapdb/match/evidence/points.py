"""Point residuals, the evidence model every stage starts from: how far each projected image object lies from its
map object, and the per-axis error of a similarity fitted to such pairs.

An image object projected by a hypothesis lands at ``w``; its residual is the distance to the map object it
is associated with, normalised by the label's density into ``u = lambda pi r^2`` (:mod:`mapdb.match.nfa`).
The other models refine this one: :mod:`~mapdb.match.evidence.areas` (stored areas), :mod:`~mapdb.match.evidence.blobs`
(cut blobs' ellipses) and :mod:`~mapdb.match.evidence.relief` (the final fit, relief weighed radially).
"""

from __future__ import annotations

import numpy as np

from .._kernel import first_per_map_object as _first_per_map_object
from .._kernel import refine_inliers as _refine_inliers
from .._kernel import residual_sigmas as _residual_sigmas
from .._kernel import verify_errors as _verify_errors

__all__ = ["GATE_SIGMAS", "first_per_map_object", "fit_errors", "refinement_inliers", "residual_sigmas"]

# Residual sigmas within which an association is kept (refinement's second net, the final assignment's gate).
GATE_SIGMAS = 3.5


def residual_sigmas(dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Per-axis error of each row's similarity fitted to its inliers: ``sqrt(sum r^2 / (2k - 4))``.

    ``dist`` and ``inlier`` are ``(H, n)``; 4 parameters are fitted, so ``2k - 4`` degrees of freedom
    (at least 1).

    Examples
    --------
    >>> residual_sigmas(np.array([[3.0, 4.0, 0.0, 0.0, 9.0]]), np.array([[True, True, True, True, False]])).tolist()
    [2.5]
    """
    dist = np.ascontiguousarray(dist, dtype=np.float64)
    if dist.ndim != 2:
        raise ValueError(f"dist must be 2-D (hypotheses x objects), got shape {dist.shape}")
    out = np.empty(dist.shape[0])
    _residual_sigmas(dist, _mask(inlier, dist.shape), out)
    return out


def fit_errors(z: np.ndarray, dist: np.ndarray, inlier: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's error model over its inliers: the residual sigma (:func:`residual_sigmas` of the row's inliers
    alone: their own pairwise sum)
    and the prediction variance factor at the image centre
    (:func:`~mapdb.match.geometry.prediction_variance_factor` of ``z[inlier[j]]``), in the compiled kernel.

    Examples
    --------
    >>> s, v = fit_errors(np.array([-1, 1, 1j, -1j]), np.array([[1.0, 1.0, 1.0, 1.0]]), np.ones((1, 4), bool))
    >>> s.tolist(), v.tolist()
    ([1.0], [0.25])
    """
    dist = np.ascontiguousarray(dist, np.float64)
    sigma = np.empty(dist.shape[0])
    variance = np.empty(dist.shape[0])
    _verify_errors(np.ascontiguousarray(z, np.complex128), dist, np.ascontiguousarray(inlier, bool), sigma, variance)
    return sigma, variance


def first_per_map_object(mid: np.ndarray, dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Mask keeping, per row and map object, only the closest of the image objects matched to it (of equally
    close ones, the first).

    Examples
    --------
    >>> first_per_map_object(np.array([[7, 7, 2, 7]]), np.array([[2.0, 1.0, 5.0, 1.0]]), np.ones((1, 4), bool)).tolist()
    [[False, True, True, False]]
    """
    mid = np.ascontiguousarray(mid, dtype=np.int64)
    if mid.ndim != 2:
        raise ValueError(f"mid must be 2-D (hypotheses x objects), got shape {mid.shape}")
    keep = np.empty(mid.shape, bool)
    _first_per_map_object(mid, np.ascontiguousarray(dist, dtype=np.float64), _mask(inlier, mid.shape), keep)
    return keep


def refinement_inliers(u: np.ndarray, dist: np.ndarray, mid: np.ndarray, k_best: np.ndarray) -> np.ndarray:
    """The inliers a refinement round fits to, ``(H, n)``: the ``k_best`` smallest normalised residuals ``u`` of
    each row (its NFA's choice), then, a generous second net, every object within ``GATE_SIGMAS`` sigmas of the
    current fit (sigma from those inliers, :func:`residual_sigmas`), so that the fit uses every true
    correspondence as the bound does; of the inliers matched to one map object only the closest
    (:func:`first_per_map_object`).  ``dist`` and ``mid``: each object's distance to its map object and that
    object's index (``inf`` where none), ``k_best``: ``(H,)``.

    Examples
    --------
    >>> u = np.array([[0.01, 0.02, 2.0, 0.03, 0.01, 0.02]])
    >>> dist = np.array([[1.0, 1.4, 14.0, 1.7, 1.0, np.inf]])
    >>> refinement_inliers(u, dist, np.array([[0, 1, 2, 3, 3, -1]]), np.array([5])).astype(int).tolist()
    [[1, 1, 0, 0, 1, 0]]
    """
    u = np.ascontiguousarray(u, dtype=np.float64)
    if u.ndim != 2:
        raise ValueError(f"u must be 2-D (hypotheses x objects), got shape {u.shape}")
    inlier = np.zeros(u.shape, bool)
    if u.shape[1]:
        _refine_inliers(u, np.ascontiguousarray(dist, dtype=np.float64), np.ascontiguousarray(mid, dtype=np.int64),
                        np.ascontiguousarray(k_best, dtype=np.int64), GATE_SIGMAS, inlier)
    return inlier


def _mask(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A contiguous boolean ``(H, n)`` mask (the kernel's checks refuse any other shape)."""
    mask = np.ascontiguousarray(mask, dtype=bool)
    if mask.shape != shape:
        raise ValueError(f"the mask must have shape {shape}, got {mask.shape}")
    return mask
