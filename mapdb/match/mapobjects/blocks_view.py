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

A point detector sees buildings, not blocks: for images without areas (ideal centroids, point detections)
the matcher searches a view *without* the blocks, the map it would have been without them, so their
answers are those of a map built with ``--no-blocks``.  Either view serves every query a
:class:`~mapdb.localize.localizer.Localizer` and the object indexes make (whole map, boxes, pages, scans).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

import numpy as np

from ...labels import BLOCK_LABEL, BUILDING_LABEL
from ...objects import Objects

__all__ = ["BlocksView", "has_blocks", "wants_blocks"]

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
        return Objects(objects.x, objects.y, label, objects.area, objects.labels, objects.crs)

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
