"""The OpenStreetMap reader: :func:`read_osm` and its spooled form, the pass and what follows it."""

from __future__ import annotations

import os
import time
from collections import Counter
from contextlib import nullcontext
from pathlib import Path

import osmium

from ...errors import SourceError
from ...geo import check_bbox
from ...labels import LabelTable
from ...objects import Objects
from ..spool import ObjectSpool, joined, release_freed_memory
from .areas import _way_objects
from .files import _XML_SUFFIXES, _check_readable, _xml_input
from .index import FILE_INDEX_BYTES, NODE_INDEXES, _Workspace
from .intersections import _intersection_objects
from .progress import Progress
from .scan import PARTS, OutlineSink, _Collected, _repair_ways, _scan, _Sink

__all__ = ["TRIM_INPUT_BYTES", "read_osm", "read_osm_spooled"]

# From this much input the freed C heap is handed back to the system between the stages of a read (see
# mapdb.sources.spool.release_freed_memory), so that one stage's leftovers do not add to the next one's peak; below it
# the heap is small, and handing it back would only make the next stage fault the same pages in again.
TRIM_INPUT_BYTES = FILE_INDEX_BYTES


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
        close), ``"missing_nodes"`` (ways tagged as areas with a node missing from the extract: a clipped
        extract's border cuts them), ``"incomplete_relations"`` (multipolygon relations osmium could not
        assemble: a member way or node missing from the extract, or out of range), ``"repaired_geometries"``
        (areas whose rings cross themselves, rebuilt with shapely's ``make_valid``) and
        ``"invalid_geometries"`` (areas that could not be repaired).
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
    libosmium cannot parse (``nan``, ``1e400``, text) is skipped and counted, not fatal (see ``files._xml_input``).

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
                     spool_dir: str | Path | None = None, outlines: OutlineSink | None = None,
                     part: str = "all") -> list[ObjectSpool]:
    """:func:`read_osm`'s objects, in order, as spools of blocks that are written to ``spool_dir`` as the pass
    goes (kept in memory when it is None), so that a country's objects are never all in memory.

    The spools are the points, the areas, then the ways and intersections; their files (``osm-*`` in
    ``spool_dir``) are the caller's to remove (:meth:`mapdb.sources.spool.ObjectSpool.discard`, or with the directory).
    Parameters, errors and the objects read are those of :func:`read_osm`; ``outlines``, when given, is handed
    the outline (a shapely geometry in lon/lat, to copy) and label code of every area read, block by block,
    before it is dropped
    (the builder's blocks of touching buildings, :class:`mapdb.build.blocks.BuildingOutlines`).  ``part``
    (one of :data:`~mapdb.sources.osm.scan.PARTS`) reads all the objects, or only the areas or only the rest:
    two processes reading the two halves give, together, the objects and counts of one read.
    """
    path = Path(path)
    if node_index not in NODE_INDEXES:
        raise SourceError(f"node index {node_index!r}: not one of {', '.join(NODE_INDEXES)}")
    if part not in PARTS:
        raise SourceError(f"part {part!r}: not one of {', '.join(PARTS)}")
    _check_readable(path)
    bbox = None if bbox is None else check_bbox(bbox)
    counts = counts if counts is not None else Counter()
    spools = [ObjectSpool(table.labels, "EPSG:4326", spool_dir, f"osm-{kind}-")
              for kind in ("points", "areas", "others")]
    try:
        with _Workspace(index_dir) as workspace:
            _read(path, table, bbox, progress or (lambda message: None), counts, workspace, node_index, spools,
                  outlines, part)
    except BaseException:
        for spool in spools:
            spool.discard()
        raise
    return spools


def _read(path: Path, table: LabelTable, bbox: tuple[float, float, float, float] | None, report: Progress,
          counts: Counter[str], workspace: _Workspace, node_index: str, spools: list[ObjectSpool],
          outlines: OutlineSink | None = None, part: str = "all") -> None:
    """:func:`read_osm` on checked arguments: collect and assemble into ``spools``, and say what came of it."""
    started = time.monotonic()
    report(f"{path}: reading OpenStreetMap data")
    collected = _collect(path, table, report, counts, workspace, node_index, _Sink(spools, bbox, len(table.labels)),
                         outlines, part)
    report(f"{path}: file read in {time.monotonic() - started:.1f} s; joining roundabouts, finding intersections")
    _assemble(collected, table, counts)
    found = collected.sink.found
    summary = ", ".join(f"{n:,} {name}" for name, n in zip(table.labels, found.tolist(), strict=True) if n) or "nothing"
    report(f"{path}: {int(found.sum()):,} objects in {time.monotonic() - started:.1f} s ({summary})")
    skipped = ", ".join(f"{n:,} {kind.replace('_', ' ')}" for kind, n in sorted(counts.items()) if n)
    if skipped:
        report(f"{path}: skipped or repaired: {skipped}")


def _collect(path: Path, table: LabelTable, report: Progress, counts: Counter[str], workspace: _Workspace,
             node_index: str, sink: _Sink, outlines: OutlineSink | None = None, part: str = "all") -> _Collected:
    """The single pass over the file (and the repair of areas osmium could not assemble)."""
    try:
        with _xml_input(path) if path.name.lower().endswith(_XML_SUFFIXES) else nullcontext(str(path)) as source:
            size = os.path.getsize(source)
            collected = _Collected(table.labels, workspace, counts, size, sink)
            collected.outlines = outlines
            collected.locations, collected.index_file = workspace.node_index(node_index, size, path)
            _scan(path, source, table, report, collected, part)
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
    collected.sink.add(2, _way_objects(collected.ways, table.labels))
    trim()
    if table.intersections is not None:
        collected.sink.add(2, _intersection_objects(collected.roads, collected.ways, collected.locations,
                                                    collected.index_file, table.intersections, table.labels,
                                                    counts))
