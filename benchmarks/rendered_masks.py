"""The matcher on objects extracted from rendered masks (``mapdb simulate --render masks``).

Images of ``../shared/data/osm`` Andorra and Monaco: 640x480, 60 degree field of view, random heading,
level camera (no attitude error, no hints), masks rendered from the extract's outlines with buildings
extruded to their heights (``heights``) or flat, no mask noise, objects extracted as ``mapdb objects``
does (8-connected, at least 4 px), at least 8 blobs per image (``--min-objects``).  Each image is
localized with no prior by :func:`mapdb.localize.localize` and scored by :mod:`mapdb.evaluation.evaluate`
(an accepted answer more than 2 m from the truth is a false positive).

Run from the repository root::

    python benchmarks/rendered_masks.py --n 150                     # 150 images per row
    python benchmarks/rendered_masks.py --n 150 --baseline REV      # also the matcher of git revision REV
    python benchmarks/rendered_masks.py --n 40 --altitudes 120 --kinds yes   # one row per extract, quick

Prints one row per extract, altitude and heights (and the two extracts together), with beside them the
ideal simulator's images at the same altitude (``heights`` "ideal": each map object at its projected
centroid, at least 8 in view): images, mean blobs (objects) per image, localized (correct answers /
images), false positives (accepted with error > 2 m, their errors), RMS error of the correct answers,
the median rendering and localizing times.  "whole" is the median number of blobs per image not touching
the image border, and ">=8 whole" the correct answers among the images with at least 8 of them: a blob cut
by the border names its map object but its centroid is pulled inward (by a median 32-39 px at 120 m), so
the whole blobs are what the image's evidence mostly rests on.

"ceiling" is the share of images that a matcher using only the whole blobs' centroids could localize at
all: the least-squares similarity of the whole blobs (at least 2) to their *true* map objects
(``truth.map_index``, :func:`mapdb.match.geometry.fit_similarity_complex`) puts the image centre within 2 m
of the truth.  No search is involved: it is the best a whole-blob fit can do once the right objects are
known, so "localized" above it means cut blobs (or the search's luck) carried an image, and the gap below it
what the search and the decision leave on the table.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import ROOT, as_json, cached_maps, import_baseline  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "osm"
EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf"}
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-maps"
ALTITUDES = (120.0, 200.0, 300.0)
MIN_BLOBS = 8
# Rendered with buildings extruded, rendered flat, and the ideal simulator's centroids for reference.
KINDS = ("yes", "no", "ideal")


def build_maps() -> dict[str, Path]:
    """The extracts' maps, built once into a cache outside the repository."""
    return cached_maps(EXTRACTS, DATA, CACHE)


def render(m: Any, scene: Any, n: int, altitude: float, kind: str, seed: int) -> tuple[list[dict], float]:
    """``n`` images and the median time to make one (ms): rendered with heights ("yes") or flat ("no"), or
    the ideal simulator's projected centroids ("ideal", at least 8 in view)."""
    from mapdb.simulation.rendered import simulate_masks
    from mapdb.simulation.simulate import simulate_images

    camera = {"altitude": altitude, "fov_deg": 60.0, "size": (640, 480), "yaw": "random",
              "min_objects": MIN_BLOBS, "seed": seed}
    if kind == "ideal":
        start = time.perf_counter()
        images = simulate_images(m, n, **camera)
        return images, (time.perf_counter() - start) * 1000.0 / max(n, 1)
    images, times = [], []
    start = time.perf_counter()
    for doc, _mask in simulate_masks(m, scene, n, heights=kind == "yes", **camera):
        now = time.perf_counter()
        times.append((now - start) * 1000.0)
        start = now
        images.append(doc)
    return images, statistics.median(times)


def score(images: list[dict], m: Any, localize: Any) -> dict[str, Any]:
    """Localize every image; the evaluation summary, the false positives' errors and the median time."""
    from mapdb.answers import Answer
    from mapdb.evaluation.evaluate import outcome, summarize

    localize(images[0], m)  # builds the map's index once, outside the timing
    outcomes = []
    for im in images:
        start = time.perf_counter()
        answer = Answer.from_json(as_json(localize(im, m)))  # an older revision answers with a dict
        outcomes.append(outcome(im, answer, (time.perf_counter() - start) * 1000.0))
    summary = summarize(outcomes)
    summary["fp_errors"] = sorted(o["error_m"] for o in outcomes if o["status"] == "ok" and o["error_m"] > 2.0)
    summary["outcomes"] = outcomes
    return summary


def ceiling(images: list[dict], m: Any) -> list[bool]:
    """Per image: whether the whole blobs' least-squares fit to their true map objects lands within 2 m."""
    import numpy as np

    from mapdb.camera import image_plane
    from mapdb.match.geometry import fit_similarity_complex

    objects = m.all()
    map_z = objects.x + 1j * objects.y
    out = []
    for im in images:
        index = np.array(im["truth"]["map_index"], np.int64)
        pick = np.array([not o.get("border", False) for o in im["objects"]], bool) & (index >= 0)
        if pick.sum() < 2:
            out.append(False)
            continue
        z = image_plane([o["x"] for o in im["objects"]], [o["y"] for o in im["objects"]], im["width"],
                        im["height"])[pick]
        _, b = fit_similarity_complex(z[None, :], map_z[index[pick]][None, :], np.ones((1, z.size), bool))
        out.append(bool(abs(b[0] - complex(im["truth"]["x"], im["truth"]["y"])) <= 2.0))
    return out


