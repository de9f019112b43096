"""Peak memory of OSM builds of Andorra copied 16 and 64 times, the per-object slope, and ``--jobs 2`` on them.

Andorra (``../shared/data/osm``) is copied into one PBF per size by ``build_memory.Replicator`` (each copy
shifted to a cell of its own, ids renumbered).  x16 (23 MB) is below the 64 MiB from which a build keeps its
objects and node locations in files, x64 (92 MB) above, so x16 is also built with ``--spool file --node-index
sparse_file_array``: the slope between that run and x64 is the growth of one path, from which the peak of a
45M-object country is projected.  Each build runs in a fresh process (``build_memory.measure``: VmHWM, and
the sampled peak of anonymous memory), ``--repeat`` times, the builds in turn (alternating order), medians
printed; with ``--baseline COMMIT`` that commit's code is built beside the working tree's, and the maps
compared byte for byte (``SOURCE_DATE_EPOCH`` set).  ``--jobs`` adds ``--jobs 2`` builds of each size, in turn
with the one-process builds.  Run::

    python benchmarks/osm_scale.py [--copies 16 64] [--repeat 3] [--baseline main] [--jobs] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
from pathlib import Path

from _baseline import shared_data
from build_memory import Replicator, Run, baseline_tree, mapdb_build

COUNTRY_OBJECTS = 45_000_000


def _median(runs: list[Run]) -> tuple[float, float, float]:
    """Median wall time, peak RSS and peak anonymous memory of runs of one build."""
    return (statistics.median(r.seconds for r in runs), statistics.median(r.peak_rss_mb for r in runs),
            statistics.median(r.peak_anon_mb for r in runs))


def _builds(copies: list[int], jobs: bool, before: Path | None) -> list[tuple[str, int, list[str], Path | None]]:
    """Every build to run: its name, the copies it reads, its extra options and the baseline tree (or None)."""
    out = []
    for n in copies:
        out.append((f"x{n}", n, [], None))
        if n < 32:
            out.append((f"x{n} file path", n, ["--spool", "file", "--node-index", "sparse_file_array"], None))
        if jobs:
            out.append((f"x{n} --jobs 2", n, ["--jobs", "2"], None))
        if before is not None:
            out.append((f"x{n} before", n, [], before))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--copies", type=int, nargs="+", default=[16, 64])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--baseline", help="also build with this commit's code")
    parser.add_argument("--jobs", action="store_true", help="also build with --jobs 2")
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
        inputs = {}
        for n in args.copies:
            inputs[n] = tmp / f"andorra_x{n}.osm.pbf"
            if not inputs[n].exists():
                Replicator(andorra).write(inputs[n], n)
        _run(args, inputs, tmp, before)


def _run(args: argparse.Namespace, inputs: dict[int, Path], tmp: Path, before: Path | None) -> None:
    with open("/proc/loadavg") as f:
        print(f"load average at the start: {f.read().split()[0]}")
    builds = _builds(args.copies, args.jobs, before)
    runs: dict[str, list[Run]] = {name: [] for name, *_ in builds}
    for i in range(args.repeat):
        for name, n, extra, tree in builds if i % 2 == 0 else builds[::-1]:
            out = tmp / (name.replace(" ", "_") + ".mapdb")
            runs[name].append(mapdb_build(name, [inputs[n]], out, list(extra), pythonpath=tree))
    print(f"\n| build | input | objects | wall (median of {args.repeat}) | peak RSS | peak anonymous | map |")
    print("|---|---|---|---|---|---|---|")
    reference = {n: (tmp / f"x{n}.mapdb").read_bytes() for n in args.copies if (tmp / f"x{n}.mapdb").exists()}
    for name, n, _, _ in builds:
        wall, rss, anon = _median(runs[name])
        out = tmp / (name.replace(" ", "_") + ".mapdb")
        same = "same bytes" if out.exists() and out.read_bytes() == reference.get(n) else "DIFFERENT"
        ok = "" if all(r.ok for r in runs[name]) else f" FAILED: {runs[name][-1].note}"
        print(f"| {name} | {inputs[n].stat().st_size / 1e6:,.0f} MB | {runs[name][0].objects or 0:,} | {wall:,.1f} s "
              f"| {rss:,.0f} MB | {anon:,.0f} MB | {same} |{ok}")
    _summary(args.copies, runs)


def _summary(copies: list[int], runs: dict[str, list[Run]]) -> None:
    small, big = min(copies), max(copies)
    rss = {name: _median(r)[1] for name, r in runs.items()}
    print(f"\npeak RSS x{big} / x{small}: {rss[f'x{big}'] / rss[f'x{small}']:.2f}")
    file_path = f"x{small} file path"
    if file_path in runs:
        objects = {name: r[0].objects or 0 for name, r in runs.items()}
        slope = (rss[f"x{big}"] - rss[file_path]) * 1e6 / max(1, objects[f"x{big}"] - objects[file_path])
        country = rss[f"x{big}"] + slope * (COUNTRY_OBJECTS - objects[f"x{big}"]) / 1e6
        print(f"growth on the file path, x{small} to x{big}: {slope:,.0f} B an object; projected peak for "
              f"{COUNTRY_OBJECTS / 1e6:.0f}M objects: {country:,.0f} MB")
    for n in copies:
        if f"x{n} --jobs 2" in runs:
            one, two = _median(runs[f"x{n}"])[0], _median(runs[f"x{n} --jobs 2"])[0]
            print(f"x{n}: --jobs 2 takes {two / one:.2f}x the time of one process")


if __name__ == "__main__":
    main()
