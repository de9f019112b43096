"""How long reading an OSM extract takes, against a bare pyosmium pass over the same file.

Side by side in one run, each repeated (default 3 times, median reported):

* ``bare pyosmium``: ``FileProcessor(...).with_locations("flex_mem").with_areas()``, iterating every
  object and doing nothing: the floor set by locating nodes and assembling areas;
* the same pass with every object dropped in C++ before Python sees it (for reference only);
* ``read_osm``: :func:`mapdb.sources.osm.reader.read_osm` with the default label table;
* ``mapdb build``: :func:`mapdb.build.pipeline.build_map` to a temporary file (if the module exists).

The goal is a whole build at most 2.5x the bare pass.  Run::

    python benchmarks/build_speed.py [OSM_FILE] [--repeat N]

With ``--baseline COMMIT`` the builder of that commit (extracted with ``git archive``) is timed beside this
tree's instead, on each OSM_FILE (default Andorra; ``--all`` for the three extracts)::

    python benchmarks/build_speed.py --baseline 00b1239 [--all] [--repeat N] [--fresh]

Three child processes, started from a temporary directory, each time one thing in process, in turn: the bare
pass, this tree's ``build_map`` and the baseline's, round after round (the order rotated each round, after one
warm-up run each that is not counted), so that a shared machine's changing load falls on all three alike.
The table gives median times, and each build's ratio to the bare pass as the median of the ratios within a
round (runs close in time met a like load).  With ``--fresh`` every run is a new process
instead (Python's start-up and the imports counted), as a user's ``mapdb build`` pays them.  The maps of the
two builders are compared at the end (all but the header's creation time).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import osmium
import osmium.filter

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[0].parent / "shared" / "data" / "osm"
DEFAULT_FILE = DATA / "andorra-2021-06-22.osm.pbf"


def bare_pass(path: Path) -> int:
    count = 0
    for _ in osmium.FileProcessor(str(path)).with_locations("flex_mem").with_areas():
        count += 1
    return count


def bare_pass_nothing_to_python(path: Path) -> None:
    # The C++ floor: same reading and assembly, every object dropped before it reaches Python.
    nothing = osmium.filter.EntityFilter(osmium.osm.NOTHING)
    for _ in osmium.FileProcessor(str(path)).with_locations("flex_mem").with_areas().with_filter(nothing):
        pass


def _timed(func: Callable[[], object], repeat: int) -> tuple[float, list[float]]:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("osm_files", nargs="*", type=Path)
    parser.add_argument("--repeat", type=int, default=None, help="runs of each case (default 3, 7 with --baseline)")
    parser.add_argument("--baseline", metavar="COMMIT", help="time the builder of COMMIT beside this tree's")
    parser.add_argument("--all", action="store_true", help="with --baseline: the three extracts in shared/data")
    parser.add_argument("--fresh", action="store_true", help="with --baseline: every run a new process")
    args = parser.parse_args()
    paths: list[Path] = sorted(DATA.glob("*.osm.pbf")) if args.all else (args.osm_files or [DEFAULT_FILE])
    missing = [p for p in paths if not p.exists()]
    if missing or not paths:
        where = missing[0] if missing else DATA
        print(f"{where}: no such file (real data lives in ../shared/data beside the checkout)")
        return
    if args.baseline:
        side_by_side(paths, args.baseline, args.repeat or 7, args.fresh)
    else:
        in_this_process(paths[0], args.repeat or 3)


def in_this_process(path: Path, repeat: int) -> None:
    """The bare pass, ``read_osm`` and ``build_map`` of this tree, one after the other in this process."""
    from mapdb.labels import default_label_table
    from mapdb.sources.osm.reader import read_osm

    table = default_label_table()
    cases: list[tuple[str, Callable[[], object]]] = [
        ("bare pyosmium (locations+areas)", lambda: bare_pass(path)),
        ("  same, nothing reaches Python", lambda: bare_pass_nothing_to_python(path)),
        ("read_osm", lambda: read_osm(path, table)),
    ]
    tmp = tempfile.TemporaryDirectory()
    try:
        from mapdb.build.pipeline import build_map
    except ImportError as exc:
        print(f"(no full build: mapdb.build.pipeline.build_map not importable: {exc})")
    else:
        output = Path(tmp.name) / "bench.mapdb"
        cases.append(("mapdb build (build_map)", lambda: build_map([path], output)))

    print(f"{path.name}: {path.stat().st_size / 1e6:.1f} MB, {repeat} runs each, median")
    header = f"{'case':<34} {'median s':>9} {'x bare':>7}  runs"
    print(header)
    print("-" * len(header))
    bare = None
    with tmp:
        for name, func in cases:
            median, times = _timed(func, repeat)
            bare = bare or median
            runs = " ".join(f"{t:.3f}" for t in times)
            print(f"{name:<34} {median:>9.3f} {median / bare:>6.2f}x  {runs}")


# --------------------------------------------------------------------------------------------------
# --baseline: the bare pass and two builders, each in a child process of its own, in turn


def serve(kind: str) -> None:
    """A child's loop: for each line ``INPUT<TAB>OUTPUT`` read, run ``kind`` ("bare" or "build", the
    ``mapdb`` on the path) on INPUT and answer with the seconds it took, as JSON."""
    if kind == "bare":
        def run(source: str, output: str) -> object:
            return bare_pass(Path(source))
    else:
        from mapdb.build.pipeline import build_map

        def run(source: str, output: str) -> object:
            return build_map([source], output)
    for line in sys.stdin:
        source, output = line.rstrip("\n").split("\t")
        start = time.perf_counter()
        run(source, output)
        print(json.dumps(time.perf_counter() - start), flush=True)


class _Child:
    """One kind of run in a child process: kept alive between runs (in process), or started for each (fresh)."""

    def __init__(self, name: str, kind: str, tree: Path | None, workdir: Path, fresh: bool) -> None:
        from build_memory import BASELINE_FIRST

        self.name, self.fresh, self.workdir = name, fresh, workdir
        code = f"import sys; sys.path.insert(0, {str(HERE)!r}); import build_speed; build_speed.serve({kind!r})"
        self.env = dict(os.environ)
        if tree is not None:
            code = BASELINE_FIRST + code
            self.env["PYTHONPATH"] = str(tree)
        self.command = [sys.executable, "-c", code]
        self.proc: subprocess.Popen[str] | None = None

    def run(self, source: Path, output: Path) -> float:
        """Seconds of one run: in process, or the whole new process's wall time (``fresh``)."""
        start = time.perf_counter()
        if self.proc is None:
            # From a temporary directory: with the checkout as the current directory, ``python -c`` would
            # import the working tree's package before the baseline's.
            self.proc = subprocess.Popen(self.command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                         env=self.env, cwd=self.workdir)
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(f"{source}\t{output}\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline()
        if not answer:
            raise RuntimeError(f"{self.name}: the child process failed on {source}")
        if not self.fresh:
            return float(json.loads(answer))
        self.close()
        return time.perf_counter() - start

    def close(self) -> None:
        if self.proc is not None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            self.proc.wait()
            self.proc = None


def _ratio(a: list[float], b: list[float]) -> float:
    """The median of the ratios of runs of the same round: the load they met was alike."""
    return statistics.median(x / y for x, y in zip(a, b, strict=True))


def side_by_side(paths: list[Path], commit: str, repeat: int, fresh: bool) -> None:
    """The bare pass, the baseline's build and this tree's, interleaved; medians and ratios to the bare pass."""
    from build_memory import baseline_tree, digest

    with tempfile.TemporaryDirectory(prefix="mapdb-build-speed-") as tmp_name:
        tmp = Path(tmp_name)
        tree = baseline_tree(commit, tmp / "baseline")
        if tree is None:
            print(f"{commit}: cannot extract that commit with git archive")
            return
        children = [_Child("bare pass", "bare", None, tmp, fresh), _Child(commit, "build", tree, tmp, fresh),
                    _Child("this tree", "build", None, tmp, fresh)]
        outputs = {(c.name, p): tmp / f"{i}-{p.name}.mapdb" for i, c in enumerate(children) for p in paths}
        times: dict[tuple[str, Path], list[float]] = {key: [] for key in outputs}
        try:
            for child in children:  # warm-up: imports, caches, the files in the page cache; not counted
                for path in paths:
                    child.run(path, outputs[child.name, path])
            for round_ in range(repeat):
                turn = children[round_ % 3:] + children[:round_ % 3]
                for path in paths:
                    for child in turn:
                        times[child.name, path].append(child.run(path, outputs[child.name, path]))
        finally:
            for child in children:
                child.close()
        how = "each run a new process" if fresh else "in process, after one warm-up run"
        print(f"{repeat} rounds, {how}; median seconds, and the median of the ratios within a round\n")
        print(f"| input | bare pass | {commit} build | this tree's build | {commit} / bare | this tree / bare "
              f"| this tree / {commit} |")
        print("|---|---|---|---|---|---|---|")
        for path in paths:
            bare, old, new = (times[c.name, path] for c in children)
            print(f"| {path.name.split('-')[0]} ({path.stat().st_size / 1e6:.1f} MB) | "
                  + " | ".join(f"{statistics.median(t):.3f} s" for t in (bare, old, new))
                  + f" | {_ratio(old, bare):.2f}x | {_ratio(new, bare):.2f}x | {_ratio(new, old):.3f} |")
        print()
        for path in paths:
            for child in children:
                print(f"{path.name} {child.name}: " + " ".join(f"{t:.3f}" for t in times[child.name, path]))
            same = digest(outputs[commit, path]) == digest(outputs["this tree", path])
            print(f"{path.name}: the two builders' maps {'identical' if same else 'DIFFERENT'} "
                  "(all but the creation time)")


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))  # build_memory, beside this script
    main()
