"""Tests of the vector-layer source: files of every supported format written here with geopandas."""

from __future__ import annotations

from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import shapely
from pyproj import Geod, Transformer
from shapely.geometry import LineString, MultiPoint, Point, Polygon, box

from mapdb.errors import MapdbIOError, SourceError
from mapdb.labels import default_label_table
from mapdb.objects import concat
from mapdb.sources.layers import LAYER_SUFFIXES, is_layer_path, read_layer

LABELS = default_label_table().labels
SEGMENTATION = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "segmentation" / "spacenet4_atlanta"

X0, Y0 = 500_000.0, 5_000_000.0


def sample_frame(crs: str | None = "EPSG:32632") -> gpd.GeoDataFrame:
    """Two points and two polygons with known centroids and areas, in UTM metres."""
    return gpd.GeoDataFrame(
        {"label": ["building", "road_intersection", "park", "water"], "name": ["a", "b", "c", "d"]},
        geometry=[
            Point(X0 + 10, Y0 + 20),
            Point(X0 + 100, Y0 - 50),
            box(X0, Y0, X0 + 200, Y0 + 100),                                       # centroid (100, 50), 20000 m^2
            Polygon([(X0 + 1000, Y0), (X0 + 1300, Y0), (X0 + 1000, Y0 + 300)]),    # triangle: (100, 100), 45000
        ],
        crs=crs,
    )


EXPECTED = {
    "building": (X0 + 10, Y0 + 20, 0.0),
    "road_intersection": (X0 + 100, Y0 - 50, 0.0),
    "park": (X0 + 100, Y0 + 50, 20_000.0),
    "water": (X0 + 1100, Y0 + 100, 45_000.0),
}


def by_name(objects) -> dict[str, tuple[float, float, float]]:
    return {n: (x, y, a) for n, x, y, a in zip(objects.names(), objects.x, objects.y, objects.area, strict=True)}


def assert_expected(objects, expected=EXPECTED) -> None:
    got = by_name(objects)
    assert sorted(got) == sorted(expected)
    for name, (x, y, area) in expected.items():
        assert got[name] == pytest.approx((x, y, area), abs=1e-6), name


def write(frame: gpd.GeoDataFrame, path: Path) -> Path:
    if path.suffix in (".parquet", ".geoparquet"):
        frame.to_parquet(path)
    else:
        frame.to_file(path, engine="pyogrio")
    return path


@pytest.mark.parametrize("suffix", [".geojson", ".json", ".gpkg", ".parquet", ".geoparquet", ".shp", ".fgb"])
def test_each_format_round_trips(tmp_path: Path, suffix: str) -> None:
    # Points and polygons in separate files: a shapefile holds one geometry type.
    frame = sample_frame()
    is_point = frame.geom_type == "Point"
    parts = [read_layer(write(frame[kind], tmp_path / f"{name}{suffix}"), LABELS)
             for name, kind in (("points", is_point), ("polygons", ~is_point))]
    for objects in parts:
        assert objects.crs == "EPSG:32632"
        assert objects.labels == LABELS
    assert parts[0].area.tolist() == [0.0, 0.0]
    assert_expected(concat(parts))


def test_label_column_by_name(tmp_path: Path) -> None:
    frame = sample_frame().rename(columns={"label": "kind"})
    path = write(frame, tmp_path / "kind.gpkg")
    assert_expected(read_layer(path, LABELS, label_column="kind"))


def test_missing_label_column(tmp_path: Path) -> None:
    path = write(sample_frame().drop(columns="label"), tmp_path / "nolabel.gpkg")
    with pytest.raises(SourceError, match=r"nolabel\.gpkg: no column 'label' \(columns: name\)"):
        read_layer(path, LABELS)


def test_unknown_labels_are_named(tmp_path: Path) -> None:
    frame = sample_frame()
    frame.loc[1, "label"] = "helipad"
    frame.loc[2, "label"] = "bandstand"
    path = write(frame, tmp_path / "odd.geojson")
    with pytest.raises(SourceError, match=r"odd\.geojson: unknown label\(s\) 'bandstand', 'helipad'.*--labels"):
        read_layer(path, LABELS)


def test_labels_fix_the_codes(tmp_path: Path) -> None:
    path = write(sample_frame(), tmp_path / "layer.fgb")
    mine = ("water", "park", "road_intersection", "building", "unused")
    objects = read_layer(path, mine)
    assert objects.labels == mine
    assert_expected(objects)


