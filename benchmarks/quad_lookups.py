"""The kernel's quad lookups (``mapdb/match/_kernel_quads.c``) against scipy's cKDTree on the matcher's own lookups.

For each real extract (``matcher_core.py``'s maps and images: 300 m, 60 degrees, 1 px), the lookups the matcher makes
on ``--n`` images are recorded (with a 300 m prior: a prior's tiles, looked up in one call; without: the whole map's
index), then replayed: the kernel's ``quads_lookup`` against what ``QuadIndex.lookup`` did before it (a cKDTree query
per tree, with the lookup's filters in numpy), taking turns call by call, ``--repeats`` times; both answers are
compared hit for hit.  The trees themselves are built by both in turn: each tile's and the whole map's.  Medians
of process time (the machine is shared: CPU time, not wall time).

Run from the repository root::

    python benchmarks/quad_lookups.py --n 40
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import cached_maps  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, simulated  # noqa: E402


def record(path: Path, n: int, prior: bool) -> list[tuple]:
    """The arguments of every ``quads_lookup`` call the matcher makes on ``n`` images (after one warm-up pass),
    with each tree's points in place of the kernel's tree."""
    from mapdb.localize.localizer import localize
    from mapdb.mapfile.reader import open_map
    from mapdb.match import quads

    images = simulated(path, n, 3)
    if not prior:
        images = [{k: v for k, v in im.items() if k != "prior"} for im in images]
    calls: list[tuple] = []
    real = quads.quads_lookup
    points: dict[int, np.ndarray] = {}

    def spy(trees, *rest):
        calls.append((tuple(points[id(t)] for t in trees), *rest))
        return real(trees, *rest)

    real_build = quads.QuadTree.__init__

    def remember(self, data):
        real_build(self, data)
        points[id(self.handle)] = self.data

    quads.QuadTree.__init__ = remember  # type: ignore[method-assign]
    try:
        with open_map(path) as m:
            for im in images:
                localize(im, m)
            quads.quads_lookup = spy
            for im in images:
                localize(im, m)
    finally:
        quads.quads_lookup = real
        quads.QuadTree.__init__ = real_build  # type: ignore[method-assign]
    return calls


def tree_lookup(trees, quad_zs, inv, key, radius, k, px, py, reach, bound, by_place):
    """The lookup before the kernel: a cKDTree query per tree and QuadIndex.lookup's filters (c0735fc)."""
    rows, found = [], []
    for tree, z in zip(trees, quad_zs, strict=True):
        m, kk = len(inv), min(k, tree.n)
        query = np.empty((m, tree.m))
        query[:, :4], query[:, 4] = inv, key
        if tree.m == 7:
            query[:, 5], query[:, 6] = px, py
        dist, hit = tree.query(query, k=kk, distance_upper_bound=bound)
        dist, hit = dist.reshape(m, kk), hit.reshape(m, kk)
        if tree.m == 5:
            r, c = np.nonzero(dist <= radius[:, None])
            rows.append(r)
            found.append(z[hit[r, c]])
            continue
        r, c = np.nonzero(dist <= bound)
        h = hit[r, c]
        off2 = (tree.data[h, 5] - px) ** 2 + (tree.data[h, 6] - py) ** 2
        keep = (dist[r, c] ** 2 - off2 <= radius[r] ** 2) & (off2 <= reach**2)
        rows.append(r[keep])
        found.append(z[h[keep]])
    return np.concatenate(rows), np.concatenate(found)


def replay(calls: list[tuple], repeats: int) -> dict[str, float]:
    """Per call: the kernel's and the cKDTree's median ms, and how many calls' hits differ (order included)."""
    from mapdb._scipy import quick_tree
    from mapdb.match._kernel import quads_build, quads_lookup

    kernel = {id(p): quads_build(p) for c in calls for p in c[0]}
    scipy = {id(p): quick_tree(p) for c in calls for p in c[0]}
    mine, theirs, differ = [], [], 0
    for call in calls:
        points, rest = call[0], call[1:]
        ours = (tuple(kernel[id(p)] for p in points), *rest)
        old = (tuple(scipy[id(p)] for p in points), *rest)
        a, b = [], []
        for _ in range(repeats):
            start = time.process_time()
            rows, flat = quads_lookup(*ours)
            a.append(time.process_time() - start)
            start = time.process_time()
            want = tree_lookup(*old)
            b.append(time.process_time() - start)
        got = np.frombuffer(rows, np.int64), np.frombuffer(flat, np.complex128).reshape(-1, 4)
        differ += not (np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]))
        mine.append(statistics.median(a))
        theirs.append(statistics.median(b))
    return {"kernel": 1e3 * statistics.median(mine), "ckdtree": 1e3 * statistics.median(theirs), "differ": differ}


def builds(calls: list[tuple], repeats: int) -> tuple[float, float]:
    """The trees of the lookups built by both, in turn: summed medians (ms)."""
    from mapdb._scipy import quick_tree
    from mapdb.match._kernel import quads_build

    distinct = {id(p): p for c in calls for p in c[0]}.values()
    mine = theirs = 0.0
    for points in distinct:
        a, b = [], []
        for _ in range(repeats):
            start = time.process_time()
            quads_build(points)
            a.append(time.process_time() - start)
            start = time.process_time()
            quick_tree(points)
            b.append(time.process_time() - start)
        mine += statistics.median(a)
        theirs += statistics.median(b)
    return 1e3 * mine, 1e3 * theirs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=40, help="images a map")
    parser.add_argument("--maps", default=",".join(EXTRACTS))
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    maps = cached_maps({name: EXTRACTS[name] for name in args.maps.split(",")}, DATA, CACHE)
    print(f"{args.n} images a map, process time, medians of {args.repeats}")
    print(f"  {'map':<14} {'case':<9} {'calls':>5} {'queries':>7} {'trees':>5} {'kernel ms':>9} {'cKDTree ms':>10} "
          f"{'ratio':>5} {'differ':>6} {'build ms':>8} {'cKDTree':>8} {'ratio':>5} {'points':>7}")
    for name, path in maps.items():
        for case in ("prior", "no prior"):
            calls = record(path, args.n, case == "prior")
            if not calls:
                print(f"  {name:<14} {case:<9} no lookups")
                continue
            times = replay(calls, args.repeats)
            built, old = builds(calls, max(3, args.repeats // 3))
            queries = statistics.median(len(c[2]) for c in calls)
            trees = statistics.median(len(c[0]) for c in calls)
            size = sum(len(p) for p in {id(p): p for c in calls for p in c[0]}.values())
            print(f"  {name:<14} {case:<9} {len(calls):5d} {queries:7.0f} {trees:5.1f} {times['kernel']:9.3f} "
                  f"{times['ckdtree']:10.3f} {times['kernel'] / times['ckdtree']:5.2f} {times['differ']:6d} "
                  f"{built:8.1f} {old:8.1f} {built / old:5.2f} {size:7d}")


if __name__ == "__main__":
    main()
