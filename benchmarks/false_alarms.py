"""Places not in the map: how often are they accepted?  And places in the map: how often localized?

Images are simulated over each real extract of ``../shared/data/osm`` (Monaco, Andorra, Liechtenstein;
all labels, random heading, 100-300 m, 35-60 degrees, 1 px and 0.05 degree errors, at least 6 objects),
then localized twice with no prior: against their own extract's map (they should be localized) and
against one map holding the other two extracts (they must be rejected: the place is not in the map).
With ``--world N``, the same images are also queried against a synthetic world of at least N objects
assembled from rotated copies of the other two extracts (``benchmarks/synthetic_world.py``).

``--baseline REV`` runs the matcher of an earlier commit on the same images in the same run, so the
figures compare side by side on this shared, noisy machine.

Run from the repository root::

    python benchmarks/false_alarms.py --n 1000                      # 3,000 images of each kind
    python benchmarks/false_alarms.py --n 300 --baseline 98b7ab6    # with the matcher before issue 8

Prints, per extract and in all: accepted / images against the other extracts (false alarms), the best
score any such image reached, localized / images against the own map, and the median time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import as_json, cached_maps, import_baseline, shared_data  # noqa: E402

DATA = shared_data("osm")
EXTRACTS = {
    "monaco": "monaco-2021-12-03.osm.pbf",
    "andorra": "andorra-2021-06-22.osm.pbf",
    "liechtenstein": "liechtenstein-2013-08-03.osm.pbf",
}
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-maps"


def build_maps() -> dict[str, Path]:
    """The extracts' maps, built once into a cache outside the repository."""
    return cached_maps(EXTRACTS, DATA, CACHE)


def _objects(path: Path):
    from mapdb.mapfile.reader import open_map

    with open_map(path) as m:
        # One nominal CRS: the extracts lie in UTM 31 and 32 but far apart; only patterns matter here.
        return dataclasses.replace(m.all(), crs="EPSG:32632")


def write_cases(maps: dict[str, Path], n: int, seed: int, world: int, workdir: Path) -> list[dict]:
    """Maps (own, the other two, optionally a world) and images, written for the worker processes."""
    from mapdb.mapfile.queries import MemoryMap
    from mapdb.mapfile.writer import write_map
    from mapdb.objects import concat
    from mapdb.simulation.simulate import simulate_images

    objects = {name: _objects(path) for name, path in maps.items()}
    cases = []
    for name in EXTRACTS:
        others = [objects[o] for o in EXTRACTS if o != name]
        own_path = workdir / f"{name}.mapdb"
        other_path = workdir / f"not-{name}.mapdb"
        write_map(own_path, objects[name])
        write_map(other_path, concat(others))
        images = simulate_images(MemoryMap(objects[name]), n, altitude=(100, 300), fov_deg=(35, 60), yaw="random",
                                 pixel_std=1.0, attitude_std=0.05, min_objects=6, seed=seed)
        images_path = workdir / f"{name}.jsonl"
        images_path.write_text("".join(json.dumps(im) + "\n" for im in images))
        targets = {"own": own_path, "others": other_path}
        if world:
            from synthetic_world import synthetic_world

            from mapdb.match.index.stored import build_index

            world_path = workdir / f"world-not-{name}.mapdb"
            write_map(world_path, dataclasses.replace(
                synthetic_world([maps[o] for o in EXTRACTS if o != name], world, seed), crs="EPSG:32632"))
            # Its stored lost-in-space index: an in-memory one for a million objects takes 13.6 GB.
            build_index(world_path)
            targets["world"] = world_path
        cases.append({"extract": name, "images": str(images_path), "maps": {k: str(v) for k, v in targets.items()}})
    return cases


def localize_all(localize, store, cases: list[dict]) -> list[dict]:
    """Every case's images against every target map, with one version's ``localize`` and ``open_map``."""
    out = []
    for case in cases:
        images = [json.loads(line) for line in open(case["images"])]
        for target, path in case["maps"].items():
            with store.open_map(path) as m:
                localize(images[0], m)  # builds the whole map's index once, outside the timing
                for im in images:
                    start = time.perf_counter()
                    a = as_json(localize(im, m))
                    ms = (time.perf_counter() - start) * 1000.0
                    scores = [c["score"] for c in a.get("candidates", []) if c.get("score") is not None]
                    best = a["score"] if a["status"] == "ok" else max(scores, default=None)
                    err = (math.hypot(a["x"] - im["truth"]["x"], a["y"] - im["truth"]["y"])
                           if a["status"] == "ok" else None)
                    out.append({"extract": case["extract"], "target": target, "status": a["status"],
                                "score": best, "error_m": err, "ms": ms})
    return out


def table(rows: list[dict], label: str) -> None:
    print(f"\n{label}")
    print(f"  {'extract':<14} {'target':<8} {'images':>6} {'accepted':>9} {'correct':>8} {'best score':>10} "
          f"{'median ms':>9}")
    groups = sorted({(r["extract"], r["target"]) for r in rows}, key=lambda g: (g[1], g[0]))
    for target in sorted({g[1] for g in groups}):
        for extract in [*EXTRACTS, "all"]:
            sel = [r for r in rows if r["target"] == target and (extract == "all" or r["extract"] == extract)]
            if not sel:
                continue
            accepted = [r for r in sel if r["status"] == "ok"]
            correct = sum(1 for r in accepted if r["error_m"] is not None and r["error_m"] <= 2.0)
            best = max((r["score"] for r in sel if r["score"] is not None), default=math.nan)
            print(f"  {extract:<14} {target:<8} {len(sel):6d} {len(accepted):9d} {correct:8d} {best:10.2f} "
                  f"{statistics.median(r['ms'] for r in sel):9.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=1000, help="images per extract")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--world", type=int, default=0, help="also a synthetic world of at least N objects")
    parser.add_argument("--baseline", metavar="REV", help="also run the matcher of this git revision")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"skipped: {DATA} not found (the real extracts are needed)")
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        cases = write_cases(build_maps(), args.n, args.seed, args.world, workdir)
        from mapdb.localize import localizer as tree_localize
        from mapdb.mapfile import reader as tree_reader

        table(localize_all(tree_localize.localize, tree_reader, cases), "this tree")
        if args.baseline:
            old = import_baseline(args.baseline, workdir)
            # The baseline has no stored index: its whole-map index of a world would be built in memory.
            local = [{**case, "maps": {k: v for k, v in case["maps"].items() if k != "world"}} for case in cases]
            table(localize_all(old.localize, import_baseline(args.baseline, workdir, "store"), local),
                  f"baseline {args.baseline}")

if __name__ == "__main__":
    main()
