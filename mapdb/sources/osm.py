"""OpenStreetMap source: labelled objects from ``.osm`` / ``.osm.pbf`` extracts.

One pass of pyosmium's :class:`osmium.FileProcessor` with its node-location
index and multipolygon assembly.  Tag filters run in C++, so only objects that
some rule of the label table may match ever reach Python:

* areas (closed ways and multipolygon relations, assembled by osmium) whose
  tags match an ``"area"`` rule become one object at the area centroid, with
  the area of the outer rings minus the inner rings;
* tagged nodes matching a ``"node"`` rule become point objects (area 0);
* ways matching a ``"way"`` rule (roundabouts drawn as rings) become one object
  per group of such ways that share nodes, at the centroid of their lines;
* road intersections are computed from the node lists of the highway ways named
  in the table's intersection rule.

Per object, Python does only the tag test and asks osmium for WKB; geometry
(areas, centroids) is computed in blocks of :data:`AREA_BLOCK` areas with shapely
and numpy as the pass goes, and the geometries are dropped: the blocks of compact
objects (position, label, area) go to spools (:func:`read_osm_spooled`: temporary
files, 28 bytes an object), the road network's node ids to temporary files past
:data:`ROAD_REFS_IN_MEMORY`, and the node location index lives in a file for inputs
from :data:`FILE_INDEX_BYTES` up (:func:`choose_node_index`).  libosmium keeps the
multipolygon relations of the first pass, with their members, until they are complete:
only those some area rule labels are given to it.  Coordinates stay in lon/lat
(``EPSG:4326``); areas are in square metres.

Broken data is skipped or repaired and counted (``read_osm(counts=...)``), never
silently moved and never a traceback: nodes whose coordinates are out of range
or not numbers, ways tagged as areas that do not close, rings that cross
themselves (rebuilt with shapely's ``make_valid``).  Compressed XML is inflated
under a bound (:func:`inflation_limit`), so a decompression bomb costs at most
that much time, memory and temporary disk before a one-line error.
"""

from __future__ import annotations

import bz2
import ctypes
import gzip
import math
import os
import re
import shutil
import tempfile
import time
import zlib
from array import array
from collections import Counter, deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import osmium
import osmium.filter
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import MapdbIOError, SourceError, reading
from ..geo import check_bbox, in_bbox
from ..labels import IntersectionRule, LabelTable, TagRule
from ..objects import Objects
from .spool import ObjectSpool, joined, release_freed_memory

__all__ = ["AREA_BLOCK", "DENSE_INDEX_BYTES", "FILE_INDEX_BYTES", "MAX_INFLATION", "MIN_INFLATED_BYTES",
           "NODE_INDEXES", "OSM_SUFFIXES", "POINT_BLOCK", "ROAD_REFS_IN_MEMORY", "TRIM_INPUT_BYTES",
           "choose_node_index", "inflation_limit", "is_osm_path", "read_osm", "read_osm_spooled"]

OSM_SUFFIXES = (".osm.pbf", ".pbf", ".osm", ".osm.bz2", ".osm.gz")
_XML_SUFFIXES = (".osm", ".osm.bz2", ".osm.gz")

# A compressed XML file may inflate to MAX_INFLATION times its size, and in any case to
# MIN_INFLATED_BYTES: real OSM XML compresses 10-30 times, so only a decompression bomb goes past.
MAX_INFLATION = 100
MIN_INFLATED_BYTES = 256 << 20
_CHUNK = 1 << 20

# libosmium's coordinate for a node it has no location for (a node missing from an extract).
_UNDEFINED = 2**31 - 1

# WGS84 ellipsoid.
_A = 6378137.0
_F = 1 / 298.257223563
_E2 = _F * (2 - _F)

# How often (seconds) a long read reports progress, and how many objects pass between clock checks.
_PROGRESS_SECONDS = 2.0
_PROGRESS_STRIDE = 4096

# Areas whose centroid and area are computed together, after which their geometries are dropped: big
# enough for shapely's vectorised calls to pay, small enough that the geometries cost a few megabytes.
AREA_BLOCK = 4096
# Labelled nodes handed on at once (1.2 MB of typed arrays).
POINT_BLOCK = 1 << 16
# Node ids of road ways kept in memory; past this many they go to a temporary file, in buckets by node
# id, and the junctions are found one bucket at a time (8 bytes a node id; 32 bytes in the buckets).
ROAD_REFS_IN_MEMORY = 1 << 19
# Buckets of road edges on disk: one per this many bytes of input (a 1 GB extract holds about 20 million
# road node ids, a bucket about a million edges), at least 2 and at most _MAX_EDGE_BUCKETS.
_INPUT_BYTES_PER_BUCKET = 16 << 20
_MAX_EDGE_BUCKETS = 1024

# Where libosmium keeps node locations (16 bytes a node in a sparse index, 8 bytes a node id in a dense
# one).  Small inputs keep them in memory; from FILE_INDEX_BYTES of input the index is a file (mapped, its
# pages released to the page cache as the pass goes, so that the process's memory stays bounded); from
# DENSE_INDEX_BYTES, a continent or the planet, whose node ids are dense, a dense file array.
FILE_INDEX_BYTES = 64 << 20
DENSE_INDEX_BYTES = 16 << 30
# From this much input the freed C heap is handed back to the system between the stages of a read (see
# mapdb.sources.spool.release_freed_memory), so that one stage's leftovers do not add to the next one's peak; below it
# the heap is small, and handing it back would only make the next stage fault the same pages in again.
TRIM_INPUT_BYTES = FILE_INDEX_BYTES
NODE_INDEXES = ("auto", "flex_mem", "sparse_mem_array", "dense_mem_array", "sparse_file_array", "dense_file_array")
# Disk a file index needs, per byte of input, as checked before the pass (a full disk would make libosmium's
# mapped file fault): sparse 16 bytes a node at up to ~0.15 nodes a PBF byte, dense 8 bytes an id.
_INDEX_BYTES_PER_INPUT_BYTE = {"sparse_file_array": 3.0, "dense_file_array": 1.0}

