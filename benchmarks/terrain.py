"""Terrain: Monaco with the shared SRTM tile, single images localized over relief (issue 33).

The project's own Monaco map is built twice from ``../shared/data/osm/monaco-2021-12-03.osm.pbf``: with
``--dem ../shared/data/dem/N43E007.hgt`` (each object at its ground elevation) and without (flat).  Images
are simulated as the issue measured them: a level camera (yaw random) at 120 m and at 300 m above the ground
under it, 60 degree field of view, 640x480, 1 px detector noise, at least 6 objects in view, field of view and
attitude given, no prior; with and without ``altitude_m`` (the camera's height above the ground under it).
The control is the same configuration over the flat map (every object at one height).  Each image is
localized against the map it was simulated from (the one with elevation for the terrain rows).

Run from the repository root::

    python benchmarks/terrain.py --n 500            # the issue's table, 500 images a row
    python benchmarks/terrain.py --n 50 --rows 120  # a quick look
    python benchmarks/terrain.py --n 500 --no-altitude --baseline main  # beside main, image by image
    python benchmarks/terrain.py --sizes            # bytes an object that elevation adds (Monaco, Andorra)
    python benchmarks/terrain.py --wrong-place      # Monaco's images against Andorra's map: false alarms
    python benchmarks/terrain.py --ground           # the map's ground under the nadirs against the DEM's

Prints, per row: images, localized within 2 m, accepted 2-5 m off, accepted more than 5 m off, rejected, the
RMS of the localized (within 2 m), and the median time per image.  ``--sizes`` builds Monaco with the SRTM
tile and Andorra with a synthetic DEM of its relief (900-2,900 m, 3 arc-second posts: no tile of Andorra is
shared), each against its flat build.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = next((p for p in (ROOT.parent / "shared" / "data", Path("/work/shared/data")) if p.is_dir()),
              ROOT.parent / "shared" / "data")
MONACO = SHARED / "osm" / "monaco-2021-12-03.osm.pbf"
ANDORRA = SHARED / "osm" / "andorra-2021-06-22.osm.pbf"
DEM = SHARED / "dem" / "N43E007.hgt"
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-terrain"


def build(source: Path, out: Path, dem: Path | None = None) -> Path:
    """A map of ``source`` (with ``dem``), built once into the cache (by this tree's map-writing code)."""
    from _baseline import code_digest

    from mapdb.build.pipeline import build_map

    out = out.with_name(f"{out.stem}.{code_digest()}{out.suffix}")
    if not out.exists():
        build_map([source], out, dem=[dem] if dem else ())
    return out


def synthetic_andorra_dem(path: Path) -> Path:
    """An Andorra-like DEM: smooth relief from 900 to 2,900 m and 15 m of roughness, 3 arc-second posts."""
    import rasterio
    from rasterio.transform import from_origin
    from scipy.ndimage import gaussian_filter

    if path.exists():
        return path
    rng = np.random.default_rng(7)
    f = gaussian_filter(rng.standard_normal((1201, 1201)), 25)
    f = (f - f.min()) / (f.max() - f.min())
    g = gaussian_filter(rng.standard_normal((1201, 1201)), 4)
    z = 900 + 2000 * f + 15 * g / g.std()
    with rasterio.open(path, "w", driver="GTiff", width=1201, height=1201, count=1, dtype="int16", crs="EPSG:4326",
                       transform=from_origin(1.0 - 1 / 2400, 43.0 + 1 / 2400, 1 / 1200, 1 / 1200),
                       nodata=-32768) as out:
        out.write(np.rint(z).astype(np.int16), 1)
    return path


def sizes() -> None:
    """Bytes an object that elevation adds to Monaco's and Andorra's maps."""
    print("| map | objects | flat bytes | with elevation | bytes an object more |")
    print("|---|---|---|---|---|")
    for name, source, dem in (("Monaco (SRTM N43E007)", MONACO, DEM),
                              ("Andorra (synthetic DEM)", ANDORRA, synthetic_andorra_dem(CACHE / "andorra.tif"))):
        flat = build(source, CACHE / f"{source.stem}.flat.mapdb")
        high = build(source, CACHE / f"{source.stem}.dem.mapdb", dem)
        from mapdb.mapfile.reader import open_map

        with open_map(high) as m:
            n = len(m)
        grew = high.stat().st_size - flat.stat().st_size
        print(f"| {name} | {n} | {flat.stat().st_size} | {high.stat().st_size} | {grew / n:.3f} |")


def row(map_path: Path, altitude: float, n: int, seed: int, with_altitude: bool, terrain: bool,
        jobs: int) -> dict:
    """Simulate and localize one row of the table."""
    from mapdb.evaluation.evaluate import evaluate_images
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.simulate import simulate_images
    from mapdb.simulation.terrain import terrain_of

    with open_map(map_path) as m:
        images = simulate_images(m, n, altitude=altitude, fov_deg=60.0, size=(640, 480), yaw="random",
                                 pixel_std=1.0, with_attitude=True, with_altitude=with_altitude, min_objects=6,
                                 seed=seed, terrain=terrain_of(m, (DEM,)) if terrain else None)
        outcomes, _ = evaluate_images(m, images, jobs=jobs)
    error = np.array([o["error_m"] if o["status"] == "ok" else np.nan for o in outcomes])
    ok = np.isfinite(error)
    good = ok & (error <= 2.0)
    return {"images": len(outcomes), "within_2m": int(good.sum()),
            "off_2_5": int((ok & (error > 2) & (error <= 5)).sum()), "off_5": int((ok & (error > 5)).sum()),
            "rejected": int((~ok).sum()),
            "rms": float(np.sqrt(np.mean(error[good] ** 2))) if good.any() else float("nan"),
            "time_ms": statistics.median(o["time_ms"] for o in outcomes)}


def wrong_place(altitude: float, n: int, seed: int) -> dict:
    """Monaco's images over its terrain (altitude given) localized against Andorra's map with elevation (its
    synthetic DEM): the place is not in the map, so every accepted answer is a false alarm."""
    from mapdb.localize.localizer import Localizer
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.simulate import simulate_images
    from mapdb.simulation.terrain import terrain_of

    with open_map(build(MONACO, CACHE / "monaco.dem.mapdb", DEM)) as m:
        images = simulate_images(m, n, altitude=altitude, fov_deg=60.0, size=(640, 480), yaw="random",
                                 pixel_std=1.0, with_attitude=True, with_altitude=True, min_objects=6, seed=seed,
                                 terrain=terrain_of(m, (DEM,)))
    andorra = build(ANDORRA, CACHE / f"{ANDORRA.stem}.dem.mapdb", synthetic_andorra_dem(CACHE / "andorra.tif"))
    with open_map(andorra) as other:
        localizer = Localizer(other)
        answers = [localizer.localize({k: v for k, v in image.items() if k != "truth"}) for image in images]
    return {"images": len(answers), "accepted": sum(a.status == "ok" for a in answers)}


def summary(errors: list[float], times: list[float]) -> dict:
    """A row's counts from each image's error (NaN: rejected) and its median time."""
    error = np.array(errors)
    ok = np.isfinite(error)
    good = ok & (error <= 2.0)
    return {"images": error.size, "within_2m": int(good.sum()),
            "off_2_5": int((ok & (error > 2) & (error <= 5)).sum()), "off_5": int((ok & (error > 5)).sum()),
            "rejected": int((~ok).sum()),
            "rms": float(np.sqrt(np.mean(error[good] ** 2))) if good.any() else float("nan"),
            "time_ms": statistics.median(times)}


def row_beside(map_path: Path, altitude: float, n: int, seed: int, with_altitude: bool, terrain: bool,
               baseline: object) -> tuple[dict, dict]:
    """One row localized by this tree and by ``baseline`` (a ``mapdb`` package of another revision) in this
    process, image by image, alternating which goes first (so both see the same load)."""
    import time

    from mapdb.localize.localizer import Localizer
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.simulate import simulate_images
    from mapdb.simulation.terrain import terrain_of

    old = baseline
    with open_map(map_path) as m, old.mapfile.reader.open_map(map_path) as m_old:  # type: ignore[attr-defined]
        images = simulate_images(m, n, altitude=altitude, fov_deg=60.0, size=(640, 480), yaw="random",
                                 pixel_std=1.0, with_attitude=True, with_altitude=with_altitude, min_objects=6,
                                 seed=seed, terrain=terrain_of(m, (DEM,)) if terrain else None)
        pair = (Localizer(m), old.localize.localizer.Localizer(m_old))  # type: ignore[attr-defined]
        errors: tuple[list[float], list[float]] = ([], [])
        times: tuple[list[float], list[float]] = ([], [])
        for i, image in enumerate(images):
            for which in ((0, 1) if i % 2 == 0 else (1, 0)):
                start = time.perf_counter()
                answer = pair[which].localize(image)
                times[which].append((time.perf_counter() - start) * 1000.0)
                truth = image["truth"]
                errors[which].append(math.hypot(answer.x - truth["x"], answer.y - truth["y"])
                                     if answer.status == "ok" else math.nan)
    return summary(errors[0], times[0]), summary(errors[1], times[1])


def ground_errors(altitude: float, n: int, seed: int) -> None:
    """The matcher's ground under the nadir (:meth:`TerrainModel.nadir_ground`, from the map's objects) against
    the DEM's, at the nadirs of a row's images: its error and the error over its modelled sigma."""
    from mapdb.mapfile.reader import open_map
    from mapdb.match.evidence.terrain import TerrainModel
    from mapdb.match.mapobjects.object_index import ObjectIndex
    from mapdb.simulation.simulate import simulate_images
    from mapdb.simulation.terrain import terrain_of

    with open_map(build(MONACO, CACHE / "monaco.dem.mapdb", DEM)) as m:
        images = simulate_images(m, n, altitude=altitude, fov_deg=60.0, size=(640, 480), yaw="random",
                                 pixel_std=1.0, with_attitude=True, with_altitude=True, min_objects=6, seed=seed,
                                 terrain=terrain_of(m, (DEM,)))
        model = TerrainModel(ObjectIndex(m.all()), 1.0, altitude)
    found = [model.nadir_ground(complex(im["truth"]["x"], im["truth"]["y"])) for im in images]
    error = np.array([abs(im["truth"]["ground_m"] - g) for im, (g, _) in zip(images, found, strict=True)])
    ratio = error / np.sqrt([v for _, v in found])
    print(f"| {altitude:.0f} m, {error.size} nadirs | {np.median(error):.2f} m | {np.quantile(error, 0.9):.2f} m | "
          f"{error.max():.1f} m | {np.quantile(ratio, 0.9):.2f} | {np.quantile(ratio, 0.99):.2f} | {ratio.max():.2f} |")


def load_baseline(rev: str) -> object:
    """The ``mapdb`` package of git revision ``rev``, as ``mapdb_baseline`` (``benchmarks/_baseline.py``)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _baseline import import_baseline

    import_baseline(rev, CACHE, "localize")
    import mapdb_baseline.localize.localizer
    import mapdb_baseline.mapfile.reader  # noqa: F401

    return sys.modules["mapdb_baseline"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=500, help="images a row")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rows", nargs="*", type=float, default=[120.0, 300.0], help="altitudes above ground")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--no-altitude", action="store_true", help="also the rows without altitude_m")
    parser.add_argument("--sizes", action="store_true", help="only the map sizes")
    parser.add_argument("--baseline", metavar="REV",
                        help="also localize every image with the matcher of this git revision, in this process")
    parser.add_argument("--ground", action="store_true",
                        help="only the error of the map's ground under the nadirs against the DEM's")
    parser.add_argument("--wrong-place", action="store_true",
                        help="only the wrong-place check: Monaco's images against Andorra's map with elevation")
    args = parser.parse_args()
    CACHE.mkdir(parents=True, exist_ok=True)
    if not MONACO.is_file() or not DEM.is_file():
        sys.exit(f"real data absent: {MONACO} or {DEM} (see ../shared/data/SOURCES.md)")
    if args.sizes:
        sizes()
        return
    if args.ground:
        print("| nadirs | median error | 90th percentile | largest | error / sigma: 90th pct (Gaussian 1.64) "
              "| 99th (2.58) | largest |")
        print("|---|---|---|---|---|---|---|")
        for altitude in args.rows:
            ground_errors(altitude, args.n, args.seed)
        return
    if args.wrong_place:
        print("| Monaco's images (altitude given) against Andorra's map with elevation | accepted (false alarms) |")
        print("|---|---|")
        for altitude in args.rows:
            r = wrong_place(altitude, args.n, args.seed)
            print(f"| {altitude:.0f} m, {r['images']} images | {r['accepted']} |", flush=True)
        return
    high = build(MONACO, CACHE / "monaco.dem.mapdb", DEM)
    flat = build(MONACO, CACHE / "monaco.flat.mapdb")
    print(f"| {args.n} images a row | localized within 2 m | accepted 2-5 m off | accepted > 5 m off | rejected "
          "| RMS of the localized | median time |")
    print("|---|---|---|---|---|---|---|")
    baseline = load_baseline(args.baseline) if args.baseline else None
    for with_altitude in [True, False] if args.no_altitude else [True]:
        for altitude in args.rows:
            for terrain, path in ((True, high), (False, flat)):
                what = "objects at their DEM heights" if terrain else "control: every object at one height"
                alt = "altitude given" if with_altitude else "no altitude"
                if baseline is None:
                    results = [("", row(path, altitude, args.n, args.seed, with_altitude, terrain, args.jobs))]
                else:
                    mine, theirs = row_beside(path, altitude, args.n, args.seed, with_altitude, terrain, baseline)
                    results = [(f", {args.baseline}", theirs), (", this tree", mine)]
                for tag, r in results:
                    print(f"| {altitude:.0f} m, {what}, {alt}{tag} | {100 * r['within_2m'] / r['images']:.1f} % | "
                          f"{r['off_2_5']} | {r['off_5']} | {r['rejected']} | {r['rms']:.2f} m | "
                          f"{r['time_ms']:.0f} ms |", flush=True)

if __name__ == "__main__":
    main()
