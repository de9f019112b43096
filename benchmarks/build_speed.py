"""How long reading an OSM extract takes, against a bare pyosmium pass over the same file.

Side by side in one run, each repeated (default 3 times, median reported):

* ``bare pyosmium``: ``FileProcessor(...).with_locations("flex_mem").with_areas()``, iterating every
  object and doing nothing: the floor set by locating nodes and assembling areas;
* the same pass with every object dropped in C++ before Python sees it (for reference only);
* ``read_osm``: :func:`mapdb.sources.osm.read_osm` with the default label table;
* ``mapdb build``: :func:`mapdb.build.build_map` to a temporary file (if the module exists).

The goal is a whole build at most 2.5x the bare pass.  Run::

    python benchmarks/build_speed.py [OSM_FILE] [--repeat N]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import osmium
import osmium.filter

DEFAULT_FILE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "osm" / "andorra-2021-06-22.osm.pbf"


def bare_pass(path: Path) -> int:
    count = 0
    for _ in osmium.FileProcessor(str(path)).with_locations("flex_mem").with_areas():
        count += 1
    return count


def bare_pass_nothing_to_python(path: Path) -> None:
    # The C++ floor: same reading and assembly, every object dropped before it reaches Python.
    nothing = osmium.filter.EntityFilter(osmium.osm.NOTHING)
    for _ in osmium.FileProcessor(str(path)).with_locations("flex_mem").with_areas().with_filter(nothing):
        pass


def _timed(func: Callable[[], object], repeat: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("osm_file", nargs="?", type=Path, default=DEFAULT_FILE)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    path: Path = args.osm_file
    if not path.exists():
        print(f"{path}: no such file (real data lives in ../shared/data beside the checkout)")
        return

    from mapdb.labels import default_label_table
    from mapdb.sources.osm import read_osm

    table = default_label_table()
    cases: list[tuple[str, Callable[[], object]]] = [
        ("bare pyosmium (locations+areas)", lambda: bare_pass(path)),
        ("  same, nothing reaches Python", lambda: bare_pass_nothing_to_python(path)),
        ("read_osm", lambda: read_osm(path, table)),
    ]
    tmp = tempfile.TemporaryDirectory()
    try:
        from mapdb.build import build_map
    except ImportError as exc:
        print(f"(no full build: mapdb.build.build_map not importable: {exc})")
    else:
        output = Path(tmp.name) / "bench.mapdb"
        cases.append(("mapdb build (build_map)", lambda: build_map([path], output)))

    print(f"{path.name}: {path.stat().st_size / 1e6:.1f} MB, {args.repeat} runs each, median")
    header = f"{'case':<34} {'median s':>9} {'x bare':>7}  runs"
    print(header)
    print("-" * len(header))
    bare = None
    with tmp:
        for name, func in cases:
            median, times = _timed(func, args.repeat)
            bare = bare or median
            runs = " ".join(f"{t:.3f}" for t in times)
            print(f"{name:<34} {median:>9.3f} {median / bare:>6.2f}x  {runs}")


if __name__ == "__main__":
    main()
