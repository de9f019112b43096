"""Area evidence against segmentation errors: rendered building masks eroded and dilated, localized.

Images of ``../shared/data/osm`` Andorra and Monaco rendered as ``benchmarks/rendered_masks.py`` renders them
(640x480, 60 degree field of view, random heading, level camera, buildings extruded to their heights unless
``--flat``, at least 8 blobs), then the building class of each mask eroded or dilated by ``--errors`` pixels
(``scipy.ndimage``, the cross structure, the image's outside counted as building so that an eroded cut building
still touches the border; eroded pixels become background, dilated ones cover what was there) and
the objects extracted again exactly as ``mapdb objects`` does.  Each image is localized with no prior by this
tree's matcher with its areas, the same with ``FastOptions(areas=False)`` (``mapdb query --no-areas``), and
with ``--baseline REV``'s matcher, image by image in turn (the order alternating), so that the times compare.

Run from the repository root::

    python benchmarks/segmentation_areas.py --n 100 --baseline REV
    python benchmarks/segmentation_areas.py --n 40 --altitudes 200 --errors -2 0 2

Prints a row per extract, altitude, mask error and matcher: images, localized (accepted within 2 m),
false positives (accepted more than 2 m off), rejected with ``rejected_by: areas`` (the areas decided the
rejection), median and 95th percentile query time.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import ROOT, as_json, cached_maps, import_baseline  # noqa: E402

_BESIDE = ROOT.parent / "shared" / "data" / "osm"
DATA = _BESIDE if _BESIDE.is_dir() else Path("/work/shared/data/osm")
EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf"}
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-maps"
MIN_BLOBS = 8


def segmentation_error(mask: np.ndarray, code: int, px: int) -> np.ndarray:
    """The label mask with class ``code`` eroded (``px < 0``) or dilated (``px > 0``) by ``|px|`` pixels."""
    from scipy import ndimage

    layer = mask == code
    if px < 0:
        # Outside the image counts as building: a model's erosion does not pull a cut building off the border.
        shrunk = ndimage.binary_erosion(layer, iterations=-px, border_value=1)
        return np.where(layer & ~shrunk, 0, mask)
    if px > 0:
        return np.where(ndimage.binary_dilation(layer, iterations=px), code, mask)
    return mask


def images_with_errors(m: Any, scene: Any, n: int, altitude: float, heights: bool, errors: list[int],
                       seed: int) -> dict[int, list[dict]]:
    """``n`` rendered images, their objects extracted from each error's mask (truth kept): error -> documents."""
    from mapdb.detections.masks import from_mask
    from mapdb.simulation.rendered import simulate_masks

    classes = {code + 1: name for code, name in enumerate(scene.labels)}
    building = 1 + list(scene.labels).index("building")
    out: dict[int, list[dict]] = {px: [] for px in errors}
    camera = {"altitude": altitude, "fov_deg": 60.0, "size": (640, 480), "yaw": "random", "min_objects": MIN_BLOBS,
              "seed": seed}
    for doc, mask in simulate_masks(m, scene, n, heights=heights, **camera):
        for px in errors:
            changed = from_mask(segmentation_error(mask, building, px), classes, image_id=doc["id"], fov_deg=60.0)
            if len(changed["objects"]) >= 4:
                out[px].append({**changed, "truth": doc["truth"]})
    return out


def localize_all(images: list[dict], matchers: dict[str, tuple[Any, Any]]) -> dict[str, list[dict]]:
    """Every image with every matcher (``label -> (localize(image), its map)``), the order alternating."""
    labels = list(matchers)
    out: dict[str, list[dict]] = {label: [] for label in labels}
    for label in labels:
        fn, m = matchers[label]
        fn(images[0], m)  # builds the map's index once, outside the timing
    for i, im in enumerate(images):
        for label in labels if i % 2 == 0 else labels[::-1]:
            fn, m = matchers[label]
            start = time.perf_counter()
            a = as_json(fn(im, m))
            ms = (time.perf_counter() - start) * 1000.0
            err = float(np.hypot(a["x"] - im["truth"]["x"], a["y"] - im["truth"]["y"])) if a["status"] == "ok" else None
            out[label].append({"ok": a["status"] == "ok", "error_m": err, "ms": ms,
                               "by_areas": a.get("rejected_by") == "areas"})
    return out


def row(extract: str, altitude: float, px: int, label: str, rows: list[dict]) -> str:
    n = len(rows)
    correct = sum(r["ok"] and r["error_m"] <= 2.0 for r in rows)
    wrong = sorted(r["error_m"] for r in rows if r["ok"] and r["error_m"] > 2.0)
    fp = f"{len(wrong)}" + (f" ({', '.join(f'{e:.1f}' for e in wrong)} m)" if wrong else "")
    ms = [r["ms"] for r in rows]
    p95 = float(np.percentile(ms, 95)) if ms else float("nan")
    return (f"{extract:<9} {altitude:>5.0f} {px:>+5d} {label:<22} {n:>6} {correct / max(n, 1):>9.1%} {fp:<16} "
            f"{sum(r['by_areas'] for r in rows):>8} {statistics.median(ms) if ms else float('nan'):>8.0f} {p95:>7.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=100, help="images per extract and altitude")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--altitudes", type=float, nargs="+", default=[120.0])
    parser.add_argument("--errors", type=int, nargs="+", default=[-2, 0, 2],
                        help="pixels: negative erodes the buildings, positive dilates them")
    parser.add_argument("--flat", action="store_true", help="render buildings flat (default: with heights)")
    parser.add_argument("--baseline", metavar="REV", help="also run the matcher of this git revision")
    args = parser.parse_args()
    missing = [p for p in EXTRACTS.values() if not (DATA / p).exists()]
    if missing:
        sys.exit(f"real data not found in {DATA}: {', '.join(missing)}")
    from mapdb.localize.localizer import localize
    from mapdb.mapfile.reader import open_map
    from mapdb.match.options import FastOptions
    from mapdb.simulation.outlines import read_scene

    no_areas = FastOptions(areas=False)
    print(f"{args.n} images per extract and altitude, 640x480, 60 deg, random heading, "
          f"{'flat' if args.flat else 'with heights'}, >= {MIN_BLOBS} blobs before the error")
    print(f"{'extract':<9} {'alt m':>5} {'px':>5} {'matcher':<22} {'images':>6} {'localized':>9} "
          f"{'false positives':<16} {'by areas':>8} {'median ms':>8} {'p95 ms':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        old = None if not args.baseline else (import_baseline(args.baseline, Path(tmp)).localize,
                                             import_baseline(args.baseline, Path(tmp), "store"))
        for name, path in cached_maps(EXTRACTS, DATA, CACHE).items():
            with open_map(path) as m:
                scene = read_scene(DATA / EXTRACTS[name], m.all(), seed=args.seed)
                for altitude in args.altitudes:
                    by_error = images_with_errors(m, scene, args.n, altitude, not args.flat, args.errors, args.seed)
                    matchers: dict[str, tuple[Any, Any]] = {
                        "areas": (localize, m), "--no-areas": (lambda im, mm: localize(im, mm, options=no_areas), m)}
                    with (old[1].open_map(path) if old else open_map(path)) as m_old:
                        if old:
                            matchers[f"baseline {args.baseline}"] = (old[0], m_old)
                        for px, images in by_error.items():
                            for label, rows in localize_all(images, matchers).items():
                                print(row(name, altitude, px, label, rows), flush=True)


if __name__ == "__main__":
    main()
