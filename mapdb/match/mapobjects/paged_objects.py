"""The whole map's object index for a big map, read page by page where queries land.

A lost-in-space answer verifies its hypotheses against the whole map's objects.  On a map of millions
of objects, building that :class:`~mapdb.match.mapobjects.object_index.ObjectIndex` means decoding every page and a
KD-tree over all of them: on a 5M-object map, 2.5 s to decode, then the trees over them, before the
first answer, which itself needs only the pages around its few hundred hypotheses.

:class:`PagedObjectIndex` answers every :class:`ObjectIndex` query *exactly as the whole map's index
would*, from only the pages those queries reach.  Before a query runs, the boxes it can reach (each
query point with its search radius: the nearest-object reach, a gate, a density disc) are checked
against what is loaded; the pages that meet a box not yet covered are decoded and appended, with KD-trees
over the new objects only (a :class:`~mapdb.match.mapobjects.kd_forest.Forest` answers as one structure over all of
them would).  Objects are only ever appended, so an object's index stays valid.  The label counts,
the region's bounds and area (hence the global densities and the label gap) are the whole map's, from
its header.  A ``k``-th-nearest density is first taken from what is loaded: the distance found there
bounds the true one from above, so covering that distance and asking again gives the exact answer.  A
nearest-object search likewise reads ``FIRST_REACH_M`` around each point first, and its whole reach only
for the points that found nothing that near.

The index suits the first answers of a process; a long-running one switches to the whole map's index once
it is built (:class:`mapdb.localize.Localizer` builds it in a background thread after the first answer).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
import shapely

from ...objects import Objects, concat
from ..arrays import sorted_unique
from .kd_forest import Forest
from .object_index import Neighbours, ObjectIndex

__all__ = ["PAGED_FROM_OBJECTS", "PagedObjectIndex", "WholeMapObjects"]

# Coverage is tracked in square cells of this side (metres) and whole numbers of cells of reach: a query
# point's box is rounded out to the cells it touches, so queries nearby share one check.
COVER_CELL_M = 100.0
# Maps of at least this many objects are read page by page until their whole index is built (the whole
# index costs about 0.9 us an object: 0.2 s here).
PAGED_FROM_OBJECTS = 250_000
# The nearest-object searches first read this far (metres) around each point (see ``nearest``).
FIRST_REACH_M = 50.0


class PagedObjectIndex(ObjectIndex):
    """An :class:`ObjectIndex` over a :class:`~mapdb.mapfile.reader.MetaMap` that reads pages as queries need them.

    Parameters
    ----------
    map_ : MetaMap
        An open map file; its pages are read through it (the caller keeps it open).

    Examples
    --------
    >>> from mapdb.mapfile.reader import open_map
    >>> from mapdb.mapfile.writer import write_map
    >>> import tempfile, pathlib
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "m.mapdb"
    >>> o = Objects.from_names([0.0, 10.0, 5000.0], [0.0, 0.0, 3000.0], ["b", "b", "p"], crs="EPSG:32631")
    >>> _ = write_map(path, o)
    >>> idx = PagedObjectIndex(open_map(path))
    >>> len(idx), idx.counts.tolist()
    (0, [2, 1])
    >>> dist, which = idx.nearest(np.array([[1.0 + 0j]]), np.array([0]), idx.density)
    >>> round(float(dist[0, 0]), 2), 0 < len(idx) <= 3
    (1.0, True)
    """

    def __init__(self, map_) -> None:
        self._map = map_
        self._loaded = np.zeros(map_.page_count, bool)
        self._checked = np.zeros(0, np.int64)
        # The region, its area and the label gap are the whole map's (its bounds); objects come as pages do.
        ObjectIndex.__init__(self, Objects.empty(map_.labels, map_.crs), bounds=map_.bounds)
        counts = map_.label_counts
        self.counts = np.array([counts.get(name, 0) for name in map_.labels], np.int64)
        self.density = np.maximum(self.counts, 1) / self.area
        self._forest = Forest(len(self.labels))

    @property
    def loaded_pages(self) -> int:
        """How many of the map's pages are loaded."""
        return int(self._loaded.sum())

    @property
    def trees(self) -> int:
        """How many KD-trees the loaded objects are held in (see :class:`Forest`)."""
        return len(self._forest.trees)

    def _cover(self, points: np.ndarray, radius: np.ndarray | float) -> bool:
        """Load every page within ``radius`` (metres, per point or one) of each point; True if any was."""
        points = np.asarray(points, np.complex128)
        radius = np.asarray(np.broadcast_to(np.asarray(radius, np.float64), points.shape)).ravel()
        points = points.ravel()
        keep = np.isfinite(points)
        points, radius = points[keep], radius[keep]
        if not points.size:
            return False
        if not np.isfinite(radius).all() or float(np.max(radius)) > 1e7:
            return self._load(np.flatnonzero(~self._loaded))
        g = COVER_CELL_M
        cells = np.column_stack([np.floor(points.real / g), np.floor(points.imag / g),
                                 np.ceil(np.maximum(radius, 0.0) / g)]).astype(np.int64)
        # One key per (cell, reach): 26 bits each way for cells (a planet in 1 km cells), 11 for reach.
        key = ((cells[:, 0] & 0x3FFFFFF) << 37) | ((cells[:, 1] & 0x3FFFFFF) << 11) | np.minimum(cells[:, 2], 2047)
        key, first = np.unique(key, return_index=True)
        new = ~np.isin(key, self._checked, assume_unique=True)
        if not new.any():
            return False
        self._checked = sorted_unique(np.concatenate([self._checked, key[new]]))  # np.union1d imports numpy.ma
        cx, cy, reach = cells[first[new]].T
        q = self._map.quantum
        boxes = shapely.box((cx - reach) * g / q, (cy - reach) * g / q, (cx + 1 + reach) * g / q,
                            (cy + 1 + reach) * g / q)
        pages = np.unique(self._map.pages_meeting(boxes)[1])
        return self._load(pages[~self._loaded[pages]])

    def _load(self, pages: np.ndarray) -> bool:
        if not pages.size:
            return False
        new = self._map.read_pages(np.sort(pages).tolist())
        self._loaded[pages] = True
        # Appended: the loaded objects keep their indices, and only the new ones need a tree.
        self.z = np.concatenate([self.z, new.x + 1j * new.y])
        self.label = np.concatenate([self.label, new.label.astype(np.int64)])
        self._area = np.concatenate([self._area, new.area])
        self._log_area = None
        self._forest.add(new.x + 1j * new.y, new.label)
        self.tree = self._forest if len(self) else None
        return True

    def _reaches(self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray) -> np.ndarray:
        """The reach :meth:`ObjectIndex.nearest` gives each projected object ``w`` (same shape)."""
        return self._reach(density, np.broadcast_to(img_label, np.shape(w)).ravel()).reshape(np.shape(w))

    def local_density(self, centres: np.ndarray, radius: np.ndarray) -> np.ndarray:
        self._cover(centres, radius)
        return super().local_density(centres, radius)

    def nearest(self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray,
                exclude: np.ndarray | None = None, near: Neighbours | None = None) -> tuple[np.ndarray, np.ndarray]:
        # ``near`` is never made for this index (:meth:`ObjectIndex.neighbours` gives None): its pages are
        # read as each query reaches them.
        # The reach :meth:`ObjectIndex.nearest` gives each object: beyond it nothing counts.  Most objects
        # find theirs close by, so the pages within ``FIRST_REACH_M`` are read first: an answer no farther
        # than what is loaded all round is the whole map's (anything nearer would be loaded too).  Only the
        # others are searched to their whole reach, a few hundred metres (a map of many similar places has
        # hypotheses all over it: reading their whole reaches read a fifth of a 5M-object map).
        reach = self._reaches(w, img_label, density)
        first = np.minimum(reach, FIRST_REACH_M)
        self._cover(w, first)
        dist, which = super().nearest(w, img_label, density, exclude)
        farther = ~(dist <= first) & (reach > first)
        if farther.any() and self._cover(w[farther], reach[farther]):
            dist, which = super().nearest(w, img_label, density, exclude)
        return dist, which

    def nearest_compatible(self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray,
                           exclude: np.ndarray | None, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Its neighbours beyond the nearest are searched to the whole reach.
        self._cover(w, self._reaches(w, img_label, density))
        return super().nearest_compatible(w, img_label, density, exclude, lo, hi)

    def disc_members(self, centres: np.ndarray, radius: np.ndarray, codes: np.ndarray) -> list[list[np.ndarray]]:
        self._cover(centres, radius)
        return super().disc_members(centres, radius, codes)

    def at(self, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
        self._cover(points, 1e-3)
        return super().at(points, labels)

    def within(self, w: np.ndarray, img_label: np.ndarray, gate: float, k: int) -> tuple[np.ndarray, ...]:
        self._cover(w, gate)
        return super().within(w, img_label, gate, k)

    def knn_density(self, w: np.ndarray, img_label: np.ndarray, k: int,
                    near: Neighbours | None = None) -> np.ndarray:
        labels = np.broadcast_to(img_label, np.shape(w))
        kk = np.minimum(k, self.counts[labels])
        grow = FIRST_REACH_M
        while True:
            density = super().knn_density(w, img_label, k)
            # The k-th distance behind each density (inf where the loaded pages hold fewer than k): the true
            # one is no larger, so once that far is loaded all round the answer is the whole map's.  Read out to
            # it in growing steps (FIRST_REACH_M, then fourfold): from the few pages around a place, a rare
            # label's k-th distance can be kilometres too long, and covering it at once read 3,700 of a
            # 5M-object world's 8,192 pages for one first answer (1.5 s from a cold page cache; now 0.1 s).
            with np.errstate(divide="ignore"):
                reach = np.where(kk > 0, np.sqrt(np.maximum(kk - 1, 1) / (math.pi * density)), 0.0)
            if self._cover(w, np.minimum(reach, grow) * (1.0 + 1e-9) + 1e-6):
                continue  # more is loaded: the distances can only shrink
            if (reach <= grow).all() or self._loaded.all():
                return density
            grow *= 4.0


class WholeMapObjects:
    """The whole map's object index as soon as it can answer: built at once for a small map; for a big
    map file, a :class:`PagedObjectIndex` first, and the whole index built in a background thread from the
    second request on (a process that answers one image never pays for it), used once it is ready.

    Both give the same answers, so an answer does not depend on which one served it.

    Parameters
    ----------
    map_ : MetaMap or MemoryMap
    paged_from : int, optional
        Map files of at least this many objects start paged (default ``PAGED_FROM_OBJECTS``).

    Examples
    --------
    >>> from mapdb.mapfile.queries import MemoryMap
    >>> whole = WholeMapObjects(MemoryMap(Objects.from_names([0.0, 50.0], [0.0, 0.0], ["park"] * 2)))
    >>> len(whole.index())
    2
    """

    def __init__(self, map_: Any, paged_from: int | None = None) -> None:
        paged_from = PAGED_FROM_OBJECTS if paged_from is None else paged_from
        self._map = map_
        self._requests = 0
        self._thread: threading.Thread | None = None
        self._built: ObjectIndex | None = None
        if hasattr(map_, "scan") and len(map_) >= paged_from:
            self._index: ObjectIndex = PagedObjectIndex(map_)
        else:
            self._index = ObjectIndex(map_.all(), bounds=map_.bounds)

    @property
    def paged(self) -> bool:
        """Whether requests are still served page by page."""
        return isinstance(self._index, PagedObjectIndex)

    def index(self, lost_in_space: bool = True) -> ObjectIndex:
        """The index to answer one image with.

        Only lost-in-space answers (``lost_in_space``) count towards building the whole index: an answer
        with a prior reads the few pages around it, and a flight's stay near its path.
        """
        self._requests += lost_in_space
        if self._built is not None:
            self._index, self._built = self._built, None
        elif self._requests > 1:
            self.start()
        return self._index

    def start(self) -> None:
        """Start building the whole index in the background, if it is needed and not started."""
        if self.paged and self._thread is None:
            self._thread = threading.Thread(target=self._build, name="mapdb-whole-map-objects", daemon=True)
            self._thread.start()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the background build (if one runs); True once the whole index serves the next request."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self._built is not None or not self.paged

    def _build(self) -> None:
        try:
            objects = concat(list(self._map.scan()), self._map.labels)
            self._map._check_label_counts(np.bincount(objects.label, minlength=len(self._map.labels)))
            self._built = ObjectIndex(objects, bounds=self._map.bounds)
        except Exception:  # a closed or damaged map: the paged index keeps serving, and says what is wrong
            return
