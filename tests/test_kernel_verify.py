"""The kernel's per-image glue (mapdb/match/_kernel_verify.c) against the numpy code it replaced, kept here verbatim
as the reference: a refined hypothesis's error model (``refine.candidates``, ``evidence.relief.fit_with_relief``) and
the rivals' repeats (``rivals._shifted``).

Random inputs and the edges (ties, duplicates, inf/NaN, one row, a single point); the kernel reproduces numpy's
arithmetic step by step, so the answers must be identical, bit for bit.  Wrong calls raise TypeError/ValueError.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from mapdb.match import _kernel
from mapdb.match.evidence.points import fit_errors, residual_sigmas
from mapdb.match.refine import Candidate, candidates
from mapdb.match.rivals import _shifted

# ---------------------------------------------------------------- the numpy reference (main at 1441f0c)


def ref_prediction_variance_factor(src, at=0j, weights=None):
    src = np.asarray(src, dtype=np.complex128)
    w = np.ones(src.shape) if weights is None else np.asarray(weights, dtype=np.float64)
    n = w.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = (w * src).sum(axis=-1) / n
        spread = (w * np.abs(src - mu[..., None]) ** 2).sum(axis=-1)
        return 1.0 / n + np.abs(at - mu) ** 2 / spread


def ref_residual_sigma(dist):
    return float(residual_sigmas(np.asarray(dist, np.float64)[None, :], np.ones((1, np.size(dist)), bool))[0])


def ref_candidates(a, b, nfa, inlier, mid, dist, z, nfa_points=None):
    out = []
    for j in range(len(a)):
        k = int(inlier[j].sum())
        if not np.isfinite(a[j]) or k < 3:
            continue
        out.append(Candidate(
            a=complex(a[j]),
            b=complex(b[j]),
            log10_nfa=float(nfa[j]),
            inliers=k,
            sigma_axis_m=ref_residual_sigma(dist[j, inlier[j]]),
            variance_factor=float(ref_prediction_variance_factor(z[inlier[j]])),
            pairs=np.column_stack([np.flatnonzero(inlier[j]), mid[j, inlier[j]]]),
            log10_nfa_points=None if nfa_points is None else float(nfa_points[j]),
        ))
    return out


def ref_shifted(best, index, tolerance):
    mid = best.pairs[:, 1]
    if mid.size < 3:
        return np.zeros(0, np.complex128), np.zeros(0, np.complex128)
    p, lab = index.z[mid], index.label[mid]
    i0 = int(np.argmin(np.abs(p - best.b)))
    gap = np.abs(p - p[i0])
    gap[gap == 0.0] = np.inf
    i1 = int(np.argmin(gap))
    base = p[i1] - p[i0]
    step = p[None, :] - p[:, None]  # step[j, k]: from inlier j's map point to inlier k's
    j, k = np.nonzero((np.abs(np.abs(step) - abs(base)) <= tolerance) & (lab[:, None] == lab[i0])
                      & (lab[None, :] == lab[i1]))
    turn = step[j, k] / base
    return turn * best.a, turn * (best.b - p[i0]) + p[j]


# ---------------------------------------------------------------- inputs


def _rows(rng, h, n, scale=300.0):
    z = (rng.uniform(-scale, scale, n) + 1j * rng.uniform(-scale, scale, n)).astype(np.complex128)
    dist = rng.exponential(2.0, (h, n))
    inlier = rng.random((h, n)) < rng.uniform(0.3, 1.0, (h, 1))
    return z, dist, inlier


def _same(x, y):
    """Bit-identical floats (NaN equal to NaN)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return x.shape == y.shape and bool(np.all((x == y) | (np.isnan(x) & np.isnan(y))))


