"""Tests of the OpenStreetMap source on tiny OSM files written here, and on the real Monaco extract."""

from __future__ import annotations

import gzip
import importlib.util
import math
from pathlib import Path

import numpy as np
import osmium
import pytest
from osmxml import OsmXml, lonlat, metres, square
from pyproj import Transformer

from mapdb.errors import MapdbIOError, SourceError
from mapdb.labels import default_label_table, load_label_table
from mapdb.sources.osm.files import OSM_SUFFIXES, is_osm_path
from mapdb.sources.osm.reader import read_osm

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TABLE = default_label_table()

def named(kind: str, name: str | None = None) -> dict[str, str]:
    return {"highway": kind, **({"name": name} if name else {})}


def of_label(objects, label: str):
    return objects.take(objects.names() == label)


# ------------------------------------------------------------------------------------------ suffixes


def test_osm_suffixes_and_is_osm_path() -> None:
    assert ".osm.pbf" in OSM_SUFFIXES and ".osm.gz" in OSM_SUFFIXES
    assert is_osm_path("a/b/Monaco.OSM.PBF") and is_osm_path(Path("x.osm.bz2"))
    assert not is_osm_path("x.osm.zip") and not is_osm_path("x.tif")


# ------------------------------------------------------------------------------------------ buildings


def test_building_closed_way_node_and_building_no(tmp_path: Path) -> None:
    doc = OsmXml()
    doc.ring(square(0, 0, 10), {"building": "yes"})
    doc.ring(square(100, 0, 10), {"building": "no"})
    doc.node(50, 50, {"building": "hut"})
    doc.node(60, 60, {"building": "no"})
    doc.node(70, 70, {"amenity": "bench"})
    objects = read_osm(doc.write(tmp_path / "b.osm"), TABLE)

    assert objects.crs == "EPSG:4326" and objects.labels == TABLE.labels
    assert objects.counts() == {"building": 2}
    xy = metres(objects.x, objects.y)
    order = np.argsort(objects.area)
    # The node (area 0) and the way (20 m x 20 m) at their own places.
    np.testing.assert_allclose(xy[order[0]], [50, 50], atol=0.01)
    np.testing.assert_allclose(xy[order[1]], [0, 0], atol=0.05)
    assert objects.area[order[0]] == 0
    assert objects.area[order[1]] == pytest.approx(400, rel=0.01)


def test_multipolygon_relation_with_hole(tmp_path: Path) -> None:
    doc = OsmXml()
    outer = doc.ring(square(0, 0, 50))  # 100 m x 100 m
    inner = doc.ring([(10, -20), (40, -20), (40, 20), (10, 20)])  # 30 m x 40 m hole, right of centre
    doc.relation([("w", outer, "outer"), ("w", inner, "inner")], {"type": "multipolygon", "building": "yes"})
    objects = read_osm(doc.write(tmp_path / "mp.osm"), TABLE)

    assert objects.counts() == {"building": 1}
    assert objects.area[0] == pytest.approx(10_000 - 1_200, rel=0.01)
    # The hole pulls the centroid left: -(1200 * 25) / 8800 m.
    np.testing.assert_allclose(metres(objects.x, objects.y)[0], [-1200 * 25 / 8800, 0], atol=0.05)


def test_area_of_known_square_in_equal_area_crs(tmp_path: Path) -> None:
    # A 200 m square drawn in LAEA Europe (EPSG:3035), an equal-area projection: 40,000 m^2 exactly.
    to_lonlat = Transformer.from_crs("EPSG:3035", "EPSG:4326", always_xy=True)
    cx, cy = Transformer.from_crs("EPSG:4326", "EPSG:3035", always_xy=True).transform(10.0, 60.0)
    doc = OsmXml()
    refs = [doc.node(*to_lonlat.transform(cx + dx, cy + dy), lon_lat=True)
            for dx, dy in [(-100, -100), (100, -100), (100, 100), (-100, 100)]]
    doc.way(refs + refs[:1], {"landuse": "forest"})
    objects = read_osm(doc.write(tmp_path / "sq.osm"), TABLE)
    assert objects.counts() == {"forest": 1}
    assert objects.area[0] == pytest.approx(40_000, rel=0.01)
    assert (objects.x[0], objects.y[0]) == pytest.approx((10.0, 60.0), abs=1e-6)


