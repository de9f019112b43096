"""The PNG of an analysis: the region's map objects under each measure, with legends, units, the CRS, a scale
bar and a title saying what was simulated; and small multiples comparing scenarios.

Cells from which no image can show a map object are left blank (the map objects show through): nothing was
measured there.  matplotlib is imported inside the drawing functions (Agg backend, no display).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from ..evaluation.drawing import crs_name, pyplot, save_figure
from .measures import MIN_VISIBLE
from .run import Analysis

__all__ = ["plot_analysis", "plot_scenarios"]

DPI = 110
# Map objects drawn under the measures at most (sampled evenly beyond).
MAX_DOTS = 150_000
# The panels of one analysis: band, colour map, fixed range (None: from the data), legend label, scale factor.
PANELS: tuple[tuple[str, str, tuple[float, float] | None, str, float], ...] = (
    ("success", "RdYlGn", (0.0, 100.0), "success: images localized (%)", 100.0),
    ("ambiguity", "magma_r", (0.0, 1.0), "ambiguity (0 unique, 1 indistinguishable)", 1.0),
    ("false_fixes", "Reds", (0.0, 100.0), "false fixes: accepted at a wrong place (%)", 100.0),
    ("visible", "viridis", None, "objects in an image (median)", 1.0),
    ("error_m", "viridis", None, "error of correct answers, median (m)", 1.0),
    ("bytes_per_km2", "cividis", None, "map storage (kB/km²)", 1e-3),
)
SCENARIO_PANELS = ("success", "ambiguity", "visible")
# Measures whose cells without a simulated image are drawn apart (in SPARSE_COLOUR), not as a measured 0.
SPARSE_APART = ("success", "false_fixes")
SPARSE_COLOUR = "#bdbdbd"
# Measures of the map's own objects, shown only in the cells that hold some.
PER_OBJECT = ("objects_per_km2", "bytes_per_km2")


def _view(analysis: Analysis) -> tuple[float, float, float, float]:
    """The part of the grid worth showing: the cells where images were localized (else those within reach of
    an object), with a margin; isolated objects far from everything else do not shrink the rest to dots."""
    grid = analysis.grid
    simulated = analysis.measures["simulated"] > 0
    rows, cols = np.nonzero(simulated if simulated.any() else analysis.reached)
    if not rows.size:
        return grid.bounds
    c = grid.cell_m
    x0, y1 = grid.bounds[0] + cols.min() * c, grid.bounds[3] - rows.min() * c
    x1, y0 = grid.bounds[0] + (cols.max() + 1) * c, grid.bounds[3] - (rows.max() + 1) * c
    pad = 0.04 * max(x1 - x0, y1 - y0) + c
    return (max(x0 - pad, grid.bounds[0]), max(y0 - pad, grid.bounds[1]), min(x1 + pad, grid.bounds[2]),
            min(y1 + pad, grid.bounds[3]))


def _dots(map_path: str, view: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    from ..mapfile.reader import open_map

    with open_map(map_path) as m:
        found = m.query_bbox(view[0], view[1], view[2], view[3])
    step = max(1, math.ceil(len(found) / MAX_DOTS))
    return found.x[::step], found.y[::step]


def _scale_bar(ax: Any, view: Sequence[float]) -> None:
    """A bar of a round length (1, 2 or 5 times a power of ten metres) about a fifth of the view wide."""
    width = view[2] - view[0]
    power = 10 ** math.floor(math.log10(width / 5))
    length = max(k * power for k in (1, 2, 5) if k * power <= width / 4) if width / 4 >= power else power
    x = view[0] + 0.05 * width
    y = view[1] + 0.05 * (view[3] - view[1])
    ax.plot([x, x + length], [y, y], color="black", linewidth=3, solid_capstyle="butt")
    text = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    ax.text(x + length / 2, y + 0.015 * (view[3] - view[1]), text, ha="center", va="bottom", fontsize=8,
            bbox={"facecolor": "white", "alpha": 0.7, "edgecolor": "none", "pad": 1})


def _extent(analysis: Analysis) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = analysis.grid.bounds
    return (x0, x1, y0, y1)


def _sparse_layer(ax: Any, analysis: Analysis) -> None:
    """Cells within reach of objects where no image showed enough of them, in one neutral colour."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    sparse = analysis.reached & (analysis.measures["simulated"] == 0)
    ax.imshow(np.ma.masked_where(~sparse, np.ones(sparse.shape)), extent=_extent(analysis), origin="upper",
              cmap=ListedColormap([SPARSE_COLOUR]), vmin=0, vmax=1, interpolation="nearest", zorder=2)
    ax.legend(handles=[Patch(color=SPARSE_COLOUR, label=f"< {MIN_VISIBLE} objects in view: 0 %")],
              loc="upper right", fontsize=7, framealpha=0.8)


