"""The whole map's object index read page by page (mapdb.match.mapobjects.paged_objects): the same answers as the index
over every object, from fewer pages; and the localizer's switch to the whole index built in the background."""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.localize.localizer import Localizer
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match.index.stored import build_index
from mapdb.match.mapobjects import paged_objects
from mapdb.match.mapobjects.kd_forest import MAX_TREES, Forest
from mapdb.match.mapobjects.label_trees import LabelTrees
from mapdb.match.mapobjects.paged_objects import PagedObjectIndex, WholeMapObjects
from mapdb.match.verify import ObjectIndex
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_images

LABELS = ("building", "road_intersection", "park", "stadium")


@pytest.fixture(scope="module")
def paged_map(tmp_path_factory):
    """6,000 objects over 8 x 6 km in about 50 pages, dense towns and sparse labels (a few stadiums)."""
    rng = np.random.default_rng(3)
    towns = rng.uniform([0, 0], [8000, 6000], (12, 2))
    n = 6000
    centre = towns[rng.integers(0, len(towns), n)]
    xy = centre + rng.normal(0, 250, (n, 2))
    label = rng.choice(4, n, p=[0.75, 0.2, 0.0495, 0.0005])
    label[:3] = 3
    objects = Objects(500_000 + xy[:, 0], 4_650_000 + xy[:, 1], label, np.full(n, 100.0), LABELS, "EPSG:32631")
    path = tmp_path_factory.mktemp("paged") / "towns.mapdb"
    write_map(path, objects, page_capacity=128)
    return path


def _both(path):
    m = open_map(path)
    return m, PagedObjectIndex(m), ObjectIndex(m.all(), bounds=m.bounds)


def _same(paged, whole, which_p, which_w) -> None:
    """Indices differ between the two indexes; the objects they name must be the same."""
    assert np.array_equal(which_p < 0, which_w < 0)
    found = which_w >= 0
    assert np.array_equal(paged.z[which_p[found]], whole.z[which_w[found]])


def test_every_query_gives_the_whole_maps_answer_from_fewer_pages(paged_map) -> None:
    m, paged, whole = _both(paged_map)
    assert m.page_count > 30 and paged.loaded_pages == 0 and paged.counts.tolist() == whole.counts.tolist()
    rng = np.random.default_rng(0)
    b = 500_000 + 1000 + 1j * (4_650_000 + 1000) + rng.normal(0, 300, 6) + 1j * rng.normal(0, 300, 6)
    w = b[:, None] + rng.normal(0, 120, (6, 20)) + 1j * rng.normal(0, 120, (6, 20))
    labels = rng.integers(0, 4, 20)
    for density in (whole.density, whole.local_density(b, np.full(6, 400.0))):
        d_p, i_p = paged.nearest(w, labels, density)
        d_w, i_w = whole.nearest(w, labels, density)
        assert np.array_equal(d_p, d_w)
        _same(paged, whole, i_p, i_w)
    assert np.array_equal(paged.local_density(b, np.full(6, 400.0)), whole.local_density(b, np.full(6, 400.0)))
    rows_p, cols_p, d2_p = paged.within(w.ravel(), np.tile(labels, 6), 30.0, 3)
    rows_w, cols_w, d2_w = whole.within(w.ravel(), np.tile(labels, 6), 30.0, 3)
    assert np.array_equal(rows_p, rows_w) and np.array_equal(d2_p, d2_w)
    assert np.array_equal(paged.z[cols_p], whole.z[cols_w])
    assert 0 < paged.loaded_pages < m.page_count
    # The 3rd nearest stadium lies kilometres away (there are 3): the paged index reads as far as it must.
    assert np.array_equal(paged.knn_density(w, labels, 3), whole.knn_density(w, labels, 3))
    assert np.array_equal(paged.knn_density(w, labels, 2), whole.knn_density(w, labels, 2))


def test_objects_keep_their_index_as_pages_are_added(paged_map) -> None:
    _, paged, whole = _both(paged_map)
    near = whole.z[whole.label == 0][:1, None] + 0.5
    _, first = paged.nearest(near, np.array([0]), paged.density)
    where, pages = paged.z[first[0, 0]], paged.loaded_pages
    assert first[0, 0] >= 0 and abs(where - near[0, 0]) < 1.0
    paged.local_density(np.array([500_000.0 + 8000 + 1j * (4_650_000.0 + 6000)]), np.array([2000.0]))
    assert paged.loaded_pages > pages and paged.z[first[0, 0]] == where


