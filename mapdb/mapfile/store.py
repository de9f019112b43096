"""The map file: labelled centroids in compressed, spatially compact pages with an R-tree.

A map is one file (format described in ``docs/format.md``)::

    magic "\\x89MAPDB\\r\\n" | u16 version | u16 flags | u32 header length | header (JSON)
    | u32 CRC-32 of everything before it | page directory (36 bytes a page) | pages

(the header is deflated JSON)

Objects are split into pages of at most ``page_capacity`` objects by recursive
median cuts, so every page covers a compact area.  Inside a page, positions are
integers at the quantum relative to the page origin; each label's objects form
one run, sorted by their row-major key ``qy * (extent_x + 1) + qx`` and stored
as Rice-coded key gaps (close to the entropy of a random point set, so labels
cost nothing beyond their run headers).  Areas are log-quantized codes, stored
as Rice-coded residuals from their run's median.  The header, the directory and each page carry a CRC-32; pages are
read and checked only when a query needs them.

Reading a file never executes anything from it (JSON and fixed binary records
only), and every length and count read from it is checked against the file
size and the format's bounds before memory is allocated for it.  The header's
meaning is checked too, not only its checksum (types, ranges, nesting, the CRS,
counts against the bytes that must hold them), and the format's layout rules
(one object per label and position, pages that share no position and are not
denser than one object a square metre beyond a pile of 255) bound what a file
of a given size can make a reader do: see "Guarantees against a hostile file"
in ``docs/format.md``.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import stat
import struct
import tempfile
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import numpy as np
import shapely
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from .. import __version__
from ..errors import EmptyMapError, MapdbError, MapdbIOError, MapFormatError, MapVersionError, reading
from ..objects import Objects
from ..outputs import atomic_open, temporary_prefix

__all__ = [
    "DEFAULT_MEMORY_OBJECTS",
    "DEFAULT_QUANTUM",
    "FORMAT_VERSION",
    "MAGIC",
    "MapBase",
    "MapWriter",
    "MemoryMap",
    "MetaMap",
    "area_codes",
    "open_map",
    "write_map",
    "write_map_from_chunks",
]

MAGIC = b"\x89MAPDB\r\n"
FORMAT_VERSION = 1
# Stored resolution of coordinates (metres) unless a map is built with another.
DEFAULT_QUANTUM = 0.1
# A version number above this is not a newer format but a damaged or foreign file.
_MAX_VERSION = 255
_PREFIX = struct.Struct("<8sHHI")
# origin x, y (quanta), extent x, y, count, byte length, crc32: the 36-byte directory record, as numpy reads it
_DIR_DTYPE = np.dtype([("ox", "<i8"), ("oy", "<i8"), ("ex", "<u4"), ("ey", "<u4"), ("count", "<u4"),
                       ("length", "<u4"), ("crc", "<u4")])
_MAX_HEADER = 16 << 20  # deflated header bytes
# The inflated header may be at most this long, and at most _HEADER_FREE + _HEADER_RATIO times its deflated
# length: a genuine header (a few kilobytes, with checksums that do not compress) is far inside both, and a
# small deflate bomb cannot make a reader allocate much more than the file's own size.
_MAX_HEADER_JSON = 16 << 20
_HEADER_FREE = 256 << 10
_HEADER_RATIO = 16
_MAX_DEPTH = 32  # nesting of the header JSON (a genuine one nests 3 deep)
_MAX_LABELS = 255
_MAX_PAGE_OBJECTS = 65535
_MAX_PAGE_BYTES = 1 << 20  # a page of 65535 objects needs at most ~570 KB however its values are spread
_MAX_EXTENT = (1 << 24) - 1  # keeps the row-major key under 2**48
_MAX_QUANTA = 1 << 52  # positions in quanta stay exact in float64 (page boxes, bounds)
_RICE_VALUE_BITS = 48  # every Rice-coded value (a key gap, an area residual) is below 2**48
# Density: a page may hold _PILE objects whatever its area (one object of each label at one position is the
# densest thing a genuine map holds); beyond that, at most one object per _M2_PER_OBJECT of its box.
_PILE = 255
_M2_PER_OBJECT = 1.0
# The fewest bits a page of c objects can take: the run count byte, one run head (8 + 16 + 1 + 16 bits), a
# Rice parameter (6 bits), and per object at least 3 bits (a key gap >= 1 costs 2 bits, an area residual 1).
_MIN_PAGE_BITS = 53
_MIN_OBJECT_BITS = 3
_PAIR_BUDGET = 1 << 20  # candidate page pairs examined at once when checking that pages do not overlap
_AREA_STEPS = 8  # codes per doubling of area: +-4.4 % relative precision
_AREA_FLOOR_LOG2 = -16  # smallest non-zero area stored: 2**-16 m^2
_MAX_AREA_CODE = (1024 - _AREA_FLOOR_LOG2) * _AREA_STEPS  # the largest code whose area is a finite float64
DEFAULT_PAGE_CAPACITY = 1024
_CACHE_OBJECTS = 4_000_000

T = TypeVar("T")


# --------------------------------------------------------------------------------------------- coding


def _area_encode(area: np.ndarray) -> np.ndarray:
    code = np.zeros(area.shape, np.uint16)
    pos = area > 0
    log = (np.log2(area[pos]) - _AREA_FLOOR_LOG2) * _AREA_STEPS
    code[pos] = np.clip(np.rint(log) + 1, 1, _MAX_AREA_CODE).astype(np.uint16)
    return code


def area_codes(area: np.ndarray) -> np.ndarray:
    """Areas (m^2) as the map stores them: uint16 codes on a log scale (0 for a point), as in ``docs/format.md``.

    Examples
    --------
    >>> area_codes(np.array([0.0, 1.0, 100.0])).tolist()[0]
    0
    """
    return _area_encode(np.asarray(area, np.float64))


def _area_decode(code: np.ndarray) -> np.ndarray:
    area = np.exp2((code.astype(np.float64) - 1) / _AREA_STEPS + _AREA_FLOOR_LOG2)
    area[code == 0] = 0.0
    return area


_GAP_BLOCK = 32  # key gaps sharing one Rice parameter: adapts to clustered objects at 6 bits a block
_AREA_BLOCK = 256  # area residuals are not clustered: one parameter for many
_K_BITS = 6


def _bits_of(values: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Each value as ``width`` bits, most significant first, concatenated (a uint8 array of 0/1)."""
    if values.size == 0 or widths.max(initial=0) == 0:
        return np.zeros(0, np.uint8)
    top = int(widths.max())
    j = np.arange(top, dtype=np.int64)
    shift = (widths[:, None] - 1 - j).clip(min=0).astype(np.uint64)
    bits = ((values.astype(np.uint64)[:, None] >> shift) & np.uint64(1)).astype(np.uint8)
    return bits[j < widths[:, None]]


class _BadPageError(Exception):
    """A page of a batch breaks a rule of the format: its position in the batch, and the problem."""

    def __init__(self, index: int, problem: str) -> None:
        super().__init__(problem)
        self.index = index
        self.problem = problem


_WINDOW = np.arange(8, dtype=np.uint64)
_BYTE_BITS = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).astype(np.int64)  # MSB first
_ZEROS_IN_BYTE = (8 - _BYTE_BITS.sum(axis=1)).astype(np.int64)
# zeros among the first j bits of a byte (j = 0..8), and the position of its t-th zero (t = 0..7; 0 if none)
_ZEROS_BEFORE = np.concatenate([np.zeros((256, 1), np.int64), np.cumsum(1 - _BYTE_BITS, axis=1)], axis=1)
_NTH_ZERO = np.array([np.r_[np.flatnonzero(row == 0), np.zeros(8, np.int64)][:8] for row in _BYTE_BITS], np.int64)
# Pages decoded in one pass, by their bytes: enough to spread the fixed cost of a pass over hundreds of small
# pages, few enough that the pass's arrays stay in the processor's cache (a 1 MiB page is a batch of its own).
_BATCH_BYTES = 1 << 18
_BATCH_OBJECTS = 1 << 16  # and by objects: a pass allocates a few hundred bytes an object for a moment


