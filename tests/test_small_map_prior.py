"""A small map answers priors from one quad index of the whole map (``localizer.SMALL_MAP_OBJECTS``), built
once, instead of the tiles each prior's disc reaches: the same answers as the tiles give, and no tile built."""

from __future__ import annotations

import numpy as np
import pytest

import mapdb.localize.localizer as localizer_module
from mapdb.localize.localizer import Localizer
from mapdb.mapfile.queries import MemoryMap
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_images


def _town(n: int = 900, size: float = 1600.0) -> MemoryMap:
    """Random buildings, parks and water over a square that spans four tiles (1000 m) and their margins."""
    rng = np.random.default_rng(11)
    labels = rng.choice(["building", "park", "water"], n, p=[0.8, 0.15, 0.05]).tolist()
    return MemoryMap(Objects.from_names(500_000.0 + rng.uniform(0, size, n), 4_500_000.0 + rng.uniform(0, size, n),
                                        labels, crs="EPSG:32631"))


def _answers(m: MemoryMap, images: list[dict]) -> tuple[Localizer, list[tuple]]:
    localizer = Localizer(m)
    answers = [localizer.localize(image) for image in images]
    return localizer, [(a.status, a.x, a.y, a.heading_deg, a.scale_m_per_px, a.inliers) for a in answers]


def test_a_small_map_answers_priors_as_its_tiles_do(monkeypatch: pytest.MonkeyPatch) -> None:
    m = _town()
    assert len(m) <= localizer_module.SMALL_MAP_OBJECTS
    images = simulate_images(m, 12, altitude=200.0, fov_deg=60.0, yaw="random", pixel_std=1.0, with_prior=300.0,
                             min_objects=6, seed=5)
    whole, whole_answers = _answers(m, images)
    assert whole._small_map_quads is not None and not whole._tiles.entries  # one index, no tile
    monkeypatch.setattr(localizer_module, "SMALL_MAP_OBJECTS", 0)
    tiled, tiled_answers = _answers(m, images)
    assert tiled._small_map_quads is None and len(tiled._tiles.entries) >= 2  # the tiles path did run
    assert whole_answers == tiled_answers
    assert sum(status == "ok" for status, *_ in whole_answers) >= 10


def test_a_map_over_the_limit_builds_tiles(monkeypatch: pytest.MonkeyPatch) -> None:
    m = _town(300)
    monkeypatch.setattr(localizer_module, "SMALL_MAP_OBJECTS", 299)
    image = simulate_images(m, 1, altitude=200.0, fov_deg=60.0, yaw="random", with_prior=300.0, min_objects=6,
                            seed=6)[0]
    localizer = Localizer(m)
    localizer.localize(image)
    assert localizer._small_map_quads is None and localizer._tiles.entries