_MADV_DONTNEED = 4  # Linux
_ETA_WINDOW_SECONDS = 60.0

Progress = Callable[[str], None]


def choose_node_index(input_bytes: int) -> str:
    """The libosmium node location index ``node_index="auto"`` uses for an input of this many bytes.

    Examples
    --------
    >>> choose_node_index(2 << 20), choose_node_index(1 << 30), choose_node_index(70 << 30)
    ('flex_mem', 'sparse_file_array', 'dense_file_array')
    """
    if input_bytes >= DENSE_INDEX_BYTES:
        return "dense_file_array"
    return "sparse_file_array" if input_bytes >= FILE_INDEX_BYTES else "flex_mem"


def is_osm_path(path: str | Path) -> bool:
    """Whether a file name has one of the OSM suffixes in :data:`OSM_SUFFIXES`.

    Examples
    --------
    >>> is_osm_path("monaco.osm.pbf"), is_osm_path("Area.OSM"), is_osm_path("map.tif")
    (True, True, False)
    """
    return str(path).lower().endswith(OSM_SUFFIXES)


def inflation_limit(compressed_bytes: int) -> int:
    """Most bytes a compressed OSM XML file of this size may inflate to (see :data:`MAX_INFLATION`).

    Examples
    --------
    >>> inflation_limit(10 << 20) == 1000 << 20, inflation_limit(1000) == MIN_INFLATED_BYTES
    (True, True)
    """
    return max(MIN_INFLATED_BYTES, MAX_INFLATION * int(compressed_bytes))


def read_osm(path: str | Path, table: LabelTable, bbox: tuple[float, float, float, float] | None = None,
             progress: Progress | None = None, counts: Counter[str] | None = None, *, node_index: str = "auto",
             index_dir: str | Path | None = None) -> Objects:
    """Read the labelled objects of an OpenStreetMap extract.

    Parameters
    ----------
    path : str or Path
        An OSM file: ``.osm.pbf``, ``.osm`` XML, or XML compressed as ``.osm.gz`` / ``.osm.bz2``.
    table : LabelTable
        Labels and the OSM rules that produce them.  For each object only the
        rules whose ``geometry`` includes the object's kind (area, node, way) are
        tried, in table order; the first that matches gives the label.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Keep only objects whose centroid lies inside (edges included); ``minlon > maxlon``
        crosses the antimeridian.
    progress : callable, optional
        Called with a one-line message now and then during long reads.
    counts : Counter, optional
        Incremented with what was skipped or repaired instead of failing the read:
        ``"invalid_coordinates"`` (objects with a coordinate that is not a number or lies outside
        lon [-180, 180], lat [-90, 90]), ``"unclosed_rings"`` (ways tagged as areas that do not
        close), ``"repaired_geometries"`` (areas whose rings cross themselves, rebuilt with
        shapely's ``make_valid``) and ``"invalid_geometries"`` (areas that could not be repaired).
    node_index : str
        Where libosmium keeps node locations: ``"auto"`` (:func:`choose_node_index`, by the input's size),
        or one of :data:`NODE_INDEXES` (``"flex_mem"`` in memory, ``"sparse_file_array"`` and
        ``"dense_file_array"`` in a temporary file).
    index_dir : path, optional
        The directory of the temporary files of large inputs (a file node index, the road network's
        buckets); the system's temporary directory by default.

    Returns
    -------
    Objects
        ``x`` = longitude, ``y`` = latitude (``crs="EPSG:4326"``), label codes
        into ``table.labels``, ``area`` in m^2 (0 for nodes and intersections).

    Raises
    ------
    MapdbIOError
        The file is missing or cannot be opened.
    SourceError
        The file is empty, truncated, not OSM data, or a compressed file that inflates past
        :func:`inflation_limit`; or ``node_index`` is not one of :data:`NODE_INDEXES`.
    MapdbIOError
        ``index_dir`` cannot hold the temporary files (missing, not writable, too little free space).

    Notes
    -----
    Compressed XML is inflated chunk by chunk, refused past :func:`inflation_limit`; a node whose coordinate
    libosmium cannot parse (``nan``, ``1e400``, text) is skipped and counted, not fatal (see ``_xml_input``).

    Examples
    --------
    >>> from mapdb.labels import default_label_table
    >>> objects = read_osm("monaco.osm.pbf", default_label_table())  # doctest: +SKIP
    >>> objects.counts()["building"]  # doctest: +SKIP
    1205
    """
    return joined(read_osm_spooled(path, table, bbox, progress, counts, node_index=node_index, index_dir=index_dir),
                  table.labels, "EPSG:4326")


def read_osm_spooled(path: str | Path, table: LabelTable, bbox: tuple[float, float, float, float] | None = None,
                     progress: Progress | None = None, counts: Counter[str] | None = None, *,
                     node_index: str = "auto", index_dir: str | Path | None = None,
                     spool_dir: str | Path | None = None) -> list[ObjectSpool]:
    """:func:`read_osm`'s objects, in order, as spools of blocks that are written to ``spool_dir`` as the pass
    goes (kept in memory when it is None), so that a country's objects are never all in memory.

    The spools are the points, the areas, then the ways and intersections; their files (``osm-*`` in
    ``spool_dir``) are the caller's to remove (:meth:`mapdb.sources.spool.ObjectSpool.discard`, or with the directory).
    Parameters, errors and the objects read are those of :func:`read_osm`.
    """
    path = Path(path)
    if node_index not in NODE_INDEXES:
        raise SourceError(f"node index {node_index!r}: not one of {', '.join(NODE_INDEXES)}")
    _check_readable(path)
    bbox = None if bbox is None else check_bbox(bbox)
    counts = counts if counts is not None else Counter()
    spools = [ObjectSpool(table.labels, "EPSG:4326", spool_dir, f"osm-{kind}-")
              for kind in ("points", "areas", "others")]
    try:
        with _Workspace(index_dir) as workspace:
            _read(path, table, bbox, progress or (lambda message: None), counts, workspace, node_index, spools)
    except BaseException:
        for spool in spools:
            spool.discard()
        raise
    return spools


