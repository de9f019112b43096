"""Reading a build's sources: each source once, in this process or as Dask tasks, into spools of lon/lat objects.

Used by :func:`mapdb.build.pipeline.build_map`: :func:`read_one_source` is a whole build's worth of one source
(the unit of work of a parallel build), :class:`_Spooling` says where the objects read wait for the map
writer (in memory or in the build's temporary directory), and :func:`_paying_jobs` whether a local cluster
can pay at all.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from pyproj import CRS, Transformer

from ..cluster import run_pool, worker_count
from ..errors import MapdbError, SourceError
from ..labels import LabelTable
from ..objects import Objects
from ..progress import Progress
from ..sources import read_source, source_kind
from ..sources.osm.index import FILE_INDEX_BYTES
from ..sources.osm.reader import TRIM_INPUT_BYTES, read_osm_spooled
from ..sources.spool import ObjectSpool, check_room, release_freed_memory, spool_bytes
from .blocks import BuildingOutlines, blocks_spool
from .inputs import duplicate_input, file_fingerprint, file_sha256
from .layersource import layer_spool, source_outlines
from .tiles import FootprintTiles, SpillingOutlines, tile_blocks_spool

__all__ = ["JOBS_MIN_BYTES", "SPLIT_OSM_BYTES", "SPOOL_CHOICES", "SPOOL_INPUT_BYTES", "read_one_source"]

# The options of read_source, and those only OSM sources take (node_index, index_dir).
_ReadOptions = tuple[dict[str, Any], dict[str, Any]]

# Where the objects read from OSM sources wait for the map writer (``build_map(spool=...)``): in memory, or in
# temporary files (28 bytes an object, read back in blocks).  "auto" keeps them in memory while the OSM inputs
# so read add up to less than SPOOL_INPUT_BYTES, the size from which libosmium's node index is a file too (about
# 6,000 objects a MB of PBF: some 11 MB of objects at most); files cost little, but a town's build would spend
# a few percent of its time writing and reading them back.
SPOOL_CHOICES = ("auto", "memory", "file")
SPOOL_INPUT_BYTES = FILE_INDEX_BYTES

# A local Dask cluster (--jobs) costs seconds to start and reads one source a task: only the sources besides the
# largest can gain, when they take longer than the cluster costs (issue 31: the shared extracts, 2.8 MB, built
# 2.3 times slower with two workers).  32 MB, some 30 s of OSM reading, is a chosen bound, not a measured one.
JOBS_MIN_BYTES = 32 << 20

def _to_lonlat(objects: Objects) -> tuple[np.ndarray, np.ndarray]:
    crs = CRS.from_user_input(objects.crs)
    if crs.equals(CRS.from_epsg(4326), ignore_axis_order=True):
        return objects.x, objects.y
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
    return np.asarray(lon), np.asarray(lat)


def _count(spools: list[ObjectSpool]) -> int:
    """How many objects a source's spools hold."""
    return sum(len(spool) for spool in spools)


def _kept(spools: list[ObjectSpool], keep: Callable[[Objects], np.ndarray],
          box: Sequence[float] | None = None) -> tuple[list[ObjectSpool], int]:
    """A source's objects that ``keep`` keeps (a mask a block), and how many it dropped.

    ``keep`` keeps at least every finite object within ``box`` when one is given: spools whose objects all
    are (:meth:`ObjectSpool.inside`, from what was added) are not read back.  Otherwise a pass over the blocks
    first: when nothing is dropped (a source already clipped or all valid) the spools are kept as they are,
    not copied; else each is rewritten beside itself and the old one discarded.
    """
    if box is not None and all(spool.inside(box) for spool in spools):
        return spools, 0
    dropped = sum(int((~keep(block)).sum()) for spool in spools for block in spool.blocks())
    if not dropped:
        return spools, 0
    kept = []
    for spool in spools:
        copy = ObjectSpool(spool.labels, spool.crs, spool.directory, "kept-")
        for block in spool.blocks():
            mask = keep(block)
            copy.add(block if mask.all() else block.take(mask))
        spool.discard()
        kept.append(copy)
    return kept, dropped


