"""Peak memory and throughput of ``mapdb build`` on big OSM inputs made by replicating the real extracts.

The three extracts in ``../shared/data/osm`` are copied over and over into one PBF, each copy shifted to a
cell of its own (about 0.4 x 0.25 degrees, around 2-10 E, 44-48 N) with its node, way and relation ids
renumbered, so that every object is a real one; the file is written here, in a temporary directory, by a
small PBF encoder (pyosmium's writer takes about 7 us a node: 15 minutes for a gigabyte), and deleted at
the end.  Then, each in a fresh process whose resident memory is sampled from ``/proc`` every 0.2 s:

* ``mapdb build`` of the current tree ("after"), and of the commit given by ``--baseline`` ("before",
  extracted with ``git archive`` and run from there) where that is feasible (up to ``--before-max-mb``);
* a bare pyosmium pass over the same file that only locates nodes and assembles areas (the floor).

Peak RSS is the kernel's high-water mark (VmHWM): anonymous memory plus the resident pages of mapped
files.  Also shown, the peak of anonymous memory alone (sampled), since a file node index's pages are page
cache that the kernel can reclaim.  The last lines give the ratio of the two builds' peaks (the country-scale
issue asks for at most 1.5x from about 100 MB to 1 GB of input, and under 2 GB).  Run::

    python benchmarks/build_memory.py [--gigabytes 1.0] [--baseline HEAD] [--keep DIR] [--stages]

With ``--stages`` each input is built once more in a process that samples its own resident memory and cuts
the time into the build's stages by its progress messages (the OSM pass, roundabouts and intersections, the
automatic CRS, projection, writing), and the peak of each stage is printed.
"""

from __future__ import annotations

import argparse
import math
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import osmium

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "osm"


