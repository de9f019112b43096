"""The CPU time of an analysis, phase by phase, measured inside the run (what a user projects a bigger area from).

Three phases, each the process's CPU (:func:`time.process_time`: user + system of every thread) between two
marks, plus the CPU its cluster's workers spent in the cells' tasks (each task's own thread, measured on the
worker by :func:`mapdb.analysis.measures.measure_cells`; their interpreters' start-up is not seen):

* ``startup``: from the start given (the process's own start for ``mapdb analyze``: the interpreter and the
  imports) to the first cell: the map and its indexes opened, the grid planned and counted;
* ``cells``: every cell's images drawn, simulated and localized, the sequential rule, the adaptive lattice,
  the bands put in place;
* ``outputs``: the GeoTIFF, the picture and ``cells.gpkg`` (``summary.json``, which records the phases, is
  written after the last mark: its own few milliseconds are not in any phase); of it, ``picture`` apart.

Start-up is paid once a run, and so, nearly, is the picture: a figure of a bounded size (at most
:data:`~mapdb.analysis.pictures.MAX_DOTS` objects drawn), 1.3 s of CPU over Monaco's 837 cells as over
Andorra's 81,840.  The cells and the other outputs grow with the cells: ``cells`` + ``outputs`` - ``picture``
over the grid's cells (``ms_per_cell``) is what a larger area costs a cell.  The figures are timings: they
differ from run to run, and ``summary.json`` holds them under ``cpu`` (its only other timings: ``run.seconds``,
``run.estimate_s``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

__all__ = ["PHASES", "CpuPhases"]

PHASES = ("startup", "cells", "outputs")


@dataclass
class CpuPhases:
    """CPU seconds by phase (:data:`PHASES`), each closed by :meth:`close` in turn.

    Parameters
    ----------
    start : float, optional
        The :func:`time.process_time` at which ``startup`` begins (0.0: the process's own start); now if None.
    """

    start: float | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    workers: float = 0.0  # CPU of the cells' tasks on other processes (a cluster's workers)
    picture: float = 0.0  # of ``outputs``, the picture's (about the same for a cell or a country)
    _last: float = 0.0

    def __post_init__(self) -> None:
        self._last = time.process_time() if self.start is None else self.start

    def close(self, phase: str) -> float:
        """End ``phase`` now: the process's CPU since the previous mark is added to it; that CPU."""
        if phase not in PHASES:
            raise ValueError(f"unknown phase {phase!r}: one of {', '.join(PHASES)}")
        now = time.process_time()
        spent = max(now - self._last, 0.0)
        self.seconds[phase] = self.seconds.get(phase, 0.0) + spent
        self._last = now
        return spent

    def total(self, phase: str) -> float:
        """CPU seconds of ``phase``: this process's, and for ``cells`` its workers' too."""
        return self.seconds.get(phase, 0.0) + (self.workers if phase == "cells" else 0.0)

    def grown(self) -> float:
        """CPU seconds that grow with the cells: the cells, and the outputs but the picture."""
        return self.total("cells") + self.total("outputs") - min(self.picture, self.total("outputs"))

    def record(self, cells: int, simulated: int) -> dict[str, Any]:
        """The phases as ``summary.json`` records them (``cpu``): seconds each, and the cells' cost a cell."""
        return {**{f"{phase}_s": round(self.total(phase), 3) for phase in PHASES},
                "picture_s": round(self.picture, 3), "workers_s": round(self.workers, 3), "grid_cells": cells,
                "cells_simulated": simulated, "ms_per_cell": round(1000 * self.grown() / max(cells, 1), 4),
                "ms_per_simulated_cell": round(1000 * self.total("cells") / max(simulated, 1), 3),
                "clock": "process_time (user + system) of the run's process, plus its workers' tasks"}

    def line(self, cells: int, simulated: int) -> str:
        """One line for the end of a run: what it cost, and a cell's share of what grows with the area."""
        per_cell, per_simulated = 1000 * self.grown() / max(cells, 1), 1000 * self.total("cells") / max(simulated, 1)
        return (f"CPU: {cells:,} cells ({simulated:,} simulated) in {self.grown():,.1f} s, {per_cell:,.2f} ms a "
                f"cell ({per_simulated:,.1f} ms a simulated cell); once a run: start-up "
                f"{self.total('startup'):,.1f} s, picture {self.picture:,.1f} s")
