"""Run a region analysis: the grid, the cells worth sampling, the tasks, the measures put back in place.

The cells are sent to workers in blocks of :data:`BLOCK_CELLS` x :data:`BLOCK_CELLS` (fixed by the grid,
not by the number of workers), each block a task of :func:`mapdb.analysis.measures.measure_cells`.  Cells
that no image taken from them could show an object in are not sent at all.  With the sequential rule (the
default), neither are the cells from which no image can show :data:`~mapdb.analysis.measures.MIN_VISIBLE`
analysed objects (fewer within reach): they are *skipped* before any work, no image drawn, their success
and false shares 0 exactly (interval width 0), ``images`` 0 and ``visible`` no value (the outputs' mark of a
skipped cell: within reach of an object, ``images`` 0).  A fixed run (``sequential`` False) samples every
cell within reach, as before.  Adaptive (the default with the sequential rule,
:mod:`~mapdb.analysis.adaptive`): the cells on the coarse lattice go first, then the cells between it, each
task carrying what the lattice says of its cells (their workers infer or measure them).  Before the run, a
warm-up task (a spread of :data:`WARMUP_CELLS` cells to simulate) is timed and the cost of the rest estimated
from it.

What a worker reads: the objects its images can show come from the map pages around its cells (a block's
box widened by an image's reach, :func:`~mapdb.analysis.measures.measure_cells`).  The localization is a
lost-in-space search over the whole map (the ambiguity measure is defined by it: the best *wrong* place
anywhere), so a worker also uses the whole map's quad index (the stored ``.qidx``, read as the images' keys
need it) and the whole map's object index (:class:`~mapdb.localize.Localizer`): not narrowed to its cells.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import __version__
from ..cluster import run_tasks, worker_count
from ..progress import ProgressLike, as_progress
from .adaptive import coarse, hints
from .cputime import CpuPhases
from .grid import CellCounts, Grid, analysis_area, cell_counts, check_labels, make_grid
from .measures import HINT_COLUMNS, MIN_VISIBLE, CellMeasures, SampleConfig, measure_cells, open_for_cells

__all__ = ["BLOCK_CELLS", "MEASURES", "Analysis", "Plan", "analyze", "analyze_scenarios", "execute", "plan"]

BLOCK_CELLS = 8
WARMUP_CELLS = 24

# Every measure (a GeoTIFF band, a GeoPackage column), in order: name -> (unit, description).  Per-label
# ``visible_<label>`` bands follow these.  No name is an SQL keyword (``false`` would read as the literal in
# ``ogrinfo -sql``): tests/test_conventions.py checks every field mapdb writes.
MEASURES: dict[str, tuple[str, str]] = {
    "success": ("fraction", "images localized within the false-positive threshold of the truth"),
    "false_fixes": ("fraction", "images accepted farther than the false-positive threshold from the truth"),
    "error_m": ("m", "median error of the correctly localized images"),
    "ambiguity": ("0-1", "best wrong place's score over the true place's, lost-in-space search (0 unique, "
                         "1 indistinguishable)"),
    "visible": ("objects", "median map objects (analysed labels) in an image"),
    "objects_per_km2": ("objects/km2", "map objects (all labels) per square kilometre"),
    "bytes_per_km2": ("bytes/km2", "map file bytes per square kilometre (its objects' share of their pages)"),
    "simulated": ("images", "images simulated and localized (the others showed too few objects)"),
    "images": ("images", "images drawn: poses and the objects they show (0: skipped, fewer than 4 analysed "
                         "objects within reach)"),
    "localizable": ("images", "images drawn that show at least 4 analysed objects (simulated: those localized)"),
    "success_low": ("fraction", "95 % interval of the success a run of every localizable image gives: low end"),
    "success_high": ("fraction", "95 % interval of the success a run of every localizable image gives: high end"),
    "inferred": ("0/1", "1: no image localized, the figures inferred from the coarse lattice's neighbouring cells "
                        "and the cell's own views (mapdb.analysis.adaptive)"),
}
# A map with elevation (format version 2) adds these bands after the per-label ones.
TERRAIN_MEASURES: dict[str, tuple[str, str]] = {
    "relief_m": ("m", "span of the elevations of the map objects an image from the cell could see"),
}


@dataclass
class Analysis:
    """One analysis's result: the grid, the parameters and every measure as a (rows, columns) array (NaN: no
    value)."""

    map_path: str
    grid: Grid
    config: SampleConfig
    counts: CellCounts
    measures: dict[str, np.ndarray]
    map_info: dict[str, Any]
    stats: dict[str, Any] = field(default_factory=dict)
    name: str = ""

    @property
    def reached(self) -> np.ndarray:
        """Cells from which an image could show at least one analysed object."""
        return self.counts.within_reach > 0

    def units(self, band: str) -> str:
        return MEASURES[band][0] if band in MEASURES else TERRAIN_MEASURES.get(band, ("objects",))[0]

    def description(self, band: str) -> str:
        if band in MEASURES:
            return MEASURES[band][1]
        if band in TERRAIN_MEASURES:
            return TERRAIN_MEASURES[band][1]
        return f"median map objects labelled {band.removeprefix('visible_')} in an image"


def _map_info(m: Any) -> dict[str, Any]:
    return {"path": str(m.path), "crs": m.crs, "objects": len(m), "file_bytes": int(m.file_size),
            "labels": dict(m.label_counts), "software": f"mapdb {__version__}"}


def analyze(map_path: str, config: SampleConfig, *, cell_m: float = 100.0, bbox: Sequence[Any] | None = None,
            client: Any = None, progress: ProgressLike = None) -> Analysis:
    """Analyse a map over a grid (see :mod:`mapdb.analysis`).

    Parameters
    ----------
    map_path : str
        The map file (workers open it from this path).
    config : SampleConfig
        Camera, errors, labels, samples per cell, prior, seed.
    cell_m : float
        Cell size in metres (map CRS).
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Analyse only the part of the map in this lon/lat box.
    client : distributed.Client, optional
        Run the cells' tasks on this cluster (:func:`mapdb.cluster.open_client`); in this process if None.
    progress : Progress or callable, optional
        The cost estimate, then a count of the cells to simulate.
    """
    return analyze_scenarios(map_path, {"": config}, cell_m=cell_m, bbox=bbox, client=client,
                             progress=progress)[0]


def analyze_scenarios(map_path: str, configs: dict[str, SampleConfig], *, cell_m: float = 100.0,
                      bbox: Sequence[Any] | None = None, client: Any = None,
                      progress: ProgressLike = None) -> list[Analysis]:
    """Analyse the same cells under several named configurations (each as :func:`analyze`)."""
    return execute(plan(map_path, configs, cell_m=cell_m, bbox=bbox, progress=progress), client, progress)


@dataclass
class Plan:
    """What is known before any image is simulated: the grid, the map, and each configuration's cell counts."""

    map_path: str
    grid: Grid
    map_info: dict[str, Any]
    runs: list[tuple[str, SampleConfig, CellCounts]]


