"""A map's blocks as the matcher sees them: buildings or blocks for mask blobs, absent for point detections.

A map built with blocks (:mod:`mapdb.build.blocks`) stores, beside its buildings, one ``building_block``
object for every group of touching buildings: what a segmentation mask shows as one blob.  An image's
building blob may then be a building or a block, and which it is only the blob's size can tell.  So for an
image whose buildings come with pixel areas (blobs of a mask, COCO segments) the matcher searches a *folded*
view of the map, where every block is one more building: quads, verification and the a-contrario decision
all see them as such.  That counts them honestly: the building density of the null hypothesis includes the
blocks (a blob has more map objects to land near by chance), every quad that holds a block is one more
hypothesis tested, and where a blob has an area the area evidence (:mod:`mapdb.match.evidence.areas`) makes
it the nearest map object of a *compatible* area, which is the block for a merged blob and the building for
a lone house.

The folded view's quads come from two worlds, merged into one quad index (:func:`block_quads`): the map
without its blocks (what a mask shows where no buildings merge) and the map with each block in place of its
buildings (where they all do).  Folding blocks into the buildings in one world would give every building of a
block its block as a neighbour, and quads that no image holds (a blob cannot be a building and the block it
is part of).  The map stores no block's members; they are found again as the block's nearest buildings
whose areas add up to the block's (:func:`block_members_near`).

A point detector sees buildings, not blocks: for images without areas (ideal centroids, point detections)
the matcher searches a view *without* the blocks, the map it would have been without them, so their
answers are those of a map built with ``--no-blocks``.  Either view serves every query a
:class:`~mapdb.localize.localizer.Localizer` and the object indexes make (whole map, boxes, pages, scans).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

import numpy as np

from ..._scipy import cKDTree
from ...labels import BLOCK_LABEL, BUILDING_LABEL
from ...objects import Objects
from ..quads import QuadIndex

__all__ = ["BlocksView", "block_quads", "block_members_near", "has_blocks", "wants_blocks"]

T = TypeVar("T")


def has_blocks(map_: Any) -> bool:
    """Whether a map (a MetaMap or MemoryMap) holds blocks beside buildings."""
    counts = getattr(map_, "label_counts", None) or {}
    return bool(counts.get(BLOCK_LABEL)) and BUILDING_LABEL in map_.labels


def wants_blocks(codes: np.ndarray, labels: tuple[str, ...], area_px: np.ndarray | None) -> bool:
    """Whether an image is matched against blocks: some building of it comes with a pixel area (a blob).

    ``codes`` are the image objects' label codes in ``labels``, ``area_px`` their pixel areas (NaN or None
    where unknown).
    """
    if area_px is None or BUILDING_LABEL not in labels:
        return False
    building = np.asarray(codes) == labels.index(BUILDING_LABEL)
    return bool(np.isfinite(np.asarray(area_px, np.float64)[building]).any())


class BlocksView:
    """A map with its blocks folded into buildings (``fold``) or left out, in the map's own interface.

    Parameters
    ----------
    map_ : MetaMap or MemoryMap
        A map that holds blocks (:func:`has_blocks`).
    fold : bool
        True: every block is a building (mask images); False: blocks are left out (point detections).

    Examples
    --------
    >>> from mapdb.mapfile.queries import MemoryMap
    >>> m = MemoryMap(Objects.from_names([0.0, 9.0, 4.5, 50.0], [0.0] * 4,
    ...               ["building", "building", "building_block", "park"], crs="EPSG:32631",
    ...               labels=["building", "park", "building_block"]))
    >>> BlocksView(m, fold=True).all().names().tolist()
    ['building', 'building', 'building', 'park']
    >>> BlocksView(m, fold=False).all().names().tolist(), len(BlocksView(m, fold=False))
    (['building', 'building', 'park'], 3)
    >>> BlocksView(m, fold=True).label_counts
    {'building': 3, 'park': 1}
    """

    def __init__(self, map_: Any, fold: bool) -> None:
        self._map = map_
        self.fold = fold
        self._block = map_.labels.index(BLOCK_LABEL)
        self._building = map_.labels.index(BUILDING_LABEL)

    @property
    def raw(self) -> Any:
        """The map itself, its blocks under their own label (what :func:`block_quads` takes)."""
        return self._map

    def __getattr__(self, name: str) -> Any:
        # Everything the view does not change (crs, labels, bounds, quantum, path, pages_meeting, ...) is the map's.
        return getattr(self._map, name)

    def _seen(self, objects: Objects) -> Objects:
        """The objects as this view shows them."""
        is_block = objects.label == self._block
        if not is_block.any():
            return objects
        if not self.fold:
            return objects.take(~is_block)
        label = np.where(is_block, self._building, objects.label)
        return Objects(objects.x, objects.y, label, objects.area, objects.labels, objects.crs,
                       elevation=objects.elevation)

    @property
    def label_counts(self) -> dict[str, int]:
        counts = dict(self._map.label_counts)
        blocks = counts.pop(BLOCK_LABEL, 0)
        if self.fold and blocks:
            counts[BUILDING_LABEL] = counts.get(BUILDING_LABEL, 0) + blocks
        return counts

    def __len__(self) -> int:
        return sum(self.label_counts.values())

    def cached(self, key: str, factory: Callable[[], T]) -> T:
        return self._map.cached(f"{key}/blocks-{'folded' if self.fold else 'left-out'}", factory)

    def all(self) -> Objects:
        return self._seen(self._map.all())

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        return self._seen(self._map.query_bbox(minx, miny, maxx, maxy, labels))

    def query_radius(self, x: float, y: float, r: float, labels: Iterable[str] | None = None) -> Objects:
        return self._seen(self._map.query_radius(x, y, r, labels))

    def read_pages(self, pages: Iterable[int]) -> Objects:
        return self._seen(self._map.read_pages(pages))

    def scan(self) -> Iterator[Objects]:
        return (self._seen(objects) for objects in self._map.scan())

    def _check_label_counts(self, per_label: np.ndarray) -> None:
        """The map's check of a whole scan, on the counts this view shows."""
        wanted = self.label_counts
        if per_label.tolist() != [wanted.get(name, 0) for name in self._map.labels]:
            from ...errors import MapFormatError

            raise MapFormatError(f"{getattr(self._map, 'path', 'map')}: header counts per label disagree with the "
                                 "pages")


