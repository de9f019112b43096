"""Building a stored quad index (:func:`build_index`): an external sort of every quad, in bounded memory.

The map is read page by page; every object's neighbours are found in one cKDTree; a sample of quads
chooses each label combination's cell and the key ranges of the sort buckets
(:mod:`~mapdb.match.index.generate`); then all quads are generated in chunks of anchors (in ``workers``
processes) and written to the bucket files by key range; each bucket is sorted in memory and written to
its place in the final file, which is written beside the map under a temporary name and renamed at the end.
The layout written is :mod:`~mapdb.match.index.layout`'s (``docs/index_format.md``).
"""

from __future__ import annotations

import concurrent.futures
import glob
import math
import multiprocessing
import os
import shutil
import tempfile
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ... import __version__
from ...errors import MapFormatError
from ...mapfile.reader import open_map
from ...objects import Objects
from ...outputs import atomic_path, check_outputs, creation_time, pid_alive
from .binding import map_identity
from .generate import (
    RECORD,
    SHARED,
    block_free_world,
    cell_for,
    choose_cells,
    chunk_records,
    neighbour_table,
    sample_quads,
    world_neighbours,
)
from .layout import (
    BLOCK,
    BLOCKS_LEFT_OUT,
    FORMAT_NAME,
    INDEX_VERSION,
    MAX_NEIGHBOURS,
    QUAD_NEIGHBOURS,
    SectionPlan,
    cell_keys,
    cells_of,
    index_path,
    key_layout,
    pwrite_all,
    triples,
    write_header,
)
from .packed import NB_BLOCK, PAGE_CELLS, directory_pages, pack_records, record_layout
from .sections import write_directory, write_objects

__all__ = ["build_index"]

_BUCKET_QUADS = 8_000_000  # quads sorted at once (about 40 bytes each while sorting)
_CHUNK_ANCHORS = 16_384  # anchors per task of quad generation (~600k quads, 20 bytes each in the result)


@dataclass
class _Build:
    """What the steps of one build share: the map's arrays, the key layout, where to write, how."""

    n: int  # objects
    k: int  # the matcher's neighbours per anchor the quads serve (below 3: no quads)
    ku: int  # nearest neighbours the quads are drawn from (at most k)
    coords: np.ndarray  # (n, 2) int32 quanta relative to origin
    table: np.ndarray  # (n, ku) uint32 neighbour ids
    identity: dict[str, Any]
    origin: tuple[int, int]
    label_bits: int
    bits: int
    target: float
    workers: int
    say: Callable[[str], None]
    tmp: Path = Path()
    workdir: Path = Path()
    pool: concurrent.futures.Executor | None = None
    blocks_left_out: bool = False  # a map with blocks, indexed without them (header key ``blocks``)