def _same_candidates(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert (g.a, g.b, g.log10_nfa, g.inliers, g.log10_nfa_points) == (w.a, w.b, w.log10_nfa, w.inliers,
                                                                           w.log10_nfa_points)
        assert _same(g.sigma_axis_m, w.sigma_axis_m) and _same(g.variance_factor, w.variance_factor)
        assert g.pairs.dtype == w.pairs.dtype and np.array_equal(g.pairs, w.pairs)


# ---------------------------------------------------------------- error model


@pytest.mark.parametrize("seed", range(6))
def test_fit_errors_match_the_reference_on_random_rows(seed):
    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 4, 7, 8, 9, 16, 17, 33, 70):
        z, dist, inlier = _rows(rng, 12, n, scale=float(10.0 ** rng.uniform(-2, 4)))
        sigma, variance = fit_errors(z, dist, inlier)
        for j in range(len(dist)):
            k = int(inlier[j].sum())
            if k == 0:
                continue
            assert _same(sigma[j], ref_residual_sigma(dist[j, inlier[j]]))
            assert _same(variance[j], ref_prediction_variance_factor(z[inlier[j]]))


def test_fit_errors_on_the_edges():
    z = np.array([1 + 1j, 1 + 1j, 1 + 1j, 2 - 1j, np.nan, np.inf])  # duplicates, NaN, inf
    dist = np.array([[0.0, 1.0, np.inf, 2.0, 3.0, 0.5]] * 5)
    inlier = np.array([[1, 1, 1, 0, 0, 0],  # all one point: no spread
                       [1, 1, 1, 1, 0, 0],
                       [1, 1, 0, 1, 1, 0],  # a NaN point
                       [0, 1, 0, 1, 0, 1],  # an infinite point
                       [1, 0, 1, 1, 0, 0]], bool)  # an infinite residual
    sigma, variance = fit_errors(z, dist, inlier)
    for j in range(len(dist)):
        assert _same(sigma[j], ref_residual_sigma(dist[j, inlier[j]]))
        with np.errstate(invalid="ignore"):
            assert _same(variance[j], ref_prediction_variance_factor(z[inlier[j]]))
    empty = fit_errors(z, np.zeros((0, 6)), np.zeros((0, 6), bool))
    assert empty[0].shape == empty[1].shape == (0,)


def test_candidates_match_the_reference():
    rng = np.random.default_rng(7)
    for h, n in ((1, 6), (5, 8), (9, 20), (3, 40)):
        z, dist, inlier = _rows(rng, h, n)
        a = rng.standard_normal(h) + 1j * rng.standard_normal(h)
        a[0] = complex(np.nan, 1.0) if h > 2 else a[0]  # not finite: left out
        b = rng.standard_normal(h) * 1e3 + 1j * rng.standard_normal(h) * 1e3
        nfa, points = rng.uniform(-20, 5, h), rng.uniform(-20, 5, h)
        mid = rng.integers(0, 500, (h, n))
        inlier[-1, 2:] = False  # two inliers: left out
        for given in (None, points):
            _same_candidates(candidates(a, b, nfa, inlier, mid, dist, z, given),
                             ref_candidates(a, b, nfa, inlier, mid, dist, z, given))
    assert candidates(np.zeros(0, complex), np.zeros(0, complex), np.zeros(0), np.zeros((0, 5), bool),
                      np.zeros((0, 5), np.int64), np.zeros((0, 5)), np.zeros(5, complex)) == []


def test_fit_errors_refuse_wrong_calls():
    z, dist, inlier = _rows(np.random.default_rng(0), 3, 5)
    out = np.empty(3)
    with pytest.raises(ValueError):
        fit_errors(z, dist, inlier[:, :4])
    with pytest.raises(ValueError):
        fit_errors(z[:4], dist, inlier)
    with pytest.raises(TypeError):
        _kernel.verify_errors(z.real.copy(), dist, inlier, out, out.copy())
    with pytest.raises(ValueError):
        _kernel.verify_errors(z, dist, inlier, np.empty(2), out)
    with pytest.raises(TypeError):
        _kernel.verify_errors(z, dist, inlier, out)


# ---------------------------------------------------------------- rivals' repeats


