"""Cut solid blobs placed by their map objects' areas (mapdb.match.evidence.blobs.cut_area_residuals)."""

from __future__ import annotations

import math

import numpy as np
from test_blob_errors import random_poses

from mapdb.match.evidence.areas import ImageAreas
from mapdb.match.evidence.blobs import AREA_SHIFT, BlobErrors, cut_area_residuals
from mapdb.match.evidence.image import ImageEvidence
from mapdb.match.refine import Candidate, polish
from mapdb.match.verify import ObjectIndex, decision_nfa
from mapdb.objects import Objects

HALF_W, HALF_H = 320.0, 240.0


def _buildings(rng: np.random.Generator, n: int, size: float) -> Objects:
    """Buildings at random places with log-normal footprints (median 300 m^2), independent of their places."""
    area = np.exp(rng.normal(math.log(300.0), 0.8, n))
    return Objects.from_names(rng.uniform(0, size, n), rng.uniform(0, size, n), ["building"] * n, area=area)


def test_area_placed_residual_is_calibrated_under_the_null() -> None:
    """Random places on a random map: the chance of ``u <= t`` for a cut blob placed by each candidate's area
    is at most the disc's ``1 - exp(-t)`` (and about it for small ``t``): never more evidence than chance."""
    rng = np.random.default_rng(5)
    objects = _buildings(rng, 4000, 2000.0)
    index = ObjectIndex(objects)
    lam = 4000 / 2000.0**2
    h, n = 400, 8
    a, b, z = random_poses(rng, h, n)
    errors = BlobErrors.of(z, np.exp(1j * rng.uniform(0, 2 * math.pi, n)), np.exp(rng.normal(7.0, 1.0, n)))
    assert errors is not None and errors.visible_px is not None
    unbounded = np.full((h, n), np.inf)
    r2, mid = cut_area_residuals(errors, a, b, z, np.arange(n), index, np.zeros(n, np.int64),
                                 np.zeros((h, 0), np.complex128), -unbounded, unbounded)
    assert (mid >= 0).all()
    u = lam * math.pi * r2.ravel()
    for t in (0.05, 0.1, 0.2, 0.5, 1.0):
        assert np.mean(u <= t) <= -math.expm1(-t) + 0.015, t
    assert abs(np.mean(u <= 0.1) - -math.expm1(-0.1)) < 0.03


