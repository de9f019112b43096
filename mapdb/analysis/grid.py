"""The grid of a region analysis, and what the map holds in and around each of its cells.

Cells are squares of ``cell_m`` metres in the map's projected CRS, aligned on its multiples: the cell
with *absolute* indices ``(i, j)`` spans ``[i cell, (i + 1) cell) x [j cell, (j + 1) cell)``.  A grid is
the block of such cells covering an area (the map's bounds, or the part of a lon/lat box over them);
its rows run from north to south, as a raster's do.  Absolute indices name a cell whatever the area
analysed, so that a cell's samples (drawn from ``(seed, i, j)``) are the same in every analysis that
covers it.

:func:`cell_counts` reads the map strip by strip (at most a few rows of cells' pages at a time): the
objects in each cell, the map bytes they stand for, and the objects of the analysed labels that an image
taken from inside the cell could possibly see, which decides the cells that need no simulation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import AnalysisError, EmptyMapError
from ..objects import Objects
from ..progress import ProgressLike, as_progress

__all__ = [
    "MAX_CELLS",
    "AnalysisError",
    "CellCounts",
    "Grid",
    "analysis_area",
    "cell_counts",
    "check_labels",
    "make_grid",
]

# The most cells one analysis may hold: its measures are arrays of this many cells (about 4 bytes a cell and
# a measure).  Germany at 100 m is about 36 million cells.
MAX_CELLS = 40_000_000
# Rows of cells read from the map at a time.
_STRIP_ROWS = 64


@dataclass(frozen=True)
class Grid:
    """Square cells of ``cell_m`` over an area; column ``c``, row ``r`` (0 = north) is the cell with absolute
    indices ``(i0 + c, j0 + nrows - 1 - r)``.

    Examples
    --------
    >>> g = make_grid((1050.0, 2010.0, 1320.0, 2150.0), 100.0, "EPSG:32631")
    >>> g.shape, g.bounds
    ((2, 4), (1000.0, 2000.0, 1400.0, 2200.0))
    >>> g.absolute(np.array([0]), np.array([2]))
    (array([12]), array([21]))
    """

    cell_m: float
    i0: int
    j0: int
    ncols: int
    nrows: int
    crs: str

    @property
    def shape(self) -> tuple[int, int]:
        return (self.nrows, self.ncols)

    @property
    def size(self) -> int:
        return self.nrows * self.ncols

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """West, south, east, north edges of the grid (map metres)."""
        c = self.cell_m
        return (self.i0 * c, self.j0 * c, (self.i0 + self.ncols) * c, (self.j0 + self.nrows) * c)

    @property
    def cell_km2(self) -> float:
        return self.cell_m**2 / 1e6

    def absolute(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Absolute indices ``(i, j)`` of cells given by row and column."""
        return self.i0 + np.asarray(cols, np.int64), self.j0 + self.nrows - 1 - np.asarray(rows, np.int64)

    def centres(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinates of cell centres."""
        i, j = self.absolute(rows, cols)
        return (i + 0.5) * self.cell_m, (j + 0.5) * self.cell_m

    def locate(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column and whether inside the grid, of map points."""
        col = np.floor(np.asarray(x, np.float64) / self.cell_m).astype(np.int64) - self.i0
        row = self.j0 + self.nrows - 1 - np.floor(np.asarray(y, np.float64) / self.cell_m).astype(np.int64)
        inside = (col >= 0) & (col < self.ncols) & (row >= 0) & (row < self.nrows)
        return row, col, inside


def make_grid(area: Sequence[float], cell_m: float, crs: str) -> Grid:
    """The cells covering ``area`` (minx, miny, maxx, maxy in map metres), or :class:`AnalysisError`.

    A cell size must be a positive number of metres, and the grid hold at most :data:`MAX_CELLS` cells.
    """
    if not (isinstance(cell_m, int | float) and math.isfinite(cell_m) and cell_m > 0):
        raise AnalysisError(f"cell size must be a positive number of metres, got {cell_m}")
    x0, y0, x1, y1 = (float(v) for v in area)
    # Counted in floats first: a tiny cell over a country would overflow the integers.
    cols = math.floor(x1 / cell_m) - math.floor(x0 / cell_m) + 1.0
    rows = math.floor(y1 / cell_m) - math.floor(y0 / cell_m) + 1.0
    if cols * rows > MAX_CELLS:
        raise AnalysisError(f"{cell_m:g} m cells over {(x1 - x0) / 1000:,.1f} x {(y1 - y0) / 1000:,.1f} km make "
                            f"{cols * rows:,.0f} cells, more than the limit of {MAX_CELLS:,}; choose larger "
                            "cells or a smaller --bbox")
    return Grid(float(cell_m), math.floor(x0 / cell_m), math.floor(y0 / cell_m), int(cols), int(rows), crs)


def analysis_area(m: Any, bbox: Sequence[Any] | None) -> tuple[float, float, float, float]:
    """The area to analyse in map metres: the map's bounds, or the part of a lon/lat box over them.

    Raises :class:`AnalysisError` for a malformed or empty box, :class:`EmptyMapError` for a box that
    misses the map or holds none of its objects.
    """
    from ..geo import bbox_text, check_bbox, projected_window

    if bbox is None:
        return tuple(float(v) for v in m.bounds)  # type: ignore[return-value]
    try:
        box = check_bbox(bbox)
    except ValueError as exc:
        raise AnalysisError(f"bbox {','.join(str(v) for v in bbox)}: {exc}") from None
    window = projected_window(m.crs, box, within=m.bounds)
    if window is None:
        raise EmptyMapError(f"{m.path}: bbox {bbox_text(box)} does not meet the map")
    x0, y0, x1, y1 = (max(window[0], m.bounds[0]), max(window[1], m.bounds[1]),
                      min(window[2], m.bounds[2]), min(window[3], m.bounds[3]))
    if not (x0 <= x1 and y0 <= y1) or not len(m.query_bbox(x0, y0, x1, y1)):
        raise EmptyMapError(f"{m.path}: bbox {bbox_text(box)} holds none of the map's objects")
    return (x0, y0, x1, y1)


def check_labels(m: Any, labels: Sequence[str] | None) -> tuple[str, ...] | None:
    """The labels to analyse, each one the map has (:class:`~mapdb.errors.LabelTableError` otherwise)."""
    if labels is None:
        return None
    # The map's own label check, so that the message (with its "did you mean") is that of every query.
    m._label_filter(Objects.empty(m.labels, m.crs), labels)
    return tuple(dict.fromkeys(labels))


@dataclass
class CellCounts:
    """What the map holds in each cell of a grid, as (rows, columns) arrays.

    ``objects``: map objects (all labels) in the cell; ``bytes``: the map bytes they stand for (each page's
    bytes and directory record shared equally by its objects, the header by all objects);
    ``within_reach``: objects of the analysed labels that an image taken from a point of the cell could
    see at most (those in the cells around it within the footprint's reach), an upper bound; ``relief``
    (a map with elevation, else None): the span (metres) of the elevations of the objects an image from the
    cell could see (those within reach, as ``within_reach``), NaN where there are none.
    """

    objects: np.ndarray
    bytes: np.ndarray
    within_reach: np.ndarray
    relief: np.ndarray | None = None


def cell_counts(m: Any, grid: Grid, labels: Sequence[str] | None, reach_m: float,
                progress: ProgressLike = None) -> CellCounts:
    """Count, for every cell, the objects in it, their map bytes and the analysed objects within reach."""
    codes = None if labels is None else np.array([m.labels.index(name) for name in labels], np.int64)
    objects = np.zeros(grid.shape, np.int64)
    chosen = np.zeros(grid.shape, np.int64)
    stored = np.zeros(grid.shape, np.float64)
    say = as_progress(progress)
    share = _ObjectBytes(m)
    low, high = np.full(grid.shape, np.inf), np.full(grid.shape, -np.inf)  # elevations in each cell
    x0, _, x1, _ = grid.bounds
    top = grid.bounds[3]
    for r0 in range(0, grid.nrows, _STRIP_ROWS):
        r1 = min(grid.nrows, r0 + _STRIP_ROWS)
        found = m.query_bbox(x0, top - r1 * grid.cell_m, x1, top - r0 * grid.cell_m)
        row, col, inside = grid.locate(found.x, found.y)
        inside &= (row >= r0) & (row < r1)
        found, row, col = found.take(inside), row[inside], col[inside]
        np.add.at(objects, (row, col), 1)
        np.add.at(stored, (row, col), share(found))
        pick = np.ones(len(found), bool) if codes is None else np.isin(found.label, codes)
        np.add.at(chosen, (row[pick], col[pick]), 1)
        if found.elevation is not None:
            known = np.isfinite(found.elevation)
            np.minimum.at(low, (row[known], col[known]), found.elevation[known])
            np.maximum.at(high, (row[known], col[known]), found.elevation[known])
    say(f"{int(objects.sum()):,} objects in {grid.size:,} cells of {grid.cell_m:g} m")
    # An image from a point of a cell sees only objects within ``reach`` of that point: less than
    # ``cell / 2 + reach`` from the cell's centre along each axis, so in the cells fewer than
    # ``1 + reach / cell`` cells away in rows and in columns.
    k = math.ceil(reach_m / grid.cell_m)
    relief = _window_span(low, high, k) if getattr(m, "has_elevation", False) else None
    return CellCounts(objects, stored, _window_sums(chosen, k), relief)


def _window_span(low: np.ndarray, high: np.ndarray, k: int) -> np.ndarray:
    """The highest less the lowest value over the (2k + 1)-square window around every cell (NaN: none)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    size = 2 * k + 1
    span = maximum_filter(high, size, mode="constant", cval=-np.inf) - minimum_filter(low, size, mode="constant",
                                                                                     cval=np.inf)
    return np.where(np.isfinite(span), span, np.nan).astype(np.float32)


def _window_sums(counts: np.ndarray, k: int) -> np.ndarray:
    """Sum of ``counts`` over the (2k + 1)-square window around every cell (a summed-area table)."""
    rows, cols = counts.shape
    table = np.zeros((rows + 1, cols + 1), np.int64)
    table[1:, 1:] = counts.cumsum(0).cumsum(1)
    r = np.arange(rows)
    c = np.arange(cols)
    r0, r1 = np.clip(r - k, 0, rows), np.clip(r + k + 1, 0, rows)
    c0, c1 = np.clip(c - k, 0, cols), np.clip(c + k + 1, 0, cols)
    return (table[r1][:, c1] - table[r0][:, c1] - table[r1][:, c0] + table[r0][:, c0]).astype(np.int64)


class _ObjectBytes:
    """Each object's share of the map file: its page's bytes and directory record shared by the page's
    objects, and the header shared by all the map's objects (the cells' shares sum to the file size)."""

    def __init__(self, m: Any) -> None:
        self.map = m
        self.per_object = m.page_shares()

    def __call__(self, objects: Objects) -> np.ndarray:
        import shapely

        if not len(objects):
            return np.zeros(0)
        quantum = self.map.quantum
        hits = self.map.pages_meeting(shapely.points(np.rint(objects.x / quantum), np.rint(objects.y / quantum)))
        page = np.zeros(len(objects), np.int64)
        page[hits[0]] = hits[1]  # page boxes are disjoint: one page a position
        return self.per_object[page]
