"""The stored lost-in-space quad index at country scale: build, open, lookups, against Andorra and QuadIndex.

For Andorra (built from ``../shared/data/osm``) and synthetic worlds of 1M and 5M objects assembled
from copies of the three extracts (``benchmarks/synthetic_world.py``):

* **build**: ``mapdb.match.index.stored.build_index`` in a child process: wall time, peak memory (the sum of
  the resident sets of the process and its workers, sampled every 0.1 s, and the largest single
  resident set from ``getrusage``), file size;
* **open**: a fresh process opens the map and its index and answers the lookups of one image, with
  the two files dropped from the page cache first (``posix_fadvise DONTNEED``): the time from
  ``open_map`` to the answer, and from process start;
* **lookups**: the quads of ``--images`` images simulated over the map (random heading, 60-400 m,
  35-60 degrees, 1 px error, at least 6 objects) are looked up as the fast matcher forms them
  (``image_queries`` below: each image quad in the frames and orderings that noise could make
  canonical, radius from a 1.5 px error, at most 16 hits): median time per image, and how often the
  true map quad is among the hits;
* **localize**: the same images answered whole, as a user meets them (``Localizer.localize``, no prior,
  with the map's stored index: lookups, verification, decision, refinement): median per image the first
  time and in the steady state, images accepted and accepted wrongly, each map's median relative to
  Andorra's; and a fresh process's first answer (map and index dropped from the page cache, from
  ``open_map`` to the answer; a big map's objects read page by page where the answer needs them,
  :mod:`mapdb.match.mapobjects.paged_objects`), median and max of ``--first-answers`` processes and images
  (with ``--baseline REV``, that revision's first answers too, in processes alternating with this tree's);
* **QuadIndex** (the in-memory cKDTree index) on Andorra and, with ``--quadindex-world``, on the 1M
  world (about 250 s and 14 GB: run once): build time and memory, and the same lookups.

Run from the repository root (about 15 minutes with the 1M QuadIndex)::

    nice python benchmarks/lost_in_space_index.py
    nice python benchmarks/lost_in_space_index.py --worlds 1000000 --images 50   # quicker
    nice python benchmarks/lost_in_space_index.py --lookups-only --worlds 5000000 --jitter 2 10   # two worlds

``--jitter 2`` keeps each copy close enough to its original that a lookup of a place also finds its copies
(near-copies); ``--jitter 10`` leaves no near-copies, so the two side by side tell what a world's size costs
from what its repeats cost.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import resource
import shutil
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import synthetic_world as _world  # noqa: E402
from _baseline import as_json, import_baseline  # noqa: E402
from _lis_children import BUILD, FIRST_ANSWER, OPEN, QUADINDEX, _child  # noqa: E402
from synthetic_world import extract_maps, synthetic_world  # noqa: E402

from mapdb.camera import image_plane  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.mapfile.writer import write_map  # noqa: E402
from mapdb.match.fast import FastOptions  # noqa: E402
from mapdb.match.hypotheses import _quad_keys  # noqa: E402
from mapdb.match.quads import neighbour_quads  # noqa: E402

SIGMA_PX = 1.5
TOLERANCE = 2.0
MAX_RADIUS = 0.3
HITS = 16
REPEATS = 3
FIRST_ANSWERS = 5  # fresh processes, one image each, for the first answer
STATE_OBJECTS = 20_000_000  # --state: a state's worth of objects (issue 31: "Lost in space on a state")
STATE_JITTER = 2.0
IMAGE_NEIGHBOURS = 5


def image_queries(z: np.ndarray, label: np.ndarray, neighbours: int = IMAGE_NEIGHBOURS,
                  sigma_px: float = SIGMA_PX) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lookups of an image's quads as ``mapdb.match.hypotheses.round_hypotheses`` forms them.

    Each image quad (every object with triples of its ``neighbours`` nearest) is looked up in its
    longest pair's frame and, when the second longest is within noise of it, in that one too; in each
    frame, in the orderings of ``A, B`` and ``C, D`` that noise could make canonical.  The radius is
    ``TOLERANCE`` times the invariants' predicted standard error for a ``sigma_px`` pixel error.

    Returns
    -------
    inv : (m, 4) invariants, labels : (m, 4) label codes, radius : (m,), ids : (m, 4) image object ids
        (``A, B, C, D`` of each lookup).
    """
    quads = neighbour_quads(np.column_stack([z.real, z.imag]), neighbours)
    empty = np.zeros((0, 4)), np.zeros((0, 4), np.int64), np.zeros(0), np.zeros((0, 4), np.int64)
    if not len(quads):
        return empty
    # The matcher's own arithmetic (frames, orderings near the canonical one, radii), not a copy of it.
    keys = _quad_keys(z[quads], FastOptions(tolerance_factor=TOLERANCE, max_invariant_radius=MAX_RADIUS), sigma_px)
    if keys is None:
        return empty
    row, order, inv, radius = keys
    ids = np.take_along_axis(quads[row], order, axis=1)
    return inv, label[ids], radius, ids


