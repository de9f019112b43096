"""Layers read in batches, GeoParquet row groups pruned, Overture buildings, blocks formed tile by tile, and
their bad inputs (issue 31, "Every source streams")."""

from __future__ import annotations

import json
import os
import re
import shutil
from collections import Counter
from pathlib import Path

import geopandas as gpd
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import shapely
from click.testing import CliRunner
from mapdb_cli.main import cli
from shapely.geometry import MultiPoint, Point, box

from mapdb.build import tiles
from mapdb.build.blocks import BuildingOutlines
from mapdb.build.pipeline import build_map
from mapdb.build.tiles import FootprintTiles
from mapdb.classmap import load_class_table
from mapdb.errors import MapdbIOError, SourceError
from mapdb.labels import default_label_table
from mapdb.objects import concat
from mapdb.sources import layerfiles
from mapdb.sources.layers import layer_batches, read_layer
from mapdb.sources.parquet import open_parquet

LABELS = default_label_table().labels
LON0, LAT0 = 7.40, 43.70
D = 0.0001  # about 8 m east-west, 11 m north-south


def _town(n: int, seed: int = 0) -> gpd.GeoDataFrame:
    """``n`` houses in lon/lat, some touching in rows (blocks), plus points and a multipoint, labelled."""
    rng = np.random.default_rng(seed)
    x = LON0 + D * 1.5 * (np.arange(n) % 40) + rng.uniform(0, D / 4, n)
    y = LAT0 + D * 2.0 * (np.arange(n) // 40)
    geoms = list(shapely.box(x, y, x + D * (1.2 + (np.arange(n) % 3 == 0) * 0.5), y + D))
    labels = ["building"] * n
    geoms += [Point(LON0 - D, LAT0 - D), MultiPoint([(LON0 - 2 * D, LAT0), (LON0 - 3 * D, LAT0)])]
    labels += ["road_intersection", "parking"]
    return gpd.GeoDataFrame({"label": labels}, geometry=geoms, crs="EPSG:4326")


def _same(a, b) -> None:  # type: ignore[no-untyped-def]
    assert a.crs == b.crs and a.labels == b.labels
    for name in ("x", "y", "label", "area"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("suffix", [".gpkg", ".fgb", ".parquet", ".geojson"])
def test_small_batches_give_the_objects_of_one_batch(tmp_path: Path, suffix: str) -> None:
    frame = _town(300)
    path = tmp_path / f"town{suffix}"
    frame.to_parquet(path) if suffix == ".parquet" else frame.to_file(path, engine="pyogrio")
    whole = read_layer(path, LABELS)
    parts = list(layer_batches(path, LABELS, rows=7))
    assert len(parts) == -(-302 // 7) and max(len(p) for p in parts) <= 8  # 7 features: a multipoint gives two
    # The equal-area projection of the geographic polygons is centred on the whole layer's box in both reads:
    # the same centroids and areas to the last bit, in the same order batch by batch (multipoints split).
    _same(concat(parts, labels=LABELS), whole)
    assert whole.counts() == {"building": 300, "road_intersection": 1, "parking": 2}


def test_csv_in_chunks_equals_one_read_and_names_the_bad_line(tmp_path: Path) -> None:
    path = tmp_path / "points.csv"
    lines = [f"{LON0 + i * D},{LAT0},park" for i in range(50)] + ["nan,43.7,park", ",43.7,park"]
    path.write_text("lon,lat,label\n" + "\n".join(lines) + "\n")
    counts: Counter[str] = Counter()
    parts = list(layer_batches(path, LABELS, counts=counts, rows=6))
    assert len(parts) == 9 and counts == {"invalid_coordinates": 2}
    _same(concat(parts, labels=LABELS), read_layer(path, LABELS))
    path.write_text(path.read_text() + "seven,43.7,park\n")
    with pytest.raises(SourceError, match=r"points\.csv: line 54: lon,lat are not numbers"):
        list(layer_batches(path, LABELS, rows=6))
    header = tmp_path / "header.csv"
    header.write_text("lon,lat,label\n")
    assert [len(p) for p in layer_batches(header, LABELS, rows=6)] == [0]


def _overture(path: Path, groups: list[tuple[float, float]], *, columns: dict | None = None,
              statistics: bool = True, n: int = 20) -> None:
    """An Overture buildings file: one row group of ``n`` houses around each (lon, lat) of ``groups``."""
    tables = []
    for g, (lon, lat) in enumerate(groups):
        houses = shapely.box(lon + D * 2 * np.arange(n), lat, lon + D * 2 * np.arange(n) + D, lat + D)
        bounds = shapely.bounds(houses)
        data = {
            "id": [f"08b{g:02d}{i:04d}" for i in range(n)],
            "geometry": shapely.to_wkb(houses),
            "bbox": pa.StructArray.from_arrays([pa.array(bounds[:, i], pa.float32()) for i in range(4)],
                                               ["xmin", "ymin", "xmax", "ymax"]),
            "subtype": ["residential"] * (n - 2) + ["transportation", None],
            "class": ["house"] * (n - 2) + ["parking", None],
            "height": np.linspace(3.0, 12.0, n),
        }
        data.update(columns or {})
        tables.append(pa.table(data))
    table = pa.concat_tables(tables)
    geo = {"version": "1.1.0", "primary_column": "geometry", "columns": {"geometry": {
        "encoding": "WKB", "geometry_types": ["Polygon"],
        "covering": {"bbox": {k: ["bbox", k] for k in ("xmin", "ymin", "xmax", "ymax")}}}}}
    if "geometry" not in table.schema.names:
        geo = {"version": "1.1.0", "primary_column": "geometry", "columns": {}}
    table = table.replace_schema_metadata({"geo": json.dumps(geo)})
    pq.write_table(table, path, row_group_size=n, write_statistics=statistics)


def _spoil_row_groups(path: Path, groups: list[int]) -> None:
    """Overwrite the column data of row groups with zeros: reading any of them fails."""
    meta = pq.ParquetFile(path).metadata
    data = bytearray(path.read_bytes())
    for g in groups:
        for c in range(meta.num_columns):
            chunk = meta.row_group(g).column(c)
            start = chunk.dictionary_page_offset or chunk.data_page_offset
            data[start:start + chunk.total_compressed_size] = bytes(chunk.total_compressed_size)
    path.write_bytes(bytes(data))


PLACES = [(7.40, 43.70), (8.50, 47.30), (-3.70, 40.40), (2.35, 48.85)]


def test_overture_row_groups_outside_the_box_are_not_read(tmp_path: Path) -> None:
    path = tmp_path / "buildings.parquet"
    _overture(path, PLACES)
    assert pq.ParquetFile(path).metadata.num_row_groups == 4
    box = (8.4, 47.2, 8.6, 47.4)  # around the second group only
    assert open_parquet(path, box).row_groups == [1]
    _spoil_row_groups(path, [0, 2, 3])
    counts: Counter[str] = Counter()
    objects = read_layer(path, LABELS, bbox=box, counts=counts)
    # Every Overture building is a building, whatever its subtype and class (as OSM's building=* are).
    assert objects.counts() == {"building": 20} and not +counts
    assert ((objects.x > 8.5) & (objects.x < 8.51) & (objects.y > 47.3) & (objects.y < 47.301)).all()
    with pytest.raises(SourceError, match=r"buildings\.parquet: not a readable vector layer"):
        read_layer(path, LABELS)  # without a box every row group is read, and the spoiled ones fail


def test_overture_class_mapped_by_a_label_map(tmp_path: Path) -> None:
    path = tmp_path / "buildings.parquet"
    _overture(path, PLACES[:2])
    table = tmp_path / "classes.toml"
    table.write_text('column = "class"\n[classes]\nhouse = "building"\nparking = "parking"\n')
    counts: Counter[str] = Counter()
    objects = read_layer(path, LABELS, label_map=load_class_table(table, LABELS, column=True), counts=counts)
    assert objects.counts() == {"building": 36, "parking": 2}  # the rows without a class have no label


@pytest.mark.parametrize(("columns", "problem"), [
    ({"geometry": None}, r"an Overture buildings file without column\(s\) geometry \(columns: id, bbox, subtype"),
    ({"id": None}, r"an Overture buildings file without column\(s\) id \(columns: geometry, bbox, subtype"),
    ({"bbox": [1.0] * 20}, "Overture column 'bbox' is double, not a struct of xmin, ymin, xmax, ymax"),
])
def test_an_overture_file_without_its_columns_is_one_line_before_any_output(tmp_path: Path, columns: dict,
                                                                            problem: str) -> None:
    path = tmp_path / "broken.parquet"
    drop = [k for k, v in columns.items() if v is None]
    _overture(path, PLACES[:1], columns={k: v for k, v in columns.items() if v is not None})
    if drop:
        table = pq.read_table(path)
        pq.write_table(table.drop_columns(drop), path)
    with pytest.raises(SourceError, match=problem):
        read_layer(path, LABELS)
    out = tmp_path / "m.mapdb"
    result = CliRunner().invoke(cli, ["build", str(path), "-o", str(out), "-q"])
    assert result.exit_code == 1 and not out.exists() and result.stdout == ""
    assert re.match(f"mapdb: error: {re.escape(str(path))}: {problem}", result.stderr)
    assert len(result.stderr.strip().splitlines()) == 1


def test_a_geoparquet_without_bbox_statistics_is_read_whole_and_said_once(tmp_path: Path) -> None:
    path = tmp_path / "nostats.parquet"
    _overture(path, PLACES, statistics=False)
    box = (8.4, 47.2, 8.6, 47.4)
    layer = open_parquet(path, box)
    assert layer.row_groups == [0, 1, 2, 3] and not layer.pruned
    notes: list[str] = []
    parts = list(layer_batches(path, LABELS, bbox=box, notes=notes.append))
    assert notes == ["nostats.parquet: no bbox statistics (a bbox column with per-row-group min/max): every row "
                     "group read, none skipped by --bbox"]
    assert concat(parts, labels=LABELS).counts() == {"building": 20}
    out = tmp_path / "m.mapdb"
    result = CliRunner().invoke(cli, ["build", str(path), "-o", str(out), "--bbox", "8.4,47.2,8.6,47.4"])
    assert result.exit_code == 0 and result.stderr.count("no bbox statistics") == 1


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the test's own NaN polygon
def test_rows_without_geometry_or_with_bad_coordinates_are_counted_and_said(tmp_path: Path) -> None:
    houses = [box(LON0 + i * 2 * D, LAT0, LON0 + i * 2 * D + D, LAT0 + D) for i in range(4)]
    nan = shapely.Polygon([(LON0, LAT0 + 5 * D), (np.nan, LAT0 + 6 * D), (LON0 + D, LAT0 + 5 * D)])
    frame = gpd.GeoDataFrame({"label": ["building"] * 6 + [None]},
                             geometry=[*houses, None, nan, None], crs="EPSG:4326")
    path = tmp_path / "gaps.parquet"
    frame.to_parquet(path)
    counts: Counter[str] = Counter()
    assert len(read_layer(path, LABELS, counts=counts)) == 4
    # The row without a label is no feature at all; the labelled one without geometry is counted.
    assert +counts == {"missing_geometries": 1, "invalid_coordinates": 1}
    out = tmp_path / "m.mapdb"
    result = CliRunner().invoke(cli, ["build", str(path), "-o", str(out), "--no-blocks"])
    assert result.exit_code == 0, result.stderr
    assert json.loads(result.stdout)["skipped"] == {"invalid_coordinates": 1, "missing_geometries": 1}
    assert "1 layer features skipped: a label but no geometry (null or empty)" in result.stderr
    assert "1 objects skipped: a coordinate not a finite number" in result.stderr


def test_a_source_too_large_for_the_free_disk_is_one_line_before_any_output(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "points.csv"
    path.write_text("lon,lat,label\n" + "".join(f"{LON0 + i * D},{LAT0},park\n" for i in range(2000)))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    real = shutil.disk_usage

    def nearly_full(where: str | os.PathLike[str]):  # type: ignore[no-untyped-def]
        usage = real(where)
        return usage._replace(free=1000) if str(where).startswith(str(scratch)) else usage

    # The disk is the machine's: its free space is made to look nearly gone for the scratch directory only.
    monkeypatch.setattr(shutil, "disk_usage", nearly_full)
    out = tmp_path / "m.mapdb"
    result = CliRunner().invoke(cli, ["build", str(path), "-o", str(out), "-q", "--spool", "file", "--index-dir",
                                      str(scratch)])
    assert result.exit_code == 1 and not out.exists() and result.stdout == ""
    line = result.stderr.strip()
    assert line.startswith(f"mapdb: error: {path}: too large for the free disk: its objects need about 0.")
    assert "which has 0.00 MB free; free some space or choose another directory (--index-dir)" in line
    assert len(line.splitlines()) == 1 and not list(scratch.iterdir())


def _houses(n: int, seed: int) -> np.ndarray:
    """``n`` houses of 10-30 m around a tile corner (7.0, 45.0), a tenth of a degree either way."""
    rng = np.random.default_rng(seed)
    cx, cy = 7.0 + rng.uniform(-0.1, 0.1, n), 45.0 + rng.uniform(-0.1, 0.1, n)
    w, h = rng.uniform(6e-5, 2e-4, n), rng.uniform(5e-5, 1.5e-4, n)
    return shapely.box(cx - w, cy - h, cx + w, cy + h)


def test_blocks_formed_tile_by_tile_equal_those_formed_at_once(tmp_path: Path) -> None:
    labels = ("building", "building_block")
    footprints = _houses(6000, 1)
    whole = BuildingOutlines(0)
    whole.keep(footprints)
    expected = whole.blocks(labels)
    tiled = FootprintTiles(tmp_path)
    for part in np.array_split(footprints, 5):
        tiled.add(part)
    got = concat(list(tiled.blocks(labels)), labels=labels)
    assert len(tiled.homes) >= 4 and tiled.cut == 0  # the footprints lie in four tiles or more
    assert len(got) == len(expected) > 100
    key = np.lexsort((expected.y, expected.x)), np.lexsort((got.y, got.x))
    for name in ("x", "y", "area"):
        assert np.array_equal(getattr(expected, name)[key[0]], getattr(got, name)[key[1]]), name
    tiled.discard()
    assert not tiled.directory.exists()


def test_a_block_longer_than_the_margin_is_cut_into_counted_parts(tmp_path: Path) -> None:
    labels = ("building", "building_block")
    # A terrace of 60 touching houses of 10 m along a parallel, across the tile edge at 7.1 E: 600 m.
    west = 7.1 - 30 * 0.000127
    terrace = shapely.box(west + 0.000127 * np.arange(60), 45.05, west + 0.000127 * (np.arange(60) + 1), 45.0501)
    tiled = FootprintTiles(tmp_path, margin_m=100.0)
    tiled.add(terrace)
    parts = concat(list(tiled.blocks(labels)), labels=labels)
    assert tiled.cut == 2 and len(parts) == 2  # cut at the tile edge: each tile stores its own 30 houses
    whole = BuildingOutlines(0)
    whole.keep(terrace)
    assert len(whole.blocks(labels)) == 1
    assert parts.area.sum() == pytest.approx(whole.blocks(labels).area[0], rel=1e-9)
    assert np.sort(parts.x)[0] < 7.1 < np.sort(parts.x)[1]
    wide = FootprintTiles(tmp_path, margin_m=750.0)
    wide.add(terrace)
    assert len(list(wide.blocks(labels))) == 1 and wide.cut == 0


def test_a_large_layer_build_writes_the_map_of_one_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    frame = _town(400)
    path = tmp_path / "town.gpkg"
    frame.to_file(path, engine="pyogrio")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    one = build_map([path], tmp_path / "one.mapdb")
    # Batches of 9 features, the objects spooled to a file, the footprints to tile files past 50 of them.
    monkeypatch.setattr(layerfiles, "BATCH_ROWS", 9)
    monkeypatch.setattr(tiles, "OUTLINES_IN_MEMORY", 50)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    say: list[str] = []
    many = build_map([path], tmp_path / "many.mapdb", spool="file", index_dir=scratch, progress=say.append)
    assert any("blocks of touching buildings" in m and "tiles" in m for m in say)
    assert one["labels"] == many["labels"] and one["labels"]["building_block"] > 5
    assert (tmp_path / "one.mapdb").read_bytes() == (tmp_path / "many.mapdb").read_bytes()
    assert not list(scratch.iterdir())


def test_a_missing_spool_directory_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(MapdbIOError, match="cannot hold the footprints read"):
        FootprintTiles(tmp_path / "absent")


def test_jobs_on_small_sources_read_here_and_write_the_same_map(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    paths = []
    for i in range(2):
        path = tmp_path / f"town{i}.gpkg"
        _town(50, seed=i).to_file(path, engine="pyogrio")
        paths.append(path)
    here = build_map(paths, tmp_path / "here.mapdb")
    say: list[str] = []
    jobs = build_map(paths, tmp_path / "jobs.mapdb", jobs=2, progress=say.append)
    # No cluster is started for sources that small: said, and the same map.
    assert [m for m in say if m.startswith("--jobs 2: reading here, in one process")]
    assert not [m for m in say if "Dask workers" in m]
    assert here["labels"] == jobs["labels"]
    assert (tmp_path / "here.mapdb").read_bytes() == (tmp_path / "jobs.mapdb").read_bytes()