def build_index(map_path: str | os.PathLike[str], output: str | os.PathLike[str] | None = None, *,
                neighbours: int = 8, target_occupancy: float = 32.0, workers: int | None = None,
                progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Build the lost-in-space quad index of a map file and write it atomically.

    Parameters
    ----------
    map_path : path
        A ``.mapdb`` file.
    output : path, optional
        The index file; default :func:`~mapdb.match.index.layout.index_path` of the map (``MAP.qidx``).
    neighbours : int
        The matcher's neighbours per anchor the index serves (``FastOptions.map_neighbours``; 3 to 12): the
        quads are each object with the triples ``QUAD_TRIPLES`` of its ``min(neighbours, QUAD_NEIGHBOURS)`` (5)
        nearest, a subset of the quads of its ``neighbours`` nearest.
    target_occupancy : float
        Other quads expected in a quad's cell: sets each label combination's cell size (the lookup
        radius is clamped to it).  Larger: fewer clamped lookups, more candidates per lookup.
    workers : int, optional
        Processes generating quads (default: up to 2, the CPUs available).
    progress : callable, optional
        Receives one-line progress messages.

    Returns
    -------
    dict
        ``output``, ``objects``, ``quads``, ``cells``, ``max_cell``, ``neighbours``, ``quad_neighbours``,
        ``bytes``, ``seconds``.

    Raises
    ------
    MapFormatError, MapdbIOError
        If the map cannot be read or the index cannot be written.
    OutputClashError
        If ``output`` is the map itself.
    ValueError
        If ``neighbours`` or ``target_occupancy`` is out of range.
    """
    if not 3 <= neighbours <= MAX_NEIGHBOURS:
        raise ValueError(f"neighbours must be in [3, {MAX_NEIGHBOURS}], got {neighbours}")
    if not target_occupancy > 0:
        raise ValueError(f"target_occupancy must be > 0, got {target_occupancy}")
    start = time.perf_counter()
    say = _timed(progress, start)
    workers = max(1, workers if workers is not None else min(2, len(os.sched_getaffinity(0))))
    out = Path(index_path(map_path) if output is None else output)
    check_outputs([out], [map_path])
    build = _read_map(map_path, neighbours, target_occupancy, workers, say)
    build.workdir = _work_directory(out)
    try:
        with atomic_path(out) as tmp:
            build.tmp = tmp
            summary = _write(build)
    finally:
        shutil.rmtree(build.workdir, ignore_errors=True)
        SHARED.clear()
    summary.update(output=str(out), objects=build.n, bytes=out.stat().st_size,
                   seconds=round(time.perf_counter() - start, 3))
    return summary


def _timed(progress: Callable[[str], None] | None, start: float) -> Callable[[str], None]:
    """``progress`` with the seconds since ``start`` before each message (nothing without ``progress``)."""

    def say(message: str) -> None:
        if progress is not None:
            progress(f"[{time.perf_counter() - start:7.1f} s] {message}")

    return say


def _read_map(map_path: str | os.PathLike[str], neighbours: int, target: float, workers: int,
              say: Callable[[str], None]) -> _Build:
    """Read the map, quantize its positions, find every object's neighbours; share what workers need."""
    map_ = open_map(os.fspath(map_path))
    with map_:
        identity = map_identity(map_)
        objects = map_.all()
        n_labels = len(map_.labels)
        quantum = float(map_.quantum)
        # A map with blocks: quads of the map without them, the world point images are matched in
        # (mapdb.match.mapobjects.blocks_view); a map without blocks is indexed as before, byte for byte.
        world = block_free_world(map_, objects)
    n = len(objects)
    coords, origin = _quantize(objects, quantum, tuple(identity["origin"]), map_path)
    k = min(neighbours, (n if world is None else int(world.sum())) - 1)
    ku = min(k, QUAD_NEIGHBOURS)
    xy = np.column_stack([objects.x, objects.y])
    z = objects.x + 1j * objects.y
    label = objects.label.astype(np.int64)
    del objects
    label_bits, bits = key_layout(n_labels)
    if k >= 3:
        say(f"finding {ku} neighbours of {n} objects ...")
        table = neighbour_table(xy, ku, workers) if world is None else world_neighbours(xy, world, ku, workers)
    else:
        table = np.zeros((n, 0), np.uint32)
    del xy
    SHARED.clear()
    SHARED.update(neighbours=table, z=z, label=label, n_labels=n_labels, bits=bits, world=world)
    build = _Build(n, k, ku, coords, table, identity, origin, label_bits, bits, target, workers, say)
    build.blocks_left_out = world is not None
    return build


def _quantize(objects: Objects, quantum: float, origin: tuple[int, ...],
              map_path: str | os.PathLike[str]) -> tuple[np.ndarray, tuple[int, int]]:
    """Positions in quanta relative to ``origin``, the smallest page origin (int32 ``(n, 2)``), and the origin.

    A map's pages are tight boxes, so the origin is its smallest position in quanta and the coordinates
    are at least 0 (checked: the reader relies on it).
    """
    n = len(objects)
    qx = np.rint(objects.x / quantum).astype(np.int64) - origin[0]
    qy = np.rint(objects.y / quantum).astype(np.int64) - origin[1]
    if n and min(int(qx.min()), int(qy.min())) < 0:
        raise MapFormatError(f"{map_path}: an object lies outside its map page: the map is damaged")
    if n and max(int(qx.max()), int(qy.max())) >= 2**31:
        raise MapFormatError(f"{map_path}: the map spans more than 2^31 quanta: too wide for an index")
    if n >= 2**32:
        raise MapFormatError(f"{map_path}: {n} objects: an index holds fewer than 2^32")
    return np.column_stack([qx, qy]).astype(np.int32), (int(origin[0]), int(origin[1]))


def _work_directory(output: Path) -> Path:
    """A new directory beside the output for the sort buckets (17 bytes a quad), after removing the ones
    that builds of this output killed before they could clean up (named with their process id)."""
    parent = Path(os.path.realpath(output)).parent
    parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{output.name[:100]}."
    for old in parent.glob(f"{glob.escape(prefix)}*.build"):
        pid = old.name[len(prefix) :].split(".")[0]
        if pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}.", suffix=".build", dir=parent))


def _pool(workers: int) -> concurrent.futures.Executor | None:
    if workers <= 1:
        return None
    return concurrent.futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"))


