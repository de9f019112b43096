"""Where the fast matcher's time goes an image: KD-tree queries, numpy calls, stages and hypotheses a round.

Reproduces the README's profile under "Speed with a prior" (issue 30): "with a prior a round holds 40
hypotheses (median), without one 195 ... a fixed ~15 KD-tree queries an image (28 % of the time: 9 on the
objects' tree, 4 on the quad tiles' 7-D trees with a prior) and ~800 numpy calls spread thin over ~30
functions (the largest, ``ObjectIndex.nearest``, 108 an image ...)".  The images are
``benchmarks/matcher_core.py``'s (300 m, 60 degrees, random yaw, 1 px, a 300 m prior; seed 3), answered
once to warm the map's tiles and indexes, then again under each probe; ``noprior`` drops the prior.

Run from the repository root (a few minutes on a loaded machine)::

    python benchmarks/diagnostics/matcher_profile.py andorra --images 30
    python benchmarks/diagnostics/matcher_profile.py andorra --images 30 --cases prior --probes kd

Probes: ``kd`` times every ``query``/``query_ball_point`` of the trees the matcher builds (wrapped where
``quick_tree`` makes them; tagged by their dimension); ``numpy`` counts calls from outside numpy into numpy by
calling function (``sys.setprofile``: slows the run, so it times nothing); ``stages`` times the matcher's
stages as ``mapdb.match.fast`` calls them and counts the hypotheses of each round.  Each prints ms an image
beside its own run's total: the probes' overheads differ, compare shares within a probe.
"""

from __future__ import annotations

import argparse
import collections
import functools
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from matcher_core import CACHE, DATA, EXTRACTS, cached_maps, simulated  # noqa: E402

import mapdb.localize.localizer as localizer_module  # noqa: E402
import mapdb.match.fast as fast  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402

TREE_MODULES = ("mapdb.match.quads", "mapdb.match.evidence.terrain")
# The map objects' queries go to the compiled kernel's trees (mapdb.match.mapobjects.label_trees), timed by method.
OBJECT_QUERIES = ("query", "count", "members")
STAGES = ("_search", "round_hypotheses", "screen_round", "find_rivals", "polish")


class TimedTree:
    """A KD-tree whose queries are timed and counted under ``tag``."""

    def __init__(self, tree: Any, tag: str, times: collections.Counter, calls: collections.Counter) -> None:
        self._tree, self._tag, self._times, self._calls = tree, tag, times, calls

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._tree, name)
        if name not in ("query", "query_ball_point"):
            return value

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return value(*args, **kwargs)
            finally:
                key = f"{self._tag}.{name}"
                self._times[key] += time.perf_counter() - start
                self._calls[key] += 1
        return timed


def answer_all(images: list[dict], map_: Any) -> float:
    """Seconds to answer every image once."""
    start = time.perf_counter()
    for image in images:
        localizer_module.localize(image, map_)
    return time.perf_counter() - start


