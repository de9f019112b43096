"""A version-4 index's packed parts as a lookup reads them: the cell directory, the neighbours, the coordinates.

:class:`Directory` holds the cells by key: the fence (one row a page, in memory) names the page that can hold a
key; a page is decoded and checked (by the kernel, ``_kernel_qdecode.c``) the first time a lookup
reads it, into arrays kept for the next lookups (the kernel's lookup, ``_kernel_stored.c``, searches them), so a
query reads only the pages it needs.
:class:`Neighbours` gives the neighbours of anchors from their packed blocks, each block checked before use;
:class:`Coordinates` the positions of objects, each block decoded and checked the first time, then kept.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ...errors import MapFormatError
from .._kernel import qdecode_directory_pages
from ..arrays import sorted_unique
from .lookup import Section
from .packed import NB_BLOCK, PAD, PAGE_CELLS, coord_fields, dense_cells, dense_side, neighbour_fields

__all__ = ["Coordinates", "Directory", "Neighbours"]

_TOP = np.uint64(2**64 - 1)


def _corrupt(where: str, what: str) -> MapFormatError:
    return MapFormatError(f"{where}: quad index {what} (file is corrupt)")


class Directory:
    """The cells of an index: the fence ``(P + 1, 4)`` (first key, first cell, first quad, first byte of each page)
    and the packed pages of ``dir_data``; combinations ``combo_keys`` (ascending) with cell sides ``combo_cell``.

    The fence is checked when the index is opened (rows ascending, its last row the counts, every page within
    :data:`PAGE_CELLS` cells of one combination the header lists, its first cell within its combination's
    cells); a page when it is first decoded (its length, gaps, counts and quads agree with the fence).
    """

    def __init__(self, fence: np.ndarray, data: Section, combo_keys: np.ndarray, combo_cell: np.ndarray,
                 counts: tuple[int, int, int, int, int], bits: int, where: str) -> None:
        n_cells, n_quads, dir_bytes, max_cell, n_pages = counts
        self.where, self.bits, self.data, self.max_cell = where, bits, data, max_cell
        key, cell, quad, byte = (fence[:, j] for j in range(4))
        if (fence.shape[0] != n_pages + 1 or int(cell[-1]) != n_cells or int(quad[-1]) != n_quads
                or int(byte[-1]) != dir_bytes or key[-1] != _TOP or cell[0] != 0 or quad[0] != 0 or byte[0] != 0):
            raise _corrupt(where, "fence does not match the counts")
        pages = np.diff(cell.astype(np.int64))
        if n_pages and (not (key[1:] > key[:-1]).all() or pages.min() < 1 or pages.max() > PAGE_CELLS
                        or not (np.diff(quad.astype(np.int64)) >= pages).all() or not (byte[1:] > byte[:-1]).all()):
            raise _corrupt(where, "fence out of order")
        self.fence_key, self.page_cells = key[:-1], pages
        self.first_cell, self.first_quad = cell.astype(np.int64), quad.astype(np.int64)
        self.first_byte = byte.astype(np.int64)
        self.page_lk = (self.fence_key >> np.uint64(4 * bits)).astype(np.int64)
        at = np.minimum(np.searchsorted(combo_keys, self.page_lk), max(combo_keys.size - 1, 0))
        if n_pages and not (combo_keys.size and (combo_keys[at] == self.page_lk).all()):
            raise MapFormatError(f"{where}: index of another map or damaged (its directory holds label combinations "
                                 f"its header does not list); rebuild with mapdb index")
        side = dense_side(combo_cell[at]) if n_pages else np.zeros(0, np.int64)
        self.page_side = side
        self.page_dense = dense_cells(self._cells(self.fence_key), side) if n_pages else np.zeros(0, np.int64)
        if n_pages and ((self._cells(self.fence_key) >= side[:, None]).any()):
            raise _corrupt(where, "fence names a cell out of range")
        self.decoded = np.zeros(n_pages, bool)
        self.key = np.zeros(n_cells, np.uint64)  # filled page by page as lookups decode them
        self.start = np.zeros(n_cells, np.int64)
        self.count = np.zeros(n_cells, np.int64)

    def _cells(self, keys: np.ndarray) -> np.ndarray:
        mask = np.uint64((1 << self.bits) - 1)
        return np.column_stack([((keys >> np.uint64(self.bits * (3 - j))) & mask).astype(np.int64)
                                for j in range(4)]).reshape(-1, 4)

    def decode(self, pages: np.ndarray) -> None:
        """Decode and check the pages not decoded yet among ``pages``."""
        todo = sorted_unique(pages[~self.decoded[pages]])
        if not todo.size:
            return
        lo, hi, n = self.first_byte[todo], self.first_byte[todo + 1], self.page_cells[todo]
        self.data.check_ranges(lo, np.minimum(hi + PAD, self.data.array.size))
        # The widths first (a page's first two bytes): the fields they place must fill the page exactly.
        wg, wc = self.data.array[lo].astype(np.int64), self.data.array[lo + 1].astype(np.int64)
        if (wg > 32).any() or (wc > 32).any() or (-(-(16 + (n - 1) * wg + n * wc) // 8) != hi - lo).any():
            raise _corrupt(self.where, "directory page out of range")
        # The kernel's (_kernel_qdecode.c): every page decoded and checked (gaps above 0, cells inside their
        # combination's span, counts at most max_cell and summing to the page's quads), then its cells' keys,
        # counts and first quads written; nothing is written unless every page passes.
        side = self.page_side[todo]
        pages = np.column_stack([lo, n, self.page_dense[todo], side**4, side, self.page_lk[todo],
                                 self.first_quad[todo], self.first_quad[todo + 1], self.first_cell[todo]])
        if not qdecode_directory_pages(self.data.array, pages, self.bits, self.max_cell, self.key, self.count,
                                       self.start):
            raise _corrupt(self.where, "directory page out of range")
        self.decoded[todo] = True

    def first_cells(self, lk: np.ndarray) -> np.ndarray:
        """The first cell of each label combination ``lk`` (a page begins there); refused if it has none."""
        page = np.searchsorted(self.page_lk, lk)
        ok = page < self.page_lk.size
        ok[ok] = self.page_lk[page[ok]] == lk[ok]
        if not ok.all():
            raise MapFormatError(f"{self.where}: index of another map or damaged (its header lists a label "
                                 f"combination its directory has no cell of); rebuild with mapdb index")
        self.decode(page)
        return self.first_cell[page]


class Neighbours:
    """Each object's ``k`` nearest neighbours, packed in blocks of :data:`NB_BLOCK` objects (``nb_start``,
    ``nb_width``, ``nb_data``); a block's offsets and width are checked against the data the first time it is
    read."""

    def __init__(self, start: Section, width: Section, data: Section, n: int, k: int, where: str) -> None:
        self.start, self.width, self.data, self.n, self.k, self.where = start, width, data, n, k, where
        self.checked = np.zeros(width.array.size, bool)
        self.max_width = max(1, (2 * max(n, 1)).bit_length())

    def rows(self, objects: np.ndarray) -> np.ndarray:
        """Neighbour ids ``(m, k)`` (int64, each checked below ``n``) of objects (already checked below ``n``)."""
        block = objects // NB_BLOCK
        todo = sorted_unique(block[~self.checked[block]])
        if todo.size:
            lo = self.start.rows(todo).astype(np.int64)
            hi = self.start.rows(todo + 1).astype(np.int64)
            w = self.width.rows(todo).astype(np.int64)
            size = np.minimum(self.n - todo * NB_BLOCK, NB_BLOCK)
            if ((w > self.max_width).any() or (hi - lo != -(-(size * self.k * w) // 8)).any() or (lo < 0).any()
                    or (hi > self.data.array.size - PAD).any()):
                raise _corrupt(self.where, "neighbour block out of range")
            self.data.check_ranges(lo, hi + PAD)
            self.checked[todo] = True
        lo = self.start.array[block].astype(np.int64)
        ids = neighbour_fields(self.data.array, lo, self.width.array[block].astype(np.int64), objects, self.k)
        if ids.size and (ids.min() < 0 or ids.max() >= self.n):
            raise _corrupt(self.where, "holds an object id out of range")
        return ids


class Coordinates:
    """Each object's position in quanta relative to the index's origin, packed in blocks of :data:`NB_BLOCK`
    objects (``co_start``, ``co_width``, ``co_base``, ``co_data``).  A block is checked (widths at most 31 bits,
    base at least 0, its length exactly what its widths give, inside ``co_data``, every position below 2^31) and
    decoded the first time it is read; its positions are kept (int32, 8 bytes an object at most) for later reads.
    """

    def __init__(self, start: Section, width: Section, base: Section, data: Section, n: int, where: str) -> None:
        self.sections = (start, width, base, data)
        self.n, self.where = n, where
        self.decoded = np.zeros(width.array.shape[0], bool)
        self.xy = np.zeros((n, 2), np.int32)  # filled block by block (untouched pages cost no memory)
        self.check: Callable[[np.ndarray, np.ndarray], None] | None = None

    def bind(self, check: Callable[[np.ndarray, np.ndarray], None]) -> None:
        """Have ``check(ids, xy)`` (the map's page boxes) refuse every block decoded from now on; the blocks
        decoded before are decoded again."""
        self.check = check
        self.decoded[:] = False

    def rows(self, objects: np.ndarray) -> np.ndarray:
        """Positions ``(m, 2)`` (int64 quanta) of objects (already checked below ``n``)."""
        block = objects // NB_BLOCK
        todo = sorted_unique(block[~self.decoded[block]])
        if todo.size:
            self._decode(todo)
        return self.xy[objects].astype(np.int64)

    def _decode(self, todo: np.ndarray) -> None:
        start, width, base, data = self.sections
        lo = start.rows(todo).astype(np.int64)
        hi = start.rows(todo + 1).astype(np.int64)
        w = width.rows(todo).astype(np.int64)
        b = base.rows(todo).astype(np.int64)
        size = np.minimum(self.n - todo * NB_BLOCK, NB_BLOCK)
        if ((w > 31).any() or (b < 0).any() or (hi - lo != -(-(size * w.sum(axis=1)) // 8)).any() or (lo < 0).any()
                or (hi > data.array.size - PAD).any()):
            raise _corrupt(self.where, "coordinate block out of range")
        data.check_ranges(lo, hi + PAD)
        # Every block is whole but the file's last (then last in todo, which is sorted): its objects end the rows.
        objects = ((todo * NB_BLOCK)[:, None] + np.arange(NB_BLOCK)).reshape(-1)[: int(size.sum())]
        xy = coord_fields(data.array, lo, w, b, size)
        if xy.size and xy.max() >= 2**31:
            raise _corrupt(self.where, "holds a coordinate out of range")
        if self.check is not None:
            self.check(objects, xy)
        whole = todo.size - int(size[-1] < NB_BLOCK)  # stored a block (64 rows) at a time
        self.xy[: self.n // NB_BLOCK * NB_BLOCK].reshape(-1, NB_BLOCK, 2)[todo[:whole]] = (
            xy[: whole * NB_BLOCK].reshape(-1, NB_BLOCK, 2))
        self.xy[objects[whole * NB_BLOCK :]] = xy[whole * NB_BLOCK :]
        self.decoded[todo] = True

    def verify(self) -> None:
        """Check every block of the four sections."""
        for section in self.sections:
            section.verify()