def _read(path: Path, table: LabelTable, bbox: tuple[float, float, float, float] | None, report: Progress,
          counts: Counter[str], workspace: _Workspace, node_index: str, spools: list[ObjectSpool]) -> None:
    """:func:`read_osm` on checked arguments: collect and assemble into ``spools``, and say what came of it."""
    started = time.monotonic()
    report(f"{path}: reading OpenStreetMap data")
    collected = _collect(path, table, report, counts, workspace, node_index, _Sink(spools, bbox, len(table.labels)))
    report(f"{path}: file read in {time.monotonic() - started:.1f} s; joining roundabouts, finding intersections")
    _assemble(collected, table, counts)
    found = collected.sink.found
    summary = ", ".join(f"{n:,} {name}" for name, n in zip(table.labels, found.tolist(), strict=True) if n) or "nothing"
    report(f"{path}: {int(found.sum()):,} objects in {time.monotonic() - started:.1f} s ({summary})")
    skipped = ", ".join(f"{n:,} {kind.replace('_', ' ')}" for kind, n in sorted(counts.items()) if n)
    if skipped:
        report(f"{path}: skipped or repaired: {skipped}")


def _collect(path: Path, table: LabelTable, report: Progress, counts: Counter[str], workspace: _Workspace,
             node_index: str, sink: _Sink) -> _Collected:
    """The single pass over the file (and the repair of areas osmium could not assemble)."""
    try:
        with _xml_input(path) if path.name.lower().endswith(_XML_SUFFIXES) else nullcontext(str(path)) as source:
            size = os.path.getsize(source)
            collected = _Collected(table.labels, workspace, counts, size, sink)
            collected.locations, collected.index_file = workspace.node_index(node_index, size, path)
            _scan(path, source, table, report, collected)
            if collected.failed_area_ways:
                _repair_ways(source, collected, counts)
            collected.finish_areas()
            collected.finish_points()
    except (RuntimeError, UnicodeDecodeError, osmium.InvalidLocationError) as exc:
        # libosmium reports bad input (XML syntax, PBF framing, unknown format) as RuntimeError.
        detail = " ".join(str(exc).split()) or exc.__class__.__name__
        raise SourceError(f"{path}: not a readable OSM file ({detail})") from None
    return collected


def _assemble(collected: _Collected, table: LabelTable, counts: Counter[str]) -> None:
    """The objects left after the pass, into the last spool: ways and (when the table asks) intersections."""
    trim = release_freed_memory if collected.input_bytes >= TRIM_INPUT_BYTES else lambda: None
    trim()
    collected.sink.add(2, _way_objects(collected, table.labels))
    trim()
    if table.intersections is not None:
        collected.sink.add(2, _intersection_objects(collected, table.intersections, table.labels, counts))


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


# --------------------------------------------------------------------------------------------------
# Reading


def _check_readable(path: Path) -> None:
    """Fail early with a clear message: osmium's own errors for these cases are less helpful."""
    with reading(path, "file"), path.open("rb") as f:
        first = f.read(1)
    if not first:
        raise SourceError(f"{path}: not a readable OSM file (empty file)")
    if not is_osm_path(path):
        raise SourceError(f"{path}: not a readable OSM file (name must end in {', '.join(OSM_SUFFIXES)})")


# Coordinates written plainly enough for libosmium, up to 180 degrees (it rejects signs, spaces, hex and
# some big numbers, and reads "1e400" as 0).  Any other value goes through _fix_coordinate.
_PLAIN = rb"-?(?:[0-9]{1,2}|1[0-7][0-9]|180)(?:\.[0-9]*)?"
# (A pattern that starts with a literal runs several times faster in ``re`` than one that starts with \s.)
_ODD_COORDINATE = re.compile(rb"(?:lat|lon)\s*=\s*([\"'])(?!" + _PLAIN + rb"\1)([^\"'<&]*)\1")
# Out of range but within what libosmium parses: the node gets a defined, invalid location.
_OUT_OF_RANGE = b"200"


def _fix_coordinate(match: re.Match[bytes]) -> bytes:
    start = match.start()
    if start == 0 or match.string[start - 1:start] not in b" \t\r\n":  # "minlat=", not an attribute "lat"
        return match.group(0)
    try:
        value = float(match.group(2))
    except ValueError:
        value = float("nan")
    text = f"{value:.7f}".encode() if abs(value) <= 180.0 else _OUT_OF_RANGE  # NaN compares False
    quote = match.group(1)
    return match.group(0)[:match.start(1) - start] + quote + text + quote


