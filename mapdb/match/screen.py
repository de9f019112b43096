"""Screen and verify one round's hypotheses: the stage after :mod:`~mapdb.match.hypotheses`, handing
refined candidates to the decision (:mod:`~mapdb.match.decide`).

A round's hypotheses (:class:`~mapdb.match.hypotheses.Hypotheses`) go through, in order:

1. **screen** (:func:`~mapdb.match.verify.screen`): a cheap test on the objects around each quad, the region's
   mean densities; the ``shortlist`` best go on;
2. **verify** (:func:`~mapdb.match.verify.decision_nfa`): the full test on every image object, tolerances
   shaped by each quad's geometry; the ``refine_candidates`` best distinct places go on;
3. **decide** each place: the same test with the label densities around it and the image's evidence models
   (:class:`~mapdb.match.evidence.image.ImageEvidence`: areas, cut blobs), taken on the hypotheses as they came
   from their quads (AC-RANSAC's rule: a model refitted to its own inliers looks better than chance says);
   with areas, floored by the same test without them (:func:`~mapdb.match.evidence.areas.points_floor`);
4. **refine** (:func:`~mapdb.match.verify.refine`): re-association and refit, which only improves the position.

Hypotheses whose coarse pose another one shares (:func:`~mapdb.match.hypotheses.pose_votes`) go through first:
a right place is found by several image quads, a chance hit of the index by one.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ._kernel import screen_knn
from .evidence.areas import points_floor
from .evidence.image import ImageEvidence
from .hypotheses import Hypotheses, pose_votes, prioritise
from .options import FastOptions
from .refine import PLACE_FRACTION, Candidate, candidates, distinct
from .verify import ObjectIndex, decision_nfa, refine, screen

__all__ = ["screen_neighbours", "screen_round"]

_SHARED_FIRST_FROM = 4  # shortlists: rounds with more hypotheses screen the shared poses first


def screen_neighbours(z: np.ndarray, opts: FastOptions) -> np.ndarray:
    """``(n, k)``: each image object's ``opts.screen_objects`` nearest image objects (itself first; equal
    distances: the lower index first), the objects the screen projects for a hypothesis whose quad starts there.

    One call of the compiled kernel (``screen_knn``: every pair of the image's few dozen objects read directly),
    not a tree built for each image: scipy's cKDTree build and query cost 0.14 ms an image there (its arrays and
    checks), the kernel's call a few microseconds.

    Examples
    --------
    >>> screen_neighbours(np.array([0, 1, 3, 1j]), FastOptions(screen_objects=3)).tolist()
    [[0, 1, 3], [1, 0, 3], [2, 1, 0], [3, 0, 1]]
    """
    z = np.ascontiguousarray(np.ravel(z), np.complex128)
    out = np.empty((z.size, min(opts.screen_objects, z.size)), np.int64)
    if z.size:
        screen_knn(z, out)
    return out


def screen_round(hyps: Hypotheses, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, screen_of: np.ndarray,
                 diag_px: float, log10_tests: float, opts: FastOptions,
                 evidence: ImageEvidence | None = None) -> list[Candidate]:
    """Screen, test, decide and refine one round's hypotheses; the refined candidates.

    The hypotheses whose coarse pose another one shares are screened first (:func:`pose_votes`): a right
    place is found by several image quads, a chance hit of the index by one.  Only when they give no
    accepted candidate is the whole round screened, as if the first pass had not been (every hypothesis of
    the round is a test either way).  A big map's lookups are mostly chance hits (a world of 5M objects:
    242 hypotheses a round against Andorra's 95), so the usual image screens a few dozen.
    """
    votes = None
    # A round a few times the shortlist is screened whole: a first pass would save little there, and when it
    # fails (a right place found once) the round is screened twice.
    if len(hyps) > _SHARED_FIRST_FROM * opts.shortlist:
        votes = pose_votes(hyps.a, hyps.b, diag_px)
        first = np.flatnonzero(votes >= 2)
        if 0 < first.size < len(hyps):
            found = _screened(hyps.take(first), votes[first], z, img_label, index, screen_of, diag_px, log10_tests,
                              opts, evidence)
            if found and min(c.log10_nfa for c in found) < opts.log10_epsilon:
                return found
    return _screened(hyps, votes, z, img_label, index, screen_of, diag_px, log10_tests, opts, evidence)


def _screened(hyps: Hypotheses, votes: np.ndarray | None, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex,
              screen_of: np.ndarray, diag_px: float, log10_tests: float, opts: FastOptions,
              evidence: ImageEvidence | None) -> list[Candidate]:
    """:func:`screen_round` on the hypotheses given: at most ``opts.max_verified``, the most shared poses first
    (``votes``: :func:`pose_votes`, computed here if None and needed)."""
    if len(hyps) > opts.max_verified:
        hyps = hyps.take(prioritise(hyps.a, hyps.b, diag_px, opts.max_verified, votes))
    # Screen: the shortlist ...
    hyps = hyps.take(screen(hyps.a, hyps.b, hyps.img_ids, screen_of, z, img_label, index, log10_tests,
                            opts.shortlist))
    # ... gets the full test (all objects, tolerances shaped by each quad's geometry) ...  One query of the
    # shortlist's projections serves this test, the decision's (its nearest objects and densities) and the first
    # association of the refinement: they all ask about the same points.
    near = index.neighbours(hyps.a[:, None] * z[None, :] + hyps.b[:, None], img_label,
                            max(1 + hyps.map_z.shape[1], opts.density_neighbours))
    nfa = decision_nfa(hyps.a, hyps.b, hyps.img_ids, hyps.map_z, z, img_label, index, index.density, log10_tests,
                       near=near)
    chosen = distinct(hyps.b, nfa.argsort(kind="stable"), np.abs(hyps.a) * diag_px * PLACE_FRACTION,
                      opts.refine_candidates)
    hyps = hyps.take(chosen)
    near = None if near is None else near.take(chosen)
    # ... and the decision is that test with the label densities around each place.  It is taken on the
    # hypotheses as they came from their quads (AC-RANSAC's rule: a model refitted to its own inliers looks
    # better than chance says); refinement then only improves the position.
    radius = opts.density_radius_factor * np.abs(hyps.a) * diag_px / 2.0
    density = index.local_density(hyps.b, radius)
    a, b = hyps.a, hyps.b
    if evidence is not None and evidence.terrain is not None:  # over terrain: each quad's rays on its heights
        a, b = evidence.terrain.requad(a, b, z[hyps.img_ids], hyps.map_z)
        near = None  # other projections
    nfa = decision_nfa(a, b, hyps.img_ids, hyps.map_z, z, img_label, index, density, log10_tests,
                       opts.density_neighbours, evidence, radius, near)
    points = None
    if evidence is not None and evidence.areas is not None:
        # The areas may add evidence, never take away a place the positions alone make certain.
        points = decision_nfa(a, b, hyps.img_ids, hyps.map_z, z, img_label, index, density, log10_tests,
                              opts.density_neighbours, replace(evidence, areas=None), radius, near)
        nfa = points_floor(nfa, points)
    a, b, _, inlier, mid, dist = refine(a, b, z, img_label, index, density, log10_tests, 2, evidence, near=near)
    return candidates(a, b, nfa, inlier, mid, dist, z, points)