def test_first_matching_rule_wins(tmp_path: Path) -> None:
    doc = OsmXml()
    doc.ring(square(0, 0, 60), {"leisure": "stadium", "building": "yes"})
    doc.node(300, 0, {"building": "yes", "leisure": "stadium"})
    doc.ring(square(500, 0, 20), {"building": "yes", "leisure": "park"})  # building comes before park
    objects = read_osm(doc.write(tmp_path / "rules.osm"), TABLE)
    assert objects.counts() == {"stadium": 2, "building": 1}


def test_rules_apply_only_to_their_geometry(tmp_path: Path) -> None:
    doc = OsmXml()
    doc.node(0, 0, {"leisure": "park"})  # the park rule is for areas only
    doc.ring(square(100, 0, 20), {"leisure": "park"})
    doc.way([doc.node(200, 0), doc.node(250, 0)], {"building": "yes"})  # an open way is no area
    objects = read_osm(doc.write(tmp_path / "geom.osm"), TABLE)
    assert objects.counts() == {"park": 1}
    np.testing.assert_allclose(metres(objects.x, objects.y)[0], [100, 0], atol=0.05)


# ------------------------------------------------------------------------------------------ intersections


def test_t_junction_counts_once_and_one_road_split_in_two_ways_does_not(tmp_path: Path) -> None:
    doc = OsmXml()
    # Main road split into two ways of the same name at the T node; the side road joins there.
    west, t_node, east, south = doc.node(-100, 0), doc.node(0, 0), doc.node(100, 0), doc.node(0, -100)
    doc.way([west, t_node], named("residential", "Main"))
    doc.way([t_node, east], named("residential", "Main"))
    doc.way([t_node, south], named("residential", "Side"))
    # Far away: one road drawn as two consecutive ways sharing a node, no side road.
    a, b, c = doc.node(1000, 0), doc.node(1100, 0), doc.node(1200, 10)
    doc.way([a, b], named("primary", "Long"))
    doc.way([b, c], named("primary", "Long"))
    # And an unnamed road split in two ways (e.g. at a bridge): still one road, not a junction.
    d, e, f = doc.node(2000, 0), doc.node(2100, 0), doc.node(2200, 0)
    doc.way([d, e], named("unclassified"))
    doc.way([e, f], named("unclassified", None) | {"bridge": "yes"})
    objects = read_osm(doc.write(tmp_path / "t.osm"), TABLE)

    assert objects.counts() == {"road_intersection": 1}
    assert objects.area[0] == 0
    np.testing.assert_allclose(metres(objects.x, objects.y)[0], [0, 0], atol=0.01)


def test_t_junction_on_an_unsplit_through_road(tmp_path: Path) -> None:
    doc = OsmXml()
    t_node = doc.node(0, 0)
    doc.way([doc.node(-100, 0), t_node, doc.node(100, 0)], named("tertiary", "Main"))
    doc.way([t_node, doc.node(0, 100)], named("tertiary", "Main"))  # same name: still a second road
    objects = read_osm(doc.write(tmp_path / "t2.osm"), TABLE)
    assert objects.counts() == {"road_intersection": 1}


def test_dual_carriageway_crossing_merges_into_one(tmp_path: Path) -> None:
    doc = OsmXml()
    # Two one-way carriageways each way, 4 m apart: four junction nodes 4 m (5.7 m diagonally) apart.
    nw, ne, sw, se = doc.node(-2, 2), doc.node(2, 2), doc.node(-2, -2), doc.node(2, -2)
    doc.way([doc.node(-2, -200), sw, nw, doc.node(-2, 200)], named("primary", "A") | {"oneway": "yes"})
    doc.way([doc.node(2, 200), ne, se, doc.node(2, -200)], named("primary", "A") | {"oneway": "yes"})
    doc.way([doc.node(-200, 2), nw, ne, doc.node(200, 2)], named("secondary", "B") | {"oneway": "yes"})
    doc.way([doc.node(200, -2), se, sw, doc.node(-200, -2)], named("secondary", "B") | {"oneway": "yes"})
    # A plain crossing 30 m away stays separate.
    cross = doc.node(30, 100)
    doc.way([doc.node(-100, 100), cross, doc.node(100, 100)], named("residential", "C"))
    doc.way([doc.node(30, 150), cross], named("residential", "D"))
    objects = read_osm(doc.write(tmp_path / "dual.osm"), TABLE)

    assert objects.counts() == {"road_intersection": 2}
    xy = metres(objects.x, objects.y)
    xy = xy[np.argsort(xy[:, 1])]
    np.testing.assert_allclose(xy, [[0, 0], [30, 100]], atol=0.01)


