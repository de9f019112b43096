"""The compiled kernel (mapdb/match/_kernel.c) against the numpy code it replaced, kept here verbatim as the reference.

Random inputs and the edges (inf, NaN, empty, one row, ties).  Where the numpy code used only sums, products,
quotients and square roots, the kernel repeats numpy's arithmetic (pairwise sums, its complex product and
quotient) and the answers must be identical; where it used ``expm1`` and ``log10``, numpy may take them from a
SIMD library (SVML on AVX-512 machines) that differs from the C library's by an ulp, so the log10 NFA must agree
to 1e-12; and the complex products numpy fuses on x86-64 with AVX2 (the kernel always does) agree to 1e-12
relative where numpy does not fuse them.  The binomial tail is the kernel's own sum, not numpy's betainc: the
NFA curve agrees with the reference where betainc's tail lies above 1e-250, and with exact rational arithmetic in
the rows reaching below it (where betainc loses digits and, below about 1e-275, underflows early).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from fractions import Fraction
from math import comb

import numpy as np
import pytest

from mapdb._scipy import betainc
from mapdb.match import _kernel
from mapdb.match.evidence.points import GATE_SIGMAS, first_per_map_object, refinement_inliers, residual_sigmas
from mapdb.match.geometry import fit_similarity_complex
from mapdb.match.mapobjects.object_index import ObjectIndex
from mapdb.match.nfa import log10_nfa_curve
from mapdb.objects import Objects

# ---------------------------------------------------------------- the numpy reference (main at 5144dec's successor)

_LOG10_FLOOR = -300.0


def ref_log10_nfa_curve(u, n_sample, log10_tests, shape=None, sample=None):
    u = np.asarray(u, dtype=np.float64)
    h, n = u.shape
    trials = n - n_sample
    if h == 0 or trials <= 0:
        return np.full(h, np.inf), np.zeros(h, dtype=np.int64)
    successes = np.arange(1, trials + 1, dtype=np.float64)
    failures, log10_trials = trials - successes + 1.0, np.log10(trials)
    if sample is not None:
        u = np.where(sample, -1.0, u)
    p = ref_trial_chances(u, n_sample, shape)
    with np.errstate(divide="ignore"):
        tail = np.log10(betainc(successes, failures, np.minimum(np.maximum(p, 0.0), 1.0)))
    curve = log10_tests + log10_trials + np.maximum(tail, _LOG10_FLOOR)
    best = curve.argmin(axis=1)
    return curve[np.arange(h), best], best + 1 + n_sample


def ref_trial_chances(u, n_sample, shape):
    if shape is None:
        u_sorted = np.sort(u, axis=1)[:, n_sample:]
        with np.errstate(over="ignore", invalid="ignore"):
            p = -np.expm1(-u_sorted)
        return np.where(np.isfinite(u_sorted), p, 1.0)
    shape = np.asarray(shape, dtype=np.float64)
    if shape.shape != u.shape:
        shape = np.broadcast_to(shape, u.shape)
    v = u / shape
    order = v.argsort(axis=1)
    rows = np.arange(len(v))[:, None]
    v_sorted = v[rows, order[:, n_sample:]]
    rest = shape[rows, order[:, n_sample:]]
    with np.errstate(over="ignore", invalid="ignore"):
        p = -(np.add.reduce(np.expm1(-v_sorted[:, :, None] * rest[:, None, :]), axis=2)
              / rest.shape[1])
    if np.isnan(p).any():
        chance = -np.expm1(-v_sorted[:, :, None] * rest[:, None, :])
        chance = np.where(np.isfinite(v_sorted)[:, :, None], chance, 1.0)
        p = np.nan_to_num(chance, nan=1.0).mean(axis=2)
    return p


def ref_fit_similarity_complex(src, dst, weights=None):
    src = np.asarray(src, dtype=np.complex128)
    dst = np.asarray(dst, dtype=np.complex128)
    w = np.ones(src.shape) if weights is None else np.asarray(weights, dtype=np.float64)
    wsum = w.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mu_s = (w * src).sum(axis=-1) / wsum
        mu_d = (w * dst).sum(axis=-1) / wsum
        s = src - mu_s[..., None]
        d = dst - mu_d[..., None]
        norm = (w * (s.real**2 + s.imag**2)).sum(axis=-1)
        a = (w * np.conj(s) * d).sum(axis=-1) / np.where(norm > 0, norm, np.nan)
    return a, mu_d - a * mu_s


def ref_residual_sigmas(dist, inlier):
    k = np.add.reduce(inlier, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.add.reduce(np.where(inlier, dist**2, 0.0), axis=1) / np.maximum(2 * k - 4, 1))


def ref_first_per_map_object(mid, dist, inlier):
    h, n = mid.shape
    keep = np.ones((h, n), bool)
    r, c = np.nonzero(inlier)
    if r.size == 0:
        return keep
    order = np.lexsort((dist[r, c], mid[r, c], r))
    r, c = r[order], c[order]
    dup = np.zeros(r.size, bool)
    dup[1:] = (r[1:] == r[:-1]) & (mid[r[1:], c[1:]] == mid[r[:-1], c[:-1]])
    keep[r[dup], c[dup]] = False
    return keep


def ref_refinement_inliers(u, dist, mid, k_best):
    """The body of main's refine loop between the NFA and the refit."""
    n = u.shape[1]
    rows = np.arange(len(u))
    u_sorted = np.sort(u, axis=1)
    u_cut = u_sorted[rows, np.minimum(np.maximum(k_best - 1, 0), n - 1)]
    finite = np.isfinite(dist)
    inlier = (u <= u_cut[:, None]) & finite
    sigma = ref_residual_sigmas(dist, inlier)
    inlier |= (dist <= GATE_SIGMAS * sigma[:, None]) & finite
    inlier &= ref_first_per_map_object(mid, dist, inlier)
    return inlier


