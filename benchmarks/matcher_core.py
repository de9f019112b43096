"""The matcher core side by side with an earlier commit: time per image and process start-up.

1. Andorra (``../shared/data/osm``, all labels) images as issue 8 measures them: 300 m, 60 degree field of
   view, random heading, 1 px and 0.05 degree errors, at least 6 objects; median time per ``localize``
   call with a 300 m prior in each image and without a prior (the whole map's index built once first,
   outside the timing), and how many were localized within 2 m.
2. Start-up: ``mapdb --help`` and a one-image ``mapdb query`` with a prior, from process start to the
   answer's line on the pipe (and to exit), median of ``--repeats`` processes.  As installed: Python's
   bytecode cache in use (kept in a temporary ``PYTHONPYCACHEPREFIX``, filled by one untimed run of each
   command, so the working tree gets no ``__pycache__``); and with ``PYTHONDONTWRITEBYTECODE=1`` and no
   cache, as in a sandbox where every process compiles mapdb's sources.  The command is the ``mapdb``
   script beside this Python (a version manager's shim on PATH, such as pyenv's, adds 0.06-0.1 s of its
   own).  ``--startup-only`` skips part 1.

With ``--baseline REV`` the code of that revision runs in the same process, image by image in turn with
this tree's, so both meet the same load.

Run from the repository root::

    python benchmarks/matcher_core.py --baseline 98b7ab6
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import ROOT, as_json, import_baseline  # noqa: E402

ANDORRA = ROOT.parent / "shared" / "data" / "osm" / "andorra-2021-06-22.osm.pbf"

def time_images(versions: dict, map_path: Path, images: list[dict]) -> dict:
    """Median ms per image of each version's ``localize``, alternating versions image by image; localized
    images, and answers (status and position) identical to the first version's."""
    result = {}
    for case in ("prior", "no prior"):
        subset = images if case == "prior" else [{k: v for k, v in im.items() if k != "prior"} for im in images]
        maps = {label: store.open_map(map_path) for label, (localize, store) in versions.items()}
        times = {label: [] for label in versions}
        good = dict.fromkeys(versions, 0)
        answers: dict[str, list] = {label: [] for label in versions}
        for label, (localize, _) in versions.items():
            localize(subset[0], maps[label])  # the whole map's index built once, outside the timing
        order = list(versions.items())
        for i, im in enumerate(subset):
            # Which version goes first alternates image by image: the first to meet an image pays 2-3 % more
            # (the same code against itself: "this tree" 2-3 % slower when it always went first).
            for label, (localize, _) in order if i % 2 == 0 else order[::-1]:
                start = time.perf_counter()
                answer = as_json(localize(im, maps[label]))
                answers[label].append((answer["status"], answer.get("x"), answer.get("y")))
                times[label].append((time.perf_counter() - start) * 1000.0)
                good[label] += answer["status"] == "ok" and math.hypot(
                    answer["x"] - im["truth"]["x"], answer["y"] - im["truth"]["y"]) <= 2.0
        first = answers[next(iter(versions))]
        for label in versions:
            maps[label].close()
            result.setdefault(label, {})[case] = {"median_ms": statistics.median(times[label]),
                                                  "localized": good[label], "images": len(subset),
                                                  "same": sum(a == b for a, b in zip(answers[label], first))}
    return result


def startup(map_path: Path, one_image: Path, cwd: Path, repeats: int, env: dict[str, str]) -> dict[str, float]:
    """Median seconds of ``mapdb --help`` (to exit) and of a one-image query with a prior (to its answer's line,
    and to exit), each process started afresh with ``env``; one untimed run of each first."""
    out: dict[str, list[float]] = {"--help": [], "query answer": [], "query exit": []}
    script = Path(sys.executable).parent / "mapdb"
    mapdb = str(script) if script.exists() else "mapdb"
    for run in range(repeats + 1):
        start = time.perf_counter()
        subprocess.run([mapdb, "--help"], check=True, capture_output=True, cwd=cwd, env=env)
        help_s = time.perf_counter() - start
        start = time.perf_counter()
        with subprocess.Popen([mapdb, "query", str(map_path), str(one_image)], stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, cwd=cwd, env=env) as proc:
            assert proc.stdout is not None
            answer = json.loads(proc.stdout.readline())  # written and flushed before the next line is read
            answer_s = time.perf_counter() - start
            proc.stdout.read()
        exit_s = time.perf_counter() - start
        if proc.returncode != 0 or answer.get("status") != "ok":
            sys.exit(f"the one-image query failed: exit {proc.returncode}, answer {answer}")
        if run:  # the first run fills the bytecode cache
            for key, value in zip(out, (help_s, answer_s, exit_s)):
                out[key].append(value)
    return {key: statistics.median(values) for key, values in out.items()}


