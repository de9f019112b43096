"""Calls an image makes outside ``match_fast``, this tree against a baseline commit: the answer's glue, counted.

The images are ``matcher_core.py``'s (300 m, 60 degrees, random heading, 1 px, a 300 m prior; seed 3), answered once
by each tree to warm the map's tiles and indexes, then once more under ``sys.setprofile`` with the calls made inside
``match_fast`` left out: Python functions called (generators resumed count), C functions called, and calls into numpy
(a numpy Python function, or a C function of numpy's), the median over the images.  Counts, not times: they do not
depend on the machine's load.

Run from the repository root::

    python benchmarks/diagnostics/glue_calls.py --maps andorra,monaco,liechtenstein --baseline main
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import cached_maps, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, simulated  # noqa: E402


def _into_numpy(arg: Any) -> bool:
    owner = getattr(arg, "__self__", None)
    return "numpy" in (getattr(arg, "__module__", None) or "") or "numpy" in type(owner).__module__


def count(localizer: ModuleType, map_: Any, image: dict) -> dict[str, int]:
    """The calls one answer makes outside ``match_fast`` (``localizer`` is a tree's ``localize.localizer``)."""
    inside = [0]
    counts = {"python": 0, "C": 0, "numpy": 0}
    matcher = localizer.match_fast

    def match_fast(*args: Any, **kwargs: Any) -> Any:
        inside[0] += 1
        try:
            return matcher(*args, **kwargs)
        finally:
            inside[0] -= 1

    def profile(frame: Any, event: str, arg: Any) -> None:
        if inside[0]:
            return
        if event == "call":
            counts["python"] += 1
            counts["numpy"] += "numpy" in frame.f_code.co_filename
        elif event == "c_call":
            counts["C"] += 1
            counts["numpy"] += _into_numpy(arg)

    localizer.match_fast = match_fast
    sys.setprofile(profile)
    try:
        localizer.localize(image, map_)
    finally:
        sys.setprofile(None)
        localizer.match_fast = matcher
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", default="andorra,monaco,liechtenstein")
    parser.add_argument("--baseline", default="main")
    parser.add_argument("--images", type=int, default=50)
    args = parser.parse_args()
    from mapdb.localize import localizer as here
    from mapdb.mapfile.reader import open_map

    there = import_baseline(args.baseline, CACHE, "localize.localizer")
    there_reader = import_baseline(args.baseline, CACHE, "mapfile.reader")
    print(f"calls an image outside match_fast (median over {args.images} images with a 300 m prior)")
    print(f"  {'map':<14} {'code':<17} {'python':>7} {'C':>7} {'numpy':>7}")
    for name in args.maps.split(","):
        path = cached_maps({name: EXTRACTS[name]}, DATA, CACHE)[name]
        images = simulated(path, args.images, 3)
        for label, module, reader in (("this tree", here, open_map), (f"baseline {args.baseline}", there,
                                                                      there_reader.open_map)):
            map_ = reader(path)
            for image in images:
                module.localize(image, map_)
            counts = [count(module, map_, image) for image in images]
            medians = [statistics.median(c[key] for c in counts) for key in ("python", "C", "numpy")]
            print(f"  {name:<14} {label:<17} {medians[0]:7.0f} {medians[1]:7.0f} {medians[2]:7.0f}")


if __name__ == "__main__":
    main()
