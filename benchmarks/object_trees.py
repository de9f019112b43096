"""The map objects' spatial queries: the kernel's KD-trees per label against scipy's cKDTree (and rtree).

:class:`mapdb.match.mapobjects.object_index.ObjectIndex` answers an image's nearest-object, density and disc
queries from :class:`~mapdb.match.mapobjects.label_trees.LabelTrees` (the compiled kernel's 2-D KD-tree per label);
before, from one cKDTree over ``(x, y, label * gap)`` (``mapdb._scipy.quick_tree``).  On the maps of
``benchmarks/matcher_core.py`` (its cache; ``--world`` adds its 1M world when cached there), this prints:

1. Build time of each, taking turns (median of ``--repeats``).
2. Time of one call of the shapes an image makes (median over many calls, microseconds): one point's nearest
   within a millimetre (``at``), 40 points' nearest within 300 m (``nearest``), 2,000 points' 6 nearest with no
   bound (``neighbours`` of 100 hypotheses), 100 discs' counts of 500 m (``local_density``); whether the
   distances (and counts) are identical.
3. With the rtree package installed (``pip install rtree``; not a mapdb dependency): its ``nearest`` for one
   point (an R-tree per label, bulk-loaded), the only form its Python API has (one call a point, no bound).
4. Why a tree and not a uniform grid per label: how clustered each map's four commonest labels are, as a grid
   of one object a cell on average would hold them (the share of empty cells, the fullest cell, the mean number
   of objects in an object's own cell).

Run from the repository root::

    python benchmarks/object_trees.py [--world] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import cached_maps  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS  # noqa: E402

from mapdb._scipy import quick_tree  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.match.mapobjects.label_trees import LabelTrees  # noqa: E402

try:
    import rtree
except ImportError:  # the comparison needs it; mapdb does not
    rtree = None


def _median_us(call, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e6


def builds(name: str, objects, repeats: int) -> None:
    z, label = objects.x + 1j * objects.y, objects.label.astype(np.int64)
    gap = 1e3 * (math.sqrt(np.ptp(objects.x) * np.ptp(objects.y)) + 1e4)
    old, new = [], []
    for r in range(repeats):
        for which in (0, 1) if r % 2 == 0 else (1, 0):
            t = time.perf_counter()
            if which == 0:
                quick_tree(np.column_stack([objects.x, objects.y, label * gap]))
                old.append(time.perf_counter() - t)
            else:
                LabelTrees(z, label, len(objects.labels))
                new.append(time.perf_counter() - t)
    a, b = statistics.median(old) * 1e3, statistics.median(new) * 1e3
    print(f"  {name:14s} {len(objects):9d} objects  build ms: cKDTree {a:8.1f}  LabelTrees {b:8.1f}  ratio {b / a:.2f}")


def queries(name: str, objects, calls: int) -> None:
    z, label = objects.x + 1j * objects.y, objects.label.astype(np.int64)
    n_labels = len(objects.labels)
    gap = 1e3 * (math.sqrt(np.ptp(objects.x) * np.ptp(objects.y)) + 1e4)
    tree, trees = quick_tree(np.column_stack([objects.x, objects.y, label * gap])), LabelTrees(z, label, n_labels)
    rng = np.random.default_rng(0)
    print(f"  {name}: one call, median us   (cKDTree | LabelTrees | ratio | identical)")
    for what, m, k, bound in (("at", 1, 1, 1e-3), ("nearest", 40, 1, 300.0), ("neighbours", 2000, 6, 0.5 * gap)):
        pick = rng.integers(0, z.size, m)
        w = z[pick] + (0 if what == "at" else rng.normal(0, 30, m) + 1j * rng.normal(0, 30, m))
        ql = label[pick] if what == "at" else rng.integers(0, n_labels, m)

        def old(w=w, ql=ql, k=k, bound=bound):
            points = np.empty((w.size, 3))
            points[:, 0], points[:, 1] = w.real, w.imag
            np.multiply(ql, gap, out=points[:, 2])
            return tree.query(points, k=k, distance_upper_bound=bound)

        def new(w=w, ql=ql, k=k, bound=bound):
            return trees.query(w, ql, k, bound)

        same = np.array_equal(np.reshape(old()[0], (m, k)), new()[0])
        a, b = _median_us(old, calls), _median_us(new, calls)
        print(f"    {what:11s} {m:5d} points k={k}: {a:9.1f} | {b:9.1f} | {b / a:5.2f} | {same}")
    centres = np.repeat(z[rng.integers(0, z.size, 100)], n_labels)
    codes, r = np.tile(np.arange(n_labels), 100), np.full(100 * n_labels, 500.0)

    def old_count():
        points = np.column_stack([centres.real, centres.imag, codes * gap])
        return tree.query_ball_point(points, r, return_length=True)

    same = np.array_equal(old_count(), trees.count(centres, codes, r))
    a, b = _median_us(old_count, calls), _median_us(lambda: trees.count(centres, codes, r), calls)
    print(f"    {'discs':11s} {centres.size:5d} discs 500 m: {a:9.1f} | {b:9.1f} | {b / a:5.2f} | {same}")
    if rtree is not None:
        rtrees = {}
        for code in np.unique(label):
            at = np.flatnonzero(label == code)
            rtrees[code] = rtree.index.Index((int(i), (z[i].real, z[i].imag, z[i].real, z[i].imag), None)
                                              for i in at)
        pick = rng.integers(0, z.size, 200)
        w = z[pick] + rng.normal(0, 30, 200) + 1j * rng.normal(0, 30, 200)

        turn = iter(range(10**9))

        def one():  # one point a call, cycling through 200
            j = next(turn) % 200
            p = w[j]
            return list(rtrees[label[pick[j]]].nearest((p.real, p.imag, p.real, p.imag), 1))

        c = _median_us(one, calls)
        b = _median_us(lambda: trees.query(w[:1], label[pick[:1]], 1, 300.0), calls)
        print(f"    rtree {rtree.__version__} nearest, 1 point: {c:9.1f} us a call (LabelTrees {b:.1f})")


def clustering(name: str, objects) -> None:
    for code in np.argsort(-np.bincount(objects.label))[:4]:
        x, y = objects.x[objects.label == code], objects.y[objects.label == code]
        if x.size < 10:
            continue
        side = math.sqrt(np.ptp(x) * np.ptp(y) / x.size)
        ix, iy = ((x - x.min()) // side).astype(np.int64), ((y - y.min()) // side).astype(np.int64)
        cells = np.bincount(ix * (iy.max() + 1) + iy, minlength=int((ix.max() + 1) * (iy.max() + 1)))
        print(f"  {name:14s} {objects.labels[code]:18s} {x.size:7d} objects, cells of {side:6.0f} m: "
              f"{np.mean(cells == 0):4.0%} empty, fullest {cells.max():4d}, an object's cell "
              f"{np.sum(cells.astype(np.float64) ** 2) / x.size:5.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--world", action="store_true", help="also the 1M world of matcher_core's cache")
    args = parser.parse_args()
    maps = cached_maps(EXTRACTS, DATA, CACHE)
    if args.world:
        found = sorted(CACHE.glob("world1m.*.mapdb"), key=lambda p: p.stat().st_mtime)
        if found:
            maps["world1m"] = found[-1]
        else:
            print("no 1M world cached: run benchmarks/matcher_core.py --maps world1m first")
    loaded = {name: open_map(path).all() for name, path in maps.items()}
    print("build (taking turns):")
    for name, objects in loaded.items():
        builds(name, objects, args.repeats)
    print("queries:")
    for name, objects in loaded.items():
        if name != "world1m":
            queries(name, objects, args.calls)
    print("clustering (a uniform grid per label at one object a cell on average):")
    for name, objects in loaded.items():
        clustering(name, objects)


if __name__ == "__main__":
    main()
