"""The numpy code the kernel's block decoding (``_kernel_qdecode.c``) replaced, kept verbatim as the tests'
reference (tests/test_kernel_qdecode.py): ``packed.neighbour_fields``, ``coord_fields`` (per object),
``page_fields``, ``cells_of_dense``, ``Directory.decode``, ``Coordinates._decode`` and ``PageBoxes.check`` as they
were at 51e92c9, each taking the object it was a method of as ``self``."""

from __future__ import annotations

import numpy as np

from mapdb.errors import MapFormatError
from mapdb.mapfile.codec import _read_fields, _unzigzag
from mapdb.match.arrays import sorted_unique
from mapdb.match.index.binding import PageBoxes, mismatch
from mapdb.match.index.directory import Coordinates, Directory
from mapdb.match.index.packed import NB_BLOCK, PAD


def _corrupt(where: str, what: str) -> MapFormatError:
    return MapFormatError(f"{where}: quad index {what} (file is corrupt)")


def neighbour_fields(data: np.ndarray, block_start: np.ndarray, width: np.ndarray, objects: np.ndarray,
                     k: int) -> np.ndarray:
    """Neighbour ids ``(m, k)`` (int64) of ``objects`` from the packed data, given their blocks' first byte and
    width (both already checked against the data's length)."""
    pos = (objects % NB_BLOCK)[:, None] * k + np.arange(k)
    start = block_start[:, None] * 8 + pos * width[:, None]
    z = _read_fields(data, start.reshape(-1), np.repeat(width, k))
    return objects[:, None] + _unzigzag(z).reshape(-1, k)


def coord_fields(data: np.ndarray, block_start: np.ndarray, width: np.ndarray, base: np.ndarray,
                 objects: np.ndarray) -> np.ndarray:
    """Coordinates ``(m, 2)`` (int64 quanta) of ``objects`` from the packed data, given their blocks' first byte,
    widths ``(m, 2)`` and bases ``(m, 2)`` (all already checked against the data's length)."""
    at = block_start * 8 + (objects % NB_BLOCK) * (width[:, 0] + width[:, 1])
    xy = _read_fields(data, np.column_stack([at, at + width[:, 0]]).reshape(-1), width.reshape(-1))
    return base + xy.astype(np.int64).reshape(-1, 2)


def page_fields(data: np.ndarray, start: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode directory pages (first byte ``start``, ``cells`` cells each; ranges already checked).

    Returns, for every cell of the pages in order, the dense gap from the page's first cell (int64, 0 for
    the first), its quad count, and each page's two widths ``(p, 2)``.
    """
    head = _read_fields(data, np.repeat(start * 8, 2) + np.tile([0, 8], start.size), np.full(2 * start.size, 8))
    w = head.astype(np.int64).reshape(-1, 2)
    rank = np.arange(int(cells.sum())) - np.repeat(np.cumsum(cells) - cells, cells)
    page = np.repeat(np.arange(start.size), cells)
    base = start[page] * 8 + 16
    wg, wc = w[page, 0], w[page, 1]
    gap_at = base + (rank - 1) * wg
    is_first = rank == 0
    gaps = _read_fields(data, np.where(is_first, base, gap_at), np.where(is_first, 0, wg)).astype(np.int64)
    count_at = base + (cells[page] - 1) * wg + rank * wc
    counts = _read_fields(data, count_at, wc).astype(np.int64) + 1
    total = np.cumsum(gaps)  # restarted at each page (its first gap is 0)
    return total - np.repeat(total[np.cumsum(cells) - cells], cells), counts, w


def cells_of_dense(dense: np.ndarray, side: np.ndarray) -> np.ndarray:
    """The cell coordinates ``(m, 4)`` of dense cell numbers (:func:`dense_cells` inverted)."""
    out = np.empty((dense.size, 4), np.int64)
    d = dense.astype(np.int64)
    for j in (3, 2, 1):
        out[:, j] = d % side
        d = d // side
    out[:, 0] = d
    return out


def decode(self: Directory, pages: np.ndarray) -> None:
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
    offsets, counts, _ = page_fields(self.data.array, lo, n)
    span = self.page_side[todo] ** 4
    page = np.repeat(np.arange(todo.size), n)
    rank = np.arange(page.size) - np.repeat(np.cumsum(n) - n, n)
    step = np.diff(offsets, prepend=-1)
    if (((step <= 0) & (rank > 0)).any() or (self.page_dense[todo][page] + offsets >= span[page]).any()
            or counts.max() > self.max_cell
            or (np.bincount(page, counts, todo.size) != self.first_quad[todo + 1] - self.first_quad[todo]).any()):
        raise _corrupt(self.where, "directory page out of range")
    dense = self.page_dense[todo][page] + offsets
    cells = cells_of_dense(dense, self.page_side[todo][page])
    key = self.page_lk[todo][page].astype(np.uint64)
    for j in range(4):
        key = (key << np.uint64(self.bits)) | cells[:, j].astype(np.uint64)
    at = self.first_cell[todo][page] + rank
    self.key[at] = key
    self.count[at] = counts
    before = np.cumsum(counts) - counts  # quads before each cell, restarted at each page
    self.start[at] = self.first_quad[todo][page] + before - np.repeat(before[np.cumsum(n) - n], n)
    self.decoded[todo] = True


def coordinates_decode(self: Coordinates, todo: np.ndarray) -> None:
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
    objects = (np.repeat(todo * NB_BLOCK, size) + np.arange(int(size.sum()))
               - np.repeat(np.cumsum(size) - size, size))
    xy = coord_fields(data.array, np.repeat(lo, size), np.repeat(w, size, axis=0), np.repeat(b, size, axis=0),
                      objects)
    if xy.size and xy.max() >= 2**31:
        raise _corrupt(self.where, "holds a coordinate out of range")
    if self.check is not None:
        self.check(objects, xy)
    self.xy[objects] = xy
    self.decoded[todo] = True


def page_boxes_check(self: PageBoxes, ids: np.ndarray, xy: np.ndarray) -> None:
    """Refuse unless every object ``ids`` (in range) at ``xy`` (quanta, ``(m, 2)``) lies inside its page's box."""
    page = np.searchsorted(self.start, ids, side="right") - 1
    outside = ((xy < self.lo[page]) | (xy > self.hi[page])).any(axis=1)
    if outside.any():
        raise mismatch(self.where, f"coordinates of objects of map page {int(page[outside][0])} lie outside "
                                   f"the page", self.map_path)
    self.checked[page] = True
