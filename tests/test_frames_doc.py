"""``docs/frames.md`` read against the frames ``mapdb simulate flight`` writes, flat and over terrain: every
field the tables list (and no other) in the flights the tables say, and the navigator's ``altitude`` record."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mapdb.mapfile.queries import MemoryMap
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.objects import Objects
from mapdb.simulation.terrain import Terrain

DOC = Path(__file__).resolve().parents[1] / "docs" / "frames.md"


def table(title: str) -> dict[str, tuple[bool, bool]]:
    """The document's table under ``## title``: field -> (in a flat flight, in a flight over terrain)."""
    text = DOC.read_text(encoding="utf-8").split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `([a-z_]+)` \| (yes|no) \| (yes|no) \|", text, flags=re.MULTILINE)
    assert rows, f"no table under {title!r}"
    return {name: (flat == "yes", terrain == "yes") for name, flat, terrain in rows}


def hillside() -> Objects:
    """400 objects on 600 x 600 m over ground rising 10 m per 100 m eastwards."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 600, 400), rng.uniform(0, 600, 400)
    o = Objects.from_names(500_000.0 + x, 5_000_000.0 + y, rng.choice(["building", "park"], 400, p=[0.8, 0.2]),
                           crs="EPSG:32631")
    return o.with_elevation(50.0 + 0.1 * x)


OPTIONS = FlightOptions(altitude_m=100.0, fov_deg=60.0, fps=2.0, imu_std_mps=0.1, map_gaps=((1.0, 1.0),), seed=2)
PATH = np.array([500_150.0 + 5_000_300.0j, 500_450.0 + 5_000_300.0j])


@pytest.fixture(scope="module")
def flights() -> dict[str, list[dict]]:
    objects = hillside()
    flat = Objects(objects.x, objects.y, objects.label, objects.area, objects.labels, objects.crs)
    return {"flat": simulate_flight(flat, OPTIONS, PATH),
            "terrain": simulate_flight(objects, OPTIONS, PATH, terrain=Terrain(objects))}


@pytest.mark.parametrize("kind", ["flat", "terrain"])
def test_every_frame_field_the_document_lists_and_no_other(flights: dict[str, list[dict]], kind: str) -> None:
    column = 0 if kind == "flat" else 1
    frames = flights[kind]
    expected = {name for name, where in table("Frame fields").items() if where[column]}
    present = set().union(*(frame.keys() for frame in frames))
    assert present == expected
    truth = {name for name, where in table("Truth fields").items() if where[column]}
    assert all(set(frame["truth"]) == truth for frame in frames)


def test_the_navigators_altitude_record_holds_the_fields_the_document_names(flights: dict[str, list[dict]]) -> None:
    objects = hillside()
    navigator = Navigator(MemoryMap(objects), NavigatorOptions(particles=300))
    start = flights["terrain"][0]["truth"]
    navigator.filter.initialise(complex(start["x"], start["y"]), 5.0)
    record = navigator.step(flights["terrain"][0]).to_json()
    section = DOC.read_text(encoding="utf-8").split("## The navigator's height above the ground\n", 1)[1]
    named = set(re.findall(r"`([a-z_]+)`", section))
    assert {"baro_m", "ground_m", "above_ground_m", "sigma_m", "used"} <= set(record["altitude"]) <= named
    assert record["altitude"]["used"] is True
