"""The synthetic world the navigation tests fly over, and their flights (shared by the navigation tests)."""

from __future__ import annotations

import numpy as np

from mapdb.mapfile.queries import MemoryMap
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.objects import Objects
from mapdb.simulation.simulate import PAPER_CRS, PAPER_ORIGIN

X0, Y0 = PAPER_ORIGIN
# A straight leg, a turn and another leg, inside the synthetic world.
WAYPOINTS = np.array([complex(X0 + 300, Y0 + 300), complex(X0 + 900, Y0 + 300), complex(X0 + 900, Y0 + 900)])
# The done-when's error model (the camera at 100 m over the synthetic world).
ERRORS = {"pixel_std": 1.0, "attitude_std": 0.1, "miss_rate": 0.2}


def synthetic_world() -> MemoryMap:
    """1.2 x 1.2 km of random objects of three labels, about 15 in a 100 m, 60 degree image."""
    rng = np.random.default_rng(7)
    n = 2200
    names = rng.choice(["building", "road_intersection", "parking"], size=n, p=[0.7, 0.2, 0.1])
    return MemoryMap(Objects.from_names(X0 + rng.uniform(0, 1200, n), Y0 + rng.uniform(0, 1200, n), names,
                                        crs=PAPER_CRS))


def fly(world: MemoryMap, seconds: float, **changes) -> list[dict]:
    """A flight of ``seconds`` at 20 m/s along :data:`WAYPOINTS`, 100 m, 60 degrees, the :data:`ERRORS`."""
    options = {"length_m": 20.0 * seconds, "altitude_m": 100.0, "fov_deg": 60.0, **ERRORS, **changes}
    return simulate_flight(world, FlightOptions(**options), WAYPOINTS)