def startup_table(map_path: Path, one_image: Path, work: Path, repeats: int) -> None:
    """Print start-up with Python's bytecode cache (as installed) and without (compiling mapdb every run)."""
    cached = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    cached["PYTHONPYCACHEPREFIX"] = str(work / "pycache")
    uncached = {k: v for k, v in os.environ.items() if k != "PYTHONPYCACHEPREFIX"}
    uncached["PYTHONDONTWRITEBYTECODE"] = "1"
    print(f"start-up (this tree, median of {repeats} processes; the query's answer is ok):")
    print(f"  {'bytecode':<34} {'--help':>7} {'query: answer':>14} {'exit':>7}")
    for label, env in (("cached (as installed)", cached), ("none (compiled every run)", uncached)):
        times = startup(map_path, one_image, work, repeats, env)
        print(f"  {label:<34} {times['--help']:6.3f}s {times['query answer']:13.3f}s {times['query exit']:6.3f}s")


def per_image_table(args: argparse.Namespace, map_path: Path, images: list[dict], work: Path) -> None:
    """Print part 1: median ms per image of this tree (and the baseline), with and without a prior."""
    from mapdb.localize import localizer as tree_localize
    from mapdb.mapfile import reader as tree_reader

    versions = {"this tree": (tree_localize.localize, tree_reader)}
    if args.baseline:
        old = import_baseline(args.baseline, work)
        versions[f"baseline {args.baseline}"] = (old.localize, import_baseline(args.baseline, work, "store"))
    results = time_images(versions, map_path, images)
    print(f"Andorra, {args.n} images: 300 m, 60 deg, random heading, 1 px, 0.05 deg, >= 6 objects "
          f"({statistics.mean(len(im['objects']) for im in images):.1f} objects per image)")
    print(f"  {'code':<24} {'case':<9} {'median ms':>9} {'localized':>10} {'same answers':>13}")
    for label, res in results.items():
        for case, r in res.items():
            print(f"  {label:<24} {case:<9} {r['median_ms']:9.2f} {r['localized']:6d}/{r['images']}"
                  f" {r['same']:>9d}/{r['images']}")
    if args.baseline:
        base = results[f"baseline {args.baseline}"]
        for case in ("prior", "no prior"):
            ratio = base[case]["median_ms"] / results["this tree"][case]["median_ms"]
            print(f"  {case}: this tree is {ratio:.2f}x the baseline's speed")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=300, help="images")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--baseline", metavar="REV", help="also run the matcher of this git revision")
    parser.add_argument("--repeats", type=int, default=5, help="runs of each start-up measurement")
    parser.add_argument("--startup-only", action="store_true", help="measure start-up only (not per image)")
    args = parser.parse_args()
    if not ANDORRA.exists():
        sys.exit(f"skipped: {ANDORRA} not found")
    from mapdb.build.pipeline import build_map
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.simulate import simulate_images

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        map_path = work / "andorra.mapdb"
        build_map([ANDORRA], map_path)
        with open_map(map_path) as m:
            images = simulate_images(m, args.n, altitude=300.0, fov_deg=60.0, yaw="random", pixel_std=1.0,
                                     attitude_std=0.05, min_objects=6, with_prior=300.0, seed=args.seed)
        images_path = work / "images.jsonl"
        images_path.write_text("".join(json.dumps(im) + "\n" for im in images))
        one_image = work / "one.jsonl"
        one_image.write_text(json.dumps(images[0]) + "\n")
        if not args.startup_only:
            per_image_table(args, map_path, images, work)
        startup_table(map_path, one_image, work, args.repeats)


if __name__ == "__main__":
    main()
