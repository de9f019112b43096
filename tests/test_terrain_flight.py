"""Flights and the navigator over terrain (issue 33): `mapdb simulate flight` at a barometric altitude over a
generated DEM, the navigator's height above the ground from the barometer minus the map's elevation, and flat
maps unchanged."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import rasterio
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import X0, Y0, OsmXml, square
from rasterio.transform import from_origin

from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.frames import read_frame
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.navigation.terrain import GroundModel, height_above_ground
from mapdb.simulation.terrain import terrain_of

# The slope of the generated ground: 15 m per 100 m eastwards, so that the flight's height above it changes.
SLOPE = 0.15
# The flight: 300 m westwards, down the slope, at 2 frames a second (a short flight keeps the test fast).
LINE = [(150.0, 0.0), (-150.0, 0.0)]


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def slope_dem(path: Path) -> Path:
    """A GeoTIFF in UTM 32N: ground 100 + SLOPE * x metres (x east of the town's origin), posts every 5 m."""
    size, post = 200, 5.0
    left, top = X0 - 500.0, Y0 + 500.0
    xs = left + post * (np.arange(size) + 0.5) - X0
    z = np.tile(100.0 + SLOPE * xs, (size, 1)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=size, height=size, count=1, dtype="float32",
                       transform=from_origin(left, top, post, post), nodata=-9999.0, crs="EPSG:32632") as f:
        f.write(z, 1)
    return path


def hillside_town(path: Path, n: int = 260) -> Path:
    """Buildings of random sizes scattered over 500 x 300 m around the origin, and a few parks."""
    rng = np.random.default_rng(5)
    doc = OsmXml()
    for x, y, half in zip(rng.uniform(-250, 250, n), rng.uniform(-150, 150, n), rng.uniform(3.0, 8.0, n),
                          strict=True):
        doc.ring(square(float(x), float(y), float(half)), {"building": "yes"})
    for x, y in rng.uniform(-200, 200, (12, 2)):
        doc.ring(square(float(x), float(y) * 0.6, 12.0), {"leisure": "park"})
    return doc.write(path)


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> dict[str, Path]:
    """The town built with the sloping DEM and without it."""
    tmp = tmp_path_factory.mktemp("terrain_flight")
    town, dem = hillside_town(tmp / "town.osm"), slope_dem(tmp / "slope.tif")
    for name, extra in (("dem", ("--dem", dem)), ("flat", ())):
        result = run("build", town, "-o", tmp / f"{name}.mapdb", *extra)
        assert result.exit_code == 0, result.output
    return {"dem": tmp / "dem.mapdb", "flat": tmp / "flat.mapdb", "tif": dem, "dir": tmp}


def waypoints(m) -> np.ndarray:
    from pyproj import Transformer

    to_map = Transformer.from_crs("EPSG:32632", m.crs, always_xy=True)
    return np.array([complex(*to_map.transform(X0 + x, Y0 + y)) for x, y in LINE])


OPTIONS = FlightOptions(altitude_m=80.0, fov_deg=60.0, fps=2.0, pixel_std=0.5, seed=4)


def test_a_flight_over_the_slope_holds_its_barometric_altitude(maps: dict[str, Path]) -> None:
    with open_map(maps["dem"]) as m:
        frames = simulate_flight(m, OPTIONS, waypoints(m), terrain=terrain_of(m))
    truth = [f["truth"] for f in frames]
    datum = np.array([t["altitude_datum_m"] for t in truth])
    ground = np.array([t["ground_m"] for t in truth])
    above = np.array([t["altitude_m"] for t in truth])
    # The aircraft holds 80 m above the ground under the start: the datum altitude is constant, and the
    # height above the ground grows as the ground falls westwards (45 m over 300 m).
    assert np.ptp(datum) < 1e-9 and abs(above[0] - 80.0) < 1e-6
    assert np.allclose(above, datum - ground) and 35.0 < above[-1] - above[0] < 55.0
    for f in frames:
        assert "altitude_m" not in f and abs(f["baro_altitude_m"] - f["truth"]["altitude_datum_m"]) < 10.0
    assert np.median([len(f["objects"]) for f in frames]) >= 8


def test_a_terrain_following_flight_stays_its_altitude_above_the_ground(maps: dict[str, Path]) -> None:
    with open_map(maps["dem"]) as m:
        frames = simulate_flight(m, replace(OPTIONS, altitude_above="ground"), waypoints(m), terrain=terrain_of(m))
    truth = [f["truth"] for f in frames]
    assert all(abs(t["altitude_m"] - 80.0) < 1e-6 for t in truth)
    datum = np.array([t["altitude_datum_m"] for t in truth])
    assert 35.0 < datum[0] - datum[-1] < 55.0  # the planned datum altitude follows the ground down the slope


def test_the_navigators_height_above_ground_tracks_the_truth(maps: dict[str, Path]) -> None:
    with open_map(maps["dem"]) as m:
        frames = simulate_flight(m, OPTIONS, waypoints(m), terrain=terrain_of(m))
        navigator = Navigator(m, NavigatorOptions(particles=500, seed=1))
        records = [navigator.step(f) for f in frames]
    given = [(r.altitude, f["truth"]) for r, f in zip(records, frames, strict=True)
             if r.altitude is not None and r.altitude.get("used")]
    # Every frame after the first fix gets a height; the barometer's bias (std 2 m) and noise (0.3 m) and the
    # ground's interpolation between objects stay within 6 m of the truth on this 15 % slope.
    assert len(given) >= len(frames) - 3
    errors = np.array([a["above_ground_m"] - t["altitude_m"] for a, t in given])
    assert np.max(np.abs(errors)) < 6.0
    assert np.max(np.abs(errors - np.median(errors))) < 1.5  # the bias is common: the ground itself tracks
    errors_m = [r.truth["error_m"] for r in records if r.truth and r.truth["error_m"] is not None]
    assert len(errors_m) >= len(frames) - 3 and max(errors_m) < 1.0


def test_flat_maps_and_flat_flights_are_unchanged(maps: dict[str, Path]) -> None:
    tmp = maps["dir"]
    flat = run("simulate", "flight", maps["flat"], "-o", tmp / "flat.jsonl", "--length", 100, "--seed", 2, "-q")
    forced = run("simulate", "flight", maps["dem"], "-o", tmp / "forced.jsonl", "--length", 100, "--seed", 2,
                 "--flat", "-q")
    assert flat.exit_code == 0 and forced.exit_code == 0, flat.output + forced.output
    # The same objects, with or without elevation: --flat over the DEM map is the flat map's flight, byte for byte.
    assert (tmp / "flat.jsonl").read_bytes() == (tmp / "forced.jsonl").read_bytes()
    frames = [json.loads(line) for line in (tmp / "flat.jsonl").read_text().splitlines()]
    assert all("altitude_m" in f and "baro_altitude_m" not in f for f in frames)
    with open_map(maps["flat"]) as m:
        assert GroundModel.of(m) is None
        frame = read_frame(frames[3])
        assert height_above_ground(frame, None, Navigator(m).filter, 0.5) is None  # its own altitude_m stays
        assert frame.image is not None and frame.image.altitude_m == frames[3]["altitude_m"]
        record = Navigator(m).step(frames[0]).to_json()
    assert "altitude" not in record


def test_without_elevation_the_barometer_is_the_height_above_the_flat_ground(maps: dict[str, Path]) -> None:
    with open_map(maps["dem"]) as m:
        frame = simulate_flight(m, OPTIONS, waypoints(m), terrain=terrain_of(m))[0]
    with open_map(maps["flat"]) as m:
        parsed = read_frame(frame)
        done = height_above_ground(parsed, GroundModel.of(m), Navigator(m).filter, 0.5)
    assert done is not None and done["used"] and parsed.altitude == frame["baro_altitude_m"]
    assert parsed.image is not None and parsed.image.altitude_m == frame["baro_altitude_m"]


def test_flight_over_terrain_errors_are_one_line(maps: dict[str, Path]) -> None:
    tmp = maps["dir"]
    low = run("simulate", "flight", maps["dem"], "-o", tmp / "low.jsonl", "--altitude", 30, "--altitude-above",
              "datum", "--length", 100)
    assert_one_line_error(low, "would be", "above the ground")
    assert not (tmp / "low.jsonl").exists()
    both = run("simulate", "flight", maps["dem"], "-o", tmp / "both.jsonl", "--flat", "--dem", maps["tif"])
    assert both.exit_code == 2 and not (tmp / "both.jsonl").exists()
