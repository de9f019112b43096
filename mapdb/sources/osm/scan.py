"""The pass over an OSM file: pyosmium's reader with its C++ tag filters, the handling of each object
it lets through, and the repair of the areas osmium could not assemble.
"""

from __future__ import annotations

from array import array
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import osmium
import osmium.filter
import shapely

from ...geo import in_bbox
from ...labels import LabelTable, TagRule
from ...objects import Objects
from ..spool import ObjectSpool
from .areas import _area_objects, _point_objects, _Ways
from .index import _defined, _Workspace
from .intersections import _RoadNetwork
from .progress import _PROGRESS_STRIDE, Progress, _ByteProgress

__all__ = ["AREA_BLOCK", "PARTS", "POINT_BLOCK", "OutlineSink"]

# What is handed each block of areas' outlines, when asked: their geometries (shapely, lon/lat) and label codes.
# The geometries are moved to local coordinates once the call returns: a sink keeps their WKB, not them.
OutlineSink = Callable[[np.ndarray, list[int]], None]

# The relations libosmium assembles into areas (with at least one way member).
_AREA_RELATION_TYPES = frozenset({"multipolygon", "boundary"})

# Areas whose centroid and area are computed together, after which their geometries are dropped: big
# enough for shapely's vectorised calls to pay, small enough that the geometries cost a few megabytes.
AREA_BLOCK = 4096
# Labelled nodes handed on at once (1.2 MB of typed arrays).
POINT_BLOCK = 1 << 16

# The halves of an extract two processes can read at once, each in a pass of its own over the whole file
# (``read_osm_spooled(part=...)``): the areas (libosmium's assembly, their centroids and areas, and the
# footprints of their blocks), and the rest (labelled nodes, the ways of "way" rules, the checks of ways tagged
# as areas, the road network).  Together they are the objects and counts of one pass ("all").
PARTS = ("all", "areas", "rest")


class _Sink:
    """Where the pass puts its objects: the spools of points, areas and the rest, each block clipped to the
    bbox first (clipping is per object, so blocks give what clipping the whole would)."""

    def __init__(self, spools: list[ObjectSpool], bbox: tuple[float, float, float, float] | None,
                 n_labels: int) -> None:
        self.spools, self.bbox = spools, bbox
        self.found = np.zeros(n_labels, np.int64)  # objects kept, per label code

    def add(self, which: int, objects: Objects) -> None:
        if self.bbox is not None and len(objects):
            inside = in_bbox(self.bbox, objects.x, objects.y)
            objects = objects if inside.all() else objects.take(inside)
        self.found += np.bincount(objects.label, minlength=self.found.size)
        self.spools[which].add(objects)


