"""The builder against broken and hostile input: what is skipped or repaired is counted, what cannot be
read ends in one line (exit 1, no traceback, no output left behind).

Every case is a small real file written here: OSM XML (tests/osmxml.py), GeoJSON and CSV layers,
sparse GeoTIFFs written with rasterio, and gzip / bzip2 bombs whose limit is scaled down (the module
constants of :mod:`mapdb.sources.osm.files`) so that they stay a few MB.
"""

from __future__ import annotations

import bz2
import gzip
import json
import math
import zlib
from collections import Counter
from pathlib import Path

import numpy as np
import osmium
import pytest
import rasterio
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import OsmXml, lonlat, square
from rasterio import Affine
from rasterio.windows import Window

import mapdb.sources.landcover.tiles as landcover_tiles
import mapdb.sources.osm.files as osm_files
from mapdb.build.pipeline import build_map
from mapdb.errors import LabelTableError, SourceError
from mapdb.labels import default_label_table, load_label_table
from mapdb.mapfile.reader import open_map
from mapdb.sources.landcover.reader import read_landcover
from mapdb.sources.layers import read_layer
from mapdb.sources.osm.reader import read_osm

TABLE = default_label_table()


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def assert_fails_cleanly(result, out: Path, *needles: str) -> str:
    """Exit 1, one ``mapdb: error:`` line naming what is wrong, no traceback, nothing left in out's folder."""
    line = assert_one_line_error(result, *needles)
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.stem}")], "temporary file left"
    return line


def build_ok(*args: object) -> dict:
    result = run("build", *args, "-q")
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


# ----------------------------------------------------------------------------------------------- OSM


def osm_with(tmp_path: Path, name: str, body: str) -> Path:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="test">\n{body}\n</osm>\n')
    return path


def test_osm_nodes_out_of_range_or_not_numbers_are_skipped_and_counted(tmp_path: Path) -> None:
    tag = '<tag k="building" v="yes"/>'
    nodes = [("60.1", "24.9"), ("95", "24.9"), ("60.1", "200"), ("nan", "24.9"), ("1e400", "24.9"),
             ("60.1", "-inf"), ("abc", "24.9"), ("60.2", " 24.9"), ("-90.5", "0"), ("60.3", "24.95")]
    body = "\n".join(f'<node id="{i + 1}" version="1" lat="{lat}" lon="{lon}">{tag}</node>'
                     for i, (lat, lon) in enumerate(nodes))
    source = osm_with(tmp_path, "nodes.osm", body)
    counts: Counter[str] = Counter()
    objects = read_osm(source, TABLE, counts=counts)
    # 60.1/24.9, " 24.9" (read as 24.9) and 60.3/24.95 are good; the other seven are skipped, never
    # moved (libosmium alone would put "1e400" at latitude 0).
    assert len(objects) == 3 and counts["invalid_coordinates"] == 7
    assert sorted(np.round(objects.y, 6).tolist()) == [60.1, 60.2, 60.3]
    summary = build_ok(source, "-o", tmp_path / "m.mapdb")
    assert summary["count"] == 3 and summary["skipped"] == {"invalid_coordinates": 7}
    with open_map(tmp_path / "m.mapdb") as m:
        assert m.metadata["sources"][0]["skipped"] == {"invalid_coordinates": 7}
    # The same nodes compressed: the same answer.
    for suffix, compress in ((".osm.gz", gzip.compress), (".osm.bz2", bz2.compress)):
        packed = tmp_path / f"nodes{suffix}"
        packed.write_bytes(compress(source.read_bytes()))
        counts = Counter()
        assert len(read_osm(packed, TABLE, counts=counts)) == 3 and counts["invalid_coordinates"] == 7


