"""Time and peak memory of the builder on hostile inputs too big for the test suite.

Each case is written to a scratch directory, then read in a fresh child process.  The figure is the
child's own peak resident memory, ``VmHWM`` of ``/proc/self/status`` (not ``ru_maxrss``: Linux carries a
parent's peak into a child it forks, and this script's own peak includes writing the inputs).  A first
row gives the floor that the imports cost:

* ``sparse 1e6 x 1e6``: a 1e6 x 1e6 GeoTIFF in 512-pixel deflate blocks, ``SPARSE_OK``, with three
  blocks of data (a 45 MB file, nearly all of it the block offset tables).  Before block skipping,
  reading it took about an hour;
* ``sparse 2e9 x 1, tiled``: 2e9 x 1 pixels in 256-pixel blocks, three of them written;
* ``sparse 2e9 x 1, one strip``: 2e9 x 1 pixels stored as one (absent) strip.  Before tiling, reading
  it tried a 14.9 GB allocation;
* ``3e8 x 1 strip with data``: an uncompressed 300 MB strip, which GDAL can only inflate whole:
  refused on one line, before any allocation;
* ``.osm.gz`` / ``.osm.bz2`` bombs: an XML header, then GiBs of spaces, as concatenated gzip members /
  bzip2 streams (each inflates 1 MiB), so a 10 GiB bomb is about 10 MB of gzip (or 0.5 MB of bzip2).
  Before the bound, such files took 1-2 minutes and 1.1 GB; now they are refused once they pass
  ``max(MIN_INFLATED_BYTES, MAX_INFLATION x compressed size)``.

Run::

    python benchmarks/builder_hostile.py [--workdir DIR] [--keep]

Scratch files take about 120 MB of disk (the 300 MB strip is written, read and deleted first).
"""

from __future__ import annotations

import argparse
import bz2
import gzip
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

_CHILD = r"""
import json, sys, time
from collections import Counter
path, kind = sys.argv[1], sys.argv[2]
from mapdb.errors import MapdbError
from mapdb.labels import default_label_table
from mapdb.sources import read_source
table = default_label_table()
def peak():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
if kind == "imports":
    print(json.dumps({"seconds": 0.0, "outcome": "", "peak": peak()}))
    raise SystemExit
counts = Counter()
start = time.perf_counter()
try:
    objects = read_source(path, table, min_area_m2=0.0, counts=counts)
    outcome = f"{len(objects)} objects " + json.dumps(objects.counts())
except MapdbError as exc:
    outcome = "error: " + str(exc).replace(path, "FILE")
print(json.dumps({"seconds": time.perf_counter() - start, "outcome": outcome, "peak": peak()}))
"""


def measure(path: str, kind: str) -> tuple[dict, float]:
    """One read in a fresh interpreter: its JSON result (with its peak memory) and wall seconds."""
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, path, kind], capture_output=True)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{path}: child failed ({proc.returncode}): {proc.stderr.decode(errors='replace').strip()}")
    return json.loads(proc.stdout), wall


# ----------------------------------------------------------------------------------------------- inputs