def _read_sources(sources: Sequence[str | Path], table: LabelTable, say: Progress, options: _ReadOptions,
                  client: Any, spooling: _Spooling
                  ) -> tuple[list[list[ObjectSpool]], list[dict[str, Any]], list[Counter[str]], list[str]]:
    """Read each source once: its objects, its metadata entry, what its reader skipped; and the warnings."""
    unique, warnings = [], []
    seen: dict[Any, Path] = {}
    for path in map(Path, sources):
        fingerprint = file_fingerprint(path)
        duplicate = duplicate_input(path, fingerprint, seen)
        if duplicate:
            warnings.append(duplicate)
            say.advance()
            continue
        unique.append((path, fingerprint))
    paths = [path for path, _ in unique]
    results = (_read_here(paths, table, options, say, spooling) if client is None
               else _read_on_cluster(paths, table, options, say, client, spooling))
    described = [{"name": path.name, "kind": source_kind(path), "size": path.stat().st_size,
                  "sha256": fingerprint[1] if fingerprint else file_sha256(path),
                  "objects": _count(spools)}
                 for (path, fingerprint), (spools, _) in zip(unique, results, strict=True)]
    return [spools for spools, _ in results], described, [counts for _, counts in results], warnings


def read_one_source(path: Path, table: LabelTable, options: _ReadOptions, say: Progress | None = None,
                    spool_dir: str | None = None, scratch: str | None = None, part: str = "all"
                    ) -> tuple[list[ObjectSpool], Counter[str]]:
    """One source's objects in lon/lat (those not on Earth dropped and counted) and what its reader skipped.

    A whole build's worth of one source.  The objects come as spools of blocks
    (:class:`mapdb.sources.spool.ObjectSpool`), in ``EPSG:4326``: an OSM source read with a ``spool_dir`` is
    written there block by block as it is read (the caller removes the files), anything else is held in memory;
    a layer is read a batch at a time, and its building footprints past
    :data:`~mapdb.build.layersource.OUTLINES_IN_MEMORY` (or the ``outlines_in_memory`` read option) wait for
    their blocks in tile files in ``scratch``, as an OSM source's do.  ``part`` reads one half of an OSM source
    (:data:`~mapdb.sources.osm.scan.PARTS`; the blocks are the areas' half's).
    """
    spools, counts, outlines, small = _read_objects(path, table, options, say, spool_dir, scratch, part)
    gap = options[0].get("block_gap")
    if outlines is not None and gap is not None:
        spools.append(blocks_spool(outlines, table.labels, gap, options[0]["bbox"], say))
    return _on_earth_only(spools, counts, small)


def _read_objects(path: Path, table: LabelTable, options: _ReadOptions, say: Progress | None, spool_dir: str | None,
                  scratch: str | None, part: str
                  ) -> tuple[list[ObjectSpool], Counter[str], BuildingOutlines | None, bool]:
    """A source's objects in lon/lat, what its reader skipped, its building footprints (None: no blocks; the
    blocks not yet formed) and whether the source is small (no memory worth giving back)."""
    counts: Counter[str] = Counter()
    read_options, osm_options = dict(options[0]), options[1]
    gap = read_options.pop("block_gap", None)
    memory = read_options.pop("outlines_in_memory", None)
    kind = source_kind(path)
    outlines = source_outlines(table, gap if part != "rest" else None, scratch if kind in ("osm", "layer") else None,
                               memory)
    if kind in ("osm", "layer") and (spool_dir or scratch):
        check_room(path, str(spool_dir or scratch), spool_bytes(path, spool_dir is not None, outlines is not None))
    if kind == "osm":
        sink = outlines.add_areas if outlines is not None else None
        spools = read_osm_spooled(path, table, bbox=read_options["bbox"], progress=say, counts=counts,
                                  spool_dir=spool_dir, outlines=sink, part=part, **osm_options)
        return spools, counts, outlines, path.stat().st_size < TRIM_INPUT_BYTES
    if kind == "layer":
        return [layer_spool(path, table, read_options, counts, outlines, say, spool_dir)], counts, outlines, False
    objects = read_source(path, table, progress=say, counts=counts, **read_options)
    lon, lat = _to_lonlat(objects) if len(objects) else (objects.x, objects.y)
    spools = [ObjectSpool(objects.labels, "EPSG:4326")]
    spools[0].add(Objects(lon, lat, objects.label, objects.area, objects.labels, "EPSG:4326"))
    del objects
    return spools, counts, outlines, False  # a raster's windows may have taken much more than the file