def test_osm_broken_ways_and_junctions(tmp_path: Path) -> None:
    doc = OsmXml()
    good = doc.ring(square(0.0, 0.0, 10.0), {"building": "yes"})
    # A ring with a node at latitude 95; a way tagged as an area that does not close; a bow tie.
    a, b, c = doc.node(100.0, 0.0), doc.node(120.0, 0.0), doc.node(120.0, 20.0)
    far = doc.node(95.0, 95.0, lon_lat=True)
    doc.way([a, b, c, far, a], {"building": "yes"})
    p, q, r, s = doc.node(200.0, 0.0), doc.node(220.0, 0.0), doc.node(220.0, 20.0), doc.node(200.0, 20.0)
    doc.way([p, q, r, s], {"building": "yes"})
    doc.way([p, r, q, s, p], {"leisure": "park"})
    # A roundabout through a node out of range, and three roads meeting at a node out of range.
    ra, rb = doc.node(300.0, 0.0), doc.node(320.0, 10.0)
    doc.way([ra, rb, far, ra], {"junction": "roundabout", "highway": "primary"})
    x0, x1, x2 = doc.node(400.0, 0.0), doc.node(450.0, 0.0), doc.node(400.0, 50.0)
    junction = doc.node(24.0, -95.0, lon_lat=True)
    for end in (x0, x1, x2):
        doc.way([end, junction], {"highway": "residential"})
    assert good
    source = doc.write(tmp_path / "ways.osm")
    counts: Counter[str] = Counter()
    objects = read_osm(source, TABLE, counts=counts)
    assert +counts == {"invalid_coordinates": 3, "unclosed_rings": 1, "repaired_geometries": 1}
    assert objects.counts() == {"building": 1, "park": 1}
    park = objects.area[objects.names() == "park"][0]
    assert 0 < park < 400.0  # the bow tie's two triangles, not a crossed ring's signed nonsense
    summary = build_ok(source, "-o", tmp_path / "m.mapdb")
    assert summary["skipped"] == dict(sorted((+counts).items()))


def test_osm_areas_cut_by_a_clipped_extract_are_counted(tmp_path: Path) -> None:
    # A clipped extract keeps the ways that cross its border but not their nodes beyond it: the ways
    # reference nodes the file does not hold, and relations reference member ways it does not hold.
    doc = OsmXml()
    doc.ring(square(0.0, 0.0, 10.0), {"building": "yes"})
    # A building missing one corner of five: the four present still make a valid ring, and are not kept.
    p = [doc.node(x, y) for x, y in square(100.0, 0.0, 10.0)]
    beyond = [doc.node(110.0, 0.0)]
    doc.way([p[0], p[1], beyond[0], p[2], p[3], p[0]], {"building": "yes"})
    q = [doc.node(x, y) for x, y in square(200.0, 0.0, 20.0)]
    beyond += [doc.node(220.0, 0.0), doc.node(180.0, 0.0)]
    doc.way([q[0], beyond[1], q[1], q[2], beyond[2], q[3], q[0]], {"leisure": "park"})
    # Multipolygons: one whose inner way is not in the file, one whose outer way lacks a node, one whole.
    r = [doc.node(x, y) for x, y in square(300.0, 0.0, 10.0)]
    inner = doc.ring(square(300.0, 0.0, 4.0))
    doc.relation([("w", doc.way(r + r[:1]), "outer"), ("w", inner, "inner")],
                 {"type": "multipolygon", "building": "yes"})
    s = [doc.node(x, y) for x, y in square(400.0, 0.0, 10.0)]
    beyond.append(doc.node(410.0, 0.0))
    cut = doc.way([s[0], s[1], beyond[3], s[2], s[3], s[0]])
    doc.relation([("w", cut, "outer")], {"type": "multipolygon", "natural": "water"})
    doc.relation([("w", doc.ring(square(500.0, 0.0, 10.0)), "outer")], {"type": "multipolygon", "building": "yes"})
    # Not areas, so not counted: an unlabelled ring, a relation osmium does not assemble (type=site), and a
    # roundabout (a "way" rule: kept from the nodes present, as before).
    t = [doc.node(x, y) for x, y in square(600.0, 0.0, 10.0)]
    doc.way([t[0], t[1], beyond[0], t[2], t[0]])
    doc.relation([("w", inner, "outer")], {"type": "site", "building": "yes"})
    v = [doc.node(x, y) for x, y in square(700.0, 0.0, 15.0)]
    doc.way([v[0], v[1], beyond[1], v[2], v[3], v[0]], {"junction": "roundabout", "highway": "primary"})
    complete = doc.write(tmp_path / "complete.osm")
    doc.nodes = [n for n in doc.nodes if not n.startswith(tuple(f'<node id="{i}" ' for i in beyond))]
    doc.ways = [w for w in doc.ways if not w.startswith(f'<way id="{inner}" ')]
    clipped = doc.write(tmp_path / "clipped.osm")

    counts: Counter[str] = Counter()
    objects = read_osm(clipped, TABLE, counts=counts)
    assert +counts == {"missing_nodes": 2, "incomplete_relations": 2}
    assert objects.counts() == {"building": 2, "roundabout": 1}
    summary = build_ok(clipped, "-o", tmp_path / "m.mapdb")
    assert summary["skipped"] == {"incomplete_relations": 2, "missing_nodes": 2}
    with open_map(tmp_path / "m.mapdb") as m:
        assert m.metadata["sources"][0]["skipped"] == {"incomplete_relations": 2, "missing_nodes": 2}
    # The same extract whole: nothing skipped, and every area above is an object.
    counts = Counter()
    objects = read_osm(complete, TABLE, counts=counts)
    assert +counts == {}
    assert objects.counts() == {"building": 4, "park": 1, "water": 1, "roundabout": 1}


