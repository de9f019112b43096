"""Adaptive cells: a coarse lattice of cells simulated first, the cells between it inferred where it agrees.

With ``SampleConfig.adaptive`` (the default, with the sequential rule), the cells to simulate are taken in two
rounds.  The **coarse lattice** is every cell whose absolute indices ``(i, j)`` are both even (a quarter of
the cells, every second cell each way); its cells are measured first, by the sequential rule.  Every other
cell lies between two or four lattice cells, its **neighbours**: ``(i +- 1, j)`` for odd ``i`` and even ``j``,
``(i, j +- 1)`` for even ``i`` and odd ``j``, the four ``(i +- 1, j +- 1)`` when both are odd (a neighbour
outside the grid is not counted).

A cell's success share is ``(L / N) p``: ``L`` of its ``N`` images can be localized (they show at least four
objects, known from its own poses and views, which every cell draws), and each of those succeeds with
probability ``p``, which is what varies smoothly from place to place.  A neighbour that localized ``m > 0``
images, ``k`` of them correct, says ``p`` lies in its 95 % Wilson interval of ``k`` of ``m`` (a neighbour with
no localizable image says nothing about ``p``).  A cell between is **run** (measured like a lattice cell) when:

* no neighbour says anything about ``p``, or their ``p`` intervals do not all overlap;
* a neighbour had a false fix (a rare event a cell between must not hide);
* the interval below is wider than the sequential rule's ``stop_width`` (0.44 for 16 images), or it holds
  :data:`DECISION_LEVEL` (0.95, the summary's "works here") without being all above it.

Otherwise it is **inferred** (``inferred`` 1, ``simulated`` 0; its ``images``, ``localizable`` and ``visible``
are its own draws'): ``p`` is taken anywhere in the hull of the neighbours' intervals ``[p_lo, p_hi]``, and the
share a fixed run would report, ``k' / N`` with ``k'`` of its ``L`` images correct, anywhere in ``(L / N)``
times ``p -+ z sqrt(p (1 - p) / L)`` (``z`` 1.96) over that hull: the cell's reported interval
(``success_low``, ``success_high``).  ``success`` is ``(L / N)`` times the mean of the neighbours' ``k / m``,
``false_fixes`` 0, ``error_m`` and ``ambiguity`` the means of those neighbours'.  A cell with ``L`` 0 needs no
image in any case (success 0 exactly) and is not inferred.

The rounds depend only on the cells' absolute indices, their own draws and the lattice's measures, so the result
is the same bytes whatever the workers or the partitioning.  A cell at the grid's edge may be decided
differently under another ``--bbox`` (its neighbours outside the grid are not counted).
"""

from __future__ import annotations

import warnings

import numpy as np

from .grid import Grid
from .measures import DECISION_LEVEL, HINT_COLUMNS, wilson_interval

__all__ = ["DECISION_LEVEL", "HINT_COLUMNS", "coarse", "hints"]

# Offsets (di, dj) of a cell's lattice neighbours, by the parity of (i, j).
_NEIGHBOURS: dict[tuple[int, int], tuple[tuple[int, int], ...]] = {
    (1, 0): ((-1, 0), (1, 0)),
    (0, 1): ((0, -1), (0, 1)),
    (1, 1): ((-1, -1), (-1, 1), (1, -1), (1, 1)),
}
_BANDS = ("success", "false_fixes", "error_m", "ambiguity", "localizable", "simulated", "images")


def coarse(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Whether the cells of absolute indices ``(i, j)`` are on the coarse lattice (both indices even)."""
    return (np.asarray(i) % 2 == 0) & (np.asarray(j) % 2 == 0)


def _gather(grid: Grid, bands: dict[str, np.ndarray], i: np.ndarray, j: np.ndarray) -> dict[str, np.ndarray]:
    """The lattice bands at every cell's (up to four) neighbours, as (cells, 4) arrays; ``present`` False (and
    NaN) where a cell has fewer neighbours in the grid."""
    out = {name: np.full((i.size, 4), np.nan) for name in _BANDS}
    out["present"] = np.zeros((i.size, 4), bool)
    parity = np.column_stack([i % 2, j % 2])
    for key, offsets in _NEIGHBOURS.items():
        rows = np.flatnonzero((parity == key).all(axis=1))
        for k, (di, dj) in enumerate(offsets):
            col = i[rows] + di - grid.i0
            row = grid.j0 + grid.nrows - 1 - (j[rows] + dj)
            inside = (col >= 0) & (col < grid.ncols) & (row >= 0) & (row < grid.nrows)
            at = rows[inside]
            out["present"][at, k] = True
            for name in _BANDS:
                out[name][at, k] = bands[name][row[inside], col[inside]]
    return out


def hints(grid: Grid, bands: dict[str, np.ndarray], i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """What the lattice says of the cells between it (absolute indices ``(i, j)``, none on the lattice): one row
    a cell of :data:`~mapdb.analysis.measures.HINT_COLUMNS` (``run`` 1: measure it; else the hull of the
    neighbours' ``p`` intervals, their mean ``k / m``, error and ambiguity), for
    :func:`~mapdb.analysis.measures.measure_cells` to decide with the cell's own draws."""
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    n = _gather(grid, bands, i, j)
    ran = n["present"] & (n["simulated"] > 0) & (n["localizable"] > 0)
    m = np.where(ran, n["simulated"], 1.0)
    k = np.where(ran, np.rint(n["success"] * n["images"] * m / np.where(ran, n["localizable"], 1.0)), 0.0)
    low, high = np.ones(k.shape), np.zeros(k.shape)
    for r, c in zip(*np.nonzero(ran), strict=True):
        low[r, c], high[r, c] = wilson_interval(int(k[r, c]), int(m[r, c]))
    p_lo, p_hi = np.where(ran, low, np.inf).min(axis=1), np.where(ran, high, -np.inf).max(axis=1)
    apart = np.where(ran, low, -np.inf).max(axis=1) > np.where(ran, high, np.inf).min(axis=1)
    fooled = (n["present"] & (n["false_fixes"] > 0)).any(axis=1)
    out = np.full((i.size, len(HINT_COLUMNS)), np.nan)
    out[:, 0] = (~ran.any(axis=1) | apart | fooled).astype(np.float64)
    out[:, 1], out[:, 2] = p_lo, p_hi
    with warnings.catch_warnings():  # a mean of nothing (no neighbour ran) is NaN, the answer wanted
        warnings.simplefilter("ignore", RuntimeWarning)
        out[:, 3] = np.nanmean(np.where(ran, k / m, np.nan), axis=1)
        out[:, 4] = np.nanmean(np.where(ran, n["error_m"], np.nan), axis=1)
        out[:, 5] = np.nanmean(np.where(ran, n["ambiguity"], np.nan), axis=1)
    return out