def plan(map_path: str, configs: dict[str, SampleConfig], *, cell_m: float = 100.0,
         bbox: Sequence[Any] | None = None, progress: ProgressLike = None) -> Plan:
    """Check the map, the labels, the box and the cell size, and count what each cell holds (no simulation:
    bad input fails here, before any worker starts)."""
    from ..mapfile.reader import open_map

    say = as_progress(progress)
    with open_map(map_path) as m:
        for config in configs.values():
            check_labels(m, config.labels)
        grid = make_grid(analysis_area(m, bbox), cell_m, m.crs)
        runs = [(name, config, cell_counts(m, grid, config.labels, config.reach_m, say if not k else None))
                for k, (name, config) in enumerate(configs.items())]
        return Plan(str(map_path), grid, _map_info(m), runs)


def execute(planned: Plan, client: Any = None, progress: ProgressLike = None,
            phases: CpuPhases | None = None) -> list[Analysis]:
    """Run every configuration of a plan (see :func:`analyze`).

    With ``phases``, its ``startup`` closes at the first cell (the map and its indexes opened first, here when
    there is no cluster) and its ``cells`` when the last is in place, the workers' tasks' CPU added.
    """
    say = as_progress(progress)
    if phases is not None:
        if client is None:  # what the first task would open: start-up, paid once however many cells
            open_for_cells(planned.map_path)
        phases.close("startup")
    analyses = [_run(planned.map_path, planned.grid, counts, config, planned.map_info, name, client, say, phases)
                for name, config, counts in planned.runs]
    if phases is not None:
        phases.close("cells")
    return analyses


