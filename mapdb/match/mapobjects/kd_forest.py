"""KD-trees per label over consecutive runs of one growing set of objects, queried as if they were one.

:class:`mapdb.match.mapobjects.paged_objects.PagedObjectIndex` appends objects as queries reach new pages.  One
structure rebuilt over everything at each growth costs the whole build again for each batch of pages; a
:class:`Forest` builds a :class:`~mapdb.match.mapobjects.label_trees.LabelTrees` over the new objects only and
merges the answers of its few structures, so each object is put in a tree about once.
"""

from __future__ import annotations

import numpy as np

from .label_trees import LabelTrees

__all__ = ["MAX_TREES", "Forest"]

# A forest of more trees merges its two smallest neighbours: each query costs one call per tree.
MAX_TREES = 4


class Forest:
    """:class:`LabelTrees` over consecutive runs of objects, answering ``query``, ``count`` and ``members`` as one
    over all the objects would (indices into the whole run; a missing neighbour gets distance ``inf`` and index
    ``n``; among equal distances the lower index first, as within one).

    Parameters
    ----------
    n_labels : int
        How many labels the objects' codes range over.

    Examples
    --------
    >>> f = Forest(1)
    >>> f.add(np.array([0.0, 10.0]), np.array([0, 0]))
    >>> f.add(np.array([1.0 + 0j]), np.array([0]))
    >>> d, i = f.query(np.array([0.9 + 0j, 20.0 + 0j]), np.array([0, 0]), 2, 15.0)
    >>> d.round(1).tolist(), i.tolist()
    ([[0.1, 0.9], [10.0, inf]], [[2, 0], [1, 3]])
    >>> f.count(np.array([0.5 + 0j]), np.array([0]), 1.0).tolist()
    [2]
    """

    def __init__(self, n_labels: int) -> None:
        self.n_labels = n_labels
        self.trees: list[LabelTrees] = []
        self.starts: list[int] = []
        self.n = 0

    def __len__(self) -> int:
        return self.n

    def add(self, z: np.ndarray, label: np.ndarray) -> None:
        """Append objects at ``z`` (complex) of ``label``: they get the indices ``n .. n + len(z) - 1``."""
        if not len(z):
            return
        self.trees.append(LabelTrees(z, label, self.n_labels))
        self.starts.append(self.n)
        self.n += len(z)
        while len(self.trees) > MAX_TREES:
            sizes = [t.n for t in self.trees]
            j = int(np.argmin([sizes[i] + sizes[i + 1] for i in range(len(sizes) - 1)]))
            a, b = self.trees[j], self.trees[j + 1]
            self.trees[j : j + 2] = [LabelTrees(np.concatenate([a.z, b.z]), np.concatenate([a.label, b.label]),
                                                self.n_labels)]
            del self.starts[j + 1]

    def query(self, w: np.ndarray, labels: np.ndarray, k: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`LabelTrees.query` over all the runs: distances and indices ``(m, k)``."""
        if len(self.trees) == 1:
            return self.trees[0].query(w, labels, k, bound)
        d_parts, i_parts = [], []
        for tree, start in zip(self.trees, self.starts, strict=True):
            d, i = tree.query(w, labels, k, bound)
            d_parts.append(d)
            i_parts.append(np.where(i < tree.n, i + start, self.n))
        d, i = np.concatenate(d_parts, axis=1), np.concatenate(i_parts, axis=1)
        # Stable: among equal distances the earlier tree's object (the lower index) comes first.
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        return np.take_along_axis(d, order, axis=1), np.take_along_axis(i, order, axis=1)

    def count(self, w: np.ndarray, labels: np.ndarray, r: np.ndarray | float) -> np.ndarray:
        """:meth:`LabelTrees.count` over all the runs."""
        return np.sum([tree.count(w, labels, r) for tree in self.trees], axis=0)

    def members(self, w: np.ndarray, labels: np.ndarray, r: np.ndarray | float) -> list[np.ndarray]:
        """:meth:`LabelTrees.members` over all the runs (indices ascending)."""
        found = [tree.members(w, labels, r) for tree in self.trees]
        return [np.concatenate([hits[j] + start for hits, start in zip(found, self.starts, strict=True)])
                for j in range(len(found[0]))]
