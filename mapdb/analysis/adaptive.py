"""Adaptive cells: a coarse lattice of cells simulated first, the cells between only where it disagrees.

With ``SampleConfig.adaptive`` (the default, with the sequential rule), the cells to simulate are taken in two
rounds.  The **coarse lattice** is every cell whose absolute indices ``(i, j)`` are both even (a quarter of
the cells, every second cell each way); its cells are simulated first.  Every other cell to simulate lies
between two or four lattice cells, its **neighbours**: ``(i +- 1, j)`` for odd ``i`` and even ``j``,
``(i, j +- 1)`` for even ``i`` and odd ``j``, the four ``(i +- 1, j +- 1)`` when both are odd.  A neighbour
that is not simulated is known exactly (success and false share 0, an interval of no width: no image can
localize there); a neighbour outside the grid is not counted.  A cell between is **run** (simulated, as in
the first round) when its neighbours disagree, that is when any of these holds:

* their 95 % success intervals (``success_low`` to ``success_high``) do not all overlap (the highest low end
  above the lowest high end);
* their success shares fall on both sides of :data:`DECISION_LEVEL` (0.95: the summary's "works here");
* any of them had a false fix (a rare event a cell between must not hide);
* it has no neighbour in the grid.

Otherwise it is **inferred**: no image is drawn (``images``, ``localizable``, ``simulated`` 0, ``visible``
no value) and ``inferred`` is 1; its ``success`` and ``false_fixes`` are the means of its neighbours',
``error_m`` and ``ambiguity`` the means of those that have one, and its interval runs from the lowest
neighbour's low end to the highest neighbour's high end, so that it covers every neighbour's interval.

The rounds depend only on the cells' absolute indices and the first round's measures, so the result is the
same bytes whatever the workers or the partitioning.  A cell at the grid's edge may be decided differently
under another ``--bbox`` (its neighbours outside the grid are not counted).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .grid import Grid

__all__ = ["DECISION_LEVEL", "Inferred", "coarse", "infer"]

# The success share at which a cell counts as "works here" (the summary's level, outputs.SUCCESS_LEVEL).
DECISION_LEVEL = 0.95

# Offsets (di, dj) of a cell's lattice neighbours, by the parity of (i, j).
_NEIGHBOURS: dict[tuple[int, int], tuple[tuple[int, int], ...]] = {
    (1, 0): ((-1, 0), (1, 0)),
    (0, 1): ((0, -1), (0, 1)),
    (1, 1): ((-1, -1), (-1, 1), (1, -1), (1, 1)),
}


def coarse(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Whether the cells of absolute indices ``(i, j)`` are on the coarse lattice (both indices even)."""
    return (np.asarray(i) % 2 == 0) & (np.asarray(j) % 2 == 0)


@dataclass
class Inferred:
    """The cells between the lattice's that are run, and the figures of the others (one row a cell)."""

    run: np.ndarray            # indices (into the cells given) of the cells to simulate
    infer: np.ndarray          # indices of the cells inferred
    success: np.ndarray
    false: np.ndarray
    error: np.ndarray
    ambiguity: np.ndarray
    low: np.ndarray
    high: np.ndarray


def _gather(grid: Grid, bands: dict[str, np.ndarray], i: np.ndarray, j: np.ndarray,
            names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Each band of ``names`` at every cell's (up to four) neighbours, as (cells, 4) arrays; NaN where a cell
    has fewer neighbours in the grid."""
    out = {name: np.full((i.size, 4), np.nan) for name in names}
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
            for name in names:
                out[name][at, k] = bands[name][row[inside], col[inside]]
    return out


def infer(grid: Grid, bands: dict[str, np.ndarray], i: np.ndarray, j: np.ndarray) -> Inferred:
    """Decide the cells between the lattice's (absolute indices ``(i, j)``, none on the lattice) from the
    lattice's measures in ``bands`` (the first round's, and 0 where no image can localize)."""
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    n = _gather(grid, bands, i, j, ("success", "false_fixes", "error_m", "ambiguity", "success_low",
                                    "success_high"))
    present = n["present"]
    count = present.sum(axis=1)
    low = np.where(present, n["success_low"], np.inf).min(axis=1)
    high = np.where(present, n["success_high"], -np.inf).max(axis=1)
    apart = np.where(present, n["success_low"], -np.inf).max(axis=1) > \
        np.where(present, n["success_high"], np.inf).min(axis=1)
    works = np.where(present, n["success"] >= DECISION_LEVEL, False).any(axis=1)
    fails = np.where(present, n["success"] < DECISION_LEVEL, False).any(axis=1)
    fooled = np.where(present, n["false_fixes"] > 0, False).any(axis=1)
    run = (count == 0) | apart | (works & fails) | fooled
    keep = ~run
    # A mean of nothing (no neighbour with an error or an ambiguity) is NaN, the answer wanted: numpy's
    # warning of it is not shown.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        error = np.nanmean(n["error_m"][keep], axis=1) if keep.any() else np.zeros(0)
        amb = np.nanmean(n["ambiguity"][keep], axis=1) if keep.any() else np.zeros(0)
    return Inferred(np.flatnonzero(run), np.flatnonzero(keep), np.nanmean(n["success"][keep], axis=1),
                    np.nanmean(n["false_fixes"][keep], axis=1), error, amb, low[keep], high[keep])
