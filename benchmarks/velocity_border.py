"""Frame-to-frame velocity on rendered masks, border-cut blobs left out (now) or kept (before): issue 29 item 1.

Pairs of consecutive frames 4 m apart along a random heading (20 m/s at 5 fps), level camera at 120 m, 60
degree field of view, 640x480, the first nadir on a random building of the extract; each frame's label mask
is rendered from the extract's outlines (:func:`mapdb.simulation.render.render_mask`, flat or with buildings
extruded to their heights) and its objects extracted as ``mapdb objects`` does.  The velocity is
:func:`mapdb.navigation.velocity.match_frames` with no guess, turned into m/s with the ground sampling
distance at the nadir; "before" strips the ``border`` field, so that every blob counts as whole.  Only pairs
with at least ``MIN_WHOLE_OBJECTS`` whole blobs in both frames are measured: on the others the change
keeps the border blobs and both rows are the same.

Run from the repository root::

    python benchmarks/velocity_border.py --pairs 400 --extract monaco

Prints, per rendering: the pairs measured, the median share of their blobs touching the border, and per
row the along-track error (m/s, truth 20): mean, median, and the mean and count of the pairs within 2 m/s.
With heights the rooftops (nearer the camera) move faster than the ground: this script's fixed ground
sampling distance reads that as speed, where the navigator's scale comes from its fixes on the same roofs.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import cached_maps, shared_data  # noqa: E402

DATA = shared_data("osm")
EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf"}
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-maps"
ALTITUDE, FOV, STEP_M, DT = 120.0, 60.0, 4.0, 0.2


def _pair_velocities(objects, scene, rng, heights: bool) -> tuple[float, float, float] | None:  # noqa: ANN001
    """Along-track speed of one pair, now and before, and the share of border blobs; None if not measured."""
    from mapdb.camera import Camera, Pose
    from mapdb.detections.images import parse_image
    from mapdb.detections.masks import from_mask
    from mapdb.navigation.velocity import (
        MIN_WHOLE_OBJECTS,
        FramePoints,
        frame_points,
        match_frames,
        velocity_from_motion,
    )
    from mapdb.simulation.render import render_mask

    cam = Camera(640, 480, FOV)
    buildings = np.flatnonzero(np.asarray(objects.labels)[objects.label] == "building")
    k = rng.choice(buildings)
    heading = float(rng.uniform(0.0, 360.0))
    h = math.radians(heading)
    ims = []
    for s in (0.0, STEP_M):
        pose = Pose(float(objects.x[k]) + s * math.sin(h), float(objects.y[k]) + s * math.cos(h), ALTITUDE, heading)
        r = render_mask(scene, pose, cam, heights=heights)
        ims.append(parse_image(from_mask(r.mask, r.classes, fov_deg=FOV), "frame"))
    names = sorted({str(n) for im in ims for n in im.names})
    pts = [frame_points(im, np.array([names.index(str(n)) for n in im.names], np.int64), None, None) for im in ims]
    whole = [int((~p.border).sum()) if p.border is not None else p.z.size for p in pts]
    if min(whole) < MIN_WHOLE_OBJECTS:
        return None
    to_map = cam.gsd(ALTITUDE) * np.exp(-1j * h)
    along = complex(math.sin(h), math.cos(h)).conjugate()
    speeds = []
    for frames in (pts, [FramePoints(p.z, p.codes, p.width, p.height) for p in pts]):
        motion = match_frames(frames[0], frames[1], 1 + 0j, None, len(names))
        v = math.nan if isinstance(motion, str) else velocity_from_motion(motion, to_map, DT).v * along
        speeds.append(float(np.real(v)))
    return speeds[0], speeds[1], float(np.mean(pts[1].border))


def main() -> None:
    """Parse the options, measure, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=400, help="pairs drawn per rendering")
    parser.add_argument("--extract", choices=sorted(EXTRACTS), default="monaco")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if not (DATA / EXTRACTS[args.extract]).exists():
        sys.exit(f"velocity_border: {DATA / EXTRACTS[args.extract]} is missing (the shared data)")
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.outlines import read_scene

    path = cached_maps({args.extract: EXTRACTS[args.extract]}, DATA, CACHE)[args.extract]
    objects = open_map(path).all()
    scene = read_scene(DATA / EXTRACTS[args.extract], objects)
    truth = STEP_M / DT
    print("| rendering | pairs measured / drawn | border share | row | mean m/s | median m/s "
          "| within 2 m/s: mean (n) |")
    print("|---|---|---|---|---|---|---|")
    for heights in (False, True):
        rng = np.random.default_rng(args.seed)
        rows = [r for r in (_pair_velocities(objects, scene, rng, heights) for _ in range(args.pairs)) if r]
        share = float(np.median([r[2] for r in rows])) if rows else math.nan
        for i, name in enumerate(("now", "before")):
            err = np.array([r[i] for r in rows]) - truth
            err = err[np.isfinite(err)]
            near = err[np.abs(err) < 2.0]
            print(f"| {'heights' if heights else 'flat'} | {len(rows)} / {args.pairs} | {share:.2f} | {name} "
                  f"| {err.mean():+.3f} | {np.median(err):+.3f} | {near.mean():+.3f} ({near.size}) |")


if __name__ == "__main__":
    main()
