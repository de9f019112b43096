"""The quads of a stored index: each object's neighbours, quads by chunks of anchors, cells chosen from a sample.

A quad is an *anchor* object and a triple of its ``K`` nearest neighbours, kept once, at the smallest-id
member whose neighbours hold the other three; its canonical order, invariants and label key are those of
:class:`~mapdb.match.quads.QuadIndex`.  :mod:`~mapdb.match.index.build` runs :func:`chunk_records` in
forked worker processes; they read the build's arrays from :data:`SHARED`, inherited copy-on-write.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..._scipy import cKDTree
from ...labels import BLOCK_LABEL
from ..nearest import nearest_others
from ..quads import canonical_quads, label_keys
from .layout import CELL_LADDER, cell_keys, cells_of, triples

__all__ = ["RECORD", "SHARED", "block_free_world", "cell_for", "choose_cells", "chunk_quads", "chunk_records",
           "neighbour_table", "sample_quads", "world_neighbours"]

_SAMPLE_QUADS = 2_000_000  # quads sampled to choose cells and buckets
_BLOCK_ANCHORS = 1024  # anchors whose quads are generated at once
RECORD = np.dtype([("key", "<u8"), ("anchor", "<u4"), ("triple", "u1"), ("sub", "u1", (4,))])  # a bucket's quads

# Arrays of the build shared with forked worker processes (read-only, inherited copy-on-write):
# neighbours, z, label, n_labels, bits, world (None, or which objects anchor quads), and once the sample has
# chosen them combo_keys, combo_cell, splitters.
SHARED: dict[str, Any] = {}


def neighbour_table(xy: np.ndarray, k: int, workers: int) -> np.ndarray:
    """Each object's ``k`` nearest other objects (uint32 ids, nearest first), as neighbour_quads finds them.

    The same cKDTree over the same points and the same search (:func:`~mapdb.match.nearest.nearest_others`)
    as :func:`~mapdb.match.quads.neighbour_quads`, so the quads built from this table are that function's
    (``tests/test_stored_index.py`` checks it); queried in chunks to bound memory.
    """
    n = len(xy)
    tree = cKDTree(xy)
    table = np.empty((n, k), np.uint32)
    step = 1 << 18
    for lo in range(0, n, step):
        ids = np.arange(lo, min(n, lo + step))
        table[ids] = nearest_others(tree, xy, ids, k, workers)
    return table


def block_free_world(map_: Any, objects: Any) -> np.ndarray | None:
    """Which of a map's objects (``map_.all()``) are not blocks, for a map holding blocks; None for one without.

    The index of a map with blocks holds the quads of the map without them: those of the view point images are
    matched in (:mod:`~mapdb.match.mapobjects.blocks_view`), identical to the map's built with ``--no-blocks``.
    """
    from ..mapobjects.blocks_view import has_blocks  # the one definition of a map holding blocks

    if not has_blocks(map_):
        return None
    return np.asarray(objects.label) != list(map_.labels).index(BLOCK_LABEL)


def world_neighbours(xy: np.ndarray, world: np.ndarray, k: int, workers: int) -> np.ndarray:
    """Each object's ``k`` nearest other objects of ``world`` (uint32 ids of all objects, nearest first).

    Objects of the world get :func:`neighbour_table` of the world alone (the same tree, in the same order, as
    the map without its other objects); the others (blocks: no quad is anchored at one) their ``k`` nearest
    world objects, so that their rows pack as small as their neighbours' ids.
    """
    ids = np.flatnonzero(world)
    table = np.empty((len(xy), k), np.uint32)
    table[ids] = ids[neighbour_table(xy[ids], k, workers)]
    rest = np.flatnonzero(~world)
    if rest.size:
        _, near = cKDTree(xy[ids]).query(xy[rest], k=k)
        table[rest] = ids[np.asarray(near).reshape(rest.size, k)]
    return table


def chunk_quads(lo: int, hi: int, anchors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The quads anchored at objects ``lo..hi`` (or at ``anchors``), each kept at one anchor only.

    Returns anchor ids, triple numbers, canonical invariants ``(m, 4)`` and label-combination keys.
    """
    table, z, label, n_labels = SHARED["neighbours"], SHARED["z"], SHARED["label"], SHARED["n_labels"]
    k = table.shape[1]
    numbered = triples(k)
    a = np.arange(lo, hi, dtype=np.int64) if anchors is None else anchors.astype(np.int64)
    if SHARED.get("world") is not None:
        a = a[SHARED["world"][a]]  # a map's blocks anchor no quad (block_free_world)
    t = len(numbered)
    anchor = np.repeat(a, t)
    triple = np.tile(np.arange(t, dtype=np.int64), a.size)
    members = np.empty((anchor.size, 4), np.int64)
    members[:, 0] = anchor
    members[:, 1:] = table[a][:, numbered].reshape(-1, 3)
    keep = _kept_here(table, anchor, members, numbered)
    anchor, triple, members = anchor[keep], triple[keep], members[keep]
    # Four objects on one spot have no frame (QuadIndex drops them too).
    zq = z[members]
    ok = np.abs(zq - zq[:, :1]).max(axis=1) > 0.0
    anchor, triple, members = anchor[ok], triple[ok], members[ok]
    # Canonical order and invariants from the quad's ids in ascending order, as QuadIndex computes them.
    members.sort(axis=1)
    order, inv, _ = canonical_quads(z[members])
    ids = np.take_along_axis(members, order, axis=1)
    lk = np.rint(label_keys(label[ids], n_labels)).astype(np.int64)
    return anchor, triple, inv, lk


