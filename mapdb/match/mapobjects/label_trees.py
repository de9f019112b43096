"""The map objects' spatial structure: a 2-D KD-tree per label, built and searched by the compiled kernel.

:class:`LabelTrees` answers the three questions :class:`~mapdb.match.mapobjects.object_index.ObjectIndex` asks of
the map's objects, each for many query points of their own labels in one call: the ``k`` nearest within a bound
(distances and indices, nearest first), how many lie within a radius, and which.  They are the answers scipy's
cKDTree over ``(x, y, label * gap)`` gave, but where distances tie (duplicate objects) the lower index comes first
(cKDTree's order was its heap's), and a call costs 4-8 microseconds where a cKDTree query cost 29-54
(``benchmarks/object_trees.py``; ``_kernel_objects.c`` describes the tree and its arithmetic).
"""

from __future__ import annotations

import numpy as np

from .._kernel import objects_build, objects_disc, objects_knn

__all__ = ["LabelTrees"]


class LabelTrees:
    """A KD-tree per label over map objects, in arrays (so it pickles; the kernel reads them at each call).

    Parameters
    ----------
    z : complex array (n,)
        The objects' positions (map metres).
    label : int array (n,)
        Their label codes, in ``0 .. n_labels - 1``.
    n_labels : int
        How many labels there are.

    Examples
    --------
    >>> t = LabelTrees(np.array([0.0, 10.0, 1.0 + 1j]), np.array([0, 0, 1]), 2)
    >>> d, i = t.query(np.array([9.0 + 0j, 1.0 + 0j]), np.array([0, 1]), 2, 50.0)
    >>> d.tolist(), i.tolist()
    ([[1.0, 9.0], [1.0, inf]], [[1, 0], [2, 3]])
    >>> t.count(np.array([0j, 0j]), np.array([0, 1]), np.array([10.0, 1.0])).tolist()
    [2, 0]
    """

    def __init__(self, z: np.ndarray, label: np.ndarray, n_labels: int) -> None:
        self.z = np.ascontiguousarray(z, np.complex128)
        self.label = np.ascontiguousarray(label, np.int64)
        self.n = int(self.z.size)
        if self.label.shape != (self.n,):
            raise ValueError(f"label must have shape ({self.n},), got {self.label.shape}")
        self.pts = np.empty((self.n, 2))
        self.pid = np.empty(self.n, np.int64)
        # At most 2 c - 1 nodes for a label of c objects (each leaf holds one at least); most hold several.
        box, node = np.empty((2 * self.n + 1, 4)), np.empty((2 * self.n + 1, 3), np.int64)
        self.root = np.empty(n_labels, np.int64)
        used = objects_build(np.ascontiguousarray(self.z.real), np.ascontiguousarray(self.z.imag), self.label,
                             self.pts, self.pid, box, node, self.root)
        self.box, self.node = box[:used].copy(), node[:used].copy()

    def __len__(self) -> int:
        return self.n

    def _tree(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.pts, self.pid, self.box, self.node, self.root

    def query(self, w: np.ndarray, labels: np.ndarray, k: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest objects of each point's label closer than ``bound``: distances and indices ``(m, k)``,
        nearest first (ties: lower index first); ``inf`` and ``n`` where there are fewer.

        ``w``: complex points (any shape, read flat), ``labels``: their label codes (as many).
        """
        w = np.ascontiguousarray(np.ravel(w), np.complex128)
        d, i = np.empty((w.size, k)), np.empty((w.size, k), np.int64)
        objects_knn(*self._tree(), w, np.ascontiguousarray(np.ravel(labels), np.int64), float(bound), self.n, d, i)
        return d, i

    def count(self, w: np.ndarray, labels: np.ndarray, r: np.ndarray | float) -> np.ndarray:
        """How many objects of each point's label lie within ``r`` (at most that far) of it: ``(m,)``."""
        w = np.ascontiguousarray(np.ravel(w), np.complex128)
        out = np.empty(w.size, np.int64)
        objects_disc(*self._tree(), w, np.ascontiguousarray(np.ravel(labels), np.int64),
                     np.ascontiguousarray(np.broadcast_to(r, w.shape), np.float64), None, out)
        return out

    def members(self, w: np.ndarray, labels: np.ndarray, r: np.ndarray | float) -> list[np.ndarray]:
        """The indices (ascending) of the objects of each point's label within ``r`` of it."""
        w = np.ascontiguousarray(np.ravel(w), np.complex128)
        labels = np.ascontiguousarray(np.ravel(labels), np.int64)
        r = np.ascontiguousarray(np.broadcast_to(r, w.shape), np.float64)
        offsets = np.zeros(w.size + 1, np.int64)
        np.cumsum(self.count(w, labels, r), out=offsets[1:])
        out = np.empty(int(offsets[-1]), np.int64)
        objects_disc(*self._tree(), w, labels, r, offsets, out)
        return np.split(out, offsets[1:-1])
