"""The pose prior (mapdb.match.pose_prior) on rendered-mask frames: how often it places a frame, how often it
places one at a wrong place, and what it costs, beside the same queries with the disc alone.

Frames: the rendered-mask flights of ``benchmarks/navigation_masks.py`` (3 km over Andorra and Monaco, 120 m,
buildings with heights, 60 degrees, 640x480; read from its ``--cache``, rendered there when missing), every
``--every``-th frame.  Each frame is localized, alternating which goes first:

* **right, pose**: a pose prior whose disc (radius uniform 5-30 m) holds the truth (its centre up to 0.8 radii
  off), heading and scale drawn from their stated errors (1 degree, 1 %) around the truth's;
  **right, disc**: the same disc as a prior, no heading or scale (the lost-in-space search in the disc);
* **wrong place**: the truth's heading and scale, the disc (radius 5-30 m) centred on a map object
  200-2,000 m from the truth: every answer accepted is a false alarm;
* **turned**: the right disc, the heading 180 degrees off: an answer more than 5 m off is a false alarm;
* **out of map**: the frame against the other town's map, the disc on a random map object of it.

``--thin``: every frame against the map missing 15 % of its buildings (``navigation_masks.py``'s ``thin15``
map: the camera sees buildings the map lacks).  ``--anchors K``: the stage's anchors
(:data:`mapdb.match.pose_prior.ANCHORS`).  ``--no-turned-check``: without the stage's half-turn check
(:data:`mapdb.match.pose_prior.TURNED_CHECK`).

Per case: frames, accepted, accepted through the pose-prior stage, within 2 m, wrong (accepted more than 5 m
from the truth), and the median and p95 time per frame.

Run from the repository root::

    python benchmarks/pose_prior.py --cache /tmp/pose-cache
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from navigation_masks import _flight, _maps  # noqa: E402

CASES = ("right, pose", "right, disc", "wrong place", "turned", "out of map")
WRONG_M = 5.0
HEADING_SIGMA_DEG = 1.0
SCALE_REL_SIGMA = 0.01


def _frames(name: str, cache: Path, every: int) -> list[tuple[Any, dict]]:
    """The flight's frames (every ``every``-th) as parsed images with their truth."""
    from mapdb.navigation.frames import read_frame

    out = []
    for i, doc in enumerate(_flight(name, "heights", 120.0, 3000.0, cache)):
        frame = read_frame(doc, f"frame {i}")
        if i % every == 0 and frame.image is not None and len(frame.image) >= 3:
            out.append((frame.image, doc["truth"]))
    return out


def _queries(image: Any, truth: dict, objects: Any, other: Any, rng: np.random.Generator) -> dict[str, tuple]:
    """Each case's (which map, prior disc, pose prior or None) for one frame (module docs)."""
    from mapdb.camera import Camera
    from mapdb.match.pose_prior import PosePrior

    scale = truth["altitude_m"] / Camera(image.width, image.height, truth["fov_deg"]).focal_px
    heading = truth["heading_deg"]
    radius = float(rng.uniform(5.0, 30.0))
    off = 0.8 * radius * math.sqrt(rng.uniform()) * complex(np.exp(2j * math.pi * rng.uniform()))
    disc = (truth["x"] + off.real, truth["y"] + off.imag, radius)
    noisy = PosePrior(*disc, (heading + rng.normal(0.0, HEADING_SIGMA_DEG)) % 360.0, HEADING_SIGMA_DEG,
                      scale * (1.0 + rng.normal(0.0, SCALE_REL_SIGMA)), SCALE_REL_SIGMA)
    far = np.flatnonzero(np.hypot(objects.x - truth["x"], objects.y - truth["y"]) > 200.0)
    far = far[np.hypot(objects.x[far] - truth["x"], objects.y[far] - truth["y"]) < 2000.0]
    k = int(rng.choice(far))
    wrong = PosePrior(float(objects.x[k]), float(objects.y[k]), float(rng.uniform(5.0, 30.0)), heading,
                      HEADING_SIGMA_DEG, scale, SCALE_REL_SIGMA)
    j = int(rng.integers(len(other.x)))
    out = PosePrior(float(other.x[j]), float(other.y[j]), float(rng.uniform(5.0, 30.0)), heading, HEADING_SIGMA_DEG,
                    scale, SCALE_REL_SIGMA)
    turned = PosePrior(*disc, (heading + 180.0) % 360.0, HEADING_SIGMA_DEG, scale, SCALE_REL_SIGMA)
    return {"right, pose": (0, None, noisy), "right, disc": (0, disc, None), "wrong place": (0, None, wrong),
            "turned": (0, None, turned), "out of map": (1, None, out)}


