"""Run the localizer on images with a known truth and measure it (the paper's Table 1 quantities and more).

An *outcome* is one image's result set against its truth: accepted (``status
"ok"``) with a horizontal error, or rejected.  An accepted answer farther than
``fp_threshold`` metres from the truth is a *false positive*; the others are
*correct*.  The summary gives the error statistics of correct answers, the
rejected fraction, false positives as a fraction of accepted answers (as the
paper counts them: 30/393), the heading error, the error of the least-squares fit
with the true correspondences (the *bound*, from the simulator) and the time per image.

**The truth** is the document's ``truth`` (``mapdb simulate``), or else its ``georef``: the centre,
heading and pixel size of a georeferenced chip that ``mapdb objects mask.tif`` wrote (see
:func:`truth_of`), in the map's CRS.

**The bound** means something only for *point detections with known pixel noise*, the ideal simulator's
images: each object is a point with a true map object behind it, and the least-squares fit through those
true pairs is the best any matcher can do with that noise.  Objects from masks (``area_px``: rendered
masks, real masks, COCO) are blobs: a blob's centroid is not its map object's (relief, cut blobs, merged
buildings), so a fit through those pairs says nothing about what a matcher can reach (it was 64 m against
answers 0.33 m off).  Such images carry no bound here, and the summary then has no bound line: their
figure is the RMS against the truth (rendered or georef).

Examples
--------
>>> outcomes = [
...     {"status": "ok", "error_m": 0.5, "bound_error_m": 0.4, "time_ms": 2.0, "n_true": 10},
...     {"status": "ok", "error_m": 50.0, "bound_error_m": 0.3, "time_ms": 3.0, "n_true": 9},
...     {"status": "rejected", "error_m": None, "bound_error_m": 0.2, "time_ms": 1.0, "n_true": 4},
... ]
>>> s = summarize(outcomes, fp_threshold=2.0)
>>> s["accepted"], s["rejected"], s["false_positives"], s["rms_m"]
(2, 1, 1, 0.5)
"""

from __future__ import annotations

import math
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..answers import Answer
from ..detections.images import read_image_documents
from ..errors import ImageInputError, MapdbError, MapdbIOError, MapFormatError
from ..mapfile.layout import DEFAULT_QUANTUM
from ..progress import Progress, ProgressLike, as_progress

__all__ = [
    "DEFAULT_FP_THRESHOLD_M",
    "evaluate_images",
    "format_summary",
    "load_images",
    "outcome",
    "check_truth_crs",
    "summarize",
    "truth_of",
]

# An accepted answer farther than this from the truth (metres) is a false positive.
DEFAULT_FP_THRESHOLD_M = 2.0


def load_images(path: str | Path) -> list[dict[str, Any]]:
    """Read simulated images (JSON Lines, each with a ``truth``) for evaluation.

    Unlike a query, an evaluation cannot skip a bad line (its truth is part of
    what is measured), so any malformed line is an error naming the file and line.
    """
    images = []
    for where, doc in read_image_documents(path):
        if isinstance(doc, ImageInputError):
            raise doc
        truth = truth_of(doc) if isinstance(doc, dict) else None
        if truth is None:
            raise ImageInputError(f"{where}: no truth x, y to evaluate against (simulate the images, or give a "
                                  "georef: mapdb objects on a georeferenced mask writes it)")
        images.append(doc if truth is doc.get("truth") else {**doc, "truth": truth})
    if not images:
        raise ImageInputError(f"{path}: no images")
    return images


def truth_of(doc: dict[str, Any]) -> dict[str, Any] | None:
    """What an image document is scored against: its ``truth`` when it has x, y, else one made from its
    ``georef`` (x, y, ``heading_deg``, ``m_per_px``, ``crs``; ``"from": "georef"``), else None.

    Examples
    --------
    >>> truth_of({"georef": {"x": 1.0, "y": 2.0, "heading_deg": 0.0, "m_per_px": 0.5, "crs": "EPSG:32616"}})
    {'x': 1.0, 'y': 2.0, 'heading_deg': 0.0, 'm_per_px': 0.5, 'crs': 'EPSG:32616', 'from': 'georef'}
    """
    truth = doc.get("truth")
    if isinstance(truth, dict) and all(_is_number(truth.get(k)) for k in ("x", "y")):
        return truth
    georef = doc.get("georef")
    if not isinstance(georef, dict) or not all(_is_number(georef.get(k)) for k in ("x", "y")):
        return None
    made = {k: georef[k] for k in ("x", "y", "heading_deg", "m_per_px") if _is_number(georef.get(k))}
    if isinstance(georef.get("crs"), str):
        made["crs"] = georef["crs"]
    return {**made, "from": "georef"}