def test_sample_extract_counts_its_cut_areas_as_an_independent_pass_does() -> None:
    # The sample map's source is clipped at its border: count, with a plain osmium handler and the label
    # table's rules, the closed ways tagged as areas with a node missing, and the labelled multipolygons
    # with a member way, or a node of one, missing.
    sample = Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"
    area_rules = [r for r in TABLE.osm_rules if "area" in r.geometry]
    way_rules = [r for r in TABLE.osm_rules if "way" in r.geometry]  # their ways are lines, not areas

    def labelled(tags: osmium.osm.TagList, rules: list = area_rules) -> bool:
        return any(r.matches(tags.get(r.key)) for r in rules)

    class Pass(osmium.SimpleHandler):
        def __init__(self) -> None:
            super().__init__()
            self.cut_ways, self.members, self.whole_ways = 0, [], set()

        def way(self, w: osmium.osm.Way) -> None:
            whole = all(n.location.valid() for n in w.nodes)
            if whole:
                self.whole_ways.add(w.id)
            elif w.is_closed() and labelled(w.tags) and not labelled(w.tags, way_rules):
                self.cut_ways += 1

        def relation(self, r: osmium.osm.Relation) -> None:
            if r.tags.get("type") in ("multipolygon", "boundary") and labelled(r.tags):
                self.members.append([m.ref for m in r.members if m.type == "w"])

    found = Pass()
    found.apply_file(str(sample), locations=True)
    cut_relations = sum(1 for ways in found.members if ways and not set(ways) <= found.whole_ways)
    counts: Counter[str] = Counter()
    read_osm(sample, TABLE, counts=counts)
    assert found.cut_ways > 0 and cut_relations > 0  # the premise: the sample is a clipped extract
    assert (counts["missing_nodes"], counts["incomplete_relations"]) == (found.cut_ways, cut_relations)


