"""Navigation from rendered masks over the real extracts: the figures of issue 29, measured (and a baseline's).

Each flight is ``mapdb simulate flight --render masks`` over the built parts of a shared extract (the
default survey pattern, :func:`mapdb.navigation.path.survey_pattern`: of lawn-mower rectangles of several
leg lengths and orientations, each placed where it holds the most map objects, the one whose path sees
the most objects within 60 m, counted up to 8, every 25 m; the **>=6 blobs** column says how built the
path is), 60 degree field of view, 640x480, 5 fps, 20 m/s,
0.1 degree attitude error, the turbulence and sensor biases of the flight simulator; its frames are the
blobs of label masks rendered from the extract's outlines with each frame's pose.  Cases (``--cases``):

* ``heights``: buildings extruded to their heights; ``flat``: drawn flat (``--no-heights``);
* ``thin15``: with heights, over a map built from the extract with 15 % of its buildings left out
  (:func:`mapdb.simulation.thinning.thin_extract`, seed 1): the camera sees buildings the map lacks;
* ``erode2`` / ``dilate2``: with heights, every mask region eroded / dilated by 2 px;
* ``blobs10``: with heights, 10 % of the objects missed and 10 % spurious blobs;
* ``ideal``: the centroid flights of ``benchmarks/navigation.py`` (150 m, 70 degrees, 10 fps, 1 px, 20 %
  missed, a 2 s blackout at 60 s), to check that they do not get worse.

Each at every ``--altitudes`` and navigated from every ``--starts``: ``lis`` (lost in space: no initial
position) and ``initial`` (``--initial`` at the true start, radius 30 m).  Per flight:

* **>=6 blobs** / **whole**: share of frames with 6 or more blobs, and with 6 or more not cut by the border
  (3 km at 120 m with heights: Monaco 100 % / 55 %, Andorra 96 % / 23 %: Andorra's blocks are large);
* **fix**: share of frames whose status is "fix"; **<=2 m**, **<=5 m**: share of the frames from the first
  fix on within 2 and 5 m of the truth; **max**: the largest error from the first fix on;
* **ttff**: seconds from the first frame to the first fix; **after 6**: seconds from the first frame with 6
  or more blobs to the first fix (the issue's "within 5 s");
* **bias along/across**: the mean error of the frame-to-frame velocity measurements from the first fix on
  (before it the heading and scale carry the magnetometer's and barometer's biases), m/s, along and across
  the true track, with its standard error; **wrong**: applied fixes more than 5 m from the truth;
* **>3 sigma**: share of the placed frames whose error lies beyond the stated 3 sigma (the error's
  Mahalanobis distance under the stated covariance over 3, 1.1 % for a consistent 2-D Gaussian);
  **NEES**: its mean square (2 for a consistent filter; clipped at 1e4 a frame);
* **ms median / p95**: the navigator's time per frame (filter and query);
* **stitched**: frames whose applied fix came from the frame stitched with the ones before it
  (``fix_frames`` of more than one frame, :mod:`mapdb.navigation.stitch`).

``--stitch K1,K2,...`` navigates every flight with each number of stitched frames (0: single frames only),
side by side in the same process, one row each.

``--variants "velocity_bias=off;velocity_bias=significant"`` navigates every flight with each set of
:class:`~mapdb.navigation.navigator.NavigatorOptions` changes, side by side in the same process, one row each.

``--baseline REV`` also navigates every flight with the mapdb of git revision ``REV`` in the same
process, frame by frame alternating which goes first, and prints its row under each row of this tree.
Flights are rendered once and kept in ``--cache`` (keyed by their parameters and the simulator's source).

Run from the repository root (a 3 km flight is 751 frames; rendering takes 0.1-0.3 s a frame and
navigating 0.05-0.3 s on the shared 2-core machine: ``--length`` shortens the flights)::

    python benchmarks/navigation_masks.py --maps andorra,monaco --length 3000 --baseline main
    python benchmarks/navigation_masks.py --maps monaco --cases heights,thin15 --starts lis --length 1000
    python benchmarks/navigation_masks.py --maps monaco,andorra --cases heights --altitudes 120 --stitch 0,3,5 \
        --baseline main
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import ROOT, import_baseline, shared_data  # noqa: E402

DATA = shared_data("osm")
EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf",
            "liechtenstein": "liechtenstein-2013-08-03.osm.pbf"}
CASES = {"heights": {}, "flat": {"heights": False}, "thin15": {"thin": 0.15}, "erode2": {"mask_offset_px": -2},
         "dilate2": {"mask_offset_px": 2}, "blobs10": {"blob_miss_rate": 0.1, "blob_spurious_rate": 0.1},
         "ideal": {"ideal": True}}
# The ideal flights of benchmarks/navigation.py (centroids, not masks; the altitude given is not used).
IDEAL = {"altitude_m": 150.0, "fps": 10.0, "pixel_std": 1.0, "attitude_std": 0.1, "miss_rate": 0.2,
         "blackouts": ((60.0, 2.0),)}
FLIGHT = {"fov_deg": 60.0, "size": (640, 480), "fps": 5.0, "speed_mps": 20.0, "attitude_std": 0.1}
START_RADIUS_M = 30.0
THIN_SEED = 1
WRONG_M = 5.0
NEES_CLIP = 1e4
SIMULATOR = ("mapdb/navigation/flight.py", "mapdb/navigation/rendered.py", "mapdb/simulation/render.py",
             "mapdb/simulation/outlines.py", "mapdb/detections/masks.py")


def _maps(name: str, cache: Path) -> tuple[Path, Path]:
    """The extract's map and its thinned map (15 % of the buildings left out), built once into ``cache``."""
    from mapdb.build.pipeline import build_map
    from mapdb.simulation.thinning import thin_extract

    cache.mkdir(parents=True, exist_ok=True)
    full, thin = cache / f"{name}.mapdb", cache / f"{name}-thin15.mapdb"
    if not full.exists():
        build_map([DATA / EXTRACTS[name]], full)
    if not thin.exists():
        extract = cache / f"{name}-thin15.osm.pbf"
        thin_extract(DATA / EXTRACTS[name], extract, 0.15, THIN_SEED)
        build_map([extract], thin)
    return full, thin


