"""Terrain: a flight over Monaco with the shared SRTM tile, navigated with and without the terrain hook (issue 33).

The project's Monaco map is built twice from ``../shared/data/osm/monaco-2021-12-03.osm.pbf``: with
``--dem ../shared/data/dem/N43E007.hgt`` (each object at its ground elevation) and without (flat).  One flight
of ``--length`` metres (default 3 km) over the default survey pattern (``mapdb simulate flight``), ideal
centroids, 60 degree field of view, 640x480, 1 px detector noise, 0.1 degree attitude error, 10 frames a
second, the default barometer (2 m bias std, 0.3 m noise), started at the truth (radius 30 m).  Rows:

* **following, hook on**: the flight over the DEM map (objects at their heights), planned ``--altitude``
  metres above the ground under each frame and flown as barometric altitudes (``--altitude-above ground``:
  the frames carry only the barometer, above the datum), navigated with the height above ground = barometer
  minus the map's elevation at the filter's position (:mod:`mapdb.navigation.terrain`);
* **following, hook off**: the same frames, the navigator taking the barometric altitude as the height above
  the ground (``NavigatorOptions(terrain=False)``: the flat assumption);
* **one pressure altitude, hook on**: the same path holding the barometric altitude of ``--altitude`` metres
  above the ground under the start (``--altitude-above start``, the default): the height above the ground
  changes with the ground;
* **flat control**: the same path at a constant ``--altitude`` over the flat map (every object on one plane).

Run from the repository root::

    python benchmarks/terrain_flight.py                    # 3 km at 120 m, the three rows
    python benchmarks/terrain_flight.py --length 500       # a quick look

Prints, per row: frames, frames within 2 m of the truth, the largest error, wrong fixes (fixes applied from
an answer more than 2 m from the truth), frames with a fix applied, the height above ground's range (truth)
and the navigator's error on it (median and largest, of the frames it was computed for), the frames showing
fewer than 6 objects, and the median time per frame.  The same
flight from the command line::

    mapdb build monaco-2021-12-03.osm.pbf --dem N43E007.hgt -o monaco-dem.mapdb
    mapdb simulate flight monaco-dem.mapdb -o flight.jsonl --length 3000 --altitude 120 --fov 60 \\
        --pixel-std 1 --attitude-std 0.1 --altitude-above ground
    mapdb navigate monaco-dem.mapdb flight.jsonl -o track.jsonl --initial X,Y,30
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.simulation.terrain import terrain_of

ROOT = Path(__file__).resolve().parents[1]
SHARED = next((p for p in (ROOT.parent / "shared" / "data", Path("/work/shared/data")) if p.is_dir()),
              ROOT.parent / "shared" / "data")
MONACO = SHARED / "osm" / "monaco-2021-12-03.osm.pbf"
DEM = SHARED / "dem" / "N43E007.hgt"
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-terrain-flight"
START_RADIUS_M = 30.0
WITHIN_M = 2.0
# A frame showing fewer objects than this is rarely localized (the fast matcher needs a quad and support).
SPARSE = 6


def build(out: Path, dem: Path | None) -> Path:
    """Monaco's map (with ``dem``), built once into the cache."""
    from mapdb.build.pipeline import build_map

    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        build_map([MONACO], out, dem=[dem] if dem else ())
    return out


def navigate(m, frames: list[dict], terrain: bool) -> list:
    """Every frame navigated from the truth's start (radius 30 m)."""
    start = frames[0]["truth"]
    navigator = Navigator(m, NavigatorOptions(terrain=terrain), initial=(start["x"], start["y"], START_RADIUS_M))
    return [navigator.step(frame) for frame in frames]


def measures(records: list, frames: list[dict]) -> dict:
    """The row's figures (module docs)."""
    error = np.array([r.truth["error_m"] if r.truth["error_m"] is not None else np.inf for r in records])
    wrong = 0
    for r, f in zip(records, frames, strict=True):
        if r.fix.get("status") in ("used", "initialised") and r.fix.get("x") is not None:
            wrong += math.hypot(r.fix["x"] - f["truth"]["x"], r.fix["y"] - f["truth"]["y"]) > WITHIN_M
    above = np.array([f["truth"]["altitude_m"] for f in frames])
    agl = np.array([abs(r.altitude["above_ground_m"] - f["truth"]["altitude_m"]) for r, f in zip(records, frames,
                    strict=True) if r.altitude and r.altitude.get("used")])
    return {"frames": len(frames), "within": float(np.mean(error <= WITHIN_M)), "max": float(np.max(error)),
            "wrong": wrong, "fixes": sum(r.status == "fix" for r in records),
            "agl": (float(above.min()), float(above.max())),
            "sparse": float(np.mean([len(f["objects"]) < SPARSE for f in frames])),
            "agl_err": (float(np.median(agl)), float(np.max(agl))) if agl.size else None,
            "ms": float(np.median([r.time_ms["total"] for r in records]))}


def rows(length: float, altitude: float) -> list[tuple[str, dict]]:
    """The four rows (module docs)."""
    options = FlightOptions(length_m=length, altitude_m=altitude, fov_deg=60.0, pixel_std=1.0, attitude_std=0.1)
    out = []
    with open_map(build(CACHE / "monaco-dem.mapdb", DEM)) as m:
        following = simulate_flight(m, replace(options, altitude_above="ground"), terrain=terrain_of(m))
        held = simulate_flight(m, options, terrain=terrain_of(m))
        for name, frames, hook in (("following, hook on", following, True), ("following, hook off", following, False),
                                   ("one pressure altitude, hook on", held, True)):
            out.append((name, measures(navigate(m, frames, hook), frames)))
            print(f"{name}: done", file=sys.stderr)
    with open_map(build(CACHE / "monaco-flat.mapdb", None)) as m:
        frames = simulate_flight(m, options)
        out.append(("flat control", measures(navigate(m, frames, True), frames)))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--length", type=float, default=3000.0, help="metres flown (default 3000)")
    parser.add_argument("--altitude", type=float, default=120.0,
                        help="height above the ground (each frame's, or the start's), metres (default 120)")
    args = parser.parse_args()
    if not (MONACO.exists() and DEM.exists()):
        sys.exit(f"skipped: {MONACO} or {DEM} not found")
    table = rows(args.length, args.altitude)
    print(f"\nMonaco, {args.length:g} m at {args.altitude:g} m above the ground, 60 deg, 640x480, "
          "1 px, 0.1 deg, 10 fps, started at the truth (R 30 m)")
    print(f"| row | frames | within {WITHIN_M:g} m | largest error m | wrong fixes | fix frames | "
          f"height above ground m | its error m (median / max) | frames < {SPARSE} objects | median ms/frame |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, r in table:
        agl_err = "-" if r["agl_err"] is None else f"{r['agl_err'][0]:.2f} / {r['agl_err'][1]:.2f}"
        print(f"| {name} | {r['frames']} | {r['within']:.1%} | {r['max']:.2f} | {r['wrong']} | {r['fixes']} | "
              f"{r['agl'][0]:.0f}-{r['agl'][1]:.0f} | {agl_err} | {r['sparse']:.1%} | {r['ms']:.1f} |")


if __name__ == "__main__":
    main()
