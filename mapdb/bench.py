"""``mapdb bench paper``: the paper's Table 1, side by side with both localizers and the bound.

The paper (Section III) simulates 500 images per case over a 250 x 150 m map of
objects of one label, 640 x 480 pixels from 100 m, and reports the standard
deviation of the horizontal error, the rejected images and the false
positives.  Here the same five cases run on the same kind of map (about 17
objects per image at 35 degrees) with ``--method fast`` on every image,
``--method paper`` on the first ``paper_images`` of them (it takes seconds per
image), and the bound: the least-squares fit given the true correspondences.

Every case uses the same camera positions (same seed), so the cases differ only
by their error levels and field of view.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from .evaluate import evaluate_images, summarize
from .simulate import paper_map, simulate_images

__all__ = ["PAPER_CASES", "bench_paper", "format_bench"]

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


def bench_paper(
    *,
    n: int = 500,
    paper_images: int = 10,
    methods: Sequence[str] = ("paper", "fast"),
    cases: Sequence[int] | None = None,
    yaw: float | str = 0.0,
    miss_rate: float = 0.0,
    spurious_rate: float = 0.0,
    label_noise: float = 0.0,
    with_prior: float | None = None,
    altitude: float = 100.0,
    map_seed: int = 0,
    seed: int = 0,
    jobs: int = 1,
    fp_threshold: float = 2.0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the paper's five cases and return the published figures next to the measured ones.

    Parameters
    ----------
    n : int
        Images per case for ``fast`` and the bound (the paper: 500).
    paper_images : int
        Images per case for ``paper`` (the first of the same images; 0 skips it).
    methods : sequence of {"paper", "fast"}
        Localizers to run.
    cases : sequence of int, optional
        Case numbers (1-5) to run; all by default.
    yaw, miss_rate, spurious_rate, label_noise, with_prior, altitude
        Harder variants, passed to :func:`mapdb.simulate.simulate_images` (the paper: yaw 0, none of them).
    map_seed, seed : int
        Seeds of the map and of the images.
    jobs : int
        Worker processes for the localizers.

    Returns
    -------
    dict
        ``{"setup": {...}, "cases": [{"case", "attitude_std", "pixel_std", "fov_deg", "published",
        "objects_mean", "bound": summary, "fast": summary, "paper": summary}, ...]}``, each summary from
        :func:`mapdb.evaluate.summarize` (the ``paper`` one over ``paper_images`` images).
    """
    from .store import MemoryMap

    say = progress or (lambda message: None)
    objects = paper_map(seed=map_seed)
    m = MemoryMap(objects)
    chosen = [c for c in PAPER_CASES if cases is None or c["case"] in set(cases)]
    out_cases = []
    for case in chosen:
        images = simulate_images(
            m,
            n,
            altitude=altitude,
            fov_deg=case["fov_deg"],
            yaw=yaw,
            attitude_std=case["attitude_std"],
            pixel_std=case["pixel_std"],
            miss_rate=miss_rate,
            spurious_rate=spurious_rate,
            label_noise=label_noise,
            with_prior=with_prior,
            seed=seed,
        )
        row: dict[str, Any] = {k: case[k] for k in ("case", "attitude_std", "pixel_std", "fov_deg", "published")}
        # The bound needs no localizer: summarise it as if every image were answered at the bound's position.
        bound_outcomes = [
            {
                "status": "ok" if im["truth"]["bound"] else "rejected",
                "error_m": im["truth"]["bound"]["error_m"] if im["truth"]["bound"] else None,
                "bound_error_m": im["truth"]["bound"]["error_m"] if im["truth"]["bound"] else None,
                "n_objects": len(im["objects"]),
                "n_true": im["truth"]["bound"]["n"] if im["truth"]["bound"] else 0,
                "time_ms": 0.0,
            }
            for im in images
        ]
        row["bound"] = summarize(bound_outcomes, fp_threshold)
        row["objects_mean"] = row["bound"]["objects_mean"]
        for method in methods:
            subset = images[:paper_images] if method == "paper" else images
            if not subset:
                continue
            say(f"case {case['case']}: {method} on {len(subset)} images")
            _, row[method] = evaluate_images(m, subset, method=method, jobs=jobs, fp_threshold=fp_threshold)
        out_cases.append(row)
    setup = {
        "map": {
            "width_m": 250.0,
            "height_m": 150.0,
            "objects": len(objects),
            "labels": list(objects.labels),
            "seed": map_seed,
            "crs": objects.crs,
        },
        "images": n,
        "paper_images": paper_images,
        "altitude_m": altitude,
        "size": [640, 480],
        "yaw": yaw,
        "miss_rate": miss_rate,
        "spurious_rate": spurious_rate,
        "label_noise": label_noise,
        "with_prior": with_prior,
        "seed": seed,
        "fp_threshold_m": fp_threshold,
        "methods": list(methods),
    }
    return {"setup": setup, "cases": out_cases}