class _Collected:
    """What the single pass over the file keeps: compact per-object values, the geometries of one block of areas."""

    def __init__(self, labels: tuple[str, ...], workspace: _Workspace, counts: Counter[str], input_bytes: int,
                 sink: _Sink) -> None:
        self.labels = labels
        self.counts = counts
        self.sink = sink
        self.input_bytes = input_bytes
        # The labelled nodes not yet handed to the sink (typed arrays, flushed every POINT_BLOCK nodes).
        self.node_lon = array("d")
        self.node_lat = array("d")
        self.node_code = array("i")
        # The current block of assembled areas (WKB and label code); each full block becomes centroids and
        # areas handed to the sink, and its geometries are dropped.
        self.area_wkb: list[str] = []
        self.area_code: list[int] = []
        # Ways matched by a "way" rule (compact typed arrays, joined into objects after the pass).
        self.ways = _Ways()
        self.roads = _RoadNetwork(workspace, input_bytes)
        self.locations: Any = None  # osmium's node location table, for looking up junction nodes
        self.index_file: str | None = None  # its file, when it has one
        # Closed ways whose area osmium could not assemble (rings crossing themselves), with their
        # label code: rebuilt by _repair_ways.
        self.failed_area_ways: dict[int, int] = {}
        # Areas osmium assembled from relations: the labelled relations it was given that never came out
        # are the ones it could not complete (see _LabelledRelations).
        self.relation_areas = 0
        # Who else wants each block of areas' outlines before they are dropped (the builder's blocks of
        # touching buildings, mapdb.build.blocks): called with the block's WKB and label codes.
        self.outlines: OutlineSink | None = None

    def add_area(self, wkb: str, code: int) -> None:
        self.area_wkb.append(wkb)
        self.area_code.append(code)
        if len(self.area_wkb) >= AREA_BLOCK:
            self.finish_areas()

    def finish_areas(self) -> None:
        """Centroids and areas of the current block of areas, to the sink; the geometries are dropped."""
        if self.area_wkb:
            # osmium's WKB parsed once for both (a block's parsing took a third of the areas' pass when each did).
            geoms = shapely.from_wkb(np.asarray(self.area_wkb, dtype=object))
            if self.outlines is not None:
                self.outlines(geoms, self.area_code)  # first: _area_objects moves the coordinates in place
            self.sink.add(1, _area_objects(geoms, self.area_code, self.labels, self.counts))
            self.area_wkb, self.area_code = [], []

    def add_point(self, lon: float, lat: float, code: int) -> None:
        self.node_lon.append(lon)
        self.node_lat.append(lat)
        self.node_code.append(code)
        if len(self.node_code) >= POINT_BLOCK:
            self.finish_points()

    def finish_points(self) -> None:
        """The labelled nodes collected so far, to the sink."""
        if len(self.node_code):
            self.sink.add(0, _point_objects(self.node_lon, self.node_lat, self.node_code, self.labels))
            self.node_lon, self.node_lat, self.node_code = array("d"), array("d"), array("i")


def _rules_for(table: LabelTable, geometry: str) -> list[tuple[int, TagRule]]:
    return [(table.code(r.label), r) for r in table.osm_rules if geometry in r.geometry]


def _first_match(rules: list[tuple[int, TagRule]], tags: Any) -> int:
    for code, rule in rules:
        if rule.matches(tags.get(rule.key)):
            return code
    return -1


def _tag_prefilter(rules: Sequence[TagRule], extra: Sequence[tuple[str, str]] = ()) -> Any:
    """A C++ filter letting through (a superset of) the objects these rules can match; None if none can.

    A TagFilter on (key, value) pairs is tighter, but a rule for any value of a key (``values``
    omitted) needs a KeyFilter; the exact test, with ``exclude``, is made in Python.
    """
    if any(r.values is None for r in rules):
        keys = sorted({r.key for r in rules} | {key for key, _ in extra})
        return osmium.filter.KeyFilter(*keys)
    pairs = sorted({(r.key, v) for r in rules for v in (r.values or ())} | set(extra))
    return osmium.filter.TagFilter(*pairs) if pairs else None


def _scan(path: Path, source: str, table: LabelTable, report: Progress, out: _Collected, part: str = "all") -> None:
    """One pass over ``source``: the labelled nodes, areas and ways, and the road ways' nodes (``part``: all of
    them, or one of the two halves of :data:`PARTS`)."""
    area_rules = _rules_for(table, "area") if part != "rest" else []
    node_rules = _rules_for(table, "node") if part != "areas" else []
    way_rules = _rules_for(table, "way") if part != "areas" else []
    roads = frozenset(table.intersections.highways) if table.intersections is not None else frozenset()
    roads = roads if part != "areas" else frozenset()
    checks = _rules_for(table, "area") if part != "areas" else []  # ways tagged as areas, checked and counted
    relations = _LabelledRelations(area_rules)
    processor = _processor(source, out.locations, area_rules, node_rules, way_rules, roads, relations, checks)
    wkb = osmium.geom.WKBFactory()
    counts = out.counts
    seen = 0
    meter = _ByteProgress(path, source, report, out.index_file)
    for obj in processor:
        seen += 1
        if seen % _PROGRESS_STRIDE == 0:
            meter.tick(seen)
        kind = obj.type_str()
        if kind == "a":
            _take_area(obj, area_rules, wkb, out, counts)
        elif kind == "n":
            _take_node(obj, node_rules, out, counts)
        elif kind == "w":
            _take_way(obj, way_rules, checks, roads, wkb, out, counts)
    meter.release()
    # Relations osmium was given but never assembled: a member way or node missing from the extract (or
    # out of range), as libosmium waits for all members and builds no rings through an invalid location.
    counts["incomplete_relations"] += relations.assembling - out.relation_areas


