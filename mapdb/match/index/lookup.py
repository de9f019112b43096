"""What a stored index's lookup reads and how: checked sections, the cells of a query, candidates' bounds.

:class:`Section` is one memory-mapped array of the file whose 4 KiB blocks are checked (CRC-32) the first
time a lookup reads them; :func:`query_cells` gives the cells a query's ball overlaps (their directory
entries: :mod:`~mapdb.match.index.directory`); :func:`bound_candidates` drops, from each quad's position
inside its cell, the candidates that cannot be among a query's ``k`` nearest within its radius; :class:`Best` keeps the
``k`` nearest per query.  :class:`~mapdb.match.index.stored.StoredQuadIndex` puts them together.
"""

from __future__ import annotations

import mmap
import zlib
from collections.abc import Iterator
from typing import Any

import numpy as np

from ...errors import MapFormatError
from ..arrays import sorted_unique
from .layout import BLOCK, BLOCK_BITS, cell_keys, pread, whole

__all__ = ["LOOKUP_CANDIDATES", "Best", "Section", "bound_candidates", "map_sections", "pieces", "query_cells",
           "take_rows"]

LOOKUP_CANDIDATES = 1 << 20  # candidates handled at once by a lookup: bounds its memory
_BOUND_MARGIN = 0.05  # in positions inside a cell (1/16 to 1/256 of it): far above float32 rounding
_PREFETCH_GAP = 8  # blocks: runs of wanted blocks closer than this are prefetched together
_CELL_SLACK = 1e-6  # in cells: far above float64 rounding, so no cell holding a quad within the radius is left out
_ONES = np.ones(4, np.float32)
_STEPS = np.array(np.meshgrid(*[[-1, 0, 1]] * 4, indexing="ij")).reshape(4, -1).T  # the 81 neighbour cells