def whole_blobs(im: dict) -> int:
    """Blobs not touching the image border: the ones whose centroids say where their objects are."""
    return sum(not o.get("border", False) for o in im["objects"])


def whole_share(images: list[dict], outcomes: list[dict]) -> str:
    """Correct answers among the images with at least ``MIN_BLOBS`` whole blobs, as "k/n"."""
    picked = [o for im, o in zip(images, outcomes) if whole_blobs(im) >= MIN_BLOBS]
    return f"{sum(o['status'] == 'ok' and o['error_m'] <= 2.0 for o in picked)}/{len(picked)}"


def row(name: str, altitude: float, heights: str, images: list[dict], s: dict[str, Any],
        render_ms: float | None) -> str:
    blobs = statistics.mean(len(im["objects"]) for im in images)
    whole = statistics.median(whole_blobs(im) for im in images)
    errors = ", ".join(f"{e:,.0f}" for e in s["fp_errors"])
    fp = f"{s['false_positives']}" + (f" ({errors} m)" if errors else "")
    rms = "-" if s["rms_m"] is None else f"{s['rms_m']:.2f}"
    render_txt = "-" if render_ms is None else f"{render_ms:.0f}"
    top = sum(s["ceiling"]) / len(images)
    return (f"{name:<9} {altitude:>5.0f} {heights:>7} {len(images):>6} {blobs:>6.1f} {whole:>5.0f} "
            f"{s['correct'] / len(images):>9.1%} {top:>7.1%} {whole_share(images, s['outcomes']):>9} {fp:<22} {rms:>7} "
            f"{render_txt:>9} {s['time_median_ms']:>8.0f}")


HEADER = (f"{'extract':<9} {'alt m':>5} {'heights':>7} {'images':>6} {'blobs':>6} {'whole':>5} {'localized':>9} "
          f"{'ceiling':>7} {'>=8 whole':>9} {'false positives':<22} {'RMS m':>7} {'render ms':>9} {'query ms':>8}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=150, help="images per extract, altitude and heights")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--baseline", metavar="REV", help="also run the matcher of this git revision")
    parser.add_argument("--altitudes", type=float, nargs="+", default=list(ALTITUDES), help="altitudes (m) to run")
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS,
                        help="rendered with heights (yes), flat (no), ideal centroids (ideal)")
    args = parser.parse_args()
    missing = [p for p in EXTRACTS.values() if not (DATA / p).exists()]
    if missing:
        sys.exit(f"real data not found in {DATA}: {', '.join(missing)}")

    from mapdb.localize import localizer as tree_localize
    from mapdb.mapfile import reader as tree_reader

    with tempfile.TemporaryDirectory() as tmp:
        # Each matcher opens the maps with its own revision's store.
        matchers = {"current": (tree_localize.localize, tree_reader)}
        if args.baseline:
            matchers[f"baseline {args.baseline}"] = (import_baseline(args.baseline, Path(tmp)).localize,
                                                     import_baseline(args.baseline, Path(tmp), "store"))
        results = run(build_maps(), matchers, args.n, args.seed, tuple(args.altitudes), tuple(args.kinds))
    report(results, args.n, tuple(args.altitudes), tuple(args.kinds))


def run(maps: dict[str, Path], matchers: dict[str, Any], n: int, seed: int, altitudes: tuple[float, ...] = ALTITUDES,
        kinds: tuple[str, ...] = KINDS) -> dict[str, list[tuple]]:
    """Render every row's images once (with this tree) and localize them with every matcher."""
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.outlines import read_scene

    results: dict[str, list[tuple]] = {k: [] for k in matchers}
    for name, path in maps.items():
        with open_map(path) as m:
            scene = read_scene(DATA / EXTRACTS[name], m.all(), seed=seed)
            rows = []
            for altitude in altitudes:
                for heights in kinds:
                    images, render_ms = render(m, scene, n, altitude, heights, seed)
                    rows.append((altitude, heights, images, render_ms, ceiling(images, m)))
        for label, (localize, store) in matchers.items():
            with store.open_map(path) as m:
                for altitude, heights, images, render_ms, feasible in rows:
                    results[label].append((name, altitude, heights, images,
                                           {**score(images, m, localize), "ceiling": feasible}, render_ms))
    return results


def report(results: dict[str, list[tuple]], n: int, altitudes: tuple[float, ...] = ALTITUDES,
           kinds: tuple[str, ...] = KINDS) -> None:
    """Print one table per matcher: a row per extract, altitude and heights, then both extracts together."""
    from mapdb.evaluation.evaluate import summarize

    for label, rows in results.items():
        print(f"\n{label} matcher: {n} images per row, 640x480, 60 deg, random heading, >= {MIN_BLOBS} blobs")
        print(HEADER)
        for name, altitude, heights, images, s, render_ms in rows:
            print(row(name, altitude, heights, images, s, render_ms))
        for altitude in altitudes:
            for heights in kinds:
                picked = [r for r in rows if r[1] == altitude and r[2] == heights]
                images = [im for r in picked for im in r[3]]
                both = summarize([o for r in picked for o in r[4]["outcomes"]])
                both["fp_errors"] = sorted(e for r in picked for e in r[4]["fp_errors"])
                both["outcomes"] = [o for r in picked for o in r[4]["outcomes"]]
                both["ceiling"] = [c for r in picked for c in r[4]["ceiling"]]
                print(row("both", altitude, heights, images, both, None))


if __name__ == "__main__":
    main()
