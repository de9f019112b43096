"""The quad index's faster paths give the numbers of the plain ones (mapdb.match.quads): canonical frames computed
column by column, a tile's index built from flat gathers, a prior's tiles looked up with one shared query array."""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.match.quads import (
    LABEL_GAP,
    OTHERS,
    PAIRS,
    POSITION_WEIGHT,
    QuadIndex,
    canonical_quads,
    label_keys,
    neighbour_quads,
)
from mapdb.objects import Objects

LABELS = ("building", "road_intersection", "park")


def _reference_canonical(zq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The canonical order, invariants and frame length as first written (fancy indexing throughout)."""
    d = np.abs(zq[:, PAIRS[:, 0]] - zq[:, PAIRS[:, 1]])
    pair = np.argmax(d, axis=1)
    rows = np.arange(len(zq))
    order = np.concatenate([PAIRS[pair], OTHERS[pair]], axis=1)
    a, b = zq[rows, order[:, 0]], zq[rows, order[:, 1]]
    t = (zq[rows[:, None], order[:, 2:]] - a[:, None]) / (b - a)[:, None]
    swap_ab = t.real.sum(axis=1) > 1.0
    order[swap_ab, :2] = order[swap_ab, 1::-1]
    t[swap_ab] = 1.0 - t[swap_ab]
    swap_cd = t[:, 0].real > t[:, 1].real
    order[swap_cd, 2:] = order[swap_cd, :1:-1]
    t[swap_cd] = t[swap_cd, ::-1]
    return order, np.column_stack([t[:, 0].real, t[:, 0].imag, t[:, 1].real, t[:, 1].imag]), d[rows, pair]


def _town(seed: int, n: int = 400) -> Objects:
    rng = np.random.default_rng(seed)
    # Map coordinates as the map holds them (UTM, 0.1 m steps): ties of distances and whole lattices included.
    xy = np.round(rng.uniform(0, 1300, (n, 2)), 1)
    xy[:49] = np.stack(np.meshgrid(np.arange(7) * 20.0, np.arange(7) * 20.0), axis=-1).reshape(-1, 2) + 300.0
    xy[49:53] = xy[60]  # four objects on one spot (duplicates in the sources)
    return Objects(390_000 + xy[:, 0], 4_700_000 + xy[:, 1], rng.integers(0, 3, n), np.full(n, 50.0), LABELS,
                   "EPSG:32631")


def test_canonical_frames_are_the_plain_computation() -> None:
    rng = np.random.default_rng(8)
    zq = np.round(rng.normal(size=(3000, 4)) * 10 + 1j * rng.normal(size=(3000, 4)) * 10) / 10 + 4.7e6 + 3.9e5j
    zq[:20] = zq[:20, :1]  # four objects on one spot: no frame (NaN invariants), as before
    zq[20:40] = np.array([0, 2, 2j, 2 + 2j]) + zq[20:40, :1]  # squares: every frame length tied
    with np.errstate(invalid="ignore", divide="ignore"):
        for quads in (zq, zq - zq[:, :1], zq[:0]):
            for mine, plain in zip(canonical_quads(quads), _reference_canonical(quads), strict=True):
                assert mine.dtype == plain.dtype and mine.shape == plain.shape
                assert np.array_equal(mine, plain, equal_nan=True)


@pytest.mark.parametrize("positions", [False, True])
def test_a_tiles_index_holds_the_plain_points(positions: bool) -> None:
    town = _town(4)
    anchors = town.x < 390_650.0
    index = QuadIndex(town, 8, anchors=anchors, positions=positions)
    assert index.tree is not None and index.n_quads > 100
    # The index as first written: quads through z[quads] again at every step, rows reordered by take_along_axis.
    z = town.x + 1j * town.y
    quads = neighbour_quads(np.column_stack([town.x, town.y]), 8, anchors=anchors)
    quads = quads[np.abs(z[quads] - z[quads[:, :1]]).max(axis=1) > 0.0]
    order, inv, _ = _reference_canonical(z[quads])
    quads = np.take_along_axis(quads, order, axis=1)
    columns = [inv, label_keys(town.label[quads], len(LABELS)) * LABEL_GAP]
    if positions:
        centroid = z[quads].mean(axis=1)
        columns += [POSITION_WEIGHT * centroid.real, POSITION_WEIGHT * centroid.imag]
    assert np.array_equal(index.quad_z, z[quads])
    assert np.array_equal(index.tree.data, np.column_stack(columns))
    # Every quad holds an anchored object, and some objects only join other anchors' quads.
    assert np.isin(index.quad_z, z[anchors]).any(axis=1).all() and np.isin(z[~anchors], index.quad_z).any()


def test_tiles_looked_up_with_one_query_array_answer_as_with_their_own() -> None:
    tiles = [QuadIndex(_town(seed), 8, positions=True) for seed in (5, 6)]
    rng = np.random.default_rng(9)
    probe = tiles[1].quad_z[rng.choice(tiles[1].n_quads, 60, replace=False)]
    order, inv, _ = canonical_quads(probe)
    z = _town(6).x + 1j * _town(6).y
    labels = _town(6).label[np.abs(probe[:, :, None] - z[None, None, :]).argmin(axis=2)]
    labels = np.take_along_axis(labels, order, axis=1)
    radius = np.full(len(inv), 0.02)
    near = (complex(390_650, 4_700_650), 900.0)
    shared = [tile.lookup(inv, labels, radius, 16, near=near) for tile in tiles]  # one array for both tiles
    for tile, (rows, quad_z) in zip(tiles, shared, strict=True):
        fresh_rows, fresh_z = tile.lookup(inv.copy(), labels.copy(), radius, 16, near=near)
        assert np.array_equal(rows, fresh_rows) and np.array_equal(quad_z, fresh_z)
    # The probed tile finds its own quads; a lookup near another place finds none of them.
    assert len(shared[1][0]) >= 60
    far = tiles[1].lookup(inv, labels, radius, 16, near=(complex(0.0, 0.0), 900.0))
    assert not len(far[0])
