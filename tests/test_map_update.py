"""The map-likelihood update (:mod:`mapdb.navigation.map_update`): a frame's objects weigh the particles where the
matcher gives no fix.

The likelihood is checked on the paper map of ``tests/conftest.py`` with a frame's objects projected from a known
pose; the navigation on an ideal flight over a synthetic town (``tests/navworld.py``) whose frames, for a stretch,
hold two objects each (too few for a query or a frame-to-frame velocity) while a biased inertial unit pulls the
track off: the objects alone must hold it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from navworld import fly, synthetic_world

from mapdb.mapfile.reader import open_map
from mapdb.navigation.filter import ParticleFilter
from mapdb.navigation.map_update import CAP_M, MapUpdate, NearestObjects, frame_log_likelihood
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.navigation.orientation import Orientation
from mapdb.navigation.velocity import FramePoints
from mapdb.simulation.simulate import paper_map

SCALE = 0.15  # metres per pixel: 100 m over a 640 px, 70 degree image
HEADING = 30.0


def _frame(objects, pose: complex, radius: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """The map offsets (metres from the nadir) and labels of the objects within ``radius`` of ``pose``, each
    moved by a blob's error (0.3 m per axis)."""
    z = objects.x + 1j * objects.y
    near = np.abs(z - pose) < radius
    noise = 0.3 * (rng.standard_normal(int(near.sum())) + 1j * rng.standard_normal(int(near.sum())))
    return z[near] - pose + noise, objects.label[near].astype(np.int64)


def _centre_frame(m, radius: float, rng) -> tuple[tuple[float, ...], complex, np.ndarray, np.ndarray]:
    """The map's bounds, its centre (the frame's true place) and the frame seen there (:func:`_frame`)."""
    x0, y0, x1, y1 = m.bounds
    truth = complex((x0 + x1) / 2, (y0 + y1) / 2)
    offsets, codes = _frame(m.all(), truth, radius, rng)
    return (x0, y0, x1, y1), truth, offsets, codes


def test_the_true_place_scores_highest_and_a_foreign_frame_moves_nothing(paper_setup) -> None:
    map_path, _ = paper_setup
    rng = np.random.default_rng(5)
    with open_map(map_path) as m:
        (x0, y0, x1, y1), truth, offsets, codes = _centre_frame(m, 50.0, rng)
        assert offsets.size >= 10
        sigmas = np.full(offsets.size, 1.0)
        field = NearestObjects(m, (x0 - 150, y0 - 150, x1 + 150, y1 + 150))
        ring = truth + np.array([3.0, 3j, -3.0, -3j, 2 + 2j, -5.0, 5j, 8 - 8j])
        particles = np.concatenate([[truth], ring])
        loglik = frame_log_likelihood(field, particles, offsets, codes, sigmas, None, math.radians(1.0))
        assert int(np.argmax(loglik)) == 0
        assert np.all(loglik[1:] < loglik[0] - 2.0)  # each 3+ m off is at least e^2 less likely
        # The same frame where the map has nothing (the frame seen beyond the map's edge): clutter alone, flat.
        outside = complex(x1 + 80.0, y1 + 80.0) + np.concatenate([[0], ring - truth])
        far = frame_log_likelihood(field, outside, offsets * 0.3, codes, sigmas, None, math.radians(1.0))
        assert np.ptp(far) < 1e-9
        # A frame of another town's objects over this one: far less contrast than the true frame's.
        other = paper_map(seed=11)
        foreign, foreign_codes = _frame(other, complex(float(np.mean(other.x)), float(np.mean(other.y))), 50.0, rng)
        spread = frame_log_likelihood(field, particles, foreign, foreign_codes, np.full(foreign.size, 1.0))
        assert np.ptp(spread) < 0.5 * np.ptp(loglik)