def _images(map_path: Path, n: int, seed: int) -> list[dict]:
    from mapdb.simulation.simulate import simulate_images

    with open_map(map_path) as m:
        return simulate_images(m, n, altitude=(60.0, 400.0), fov_deg=(35.0, 60.0), yaw="random",
                               attitude_std=0.05, pixel_std=1.0, min_objects=6, seed=seed)


def _image_arrays(image: dict, labels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    code = {name: i for i, name in enumerate(labels)}
    objs = image["objects"]
    z = image_plane([o["x"] for o in objs], [o["y"] for o in objs], image["width"], image["height"])
    label = np.array([code[o["label"]] for o in objs], np.int64)
    return z, label, np.array(image["truth"]["map_index"], np.int64)


def _stored_lookups(map_path: Path, images: list[dict]) -> dict:
    """Time the stored index's lookups of every image, twice; how often the true quad is among the hits.

    The first pass reads and checksums the index blocks the images need (the files were just written,
    so they are in the page cache); then ``REPEATS`` passes, the steady state of a long-running matcher,
    of which each image keeps its fastest (the machine is shared: the least disturbed measurement).
    """
    from mapdb.match.index.stored import StoredQuadIndex

    with open_map(map_path) as m, StoredQuadIndex.for_map(m) as ix:
        labels = tuple(m.labels)
        queries = [image_queries(*_image_arrays(image, labels)[:2]) for image in images]
        result = {"found": 0, "true": 0, "queries": 0, "hits": 0}
        passes, cpu = [], []
        for run in range(1 + REPEATS):
            times, cpu_times = [], []
            for image, (inv, lab, radius, ids) in zip(images, queries):
                start, start_cpu = time.perf_counter(), time.process_time()
                row, hit = ix.lookup(inv, lab, radius, HITS)
                times.append((time.perf_counter() - start) * 1000.0)
                cpu_times.append((time.process_time() - start_cpu) * 1000.0)
                if run == 0:
                    f, t = _true_found(ids, _image_arrays(image, labels)[2], row, hit)
                    result["found"] += f
                    result["true"] += t
                    result["queries"] += len(inv)
                    result["hits"] += len(row)
            passes.append(times)
            cpu.append(cpu_times)
        result["first_ms"] = passes[0]
        result["ms"] = np.min(passes[1:], axis=0).tolist()
        result["cpu_ms"] = np.min(cpu[1:], axis=0).tolist()
    return result


def _localize_times(map_path: Path, images: list[dict], baseline: tuple[str, Path, Path] | None = None) -> dict:
    """Whole lost-in-space answers (``Localizer.localize``, no prior) with the map's stored index, per image.

    What a user meets, lookups, verification, decision and refinement together.  The map's whole-map
    indexes (the stored quad index, opened; the object index, built from ``MetaMap.all()``) are made
    once, before the timing (``index_s``); then each image is localized once (``first_ms``: the index
    blocks it needs read and checksummed the first time), and ``REPEATS`` more passes of which each
    image keeps its fastest (``ms``, the steady state of a long-running process).  ``ok``: images
    accepted; ``wrong``: accepted more than 5 m from the truth.  With ``baseline`` (a revision, the
    work directory :func:`_baseline.import_baseline` extracts it into, and the map beside which that revision's
    own index was built), that revision's localizer answers each image right after this tree's, with its own
    indexes: ``baseline_cpu_ms``, ``baseline_ms``, ``baseline_ok``, ``baseline_within_2m`` and
    ``baseline_wrong``, and ``same``, the images both answered alike.
    """
    from mapdb.localize.localizer import Localizer, StoredQuads

    versions = {"tree": (Localizer, open_map)}
    paths = {"tree": map_path}
    if baseline is not None:
        versions["baseline"] = (import_baseline(*baseline[:2]).Localizer,
                                import_baseline(*baseline[:2], "store").open_map)
        paths["baseline"] = baseline[2]
    maps = {name: open_map_(paths[name]) for name, (_, open_map_) in versions.items()}
    try:
        locs = {name: make(maps[name]) for name, (make, _) in versions.items()}
        start = time.perf_counter()
        # Point images only (``masks=False``): the view with blocks folded in, which mask images need, would build
        # an in-memory quad index of the whole map (a world of 1M objects: over 20 GB, killed by the kernel).
        _, quads = locs["tree"].whole_map_indexes(masks=False)
        # a big map's whole object index, built in the background, serves the timing
        locs["tree"].whole_map_ready(masks=False)
        index_s = time.perf_counter() - start
        if not isinstance(quads, StoredQuads):
            raise RuntimeError(f"{map_path}: the localizer does not use a stored index")
        for name in list(locs)[1:]:
            for method in ("whole_map_indexes", "whole_map_ready"):  # as far as that revision has them
                whole = getattr(locs[name], method, lambda: None)
                whole(**({"masks": False} if "masks" in inspect.signature(whole).parameters else {}))
        passes = {name: [] for name in locs}
        cpu = {name: [] for name in locs}
        answers: dict[str, list] = {name: [] for name in locs}
        for run in range(1 + REPEATS):
            for name in locs:
                passes[name].append([])
                cpu[name].append([])
            for image in images:
                for name, loc in locs.items():  # image by image in turn: the same load on both versions
                    start, start_cpu = time.perf_counter(), time.process_time()
                    answer = as_json(loc.localize(image))
                    passes[name][-1].append((time.perf_counter() - start) * 1000.0)
                    cpu[name][-1].append((time.process_time() - start_cpu) * 1000.0)
                    if run == 0:
                        answers[name].append(answer)
    finally:
        for m in maps.values():
            m.close()
    result = {"first_ms": passes["tree"][0], "ms": np.min(passes["tree"][1:], axis=0).tolist(),
              "index_s": index_s, "images": len(images)}
    for name in locs:
        prefix = "" if name == "tree" else "baseline_"
        error = [math.hypot(a["x"] - im["truth"]["x"], a["y"] - im["truth"]["y"])
                 for a, im in zip(answers[name], images) if a["status"] == "ok"]
        result.update({prefix + "cpu_ms": np.min(cpu[name][1:], axis=0).tolist(), prefix + "ok": len(error),
                       prefix + "wrong": sum(e > 5.0 for e in error),
                       prefix + "within_2m": sum(e <= 2.0 for e in error),
                       prefix + "ms": np.min(passes[name][1:], axis=0).tolist()})
    result["answers"] = [[a["status"], a.get("x"), a.get("y")] for a in answers["tree"]]
    if "baseline" in answers:
        result["same"] = sum(a["status"] == b["status"] and a.get("x") == b.get("x") and a.get("y") == b.get("y")
                             for a, b in zip(answers["tree"], answers["baseline"]))
    return result


def _true_found(ids: np.ndarray, truth: np.ndarray, row: np.ndarray, hit_ids: np.ndarray) -> tuple[int, int]:
    """Image quads (all four objects real) whose true map quad is among their lookups' hits; and their number."""
    true_map = truth[ids]
    real = (true_map >= 0).all(axis=1)
    quad_of = {}
    for r in np.flatnonzero(real):
        quad_of.setdefault(tuple(sorted(ids[r].tolist())), []).append(r)
    hits_by_row: dict[int, set] = {}
    for r, h in zip(row.tolist(), np.sort(hit_ids, axis=1).tolist()):
        hits_by_row.setdefault(r, set()).add(tuple(h))
    found = 0
    for rows in quad_of.values():
        target = tuple(sorted(true_map[rows[0]].tolist()))
        found += any(target in hits_by_row.get(r, ()) for r in rows)
    return found, len(quad_of)


def _quadindex_lookups(map_path: Path, images: list[dict]) -> dict:
    """QuadIndex (in memory, the kernel's k-d tree) on the same map and lookups: build time and memory, lookup
    times."""
    from mapdb.match.fast import QuadIndex

    with open_map(map_path) as m:
        objects = m.all()
    labels = tuple(objects.labels)
    start = time.perf_counter()
    qi = QuadIndex(objects, 8)
    build_s = time.perf_counter() - start
    z_map = objects.x + 1j * objects.y
    position = {complex(v): i for i, v in enumerate(z_map.tolist())} if len(z_map) < 2_000_000 else None
    times, cpu_times, found, n_true, n_queries, n_hits = [], [], 0, 0, 0, 0
    for image in images:
        z, label, truth = _image_arrays(image, labels)
        inv, lab, radius, ids = image_queries(z, label)
        best = best_cpu = math.inf
        for _ in range(REPEATS):
            start, start_cpu = time.perf_counter(), time.process_time()
            # The index's own lookup (the kernel's tree since the cKDTree left it): each hit's query row and points.
            q_row, map_z = qi.lookup(inv, lab, radius, min(HITS, qi.n_quads))
            best = min(best, (time.perf_counter() - start) * 1000.0)
            best_cpu = min(best_cpu, (time.process_time() - start_cpu) * 1000.0)
        times.append(best)
        cpu_times.append(best_cpu)
        hit_ids = np.vectorize(lambda v: position.get(complex(v), -1))(map_z) if len(map_z) and position else \
            np.zeros((0, 4), np.int64)
        f, t = _true_found(ids, truth, q_row, hit_ids)
        found, n_true = found + f, n_true + t
        n_queries, n_hits = n_queries + len(inv), n_hits + len(q_row)
    return {"ms": times, "cpu_ms": cpu_times, "found": found, "true": n_true, "queries": n_queries, "hits": n_hits,
            "build_s": build_s, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worlds", type=int, nargs="*", default=[1_000_000, 5_000_000], help="world sizes")
    parser.add_argument("--state", action="store_true",
                        help=f"also the {STATE_OBJECTS / 1e6:g}M-object world (jittered by {STATE_JITTER:g} m), "
                             "a state's worth of objects: no QuadIndex, no baseline build")
    parser.add_argument("--images", type=int, default=100, help="images per map")
    parser.add_argument("--workers", type=int, default=2, help="processes building an index")
    parser.add_argument("--quadindex-world", type=int, default=1_000_000,
                        help="world size also indexed by the in-memory QuadIndex (0: none)")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "mapdb-lis-bench")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--lookups-only", action="store_true",
                        help="reuse the indexes already built (no builds, no QuadIndex): re-measure lookups")
    parser.add_argument("--jitter", type=float, nargs="+", default=[0.0],
                        help="worlds of copies with every object displaced by this (m, 1 sigma): distinct places;"
                             " several values: a world of each size for each, measured side by side")
    parser.add_argument("--baseline", metavar="REV",
                        help="also time this git revision's first answers (processes alternating with this tree's)")
    parser.add_argument("--first-answers", type=int, default=FIRST_ANSWERS,
                        help="fresh processes (one image each) timed for the first answer")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if not _world.DATA.is_dir():  # a worktree beside the repository: the shared data's absolute place
        _world.DATA = Path("/work/shared/data/osm")
    if not _world.DATA.is_dir():
        print(f"no shared data at {_world.DATA}: nothing to measure", file=sys.stderr)
        return 1
    args.workdir.mkdir(parents=True, exist_ok=True)
    maps, quadindex_path, state_path = _maps(args)
    rows, whole, index_rows, states = [], [], [], []
    for name, path in maps.items():
        baseline = args.baseline if path != state_path else None  # the state's world: this tree's index only
        row, located, index_row = _measure(name, path, args, baseline, len(rows) % 2 == 0)
        rows.append(row)
        whole.append((name, located))
        states.append((name, row[1], row[3], located))
        if index_row is not None:
            index_rows.append(index_row)
        if name == "Andorra" or (not args.lookups_only and path == quadindex_path):
            rows.append(_quadindex_row(name, path, args, row))
    _lookup_table(rows)
    _whole_table(whole)
    _index_table(index_rows, args.baseline)
    _state_table(states)
    return 0


