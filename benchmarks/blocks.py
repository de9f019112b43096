"""Blocks of touching buildings (``mapdb build --blocks``): what they add to the map, and to mask matching.

Real data: ``../shared/data/osm`` Monaco and Andorra (and Liechtenstein for the storage table).  Prints four
tables:

1. **The gap**: the share of the extract's building outlines that touch a neighbour or lie within 0, 0.5,
   0.75, 1 and 2 m of one (:func:`mapdb.build.blocks.block_members`), and the ground size of a pixel of the
   rendered images at each altitude.
2. **Storage**: each map built with and without blocks (``SOURCE_DATE_EPOCH`` fixed): objects, blocks,
   file bytes, bytes an object, and the growth of the file.
3. **Masks**: per extract and altitude, images rendered with building heights (640x480, 60 degrees, random
   heading, level camera, at least 8 blobs, no mask noise: ``benchmarks/rendered_masks.py``'s images), each
   localized by one map built with blocks, twice side by side: with its blocks (mask blobs matched against
   buildings and blocks) and without (``Localizer(blocks=False)``: the map as if built with ``--no-blocks``),
   the order alternating image by image.  Columns: buildings in blocks (the map's), blobs an image (mean),
   blobs standing for a block (``truth.block``, mean), localized (correct answers within 2 m / images) with
   and without blocks and their difference in points, answers more than 2 m off with and without.
   Then, for the gap: of the whole blobs (not touching the border) that cover two or more buildings (each
   with at least a tenth of the blob's pixels), the share whose buildings all fall in one block at each gap;
   and the same in as many images rendered flat (no relief: the merges a mask's pixels alone make).
4. **Wrong places**: each extract's masks against the *other* extract's map, with its blocks and without:
   every answer accepted there is a false positive.
5. **Ideal centroids**: images of the ideal simulator (map objects at their projected centroids) of the map
   built without blocks, answered by it and by the map with blocks: the answers must be the same.

Run from the repository root::

    python benchmarks/blocks.py --n 60                  # 60 images a row
    python benchmarks/blocks.py --n 20 --altitudes 120  # quick
    python benchmarks/blocks.py --n 60 --gap 2          # maps whose blocks join buildings up to 2 m apart
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
_RELATIVE = ROOT.parent / "shared" / "data" / "osm"
DATA = _RELATIVE if _RELATIVE.exists() else Path("/work/shared/data/osm")
EXTRACTS = {"monaco": "monaco-2021-12-03.osm.pbf", "andorra": "andorra-2021-06-22.osm.pbf",
            "liechtenstein": "liechtenstein-2013-08-03.osm.pbf"}
MATCHED = ("monaco", "andorra")
ALTITUDES = (120.0, 200.0, 300.0)
GAPS = (0.0, 0.5, 0.75, 1.0, 2.0)
CAMERA = {"fov_deg": 60.0, "size": (640, 480), "yaw": "random", "min_objects": 8}


GAP = DEFAULT_GAP = 0.75  # the blocks' gap (metres) of the maps built: --gap


def build(cache: Path, name: str, blocks: bool) -> Path:
    """The extract's map with or without blocks (of gap :data:`GAP`), built once into ``cache`` (dates fixed: the
    bytes are the build's)."""
    from mapdb.build.pipeline import build_map

    path = cache / f"{name}-{f'blocks-{GAP:g}' if blocks else 'plain'}.mapdb"
    if not path.exists():
        os.environ.setdefault("SOURCE_DATE_EPOCH", "1700000000")
        build_map([DATA / EXTRACTS[name]], path, blocks=blocks, block_gap=GAP)
    return path


def gap_table(scenes: dict[str, Any]) -> None:
    from mapdb.build.blocks import block_members
    from mapdb.simulation.outlines import LAYER_BUILDING

    print("1. Buildings in blocks by gap (share of the extract's building outlines)\n")
    print(f"{'extract':<14} {'buildings':>9} " + " ".join(f"{f'{g:g} m':>7}" for g in GAPS))
    for name, scene in scenes.items():
        outlines = scene.geometry[scene.layer == LAYER_BUILDING]
        shares = [(block_members(outlines, g) >= 0).mean() for g in GAPS]
        print(f"{name:<14} {outlines.size:>9,} " + " ".join(f"{s:>7.1%}" for s in shares))
    pixel = {a: 2 * a * math.tan(math.radians(CAMERA["fov_deg"] / 2)) / CAMERA["size"][0] for a in ALTITUDES}
    print("ground pixel, 640 px over 60 degrees: " + ", ".join(f"{p:.2f} m at {a:.0f} m" for a, p in pixel.items()))


