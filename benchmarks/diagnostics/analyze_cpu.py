"""Whole-run CPU of ``mapdb analyze`` (its default: the sequential rule) on the shared extracts, a baseline revision
against this tree, the two taking turns (the order reversed every round), and whether their outputs are the same.

Reproduces the README's "analyze: whole-run CPU, this tree against main" figures (per-cell and per-image cost
outside the quad lookup)::

    python benchmarks/diagnostics/analyze_cpu.py --maps monaco,andorra --rounds 4 --baseline main

Each run is its own process (``SOURCE_DATE_EPOCH=1700000000``), its CPU the user + system time of the process;
the baseline runs from a copy of its ``mapdb`` and CLI first on ``PYTHONPATH`` (``_baseline.cli_tree``).  The table
gives each version's median, its runs and the ratio; the last column says whether the two wrote the same
``analysis.tif`` bytes, the same rows in every table of ``cells.gpkg`` and the same ``summary.json`` apart from its
timings (``seconds``, ``estimate_s``, the CPU by phase ``cpu``).  Beside the whole run, the cells phase
(``summary.json``'s ``cpu.cells_s``: the simulated cells' images drawn, localized and recorded, what the country
projection counts), whose change a whole run's start-up and picture (3-5 s on Monaco) can hide; "-" for a version
that does not account its phases.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import resource
import shutil
import sqlite3
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cli_tree, shared_data  # noqa: E402

EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf",
            "liechtenstein": "liechtenstein-2013-08-03.osm.pbf"}


def mapdb(*args: object, env: dict[str, str] | None = None) -> None:
    exe = shutil.which("mapdb") or str(Path(sys.executable).with_name("mapdb"))
    subprocess.run([exe, *map(str, args)], check=True, env=env)


def cpu_of(args: list[object], env: dict[str, str]) -> float:
    """User + system seconds of ``mapdb ARGS`` run as its own process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    mapdb(*args, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _tables(path: Path) -> dict[str, list[tuple[Any, ...]]]:
    with sqlite3.connect(path) as db:
        names = [row[0] for row in db.execute("select table_name from gpkg_contents")]
        return {name: db.execute(f'select * from "{name}" order by 1').fetchall() for name in names}


def _untimed(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if k not in ("seconds", "estimate_s", "cpu")}
    return [_untimed(v) for v in value] if isinstance(value, list) else value


def same_outputs(a: Path, b: Path) -> bool:
    """The same GeoTIFF bytes, cells and summary (timings apart)."""
    return (filecmp.cmp(a / "analysis.tif", b / "analysis.tif", shallow=False)
            and _tables(a / "cells.gpkg") == _tables(b / "cells.gpkg")
            and _untimed(json.loads((a / "summary.json").read_text()))
            == _untimed(json.loads((b / "summary.json").read_text())))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default="monaco,andorra")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--baseline", default="main")
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    data = shared_data("osm")
    if not data.is_dir():
        print(f"no shared data at {data}: nothing to measure", file=sys.stderr)
        return 1
    work = args.workdir or Path(tempfile.mkdtemp(prefix="analyze-cpu-"))
    work.mkdir(parents=True, exist_ok=True)
    stamp = {"SOURCE_DATE_EPOCH": "1700000000"}
    envs = {args.baseline: {**os.environ, **stamp, "PYTHONPATH": str(cli_tree(args.baseline, work / "baseline"))},
            "tree": {**os.environ, **stamp}}
    maps = {}
    for name in args.maps.split(","):
        maps[name] = work / f"{name}.mapdb"
        if not maps[name].exists():
            mapdb("build", "-q", data / EXTRACTS[name], "-o", maps[name])
            mapdb("index", maps[name])
    cpu: dict[tuple[str, str], list[float]] = {(m, v): [] for m in maps for v in envs}
    cells: dict[tuple[str, str], list[float]] = {(m, v): [] for m in maps for v in envs}
    start_load = os.getloadavg()[0]
    for k in range(args.rounds):
        for name, path in maps.items():
            for version in (list(envs) if k % 2 == 0 else list(envs)[::-1]):
                out = work / f"{name}-{version}"
                shutil.rmtree(out, ignore_errors=True)
                cpu[(name, version)].append(cpu_of(["analyze", path, "-o", out, "-q"], envs[version]))
                phases = json.loads((out / "summary.json").read_text()).get("cpu") or {}
                if "cells_s" in phases:
                    cells[(name, version)].append(phases["cells_s"])
    print(f"mapdb analyze MAP -o OUT, {args.rounds} rounds, order reversed every round; load average "
          f"{start_load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
    print(f"| map | {args.baseline} CPU (s), median | tree CPU (s), median | tree / {args.baseline} | "
          f"{args.baseline} runs | tree runs | cells phase (s), {args.baseline} / tree / ratio | outputs the same |")
    print("|---|---|---|---|---|---|---|---|")
    for name in maps:
        base, tree = (cpu[(name, v)] for v in envs)
        same = same_outputs(work / f"{name}-{args.baseline}", work / f"{name}-tree")
        print(f"| {name} | {statistics.median(base):.2f} | {statistics.median(tree):.2f} | "
              f"{statistics.median(tree) / statistics.median(base):.3f} | {', '.join(f'{c:.2f}' for c in base)} | "
              f"{', '.join(f'{c:.2f}' for c in tree)} | {_cells_column(*(cells[(name, v)] for v in envs))} | "
              f"{'yes' if same else 'NO'} |")
    return 0


def _cells_column(base: list[float], tree: list[float]) -> str:
    """The cells phase's medians and their ratio, "-" for a version that does not account its phases."""
    b, t = (f"{statistics.median(c):.3f}" if c else "-" for c in (base, tree))
    return f"{b} / {t} / {statistics.median(tree) / statistics.median(base):.3f}" if base and tree else f"{b} / {t}"


if __name__ == "__main__":
    sys.exit(main())
