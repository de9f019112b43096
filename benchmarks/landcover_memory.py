"""Peak memory and time of reading land-cover rasters, each in a fresh subprocess.

For every raster (default: the 36000 x 36000 ESA WorldCover tile and the two CORINE rasters in
``../shared/data/landcover``), a child Python process runs
:func:`mapdb.sources.landcover.reader.read_landcover` with the default label table and min area, and
this script reports, side by side:

* peak RSS of the child (``ru_maxrss`` of that child, from ``os.wait4``: the per-child figure that
  ``resource.getrusage(RUSAGE_CHILDREN)`` aggregates as a maximum);
* the size of the raster's pixel array, and peak RSS as a ratio of it;
* wall time of ``read_landcover`` inside the child, and of the whole child (interpreter start and
  imports included);
* object counts per label.

A first row runs a child that only imports the module: the floor that Python, numpy, scipy,
rasterio and pyproj cost before any pixel is read.  Below each raster, for comparison, two
children that only read pixels, no labelling: one in the same block-aligned tiles with the same
small GDAL cache (the I/O and decompression floor of ``read_landcover``), one reading the whole
array in a single ``rasterio`` call (``--no-compare`` skips both).  CPU seconds (user + system) of
each child are given too: on a machine shared with other jobs they vary less than wall time.

The goal for the WorldCover tile is a peak under 1.5 GB (its whole array is 1.3 GB).  Run::

    python benchmarks/landcover_memory.py [RASTER ...]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "landcover"
DEFAULT_FILES = [
    DATA / "ESA_WorldCover_10m_2021_v200_N00E006_Map.tif",
    DATA / "corine2000_bern_valais_g100_clc00.tif",
    DATA / "corine2006_lausanne_ls100_06.tif",
]
GOAL_BYTES = 1.5e9

_CHILD = r"""
import json, sys, time
from mapdb.labels import default_label_table
from mapdb.sources.landcover.reader import read_landcover
path, mode = sys.argv[1], sys.argv[2]
if mode == "imports":
    print(json.dumps({"seconds": 0.0, "counts": {}, "crs": ""}))
    raise SystemExit
start = time.perf_counter()
if mode == "strips":
    import rasterio
    from rasterio.windows import Window
    from pathlib import Path
    from mapdb.sources.landcover.reader import _GDAL_CACHE_MB
    from mapdb.sources.landcover.tiles import _Tiling
    with rasterio.Env(GDAL_CACHEMAX=_GDAL_CACHE_MB), rasterio.open(path) as src:
        tiling = _Tiling(Path(path), src, Window(0, 0, src.width, src.height), skip_absent=False)
        for r0, r1, tiles in tiling.rows():
            for _, c0, c1 in tiles:
                src.read(1, window=Window(c0, r0, c1 - c0, r1 - r0))
    print(json.dumps({"seconds": time.perf_counter() - start, "counts": {}, "crs": str(src.crs)}))
    raise SystemExit
if mode == "whole":
    import rasterio
    with rasterio.open(path) as src:
        src.read(1)
    print(json.dumps({"seconds": time.perf_counter() - start, "counts": {}, "crs": str(src.crs)}))
    raise SystemExit
objects = read_landcover(path, default_label_table())
print(json.dumps({"seconds": time.perf_counter() - start, "counts": objects.counts(), "crs": objects.crs}))
"""


def run_child(path: str, mode: str = "read_landcover") -> tuple[dict, float, float, int]:
    """Run one read in a child; its JSON result, wall seconds, CPU seconds and peak RSS in bytes."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, path, mode], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out = proc.stdout.read() if proc.stdout else b""
    err = proc.stderr.read() if proc.stderr else b""
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{path}: child failed ({proc.returncode}): {err.decode(errors='replace').strip()}")
    # ru_maxrss is in kilobytes on Linux.
    return json.loads(out), wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024


def array_bytes(path: Path) -> int:
    import numpy as np
    import rasterio

    with rasterio.open(path) as src:
        return src.width * src.height * src.count * np.dtype(src.dtypes[0]).itemsize


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("rasters", nargs="*", type=Path, default=DEFAULT_FILES)
    parser.add_argument("--no-compare", dest="compare", action="store_false",
                        help="skip the comparison children (bare strip read, whole-array read)")
    args = parser.parse_args()
    rasters = [p for p in args.rasters if p.exists()]
    for p in args.rasters:
        if not p.exists():
            print(f"{p}: no such file (real data lives in ../shared/data beside the checkout); skipped")
    if not rasters:
        return

    rows = []

    def add(name: str, path: str, mode: str, size: int | None) -> None:
        result, wall, cpu, rss = run_child(path, mode)
        rows.append((name, result["crs"], rss, size, result["seconds"], wall, cpu, result["counts"]))

    add("(imports only)", "-", "imports", None)
    for path in rasters:
        size = array_bytes(path)
        add(path.name, str(path), "read_landcover", size)
        if args.compare:
            add("  same file, block-aligned tiles read, nothing done", str(path), "strips", size)
            add("  same file, whole array in one rasterio read", str(path), "whole", size)

    header = (f"{'raster':52s} {'crs':10s} {'peak RSS':>9s} {'array':>9s} {'RSS/array':>9s} {'read s':>7s} "
              f"{'child s':>7s} {'cpu s':>6s}  objects")
    print(header)
    print("-" * len(header))
    for name, crs, rss, size, seconds, wall, cpu, counts in rows:
        ratio = f"{rss / size:9.2f}" if size else f"{'':9s}"
        size_text = f"{size / 1e6:7.1f}MB" if size else f"{'':9s}"
        total = sum(counts.values())
        print(f"{name:52s} {crs:10s} {rss / 1e6:7.0f}MB {size_text} {ratio} {seconds:7.2f} {wall:7.2f} {cpu:6.2f}  "
              f"{total if counts else ''}")
        if counts:
            print(f"{'':52s}   " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])))
    print()
    children_max = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    print(f"largest child peak (getrusage RUSAGE_CHILDREN ru_maxrss): {children_max / 1e6:.0f} MB; "
          f"goal for the WorldCover tile: < {GOAL_BYTES / 1e9:.1f} GB")
    for name, _crs, rss, *_ in rows[1:]:
        if "worldcover" in name.lower():  # the read_landcover row, not the comparisons
            verdict = "met" if rss < GOAL_BYTES else "NOT met"
            print(f"{name}: peak {rss / 1e9:.2f} GB -> goal {verdict}")


if __name__ == "__main__":
    main()