def _run(map_path: str, grid: Grid, counts: CellCounts, config: SampleConfig, info: dict[str, Any], name: str,
         client: Any, say: Any, phases: CpuPhases | None = None) -> Analysis:
    """Sample every cell within reach of an object (or, adaptive, the lattice's and those between it where it
    disagrees), in blocks, and put the measures in place."""
    start = time.perf_counter()
    rows, cols = np.nonzero(counts.within_reach > 0)
    heavy = counts.within_reach[rows, cols] >= MIN_VISIBLE
    bands = _empty_bands(grid, config.labels or tuple(info["labels"]))
    # Sequential: the cells no image can localize from are skipped before any work (their bands set below).
    sent = np.flatnonzero(heavy) if config.sequential else np.arange(rows.size)
    i, j = grid.absolute(rows, cols)
    adaptive = config.sequential and config.adaptive
    first = sent[coarse(i[sent], j[sent])] if adaptive else sent
    cells = _Cells(map_path, grid, config, rows, cols, heavy, bands, phases=phases)
    prefix = f"{name}: " if name else ""
    warm = _warmup_cells(first[heavy[first]])
    result = cells.round(client, [warm])
    estimate_s = _announce(say, prefix, grid, rows.size, int(heavy.sum()), config, result, len(warm),
                           worker_count(client))
    say.start(int(heavy.sum()), f"{prefix}analyze")
    say.advance(len(warm))
    cells.round(client, _blocks(rows, cols, np.setdiff1d(first, warm)), say)
    between = np.setdiff1d(sent, first)
    if adaptive and between.size:  # what the lattice says of each cell between it, for its worker to decide
        cells.hints = np.full((rows.size, len(HINT_COLUMNS)), np.nan)
        cells.hints[between] = hints(grid, bands, i[between], j[between])
        cells.round(client, _blocks(rows, cols, between), say)
    say.done()
    inferred = int((bands["inferred"] > 0).sum())
    _density_bands(bands, counts, grid)
    _mark_skipped(bands, rows[~heavy], cols[~heavy], config.sequential)
    stats = {"cells": grid.size, "cells_within_reach": int(rows.size),
             "cells_simulated": int(heavy.sum()) - inferred,
             "cells_skipped": int((~heavy).sum()) if config.sequential else 0, "cells_inferred": inferred,
             "images_localized": int(np.nansum(bands["simulated"])),
             "images_drawn": int(np.nansum(bands["images"])),
             "images_localizable": int(np.nansum(bands["localizable"])), "workers": worker_count(client),
             "estimate_s": None if estimate_s is None else round(estimate_s, 1),
             "seconds": round(time.perf_counter() - start, 1)}
    return Analysis(map_path, grid, config, counts, bands, info, stats, name)


@dataclass
class _Cells:
    """The cells within reach (indices into ``rows``, ``cols``), and the bands their measures go to."""

    map_path: str
    grid: Grid
    config: SampleConfig
    rows: np.ndarray
    cols: np.ndarray
    heavy: np.ndarray
    bands: dict[str, np.ndarray]
    hints: np.ndarray | None = None  # a row a cell (NaN: none), for the cells between the lattice
    phases: CpuPhases | None = None  # the run's CPU, to which the workers' tasks' is added

    def round(self, client: Any, task_cells: list[np.ndarray], say: Any = None) -> CellMeasures:
        """Measure groups of cells, a task each (the groups with the most cells to simulate first, so that no
        long task is left for the end), their measures put in place; the last task's measures."""
        tasks = [(self.map_path, self.config, self.grid.cell_m,
                  np.column_stack(self.grid.absolute(self.rows[c], self.cols[c])),
                  None if self.hints is None else self.hints[c]) for c in task_cells]
        order = sorted(range(len(tasks)), key=lambda t: -int(self.heavy[task_cells[t]].sum()))
        result = CellMeasures.empty(0, ())
        for t, result in run_tasks(client, measure_cells, [tasks[t] for t in order]):
            index = task_cells[order[t]]
            _place(self.bands, result, self.rows[index], self.cols[index])
            if client is not None and self.phases is not None:  # in this process, its CPU is the process's
                self.phases.workers += result.cpu_s
            if say is not None:
                say.advance(int(self.heavy[index].sum()))
        return result


