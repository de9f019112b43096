"""Medians and longitude arcs of values read in blocks, in bounded memory, equal to the in-memory ones.

The automatic CRS of a build is the UTM zone of the objects' median place, counted around the globe from
the widest gap between their longitudes (:func:`mapdb.geo.central_longitude`).  A country's objects are read
back from disk in blocks (:mod:`mapdb.sources.spool`), so these take a function that gives the blocks afresh and read
them a few times, holding a fixed amount of memory, and return exactly what :func:`numpy.median`,
:func:`mapdb.geo._lon_arc` and :func:`mapdb.geo.central_longitude` return on all the values at once:

* a median is found digit by digit (16 bits of an order-preserving integer key of each float at a time: four
  passes, one histogram of 65,536 counts);
* the widest gap between longitudes from the lowest and highest value of each of :data:`ARC_BINS` bins (one
  pass); only when no gap between bins is wider than the spread inside some bin (data leaving no gap of
  360 / ARC_BINS degrees anywhere around the globe) are the values of those bins gathered.

Values that number at most :data:`IN_MEMORY_VALUES` (a town's or a small country's objects) are gathered
in one array and given to the in-memory functions themselves: the passes above would only cost more time.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from ..geo import _lon_arc, central_longitude

__all__ = ["ARC_BINS", "IN_MEMORY_VALUES", "Blocks", "central_longitude_of", "lon_arc_of", "median_of"]

# A zero-argument function giving the values again, block by block (1-D float arrays).
Blocks = Callable[[], Iterable[np.ndarray]]

# Longitude bins of the widest-gap search (two float arrays of this many values).
ARC_BINS = 1 << 16
_DIGIT = 16
_SIGN = np.uint64(1 << 63)
# Values gathered in memory, when there are no more (8 MB, a few times that while sorted): below it the
# blocks are read once; from it in the passes above, the first of which stops reading here.
IN_MEMORY_VALUES = 1 << 20


def _gathered(blocks: Blocks, most: int) -> np.ndarray | None:
    """All the values in one array when they number at most ``most``, else None."""
    parts, n = [], 0
    for block in blocks():
        block = np.asarray(block, np.float64).ravel()
        n += block.size
        if n > most:
            return None
        parts.append(block)
    return np.concatenate(parts) if parts else np.zeros(0)


def _keys(values: np.ndarray) -> np.ndarray:
    """Unsigned integer keys in the order of the (non-NaN) floats: the sign bit set for positives, all bits
    flipped for negatives."""
    bits = np.ascontiguousarray(values, np.float64).view(np.uint64)
    return np.where(bits & _SIGN, ~bits, bits | _SIGN)


def _value(key: int) -> np.float64:
    bits = np.uint64(key)
    bits = bits & ~_SIGN if bits & _SIGN else ~bits
    return np.array([bits], np.uint64).view(np.float64)[0]


def _select(blocks: Blocks, ranks: list[int]) -> list[np.float64]:
    """The values of the given 0-based ranks in the sorted order of all values, exactly."""
    prefixes, below = [0] * len(ranks), [0] * len(ranks)
    for shift in range(64 - _DIGIT, -1, -_DIGIT):
        counts = [np.zeros(1 << _DIGIT, np.int64) for _ in ranks]
        for block in blocks():
            keys = _keys(block)
            for i, prefix in enumerate(prefixes):
                chosen = keys if shift == 64 - _DIGIT else keys[(keys >> np.uint64(shift + _DIGIT)) == prefix]
                digits = ((chosen >> np.uint64(shift)) & np.uint64((1 << _DIGIT) - 1)).astype(np.intp)
                counts[i] += np.bincount(digits, minlength=1 << _DIGIT)
        for i, rank in enumerate(ranks):
            cumulative = np.cumsum(counts[i])
            digit = int(np.searchsorted(cumulative, rank - below[i], side="right"))
            below[i] += int(cumulative[digit - 1]) if digit else 0
            prefixes[i] = (prefixes[i] << _DIGIT) | digit
    return [_value(prefix) for prefix in prefixes]


def median_of(blocks: Blocks, in_memory: int = IN_MEMORY_VALUES) -> np.float64:
    """``np.median`` of all the values (the mean of the two middle ones for an even count); up to
    ``in_memory`` values are gathered and given to it.

    Examples
    --------
    >>> float(median_of(lambda: [np.array([3.0, -1.0]), np.array([7.0, 2.0])]))
    2.5
    >>> float(median_of(lambda: [np.array([3.0, -1.0]), np.array([7.0, 2.0])], in_memory=0))
    2.5
    """
    values = _gathered(blocks, in_memory)
    if values is not None and values.size:
        return np.median(values)
    n = sum(np.asarray(block).size for block in blocks())
    if n == 0:
        raise ValueError("the median of no values")
    if n % 2:
        return _select(blocks, [n // 2])[0]
    low, high = _select(blocks, [n // 2 - 1, n // 2])
    return (low + high) / 2


def _wrapped(lon: np.ndarray) -> np.ndarray:
    """Longitudes in [-180, 180), sorted (as :func:`mapdb.geo._lon_arc` takes them)."""
    return np.sort(np.mod(np.asarray(lon, np.float64) + 180.0, 360.0) - 180.0)


def _bin_of(values: np.ndarray, bins: int) -> np.ndarray:
    return np.clip(((values + 180.0) * (bins / 360.0)).astype(np.int64), 0, bins - 1)


def lon_arc_of(blocks: Blocks, bins: int | None = None, in_memory: int = IN_MEMORY_VALUES) -> tuple[float, float]:
    """The shortest eastward arc (start, width in degrees) holding every longitude, as ``geo._lon_arc`` (which
    is given up to ``in_memory`` values gathered).

    Examples
    --------
    >>> lon_arc_of(lambda: [np.array([179.0, -179.8]), np.array([179.5])])
    (179.0, 1.1999999999999886)
    >>> lon_arc_of(lambda: [np.array([179.0, -179.8]), np.array([179.5])], in_memory=0)
    (179.0, 1.1999999999999886)
    """
    values = _gathered(blocks, in_memory)
    if values is not None and values.size:
        return _lon_arc(values)
    bins = bins or ARC_BINS
    low, high = np.full(bins, np.inf), np.full(bins, -np.inf)
    for block in blocks():
        values = _wrapped(block)
        if not values.size:
            continue
        where = _bin_of(values, bins)
        first = np.flatnonzero(np.concatenate([[True], where[1:] != where[:-1]]))
        last = np.concatenate([first[1:] - 1, [values.size - 1]])
        used = where[first]
        low[used] = np.minimum(low[used], values[first])
        high[used] = np.maximum(high[used], values[last])
    used = np.flatnonzero(np.isfinite(low))
    if not used.size:
        raise ValueError("the arc of no longitudes")
    # The gaps between consecutive bins in order, then the one across the antimeridian back to the first.
    gaps = np.concatenate([low[used[1:]] - high[used[:-1]], [(low[used[0]] + 360.0) - high[used[-1]]]])
    after = np.concatenate([low[used[1:]], low[used[:1]]])
    spread = high[used] - low[used]
    if gaps.max() <= spread.max():  # some bin may hold the widest gap: look inside those bins
        gaps, after = _gaps_with_insides(blocks, bins, used, gaps, after, spread >= gaps.max())
    widest = int(np.argmax(gaps))  # the first of equal gaps in sorted order, as np.argmax over all values
    return float(after[widest]), 360.0 - float(gaps[widest])


def _gaps_with_insides(blocks: Blocks, bins: int, used: np.ndarray, gaps: np.ndarray, after: np.ndarray,
                       open_bins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gaps between bins with those inside the ``open_bins`` (a mask over ``used``) put in their
    places: each bin's inner gaps come before the gap that follows it."""
    wanted = used[open_bins]
    inside = [values[np.isin(_bin_of(values, bins), wanted)] for values in map(_wrapped, blocks())]
    values = np.sort(np.concatenate(inside))
    where = _bin_of(values, bins)
    same = where[1:] == where[:-1]
    inner_gap, inner_after, inner_bin = (values[1:] - values[:-1])[same], values[1:][same], where[1:][same]
    # Order: by bin, the inner gaps (in value order) before the bin's following gap.
    bin_of_gap = np.concatenate([inner_bin, used])
    kind = np.concatenate([np.zeros(inner_bin.size, np.int8), np.ones(used.size, np.int8)])
    order = np.lexsort((kind, bin_of_gap))  # stable: inner gaps keep their value order
    return np.concatenate([inner_gap, gaps])[order], np.concatenate([inner_after, after])[order]


def central_longitude_of(blocks: Blocks, in_memory: int = IN_MEMORY_VALUES) -> float:
    """The median longitude counted from the widest gap, as :func:`mapdb.geo.central_longitude` (which is given
    up to ``in_memory`` values gathered).

    Examples
    --------
    >>> central_longitude_of(lambda: [np.array([179.0, 179.5]), np.array([-179.8])])
    179.5
    >>> central_longitude_of(lambda: [np.array([179.0, 179.5]), np.array([-179.8])], in_memory=0)
    179.5
    """
    values = _gathered(blocks, in_memory)
    if values is not None and values.size:
        return central_longitude(values)
    start, _ = lon_arc_of(blocks, in_memory=0)

    def unwrapped() -> Iterable[np.ndarray]:
        for lon in blocks():
            yield np.mod(np.asarray(lon, np.float64) - start, 360.0) + start

    return float((median_of(unwrapped, in_memory=0) + 180.0) % 360.0 - 180.0)
