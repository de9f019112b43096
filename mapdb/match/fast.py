"""The fast matcher: indexed quad invariants, vectorised verification, an a contrario decision.

The design follows blind astrometry (astrometry.net's quads) and AC-RANSAC, one module a stage:
:mod:`~mapdb.match.quads` (index), :mod:`~mapdb.match.hypotheses`, :mod:`~mapdb.match.verify`,
:mod:`~mapdb.match.decision` and :mod:`~mapdb.match.refine`; :func:`match_fast` hands each the next.

1. **Index** (built once per map, or per map tile, and cached).  Every map object
   and three of its ``map_neighbours`` nearest neighbours form a *quad*.  Its two
   most distant points ``A``, ``B`` define a frame in which ``A = 0`` and
   ``B = 1`` (complex numbers); the other two points' coordinates in that
   frame, ``t = (P - A) / (B - A)``, are four numbers invariant to translation,
   rotation and scale, but not to reflection (images are not mirrored).  The
   labels of ``A, B, C, D`` are part of the key.  ``(A, B)`` and ``(C, D)`` are
   ordered canonically so that each quad is stored once, in a cKDTree over
   ``(t_C, t_D, label key)``.
2. **Hypotheses.**  Image quads (each object with three of its
   ``image_neighbours`` nearest, fewer than the map's so that a missing or
   extra object still leaves quads whose members are all among the map's
   neighbours) are looked up with a radius from the pixel error and the quad's
   size; near the canonical-order boundaries every ordering is looked up, so
   noise cannot hide a quad behind a flip.  Each hit gives four
   correspondences and a least-squares similarity ``z -> a z + b`` (pixels,
   centred, y up, to map metres): ``b`` is the map point under the image centre.
   Objects nearest the image centre anchor the first quads (their
   neighbourhoods are least cut by the image edge), a few anchors per round;
   the search stops at the first round that accepts.
3. **Verification**, all hypotheses at once: project image objects into the map
   and find each one's nearest map object of its label (a cKDTree per label).
   A cheap screen (the objects around each quad, the region's mean densities)
   ranks the hypotheses; the best are tested on every image object.  Hypotheses
   whose coarse pose another one shares (a right place is found by several
   image quads, a chance hit of a big map's index by one) are screened first,
   and the whole round only when they give nothing accepted.
4. **Decision** (:mod:`mapdb.match.decision`): the number of false alarms of a
   hypothesis *as it came from its quad* (refitting a model to its own inliers
   makes it look better than chance says), with tolerance discs shaped by how
   far each object lies from the quad, the quad's own map points excluded
   from the evidence, and the label densities counted around the answer.
   Accepted when ``log10 NFA < log10_epsilon``, no distinct runner-up comes
   within ``ambiguity_margin`` of the winner's score, and the final position's
   estimated error is within ``max_sigma_m``.
5. **Refinement** of the winner: re-association and least-squares similarity
   (Umeyama, no reflection) over all inliers, twice, then a final optimal
   one-to-one assignment (minimum-weight bipartite matching) and fit: with the true
   correspondences found, the position is the least-squares bound.

Objects extracted from masks bring what they know of their errors (``anchorable``, ``area_px``,
``outward``): blobs cut by the border anchor no quad of the first rounds, are verified in an ellipse along
their border's normal (:mod:`mapdb.match.evidence.blobs`; cut buildings with an area, from where each candidate map
object's own area puts it), and join quads only in the last rounds (:mod:`mapdb.match.cut_quads`).

Lookup tolerances are tried in passes (``pixel_sigmas``): a tight one first,
a wider one only when the first finds nothing certain, so the usual image costs
the tight pass.  Every hypothesis of every round counts as a test.
"""


from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._scipy import cKDTree
from .ambiguity import find_rivals
from .cut_quads import cut_batches, cut_round_hypotheses
from .evidence.areas import ImageAreas, solid_objects
from .evidence.blobs import BlobErrors
from .hypotheses import anchor_batches, pose_votes, prioritise, round_hypotheses
from .quads import QuadIndex
from .refine import PLACE_FRACTION, Candidate, candidates, distinct, merge_candidates, polish
from .verify import ObjectIndex, decision_nfa, refine, screen

