"""The kernel's quad lookups (``_kernel_quads.c``) against the cKDTree lookup they replace, kept here verbatim as
the reference: the same hits in the same order on random and edge inputs; ties ordered by quad row; wrong calls
raise TypeError / ValueError."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from mapdb._scipy import quick_tree
from mapdb.match import _kernel
from mapdb.match.quads import LABEL_GAP, POSITION_WEIGHT, QuadIndex, label_keys, lookup_parts, near_only
from mapdb.objects import Objects


def ref_lookup(self, invariants, labels, radius, k, near=None):
    """QuadIndex.lookup as it was (c0735fc), on a cKDTree over the index's tree points."""
    tree = quick_tree(self.tree.data)
    if not len(invariants):
        return np.zeros(0, np.int64), np.zeros((0, 4), np.complex128)
    bound = float(radius.max())
    place, reach = 0j, 0.0  # the prior's disc in tree units
    if self.positions:
        if near is None:
            raise ValueError("an index with positions is looked up near a place")
        place, reach = complex(near[0]) * POSITION_WEIGHT, POSITION_WEIGHT * float(near[1])
        if self._out_of_reach(place, reach):
            return np.zeros(0, np.int64), np.zeros((0, 4), np.complex128)
        bound += reach
    k = min(k, self.n_quads)
    m = len(invariants)
    query = np.empty((m, 5 if not self.positions else 7))
    query[:, :4] = invariants
    np.multiply(label_keys(labels, len(self.labels)), LABEL_GAP, out=query[:, 4])
    if self.positions:
        query[:, 5] = place.real
        query[:, 6] = place.imag
    dist, hit = tree.query(query, k=k, distance_upper_bound=bound)
    dist, hit = dist.reshape(len(invariants), k), hit.reshape(len(invariants), k)
    if not self.positions:
        rows, cols = np.nonzero(dist <= radius[:, None])
        return near_only(rows, self.quad_z[hit[rows, cols]], near)
    rows, cols = np.nonzero(dist <= bound)
    hit = hit[rows, cols]
    where = tree.data[hit, 5:7]
    off2 = (where[:, 0] - place.real) ** 2 + (where[:, 1] - place.imag) ** 2
    keep = (dist[rows, cols] ** 2 - off2 <= radius[rows] ** 2) & (off2 <= reach**2)
    return rows[keep], self.quad_z[hit[keep]]


def _town(seed: int, n: int = 400, size: float = 1500.0, x0: float = 0.0) -> Objects:
    rng = np.random.default_rng(seed)
    labels = rng.choice(["building", "park", "water", "tree"], n, p=[0.7, 0.15, 0.1, 0.05]).tolist()
    return Objects.from_names(x0 + rng.uniform(0, size, n), rng.uniform(0, size, n), labels, crs="EPSG:32631")


def _queries(index: QuadIndex, m: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Invariants near ``m`` of the index's quads and their labels (decoded from the label key)."""
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, index.n_quads, m)
    invariants = index.tree.data[pick, :4] + rng.normal(0, noise, (m, 4))
    codes = np.round(index.tree.data[pick, 4] / LABEL_GAP).astype(np.int64)
    labels = np.zeros((m, 4), np.int64)
    base = max(len(index.labels), 1)
    for j in range(4):
        labels[:, 3 - j] = codes % base
        codes //= base
    return invariants, labels


def _same(got, want) -> None:
    assert got[0].dtype == np.int64 and got[1].dtype == np.complex128 and got[1].shape[1:] == (4,)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


@pytest.mark.parametrize("positions", [False, True])
@pytest.mark.parametrize("k", [1, 4, 16])
def test_lookups_are_the_ckdtree_s_on_random_towns(positions: bool, k: int) -> None:
    index = QuadIndex(_town(1), 8, positions=positions)
    invariants, labels = _queries(index, 200, 0.01, 2)
    rng = np.random.default_rng(3)
    hits = 0
    for radius in (np.full(200, 0.02), rng.uniform(0.001, 0.3, 200), np.full(200, 1e-12)):
        for near in ((700 + 800j, 500.0), (100 + 100j, 150.0), (3000 + 3000j, 100.0)):
            got = index.lookup(invariants, labels, radius, k, near=near if positions or near[1] < 200 else None)
            want = ref_lookup(index, invariants, labels, radius, k, near=near if positions or near[1] < 200 else None)
            _same(got, want)
            hits += len(got[0])
    assert hits > 50  # the lookups found something to compare


def test_a_prior_s_tiles_in_one_call_are_their_lookups_one_after_another() -> None:
    objects = _town(4, 900, 3000.0)
    tiles = [QuadIndex(objects, 8, positions=True, anchors=(objects.x >= x0) & (objects.x < x0 + 1000))
             for x0 in (0.0, 1000.0, 2000.0)]
    invariants, labels = _queries(tiles[1], 150, 0.005, 5)
    radius = np.random.default_rng(6).uniform(0.005, 0.1, 150)
    near = (1500 + 1500j, 900.0)
    got = lookup_parts([(tile, near) for tile in tiles], invariants, labels, radius, 16)
    each = [ref_lookup(tile, invariants, labels, radius, 16, near) for tile in tiles]
    _same(got, (np.concatenate([e[0] for e in each]), np.concatenate([e[1] for e in each])))
    assert len({len(e[0]) > 0 for e in each}) >= 1 and len(got[0]) > 0
    merged = QuadIndex.merged(tiles)  # a block of tiles merged: one tree, the same hits as its reference
    _same(merged.lookup(invariants, labels, radius, 16, near), ref_lookup(merged, invariants, labels, radius, 16, near))