def _maps(args: argparse.Namespace) -> tuple[dict[str, Path], Path | None, Path | None]:
    """Andorra and the worlds to measure (assembled and written once into the work directory), the world the
    in-memory QuadIndex indexes too, and the state's world (``--state``)."""
    extracts = extract_maps()
    # Andorra's map copied into the work directory: its index is built beside it, not in the shared cache
    # (where another run's index of another format may be).
    andorra = args.workdir / extracts[0].name
    if not andorra.exists():
        shutil.copyfile(extracts[0], andorra)
    maps = {"Andorra": andorra}
    world_path: dict[int, Path] = {}
    worlds = [(n, jitter) for n in args.worlds for jitter in args.jitter]
    if args.state and (STATE_OBJECTS, STATE_JITTER) not in worlds:
        worlds.append((STATE_OBJECTS, STATE_JITTER))
    for n, jitter in worlds:
        path = args.workdir / (f"world-{n}.mapdb" if not jitter else f"world-{n}-jitter{jitter:g}.mapdb")
        if not path.exists():
            start = time.perf_counter()
            # Rotated copies, every object jittered: no window of the world repeats another exactly.
            write_map(path, synthetic_world(extracts, n, seed=0, jitter_m=jitter))
            print(f"{path.name}: assembled and written in {time.perf_counter() - start:.0f} s", flush=True)
        maps[f"world {n / 1e6:g}M" + (f" jitter {jitter:g} m" if jitter else "")] = path
        world_path.setdefault(n, path)
    state = world_path.get(STATE_OBJECTS) if args.state else None
    return maps, world_path.get(args.quadindex_world) if args.quadindex_world else None, state


