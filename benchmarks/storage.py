"""`mapdb bench storage` on the real extracts, and what the map's pages buy over one compressed stream.

For Monaco, Andorra and Liechtenstein (../shared/data/osm): the storage tables (as `mapdb bench storage
../shared/data/osm/*.osm.pbf` prints them).  Then reading one 1 km window, on each extract and on a synthetic
world of 1,000,000 objects (copies of the extracts, ``benchmarks/synthetic_world.py``): a freshly opened map
reads, checks and decodes only the pages that meet the window; the same sorted columns as one .xz stream
(the compressor row of the table) must be inflated whole first.  Median of 50 windows centred on random
objects.

    python benchmarks/storage.py
"""

from __future__ import annotations

import lzma
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mapdb.build.pipeline import build_map
from mapdb.evaluation.storage import format_storage, sorted_columns, storage_reports
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map

sys.path.insert(0, str(Path(__file__).resolve().parent))
from synthetic_world import synthetic_world  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "osm"
EXTRACTS = ["monaco-2021-12-03.osm.pbf", "andorra-2021-06-22.osm.pbf", "liechtenstein-2013-08-03.osm.pbf"]
WINDOW_M = 1000.0
WINDOWS = 50
WORLD_OBJECTS = 1_000_000


def window_reads(path: Path, rng: np.random.Generator) -> tuple[float, float, float, int, int]:
    """Median ms to open the map and read one window, its objects, the .xz stream's size and ms to inflate
    it, and the map's size."""
    with open_map(path) as m:
        objects, quantum, size = m.all(), m.quantum, m.file_size
    pick = rng.integers(0, len(objects), WINDOWS)
    half = WINDOW_M / 2
    cold, found = [], []
    for x, y in zip(objects.x[pick], objects.y[pick]):
        t = time.perf_counter()
        with open_map(path) as m:
            found.append(len(m.query_bbox(x - half, y - half, x + half, y + half)))
        cold.append(time.perf_counter() - t)
    packed = lzma.compress(sorted_columns(objects, quantum), preset=9 | lzma.PRESET_EXTREME)
    inflate = []
    for _ in range(min(WINDOWS, 10)):
        t = time.perf_counter()
        lzma.decompress(packed)
        inflate.append(time.perf_counter() - t)
    return float(np.median(cold)) * 1e3, float(np.median(found)), float(np.median(inflate)) * 1e3, len(packed), size


def main() -> int:
    sources = [DATA / name for name in EXTRACTS]
    if not all(s.is_file() for s in sources):
        print(f"no shared data at {DATA}: nothing to measure", file=sys.stderr)
        return 1
    result = storage_reports(sources)
    print(format_storage(result))
    print()
    print(f"One {WINDOW_M / 1000:g} km window, median of {WINDOWS}: open the map and read it, against inflating "
          "the whole .xz stream of the sorted columns")
    print(f"{'map':<16}{'objects':>10}{'map (B)':>12}{'.xz (B)':>12}{'in window':>11}{'open+window ms':>16}"
          f"{'inflate all ms':>16}")
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for source in sources:
            paths.append(Path(tmp) / (source.name.split("-")[0] + ".mapdb"))
            build_map([source], paths[-1])
        world = Path(tmp) / "world-1M.mapdb"
        write_map(world, synthetic_world(paths, WORLD_OBJECTS, seed=0))
        for path in [*paths, world]:
            cold, found, inflate, xz, size = window_reads(path, rng)
            with open_map(path) as m:
                n = len(m)
            print(f"{path.stem:<16}{n:>10,}{size:>12,}{xz:>12,}{found:>11,.0f}{cold:>16.2f}{inflate:>16.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
