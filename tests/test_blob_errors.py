"""Blob errors (mapdb.match.evidence.blobs) and quads with cut blobs (mapdb.match.cut_quads)."""

from __future__ import annotations

import math

import numpy as np

from mapdb.match.cut_quads import cut_batches
from mapdb.match.evidence.blobs import BlobErrors, outward_normals
from mapdb.match.fast import FastOptions, ObjectIndex, QuadIndex, match_fast
from mapdb.match.hypotheses import _quad_keys
from mapdb.objects import Objects


def random_poses(rng: np.random.Generator, h: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``h`` random similarities (0.3 m per pixel, any heading) over the middle of a 2 km map, and ``n`` image
    objects anywhere in a 640x480 image: places a null test of a residual looks at."""
    a = 0.3 * np.exp(1j * rng.uniform(0, 2 * math.pi, h))
    b = rng.uniform(400, 1600, h) + 1j * rng.uniform(400, 1600, h)
    z = rng.uniform(-320, 320, n) + 1j * rng.uniform(-240, 240, n)
    return a, b, z


def _random_map(rng: np.random.Generator, n: int, size: float) -> Objects:
    return Objects.from_names(rng.uniform(0, size, n), rng.uniform(0, size, n), ["building"] * n)


def test_ellipse_residual_is_calibrated_under_the_null() -> None:
    """Random places on a random map: the chance of ``u <= t`` for a cut blob's ellipse is at most the disc's
    ``1 - exp(-t)`` (and about it for small ``t``): the ellipse never gives more evidence than chance."""
    rng = np.random.default_rng(1)
    objects = _random_map(rng, 4000, 2000.0)
    index = ObjectIndex(objects)
    lam = 4000 / 2000.0**2
    h, n = 400, 8
    a, b, z = random_poses(rng, h, n)
    outward = np.exp(1j * rng.uniform(0, 2 * math.pi, n))
    errors = BlobErrors.of(z, outward)
    assert errors is not None
    _, mid = index.nearest(errors.expected(a, b, z), np.zeros(n, np.int64), np.full(1, 1e-6))
    assert (mid >= 0).all()
    u = lam * math.pi * errors.r2(a, b, z, index.z[mid]).ravel()
    for t in (0.05, 0.1, 0.2, 0.5, 1.0):
        assert np.mean(u <= t) <= -math.expm1(-t) + 0.015, t
    assert abs(np.mean(u <= 0.1) - -math.expm1(-0.1)) < 0.03


def test_outward_normals_and_errors() -> None:
    """A box on the left border points left, a corner box diagonally out, an inner box nowhere; whole blobs get
    a radial disc, cut ones the shifted ellipse."""
    normals = outward_normals(np.array([[0, 10, 30, 40], [600, 450, 640, 480], [50, 50, 60, 60]]), 640, 480)
    assert np.allclose(normals, [-1, (1 - 1j) / math.sqrt(2), 0])
    z = np.array([-300 + 10j, 300 - 220j, 5 + 5j])
    errors = BlobErrors.of(z, normals)
    assert errors is not None and BlobErrors.of(z, None) is None
    assert errors.shift_px[2] == 0 and errors.stretch[2] == 1 and errors.shift_px[0] > 0 and errors.stretch[0] > 1
    assert np.allclose(errors.direction[2], (5 + 5j) / abs(5 + 5j))


def test_cut_batches_hold_the_whole_blobs_and_a_cut_one() -> None:
    rng = np.random.default_rng(2)
    z = rng.uniform(-300, 300, 12) + 1j * rng.uniform(-200, 200, 12)
    for n_whole in (0, 2, 3, 5):
        whole = np.zeros(12, bool)
        whole[:n_whole] = True
        batches = cut_batches(z, whole, FastOptions())
        quads = np.concatenate(batches) if batches else np.zeros((0, 4), np.int64)
        assert len(quads), n_whole
        inside = whole[quads].sum(axis=1)
        assert (inside >= min(3, n_whole)).all() and (inside < 4).all()
    assert cut_batches(z, np.ones(12, bool), FastOptions()) == []


def test_per_point_sigmas_match_one_sigma() -> None:
    """Lookup radii with a sigma per point equal the one-sigma radii when all are equal, and grow with one."""
    rng = np.random.default_rng(3)
    zq = rng.uniform(-100, 100, (20, 4)) + 1j * rng.uniform(-100, 100, (20, 4))
    one = _quad_keys(zq, FastOptions(), 2.0)
    each = _quad_keys(zq, FastOptions(), np.full((20, 4), 2.0))
    assert one is not None and each is not None
    for x, y in zip(one, each, strict=True):
        assert np.allclose(x, y)
    wide = np.full((20, 4), 2.0)
    wide[:, 3] = 8.0
    wider = _quad_keys(zq, FastOptions(max_invariant_radius=10.0), wide)
    base = _quad_keys(zq, FastOptions(max_invariant_radius=10.0), 2.0)
    assert wider is not None and base is not None and wider[3].max() > base[3].max()


def test_image_with_three_whole_blobs_is_localized_with_its_cut_ones() -> None:
    """Three whole blobs in the middle and cut ones, pulled 25 px inward, along the border: the whole blobs
    alone make no quad, the cut rounds and ellipses find the place."""
    rng = np.random.default_rng(4)
    a_true, b_true = 0.22 * np.exp(0.7j), 480 + 520j
    w = rng.uniform(0, 1000, 4000) + 1j * rng.uniform(0, 1000, 4000)
    z_all = (w - b_true) / a_true
    inner = (np.abs(z_all.real) < 280) & (np.abs(z_all.imag) < 200)
    middle = np.flatnonzero(inner)[np.argsort(np.abs(z_all[inner]))[:3]]
    w = np.concatenate([w[~inner], w[middle]])  # the map holds nothing else inside the band
    objects = Objects.from_names(w.real, w.imag, ["building"] * w.size)
    index, quads = ObjectIndex(objects), [QuadIndex(objects, 8)]
    z = (w - b_true) / a_true
    seen = (np.abs(z.real) < 340) & (np.abs(z.imag) < 260)
    z = z[seen]
    whole = (np.abs(z.real) < 280) & (np.abs(z.imag) < 200)
    side = np.where(np.abs(z.real) / 320 > np.abs(z.imag) / 240, np.sign(z.real), 1j * np.sign(z.imag))
    outward = np.where(whole, 0, side)
    z = np.where(whole, z, np.clip(z.real, -320, 320) + 1j * np.clip(z.imag, -240, 240) - 25 * outward)
    labels = np.zeros(z.size, np.int64)
    assert whole.sum() == 3
    found = match_fast(z, labels, index, quads, 800.0, anchorable=whole, outward=outward)
    assert found.best is not None, found.reason
    assert abs(found.best.b - b_true) < 3.0
    assert match_fast(z, labels, index, quads, 800.0, anchorable=whole).best is None
