"""The rivals' places (``rivals._places``: one hypothesis a cell of a place's width and a twelfth of a turn) against
the numpy code it replaced, kept here verbatim as the reference (main at bc671ca): np.angle's arctan2 now called
directly and the poses taken again only when some are not elsewhere, so the chosen hypotheses must be the same on
random inputs and on the edges (cell and turn boundaries, negative zeros, duplicates, NaN and infinities, huge
coordinates, one row, none).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from mapdb.match.refine import PLACE_FRACTION, pose_shift
from mapdb.match.rivals import _places

# ---------------------------------------------------------------- the numpy reference (main at bc671ca)


def ref_elsewhere(a, b, best, diag_px):
    return pose_shift(a, b, best.a, best.b, diag_px) > abs(best.a) * diag_px * PLACE_FRACTION


def ref_places(a, b, best, diag_px):
    separation = abs(best.a) * diag_px * PLACE_FRACTION
    away = np.flatnonzero(ref_elsewhere(a, b, best, diag_px) & np.isfinite(b))
    if not away.size:
        return np.zeros(0, np.int64)
    turn = np.floor(np.angle(a[away] / best.a) / (np.pi / 6.0))
    cell = (np.floor(b[away].real / separation) * 2.0**24 + np.floor(b[away].imag / separation)) * 16.0 + turn
    first = {}
    for j, c in enumerate(cell.tolist()):
        first.setdefault(c if c == c else None, j)
    return away[list(first.values())]


# ---------------------------------------------------------------- inputs


def _case(rng, h, spread=2000.0):
    best = SimpleNamespace(a=complex(rng.uniform(0.2, 1.0), rng.uniform(-1.0, 1.0)),
                           b=complex(rng.uniform(-50, 50), rng.uniform(-50, 50)))
    a = best.a * np.exp(1j * rng.uniform(-np.pi, np.pi, h)) * rng.uniform(0.9, 1.1, h)
    b = rng.uniform(-spread, spread, h) + 1j * rng.uniform(-spread, spread, h)
    return a.astype(np.complex128), b.astype(np.complex128), best


def _check(a, b, best, diag_px=800.0):
    with np.errstate(all="ignore"):
        got, want = _places(a, b, best, diag_px), ref_places(a, b, best, diag_px)
    assert got.dtype == want.dtype and got.tolist() == want.tolist()
    return got


@pytest.mark.parametrize("seed", range(6))
def test_places_match_the_reference(seed):
    rng = np.random.default_rng(seed)
    for h in (1, 2, 5, 18, 60, 400):
        for spread in (30.0, 300.0, 3000.0):
            a, b, best = _case(rng, h, spread)
            _check(a, b, best)
            # duplicates and near-duplicates: hypotheses sharing a cell
            _check(np.repeat(a, 3), np.repeat(b, 3) + rng.uniform(0, 1e-6, 3 * h), best)


def test_places_on_cell_and_turn_boundaries():
    best = SimpleNamespace(a=1.0 + 0j, b=0j)
    separation = abs(best.a) * 800.0 * PLACE_FRACTION
    k = np.arange(-6, 7)
    # b exactly on cell corners (and signed zeros), a exactly on twelfths of a turn, and just beside them
    b = np.concatenate([k * separation + 1j * k[::-1] * separation, [complex(-0.0, -0.0), complex(0.0, -0.0)],
                        np.nextafter(k * separation, np.inf) + 1j * np.nextafter(k * separation, -np.inf)])
    a = np.exp(1j * np.pi / 6.0 * np.resize(k, b.size))
    a[:3] = [1.0, -1.0, complex(-1.0, -0.0)]
    kept = _check(a.astype(np.complex128), (b + 500.0).astype(np.complex128), best)
    assert kept.size > 1  # (the places are not all one)
    _check(a.astype(np.complex128), b.astype(np.complex128), best)
    # a turn exactly on a twelfth (no turn) and one just past it, at one spot: one cell, the first kept
    a = np.array([1.0, np.exp(1e-9j)], np.complex128)
    assert _check(a, np.full(2, 500.0 + 500.0j), best).tolist() == [0]


def test_places_edges():
    best = SimpleNamespace(a=0.5 - 0.1j, b=3.0 + 4.0j)
    inf, nan = math.inf, math.nan
    a = np.array([1, nan, complex(inf, 0), complex(0, -inf), 0.5, 0j, complex(nan, nan), 2j], np.complex128)
    b = np.array([1e3, 2e3, 3e3, complex(4e3, nan), complex(inf, 1.0), 5e3j, -6e3, 1e300 + 1e300j], np.complex128)
    _check(a, b, best)
    _check(a[:1], b[:1], best)  # one row
    _check(a[:0], b[:0], best)  # none
    _check(np.full(4, best.a), np.full(4, best.b), best)  # all at the winner's place: none elsewhere
    tiny = SimpleNamespace(a=complex(5e-324, 0.0), b=0j)  # a denormal separation: infinite quotients
    _check(np.array([1.0, 1j, -1.0], np.complex128), np.array([1.0, -1.0, 0.0], np.complex128), tiny)
