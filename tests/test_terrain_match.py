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


def slope_scene(depth_m: float = 300.0, seed: int = 0, noise_px: float = 1.0, slope: float = 0.3,
                seen_n: int = 12) -> tuple:
    """A level camera (focal 554 px) ``depth_m`` above a ``slope``, the ``seen_n`` objects it sees all on one
    side of the nadir (80-160 m east): the position leans on the camera's height.  The map, the image points, the
    objects' positions and heights."""
    rng = np.random.default_rng(seed)
    focal = 554.0
    # A mapped area of the slope, and the objects seen: east of the nadir at the origin.
    mx, my = rng.uniform(-40, 200, 300), rng.uniform(-150, 150, 300)
    names = ["b"] * mx.size
    seen = np.flatnonzero((mx > 80) & (mx < 160) & (np.abs(my) < 100))[:seen_n]
    heights = slope * mx
    index = ObjectIndex(Objects.from_names(mx, my, names).with_elevation(heights))
    w = mx[seen] + 1j * my[seen]
    heading = np.exp(0.7j)
    z = focal * w / (heading * (depth_m - heights[seen]))
    z = z + noise_px * (rng.standard_normal(z.size) + 1j * rng.standard_normal(z.size))
    return index, focal, z, w, heights[seen]


def test_the_altitude_given_measures_the_cameras_height_and_narrows_the_position() -> None:
    from mapdb.match.evidence.relief import fit_with_relief

    index, focal, z, w, h = slope_scene(noise_px=0.0)
    with_altitude = TerrainModel(index, focal, 300.0)
    without = TerrainModel(index, focal, None)
    g, g_var = with_altitude.nadir_ground(0j)
    assert abs(g) < 1e-6 and g_var > 0  # the plane through the slope's objects: exact at the nadir
    for model in (with_altitude, without):
        src, variance = model.fit_sources(z, w, 0j, 300.0 / focal, h)
        fit = fit_with_relief(src, w)
        assert fit is not None and abs(fit.b) < 0.05  # exact rays: the nadir found
    noisy = slope_scene(noise_px=1.0, seed=1)
    v_with = TerrainModel(noisy[0], focal, 300.0).fit_sources(noisy[2], noisy[3], 0j, 300.0 / focal, noisy[4])[1]
    v_without = TerrainModel(noisy[0], focal, None).fit_sources(noisy[2], noisy[3], 0j, 300.0 / focal, noisy[4])[1]
    assert 0 < v_with < v_without


def test_the_ground_under_the_nadir_is_less_certain_far_from_any_object() -> None:
    index = slope_scene()[0]
    model = TerrainModel(index, 554.0, 300.0)
    near, far = model.nadir_ground(100 + 0j)[1], model.nadir_ground(600 + 0j)[1]
    assert far > 25 * near  # 400 m beyond the last object: at least 0.1 m a metre of unseen relief


def test_the_position_error_stated_over_a_slope_is_honest() -> None:
    """Over 100 noisy images of the one-sided slope the error of the position over the stated sigma
    (position's from the fit and from the height) has the spread of a 2-D Gaussian error: median 1.18."""
    from mapdb.match.evidence.relief import fit_with_relief

    ratios = []
    for seed in range(100):
        index, focal, z, w, h = slope_scene(seed=seed)
        model = TerrainModel(index, focal, 300.0)
        src, depth_variance = model.fit_sources(z, w, 0j, 300.0 / focal, h)
        fit = fit_with_relief(src, w)
        assert fit is not None
        sigma = np.sqrt(fit.sigma_axis**2 * fit.variance_factor + depth_variance)
        ratios.append(abs(fit.b) / sigma)
    assert 0.8 < np.median(ratios) < 1.6
    assert np.quantile(ratios, 0.95) < 3.5
