"""The kernel's quad lookups (``_kernel_quads.c``) against the cKDTree lookup they replace, kept here verbatim as
the reference: the same hits in the same order on random and edge inputs; ties ordered by quad row; wrong calls
raise TypeError / ValueError."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from quadrefs import anchored_quads, first_rows

from mapdb._scipy import quick_tree
from mapdb.match import _kernel
from mapdb.match.hypotheses import FRAME_TIE_SIGMAS, PRIOR_SLACK, _quad_keys, allowed_poses, anchor_batches
from mapdb.match.options import FastOptions
from mapdb.match.quads import (
    LABEL_GAP,
    OTHERS,
    PAIRS,
    POSITION_WEIGHT,
    QuadIndex,
    label_keys,
    lookup_parts,
    near_only,
)
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


# The numpy code the kernel's image side replaced (c0735fc's hypotheses.py and quads.quad_frames), verbatim.

def ref_quad_frames(zq: np.ndarray, pair: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertex order ``(A, B, C, D)`` per quad for the chosen pair index, and ``t_C``, ``t_D``."""
    rows = np.arange(len(zq))
    order = np.concatenate([PAIRS[pair], OTHERS[pair]], axis=1)
    a, b = zq[rows, order[:, 0]], zq[rows, order[:, 1]]
    t = (zq[rows[:, None], order[:, 2:]] - a[:, None]) / (b - a)[:, None]
    return order, t


def ref_quad_keys(zq: np.ndarray, opts: FastOptions, sigma_px: float | np.ndarray) -> tuple[np.ndarray, ...] | None:
    """Every frame and ordering of the quads ``zq`` (m, 4) worth looking up: quad rows, orderings (k, 4),
    invariants (k, 4) and lookup radii (k,); None when there is none.

    ``sigma_px`` is one pixel error for every point, or one per point ``(m, 4)`` (a cut blob's is wider).
    Rows come frame by frame (the longest pair's, then the second longest's), each ordering in turn
    (A, B swapped or not, C, D swapped or not), in quad order within: all of it in a few array operations,
    since an image has a few hundred quads and per-block calls would cost more than the arithmetic.
    """
    m = len(zq)
    # One pixel error for every point (the usual round): scalars where arrays of one value would do, the same
    # arithmetic element by element.
    one = float(sigma_px) if np.ndim(sigma_px) == 0 else None
    sigma = np.broadcast_to(np.asarray(sigma_px, np.float64), zq.shape)
    d = np.abs(zq[:, PAIRS[:, 0]] - zq[:, PAIRS[:, 1]])
    by_length = np.argsort(-d, axis=1)
    length = d[np.arange(m)[:, None], by_length[:, :2]]  # (m, 2): longest, second longest
    # The longest pair decides the frame; when the second longest is within noise of it, a noisy image can
    # pick either, so both frames are looked up.
    tie = FRAME_TIE_SIGMAS * math.sqrt(2.0) * (sigma.max(axis=1) if one is None else one)
    use = np.column_stack([np.ones(m, bool), length[:, 0] - length[:, 1] < tie]) & (length > 0.0)
    rank, sel = np.nonzero(use.T)  # frame-major: every quad's first frame, then the ties' second
    if not sel.size:
        return None
    order0, t0 = ref_quad_frames(zq[sel], by_length[sel, rank])
    # Predicted standard error of the four invariants (see the module docs of decision): per point P of C, D
    # sigma_P^2 + sigma_A^2 |1 - t|^2 + sigma_B^2 |t|^2, over |AB|^2, per axis.
    s2 = sigma[sel[:, None], order0] ** 2 if one is None else np.full((1, 4), one * one)
    spread = (s2[:, 2:] + s2[:, :1] * np.abs(1.0 - t0) ** 2 + s2[:, 1:2] * np.abs(t0) ** 2).sum(axis=1)
    radius = opts.tolerance_factor * np.sqrt(spread) / length[sel, rank]
    order, t, ok = ref_orderings(order0, t0, radius, opts.max_invariant_radius)  # (4, k, ...)
    # Output order: frame, then ordering, then quad.
    block = int(np.searchsorted(rank, 1))
    which, row = np.nonzero(ok[:, :block])
    which2, row2 = np.nonzero(ok[:, block:])
    which = np.concatenate([which, which2])
    row = np.concatenate([row, row2 + block])
    if not row.size:
        return None
    inv = t[which, row].view(np.float64).reshape(-1, 4)  # Re t_C, Im t_C, Re t_D, Im t_D
    return sel[row], order[which, row], inv, radius[row]