__all__ = ["Candidate", "FastOptions", "MatchResult", "ObjectIndex", "QuadIndex", "match_fast"]


@dataclass(frozen=True)
class FastOptions:
    """Tuning of :func:`match_fast`; the defaults are the ones the benchmarks measured.

    Attributes
    ----------
    map_neighbours, image_neighbours : int
        Neighbours per anchor object whose triples form quads, in the map and in the image.
    pixel_sigmas : tuple of float
        Assumed pixel error (1 sigma) of the lookup passes, tried in order (each over all anchor
        batches) until a match is accepted.
    tolerance_factor : float
        Lookup radius in units of the quad invariant's predicted standard error (2.0 ~ 99% in 4-D).
    max_invariant_radius : float
        Image quads needing a wider lookup radius (tiny quads) are not looked up.
    max_hits_per_quad : int
        At most this many nearest map quads per lookup.
    max_verified : int
        Hypotheses screened per round, those whose pose most others share first
        (:func:`~mapdb.match.hypotheses.prioritise`).  Andorra's images bring 57-134 a round, so 256 rarely
        binds there; a 5M-object world (245 jittered copies of three towns) brings
        500-830 (chance hits of a key space of 183 million quads: a world without near-copies brings as
        many), and the screen's KD-tree queries grew with them.
        At 256 (3,000 before) that world's lost-in-space answers cost 0.85x the CPU time, 99 of 100 answers
        the same (``python benchmarks/lost_in_space_index.py --lookups-only --worlds 5000000 --jitter 2
        --baseline 0ef3d71``); Andorra's, the rendered masks' and the paper bench's answers were kept, bar two
        rendered images it improved.  128 answered one world image wrongly.
    screen_objects : int
        Image objects (around each hypothesis's quad) used to screen hypotheses; the shortlist is
        tested on all objects.
    anchors_per_batch : int
        Image objects (nearest the centre first) whose quads are looked up together; the search stops
        at the first batch that gives an accepted match.
    shortlist : int
        Best screened hypotheses given the full test.
    refine_candidates : int
        Distinct places per round given the decision test and refined.
    log10_epsilon : float
        Accept when log10 NFA is below this.
    ambiguity_margin : float
        Reject as ambiguous when a distinct runner-up is accepted too and scores within this of the best.
    density_radius_factor : float
        Local label densities are counted within this many footprint half-diagonals of the answer.
    max_candidates : int
        Runners-up reported.
    max_sigma_m : float or None
        Withhold (reject as imprecise, listing it as a candidate) an answer whose estimated 1-sigma
        position error exceeds this many metres: a few objects in one corner of the image place its
        centre poorly, and an answer metres off is worse than none.
    max_objects : int
        An image with more objects is matched on the ``max_objects`` nearest its centre (ties broken
        by input order): the decision's cost grows with the square of the objects, and a few hundred
        objects place an image as well as thousands.  This bounds memory and time per image.
    density_neighbours : int
        The decision's label density around each projected image object comes from the distance to
        its ``density_neighbours``-th nearest map object of its label (0: one density per label around
        the answer, as the ranking uses).
    max_batches : int
        Anchor batches tried per lookup pass: an image that matches nowhere costs at most
        ``len(pixel_sigmas) * max_batches`` rounds, whatever its number of objects.
    ambiguity_anchors : int
        The winner's inliers (nearest the image centre) whose quads are looked up again in the quad indexes
        for far places holding the same pattern (:mod:`mapdb.match.ambiguity`; 0, the default: the repeats
        within the footprint and the search's runner-ups only, about 15 % less time an image).
    ambiguity_places : int
        At most this many other places (runner-ups, repeats, look-up hits; those where most image objects
        land near a map object first) are refitted beside the winner.
    """

    map_neighbours: int = 8
    image_neighbours: int = 5
    pixel_sigmas: tuple[float, ...] = (1.5, 4.0)
    tolerance_factor: float = 2.0
    max_invariant_radius: float = 0.3
    max_hits_per_quad: int = 16
    max_verified: int = 256
    screen_objects: int = 12
    anchors_per_batch: int = 6
    shortlist: int = 16
    refine_candidates: int = 4
    log10_epsilon: float = -4.0
    ambiguity_margin: float = 1.0
    density_radius_factor: float = 1.5
    max_candidates: int = 5
    max_sigma_m: float | None = 1.0
    max_objects: int = 256
    density_neighbours: int = 6
    max_batches: int = 8
    ambiguity_anchors: int = 0
    ambiguity_places: int = 8