def ref_first_allowed(z, d, i, reach, exclude, allowed=None):
    found = d <= reach[:, None]
    if exclude is not None:
        near = np.abs(z[np.minimum(i, len(z) - 1)][:, :, None] - exclude[:, None, :])
        found &= ~(near < 1e-6).any(axis=2)
    if allowed is not None:
        found &= allowed
    first = np.argmax(found, axis=1)
    pick = np.arange(d.shape[0])
    ok = found[pick, first]
    return np.where(ok, d[pick, first], np.inf), np.where(ok, i[pick, first], -1)


def ref_quad_tolerance(z, img_ids):
    """main's decision_nfa: the tolerance shapes of each quad's hypothesis and its sample mask."""
    h, n = len(img_ids), z.size
    zq = z[img_ids]
    mean = np.add.reduce(zq, axis=1) / zq.shape[1]
    spread = np.add.reduce(np.abs(zq - mean[:, None]) ** 2, axis=1)
    shape = 1.25 + np.abs(z[None, :] - mean[:, None]) ** 2 / spread[:, None]
    sample = np.zeros((h, n), bool)
    sample[np.arange(h)[:, None], img_ids] = True
    return shape, sample


# ---------------------------------------------------------------- inputs


def random_u(rng, h, n):
    """Normalised residuals as verification makes them: small for inliers, up to a few for chance, inf unmatched."""
    u = rng.exponential(1.0, (h, n)) * rng.choice([1e-4, 1e-2, 1.0, 3.0], size=(h, 1))
    u[rng.random((h, n)) < 0.2] = np.inf
    return u


def random_sample(rng, h, n, s):
    sample = np.zeros((h, n), bool)
    for r in range(h):
        sample[r, rng.choice(n, s, replace=False)] = True
    return sample


# Below this log10 tail betainc loses digits and, below about 1e-275, underflows early (to 0, read as the floor):
# rows of the reference reaching below it are computed again in exact rational arithmetic.
_BETAINC_TRUSTED = -250.0