def ref_orderings(order0: np.ndarray, t0: np.ndarray, radius: np.ndarray, max_radius: float):
    """The quads' four orderings (A, B swapped or not, C, D swapped or not) stacked: orders ``(4, k, 4)``,
    invariants ``(4, k, 2)`` and ``ok`` ``(4, k)``, marking the quads for which that ordering could be the
    canonical one within the lookup radius (and whose radius is at most ``max_radius``)."""
    swapped_ab = np.concatenate([order0[:, 1::-1], order0[:, 2:]], axis=1)
    order = np.stack([order0, order0[:, [0, 1, 3, 2]], swapped_ab, swapped_ab[:, [0, 1, 3, 2]]])
    t_ab = 1.0 - t0
    t = np.stack([t0, t0[:, ::-1], t_ab, t_ab[:, ::-1]])
    slack = radius * math.sqrt(2.0)
    ok = (t.real.sum(axis=2) - 1.0 <= slack) & (t[:, :, 0].real - t[:, :, 1].real <= slack)
    ok &= radius <= max_radius
    return order, t, ok


def ref_anchor_batches(z: np.ndarray, opts: FastOptions, anchorable: np.ndarray | None = None) -> list[np.ndarray]:
    """Image quads ``(m, 4)`` in rounds: anchors nearest the image centre first, each quad in its earliest
    round, at most ``opts.max_batches`` rounds.

    ``anchorable`` (bool, ``(n,)``) limits quads to those objects: a region cut by the image border has its
    centroid pulled inward, by up to half the hidden part, so a quad holding one predicts the others badly
    and its invariants miss the map's.  Such objects still count as evidence in verification.
    """
    n = z.size
    members = np.arange(n) if anchorable is None else np.flatnonzero(anchorable)
    img_quads, anchor = anchored_quads(np.column_stack([z.real, z.imag])[members], opts.image_neighbours)
    if not len(img_quads):
        return []
    img_quads, anchor = members[img_quads], members[anchor]
    rank = np.empty(n, np.int64)
    rank[np.argsort(np.abs(z), kind="stable")] = np.arange(n)
    batch_of = rank[anchor] // opts.anchors_per_batch
    by_batch = np.argsort(batch_of, kind="stable")
    in_order = img_quads[by_batch]  # batch by batch, each in quad order
    first = np.sort(first_rows(in_order, n))
    n_batches = min(int(batch_of[by_batch[-1]]) + 1, opts.max_batches)
    # Cut where each batch ends: a few calls, not a few per batch.
    ends = np.searchsorted(batch_of[by_batch[first]], np.arange(1, n_batches + 1))
    return np.split(in_order[first], ends)[:n_batches]


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
    # Looked up near a place, equal distances come nearest it first: the k kept are the copies near_only keeps.
    place = complex(objects.x.mean(), objects.y.mean())
    rows, found = index.lookup(invariants, labels, radius, 8, near=(place, 1e9))
    dist = np.array([np.sqrt(((data[tuple(z)] - np.r_[invariants[r], key[r]]) ** 2).sum())
                     for r, z in zip(rows, found, strict=True)])
    off = np.abs(found.mean(axis=1) - place)
    tied = (rows[1:] == rows[:-1]) & (dist[1:] == dist[:-1])
    assert tied.sum() > 50 and np.all(np.diff(off)[tied] >= -1e-9)
    assert len(index.lookup(invariants, labels, radius, 8, near=(place, 30.0))[0]) > 0


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
        (((good,), (z,), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1, False), TypeError),  # not a tree
        (((tree,), (), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1, False), ValueError),  # no map points for it
        (((tree,), (z[:5],), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1, False), ValueError),  # map points of another size
        (((tree,), (z.real.copy(),), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1, False), TypeError),
        (((tree,), (z,), inv[:, :3].copy(), key, rad, 16, 0.0, 0.0, 0.0, 0.1, False), ValueError),
        (((tree,), (z,), inv, key[:1], rad, 16, 0.0, 0.0, 0.0, 0.1, False), ValueError),
        (((tree,), (z,), inv, key, rad, 0, 0.0, 0.0, 0.0, 0.1, False), ValueError),
        (([tree], [z], inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1, False), TypeError),
    ]:
        with pytest.raises(error):
            _kernel.quads_lookup(*args)
    rows, found = _kernel.quads_lookup((tree,), (z,), inv, key, rad, 16, 0.0, 0.0, 0.0, 0.1, False)
    assert isinstance(rows, bytearray) and isinstance(found, bytearray) and len(rows) * 8 == len(found)