def _measure(name: str, path: Path, args: argparse.Namespace, baseline: str | None,
             tree_first: bool) -> tuple[tuple, dict, tuple | None]:
    """One map: its index built (this tree's and the baseline's, in alternating order), fresh first answers,
    lookups and whole answers; its row of the lookup table, its whole answers, its row of the index table."""
    with open_map(path) as m:
        n_objects, map_bytes = len(m), path.stat().st_size
    # With a baseline, its own index beside a link to the same map (this tree's may be another format).
    base_path = _baseline_map(path, args.workdir) if baseline else None
    builds = {}
    for who in (("tree", "baseline") if tree_first else ("baseline", "tree")):
        if who == "baseline" and base_path is None:
            continue
        target = path if who == "tree" else base_path
        if args.lookups_only:
            builds[who] = _index_facts(target)
        else:
            extra = () if who == "tree" else (baseline, str(args.workdir))
            builds[who] = _child(BUILD, str(target), str(args.workers), *extra)
        builds[who]["bytes"] = Path(str(target) + ".qidx").stat().st_size
    build = builds["tree"]
    images = _images(path, args.images, args.seed)
    first = _child(OPEN, str(path), json.dumps(images[0]))
    located = _first_answers(name, path, images, args, baseline, base_path)
    look = _stored_lookups(path, images)
    located.update(_localize_times(path, images, (baseline, args.workdir, base_path) if base_path else None))
    print(f"{name}: {n_objects} objects, index {build['bytes'] / 2**20:.0f} MiB ({build['quads']} quads) built "
          f"in {build.get('wall_s', math.nan):.1f} s, peak {build.get('peak_pss_mb', math.nan):.0f} MB; open+first "
          f"answer {first['open_to_answer_s'] * 1000:.0f} ms; lookups median "
          f"{statistics.median(look['ms']):.2f} ms; localize median {statistics.median(located['ms']):.2f} ms"
          f" ({statistics.median(located['first_ms']):.2f} ms the first time)", flush=True)
    index_row = (name, n_objects, builds["tree"], builds["baseline"]) if base_path is not None else None
    return (name, n_objects, map_bytes, build, first, look), located, index_row