def _timed(f: Callable[..., Any], tag: str, times: collections.Counter, calls: collections.Counter
           ) -> Callable[..., Any]:
    """``f`` timed and counted under ``tag``."""

    @functools.wraps(f)
    def timed(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        try:
            return f(*args, **kwargs)
        finally:
            times[tag] += time.perf_counter() - start
            calls[tag] += 1

    return timed


def kd_probe(path: Path, images: list[dict]) -> None:
    """KD-tree queries an image, their time and share of the whole, by tree."""
    import importlib

    times: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    modules = [importlib.import_module(name) for name in TREE_MODULES]
    made = [module.quick_tree for module in modules]
    for module, f in zip(modules, made):
        module.quick_tree = lambda points, f=f: TimedTree(f(points), f"tree{points.shape[1]}d", times, calls)
    from mapdb.match.mapobjects.label_trees import LabelTrees

    kernel = {name: getattr(LabelTrees, name) for name in OBJECT_QUERIES}
    for name, f in kernel.items():
        setattr(LabelTrees, name, _timed(f, f"objects {name}", times, calls))
    try:
        with open_map(path) as m:
            answer_all(images, m)
            times.clear()
            calls.clear()
            total = answer_all(images, m)
    finally:
        for module, f in zip(modules, made):
            module.quick_tree = f
        for name, f in kernel.items():
            setattr(LabelTrees, name, f)
    n = len(images)
    print(f"  ms/image {1000 * total / n:.2f}; KD-tree queries {sum(calls.values()) / n:.1f} an image,"
          f" {1000 * sum(times.values()) / n:.2f} ms an image ({sum(times.values()) / total:.0%})")
    for key, seconds in times.most_common():
        print(f"    {key:<28} {1000 * seconds / n:6.2f} ms  {calls[key] / n:5.1f} queries an image")


def numpy_probe(path: Path, images: list[dict]) -> None:
    """Calls into numpy an image, by the calling function (the 40 largest)."""
    import numpy as np

    by: collections.Counter = collections.Counter()

    def in_numpy(frame: Any) -> bool:
        return frame is not None and str(frame.f_globals.get("__name__", "")).startswith("numpy")

    def where(frame: Any) -> str:
        return f"{str(frame.f_globals.get('__name__', '?')).replace('mapdb.', '')}.{frame.f_code.co_qualname}"

    def profile(frame: Any, event: str, arg: Any) -> None:
        if event == "call" and in_numpy(frame) and not in_numpy(frame.f_back):
            by[where(frame.f_back)] += 1
        elif event == "c_call" and not in_numpy(frame):
            owner = getattr(arg, "__self__", None)
            if (isinstance(arg, np.ufunc) or isinstance(owner, np.ndarray | np.generic)
                    or str(getattr(arg, "__module__", "") or "").startswith("numpy")):
                by[where(frame)] += 1

    with open_map(path) as m:
        answer_all(images, m)
        sys.setprofile(profile)
        try:
            answer_all(images, m)
        finally:
            sys.setprofile(None)
    n, total = len(images), sum(by.values())
    print(f"  numpy calls an image {total / n:.0f}, from {len(by)} functions")
    for key, count in by.most_common(40):
        print(f"    {count / n:7.1f} ({count / total:4.0%}) {key}")


def stages_probe(path: Path, images: list[dict]) -> None:
    """The matcher's stages' time an image, and the hypotheses a round."""
    times: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    sizes: list[int] = []

    def timed(name: str, f: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(f)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            result = f(*args, **kwargs)
            times[name] += time.perf_counter() - start
            calls[name] += 1
            if name == "round_hypotheses":
                sizes.append(len(result))
            return result
        return wrapper

    saved = {name: getattr(fast, name) for name in STAGES}
    match_fast = localizer_module.match_fast
    try:
        with open_map(path) as m:
            answer_all(images, m)
            for name, f in saved.items():
                setattr(fast, name, timed(name, f))
            localizer_module.match_fast = timed("match_fast", match_fast)
            total = answer_all(images, m)
    finally:
        for name, f in saved.items():
            setattr(fast, name, f)
        localizer_module.match_fast = match_fast
    n = len(images)
    print(f"  ms/image {1000 * total / n:.2f}")
    for key, seconds in times.most_common():
        print(f"    {key:<18} {1000 * seconds / n:7.2f} ms an image  {calls[key] / n:5.1f} calls an image")
    if sizes:
        print(f"  hypotheses a round: median {statistics.median(sizes):g}, max {max(sizes)},"
              f" rounds an image {len(sizes) / n:.1f}")


PROBES = {"kd": kd_probe, "numpy": numpy_probe, "stages": stages_probe}


def main(argv: list[str] | None = None) -> int:
    """Each case (with and without the prior) under each probe."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("extract", choices=sorted(EXTRACTS), help="the shared OSM extract whose map to use")
    parser.add_argument("--images", type=int, default=30)
    parser.add_argument("--seed", type=int, default=3, help="matcher_core.py's seed")
    parser.add_argument("--cases", nargs="+", choices=("prior", "noprior"), default=["prior", "noprior"])
    parser.add_argument("--probes", nargs="+", choices=sorted(PROBES), default=["kd", "numpy", "stages"])
    args = parser.parse_args(argv)
    if not (DATA / EXTRACTS[args.extract]).exists():
        print(f"needs the shared data: {DATA / EXTRACTS[args.extract]}", file=sys.stderr)
        return 1
    path = cached_maps({args.extract: EXTRACTS[args.extract]}, DATA, CACHE)[args.extract]
    images = simulated(path, args.images, args.seed)
    for case in args.cases:
        chosen = images if case == "prior" else [{k: v for k, v in im.items() if k != "prior"} for im in images]
        for probe in args.probes:
            print(f"{args.extract}, {len(chosen)} images, {case}, probe {probe}:", flush=True)
            PROBES[probe](path, chosen)
    return 0


if __name__ == "__main__":
    sys.exit(main())
