"""The numpy code of the stored index's lookup the compiled kernel replaced (``_kernel_stored.c``), kept verbatim
as the tests' reference: ``query_cells``, ``bound_candidates``, ``pieces`` and ``Best`` as
mapdb/match/index/lookup.py had them, ``Directory.find`` as directory.py had it, and ``StoredQuadIndex.lookup``
with its ``_cell_ranges``, ``_candidates`` and ``_resolve`` as stored.py had them at 6767bec (methods made
functions of the index: ``self`` is the index)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from mapdb.errors import MapFormatError
from mapdb.match.arrays import sorted_unique
from mapdb.match.index.binding import check_filed
from mapdb.match.index.directory import Directory
from mapdb.match.index.layout import cell_keys
from mapdb.match.index.lookup import LOOKUP_CANDIDATES, take_rows
from mapdb.match.index.packed import PAGE_CELLS, unpack_records
from mapdb.match.index.stored import AUDITED, StoredQuadIndex
from mapdb.match.quads import canonical_quads

_BOUND_MARGIN = 0.05  # in positions inside a cell (1/16 to 1/256 of it): far above float32 rounding
_CELL_SLACK = 1e-6  # in cells: far above float64 rounding, so no cell holding a quad within the radius is left out
_ONES = np.ones(4, np.float32)
_STEPS = np.array(np.meshgrid(*[[-1, 0, 1]] * 4, indexing="ij")).reshape(4, -1).T  # the 81 neighbour cells


def query_cells(q: np.ndarray, r: np.ndarray, cell: np.ndarray, lk: np.ndarray, bits: int,
                sub_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells the balls of radius ``r`` (at most ``cell``) around invariants ``q`` reach.

    At most 3 per invariant, 81 in all, within the key's range; of those, only the cells whose box
    comes within ``r`` of ``q`` (a 4-D ball fills a third of its bounding cube: the corner cells of
    the cube hold no quad within the radius).  Returns the query row of each cell (ascending), the
    query's position relative to the cell's corner in 1/sub_cells of the cell, float32 ``(c, 4)`` (what
    :func:`bound_candidates` measures quads' positions inside their cells from), and its key (with the
    query's label key ``lk``).
    """
    s = (q + 1.0) / cell[:, None]  # the query in cell units: cell g spans [g, g + 1)
    base = np.maximum(np.floor(s), 0).astype(np.int64)
    top = (1 << bits) - 1
    cand = base[:, None, :] + _STEPS[None, :, :]
    gap = np.maximum(np.maximum(cand - s[:, None, :], s[:, None, :] - (cand + 1)), 0.0)
    reach = (r / cell)[:, None] * (1.0 + _CELL_SLACK) + _CELL_SLACK
    inside = ((gap * gap).sum(axis=2) <= reach * reach) & ((cand >= 0) & (cand <= top)).all(axis=2)
    which, step = np.nonzero(inside)
    cells = cand[which, step]
    rel = ((s[which] - cells) * sub_cells).astype(np.float32)
    return which, rel, cell_keys(lk[which], cells, bits)


