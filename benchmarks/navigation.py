"""Navigation over the real extracts: the figures issue 12 asks for, measured.

For Andorra and Monaco (``../shared/data/osm``, built with ``mapdb build`` into a temporary directory), a
5 km flight over the map's densest part (the default survey pattern of ``mapdb simulate flight``) at 150 m,
20 m/s and 10 frames per second, 70 degree field of view, 1 px pixel error, 0.1 degree attitude error, 20 %
missed detections and a 2 s blackout (no detections at all) from 60 s, navigated three ways:

1. **tracking**: started at the true position (radius 30 m): RMS and largest error over every frame, frames
   with an error over 10 m; the time per frame (filter plus query) against the 100 ms of a 10 Hz camera,
   and the prior-aided query's share;
2. **started 200 m off**: ``--initial`` 200 m east of the truth with a radius of 30 m (a confident, wrong
   start): seconds until the error falls below 1 m and stays below 2 m, the RMS and largest error after;
3. **map withheld for 30 s** (from 100 s; the matcher off, frame-to-frame velocity alone): the error when
   the map returns divided by the 30 s (drift per second of flight), the largest error in the gap, and the
   seconds from the map's return until the error is below 1 m again.

Run from the repository root (about 5 minutes on the 2-core machine)::

    python benchmarks/navigation.py [--plot DIR]

``--plot DIR`` also draws each map's tracking run (``DIR/MAP.png``).  The same runs from the command line::

    mapdb simulate flight andorra.mapdb -o flight.jsonl --pixel-std 1 --attitude-std 0.1 --miss-rate 0.2 \\
        --blackout 60:2 [--map-gap 100:30]
    mapdb navigate andorra.mapdb flight.jsonl -o track.jsonl --initial X,Y,30 --plot track.png
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.navigator import Navigator
from mapdb.navigation.track import plot_track

OSM = next((p for p in (Path(__file__).resolve().parents[2] / "shared" / "data" / "osm", Path("/work/shared/data/osm"))
            if p.exists()), Path(__file__).resolve().parents[2] / "shared" / "data" / "osm")
MAPS = {"Andorra": "andorra-2021-06-22.osm.pbf", "Monaco": "monaco-2021-12-03.osm.pbf"}
FLIGHT = {"length_m": 5000.0, "altitude_m": 150.0, "fps": 10.0, "pixel_std": 1.0, "attitude_std": 0.1,
          "miss_rate": 0.2, "blackouts": ((60.0, 2.0),)}
GAP = (100.0, 30.0)
OFFSET_M = 200.0
START_RADIUS_M = 30.0


def _errors(records) -> np.ndarray:
    return np.array([r.truth["error_m"] if r.truth["error_m"] is not None else np.inf for r in records])


def _navigate(m, frames, offset: float = 0.0) -> list:
    start = frames[0]["truth"]
    navigator = Navigator(m, initial=(start["x"] + offset, start["y"], START_RADIUS_M))
    return [navigator.step(frame) for frame in frames]


def _settled(error: np.ndarray, below: float, stays: float) -> int | None:
    """First frame from which the error is below ``below`` and stays below ``stays``."""
    over = np.flatnonzero(error >= stays)
    for i in np.flatnonzero(error < below):
        if not over.size or over[-1] < i:
            return int(i)
    return None


def _tracking(name: str, m, frames, plot_dir: Path | None) -> dict:
    records = _navigate(m, frames)
    error = _errors(records)
    total = np.array([r.time_ms["total"] for r in records])
    query = np.array([r.time_ms.get("query", 0.0) for r in records])
    if plot_dir is not None:
        plot_track(records, m, plot_dir / f"{name.lower()}.png",
                   title=f"{name}: 5 km at 150 m, 1 px, 0.1°, 20 % missed, 2 s blackout at 60 s")
    return {"frames": len(frames), "rms": math.sqrt(float(np.mean(error**2))), "max": float(np.max(error)),
            "over10": int(np.sum(error > 10.0)), "fixes": sum(r.status == "fix" for r in records),
            "median_ms": float(np.median(total)), "p95_ms": float(np.percentile(total, 95)),
            "query_median_ms": float(np.median(query[query > 0])), "query_share": float(query.sum() / total.sum())}


def _offset(m, frames) -> dict:
    records = _navigate(m, frames, OFFSET_M)
    error = _errors(records)
    settled = _settled(error, 1.0, 2.0)
    after = error[settled:] if settled is not None else np.array([np.inf])
    return {"start_error": float(error[0]),
            "recovered_s": None if settled is None else frames[settled]["time_s"],
            "rms_after": math.sqrt(float(np.mean(after**2))), "max_after": float(np.max(after))}


def _gap(m, frames) -> dict:
    records = _navigate(m, frames)
    error = _errors(records)
    t = np.array([f["time_s"] for f in frames])
    inside = np.array([bool(f.get("map_withheld")) for f in frames])
    last = int(np.flatnonzero(inside)[-1])
    back = next((i for i in range(last + 1, len(frames)) if error[i] < 1.0), None)
    outside = ~inside
    return {"at_return": float(error[last]), "drift_per_s": float(error[last]) / GAP[1],
            "max_in_gap": float(np.max(error[inside])),
            "snap_back_s": None if back is None else float(t[back] - t[last + 1]) + 0.1,
            "rms_outside": math.sqrt(float(np.mean(error[outside] ** 2)))}


def _fmt(value, digits: int = 2) -> str:
    return "never" if value is None else f"{value:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--plot", type=Path, default=None, metavar="DIR")
    args = parser.parse_args()
    if not OSM.exists():
        sys.exit(f"skipped: {OSM} not found")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, source in MAPS.items():
            map_path = Path(tmp) / f"{name.lower()}.mapdb"
            subprocess.run(["mapdb", "build", "-q", str(OSM / source), "-o", str(map_path)], check=True,
                           stdout=subprocess.DEVNULL)
            with open_map(map_path) as m:
                frames = simulate_flight(m, FlightOptions(**FLIGHT))
                gapped = simulate_flight(m, FlightOptions(**FLIGHT, map_gaps=(GAP,)))
                row = {"map": name, **_tracking(name, m, frames, args.plot), **_offset(m, frames), **_gap(m, gapped)}
            rows.append(row)
            print(f"{name}: done", file=sys.stderr)
    _print(rows)


def _print(rows: list[dict]) -> None:
    print("\n5 km at 150 m, 10 fps, 1 px, 0.1 deg, 20 % missed, 2 s blackout at 60 s; started at the truth (R 30 m)")
    print(f"{'map':<8} {'frames':>6} {'fix frames':>10} {'RMS m':>6} {'max m':>6} {'>10 m':>5} "
          f"{'median ms':>9} {'95th ms':>7} {'query median ms':>15} {'query share':>11}")
    for r in rows:
        print(f"{r['map']:<8} {r['frames']:>6} {r['fixes']:>10} {r['rms']:>6.2f} {r['max']:>6.2f} {r['over10']:>5} "
              f"{r['median_ms']:>9.1f} {r['p95_ms']:>7.1f} {r['query_median_ms']:>15.1f} {r['query_share']:>11.0%}")
    print(f"\nthe same flight started {OFFSET_M:g} m off (R {START_RADIUS_M:g} m)")
    print(f"{'map':<8} {'start error m':>13} {'recovered at s':>14} {'RMS after m':>11} {'max after m':>11}")
    for r in rows:
        print(f"{r['map']:<8} {r['start_error']:>13.1f} {_fmt(r['recovered_s'], 1):>14} {r['rms_after']:>11.2f} "
              f"{r['max_after']:>11.2f}")
    print(f"\nthe map withheld for {GAP[1]:g} s from {GAP[0]:g} s (frame-to-frame velocity alone)")
    print(f"{'map':<8} {'error at return m':>17} {'drift m/s':>9} {'max in gap m':>12} {'snap back s':>11} "
          f"{'RMS outside m':>13}")
    for r in rows:
        print(f"{r['map']:<8} {r['at_return']:>17.2f} {r['drift_per_s']:>9.3f} {r['max_in_gap']:>12.2f} "
              f"{_fmt(r['snap_back_s'], 1):>11} {r['rms_outside']:>13.2f}")


if __name__ == "__main__":
    main()
