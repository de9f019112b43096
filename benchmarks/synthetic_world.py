"""Synthetic worlds of millions of objects, assembled from copies of real maps.

Each copy is one real map's objects rotated by a random angle about the map's centre and moved to a
free slot of a square grid whose slots are wider than any map's diagonal, so copies never overlap.
Rotation keeps every pattern of the map, so a world is as realistic, place by place, as the maps it
is made of (and as repetitive as the number of copies makes it).  Used to measure the lost-in-space
index at country scale (``benchmarks/lost_in_space_index.py``) and false alarms: images of one
extract against a world assembled from the others.

    python benchmarks/synthetic_world.py 1000000 -o /tmp/world-1M.mapdb

builds the three extracts of ``../shared/data/osm`` (cached under ``/tmp``) and writes a world of at
least 1,000,000 objects.  ``--extract`` (repeatable) picks the extracts.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from _baseline import code_digest, shared_data

from mapdb.build.pipeline import build_map
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects, concat

DATA = shared_data("osm")
EXTRACTS = ("andorra-2021-06-22.osm.pbf", "liechtenstein-2013-08-03.osm.pbf", "monaco-2021-12-03.osm.pbf")
CACHE = Path("/tmp/mapdb-synthetic-cache")
SLOT_MARGIN_M = 1000.0


def synthetic_world(map_paths: Sequence[str | Path], n_objects: int, seed: int = 0, *,
                    jitter_m: float = 0.0) -> Objects:
    """A world of at least ``n_objects`` objects from rotated, translated copies of the given maps.

    Copies take the maps in turn (first, second, ..., first again) until the world holds ``n_objects``;
    each is rotated by a uniform random angle about its map's bounding-box centre and centred on a
    random free slot of a square grid of slots ``max diagonal + 1 km`` wide.  The world has the first
    map's CRS (its coordinates start at that map's south-west corner) and the union of the maps' labels.

    Parameters
    ----------
    map_paths : sequence of paths
        ``.mapdb`` files (at least one, none empty).
    n_objects : int
        Least number of objects in the world.
    seed : int
        Angles and slots (and jitter) depend only on it.
    jitter_m : float
        Standard deviation (metres, per axis) of a random displacement of every object of every copy.
        0 (the default) keeps copies exact, so that every pattern of a map recurs once per copy; a few
        metres make each copy a distinct place that resembles its original, as towns resemble each other.

    Returns
    -------
    Objects
    """
    if not map_paths:
        raise ValueError("no maps to assemble a world from")
    maps = []
    for path in map_paths:
        with open_map(path) as m:
            o = m.all()
        if not len(o):
            raise ValueError(f"{path}: empty map")
        maps.append(o)
    labels = tuple(concat([Objects.empty(o.labels) for o in maps]).labels)
    maps = [o.relabel(labels) for o in maps]
    centres = [complex((o.x.min() + o.x.max()) / 2, (o.y.min() + o.y.max()) / 2) for o in maps]
    radius = max(float(np.abs(o.x + 1j * o.y - c).max()) for o, c in zip(maps, centres))
    slot = 2.0 * radius + SLOT_MARGIN_M
    sizes = [len(o) for o in maps]
    copies = []
    total = 0
    while total < n_objects or not copies:
        which = len(copies) % len(maps)
        copies.append(which)
        total += sizes[which]
    side = math.ceil(math.sqrt(len(copies)))
    rng = np.random.default_rng(seed)
    slots = rng.permutation(side * side)[: len(copies)]
    angles = rng.uniform(0.0, 2.0 * math.pi, len(copies))
    x0, y0 = float(maps[0].x.min()), float(maps[0].y.min())
    parts = []
    for which, s, angle in zip(copies, slots, angles):
        o = maps[which]
        w = (o.x + 1j * o.y - centres[which]) * complex(math.cos(angle), math.sin(angle))
        w += complex(x0 + (s % side + 0.5) * slot, y0 + (s // side + 0.5) * slot)
        if jitter_m > 0:
            w += jitter_m * (rng.standard_normal(w.size) + 1j * rng.standard_normal(w.size))
        parts.append(Objects(w.real, w.imag, o.label, o.area, labels, maps[0].crs))
    return concat(parts, labels=labels)


def extract_maps(extracts: Sequence[str] = EXTRACTS, cache: Path = CACHE) -> list[Path]:
    """Maps of the OSM extracts in ``../shared/data/osm``, built once into ``cache`` by this tree's map-writing
    code (its digest in the file name: a map built by other code is not reused)."""
    cache.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in extracts:
        out = cache / f"{name.split('-')[0]}.{code_digest()}.mapdb"
        if not out.exists():
            build_map([DATA / name], out)
        paths.append(out)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("objects", type=int, help="least number of objects in the world")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the world's .mapdb file")
    parser.add_argument("--extract", action="append", help=f"OSM extract in {DATA} (default: all three)")
    parser.add_argument("--cache", type=Path, default=CACHE, help="where the extracts' maps are built")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jitter", type=float, default=0.0, help="displace every object by this (m, 1 sigma)")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to assemble", file=sys.stderr)
        return 1
    start = time.perf_counter()
    maps = extract_maps(args.extract or EXTRACTS, args.cache)
    world = synthetic_world(maps, args.objects, args.seed, jitter_m=args.jitter)
    write_map(args.output, world, metadata={"synthetic_world": {
        "maps": [p.name for p in maps], "objects": args.objects, "seed": args.seed, "jitter_m": args.jitter}})
    print(f"{args.output}: {len(world)} objects from copies of {', '.join(p.name for p in maps)} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