def _processor(source: str, locations: Any, area_rules: list[tuple[int, TagRule]],
               node_rules: list[tuple[int, TagRule]], way_rules: list[tuple[int, TagRule]],
               roads: frozenset[str], relations: _LabelledRelations | None = None,
               checks: list[tuple[int, TagRule]] | None = None) -> Any:
    """osmium's reader of ``source``, letting through (a superset of) the objects the rules may use;
    ``relations`` (made here when None) is the first pass's filter of the relations to assemble, ``checks``
    the area rules whose ways are checked (``area_rules`` when None)."""
    checks = area_rules if checks is None else checks
    area_filter = _tag_prefilter([r for _, r in area_rules])
    node_filter = _tag_prefilter([r for _, r in node_rules])
    # Ways tagged as areas come through too: osmium silently drops those that do not close or have a
    # node out of range, and they must be counted.
    way_filter = _tag_prefilter([r for _, r in way_rules + checks], [("highway", h) for h in sorted(roads)])

    processor = osmium.FileProcessor(source).with_locations(locations)
    kinds = osmium.osm.NOTHING
    if area_filter is not None:
        # The same filter picks the multipolygon relations worth assembling in the first pass, and then the
        # rules themselves: libosmium keeps every relation it is given, with its members, until it is
        # complete, and a relation no rule labels (a peninsula or a mountain range of thousands of members,
        # most of them outside the extract) never gives an object.
        relations = relations if relations is not None else _LabelledRelations(area_rules)
        processor.with_areas(_tag_prefilter([r for _, r in area_rules]), relations)
        processor.with_filter(area_filter.enable_for(osmium.osm.AREA))
        kinds |= osmium.osm.AREA
    if node_filter is not None:
        processor.with_filter(node_filter.enable_for(osmium.osm.NODE))
        kinds |= osmium.osm.NODE
    if way_filter is not None:
        processor.with_filter(way_filter.enable_for(osmium.osm.WAY))
        kinds |= osmium.osm.WAY
    # Relations themselves (and changesets) are never objects: their areas come as Area objects.
    processor.with_filter(osmium.filter.EntityFilter(kinds))
    return processor


class _LabelledRelations:
    """A first-pass filter for osmium's area assembly: drops the relations no area rule labels, and counts
    those of the others that libosmium's multipolygon manager will try to assemble."""

    def __init__(self, area_rules: list[tuple[int, TagRule]]) -> None:
        self.area_rules = area_rules
        self.assembling = 0

    def relation(self, relation: Any) -> bool:
        if _first_match(self.area_rules, relation.tags) < 0:
            return True  # filtered out
        # The relations libosmium's MultipolygonManager takes: type multipolygon or boundary, a way member.
        if relation.tags.get("type") in _AREA_RELATION_TYPES and any(m.type == "w" for m in relation.members):
            self.assembling += 1
        return False


def _take_area(obj: Any, area_rules: list[tuple[int, TagRule]], wkb: Any, out: _Collected,
               counts: Counter[str]) -> None:
    """Keep an assembled area that an area rule labels (or note why it cannot be kept)."""
    if not obj.from_way():
        out.relation_areas += 1
    code = _first_match(area_rules, obj.tags)
    if code < 0:
        return
    try:
        geometry = wkb.create_multipolygon(obj)
    except osmium.InvalidLocationError:
        counts["invalid_coordinates"] += 1
        return
    except RuntimeError:  # osmium found the rings invalid (crossing themselves)
        if obj.from_way():
            out.failed_area_ways[obj.orig_id()] = code
        else:
            counts["invalid_geometries"] += 1
        return
    out.add_area(geometry, code)