def test_merge_distance_is_respected(tmp_path: Path) -> None:
    doc = OsmXml()
    # Two T junctions 8 m apart along one road: more than the 5 m merge distance.
    left, right = doc.node(0, 0), doc.node(8, 0)
    doc.way([doc.node(-100, 0), left, right, doc.node(100, 0)], named("residential", "Main"))
    doc.way([left, doc.node(0, -100)], named("residential", "L"))
    doc.way([right, doc.node(8, 100)], named("residential", "R"))
    path = doc.write(tmp_path / "two.osm")
    assert read_osm(path, TABLE).counts() == {"road_intersection": 2}


def test_footway_crossings_do_not_count(tmp_path: Path) -> None:
    doc = OsmXml()
    mid = doc.node(0, 0)
    doc.way([doc.node(-100, 0), mid, doc.node(100, 0)], named("residential", "Main"))
    doc.way([doc.node(0, -50), mid, doc.node(0, 50)], named("footway"))
    doc.way([mid, doc.node(50, 50)], named("cycleway"))
    objects = read_osm(doc.write(tmp_path / "foot.osm"), TABLE)
    assert len(objects) == 0


def test_roundabout_pieces_make_one_object_without_entry_intersections(tmp_path: Path) -> None:
    doc = OsmXml()
    # A ring of radius 20 m drawn as two half-ring ways, with two entry roads.
    ring = [doc.node(20 * math.cos(t), 20 * math.sin(t)) for t in np.linspace(0, 2 * math.pi, 16, endpoint=False)]
    doc.way(ring[:9], {"highway": "primary", "junction": "roundabout"})
    doc.way(ring[8:] + ring[:1], {"highway": "primary", "junction": "roundabout"})
    doc.way([doc.node(100, 0), ring[0]], named("primary", "East"))
    doc.way([doc.node(-100, 0), ring[8]], named("primary", "West"))
    objects = read_osm(doc.write(tmp_path / "rb.osm"), TABLE)

    assert objects.counts() == {"roundabout": 1}
    np.testing.assert_allclose(metres(objects.x, objects.y)[0], [0, 0], atol=0.05)
    # The ground the ring encloses: a regular 16-gon of radius 20 m.
    assert objects.area[0] == pytest.approx(0.5 * 16 * 20**2 * math.sin(2 * math.pi / 16), rel=0.01)


def test_custom_table_without_intersections(tmp_path: Path) -> None:
    labels = tmp_path / "labels.toml"
    labels.write_text(
        'labels = ["bridge", "tower"]\n'
        '[[osm.rules]]\nlabel = "bridge"\nkey = "bridge"\nexclude = ["no"]\ngeometry = ["way"]\n'
        '[[osm.rules]]\nlabel = "tower"\nkey = "man_made"\nvalues = ["tower"]\ngeometry = ["node"]\n'
        "[raster.worldcover]\n[raster.corine]\n"  # the default raster classes name labels not declared here
    )
    table = load_label_table(labels)
    doc = OsmXml()
    mid = doc.node(0, 0)
    doc.way([doc.node(-50, 0), mid, doc.node(50, 0)], named("primary", "A") | {"bridge": "yes"})
    doc.way([mid, doc.node(0, 50)], named("primary", "B") | {"bridge": "no"})
    doc.node(30, 30, {"man_made": "tower"})
    doc.ring(square(200, 0, 10), {"building": "yes"})
    objects = read_osm(doc.write(tmp_path / "custom.osm"), table)
    assert objects.labels == ("bridge", "tower")
    assert objects.counts() == {"bridge": 1, "tower": 1}
    bridge = of_label(objects, "bridge")
    np.testing.assert_allclose(metres(bridge.x, bridge.y)[0], [0, 0], atol=0.05)
    assert bridge.area[0] == pytest.approx(0, abs=1e-3)  # a straight line encloses nothing


# ------------------------------------------------------------------------------------------ bbox, formats


def test_bbox_keeps_objects_with_centroid_inside(tmp_path: Path) -> None:
    doc = OsmXml()
    doc.ring(square(0, 0, 10), {"building": "yes"})
    doc.ring(square(500, 0, 10), {"building": "yes"})
    doc.node(0, 300, {"building": "yes"})
    path = doc.write(tmp_path / "bbox.osm")
    lon_min, lat_min = lonlat(-50, -50)
    lon_max, lat_max = lonlat(50, 50)
    objects = read_osm(path, TABLE, bbox=(lon_min, lat_min, lon_max, lat_max))
    assert len(objects) == 1
    np.testing.assert_allclose(metres(objects.x, objects.y)[0], [0, 0], atol=0.05)
    assert len(read_osm(path, TABLE)) == 3


