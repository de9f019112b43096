"""Decide: accept the search's best place, or say why not, and the answer the fast matcher returns.

The search (:mod:`~mapdb.match.hypotheses` then :mod:`~mapdb.match.screen`, round by round) hands over its
candidates best first; each check here takes the previous stage's result and either passes or gives the
:class:`MatchResult` that rejects the image:

* :func:`uncertain` - no candidate, or the best one's number of false alarms (:mod:`mapdb.match.nfa`) is
  not below ``10**log10_epsilon``; when a candidate's test without the objects' areas is below it (the
  areas' share of the budget is what rejected it, :func:`~mapdb.match.evidence.areas.points_floor`), the
  result says so (``rejected_by = "areas"``, with that test's log10 NFA);
* :func:`ambiguous` - after the rivals (:mod:`~mapdb.match.rivals`), a distinct place comes within
  ``ambiguity_margin`` of the winner's score;
* :func:`answer` - after the final fit (:func:`~mapdb.match.refine.polish`), the answer's estimated error
  exceeds ``max_sigma_m``; otherwise the answer is accepted.
"""

from __future__ import annotations

from dataclasses import dataclass

from .options import FastOptions
from .refine import Candidate

__all__ = ["MatchResult", "ambiguous", "answer", "uncertain"]


@dataclass
class MatchResult:
    """What :func:`match_fast` found: ``best`` is None when the image is rejected (``reason`` says why;
    ``rejected_by`` is ``"areas"`` when the test without the objects' areas would have accepted, whose best
    log10 NFA is ``log10_nfa_points``)."""

    best: Candidate | None
    candidates: list[Candidate]
    reason: str | None
    n_hypotheses: int
    rounds: int
    rejected_by: str | None = None
    log10_nfa_points: float | None = None
    # Which search decided, when a pose prior was given: "pose-prior" (:mod:`~mapdb.match.pose_prior`) or
    # "quads" (the lost-in-space rounds); None without a pose prior.
    path: str | None = None


def uncertain(pool: list[Candidate], opts: FastOptions, n_tests: int, rounds: int) -> MatchResult | None:
    """The rejection when the search found no place, or none certain enough; None when its best is."""
    if not pool:
        return MatchResult(None, [], "no consistent pattern found in the map", n_tests, rounds)
    best = pool[0]
    if best.log10_nfa >= opts.log10_epsilon:
        reason = (f"no match is certain enough (best log10 NFA {best.log10_nfa:.1f} with {best.inliers} inliers; "
                  f"needs < {opts.log10_epsilon:g})")
        points = [c.log10_nfa_points for c in pool if c.log10_nfa_points is not None]
        by_areas = bool(points) and min(points) < opts.log10_epsilon
        return MatchResult(None, pool[: opts.max_candidates], reason, n_tests, rounds, "areas" if by_areas else None,
                           min(points) if by_areas else None)
    return None


def ambiguous(best: Candidate, rest: list[Candidate], opts: FastOptions, n_tests: int,
              rounds: int) -> MatchResult | None:
    """The rejection when a distinct place of ``rest`` (runner-ups and rivals, best first) is accepted too and
    scores within ``opts.ambiguity_margin`` of ``best``; None when none does."""
    close = [c for c in rest if c.log10_nfa < opts.log10_epsilon and c.score > best.score - opts.ambiguity_margin]
    if not close:
        return None
    reason = f"ambiguous: two places match about equally well (scores {best.score:.1f} and {close[0].score:.1f})"
    return MatchResult(None, [best, *rest][: opts.max_candidates], reason, n_tests, rounds)


def answer(best: Candidate, rest: list[Candidate], opts: FastOptions, n_tests: int, rounds: int) -> MatchResult:
    """The answer: ``best`` (finally fitted) accepted, or withheld as imprecise when its estimated 1-sigma
    error exceeds ``opts.max_sigma_m`` (then listed first among the candidates)."""
    if opts.max_sigma_m is not None and best.sigma_m > opts.max_sigma_m:
        reason = (f"imprecise: estimated 1-sigma error {best.sigma_m:.2f} m exceeds {opts.max_sigma_m:g} m "
                  f"({best.inliers} inliers)")
        return MatchResult(None, [best, *rest][: opts.max_candidates], reason, n_tests, rounds)
    return MatchResult(best, rest, None, n_tests, rounds)
