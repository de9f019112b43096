"""Parameters of the paper's Algorithm 1, in a module of their own: the search
(:mod:`~mapdb.match.paper.algorithm`) and its pruning bound (:mod:`~mapdb.match.paper.bound`) both read them,
neither imports the other's caller.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PaperOptions"]


@dataclass(frozen=True)
class PaperOptions:
    """The published parameters, plus a guard against runs that would take days.

    Attributes
    ----------
    delta_r, delta_theta : float
        Tolerances on the radius ratio and the relative angle (radians); paper: 0.2 and 0.2.
    n_min : int
        Matched objects (the pair included) needed for a candidate; paper: 6.
    chunk : int
        Map pairs evaluated at once (memory: about ``chunk * n_img * n_map * 40`` bytes).
    max_work : float
        Refuse images for which ``pairs of image objects * pairs of map objects * n_img * n_map`` exceeds
        this (the paper set-up is about 2e10; a city map would be 1e15).  The estimate ignores the bound.
    prune : bool
        Skip the work on candidates that cannot change the answer: those the exact bound (module notes) rules
        out, and the ``std`` of those with ``N_matched < N_best``.  False runs the algorithm as written,
        every candidate through the full test: the same result, many times slower; for checking.
    """

    delta_r: float = 0.2
    delta_theta: float = 0.2
    n_min: int = 6
    chunk: int = 256
    max_work: float = 5e11
    prune: bool = True
