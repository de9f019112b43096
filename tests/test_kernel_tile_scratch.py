"""A tile's two kernel calls with their scratch kept between calls (``_kernel_map_quads.c``, ``_kernel_quad_tree.c``):
the same answers whatever was built before (larger or smaller, with or without the quads' ids), and ``map_quads``
without ids (QuadIndex's call) the same points as with them."""

from __future__ import annotations

import numpy as np
from test_kernel_map_quads import edge_sets, random_sets, ref_index, same_bits

from mapdb.match import _kernel
from mapdb.match.quads import LABEL_GAP, POSITION_WEIGHT, QuadIndex, _anchor_neighbours, neighbour_quads
from mapdb.objects import Objects


def _calls(rng):
    """(nn, anchors, n, z, label, n_labels) of point sets large and small, in an order that grows and shrinks."""
    sets = random_sets(rng, 6) + edge_sets(rng) + [(rng.uniform(0, 3000, (1500, 2)), rng.integers(0, 4, 1500))]
    out = []
    for xy, label in sets:
        found = _anchor_neighbours(xy[:, 0], xy[:, 1], 8, None) if len(xy) >= 4 else None
        if found is not None:
            z = np.ascontiguousarray(xy[:, 0] + 1j * xy[:, 1], np.complex128)
            out.append((*found, len(xy), z, np.ascontiguousarray(label, np.int64), 4))
    order = rng.permutation(len(out))
    return [out[i] for i in np.concatenate([order, order[::-1]])]


def test_map_quads_without_ids_makes_the_same_points_whatever_came_before():
    rng = np.random.default_rng(5)
    calls = _calls(rng)
    first = {}
    for j, (nn, anchors, n, z, label, n_labels) in enumerate(calls):
        positions = bool(j % 2)
        with_ids = _kernel.map_quads(nn, anchors, n, False, z, label, n_labels, positions, LABEL_GAP, POSITION_WEIGHT)
        without = _kernel.map_quads(nn, anchors, n, False, z, label, n_labels, positions, LABEL_GAP, POSITION_WEIGHT,
                                    False)
        assert len(without[0]) == 0 and without[1] == with_ids[1] and without[2] == with_ids[2]
        key = (id(nn), positions)
        assert first.setdefault(key, without) == without  # the same call, later, after others of other sizes
    assert any(len(w[1]) > 100_000 for w in first.values())  # a large one grew the scratch


def test_index_and_quads_of_a_set_after_larger_ones_are_the_references():
    rng = np.random.default_rng(8)
    big = rng.uniform(0, 3000, (2000, 2))
    QuadIndex(Objects.from_names(big[:, 0], big[:, 1], ["a"] * len(big)), 8, positions=True)  # scratch grown
    for xy, label in edge_sets(rng) + random_sets(rng, 5):
        names = list(np.array(["a", "b", "c", "d"])[label])
        objects = Objects.from_names(xy[:, 0], xy[:, 1], names)
        index = QuadIndex(objects, 8, positions=True)
        points, zq = ref_index(objects, 8, positions=True)
        assert same_bits(index.quad_z, zq)
        assert (index.tree is None) == (points is None)
        if points is not None:
            assert index.tree is not None and same_bits(index.tree.data, points)
        assert len(neighbour_quads(xy, 8)) >= len(zq)  # ids wanted: made in their own answer


def test_a_tree_looks_up_the_same_whatever_was_built_before():
    rng = np.random.default_rng(9)
    points = np.ascontiguousarray(np.column_stack([rng.uniform(0, 1, (300, 4)), rng.integers(0, 3, 300) * LABEL_GAP]))
    queries = np.ascontiguousarray(points[:50, :4] + rng.normal(0, 0.01, (50, 4)))
    zq = np.ascontiguousarray(rng.normal(size=(300, 4)) + 0j)
    radius = np.full(50, 0.05)

    def hits():
        tree = _kernel.quads_build(points)
        rows, flat = _kernel.quads_lookup((tree,), (zq,), queries, np.ascontiguousarray(points[:50, 4]), radius, 8,
                                          0.0, 0.0, 0.0, 0.05, False, False)
        return bytes(rows), bytes(flat)

    alone = hits()
    for n in (5000, 20, 3000, 1):  # larger and smaller builds between, each over its own scratch's use
        other = np.ascontiguousarray(np.column_stack([rng.uniform(0, 1, (n, 4)), rng.integers(0, 50, n) * LABEL_GAP]))
        _kernel.quads_build(other)
        assert hits() == alone
    assert len(alone[0]) // 8 >= 50  # int64 rows: each query found its own point, so something was compared
