"""KD-trees over consecutive runs of one growing point array, queried as if they were one cKDTree.

:class:`mapdb.match.mapobjects.paged_objects.PagedObjectIndex` appends objects as queries reach new pages.  One tree
rebuilt over everything at each growth costs the whole build again (0.2-0.4 s per million objects) for
each batch of pages; a :class:`Forest` builds a tree over the new points only and merges the answers of
its few trees, so each object is put in a tree about once.
"""

from __future__ import annotations

import numpy as np

from ..._scipy import cKDTree, quick_tree

__all__ = ["MAX_TREES", "Forest"]

# A forest of more trees merges its two smallest neighbours: each query costs one call per tree.
MAX_TREES = 4


class Forest:
    """KD-trees over consecutive runs of points, answering ``query`` and ``query_ball_point`` as one
    :class:`scipy.spatial.cKDTree` over all the points would (indices into the whole run; a missing
    neighbour gets distance ``inf`` and index ``n``, as cKDTree gives).

    Examples
    --------
    >>> f = Forest()
    >>> f.add(np.array([[0.0, 0.0], [10.0, 0.0]]))
    >>> f.add(np.array([[1.0, 0.0]]))
    >>> d, i = f.query(np.array([[0.9, 0.0], [20.0, 0.0]]), k=2, distance_upper_bound=15.0)
    >>> d.round(1).tolist(), i.tolist()
    ([[0.1, 0.9], [10.0, inf]], [[2, 0], [1, 3]])
    >>> f.query_ball_point(np.array([[0.5, 0.0]]), 1.0, return_length=True).tolist()
    [2]
    """

    def __init__(self) -> None:
        self.trees: list[cKDTree] = []
        self.starts: list[int] = []
        self.n = 0

    def add(self, points: np.ndarray) -> None:
        """Append ``points`` (``(m, d)``): they get the indices ``n .. n + m - 1``."""
        if not len(points):
            return
        self.trees.append(quick_tree(points))
        self.starts.append(self.n)
        self.n += len(points)
        while len(self.trees) > MAX_TREES:
            sizes = [t.n for t in self.trees]
            j = int(np.argmin([sizes[i] + sizes[i + 1] for i in range(len(sizes) - 1)]))
            self.trees[j : j + 2] = [quick_tree(np.concatenate([self.trees[j].data, self.trees[j + 1].data]))]
            del self.starts[j + 1]

    def query(self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest points of each row of ``x`` (``(m, d)``) within ``distance_upper_bound``: distances
        and indices, ``(m,)`` for ``k == 1``, else ``(m, k)``."""
        if len(self.trees) == 1:
            return self.trees[0].query(x, k=k, distance_upper_bound=distance_upper_bound)
        m = len(x)
        d_parts, i_parts = [], []
        for tree, start in zip(self.trees, self.starts, strict=True):
            d, i = tree.query(x, k=k, distance_upper_bound=distance_upper_bound)
            d, i = d.reshape(m, k), i.reshape(m, k)
            d_parts.append(d)
            i_parts.append(np.where(i < tree.n, i + start, self.n))
        d, i = np.concatenate(d_parts, axis=1), np.concatenate(i_parts, axis=1)
        # Stable: among equal distances the earlier tree's point comes first.
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        d, i = np.take_along_axis(d, order, axis=1), np.take_along_axis(i, order, axis=1)
        return (d[:, 0], i[:, 0]) if k == 1 else (d, i)

    def query_ball_point(self, x: np.ndarray, r: np.ndarray | float, return_length: bool = False) -> np.ndarray:
        """Indices of the points within ``r`` of each row of ``x`` (sorted lists, an object array), or their
        numbers with ``return_length``."""
        if len(self.trees) == 1:
            return self.trees[0].query_ball_point(x, r, return_length=return_length)
        found = [tree.query_ball_point(x, r, return_length=return_length) for tree in self.trees]
        if return_length:
            return np.sum(found, axis=0)
        out = np.empty(len(x), dtype=object)
        for j in range(len(x)):
            out[j] = sorted(idx + start for hits, start in zip(found, self.starts, strict=True) for idx in hits[j])
        return out
