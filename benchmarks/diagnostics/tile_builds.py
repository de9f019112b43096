"""A prior's first visit of a map tile, this tree's against a baseline revision's: the tile's objects read from the map
(``query_bbox`` of the tile and its ``TILE_PAD_M`` of neighbours) and its quad index built (``QuadIndex`` with
positions), what ``Localizer._tile`` does, on the tiles ``benchmarks/matcher_core.py``'s simulated images (its ``--n``
and seed, 300 m priors) first reach, in the order they reach them.

Each tile is built ``--repeats`` times a version, the two taking turns (which goes first alternates), and its fastest
run kept (the least disturbed by the machine's other work); the map's pages are decoded before (the same decoder in
both).  Per map: the median, p95 and sum over tiles of those ms, the ratio of this tree's sum to the baseline's, and
whether every tile's objects, quads and tree points are the same.  Run from the repository root::

    python benchmarks/diagnostics/tile_builds.py --baseline main
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import extract_maps, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, gauge_ms, p95, simulated  # noqa: E402


def first_visits(path: Path, n: int, seed: int) -> list[tuple[int, int]]:
    """The tiles (ix, iy) this tree's localizer builds answering ``n`` simulated images with priors, in order."""
    from mapdb.localize import localizer
    from mapdb.mapfile.reader import open_map

    images = simulated(path, n, seed)
    built: list[tuple[int, int]] = []
    tile = localizer.Localizer._tile

    def recorded(self: localizer.Localizer, ix: int, iy: int) -> object:
        if (ix, iy) not in self._tiles:
            built.append((ix, iy))
        return tile(self, ix, iy)

    localizer.Localizer._tile = recorded  # type: ignore[method-assign]
    try:
        with open_map(path) as m:
            for image in images:
                localizer.localize(image, m)
    finally:
        localizer.Localizer._tile = tile  # type: ignore[method-assign]
    return built


def build(version: tuple, m: object, ix: int, iy: int) -> tuple[float, tuple]:
    """One tile as ``Localizer._tile`` builds it, with ``version``'s (QuadIndex, TILE_SIZE_M, TILE_PAD_M): ms, and what
    it made (objects, quads, tree points)."""
    index_class, t, pad = version
    start = time.perf_counter()
    x0, y0 = ix * t, iy * t
    objects = m.query_bbox(x0 - pad, y0 - pad, x0 + t + pad, y0 + t + pad)  # type: ignore[attr-defined]
    anchors = (objects.x >= x0) & (objects.x < x0 + t) & (objects.y >= y0) & (objects.y < y0 + t)
    index = index_class(objects, 8, anchors=anchors, positions=True)
    ms = (time.perf_counter() - start) * 1000.0
    made = (objects.x.tobytes() + objects.y.tobytes() + objects.label.tobytes(), index.quad_z.tobytes(),
            b"" if index.tree is None else index.tree.data.tobytes())
    return ms, made


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", default="main", metavar="REV", help="the revision compared with")
    parser.add_argument("--maps", default=",".join(EXTRACTS), help="maps measured (comma separated)")
    parser.add_argument("--n", type=int, default=100, help="simulated images a map")
    parser.add_argument("--repeats", type=int, default=5, help="builds of a tile a version (the fastest kept)")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    from mapdb.localize.localizer import TILE_PAD_M, TILE_SIZE_M
    from mapdb.mapfile.reader import open_map
    from mapdb.match.quads import QuadIndex

    maps = extract_maps([n for n in args.maps.split(",") if n], EXTRACTS, DATA, CACHE)
    with tempfile.TemporaryDirectory() as tmp:
        old = import_baseline(args.baseline, Path(tmp), "localize.localizer")
        old_quads = import_baseline(args.baseline, Path(tmp), "match.quads")
        old_reader = import_baseline(args.baseline, Path(tmp), "mapfile.reader")
        versions = {"this tree": ((QuadIndex, TILE_SIZE_M, TILE_PAD_M), open_map),
                    f"baseline {args.baseline}": ((old_quads.QuadIndex, old.TILE_SIZE_M, old.TILE_PAD_M),
                                                  old_reader.open_map)}
        print(f"a tile's first build (query_bbox and QuadIndex), fastest of {args.repeats} a tile, ms; load average "
              f"{os.getloadavg()[0]:.1f}, gauge {gauge_ms():.1f} ms:")
        for name in maps:
            tiles = first_visits(maps[name], args.n, args.seed)
            opened = {label: opener(maps[name]) for label, (_, opener) in versions.items()}
            for m in opened.values():
                m.all()  # every page decoded once: the decoder is not what is compared
            ms: dict[str, list[float]] = {label: [] for label in versions}
            same = True
            order = list(versions)
            for j, (ix, iy) in enumerate(tiles):
                best = dict.fromkeys(versions, float("inf"))
                made = {}
                for rep in range(args.repeats):
                    for label in order if (j + rep) % 2 == 0 else order[::-1]:
                        took, made[label] = build(versions[label][0], opened[label], ix, iy)
                        best[label] = min(best[label], took)
                same = same and made[order[0]] == made[order[1]]
                for label in versions:
                    ms[label].append(best[label])
            for m in opened.values():
                m.close()
            base = sum(ms[order[1]])
            for label, values in ms.items():
                print(f"  {name:<14} {label:<17} {len(values)} tiles  median {statistics.median(values):6.3f}  p95 "
                      f"{p95(values):6.3f}  sum {sum(values):8.2f} ms  ({sum(values) / base:.2f} of the baseline's)")
            print(f"  {name:<14} objects, quads and tree points identical: {same}")


if __name__ == "__main__":
    main()
