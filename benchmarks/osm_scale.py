"""Peak memory of OSM builds of Andorra copied 16 and 64 times, the per-object slope, and ``--jobs 2`` on them.

Andorra (``../shared/data/osm``) is copied into one PBF per size by ``build_memory.Replicator`` (each copy
shifted to a cell of its own, ids renumbered).  x16 (23 MB) is below the 64 MiB from which a build keeps its
objects and node locations in files, x64 (92 MB) above, so x16 is also built with ``--spool file --node-index
sparse_file_array``: the slope between that run and x64 is the growth of one path, from which the peak of a
45M-object country is projected.  Each build runs in a fresh process (``build_memory.measure``: VmHWM, and
the sampled peak of anonymous memory), ``--repeat`` times, the builds in turn (alternating order), medians
printed; with ``--baseline COMMIT`` that commit's code is built beside the working tree's, and the maps
compared byte for byte (``SOURCE_DATE_EPOCH`` set).  ``--jobs`` adds ``--jobs 2`` builds of each size, in turn
with the one-process builds; ``--extracts`` adds builds of the three shared extracts together (with and without
``--jobs 2`` when ``--jobs`` is given), which are read in one process whatever ``--jobs`` says.

Beside each build's wall time: its CPU time (user and system, of the command and every process it started and
waited for: the Dask workers too), the load average when it started (the machine is shared), and the processes it
left running after it ended (found by a variable set in the command's environment, which its children inherit).
Run::

    python benchmarks/osm_scale.py [--copies 16 64] [--repeat 3] [--baseline main] [--jobs] [--extracts]
                                   [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from _baseline import shared_data
from build_memory import Replicator, Run, baseline_tree, mapdb_build

COUNTRY_OBJECTS = 45_000_000


@dataclass
class _Timed:
    """One build: the run (wall time, peaks), its CPU seconds, the load when it started, the processes left."""

    run: Run
    cpu: float
    load: float
    left: int


def _median(runs: list[_Timed]) -> tuple[float, float, float, float, float]:
    """Median wall time, CPU time, load, peak RSS and peak anonymous memory of runs of one build."""
    return (statistics.median(r.run.seconds for r in runs), statistics.median(r.cpu for r in runs),
            statistics.median(r.load for r in runs), statistics.median(r.run.peak_rss_mb for r in runs),
            statistics.median(r.run.peak_anon_mb for r in runs))


def _load() -> float:
    with open("/proc/loadavg") as f:
        return float(f.read().split()[0])


def _marked(mark: str) -> int:
    """Processes still running whose environment holds ``mark``."""
    found = 0
    for entry in Path("/proc").iterdir():
        try:
            found += entry.name.isdigit() and mark.encode() in (entry / "environ").read_bytes()
        except OSError:  # ended meanwhile, or not ours
            pass
    return found


def _timed(name: str, sources: list[Path], out: Path, extra: list[str], tree: Path | None) -> _Timed:
    """A build in a fresh process, its CPU time that of its process tree, and the processes it left after 2 s."""
    mark = f"MAPDB_BENCH_{uuid.uuid4().hex}"
    os.environ[mark] = "1"
    load, before = _load(), resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        run = mapdb_build(name, sources, out, list(extra), pythonpath=tree)
    finally:
        del os.environ[mark]
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    time.sleep(2.0)
    return _Timed(run, cpu, load, _marked(mark))


def _builds(copies: list[int], jobs: bool, before: Path | None, extracts: bool
            ) -> list[tuple[str, str, list[str], Path | None]]:
    """Every build to run: its name, its input's name, its extra options and the baseline tree (or None)."""
    out = []
    inputs = [f"x{n}" for n in copies] + (["extracts"] if extracts else [])
    for name in inputs:
        out.append((name, name, [], None))
        if name != "extracts" and int(name[1:]) < 32:
            out.append((f"{name} file path", name, ["--spool", "file", "--node-index", "sparse_file_array"], None))
        if jobs:
            out.append((f"{name} --jobs 2", name, ["--jobs", "2"], None))
        if before is not None:
            out.append((f"{name} before", name, [], before))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--copies", type=int, nargs="*", default=[16, 64])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--baseline", help="also build with this commit's code")
    parser.add_argument("--jobs", action="store_true", help="also build with --jobs 2")
    parser.add_argument("--extracts", action="store_true", help="also build the three shared extracts together")
    parser.add_argument("--keep", type=Path, help="keep the inputs and maps in this directory")
    args = parser.parse_args()
    data = shared_data("osm")
    andorra = sorted(data.glob("andorra*.osm.pbf"))
    if not andorra:
        print(f"{data}: no Andorra extract (real data lives in ../shared/data beside the checkout)")
        return
    os.environ["SOURCE_DATE_EPOCH"] = "1700000000"
    with tempfile.TemporaryDirectory(prefix="mapdb-osm-scale-") as name:
        os.chdir(name)  # so that a baseline's python -c does not import the working tree's package
        tmp = (args.keep or Path(name)).resolve()
        tmp.mkdir(parents=True, exist_ok=True)
        before = baseline_tree(args.baseline, Path(name) / "baseline") if args.baseline else None
        inputs: dict[str, list[Path]] = {}
        for n in args.copies:
            inputs[f"x{n}"] = [tmp / f"andorra_x{n}.osm.pbf"]
            if not inputs[f"x{n}"][0].exists():
                Replicator(andorra).write(inputs[f"x{n}"][0], n)
        if args.extracts:
            inputs["extracts"] = sorted(data.glob("*.osm.pbf"))
        _run(args, inputs, tmp, before)


