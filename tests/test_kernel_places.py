"""A round's places in the compiled kernel (mapdb/match/_kernel_places.c) against the numpy and Python code they
replaced, kept here verbatim as the reference: the shortlist (``places_shortlist``), the distinct places
(``places_chosen``, ``places_distinct`` through :func:`mapdb.match.refine.distinct`), the candidates' rows and pairs
(``places_pairs`` through :func:`mapdb.match.refine.candidates`), the labels' reach under a round's densities
(``places_reach`` through :meth:`~mapdb.match.mapobjects.object_index.ObjectIndex.label_reach`); and the fused round
(:func:`mapdb.match.screen._screened_fused`) against the general one on the same hypotheses.

Random inputs and the edges (ties, duplicate places, inf and NaN, one row, none); the answers must be identical, bit
for bit.
"""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from mapdb.match import screen as screen_module
from mapdb.match._kernel import places_chosen, places_distinct, places_pairs, places_reach, places_shortlist
from mapdb.match.evidence.image import ImageEvidence
from mapdb.match.evidence.points import fit_errors
from mapdb.match.hypotheses import Hypotheses
from mapdb.match.mapobjects.object_index import U_MAX, Neighbours, ObjectIndex, _flat_labels
from mapdb.match.options import FastOptions
from mapdb.match.refine import PLACE_FRACTION, Candidate, _paired, candidates, distinct
from mapdb.objects import Objects

LABELS = ["building", "tree", "pole", "absent"]
# inf and NaN among the inputs: numpy's products of them warn, as they did in the library
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")


def ref_distinct(b, order, separation, limit):
    # main at bc671ca, mapdb/match/refine.py: distinct
    chosen: list[int] = []
    places, apart = np.asarray(b).tolist(), np.asarray(separation).tolist()
    for i in np.asarray(order).tolist():
        if all(abs(places[i] - places[j]) > max(apart[i], apart[j]) for j in chosen):
            chosen.append(int(i))
            if len(chosen) >= limit:
                break
    return chosen


def ref_shortlist(nfa, hyps, z, img_label, shortlist):
    # main at bc671ca, mapdb/match/screen.py: _screened's shortlist and the projections its neighbours' query read
    hyps = hyps.take(nfa.argsort(kind="stable")[:shortlist])
    w = hyps.a[:, None] * z[None, :] + hyps.b[:, None]
    return hyps, w.ravel(), _flat_labels(img_label, w.shape)


def ref_chosen(nfa, hyps, near, diag_px, limit, factor):
    # main at bc671ca, mapdb/match/screen.py: _screened's distinct places and their density discs' radii
    chosen = ref_distinct(hyps.b, nfa.argsort(kind="stable"), np.abs(hyps.a) * diag_px * PLACE_FRACTION, limit)
    hyps = hyps.take(chosen)
    near = near.take(chosen)
    radius = factor * np.abs(hyps.a) * diag_px / 2.0
    return hyps, near, radius


def ref_candidates(a, b, nfa, inlier, mid, dist, z, nfa_points=None):
    # main at bc671ca, mapdb/match/refine.py: candidates
    inlier = np.ascontiguousarray(inlier, bool)
    counts = inlier.sum(axis=1)
    keep = (np.isfinite(a) & (counts >= 3)).nonzero()[0]
    if not keep.size:
        return []
    kept = inlier[keep]
    sigma, variance = fit_errors(z, dist[keep], kept)
    rows, cols = np.nonzero(kept)
    pairs = _paired(cols, mid[keep[rows], cols])
    ends = counts[keep].cumsum().tolist()
    points = None if nfa_points is None else nfa_points[keep].tolist()
    return [Candidate(a=a_j, b=b_j, log10_nfa=nfa_j, inliers=end - start, sigma_axis_m=sigma_j,
                      variance_factor=variance_j, pairs=pairs[start:end],
                      log10_nfa_points=None if points is None else points[j])
            for j, (a_j, b_j, nfa_j, sigma_j, variance_j, start, end) in enumerate(zip(
                a[keep].tolist(), b[keep].tolist(), nfa[keep].tolist(), sigma.tolist(), variance.tolist(),
                [0, *ends[:-1]], ends, strict=True))]


