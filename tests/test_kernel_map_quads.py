"""A map tile's quad index in the kernel (``_kernel_map_quads.c``) against the numpy code it replaced, kept here
verbatim as the reference (quads.py at 2e39d85): the same quads in the same order, the same invariants, tree points
and complex points bit for bit, on random and edge inputs (duplicate points, collinear quads, ties in pair lengths,
one quad, empty); wrong calls raise ValueError."""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest
from quadrefs import SORT4, first_rows

from mapdb._scipy import quick_tree
from mapdb.mapfile.reader import open_map
from mapdb.match import _kernel
from mapdb.match.nearest import nearest_others
from mapdb.match.quads import (
    _PACKABLE,
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

_ORDERS = np.concatenate([PAIRS, OTHERS], axis=1)


def ref_neighbour_quads(xy, neighbours, *, anchors=None):
    """neighbour_quads as it was (its quads without the anchors)."""
    n = len(xy)
    k = min(neighbours, n - 1)
    anchor_ids = np.arange(n) if anchors is None else np.flatnonzero(anchors)
    if k < 3 or not anchor_ids.size:
        return np.zeros((0, 4), dtype=np.int64)
    nn = nearest_others(quick_tree(xy), xy, anchor_ids, k)
    triples = np.array(list(combinations(range(k), 3)))
    anchor = np.repeat(anchor_ids, len(triples))
    cols = [anchor, *(nn[:, triples[:, j]].ravel() for j in range(3))]
    for i, j in SORT4:  # each row sorted by five compare-exchanges of columns: faster than sorting rows
        cols[i], cols[j] = np.minimum(cols[i], cols[j]), np.maximum(cols[i], cols[j])
    quads = np.column_stack(cols)
    if n < _PACKABLE:
        return quads[np.sort(first_rows(quads, n))]
    return np.unique(quads, axis=0)


def ref_canonical_quads(zq):
    """canonical_quads as it was."""
    m = len(zq)
    d = np.empty((m, 6))
    for j, (p, q) in enumerate(PAIRS.tolist()):
        np.abs(zq[:, p] - zq[:, q], out=d[:, j])
    pair = d.argmax(axis=1)
    order = _ORDERS[pair]
    ordered = zq.ravel()[order + 4 * np.arange(m)[:, None]]  # A, B, C, D of each quad
    a = ordered[:, 0]
    t = (ordered[:, 2:] - a[:, None]) / (ordered[:, 1] - a)[:, None]
    swap_ab = t.real.sum(axis=1) > 1.0
    order[swap_ab, :2] = order[swap_ab, 1::-1]
    t[swap_ab] = 1.0 - t[swap_ab]
    swap_cd = t[:, 0].real > t[:, 1].real
    order[swap_cd, 2:] = order[swap_cd, :1:-1]
    t[swap_cd] = t[swap_cd, ::-1]
    return order, t.view(np.float64).reshape(m, 4), d[np.arange(m), pair]


def ref_index(objects, neighbours=8, anchors=None, positions=False):
    """QuadIndex.__init__ as it was: its tree points (None without quads) and quad_z."""
    labels = tuple(objects.labels)
    z = objects.x + 1j * objects.y
    label = objects.label.astype(np.int64)
    if len(objects) >= 4:
        quads = ref_neighbour_quads(np.column_stack([objects.x, objects.y]), neighbours, anchors=anchors)
    else:
        quads = np.zeros((0, 4), np.int64)
    zq = z[quads]
    if len(quads):
        frame = (zq[:, 1:] != zq[:, :1]).any(axis=1)
        quads, zq = quads[frame], zq[frame]
    points = None
    if len(quads):
        order, inv, _ = ref_canonical_quads(zq)
        flat = order + 4 * np.arange(len(quads))[:, None]
        quads, zq = quads.ravel()[flat], zq.ravel()[flat]
        points = np.empty((len(quads), 7 if positions else 5))
        points[:, :4] = inv
        np.multiply(label_keys(label[quads], len(labels)), LABEL_GAP, out=points[:, 4])
        if positions:
            centroid = zq.mean(axis=1)
            np.multiply(POSITION_WEIGHT, centroid.real, out=points[:, 5])
            np.multiply(POSITION_WEIGHT, centroid.imag, out=points[:, 6])
    return points, zq


def same_bits(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def edge_sets(rng):
    """Point sets (xy, labels) that stress the kernel: lattices (ties everywhere), duplicates, collinear points."""
    grid = np.stack(np.meshgrid(np.arange(7.0), np.arange(6.0)), -1).reshape(-1, 2) * 10.0
    line = np.column_stack([np.arange(12.0), np.zeros(12)])
    dup = np.repeat(rng.uniform(0, 50, (6, 2)), 3, axis=0)
    stacked = np.zeros((5, 2))
    signed = np.array([[0.0, 0.0], [-0.0, 0.0], [0.0, -0.0], [-0.0, -0.0], [1e-300, 0.0], [0.0, 1e-300]])
    big = rng.uniform(-1e6, 1e6, (30, 2)) + 1e7
    sets = [grid, line, dup, stacked, signed, big, grid[:4], grid[:5], rng.uniform(0, 100, (3, 2)),
            np.zeros((0, 2)), np.round(rng.uniform(0, 5, (40, 2)))]
    return [(xy, rng.integers(0, 3, len(xy))) for xy in sets]


def random_sets(rng, count):
    return [(rng.normal(0, 100, (int(n), 2)), rng.integers(0, 4, int(n))) for n in rng.integers(4, 120, count)]


def test_canonical_quads_same_bits():
    rng = np.random.default_rng(3)
    zq = rng.normal(size=(2000, 4)) + 1j * rng.normal(size=(2000, 4))
    square = np.array([[0, 1, 1 + 1j, 1j]])  # two diagonals of one length: the first maximum
    rhombus = np.array([[0, 2, 1 + 1j, 1 - 1j], [0, 1, 2, 3], [0, 0, 0, 1], [5, 5, 5, 5], [1, 1j, -1, -1j]])
    ints = rng.integers(-2, 3, (500, 4)) + 1j * rng.integers(-2, 3, (500, 4))  # ties and duplicates
    special = np.array([[np.nan, 0, 1, 1j], [0, np.inf, 1, 1j], [-0.0, 0.0, 1, 1j]])
    for z in (zq, square, rhombus, ints, special, zq[:1], zq[:0], zq[:, ::-1], np.conj(zq)):
        with np.errstate(all="ignore"):  # the NaN and infinite rows divide by NaN
            want = ref_canonical_quads(np.asarray(z, np.complex128))
        got = canonical_quads(z)
        for g, w in zip(got, want, strict=True):
            assert same_bits(g, w)


@pytest.mark.parametrize("neighbours", [3, 5, 8])
def test_neighbour_quads_same_rows(neighbours):
    rng = np.random.default_rng(neighbours)
    for xy, _ in edge_sets(rng) + random_sets(rng, 20):
        for anchors in (None, rng.uniform(size=len(xy)) < 0.5, np.zeros(len(xy), bool)):
            got = neighbour_quads(xy, neighbours, anchors=anchors)
            assert same_bits(got, ref_neighbour_quads(xy, neighbours, anchors=anchors))


def test_neighbour_quads_sorted_beyond_packable():
    """From _PACKABLE points on, np.unique's rows: sorted."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 1e5, (_PACKABLE + 10, 2))
    anchors = np.zeros(len(xy), bool)
    anchors[rng.choice(len(xy), 300, replace=False)] = True
    got = neighbour_quads(xy, 6, anchors=anchors)
    assert len(got) > 0 and same_bits(got, ref_neighbour_quads(xy, 6, anchors=anchors))


@pytest.mark.parametrize("positions", [False, True])
def test_index_same_points(positions):
    rng = np.random.default_rng(11 + positions)
    for xy, label in edge_sets(rng) + random_sets(rng, 25):
        names = np.array(["a", "b", "c", "d"])[label]
        objects = Objects.from_names(xy[:, 0], xy[:, 1], list(names))
        for anchors in (None, rng.uniform(size=len(xy)) < 0.4):
            for neighbours in (3, 8):
                index = QuadIndex(objects, neighbours, anchors=anchors, positions=positions)
                points, zq = ref_index(objects, neighbours, anchors=anchors, positions=positions)
                assert same_bits(index.quad_z, zq)
                assert (index.tree is None) == (points is None)
                if points is not None:
                    assert index.tree is not None and same_bits(index.tree.data, points)


def test_index_of_a_map_tile(paper_setup):
    """A tile of a stored map, anchored in its middle with a margin read around it, as the localizer builds it."""
    with open_map(paper_setup[0]) as m:
        everything = m.all()
        x, y = float(np.median(everything.x)), float(np.median(everything.y))
        objects = m.query_bbox(x - 600, y - 600, x + 600, y + 600)
    anchors = (np.abs(objects.x - x) < 400) & (np.abs(objects.y - y) < 400)
    index = QuadIndex(objects, 8, anchors=anchors, positions=True)
    points, zq = ref_index(objects, 8, anchors=anchors, positions=True)
    assert index.n_quads > 100 and same_bits(index.quad_z, zq)
    assert index.tree is not None and same_bits(index.tree.data, points)


def test_wrong_calls_raise():
    nn = np.array([[1, 2, 3]], np.int64)
    z = np.zeros(4, np.complex128)
    label = np.zeros(4, np.int64)
    for bad in (np.array([[1, 2, 9]], np.int64), np.array([[1, 2, -1]], np.int64)):
        with pytest.raises(ValueError):
            _kernel.map_quads(bad, np.array([0]), 4, False, z, label, 1, False, LABEL_GAP, POSITION_WEIGHT)
    with pytest.raises(ValueError):  # z without labels
        _kernel.map_quads(nn, np.array([0]), 4, False, z, None, 1, False, LABEL_GAP, POSITION_WEIGHT)
    with pytest.raises(ValueError):  # anchors not one per row
        _kernel.map_quads(nn, np.array([0, 1]), 4, False, None, None, 0, False, LABEL_GAP, POSITION_WEIGHT)
    with pytest.raises(ValueError):  # z of another length
        _kernel.map_quads(nn, np.array([0]), 4, False, z[:3], label[:3], 1, False, LABEL_GAP, POSITION_WEIGHT)
    with pytest.raises((TypeError, ValueError)):
        _kernel.map_canonical(np.zeros((2, 3), np.complex128), np.zeros((2, 4), np.int64), np.zeros((2, 4)),
                              np.zeros(2))


def test_neighbours_must_be_distinct_and_anchors_ascending():
    """The kernel keeps a quad unless an earlier anchor among its points made it: that needs distinct neighbours other
    than the anchor, and anchors in ascending order (as nearest_others and neighbour_quads give them)."""
    z = np.arange(6, dtype=np.complex128)
    label = np.zeros(6, np.int64)
    calls = [
        (np.array([[1, 2, 2]], np.int64), np.array([0])),  # a repeated neighbour
        (np.array([[0, 2, 3]], np.int64), np.array([0])),  # the anchor among its neighbours
        (np.array([[2, 3, 4], [2, 3, 4]], np.int64), np.array([1, 0])),  # anchors descending
        (np.array([[2, 3, 4], [2, 3, 4]], np.int64), np.array([1, 1])),  # an anchor twice
    ]
    for nn, anchors in calls:
        with pytest.raises(ValueError):
            _kernel.map_quads(nn, anchors, 6, False, z, label, 1, False, LABEL_GAP, POSITION_WEIGHT)
    good = _kernel.map_quads(np.array([[2, 3, 4], [2, 3, 4]], np.int64), np.array([0, 1]), 6, False, None, None, 0,
                             False, LABEL_GAP, POSITION_WEIGHT)[0]
    assert np.frombuffer(good, np.int64).reshape(-1, 4).tolist() == [[0, 2, 3, 4], [1, 2, 3, 4]]