def _map_chunks(pool: concurrent.futures.Executor | None, workers: int, fn: Callable[..., Any],
                ranges: Sequence[tuple[Any, int]]) -> Iterator[Any]:
    """``fn(lo, hi)`` over ranges, in order, in the pool's processes (at most a few chunks in flight)."""
    if pool is None:
        for lo, hi in ranges:
            yield fn(lo, hi)
        return
    ahead = 2 * workers  # bounded look-ahead keeps finished chunks from piling up in memory
    futures: list[concurrent.futures.Future[Any]] = []
    for lo, hi in ranges:
        futures.append(pool.submit(fn, lo, hi))
        if len(futures) > ahead:
            yield futures.pop(0).result()
    for f in futures:
        yield f.result()


def _write(b: _Build) -> dict[str, Any]:
    """Choose cells and buckets from a sample, generate every quad into its bucket, then write the file."""
    n_triples = len(triples(b.ku)) if b.k >= 3 else 0
    SHARED.update(sub_cells=1 << record_layout(b.n, n_triples)[1])
    ranges = [(lo, min(b.n, lo + _CHUNK_ANCHORS)) for lo in range(0, b.n, _CHUNK_ANCHORS)] if n_triples else []

    # 1. A sample of anchors chooses each label combination's cell and the sort buckets.
    s_inv, s_lk, rate = sample_quads(b.n, n_triples)
    combo_keys, combo_cell = choose_cells(s_inv, s_lk, rate, b.target)
    b.say(f"sampled {s_lk.size} quads ({rate:.3g} of the anchors): {combo_keys.size} label combinations, "
          f"cells {combo_cell.min(initial=1):.3g}..{combo_cell.max(initial=0):.3g}")
    splitters = _splitters(s_inv, s_lk, rate, combo_keys, combo_cell, b.bits)
    del s_inv, s_lk
    SHARED.update(combo_keys=combo_keys, combo_cell=combo_cell, splitters=splitters)

    # 2. Every quad, generated chunk by chunk, goes to the bucket file of its key range.
    b.say(f"generating quads of {b.n} anchors in {len(ranges)} chunks ({b.workers} processes) ...")
    b.pool = _pool(b.workers)  # forked now that SHARED holds everything the workers read
    try:
        sizes, present = _scatter(b, ranges, splitters.size + 1)
        return _write_sorted(b, combo_keys, combo_cell, sizes, present)
    finally:
        if b.pool is not None:
            b.pool.shutdown(cancel_futures=True)