@contextmanager
def _xml_input(path: Path) -> Iterator[str]:
    """The name of an XML file libosmium can read in full: ``path`` itself, or a bounded, fixed copy.

    A compressed file is inflated into a temporary file, chunk by chunk, and refused (one-line
    :class:`SourceError`) once it passes :func:`inflation_limit`: memory holds one chunk and disk
    at most the limit.  libosmium reads the copy twice (relations first).  Coordinates libosmium cannot
    parse (``nan``, ``inf``, ``1e400``, text) are made out of range on the way, so that such a node is skipped
    and counted like a node at latitude 95 instead of failing the whole file (and libosmium would read
    ``1e400`` as 0); a plain file is copied only when it has such a coordinate.
    """
    name = path.name.lower()
    opener: Callable[..., Any] = gzip.open if name.endswith(".gz") else bz2.open if name.endswith(".bz2") else open
    if opener is open and not _has_odd_coordinate(path):
        yield str(path)
        return
    limit = inflation_limit(path.stat().st_size) if opener is not open else None
    with tempfile.TemporaryDirectory(prefix="mapdb-osm-") as tmp:
        copy = os.path.join(tmp, "input.osm")
        total = 0
        carry = b""
        try:
            with opener(path, "rb") as f, open(copy, "wb") as out:
                while chunk := f.read(_CHUNK):
                    total += len(chunk)
                    if limit is not None and total > limit:
                        raise SourceError(
                            f"{path}: inflates to more than {limit:,} bytes ({MAX_INFLATION} times its size, "
                            f"at least {MIN_INFLATED_BYTES >> 20} MiB): refused as a decompression bomb")
                    data = carry + chunk
                    # An attribute value never holds "<": cut there, so no coordinate is split in two.
                    cut = data.rfind(b"<")
                    if cut <= 0 or len(data) - cut > _CHUNK:
                        cut = len(data)
                    carry = data[cut:]
                    out.write(_ODD_COORDINATE.sub(_fix_coordinate, data[:cut]))
                out.write(_ODD_COORDINATE.sub(_fix_coordinate, carry))
        except (EOFError, zlib.error, gzip.BadGzipFile) as exc:  # a corrupt .gz / .bz2 file
            detail = " ".join(str(exc).split()) or exc.__class__.__name__
            raise SourceError(f"{path}: not a readable OSM file ({detail})") from None
        except OSError as exc:
            if exc.filename == copy:
                raise MapdbIOError(f"{path}: cannot write its inflated copy in {tmp} ({exc.strerror or exc})") from None
            detail = " ".join(str(exc).split()) or exc.__class__.__name__  # bz2 reports bad data as OSError
            raise SourceError(f"{path}: not a readable OSM file ({detail})") from None
        yield copy


def _has_odd_coordinate(path: Path) -> bool:
    """Whether a plain XML file holds a coordinate :func:`_fix_coordinate` would change."""
    carry = b""
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            data = carry + chunk
            if _ODD_COORDINATE.search(data):
                return True
            carry = data[-256:]  # an attribute split between two chunks is seen whole in the next
    return False


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
        # Ways matched by a "way" rule: node ids and locations of all of them, one after the other, and the
        # number of nodes and label code of each (typed arrays: no long-lived Python numbers, which would
        # pin the allocator's arenas between the blocks of areas).
        self.way_refs = array("q")
        self.way_lon = array("d")
        self.way_lat = array("d")
        self.way_lengths = array("q")
        self.way_code = array("i")
        self.roads = _RoadNetwork(workspace, input_bytes)
        self.locations: Any = None  # osmium's node location table, for looking up junction nodes
        self.index_file: str | None = None  # its file, when it has one
        # Closed ways whose area osmium could not assemble (rings crossing themselves), with their
        # label code: rebuilt by _repair_ways.
        self.failed_area_ways: dict[int, int] = {}

    def add_area(self, wkb: str, code: int) -> None:
        self.area_wkb.append(wkb)
        self.area_code.append(code)
        if len(self.area_wkb) >= AREA_BLOCK:
            self.finish_areas()

    def finish_areas(self) -> None:
        """Centroids and areas of the current block of areas, to the sink; the geometries are dropped."""
        if self.area_wkb:
            self.sink.add(1, _area_objects(self.area_wkb, self.area_code, self.labels, self.counts))
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


def _scan(path: Path, source: str, table: LabelTable, report: Progress, out: _Collected) -> None:
    """One pass over ``source``: the labelled nodes, areas and ways, and the road ways' nodes."""
    area_rules = _rules_for(table, "area")
    node_rules = _rules_for(table, "node")
    way_rules = _rules_for(table, "way")
    roads = frozenset(table.intersections.highways) if table.intersections is not None else frozenset()
    processor = _processor(source, out.locations, area_rules, node_rules, way_rules, roads)
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
            _take_way(obj, way_rules, area_rules, roads, wkb, out, counts)
    meter.release()


def _processor(source: str, locations: Any, area_rules: list[tuple[int, TagRule]],
               node_rules: list[tuple[int, TagRule]], way_rules: list[tuple[int, TagRule]],
               roads: frozenset[str]) -> Any:
    """osmium's reader of ``source``, letting through (a superset of) the objects the rules may use."""
    area_filter = _tag_prefilter([r for _, r in area_rules])
    node_filter = _tag_prefilter([r for _, r in node_rules])
    # Ways tagged as areas come through too: osmium silently drops those that do not close or have a
    # node out of range, and they must be counted.
    way_filter = _tag_prefilter([r for _, r in way_rules + area_rules], [("highway", h) for h in sorted(roads)])

    processor = osmium.FileProcessor(source).with_locations(locations)
    kinds = osmium.osm.NOTHING
    if area_filter is not None:
        # The same filter picks the multipolygon relations worth assembling in the first pass, and then the
        # rules themselves: libosmium keeps every relation it is given, with its members, until it is
        # complete, and a relation no rule labels (a peninsula or a mountain range of thousands of members,
        # most of them outside the extract) never gives an object.
        processor.with_areas(_tag_prefilter([r for _, r in area_rules]), _LabelledRelations(area_rules))
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
    """A first-pass filter for osmium's area assembly: drops the relations no area rule labels."""

    def __init__(self, area_rules: list[tuple[int, TagRule]]) -> None:
        self.area_rules = area_rules

    def relation(self, relation: Any) -> bool:
        return _first_match(self.area_rules, relation.tags) < 0  # True: filtered out


def _take_area(obj: Any, area_rules: list[tuple[int, TagRule]], wkb: Any, out: _Collected,
               counts: Counter[str]) -> None:
    """Keep an assembled area that an area rule labels (or note why it cannot be kept)."""
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


def _defined(location: Any) -> bool:
    """Whether a node has coordinates at all (a node missing from an extract has none)."""
    return location.x != _UNDEFINED or location.y != _UNDEFINED


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
        out.way_refs.extend(n.ref for n in nodes)
        out.way_lon.extend(n.lon for n in nodes)
        out.way_lat.extend(n.lat for n in nodes)
        out.way_lengths.append(len(nodes))
        out.way_code.append(code)


