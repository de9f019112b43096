"""The compact parts of a version-4 quad index (``docs/index_format.md``): packed records, objects and directory.

Four codes, each read at random without decoding more than a lookup needs:

* **quad records** of ``record_bytes`` bytes (a little-endian integer: anchor id, triple number, the four
  positions inside the cell), one per quad in key order (:func:`pack_records`, :func:`unpack_records`);
* **neighbours**: each object's ``quad_neighbours`` nearest as zigzag differences from its own id, in blocks
  of :data:`NB_BLOCK` objects bit-packed at the block's width (:func:`pack_neighbours`,
  :func:`neighbour_fields`);
* **coordinates**: each object's position as offsets from the smallest x and y of its block of
  :data:`NB_BLOCK` objects, bit-packed at the block's two widths (:func:`pack_coords`, :func:`coord_fields`);
* **directory pages** of at most :data:`PAGE_CELLS` cells of one label combination: the gaps between the
  cells' dense numbers and their quad counts, bit-packed at the page's two widths (:func:`pack_pages`; decoded
  and checked by :meth:`~mapdb.match.index.directory.Directory.decode`).

Bits are packed most significant first (by the map's codec, :mod:`mapdb.mapfile.codec`) and read by the compiled
kernel (``_kernel_qdecode.c``) exactly as the codec's reader reads them: through the 64-bit window at a field's
first byte, so 8 zero bytes follow the data: every packed section ends with them.
"""

from __future__ import annotations

import numpy as np

from ...mapfile.codec import _bits_of, _zigzag
from .._kernel import qdecode_coord_fields, qdecode_neighbour_fields

__all__ = ["NB_BLOCK", "PAGE_CELLS", "PAD", "coord_fields", "dense_cells", "dense_side", "directory_pages",
           "neighbour_fields", "pack_coords", "pack_neighbours", "pack_pages", "pack_records", "record_layout",
           "unpack_records"]

NB_BLOCK = 64  # objects whose neighbours share one bit width
PAGE_CELLS = 64  # cells of a directory page (the fence, in memory, holds one row a page)
PAD = 8  # zero bytes after every bit-packed section (the codec's reader reads 8-byte windows)
_PAGES_AT_ONCE = 2048  # directory pages packed at once (about 130k cells: some 50 MB of bit arrays)


