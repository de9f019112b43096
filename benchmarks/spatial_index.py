"""shapely's STRtree against the rtree package (libspatialindex) for what mapdb asks of a spatial index.

mapdb builds one spatial index at map open, over the page directory's boxes (every page a box of at most 1024
objects), and asks it for the pages a query box touches; the renderer asks one over a scene's outlines.  Both
trees are built from the same boxes and asked the same windows, and their answers are checked equal.

    python benchmarks/spatial_index.py [--repeats 5]

Prints, per directory size: build time, the time of 1,000 window queries (one call each, as a query makes
them) and of the same 1,000 windows in one vectorised call (STRtree only: rtree has no bulk query of boxes in
its Python API), medians of the repeats.  rtree is not a mapdb dependency: ``pip install rtree`` to run the
comparison, otherwise only STRtree is timed.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import shapely

try:
    import rtree
except ImportError:  # the comparison needs it; mapdb does not
    rtree = None


def page_boxes(n: int, seed: int = 0) -> np.ndarray:
    """``n`` square pages tiling a square region, jittered like a real directory (minx, miny, maxx, maxy)."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    i = np.arange(n)
    x0, y0 = (i % side) * 500.0, (i // side) * 500.0
    w = rng.uniform(200.0, 500.0, (n, 2))
    return np.column_stack([x0, y0, x0 + w[:, 0], y0 + w[:, 1]])


def windows(boxes: np.ndarray, n: int = 1000, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo = boxes[:, :2].min(axis=0)
    hi = boxes[:, 2:].max(axis=0)
    corner = rng.uniform(lo, hi, (n, 2))
    size = rng.uniform(100.0, 1500.0, (n, 1))
    return np.column_stack([corner, corner + size])


def timed(function, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def run(n: int, repeats: int) -> dict[str, float]:
    boxes, asked = page_boxes(n), windows(page_boxes(n))
    geometry, asked_geometry = shapely.box(*boxes.T), shapely.box(*asked.T)
    row: dict[str, float] = {}
    row["str_build"], tree = timed(lambda: shapely.STRtree(geometry), repeats)
    row["str_each"], str_hits = timed(lambda: [np.sort(tree.query(g)) for g in asked_geometry], repeats)
    row["str_bulk"], _ = timed(lambda: tree.query(asked_geometry), repeats)
    if rtree is not None:
        def build() -> rtree.index.Index:
            return rtree.index.Index((i, tuple(b), None) for i, b in enumerate(boxes))

        row["rtree_build"], index = timed(build, repeats)
        row["rtree_each"], rtree_hits = timed(lambda: [np.sort(np.fromiter(index.intersection(tuple(w)), np.int64))
                                                       for w in asked], repeats)
        assert all(np.array_equal(a, b) for a, b in zip(str_hits, rtree_hits)), "the two trees disagree"
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", default="1000,10000,100000")
    args = parser.parse_args()
    print(f"rtree {rtree.__version__ + ' (libspatialindex)' if rtree else 'not installed'}, "
          f"shapely {shapely.__version__}; medians of {args.repeats}, milliseconds")
    print(f"{'pages':>8} {'STR build':>10} {'rtree build':>12} {'STR 1000 q':>11} {'rtree 1000 q':>13} "
          f"{'STR bulk 1000':>14}")
    for n in (int(s) for s in args.sizes.split(",")):
        row = run(n, args.repeats)
        ms = {key: value * 1e3 for key, value in row.items()}
        print(f"{n:>8} {ms['str_build']:>10.2f} {ms.get('rtree_build', float('nan')):>12.2f} "
              f"{ms['str_each']:>11.2f} {ms.get('rtree_each', float('nan')):>13.2f} {ms['str_bulk']:>14.2f}")


if __name__ == "__main__":
    main()
