"""The map file's value codecs: log-quantized area codes, and the bit-level Rice code of the pages.

Encoding (:func:`_rice_streams`, :func:`_bits_of`) and the vectorised primitives a reader decodes a batch of
pages with (:func:`_read_fields`, segment-wise ranks, offsets and sums, byte tables for counting zero bits).
The page layout that uses them is in :mod:`~mapdb.mapfile.pages`.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "area_codes",
]

_AREA_STEPS = 8  # codes per doubling of area: +-4.4 % relative precision
_AREA_FLOOR_LOG2 = -16  # smallest non-zero area stored: 2**-16 m^2
_MAX_AREA_CODE = (1024 - _AREA_FLOOR_LOG2) * _AREA_STEPS  # the largest code whose area is a finite float64
_RICE_VALUE_BITS = 48  # every Rice-coded value (a key gap, an area residual) is below 2**48


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


_WINDOW = np.arange(8, dtype=np.uint64)
_BYTE_BITS = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).astype(np.int64)  # MSB first
_ZEROS_IN_BYTE = (8 - _BYTE_BITS.sum(axis=1)).astype(np.int64)
# zeros among the first j bits of a byte (j = 0..8), and the position of its t-th zero (t = 0..7; 0 if none)
_ZEROS_BEFORE = np.concatenate([np.zeros((256, 1), np.int64), np.cumsum(1 - _BYTE_BITS, axis=1)], axis=1)
_NTH_ZERO = np.array([np.r_[np.flatnonzero(row == 0), np.zeros(8, np.int64)][:8] for row in _BYTE_BITS], np.int64)


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
