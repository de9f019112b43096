"""Pixel class codes to one boolean mask per label present in a tile."""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping

import numpy as np

# Nothing public: read_landcover (mapdb.sources.landcover.reader) is the interface.
__all__: list[str] = []

# Up to this many class codes, label masks come from one comparison per code; beyond, from a lookup
# table (indexed by the code for up to 16-bit pixels, searched for wider ones).
_COMPARE_MAX_CODES = 16
_LUT_MAX_BITS = 16


class _ClassMasks:
    """Pixel codes -> one boolean mask per label present (codes not in the table and nodata excluded).

    With few codes (WorldCover has 10) a comparison per code is cheapest; with many (CORINE maps 32
    codes to 11 labels) the codes first go through a lookup table to label numbers.
    """

    def __init__(self, dtype: str, code_labels: Mapping[int, str], labels: tuple[str, ...],
                 nodata: float | None) -> None:
        dtype_ = np.dtype(dtype)
        info = np.iinfo(dtype_)
        index = {name: i + 1 for i, name in enumerate(labels)}
        pairs = {int(c): index[name] for c, name in code_labels.items() if info.min <= int(c) <= info.max}
        if nodata is not None and math.isfinite(nodata) and float(nodata).is_integer():
            pairs.pop(int(nodata), None)
        self.codes_present = frozenset(pairs)
        self.by_class: dict[int, list[int]] = {}
        for code, cls in sorted(pairs.items()):
            self.by_class.setdefault(cls, []).append(code)
        self.use_table = len(pairs) > _COMPARE_MAX_CODES
        if self.use_table and dtype_.itemsize * 8 <= _LUT_MAX_BITS:
            # Index by the code's unsigned bit pattern so signed types need no offset arithmetic.
            self.unsigned = np.dtype(f"u{dtype_.itemsize}")
            self.table = np.zeros(1 << (8 * dtype_.itemsize), np.uint8)
            for code, cls in pairs.items():
                self.table[np.array(code, dtype_).view(self.unsigned)] = cls
        elif self.use_table:
            order = sorted(pairs)
            self.codes = np.array(order, dtype=dtype_)
            self.values = np.array([pairs[c] for c in order], dtype=np.uint8)

    def is_class(self, value: float) -> bool:
        """Whether pixels of this value belong to some label."""
        return float(value).is_integer() and int(value) in self.codes_present

    def _classes(self, data: np.ndarray) -> np.ndarray:
        if hasattr(self, "table"):
            return self.table[data.view(self.unsigned)]
        pos = np.searchsorted(self.codes, data)
        np.minimum(pos, self.codes.size - 1, out=pos)
        return np.where(self.codes[pos] == data, self.values[pos], np.uint8(0))

    def __call__(self, data: np.ndarray, valid: np.ndarray | None) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(class number, first row, mask of rows first..last)`` for each label present."""
        if self.use_table:
            data = self._classes(data)
            by_value = {cls: [cls] for cls in self.by_class}
        else:
            by_value = self.by_class
        values = [v for vs in by_value.values() for v in vs]
        rows_with = dict(zip(values, _rows_with_values(data, values), strict=True))
        for cls, vs in by_value.items():
            present = [v for v in vs if rows_with[v].size]
            if not present:
                continue
            r0 = min(int(rows_with[v][0]) for v in present)
            r1 = max(int(rows_with[v][-1]) for v in present) + 1
            part = data[r0:r1]
            mask = part == present[0]
            for v in present[1:]:
                mask |= part == v
            if valid is not None:
                mask &= valid[r0:r1] != 0
            yield cls, r0, mask


def _rows_with_values(data: np.ndarray, values: list[int]) -> list[np.ndarray]:
    """For each value, the rows of ``data`` where it occurs.

    One pass over ``data`` in cache-sized row chunks, comparing each chunk with every value: a
    full-size comparison per value would stream the whole tile through memory once per value.
    """
    h, w = data.shape
    chunk = max(1, 1_000_000 // max(1, w))
    found = np.zeros((len(values), h), bool)
    scratch = np.empty((chunk, w), bool)
    for r in range(0, h, chunk):
        part = data[r:r + chunk]
        out = scratch[:part.shape[0]]
        for i, v in enumerate(values):
            np.equal(part, v, out=out)
            out.any(axis=1, out=found[i, r:r + part.shape[0]])
    return [np.flatnonzero(f) for f in found]
