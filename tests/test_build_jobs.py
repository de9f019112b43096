"""A parallel build's blocks: a source's footprints in tile files made into blocks by tasks of their own, over
runs of tiles of about equal weight (mapdb.build.tiles.balanced_runs), whose spools joined in order are the one
process's; the map the same bytes with and without ``--jobs 2``, and no worker process left after it."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import shapely
from osmxml import OsmXml, lonlat, square

import mapdb.build.reading as reading
from mapdb.build.pipeline import build_map
from mapdb.build.tiles import FootprintTiles, balanced_runs, tile_blocks_spool
from mapdb.labels import default_label_table
from mapdb.sources.spool import joined

TABLE = default_label_table()

# Towns of terraces (and a street each) in six 0.1-degree tiles about (LON0, LAT0) = (7.42, 43.73): tile edges
# at lon 7.5 (6.4 km east) and 7.6 (14.5 km), lat 43.8 (7.8 km north); one row of houses across lon 7.5.
_TOWNS = [(0.0, 0.0), (3000.0, 0.0), (6380.0, 0.0), (7000.0, 0.0), (9000.0, 9000.0), (15000.0, 0.0),
          (15000.0, 9000.0), (0.0, 9000.0)]


def _terraces(path: Path) -> Path:
    doc = OsmXml()
    for x0, y0 in _TOWNS:
        for row in range(4):
            for house in range(5):
                # 10 m houses 0.4 m apart (within the 0.75 m gap); a lone house beside every other row.
                doc.ring(square(x0 + house * 10.4, y0 + row * 40.0, 5.0), {"building": "yes"})
            if row % 2 == 0:
                doc.ring(square(x0 + 90.0, y0 + row * 40.0, 4.0), {"building": "house"})
        street = [doc.node(x0 - 20.0 + 40.0 * i, y0 - 20.0) for i in range(4)]
        cross = [doc.node(x0 + 20.0, y0 - 60.0 + 40.0 * i) for i in range(3)]
        doc.way(street, {"highway": "residential"})
        doc.way([cross[0], street[1], cross[2]], {"highway": "tertiary"})
    doc.ring(square(100.0, 400.0, 30.0), {"leisure": "park"})
    return doc.write(path)


def test_runs_are_consecutive_cover_every_item_and_weigh_about_the_same() -> None:
    rng = np.random.default_rng(7)
    for n_items, parts in [(1, 1), (1, 3), (5, 8), (40, 2), (605, 8), (300, 3)]:
        weights = rng.integers(1, 1000, n_items).astype(float)
        weights[rng.integers(0, n_items)] *= 20  # one heavy tile (a city centre)
        runs = balanced_runs(weights, parts)
        assert [i for run in runs for i in run] == list(range(n_items))
        assert 1 <= len(runs) <= parts and all(len(run) for run in runs)
        totals = [weights[run.start:run.stop].sum() for run in runs]
        # Within the heaviest item of an equal share, each way.
        assert max(abs(t - weights.sum() / len(runs)) for t in totals) <= weights.max() + 1e-9 or len(runs) < parts
    assert balanced_runs([], 4) == []
    assert balanced_runs([1.0] * 10, 2) == [range(0, 5), range(5, 10)]
    assert balanced_runs([9.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0], 2) == [range(0, 1), range(1, 10)]


def test_groups_of_tiles_give_the_blocks_of_all_tiles_in_order(tmp_path: Path) -> None:
    tiles = FootprintTiles(tmp_path)
    centres = [lonlat(x0 + house * 10.4, y0 + row * 40.0) for x0, y0 in _TOWNS for row in range(4)
               for house in range(5)]
    half = 5.0 / 111_000.0
    tiles.add(shapely.box([c[0] - half * 1.4 for c in centres], [c[1] - half for c in centres],
                          [c[0] + half * 1.4 for c in centres], [c[1] + half for c in centres]))
    homes = sorted(tiles.homes)
    assert len(homes) >= 5
    groups = tiles.groups(3)
    assert [t for g in groups for t in g] == homes and 2 <= len(groups) <= 3
    sizes = [sum((tiles.directory / f"{i}_{j}.tile").stat().st_size for i, j in g) for g in groups]
    largest = max((tiles.directory / f"{i}_{j}.tile").stat().st_size for i, j in homes)
    assert max(sizes) - min(sizes) <= 2 * largest  # balanced by the tile files' sizes
    whole, cut = tile_blocks_spool(tiles, TABLE.labels, 0.75, None)
    parts = [tile_blocks_spool(tiles, TABLE.labels, 0.75, None, g) for g in groups]
    assert len(whole) == 4 * len(_TOWNS) and sum(c for _, c in parts) == cut
    a = joined([whole], TABLE.labels, "EPSG:4326")
    b = joined([s for s, _ in parts], TABLE.labels, "EPSG:4326")
    for left, right in [(a.x, b.x), (a.y, b.y), (a.area, b.area), (a.label, b.label)]:
        np.testing.assert_array_equal(left, right)
    tiles.discard()


def _children() -> list[str]:
    """This process's child processes still running (Dask's nanny and workers, if any were left); not
    multiprocessing's resource tracker, one a process that started any, which ends with it."""
    import psutil

    def running() -> list[str]:
        found = []
        for child in psutil.Process().children(recursive=True):
            try:
                line = " ".join(child.cmdline())
            except psutil.Error:  # ended meanwhile
                continue
            if "multiprocessing.resource_tracker" not in line:
                found.append(line)
        return found

    deadline = time.monotonic() + 5.0
    while running() and time.monotonic() < deadline:
        time.sleep(0.1)  # a process that is ending
    return running()