def test_pbf_and_gzip_read_like_xml(tmp_path: Path) -> None:
    doc = OsmXml()
    doc.ring(square(0, 0, 10), {"building": "yes"})
    doc.node(50, 50, {"amenity": "parking"})
    xml = doc.write(tmp_path / "same.osm")
    pbf = tmp_path / "same.osm.pbf"
    with osmium.SimpleWriter(str(pbf)) as writer:
        for obj in osmium.FileProcessor(str(xml)):
            writer.add(obj)
    gz = tmp_path / "same.osm.gz"
    gz.write_bytes(gzip.compress(xml.read_bytes()))
    want = read_osm(xml, TABLE)
    assert want.counts() == {"building": 1, "parking": 1}
    for other in (pbf, gz):
        got = read_osm(other, TABLE)
        assert got.counts() == want.counts()
        np.testing.assert_allclose(np.sort(got.x), np.sort(want.x), atol=1e-7)


def test_progress_goes_to_the_callback_not_stdout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = OsmXml()
    doc.node(0, 0, {"building": "yes"})
    messages: list[str] = []
    read_osm(doc.write(tmp_path / "p.osm"), TABLE, progress=messages.append)
    assert messages and all("p.osm" in m and "\n" not in m for m in messages)
    assert "1 objects" in messages[-1]
    assert capsys.readouterr().out == ""


# ------------------------------------------------------------------------------------------ bad input


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nothing.osm.pbf"
    with pytest.raises(MapdbIOError, match=r"nothing\.osm\.pbf: no such file$"):
        read_osm(path, TABLE)


def _assert_unreadable(path: Path) -> None:
    with pytest.raises(SourceError) as info:
        read_osm(path, TABLE)
    message = str(info.value)
    assert message.startswith(f"{path}: not a readable OSM file (") and message.endswith(")")
    assert "\n" not in message


def test_empty_file(tmp_path: Path) -> None:
    for name in ("empty.osm", "empty.osm.pbf"):
        (tmp_path / name).write_bytes(b"")
        _assert_unreadable(tmp_path / name)


def test_text_file_named_osm(tmp_path: Path) -> None:
    path = tmp_path / "x.osm"
    path.write_text("this is not XML at all\nsecond line\n")
    _assert_unreadable(path)


def test_random_bytes_named_pbf(tmp_path: Path) -> None:
    path = tmp_path / "x.osm.pbf"
    path.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    _assert_unreadable(path)


def test_truncated_pbf_and_xml(tmp_path: Path) -> None:
    doc = OsmXml()
    for i in range(300):
        doc.ring(square(i * 30, 0, 10), {"building": "yes", "name": f"house {i}"})
    xml = doc.write(tmp_path / "full.osm")
    pbf = tmp_path / "full.osm.pbf"
    with osmium.SimpleWriter(str(pbf)) as writer:
        for obj in osmium.FileProcessor(str(xml)):
            writer.add(obj)
    assert read_osm(pbf, TABLE).counts() == {"building": 300}
    cut = tmp_path / "cut.osm.pbf"
    cut.write_bytes(pbf.read_bytes()[: pbf.stat().st_size // 2])
    _assert_unreadable(cut)
    cut_xml = tmp_path / "cut.osm"
    cut_xml.write_bytes(xml.read_bytes()[: xml.stat().st_size // 2])
    _assert_unreadable(cut_xml)


def test_file_without_an_osm_suffix(tmp_path: Path) -> None:
    doc = OsmXml()
    path = tmp_path / "data.xml"
    path.write_text(doc.text())
    _assert_unreadable(path)


# ------------------------------------------------------------------------------------------ real data


def _independent_counter():
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "osm_building_count.py"
    spec = importlib.util.spec_from_file_location("osm_building_count", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.count_buildings


def test_monaco_building_count_matches_an_independent_count() -> None:
    monaco = DATA / "osm" / "monaco-2021-12-03.osm.pbf"
    if not monaco.exists():
        pytest.skip(f"real data absent: {monaco} (see ../shared/data/SOURCES.md)")
    independent = _independent_counter()(monaco)
    assert independent["closed_ways"] > 1000  # the counter itself saw the city
    objects = read_osm(monaco, TABLE)
    ours = objects.counts()["building"]
    assert abs(ours - independent["total"]) <= 0.01 * independent["total"]
    # Every object lies in Monaco's extract and buildings have plausible sizes.
    assert np.all((objects.x > 7.3) & (objects.x < 7.6) & (objects.y > 43.6) & (objects.y < 43.8))
    building_area = of_label(objects, "building").area
    assert 50 < np.median(building_area[building_area > 0]) < 2000