def test_geographic_polygons_centroid_and_area(tmp_path: Path) -> None:
    # A 1 km x 2 km rectangle and a triangle drawn in UTM, stored in lon/lat.
    to_lonlat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    frame = sample_frame().to_crs("EPSG:4326")
    path = write(frame, tmp_path / "lonlat.geojson")
    objects = read_layer(path, LABELS)
    assert objects.crs == "EPSG:4326"
    geod = Geod(ellps="WGS84")
    got = by_name(objects)
    for name, (x, y, area) in EXPECTED.items():
        lon, lat = to_lonlat.transform(x, y)
        # Centroids: the UTM centroid and the lon/lat one differ by far less than a metre at this size.
        assert got[name][0] == pytest.approx(lon, abs=1e-6) and got[name][1] == pytest.approx(lat, abs=1e-6)
        if area:
            geodesic = abs(geod.geometry_area_perimeter(frame.geometry[frame.label == name].iloc[0])[0])
            assert got[name][2] == pytest.approx(geodesic, rel=1e-4)
            # and the ground area matches the UTM drawing up to UTM's scale factor (0.9996^2)
            assert got[name][2] == pytest.approx(area, rel=2e-3)
        else:
            assert got[name][2] == 0.0


def test_projected_feet_areas_in_square_metres(tmp_path: Path) -> None:
    # EPSG:2229 (California zone 5) is in US survey feet: 1000 ft x 1000 ft = 92903.4 m^2.
    frame = gpd.GeoDataFrame({"label": ["park"]}, geometry=[box(6.5e6, 1.8e6, 6.5e6 + 1000, 1.8e6 + 1000)],
                             crs="EPSG:2229")
    objects = read_layer(write(frame, tmp_path / "feet.gpkg"), LABELS)
    assert objects.crs == "EPSG:2229"
    assert objects.area[0] == pytest.approx((1000 * 1200 / 3937) ** 2)
    assert objects.x[0] == pytest.approx(6.5e6 + 500)   # centroid stays in the layer's units


def test_csv_lonlat(tmp_path: Path) -> None:
    path = tmp_path / "poi.csv"
    path.write_text("lon,lat,label,note\n7.44,46.95,stadium,Wankdorf\n7.45, 46.94 ,building,\n")
    objects = read_layer(path, LABELS)
    assert objects.crs == "EPSG:4326"
    assert objects.names().tolist() == ["stadium", "building"]
    assert objects.x.tolist() == [7.44, 7.45] and objects.y.tolist() == [46.95, 46.94]
    assert objects.area.tolist() == [0.0, 0.0]


def test_csv_xy_needs_crs(tmp_path: Path) -> None:
    path = tmp_path / "xy.csv"
    path.write_text("x,y,label\n500010,5000020,building\n500100,4999950,road_intersection\n")
    with pytest.raises(SourceError, match=r"xy\.csv: CSV with x,y columns needs their CRS"):
        read_layer(path, LABELS)
    objects = read_layer(path, LABELS, crs="EPSG:32632")
    assert objects.crs == "EPSG:32632"
    assert_expected(objects, {k: v for k, v in EXPECTED.items() if k in ("building", "road_intersection")})


def test_csv_problems(tmp_path: Path) -> None:
    no_coords = tmp_path / "nocoords.csv"
    no_coords.write_text("east,north,label\n1,2,building\n")
    with pytest.raises(SourceError, match=r"needs columns x,y or lon,lat \(columns: east, north, label\)"):
        read_layer(no_coords, LABELS)
    no_label = tmp_path / "nolabel.csv"
    no_label.write_text("lon,lat,kind\n1,2,building\n")
    with pytest.raises(SourceError, match=r"nolabel\.csv: no column 'label' \(columns: lon, lat, kind\)"):
        read_layer(no_label, LABELS)
    bad_number = tmp_path / "bad.csv"
    bad_number.write_text("lon,lat,label\n1,2,building\nseven,2,building\n")
    with pytest.raises(SourceError, match=r"bad\.csv: line 3: lon,lat are not numbers"):
        read_layer(bad_number, LABELS)
    xy = tmp_path / "xy.csv"
    xy.write_text("x,y,label\n1,2,building\n")
    with pytest.raises(SourceError, match="is not a CRS"):
        read_layer(xy, LABELS, crs="EPSG:nonsense")


def test_nulls_and_empty_geometries_skipped(tmp_path: Path) -> None:
    frame = gpd.GeoDataFrame(
        {"label": ["building", None, "park", "water", "  "]},
        geometry=[Point(X0, Y0), Point(X0 + 1, Y0), None, Polygon(), Point(X0 + 2, Y0)],
        crs="EPSG:32632",
    )
    path = write(frame, tmp_path / "gaps.gpkg")
    objects = read_layer(path, LABELS)
    assert objects.names().tolist() == ["building"]