@pytest.mark.parametrize("compress", ["gz", "bz2"])
def test_decompression_bomb_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, compress: str) -> None:
    # The limit scaled down a thousandfold (256 KiB floor, ratio 100): an 8 MB inflate is a bomb here.
    monkeypatch.setattr(osm_files, "MIN_INFLATED_BYTES", 256 << 10)
    header = b'<?xml version="1.0"?>\n<osm version="0.6">\n<node id="1" version="1" lat="60" lon="24">'
    body = header + b" " * (8 << 20) + b'<tag k="building" v="yes"/></node>\n</osm>\n'
    bomb = tmp_path / f"bomb.osm.{compress}"
    bomb.write_bytes(gzip.compress(body, 9) if compress == "gz" else bz2.compress(body, 9))
    assert bomb.stat().st_size * osm_files.MAX_INFLATION < len(body)  # the test's own premise
    out = tmp_path / "m.mapdb"
    message = assert_fails_cleanly(run("build", bomb, "-o", out), out, bomb.name, "decompression bomb")
    assert f"{osm_files.inflation_limit(bomb.stat().st_size):,} bytes" in message
    # Under the limit, the same content reads.
    small = header + b" " * (100 << 10) + b'<tag k="building" v="yes"/></node>\n</osm>\n'
    fine = tmp_path / f"fine.osm.{compress}"
    fine.write_bytes(gzip.compress(small) if compress == "gz" else bz2.compress(small))
    assert len(read_osm(fine, TABLE)) == 1


@pytest.mark.parametrize("name, data", [
    ("bad.osm.gz", b"not gzip at all"),
    ("bad.osm.bz2", b"BZh9 not bzip2 data"),
    ("cut.osm.gz", gzip.compress(b'<?xml version="1.0"?>\n<osm version="0.6">' + b"<node/>" * 5000)[:300]),
    ("raw.osm.gz", zlib.compress(b"<osm></osm>")),
])
def test_corrupt_compressed_osm(tmp_path: Path, name: str, data: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(data)
    out = tmp_path / "m.mapdb"
    assert_fails_cleanly(run("build", path, "-o", out), out, name, "not a readable OSM file")


# ----------------------------------------------------------------------------------------------- layers


def test_geojson_with_bad_coordinates_and_broken_polygons(tmp_path: Path) -> None:
    def poly(ring: list[tuple[float, float]]) -> dict:
        return {"type": "Polygon", "coordinates": [[list(p) for p in ring]]}

    lon, lat = lonlat(0.0, 0.0)
    d = 0.001
    features = [
        {"type": "Point", "coordinates": [lon, lat]},                       # good
        {"type": "Point", "coordinates": [lon, 95.0]},                      # out of range
        {"type": "Point", "coordinates": [200.0, lat]},                     # out of range
        poly([(lon, lat), (lon + d, lat), (lon + d, lat + d), (lon, lat + d), (lon, lat)]),  # good
        # (each polygon apart from the others: the writer merges objects of one label at one position)
        poly([(lon + 3 * d, lat), (lon + 4 * d, lat), (lon + 4 * d, lat + d), (lon + 3 * d, lat + d)]),  # unclosed
        poly([(lon + 6 * d, lat), (lon + 7 * d, lat + d), (lon + 7 * d, lat), (lon + 6 * d, lat + d),
              (lon + 6 * d, lat)]),                                                                     # bow tie
        poly([(lon, lat), (lon + d, 91.0), (lon + d, lat), (lon, lat)]),                      # vertex out of range
        poly([(lon, lat), (lon + d, lat), (lon, lat)]),                                       # no area: dropped
    ]
    text = json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"label": "building"}, "geometry": g} for g in features]})
    # JSON has no NaN, but GDAL reads it: a point at NaN is skipped too.
    text = text[:-2] + ', {"type": "Feature", "properties": {"label": "building"}, ' \
                       '"geometry": {"type": "Point", "coordinates": [NaN, 60.0]}}]}'
    path = tmp_path / "broken.geojson"
    path.write_text(text)
    counts: Counter[str] = Counter()
    objects = read_layer(path, TABLE.labels, counts=counts)
    # GDAL's Arrow stream hands the point at NaN over as an empty point: skipped as a missing geometry.
    assert +counts == {"invalid_coordinates": 3, "missing_geometries": 1, "repaired_geometries": 2,
                       "invalid_geometries": 1}
    assert len(objects) == 4
    areas = np.sort(objects.area)
    assert areas[0] == 0.0 and areas[-1] > 0  # the point, and polygons with their areas
    summary = build_ok(path, "-o", tmp_path / "m.mapdb")
    assert summary["count"] == 4 and summary["skipped"] == dict(sorted(counts.items()))