# A block's members are looked for among its this many nearest buildings, within this many times the side of a
# square of its area (and this many metres more), until their areas add up to this share of the block's.
_MEMBERS_K = 32
_MEMBERS_REACH = 1.5
_MEMBERS_SLACK_M = 10.0
_MEMBERS_SHARE = 0.9


def block_members_near(objects: Objects) -> np.ndarray:
    """Which buildings of ``objects`` (a map's, blocks under their own label) belong to one of its blocks.

    A block's members are its nearest buildings, nearest first, until their stored areas add up to 90 % of
    the block's (stored areas are quantised to 9 % steps; the block's area is its members' union).  Nearest
    first is exact for compact blocks and may swap a far member of a long terrace for a close neighbour
    of it: the quads of that place then miss, never mislead (the decision verifies every hypothesis).

    Examples
    --------
    >>> o = Objects.from_names([0.0, 10.0, 5.0, 30.0], [0.0] * 4, ["building", "building", BLOCK_LABEL, "building"],
    ...                        area=[100.0, 100.0, 200.0, 100.0])
    >>> block_members_near(o).tolist()
    [True, True, False, False]
    """
    labels = objects.labels
    members = np.zeros(len(objects), bool)
    if BLOCK_LABEL not in labels or BUILDING_LABEL not in labels:
        return members
    blocks = np.flatnonzero(objects.label == labels.index(BLOCK_LABEL))
    buildings = np.flatnonzero(objects.label == labels.index(BUILDING_LABEL))
    if not blocks.size or not buildings.size:
        return members
    k = min(_MEMBERS_K, buildings.size)
    reach = _MEMBERS_REACH * np.sqrt(objects.area[blocks]) + _MEMBERS_SLACK_M
    tree = cKDTree(np.column_stack([objects.x[buildings], objects.y[buildings]]))
    dist, near = tree.query(np.column_stack([objects.x[blocks], objects.y[blocks]]), k=k)
    dist, near = dist.reshape(blocks.size, k), near.reshape(blocks.size, k)
    found = np.isfinite(dist) & (dist <= reach[:, None])
    area = np.where(found, objects.area[buildings[np.minimum(near, buildings.size - 1)]], 0.0)
    before = np.cumsum(area, axis=1) - area  # the area of the nearer members
    take = found & (before < _MEMBERS_SHARE * objects.area[blocks][:, None])
    members[buildings[near[take]]] = True
    return members


def block_quads(objects: Objects, neighbours: int, anchors: np.ndarray | None = None,
                positions: bool = False) -> QuadIndex:
    """The folded view's quad index over a map's objects (blocks under their own label): the quads of the map
    without blocks and those of the map with each block in place of its members, the blocks labelled as
    buildings, each quad once (module docs).  ``anchors`` and ``positions`` are :class:`QuadIndex`'s."""
    labels = objects.labels
    is_block = objects.label == labels.index(BLOCK_LABEL)
    anchors = np.ones(len(objects), bool) if anchors is None else np.asarray(anchors, bool)
    plain = ~is_block
    merged = ~block_members_near(objects)
    folded = np.where(is_block, labels.index(BUILDING_LABEL), objects.label)
    objects = Objects(objects.x, objects.y, folded, objects.area, labels, objects.crs)
    parts = [QuadIndex(objects.take(keep), neighbours, anchors=anchors[keep], positions=positions)
             for keep in (plain, merged)]
    both = QuadIndex.merged(parts)
    if both.tree is None:
        return both
    # A quad far from any block is in both worlds: kept once, so that it is not tried twice.
    _, first = np.unique(np.round(both.quad_z, 3), axis=0, return_index=True)
    if first.size == len(both.quad_z):
        return both
    first.sort()
    return QuadIndex.merged([_rows(both, first)])


def _rows(index: QuadIndex, rows: np.ndarray) -> QuadIndex:
    """An index holding only these quads of ``index`` (its tree's rows and map points)."""
    assert index.tree is not None  # block_quads keeps only indexes that hold quads
    part = QuadIndex.__new__(QuadIndex)
    part.labels, part.positions = index.labels, index.positions
    part.tree = _DataOnly(index.tree.data[rows])
    part.quad_z = index.quad_z[rows]
    return part


class _DataOnly:
    """The one thing :meth:`QuadIndex.merged` reads of a part's tree: its data."""

    def __init__(self, data: np.ndarray) -> None:
        self.data = data

