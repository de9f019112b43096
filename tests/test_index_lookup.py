"""The stored index's lookup steps against brute force: the directory search and the candidates' bounds."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from mapdb.errors import MapFormatError
from mapdb.match.index.layout import BLOCK, FENCE, SUB_CELLS
from mapdb.match.index.lookup import Section, bound_candidates, find_cells, take_rows


def _section(array: np.ndarray) -> Section:
    raw = array.tobytes()
    crcs = np.array([zlib.crc32(raw[i : i + BLOCK]) for i in range(0, len(raw), BLOCK)], np.uint32)
    return Section("dir_key", array, crcs, "test.qidx")


@pytest.mark.parametrize("n_cells", [1, 7, FENCE, FENCE + 1, 3 * FENCE + 200])
def test_find_cells_finds_every_key_and_no_absent_one(n_cells: int) -> None:
    rng = np.random.default_rng(n_cells)
    # Even keys only, so that every odd key between them (and below and above all of them) is absent.
    keys = np.sort(rng.choice(np.arange(2, 40 * n_cells, 2, dtype=np.uint64), n_cells, replace=False))
    directory = _section(keys)
    fence = keys[::FENCE].copy()
    present = rng.permutation(keys)
    edges = np.array([0, 1, int(keys[-1]) + 1, np.iinfo(np.uint64).max], np.uint64)
    absent = np.concatenate([present[: min(50, n_cells)] + np.uint64(1), edges])
    assert find_cells(fence, directory, n_cells, present).tolist() == np.searchsorted(keys, present).tolist()
    assert (find_cells(fence, directory, n_cells, absent) == -1).all()


def test_find_cells_reads_only_checked_pages() -> None:
    keys = np.arange(0, 6 * FENCE, dtype=np.uint64) * np.uint64(3)
    corrupt = keys.copy()
    corrupt[4 * FENCE + 5] += np.uint64(1)  # after its checksum was taken: page 4 is damaged
    directory = _section(keys)
    directory.array = corrupt
    directory.raw = corrupt.view(np.uint8)
    fence = keys[::FENCE].copy()
    wanted = keys[[3, FENCE + 2, 3 * FENCE + 100]]
    assert find_cells(fence, directory, keys.size, wanted).tolist() == [3, FENCE + 2, 3 * FENCE + 100]
    with pytest.raises(MapFormatError, match="dir_key block"):
        find_cells(fence, directory, keys.size, keys[[4 * FENCE + 9]])


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
    kept_which, kept = bound_candidates(which, np.arange(which.size), rel, sub, r, cell, k)
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