def test_csv_bad_numbers_skipped_text_refused(tmp_path: Path) -> None:
    good = tmp_path / "points.csv"
    good.write_text("lon,lat,label\n24.9,60.1,stadium\nnan,60.1,stadium\n24.9,inf,stadium\n181,60,stadium\n"
                    "24.9,-91,stadium\n,60,stadium\n24.95,60.2,stadium\n")
    counts: Counter[str] = Counter()
    assert len(read_layer(good, TABLE.labels, counts=counts)) == 2 and +counts == {"invalid_coordinates": 5}
    text = tmp_path / "text.csv"
    text.write_text("lon,lat,label\n24.9,60.1,stadium\nseven,60.1,stadium\n")
    out = tmp_path / "m.mapdb"
    assert_fails_cleanly(run("build", text, "-o", out), out, "text.csv", "line 3")


# ----------------------------------------------------------------------------------------------- labels


@pytest.mark.parametrize("toml, key", [
    ("[osm]\nrules = 5\n", "osm.rules"),
    ('[osm]\nrules = "building"\n', "osm.rules"),
    ('[osm]\nrules = ["x"]\n', "osm.rules[1]"),
    ("[osm]\nintersections = 5\n", "osm.intersections"),
    ('[[osm.intersections]]\nlabel = "road_intersection"\n', "osm.intersections"),
    ('[osm.intersections]\nhighways = "primary"\n', "osm.intersections.highways"),
    ("[osm.intersections]\nmerge_distance_m = nan\n", "osm.intersections.merge_distance_m"),
    ("[osm.intersections]\nmerge_distance_m = inf\n", "osm.intersections.merge_distance_m"),
    ("[osm.intersections]\nmerge_distance_m = true\n", "osm.intersections.merge_distance_m"),
    ("[osm.intersections]\nmerge_distance_m = 1e9\n", "osm.intersections.merge_distance_m"),
    ("[osm.intersections]\nradius = 5\n", "osm.intersections.radius"),
    ('[[osm.rules]]\nlabel = "building"\nkey = "building"\nvaleus = ["yes"]\n', "osm.rules[1].valeus"),
    ('[[osm.rules]]\nlabel = "building"\nkey = 5\n', "osm.rules[1].key"),
    ('[[osm.rules]]\nlabel = "building"\nkey = "building"\ngeometry = ["line"]\n', "osm.rules[1].geometry"),
    ('[[osm.rules]]\nlabel = "castle"\nkey = "historic"\n', "osm.rules[1].label"),
    ("[osm]\nrelations = []\n", "osm.relations"),
    ("raster = 5\n", "raster"),
    ('[raster.mine]\nwater = "water"\n', "raster.mine.water"),
    ("[raster.mine]\n1 = 5\n", "raster.mine.1"),
    ('labels = ["a", "a"]\n', "labels"),
    ('labels = ["a", 1]\n', "labels"),
    ("labels = []\n", "labels"),
    ("rules = []\n", "rules"),
])
def test_junk_label_files_fail_on_one_line_naming_the_key(tmp_path: Path, toml: str, key: str) -> None:
    labels = tmp_path / "my_labels.toml"
    labels.write_text(toml)
    with pytest.raises(LabelTableError) as info:
        load_label_table(labels)
    assert str(info.value).startswith(f"{labels}: {key}: ") and "\n" not in str(info.value)
    source = osm_with(tmp_path, "one.osm", '<node id="1" version="1" lat="60" lon="24"><tag k="building" v="yes"/>'
                                           "</node>")
    out = tmp_path / "m.mapdb"
    assert_fails_cleanly(run("build", source, "-o", out, "--labels", labels), out, "my_labels.toml", key)


