"""Georeferenced answers: how close each answer's footprint is to the camera's, how far a tilted camera's best
affine (the world file) strays from its pinhole projection, and what the georeference costs an answer.

Images are simulated on the paper-style map (640x480, 60 degree field of view, 100 m, random heading, 1 px
detector noise), level or with roll and pitch drawn with the given standard deviation and handed to the
localizer (``--with-attitude``).  For each accepted answer: the largest distance between its four footprint
corners and the true camera's (:func:`mapdb.camera.footprint` of the simulator's pose), and its
``transform_error_m``.  The cost is :func:`mapdb.localize.records.georef_fields` timed alone (median over
the answers, each the best of 5 calls), beside the median time of the whole localization.

Run from the repository root::

    python benchmarks/georef.py [--n 50]
"""

from __future__ import annotations

import argparse
import cmath
import math
import statistics
import time

import numpy as np

from mapdb.camera import Camera, Pose, footprint
from mapdb.detections.images import parse_image
from mapdb.localize import localize
from mapdb.localize.records import georef_fields
from mapdb.mapfile.queries import MemoryMap
from mapdb.simulation.simulate import paper_map, simulate_images


def _row(m: MemoryMap, n: int, tilt_std: float) -> dict[str, float]:
    extra = {"attitude_std": tilt_std, "with_attitude": True} if tilt_std else {}
    images = simulate_images(m, n, pixel_std=1.0, yaw="random", seed=11, fov_deg=60.0, **extra)
    corner, affine, cost, whole = [], [], [], []
    for image in images:
        start = time.perf_counter()
        answer = localize(image, m)
        whole.append(time.perf_counter() - start)
        if not answer.ok or answer.footprint is None:
            continue
        t = image["truth"]
        true = footprint(Pose(t["x"], t["y"], t["altitude_m"], t["heading_deg"], t["roll_deg"], t["pitch_deg"]),
                         Camera(image["width"], image["height"], t["fov_deg"]))
        corner.append(float(np.hypot(*(np.array(answer.footprint) - true).T).max()))
        affine.append(float(answer.transform_error_m or 0.0))
        a = answer.scale_m_per_px * cmath.exp(-1j * math.radians(answer.heading_deg))
        im = parse_image(image, "bench")
        calls = []
        for _ in range(5):
            start = time.perf_counter()
            georef_fields(m.crs, a, complex(answer.x, answer.y), im, bool(answer.levelled))
            calls.append(time.perf_counter() - start)
        cost.append(min(calls))
    return {"tilt": tilt_std, "images": len(images), "accepted": len(corner),
            "corner_median": statistics.median(corner), "corner_max": max(corner),
            "affine_median": statistics.median(affine), "affine_max": max(affine),
            "cost_ms": 1000 * statistics.median(cost), "whole_ms": 1000 * statistics.median(whole)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=50, help="images a row")
    args = parser.parse_args()
    m = MemoryMap(paper_map(seed=2))
    print("| roll, pitch std | accepted | footprint corner error vs the camera: median / max | "
          "affine error (transform_error_m): median / max | georef per answer | whole answer |")
    print("|---|---|---|---|---|---|")
    for tilt in (0.0, 2.0, 5.0, 10.0):
        r = _row(m, args.n, tilt)
        print(f"| {r['tilt']:g} deg | {r['accepted']}/{r['images']} | {r['corner_median']:.3f} / "
              f"{r['corner_max']:.3f} m | {r['affine_median']:.3f} / {r['affine_max']:.3f} m | "
              f"{r['cost_ms']:.3f} ms | {r['whole_ms']:.1f} ms |")


if __name__ == "__main__":
    main()