def bound_candidates(which: np.ndarray, idx: np.ndarray, rel: np.ndarray, sub: np.ndarray,
                     r: np.ndarray, cell: np.ndarray, k: int, sub_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The candidates (query rows ``which``, ascending; quad positions ``idx``) worth measuring.

    Drops, from bounds on a candidate's distance given by its position ``sub`` inside its cell and its
    query's position ``rel`` relative to that cell (both in 1/sub_cells of the cell, :func:`query_cells`),
    those farther than the radius and those that cannot be among their query's ``k`` nearest.
    """
    # The candidate lies in [sub, sub + 1) per invariant: its gap to the query is max(d, -1 - d, 0) with
    # d = sub - rel, which is |d + 1/2| - 1/2 clipped at 0 (one shift and an absolute value instead of two
    # maxima: a quarter of the time).  Float32 (half the memory traffic; all of a lookup's time is here where
    # cells are crowded) with a margin far above its rounding keeps the bounds safe.
    d = sub.astype(np.float32)
    d -= rel - np.float32(0.5)
    np.abs(d, out=d)
    d -= np.float32(0.5)
    np.maximum(d, 0.0, out=d)
    d *= d
    lower = d @ _ONES  # a product with ones sums the four columns several times faster than sum(axis=1)
    reach = (r * (sub_cells / cell) + _BOUND_MARGIN).astype(np.float32)
    sel = np.flatnonzero(lower <= (reach * reach)[which])
    which, idx, lower = which[sel], idx[sel], lower[sel]
    if not idx.size or np.bincount(which).max() <= k:
        return which, idx
    # Only candidates that may be among the k nearest: the k-th smallest upper bound of a query's
    # candidates bounds its k-th nearest distance.  (Where many quads crowd a cell, this spares
    # reading and measuring most of them.)  The far corner lies max(d + 1, -d) = |d + 1/2| + 1/2 away.
    far = take_rows(sub, sel).astype(np.float32)
    far -= take_rows(rel, sel) - np.float32(0.5)
    np.abs(far, out=far)
    far += np.float32(0.5)
    far *= far
    # Upper bounds rounded up to 1/16ths in one exact integer sort key with the (ascending) row.
    upper = np.ceil(np.sqrt(far @ _ONES) * 16.0).astype(np.int64)
    key = (which << 24) | np.minimum(upper, (1 << 24) - 1)
    order = np.argsort(key)
    rank = np.arange(which.size) - np.searchsorted(which[order], which[order])
    kth = np.full(reach.size, np.inf, np.float32)
    kth[which[order[rank == k - 1]]] = upper[order[rank == k - 1]] / 16.0 + _BOUND_MARGIN
    sel = np.flatnonzero(lower <= np.minimum(kth, reach)[which] ** 2)
    return which[sel], idx[sel]


def pieces(start: np.ndarray, length: np.ndarray, limit: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Candidate quad positions of the ranges ``start + [0, length)``, at most about ``limit`` at a time.

    Yields the range number of each candidate and its position; a range longer than ``limit`` is cut.
    """
    if not start.size:
        return
    cuts = -(-length // limit)
    seg = np.repeat(np.arange(start.size), cuts)
    part = np.arange(seg.size) - np.repeat(np.cumsum(cuts) - cuts, cuts)
    s0 = start[seg] + part * limit
    n = np.minimum(length[seg] - part * limit, limit)
    ends = np.cumsum(n)
    group = (ends - 1) // limit
    bounds = np.flatnonzero(np.diff(group)) + 1
    for sel in np.split(np.arange(seg.size), bounds):
        counts = n[sel]
        total = int(counts.sum())
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        yield np.repeat(seg[sel], counts), np.repeat(s0[sel], counts) + offsets


class Best:
    """The ``k`` nearest hits per query row seen so far (ties kept in the order offered)."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.size = 0

    def offer(self, row: np.ndarray, ids: np.ndarray, dist: np.ndarray) -> None:
        """Add hits: query rows, object ids ``(h, 4)``, distances (memory stays bounded)."""
        self.parts.append((row, ids, dist))
        self.size += row.size
        if self.size > LOOKUP_CANDIDATES:
            self.parts = [self.result()]
            self.size = self.parts[0][0].size

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows (ascending), ids and distances of the ``k`` nearest hits per row, nearest first."""
        if not self.parts:
            return np.zeros(0, np.int64), np.zeros((0, 4), np.int64), np.zeros(0)
        row = np.concatenate([p[0] for p in self.parts])
        ids = np.concatenate([p[1] for p in self.parts])
        dist = np.concatenate([p[2] for p in self.parts])
        order = np.lexsort((dist, row))
        row, ids, dist = row[order], ids[order], dist[order]
        first = np.flatnonzero(np.concatenate([[True], row[1:] != row[:-1]])) if row.size else np.zeros(0, np.int64)
        rank = np.arange(row.size) - np.repeat(first, np.diff(np.append(first, row.size)))
        keep = rank < self.k
        return row[keep], ids[keep], dist[keep]


def find(self: Directory, keys: np.ndarray) -> np.ndarray:
    """Cell numbers of cell keys (-1 where absent): the fence names the page, a search inside it the cell."""
    if not self.fence_key.size or not keys.size:
        return np.full(keys.size, -1, np.int64)
    page = np.searchsorted(self.fence_key, keys, side="right") - 1
    ok = page >= 0
    page = np.maximum(page, 0)
    self.decode(page[ok])
    lo, hi = self.first_cell[page], self.first_cell[page + 1]
    # Branchless binary search inside each page (at most PAGE_CELLS cells): every probe stays on the page.
    at = lo
    for step in (PAGE_CELLS >> 1) >> np.arange((PAGE_CELLS >> 1).bit_length()):
        at = at + step * (self.key[np.minimum(at + (step - 1), hi - 1)] < keys)
    found = ok & (at < hi)
    found[found] = self.key[at[found]] == keys[found]
    return np.where(found, at, -1)


def lookup(self: StoredQuadIndex, invariants: np.ndarray, labels: np.ndarray, radius: np.ndarray | float, k: int, *,
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
    inv = np.asarray(invariants, np.float64).reshape(-1, 4)
    labels = np.asarray(labels, np.int64).reshape(-1, 4)
    m = len(inv)
    radius = np.broadcast_to(np.asarray(radius, np.float64), (m,))
    if len(labels) != m:
        raise ValueError(f"{m} invariant rows but {len(labels)} label rows")
    empty = (np.zeros(0, np.int64), np.zeros((0, 4), np.int64)) + ((np.zeros(0),) if return_distance else ())
    if m == 0 or k <= 0 or self.n_quads == 0:
        return empty
    pos, present = self._combo(labels)
    present &= np.isfinite(inv).all(axis=1) & np.isfinite(radius) & (radius >= 0)
    present &= ((labels >= 0) & (labels < len(self.labels))).all(axis=1)
    rows = np.flatnonzero(present)
    if not rows.size:
        return empty
    cell = self._combo_cell[pos[rows]]
    q = inv[rows]
    r = np.minimum(radius[rows], cell)
    self._audit(sorted_unique(self._combo_keys[pos[rows]]))
    which, start, length, rel, keys = _cell_ranges(self, q, r, cell, self._combo_keys[pos[rows]])
    best = Best(k)
    for piece, idx in pieces(start, length, LOOKUP_CANDIDATES):
        _candidates(self, which[piece], idx, take_rows(rel, piece), keys[piece], q, r, cell, k, best)
    row, ids, dist = best.result()
    row = rows[row]
    return (row, ids, dist) if return_distance else (row, ids)


def _cell_ranges(self: StoredQuadIndex, q: np.ndarray, r: np.ndarray, cell: np.ndarray,
                 lk: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The non-empty cells the queries' balls reach: query row, first quad, quads, the query's position
    relative to the cell (:func:`~mapdb.match.index.lookup.query_cells`), the cell's key.

    Their directory pages are decoded and checked, and the blocks of ``quads`` holding them (read below
    range by range).
    """
    which, rel, keys = query_cells(q, r, cell, lk, self._bits, 1 << self._sub_bits)
    at = find(self._directory, keys)
    found = at >= 0
    which, at = which[found], at[found]
    start, length = self._directory.start[at], self._directory.count[at]
    # Every candidate's record is read (its position inside the cell bounds its distance).
    self._sections["quads"].check_ranges(start, start + length)
    return which, start, length, rel[found], keys[found]


def _candidates(self: StoredQuadIndex, which: np.ndarray, idx: np.ndarray, rel: np.ndarray, key: np.ndarray,
                q: np.ndarray, r: np.ndarray, cell: np.ndarray, k: int, best: Best) -> None:
    """Bound, resolve and measure one batch of candidates; offer those within the radius to ``best``.

    ``which`` (the query row of each candidate) is ascending; ``key`` is the key of its cell.  Every
    resolved candidate must be filed where its recomputed invariants put it (``check_filed``).
    """
    anchor, triple, sub = unpack_records(take_rows(self._sections["quads"].array, idx), self._sub_bits,
                                         self._triple_bits)  # its blocks checked by _cell_ranges
    which_all = which
    which, kept = bound_candidates(which, np.arange(idx.size), rel, sub, r, cell, k, 1 << self._sub_bits)
    # A few candidates the bounds dropped are resolved and checked too: forged positions in cells (or cell
    # sides) would otherwise make every candidate look far, and lookups find nothing without a word.
    audit = sorted_unique(np.linspace(0, idx.size - 1, min(idx.size, AUDITED)).astype(np.int64))
    both = np.concatenate([kept, audit])
    ids, inv = _resolve(self, anchor[both], triple[both])
    check_filed(inv, key[both], take_rows(sub, both), cell[which_all[both]], self._bits, self._sub_bits,
                self.where)
    ids, inv = ids[: kept.size], inv[: kept.size]
    if not kept.size:
        return
    dist = np.sqrt(((inv - q[which]) ** 2).sum(axis=1))
    hit = dist <= r[which]
    best.offer(which[hit], ids[hit], dist[hit])


def _resolve(self: StoredQuadIndex, anchor: np.ndarray, triple: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Object ids ``(m, 4)`` in canonical order and invariants of quads given by anchors and triple numbers."""
    if anchor.size and (anchor.max() >= self.n_objects or triple.max() >= len(self._triples)):
        raise MapFormatError(f"{self.where}: quad index holds an object id out of range (file is corrupt)")
    nb = self._neighbours.rows(anchor)
    members = np.empty((anchor.size, 4), np.int64)
    members[:, 0] = anchor
    members[:, 1:] = np.take_along_axis(nb, self._triples[triple], axis=1)
    # The canonical order from the ids in ascending order, as at build time (and as QuadIndex does).
    members.sort(axis=1)
    with np.errstate(all="ignore"):  # four objects on one spot (forged coordinates): NaN, refused by the caller
        order, inv, _ = canonical_quads(self.coordinates(members))
    return np.take_along_axis(members, order, axis=1), inv
