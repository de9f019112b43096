"""A quad index bound to its map: what the index records of the map, and the checks that it still describes it.

An index file's checksums only say that its bytes are the ones its writer wrote; a forger (or a tool that
rewrote the file) can make them right again.  What makes an index trustworthy is that it agrees with the
map it serves, which is checked in three steps, each where it costs little:

* **when the index is opened with its map** (:func:`check_identity`): the header's ``map`` section (the
  map's header CRC-32, file size, object count, quantum, labels, the ``origin`` of the index's
  coordinates and ``pages_sha256``, the SHA-256 of the map's page directory) must equal what the open
  map gives (:func:`map_identity`; the directory is already in memory, so this costs microseconds);
* **the first time a lookup reads an object's block of coordinates** (:class:`PageBoxes`): each of the
  block's objects must lie inside its page's box from the map's directory, so that an index whose
  coordinates were shifted, scaled, zeroed or permuted between pages is refused before its first answer;
* **every quad a lookup resolves** (:func:`check_filed`): its invariants, recomputed from the coordinates,
  must put it in the cell it was found in and at the position inside the cell that the index stores, so
  that coordinates, neighbours, anchors, triples, directory or cell sides altered in any way a lookup
  reads are refused instead of answering from the wrong quads.

Where the map's objects are decoded anyway (a map small enough for the localizer to hold whole),
:func:`check_positions` compares every coordinate with them exactly.  Each failure is one
:class:`~mapdb.errors.MapFormatError`: ``MAP.qidx: index of another map or damaged (why); rebuild with
mapdb index MAP``.
"""

from __future__ import annotations

import hashlib
import os
import struct
from typing import Any

import numpy as np

from ...errors import MapFormatError, open_regular, reading
from ...mapfile.layout import MAGIC as MAP_MAGIC
from ...mapfile.reader import MetaMap
from .._kernel import qdecode_page_boxes
from .layout import cell_keys, cells_of

__all__ = ["IDENTITY_KEYS", "PageBoxes", "check_filed", "check_identity", "check_positions", "map_identity",
           "mismatch"]

_MAP_PREFIX = struct.Struct("<8sHHI")  # the map file's own prefix (mapdb.mapfile.layout), for its header CRC
# What the header's ``map`` section holds, in the order checked (the cheapest and most telling first).
IDENTITY_KEYS = ("count", "labels", "quantum", "origin", "file_size", "header_crc32", "pages_sha256")


def mismatch(where: str, why: str, map_path: Any = None) -> MapFormatError:
    """The one error of an index that does not describe its map."""
    rebuild = "mapdb index" + (f" {map_path}" if map_path is not None else "")
    return MapFormatError(f"{where}: index of another map or damaged ({why}); rebuild with {rebuild}")


def map_identity(map_: MetaMap) -> dict[str, Any]:
    """What an index records of its map (its header's ``map`` section) and checks when it is opened.

    The map's header CRC-32, file size, object count, quantum and labels; the ``origin`` of the index's
    coordinates (the smallest page origin, in quanta: the smallest object position, pages being tight
    boxes); and ``pages_sha256``, the SHA-256 of the map's page directory (every page's origin, extent,
    count, length and the CRC-32 of its bytes: a digest of its object content, read when the map is opened,
    so it costs microseconds).  A rewritten map, another map of the same size, or an index whose quantum
    or origin was altered does not pass for the indexed one.
    """
    where = str(map_.path)
    with reading(where, "map file"), open_regular(map_.path, where, "map file") as f:
        head = f.read(_MAP_PREFIX.size)
        if len(head) < _MAP_PREFIX.size or not head.startswith(MAP_MAGIC):
            raise MapFormatError(f"{where}: not a mapdb map (bad magic number)")
        header_len = _MAP_PREFIX.unpack(head)[3]
        f.seek(_MAP_PREFIX.size + header_len)
        tail = f.read(4)
        size = os.fstat(f.fileno()).st_size
    if len(tail) < 4:
        raise MapFormatError(f"{where}: truncated map file (header runs past the end)")
    table = map_.page_directory
    return {
        "header_crc32": struct.unpack("<I", tail)[0],
        "file_size": size,
        "count": len(map_),
        "quantum": float(map_.quantum),
        "labels": list(map_.labels),
        "origin": [int(table["ox"].min()), int(table["oy"].min())] if len(table) else [0, 0],
        "pages_sha256": hashlib.sha256(table.tobytes()).hexdigest(),
    }


