"""The shapes a camera would see, read from an OpenStreetMap extract: what :mod:`mapdb.simulation.render` draws.

A map stores one point per object; a rendered mask needs the objects' outlines.  This module reads
them from the extract the map was built from, with the same label rules (:mod:`mapdb.labels`, tried
by the reader's own rule matching) and the pieces of :mod:`mapdb.sources.osm` that make a read safe
(its file checks, bounded decompression and repair of XML, C++ tag pre-filters), in one pyosmium pass
of its own that keeps the outlines the reader turns into centroids; it projects them into the map's
CRS, gives every building a height, and links every shape to the map object it is (:class:`Scene`).

What becomes a shape
--------------------
* **Areas** (closed ways and multipolygon relations matching an ``"area"`` rule): their polygons.
  Objects labelled ``building`` are prisms standing on the ground; every other label is flat.
* **Ways** matching a ``"way"`` rule (roundabouts drawn as rings): the line widened to a road
  :data:`ROAD_WIDTH_M` wide, flat; the pieces of one roundabout touch, so they merge in a mask.
* **Road intersections**: discs :data:`INTERSECTION_DIAMETER_M` across (about the crossing of two
  streets), flat, at the map's own intersection points (their merging rule lives in the reader).
* **Tagged nodes** (a building or a car park mapped as a point) have no outline: they are left out of
  masks, as are areas osmium cannot assemble (rings crossing themselves); ``counts`` says how many.

Building heights (metres), first rule that applies
--------------------------------------------------
1. the ``height`` tag: ``"12"``, ``"12.5"``, ``"12 m"``, ``"12,5"``, ``"40'"`` / ``"40 ft"`` (feet),
   ``"12'6\\""``; values outside (0, 1000] m are ignored;
2. ``building:levels`` (plus ``roof:levels`` when tagged) times :data:`LEVEL_HEIGHT_M`, plus
   :data:`ROOF_ALLOWANCE_M` for the roof slab or parapet above the top floor;
3. the building type (the ``building`` value) in :data:`TYPE_HEIGHTS_M` (else
   :data:`DEFAULT_HEIGHT_M`), times a factor drawn uniformly in ``1 +- HEIGHT_SPREAD`` per building,
   seeded: the same extract and seed give the same heights.

In the 2021 Monaco extract 39 of 1,206 buildings have a ``height`` and 114 ``building:levels``; in
Andorra 2 and 163 of 4,914: most heights come from rule 3.
"""

from __future__ import annotations

import re
from collections import Counter
from contextlib import nullcontext
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import osmium
import shapely
from pyproj import Transformer

from .._scipy import cKDTree
from ..errors import SourceError
from ..labels import LabelTable, TagRule, default_label_table
from ..objects import Objects

# One reader of OSM files: the same checks, XML repair, tag pre-filters and label-rule matching.
from ..sources.osm.files import _XML_SUFFIXES, _check_readable, _xml_input
from ..sources.osm.scan import _first_match, _rules_for, _tag_prefilter

__all__ = [
    "DEFAULT_HEIGHT_M",
    "HEIGHT_SPREAD",
    "INTERSECTION_DIAMETER_M",
    "LEVEL_HEIGHT_M",
    "ROAD_WIDTH_M",
    "ROOF_ALLOWANCE_M",
    "TYPE_HEIGHTS_M",
    "Scene",
    "building_heights",
    "parse_height",
    "read_scene",
]