def _first_answers(name: str, path: Path, images: list[dict], args: argparse.Namespace, baseline: str | None,
                   base_path: Path | None) -> dict:
    """Fresh processes' first answers (one image each), with a baseline's processes alternating image by image
    (the same load on both)."""
    mine, theirs = [], []
    for image in images[: args.first_answers]:
        mine.append(_child(FIRST_ANSWER, str(path), json.dumps(image), "", "")["open_to_answer_s"])
        if base_path is not None:
            theirs.append(_child(FIRST_ANSWER, str(base_path), json.dumps(image), str(baseline),
                                 str(args.workdir))["open_to_answer_s"])
    if theirs:
        print(f"{name}: first answers (s), this tree {[round(t, 2) for t in mine]} median "
              f"{statistics.median(mine):.2f} max {max(mine):.2f}; baseline {baseline} "
              f"{[round(t, 2) for t in theirs]} median {statistics.median(theirs):.2f} max {max(theirs):.2f}",
              flush=True)
    return {"first_answer_s": statistics.median(mine), "first_answer_max_s": max(mine), "first_answers_s": mine}


def _quadindex_row(name: str, path: Path, args: argparse.Namespace, row: tuple) -> tuple:
    """The in-memory QuadIndex on the same map and images, in a child process."""
    images = _images(path, args.images, args.seed)
    images_file = args.workdir / f"{path.stem}-images.json"
    images_file.write_text(json.dumps(images))
    qi = _child(QUADINDEX, str(path), str(images_file))
    print(f"{name} QuadIndex: built in {qi['build_s']:.0f} s, peak {qi['peak_pss_mb']:.0f} MB; lookups "
          f"median {statistics.median(qi['ms']):.2f} ms", flush=True)
    return (f"{name} QuadIndex", row[1], row[2], None, None, qi)