def _empty_bands(grid: Grid, label_names: Sequence[str]) -> dict[str, np.ndarray]:
    """Every band of a grid where nothing is in view: zeros, NaN (no value) for error and ambiguity."""
    bands = {band: np.zeros(grid.shape, np.float32) for band in MEASURES}
    bands["error_m"][:] = np.nan
    bands["ambiguity"][:] = np.nan
    bands.update({f"visible_{label}": np.zeros(grid.shape, np.float32) for label in label_names})
    return bands


def _mark_skipped(bands: dict[str, np.ndarray], rows: np.ndarray, cols: np.ndarray, sequential: bool) -> None:
    """Cells within reach of fewer than MIN_VISIBLE analysed objects: success 0 exactly; skipped by the
    sequential rule, their objects in view unknown (no image drawn)."""
    if sequential:
        for band in bands:
            if band == "visible" or band.startswith("visible_"):
                bands[band][rows, cols] = np.nan


def _place(bands: dict[str, np.ndarray], result: CellMeasures, rows: np.ndarray, cols: np.ndarray) -> None:
    for band, values in (("success", result.success), ("false_fixes", result.false), ("error_m", result.error),
                         ("ambiguity", result.ambiguity), ("visible", result.visible),
                         ("simulated", result.simulated), ("images", result.images),
                         ("localizable", result.localizable), ("success_low", result.low),
                         ("success_high", result.high), ("inferred", result.inferred)):
        bands[band][rows, cols] = values
    for k, label in enumerate(result.label_names):
        bands[f"visible_{label}"][rows, cols] = result.per_label[:, k]


def _density_bands(bands: dict[str, np.ndarray], counts: CellCounts, grid: Grid) -> None:
    bands["objects_per_km2"][:] = counts.objects / grid.cell_km2
    bands["bytes_per_km2"][:] = counts.bytes / grid.cell_km2
    if counts.relief is not None:  # a map with elevation: one more band, last (flat maps' outputs unchanged)
        bands["relief_m"] = counts.relief


def _warmup_cells(heavy: np.ndarray) -> np.ndarray:
    """Indices of the warm-up cells: up to WARMUP_CELLS spread evenly over the cells to simulate."""
    if not heavy.size:
        return heavy
    picks = np.unique(np.linspace(0, heavy.size - 1, min(WARMUP_CELLS, heavy.size)).round().astype(np.int64))
    return heavy[picks]


def _blocks(rows: np.ndarray, cols: np.ndarray, index: np.ndarray) -> list[np.ndarray]:
    """``index`` (into rows/cols) grouped by the grid's blocks of BLOCK_CELLS x BLOCK_CELLS cells."""
    groups: dict[tuple[int, int], list[int]] = defaultdict(list)
    for k in index.tolist():
        groups[(int(rows[k]) // BLOCK_CELLS, int(cols[k]) // BLOCK_CELLS)].append(k)
    return [np.array(groups[key], np.int64) for key in sorted(groups)]


def _announce(say: Any, prefix: str, grid: Grid, within: int, heavy: int, config: SampleConfig,
              warm: CellMeasures, n_warm: int, workers: int) -> float | None:
    """Print what the run will cost, from the warm-up's time per cell; the estimate in seconds."""
    per_cell = warm.seconds / n_warm if n_warm else 0.0
    estimate = per_cell * max(heavy - n_warm, 0) / workers
    say(f"{prefix}{grid.size:,} cells of {grid.cell_m:g} m ({grid.size * grid.cell_km2:,.1f} km²): {within:,} "
        f"within an image's reach of a map object, {heavy:,} to simulate ({config.samples} images each at "
        f"most{_rule(config)}); the other {grid.size - heavy:,} are decided without simulating")
    if n_warm:
        say(f"{prefix}warm-up: {per_cell * 1000:,.0f} ms a cell over {n_warm} cells; estimated "
            f"{_duration(estimate)} with {workers} worker{'s' if workers > 1 else ''}")
    return estimate if n_warm else None


def _rule(config: SampleConfig) -> str:
    if not config.sequential:
        return ", all of them"
    return f", localized until the 95 % interval of success is {config.stop_width:.3f} wide"


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:,.1f} h"