def _run(names: list[str], cache: Path, every: int, seed: int, thin: bool = False) -> dict[str, list[tuple]]:
    """Every frame of every flight in every case: (accepted, path, error m, ms)."""
    from mapdb.localize.localizer import Localizer
    from mapdb.mapfile.reader import open_map

    rng = np.random.default_rng(seed)
    rows: dict[str, list[tuple]] = {case: [] for case in CASES}
    for k, name in enumerate(names):
        other_name = names[(k + 1) % len(names)]
        which_map = 1 if thin else 0
        with open_map(_maps(name, cache)[which_map]) as m, open_map(_maps(other_name, cache)[which_map]) as o:
            objects, other = m.all(), o.all()
            locs = [Localizer(m), Localizer(o)]
            for i, (image, truth) in enumerate(_frames(name, cache, every)):
                queries = list(_queries(image, truth, objects, other, rng).items())
                for case, (which, disc, pose) in (queries if i % 2 == 0 else queries[::-1]):
                    t0 = time.perf_counter()
                    answer = locs[which].localize(image, prior=disc, pose=pose)
                    ms = 1e3 * (time.perf_counter() - t0)
                    error = (math.hypot(answer.x - truth["x"], answer.y - truth["y"]) if answer.ok and which == 0
                             else math.inf)
                    rows[case].append((answer.ok, answer.path, error, ms))
    return rows


def main() -> None:
    """Parse the options, run the cases, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--maps", default="andorra,monaco", help="extracts, comma separated (%(default)s)")
    parser.add_argument("--every", type=int, default=1, help="every N-th frame of each flight (%(default)s)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/mapdb-bench-nav-masks"))
    parser.add_argument("--thin", action="store_true", help="against the maps missing 15 %% of their buildings")
    parser.add_argument("--anchors", type=int, default=None, help="the pose stage's anchors (default ANCHORS)")
    parser.add_argument("--no-turned-check", action="store_true",
                        help="without the stage's half-turn check (pose_prior.TURNED_CHECK), to measure its cost")
    args = parser.parse_args()
    import mapdb.match.pose_prior as pose_prior

    if args.anchors is not None:
        pose_prior.ANCHORS = args.anchors
    pose_prior.TURNED_CHECK = not args.no_turned_check
    names = args.maps.split(",")
    load = os.getloadavg()[0]
    rows = _run(names, args.cache, args.every, args.seed, args.thin)
    print(f"rendered-mask frames of {', '.join(names)} (120 m, heights), every {args.every}, "
          f"{'thinned' if args.thin else 'full'} maps, {pose_prior.ANCHORS} anchors, half-turn check "
          f"{'on' if pose_prior.TURNED_CHECK else 'off'}; load average {load:.1f} at "
          f"the start, {os.getloadavg()[0]:.1f} at the end")
    print("| case | frames | accepted | through the pose prior | within 2 m | wrong (> 5 m) | ms median | ms p95 |")
    print("|---|---|---|---|---|---|---|---|")
    for case, r in rows.items():
        ok = [x for x in r if x[0]]
        ms = np.array([x[3] for x in r])
        wrong = sum(1 for x in ok if x[2] > WRONG_M)
        print(f"| {case} | {len(r)} | {len(ok)} | {sum(1 for x in ok if x[1] == 'pose-prior')} "
              f"| {sum(1 for x in ok if x[2] <= 2.0)} | {wrong} | {np.median(ms):.1f} | {np.percentile(ms, 95):.1f} |")


if __name__ == "__main__":
    main()