def _varint(v: int) -> bytes:
    out = bytearray()
    while v > 0x7F:
        out.append((v & 0x7F) | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def _zz(v: int) -> int:
    return (v << 1) ^ (v >> 63)


def _varints(values: np.ndarray) -> bytes:
    """Protobuf varints of non-negative integers, vectorised."""
    v = np.asarray(values, np.uint64)
    if v.size == 0:
        return b""
    nbytes = np.ones(v.size, np.int64)
    for j in range(1, 10):
        nbytes += (v >> np.uint64(7 * j)) > 0
    ends = np.cumsum(nbytes)
    out = np.zeros(int(ends[-1]), np.uint8)
    starts = ends - nbytes
    for j in range(int(nbytes.max())):
        has = nbytes > j
        byte = (v[has] >> np.uint64(7 * j)) & np.uint64(0x7F)
        more = (nbytes[has] > j + 1).astype(np.uint64) << np.uint64(7)
        out[starts[has] + j] = (byte | more).astype(np.uint8)
    return out.tobytes()


def _zzs(values: np.ndarray) -> np.ndarray:
    v = np.asarray(values, np.int64)
    return ((v << 1) ^ (v >> 63)).astype(np.uint64)


def _field(number: int, payload: bytes) -> bytes:
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def _vfield(number: int, value: int) -> bytes:
    return _varint(number << 3) + _varint(value)


@dataclass
class _Source:
    node_id: np.ndarray
    node_x: np.ndarray
    node_y: np.ndarray
    node_tags: dict[int, list[tuple[str, str]]]  # index -> tags
    ways: list[tuple[int, list[int], list[tuple[str, str]]]] = field(default_factory=list)
    relations: list[tuple[int, list[tuple[str, int, str]], list[tuple[str, str]]]] = field(default_factory=list)
    box: tuple[float, float, float, float] = (0, 0, 0, 0)


def _load(path: Path) -> _Source:
    ids, xs, ys, tags = [], [], [], {}
    ways, relations = [], []
    for obj in osmium.FileProcessor(str(path)):
        kind = obj.type_str()
        if kind == "n":
            if obj.tags:
                tags[len(ids)] = [(t.k, t.v) for t in obj.tags]
            ids.append(obj.id)
            xs.append(obj.location.x)
            ys.append(obj.location.y)
        elif kind == "w":
            ways.append((obj.id, [n.ref for n in obj.nodes], [(t.k, t.v) for t in obj.tags]))
        elif kind == "r":
            relations.append((obj.id, [(m.type, m.ref, m.role) for m in obj.members], [(t.k, t.v) for t in obj.tags]))
    x, y = np.asarray(xs, np.int64), np.asarray(ys, np.int64)
    box = (x.min() / 1e7, y.min() / 1e7, x.max() / 1e7, y.max() / 1e7)
    return _Source(np.asarray(ids, np.int64), x, y, tags, ways, relations, box)


class _Renumber:
    """Old id -> 1-based rank among this source's ids of that type (unknown ids after the known)."""

    def __init__(self, ids: np.ndarray) -> None:
        self.sorted = np.sort(ids)
        self.extra: dict[int, int] = {}

    def __call__(self, old: int) -> int:
        i = int(np.searchsorted(self.sorted, old))
        if i < self.sorted.size and self.sorted[i] == old:
            return i + 1
        return self.sorted.size + 1 + self.extra.setdefault(old, len(self.extra))

    def many(self, old: np.ndarray) -> np.ndarray:
        i = np.searchsorted(self.sorted, old)
        inside = i < self.sorted.size
        hit = np.zeros(old.size, bool)
        hit[inside] = self.sorted[i[inside]] == old[inside]
        out = i + 1
        for k in np.flatnonzero(~hit):
            out[k] = self(int(old[k]))
        return out


class _Strings:
    def __init__(self) -> None:
        self.index: dict[str, int] = {"": 0}

    def __call__(self, s: str) -> int:
        return self.index.setdefault(s, len(self.index))

    def table(self) -> bytes:
        return _field(1, b"".join(_field(1, s.encode()) for s in self.index))


def _blob(kind: str, payload: bytes, level: int) -> bytes:
    blob = _vfield(2, len(payload)) + _field(3, zlib.compress(payload, level))
    header = _field(1, kind.encode()) + _vfield(3, len(blob))
    return struct.pack(">I", len(header)) + header + blob



def _varint_parts(values: np.ndarray, lengths: np.ndarray) -> list[bytes]:
    """The varints of consecutive runs of ``values`` (run i has lengths[i] values), one bytes object a run."""
    v = np.asarray(values, np.uint64)
    nbytes = np.ones(v.size, np.int64)
    for j in range(1, 10):
        nbytes += (v >> np.uint64(7 * j)) > 0
    data = _varints(v)
    value_end = np.concatenate([[0], np.cumsum(nbytes)])
    run_end = np.concatenate([[0], np.cumsum(lengths)])
    cuts = value_end[run_end]
    return [data[a:b] for a, b in zip(cuts[:-1].tolist(), cuts[1:].tolist(), strict=True)]


class _Templates:
    """What stays the same in every copy of one source: strings, tags, deltas after each block's or way's first."""

    BLOCK = 8000

    def __init__(self, s: _Source, nodes: _Renumber, refs: list[np.ndarray]) -> None:
        self.node_blocks = []
        for start in range(0, s.node_id.size, self.BLOCK):
            stop = min(start + self.BLOCK, s.node_id.size)
            strings = _Strings()
            kv_field = b""
            if any(k in s.node_tags for k in range(start, stop)):
                kv: list[int] = []
                for k in range(start, stop):
                    for key, value in s.node_tags.get(k, ()):
                        kv += [strings(key), strings(value)]
                    kv.append(0)
                kv_field = _field(10, _varints(np.asarray(kv)))
            lat, lon = s.node_y[start:stop], s.node_x[start:stop]
            self.node_blocks.append((strings.table(), start, int(lat[0]), int(lon[0]), b"\x02" * (stop - start - 1),
                                     _varints(_zzs(np.diff(lat))), _varints(_zzs(np.diff(lon))), kv_field))
        lengths = np.asarray([r.size for r in refs], np.int64)
        flat = np.concatenate(refs) if refs else np.zeros(0, np.int64)
        deltas = np.diff(flat, prepend=0)
        firsts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        rests = _varint_parts(_zzs(np.delete(deltas, firsts[lengths > 0])), np.maximum(lengths - 1, 0))
        self.way_blocks = []
        for start in range(0, len(s.ways), self.BLOCK):
            strings = _Strings()
            ways = []
            for k in range(start, min(start + self.BLOCK, len(s.ways))):
                tags = s.ways[k][2]
                kv = b""
                if tags:
                    kv = _field(2, b"".join(_varint(strings(t[0])) for t in tags)) \
                        + _field(3, b"".join(_varint(strings(t[1])) for t in tags))
                ways.append((k, kv, int(refs[k][0]) if refs[k].size else None, rests[k]))
            self.way_blocks.append((strings.table(), ways))


class Replicator:  # noqa: D101
    """Writes ``copies`` shifted copies of the sources, nodes then ways then relations, ids renumbered."""

    def __init__(self, paths: list[Path], level: int = 6, cell: tuple[float, float] = (0.4, 0.25)) -> None:
        self.sources = [_load(p) for p in paths]
        self.level = level
        self.node_ids = [_Renumber(s.node_id) for s in self.sources]
        self.way_ids = [_Renumber(np.asarray([w[0] for w in s.ways], np.int64)) for s in self.sources]
        self.rel_ids = [_Renumber(np.asarray([r[0] for r in s.relations], np.int64)) for s in self.sources]
        # Renumber every reference once (unknown ids are registered here, before spans are fixed).
        way_refs = [[self.node_ids[i].many(np.asarray(w[1], np.int64)) for w in s.ways]
                    for i, s in enumerate(self.sources)]
        self.rel_members = [[[(t, self._ref(i, t, ref), role) for t, ref, role in r[1]] for r in s.relations]
                            for i, s in enumerate(self.sources)]
        self.templates = [_Templates(s, self.node_ids[i], way_refs[i]) for i, s in enumerate(self.sources)]
        # One copy of all sources takes this many ids of each type.
        self.span = {kind: sum(r.sorted.size + len(r.extra) + 1 for r in table)
                     for kind, table in (("n", self.node_ids), ("w", self.way_ids), ("r", self.rel_ids))}
        self.cell = cell

    def _ref(self, i: int, kind: str, ref: int) -> int:
        return {"n": self.node_ids, "w": self.way_ids, "r": self.rel_ids}[kind][i](ref)

    def _base(self, copy: int, i: int, kind: str) -> int:
        """Id offset of source i in copy ``copy`` for this type."""
        table = {"n": self.node_ids, "w": self.way_ids, "r": self.rel_ids}[kind]
        return copy * self.span[kind] + sum(r.sorted.size + len(r.extra) + 1 for r in table[:i])


    def _shift(self, copy: int, i: int, columns: int) -> tuple[int, int]:
        """Shift (1e-7 degrees) putting source i of copy ``copy`` in its own grid cell."""
        n = copy * len(self.sources) + i
        col, row = n % columns, n // columns
        box = self.sources[i].box
        lon = 2.0 + col * self.cell[0] - box[0]
        lat = 44.0 + row * self.cell[1] - box[1]
        return int(round(lon * 1e7)), int(round(lat * 1e7))

    def write(self, path: Path, copies: int) -> None:
        columns = max(1, math.ceil(math.sqrt(copies * len(self.sources) * self.cell[1] / self.cell[0])))
        with open(path, "wb") as out:
            header = _field(4, b"OsmSchema-V0.6") + _field(4, b"DenseNodes") + _field(5, b"Sort.Type_then_ID") \
                + _field(16, b"mapdb build_memory benchmark")
            out.write(_blob("OSMHeader", header, self.level))
            for copy in range(copies):
                for i in range(len(self.sources)):
                    self._write_nodes(out, copy, i, columns)
            for copy in range(copies):
                for i in range(len(self.sources)):
                    self._write_ways(out, copy, i)
            for copy in range(copies):
                for i in range(len(self.sources)):
                    self._write_relations(out, copy, i)

    def _write_nodes(self, out, copy: int, i: int, columns: int) -> None:
        dx, dy = self._shift(copy, i, columns)
        base = self._base(copy, i, "n")
        for strings, start, lat0, lon0, id_rest, lat_rest, lon_rest, kv in self.templates[i].node_blocks:
            dense = _field(1, _varint(_zz(base + start + 1)) + id_rest) \
                + _field(8, _varint(_zz(lat0 + dy)) + lat_rest) + _field(9, _varint(_zz(lon0 + dx)) + lon_rest) + kv
            out.write(_blob("OSMData", strings + _field(2, _field(2, dense)), self.level))

    def _write_ways(self, out, copy: int, i: int) -> None:
        node_base = self._base(copy, i, "n")
        way_base = self._base(copy, i, "w")
        for strings, ways in self.templates[i].way_blocks:
            group = [_field(3, _vfield(1, way_base + k + 1) + kv
                            + (b"" if first is None else _field(8, _varint(_zz(first + node_base)) + rest)))
                     for k, kv, first, rest in ways]
            out.write(_blob("OSMData", strings + _field(2, b"".join(group)), self.level))

    def _write_relations(self, out, copy: int, i: int) -> None:
        s = self.sources[i]
        if not s.relations:
            return
        kinds = {"n": 0, "w": 1, "r": 2}
        strings = _Strings()
        members = self.rel_members[i]
        lengths = np.asarray([len(m) for m in members], np.int64)
        bases = {t: self._base(copy, i, t) for t in kinds}
        flat = np.asarray([bases[t] + ref for m in members for t, ref, _ in m], np.int64)
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        deltas = np.diff(flat, prepend=0)
        deltas[starts[lengths > 0]] = flat[starts[lengths > 0]]
        memids = _varint_parts(_zzs(deltas), lengths)
        group = []
        for k, (_, _, tags) in enumerate(s.relations):
            msg = _vfield(1, bases["r"] + k + 1)
            if tags:
                msg += _field(2, b"".join(_varint(strings(t[0])) for t in tags))
                msg += _field(3, b"".join(_varint(strings(t[1])) for t in tags))
            if members[k]:
                msg += _field(8, b"".join(_varint(strings(role)) for _, _, role in members[k]))
                msg += _field(9, memids[k])
                msg += _field(10, bytes(kinds[t] for t, _, _ in members[k]))
            group.append(_field(4, msg))
        out.write(_blob("OSMData", strings.table() + _field(2, b"".join(group)), self.level))


# --------------------------------------------------------------------------------------------------
# Measuring


@dataclass
class Run:
    name: str
    seconds: float
    peak_rss_mb: float  # VmHWM
    peak_anon_mb: float  # sampled RssAnon
    objects: int | None
    ok: bool
    note: str = ""


def measure(name: str, command: list[str], env: dict[str, str] | None = None) -> Run:
    """Run ``command`` in a fresh process; wall time, VmHWM at the end and the sampled peak of RssAnon."""
    start = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    peak = {"VmHWM": 0, "RssAnon": 0}

    def sample() -> None:
        while proc.poll() is None:
            try:
                with open(f"/proc/{proc.pid}/status") as f:
                    for line in f:
                        key = line.split(":")[0]
                        if key in peak:
                            peak[key] = max(peak[key], int(line.split()[1]))
            except (OSError, ValueError):
                pass
            time.sleep(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = proc.communicate()
    seconds = time.perf_counter() - start
    sampler.join()
    objects = None
    for line in out.splitlines()[::-1]:
        if line.startswith("{"):
            import json
            objects = int(json.loads(line).get("count", 0))
            break
        if line.startswith("objects "):
            objects = int(line.split()[1])
            break
    note = "" if proc.returncode == 0 else (err.strip().splitlines() or ["?"])[-1][:100]
    return Run(name, seconds, peak["VmHWM"] / 1024, peak["RssAnon"] / 1024, objects, proc.returncode == 0, note)


BARE = """
import sys, osmium
n = 0
for _ in osmium.FileProcessor(sys.argv[1]).with_locations(sys.argv[2]).with_areas():
    n += 1
print("objects", n)
"""


# A build in this process with its resident memory (VmRSS: anonymous and mapped pages) sampled every 0.05 s,
# cut into stages by the build's own progress messages; prints the peak of each stage as JSON.
STAGES = """
import json, sys, threading, time
from mapdb.build.pipeline import build_map
MARKS = [("reading OpenStreetMap data", "the OSM pass (libosmium's reading and area assembly)"),
         ("file read in", "roundabouts and road intersections after the pass"),
         ("objects from", "checks and the automatic CRS (passes over the spooled objects)"),
         ("projecting", "projection into the map writer"), ("writing", "writing the map")]
samples, marks, done = [], [(0.0, "start-up and imports")], False
t0 = time.monotonic()
def rss():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024
def sample():
    while not done:
        samples.append((time.monotonic() - t0, rss()))
        time.sleep(0.05)
def say(message):
    for text, stage in MARKS:
        if text in message and marks[-1][1] != stage:
            marks.append((time.monotonic() - t0, stage))
threading.Thread(target=sample, daemon=True).start()
build_map([sys.argv[1]], sys.argv[2], progress=say)
done = True
time.sleep(0.1)
ends = [t for t, _ in marks[1:]] + [samples[-1][0] + 1e-9]
print(json.dumps([(stage, max([r for t, r in samples if start <= t < end] or [0.0]), end - start)
                  for (start, stage), end in zip(marks, ends)]))
"""


def stages(path: Path, out: Path) -> list[tuple[str, float, float]]:
    """Peak resident memory (MB) and duration (s) of each stage of ``mapdb build`` of ``path``."""
    import json
    run = subprocess.run([sys.executable, "-c", STAGES, str(path), str(out)], capture_output=True, text=True)
    if run.returncode:
        print(f"| (stages of {path.name} FAILED: {(run.stderr.strip().splitlines() or ['?'])[-1][:100]}) |")
        return []
    return [tuple(row) for row in json.loads(run.stdout.strip().splitlines()[-1])]


def median(runs: list[Run]) -> Run:
    return sorted(runs, key=lambda r: r.seconds)[len(runs) // 2]


def bare_pass(path: Path, index: str) -> Run:
    """The floor: every object located and every area assembled, nothing else (``index``: node index)."""
    return measure(f"bare pyosmium pass ({index})", [sys.executable, "-c", BARE, str(path), index])


# The first statements of a child process that imports the baseline's package from PYTHONPATH (a tree made by
# baseline_tree): the editable install's import hook would find the working tree first, so it is left out.
BASELINE_FIRST = ("import sys; sys.meta_path = [f for f in sys.meta_path "
                  "if '__editable__' not in type(f).__module__]; ")


def mapdb_build(name: str, sources: list[Path], out: Path, extra: list[str] = (), pythonpath: Path | None = None
                ) -> Run:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    code = "import sys; from mapdb_cli.main import cli; sys.argv[0] = 'mapdb'; cli()"
    if pythonpath is not None:  # the baseline's package is not installed: put its cli under the name mapdb_cli
        code = (BASELINE_FIRST + "import importlib; sys.modules['mapdb_cli'] = importlib.import_module('cli'); "
                "sys.argv[0] = 'mapdb'; from cli.main import cli; cli()")
    return measure(name, [sys.executable, "-c", code, "build", "-q", *map(str, sources), "-o", str(out),
                          "--overwrite", *extra], env)


def baseline_tree(commit: str, where: Path) -> Path | None:
    """The package as it was at ``commit`` (``git archive``, read-only for the working tree)."""
    try:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "mapdb", "cli"], check=True,
                                 capture_output=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    where.mkdir(parents=True, exist_ok=True)
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive, check=True)
    return where


def digest(path: Path) -> str:
    from mapdb.build.merge import content_digest
    return content_digest(path)[:12] if path.exists() else "-"


def row(run: Run, input_mb: float, bare: Run | None = None) -> str:
    rate = f"{run.objects / run.seconds:,.0f}" if run.objects and run.ok else "-"
    ratio = f"{run.seconds / bare.seconds:.2f}x" if bare and bare.ok and run.ok else ""
    status = "" if run.ok else f" FAILED: {run.note}"
    return (f"| {run.name} | {input_mb:,.0f} MB | {run.seconds:,.1f} s | {run.peak_rss_mb:,.0f} MB | "
            f"{run.peak_anon_mb:,.0f} MB | {run.objects or '-':,} | {rate} | {ratio} |{status}")


HEADER = ("| run | input | wall | peak RSS (VmHWM) | peak anonymous | objects | objects/s | vs bare pass |\n"
          "|---|---|---|---|---|---|---|---|")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--gigabytes", type=float, default=1.0, help="size of the big input (default 1.0)")
    parser.add_argument("--small-mb", type=float, default=100.0, help="size of the small input (default 100)")
    parser.add_argument("--baseline", default="HEAD", help="commit of the 'before' build (default HEAD)")
    parser.add_argument("--before-max-mb", type=float, default=150.0,
                        help="run the 'before' build only on inputs up to this size (it needs ~15 MB a MB)")
    parser.add_argument("--keep", type=Path, help="keep the generated inputs in this directory")
    parser.add_argument("--stages", action="store_true",
                        help="also build each input once more, sampling memory by stage, and print the peaks")
    args = parser.parse_args()
    extracts = sorted(DATA.glob("*.osm.pbf"))
    if not extracts:
        print(f"{DATA}: no OSM extracts (real data lives in ../shared/data beside the checkout)")
        return
    with tempfile.TemporaryDirectory(prefix="mapdb-build-memory-") as tmp_name:
        # Commands run from here: with the checkout as the current directory, ``python -c`` would import the
        # working tree's package before the baseline's.
        os.chdir(tmp_name)
        tmp = (args.keep or Path(tmp_name)).resolve()
        tmp.mkdir(parents=True, exist_ok=True)
        before = baseline_tree(args.baseline, Path(tmp_name) / "baseline")
        print(f"before: {args.baseline} ({'extracted' if before else 'not available'}); after: the working tree")
        run_all(args, extracts, tmp, before)


def run_all(args: argparse.Namespace, extracts: list[Path], tmp: Path, before: Path | None) -> None:
    replicator = Replicator(extracts)
    one_copy = tmp / "one.osm.pbf"
    replicator.write(one_copy, 1)
    per_copy = one_copy.stat().st_size
    print(HEADER)
    andorra = next(p for p in extracts if "andorra" in p.name)
    mb = andorra.stat().st_size / 1e6
    # Small runs: the median of three, in turn, as process start-up and a shared machine weigh on them.
    bare = median([bare_pass(andorra, "flex_mem") for _ in range(3)])
    print(row(bare, mb))
    print(row(median([mapdb_build("mapdb build, Andorra (after)", [andorra], tmp / "andorra.mapdb")
                      for _ in range(3)]), mb, bare))
    if before is not None:
        print(row(median([mapdb_build("mapdb build, Andorra (before)", [andorra], tmp / "andorra_before.mapdb",
                                      pythonpath=before) for _ in range(3)]), mb, bare))
    sizes = [("small", args.small_mb * 1e6), ("big", args.gigabytes * 1e9)]
    peaks: dict[str, tuple[float, float]] = {}
    breakdown: dict[str, tuple[float, list[tuple[str, float, float]]]] = {}
    for label, target in sizes:
        copies = math.ceil(target / per_copy)
        path = tmp / f"{label}.osm.pbf"
        started = time.perf_counter()
        replicator.write(path, copies)
        mb = path.stat().st_size / 1e6
        print(f"| ({label}: {copies} copies, {path.stat().st_size:,} bytes, written in "
              f"{time.perf_counter() - started:.0f} s) | | | | | | | |")
        index = "sparse_file_array" if path.stat().st_size >= (64 << 20) else "flex_mem"
        bare = bare_pass(path, index if label == "small" else "dense_file_array," + str(tmp / "bare.idx"))
        print(row(bare, mb))
        after = mapdb_build(f"mapdb build ({label}, after)", [path], tmp / f"{label}_after.mapdb")
        print(row(after, mb, bare))
        peaks[label] = (mb, after.peak_rss_mb if after.ok else math.nan)
        if args.stages:
            breakdown[label] = (mb, stages(path, tmp / f"{label}_stages.mapdb"))
        if before is not None and mb <= args.before_max_mb:
            old = mapdb_build(f"mapdb build ({label}, before)", [path], tmp / f"{label}_before.mapdb",
                              pythonpath=before)
            print(row(old, mb, bare))
            same = digest(tmp / f"{label}_before.mapdb") == digest(tmp / f"{label}_after.mapdb")
            print(f"| (before and after maps {'identical' if same else 'DIFFERENT'} but for the creation time) "
                  "| | | | | | | |")
        (tmp / "bare.idx").unlink(missing_ok=True)
        path.unlink()
    (small_mb, small), (big_mb, big) = peaks["small"], peaks["big"]
    print(f"\npeak RSS of the build (after): {big:,.0f} MB on {big_mb:,.0f} MB of input, {big / small:.2f}x the "
          f"{small:,.0f} MB on {small_mb:,.0f} MB (the country-scale issue asks for at most 1.5x and 2 GB)\n")
    if breakdown:
        print_stages(breakdown)
    jobs(extracts, tmp)


def print_stages(breakdown: dict[str, tuple[float, list[tuple[str, float, float]]]]) -> None:
    """The peak resident memory of each stage, the inputs side by side."""
    labels = list(breakdown)
    print("| stage | " + " | ".join(f"{breakdown[k][0]:,.0f} MB: peak RSS, time" for k in labels) + " |")
    print("|---|" + "---|" * len(labels))
    names = [name for name, _, _ in breakdown[labels[0]][1]]
    for name in names:
        cells = []
        for k in labels:
            found = [(peak, secs) for stage, peak, secs in breakdown[k][1] if stage == name]
            if found and not found[0][0]:  # over before the first sample (0.05 s)
                cells.append(f"(not sampled), {found[0][1]:,.2f} s")
            else:
                cells.append(f"{found[0][0]:,.0f} MB, {found[0][1]:,.1f} s" if found else "-")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print()


def jobs(extracts: list[Path], tmp: Path) -> None:
    """The three extracts with and without --jobs 2: time and whether the maps are identical."""
    one = mapdb_build("mapdb build of the 3 extracts", extracts, tmp / "three.mapdb")
    two = mapdb_build("same, --jobs 2", extracts, tmp / "three_jobs.mapdb", ["--jobs", "2"])
    size = sum(p.stat().st_size for p in extracts) / 1e6
    print(row(one, size))
    print(row(two, size))
    same = digest(tmp / "three.mapdb") == digest(tmp / "three_jobs.mapdb")
    print(f"\n--jobs 2: {one.seconds / two.seconds:.2f}x the speed of one process; maps "
          f"{'identical' if same else 'DIFFERENT'} but for the creation time")


if __name__ == "__main__":
    main()