LEVEL_HEIGHT_M = 3.0
ROOF_ALLOWANCE_M = 1.0
DEFAULT_HEIGHT_M = 7.0
HEIGHT_SPREAD = 0.25
ROAD_WIDTH_M = 6.0
INTERSECTION_DIAMETER_M = 8.0
# Typical heights (metres) of untagged buildings by their ``building`` value: a few storeys of 3 m.
TYPE_HEIGHTS_M: dict[str, float] = {
    "house": 6.0, "detached": 6.0, "semidetached_house": 6.0, "bungalow": 4.0, "terrace": 8.0,
    "residential": 10.0, "apartments": 15.0, "dormitory": 12.0, "hotel": 15.0, "office": 15.0,
    "commercial": 10.0, "retail": 6.0, "supermarket": 6.0, "industrial": 8.0, "warehouse": 8.0,
    "hangar": 10.0, "church": 15.0, "cathedral": 25.0, "chapel": 6.0, "mosque": 12.0, "temple": 8.0,
    "school": 10.0, "university": 12.0, "hospital": 15.0, "public": 10.0, "civic": 10.0,
    "government": 12.0, "train_station": 10.0, "garage": 3.0, "garages": 3.0, "carport": 3.0,
    "shed": 3.0, "hut": 3.0, "cabin": 4.0, "kiosk": 3.0, "toilets": 3.0, "service": 3.0,
    "farm_auxiliary": 5.0, "barn": 7.0, "stable": 5.0, "greenhouse": 4.0, "roof": 4.0,
    "construction": 5.0,
}
# Painter's layers: ground areas first, then marks on the ground, then what stands on it.
LAYER_AREA, LAYER_MARK, LAYER_BUILDING = 0, 1, 2
# Height source codes (Scene.height_source).
FLAT, FROM_HEIGHT, FROM_LEVELS, FROM_TYPE = 0, 1, 2, 3

_METRES = re.compile(r"([0-9]+(?:[.,][0-9]+)?)\s*(?:m|metres|meters|metre|meter)?")
_FEET = re.compile(r"([0-9]+(?:\.[0-9]+)?)\s*(?:'|ft|feet)(?:\s*([0-9]+(?:\.[0-9]+)?)\s*(?:\"|in))?")
_MAX_HEIGHT_M = 1000.0
_MAX_LEVELS = 300.0
# A shape is the map object of its label nearest its centroid within this (metres); see read_scene.
_LINK_TOLERANCE_M = 1.0


def parse_height(text: str | None) -> float | None:
    """Metres from an OSM ``height`` value, None when it is missing, unreadable or not in (0, 1000].

    Examples
    --------
    >>> [parse_height(t) for t in ["12", "12.5 m", "12,5", "40'", "12'6\\"", "tall", "-3", None]]
    [12.0, 12.5, 12.5, 12.192, 3.81, None, None, None]
    """
    if text is None:
        return None
    text = text.strip().lower()
    if m := _METRES.fullmatch(text):
        value = float(m.group(1).replace(",", "."))
    elif m := _FEET.fullmatch(text):
        value = round((float(m.group(1)) + float(m.group(2) or 0.0) / 12.0) * 0.3048, 6)
    else:
        return None
    return value if 0.0 < value <= _MAX_HEIGHT_M else None


def _parse_levels(text: str | None) -> float | None:
    """A ``building:levels`` count (``"3"``, ``"2.5"``), None when missing or unreadable."""
    if text is None:
        return None
    try:
        value = float(text.strip())
    except ValueError:
        return None
    return value if 0.0 <= value <= _MAX_LEVELS else None


