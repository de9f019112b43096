"""The fast matcher: indexed quad invariants, vectorised verification, an a contrario decision.

The design follows blind astrometry (astrometry.net's solver) and AC-RANSAC, one module a stage, each handed
the previous one's result by :func:`match_fast`, which reads as the stages in order:

======================================  =================================================================
stage (module)                          hands on
======================================  =================================================================
:mod:`~mapdb.match.pose_prior`          with a pose prior's heading and scale, first: one correspondence a
                                        hypothesis; its certain answer, else its number of tests
:mod:`~mapdb.match.hypotheses`          a round's :class:`~mapdb.match.hypotheses.Hypotheses` (image quads
(:mod:`~mapdb.match.cut_quads`)         looked up in the :mod:`~mapdb.match.quads` index)
:mod:`~mapdb.match.screen`              the round's places, screened, verified (:mod:`~mapdb.match.verify`),
                                        decided and refined: :class:`~mapdb.match.refine.Candidate` s
:mod:`~mapdb.match.decide`              the best place if certain, else the rejection
:mod:`~mapdb.match.rivals`              other places holding the winner's pattern; ambiguous or not
:mod:`~mapdb.match.refine`              the final fit (:func:`~mapdb.match.refine.polish`); the answer
======================================  =================================================================

The rivals come before the final fit: they are compared with the winner as the search refined it, and an
ambiguous image is rejected without the fit's cost.  Every stage reads :class:`~mapdb.match.options.FastOptions`
and the image's :class:`~mapdb.match.evidence.image.ImageEvidence` (the evidence models beyond point residuals:
areas, cut blobs, relief), set up once here.

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
4. **Decision** (:mod:`mapdb.match.nfa`): the number of false alarms of a
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

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .cut_quads import cut_batches, cut_round_hypotheses
from .decide import MatchResult, ambiguous, answer, uncertain
from .evidence.blobs import BlobErrors
from .evidence.image import ImageEvidence
from .evidence.terrain import TerrainModel
from .hypotheses import anchor_batches, round_hypotheses
from .options import FastOptions
from .pose_prior import PosePrior, match_pose
from .quads import QuadIndex
from .refine import Candidate, merge_candidates, polish
from .rivals import find_rivals
from .screen import screen_neighbours, screen_round
from .verify import ObjectIndex

__all__ = ["Candidate", "FastOptions", "MatchResult", "ObjectIndex", "PosePrior", "QuadIndex", "match_fast"]


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
    focal_px: float | None = None,
    altitude_m: float | None = None,
    pose_prior: PosePrior | None = None,
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
        Ignored when ``options.areas`` is False.
    outward : complex array (n,), optional
        Unit outward normal (y up) of the image border each object touches, 0 for whole ones
        (:func:`mapdb.match.evidence.blobs.outward_normals` of the objects' boxes).  With it and ``anchorable`` the
        decision measures each cut blob in an ellipse along that normal (:mod:`mapdb.match.evidence.blobs`) and, when
        the whole blobs' quads find nothing, quads holding cut blobs are looked up
        (:mod:`mapdb.match.cut_quads`).

    focal_px, altitude_m : float, optional
        The camera's focal length (pixels) and height above the ground under it (metres), when the image gives
        them: over a map with elevation the decision and the final fit then cast each ray onto the objects'
        heights (:mod:`mapdb.match.evidence.terrain`).
    pose_prior : PosePrior, optional
        Where the camera is, which way it points and at what scale (:mod:`mapdb.match.pose_prior`).  With its
        heading and scale (:attr:`~mapdb.match.pose_prior.PosePrior.usable`) the pose-prior stage runs first
        and its certain answer is returned; else the lookup rounds run, their number of tests counting the
        stage's.  The result's ``path`` says which decided.  Its disc is not ``prior``: give both.

    Returns
    -------
    MatchResult
    """
    opts = options or FastOptions()
    if not opts.areas:
        area_px = None  # the objects answered as if they carried no areas
    z, img_label, anchorable, area_px, outward = _central_objects(z, img_label, opts.max_objects, anchorable,
                                                                  area_px, outward)
    reason = _unmatchable(z.size, objects, quads)
    if reason is not None:
        return MatchResult(None, [], reason, 0, 0)
    evidence = ImageEvidence.of(z, img_label, objects.labels, anchorable, area_px, outward)
    terrain = TerrainModel.of(objects, focal_px, altitude_m)
    if terrain is not None:
        evidence = dataclasses.replace(evidence, terrain=terrain)
    # 0. With a pose prior's heading and scale, one correspondence a hypothesis first (:mod:`.pose_prior`; not
    # over terrain): its certain answer is the answer, else its tests count in the rounds'.
    tests, path = 0, None if pose_prior is None else "quads"
    if pose_prior is not None and pose_prior.usable and terrain is None:
        found = match_pose(z, img_label, objects, diag_px, opts, evidence, pose_prior)
        if found.best is not None:
            return dataclasses.replace(found, path="pose-prior")
        tests = found.n_hypotheses
    # 1-2. Hypotheses, screened and verified round by round (each round's places decided and refined) until
    # a round brings a certain one: candidates best first.
    pool, n_tests, rounds = _search(z, img_label, objects, quads, diag_px, opts, prior, scale_range, evidence,
                                    tests)
    # 3. Decide: the best place certain enough?
    rejected = uncertain(pool, opts, n_tests, rounds)
    if rejected is not None:
        return _said(rejected, path)
    best, rest = pool[0], pool[1 : 1 + opts.max_candidates]
    # 4. Rivals: other places holding the winner's pattern, scored beside it (before the final fit: compared with
    # the winner as the search refined it).  They stand for the runner-ups' places too; a place keeps its better
    # score.  With none, ``best, *rest`` is a prefix of the search's merged pool: merging it again keeps it.
    rivals = find_rivals(best, rest, z, img_label, objects, quads, diag_px, opts, math.log10(max(n_tests, 1)),
                         prior, scale_range, evidence.terrain)
    rest = merge_candidates([best, *rivals, *rest], diag_px)[1 : 1 + opts.max_candidates] if rivals else rest
    rejected = ambiguous(best, rest, opts, n_tests, rounds)
    if rejected is not None:
        return _said(rejected, path)
    # 5. Refine: the final association and fit, then the answer unless its error is too large.
    best = polish(best, z, img_label, objects, evidence=evidence)
    if terrain is not None and (opts.max_sigma_m is None or opts.max_sigma_m > TERRAIN_MAX_SIGMA_M):
        opts = dataclasses.replace(opts, max_sigma_m=TERRAIN_MAX_SIGMA_M)
    return _said(answer(best, rest, opts, n_tests, rounds), path)