def _raster(path: Path, width: int, height: int, blocks: list[tuple[int, int]], block: int | None,
            compress: str | None = "deflate", bigtiff: bool = False) -> Path:
    import numpy as np
    import rasterio
    from rasterio import Affine
    from rasterio.windows import Window

    profile = {"driver": "GTiff", "width": width, "height": height, "count": 1, "dtype": "uint8",
               "crs": "EPSG:3035", "transform": Affine(100.0, 0.0, 4e6, 0.0, -100.0, 3e6), "nodata": 255,
               "SPARSE_OK": True}
    if compress:
        profile["compress"] = compress
    if bigtiff:  # 8-byte block offsets, as GDAL writes for a raster of more than 4 GB
        profile["BIGTIFF"] = "YES"
    if block:
        profile.update(tiled=True, blockxsize=block, blockysize=block)
    with rasterio.open(path, "w", **profile) as dst:
        for br, bc in blocks:
            rows, cols = min(block, height - br * block), min(block, width - bc * block)
            data = np.full((rows, cols), 255, np.uint8)
            data[: max(1, rows // 2), : cols // 2] = 41   # water
            data[-1:, cols // 2:] = 24                    # forest
            dst.write(data, 1, window=Window(bc * block, br * block, cols, rows))
    return path


def _dense_strip(path: Path, width: int) -> Path:
    import numpy as np
    import rasterio
    from rasterio import Affine

    with rasterio.open(path, "w", driver="GTiff", width=width, height=1, count=1, dtype="uint8", crs="EPSG:3035",
                       transform=Affine(100.0, 0.0, 4e6, 0.0, -100.0, 3e6), nodata=255) as dst:
        dst.write(np.full((1, width), 41, np.uint8), 1)
    return path


_HEADER = b'<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="bomb">\n'
_FOOTER = b'<node id="1" version="1" lat="60" lon="24"><tag k="building" v="yes"/></node>\n</osm>\n'


def _bomb(path: Path, gib: int, compress: Callable[[bytes], bytes]) -> Path:
    """An OSM XML document padded with ``gib`` GiB of spaces, as concatenated compressed members."""
    member = compress(b" " * (1 << 20))
    with open(path, "wb") as f:
        f.write(compress(_HEADER))
        for _ in range(gib << 10):
            f.write(member)
        f.write(compress(_FOOTER))
    return path


def cases(work: Path) -> list[tuple[str, Callable[[], Path], str]]:
    return [
        ("3e8 x 1 uncompressed strip with data", lambda: _dense_strip(work / "clc_strip_3e8.tif", 300_000_000),
         "delete"),
        ("sparse 1e6 x 1e6, 512 blocks, 3 written",
         lambda: _raster(work / "clc_sparse_1e6.tif", 10**6, 10**6, [(0, 0), (900, 1200), (1953, 1953)], 512,
                         bigtiff=True), ""),
        ("sparse 2e9 x 1, 256 blocks, 3 written",
         lambda: _raster(work / "clc_sparse_2e9_tiled.tif", 2 * 10**9, 1, [(0, 0), (0, 4_000_000), (0, 7_812_499)],
                         256), ""),
        ("sparse 2e9 x 1, one absent strip", lambda: _raster(work / "clc_sparse_2e9_strip.tif", 2 * 10**9, 1, [],
                                                             None), ""),
        (".osm.gz bomb, 1 GiB of spaces", lambda: _bomb(work / "bomb_1g.osm.gz", 1, gzip.compress), ""),
        (".osm.gz bomb, 10 GiB of spaces", lambda: _bomb(work / "bomb_10g.osm.gz", 10, gzip.compress), ""),
        (".osm.bz2 bomb, 10 GiB of spaces", lambda: _bomb(work / "bomb_10g.osm.bz2", 10, bz2.compress), ""),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, help="scratch directory (default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch files")
    args = parser.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="mapdb-hostile-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        result, wall = measure("-", "imports")
        rows.append(("(imports only)", None, None, 0.0, wall, result["peak"], ""))
        for name, make, after in cases(work):
            t = time.perf_counter()
            path = make()
            made = time.perf_counter() - t
            result, wall = measure(str(path), "read")
            rows.append((name, path.stat().st_size, made, result["seconds"], wall, result["peak"], result["outcome"]))
            if after == "delete":
                path.unlink()
    finally:
        if not args.keep and args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)

    header = f"{'case':40s} {'file':>10s} {'read s':>7s} {'child s':>7s} {'peak RSS':>9s}  outcome"
    print(header)
    print("-" * len(header))
    for name, size, _made, seconds, wall, rss, outcome in rows:
        size_text = f"{size / 1e6:8.2f}MB" if size is not None else f"{'':10s}"
        print(f"{name:40s} {size_text} {seconds:7.2f} {wall:7.2f} {rss / 1e6:7.0f}MB  {outcome}")
    from mapdb.sources.landcover.tiles import _MAX_BLOCK_BYTES, _TILE_PIXELS
    from mapdb.sources.osm.files import MAX_INFLATION, MIN_INFLATED_BYTES

    print()
    print(f"limits: tiles of {_TILE_PIXELS:,} pixels; blocks holding data up to {_MAX_BLOCK_BYTES >> 20} MiB; "
          f"XML inflates up to max({MIN_INFLATED_BYTES >> 20} MiB, {MAX_INFLATION} x compressed size)")


if __name__ == "__main__":
    main()
