"""The nearest others of a map tile's anchors, which decide which quads exist (:mod:`~mapdb.match.quads`).

Among points at distinct distances the nearest are the same for every exact search; where distances tie, the order is
the search's own, and a map's quads were made with cKDTree's (``quick_tree``).  :func:`decided_nearest` takes the rows
the distances decide from the kernel's object tree (``_kernel_objects.c``) and asks cKDTree for the others only.
"""

from __future__ import annotations

import math

import numpy as np

from .._scipy import cKDTree, quick_tree
from ._kernel import objects_build, objects_knn

__all__ = ["decided_nearest", "decided_nearest_xy", "nearest_others"]


def nearest_others(tree: cKDTree, xy: np.ndarray, ids: np.ndarray, k: int, workers: int = 1) -> np.ndarray:
    """The ``k`` nearest other points of points ``ids`` (rows nearest first), from ``tree`` over ``xy``.

    Examples
    --------
    >>> xy = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]])
    >>> nearest_others(cKDTree(xy), xy, np.arange(3), 1).ravel().tolist()
    [1, 0, 1]
    """
    _, nn = tree.query(xy[ids], k + 1, workers=workers)
    if np.array_equal(nn[:, 0], ids):
        # Each point first in its own row (no other on it), as in all but a few rows of a map: the rest are its
        # others, as the general case below takes them (a row holds a point once), without its masks.
        return nn[:, 1:]
    # The point itself is usually first, but not when another point sits on it: drop it wherever it is.
    own = nn == ids[:, None]
    own[~own.any(axis=1), -1] = True
    return nn[~own].reshape(ids.size, k)


# Two distances closer than this (relative) are taken for a tie by decided_nearest: far beyond the rounding of a
# squared distance (a few units in the last place), so that rows it decides are decided for every exact search.
_TIE = 1e-9


def decided_nearest(xy: np.ndarray, ids: np.ndarray, k: int) -> np.ndarray:
    """:func:`nearest_others` over ``quick_tree(xy)``, the same rows: ``(len(ids), k)`` int64, C-contiguous.

    A row whose point and its ``k + 1`` nearest others (its ``k`` and the next, when there is one) lie at distinct
    distances, each nearer than the next by more than ``_TIE`` of it, has one answer, whatever the exact search: the
    kernel's object tree gives it (``_kernel_objects.c``, half cKDTree's time on a map tile).  The other rows (equal
    distances, points on one spot, non-finite or vanishing distances) are cKDTree's, whose heap's order among equal
    distances no other search reproduces: asked of the same tree over the same points, row by row as before.

    Examples
    --------
    >>> xy = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [7.0, 0.0], [-2.5, 0.0]])
    >>> decided_nearest(xy, np.arange(5), 2).tolist()
    [[1, 4], [0, 2], [1, 0], [2, 1], [0, 1]]
    """
    xy = np.asarray(xy, np.float64)
    return decided_nearest_xy(np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1]), ids, k)


def decided_nearest_xy(x: np.ndarray, y: np.ndarray, ids: np.ndarray, k: int, z: np.ndarray | None = None
                       ) -> np.ndarray:
    """:func:`decided_nearest` of points ``x, y`` (C-contiguous float64; ``z``, if given, them as complex)."""
    n, m = len(x), min(k + 2, len(x))
    if not 0 < k < n:
        raise ValueError(f"need 0 < k < {n} points, got k = {k}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):  # no distance decides: every row cKDTree's
        xy = np.column_stack([x, y])
        return np.ascontiguousarray(nearest_others(quick_tree(xy), xy, ids, k), np.int64)
    label, query_label = np.zeros(n, np.int64), np.zeros(ids.size, np.int64)
    pts, pid, root = np.empty((n, 2)), np.empty(n, np.int64), np.empty(1, np.int64)
    box, node = np.empty((2 * n + 1, 4)), np.empty((2 * n + 1, 3), np.int64)
    objects_build(x, y, label, pts, pid, box, node, root)
    d, i = np.empty((ids.size, m)), np.empty((ids.size, m), np.int64)
    objects_knn(pts, pid, box, node, root, z[ids] if z is not None else x[ids] + 1j * y[ids], query_label, math.inf,
                n, d, i)
    # Undecided: the point not first, or a distance not beyond the one before by more than _TIE of it, or not beyond
    # 1e-100 (where a squared distance loses digits); two overflowing distances (inf) are not beyond each other.
    # The coordinates are finite: no distance is NaN.
    with np.errstate(over="ignore"):
        limit = d[:, :-1] * (1.0 + _TIE)
    np.maximum(limit, 1e-100, out=limit)
    undecided = (d[:, 1:] <= limit).any(axis=1)
    undecided |= i[:, 0] != ids
    nn = np.ascontiguousarray(i[:, 1:k + 1])
    if undecided.any():
        xy = np.column_stack([x, y])
        nn[undecided] = nearest_others(quick_tree(xy), xy, np.asarray(ids)[undecided], k)
    return nn
