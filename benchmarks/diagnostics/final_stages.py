"""The winner's stages (the final fit ``polish``, the rivals ``find_rivals``) and the whole ``match_fast``, this tree's
against a baseline revision's on the very same calls, and whether they answer the same.

Each map's images (``matcher_core.py``'s: 300 m, 60 degrees, random heading, 1 px; with their prior and without)
are localized once by this tree while every call of the three functions is recorded; the recorded calls are then
replayed ``--rounds`` times through this tree's functions and the baseline's (``mapdb_baseline``, its own compiled
kernel), taking turns (the order reversed every round), each pass timed in process CPU (less moved by other
processes than the wall clock on a shared machine).  Printed: the median CPU a call of each version, their ratio,
and whether the two versions' outputs are identical (a digest of every field, array bytes included).  Unlike
``glue_stages.py``'s clocks inside whole runs, the stages here see identical inputs, so small differences show
through the load.

With ``--analyze`` also the calls of one ``mapdb analyze`` run of each map (a copy indexed in ``--workdir``): the
cells' images, the ones issue 31's country projection counts.  Run from the repository root::

    python benchmarks/diagnostics/final_stages.py --maps monaco,andorra,liechtenstein --baseline main --analyze
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import importlib
import os
import shutil
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from _baseline import extract_maps, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, gauge_ms, simulated  # noqa: E402

# (module under the package, function) replayed; match_fast is recorded where the localizer calls it.
STAGES = [("match.refine", "polish"), ("match.rivals", "find_rivals"), ("match.fast", "match_fast")]


def digest(obj: Any) -> str:
    """A digest of a result: every dataclass field, list item and array's dtype, shape and bytes."""
    h = hashlib.sha1()

    def walk(o: Any) -> None:
        if isinstance(o, np.ndarray):
            h.update(f"{o.dtype}{o.shape}".encode())
            h.update(np.ascontiguousarray(o).tobytes())
        elif isinstance(o, (list, tuple)):
            h.update(b"[")
            for x in o:
                walk(x)
            h.update(b"]")
        elif hasattr(o, "__dataclass_fields__"):
            h.update(type(o).__name__.encode())
            for name in o.__dataclass_fields__:
                walk(getattr(o, name))
        else:
            h.update(repr(o).encode())

    walk(obj)
    return h.hexdigest()


def record(path: Path, images: list[dict] | None, out: Path | None = None) -> dict[str, list[tuple[tuple, dict]]]:
    """Every call of the stages while this tree localizes ``images`` (None: while ``mapdb analyze`` of the map, indexed,
    writes into ``out``; the final fit's candidate copied: the caller keeps no reference to it, but a copy keeps the
    replay honest should one change it)."""
    import mapdb.localize.localizer as localizer
    import mapdb.match.fast as fast
    from mapdb.mapfile.reader import open_map

    calls: dict[str, list[tuple[tuple, dict]]] = {name: [] for _, name in STAGES}
    owners = {"polish": fast, "find_rivals": fast, "match_fast": localizer}
    saved = {name: getattr(owner, name) for name, owner in owners.items()}

    def recorder(name: str, original: Callable) -> Callable:
        def call(*args: Any, **kwargs: Any) -> Any:
            calls[name].append(((copy.deepcopy(args[0]), *args[1:]), kwargs))
            return original(*args, **kwargs)
        return call

    for name, owner in owners.items():
        setattr(owner, name, recorder(name, saved[name]))
    try:
        if images is None:
            from mapdb_cli.main import cli

            cli(["analyze", str(path), "-o", str(out), "--overwrite"], standalone_mode=False)
        else:
            loc = localizer.localizer_for(open_map(path))
            for image in images:
                loc.localize(image)
    finally:
        for name, owner in owners.items():
            setattr(owner, name, saved[name])
    return calls


def compare(calls: list[tuple[tuple, dict]], mine: Callable, base: Callable, rounds: int) -> tuple[float, float, bool]:
    """Median CPU ms a call of ``mine`` and ``base`` over ``calls`` (taking turns), and whether they answer alike."""
    same = digest([mine(*a, **k) for a, k in calls]) == digest([base(*a, **k) for a, k in calls])
    spent: dict[str, list[float]] = {"mine": [], "base": []}
    for r in range(rounds):
        order = [("mine", mine), ("base", base)]
        for key, f in order if r % 2 == 0 else order[::-1]:
            start = time.process_time()
            for a, k in calls:
                f(*a, **k)
            spent[key].append((time.process_time() - start) / max(len(calls), 1) * 1e3)
    return statistics.median(spent["mine"]), statistics.median(spent["base"]), same


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--maps", default="monaco,andorra")
    parser.add_argument("--n", type=int, default=100, help="images a map")
    parser.add_argument("--rounds", type=int, default=7, help="replays of each version (taking turns)")
    parser.add_argument("--baseline", default="main")
    parser.add_argument("--analyze", action="store_true",
                        help="also the calls of one `mapdb analyze` run of each map (its own images: the cells')")
    parser.add_argument("--workdir", default=os.path.join(CACHE, "final-stages"))
    args = parser.parse_args()
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    import_baseline(args.baseline, work)
    import mapdb

    ours = {name: getattr(importlib.import_module(f"mapdb.{mod}"), name) for mod, name in STAGES}
    theirs = {name: getattr(importlib.import_module(f"mapdb_baseline.{mod}"), name) for mod, name in STAGES}
    print(f"this tree ({Path(mapdb.__file__).parent}) against {args.baseline}; load average "
          f"{os.getloadavg()[0]:.1f}, gauge {gauge_ms():.1f} ms; process CPU a call, median of {args.rounds}")
    print(f"  {'map':14s} {'case':9s} {'stage':12s} {'calls':>5s} {'tree ms':>9s} {'base ms':>9s} {'ratio':>6s} same")
    for name in args.maps.split(","):
        path = extract_maps([name], EXTRACTS, DATA, Path(CACHE))[name]
        for case in ("prior", "no prior", "analyze") if args.analyze else ("prior", "no prior"):
            if case == "analyze":
                # analyze reads the map's stored index: a copy indexed here, outside the shared cache
                indexed = work / f"{name}.mapdb"
                shutil.copyfile(path, indexed)
                from mapdb_cli.main import cli

                cli(["index", str(indexed), "--overwrite"], standalone_mode=False)
                calls = record(indexed, None, work / f"{name}-analysis")
            else:
                images = simulated(path, args.n, 3)
                if case == "no prior":
                    images = [{k: v for k, v in im.items() if k != "prior"} for im in images]
                calls = record(path, images)
            for _, stage in STAGES:
                tree_ms, base_ms, same = compare(calls[stage], ours[stage], theirs[stage], args.rounds)
                print(f"  {name:14s} {case:9s} {stage:12s} {len(calls[stage]):5d} {tree_ms:9.4f} {base_ms:9.4f} "
                      f"{tree_ms / base_ms:6.3f} {'yes' if same else 'NO'}", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.1f}; gauge {gauge_ms():.1f} ms")


if __name__ == "__main__":
    main()
