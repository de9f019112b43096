"""Small map files written by tests: an irregular town of buildings."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects


def write_town(path: Path, n: int, seed: int, width: float, height: float) -> Path:
    """A map file of ``n`` buildings scattered uniformly over ``width`` x ``height`` metres (UTM 31N): an
    irregular town, some cells of an analysis to simulate and some empty."""
    rng = np.random.default_rng(seed)
    x = 500_000.0 + rng.uniform(0, width, n)
    y = 5_000_000.0 + rng.uniform(0, height, n)
    write_map(path, Objects.from_names(x, y, ["building"] * n, crs="EPSG:32631"))
    return path