def _on_earth_only(spools: list[ObjectSpool], counts: Counter[str], small: bool = True
                   ) -> tuple[list[ObjectSpool], Counter[str]]:
    """The spools less the objects not on Earth, those counted (after the memory a large source's reading
    freed is given back)."""
    if not small:
        release_freed_memory()
    # Every source, whatever its CRS, must give places on Earth: a point whose lon/lat is not finite or out of
    # range (a projected layer outside its projection) is dropped and counted.
    spools, dropped = _kept(spools, _on_earth, _EARTH)
    counts["invalid_coordinates"] += dropped
    return spools, counts


_EARTH = (-180.0, -90.0, 180.0, 90.0)


def _on_earth(block: Objects) -> np.ndarray:
    lon, lat = block.x, block.y
    return np.isfinite(lon) & np.isfinite(lat) & (np.abs(lon) <= 180) & (np.abs(lat) <= 90)


class _Spooling(NamedTuple):
    """The build's temporary directory, and where OSM sources' objects go (one of :data:`SPOOL_CHOICES`)."""

    directory: str
    spool: str
    shared: bool = False  # whether Dask workers write there too (a local cluster, on this machine's disk)

    def spool_dirs(self, paths: list[Path]) -> list[str | None]:
        """The ``spool_dir`` of each source read in this process: the directory, or None (in memory)."""
        held, dirs = 0, []
        for path in paths:
            try:
                size = path.stat().st_size if source_kind(path) in ("osm", "layer") else 0
            except OSError:  # the reader says what is wrong with it
                size = 0
            memory = self.spool == "memory" or (self.spool == "auto" and held + size < SPOOL_INPUT_BYTES)
            held += size if memory else 0
            dirs.append(None if memory else self.directory)
        return dirs


def _read_here(paths: list[Path], table: LabelTable, options: _ReadOptions, say: Progress, spooling: _Spooling
               ) -> list[tuple[list[ObjectSpool], Counter[str]]]:
    results = []
    for path, spool_dir in zip(paths, spooling.spool_dirs(paths), strict=True):
        say(f"reading {path} ...")
        results.append(read_one_source(path, table, options, say, spool_dir, spooling.directory))
        say(f"  {_count(results[-1][0])} objects from {path.name}")
        say.advance()
    return results


# A read task's result: the source's objects, what its reader skipped, and its footprints in tile files whose
# blocks are still to be formed (None: formed, or none).
_Result = tuple[list[ObjectSpool], Counter[str], FootprintTiles | None]

# The blocks of a source whose footprints wait in tile files are formed by this many tasks a worker (runs of
# tiles of about equal weight, mapdb.build.tiles.balanced_runs): more than one a worker, so that a worker
# that frees up late (another still reading) finds some left to take.
BLOCK_TASKS_PER_WORKER = 4


class _Task(NamedTuple):
    """A task of a parallel read: the function and its arguments, the piece (of :func:`_pieces`) it is part
    of, and which group of the piece's tiles' blocks it forms (-1: the piece's reading)."""

    fn: Callable[..., Any]
    args: tuple[Any, ...]
    piece: int
    group: int = -1


def _read_on_cluster(paths: list[Path], table: LabelTable, options: _ReadOptions, say: Progress, client: Any,
                     spooling: _Spooling) -> list[tuple[list[ObjectSpool], Counter[str]]]:
    """The sources read as Dask tasks: one a source or one a half of a large OSM extract (:func:`_pieces`), and
    the blocks of a source whose footprints wait in tile files in tasks of their own, over runs of tiles of
    about equal weight, submitted as soon as its reading is done.  The results in source order, a source's
    pieces and groups of blocks joined in the order one process gives them, whatever order they end in."""
    workers = worker_count(client)
    pieces = _pieces(paths, spooling, workers)
    say(f"reading {len(paths)} sources on {workers} Dask workers ({len(pieces)} tasks) ...")
    read = _ClusterRead(paths, table, options, pieces, say, workers)
    # The longest first (the largest sources, an extract's areas before the rest), so that no long task starts
    # last while the other workers idle.
    order = sorted(range(len(pieces)), key=lambda k: (-_size(paths[pieces[k][0]]), k))
    tasks = [_Task(_read_task, (paths[i], table, options, part, spool_dir, scratch), k)
             for k in order for i, part, spool_dir, scratch in [pieces[k]]]
    try:
        run_pool(client, workers, tasks, read.done)
    except MapdbError:
        raise
    except Exception as exc:  # a worker lost (killed, out of memory): the sources not read are named
        pending = ", ".join(str(paths[i]) for i in sorted(read.left) if read.left[i])
        detail = " ".join(str(exc).split())[:200] or exc.__class__.__name__
        raise SourceError(f"{pending}: not read, a Dask worker failed ({exc.__class__.__name__}: {detail})") from None
    return read.joined()


