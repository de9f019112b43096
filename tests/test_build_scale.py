"""The streaming OSM build (areas in blocks, the road network in buckets on disk, file node indexes), its
progress by bytes read, and builds of several sources on Dask: each gives the map of the one-shot build."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from osmxml import OsmXml, square

import mapdb.sources.osm as osm
from mapdb.build import build_map
from mapdb.errors import MapdbIOError, SourceError
from mapdb.labels import default_label_table
from mapdb.merge import content_digest
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
    monkeypatch.setattr(osm, "AREA_BLOCK", 3)
    monkeypatch.setattr(osm, "ROAD_REFS_IN_MEMORY", 8)
    blocks = read_osm_counts(source)
    assert whole[1]["road_intersection"] == 32 and whole[1]["building"] == 50
    for a, b in zip(arrays(whole[0]), arrays(blocks[0]), strict=True):
        np.testing.assert_array_equal(a, b)


def read_osm_counts(source: Path, **kwargs) -> tuple[Objects, Counter[str]]:
    objects = osm.read_osm(source, TABLE, **kwargs)
    return objects, Counter(objects.names().tolist())


def test_blockwise_build_writes_the_same_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = town().write(tmp_path / "town.osm")
    build_map([source], tmp_path / "one.mapdb")
    monkeypatch.setattr(osm, "AREA_BLOCK", 2)
    monkeypatch.setattr(osm, "ROAD_REFS_IN_MEMORY", 5)
    build_map([source], tmp_path / "blocks.mapdb")
    assert content_digest(tmp_path / "one.mapdb") == content_digest(tmp_path / "blocks.mapdb")


@pytest.mark.parametrize("index", ["sparse_file_array", "dense_file_array"])
def test_file_node_indexes_give_the_same_objects_and_leave_nothing(tmp_path: Path, index: str) -> None:
    source = town().write(tmp_path / "town.osm")
    work = tmp_path / "work"
    work.mkdir()
    in_memory = osm.read_osm(source, TABLE, node_index="flex_mem")
    in_file = osm.read_osm(source, TABLE, node_index=index, index_dir=work)
    for a, b in zip(arrays(in_memory), arrays(in_file), strict=True):
        np.testing.assert_array_equal(a, b)
    assert list(work.iterdir()) == []  # the index file and its directory are gone


def test_junctions_from_buckets_equal_the_in_memory_ones() -> None:
    rng = np.random.default_rng(5)
    lengths = rng.integers(2, 9, 400)
    refs = rng.integers(0, 300, int(lengths.sum()))
    expected = osm._junction_node_ids(refs, lengths)
    got = osm._nodes_with_three_arms(*osm._directed_edges(refs, lengths))
    assert expected.size > 50
    np.testing.assert_array_equal(expected, got)


def test_auto_node_index_follows_the_input_size() -> None:
    assert osm.choose_node_index(osm.FILE_INDEX_BYTES - 1) == "flex_mem"
    assert osm.choose_node_index(osm.FILE_INDEX_BYTES) == "sparse_file_array"
    assert osm.choose_node_index(osm.DENSE_INDEX_BYTES) == "dense_file_array"


def test_an_index_directory_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    source = town(size=3).write(tmp_path / "town.osm")
    missing = tmp_path / "no" / "such"
    with pytest.raises(MapdbIOError, match=r"no/such: cannot hold the node location index"):
        osm.read_osm(source, TABLE, node_index="sparse_file_array", index_dir=missing)
    with pytest.raises(SourceError, match="node index 'mmap'"):
        osm.read_osm(source, TABLE, node_index="mmap")
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
        assert osm._bytes_read(osm._file_identity(str(path))) == 1000


def test_progress_reports_the_share_read_and_the_time_left(tmp_path: Path) -> None:
    if not Path("/proc/self/fdinfo").is_dir():
        pytest.skip("no /proc/self/fdinfo (not Linux): progress counts objects only")
    path = tmp_path / "big.osm.pbf"
    path.write_bytes(bytes(4 << 20))
    lines: list[str] = []
    meter = osm._ByteProgress(path, str(path), lines.append, None)
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
    summary = build_map(sources, tmp_path / "dask.mapdb", jobs=2)
    assert summary["count"] > 100
    assert content_digest(tmp_path / "here.mapdb") == content_digest(tmp_path / "dask.mapdb")


@pytest.mark.slow
def test_a_source_failing_on_dask_fails_the_build_naming_it(tmp_path: Path) -> None:
    good = town().write(tmp_path / "good.osm")
    bad = tmp_path / "bad.osm"
    bad.write_text('<?xml version="1.0"?><osm version="0.6"><node id="1" lat="1" lon="1"><tag k=', encoding="utf-8")
    out = tmp_path / "out.mapdb"
    with pytest.raises(SourceError, match="bad.osm: not a readable OSM file"):
        build_map([good, bad], out, jobs=2)
    assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.slow
def test_the_real_extracts_with_two_jobs_give_the_same_map(tmp_path: Path) -> None:
    extracts = sorted((DATA / "osm").glob("*.osm.pbf"))
    if not extracts:
        pytest.skip(f"no real data at {DATA} (../shared/data beside the checkout)")
    build_map(extracts, tmp_path / "here.mapdb")
    build_map(extracts, tmp_path / "jobs.mapdb", jobs=2)
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
