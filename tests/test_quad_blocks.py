"""A block of a prior's tiles looked up as one (:class:`~mapdb.match.quads.QuadBlock`): the kernel searches the tiles'
trees together and must answer exactly what one tree over their quads concatenated (:meth:`QuadIndex.merged`)
answers: the same hits, in the same order, equal distances in the merged rows' order (tiles that repeat one
another tie exactly), with and without positions, near a place or not, empty and one-quad tiles."""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.match._kernel import quads_lookup
from mapdb.match.quad_block import MERGE_AFTER, QuadBlock
from mapdb.match.quads import LABEL_GAP, QuadIndex, lookup_parts
from mapdb.objects import Objects


def _town(seed: int, n: int, x0: float, size: float = 1000.0) -> Objects:
    rng = np.random.default_rng(seed)
    labels = rng.choice(["building", "park", "water"], n, p=[0.8, 0.15, 0.05]).tolist()
    return Objects.from_names(x0 + rng.uniform(0, size, n), rng.uniform(0, size, n), labels, crs="EPSG:32631")


def _lattice(x0: float) -> Objects:
    """A 10 x 10 lattice of buildings: hundreds of quads with the very same invariants."""
    i, j = np.meshgrid(np.arange(10), np.arange(10))
    return Objects.from_names(x0 + i.ravel() * 20.0, j.ravel() * 20.0, ["building"] * i.size, crs="EPSG:32631")


def _tiles(kind: str, positions: bool) -> list[QuadIndex]:
    if kind == "random":
        parts = [_town(s, 300, 1000.0 * s) for s in range(3)]
    elif kind == "lattices":  # the same lattice three times, and once shifted: ties within and across tiles
        parts = [_lattice(0.0), _lattice(0.0), _lattice(5000.0), _lattice(0.0)]
    else:  # one town, a tile too small for quads, one of exactly four points (one quad), the town again
        one = _town(7, 4, 0.0, 50.0)
        parts = [_town(8, 200, 0.0), _town(9, 3, 0.0), one, _town(8, 200, 0.0)]
    return [QuadIndex(p, 8, positions=positions) for p in parts]


def _queries(index: QuadIndex, m: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Invariants near ``m`` of the index's quads (some exactly on them), their labels and radii."""
    rng = np.random.default_rng(seed)
    assert index.tree is not None
    pick = rng.integers(0, index.n_quads, m)
    invariants = index.tree.data[pick, :4] + rng.normal(0, 0.01, (m, 4)) * (rng.random((m, 1)) < 0.7)
    codes = np.round(index.tree.data[pick, 4] / LABEL_GAP).astype(np.int64)
    base = max(len(index.labels), 1)
    labels = np.stack([codes // base**3 % base, codes // base**2 % base, codes // base % base, codes % base], 1)
    return invariants, labels, rng.uniform(0.0, 0.2, m)


@pytest.mark.parametrize("positions", [False, True])
@pytest.mark.parametrize("kind", ["random", "lattices", "edges"])
def test_a_block_answers_as_its_merged_index(kind: str, positions: bool) -> None:
    tiles = _tiles(kind, positions)
    merged, block = QuadIndex.merged(tiles), QuadBlock(tiles)
    assert block.n_quads == merged.n_quads and np.array_equal(block.quad_z, merged.quad_z)
    invariants, labels, radius = _queries(merged, 300, 1)
    nears = [(500 + 500j, 700.0), (5100 + 100j, 150.0), (1e6 + 0j, 10.0)] + ([None] if not positions else [])
    hits = 0
    for near in nears:
        for k in (1, 4, 16, 10**6):
            for r in (radius, np.full(len(radius), 1e9)):
                want = merged.lookup(invariants, labels, r, k, near)
                block.lookups = 0  # its tiles searched together every time (not yet merged: the next test)
                got = block.lookup(invariants, labels, r, k, near)
                assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
                hits += len(got[0])
    assert hits > 1000  # the lookups found something to compare
    # Per tile, the k nearest of each: not the block's (the block is not its tiles one after another).
    each = lookup_parts([(tile, nears[0]) for tile in tiles], invariants, labels, radius, 4)
    assert len(each[0]) > len(block.lookup(invariants, labels, radius, 4, nears[0])[0])


def test_a_block_looked_up_often_merges_its_tiles_and_answers_the_same() -> None:
    tiles = _tiles("lattices", True)
    block, merged = QuadBlock(tiles), QuadIndex.merged(tiles)
    invariants, labels, radius = _queries(merged, 50, 2)
    near = (100 + 100j, 300.0)
    want = merged.lookup(invariants, labels, radius, 16, near)
    for j in range(MERGE_AFTER + 2):
        got = block.lookup(invariants, labels, radius, 16, near)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert (block.merged_index is not None) == (j >= MERGE_AFTER)
    assert block.merged_index is not None and np.array_equal(block.merged_index.quad_z, merged.quad_z)


def test_an_empty_block_and_wrong_calls() -> None:
    empty = QuadBlock([QuadIndex(_town(1, 3, 0.0), positions=True)])
    assert empty.n_quads == 0 and empty.quad_z.shape == (0, 4)
    rows, z = empty.lookup(np.zeros((2, 4)), np.zeros((2, 4), np.int64), np.full(2, 0.1), 4, (0j, 10.0))
    assert rows.size == 0 and z.shape == (0, 4)
    with pytest.raises(ValueError, match="with and without positions"):
        QuadBlock([QuadIndex(_town(1, 50, 0.0)), QuadIndex(_town(2, 50, 0.0), positions=True)])
    plain, placed = QuadIndex(_town(1, 50, 0.0)), QuadIndex(_town(2, 50, 0.0), positions=True)
    assert plain.tree is not None and placed.tree is not None
    args = (np.zeros((1, 4)), np.zeros(1), np.full(1, 0.1), 4, 0.0, 0.0, 0.0, 0.1, False)
    with pytest.raises(ValueError, match="same columns"):
        quads_lookup((plain.tree.handle, placed.tree.handle), (plain.quad_z, placed.quad_z), *args, True)
    with pytest.raises(TypeError):
        quads_lookup((plain.tree.handle, "no tree"), (plain.quad_z, plain.quad_z), *args, True)