class _ClusterRead:
    """What a parallel read has gathered: each task's result, the tasks each source still waits for, and the
    tile files whose blocks are being formed."""

    def __init__(self, paths: list[Path], table: LabelTable, options: _ReadOptions,
                 pieces: list[tuple[int, str, str | None, str | None]], say: Progress, workers: int) -> None:
        self.paths, self.table, self.options, self.pieces, self.say = paths, table, options, pieces, say
        self.groups = BLOCK_TASKS_PER_WORKER * workers
        self.results: dict[tuple[int, int], tuple[list[ObjectSpool], Counter[str]]] = {}
        self.left = Counter(i for i, *_ in pieces)
        self.tiles: dict[int, tuple[FootprintTiles, list[int]]] = {}  # piece: tiles, [tasks left, blocks, tasks]

    def done(self, task: _Task, result: Any) -> list[_Task]:
        """Keep a task's result; the tasks forming the blocks of a piece just read, if its footprints wait in
        tile files."""
        if isinstance(result, MapdbError):
            raise result
        source = self.pieces[task.piece][0]
        more = []
        if task.group < 0:
            spools, counts, tiles = result
            self.results[task.piece, -1] = (spools, counts)
            if tiles is not None:
                more = self._block_tasks(task.piece, tiles)
        else:
            spools, counts, cut = result
            self.results[task.piece, task.group] = (spools, counts)
            self._formed(task.piece, _count(spools), cut)
        self.left[source] += len(more) - 1
        if not self.left[source]:
            mine = [r for (k, _), r in self.results.items() if self.pieces[k][0] == source]
            self.say(f"  {sum(_count(spools) for spools, _ in mine)} objects from {self.paths[source].name}")
            self.say.advance()
        return more

    def _block_tasks(self, piece: int, tiles: FootprintTiles) -> list[_Task]:
        groups = tiles.groups(self.groups)
        if not groups:
            tiles.discard()
            return []
        self.tiles[piece] = (tiles, [len(groups), 0, len(groups)])
        path, read_options = self.paths[self.pieces[piece][0]], self.options[0]
        return [_Task(_blocks_task, (path, tiles, group, self.table.labels, read_options["block_gap"],
                                     read_options["bbox"]), piece, j) for j, group in enumerate(groups)]

    def _formed(self, piece: int, blocks: int, cut: int) -> None:
        """One group of a piece's blocks formed: once all are, say so and remove the tile files."""
        tiles, state = self.tiles[piece]
        tiles.cut += cut
        state[0] -= 1
        state[1] += blocks
        if not state[0]:
            self.say(tiles.said(state[1], self.options[0]["block_gap"], f" ({state[2]} tasks)"))
            tiles.discard()

    def joined(self) -> list[tuple[list[ObjectSpool], Counter[str]]]:
        """Each source's objects and counts: its pieces in order, each piece's objects before its blocks."""
        out: list[tuple[list[ObjectSpool], Counter[str]]] = [([], Counter()) for _ in self.paths]
        for (piece, _), (spools, counts) in sorted(self.results.items()):
            out[self.pieces[piece][0]][0].extend(spools)
            out[self.pieces[piece][0]][1].update(counts)
        return out


# An OSM extract from this size is read by two tasks at once on a cluster of two workers or more: its areas and
# the rest, each a pass of its own over the file (mapdb.sources.osm.scan.PARTS).  libosmium's pass alone, made
# twice, took 17 s against 70 s for the build of Andorra copied 64 times (92 MB); read alone, the areas half took
# 30.5 s and the rest 13.3 s (benchmarks/osm_scale.py --jobs).  Below this size a source is one task.
SPLIT_OSM_BYTES = FILE_INDEX_BYTES


