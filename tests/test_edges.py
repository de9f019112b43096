"""Edges of the world: boxes spanning the globe, touching the poles, crossing the antimeridian.

A lon/lat box selects exactly the objects whose own lon/lat lies in it, whatever the map's projection,
in ``mapdb export --bbox``, ``mapdb build --bbox`` (OSM, layers, rasters) and ``mapdb simulate --bbox``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import OsmXml
from pyproj import Transformer

from mapdb.build.pipeline import build_map
from mapdb.errors import EmptyMapError, SourceError
from mapdb.geo import (
    WORLD,
    central_longitude,
    check_bbox,
    in_bbox,
    intersect_bboxes,
    lonlat_extent,
    projected_window,
    split_bbox,
)
from mapdb.mapfile.export import select_lonlat
from mapdb.mapfile.reader import open_map
from mapdb.simulation.poses import map_bbox_from_lonlat
from mapdb.simulation.simulate import simulate_images

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"
CORINE = REPO.parent / "shared" / "data" / "landcover" / "corine2006_lausanne_ls100_06.tif"
CORINE_3035 = REPO.parent / "shared" / "data" / "landcover" / "corine2000_bern_valais_g100_clc00.tif"


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])




@pytest.fixture(scope="module")
def helsinki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample map, built once for the module."""
    out = tmp_path_factory.mktemp("edges") / "helsinki.mapdb"
    result = run("build", SAMPLE, "-o", out, "-q")
    assert result.exit_code == 0, result.output
    return out


