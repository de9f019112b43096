"""A disk-backed lost-in-space quad index: built in bounded memory, opened in milliseconds, memory-mapped.

The whole-map :class:`~mapdb.match.fast.QuadIndex` keeps every quad's complex coordinates and labels and
a cKDTree in memory, built at the first query (1M objects: 250 s, 13.8 GB).  This index holds the same
quads (:func:`~mapdb.match.fast.neighbour_quads` with the same number of neighbours, the same canonical
order and invariants from :func:`~mapdb.match.fast.canonical_quads`) in a sidecar file ``MAP.qidx``
beside the map (``monaco.mapdb`` -> ``monaco.mapdb.qidx``); the format is in ``docs/index_format.md``.

How a quad is stored
    A quad is an *anchor* object and a triple of its ``K`` nearest neighbours (the neighbour table,
    ``K`` object ids per object, is in the file), so it costs a 4-byte anchor id and a 1-byte triple
    number instead of four ids; it is kept once, at the smallest-id member whose neighbours hold the
    other three (checked against the neighbour table, so chunks of anchors need no coordination).
    Object ids are positions in ``MetaMap.all()`` (pages in page order); their quantized positions are
    in the file too, so that ids resolve to map metres without decoding pages.

How quads are found (geometric hashing)
    The four invariants of each label combination are cut into a grid of cells of side ``c`` (one ``c``
    per label combination, chosen at build time from a sample so that a quad's cell holds about
    ``target_occupancy`` other quads); quads are sorted by ``(label combination, cell)`` and a directory
    of the non-empty cells gives each one's range.  Each quad also keeps its position inside its cell
    to 1/256 of ``c`` (4 bytes): bounds on its distance to a query without reading its coordinates.
    A lookup enumerates the cells its ball overlaps (at most 3^4), finds them in the memory-mapped
    directory (a fence of every 512th key, read when opening, names the one page to search), drops
    the candidates whose lower bound exceeds the radius or the query's k-th smallest upper bound
    (they cannot be among its ``k`` nearest), recomputes the others' exact invariants from the
    coordinate table with ``canonical_quads`` (bit-identical to the in-memory index's) and keeps those
    within the radius, the ``k`` nearest per query.

    **The lookup radius is clamped to the cell size** of the query's label combination: a ball wider
    than a cell would cover many cells, and where ``c`` is smaller than the radius the quads are dense
    enough that the ``k`` nearest usually lie within ``c`` anyway (``c`` is chosen so that a ball of
    radius ``c`` around a quad holds about five times ``target_occupancy`` others, and the matcher keeps
    at most 16 hits per lookup).  :meth:`StoredQuadIndex.cell_size` tells the clamp.

Safety
    Nothing in the file is executed (a JSON header, fixed-size little-endian arrays); every count and
    length is checked against the file size and the format's bounds when the file is opened; every
    section is checksummed in 4 KiB blocks (CRC-32), each block checked the first time a lookup reads
    it (:meth:`StoredQuadIndex.verify` checks all); ids and ranges read from the file are checked
    before use, and a lookup's memory is bounded whatever the file says.  A lookup asks the kernel for
    all the pages it is about to read at once (``MADV_WILLNEED``), so on a cold file it waits for a few
    rounds of parallel reads (5M objects: about 0.6 s for an image's lookups) rather than for each page
    fault in turn (2 s).  The header records the map's header CRC-32, file size, object count and
    labels: an index is refused for any other map.

Building (:func:`build_index`) reads the map page by page, finds every object's neighbours in one
cKDTree, samples quads to choose the cells and the sort buckets, then generates all quads in chunks
of anchors (in ``workers`` processes), writes them to bucket files by key range, sorts each bucket in
memory and writes the final file beside the map under a temporary name, renamed at the end.
"""

from __future__ import annotations

import concurrent.futures
import glob
import json
import math
import mmap
import multiprocessing
import os
import shutil
import struct
import tempfile
import time
import zlib
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .. import __version__
from ..errors import MapdbIOError, MapFormatError, MapVersionError, reading
from ..outputs import atomic_path, check_outputs
from ..store import MAGIC as MAP_MAGIC
from ..store import MetaMap, open_map
from .quads import canonical_quads, label_keys, nearest_others

__all__ = [
    "INDEX_SUFFIX",
    "StoredQuadIndex",
    "build_index",
    "index_path",
    "map_identity",
    "open_index",
]

INDEX_MAGIC = b"\x89MAPDBQX"
INDEX_VERSION = 1
INDEX_SUFFIX = ".qidx"
# magic | u16 version | u16 flags | u64 header offset | u32 header length | u32 header CRC-32 | u32 CRC-32 of
# the 28 bytes before it.  The JSON header is written last, at the end of the file, since it holds the
# section sizes and checksums.
_PREFIX = struct.Struct("<8sHHQII")
_PREFIX_SIZE = _PREFIX.size + 4
_MAP_PREFIX = struct.Struct("<8sHHI")  # the map file's own prefix (mapdb.store), for its header CRC
_MAX_HEADER = 16 << 20
_ALIGN = 4096
_BLOCK_BITS = 12
BLOCK = 1 << _BLOCK_BITS  # checksum block of every section: a page, what a lookup's first read of it costs
_SUB = 256  # positions inside a cell, per invariant
_CELL_LADDER = 0.5 * 2.0 ** (-np.arange(12) / 2.0)  # 0.5 .. 0.011: cell sides tried per label combination
_MAX_NEIGHBOURS = 12  # C(12, 3) = 220 triples fit in one byte
_SAMPLE_QUADS = 2_000_000  # quads sampled to choose cells and buckets
_BUCKET_QUADS = 8_000_000  # quads sorted at once (about 40 bytes each while sorting)
_CHUNK_ANCHORS = 16_384  # anchors per task of quad generation (~600k quads, 20 bytes each in the result)
_BLOCK_ANCHORS = 1024  # anchors whose quads are generated at once
_BOUND_MARGIN = 0.05  # in 1/256ths of a cell: far above float32 rounding of positions below 2^16
_LOOKUP_CANDIDATES = 1 << 20  # candidates handled at once by a lookup: bounds its memory
_SECTIONS = {  # name: dtype
    "coords": "<i4",
    "neighbours": "<u4",
    "anchor": "<u4",
    "triple": "u1",
    "sub": "u1",
    "dir_key": "<u8",
    "dir_start": None,  # _start_dtype: 4 bytes while quads number fewer than 2^32
    "fence": "<u8",  # every _FENCE-th cell key: the page of dir_key to search, read once when opening
}
_FENCE = BLOCK // 8  # cell keys per page of dir_key
_STEPS = np.array(np.meshgrid(*[[-1, 0, 1]] * 4, indexing="ij")).reshape(4, -1).T  # the 81 neighbour cells
_RECORD = np.dtype([("key", "<u8"), ("anchor", "<u4"), ("triple", "u1"), ("sub", "u1", (4,))])


def _start_dtype(quads: int) -> str:
    return "<u4" if quads < 2**32 else "<u8"


def index_path(map_path: str | os.PathLike[str]) -> Path:
    """The sidecar index of a map file: ``MAP`` + ``.qidx`` (``andorra.mapdb`` -> ``andorra.mapdb.qidx``)."""
    return Path(os.fspath(map_path) + INDEX_SUFFIX)