def check_identity(recorded: dict[str, Any], map_: MetaMap, where: str) -> None:
    """Refuse (:func:`mismatch`) unless the header's ``map`` section is exactly what ``map_`` gives."""
    theirs = map_identity(map_)
    for key in IDENTITY_KEYS:
        if recorded.get(key) != theirs[key]:
            raise mismatch(where, f"its {key.replace('_', ' ')} differs from {map_.path}'s", map_.path)


class PageBoxes:
    """The map's page boxes (quanta relative to the index's origin), to check the index's coordinates as they are
    decoded (:class:`~mapdb.match.index.directory.Coordinates` calls :meth:`check` with each block it decodes).

    Parameters
    ----------
    table : numpy structured array
        The map's page directory (``MetaMap.page_directory``): ``ox, oy, ex, ey, count``.
    origin : (int, int)
        The index's origin in quanta (already checked against the directory).
    where, map_path
        For the error message.
    """

    def __init__(self, table: np.ndarray, origin: tuple[int, ...], where: str, map_path: Any) -> None:
        self.start = np.concatenate([[0], np.cumsum(table["count"].astype(np.int64))])
        self.lo = np.column_stack([table["ox"] - origin[0], table["oy"] - origin[1]]).astype(np.int64)
        self.hi = self.lo + np.column_stack([table["ex"], table["ey"]]).astype(np.int64)
        self.checked = np.zeros(len(table), bool)  # pages some of whose objects were checked
        self.where, self.map_path = where, map_path

    def check(self, ids: np.ndarray, xy: np.ndarray) -> None:
        """Refuse unless every object ``ids`` (in range) at ``xy`` (quanta, ``(m, 2)``) lies inside its page's box
        (the kernel's, ``_kernel_qdecode.c``: a block's objects are each a search of the pages' first objects)."""
        page = qdecode_page_boxes(np.ascontiguousarray(ids, np.int64), np.ascontiguousarray(xy, np.int64),
                                  self.start, self.lo, self.hi, self.checked)
        if page >= 0:
            raise mismatch(self.where, f"coordinates of objects of map page {page} lie outside the page",
                           self.map_path)


def check_filed(inv: np.ndarray, key: np.ndarray, sub: np.ndarray, cell: np.ndarray, bits: int, sub_bits: int,
                where: str) -> None:
    """Refuse unless each resolved quad lies in the cell it was found in, at its stored place inside it.

    ``inv`` are the quads' invariants recomputed from the index's coordinates (bit for bit the writer's
    for a genuine index), ``key`` the cells' keys, ``sub`` the stored positions inside them and ``cell``
    the cell sides (of each quad's label combination); positions are in 1/``2 ** sub_bits`` of a cell.
    """
    if not key.size:
        return
    with np.errstate(all="ignore"):  # forged coordinates can make degenerate quads: NaN, refused below
        cells, mine = cells_of(inv, cell, 1 << sub_bits)
        lk = (key >> np.uint64(4 * bits)).astype(np.int64)
        ok = np.isfinite(inv).all(axis=1) & (cell_keys(lk, cells, bits) == key) & (mine == sub).all(axis=1)
    if not ok.all():
        raise mismatch(where, "a quad recomputed from its objects is not where the index files it")


def check_positions(coordinates: np.ndarray, x: np.ndarray, y: np.ndarray, where: str, map_path: Any) -> None:
    """Refuse unless the index's coordinates of every object (complex, in id order) are the map's ``x, y``."""
    if coordinates.shape != x.shape or not (np.array_equal(coordinates.real, x)
                                            and np.array_equal(coordinates.imag, y)):
        raise mismatch(where, "its coordinates are not the map's objects", map_path)
