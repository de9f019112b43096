"""The map objects' KD-trees per label in the compiled kernel (mapdb/match/_kernel_objects.c, wrapped by
mapdb.match.mapobjects.label_trees) against the cKDTree code they replaced, kept here verbatim as the reference.

:class:`RefObjectIndex` is :class:`ObjectIndex` as it was (one cKDTree over ``(x, y, label * gap)``); every query
method is compared on random maps and queries and at the edges (duplicate objects, so tied distances; a label with
fewer objects than asked for, or none; one object; an empty map; bounds and radii met exactly).  Distances and counts
must be identical; indices too, except among tied distances, where the kernel puts the lower index first (cKDTree's
order there was its heap's): there the objects named must be at the same place.
"""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from mapdb._scipy import cKDTree, quick_tree
from mapdb.match import _kernel
from mapdb.match.arrays import sorted_unique
from mapdb.match.evidence.areas import compatible
from mapdb.match.mapobjects.label_trees import LabelTrees
from mapdb.match.mapobjects.object_index import _DISC, AREA_NEIGHBOURS, Neighbours, ObjectIndex, _flat_labels
from mapdb.objects import Objects

LABELS = ("building", "road_intersection", "park", "stadium")

# ---------------------------------------------------------------- the cKDTree reference (main at 1441f0c)


