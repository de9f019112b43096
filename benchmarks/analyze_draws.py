"""The part of ``mapdb analyze`` that is not the matcher, per cell: drawing its images (poses, the objects in
view) and making the documents of the images it localizes, this tree's against a baseline revision's, in one
process, taking turns block by block (so that a neighbour's load falls on both alike).

    python benchmarks/analyze_draws.py [--map andorra] [--baseline c0735fc] [--cells 800] [--repeat 3]

For the map's cells to simulate (every one within reach of at least 4 analysed objects, a spread of ``--cells``
of them), at the analysis defaults (100 m cells, 16 images, 150 m, 45 degrees, 0.05 degree attitude, 1 px):

* **draws**: the baseline's ``measures._draws`` (a generator seeded per image, one projection per image) against
  this tree's ``draws.cell_poses`` + ``draws.cell_views`` (seeds hashed on arrays, one stacked projection per
  cell), a cell at a time; and whether every image shows the same objects in both;
* **images**: the documents of each cell's localizable images (at most 4 a cell, as the sequential rule
  localizes 2 to 5): the baseline's ``simulate_image_at`` of the objects within reach against
  ``draws.cell_image``, and whether the documents are equal (``truth`` aside).

Prints the medians over the repeats of the CPU microseconds (this process's) a cell and an image, and the ratios.

``--picture OUT``: also the PNG of an earlier run's ``OUT/analysis.tif`` (``mapdb analyze MAP -o OUT`` at the
defaults above), drawn by the baseline's ``plot_analysis`` and by this tree's, taking turns: CPU seconds and
whether the files are the same bytes (under ``SOURCE_DATE_EPOCH``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import import_baseline, map_argument  # noqa: E402

from mapdb.analysis import draws  # noqa: E402
from mapdb.analysis import measures as tree  # noqa: E402
from mapdb.analysis.measures import MIN_VISIBLE, SampleConfig  # noqa: E402
from mapdb.analysis.run import plan  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402

CONFIG = SampleConfig(attitude_std=0.05, pixel_std=1.0)
BLOCK = 8


def cells_to_draw(map_path: Path, n: int) -> np.ndarray:
    """Absolute indices of up to ``n`` of the map's cells to simulate, spread evenly."""
    planned = plan(str(map_path), {"": CONFIG})
    grid, counts = planned.grid, planned.runs[0][2]
    rows, cols = np.nonzero(counts.within_reach >= MIN_VISIBLE)
    pick = np.unique(np.linspace(0, rows.size - 1, min(n, rows.size)).round().astype(np.int64))
    return np.column_stack(grid.absolute(rows[pick], cols[pick]))


def contexts(m, base, cells: np.ndarray, cell_m: float) -> list[tuple[np.ndarray, object, object]]:
    """Per block of cells: its cells and both versions' contexts (the objects around them, their tree)."""
    names = tuple(m.label_counts)
    codes = np.array([m.labels.index(k) for k in names], np.int64)
    label_counts = {k: m.label_counts[k] for k in names if m.label_counts.get(k)}
    out = []
    blocks = cells // BLOCK
    for block in np.unique(blocks, axis=0):
        mine = cells[(blocks == block).all(axis=1)]
        args = (m, None, CONFIG, cell_m, mine, names, codes, label_counts)
        out.append((mine, base._context(*args), tree._context(*args)))
    return out


def time_draws(blocks, base, order: int) -> tuple[float, float, int, int]:
    """Seconds of the baseline's and the tree's draws over every block (taking turns), cells, images that differ."""
    spent = [0.0, 0.0]
    differ = images = 0
    for k, (cells, old_ctx, new_ctx) in enumerate(blocks):
        runs = [0, 1] if (k + order) % 2 == 0 else [1, 0]
        for who in runs:
            start = time.process_time()
            if who == 0:
                old = [base._draws(old_ctx, int(i), int(j)) for i, j in cells]
            else:
                poses = draws.cell_poses(CONFIG.seed, cells, CONFIG.samples, new_ctx.cell_m, CONFIG.altitude,
                                         CONFIG.attitude_std)
                near = draws.near_cells(new_ctx.tree, (cells + 0.5) * new_ctx.cell_m,
                                        np.hypot(0.5, 0.5) * new_ctx.cell_m, new_ctx.reach)
                new = [draws.cell_views(new_ctx.objects, new_ctx.tree, k, p, new_ctx.camera, new_ctx.reach)
                       for p, k in zip(poses, near)]
            spent[who] += time.process_time() - start
        for drawn, views in zip(old, new, strict=True):
            for s, (_, _, near, seen) in enumerate(drawn):
                images += 1
                differ += int(not np.array_equal(near[seen], views.near[views.seen[s]]))
    return spent[0], spent[1], images, differ