def assert_nfa_agrees(u, n_sample, log10_tests=2.0, shape=None, sample=None):
    """The kernel's curve minimum is numpy's, or exact arithmetic's in the rows where betainc's tail is not trusted."""
    want, k_want = ref_log10_nfa_curve(u, n_sample, log10_tests, shape, sample)
    got, k_got = log10_nfa_curve(u, n_sample, log10_tests, shape=shape, sample=sample)
    deep = deep_rows(u, n_sample, shape, sample)
    if deep.any():
        want[deep], k_want[deep] = exact_nfa_curve(u, n_sample, log10_tests, shape, sample, deep)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(k_got, k_want)
    return deep


def ref_chances(u, n_sample, shape, sample):
    """The reference's chances of each row's trials, as its betainc reads them."""
    u = np.asarray(u, dtype=np.float64)
    if sample is not None:
        u = np.where(sample, -1.0, u)
    return np.minimum(np.maximum(ref_trial_chances(u, n_sample, shape), 0.0), 1.0)


def deep_rows(u, n_sample, shape, sample):
    """The rows whose reference tail (betainc's) reaches below ``_BETAINC_TRUSTED`` at some ``k``."""
    h, n = np.shape(u)
    trials = n - n_sample
    if h == 0 or trials <= 0:
        return np.zeros(h, bool)
    successes = np.arange(1, trials + 1, dtype=np.float64)
    with np.errstate(divide="ignore"):
        tail = np.log10(betainc(successes, trials - successes + 1.0, ref_chances(u, n_sample, shape, sample)))
    return (tail < _BETAINC_TRUSTED).any(axis=1)


def exact_nfa_curve(u, n_sample, log10_tests, shape, sample, rows):
    """The curve's minimum and its ``k`` in the rows picked, each tail in exact rational arithmetic."""
    p = ref_chances(u, n_sample, shape, sample)[rows]
    trials = p.shape[1]
    tail = np.array([[math.nan if math.isnan(c) else exact_log10_tail(trials, j + 1, float(c))
                      for j, c in enumerate(row)] for row in p])
    curve = log10_tests + np.log10(trials) + np.maximum(tail, _LOG10_FLOOR)
    best = curve.argmin(axis=1)
    return curve[np.arange(len(p)), best], best + 1 + n_sample


# ---------------------------------------------------------------- log10_nfa_curve


@pytest.mark.parametrize("shaped", [False, True])
def test_the_nfa_curve_agrees_with_numpy_s_on_random_hypotheses(shaped: bool) -> None:
    rng = np.random.default_rng(30)
    for _ in range(200):
        h, n = int(rng.integers(1, 12)), int(rng.integers(5, 45))
        u = random_u(rng, h, n)
        shape = 1.25 + 3 * rng.random((h, n)) if shaped else None
        sample = random_sample(rng, h, n, 4) if shaped else None
        assert_nfa_agrees(u, 4, 2.5, shape, sample)
        if shaped:
            assert_nfa_agrees(u, 4, 2.5, shape)  # the sample the smallest u / shape
            assert_nfa_agrees(u, 1, 0.5, shape, random_sample(rng, h, n, 1))  # the pose prior's one correspondence


def test_the_nfa_curve_at_its_edges() -> None:
    rng = np.random.default_rng(1)
    cases = [
        np.full((3, 8), np.inf),  # nothing matched
        np.zeros((2, 9)),  # ties: every object exactly on its map object
        np.full((1, 6), 0.5),  # one row of ties
        np.array([[np.nan, 0.1, 0.2, np.inf, 0.0, 0.3, np.nan, 1e-300]]),
        np.array([[1e-300, 1e-250, 1e-200, 1e-150, 1e-100, 1e-50, 1e-20, 1e-10]]),  # the floor of the tail
        random_u(rng, 1, 5),  # one trial
        np.zeros((0, 7)),  # no hypothesis
        random_u(rng, 4, 4),  # no trial: n == n_sample
        random_u(rng, 2, 2),
    ]
    for u in cases:
        assert_nfa_agrees(u, 4)
        if u.size and u.shape[1] > 4:
            assert_nfa_agrees(u, 4, shape=np.full(u.shape, 1.25), sample=random_sample(rng, *u.shape, 4))


