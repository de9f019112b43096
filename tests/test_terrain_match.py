"""The matcher over terrain: rays cast onto the map objects' heights (mapdb/match/evidence/terrain.py)."""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.evaluation.evaluate import evaluate_images
from mapdb.mapfile.queries import MemoryMap
from mapdb.match.evidence.terrain import TerrainModel
from mapdb.match.mapobjects.object_index import ObjectIndex
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_images
from mapdb.simulation.terrain import Terrain


def hilly_town(seed: int = 2) -> Objects:
    """1,500 objects on 1.2 km square over a hill 60 m high (a bump in the middle, a slope to the east)."""
    rng = np.random.default_rng(seed)
    n = 1500
    x, y = rng.uniform(0, 1200, n), rng.uniform(0, 1200, n)
    z = 20.0 + 0.04 * x + 60.0 * np.exp(-((x - 600) ** 2 + (y - 600) ** 2) / (2 * 250.0**2))
    o = Objects.from_names(500_000.0 + x, 5_000_000.0 + y, rng.choice(["building", "park", "parking"], n,
                                                                          p=[0.7, 0.15, 0.15]), crs="EPSG:32631")
    return o.with_elevation(z)


def localized(objects: Objects, images: list[dict]) -> np.ndarray:
    """Each image's error (metres), NaN where it was rejected."""
    outcomes, _ = evaluate_images(MemoryMap(objects), images)
    return np.array([o["error_m"] if o["status"] == "ok" else np.nan for o in outcomes])


@pytest.mark.parametrize("with_altitude", [True, False])
def test_rays_cast_onto_the_heights_place_the_images_the_flat_model_misplaces(with_altitude: bool) -> None:
    objects = hilly_town()
    images = simulate_images(objects, 12, altitude=120.0, fov_deg=60.0, yaw="random", pixel_std=0.5,
                             with_attitude=True, with_altitude=with_altitude, min_objects=8, seed=3,
                             terrain=Terrain(objects))
    over_terrain = localized(objects, images)
    flat = localized(objects.with_elevation(None), images)  # the same map without its elevation
    # No answer accepted more than 2 m off, and the rays placed at least as many as the similarity, better.
    assert not np.any(over_terrain > 2.0)
    assert np.sum(over_terrain <= 2.0) >= max(np.sum(flat <= 2.0), 9)
    assert np.nanmedian(over_terrain) < np.nanmedian(flat)


def test_on_flat_ground_the_rays_are_the_similarity() -> None:
    o = Objects.from_names([0.0, 30.0, 0.0, 50.0, -20.0], [0.0, 0.0, 30.0, 40.0, 10.0], ["b"] * 5)
    index = ObjectIndex(o.with_elevation(np.full(5, 42.0)))
    terrain = TerrainModel.of(index, 550.0, 120.0)
    assert terrain is not None
    a, b = np.array([120.0 / 550.0 * np.exp(0.3j)]), np.array([5 + 3j])
    z = np.array([10 + 20j, -200 + 40j, 300 - 100j])
    assert np.allclose(terrain.project(a, b, z), a[:, None] * z + b[:, None])
    assert TerrainModel.of(ObjectIndex(o), 550.0, 120.0) is None  # no elevation: no terrain model
    assert TerrainModel.of(index, None, 120.0) is None  # no field of view: none either
