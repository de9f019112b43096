"""Objects kept in blocks, in memory or in a temporary file, and read back in blocks in the order they came.

A country's objects do not fit comfortably in memory together with what reads them: the OSM reader appends
each block of objects it finishes to an :class:`ObjectSpool` (28 bytes an object on disk), and the build reads
them back a block at a time to choose its CRS and to project them into the map writer.  The objects read back
are exactly those appended, in the same order; only the cutting into blocks may differ.
"""

from __future__ import annotations

import ctypes
import math
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from ..errors import MapdbIOError
from ..objects import Objects

__all__ = ["RECORD_BYTES", "READ_BLOCK", "ObjectSpool", "check_room", "joined", "release_freed_memory",
           "spool_bytes"]

# Objects read back at once (7 MB of records).
READ_BLOCK = 1 << 18

_RECORD = np.dtype([("x", "<f8"), ("y", "<f8"), ("area", "<f8"), ("label", "<i4")])
RECORD_BYTES = _RECORD.itemsize

# Objects a byte of input, at most, as the room a source's spool needs is foreseen: OSM PBF gives about 6,000
# objects a MB (0.006 a byte) and XML far fewer; a CSV line of a point takes 12 bytes or more; a GeoParquet
# or GeoPackage row of a polygon 60 or more.
_OBJECTS_A_BYTE = {"osm": 0.01, "csv": 1 / 12, "layer": 1 / 40}


class ObjectSpool:
    """A sequence of objects appended in blocks: in memory, or in the file ``path`` (made on the first block).

    Parameters
    ----------
    labels : sequence of str
        The label table of every block (blocks in other tables are relabelled into it).
    crs : str or None
        The CRS of the objects.
    directory : str, optional
        Where the temporary file that holds the objects is made (named ``PREFIX*``, on the first block); None
        keeps the blocks in memory.  The file is removed by :meth:`discard` (and with the caller's temporary
        directory in any case).
    prefix : str
        The start of the file's name.

    Examples
    --------
    >>> spool = ObjectSpool(("a", "b"), "EPSG:4326")
    >>> spool.add(Objects(np.array([1.0, 2.0]), np.zeros(2), np.array([0, 1]), np.zeros(2), ("a", "b"), "EPSG:4326"))
    >>> len(spool), [len(block) for block in spool.blocks(1)]
    (2, [1, 1])
    """

    def __init__(self, labels: Sequence[str], crs: str | None, directory: str | os.PathLike[str] | None = None,
                 prefix: str = "objects-") -> None:
        self.labels = tuple(labels)
        self.crs = crs
        self.directory = None if directory is None else os.fspath(directory)
        self.prefix = prefix
        self.path: str | None = None  # the file, once made
        self._blocks: list[Objects] = []
        self._count = 0
        # The objects' box (min x, min y, max x, max y), NaN once a coordinate is not finite: lets a caller
        # see that a filter by place keeps everything without reading the objects back.
        self.bounds = (math.inf, math.inf, -math.inf, -math.inf)

    def __len__(self) -> int:
        return self._count

    def add(self, objects: Objects) -> None:
        """Append a block of objects."""
        if not len(objects):
            return
        objects = objects.relabel(self.labels)
        x, y = objects.x, objects.y
        if not (np.isfinite(x).all() and np.isfinite(y).all()):
            self.bounds = (math.nan,) * 4
        elif not math.isnan(self.bounds[0]):
            lo_x, lo_y, hi_x, hi_y = self.bounds
            self.bounds = (min(lo_x, float(x.min())), min(lo_y, float(y.min())), max(hi_x, float(x.max())),
                           max(hi_y, float(y.max())))
        if self.directory is None:
            self._blocks.append(objects)
            self._count += len(objects)
            return
        records = np.empty(len(objects), _RECORD)
        records["x"], records["y"], records["area"], records["label"] = (objects.x, objects.y, objects.area,
                                                                         objects.label)
        try:
            if self.path is None:
                handle, self.path = tempfile.mkstemp(prefix=self.prefix, dir=self.directory)
                os.close(handle)
            with open(self.path, "ab") as f:
                records.tofile(f)
        except OSError as exc:
            raise MapdbIOError(f"{self.directory}: cannot hold the objects read ({exc.strerror or exc}); "
                               "free some space or choose another directory") from None
        self._count += len(objects)

    def blocks(self, size: int = READ_BLOCK) -> Iterator[Objects]:
        """The objects in order, in blocks of at most ``size``."""
        if self.directory is None:
            for block in self._blocks:
                for start in range(0, len(block), size):
                    yield block if len(block) <= size else block.take(np.arange(start, min(start + size, len(block))))
            return
        if self.path is None:
            return
        with open(self.path, "rb") as f:
            while True:
                records = np.fromfile(f, _RECORD, count=size)
                if not records.size:
                    return
                yield Objects(records["x"], records["y"], records["label"], records["area"], self.labels, self.crs)

    def inside(self, box: Sequence[float]) -> bool:
        """Whether every object is finite and within ``box`` (min x, min y, max x, max y; edges included)."""
        lo_x, lo_y, hi_x, hi_y = self.bounds
        return lo_x >= box[0] and lo_y >= box[1] and hi_x <= box[2] and hi_y <= box[3]

    def discard(self) -> None:
        """Forget the objects and remove the file."""
        self._blocks, self._count = [], 0
        if self.path is not None:
            os.unlink(self.path)
            self.path = None