def storage_table(cache: Path) -> None:
    from mapdb.mapfile.reader import open_map

    print("\n2. Storage (bytes of the map file)\n")
    print(f"{'extract':<14} {'objects':>8} {'blocks':>7} {'bytes':>8} {'B/object':>9} {'no-blocks bytes':>15} "
          f"{'B/object':>9} {'file growth':>11}")
    for name in EXTRACTS:
        sizes = {}
        for blocks in (True, False):
            path = build(cache, name, blocks)
            with open_map(path) as m:
                sizes[blocks] = (len(m), m.label_counts.get("building_block", 0), path.stat().st_size)
        (n, b, size), (n0, _, size0) = sizes[True], sizes[False]
        print(f"{name:<14} {n:>8,} {b:>7,} {size:>8,} {size / n:>9.2f} {size0:>15,} {size0 / n0:>9.2f} "
              f"{size / size0 - 1:>+11.1%}")


def masks(m: Any, scene: Any, n: int, altitude: float, seed: int, heights: bool = True) -> list[dict]:
    from mapdb.simulation.rendered import simulate_masks

    return [doc for doc, _ in simulate_masks(m, scene, n, altitude=altitude, seed=seed, heights=heights, **CAMERA)]


def answer_both(m: Any, images: list[dict]) -> dict[bool, list[Any]]:
    """Each image answered with the map's blocks and without, alternating which goes first."""
    from mapdb.localize.localizer import Localizer

    localizers = {True: Localizer(m, blocks=True), False: Localizer(m, blocks=False)}
    answers: dict[bool, list[Any]] = {True: [], False: []}
    for i, im in enumerate(images):
        for blocks in ((True, False) if i % 2 == 0 else (False, True)):
            answers[blocks].append(localizers[blocks].localize(im))
    return answers


def tally(images: list[dict], answers: list[Any]) -> tuple[int, list[float]]:
    """Correct answers (within 2 m) and the errors of those more than 2 m off."""
    errors = [math.hypot(a.x - im["truth"]["x"], a.y - im["truth"]["y"]) for im, a in zip(images, answers) if a.ok]
    return sum(e <= 2.0 for e in errors), sorted(e for e in errors if e > 2.0)


def mask_rows(maps: dict[str, Path], scenes: dict[str, Any], n: int, seed: int, altitudes: tuple[float, ...]
              ) -> dict[str, dict[float, list[dict]]]:
    from mapdb.mapfile.reader import open_map

    print(f"\n3. Rendered masks with building heights, {n} images a row: localized with and without blocks\n")
    print(f"{'extract':<9} {'alt m':>5} {'in blocks':>9} {'blobs':>6} {'block blobs':>11} {'with':>7} {'without':>7} "
          f"{'gain':>6}  {'>2 m off with / without'}")
    made: dict[str, dict[float, list[dict]]] = {}
    for name in MATCHED:
        with open_map(maps[name]) as m:
            in_blocks = _buildings_in_blocks(scenes[name])
            made[name] = {}
            for altitude in altitudes:
                images = masks(m, scenes[name], n, altitude, seed)
                made[name][altitude] = images
                answers = answer_both(m, images)
                (good, off), (good0, off0) = tally(images, answers[True]), tally(images, answers[False])
                blobs = statistics.mean(len(im["objects"]) for im in images)
                block_blobs = statistics.mean(sum(im["truth"]["block"]) for im in images)
                print(f"{name:<9} {altitude:>5.0f} {in_blocks:>9.1%} {blobs:>6.1f} {block_blobs:>11.1f} "
                      f"{good / n:>7.1%} {good0 / n:>7.1%} {100 * (good - good0) / n:>+6.1f}  "
                      f"{_errors(off)} / {_errors(off0)}")
    return made


def merges_explained(maps: dict[str, Path], scenes: dict[str, Any], made: dict[str, dict[float, list[dict]]],
                     seed: int) -> None:
    """Whole merged blobs whose buildings are one block, at each gap (the gap's measure), in the images with
    heights and in as many rendered flat."""
    from mapdb.mapfile.reader import open_map

    flat: dict[str, dict[float, list[dict]]] = {}
    for name, rows in made.items():
        with open_map(maps[name]) as m:
            flat[name] = {a: masks(m, scenes[name], len(images), a, seed, heights=False) for a, images in rows.items()}
    for title, images in (("with heights", made), ("flat", flat)):
        _merges_table(scenes, images, title)