def test_the_nfa_curve_keeps_the_tails_betainc_underflows_on() -> None:
    # 115 trials: 91 at a chance whose tail at k = 91 is 1e-299.07 (betainc gives 0 there), 24 far ones.
    p = 0.0002778737894631962
    u = np.concatenate([np.zeros(4), np.full(91, -math.log1p(-p)), np.full(24, 1.0)])[None]
    assert deep_rows(u, 4, None, None).all() and betainc(91, 25, p) == 0
    nfa, k = log10_nfa_curve(u, 4, 2.0)
    want = 2.0 + math.log10(115) + exact_log10_tail(115, 91, p)
    assert abs(nfa[0] - want) < 1e-12 and k[0] == 95
    assert nfa[0] > ref_log10_nfa_curve(u, 4, 2.0)[0][0] + 0.9  # numpy's curve read betainc's 0 as the floor
    # The same through the shaped path, and random rows reaching below 1e-250 against exact arithmetic.
    assert_nfa_agrees(u, 4, shape=np.ones(u.shape))
    rng = np.random.default_rng(9)
    deep = 0
    for _ in range(30):
        h, n = int(rng.integers(1, 4)), int(rng.integers(40, 80))
        u = rng.exponential(1.0, (h, n)) * 10.0 ** rng.uniform(-12, -6, (h, 1))
        u[rng.random((h, n)) < 0.1] = np.inf
        deep += int(assert_nfa_agrees(u, 4, 2.5).sum())
        deep += int(assert_nfa_agrees(u, 4, 2.5, 1.25 + rng.random((h, n)), random_sample(rng, h, n, 4)).sum())
    assert deep >= 20  # the comparison with exact arithmetic did take place


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's reference divides by zero there
def test_degenerate_shapes_take_numpy_s_second_form() -> None:
    # A zero or infinite tolerance shape makes NaN chances, which numpy recomputed for the whole array.
    rng = np.random.default_rng(2)
    u = random_u(rng, 5, 12)
    for bad in (0.0, np.inf):
        shape = 1.25 + rng.random(u.shape)
        shape[1, 3] = bad
        shape[4, 0] = bad
        assert_nfa_agrees(u, 4, shape=shape)
        assert_nfa_agrees(u, 4, shape=shape, sample=random_sample(rng, 5, 12, 4))


def test_a_broadcast_shape_is_the_full_one() -> None:
    rng = np.random.default_rng(3)
    u = random_u(rng, 6, 10)
    shape = 1.25 + rng.random((1, 10))
    assert_nfa_agrees(u, 4, shape=shape)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the reference's quad of one point repeated: 0 / 0
def test_the_decision_s_tolerance_shapes_are_numpy_s() -> None:
    rng = np.random.default_rng(7)
    cases = [(rng.normal(size=n) + 1j * rng.normal(size=n)) * 300 for n in rng.integers(4, 60, 100)]
    cases += [np.array([0, 1, 1j, 1 + 1j, np.inf, np.nan + 0j, 1e300 + 1e300j, 0])]  # inf, nan, overflow, ties
    for z in cases:
        ids = np.array([rng.choice(z.size, 4, replace=False) for _ in range(int(rng.integers(1, 30)))], np.int64)
        if z.size == 8:
            ids = np.vstack([ids, [[0, 7, 0, 7], [0, 1, 2, 3]]]).astype(np.int64)
        shape, sample = np.empty((len(ids), z.size)), np.empty((len(ids), z.size), bool)
        _kernel.quad_tolerance(z, ids, shape, sample)
        want_shape, want_sample = ref_quad_tolerance(z, ids)
        np.testing.assert_allclose(shape, want_shape, rtol=1e-14)  # bit-identical where numpy fuses as the kernel
        np.testing.assert_array_equal(sample, want_sample)


