"""Quads: four map or image objects and their similarity invariants, and the map's index of them.

Every object and three of its nearest neighbours form a *quad*.  Its two most distant points ``A``, ``B``
define a frame in which ``A = 0`` and ``B = 1`` (complex numbers); the other two points' coordinates in that
frame, ``t = (P - A) / (B - A)``, are four numbers invariant to translation, rotation and scale, but not to
reflection (images are not mirrored).  The labels of ``A, B, C, D`` are part of the key.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from ..objects import Objects
from ._kernel import map_canonical, map_quads, quads_build, quads_lookup
from .nearest import decided_nearest_xy

__all__ = ["LABEL_GAP", "POSITION_WEIGHT", "QuadIndex", "QuadTree", "canonical_quads", "label_keys", "lookup_parts",
           "mergeable_parts", "near_only", "neighbour_quads"]

# The label key is a fifth tree coordinate, spaced far beyond any lookup radius so that a lookup never
# crosses from one label combination to another.
LABEL_GAP = 100.0

# The six point pairs of a quad and, for each, the two other points.
PAIRS = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])

OTHERS = np.array([(2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1)])

# Below this many points the kernel keeps each quad where it first comes; from it on it sorts them (np.unique's
# order), as the numpy code did when a quad no longer packed into one int64 key (n**4 < 2**63).
_PACKABLE = 55_000

# An index built with ``positions`` also holds each quad's centroid, in tree units per metre.  Small beside
# lookup radii (0.01-0.3: a kilometre adds 0.01), so among quads that match an image quad about as well
# the nearest to the prior come first, and a pattern repeated across a tile (a street grid, a lattice) does
# not fill a lookup's hits with copies outside the prior's disc.
POSITION_WEIGHT = 1e-5


def neighbour_quads(xy: np.ndarray, neighbours: int, *, anchors: np.ndarray | None = None) -> np.ndarray:
    """Quads ``(m, 4)``: each (anchor) point with every triple of its ``neighbours`` nearest.

    Rows are sorted point indices, each quad once (the same four points reached from different anchors), where it
    first comes.  (An image's quads, round by round, are :func:`~mapdb.match.hypotheses.anchor_batches`'.)

    Examples
    --------
    >>> q = neighbour_quads(np.array([[0, 0], [1, 0], [0, 1], [1, 1], [5, 5.0]]), 3)
    >>> q.shape[1], len(q) > 0, bool(np.all(np.diff(q, axis=1) > 0))
    (4, True, True)
    """
    xy = np.asarray(xy, np.float64)
    found = _anchor_neighbours(xy[:, 0], xy[:, 1], neighbours, anchors)
    if found is None:
        return np.zeros((0, 4), dtype=np.int64)
    nn, anchor_ids = found
    # The kernel keeps each quad where it first comes, or from _PACKABLE points on sorts them (np.unique's order).
    quads = map_quads(nn, anchor_ids, len(xy), len(xy) >= _PACKABLE, None, None, 0, False, LABEL_GAP,
                      POSITION_WEIGHT)[0]
    return np.frombuffer(quads, np.int64).reshape(-1, 4)


def _anchor_neighbours(x: np.ndarray, y: np.ndarray, neighbours: int, anchors: np.ndarray | None,
                       z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Each anchor's ``neighbours`` nearest others among points ``x, y`` (cKDTree's, whose order among equal distances
    decides which quads exist: :mod:`.nearest`) and the anchors' ids, as int64; None when there are no quads
    (fewer than three neighbours, no anchor).  ``z``: the points as complex numbers, if at hand."""
    n = len(x)
    k = min(neighbours, n - 1)
    anchor_ids = np.arange(n) if anchors is None else np.flatnonzero(anchors)
    if k < 3 or not anchor_ids.size:
        return None
    nn = decided_nearest_xy(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64), anchor_ids, k, z)
    return nn, np.ascontiguousarray(anchor_ids, np.int64)


