"""Reading map files: :func:`open_map` and :class:`MetaMap`, which checks the header and directory at once and
reads, checks, decodes and caches pages as queries need them.

Reading a file never executes anything from it, and every length and count read from it is checked before
memory is allocated for it (see :mod:`~mapdb.mapfile.layout` and ``docs/format.md``).
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from .. import __version__
from ..errors import MapFormatError, MapVersionError, open_regular, reading
from ..objects import Objects
from .header import _MAX_HEADER, _check_directory, _check_header, _header_json_limit, _one_line, _parse_header_json
from .layout import _DIR_DTYPE, _MAX_QUANTA, _MAX_VERSION, _PREFIX, FORMAT_VERSION, MAGIC
from .pages import NO_ELEVATION, _BadPageError, _decode_pages
from .queries import MapBase

__all__ = [
    "MetaMap",
    "open_map",
]

# Pages decoded in one pass, by their bytes: enough to spread the fixed cost of a pass over hundreds of small
# pages, few enough that the pass's arrays stay in the processor's cache (a 1 MiB page is a batch of its own).
_BATCH_BYTES = 1 << 18
_BATCH_OBJECTS = 1 << 16  # and by objects: a pass allocates a few hundred bytes an object for a moment
_CACHE_OBJECTS = 4_000_000  # decoded objects an open map keeps in its page cache, least recently used dropped first


class MetaMap(MapBase):
    """A map file opened for queries; pages are read, checked and decoded on demand.

    Use :func:`open_map` to get one.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        where = str(self.path)
        self._file = open_regular(self.path, where, "map file")
        try:
            self._read_header(where)
        except BaseException:
            self._file.close()
            raise
        self._cache: OrderedDict[int, tuple[np.ndarray, ...]] = OrderedDict()
        self._cached_objects = 0

    def _read_header(self, where: str) -> None:
        size = os.fstat(self._file.fileno()).st_size
        self.file_size = size
        if size == 0:
            raise MapFormatError(f"{where}: empty file, not a map")
        head = self._file.read(_PREFIX.size)
        if len(head) < _PREFIX.size or not head.startswith(MAGIC):
            raise MapFormatError(f"{where}: not a mapdb map (bad magic number)")
        _, version, flags, header_len = _PREFIX.unpack(head)
        if not 1 <= version <= _MAX_VERSION:
            raise MapFormatError(f"{where}: not a valid map (format version {version})")
        if header_len > _MAX_HEADER or _PREFIX.size + header_len + 4 > size:
            raise MapFormatError(f"{where}: truncated map file (header runs past the end)")
        header_bytes = self._file.read(header_len)
        (crc,) = struct.unpack("<I", self._file.read(4))
        if zlib.crc32(head + header_bytes) != crc:
            raise MapFormatError(f"{where}: header checksum mismatch (file is corrupt)")
        # Every version keeps this frame (prefix, header, CRC), so only a version number that passed the CRC
        # is taken for a newer format rather than for damage.
        if version > FORMAT_VERSION:
            raise MapVersionError(
                f"{where}: written by a newer map format (version {version}); "
                f"this mapdb {__version__} reads up to version {FORMAT_VERSION}"
            )
        if flags != 0:
            raise MapFormatError(f"{where}: not a valid map (flags {flags:#06x}; version {version} defines none)")
        header = _parse_header_json(self._inflate_header(header_bytes, where), where)
        fields = _check_header(header, where, version)
        n_pages, self.quantum, self.crs = fields["pages"], fields["quantum"], fields["crs"]
        self.format_version = version
        # Version 2 holds each object's ground elevation: codes of elevation_step_m metres, cells of
        # elevation_cell quanta (docs/format.md, "Elevation").
        self.elevation_step: float | None = fields.get("elevation_step_m")
        self._cell: int | None = fields.get("elevation_cell")
        self.labels, self.bounds = fields["labels"], fields["bounds"]
        dir_start = _PREFIX.size + header_len + 4
        dir_len = n_pages * _DIR_DTYPE.itemsize
        if dir_start + dir_len > size:
            raise MapFormatError(f"{where}: truncated map file (page directory runs past the end)")
        directory = self._file.read(dir_len)
        if zlib.crc32(directory) != fields["directory_crc32"]:
            raise MapFormatError(f"{where}: page directory checksum mismatch (file is corrupt)")
        table = np.frombuffer(directory, _DIR_DTYPE)
        lengths = table["length"].astype(np.int64)
        end = dir_start + dir_len + int(lengths.sum())
        if end > size:
            raise MapFormatError(f"{where}: truncated map file ({size} bytes, pages need {end})")
        if end < size:
            raise MapFormatError(f"{where}: {size - end} unexpected bytes after the last page")
        self._tree = _check_directory(table, self.quantum, self.bounds, fields["count"], where)
        self._table = table
        self._offsets = dir_start + dir_len + np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        self.metadata = header

    @property
    def page_directory(self) -> np.ndarray:
        """The checked page directory: one record per page (origin and extent in quanta, count, length)."""
        return self._table

    def page_shares(self) -> np.ndarray:
        """What the file spends on one object of each page, in bytes: the page and its directory record shared
        by the page's objects, the rest of the file (prefix, header) by all the map's objects.  Summed over
        every object, the file's size."""
        page_bytes = self._table["length"].astype(np.float64) + _DIR_DTYPE.itemsize
        header = self.file_size - float(page_bytes.sum())
        return page_bytes / np.maximum(self._table["count"], 1) + header / max(len(self), 1)

    def pages_meeting(self, geometries: np.ndarray) -> np.ndarray:
        """``(2, k)`` pairs (geometry index, page index) of the pages whose box meets each shapely geometry, in
        quanta.  Page boxes are disjoint (the reader refuses a map whose boxes share a position), so a point
        of the map is in exactly one pair."""
        return self._tree.query(geometries, predicate="intersects")

    @staticmethod
    def _inflate_header(header_bytes: bytes, where: str) -> bytes:
        limit = _header_json_limit(len(header_bytes))
        unpacker = zlib.decompressobj(-15)
        try:
            text = unpacker.decompress(header_bytes, limit)
        except zlib.error:
            raise MapFormatError(f"{where}: header is not valid DEFLATE data") from None
        if unpacker.unconsumed_tail or (not unpacker.eof and len(text) >= limit):
            raise MapFormatError(f"{where}: header inflates past {limit} bytes")
        if not unpacker.eof or unpacker.unused_data:
            raise MapFormatError(f"{where}: header's DEFLATE stream does not fill its length exactly")
        return text

    @property
    def page_count(self) -> int:
        return len(self._table)

    def close(self) -> None:
        super().close()
        self._cache.clear()
        self._file.close()

    def _pages(self, indices: Iterable[int]) -> Iterator[tuple[int, tuple[np.ndarray, ...]]]:
        """(index, (x, y, label code, area)) of each page asked for, in order, each checked and decoded once.

        Pages not in the cache are read and decoded in batches of up to ``_BATCH_BYTES`` and
        ``_BATCH_OBJECTS`` (or one page, if larger), one vectorised pass a batch, so that a thousand tiny
        pages cost about what one big one does.
        """
        pending: list[int] = []
        size = objects = 0
        for i in [*indices, None]:
            if i is not None and i in self._cache:
                if not pending:
                    self._cache.move_to_end(i)
                    yield i, self._cache[i]
                    continue
            elif i is not None:
                length, count = int(self._table["length"][i]), int(self._table["count"][i])
                if not pending or (size + length <= _BATCH_BYTES and objects + count <= _BATCH_OBJECTS):
                    pending.append(i)
                    size, objects = size + length, objects + count
                    continue
            # a cached page after pending ones, a page that does not fit the batch, or the end
            if pending:
                yield from self._decode_batch(pending)
            pending, size, objects = [], 0, 0
            if i is not None:
                if i in self._cache:
                    yield i, self._cache[i]
                else:
                    pending = [i]
                    size, objects = int(self._table["length"][i]), int(self._table["count"][i])

    def _decode_batch(self, indices: list[int]) -> list[tuple[int, tuple[np.ndarray, ...]]]:
        records = self._table[indices]
        columns = self._read_batch(indices)
        done = []
        cuts = np.cumsum(records["count"].astype(np.int64))[:-1]
        for i, page in zip(indices, zip(*(np.split(a, cuts) for a in columns if a is not None), strict=True),
                           strict=True):
            self._cache[i] = page
            self._cached_objects += page[2].size
            done.append((i, page))
        while self._cached_objects > _CACHE_OBJECTS and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cached_objects -= old[2].size
        return done

    def _read_batch(self, indices: list[int]) -> tuple[Any, ...]:
        """(x, y, label code, area, elevation) of the pages' objects, read, checked and decoded (elevation in
        metres, NaN where unknown; None for a map without elevation); the cache untouched."""
        records = self._table[indices]
        payloads = []
        for i, record in zip(indices, records, strict=True):
            length = int(record["length"])
            with reading(self.path, "map file"):
                payload = os.pread(self._file.fileno(), length, int(self._offsets[i]))
            if len(payload) != length:
                raise MapFormatError(f"{self.path} page {i}: truncated")
            if zlib.crc32(payload) != record["crc"]:
                raise MapFormatError(f"{self.path} page {i}: checksum mismatch (file is corrupt)")
            payloads.append(payload)
        try:
            qx, qy, label, area, code = _decode_pages(payloads, records, len(self.labels), self._cell)
        except _BadPageError as bad:
            raise MapFormatError(f"{self.path} page {indices[bad.index]}: {bad.problem}") from None
        except (ValueError, IndexError, OverflowError, TypeError) as exc:
            # The checks are meant to leave nothing for numpy to trip on; should one be missing, the pages
            # are still reported as what they are, bad pages, and not as a crash.
            raise MapFormatError(f"{self.path} pages {indices[0]} to {indices[-1]}: malformed page data "
                                 f"({_one_line(exc, 80)})") from None
        elevation = None
        if code is not None and self.elevation_step is not None:
            elevation = np.where(code == NO_ELEVATION, np.nan, code * self.elevation_step)
        return qx * self.quantum, qy * self.quantum, label, area, elevation

    def scan(self) -> Iterator[Objects]:
        """Every page's objects in page order, in batches of about 64k objects, checked as every read is.

        The page cache is not used (a whole-map scan would only evict what queries keep there), so a scan
        may run in another thread beside queries on this map.
        """
        counts, lengths = self._table["count"].astype(np.int64), self._table["length"].astype(np.int64)
        start = 0
        while start < self.page_count:
            stop, size, objects = start + 1, int(lengths[start]), int(counts[start])
            while (stop < self.page_count and size + lengths[stop] <= _BATCH_BYTES
                   and objects + counts[stop] <= _BATCH_OBJECTS):
                size, objects, stop = size + int(lengths[stop]), objects + int(counts[stop]), stop + 1
            x, y, label, area, elevation = self._read_batch(list(range(start, stop)))
            yield Objects(x, y, label, area, self.labels, self.crs, elevation)
            start = stop

    def _page(self, i: int) -> tuple[np.ndarray, ...]:
        return next(self._pages([i]))[1]

    def read_pages(self, pages: Iterable[int]) -> Objects:
        """The objects of the pages with these indices (directory order, see :meth:`pages_meeting`),
        page after page, each page's objects as it decodes them; checked as every read is."""
        return self._objects(pages)

    def _objects(self, pages: Iterable[int]) -> Objects:
        parts = [page for _, page in self._pages(pages)]
        if not parts:
            return Objects.empty(self.labels, self.crs)
        x, y, label, area, *elevation = (np.concatenate(p) for p in zip(*parts, strict=True))
        return Objects(x, y, label, area, self.labels, self.crs, elevation[0] if elevation else None)

    def verify(self) -> None:
        """Read and check every page; raises :class:`MapFormatError` at the first bad one.

        Also checks the header's objects per label against the pages'.
        """
        per_label = np.zeros(len(self.labels), np.int64)
        for _, page in self._pages(range(self.page_count)):
            per_label += np.bincount(page[2], minlength=len(self.labels))
        self._check_label_counts(per_label)

    def _check_label_counts(self, per_label: np.ndarray) -> None:
        if per_label.tolist() != [d["count"] for d in self.metadata["labels"]]:
            raise MapFormatError(f"{self.path}: header counts per label disagree with the pages")

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        """Objects inside the box (projected metres, edges included)."""
        # The R-tree is in whole quanta; widen the box to whole quanta, then select objects exactly.  Plain
        # floats: a prior's query is one box, where numpy's per-call cost would exceed the arithmetic.
        box = [float(v) / self.quantum for v in (minx, miny, maxx, maxy)]
        if any(math.isnan(v) for v in box):
            return Objects.empty(self.labels, self.crs)
        limit = 2.0 * _MAX_QUANTA
        box = [min(max(v, -limit), limit) for v in box]
        lo_x, lo_y, hi_x, hi_y = math.floor(box[0]), math.floor(box[1]), math.ceil(box[2]), math.ceil(box[3])
        hits = np.sort(self._tree.query(shapely.box(lo_x, lo_y, hi_x, hi_y)))
        # Each page's objects in the box taken from the page itself (a prior's tile keeps about a tenth of the
        # pages it meets): no copy of whole pages to cut, one Objects made; the same objects in the same order.
        parts = []
        for _, page in self._pages(hits.tolist()):
            x, y = page[0], page[1]
            inside = (x >= minx) & (x <= maxx) & (y >= miny) & (y <= maxy)
            parts.append([column[inside] for column in page])
        if not parts:
            return Objects.empty(self.labels, self.crs)
        x, y, label, area, *elevation = (np.concatenate(p) if len(p) > 1 else p[0] for p in zip(*parts, strict=True))
        found = Objects(x, y, label, area, self.labels, self.crs, elevation[0] if elevation else None)
        return self._label_filter(found, labels)

    def all(self) -> Objects:
        objects = self._objects(range(self.page_count))
        self._check_label_counts(np.bincount(objects.label, minlength=len(self.labels)))
        return objects


def open_map(path: str | Path) -> MetaMap:
    """Open a map file for queries (also a context manager).

    The header and the page directory are read and checked at once (see ``docs/format.md``, "Limits a
    reader enforces"); each page when a query first needs it.

    Raises
    ------
    MapdbIOError
        If the file is missing, unreadable or not a regular file (a directory, a FIFO, a device).
    MapFormatError
        If it is not a map, is truncated, fails a checksum or breaks a rule of the format.
    MapVersionError
        If a newer format version wrote it.
    """
    return MetaMap(path)
