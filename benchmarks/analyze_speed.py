"""``mapdb analyze`` of whole maps, fixed-16 against the sequential rule, side by side; and the projected
core-hours of a country from the measured densities.

Builds and indexes the maps (../shared/data/osm: Andorra, sparse valleys and mountains; Monaco, dense
urban) in a work folder, then runs each mode as its own process as a user would (100 m cells, at most 16
images a cell, 150 m, 45 degrees, in one process so that CPU time is core time), alternating the modes
(fixed, sequential, sequential, fixed, ...) so that a neighbour's load falls on both alike::

    mapdb analyze MAP -o OUT --no-sequential        # fixed: 16 images in every cell within reach
    mapdb analyze MAP -o OUT                        # sequential (the default)

    python benchmarks/analyze_speed.py [--repeat 2] [--maps andorra,monaco] [--workdir DIR]
                                       [--country Germany:357588:45e6] [--jobs N]

Per run: cells, cells simulated, skipped, images drawn and localized, CPU (user + system of the process and
its workers), core-ms a simulated cell.  Agreement: for every cell simulated in both modes, whether the
fixed run's success (and false-fix) share lies inside the sequential run's 95 % Wilson interval (the width
the outputs report, rebuilt from its ``images`` and share), and how far the other figures moved.

The projection: a country of AREA km² and OBJECTS map objects in 100 m cells, its cells a mixture of the
measured maps' cells (a share of Monaco-like cells, the rest Andorra-like, the share chosen so that the
objects per cell match the country's); each mode's core-seconds a grid cell (the median run's CPU over its
grid cells, everything included: set-up, empty cells, outputs) times the country's cells.  Not included:
the growth of the per-image cost with the map's size (a country's lost-in-space search is slower).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "osm"
if not DATA.is_dir():
    DATA = Path("/work/shared/data/osm")
EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf",
            "liechtenstein": "liechtenstein-2013-08-03.osm.pbf"}
MODES = {"fixed": ["--no-sequential"], "sequential": []}


def mapdb(*args: object) -> None:
    exe = shutil.which("mapdb") or str(Path(sys.executable).with_name("mapdb"))
    subprocess.run([exe, *map(str, args)], check=True)


def build(workdir: Path, name: str) -> Path:
    out = workdir / f"{name}.mapdb"
    if not out.exists():
        mapdb("build", "-q", DATA / EXTRACTS[name], "-o", out)
        mapdb("index", out)
    return out


def analyse(map_path: Path, out: Path, mode: str, jobs: int | None) -> dict:
    """One run as its own process: wall time, CPU of it and its workers, the load when it started."""
    if out.exists():
        shutil.rmtree(out)
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    mapdb("analyze", map_path, "-o", out, "-q", *MODES[mode], *(["--jobs", jobs] if jobs else []))
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    summary = json.loads((out / "summary.json").read_text())
    return {"mode": mode, "wall_s": wall, "cpu_s": cpu, "load": load, "summary": summary, "out": out}


def read_bands(out: Path) -> dict[str, np.ndarray]:
    import rasterio

    with rasterio.open(out / "analysis.tif") as src:
        return {name: src.read(k + 1).astype(np.float64) for k, name in enumerate(src.descriptions)}


def agreement(fixed: Path, sequential: Path) -> dict:
    """Whether the fixed run's cell figures lie within the sequential run's reported 95 % intervals."""
    from mapdb.analysis.measures import wilson_interval

    f, s = read_bands(fixed), read_bands(sequential)
    both = s["images"] > 0  # the cells the sequential run sampled (the others: success 0 in both, exactly)
    ok = (s["success_low"] - 1e-6 <= f["success"]) & (f["success"] <= s["success_high"] + 1e-6)
    false_ok = 0
    for r, c in zip(*np.nonzero(both), strict=True):
        ready, ran, n = int(s["localizable"][r, c]), int(s["simulated"][r, c]), int(s["images"][r, c])
        if ran == ready:  # every localizable image ran: the fixed run's share exactly
            false_ok += int(f["false_fixes"][r, c] == s["false_fixes"][r, c])
            continue
        low, high = wilson_interval(round(s["false_fixes"][r, c] * n * ran / ready), ran)
        false_ok += int(low * ready / n - 1e-6 <= f["false_fixes"][r, c] <= high * ready / n + 1e-6)
    cells = int(both.sum())

    def moved(band: str) -> float:
        known = both & (f[band] != -9999.0) & (s[band] != -9999.0)
        return float(np.median(np.abs(f[band][known] - s[band][known]))) if known.any() else float("nan")

    bearing = f["objects_per_km2"] > 0
    all_ran = both & (s["simulated"] == s["localizable"])
    width = (s["success_high"] - s["success_low"])[both]
    return {"cells": cells, "success_inside": int(ok[both].sum()) / max(cells, 1),
            "false_inside": false_ok / max(cells, 1), "median_width": float(np.median(width)) if cells else 0.0,
            "max_width": float(width.max()) if cells else 0.0,
            "mean_success": (float(f["success"][bearing].mean()), float(s["success"][bearing].mean())),
            "mean_abs_diff": float(np.abs(f["success"] - s["success"])[both].mean()) if cells else 0.0,
            "at_least_95": (int((f["success"] >= 0.95).sum()), int((s["success"] >= 0.95).sum()),
                            int((s["success_low"] >= 0.95).sum()), int((s["success_high"] >= 0.95).sum())),
            "false_cells": (int((f["false_fixes"] > 0).sum()), int((s["false_fixes"] > 0).sum())),
            "error_moved_m": moved("error_m"), "ambiguity_moved": moved("ambiguity"),
            "all_ran": int(all_ran.sum()),
            "same_where_all_ran": bool(np.array_equal(f["success"][all_ran], s["success"][all_ran]))}


def run_table(name: str, runs: list[dict]) -> None:
    print(f"\n{name}: mapdb analyze, 100 m cells, at most 16 images a cell, 150 m, 45 deg, pixel 1 px, "
          "attitude 0.05 deg, one process")
    print("| run | mode | wall (s) | CPU (s) | load | cells | simulated | skipped | images localizable | "
          "images localized | core-ms a simulated cell |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k, r in enumerate(runs, start=1):
        run = r["summary"]["run"]
        per_cell = 1000 * r["cpu_s"] / max(run["cells_simulated"], 1)
        print(f"| {k} | {r['mode']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['load']:.1f} | {run['cells']:,} | "
              f"{run['cells_simulated']:,} | {run['cells_skipped']:,} | {run['images_localizable']:,} | "
              f"{run['images_localized']:,} | {per_cell:,.0f} |")


def medians(runs: list[dict]) -> dict[str, dict]:
    out = {}
    for mode in MODES:
        mine = [r for r in runs if r["mode"] == mode]
        run = mine[0]["summary"]["run"]  # the measures are the same bytes in every run of a mode
        out[mode] = {"cpu_s": statistics.median(r["cpu_s"] for r in mine), "cells": run["cells"],
                     "simulated": run["cells_simulated"], "drawn": run["images_localizable"],
                     "localized": run["images_localized"], "objects": mine[0]["summary"]["area"]["objects"],
                     "out": mine[0]["out"]}
    return out


def side_by_side(name: str, med: dict[str, dict]) -> None:
    f, s = med["fixed"], med["sequential"]
    print(f"\n{name}, medians | fixed | sequential | sequential / fixed |\n|---|---|---|---|")
    for key, label in (("drawn", "images localizable"), ("localized", "images localized (run)"), ("cpu_s", "CPU (s)")):
        print(f"| {label} | {f[key]:,.1f} | {s[key]:,.1f} | {s[key] / f[key]:.2f} |")
    for mode in (f, s):
        mode["ms_cell"] = 1000 * mode["cpu_s"] / max(mode["simulated"], 1)
    print(f"| core-ms a simulated cell | {f['ms_cell']:,.0f} | {s['ms_cell']:,.0f} | "
          f"{s['ms_cell'] / f['ms_cell']:.2f} |")
    a = agreement(f["out"], s["out"])
    print(f"\nAgreement over the {a['cells']:,} cells simulated: fixed success inside the sequential 95 % "
          f"interval (median width {a['median_width']:.3f}, widest {a['max_width']:.3f}) in "
          f"{a['success_inside']:.1%}, false share in {a['false_inside']:.1%}; mean |difference| of success "
          f"{a['mean_abs_diff']:.3f}; mean success of "
          f"objects-bearing cells {a['mean_success'][0]:.3f} fixed, {a['mean_success'][1]:.3f} sequential; cells "
          f"with success >= 95 %: {a['at_least_95'][0]} fixed, {a['at_least_95'][1]} sequential (its interval: "
          f"{a['at_least_95'][2]} to {a['at_least_95'][3]}); cells with a "
          f"false fix: {a['false_cells'][0]} fixed, {a['false_cells'][1]} sequential; median change of error_m "
          f"{a['error_moved_m']:.2f} m, of ambiguity {a['ambiguity_moved']:.3f}; the {a['all_ran']:,} cells that "
          f"ran every localizable image: the same success {'yes' if a['same_where_all_ran'] else 'NO'}")


def projection(country: str, maps: dict[str, dict[str, dict]]) -> None:
    """Core-hours of a country whose cells mix the measured maps' cells to its objects per cell."""
    name, area, objects = country.split(":")
    cells = float(area) / 0.01
    density = float(objects) / cells
    dense, sparse = maps.get("monaco"), maps.get("andorra")
    if dense is None or sparse is None:
        print("\n(projection needs the andorra and monaco maps)")
        return
    d_dense = dense["fixed"]["objects"] / dense["fixed"]["cells"]
    d_sparse = sparse["fixed"]["objects"] / sparse["fixed"]["cells"]
    share = min(1.0, max(0.0, (density - d_sparse) / (d_dense - d_sparse)))
    print(f"\n{name}: {float(area):,.0f} km², {float(objects) / 1e6:,.1f} M objects, {cells / 1e6:,.1f} M cells of "
          f"100 m ({density:.3f} objects a cell): {share:.1%} Monaco-like cells ({d_dense:.3f} objects a cell), "
          f"{1 - share:.1%} Andorra-like ({d_sparse:.4f})")
    print("| mode | core-ms a grid cell, Monaco | Andorra | country core-hours |\n|---|---|---|---|")
    hours = {}
    for mode in MODES:
        per_dense = dense[mode]["cpu_s"] / dense[mode]["cells"]
        per_sparse = sparse[mode]["cpu_s"] / sparse[mode]["cells"]
        hours[mode] = cells * (share * per_dense + (1 - share) * per_sparse) / 3600
        print(f"| {mode} | {1000 * per_dense:,.2f} | {1000 * per_sparse:,.3f} | {hours[mode]:,.0f} |")
    print(f"| sequential / fixed | | | {hours['sequential'] / hours['fixed']:.2f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default="andorra,monaco", help="shared extracts to analyse, comma-separated")
    parser.add_argument("--repeat", type=int, default=2, help="runs of each mode and map")
    parser.add_argument("--jobs", type=int, default=None, help="local Dask workers (default: one process)")
    parser.add_argument("--workdir", type=Path, default=None, help="keep the maps and outputs here")
    parser.add_argument("--country", default="Germany:357588:45e6", help="NAME:AREA_KM2:OBJECTS to project")
    args = parser.parse_args()
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to measure", file=sys.stderr)
        return 1
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="analyze-speed-"))
    workdir.mkdir(parents=True, exist_ok=True)
    measured = {}
    for name in args.maps.split(","):
        map_path = build(workdir, name)
        order = [m for k in range(args.repeat) for m in (("fixed", "sequential") if k % 2 == 0
                                                          else ("sequential", "fixed"))]
        runs = [analyse(map_path, workdir / f"{name}-{mode}-{k}", mode, args.jobs) for k, mode in enumerate(order)]
        run_table(name, runs)
        measured[name] = medians(runs)
        side_by_side(name, measured[name])
    projection(args.country, measured)
    return 0


if __name__ == "__main__":
    sys.exit(main())
