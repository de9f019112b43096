"""Verification: how well a hypothesis explains the image, against the map's objects.

Image objects are projected into the map by each hypothesis and matched to the nearest map object of
their label (:class:`ObjectIndex`); residuals become normalised ``u = lambda pi r^2`` and the a contrario
model of :mod:`mapdb.match.nfa` turns them into a number of false alarms.  :func:`screen` ranks many
hypotheses cheaply, :func:`decision_nfa` is the full test, :func:`refine` re-associates and refits.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ._kernel import quad_tolerance, verify_decision, verify_refine
from .evidence.image import ImageEvidence
from .evidence.points import GATE_SIGMAS, refinement_inliers
from .geometry import fit_similarity_complex
from .mapobjects.label_trees import LabelTrees
from .mapobjects.object_index import Neighbours, ObjectIndex
from .nfa import LOG10_FLOOR, log10_nfa_curve, log10_trials

__all__ = ["ObjectIndex", "decision_nfa", "refine", "screen"]

_POINTS = ImageEvidence()  # ideal centroids: point residuals only


def screen(
    a: np.ndarray,
    b: np.ndarray,
    img_ids: np.ndarray,
    screen_of: np.ndarray,
    z: np.ndarray,
    img_label: np.ndarray,
    index: ObjectIndex,
    log10_tests: float,
    keep: int,
) -> np.ndarray:
    """Indices of the ``keep`` best hypotheses by a cheap NFA: the region's mean densities and only the
    image objects around each hypothesis's quad (``screen_of[first quad point]``), where a right
    hypothesis predicts positions best.

    Tried and taken out: not looking up the quad's own objects (its sample; a third fewer queries, 15 % less
    time an image on a 5M-object map).  Its different shortlist gave Andorra's rendered sim-000056 at 300 m
    with heights a pose scoring 4.46, accepted with an estimated sigma of 0.996 m but 3.3 m off, that this
    screen's shortlist misses (-3.7, rejected): the precision gate's weakness on fits of few whole blobs,
    which any change of the shortlist can bring to the surface.  Tried again once the final fit's sigma had
    the jackknife's (:func:`mapdb.match.refine.polish`) and a round screened at most 256 hypotheses: that image
    was withheld, but the saving had shrunk to 3 % (0.97x the CPU time an image on the 5M world, ``python
    benchmarks/lost_in_space_index.py --lookups-only --worlds 5000000 --jitter 2 --baseline 2731d67``) and
    Monaco's rendered sim-000073 (300 m, heights) moved from 0.08 to 1.66 m off: left out."""
    nfa = index.screen_nfa(a, b, z, screen_of[img_ids[:, 0]], img_label, log10_tests)
    return nfa.argsort(kind="stable")[:keep]