def _pieces(paths: list[Path], spooling: _Spooling, workers: int) -> list[tuple[int, str, str | None, str | None]]:
    """The tasks of a parallel read: (source index, part, spool directory, scratch directory) each.

    Workers on this machine (``spooling.shared``) spool large sources' objects and footprints to the build's
    temporary directory as this process would; others keep them in memory and send them back.
    """
    dirs = spooling.spool_dirs(paths) if spooling.shared else [None] * len(paths)
    scratch = spooling.directory if spooling.shared else None
    pieces = []
    for i, (path, spool_dir) in enumerate(zip(paths, dirs, strict=True)):
        halves = workers >= 2 and source_kind(path) == "osm" and _size(path) >= SPLIT_OSM_BYTES
        pieces += [(i, part, spool_dir, scratch) for part in (("areas", "rest") if halves else ("all",))]
    return pieces


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:  # the reader says what is wrong with it
        return 0


def _read_task(path: Path, table: LabelTable, options: _ReadOptions, part: str = "all", spool_dir: str | None = None,
               scratch: str | None = None) -> _Result | MapdbError:
    """:func:`read_one_source` on a worker, but the blocks of footprints that wait in tile files left to be formed
    (their projection chosen first).  An error is returned, not raised (:func:`_task_error`)."""
    try:
        spools, counts, outlines, small = _read_objects(path, table, options, None, spool_dir, scratch, part)
        tiles = outlines.tiles if isinstance(outlines, SpillingOutlines) else None
        gap = options[0].get("block_gap")
        if tiles is not None:
            tiles.zone()
        elif outlines is not None and gap is not None:
            spools.append(blocks_spool(outlines, table.labels, gap, options[0]["bbox"], None))
        return (*_on_earth_only(spools, counts, small), tiles)
    except Exception as exc:
        return _task_error(path, "reading", exc)


def _blocks_task(path: Path, tiles: FootprintTiles, group: list[tuple[int, int]], labels: tuple[str, ...],
                 gap: float, bbox: tuple[float, float, float, float] | None
                 ) -> tuple[list[ObjectSpool], Counter[str], int] | MapdbError:
    """The blocks of a group of a source's tiles on a worker (:func:`~mapdb.build.tiles.tile_blocks_spool`), and
    how many were cut.  An error is returned, not raised (:func:`_task_error`)."""
    try:
        spool, cut = tile_blocks_spool(tiles, labels, gap, bbox, group)
        return (*_on_earth_only([spool], Counter()), cut)
    except Exception as exc:
        return _task_error(path, "forming blocks", exc)


def _task_error(path: Path, doing: str, exc: Exception) -> MapdbError:
    """A task's error as the one-line error the build raises, naming the source.

    Returned by the task rather than raised: a task that raises is logged by its Dask worker, with a traceback,
    on the command's stderr, where a bad source must give one line.
    """
    if isinstance(exc, MapdbError):
        return exc
    detail = " ".join(str(exc).split())[:200] or exc.__class__.__name__
    return SourceError(f"{path}: {doing} failed on a Dask worker ({exc.__class__.__name__}: {detail})")


def _paying_jobs(sources: Sequence[str | Path], jobs: int | None, least: int, say: Progress) -> int | None:
    """``jobs``, or None (read here) when the sources besides the largest add up to less than ``least`` bytes and
    no OSM extract is large enough to be read in halves (:data:`SPLIT_OSM_BYTES`)."""
    if jobs is None:
        return None
    sizes = sorted(Path(p).stat().st_size if Path(p).is_file() else 0 for p in sources)
    beside = sum(sizes[:-1])
    if beside >= least:
        return jobs
    if jobs >= 2 and any(source_kind(p) == "osm" and _size(Path(p)) >= SPLIT_OSM_BYTES for p in sources):
        return jobs  # a large extract's halves are read at once
    say(f"--jobs {jobs}: reading here, in one process: the sources besides the largest add up to "
        f"{beside / 1e6:,.1f} MB, less than the {least / 1e6:,.0f} MB from which workers pay")
    return None