def _splitters(s_inv: np.ndarray, s_lk: np.ndarray, rate: float, combo_keys: np.ndarray, combo_cell: np.ndarray,
               bits: int) -> np.ndarray:
    """Keys that cut the quads into buckets of about ``_BUCKET_QUADS``: quantiles of the sample's keys."""
    estimate = s_lk.size / rate
    n_buckets = max(1, math.ceil(estimate / _BUCKET_QUADS))
    if not s_lk.size:
        return np.zeros(0, np.uint64)
    s_cells, _ = cells_of(s_inv, cell_for(s_lk, combo_keys, combo_cell), 1)
    s_keys = np.sort(cell_keys(s_lk, s_cells, bits))
    return s_keys[(np.arange(1, n_buckets) * s_keys.size) // n_buckets]


def _scatter(b: _Build, ranges: list[tuple[int, int]], n_buckets: int) -> tuple[np.ndarray, set[int]]:
    """Generate every quad into the bucket file of its key range; the buckets' sizes, the label keys seen."""
    files = [open(b.workdir / f"bucket{i:04d}", "wb") for i in range(n_buckets)]  # noqa: SIM115
    sizes = np.zeros(len(files), np.int64)
    present: set[int] = set()
    try:
        for rec, counts, lks in _map_chunks(b.pool, b.workers, chunk_records, ranges):
            ends = np.cumsum(counts)
            for i in np.flatnonzero(counts):
                files[i].write(rec[ends[i] - counts[i] : ends[i]].tobytes())
            sizes += counts
            present.update(lks.tolist())
    finally:
        for f in files:
            f.close()
    return sizes, present


def _sort_bucket(path: str, _: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A bucket file's quads sorted by key (then deleted): anchors, triples, positions in cells, and its cells'
    keys and quad counts."""
    rec = np.fromfile(path, dtype=RECORD)
    os.unlink(path)
    rec = rec[np.argsort(rec["key"], kind="stable")]  # deterministic: the chunks came in anchor order
    key = rec["key"]
    first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]])) if key.size else np.zeros(0, np.int64)
    return (rec["anchor"], rec["triple"], np.ascontiguousarray(rec["sub"]), key[first],
            np.diff(np.append(first, key.size)))


def _write_sorted(b: _Build, combo_keys: np.ndarray, combo_cell: np.ndarray, sizes: np.ndarray,
                  present: set[int]) -> dict[str, Any]:
    """Sort the bucket files (in the pool's processes), then write every section, the checksums, the header."""
    q = int(sizes.sum())
    # 3. Sections one after another: coordinates, packed neighbours, quad records in key order, the directory.
    layout = SectionPlan()
    co_bytes, nb_bytes = write_objects(b.tmp, b.workdir, layout, b.coords, b.table)
    rb, sb, tb = record_layout(b.n, len(triples(b.ku)) if b.k >= 3 else 0)
    layout.place("quads", "u1", (q, rb))
    b.say(f"sorting {q} quads in {sizes.size} buckets ...")
    keys, counts = _write_quads(b, layout, (rb, sb, tb), sizes.size)
    used = np.array(sorted(present), np.int64)
    dir_bytes, pages = write_directory(b.tmp, layout, directory_pages(keys, counts, used,
                                                                       cell_for(used, combo_keys, combo_cell), b.bits))

    # 4. Checksums of every 4 KiB block, the header at the end, the prefix last.
    b.say("checksumming ...")
    crc_table = layout.checksums(b.tmp)
    layout.place("crc", "<u4", (crc_table.size,))
    summary = {"objects": b.n, "neighbours": b.k if b.k >= 3 else 0, "quad_neighbours": b.ku if b.k >= 3 else 0,
               "quads": q, "cells": int(keys.size), "pages": pages,
               "max_cell": int(counts.max(initial=0)), "nb_bytes": nb_bytes, "co_bytes": co_bytes,
               "dir_bytes": dir_bytes, "record_bytes": rb, "sub_bits": sb,
               "quad_triples": triples(b.ku if b.k >= 3 else 0).tolist()}
    header = _header(b, summary, list(zip(used.tolist(), cell_for(used, combo_keys, combo_cell).tolist(),
                                          strict=True)), layout, crc_table)
    with open(b.tmp, "r+b") as out:
        pwrite_all(out.fileno(), crc_table.tobytes(), layout["crc"]["offset"])
        write_header(out.fileno(), header, layout.offset)
    return {key: summary[key] for key in ("quads", "cells", "max_cell", "neighbours", "quad_neighbours")}


def _write_quads(b: _Build, layout: SectionPlan, record: tuple[int, int, int],
                 n_buckets: int) -> tuple[np.ndarray, np.ndarray]:
    """Write the buckets' sorted quads as records; return every cell's key and quad count, in key order."""
    keys, counts = [], []
    rb, sb, tb = record
    paths = [(str(b.workdir / f"bucket{i:04d}"), 0) for i in range(n_buckets)]
    with open(b.tmp, "r+b") as out:
        at = layout["quads"]["offset"]
        for anchor, triple, sub, cell_key, count in _map_chunks(b.pool, b.workers, _sort_bucket, paths):
            rows = pack_records(anchor, triple, sub, rb, sb, tb)
            pwrite_all(out.fileno(), rows.tobytes(), at)
            at += rows.size
            keys.append(cell_key)
            counts.append(count)
    return (np.concatenate(keys) if keys else np.zeros(0, np.uint64),
            np.concatenate(counts) if counts else np.zeros(0, np.int64))


def _header(b: _Build, counts: dict[str, int], combos: list[tuple[int, float]], layout: SectionPlan,
            crc_table: np.ndarray) -> dict[str, Any]:
    """The JSON header (``docs/index_format.md``), its keys in the order written."""
    return {
        "format": FORMAT_NAME,
        "format_version": INDEX_VERSION,
        "map": b.identity,  # what binds the index to its map (origin included): docs/index_format.md
        **counts,
        "key_label_bits": b.label_bits,
        "key_cell_bits": b.bits,
        "page_cells": PAGE_CELLS,
        "nb_block": NB_BLOCK,
        "block_size": BLOCK,
        "target_occupancy": b.target,
        "combos": [[int(c), float(s)] for c, s in combos],
        "sections": layout.sections,
        "crc_crc32": zlib.crc32(crc_table.tobytes()),
        "software": f"mapdb {__version__}",
        "created": creation_time(),
        **({"blocks": BLOCKS_LEFT_OUT} if b.blocks_left_out else {}),
    }
