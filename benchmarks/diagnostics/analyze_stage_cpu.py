"""CPU seconds by matcher stage of ``mapdb analyze`` on an indexed map, a baseline revision against this tree.

Reproduces the README's "the lookup stage in fewer calls" figures (issue 31's Monaco-like cells)::

    python benchmarks/diagnostics/analyze_stage_cpu.py MAP.mapdb --rounds 3 --baseline main

``MAP.mapdb`` is indexed first (``mapdb index MAP``, as ``mapdb analyze`` finds its ``.qidx`` beside it; for
example a copy of matcher_core's cached Monaco map).  Each run is a fresh process running ``mapdb analyze MAP``
in-process with the matcher's stages wrapped in process-CPU clocks (``time.process_time``: other processes'
load counts less than in wall time): ``fast.round_hypotheses`` (the lookup stage), ``fast.anchor_batches``,
``fast.screen_round``, ``fast.polish`` and ``localizer.match_fast``; the run's ``CPU:`` line gives ms a cell.
The baseline runs from ``_baseline.cli_tree`` first on ``PYTHONPATH``; the two take turns in ABBA order.  Prints
each run and the medians, with the ratio of this tree to the baseline and the load average.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cli_tree, clocked  # noqa: E402

STAGES = ("lookup", "anchor_batches", "screen", "final fit", "match_fast")


def child(map_path: str, out: str) -> None:
    """One analyze run in this process, its stages clocked; prints ``ms_cell=`` and each stage's seconds."""
    import mapdb.localize.localizer as localizer
    import mapdb.match.fast as fast

    spent: collections.Counter = collections.Counter()

    for owner, name, label in [(fast, "round_hypotheses", "lookup"), (fast, "anchor_batches", "anchor_batches"),
                               (fast, "screen_round", "screen"), (fast, "polish", "final fit"),
                               (localizer, "match_fast", "match_fast")]:
        setattr(owner, name, clocked(getattr(owner, name), label, spent, time.process_time))
    from mapdb_cli.main import cli

    log = io.StringIO()
    with contextlib.redirect_stderr(log), contextlib.redirect_stdout(log):
        try:
            cli(["analyze", map_path, "-o", out, "--overwrite"], standalone_mode=False)
        except SystemExit:
            pass
    ms = re.search(r"^CPU: .* ([0-9.]+) ms a cell", log.getvalue(), re.MULTILINE)
    print(json.dumps({"ms_cell": float(ms.group(1)) if ms else float("nan"), **{k: spent[k] for k in STAGES}}))


def run(map_path: Path, out: Path, pythonpath: str | None) -> dict[str, float]:
    """One run in a fresh process (the baseline's ``mapdb`` first on ``pythonpath``, if given)."""
    env = dict(os.environ, SOURCE_DATE_EPOCH="1700000000")
    env.pop("PYTHONPATH", None)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    done = subprocess.run([sys.executable, __file__, "--child", str(map_path), str(out)], env=env, check=True,
                          capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("map", type=Path, nargs="?", help="an indexed map (mapdb index MAP first)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--baseline", default="main")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return 0
    if args.map is None:
        parser.error("the map to analyze is required")
    work = Path(tempfile.mkdtemp(prefix="analyze-stage-cpu-"))
    base = str(cli_tree(args.baseline, work / "baseline"))
    runs: dict[str, list[dict[str, float]]] = {"baseline": [], "tree": []}
    print(f"mapdb analyze {args.map}: CPU s by stage, {args.rounds} rounds ABBA; load {os.getloadavg()[0]:.1f}")
    for _ in range(args.rounds):
        for who in ("baseline", "tree", "tree", "baseline"):
            got = run(args.map.resolve(), work / f"out-{who}", base if who == "baseline" else None)
            runs[who].append(got)
            print(f"  {who:8s} " + " ".join(f"{k}={v:.3f}" for k, v in got.items()))
    print(f"| stage | {args.baseline} (median) | this tree (median) | tree / {args.baseline} |\n|---|---|---|---|")
    for key in ("ms_cell", *STAGES):
        b = statistics.median(r[key] for r in runs["baseline"])
        t = statistics.median(r[key] for r in runs["tree"])
        print(f"| {key} | {b:.3f} | {t:.3f} | {t / b:.3f} |")
    print("(ms_cell: the run's CPU line, ms a cell; the stages: CPU seconds a run)")
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
