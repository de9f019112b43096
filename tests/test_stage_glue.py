"""The matcher stages' Python glue rewritten with fewer numpy calls, against the code it replaced, kept here verbatim
as the reference: the relief fit's radial and tangential residuals (``evidence.relief.radial_excess``: numpy's
wrappers before).  Random inputs and the edges (ties, duplicates, NaN, signed zeros, one row); the answers must be
identical.  The rivals' places (``rivals._places``) are compared with their reference in ``test_rivals_places.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapdb.match.evidence.relief import radial_excess

# ---------------------------------------------------------------- the reference (main at 9b40c11)


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