class RefObjectIndex(ObjectIndex):
    """ObjectIndex's queries as they were, on one cKDTree over (x, y, label * gap)."""

    def __init__(self, objects: Objects, bounds=None) -> None:
        super().__init__(objects, bounds)
        n = len(objects)
        self.tree = quick_tree(np.column_stack([objects.x, objects.y, self.label * self.gap])) if n else None

    def _points(self, w: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """The tree points of map positions ``w`` (complex, 1-D) of ``labels``: ``(x, y, label * gap)``."""
        points = np.empty((w.size, 3))  # filled column by column: a column_stack costs several calls more
        points[:, 0] = w.real
        points[:, 1] = w.imag
        np.multiply(labels, self.gap, out=points[:, 2])
        return points

    def local_density(self, centres: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Objects per square metre of each label within ``radius`` of each centre (inside the bounds).

        ``centres`` (complex) and ``radius`` have shape ``(H,)``; the result ``(H, L)``.  A label with no
        object in a disc counts one, so that no density is zero.
        """
        centres = np.atleast_1d(np.asarray(centres, np.complex128))
        radius = np.broadcast_to(np.asarray(radius, np.float64), centres.shape)
        h, n_labels = centres.size, len(self.labels)
        minx, miny, maxx, maxy = self.bounds
        disc = centres[:, None] + radius[:, None] * _DISC[None, :]
        inside = (disc.real >= minx) & (disc.real <= maxx) & (disc.imag >= miny) & (disc.imag <= maxy)
        share = np.add.reduce(inside, axis=1, dtype=np.float64) / _DISC.size  # inside.mean(axis=1), one call
        area = math.pi * radius**2 * np.maximum(share, 1.0 / _DISC.size)
        count = np.ones((h, n_labels))
        present = np.flatnonzero(self.counts)
        if self.tree is not None and present.size:
            w = np.repeat(centres, present.size)
            codes = present[None, :].repeat(h, axis=0).ravel()  # np.tile's numbers in one call
            r = np.minimum(np.repeat(radius, present.size), 0.5 * self.gap)
            found = self.tree.query_ball_point(self._points(w, codes), r, return_length=True)
            count[:, present] = np.maximum(np.asarray(found).reshape(h, present.size), 1)
        return count / area[:, None]

    def neighbours(self, w: np.ndarray, img_label: np.ndarray, k: int) -> Neighbours | None:
        """The ``k`` nearest map objects of each projected image object's label (``w``: ``(H, n)`` complex,
        ``img_label``: ``(n,)``), for :meth:`nearest` and :meth:`knn_density` of the same ``w`` (their ``near``);
        None where one query cannot serve them (no objects; an index reading pages as queries need them)."""
        if self.tree is None or type(self).nearest is not RefObjectIndex.nearest:
            return None
        labels = _flat_labels(img_label, w.shape)
        d, i = self.tree.query(self._points(w.ravel(), labels), k=k, distance_upper_bound=self._bound(0.5 * self.gap))
        return Neighbours(d.reshape(labels.size, k), i.reshape(labels.size, k), w.shape)

    def knn_density(self, w: np.ndarray, img_label: np.ndarray, k: int,
                    near: Neighbours | None = None) -> np.ndarray:
        """Objects per square metre of each projected image object's label around where it lands.

        ``(k - 1) / (pi d_k^2)``, ``d_k`` the distance to the ``k``-th nearest map object of that label: a
        density that follows the map's clustering (a dense old town beside empty slopes), where one
        density over the footprint would make chance alignments in the town look significant.  A label
        with a single map object gets ``1 / (pi d_1^2)``; a label absent from the map, the region's floor.
        ``w`` is ``(H, n)`` complex; ``img_label`` ``(n,)``.  Returns ``(H, n)``.  ``near``: :meth:`neighbours` of
        the same ``w`` with at least ``k`` (used instead of a query of its own).
        """
        shape = w.shape
        labels = _flat_labels(img_label, shape)
        out = np.full(labels.size, 1.0 / self.area)
        kk = np.minimum(k, self.counts[labels])
        sel = np.flatnonzero(kk > 0)
        if self.tree is None or not sel.size:
            return out.reshape(shape)
        if near is not None and near.k >= k:
            d = near.dist[sel, kk[sel] - 1]
        else:
            k_max = int(kk[sel].max())
            d, _ = self.tree.query(self._points(w.ravel()[sel], labels[sel]), k=k_max,
                                   distance_upper_bound=self._bound(0.5 * self.gap))
            d = d.reshape(sel.size, k_max)[np.arange(sel.size), kk[sel] - 1]
        out[sel] = np.maximum(kk[sel] - 1, 1) / (math.pi * np.maximum(d, 1e-3) ** 2)
        return out.reshape(shape)

    def nearest(
        self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray, exclude: np.ndarray | None = None,
        near: Neighbours | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance to, and index of, the nearest map object of each projected image object's label.

        ``w`` has shape ``(H, n)`` (map metres, complex); ``img_label`` is ``(n,)`` or ``(H, n)``;
        ``density`` is ``(L,)`` or ``(H, L)``.  Objects with nothing of their label within the
        normalised residual ``U_MAX`` get ``inf`` and -1.  ``exclude`` (complex, ``(H, m)``) lists map
        positions that row ``h`` may not use: the map points a hypothesis was built from.  ``near``:
        :meth:`neighbours` of the same ``w`` (read instead of a query of its own when it holds enough).
        """
        shape = w.shape
        labels = _flat_labels(img_label, shape)
        if self.tree is None:
            return np.full(shape, np.inf), np.full(shape, -1, dtype=np.int64)
        reach = self._reach(density, labels)
        k = 1 if exclude is None else 1 + exclude.shape[1]
        if near is not None and near.k >= k:
            # Its first k within the reach are what a query of k bounded by the reach finds.
            d, i = (near.dist[:, 0], near.index[:, 0]) if k == 1 else (near.dist[:, :k], near.index[:, :k])
        else:
            d, i = self.tree.query(self._points(w.ravel(), labels), k=k,
                                   distance_upper_bound=self._bound(reach.max()))
        if exclude is None:  # nothing to exclude: the nearest is the answer when within reach
            ok = d <= reach
            return np.where(ok, d, np.inf).reshape(shape), np.where(ok, i, -1).reshape(shape)
        dist, index = self._first_allowed(d.reshape(labels.size, k), i.reshape(labels.size, k), reach, exclude,
                                          repeat=shape[1])
        return dist.reshape(shape), index.reshape(shape)

    def nearest_compatible(self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray, exclude: np.ndarray | None,
                           lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`nearest`, among the map objects whose areas are compatible with each image object's band
        (``lo``, ``hi``: ``(H, n)`` log square metres, :func:`mapdb.match.evidence.areas.bands`).  Where the nearest is
        not compatible, the next ``AREA_NEIGHBOURS`` are looked at; none compatible counts as unmatched."""
        dist, index = self.nearest(w, img_label, density, exclude)  # also what a paged index loads for the reach
        ok = compatible(self.log_area[np.maximum(index, 0)], lo, hi) | (index < 0)
        redo = np.flatnonzero(~ok.ravel())
        if not redo.size:
            return dist, index
        shape = w.shape
        labels = np.broadcast_to(img_label, shape).ravel()[redo]
        reach = self._reach(density, labels)
        k = min(len(self), AREA_NEIGHBOURS + (0 if exclude is None else exclude.shape[1]))
        d, i = self.tree.query(self._points(w.ravel()[redo], labels), k=k,  # type: ignore[union-attr]
                               distance_upper_bound=self._bound(reach.max()))
        d, i = d.reshape(redo.size, k), i.reshape(redo.size, k)
        allowed = compatible(self.log_area[np.minimum(i, len(self) - 1)], lo.ravel()[redo][:, None],
                             hi.ravel()[redo][:, None])
        rows = redo // shape[1]
        dist, index = dist.ravel().copy(), index.ravel().copy()
        dist[redo], index[redo] = self._first_allowed(d, i, reach, None if exclude is None else exclude[rows], allowed)
        return dist.reshape(shape), index.reshape(shape)

    def at(self, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Index of the map object at each of ``points`` (complex, any shape) of ``labels`` (same shape), -1
        where there is none (within a millimetre)."""
        if self.tree is None:
            return np.full(np.shape(points), -1, np.int64)
        d, i = self.tree.query(self._points(np.ravel(points), np.ravel(labels)), k=1, distance_upper_bound=1e-3)
        return np.where(np.isfinite(d), i, -1).reshape(np.shape(points))

    def disc_members(self, centres: np.ndarray, radius: np.ndarray, codes: np.ndarray) -> list[list[np.ndarray]]:
        """Indices of the map objects of each label in ``codes`` within ``radius`` of each centre:
        ``out[h][code]`` (empty for the labels not asked)."""
        centres = np.atleast_1d(np.asarray(centres, np.complex128))
        radius = np.broadcast_to(np.asarray(radius, np.float64), centres.shape)
        empty = np.zeros(0, np.int64)
        out = [[empty] * len(self.labels) for _ in range(centres.size)]
        if self.tree is None:
            return out
        codes = sorted_unique(codes)
        w = np.repeat(centres, codes.size)
        found = self.tree.query_ball_point(self._points(w, np.tile(codes, centres.size)),
                                           np.minimum(np.repeat(radius, codes.size), 0.5 * self.gap))
        for j, hits in enumerate(found):
            out[j // codes.size][int(codes[j % codes.size])] = np.asarray(hits, np.int64)
        return out

    def within(self, w: np.ndarray, img_label: np.ndarray, gate: float, k: int) -> tuple[np.ndarray, ...]:
        """Pairs (image object, map object, squared distance) within ``gate`` metres, up to ``k`` per object."""
        if self.tree is None or not w.size:
            empty = np.zeros(0, np.int64)
            return empty, empty, np.zeros(0)
        k = max(1, min(k, len(self)))
        d, i = self.tree.query(self._points(w, img_label), k=k, distance_upper_bound=self._bound(gate))
        d, i = d.reshape(w.size, k), i.reshape(w.size, k)
        rows, cols = np.nonzero(np.isfinite(d))
        return rows, i[rows, cols], d[rows, cols] ** 2


# ---------------------------------------------------------------- maps and queries


def _map(rng: np.random.Generator, n: int, duplicates: float = 0.1, decimals: int | None = 1) -> Objects:
    """``n`` objects of four labels in a few clusters (one label rare), some duplicated (same place and label),
    places rounded to ``decimals`` so that distances tie often."""
    centres = rng.uniform(0, 3000, (5, 2))
    xy = centres[rng.integers(0, 5, n)] + rng.normal(0, 200, (n, 2))
    if decimals is not None:
        xy = xy.round(decimals)
    label = rng.choice(4, n, p=[0.6, 0.25, 0.14, 0.01])
    dup = np.flatnonzero(rng.random(n) < duplicates)
    src = rng.integers(0, n, dup.size)
    xy[dup], label[dup] = xy[src], label[src]
    area = rng.choice([np.nan, 50.0, 400.0, 3000.0], n)
    return Objects(500_000 + xy[:, 0], 4_600_000 + xy[:, 1], label, area, LABELS, "EPSG:32631")


def _same_objects(index: ObjectIndex, got: np.ndarray, want: np.ndarray) -> None:
    """Indices agree, or name objects at the same place (ties among duplicates); -1 / n for none agree."""
    got, want = np.asarray(got), np.asarray(want)
    assert got.shape == want.shape
    n = len(index)
    none_g, none_w = (got < 0) | (got >= n), (want < 0) | (want >= n)
    assert np.array_equal(none_g, none_w)
    found = ~none_g
    assert np.array_equal(index.z[got[found]], index.z[want[found]])
    assert np.array_equal(index.label[got[found]], index.label[want[found]])


def _both(objects: Objects, bounds=None) -> tuple[ObjectIndex, RefObjectIndex]:
    return ObjectIndex(objects, bounds), RefObjectIndex(objects, bounds)


def _hypotheses(index: ObjectIndex, rng: np.random.Generator, h: int, n: int):
    z = rng.uniform(-300, 300, n) + 1j * rng.uniform(-300, 300, n)
    img_label = rng.integers(0, len(LABELS), n)
    a = 0.5 * np.exp(1j * rng.uniform(0, 2 * np.pi, h))
    b = index.z[rng.integers(0, len(index), h)] + rng.normal(0, 20, h)
    w = a[:, None] * z[None, :] + b[:, None]
    w[:, :3] = index.z[rng.integers(0, len(index), (h, 3))]  # some land exactly on objects (and their duplicates)
    return a, b, z, img_label, w


# ---------------------------------------------------------------- every query against the reference


@pytest.mark.parametrize("seed", range(4))
def test_every_query_answers_as_the_ckdtree_did(seed: int) -> None:
    rng = np.random.default_rng(seed)
    new, ref = _both(_map(rng, int(rng.integers(200, 1500))))
    a, b, z, img_label, w = _hypotheses(new, rng, 15, 24)
    radius = rng.uniform(0, 600, b.size)
    np.testing.assert_array_equal(new.local_density(b, radius), ref.local_density(b, radius))
    near_n, near_r = new.neighbours(w, img_label, 6), ref.neighbours(w, img_label, 6)
    np.testing.assert_array_equal(near_n.dist, near_r.dist)
    _same_objects(new, near_n.index, near_r.index)
    for k in (1, 3, 8):
        np.testing.assert_array_equal(new.knn_density(w, img_label, k), ref.knn_density(w, img_label, k))
    exclude = new.z[new.at(w[:, :3], np.broadcast_to(img_label[:3], (15, 3)))]
    for density in (new.density, new.local_density(b, radius)):
        for ex in (None, exclude):
            got, want = new.nearest(w, img_label, density, ex), ref.nearest(w, img_label, density, ex)
            np.testing.assert_array_equal(got[0], want[0])
            _same_objects(new, got[1], want[1])
    lo = rng.uniform(2, 7, w.shape)
    hi = lo + rng.uniform(0, 2, w.shape)
    got = new.nearest_compatible(w, img_label, new.density, exclude, lo, hi)
    want = ref.nearest_compatible(w, img_label, new.density, exclude, lo, hi)
    np.testing.assert_array_equal(got[0], want[0])
    _same_objects(new, got[1], want[1])
    got, want = new.at(w, np.broadcast_to(img_label, w.shape)), ref.at(w, np.broadcast_to(img_label, w.shape))
    _same_objects(new, got, want)
    assert (got[:, :3] >= 0).any()
    codes = img_label[:5]
    for g, r in zip(new.disc_members(b, radius, codes), ref.disc_members(b, radius, codes), strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(g, r, strict=True))  # sorted lists: the same indices
    for gate, k in ((5.0, 1), (40.0, 3), (400.0, 8)):
        got, want = new.within(w.ravel(), np.tile(img_label, 15), gate, k), ref.within(
            w.ravel(), np.tile(img_label, 15), gate, k)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[2], want[2])
        _same_objects(new, got[1], want[1])


def test_ties_come_lowest_index_first_and_the_same_distance_as_ckdtree() -> None:
    # Five copies of one object, and a ring of four at the same distance: every answer a tie.
    z = np.array([0j] * 5 + [10, 10j, -10, -10j] + [3 + 4j])
    trees = LabelTrees(z, np.zeros(z.size, np.int64), 1)
    d, i = trees.query(np.array([0j, 0j]), np.array([0, 0]), 10, 20.0)
    assert i[0].tolist() == [0, 1, 2, 3, 4, 9, 5, 6, 7, 8] and d[0].tolist() == [0.0] * 5 + [5.0] + [10.0] * 4
    ref_d, ref_i = cKDTree(np.column_stack([z.real, z.imag])).query([0.0, 0.0], k=10, distance_upper_bound=20.0)
    assert np.array_equal(ref_d, d[0]) and sorted(ref_i[:5]) == [0, 1, 2, 3, 4]
    # A bound is strict (as cKDTree's), a radius is not.
    assert trees.query(np.array([0j]), np.array([0]), 10, 10.0)[1][0].tolist() == [0, 1, 2, 3, 4, 9] + [10] * 4
    assert trees.count(np.array([0j, 0j]), np.array([0, 0]), np.array([10.0, 5.0])).tolist() == [10, 6]
    assert [m.tolist() for m in trees.members(np.array([0j]), np.array([0]), 5.0)] == [[0, 1, 2, 3, 4, 9]]


def test_the_edges_few_objects_no_objects_missing_labels_and_points_that_are_not_finite() -> None:
    one, one_ref = _both(Objects.from_names([5.0], [5.0], ["park"], labels=list(LABELS)))
    w = np.array([[5.0 + 5j, 5.5 + 5j, 1e4 + 0j]])
    for k in (1, 4):
        got, want = one.neighbours(w, np.array([2, 2, 2]), k), one_ref.neighbours(w, np.array([2, 2, 2]), k)
        np.testing.assert_array_equal(got.dist, want.dist)
        np.testing.assert_array_equal(got.index, want.index)  # the missing: inf and len(index) = 1
    got = one.nearest(w, np.array([0, 2, 2]), one.density)
    want = one_ref.nearest(w, np.array([0, 2, 2]), one.density)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]) and got[1].tolist() == [[-1, 0, -1]]
    np.testing.assert_array_equal(one.local_density(np.array([0j]), np.array([50.0])),
                                  one_ref.local_density(np.array([0j]), np.array([50.0])))
    empty = ObjectIndex(Objects.empty(list(LABELS)))
    assert empty.tree is None and empty.neighbours(w, np.array([0, 1, 2]), 3) is None
    assert empty.at(w, np.zeros(w.shape, np.int64)).tolist() == [[-1, -1, -1]]
    trees = LabelTrees(np.array([0j, 1 + 0j]), np.array([0, 1]), 3)
    d, i = trees.query(np.array([np.nan + 0j, np.inf + 0j, 0j, 0j]), np.array([0, 0, 2, 7]), 2, 1e9)
    assert np.isinf(d).all() and (i == 2).all()  # not finite, a label without objects, no such label: nothing
    assert trees.count(np.array([np.nan + 0j, 0j, 0j]), np.array([0, 0, 0]), np.array([5.0, np.nan, -1.0])).tolist() \
        == [0, 0, 0]
    assert [m.size for m in trees.members(np.zeros(2, complex), np.array([0, 5]), 5.0)] == [1, 0]
    assert trees.query(np.zeros(0, complex), np.zeros(0, np.int64), 3, 5.0)[0].shape == (0, 3)


