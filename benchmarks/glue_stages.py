"""Where an image's time goes, stage by stage, side by side with an earlier commit (issue 30's per-image glue).

Each stage's function is wrapped with a clock (inclusive real time, not a profiler's: the wrappers cost well under
a microsecond a call, a few dozen calls an image) in this tree's ``mapdb`` and in the baseline's copy, and the same
images (``matcher_core.py``'s: 300 m, 60 degrees, random heading, 1 px, >= 6 objects; with their 300 m prior, or
without with ``--no-prior``) are localized by both, alternating image by image which goes first, ``--rounds``
times.  Printed: the mean ms an image of each stage, this tree's, the baseline's and their ratio; the stages nest
(``screen_round`` holds ``screen``, ``decision_nfa``, ``refine``, ``candidates``; the ``ObjectIndex`` rows are the
map queries inside them), so the rows do not add up.

Run from the repository root::

    python benchmarks/glue_stages.py --map andorra --baseline main
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _baseline import cached_maps, clocked, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, gauge_ms, simulated  # noqa: E402

# (module under the package, function): the stages timed.
STAGES = [
    ("match.fast", "match_fast"), ("match.screen", "screen_round"), ("match.screen", "screen_neighbours"),
    ("match.verify", "screen"), ("match.verify", "decision_nfa"), ("match.verify", "refine"),
    ("match.refine", "candidates"), ("match.refine", "distinct"), ("match.refine", "merge_candidates"),
    ("match.rivals", "find_rivals"), ("match.refine", "polish"), ("match.evidence.relief", "fit_with_relief"),
    ("match.hypotheses", "round_hypotheses"), ("match.hypotheses", "anchor_batches"),
    ("detections.images", "parse_image"), ("localize.records", "ok_record"),
]
QUERIES = ["nearest", "neighbours", "within", "local_density", "knn_density"]


def _wrap(package: str, totals: collections.Counter) -> None:
    """Clock every stage of ``package`` (``mapdb`` or ``mapdb_baseline``) into ``totals``, wherever it was imported
    by name."""
    modules = [m for name, m in list(sys.modules.items()) if m is not None and name.split(".")[0] == package]
    for module_name, attr in STAGES:
        module = sys.modules.get(f"{package}.{module_name}")
        if module is None or not hasattr(module, attr):
            continue
        original = getattr(module, attr)
        timed = clocked(original, attr, totals)
        for m in modules:
            if getattr(m, attr, None) is original:
                setattr(m, attr, timed)
    index_module = sys.modules.get(f"{package}.match.mapobjects.object_index")
    if index_module is not None:
        cls = index_module.ObjectIndex
        for attr in QUERIES:
            if hasattr(cls, attr):
                setattr(cls, attr, clocked(getattr(cls, attr), f"ObjectIndex.{attr}", totals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--map", default="andorra", choices=sorted(EXTRACTS))
    parser.add_argument("--n", type=int, default=100, help="images")
    parser.add_argument("--rounds", type=int, default=3, help="passes over the images")
    parser.add_argument("--baseline", default="main", help="git revision compared with")
    parser.add_argument("--no-prior", action="store_true", help="images without their prior")
    args = parser.parse_args()
    maps = cached_maps({args.map: EXTRACTS[args.map]}, DATA, CACHE)
    images = simulated(maps[args.map], args.n, 3)
    if args.no_prior:
        images = [{k: v for k, v in im.items() if k != "prior"} for im in images]
    import mapdb.localize as tree_localizer
    import mapdb.store as tree_reader

    with tempfile.TemporaryDirectory() as tmp:
        base_localizer: ModuleType = import_baseline(args.baseline, Path(tmp))
        base_reader: ModuleType = import_baseline(args.baseline, Path(tmp), "store")
        _run(args, maps[args.map], images, (tree_localizer, tree_reader), (base_localizer, base_reader))


def _run(args: argparse.Namespace, map_path: Path, images: list[dict], tree: tuple[ModuleType, ModuleType],
         base: tuple[ModuleType, ModuleType]) -> None:
    """Time the images with both versions, alternating, and print the table."""
    totals = {"tree": collections.Counter(), "base": collections.Counter()}
    _wrap("mapdb", totals["tree"])
    _wrap("mapdb_baseline", totals["base"])
    versions = {"tree": (tree[0].localize, tree[1].open_map(map_path)),
                "base": (base[0].localize, base[1].open_map(map_path))}
    for localize, m in versions.values():  # indexes built, caches warm
        for image in images:
            localize(image, m)
    for counter in totals.values():
        counter.clear()
    whole = collections.Counter()
    load, gauge = os.getloadavg()[0], gauge_ms()
    for r in range(args.rounds):
        for i, image in enumerate(images):
            order = ("tree", "base") if (i + r) % 2 == 0 else ("base", "tree")
            for name in order:
                localize, m = versions[name]
                start = time.perf_counter()
                localize(image, m)
                whole[name] += time.perf_counter() - start
    count = args.rounds * len(images)
    print(f"{args.map}, {len(images)} images x {args.rounds}, {'no prior' if args.no_prior else 'prior 300 m'}; "
          f"load average {load:.1f}, gauge {gauge:.1f} ms (after: {os.getloadavg()[0]:.1f}, {gauge_ms():.1f} ms)")
    print(f"  {'stage (inclusive)':28s} {'this tree ms':>12s} {args.baseline + ' ms':>12s} {'ratio':>6s}")
    rows = [("localize (whole)", whole["tree"], whole["base"])]
    rows += [(label, value, totals["base"][label]) for label, value in totals["tree"].most_common()]
    for label, tree, base in rows:
        ratio = f"{tree / base:6.2f}" if base else "     -"
        print(f"  {label:28s} {tree / count * 1e3:12.3f} {base / count * 1e3:12.3f} {ratio}")


if __name__ == "__main__":
    main()