def _kept_here(table: np.ndarray, anchor: np.ndarray, members: np.ndarray, numbered: np.ndarray) -> np.ndarray:
    """Which quads ``members`` (anchor first) are kept at ``anchor``.

    A quad reached from several of its members is kept at the smallest-id one whose neighbours hold the
    other three at the places of one of the triples ``numbered``: dropped here when a smaller member
    generates it too.
    """
    k = table.shape[1]
    made = np.zeros(k**3, bool)  # the triples generated, by their places sorted: (i * k + j) * k + l
    made[(numbered[:, 0] * k + numbered[:, 1]) * k + numbered[:, 2]] = True
    keep = np.ones(anchor.size, bool)
    for j in (1, 2, 3):
        m = members[:, j]
        rows = np.flatnonzero(keep & (m < anchor))
        if not rows.size:
            continue
        theirs = table[m[rows]]
        others = members[rows][:, [i for i in range(4) if i != j]]
        at = theirs[:, None, :] == others[:, :, None]  # (rows, 3, k): where each other member is in m's neighbours
        holds = at.any(axis=2).all(axis=1)
        place = np.sort(at.argmax(axis=2), axis=1)
        generates = holds & made[(place[:, 0] * k + place[:, 1]) * k + place[:, 2]]
        keep[rows[generates]] = False
    return keep


def chunk_records(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Final records of a chunk of anchors, grouped by sort bucket; the bucket sizes; label keys present."""
    parts = []
    # Blocks of a few thousand anchors keep the arrays of quad generation in the CPU caches (1.5x faster).
    for a in range(lo, hi, _BLOCK_ANCHORS):
        anchor, triple, inv, lk = chunk_quads(a, min(hi, a + _BLOCK_ANCHORS))
        cells, sub = cells_of(inv, cell_for(lk, SHARED["combo_keys"], SHARED["combo_cell"]), SHARED["sub_cells"])
        rec = np.empty(anchor.size, RECORD)
        rec["key"] = cell_keys(lk, cells, SHARED["bits"])
        rec["anchor"] = anchor
        rec["triple"] = triple
        rec["sub"] = sub
        parts.append((rec, lk))
    rec = np.concatenate([p[0] for p in parts])
    bucket = np.searchsorted(SHARED["splitters"], rec["key"], side="right")
    order = np.argsort(bucket, kind="stable")
    counts = np.bincount(bucket, minlength=SHARED["splitters"].size + 1)
    return rec[order], counts, np.unique(np.concatenate([p[1] for p in parts]))


def sample_quads(n: int, n_triples: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Invariants and label keys of the quads of a random sample of anchors (fixed seed), and its rate.

    About ``_SAMPLE_QUADS`` quads: enough to choose each label combination's cell and the sort buckets.
    """
    expected = n * n_triples * 0.65  # about 4.1 of 6 quads per anchor survive de-duplication
    rate = min(1.0, _SAMPLE_QUADS / max(expected, 1.0))
    if not n_triples:
        return np.zeros((0, 4)), np.zeros(0, np.int64), rate
    rng = np.random.default_rng(0)
    sample_anchors = np.flatnonzero(rng.random(n) < rate) if rate < 1.0 else np.arange(n)
    parts = [chunk_quads(0, 0, sample_anchors[i : i + _BLOCK_ANCHORS])
             for i in range(0, sample_anchors.size, _BLOCK_ANCHORS)]
    inv = np.concatenate([p[2] for p in parts]) if parts else np.zeros((0, 4))
    lk = np.concatenate([p[3] for p in parts]) if parts else np.zeros(0, np.int64)
    return inv, lk, rate


def cell_for(lk: np.ndarray, combo_keys: np.ndarray, combo_cell: np.ndarray) -> np.ndarray:
    """Cell side of each label-combination key: its chosen one, the ladder's largest for one not sampled."""
    cell = np.full(lk.size, CELL_LADDER[0])
    if combo_keys.size:
        pos = np.minimum(np.searchsorted(combo_keys, lk), combo_keys.size - 1)
        known = combo_keys[pos] == lk
        cell[known] = combo_cell[pos[known]]
    return cell


def choose_cells(inv: np.ndarray, lk: np.ndarray, rate: float, target: float) -> tuple[np.ndarray, np.ndarray]:
    """Per label combination in the sample, the largest ladder cell whose occupancy is at most ``target``.

    Occupancy is the number of other quads in a quad's own cell, averaged over quads:
    ``sum n (n - 1) / N`` over cells, estimated from a sample taken at ``rate`` as
    ``sum s (s - 1) / (rate * S)``.
    """
    combos, combo_of, size = np.unique(lk, return_inverse=True, return_counts=True)
    chosen = np.full(combos.size, CELL_LADDER[-1])
    settled = np.zeros(combos.size, bool)
    for c in CELL_LADDER:
        # One integer per (combination, cell): cell coordinates stay below 2 / c + 1 < 2^11.
        cells = np.floor((inv + 1.0) / c).astype(np.int64)
        key = combo_of.astype(np.int64) << 44
        for j in range(4):
            key |= cells[:, j] << (11 * j)
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        # sum over cells of s (s - 1): each sampled quad counts the others in its cell
        pairs = np.bincount(combo_of, weights=counts[inverse] - 1.0, minlength=combos.size)
        occupancy = pairs / (rate * size)
        fits = ~settled & (occupancy <= target)
        chosen[fits] = c
        settled |= fits
    return combos, chosen