def record_layout(n_objects: int, n_triples: int) -> tuple[int, int, int]:
    """Bytes of a quad record, bits of each position inside a cell, bits of the triple number.

    The record holds ``anchor | triple | 4 positions``; it is rounded up to whole bytes and the spare bits go
    to the positions (at least 4 bits each, at most 8): finer positions spare lookups resolving candidates.
    """
    id_bits = max(1, (max(n_objects, 1) - 1).bit_length())
    triple_bits = max(1, (max(n_triples, 1) - 1).bit_length())
    nbytes = -(-(id_bits + triple_bits + 16) // 8)
    sub_bits = min(8, (8 * nbytes - id_bits - triple_bits) // 4)
    return nbytes, sub_bits, triple_bits


def pack_records(anchor: np.ndarray, triple: np.ndarray, sub: np.ndarray, nbytes: int, sub_bits: int,
                 triple_bits: int) -> np.ndarray:
    """Quad records ``(m, nbytes)`` uint8 of anchors, triple numbers and positions ``(m, 4)``."""
    v = anchor.astype(np.uint64) << np.uint64(triple_bits)
    v |= triple.astype(np.uint64)
    for j in range(4):
        v = (v << np.uint64(sub_bits)) | sub[:, j].astype(np.uint64)
    return np.ascontiguousarray(v.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :nbytes])


def unpack_records(rows: np.ndarray, sub_bits: int, triple_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Anchors (int64), triple numbers (int64) and positions ``(m, 4)`` (uint8) of records ``(m, nbytes)``."""
    wide = np.zeros((len(rows), 8), np.uint8)
    wide[:, : rows.shape[1]] = rows
    v = wide.view("<u8").reshape(-1)
    mask = np.uint64((1 << sub_bits) - 1)
    sub = np.empty((v.size, 4), np.uint8)
    for j in range(4):
        sub[:, 3 - j] = (v >> np.uint64(sub_bits * j)) & mask
    v = v >> np.uint64(4 * sub_bits)
    triple = (v & np.uint64((1 << triple_bits) - 1)).astype(np.int64)
    return (v >> np.uint64(triple_bits)).astype(np.int64), triple, sub


def pack_neighbours(table: np.ndarray, first: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neighbour ids ``(m, k)`` of objects ``first ..`` (``first`` a multiple of :data:`NB_BLOCK`) as packed blocks.

    Returns the bytes, each block's length in bytes and each block's bit width.
    """
    m, k = table.shape
    ids = np.arange(first, first + m, dtype=np.int64)[:, None]
    z = _zigzag(table.astype(np.int64) - ids).reshape(-1)
    starts = np.append(np.arange(0, m, NB_BLOCK), m) * k
    top = np.maximum.reduceat(z, starts[:-1]) if z.size else np.zeros(0, np.uint64)
    widths = np.array([int(t).bit_length() for t in top.tolist()], np.int64)
    counts = np.diff(starts)
    data, lengths = _packed_groups(z, np.repeat(widths, counts), starts, counts * widths)
    return data, lengths, widths.astype(np.uint8)


def neighbour_fields(data: np.ndarray, block_start: np.ndarray, width: np.ndarray, objects: np.ndarray,
                     k: int) -> np.ndarray:
    """Neighbour ids ``(m, k)`` (int64) of ``objects`` from the packed data, given their blocks' first byte and
    width (both already checked against the data's length; the kernel's, ``_kernel_qdecode.c``).

    Raises
    ------
    ValueError
        If a field lies outside ``data`` (which must end in :data:`PAD` zero bytes) or is wider than 57 bits.
    """
    out = qdecode_neighbour_fields(data, _int64(block_start), _int64(width), _int64(objects), int(k))
    return np.frombuffer(out, np.int64).reshape(-1, k) if k else np.zeros((len(objects), 0), np.int64)


def pack_coords(coords: np.ndarray, first: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coordinates ``(m, 2)`` (quanta, at least 0) of objects ``first ..`` (a multiple of :data:`NB_BLOCK`) as
    packed blocks: each object's offsets from its block's smallest x and y, at the block's two widths.

    Returns the bytes, each block's length in bytes, its widths ``(b, 2)`` (uint8) and its base ``(b, 2)``.
    """
    m = len(coords)
    starts = np.append(np.arange(0, m, NB_BLOCK), m)
    c = coords.astype(np.int64)
    base = np.minimum.reduceat(c, starts[:-1], axis=0) if m else np.zeros((0, 2), np.int64)
    top = np.maximum.reduceat(c, starts[:-1], axis=0) - base if m else np.zeros((0, 2), np.int64)
    widths = np.array([int(t).bit_length() for t in top.reshape(-1).tolist()], np.int64).reshape(-1, 2)
    counts = np.diff(starts)
    block = np.repeat(np.arange(counts.size), counts)
    values = (c - base[block]).reshape(-1)  # x, y of each object in turn
    data, lengths = _packed_groups(values, widths[block].reshape(-1), starts * 2, counts * widths.sum(axis=1))
    return data, lengths, widths.astype(np.uint8), base


def coord_fields(data: np.ndarray, block_start: np.ndarray, width: np.ndarray, base: np.ndarray,
                 size: np.ndarray) -> np.ndarray:
    """Coordinates ``(m, 2)`` (int64 quanta) of the first ``size`` objects of each block from the packed data, given
    the blocks' first byte, widths ``(b, 2)`` and bases ``(b, 2)`` (all already checked against the data's length;
    the kernel's, ``_kernel_qdecode.c``): the blocks' objects in turn.

    Raises
    ------
    ValueError
        If a field lies outside ``data`` (which must end in :data:`PAD` zero bytes) or is wider than 57 bits.
    """
    out = qdecode_coord_fields(data, _int64(block_start), _int64(width).reshape(-1, 2),
                               _int64(base).reshape(-1, 2), _int64(size))
    return np.frombuffer(out, np.int64).reshape(-1, 2)


def dense_side(cell: np.ndarray) -> np.ndarray:
    """Cells per invariant of a cell side: ``floor(2 / c) + 1`` (invariants in [-1, 1], cells from 0)."""
    return (np.floor(2.0 / cell) + 1).astype(np.int64)


def dense_cells(cells: np.ndarray, side: np.ndarray) -> np.ndarray:
    """A cell's number among its combination's ``side ** 4`` cells (int64), in key order."""
    d = cells[:, 0].astype(np.int64)
    for j in (1, 2, 3):
        d = d * side + cells[:, j]
    return d


def pack_pages(dense: np.ndarray, count: np.ndarray, page_first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directory pages: per page a byte of the gap width, a byte of the count width, then the gaps between
    consecutive dense cell numbers and the counts less one, bit-packed.  ``page_first``: each page's first cell
    (the last entry the end).  Returns the bytes and each page's length in bytes."""
    n_pages = page_first.size - 1
    gap = np.diff(dense, prepend=0).astype(np.uint64)
    gap[page_first[:-1]] = 0  # a page's first cell is in the fence
    less = (count - 1).astype(np.uint64)
    top_gap = np.maximum.reduceat(gap, page_first[:-1]) if n_pages else np.zeros(0, np.uint64)
    top_count = np.maximum.reduceat(less, page_first[:-1]) if n_pages else np.zeros(0, np.uint64)
    wg = np.array([int(t).bit_length() for t in top_gap.tolist()], np.int64)
    wc = np.array([int(t).bit_length() for t in top_count.tolist()], np.int64)
    cells = np.diff(page_first)
    # Per page: wg, wc (8 bits each), its gaps after the first, its counts.
    first_of = np.zeros(gap.size, bool)
    first_of[page_first[:-1]] = True
    rank_page = np.repeat(np.arange(n_pages), cells)
    values = np.concatenate([np.column_stack([wg, wc]).reshape(-1), gap[~first_of], less]).astype(np.uint64)
    widths = np.concatenate([np.full(2 * n_pages, 8), wg[rank_page[~first_of]], wc[rank_page]])
    group = np.concatenate([np.repeat(np.arange(n_pages), 2), rank_page[~first_of], rank_page])
    part = np.concatenate([np.zeros(2 * n_pages, np.int64), np.ones(int((~first_of).sum()), np.int64),
                           np.full(rank_page.size, 2)])
    order = np.lexsort((part, group))  # stable: within a page, header, gaps, counts in cell order
    bits = np.bincount(group, weights=widths, minlength=n_pages).astype(np.int64)
    values, widths = values[order], widths[order]
    starts = np.concatenate([[0], np.cumsum(np.bincount(group, minlength=n_pages))])
    data, lengths = _packed_groups(values, widths, starts, bits)
    return data, lengths


def _packed_groups(values: np.ndarray, widths: np.ndarray, starts: np.ndarray,
                   bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bytes of groups of values of their own widths, each group padded to a byte boundary."""
    nbytes = -(-bits // 8)
    counts = np.diff(starts)
    # After each group, one zero value as wide as its padding: value i of group g goes to i + g, the pad after
    # group g to starts[g + 1] + g.
    at = np.concatenate([np.arange(values.size) + np.repeat(np.arange(counts.size), counts),
                         starts[1:] + np.arange(counts.size)])
    allv = np.zeros(at.size, np.uint64)
    allw = np.zeros(at.size, np.int64)
    allv[at] = np.concatenate([values.astype(np.uint64), np.zeros(counts.size, np.uint64)])
    allw[at] = np.concatenate([widths, nbytes * 8 - bits])
    return np.packbits(_bits_of(allv, allw)), nbytes


def _int64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.int64)


def directory_pages(keys: np.ndarray, counts: np.ndarray, combos: np.ndarray, cells: np.ndarray,
                    bits: int) -> tuple[np.ndarray, np.ndarray]:
    """The directory of cells ``keys`` (ascending) holding ``counts`` quads: the packed pages (without their
    padding) and the fence ``(P + 1, 4)`` uint64; ``combos`` (ascending) are the label combinations and ``cells``
    their cell sides.  A page starts at every combination's first cell and every :data:`PAGE_CELLS` cells after."""
    lk = (keys >> np.uint64(4 * bits)).astype(np.int64)
    side = dense_side(cells[np.searchsorted(combos, lk)]) if keys.size else np.zeros(0, np.int64)
    mask = np.uint64((1 << bits) - 1)
    g = np.column_stack([((keys >> np.uint64(bits * (3 - j))) & mask).astype(np.int64) for j in range(4)])
    dense = dense_cells(g.reshape(-1, 4), side)
    new_combo = np.flatnonzero(np.diff(lk, prepend=-1) != 0) if keys.size else np.zeros(0, np.int64)
    run = np.diff(np.append(new_combo, keys.size))
    per = -(-run // PAGE_CELLS)
    first = np.repeat(new_combo, per) + (np.arange(int(per.sum())) - np.repeat(np.cumsum(per) - per, per)) * PAGE_CELLS
    page_first = np.append(first, keys.size).astype(np.int64)
    # Pages are whole bytes each: packed a few thousand at a time (the bit arrays take 8 bytes a bit).
    parts = [pack_pages(dense[page_first[p] : page_first[min(p + _PAGES_AT_ONCE, first.size)]],
                        counts[page_first[p] : page_first[min(p + _PAGES_AT_ONCE, first.size)]],
                        page_first[p : p + _PAGES_AT_ONCE + 1] - page_first[p])
             for p in range(0, first.size, _PAGES_AT_ONCE)]
    data = np.concatenate([d for d, _ in parts]) if parts else np.zeros(0, np.uint8)
    lengths = np.concatenate([n for _, n in parts]) if parts else np.zeros(0, np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    fence = np.zeros((first.size + 1, 4), "<u8")
    fence[:, 0] = np.append(keys[first], np.uint64(2**64 - 1))
    fence[:, 1] = page_first
    fence[:, 2] = starts[page_first]
    fence[:, 3] = np.concatenate([[0], np.cumsum(lengths)])
    return data, fence
