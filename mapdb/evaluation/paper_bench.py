"""``mapdb bench paper``: the paper's Table 1, side by side with both localizers and the bound.

The paper (Section III) simulates 500 images per case over a 250 x 150 m map of
objects of one label, 640 x 480 pixels from 100 m, and reports the standard
deviation of the horizontal error, the rejected images and the false
positives.  Here the same five cases run on the same kind of map (about 17
objects per image at 35 degrees) with ``--method fast`` on every image,
``--method paper`` on as many of the same images as a time budget allows (it
takes minutes per image; the count is reported), and the bound: the
least-squares fit given the true correspondences.

Every case uses the same camera positions (same seed), so the cases differ only
by their error levels and field of view.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from ..progress import ProgressLike, as_progress
from ..simulation.simulate import paper_map, simulate_images
from .evaluate import evaluate_images, summarize

__all__ = ["PAPER_CASES", "bench_paper", "format_bench", "paper_cost"]

# Table 1 of the paper: control variables and published results.
PAPER_CASES: tuple[dict[str, Any], ...] = (
    {
        "case": 1,
        "attitude_std": 0.0,
        "pixel_std": 0.0,
        "fov_deg": 35.0,
        "published": {"error_std_m": 0.01, "rejected": (0, 500), "false_positives": (0, 500)},
    },
    {
        "case": 2,
        "attitude_std": 0.05,
        "pixel_std": 1.0,
        "fov_deg": 35.0,
        "published": {"error_std_m": 0.53, "rejected": (22, 500), "false_positives": (2, 478)},
    },
    {
        "case": 3,
        "attitude_std": 0.05,
        "pixel_std": 3.0,
        "fov_deg": 35.0,
        "published": {"error_std_m": 1.97, "rejected": (107, 500), "false_positives": (30, 393)},
    },
    {
        "case": 4,
        "attitude_std": 0.15,
        "pixel_std": 3.0,
        "fov_deg": 35.0,
        "published": {"error_std_m": 1.74, "rejected": (95, 500), "false_positives": (36, 405)},
    },
    {
        "case": 5,
        "attitude_std": 0.15,
        "pixel_std": 3.0,
        "fov_deg": 45.0,
        "published": {"error_std_m": 3.29, "rejected": (0, 500), "false_positives": (9, 500)},
    },
)


def paper_cost(image: dict[str, Any]) -> float:
    """Relative cost of the paper's method on an image: pairs of image objects times the other objects."""
    n = len(image["objects"])
    return max(n * (n - 1) / 2 * n, 1.0)


def bench_paper(
    *, n: int = 500, paper_images: int = 500, budget_s: float | None = 540.0,
    methods: Sequence[str] = ("paper", "fast"), cases: Sequence[int] | None = None, yaw: float | str = 0.0,
    miss_rate: float = 0.0, spurious_rate: float = 0.0, label_noise: float = 0.0, with_prior: float | None = None,
    altitude: float = 100.0, map_seed: int = 0, seed: int = 0, jobs: int = 1, fp_threshold: float = 2.0,
    progress: ProgressLike = None,
) -> dict[str, Any]:
    """Run the paper's five cases and return the published figures next to the measured ones.

    Parameters
    ----------
    n : int
        Images per case for ``fast`` and the bound (the paper: 500).
    paper_images : int
        At most this many images per case for ``paper`` (the first of the same images).
    budget_s : float or None
        Wall-clock budget of the whole run.  ``fast`` runs first on every image; ``paper`` then takes the
        images round-robin over the cases (image 0 of each case, then image 1, ...) while each is predicted
        to finish within the budget (minutes per image: the count actually run is reported per case).
        None: no budget, exactly ``paper_images`` per case.
    methods : sequence of {"paper", "fast"}
        Localizers to run.
    cases : sequence of int, optional
        Case numbers (1-5) to run; all by default.
    yaw, miss_rate, spurious_rate, label_noise, with_prior, altitude
        Harder variants, passed to :func:`mapdb.simulation.simulate.simulate_images` (the paper: yaw 0, none of them).
    map_seed, seed : int
        Seeds of the map and of the images.
    jobs : int
        Worker processes for the localizers.

    Returns
    -------
    dict
        ``{"setup": {...}, "cases": [{"case", "attitude_std", "pixel_std", "fov_deg", "published",
        "objects_mean", "bound": summary, "fast": summary, "paper": summary}, ...], "elapsed_s": ...}``, each
        summary from :func:`mapdb.evaluation.evaluate.summarize` (``paper`` over the images it ran on; absent if none).
    """
    from ..mapfile.queries import MemoryMap

    start = time.perf_counter()
    say = as_progress(progress)
    objects = paper_map(seed=map_seed)
    m = MemoryMap(objects)
    chosen = [c for c in PAPER_CASES if cases is None or c["case"] in set(cases)]
    variant = {"altitude": altitude, "yaw": yaw, "miss_rate": miss_rate, "spurious_rate": spurious_rate,
               "label_noise": label_noise, "with_prior": with_prior, "seed": seed}
    rows, images_of = _simulate_cases(m, chosen, n, variant, fp_threshold)
    if "fast" in methods:
        _run_fast(m, rows, images_of, n, jobs, fp_threshold, say)
    if "paper" in methods and paper_images > 0:
        remaining = None if budget_s is None else max(0.0, budget_s - (time.perf_counter() - start))
        _run_paper(m, rows, images_of, min(paper_images, n), remaining, jobs, fp_threshold, say)
    setup = {"map": {"width_m": 250.0, "height_m": 150.0, "objects": len(objects), "labels": list(objects.labels),
                     "seed": map_seed, "crs": objects.crs},
             "images": n, "paper_images": paper_images, "budget_s": budget_s, "altitude_m": altitude,
             "size": [640, 480], "yaw": yaw, "miss_rate": miss_rate, "spurious_rate": spurious_rate,
             "label_noise": label_noise, "with_prior": with_prior, "seed": seed, "fp_threshold_m": fp_threshold,
             "methods": list(methods), "jobs": jobs}
    return {"setup": setup, "cases": rows, "elapsed_s": time.perf_counter() - start}


