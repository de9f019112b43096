"""A large OSM extract read by two Dask tasks at once, its areas and the rest (mapdb.sources.osm.scan.PARTS): the
halves hold the objects and the counts of one read, and the map built from them is the same bytes."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from osmxml import OsmXml, square

import mapdb.build.reading as reading
from mapdb.build.pipeline import build_map
from mapdb.errors import SourceError
from mapdb.labels import default_label_table
from mapdb.progress import as_progress
from mapdb.sources.osm.reader import read_osm_spooled
from mapdb.sources.spool import joined

TABLE = default_label_table()


def _town(path: Path) -> Path:
    """Streets with junctions, a roundabout drawn as a ring, terraces (blocks), a park, a multipolygon lake, a
    labelled node, an unclosed area way and one whose rings cross: every kind of object and of count."""
    doc = OsmXml()
    grid = [[doc.node(i * 80.0, j * 80.0) for i in range(4)] for j in range(4)]
    for j in range(4):
        doc.way(grid[j], {"highway": "residential"})
        doc.way([grid[i][j] for i in range(4)], {"highway": "tertiary"})
    ring = [doc.node(300 + 15 * np.cos(a), 300 + 15 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 9)[:-1]]
    doc.way([*ring, ring[0]], {"highway": "primary", "junction": "roundabout"})
    for row in range(3):
        for house in range(4):
            doc.ring(square(20 + house * 10.4, 20 + row * 80.0, 5.0), {"building": "yes"})
    doc.ring(square(200.0, 120.0, 25.0), {"leisure": "park"})
    outer = doc.ring(square(500.0, 500.0, 40.0))
    inner = doc.ring(square(500.0, 500.0, 10.0))
    doc.relation([("w", outer, "outer"), ("w", inner, "inner")], {"type": "multipolygon", "natural": "water"})
    doc.node(150.0, 150.0, {"amenity": "fountain"})
    corners = [doc.node(x, y) for x, y in square(600.0, 100.0, 10.0)]
    doc.way(corners, {"building": "yes"})  # does not close
    bow = [doc.node(x, y) for x, y in [(700, 0), (720, 20), (720, 0), (700, 20)]]
    doc.way([*bow, bow[0]], {"building": "yes"})  # rings crossing themselves: repaired
    return doc.write(path)


def _read(source: Path, part: str) -> tuple[np.ndarray, Counter[str]]:
    counts: Counter[str] = Counter()
    objects = joined(read_osm_spooled(source, TABLE, counts=counts, part=part), TABLE.labels, "EPSG:4326")
    rows = np.rec.fromarrays([objects.x, objects.y, objects.label, objects.area])
    return np.sort(rows), Counter({k: n for k, n in counts.items() if n})


def test_the_halves_hold_the_objects_and_counts_of_one_read(tmp_path: Path) -> None:
    source = _town(tmp_path / "town.osm")
    whole, counts = _read(source, "all")
    areas, area_counts = _read(source, "areas")
    rest, rest_counts = _read(source, "rest")
    names = Counter(TABLE.labels[c] for c in whole["f2"])
    assert names["road_intersection"] >= 4 and names["roundabout"] == 1 and names["water"] == 1
    assert counts["unclosed_rings"] == 1 and counts["repaired_geometries"] == 1
    assert len(areas) and len(rest)
    np.testing.assert_array_equal(np.sort(np.concatenate([areas, rest])), whole)
    assert area_counts + rest_counts == counts


def test_an_unknown_part_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="part 'half': not one of all, areas, rest"):
        read_osm_spooled(_town(tmp_path / "town.osm"), TABLE, part="half")


def test_a_large_extract_makes_workers_pay(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = _town(tmp_path / "town.osm")
    say = as_progress(None)
    assert reading._paying_jobs([source], 2, 1 << 30, say) is None
    monkeypatch.setattr(reading, "SPLIT_OSM_BYTES", 1000)
    assert reading._paying_jobs([source], 2, 1 << 30, say) == 2
    assert reading._paying_jobs([source], 1, 1 << 30, say) is None  # one worker: no halves
    spooling = reading._Spooling(str(tmp_path), "auto", True)
    assert [p[1] for p in reading._pieces([source, source], spooling, 2)] == ["areas", "rest", "areas", "rest"]
    assert [p[1] for p in reading._pieces([source], spooling, 1)] == ["all"]


@pytest.mark.slow
def test_a_build_of_halves_on_dask_is_the_same_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    source = _town(tmp_path / "town.osm")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    one = build_map([source], tmp_path / "one.mapdb")
    monkeypatch.setattr(reading, "SPLIT_OSM_BYTES", 0)
    say: list[str] = []
    two = build_map([source], tmp_path / "two.mapdb", jobs=2, progress=say.append)
    assert any("(2 tasks)" in m for m in say), say
    assert one["count"] == two["count"] and one["skipped"] == two["skipped"]
    assert (tmp_path / "one.mapdb").read_bytes() == (tmp_path / "two.mapdb").read_bytes()