def _panel(ax: Any, analysis: Analysis, band: str, cmap: str, limits: tuple[float, float] | None, label: str,
           factor: float, dots: tuple[np.ndarray, np.ndarray], view: Sequence[float]) -> None:
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    plt = pyplot()
    values = analysis.measures[band] * factor
    hidden = ~analysis.reached | np.isnan(values)
    if band in PER_OBJECT:
        hidden |= analysis.counts.objects == 0
    if band in SPARSE_APART:
        # Cells where no image showed enough objects: their 0 is the rule, not a failure of the matcher.
        hidden |= analysis.measures["simulated"] == 0
        _sparse_layer(ax, analysis)
    shown = np.ma.masked_where(hidden, values)
    if limits is None:
        finite = shown.compressed()
        limits = (0.0, float(np.percentile(finite, 99)) if finite.size else 1.0)
        limits = (limits[0], limits[1] if limits[1] > limits[0] else limits[0] + 1.0)
    ax.set_facecolor("#f4f4f4")
    ax.scatter(*dots, s=0.3, c="#505050", linewidths=0, zorder=1)
    image = ax.imshow(shown, extent=_extent(analysis), origin="upper", cmap=cmap, vmin=limits[0],
                      vmax=limits[1], interpolation="nearest", alpha=0.85, zorder=2)
    colorbar = plt.colorbar(image, ax=ax, shrink=0.85, pad=0.02)
    colorbar.set_label(label, fontsize=8)
    colorbar.ax.tick_params(labelsize=7)
    ax.set_xlim(view[0], view[2])
    ax.set_ylim(view[1], view[3])
    ax.set_aspect("equal")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(nbins=4, steps=[1, 2, 5, 10]))
        axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v / 1000:,.{0 if v % 1000 == 0 else 1}f}"))
    ax.tick_params(labelsize=7)
    ax.set_xlabel("easting (km)", fontsize=8)
    ax.set_ylabel("northing (km)", fontsize=8)
    _scale_bar(ax, view)


def _what(analysis: Analysis) -> str:
    """What was simulated, in one or two lines."""
    c = analysis.config
    errors = [f"pixel {c.pixel_std:g} px", f"attitude {c.attitude_std:g}°"]
    errors += [f"{name} {value:g}" for name, value in (("missed", c.miss_rate), ("spurious", c.spurious_rate),
                                                       ("label noise", c.label_noise)) if value]
    labels = ", ".join(c.labels) if c.labels else "all labels"
    prior = f"; prior {c.prior:g} m (ambiguity: no prior)" if c.prior else "; no prior"
    rule = f" (localized until success is known to {c.stop_width:.2f})" if c.sequential else ""
    return (f"{c.samples} images per {analysis.grid.cell_m:g} m cell{rule}, random position and heading: "
            f"{c.altitude:g} m, {c.fov_deg:g}° field of view, {c.size[0]}x{c.size[1]} px; "
            f"errors: {', '.join(errors)}; {labels}{prior}; seed {c.seed}")


def _footnote(fig: Any, analysis: Analysis) -> None:
    fig.text(0.01, 0.005, f"CRS {crs_name(analysis.grid.crs)}. Blank: no map object within an image's reach "
             f"(not simulated). Grey dots: map objects. mapdb analyze, {analysis.map_info['software']}.",
             fontsize=7, ha="left", va="bottom", color="#333333")


def _note(analysis: Analysis, band: str) -> str:
    """One line of what a panel adds up to."""
    m = analysis.measures
    images = float(np.nansum(m["simulated"]))
    ran = m["simulated"] > 0
    if band == "success":
        bearing = analysis.counts.objects > 0
        works = float((m["success"][bearing] >= 0.95).mean()) if bearing.any() else 0.0
        return f">= 95 % in {works:.0%} of the cells holding objects"
    if band == "false_fixes":
        wrong = float(np.nansum(m["false_fixes"] * analysis.config.samples))
        return f"{wrong:,.0f} of {images:,.0f} images accepted at a wrong place"
    if band == "ambiguity":
        amb = m["ambiguity"][~np.isnan(m["ambiguity"])]
        high = int((amb >= 0.5).sum())
        return "" if not amb.size else f"median {np.median(amb):.2f}; {high:,} cell{'s' * (high != 1)} >= 0.5"
    if band in ("visible", "error_m"):
        values = m[band][ran & ~np.isnan(m[band])]
        if not values.size:
            return ""
        shown = f"{np.median(values):.2f} m" if band == "error_m" else f"{np.median(values):.0f} objects"
        return f"median {shown} where simulated"
    total = float(analysis.counts.bytes.sum())
    return f"{total / 1e3:,.1f} kB over {analysis.grid.size * analysis.grid.cell_km2:,.0f} km²"


