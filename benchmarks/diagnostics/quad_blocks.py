"""A block of a prior's tiles looked up as one: its tiles' trees searched together (``QuadBlock``) against one tree
built over their quads (``QuadIndex.merged``, what the localizer built before); the figures behind ``QuadBlock``'s
docstring and the localizer's choice.

The images are ``benchmarks/matcher_core.py``'s (300 m prior, seed 3).  Each is answered by the localizer; every
lookup made in a block of tiles is recorded (its image quads, radii, ``k`` and disc), then replayed: per map, the
blocks met, the median and p95 ms to merge a block (concatenate and build its tree), the median ms per image of its
lookups through the merged tree and through the block's tiles together (the block kept from merging itself), and
whether every hit is the same.  Run from the
repository root::

    python benchmarks/diagnostics/quad_blocks.py --maps andorra,monaco,liechtenstein --images 100
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cached_maps  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, p95, simulated  # noqa: E402


def recorded_lookups(path: Path, images: list[dict]) -> list[tuple]:
    """The lookups the images make in blocks of tiles: (block, invariants, labels, radius, k, near) each."""
    from mapdb.localize.localizer import localize
    from mapdb.mapfile.reader import open_map
    from mapdb.match import hypotheses
    from mapdb.match.quad_block import QuadBlock

    calls: list[tuple] = []
    plain = hypotheses.lookup_parts

    def recording(parts, invariants, labels, radius, k):  # type: ignore[no-untyped-def]
        if len(parts) == 1 and isinstance(parts[0][0], QuadBlock):
            calls.append((parts[0][0], invariants.copy(), labels.copy(), radius.copy(), k, parts[0][1]))
        return plain(parts, invariants, labels, radius, k)

    hypotheses.lookup_parts = recording  # an instrument, not a change: the same function answers
    try:
        with open_map(path) as m:
            for im in images:
                localize(im, m)
    finally:
        hypotheses.lookup_parts = plain
    return calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default=",".join(EXTRACTS))
    parser.add_argument("--images", type=int, default=100)
    args = parser.parse_args()
    from mapdb.match.quads import QuadIndex

    print(f"{'map':<14} {'blocks':>6} {'lookups':>7} {'merge ms':>9} {'merge p95':>9} {'merged ms/lookup':>16} "
          f"{'block ms/lookup':>15} {'identical':>9}")
    for name in args.maps.split(","):
        path = cached_maps({name: EXTRACTS[name]}, DATA, CACHE)[name]
        calls = recorded_lookups(path, simulated(path, args.images, 3))
        blocks = {id(c[0]): c[0] for c in calls}
        merge_ms, merged = [], {}
        for key, block in blocks.items():
            block.merged_index = None  # replayed through its tiles together (the answer would merge it once used often)
            start = time.perf_counter()
            merged[key] = QuadIndex.merged(block.parts)
            merge_ms.append((time.perf_counter() - start) * 1000.0)
        times: dict[str, list[float]] = {"merged": [], "block": []}
        same = True
        for j, (block, *ask) in enumerate(calls):
            got = {}
            for label in ("merged", "block") if j % 2 == 0 else ("block", "merged"):  # alternating, one load
                index = merged[id(block)] if label == "merged" else block
                block.lookups = 0
                start = time.perf_counter()
                got[label] = index.lookup(*ask)
                times[label].append((time.perf_counter() - start) * 1000.0)
            same = same and all(np.array_equal(a, b) for a, b in zip(got["merged"], got["block"], strict=True))
        if not calls:
            print(f"{name:<14} {0:>6} {0:>7}   (no image looked up in a block)")
            continue
        print(f"{name:<14} {len(blocks):>6} {len(calls):>7} {statistics.median(merge_ms):9.2f} {p95(merge_ms):9.2f} "
              f"{statistics.median(times['merged']):16.3f} {statistics.median(times['block']):15.3f} {same!s:>9}")


if __name__ == "__main__":
    main()