def test_answers_are_the_same_paged_and_whole_and_the_whole_index_takes_over(paged_map, tmp_path,
                                                                            monkeypatch) -> None:
    path = tmp_path / "towns.mapdb"
    path.write_bytes(paged_map.read_bytes())
    build_index(path, workers=1)
    with open_map(path) as m:
        images = simulate_images(m, 6, pixel_std=0.5, yaw="random", seed=2, min_objects=8)
        whole = [Localizer(m).localize(im) for im in images]
        monkeypatch.setattr(paged_objects, "PAGED_FROM_OBJECTS", 1)
        loc = Localizer(m)
        paged = [loc.localize(im) for im in images[:2]]
        served = loc._whole_objects
        assert served.paged  # the first answers read pages; the second request started the whole index
        assert loc.whole_map_ready(60.0)
        paged += [loc.localize(im) for im in images[2:]]
        assert not served.paged and len(served.index()) == len(m)
    assert sum(a.status == "ok" for a in whole) >= 4
    assert [(a.status, a.x, a.y) for a in paged] == [(a.status, a.x, a.y) for a in whole]


def test_a_small_or_in_memory_map_is_indexed_whole_at_once(paged_map) -> None:
    with open_map(paged_map) as m:
        served = WholeMapObjects(m)
        assert not served.paged and len(served.index()) == len(m)
        assert not WholeMapObjects(m, paged_from=10**9).paged and WholeMapObjects(m, paged_from=1).paged


def test_a_forest_answers_as_one_tree_over_all_its_points() -> None:
    rng = np.random.default_rng(5)
    z = rng.uniform(0, 1000, 3000) + 1j * rng.uniform(0, 1000, 3000)
    z[2500:2600] = z[:100]  # duplicates in another run: ties across trees, the lower index first
    label = rng.integers(0, 3, 3000)
    label[2500:2600] = label[:100]
    forest = Forest(3)
    # Seven runs, more than MAX_TREES: the smallest neighbours are merged as runs come.
    cuts = [0, 900, 1000, 1010, 1500, 1600, 2999, 3000]
    for a, b in zip(cuts[:-1], cuts[1:]):
        forest.add(z[a:b], label[a:b])
    assert 1 < len(forest.trees) <= MAX_TREES and forest.n == 3000
    whole = LabelTrees(z, label, 3)
    x = rng.uniform(-50, 1050, 400) + 1j * rng.uniform(-50, 1050, 400)
    x[:50] = z[:50]
    xl = rng.integers(0, 3, 400)
    xl[:50] = label[:50]
    for k in (1, 5):
        d_f, i_f = forest.query(x, xl, k, 40.0)
        d_w, i_w = whole.query(x, xl, k, 40.0)
        assert d_f.shape == d_w.shape and np.array_equal(d_f, d_w) and np.array_equal(i_f, i_w)
        assert np.isinf(d_f).any() and (i_f[np.isinf(d_f)] == 3000).all()  # missing: inf and n
    assert (whole.query(x[:50], xl[:50], 2, 1.0)[1] == np.arange(50)[:, None] + [0, 2500]).all()
    r = rng.uniform(0, 60, 400)
    assert np.array_equal(forest.count(x, xl, r), whole.count(x, xl, r))
    assert all(np.array_equal(a, b) for a, b in zip(forest.members(x, xl, r), whole.members(x, xl, r), strict=True))


def test_the_paged_index_grows_by_new_trees_and_finds_nearest_objects_beyond_its_first_reach(paged_map) -> None:
    m, paged, whole = _both(paged_map)
    trees, pages = [], []
    for end in (np.argmin(whole.z.real), np.argmax(whole.z.real)):  # objects at the two ends of the map
        paged.nearest(whole.z[end] + np.zeros((1, 3)), np.array([0, 1, 2]), whole.density)
        trees.append(paged.trees)
        pages.append(paged.loaded_pages)
    assert 1 <= trees[0] < trees[1] <= MAX_TREES and 0 < pages[0] < pages[1] < m.page_count
    # Stadiums: a few, kilometres apart, so points near one find it beyond the first reach.
    labels = np.array([3, 0, 2, 3])
    density = whole.local_density(np.array([501_000.0 + 4_651_000j]), np.array([400.0]))
    w = whole.z[whole.label == 3][:, None] + np.array([30.0, 120.0 + 40j, 250.0, 600.0])
    d_p, i_p = paged.nearest(w, labels, density)
    d_w, i_w = whole.nearest(w, labels, density)
    assert np.array_equal(d_p, d_w) and np.isfinite(d_w[:, 0]).all() and (d_w > paged_objects.FIRST_REACH_M).any()
    _same(paged, whole, i_p, i_w)


def test_a_k_th_nearest_density_reads_only_as_far_as_it_must(paged_map) -> None:
    """From pages that hold too few of a label, the k-th distance is an overestimate (nothing loaded: the whole
    map's extent): the paged index reads outward in steps from the point, not everything that estimate covers."""
    m, paged, whole = _both(paged_map)
    rng = np.random.default_rng(5)
    w = whole.z[whole.label == 0][rng.integers(0, 4000, 3)][:, None]
    labels = np.array([0])
    assert paged.loaded_pages == 0
    assert np.array_equal(paged.knn_density(w, labels, 6), whole.knn_density(w, labels, 6))
    assert 0 < paged.loaded_pages < m.page_count // 4