@dataclass
class MatchResult:
    """What :func:`match_fast` found: ``best`` is None when the image is rejected (``reason`` says why)."""

    best: Candidate | None
    candidates: list[Candidate]
    reason: str | None
    n_hypotheses: int
    rounds: int


def match_fast(
    z: np.ndarray,
    img_label: np.ndarray,
    objects: ObjectIndex,
    quads: Sequence[QuadIndex],
    diag_px: float,
    *,
    options: FastOptions | None = None,
    prior: tuple[float, float, float] | None = None,
    scale_range: tuple[float, float] | None = None,
    anchorable: np.ndarray | None = None,
    area_px: np.ndarray | None = None,
    outward: np.ndarray | None = None,
) -> MatchResult:
    """Match image objects against a map's indexes.

    Parameters
    ----------
    z : complex array (n,)
        Image objects in pixels relative to the image centre, **y up** (``x - w/2 + i (h/2 - y)``).
    img_label : int array (n,)
        Label codes in ``objects.labels``.
    objects : ObjectIndex
        The map objects answers are verified against.
    quads : sequence of QuadIndex
        Where hypotheses are looked up (the whole map's, or the tiles around a prior); anything with
        :meth:`QuadIndex.lookup` and ``n_quads``.
    diag_px : float
        Image diagonal in pixels (sets the footprint for densities and pose bins).
    options : FastOptions, optional
    prior : (x, y, radius), optional
        The map point under the image centre must lie within ``radius`` of ``(x, y)`` (hypotheses
        within 1.1 times the radius are tried).
    scale_range : (low, high), optional
        Allowed metres per pixel (from a known altitude and field of view).
    anchorable : bool array (n,), optional
        Objects that may build hypotheses (default all): objects cut by the image border are better left
        out (:func:`~mapdb.match.hypotheses.anchor_batches`).  Ignored when fewer than 4 are anchorable.
    area_px : float array (n,), optional
        Pixel area of each object (NaN where unknown): the decision then also asks each object's map object
        for a compatible stored area (:mod:`mapdb.match.evidence.areas`; ``anchorable`` says which blobs are whole).
    outward : complex array (n,), optional
        Unit outward normal (y up) of the image border each object touches, 0 for whole ones
        (:func:`mapdb.match.evidence.blobs.outward_normals` of the objects' boxes).  With it and ``anchorable`` the
        decision measures each cut blob in an ellipse along that normal (:mod:`mapdb.match.evidence.blobs`) and, when
        the whole blobs' quads find nothing, quads holding cut blobs are looked up
        (:mod:`mapdb.match.cut_quads`).

    Returns
    -------
    MatchResult
    """
    opts = options or FastOptions()
    z, img_label, anchorable, area_px, outward = _central_objects(z, img_label, opts.max_objects, anchorable,
                                                                  area_px, outward)
    reason = _unmatchable(z.size, objects, quads)
    if reason is not None:
        return MatchResult(None, [], reason, 0, 0)
    areas = ImageAreas.of(area_px, anchorable, img_label, objects.labels)
    solid_px = None if area_px is None else np.where(solid_objects(img_label, objects.labels), area_px, np.nan)
    errors = BlobErrors.of(z, outward, solid_px)
    whole = anchorable
    if anchorable is not None and anchorable.sum() < 4:
        anchorable = None
    pool, n_tests, done_rounds = _search(z, img_label, objects, quads, diag_px, opts, prior, scale_range,
                                         anchorable, areas, errors, whole)
    return _decide(pool, z, img_label, objects, opts, n_tests, done_rounds, quads, diag_px, prior, scale_range,
                   whole=anchorable, blobs=errors is not None or areas is not None, errors=errors)