def _lookup_table(rows: list) -> None:
    """The lookups of every map's images: index, build, open, lookup times, how often the true quad is found."""
    print()
    print(f"{'map':<28} {'objects':>9} {'quads':>11} {'index MiB':>9} {'B/obj':>6} {'build s':>8} {'PSS MB':>7}"
          f" {'RSS MB':>7} {'open+1st ms':>11} {'1st pass':>8} {'lookup ms':>9} {'p95 ms':>7} {'CPU ms':>7}"
          f" {'queries':>7} {'hits':>5} {'true found':>10}")
    for name, n_objects, _, build, first, look in rows:
        mem = build if build is not None else look
        if build is not None:
            cols = (f"{build['quads']:>11} {build['bytes'] / 2**20:>9.0f} {build['bytes'] / n_objects:>6.0f}"
                    f" {build.get('wall_s', math.nan):>8.1f}")
        else:
            cols = f"{'-':>11} {'-':>9} {'-':>6} {look['build_s']:>8.1f}"
        cols += f" {mem.get('peak_pss_mb', math.nan):>7.0f} {mem.get('peak_rss_mb', math.nan):>7.0f}"
        cols += f" {first['open_to_answer_s'] * 1000:>11.0f}" if first is not None else f" {'-':>11}"
        cols += f" {statistics.median(look['first_ms']):>8.2f}" if "first_ms" in look else f" {'-':>8}"
        print(f"{name:<28} {n_objects:>9} {cols} {statistics.median(look['ms']):>9.2f}"
              f" {np.percentile(look['ms'], 95):>7.2f} {statistics.median(look['cpu_ms']):>7.2f}"
              f" {look['queries'] / len(look['ms']):>7.0f} {look['hits'] / len(look['ms']):>5.0f}"
              f" {look['found'] / max(look['true'], 1):>10.1%}")
    print("\nmedian lookup CPU time per image relative to Andorra's with the same index: " + ", ".join(
        f"{r[0]} {statistics.median(r[5]['cpu_ms']) / statistics.median(a[5]['cpu_ms']):.2f}x"
        for r in rows for a in rows[:2] if r[0] != a[0] and (r[3] is None) == (a[3] is None)))
    print("build: wall time in a child process; PSS MB: peak proportional set size of the child and its workers"
          " (shared pages divided among them), RSS MB: peak sum of their resident sets (shared pages counted per"
          " process); open+1st: fresh process, map and index dropped from the page cache, open_map to the first"
          " image's lookups answered; 1st pass: median per image the first time the images are looked up"
          " (index blocks read and checksummed), lookup ms and p95: the fastest of 3 more passes, CPU ms: the same"
          " in CPU time (process_time: what other processes on the machine do not inflate);"
          " queries: lookups per image, hits: per image; true"
          " found: image quads of real objects whose true map quad is among the hits")