def test_the_update_moves_the_cloud_to_the_objects_and_skips_empty_frames(paper_setup) -> None:
    map_path, _ = paper_setup
    rng = np.random.default_rng(6)
    with open_map(map_path) as m:
        _, truth, offsets, codes = _centre_frame(m, 45.0, rng)
        orientation = Orientation(heading=HEADING, scale=SCALE, heading_sigma=0.5, scale_rel_sigma=0.005, fixed_s=0.0)
        to_map = orientation.to_map()
        assert to_map is not None
        points = FramePoints(offsets / to_map, codes, 640.0, 480.0)
        flt = ParticleFilter(2000, seed=3)
        flt.initialise(truth + 4.0 + 3j, 6.0, 20 + 0j, 1.0)  # a cloud 5 m off, 6 m wide: the truth at its edge
        before = abs(flt.estimate()[0] - truth)
        updater = MapUpdate(m)
        for _ in range(5):
            out = updater.update(flt, points, orientation, 0.0, 0.2)
            assert out["status"] == "used" and out["objects"] == offsets.size and 0 < out["ess"] <= 2000
        after = abs(flt.estimate()[0] - truth)
        assert before > 4.0 and after < 1.5, (before, after)
        empty = FramePoints(np.zeros(0, complex), np.zeros(0, np.int64), 640.0, 480.0)
        assert updater.update(flt, empty, orientation, 0.0, 0.2)["status"] == "skipped"
        # A cut blob is left out: one object, cut, is a frame of no object.
        cut = FramePoints(points.z[:1], points.codes[:1], 640.0, 480.0, np.array([True]))
        assert updater.update(flt, cut, orientation, 0.0, 0.2)["reason"].startswith("0 whole objects")
    assert CAP_M > 3.0


world = pytest.fixture(scope="module", name="world")(synthetic_world)


def _sparse_and_biased(frames: list[dict], start: float, end: float) -> list[dict]:
    """Frames from ``start`` to ``end`` s keep their two objects nearest the image centre (no query, no
    frame-to-frame velocity) and carry an inertial velocity 2 m/s off across the track."""
    out = []
    for f in frames:
        f = dict(f)
        if start <= f["time_s"] < end:
            centre = complex(f["width"] / 2, f["height"] / 2)
            f["objects"] = sorted(f["objects"], key=lambda o: abs(complex(o["x"], o["y"]) - centre))[:2]
            v = f["truth"]["velocity_mps"]
            f["imu_velocity_mps"] = [v[0], v[1] + 2.0]
        out.append(f)
    return out


def test_two_objects_a_frame_hold_the_track_a_biased_inertial_unit_pulls_off(world) -> None:
    frames = _sparse_and_biased(fly(world, 12.0), 3.0, 11.0)
    start = frames[0]["truth"]
    errors = {}
    for on in (False, True):
        navigator = Navigator(world, NavigatorOptions(map_update=on), initial=(start["x"], start["y"], 20.0))
        records = [navigator.step(f, f"line {i + 1}") for i, f in enumerate(frames)]
        stretch = [r for r, f in zip(records, frames, strict=True) if 3.0 <= f["time_s"] < 11.0]
        assert all(r.fix["status"] == "none" for r in stretch)  # two objects: no query
        errors[on] = max(r.truth["error_m"] for r in stretch)
        used = [r for r in stretch if (r.map_update or {}).get("status") == "used"]
        assert len(used) == (len(stretch) if on else 0)
    assert errors[False] > 5.0 and errors[True] < 2.0, errors


def test_a_map_gap_withholds_the_map_from_the_update_too(world) -> None:
    frames = fly(world, 3.0, map_gaps=((1.0, 1.0),))
    start = frames[0]["truth"]
    navigator = Navigator(world, initial=(start["x"], start["y"], 20.0))
    records = [navigator.step(f, f"line {i + 1}") for i, f in enumerate(frames)]
    gap = [r for r, f in zip(records, frames, strict=True) if f.get("map_withheld")]
    assert gap and all(r.map_update == {"status": "skipped", "reason": "the flight withholds the map here"}
                       for r in gap)
    assert all(r.map_update is None for r in records if r.fix.get("status") == "used")