def _same_keys(got, want) -> None:
    assert (got is None) == (want is None)
    if got is not None:
        assert len(got) == len(want) == 4
        for x, y in zip(got, want, strict=True):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)


def test_quad_keys_are_numpy_s_on_random_and_edge_quads() -> None:
    rng = np.random.default_rng(20)
    opts = FastOptions()
    found = 0
    for trial in range(200):
        m = int(rng.integers(1, 50))
        zq = rng.uniform(0, 640, (m, 4)) + 1j * rng.uniform(0, 480, (m, 4))
        if trial % 4 == 1:
            zq[: m // 2, 1] = zq[: m // 2, 0]  # two points on one spot
        if trial % 4 == 2:
            zq[:, :] = zq[:, :1]  # every quad on one spot: no frame
        sigma = rng.uniform(0.5, 12.0, (m, 4)) if trial % 3 == 0 else float(rng.uniform(0.2, 20.0))
        got, want = _quad_keys(zq, opts, sigma), ref_quad_keys(zq, opts, sigma)
        _same_keys(got, want)
        found += 0 if got is None else len(got[0])
    assert found > 1000
    _same_keys(_quad_keys(np.zeros((0, 4), complex), opts, 1.0), ref_quad_keys(np.zeros((0, 4), complex), opts, 1.0))
    zq = rng.uniform(0, 640, (5, 4)) + 1j * rng.uniform(0, 480, (5, 4))
    for sigma in (np.inf, np.nan, 0.0):  # no radius, or none that is finite: what numpy made of them
        with np.errstate(invalid="ignore"):
            _same_keys(_quad_keys(zq, opts, sigma), ref_quad_keys(zq, opts, sigma))
    assert FRAME_TIE_SIGMAS > 0 and math.isfinite(FRAME_TIE_SIGMAS)


def test_quad_keys_rank_equal_lengths_in_pair_order() -> None:
    # A square of integer pixels: its two diagonals (pairs 0-3 and 1-2) and its sides tie exactly.  numpy's default
    # argsort leaves the order of ties to the machine (AVX-512 sorts differ from the stable order); the kernel takes
    # pair order, numpy's stable sort's.
    zq = np.array([[0, 100, 100j, 100 + 100j]], complex)
    got = _quad_keys(zq, FastOptions(), 1.0)
    assert got is not None
    d = np.abs(zq[:, PAIRS[:, 0]] - zq[:, PAIRS[:, 1]])
    by_length = np.argsort(-d, axis=1, kind="stable")[0]
    assert by_length[:2].tolist() == [2, 3]  # the diagonals 0-3 and 1-2, in pair order
    assert sorted(got[1][0, :2].tolist()) == sorted(PAIRS[2].tolist())  # the first frame: the first diagonal
    assert sorted(OTHERS[2].tolist()) == sorted(got[1][0, 2:].tolist())
    frames = {tuple(sorted(order[:2].tolist())) for order in got[1]}
    assert frames == {(0, 3), (1, 2)}  # both diagonals' frames looked up (tied within noise)
    assert got[1][-1, :2].tolist() in ([1, 2], [2, 1])  # the second diagonal's last


def test_anchor_batches_are_numpy_s() -> None:
    rng = np.random.default_rng(21)
    total = 0
    for trial in range(300):
        n = int(rng.integers(0, 60))
        z = rng.uniform(-320, 320, n) + 1j * rng.uniform(-240, 240, n)
        opts = FastOptions(image_neighbours=int(rng.integers(3, 8)), anchors_per_batch=int(rng.integers(1, 8)),
                           max_batches=int(rng.integers(0, 10)))
        anchorable = rng.uniform(size=n) < 0.8 if trial % 2 else None
        got, want = anchor_batches(z, opts, anchorable), ref_anchor_batches(z, opts, anchorable)
        assert len(got) == len(want)
        for x, y in zip(got, want, strict=True):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)
        total += sum(len(x) for x in got)
    assert total > 10_000


