"""The stored index's lookup steps against brute force: the directory search, the packed codes, the bounds."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from storedrefs import bound_candidates, find

from mapdb.errors import MapFormatError
from mapdb.match.index.directory import Directory, Neighbours
from mapdb.match.index.layout import BLOCK, cell_keys
from mapdb.match.index.lookup import Section, take_rows
from mapdb.match.index.packed import (
    NB_BLOCK,
    PAD,
    PAGE_CELLS,
    directory_pages,
    pack_neighbours,
    pack_records,
    record_layout,
    unpack_records,
)

SUB_CELLS = 256
BITS = 12


def _section(array: np.ndarray, name: str = "dir_data") -> Section:
    raw = array.tobytes()
    crcs = np.array([zlib.crc32(raw[i : i + BLOCK]) for i in range(0, len(raw), BLOCK)], np.uint32)
    return Section(name, array, crcs, "test.qidx")


def _directory(n_cells: int, seed: int) -> tuple[Directory, np.ndarray, np.ndarray]:
    """A directory of ``n_cells`` random cells of two label combinations (cell sides 0.1 and 0.011)."""
    rng = np.random.default_rng(seed)
    combos, sides = np.array([3, 9]), np.array([0.1, 0.011])
    lk = np.sort(rng.choice(combos, n_cells))
    top = np.floor(2.0 / sides[np.searchsorted(combos, lk)]).astype(np.int64)
    cells = (rng.uniform(0, 1, (n_cells, 4)) * (top[:, None] + 1)).astype(np.int64)
    keys, first = np.unique(cell_keys(lk, cells, BITS), return_index=True)
    counts = rng.integers(1, 30, keys.size)
    data, fence = directory_pages(keys, counts, combos, sides, BITS)
    data = np.concatenate([data, np.zeros(PAD, np.uint8)])
    d = Directory(fence, _section(data), combos, sides, (keys.size, int(counts.sum()), data.size - PAD,
                                                             int(counts.max()), fence.shape[0] - 1), BITS, "test.qidx")
    return d, keys, counts


@pytest.mark.parametrize("n_cells", [1, 7, PAGE_CELLS, PAGE_CELLS + 1, 3 * PAGE_CELLS + 200, 5000])
def test_the_directory_finds_every_cell_and_no_absent_one(n_cells: int) -> None:
    d, keys, counts = _directory(n_cells, n_cells)
    present = np.random.default_rng(1).permutation(keys)
    at = find(d, present)
    assert at.tolist() == np.searchsorted(keys, present).tolist()
    assert d.count[at].tolist() == counts[at].tolist()
    assert d.start[at].tolist() == (np.cumsum(counts) - counts)[at].tolist()
    absent = np.setdiff1d(np.concatenate([keys + np.uint64(1), keys - np.uint64(1)]), keys)
    edges = np.array([0, 1, np.iinfo(np.uint64).max], np.uint64)
    assert (find(d, np.setdiff1d(np.concatenate([absent, edges]), keys)) == -1).all()


def test_the_directory_decodes_only_the_pages_a_lookup_reaches() -> None:
    d, keys, _ = _directory(20 * PAGE_CELLS, 3)
    find(d, keys[[3, PAGE_CELLS * 5]])
    assert 1 <= d.decoded.sum() <= 2 and not d.decoded.all()
    # A damaged byte of a page not read yet fails its checksum when a lookup first reaches it.
    d, keys, _ = _directory(200 * PAGE_CELLS, 3)
    assert d.data.crcs.size > 2
    raw = d.data.array.copy()
    last = d.first_byte[-2]
    raw[last + 2] ^= 0x10
    d.data.array, d.data.raw = raw, raw
    assert find(d, keys[[3]]).tolist() == [3]
    with pytest.raises(MapFormatError, match="dir_data block"):
        find(d, keys[[-1]])


def test_records_and_neighbours_decode_to_what_was_packed() -> None:
    rng = np.random.default_rng(7)
    for n in (10, 1500, 6826, 10**6, 5 * 10**6, 2**32 - 1):
        nbytes, sub_bits, triple_bits = record_layout(n, 4)
        assert 4 <= sub_bits <= 8 and nbytes * 8 >= (n - 1).bit_length() + triple_bits + 4 * sub_bits
        anchor, triple = rng.integers(0, n, 500), rng.integers(0, 4, 500)
        sub = rng.integers(0, 1 << sub_bits, (500, 4))
        back = unpack_records(pack_records(anchor, triple, sub, nbytes, sub_bits, triple_bits), sub_bits, triple_bits)
        assert [np.array_equal(x, y) for x, y in zip(back, (anchor, triple, sub), strict=True)] == [True] * 3
    n = 3 * NB_BLOCK + 5
    table = np.clip(np.arange(n)[:, None] + rng.integers(-40, 40, (n, 4)), 0, n - 1)
    table[70, 1] = n - 1  # a far neighbour widens its block only
    data, lengths, widths = pack_neighbours(table, 0)
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype("<u8")
    nb = Neighbours(_section(starts, "nb_start"), _section(widths, "nb_width"),
                    _section(np.concatenate([data, np.zeros(PAD, np.uint8)]), "nb_data"), n, 4, "test.qidx")
    assert widths[1] > widths[0]
    objects = rng.permutation(n)
    assert np.array_equal(nb.rows(objects), table[objects])


def test_bound_candidates_keeps_every_one_of_the_k_nearest_within_the_radius() -> None:
    rng = np.random.default_rng(5)
    queries, per_query, k = 40, 300, 16
    cell = np.full(queries, 0.1)
    r = rng.uniform(0.02, 0.1, queries)
    which = np.repeat(np.arange(queries), per_query)
    # Each candidate in a cell next to its query's (sub: its position inside in 1/256ths), the query
    # anywhere within one cell of that cell's corner (rel, in 1/256ths).
    sub = rng.integers(0, SUB_CELLS, (which.size, 4)).astype(np.uint8)
    rel = np.repeat(rng.uniform(-SUB_CELLS, 2 * SUB_CELLS, (queries, 4)), per_query, axis=0).astype(np.float32)
    exact = (sub + rng.uniform(0, 1, sub.shape) - rel) * (cell[which] / SUB_CELLS)[:, None]
    dist = np.sqrt((exact**2).sum(axis=1))
    kept_which, kept = bound_candidates(which, np.arange(which.size), rel, sub, r, cell, k, SUB_CELLS)
    assert np.all(np.diff(kept_which) >= 0) and (which[kept] == kept_which).all()
    assert kept.size < which.size / 4  # the bounds do prune
    for q in range(queries):
        mine = np.flatnonzero(which == q)
        inside = mine[dist[mine] <= r[q]]
        nearest = inside[np.argsort(dist[inside])[:k]]
        assert set(nearest) <= set(kept[kept_which == q])


def test_take_rows_matches_fancy_indexing() -> None:
    a = np.arange(60, dtype=np.float32).reshape(15, 4)
    index = np.array([14, 0, 0, 7])
    assert np.array_equal(take_rows(a, index), a[index])
    assert np.array_equal(take_rows(a[:, :2], index), a[:, :2][index])  # not contiguous: numpy's own
    assert take_rows(a, np.zeros(0, np.int64)).shape == (0, 4)


def test_directory_pages_packed_in_groups_are_the_same_bytes(monkeypatch) -> None:
    from mapdb.match.index import packed

    rng = np.random.default_rng(11)
    combos, sides = np.array([3, 9]), np.array([0.1, 0.011])
    lk = np.sort(rng.choice(combos, 3000))
    cells = (rng.uniform(0, 1, (lk.size, 4)) * 20).astype(np.int64)
    keys = np.unique(cell_keys(lk, cells, BITS))
    counts = rng.integers(1, 30, keys.size)
    whole = directory_pages(keys, counts, combos, sides, BITS)
    monkeypatch.setattr(packed, "_PAGES_AT_ONCE", 3)
    grouped = directory_pages(keys, counts, combos, sides, BITS)
    assert whole[1].shape[0] > 10 and all(np.array_equal(a, b) for a, b in zip(whole, grouped, strict=True))