def check_truth_crs(images: Sequence[dict[str, Any]], map_crs: str | None) -> None:
    """Refuse a truth taken from a ``georef`` in a CRS other than the map's: its x, y and the answers' are not
    comparable (:class:`~mapdb.errors.ImageInputError`, naming the first such image)."""
    from pyproj import CRS

    same: dict[str, bool] = {}
    for image in images:
        crs = image["truth"].get("crs") if image["truth"].get("from") == "georef" else None
        if not crs or not map_crs:
            continue
        if crs not in same:
            try:
                same[crs] = CRS.from_user_input(crs).equals(CRS.from_user_input(map_crs))
            except Exception:  # pyproj raises several kinds for text it cannot read
                same[crs] = False
        if not same[crs]:
            raise ImageInputError(f"image {image.get('id')!r}: its georef is in {crs[:60]}, the map in "
                                  f"{map_crs[:60]}: build the map in the chip's CRS to score it")


def _meaningful_bound(image: dict[str, Any]) -> bool:
    """Whether the truth's bound means something: point detections, not blobs from masks (module docs)."""
    objects = image.get("objects") or ()
    return not image["truth"].get("mask") and not any(isinstance(o, dict) and "area_px" in o for o in objects)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def outcome(image: dict[str, Any], result: Answer, time_ms: float) -> dict[str, Any]:
    """One image's result compared with its truth.

    Returns a dict with ``id``, ``status`` ("ok", "rejected" or "error"), ``x``, ``y`` (None unless ok),
    ``truth_x``, ``truth_y``, ``error_m`` (None unless ok), ``heading_error_deg`` (the answer's heading
    minus the truth's, in [-180, 180); None unless ok with a true heading), ``bound_error_m`` (None without a
    bound, or where it means nothing: module docs), ``n_objects`` (in the image), ``n_true`` (of them from
    the map; None if unknown), ``n_blocks`` (of them blobs standing for a block of touching buildings,
    ``truth.block``; None if unknown), ``time_ms``, ``reason``.
    """
    truth = truth_of(image) or image["truth"]
    status = result.status
    x, y, error, heading_error = None, None, None, None
    if result.ok and result.x is not None and result.y is not None:
        x, y = float(result.x), float(result.y)
        error = math.hypot(x - truth["x"], y - truth["y"])
        if _is_number(truth.get("heading_deg")) and result.heading_deg is not None:
            heading_error = (float(result.heading_deg) - truth["heading_deg"] + 180.0) % 360.0 - 180.0
    bound = truth.get("bound") if _meaningful_bound({**image, "truth": truth}) else None
    index = truth.get("map_index")
    return {
        "id": image.get("id"),
        "status": status,
        "x": x,
        "y": y,
        "truth_x": float(truth["x"]),
        "truth_y": float(truth["y"]),
        "error_m": error,
        "heading_error_deg": heading_error,
        "bound_error_m": None if not bound else float(bound["error_m"]),
        "n_objects": len(image.get("objects") or ()),
        "n_true": None if index is None else int(np.sum(np.asarray(index) >= 0)),
        # Rendered masks of a map with blocks: the blobs whose map object is a block of touching buildings.
        "n_blocks": int(sum(truth["block"])) if "block" in truth else None,
        "time_ms": float(time_ms),
        "reason": result.reason,
    }


def _mean_known(outcomes: Sequence[dict[str, Any]], key: str) -> float | None:
    """The mean of ``key`` over the outcomes that know it (None if none does)."""
    known = [o[key] for o in outcomes if o.get(key) is not None]
    return float(np.mean(known)) if known else None


def _rms(values: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(values**2))) if values.size else None


def _pct(values: np.ndarray, q: float) -> float | None:
    return float(np.percentile(values, q)) if values.size else None


