"""The matcher core side by side with an earlier commit: time per image, numpy calls per image, start-up.

1. Per image, on each real extract of ``shared/data/osm`` (Andorra, Monaco, Liechtenstein; all labels; maps built
   once into a cache outside the repository) with images as issue 8 measures them: 300 m, 60 degree field of
   view, random heading, 1 px and 0.05 degree errors, at least 6 objects. Median and p95 time per ``localize``
   call with a 300 m prior in each image ("prior"), without a prior ("no prior"; the whole map's index built once
   first, outside the timing), and with a pose prior ("pose prior": the 300 m disc, the true heading as the
   prior's ``heading_deg`` with ``heading_sigma_deg`` 5, and the true ``altitude_m``, which with the field of
   view gives the scale; :func:`case_images`), how many were localized within 2 m, and how many answers (status
   and position) are the same as the first version's: the same status and, when accepted, position, heading and
   scale within 1e-6 (``SAME_POSE``); each differing image is listed and the differences counted. A baseline
   without the pose-prior stage (5144dec) reads the "pose prior" documents as a disc and an altitude only (its
   image schema ignores the heading): its row of that case is its disc-only prior, with the altitude's scale
   range.
2. Numpy calls per image (median): calls from code outside numpy into numpy (a ufunc, an array method, a
   function of numpy's package), counted with ``sys.setprofile`` on a separate untimed pass.
3. A gauge of the machine's speed: the median time of a fixed numpy workload (:func:`gauge_ms`), taken before
   each map's timings and printed beside them, and the load average, so that figures from different machines
   (or one machine under different loads) can be compared.
4. A map tile's quad index: what an answer with a prior builds where its disc first reaches a tile
   (``localizer.TILE_SIZE_M`` square, ``TILE_PAD_M`` of neighbours around it; the tiles of 40 objects picked at
   random): median and p95 ms, this tree's and the baseline's taking turns tile by tile, and whether their trees
   and quads are identical.
5. The 1M world (``--maps ...,world1m``): the synthetic world of ``benchmarks/lost_in_space_index.py`` (copies
   of the three extracts, rotated, each object jittered by 2 m: ``synthetic_world.synthetic_world``), assembled
   and written once with its stored quad index (``mapdb index``) into the cache directory (the build time is
   printed when it is made), timed without a prior only (with one, most of a hundred scattered images would
   build their own tiles: a tile build, not the matcher).  A baseline whose stored index is of format 1 (5144dec)
   reads the same world with its own index, built once by its own code beside a link to the world in the cache
   (:func:`_world_versions`); one without any would build the world's quad index in memory (about 250 s and 14
   GB): its 1M row is left out, saying so.
6. Start-up: ``mapdb --help`` and a one-image ``mapdb query`` with a prior, from process start to the
   answer's line on the pipe (the first answer) and to exit, median of ``--repeats`` fresh processes (5 by
   default), the baseline's beside this tree's (its ``mapdb`` and CLI first on ``PYTHONPATH``).  As installed: Python's
   bytecode cache in use (kept in a temporary ``PYTHONPYCACHEPREFIX``, filled by one untimed run of each
   command, so the working tree gets no ``__pycache__``); and with ``PYTHONDONTWRITEBYTECODE=1`` and no
   cache, as in a sandbox where every process compiles mapdb's sources.  The command is the ``mapdb``
   script beside this Python (a version manager's shim on PATH, such as pyenv's, adds 0.06-0.1 s of its
   own).  ``--startup-only`` skips parts 1-5, ``--no-startup`` skips part 6.

With ``--baseline REV`` the code of that revision runs in the same process, image by image in turn with
this tree's (which goes first alternates image by image), so both meet the same load.

Run from the repository root::

    python benchmarks/matcher_core.py --baseline 5144dec
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
from _baseline import as_json, cached_maps, cli_tree, code_digest, import_baseline, shared_data  # noqa: E402

DATA = shared_data("osm")
EXTRACTS = {
    "andorra": "andorra-2021-06-22.osm.pbf",
    "monaco": "monaco-2021-12-03.osm.pbf",
    "liechtenstein": "liechtenstein-2013-08-03.osm.pbf",
}
CACHE = Path(tempfile.gettempdir()) / "mapdb-bench-matcher-core"
# The synthetic world (part 5): its objects (at least), each copy's objects jittered by this (m, 1 sigma), as
# lost_in_space_index.py's default world.
WORLD = "world1m"
WORLD_OBJECTS = 1_000_000
WORLD_JITTER_M = 2.0
ANDORRA = DATA / EXTRACTS["andorra"]


def gauge_ms(repeats: int = 7) -> float:
    """The machine's speed: median ms of a fixed numpy workload (a 256 x 256 matrix product, a sort of 200,000
    numbers and 2,000 small-array calls, the matcher's mix of arithmetic and dispatch)."""
    import numpy as np

    rng = np.random.default_rng(0)
    m = rng.random((256, 256))
    v = rng.random(200_000)
    small = rng.random(16)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        (m @ m).sum()
        np.sort(v)
        for _ in range(2_000):
            np.abs(small - 0.5).argmin()
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def count_numpy_calls(localize, image: dict, map_) -> int:
    """Calls from outside numpy into numpy made by one ``localize`` call (``sys.setprofile``)."""
    import numpy as np

    count = 0

    def in_numpy(frame) -> bool:
        return frame is not None and str(frame.f_globals.get("__name__", "")).startswith("numpy")

    def profile(frame, event, arg) -> None:
        nonlocal count
        if event == "call":
            count += in_numpy(frame) and not in_numpy(frame.f_back)
        elif event == "c_call" and not in_numpy(frame):
            owner = getattr(arg, "__self__", None)
            count += (isinstance(arg, np.ufunc) or isinstance(owner, (np.ndarray, np.generic))
                      or str(getattr(arg, "__module__", "") or "").startswith("numpy"))

    sys.setprofile(profile)
    try:
        localize(image, map_)
    finally:
        sys.setprofile(None)
    return count


