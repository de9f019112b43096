"""Pages of a map file: the recursive cuts that make them, their encoding, and the batch decoder that checks them.

A page holds the objects of a compact box: one run per label, sorted by row-major key, with Rice-coded key
gaps and area residuals (see ``docs/format.md``, "Pages").  :func:`_split_pages` cuts objects into pages,
:func:`_encode_page` writes one, and :func:`_decode_pages` reads a batch of them in one vectorised pass,
checking every rule of the page layout on the way.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from .codec import (
    _AREA_BLOCK,
    _GAP_BLOCK,
    _K_BITS,
    _MAX_AREA_CODE,
    _NTH_ZERO,
    _RICE_VALUE_BITS,
    _ZEROS_BEFORE,
    _ZEROS_IN_BYTE,
    _area_decode,
    _bits_of,
    _offsets,
    _ranks,
    _read_fields,
    _rice_streams,
    _sums,
    _unzigzag,
    _zigzag,
)
from .layout import _M2_PER_OBJECT, _MAX_EXTENT, _PILE

__all__: list[str] = []

# Version 2 (elevation): an unknown elevation, as the writer holds it; the bias of the page's first cell base
# (a u16: codes -32768..32767); the block of the elevation sequences' Rice parameters (adapts to the relief).
NO_ELEVATION = np.iinfo(np.int32).min
_ELEVATION_BIAS = 1 << 15
_ELEVATION_BLOCK = 32


class _BadPageError(Exception):
    """A page of a batch breaks a rule of the format: its position in the batch, and the problem."""

    def __init__(self, index: int, problem: str) -> None:
        super().__init__(problem)
        self.index = index
        self.problem = problem


def _key_bits(ex: Any, ey: Any) -> Any:
    """Bits of the row-major keys of pages of these extents (scalars or arrays): of the largest, at least 1."""
    largest = (np.asarray(ex, np.int64) + 1) * (np.asarray(ey, np.int64) + 1) - 1
    return np.maximum(1, np.frexp(largest.astype(np.float64))[1])  # exact: the largest key is below 2**48


def _encode_page(qx: np.ndarray, qy: np.ndarray, label: np.ndarray, code: np.ndarray,
                 elevation: tuple[np.ndarray, int] | None = None) -> tuple[bytes, tuple]:
    """A page's bytes and its directory record, from its objects' positions (quanta), labels and area codes;
    with ``elevation`` (each object's elevation code, :data:`NO_ELEVATION` where unknown, and the cell side in
    quanta) a version 2 page, else a version 1 page."""
    ox, oy = int(qx.min()), int(qy.min())
    ex, ey = int(qx.max()) - ox, int(qy.max()) - oy
    keys = (qy - oy).astype(np.uint64) * np.uint64(ex + 1) + (qx - ox).astype(np.uint64)
    order = np.lexsort((keys, label))
    keys, label, area_code = keys[order], label[order], code[order].astype(np.int64)
    codes, starts, counts = np.unique(label, return_index=True, return_counts=True)
    runs = [slice(a, a + n) for a, n in zip(starts, counts, strict=True)]
    # Areas of one label cluster around a typical size: code them as residuals from the run's median.
    medians = np.array([int(np.median(area_code[r])) for r in runs], np.uint64)
    heads = np.column_stack([codes.astype(np.uint64), counts.astype(np.uint64), keys[starts], medians])
    widths = np.tile([8, 16, _key_bits(ex, ey), 16], codes.size)
    sequences = [np.diff(keys[r]) for r in runs] + [_zigzag(area_code[r] - m) for r, m in
                                                     zip(runs, medians.astype(np.int64), strict=True)]
    blocks = [_GAP_BLOCK] * len(runs) + [_AREA_BLOCK] * len(runs)
    head_bits = _bits_of(heads.reshape(-1), widths)
    if elevation is not None:
        e_head, e_sequences = _elevation_sequences(qx[order], qy[order], elevation[0][order], elevation[1])
        head_bits = np.concatenate([head_bits, _bits_of(e_head, np.array([16, 16]))])
        sequences += e_sequences
        blocks += [_ELEVATION_BLOCK, _ELEVATION_BLOCK]
    bits = np.concatenate([head_bits, *_rice_streams(sequences, blocks)])
    payload = bytes([codes.size]) + np.packbits(bits).tobytes()
    return payload, (ox, oy, ex, ey, int(qx.size), len(payload), zlib.crc32(payload))


def _cells_of(qx: np.ndarray, qy: np.ndarray, cell: int) -> tuple[np.ndarray, np.ndarray]:
    """The elevation cells (row-major ``(cy, cx)`` order, as a rank) of objects at map positions in quanta."""
    cy, cx = np.floor_divide(qy, cell), np.floor_divide(qx, cell)
    occupied, rank = np.unique(np.column_stack([cy, cx]), axis=0, return_inverse=True)
    return rank.reshape(-1), occupied


def _elevation_sequences(qx: np.ndarray, qy: np.ndarray, elevation: np.ndarray,
                         cell: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """A version 2 page's elevation head (``E``, ``K``) and its two sequences (cell base steps, residuals),
    the objects given in the page's order (``docs/format.md``, "Elevation")."""
    rank, occupied = _cells_of(qx.astype(np.int64), qy.astype(np.int64), cell)
    known = elevation != NO_ELEVATION
    # Each cell's base: the lower median of its known codes (sorted by cell, then code).
    order = np.lexsort((elevation[known], rank[known]))
    cells, first, count = np.unique(rank[known][order], return_index=True, return_counts=True)
    base = np.full(len(occupied), NO_ELEVATION, np.int64)
    base[cells] = elevation[known][order][first + (count - 1) // 2]
    # A cell of unknowns only repeats the previous base (a step of 0 costs the least), the first one 0.
    have = np.where(base != NO_ELEVATION, np.arange(base.size), -1)
    filled = np.maximum.accumulate(have)
    base = np.where(filled >= 0, base[np.maximum(filled, 0)], 0)
    residual = np.where(known, _zigzag(elevation - base[rank]).astype(np.int64) + 1, 0).astype(np.uint64)
    head = np.array([int(base[0]) + _ELEVATION_BIAS, len(occupied)], np.uint64)
    return head, [_zigzag(np.diff(base)), residual]


def _decode_pages(payloads: list[bytes], table: np.ndarray, n_labels: int,
                  cell: int | None = None) -> tuple[Any, ...]:
    """Decode a batch of pages in one vectorised pass: (qx, qy, label code, area, elevation code) of their
    objects, page by page; the elevation codes (:data:`NO_ELEVATION` where unknown) of version 2 pages, whose
    elevation cell side (quanta) is ``cell``, else None.

    ``table`` holds the pages' directory records (checked when the map was opened).  Every rule of the page
    layout is checked on the way, stage by stage, before anything the stage's values promise is allocated:
    the first page found breaking one raises :class:`_BadPageError`.  Time and memory are linear in the batch's
    bytes and objects (about 20 bytes a payload byte and 100 an object), with a fixed cost per batch, not
    per page, so that a map of many tiny pages costs about what a genuine map of its size does.
    """
    length = np.array([len(p) for p in payloads], np.int64)
    first_byte = np.cumsum(length) - length
    b = _Batch(buf=np.frombuffer(b"".join(payloads) + bytes(8), np.uint8), first_byte=first_byte,
               end=8 * (first_byte + length), objects=table["count"].astype(np.int64),
               ex=table["ex"].astype(np.int64), ey=table["ey"].astype(np.int64), every_page=np.arange(len(payloads)),
               elevated=cell is not None)
    runs, run_page, code, n, first, median, head_end = _read_run_heads(b, n_labels)
    e_head = _read_elevation_heads(b, head_end) if b.elevated else None
    if e_head is not None:
        head_end = head_end + 32
    k_end, k = _read_rice_parameters(b, runs, run_page, n, head_end, e_head)
    gaps, residual, steps, e_residual = _read_rice_values(b, runs, k_end, k, e_head)
    qx, qy, run_of, object_page = _decode_positions(b, run_page, n, first, gaps)
    area_code = median[run_of] + _unzigzag(residual)
    _refuse((area_code < 0) | (area_code > _MAX_AREA_CODE), object_page, "page area code out of range")
    qx, qy = qx + table["ox"][object_page], qy + table["oy"][object_page]
    elevation = None
    if e_head is not None and cell is not None:
        elevation = _decode_elevation(b, qx, qy, object_page, cell, e_head, steps, e_residual)
    return qx, qy, code[run_of].astype(np.int32), _area_decode(area_code), elevation


def _read_elevation_heads(b: _Batch, head_end: np.ndarray) -> np.ndarray:
    """Each version 2 page's elevation head: its first cell base (bias removed) and its occupied cells ``K``."""
    _refuse(head_end + 32 > b.end, b.every_page, _SHORT)
    fields = _read_fields(b.buf, np.repeat(head_end, 2) + np.tile([0, 16], head_end.size), np.full(2 * head_end.size,
                                                                                                   16))
    e_head = fields.astype(np.int64).reshape(-1, 2)
    e_head[:, 0] -= _ELEVATION_BIAS
    _refuse((e_head[:, 1] < 1) | (e_head[:, 1] > b.objects), b.every_page,
            lambda i: f"{e_head[i, 1]} elevation cells for {b.objects[i]} objects")
    return e_head


def _decode_elevation(b: _Batch, qx: np.ndarray, qy: np.ndarray, object_page: np.ndarray, cell: int,
                      e_head: np.ndarray, steps: np.ndarray, e_residual: np.ndarray) -> np.ndarray:
    """The elevation codes of a batch's objects (map positions in quanta), from each page's head, cell base
    steps and residuals, checked: the occupied cells are as many as the head says, every code in range."""
    cy, cx = np.floor_divide(qy, cell), np.floor_divide(qx, cell)
    order = np.lexsort((cx, cy, object_page))
    key = np.column_stack([object_page[order], cy[order], cx[order]])
    new = np.ones(order.size, bool)
    new[1:] = np.any(key[1:] != key[:-1], axis=1)
    cell_page = object_page[order][new]
    _refuse(np.bincount(cell_page, minlength=b.every_page.size) != e_head[:, 1], b.every_page,
            "elevation cells do not match the page's objects")
    rank = np.empty(order.size, np.int64)
    rank[order] = np.cumsum(new) - 1  # each object's cell, numbered over the batch
    step = _unzigzag(steps)
    _refuse(np.abs(step) > 2 * _ELEVATION_BIAS, cell_page[_not_first(cell_page)], "elevation step out of range")
    # Each page's bases: its first cell's, then a running sum of its steps (exact: each step below 2**17).
    start = np.flatnonzero(~_not_first(cell_page))
    increments = np.zeros(cell_page.size, np.int64)
    increments[_not_first(cell_page)] = step
    increments[start] = e_head[:, 0]
    total = np.cumsum(increments)
    base = total - np.repeat(total[start] - e_head[:, 0], np.diff(np.append(start, cell_page.size)))
    _refuse(np.abs(base + 0.5) > _ELEVATION_BIAS, cell_page, "elevation base out of range")
    known = e_residual > 0
    code = np.full(qx.size, NO_ELEVATION, np.int64)
    code[known] = base[rank[known]] + _unzigzag(e_residual[known] - np.uint64(1))
    _refuse(known & (np.abs(code + 0.5) > _ELEVATION_BIAS), object_page, "elevation code out of range")
    return code


def _not_first(page_of: np.ndarray) -> np.ndarray:
    """Whether each item (grouped by page) is not its page's first."""
    out = np.ones(page_of.size, bool)
    out[0:1] = False
    out[1:] = page_of[1:] == page_of[:-1]
    return out


class _Batch(NamedTuple):
    """The pages of a batch being decoded: their bytes and their directory fields, page by page."""

    buf: np.ndarray  # the payloads one after another, then 8 zero bytes (so a field read never runs off)
    first_byte: np.ndarray  # where each page starts in buf
    end: np.ndarray  # each page's end, in bits
    objects: np.ndarray  # objects in each page (its directory count)
    ex: np.ndarray
    ey: np.ndarray
    every_page: np.ndarray  # 0, 1, ... (the page of each page, for the page-wise checks)
    elevated: bool = False  # version 2 pages (elevation)


_SHORT = "page data is shorter than its counts"


def _refuse(bad: np.ndarray, page_of: np.ndarray, problem: str | Callable[[int], str]) -> None:
    """Raise :class:`_BadPageError` for the first page with a ``bad`` item (``page_of`` gives their pages)."""
    if bad.any():
        i = int(page_of[bad].min())
        raise _BadPageError(i, problem(i) if callable(problem) else problem)


def _read_run_heads(b: _Batch, n_labels: int) -> tuple[np.ndarray, ...]:
    """Read and check each page's label run heads.

    Returns the runs of each page; the page, label code, objects, first key and median area code of each run;
    and the bit where each page's run heads end.
    """
    runs = b.buf[b.first_byte].astype(np.int64)
    _refuse((runs < 1) | (runs > np.minimum(b.objects, n_labels)), b.every_page,
            lambda i: f"{runs[i]} label runs for {b.objects[i]} objects of {n_labels} labels")
    # Run heads: label code, objects, first key (in the page's key bits), median area code.
    run_page = np.repeat(b.every_page, runs)
    widths = np.column_stack([np.full(run_page.size, 8), np.full(run_page.size, 16),
                              _key_bits(b.ex, b.ey)[run_page], np.full(run_page.size, 16)]).ravel()
    head_start = 8 * (b.first_byte + 1)
    head_end = head_start + _sums(widths, 4 * runs)
    _refuse(head_end > b.end, b.every_page, _SHORT)
    heads = _read_fields(b.buf, np.repeat(head_start, 4 * runs) + _offsets(widths, 4 * runs), widths)
    code, n, first, median = heads.reshape(-1, 4).T.astype(np.int64)
    bad = code >= n_labels
    bad[1:] |= (run_page[1:] == run_page[:-1]) & (np.diff(code) <= 0)
    _refuse(bad, run_page, "label runs out of order or outside the label table")
    _refuse((n < 1) | (_sums(n, runs)[run_page] != b.objects[run_page]), run_page,
            lambda i: f"page runs do not add up to its directory count {b.objects[i]}")
    return runs, run_page, code, n, first, median, head_end


def _read_rice_parameters(b: _Batch, runs: np.ndarray, run_page: np.ndarray, n: np.ndarray,
                          head_end: np.ndarray, e_head: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The bit where each page's Rice parameters end, and the Rice parameter of each value of the batch."""
    # Rice sequences of each page: the key gaps of each run, then the area residuals of each run (then, in
    # version 2, the cell base steps and the elevation residuals); their blocks, and a 6-bit parameter a block.
    pages = [run_page, run_page]
    lengths = [n - 1, n]
    sizes = [np.full(n.size, _GAP_BLOCK), np.full(n.size, _AREA_BLOCK)]
    if e_head is not None:
        pages += [b.every_page, b.every_page]
        lengths += [e_head[:, 1] - 1, b.objects]
        sizes += [np.full(b.every_page.size, _ELEVATION_BLOCK)] * 2
    order = np.argsort(np.concatenate(pages), kind="stable")
    seq_len = np.concatenate(lengths)[order]
    seq_block = np.concatenate(sizes)[order]
    seq_page = np.concatenate(pages)[order]
    n_blocks = -(-seq_len // seq_block)
    of_block = np.repeat(np.arange(seq_len.size), n_blocks)
    size = np.minimum(seq_block[of_block], seq_len[of_block] - seq_block[of_block] * _ranks(n_blocks))
    page_blocks = np.bincount(seq_page, weights=n_blocks, minlength=b.every_page.size).astype(np.int64)
    k_end = head_end + _K_BITS * page_blocks
    _refuse(k_end > b.end, b.every_page, _SHORT)
    block_page = np.repeat(b.every_page, page_blocks)
    k_block = _read_fields(b.buf, np.repeat(head_end, page_blocks) + _K_BITS * _ranks(page_blocks), np.full(
        block_page.size, _K_BITS)).astype(np.int64)
    _refuse(k_block > _RICE_VALUE_BITS, block_page, "Rice parameter out of range")
    return k_end, np.repeat(k_block, size)


def _read_rice_values(b: _Batch, runs: np.ndarray, k_end: np.ndarray, k: np.ndarray,
                      e_head: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The Rice-coded values of each page, split into key gaps and area residuals (zigzagged), and in version
    2 the cell base steps (zigzagged) and the elevation residuals (else empty)."""
    # Unary quotients: the first `values` zero bits after the parameters, found by rank (zeros before a bit).
    values = 2 * b.objects - runs
    if e_head is not None:
        values = values + e_head[:, 1] - 1 + b.objects
    value_page = np.repeat(b.every_page, values)
    zeros = np.concatenate([[0], np.cumsum(_ZEROS_IN_BYTE[b.buf[:-8]])])

    def zeros_before(bit: np.ndarray) -> np.ndarray:
        return zeros[bit >> 3] + _ZEROS_BEFORE[b.buf[bit >> 3], bit & 7]

    rank0 = zeros_before(k_end)
    _refuse(rank0 + values > zeros_before(b.end), b.every_page, _SHORT)
    rank = np.repeat(rank0, values) + _ranks(values)  # zeros before each stop bit
    byte = np.searchsorted(zeros, rank, side="right") - 1
    stop = 8 * byte + _NTH_ZERO[b.buf[byte], rank - zeros[byte]]
    previous = np.empty_like(stop)
    previous[1:] = stop[:-1]
    page_first_value = np.cumsum(values) - values
    previous[page_first_value] = k_end - 1
    quotient = stop - previous - 1
    # A value is below 2**48 (a key gap in a key space of 2**48, an area residual far less): a longer quotient
    # would overflow the 64-bit arithmetic below and wrap round to a plausible small value.
    _refuse((quotient >> (_RICE_VALUE_BITS - k)) != 0, value_page, "Rice-coded value out of range")
    rem_start = stop[page_first_value + values - 1] + 1
    rem_end = rem_start + _sums(k, values)
    _refuse(rem_end > b.end, b.every_page, _SHORT)
    remainder = _read_fields(b.buf, np.repeat(rem_start, values) + _offsets(k, values), k)
    rest = b.end - rem_end
    padding = _read_fields(b.buf, rem_end, np.minimum(rest, 7))
    _refuse((rest >= 8) | (padding != 0), b.every_page, "page contents do not match its directory record")
    coded = (quotient.astype(np.uint64) << k.astype(np.uint64)) | remainder
    rank = _ranks(values)
    ends = np.cumsum(np.column_stack([b.objects - runs, b.objects, *(
        [e_head[:, 1] - 1, b.objects] if e_head is not None else [])]), axis=1)
    part = (rank[:, None] >= np.repeat(ends, values, axis=0)).sum(axis=1)  # 0 gap, 1 area, 2 step, 3 elevation
    gaps = coded[part == 0]
    _refuse(gaps < 1, value_page[part == 0], "two objects of one label at one position")
    return gaps, coded[part == 1], coded[part == 2], coded[part == 3]


def _decode_positions(b: _Batch, run_page: np.ndarray, n: np.ndarray, first: np.ndarray,
                      gaps: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each object's quantized position within its page's box, its run and its page."""
    # Keys: each run starts at its first key and adds its gaps.  One cumulative sum over the batch: it may
    # wrap round 2**64, but differences within a run are exact (a run's keys are below 2**48).
    run_of = np.repeat(np.arange(n.size), n)
    object_page = run_page[run_of]
    run_start = np.cumsum(n) - n
    steps = np.empty(run_of.size, np.uint64)
    is_start = np.zeros(run_of.size, bool)
    is_start[run_start] = True
    steps[is_start] = first.astype(np.uint64)
    steps[~is_start] = gaps
    total = np.cumsum(steps, dtype=np.uint64)
    key = total - (total[run_start] - first.astype(np.uint64))[run_of]
    keyspace = (b.ex + 1) * (b.ey + 1)
    _refuse(key >= keyspace[object_page].astype(np.uint64), object_page, "page position outside its extent")
    width = (b.ex + 1).astype(np.uint64)[object_page]
    qx, qy = (key % width).astype(np.int64), (key // width).astype(np.int64)
    # The directory box is the objects' own box: what the R-tree and the header bounds promise is true.
    starts = np.cumsum(b.objects) - b.objects
    _refuse((np.minimum.reduceat(qx, starts) != 0) | (np.minimum.reduceat(qy, starts) != 0)
            | (np.maximum.reduceat(qx, starts) != b.ex) | (np.maximum.reduceat(qy, starts) != b.ey), b.every_page,
            "objects do not fill the page's box")
    return qx, qy, run_of, object_page


def _too_dense(count: Any, ex: Any, ey: Any, quantum: float) -> Any:
    """Whether pages of these counts and extents (scalars or arrays) break the density rule."""
    area_m2 = (np.asarray(ex, np.float64) + 1.0) * (np.asarray(ey, np.float64) + 1.0) * quantum * quantum
    return (np.asarray(count) > _PILE) & (np.asarray(count) > area_m2 / _M2_PER_OBJECT)


def _split_pages(qx: np.ndarray, qy: np.ndarray, capacity: int, quantum: float) -> list[np.ndarray]:
    """Recursive cuts on the longer side until each page fits its capacity, extent and density bounds.

    A cut falls between two distinct coordinates (the one nearest the median), so that no two pages share
    a position: the reader checks that page boxes do not overlap.  Objects at one position (at most one
    per label, after :func:`_unique_records`) are never cut, even beyond the capacity.
    """
    pages = []
    stack = [np.arange(qx.size)]
    while stack:
        idx = stack.pop()
        x, y = qx[idx], qy[idx]
        dx, dy = int(x.max() - x.min()), int(y.max() - y.min())
        if (dx == 0 and dy == 0) or (idx.size <= capacity and dx <= _MAX_EXTENT and dy <= _MAX_EXTENT
                                     and not _too_dense(idx.size, dx, dy, quantum)):
            pages.append(idx)
            continue
        axis = x if dx >= dy else y
        order = np.argsort(axis, kind="stable")
        ranked = axis[order]
        breaks = np.flatnonzero(ranked[1:] != ranked[:-1]) + 1
        cut = int(breaks[np.argmin(np.abs(breaks - idx.size // 2))])
        stack += [idx[order[:cut]], idx[order[cut:]]]
    return pages