def near_only(rows: np.ndarray, quad_z: np.ndarray, near: tuple[complex, float] | None
              ) -> tuple[np.ndarray, np.ndarray]:
    """The hits (query rows, map points ``(h, 4)``) whose quad's centroid lies within ``near = (centre,
    reach)``, all of them when ``near`` is None: a prior applied to an index that knows no positions, after
    its nearest hits were taken.

    Examples
    --------
    >>> rows, quad_z = near_only(np.array([0, 1]), np.array([[0, 2, 2j, 2 + 2j], [10, 12, 10j, 12 + 10j]]), (0j, 5.0))
    >>> rows.tolist(), near_only(rows, quad_z, None)[0].tolist()
    ([0], [0])
    """
    if near is None:
        return rows, quad_z
    keep = np.abs(quad_z.mean(axis=1) - near[0]) <= near[1]
    return rows[keep], quad_z[keep]


def canonical_quads(zq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canonical vertex order and invariants of quads given as complex points ``(m, 4)``.

    ``A, B`` is the most distant pair, ordered so that ``Re t_C + Re t_D <= 1``; ``C, D`` are ordered
    so that ``Re t_C <= Re t_D``.

    Returns
    -------
    order : (m, 4) int
        Positions (0..3) of ``A, B, C, D`` in each input row.
    invariants : (m, 4) float
        ``Re t_C, Im t_C, Re t_D, Im t_D``.
    ab : (m,) float
        Length of ``AB``.
    """
    # The kernel's row by row (_kernel_map_quads.c): numpy's arithmetic, the same bits.
    m = len(zq)
    order, inv, ab = np.empty((m, 4), np.int64), np.empty((m, 4)), np.empty(m)
    map_canonical(np.ascontiguousarray(zq, np.complex128), order, inv, ab)
    return order, inv, ab

def label_keys(labels: np.ndarray, n_labels: int) -> np.ndarray:
    """One number per ordered label 4-tuple ``(m, 4)``."""
    base = max(n_labels, 1)
    key = np.zeros(len(labels), dtype=np.float64)
    for j in range(4):
        key = key * base + labels[:, j]
    return key


class TreePoints(Protocol):
    """What every quad index's ``tree`` holds: its tree points (a :class:`QuadTree`, or only the points, as the parts
    of :func:`~mapdb.match.mapobjects.blocks_view.block_quads` before they are merged)."""

    data: np.ndarray


class QuadTree:
    """A quad index's tree points ``data`` (:class:`QuadIndex`) and the kernel's k-d tree over them
    (``_kernel_quads.c``), which answers its lookups; pickled as its points (the tree is built again)."""

    def __init__(self, data: np.ndarray) -> None:
        self.data = data
        self.handle = quads_build(np.ascontiguousarray(data, np.float64))

    def __reduce__(self) -> tuple:
        return (QuadTree, (self.data,))


class QuadIndex:
    """Quad invariants of map objects in a k-d tree (:class:`QuadTree`): where image quads are looked up.

    A quad index keeps the map coordinates of its quads' points (not indices into a map), so that
    indexes of separate tiles of a map can be built, cached and searched independently.

    Parameters
    ----------
    objects : Objects
        Map objects in projected metres: the anchors and everything that may be their neighbours.
    neighbours : int
        Neighbours per anchor in the quads (``FastOptions.map_neighbours``).
    anchors : bool array, optional
        Which objects anchor quads (default all): a tile anchors its own objects and reads a margin
        around them for their neighbours.
    positions : bool
        Also index where each quad lies (its centroid, weighted by ``POSITION_WEIGHT``), so that a lookup
        can be restricted to a disc *before* its ``k`` nearest are taken (``near``); such an index is only
        looked up with ``near``.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> idx = QuadIndex(Objects.from_names(rng.uniform(0, 100, 50), rng.uniform(0, 100, 50), ["b"] * 50))
    >>> idx.n_quads > 0, idx.quad_z.shape[1]
    (True, 4)
    """

    # The box of the quads' positions (tree units), made on the first lookup that needs it (for every index,
    # however made: merged, or a part of blocks_view's).
    _where: tuple[float, float, float, float] | None = None

    def __init__(self, objects: Objects, neighbours: int = 8, anchors: np.ndarray | None = None,
                 positions: bool = False) -> None:
        self.labels = tuple(objects.labels)
        self.positions = positions
        z = np.ascontiguousarray(objects.x + 1j * objects.y, np.complex128)
        found = _anchor_neighbours(objects.x, objects.y, neighbours, anchors, z) if len(objects) >= 4 else None
        self.tree: TreePoints | None = None
        zq = np.zeros((0, 4), np.complex128)
        if found is not None:
            # One kernel call: the distinct quads, those with a frame (four objects on one spot, duplicates in the
            # sources, have none) in canonical order, and their tree points.
            label = np.ascontiguousarray(objects.label, np.int64)
            # (the ids are not wanted: not copied out of the kernel's scratch)
            _, points, flat = map_quads(*found, len(objects), len(objects) >= _PACKABLE, z, label, len(self.labels),
                                        positions, LABEL_GAP, POSITION_WEIGHT, False)
            zq = np.frombuffer(flat, np.complex128).reshape(-1, 4)
            if len(zq):
                self.tree = QuadTree(np.frombuffer(points, np.float64).reshape(len(zq), 7 if positions else 5))
        self.quad_z = zq

    @property
    def n_quads(self) -> int:
        return int(len(self.quad_z))

    def lookup(
        self, invariants: np.ndarray, labels: np.ndarray, radius: np.ndarray, k: int,
        near: tuple[complex, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Map quads near image quads: the query row of each hit and the hit's four map points.

        Parameters
        ----------
        invariants : (m, 4) float
            ``Re t_C, Im t_C, Re t_D, Im t_D`` of each image quad in its (canonical) vertex order.
        labels : (m, 4) int
            Label codes of ``A, B, C, D``.
        radius : (m,) float
            Lookup radius in invariant space, per query.
        k : int
            At most this many nearest map quads per query.
        near : (centre, reach), optional
            Only quads whose centroid lies within ``reach`` metres of ``centre`` (complex): a prior applied
            before the ``k`` nearest are taken when the index holds positions, after otherwise.

        Returns
        -------
        rows : (h,) int
            Query row of each hit.
        map_z : (h, 4) complex
            The hit's map points ``A, B, C, D`` (projected metres).
        """
        return lookup_parts([(self, near)], invariants, labels, radius, k)

    def _out_of_reach(self, place: complex, reach: float) -> bool:
        """No quad's position (tree units) within ``reach`` of ``place``, by the box of the positions (per axis no
        nearer than any position, in floating point too): the lookup would keep no hit, its tree query is saved."""
        x0, y0, x1, y1 = self._box()
        dx = max(x0 - place.real, 0.0, place.real - x1)
        dy = max(y0 - place.imag, 0.0, place.imag - y1)
        return dx * dx + dy * dy > reach * reach

    def _box(self) -> tuple[float, float, float, float]:
        """The box of the quads' positions (tree units), made once."""
        if self._where is None:
            assert self.tree is not None
            lo, hi = self.tree.data[:, 5:7].min(axis=0).tolist(), self.tree.data[:, 5:7].max(axis=0).tolist()
            self._where = (lo[0], lo[1], hi[0], hi[1])
        return self._where

    @classmethod
    def merged(cls, parts: Sequence[QuadIndex]) -> QuadIndex:
        """One index over the quads of several (the tiles around a prior): one lookup instead of one per part.

        Examples
        --------
        >>> rng = np.random.default_rng(0)
        >>> parts = [QuadIndex(Objects.from_names(rng.uniform(0, 100, 30), rng.uniform(0, 100, 30), ["b"] * 30))
        ...          for _ in range(2)]
        >>> QuadIndex.merged(parts).n_quads == parts[0].n_quads + parts[1].n_quads
        True
        """
        merged = cls.__new__(cls)
        parts, merged.labels, merged.positions = mergeable_parts(parts)
        if not parts:
            merged.tree = None
            merged.quad_z = np.zeros((0, 4), np.complex128)
            return merged
        merged.tree = QuadTree(np.concatenate([q.tree.data for q in parts if q.tree is not None]))
        merged.quad_z = np.concatenate([q.quad_z for q in parts])
        return merged


