"""The picture of an evaluation (:func:`plot_evaluation`, ``mapdb evaluate --plot``).

It is for people checking a localizer, so it shows what can be wrong: where each image was and what
became of it (a false positive's truth joined to where its answer landed, with the error written
beside), and the error distribution against the bound.  Axes are the map's projected metres with its
CRS named.

matplotlib is imported inside the drawing functions (with the Agg backend, no display), so that
``import mapdb`` does not pay for it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..objects import Objects
from .drawing import OUTLIER_COLOUR, OVERVIEW_POINTS, metre_axes, pyplot, save_figure
from .evaluate import DEFAULT_FP_THRESHOLD_M

__all__ = ["plot_evaluation"]

# An evaluation picture writes the error beside at most this many false positives (the largest).
MAX_ERRORS_NAMED = 12
# About the size of such a label ("12.3 m" at 7 points, 110 dpi) in pixels: closer labels would overprint.
LABEL_BOX_PX = (48.0, 14.0)


def plot_evaluation(
    outcomes: Sequence[dict[str, Any]],
    path: str | Path,
    *,
    fp_threshold: float = DEFAULT_FP_THRESHOLD_M,
    map_objects: Objects | None = None,
    title: str | None = None,
    crs: str | None = None,
) -> None:
    """Save a figure of an evaluation: where each image was and what became of it, and the error distribution.

    The map panel shows every image at its true position: correct answers (green), rejected images (grey
    rings) and false positives (a red ring at the truth, a red cross where the answer landed, a line
    between).  Beside it, the cumulative distribution of the error of accepted answers with the bound
    (the fit with the true correspondences) and the false-positive threshold.

    Parameters
    ----------
    outcomes : sequence of dict
        From :func:`mapdb.evaluation.evaluate.outcome` (``status``, ``x``, ``y``, ``truth_x``, ``truth_y``,
        ``error_m``, ``bound_error_m``).
    path : str or Path
        The picture; matplotlib picks the format from the ending.
    fp_threshold : float
        Accepted answers farther than this (m) from the truth are false positives.
    map_objects : Objects, optional
        Drawn faintly under the images.
    title : str, optional
        The figure's title.
    crs : str, optional
        The CRS to name on the axes (default: that of ``map_objects``).

    Raises
    ------
    MapdbIOError
        If the picture cannot be written.
    """
    status = np.array([o["status"] for o in outcomes], dtype=object)
    ok = status == "ok"
    error = np.array([o["error_m"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    fp = ok & (error > fp_threshold)
    plt = pyplot()
    fig, (ax_err, ax_map) = plt.subplots(1, 2, figsize=(12.5, 5.8), gridspec_kw={"width_ratios": [1, 1.35]})
    _draw_error_cdf(ax_err, outcomes, error, ok, fp, fp_threshold)
    _draw_outcome_map(ax_map, outcomes, ok, fp, map_objects, crs or (map_objects.crs if map_objects else None))
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    if fp.any():
        _name_errors(ax_map, outcomes, fp)
    save_figure(fig, path)


def _draw_error_cdf(ax: Any, outcomes: Sequence[dict[str, Any]], error: np.ndarray, ok: np.ndarray,
                    fp: np.ndarray, fp_threshold: float) -> None:
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    bound = np.array([np.nan if o["bound_error_m"] is None else o["bound_error_m"] for o in outcomes])
    floor = 1e-4  # an error of exactly 0 (a noiseless simulation) still has a place on the log axis
    n = len(outcomes)
    drawn = False
    for values, name, colour in (
        (error[ok], "localizer (accepted answers)", "tab:blue"),
        (bound[np.isfinite(bound)], "bound (fit with the true correspondences)", "0.45"),
    ):
        if values.size:
            v = np.sort(np.maximum(values, floor))
            ax.step(np.concatenate([[v[0]], v]), np.arange(0, v.size + 1) / max(n, 1), where="post", label=name,
                    color=colour, linewidth=1.6)
            drawn = True
    ax.axvline(fp_threshold, color=OUTLIER_COLOUR, linestyle="--", linewidth=1.0,
               label=f"false-positive threshold ({fp_threshold:g} m)")
    if ok.any():
        ax.axhline(ok.sum() / max(n, 1), color="tab:blue", linestyle=":", linewidth=0.8)
    ax.set_xscale("log")
    if not drawn:
        ax.set_xlim(0.01, 100.0)
    lo, hi = ax.get_xlim()
    # Over a few decades, 1-2-5 steps label enough of the axis to read it; over more they would crowd it.
    subs = (1.0, 2.0, 5.0) if math.log10(hi / lo) <= 3.0 else (1.0,)
    ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=subs, numticks=12))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(0.0, 1.02)
    ax.tick_params(labelsize=8)
    ax.set_xlabel("horizontal error (m, log scale)", fontsize=9)
    ax.set_ylabel("fraction of all images with at most this error", fontsize=9)
    ax.set_title("error distribution (cumulative)", fontsize=10)
    ax.grid(True, which="major", alpha=0.3)
    ax.grid(True, which="minor", alpha=0.1)
    correct = int((ok & ~fp).sum())
    rejected = int((~ok).sum())
    good = error[ok & ~fp]
    rms = f"{math.sqrt(float(np.mean(good**2))):.2f} m" if good.size else "-"
    text = (f"{n} images: {correct} correct (RMS {rms}), {int(fp.sum())} false positive(s), {rejected} rejected\n"
            "dotted line: fraction accepted")
    ax.text(0.02, 0.98, text, transform=ax.transAxes, fontsize=8, va="top",
            bbox={"boxstyle": "round", "facecolor": "white", "edgecolor": "0.8"})
    ax.legend(loc="lower right", fontsize=8)


def _name_errors(ax: Any, outcomes: Sequence[dict[str, Any]], fp: np.ndarray) -> None:
    """Write the error beside false positives, largest first, skipping any that would overprint another.

    An error of metres is invisible at the scale of a map; its size in words is not.  Call once the
    figure's layout is done: overlaps are judged in pixels.
    """
    ax.apply_aspect()
    where = ax.transData.transform([(o["x"], o["y"]) if f else (0.0, 0.0) for o, f in zip(outcomes, fp, strict=True)])
    error = np.array([o["error_m"] if f else 0.0 for o, f in zip(outcomes, fp, strict=True)], dtype=np.float64)
    width, height = LABEL_BOX_PX
    placed: list[np.ndarray] = []
    for i in sorted(np.flatnonzero(fp).tolist(), key=lambda i: -error[i]):
        if any(abs(where[i, 0] - p[0]) < width and abs(where[i, 1] - p[1]) < height for p in placed):
            continue
        placed.append(where[i])
        o = outcomes[i]
        ax.annotate(f"{error[i]:,.0f} m" if error[i] >= 10 else f"{error[i]:.1f} m", (o["x"], o["y"]), xytext=(5, -3),
                    textcoords="offset points", fontsize=7, color=OUTLIER_COLOUR, zorder=6)
        if len(placed) >= MAX_ERRORS_NAMED:
            break


def _draw_outcome_map(ax: Any, outcomes: Sequence[dict[str, Any]], ok: np.ndarray, fp: np.ndarray,
                      map_objects: Objects | None, crs: str | None) -> None:
    tx = np.array([o["truth_x"] for o in outcomes], dtype=np.float64)
    ty = np.array([o["truth_y"] for o in outcomes], dtype=np.float64)
    ex = np.array([o["x"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    ey = np.array([o["y"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    if map_objects is not None and len(map_objects):
        step = max(1, len(map_objects) // OVERVIEW_POINTS)
        ax.scatter(map_objects.x[::step], map_objects.y[::step], s=1.0, color="0.8", linewidths=0, zorder=1,
                   label="map objects", rasterized=True)
    correct = ok & ~fp
    if correct.any():
        ax.scatter(tx[correct], ty[correct], s=16, color="tab:green", edgecolors="none", zorder=3,
                   label=f"correct ({int(correct.sum())})")
    if (~ok).any():
        ax.scatter(tx[~ok], ty[~ok], s=30, facecolors="none", edgecolors="0.25", linewidths=1.0, zorder=3,
                   label=f"rejected ({int((~ok).sum())}), at the truth")
    if fp.any():
        for i in np.flatnonzero(fp):
            ax.plot([tx[i], ex[i]], [ty[i], ey[i]], color=OUTLIER_COLOUR, linewidth=0.9, alpha=0.8, zorder=4)
        ax.scatter(tx[fp], ty[fp], s=36, facecolors="none", edgecolors=OUTLIER_COLOUR, linewidths=1.3, zorder=5,
                   label=f"false positive ({int(fp.sum())}): truth")
        ax.scatter(ex[fp], ey[fp], s=40, marker="X", color=OUTLIER_COLOUR, edgecolors="white", linewidths=0.5, zorder=5,
                   label="false positive: where it landed")
    ax.set_aspect("equal", adjustable="datalim")
    metre_axes(ax, crs)
    ax.set_title("images at their true position, by outcome", fontsize=10)
    ax.legend(loc="best", fontsize=8, framealpha=0.9)
