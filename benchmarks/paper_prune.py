"""The paper's Algorithm 1 with and without its exact bound, side by side on the same images.

The paper's set-up (250 x 150 m map of ~214 objects of one label, 640x480 images from 100 m at 35 degrees,
1 px and 0.05 degree errors).  Each image runs through :func:`mapdb.match.paper.algorithm.match_paper` twice, with
``PaperOptions(prune=False)`` (the algorithm as written: every candidate through the full test) and with the
default ``prune=True``; the table gives the time of each, the ratio, and whether the two results are identical
(bit for bit: the map point, the similarity, ``N_matched``, ``std`` and the count of candidates).

Run from the repository root::

    python benchmarks/paper_prune.py               # 3 images, about 5 minutes (mostly prune=False)
    python benchmarks/paper_prune.py --images 10 --seed 1
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

from mapdb.camera import image_plane
from mapdb.match.paper.algorithm import PaperOptions, PaperResult, match_paper
from mapdb.simulation.simulate import paper_map, simulate_images


def _image_input(image: dict, labels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Objects of an image document as :func:`mapdb.localize.localize` hands them to the matcher (no attitude)."""
    objs = image["objects"]
    z = image_plane([o["x"] for o in objs], [o["y"] for o in objs], image["width"], image["height"])
    codes = np.array([labels.index(o["label"]) for o in objs], dtype=np.int64)
    return z, codes


def _key(result: PaperResult) -> tuple:
    best = result.best
    fields = None if best is None else (best.a, best.b, best.matched, best.error_std)
    return fields, result.reason, result.candidates_tested


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    objects = paper_map(seed=0)
    images = simulate_images(objects, args.images, attitude_std=0.05, pixel_std=1.0, seed=args.seed)
    print(f"paper set-up: {len(objects)} map objects, {args.images} images (seed {args.seed})")
    print(f"  {'image':<12} {'objects':>7} {'prune=False (s)':>16} {'prune=True (s)':>15} {'ratio':>7}"
          f" {'identical':>9} {'result':>14}")
    before, after, all_same = [], [], True
    for image in images:
        z, codes = _image_input(image, objects.labels)
        times, results = [], []
        for prune in (False, True):
            start = time.perf_counter()
            results.append(match_paper(z, codes, objects, options=PaperOptions(prune=prune)))
            times.append(time.perf_counter() - start)
        same = _key(results[0]) == _key(results[1])
        all_same &= same
        best = results[1].best
        outcome = "rejected" if best is None else f"N={best.matched}"
        before.append(times[0])
        after.append(times[1])
        print(f"  {image['id']:<12} {z.size:7d} {times[0]:16.2f} {times[1]:15.2f} {times[0] / times[1]:7.1f}"
              f" {'yes' if same else 'NO':>9} {outcome:>14}")
    print(f"  median: prune=False {statistics.median(before):.2f} s, prune=True {statistics.median(after):.2f} s, "
          f"ratio {statistics.median(before) / statistics.median(after):.1f}")
    print(f"  identical results on every image: {'yes' if all_same else 'NO'}")
    return 0 if all_same else 1


if __name__ == "__main__":
    sys.exit(main())