def plot_analysis(path: str | os.PathLike[str], analysis: Analysis) -> None:
    """Six panels (success, ambiguity, false, visible objects, error, storage) over the map's objects."""
    plt = pyplot()
    view = _view(analysis)
    dots = _dots(analysis.map_path, view)
    aspect = (view[3] - view[1]) / max(view[2] - view[0], 1e-9)
    fig, axes = plt.subplots(2, 3, figsize=(18, min(max(2 * 4.6 * aspect + 1.6, 6.5), 16)), squeeze=False)
    for ax, (band, cmap, limits, label, factor) in zip(axes.flat, PANELS, strict=True):
        _panel(ax, analysis, band, cmap, limits, label, factor, dots, view)
        ax.set_title(_note(analysis, band), fontsize=9, loc="left")
    for ax in axes[0]:
        ax.set_xlabel("")  # the row below names and numbers the axis; the titles need the room
        ax.tick_params(labelbottom=False)
    name = os.path.basename(analysis.map_path)
    fig.suptitle(f"Where {name} localizes an aircraft\n{_what(analysis)}", fontsize=11)
    _footnote(fig, analysis)
    with _measured_once(fig):
        fig.tight_layout(rect=(0, 0.02, 1, 0.96))
    _laid_out(fig)
    save_figure(fig, path, DPI)


@contextmanager
def _measured_once(fig: Any) -> Iterator[None]:
    """Within the block, each of the figure's axes measures its tight box once per renderer and arguments.

    ``tight_layout(rect=...)`` measures every axes twice, the second time (to fit the rect) at the same
    positions with the same renderer: the same boxes, half its time (and the same bytes).
    """
    axes = list(fig.axes)
    for ax in axes:
        ax.get_tightbbox = _once(ax.get_tightbbox)  # an attribute of this axes, removed below
    try:
        yield
    finally:
        for ax in axes:
            del ax.get_tightbbox


def _once(measure: Any) -> Any:
    """``measure`` with its answers kept, by renderer and arguments."""
    kept: dict[tuple[Any, ...], Any] = {}

    def measured(*args: Any, **kwargs: Any) -> Any:
        key = (*(id(a) for a in args), *sorted(kwargs.items()))
        if key not in kept:
            kept[key] = measure(*args, **kwargs)
        return kept[key]

    return measured


def _laid_out(fig: Any) -> None:
    """Drop the placeholder layout engine ``tight_layout`` leaves behind: with it, ``savefig`` lays the figure out
    again in a draw of its own before drawing it (a quarter of the picture's time; the same bytes without)."""
    fig.set_layout_engine(None)


def _settings(analysis: Analysis) -> str:
    """A scenario's own settings, short enough for a panel's title."""
    c = analysis.config
    labels = ", ".join(c.labels) if c.labels else "all labels"
    extra = "".join(f", {name} {value:g}" for name, value in (("missed", c.miss_rate), ("spurious", c.spurious_rate),
                                                              ("label noise", c.label_noise), ("prior m", c.prior or 0))
                    if value)
    return (f"{c.altitude:g} m, {c.fov_deg:g}°, {labels}, {c.pixel_std:g} px, {c.attitude_std:g}°, "
            f"{c.samples} images{extra}")


def plot_scenarios(path: str | os.PathLike[str], analyses: Sequence[Analysis]) -> None:
    """Small multiples: one row per scenario, one column per measure of :data:`SCENARIO_PANELS`, each
    measure on one colour scale across the rows."""
    plt = pyplot()
    first = analyses[0]
    view = _view(first)
    dots = _dots(first.map_path, view)
    panels = [p for p in PANELS if p[0] in SCENARIO_PANELS]
    aspect = (view[3] - view[1]) / max(view[2] - view[0], 1e-9)
    fig, axes = plt.subplots(len(analyses), len(panels), squeeze=False,
                             figsize=(5.8 * len(panels), len(analyses) * (4.6 * aspect + 0.9) + 1.0))
    for row, analysis in enumerate(analyses):
        for ax, (band, cmap, limits, label, factor) in zip(axes[row], panels, strict=True):
            _panel(ax, analysis, band, cmap, limits or _shared_limits(analyses, band, factor), label, factor,
                   dots, view)
            ax.set_title(_note(analysis, band), fontsize=8, loc="left")
            if row < len(analyses) - 1:
                ax.set_xlabel("")
                ax.tick_params(labelbottom=False)
        axes[row][0].set_title(f"{analysis.name}: {_settings(analysis)}\n{_note(analysis, panels[0][0])}",
                               fontsize=8, loc="left")
    fig.suptitle(f"Scenarios over {os.path.basename(first.map_path)}: the same {first.grid.cell_m:g} m cells, "
                 f"random positions and headings, seed {first.config.seed}", fontsize=11)
    _footnote(fig, first)
    with _measured_once(fig):
        fig.tight_layout(rect=(0, 0.02, 1, 0.97))
    _laid_out(fig)
    save_figure(fig, path, DPI)


def _shared_limits(analyses: Sequence[Analysis], band: str, factor: float) -> tuple[float, float]:
    """One colour range for a measure across scenarios, so that their panels compare."""
    values = np.concatenate([(a.measures[band] * factor)[a.reached] for a in analyses])
    values = values[~np.isnan(values)]
    top = float(np.percentile(values, 99)) if values.size else 1.0
    return (0.0, top if top > 0 else 1.0)
