"""Pose priors that are wrong on the Helsinki sample: another place, or the heading turned half round.

Reproduces the README's "Where it fails" line of the pose prior (Navigation, issue 29): on the sample map's
symmetric blocks, images given a pose prior whose heading is 180 degrees off can be accepted 20-30 m from the
truth through the pose stage (a place whose half-turn repeats the pattern, which the a-contrario null does not
model).  Each simulated image (120 m, 60 degrees, random heading, 1 px, 0.05 degrees, at least 4 objects) is
localized three times, each with a disc of radius uniform 5-30 m, heading sigma 0.3 degrees and scale sigma
0.5 %: on a map object at least 200 m away with the true heading ("wrong place"), on the truth with the heading
turned by 180 degrees ("turned"), and on the truth with the true heading ("right")::

    python benchmarks/diagnostics/pose_turned.py 300

Prints each wrong or turned acceptance, then the counts: wrong-place answers accepted, turned answers accepted
more than 5 m off (and how many of them through the pose stage), right answers within 2 m.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def sample_map() -> Path:
    """The sample map, built once into the temporary folder."""
    from mapdb.build.pipeline import build_map

    out = Path(tempfile.gettempdir()) / "mapdb-diag-pose" / "helsinki.mapdb"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        build_map([ROOT / "sample_maps" / "helsinki.osm.pbf"], out)
    return out


def run(n: int, seed: int) -> dict[str, int]:
    """The three localizations of ``n`` images (module docs); the counts."""
    from mapdb.localize.localizer import Localizer
    from mapdb.mapfile.reader import open_map
    from mapdb.match.pose_prior import PosePrior
    from mapdb.simulation.simulate import simulate_images

    counts = {"images": 0, "wrong place accepted": 0, "turned accepted > 5 m off": 0,
              "of them through the pose stage": 0, "right within 2 m": 0}
    with open_map(sample_map()) as m:
        objects = m.all()
        images = simulate_images(m, n, altitude=120.0, fov_deg=60.0, yaw="random", pixel_std=1.0,
                                 attitude_std=0.05, min_objects=4, seed=seed)
        localizer, rng = Localizer(m), np.random.default_rng(1)
        for image in images:
            t = image["truth"]
            scale = t["altitude_m"] / (320 / math.tan(math.radians(30)))
            k = int(rng.integers(len(objects.x)))
            while math.hypot(objects.x[k] - t["x"], objects.y[k] - t["y"]) < 200:
                k = int(rng.integers(len(objects.x)))
            radius = float(rng.uniform(5, 30))
            elsewhere = PosePrior(float(objects.x[k]), float(objects.y[k]), radius, t["heading_deg"], 0.3, scale, 0.005)
            a = localizer.localize(image, pose=elsewhere)
            if a.ok:
                counts["wrong place accepted"] += 1
                print("wrong place:", image["id"], a.score, a.path)
            a = localizer.localize(image, pose=PosePrior(t["x"], t["y"], radius, t["heading_deg"] + 180.0, 0.3,
                                                         scale, 0.005))
            if a.ok and math.hypot(a.x - t["x"], a.y - t["y"]) > 5:
                counts["turned accepted > 5 m off"] += 1
                counts["of them through the pose stage"] += a.path == "pose-prior"
                print("turned:", image["id"], a.score, a.path, round(math.hypot(a.x - t["x"], a.y - t["y"]), 1), "m")
            a = localizer.localize(image, pose=PosePrior(t["x"], t["y"], radius, t["heading_deg"], 0.3, scale, 0.005))
            counts["right within 2 m"] += bool(a.ok and math.hypot(a.x - t["x"], a.y - t["y"]) < 2)
            counts["images"] += 1
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("n", type=int, nargs="?", default=300, help="images (%(default)s)")
    parser.add_argument("--seed", type=int, default=5, help="the images' seed (%(default)s)")
    args = parser.parse_args(argv)
    for name, count in run(args.n, args.seed).items():
        print(f"{name:32} {count}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
