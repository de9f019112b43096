"""The per-image path's shortcuts answer exactly as the steps they replace (issue 30): a tile lookup
skipped when the prior's disc holds none of its quads, an answer's lon/lat in one transform."""

from __future__ import annotations

import math
from itertools import combinations

import numpy as np
from quadrefs import anchored_quads

from mapdb._scipy import cKDTree
from mapdb.localize.lonlat import to_lonlat, to_lonlat_many
from mapdb.match.quads import POSITION_WEIGHT, QuadIndex
from mapdb.objects import Objects


def test_neighbour_quads_of_an_image_are_the_tree_s() -> None:
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 640, (30, 2))
    quads, anchor = anchored_quads(xy, 5)
    nn = cKDTree(xy).query(xy, k=6)[1][:, 1:]
    triples = np.array(list(combinations(range(5), 3)))
    expected = np.sort(np.concatenate([np.repeat(np.arange(30), len(triples))[:, None],
                                       nn[:, triples].reshape(-1, 3)], axis=1), axis=1)
    assert np.array_equal(quads, expected)
    assert np.array_equal(anchor, np.repeat(np.arange(30), len(triples)))


def _tile() -> QuadIndex:
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 1000, 300), rng.uniform(0, 1000, 300)
    objects = Objects.from_names(x, y, rng.choice(["building", "park"], 300).tolist(), crs="EPSG:32631")
    return QuadIndex(objects, 8, positions=True)


def test_a_tile_out_of_the_disc_is_not_queried_and_answers_the_same() -> None:
    tile = _tile()
    always = _tile()
    always._where = (-math.inf, -math.inf, math.inf, math.inf)  # never skipped: the tree decides every lookup
    rng = np.random.default_rng(4)
    pick = rng.integers(0, tile.n_quads, 60)
    invariants = tile.tree.data[pick, :4] + rng.normal(0, 0.002, (60, 4))
    labels = np.zeros((60, 4), np.int64)
    codes = np.round(tile.tree.data[pick, 4] / 100.0).astype(np.int64)  # label_keys: the four labels' digits
    base = max(len(tile.labels), 1)
    for j in range(4):
        labels[:, 3 - j] = codes % base
        codes //= base
    radius = np.full(60, 0.02)
    skipped = 0
    for centre, reach in [(500 + 500j, 300.0), (-400 - 400j, 450.0), (1600 + 500j, 550.0), (1300 + 1300j, 400.0),
                          (-50 + 500j, 60.0), (2500 + 2500j, 100.0)]:
        got = tile.lookup(invariants, labels, radius, 16, near=(centre, reach))
        want = always.lookup(invariants, labels, radius, 16, near=(centre, reach))
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        skipped += tile._out_of_reach(centre * POSITION_WEIGHT, reach * POSITION_WEIGHT)
    assert 0 < skipped < 6  # both kinds of lookup were tried
    assert len(tile.lookup(invariants, labels, radius, 16, near=(500 + 500j, 300.0))[0]) > 0


def test_lonlat_in_one_transform_is_point_by_point() -> None:
    rng = np.random.default_rng(5)
    x, y = (384000 + rng.uniform(0, 5000, 5)).tolist(), (4712000 + rng.uniform(0, 5000, 5)).tolist()
    assert to_lonlat_many("EPSG:32631", x, y) == [to_lonlat("EPSG:32631", u, v) for u, v in zip(x, y, strict=True)]
    assert to_lonlat_many("EPSG:32631", [x[0], 1e300], [y[0], math.inf])[1] == (None, None)
