"""Storage per object and radius-query latency of built maps.

Builds Monaco and Andorra (from ../shared/data/osm), exports each to GeoPackage and GeoParquet
for comparison, and times 500 m radius queries at random object positions after the map is open:
"cold" opens a fresh map for every query (every page read, checked and decoded), "warm" reuses one
open map (decoded pages cached).

    python benchmarks/store_bench.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mapdb.build.pipeline import build_map
from mapdb.mapfile.export import export_map
from mapdb.mapfile.reader import open_map

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "osm"
EXTRACTS = ["monaco-2021-12-03.osm.pbf", "andorra-2021-06-22.osm.pbf", "liechtenstein-2013-08-03.osm.pbf"]


def main() -> int:
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to measure", file=sys.stderr)
        return 1
    rng = np.random.default_rng(0)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in EXTRACTS:
            out = Path(tmp) / (name.split("-")[0] + ".mapdb")
            build_map([DATA / name], out)
            sizes = {"mapdb": out.stat().st_size}
            with open_map(out) as m:
                n = len(m)
                for suffix in (".gpkg", ".parquet"):
                    target = out.with_suffix(suffix)
                    export_map(m, target)
                    sizes[suffix] = target.stat().st_size
                objects = m.all()
                pick = rng.integers(0, n, 200)
                centres = np.c_[objects.x[pick], objects.y[pick]]
            cold, warm, found = [], [], []
            for x, y in centres:
                with open_map(out) as m:
                    t = time.perf_counter()
                    hits = m.query_radius(x, y, 500.0)
                    cold.append(time.perf_counter() - t)
                found.append(len(hits))
            with open_map(out) as m:
                for x, y in centres:
                    t = time.perf_counter()
                    m.query_radius(x, y, 500.0)
                    warm.append(time.perf_counter() - t)
            rows.append((name.split("-")[0], n, sizes, np.median(cold) * 1e3, np.median(warm) * 1e3,
                         int(np.median(found))))
    print("Storage, whole file / objects (bytes per object), quantum 0.1 m")
    print(f"{'map':<14}{'objects':>9}{'mapdb':>9}{'GeoPackage':>12}{'GeoParquet':>12}{'gpkg/mapdb':>12}")
    for name, n, sizes, *_ in rows:
        print(f"{name:<14}{n:>9}{sizes['mapdb'] / n:>9.2f}{sizes['.gpkg'] / n:>12.1f}"
              f"{sizes['.parquet'] / n:>12.1f}{sizes['.gpkg'] / sizes['mapdb']:>11.0f}x")
    print()
    print("500 m radius query after open, median of 200 (ms)")
    print(f"{'map':<14}{'objects hit':>12}{'cold pages':>12}{'warm cache':>12}")
    for name, _, _, cold, warm, hits in rows:
        print(f"{name:<14}{hits:>12}{cold:>12.3f}{warm:>12.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