def mergeable_parts(parts: Sequence[QuadIndex]) -> tuple[list[QuadIndex], tuple[str, ...], bool]:
    """The indexes among ``parts`` that hold quads, their labels and whether they hold positions: what one index
    over them (:meth:`QuadIndex.merged`, :class:`~mapdb.match.quad_block.QuadBlock`) shares.

    Raises
    ------
    ValueError
        If some hold positions and others do not.
    """
    held = [q for q in parts if q.tree is not None]
    positions = bool(held) and held[0].positions
    if any(q.positions != positions for q in held):
        raise ValueError("cannot merge quad indexes with and without positions")
    return held, held[0].labels if held else (), positions


def lookup_parts(
    parts: Sequence[tuple[QuadIndex, tuple[complex, float] | None]], invariants: np.ndarray, labels: np.ndarray,
    radius: np.ndarray, k: int,
) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`QuadIndex.lookup` of several indexes, each with its ``near``: their hits index by index, as
    successive lookups give them, in one kernel call where the indexes share their labels, positions and ``near``
    (a prior's tiles).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> idx = QuadIndex(Objects.from_names(rng.uniform(0, 100, 30), rng.uniform(0, 100, 30), ["b"] * 30))
    >>> inv = idx.tree.data[:3, :4]
    >>> rows, _ = lookup_parts([(idx, None), (idx, None)], inv, np.zeros((3, 4), np.int64), np.full(3, 1e-9), 1)
    >>> rows.tolist()
    [0, 1, 2, 0, 1, 2]
    """
    empty = np.zeros(0, np.int64), np.zeros((0, 4), np.complex128)
    parts = [(ix, near) for ix, near in parts if ix.tree is not None]
    if not parts or not len(invariants):
        return empty
    first, near = parts[0]
    if len(parts) > 1 and any(hasattr(ix, "searched") or (ix.positions, len(ix.labels), nr)
                              != (first.positions, len(first.labels), near) for ix, nr in parts):
        found = [lookup_parts([part], invariants, labels, radius, k) for part in parts]
        return np.concatenate([f[0] for f in found]), np.concatenate([f[1] for f in found])
    bound = float(radius.max())
    place, reach = 0j, 0.0  # the prior's disc in tree units
    if first.positions:
        if near is None:
            raise ValueError("an index with positions is looked up near a place")
        place, reach = complex(near[0]) * POSITION_WEIGHT, POSITION_WEIGHT * float(near[1])
        parts = [(ix, nr) for ix, nr in parts if not ix._out_of_reach(place, reach)]
        if not parts:
            return empty
        bound += reach
    # A block (quad_block.QuadBlock): its parts searched together, as one index (or, looked up often, merged).
    searched = getattr(first, "searched", None)
    indexes, joint = searched() if searched is not None else ([ix for ix, _ in parts], False)
    trees = [_kernel_tree(ix) for ix in indexes]
    key = label_keys(labels, len(first.labels))
    np.multiply(key, LABEL_GAP, out=key)
    if not first.positions and near is not None:
        # Equal distances (a regular pattern's copies) ranked nearest the prior's place, so that the k nearest kept
        # before near_only are those it keeps where the map repeats itself.
        place = complex(near[0])
    rows, flat = quads_lookup(
        tuple(trees), tuple(np.ascontiguousarray(ix.quad_z, np.complex128) for ix in indexes),
        np.ascontiguousarray(invariants, np.float64), key, np.ascontiguousarray(radius, np.float64), int(k),
        place.real, place.imag, reach, bound, not first.positions and near is not None, joint)
    hit_rows, map_z = np.frombuffer(rows, np.int64), np.frombuffer(flat, np.complex128).reshape(-1, 4)
    return (hit_rows, map_z) if first.positions else near_only(hit_rows, map_z, near)


def _kernel_tree(index: QuadIndex) -> object:
    """The kernel's tree of an index (made now for one holding only its points, as a view's parts do)."""
    tree = index.tree
    if not isinstance(tree, QuadTree):
        assert tree is not None
        tree = index.tree = QuadTree(tree.data)
    return tree.handle