def take_rows(array: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``array[index]`` for a 2-D array whose rows are contiguous: each row gathered as one opaque element.

    numpy gathers the rows of a narrow 2-D array element by element; one ``void`` element per row is
    about ten times faster (30,000 rows of 4 bytes: 42 against 420 microseconds).

    Examples
    --------
    >>> a = np.arange(12, dtype=np.uint8).reshape(4, 3)
    >>> take_rows(a, np.array([3, 0, 3])).tolist()
    [[9, 10, 11], [0, 1, 2], [9, 10, 11]]
    >>> take_rows(a, np.zeros(0, np.int64)).shape
    (0, 3)
    """
    if array.ndim != 2 or not array.flags.c_contiguous or not array.size:
        return array[index]
    rows = array.view(np.dtype((np.void, array.shape[1] * array.itemsize))).reshape(-1)
    return rows[index].view(array.dtype).reshape(-1, array.shape[1])


class Section:
    """One memory-mapped array of the file; each 4 KiB block's CRC-32 is checked the first time it is read."""

    def __init__(self, name: str, array: np.ndarray, crcs: np.ndarray, where: str,
                 mapping: mmap.mmap | None = None, offset: int = 0) -> None:
        self.mapping, self.offset = mapping, offset
        self.name = name
        self.array = array
        self.crcs = crcs
        self.where = where
        self.raw = array.reshape(-1).view(np.uint8) if array.size else np.zeros(0, np.uint8)
        self.row_bytes = max(1, int(np.prod(array.shape[1:], dtype=np.int64)) * array.itemsize)
        self.checked = np.zeros(crcs.size, bool)
        self.all_checked = crcs.size == 0

    def _check(self, blocks: np.ndarray) -> None:
        todo = sorted_unique(blocks[~self.checked[blocks]])
        if todo.size > 1:
            self._prefetch(todo)
        for b in todo.tolist():
            data = self.raw[b * BLOCK : (b + 1) * BLOCK]
            if zlib.crc32(data.data) != int(self.crcs[b]):
                raise MapFormatError(f"{self.where}: {self.name} block {b} checksum mismatch (file is corrupt)")
            self.checked[b] = True
        if todo.size and self.checked.all():
            self.all_checked = True

    def _prefetch(self, blocks: np.ndarray) -> None:
        """Have the kernel read these blocks now, together: a cold lookup then waits for one round of reads
        in parallel, not for one page fault after another."""
        if self.mapping is None or not hasattr(mmap, "MADV_WILLNEED"):
            return
        # Runs of blocks a few blocks apart are asked for in one call (a system call costs about as much as
        # reading those few pages from the page cache; from a disk, one read of them costs about one seek).
        cut = np.flatnonzero(np.diff(blocks) > _PREFETCH_GAP) + 1
        first, last = blocks[np.r_[0, cut]], blocks[np.r_[cut - 1, blocks.size - 1]]
        end = len(self.mapping)
        try:
            for a, b in zip(first.tolist(), last.tolist(), strict=True):
                start = self.offset + a * BLOCK
                start -= start % mmap.PAGESIZE  # sections start on 64-byte boundaries; madvise wants a page's
                self.mapping.madvise(mmap.MADV_WILLNEED, start, min(self.offset + (b + 1) * BLOCK, end) - start)
        except OSError:  # pages larger than a block, say: reading on demand is correct, only slower
            pass

    def rows(self, index: np.ndarray) -> np.ndarray:
        """``array[index]`` (``index`` already known to be in range), its blocks checked."""
        if not self.all_checked and index.size:
            first = (index.astype(np.int64) * self.row_bytes) >> BLOCK_BITS
            self._check(first)
            if BLOCK % self.row_bytes:
                self._check(((index.astype(np.int64) + 1) * self.row_bytes - 1) >> BLOCK_BITS)
        return take_rows(self.array, index)

    def check_ranges(self, start: np.ndarray, stop: np.ndarray) -> None:
        """Check the blocks of the rows ``start[i] .. stop[i] - 1`` (non-empty ranges, already known in range).

        Cheaper than checking each row of a range as it is read: a range lies in one or two blocks.
        """
        if self.all_checked or not start.size:
            return
        b0 = (start.astype(np.int64) * self.row_bytes) >> BLOCK_BITS
        b1 = (stop.astype(np.int64) * self.row_bytes - 1) >> BLOCK_BITS
        span = b1 - b0 + 1
        self._check(np.repeat(b0, span) + np.arange(int(span.sum())) - np.repeat(np.cumsum(span) - span, span))

    def verify(self) -> None:
        """Check every block."""
        self._check(np.arange(self.crcs.size))


def map_sections(mapping: mmap.mmap | None, fd: int, h: dict[str, Any],
                 shapes: dict[str, tuple[tuple[int, ...], str]], total_blocks: int,
                 where: str) -> tuple[dict[str, Section], np.ndarray]:
    """The sections of an index (header ``h``, its sections checked against ``shapes``) and its fence.

    The checksum table is checked, each section mapped from ``mapping`` with its blocks' CRC-32s, and
    the fence read (and checked) into memory.
    """
    layout = h["sections"]
    # The small sections are read with one system call each (the mapping reads a page per fault).
    crc_table = np.frombuffer(pread(fd, int(layout["crc"]["offset"]), 4 * total_blocks, where), "<u4")
    if zlib.crc32(crc_table.data) != int(h["crc_crc32"]):
        raise MapFormatError(f"{where}: quad index checksum table mismatch (file is corrupt)")
    sections: dict[str, Section] = {}
    for name, (shape, dtype) in shapes.items():
        sec = layout[name]
        first = whole(sec["first_block"], where, f"{name} first_block")
        blocks = -(-int(sec["length"]) // BLOCK)
        if first < 0 or first + blocks > total_blocks:
            raise MapFormatError(f"{where}: quad index checksum table does not match the sections")
        array = _mapped(mapping, dtype, int(sec["offset"]), shape)
        sections[name] = Section(name, array, crc_table[first : first + blocks], where, mapping, int(sec["offset"]))
    fence = sections.pop("fence")
    raw = pread(fd, int(layout["fence"]["offset"]), int(layout["fence"]["length"]), where)
    for b in range(fence.crcs.size):
        if zlib.crc32(raw[b * BLOCK : (b + 1) * BLOCK]) != int(fence.crcs[b]):
            raise MapFormatError(f"{where}: fence block {b} checksum mismatch (file is corrupt)")
    return sections, np.frombuffer(raw, "<u8").reshape(shapes["fence"][0]).astype(np.uint64)


def _mapped(mapping: mmap.mmap | None, dtype: str, offset: int, shape: tuple[int, ...]) -> np.ndarray:
    count = int(np.prod(shape, dtype=np.int64))
    if mapping is None or count == 0:
        return np.zeros(shape, dtype)
    return np.frombuffer(mapping, dtype=dtype, count=count, offset=offset).reshape(shape)


def query_cells(q: np.ndarray, r: np.ndarray, cell: np.ndarray, lk: np.ndarray, bits: int,
                sub_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells the balls of radius ``r`` (at most ``cell``) around invariants ``q`` reach.

    At most 3 per invariant, 81 in all, within the key's range; of those, only the cells whose box
    comes within ``r`` of ``q`` (a 4-D ball fills a third of its bounding cube: the corner cells of
    the cube hold no quad within the radius).  Returns the query row of each cell (ascending), the
    query's position relative to the cell's corner in 1/sub_cells of the cell, float32 ``(c, 4)`` (what
    :func:`bound_candidates` measures quads' positions inside their cells from), and its key (with the
    query's label key ``lk``).
    """
    s = (q + 1.0) / cell[:, None]  # the query in cell units: cell g spans [g, g + 1)
    base = np.maximum(np.floor(s), 0).astype(np.int64)
    top = (1 << bits) - 1
    cand = base[:, None, :] + _STEPS[None, :, :]
    gap = np.maximum(np.maximum(cand - s[:, None, :], s[:, None, :] - (cand + 1)), 0.0)
    reach = (r / cell)[:, None] * (1.0 + _CELL_SLACK) + _CELL_SLACK
    inside = ((gap * gap).sum(axis=2) <= reach * reach) & ((cand >= 0) & (cand <= top)).all(axis=2)
    which, step = np.nonzero(inside)
    cells = cand[which, step]
    rel = ((s[which] - cells) * sub_cells).astype(np.float32)
    return which, rel, cell_keys(lk[which], cells, bits)


def bound_candidates(which: np.ndarray, idx: np.ndarray, rel: np.ndarray, sub: np.ndarray,
                     r: np.ndarray, cell: np.ndarray, k: int, sub_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The candidates (query rows ``which``, ascending; quad positions ``idx``) worth measuring.

    Drops, from bounds on a candidate's distance given by its position ``sub`` inside its cell and its
    query's position ``rel`` relative to that cell (both in 1/sub_cells of the cell, :func:`query_cells`),
    those farther than the radius and those that cannot be among their query's ``k`` nearest.
    """
    # The candidate lies in [sub, sub + 1) per invariant: its gap to the query is max(d, -1 - d, 0) with
    # d = sub - rel, which is |d + 1/2| - 1/2 clipped at 0 (one shift and an absolute value instead of two
    # maxima: a quarter of the time).  Float32 (half the memory traffic; all of a lookup's time is here where
    # cells are crowded) with a margin far above its rounding keeps the bounds safe.
    d = sub.astype(np.float32)
    d -= rel - np.float32(0.5)
    np.abs(d, out=d)
    d -= np.float32(0.5)
    np.maximum(d, 0.0, out=d)
    d *= d
    lower = d @ _ONES  # a product with ones sums the four columns several times faster than sum(axis=1)
    reach = (r * (sub_cells / cell) + _BOUND_MARGIN).astype(np.float32)
    sel = np.flatnonzero(lower <= (reach * reach)[which])
    which, idx, lower = which[sel], idx[sel], lower[sel]
    if not idx.size or np.bincount(which).max() <= k:
        return which, idx
    # Only candidates that may be among the k nearest: the k-th smallest upper bound of a query's
    # candidates bounds its k-th nearest distance.  (Where many quads crowd a cell, this spares
    # reading and measuring most of them.)  The far corner lies max(d + 1, -d) = |d + 1/2| + 1/2 away.
    far = take_rows(sub, sel).astype(np.float32)
    far -= take_rows(rel, sel) - np.float32(0.5)
    np.abs(far, out=far)
    far += np.float32(0.5)
    far *= far
    # Upper bounds rounded up to 1/16ths in one exact integer sort key with the (ascending) row.
    upper = np.ceil(np.sqrt(far @ _ONES) * 16.0).astype(np.int64)
    key = (which << 24) | np.minimum(upper, (1 << 24) - 1)
    order = np.argsort(key)
    rank = np.arange(which.size) - np.searchsorted(which[order], which[order])
    kth = np.full(reach.size, np.inf, np.float32)
    kth[which[order[rank == k - 1]]] = upper[order[rank == k - 1]] / 16.0 + _BOUND_MARGIN
    sel = np.flatnonzero(lower <= np.minimum(kth, reach)[which] ** 2)
    return which[sel], idx[sel]


def pieces(start: np.ndarray, length: np.ndarray, limit: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Candidate quad positions of the ranges ``start + [0, length)``, at most about ``limit`` at a time.

    Yields the range number of each candidate and its position; a range longer than ``limit`` is cut.
    """
    if not start.size:
        return
    cuts = -(-length // limit)
    seg = np.repeat(np.arange(start.size), cuts)
    part = np.arange(seg.size) - np.repeat(np.cumsum(cuts) - cuts, cuts)
    s0 = start[seg] + part * limit
    n = np.minimum(length[seg] - part * limit, limit)
    ends = np.cumsum(n)
    group = (ends - 1) // limit
    bounds = np.flatnonzero(np.diff(group)) + 1
    for sel in np.split(np.arange(seg.size), bounds):
        counts = n[sel]
        total = int(counts.sum())
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        yield np.repeat(seg[sel], counts), np.repeat(s0[sel], counts) + offsets


class Best:
    """The ``k`` nearest hits per query row seen so far (ties kept in the order offered)."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.size = 0

    def offer(self, row: np.ndarray, ids: np.ndarray, dist: np.ndarray) -> None:
        """Add hits: query rows, object ids ``(h, 4)``, distances (memory stays bounded)."""
        self.parts.append((row, ids, dist))
        self.size += row.size
        if self.size > LOOKUP_CANDIDATES:
            self.parts = [self.result()]
            self.size = self.parts[0][0].size

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows (ascending), ids and distances of the ``k`` nearest hits per row, nearest first."""
        if not self.parts:
            return np.zeros(0, np.int64), np.zeros((0, 4), np.int64), np.zeros(0)
        row = np.concatenate([p[0] for p in self.parts])
        ids = np.concatenate([p[1] for p in self.parts])
        dist = np.concatenate([p[2] for p in self.parts])
        order = np.lexsort((dist, row))
        row, ids, dist = row[order], ids[order], dist[order]
        first = np.flatnonzero(np.concatenate([[True], row[1:] != row[:-1]])) if row.size else np.zeros(0, np.int64)
        rank = np.arange(row.size) - np.repeat(first, np.diff(np.append(first, row.size)))
        keep = rank < self.k
        return row[keep], ids[keep], dist[keep]