def p95(values: list[float]) -> float:
    """The 95th percentile (nearest rank)."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, math.ceil(0.95 * len(ordered)) - 1)]


# Two answers are the same when their status is, and their position, heading and scale differ by at most this
# (the answers' own rounding: mm, 0.001 degree, 1e-6 m a pixel; so in effect equal as written).
SAME_POSE = 1e-6


def pose_of(answer: dict) -> tuple:
    """What :func:`same_answer` compares: accepted or not, and the pose of an accepted answer."""
    accepted = answer["status"] == "ok"
    pose = tuple(answer.get(k) for k in ("x", "y", "heading_deg", "scale_m_per_px")) if accepted else ()
    return (accepted, *pose)


def same_answer(one: tuple, other: tuple) -> bool:
    """Both accepted with poses within ``SAME_POSE``, or both rejected (:func:`pose_of`)."""
    if one[0] != other[0]:
        return False
    return all(abs(a - b) <= SAME_POSE for a, b in zip(one[1:], other[1:], strict=True))


CASES = ("prior", "no prior", "pose prior")
# The pose prior's heading error (degrees): a compass's, the image prior's default.
HEADING_SIGMA_DEG = 5.0


def case_images(case: str, images: list[dict]) -> list[dict]:
    """The images of one case (:data:`CASES`): as simulated (a 300 m disc), without their prior, or with the disc
    plus the true heading (sigma ``HEADING_SIGMA_DEG``) and the true altitude (the scale, with the field of view)."""
    if case == "prior":
        return images
    if case == "no prior":
        return [{k: v for k, v in im.items() if k != "prior"} for im in images]
    return [{**im, "altitude_m": im["truth"]["altitude_m"],
             "prior": {**im["prior"], "heading_deg": im["truth"]["heading_deg"] % 360.0,
                       "heading_sigma_deg": HEADING_SIGMA_DEG}} for im in images]


def time_images(versions: dict, map_path: Path, images: list[dict], counted: int,
                cases: tuple[str, ...] = CASES, paths: dict[str, Path] | None = None) -> dict:
    """Per version and case (:data:`CASES`): median and p95 ms per image of ``localize``, alternating
    versions image by image; localized images, answers the same as the first version's (:func:`same_answer`;
    ``differ`` lists the others: image id, this version's and the first's), and the median numpy calls an image
    over the first ``counted`` images."""
    result = {}
    for case in cases:
        subset = case_images(case, images)
        maps = {label: store.open_map((paths or {}).get(label, map_path))
                for label, (localize, store) in versions.items()}
        times: dict[str, list[float]] = {label: [] for label in versions}
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
                times[label].append((time.perf_counter() - start) * 1000.0)
                answers[label].append(pose_of(answer))
                good[label] += answer["status"] == "ok" and math.hypot(
                    answer["x"] - im["truth"]["x"], answer["y"] - im["truth"]["y"]) <= 2.0
        first = answers[next(iter(versions))]
        for label, (localize, _) in versions.items():
            calls = [count_numpy_calls(localize, im, maps[label]) for im in subset[:counted]]
            maps[label].close()
            result.setdefault(label, {})[case] = {
                "median_ms": statistics.median(times[label]), "p95_ms": p95(times[label]),
                "localized": good[label], "images": len(subset),
                "same": sum(same_answer(a, b) for a, b in zip(answers[label], first, strict=True)),
                "differ": [(im.get("id"), a, b) for im, a, b in zip(subset, answers[label], first, strict=True)
                           if not same_answer(a, b)],
                "numpy_calls": statistics.median(calls) if calls else float("nan")}
    return result


def startup_run(mapdb: str, map_path: Path, one_image: Path, cwd: Path, env: dict[str, str]) -> tuple[float, ...]:
    """Seconds of one fresh ``mapdb --help`` (to exit) and one one-image query with a prior (to its answer's
    line, and to exit)."""
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
    return help_s, answer_s, exit_s


def startup(map_path: Path, one_image: Path, cwd: Path, repeats: int, envs: dict[str, dict[str, str]]
            ) -> dict[str, dict[str, float]]:
    """Per version (``envs``: its environment), median seconds of ``mapdb --help`` (to exit) and of a one-image
    query with a prior (to its answer's line, and to exit), each process started afresh; the versions take turns
    (which goes first alternates), after one untimed run of each."""
    out: dict[str, dict[str, list[float]]] = {v: {"--help": [], "query answer": [], "query exit": []} for v in envs}
    script = Path(sys.executable).parent / "mapdb"
    mapdb = str(script) if script.exists() else "mapdb"
    order = list(envs.items())
    for run in range(repeats + 1):
        for version, env in order if run % 2 == 0 else order[::-1]:
            times = startup_run(mapdb, map_path, one_image, cwd, env)
            if run:  # the first run fills the bytecode cache
                for key, value in zip(out[version], times, strict=True):
                    out[version][key].append(value)
    return {v: {key: statistics.median(values) for key, values in t.items()} for v, t in out.items()}


def baseline_tree(rev: str, work: Path) -> Path:
    """A directory holding revision ``rev``'s ``mapdb`` and its CLI as ``mapdb_cli`` (:func:`_baseline.cli_tree`)."""
    return cli_tree(rev, work / f"startup-{rev}")


def startup_table(map_path: Path, one_image: Path, work: Path, repeats: int, baseline: str | None) -> None:
    """Print start-up with Python's bytecode cache (as installed) and without (compiling mapdb every run), this
    tree's and the baseline's side by side."""
    cached = {k: v for k, v in os.environ.items() if k not in ("PYTHONDONTWRITEBYTECODE", "PYTHONPATH")}
    cached["PYTHONPYCACHEPREFIX"] = str(work / "pycache")
    uncached = {k: v for k, v in os.environ.items() if k not in ("PYTHONPYCACHEPREFIX", "PYTHONPATH")}
    uncached["PYTHONDONTWRITEBYTECODE"] = "1"
    print(f"start-up (median of {repeats} fresh processes a version, taking turns; the query's answer is ok; "
          f"load average {os.getloadavg()[0]:.1f}):")
    print(f"  {'bytecode':<28} {'code':<17} {'--help':>7} {'first answer':>13} {'exit':>7}")
    for label, env in (("cached (as installed)", cached), ("none (compiled every run)", uncached)):
        envs = {"this tree": env}
        if baseline:
            envs[f"baseline {baseline}"] = {**env, "PYTHONPATH": str(baseline_tree(baseline, work))}
        for version, t in startup(map_path, one_image, work, repeats, envs).items():
            print(f"  {label:<28} {version:<17} {t['--help']:6.3f}s {t['query answer']:12.3f}s "
                  f"{t['query exit']:6.3f}s")


def simulated(map_path: Path, n: int, seed: int, radius: float = 300.0) -> list[dict]:
    """``n`` images over the map as issue 8 measures them, each with a prior of ``radius`` metres (300 m)."""
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.simulate import simulate_images

    with open_map(map_path) as m:
        return simulate_images(m, n, altitude=300.0, fov_deg=60.0, yaw="random", pixel_std=1.0,
                               attitude_std=0.05, min_objects=6, with_prior=radius, seed=seed)


def per_image_table(args: argparse.Namespace, maps: dict[str, Path], work: Path) -> None:
    """Print parts 1-3: per map, median and p95 ms per image of this tree (and the baseline), with and without
    a prior, numpy calls an image and the gauge taken just before."""
    from mapdb.localize import localizer as tree_localize
    from mapdb.mapfile import reader as tree_reader

    versions = {"this tree": (tree_localize.localize, tree_reader)}
    if args.baseline:
        old = import_baseline(args.baseline, work)
        versions[f"baseline {args.baseline}"] = (old.localize, import_baseline(args.baseline, work, "store"))
    print(f"{args.n} images a map: 300 m, 60 deg, random heading, 1 px, 0.05 deg, >= 6 objects, prior "
          f"{args.prior_radius:g} m; "
          f"pose prior: the disc, the true heading (sigma {HEADING_SIGMA_DEG:g} deg) and altitude; numpy calls over "
          f"the first {min(args.count, args.n)}; load average {os.getloadavg()[0]:.1f}")
    if args.baseline and not _has_module(args.baseline, work, "match.pose_prior"):
        print(f"  (baseline {args.baseline} has no pose-prior stage: its \"pose prior\" row is its disc-only prior, "
              "the same documents with the heading ignored and the altitude's scale range applied)")
    print(f"  {'map':<14} {'code':<17} {'case':<10} {'median ms':>9} {'p95 ms':>8} {'localized':>10} "
          f"{'same':>8} {'numpy calls':>11} {'gauge ms':>8}")
    for name, path in maps.items():
        images = simulated(path, args.n, args.seed, args.prior_radius)
        gauge = gauge_ms()
        cases, here, paths = CASES, versions, None
        if name == WORLD:
            cases, here, paths = ("no prior",), *_world_versions(versions, args.baseline, work, path)
        results = time_images(here, path, images, args.count, cases, paths)
        for label, res in results.items():
            for case, r in res.items():
                print(f"  {name:<14} {label:<17} {case:<10} {r['median_ms']:9.2f} {r['p95_ms']:8.2f} "
                      f"{r['localized']:5d}/{r['images']:<4d} {r['same']:4d}/{r['images']:<4d}"
                      f"{r['numpy_calls']:11.0f} {gauge:8.1f}")
        for label, res in results.items():
            for case, r in res.items():
                for image_id, mine, theirs in r["differ"]:
                    print(f"  {name:<14} {label}, {case}: {image_id} differs: {_said(mine)} against {_said(theirs)}")
        _ratios(name, results, args.baseline if len(here) > 1 else None)
    print(f"  load average after: {os.getloadavg()[0]:.1f}; gauge {gauge_ms():.1f} ms")


def _has_module(rev: str, work: Path, module: str) -> bool:
    """Whether revision ``rev``'s mapdb has ``mapdb.<module>`` (imported, as the baseline is)."""
    try:
        import_baseline(rev, work, module)
    except ImportError:
        return False
    return True


def _world_versions(versions: dict, baseline: str | None, work: Path, world: Path) -> tuple[dict, dict]:
    """The versions timed on the 1M world and the world's path for each: a baseline whose stored quad index is
    of an older format (``mapdb.match.stored_index``, format 1, as 5144dec's) gets the same world with its own
    index, built once by its own ``build_index`` beside a link to the world in the cache (the time taken
    printed); a baseline without any is left out (it would build the world's in memory: about 250 s and 14 GB)."""
    if baseline is None or _has_module(baseline, work, "match.index.stored"):
        return versions, {}
    if not _has_module(baseline, work, "match.stored_index"):
        print(f"  {WORLD}: baseline {baseline} has no stored quad index (it would build the world's in memory, "
              "about 250 s and 14 GB): this tree only")
        return {"this tree": versions["this tree"]}, {}
    own = world.parent / f"{world.stem}-index-of-{baseline}" / world.name
    index = own.with_name(own.name + ".qidx")
    if not index.exists():
        own.parent.mkdir(parents=True, exist_ok=True)
        if not own.exists():
            own.symlink_to(world)
        start = time.perf_counter()
        partial = own.with_name(own.name + ".partial")
        import_baseline(baseline, work, "match.index_build").build_index(own, partial)
        partial.rename(index)
        print(f"  {WORLD}: baseline {baseline}'s own stored index (format 1) built in "
              f"{time.perf_counter() - start:.0f} s, {index.stat().st_size / 1e6:.0f} MB", flush=True)
    return versions, {f"baseline {baseline}": own}


def world_map(cache: Path) -> Path:
    """The 1M world (part 5) and its stored quad index, assembled, written and indexed once into ``cache`` (under
    the digest of the code that writes maps); the time taken is printed when they are made."""
    import synthetic_world

    from mapdb.mapfile.writer import write_map
    from mapdb.match.index.layout import index_path
    from mapdb.match.index.stored import build_index

    path = cache / f"{WORLD}.{code_digest()}.mapdb"
    if not path.exists() or not index_path(path).exists():
        start = time.perf_counter()
        cache.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial.mapdb")
        write_map(partial, synthetic_world.synthetic_world(synthetic_world.extract_maps(), WORLD_OBJECTS, seed=0,
                                                           jitter_m=WORLD_JITTER_M))
        written = time.perf_counter() - start
        build_index(partial, index_path(path))
        partial.rename(path)
        print(f"{path.name}: assembled and written in {written:.0f} s, its quad index built in "
              f"{time.perf_counter() - start - written:.0f} s", flush=True)
    return path


def _ratios(name: str, results: dict, baseline: str | None) -> None:
    """Print the cases' ratios in this tree, and this tree's to the baseline's per case."""
    tree = results["this tree"]
    for one, other in (("prior", "no prior"), ("pose prior", "prior"), ("pose prior", "no prior")):
        if one not in tree or other not in tree:
            continue
        print(f"  {name:<14} this tree, {one} / {other}: median {tree[one]['median_ms'] / tree[other]['median_ms']:.2f}"
              f", p95 {tree[one]['p95_ms'] / tree[other]['p95_ms']:.2f}")
    if not baseline:
        return
    base = results[f"baseline {baseline}"]
    for case in tree:
        said = " (the baseline's: disc only)" if case == "pose prior" else ""
        print(f"  {name:<14} {case}: answers differing from the baseline's{said}: "
              f"{len(base[case]['differ'])} of {base[case]['images']}")
        print(f"  {name:<14} {case}: this tree / baseline{said}: median "
              f"{tree[case]['median_ms'] / base[case]['median_ms']:.2f}, "
              f"p95 {tree[case]['p95_ms'] / base[case]['p95_ms']:.2f}")


def tile_table(args: argparse.Namespace, maps: dict[str, Path], work: Path, tiles: int = 40) -> None:
    """Print part 4: per map, median and p95 ms to build a map tile's quad index (with positions, as an answer
    with a prior does), this tree's and the baseline's taking turns; identical when every tree and quad is."""
    import numpy as np

    from mapdb.localize.localizer import TILE_PAD_M, TILE_SIZE_M
    from mapdb.mapfile.reader import open_map
    from mapdb.match import quads as tree_quads

    versions = {"this tree": tree_quads.QuadIndex}
    if args.baseline:
        versions[f"baseline {args.baseline}"] = import_baseline(args.baseline, work, "match.quads").QuadIndex
    print(f"quad index of a map tile ({TILE_SIZE_M:.0f} m, {TILE_PAD_M:.0f} m of neighbours; {tiles} tiles a map "
          f"under random objects; load average {os.getloadavg()[0]:.1f}):")
    for name, path in maps.items():
        rng = np.random.default_rng(args.seed)
        with open_map(path) as m:
            everything = m.all()
            picked = rng.integers(0, len(everything), tiles)
            boxes = [(np.floor(everything.x[i] / TILE_SIZE_M) * TILE_SIZE_M,
                      np.floor(everything.y[i] / TILE_SIZE_M) * TILE_SIZE_M) for i in picked]
            parts = [(m.query_bbox(x0 - TILE_PAD_M, y0 - TILE_PAD_M, x0 + TILE_SIZE_M + TILE_PAD_M,
                                   y0 + TILE_SIZE_M + TILE_PAD_M), x0, y0) for x0, y0 in boxes]
        times: dict[str, list[float]] = {label: [] for label in versions}
        built: dict[str, list] = {label: [] for label in versions}
        order = list(versions.items())
        for j, (objects, x0, y0) in enumerate(parts):
            anchors = ((objects.x >= x0) & (objects.x < x0 + TILE_SIZE_M) & (objects.y >= y0)
                       & (objects.y < y0 + TILE_SIZE_M))
            for label, cls in order if j % 2 == 0 else order[::-1]:
                start = time.perf_counter()
                index = cls(objects, 8, anchors=anchors, positions=True)
                times[label].append((time.perf_counter() - start) * 1000.0)
                built[label].append((index.quad_z, None if index.tree is None else index.tree.data))
        first = built["this tree"]
        for label in versions:
            same = all(np.array_equal(a[0], b[0]) and (a[1] is None) == (b[1] is None)
                       and (a[1] is None or np.array_equal(a[1], b[1]))
                       for a, b in zip(built[label], first, strict=True))
            print(f"  {name:<14} {label:<17} median {statistics.median(times[label]):7.2f} ms  p95 "
                  f"{p95(times[label]):7.2f} ms  identical to this tree's: {same}")


def _said(pose: tuple) -> str:
    """A :func:`pose_of` tuple, short."""
    return "rejected" if not pose[0] else "ok at ({:.3f}, {:.3f}) heading {:.3f} scale {:.6f}".format(*pose[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=300, help="images a map")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--baseline", metavar="REV", help="also run the matcher of this git revision")
    parser.add_argument("--maps", default=",".join(EXTRACTS),
                        help=f"maps measured (comma separated): the extracts' names, {WORLD} (the 1M world)")
    parser.add_argument("--prior-radius", type=float, default=300.0,
                        help="the priors' radius, metres (their centres drawn within it of the truth)")
    parser.add_argument("--count", type=int, default=20, help="images whose numpy calls are counted")
    parser.add_argument("--repeats", type=int, default=5, help="runs of each start-up measurement")
    parser.add_argument("--startup-only", action="store_true", help="measure start-up only (not per image)")
    parser.add_argument("--no-startup", action="store_true", help="measure per image only (not start-up)")
    args = parser.parse_args()
    names = [n for n in args.maps.split(",") if n]
    unknown = [n for n in names if n not in EXTRACTS and n != WORLD]
    if unknown:
        parser.error(f"unknown map {unknown[0]!r}; choose from {', '.join([*EXTRACTS, WORLD])}")
    needed = set(EXTRACTS.values()) if WORLD in names else {EXTRACTS[n] for n in names}
    if not all((DATA / pbf).exists() for pbf in needed):
        sys.exit(f"skipped: the extracts are not all in {DATA}")
    built = cached_maps({n: EXTRACTS[n] for n in names if n in EXTRACTS}, DATA, CACHE)
    maps = {n: world_map(CACHE) if n == WORLD else built[n] for n in names}
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; gauge (fixed numpy "
          f"workload) {gauge_ms():.1f} ms")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if not args.startup_only:
            per_image_table(args, maps, work)
            tile_table(args, maps, work)
        if not args.no_startup:
            one_image = work / "one.jsonl"
            one_image.write_text(json.dumps(simulated(maps[names[0]], 1, args.seed)[0]) + "\n")
            startup_table(maps[names[0]], one_image, work, args.repeats, args.baseline)


if __name__ == "__main__":
    main()
