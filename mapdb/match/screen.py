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

On point residuals over an in-memory index (every image without areas, cut blobs or terrain) a round is eleven
kernel calls back to back, the steps between the verification's calls among them (``_kernel_places.c``: the
shortlist, the distinct places, the labels' reach, the candidates' pairs), each array converted once; otherwise the
stages' functions run one by one, as above.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ._kernel import (
    objects_density,
    objects_knn,
    places_chosen,
    places_shortlist,
    screen_knn,
    verify_decision,
    verify_refine,
    verify_screen,
)
from .evidence.areas import points_floor
from .evidence.image import ImageEvidence
from .evidence.points import GATE_SIGMAS
from .hypotheses import Hypotheses, pose_votes, prioritise
from .mapobjects.fused_arrays import FusedArrays
from .nfa import LOG10_FLOOR, log10_trials
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
    fused = index.fused()
    if fused is not None and _points_only(evidence) and len(hyps) and z.size > 4:
        return _screened_fused(hyps, z, img_label, index, fused, screen_of, diag_px, log10_tests, opts)
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


def _points_only(evidence: ImageEvidence | None) -> bool:
    """Whether the decision and the refinement read point residuals alone (no areas, blob errors or terrain)."""
    return evidence is None or (evidence.areas is None and evidence.errors is None and evidence.terrain is None)


def _screened_fused(hyps: Hypotheses, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, f: FusedArrays,
                    screen_of: np.ndarray, diag_px: float, log10_tests: float, opts: FastOptions) -> list[Candidate]:
    """:func:`_screened` on point residuals over an in-memory index (``f``: :meth:`ObjectIndex.fused`) with more than
    four image objects: the kernel calls :func:`screen`, :meth:`ObjectIndex.neighbours`, :func:`decision_nfa` (twice)
    and :func:`refine` make there, with the same arguments, each array converted once.

    The usual analysis image is one round; its screen cost 0.5 ms, two thirds of it the Python and numpy calls
    between these five kernel calls (each wrapper converting, checking and looking up the same arrays again)."""
    zc, lab, n = np.ascontiguousarray(z, np.complex128), np.ascontiguousarray(img_label, np.int64), z.size
    objects = np.ascontiguousarray(screen_of[hyps.img_ids[:, 0]], np.int64)
    if objects.shape[1] <= 4:
        nfa = np.full(len(hyps), np.inf)
    else:
        nfa = np.empty(len(hyps))
        verify_screen(*f.tree, np.ascontiguousarray(hyps.a, np.complex128), np.ascontiguousarray(hyps.b, np.complex128),
                      zc, objects, lab, f.reach, f.density, f.half_gap, 4,
                      log10_tests + log10_trials(objects.shape[1] - 4), LOG10_FLOOR, nfa)
    # The shortlist, its projections and their labels (places_shortlist: argsort, row takes, a z + b, repeat).
    h, q = min(opts.shortlist, len(hyps)), hyps.map_z.shape[1]
    a, b, ids, map_z = np.empty(h, np.complex128), np.empty(h, np.complex128), np.empty((h, q), np.int64), np.empty(
        (h, q), np.complex128)
    w, w_label = np.empty(h * n, np.complex128), np.empty(h * n, np.int64)
    places_shortlist(nfa, np.ascontiguousarray(hyps.a, np.complex128), np.ascontiguousarray(hyps.b, np.complex128),
                     np.ascontiguousarray(hyps.img_ids, np.int64), np.ascontiguousarray(hyps.map_z, np.complex128), zc,
                     lab, h, a, b, ids, map_z, w, w_label)
    # One query of the shortlist's projections serves both decisions and the refinement's first association.
    k = max(1 + q, opts.density_neighbours)
    near_d, near_i = np.empty((h * n, k)), np.empty((h * n, k), np.int64)
    objects_knn(*f.tree, w, w_label, float(f.half_gap), f.n, near_d, near_i)
    offset = log10_tests + log10_trials(n - 4)
    nfa = np.empty(h)
    verify_decision(near_d, near_i, 1 + q, f.z, map_z, ids, zc, lab, f.reach, f.density_2d, f.counts, 0, f.kd_floor,
                    4, offset, LOG10_FLOOR, nfa)
    # The distinct places, their rows and their density discs (places_chosen: argsort, distinct, row takes, radii).
    # a and b are this function's own arrays: the refinement's kernel refits them in place.
    m = min(max(opts.refine_candidates, 1), h)  # distinct keeps the first place whatever the limit
    outs = (np.empty(m, np.complex128), np.empty(m, np.complex128), np.empty((m, q), np.int64),
            np.empty((m, q), np.complex128), np.empty((m * n, k)), np.empty((m * n, k), np.int64), np.empty(m))
    c = places_chosen(nfa, a, b, ids, map_z, near_d, near_i, n, diag_px, PLACE_FRACTION, opts.density_radius_factor,
                      m, *outs)
    a, b, ids, map_z, radius = outs[0][:c], outs[1][:c], outs[2][:c], outs[3][:c], outs[6][:c]
    near_d, near_i = outs[4][:c * n], outs[5][:c * n]
    density = np.empty((c, f.n_labels))
    objects_density(f.trees, b, radius, f.disc, f.bounds, f.present, f.half_gap, density)
    reach = index.label_reach(density)
    nfa = np.empty(c)
    verify_decision(near_d, near_i, 1 + q, f.z, map_z, ids, zc, lab, reach, density, f.counts,
                    opts.density_neighbours, f.kd_floor, 4, offset, LOG10_FLOOR, nfa)
    inlier, mid, dist = np.empty((c, n), bool), np.empty((c, n), np.int64), np.empty((c, n))
    verify_refine(*f.tree, a, b, zc, lab, f.z, reach, density, f.half_gap, 2, near_d, near_i, offset, LOG10_FLOOR,
                  GATE_SIGMAS, np.empty(c), inlier, mid, dist)
    return candidates(a, b, nfa, inlier, mid, dist, z)