def _check_area_way(way: Any, tags: Any, area_rules: list[tuple[int, TagRule]], wkb: Any,
                    counts: Counter[str]) -> None:
    """Count a way tagged as an area that osmium will not make one of: unclosed, or a node out of range.

    The cheap tests come first: most ways here are closed and sound, and the tag rules are tried
    only for the few that are not.
    """
    if way.is_closed():
        try:
            wkb.create_linestring(way)  # one C++ pass over the node locations; the result is not needed
            return
        except osmium.InvalidLocationError:
            kind = "invalid_coordinates" if _has_bad_node(way) else None  # else: nodes missing from an extract
        except RuntimeError:  # fewer than two distinct nodes: osmium will not assemble it either
            kind = "invalid_geometries"
    else:
        kind = "unclosed_rings"
    if kind is not None and _first_match(area_rules, tags) >= 0:
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


# --------------------------------------------------------------------------------------------------
# Temporary files of large inputs: the node location index, the road network's buckets


class _Workspace:
    """A temporary directory under ``index_dir``, made when first needed and removed at the end."""

    def __init__(self, index_dir: str | Path | None) -> None:
        self.parent = Path(index_dir) if index_dir is not None else Path(tempfile.gettempdir())
        self._tmp: tempfile.TemporaryDirectory[str] | None = None

    def __enter__(self) -> _Workspace:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()

    def file(self, name: str, need_bytes: int = 0, what: str = "temporary files") -> str:
        """A path for a new temporary file, after checking that ``need_bytes`` fit in the directory."""
        try:
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix="mapdb-osm-", dir=self.parent)
            free = shutil.disk_usage(self._tmp.name).free
        except OSError as exc:
            raise MapdbIOError(f"{self.parent}: cannot hold the {what} ({exc.strerror or exc})") from None
        if need_bytes > free:
            raise MapdbIOError(f"{self.parent}: {free / 2**30:.1f} GiB free, the {what} need about "
                               f"{need_bytes / 2**30:.1f} GiB; free some space or choose another directory")
        return os.path.join(self._tmp.name, name)

    def node_index(self, kind: str, input_bytes: int, path: Path) -> tuple[Any, str | None]:
        """libosmium's node location index for an input of ``input_bytes`` (``kind`` "auto": by its size),
        and its file (None in memory)."""
        kind = choose_node_index(input_bytes) if kind == "auto" else kind
        if kind not in _INDEX_BYTES_PER_INPUT_BYTE:
            return osmium.index.create_map(kind), None
        need = int(_INDEX_BYTES_PER_INPUT_BYTE[kind] * input_bytes)
        location = self.file("node-locations", need, f"node location index of {path.name} ({kind})")
        try:
            return osmium.index.create_map(f"{kind},{location}"), location
        except (RuntimeError, OSError) as exc:
            raise MapdbIOError(f"{self.parent}: cannot hold the node location index ({exc})") from None


