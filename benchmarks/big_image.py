"""Work per image is bounded: time and peak memory of one image with many objects, in a fresh process each.

Images of 20 (a real simulated image), 300, 3,000, 5,000 and 20,000 (the input limit) building objects at
random pixels of a 4000x3000 image, localized with no prior against the Andorra map
(``../shared/data/osm``).  Before the bound, 5,000 objects took 8.2 GB and 65 s and 20,000 tried to
allocate 15-48 GB (issue 7); the matcher now uses the 256 objects nearest the image centre and at most
8 anchor batches a lookup pass.

Run from the repository root::

    python benchmarks/big_image.py
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

ANDORRA = Path(__file__).resolve().parents[2] / "shared" / "data" / "osm" / "andorra-2021-06-22.osm.pbf"

CHILD = r"""
import json, resource, sys, time
import numpy as np
from mapdb.localize.localizer import localize
from mapdb.mapfile.reader import open_map
n, map_path = int(sys.argv[1]), sys.argv[2]
with open_map(map_path) as m:
    if n == 20:
        from mapdb.simulation.simulate import simulate_images
        image = simulate_images(m, 1, altitude=300.0, fov_deg=60.0, yaw="random", pixel_std=1.0, min_objects=15,
                                seed=1)[0]
    else:
        rng = np.random.default_rng(0)
        image = {"width": 4000, "height": 3000, "objects": [
            {"label": "building", "x": float(x), "y": float(y)}
            for x, y in zip(rng.uniform(0, 4000, n), rng.uniform(0, 3000, n))]}
    localize({"width": 10, "height": 10, "objects": []}, m)  # imports warm, nothing else
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    answer = localize(image, m)
    seconds = time.perf_counter() - start
print(json.dumps({"objects": n, "status": answer.status, "seconds": seconds,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "before_mb": base / 1024}))
"""


def main() -> None:
    if not ANDORRA.exists():
        sys.exit(f"skipped: {ANDORRA} not found")
    from mapdb.build.pipeline import build_map

    with tempfile.TemporaryDirectory() as tmp:
        map_path = Path(tmp) / "andorra.mapdb"
        build_map([ANDORRA], map_path)
        print(f"{'objects':>8} {'answer':>9} {'seconds':>8} {'peak RSS MB':>12} {'RSS before MB':>14}")
        for n in (20, 300, 3000, 5000, 20000):
            out = subprocess.run([sys.executable, "-c", CHILD, str(n), str(map_path)], check=True,
                                 capture_output=True, text=True, cwd=tmp).stdout
            r = json.loads(out)
            print(f"{r['objects']:8d} {r['status']:>9} {r['seconds']:8.2f} {r['peak_mb']:12.0f} {r['before_mb']:14.0f}")


if __name__ == "__main__":
    main()
