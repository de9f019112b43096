"""An OSM extract's building footprints past OUTLINES_IN_MEMORY wait in tile files (mapdb.build.tiles), as a
layer's do: the blocks, and the map, are those of the footprints held in memory."""

from __future__ import annotations

from pathlib import Path

import pytest
from osmxml import OsmXml, square

import mapdb.build.tiles as tiles
from mapdb.build.pipeline import build_map
from mapdb.sources.spool import spool_bytes


def _terraces(path: Path) -> Path:
    """Rows of touching houses in two 0.1-degree tiles (7 km apart, tile edge at lon 7.5 between them), a row
    across that edge, lone houses and a park: blocks in every tile."""
    doc = OsmXml()
    for x0 in (0.0, 3000.0, 6380.0, 7000.0):
        for row in range(6):
            for house in range(5):
                # 10 m houses 0.4 m apart (within the 0.75 m gap); every third row has a lone house 30 m off.
                doc.ring(square(x0 + house * 10.4, row * 40.0, 5.0), {"building": "yes"})
            if row % 3 == 0:
                doc.ring(square(x0 + 90.0, row * 40.0, 4.0), {"building": "house"})
    doc.ring(square(100.0, 400.0, 30.0), {"leisure": "park"})
    return doc.write(path)


def test_footprints_in_tile_files_give_the_map_of_footprints_in_memory(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    source = _terraces(tmp_path / "terraces.osm")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    held = build_map([source], tmp_path / "held.mapdb")
    # Past 20 footprints they go to tile files, and the blocks are formed tile by tile.
    monkeypatch.setattr(tiles, "OUTLINES_IN_MEMORY", 20)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    say: list[str] = []
    tiled = build_map([source], tmp_path / "tiled.mapdb", index_dir=scratch, progress=say.append)
    assert any("blocks of touching buildings" in m and "in 2 tiles" in m for m in say), say
    assert held["labels"]["building_block"] == 24 == tiled["labels"]["building_block"]
    assert (tmp_path / "held.mapdb").read_bytes() == (tmp_path / "tiled.mapdb").read_bytes()
    assert not list(scratch.iterdir())


def test_the_room_foreseen_for_an_extract_counts_its_footprints(tmp_path: Path) -> None:
    source = _terraces(tmp_path / "terraces.osm")
    size = source.stat().st_size
    assert spool_bytes(source, True, True) == spool_bytes(source, True, False) + size
    assert spool_bytes(source, False, True) == size