def _flight(name: str, case: str, altitude: float, length: float, cache: Path) -> list[dict[str, Any]]:
    """The rendered flight (from the cache when it was rendered before by the same simulator)."""
    from mapdb.mapfile.reader import open_map
    from mapdb.navigation.flight import FlightOptions, simulate_flight
    from mapdb.navigation.path import survey_pattern
    from mapdb.navigation.rendered import FlightRender
    from mapdb.simulation.outlines import read_scene

    source = hashlib.sha256(b"".join((ROOT / p).read_bytes() for p in SIMULATOR)).hexdigest()[:12]
    path = cache / f"flight-{name}-{case}-{altitude:g}-{length:g}-{source}.jsonl.gz"
    if path.exists():
        with gzip.open(path, "rt") as f:
            return [json.loads(line) for line in f]
    params = dict(CASES[case])
    full, thin = _maps(name, cache)
    with open_map(full) as m:
        waypoints = survey_pattern(m.all(), length)  # the same path over the full and the thinned map
        if params.get("ideal"):
            frames = simulate_flight(m, FlightOptions(length_m=length, **IDEAL), waypoints)
            with gzip.open(path, "wt") as f:
                f.writelines(json.dumps(frame) + "\n" for frame in frames)
            return frames
    with open_map(thin if params.pop("thin", None) else full) as m:
        scene = read_scene(DATA / EXTRACTS[name], m.all())
        render = FlightRender(scene, EXTRACTS[name], **params)
        frames = simulate_flight(m, FlightOptions(length_m=length, altitude_m=altitude, **FLIGHT), waypoints,
                                 render=render)
    with gzip.open(path, "wt") as f:
        f.writelines(json.dumps(frame) + "\n" for frame in frames)
    return frames


def _navigate(navigators: list[Any], frames: list[dict[str, Any]]) -> list[list[Any]]:
    """Each navigator over the frames, frame by frame, alternating which goes first."""
    records: list[list[Any]] = [[] for _ in navigators]
    for i, frame in enumerate(frames):
        order = range(len(navigators)) if i % 2 == 0 else reversed(range(len(navigators)))
        for k in order:
            records[k].append(navigators[k].step(frame, f"frame {i}"))
    return records