def _state_table(states: list[tuple[str, int, dict, dict]]) -> None:
    """Lost in space on a state: every map's recall, wrong answers, time per image, first answer, index and build,
    side by side (with ``--state``, the state's world beside Andorra)."""
    print(f"\n{'lost in space':<28} {'objects':>10} {'<=2 m':>7} {'wrong':>5} {'median ms':>9} {'p99 ms':>7}"
          f" {'1st answer s (max)':>18} {'index MiB':>9} {'B/obj':>6} {'build s':>8} {'PSS MB':>7} {'RSS MB':>7}")
    for name, n, build, r in states:
        print(f"{name:<28} {n:>10} {r['within_2m']:>3}/{r['images']:<3} {r['wrong']:>5}"
              f" {statistics.median(r['ms']):>9.2f} {np.percentile(r['ms'], 99):>7.2f}"
              f" {r['first_answer_s']:>11.2f} ({r['first_answer_max_s']:4.2f}) {build['bytes'] / 2**20:>9.0f}"
              f" {build['bytes'] / n:>6.1f} {build.get('wall_s', math.nan):>8.0f}"
              f" {build.get('peak_pss_mb', math.nan):>7.0f} {build.get('peak_rss_mb', math.nan):>7.0f}")
    print("<=2 m: images localized within 2 m of the truth (Localizer.localize, no prior, the map's stored index);"
          " wrong: accepted more than 5 m away; median and p99: per image, the fastest of 3 passes; 1st answer:"
          " fresh processes, map and index dropped from the page cache; index: its file; build: wall time and peak"
          " memory of the building process and its workers")


def _baseline_map(path: Path, workdir: Path) -> Path:
    """A hard link to the map (a copy where links fail) in ``workdir/baseline-maps``, for the baseline's index."""
    base = workdir / "baseline-maps" / path.name
    base.parent.mkdir(parents=True, exist_ok=True)
    if base.exists() and base.stat().st_ino != path.stat().st_ino:
        base.unlink()
    if not base.exists():
        try:
            os.link(path, base)
        except OSError:
            shutil.copyfile(path, base)
    return base


def _index_facts(map_path: Path) -> dict:
    """Quads of an index already built (any format version: its JSON header read from the prefix)."""
    with open(str(map_path) + ".qidx", "rb") as f:
        _, _, _, h_off, h_len, _ = struct.unpack("<8sHHQII", f.read(28))
        f.seek(h_off)
        return {"quads": json.loads(f.read(h_len))["quads"]}


