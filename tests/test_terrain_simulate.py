"""`mapdb simulate` over terrain: objects at their heights, the camera above the ground or the datum."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.camera import Camera, Pose, project_points
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_images
from mapdb.simulation.terrain import Terrain


def hill_map(tmp_path: Path, elevation: bool = True) -> Path:
    """Objects on a 1 km square, the ground rising 20 m every 100 m eastwards (a steep hillside)."""
    rng = np.random.default_rng(5)
    n = 3000
    x, y = 500_000.0 + rng.uniform(0, 1000, n), 5_000_000.0 + rng.uniform(0, 1000, n)
    o = Objects.from_names(x, y, rng.choice(["building", "park"], n), crs="EPSG:32631")
    path = tmp_path / ("hill.mapdb" if elevation else "flat.mapdb")
    write_map(path, o.with_elevation(50.0 + 0.2 * (x - 500_000.0)) if elevation else o)
    return path


def test_objects_stand_at_their_heights_and_the_camera_above_the_ground(tmp_path: Path) -> None:
    with open_map(hill_map(tmp_path)) as m:
        objects = m.all()
        images = simulate_images(m, 5, altitude=120.0, fov_deg=60.0, with_altitude=True, min_objects=5,
                                 terrain=Terrain(objects))
    for image in images:
        t = image["truth"]
        ground = 50.0 + 0.2 * (t["x"] - 500_000.0)
        assert abs(t["ground_m"] - ground) < 1.0  # the map's neighbours on a plane: within the 1 m step
        assert image["altitude_m"] == t["altitude_m"] == pytest.approx(120.0)  # above the ground under it
        assert t["altitude_datum_m"] == pytest.approx(120.0 + t["ground_m"])
        pose = Pose(t["x"], t["y"], t["altitude_datum_m"], t["heading_deg"], t["roll_deg"], t["pitch_deg"])
        index = np.array(t["map_index"])
        u, v = project_points(objects.x[index], objects.y[index], objects.elevation[index], pose,
                              Camera(640, 480, 60.0))
        seen = np.array([[o["x"], o["y"]] for o in image["objects"]])
        assert np.allclose(seen, np.column_stack([u, v]), atol=1e-6)  # every object where its height puts it
        flat_u, _ = project_points(objects.x[index], objects.y[index], 0.0, Pose(t["x"], t["y"], 120.0), Camera(
            640, 480, 60.0))
        assert np.max(np.abs(flat_u - u)) > 5.0  # and not where a flat world would


def test_a_datum_altitude_leaves_the_height_above_ground_varying(tmp_path: Path) -> None:
    with open_map(hill_map(tmp_path)) as m:
        images = simulate_images(m, 6, altitude=300.0, fov_deg=60.0, with_altitude=True, min_objects=5,
                                 terrain=Terrain(m.all(), above="datum"))
    for image in images:
        t = image["truth"]
        assert t["altitude_datum_m"] == 300.0 and image["altitude_m"] == pytest.approx(300.0 - t["ground_m"])
    assert np.ptp([im["altitude_m"] for im in images]) > 20.0


def test_the_cli_uses_the_maps_elevation_and_flat_maps_are_unchanged(tmp_path: Path) -> None:
    hill, flat = hill_map(tmp_path), hill_map(tmp_path, elevation=False)

    def simulate(*args: object) -> list[dict]:
        result = CliRunner().invoke(cli, ["simulate", *map(str, args), "--n", "3", "--altitude", "120", "--fov", "60",
                                          "--min-objects", "5", "-q"])
        assert result.exit_code == 0, result.output
        return [json.loads(line) for line in result.stdout.splitlines()]

    over_hill, on_flat = simulate(hill), simulate(flat)
    assert all("ground_m" in im["truth"] for im in over_hill)
    assert all("ground_m" not in im["truth"] for im in on_flat)
    assert simulate(hill, "--flat") == on_flat  # the map's elevation ignored: the flat map's images exactly
    assert over_hill != on_flat


def test_a_map_without_elevation_cannot_make_terrain() -> None:
    o = Objects.from_names([0.0, 1.0], [0.0, 1.0], ["a", "a"], crs="EPSG:32631")
    with pytest.raises(ValueError, match="no map object has an elevation"):
        Terrain(o)


def test_analyze_counts_the_relief_each_cell_sees(tmp_path: Path) -> None:
    from mapdb.analysis.grid import cell_counts, make_grid

    with open_map(hill_map(tmp_path)) as m, open_map(hill_map(tmp_path, elevation=False)) as flat:
        grid = make_grid(m.bounds, 100.0, m.crs)
        relief = cell_counts(m, grid, None, 150.0).relief
        assert cell_counts(flat, grid, None, 150.0).relief is None  # a flat map: no relief band
    assert relief is not None
    # The ground rises 20 m every 100 m east; a cell sees objects within 2 cells each way: 5 cells, up to ~100 m
    # of ground (less at the map's edges).
    inner = relief[2:-2, 2:-2]
    assert np.all((inner >= 79.0) & (inner <= 101.0)) and np.nanmax(relief) == pytest.approx(100.0, abs=1.5)
    assert np.nanmin(relief) < np.nanmin(inner)  # the edges see less of the slope