def _read_fields(buf: np.ndarray, start: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Fields of the given widths (each at most 57 bits) at the given bit positions of ``buf``.

    ``buf`` must end in 8 zero bytes, so that every field is read through the 64-bit window at its first byte.
    """
    start, widths = np.asarray(start, np.uint64), np.asarray(widths, np.uint64)
    word = buf[(start >> np.uint64(3))[:, None] + _WINDOW].view(">u8")[:, 0].astype(np.uint64)
    # 63 bits of the window from the field's first bit, so that a width of 0 shifts by a legal 63 and gives 0
    head = (word << (start & np.uint64(7))) >> np.uint64(1)
    return head >> (np.uint64(63) - widths)


def _ranks(lengths: np.ndarray) -> np.ndarray:
    """0, 1, ... within each of consecutive segments of the given lengths."""
    return np.arange(int(lengths.sum())) - np.repeat(np.cumsum(lengths) - lengths, lengths)


def _offsets(values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Running sums of ``values`` before each element, restarting at each segment."""
    edges = np.concatenate([[0], np.cumsum(values)])
    return edges[:-1] - np.repeat(edges[np.cumsum(lengths) - lengths], lengths)


def _sums(values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """The sum of each of consecutive segments (empty ones included) of ``values``."""
    edges = np.concatenate([[0], np.cumsum(values)])
    ends = np.cumsum(lengths)
    return edges[ends] - edges[ends - lengths]


def _rice_streams(sequences: list[np.ndarray], blocks: list[int]) -> list[np.ndarray]:
    """Block-adaptive Rice code of several sequences of non-negative integers, as three bit streams.

    For every block of ``blocks[i]`` consecutive values of sequence i, the k that codes it shortest;
    then the unary quotients ``v >> k`` of all values; then their k-bit remainders.  Page-wide streams
    (rather than one set per sequence) let a reader decode a whole page in a few vectorised steps.
    """
    k_fields, k_values, values_all = [], [], []
    for values, block in zip(sequences, blocks, strict=True):
        n = values.size
        if n == 0:
            continue
        values = values.astype(np.uint64)
        count = -(-n // block)
        padded = np.zeros(count * block, np.uint64)
        padded[:n] = values
        sizes = np.minimum(block, n - block * np.arange(count))
        ks = np.arange(int(values.max()).bit_length() + 1, dtype=np.uint64)
        # coded size of each block for each k: the quotients, plus a stop bit and k remainder bits a value
        cost = (padded.reshape(count, block)[:, :, None] >> ks).sum(axis=1) + sizes[:, None] * (ks + np.uint64(1))
        k_block = np.argmin(cost, axis=1)
        k_fields.append(k_block)
        k_values.append(np.repeat(k_block, sizes))
        values_all.append(values)
    if not values_all:
        return []
    values = np.concatenate(values_all)
    k = np.concatenate(k_values).astype(np.uint64)
    quotient = (values >> k).astype(np.int64)
    unary = np.ones(int(quotient.sum()) + values.size, np.uint8)
    unary[np.cumsum(quotient + 1) - 1] = 0
    k_all = np.concatenate(k_fields)
    return [_bits_of(k_all, np.full(k_all.size, _K_BITS)), unary,
            _bits_of(values & ((np.uint64(1) << k) - np.uint64(1)), k.astype(np.int64))]


def _zigzag(v: np.ndarray) -> np.ndarray:
    return np.where(v >= 0, 2 * v, -2 * v - 1).astype(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.int64)
    return np.where(z % 2 == 0, z // 2, -(z + 1) // 2)


def _key_bits(ex: Any, ey: Any) -> Any:
    """Bits of the row-major keys of pages of these extents (scalars or arrays): of the largest, at least 1."""
    largest = (np.asarray(ex, np.int64) + 1) * (np.asarray(ey, np.int64) + 1) - 1
    return np.maximum(1, np.frexp(largest.astype(np.float64))[1])  # exact: the largest key is below 2**48


def _encode_page(qx: np.ndarray, qy: np.ndarray, label: np.ndarray, code: np.ndarray) -> tuple[bytes, tuple]:
    """A page's bytes and its directory record, from its objects' positions (quanta), labels and area codes."""
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
    bits = np.concatenate([_bits_of(heads.reshape(-1), widths), *_rice_streams(sequences, blocks)])
    payload = bytes([codes.size]) + np.packbits(bits).tobytes()
    return payload, (ox, oy, ex, ey, int(qx.size), len(payload), zlib.crc32(payload))


def _decode_pages(payloads: list[bytes], table: np.ndarray, n_labels: int) -> tuple[np.ndarray, ...]:
    """Decode a batch of pages in one vectorised pass: (qx, qy, label code, area) of their objects, page by page.

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
               ex=table["ex"].astype(np.int64), ey=table["ey"].astype(np.int64), every_page=np.arange(len(payloads)))
    runs, run_page, code, n, first, median, head_end = _read_run_heads(b, n_labels)
    k_end, k = _read_rice_parameters(b, runs, run_page, n, head_end)
    gaps, residual = _read_rice_values(b, runs, k_end, k)
    qx, qy, run_of, object_page = _decode_positions(b, run_page, n, first, gaps)
    area_code = median[run_of] + _unzigzag(residual)
    _refuse((area_code < 0) | (area_code > _MAX_AREA_CODE), object_page, "page area code out of range")
    return (qx + table["ox"][object_page], qy + table["oy"][object_page], code[run_of].astype(np.int32),
            _area_decode(area_code))


class _Batch(NamedTuple):
    """The pages of a batch being decoded: their bytes and their directory fields, page by page."""

    buf: np.ndarray  # the payloads one after another, then 8 zero bytes (so a field read never runs off)
    first_byte: np.ndarray  # where each page starts in buf
    end: np.ndarray  # each page's end, in bits
    objects: np.ndarray  # objects in each page (its directory count)
    ex: np.ndarray
    ey: np.ndarray
    every_page: np.ndarray  # 0, 1, ... (the page of each page, for the page-wise checks)


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
                          head_end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bit where each page's Rice parameters end, and the Rice parameter of each value of the batch."""
    # Rice sequences of each page: the key gaps of each run, then the area residuals of each run; then
    # their blocks, and a 6-bit parameter per block.
    order = np.argsort(np.concatenate([run_page, run_page]), kind="stable")
    seq_len = np.concatenate([n - 1, n])[order]
    seq_block = np.concatenate([np.full(n.size, _GAP_BLOCK), np.full(n.size, _AREA_BLOCK)])[order]
    n_blocks = -(-seq_len // seq_block)
    of_block = np.repeat(np.arange(seq_len.size), n_blocks)
    size = np.minimum(seq_block[of_block], seq_len[of_block] - seq_block[of_block] * _ranks(n_blocks))
    page_blocks = _sums(n_blocks, 2 * runs)
    k_end = head_end + _K_BITS * page_blocks
    _refuse(k_end > b.end, b.every_page, _SHORT)
    block_page = np.repeat(b.every_page, page_blocks)
    k_block = _read_fields(b.buf, np.repeat(head_end, page_blocks) + _K_BITS * _ranks(page_blocks), np.full(
        block_page.size, _K_BITS)).astype(np.int64)
    _refuse(k_block > _RICE_VALUE_BITS, block_page, "Rice parameter out of range")
    return k_end, np.repeat(k_block, size)


def _read_rice_values(b: _Batch, runs: np.ndarray, k_end: np.ndarray,
                      k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Rice-coded values of each page, split into key gaps and area residuals (zigzagged)."""
    # Unary quotients: the first `values` zero bits after the parameters, found by rank (zeros before a bit).
    values = 2 * b.objects - runs
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
    is_gap = _ranks(values) < np.repeat(b.objects - runs, values)
    gaps, residual = coded[is_gap], coded[~is_gap]
    _refuse(gaps < 1, value_page[is_gap], "two objects of one label at one position")
    return gaps, residual


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


# --------------------------------------------------------------------------------------------- writing
# The writer takes objects in chunks and holds a bounded number of them (``memory_objects``), whatever the map's
# size: past that bound they wait in temporary files beside the output, as compact records (quantized position,
# label code, area code: 19 bytes an object), and the pages are cut and encoded one part of the map at a time.
# The cuts are the same as those of the whole map in memory (see MapWriter), so the file is the same.

# Objects a writer holds in memory at once, by default.  Measured, 4 million objects given in 16 chunks: a
# peak of 150 MB over the process's memory before (chunks included), 60 MB with 262,144; as fast either way.
DEFAULT_MEMORY_OBJECTS = 1 << 20
_RECORD = np.dtype([("x", "<i8"), ("y", "<i8"), ("label", "u1"), ("code", "<u2")])  # packed: 19 bytes
_PAGE_BYTES_IN_MEMORY = 32 << 20  # encoded pages kept in memory before they go to a temporary file
_HISTOGRAM_BINS = 1 << 16  # bins of a pass that narrows down the median of a part too big to sort in memory


class _Scratch:
    """The temporary directory of one write, beside the output, made when first needed and removed at the end."""

    def __init__(self, output: Path) -> None:
        self.output = output
        self.dir: Path | None = None
        self.files = 0

    def new_file(self) -> Path:
        if self.dir is None:
            with self.writing():
                self.dir = Path(tempfile.mkdtemp(prefix=temporary_prefix(self.output), suffix=".spill",
                                                 dir=self.output.parent))
        self.files += 1
        return self.dir / f"{self.files}.bin"

    @contextmanager
    def writing(self) -> Iterator[None]:
        """OS errors of the temporary files (a full disk, a directory that cannot be written) as one line."""
        try:
            yield
        except OSError as exc:
            if isinstance(exc, MapdbError):
                raise
            where = self.dir or self.output.parent
            raise MapdbIOError(f"{self.output}: cannot write temporary files in {where} "
                               f"({exc.strerror or exc})") from None

    def close(self) -> None:
        if self.dir is not None:
            shutil.rmtree(self.dir, ignore_errors=True)
            self.dir = None


class _Spill:
    """Records appended chunk by chunk: in memory up to ``limit`` of them, past that all in a temporary file.

    Tracks their number and the box of their positions (in quanta).
    """

    def __init__(self, scratch: _Scratch, limit: int) -> None:
        self.scratch, self.limit = scratch, limit
        self.parts: list[np.ndarray] = []
        self.file: Path | None = None
        self.count = 0
        self.low = [_MAX_QUANTA, _MAX_QUANTA]
        self.high = [-_MAX_QUANTA, -_MAX_QUANTA]

    def append(self, records: np.ndarray) -> None:
        if records.size == 0:
            return
        self.count += records.size
        for i, axis in enumerate(("x", "y")):
            self.low[i] = min(self.low[i], int(records[axis].min()))
            self.high[i] = max(self.high[i], int(records[axis].max()))
        if self.file is None:
            self.parts.append(records)
            if self.count <= self.limit:
                return
            self.file = self.scratch.new_file()
        with self.scratch.writing(), open(self.file, "ab") as f:
            for part in self.parts or [records]:
                part.tofile(f)
        self.parts = []

    def chunks(self, size: int) -> Iterator[np.ndarray]:
        """The records, ``size`` at most at a time."""
        if self.file is None:
            if self.parts:  # at most ``limit`` records: one array, then cut
                whole = self.parts[0] if len(self.parts) == 1 else np.concatenate(self.parts)
                self.parts = [whole]
                for start in range(0, whole.size, size):
                    yield whole[start:start + size]
            return
        with self.scratch.writing(), open(self.file, "rb") as f:
            while True:
                chunk = np.fromfile(f, _RECORD, count=size)
                if chunk.size == 0:
                    return
                yield chunk

    def load(self) -> np.ndarray:
        """All the records as one array (the caller knows they fit), and the spill emptied."""
        records = np.concatenate(list(self.chunks(max(self.count, 1)))) if self.count else np.zeros(0, _RECORD)
        self.drop()
        return records

    def drop(self) -> None:
        self.parts = []
        if self.file is not None:
            self.file.unlink(missing_ok=True)
            self.file = None


class _PageSink:
    """The encoded pages in file order, and their directory records; the bytes go to a temporary file past
    ``_PAGE_BYTES_IN_MEMORY``."""

    def __init__(self, scratch: _Scratch) -> None:
        self.scratch = scratch
        self.payloads: list[bytes] = []
        self.held = 0
        self.file: Path | None = None
        self.records: list[tuple] = []

    def add(self, payload: bytes, record: tuple) -> None:
        self.payloads.append(payload)
        self.records.append(record)
        self.held += len(payload)
        if self.held > _PAGE_BYTES_IN_MEMORY:
            if self.file is None:
                self.file = self.scratch.new_file()
            with self.scratch.writing(), open(self.file, "ab") as f:
                f.writelines(self.payloads)
            self.payloads, self.held = [], 0

    def table(self) -> np.ndarray:
        return np.array(self.records, dtype=_DIR_DTYPE)

    def copy_to(self, out: Any) -> None:
        """Write every page, in order, to the open file ``out``."""
        if self.file is not None:
            with self.scratch.writing(), open(self.file, "rb") as f:
                shutil.copyfileobj(f, out, 1 << 20)
        out.writelines(self.payloads)


def _unique_records(records: np.ndarray) -> np.ndarray:
    """The records less same-label duplicates: one per label and position, the one of largest area code.

    The largest code is that of the largest area (the code grows with the area), so the map is the one a
    choice by area would give; and the result does not depend on the order of the records.
    """
    order = np.lexsort((-records["code"].astype(np.int32), records["y"], records["x"], records["label"]))
    lab, x, y = records["label"][order], records["x"][order], records["y"][order]
    first = np.ones(order.size, bool)
    first[1:] = (lab[1:] != lab[:-1]) | (x[1:] != x[:-1]) | (y[1:] != y[:-1])
    return records[np.sort(order[first])]


def _bucket_of(records: np.ndarray, buckets: int) -> np.ndarray:
    """A bucket for each record by a hash of its position: the objects of one position share a bucket, and
    buckets are about equal whatever the positions' spread."""
    mixed = (records["x"].astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             ^ records["y"].astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F))
    return ((mixed >> np.uint64(32)) % np.uint64(buckets)).astype(np.int64)


def _select(part: _Spill, axis: str, rank: int, batch: int) -> tuple[int, int, int]:
    """The value of rank ``rank`` (from 0) of the part's coordinates on ``axis``, and how many are below it and
    up to it, in passes over the part that each keep a histogram, until the values left fit ``batch``."""
    i = 0 if axis == "x" else 1
    lo, hi = part.low[i], part.high[i]
    below, inside = 0, part.count
    while inside > batch and hi > lo:
        width = hi - lo + 1
        size = -(-width // min(width, _HISTOGRAM_BINS))
        bins = -(-width // size)
        hist = np.zeros(bins, np.int64)
        for chunk in part.chunks(batch):
            v = chunk[axis]
            hist += np.bincount((v[(v >= lo) & (v <= hi)] - lo) // size, minlength=bins)
        cum = np.cumsum(hist)
        j = int(np.searchsorted(cum, rank - below, side="right"))
        below, inside = below + int(cum[j] - hist[j]), int(hist[j])
        lo, hi = lo + j * size, min(hi, lo + (j + 1) * size - 1)
    if lo == hi:
        return lo, below, below + inside
    values = np.sort(np.concatenate([v[(v >= lo) & (v <= hi)] for v in (c[axis] for c in part.chunks(batch))]))
    value = values[rank - below]
    return (int(value), below + int(np.searchsorted(values, value, "left")),
            below + int(np.searchsorted(values, value, "right")))


class MapWriter:
    """Write a map file from objects given in chunks, in bounded memory.

    Chunks are added with :meth:`add` and the file is written by :meth:`finish`, to a temporary file renamed
    into place (as :func:`write_map`, which is this writer given one chunk).  The map is the one
    :func:`write_map` writes of all the chunks' objects together, byte for byte, whatever the chunks.

    Memory: the writer holds at most ``memory_objects`` objects at once (19 bytes each while they wait, and
    about 100 bytes each while a part of the map is cut into pages and encoded), plus 36 bytes a page of
    directory and up to 32 MiB of encoded pages; the caller's chunk comes on top.  Past that, objects wait in
    a temporary directory beside the output (``.NAME.PID.XXXX.spill``, at most about 40 bytes of disk an
    object: two copies of the records), removed when the writer finishes or fails.  With more objects than
    ``memory_objects``, duplicates are merged in buckets by a hash of the position (about half that many
    objects a bucket, read a chunk at a time), and the pages' recursive cuts are made by passes over the
    files: a cut falls where it falls in memory (the break between distinct coordinates nearest the median,
    found by histogram passes), and a part that fits in memory is cut as :func:`write_map` always did.  (Only
    a bucket that the hash fills with far more than its share of distinct positions would exceed the bound.)

    Parameters
    ----------
    path : str or Path
        Destination ``.mapdb`` file.
    quantum, page_capacity, metadata
        As for :func:`write_map`.
    memory_objects : int
        Most objects held in memory at once (at least the page capacity and 256).

    Raises
    ------
    ValueError
        A quantum or page capacity out of range (here); in :meth:`add`, as :func:`write_map` says, and a chunk
        whose labels (names, in order) or CRS differ from the first chunk's.
    MapdbIOError
        The temporary files cannot be written (a full disk): the output is left untouched.

    Examples
    --------
    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "chunks.mapdb")
    >>> with MapWriter(p) as writer:
    ...     for x in (500000.0, 500010.0):
    ...         writer.add(Objects.from_names([x], [6e6], ["park"], crs="EPSG:32635"))
    ...     writer.finish()
    2
    """

    def __init__(self, path: str | Path, *, quantum: float = DEFAULT_QUANTUM, metadata: dict[str, Any] | None = None,
                 page_capacity: int = DEFAULT_PAGE_CAPACITY, memory_objects: int = DEFAULT_MEMORY_OBJECTS) -> None:
        if not (0 < quantum <= 1000) or not (1 <= page_capacity <= _MAX_PAGE_OBJECTS):
            raise ValueError(f"quantum must be in (0, 1000] m and page capacity in [1, {_MAX_PAGE_OBJECTS}]")
        self.path = Path(path)
        self.quantum, self.page_capacity, self.metadata = quantum, page_capacity, dict(metadata or {})
        self.label_counts: dict[str, int] = {}
        # A part of the map is cut in memory once it fits: never one that must still be cut for its size.
        self.memory_objects = max(int(memory_objects), page_capacity, _PILE + 1)
        self.labels: tuple[str, ...] | None = None
        self.crs: CRS | None = None
        self._crs_text: str | None = None
        self._scratch = _Scratch(Path(os.path.realpath(self.path)))
        self._objects = _Spill(self._scratch, self.memory_objects)

    def __enter__(self) -> MapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Remove the temporary files (also done by :meth:`finish` and on leaving a ``with`` block)."""
        self._objects.drop()
        self._scratch.close()

    @property
    def count(self) -> int:
        """Objects added so far (before same-label duplicates are merged)."""
        return self._objects.count

    def add(self, objects: Objects) -> None:
        """Add a chunk of objects (in a projected CRS); an empty chunk is ignored.

        Raises ``ValueError`` for what :func:`write_map` refuses (no CRS, too many labels, coordinates not
        finite or too far out for the quantum) and for a chunk whose labels or CRS differ from the first's.
        """
        if len(objects) == 0:
            return
        self._check_chunk(objects)
        fx, fy = np.rint(objects.x / self.quantum), np.rint(objects.y / self.quantum)
        if max(np.abs(fx).max(), np.abs(fy).max()) > _MAX_QUANTA - _MAX_EXTENT:
            raise ValueError(f"coordinates beyond {_MAX_QUANTA - _MAX_EXTENT:.3g} quanta of {self.quantum} m")
        records = np.empty(len(objects), _RECORD)
        records["x"], records["y"], records["label"] = fx, fy, objects.label
        records["code"] = _area_encode(np.where(np.isfinite(objects.area) & (objects.area > 0), objects.area, 0.0))
        self._objects.append(records)

    def _check_chunk(self, objects: Objects) -> None:
        if objects.crs is None:
            raise ValueError("objects need a CRS to be written to a map")
        if self.labels is None:
            if len(objects.labels) > _MAX_LABELS:
                raise ValueError(f"a map holds at most {_MAX_LABELS} labels")
            crs = CRS.from_user_input(objects.crs)
            try:  # the header's CRS rule, checked now rather than after every object is written
                _check_crs(crs.to_string(), None if crs.to_epsg() else crs.to_wkt(), str(self.path))
            except MapFormatError as exc:
                raise ValueError(f"cannot write a valid map: {exc}") from None
            self.crs, self._crs_text, self.labels = crs, objects.crs, objects.labels
        elif objects.labels != self.labels:
            raise ValueError(f"a chunk's labels {list(objects.labels)} differ from the first chunk's "
                             f"{list(self.labels)}; relabel it first")
        elif objects.crs != self._crs_text and CRS.from_user_input(objects.crs) != self.crs:
            raise ValueError(f"a chunk in CRS {objects.crs} after chunks in {self._crs_text}; reproject it first")
        finite = np.isfinite(objects.x) & np.isfinite(objects.y)
        if not finite.all():
            raise ValueError(f"{int((~finite).sum())} objects have non-finite coordinates")

    def finish(self, metadata: dict[str, Any] | None = None) -> int:
        """Write the map file; ``metadata`` adds header entries to those given when the writer was made.

        Returns the number of objects written (those added less the merged same-label duplicates); their
        number per label (the header's counts, labels without objects left out) is then ``label_counts``.  Raises
        :class:`EmptyMapError` when no object was added, and ``ValueError`` when the header would break a rule
        of the format (a CRS that is not projected, metadata that is not JSON).
        """
        try:
            added = self._objects.count
            if added == 0:
                raise EmptyMapError(f"{self.path}: no objects to write")
            assert self.crs is not None and self.labels is not None
            unique, per_label = self._deduplicated()
            pages = _PageSink(self._scratch)
            self._cut_pages(unique, pages)
            table = pages.table()
            header = _map_header(self.crs, self.labels, per_label, table, self.quantum, self.page_capacity,
                                 added - int(per_label.sum()), {**self.metadata, **(metadata or {})})
            prefix = _pack_prefix(self.path, header, table, self.quantum)
            with atomic_open(self.path, "wb") as f:
                f.write(prefix)
                f.write(table.tobytes())
                pages.copy_to(f)
            self.label_counts = {name: int(n) for name, n in zip(self.labels, per_label, strict=True) if n}
            return int(per_label.sum())
        finally:
            self.close()

    def _deduplicated(self) -> tuple[_Spill, np.ndarray]:
        """The objects less same-label duplicates, and their number per label code.

        Beyond ``memory_objects``, in buckets by position (a position's objects share one), one at a time.
        """
        raw, limit = self._objects, self.memory_objects
        assert self.labels is not None
        per_label = np.zeros(len(self.labels), np.int64)
        unique = _Spill(self._scratch, limit)
        if raw.count <= limit:
            buckets = [raw]
        else:
            buckets = [_Spill(self._scratch, 0) for _ in range(-(-2 * raw.count // limit))]
            for chunk in raw.chunks(limit):
                which = _bucket_of(chunk, len(buckets))
                order = np.argsort(which, kind="stable")
                ends = np.cumsum(np.bincount(which, minlength=len(buckets)))
                for bucket, part in zip(buckets, np.split(chunk[order], ends[:-1]), strict=True):
                    bucket.append(part)
            raw.drop()
        for bucket in buckets:
            kept = np.zeros(0, _RECORD)
            for chunk in bucket.chunks(limit):
                kept = _unique_records(np.concatenate([kept, chunk]))
            bucket.drop()
            per_label += np.bincount(kept["label"], minlength=per_label.size)
            unique.append(kept)
        return unique, per_label

    def _cut_pages(self, whole: _Spill, pages: _PageSink) -> None:
        """Cut the objects into pages as :func:`_split_pages` cuts them in memory, and encode them in its order.

        A part too big for memory is cut in two by passes over its file (the same cut as in memory); the
        part that waits goes to a file, so that at most one part is in memory at a time.
        """
        stack = [whole]
        while stack:
            part = stack.pop()
            if part.count <= self.memory_objects:
                records = part.load()
                qx, qy, label, code = (np.ascontiguousarray(records[k]) for k in ("x", "y", "label", "code"))
                del records
                for idx in _split_pages(qx, qy, self.page_capacity, self.quantum):
                    pages.add(*_encode_page(qx[idx], qy[idx], label[idx], code[idx]))
                continue
            axis = "x" if part.high[0] - part.low[0] >= part.high[1] - part.low[1] else "y"
            half = part.count // 2
            value, below, through = _select(part, axis, half, self.memory_objects)
            # The break between distinct values nearest the median, the lower one on a tie (as np.argmin takes).
            strict = below > 0 and (through == part.count or half - below <= through - half)
            first, second = _Spill(self._scratch, 0), _Spill(self._scratch, self.memory_objects)
            for chunk in part.chunks(self.memory_objects):
                low = chunk[axis] < value if strict else chunk[axis] <= value
                first.append(chunk[low])
                second.append(chunk[~low])
            part.drop()
            stack += [first, second]


def _lonlat_bounds(crs: CRS, bounds: tuple[float, float, float, float]) -> list[float] | None:
    try:
        to_lonlat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lonlat = [float(v) for v in to_lonlat.transform_bounds(*bounds, densify_pts=21)]
    except Exception:  # a CRS without a lon/lat relation (engineering CRS): no geographic bounds
        return None
    return lonlat if all(map(math.isfinite, lonlat)) else None  # positions outside the projection's domain


def write_map(path: str | Path, objects: Objects, *, quantum: float = DEFAULT_QUANTUM,
              metadata: dict[str, Any] | None = None, page_capacity: int = DEFAULT_PAGE_CAPACITY) -> int:
    """Write objects (in a projected CRS) to a map file, atomically.

    The file is written beside ``path`` under a temporary name and renamed into
    place, so a failed write leaves any earlier map of that name intact.

    Objects of one label at the same quantized position are merged into one (the
    one of largest area is kept; the header's ``merged_duplicates`` counts the
    others): the format allows one object per label and position.

    The header's ``created`` time is now, or the time ``SOURCE_DATE_EPOCH`` gives
    (seconds since 1970, the reproducible-builds convention): two writes of the
    same objects with it set give the same bytes.

    Parameters
    ----------
    path : str or Path
        Destination ``.mapdb`` file.
    objects : Objects
        Centroids in projected metres; ``objects.crs`` names the CRS.
    quantum : float
        Stored resolution in metres; positions are rounded to multiples of it.
    metadata : dict, optional
        JSON-able entries kept in the header (``sources``, ``build`` options, ...).
    page_capacity : int
        Most objects in one page (objects at one position are never split, so such a pile of up to one
        object per label may exceed it).

    Returns
    -------
    int
        The number of objects written (``len(objects)`` less the merged duplicates).

    Raises
    ------
    EmptyMapError
        If ``objects`` is empty.
    ValueError
        If the CRS is not a projected one, a coordinate is not finite or too far out for the quantum, the
        labels are too many or unprintable, or ``metadata`` would break a header rule.

    See Also
    --------
    MapWriter, write_map_from_chunks : the same map from objects given in chunks, in bounded memory.

    Examples
    --------
    >>> import tempfile, os
    >>> o = Objects.from_names([500000.0, 500010.0], [6e6, 6e6], ["park", "water"], crs="EPSG:32635")
    >>> p = os.path.join(tempfile.mkdtemp(), "two.mapdb")
    >>> write_map(p, o)
    2
    >>> with open_map(p) as m:
    ...     m.label_counts
    {'park': 1, 'water': 1}
    """
    return write_map_from_chunks(path, [objects], quantum=quantum, metadata=metadata, page_capacity=page_capacity)


def write_map_from_chunks(path: str | Path, chunks: Iterable[Objects], *, quantum: float = DEFAULT_QUANTUM,
                          metadata: dict[str, Any] | None = None, page_capacity: int = DEFAULT_PAGE_CAPACITY,
                          memory_objects: int = DEFAULT_MEMORY_OBJECTS) -> int:
    """Write the objects of every chunk to one map file, in bounded memory (a :class:`MapWriter`).

    The file is the one :func:`write_map` writes of the chunks' objects together; each chunk may be dropped
    by the caller once the next is asked for.  Returns the number of objects written; raises what
    :func:`write_map` and :meth:`MapWriter.add` raise.

    Examples
    --------
    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "chunks.mapdb")
    >>> parts = (Objects.from_names([500000.0 + i], [6e6], ["park"], crs="EPSG:32635") for i in range(3))
    >>> write_map_from_chunks(p, parts)
    3
    """
    with MapWriter(path, quantum=quantum, metadata=metadata, page_capacity=page_capacity,
                   memory_objects=memory_objects) as writer:
        for chunk in chunks:
            writer.add(chunk)
        return writer.finish()


def _created() -> str:
    """The header's time of writing: now, or ``SOURCE_DATE_EPOCH`` when set (for reproducible files)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    when = datetime.fromtimestamp(int(epoch), UTC) if epoch.isdigit() else datetime.now(UTC)
    return when.isoformat(timespec="seconds")


def _map_header(crs: CRS, labels: tuple[str, ...], counts: np.ndarray, table: np.ndarray, quantum: float,
                page_capacity: int, merged: int, metadata: dict[str, Any] | None) -> dict[str, Any]:
    """The header of a map of these pages and objects per label code; ``metadata`` adds entries but replaces
    none."""
    bounds = _page_span(table, quantum)
    header = {
        "format": "mapdb",
        "format_version": FORMAT_VERSION,
        "crs": crs.to_string(),
        # An authority code names the CRS exactly; WKT (about a kilobyte) only when there is none.
        "crs_wkt": None if crs.to_epsg() else crs.to_wkt(),
        "quantum": quantum,
        "area_log2_steps": _AREA_STEPS,
        "area_floor_log2": _AREA_FLOOR_LOG2,
        "count": int(counts.sum()),
        "merged_duplicates": int(merged),
        "labels": [{"name": name, "code": i, "count": int(counts[i])} for i, name in enumerate(labels)],
        "bounds": list(bounds),
        "bounds_lonlat": _lonlat_bounds(crs, bounds),
        "page_capacity": page_capacity,
        "pages": len(table),
        "directory_crc32": zlib.crc32(table.tobytes()),
        "software": f"mapdb {__version__}",
        "created": _created(),
    }
    for key, value in (metadata or {}).items():
        header.setdefault(key, value)
    return header


def _pack_prefix(path: Path, header: dict[str, Any], table: np.ndarray, quantum: float) -> bytes:
    """The file's prefix (fixed fields, deflated header, CRC), once the reader's own checks pass on it."""
    header_json = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    header_bytes = packer.compress(header_json) + packer.flush()
    # The reader's own checks, so that a map this writes is never one the reader refuses.
    try:
        if len(header_json) > _header_json_limit(len(header_bytes)):
            raise MapFormatError(f"{path}: header of {len(header_json)} bytes is too long")
        _check_header(_parse_header_json(header_json, str(path)), str(path), FORMAT_VERSION)
        _check_directory(table, quantum, tuple(header["bounds"]), int(header["count"]), str(path))
    except MapFormatError as exc:
        raise ValueError(f"cannot write a valid map: {exc}") from None
    prefix = _PREFIX.pack(MAGIC, FORMAT_VERSION, 0, len(header_bytes)) + header_bytes
    return prefix + struct.pack("<I", zlib.crc32(prefix))


# --------------------------------------------------------------------------------------------- checking
# One set of rules for the reader (a file from a stranger) and the writer (which checks what it is about to
# write, so that a genuine map always passes).  Each names the file and the broken rule in one line.


def _header_json_limit(deflated: int) -> int:
    """The longest inflated header a deflated header of ``deflated`` bytes may have."""
    return min(_MAX_HEADER_JSON, _HEADER_FREE + _HEADER_RATIO * deflated)


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:20]} is not a finite number")
    return value


def _short_int(text: str) -> int:
    # Python converts long digit strings in quadratic time; no header integer needs more than 20 digits.
    if len(text.lstrip("-")) > 20:
        raise ValueError(f"an integer of {len(text)} digits")
    return int(text)


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    doc = dict(pairs)
    if len(doc) != len(pairs):
        raise ValueError("an object repeats a key")
    return doc


def _one_line(text: object, limit: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _parse_header_json(text: bytes, where: str) -> Any:
    """Decode the header JSON: strict numbers, unique keys, bounded nesting, every string valid Unicode."""
    try:
        doc = json.loads(text.decode("utf-8"), parse_constant=_refuse_constant, parse_float=_finite_float,
                         parse_int=_short_int, object_pairs_hook=_unique_keys)
    except RecursionError:
        # json's C scanner counts its recursion against the interpreter's limit (about 1000 levels), so a
        # deeply nested header ends here long before the C stack is at risk.
        raise MapFormatError(f"{where}: header nests deeper than {_MAX_DEPTH} levels") from None
    except ValueError as exc:  # includes JSONDecodeError and UnicodeDecodeError
        raise MapFormatError(f"{where}: header is not valid JSON ({_one_line(exc, 80)})") from None
    # Walk it without recursion: nesting depth, and strings that can be printed (no lone surrogates).
    stack = [(doc, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict | list):
            if depth > _MAX_DEPTH:
                raise MapFormatError(f"{where}: header nests deeper than {_MAX_DEPTH} levels")
            items = value.items() if isinstance(value, dict) else ((None, v) for v in value)
            for key, item in items:
                if key is not None:
                    stack.append((key, depth))
                stack.append((item, depth + 1))
        elif isinstance(value, str):
            try:
                value.encode("utf-8")
            except UnicodeEncodeError:
                raise MapFormatError(f"{where}: header holds a string that is not valid Unicode") from None
    return doc


def _shown(value: Any) -> str:
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    return _one_line(repr(value[:40] if isinstance(value, str) else value), 48)


def _is_int(value: Any) -> bool:
    return type(value) is int  # not bool


def _is_number(value: Any) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


_MISSING = object()
_AUTHORITY_CODE = re.compile(r"[A-Za-z][A-Za-z0-9_.-]{0,31}:[A-Za-z0-9_.-]{1,32}")
_WKT_START = re.compile(r"\s*[A-Za-z][A-Za-z0-9_]*\s*\[")
# WKT constructs that name files (grids) or embed a PROJ string (which can name files): a map's CRS is
# resolved from PROJ's own database only.
_WKT_FILE_WORDS = re.compile(r"PARAMETERFILE|EXTENSION", re.IGNORECASE)


def _field(header: dict[str, Any], key: str, where: str, ok: Callable[[Any], bool], rule: str,
           required: bool = True) -> Any:
    """``header[key]`` if ``ok`` says it is well formed (None if optional and missing or null)."""
    value = header.get(key, _MISSING)
    if value is _MISSING or (value is None and not required):
        if required:
            raise MapFormatError(f"{where}: header lacks the field {key!r}")
        return None
    if not ok(value):
        raise MapFormatError(f"{where}: header field {key!r} must be {rule} (got {_shown(value)})")
    return value


def _check_crs(crs: str, crs_wkt: str | None, where: str) -> str:
    """The CRS text readers will use (WKT if given, else the authority code), checked to be projected."""
    if crs_wkt is None:
        if not _AUTHORITY_CODE.fullmatch(crs):
            raise MapFormatError(f"{where}: header field 'crs' must be AUTHORITY:CODE when there is no crs_wkt "
                                 f"(got {_shown(crs)})")
        text = crs
    else:
        if not _WKT_START.match(crs_wkt) or _WKT_FILE_WORDS.search(crs_wkt):
            raise MapFormatError(f"{where}: header field 'crs_wkt' is not a self-contained WKT CRS")
        text = crs_wkt
    try:
        parsed = CRS.from_user_input(text)
    except CRSError as exc:
        raise MapFormatError(f"{where}: the map's CRS is not one pyproj knows ({_one_line(exc, 100)})") from None
    if not parsed.is_projected:
        raise MapFormatError(f"{where}: the map's CRS {_shown(parsed.name)} is not a projected CRS")
    return text


def _is_source(entry: Any) -> bool:
    return (isinstance(entry, dict) and all(isinstance(entry.get(k), str) for k in ("name", "kind", "sha256"))
            and all(_is_int(entry.get(k)) and entry[k] >= 0 for k in ("size", "objects")))


def _check_header(header: Any, where: str, version: int) -> dict[str, Any]:
    """Check a decoded header's meaning; returns the fields a reader uses (``crs`` is the text to parse)."""
    if not isinstance(header, dict):
        raise MapFormatError(f"{where}: header is not a JSON object")
    _field(header, "format", where, lambda v: v == "mapdb", '"mapdb"')
    _field(header, "format_version", where, lambda v: _is_int(v) and v == version,
           f"{version}, the version in the file's first bytes")
    _field(header, "area_log2_steps", where, lambda v: _is_int(v) and v == _AREA_STEPS, str(_AREA_STEPS))
    _field(header, "area_floor_log2", where, lambda v: _is_int(v) and v == _AREA_FLOOR_LOG2, str(_AREA_FLOOR_LOG2))
    quantum = float(_field(header, "quantum", where, lambda v: _is_number(v) and 0 < v <= 1000,
                           "a number in (0, 1000]"))
    count = _field(header, "count", where, lambda v: _is_int(v) and v >= 1, "a positive integer")
    pages = _field(header, "pages", where, lambda v: _is_int(v) and v >= 1, "a positive integer")
    crc = _field(header, "directory_crc32", where, lambda v: _is_int(v) and 0 <= v < 1 << 32, "a CRC-32")
    bounds = _field(header, "bounds", where, lambda v: isinstance(v, list) and len(v) == 4 and all(map(
        _is_number, v)) and v[0] <= v[2] and v[1] <= v[3], "[minx, miny, maxx, maxy], finite, min <= max")
    _field(header, "bounds_lonlat", where, lambda v: isinstance(v, list) and len(v) == 4 and all(map(
        _is_number, v)), "null or four numbers", required=False)
    _field(header, "page_capacity", where, lambda v: _is_int(v) and 1 <= v <= _MAX_PAGE_OBJECTS,
           f"an integer in [1, {_MAX_PAGE_OBJECTS}]", required=False)
    _field(header, "merged_duplicates", where, lambda v: _is_int(v) and v >= 0, "a count", required=False)
    for key in ("software", "created"):
        _field(header, key, where, lambda v: isinstance(v, str), "null or a string", required=False)
    _field(header, "sources", where, lambda v: isinstance(v, list) and all(map(_is_source, v)),
           "a list of {name, kind, size, sha256, objects}", required=False)
    _field(header, "build", where, lambda v: isinstance(v, dict), "an object", required=False)
    labels = _field(header, "labels", where, lambda v: isinstance(v, list) and 1 <= len(v) <= _MAX_LABELS,
                    f"a list of 1 to {_MAX_LABELS} labels")
    names = []
    for i, entry in enumerate(labels):
        if not (isinstance(entry, dict) and isinstance(entry.get("name"), str) and 0 < len(entry["name"]) <= 100
                and entry["name"].isprintable() and entry.get("code") == i and _is_int(entry.get("code"))
                and _is_int(entry.get("count")) and entry["count"] >= 0):
            raise MapFormatError(f"{where}: header label {i} must be {{name: printable text, code: {i}, "
                                 f"count: integer >= 0}} (got {_shown(entry)})")
        names.append(entry["name"])
    if len(set(names)) != len(names):
        raise MapFormatError(f"{where}: header names a label twice")
    if sum(entry["count"] for entry in labels) != count:
        raise MapFormatError(f"{where}: header label counts do not add up to its count {count}")
    crs = _field(header, "crs", where, lambda v: isinstance(v, str) and 0 < len(v) <= 4096, "a CRS name")
    crs_wkt = _field(header, "crs_wkt", where, lambda v: isinstance(v, str) and len(v) <= 1 << 20,
                     "null or WKT text", required=False)
    return {"quantum": quantum, "count": count, "pages": pages, "directory_crc32": crc,
            "bounds": tuple(float(v) for v in bounds), "labels": tuple(names), "crs": _check_crs(crs, crs_wkt, where)}


def _page_span(table: np.ndarray, quantum: float) -> tuple[float, float, float, float]:
    """The box of all page boxes in metres: the header bounds of a map with this directory."""
    ex, ey = table["ex"].astype(np.int64), table["ey"].astype(np.int64)
    return (float(table["ox"].min() * quantum), float(table["oy"].min() * quantum),
            float((table["ox"] + ex).max() * quantum), float((table["oy"] + ey).max() * quantum))


def _check_directory(table: np.ndarray, quantum: float, bounds: tuple[float, ...], count: int,
                     where: str) -> shapely.STRtree:
    """Check the page records against the format's limits and each other; returns their R-tree (in quanta).

    Vectorised, so that a directory of many tiny pages costs little more than a genuine one.
    """
    ox, oy = table["ox"], table["oy"]
    ex, ey = table["ex"].astype(np.int64), table["ey"].astype(np.int64)
    n, length = table["count"].astype(np.int64), table["length"].astype(np.int64)

    def refuse(bad: np.ndarray, problem: str) -> None:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise MapFormatError(f"{where}: page {i} {problem.format(n=int(n[i]), length=int(length[i]))}")

    refuse((n < 1) | (n > _MAX_PAGE_OBJECTS), f"holds {{n}} objects (1 to {_MAX_PAGE_OBJECTS} allowed)")
    refuse((ex > _MAX_EXTENT) | (ey > _MAX_EXTENT), f"extends {1 << 24} quanta or more")
    far = _MAX_QUANTA - _MAX_EXTENT
    refuse((ox > far) | (ox < -far) | (oy > far) | (oy < -far), f"lies beyond {far} quanta from the origin")
    refuse(8 * length < _MIN_PAGE_BITS + _MIN_OBJECT_BITS * n, "has {length} bytes, too few for {n} objects")
    refuse(length > _MAX_PAGE_BYTES, f"has {{length}} bytes (at most {_MAX_PAGE_BYTES})")
    refuse(_too_dense(n, ex, ey, quantum), f"is too dense: {{n}} objects, more than {_PILE} and more than one "
           f"per {_M2_PER_OBJECT:g} m2 of its box")
    if int(n.sum()) != count:
        raise MapFormatError(f"{where}: pages hold {int(n.sum())} objects, the header counts {count}")
    span = _page_span(table, quantum)
    if span != tuple(bounds):
        raise MapFormatError(f"{where}: header bounds {list(bounds)} are not the pages' box {list(span)}")
    # Page boxes as closed boxes of whole quanta: two pages overlap exactly when they share a position.
    boxes = shapely.box(ox, oy, ox + ex, oy + ey)
    tree = shapely.STRtree(boxes)
    step = max(1, _PAIR_BUDGET // len(boxes))  # a directory of pages piled on one spot cannot blow up the pairs
    for start in range(0, len(boxes), step):
        pairs = tree.query(boxes[start : start + step])
        other = pairs[1] != pairs[0] + start
        if other.any():
            j = int(np.flatnonzero(other)[0])
            raise MapFormatError(f"{where}: pages {int(pairs[0][j]) + start} and {int(pairs[1][j])} overlap")
    return tree


# --------------------------------------------------------------------------------------------- reading


class MapBase:
    """Queries shared by file-backed and in-memory maps; subclasses provide ``query_bbox`` and ``all``."""

    crs: str
    quantum: float
    labels: tuple[str, ...]
    bounds: tuple[float, float, float, float]
    metadata: dict[str, Any]

    def __init__(self) -> None:
        self._derived: dict[str, Any] = {}

    @property
    def label_counts(self) -> dict[str, int]:
        return {d["name"]: d["count"] for d in self.metadata["labels"] if d["count"]}

    def __len__(self) -> int:
        return int(self.metadata["count"])

    def __enter__(self) -> MapBase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._derived.clear()

    def cached(self, key: str, factory: Callable[[], T]) -> T:
        """A value derived from this map (an index, say), computed once per open map."""
        if key not in self._derived:
            self._derived[key] = factory()
        return self._derived[key]

    def _label_filter(self, objects: Objects, labels: Iterable[str] | None) -> Objects:
        """The objects of the named labels (all of them for None); a name the map does not know is an error.

        A mistyped name would otherwise select nothing, which looks like an answer ("no buildings here").
        """
        if labels is None:
            return objects
        names = [labels] if isinstance(labels, str) else list(labels)
        unknown = [name for name in names if name not in self.labels]
        if unknown:
            import difflib

            from ..errors import LabelTableError

            close = difflib.get_close_matches(str(unknown[0]), self.labels, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            path = getattr(self, "path", None)  # None for a map in memory
            where = f"{path}: " if path is not None else ""
            raise LabelTableError(f"{where}unknown label {unknown[0]!r}{hint}; the map's labels are "
                                  f"{', '.join(self.labels)}")
        wanted = [self.labels.index(name) for name in names]
        return objects.take(np.isin(objects.label, wanted))

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        raise NotImplementedError

    def all(self) -> Objects:
        raise NotImplementedError

    def query_radius(self, x: float, y: float, r: float, labels: Iterable[str] | None = None) -> Objects:
        """Objects within ``r`` metres of (x, y), optionally only of the named labels."""
        found = self.query_bbox(x - r, y - r, x + r, y + r, labels)
        return found.take((found.x - x) ** 2 + (found.y - y) ** 2 <= r * r)

    def query_geometry(self, geometry: shapely.Geometry, labels: Iterable[str] | None = None) -> Objects:
        """Objects inside a shapely geometry given in the map's CRS, edges included.

        The pages under the geometry's bounding box are read, then each object is tested against the
        geometry itself (vectorised, :func:`shapely.intersects_xy`: inside or on the boundary, as
        :meth:`query_bbox` includes its edges, so that a box gives what ``query_bbox`` gives).

        Parameters
        ----------
        geometry : shapely.Geometry
            A polygon, multipolygon, line or point, in the map's CRS (reproject a lon/lat geometry first,
            e.g. ``geopandas.GeoSeries([g], crs="EPSG:4326").to_crs(m.crs)[0]``).  An empty geometry
            holds nothing.
        labels : iterable of str, optional
            Only objects of these labels; a name the map does not know raises :class:`LabelTableError`.

        Returns
        -------
        Objects
            In the map's CRS; empty if nothing lies inside.

        Raises
        ------
        TypeError
            If ``geometry`` is not a shapely geometry.

        Examples
        --------
        >>> m = MemoryMap(Objects.from_names([0.0, 10.0, 50.0], [0.0, 10.0, 0.0], ["park", "water", "park"],
        ...                                  crs="EPSG:32631"))
        >>> triangle = shapely.Polygon([(-1, -1), (30, -1), (-1, 30)])
        >>> m.query_geometry(triangle).names().tolist()
        ['park', 'water']
        >>> len(m.query_geometry(triangle, labels=["water"])), len(m.query_geometry(shapely.Polygon()))
        (1, 0)
        >>> m.query_geometry(triangle, labels=["prak"])
        Traceback (most recent call last):
        mapdb.errors.LabelTableError: unknown label 'prak' (did you mean 'park'?); the map's labels are park, water
        """
        if not isinstance(geometry, shapely.Geometry):
            raise TypeError(f"query_geometry needs a shapely geometry, not {type(geometry).__name__}")
        if geometry.is_empty:
            return self._label_filter(Objects.empty(self.labels, self.crs), labels)
        minx, miny, maxx, maxy = geometry.bounds
        found = self.query_bbox(minx, miny, maxx, maxy, labels=labels)
        return found.take(shapely.intersects_xy(geometry, found.x, found.y))

    def query_lonlat_bbox(self, bbox: Iterable[float], labels: Iterable[str] | None = None) -> Objects:
        """Objects whose WGS 84 longitude and latitude fall in a lon/lat box, edges included.

        Parameters
        ----------
        bbox : (minlon, minlat, maxlon, maxlat)
            Degrees.  The box may span the world, touch the poles or cross the antimeridian
            (``minlon > maxlon``, as in GeoJSON); see :func:`mapdb.geo.check_bbox` for what is refused.
        labels : iterable of str, optional
            Only objects of these labels; a name the map does not know raises :class:`LabelTableError`.

        Returns
        -------
        Objects
            In the map's CRS (the test is made on each object's own lon/lat, so the answer does not depend
            on how the box projects); empty when the box misses the map.

        Raises
        ------
        ValueError
            If ``bbox`` is not a valid lon/lat box.

        Examples
        --------
        >>> m = MemoryMap(Objects.from_names([500000.0, 600000.0], [4649776.0, 4649776.0], ["park", "water"],
        ...                                  crs="EPSG:32631"))  # lon 3 and 4.2, lat 42
        >>> m.query_lonlat_bbox((2.9, 41.9, 3.1, 42.1)).names().tolist()
        ['park']
        >>> len(m.query_lonlat_bbox((-10.0, 0.0, -9.0, 1.0)))
        0
        >>> m.query_lonlat_bbox((3.1, 41.9, 2.9, 42.1)).names().tolist()  # crosses 180: all but lon 2.9 to 3.1
        ['water']
        >>> m.query_lonlat_bbox((2.9, 42.1, 3.1, 41.9))
        Traceback (most recent call last):
        ValueError: minlat must be below maxlat
        """
        from ..geo import check_bbox

        return self._in_lonlat_bbox(check_bbox(list(bbox)), labels)[0]

    def query_lonlat(self, lon: float, lat: float, radius_m: float, labels: Iterable[str] | None = None) -> Objects:
        """Objects within ``radius_m`` metres on the ground (geodesic, on WGS 84) of a longitude and latitude.

        Parameters
        ----------
        lon, lat : float
            WGS 84 degrees, longitude in [-180, 180], latitude in [-90, 90].
        radius_m : float
            Ground distance in metres, >= 0.  Not a distance in the map's CRS: a projection stretches
            distances (by up to 0.1 % inside a UTM zone, by 1 / cos(latitude) in Web Mercator).
        labels : iterable of str, optional
            Only objects of these labels; a name the map does not know raises :class:`LabelTableError`.

        Returns
        -------
        Objects
            In the map's CRS; empty when the place is off the map.

        Raises
        ------
        ValueError
            If a number is out of range or not finite (lon and lat swapped often ends here).

        Examples
        --------
        >>> m = MemoryMap(Objects.from_names([500000.0, 500050.0, 500000.0], [4649776.0, 4649776.0, 4650776.0],
        ...                                  ["park", "water", "park"], crs="EPSG:32631"))
        >>> m.query_lonlat(3.0, 42.0, 100.0).names().tolist()  # the third object is 1 km north
        ['park', 'water']
        >>> len(m.query_lonlat(3.0, 42.0, 100.0, labels=["water"])), len(m.query_lonlat(3.0, 42.0, 0.5))
        (1, 1)
        >>> len(m.query_lonlat(-3.0, 42.0, 100.0))  # off the map
        0
        >>> m.query_lonlat(42.0, 95.0, 100.0)
        Traceback (most recent call last):
        ValueError: latitude 95.0 must be a number in [-90, 90]
        """
        from pyproj import Geod

        checks = (("longitude", lon, -180.0, 180.0), ("latitude", lat, -90.0, 90.0),
                  ("radius_m", radius_m, 0.0, math.inf))
        for name, value, low, high in checks:
            if not (isinstance(value, int | float | np.number) and low <= value <= high and math.isfinite(value)):
                raise ValueError(f"{name} {value!r} must be a number in [{low:g}, {high:g}]"
                                 if name != "radius_m" else f"radius_m {value!r} must be a finite number >= 0")
        lon, lat, radius_m = float(lon), float(lat), float(radius_m)
        found, found_lon, found_lat = self._in_lonlat_bbox(self._disc_bbox(lon, lat, radius_m), labels)
        n = len(found)
        _, _, distance = Geod(ellps="WGS84").inv(np.full(n, lon), np.full(n, lat), found_lon, found_lat)
        return found.take(np.asarray(distance) <= radius_m)

    @staticmethod
    def _disc_bbox(lon: float, lat: float, radius_m: float) -> tuple[float, float, float, float]:
        """A lon/lat box sure to hold every point within ``radius_m`` metres (geodesic, WGS 84) of a place.

        Along a geodesic, latitude changes by at most 1/M radians a metre (M, the meridian's radius of
        curvature, is at least a(1 - e^2) on WGS 84) and longitude by at most 1/(N cos(latitude)), N >= a.
        The box crosses the antimeridian (``minlon > maxlon``) or spans every longitude (a pole inside).

        Examples
        --------
        >>> [round(v, 4) for v in MapBase._disc_bbox(179.99, 0.0, 10_000.0)]
        [179.9002, -0.0904, -179.9202, 0.0904]
        >>> MapBase._disc_bbox(0.0, 89.99, 2_000.0)[::2]
        (-180.0, 180.0)
        """
        half_lat = math.degrees(radius_m / 6_335_439.0) + 1e-9  # (the constant keeps a zero radius a proper box)
        south, north = max(-90.0, lat - half_lat), min(90.0, lat + half_lat)
        widest = math.radians(abs(lat) + half_lat)
        if widest >= math.pi / 2:
            return (-180.0, south, 180.0, north)
        half_lon = math.degrees(radius_m / (6_378_137.0 * math.cos(widest))) + 1e-9
        if half_lon >= 180.0:
            return (-180.0, south, 180.0, north)
        west, east = lon - half_lon, lon + half_lon
        return (west + 360.0 if west < -180.0 else west, south, east - 360.0 if east > 180.0 else east, north)

    def _in_lonlat_bbox(self, bbox: tuple[float, float, float, float],
                        labels: Iterable[str] | None) -> tuple[Objects, np.ndarray, np.ndarray]:
        """Objects in a checked lon/lat box, with their longitudes and latitudes.

        The pages are found by :func:`mapdb.geo.projected_window` (which may keep too much, never too
        little); the selection is made on each object's own lon/lat.
        """
        from ..geo import in_bbox, projected_window

        window = projected_window(self.crs, bbox, within=self.bounds)
        if window is None:
            return self._label_filter(Objects.empty(self.labels, self.crs), labels), np.zeros(0), np.zeros(0)
        found = self.query_bbox(*window, labels=labels)
        to_lonlat = self.cached("mapdb.to_lonlat", lambda: Transformer.from_crs(self.crs, "EPSG:4326",
                                                                                always_xy=True))
        lon, lat = (np.asarray(v, np.float64) for v in to_lonlat.transform(found.x, found.y))
        inside = in_bbox(bbox, lon, lat)
        return found.take(inside), lon[inside], lat[inside]


class MetaMap(MapBase):
    """A map file opened for queries; pages are read, checked and decoded on demand.

    Use :func:`open_map` to get one.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        where = str(self.path)
        self._file = _open_regular(self.path, where)
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
            raise MapFormatError(f"{where}: not a valid map (flags {flags:#06x}; version 1 defines none)")
        header = _parse_header_json(self._inflate_header(header_bytes, where), where)
        fields = _check_header(header, where, version)
        n_pages, self.quantum, self.crs = fields["pages"], fields["quantum"], fields["crs"]
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
        x, y, label, area = self._read_batch(indices)
        done = []
        cuts = np.cumsum(records["count"].astype(np.int64))[:-1]
        for i, page in zip(indices, zip(*(np.split(a, cuts) for a in (x, y, label, area)), strict=True),
                           strict=True):
            self._cache[i] = page
            self._cached_objects += page[2].size
            done.append((i, page))
        while self._cached_objects > _CACHE_OBJECTS and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cached_objects -= old[2].size
        return done

    def _read_batch(self, indices: list[int]) -> tuple[np.ndarray, ...]:
        """(x, y, label code, area) of the pages' objects, read, checked and decoded; the cache untouched."""
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
            qx, qy, label, area = _decode_pages(payloads, records, len(self.labels))
        except _BadPageError as bad:
            raise MapFormatError(f"{self.path} page {indices[bad.index]}: {bad.problem}") from None
        except (ValueError, IndexError, OverflowError, TypeError) as exc:
            # The checks are meant to leave nothing for numpy to trip on; should one be missing, the pages
            # are still reported as what they are, bad pages, and not as a crash.
            raise MapFormatError(f"{self.path} pages {indices[0]} to {indices[-1]}: malformed page data "
                                 f"({_one_line(exc, 80)})") from None
        return qx * self.quantum, qy * self.quantum, label, area

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
            x, y, label, area = self._read_batch(list(range(start, stop)))
            yield Objects(x, y, label, area, self.labels, self.crs)
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
        x, y, label, area = (np.concatenate(p) for p in zip(*parts, strict=True))
        return Objects(x, y, label, area, self.labels, self.crs)

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
        found = self._objects(hits.tolist())
        inside = (found.x >= minx) & (found.x <= maxx) & (found.y >= miny) & (found.y <= maxy)
        return self._label_filter(found.take(inside), labels)

    def all(self) -> Objects:
        objects = self._objects(range(self.page_count))
        self._check_label_counts(np.bincount(objects.label, minlength=len(self.labels)))
        return objects


class MemoryMap(MapBase):
    """The :class:`MetaMap` interface over objects held in memory (simulations, tests).

    Positions are rounded to the quantum as a file would store them.

    Examples
    --------
    >>> m = MemoryMap(Objects.from_names([0.0, 100.0], [0.0, 0.0], ["park", "park"], crs="EPSG:3857"))
    >>> len(m.query_radius(0.0, 0.0, 10.0))
    1
    >>> len(m.query_bbox(500.0, 500.0, 600.0, 600.0))
    0
    """

    def __init__(
        self, objects: Objects, quantum: float = DEFAULT_QUANTUM, metadata: dict[str, Any] | None = None
    ) -> None:
        super().__init__()
        self.path = None
        self.quantum = quantum
        self.crs = objects.crs or ""
        self.labels = objects.labels
        x = np.rint(objects.x / quantum) * quantum
        y = np.rint(objects.y / quantum) * quantum
        self._objects = Objects(x, y, objects.label, objects.area, objects.labels, objects.crs)
        self.bounds = (float(x.min()), float(y.min()), float(x.max()), float(y.max())) if len(objects) else (
            0.0, 0.0, 0.0, 0.0)
        counts = np.bincount(objects.label, minlength=len(self.labels))
        self.metadata = {"count": len(objects), "crs": self.crs, "quantum": quantum, "bounds": list(self.bounds),
                         "labels": [{"name": n, "code": i, "count": int(counts[i])}
                                    for i, n in enumerate(self.labels)], **(metadata or {})}

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        o = self._objects
        inside = (o.x >= minx) & (o.x <= maxx) & (o.y >= miny) & (o.y <= maxy)
        return self._label_filter(o.take(inside), labels)

    def all(self) -> Objects:
        return self._objects


def _open_regular(path: Path, where: str) -> Any:
    """The file opened for reading, if it is a regular file.

    Opened without blocking and checked with fstat (not stat then open, which a swap could defeat): a FIFO
    or a device given as a map would otherwise hang the command or feed it endless bytes.
    """
    with reading(where, "map file"):
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                    else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
            raise MapdbIOError(f"{where}: is {kind}, not a map file" if kind.startswith("a ")
                               else f"{where}: not a regular file, not a map file")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


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
