"""Build a map file from sources: read, label, reproject, clip, write."""

from __future__ import annotations

import math
import tempfile
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from pyproj import CRS, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from ..classmap import ClassTable, check_label, load_class_table
from ..cluster import open_client
from ..errors import EmptyMapError, MapdbIOError, SourceError
from ..geo import bbox_text, check_bbox, in_bbox
from ..labels import LabelTable, load_label_table
from ..mapfile.writer import MapWriter
from ..objects import Objects
from ..progress import Progress, ProgressLike, as_progress
from ..sources import SKIPPED_KINDS, source_kind
from ..sources.osm.index import NODE_INDEXES
from ..sources.spool import ObjectSpool
from .blocks import DEFAULT_GAP_M, MAX_GAP_M
from .blockstats import Blocks, central_longitude_of, lon_arc_of, median_of
from .elevation import ElevationTally
from .inputs import file_sha256
from .reading import (
    JOBS_MIN_BYTES,
    SPOOL_CHOICES,
    SPOOL_INPUT_BYTES,
    _count,
    _kept,
    _paying_jobs,
    _read_sources,
    _ReadOptions,
    _Spooling,
    read_one_source,
)

__all__ = ["JOBS_MIN_BYTES", "MAX_AUTO_CRS_SPAN_DEG", "SPOOL_CHOICES", "SPOOL_INPUT_BYTES", "build_map",
           "read_one_source", "utm_crs_for"]

# With ``crs="auto"`` the map is projected in one UTM zone (6 degrees of longitude wide).  Sources whose
# objects span more longitude than two zones put some of them about 6 degrees or more from the zone's
# central meridian, where the projection stretches distances by up to half a percent (at the equator) and
# its grid north turns from true north by up to 6 degrees (towards the poles): the build warns and suggests
# an explicit CRS or one map per area.
MAX_AUTO_CRS_SPAN_DEG = 12.0


def utm_crs_for(lon: float, lat: float) -> str:
    """The WGS 84 UTM zone CRS that contains a point, as ``"EPSG:n"``.

    Examples
    --------
    >>> utm_crs_for(7.42, 43.73)   # Monaco
    'EPSG:32632'
    >>> utm_crs_for(-70.0, -33.0)
    'EPSG:32719'
    """
    finite = math.isfinite(lon) and math.isfinite(lat)
    # Several zones touch on a zone edge; the formula's zone is the conventional choice.
    zone = int((lon + 180) // 6) % 60 + 1 if finite else 0
    wanted = f"{326 if lat >= 0 else 327}{zone:02d}"
    if finite and _strictly_inside(wanted, lon, lat):
        return f"EPSG:{wanted}"  # the zone the query below would find first, without it (60 ms)
    found = query_utm_crs_info(
        datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat)
    )
    if not found:
        raise ValueError(f"no UTM zone for lon {lon}, lat {lat}")
    codes = [c.code for c in found]
    return f"EPSG:{wanted if wanted in codes else codes[0]}"


def _strictly_inside(code: str, lon: float, lat: float) -> bool:
    """Whether a point lies inside the area of use of the CRS ``EPSG:code``, off its edges (where the database's
    query of the zones that hold a point, which takes tens of milliseconds, surely finds it)."""
    area = CRS.from_epsg(int(code)).area_of_use
    return area is not None and area.west < lon < area.east and area.south < lat < area.north


def _spread_warning(names: list[str], lonlat: list[Blocks], target: str) -> str | None:
    """The warning for sources too wide in longitude for one auto-chosen UTM zone, else None (``lonlat``: each
    source's longitudes, block by block)."""
    start, width = lon_arc_of(lambda: (lon for blocks in lonlat for lon in blocks()))
    if width <= MAX_AUTO_CRS_SPAN_DEG:
        return None
    # Name the sources at the two ends of the arc, by their own central longitude counted from its start.
    middles = []
    for name, blocks in zip(names, lonlat, strict=True):
        if any(lon.size for lon in blocks()):
            middle = central_longitude_of(blocks)
            middles.append((float(np.mod(middle - start, 360.0)), name, middle))
    (_, west, west_lon), (_, east, east_lon) = min(middles), max(middles)
    where = (f"{west} (lon {west_lon:.1f}) and {east} (lon {east_lon:.1f})" if west != east
             else f"{west}")
    return (f"sources span {width:.1f} degrees of longitude ({where}), more than the "
            f"{MAX_AUTO_CRS_SPAN_DEG:g} (two UTM zones) that the automatic {target} holds without distortion; "
            "give a CRS that fits them all (--crs) or build one map per area")


