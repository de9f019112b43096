"""What a stored index's lookup reads and how: checked sections.

:class:`Section` is one memory-mapped array of the file whose 4 KiB blocks are checked (CRC-32) the first
time a lookup reads them.  A lookup's per-query work (the cells a query's ball reaches, their directory entries,
the candidates' bounds from their positions inside their cells, resolving and checking them, the ``k`` nearest)
is the kernel's (``_kernel_stored.c``), which reads only what these sections have checked;
:class:`~mapdb.match.index.stored.StoredQuadIndex` puts them together.
"""

from __future__ import annotations

import mmap
import zlib
from typing import Any

import numpy as np

from ...errors import MapFormatError
from ..arrays import sorted_unique
from .layout import BLOCK, BLOCK_BITS, pread, whole

__all__ = ["LOOKUP_CANDIDATES", "Section", "map_sections", "take_rows"]

LOOKUP_CANDIDATES = 1 << 20  # candidates handled at once by a lookup: bounds its memory
_PREFETCH_GAP = 8  # blocks: runs of wanted blocks closer than this are prefetched together


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
