"""The matcher stages' Python glue rewritten with fewer numpy calls, against the code it replaced, kept here verbatim
as the reference: the rivals' places (``rivals._places``: np.unique before) and the relief fit's radial and
tangential residuals (``evidence.relief.radial_excess``: numpy's wrappers before).  Random inputs and the edges (ties,
duplicates, NaN, signed zeros, one row); the answers must be identical.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from mapdb.match.evidence.relief import radial_excess
from mapdb.match.refine import PLACE_FRACTION, pose_shift
from mapdb.match.rivals import _places

# ---------------------------------------------------------------- the reference (main at 9b40c11)


def ref_elsewhere(a, b, best, diag_px):
    return pose_shift(a, b, best.a, best.b, diag_px) > abs(best.a) * diag_px * PLACE_FRACTION


def ref_places(a, b, best, diag_px):
    separation = abs(best.a) * diag_px * PLACE_FRACTION
    away = np.flatnonzero(ref_elsewhere(a, b, best, diag_px) & np.isfinite(b))
    if not away.size:
        return np.zeros(0, np.int64)
    turn = np.floor(np.angle(a[away] / best.a) / (np.pi / 6.0))
    cell = (np.floor(b[away].real / separation) * 2.0**24 + np.floor(b[away].imag / separation)) * 16.0 + turn
    _, first = np.unique(cell, return_index=True)
    return away[np.sort(first)]


def ref_radial_excess(src, dst, a, b):
    w = a * src + b
    radial = np.exp(1j * np.angle(a * src))  # unit vectors away from the nadir, in map metres
    q = (w - dst) * np.conj(radial)
    n = src.size
    if n <= 4:
        return q.real, q.imag, False
    ratio_limit = math.exp(2.33 * 2.0 / math.sqrt(n - 2))
    excess = bool(np.sum(q.real**2) > ratio_limit * max(float(np.sum(q.imag**2)), 1e-300))
    return q.real, q.imag, excess


# ---------------------------------------------------------------- the rivals' places


def _check(a, b, best, diag_px):
    got, ref = _places(a, b, best, diag_px), ref_places(a, b, best, diag_px)
    assert got.dtype == ref.dtype == np.int64
    np.testing.assert_array_equal(got, ref)
    return got


@pytest.mark.parametrize("seed", range(20))
def test_places_identical_to_the_reference(seed):
    rng = np.random.default_rng(seed)
    h = int(rng.integers(1, 300))
    best = SimpleNamespace(a=0.4 * np.exp(1j * rng.uniform(-3, 3)), b=complex(rng.uniform(0, 500), rng.uniform(0, 500)))
    # many poses a few places apart (repeats of a lattice), some at the winner's place, some turned
    a = best.a * np.exp(1j * rng.choice([0.0, np.pi / 2, np.pi / 6 + 1e-9, -np.pi], h)) * rng.choice([1.0, 1.01], h)
    b = best.b + rng.integers(-6, 7, h) * 17.0 + 1j * rng.integers(-6, 7, h) * 13.0 + rng.normal(0, 0.5, h)
    _check(a, b, best, 1200.0)


def test_places_edges():
    best = SimpleNamespace(a=0.5 + 0j, b=100 + 100j)
    diag = 1000.0
    far = 100 + 100j + 400.0
    # duplicates, non-finite positions and scales, signed zeros, a pose at the winner's place
    a = np.array([0.5, 0.5, 0.5, 0.5, np.nan, 0.5 + 0j, complex(0.5, -0.0), 0.5, np.inf, 0.5], np.complex128)
    b = np.array([far, far, far + 1e-9, np.nan, far, best.b, far - 400.0, -far, far, complex(np.inf, 0)],
                 np.complex128)
    got = _check(a, b, best, diag)
    assert got.tolist()[:1] == [0]  # the first of the duplicates kept
    _check(a[:1], b[:1], best, diag)  # one row
    _check(a[:0], b[:0], best, diag)  # none
    _check(np.full(3, np.nan + 0j), np.full(3, far), best, diag)  # NaN cells are one cell
    # signed zeros in the cells' coordinates: -0.0 and 0.0 are one cell
    zero = SimpleNamespace(a=1.0 + 0j, b=1000 + 1000j)
    _check(np.array([1.0, 1.0], np.complex128), np.array([complex(-0.0, 0.0), complex(0.0, -0.0)]), zero, 100.0)


# ---------------------------------------------------------------- the relief fit's residuals


def _same_residuals(src, dst, a, b):
    got, ref = radial_excess(src, dst, a, b), ref_radial_excess(src, dst, a, b)
    for g, r in zip(got[:2], ref[:2], strict=True):
        assert g.tobytes() == r.tobytes()  # bit for bit, NaN and signed zeros included
    assert got[2] is ref[2]
    return got


@pytest.mark.parametrize("seed", range(20))
def test_radial_excess_identical_to_the_reference(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 120))
    src = rng.uniform(-400, 400, n) + 1j * rng.uniform(-300, 300, n)
    a = complex(rng.uniform(0.1, 2) * np.exp(1j * rng.uniform(-np.pi, np.pi)))
    b = complex(rng.uniform(-1e5, 1e5), rng.uniform(-1e5, 1e5))
    relief = 1 + rng.uniform(0, 0.05, n) * (rng.random() < 0.5)  # radial displacements in half the cases
    dst = (a * src) * relief + b + rng.normal(0, 0.3, n) + 1j * rng.normal(0, 0.3, n)
    _same_residuals(src, dst, a, b)
    _same_residuals(src, dst, np.complex128(a), np.complex128(b))  # numpy scalars, as the fit hands them


def test_radial_excess_edges():
    src = np.array([0, 1, 1j, -1, -1j, 0, 2 + 2j], np.complex128)  # the nadir itself, a duplicate
    dst = src * 1.0
    _same_residuals(src, dst, 1.0 + 0j, 0j)  # an exact fit: no excess
    _same_residuals(src[:4], dst[:4] + 1, 1.0 + 0j, 0j)  # four points: never an excess
    _same_residuals(src[:1], dst[:1], 1.0 + 0j, 0j)  # one row
    _same_residuals(src[:0], dst[:0], 1.0 + 0j, 0j)  # none
    _same_residuals(src, dst, complex(-0.0, -0.0), complex(0.0, -0.0))  # signed zeros
    bad = dst.copy()
    bad[2] = complex(np.nan, 1.0)
    _same_residuals(src, bad, 1.0 + 0j, 0j)
    bad[3] = complex(np.inf, -np.inf)
    _same_residuals(src, bad, 1.0 + 0j, 0j)
    _same_residuals(src, dst, complex(np.inf, 0.0), 0j)
