"""Area evidence in the fast matcher's decision (mapdb.match.evidence.areas): calibrated, and inert without areas."""

from __future__ import annotations

import math

import numpy as np

from mapdb.localize.localizer import localize
from mapdb.mapfile.queries import MemoryMap
from mapdb.match.evidence.areas import ImageAreas, bands, disc_chances
from mapdb.match.fast import match_fast
from mapdb.match.quads import QuadIndex
from mapdb.match.verify import ObjectIndex
from mapdb.objects import Objects


def _town(seed: int = 0, n: int = 400, side: float = 1000.0) -> Objects:
    """Buildings at random places with log-normal footprints (median 200 m^2), and some points."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, side, n), rng.uniform(0, side, n)
    labels = np.where(rng.random(n) < 0.8, "building", "road_intersection")
    area = np.where(labels == "building", np.exp(rng.normal(math.log(200.0), 1.0, n)), 0.0)
    return Objects.from_names(x, y, labels, area=area)


def _view(objects: Objects, centre: complex, scale: float, heading: float, half_px: float = 390.0):
    """The objects seen in an 800x800 image centred on ``centre`` as pixels (y up, centred), with their true
    areas in pixels."""
    pix = (objects.x + 1j * objects.y - centre) * np.exp(-1j * heading) / scale
    keep = np.flatnonzero((np.abs(pix.real) < half_px) & (np.abs(pix.imag) < half_px))
    return keep, pix[keep], objects.area[keep] / scale**2


def test_normalised_residual_is_calibrated_under_the_null():
    # Random points and random blob areas against a random map: the chance that the area-thinned normalised
    # residual u = lambda q pi r^2 is below t must be about 1 - exp(-t), as for positions alone.
    objects = _town(seed=1, n=3000, side=2000.0)
    index = ObjectIndex(objects)
    rng = np.random.default_rng(2)
    m = 4000
    w = (rng.uniform(300, 1700, m) + 1j * rng.uniform(300, 1700, m))[None, :]
    code = np.zeros(m, np.int64)  # building
    areas = ImageAreas(np.log(np.exp(rng.normal(math.log(200.0), 1.0, m)) / 0.25), np.ones(m, bool))
    lo, hi = bands(areas, np.array([0.5]))  # 0.5 m per pixel: the blobs' areas in square metres as drawn
    dist, _ = index.nearest_compatible(w, code, index.density, None, lo, hi)
    members = index.disc_members(np.array([1000 + 1000j]), np.array([1500.0]), code)
    q = disc_chances(index.log_area, members, code, lo, hi)
    density = np.sum(objects.label == objects.labels.index("building")) / 2000.0**2
    u = density * q * math.pi * dist**2
    for t in (0.05, 0.2):  # where decisions are taken: exact within sampling noise
        assert abs(np.mean(u <= t) - (1 - math.exp(-t))) < 0.015, t
    for t in (0.5, 1.0):  # farther, conservative: only 8 neighbours are looked at for a compatible one
        assert np.mean(u <= t) <= 1 - math.exp(-t) + 0.015, t
    assert 0.2 < np.median(q) < 0.6  # the areas do say something


def test_images_without_areas_are_answered_exactly_as_before():
    objects = _town()
    index, quads = ObjectIndex(objects), [QuadIndex(objects)]
    keep, z, area_px = _view(objects, 500 + 500j, 0.4, 0.7)
    label = objects.label[keep]
    plain = match_fast(z, label, index, quads, math.hypot(800, 800))
    nan = match_fast(z, label, index, quads, math.hypot(800, 800), area_px=np.full(z.size, np.nan))
    assert plain.best is not None
    assert (plain.best.b, plain.best.log10_nfa) == (nan.best.b, nan.best.log10_nfa)
    # Through the localizer (whose map stores positions to 0.1 m): areas given change the score, not the place.
    doc = {"width": 800, "height": 800, "objects": [
        {"label": objects.labels[c], "x": 400 + p.real, "y": 400 - p.imag} for c, p in zip(label, z)]}
    without = localize(doc, MemoryMap(objects)).to_json()
    for o, px in zip(doc["objects"], area_px):
        o["area_px"] = float(px)
    with_areas = localize(doc, MemoryMap(objects)).to_json()
    assert without["status"] == with_areas["status"] == "ok"
    assert abs(without["x"] - plain.best.b.real) < 0.2 and abs(with_areas["x"] - without["x"]) < 0.2
    assert with_areas["score"] > without["score"] + 1.0


def test_true_areas_add_evidence_and_wrong_ones_add_none():
    objects = _town()
    index, quads = ObjectIndex(objects), [QuadIndex(objects)]
    keep, z, area_px = _view(objects, 500 + 500j, 0.4, 0.7)
    label = objects.label[keep]
    whole = np.ones(z.size, bool)
    plain = match_fast(z, label, index, quads, 800.0)
    right = match_fast(z, label, index, quads, 800.0, anchorable=whole, area_px=np.where(area_px > 0, area_px, np.nan))
    # Every blob's area ten times its building's: no map object near is compatible, so no evidence is gained.
    wrong = match_fast(z, label, index, quads, 800.0, anchorable=whole, area_px=np.where(area_px > 0, 10 * area_px,
                                                                                           np.nan))
    assert right.best is not None and abs(right.best.b - plain.best.b) < 1e-6
    assert right.best.log10_nfa < plain.best.log10_nfa - 1.0
    assert wrong.best is None or wrong.best.log10_nfa >= plain.best.log10_nfa
