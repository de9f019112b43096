"""What the compiled kernel's fused queries read of an in-memory object index, in the types they take, made once.

A round's screen (:func:`mapdb.match.screen._screened_fused`) passes the index's tree, positions, label counts,
densities and reaches to five kernel calls; each of the wrappers it replaced converted and looked them up again.
:func:`fused_of` (:meth:`~mapdb.match.mapobjects.object_index.ObjectIndex.fused`) makes them once an index, and again
if the index's tree, positions, counts or densities are replaced; they are kept beside the index (weakly: they go
with it), not in it, so that it pickles as before.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple, Protocol

import numpy as np

from .label_trees import LabelTrees

__all__ = ["FusedArrays", "fused_of"]


class _Index(Protocol):
    """What :func:`fused_of` reads of an :class:`~mapdb.match.mapobjects.object_index.ObjectIndex` (named so, not
    imported: that module imports this one)."""

    z: np.ndarray
    counts: np.ndarray
    density: np.ndarray
    labels: tuple[str, ...]
    bounds: tuple[float, ...]
    gap: float
    area: float

    def fused_tree(self) -> LabelTrees | None: ...

    def label_reach(self, density: np.ndarray) -> np.ndarray: ...


# Each index's arrays, with what they were made from (compared by identity: a replaced array makes them again).
_MADE: weakref.WeakKeyDictionary[_Index, tuple[tuple[object, ...], FusedArrays]] = weakref.WeakKeyDictionary()


class FusedArrays(NamedTuple):
    """An in-memory index's arrays as the kernel's fused queries read them."""

    tree: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # the LabelTrees' five arrays
    n: int  # objects (the index a missing neighbour gets)
    z: np.ndarray  # positions, complex128
    counts: np.ndarray  # objects a label, int64
    density: np.ndarray  # the region's densities (L,)
    density_2d: np.ndarray  # the same, (1, L)
    reach: np.ndarray  # each label's reach under them (ObjectIndex.label_reach)
    present: np.ndarray  # the labels with objects
    n_labels: int
    trees: list[tuple[np.ndarray, ...]]  # [tree]: what the density kernel reads
    disc: np.ndarray  # the unit disc's sample the density kernel measures a disc's share inside the bounds with
    bounds: np.ndarray  # (minx, miny, maxx, maxy)
    half_gap: float  # the longest search bound
    kd_floor: float  # the density of a label absent from the map (1 / area)


def fused_of(index: _Index, disc: np.ndarray) -> FusedArrays | None:
    """The :class:`FusedArrays` of ``index`` when it holds its objects in one tree that answers its queries
    (:meth:`~mapdb.match.mapobjects.object_index.ObjectIndex.fused_tree`), else None; ``disc``: the density kernel's
    sample of the unit disc."""
    tree = index.fused_tree()
    if tree is None:
        return None
    made = _MADE.get(index)
    if made is None or made[0][0] is not tree or made[0][1] is not index.z or made[0][2] is not index.counts or (
            made[0][3] is not index.density):
        made = _MADE[index] = (tree, index.z, index.counts, index.density), _arrays(index, tree, disc)
    return made[1]


def _arrays(index: _Index, tree: LabelTrees, disc: np.ndarray) -> FusedArrays:
    density = index.density
    return FusedArrays(tree._tree(), len(tree), np.ascontiguousarray(index.z, np.complex128),
                       np.ascontiguousarray(index.counts, np.int64), density,
                       np.ascontiguousarray(np.atleast_2d(density), np.float64), index.label_reach(density),
                       np.flatnonzero(index.counts), len(index.labels), [tree._tree()], disc,
                       np.array(index.bounds, np.float64), 0.5 * index.gap, 1.0 / index.area)