def test_label_files_nested_too_deep_or_too_big(tmp_path: Path) -> None:
    deep = tmp_path / "deep.toml"
    deep.write_text("labels = " + "[" * 50_000 + "]" * 50_000 + "\n")
    with pytest.raises(LabelTableError, match="nested too deep"):
        load_label_table(deep)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (5 << 20) + "\n")
    with pytest.raises(LabelTableError, match="at most"):
        load_label_table(big)


# ----------------------------------------------------------------------------------------------- options


@pytest.mark.parametrize("option, value", [("quantum", math.nan), ("quantum", math.inf), ("quantum", 0.0),
                                           ("quantum", -1.0), ("min_area_m2", math.nan), ("min_area_m2", -5.0)])
def test_build_map_rejects_bad_numbers(tmp_path: Path, option: str, value: float) -> None:
    source = osm_with(tmp_path, "one.osm", '<node id="1" version="1" lat="60" lon="24"><tag k="building" v="yes"/>'
                                           "</node>")
    with pytest.raises(SourceError, match=option.split("_")[0]):
        build_map([source], tmp_path / "m.mapdb", **{option: value})
    assert not (tmp_path / "m.mapdb").exists()


@pytest.mark.parametrize("args", [["--quantum", "nan"], ["--quantum", "inf"], ["--min-area", "nan"],
                                  ["--bbox=-inf,0,1,1"], ["--bbox=0,nan,1,1"]])
def test_cli_rejects_bad_numbers_without_traceback(tmp_path: Path, args: list[str]) -> None:
    source = osm_with(tmp_path, "one.osm", '<node id="1" version="1" lat="60" lon="24"><tag k="building" v="yes"/>'
                                           "</node>")
    out = tmp_path / "m.mapdb"
    result = run("build", source, "-o", out, *args)
    assert result.exit_code in (1, 2) and "Traceback" not in result.output
    assert not out.exists()


# ----------------------------------------------------------------------------------------------- rasters

WATER, FOREST = 41, 24


