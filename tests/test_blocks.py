"""Blocks of touching buildings: formed at build time from OSM and layer footprints, kept by info, export and
merge, matched by mask images only, never seen by the simulators."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import shapely
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import OsmXml, square

from mapdb.build.blocks import DEFAULT_GAP_M, block_members, blocks_of
from mapdb.build.pipeline import build_map
from mapdb.labels import BLOCK_LABEL, default_label_table
from mapdb.localize.localizer import Localizer
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.match.mapobjects.blocks_view import BlocksView, wants_blocks
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_images

# A terrace of three 10 m houses side by side (the middle one 0.5 m from the first, within the gap; touching
# the third), and a lone house 5 m away: one block of three.  Metres east/north of the test origin.
TERRACE = [(0.0, 0.0), (10.5, 0.0), (20.5, 0.0)]
LONE = (36.0, 0.0)


def _terrace_osm(path: Path) -> Path:
    doc = OsmXml()
    for cx, cy in [*TERRACE, LONE]:
        doc.ring(square(cx, cy, 5.0), {"building": "yes"})
    doc.ring(square(0.0, 80.0, 20.0), {"leisure": "park"})
    return doc.write(path)


def _terrace_geojson(path: Path) -> Path:
    from osmxml import lonlat

    features = []
    for cx, cy in [*TERRACE, LONE]:
        ring = [list(lonlat(x, y)) for x, y in square(cx, cy, 5.0)]
        features.append({"type": "Feature", "properties": {"label": "building"},
                         "geometry": {"type": "Polygon", "coordinates": [ring + ring[:1]]}})
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return path


def test_footprints_within_the_gap_form_one_block_and_lone_ones_none() -> None:
    boxes = shapely.box([0.0, 10.5, 20.5, 36.0], -5.0, [10.0, 20.5, 30.5, 46.0], 5.0)
    assert block_members(boxes, DEFAULT_GAP_M).tolist() == [0, 0, 0, -1]
    assert block_members(boxes, 0.0).tolist() == [-1, 0, 0, -1]  # 0.5 m apart: only with a gap
    assert block_members(boxes, 5.6).tolist() == [0, 0, 0, 0]  # the lone house is 5.5 m away
    # Overlapping footprints count once in the union: two 10 m squares overlapping by half.
    xy, area, members = blocks_of(shapely.box([0.0, 5.0], 0.0, [10.0, 15.0], 10.0))
    assert area.tolist() == [150.0] and xy.tolist() == [[7.5, 5.0]] and members.tolist() == [2]
    # A multipolygon building joins by any of its parts.
    multi = shapely.multipolygons([shapely.box(0, 0, 1, 1), shapely.box(50, 0, 51, 1)])
    assert block_members(np.array([multi, shapely.box(51.2, 0, 52, 1)], object)).tolist() == [0, 0]


@pytest.mark.parametrize("make", [_terrace_osm, _terrace_geojson], ids=["osm", "geojson"])
def test_build_stores_the_block_beside_its_buildings(tmp_path: Path, make) -> None:
    source = make(tmp_path / ("t.osm" if make is _terrace_osm else "t.geojson"))
    with_blocks, without = tmp_path / "b.mapdb", tmp_path / "n.mapdb"
    summary = build_map([source], with_blocks, label="building" if make is _terrace_geojson else None)
    build_map([source], without, blocks=False, label="building" if make is _terrace_geojson else None)
    assert summary["labels"][BLOCK_LABEL] == 1
    with open_map(with_blocks) as m, open_map(without) as n:
        objects, plain = m.all(), n.all()
        assert BLOCK_LABEL not in n.label_counts and n.label_counts["building"] == m.label_counts["building"] == 4
        assert m.metadata["build"]["block_gap_m"] == DEFAULT_GAP_M and n.metadata["build"]["block_gap_m"] is None
    block = objects.take(objects.names() == BLOCK_LABEL)
    houses = plain.take(plain.names() == "building")
    # The union of three 10 m squares, at their mean centre (the map's quantum is 0.1 m).
    terrace = np.isin(np.round(houses.x - houses.x.min()), [0.0, 10.0, 20.0])
    assert block.area[0] == pytest.approx(300.0, rel=0.05)  # areas are stored in steps of 2^(1/8)
    assert block.x[0] == pytest.approx(houses.x[terrace].mean(), abs=0.1)
    assert block.y[0] == pytest.approx(houses.y[terrace].mean(), abs=0.1)


def test_osm_and_layer_footprints_form_the_same_blocks(tmp_path: Path) -> None:
    osm, layer = tmp_path / "o.mapdb", tmp_path / "l.mapdb"
    build_map([_terrace_osm(tmp_path / "t.osm")], osm, crs="EPSG:32632")
    build_map([_terrace_geojson(tmp_path / "t.geojson")], layer, crs="EPSG:32632", label="building")
    with open_map(osm) as a, open_map(layer) as b:
        x, y = (o.take(o.names() == BLOCK_LABEL) for o in (a.all(), b.all()))
    assert abs(x.x[0] - y.x[0]) <= 0.11 and abs(x.y[0] - y.y[0]) <= 0.11
    assert x.area[0] == pytest.approx(y.area[0], rel=0.01)


def test_info_export_and_merge_keep_the_blocks(tmp_path: Path) -> None:
    runner = CliRunner()
    source = _terrace_osm(tmp_path / "t.osm")
    assert runner.invoke(cli, ["build", str(source), "-o", str(tmp_path / "a.mapdb"), "-q"]).exit_code == 0
    info = runner.invoke(cli, ["info", str(tmp_path / "a.mapdb")])
    assert info.exit_code == 0 and BLOCK_LABEL in info.output
    out = runner.invoke(cli, ["export", str(tmp_path / "a.mapdb"), "-o", str(tmp_path / "a.geojson")])
    assert out.exit_code == 0, out.output
    labels = [f["properties"]["label"] for f in json.loads((tmp_path / "a.geojson").read_text())["features"]]
    assert labels.count(BLOCK_LABEL) == 1
    merged = runner.invoke(cli, ["merge", str(tmp_path / "a.mapdb"), "-o", str(tmp_path / "m.mapdb"), "-q"])
    assert merged.exit_code == 0, merged.output
    with open_map(tmp_path / "m.mapdb") as m:
        assert m.label_counts[BLOCK_LABEL] == 1
    off = runner.invoke(cli, ["build", str(source), "-o", str(tmp_path / "n.mapdb"), "-q", "--no-blocks"])
    with open_map(tmp_path / "n.mapdb") as m:
        assert off.exit_code == 0 and BLOCK_LABEL not in m.label_counts
    bad = runner.invoke(cli, ["build", str(source), "-o", str(tmp_path / "x.mapdb"), "--block-gap", "9"])
    assert bad.exit_code == 2 and not (tmp_path / "x.mapdb").exists()


def _town_with_blocks() -> MemoryMap:
    """A grid of houses where every fourth pair touches (a block at the pair's centre), and a few parks."""
    rng = np.random.default_rng(5)
    x, y = np.meshgrid(np.arange(0.0, 600.0, 23.0), np.arange(0.0, 600.0, 29.0))
    x, y = x.ravel() + rng.uniform(-6, 6, x.size), y.ravel() + rng.uniform(-6, 6, x.size)
    names = ["building"] * x.size
    pairs = np.arange(0, x.size - 1, 4)
    bx, by = (x[pairs] + x[pairs + 1]) / 2, (y[pairs] + y[pairs + 1]) / 2
    labels = default_label_table().labels
    return MemoryMap(Objects.from_names(np.concatenate([x, bx]), np.concatenate([y, by]),
                                        names + [BLOCK_LABEL] * pairs.size, area=np.full(x.size + pairs.size, 100.0),
                                        crs="EPSG:32632", labels=labels))


def test_point_images_never_see_blocks_and_answer_as_without_them() -> None:
    town = _town_with_blocks()
    objects = town.all()
    plain = MemoryMap(objects.take(objects.names() != BLOCK_LABEL))
    images = simulate_images(town, 6, altitude=150.0, fov_deg=60.0, yaw="random", min_objects=10, seed=1)
    for im in images:
        assert BLOCK_LABEL not in {o["label"] for o in im["objects"]}
        index = np.asarray(im["truth"]["map_index"])
        assert not (objects.names()[index[index >= 0]] == BLOCK_LABEL).any()
    with_blocks, without = Localizer(town), Localizer(plain)
    for im in images:
        a, b = with_blocks.localize(im), without.localize(im)
        assert (a.status, a.x, a.y) == (b.status, b.x, b.y)
    assert sum(Localizer(town).localize(im).ok for im in images) >= 4


def test_only_images_whose_buildings_have_areas_are_matched_against_blocks() -> None:
    labels = ("building", "park", BLOCK_LABEL)
    codes = np.array([0, 0, 1])
    assert wants_blocks(codes, labels, np.array([np.nan, 120.0, np.nan]))
    assert not wants_blocks(codes, labels, np.array([np.nan, np.nan, 500.0]))  # only the park has one
    assert not wants_blocks(codes, labels, None)
    town = _town_with_blocks()
    folded, left_out = BlocksView(town, fold=True), BlocksView(town, fold=False)
    n_blocks = town.label_counts[BLOCK_LABEL]
    assert folded.label_counts["building"] == town.label_counts["building"] + n_blocks
    assert len(left_out) == len(town) - n_blocks and BLOCK_LABEL not in left_out.all().names()
    loc = Localizer(town)
    assert loc.matcher_for(codes, np.array([np.nan, 120.0, np.nan])).map.fold
    assert not loc.matcher_for(codes, None).map.fold
    assert Localizer(town, blocks=False).matcher_for(codes, np.array([np.nan, 120.0, np.nan])).map.fold is False


def test_rendered_truth_names_the_block_a_merged_blob_stands_for(tmp_path: Path) -> None:
    from mapdb.simulation.outlines import read_scene
    from mapdb.simulation.rendered import simulate_masks

    # Pairs of touching 8 m houses and lone houses, scattered so that no two images look alike.
    rng = np.random.default_rng(3)
    doc = OsmXml()
    for i in range(60):
        cx, cy = (i % 8) * 30.0 + rng.uniform(-5, 5), (i // 8) * 30.0 + rng.uniform(-5, 5)
        doc.ring(square(cx, cy, 4.0), {"building": "yes"})
        if i % 2 == 0:
            doc.ring(square(cx + 8.0, cy, 4.0), {"building": "yes"})
    source = doc.write(tmp_path / "pairs.osm")
    build_map([source], tmp_path / "p.mapdb")
    with open_map(tmp_path / "p.mapdb") as m:
        objects = m.all()
        scene = read_scene(source, objects)
        images = [d for d, _ in simulate_masks(m, scene, 3, altitude=120.0, fov_deg=60.0, heights=False,
                                               min_objects=8, seed=2)]
    names = objects.names()
    flagged = 0
    for im in images:
        truth = im["truth"]
        for index, block, covers in zip(truth["map_index"], truth["block"], truth["covers"], strict=True):
            assert (names[index] == BLOCK_LABEL) == block
            if block:  # a merged pair: both houses under the blob, the block at their middle
                flagged += 1
                assert len(covers) == 2 and all(names[j] == "building" for j in covers)
                assert objects.x[index] == pytest.approx(objects.x[covers].mean(), abs=0.2)
    assert flagged >= 5


def test_evaluate_counts_the_blobs_standing_for_blocks() -> None:
    from mapdb.answers import Answer
    from mapdb.evaluation.evaluate import format_summary, outcome, summarize

    image = {"id": "a", "objects": [{}, {}, {}], "truth": {"x": 0.0, "y": 0.0, "map_index": [4, 7, -1],
                                                        "block": [False, True, False]}}
    plain = {"id": "b", "objects": [{}], "truth": {"x": 0.0, "y": 0.0, "map_index": [3]}}
    rejected = Answer.from_json({"id": "a", "status": "rejected", "reason": "no"})
    outcomes = [outcome(image, rejected, 1.0), outcome(plain, rejected, 1.0)]
    assert [o["n_blocks"] for o in outcomes] == [1, None]
    summary = summarize(outcomes)
    assert summary["blocks_mean"] == 1.0 and "1.0 of them blocks" in format_summary(summary)
    assert summarize(outcomes[1:])["blocks_mean"] is None


def test_whole_map_indexes_of_a_map_with_blocks_are_its_views() -> None:
    town = _town_with_blocks()
    loc = Localizer(town)
    objects, quads = loc.whole_map_indexes()
    assert BLOCK_LABEL not in {town.labels[c] for c in np.flatnonzero(objects.counts)}  # the view without blocks
    assert sorted(loc._views) == [False, True] and loc.whole_map_ready(1.0)
    folded, _ = loc._views[True].whole_map_indexes()
    assert folded.counts[town.labels.index("building")] == objects.counts[town.labels.index("building")] + \
        town.label_counts[BLOCK_LABEL]


def test_point_images_only_leave_the_folded_view_until_a_mask_image_comes() -> None:
    """whole_map_indexes(masks=False) (the analysis's): only the view point images are matched in is built; the
    folded view, made when an image with building areas first comes, has its whole-map indexes at once, and
    answers as a localizer that built both at the start."""
    town = _town_with_blocks()
    lazy, eager = Localizer(town), Localizer(town)
    lazy_objects, _ = lazy.whole_map_indexes(masks=False)
    eager_objects, _ = eager.whole_map_indexes()
    assert sorted(lazy._views) == [False] and sorted(eager._views) == [False, True]
    assert np.array_equal(lazy_objects.counts, eager_objects.counts)
    assert lazy.whole_map_ready(1.0, masks=False) and sorted(lazy._views) == [False]  # readying builds no fold
    image = simulate_images(town, 1, altitude=150.0, fov_deg=60.0, yaw="random", min_objects=10, seed=1)[0]
    for o in image["objects"]:
        o["area_px"] = 400.0  # mask blobs: matched in the folded view
    a, b = lazy.localize(image), eager.localize(image)
    assert sorted(lazy._views) == [False, True] and lazy._views[True]._whole_quads is not None
    assert (a.status, a.x, a.y, a.score) == (b.status, b.x, b.y, b.score)


def test_a_footprint_crossing_itself_still_joins_its_block(tmp_path: Path) -> None:
    doc = OsmXml()
    doc.ring(square(0.0, 0.0, 5.0), {"building": "yes"})
    doc.ring([(5.0, -5.0), (15.0, 5.0), (15.0, -5.0), (5.0, 5.0)], {"building": "yes"})  # a bow tie touching it
    doc.ring(square(0.0, 80.0, 20.0), {"leisure": "park"})
    summary = build_map([doc.write(tmp_path / "bow.osm")], tmp_path / "b.mapdb")
    assert summary["labels"].get(BLOCK_LABEL) == 1 and summary["skipped"].get("repaired_geometries") == 1
