"""Building counts of the real OSM extracts: an independent count beside ``read_osm``.

The independent count shares no code with :mod:`mapdb.sources.osm` and does not use osmium's
area assembly: a plain :class:`osmium.SimpleHandler` counts

* closed building ways (first node == last node, at least 4 node references),
* building multipolygon relations whose member ways join into closed rings that give a valid
  shapely (multi)polygon under the even-odd rule, and
* building nodes,

where "building" means a ``building`` tag other than ``no``.  ``read_osm`` labels some of these
objects otherwise (``leisure=stadium`` wins over ``building``), so small differences are expected.

Run::

    python benchmarks/osm_building_count.py [DATA_DIR]

DATA_DIR defaults to ``../shared/data/osm`` beside the checkout.
"""

from __future__ import annotations

import sys
import time
from functools import reduce
from pathlib import Path

import osmium
import shapely
from shapely.geometry import LineString, MultiLineString, Polygon

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "osm"


def _is_building(tags: osmium.osm.TagList) -> bool:
    value = tags.get("building")
    return value is not None and value != "no"


class _RelationPass(osmium.SimpleHandler):
    """First pass: building multipolygon relations and the ways they are made of."""

    def __init__(self) -> None:
        super().__init__()
        self.members: dict[int, list[int]] = {}

    def relation(self, r: osmium.osm.Relation) -> None:
        if r.tags.get("type") == "multipolygon" and _is_building(r.tags):
            self.members[r.id] = [m.ref for m in r.members if m.type == "w"]


class _WayNodePass(osmium.SimpleHandler):
    """Second pass: closed building ways, building nodes, and the coordinates of member ways."""

    def __init__(self, wanted_ways: set[int]) -> None:
        super().__init__()
        self.wanted = wanted_ways
        self.closed_ways = 0
        self.nodes = 0
        self.lines: dict[int, list[tuple[float, float]]] = {}

    def node(self, n: osmium.osm.Node) -> None:
        if _is_building(n.tags):
            self.nodes += 1

    def way(self, w: osmium.osm.Way) -> None:
        refs = w.nodes
        if _is_building(w.tags) and len(refs) >= 4 and refs[0].ref == refs[-1].ref:
            self.closed_ways += 1
        if w.id in self.wanted:
            coords = [(n.lon, n.lat) for n in refs if n.location.valid()]
            if len(coords) == len(refs) and len(coords) >= 2:
                self.lines[w.id] = coords


def _valid_multipolygon(lines: list[list[tuple[float, float]]]) -> bool:
    if not lines:
        return False
    merged = shapely.line_merge(MultiLineString([LineString(c) for c in lines]))
    rings = list(merged.geoms) if hasattr(merged, "geoms") else [merged]
    if not rings or not all(r.is_ring for r in rings):
        return False
    polygons = [Polygon(r.coords) for r in rings]
    if not all(p.is_valid for p in polygons):
        return False
    shape = reduce(lambda a, b: a.symmetric_difference(b), polygons)
    return shape.is_valid and shape.area > 0


def count_buildings(path: str | Path) -> dict[str, int]:
    """Independent building count of one OSM file.

    Returns
    -------
    dict
        ``closed_ways``, ``relations`` (valid building multipolygons), ``relations_seen`` (all
        building multipolygon relations), ``nodes`` and their ``total``
        (closed_ways + relations + nodes).
    """
    relations = _RelationPass()
    relations.apply_file(str(path))
    wanted = {w for ways in relations.members.values() for w in ways}
    ways_nodes = _WayNodePass(wanted)
    ways_nodes.apply_file(str(path), locations=True)
    valid = 0
    for member_ways in relations.members.values():
        if all(w in ways_nodes.lines for w in member_ways):
            valid += _valid_multipolygon([ways_nodes.lines[w] for w in member_ways])
    total = ways_nodes.closed_ways + valid + ways_nodes.nodes
    return {"closed_ways": ways_nodes.closed_ways, "relations": valid,
            "relations_seen": len(relations.members), "nodes": ways_nodes.nodes, "total": total}


def main(data_dir: Path = DEFAULT_DATA) -> None:
    from mapdb.labels import default_label_table
    from mapdb.sources.osm.reader import read_osm

    files = sorted(data_dir.glob("*.osm.pbf"))
    if not files:
        print(f"no .osm.pbf files in {data_dir}")
        return
    table = default_label_table()
    header = (f"{'extract':<34} {'ways':>6} {'rels':>9} {'nodes':>6} {'indep.':>7} {'read_osm':>8} "
              f"{'diff':>6} {'rel.diff':>8} {'indep s':>7} {'read s':>6}")
    print(header)
    print("-" * len(header))
    for path in files:
        t0 = time.perf_counter()
        c = count_buildings(path)
        t1 = time.perf_counter()
        ours = read_osm(path, table).counts().get("building", 0)
        t2 = time.perf_counter()
        diff = ours - c["total"]
        rels = f"{c['relations']}/{c['relations_seen']}"
        print(f"{path.name:<34} {c['closed_ways']:>6} {rels:>9} {c['nodes']:>6} {c['total']:>7} {ours:>8} "
              f"{diff:>+6} {diff / max(c['total'], 1):>+8.2%} {t1 - t0:>7.2f} {t2 - t1:>6.2f}")
    print("\nrels = valid building multipolygons / all building multipolygon relations; "
          "diff = read_osm - independent")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_DATA)