def map_identity(map_: MetaMap) -> dict[str, Any]:
    """What an index records of its map: header CRC-32, file size, object count, quantum, labels.

    The header CRC-32 covers the header and, through its ``directory_crc32``, every page's CRC-32, so a
    rewritten map (or another map of the same size) does not pass for the indexed one.
    """
    where = str(map_.path)
    with reading(where, "map file"), open(map_.path, "rb") as f:
        head = f.read(_MAP_PREFIX.size)
        if len(head) < _MAP_PREFIX.size or not head.startswith(MAP_MAGIC):
            raise MapFormatError(f"{where}: not a mapdb map (bad magic number)")
        header_len = _MAP_PREFIX.unpack(head)[3]
        f.seek(_MAP_PREFIX.size + header_len)
        tail = f.read(4)
        size = os.fstat(f.fileno()).st_size
    if len(tail) < 4:
        raise MapFormatError(f"{where}: truncated map file (header runs past the end)")
    return {
        "header_crc32": struct.unpack("<I", tail)[0],
        "file_size": size,
        "count": len(map_),
        "quantum": float(map_.quantum),
        "labels": list(map_.labels),
    }


def _triples(k: int) -> np.ndarray:
    return np.array(list(combinations(range(k), 3)), dtype=np.int64).reshape(-1, 3)


def _key_layout(n_labels: int) -> tuple[int, int]:
    """Bits of the label combination and of each invariant's cell in a 64-bit key."""
    label_bits = max(1, (max(n_labels, 1) ** 4 - 1).bit_length())
    return label_bits, (64 - label_bits) // 4


