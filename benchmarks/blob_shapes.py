"""Do building blobs keep their footprints' orientation?  Evidence a map of centroids and areas leaves unused.

Masks rendered as ``mapdb simulate --render masks`` renders them (``../shared/data/osm`` Andorra and Monaco,
640x480, 60 degree field of view, random heading, at least 8 blobs, buildings extruded to their heights or
flat).  For each building blob that covers exactly one map object, the orientation of the blob's pixels
(``orientation_deg``, the major axis of their second moments, as ``mapdb objects`` writes it) is compared
with that of the object's footprint outline (the extract's polygon, the same moments), turned into the image
by the truth's similarity (the least-squares fit
of the image's whole blobs to their true map objects).  Rows by the footprint's elongation (the square root
of the ratio of its moments' eigenvalues: 1 a square or a disc, 2 a 2:1 rectangle), whole blobs and blobs cut
by the image border apart: how many, and the percentiles of the absolute angle between the two axes
(degrees, 0-90).  Under the matcher's null (a wrong place) that angle is uniform on 0-90, so a blob whose
footprints agree within ``t`` degrees 95 % of the time would be evidence of ``log10(t / 90)`` if the map
stored each object's orientation (it stores a centroid and an area).  Measured with such a map (the branch
``experiment/footprint-axes``), it is worth far less: street grids align a district's buildings, so the share of
map objects around a place whose axis agrees with a blob's is large, and a blob gains 0.2-0.3 in log10.

Run from the repository root::

    python benchmarks/blob_shapes.py                 # 120 m with heights, 80 images per extract
    python benchmarks/blob_shapes.py --altitudes 120 200 300 --kinds yes no --n 80
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rendered_masks import DATA, EXTRACTS, build_maps  # noqa: E402

ELONGATION_ROWS = ((1.0, 1.3), (1.3, 1.6), (1.6, 2.5), (2.5, math.inf))
GRID = 60  # footprint moments from a grid of about GRID x GRID points over its box


def footprint_axis(polygon) -> tuple[float, float]:
    """Major axis (degrees, y up) and elongation of a polygon's area, from the grid points inside it."""
    import shapely

    from mapdb.detections.masks import major_axes

    minx, miny, maxx, maxy = polygon.bounds
    step = max(maxx - minx, maxy - miny) / GRID
    xs, ys = np.meshgrid(np.arange(minx, maxx, step) + step / 2, np.arange(miny, maxy, step) + step / 2)
    inside = shapely.contains_xy(polygon, xs.ravel(), ys.ravel())
    dx, dy = xs.ravel()[inside], ys.ravel()[inside]
    dx, dy = dx - dx.mean(), dy - dy.mean()
    # major_axes takes moments with y down, as pixel rows count: map y is up, so the cross moment flips.
    turn, stretch = major_axes(np.array([(dx * dx).mean()]), np.array([(dy * dy).mean()]),
                               np.array([-(dx * dy).mean()]))
    return float(turn[0]), float(stretch[0])


def measure(altitude: float, heights: bool, n: int, seed: int) -> np.ndarray:
    """Rows ``(cut, footprint elongation, blob elongation, angle in degrees)`` of both extracts' building blobs."""
    from mapdb.mapfile.reader import open_map
    from mapdb.match.geometry import fit_similarity_complex
    from mapdb.simulation.outlines import read_scene
    from mapdb.simulation.rendered import simulate_masks

    rows = []
    for name, path in build_maps().items():
        with open_map(path) as m:
            objects = m.all()
            at = objects.x + 1j * objects.y
            scene = read_scene(DATA / EXTRACTS[name], objects, seed=seed)
            outline = {int(i): g for i, g in zip(scene.map_index, scene.geometry, strict=True) if i >= 0}
            for doc, _mask in simulate_masks(m, scene, n, altitude=altitude, fov_deg=60.0, size=(640, 480),
                                            yaw="random", min_objects=8, seed=seed, heights=heights):
                truth, blobs = doc["truth"], doc["objects"]
                mapped = np.array(truth["map_index"])
                whole = np.array([not b.get("border", False) for b in blobs]) & (mapped >= 0)
                if whole.sum() < 2:
                    continue
                z = np.array([b["x"] - doc["width"] / 2 + 1j * (doc["height"] / 2 - b["y"]) for b in blobs])
                a, _ = fit_similarity_complex(z[whole][None], at[mapped[whole]][None], np.ones((1, whole.sum()), bool))
                turn = float(np.angle(a[0]))
                for blob, covers in zip(blobs, truth["covers"], strict=True):
                    if blob["label"] != "building" or len(covers) != 1 or int(covers[0]) not in outline:
                        continue
                    ground = footprint_axis(outline[int(covers[0])])
                    angle = (ground[0] - math.degrees(turn) - blob["orientation_deg"] + 90.0) % 180.0 - 90.0
                    rows.append((bool(blob.get("border")), ground[1], blob["elongation"], abs(angle)))
    return np.array(rows, float).reshape(-1, 4)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=80, help="images per extract and row")
    parser.add_argument("--altitudes", type=float, nargs="+", default=[120.0])
    parser.add_argument("--kinds", nargs="+", choices=("yes", "no"), default=["yes"],
                        help="buildings extruded to their heights (yes) or flat (no)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to measure", file=sys.stderr)
        return 1
    print(f"{'alt m':>5} {'heights':>7} {'blobs':>5} {'footprint elong.':>16} {'n':>5} {'angle p50':>9} {'p75':>6}"
          f" {'p90':>6} {'p95':>6} {'blob elong. p50':>15} {'share':>6}")
    for altitude in args.altitudes:
        for kind in args.kinds:
            rows = measure(altitude, kind == "yes", args.n, args.seed)
            for cut in (False, True):
                part = rows[rows[:, 0] == cut]
                for lo, hi in ELONGATION_ROWS:
                    sel = part[(part[:, 1] >= lo) & (part[:, 1] < hi)]
                    if not len(sel):
                        continue
                    p50, p75, p90, p95 = np.percentile(sel[:, 3], [50, 75, 90, 95])
                    print(f"{altitude:>5.0f} {kind:>7} {'cut' if cut else 'whole':>5} {f'{lo:g}-{hi:g}':>16}"
                          f" {len(sel):>5} {p50:>9.1f} {p75:>6.1f} {p90:>6.1f} {p95:>6.1f}"
                          f" {np.median(sel[:, 2]):>15.2f} {len(sel) / max(len(part), 1):>6.0%}")
    print("angle: degrees between the blob's major axis and its footprint's in the image (0-90; uniform under a"
          " wrong place); share: of the whole (or cut) building blobs with one map object")
    return 0


if __name__ == "__main__":
    sys.exit(main())