def _index_table(rows: list, baseline: str | None) -> None:
    """This tree's index beside the baseline's, map by map: size, quads, build time and memory."""
    if not rows:
        return
    print(f"\n{'index (this tree / ' + str(baseline) + ')':<40} {'B/obj':>13} {'quads/obj':>13} {'build s':>15}"
          f" {'PSS MB':>13} {'RSS MB':>13}")
    def pair(tree: dict, base: dict, key: str, scale: float = 1.0, fmt: str = ".1f") -> str:
        a, b = tree.get(key, math.nan) * scale, base.get(key, math.nan) * scale
        return f"{a:{fmt}} / {b:{fmt}}"

    for name, n, tree, base in rows:
        print(f"{name:<40} {pair(tree, base, 'bytes', 1 / n):>13} {pair(tree, base, 'quads', 1 / n):>13}"
              f" {pair(tree, base, 'wall_s'):>15} {pair(tree, base, 'peak_pss_mb', fmt='.0f'):>13}"
              f" {pair(tree, base, 'peak_rss_mb', fmt='.0f'):>13}")
    print("B/obj: index file bytes an object; build: wall time and peak memory of the building process and its"
          " workers (a child process each, this tree's and the baseline's in alternating order)")


def _whole_table(whole: list[tuple[str, dict]]) -> None:
    """The table of whole lost-in-space answers per image (``_localize_times``), with ratios to the first map's."""
    print(f"\n{'map':<28} {'ok':>7} {'<=2 m':>5} {'wrong':>5} {'indexes s':>9} {'1st answer s (max)':>18}"
          f" {'1st pass ms':>11} {'localize ms':>11} {'p95 ms':>7} {'p99 ms':>7} {'CPU ms':>7} {'x first map':>11}"
          f" {'x (1st pass)':>12}")
    ref = whole[0][1] if whole else None
    for name, r in whole:
        ratio = statistics.median(r["ms"]) / statistics.median(ref["ms"])
        ratio_first = statistics.median(r["first_ms"]) / statistics.median(ref["first_ms"])
        print(f"{name:<28} {r['ok']:>3}/{r['images']:<3} {r['within_2m']:>5} {r['wrong']:>5} {r['index_s']:>9.2f}"
              f" {r['first_answer_s']:>11.2f} ({r['first_answer_max_s']:4.2f})"
              f" {statistics.median(r['first_ms']):>11.2f}"
              f" {statistics.median(r['ms']):>11.2f} {np.percentile(r['ms'], 95):>7.2f}"
              f" {np.percentile(r['ms'], 99):>7.2f}"
              f" {statistics.median(r['cpu_ms']):>7.2f} {ratio:>10.2f}x {ratio_first:>11.2f}x")
        if "baseline_cpu_ms" in r:
            print(f"{'  baseline, same images':<28} {r['baseline_ok']:>3}/{r['images']:<3}"
                  f" {r['baseline_within_2m']:>5} {r['baseline_wrong']:>5} {'':>28} {'':>11}"
                  f" {statistics.median(r['baseline_ms']):>11.2f} {np.percentile(r['baseline_ms'], 95):>7.2f}"
                  f" {np.percentile(r['baseline_ms'], 99):>7.2f} {statistics.median(r['baseline_cpu_ms']):>7.2f}"
                  f"   this tree: {statistics.median(r['cpu_ms']) / statistics.median(r['baseline_cpu_ms']):.2f}x"
                  f" the baseline's CPU time, {r['same']}/{r['images']} answers the same")
    if ref is not None and len(whole) > 1:
        print("CPU time per image relative to the first map's: " + ", ".join(
            f"{name} {statistics.median(r['cpu_ms']) / statistics.median(ref['cpu_ms']):.2f}x"
            + (f" (baseline {statistics.median(r['baseline_cpu_ms']) / statistics.median(ref['baseline_cpu_ms']):.2f}x)"
               if "baseline_cpu_ms" in r else "") for name, r in whole[1:]))
    print("whole lost-in-space answers, Localizer.localize with no prior and the map's stored index: ok: images"
          " accepted, wrong: accepted more than 5 m from the truth; indexes s: opening the stored index and"
          " building the whole map's object index (once per process, before the timing); 1st answer s: median"
          f" (and max) of --first-answers (default {FIRST_ANSWERS}) fresh processes, each answering one image with"
          " the map and index"
          " dropped from the page cache, open_map to the answer (a big map read page by page); 1st pass:"
          " median per image the first time each image is localized, localize ms and p95: the fastest of 3 more"
          " passes, CPU ms the same in CPU time; x first map: median localize time relative to the first map's"
          " (Andorra's)")


if __name__ == "__main__":
    sys.exit(main())
