"""Speed of the localizer, measured side by side in one run (the figures are ratios and medians).

1. The paper's set-up (250 x 150 m map of ~214 objects of one label, 640x480 images from 100 m at 35
   degrees, 1 px and 0.05 degree errors): ``--method fast`` and ``--method paper`` on the same images,
   time per image and the ratios.  The paper's Algorithm 1 runs twice: exhaustive, as published (minutes
   per image), and with mapdb's exact pruning (seconds, the same answers), on ``--paper-images`` images
   (default 1); fast runs on all ``--fast-images``.
2. Real maps built from ``../shared/data/osm`` (Monaco and Andorra, buildings and road intersections):
   simulated images with random yaw, altitude 60-400 m, field of view 35-60 degrees, 1 px and 0.05 degree
   errors, placed over the densest part of each map; median time per image with a 300 m prior in each
   image, and without a prior.  Times are per ``localize`` call (parsing and checking included); caches
   (the whole-map index without a prior, the tile indexes with one) fill as the run goes, and the
   one-off build of the whole-map index is shown on its own.

Run from the repository root::

    python benchmarks/match_speed.py                    # about 5 minutes, mostly the paper's method
    python benchmarks/match_speed.py --paper-images 0   # fast only, seconds
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mapdb.build.pipeline import build_map
from mapdb.localize.localizer import localize
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match.paper.algorithm import PaperOptions
from mapdb.simulation.simulate import paper_map, simulate_images

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import as_json  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL_MAPS = {"Monaco": "osm/monaco-2021-12-03.osm.pbf", "Andorra": "osm/andorra-2021-06-22.osm.pbf"}
KEEP_LABELS = ("building", "road_intersection")


def _timed(image: dict, m, **kwargs) -> tuple[dict, float]:
    start = time.perf_counter()
    answer = as_json(localize(image, m, **kwargs))
    return answer, (time.perf_counter() - start) * 1000.0


def paper_setup(fast_images: int, paper_images: int, seed: int) -> None:
    m = MemoryMap(paper_map(seed=0))
    images = simulate_images(m, max(fast_images, paper_images), attitude_std=0.05, pixel_std=1.0, seed=seed)
    localize(images[0], m)  # builds and caches the map's index (once per map, not per image)
    fast_ms = [_timed(im, m)[1] for im in images[:fast_images]]
    print(f"paper set-up: {len(m.all())} map objects, "
          f"{statistics.mean(len(im['objects']) for im in images):.1f} objects per image")
    print(f"  fast:  median {statistics.median(fast_ms):8.2f} ms over {len(fast_ms)} images "
          f"(95%: {np.percentile(fast_ms, 95):.2f} ms)")
    if not paper_images:
        print("  paper: skipped (--paper-images 0)")
        return
    # The paper's Algorithm 1 twice: exhaustive, as published, and with mapdb's exact pruning (same answers,
    # skipping candidates that provably cannot reach N_min).
    rows = []
    for image in images[:paper_images]:
        answer_x, exhaustive_ms = _timed(image, m, method="paper", options=PaperOptions(prune=False))
        answer_p, pruned_ms = _timed(image, m, method="paper")
        answer_f, fast_one = _timed(image, m)
        truth = image["truth"]
        err = {k: (math.hypot(a["x"] - truth["x"], a["y"] - truth["y"]) if a["status"] == "ok" else None)
               for k, a in (("paper", answer_p), ("exhaustive", answer_x), ("fast", answer_f))}
        rows.append((image["id"], len(image["objects"]), exhaustive_ms, pruned_ms, fast_one, err))
    print(f"  {'image':<12} {'objects':>7} {'exhaustive (s)':>15} {'pruned (s)':>11} {'fast (ms)':>10}"
          f" {'exh/fast':>9} {'pruned/fast':>12} {'err paper':>10} {'err fast':>9}")
    for ident, n, exhaustive_ms, pruned_ms, fast_one, err in rows:
        same = "" if err["paper"] == err["exhaustive"] else "  (paper answers differ!)"
        print(f"  {ident:<12} {n:7d} {exhaustive_ms / 1000:15.1f} {pruned_ms / 1000:11.1f} {fast_one:10.2f}"
              f" {exhaustive_ms / fast_one:9.0f} {pruned_ms / fast_one:12.0f} {_m(err['paper']):>10}"
              f" {_m(err['fast']):>9}{same}")
    fast_med = statistics.median(fast_ms)
    print(f"  median exhaustive paper / median fast: {statistics.median(r[2] for r in rows) / fast_med:,.0f}x;"
          f" pruned paper / fast: {statistics.median(r[3] for r in rows) / fast_med:,.0f}x")


def _m(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} m"


def _real_map(name: str, source: Path, workdir: Path) -> Path:
    full = workdir / f"{name}-all.mapdb"
    build_map([source], full)
    with open_map(full) as m:
        objects = m.all()
    keep = np.isin(objects.names(), KEEP_LABELS)
    path = workdir / f"{name}.mapdb"
    write_map(path, objects.take(keep))
    return path


def _dense_bbox(m, half: float = 1000.0) -> tuple[float, float, float, float]:
    """A square around the densest 500 m cell: where images see objects (the extracts are mostly empty)."""
    o = m.all()
    cell = 500.0
    ix = np.floor(o.x / cell).astype(np.int64)
    iy = np.floor(o.y / cell).astype(np.int64)
    keys, counts = np.unique(np.stack([ix, iy]), axis=1, return_counts=True)
    bx, by = keys[:, np.argmax(counts)]
    cx, cy = (bx + 0.5) * cell, (by + 0.5) * cell
    return (cx - half, cy - half, cx + half, cy + half)


def real_maps(n_images: int, seed: int) -> None:
    if not DATA.is_dir():
        print(f"real maps: skipped ({DATA} not found)")
        return
    with tempfile.TemporaryDirectory() as tmp:
        for name, rel in REAL_MAPS.items():
            path = _real_map(name, DATA / rel, Path(tmp))
            with open_map(path) as m:
                images = simulate_images(
                    m, n_images, altitude=(60.0, 400.0), fov_deg=(35.0, 60.0), yaw="random",
                    attitude_std=0.05, pixel_std=1.0, with_prior=300.0, bbox=_dense_bbox(m), seed=seed,
                )
                enough = [len(im["objects"]) >= 6 for im in images]
                print(f"{name}: {len(m)} objects ({', '.join(f'{k} {v}' for k, v in m.label_counts.items())}); "
                      f"{n_images} images, {sum(enough)} with >= 6 objects")
                prior_ms = [_timed(im, m) for im in images]
                _report("  300 m prior", images, prior_ms, enough)
            with open_map(path) as m:  # a fresh map: no tile caches, the whole-map index built once
                first = images[enough.index(True)] if any(enough) else images[0]
                start = time.perf_counter()
                localize(_without_prior(first), m)
                print(f"  whole-map index: built (with one image answered) in "
                      f"{(time.perf_counter() - start) * 1000:.0f} ms, once per map")
                none_ms = [_timed(_without_prior(im), m) for im in images]
                _report("  no prior   ", images, none_ms, enough)


def _without_prior(image: dict) -> dict:
    return {k: v for k, v in image.items() if k != "prior"}


def _report(title: str, images: list[dict], results: list[tuple[dict, float]], enough: list[bool]) -> None:
    ms = np.array([t for _, t in results])
    sel = np.array(enough)
    ok = np.array([a["status"] == "ok" for a, _ in results])
    err = np.array([
        math.hypot(a["x"] - im["truth"]["x"], a["y"] - im["truth"]["y"]) if a["status"] == "ok" else np.nan
        for (a, _), im in zip(results, images, strict=True)
    ])
    fp = int(np.sum(err[ok] > 2.0))
    print(f"{title}: median {np.median(ms[sel]):6.2f} ms (95%: {np.percentile(ms[sel], 95):6.2f}) on images with"
          f" >= 6 objects, median {np.median(ms):6.2f} ms on all; accepted {ok.sum()}, rejected with >= 6 "
          f"objects {np.sum(~ok & sel)}/{sel.sum()}, false positives (> 2 m) {fp}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fast-images", type=int, default=200, help="paper set-up images for fast")
    parser.add_argument("--paper-images", type=int, default=1, help="paper set-up images for the paper's method")
    parser.add_argument("--real-images", type=int, default=300, help="images per real map")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    paper_setup(args.fast_images, args.paper_images, args.seed)
    real_maps(args.real_images, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