def _cells(inv: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell coordinates (int64) and position inside the cell (uint8, 1/256ths) of invariants ``(m, 4)``.

    Invariants lie in [-1, 1] (``A``, ``B`` are the most distant pair), so ``t + 1`` is >= 0 and cells
    count from 0; the ladder's smallest cell keeps the largest coordinate far below ``2 ** bits``.
    """
    s = (inv + 1.0) / cell[:, None]
    k = np.floor(s)
    sub = np.clip(np.floor((s - k) * _SUB), 0, _SUB - 1).astype(np.uint8)
    return np.maximum(k, 0).astype(np.int64), sub


def _keys(label_key: np.ndarray, cells: np.ndarray, bits: int) -> np.ndarray:
    key = label_key.astype(np.uint64)
    for j in range(4):
        key = (key << np.uint64(bits)) | cells[:, j].astype(np.uint64)
    return key


# --------------------------------------------------------------------------------------------- building

# Arrays of the build shared with forked worker processes (read-only, inherited copy-on-write).
_SHARED: dict[str, Any] = {}


def _neighbour_table(xy: np.ndarray, k: int, workers: int) -> np.ndarray:
    """Each object's ``k`` nearest other objects (uint32 ids, nearest first), as neighbour_quads finds them.

    The same cKDTree over the same points and the same search (:func:`~mapdb.match.quads.nearest_others`)
    as :func:`~mapdb.match.quads.neighbour_quads`, so the quads built from this table are that function's
    (``tests/test_stored_index.py`` checks it); queried in chunks to bound memory.
    """
    n = len(xy)
    tree = cKDTree(xy)
    table = np.empty((n, k), np.uint32)
    step = 1 << 18
    for lo in range(0, n, step):
        ids = np.arange(lo, min(n, lo + step))
        table[ids] = nearest_others(tree, xy, ids, k, workers)
    return table


def _chunk_quads(lo: int, hi: int, anchors: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """The quads anchored at objects ``lo..hi`` (or at ``anchors``), each kept at one anchor only.

    Returns anchor ids, triple numbers, canonical invariants ``(m, 4)`` and label-combination keys.
    """
    table, z, label, n_labels = _SHARED["neighbours"], _SHARED["z"], _SHARED["label"], _SHARED["n_labels"]
    k = table.shape[1]
    triples = _triples(k)
    a = np.arange(lo, hi, dtype=np.int64) if anchors is None else anchors.astype(np.int64)
    t = len(triples)
    anchor = np.repeat(a, t)
    triple = np.tile(np.arange(t, dtype=np.int64), a.size)
    members = np.empty((anchor.size, 4), np.int64)
    members[:, 0] = anchor
    members[:, 1:] = table[a][:, triples].reshape(-1, 3)
    # A quad reached from several of its members is kept at the smallest-id one whose neighbours hold
    # the other three: drop it here when a smaller member generates it too.
    keep = np.ones(anchor.size, bool)
    for j in (1, 2, 3):
        m = members[:, j]
        rows = np.flatnonzero(keep & (m < anchor))
        if not rows.size:
            continue
        theirs = table[m[rows]]
        others = members[rows][:, [i for i in range(4) if i != j]]
        generates = np.ones(rows.size, bool)
        for col in range(3):
            generates &= (theirs == others[:, col : col + 1]).any(axis=1)
        keep[rows[generates]] = False
    anchor, triple, members = anchor[keep], triple[keep], members[keep]
    # Four objects on one spot have no frame (QuadIndex drops them too).
    zq = z[members]
    ok = np.abs(zq - zq[:, :1]).max(axis=1) > 0.0
    anchor, triple, members = anchor[ok], triple[ok], members[ok]
    # Canonical order and invariants from the quad's ids in ascending order, as QuadIndex computes them.
    members.sort(axis=1)
    order, inv, _ = canonical_quads(z[members])
    ids = np.take_along_axis(members, order, axis=1)
    lk = np.rint(label_keys(label[ids], n_labels)).astype(np.int64)
    return anchor, triple, inv, lk


def _chunk_records(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Final records of a chunk of anchors, grouped by sort bucket; the bucket sizes; label keys present."""
    parts = []
    # Blocks of a few thousand anchors keep the arrays of quad generation in the CPU caches (1.5x faster).
    for a in range(lo, hi, _BLOCK_ANCHORS):
        anchor, triple, inv, lk = _chunk_quads(a, min(hi, a + _BLOCK_ANCHORS))
        cells, sub = _cells(inv, _cell_for(lk, _SHARED["combo_keys"], _SHARED["combo_cell"]))
        rec = np.empty(anchor.size, _RECORD)
        rec["key"] = _keys(lk, cells, _SHARED["bits"])
        rec["anchor"] = anchor
        rec["triple"] = triple
        rec["sub"] = sub
        parts.append((rec, lk))
    rec = np.concatenate([p[0] for p in parts])
    bucket = np.searchsorted(_SHARED["splitters"], rec["key"], side="right")
    order = np.argsort(bucket, kind="stable")
    counts = np.bincount(bucket, minlength=_SHARED["splitters"].size + 1)
    return rec[order], counts, np.unique(np.concatenate([p[1] for p in parts]))


def _sort_bucket(path: str, _: int) -> tuple[np.ndarray, ...]:
    """A bucket file's quads sorted by key (then deleted): anchors, triples, positions in cells, and its cells'
    keys, first quads (relative to the bucket) and largest size."""
    rec = np.fromfile(path, dtype=_RECORD)
    os.unlink(path)
    if not rec.size:
        empty = np.zeros(0, np.int64)
        return np.zeros(0, "<u4"), np.zeros(0, "u1"), np.zeros((0, 4), "u1"), np.zeros(0, "<u8"), empty, 0
    rec = rec[np.argsort(rec["key"])]  # deterministic: the chunks came in anchor order
    key = rec["key"]
    first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    longest = int(np.diff(np.append(first, key.size)).max())
    return (np.ascontiguousarray(rec["anchor"]), np.ascontiguousarray(rec["triple"]), np.ascontiguousarray(rec["sub"]),
            key[first], first, longest)


def _cell_for(lk: np.ndarray, combo_keys: np.ndarray, combo_cell: np.ndarray) -> np.ndarray:
    """Cell side of each label-combination key: its chosen one, the ladder's largest for one not sampled."""
    cell = np.full(lk.size, _CELL_LADDER[0])
    if combo_keys.size:
        pos = np.minimum(np.searchsorted(combo_keys, lk), combo_keys.size - 1)
        known = combo_keys[pos] == lk
        cell[known] = combo_cell[pos[known]]
    return cell


def _choose_cells(inv: np.ndarray, lk: np.ndarray, rate: float, target: float) -> tuple[np.ndarray, np.ndarray]:
    """Per label combination in the sample, the largest ladder cell whose occupancy is at most ``target``.

    Occupancy is the number of other quads in a quad's own cell, averaged over quads:
    ``sum n (n - 1) / N`` over cells, estimated from a sample taken at ``rate`` as
    ``sum s (s - 1) / (rate * S)``.
    """
    combos, combo_of, size = np.unique(lk, return_inverse=True, return_counts=True)
    chosen = np.full(combos.size, _CELL_LADDER[-1])
    settled = np.zeros(combos.size, bool)
    for c in _CELL_LADDER:
        # One integer per (combination, cell): cell coordinates stay below 2 / c + 1 < 2^11.
        cells = np.floor((inv + 1.0) / c).astype(np.int64)
        key = combo_of.astype(np.int64) << 44
        for j in range(4):
            key |= cells[:, j] << (11 * j)
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        # sum over cells of s (s - 1): each sampled quad counts the others in its cell
        pairs = np.bincount(combo_of, weights=counts[inverse] - 1.0, minlength=combos.size)
        occupancy = pairs / (rate * size)
        fits = ~settled & (occupancy <= target)
        chosen[fits] = c
        settled |= fits
    return combos, chosen


def build_index(
    map_path: str | os.PathLike[str],
    output: str | os.PathLike[str] | None = None,
    *,
    neighbours: int = 8,
    target_occupancy: float = 32.0,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Build the lost-in-space quad index of a map file and write it atomically.

    Parameters
    ----------
    map_path : path
        A ``.mapdb`` file.
    output : path, optional
        The index file; default :func:`index_path` of the map (``MAP.qidx``).
    neighbours : int
        Neighbours per anchor (``FastOptions.map_neighbours``; 3 to 12).
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
        ``output``, ``objects``, ``quads``, ``cells``, ``bytes``, ``seconds``.

    Raises
    ------
    MapFormatError, MapdbIOError
        If the map cannot be read or the index cannot be written.
    OutputClashError
        If ``output`` is the map itself.
    ValueError
        If ``neighbours`` or ``target_occupancy`` is out of range.
    """
    if not 3 <= neighbours <= _MAX_NEIGHBOURS:
        raise ValueError(f"neighbours must be in [3, {_MAX_NEIGHBOURS}], got {neighbours}")
    if not target_occupancy > 0:
        raise ValueError(f"target_occupancy must be > 0, got {target_occupancy}")
    start = time.perf_counter()

    def say(message: str) -> None:
        if progress is not None:
            progress(f"[{time.perf_counter() - start:7.1f} s] {message}")

    workers = max(1, workers if workers is not None else min(2, len(os.sched_getaffinity(0))))
    output = Path(index_path(map_path) if output is None else output)
    check_outputs([output], [map_path])
    with open_map(map_path) as m:
        identity = map_identity(m)
        objects = m.all()
        labels = tuple(m.labels)
        quantum = float(m.quantum)
    n = len(objects)
    qx = np.rint(objects.x / quantum).astype(np.int64)
    qy = np.rint(objects.y / quantum).astype(np.int64)
    origin = (int(qx.min()), int(qy.min())) if n else (0, 0)
    if n and max(int(qx.max()) - origin[0], int(qy.max()) - origin[1]) >= 2**31:
        raise MapFormatError(f"{map_path}: the map spans more than 2^31 quanta: too wide for an index")
    if n >= 2**32:
        raise MapFormatError(f"{map_path}: {n} objects: an index holds fewer than 2^32")
    coords = np.column_stack([qx - origin[0], qy - origin[1]]).astype(np.int32)
    k = min(neighbours, n - 1)
    xy = np.column_stack([objects.x, objects.y])
    z = objects.x + 1j * objects.y
    label = objects.label.astype(np.int64)
    del objects, qx, qy
    label_bits, bits = _key_layout(len(labels))

    if k >= 3:
        say(f"finding {k} neighbours of {n} objects ...")
        table = _neighbour_table(xy, k, workers)
    else:
        table = np.zeros((n, max(k, 0)), np.uint32)
    del xy
    _SHARED.clear()
    _SHARED.update(neighbours=table, z=z, label=label, n_labels=len(labels), bits=bits)

    workdir = _work_directory(output)
    try:
        with atomic_path(output) as tmp:
            summary = _write(tmp, workdir, n, k, coords, table, identity, origin, label_bits, bits,
                             target_occupancy, workers, say)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
        _SHARED.clear()
    summary.update(output=str(output), objects=n, bytes=output.stat().st_size,
                   seconds=round(time.perf_counter() - start, 3))
    return summary


def _work_directory(output: Path) -> Path:
    """A new directory beside the output for the sort buckets (17 bytes a quad), after removing the ones
    that builds of this output killed before they could clean up (named with their process id)."""
    parent = Path(os.path.realpath(output)).parent
    parent.mkdir(parents=True, exist_ok=True)
    prefix = f".{output.name[:100]}."
    for old in parent.glob(f"{glob.escape(prefix)}*.build"):
        pid = old.name[len(prefix) :].split(".")[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}.", suffix=".build", dir=parent))


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # someone else's process, or unknown: keep its files
        return True
    return True


def _pool(workers: int) -> concurrent.futures.Executor | None:
    if workers <= 1:
        return None
    return concurrent.futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"))


def _map_chunks(pool, workers: int, fn, ranges: list[tuple[int, int]]) -> Iterator[Any]:
    """``fn(lo, hi)`` over ranges, in order, in the pool's processes (at most a few chunks in flight)."""
    if pool is None:
        for lo, hi in ranges:
            yield fn(lo, hi)
        return
    ahead = 2 * workers  # bounded look-ahead keeps finished chunks from piling up in memory
    futures: list[concurrent.futures.Future] = []
    for lo, hi in ranges:
        futures.append(pool.submit(fn, lo, hi))
        if len(futures) > ahead:
            yield futures.pop(0).result()
    for f in futures:
        yield f.result()


def _write(tmp: Path, workdir: Path, n: int, k: int, coords: np.ndarray, table: np.ndarray,
           identity: dict, origin: tuple[int, int], label_bits: int, bits: int, target: float, workers: int,
           say: Callable[[str], None]) -> dict[str, Any]:
    n_triples = len(_triples(k)) if k >= 3 else 0
    ranges = [(lo, min(n, lo + _CHUNK_ANCHORS)) for lo in range(0, n, _CHUNK_ANCHORS)] if n_triples else []

    # 1. A sample of anchors chooses each label combination's cell and the sort buckets.
    expected = n * n_triples * 0.65  # about 35 of 56 quads per anchor survive de-duplication (k = 8)
    rate = min(1.0, _SAMPLE_QUADS / max(expected, 1.0))
    if n_triples:
        rng = np.random.default_rng(0)
        sample_anchors = np.flatnonzero(rng.random(n) < rate) if rate < 1.0 else np.arange(n)
        parts = [_chunk_quads(0, 0, sample_anchors[i : i + _BLOCK_ANCHORS])
                 for i in range(0, sample_anchors.size, _BLOCK_ANCHORS)]
        s_inv = np.concatenate([p[2] for p in parts]) if parts else np.zeros((0, 4))
        s_lk = np.concatenate([p[3] for p in parts]) if parts else np.zeros(0, np.int64)
        del parts
    else:
        s_inv, s_lk = np.zeros((0, 4)), np.zeros(0, np.int64)
    combo_keys, combo_cell = _choose_cells(s_inv, s_lk, rate, target)
    say(f"sampled {s_lk.size} quads ({rate:.3g} of the anchors): {combo_keys.size} label combinations, "
        f"cells {combo_cell.min(initial=1):.3g}..{combo_cell.max(initial=0):.3g}")
    estimate = s_lk.size / rate
    n_buckets = max(1, math.ceil(estimate / _BUCKET_QUADS))
    if s_lk.size:
        s_cells, _ = _cells(s_inv, _cell_for(s_lk, combo_keys, combo_cell))
        s_keys = np.sort(_keys(s_lk, s_cells, bits))
        splitters = s_keys[(np.arange(1, n_buckets) * s_keys.size) // n_buckets]
    else:
        splitters = np.zeros(0, np.uint64)
    del s_inv, s_lk
    _SHARED.update(combo_keys=combo_keys, combo_cell=combo_cell, splitters=splitters)

    # 2. Every quad, generated chunk by chunk, goes to the bucket file of its key range.
    say(f"generating quads of {n} anchors in {len(ranges)} chunks ({workers} processes) ...")
    files = [open(workdir / f"bucket{b:04d}", "wb") for b in range(splitters.size + 1)]  # noqa: SIM115
    sizes = np.zeros(len(files), np.int64)
    present: set[int] = set()
    pool = _pool(workers)
    try:
        for rec, counts, lks in _map_chunks(pool, workers, _chunk_records, ranges):
            ends = np.cumsum(counts)
            for b in np.flatnonzero(counts):
                files[b].write(rec[ends[b] - counts[b] : ends[b]].tobytes())
            sizes += counts
            present.update(lks.tolist())
        for f in files:
            f.close()
        return _write_sorted(tmp, workdir, pool, workers, n, k, coords, table, identity, origin, label_bits, bits,
                             target, combo_keys, combo_cell, len(files), sizes, present, say)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        for f in files:
            f.close()


def _write_sorted(tmp: Path, workdir: Path, pool, workers: int, n: int, k: int, coords: np.ndarray,
                  table: np.ndarray, identity: dict, origin: tuple[int, int], label_bits: int, bits: int,
                  target: float, combo_keys: np.ndarray, combo_cell: np.ndarray, n_buckets: int,
                  sizes: np.ndarray, present: set[int], say: Callable[[str], None]) -> dict[str, Any]:
    """Sort the bucket files (in the pool's processes), then write every section, the checksums, the header."""
    q = int(sizes.sum())
    used = np.array(sorted(present), np.int64)
    cell_of_used = _cell_for(used, combo_keys, combo_cell)

    # 3. Sections at fixed offsets: quads sorted bucket by bucket, the cell directory after them.
    layout: dict[str, dict[str, Any]] = {}
    offset = _ALIGN

    def place(name: str, dtype: str, shape: tuple[int, ...]) -> None:
        nonlocal offset
        length = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        layout[name] = {"offset": offset, "length": length, "dtype": dtype, "shape": list(shape)}
        offset += -(-length // _ALIGN) * _ALIGN

    place("coords", "<i4", (n, 2))
    place("neighbours", "<u4", (n, k if k >= 3 else 0))
    place("anchor", "<u4", (q,))
    place("triple", "u1", (q,))
    place("sub", "u1", (q, 4))
    say(f"sorting {q} quads in {n_buckets} buckets ...")
    max_cell = 0
    n_cells = 0
    with open(tmp, "r+b") as out, open(workdir / "dir_key", "wb") as dk, open(workdir / "dir_start", "wb") as ds:
        fd = out.fileno()
        _pwrite_all(fd, coords.tobytes(), layout["coords"]["offset"])
        _pwrite_all(fd, np.ascontiguousarray(table[:, : layout["neighbours"]["shape"][1]]).tobytes(),
                    layout["neighbours"]["offset"])
        done = 0
        paths = [str(workdir / f"bucket{b:04d}") for b in range(n_buckets)]
        for anchor, triple, sub, keys, first, longest in _map_chunks(pool, workers, _sort_bucket,
                                                                     [(p, 0) for p in paths]):
            for name, data, itemsize in (("anchor", anchor, 4), ("triple", triple, 1), ("sub", sub, 4)):
                _pwrite_all(fd, data.tobytes(), layout[name]["offset"] + done * itemsize)
            max_cell = max(max_cell, longest)
            n_cells += first.size
            dk.write(keys.tobytes())
            ds.write((first + done).astype(_start_dtype(q)).tobytes())
            done += anchor.size
        ds.write(np.array([q], _start_dtype(q)).tobytes())
    place("dir_key", "<u8", (n_cells,))
    place("dir_start", _start_dtype(q), (n_cells + 1,))
    fence = np.array(np.memmap(workdir / "dir_key", "<u8", "r")[::_FENCE]) if n_cells else np.zeros(0, "<u8")
    place("fence", "<u8", (fence.size,))
    with open(tmp, "r+b") as out:
        for name in ("dir_key", "dir_start"):
            out.seek(layout[name]["offset"])
            with open(workdir / name, "rb") as src:
                shutil.copyfileobj(src, out, 16 << 20)
        _pwrite_all(out.fileno(), fence.tobytes(), layout["fence"]["offset"])

    # 4. Checksums of every 4 KiB block, the header at the end, the prefix last.
    say("checksumming ...")
    crcs = []
    with open(tmp, "rb") as f:
        for name in _SECTIONS:
            sec = layout[name]
            sec["first_block"] = sum(len(c) for c in crcs)
            crcs.append(_block_crcs(f, sec["offset"], sec["length"]))
    crc_table = np.concatenate(crcs).astype("<u4") if crcs else np.zeros(0, "<u4")
    place("crc", "<u4", (crc_table.size,))
    header = {
        "format": "mapdb-quad-index",
        "format_version": INDEX_VERSION,
        "map": identity,
        "origin": list(origin),
        "objects": n,
        "neighbours": k if k >= 3 else 0,
        "quads": q,
        "cells": n_cells,
        "max_cell": max_cell,
        "key_label_bits": label_bits,
        "key_cell_bits": bits,
        "sub_cells": _SUB,
        "block_size": BLOCK,
        "target_occupancy": target,
        "combos": [[int(c), float(s)] for c, s in zip(used.tolist(), cell_of_used.tolist(), strict=True)],
        "sections": layout,
        "crc_crc32": zlib.crc32(crc_table.tobytes()),
        "software": f"mapdb {__version__}",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    header_bytes = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    with open(tmp, "r+b") as out:
        fd = out.fileno()
        _pwrite_all(fd, crc_table.tobytes(), layout["crc"]["offset"])
        _pwrite_all(fd, header_bytes, offset)
        prefix = _PREFIX.pack(INDEX_MAGIC, INDEX_VERSION, 0, offset, len(header_bytes), zlib.crc32(header_bytes))
        _pwrite_all(fd, prefix + struct.pack("<I", zlib.crc32(prefix)), 0)
        os.ftruncate(fd, offset + len(header_bytes))
    return {"quads": q, "cells": n_cells, "max_cell": max_cell, "neighbours": header["neighbours"]}


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        written = os.pwrite(fd, view, offset)
        view, offset = view[written:], offset + written


def _block_crcs(f, offset: int, length: int) -> np.ndarray:
    out = np.zeros(-(-length // BLOCK), np.uint32)
    f.seek(offset)
    done = 0
    step = 4096 * BLOCK
    while done < length:
        chunk = f.read(min(step, length - done))
        if not chunk:
            raise MapdbIOError(f"{f.name}: could not read back what was written")
        view = memoryview(chunk)
        for i in range(0, len(chunk), BLOCK):
            out[(done + i) // BLOCK] = zlib.crc32(view[i : i + BLOCK])
        done += len(chunk)
    return out


# --------------------------------------------------------------------------------------------- reading


class _Section:
    """One memory-mapped array of the file; each 4 KiB block's CRC-32 is checked the first time it is read."""

    def __init__(self, name: str, array: np.ndarray, crcs: np.ndarray, where: str,
                 mapping: mmap.mmap | None = None, offset: int = 0) -> None:
        self.mapping, self.offset = mapping, offset
        self.name = name
        self.array = array
        self.crcs = crcs
        self.where = where
        self.raw = array.reshape(-1).view(np.uint8) if array.size else np.zeros(0, np.uint8)
        self.row_bytes = max(1, int(np.prod(array.shape[1:], dtype=np.int64)) * array.itemsize)
        self.checked = np.zeros(crcs.size, bool)
        self.all_checked = crcs.size == 0

    def _check(self, blocks: np.ndarray) -> None:
        todo = np.unique(blocks[~self.checked[blocks]])
        if todo.size > 1:
            self._prefetch(todo)
        for b in todo.tolist():
            data = self.raw[b * BLOCK : (b + 1) * BLOCK]
            if zlib.crc32(data) != int(self.crcs[b]):
                raise MapFormatError(f"{self.where}: {self.name} block {b} checksum mismatch (file is corrupt)")
            self.checked[b] = True
        if todo.size and self.checked.all():
            self.all_checked = True

    def _prefetch(self, blocks: np.ndarray) -> None:
        """Have the kernel read these blocks now, together: a cold lookup then waits for one round of reads
        in parallel, not for one page fault after another."""
        if self.mapping is None or not hasattr(mmap, "MADV_WILLNEED"):
            return
        cut = np.flatnonzero(np.diff(blocks) != 1) + 1
        first, last = blocks[np.r_[0, cut]], blocks[np.r_[cut - 1, blocks.size - 1]]
        end = len(self.mapping)
        try:
            for a, b in zip(first.tolist(), last.tolist(), strict=True):
                start = self.offset + a * BLOCK
                self.mapping.madvise(mmap.MADV_WILLNEED, start, min((b + 1 - a) * BLOCK, end - start))
        except OSError:  # pages larger than a block, say: reading on demand is correct, only slower
            pass

    def rows(self, index: np.ndarray) -> np.ndarray:
        """``array[index]`` (``index`` already known to be in range), its blocks checked."""
        if not self.all_checked and index.size:
            first = (index.astype(np.int64) * self.row_bytes) >> _BLOCK_BITS
            self._check(first)
            if BLOCK % self.row_bytes:
                self._check(((index.astype(np.int64) + 1) * self.row_bytes - 1) >> _BLOCK_BITS)
        return self.array[index]

    def check_ranges(self, start: np.ndarray, stop: np.ndarray) -> None:
        """Check the blocks of the rows ``start[i] .. stop[i] - 1`` (non-empty ranges, already known in range).

        Cheaper than checking each row of a range as it is read: a range lies in one or two blocks.
        """
        if self.all_checked or not start.size:
            return
        b0 = (start.astype(np.int64) * self.row_bytes) >> _BLOCK_BITS
        b1 = (stop.astype(np.int64) * self.row_bytes - 1) >> _BLOCK_BITS
        span = b1 - b0 + 1
        self._check(np.repeat(b0, span) + np.arange(int(span.sum())) - np.repeat(np.cumsum(span) - span, span))

    def verify(self) -> None:
        self._check(np.arange(self.crcs.size))


class StoredQuadIndex:
    """A quad index file opened for lookups (memory-mapped; use :func:`open_index` or :meth:`for_map`).

    Attributes
    ----------
    path : Path
    labels : tuple of str
        The map's label names: label codes in lookups index into them.
    neighbours : int
        Neighbours per anchor the quads were built with.
    n_objects, n_quads, n_cells : int
    quantum : float
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        where = str(self.path)
        with reading(where, "quad index"):
            f = open(self.path, "rb")  # noqa: SIM115 - closed below once mapped and the small sections read
        try:
            try:
                size = os.fstat(f.fileno()).st_size
                header = self._read_header(f, size, where)
                self._mmap = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else None
                if self._mmap is not None and hasattr(mmap, "MADV_RANDOM"):
                    # Lookups read scattered pages: no read-ahead around each (a cold lookup reads what it needs).
                    self._mmap.madvise(mmap.MADV_RANDOM)
            except OSError as exc:
                raise MapdbIOError(f"{where}: cannot read quad index ({exc.strerror or exc})") from None
            try:
                self._setup(header, size, where, f.fileno())
            except BaseException as exc:
                self.close()
                if isinstance(exc, MapFormatError) or not isinstance(
                        exc, LookupError | TypeError | ValueError | OverflowError | AttributeError):
                    raise
                raise MapFormatError(f"{where}: header is not valid quad index metadata") from None
        finally:
            f.close()

    @staticmethod
    def _read_header(f, size: int, where: str) -> dict[str, Any]:
        head = f.read(_PREFIX_SIZE)
        if len(head) < 8 or not head.startswith(INDEX_MAGIC):
            raise MapFormatError(f"{where}: not a mapdb quad index (bad magic number)")
        if len(head) < _PREFIX_SIZE:
            raise MapFormatError(f"{where}: truncated quad index")
        _, version, _flags, h_off, h_len, h_crc = _PREFIX.unpack_from(head)
        if zlib.crc32(head[: _PREFIX.size]) != struct.unpack_from("<I", head, _PREFIX.size)[0]:
            raise MapFormatError(f"{where}: quad index prefix checksum mismatch (file is corrupt)")
        if version > INDEX_VERSION:
            raise MapVersionError(f"{where}: written by a newer quad index format (version {version}); "
                                  f"this mapdb {__version__} reads up to version {INDEX_VERSION}")
        if h_len > _MAX_HEADER or h_off < _PREFIX_SIZE or h_off + h_len != size:
            raise MapFormatError(f"{where}: truncated quad index ({size} bytes; its header says "
                                 f"{h_off + h_len})")
        f.seek(h_off)
        raw = f.read(h_len)
        if len(raw) != h_len or zlib.crc32(raw) != h_crc:
            raise MapFormatError(f"{where}: quad index header checksum mismatch (file is corrupt)")
        try:
            header = json.loads(raw.decode("utf-8"))
        except (ValueError, RecursionError):  # RecursionError: nesting deeper than the parser's stack
            raise MapFormatError(f"{where}: quad index header is not JSON") from None
        if not isinstance(header, dict) or header.get("format") != "mapdb-quad-index":
            raise MapFormatError(f"{where}: not a mapdb quad index (header)")
        header["_header_offset"] = h_off
        return header

    def _setup(self, h: dict[str, Any], size: int, where: str, fd: int) -> None:
        self.where = where
        self.header = h
        self.identity = dict(h["map"])
        self.labels = tuple(str(s) for s in self.identity["labels"])
        self.quantum = float(self.identity["quantum"])
        n, k, q, d = (int(h[key]) for key in ("objects", "neighbours", "quads", "cells"))
        self.max_cell = int(h["max_cell"])
        self.origin = tuple(int(v) for v in h["origin"])
        label_bits, bits = int(h["key_label_bits"]), int(h["key_cell_bits"])
        if (label_bits, bits) != _key_layout(len(self.labels)) or int(h["sub_cells"]) != _SUB or \
                int(h["block_size"]) != BLOCK:
            raise MapFormatError(f"{where}: unsupported key layout")
        n_triples = len(_triples(k)) if k >= 3 else 0
        if not (0 <= n < 2**32 and n == int(self.identity["count"]) and (k == 0 or 3 <= k <= _MAX_NEIGHBOURS)
                and 0 <= q <= n * n_triples and 0 <= d <= q and 0 <= self.max_cell <= q
                and (d > 0) == (q > 0) and (self.max_cell > 0) == (q > 0)):
            raise MapFormatError(f"{where}: quad index counts out of range (objects {n}, neighbours {k}, "
                                 f"quads {q}, cells {d})")
        self.n_objects, self.neighbours, self.n_quads, self.n_cells = n, k, q, d
        self._bits = bits
        self._triples = _triples(k) if k >= 3 else np.zeros((0, 3), np.int64)
        combos = h["combos"]
        if not isinstance(combos, list) or len(combos) > max(q, 0):
            raise MapFormatError(f"{where}: quad index label combinations out of range")
        ck = np.array([int(c[0]) for c in combos], np.int64)
        cc = np.array([float(c[1]) for c in combos], np.float64)
        if ck.size and (np.any(np.diff(ck) <= 0) or ck[0] < 0 or ck[-1] >= max(len(self.labels), 1) ** 4
                        or not np.all((cc >= _CELL_LADDER[-1] * 0.999) & (cc <= _CELL_LADDER[0] * 1.001))):
            raise MapFormatError(f"{where}: quad index label combinations out of range")
        self._combo_keys, self._combo_cell = ck, cc
        shapes = {"coords": (n, 2), "neighbours": (n, k), "anchor": (q,), "triple": (q,), "sub": (q, 4),
                  "dir_key": (d,), "dir_start": (d + 1,), "fence": (-(-d // _FENCE),)}
        layout = h["sections"]
        end = int(h["_header_offset"])
        spans = []
        total_blocks = 0
        dtypes = {name: _SECTIONS[name] or _start_dtype(q) for name in shapes}
        for name, shape in shapes.items():
            sec = layout[name]
            dtype = dtypes[name]
            length = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
            if sec["dtype"] != dtype or [int(v) for v in sec["shape"]] != list(shape) or int(sec["length"]) != length:
                raise MapFormatError(f"{where}: quad index section {name} does not match the counts")
            total_blocks += -(-length // BLOCK)
            spans.append((int(sec["offset"]), length, name))
        crc_sec = layout["crc"]
        if crc_sec["dtype"] != "<u4" or [int(v) for v in crc_sec["shape"]] != [total_blocks] or \
                int(crc_sec["length"]) != 4 * total_blocks:
            raise MapFormatError(f"{where}: quad index checksum table does not match the sections")
        spans.append((int(crc_sec["offset"]), 4 * total_blocks, "crc"))
        spans.sort()
        at = _PREFIX_SIZE
        for off, length, name in spans:
            if off < at or off + length > end:
                raise MapFormatError(f"{where}: truncated or overlapping quad index section {name}")
            at = off + length
        # The small sections are read with one system call each (the mapping reads a page per fault).
        crc_table = np.frombuffer(_pread(fd, int(crc_sec["offset"]), 4 * total_blocks, where), "<u4")
        if zlib.crc32(crc_table) != int(h["crc_crc32"]):
            raise MapFormatError(f"{where}: quad index checksum table mismatch (file is corrupt)")
        self._sections: dict[str, _Section] = {}
        for name, shape in shapes.items():
            sec = layout[name]
            first = int(sec["first_block"])
            blocks = -(-int(sec["length"]) // BLOCK)
            if first < 0 or first + blocks > total_blocks:
                raise MapFormatError(f"{where}: quad index checksum table does not match the sections")
            array = self._array(dtypes[name], int(sec["offset"]), shape)
            self._sections[name] = _Section(name, array, crc_table[first : first + blocks], where, self._mmap,
                                            int(sec["offset"]))
        fence = self._sections.pop("fence")
        raw = _pread(fd, int(layout["fence"]["offset"]), int(layout["fence"]["length"]), where)
        for b in range(fence.crcs.size):
            if zlib.crc32(raw[b * BLOCK : (b + 1) * BLOCK]) != int(fence.crcs[b]):
                raise MapFormatError(f"{where}: fence block {b} checksum mismatch (file is corrupt)")
        self._fence = np.frombuffer(raw, "<u8")

    def _array(self, dtype: str, offset: int, shape: tuple[int, ...]) -> np.ndarray:
        count = int(np.prod(shape, dtype=np.int64))
        if self._mmap is None or count == 0:
            return np.zeros(shape, dtype)
        return np.frombuffer(self._mmap, dtype=dtype, count=count, offset=offset).reshape(shape)

    # ------------------------------------------------------------------------------------------ public

    @classmethod
    def for_map(cls, map_: MetaMap, path: str | os.PathLike[str] | None = None) -> StoredQuadIndex | None:
        """The index beside an open map file (``path``, default :func:`index_path`), or None if there is none.

        A map held in memory (no file) has none.

        Raises
        ------
        MapFormatError
            If the index is damaged or was built for another map (or another version of this one).
        """
        if path is None and getattr(map_, "path", None) is None:
            return None
        path = index_path(map_.path) if path is None else Path(path)
        if not path.exists():
            return None
        return open_index(path, map_)

    def check_map(self, map_: MetaMap) -> None:
        """Refuse (:class:`MapFormatError`) unless this index was built from exactly this map file."""
        mine, theirs = self.identity, map_identity(map_)
        for key in ("header_crc32", "file_size", "count", "labels"):
            if mine.get(key) != theirs[key]:
                raise MapFormatError(f"{self.where}: quad index of another map (or of an earlier version of "
                                     f"{map_.path}: its {key.replace('_', ' ')} differs); rebuild it with "
                                     f"`mapdb index {map_.path}`")

    def close(self) -> None:
        """Release the mapping (arrays returned by lookups are copies and stay valid)."""
        self._sections = {}
        if self._mmap is not None:
            try:
                self._mmap.close()
            except BufferError:  # a caller still holds a view: the mapping goes with it
                pass
            self._mmap = None

    def __enter__(self) -> StoredQuadIndex:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def verify(self) -> None:
        """Check every block of every section (lookups check only the blocks they read)."""
        for section in self._sections.values():
            section.verify()

    def cell_size(self, labels: np.ndarray) -> np.ndarray:
        """The cell side (the largest effective lookup radius) for label 4-tuples ``(m, 4)``; 0 if absent."""
        labels = np.asarray(labels, np.int64).reshape(-1, 4)
        pos, present = self._combo(labels)
        return np.where(present, self._combo_cell[np.minimum(pos, max(self._combo_cell.size - 1, 0))]
                        if self._combo_cell.size else 0.0, 0.0)

    def _combo(self, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lk = np.rint(label_keys(labels, len(self.labels))).astype(np.int64) if len(labels) else np.zeros(0, np.int64)
        if not self._combo_keys.size:
            return np.zeros(lk.size, np.int64), np.zeros(lk.size, bool)
        pos = np.searchsorted(self._combo_keys, lk)
        ok = pos < self._combo_keys.size
        ok[ok] = self._combo_keys[pos[ok]] == lk[ok]
        return pos, ok

    def coordinates(self, ids: np.ndarray) -> np.ndarray:
        """Map positions (complex ``x + iy``, map metres, as ``MetaMap.all()`` gives them) of object ids."""
        ids = np.asarray(ids, np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= self.n_objects):
            raise IndexError(f"object ids must be in [0, {self.n_objects})")
        c = self._sections["coords"].rows(ids.reshape(-1)).astype(np.int64)
        x = (c[:, 0] + self.origin[0]) * self.quantum
        y = (c[:, 1] + self.origin[1]) * self.quantum
        return (x + 1j * y).reshape(ids.shape)

    def lookup(
        self,
        invariants: np.ndarray,
        labels: np.ndarray,
        radius: np.ndarray | float,
        k: int,
        *,
        return_distance: bool = False,
    ) -> tuple[np.ndarray, ...]:
        """Map quads near query quads: at most ``k`` per query, nearest first, within its radius.

        Parameters
        ----------
        invariants : (m, 4) float
            ``Re t_C, Im t_C, Re t_D, Im t_D`` of each query quad in canonical order
            (:func:`~mapdb.match.fast.canonical_quads`).
        labels : (m, 4) int
            Label codes (into :attr:`labels`) of the query's ``A, B, C, D``.
        radius : (m,) float or float
            Lookup radius in invariant space, clamped to :meth:`cell_size` of the query's labels.
        k : int
            Most hits per query.

        Returns
        -------
        row : (h,) int64
            The query row of each hit (ascending; within a row, nearest first).
        ids : (h, 4) int64
            The hit's object ids in canonical order ``A, B, C, D``; :meth:`coordinates` gives their
            positions.
        distance : (h,) float64
            Only with ``return_distance``: Euclidean distance of the invariants.

        Raises
        ------
        MapFormatError
            If a block read is corrupt or the file's ranges and ids are inconsistent.
        """
        inv = np.asarray(invariants, np.float64).reshape(-1, 4)
        labels = np.asarray(labels, np.int64).reshape(-1, 4)
        m = len(inv)
        radius = np.broadcast_to(np.asarray(radius, np.float64), (m,))
        if len(labels) != m:
            raise ValueError(f"{m} invariant rows but {len(labels)} label rows")
        empty = (np.zeros(0, np.int64), np.zeros((0, 4), np.int64)) + ((np.zeros(0),) if return_distance else ())
        if m == 0 or k <= 0 or self.n_quads == 0:
            return empty
        pos, present = self._combo(labels)
        present &= np.isfinite(inv).all(axis=1) & np.isfinite(radius) & (radius >= 0)
        present &= ((labels >= 0) & (labels < len(self.labels))).all(axis=1)
        rows = np.flatnonzero(present)
        if not rows.size:
            return empty
        cell = self._combo_cell[pos[rows]]
        q = inv[rows]
        r = np.minimum(radius[rows], cell)
        lo, _ = _cells(q - r[:, None], cell)
        hi, _ = _cells(q + r[:, None], cell)
        base, _ = _cells(q, cell)
        top = (1 << self._bits) - 1
        cand = base[:, None, :] + _STEPS[None, :, :]
        inside = ((cand >= lo[:, None, :]) & (cand <= hi[:, None, :]) & (cand >= 0) & (cand <= top)).all(axis=2)
        which, s = np.nonzero(inside)
        lk = self._combo_keys[pos[rows]]
        keys = _keys(lk[which], cand[which, s], self._bits)
        # Cells present in the directory, and their quad ranges.
        dir_start = self._sections["dir_start"]
        at = self._find_cells(keys)
        found = at >= 0
        which, at = which[found], at[found]
        start = dir_start.rows(at).astype(np.int64)
        stop = dir_start.rows(at + 1).astype(np.int64)
        length = stop - start
        if length.size and (start.min() < 0 or stop.max() > self.n_quads or length.min() < 1
                            or length.max() > self.max_cell):
            raise MapFormatError(f"{self.where}: quad index directory out of range (file is corrupt)")
        cell_coords = cand[which, s[found]] if which.size else np.zeros((0, 4), np.int64)
        for name in ("sub", "anchor", "triple"):  # read below range by range
            self._sections[name].check_ranges(start, stop)
        best = _Best(k)
        for piece, idx in _pieces(start, length, _LOOKUP_CANDIDATES):
            self._candidates(which[piece], idx, cell_coords[piece], q, r, cell, k, best)
        row, ids, dist = best.result()
        row = rows[row]
        return (row, ids, dist) if return_distance else (row, ids)

    def _find_cells(self, keys: np.ndarray) -> np.ndarray:
        """Directory positions of cell keys (-1 where absent).

        The fence (every 512th key, in memory) names the one page of ``dir_key`` that can hold each key;
        a binary search inside it reads that page only: a cold lookup costs a page read per cell, not one
        per step of a search over the whole directory.
        """
        d = self.n_cells
        if not d or not keys.size:
            return np.full(keys.size, -1, np.int64)
        page = np.searchsorted(self._fence, keys, side="right") - 1
        ok = page >= 0
        lo = np.maximum(page, 0) * _FENCE
        hi = np.minimum(lo + _FENCE, d)
        dir_key = self._sections["dir_key"]
        dir_key.check_ranges(lo[ok], hi[ok])
        for _ in range(_FENCE.bit_length()):  # leftmost position in [lo, hi) whose key is >= the key
            mid = (lo + hi) // 2
            active = lo < hi
            go = active & (dir_key.array[np.minimum(mid, d - 1)] < keys)
            lo = np.where(go, mid + 1, lo)
            hi = np.where(active & ~go, mid, hi)
        found = ok & (lo < d)
        found[found] = dir_key.array[lo[found]] == keys[found]
        return np.where(found, lo, -1)

    def _candidates(self, which: np.ndarray, idx: np.ndarray, cell_coords: np.ndarray, q: np.ndarray,
                    r: np.ndarray, cell: np.ndarray, k: int, best: _Best) -> None:
        """Bound, resolve and measure one batch of candidates; offer those within the radius to ``best``.

        ``which`` (the query row of each candidate) is ascending.
        """
        # Bounds of the distance from the position inside the cell, in 1/256ths of the cell: the candidate
        # lies in [p, p + 1) per invariant.  Float32 (half the memory traffic; all of a lookup's time is
        # here where cells are crowded) with a margin far above its rounding keeps the bounds safe.
        scale = _SUB / cell
        p = (cell_coords * _SUB + self._sections["sub"].array[idx]).astype(np.float32)  # blocks checked in lookup()
        d = p - ((q + 1.0) * scale[:, None]).astype(np.float32)[which]
        lower = (np.maximum(np.maximum(d, -1.0 - d), 0.0) ** 2).sum(axis=1)
        reach = (r * scale + _BOUND_MARGIN).astype(np.float32)
        near = lower <= reach[which] ** 2
        which, idx, lower, d = which[near], idx[near], lower[near], d[near]
        if not idx.size:
            return
        if np.bincount(which).max() > k:
            # Only candidates that may be among the k nearest: the k-th smallest upper bound of a query's
            # candidates bounds its k-th nearest distance.  (Where many quads crowd a cell, this spares
            # reading and measuring most of them.)
            # Upper bounds rounded up to 1/16ths in one exact integer sort key with the (ascending) row.
            upper = np.ceil(np.sqrt((np.maximum(d + 1.0, -d) ** 2).sum(axis=1)) * 16.0).astype(np.int64)
            key = (which << 24) | np.minimum(upper, (1 << 24) - 1)
            order = np.argsort(key)
            rank = np.arange(which.size) - np.searchsorted(which[order], which[order])
            kth = np.full(len(q), np.inf, np.float32)
            kth[which[order[rank == k - 1]]] = upper[order[rank == k - 1]] / 16.0 + _BOUND_MARGIN
            near = lower <= np.minimum(kth, reach)[which] ** 2
            which, idx = which[near], idx[near]
        ids, inv = self._resolve(idx, checked=True)
        dist = np.sqrt(((inv - q[which]) ** 2).sum(axis=1))
        hit = dist <= r[which]
        best.offer(which[hit], ids[hit], dist[hit])

    def _resolve(self, positions: np.ndarray, checked: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Object ids ``(m, 4)`` in canonical order and invariants of the stored quads at ``positions``.

        ``checked``: the blocks of ``anchor`` and ``triple`` holding them are known to be checked.
        """
        read = (lambda name: self._sections[name].array[positions]) if checked else \
            (lambda name: self._sections[name].rows(positions))
        anchor = read("anchor").astype(np.int64)
        triple = read("triple").astype(np.int64)
        if anchor.size and (anchor.max() >= self.n_objects or triple.max() >= len(self._triples)):
            raise MapFormatError(f"{self.where}: quad index holds an object id out of range (file is corrupt)")
        nb = self._sections["neighbours"].rows(anchor).astype(np.int64)
        members = np.empty((positions.size, 4), np.int64)
        members[:, 0] = anchor
        members[:, 1:] = np.take_along_axis(nb, self._triples[triple], axis=1)
        if members.size and members.max() >= self.n_objects:
            raise MapFormatError(f"{self.where}: quad index holds an object id out of range (file is corrupt)")
        # The canonical order from the ids in ascending order, as at build time (and as QuadIndex does).
        members.sort(axis=1)
        order, inv, _ = canonical_quads(self.coordinates(members))
        return np.take_along_axis(members, order, axis=1), inv

    def quads(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Object ids ``(m, 4)``, in canonical order, of the stored quads ``start:stop`` (in key order)."""
        stop = self.n_quads if stop is None else min(stop, self.n_quads)
        return self._resolve(np.arange(max(start, 0), max(stop, start, 0), dtype=np.int64))[0]


def _pread(fd: int, offset: int, length: int, where: str) -> bytes:
    data = os.pread(fd, length, offset) if length else b""
    if len(data) != length:
        raise MapFormatError(f"{where}: truncated quad index")
    return data


def _pieces(start: np.ndarray, length: np.ndarray, limit: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Candidate quad positions of the ranges ``start + [0, length)``, at most about ``limit`` at a time.

    Yields the range number of each candidate and its position; a range longer than ``limit`` is cut.
    """
    if not start.size:
        return
    cuts = -(-length // limit)
    seg = np.repeat(np.arange(start.size), cuts)
    part = np.arange(seg.size) - np.repeat(np.cumsum(cuts) - cuts, cuts)
    s0 = start[seg] + part * limit
    n = np.minimum(length[seg] - part * limit, limit)
    ends = np.cumsum(n)
    group = (ends - 1) // limit
    bounds = np.flatnonzero(np.diff(group)) + 1
    for sel in np.split(np.arange(seg.size), bounds):
        counts = n[sel]
        total = int(counts.sum())
        offsets = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        yield np.repeat(seg[sel], counts), np.repeat(s0[sel], counts) + offsets


class _Best:
    """The ``k`` nearest hits per query row seen so far (ties kept in the order offered)."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.size = 0

    def offer(self, row: np.ndarray, ids: np.ndarray, dist: np.ndarray) -> None:
        self.parts.append((row, ids, dist))
        self.size += row.size
        if self.size > _LOOKUP_CANDIDATES:
            self.parts = [self.result()]
            self.size = self.parts[0][0].size

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not self.parts:
            return np.zeros(0, np.int64), np.zeros((0, 4), np.int64), np.zeros(0)
        row = np.concatenate([p[0] for p in self.parts])
        ids = np.concatenate([p[1] for p in self.parts])
        dist = np.concatenate([p[2] for p in self.parts])
        order = np.lexsort((dist, row))
        row, ids, dist = row[order], ids[order], dist[order]
        first = np.flatnonzero(np.concatenate([[True], row[1:] != row[:-1]])) if row.size else np.zeros(0, np.int64)
        rank = np.arange(row.size) - np.repeat(first, np.diff(np.append(first, row.size)))
        keep = rank < self.k
        return row[keep], ids[keep], dist[keep]


def open_index(path: str | os.PathLike[str], map_: MetaMap | None = None) -> StoredQuadIndex:
    """Open a quad index file; with ``map_``, refuse it unless it was built from that map file.

    Raises
    ------
    MapdbIOError
        If the file is missing or unreadable.
    MapFormatError
        If it is not a quad index, is truncated, fails a checksum, holds counts its size cannot hold, or
        (with ``map_``) belongs to another map.
    """
    index = StoredQuadIndex(path)
    if map_ is not None:
        try:
            index.check_map(map_)
        except BaseException:
            index.close()
            raise
    return index
