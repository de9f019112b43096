"""The pruning bound of the paper's Algorithm 1: lower bounds on distances to the nearest map object.

:func:`mapdb.match.paper.algorithm.match_paper` skips a candidate pair of map objects when this bound proves that
not enough image objects can match under it (the answers are identical to the exhaustive loop; the tests
compare both).
"""

from __future__ import annotations

import math

import numpy as np

from ..._scipy import cKDTree
from .options import PaperOptions

__all__ = ["NearestBound", "wrap_angle"]


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2.0 * np.pi)


# Sector pieces of the bound, tried in turn on the survivors of the previous stage: n x n pieces (radius x angle).
_BOUND_STAGES = (1, 2)
# Grid cells along the longer side of the map's box (about 1 m on the paper's 250 x 150 m map).
_GRID_CELLS = 256


class NearestBound:
    """Per label, a grid of lower bounds on the distance from any point of a cell to the nearest map object.

    A cell's bound is the distance from its centre to the nearest object minus half its diagonal.  A point
    outside the grid's box is moved to the nearest point ``p'`` of the box first: every map object lies in the
    box, which is convex, so its distance from ``p`` is at least ``sqrt(|p - p'|^2 + bound(p')^2)``.
    """

    def __init__(self, map_z: np.ndarray, map_label: np.ndarray, label_keys: list[int | None]) -> None:
        x, y = map_z.real, map_z.imag
        self.x0, self.y0 = float(x.min()), float(y.min())
        width, height = float(x.max()) - self.x0, float(y.max()) - self.y0
        self.cell = max(width, height) / _GRID_CELLS if max(width, height) > 0 else 1.0
        self.nx, self.ny = int(width / self.cell) + 1, int(height / self.cell) + 1
        self.x1, self.y1 = self.x0 + self.nx * self.cell, self.y0 + self.ny * self.cell
        cx = self.x0 + (np.arange(self.nx) + 0.5) * self.cell
        cy = self.y0 + (np.arange(self.ny) + 0.5) * self.cell
        centres = np.column_stack([np.repeat(cx, self.ny), np.tile(cy, self.nx)])
        # 1e-4 beyond half the diagonal covers a point that rounding puts in the next cell.
        half_diagonal = self.cell * math.sqrt(0.5) * (1.0 + 1e-4)
        self.key_row = {key: row for row, key in enumerate(label_keys)}
        # One row of cells per label, flattened: a look-up is one gather whatever the labels.
        grids = np.full((len(label_keys), self.nx * self.ny), np.inf)
        for key, row in self.key_row.items():
            mine = map_z if key is None else map_z[map_label == key]
            if mine.size:
                nearest, _ = cKDTree(np.column_stack([mine.real, mine.imag])).query(centres)
                grids[row] = np.maximum(nearest - half_diagonal, 0.0)
        self.grids: np.ndarray = grids.ravel()
        # Far above the float64 rounding of the map's coordinates (in the matcher's tests and in this bound).
        self.slack = 1e-9 * (1.0 + float(max(np.abs(x).max(), np.abs(y).max())))

    def may_hold(self, q: np.ndarray, radius: np.ndarray, slack: np.ndarray, row_offset: np.ndarray) -> np.ndarray:
        """False where the disk of ``radius`` about ``q`` certainly holds no map object of the label.

        ``row_offset`` (broadcast with ``q``) is the label's row in the grid times the cells per row;
        ``slack`` (m) is added to the radius besides a relative 1e-6.  Not-a-number or infinite inputs give
        True (no claim).
        """
        with np.errstate(invalid="ignore", over="ignore"):
            px = np.minimum(np.maximum(q.real, self.x0), self.x1)
            py = np.minimum(np.maximum(q.imag, self.y0), self.y1)
            ix = np.clip(((px - self.x0) / self.cell).astype(np.int64), 0, self.nx - 1)
            iy = np.clip(((py - self.y0) / self.cell).astype(np.int64), 0, self.ny - 1)
            nearest = self.grids[ix * self.ny + iy + row_offset]
            dx, dy = q.real - px, q.imag - py
            low2 = dx * dx + dy * dy + nearest * nearest
            reach = radius * (1.0 + 1e-6) + slack
            return ~(low2 > reach * reach)

    def survivors(
        self,
        centre: np.ndarray,
        rel_i: np.ndarray,
        ratio_k: np.ndarray,
        dtheta_k: np.ndarray,
        keys: list[int | None],
        need: int,
        opts: PaperOptions,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Candidates whose bound on ``N_matched`` reaches ``need`` (indices, in order) and those bounds.

        ``centre`` and ``rel_i`` (``O_I - c``) are the candidates' (as the full test computes them);
        ``ratio_k``, ``dtheta_k`` and ``keys`` (labels) describe the other image objects.
        """
        n_other = ratio_k.size
        alive = np.arange(centre.size)
        if need <= 2:
            return alive, np.full(centre.size, n_other + 2)
        if need > n_other + 2:
            return alive[:0], alive[:0]
        rho_i = np.abs(rel_i)
        # Rounding grows with the coordinates of c and of the sectors' points (far less than 1e-9 of them).
        slack = self.slack + 1e-9 * (np.abs(centre.real) + np.abs(centre.imag) + rho_i * (ratio_k.max() + 1.0))
        row_offset = np.array([self.key_row[key] for key in keys], dtype=np.int64) * (self.nx * self.ny)
        # Objects near the image centre first: their sectors are the smallest, so they rule out the most.
        order = np.argsort(ratio_k, kind="stable")
        low_k = np.maximum(ratio_k - opts.delta_r, 0.0)
        step_k = ratio_k + opts.delta_r - low_k
        for pieces in _BOUND_STAGES:
            # Piece (a, b): the a-th of `pieces` equal parts of the angles [-delta, delta] about the sector's
            # axis, the b-th of its radii.  In units of R_I = |O_I - c| along O_I - c, its middle point is
            # `middle * turn` and the disk about it has radius `reach`: the bound scales with the candidate.
            beta = opts.delta_theta / pieces
            a, b = np.divmod(np.arange(pieces * pieces), pieces)
            half = 0.5 * step_k[:, None] / pieces  # (n_other, P)
            middle = low_k[:, None] + (2 * b + 1) * half
            reach = np.sqrt(half * half + (middle + half) * middle * (beta * beta))
            turn = np.exp(-1j * (dtheta_k[:, None] + (opts.delta_theta - (2 * a + 1) * beta)))
            offset = middle * turn
            hits = np.zeros(alive.size, dtype=np.int64)
            done = 0
            while done < n_other:
                # One object at a time while many candidates are left (each rules out many), then all the rest.
                block = order[done : done + (1 if alive.size > 4096 else n_other)]
                done += block.size
                q = centre[:, None, None] + rel_i[:, None, None] * offset[block]  # (H, K, P)
                radius = rho_i[:, None, None] * reach[block]
                hold = self.may_hold(q, radius, slack[:, None, None], row_offset[block][:, None])
                hits += hold.any(axis=2).sum(axis=1)
                # The candidates that can still reach ``need`` with every remaining object matched.
                keep = hits + (n_other - done) + 2 >= need
                if not keep.all():
                    alive, hits, centre = alive[keep], hits[keep], centre[keep]
                    rel_i, rho_i, slack = rel_i[keep], rho_i[keep], slack[keep]
                if not alive.size:
                    return alive, hits
        return alive, hits + 2
