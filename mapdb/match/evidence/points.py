"""Point residuals, the evidence model every stage starts from: how far each projected image object lies from its
map object, and the per-axis error of a similarity fitted to such pairs.

An image object projected by a hypothesis lands at ``w``; its residual is the distance to the map object it
is associated with, normalised by the label's density into ``u = lambda pi r^2`` (:mod:`mapdb.match.nfa`).
The other models refine this one: :mod:`~mapdb.match.evidence.areas` (stored areas), :mod:`~mapdb.match.evidence.blobs`
(cut blobs' ellipses) and :mod:`~mapdb.match.evidence.relief` (the final fit, relief weighed radially).
"""

from __future__ import annotations

import numpy as np

__all__ = ["GATE_SIGMAS", "first_per_map_object", "residual_sigmas"]

# Residual sigmas within which an association is kept (refinement's second net, the final assignment's gate).
GATE_SIGMAS = 3.5


def residual_sigmas(dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Per-axis error of each row's similarity fitted to its inliers: ``sqrt(sum r^2 / (2k - 4))``.

    ``dist`` and ``inlier`` are ``(H, n)``; 4 parameters are fitted, so ``2k - 4`` degrees of freedom
    (at least 1).
    """
    k = np.add.reduce(inlier, axis=1)  # an integer count (as inlier.sum), without the method's Python wrapper
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.add.reduce(np.where(inlier, dist**2, 0.0), axis=1) / np.maximum(2 * k - 4, 1))


def first_per_map_object(mid: np.ndarray, dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Mask keeping, per row and map object, only the closest of the image objects matched to it."""
    h, n = mid.shape
    keep = np.ones((h, n), bool)
    r, c = np.nonzero(inlier)
    if r.size == 0:
        return keep
    order = np.lexsort((dist[r, c], mid[r, c], r))
    r, c = r[order], c[order]
    dup = np.zeros(r.size, bool)
    dup[1:] = (r[1:] == r[:-1]) & (mid[r[1:], c[1:]] == mid[r[:-1], c[:-1]])
    keep[r[dup], c[dup]] = False
    return keep