def summarize(
    outcomes: Sequence[dict[str, Any]], fp_threshold: float = DEFAULT_FP_THRESHOLD_M, min_objects: int = 6
) -> dict[str, Any]:
    """Statistics over outcomes (see :func:`outcome`).

    Returns
    -------
    dict
        ``images``; ``accepted``, ``rejected`` (includes errors), ``errors``, ``rejected_fraction``;
        ``false_positives`` (accepted with error > ``fp_threshold``) and ``false_positive_fraction`` (of
        accepted); ``correct``; ``rms_m``, ``median_m``, ``p95_m``, ``std_m``, ``max_m`` of correct answers;
        ``heading_rms_deg``, ``heading_max_deg`` (largest absolute) of correct answers with a true heading;
        ``bound_rms_m`` (bound over all images that have one), ``bound_rms_correct_m`` (over the images
        answered correctly: the like-for-like reference for ``rms_m``) and ``rms_over_bound`` (None when
        that bound is under 1 mm, where the ratio measures output rounding, not matching);
        ``rejected_fraction_min_objects`` over images with at least ``min_objects`` true objects (of the
        ``images_true_counted`` that say how many they have: simulated ones);
        ``time_median_ms``, ``time_p95_ms``; ``objects_mean``; ``blocks_mean`` (blobs standing for blocks an
        image, over the images whose truth says).  Statistics of empty sets are None.
    """
    n = len(outcomes)
    status = np.array([o["status"] for o in outcomes], dtype=object)
    ok = status == "ok"
    error = np.array([o["error_m"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    false_pos = ok & (error > fp_threshold)
    correct = ok & ~false_pos
    good = error[correct]
    bound = np.array([np.nan if o["bound_error_m"] is None else o["bound_error_m"] for o in outcomes], np.float64)
    times = np.array([o["time_ms"] for o in outcomes], dtype=np.float64)
    n_true = np.array([-1 if o.get("n_true") is None else o["n_true"] for o in outcomes])
    enough = n_true >= min_objects
    rms = _rms(good)
    heading = np.array([np.nan if o.get("heading_error_deg") is None else o["heading_error_deg"] for o in outcomes],
                       dtype=np.float64)[correct]
    heading = heading[np.isfinite(heading)]
    bound_correct = _rms(bound[correct & np.isfinite(bound)])
    return {
        "images": n,
        "accepted": int(ok.sum()),
        "rejected": int(n - ok.sum()),
        "errors": int(np.sum(status == "error")),
        "rejected_fraction": float(1.0 - ok.mean()) if n else None,
        "false_positives": int(false_pos.sum()),
        "false_positive_fraction": float(false_pos.sum() / ok.sum()) if ok.any() else None,
        "fp_threshold_m": fp_threshold,
        "correct": int(correct.sum()),
        "rms_m": rms,
        "median_m": _pct(good, 50),
        "p95_m": _pct(good, 95),
        "std_m": float(np.std(good)) if good.size else None,
        "max_m": float(good.max()) if good.size else None,
        "heading_rms_deg": _rms(heading),
        "heading_max_deg": float(np.abs(heading).max()) if heading.size else None,
        "bound_rms_m": _rms(bound[np.isfinite(bound)]),
        "bound_rms_correct_m": bound_correct,
        "rms_over_bound": rms / bound_correct if rms is not None and bound_correct and bound_correct >= 1e-3 else None,
        "min_objects": min_objects,
        "images_min_objects": int(enough.sum()),
        "images_true_counted": int(np.sum(n_true >= 0)),
        "rejected_fraction_min_objects": float(1.0 - ok[enough].mean()) if enough.any() else None,
        "time_median_ms": _pct(times, 50),
        "time_p95_ms": _pct(times, 95),
        "objects_mean": float(np.mean([o.get("n_objects", 0) for o in outcomes])) if n else None,
        "blocks_mean": _mean_known(outcomes, "n_blocks"),
    }


# Worker state: each process opens the map once and keeps it (and whatever index the localizer caches on it).
_WORKER: dict[str, Any] = {}


def _open_for_worker(spec: tuple[str, Any]) -> Any:
    from ..mapfile.queries import MemoryMap
    from ..mapfile.reader import open_map

    kind, value = spec
    if kind == "path":
        return open_map(value)
    objects, quantum = value
    return MemoryMap(objects, quantum=quantum)


def _init_worker(spec: tuple[str, Any], method: str) -> None:
    # An error here must not escape: a pool restarts a worker whose initializer fails, forever.  It is kept
    # and raised by the worker's first image instead, which ends the run with it.
    try:
        _WORKER["map"] = _open_for_worker(spec)
    except MapdbError as exc:
        _WORKER["map_error"] = exc
    _WORKER["method"] = method


def _localize_timed(map_: Any, image: dict[str, Any], method: str) -> tuple[Answer, float]:
    from ..localize.localizer import localize

    start = time.perf_counter()
    try:
        result = localize(image, map_, method=method)
    except (MapFormatError, MapdbIOError):
        # The map is damaged or unreadable: every other image would fail the same way, and figures over the
        # images that happened to avoid the bad page would mislead.  The run ends with this one-line error.
        raise
    except MapdbError as exc:  # a problem with this image must not lose the other images' figures
        result = Answer(id=None, status="error", reason=str(exc))
    return result, (time.perf_counter() - start) * 1000.0


def _worker_run(image: dict[str, Any]) -> tuple[Answer, float]:
    if "map_error" in _WORKER:
        raise _WORKER["map_error"]
    return _localize_timed(_WORKER["map"], image, _WORKER["method"])


def _worker_spec(map_: Any) -> tuple[str, Any]:
    path = getattr(map_, "path", None)
    if path is not None:
        return ("path", str(path))
    return ("memory", (map_.all(), getattr(map_, "quantum", DEFAULT_QUANTUM)))


def _pool(jobs: int, map_: Any, method: str) -> Any:
    # Workers from a fork server, not forked from this process: a forked worker inherits this process's
    # threads' locks and the CLI's signal handlers, and a pool terminated after a worker's error could then
    # wait forever for a worker blocked on the task queue's lock (seen in the test suite).
    context = multiprocessing.get_context("forkserver")
    return context.Pool(jobs, initializer=_init_worker, initargs=(_worker_spec(map_), method))


def _run_budgeted(
    map_: Any,
    images: Sequence[dict[str, Any]],
    method: str,
    jobs: int,
    budget_s: float,
    cost: Callable[[dict[str, Any]], float],
    say: Progress,
) -> dict[int, tuple[Answer, float]]:
    """Localize images in order, in worker processes, until ``budget_s`` runs out: a hard limit.

    An image is started only while it is predicted (its ``cost`` times 1.5 x the mean time per unit of
    cost so far) to finish within the budget; the first one predicted to overrun ends the run, because
    skipping it for a later, cheaper one would bias the sample towards images with few objects.  The
    paper's method varies tenfold in time per unit of cost, so predictions can miss: at the deadline,
    images still running are stopped and left out.
    """
    deadline = time.perf_counter() + budget_s
    done: dict[int, tuple[Answer, float]] = {}
    spent_ms, spent_cost = 0.0, 0.0
    pending = list(range(len(images)))
    # The pool's context exit terminates its workers, which is what stops images running at the deadline.
    with _pool(max(jobs, 1), map_, method) as pool:
        running: dict[int, Any] = {}
        while pending or running:
            while pending and len(running) < max(jobs, 1):
                if done:
                    rate_s = 1.5 * spent_ms / max(spent_cost, 1e-12) / 1000.0
                    if time.perf_counter() + rate_s * cost(images[pending[0]]) > deadline:
                        pending.clear()
                        break
                i = pending.pop(0)
                running[i] = pool.apply_async(_worker_run, (images[i],))
            if not running:
                break
            if time.perf_counter() > deadline:
                say(f"{method}: budget of {budget_s:.0f} s reached; {len(running)} running image(s) stopped, "
                    "left out")
                break
            for i in [i for i, job in running.items() if job.ready()]:
                done[i] = running.pop(i).get()
                spent_ms += done[i][1]
                spent_cost += cost(images[i])
                say.advance()
            time.sleep(0.02)
    return done


def evaluate_images(
    map: Any,
    images: Sequence[dict[str, Any]],
    *,
    method: str = "fast",
    jobs: int = 1,
    fp_threshold: float = DEFAULT_FP_THRESHOLD_M,
    budget_s: float | None = None,
    cost: Callable[[dict[str, Any]], float] | None = None,
    progress: ProgressLike = None,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Localize every image against ``map`` and compare with its truth.

    Parameters
    ----------
    map : MetaMap or MemoryMap
        The map to localize in (a file-backed map is reopened in each worker; an in-memory one is copied).
    images : sequence of dict
        Image documents with a ``truth`` (from :func:`mapdb.simulation.simulate.simulate_images`).
    method : {"fast", "paper"}
        Passed to :func:`mapdb.localize.localize`.
    jobs : int
        Worker processes (1: in this process).  Times are per image, measured inside the worker.
    fp_threshold : float
        Accepted answers farther than this (metres) from the truth are false positives.
    budget_s : float, optional
        Wall-clock budget: images are taken in order until one is predicted to finish later; it and the
        rest are left out of the outcomes.  For a slow method; the prediction scales the time seen so far by ``cost``.
    cost : callable, optional
        Relative cost of an image for the budget (default: 1 per image).
    progress : callable, optional
        Receives a short message now and then.

    Returns
    -------
    outcomes, summary
        One :func:`outcome` per image localized (input order) and :func:`summarize` of them.
    """
    check_truth_crs(images, getattr(map, "crs", None))
    say = as_progress(progress)
    jobs = max(1, min(jobs, len(images), os.cpu_count() or 1))
    say.start(len(images), method)
    if budget_s is not None:
        done = _run_budgeted(map, images, method, jobs, budget_s, cost or (lambda image: 1.0), say)
        say.done()
        outcomes = [outcome(images[i], *done[i]) for i in sorted(done)]
        return outcomes, summarize(outcomes, fp_threshold)
    results: list[tuple[Answer, float]] = []
    if jobs <= 1:
        for image in images:
            results.append(_localize_timed(map, image, method))
            say.advance()
    else:
        with _pool(jobs, map, method) as pool:
            chunk = max(1, len(images) // (8 * jobs))
            for result in pool.imap(_worker_run, images, chunksize=chunk):
                results.append(result)
                say.advance()
    say.done()
    outcomes = [outcome(image, result, ms) for image, (result, ms) in zip(images, results, strict=True)]
    return outcomes, summarize(outcomes, fp_threshold)


def _fmt(value: float | None, unit: str = "", digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}{unit}"


def _percent(fraction: float | None) -> str:
    return "-" if fraction is None else f"{100.0 * fraction:.1f}%"


def format_summary(summary: dict[str, Any], title: str | None = None) -> str:
    """A short table of a :func:`summarize` result, for people."""
    s = summary
    acc = s["accepted"]
    lines = [title] if title else []
    lines += [
        f"images:            {s['images']}  ({_fmt(s['objects_mean'], '', 1)} objects per image"
        + (f", {s['blocks_mean']:.1f} of them blocks of touching buildings" if s.get("blocks_mean") else "") + ")",
        f"accepted:          {acc}   rejected: {s['rejected']} ({_percent(s['rejected_fraction'])})"
        + (f", {s['errors']} errors" if s["errors"] else ""),
        f"false positives:   {s['false_positives']}/{acc} accepted"
        f" ({_percent(s['false_positive_fraction'])};"
        f" error > {s['fp_threshold_m']:g} m)",
        f"error (correct):   RMS {_fmt(s['rms_m'], ' m', 3)}, median {_fmt(s['median_m'], ' m', 3)}, "
        f"95% {_fmt(s['p95_m'], ' m', 3)}, std {_fmt(s['std_m'], ' m', 3)}",
    ]
    if s.get("images_true_counted", 1):
        # Only simulated images say which of their objects are the map's (a georef chip does not).
        lines.insert(len(lines) - 2, f"  with >= {s['min_objects']} true objects: {s['images_min_objects']} images, "
                                     f"rejected {_percent(s['rejected_fraction_min_objects'])}")
    if s.get("heading_rms_deg") is not None:
        lines.append(f"heading (correct): RMS {_fmt(s['heading_rms_deg'], ' deg', 3)}, "
                     f"max {_fmt(s['heading_max_deg'], ' deg', 3)}")
    if s["bound_rms_m"] is not None:
        # Only images of point detections have a bound (module docs); blobs from masks have none to show.
        lines.append(f"bound (true fit):  RMS {_fmt(s['bound_rms_m'], ' m', 3)} all, "
                     f"{_fmt(s['bound_rms_correct_m'], ' m', 3)} on the same images; "
                     f"RMS / bound {_fmt(s['rms_over_bound'], '', 2)}")
    lines.append(f"time per image:    median {_fmt(s['time_median_ms'], ' ms', 2)}, "
                 f"95% {_fmt(s['time_p95_ms'], ' ms', 2)}")
    return "\n".join(lines)