class _RoadNetwork:
    """The node ids of the road ways, for finding junctions: in memory, or in buckets by node id on disk.

    Up to :data:`ROAD_REFS_IN_MEMORY` ids are kept in memory (typed arrays, 8 bytes an id) and the
    junctions found by :func:`_junction_node_ids`.  Past that, each full buffer is turned into directed
    edges ``(node, neighbour)`` that are appended to temporary bucket files by ``node % buckets``, and
    the junctions are found one bucket at a time: memory holds one bucket, not the network.
    """

    def __init__(self, workspace: _Workspace, input_bytes: int) -> None:
        self.workspace = workspace
        self.bucket_count = min(_MAX_EDGE_BUCKETS, max(2, input_bytes // _INPUT_BYTES_PER_BUCKET))
        self.in_memory = ROAD_REFS_IN_MEMORY
        self.refs = array("q")
        self.lengths = array("q")
        self.buckets: list[str] = []

    def add(self, refs: list[int]) -> None:
        if len(refs) < 2:
            return
        self.refs.extend(refs)
        self.lengths.append(len(refs))
        if len(self.refs) >= self.in_memory:
            self._spill()

    def _spill(self) -> None:
        if not self.buckets:
            self.buckets = [self.workspace.file(f"road-edges-{i}", what="road network")
                            for i in range(self.bucket_count)]
        src, dst = _directed_edges(np.frombuffer(self.refs, np.int64), np.frombuffer(self.lengths, np.int64))
        bucket = (src % len(self.buckets)).astype(np.uint16)
        order = np.argsort(bucket, kind="stable")  # a radix sort on 16 bits
        bounds = np.searchsorted(bucket[order], np.arange(len(self.buckets) + 1))
        pairs = np.empty((src.size, 2), np.int64)
        pairs[:, 0], pairs[:, 1] = src[order], dst[order]
        del src, dst, order
        for i, name in enumerate(self.buckets):
            with open(name, "ab") as f:
                pairs[bounds[i]:bounds[i + 1]].tofile(f)
        self.refs, self.lengths = array("q"), array("q")

    def junctions(self) -> np.ndarray:
        """Sorted ids of the nodes with three or more arms (as :func:`_junction_node_ids`)."""
        if not self.buckets:
            return _junction_node_ids(np.frombuffer(self.refs, np.int64), np.frombuffer(self.lengths, np.int64))
        if len(self.refs):
            self._spill()
        found = []
        for name in self.buckets:
            pairs = np.fromfile(name, np.int64).reshape(-1, 2)
            os.unlink(name)
            found.append(_nodes_with_three_arms(pairs[:, 0], pairs[:, 1]))
        return np.sort(np.concatenate(found))


class _ByteProgress:
    """Progress of the pass by bytes of input read, with the time left; releases a file index's pages.

    The bytes read are the position of libosmium's descriptor of the input (``/proc/self/fdinfo``, Linux);
    elsewhere only the objects are counted.  A file node index is a shared mapping: its pages stay in the
    page cache, which the kernel reclaims under pressure, and are released from the process (``madvise``)
    at each report so that its resident memory does not grow with the input.
    """

    def __init__(self, path: Path, source: str, report: Progress, index_file: str | None) -> None:
        self.path, self.report = path, report
        self.size = max(1, os.path.getsize(source))
        self.identity = _file_identity(source)
        self.last = time.monotonic()
        self.index_file = index_file
        # (time, bytes read) of the last minute or so: the rate of the recent past gives the time left,
        # since nodes (most of a PBF's bytes) go much faster than ways and areas.
        self.history: deque[tuple[float, int]] = deque()

    def tick(self, seen: int) -> None:
        now = time.monotonic()
        if now - self.last < _PROGRESS_SECONDS:
            return
        self.last = now
        self.release()
        done = _bytes_read(self.identity)
        if done is None:
            self.report(f"{self.path}: {seen:,} tagged objects read")
            return
        self.history.append((now, done))
        while len(self.history) > 2 and now - self.history[1][0] >= _ETA_WINDOW_SECONDS:
            self.history.popleft()
        then, before = self.history[0]
        rate = (done - before) / (now - then) if now > then else 0.0
        left = (self.size - done) / rate if rate > 0 else float("nan")
        self.report(f"{self.path}: {min(1.0, done / self.size):.0%} of {self.size / 2**20:,.1f} MiB read, "
                    f"{seen:,} tagged objects, about {_duration(left)} left")

    def release(self) -> None:
        if self.index_file is not None:
            _release_mapped(self.index_file)


def _duration(seconds: float) -> str:
    """``"2 h 05 min"``, ``"3 min 20 s"``, ``"40 s"``; ``"?"`` when not known.

    Examples
    --------
    >>> _duration(40.2), _duration(200), _duration(7500), _duration(float("nan"))
    ('40 s', '3 min 20 s', '2 h 05 min', '?')
    """
    if not math.isfinite(seconds):
        return "?"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def _file_identity(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _bytes_read(identity: tuple[int, int] | None) -> int | None:
    """How far this process has read the file of this (device, inode), or None if that cannot be told."""
    if identity is None:
        return None
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return None
    positions = []
    for fd in fds:
        try:
            st = os.stat(f"/proc/self/fd/{fd}")
            if (st.st_dev, st.st_ino) != identity:
                continue
            with open(f"/proc/self/fdinfo/{fd}") as f:
                positions += [int(line.split()[1]) for line in f if line.startswith("pos:")]
        except (OSError, ValueError, IndexError):
            continue
    return max(positions) if positions else None


def _release_mapped(path: str) -> None:
    """Drop this process's resident pages of a shared file mapping (they stay in the page cache); Linux only."""
    try:
        with open("/proc/self/maps") as f:
            ranges = [line.split()[0] for line in f if line.rstrip().endswith(path)]
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return
    for span in ranges:
        start, end = (int(v, 16) for v in span.split("-"))
        libc.madvise(ctypes.c_void_p(start), ctypes.c_size_t(end - start), _MADV_DONTNEED)


# --------------------------------------------------------------------------------------------------
# Geometry: local equal-area coordinates
#
# x = N(lat0) * cos(lat) * (lon - lon0), y = M(lat0) * (lat - lat0), in radians, with the meridional
# (M) and prime-vertical (N) radii of curvature of the ellipsoid frozen at the object's reference
# latitude lat0.  The Jacobian is M(lat0) N(lat0) cos(lat): the ellipsoid's own area element with
# M and N taken constant, so areas are exact up to the change of M and N across one object (below
# 1e-3 relative for objects under 100 km).  Centroids computed in these coordinates are area
# centroids and map back exactly.


def _radii(lat0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s2 = np.sin(np.radians(lat0)) ** 2
    w = np.sqrt(1 - _E2 * s2)
    return _A * (1 - _E2) / w**3, _A / w


def _to_local(lon: np.ndarray, lat: np.ndarray, lon0: np.ndarray, lat0: np.ndarray) -> np.ndarray:
    m, n = _radii(lat0)
    x = n * np.cos(np.radians(lat)) * np.radians(lon - lon0)
    y = m * np.radians(lat - lat0)
    return np.column_stack([x, y])


def _from_local(
    x: np.ndarray, y: np.ndarray, lon0: np.ndarray, lat0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    m, n = _radii(lat0)
    lat = lat0 + np.degrees(y / m)
    lon = lon0 + np.degrees(x / (n * np.cos(np.radians(lat))))
    return lon, lat


def _point_objects(lon: array, lat: array, code: array, labels: tuple[str, ...]) -> Objects:
    return Objects(np.frombuffer(lon, float), np.frombuffer(lat, float), np.frombuffer(code, np.int32),
                   np.zeros(len(code)), labels, "EPSG:4326")


def _area_objects(wkbs: list[str], codes: list[int], labels: tuple[str, ...], counts: Counter[str]) -> Objects:
    """Centroid and m^2 area of osmium's multipolygons, all in a few vectorised shapely calls.

    A multipolygon that is not valid in the local equal-area coordinates (osmium checks the rings
    it assembles, so this is rare) is repaired with ``make_valid`` and counted, or dropped and counted
    when nothing of it has an area.
    """
    if not wkbs:
        return Objects.empty(labels, "EPSG:4326")
    codes_ = np.asarray(codes, np.int32)
    geoms = shapely.from_wkb(np.asarray(wkbs, dtype=object))
    bounds = shapely.bounds(geoms)
    lon0 = (bounds[:, 0] + bounds[:, 2]) / 2
    lat0 = (bounds[:, 1] + bounds[:, 3]) / 2
    coords, owner = shapely.get_coordinates(geoms, return_index=True)
    local = shapely.set_coordinates(geoms, _to_local(coords[:, 0], coords[:, 1], lon0[owner], lat0[owner]))
    invalid = ~shapely.is_valid(local)
    if invalid.any():
        local[invalid] = shapely.make_valid(local[invalid], method="structure", keep_collapsed=False)
    area = shapely.area(local)
    centroid = shapely.get_coordinates(shapely.centroid(local))
    lon, lat = _from_local(centroid[:, 0], centroid[:, 1], lon0, lat0)
    keep = np.isfinite(lon) & np.isfinite(lat) & (~invalid | (area > 0))
    counts["repaired_geometries"] += int((invalid & keep).sum())
    counts["invalid_geometries"] += int((invalid & ~keep).sum())
    return Objects(lon[keep], lat[keep], codes_[keep], area[keep], labels, "EPSG:4326")


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected-component id of each of ``n`` vertices joined by edges ``a[i]--b[i]``."""
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _way_objects(c: _Collected, labels: tuple[str, ...]) -> Objects:
    """One object per group of same-label ways sharing nodes (the pieces of one roundabout).

    Centroid: length-weighted centroid of the group's lines.  Area: the convex hull of the
    group's nodes, which for a roundabout ring is the ground it encloses (0 for a straight line).
    """
    if not len(c.way_code):
        return Objects.empty(labels, "EPSG:4326")
    lengths = np.frombuffer(c.way_lengths, np.int64)
    way_of_node = np.repeat(np.arange(lengths.size), lengths)
    refs = np.frombuffer(c.way_refs, np.int64)
    lon = np.frombuffer(c.way_lon, float)
    lat = np.frombuffer(c.way_lat, float)
    codes = np.frombuffer(c.way_code, np.int32)

    # Ways join when they share a node and a label: components of the way--node bipartite graph,
    # nodes keyed by (id, label) so that differently labelled ways never merge.
    node_index = _pair_index(refs, codes[way_of_node])
    n_ways = lengths.size
    group_of_way = _components(n_ways + int(node_index.max()) + 1, way_of_node, n_ways + node_index)[:n_ways]
    _, group_of_way = np.unique(group_of_way, return_inverse=True)
    n_groups = int(group_of_way.max()) + 1
    group = group_of_way[way_of_node]

    count = np.bincount(group, minlength=n_groups)
    lon0 = np.bincount(group, lon, n_groups) / count
    lat0 = np.bincount(group, lat, n_groups) / count
    xy = _to_local(lon, lat, lon0[group], lat0[group])

    # Segments inside each way (not across the boundary between two consecutive ways).
    same_way = way_of_node[1:] == way_of_node[:-1]
    seg_len = np.hypot(*(xy[1:] - xy[:-1]).T) * same_way
    seg_mid = (xy[1:] + xy[:-1]) / 2
    seg_group = group[1:]
    total = np.bincount(seg_group, seg_len, n_groups)
    mean_x = np.bincount(group, xy[:, 0], n_groups) / count
    mean_y = np.bincount(group, xy[:, 1], n_groups) / count
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = np.where(total > 0, np.bincount(seg_group, seg_len * seg_mid[:, 0], n_groups) / total, mean_x)
        cy = np.where(total > 0, np.bincount(seg_group, seg_len * seg_mid[:, 1], n_groups) / total, mean_y)
    out_lon, out_lat = _from_local(cx, cy, lon0, lat0)

    area = _hull_areas(xy, group, n_groups)
    group_code = np.zeros(n_groups, np.int32)
    group_code[group_of_way] = codes
    return Objects(out_lon, out_lat, group_code, area, labels, "EPSG:4326")


def _pair_index(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The index of each pair (a[i], b[i]) among the distinct pairs in sorted order (``np.unique`` of the
    rows' inverse, without its copies of the rows).

    Examples
    --------
    >>> _pair_index(np.array([5, 3, 5, 5]), np.array([1, 2, 1, 0])).tolist()
    [2, 0, 2, 1]
    """
    order = np.lexsort((b, a))
    a_sorted, b_sorted = a[order], b[order]
    new = np.ones(order.size, bool)
    new[1:] = (a_sorted[1:] != a_sorted[:-1]) | (b_sorted[1:] != b_sorted[:-1])
    del a_sorted, b_sorted
    index = np.empty(order.size, np.int64)
    index[order] = np.cumsum(new) - 1
    return index


# Points whose convex hulls GEOS builds at once (its geometries take some 200 bytes a point).
_HULL_POINTS = 1 << 16


def _hull_areas(xy: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """The area of the convex hull of each group's points, groups taken a slice at a time so that GEOS holds a
    bounded number of points."""
    order = np.argsort(group, kind="stable")
    ends = np.cumsum(np.bincount(group, minlength=n_groups))
    area = np.empty(n_groups)
    first = 0
    while first < n_groups:
        start = ends[first - 1] if first else 0
        # Whole groups up to about _HULL_POINTS points (at least one group).
        last = max(first + 1, int(np.searchsorted(ends, start + _HULL_POINTS, side="right")))
        take = order[start:ends[last - 1]]
        points = shapely.multipoints(xy[take], indices=group[take] - first)
        area[first:last] = shapely.area(shapely.convex_hull(points))
        first = last
    return area


# --------------------------------------------------------------------------------------------------
# Road intersections


def _ecef(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Earth-centred metric coordinates on the ellipsoid: straight-line distances are true metres."""
    lam, phi = np.radians(lon), np.radians(lat)
    n = _A / np.sqrt(1 - _E2 * np.sin(phi) ** 2)
    return np.column_stack([n * np.cos(phi) * np.cos(lam), n * np.cos(phi) * np.sin(lam),
                            n * (1 - _E2) * np.sin(phi)])


def _ecef_to_lonlat(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.hypot(xyz[:, 0], xyz[:, 1])
    # Exact on the ellipsoid's surface; means of points metres apart lie millimetres below it.
    return np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])), np.degrees(np.arctan2(xyz[:, 2], (1 - _E2) * p))


def _junction_node_ids(refs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Ids of nodes with three or more arms in the network of the given ways.

    Parameters
    ----------
    refs : array of int
        Node ids of all ways, concatenated.
    lengths : array of int
        Number of nodes of each way (each at least 2).

    Returns
    -------
    ndarray of int64
        Sorted ids of the nodes with edges to three or more distinct neighbour nodes.

    Notes
    -----
    "Arms" are counted as distinct neighbouring nodes over all ways.  A node where one road simply
    continues in its next way has two arms, whatever the names of the two ways (an unnamed road
    split at a bridge, a road whose name changes): it is not an intersection.  Two or more distinct
    roads meeting (a T has three arms, a crossing four) always give three or more.  This makes the
    "distinct roads" test independent of ``name``/``ref`` tagging, which is often missing.

    Examples
    --------
    A T junction: a road 1-2-3 split into two ways at node 2 and a side road 2-4.

    >>> _junction_node_ids(np.array([1, 2, 2, 3, 2, 4]), np.array([2, 2, 2])).tolist()
    [2]
    """
    refs = np.asarray(refs, np.int64)
    lengths = np.asarray(lengths, np.int64)
    if refs.size < 2:
        return np.zeros(0, np.int64)
    ids, index = np.unique(refs, return_inverse=True)
    index = index.reshape(-1)
    way = np.repeat(np.arange(lengths.size), lengths)
    inside = (way[1:] == way[:-1]) & (index[1:] != index[:-1])
    a, b = index[:-1][inside], index[1:][inside]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    edges = _sorted_unique(lo * ids.size + hi)
    arms = np.bincount(edges // ids.size, minlength=ids.size) + np.bincount(edges % ids.size, minlength=ids.size)
    return ids[arms >= 3]


def _sorted_unique(values: np.ndarray) -> np.ndarray:
    """``np.unique(values)`` by a sort (numpy 2.3's hashing ``unique`` takes seconds on millions of ids).

    Examples
    --------
    >>> _sorted_unique(np.array([3, 1, 3, 2])).tolist()
    [1, 2, 3]
    """
    values = np.sort(values)
    keep = np.ones(values.size, bool)
    keep[1:] = values[1:] != values[:-1]
    return values[keep]


def _directed_edges(refs: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both directions of every step between two different consecutive nodes of a way: (node, neighbour).

    Examples
    --------
    >>> [e.tolist() for e in _directed_edges(np.array([1, 2, 2, 3, 2, 4]), np.array([2, 2, 2]))]
    [[1, 2, 2, 2, 3, 4], [2, 3, 4, 1, 2, 2]]
    """
    way = np.repeat(np.arange(lengths.size), lengths)
    inside = (way[1:] == way[:-1]) & (refs[1:] != refs[:-1])
    a, b = refs[:-1][inside], refs[1:][inside]
    return np.concatenate([a, b]), np.concatenate([b, a])


def _nodes_with_three_arms(node: np.ndarray, neighbour: np.ndarray) -> np.ndarray:
    """Sorted ids of the nodes with three or more distinct neighbours among directed edges.

    The arms of :func:`_junction_node_ids`, counted from the edges of the nodes of one bucket.

    Examples
    --------
    >>> _nodes_with_three_arms(*_directed_edges(np.array([1, 2, 2, 3, 2, 4]), np.array([2, 2, 2]))).tolist()
    [2]
    """
    if node.size == 0:
        return np.zeros(0, np.int64)
    nodes, node_index = np.unique(node, return_inverse=True)
    others, other_index = np.unique(neighbour, return_inverse=True)
    edges = _sorted_unique(node_index.reshape(-1) * others.size + other_index.reshape(-1))
    arms = np.bincount(edges // others.size, minlength=nodes.size)
    return nodes[arms >= 3]


def _junction_locations(c: _Collected, junctions: np.ndarray, counts: Counter[str]) -> tuple[np.ndarray, np.ndarray]:
    """Lon/lat of the junction nodes the index holds (a file index's pages released as the lookups go)."""
    lon, lat = array("d"), array("d")
    for i, node_id in enumerate(junctions.tolist()):
        if c.index_file is not None and i % _PROGRESS_STRIDE == 0:
            _release_mapped(c.index_file)
        try:
            location = c.locations.get(node_id)
        except KeyError:  # a node outside the extract: no location, no object
            continue
        if not location.valid():
            counts["invalid_coordinates"] += int(_defined(location))
            continue
        lon.append(location.lon)
        lat.append(location.lat)
    if c.index_file is not None:
        _release_mapped(c.index_file)
    return np.frombuffer(lon, float), np.frombuffer(lat, float)


def _intersection_objects(c: _Collected, rule: IntersectionRule, labels: tuple[str, ...],
                          counts: Counter[str]) -> Objects:
    """Junction nodes of the road network, those of one crossing within ``merge_distance_m`` merged."""
    junctions = c.roads.junctions()
    if len(c.way_refs):
        # A junction on a way that is an object of its own (a roundabout ring) is part of that
        # object: the camera sees one roundabout, not one intersection per entry.
        junctions = junctions[~np.isin(junctions, np.frombuffer(c.way_refs, np.int64))]
    lon, lat = _junction_locations(c, junctions, counts)
    if not lon.size:
        return Objects.empty(labels, "EPSG:4326")
    xyz = _ecef(lon, lat)
    pairs = cKDTree(xyz).query_pairs(rule.merge_distance_m, output_type="ndarray")
    cluster = _components(len(xyz), pairs[:, 0], pairs[:, 1])
    n = int(cluster.max()) + 1
    size = np.bincount(cluster, minlength=n)
    mean = np.column_stack([np.bincount(cluster, xyz[:, k], n) / size for k in range(3)])
    out_lon, out_lat = _ecef_to_lonlat(mean)
    code = np.full(n, labels.index(rule.label), np.int32)
    return Objects(out_lon, out_lat, code, np.zeros(n), labels, "EPSG:4326")