def _simulate_cases(m: Any, chosen: list[dict[str, Any]], n: int, variant: dict[str, Any], fp_threshold: float
                    ) -> tuple[list[dict[str, Any]], dict[int, list[dict[str, Any]]]]:
    """Each case's ``n`` images (``variant``: the simulator's harder settings), and its row of the table with
    the bound summarised."""
    rows, images_of = [], {}
    for case in chosen:
        images = simulate_images(m, n, fov_deg=case["fov_deg"], attitude_std=case["attitude_std"],
                                 pixel_std=case["pixel_std"], id_prefix=f"case{case['case']}-", **variant)
        images_of[case["case"]] = images
        row: dict[str, Any] = {k: case[k] for k in ("case", "attitude_std", "pixel_std", "fov_deg", "published")}
        row["bound"] = summarize([_bound_outcome(im) for im in images], fp_threshold)
        row["objects_mean"] = row["bound"]["objects_mean"]
        rows.append(row)
    return rows, images_of


def _bound_outcome(image: dict[str, Any]) -> dict[str, Any]:
    """The bound needs no localizer: an outcome as if the image were answered at the bound's position."""
    b = image["truth"]["bound"]
    return {
        "status": "ok" if b else "rejected",
        "error_m": b["error_m"] if b else None,
        "bound_error_m": b["error_m"] if b else None,
        "n_objects": len(image["objects"]),
        "n_true": b["n"] if b else 0,
        "time_ms": 0.0,
    }


def _run_fast(m: Any, rows: list[dict[str, Any]], images_of: dict[int, list[dict[str, Any]]], n: int, jobs: int,
              fp_threshold: float, say: Any) -> None:
    """``--method fast`` on every image of each case; each row gets its summary."""
    for row in rows:
        say(f"case {row['case']}: fast on {n} images")
        _, row["fast"] = evaluate_images(
            m, images_of[row["case"]], method="fast", jobs=jobs, fp_threshold=fp_threshold, progress=say
        )


def _run_paper(m: Any, rows: list[dict[str, Any]], images_of: dict[int, list[dict[str, Any]]], per_case: int,
               remaining: float | None, jobs: int, fp_threshold: float, say: Any) -> None:
    """``--method paper`` on the first ``per_case`` images of each case, round-robin over the cases, within
    ``remaining`` seconds; each row gets the summary of the images it ran on."""
    queue = [images_of[row["case"]][j] for j in range(per_case) for row in rows]
    say(f"paper: up to {len(queue)} images" + ("" if remaining is None else f" within {remaining:.0f} s"))
    outcomes, _ = evaluate_images(m, queue, method="paper", jobs=jobs, fp_threshold=fp_threshold,
                                  budget_s=remaining, cost=paper_cost, progress=say)
    for row in rows:
        mine = [o for o in outcomes if str(o["id"]).startswith(f"case{row['case']}-")]
        if mine:
            row["paper"] = summarize(mine, fp_threshold)


def _ratio(count: int, total: int) -> str:
    return f"{count}/{total} ({100.0 * count / total:.1f}%)" if total else f"{count}/{total}"


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def format_bench(result: dict[str, Any]) -> str:
    """The side-by-side table of :func:`bench_paper`'s result, for people."""
    cases = result["cases"]
    return "\n".join([_title(result), *_case_rows(cases), *_error_rows(cases), *_outcome_rows(cases),
                      *_time_rows(cases)])