def _ratio(count: int, total: int) -> str:
    return f"{count}/{total} ({100.0 * count / total:.1f}%)" if total else f"{count}/{total}"


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def format_bench(result: dict[str, Any]) -> str:
    """The side-by-side table of :func:`bench_paper`'s result, for people."""
    cases = result["cases"]
    setup = result["setup"]
    width = 17
    label_width = 34

    def line(label: str, cells: Sequence[str]) -> str:
        return f"{label:<{label_width}}" + "".join(f"{c:>{width}}" for c in cells)

    def per_method(method: str, what: str) -> list[str]:
        cells = []
        for c in cases:
            s = c.get(method)
            if s is None:
                cells.append("-")
            elif what == "rms":
                cells.append(_metres(s["rms_m"]))
            elif what == "std":
                cells.append(_metres(s["std_m"]))
            elif what == "rejected":
                cells.append(_ratio(s["rejected"], s["images"]))
            elif what == "fp":
                cells.append(_ratio(s["false_positives"], s["accepted"]))
            elif what == "time":
                cells.append("-" if s["time_median_ms"] is None else f"{s['time_median_ms']:.2f}")
        return cells

    n_paper = max((c["paper"]["images"] for c in cases if c.get("paper")), default=0)
    n_fast = max((c["fast"]["images"] for c in cases if c.get("fast")), default=0)
    pub = [c["published"] for c in cases]
    lines = [
        f"Paper Table 1 reproduction: {setup['map']['objects']} objects of one label on 250x150 m, "
        f"640x480 px from {setup['altitude_m']:g} m, yaw {setup['yaw']}, miss {setup['miss_rate']:g}, "
        f"spurious {setup['spurious_rate']:g}, label noise {setup['label_noise']:g}; "
        f"false positive = accepted with error > {setup['fp_threshold_m']:g} m",
        line("", [f"Case {c['case']}" for c in cases]),
        line("attitude error std (deg)", [f"{c['attitude_std']:g}" for c in cases]),
        line("pixel error std (px)", [f"{c['pixel_std']:g}" for c in cases]),
        line("field of view (deg)", [f"{c['fov_deg']:g}" for c in cases]),
        line("objects per image (mean)", [f"{c['objects_mean']:.1f}" for c in cases]),
        "error (m)",
        line("  published (std)", [f"{p['error_std_m']:.2f}" for p in pub]),
        line(f"  --method paper, RMS (n={n_paper})", per_method("paper", "rms")),
        line(f"  --method fast, RMS (n={n_fast})", per_method("fast", "rms")),
        line("  --method fast, std", per_method("fast", "std")),
        line("  bound (true correspondences), RMS", [_metres(c["bound"]["bound_rms_m"]) for c in cases]),
        line(
            "  fast RMS / bound on same images",
            [
                "-"
                if not c.get("fast") or c["fast"]["rms_over_bound"] is None
                else f"{c['fast']['rms_over_bound']:.2f}"
                for c in cases
            ],
        ),
        "rejected images",
        line("  published", [_ratio(*p["rejected"]) for p in pub]),
        line("  --method paper", per_method("paper", "rejected")),
        line("  --method fast", per_method("fast", "rejected")),
        "false positives (of accepted)",
        line("  published", [_ratio(*p["false_positives"]) for p in pub]),
        line("  --method paper", per_method("paper", "fp")),
        line("  --method fast", per_method("fast", "fp")),
        "time per image, median (ms)",
        line("  --method paper", per_method("paper", "time")),
        line("  --method fast", per_method("fast", "time")),
    ]
    speedups = []
    for c in cases:
        p, f = c.get("paper"), c.get("fast")
        if p and f and p["time_median_ms"] and f["time_median_ms"]:
            speedups.append(f"{p['time_median_ms'] / f['time_median_ms']:.0f}x")
        else:
            speedups.append("-")
    lines.append(line("  paper / fast", speedups))
    return "\n".join(lines)