def _run(args: argparse.Namespace, inputs: dict[str, list[Path]], tmp: Path, before: Path | None) -> None:
    print(f"load average at the start: {_load():.2f}; {os.cpu_count()} CPUs")
    builds = _builds(args.copies, args.jobs, before, args.extracts)
    runs: dict[str, list[_Timed]] = {name: [] for name, *_ in builds}
    for i in range(args.repeat):
        for name, source, extra, tree in builds if i % 2 == 0 else builds[::-1]:
            out = tmp / (name.replace(" ", "_") + ".mapdb")
            runs[name].append(_timed(name, inputs[source], out, extra, tree))
    print(f"load average at the end: {_load():.2f}")
    print(f"\n| build | input | objects | wall (median of {args.repeat}) | CPU | load at start | peak RSS "
          "| peak anonymous | map | processes left |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    reference = {n: (tmp / f"{n}.mapdb").read_bytes() for n in inputs if (tmp / f"{n}.mapdb").exists()}
    for name, source, _, _ in builds:
        wall, cpu, load, rss, anon = _median(runs[name])
        out = tmp / (name.replace(" ", "_") + ".mapdb")
        same = "same bytes" if out.exists() and out.read_bytes() == reference.get(source) else "DIFFERENT"
        ok = "" if all(r.run.ok for r in runs[name]) else f" FAILED: {runs[name][-1].run.note}"
        size = sum(p.stat().st_size for p in inputs[source]) / 1e6
        walls = " / ".join(f"{r.run.seconds:.1f}" for r in runs[name])
        print(f"| {name} | {size:,.1f} MB | {runs[name][0].run.objects or 0:,} | {wall:,.1f} s ({walls}) "
              f"| {cpu:,.1f} s | {load:.1f} | {rss:,.0f} MB | {anon:,.0f} MB | {same} "
              f"| {sum(r.left for r in runs[name])} |{ok}")
    _summary(args.copies, runs, list(inputs))


def _summary(copies: list[int], runs: dict[str, list[_Timed]], inputs: list[str]) -> None:
    if len(copies) >= 2:
        small, big = min(copies), max(copies)
        rss = {name: _median(r)[3] for name, r in runs.items()}
        print(f"\npeak RSS x{big} / x{small}: {rss[f'x{big}'] / rss[f'x{small}']:.2f}")
        file_path = f"x{small} file path"
        if file_path in runs:
            objects = {name: r[0].run.objects or 0 for name, r in runs.items()}
            slope = (rss[f"x{big}"] - rss[file_path]) * 1e6 / max(1, objects[f"x{big}"] - objects[file_path])
            country = rss[f"x{big}"] + slope * (COUNTRY_OBJECTS - objects[f"x{big}"]) / 1e6
            print(f"growth on the file path, x{small} to x{big}: {slope:,.0f} B an object; projected peak for "
                  f"{COUNTRY_OBJECTS / 1e6:.0f}M objects: {country:,.0f} MB")
    for n in inputs:
        for other, what in ((f"{n} --jobs 2", "--jobs 2"), (f"{n} before", "the baseline")):
            if other in runs:
                one, two = _median(runs[n]), _median(runs[other])
                print(f"{n}: {what} takes {two[0] / one[0]:.2f}x the wall time of one process of this tree "
                      f"({two[0]:.1f} s against {one[0]:.1f} s), {two[1] / one[1]:.2f}x its CPU time")


if __name__ == "__main__":
    main()
