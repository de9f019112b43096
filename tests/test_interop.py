"""Outputs GIS tools read right, and a Python API that speaks geopandas, shapely and lon/lat.

GeoJSON is exported in WGS 84 lon/lat (RFC 7946), the other formats in the map's CRS (they name it);
checked with geopandas, pyproj and, when installed, GDAL's ``ogrinfo``.  The map queries by shapely
geometry, by lon/lat box and by lon/lat and ground radius are checked against brute force.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import shapely
from click.testing import CliRunner
from mapdb_cli.main import cli
from pyproj import CRS, Geod, Transformer

from mapdb.build.pipeline import build_map
from mapdb.errors import LabelTableError
from mapdb.geo import in_bbox
from mapdb.mapfile.export import export_map
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.objects import Objects

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def helsinki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("interop") / "helsinki.mapdb"
    build_map([SAMPLE], out)
    return out


@pytest.fixture(scope="module")
def stored(helsinki: Path) -> tuple[Objects, np.ndarray, np.ndarray]:
    """The map's objects, and their lon/lat by pyproj."""
    with open_map(helsinki) as m:
        objects = m.all()
    lon, lat = Transformer.from_crs(objects.crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
    return objects, np.asarray(lon), np.asarray(lat)


# ------------------------------------------------------------------------------------------ export


def test_geojson_is_rfc7946_lonlat(helsinki: Path, stored, tmp_path: Path) -> None:
    objects, lon, lat = stored
    out = tmp_path / "objects.geojson"
    result = run("export", helsinki, "-o", out)
    assert result.exit_code == 0, result.output
    assert "WGS 84 lon/lat (EPSG:4326)" in result.stderr
    doc = json.loads(out.read_text())
    assert "crs" not in doc  # RFC 7946 section 4: no CRS member, lon/lat WGS 84 implied
    first = doc["features"][0]["geometry"]["coordinates"]
    assert 24.9 < first[0] < 25.0 and 60.1 < first[1] < 60.2  # longitude first (Helsinki: 24.9 E, 60.2 N)
    frame = gpd.read_file(out)
    assert frame.crs.to_epsg() == 4326 and len(frame) == len(objects)
    assert list(frame.columns) == ["label", "area_m2", "x", "y", "geometry"]
    # rows in the map's order; positions rounded to 7 decimals (RFC 7946's advice: about a centimetre)
    assert np.abs(frame.geometry.x.to_numpy() - lon).max() <= 5.1e-8
    assert np.abs(frame.geometry.y.to_numpy() - lat).max() <= 5.1e-8
    # the map positions too (GDAL writes 15 significant digits: the quantum's multiple, to the last bit or so)
    assert np.allclose(frame["x"], objects.x, rtol=1e-15, atol=0) and np.allclose(frame["y"], objects.y, rtol=1e-15)
    assert frame["label"].tolist() == objects.names().tolist()
    assert np.allclose(frame["area_m2"].to_numpy(), objects.area, rtol=1e-12)


def test_geojson_in_the_map_crs_on_request(helsinki: Path, stored, tmp_path: Path) -> None:
    objects, _, _ = stored
    out = tmp_path / "utm.geojson"
    result = run("export", helsinki, "-o", out, "--crs", "map")
    assert result.exit_code == 0, result.output
    assert "EPSG::32635" in json.loads(out.read_text())["crs"]["properties"]["name"]
    frame = gpd.read_file(out)
    assert frame.crs.to_epsg() == 32635
    assert np.allclose(frame.geometry.x, objects.x, atol=1e-6) and np.allclose(frame.geometry.y, objects.y, atol=1e-6)
    bad = run("export", helsinki, "-o", tmp_path / "x.geojson", "--crs", "EPSG:4326")
    assert bad.exit_code == 2 and "'lonlat', 'map'" in bad.output and not (tmp_path / "x.geojson").exists()


@pytest.mark.parametrize("suffix", [".gpkg", ".fgb", ".parquet"])
def test_formats_naming_their_crs_keep_the_map_crs_or_take_lonlat(helsinki: Path, stored, tmp_path: Path,
                                                                  suffix: str) -> None:
    objects, lon, lat = stored
    read = gpd.read_parquet if suffix == ".parquet" else gpd.read_file
    with open_map(helsinki) as m:
        assert export_map(m, tmp_path / f"map{suffix}") == len(objects)
        assert export_map(m, tmp_path / f"lonlat{suffix}", crs="lonlat") == len(objects)
        with pytest.raises(ValueError, match="lonlat, map"):
            export_map(m, tmp_path / f"bad{suffix}", crs="utm")
    in_map, in_lonlat = read(tmp_path / f"map{suffix}"), read(tmp_path / f"lonlat{suffix}")
    assert in_map.crs.to_epsg() == 32635 and in_lonlat.crs.to_epsg() == 4326
    # FlatGeobuf writes its spatial index order: compare by the exact map positions each row carries
    index = {(x, y, name): i for i, (x, y, name) in enumerate(zip(objects.x, objects.y, objects.names()))}
    for frame, want_x, want_y, tol in ((in_map, objects.x, objects.y, 1e-6), (in_lonlat, lon, lat, 1e-9)):
        rows = [index[(x, y, name)] for x, y, name in zip(frame["x"], frame["y"], frame["label"])]
        assert sorted(rows) == list(range(len(objects)))
        assert np.allclose(frame.geometry.x.to_numpy(), want_x[rows], rtol=0, atol=tol)
        assert np.allclose(frame.geometry.y.to_numpy(), want_y[rows], rtol=0, atol=tol)
    assert not (tmp_path / f"bad{suffix}").exists()


def test_csv_holds_map_positions_and_lonlat(helsinki: Path, stored, tmp_path: Path) -> None:
    objects, lon, lat = stored
    out = tmp_path / "objects.csv"
    result = run("export", helsinki, "-o", out)
    assert result.exit_code == 0 and "x,y in EPSG:32635 and WGS 84 lon,lat" in result.stderr
    table = pd.read_csv(out)
    assert list(table.columns) == ["label", "area_m2", "x", "y", "lon", "lat"]
    assert np.allclose(table["x"], objects.x, rtol=0, atol=1e-6)
    assert np.abs(table["lon"].to_numpy() - lon).max() <= 5.1e-9 and np.abs(table["lat"] - lat).max() <= 5.1e-9


def test_export_into_a_missing_directory_only_with_parents(helsinki: Path, tmp_path: Path) -> None:
    out = tmp_path / "no" / "such" / "objects.geojson"
    refused = run("export", helsinki, "-o", out)
    assert refused.exit_code == 1 and not (tmp_path / "no").exists()
    assert refused.stderr.splitlines() == [f"mapdb: error: {out}: directory {out.parent} does not exist"]
    made = run("export", helsinki, "-o", out, "--parents")
    assert made.exit_code == 0, made.output
    assert len(gpd.read_file(out)) > 500


def test_ogrinfo_reads_the_geojson_as_wgs84(helsinki: Path, stored, tmp_path: Path) -> None:
    ogrinfo = shutil.which("ogrinfo")
    if ogrinfo is None:
        pytest.skip("ogrinfo is not on PATH (GDAL's command-line tools: Debian package gdal-bin)")
    objects, lon, lat = stored
    out = tmp_path / "objects.geojson"
    assert run("export", helsinki, "-o", out).exit_code == 0
    report = subprocess.run([ogrinfo, "-so", "-al", str(out)], capture_output=True, text=True, check=True).stdout
    assert f"Feature Count: {len(objects)}" in report
    assert 'GEOGCRS["WGS 84"' in report and 'ID["EPSG",4326]' in report
    found = re.search(r"Extent: \(([-\d.]+), ([-\d.]+)\) - \(([-\d.]+), ([-\d.]+)\)", report)
    assert found, report
    extent = [float(v) for v in found.groups()]
    assert np.allclose(extent, [lon.min(), lat.min(), lon.max(), lat.max()], atol=1e-6)
    # and a GeoPackage names the map's projected CRS
    gpkg = tmp_path / "objects.gpkg"
    assert run("export", helsinki, "-o", gpkg).exit_code == 0
    report = subprocess.run([ogrinfo, "-so", "-al", str(gpkg)], capture_output=True, text=True, check=True).stdout
    assert 'ID["EPSG",32635]' in report and f"Feature Count: {len(objects)}" in report


# ------------------------------------------------------------------------------------------ Python API


def test_objects_to_geodataframe() -> None:
    o = Objects.from_names([1.0, 2.0, 3.0], [4.0, 5.0, 6.0], ["park", "water", "park"], area=[10.0, 0.0, 2.5],
                           crs="EPSG:32631")
    frame = o.to_geodataframe()
    assert list(frame.columns) == ["label", "area_m2", "geometry"] and frame.crs == CRS.from_epsg(32631)
    assert frame["label"].tolist() == ["park", "water", "park"] and frame["area_m2"].tolist() == [10.0, 0.0, 2.5]
    assert frame.geometry.x.tolist() == [1.0, 2.0, 3.0] and frame.geometry.y.tolist() == [4.0, 5.0, 6.0]
    empty = Objects.empty(["park"], crs="EPSG:32631").to_geodataframe()
    assert len(empty) == 0 and empty.crs == CRS.from_epsg(32631) and list(empty.columns) == list(frame.columns)
    assert Objects.from_names([0.0], [0.0], ["a"]).to_geodataframe().crs is None


def test_query_geometry_matches_brute_force(helsinki: Path, stored) -> None:
    objects, _, _ = stored
    rng = np.random.default_rng(3)
    with open_map(helsinki) as m:
        x0, y0, x1, y1 = m.bounds
        for _ in range(15):
            cx, cy = rng.uniform(x0, x1), rng.uniform(y0, y1)
            angles = np.sort(rng.uniform(0, 2 * np.pi, 7))
            radii = rng.uniform(50, 600, 7)
            polygon = shapely.Polygon(np.column_stack([cx + radii * np.cos(angles), cy + radii * np.sin(angles)]))
            want = shapely.intersects_xy(polygon, objects.x, objects.y)
            got = m.query_geometry(polygon)
            assert sorted(zip(got.x, got.y, got.label)) == sorted(zip(objects.x[want], objects.y[want],
                                                                      objects.label[want]))
            parks = m.query_geometry(polygon, labels=["park", "water"])
            assert len(parks) == int((want & np.isin(objects.names(), ["park", "water"])).sum())
        # a box gives what query_bbox gives, edges included
        box = (objects.x[0], objects.y[0], objects.x[0] + 300.0, objects.y[0] + 300.0)
        a, b = m.query_geometry(shapely.box(*box)), m.query_bbox(*box)
        assert len(a) > 0 and sorted(zip(a.x, a.y)) == sorted(zip(b.x, b.y))
        assert len(m.query_geometry(shapely.Point(objects.x[0], objects.y[0]))) >= 1
        assert len(m.query_geometry(shapely.Polygon())) == 0
        assert len(m.query_geometry(shapely.box(0, 0, 10, 10))) == 0  # far off the map
        with pytest.raises(TypeError, match="shapely geometry"):
            m.query_geometry((0, 0, 10, 10))


def test_query_lonlat_bbox_matches_brute_force(helsinki: Path, stored) -> None:
    objects, lon, lat = stored
    with open_map(helsinki) as m:
        for box in [(24.94, 60.165, 24.95, 60.175), (24.0, 60.0, 25.0, 61.0), (24.95, 60.17, 24.94, 60.18)]:
            want = in_bbox(box, lon, lat)
            got = m.query_lonlat_bbox(box)
            assert sorted(zip(got.x, got.y)) == sorted(zip(objects.x[want], objects.y[want]))
        assert len(m.query_lonlat_bbox((0.0, 0.0, 1.0, 1.0))) == 0
        assert len(m.query_lonlat_bbox((24.0, 60.0, 25.0, 61.0), labels=["water"])) == m.label_counts["water"]
        with pytest.raises(ValueError, match="latitudes"):
            m.query_lonlat_bbox((60.17, 24.94, 60.18, 95.0))  # lat, lon swapped: 95 is no latitude


def test_query_lonlat_is_the_geodesic_disc(helsinki: Path, stored) -> None:
    objects, lon, lat = stored
    geod = Geod(ellps="WGS84")
    rng = np.random.default_rng(5)
    with open_map(helsinki) as m:
        for i in range(12):
            k = rng.integers(len(objects))
            plon, plat = lon[k] + rng.normal(0, 0.002), lat[k] + rng.normal(0, 0.001)
            radius = [0.0, 1.0, 80.0, 400.0, 5000.0][i % 5]
            distance = geod.inv(np.full(len(lon), plon), np.full(len(lon), plat), lon, lat)[2]
            got = m.query_lonlat(plon, plat, radius)
            want = distance <= radius
            assert sorted(zip(got.x, got.y)) == sorted(zip(objects.x[want], objects.y[want]))
        # an object exactly at the place is found with a radius of 0
        assert len(m.query_lonlat(float(lon[0]), float(lat[0]), 0.0)) >= 1
        assert len(m.query_lonlat(float(lon[0]), float(lat[0]), 100_000.0)) == len(objects)
        assert len(m.query_lonlat(-24.94, 60.17, 1000.0)) == 0  # the other side of Greenwich: off the map
        found = m.query_lonlat(24.945, 60.17, 1000.0, labels="building")  # one name, not its letters
        assert set(found.names()) == {"building"}
        for args, problem in [((60.17, 94.9, 10.0), "latitude"), ((200.0, 60.0, 10.0), "longitude"),
                              ((24.9, 60.1, -1.0), "radius_m"), ((24.9, 60.1, float("nan")), "radius_m"),
                              (("24.9", 60.1, 10.0), "longitude")]:
            with pytest.raises(ValueError, match=problem):
                m.query_lonlat(*args)


@pytest.mark.parametrize("crs, place, far", [
    ("EPSG:3995", (0.0, 89.999), (180.0, 89.999)),  # Arctic polar stereographic: the disc holds the pole
    ("EPSG:32760", (179.9995, -17.0), (-179.9995, -17.0)),  # UTM 60S: the disc crosses the antimeridian
])
def test_query_lonlat_across_the_pole_and_the_antimeridian(crs: str, place, far) -> None:
    rng = np.random.default_rng(11)
    lon = np.concatenate([place[0] + rng.normal(0, 0.0005, 40), far[0] + rng.normal(0, 0.0005, 40)])
    lat = np.concatenate([place[1] + rng.normal(0, 0.0002, 40), far[1] + rng.normal(0, 0.0002, 40)])
    lon = (lon + 180.0) % 360.0 - 180.0
    lat = np.minimum(lat, 90.0)
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    m = MemoryMap(Objects.from_names(x, y, ["park"] * 80, crs=crs), quantum=0.01)
    stored = m.all()
    slon, slat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(stored.x, stored.y)
    distance = Geod(ellps="WGS84").inv(np.full(80, place[0]), np.full(80, place[1]), slon, slat)[2]
    for radius in (30.0, 150.0, 400.0):
        want = distance <= radius
        got = m.query_lonlat(*place, radius)
        assert sorted(zip(got.x, got.y)) == sorted(zip(stored.x[want], stored.y[want]))
    assert 40 < len(m.query_lonlat(*place, 400.0))  # objects on both sides


def test_a_mistyped_label_is_an_error_naming_the_labels(helsinki: Path) -> None:
    with open_map(helsinki) as m:
        x0, y0, x1, y1 = m.bounds
        queries = [lambda labels: m.query_bbox(x0, y0, x1, y1, labels=labels),
                   lambda labels: m.query_radius(x0, y0, 500.0, labels),
                   lambda labels: m.query_geometry(shapely.box(x0, y0, x1, y1), labels=labels),
                   lambda labels: m.query_lonlat(24.94, 60.17, 500.0, labels=labels),
                   lambda labels: m.query_lonlat_bbox((0.0, 0.0, 1.0, 1.0), labels=labels)]  # off the map too
        for query in queries:
            with pytest.raises(LabelTableError) as caught:
                query(["park", "buildng"])
            message = str(caught.value)
            assert "\n" not in message and str(m.path) in message and "'buildng'" in message
            assert "did you mean 'building'?" in message and "building, road_intersection" in message
            assert isinstance(caught.value, ValueError)
        assert len(m.query_bbox(x0, y0, x1, y1, labels=[])) == 0
        assert len(m.query_bbox(x0, y0, x1, y1, labels="park")) == m.label_counts["park"]
