"""The stored index's lookup (``StoredQuadIndex.lookup``) of this tree beside a baseline revision's: µs a lookup.

The lookups are the ones the matcher makes: simulated images without a prior (matcher_core's: 300 m, 60 deg,
random heading) are localized once with the map's ``.qidx`` and every ``lookup`` call recorded (its query rows,
labels, radii and k).  Each recorded lookup is then made by this tree's index and by the baseline's, opened on the
same file, taking turns (which goes first alternates lookup by lookup, so both meet the same load), each index warm
(every lookup made once before, cold: each index opened fresh, its pages and blocks decoded and checked as the
lookups reach them; the OS's page cache warm).  Prints, per map: lookups, query rows a lookup, median and p95 µs a
warm lookup of each, their ratios, the mean µs a cold lookup of each, whether every answer is identical (rows, ids,
distances), the load average and matcher_core's gauge (a fixed numpy workload's ms).

Run from the repository root::

    python benchmarks/stored_lookup.py --baseline main --maps andorra,monaco,world1m
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import cached_maps, import_baseline  # noqa: E402
from matcher_core import CACHE as WORLD_CACHE  # noqa: E402
from matcher_core import EXTRACTS, WORLD, gauge_ms, simulated, world_map  # noqa: E402

CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-stored-lookup"


def recorded_lookups(map_path: Path, n: int, seed: int) -> list[tuple]:
    """The stored index's lookups of ``n`` simulated images without a prior: (invariants, labels, radius, k)."""
    from mapdb.localize.localizer import localize
    from mapdb.mapfile.reader import open_map
    from mapdb.match.index.stored import StoredQuadIndex

    calls: list[tuple] = []
    original = StoredQuadIndex.lookup

    def record(self, invariants, labels, radius, k, **kw):  # type: ignore[no-untyped-def]
        calls.append((np.array(invariants), np.array(labels), np.array(radius), k))
        return original(self, invariants, labels, radius, k, **kw)

    images = [{key: v for key, v in im.items() if key != "prior"} for im in simulated(map_path, n, seed)]
    StoredQuadIndex.lookup = record  # type: ignore[method-assign]
    try:
        with open_map(map_path) as m:
            for im in images:
                localize(im, m)
    finally:
        StoredQuadIndex.lookup = original  # type: ignore[method-assign]
    return calls


def time_map(name: str, map_path: Path, baseline: str, n: int) -> str:
    """One table row: this tree's and the baseline's lookups of one map's recorded calls."""
    from mapdb.match.index.stored import StoredQuadIndex, build_index, index_path

    if not index_path(map_path).exists():
        build_index(map_path)
    calls = recorded_lookups(map_path, n, 3)
    old_module = import_baseline(baseline, CACHE, "match.index.stored")
    ours, theirs = StoredQuadIndex(index_path(map_path)), old_module.StoredQuadIndex(index_path(map_path))
    same, gauge = True, gauge_ms()
    cold: dict[str, list[float]] = {"ours": [], "theirs": []}
    for i, c in enumerate(calls):  # first: each index cold (its pages and blocks decoded and checked as reached)
        got = {}
        for label, ix in (("ours", ours), ("theirs", theirs))[:: 1 if i % 2 else -1]:
            start = time.perf_counter()
            got[label] = ix.lookup(*c, return_distance=True)
            cold[label].append((time.perf_counter() - start) * 1e6)
        same = same and all(np.array_equal(x, y) for x, y in zip(got["ours"], got["theirs"], strict=True))
    times: dict[str, list[float]] = {"ours": [], "theirs": []}
    for i, c in enumerate(calls):  # then warm
        for label, ix in (("ours", ours), ("theirs", theirs))[:: 1 if i % 2 else -1]:
            start = time.perf_counter()
            ix.lookup(*c)
            times[label].append((time.perf_counter() - start) * 1e6)
    med = {k: statistics.median(v) for k, v in times.items()}
    cold_sum = {k: sum(v) / len(v) for k, v in cold.items()}
    p95 = {k: float(np.percentile(v, 95)) for k, v in times.items()}
    rows = statistics.median([len(c[0]) for c in calls])
    return (f"  {name:<8} {len(calls):>7} {rows:>6.0f} {med['ours']:>9.0f} {p95['ours']:>9.0f} {med['theirs']:>9.0f} "
            f"{p95['theirs']:>9.0f} {med['ours'] / med['theirs']:>7.2f} {p95['ours'] / p95['theirs']:>7.2f} "
            f"{cold_sum['ours']:>9.0f} {cold_sum['theirs']:>9.0f} {'yes' if same else 'NO':>5} "
            f"{os.getloadavg()[0]:>5.1f} {gauge:>6.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="main", help="the git revision compared")
    parser.add_argument("--maps", default="andorra,monaco",
                        help=f"shared extracts or {WORLD} (matcher_core's 1M world), comma-separated")
    parser.add_argument("--n", type=int, default=100, help="simulated images a map (their lookups are timed)")
    args = parser.parse_args()
    from _baseline import shared_data

    data = shared_data("osm")
    names = args.maps.split(",")
    needed = set(EXTRACTS) if WORLD in names else set(names)  # the 1M world is built from every extract
    missing = [name for name in sorted(needed) if not (data / EXTRACTS[name]).exists()]
    if missing:
        sys.exit(f"needs the shared data: {', '.join(str(data / EXTRACTS[m]) for m in missing)}")
    maps = cached_maps({name: EXTRACTS[name] for name in names if name != WORLD}, data, CACHE)
    if WORLD in names:  # matcher_core's, with its .qidx (built once, minutes)
        maps[WORLD] = world_map(WORLD_CACHE)
    print(f"stored index lookups of {args.n} images a map without a prior, this tree and {args.baseline} taking "
          f"turns, µs a lookup; {os.cpu_count()} cores")
    print(f"  {'map':<8} {'lookups':>7} {'rows':>6} {'median':>9} {'p95':>9} {'base med':>9} {'base p95':>9} "
          f"{'ratio':>7} {'p95 rat':>7} {'cold':>9} {'base cold':>9} {'same':>5} {'load':>5} {'gauge':>6}")
    for name in names:
        print(time_map(name, maps[name], args.baseline, args.n), flush=True)


if __name__ == "__main__":
    main()