def sparse_raster(path: Path, width: int, height: int, blocks: list[tuple[int, int]], block: int = 256,
                  nodata: int | None = 255, tiled: bool = True) -> Path:
    """A sparse GeoTIFF: only the given blocks (row, col) are written, each with a water square and a forest bar."""
    profile = {"driver": "GTiff", "width": width, "height": height, "count": 1, "dtype": "uint8",
               "crs": "EPSG:3035", "transform": Affine(100.0, 0.0, 4_000_000.0, 0.0, -100.0, 3_000_000.0),
               "SPARSE_OK": True, "compress": "deflate"}
    if nodata is not None:
        profile["nodata"] = nodata
    if tiled:
        profile.update(tiled=True, blockxsize=block, blockysize=block)
    with rasterio.open(path, "w", **profile) as dst:
        for br, bc in blocks:
            rows, cols = min(block, height - br * block), min(block, width - bc * block)
            data = np.full((rows, cols), 255 if nodata is not None else 44, np.uint8)
            data[: rows // 2, : cols // 2] = WATER
            data[-1:, :] = FOREST
            dst.write(data, 1, window=Window(bc * block, br * block, cols, rows))
    return path


def test_sparse_raster_reads_only_its_blocks(tmp_path: Path) -> None:
    # 100 000 x 100 000 pixels (10^10) in 256-pixel blocks, three of them written.
    written = [(0, 0), (200, 300), (390, 390)]
    path = sparse_raster(tmp_path / "clc_sparse.tif", 100_000, 100_000, written)
    with rasterio.open(path) as src:
        # The premise: GDAL sees absent blocks as absent.
        assert src.get_tag_item("BLOCK_OFFSET_1_0", "TIFF", bidx=1) in (None, "", "0")
        assert src.get_tag_item("BLOCK_OFFSET_0_0", "TIFF", bidx=1) not in (None, "", "0")
        tiling = landcover_tiles._Tiling(path, src, Window(0, 0, src.width, src.height), skip_absent=True)
        present = tiling.present
        tiles = [t for _, _, row in tiling.rows() for t in row]
    assert present is not None and present.shape == (391, 391) and np.flatnonzero(present.ravel()).size == 3
    assert len(tiles) == 3  # three tiles read, out of thousands
    objects = read_landcover(path, TABLE, min_area_m2=0.0)
    assert objects.counts() == {"water": 3, "forest": 3}
    last_rows = 100_000 - 390 * 256  # the corner block is cut by the raster's edge
    assert sorted(np.round(objects.area[objects.names() == "water"]).tolist()) == sorted(
        [128 * 128 * 1e4, 128 * 128 * 1e4, (last_rows // 2) * ((100_000 - 390 * 256) // 2) * 1e4])


def test_absent_blocks_are_read_when_their_fill_is_a_class(tmp_path: Path) -> None:
    # No nodata: GDAL fills absent blocks with 0, and this table makes 0 a class.
    labels = tmp_path / "labels.toml"
    labels.write_text('labels = ["sea", "lake"]\n[osm]\nrules = []\n[raster.mine]\n0 = "sea"\n41 = "lake"\n')
    table = load_label_table(labels)
    path = sparse_raster(tmp_path / "sparse.tif", 2048, 2048, [(1, 1)], nodata=None)
    objects = read_landcover(path, table, classes="mine", min_area_m2=0.0)
    sea = objects.area[objects.names() == "sea"]
    assert sea.size == 1 and sea[0] == pytest.approx((2048 * 2048 - 256 * 256) * 1e4)


def test_huge_row_read_in_bounded_tiles(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # One row of 200 000 pixels stored as a single strip, read in tiles of 4096 pixels: a line of water
    # across many tiles is still one patch.
    monkeypatch.setattr(landcover_tiles, "_TILE_PIXELS", 4096)
    data = np.full((1, 200_000), 255, np.uint8)
    data[0, 1_000:150_000] = WATER
    path = tmp_path / "clc_row.tif"
    with rasterio.open(path, "w", driver="GTiff", width=200_000, height=1, count=1, dtype="uint8", crs="EPSG:3035",
                       transform=Affine(100.0, 0.0, 4e6, 0.0, -100.0, 3e6), nodata=255) as dst:
        dst.write(data, 1)
    with rasterio.open(path) as src:
        assert src.block_shapes[0] == (1, 200_000)
        tiling = landcover_tiles._Tiling(path, src, Window(0, 0, src.width, src.height), skip_absent=True)
        assert (tiling.tile_rows, tiling.tile_cols) == (1, 4096)
    objects = read_landcover(path, TABLE, min_area_m2=0.0)
    assert len(objects) == 1 and objects.area[0] == pytest.approx(149_000 * 1e4)
    assert objects.x[0] == pytest.approx(4e6 + 100.0 * (1_000 + 149_000 / 2))


def test_block_too_big_to_read_in_parts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A strip GDAL would inflate whole: refused on one line when it holds data, skipped when absent.
    monkeypatch.setattr(landcover_tiles, "_MAX_BLOCK_BYTES", 1 << 16)
    full = tmp_path / "clc_strip.tif"
    empty = tmp_path / "clc_empty_strip.tif"
    for path, fill in ((full, WATER), (empty, None)):
        with rasterio.open(path, "w", driver="GTiff", width=100_000, height=1, count=1, dtype="uint8",
                           crs="EPSG:3035", transform=Affine(100.0, 0.0, 4e6, 0.0, -100.0, 3e6), nodata=255,
                           SPARSE_OK=True) as dst:
            if fill is not None:
                dst.write(np.full((1, 100_000), fill, np.uint8), 1)
    with pytest.raises(SourceError, match="too big to read in parts") as info:
        read_landcover(full, TABLE)
    assert "\n" not in str(info.value)
    assert len(read_landcover(empty, TABLE)) == 0
    out = tmp_path / "m.mapdb"
    assert_fails_cleanly(run("build", full, "-o", out), out, "clc_strip.tif", "retile")