def _central_objects(z, img_label, max_objects: int, anchorable=None, area_px=None,
                     outward=None) -> tuple[Any, ...]:
    """The image objects as arrays, at most ``max_objects`` of them nearest the centre (input order kept):
    ``z``, ``img_label`` and the per-object arrays given (None stays None), cut alike."""
    z = np.asarray(z, dtype=np.complex128)
    arrays = [np.asarray(img_label, dtype=np.int64)] + [
        None if v is None else np.asarray(v, dtype=t)
        for v, t in ((anchorable, bool), (area_px, np.float64), (outward, np.complex128))
    ]
    if z.size > max_objects:
        central = np.sort(np.argsort(np.abs(z), kind="stable")[:max_objects])
        z = z[central]
        arrays = [None if v is None else v[central] for v in arrays]
    return (z, *arrays)


def _unmatchable(n: int, objects: ObjectIndex, quads: Sequence[QuadIndex]) -> str | None:
    """Why ``n`` image objects cannot be matched against these indexes at all, or None."""
    # The counts, not len(): an index that reads pages as queries need them holds none before the first.
    total = int(objects.counts.sum())
    if n < 4:
        return f"{n} objects: the fast matcher needs at least 4"
    if total < 4:
        return f"the map has only {total} objects here: at least 4 are needed"
    if not any(q.n_quads for q in quads):
        return f"the map's {total} objects here form no pattern to match"
    return None


def _search(z, img_label, objects, quads, diag_px, opts, prior, scale_range,
            anchorable=None, areas=None, errors=None, whole=None) -> tuple[list[Candidate], int, int]:
    """The lookup rounds (pixel sigma x anchor batch) until one accepts: candidates best first, tests, rounds."""
    n = z.size
    screen_of = cKDTree(np.column_stack([z.real, z.imag])).query(
        np.column_stack([z.real, z.imag]), k=min(opts.screen_objects, n)
    )[1].reshape(n, -1)
    batches = anchor_batches(z, opts, anchorable)
    rounds = [(sigma_px, batch, False) for sigma_px in opts.pixel_sigmas for batch in batches]
    if errors is not None and whole is not None:
        rounds += [(opts.pixel_sigmas[-1], batch, True) for batch in cut_batches(z, whole, opts)]
    n_tests = 0
    pool: list[Candidate] = []
    done_rounds = 0
    for sigma_px, batch, with_cut in rounds:
        done_rounds += 1
        if with_cut:
            a, b, img_ids, map_z = cut_round_hypotheses(z, img_label, batch, quads, opts, sigma_px, errors, whole,
                                                        prior, scale_range)
        else:
            a, b, img_ids, map_z = round_hypotheses(z, img_label, batch, quads, opts, sigma_px, prior, scale_range)
        n_tests += a.size
        if not a.size:
            continue
        pool = merge_candidates(pool + _verify_round(a, b, img_ids, map_z, z, img_label, objects, screen_of, diag_px,
                                                     math.log10(n_tests), opts, areas, errors), diag_px)
        if pool and pool[0].log10_nfa < opts.log10_epsilon:
            break
    return pool, n_tests, done_rounds


_SHARED_FIRST_FROM = 4  # shortlists: rounds with more hypotheses screen the shared poses first


def _verify_round(a, b, img_ids, map_z, z, img_label, index, screen_of, diag_px, log10_tests, opts,
                  areas=None, errors=None) -> list[Candidate]:
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
    if len(a) > _SHARED_FIRST_FROM * opts.shortlist:
        votes = pose_votes(a, b, diag_px)
        first = np.flatnonzero(votes >= 2)
        if 0 < first.size < len(a):
            found = _screened(a[first], b[first], img_ids[first], map_z[first], votes[first], z, img_label, index,
                              screen_of, diag_px, log10_tests, opts, areas, errors)
            if found and min(c.log10_nfa for c in found) < opts.log10_epsilon:
                return found
    return _screened(a, b, img_ids, map_z, votes, z, img_label, index, screen_of, diag_px, log10_tests, opts, areas,
                     errors)


