"""The verification's fused kernel calls (mapdb/match/_kernel_verify.c) against the numpy code they replaced, kept
here verbatim as the reference: the screen's (``verify_screen`` through :meth:`ObjectIndex.screen_nfa`: projection,
nearest map object within reach, normalised residuals, the NFA curve) and the decision's on point residuals
(``verify_decision`` in :func:`mapdb.match.verify.decision_nfa`: the nearest allowed neighbour, the local density,
tolerance shapes, the curve).

Random maps and hypotheses and the edges (duplicate objects, ties at the reach, labels absent from the map, points
far outside the map, NaN, one row, too few objects); the answers must be identical, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapdb.match import _kernel
from mapdb.match._kernel import quad_tolerance
from mapdb.match.evidence.points import refinement_inliers
from mapdb.match.geometry import fit_similarity_complex
from mapdb.match.mapobjects.kd_forest import Forest
from mapdb.match.mapobjects.object_index import _DISC, ObjectIndex
from mapdb.match.nfa import log10_nfa_curve
from mapdb.match.verify import _POINTS, decision_nfa, refine, screen
from mapdb.objects import Objects

LABELS = ["building", "tree", "pole", "absent"]


def ref_screen(a, b, img_ids, screen_of, z, img_label, index, log10_tests, keep):
    # main at 28ca4ba, mapdb/match/verify.py: screen
    objects = screen_of[img_ids[:, 0]]
    labels = img_label[objects]
    dist, _ = index.nearest(a[:, None] * z[objects] + b[:, None], labels, index.density)
    u = index.density[labels] * math.pi * dist**2
    nfa, _ = log10_nfa_curve(u, 4, log10_tests)
    return np.argsort(nfa, kind="stable")[:keep], nfa


def _index(rng, m, duplicates=0):
    """A clustered map of ``m`` objects of the first three labels (the fourth has none), some duplicated."""
    centres = rng.uniform(0, 3000, (6, 2))
    xy = centres[rng.integers(0, 6, m)] + rng.normal(0, 150, (m, 2))
    label = rng.choice(3, m, p=[0.6, 0.3, 0.1])
    if duplicates:
        xy[-duplicates:], label[-duplicates:] = xy[:duplicates], label[:duplicates]
    return ObjectIndex(Objects(xy[:, 0], xy[:, 1], label, np.full(m, np.nan), LABELS, "EPSG:32631"))


def _hypotheses(rng, index, h, n, k):
    """``h`` hypotheses over ``n`` image objects, ``k`` screened a quad: half near map objects, half anywhere."""
    z = rng.normal(0, 200, n) + 1j * rng.normal(0, 200, n)
    img_label = rng.choice(4, n, p=[0.5, 0.3, 0.15, 0.05]).astype(np.int64)
    a = rng.uniform(0.05, 0.5, h) * np.exp(1j * rng.uniform(-np.pi, np.pi, h))
    b = index.z[rng.integers(0, len(index), h)] + rng.normal(0, 20, h) + 1j * rng.normal(0, 20, h)
    b[::2] = rng.uniform(-5000, 8000, b[::2].size) + 1j * rng.uniform(-5000, 8000, b[::2].size)
    screen_of = np.stack([rng.permutation(n)[:k] for _ in range(n)]).astype(np.int64)
    img_ids = rng.integers(0, n, (h, 4)).astype(np.int64)
    return a, b, z, img_label, screen_of, img_ids


def _same(got, want):
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.array_equal(got, want, equal_nan=True), np.flatnonzero(got != want)[:10]


@pytest.mark.parametrize("seed", range(8))
def test_screen_matches_the_reference(seed):
    rng = np.random.default_rng(seed)
    index = _index(rng, int(rng.integers(50, 3000)), duplicates=int(rng.integers(0, 20)))
    h, n = int(rng.integers(1, 300)), int(rng.integers(5, 40))
    a, b, z, img_label, screen_of, img_ids = _hypotheses(rng, index, h, n, min(12, n))
    want_order, want = ref_screen(a, b, img_ids, screen_of, z, img_label, index, 3.2, 24)
    got = index.screen_nfa(a, b, z, screen_of[img_ids[:, 0]], img_label, 3.2)
    _same(got, want)
    assert np.isfinite(want).any()  # some hypotheses found objects: the comparison tested the queries
    _same(screen(a, b, img_ids, screen_of, z, img_label, index, 3.2, 24), want_order)


def test_screen_edges():
    rng = np.random.default_rng(1)
    # Duplicates and a lattice (ties of distance), an object exactly at the capped reach (300 m) of a sparse label.
    xy = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [300.0, 0.0], [5.0, 5.0]])
    index = ObjectIndex(Objects(xy[:, 0], xy[:, 1], np.array([0, 0, 0, 0, 0, 2, 1]), np.full(7, np.nan), LABELS,
                                "EPSG:32631"), bounds=(-1e5, -1e5, 1e5, 1e5))
    z = np.array([0, 5, 5j, 5 + 5j, 0, 1, 2, np.nan, 3j])
    img_label = np.array([0, 0, 0, 0, 2, 1, 3, 0, 0])
    screen_of = np.stack([np.roll(np.arange(9), -i) for i in range(9)])
    a = np.array([1.0, 1j, 2.0, 1.0 + 0j])
    b = np.array([0j, 5 + 5j, -1e9, np.inf])
    img_ids = np.array([[0, 1, 2, 3], [4, 1, 2, 3], [5, 1, 2, 3], [8, 1, 2, 3]])
    want = ref_screen(a, b, img_ids, screen_of, z, img_label, index, 1.0, 2)[1]
    _same(index.screen_nfa(a, b, z, screen_of[img_ids[:, 0]], img_label, 1.0), want)
    assert np.isfinite(want[:2]).all() and want[2] == want[3]  # matched rows; rows matching nothing alike
    # One row; four or fewer objects a quad (no trials: inf); no hypotheses.
    _same(index.screen_nfa(a[:1], b[:1], z, screen_of[:1], img_label, 1.0),
          ref_screen(a[:1], b[:1], img_ids[:1], screen_of, z, img_label, index, 1.0, 2)[1])
    _same(index.screen_nfa(a, b, z, screen_of[img_ids[:, 0], :4], img_label, 1.0),
          ref_screen(a, b, img_ids, screen_of[:, :4], z, img_label, index, 1.0, 2)[1])
    _same(index.screen_nfa(a[:0], b[:0], z, screen_of[:0], img_label, 1.0), np.zeros(0))
    # An empty map: nothing found anywhere.
    empty = ObjectIndex(Objects.empty(LABELS))
    _same(empty.screen_nfa(a, b, z, screen_of[img_ids[:, 0]], img_label, 1.0),
          ref_screen(a, b, img_ids, screen_of, z, img_label, empty, 1.0, 2)[1])
    del rng


def test_screen_kernel_refuses_wrong_calls():
    index = ObjectIndex(Objects.from_names([0.0, 10.0, 20.0], [0.0, 0.0, 5.0], ["b", "b", "p"]))
    tree = index.tree._tree()
    a, b, z = np.ones(2, complex), np.zeros(2, complex), np.arange(6, dtype=complex)
    objects, labels = np.zeros((2, 6), np.int64), np.zeros(6, np.int64)
    reach, dens = index._label_reach(), index.density

    def call(**kw):
        args = dict(a=a, b=b, z=z, objects=objects, labels=labels, reach=reach, dens=dens, ns=4, nfa=np.empty(2))
        args.update(kw)
        _kernel.verify_screen(*tree, args["a"], args["b"], args["z"], args["objects"], args["labels"], args["reach"],
                              args["dens"], 1e6, args["ns"], 0.0, -300.0, args["nfa"])
        return args["nfa"]

    assert np.isfinite(call()).all()
    with pytest.raises(ValueError, match="objects holds"):
        call(objects=np.full((2, 6), 6, np.int64))
    with pytest.raises(ValueError, match="img_label holds"):
        call(labels=np.full(6, 2, np.int64))
    with pytest.raises(ValueError, match="n_sample"):
        call(ns=6)
    with pytest.raises(ValueError):
        call(nfa=np.empty(3))
    with pytest.raises(ValueError):
        call(b=np.zeros(3, complex))
    with pytest.raises(TypeError):
        call(objects=objects.astype(np.int32))
    with pytest.raises(TypeError):
        call(a=a.real.copy())


# ---------------------------------------------------------------- the decision on points, fused


def ref_decision_nfa(a, b, img_ids, map_z, z, img_label, index, density, log10_tests, local_neighbours=0,
                     evidence=None, area_radius=None, near=None):
    # main at 28ca4ba, mapdb/match/verify.py: decision_nfa (its body, evidence None or plain)
    h, n = len(a), z.size
    w = a[:, None] * z[None, :] + b[:, None] if evidence is None else evidence.project(a, b, z)
    r2, share, from_sample = (evidence or _POINTS).residuals(w, a, b, img_ids, map_z, z, img_label, index, density,
                                                             area_radius, near)
    lam = density[:, img_label] if density.ndim > 1 else density[img_label][None, :]
    if local_neighbours:
        lam = np.maximum(lam, index.knn_density(w, img_label, local_neighbours, near=near))
    u = (lam if isinstance(share, float) and share == 1.0 else lam * share) * math.pi * r2
    shape = np.empty((h, n))
    sample = np.empty((h, n), bool)
    quad_tolerance(np.ascontiguousarray(z, np.complex128), np.ascontiguousarray(img_ids, np.int64), shape, sample)
    nfa, _ = log10_nfa_curve(u, 4, log10_tests, shape=shape, sample=sample)
    return nfa + from_sample


def _quads(rng, index, h, n):
    """``h`` hypotheses from quads of image objects: the quad's projections land on map objects (their map points)
    for half of them, anywhere for the rest."""
    a, b, z, img_label, _, _ = _hypotheses(rng, index, h, n, 5)
    img_ids = np.stack([rng.permutation(n)[:4] for _ in range(h)]).astype(np.int64)
    map_z = a[:, None] * z[img_ids] + b[:, None]
    snap = index.z[index.nearest(map_z, img_label[img_ids], index.density)[1].clip(0)]
    map_z[::2] = snap[::2]  # at map objects: the exclusion is exercised
    return a, b, z, img_label, img_ids, map_z


@pytest.mark.parametrize("seed", range(8))
def test_decision_matches_the_reference(seed):
    rng = np.random.default_rng(100 + seed)
    index = _index(rng, int(rng.integers(50, 3000)), duplicates=int(rng.integers(0, 20)))
    h, n = int(rng.integers(1, 40)), int(rng.integers(5, 40))
    a, b, z, img_label, img_ids, map_z = _quads(rng, index, h, n)
    near = index.neighbours(a[:, None] * z[None, :] + b[:, None], img_label, 6)
    radius = rng.uniform(50, 800, h)
    density = index.local_density(b, radius)
    for dens, local in ((index.density, 0), (density, 6), (density, 0), (index.density, 6)):
        want = ref_decision_nfa(a, b, img_ids, map_z, z, img_label, index, dens, 2.5, local, None, radius, near)
        got = decision_nfa(a, b, img_ids, map_z, z, img_label, index, dens, 2.5, local, None, radius, near)
        _same(got, want)
        assert np.isfinite(want).any()
        # The same without the neighbours: the index's own queries.
        _same(decision_nfa(a, b, img_ids, map_z, z, img_label, index, dens, 2.5, local, None, radius), want)


def test_decision_edges():
    # Duplicates at a quad's map point (one excluded, its twin not), ties, NaN, too few objects, one row.
    xy = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [300.0, 0.0], [5.0, 5.0]])
    index = ObjectIndex(Objects(xy[:, 0], xy[:, 1], np.array([0, 0, 0, 0, 0, 2, 1]), np.full(7, np.nan), LABELS,
                                "EPSG:32631"), bounds=(-1e5, -1e5, 1e5, 1e5))
    z = np.array([0, 10, 10j, 10 + 10j, 5 + 5j, 300, 2, np.nan, 3j])
    img_label = np.array([0, 0, 0, 0, 1, 2, 3, 0, 0])
    a = np.array([1.0 + 0j, 1.0, 1j, 1e-9])
    b = np.array([0j, 0.5, 3 + 1j, 1e9])
    img_ids = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [0, 2, 4, 6], [5, 6, 7, 8]])
    map_z = a[:, None] * z[img_ids] + b[:, None]
    near = index.neighbours(a[:, None] * z[None, :] + b[:, None], img_label, 6)
    dens = index.local_density(b, np.full(4, 100.0))
    for rows in (slice(None), slice(0, 1)):
        args = (a[rows], b[rows], img_ids[rows], map_z[rows], z, img_label, index)
        near_rows = near.take(np.arange(4)[rows])
        for d, local in ((index.density, 0), (dens[rows], 6)):
            want = ref_decision_nfa(*args, d, 1.0, local, None, None, near_rows)
            _same(decision_nfa(*args, d, 1.0, local, near=near_rows), want)
    short = index.neighbours(a[:, None] * z[None, :4] + b[:, None], img_label[:4], 6)
    assert np.isinf(decision_nfa(a, b, img_ids % 4, map_z, z[:4], img_label[:4], index, index.density, 1.0,
                                 near=short)).all()


def test_decision_kernel_refuses_wrong_calls():
    index = ObjectIndex(Objects.from_names([0.0, 10.0, 20.0], [0.0, 0.0, 5.0], ["b", "b", "p"]))
    z = np.arange(6, dtype=complex)
    lab = np.zeros(6, np.int64)
    near = index.neighbours(z[None, :], lab, 3)
    ids, map_z = np.array([[0, 1, 2, 3]]), np.zeros((1, 4), complex)

    def call(**kw):
        args = dict(nd=near.dist, ni=near.index, k_first=3, ids=ids, lab=lab, dens=np.atleast_2d(index.density),
                    local=0, nfa=np.empty(1), ns=4)
        args.update(kw)
        _kernel.verify_decision(args["nd"], args["ni"], args["k_first"], index.z, map_z, args["ids"], z, args["lab"],
                                index.label_reach(index.density), args["dens"], index.counts, args["local"], 1e-6,
                                args["ns"], 0.0, -300.0, args["nfa"])
        return args["nfa"]

    assert call().shape == (1,)
    for kw, match in ((dict(k_first=4), "k_first"), (dict(local=4), "local"), (dict(ids=ids + 3), "img_ids"),
                      (dict(lab=lab + 2), "img_label"), (dict(ni=-near.index), "negative"), (dict(ns=6), "n_sample"),
                      (dict(dens=np.ones((2, 2))), "density"), (dict(nfa=np.empty(2)), "nfa")):
        with pytest.raises(ValueError, match=match):
            call(**kw)
    with pytest.raises(TypeError):
        call(ni=near.index.astype(np.int32))


# ---------------------------------------------------------------- label densities in discs, fused


def ref_local_density(self, centres, radius):
    # main at 28ca4ba, mapdb/match/mapobjects/object_index.py: ObjectIndex.local_density
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
        found = self.tree.count(w, codes, r)
        count[:, present] = np.maximum(found.reshape(h, present.size), 1)
    return count / area[:, None]


@pytest.mark.parametrize("seed", range(6))
def test_local_density_matches_the_reference(seed):
    rng = np.random.default_rng(200 + seed)
    index = _index(rng, int(rng.integers(20, 3000)), duplicates=int(rng.integers(0, 20)))
    h = int(rng.integers(1, 60))
    centres = index.z[rng.integers(0, len(index), h)] + rng.normal(0, 100, h) + 1j * rng.normal(0, 100, h)
    centres[::3] = rng.uniform(-3000, 6000, centres[::3].size) + 1j * rng.uniform(-3000, 6000, centres[::3].size)
    radius = rng.uniform(0, 2000, h)
    _same(index.local_density(centres, radius), ref_local_density(index, centres, radius))
    # A forest of runs (a paged index's trees) counts as one tree over them all.
    forest = Forest(len(LABELS))
    cut = np.sort(rng.integers(0, len(index), 3))
    for lo, hi in zip([0, *cut], [*cut, len(index)], strict=True):
        forest.add(index.z[lo:hi], index.label[lo:hi])
    index.tree = forest
    assert len(forest.trees) > 1
    _same(index.local_density(centres, radius), ref_local_density(index, centres, radius))


def test_local_density_edges():
    xy = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    index = ObjectIndex(Objects(xy[:, 0], xy[:, 1], np.array([0, 0, 0, 2]), np.full(4, np.nan), LABELS, "EPSG:32631"))
    # On the disc's edge (at most the radius counts), zero and NaN and huge radii, centres far off and not finite.
    centres = np.array([0j, 0j, 5 + 5j, 1e7 + 0j, np.nan + 0j, 0j, 0j])
    radius = np.array([10.0, 0.0, 7.0, 50.0, 10.0, np.nan, 1e300])
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        want = ref_local_density(index, centres, radius)
    _same(index.local_density(centres, radius), want)
    _same(index.local_density(0j, 10.0), ref_local_density(index, 0j, 10.0))
    empty = ObjectIndex(Objects.empty(LABELS))
    _same(empty.local_density(centres[2:4], radius[2:4]), ref_local_density(empty, centres[2:4], radius[2:4]))
    tree = index.tree._tree()
    out = np.empty((1, 4))
    args = (np.array([0j]), np.array([1.0]), _DISC, np.array(index.bounds), np.array([0, 2]), 1e6, out)
    _kernel.objects_density([tree], *args)
    with pytest.raises(TypeError):
        _kernel.objects_density([tree[:4]], *args)
    with pytest.raises(TypeError):
        _kernel.objects_density(5, *args)
    with pytest.raises(ValueError, match="present"):
        _kernel.objects_density([tree], *args[:4], np.array([4]), *args[5:])
    with pytest.raises(ValueError):
        _kernel.objects_density([tree], *args[:6], np.empty((2, 4)))
    with pytest.raises(ValueError, match="disc"):
        _kernel.objects_density([tree], args[0], args[1], _DISC[:0], *args[3:])


# ---------------------------------------------------------------- the refinement, fused


def ref_refine(a, b, z, img_label, index, density, log10_tests, iterations, evidence=None, map_z=None, near=None):
    # main at 28ca4ba, mapdb/match/verify.py: refine (flat ground: its terrain branches never taken here)
    previous = None
    terrain = None if evidence is None else evidence.terrain
    lam = (density[:, img_label] if density.ndim > 1 else density[img_label][None, :]) * math.pi
    for it in range(iterations + 1):
        w = a[:, None] * z[None, :] + b[:, None]
        dist, mid = index.nearest(w, img_label, density, near=near if it == 0 and terrain is None else None)
        u = lam * dist**2
        nfa, k_best = log10_nfa_curve(u, 4, log10_tests)
        inlier = refinement_inliers(u, dist, mid, k_best)
        if it == iterations:
            break
        if previous is not None and (previous[0] == inlier).all() and (previous[1] == mid).all():
            break
        previous = inlier, mid
        target = index.z[np.maximum(mid, 0)]
        a_new, b_new = fit_similarity_complex(z[None, :], target, inlier)
        ok = np.isfinite(a_new) & (inlier.sum(axis=1) >= 3)
        a = np.where(ok, a_new, a)
        b = np.where(ok, b_new, b)
    return a, b, nfa, inlier, mid, dist


def _near_truth(rng, index, h, n):
    """Image objects that are a similarity of map objects (with noise and a few strays), and hypotheses near it."""
    picks = rng.choice(len(index), n, replace=False) if n <= len(index) else rng.integers(0, len(index), n)
    a0 = 0.3 * np.exp(1j * rng.uniform(-np.pi, np.pi))
    b0 = index.z[picks].mean()
    z = (index.z[picks] - b0) / a0 + rng.normal(0, 1.0, n) + 1j * rng.normal(0, 1.0, n)
    z[: n // 5] += rng.normal(0, 300, n // 5)
    img_label = index.label[picks].copy()
    a = a0 * (1 + rng.normal(0, 0.01, h)) * np.exp(1j * rng.normal(0, 0.01, h))
    b = b0 + rng.normal(0, 5, h) + 1j * rng.normal(0, 5, h)
    b[::3] = index.z[rng.integers(0, len(index), b[::3].size)]  # elsewhere
    return a, b, z, img_label


def _same_all(got, want):
    for g, w in zip(got, want, strict=True):
        _same(np.asarray(g), np.asarray(w))


@pytest.mark.parametrize("seed", range(8))
def test_refine_matches_the_reference(seed):
    rng = np.random.default_rng(300 + seed)
    index = _index(rng, int(rng.integers(200, 3000)), duplicates=int(rng.integers(0, 20)))
    h, n = int(rng.integers(1, 12)), int(rng.integers(5, 30))
    a, b, z, img_label = _near_truth(rng, index, h, n)
    near = index.neighbours(a[:, None] * z[None, :] + b[:, None], img_label, 6)
    local = index.local_density(b, np.full(h, 600.0))
    for density in (index.density, local):
        for iterations in (0, 1, 2, 4):
            want = ref_refine(a, b, z, img_label, index, density, 2.0, iterations, near=near)
            _same_all(refine(a, b, z, img_label, index, density, 2.0, iterations, near=near), want)
            want = ref_refine(a, b, z, img_label, index, density, 2.0, iterations)
            _same_all(refine(a, b, z, img_label, index, density, 2.0, iterations), want)
            assert want[3].any()  # some inliers: the fits ran


def test_refine_edges():
    # Duplicates (ties), a lattice, NaN and far-off hypotheses, one row, too few objects for a curve (n <= 4).
    xy = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [20.0, 0.0], [5.0, 5.0]])
    index = ObjectIndex(Objects(xy[:, 0], xy[:, 1], np.array([0, 0, 0, 0, 0, 0, 1]), np.full(7, np.nan), LABELS,
                                "EPSG:32631"), bounds=(-1e4, -1e4, 1e4, 1e4))
    z = np.array([0, 10, 10j, 10 + 10j, 20, 5 + 5j, 3])
    img_label = np.array([0, 0, 0, 0, 0, 1, 3])
    a = np.array([1.0 + 0j, 1.0, np.nan, 1j])
    b = np.array([0j, 0.3 + 0.2j, 0j, 1e8])
    for rows in (slice(None), slice(0, 1)):
        for zz, lab in ((z, img_label), (z[:4], img_label[:4]), (z[:1], img_label[:1])):
            want = ref_refine(a[rows], b[rows], zz, lab, index, index.density, 1.0, 2)
            _same_all(refine(a[rows], b[rows], zz, lab, index, index.density, 1.0, 2), want)


def test_refine_kernel_refuses_wrong_calls():
    index = ObjectIndex(Objects.from_names([0.0, 10.0, 20.0], [0.0, 0.0, 5.0], ["b", "b", "p"]))
    tree = index.tree._tree()
    z, lab = np.arange(6, dtype=complex), np.zeros(6, np.int64)

    def call(**kw):
        args = dict(a=np.ones(2, complex), lab=lab, dens=np.atleast_2d(index.density), nd=None, ni=None,
                    inlier=np.empty((2, 6), bool), it=2)
        args.update(kw)
        _kernel.verify_refine(*tree, args["a"], np.zeros(2, complex), z, args["lab"], index.z,
                              index.label_reach(index.density), args["dens"], 1e6, args["it"], args["nd"], args["ni"],
                              0.0, -300.0, 3.5, np.empty(2), args["inlier"], np.empty((2, 6), np.int64),
                              np.empty((2, 6)))

    call()
    near = index.neighbours(z[None, :].repeat(2, axis=0), lab, 2)
    call(nd=near.dist, ni=near.index)
    for kw in (dict(lab=lab + 2), dict(dens=np.ones((3, 2))), dict(nd=near.dist), dict(ni=-near.index, nd=near.dist),
               dict(inlier=np.empty((2, 5), bool)), dict(it=-1), dict(a=np.ones(3, complex))):
        with pytest.raises(ValueError):
            call(**kw)
    with pytest.raises(TypeError):
        call(a=np.ones(2))
