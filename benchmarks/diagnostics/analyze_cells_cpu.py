"""The cells phase's CPU of ``mapdb analyze`` (what the country projection counts), a baseline revision against this
tree, the two taking turns, and whether their outputs are the same.

:mod:`analyze_cpu` times whole runs, whose start-up and picture (3-5 s on Monaco) hide a change of the matcher's
cost; each run's ``summary.json`` states the CPU of its phases (``cpu.cells_s``: the simulated cells' images,
measured, localized and recorded), which this script compares.  The maps are built as :mod:`analyze_cpu` builds
them (the shared extracts, indexed); the baseline runs from its CLI tree first on ``PYTHONPATH``; every run with
``SOURCE_DATE_EPOCH=1700000000``.  Reproduces the issue 31 screen figure (the cells phase 0.90x of main)::

    python benchmarks/diagnostics/analyze_cells_cpu.py --maps monaco --rounds 5 --baseline main
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cli_tree, shared_data  # noqa: E402
from analyze_cpu import EXTRACTS, mapdb, same_outputs  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default="monaco")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--baseline", default="main")
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    data = shared_data("osm")
    if not data.is_dir():
        print(f"no shared data at {data}: nothing to measure", file=sys.stderr)
        return 1
    work = args.workdir or Path(tempfile.mkdtemp(prefix="analyze-cells-"))
    work.mkdir(parents=True, exist_ok=True)
    stamp = {"SOURCE_DATE_EPOCH": "1700000000"}
    envs = {args.baseline: {**os.environ, **stamp, "PYTHONPATH": str(cli_tree(args.baseline, work / "baseline"))},
            "tree": {**os.environ, **stamp}}
    maps = {name: work / f"{name}.mapdb" for name in args.maps.split(",")}
    for name, path in maps.items():
        if not path.exists():
            mapdb("build", "-q", data / EXTRACTS[name], "-o", path)
            mapdb("index", path)
    cells: dict[tuple[str, str], list[float]] = {(m, v): [] for m in maps for v in envs}
    start_load = os.getloadavg()[0]
    for k in range(args.rounds):
        for name, path in maps.items():
            for version in (list(envs) if k % 2 == 0 else list(envs)[::-1]):
                out = work / f"{name}-{version}"
                shutil.rmtree(out, ignore_errors=True)
                mapdb("analyze", path, "-o", out, "-q", env=envs[version])
                cells[(name, version)].append(json.loads((out / "summary.json").read_text())["cpu"]["cells_s"])
    print(f"mapdb analyze MAP -o OUT, {args.rounds} rounds, order reversed every round; load average "
          f"{start_load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
    print(f"| map | {args.baseline} cells CPU (s), median | tree, median | tree / {args.baseline} | "
          f"{args.baseline} runs | tree runs | outputs the same |")
    print("|---|---|---|---|---|---|---|")
    for name in maps:
        base, tree = (cells[(name, v)] for v in envs)
        same = same_outputs(work / f"{name}-{args.baseline}", work / f"{name}-tree")
        print(f"| {name} | {statistics.median(base):.3f} | {statistics.median(tree):.3f} | "
              f"{statistics.median(tree) / statistics.median(base):.3f} | {', '.join(f'{c:.3f}' for c in base)} | "
              f"{', '.join(f'{c:.3f}' for c in tree)} | {'yes' if same else 'NO'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
