"""One KD-tree query a round (mapdb.match.mapobjects.object_index.Neighbours): the nearest-object, density and
association queries read from it give what their own queries give, and the matcher's answers do not move."""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.match.fast import match_fast
from mapdb.match.mapobjects.object_index import ObjectIndex
from mapdb.match.quads import QuadIndex
from mapdb.match.verify import decision_nfa, refine
from mapdb.objects import Objects

LABELS = ("building", "road_intersection", "park", "stadium")


@pytest.fixture(scope="module")
def town():
    """3,000 objects of four labels over 4 x 3 km: dense quarters, a rare label (three stadiums)."""
    rng = np.random.default_rng(11)
    centres = rng.uniform([0, 0], [4000, 3000], (6, 2))
    xy = centres[rng.integers(0, 6, 3000)] + rng.normal(0, 300, (3000, 2))
    label = rng.choice(3, 3000, p=[0.7, 0.2, 0.1])
    label[:3] = 3
    return Objects(600_000 + xy[:, 0], 4_700_000 + xy[:, 1], label, np.full(3000, 80.0), LABELS, "EPSG:32631")


def _projections(index: ObjectIndex, rng: np.random.Generator, h: int, n: int):
    """``h`` poses over the map and ``n`` image objects of every label: projections, labels, quads' map points."""
    z = rng.uniform(-400, 400, n) + 1j * rng.uniform(-300, 300, n)
    img_label = rng.integers(0, len(LABELS), n)
    a = 0.5 * np.exp(1j * rng.uniform(0, 2 * np.pi, h))
    b = index.z[rng.integers(0, len(index), h)]
    img_ids = np.stack([rng.choice(n, 4, replace=False) for _ in range(h)])
    map_z = index.z[index.at(a[:, None] * z[img_ids] + b[:, None], img_label[img_ids]).clip(0)]
    return a, b, z, img_label, img_ids, map_z


def test_queries_read_from_the_table_match_their_own(town):
    index = ObjectIndex(town)
    rng = np.random.default_rng(5)
    a, b, z, img_label, img_ids, map_z = _projections(index, rng, 12, 40)
    w = a[:, None] * z[None, :] + b[:, None]
    near = index.neighbours(w, img_label, 6)
    assert near is not None and near.k == 6 and near.shape == w.shape
    density = index.local_density(b, np.full(b.size, 500.0))
    for dens in (index.density, density):
        for exclude in (None, map_z):
            own = index.nearest(w, img_label, dens, exclude)
            read = index.nearest(w, img_label, dens, exclude, near=near)
            assert np.array_equal(own[0], read[0]) and np.array_equal(own[1], read[1])
    assert np.array_equal(index.knn_density(w, img_label, 6), index.knn_density(w, img_label, 6, near=near))
    # Some objects find nothing within the mean densities' reach, some the rare label's far neighbours: both kinds
    # of row are compared above.
    assert np.isinf(index.nearest(w, img_label, index.density)[0]).any()
    rows = [7, 2, 3]
    part = near.take(rows)
    own = index.nearest(w[rows], img_label, density[rows], map_z[rows])
    read = index.nearest(w[rows], img_label, density[rows], map_z[rows], near=part)
    assert np.array_equal(own[0], read[0]) and np.array_equal(own[1], read[1])
    # Through the decision and the refinement: the same numbers.
    plain = decision_nfa(a, b, img_ids, map_z, z, img_label, index, density, 2.0, 6)
    assert np.array_equal(plain, decision_nfa(a, b, img_ids, map_z, z, img_label, index, density, 2.0, 6, near=near))
    for one, other in zip(refine(a, b, z, img_label, index, density, 2.0, 2),
                          refine(a, b, z, img_label, index, density, 2.0, 2, near=near), strict=True):
        assert np.array_equal(one, other)


def test_too_few_neighbours_in_the_table_are_not_used(town):
    index = ObjectIndex(town)
    rng = np.random.default_rng(6)
    a, b, z, img_label, _, map_z = _projections(index, rng, 5, 20)
    w = a[:, None] * z[None, :] + b[:, None]
    near = index.neighbours(w, img_label, 2)  # fewer than the exclusion of four map points needs
    assert near is not None
    own = index.nearest(w, img_label, index.density, map_z)
    read = index.nearest(w, img_label, index.density, map_z, near=near)
    assert np.array_equal(own[0], read[0]) and np.array_equal(own[1], read[1])
    assert np.array_equal(index.knn_density(w, img_label, 6), index.knn_density(w, img_label, 6, near=near))
    assert ObjectIndex(Objects.empty(LABELS)).neighbours(w, img_label, 6) is None


def test_matcher_answers_an_image_of_the_map(town):
    # An image cut from the map, turned and scaled: found where it was cut (the table serves the whole search).
    index = ObjectIndex(town)
    centre = index.z[1500]
    keep = np.flatnonzero(np.abs(index.z - centre) < 250.0)
    a_true = 2.0 * np.exp(0.7j)
    z = (index.z[keep] - centre) / a_true
    found = match_fast(z, index.label[keep], index, [QuadIndex(town)], 800.0)
    assert found.best is not None, found.reason
    assert abs(found.best.b - centre) < 0.5