# Column widths of the table: the row labels, then one column a case.
_LABEL_WIDTH = 34
_CELL_WIDTH = 17


def _line(label: str, cells: Sequence[str]) -> str:
    return f"{label:<{_LABEL_WIDTH}}" + "".join(f"{c:>{_CELL_WIDTH}}" for c in cells)


def _per_method(cases: list[dict[str, Any]], method: str, what: str) -> list[str]:
    """One cell a case: ``what`` of ``method``'s summary ("-" where the method did not run)."""
    return [_cell(c.get(method), what) for c in cases]


def _cell(s: dict[str, Any] | None, what: str) -> str:
    if s is None:
        return "-"
    if what == "rms":
        return _metres(s["rms_m"])
    if what == "std":
        return _metres(s["std_m"])
    if what == "rejected":
        return _ratio(s["rejected"], s["images"])
    if what == "fp":
        return _ratio(s["false_positives"], s["accepted"])
    if what == "time":
        return "-" if s["time_median_ms"] is None else f"{s['time_median_ms']:.2f}"
    raise ValueError(f"unknown column {what!r}")


def _title(result: dict[str, Any]) -> str:
    setup = result["setup"]
    return (
        f"Paper Table 1 reproduction: {setup['map']['objects']} objects of one label on 250x150 m, "
        f"640x480 px from {setup['altitude_m']:g} m, yaw {setup['yaw']}, miss {setup['miss_rate']:g}, "
        f"spurious {setup['spurious_rate']:g}, label noise {setup['label_noise']:g}; "
        f"false positive = accepted with error > {setup['fp_threshold_m']:g} m; "
        f"{result['elapsed_s']:.0f} s with {setup['jobs']} job(s)"
    )


def _case_rows(cases: list[dict[str, Any]]) -> list[str]:
    return [
        _line("", [f"Case {c['case']}" for c in cases]),
        _line("attitude error std (deg)", [f"{c['attitude_std']:g}" for c in cases]),
        _line("pixel error std (px)", [f"{c['pixel_std']:g}" for c in cases]),
        _line("field of view (deg)", [f"{c['fov_deg']:g}" for c in cases]),
        _line("objects per image (mean)", [f"{c['objects_mean']:.1f}" for c in cases]),
        _line("images: --method paper", [str(c["paper"]["images"]) if c.get("paper") else "0" for c in cases]),
        _line("images: --method fast, bound", [str(c["bound"]["images"]) for c in cases]),
    ]


def _error_rows(cases: list[dict[str, Any]]) -> list[str]:
    over_bound = ["-" if not c.get("fast") or c["fast"]["rms_over_bound"] is None
                  else f"{c['fast']['rms_over_bound']:.2f}" for c in cases]
    return [
        "error (m)",
        _line("  published (std)", [f"{c['published']['error_std_m']:.2f}" for c in cases]),
        _line("  --method paper, RMS", _per_method(cases, "paper", "rms")),
        _line("  --method fast, RMS", _per_method(cases, "fast", "rms")),
        _line("  --method fast, std", _per_method(cases, "fast", "std")),
        _line("  bound (true correspondences), RMS", [_metres(c["bound"]["bound_rms_m"]) for c in cases]),
        _line("  fast RMS / bound on same images", over_bound),
    ]


def _outcome_rows(cases: list[dict[str, Any]]) -> list[str]:
    return [
        "rejected images",
        _line("  published", [_ratio(*c["published"]["rejected"]) for c in cases]),
        _line("  --method paper", _per_method(cases, "paper", "rejected")),
        _line("  --method fast", _per_method(cases, "fast", "rejected")),
        "false positives (of accepted)",
        _line("  published", [_ratio(*c["published"]["false_positives"]) for c in cases]),
        _line("  --method paper", _per_method(cases, "paper", "fp")),
        _line("  --method fast", _per_method(cases, "fast", "fp")),
    ]


def _time_rows(cases: list[dict[str, Any]]) -> list[str]:
    speedups = []
    for c in cases:
        p, f = c.get("paper"), c.get("fast")
        if p and f and p["time_median_ms"] and f["time_median_ms"]:
            speedups.append(f"{p['time_median_ms'] / f['time_median_ms']:.0f}x")
        else:
            speedups.append("-")
    return [
        "time per image, median (ms)",
        _line("  --method paper", _per_method(cases, "paper", "time")),
        _line("  --method fast", _per_method(cases, "fast", "time")),
        _line("  paper / fast", speedups),
    ]