def _take_node(obj: Any, node_rules: list[tuple[int, TagRule]], out: _Collected, counts: Counter[str]) -> None:
    """Keep a node that a node rule labels, when its location is valid (counted when out of range)."""
    code = _first_match(node_rules, obj.tags)
    if code < 0:
        return
    location = obj.location
    if location.valid():
        out.add_point(location.lon, location.lat, code)
    elif _defined(location):
        counts["invalid_coordinates"] += 1


def _take_way(obj: Any, way_rules: list[tuple[int, TagRule]], area_rules: list[tuple[int, TagRule]],
              roads: frozenset[str], wkb: Any, out: _Collected, counts: Counter[str]) -> None:
    """Keep a way that a way rule labels, check one tagged as an area, and keep a road's nodes."""
    tags = obj.tags
    code = _first_match(way_rules, tags)
    if code >= 0:
        _collect_way(obj, code, out, counts)
    elif area_rules:
        _check_area_way(obj, tags, area_rules, wkb, counts)
    if roads and tags.get("highway") in roads:
        out.roads.add([n.ref for n in obj.nodes])


def _has_bad_node(way: Any) -> bool:
    """Whether some node of a way has coordinates out of range (not merely missing from the extract)."""
    return any(not n.location.valid() and _defined(n.location) for n in way.nodes)


def _collect_way(way: Any, code: int, out: _Collected, counts: Counter[str]) -> None:
    """Keep a way matched by a "way" rule, unless a node of it lies out of range."""
    if _has_bad_node(way):
        counts["invalid_coordinates"] += 1
        return
    nodes = [n for n in way.nodes if n.location.valid()]  # nodes missing from an extract are left out
    if nodes:
        out.ways.add(nodes, code)


def _check_area_way(way: Any, tags: Any, area_rules: list[tuple[int, TagRule]], wkb: Any,
                    counts: Counter[str]) -> None:
    """Count a way tagged as an area that osmium will not make one of: unclosed, a node out of range, or a
    node missing from the extract (a way cut by a clipped extract's border).

    A ring closed from the nodes present is not kept: it is not the area's outline (a building that loses one
    corner keeps half its area, its centroid moves some 4 m; ``benchmarks/clipped_areas.py``).

    The cheap tests come first: most ways here are closed and sound, and the tag rules are tried
    only for the few that are not.
    """
    if way.is_closed():
        try:
            wkb.create_linestring(way)  # one C++ pass over the node locations; the result is not needed
            return
        except osmium.InvalidLocationError:
            kind = "invalid_coordinates" if _has_bad_node(way) else "missing_nodes"
        except RuntimeError:  # fewer than two distinct nodes: osmium will not assemble it either
            kind = "invalid_geometries"
    else:
        kind = "unclosed_rings"
    if _first_match(area_rules, tags) >= 0:
        counts[kind] += 1


def _repair_ways(source: str, c: _Collected, counts: Counter[str]) -> None:
    """Rebuild the areas of closed ways whose rings cross themselves, with shapely's ``make_valid``.

    A second pass over the file, reading ways only, finds their node ids; the locations come from
    the first pass's table.
    """
    wanted = c.failed_area_ways
    processor = osmium.FileProcessor(source, osmium.osm.WAY).with_filter(osmium.filter.IdFilter(list(wanted)))
    for way in processor:
        if not isinstance(way, osmium.osm.Way):  # never taken (ways only are read); narrows the type for mypy
            continue
        code = wanted.get(way.id)
        if code is None:
            continue
        try:
            points = [c.locations.get(n.ref) for n in way.nodes]
            ring = [(p.lon, p.lat) for p in points]
        except (KeyError, osmium.InvalidLocationError):
            counts["invalid_coordinates"] += 1
            continue
        fixed = shapely.make_valid(shapely.Polygon(ring), method="structure", keep_collapsed=False)
        if fixed.is_empty or shapely.area(fixed) <= 0:
            counts["invalid_geometries"] += 1
            continue
        counts["repaired_geometries"] += 1
        c.add_area(shapely.to_wkb(fixed, hex=True), code)