def _bias(records: list[Any], frames: list[dict[str, Any]], first: int | None) -> tuple[float, ...]:
    """Mean frame-to-frame velocity error along and across the true track (m/s) from the first fix on (before
    it the heading and scale carry the magnetometer's and the barometer's biases), and their standard errors."""
    errors = []
    for r, f in list(zip(records, frames, strict=True))[first or 0:]:
        measured = r.velocity_measurement.get("velocity_mps")
        truth = complex(*f["truth"]["velocity_mps"])
        if measured is not None and abs(truth) > 0:
            errors.append((complex(*measured) - truth) * (truth / abs(truth)).conjugate())
    if len(errors) < 2:
        return (math.nan,) * 4
    e = np.array(errors)
    root = math.sqrt(e.size)
    return (float(e.real.mean()), float(e.imag.mean()), float(e.real.std(ddof=1)) / root,
            float(e.imag.std(ddof=1)) / root)


def _consistency(records: list[Any], frames: list[dict[str, Any]]) -> tuple[float, float]:
    """Share of the placed frames beyond the stated 3 sigma, and the mean NEES."""
    nees = []
    for r, f in zip(records, frames, strict=True):
        if r.x is None or r.cov is None:
            continue
        e = np.array([r.x - f["truth"]["x"], r.y - f["truth"]["y"]])
        cov = np.asarray(r.cov, float) + 1e-9 * np.eye(2)
        nees.append(min(float(e @ np.linalg.solve(cov, e)), NEES_CLIP))
    if not nees:
        return math.nan, math.nan
    values = np.array(nees)
    return float(np.mean(values > 9.0)), float(np.mean(values))