def _screened(a, b, img_ids, map_z, votes, z, img_label, index, screen_of, diag_px, log10_tests, opts,
              areas=None, errors=None) -> list[Candidate]:
    """:func:`_verify_round` on the hypotheses given: at most ``opts.max_verified``, the most shared poses first
    (``votes``: :func:`pose_votes`, computed here if None and needed)."""
    if len(a) > opts.max_verified:
        pick = prioritise(a, b, diag_px, opts.max_verified, votes)
        a, b, img_ids, map_z = a[pick], b[pick], img_ids[pick], map_z[pick]
    top = screen(a, b, img_ids, screen_of, z, img_label, index, log10_tests, opts.shortlist)
    a, b, img_ids, map_z = a[top], b[top], img_ids[top], map_z[top]
    # The shortlist gets the full test (all objects, tolerances shaped by each quad's geometry) ...
    nfa = decision_nfa(a, b, img_ids, map_z, z, img_label, index, index.density, log10_tests)
    chosen = distinct(b, np.argsort(nfa, kind="stable"), np.abs(a) * diag_px * PLACE_FRACTION,
                      opts.refine_candidates)
    a, b, img_ids, map_z = a[chosen], b[chosen], img_ids[chosen], map_z[chosen]
    # ... and the decision is that test with the label densities around each place.  It is taken on the
    # hypotheses as they came from their quads (AC-RANSAC's rule: a model refitted to its own inliers looks
    # better than chance says); refinement then only improves the position.
    radius = opts.density_radius_factor * np.abs(a) * diag_px / 2.0
    density = index.local_density(b, radius)
    nfa = decision_nfa(a, b, img_ids, map_z, z, img_label, index, density, log10_tests, opts.density_neighbours,
                       areas, radius, errors)
    a, b, _, inlier, mid, dist = refine(a, b, z, img_label, index, density, log10_tests, 2)
    return candidates(a, b, nfa, inlier, mid, dist, z)


def _decide(pool: list[Candidate], z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, opts: FastOptions,
            n_tests: int, rounds: int, quads: Sequence[QuadIndex], diag_px: float,
            prior: tuple[float, float, float] | None, scale_range: tuple[float, float] | None,
            whole: np.ndarray | None = None, blobs: bool = False, errors: BlobErrors | None = None) -> MatchResult:
    """Accept the best candidate, or say why not: none, not certain enough, ambiguous, imprecise.

    Ambiguous: a distinct place comes within ``ambiguity_margin`` of the winner's score, either one of the
    search's runner-ups (its own score) or one of the places where the map repeats the winner's pattern,
    looked for on purpose and scored beside the winner (:func:`mapdb.match.ambiguity.find_rivals`).
    """
    if not pool:
        return MatchResult(None, [], "no consistent pattern found in the map", n_tests, rounds)
    best, rest = pool[0], pool[1 : 1 + opts.max_candidates]
    listed = pool[: opts.max_candidates]
    if best.log10_nfa >= opts.log10_epsilon:
        reason = (f"no match is certain enough (best log10 NFA {best.log10_nfa:.1f} with {best.inliers} inliers; "
                  f"needs < {opts.log10_epsilon:g})")
        return MatchResult(None, listed, reason, n_tests, rounds)
    rivals = find_rivals(best, rest, z, img_label, index, quads, diag_px, opts, math.log10(max(n_tests, 1)),
                         prior, scale_range)
    # The rivals stand for the runner-ups' places too (scored beside the winner); a place keeps its better score.
    rest = merge_candidates([best, *rivals, *rest], diag_px)[1 : 1 + opts.max_candidates]
    close = [c for c in rest if c.log10_nfa < opts.log10_epsilon and c.score > best.score - opts.ambiguity_margin]
    if close:
        reason = f"ambiguous: two places match about equally well (scores {best.score:.1f} and {close[0].score:.1f})"
        return MatchResult(None, [best, *rest][: opts.max_candidates], reason, n_tests, rounds)
    best = polish(best, z, img_label, index, whole=whole, jackknife=blobs, errors=errors)
    if opts.max_sigma_m is not None and best.sigma_m > opts.max_sigma_m:
        reason = (f"imprecise: estimated 1-sigma error {best.sigma_m:.2f} m exceeds {opts.max_sigma_m:g} m "
                  f"({best.inliers} inliers)")
        return MatchResult(None, [best, *rest][: opts.max_candidates], reason, n_tests, rounds)
    return MatchResult(best, rest, None, n_tests, rounds)