def test_trees_pickle_and_answer_alike_after() -> None:
    rng = np.random.default_rng(2)
    index = ObjectIndex(_map(rng, 300))
    back = pickle.loads(pickle.dumps(index))
    _, _, _, img_label, w = _hypotheses(index, rng, 4, 10)
    assert np.array_equal(back.neighbours(w, img_label, 4).index, index.neighbours(w, img_label, 4).index)


@pytest.mark.parametrize("decimals", [None, 0])
def test_many_random_queries_give_ckdtree_s_distances_and_counts(decimals: int | None) -> None:
    rng = np.random.default_rng(9)
    objects = _map(rng, 5000, duplicates=0.05, decimals=decimals)
    z, label = objects.x + 1j * objects.y, objects.label.astype(np.int64)
    gap = 1e7
    trees, ref = LabelTrees(z, label, 4), cKDTree(np.column_stack([objects.x, objects.y, label * gap]))
    q = z[rng.integers(0, z.size, 3000)] + rng.normal(0, 40, 3000).round(0) + 1j * rng.normal(0, 40, 3000).round(0)
    ql = rng.integers(0, 4, q.size)
    points = np.column_stack([q.real, q.imag, ql * gap])
    ties = 0
    for k, bound in ((1, 1e-3), (1, 30.0), (5, 100.0), (12, 1e6)):
        d, i = trees.query(q, ql, k, bound)
        ref_d, ref_i = ref.query(points, k=k, distance_upper_bound=bound)
        np.testing.assert_array_equal(d, ref_d.reshape(q.size, k))
        ref_i = ref_i.reshape(q.size, k)
        named = z[np.minimum(ref_i, z.size - 1)]
        same_distance = np.sqrt((named.real - q.real[:, None]) ** 2 + (named.imag - q.imag[:, None]) ** 2) == d
        assert ((i == ref_i) | same_distance).all() and (i == ref_i).mean() > 0.9  # differing: only among ties
        tied = (d[:, 1:] == d[:, :-1]) & np.isfinite(d[:, 1:])
        assert (i[:, 1:][tied] > i[:, :-1][tied]).all()  # the lower index first
        ties += int(tied.sum())
    assert ties > 100  # the duplicates made ties to order
    r = rng.uniform(0, 150, q.size)
    r[:10] = np.abs(q[:10] - z[0])  # radii met exactly
    ql[:10] = label[0]
    points[:10, 2] = label[0] * gap
    assert np.array_equal(trees.count(q, ql, r), ref.query_ball_point(points, r, return_length=True))