def _check_number(name: str, value: float, low: float, high: float, low_open: bool) -> float:
    """A finite number within [low, high] (or (low, high]), as a SourceError saying which option is wrong."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SourceError(f"{name} {value!r}: not a number") from None
    below = number <= low if low_open else number < low
    if not math.isfinite(number) or below or number > high:
        raise SourceError(f"{name} {value!r}: must be a finite number in {'(' if low_open else '['}{low:g}, {high:g}]")
    return number


def _projected_crs(crs: str) -> str:
    try:
        parsed = CRS.from_user_input(crs)
    except Exception:
        raise SourceError(f"--crs {crs}: not a CRS that pyproj knows") from None
    if not parsed.is_projected:
        raise SourceError(f"--crs {crs}: a map needs a projected CRS in metres")
    return parsed.to_string()


def build_map(
    sources: Sequence[str | Path], output: str | Path, *, labels: str | Path | None = None, crs: str = "auto",
    bbox: tuple[float, float, float, float] | None = None, quantum: float = 0.1, raster_classes: str | None = None,
    min_area_m2: float = 10_000.0, label_column: str = "label", layer_crs: str | None = None,
    label: str | None = None, label_map: str | Path | None = None, node_index: str = "auto",
    index_dir: str | Path | None = None, spool: str = "auto", jobs: int | None = None,
    scheduler: str | None = None, progress: ProgressLike = None, blocks: bool = True,
    block_gap: float = DEFAULT_GAP_M, dem: Sequence[str | Path] = (), jobs_min_bytes: int | None = None,
    outlines_in_memory: int | None = None,
) -> dict[str, Any]:
    """Read every source, reproject to one metric CRS, clip and write one map file.

    Parameters
    ----------
    sources : sequence of paths
        OSM extracts, land-cover GeoTIFFs and point/polygon layers, in any mix.  A source given twice
        (the same file, or a file with the same SHA-256) is read once, with a warning.
    output : path
        The ``.mapdb`` file; replaced atomically, left untouched on failure.  Its directory must exist.
    labels : path, optional
        A TOML label table read over the defaults (see ``mapdb/data/labels.toml``).
    crs : str
        ``"auto"`` for the UTM zone of the data, or any CRS pyproj accepts.  With ``"auto"``, sources
        spanning more than :data:`MAX_AUTO_CRS_SPAN_DEG` degrees of longitude give a warning.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Keep only objects whose centroid falls inside.  The box may span the world, touch the poles
        or cross the antimeridian (``minlon > maxlon``, as in GeoJSON).
    quantum : float
        Stored resolution in metres, in (0, 1000].
    min_area_m2 : float
        Smallest land-cover patch kept, finite and >= 0.
    label : str, optional
        The label of every feature of a layer that has no label column (a building footprint file).
    label_map : path, optional
        A TOML class table (:mod:`mapdb.classmap`) mapping the values of a layer column to labels;
        features with other values are skipped and counted (``unmapped_labels``).
    node_index, index_dir : str, path, optional
        Where OSM node locations are kept (:func:`mapdb.sources.osm.reader.read_osm`: ``"auto"`` chooses memory or a
        temporary file by the input's size) and the directory of such temporary files, and of the objects
        read from OSM sources (28 bytes an object, read back in blocks; all removed at the end).
    spool : str
        Where the objects read from OSM sources are kept until they are written: ``"memory"``, ``"file"``
        (in ``index_dir``) or ``"auto"``, in memory while the OSM sources so read add up to less than
        :data:`SPOOL_INPUT_BYTES` (64 MiB) and in files from there.  The map is the same.
    jobs, scheduler : int, str, optional
        Read the sources in parallel, one Dask task a source (two for an OSM extract from
        :data:`~mapdb.build.reading.SPLIT_OSM_BYTES`: its areas and the rest), on a local cluster of ``jobs``
        worker processes or on the scheduler at ``scheduler`` (see :mod:`mapdb.cluster`); the blocks of a
        source whose footprints wait in tile files are formed by tasks of their own, over runs of tiles, once
        it is read.  The map is the same as the one read in this process.  A source that fails fails the
        build, naming the source.  A local cluster is started only when the sources besides the largest add up
        to ``jobs_min_bytes`` (default :data:`JOBS_MIN_BYTES`) or an OSM extract is read in halves: otherwise
        they are read in this process (and it is said).
    dem : sequence of paths
        Elevation rasters (GeoTIFF or SRTM ``.hgt``, any CRS, a mosaic in the order given): the map stores
        each object's ground elevation (:mod:`mapdb.build.elevation`; a version 2 map).  Objects off the DEMs
        are counted in one warning; DEMs under none of them are refused.
    progress : Progress or callable, optional
        Receives the stages as messages, and a count over the sources read, the projection and the
        writing (see :class:`mapdb.progress.Progress`).
    blocks, block_gap : bool, float
        Also store each group of two or more buildings of a source whose footprints lie within ``block_gap``
        metres (in [0, 5]) as a ``building_block`` object (:mod:`mapdb.build.blocks`: a mask's merged blob).
    outlines_in_memory : int, optional
        The building footprints of an OSM or layer source kept in memory for its blocks, past which they go to
        tile files (default :data:`~mapdb.build.tiles.OUTLINES_IN_MEMORY`; :mod:`mapdb.build.tiles`, where a
        block longer than the tiles' margin is stored in parts).

    Returns
    -------
    dict
        ``{"count": n, "labels": {name: count}, "crs": ..., "output": ..., "skipped": {kind: n},
        "warnings": [...]}``; ``skipped`` counts what the readers skipped or repaired instead of failing
        (kinds in :data:`mapdb.sources.SKIPPED_KINDS`), also recorded per source in the map's metadata;
        ``warnings`` are one-line messages about the sources (duplicates, too far apart for the
        automatic CRS) that did not stop the build.

    Raises
    ------
    SourceError
        A bad source, or an argument out of range (``quantum``, ``min_area_m2``, ``bbox``, ``node_index``,
        ``spool``, both ``jobs`` and ``scheduler``).
    MapdbIOError
        ``index_dir`` cannot hold an OSM source's temporary files; a Dask scheduler that does not answer.
    EmptyMapError
        If no object survives (for example a bbox over empty ground).
    """
    quantum, min_area_m2, bbox, target, table = _checked_arguments(sources, quantum, min_area_m2, bbox, crs, labels)
    gap = _check_number("block_gap", block_gap, 0.0, MAX_GAP_M, low_open=False) if blocks else None
    elevation = ElevationTally(dem) if dem else None  # the DEMs checked before any source is read
    say = as_progress(progress)
    say.start(len(sources) + 2, "build")  # one count: each source read, then the projection, then the writing
    read_options = {"bbox": bbox, "raster_classes": raster_classes, "min_area_m2": min_area_m2,
                    "label_column": label_column, "layer_crs": layer_crs, "label": label,
                    "label_map": _label_map(label_map, label, table), "block_gap": gap,
                    "outlines_in_memory": outlines_in_memory}
    osm_options = {"node_index": _checked_node_index(node_index), "index_dir": index_dir}
    if jobs is not None and scheduler is not None:
        raise SourceError("give jobs (a local Dask cluster) or scheduler (an existing one), not both")
    if spool not in SPOOL_CHOICES:
        raise SourceError(f"spool {spool!r}: not one of {', '.join(SPOOL_CHOICES)}")
    jobs = _paying_jobs(sources, jobs, JOBS_MIN_BYTES if jobs_min_bytes is None else jobs_min_bytes, say)
    with open_client(jobs, scheduler) as client, _scratch(index_dir) as directory:
        spooling = _Spooling(directory, spool, scheduler is None)
        read = _gather(sources, table, (read_options, osm_options), target, say, client, spooling)
        return _built(output, read, table, quantum, say, elevation, {
            "crs": crs, "bbox": list(bbox) if bbox else None, "quantum": quantum,
            "labels_file": Path(labels).name if labels else None,
            "labels_sha256": file_sha256(Path(labels)) if labels else None, "raster_classes": raster_classes,
            "min_area_m2": min_area_m2, "label_column": label_column, "layer_crs": layer_crs, "label": label,
            "label_map": Path(label_map).name if label_map else None,
            "label_map_sha256": file_sha256(Path(label_map)) if label_map else None, "block_gap_m": gap})


def _built(output: str | Path, read: _Read, table: LabelTable, quantum: float, say: Progress,
           elevation: ElevationTally | None, build: dict[str, Any]) -> dict[str, Any]:
    """Write the map of what was read, and say what came of it (:func:`build_map`'s result)."""
    written, label_counts, totals = _write(output, read, table, quantum, build, say, elevation)
    return {"output": str(output), "crs": read.target, "count": written, "labels": label_counts,
            "skipped": {kind: n for kind, n in sorted(totals.items()) if n}, "warnings": read.warnings}


class _Read(NamedTuple):
    """The sources read and clipped, not yet projected: each source's objects in lon/lat (spools of blocks), the
    map's CRS, the sources' metadata entries, what each reader skipped, the warnings and the sources' names."""

    parts: list[list[ObjectSpool]]
    target: str
    described: list[dict[str, Any]]
    skipped: list[Counter[str]]
    warnings: list[str]
    names: str


def _gather(sources: Sequence[str | Path], table: LabelTable, options: _ReadOptions, target: str | None,
            say: Progress, client: Any, spooling: _Spooling) -> _Read:
    """Read and clip every source, and choose the CRS when ``target`` is None (from every object's lon/lat)."""
    parts, described, skipped, warnings = _read_sources(sources, table, say, options, client, spooling)
    bbox = options[0]["bbox"]
    if bbox is not None:
        # A box across the antimeridian is no plain box: those spools are always checked.
        plain = bbox if bbox[0] <= bbox[2] else None
        parts = [_kept(spools, lambda block: in_bbox(bbox, block.x, block.y), plain)[0] for spools in parts]
    names = ", ".join(str(s) for s in sources)
    if sum(map(_count, parts)) == 0:
        where = f" inside bbox {bbox_text(bbox)}" if bbox else ""
        raise EmptyMapError(f"{names}: no labelled objects{where}")
    if target is None:
        lon = [_coordinate(spools, "x") for spools in parts]
        target = _crs_of(lambda: (block for blocks in lon for block in blocks()),
                         lambda: (block for spools in parts for block in _coordinate(spools, "y")()))
        spread = _spread_warning([d["name"] for d in described], lon, target)
        warnings += [spread] if spread else []
    return _Read(parts, target, described, skipped, warnings, names)


def _coordinate(spools: list[ObjectSpool], axis: str) -> Blocks:
    """One coordinate (``"x"``: longitude, ``"y"``: latitude) of a source's objects, block by block, afresh
    at each call."""
    return lambda: (getattr(block, axis) for spool in spools for block in spool.blocks())


def _write(output: str | Path, read: _Read, table: LabelTable, quantum: float, build: dict[str, Any],
           say: Progress, elevation: ElevationTally | None = None) -> tuple[int, dict[str, int], Counter[str]]:
    """Project the sources' objects block by block into a streaming map writer, which holds a bounded number
    of them, and write the map: the objects written, the count per label, and what was skipped in all
    (merged duplicates included)."""
    total = sum(map(_count, read.parts))
    say(f"projecting {total} objects to {read.target} ...")
    with MapWriter(output, quantum=quantum) as writer:
        blocks = _project(read.parts, read.skipped, read.target, table)
        for block in elevation.sampled(blocks) if elevation else blocks:
            writer.add(block)
        say.advance()
        if writer.count == 0:
            raise EmptyMapError(f"{read.names}: no object projects into {read.target}")
        if elevation:
            elevation.check()
            build = {**build, "dem": elevation.record()}
            read.warnings.extend(filter(None, [elevation.warning()]))
        totals = _tally_skipped(read.described, read.skipped, say)
        say(f"writing {writer.count} objects to {output} ({read.target}, quantum {quantum} m) ...")
        written = writer.finish({"sources": read.described, "build": build})
        say.advance()
        say.done()
        if written < writer.count:
            totals["merged_duplicates"] += writer.count - written
    return written, writer.label_counts, totals


def _checked_arguments(sources: Sequence[str | Path], quantum: float, min_area_m2: float,
                       bbox: tuple[float, float, float, float] | None, crs: str, labels: str | Path | None
                       ) -> tuple[float, float, tuple[float, float, float, float] | None, str | None, LabelTable]:
    """The arguments checked before any reading: quantum, min_area_m2, bbox, the target CRS (None: auto) and
    the label table."""
    if not sources:
        raise SourceError("no sources given")
    quantum = _check_number("quantum", quantum, 0.0, 1000.0, low_open=True)
    min_area_m2 = _check_number("min_area_m2", min_area_m2, 0.0, math.inf, low_open=False)
    if bbox is not None:
        try:
            bbox = check_bbox(bbox)
        except ValueError as exc:
            raise SourceError(f"bbox {bbox!r}: {exc}") from None
    for path in sources:  # fail on a bad name before spending time on the others
        source_kind(path)
    target = None if crs == "auto" else _projected_crs(crs)
    return quantum, min_area_m2, bbox, target, load_label_table(labels)


def _auto_crs(lonlat: list[tuple[np.ndarray, np.ndarray]]) -> str:
    """The UTM zone of the objects' median place (``lonlat``: each set's longitudes and latitudes)."""
    return _crs_of(lambda: (lon for lon, _ in lonlat), lambda: (lat for _, lat in lonlat))


def _crs_of(lon: Blocks, lat: Blocks) -> str:
    """The UTM zone of the median place of the objects whose longitudes and latitudes these blocks give.

    The median longitude is taken around the globe's widest empty gap: data on both sides of the antimeridian
    (Fiji) get the zone at 180, not the one at 0.  Read in passes over the blocks, in bounded memory, and
    equal to the medians of all the values at once (:mod:`mapdb.build.blockstats`).
    """
    return utm_crs_for(central_longitude_of(lon), float(median_of(lat)))


# Objects projected at once: the blocks handed to the map writer (about 20 MB of arrays a block).
_PROJECT_BLOCK = 1 << 18


def _project(parts: list[list[ObjectSpool]], skipped: list[Counter[str]], target: str, table: LabelTable
             ) -> Iterator[Objects]:
    """Every source's objects (in lon/lat) in ``target`` and in the label table, in blocks of at most
    :data:`_PROJECT_BLOCK`; those the CRS cannot hold are dropped and counted.

    Each source's spools are discarded once projected (``parts`` is emptied), so that a source is released
    once its last block is written, and no merged copy of all the sources is ever made.
    """
    to_target = Transformer.from_crs("EPSG:4326", target, always_xy=True)
    for counts in skipped:
        for spool in parts.pop(0):
            for block in spool.blocks(_PROJECT_BLOCK):
                x, y = to_target.transform(block.x, block.y)
                finite = np.isfinite(x) & np.isfinite(y)
                counts["outside_crs"] += int((~finite).sum())
                moved = Objects(x, y, block.label, block.area, block.labels, target)
                yield (moved if finite.all() else moved.take(finite)).relabel(table.labels)
            spool.discard()


def _tally_skipped(described: list[dict[str, Any]], skipped: list[Counter[str]], say: Progress) -> Counter[str]:
    """Record what each source's reader skipped in its metadata entry, say the totals, and return them."""
    for entry, counts in zip(described, skipped, strict=True):
        entry["skipped"] = {kind: n for kind, n in sorted(counts.items()) if n}
    totals = sum(skipped, Counter())
    for kind, n in sorted(totals.items()):
        if n:
            say(f"  {n:,} {SKIPPED_KINDS.get(kind, kind)}")
    return totals


def _label_map(path: str | Path | None, label: str | None, table: LabelTable) -> ClassTable | None:
    """The --label-map table, checked against the label table (and --label checked too)."""
    if label is not None:
        check_label(label, table.labels, "--label")
    return None if path is None else load_class_table(path, table.labels, column=True)


@contextmanager
def _scratch(index_dir: str | Path | None) -> Iterator[str]:
    """A temporary directory for the objects read (under ``index_dir``, else the system's), removed at the end."""
    try:
        tmp = tempfile.TemporaryDirectory(prefix="mapdb-build-", dir=index_dir)
    except OSError as exc:
        raise MapdbIOError(f"{index_dir or tempfile.gettempdir()}: cannot hold the build's temporary files "
                           f"({exc.strerror or exc})") from None
    with tmp as name:
        yield name


def _checked_node_index(node_index: str) -> str:
    if node_index not in NODE_INDEXES:
        raise SourceError(f"node index {node_index!r}: not one of {', '.join(NODE_INDEXES)}")
    return node_index
