"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest

from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.writer import write_map
from mapdb.simulation.simulate import paper_map, simulate_images


@pytest.fixture(scope="module")
def paper_setup(tmp_path_factory):
    """A paper-style map file and three simulated images of it (with their truth)."""
    root = tmp_path_factory.mktemp("paper")
    objects = paper_map(seed=2)
    map_path = root / "paper.mapdb"
    write_map(map_path, objects)
    # Simulate from the stored (quantised) positions, as a user's images would see the map.
    images = simulate_images(MemoryMap(objects), 3, pixel_std=1.0, yaw="random", seed=3)
    return map_path, images
