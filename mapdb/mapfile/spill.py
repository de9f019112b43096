"""The map writer's external memory: records and encoded pages past a bound wait in temporary files.

The writer takes objects in chunks and holds a bounded number of them (``memory_objects``), whatever the map's
size: past that bound they wait in temporary files beside the output, as compact records (quantized position,
label code, area code, elevation code: 23 bytes an object).  Here are those files (:class:`_Scratch`, :class:`_Spill`,
:class:`_PageSink`), the duplicate merge by buckets (:func:`_unique_records`, :func:`_bucket_of`) and the
histogram passes that find a median cut in a part too big to sort in memory (:func:`_select`).  How the
writer uses them is in :mod:`~mapdb.mapfile.writer`.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MapdbError, MapdbIOError
from ..outputs import temporary_prefix
from .layout import _DIR_DTYPE, _MAX_QUANTA

__all__: list[str] = []

# packed: 23 bytes; "elev" is the elevation code (NO_ELEVATION where unknown, and in maps without elevation)
_RECORD = np.dtype([("x", "<i8"), ("y", "<i8"), ("label", "u1"), ("code", "<u2"), ("elev", "<i4")])
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