def _same(got, want):
    got, want = np.asarray(got), np.asarray(want)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes(), (got, want)


def _same_candidates(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert repr((g.a, g.b, g.log10_nfa, g.inliers, g.sigma_axis_m, g.variance_factor, g.log10_nfa_points)) == repr(
            (w.a, w.b, w.log10_nfa, w.inliers, w.sigma_axis_m, w.variance_factor, w.log10_nfa_points))
        _same(g.pairs, w.pairs)


def _edgy(rng, h, scale=1.0):
    """``h`` values with ties, duplicates, infinities and NaNs among them."""
    x = rng.normal(0, scale, h)
    if h > 3:
        x[rng.integers(0, h, 2)] = x[0]
        x[rng.integers(0, h)] = rng.choice([np.inf, -np.inf, np.nan])
    return x


def _hyps(rng, h, n, q=4):
    a = rng.uniform(0.05, 0.5, h) * np.exp(1j * rng.uniform(-np.pi, np.pi, h))
    b = 4.7e6 + rng.normal(0, 30, h) + 1j * rng.normal(0, 30, h)
    if h > 3:
        b[rng.integers(0, h)] = b[0]  # two hypotheses at one place
        a[rng.integers(0, h)] = complex(rng.choice([np.nan, np.inf]), 0.1)
    ids = rng.integers(0, n, (h, q)).astype(np.int64)
    return Hypotheses(a, b, ids, a[:, None] * rng.normal(0, 50, (h, q)) + b[:, None])


@pytest.mark.parametrize("seed", range(6))
def test_shortlist_matches_the_reference(seed):
    rng = np.random.default_rng(seed)
    for h in (0, 1, 2, 7, 16, 40, 300):
        n = int(rng.integers(1, 30))
        hyps, nfa = _hyps(rng, h, n), _edgy(rng, h)
        if seed % 2:
            nfa = np.round(nfa)  # many ties
        z = rng.normal(0, 300, n) + 1j * rng.normal(0, 300, n)
        z[rng.integers(0, n)] = complex(rng.choice([np.nan, np.inf, 0.0]), 1.0)
        img_label = rng.integers(0, 4, n).astype(np.int64)
        for shortlist in (0, 1, 16, 1000):
            want, w, labels = ref_shortlist(nfa, hyps, z, img_label, shortlist)
            m = min(shortlist, h)
            out = (np.empty(m, complex), np.empty(m, complex), np.empty((m, 4), np.int64), np.empty((m, 4), complex),
                   np.empty(m * n, complex), np.empty(m * n, np.int64))
            assert places_shortlist(nfa, hyps.a, hyps.b, hyps.img_ids, hyps.map_z, z, img_label, shortlist,
                                    *out) == m
            for got, ref in zip(out, (want.a, want.b, want.img_ids, want.map_z, w, labels), strict=True):
                _same(got, ref)


@pytest.mark.parametrize("seed", range(6))
def test_chosen_matches_the_reference(seed):
    rng = np.random.default_rng(10 + seed)
    for h in (1, 2, 5, 16, 60):
        n, k = int(rng.integers(1, 12)), int(rng.integers(1, 7))
        hyps, nfa = _hyps(rng, h, n), _edgy(rng, h)
        if seed % 2:
            nfa = np.round(nfa)
            hyps.b[:] = hyps.b[0] + np.round(hyps.b - hyps.b[0], -1)  # places on a 10 m lattice: distances tie
        near = Neighbours(rng.normal(0, 5, (h * n, k)), rng.integers(0, 99, (h * n, k)).astype(np.int64), (h, n))
        for diag_px, limit, factor in ((800.0, 4, 1.5), (1e-3, 3, 2.0), (1e4, 0, 1.5), (500.0, 1, 0.5)):
            want, want_near, want_radius = ref_chosen(nfa, hyps, near, diag_px, limit, factor)
            m = min(max(limit, 1), h)
            out = (np.empty(m, complex), np.empty(m, complex), np.empty((m, 4), np.int64), np.empty((m, 4), complex),
                   np.empty((m * n, k)), np.empty((m * n, k), np.int64), np.empty(m))
            c = places_chosen(nfa, hyps.a, hyps.b, hyps.img_ids, hyps.map_z, near.dist, near.index, n, diag_px,
                              PLACE_FRACTION, factor, limit, *out)
            assert c == len(want)
            refs = (want.a, want.b, want.img_ids, want.map_z, want_near.dist, want_near.index, want_radius)
            for got, ref in zip(out, refs, strict=True):
                _same(got[:c * n] if got.shape[0] == m * n and n > 1 else got[:c], ref)


def test_distinct_matches_the_plain_loop_on_edges():
    rng = np.random.default_rng(3)
    for _ in range(300):
        h = int(rng.integers(0, 25))
        b = 4.7e6 + _edgy(rng, h, 30) + 1j * _edgy(rng, h, 30)
        separation = rng.choice([5.0, 20.0, 0.0, np.nan, np.inf, rng.uniform(0, 40)], h)
        order = rng.permutation(h) if rng.uniform() < 0.8 else np.argsort(rng.normal(size=h), kind="stable")
        for limit in (-1, 0, 1, 4, 100):
            assert distinct(b, order, separation, limit) == ref_distinct(b, order, separation, limit)
    # Repeated rows of the order, real places.
    assert distinct(np.array([0.0, 1.0, 5.0]), np.array([2, 2, 0, 1]), np.ones(3), 4) == ref_distinct(
        np.array([0.0, 1.0, 5.0]), np.array([2, 2, 0, 1]), np.ones(3), 4) == [2, 0]


@pytest.mark.parametrize("seed", range(6))
def test_candidates_match_the_reference(seed):
    rng = np.random.default_rng(20 + seed)
    for h in (0, 1, 2, 4, 9):
        n = int(rng.integers(1, 15))
        a = rng.normal(0, 1, h) + 1j * rng.normal(0, 1, h)
        if h > 2:
            a[1] = complex(np.nan, 0.0)
            a[2] = complex(0.0, np.inf)
        inlier = rng.uniform(size=(h, n)) < rng.choice([0.2, 0.6, 1.0])
        mid = np.where(inlier, rng.integers(0, 500, (h, n)), -1).astype(np.int64)
        dist = np.where(inlier, rng.uniform(0, 3, (h, n)), np.inf)
        z = rng.normal(0, 100, n) + 1j * rng.normal(0, 100, n)
        nfa, points = rng.normal(0, 5, h), rng.normal(0, 5, h)
        b = rng.normal(0, 1e3, h) + 1j * rng.normal(0, 1e3, h)
        _same_candidates(candidates(a, b, nfa, inlier, mid, dist, z), ref_candidates(a, b, nfa, inlier, mid, dist, z))
        _same_candidates(candidates(a, b, nfa, inlier, mid, dist, z, points),
                         ref_candidates(a, b, nfa, inlier, mid, dist, z, points))
        # Not contiguous, not of the kernel's types (a Fortran-ordered mask, int32 ids).
        _same_candidates(candidates(a, b, nfa, np.asfortranarray(inlier), mid.astype(np.int32), dist, z),
                         ref_candidates(a, b, nfa, np.asfortranarray(inlier), mid.astype(np.int32), dist, z))


def ref_label_reach(density):
    # main at bc671ca, mapdb/match/mapobjects/object_index.py: ObjectIndex._reach of a 2-D density, every label
    return np.sqrt(U_MAX / (math.pi * np.min(density, axis=0)))


def test_label_reach_matches_the_reference():
    rng = np.random.default_rng(5)
    index = ObjectIndex(Objects.from_names([0.0, 10.0, 20.0], [0.0, 0.0, 5.0], ["b", "b", "p"]))
    for h in (1, 2, 4, 17):
        density = rng.uniform(1e-7, 1e-2, (h, 2)) * rng.choice([1.0, 1e-3, 1e3], (h, 2))
        density[rng.integers(0, h)] = density[0]  # ties
        _same(index.label_reach(density), ref_label_reach(density))
        if h > 1:
            density[rng.integers(0, h), rng.integers(0, 2)] = rng.choice([np.nan, np.inf])
            _same(index.label_reach(density), ref_label_reach(density))
            _same(index.label_reach(np.asfortranarray(density)), ref_label_reach(density))
    with pytest.raises(ValueError):
        ref_label_reach(np.zeros((0, 2)))
    with pytest.raises(ValueError):  # no rows: no minimum, as numpy said
        index.label_reach(np.zeros((0, 2)))


def test_places_kernel_refuses_wrong_calls():
    b, order, sep = np.zeros(3, complex), np.arange(3), np.ones(3)
    with pytest.raises(ValueError, match="order"):
        places_distinct(b, np.array([0, 3]), sep, 2, np.empty(2, np.int64))
    with pytest.raises(ValueError, match="order"):
        places_distinct(b, np.array([-1]), sep, 2, np.empty(2, np.int64))
    with pytest.raises(ValueError, match="out"):
        places_distinct(b, order, sep, 3, np.empty(2, np.int64))
    with pytest.raises(ValueError):
        places_distinct(b, order, np.ones(2), 3, np.empty(3, np.int64))
    with pytest.raises(TypeError):
        places_distinct(np.zeros(3), order, sep, 3, np.empty(3, np.int64))
    with pytest.raises(TypeError):
        places_distinct(b, order.astype(np.int32), sep, 3, np.empty(3, np.int64))
    hyps = _hyps(np.random.default_rng(0), 3, 5)
    z, lab = np.zeros(5, complex), np.zeros(5, np.int64)
    good = (np.empty(2, complex), np.empty(2, complex), np.empty((2, 4), np.int64), np.empty((2, 4), complex),
            np.empty(10, complex), np.empty(10, np.int64))
    args = (np.zeros(3), hyps.a, hyps.b, hyps.img_ids, hyps.map_z, z, lab)
    assert places_shortlist(*args, 2, *good) == 2
    with pytest.raises(ValueError):
        places_shortlist(*args, 3, *good)  # outputs of 2 rows for 3
    with pytest.raises(ValueError):
        places_shortlist(*args, -1, *good)
    with pytest.raises(ValueError):
        places_shortlist(np.zeros(4), *args[1:], 2, *good)
    with pytest.raises(TypeError):
        places_shortlist(*args[:5], np.zeros(5), lab, 2, *good)
    with pytest.raises(TypeError):
        places_shortlist(*args, 2, *good[:2], good[2].astype(np.int32), *good[3:])
    near_d, near_i = np.zeros((15, 2)), np.zeros((15, 2), np.int64)
    outs = (*good[:4], np.empty((10, 2)), np.empty((10, 2), np.int64), np.empty(2))
    cargs = (np.zeros(3), hyps.a, hyps.b, hyps.img_ids, hyps.map_z, near_d, near_i, 5, 800.0, PLACE_FRACTION, 1.5)
    assert 1 <= places_chosen(*cargs, 2, *outs) <= 2
    with pytest.raises(ValueError):
        places_chosen(*cargs[:7], 4, *cargs[8:], 2, *outs)  # neighbours of 3 x 5 read as 3 x 4
    with pytest.raises(ValueError):
        places_chosen(*cargs, 3, *outs)  # outputs of 2 rows for 3
    with pytest.raises(TypeError):
        places_chosen(*cargs[:5], near_d.astype(np.float32), *cargs[6:], 2, *outs)
    with pytest.raises(ValueError):
        places_reach(np.ones((2, 3)), U_MAX, np.empty(2))
    with pytest.raises(ValueError):
        places_reach(np.ones(3), U_MAX, np.empty(3))
    with pytest.raises(TypeError):
        places_reach(np.ones((2, 3), np.float32), U_MAX, np.empty(3))
    with pytest.raises(ValueError):
        places_pairs(hyps.a, np.zeros((3, 5), bool), np.zeros((3, 4), np.int64), np.empty(3, np.int64),
                     np.empty(3, np.int64), np.empty((15, 2), np.int64))
    with pytest.raises(TypeError):
        places_pairs(hyps.a, np.zeros((3, 5)), np.zeros((3, 5), np.int64), np.empty(3, np.int64),
                     np.empty(3, np.int64), np.empty((15, 2), np.int64))


def _scene(rng, m, n_seen, wrong):
    """A clustered map of ``m`` objects, an image of ``n_seen`` of them (1 m noise), and a round's hypotheses: the
    true pose from a few quads, nearby poses and ``wrong`` poses anywhere."""
    centres = rng.uniform(0, 3000, (6, 2))
    xy = centres[rng.integers(0, 6, m)] + rng.normal(0, 150, (m, 2))
    label = rng.choice(3, m, p=[0.6, 0.3, 0.1])
    xy[-5:], label[-5:] = xy[:5], label[:5]  # duplicate objects
    index = ObjectIndex(Objects(xy[:, 0], xy[:, 1], label, np.full(m, np.nan), LABELS, "EPSG:32631"))
    centre = complex(*xy[rng.integers(0, m)])
    a_true = 0.25 * np.exp(1j * rng.uniform(-np.pi, np.pi))
    seen = np.argsort(np.abs(index.z - centre))[:n_seen]
    z = (index.z[seen] - centre) / a_true + rng.normal(0, 1, n_seen) + 1j * rng.normal(0, 1, n_seen)
    img_label = index.label[seen].astype(np.int64)
    h = 6 + wrong
    img_ids = np.stack([rng.choice(n_seen, 4, replace=False) for _ in range(h)]).astype(np.int64)
    a = np.concatenate([np.full(3, a_true), a_true * (1 + rng.normal(0, 0.01, 3)),
                        0.25 * np.exp(1j * rng.uniform(-np.pi, np.pi, wrong))])
    b = np.concatenate([np.full(3, centre), centre + rng.normal(0, 3, 3) + 1j * rng.normal(0, 3, 3),
                        index.z[rng.integers(0, m, wrong)] + rng.normal(0, 30, wrong)])
    map_z = a[:, None] * z[img_ids] + b[:, None]
    map_z[:3] = index.z[seen[img_ids[:3]]]  # the true quads' own map points
    return index, Hypotheses(a, b, img_ids, map_z), z, img_label


@pytest.mark.parametrize("seed", range(6))
def test_fused_round_is_the_general_round(seed, monkeypatch):
    rng = np.random.default_rng(40 + seed)
    index, hyps, z, img_label = _scene(rng, int(rng.integers(200, 3000)), int(rng.integers(5, 40)),
                                       int(rng.integers(0, 300)))
    opts = FastOptions()
    screen_of = screen_module.screen_neighbours(z, opts)
    diag_px, tests = math.hypot(1000.0, 750.0), math.log10(len(hyps) + 1)
    fused = []
    for evidence in (None, ImageEvidence()):
        fused.append(screen_module._screened(hyps, None, z, img_label, index, screen_of, diag_px, tests, opts,
                                             evidence))
    assert index.fused() is not None
    monkeypatch.setattr(ObjectIndex, "fused", lambda self: None)  # the general path: the wrappers one by one
    general = screen_module._screened(hyps, None, z, img_label, index, screen_of, diag_px, tests, opts, None)
    for found in fused:
        _same_candidates(found, general)
    assert general and min(c.log10_nfa for c in general) < opts.log10_epsilon  # the right place was decided


def test_fused_arrays_follow_the_index():
    index = ObjectIndex(Objects.from_names([0.0, 10.0, 20.0], [0.0, 0.0, 5.0], ["b", "b", "p"]))
    first = index.fused()
    assert first is not None and index.fused() is first  # made once
    _same(first.reach, index.label_reach(index.density))
    index.density = index.density * 2.0  # replaced: made again
    again = index.fused()
    assert again is not first and again.density is index.density
    assert ObjectIndex(Objects.empty(["b"])).fused() is None
    copy = pickle.loads(pickle.dumps(index))  # pickled as before (the arrays are kept beside it), made again
    assert set(vars(copy)) == set(vars(index)) and copy.fused() is not None
    _same(copy.fused().reach, again.reach)