def decision_nfa(
    a: np.ndarray,
    b: np.ndarray,
    img_ids: np.ndarray,
    map_z: np.ndarray,
    z: np.ndarray,
    img_label: np.ndarray,
    index: ObjectIndex,
    density: np.ndarray,
    log10_tests: float,
    local_neighbours: int = 0,
    evidence: ImageEvidence | None = None,
    area_radius: np.ndarray | None = None,
    near: Neighbours | None = None,
) -> np.ndarray:
    """log10 NFA of quad hypotheses over all image objects, tolerances shaped by each quad's geometry.

    A similarity fitted to four points predicts the others with an error growing with their distance
    from the quad: per-axis variance ``sigma^2 (1 + 1/4 + |z - mean|^2 / spread)``.  The tolerance disc of
    each object scales with that, so a near object must match tightly and a far one loosely.

    The residuals come from the image's evidence models (:meth:`~mapdb.match.evidence.image.ImageEvidence.residuals`;
    None: point residuals only).  With its ``areas`` and ``area_radius`` (the density disc's radius per
    hypothesis), an object's evidence is its nearest map object of a compatible area, at the density of those
    (:mod:`mapdb.match.evidence.areas`).  With its ``errors``, each object's map object is looked for from where
    its blob says it lies and its residual measured in its error ellipse (:mod:`mapdb.match.evidence.blobs`: blobs
    cut by the image border); with both, a cut blob of a solid label is measured from where each candidate map
    object's own area puts it (:func:`~mapdb.match.evidence.blobs.cut_area_residuals`).

    ``near`` (:meth:`~mapdb.match.mapobjects.object_index.ObjectIndex.neighbours` of ``a z + b``, at least
    ``max(5, local_neighbours)`` of them) answers the nearest-object and density queries instead of the index.
    """
    h, n = len(a), z.size
    if near is not None and _plain(evidence, area_radius) and near.k >= max(1 + map_z.shape[1], local_neighbours):
        return _decision_points(img_ids, map_z, z, img_label, index, density, log10_tests, local_neighbours, near)
    w = a[:, None] * z[None, :] + b[:, None] if evidence is None else evidence.project(a, b, z)
    # The hypothesis's own map points are not evidence: an image object next to one of its quad's points
    # would find that point next to its projection by construction, not by chance.
    r2, share, from_sample = (evidence or _POINTS).residuals(w, a, b, img_ids, map_z, z, img_label, index, density,
                                                             area_radius, near)
    lam = density[:, img_label] if density.ndim > 1 else density[img_label][None, :]
    if local_neighbours:
        # The larger of the two densities: neither a dense old town beside empty slopes (the footprint's
        # mean density is too low there) nor an isolated object on a slope (its neighbours' distances
        # say the map is emptier than it is around the footprint) makes a chance alignment look rarer.
        lam = np.maximum(lam, index.knn_density(w, img_label, local_neighbours, near=near))
    # A share of 1.0 (no areas) leaves lam as it is: its product skipped.
    u = (lam if isinstance(share, float) and share == 1.0 else lam * share) * math.pi * r2
    # shape = 1.25 + |z - mean|^2 / spread of each quad's points, and its sample mask, in the compiled kernel.
    shape = np.empty((h, n))
    sample = np.empty((h, n), bool)
    quad_tolerance(np.ascontiguousarray(z, np.complex128), np.ascontiguousarray(img_ids, np.int64), shape, sample)
    nfa, _ = log10_nfa_curve(u, 4, log10_tests, shape=shape, sample=sample)
    return nfa + from_sample


def _plain(evidence: ImageEvidence | None, area_radius: np.ndarray | None) -> bool:
    """Whether the decision's residuals are plain point residuals measured from the projections themselves."""
    return evidence is None or (evidence.errors is None and evidence.terrain is None
                                and (evidence.areas is None or area_radius is None))


def _decision_points(img_ids: np.ndarray, map_z: np.ndarray, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex,
                     density: np.ndarray, log10_tests: float, local_neighbours: int, near: Neighbours) -> np.ndarray:
    """:func:`decision_nfa` on point residuals, read from ``near`` (the projections' neighbours, at least
    ``max(1 + m, local_neighbours)`` of them for ``m`` map points a hypothesis): one call of the compiled kernel
    (``verify_decision``) for :meth:`~ObjectIndex.nearest` with the quad's own map points excluded,
    :meth:`~ObjectIndex.knn_density`, ``u``, :func:`quad_tolerance` and the NFA curve."""
    h, n = near.shape
    if h == 0 or n <= 4:
        return np.full(h, np.inf)
    nfa = np.empty(h)
    verify_decision(near.dist, near.index, 1 + map_z.shape[1], np.ascontiguousarray(index.z, np.complex128),
                    np.ascontiguousarray(map_z, np.complex128), np.ascontiguousarray(img_ids, np.int64),
                    np.ascontiguousarray(z, np.complex128), np.ascontiguousarray(img_label, np.int64),
                    index.label_reach(density), np.ascontiguousarray(np.atleast_2d(density), np.float64),
                    np.ascontiguousarray(index.counts, np.int64), local_neighbours, 1.0 / index.area, 4,
                    log10_tests + log10_trials(n - 4), LOG10_FLOOR, nfa)
    return nfa


