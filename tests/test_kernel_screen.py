"""The matcher's cheap screens (mapdb/match/_kernel_screen.c) against the code they replaced, kept here verbatim as
the reference: the screen's neighbours of image objects (``screen.screen_neighbours``, scipy's tree before) and
the rivals' quick count (``ObjectIndex.near_counts``, ``rivals._near_counts``' numpy before).

Where no two distances of a row tie the k nearest are unique and both must give the same indices in the same order;
where they tie (duplicates, a lattice) the kernel ranks the lower index first, scipy by its heap: there the
distances must be the same and the order the kernel's rule.  Wrong calls raise TypeError/ValueError.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapdb._scipy import cKDTree
from mapdb.match import _kernel
from mapdb.match.mapobjects.object_index import ObjectIndex
from mapdb.match.options import FastOptions
from mapdb.match.screen import screen_neighbours
from mapdb.objects import Objects

# ---------------------------------------------------------------- the scipy reference (main at 9b40c11)


def ref_screen_neighbours(z: np.ndarray, opts: FastOptions) -> np.ndarray:
    n = z.size
    xy = np.column_stack([z.real, z.imag])
    return cKDTree(xy).query(xy, k=min(opts.screen_objects, n))[1].reshape(n, -1)


def ref_near_counts(a, b, z, img_label, index, gate):
    # rivals._near_counts before the kernel (its sigma and SCREEN_SIGMAS folded into ``gate``)
    w = (a[:, None] * z[None, :] + b[:, None]).ravel()
    rows, _, _ = index.within(w, np.tile(img_label, a.size), gate, 1)
    near = np.bincount(rows // z.size, minlength=a.size)
    return near


# ---------------------------------------------------------------- helpers


def _sq(z: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Each row's squared distances to its neighbours, computed as both sides compare them."""
    d = z[rows] - z[:, None]
    return d.real * d.real + d.imag * d.imag


def _check_tie_rule(z: np.ndarray, got: np.ndarray) -> None:
    """Nearest first; among equal distances, the lower index first; and nothing left out is closer."""
    d2 = _sq(z, got)
    assert np.all(np.diff(d2, axis=1) >= 0)
    same = np.diff(d2, axis=1) == 0
    assert np.all(np.diff(got, axis=1)[same] > 0)
    everything = _sq(z, np.broadcast_to(np.arange(z.size), (z.size, z.size)))
    for i in range(z.size):
        left_out = np.setdiff1d(np.arange(z.size), got[i])
        assert not np.any(everything[i, left_out] < d2[i, -1])
        # an object left out at the k-th distance has a higher index than those kept there
        at_edge = left_out[everything[i, left_out] == d2[i, -1]]
        assert not at_edge.size or at_edge.min() > got[i][d2[i] == d2[i, -1]].max()


# ---------------------------------------------------------------- random inputs: identical to scipy


@pytest.mark.parametrize("seed", range(20))
def test_random_images_identical_to_scipy(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 80))
    z = rng.uniform(-500, 500, n) + 1j * rng.uniform(-400, 400, n)
    for k in (1, 4, 12, n):
        opts = FastOptions(screen_objects=k)
        got = screen_neighbours(z, opts)
        assert got.dtype == np.int64 and got.shape == (n, min(k, n))
        np.testing.assert_array_equal(got, ref_screen_neighbours(z, opts))
        assert np.all(got[:, 0] == np.arange(n))  # itself first


def test_more_objects_than_a_scipy_leaf_and_the_largest_image():
    rng = np.random.default_rng(7)
    z = rng.normal(0, 300, 256) + 1j * rng.normal(0, 300, 256)
    opts = FastOptions()
    np.testing.assert_array_equal(screen_neighbours(z, opts), ref_screen_neighbours(z, opts))


# ---------------------------------------------------------------- edges: ties, duplicates, one row


def test_lattice_ties_same_distances_lower_index_first():
    g = np.arange(5)
    z = (g[:, None] * 10 + 1j * g[None, :] * 10).ravel().astype(np.complex128)
    opts = FastOptions(screen_objects=6)
    got, ref = screen_neighbours(z, opts), ref_screen_neighbours(z, opts)
    np.testing.assert_array_equal(_sq(z, got), _sq(z, ref))
    _check_tie_rule(z, got)