def lonlat_of(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """Every object's lon/lat, computed here independently of the code under test."""
    with open_map(path) as m:
        objects = m.all()
        lon, lat = Transformer.from_crs(m.crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
    return np.asarray(lon), np.asarray(lat), len(objects)


def exported_count(path: Path, bbox: str, out: Path):
    result = run("export", path, "-o", out, f"--bbox={bbox}")
    return result, (len(pd.read_csv(out)) if result.exit_code == 0 else None)


# ------------------------------------------------------------------------------------ export


@pytest.mark.parametrize("bbox", ["-180,-90,180,90", "-179,-89,179,89", "20,50,-170,70", "-180,0,180,90",
                                  "24,60,-179.5,61"])
def test_export_boxes_holding_the_whole_map_give_every_object(helsinki: Path, tmp_path: Path, bbox: str) -> None:
    _, _, n = lonlat_of(helsinki)
    result, count = exported_count(helsinki, bbox, tmp_path / "all.csv")
    assert result.exit_code == 0, result.output
    assert count == n and n > 500


@pytest.mark.parametrize("bbox", ["170,50,-170,70", "-180,-90,0,90", "100,-90,-100,90", "-10,-90,10,90"])
def test_export_boxes_missing_the_map_say_no_objects(helsinki: Path, tmp_path: Path, bbox: str) -> None:
    out = tmp_path / "none.csv"
    assert_one_line_error(run("export", helsinki, "-o", out, f"--bbox={bbox}"), "no objects")
    assert not out.exists()


def test_export_box_cutting_the_map_is_exact(helsinki: Path, tmp_path: Path) -> None:
    lon, lat, _ = lonlat_of(helsinki)
    # Boxes through the middle of the data, one plain and one written across the antimeridian.
    mid_lon, mid_lat = float(np.median(lon)), float(np.median(lat))
    for bbox in [(mid_lon, mid_lat, 180.0, 90.0), (mid_lon, -90.0, -120.0, mid_lat), (-180.0, mid_lat, mid_lon, 90.0)]:
        expected = int(in_bbox(bbox, lon, lat).sum())
        west, east = (lon >= bbox[0]), (lon <= bbox[2])
        manual = (lat >= bbox[1]) & (lat <= bbox[3]) & ((west & east) if bbox[0] <= bbox[2] else (west | east))
        assert expected == int(manual.sum()) and 0 < expected < lon.size
        result, count = exported_count(helsinki, ",".join(map(str, bbox)), tmp_path / "part.csv")
        assert result.exit_code == 0, result.output
        assert count == expected
        exported = pd.read_csv(tmp_path / "part.csv")
        # (The CSV's lon/lat are rounded to 1e-8 degrees: an object on the box's edge may round out.)
        grown = (bbox[0] - 1e-7, bbox[1] - 1e-7, bbox[2] + 1e-7, bbox[3] + 1e-7)
        assert in_bbox(grown, exported["lon"].to_numpy(), exported["lat"].to_numpy()).all()
        (tmp_path / "part.csv").unlink()


@pytest.mark.parametrize("bbox", ["-inf,-90,180,90", "nan,0,1,1", "0,-91,1,1", "0,0,1,91", "-181,0,1,1",
                                  "0,0,181,1", "0,10,1,5", "5,0,5,1", "1,2,3", "a,b,c,d"])
def test_bad_boxes_are_usage_errors(helsinki: Path, tmp_path: Path, bbox: str) -> None:
    for command in (["export", helsinki, "-o", tmp_path / "x.csv"], ["build", SAMPLE, "-o", tmp_path / "x.mapdb"],
                    ["simulate", helsinki, "-o", tmp_path / "x.jsonl"]):
        result = run(*command, f"--bbox={bbox}")
        assert result.exit_code == 2, result.output
        assert "--bbox" in result.output and "Traceback" not in result.output
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------ maps at the edges


def _antimeridian_town(tmp_path: Path) -> Path:
    """Buildings on both sides of the 180th meridian (as in Fiji), as tagged nodes."""
    doc = OsmXml()
    for i in range(5):
        doc.node(179.995 + 0.0008 * i, -17.0 + 0.001 * i, {"building": "yes"}, lon_lat=True)
        doc.node(-179.995 - 0.0008 * i, -17.0 + 0.001 * i, {"building": "yes"}, lon_lat=True)
    return doc.write(tmp_path / "fiji.osm")


def test_map_across_the_antimeridian(tmp_path: Path) -> None:
    source = _antimeridian_town(tmp_path)
    out = tmp_path / "fiji.mapdb"
    summary = json.loads(run("build", source, "-o", out, "-q").stdout)
    # The zone of the data's middle (180 degrees), not of lon 0 (the plain median of +-180).
    assert summary["count"] == 10 and summary["crs"] in ("EPSG:32701", "EPSG:32760")
    with open_map(out) as m:
        assert len(select_lonlat(m, (179.9, -18.0, -179.9, -16.0))) == 10
        assert len(select_lonlat(m, (179.9, -18.0, 180.0, -16.0))) == 5
        assert len(select_lonlat(m, (-180.0, -18.0, -179.9, -16.0))) == 5
        assert len(select_lonlat(m, WORLD)) == 10
        assert len(select_lonlat(m, (-179.0, -18.0, 179.0, -16.0))) == 0
    built = tmp_path / "east.mapdb"
    result = run("build", source, "-o", built, "-q", "--bbox=-180,-18,-179.9,-16")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["count"] == 5
    both = json.loads(run("build", source, "-o", tmp_path / "both.mapdb", "-q", "--bbox=179,-18,-179,-16").stdout)
    assert both["count"] == 10


def test_map_at_the_north_pole(tmp_path: Path) -> None:
    # Points around the pole in a polar stereographic map: the pole is inside the map's extent.
    doc = OsmXml()
    for k in range(12):
        doc.node(-180.0 + 30.0 * k + 5.0, 89.95, {"building": "yes"}, lon_lat=True)
    source = doc.write(tmp_path / "pole.osm")
    out = tmp_path / "pole.mapdb"
    assert run("build", source, "-o", out, "-q", "--crs", "EPSG:3413").exit_code == 0
    lon, lat, n = lonlat_of(out)
    assert n == 12
    with open_map(out) as m:
        assert len(select_lonlat(m, (-180.0, 89.0, 180.0, 90.0))) == 12
        assert len(select_lonlat(m, WORLD)) == 12
        for bbox in [(0.0, 89.9, 90.0, 90.0), (150.0, 89.0, -150.0, 90.0), (-90.0, 89.0, 0.0, 90.0)]:
            assert len(select_lonlat(m, bbox)) == int(in_bbox(bbox, lon, lat).sum()) > 0
        assert len(select_lonlat(m, (-180.0, -90.0, 180.0, 89.0))) == 0


# ------------------------------------------------------------------------------------ build --bbox


@pytest.mark.parametrize("bbox", ["-180,-90,180,90", "-179,-89,179,89", "20,50,-170,70"])
def test_build_with_boxes_holding_everything(helsinki: Path, tmp_path: Path, bbox: str) -> None:
    _, _, n = lonlat_of(helsinki)
    result = run("build", SAMPLE, "-o", tmp_path / "m.mapdb", "-q", f"--bbox={bbox}")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["count"] == n


def test_build_with_a_box_missing_everything(tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    assert_one_line_error(run("build", SAMPLE, "-o", out, "-q", "--bbox=170,50,-170,70"), "no labelled objects",
                          "170,50,-170,70")
    assert not out.exists()


def test_csv_layer_across_the_antimeridian(tmp_path: Path) -> None:
    layer = tmp_path / "points.csv"
    layer.write_text("lon,lat,label\n179.99,-17,stadium\n-179.99,-17,stadium\n180,-17.001,stadium\n10,10,stadium\n")
    out = tmp_path / "m.mapdb"
    result = run("build", layer, "-o", out, "-q", "--bbox=179.9,-18,-179.9,-16", "--crs", "EPSG:32760")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["count"] == 3


@pytest.mark.parametrize("path", [CORINE, CORINE_3035], ids=["EPSG:2056", "EPSG:3035"])
def test_corine_build_with_the_whole_world_box(tmp_path: Path, path: Path) -> None:
    if not path.exists():
        pytest.skip(f"real data absent: {path} (expected ../shared/data beside the checkout)")
    plain = json.loads(run("build", path, "-o", tmp_path / "a.mapdb", "-q").stdout)
    for bbox in ["-180,-90,180,90", "-179,-89,179,89", "0,0,-1,89"]:
        boxed = run("build", path, "-o", tmp_path / "b.mapdb", "-q", f"--bbox={bbox}", "--overwrite")
        assert boxed.exit_code == 0, boxed.output
        assert json.loads(boxed.stdout)["labels"] == plain["labels"] and plain["count"] > 100
        with open_map(tmp_path / "a.mapdb") as a, open_map(tmp_path / "b.mapdb") as b:
            assert np.array_equal(np.sort(a.all().x), np.sort(b.all().x))
    assert_one_line_error(run("build", path, "-o", tmp_path / "c.mapdb", "-q", "--bbox=170,-90,-170,90"),
                          "no labelled objects")


# ------------------------------------------------------------------------------------ simulate --bbox


@pytest.mark.parametrize("bbox", [None, "-180,-90,180,90", "-179,-89,179,89", "20,50,-170,70"])
def test_simulate_spreads_cameras_over_the_map(helsinki: Path, tmp_path: Path, bbox: str | None) -> None:
    out = tmp_path / "images.jsonl"
    args = ["simulate", helsinki, "-o", out, "--n", "200", "-q"] + ([f"--bbox={bbox}"] if bbox else [])
    result = run(*args)
    assert result.exit_code == 0, result.output
    truth = [json.loads(line)["truth"] for line in out.read_text().splitlines()]
    x = np.array([t["x"] for t in truth])
    y = np.array([t["y"] for t in truth])
    with open_map(helsinki) as m:
        minx, miny, maxx, maxy = m.bounds
    # Uniform over the map: the cameras span most of its extent both ways, and stay on it.
    assert np.ptp(x) > 0.8 * (maxx - minx) and np.ptp(y) > 0.8 * (maxy - miny)
    assert x.min() >= minx - 1 and x.max() <= maxx + 1 and y.min() >= miny - 1 and y.max() <= maxy + 1


def test_simulate_box_missing_the_map(helsinki: Path, tmp_path: Path) -> None:
    out = tmp_path / "images.jsonl"
    assert_one_line_error(run("simulate", helsinki, "-o", out, "--bbox=170,50,-170,70"), "bbox")
    assert not out.exists()
    with open_map(helsinki) as m:
        with pytest.raises(EmptyMapError):
            map_bbox_from_lonlat(m.crs, (170.0, 50.0, -170.0, 70.0), within=m.bounds)
        # A box over part of the map keeps the cameras inside that part.
        lon, lat, _ = lonlat_of(helsinki)
        box = (float(np.median(lon)), float(np.median(lat)), 180.0, 90.0)
        area = map_bbox_from_lonlat(m.crs, box, within=m.bounds)
        images = simulate_images(m, 50, bbox=area, seed=3)
        cams = np.array([[im["truth"]["x"], im["truth"]["y"]] for im in images])
        cam_lon, cam_lat = Transformer.from_crs(m.crs, "EPSG:4326", always_xy=True).transform(cams[:, 0], cams[:, 1])
        assert (np.asarray(cam_lon) >= box[0] - 0.01).all() and (np.asarray(cam_lat) >= box[1] - 0.01).all()


# ------------------------------------------------------------------------------------ the geometry itself


def test_check_bbox_rules() -> None:
    assert check_bbox(["170", "50", "-170", "70"]) == (170.0, 50.0, -170.0, 70.0)
    assert check_bbox(WORLD) == WORLD
    for bad in [(0, 0, 1), (math.inf, 0, 1, 1), (0, math.nan, 1, 1), (0, -91, 1, 1), (-180.5, 0, 1, 1),
                (0, 1, 1, 1), (0, 2, 1, 1), (3, 0, 3, 1), ("x", 0, 1, 1)]:
        with pytest.raises(ValueError):
            check_bbox(bad)


def test_in_bbox_and_splitting() -> None:
    lon = np.array([175.0, -175.0, 0.0, 180.0, -180.0, 170.0])
    lat = np.full(lon.size, 60.0)
    assert in_bbox((170, 50, -170, 70), lon, lat).tolist() == [True, True, False, True, True, True]
    assert in_bbox((170, 50, 180, 70), lon, lat).tolist() == [True, False, False, True, True, True]
    assert in_bbox((-180, 50, -170, 70), lon, lat).tolist() == [False, True, False, True, True, False]
    assert not in_bbox((170, 61, -170, 70), lon, lat).any()
    assert split_bbox((170, 50, -170, 70)) == [(170.0, 50.0, 180.0, 70.0), (-180.0, 50.0, -170.0, 70.0)]
    assert intersect_bboxes((170, 50, -170, 70), (0, 0, 10, 10)) == []
    assert intersect_bboxes(WORLD, (170, 50, -170, 70)) == split_bbox((170, 50, -170, 70))
    assert central_longitude(np.array([179.0, 179.5, -179.8])) == 179.5


def test_projected_window_holds_the_data_and_stays_in_the_domain() -> None:
    # A UTM zone 35 box around Helsinki: the world, or a box crossing the antimeridian that holds
    # Helsinki, gives the map itself; a box elsewhere gives None.
    within = (370_000.0, 6_660_000.0, 410_000.0, 6_690_000.0)
    assert projected_window("EPSG:32635", WORLD, within) == within
    assert projected_window("EPSG:32635", (20, 50, -170, 70), within) == within
    assert projected_window("EPSG:32635", (170, 50, -170, 70), within) is None
    # Without the data's extent, the CRS's area of use (24-30 E, 0-84 N) bounds the answer: finite.
    box = projected_window("EPSG:32635", WORLD)
    assert box is not None and all(math.isfinite(v) for v in box)
    assert 100_000 < box[0] < 200_000 and 800_000 < box[2] < 900_000
    # A polar map: its lon/lat extent is every longitude, up to the pole.
    extent = lonlat_extent("EPSG:3413", (-1e6, -1e6, 1e6, 1e6))
    assert extent is not None and extent[0] == -180.0 and extent[2] == 180.0 and extent[3] == 90.0


def test_build_map_api_checks_its_box(tmp_path: Path) -> None:
    source = _antimeridian_town(tmp_path)
    for bad in [(math.inf, 0, 1, 1), (0, 95, 1, 96), (0, 10, 1, 5)]:
        with pytest.raises(SourceError, match="bbox"):
            build_map([source], tmp_path / "m.mapdb", bbox=bad)
    assert not (tmp_path / "m.mapdb").exists()
