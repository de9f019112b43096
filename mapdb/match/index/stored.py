"""A disk-backed lost-in-space quad index: built in bounded memory, opened in milliseconds, memory-mapped.

The whole-map :class:`~mapdb.match.quads.QuadIndex` keeps every quad's complex coordinates and labels and
a cKDTree in memory, built at the first query (1M objects: 250 s, 13.8 GB).  This index holds a ninth of
those quads, each object's closest (six triples of its 5 nearest, :data:`~mapdb.match.index.layout.QUAD_TRIPLES`;
the canonical order and invariants from :func:`~mapdb.match.quads.canonical_quads`), packed with the objects'
coordinates into about 35 bytes an object, in a sidecar file ``MAP.qidx`` beside the map (``monaco.mapdb`` ->
``monaco.mapdb.qidx``); the format (version 4) is in ``docs/index_format.md``.

How it works (``docs/index_format.md`` in full)
    A quad is an anchor object and a triple of its 5 nearest neighbours, filed by its label combination
    and the cell of its invariants (side ``c`` per combination) with its position inside the cell; a
    lookup reads the cells its ball reaches and recomputes the candidates the positions do not rule out.
    **The lookup radius is clamped to the cell size** (:meth:`StoredQuadIndex.cell_size`): where ``c`` is
    smaller than the radius the quads are dense enough that the matcher's 16 nearest lie within ``c``.

Safety
    Nothing in the file is executed; every count and length is checked against the file size and the
    format's bounds when it is opened; every section is checksummed in 4 KiB blocks (CRC-32), each block
    checked the first time a lookup reads it (:meth:`StoredQuadIndex.verify` checks all); ids and ranges are
    checked before use, a lookup's memory is bounded, and its pages are asked for at once
    (``MADV_WILLNEED``: 5M objects, about 0.6 s for a cold image's lookups instead of 2 s).  The index is
    bound to its map (:mod:`~mapdb.match.index.binding`): the header's ``map`` section when it is opened with
    its map, each block of coordinates against its objects' page boxes, and each resolved quad (with a few the
    bounds dropped, and each label combination's first cell) against the cell it was found in.

The code is in the modules beside this one (the reader): :mod:`~mapdb.match.index.layout` (the format:
prefix, header, sections, cell keys), :mod:`~mapdb.match.index.packed` (the packed codes),
:mod:`~mapdb.match.index.build` (:func:`build_index`, the external sort; :mod:`~mapdb.match.index.sections`),
:mod:`~mapdb.match.index.generate` (neighbours, quads, cells), :mod:`~mapdb.match.index.lookup` (checked
sections), :mod:`~mapdb.match.index.directory` (the cell directory and the neighbours, decoded as lookups reach
them), :mod:`~mapdb.match.index.binding` (the index checked against its map).  A lookup's per-query work (its
cells, the directory search, the candidates' bounds, resolving and checking them, the ``k`` nearest) is the
compiled kernel's (``_kernel_stored.c``), which reads only what this reader has checked (:meth:`_kernel`).
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import MapdbIOError, MapFormatError, open_regular, reading
from ...mapfile.reader import MetaMap
from .._kernel import hits_points, hits_stored_lookup, stored_resolve
from ..arrays import sorted_unique
from ..quads import label_keys
from .binding import PageBoxes, check_filed, check_identity, check_positions, map_identity, mismatch
from .build import build_index
from .directory import Coordinates, Directory, Neighbours
from .layout import (
    INDEX_SUFFIX,
    check_sections,
    header_blocks,
    header_combos,
    header_counts,
    index_path,
    read_header,
    section_shapes,
    triples,
)
from .lookup import LOOKUP_CANDIDATES, map_sections
from .packed import unpack_records

# _kernel_stored.h's corruption codes: an id out of range, a quad not filed where its invariants put it, and (plus
# the block's number) a quads block whose checksum fails; any other code is a block out of range.
_BAD_ID, _NOT_FILED, _BAD_BLOCK = 1, 2, 16
AUDITED = 16  # candidates a lookup's batch resolves and checks whatever their bounds (check_filed)

__all__ = [
    "AUDITED",
    "INDEX_SUFFIX",
    "StoredQuadIndex",
    "build_index",
    "index_path",
    "map_identity",
    "open_index",
]


class StoredQuadIndex:
    """A quad index file opened for lookups (memory-mapped; use :func:`open_index` or :meth:`for_map`).

    Attributes
    ----------
    path : Path
    labels : tuple of str
        The map's label names: label codes in lookups index into them.
    neighbours : int
        The matcher's neighbours per anchor the index serves (its quads are of each object's 5 nearest).
    blocks_left_out : bool
        True for the index of a map with blocks of buildings: its quads are those of the map without the blocks.
    n_objects, n_quads, n_cells : int
    quantum : float
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        where = str(self.path)
        self._tables: tuple[object, ...] = ()  # the arrays the kernel's lookup reads (_kernel_tables)
        self._boxes: PageBoxes | None = None  # the map's page boxes, once bound to it (check_map)
        # Label combinations whose first cell was checked (_audit), by position in the combinations (the kernel
        # reads it).
        self._audited_at = np.zeros(0, bool)
        with reading(where, "quad index"):
            f = open_regular(self.path, where, "quad index")  # closed below once mapped and the small sections read
        try:
            try:
                size = os.fstat(f.fileno()).st_size
                header = read_header(f, size, where)
                self._mmap = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else None
                if self._mmap is not None and hasattr(mmap, "MADV_RANDOM"):
                    # Lookups read scattered pages: no read-ahead around each (a cold lookup reads what it needs).
                    self._mmap.madvise(mmap.MADV_RANDOM)
            except OSError as exc:
                raise MapdbIOError(f"{where}: cannot read quad index ({exc.strerror or exc})") from None
            try:
                self._setup(header, size, where, f.fileno())
            except BaseException as exc:
                self.close()
                if isinstance(exc, MapFormatError) or not isinstance(
                        exc, LookupError | TypeError | ValueError | OverflowError | AttributeError):
                    raise
                raise MapFormatError(f"{where}: header is not valid quad index metadata") from None
        finally:
            f.close()

    def _setup(self, h: dict[str, Any], size: int, where: str, fd: int) -> None:
        self.where = where
        self.header = h
        self.identity = dict(h["map"])
        self.labels = tuple(str(s) for s in self.identity["labels"])
        self.blocks_left_out = header_blocks(h, where)
        c = header_counts(h, len(self.labels), self.identity, where)
        self.quantum = float(self.identity["quantum"])
        self.max_cell, self.origin, self._bits = c.max_cell, c.origin, c.cell_bits
        self.n_objects, self.neighbours, self.n_quads, self.n_cells = c.objects, c.neighbours, c.quads, c.cells
        self.quad_neighbours, self._sub_bits, self._triple_bits = c.quad_neighbours, c.sub_bits, c.triple_bits
        self._triples = triples(c.quad_neighbours) if c.quad_neighbours >= 3 else np.zeros((0, 3), np.int64)
        self._combo_keys, self._combo_cell = header_combos(h["combos"], c.quads, len(self.labels), where)
        self._combo_cell = np.ascontiguousarray(self._combo_cell)  # a column of the header's table: the kernel's
        self._audited_at = np.zeros(self._combo_keys.size, bool)
        shapes = section_shapes(c)
        total_blocks = check_sections(h["sections"], shapes, int(h["_header_offset"]), where)
        self._sections, fence = map_sections(self._mmap, fd, h, shapes, total_blocks, where)
        read = self._sections
        self._directory = Directory(fence, read["dir_data"], self._combo_keys, self._combo_cell,
                                    (c.cells, c.quads, c.dir_bytes, c.max_cell, c.pages), c.cell_bits, where)
        self._neighbours = Neighbours(read["nb_start"], read["nb_width"], read["nb_data"], c.objects,
                                      c.quad_neighbours, where)
        self._coords = Coordinates(read["co_start"], read["co_width"], read["co_base"], read["co_data"], c.objects,
                                   where)
        self._tables = self._kernel_tables()

    def _kernel_tables(self) -> tuple[object, ...]:
        """The arrays the kernel's lookup reads (``_kernel_stored.h``), in its order: views of the sections and of
        the directory's, neighbours' and coordinates' arrays, which they fill in place as blocks are checked, and
        the quads section's checksums (the kernel checks the quads blocks it reaches, marking ``quads.checked``)."""
        d, nb, co, quads = self._directory, self._neighbours, self._coords, self._sections["quads"]
        return (quads.array, quads.checked, np.ascontiguousarray(d.fence_key), d.first_cell, d.decoded, d.key,
                d.start, d.count, np.ascontiguousarray(self._triples, np.int64), nb.start.array, nb.width.array,
                nb.data.array, nb.checked, co.xy, co.decoded, quads.crcs,
                (self._sub_bits, self._triple_bits, self._bits, self.quad_neighbours, self.n_objects,
                 int(self.origin[0]), int(self.origin[1]), self.quantum))

    # ------------------------------------------------------------------------------------------ public

    @classmethod
    def for_map(cls, map_: MetaMap, path: str | os.PathLike[str] | None = None) -> StoredQuadIndex | None:
        """The index beside an open map file (``path``, default :func:`index_path`), or None if there is none.

        A map held in memory (no file) has none.

        Raises
        ------
        MapFormatError
            If the index is damaged or was built for another map (or another version of this one).
        """
        if path is None and getattr(map_, "path", None) is None:
            return None
        path = index_path(map_.path) if path is None else Path(path)
        if not path.exists():
            return None
        return open_index(path, map_)

    def check_map(self, map_: MetaMap) -> None:
        """Refuse (:class:`MapFormatError`) unless this index was built from exactly this map file; then bind
        it to the map: each block of coordinates decoded from then on is checked against the map's page boxes."""
        check_identity(self.identity, map_, self.where)
        self._boxes = PageBoxes(map_.page_directory, self.origin, self.where, map_.path)
        self._coords.bind(self._boxes.check)

    def check_positions(self, x: np.ndarray, y: np.ndarray) -> None:
        """Refuse unless the index's coordinates are exactly the map's object positions ``x, y`` (map order):
        for a caller that holds the map's objects decoded anyway (it costs O(N))."""
        self._coords.verify()
        check_positions(self.coordinates(np.arange(self.n_objects)), np.asarray(x), np.asarray(y), self.where,
                        None if self._boxes is None else self._boxes.map_path)

    def close(self) -> None:
        """Release the mapping (arrays returned by lookups are copies and stay valid)."""
        self._sections = {}
        self._tables = ()
        if self._mmap is not None:
            try:
                self._mmap.close()
            except BufferError:  # a caller still holds a view: the mapping goes with it
                pass
            self._mmap = None

    def __enter__(self) -> StoredQuadIndex:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def verify(self) -> None:
        """Check every block of every section (lookups check only the blocks they read)."""
        for section in self._sections.values():
            section.verify()

    def cell_size(self, labels: np.ndarray) -> np.ndarray:
        """The cell side (the largest effective lookup radius) for label 4-tuples ``(m, 4)``; 0 if absent."""
        labels = np.asarray(labels, np.int64).reshape(-1, 4)
        pos, present = self._combo(labels)
        return np.where(present, self._combo_cell[np.minimum(pos, max(self._combo_cell.size - 1, 0))]
                        if self._combo_cell.size else 0.0, 0.0)

    def _combo(self, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lk = np.rint(label_keys(labels, len(self.labels))).astype(np.int64) if len(labels) else np.zeros(0, np.int64)
        if not self._combo_keys.size:
            return np.zeros(lk.size, np.int64), np.zeros(lk.size, bool)
        pos = np.searchsorted(self._combo_keys, lk)
        ok = pos < self._combo_keys.size
        ok[ok] = self._combo_keys[pos[ok]] == lk[ok]
        return pos, ok

    def coordinates(self, ids: np.ndarray) -> np.ndarray:
        """Map positions (complex ``x + iy``, map metres, as ``MetaMap.all()`` gives them) of object ids."""
        ids = np.asarray(ids, np.int64)
        # One kernel call (_kernel_hits.c) where the ids' blocks are decoded (those of a lookup's hits are).
        got = hits_points(self._tables, np.ascontiguousarray(ids.reshape(-1))) if self._tables else (1,)
        if got[0] == 0:
            return np.frombuffer(got[1], np.complex128).reshape(ids.shape)
        if got[0] == 2 or (ids.size and (ids.min() < 0 or ids.max() >= self.n_objects)):
            raise IndexError(f"object ids must be in [0, {self.n_objects})")
        c = self._coords.rows(ids.reshape(-1))
        x = (c[:, 0] + self.origin[0]) * self.quantum
        y = (c[:, 1] + self.origin[1]) * self.quantum
        return (x + 1j * y).reshape(ids.shape)

    def lookup(self, invariants: np.ndarray, labels: np.ndarray, radius: np.ndarray | float, k: int, *,
               return_distance: bool = False) -> tuple[np.ndarray, ...]:
        """Map quads near query quads: at most ``k`` per query, nearest first, within its radius.

        Parameters
        ----------
        invariants : (m, 4) float
            ``Re t_C, Im t_C, Re t_D, Im t_D`` of each query quad in canonical order
            (:func:`~mapdb.match.quads.canonical_quads`).
        labels : (m, 4) int
            Label codes (into :attr:`labels`) of the query's ``A, B, C, D``.
        radius : (m,) float or float
            Lookup radius in invariant space, clamped to :meth:`cell_size` of the query's labels.
        k : int
            Most hits per query.

        Returns
        -------
        row : (h,) int64
            The query row of each hit (ascending; within a row, nearest first).
        ids : (h, 4) int64
            The hit's object ids in canonical order ``A, B, C, D``; :meth:`coordinates` gives their
            positions.
        distance : (h,) float64
            Only with ``return_distance``: Euclidean distance of the invariants.

        Raises
        ------
        MapFormatError
            If a block read is corrupt or the file's ranges and ids are inconsistent.
        """
        inv = np.ascontiguousarray(np.asarray(invariants, np.float64).reshape(-1, 4))
        labels = np.ascontiguousarray(np.asarray(labels, np.int64).reshape(-1, 4))
        m = len(inv)
        radius = np.asarray(radius, np.float64)
        radius = np.full(m, radius) if radius.ndim == 0 else np.ascontiguousarray(radius)
        if len(labels) != m:
            raise ValueError(f"{m} invariant rows but {len(labels)} label rows")
        if radius.shape != (m,):  # one radius for all, say (ValueError if it cannot be)
            radius = np.ascontiguousarray(np.broadcast_to(radius, (m,)))
        empty = (np.zeros(0, np.int64), np.zeros((0, 4), np.int64)) + ((np.zeros(0),) if return_distance else ())
        if m == 0 or k <= 0 or self.n_quads == 0:
            return empty
        # One kernel call (_kernel_hits.c, then _kernel_stored.c's lookup): the rows with known label combinations,
        # finite invariants and radii, their radii clamped to their cells, then cells, directory, bounds, resolving,
        # filing checks and the best k, the hits' rows the query's.
        row, ids, dist = self._kernel(hits_stored_lookup, inv, labels, radius, self._combo_keys, self._combo_cell,
                                      len(self.labels), self._audited_at, int(k), LOOKUP_CANDIDATES)
        row = np.frombuffer(row, np.int64).copy()
        ids = np.frombuffer(ids, np.int64).reshape(-1, 4).copy()
        return (row, ids, np.frombuffer(dist, np.float64).copy()) if return_distance else (row, ids)

    def _kernel(self, call: Any, *args: Any) -> tuple[Any, ...]:
        """A kernel call on this index's tables: where it reaches a directory page, neighbour block or coordinate
        block not checked yet, those are decoded and checked here (the checks and their errors are Python's) and
        the call made again.  The quads blocks it reaches the kernel checksums itself and goes on."""
        for _ in range(9):  # a round checks what the previous reached: pages, quads, neighbours (and coordinates)
            out = call(self._tables, *args)
            if out[0] == 0:
                return tuple(out[1:])
            if out[0] == 3:  # (hits_stored_lookup) label combinations not audited yet: audit them, then ask again
                self._audit(np.frombuffer(out[1], np.int64))
                continue
            if out[0] == 2:
                raise self._corruption(int(out[1]))
            # The quads blocks the lookup reaches it checks itself (_kernel_qcheck.c): it asks for no quad ranges.
            pages, _, nb, co = (np.frombuffer(b, np.int64) for b in out[1:])
            if pages.size:
                self._directory.decode(pages)
            if nb.size:  # and the coordinates of those anchors' quads, which the next round would ask for
                co = np.concatenate([co, nb, self._neighbours.rows(nb).reshape(-1)])
            if co.size:
                self._coords.rows(co)
        raise MapFormatError(f"{self.where}: quad index blocks could not be checked (file is corrupt)")

    def _corruption(self, code: int) -> MapFormatError:
        """The error of a kernel's corruption code (_kernel_stored.h: STORED_BAD_ID, NOT_FILED, BAD_RANGE, and
        STORED_BAD_BLOCK plus a quads block's number: the message :class:`~.lookup.Section` gives it)."""
        if code >= _BAD_BLOCK:
            return MapFormatError(f"{self.where}: quads block {code - _BAD_BLOCK} checksum mismatch (file is corrupt)")
        if code == _BAD_ID:
            return MapFormatError(f"{self.where}: quad index holds an object id out of range (file is corrupt)")
        if code == _NOT_FILED:
            return mismatch(self.where, "a quad recomputed from its objects is not where the index files it")
        return MapFormatError(f"{self.where}: quad index block out of range (file is corrupt)")

    def _audit(self, lk: np.ndarray) -> None:
        """The first lookup of each label combination resolves the first quad of its first cell and checks that
        it is filed there (``check_filed``): a forged cell side would make lookups of the combination miss
        every cell, finding nothing to check and nothing to answer with."""
        # sorted_unique, not np.unique: it imports numpy.ma (0.05 s of a first answer), see mapdb.match.arrays.
        combos = np.searchsorted(self._combo_keys, sorted_unique(lk))
        new = combos[~self._audited_at[combos]]
        if new.size:
            at = self._directory.first_cells(self._combo_keys[new])
            records = self._records(self._directory.start[at])
            _, inv = self._resolve(records[0], records[1])
            check_filed(inv, self._directory.key[at], records[2], self._combo_cell[new], self._bits, self._sub_bits,
                        self.where)
        self._audited_at[combos] = True

    def _records(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Anchors, triple numbers and positions inside their cells of the quads at ``positions``."""
        rows = self._sections["quads"].rows(positions)
        return unpack_records(rows, self._sub_bits, self._triple_bits)

    def _resolve(self, anchor: np.ndarray, triple: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Object ids ``(m, 4)`` in canonical order and invariants of quads given by anchors and triple numbers
        (the kernel's: ids sorted, then :func:`~mapdb.match.quads.canonical_quads`' order; NaN invariants for four
        objects on one spot, refused by the caller)."""
        ids, inv = self._kernel(stored_resolve, np.ascontiguousarray(anchor, np.int64),
                                np.ascontiguousarray(triple, np.int64))
        return np.frombuffer(ids, np.int64).reshape(-1, 4).copy(), np.frombuffer(inv, np.float64).reshape(-1, 4).copy()

    def quads(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Object ids ``(m, 4)``, in canonical order, of the stored quads ``start:stop`` (in key order)."""
        stop = self.n_quads if stop is None else min(stop, self.n_quads)
        anchor, triple, _ = self._records(np.arange(max(start, 0), max(stop, start, 0), dtype=np.int64))
        return self._resolve(anchor, triple)[0]




def open_index(path: str | os.PathLike[str], map_: MetaMap | None = None) -> StoredQuadIndex:
    """Open a quad index file; with ``map_``, refuse it unless it was built from that map file.

    Raises
    ------
    MapdbIOError
        If the file is missing or unreadable.
    MapFormatError
        If it is not a quad index, is truncated, fails a checksum, holds counts its size cannot hold, or
        (with ``map_``) belongs to another map.
    """
    index = StoredQuadIndex(path)
    if map_ is not None:
        try:
            index.check_map(map_)
        except BaseException:
            index.close()
            raise
    return index
