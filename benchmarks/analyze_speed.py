"""``mapdb analyze`` of whole maps: today's fixed-16 run, the sequential rule and adaptive cells side by side;
and the projected core-hours of a country from the measured densities.

Builds and indexes the maps (../shared/data/osm: Andorra, sparse valleys and mountains; Monaco, dense
urban) in a work folder, then runs each mode as its own process as a user would (100 m cells, at most 16
images a cell, 150 m, 45 degrees, in one process so that CPU time is core time), the modes taking turns
(the order reversed every repeat) so that a neighbour's load falls on all alike::

    today:      mapdb analyze MAP -o OUT --no-sequential   # the baseline revision's code (--baseline REV)
    sequential: mapdb analyze MAP -o OUT                   # this tree's default: every cell simulated, sequential rule
    adaptive:   mapdb analyze MAP -o OUT --adaptive        # this tree: adaptive cells

    main:       mapdb analyze MAP -o OUT --no-adaptive     # the --main REV revision's default (with --main)

    python benchmarks/analyze_speed.py [--repeat 2] [--maps andorra,monaco] [--workdir DIR]
                                       [--country Germany:357588:45e6] [--baseline 402f56b] [--identity]
                                       [--main REV --modes today,main,sequential]

"Today's projection" is the projection of the baseline revision's fixed-16 run (every image of every cell
within reach), measured in the same run: the figure the issue's "a tenth of today's projection" is measured
against (293 core-hours for Germany in the README of 402f56b).  The baseline's code runs from a copy of
that revision (its ``mapdb`` and CLI first on ``PYTHONPATH``).

Per run: cells, cells simulated, skipped, inferred, images localizable and localized, CPU (user + system of
the process and its workers), core-ms a simulated cell.  Agreement with today's fixed-16 figures, separately
for the cells simulated and the cells inferred: whether the fixed run's success (and false share) lies inside
the reported 95 % interval.  With ``--identity``, the baseline's sequential run too (once), compared band by
band with this tree's ``--no-adaptive`` run: the same bytes in every cell (the per-image work changed, not the
answers).  With ``--main REV`` and the mode ``main`` among ``--modes``: the default run of another revision (the
branch this tree is to be merged into), taking turns with the others; the tree's modes are then also given as
ratios to it, its start-up measured as the others', and its bands compared with ``sequential``'s.

The projection: a country of AREA km² and OBJECTS map objects in 100 m cells, its cells a mixture of the
measured maps' cells (a share of Monaco-like cells, the rest Andorra-like, the share chosen so that the
objects per cell match the country's); each mode's core-seconds a grid cell (the median run's CPU over its
grid cells, everything included: start-up, empty cells, outputs) times the country's cells.  A second
projection takes out each version's start-up, which a country's run pays once, not per cell:

* a version whose ``mapdb analyze`` accounts its own CPU by phase (``summary.json``'s ``cpu``,
  :mod:`mapdb.analysis.cputime`: this tree's) is measured inside the same runs: the median over a mode's runs
  of its cells + outputs CPU but the picture's (left out with the start-up phase, imports, map and index
  opening, planning, the output writers' imports: the picture is a figure of a bounded size, 1.3 s over
  Monaco's 837 cells as over Andorra's 81,840, and the one-cell run subtracted below holds one picture too);
* a version that does not (today's 402f56b, and a ``--main`` older than the accounting) by subtraction: the
  whole run's median CPU less that version's start-up, the median CPU of ``--startup-repeat`` runs of the same
  command over one cell of the map (``--bbox``, the versions taking turns), which also holds one cell's outputs.
  On Monaco the run's cell work is about its start-up's size, so this figure's noise is the subtraction's.

The table says which each mode's figure is ("in-run" or "subtracted").  Not included: the growth of the
per-image cost with the map's size (a country's lost-in-space search is slower), nor that of the outputs a
country's run writes beyond the measured maps' per-cell share.
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
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import cli_tree, shared_data  # noqa: E402

DATA = shared_data("osm")
EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf",
            "liechtenstein": "liechtenstein-2013-08-03.osm.pbf"}
# mode -> (code: "base" the baseline revision's, "tree" this one's; options)
MODES = {"today": ("base", ["--no-sequential"]), "sequential": ("tree", ["--no-adaptive"]),
         "adaptive": ("tree", ["--adaptive"]), "base-sequential": ("base", []), "main": ("main", ["--no-adaptive"])}
BASELINE = "402f56b"


def mapdb(*args: object, env: dict[str, str] | None = None) -> None:
    exe = shutil.which("mapdb") or str(Path(sys.executable).with_name("mapdb"))
    subprocess.run([exe, *map(str, args)], check=True, env=env)


def baseline_env(rev: str, work: Path) -> dict[str, str]:
    """The environment in which the installed ``mapdb`` script runs revision ``rev``: a copy of its ``mapdb``
    and its CLI (as ``mapdb_cli``) first on ``PYTHONPATH`` (the editable install's finder comes after it)."""
    return {**os.environ, "PYTHONPATH": str(cli_tree(rev, work / f"baseline-{rev}"))}


def build(workdir: Path, name: str) -> Path:
    out = workdir / f"{name}.mapdb"
    if not out.exists():
        mapdb("build", "-q", DATA / EXTRACTS[name], "-o", out)
        mapdb("index", out)
    return out


def cpu_of(args: list[object], env: dict[str, str] | None) -> tuple[float, float]:
    """Run ``mapdb ARGS`` as its own process: its CPU (user + system, with its workers) and wall time."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    mapdb(*args, env=env)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), wall


def analyse(map_path: Path, out: Path, mode: str, envs: dict[str, dict[str, str] | None]) -> dict:
    """One run as its own process: wall time, CPU of it and its workers, the load when it started."""
    if out.exists():
        shutil.rmtree(out)
    code, options = MODES[mode]
    load = os.getloadavg()[0]
    cpu, wall = cpu_of(["analyze", map_path, "-o", out, "-q", *options], envs[code])
    summary = json.loads((out / "summary.json").read_text())
    return {"mode": mode, "wall_s": wall, "cpu_s": cpu, "load": load, "summary": summary, "out": out}


def startup(map_path: Path, work: Path, code: str, envs: dict[str, dict[str, str] | None]) -> float:
    """The CPU of ``mapdb analyze`` over one cell of the map (a 100 m box around the object nearest the objects'
    median): what a run costs whatever its size (imports, the map and its index opened, the outputs written)."""
    from pyproj import Transformer

    from mapdb.mapfile.reader import open_map

    with open_map(map_path) as m:
        objects = m.all()
        k = int(np.argmin(np.hypot(objects.x - np.median(objects.x), objects.y - np.median(objects.y))))
        x, y = float(objects.x[k]), float(objects.y[k])
        to_lonlat = Transformer.from_crs(m.crs, "EPSG:4326", always_xy=True)
    lon0, lat0 = to_lonlat.transform(x - 50, y - 50)
    lon1, lat1 = to_lonlat.transform(x + 50, y + 50)
    out = work / f"startup-{code}"
    if out.exists():
        shutil.rmtree(out)
    cpu, _ = cpu_of(["analyze", map_path, "-o", out, "-q", "--bbox", f"{lon0},{lat0},{lon1},{lat1}"], envs[code])
    shutil.rmtree(out)
    return cpu


def read_bands(out: Path) -> dict[str, np.ndarray]:
    import rasterio

    with rasterio.open(out / "analysis.tif") as src:
        return {name: src.read(k + 1).astype(np.float64) for k, name in enumerate(src.descriptions)}


def inside(f: dict[str, np.ndarray], s: dict[str, np.ndarray], cells: np.ndarray) -> tuple[float, float]:
    """Of ``cells``: the share whose fixed-run success lies inside the reported 95 % interval, and whose false
    share does (inside the interval rebuilt from the false share and the images run; for an inferred cell, the
    hull of its neighbours' false shares is not reported: its point figure must be the fixed run's)."""
    from mapdb.analysis.measures import wilson_interval

    ok = (s["success_low"] - 1e-6 <= f["success"]) & (f["success"] <= s["success_high"] + 1e-6)
    false_ok = 0
    for r, c in zip(*np.nonzero(cells), strict=True):
        ready, ran, n = int(s["localizable"][r, c]), int(s["simulated"][r, c]), int(s["images"][r, c])
        if ran == ready:  # every localizable image ran (or none: inferred): the fixed run's share exactly
            false_ok += int(abs(f["false_fixes"][r, c] - s["false_fixes"][r, c]) < 1e-6)
            continue
        low, high = wilson_interval(round(s["false_fixes"][r, c] * n * ran / ready), ran)
        false_ok += int(low * ready / n - 1e-6 <= f["false_fixes"][r, c] <= high * ready / n + 1e-6)
    n_cells = max(int(cells.sum()), 1)
    return int(ok[cells].sum()) / n_cells, false_ok / n_cells


def agreement(fixed: Path, sequential: Path) -> dict:
    """Whether the fixed run's cell figures lie within the sequential (or adaptive) run's reported intervals,
    for the cells it simulated and for those it inferred."""
    f, s = read_bands(fixed), read_bands(sequential)
    inferred = s.get("inferred", np.zeros_like(s["success"])) > 0
    ran = (s["images"] > 0) & ~inferred  # the cells simulated (skipped ones: success 0 in both, exactly)
    width = s["success_high"] - s["success_low"]
    bearing = f["objects_per_km2"] > 0
    out = {"ran": int(ran.sum()), "inferred": int(inferred.sum())}
    out["ran_inside"], out["ran_false_inside"] = inside(f, s, ran)
    out["inferred_inside"], out["inferred_false_inside"] = inside(f, s, inferred) if inferred.any() else (None, None)
    for key, cells in (("ran", ran), ("inferred", inferred)):
        out[f"{key}_width"] = float(np.median(width[cells])) if cells.any() else None
        out[f"{key}_diff"] = float(np.abs(f["success"] - s["success"])[cells].mean()) if cells.any() else None
    out["mean_success"] = (float(f["success"][bearing].mean()), float(s["success"][bearing].mean()))
    out["at_least_95"] = (int((f["success"] >= 0.95).sum()), int((s["success"] >= 0.95).sum()))
    out["false_cells"] = (int((f["false_fixes"] > 0).sum()), int((s["false_fixes"] > 0).sum()))
    return out


def identical(base: Path, tree: Path) -> tuple[int, list[str]]:
    """Cells and the bands (of those both write) that differ between two runs' GeoTIFFs."""
    a, b = read_bands(base), read_bands(tree)
    differ = [k for k in a if k in b and not np.array_equal(a[k], b[k])]
    return int(a["success"].size), differ


def run_table(name: str, runs: list[dict]) -> None:
    print(f"\n{name}: mapdb analyze, 100 m cells, at most 16 images a cell, 150 m, 45 deg, pixel 1 px, "
          "attitude 0.05 deg, one process")
    print("| run | mode | wall (s) | CPU (s) | load | cells | simulated | skipped | inferred | images localizable | "
          "images localized | core-ms a simulated cell |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for k, r in enumerate(runs, start=1):
        run = r["summary"]["run"]
        per_cell = 1000 * r["cpu_s"] / max(run["cells_simulated"], 1)
        print(f"| {k} | {r['mode']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['load']:.1f} | {run['cells']:,} | "
              f"{run['cells_simulated']:,} | {run['cells_skipped']:,} | {run.get('cells_inferred', 0):,} | "
              f"{run['images_localizable']:,} | {run['images_localized']:,} | {per_cell:,.0f} |")


def medians(runs: list[dict]) -> dict[str, dict]:
    out = {}
    for mode in dict.fromkeys(r["mode"] for r in runs):
        mine = [r for r in runs if r["mode"] == mode]
        run = mine[0]["summary"]["run"]  # the measures are the same bytes in every run of a mode
        out[mode] = {"cpu_s": statistics.median(r["cpu_s"] for r in mine), "cells": run["cells"],
                     "simulated": run["cells_simulated"], "drawn": run["images_localizable"],
                     "localized": run["images_localized"], "objects": mine[0]["summary"]["area"]["objects"],
                     "out": mine[0]["out"], **in_run(mine)}
    return out


def in_run(runs: list[dict]) -> dict[str, float | None]:
    """The runs' own CPU accounting (``summary.json``'s ``cpu``), medians over the runs: what a run pays once
    (start-up and the picture, a bounded figure), and what grows with the area (the cells, the other outputs);
    None for a version that does not account it."""
    cpus = [r["summary"].get("cpu") for r in runs]
    if not all(cpus) or not all("picture_s" in c for c in cpus):
        return {"startup_in_s": None, "net_s": None}
    return {"startup_in_s": statistics.median(c["startup_s"] + c["picture_s"] for c in cpus),
            "net_s": statistics.median(c["cells_s"] + c["outputs_s"] - c["picture_s"] for c in cpus)}


def side_by_side(name: str, med: dict[str, dict], startups: dict[str, float | None]) -> None:
    today = med["today"]
    modes = [m for m in ("today", "base-sequential", "main", "sequential", "adaptive") if m in med]
    print(f"\n{name}, medians | " + " | ".join(modes) + " |\n|---|" + "---|" * len(modes))
    for mode in modes:
        med[mode]["ms_cell"] = 1000 * med[mode]["cpu_s"] / max(med[mode]["simulated"], 1)
    for key, label in (("drawn", "images localizable"), ("localized", "images localized (run)"),
                       ("simulated", "cells simulated"), ("cpu_s", "CPU (s)"), ("ms_cell", "core-ms a simulated cell")):
        print(f"| {label} | " + " | ".join(f"{med[m][key]:,.1f} ({med[m][key] / today[key]:.2f}x)" for m in modes)
              + " |")
    print("| start-up CPU (s) | " + " | ".join(
        f"{med[m]['startup_in_s']:.1f} (in-run, with the picture)" if med[m]["net_s"] is not None
        else f"{startups[MODES[m][0]]:.1f} (one-cell run)" for m in modes) + " |")
    if "main" in med:
        for mode in (m for m in ("sequential", "adaptive") if m in med):
            print(f"\n{mode} against main: CPU {med[mode]['cpu_s'] / med['main']['cpu_s']:.3f}x, core-ms a simulated "
                  f"cell {med[mode]['ms_cell'] / med['main']['ms_cell']:.3f}x, images localized "
                  f"{med[mode]['localized'] / med['main']['localized']:.3f}x")
    for mode in modes[1:]:
        a = agreement(today["out"], med[mode]["out"])
        inferred = "" if not a["inferred"] else (
            f"; the {a['inferred']:,} cells inferred: {a['inferred_inside']:.1%} (false share "
            f"{a['inferred_false_inside']:.1%}), median width {a['inferred_width']:.3f}, mean |difference| of "
            f"success {a['inferred_diff']:.3f}")
        print(f"\n{mode} against today's fixed-16: fixed success inside the reported 95 % interval in the "
              f"{a['ran']:,} cells simulated: {a['ran_inside']:.1%} (false share {a['ran_false_inside']:.1%}), "
              f"median width {a['ran_width']:.3f}, mean |difference| {a['ran_diff']:.3f}{inferred}; mean success of "
              f"objects-bearing cells {a['mean_success'][0]:.3f} fixed, {a['mean_success'][1]:.3f} {mode}; cells "
              f">= 95 %: {a['at_least_95'][0]} fixed, {a['at_least_95'][1]} {mode}; cells with a false fix: "
              f"{a['false_cells'][0]} fixed, {a['false_cells'][1]} {mode}")


def projection(country: str, maps: dict[str, dict[str, dict]], startups: dict[str, dict[str, float | None]]) -> None:
    """Core-hours of a country whose cells mix the measured maps' cells to its objects per cell."""
    name, area, objects = country.split(":")
    cells = float(area) / 0.01
    density = float(objects) / cells
    dense, sparse = maps.get("monaco"), maps.get("andorra")
    if dense is None or sparse is None:
        print("\n(projection needs the andorra and monaco maps)")
        return
    d_dense = dense["today"]["objects"] / dense["today"]["cells"]
    d_sparse = sparse["today"]["objects"] / sparse["today"]["cells"]
    share = min(1.0, max(0.0, (density - d_sparse) / (d_dense - d_sparse)))
    print(f"\n{name}: {float(area):,.0f} km², {float(objects) / 1e6:,.1f} M objects, {cells / 1e6:,.1f} M cells of "
          f"100 m ({density:.3f} objects a cell): {share:.1%} Monaco-like cells ({d_dense:.3f} objects a cell), "
          f"{1 - share:.1%} Andorra-like ({d_sparse:.4f})")
    print("| mode | core-ms a grid cell, Monaco | Andorra | country core-hours | / today's | without start-up: "
          "Monaco | Andorra | core-hours | / today's | start-up taken out |\n|---|---|---|---|---|---|---|---|---|---|")
    hours: dict[str, tuple[float, float]] = {}
    for mode in dense:
        per = [m[mode]["cpu_s"] / m[mode]["cells"] for m in (dense, sparse)]
        net = [without_startup(m[mode], startups[k][MODES[mode][0]]) / m[mode]["cells"]
               for m, k in ((dense, "monaco"), (sparse, "andorra"))]
        how = "in-run" if dense[mode]["net_s"] is not None and sparse[mode]["net_s"] is not None else "subtracted"
        hours[mode] = tuple(cells * (share * p[0] + (1 - share) * p[1]) / 3600 for p in (per, net))  # type: ignore
        print(f"| {mode} | {1000 * per[0]:,.2f} | {1000 * per[1]:,.3f} | {hours[mode][0]:,.0f} | "
              f"{hours[mode][0] / hours['today'][0]:.3f} | {1000 * net[0]:,.2f} | {1000 * net[1]:,.3f} | "
              f"{hours[mode][1]:,.0f} | {hours[mode][1] / hours['today'][1]:.3f} | {how} |")
    if "main" in hours:
        for mode in (m for m in hours if MODES[m][0] == "tree"):
            print(f"\n{mode} against main: {hours[mode][0] / hours['main'][0]:.3f}x the core-hours, "
                  f"{hours[mode][1] / hours['main'][1]:.3f}x without start-up")


def without_startup(med: dict, startup_cpu: float | None) -> float:
    """A mode's median CPU without its start-up: its runs' own cells + outputs CPU where they account it (the
    same runs), else the whole run's less a one-cell run's (another process: the subtraction's noise)."""
    if med["net_s"] is not None:
        return float(med["net_s"])
    assert startup_cpu is not None, "a version without in-run accounting needs its one-cell start-up runs"
    return max(med["cpu_s"] - startup_cpu, 0.0)


def measure_map(name: str, args: argparse.Namespace, workdir: Path,
                envs: dict[str, dict[str, str] | None]) -> tuple[dict[str, dict], dict[str, float | None]]:
    """Every mode's runs of one map, taking turns; the medians, and each version's start-up CPU."""
    map_path = build(workdir, name)
    modes = args.modes.split(",")
    order = [m for k in range(args.repeat) for m in (modes if k % 2 == 0 else modes[::-1])]
    if args.identity:
        order.append("base-sequential")
    runs = [analyse(map_path, workdir / f"{name}-{mode}-{k}", mode, envs) for k, mode in enumerate(order)]
    # One-cell start-up runs only for the versions whose runs do not account their own CPU by phase.
    codes = list(dict.fromkeys(MODES[r["mode"]][0] for r in runs if "cpu" not in r["summary"]))
    samples: dict[str, list[float]] = {code: [] for code in codes}
    for k in range(args.startup_repeat):  # the versions taking turns, as the runs do: one cell's CPU is small
        for code in codes if k % 2 == 0 else codes[::-1]:
            samples[code].append(startup(map_path, workdir, code, envs))
    startups: dict[str, float | None] = {code: None for code, _ in MODES.values()}
    startups.update({code: statistics.median(samples[code]) for code in codes})
    run_table(name, runs)
    med = medians(runs)
    side_by_side(name, med, startups)
    if args.identity:
        n, differ = identical(med["base-sequential"]["out"], med["sequential"]["out"])
        print(f"\n{name}: baseline {args.baseline}'s sequential run against this tree's --no-adaptive run, "
              f"{n:,} cells: bands that differ: {', '.join(differ) if differ else 'none'}")
    if "main" in med and "sequential" in med:
        n, differ = identical(med["main"]["out"], med["sequential"]["out"])
        print(f"\n{name}: main {args.main}'s default run against this tree's --no-adaptive run, {n:,} cells: bands "
              f"that differ: {', '.join(differ) if differ else 'none'}")
    return med, startups


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default="andorra,monaco", help="shared extracts to analyse, comma-separated")
    parser.add_argument("--repeat", type=int, default=2, help="runs of each mode and map")
    parser.add_argument("--startup-repeat", type=int, default=5,
                        help="one-cell runs of each version for its start-up (the median taken; taking turns)")
    parser.add_argument("--modes", default="today,sequential,adaptive", help="modes to run (today first)")
    parser.add_argument("--baseline", default=BASELINE, help="the revision whose fixed-16 run is today's")
    parser.add_argument("--identity", action="store_true",
                        help="also run the baseline's sequential rule once and compare it with --no-adaptive")
    parser.add_argument("--workdir", type=Path, default=None, help="keep the maps and outputs here")
    parser.add_argument("--main", default=None, metavar="REV",
                        help="the revision whose default run is mode 'main' (e.g. the branch this tree merges into)")
    parser.add_argument("--country", default="Germany:357588:45e6", help="NAME:AREA_KM2:OBJECTS to project")
    args = parser.parse_args()
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to measure", file=sys.stderr)
        return 1
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="analyze-speed-"))
    workdir.mkdir(parents=True, exist_ok=True)
    envs = {"base": baseline_env(args.baseline, workdir), "tree": None}
    if args.main:
        envs["main"] = {**os.environ, "PYTHONPATH": str(cli_tree(args.main, workdir / f"main-{args.main}"))}
    elif "main" in args.modes.split(","):
        parser.error("mode 'main' needs --main REV")
    print(f"today: {args.baseline}'s fixed-16 run{f'; main: {args.main}' if args.main else ''}; load average at the "
          f"start {os.getloadavg()[0]:.1f}")
    measured, startups = {}, {}
    for name in args.maps.split(","):
        measured[name], startups[name] = measure_map(name, args, workdir, envs)
    projection(args.country, measured, startups)
    return 0


if __name__ == "__main__":
    sys.exit(main())