def exact_log10_tail(n: int, k: int, p: float) -> float:
    """log10 P(Binomial(n, p) >= k) in exact rational arithmetic (p as the double it is)."""
    chance = Fraction(p)
    tail = sum(comb(n, j) * chance**j * (1 - chance) ** (n - j) for j in range(k, n + 1))
    if tail == 0:
        return -math.inf
    digits = len(str(tail.denominator)) - len(str(tail.numerator))  # keep the ratio within float range
    return math.log10(float(tail * Fraction(10) ** digits)) - digits


def test_the_binomial_tail_is_exact_where_betainc_is_and_where_it_is_not() -> None:
    rng = np.random.default_rng(8)
    worst_exact = worst_betainc = 0.0
    for _ in range(150):
        n = int(rng.integers(1, 60))
        k = int(rng.integers(1, n + 1))
        p = float(10 ** rng.uniform(-12, 0)) if rng.random() < 0.7 else float(1 - 10 ** rng.uniform(-15, -0.3))
        got, exact = _kernel.tail_log10(n, k, p), exact_log10_tail(n, k, p)
        if exact > -300:
            worst_exact = max(worst_exact, abs(got - exact))
        if exact > -250:
            worst_betainc = max(worst_betainc, abs(got - float(np.log10(betainc(k, n - k + 1, p)))))
    assert worst_exact < 1e-12
    assert worst_betainc < 1e-12
    # Below about 1e-275 betainc underflows early (to 0 here, for a tail of 1e-299.07); the kernel keeps its value.
    p = 0.0002778737894631962
    assert abs(_kernel.tail_log10(115, 91, p) - exact_log10_tail(115, 91, p)) < 1e-12
    assert exact_log10_tail(115, 91, p) > -300 and betainc(91, 25, p) == 0
    assert _kernel.tail_log10(5, 1, 0.0) == -math.inf and _kernel.tail_log10(5, 5, 1.0) == 0.0
    assert math.isnan(_kernel.tail_log10(5, 2, math.nan))


# ---------------------------------------------------------------- refinement


def random_association(rng, h, n, labels=6):
    dist = rng.exponential(2.0, (h, n))
    dist[rng.random((h, n)) < 0.15] = np.inf
    mid = rng.integers(0, labels, (h, n)).astype(np.int64)
    mid[~np.isfinite(dist)] = -1
    dist[:, : n // 3] = np.round(dist[:, : n // 3])  # ties of distance
    u = 0.01 * dist**2
    return u, dist, mid


def test_the_refinement_inliers_are_numpy_s() -> None:
    rng = np.random.default_rng(4)
    for _ in range(300):
        h, n = int(rng.integers(1, 10)), int(rng.integers(1, 40))
        u, dist, mid = random_association(rng, h, n, labels=int(rng.integers(1, 2 * n + 2)))
        k_best = rng.integers(0, n + 2, h).astype(np.int64)
        np.testing.assert_array_equal(refinement_inliers(u, dist, mid, k_best),
                                      ref_refinement_inliers(u, dist, mid, k_best))
        inlier = rng.random((h, n)) < 0.6
        np.testing.assert_array_equal(residual_sigmas(dist, inlier), ref_residual_sigmas(dist, inlier))
        np.testing.assert_array_equal(first_per_map_object(mid, dist, inlier),
                                      ref_first_per_map_object(mid, dist, inlier))


def test_the_refinement_inliers_at_their_edges() -> None:
    one = np.array([[0.5]])
    for u, dist, mid in [
        (one, np.sqrt(one), np.zeros((1, 1), np.int64)),
        (np.full((2, 5), np.inf), np.full((2, 5), np.inf), np.full((2, 5), -1, np.int64)),
        (np.zeros((3, 6)), np.zeros((3, 6)), np.zeros((3, 6), np.int64)),  # every pair at one map object, tied
        (np.full((1, 70), 0.1), np.full((1, 70), 1.0), np.arange(70, dtype=np.int64)[None]),  # pairwise blocks
    ]:
        for k in (0, 1, u.shape[1]):
            k_best = np.full(len(u), k, np.int64)
            np.testing.assert_array_equal(refinement_inliers(u, dist, mid, k_best),
                                          ref_refinement_inliers(u, dist, mid, k_best))
    assert refinement_inliers(np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, 4), np.int64),
                              np.zeros(0, np.int64)).shape == (0, 4)


