"""cProfile of the fast matcher over ``benchmarks/matcher_core.py``'s images: where an image's time goes now.

The images are matcher_core's (300 m, 60 degrees, random heading, 1 px, a 300 m prior; seed 3), answered once to
warm the map's tiles and indexes, timed once (the median printed), then answered again under cProfile; the table
is cProfile's, sorted by ``--sort`` (divide by ``--images`` for a figure an image).  ``--no-prior`` drops the prior.

Run from the repository root::

    python benchmarks/diagnostics/profile_images.py andorra --images 100
    python benchmarks/diagnostics/profile_images.py andorra --images 100 --no-prior --sort cumulative
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cached_maps  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, simulated  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", choices=sorted(EXTRACTS))
    parser.add_argument("--images", type=int, default=100)
    parser.add_argument("--no-prior", action="store_true")
    parser.add_argument("--sort", default="tottime")
    parser.add_argument("--rows", type=int, default=40)
    args = parser.parse_args()
    from mapdb.localize.localizer import localize
    from mapdb.mapfile.reader import open_map

    path = cached_maps({args.map: EXTRACTS[args.map]}, DATA, CACHE)[args.map]
    images = simulated(path, args.images, 3)
    if args.no_prior:
        images = [{k: v for k, v in image.items() if k != "prior"} for image in images]
    map_ = open_map(path)
    for image in images:  # warm: tiles and indexes
        localize(image, map_)
    times = []
    for image in images:
        start = time.perf_counter()
        localize(image, map_)
        times.append(time.perf_counter() - start)
    print(f"{args.map}, {len(images)} images, {'no prior' if args.no_prior else 'prior'}: "
          f"median {statistics.median(times) * 1e3:.2f} ms an image (tiles built)")
    profile = cProfile.Profile()
    profile.enable()
    for image in images:
        localize(image, map_)
    profile.disable()
    pstats.Stats(profile).sort_stats(args.sort).print_stats(args.rows)


if __name__ == "__main__":
    main()