def _lattice_case(rng, m, step=10.0, labels=2, jitter=0.0):
    """A winner's inliers on a lattice (repeats everywhere), with ties and duplicates of distance."""
    ix = rng.integers(-4, 5, m) + 1j * rng.integers(-4, 5, m)
    p = ix * step + jitter * (rng.standard_normal(m) + 1j * rng.standard_normal(m))
    index = SimpleNamespace(z=np.concatenate([p, [0j]]), label=rng.integers(0, labels, m + 1).astype(np.int64))
    best = SimpleNamespace(a=complex(rng.standard_normal(), rng.standard_normal()) * 0.5,
                           b=complex(rng.uniform(-20, 20), rng.uniform(-20, 20)),
                           pairs=np.column_stack([np.arange(m), np.arange(m)]))
    return best, index


@pytest.mark.parametrize("seed", range(8))
def test_shifted_matches_the_reference(seed):
    rng = np.random.default_rng(seed)
    for m in (3, 4, 9, 25, 60):
        for jitter, tolerance in ((0.0, 0.0), (0.0, 1e-9), (0.7, 1.5), (2.0, 0.3)):
            best, index = _lattice_case(rng, m, labels=int(rng.integers(1, 4)), jitter=jitter)
            got, want = _shifted(best, index, tolerance), ref_shifted(best, index, tolerance)
            assert all(_same(g.real, w.real) and _same(g.imag, w.imag) for g, w in zip(got, want))


@pytest.mark.parametrize("seed", range(4))
def test_shifted_at_the_tolerance_boundary(seed):
    # The kernel skips a pair by its squared distance before the exact test: pairs exactly at reach +- tolerance
    # (a lattice's steps of 0, 1, sqrt 2, 2 ... spacings, tolerances landing on them) and off the plane must still
    # be decided by the exact test, as the reference decides them.
    rng = np.random.default_rng(seed)
    for tolerance in (0.0, 10.0, 10.0 * math.sqrt(2.0) - 10.0, 20.0, 10.0 * math.sqrt(5.0) - 10.0, 1e300, -1.0):
        best, index = _lattice_case(rng, 30, labels=1 + seed % 2)
        if seed == 3:
            index.z[4] = complex(math.inf, 0.0)
        with np.errstate(invalid="ignore"):
            got, want = _shifted(best, index, tolerance), ref_shifted(best, index, tolerance)
        assert got[0].size == want[0].size
        assert all(_same(g.real, w.real) and _same(g.imag, w.imag) for g, w in zip(got, want))


def test_shifted_edges():
    rng = np.random.default_rng(3)
    best, index = _lattice_case(rng, 2)
    assert [v.size for v in _shifted(best, index, 1.0)] == [0, 0]  # fewer than three inliers
    best, index = _lattice_case(rng, 5)
    index.z[:5] = 3 + 4j  # every inlier on one map point: no second point, nothing repeats
    with np.errstate(invalid="ignore"):
        for got, want in zip(_shifted(best, index, 1.0), ref_shifted(best, index, 1.0)):
            assert _same(got.real, want.real) and _same(got.imag, want.imag)
    best, index = _lattice_case(rng, 6)
    index.z[2] = complex(math.nan, 0.0)
    with np.errstate(invalid="ignore"):
        for got, want in zip(_shifted(best, index, 1.0), ref_shifted(best, index, 1.0)):
            assert _same(got.real, want.real) and _same(got.imag, want.imag)


def test_shifted_refuses_wrong_calls():
    p = np.array([0j, 1 + 0j, 2j])
    lab = np.zeros(3, np.int64)
    out = np.empty(9, complex)
    with pytest.raises(ValueError):
        _kernel.verify_shifted(p, lab, 1j, 0j, 1.0, np.empty(8, complex), out)
    with pytest.raises(ValueError):
        _kernel.verify_shifted(p[:0], lab[:0], 1j, 0j, 1.0, out[:0], out[:0])
    with pytest.raises(TypeError):
        _kernel.verify_shifted(p, lab.astype(np.float64), 1j, 0j, 1.0, out, out.copy())
    with pytest.raises(TypeError):
        _kernel.verify_shifted(p, lab, "a", 0j, 1.0, out, out.copy())
    assert _kernel.verify_shifted(p, lab, 1j, 0j, 1.0, out, out.copy()) >= 0
