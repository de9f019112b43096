"""What binding a quad index to its map costs: opening it, the exact position check, lost-in-space answers.

For each map given (its index ``MAP.qidx`` built beside it by ``mapdb index MAP``), prints a table of:

* **open warm**: ``open_map`` then ``StoredQuadIndex.for_map`` (the index opened and checked against the
  map: its header's ``map`` section), files in the page cache: median and fastest of ``--repeat`` runs (on
  a shared machine the fastest run is the one least disturbed);
* **open cold**: the same with both files dropped from the page cache first (``posix_fadvise DONTNEED``;
  a file another process holds open may stay cached);
* **positions**: the exact check of every coordinate against ``MetaMap.all()`` that the localizer makes for
  a map it holds whole: the comparison only (the localizer decodes the map for its object index anyway),
  median;
* **first**: with ``--images``, a fresh process's first answer as ``mapdb query`` meets it: ``open_map``, a
  new ``Localizer`` and its first image without prior (the index opened and checked, the position check,
  the object index built, the answer), median of ``--repeat`` / 5 runs (min 3);
* **answer**: with ``--images``, the median time of ``Localizer.localize`` per image without prior (the
  stored index's lookups, with their checks, and the rest of the answer), after a first image.

Run the same command with an older tree first on ``PYTHONPATH`` to compare (an index of format 1 for it:
build the maps' indexes with that tree), for example::

    python benchmarks/index_binding.py andorra.mapdb helsinki.mapdb --images andorra.jsonl helsinki.jsonl
    PYTHONPATH=/tmp/old-tree python benchmarks/index_binding.py old/andorra.mapdb ...
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

from mapdb.localize.localizer import Localizer
from mapdb.mapfile.reader import open_map
from mapdb.match.index.stored import StoredQuadIndex, index_path


def _drop_cache(path: str) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def _open_ms(map_path: str, cold: bool) -> float:
    if cold:
        _drop_cache(map_path)
        _drop_cache(str(index_path(map_path)))
    start = time.perf_counter()
    with open_map(map_path) as m:
        ix = StoredQuadIndex.for_map(m)
        assert ix is not None, f"{map_path}: no index beside it (mapdb index {map_path})"
        elapsed = time.perf_counter() - start
        ix.close()
    return elapsed * 1000.0


def _positions_ms(map_path: str) -> float | None:
    with open_map(map_path) as m, StoredQuadIndex.for_map(m) as ix:
        if not hasattr(ix, "check_positions"):
            return None  # a tree from before the binding
        objects = m.all()
        start = time.perf_counter()
        ix.check_positions(objects.x, objects.y)
        return (time.perf_counter() - start) * 1000.0


def _answer_ms(map_path: str, images_path: str) -> tuple[float, int, int]:
    images = [json.loads(line) for line in open(images_path) if line.strip()]
    with open_map(map_path) as m:
        localizer = Localizer(m)
        localizer.localize(images[0])  # the first answer opens the index and builds the object index
        times, ok = [], 0
        for image in images:
            start = time.perf_counter()
            ok += localizer.localize(image).ok
            times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times), ok, len(images)


def _first_ms(map_path: str, images_path: str) -> float:
    with open(images_path) as f:
        image = json.loads(f.readline())
    start = time.perf_counter()
    with open_map(map_path) as m:
        Localizer(m).localize(image)
    return (time.perf_counter() - start) * 1000.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("maps", nargs="+")
    parser.add_argument("--images", nargs="*", default=[], help="an images file per map, in the same order")
    parser.add_argument("--repeat", type=int, default=30)
    args = parser.parse_args()
    print(f"{'map':16} {'open warm ms (min)':>18} {'open cold ms':>12} {'positions ms':>12} {'first ms':>9} "
          f"{'answer ms':>10}  ok")
    for i, map_path in enumerate(args.maps):
        warm_runs = [_open_ms(map_path, False) for _ in range(args.repeat)]
        warm = f"{statistics.median(warm_runs):.2f} ({min(warm_runs):.2f})"
        cold = statistics.median(_open_ms(map_path, True) for _ in range(max(3, args.repeat // 5)))
        pos = [_positions_ms(map_path) for _ in range(max(3, args.repeat // 5))]
        pos_text = "-" if pos[0] is None else f"{statistics.median(p for p in pos if p is not None):.2f}"
        first, answer, ok = "-", "-", ""
        if i < len(args.images):
            runs = [_first_ms(map_path, args.images[i]) for _ in range(max(3, args.repeat // 5))]
            first = f"{statistics.median(runs):.1f}"
            ms, n_ok, n = _answer_ms(map_path, args.images[i])
            answer, ok = f"{ms:.1f}", f"{n_ok}/{n}"
        print(f"{os.path.basename(map_path):16} {warm:>18} {cold:12.2f} {pos_text:>12} {first:>9} {answer:>10}  {ok}")


if __name__ == "__main__":
    main()