@pytest.mark.parametrize("seed", range(6))
def test_integer_pixels_many_ties(seed):
    # detections rounded to whole pixels: equal x everywhere, equal distances often
    rng = np.random.default_rng(50 + seed)
    n = int(rng.integers(5, 200))
    z = rng.integers(-20, 21, n) + 1j * rng.integers(-15, 16, n).astype(np.float64)
    for k in (3, 12):
        opts = FastOptions(screen_objects=k)
        got, ref = screen_neighbours(z, opts), ref_screen_neighbours(z, opts)
        np.testing.assert_array_equal(_sq(z, got), _sq(z, ref))
        _check_tie_rule(z, got)


def test_duplicates():
    z = np.array([0, 5, 0, 5, 1j, 0], np.complex128)
    got = screen_neighbours(z, FastOptions(screen_objects=4))
    ref = ref_screen_neighbours(z, FastOptions(screen_objects=4))
    np.testing.assert_array_equal(_sq(z, got), _sq(z, ref))
    _check_tie_rule(z, got)
    assert got[2].tolist() == [0, 2, 5, 4]  # the duplicates of point 2, lower index first, then the nearest


def test_one_object_and_none():
    assert screen_neighbours(np.array([3 + 4j]), FastOptions()).tolist() == [[0]]
    assert screen_neighbours(np.zeros(0, np.complex128), FastOptions()).shape == (0, 0)


def test_huge_coordinates_overflowing_the_squares():
    z = np.array([0, 1e200, -1e200, 1e200j], np.complex128)
    got = screen_neighbours(z, FastOptions(screen_objects=4))
    # every other point's squared distance overflows to inf: a tie, so itself and then the others in order
    for i, row in enumerate(got.tolist()):
        assert row == [i] + [j for j in range(4) if j != i]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, complex(0, np.nan)])
def test_non_finite_refused_as_scipy_refused(bad):
    z = np.array([0, 1, bad, 1j], np.complex128)
    with pytest.raises(ValueError):
        ref_screen_neighbours(z, FastOptions())
    with pytest.raises(ValueError, match="finite"):
        screen_neighbours(z, FastOptions())


# ---------------------------------------------------------------- wrong calls


def test_wrong_calls_raise():
    z = np.array([0, 1, 1j], np.complex128)
    with pytest.raises(TypeError):
        _kernel.screen_knn(z.real.copy(), np.empty((3, 2), np.int64))  # not complex
    with pytest.raises(TypeError):
        _kernel.screen_knn(z, np.empty((3, 2), np.int32))  # not int64
    with pytest.raises(ValueError):
        _kernel.screen_knn(z, np.empty((3, 4), np.int64))  # more neighbours than objects
    with pytest.raises(ValueError):
        _kernel.screen_knn(z, np.empty((3, 0), np.int64))
    with pytest.raises(ValueError):
        _kernel.screen_knn(z, np.empty((2, 2), np.int64))  # a row short
    with pytest.raises((TypeError, ValueError)):
        _kernel.screen_knn(z, np.empty((3, 2), np.int64)[:, ::-1])  # not C-contiguous
    frozen = np.empty((3, 2), np.int64)
    frozen.setflags(write=False)
    with pytest.raises((TypeError, ValueError, BufferError)):
        _kernel.screen_knn(z, frozen)
    with pytest.raises(TypeError):
        _kernel.screen_knn(z)


# ---------------------------------------------------------------- the rivals' quick count


def _town(seed: int, n: int, labels: int = 3, grid: bool = False) -> ObjectIndex:
    rng = np.random.default_rng(seed)
    if grid:  # a lattice: ties everywhere, and objects exactly at the gate's distance
        g = np.arange(int(np.sqrt(n)))
        x, y = (g[:, None] * 10.0 + 0 * g[None, :]).ravel(), (0 * g[:, None] + g[None, :] * 10.0).ravel()
    else:
        x, y = rng.uniform(0, 1000, n), rng.uniform(0, 800, n)
    label = rng.integers(0, labels, x.size)
    return ObjectIndex(Objects(x, y, label, np.zeros(x.size), tuple(f"l{j}" for j in range(labels))))