def test_anchor_batches_on_a_grid_of_ties_are_sorted_distinct_quads_of_near_objects() -> None:
    # Integer pixels in a lattice: neighbours at equal distances, taken in object order (the tree's order among
    # them is its own); the quads are still each anchor's with three of its nearest, sorted, each once.
    g = np.arange(6) * 50.0 - 125.0
    z = (g[:, None] + 1j * g[None, :]).ravel()
    batches = anchor_batches(z, FastOptions())
    quads = np.concatenate(batches)
    assert np.all(np.diff(quads, axis=1) > 0)
    assert len(np.unique(quads, axis=0)) == len(quads)
    assert np.max(np.abs(z[quads] - z[quads].mean(axis=1, keepdims=True))) <= 2 * 50.0 * math.sqrt(2)
    assert [b.tolist() for b in anchor_batches(z, FastOptions())] == [b.tolist() for b in batches]  # deterministic


def test_wrong_image_side_calls_raise_type_or_value_errors() -> None:
    zq = np.zeros((3, 4), complex)
    for args, error in [
        ((zq.real.copy(), None, 1.0, 4.2, 2.0, 0.3), TypeError),
        ((zq[:, :3].copy(), None, 1.0, 4.2, 2.0, 0.3), ValueError),
        ((zq, np.zeros((2, 4)), 1.0, 4.2, 2.0, 0.3), ValueError),
        ((zq, np.zeros((3, 4), np.float32), 1.0, 4.2, 2.0, 0.3), TypeError),
    ]:
        with pytest.raises(error):
            _kernel.quads_keys(*args)
    z = np.arange(6) * (1 + 1j)
    for args, error in [
        ((z.real.copy(), np.arange(6), 5, 6, 8), TypeError),
        ((z, np.arange(6, dtype=np.int32), 5, 6, 8), TypeError),
        ((z, np.array([0, 7]), 5, 6, 8), ValueError),  # not an object
        ((z, np.array([3, 1, 2]), 5, 6, 8), ValueError),  # not ascending
        ((z, np.arange(6), 5, 0, 8), ValueError),
        ((z, np.arange(6), 65, 6, 8), ValueError),
    ]:
        with pytest.raises(error):
            _kernel.quads_batches(*args)


def test_neighbour_quads_of_a_map_stay_the_tree_s() -> None:
    # The map side keeps its tree (tens of thousands of points): its quads, the image side's rule for a few dozen.
    rng = np.random.default_rng(22)
    z = rng.uniform(0, 640, 40) + 1j * rng.uniform(0, 480, 40)
    quads, anchor = anchored_quads(np.column_stack([z.real, z.imag]), 5)
    in_order = quads[np.argsort(anchor // 100, kind="stable")]
    kept = np.concatenate(anchor_batches(z, FastOptions(anchors_per_batch=100, max_batches=1)))
    assert np.array_equal(kept, in_order[np.sort(first_rows(in_order, 40))])


def ref_allowed_poses(a, b, prior, scale_range):
    """hypotheses.allowed_poses as it was (c0735fc), verbatim."""
    ok = np.isfinite(a) & (np.abs(a) > 0)
    if prior is not None:
        ok &= np.abs(b - complex(prior[0], prior[1])) <= PRIOR_SLACK * prior[2]
    if scale_range is not None:
        ok &= (np.abs(a) >= scale_range[0]) & (np.abs(a) <= scale_range[1])
    return ok


def test_allowed_poses_are_numpy_s() -> None:
    rng = np.random.default_rng(23)
    a = rng.normal(0, 1, 400) + 1j * rng.normal(0, 1, 400)
    b = rng.normal(1000, 300, 400) + 1j * rng.normal(5000, 300, 400)
    a[:8] = [0, np.nan, np.inf, complex(np.nan, 1), complex(1, np.inf), 1e-300, 0.5, 2.0]
    b[8:12] = [np.nan, np.inf, 1000 + 5000j, complex(1000 + 330, 5000)]
    kinds = 0
    for prior in (None, (1000.0, 5000.0, 300.0), (np.float64(1100.0), 4900.0, 0.0)):
        for scale_range in (None, (0.5, 2.0), (1.0, 1.0)):
            got = allowed_poses(a, b, prior, scale_range)
            assert got.dtype == bool and np.array_equal(got, ref_allowed_poses(a, b, prior, scale_range))
            kinds += int(got.any()) + int((~got).any())
    assert kinds >= 12  # both answers met in most cases
    assert allowed_poses(a[:0], b[:0], (0.0, 0.0, 1.0), (0.5, 2.0)).shape == (0,)
