"""Georeferenced answers (issue 32): each accepted answer's footprint on the ground and image-to-map affine,
checked against the simulator's camera (the truth the images were drawn from), and ``__geo_interface__``."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import geopandas as gpd
import numpy as np
import pyogrio
import pytest
import rasterio
import shapely
import shapely.geometry
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.answers import Answer
from mapdb.camera import Camera, Pose, footprint, image_to_ground
from mapdb.localize import localize
from mapdb.localize.georef import GRID, georeference, pixel_to_map
from mapdb.localize.lonlat import to_lonlat
from mapdb.mapfile.queries import MemoryMap
from mapdb.simulation.simulate import paper_map, simulate_images


@pytest.fixture(scope="module")
def paper() -> MemoryMap:
    return MemoryMap(paper_map(seed=2))


def _true_footprint(image: dict) -> np.ndarray:
    t = image["truth"]
    camera = Camera(image["width"], image["height"], t["fov_deg"])
    pose = Pose(t["x"], t["y"], t["altitude_m"], t["heading_deg"], t["roll_deg"], t["pitch_deg"])
    return footprint(pose, camera)


def _apply(transform: list[float], col: float, row: float) -> tuple[float, float]:
    a, b, c, d, e, f = transform
    return a * col + b * row + c, d * col + e * row + f


@pytest.mark.parametrize("tilted", [False, True], ids=["level", "tilted"])
def test_answers_footprint_is_the_cameras(paper: MemoryMap, tilted: bool) -> None:
    """The answer's corners lie where the simulated camera saw them (within the fix's error, well under 1 m);
    the transform maps the corners onto them exactly for a level image, within transform_error_m tilted."""
    extra = {"attitude_std": 5.0, "with_attitude": True} if tilted else {}
    images = simulate_images(paper, 4, pixel_std=1.0, yaw="random", seed=3, **extra)
    for image in images:
        answer = localize(image, paper)
        assert answer.ok, answer.reason
        record = answer.to_json()
        assert record["levelled"] is tilted
        assert (record["width"], record["height"]) == (image["width"], image["height"])
        corners = np.array(record["footprint"])
        assert np.hypot(*(corners - _true_footprint(image)).T).max() < 0.5
        w, h = image["width"], image["height"]
        mapped = np.array([_apply(record["transform"], c, r) for c, r in [(0, 0), (w, 0), (w, h), (0, h)]])
        gap = np.hypot(*(mapped - corners).T).max()
        if tilted:
            assert 0.1 < record["transform_error_m"] and gap <= record["transform_error_m"] + 1e-3
        else:
            assert record["transform_error_m"] == 0.0 and gap < 2e-3
        lonlat = [to_lonlat(answer.crs, x, y) for x, y in corners]
        # From the unrounded corners: within a millimetre's worth of degrees of the rounded ones'.
        assert np.abs(np.array(record["footprint_lonlat"]) - np.array(lonlat)).max() < 1e-7
        assert Answer.from_json(record).to_json() == record


def test_a_brief_answer_is_the_full_ones_position_score_and_candidates(paper: MemoryMap) -> None:
    """Localizer.localize(brief=True) (the analysis's answers): the full answer's position, score, inliers and
    candidates (and what the search adds), nothing else derived from the pose."""
    from mapdb.localize import Localizer

    images = simulate_images(paper, 4, pixel_std=1.0, yaw="random", seed=3, attitude_std=5.0, with_attitude=True)
    images.append({"width": 640, "height": 480, "objects": []})  # a rejection: nothing to leave out
    localizer = Localizer(paper)
    for image in images:
        full, brief = localizer.localize(image), localizer.localize(image, brief=True)
        ground = ("lon", "lat", "width", "height", "transform", "transform_error_m", "footprint", "footprint_lonlat")
        derived = ("heading_deg", "scale_m_per_px", "sigma_m", "expected_false_alarms", "altitude_m")
        if full.ok:
            assert all(getattr(full, name) is not None for name in ground + derived)
            assert all(getattr(brief, name) is None for name in ground + derived)
            assert dataclasses.replace(full, time_ms=0.0, **dict.fromkeys(ground + derived)) == brief
        else:
            assert dataclasses.replace(full, time_ms=0.0) == dataclasses.replace(brief, time_ms=0.0)
    assert sum(localizer.localize(image).ok for image in images) == 4


def test_the_geometry_is_the_pinhole_camera_exactly() -> None:
    """With the true similarity of a levelled image (scale altitude / f, the heading's rotation, b the nadir),
    every pixel lands where :func:`mapdb.camera.image_to_ground` puts it, and the best affine's error is the
    largest gap over the grid it was fitted on."""
    camera, pose = Camera(640, 480, 60.0), Pose(500.0, 800.0, 120.0, 30.0, 4.0, -7.0)
    a = pose.altitude / camera.focal_px * complex(math.cos(math.radians(-30.0)), math.sin(math.radians(-30.0)))
    b = complex(pose.x, pose.y)
    attitude = (camera.fov_deg, pose.roll_deg, pose.pitch_deg)
    cols, rows = np.meshgrid(np.linspace(0, 640, 9), np.linspace(0, 480, 7))
    x, y = pixel_to_map(cols, rows, a, b, 640, 480, attitude)
    tx, ty = image_to_ground(cols.ravel(), rows.ravel(), pose, camera)
    assert np.allclose(x, tx, atol=1e-6) and np.allclose(y, ty, atol=1e-6)
    g = georeference(a, b, 640, 480, attitude)
    assert g is not None and np.allclose(g.footprint, footprint(pose, camera), atol=1e-6)
    gc, gr = np.meshgrid(np.linspace(0, 640, GRID), np.linspace(0, 480, GRID))
    gx, gy = pixel_to_map(gc, gr, a, b, 640, 480, attitude)
    fx, fy = _apply(list(g.transform), gc.ravel(), gr.ravel())
    assert g.error_m == pytest.approx(np.hypot(fx - gx, fy - gy).max())
    # Looking at the horizon: no footprint to give.
    assert georeference(a, b, 640, 480, (60.0, 0.0, 75.0)) is None


def test_geo_interface_is_a_lonlat_point_feature(paper: MemoryMap) -> None:
    (image,) = simulate_images(paper, 1, pixel_std=1.0, seed=5)
    answer = localize(image, paper)
    feature = answer.__geo_interface__
    point = shapely.geometry.shape(answer)
    assert feature["type"] == "Feature" and (point.x, point.y) == (answer.lon, answer.lat)
    properties = feature["properties"]
    assert properties["id"] == image["id"] and properties["heading_deg"] == answer.heading_deg
    assert not any(isinstance(v, list | dict) for v in properties.values())
    polygon = shapely.geometry.shape(answer.footprint_feature()["geometry"])
    assert polygon.exterior.is_ccw and polygon.contains(point)
    rejected = Answer(id="r", status="rejected", reason="no match")
    assert rejected.__geo_interface__["geometry"] is None and rejected.footprint_feature() is None


def _query(*args: str):
    return CliRunner().invoke(cli, ["query", *args], catch_exceptions=False)


def test_query_writes_fixes_and_footprints_as_geojson(paper_setup, tmp_path: Path) -> None:
    """--geojson and --footprints read back with pyogrio: one feature an accepted image, one geometry type a
    file, the JSON answers' positions and fields; the output rule as for every command."""
    map_path, images = paper_setup
    lines = [json.dumps(images[0]), json.dumps({"id": "empty", "width": 640, "height": 480, "objects": []}),
             json.dumps(images[1]), json.dumps(images[2])]
    images_path, answers_path = tmp_path / "in.jsonl", tmp_path / "out.jsonl"
    images_path.write_text("\n".join(lines) + "\n")
    fixes, prints = tmp_path / "fixes.geojson", tmp_path / "footprints.geojson"
    result = _query(str(map_path), str(images_path), "-o", str(answers_path), "--geojson", str(fixes),
                    "--footprints", str(prints))
    assert result.exit_code == 0, result.output
    answers = [json.loads(line) for line in answers_path.read_text().splitlines()]
    accepted = [a for a in answers if a["status"] == "ok"]
    assert len(accepted) == 3 and answers[1]["status"] == "rejected"
    points, polygons = gpd.read_file(fixes, engine="pyogrio"), gpd.read_file(prints, engine="pyogrio")
    assert pyogrio.read_info(fixes)["geometry_type"] == "Point"
    assert pyogrio.read_info(prints)["geometry_type"] == "Polygon"
    assert points.crs.to_epsg() == 4326 and polygons.crs.to_epsg() == 4326
    assert list(points["id"]) == list(polygons["id"]) == [a["id"] for a in accepted]
    for answer, point, polygon, heading in zip(accepted, points.geometry, polygons.geometry, points["heading_deg"],
                                               strict=True):
        assert (point.x, point.y) == (answer["lon"], answer["lat"]) and heading == answer["heading_deg"]
        assert shapely.Polygon(answer["footprint_lonlat"]).equals(polygon) and polygon.contains(point)
    # The output rule: an existing layer is refused before any work (the answers file is not written either).
    answers_path.unlink()
    refused = _query(str(map_path), str(images_path), "-o", str(answers_path), "--geojson", str(fixes))
    assert refused.exit_code == 1 and "exists; pass --overwrite" in refused.output and not answers_path.exists()
    assert _query(str(map_path), str(images_path), "--geojson", str(fixes), "--overwrite").exit_code == 0
    to_stdout = _query(str(map_path), str(images_path), "--footprints", "-")
    assert to_stdout.exit_code == 2 and "not to stdout" in to_stdout.output
    clash = _query(str(map_path), str(images_path), "--geojson", str(images_path), "--overwrite")
    assert clash.exit_code == 1 and json.loads(images_path.read_text().splitlines()[0]) == images[0]


def _placed(image: Path) -> tuple[Any, np.ndarray]:
    """The CRS and the corners (4, 2) at which rasterio (GDAL) places ``image``."""
    with rasterio.open(image) as ds:
        t, w, h = ds.transform, ds.width, ds.height
        return ds.crs, np.array([t @ (0, 0), t @ (w, 0), t @ (w, h), t @ (0, h)])


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")  # the PNG, before its sidecars
def test_georef_places_the_camera_image_on_the_map(paper_setup, tmp_path: Path) -> None:
    """A PNG of the answer's size, georeferenced by ``mapdb georef``: rasterio reads its world file and
    .aux.xml and puts its corners on the answer's footprint, in the map's CRS."""
    map_path, images = paper_setup
    images_path, answers_path = tmp_path / "in.jsonl", tmp_path / "out.jsonl"
    images_path.write_text("".join(json.dumps(im) + "\n" for im in images))
    assert _query(str(map_path), str(images_path), "-o", str(answers_path)).exit_code == 0
    answer = json.loads(answers_path.read_text().splitlines()[1])
    w, h = int(answer["width"]), int(answer["height"])
    png, small = tmp_path / "frame.png", tmp_path / "small.png"
    for path, width in ((png, w), (small, w - 1)):
        with rasterio.open(path, "w", driver="PNG", width=width, height=h, count=1, dtype="uint8") as ds:
            ds.write(np.full((1, h, width), 200, np.uint8))
    runner = CliRunner()
    result = runner.invoke(cli, ["georef", str(answers_path), str(png), "--id", answer["id"]])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "frame.pgw").is_file() and (tmp_path / "frame.png.aux.xml").is_file()
    crs, corners = _placed(png)
    assert crs.to_epsg() == 32631
    assert np.hypot(*(corners - np.array(answer["footprint"])).T).max() < 0.01
    # A camera image of another size: one line naming both sizes, exit 1, nothing written.
    result = runner.invoke(cli, ["georef", str(answers_path), str(small), "--id", answer["id"]])
    assert result.exit_code == 1 and result.output.count("\n") == 1
    assert f"{w - 1}x{h}" in result.output and f"{w}x{h}" in result.output
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("small")) == ["small.png"]
    # Several accepted answers and no --id: which one is asked for; existing sidecars need --overwrite.
    result = runner.invoke(cli, ["georef", str(answers_path), str(png), "--overwrite"])
    assert result.exit_code == 1 and "3 accepted answers; choose one with --id" in result.output
    result = runner.invoke(cli, ["georef", str(answers_path), str(png), "--id", answer["id"]])
    assert result.exit_code == 1 and "exists; pass --overwrite" in result.output