def _said(result: MatchResult, path: str | None) -> MatchResult:
    """The result saying which search decided (``path``: None without a pose prior, the result unchanged)."""
    return result if path is None else dataclasses.replace(result, path=path)


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


def _search(z: np.ndarray, img_label: np.ndarray, objects: ObjectIndex, quads: Sequence[QuadIndex], diag_px: float,
            opts: FastOptions, prior: tuple[float, float, float] | None, scale_range: tuple[float, float] | None,
            evidence: ImageEvidence, tests: int = 0) -> tuple[list[Candidate], int, int]:
    """The lookup rounds (pixel sigma x anchor batch, then the cut blobs' rounds) until one accepts: each round's
    hypotheses (:mod:`~mapdb.match.hypotheses`, :mod:`~mapdb.match.cut_quads`) handed to the screen
    (:func:`~mapdb.match.screen.screen_round`).  Candidates best first, tests (from ``tests`` tried before), rounds."""
    screen_of = screen_neighbours(z, opts)
    batches = anchor_batches(z, opts, evidence.anchors)
    # Each round: its pixel error, its image quads and, for the cut blobs' rounds, their errors and which are whole.
    plan: list[tuple[float, np.ndarray, tuple[BlobErrors, np.ndarray] | None]] = [
        (sigma_px, batch, None) for sigma_px in _sigmas(opts, evidence) for batch in batches]
    if evidence.errors is not None and evidence.whole is not None:
        blobs = evidence.errors, evidence.whole
        plan += [(opts.pixel_sigmas[-1], batch, blobs) for batch in cut_batches(z, evidence.whole, opts)]
    n_tests = tests
    pool: list[Candidate] = []
    done_rounds = 0
    for sigma_px, batch, cut in plan:
        done_rounds += 1
        if cut is not None:
            hyps = cut_round_hypotheses(z, img_label, batch, quads, opts, sigma_px, *cut, prior, scale_range)
        else:
            hyps = round_hypotheses(z, img_label, batch, quads, opts, sigma_px, prior, scale_range)
        n_tests += len(hyps)
        if not len(hyps):
            continue
        found = screen_round(hyps, z, img_label, objects, screen_of, diag_px, math.log10(n_tests), opts, evidence)
        pool = merge_candidates(pool + found, diag_px)
        if pool and pool[0].log10_nfa < opts.log10_epsilon:
            break
    return pool, n_tests, done_rounds


# Over terrain the final position's estimated error (per axis) must be within this: a 2-D Gaussian error of
# that sigma lies beyond 2 m with a chance of exp(-(2 / 0.66)^2 / 2), 1 %.  The flat gate (1 m: 13 %) leans on
# the flat fit's error model being tight; over terrain the fit also chooses the camera's height, whose
# uncertainty its sigma holds only to first order.  Measured (``python benchmarks/terrain.py``, Monaco, 300 m,
# 500 images, altitude given): with the flat gate 494 within 2 m and one accepted 2.13 m off with an estimated
# sigma of 0.79 m (a camera over a hilltop with no objects near its nadir, its visible objects 55-80 m lower).
TERRAIN_MAX_SIGMA_M = 0.66
# Over terrain a last lookup pass this wide (pixels): relief bends an image quad's shape (its objects at
# different heights are seen at different scales) beyond the flat passes' tolerance when its objects lie far
# apart, as in images of few objects.
TERRAIN_PIXEL_SIGMA = 10.0


def _sigmas(opts: FastOptions, evidence: ImageEvidence) -> tuple[float, ...]:
    """The lookup passes' pixel errors: the options', and over terrain a wider last one."""
    if evidence.terrain is None or max(opts.pixel_sigmas) >= TERRAIN_PIXEL_SIGMA:
        return tuple(opts.pixel_sigmas)
    return (*opts.pixel_sigmas, TERRAIN_PIXEL_SIGMA)
