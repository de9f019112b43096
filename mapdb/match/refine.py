"""Refinement: candidates from verified hypotheses, one per place, and the final least-squares fit.

The winner is re-associated by an optimal one-to-one assignment and refitted (Umeyama similarity, no
reflection): with the true correspondences found, the position is the least-squares bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._scipy import csr_array, min_weight_full_bipartite_matching
from ._kernel import places_distinct, places_pairs
from .evidence.image import ImageEvidence
from .evidence.points import GATE_SIGMAS, fit_errors, residual_sigmas
from .evidence.relief import ReliefFit
from .mapobjects.object_index import ObjectIndex

__all__ = ["PLACE_FRACTION", "Candidate", "candidates", "distinct", "merge_candidates", "merged_one_by_one", "polish",
           "pose_shift"]

# Two answers closer than this fraction of the footprint's diagonal are one place.
PLACE_FRACTION = 1.0 / 20.0


@dataclass
class Candidate:
    """One refined hypothesis."""

    a: complex
    b: complex
    log10_nfa: float
    inliers: int
    sigma_axis_m: float
    variance_factor: float
    pairs: np.ndarray = field(repr=False)  # (k, 2): image index, map index
    # The decision's log10 NFA without the objects' areas (None: the image has none, or not computed).
    log10_nfa_points: float | None = None

    @property
    def score(self) -> float:
        return -self.log10_nfa

    @property
    def sigma_m(self) -> float:
        """Estimated 1-sigma error (per axis, metres) of the map point under the image centre."""
        return self.sigma_axis_m * math.sqrt(self.variance_factor)


def candidates(a: np.ndarray, b: np.ndarray, nfa: np.ndarray, inlier: np.ndarray, mid: np.ndarray,
               dist: np.ndarray, z: np.ndarray, nfa_points: np.ndarray | None = None) -> list[Candidate]:
    """Refined hypotheses with at least three inliers as :class:`Candidate` s (``nfa_points``: their decision's
    log10 NFA without areas, when it has them)."""
    inlier = np.ascontiguousarray(inlier, bool)
    h, n = inlier.shape
    # The kept rows and their pairs in one kernel call (places_pairs: the rows with a finite pose and three inliers
    # at least, each row's pairs sliced from one array), every row's error model in another (the residual sigma and
    # the prediction variance factor of each row's inliers: fit_errors): no numpy call a candidate.
    keep, ends, pairs = np.empty(h, np.int64), np.empty(h, np.int64), np.empty((h * n, 2), np.int64)
    kept = places_pairs(np.ascontiguousarray(a, np.complex128), inlier, np.ascontiguousarray(mid, np.int64), keep, ends,
                        pairs)
    if not kept:
        return []
    if kept < h:  # (usually every row is kept: no copies then)
        keep = keep[:kept]
        a, b, nfa, inlier, dist = a[keep], b[keep], nfa[keep], inlier[keep], dist[keep]
        nfa_points = None if nfa_points is None else nfa_points[keep]
    sigma, variance = fit_errors(z, dist, inlier)
    stops = ends[:kept].tolist()
    points = [None] * kept if nfa_points is None else nfa_points.tolist()
    return [Candidate(a=a_j, b=b_j, log10_nfa=nfa_j, inliers=end - start, sigma_axis_m=sigma_j,
                      variance_factor=variance_j, pairs=pairs[start:end], log10_nfa_points=points_j)
            for a_j, b_j, nfa_j, sigma_j, variance_j, start, end, points_j in zip(
                a.tolist(), b.tolist(), nfa.tolist(), sigma.tolist(), variance.tolist(), [0, *stops[:-1]], stops,
                points, strict=True)]


def residual_sigma(dist: np.ndarray) -> float:
    """Per-axis error of a similarity fitted to ``k`` pairs: ``sqrt(sum r^2 / (2k - 4))`` (4 parameters)."""
    return float(residual_sigmas(np.asarray(dist, np.float64)[None, :], np.ones((1, np.size(dist)), bool))[0])


def distinct(b: np.ndarray, order: np.ndarray, separation: np.ndarray, limit: int) -> list[int]:
    """Greedy non-maximum suppression: indices (in ``order``) at least ``separation`` apart.

    Each index of ``order`` in turn is kept when ``|b[i] - b[j]| > max(separation[i], separation[j])`` for every
    ``j`` kept before it, until ``limit`` are kept; one call of the compiled kernel (``places_distinct``: the Python
    loop over Python numbers it replaced, comparison for comparison).

    Examples
    --------
    >>> distinct(np.array([0, 1, 10, 10.5]), np.array([1, 0, 3, 2]), np.full(4, 2.0), 3)
    [1, 3]
    """
    b = np.ascontiguousarray(np.ravel(b), np.complex128)
    order = np.ascontiguousarray(np.ravel(order), np.int64)
    out = np.empty(min(order.size, max(int(limit), 1)), np.int64)  # the first row is kept whatever the limit
    kept = places_distinct(b, order, np.ascontiguousarray(np.ravel(separation), np.float64), int(limit), out)
    return out[:kept].tolist()


def polish(
    cand: Candidate, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, iterations: int = 2,
    evidence: ImageEvidence | None = None,
) -> Candidate:
    """Final association by optimal assignment, then the least-squares fit over it.

    Nearest-neighbour association with one image object per map object loses a true pair when two map
    objects lie closer together than the noise (the loser's own map object is its second nearest).
    Here every image object may take any map object of its label within the gate (3.5 sigma of the
    current fit, and at least its farthest inlier), and the pairs minimising the total squared
    distance are kept (a minimum-weight full bipartite matching).

    The fit is the image's evidence models' (:meth:`~mapdb.match.evidence.image.ImageEvidence.fit`; None: point
    residuals): :func:`~mapdb.match.evidence.relief.fit_with_relief` over the pairs whose image object is one of
    its ``anchors`` (not cut by the image border) when at least four are, else over all pairs; every pair
    still counts as an inlier.  With its ``errors`` (:class:`~mapdb.match.evidence.blobs.BlobErrors`), a fit that
    must use cut blobs places each where its blob puts its map object
    (:func:`~mapdb.match.evidence.blobs.placed_sources`: a cut building by the map object's stored area), not at
    the visible part's centroid, pulled inward.

    With its ``jackknife`` (objects extracted from masks: blobs, whose errors are not alike), the answer's error
    (``sigma_m``) is the larger of the fit's model, ``sigma_axis * sqrt(variance_factor)``, and the
    jackknife's (:func:`~mapdb.match.evidence.relief.leave_one_out_sigma`; folded into ``variance_factor``).  The model
    trusts the residuals to be independent and alike, which a handful of blobs, one of them a partly hidden
    park or a merged pair of buildings, are not.  Measured on the images of ``python
    benchmarks/rendered_masks.py --n 80`` (960 masks at 120-300 m, with and without heights; a ``/tmp`` script
    recording each final fit): every answer more than 2 m off (five, 2.1-4.1 m, with model sigmas of 0.47-1.0 m,
    so under ``max_sigma_m``) had a jackknife sigma of 1.3-2.0 m; on the correct answers the error over the
    jackknife sigma had median 1.11 and 90th percentile 2.22, where a calibrated 2-D Gaussian sigma gives 1.18
    and 2.15.  With ``--seed 1`` three answers 2.2-2.4 m off remain, with sigmas of 0.93-0.98 m: honest sigmas
    just under ``max_sigma_m = 1``, which lets an answer 2 m off through about one time in eight
    (``exp(-2)``); ``FastOptions(max_sigma_m=0.9)`` withholds them, at 0-1.9 points of localized a row.
    Points with like errors (ideal centroids plus Gaussian noise) keep the model's sigma, the right estimate
    for them: the jackknife's is noisier, and on ``benchmarks/matcher_core.py``'s 300 Andorra images (6-8
    objects in the ones it changed) it withheld 3 more answers, 0.5-1.7 m off.
    """
    evidence = evidence or ImageEvidence()
    a, b = cand.a, cand.b
    w = _projected(evidence, a, b, z)  # the first association's projections too
    farthest = float(np.abs(w[cand.pairs[:, 0]] - index.z[cand.pairs[:, 1]]).max())
    gate = max(GATE_SIGMAS * cand.sigma_axis_m, farthest, 1e-9)
    pairs = cand.pairs
    fit: ReliefFit | None = None
    fitted: tuple[list[int], list[int]] | None = None  # the last fit's pairs as Python lists (compared cheaply)
    scale = abs(a)
    for it in range(iterations):
        if it:
            w = _projected(evidence, a, b, z)
        rows, cols, costs = index.within(w, img_label, gate, 3)
        if not rows.size:
            return cand
        # all_distinct of rows and cols on lists made once: their lists also say whether the pairs are the last fit's.
        listed = rows.tolist(), cols.tolist()
        if len(set(listed[0])) == len(listed[0]) and len(set(listed[1])) == len(listed[1]):
            found = _paired(rows, cols)  # no image or map object has a rival: nothing to assign
        else:
            found = _assigned(rows, cols, costs, gate)
            listed = found[:, 0].tolist(), found[:, 1].tolist()
        if fitted is not None and listed == fitted:
            break  # the pairs of the last fit: fitting them again gives it again
        pairs, fitted = found, listed
        scale = abs(a)  # the scale cut blobs are placed at, the jackknife's too
        fit = evidence.fit(z, index, pairs, scale, b)
        if fit is None:
            return cand
        a, b = fit.a, fit.b
    if fit is None:
        return cand
    sigma_axis, variance = evidence.error(z, index, pairs, fit, scale)
    return Candidate(a=a, b=b, log10_nfa=cand.log10_nfa, inliers=len(pairs), sigma_axis_m=sigma_axis,
                     variance_factor=variance, pairs=pairs, log10_nfa_points=cand.log10_nfa_points)


def _assigned(rows: np.ndarray, cols: np.ndarray, costs: np.ndarray, gate: float) -> np.ndarray:
    """The pairs ``(k, 2)`` of image objects ``rows`` and map objects ``cols`` (each pair's squared distance in
    ``costs``, all within ``gate``) minimising the total squared distance, one map object an image object."""
    img_u, img_inv = np.unique(rows, return_inverse=True)
    map_u, map_inv = np.unique(cols, return_inverse=True)
    big = 1e6 * (gate * gate + 1.0)
    cost = np.full((img_u.size, map_u.size), big)
    cost[img_inv, map_inv] = costs
    # Every pair is an edge (non-pairs at a prohibitive cost), so a full matching always exists; this is
    # linear_sum_assignment without importing scipy.optimize (a tenth of a second at start-up).
    # Costs are shifted by one so that no pair (a zero distance) reads as a missing edge; every full
    # matching has the same number of pairs, so the shift changes none.
    edges = csr_array(cost + 1.0)
    if img_u.size <= map_u.size:
        r_opt, c_opt = np.arange(img_u.size), min_weight_full_bipartite_matching(edges)[1]
    else:
        r_opt, c_opt = min_weight_full_bipartite_matching(edges.T.tocsr())[1], np.arange(map_u.size)
    good = cost[r_opt, c_opt] < big
    return _paired(img_u[r_opt[good]], map_u[c_opt[good]])


def _paired(image_ids: np.ndarray, map_ids: np.ndarray) -> np.ndarray:
    """Pairs ``(k, 2)`` (int64) of image and map ids: ``np.column_stack`` of them (integer arrays) in half its calls."""
    pairs = np.empty((image_ids.size, 2), np.int64)
    pairs[:, 0] = image_ids
    pairs[:, 1] = map_ids
    return pairs


def _projected(evidence: ImageEvidence, a: complex, b: complex, z: np.ndarray) -> np.ndarray:
    """The image objects where pose ``(a, b)`` puts them: ``a z + b``, or over terrain each ray cast onto the
    ground (:meth:`~mapdb.match.evidence.image.ImageEvidence.project`)."""
    if evidence.terrain is None:
        return a * z + b
    return evidence.project(np.array([a]), np.array([b]), z)[0]


def pose_shift(a: Any, b: Any, a0: complex, b0: complex, diag_px: float) -> Any:
    """How far (map metres, at most) any point of the image moves between poses ``(a, b)`` and ``(a0, b0)``.

    ``a``, ``b`` are complex numbers (a float back) or arrays of them (an array back).

    ``|a z + b - (a0 z + b0)| <= |b - b0| + |a - a0| diag_px / 2`` over the image (``|z| <= diag_px / 2``):
    two poses are one place when this is below the place's width, so the same centre seen a quarter turn
    apart (a square lattice does that) is two places, not one.

    Examples
    --------
    >>> float(pose_shift(1.0, 3.0, 1.0, 0.0, 100.0)), float(pose_shift(1j, 0.0, 1.0, 0.0, 100.0)) > 70
    (3.0, True)
    """
    return abs(b - b0) + abs(a - a0) * (diag_px / 2.0)  # builtin abs: Python numbers stay cheap in a loop


def merged_one_by_one(pool: list[Candidate], diag_px: float) -> list[Candidate]:
    """:func:`merge_candidates` of a pool sorted best first, a candidate at a time (the plain loop over
    :func:`pose_shift` that the array operations of a big pool reproduce)."""
    kept: list[Candidate] = []
    for c in pool:
        sep = abs(c.a) * diag_px * PLACE_FRACTION
        if all(pose_shift(c.a, c.b, k.a, k.b, diag_px) > sep for k in kept):
            kept.append(c)
    return kept


def merge_candidates(pool: list[Candidate], diag_px: float) -> list[Candidate]:
    """Best first, one candidate per place (refinement often brings several hypotheses to one pose)."""
    pool = sorted(pool, key=lambda c: (c.log10_nfa, -c.inliers))
    if len(pool) < _MERGED_AT_ONCE_FROM:
        return merged_one_by_one(pool, diag_px)
    # The search merges its pool with each round's candidates: an image that matches nowhere runs every round
    # and its pool grows to dozens, whose pairwise pose shifts are then taken in a few array operations (the
    # same numbers as pose_shift's), the greedy choice staying a loop over Python lists.
    a = np.array([c.a for c in pool], np.complex128)
    b = np.array([c.b for c in pool], np.complex128)
    shift = np.abs(b[:, None] - b[None, :]) + np.abs(a[:, None] - a[None, :]) * (diag_px / 2.0)
    apart = (shift > (np.abs(a) * diag_px * PLACE_FRACTION)[:, None]).tolist()
    chosen: list[int] = []
    for i, row in enumerate(apart):
        if all(row[j] for j in chosen):
            chosen.append(i)
    return [pool[i] for i in chosen]


# Pools of at least this many candidates are merged with array operations (below it the loop is cheaper).
_MERGED_AT_ONCE_FROM = 16
