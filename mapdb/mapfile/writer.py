"""Writing map files: :class:`MapWriter` (objects in chunks, bounded memory), :func:`write_map` and
:func:`write_map_from_chunks`.

The writer takes objects in chunks and holds a bounded number of them (``memory_objects``), whatever the map's
size: past that bound they wait in temporary files (:mod:`~mapdb.mapfile.spill`), and the pages are cut and
encoded one part of the map at a time.  The cuts are the same as those of the whole map in memory (see
:class:`MapWriter`), so the file is the same.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from ..errors import EmptyMapError, MapFormatError
from ..objects import Objects
from ..outputs import atomic_open
from .codec import _area_encode
from .header import _check_crs, _map_header, _pack_prefix
from .layout import (
    _MAX_EXTENT,
    _MAX_LABELS,
    _MAX_PAGE_OBJECTS,
    _MAX_QUANTA,
    _PILE,
    DEFAULT_ELEVATION_CELL_M,
    DEFAULT_ELEVATION_STEP,
    DEFAULT_QUANTUM,
)
from .pages import _ELEVATION_BIAS, NO_ELEVATION, _encode_page, _split_pages
from .spill import _RECORD, _bucket_of, _PageSink, _Scratch, _select, _Spill, _unique_records

__all__ = [
    "DEFAULT_MEMORY_OBJECTS",
    "DEFAULT_PAGE_CAPACITY",
    "MapWriter",
    "write_map",
    "write_map_from_chunks",
]

# Objects a writer holds in memory at once, by default.  Measured, 4 million objects given in 16 chunks: a
# peak of 150 MB over the process's memory before (chunks included), 60 MB with 262,144; as fast either way.
DEFAULT_MEMORY_OBJECTS = 1 << 20
# Most objects in one page, by default (a pile at one position may exceed it).
DEFAULT_PAGE_CAPACITY = 1024


class MapWriter:
    """Write a map file from objects given in chunks, in bounded memory.

    Chunks are added with :meth:`add` and the file is written by :meth:`finish`, to a temporary file renamed
    into place (as :func:`write_map`, which is this writer given one chunk).  The map is the one
    :func:`write_map` writes of all the chunks' objects together, byte for byte, whatever the chunks.

    Memory: the writer holds at most ``memory_objects`` objects at once (23 bytes each while they wait, and
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
    elevation_step, elevation_cell_m : float
        When a chunk carries ``elevation`` the map is a version 2 map holding each object's ground elevation
        in codes of ``elevation_step`` metres, relative to a base per cell of ``elevation_cell_m`` metres
        (``docs/format.md``, "Elevation"); objects of chunks without it, or NaN, are stored as unknown.

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
                 page_capacity: int = DEFAULT_PAGE_CAPACITY, memory_objects: int = DEFAULT_MEMORY_OBJECTS,
                 elevation_step: float = DEFAULT_ELEVATION_STEP,
                 elevation_cell_m: float = DEFAULT_ELEVATION_CELL_M) -> None:
        if not (0 < quantum <= 1000) or not (1 <= page_capacity <= _MAX_PAGE_OBJECTS):
            raise ValueError(f"quantum must be in (0, 1000] m and page capacity in [1, {_MAX_PAGE_OBJECTS}]")
        if not (0 < elevation_step <= 1000) or not (0 < elevation_cell_m <= 1e6):
            raise ValueError("elevation step must be in (0, 1000] m and elevation cell in (0, 1e6] m")
        self.elevation_step = elevation_step
        self._cell = int(min(max(round(elevation_cell_m / quantum), 1), _MAX_EXTENT + 1))
        self.elevated = False  # whether any chunk carried elevation: the map is then version 2
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
        records["elev"] = NO_ELEVATION
        if objects.elevation is not None:
            self.elevated = True
            code = np.rint(objects.elevation / self.elevation_step)
            # Beyond the format's codes (+-32 km at 1 m) a height is no ground's: stored as unknown.
            ok = np.isfinite(code) & (np.abs(code + 0.5) <= _ELEVATION_BIAS)
            records["elev"][ok] = code[ok].astype(np.int32)
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
                                 added - int(per_label.sum()), {**self.metadata, **(metadata or {})},
                                 (self.elevation_step, self._cell) if self.elevated else None)
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
                qx, qy, label, code, elev = (np.ascontiguousarray(records[k]) for k in ("x", "y", "label", "code",
                                                                                        "elev"))
                del records
                for idx in _split_pages(qx, qy, self.page_capacity, self.quantum):
                    elevation = (elev[idx].astype(np.int64), self._cell) if self.elevated else None
                    pages.add(*_encode_page(qx[idx], qy[idx], label[idx], code[idx], elevation))
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
    >>> from mapdb.mapfile.reader import open_map
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