def refine(
    a: np.ndarray,
    b: np.ndarray,
    z: np.ndarray,
    img_label: np.ndarray,
    index: ObjectIndex,
    density: np.ndarray,
    log10_tests: float,
    iterations: int,
    evidence: ImageEvidence | None = None,
    map_z: np.ndarray | None = None,
    near: Neighbours | None = None,
) -> tuple[np.ndarray, ...]:
    """Re-associate and refit ``H`` hypotheses; returns a, b, log10 NFA, inlier mask, map ids, distances.

    Over terrain (``evidence.terrain``) each ray is cast onto the ground (``map_z``: the map points each
    hypothesis was fitted to) and the refit takes the image points rescaled for their map objects' heights.
    ``near``: :meth:`~mapdb.match.mapobjects.object_index.ObjectIndex.neighbours` of ``a z + b``, the first
    association's (on flat ground) instead of a query."""
    previous: tuple[np.ndarray, np.ndarray] | None = None
    terrain = None if evidence is None else evidence.terrain
    tree = index.fused_tree()
    if terrain is None and tree is not None and z.size:
        return _refine_flat(tree, a, b, z, img_label, index, density, log10_tests, iterations, near)
    # Each object's density and its share of u, the same every iteration.
    lam = (density[:, img_label] if density.ndim > 1 else density[img_label][None, :]) * math.pi
    for it in range(iterations + 1):
        w = a[:, None] * z[None, :] + b[:, None] if terrain is None else terrain.project(a, b, z, map_z)
        dist, mid = index.nearest(w, img_label, density, near=near if it == 0 and terrain is None else None)
        u = lam * dist**2
        nfa, k_best = log10_nfa_curve(u, 4, log10_tests)
        inlier = refinement_inliers(u, dist, mid, k_best)
        if it == iterations:
            break
        if previous is not None and (previous[0] == inlier).all() and (previous[1] == mid).all():
            # The same association as the fit that gave (a, b): refitting gives (a, b) again, and every
            # further round the same association, so this is where the iterations would end.
            break
        previous = inlier, mid
        target = index.z[np.maximum(mid, 0)]
        src = z[None, :] if terrain is None or index.elevation is None else _rescaled(
            terrain, a, b, z, map_z, index.elevation[np.maximum(mid, 0)])
        a_new, b_new = fit_similarity_complex(src, target, inlier)
        map_z = None  # the refit's scale is the nadir ground's
        ok = np.isfinite(a_new) & (inlier.sum(axis=1) >= 3)
        a = np.where(ok, a_new, a)
        b = np.where(ok, b_new, b)
    return a, b, nfa, inlier, mid, dist


def _refine_flat(tree: LabelTrees, a: np.ndarray, b: np.ndarray, z: np.ndarray, img_label: np.ndarray,
                 index: ObjectIndex, density: np.ndarray, log10_tests: float, iterations: int,
                 near: Neighbours | None) -> tuple[np.ndarray, ...]:
    """:func:`refine` on flat ground against an in-memory index's ``tree``: one call of the compiled kernel
    (``verify_refine``) that runs each hypothesis's rounds (association, curve, inliers, refit) until the last or
    until its association repeats (each row's rounds are its own: a row whose association repeats would refit to
    the same bits)."""
    h, n = len(a), z.size
    a, b = np.array(a, np.complex128), np.array(b, np.complex128)
    nfa, inlier = np.empty(h), np.empty((h, n), bool)
    mid, dist = np.empty((h, n), np.int64), np.empty((h, n))
    verify_refine(*tree._tree(), a, b, np.ascontiguousarray(z, np.complex128),
                  np.ascontiguousarray(img_label, np.int64), np.ascontiguousarray(index.z, np.complex128),
                  index.label_reach(density), np.ascontiguousarray(np.atleast_2d(density), np.float64),
                  0.5 * index.gap, iterations, None if near is None else near.dist,
                  None if near is None else near.index, log10_tests + log10_trials(n - 4) if n > 4 else 0.0,
                  LOG10_FLOOR, GATE_SIGMAS, nfa, inlier, mid, dist)
    return a, b, nfa, inlier, mid, dist


def _rescaled(terrain: Any, a: np.ndarray, b: np.ndarray, z: np.ndarray, map_z: np.ndarray | None,
              elevation: np.ndarray) -> np.ndarray:
    """Image points rescaled to each hypothesis's nadir ground for the rays onto their map objects'
    ``elevation`` (``(H, n)``): ``z (D - (h - g)) / D`` (:mod:`~mapdb.match.evidence.terrain`)."""
    depth = terrain.depth(a, b, map_z)[:, None]
    rise = np.where(np.isfinite(elevation), elevation - terrain.ground(b)[:, None], 0.0)
    return z[None, :] * np.maximum(depth - rise, 1.0) / depth