def test_ties_come_in_quad_order_and_the_k_nearest_are_the_same_distances() -> None:
    # A square lattice: many quads with the very same invariants, so distances tie exactly.
    g = np.arange(12, dtype=float) * 10.0
    x, y = np.meshgrid(g, g)
    objects = Objects.from_names(x.ravel(), y.ravel(), ["building"] * x.size, crs="EPSG:32631")
    index = QuadIndex(objects, 8)
    invariants, labels = _queries(index, 40, 0.0, 7)
    radius = np.full(40, 0.05)
    for k in (3, 16, 200):
        got = index.lookup(invariants, labels, radius, k)
        want = ref_lookup(index, invariants, labels, radius, k)
        assert np.array_equal(got[0], want[0])  # as many hits a query
        # The same distances in the same order: only which of equally distant quads (and their order) may differ.
        data = {tuple(z): d for z, d in zip(map(tuple, index.quad_z), index.tree.data, strict=True)}
        key = label_keys(labels, 1) * LABEL_GAP
        dist, dist_ref = ([np.sqrt(((data[tuple(z)] - np.r_[invariants[r], key[r]]) ** 2).sum())
                           for r, z in zip(*side, strict=True)] for side in (got, want))
        assert np.array_equal(dist, dist_ref)
        # Among equal distances, quad rows ascending: the hits of each query are its first rows of that distance.
        row_of = {tuple(z): i for i, z in enumerate(map(tuple, index.quad_z))}
        rows = np.array([row_of[tuple(z)] for z in got[1]])
        same_query_and_distance = (got[0][1:] == got[0][:-1]) & (np.diff(dist) == 0)
        assert np.all(np.diff(rows)[same_query_and_distance] > 0)
    assert len(got[0]) > 40


def test_edge_inputs_answer_without_crashing() -> None:
    index = QuadIndex(_town(8, 60), 8, positions=True)
    invariants, labels = _queries(index, 5, 0.0, 9)
    near = (750 + 750j, 2000.0)
    for inv, lab, rad in [
        (invariants[:0], labels[:0], np.zeros(0)),  # no query
        (invariants[:1], labels[:1], np.full(1, 0.01)),  # one row
        (invariants, labels, np.full(5, np.inf)),  # an infinite radius: every quad within reach, k of them
        (invariants, labels, np.zeros(5)),  # a zero radius: only exact matches
    ]:
        with np.errstate(invalid="ignore"):
            _same(index.lookup(inv, lab, rad, 16, near), ref_lookup(index, inv, lab, rad, 16, near))
    for bad in (np.nan, np.inf):  # the cKDTree refused non-finite queries (ValueError); the kernel finds no hit
        with pytest.raises(ValueError):
            ref_lookup(index, np.full((5, 4), bad), labels, np.full(5, 0.01), 16, near)
        assert len(index.lookup(np.full((5, 4), bad), labels, np.full(5, 0.01), 16, near)[0]) == 0
    plain = QuadIndex(_town(8, 60), 8)  # without positions a tiny radius finds the quad itself (distance 0)
    assert len(plain.lookup(*_queries(plain, 5, 0.0, 9), np.full(5, 1e-12), 16)[0]) >= 5
    assert len(index.lookup(invariants, labels, np.full(5, 1e9), 10**6, near)[0]) == 5 * index.n_quads
    with pytest.raises(ValueError, match="near a place"):
        index.lookup(invariants, labels, np.full(5, 0.01), 16)


def test_an_index_pickles_and_looks_up_the_same() -> None:
    index = QuadIndex(_town(10, 200), 8, positions=True)
    again = pickle.loads(pickle.dumps(index))
    invariants, labels = _queries(index, 50, 0.01, 11)
    radius = np.full(50, 0.05)
    _same(again.lookup(invariants, labels, radius, 16, (700 + 700j, 900.0)),
          index.lookup(invariants, labels, radius, 16, (700 + 700j, 900.0)))


def test_wrong_calls_raise_type_or_value_errors() -> None:
    good = np.zeros((10, 5))
    good[:, :4] = np.random.default_rng(12).uniform(0, 1, (10, 4))
    tree = _kernel.quads_build(good)
    z = np.zeros((10, 4), np.complex128)
    inv, key, rad = np.zeros((2, 4)), np.zeros(2), np.full(2, 0.1)
    for bad, error in [
        (good.astype(np.float32), TypeError), (good[:, :4].copy(), ValueError), (np.zeros((0, 5)), ValueError),
        (np.full((3, 5), np.nan), ValueError), (np.zeros(5), ValueError), ([[0.0] * 5], TypeError),
        (np.asfortranarray(np.zeros((4, 7))), ValueError),
    ]:
        with pytest.raises(error):
            _kernel.quads_build(bad)
    for args, error in [
        (((good,), (z,), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1), TypeError),  # not a tree
        (((tree,), (), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1), ValueError),  # no map points for it
        (((tree,), (z[:5],), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1), ValueError),  # map points of another size
        (((tree,), (z.real.copy(),), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1), TypeError),
        (((tree,), (z,), inv[:, :3].copy(), key, rad, 16, 0.0, 0.0, 0.0, 0.1), ValueError),
        (((tree,), (z,), inv, key[:1], rad, 16, 0.0, 0.0, 0.0, 0.1), ValueError),
        (((tree,), (z,), inv, key, rad, 0, 0.0, 0.0, 0.0, 0.1), ValueError),
        (([tree], [z], inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1), TypeError),
    ]:
        with pytest.raises(error):
            _kernel.quads_lookup(*args)
    rows, found = _kernel.quads_lookup((tree,), (z,), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1)
    assert isinstance(rows, bytearray) and isinstance(found, bytearray) and len(rows) * 8 == len(found)