def joined(spools: Iterable[ObjectSpool], labels: Sequence[str], crs: str | None) -> Objects:
    """The objects of ``spools``, in order, as one set (each spool discarded once copied).

    Examples
    --------
    >>> a = ObjectSpool(("a",), None)
    >>> a.add(Objects(np.array([1.0]), np.zeros(1), np.zeros(1, np.int32), np.zeros(1), ("a",), None))
    >>> joined([a, ObjectSpool(("a",), None)], ("a",), None).x.tolist()
    [1.0]
    """
    spools = list(spools)
    n = sum(len(s) for s in spools)
    x, y, area = np.empty(n), np.empty(n), np.empty(n)
    label = np.empty(n, np.int32)
    at = 0
    for spool in spools:
        for block in spool.blocks():
            block = block.relabel(labels)
            end = at + len(block)
            x[at:end], y[at:end], label[at:end], area[at:end] = block.x, block.y, block.label, block.area
            at = end
        spool.discard()
    return Objects(x, y, label, area, tuple(labels), crs)


def release_freed_memory() -> None:
    """Give the C heap's freed pages back to the system; where that cannot be asked (not glibc), nothing.

    glibc keeps the pages of big transient allocations (numpy's temporaries, GEOS geometries) once the mmap
    threshold has grown, and a stage's leftovers would add to the next stage's peak.
    """
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


def spool_bytes(path: str | os.PathLike[str], objects: bool = True, footprints: bool = False) -> int:
    """The disk a source's spool may need, foreseen from its size: its ``objects`` (:data:`RECORD_BYTES`
    each, twice: a copy less the objects outside the box or off the Earth is written beside the first) and,
    for a source whose buildings form blocks, its ``footprints`` (WKB, a footprint near a tile's edge written to
    each tile it reaches: twice a layer's file, once an OSM extract's).  An upper estimate, not a promise.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "points.csv"
    >>> _ = p.write_text("lon,lat,label\\n" + "7.44,46.95,park\\n" * 1000)
    >>> spool_bytes(p)
    74760
    """
    try:
        size = os.stat(path).st_size
    except OSError:  # the reader says what is wrong with the file
        return 0
    name = os.fspath(path).lower()
    kind = "osm" if ".osm" in name else "csv" if name.endswith(".csv") else "layer"
    need = 2 * RECORD_BYTES * math.ceil(size * _OBJECTS_A_BYTE[kind]) if objects else 0
    # An OSM extract's footprints take less than its file (WKB of about 100 bytes a building): its size, once.
    return need + ((2 if kind == "layer" else 1) * size if footprints else 0)


def check_room(path: str | os.PathLike[str], directory: str | os.PathLike[str], need: int) -> None:
    """MapdbIOError, in one line, when ``directory`` has less free space than the ``need`` bytes of ``path``'s
    spool: before anything is read, not once the disk is full."""
    try:
        free = shutil.disk_usage(directory).free
    except OSError:  # the spool says what is wrong with the directory when it writes there
        return
    if need > free:
        raise MapdbIOError(f"{path}: too large for the free disk: its objects need about {_mb(need)} of temporary "
                           f"files in {directory}, which has {_mb(free)} free; free some space or choose another "
                           "directory (--index-dir)")


def _mb(n: int) -> str:
    return f"{n / 1e6:,.0f} MB" if n >= 1e6 else f"{n / 1e6:.2f} MB"
