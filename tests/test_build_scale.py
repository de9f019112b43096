"""The streaming OSM build (areas in blocks, the road network in buckets on disk, file node indexes), its
progress by bytes read, and builds of several sources on Dask: each gives the map of the one-shot build."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import osmium
import pytest
from osmxml import OsmXml, square

import mapdb.sources.osm.areas as osm_areas
import mapdb.sources.osm.index as osm_index
import mapdb.sources.osm.intersections as osm_roads
import mapdb.sources.osm.progress as osm_progress
import mapdb.sources.osm.reader as osm_reader
import mapdb.sources.osm.scan as osm_scan
from mapdb.build.merge import content_digest
from mapdb.build.pipeline import build_map
from mapdb.errors import EmptyMapError, MapdbIOError, SourceError
from mapdb.labels import default_label_table
from mapdb.objects import Objects

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TABLE = default_label_table()


def town(offset: float = 0.0, size: int = 6) -> OsmXml:
    """A grid of streets with a building, a park and a forest in each block: areas, junctions, points."""
    doc = OsmXml()
    step = 60.0
    grid = [[doc.node(offset + i * step, j * step) for i in range(size)] for j in range(size)]
    for j in range(size):
        doc.way(grid[j], {"highway": "residential"})
    for i in range(size):
        doc.way([grid[j][i] for j in range(size)], {"highway": "tertiary"})
    for j in range(size - 1):
        for i in range(size - 1):
            cx, cy = offset + (i + 0.5) * step, (j + 0.5) * step
            doc.ring(square(cx - 12, cy, 6), {"building": "yes"})
            doc.ring(square(cx + 12, cy, 5 + (i + j) % 3), {"leisure": "park" if (i + j) % 2 else "pitch"})
            doc.node(cx, cy + 20, {"building": "yes"})
    return doc


def arrays(objects: Objects) -> tuple[np.ndarray, ...]:
    return objects.x, objects.y, objects.label, objects.area


def test_blockwise_read_equals_one_shot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = town().write(tmp_path / "town.osm")
    whole = read_osm_counts(source)
    # Blocks of 3 areas and a road network spilled to buckets after 8 node ids: the same objects.
    monkeypatch.setattr(osm_scan, "AREA_BLOCK", 3)
    monkeypatch.setattr(osm_roads, "ROAD_REFS_IN_MEMORY", 8)
    blocks = read_osm_counts(source)
    assert whole[1]["road_intersection"] == 32 and whole[1]["building"] == 50
    for a, b in zip(arrays(whole[0]), arrays(blocks[0]), strict=True):
        np.testing.assert_array_equal(a, b)


def read_osm_counts(source: Path, **kwargs) -> tuple[Objects, Counter[str]]:
    objects = osm_reader.read_osm(source, TABLE, **kwargs)
    return objects, Counter(objects.names().tolist())


def test_blockwise_build_writes_the_same_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = town().write(tmp_path / "town.osm")
    build_map([source], tmp_path / "one.mapdb")
    monkeypatch.setattr(osm_scan, "AREA_BLOCK", 2)
    monkeypatch.setattr(osm_roads, "ROAD_REFS_IN_MEMORY", 5)
    build_map([source], tmp_path / "blocks.mapdb")
    assert content_digest(tmp_path / "one.mapdb") == content_digest(tmp_path / "blocks.mapdb")


@pytest.mark.parametrize("index", ["sparse_file_array", "dense_file_array"])
def test_file_node_indexes_give_the_same_objects_and_leave_nothing(tmp_path: Path, index: str) -> None:
    source = town().write(tmp_path / "town.osm")
    work = tmp_path / "work"
    work.mkdir()
    in_memory = osm_reader.read_osm(source, TABLE, node_index="flex_mem")
    in_file = osm_reader.read_osm(source, TABLE, node_index=index, index_dir=work)
    for a, b in zip(arrays(in_memory), arrays(in_file), strict=True):
        np.testing.assert_array_equal(a, b)
    assert list(work.iterdir()) == []  # the index file and its directory are gone


def test_junctions_from_buckets_equal_the_in_memory_ones() -> None:
    rng = np.random.default_rng(5)
    lengths = rng.integers(2, 9, 400)
    refs = rng.integers(0, 300, int(lengths.sum()))
    expected = osm_roads._junction_node_ids(refs, lengths)
    got = osm_roads._nodes_with_three_arms(*osm_roads._directed_edges(refs, lengths))
    assert expected.size > 50
    np.testing.assert_array_equal(expected, got)


def test_auto_node_index_follows_the_input_size() -> None:
    assert osm_index.choose_node_index(osm_index.FILE_INDEX_BYTES - 1) == "flex_mem"
    assert osm_index.choose_node_index(osm_index.FILE_INDEX_BYTES) == "sparse_file_array"
    assert osm_index.choose_node_index(osm_index.DENSE_INDEX_BYTES) == "dense_file_array"


def test_an_index_directory_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    source = town(size=3).write(tmp_path / "town.osm")
    missing = tmp_path / "no" / "such"
    with pytest.raises(MapdbIOError, match=r"no/such: cannot hold the node location index"):
        osm_reader.read_osm(source, TABLE, node_index="sparse_file_array", index_dir=missing)
    with pytest.raises(SourceError, match="node index 'mmap'"):
        osm_reader.read_osm(source, TABLE, node_index="mmap")
    out = tmp_path / "map.mapdb"
    run = subprocess.run([sys.executable, "-m", "mapdb_cli", "build", str(source), "-o", str(out), "-q",
                          "--node-index", "sparse_file_array", "--index-dir", str(missing)],
                         capture_output=True, text=True)
    assert run.returncode == 1 and run.stderr.count("\n") == 1 and "mapdb: error:" in run.stderr
    assert not out.exists()


def test_bytes_read_is_the_position_of_the_descriptor(tmp_path: Path) -> None:
    if not Path("/proc/self/fdinfo").is_dir():
        pytest.skip("no /proc/self/fdinfo (not Linux): progress counts objects only")
    path = tmp_path / "data.bin"
    path.write_bytes(bytes(4096))
    with open(path, "rb", buffering=0) as f:
        f.read(1000)
        assert osm_progress._bytes_read(osm_progress._file_identity(str(path))) == 1000


def test_progress_reports_the_share_read_and_the_time_left(tmp_path: Path) -> None:
    if not Path("/proc/self/fdinfo").is_dir():
        pytest.skip("no /proc/self/fdinfo (not Linux): progress counts objects only")
    path = tmp_path / "big.osm.pbf"
    path.write_bytes(bytes(4 << 20))
    lines: list[str] = []
    meter = osm_progress._ByteProgress(path, str(path), lines.append, None)
    with open(path, "rb", buffering=0) as f:  # stands for libosmium's descriptor of the input
        f.read(1 << 20)
        meter.last -= 10
        meter.tick(1000)
        f.read(1 << 20)
        meter.last -= 10
        meter.history[0] = (meter.history[0][0] - 10, meter.history[0][1])  # a quarter of the file in 10 s
        meter.tick(2000)
    assert lines[0] == f"{path}: 25% of 4.0 MiB read, 1,000 tagged objects, about ? left"
    assert lines[1] == f"{path}: 50% of 4.0 MiB read, 2,000 tagged objects, about 20 s left"
    lines.clear()
    meter.last -= 10
    meter.tick(3000)  # the file closed: libosmium has read it all
    assert lines == [f"{path}: 3,000 tagged objects read"]


# ------------------------------------------------------------------------------------------ on Dask


@pytest.mark.slow
def test_a_build_on_dask_equals_the_sequential_build(tmp_path: Path) -> None:
    sources = [town().write(tmp_path / "west.osm"), town(offset=2000.0, size=4).write(tmp_path / "east.osm")]
    build_map(sources, tmp_path / "here.mapdb")
    summary = build_map(sources, tmp_path / "dask.mapdb", jobs=2, jobs_min_bytes=0)
    assert summary["count"] > 100
    assert content_digest(tmp_path / "here.mapdb") == content_digest(tmp_path / "dask.mapdb")


@pytest.mark.slow
def test_a_source_failing_on_dask_fails_the_build_naming_it(tmp_path: Path) -> None:
    good = town().write(tmp_path / "good.osm")
    bad = tmp_path / "bad.osm"
    bad.write_text('<?xml version="1.0"?><osm version="0.6"><node id="1" lat="1" lon="1"><tag k=', encoding="utf-8")
    out = tmp_path / "out.mapdb"
    with pytest.raises(SourceError, match="bad.osm: not a readable OSM file"):
        build_map([good, bad], out, jobs=2, jobs_min_bytes=0)
    assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_the_real_extracts_with_two_jobs_give_the_same_map(tmp_path: Path) -> None:
    extracts = sorted((DATA / "osm").glob("*.osm.pbf"))
    if not extracts:
        pytest.skip(f"no real data at {DATA} (../shared/data beside the checkout)")
    build_map(extracts, tmp_path / "here.mapdb")
    build_map(extracts, tmp_path / "jobs.mapdb", jobs=2, jobs_min_bytes=0)
    assert content_digest(tmp_path / "here.mapdb") == content_digest(tmp_path / "jobs.mapdb")


@pytest.mark.slow
def test_the_cli_takes_the_scale_options(tmp_path: Path) -> None:
    source = town(size=3).write(tmp_path / "town.osm")
    out = tmp_path / "map.mapdb"
    env = dict(os.environ)
    run = subprocess.run([sys.executable, "-m", "mapdb_cli", "build", str(source), "-o", str(out), "-q",
                          "--node-index", "dense_file_array", "--index-dir", str(tmp_path)],
                         capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    both = subprocess.run([sys.executable, "-m", "mapdb_cli", "build", str(source), "-o", str(tmp_path / "b.mapdb"),
                           "--jobs", "2", "--scheduler", "tcp://127.0.0.1:1"], capture_output=True, text=True)
    assert both.returncode == 2 and "not both" in both.stderr


# ------------------------------------------------------------------------------------------ spooled objects


def test_block_medians_and_arcs_equal_those_of_all_values() -> None:
    from mapdb.build import blockstats
    from mapdb.geo import _lon_arc, central_longitude

    rng = np.random.default_rng(11)
    samples = [rng.uniform(-180, 180, 1001), rng.normal(179.99, 0.02, 500), np.round(rng.uniform(5, 9, 800), 2),
               np.array([0.0, -0.0, 2.5, 2.5, -3.0, 1.0]), np.concatenate([rng.uniform(5, 9, 300), [-120.0, 150.0]])]
    for values in samples:
        pieces = np.array_split(values, 4)
        blocks = lambda pieces=pieces: iter(pieces)  # noqa: E731
        # in_memory: 0 reads in passes, the default gathers these few values, one less than them stops early.
        for in_memory in (0, blockstats.IN_MEMORY_VALUES, values.size - 1):
            assert blockstats.median_of(blocks, in_memory) == np.median(values)
            assert blockstats.central_longitude_of(blocks, in_memory) == central_longitude(values)
            # Few bins: the widest gap is often inside a bin, and those bins' values are looked into.
            for bins in (None, 3, 64):
                assert blockstats.lon_arc_of(blocks, bins, in_memory) == _lon_arc(values)


def test_spooled_objects_come_back_in_order_and_leave_nothing(tmp_path: Path) -> None:
    from mapdb.sources.spool import ObjectSpool, joined

    labels = ("a", "b")
    blocks = [Objects(np.arange(n, dtype=float) + 10 * n, np.full(n, float(n)), np.arange(n) % 2, np.ones(n), labels,
                      "EPSG:4326") for n in (5, 1, 7)]
    on_disk, in_memory = ObjectSpool(labels, "EPSG:4326", tmp_path, "t-"), ObjectSpool(labels, "EPSG:4326")
    for block in blocks:
        on_disk.add(block)
        in_memory.add(block)
    assert len(on_disk) == len(in_memory) == 13 and [p.name[:2] for p in tmp_path.iterdir()] == ["t-"]
    assert [len(b) for b in on_disk.blocks(3)] == [3, 3, 3, 3, 1] and max(len(b) for b in in_memory.blocks(4)) == 4
    whole = joined([on_disk], labels, "EPSG:4326")
    np.testing.assert_array_equal(whole.x, np.concatenate([b.x for b in blocks]))
    np.testing.assert_array_equal(whole.label, np.concatenate([b.label for b in blocks]))
    np.testing.assert_array_equal(joined([in_memory], labels, "EPSG:4326").y, whole.y)
    assert list(tmp_path.iterdir()) == []  # joined discards what it copied


def test_a_spooled_read_equals_read_osm_and_a_build_leaves_no_files(tmp_path: Path) -> None:
    source = town().write(tmp_path / "town.osm")
    spool_dir = tmp_path / "spools"
    spool_dir.mkdir()
    spools = osm_reader.read_osm_spooled(source, TABLE, spool_dir=spool_dir)
    assert sorted(p.name.split("-")[1] for p in spool_dir.iterdir()) == ["areas", "others", "points"]
    from mapdb.sources.spool import joined

    for a, b in zip(arrays(joined(spools, TABLE.labels, "EPSG:4326")), arrays(osm_reader.read_osm(source, TABLE)),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    work = tmp_path / "work"
    work.mkdir()
    build_map([source], tmp_path / "map.mapdb", index_dir=work)
    assert list(work.iterdir()) == []
    with pytest.raises(EmptyMapError):
        build_map([source], tmp_path / "none.mapdb", index_dir=work, bbox=(100.0, 10.0, 100.1, 10.1))
    assert list(work.iterdir()) == [] and not (tmp_path / "none.mapdb").exists()


def test_dropped_objects_are_rewritten_and_the_old_file_removed(tmp_path: Path) -> None:
    from mapdb.build.reading import _kept
    from mapdb.sources.spool import ObjectSpool

    spool = ObjectSpool(("a",), "EPSG:4326", tmp_path)
    spool.add(Objects(np.array([1.0, 200.0, 3.0]), np.zeros(3), np.zeros(3, np.int32), np.zeros(3), ("a",),
                      "EPSG:4326"))
    same, dropped = _kept([spool], lambda b: np.ones(len(b), bool))
    assert same == [spool] and dropped == 0
    kept, dropped = _kept([spool], lambda b: np.abs(b.x) <= 180)
    assert dropped == 1 and [b.x.tolist() for b in kept[0].blocks()] == [[1.0, 3.0]]
    assert [p.name.split("-")[0] for p in tmp_path.iterdir()] == ["kept"]


def test_relations_no_rule_labels_are_not_assembled(tmp_path: Path) -> None:
    doc = town(size=3)
    forest = doc.ring(square(500, 500, 40))
    cape = doc.ring(square(900, 500, 40))
    labelled = doc.relation([("w", forest, "outer")], {"type": "multipolygon", "landuse": "forest"})
    unlabelled = doc.relation([("w", cape, "outer")], {"type": "multipolygon", "natural": "peninsula"})
    source = doc.write(tmp_path / "town.osm")
    table = TABLE
    rules = {kind: osm_scan._rules_for(table, kind) for kind in ("area", "node", "way")}
    processor = osm_scan._processor(str(source), osmium.index.create_map("flex_mem"), rules["area"], rules["node"],
                               rules["way"], frozenset())
    from_relations = {obj.orig_id() for obj in processor if obj.type_str() == "a" and not obj.from_way()}
    assert from_relations == {labelled} and unlabelled not in from_relations
    assert osm_reader.read_osm(source, TABLE).counts()["forest"] == 1


def test_hulls_in_slices_equal_hulls_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    doc = OsmXml()
    for i in range(7):
        ring = [doc.node(i * 300 + 20 * np.cos(a), 20 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 9)[:-1]]
        half = 3 + i % 3
        doc.way(ring[:half + 1], {"junction": "roundabout"})
        doc.way(ring[half:] + ring[:1], {"junction": "roundabout"})
    source = doc.write(tmp_path / "rings.osm")
    whole = osm_reader.read_osm(source, TABLE)
    monkeypatch.setattr(osm_areas, "_HULL_POINTS", 3)
    sliced = osm_reader.read_osm(source, TABLE)
    assert whole.counts() == {"roundabout": 7} and (whole.area > 1000).all()
    for a, b in zip(arrays(whole), arrays(sliced), strict=True):
        np.testing.assert_array_equal(a, b)
