"""The stored index of a map with blocks: its size, and the answers it gives against the in-memory search.

For each extract (default Monaco, from ``../shared/data/osm``): the map built with blocks (the default) and with
``--no-blocks``, each indexed with ``mapdb index`` (``SOURCE_DATE_EPOCH`` fixed, so the bytes repeat); point
images (``mapdb simulate``) and mask images (``mapdb simulate --render masks``) of the map with blocks, answered
by ``mapdb query`` three ways:

* **stored**: the map with blocks and its index (point images from the index, mask images in memory);
* **memory**: the same map without an index (both views searched in memory);
* **no-blocks + index**: the map built without blocks and its index.

It prints the index sizes, and per kind of image how many answers are accepted, how many are identical
(status, position, inliers, score) between the ways and how many give the same status and position, and the
median ``time_ms`` an image.  The in-memory search of point images looks up more quads than the index holds
(every triple of 8 neighbours against 4), so its scores differ from the stored index's where its positions agree.

Run from the repository root::

    nice python benchmarks/blocks_index.py
    nice python benchmarks/blocks_index.py --extracts monaco-2021-12-03 andorra-2021-06-22 --images 40
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DATA = _DATA if _DATA.is_dir() else Path("/work/shared/data")
MAPDB = [str(Path(sys.executable).parent / "mapdb")]
FIELDS = ("id", "status", "x", "y", "inliers", "score")


def run(*args: str) -> None:
    """Run one mapdb command quietly, failing loudly."""
    env = {**os.environ, "SOURCE_DATE_EPOCH": "1700000000"}
    subprocess.run([*MAPDB, *args], check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def answers(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def key(answer: dict) -> tuple:
    return tuple(answer.get(field) for field in FIELDS)


def extract_rows(name: str, work: Path, n: int) -> list[str]:
    """Build, index, simulate and query one extract; the table rows."""
    source = DATA / "osm" / f"{name}.osm.pbf"
    maps = {"blocks": work / f"{name}-blocks.mapdb", "plain": work / f"{name}-plain.mapdb"}
    run("build", str(source), "-o", str(maps["blocks"]), "-q")
    run("build", str(source), "-o", str(maps["plain"]), "-q", "--no-blocks")
    bare = work / f"{name}-bare.mapdb"
    shutil.copyfile(maps["blocks"], bare)
    sizes = {}
    for which, path in maps.items():
        run("index", str(path), "-q")
        sizes[which] = (Path(str(path) + ".qidx").stat().st_size, _count(path))
    rows = [f"| {name} | index bytes (bytes an object): with blocks {sizes['blocks'][0]:,} "
            f"({sizes['blocks'][0] / sizes['blocks'][1]:.1f}), without {sizes['plain'][0]:,} "
            f"({sizes['plain'][0] / sizes['plain'][1]:.1f}) | | | | |"]
    common = ["--n", str(n), "--altitude", "150", "--fov", "60", "--yaw", "random", "--seed", "3"]
    images = {"points": work / f"{name}-points.jsonl", "masks": work / f"{name}-masks.jsonl"}
    run("simulate", str(maps["blocks"]), *common, "--min-objects", "10", "-o", str(images["points"]))
    run("simulate", str(maps["blocks"]), *common, "--min-objects", "8", "--render", "masks", "--source", str(source),
        "--masks-dir", str(work / f"{name}-masks"), "-o", str(images["masks"]))
    for kind, path in images.items():
        got = {}
        for way, map_path in (("stored", maps["blocks"]), ("memory", bare), ("plain", maps["plain"])):
            out = work / f"{name}-{kind}-{way}.jsonl"
            run("query", str(map_path), str(path), "-o", str(out))
            got[way] = answers(out)
        s, m, p = ([key(a) for a in got[way]] for way in ("stored", "memory", "plain"))
        same = lambda a, b: sum(x == y for x, y in zip(a, b, strict=True))  # noqa: E731
        placed = lambda a, b: sum(x[:4] == y[:4] for x, y in zip(a, b, strict=True))  # noqa: E731
        ms = {way: statistics.median(a["time_ms"] for a in got[way]) for way in got}
        rows.append(f"| {name} | {kind} | {len(s)} | {sum(a[1] == 'ok' for a in s)} | "
                    f"{same(s, m)} ({placed(s, m)}) / {same(s, p)} ({placed(s, p)}) | "
                    f"{ms['stored']:.0f} / {ms['memory']:.0f} / {ms['plain']:.0f} |")
    return rows


def _count(path: Path) -> int:
    from mapdb.mapfile.reader import open_map

    with open_map(path) as m:
        return len(m)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--extracts", nargs="+", default=["monaco-2021-12-03"])
    parser.add_argument("--images", type=int, default=40)
    args = parser.parse_args()
    if not (DATA / "osm").is_dir():
        sys.exit(f"shared data not found at {DATA}")
    print("| extract | images | n | accepted (stored) | identical (same status and position): stored vs memory / "
          "vs no-blocks map + index "
          "| median time_ms: stored / memory / no-blocks + index |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.extracts:
            for row in extract_rows(name, Path(tmp), args.images):
                print(row, flush=True)


if __name__ == "__main__":
    main()