def time_images(blocks, base_sim, order: int) -> tuple[float, float, int, int]:
    """Seconds of the baseline's and the tree's documents of up to 4 localizable images a cell; images, unequal."""
    spent = [0.0, 0.0]
    unequal = n = 0
    for k, (cells, old_ctx, new_ctx) in enumerate(blocks):
        poses = draws.cell_poses(CONFIG.seed, cells, CONFIG.samples, new_ctx.cell_m, CONFIG.altitude,
                                 CONFIG.attitude_std)
        jobs = []
        near = draws.near_cells(new_ctx.tree, (cells + 0.5) * new_ctx.cell_m, np.hypot(0.5, 0.5) * new_ctx.cell_m,
                                new_ctx.reach)
        for p, (i, j), k in zip(poses, cells.tolist(), near):
            views = draws.cell_views(new_ctx.objects, new_ctx.tree, k, p, new_ctx.camera, new_ctx.reach)
            ready = np.flatnonzero(views.seen.sum(axis=1) >= MIN_VISIBLE)[:4]
            jobs += [(p, int(s), i, j, views.shown(int(s))) for s in ready]
        docs: list[list[dict]] = [[], []]
        for who in ([0, 1] if (k + order) % 2 == 0 else [1, 0]):
            start = time.process_time()
            for p, s, i, j, shown in jobs:
                pose = p.pose(s)
                if who == 0:
                    near = np.sort(np.asarray(old_ctx.tree.query_ball_point((pose.x, pose.y), CONFIG.reach_m),
                                              np.int64))
                    doc = base_sim(old_ctx.objects.take(near), pose, CONFIG.camera,
                                   draws.positioned(p, s, CONFIG.seed, i, j), pixel_std=CONFIG.pixel_std,
                                   label_counts=old_ctx.label_counts, image_id=f"{i},{j},{s}")
                else:
                    doc = draws.cell_image(new_ctx.objects, *shown, pose, new_ctx.camera,
                                           draws.positioned(p, s, CONFIG.seed, i, j, new_ctx.generator),
                                           new_ctx.detector, None, f"{i},{j},{s}")
                docs[who].append(doc)
            spent[who] += time.process_time() - start
        for a, b in zip(*docs, strict=True):
            a.pop("truth")
            unequal += int(a != b)
        n += len(jobs)
    return spent[0], spent[1], n, unequal


def time_picture(map_path: Path, out: Path, baseline: str, workdir: Path, repeat: int) -> None:
    """The PNG of ``out/analysis.tif`` drawn by both versions, taking turns: CPU seconds, same bytes or not."""
    import hashlib

    import rasterio

    from mapdb.analysis.pictures import plot_analysis
    from mapdb.analysis.run import Analysis

    planned = plan(str(map_path), {"": CONFIG})
    with rasterio.open(out / "analysis.tif") as src:
        bands = {name: src.read(k + 1) for k, name in enumerate(src.descriptions)}
        bands = {name: np.where(values == src.nodata, np.nan, values) for name, values in bands.items()}
    analysis = Analysis(str(map_path), planned.grid, CONFIG, planned.runs[0][2], bands, planned.map_info)
    drawers = {"baseline": import_baseline(baseline, workdir, "analysis.pictures").plot_analysis,
               "tree": plot_analysis}
    spent: dict[str, list[float]] = {"baseline": [], "tree": []}
    for r in range(repeat):
        for who in (["baseline", "tree"] if r % 2 == 0 else ["tree", "baseline"]):
            start = time.process_time()
            drawers[who](workdir / f"{who}.png", analysis)
            spent[who].append(time.process_time() - start)
    same = hashlib.sha256((workdir / "baseline.png").read_bytes()).digest() == \
        hashlib.sha256((workdir / "tree.png").read_bytes()).digest()
    old, new = statistics.median(spent["baseline"]), statistics.median(spent["tree"])
    print(f"| the PNG of {out / 'analysis.tif'} (s) | {old:.2f} | {new:.2f} | {new / old:.3f} | "
          f"{'same bytes' if same else 'different bytes'} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map", default="andorra", help="a shared extract's name or a map file")
    parser.add_argument("--baseline", default="c0735fc", help="the revision to compare with")
    parser.add_argument("--cells", type=int, default=800, help="cells to draw (a spread of those to simulate)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--picture", type=Path, default=None, metavar="OUT",
                        help="also draw OUT/analysis.tif's PNG with both versions")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "mapdb-analyze-draws")
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    map_path = map_argument(args.map, args.workdir / "maps")
    if map_path is None:
        return 1
    base = import_baseline(args.baseline, args.workdir, "analysis.measures")
    base_sim = import_baseline(args.baseline, args.workdir, "simulation.simulate").simulate_image_at
    cells = cells_to_draw(map_path, args.cells)
    with open_map(map_path) as m:
        blocks = contexts(m, base, cells, 100.0)
        rows = [(time_draws(blocks, base, r), time_images(blocks, base_sim, r)) for r in range(args.repeat)]
    (_, _, images, differ), (_, _, docs, unequal) = rows[0]
    print(f"{map_path.name}: {len(cells)} cells, {images} images drawn, {docs} documents; baseline "
          f"{args.baseline}; {args.repeat} repeats taking turns block by block")
    print("| part | baseline (us) | this tree (us) | ratio | results that differ |\n|---|---|---|---|---|")
    for k, (label, per, count, bad) in enumerate((("draws a cell", len(cells), images, differ),
                                                  ("document an image", docs, docs, unequal))):
        old = statistics.median(r[k][0] for r in rows) / per * 1e6
        new = statistics.median(r[k][1] for r in rows) / per * 1e6
        print(f"| {label} | {old:,.0f} | {new:,.0f} | {new / old:.3f} | {bad} of {count} |")
    if args.picture is not None:
        time_picture(map_path, args.picture, args.baseline, args.workdir, args.repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