# ---------------------------------------------------------------- a wrong call raises, never crashes


def test_wrong_calls_raise_type_or_value_errors() -> None:
    trees = LabelTrees(np.arange(40) * (1 + 1j), np.arange(40) % 2, 2)
    w, lab = np.zeros(3, complex), np.zeros(3, np.int64)
    d, i = np.empty((3, 2)), np.empty((3, 2), np.int64)
    parts = [trees.pts, trees.pid, trees.box, trees.node, trees.root]
    _kernel.objects_knn(*parts, w, lab, 5.0, 40, d, i)  # the right call goes through
    with pytest.raises(TypeError):
        _kernel.objects_knn(*parts, w.real.copy(), lab, 5.0, 40, d, i)  # not complex
    with pytest.raises(TypeError):
        _kernel.objects_knn(*parts, w, lab.astype(np.int32), 5.0, 40, d, i)
    with pytest.raises(ValueError):
        _kernel.objects_knn(*parts, w, lab, 5.0, 40, d[:2], i)
    with pytest.raises(ValueError):
        _kernel.objects_knn(*parts, w, lab, 5.0, 40, np.empty((3, 0)), np.empty((3, 0), np.int64))
    with pytest.raises(ValueError):
        _kernel.objects_knn(*parts, w[::2], lab[::2], 5.0, 40, d[:2], i[:2])  # w not contiguous: w[::2] is
    with pytest.raises(TypeError):
        _kernel.objects_knn(*parts[:4], None, w, lab, 5.0, 40, d, i)
    for bad_node in ([[0, 99, -1]], [[0, 10, 0]], [[-1, 5, -1]]):  # outside the arrays, a child that loops
        node = trees.node.copy()
        node[0] = bad_node[0]
        with pytest.raises(ValueError):
            _kernel.objects_knn(parts[0], parts[1], parts[2], node, parts[4], w, lab, 1e9, 40, d, i)
        with pytest.raises(ValueError):
            _kernel.objects_disc(parts[0], parts[1], parts[2], node, parts[4], w, lab, np.full(3, 1e9), None,
                                 np.empty(3, np.int64))
    with pytest.raises(ValueError):
        _kernel.objects_knn(*parts[:4], np.array([99, 0]), w, lab, 5.0, 40, d, i)  # a root outside the tree
    with pytest.raises(ValueError):
        _kernel.objects_disc(*parts, w, lab, np.full(3, 9.0), np.array([0, 1, 1, 5]), np.empty(5, np.int64))
    with pytest.raises(ValueError):
        LabelTrees(np.zeros(2, complex), np.array([0, 2]), 2)  # a label beyond the labels
    with pytest.raises(ValueError):
        LabelTrees(np.zeros(2, complex), np.array([0]), 2)
    with pytest.raises(ValueError):
        _kernel.objects_build(np.zeros(3), np.zeros(3), np.zeros(3, np.int64), np.empty((3, 2)),
                              np.empty(3, np.int64), np.empty((0, 4)), np.empty((0, 3), np.int64),
                              np.empty(1, np.int64))  # no room for a node
