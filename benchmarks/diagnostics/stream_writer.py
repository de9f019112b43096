"""Peak memory of a ``MapWriter`` fed random objects in blocks of 262,144: the map writer's part of a build.

Reproduces the README's "a ``MapWriter`` fed random objects in blocks of 262,144 peaks at 127 MB for 1,065,854
objects and 212 MB for 5,005,004" (the streaming build's section): ``N`` objects uniform over a 1,000 km
square, two labels, areas up to 500 m^2 (seed 0), added block by block and written to ``OUT`` (quantum 0.1 m;
its parts in memory reach ``DEFAULT_MEMORY_OBJECTS`` objects before they spill).

Run from the repository root, one size a process (the peak is the process's)::

    /usr/bin/time -f "%M KB" python benchmarks/diagnostics/stream_writer.py 1065854 /tmp/w1.mapdb
    /usr/bin/time -f "%M KB" python benchmarks/diagnostics/stream_writer.py 5005004 /tmp/w5.mapdb

Prints the objects written, the seconds and the process's peak resident set (``getrusage``, the same figure
as ``/usr/bin/time``'s ``%M``).  ``OUT`` must not exist (``--overwrite`` replaces it).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

from mapdb.mapfile.writer import DEFAULT_MEMORY_OBJECTS, MapWriter
from mapdb.objects import Objects

BLOCK = 1 << 18
LABELS = ("building", "park")


def write(n: int, out: Path) -> None:
    """``n`` random objects into ``out``, ``BLOCK`` at a time."""
    rng = np.random.default_rng(0)
    with MapWriter(out, quantum=0.1) as writer:
        for start in range(0, n, BLOCK):
            k = min(BLOCK, n - start)
            writer.add(Objects(rng.uniform(0, 1e6, k), rng.uniform(0, 1e6, k), rng.integers(0, 2, k).astype(np.int32),
                               rng.uniform(0, 500, k), LABELS, "EPSG:32631"))
        writer.finish({})


def main(argv: list[str] | None = None) -> int:
    """Write the map, print the peak."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("n", type=int, help="objects")
    parser.add_argument("out", type=Path, help="the map written (.mapdb)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.out.exists() and not args.overwrite:
        print(f"stream_writer: error: {args.out}: exists (use --overwrite)", file=sys.stderr)
        return 2
    start = time.perf_counter()
    write(args.n, args.out)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{args.n:,} objects in blocks of {BLOCK:,} (parts in memory up to {DEFAULT_MEMORY_OBJECTS:,}):"
          f" {time.perf_counter() - start:.1f} s, peak RSS {peak_mb:.0f} MB, {args.out.stat().st_size:,} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