# ---------------------------------------------------------------- the similarity fit


def assert_fits_agree(src, dst, weights=None):
    want = ref_fit_similarity_complex(src, dst, weights)
    got = fit_similarity_complex(src, dst, weights)
    for g, w in zip(got, want):
        assert np.shape(g) == np.shape(w)
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-9)  # nan where numpy's is nan, inf where inf


def test_the_fit_agrees_with_numpy_s_on_random_sets() -> None:
    rng = np.random.default_rng(5)
    for t in range(300):
        h, k = int(rng.integers(1, 8)), int(rng.integers(2, 80))
        src = (rng.normal(size=(h, k)) + 1j * rng.normal(size=(h, k))) * rng.choice([1.0, 300.0, 2e4])
        dst = (0.9 - 0.4j) * src + (4e5 + 6e6j) + rng.normal(size=(h, k))
        weights = (rng.random((h, k)) < 0.7) if t % 3 else (rng.random((h, k)) if t % 2 else None)
        assert_fits_agree(src[0] if t % 5 == 0 else src, dst, weights)


def test_the_fit_at_its_edges() -> None:
    src = np.array([0, 1, 1j, 1 + 1j])
    assert_fits_agree(src, 2j * src + 5)  # one set: numpy scalars back
    assert_fits_agree(src[None], (2j * src + 5)[None], np.zeros((1, 4)))  # no weight: nan
    assert_fits_agree(np.zeros((2, 3), complex), np.ones((2, 3), complex))  # all source points equal: nan
    assert_fits_agree(np.zeros((2, 0), complex), np.zeros((2, 0), complex))  # no point
    assert_fits_agree(src[:1], src[:1])  # one point
    assert_fits_agree(np.array([[0, 1, np.inf]]), np.array([[0, 1, 2]]))  # inf and nan propagate
    assert_fits_agree(np.array([[0, 1, np.nan]]), np.array([[0, 1, 2]]))
    a, b = fit_similarity_complex(src, (1 - 1j) * src + 3)
    assert isinstance(a, np.complexfloating) and abs(complex(a) - (1 - 1j)) < 1e-12


# ---------------------------------------------------------------- the first allowed neighbour


def test_the_first_allowed_neighbour_is_numpy_s() -> None:
    rng = np.random.default_rng(6)
    objects = Objects.from_names(rng.random(50) * 100, rng.random(50) * 100, ["b"] * 50)
    index = ObjectIndex(objects)
    for t in range(100):
        m, k = int(rng.integers(1, 40)), int(rng.integers(1, 6))
        d = np.sort(rng.exponential(20.0, (m, k)), axis=1)
        i = rng.integers(0, len(index), (m, k)).astype(np.int64)
        d[:, -1][rng.random(m) < 0.3], i[:, -1][rng.random(m) < 0.3] = np.inf, len(index)  # missing neighbours
        reach = rng.random(m) * 40
        exclude = index.z[rng.integers(0, len(index), (m, 4))] if t % 2 else None
        allowed = rng.random((m, k)) < 0.7 if t % 3 == 0 else None
        got = index._first_allowed(d, i, reach, exclude, allowed)
        want = ref_first_allowed(index.z, d, i, reach, exclude, allowed)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        if exclude is not None and m % 2 == 0:  # one exclude row for each pair of queries
            half = exclude[::2]
            got = index._first_allowed(d, i, reach, half, allowed, repeat=2)
            want = ref_first_allowed(index.z, d, i, reach, np.repeat(half, 2, axis=0), allowed)
            np.testing.assert_array_equal(got[1], want[1])


