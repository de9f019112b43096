"""Priors at the wrong place: how often is an image accepted there?  Side by side with a baseline commit.

Images are simulated over each real extract of ``shared/data/osm`` (Andorra, Monaco, Liechtenstein; as
``benchmarks/matcher_core.py`` makes them: 300 m, 60 degrees, random heading, 1 px, 0.05 degree errors, at
least 6 objects), each then localized with a 300 m prior that is wrong:

* **wrong place**: against its own map, the prior's centre moved 2-4 km in a random direction (within the
  map's bounds; the true place lies outside the disc, so any answer is a false alarm);
* **out of map**: against the next extract's map, the prior at a random map object of it;
* **... + heading**: each of the two with the image's true heading in the prior (``heading_deg``, sigma 5 degrees)
  and its true ``altitude_m``: a pose prior (:mod:`mapdb.match.pose_prior`), whose stage runs first and counts
  its own tests.  A baseline without that stage (5144dec) answers these with the disc and the altitude alone.

Every answer accepted is a false alarm.  The disc's search (:mod:`mapdb.match.disc`) counts its pairings as
tests; this says whether that count keeps the wrong-place figures where the quad lookups had them.

Run from the repository root::

    python benchmarks/prior_false_alarms.py --n 100 --baseline 5144dec
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import as_json, cached_maps, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, HEADING_SIGMA_DEG, simulated  # noqa: E402


def wrong_priors(images: list[dict], map_path: Path, other: Path, seed: int) -> dict[str, list[tuple[dict, Path]]]:
    """The images with a wrong prior, per case: (image, the map it is queried against)."""
    from mapdb.mapfile.reader import open_map

    rng = np.random.default_rng(seed)
    with open_map(map_path) as m:
        x0, y0, x1, y1 = m.bounds
    with open_map(other) as m:
        objects = m.all()
    cases: dict[str, list[tuple[dict, Path]]] = {"wrong place": [], "out of map": []}
    for im in images:
        t = im["truth"]
        angle, dist = rng.uniform(0, 2 * math.pi), rng.uniform(2000.0, 4000.0)
        x = min(max(t["x"] + dist * math.cos(angle), x0), x1)
        y = min(max(t["y"] + dist * math.sin(angle), y0), y1)
        if math.hypot(x - t["x"], y - t["y"]) > 1000.0:  # clamped into the map, still far from the truth
            cases["wrong place"].append(({**im, "prior": {"x": x, "y": y, "radius": 300.0}}, map_path))
        k = int(rng.integers(len(objects.x)))
        prior = {"x": float(objects.x[k]), "y": float(objects.y[k]), "radius": 300.0}
        cases["out of map"].append(({**im, "prior": prior}, other))
    # The heading and the scale right, the place wrong: the pose prior's own false alarms.
    for case in ("wrong place", "out of map"):
        cases[f"{case} + heading"] = [(posed(im), path) for im, path in cases[case]]
    return cases


def posed(im: dict) -> dict:
    """The image with its true heading in its prior (sigma ``HEADING_SIGMA_DEG``) and its true altitude."""
    heading = {"heading_deg": im["truth"]["heading_deg"] % 360.0, "heading_sigma_deg": HEADING_SIGMA_DEG}
    return {**im, "altitude_m": im["truth"]["altitude_m"], "prior": {**im["prior"], **heading}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=100, help="images a map")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--baseline", metavar="REV", help="also run the matcher of this git revision")
    args = parser.parse_args()
    if not all((DATA / pbf).exists() for pbf in EXTRACTS.values()):
        sys.exit(f"skipped: the extracts are not all in {DATA}")
    maps = cached_maps(EXTRACTS, DATA, CACHE)
    from mapdb.localize import localizer
    from mapdb.mapfile import reader

    with tempfile.TemporaryDirectory() as tmp:
        versions = {"this tree": (localizer.localize, reader)}
        if args.baseline:
            old = import_baseline(args.baseline, Path(tmp))
            versions[f"baseline {args.baseline}"] = (old.localize, import_baseline(args.baseline, Path(tmp), "store"))
        names = list(maps)
        print(f"{args.n} images a map, 300 m priors at the wrong place; accepted = false alarms; \"+ heading\": the "
              f"true heading (sigma {HEADING_SIGMA_DEG:g} deg) and altitude too (a baseline without the pose-prior "
              "stage: disc and altitude only); pose-prior = answers decided by that stage")
        print(f"  {'map':<14} {'code':<17} {'case':<22} {'accepted':>9} {'best score':>10} {'pose-prior':>10}")
        for i, name in enumerate(names):
            other = maps[names[(i + 1) % len(names)]]
            cases = wrong_priors(simulated(maps[name], args.n, args.seed), maps[name], other, args.seed + i)
            for label, (localize, store) in versions.items():
                for case, items in cases.items():
                    opened = {path: store.open_map(path) for path in {p for _, p in items}}
                    answers = [as_json(localize(im, opened[path])) for im, path in items]
                    for m in opened.values():
                        m.close()
                    accepted = sum(a["status"] == "ok" for a in answers)
                    scores = [c["score"] for a in answers for c in a.get("candidates", []) if c.get("score")]
                    best = max(scores, default=float("nan"))
                    staged = sum(a.get("path") == "pose-prior" for a in answers)  # accepted by the pose stage
                    print(f"  {name:<14} {label:<17} {case:<22} {accepted:4d}/{len(answers):<4d} {best:10.1f} "
                          f"{staged:10d}")


if __name__ == "__main__":
    main()