def _merges_table(scenes: dict[str, Any], made: dict[str, dict[float, list[dict]]], title: str) -> None:
    import numpy as np

    from mapdb.build.blocks import block_members
    from mapdb.simulation.outlines import LAYER_BUILDING

    print(f"\nWhole blobs covering two or more buildings, rendered {title}: share whose buildings are one block, "
          "by gap\n")
    print(f"{'extract':<9} {'alt m':>5} {'merged':>6} " + " ".join(f"{f'{g:g} m':>7}" for g in GAPS))
    for name, rows in made.items():
        scene = scenes[name]
        shapes = np.flatnonzero((scene.layer == LAYER_BUILDING) & (scene.map_index >= 0))
        groups = {g: dict(zip(scene.map_index[shapes].tolist(), block_members(scene.geometry[shapes], g).tolist(),
                              strict=True)) for g in GAPS}
        for altitude, images in rows.items():
            merged = []
            for im in images:
                for o, covers, px in zip(im["objects"], im["truth"]["covers"], im["truth"]["cover_px"], strict=True):
                    big = [j for j, p in zip(covers, px, strict=True) if j in groups[GAPS[0]] and p >= 0.1 * sum(px)]
                    if not o.get("border") and len(big) >= 2:
                        merged.append(big)
            shares = [sum(len({groups[g][j] for j in big}) == 1 and groups[g][big[0]] >= 0 for big in merged)
                      / max(len(merged), 1) for g in GAPS]
            print(f"{name:<9} {altitude:>5.0f} {len(merged):>6} " + " ".join(f"{v:>7.1%}" for v in shares))


def _buildings_in_blocks(scene: Any) -> float:
    from mapdb.build.blocks import block_members
    from mapdb.simulation.outlines import LAYER_BUILDING

    return float((block_members(scene.geometry[scene.layer == LAYER_BUILDING], GAP) >= 0).mean())


def _errors(errors: list[float]) -> str:
    return f"{len(errors)}" + (f" ({', '.join(f'{e:.1f}' for e in errors)} m)" if errors else "")


def wrong_places(maps: dict[str, Path], made: dict[str, dict[float, list[dict]]]) -> None:
    from mapdb.mapfile.reader import open_map

    print("\n4. Wrong places: each extract's masks against the other extract's map (accepted = false positive)\n")
    print(f"{'masks of':<9} {'map of':<9} {'images':>6} {'accepted with blocks':>20} {'without':>8}")
    for name, other in ((MATCHED[0], MATCHED[1]), (MATCHED[1], MATCHED[0])):
        images = [im for rows in made[name].values() for im in rows]
        with open_map(maps[other]) as m:
            answers = answer_both(m, images)
        print(f"{name:<9} {other:<9} {len(images):>6} {sum(a.ok for a in answers[True]):>20} "
              f"{sum(a.ok for a in answers[False]):>8}")


def ideal(cache: Path, n: int, seed: int, altitudes: tuple[float, ...]) -> None:
    from mapdb.localize.localizer import Localizer
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.simulate import simulate_images

    print(f"\n5. Ideal centroids ({n} images a row, of the map without blocks): answered by both maps\n")
    print(f"{'extract':<9} {'alt m':>5} {'localized (no blocks)':>21} {'localized (blocks)':>18} {'same answers':>12}")
    for name in MATCHED:
        with open_map(build(cache, name, False)) as plain, open_map(build(cache, name, True)) as blocked:
            for altitude in altitudes:
                images = simulate_images(plain, n, altitude=altitude, seed=seed, **CAMERA)
                a, b = Localizer(plain), Localizer(blocked)
                got = [(a.localize(im), b.localize(im)) for im in images]
                same = sum((x.status, x.x, x.y) == (y.status, y.x, y.y) for x, y in got)
                good = [tally(images, [g[k] for g in got])[0] for k in (0, 1)]
                print(f"{name:<9} {altitude:>5.0f} {good[0] / n:>21.1%} {good[1] / n:>18.1%} {same:>8}/{n}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=60, help="images a row")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--altitudes", type=float, nargs="+", default=list(ALTITUDES))
    parser.add_argument("--gap", type=float, default=DEFAULT_GAP, help="the blocks' gap of the maps, metres")
    args = parser.parse_args()
    global GAP
    GAP = args.gap
    missing = [p for p in EXTRACTS.values() if not (DATA / p).exists()]
    if missing:
        sys.exit(f"real data not found in {DATA}: {', '.join(missing)}")
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.outlines import read_scene

    cache = Path(tempfile.gettempdir()) / "mapdb-bench-blocks"
    cache.mkdir(exist_ok=True)
    maps = {name: build(cache, name, True) for name in MATCHED}
    scenes = {}
    for name in MATCHED:
        with open_map(maps[name]) as m:
            scenes[name] = read_scene(DATA / EXTRACTS[name], m.all(), seed=args.seed)
    altitudes = tuple(args.altitudes)
    gap_table(scenes)
    storage_table(cache)
    made = mask_rows(maps, scenes, args.n, args.seed, altitudes)
    merges_explained(maps, scenes, made, args.seed)
    wrong_places(maps, made)
    ideal(cache, args.n, args.seed, altitudes)


if __name__ == "__main__":
    main()
