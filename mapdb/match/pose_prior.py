"""The pose-prior stage: one correspondence a hypothesis when the camera's heading and scale are known.

A navigator that has had a fix knows more than where the camera is: it knows which way the image points and
at what scale (the image-to-map similarity ``a = s exp(-i heading)``, carried from the last fix by the
autopilot's yaw and the barometer: :mod:`mapdb.navigation.orientation`).  The lost-in-space search spends four
image objects on every hypothesis (a quad), and they are no evidence; a frame of five whole blobs, the usual
frame at 120 m over a town of large blocks, then has one object of evidence left and is never decided.  With
``a`` known, **one** correspondence fixes a pose: image object ``i`` on map object ``j`` of its label gives
``b = m_j - a z_i``, and the other ``n - 1`` objects (cut blobs included, in their error ellipses) are evidence.

**Hypotheses** (:func:`prior_hypotheses`). Anchors are the whole image objects nearest the image centre, then the
cut ones, at most ``ANCHORS``: central whole blobs carry the least relief displacement and their hypotheses the
least error from ``a``; a cut blob anchors at where it puts each candidate map object (a cut building by the map
object's own area, :func:`~mapdb.match.evidence.blobs.placed_sources`), as the final fit places it. For each
anchor, the map objects of its label that put the image centre within ``PRIOR_SLACK`` radii of the prior's centre,
the radius widened by three times the error ``a``'s uncertainty moves the centre by (``|z_i| s sigma_rel``,
``sigma_rel = sqrt(sigma_heading^2 + sigma_scale^2)``, heading in radians): one ball query of the map's label tree
per anchor. Each pair ``(i, j)`` is one test; the number of tests is every pair tried (a 20 m disc over a town: a
few to a few dozen, where a lost-in-space round tries hundreds).

**Decision** (the a-contrario model of :mod:`mapdb.match.nfa`, unchanged).  The hypothesis is judged as it came
from its correspondence, before any refit (AC-RANSAC's rule).  Its sample is the anchor (``n_sample = 1``: the
anchor's map object is excluded from the other objects' nearest neighbours, and the anchor's own area, when it
has one, is its sample evidence as a quad's are: :func:`~mapdb.match.evidence.areas.sample_evidence`).  The
residuals, densities (the larger of the footprint's and the ``density_neighbours``-th nearest's), the areas'
thinning and the cut blobs' ellipses are those of :meth:`~mapdb.match.evidence.image.ImageEvidence.residuals`.
Each object's tolerance disc grows with the prior's error propagated to its distance from the anchor: per
axis, ``sigma_k^2 = 2 sigma_px^2 + |z_k - z_i|^2 sigma_rel^2 / 2`` (pixels; the anchor's and the object's own
errors, ``POSE_PIXEL_SIGMA`` each, and the rotation and scale error of ``a`` acting on the lever ``z_k - z_i``),
so the relative tolerance area ``shape_k = sigma_k^2 / sigma_px^2``: with the prior right after a fix (0.14
degrees, 0.2 %) the far corner of a 640x480 frame, 800 px from the anchor, gets ``shape = 2.1`` (its disc 1.05 times
a near object's), and with the magnetometer's heading alone (3 degrees, 5 %) ``shape = 12``.
Accepted when ``log10 NFA < log10_epsilon`` as any answer.

**Ambiguity.**  With ``a`` fixed, a row of like houses gives poses one house apart that explain the image
about equally well.  The candidates' places are told apart at ``SEPARATION_M`` (not the lost-in-space search's
twentieth of the footprint, 8.7 m at 120 m: a neighbour's house is within it) and the winner is rejected as
ambiguous when a distinct place is accepted too within ``ambiguity_margin`` of its score
(:func:`~mapdb.match.decide.ambiguous`).

**Precision.**  The accepted answer is refined (:func:`~mapdb.match.verify.refine`) and finally fitted
(:func:`~mapdb.match.refine.polish`, a free similarity: the prior's heading and scale only chose the hypotheses)
and withheld when its estimated error exceeds ``POSE_MAX_SIGMA_M`` (0.6 m, where the lookup rounds allow
``max_sigma_m``, 1 m): an honest 2-D Gaussian sigma of 0.6 m puts an answer beyond 2 m with a chance of
``exp(-(2 / 0.6)^2 / 2)``, 0.4 %.  The stage decides frames of few whole blobs, whose fits' sigmas are least
honest: measured on the first 1 km of Andorra's rendered-mask flight at 120 m with heights (``python
benchmarks/navigation_masks.py --maps andorra --cases heights --starts lis --length 1000``, each fix against the
truth), of 139 fixes decided here none of the 121 with a sigma under 0.6 m was more than 2 m off, and 7 of the
18 between 0.6 and 1 m were (1.6-4.4 m off).

**A turned heading.**  The null hypothesis does not model a pattern that repeats turned half round (a block
of like houses seen from either side): with the heading prior turned, such an image is certain at a place
20-30 m off (2 of 300 images on the sample map: ``python benchmarks/diagnostics/pose_turned.py 300`` before this
check).  So an accepted answer is tried once more with the heading turned by 180 degrees, the same
hypotheses and the same number of tests; when the turned image is certain at a place more than ``SEPARATION_M``
from the winner, the answer is rejected as ambiguous (the prior's heading, not the image, chose between them),
and the lookup rounds run.  Its price, measured: on the rendered-mask frames of ``python benchmarks/pose_prior.py
--every 2`` none (425 of 752 accepted with and without it, ``--no-turned-check``), 1.1x the stage's median time;
on the sample's five-object frames (``tests/test_pose_prior.py``) 1 of 45 right answers left to the rounds; after
it, no turned heading places an image of ``pose_turned.py`` more than 5 m off.

**A wide disc.**  The stage pays when the disc is narrow, as after a navigator's fix: its hypotheses are
few and a frame it does not decide costs the lookup rounds a few tests.  Over a wide disc (a compass heading
with a 300 m disc) each anchor meets hundreds of map objects of its label: measured (``python
benchmarks/matcher_core.py --n 100 --maps andorra,monaco,liechtenstein --baseline 5144dec``, 300 m discs, the
true heading to 5 degrees) 1.6-5.7 times the disc alone's time, and six-object images that the disc alone
accepts rejected once 170-380 undecided hypotheses were counted; with 30 m discs 0.87-1.07 times.  So when the
anchors' map objects in the disc (known before any image evidence is looked at: the count says nothing of the
answer) number over ``POSE_MAX_HYPOTHESES``, the stage tries none and counts none.

**When the stage gives no answer** the lost-in-space rounds run, their number of tests counting this stage's
(:func:`mapdb.match.fast.match_fast`): a false alarm of the image costs at most ``epsilon`` in each, as the
lookup passes of increasing pixel error already do.  Over a map with elevation (terrain) the stage is skipped:
its hypotheses have no quad for the rays' heights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .decide import MatchResult, ambiguous, answer, uncertain
from .evidence.areas import points_floor
from .evidence.blobs import CUT_SHIFT_PX, BlobErrors, placed_sources
from .evidence.image import ImageEvidence
from .geometry import image_to_map
from .hypotheses import PRIOR_SLACK
from .mapobjects.object_index import ObjectIndex
from .nfa import log10_nfa_curve
from .options import FastOptions
from .refine import Candidate, candidates, distinct, polish, pose_shift
from .verify import refine

__all__ = ["ALTITUDE_SCALE_REL_SIGMA", "ANCHORS", "MAX_HEADING_SIGMA_DEG", "MAX_SCALE_REL_SIGMA",
           "POSE_MAX_HYPOTHESES", "POSE_MAX_SIGMA_M", "POSE_PIXEL_SIGMA", "SEPARATION_M", "TURNED_CHECK",
           "PoseHypotheses", "PosePrior", "match_pose", "pose_nfa", "prior_hypotheses"]

# Anchors tried (whole objects nearest the centre first): one missing from the map, or merged with a
# neighbour into one blob, still leaves others.  Measured (``python benchmarks/pose_prior.py --every 5
# --anchors K [--thin]``, 302 rendered-mask frames, right pose priors): 1, 3, 5 anchors placed 172, 170, 168
# frames over the full maps, 1 and 3 placed 151 and 155 over the maps missing 15 % of their buildings; none
# wrong, and none at the wrong place or out of the map, in any.
ANCHORS = 3
# The per-axis pixel error of a blob's centroid the tolerances are shaped with (the navigator's blob floor).
POSE_PIXEL_SIGMA = 2.0
# A prior less certain than these is no prior for this stage: its tolerances would admit most of the footprint.
MAX_HEADING_SIGMA_DEG = 10.0
MAX_SCALE_REL_SIGMA = 0.2
# Two candidate poses whose image points differ by more than this (metres) are two places (module docs).
SEPARATION_M = 3.0
# Above this many hypotheses the stage is not run (module docs, a wide disc).
POSE_MAX_HYPOTHESES = 100
# Each answer is also tried turned half round (module docs, a turned heading); off only to measure its cost.
TURNED_CHECK = True
# The relative 1-sigma error of a scale from an altitude and a focal length (a barometer's or altimeter's bias
# against the height above the ground, the relief under the camera): the navigator's before its first fix, an
# image's with altitude_m and a field of view.
ALTITUDE_SCALE_REL_SIGMA = 0.05
# The stage's answers must be this precise (estimated 1-sigma error per axis, metres; module docs, precision).
POSE_MAX_SIGMA_M = 0.6


@dataclass(frozen=True)
class PosePrior:
    """Where the camera is, which way it points and at what scale, each with its uncertainty.

    Attributes
    ----------
    x, y, radius_m : float
        The map point under the image centre lies within ``radius_m`` of ``(x, y)`` (map CRS metres).
    heading_deg, heading_sigma_deg : float
        The direction the image's up points to, clockwise from map north (the answer's ``heading_deg``), and
        its 1-sigma error; None when unknown.
    scale_m_per_px, scale_rel_sigma : float
        Metres per pixel at the image centre (the answer's ``scale_m_per_px``) and its relative 1-sigma
        error; None when unknown.

    Examples
    --------
    >>> p = PosePrior(10.0, 20.0, 15.0, 90.0, 0.5, 0.25, 0.01)
    >>> p.disc, p.usable, round(abs(p.to_map() + 0.25j), 12)
    ((10.0, 20.0, 15.0), True, 0.0)
    >>> PosePrior(0.0, 0.0, 10.0).usable
    False
    """

    x: float
    y: float
    radius_m: float
    heading_deg: float | None = None
    heading_sigma_deg: float = 180.0
    scale_m_per_px: float | None = None
    scale_rel_sigma: float = 1.0

    @property
    def disc(self) -> tuple[float, float, float]:
        """``(x, y, radius)``: the position prior alone."""
        return (self.x, self.y, self.radius_m)

    @property
    def usable(self) -> bool:
        """Whether heading and scale are known well enough for this stage (``MAX_HEADING_SIGMA_DEG``,
        ``MAX_SCALE_REL_SIGMA``) and every number is finite."""
        if self.heading_deg is None or self.scale_m_per_px is None:
            return False
        values = (self.x, self.y, self.radius_m, self.heading_deg, self.heading_sigma_deg, self.scale_m_per_px,
                  self.scale_rel_sigma)
        return (all(math.isfinite(v) for v in values) and self.radius_m >= 0 and self.scale_m_per_px > 0
                and 0 <= self.heading_sigma_deg <= MAX_HEADING_SIGMA_DEG
                and 0 <= self.scale_rel_sigma <= MAX_SCALE_REL_SIGMA)

    def to_map(self) -> complex:
        """The predicted image-to-map similarity ``a = s exp(-i heading)`` (levelled image, y up)."""
        assert self.heading_deg is not None and self.scale_m_per_px is not None
        return image_to_map(self.scale_m_per_px, self.heading_deg)

    @property
    def rel_sigma(self) -> float:
        """``sqrt(sigma_heading^2 + sigma_scale^2)``: the relative error of ``a`` (heading in radians)."""
        return math.hypot(math.radians(self.heading_sigma_deg), self.scale_rel_sigma)


@dataclass(frozen=True)
class PoseHypotheses:
    """One correspondence a hypothesis: ``z -> a z + b`` with anchor image object ``anchor`` on map object
    ``map_id`` (at ``map_z``), all ``(H,)``."""

    a: np.ndarray
    b: np.ndarray
    anchor: np.ndarray
    map_id: np.ndarray
    map_z: np.ndarray
    over_limit: int = 0  # the pairs the prior allows when they were over the limit and none was made

    def __len__(self) -> int:
        return int(self.a.size)

    def take(self, rows: np.ndarray | list[int]) -> PoseHypotheses:
        rows = np.asarray(rows, np.int64)
        return PoseHypotheses(self.a[rows], self.b[rows], self.anchor[rows], self.map_id[rows], self.map_z[rows])


def prior_hypotheses(z: np.ndarray, img_label: np.ndarray, objects: ObjectIndex, pose: PosePrior,
                     whole: np.ndarray | None = None, anchors: int | None = None,
                     errors: BlobErrors | None = None, limit: int | None = None) -> PoseHypotheses:
    """Every (anchor, map object) pair the pose prior allows (module docs, hypotheses).

    Parameters
    ----------
    z : complex array (n,)
        Image objects, pixels from the image centre, y up.
    img_label : int array (n,)
        Their label codes in ``objects.labels`` (codes beyond them are never anchors).
    objects : ObjectIndex
        The map objects (anything with ``disc_members``, ``z`` and ``log_area``).
    pose : PosePrior
        A usable prior (:attr:`PosePrior.usable`).
    whole : bool array (n,), optional
        Objects not cut by the image border (default all): anchors are the whole ones nearest the centre
        first, then the cut ones.
    anchors : int, optional
        At most this many anchors (default ``ANCHORS``).
    errors : BlobErrors, optional
        The objects' blob errors: a cut anchor's map object is then where its blob puts it
        (:func:`~mapdb.match.evidence.blobs.placed_sources`: a cut building by the map object's own area),
        not at the visible part's centroid.
    limit : int, optional
        When the prior allows more pairs than this, none is made (``over_limit`` says how many it allows).

    Returns
    -------
    PoseHypotheses
        Anchor by anchor, map objects in index order.
    """
    a0 = pose.to_map()
    anchors = ANCHORS if anchors is None else anchors
    allowed = np.asarray(img_label) < len(objects.labels)
    cut = np.zeros(z.size, bool) if whole is None else ~np.asarray(whole, bool)
    order = [int(i) for i in np.lexsort((np.abs(z), cut)) if allowed[i]][:anchors]
    if not order:
        return _no_hypotheses(0)
    ids = np.asarray(order, np.int64)
    centre = complex(pose.x, pose.y)
    # The map object under anchor i when the centre is at the prior's: the disc moves with it, widened by
    # the error a's uncertainty gives b = m_j - a z_i, and for a cut blob by how far its map object may lie
    # outward of the visible part.
    shift = 0.0 if errors is None else np.where(cut[ids], 2.0 * CUT_SHIFT_PX, 0.0)
    reach = PRIOR_SLACK * pose.radius_m + np.abs(a0) * (3.0 * np.abs(z[ids]) * pose.rel_sigma + shift
                                                        + 3.0 * math.sqrt(2.0) * POSE_PIXEL_SIGMA)
    members = objects.disc_members(centre + a0 * z[ids], reach, img_label[ids])
    allowed_pairs = sum(int(members[k][int(img_label[i])].size) for k, i in enumerate(ids))
    if limit is not None and allowed_pairs > limit:
        return _no_hypotheses(allowed_pairs)
    anchor = np.concatenate([np.full(members[k][int(img_label[i])].size, i) for k, i in enumerate(ids)])
    map_id = np.concatenate([np.sort(members[k][int(img_label[i])]) for k, i in enumerate(ids)]).astype(np.int64)
    anchor = anchor.astype(np.int64)
    source = z[anchor] if errors is None else placed_sources(errors, z, np.column_stack([anchor, map_id]), objects,
                                                             abs(a0))
    map_z = objects.z[map_id]
    return PoseHypotheses(np.full(anchor.size, a0), map_z - a0 * source, anchor, map_id, map_z)


def _no_hypotheses(over_limit: int) -> PoseHypotheses:
    empty = np.zeros(0, np.int64)
    return PoseHypotheses(np.zeros(0, complex), np.zeros(0, complex), empty, empty, np.zeros(0, complex), over_limit)


def pose_nfa(hyps: PoseHypotheses, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, rel_sigma: float,
             density: np.ndarray, radius: np.ndarray, log10_tests: float, opts: FastOptions,
             evidence: ImageEvidence) -> np.ndarray:
    """log10 NFA ``(H,)`` of one-correspondence hypotheses (module docs, decision): the anchor is the sample,
    each object's tolerance shaped by the prior's error at its distance from the anchor."""
    a, b = hyps.a, hyps.b
    h = len(hyps)
    w = evidence.project(a, b, z)
    r2, share, from_sample = evidence.residuals(w, a, b, hyps.anchor[:, None], hyps.map_z[:, None], z, img_label,
                                                index, density, radius)
    lam = density[:, img_label]
    if opts.density_neighbours:
        lam = np.maximum(lam, index.knn_density(w, img_label, opts.density_neighbours))
    u = lam * share * math.pi * r2
    lever = np.abs(z[None, :] - z[hyps.anchor][:, None]) ** 2
    shape = 2.0 + lever * rel_sigma**2 / (2.0 * POSE_PIXEL_SIGMA**2)
    sample = np.zeros((h, z.size), bool)
    sample[np.arange(h), hyps.anchor] = True
    nfa, _ = log10_nfa_curve(u, 1, log10_tests, shape=shape, sample=sample)
    return nfa + from_sample


def match_pose(z: np.ndarray, img_label: np.ndarray, objects: ObjectIndex, diag_px: float, opts: FastOptions,
               evidence: ImageEvidence, pose: PosePrior) -> MatchResult:
    """The pose-prior stage (module docs): the polished answer when one place is certain, unambiguous and
    precise, else the rejection saying why; ``n_hypotheses`` is every hypothesis tried."""
    hyps = prior_hypotheses(z, img_label, objects, pose, evidence.whole, errors=evidence.errors,
                            limit=POSE_MAX_HYPOTHESES)
    n_tests = len(hyps)
    if hyps.over_limit:  # a wide disc: none tried, none counted (module docs, a wide disc)
        return MatchResult(None, [], f"pose prior: {hyps.over_limit} hypotheses in the disc, over "
                           f"{POSE_MAX_HYPOTHESES}", 0, 1)
    if not n_tests:
        return MatchResult(None, [], "pose prior: no map object of an anchor's label in the disc", 0, 1)
    log10_tests = math.log10(n_tests)
    radius = opts.density_radius_factor * np.abs(hyps.a) * diag_px / 2.0
    density = objects.local_density(hyps.b, radius)
    nfa = pose_nfa(hyps, z, img_label, objects, pose.rel_sigma, density, radius, log10_tests, opts, evidence)
    points = None
    if evidence.areas is not None:  # the areas may add evidence, never take away what positions make certain
        points = pose_nfa(hyps, z, img_label, objects, pose.rel_sigma, density, radius, log10_tests, opts,
                          replace(evidence, areas=None))
        nfa = points_floor(nfa, points)
    keep = distinct(hyps.b, np.argsort(nfa, kind="stable"), np.full(len(hyps), SEPARATION_M),
                    opts.refine_candidates)
    a, b, _, inlier, mid, dist = refine(hyps.a[keep], hyps.b[keep], z, img_label, objects, density[keep],
                                        log10_tests, 2, evidence)
    pool = _places(candidates(a, b, nfa[keep], inlier, mid, dist, z, None if points is None else points[keep]),
                   diag_px)
    rejected = uncertain(pool, opts, n_tests, 1)
    if rejected is not None:
        return rejected
    best, rest = pool[0], pool[1 : 1 + opts.max_candidates]
    rejected = ambiguous(best, rest, opts, n_tests, 1)
    if rejected is not None:
        return rejected
    if TURNED_CHECK:
        rejected = _turned(best, z, img_label, objects, diag_px, opts, evidence, pose, n_tests)
        if rejected is not None:
            return rejected
    gate = POSE_MAX_SIGMA_M if opts.max_sigma_m is None else min(opts.max_sigma_m, POSE_MAX_SIGMA_M)
    return answer(polish(best, z, img_label, objects, evidence=evidence), rest, replace(opts, max_sigma_m=gate),
                  n_tests, 1)


def _turned(best: Candidate, z: np.ndarray, img_label: np.ndarray, objects: ObjectIndex, diag_px: float,
            opts: FastOptions, evidence: ImageEvidence, pose: PosePrior, n_tests: int) -> MatchResult | None:
    """The rejection when the image, turned half round, is also certain at another place in the disc (module
    docs, a turned heading), else None: the winner's place is then the prior's heading's choice, not the
    image's."""
    turned = replace(pose, heading_deg=(pose.heading_deg or 0.0) + 180.0)
    hyps = prior_hypotheses(z, img_label, objects, turned, evidence.whole, errors=evidence.errors)
    if not len(hyps):
        return None
    hyps = hyps.take(np.arange(min(len(hyps), opts.max_verified)))
    radius = opts.density_radius_factor * np.abs(hyps.a) * diag_px / 2.0
    density = objects.local_density(hyps.b, radius)
    nfa = pose_nfa(hyps, z, img_label, objects, turned.rel_sigma, density, radius, math.log10(n_tests), opts,
                   evidence)
    far = np.abs(hyps.b - best.b) > SEPARATION_M  # the same place turned (a symmetric pattern) is no rival
    if not far.any() or float(nfa[far].min()) >= opts.log10_epsilon:
        return None
    rival = int(np.flatnonzero(far)[np.argmin(nfa[far])])
    return MatchResult(None, [best], f"ambiguous: the image turned half round is certain "
                       f"{abs(hyps.b[rival] - best.b):.0f} m away (log10 NFA {nfa[rival]:.1f}); the prior's "
                       "heading alone chose", n_tests, 1)


def _places(pool: list[Candidate], diag_px: float) -> list[Candidate]:
    """Best first, one candidate a place, places ``SEPARATION_M`` apart (module docs, ambiguity)."""
    pool = sorted(pool, key=lambda c: (c.log10_nfa, -c.inliers))
    kept: list[Candidate] = []
    for c in pool:
        if all(pose_shift(c.a, c.b, k.a, k.b, diag_px) > SEPARATION_M for k in kept):
            kept.append(c)
    return kept
