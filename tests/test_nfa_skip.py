"""The shaped NFA curve's thresholds skipped (mapdb/match/_kernel_nfa.c: nfa_shaped_row) give the bits of the curve
with every threshold formed.

The kernel forms every threshold of every row, in order, when any chance of the array is NaN (numpy's second form
for the whole array): a row of NaN residuals appended to an array makes the kernel answer the other rows that way,
so the same rows with and without it must agree bit for bit, minimum and index.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.match._kernel import nfa_curve
from mapdb.match.nfa import LOG10_FLOOR


def _curve(u: np.ndarray, shape: np.ndarray, sample: np.ndarray | None, ns: int,
           offset: float) -> tuple[np.ndarray, np.ndarray]:
    nfa, best = np.empty(len(u)), np.empty(len(u), np.int64)
    nfa_curve(np.ascontiguousarray(u), np.ascontiguousarray(shape), sample, ns, offset, LOG10_FLOOR, nfa, best)
    return nfa, best


def assert_skips_exact(u: np.ndarray, shape: np.ndarray, sample: np.ndarray | None, ns: int = 4,
                       offset: float = 3.5) -> None:
    h, n = u.shape
    skipped = _curve(u, shape, sample, ns, offset)
    full_u = np.vstack([u, np.full((1, n), np.nan)])
    full_shape = np.vstack([shape, np.ones((1, n))])
    full_sample = None if sample is None else np.vstack([sample, sample[:1]])
    full = _curve(full_u, full_shape, full_sample, ns, offset)
    # the NaN row: numpy's second form reads its NaN chances as 1, tails of 1
    assert full[0][h] == offset or not np.isfinite(offset)
    np.testing.assert_array_equal(skipped[0].view(np.int64), full[0][:h].view(np.int64))
    np.testing.assert_array_equal(skipped[1], full[1][:h])


def _sample(rng: np.random.Generator, h: int, n: int, s: int) -> np.ndarray:
    sample = np.zeros((h, n), bool)
    for r in range(h):
        sample[r, rng.choice(n, s, replace=False)] = True
    return sample


def test_random_rows_inliers_and_outliers() -> None:
    rng = np.random.default_rng(31)
    for _ in range(150):
        h, n = int(rng.integers(1, 10)), int(rng.integers(5, 90))
        # inliers at a small scale, outliers up to a few, some unmatched: the curve's minimum anywhere
        u = rng.exponential(1.0, (h, n)) * rng.choice([1e-6, 1e-4, 1e-2, 0.3, 1.0, 3.0], size=(h, 1))
        out = rng.random((h, n)) < rng.uniform(0.0, 0.6)
        u[out] = rng.uniform(0.0, 3.0, int(out.sum()))
        u[rng.random((h, n)) < 0.1] = np.inf
        shape = 1.25 + rng.exponential(2.0, (h, n))
        assert_skips_exact(u, shape, _sample(rng, h, n, 4), 4, float(rng.uniform(-2, 8)))
        assert_skips_exact(u, shape, None, 4)
        assert_skips_exact(u, shape, _sample(rng, h, n, 1), 1, 0.5)


def test_ties_floors_and_edges() -> None:
    rng = np.random.default_rng(32)
    n = 40
    cases = [
        np.zeros((2, n)),  # every threshold 0: ties everywhere, the lowest index kept
        np.full((2, n), 0.5),
        np.full((2, n), 1e-300),  # the curve at the floor for many thresholds: ties there
        np.full((2, n), np.inf),
        np.concatenate([np.full((2, n - 10), 1e-9), np.full((2, 10), 2.0)], axis=1),
        np.round(rng.exponential(0.01, (3, n)), 3),  # repeated values
    ]
    for u in cases:
        shape = np.full(u.shape, 1.25)
        assert_skips_exact(u, shape, _sample(rng, *u.shape, 4))
        assert_skips_exact(u, 1.25 + rng.random(u.shape), None)
    u = rng.exponential(1e-3, (2, n))
    for offset in (np.inf, -np.inf, 0.0, 1e300):
        assert_skips_exact(u, np.full(u.shape, 2.0), None, 4, offset)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_rows_that_cannot_skip_beside_rows_that_can() -> None:
    rng = np.random.default_rng(33)
    u = rng.exponential(1e-3, (4, 30))
    shape = 1.25 + rng.random(u.shape)
    shape[1, 5] = np.inf  # a shape not finite: that row forms every threshold
    u[2, 7] = -0.5  # a negative residual: thresholds below 0 are formed
    assert_skips_exact(u, shape, None)


def test_long_rows() -> None:
    rng = np.random.default_rng(34)
    u = rng.exponential(1e-4, (2, 600))
    u[:, 500:] = rng.uniform(0.5, 3.0, (2, 100))
    assert_skips_exact(u, 1.25 + rng.exponential(1.0, u.shape), _sample(rng, 2, 600, 4))