def _seen(objects: Objects, a: complex, b: complex, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """The map objects in a 640x480 image (pixels centred, y up) under ``z -> a z + b`` as blobs: those within
    60 px of the border cut by it, a random share of their area visible and their centroid pulled inward by
    ``AREA_SHIFT * sqrt(hidden)`` (the model's mean, plus 3 px of noise); the others whole (1 px of noise).
    Map ids, centroids, pixel areas, outward normals (0 for whole ones)."""
    z = ((objects.x + 1j * objects.y) - b) / a
    seen = np.flatnonzero((np.abs(z.real) < HALF_W) & (np.abs(z.imag) < HALF_H))
    z, area = z[seen], objects.area[seen] / abs(a) ** 2
    gap = np.column_stack([HALF_W - z.real, HALF_W + z.real, HALF_H - z.imag, HALF_H + z.imag])
    side = np.argmin(gap, axis=1)
    cut = gap[np.arange(z.size), side] < 60
    outward = np.where(cut, np.array([1, -1, 1j, -1j])[side], 0)
    visible = np.where(cut, area * rng.uniform(0.1, 0.9, z.size), area * 1.2)
    noise = rng.normal(0, 1, z.size) + 1j * rng.normal(0, 1, z.size)
    z = z - AREA_SHIFT * np.sqrt(area - np.minimum(visible, area)) * outward + np.where(cut, 3, 1) * noise
    return seen, z, visible, outward


def test_cut_buildings_placed_by_area_give_more_evidence_at_the_true_pose() -> None:
    """Cut blobs whose map objects lie outward by an amount growing with the hidden area: placed by each
    candidate's area, they lie closer to their map objects than the fixed shift's ellipse puts them, so the
    decision finds more evidence at the true pose, and none at a wrong place."""
    rng = np.random.default_rng(6)
    objects = _buildings(rng, 1500, 1200.0)
    index = ObjectIndex(objects)
    a_true, b_true = 0.22 * np.exp(0.4j), 600 + 600j
    seen, z, area_px, outward = _seen(objects, a_true, b_true, rng)
    whole = outward == 0
    assert whole.sum() >= 4 and (~whole).sum() >= 6
    labels = np.zeros(z.size, np.int64)
    quad = np.flatnonzero(whole)[np.argsort(np.abs(z[whole]))[:4]]
    map_z = index.z[seen[quad]]
    areas = ImageAreas.of(area_px, whole, labels, index.labels)
    fixed, by_area = BlobErrors.of(z, outward), BlobErrors.of(z, outward, area_px)
    assert fixed is not None and by_area is not None and fixed.visible_px is None

    def nfa(errors: BlobErrors, a: complex, b: complex, mz: np.ndarray) -> float:
        radius = np.array([1.5 * abs(a) * 800.0 / 2])
        density = index.local_density(np.array([b]), radius)
        return float(decision_nfa(np.array([a]), np.array([b]), quad[None, :], mz[None, :], z, labels, index,
                                  density, 3.0, 6, ImageEvidence(areas=areas, errors=errors), radius)[0])

    a, b = np.array([a_true]), np.array([b_true])
    cut = np.flatnonzero(~whole)
    unbounded = np.full((1, z.size), np.inf)
    r2, mid = cut_area_residuals(by_area, a, b, z, cut, index, labels, map_z[None, :], -unbounded, unbounded)
    old = by_area.r2(a, b, z, index.z[seen][None, :])[0, cut]
    assert np.median(r2[0]) < 0.25 * np.median(old)
    assert np.mean(mid[0] == seen[cut]) > 0.8
    assert nfa(by_area, a_true, b_true, map_z) < nfa(fixed, a_true, b_true, map_z) - 1.0
    shift = 300 + 200j
    assert nfa(by_area, a_true, b_true + shift, map_z + shift) > -1.0


def test_the_final_fit_places_cut_buildings_by_their_map_objects_areas() -> None:
    """Two whole blobs and five cut ones, each cut blob's visible centroid pulled inward as the area model says:
    the final fit (too few whole blobs to fit them alone) lands on the truth only when it places the cut blobs."""
    rng = np.random.default_rng(11)
    w = np.array([0, 60, 120, 180, 30, 90, 150]) + 1j * np.array([0, 40, -30, 20, 110, -90, 80]) + (1000 + 2000j)
    area = rng.uniform(150.0, 500.0, w.size)
    index = ObjectIndex(Objects.from_names(w.real, w.imag, ["building"] * w.size, area=area))
    a, b = 0.25 * np.exp(0.4j), 1090 + 2010j  # metres per pixel with the heading; the map point under the centre
    z = (w - b) / a
    outward = np.array([0, 0, 1, -1, 1j, -1j, 1], np.complex128)  # the first two whole, the others cut
    full_px = area / abs(a) ** 2
    visible = np.where(outward != 0, rng.uniform(0.3, 0.8, w.size) * full_px, full_px)
    z = z - np.where(outward != 0, AREA_SHIFT * np.sqrt(full_px - visible), 0.0) * outward  # pulled inward
    errors = BlobErrors.of(z, outward, visible)
    labels = np.zeros(w.size, np.int64)
    cand = Candidate(a=a * 1.01, b=b + 3 + 2j, log10_nfa=-9.0, inliers=w.size, sigma_axis_m=2.0, variance_factor=0.3,
                     pairs=np.column_stack([np.arange(w.size), np.arange(w.size)]))
    placed = polish(cand, z, labels, index, evidence=ImageEvidence(errors=errors))
    # Placed at the scale of the fit before (1 % off at first), so within millimetres after two rounds.
    assert placed.inliers == w.size and abs(placed.b - b) < 0.02 and abs(placed.a - a) < 1e-4
    assert abs(polish(cand, z, labels, index).b - b) > 1.0  # at the visible centroids: metres off