def _poses(rng, h: int, n: int):
    a = rng.uniform(0.3, 0.6, h) * np.exp(1j * rng.uniform(-np.pi, np.pi, h))
    b = rng.uniform(0, 1000, h) + 1j * rng.uniform(0, 800, h)
    z = rng.uniform(-300, 300, n) + 1j * rng.uniform(-200, 200, n)
    return a, b, z


@pytest.mark.parametrize("seed", range(12))
def test_near_counts_identical_to_the_reference(seed):
    rng = np.random.default_rng(100 + seed)
    index = _town(seed, int(rng.integers(50, 3000)), int(rng.integers(1, 5)))
    h, n = int(rng.integers(1, 60)), int(rng.integers(1, 40))
    a, b, z = _poses(rng, h, n)
    img_label = rng.integers(0, len(index.labels), n)
    for gate in (0.5, 5.0, 30.0, 1e9):
        got = index.near_counts(a, b, z, img_label, gate)
        assert got.dtype == np.int64
        ref = ref_near_counts(a, b, z, img_label, index, gate)
        np.testing.assert_array_equal(got, ref)
        # with a count to reach, those reaching it are exact and the others stay below it
        for need in (1, 4, n // 2, n, n + 1):
            short = index.near_counts(a, b, z, img_label, gate, need)
            np.testing.assert_array_equal(short >= need, ref >= need)
            np.testing.assert_array_equal(short[ref >= need], ref[ref >= need])
            assert np.all(short <= ref)


def test_near_counts_edges():
    index = _town(0, 400, 2, grid=True)
    rng = np.random.default_rng(5)
    a = np.array([1.0, 1.0, 1j, np.nan, 1.0], np.complex128)
    b = np.array([0, 5, 3 + 4j, 0, np.inf], np.complex128)
    z = np.array([0, 10, 10j, 20 + 20j, 0, 5 + 5j], np.complex128)  # a duplicate, a point between the lattice's
    img_label = rng.integers(0, 2, z.size)
    for gate in (0.0, 5.0, 5.000000001, 10.0, np.nan, np.inf):
        got = index.near_counts(a, b, z, img_label, gate)
        np.testing.assert_array_equal(got, ref_near_counts(a, b, z, img_label, index, gate))
    one = index.near_counts(a[:1], b[:1], z[:1], img_label[:1], 1.0)
    np.testing.assert_array_equal(one, ref_near_counts(a[:1], b[:1], z[:1], img_label[:1], index, 1.0))
    none = index.near_counts(a[:0], b[:0], z, img_label, 1.0)
    assert none.shape == (0,) and none.dtype == np.int64
    # a label the map does not hold counts nothing, as the tree's query finds nothing for it
    assert index.near_counts(a[:1], b[:1], z, np.full(z.size, 7), 1e9).tolist() == [0]


def test_near_counts_refuse_wrong_calls():
    index = _town(1, 100)
    tree = index.fused_tree()._tree()
    a = b = np.zeros(2, np.complex128)
    z, lab = np.zeros(3, np.complex128), np.zeros(3, np.int64)
    out = np.empty(2, np.int64)
    _kernel.screen_near_counts(*tree, a, b, z, lab, 1.0, 0, out)
    with pytest.raises(TypeError):
        _kernel.screen_near_counts(*tree, a.real.copy(), b, z, lab, 1.0, 0, out)
    with pytest.raises(TypeError):
        _kernel.screen_near_counts(*tree, a, b, z, lab.astype(np.int32), 1.0, 0, out)
    with pytest.raises(ValueError):
        _kernel.screen_near_counts(*tree, a, b[:1], z, lab, 1.0, 0, out)
    with pytest.raises(ValueError):
        _kernel.screen_near_counts(*tree, a, b, z, lab[:2], 1.0, 0, out)
    with pytest.raises(ValueError):
        _kernel.screen_near_counts(*tree, a, b, z, lab, 1.0, 0, np.empty(3, np.int64))
    with pytest.raises(TypeError):
        _kernel.screen_near_counts(*tree, a, b, z, lab, "1", 0, out)
    with pytest.raises(TypeError):
        _kernel.screen_near_counts(*tree, a, b, z, lab, 1.0, 0.5, out)
    bad_node = tree[3].copy()
    bad_node[:] = 10**9
    with pytest.raises(ValueError):
        _kernel.screen_near_counts(tree[0], tree[1], tree[2], bad_node, tree[4], a, b, z, lab, 1e9, 0, out)
