"""What a simulated cell costs besides the matcher in ``mapdb analyze``: a baseline revision against this tree, the
two taking turns (each its own process, the order reversed every round).

Reproduces the README's "analyze: a cell's own work" figures::

    python benchmarks/diagnostics/analyze_own.py --maps monaco,andorra --rounds 3 --baseline main

Each process runs ``mapdb analyze`` of the map once (its defaults), recording the cell tasks it hands to
``measure_cells``, then replays them in the process: once with the matcher (``match_fast``, its answers kept by
their image), then ``--replays`` times with the kept answers, so that what is timed is the cells' own work (the
poses, views, simulated images, the localizer's glue around the matcher and the measures) and nothing of the
matcher's.  The table gives each version's median CPU seconds of those replays (this process's), their ratio,
and the whole replay with the matcher; the last column says whether the replays' measures equal the run's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cli_tree, shared_data  # noqa: E402

EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "monaco": "monaco-2021-12-03.osm.pbf",
            "liechtenstein": "liechtenstein-2013-08-03.osm.pbf"}
FIELDS = ("visible", "per_label", "success", "false", "error", "ambiguity", "simulated", "low", "high")


def measure(map_path: str, out: str, replays: int) -> dict[str, Any]:
    """This process: one analyze run, its cell tasks replayed with the matcher and then with its kept answers."""
    import numpy as np
    from mapdb_cli.main import cli

    import mapdb.analysis.run as run
    import mapdb.localize.localizer as localizer

    tasks: list[tuple[tuple[Any, ...], dict[str, Any]]] = []
    measure_cells = run.measure_cells

    def recorded(*args: Any, **kwargs: Any) -> Any:
        tasks.append((args, kwargs))
        return measure_cells(*args, **kwargs)

    run.measure_cells = recorded
    try:
        cli(["analyze", map_path, "-o", out, "--overwrite", "-q"], standalone_mode=False)
    except SystemExit:
        pass
    run.measure_cells = measure_cells
    match_fast, kept = localizer.match_fast, {}

    def answered(z: Any, codes: Any, *args: Any, **kwargs: Any) -> Any:
        key = (z.tobytes(), codes.tobytes(), kwargs.get("prior"))
        if key not in kept:
            kept[key] = match_fast(z, codes, *args, **kwargs)
        return kept[key]

    localizer.match_fast = answered

    def replay() -> tuple[float, list[Any]]:
        start = time.process_time()
        results = [measure_cells(*args, **kwargs) for args, kwargs in tasks]
        return time.process_time() - start, results

    whole, first = replay()
    own, same = [], True
    for _ in range(replays):
        seconds, results = replay()
        own.append(seconds)
        same &= all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
                    for a, b in zip(first, results, strict=True) for f in FIELDS)
    return {"cells": int(sum(len(args[3]) for args, _ in tasks)), "whole": whole, "own": statistics.median(own),
            "same": bool(same)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default="monaco,andorra")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--replays", type=int, default=3)
    parser.add_argument("--baseline", default="main")
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--child", nargs=2, metavar=("MAP", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child[0], args.child[1], args.replays)))
        return 0
    data = shared_data("osm")
    if not data.is_dir():
        print(f"no shared data at {data}: nothing to measure", file=sys.stderr)
        return 1
    work = args.workdir or Path(tempfile.mkdtemp(prefix="analyze-own-"))
    work.mkdir(parents=True, exist_ok=True)
    exe = shutil.which("mapdb") or str(Path(sys.executable).with_name("mapdb"))
    envs = {args.baseline: {**os.environ, "PYTHONPATH": str(cli_tree(args.baseline, work / "baseline"))},
            "tree": dict(os.environ)}
    maps = {}
    for name in args.maps.split(","):
        maps[name] = work / f"{name}.mapdb"
        if not maps[name].exists():
            subprocess.run([exe, "build", "-q", data / EXTRACTS[name], "-o", maps[name]], check=True)
            subprocess.run([exe, "index", maps[name]], check=True)
    got: dict[tuple[str, str], list[dict[str, Any]]] = {(m, v): [] for m in maps for v in envs}
    start_load = os.getloadavg()[0]
    for k in range(args.rounds):
        for name, path in maps.items():
            for version in (list(envs) if k % 2 == 0 else list(envs)[::-1]):
                done = subprocess.run([sys.executable, __file__, "--replays", str(args.replays), "--child", str(path),
                                       str(work / f"{name}-{version}")], env=envs[version], check=True,
                                      capture_output=True, text=True)
                got[(name, version)].append(json.loads(done.stdout.strip().splitlines()[-1]))
    print(f"a cell's own work in mapdb analyze (the matcher's answers replayed), {args.rounds} rounds, order reversed "
          f"every round; load average {start_load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
    print(f"| map | cells | {args.baseline} own (s) | tree own (s) | tree / {args.baseline} | {args.baseline} with "
          "matcher (s) | tree with matcher (s) | replays the run's |")
    print("|---|---|---|---|---|---|---|---|")
    for name in maps:
        base, tree = (got[(name, v)] for v in envs)
        own = [statistics.median(r["own"] for r in runs) for runs in (base, tree)]
        whole = [statistics.median(r["whole"] for r in runs) for runs in (base, tree)]
        same = all(r["same"] for r in base + tree)
        print(f"| {name} | {tree[0]['cells']} | {own[0]:.3f} | {own[1]:.3f} | {own[1] / own[0]:.3f} | "
              f"{whole[0]:.2f} | {whole[1]:.2f} | {'yes' if same else 'NO'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
