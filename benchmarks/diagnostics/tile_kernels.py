"""A map tile's two kernel calls, this tree's against a baseline revision's: ``map_quads`` (the tile's quads, their
tree points and complex points) and ``quads_build`` (the quad k-d tree over the points), on the tiles
``benchmarks/matcher_core.py``'s part 4 builds (40 tiles a map under random objects, ``localizer.TILE_SIZE_M`` with
``TILE_PAD_M`` of neighbours, positions indexed; its seed).

The inputs of each call (the anchors' neighbours, found once by cKDTree) are the same for both kernels; each tile is
timed ``--repeats`` times a kernel, the two taking turns (which goes first alternates), and its fastest run kept (the
least disturbed by the machine's other work).  Per map: the median and p95 over tiles of those ms, the sums, the
ratio of this tree's to the baseline's (of the sums), the page faults a tile and the share of system time over all
its runs (``getrusage``: fresh memory, faulted in page by page), and whether every output is the same bytes (quads,
tree points, complex points).  The outputs of the last 200 calls are kept alive, as a localizer's tile cache keeps
its tiles, so that fresh memory is faulted in as in an answer.  Run from the repository root::

    python benchmarks/diagnostics/tile_kernels.py --baseline main
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import extract_maps, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, p95  # noqa: E402


def tile_inputs(path: Path, tiles: int, seed: int) -> list[tuple]:
    """matcher_core part 4's tiles of one map: (nn, anchors, z, label, n_labels) each, those with quads."""
    from mapdb.localize.localizer import TILE_PAD_M, TILE_SIZE_M
    from mapdb.mapfile.reader import open_map
    from mapdb.match.quads import _anchor_neighbours

    rng = np.random.default_rng(seed)
    out = []
    with open_map(path) as m:
        everything = m.all()
        for i in rng.integers(0, len(everything), tiles):
            x0 = np.floor(everything.x[i] / TILE_SIZE_M) * TILE_SIZE_M
            y0 = np.floor(everything.y[i] / TILE_SIZE_M) * TILE_SIZE_M
            far = TILE_SIZE_M + TILE_PAD_M
            o = m.query_bbox(x0 - TILE_PAD_M, y0 - TILE_PAD_M, x0 + far, y0 + far)
            anchors = (o.x >= x0) & (o.x < x0 + TILE_SIZE_M) & (o.y >= y0) & (o.y < y0 + TILE_SIZE_M)
            found = _anchor_neighbours(o.x, o.y, 8, anchors) if len(o) >= 4 else None
            if found is not None:
                z = np.ascontiguousarray(o.x + 1j * o.y, np.complex128)
                out.append((*found, z, np.ascontiguousarray(o.label, np.int64), len(o.labels)))
    return out


def timed(kernel: object, tile: tuple, keep: list, usage: list[float]) -> tuple[float, float, bytes]:
    """One tile through ``kernel``: ms of map_quads, ms of quads_build, and the outputs' bytes; its page faults, system
    and total CPU seconds added to ``usage``."""
    from mapdb.match.quads import LABEL_GAP, POSITION_WEIGHT

    nn, anchors, z, label, n_labels = tile
    before = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    ids, points, flat = kernel.map_quads(nn, anchors, len(z), False, z, label, n_labels, True,  # type: ignore[attr-defined]
                                         LABEL_GAP, POSITION_WEIGHT)
    middle = time.perf_counter()
    pts = np.frombuffer(points, np.float64).reshape(-1, 7)
    tree = kernel.quads_build(pts) if len(pts) else None  # type: ignore[attr-defined]
    end = time.perf_counter()
    after = resource.getrusage(resource.RUSAGE_SELF)
    usage[0] += after.ru_minflt - before.ru_minflt
    usage[1] += after.ru_stime - before.ru_stime
    usage[2] += after.ru_stime - before.ru_stime + after.ru_utime - before.ru_utime
    keep.append((flat, pts, tree))
    del keep[:-200]
    return (middle - start) * 1000.0, (end - middle) * 1000.0, bytes(ids) + bytes(points) + bytes(flat)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", default="main", metavar="REV", help="the revision compared with")
    parser.add_argument("--maps", default=",".join(EXTRACTS), help="maps measured (comma separated)")
    parser.add_argument("--tiles", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=5, help="runs a tile a kernel (the fastest kept)")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    from mapdb.match import _kernel

    maps = extract_maps([n for n in args.maps.split(",") if n], EXTRACTS, DATA, CACHE)
    with tempfile.TemporaryDirectory() as tmp:
        kernels = {"this tree": _kernel, f"baseline {args.baseline}": import_baseline(args.baseline, Path(tmp),
                                                                                     "match._kernel")}
        print(f"a tile's kernel calls, fastest of {args.repeats} runs a tile, ms (map_quads | quads_build):")
        keep: list = []
        for name in maps:
            ms: dict[str, tuple[list[float], list[float]]] = {label: ([], []) for label in kernels}
            usage = {label: [0.0, 0.0, 0.0] for label in kernels}
            same = True
            runs = 0
            for j, tile in enumerate(tile_inputs(maps[name], args.tiles, args.seed)):
                best = {label: [float("inf"), float("inf")] for label in kernels}
                outputs = {}
                order = list(kernels.items())
                for rep in range(args.repeats):
                    for label, kernel in order if (j + rep) % 2 == 0 else order[::-1]:
                        quads_ms, build_ms, outputs[label] = timed(kernel, tile, keep, usage[label])
                        best[label] = [min(best[label][0], quads_ms), min(best[label][1], build_ms)]
                runs += args.repeats
                same = same and len(set(outputs.values())) == 1
                for label in kernels:
                    ms[label][0].append(best[label][0])
                    ms[label][1].append(best[label][1])
            base = ms[f"baseline {args.baseline}"]
            for label, (quads_ms, build_ms) in ms.items():
                print(f"  {name:<14} {label:<15} median {statistics.median(quads_ms):6.2f} | "
                      f"{statistics.median(build_ms):6.2f}  p95 {p95(quads_ms):6.2f} | {p95(build_ms):6.2f}  "
                      f"sum ratio {sum(quads_ms) / sum(base[0]):.2f} | {sum(build_ms) / sum(base[1]):.2f}  "
                      f"faults a tile {usage[label][0] / runs:5.0f}, system time "
                      f"{usage[label][1] / usage[label][2]:.0%} of CPU")
            print(f"  {name:<14} outputs identical: {same}")


if __name__ == "__main__":
    main()