def _row(records: list[Any], frames: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures of one navigated flight (module docs)."""
    t = np.array([f["time_s"] for f in frames])
    error = np.array([r.truth["error_m"] if r.truth and r.truth["error_m"] is not None else np.inf for r in records])
    fixed = np.array([r.status == "fix" for r in records])
    first = int(np.argmax(fixed)) if fixed.any() else None
    six = next((i for i, f in enumerate(frames) if len(f["objects"]) >= 6), None)
    after = error[first:] if first is not None else np.array([np.inf])
    wrong = sum(1 for r, f in zip(records, frames, strict=True)
                if r.fix.get("status") in ("used", "initialised") and r.fix.get("x") is not None
                and math.hypot(r.fix["x"] - f["truth"]["x"], r.fix["y"] - f["truth"]["y"]) > WRONG_M)
    beyond, nees = _consistency(records, frames)
    total = np.array([r.time_ms.get("total", math.nan) for r in records])
    blobs = np.array([len(f["objects"]) for f in frames])
    whole = np.array([sum(1 for o in f["objects"] if not o.get("border")) for f in frames])
    return {"frames": len(frames), "six": float(np.mean(blobs >= 6)), "six_whole": float(np.mean(whole >= 6)),
            "fix": float(fixed.mean()), "within2": float(np.mean(after <= 2.0)),
            "within5": float(np.mean(after <= 5.0)), "max": float(np.max(after)),
            "ttff": None if first is None else float(t[first] - t[0]),
            "after6": None if first is None or six is None else float(t[first] - t[six]),
            "bias": _bias(records, frames, first), "wrong": wrong, "beyond": beyond, "nees": nees,
            "median_ms": float(np.nanmedian(total)), "p95_ms": float(np.nanpercentile(total, 95)),
            "stitched": sum(1 for r in records if len(getattr(r, "fix_frames", None) or ()) > 1)}


def _fmt(value: float | None, spec: str) -> str:
    return "never" if value is None else format(value, spec)


def _print_row(label: str, r: dict[str, Any]) -> None:
    print(f"| {label} | {r['frames']} | {r['six']:.0%} / {r['six_whole']:.0%} | {r['fix']:.1%} "
          f"| {r['within2']:.1%} | {r['within5']:.1%} | {r['max']:.1f} "
          f"| {_fmt(r['ttff'], '.1f')} | {_fmt(r['after6'], '.1f')} | "
          f"{r['bias'][0]:+.2f}±{r['bias'][2]:.2f} / {r['bias'][1]:+.2f}±{r['bias'][3]:.2f} "
          f"| {r['wrong']} | {r['beyond']:.1%} | {r['nees']:.1f} | {r['median_ms']:.0f} / {r['p95_ms']:.0f} "
          f"| {r['stitched']} |",
          flush=True)


def _navigators(maps: list[Any], versions: list[tuple[Any, ...]], frames: list[dict[str, Any]],
                start: str) -> list[Any]:
    """One navigator a version (its navigator module and its options' changes, None for the defaults)."""
    truth = frames[0]["truth"]
    initial = (truth["x"], truth["y"], START_RADIUS_M) if start == "initial" else None
    return [mod.Navigator(m, options=None if changes is None else mod.NavigatorOptions(**changes), initial=initial)
            for m, (_, mod, _, changes) in zip(maps, versions, strict=True)]


def _changes(variant: str) -> dict[str, Any]:
    """``field=value,...`` as NavigatorOptions changes (values typed as the fields' defaults)."""
    from mapdb.navigation.navigator import NavigatorOptions

    defaults = NavigatorOptions()
    changes: dict[str, Any] = {}
    for item in variant.split(","):
        name, _, value = item.partition("=")
        kind = type(getattr(defaults, name))
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return changes


def main() -> None:
    """Parse the options, render (or read) the flights, navigate them, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--maps", default="andorra,monaco", help="extracts, comma separated (%(default)s)")
    parser.add_argument("--cases", default="heights,thin15,flat,erode2,dilate2,blobs10",
                        help=f"of {', '.join(CASES)} (%(default)s)")
    parser.add_argument("--altitudes", default="120,200", help="metres, comma separated (%(default)s)")
    parser.add_argument("--starts", default="lis,initial", help="lis, initial (%(default)s)")
    parser.add_argument("--length", type=float, default=3000.0, help="metres flown (%(default)s)")
    parser.add_argument("--baseline", default=None, metavar="REV", help="also navigate with this git revision")
    parser.add_argument("--stitch", default=None, metavar="K,...",
                        help="navigate with each of these numbers of stitched frames (default: the navigator's)")
    parser.add_argument("--variants", default=None, metavar="FIELD=VALUE;...",
                        help="navigate with each of these NavigatorOptions changes (';' between variants, "
                             "',' within one)")
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "mapdb-bench-nav-masks")
    args = parser.parse_args()
    names = args.maps.split(",")
    missing = [EXTRACTS[n] for n in names if not (DATA / EXTRACTS[n]).exists()]
    if missing:
        sys.exit(f"navigation_masks: {DATA} lacks {', '.join(missing)} (the shared data)")
    from mapdb.mapfile import reader
    from mapdb.navigation import navigator

    versions: list[tuple[Any, ...]] = [(reader, navigator, "now", None)]
    if args.stitch:
        versions = [(reader, navigator, f"K={k}", {"stitch_frames": int(k)}) for k in args.stitch.split(",")]
    if args.variants:
        versions = [(reader, navigator, v, _changes(v)) for v in args.variants.split(";")]
    if args.baseline:
        work = args.cache / "baseline"
        versions.append((import_baseline(args.baseline, work, "mapfile.reader"),
                         import_baseline(args.baseline, work, "navigation.navigator"), args.baseline, None))
    print("| flight | frames | >=6 blobs / whole | fix | <=2 m | <=5 m | max m | ttff s | after 6 s "
          "| bias along/across m/s | wrong | >3 sigma | NEES | ms median / p95 | stitched |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        for case in args.cases.split(","):
            for altitude in (float(a) for a in args.altitudes.split(",")):
                t0 = time.perf_counter()
                frames = _flight(name, case, altitude, args.length, args.cache)
                print(f"{name} {case} {altitude:g} m: {len(frames)} frames in {time.perf_counter() - t0:.0f} s",
                      file=sys.stderr)
                full, thin = _maps(name, args.cache)
                path = thin if case == "thin15" else full
                for start in args.starts.split(","):
                    maps = [rd.open_map(path) for rd, _, _, _ in versions]
                    try:
                        navs = _navigators(maps, versions, frames, start)
                        for (_, _, label, _), records in zip(versions, _navigate(navs, frames), strict=True):
                            _print_row(f"{name} {case} {altitude:g} m {start} ({label})", _row(records, frames))
                    finally:
                        for m in maps:
                            m.close()


if __name__ == "__main__":
    main()