def test_lines_become_their_centroid_and_multipoints_split(tmp_path: Path) -> None:
    frame = gpd.GeoDataFrame(
        {"label": ["roundabout", "building"]},
        geometry=[LineString([(X0, Y0), (X0 + 30, Y0), (X0 + 30, Y0 + 10)]),
                  MultiPoint([(X0 + 5, Y0 + 5), (X0 + 7, Y0 + 9)])],
        crs="EPSG:32632",
    )
    path = write(frame, tmp_path / "mixed.geojson")
    objects = read_layer(path, LABELS)
    assert objects.counts() == {"building": 2, "roundabout": 1}
    line = objects.names() == "roundabout"
    # Length-weighted centroid of the two segments: 30 m at (15, 0) and 10 m at (30, 5).
    assert objects.x[line][0] == pytest.approx(X0 + (30 * 15 + 10 * 30) / 40)
    assert objects.y[line][0] == pytest.approx(Y0 + (10 * 5) / 40)
    assert objects.area.tolist() == [0.0, 0.0, 0.0]
    assert sorted(objects.x[~line].tolist()) == [X0 + 5, X0 + 7]


@pytest.mark.filterwarnings("ignore:'crs' was not provided")
def test_layer_without_crs(tmp_path: Path) -> None:
    frame = sample_frame(crs=None)
    path = write(frame[frame.geom_type == "Polygon"], tmp_path / "noprj.shp")
    assert not path.with_suffix(".prj").exists()
    with pytest.raises(SourceError, match=r"noprj\.shp: layer has no CRS"):
        read_layer(path, LABELS)
    # The caller may say what it is.
    assert_expected(read_layer(path, LABELS, crs="EPSG:32632"), {k: EXPECTED[k] for k in ("park", "water")})


def test_bbox_filters_by_centroid(tmp_path: Path) -> None:
    path = write(sample_frame(), tmp_path / "layer.gpkg")
    to_lonlat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    lon0, lat0 = to_lonlat.transform(X0 - 20, Y0 - 100)
    lon1, lat1 = to_lonlat.transform(X0 + 500, Y0 + 200)
    objects = read_layer(path, LABELS, bbox=(lon0, lat0, lon1, lat1))
    assert sorted(objects.names().tolist()) == ["building", "park", "road_intersection"]


def test_not_a_layer_and_missing(tmp_path: Path) -> None:
    junk = tmp_path / "junk.geojson"
    junk.write_text("{ this is not json")
    with pytest.raises(SourceError, match=r"junk\.geojson: not a readable vector layer \("):
        read_layer(junk, LABELS)
    plain_parquet = tmp_path / "plain.parquet"
    sample_frame().drop(columns="geometry").to_parquet(plain_parquet)
    with pytest.raises(SourceError, match=r"plain\.parquet: not a readable vector layer"):
        read_layer(plain_parquet, LABELS)
    with pytest.raises(MapdbIOError, match="no such file"):
        read_layer(tmp_path / "absent.gpkg", LABELS)


def test_layer_suffixes() -> None:
    assert all(is_layer_path(f"a{s}") for s in LAYER_SUFFIXES)
    assert is_layer_path("A.GPKG") and not is_layer_path("a.tif")


def test_real_building_footprints(tmp_path: Path) -> None:
    path = SEGMENTATION / "geotiff_labels.geojson"
    if not path.exists():
        pytest.skip(f"real data absent: {path} (expected ../shared/data beside the checkout)")
    # As published, the footprints carry OSM columns but no label column.
    with pytest.raises(SourceError, match=r"geotiff_labels\.geojson: no column 'label' \(columns: access, "):
        read_layer(path, LABELS)
    frame = gpd.read_file(path, engine="pyogrio")
    frame["label"] = "building"
    objects = read_layer(write(frame, tmp_path / "footprints.gpkg"), LABELS)
    assert objects.counts() == {"building": 43}
    # Atlanta houses of 18 to 377 m^2, inside the chip's bounds (EPSG:32616).
    assert objects.crs == "EPSG:32616"
    assert np.allclose(objects.area, shapely.area(frame.geometry.to_numpy()))
    assert 10 < objects.area.min() and objects.area.max() < 1000
    assert ((objects.x > 733_601) & (objects.x < 734_051) & (objects.y > 3_724_689) & (objects.y < 3_725_139)).all()