@pytest.mark.slow
def test_a_split_build_with_blocks_in_tasks_is_the_map_of_one_process(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("distributed")
    source = _terraces(tmp_path / "terraces.osm")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    # Past 20 footprints they go to tile files, in this process and on the workers alike.
    one = build_map([source], tmp_path / "one.mapdb", outlines_in_memory=20)
    monkeypatch.setattr(reading, "SPLIT_OSM_BYTES", 0)  # read here (this process chooses the pieces)
    say: list[str] = []
    two = build_map([source], tmp_path / "two.mapdb", jobs=2, outlines_in_memory=20, progress=say.append)
    assert any("(2 tasks)" in m for m in say), say  # its areas and the rest
    formed = [m for m in say if "blocks of touching buildings" in m]
    assert len(formed) == 1 and "tiles (" in formed[0] and " tasks)" in formed[0], say
    assert int(formed[0].split("tiles (")[1].split()[0]) >= 2
    assert one["labels"]["building_block"] == 4 * len(_TOWNS) == two["labels"]["building_block"]
    assert one["count"] == two["count"] and one["skipped"] == two["skipped"]
    assert (tmp_path / "one.mapdb").read_bytes() == (tmp_path / "two.mapdb").read_bytes()
    assert _children() == []


def _marked(mark: str) -> list[int]:
    """Processes whose environment holds ``mark`` (those a command started inherit it)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if mark.encode() in (entry / "environ").read_bytes():
                found.append(int(entry.name))
        except OSError:  # ended meanwhile, or not ours to read
            continue
    return found


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc to find the processes left")
def test_no_process_is_left_after_the_command_ends(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    source = _terraces(tmp_path / "terraces.osm")
    mark = f"MAPDB_TEST_MARK_{uuid.uuid4().hex}"
    env = {**os.environ, mark: "1"}
    # The extract split (its areas and the rest) whatever its size, so that the command starts its cluster.
    code = ("import sys, mapdb.build.reading as r; r.SPLIT_OSM_BYTES = 0; from mapdb_cli.main import cli; "
            "sys.argv[0] = 'mapdb'; cli()")
    bad = tmp_path / "bad.osm"
    bad.write_text('<?xml version="1.0"?><osm version="0.6"><node id="1" lat="1" lon="1"><tag k=', encoding="utf-8")
    for sources in ([source], [source, bad]):
        run = subprocess.run([sys.executable, "-c", code, "build", *map(str, sources), "-o", str(tmp_path / "m.mapdb"),
                              "--overwrite", "--jobs", "2", "-q"], capture_output=True, text=True, env=env, timeout=300)
        assert run.returncode == (0 if len(sources) == 1 else 1), run.stderr
        if len(sources) > 1:
            # One line, not the worker's log of a task that failed.
            lines = run.stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith(f"mapdb: error: {bad}: not a readable OSM file"), lines
        deadline = time.monotonic() + 5.0
        while _marked(mark) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _marked(mark) == []