# ---------------------------------------------------------------- a wrong call raises, never crashes


def test_wrong_calls_raise_type_or_value_errors() -> None:
    u = np.zeros((2, 6))
    nfa, best = np.empty(2), np.empty(2, np.int64)

    def curve(u=u, shape=None, sample=None, n_sample=4, nfa=nfa, best=best):
        _kernel.nfa_curve(u, shape, sample, n_sample, 0.0, -300.0, nfa, best)

    curve()  # the right call goes through
    with pytest.raises(TypeError):
        curve(u=u.astype(np.float32))
    with pytest.raises(TypeError):
        curve(u=[[0.0] * 6] * 2)
    with pytest.raises(TypeError):
        curve(sample=np.zeros((2, 6), np.int8))
    with pytest.raises(TypeError):
        curve(best=np.empty(2))
    with pytest.raises(ValueError, match="contiguous"):
        curve(u=np.zeros((6, 2)).T)
    with pytest.raises(ValueError, match="shape"):
        curve(nfa=np.empty(3))
    with pytest.raises(ValueError, match="shape"):
        curve(shape=np.ones((2, 5)))
    with pytest.raises(ValueError, match="shape"):
        curve(sample=np.zeros((1, 6), bool))
    with pytest.raises(ValueError, match="n_sample"):
        curve(n_sample=6)
    with pytest.raises(ValueError, match="n_sample"):
        curve(n_sample=-1)
    with pytest.raises(ValueError, match="writable"):
        frozen = np.empty(2)
        frozen.flags.writeable = False
        curve(nfa=frozen)
    with pytest.raises(ValueError, match="1-D"):
        curve(nfa=np.empty((2, 1)))
    with pytest.raises(TypeError):
        _kernel.fit_similarity(np.zeros((1, 3)), np.zeros((1, 3), complex), np.ones((1, 3)),
                               np.empty(1, complex), np.empty(1, complex))
    with pytest.raises(ValueError, match="exclude"):
        _kernel.first_allowed(np.zeros((4, 2)), np.zeros((4, 2), np.int64), np.ones(4), np.zeros(3, complex),
                              np.zeros((1, 2), complex), 2, None, np.empty(4), np.empty(4, np.int64))
    with pytest.raises(ValueError, match="negative"):
        _kernel.first_allowed(np.zeros((4, 2)), np.full((4, 2), -1, np.int64), np.ones(4), np.zeros(3, complex),
                              None, 1, None, np.empty(4), np.empty(4, np.int64))
    with pytest.raises(ValueError, match="k <= n"):
        _kernel.tail_log10(3, 4, 0.5)
    with pytest.raises(ValueError, match="img_ids"):
        _kernel.quad_tolerance(np.zeros(3, complex), np.array([[0, 1, 2, 3]]), np.empty((1, 3)),
                               np.empty((1, 3), bool))
    with pytest.raises(ValueError):
        log10_nfa_curve(np.zeros(5), 4, 1.0)
    with pytest.raises(ValueError):
        refinement_inliers(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 4), np.int64), np.zeros(2, np.int64))


def test_mapdb_help_does_not_load_the_kernel() -> None:
    code = textwrap.dedent("""
        import atexit, json, runpy, sys
        atexit.register(lambda: print(json.dumps(sorted(m for m in sys.modules if m.endswith("_kernel")))))
        sys.argv = ["mapdb", "--help"]
        runpy.run_module("mapdb_cli", run_name="__main__")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False).stdout
    assert "Usage: mapdb" in out
    assert json.loads(out.splitlines()[-1]) == []
