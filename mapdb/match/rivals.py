"""Rivals: does the map hold the winner's pattern at another place too?  The stage after the decision.

The search stops at the first round that accepts, so the runner-ups it compares the winner with are the
ones it happened to find, each scored with its own label densities.  On a map with repeated structure (a
lattice, rows of identical houses, a street grid) an equally good place found near a gap or a park scores
a unit or two below the winner only because its density estimate differs (on the perfect lattice of
``tests/test_analyze.py`` that accepted about one image in ten at a wrong place), and where a pattern
repeats more often than a quad look-up returns hits, the places within a prior's disc may never be tried.
Here runner-ups are looked for on purpose and compared fairly:

1. **Repeats.**  The winner's pose moved by the map's own repetitions, read off its matched map objects:
   every way of laying two of them onto two others of the same labels and spacing (:func:`_shifted`).
   Cheap (a distance matrix of a few dozen points), and it finds every repeat that moves the image by
   less than its own size: the lattice's, a row's.
2. **Look-up** (``FastOptions.ambiguity_anchors`` > 0; off by default, it costs about 15 % of an image's
   time and the search's runner-ups already held the far places in every test).  Quads of the winner's
   inliers looked up again in the quad indexes: far places holding the same pattern.
3. **Comparison.**  Those places and the search's own runner-ups are refitted, each side by side with the
   winner under one density (per label, the larger of the two places' local densities): neither a thin
   density estimate makes a place look better nor chance alignments in a dense town look as good as a
   real fit.  A quick count screens places first (:func:`_near_counts`): most are never refitted.

Places are distinct when some image point moves by more than a place's width between the two poses
(:func:`~mapdb.match.refine.pose_shift`), so a quarter turn at the same spot is another place.  The prior
and the scale range rule poses out exactly as in the search: a place outside the prior's disc is no rival,
the prior resolves it.  A rival is reported on the winner's scale: the winner's score less how much worse
it explains the image under the common density; :func:`mapdb.match.decide.ambiguous` rejects the image
when a rival comes within ``ambiguity_margin`` of the winner.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import combinations

import numpy as np

from ._kernel import verify_shifted
from .evidence.image import ImageEvidence
from .evidence.terrain import TerrainModel
from .hypotheses import allowed_poses, round_hypotheses
from .options import FastOptions
from .quads import QuadIndex
from .refine import PLACE_FRACTION, Candidate, candidates, merge_candidates, pose_shift
from .verify import ObjectIndex, refine

__all__ = ["find_rivals", "inlier_quads"]

# A place is refitted beside the winner only when this share of the winner's number of inliers land within
# SCREEN_SIGMAS of the winner's residual error of a map object of their label: a rival within a unit of the
# winner's score explains nearly as many objects, and an unrefined pose (a quad's, or moved by the map's
# repetition) predicts far objects a few times less well than the refined winner.
SCREEN_SHARE = 0.7
SCREEN_SIGMAS = 10.0


def find_rivals(
    best: Candidate,
    others: Sequence[Candidate],
    z: np.ndarray,
    img_label: np.ndarray,
    index: ObjectIndex,
    quads: Sequence[QuadIndex],
    diag_px: float,
    opts: FastOptions,
    log10_tests: float,
    prior: tuple[float, float, float] | None = None,
    scale_range: tuple[float, float] | None = None,
    terrain: TerrainModel | None = None,
) -> list[Candidate]:
    """Other places that explain the image, best first, each scored on the winner's scale.

    Parameters
    ----------
    best : Candidate
        The winner (refined): its matched map objects give the repeats, its inliers' quads the look-up.
    others : sequence of Candidate
        The search's own runner-ups: compared too.
    z, img_label, index, quads, diag_px, prior, scale_range
        As for :func:`mapdb.match.fast.match_fast`.
    opts : FastOptions
        ``ambiguity_anchors`` and ``ambiguity_places`` bound the work.
    log10_tests : float
        log10 of the hypotheses the search tried.

    Returns
    -------
    list of Candidate
        Places distinct from the winner's (some image point moves by more than
        :data:`~mapdb.match.refine.PLACE_FRACTION` of the footprint's diagonal), with ``log10_nfa`` = the
        winner's plus how much worse the place's fit is under the common density (never better).
    """
    # The places compared: the runner-ups, then the hits' places, with which are another place than the winner's
    # (the hits' are, by _places); put together once at the end (often one part, or none, comes).
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    if others:
        a = np.array([c.a for c in others], np.complex128)
        b = np.array([c.b for c in others], np.complex128)
        parts.append((a, b, _elsewhere(a, b, best, diag_px)))
    sigma_px = max(opts.pixel_sigmas[0], best.sigma_axis_m / max(abs(best.a), 1e-12))
    hit_a, hit_b = _shifted(best, index, opts.tolerance_factor * math.sqrt(2.0) * sigma_px * abs(best.a))
    allowed = allowed_poses(hit_a, hit_b, prior, scale_range)
    hit_a, hit_b = hit_a[allowed], hit_b[allowed]
    if opts.ambiguity_anchors > 0:
        batch = inlier_quads(z, best.pairs[:, 0], opts.image_neighbours, opts.ambiguity_anchors)
        if len(batch):
            found = round_hypotheses(z, img_label, batch, quads, opts, sigma_px, prior, scale_range)
            hit_a, hit_b = np.concatenate([hit_a, found.a]), np.concatenate([hit_b, found.b])
    if hit_a.size:  # (no repeats, no look-up: the runner-ups alone)
        keep = _places(hit_a, hit_b, best, diag_px)
        if keep.size:
            parts.append((hit_a[keep], hit_b[keep], np.ones(keep.size, bool)))
    if not parts:
        return []
    a, b, apart = parts[0] if len(parts) == 1 else (np.concatenate(v) for v in zip(*parts, strict=True))
    need = max(4.0, SCREEN_SHARE * best.inliers)
    near = _near_counts(a, b, best, z, img_label, index, opts, math.ceil(need))
    ok = apart & (near >= need)
    # The places where most objects land near a map object of their label are refitted first.
    keep = np.flatnonzero(ok)[np.argsort(-near[ok], kind="stable")][: opts.ambiguity_places]
    if not keep.size:
        return []
    return _compared(best, a[keep], b[keep], z, img_label, index, diag_px, opts, log10_tests, terrain)


def inlier_quads(z: np.ndarray, inliers: np.ndarray, neighbours: int, anchors: int) -> np.ndarray:
    """Image quads ``(m, 4)`` among the ``inliers`` (image ids): each of the ``anchors`` inliers nearest the
    image centre with every triple of its ``neighbours`` nearest inliers (the search's own kind of quad).

    Examples
    --------
    >>> z = np.array([0, 1, 1j, 1 + 1j, 5 + 5j, 9 + 9j])
    >>> inlier_quads(z, np.array([0, 1, 2, 3, 4]), 3, 1).tolist()
    [[0, 1, 2, 3]]
    """
    inliers = np.asarray(inliers, np.int64)
    k = min(neighbours, inliers.size - 1)
    if k < 3 or anchors < 1:
        return np.zeros((0, 4), np.int64)
    zi = z[inliers]
    central = np.argsort(np.abs(zi), kind="stable")[:anchors]
    # Each anchor's nearest inliers (itself first, at distance 0).  A few dozen points: a distance matrix is
    # cheaper than building a tree.
    near = np.argsort(np.abs(zi[central][:, None] - zi[None, :]), axis=1, kind="stable")[:, : k + 1]
    triples = np.array(list(combinations(range(1, k + 1), 3)))
    quads = np.concatenate([np.repeat(near[:, :1], len(triples), axis=0),
                            near[:, triples].reshape(-1, 3)], axis=1)
    return inliers[quads]


def _shifted(best: Candidate, index: ObjectIndex, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """The winner's pose moved by the map's own repetitions among its inliers: every way of laying the map
    points of two inliers (the one nearest the image centre and its nearest) onto two other inliers' points
    of the same labels and the same distance apart (within ``tolerance`` metres).

    The quad look-up returns a bounded number of map quads per image quad, whichever they are: where a
    pattern repeats more often (a lattice), those within a prior's disc may all be left out.  The
    repetitions that move the image by less than its own size are read off the winner's own matches.
    """
    mid = best.pairs[:, 1]
    if mid.size < 3:
        return np.zeros(0, np.complex128), np.zeros(0, np.complex128)
    # The pairwise steps of a few dozen points and the poses they give, in one kernel call.
    hit_a = np.empty(mid.size * mid.size, np.complex128)
    hit_b = np.empty(mid.size * mid.size, np.complex128)
    found = verify_shifted(index.z[mid], np.ascontiguousarray(index.label[mid], np.int64), best.a, best.b, tolerance,
                           hit_a, hit_b)
    return hit_a[:found], hit_b[:found]


def _elsewhere(a: np.ndarray, b: np.ndarray, best: Candidate, diag_px: float) -> np.ndarray:
    """Which poses ``(a, b)`` are another place than the winner's: some image point moves by more than a
    place's width (:data:`~mapdb.match.refine.PLACE_FRACTION` of the footprint's diagonal) between them."""
    return pose_shift(a, b, best.a, best.b, diag_px) > abs(best.a) * diag_px * PLACE_FRACTION


def _places(a: np.ndarray, b: np.ndarray, best: Candidate, diag_px: float) -> np.ndarray:
    """Indices of one hypothesis per place other than the winner's (cells of a place's width)."""
    separation = abs(best.a) * diag_px * PLACE_FRACTION
    away = np.flatnonzero(_elsewhere(a, b, best, diag_px) & np.isfinite(b))
    if not away.size:
        return np.zeros(0, np.int64)
    if away.size < a.size:
        a, b = a[away], b[away]
    # One number per cell of a place's width and twelfth of a turn (a lattice repeats itself turned too).
    # (np.angle's arctan2 called directly: the same numbers in fewer calls.)
    turned = a / best.a
    turn = np.floor(np.arctan2(turned.imag, turned.real) / (np.pi / 6.0))
    cell = (np.floor(b.real / separation) * 2.0**24 + np.floor(b.imag / separation)) * 16.0 + turn
    # Each cell's first hypothesis, in order: a dict of a few dozen Python numbers, not np.unique's sort (its
    # first indices, sorted, are these; NaN cells are one cell there, the key None here).
    first: dict[float | None, int] = {}
    for j, c in enumerate(cell.tolist()):
        first.setdefault(c if c == c else None, j)
    return away[list(first.values())]


def _near_counts(a: np.ndarray, b: np.ndarray, best: Candidate, z: np.ndarray, img_label: np.ndarray,
                 index: ObjectIndex, opts: FastOptions, need: int = 0) -> np.ndarray:
    """How many image objects each place ``(a, b)`` puts within :data:`SCREEN_SIGMAS` of the winner's
    residual error of a map object of their label (a count below ``need`` may stop short, staying below it).

    One bounded query for all places: a place where fewer than :data:`SCREEN_SHARE` of the winner's number
    of inliers land so (most chance alignments of an ordinary map) is never refitted, and its count stops as
    soon as the objects left cannot bring it there.
    """
    if not a.size:
        return np.zeros(0, np.int64)
    sigma = max(best.sigma_axis_m, opts.pixel_sigmas[0] * abs(best.a))
    return index.near_counts(a, b, z, img_label, SCREEN_SIGMAS * sigma, need)


def _compared(best: Candidate, a: np.ndarray, b: np.ndarray, z: np.ndarray, img_label: np.ndarray,
              index: ObjectIndex, diag_px: float, opts: FastOptions, log10_tests: float,
              terrain: TerrainModel | None = None) -> list[Candidate]:
    """The places ``(a, b)`` refitted beside the winner under common densities, as candidates on the
    winner's scale (those that converged onto the winner left out); over ``terrain`` both with rays cast onto
    the objects' heights, as the winner was scored."""
    h = a.size
    radius = opts.density_radius_factor * diag_px / 2.0
    own = index.local_density(np.array([best.b]), np.array([abs(best.a) * radius]))
    common = np.maximum(own, index.local_density(b, np.abs(a) * radius))
    # Rows 0..h-1: the winner under each rival's common density; rows h..2h-1: the rivals.
    rows_a = np.concatenate([np.full(h, best.a), a])
    rows_b = np.concatenate([np.full(h, best.b), b])
    ra, rb, nfa, inlier, mid, dist = refine(rows_a, rows_b, z, img_label, index, np.concatenate([common, common]),
                                            log10_tests, 1, None if terrain is None else ImageEvidence(terrain=terrain))
    worse = nfa[h:] - nfa[:h]
    keep = np.flatnonzero(_elsewhere(ra[h:], rb[h:], best, diag_px) & np.isfinite(worse))
    found = candidates(ra[h:][keep], rb[h:][keep], best.log10_nfa + np.maximum(worse[keep], 0.0),
                       inlier[h:][keep], mid[h:][keep], dist[h:][keep], z)
    return merge_candidates(found, diag_px)