def building_heights(tags: list[dict[str, str]], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Heights (metres) of buildings from their tags by the module's rules, and which rule gave each.

    The spread of rule 3 is drawn for every building in order (one draw each), so a building's height
    depends on its place in the list and the seed only.

    Examples
    --------
    >>> h, rule = building_heights([{"height": "20 m"}, {"building:levels": "4", "roof:levels": "1"},
    ...                             {"building": "house"}], seed=1)
    >>> h[:2].tolist(), rule.tolist(), bool(6.0 * 0.75 <= h[2] <= 6.0 * 1.25)
    ([20.0, 16.0], [1, 2, 3], True)
    """
    spread = np.random.default_rng(seed).uniform(1.0 - HEIGHT_SPREAD, 1.0 + HEIGHT_SPREAD, len(tags))
    height = np.zeros(len(tags))
    rule = np.zeros(len(tags), np.int8)
    for i, t in enumerate(tags):  # a few tags per building; the scan already spent more per object
        tagged = parse_height(t.get("height"))
        levels = _parse_levels(t.get("building:levels"))
        if tagged is not None:
            height[i], rule[i] = tagged, FROM_HEIGHT
        elif levels is not None:
            roof = _parse_levels(t.get("roof:levels")) or 0.0
            height[i], rule[i] = LEVEL_HEIGHT_M * (levels + roof) + ROOF_ALLOWANCE_M, FROM_LEVELS
        else:
            base = TYPE_HEIGHTS_M.get(t.get("building", ""), DEFAULT_HEIGHT_M)
            height[i], rule[i] = base * spread[i], FROM_TYPE
    return height, rule


@dataclass(frozen=True)
class Scene:
    """Shapes in a map's CRS, each linked to the map object it is.

    Attributes
    ----------
    geometry : ndarray of shapely Polygon / MultiPolygon
        Outlines on the ground (map CRS metres).
    label : ndarray of int32
        Codes into ``labels`` (the map's labels).
    height : ndarray of float64
        Metres above ground of the top of each shape (0: flat).
    layer : ndarray of int8
        0 ground area, 1 mark on the ground (road, intersection), 2 building.
    map_index : ndarray of int64
        Index of the object in ``map.all()`` that each shape is, -1 for none.
    height_source : ndarray of int8
        0 flat, 1 ``height`` tag, 2 levels, 3 building type.
    """

    geometry: np.ndarray
    label: np.ndarray
    height: np.ndarray
    layer: np.ndarray
    map_index: np.ndarray
    height_source: np.ndarray
    labels: tuple[str, ...]
    crs: str | None

    def __len__(self) -> int:
        return int(self.geometry.size)

    @cached_property
    def tree(self) -> shapely.STRtree:
        """Spatial index of the shapes (built on first use)."""
        return shapely.STRtree(self.geometry)


class _Shapes:
    """What the pass over the file keeps: lon/lat WKB, label names, and the tags heights need."""

    def __init__(self) -> None:
        self.wkb: list[bytes] = []
        self.label: list[str] = []
        self.is_line: list[bool] = []
        self.building_tags: dict[int, dict[str, str]] = {}


_HEIGHT_KEYS = ("height", "building:levels", "roof:levels", "building")


def _processor(source: str, area_rules: list[tuple[int, TagRule]], way_rules: list[tuple[int, TagRule]]) -> Any:
    """osmium's reader of ``source`` letting through only areas and ways that the rules may label.

    The tag filters run in C++ (the reader's own :func:`mapdb.sources.osm.scan._tag_prefilter`); nodes are
    read for their locations only, and relations only to assemble multipolygons.
    """
    processor = osmium.FileProcessor(source).with_locations("flex_mem")
    kinds = osmium.osm.NOTHING
    area_filter = _tag_prefilter([r for _, r in area_rules])
    if area_filter is not None:
        processor.with_areas(_tag_prefilter([r for _, r in area_rules]))
        processor.with_filter(area_filter.enable_for(osmium.osm.AREA))
        kinds |= osmium.osm.AREA
    way_filter = _tag_prefilter([r for _, r in way_rules])
    if way_filter is not None:
        processor.with_filter(way_filter.enable_for(osmium.osm.WAY))
        kinds |= osmium.osm.WAY
    processor.with_filter(osmium.filter.EntityFilter(kinds))
    return processor


def _scan(source: str, table: LabelTable, counts: Counter[str]) -> _Shapes:
    """One osmium pass: area outlines and way lines that the label rules label (tag filters in C++)."""
    area_rules = _rules_for(table, "area")
    way_rules = _rules_for(table, "way")
    processor = _processor(source, area_rules, way_rules)
    wkb = osmium.geom.WKBFactory()
    out = _Shapes()
    for obj in processor:
        kind = obj.type_str()
        rules: list[tuple[int, TagRule]] = area_rules if kind == "a" else way_rules if kind == "w" else []
        code = _first_match(rules, obj.tags)
        if code < 0:
            continue
        try:
            geometry = wkb.create_multipolygon(obj) if kind == "a" else wkb.create_linestring(obj)
        except (osmium.InvalidLocationError, RuntimeError):  # nodes out of range or missing, crossing rings
            counts["shapes_not_assembled"] += 1
            continue
        label = table.labels[code]
        if label == "building":
            out.building_tags[len(out.wkb)] = {k: obj.tags[k] for k in _HEIGHT_KEYS if k in obj.tags}
        out.wkb.append(bytes.fromhex(geometry))
        out.label.append(label)
        out.is_line.append(kind == "w")
    return out


def _read_shapes(path: Path, table: LabelTable, counts: Counter[str]) -> _Shapes:
    """:func:`_scan` of an OSM file, with the reader's errors as one-line :class:`SourceError`."""
    _check_readable(path)
    try:
        with _xml_input(path) if path.name.lower().endswith(_XML_SUFFIXES) else nullcontext(str(path)) as source:
            return _scan(source, table, counts)
    except (RuntimeError, UnicodeDecodeError, osmium.InvalidLocationError) as exc:
        detail = " ".join(str(exc).split()) or exc.__class__.__name__
        raise SourceError(f"{path}: not a readable OSM file ({detail})") from None


def _to_crs(geoms: np.ndarray, crs: str | None) -> np.ndarray:
    """lon/lat geometries into ``crs`` (vectorised), repaired where the projection made them invalid."""
    if crs is None:
        raise SourceError("the map has no CRS: its objects cannot be placed on an OSM extract")
    to_map = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    projected = shapely.transform(geoms, lambda xy: np.column_stack(to_map.transform(xy[:, 0], xy[:, 1])))
    bad = ~shapely.is_valid(projected)
    if bad.any():
        projected[bad] = shapely.make_valid(projected[bad], method="structure", keep_collapsed=False)
    return projected


def _link(objects: Objects, label: np.ndarray, points: np.ndarray, tolerance: np.ndarray,
          piece: np.ndarray) -> np.ndarray:
    """Index of the nearest map object of the same label within reach of each point, else -1.

    The reach is ``tolerance``, plus the object's own radius ``sqrt(area / pi)`` for a ``piece``
    of an object (a road piece): the centroid of an arc of a roundabout lies about a
    radius from the roundabout's centre.  The nearest objects are tried in order (up to 8).
    """
    found = np.full(label.size, -1, np.int64)
    for code in np.unique(label):
        mine = np.flatnonzero(label == code)
        theirs = np.flatnonzero(objects.label == code)
        if not theirs.size:
            continue
        k = min(8, theirs.size)
        dist, j = cKDTree(np.column_stack([objects.x[theirs], objects.y[theirs]])).query(points[mine], k=k)
        dist, j = dist.reshape(mine.size, k), j.reshape(mine.size, k)
        radius = np.sqrt(objects.area[theirs][j] / np.pi) * piece[mine][:, None]
        ok = dist <= tolerance[mine][:, None] + radius
        first = np.argmax(ok, axis=1)
        hit = ok[np.arange(mine.size), first]
        found[mine[hit]] = theirs[j[hit, first[hit]]]
    return found


def _intersection_discs(objects: Objects, table: LabelTable, diameter: float) -> tuple[np.ndarray, np.ndarray]:
    """Discs at the map's road intersections and their map indices (none when ``diameter`` is 0)."""
    rule = table.intersections
    if rule is None or diameter <= 0 or rule.label not in objects.labels:
        return np.zeros(0, object), np.zeros(0, np.int64)
    index = np.flatnonzero(objects.label == objects.labels.index(rule.label))
    discs = shapely.buffer(shapely.points(objects.x[index], objects.y[index]), diameter / 2.0, quad_segs=4)
    return discs, index.astype(np.int64)


def read_scene(path: str | Path, objects: Objects, *, table: LabelTable | None = None, seed: int = 0,
               intersection_diameter_m: float = INTERSECTION_DIAMETER_M,
               counts: Counter[str] | None = None) -> Scene:
    """The shapes of an OSM extract in the CRS of a map's objects, with heights, linked to the objects.

    Parameters
    ----------
    path : str or Path
        The OSM extract (``.osm.pbf``, ``.osm``, ``.osm.gz``, ``.osm.bz2``) the map was built from.
    objects : Objects
        The map's objects (``map.all()``): their CRS, labels and the indices the shapes are linked to.
        A shape is linked to the nearest object of its label within 1 m (plus 0.1 % of the shape's
        size, for big areas) of its centroid; a road piece (a roundabout is drawn in several) to the
        nearest whose centre lies within its half-extent plus the object's radius plus 2 m.  Shapes of
        labels the map lacks are left out.
    table : LabelTable, optional
        The label rules (default: :func:`mapdb.labels.default_label_table`): those the map was built with.
    seed : int
        Seed of the building-type height spread.
    intersection_diameter_m : float
        Diameter of the discs drawn at road intersections; 0 leaves them out.
    counts : Counter, optional
        Incremented with ``shapes_not_assembled`` (osmium could not build the outline),
        ``labels_not_in_map`` and ``shapes_not_in_map`` (no map object to link to).

    Raises
    ------
    SourceError
        The file is not OSM data, the map has no CRS, or no outline of the file is an object of the map.
    MapdbIOError
        The file cannot be read.
    """
    table = table or default_label_table()
    counts = counts if counts is not None else Counter()
    shapes = _read_shapes(Path(path), table, counts)
    in_map = np.array([name in objects.labels for name in shapes.label], bool)
    counts["labels_not_in_map"] += int((~in_map).sum())
    tags = [shapes.building_tags.get(i, {}) for i in range(len(shapes.wkb))]
    heights, rule = building_heights(tags, seed)
    is_building = np.array([name == "building" for name in shapes.label], bool)
    heights, rule = np.where(is_building, heights, 0.0), np.where(is_building, rule, FLAT).astype(np.int8)
    keep = np.flatnonzero(in_map)
    geoms, label, layer, map_index = _placed(shapes, keep, is_building[keep], objects)
    counts["shapes_not_in_map"] += int((map_index < 0).sum())
    if map_index.size and (map_index < 0).all():
        raise SourceError(f"{path}: none of its {map_index.size:,} outlines is an object of the map; "
                          "give the extract the map was built from")

    discs, disc_index = _intersection_discs(objects, table, intersection_diameter_m)
    n_discs = disc_index.size
    return Scene(
        geometry=np.concatenate([geoms, discs]).astype(object),
        label=np.concatenate([label, objects.label[disc_index]]).astype(np.int32),
        height=np.concatenate([heights[keep], np.zeros(n_discs)]),
        layer=np.concatenate([layer, np.full(n_discs, LAYER_MARK, np.int8)]),
        map_index=np.concatenate([map_index, disc_index]),
        height_source=np.concatenate([rule[keep], np.zeros(n_discs, np.int8)]),
        labels=objects.labels,
        crs=objects.crs,
    )


def _placed(shapes: _Shapes, keep: np.ndarray, is_building: np.ndarray, objects: Objects
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kept shapes in the map's CRS (lines widened to roads), their label codes, layers and map indices."""
    if not keep.size:
        return np.zeros(0, object), np.zeros(0, np.int32), np.zeros(0, np.int8), np.zeros(0, np.int64)
    geoms = _to_crs(shapely.from_wkb(np.asarray(shapes.wkb, dtype=object)[keep]), objects.crs)
    is_line = np.asarray(shapes.is_line, bool)[keep]
    label = np.array([objects.labels.index(shapes.label[i]) for i in keep], np.int32)
    centre = shapely.get_coordinates(shapely.centroid(geoms))
    bounds = shapely.bounds(geoms)
    size = np.hypot(bounds[:, 2] - bounds[:, 0], bounds[:, 3] - bounds[:, 1])
    tolerance = np.where(is_line, size / 2.0 + 2.0 * _LINK_TOLERANCE_M, _LINK_TOLERANCE_M + 1e-3 * size)
    map_index = _link(objects, label, centre, tolerance, is_line)
    geoms = np.where(is_line, shapely.buffer(geoms, ROAD_WIDTH_M / 2.0, quad_segs=4), geoms)
    layer = np.where(is_line, LAYER_MARK, np.where(is_building, LAYER_BUILDING, LAYER_AREA)).astype(np.int8)
    return geoms, label, layer, map_index
