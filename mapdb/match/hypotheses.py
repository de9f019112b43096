"""Hypotheses: image quads looked up in the map's quad indexes, each hit a similarity ``z -> a z + b``.

Image quads (each object with three of its ``image_neighbours`` nearest, fewer than the map's so that a
missing or extra object still leaves quads whose members are all among the map's neighbours) are looked
up with a radius from the pixel error and the quad's size; near the canonical-order boundaries every
ordering is looked up, so noise cannot hide a quad behind a flip.  Objects nearest the image centre anchor
the first quads (their neighbourhoods are least cut by the image edge), a few anchors per round.

The first stage of :func:`mapdb.match.fast.match_fast`: each round's :class:`Hypotheses` go to the screen
(:mod:`mapdb.match.screen`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._kernel import hits_hypotheses, quads_allowed, quads_batches, quads_keys
from .options import FastOptions
from .quads import QuadIndex, lookup_parts

__all__ = [
    "Hypotheses", "allowed_poses", "anchor_batches", "pose_votes", "prioritise",
    "round_hypotheses",
]


@dataclass(frozen=True)
class Hypotheses:
    """A round's hypotheses, what this stage hands the screen (:mod:`mapdb.match.screen`): similarities
    ``z -> a z + b`` (``a``, ``b`` complex, ``(H,)``), each from the image objects ``img_ids`` ``(H, 4)`` of its
    quad and their map points ``map_z`` ``(H, 4)``."""

    a: np.ndarray
    b: np.ndarray
    img_ids: np.ndarray
    map_z: np.ndarray

    def __len__(self) -> int:
        return len(self.a)

    def take(self, rows: np.ndarray | list[int]) -> Hypotheses:
        """The hypotheses of ``rows`` (indices or a mask), in that order."""
        return Hypotheses(self.a[rows], self.b[rows], self.img_ids[rows], self.map_z[rows])


def anchor_batches(z: np.ndarray, opts: FastOptions, anchorable: np.ndarray | None = None) -> list[np.ndarray]:
    """Image quads ``(m, 4)`` in rounds: anchors nearest the image centre first, each quad in its earliest
    round, at most ``opts.max_batches`` rounds.

    Each (anchorable) object anchors the quads of itself and every triple of its ``opts.image_neighbours`` nearest
    (:func:`~mapdb.match.quads.neighbour_quads` with its anchors; equal distances in object order), rows of sorted
    object ids; anchors ranked by ``|z|`` (a stable order), ``opts.anchors_per_batch`` a round.  One kernel call
    (``_kernel_quads.c``): an image has a few dozen objects, whose arithmetic costs less than numpy's calls.

    ``anchorable`` (bool, ``(n,)``) limits quads to those objects: a region cut by the image border has its
    centroid pulled inward, by up to half the hidden part, so a quad holding one predicts the others badly
    and its invariants miss the map's.  Such objects still count as evidence in verification.
    """
    members = np.arange(z.size, dtype=np.int64) if anchorable is None else np.flatnonzero(anchorable).astype(np.int64)
    quads, counts = quads_batches(np.ascontiguousarray(z, np.complex128), members,
                                  int(opts.image_neighbours), int(opts.anchors_per_batch), int(opts.max_batches))
    # The rounds as slices (np.split's views, without its per-call overhead: a few rounds an image).
    rows, out, at = np.frombuffer(quads, np.int64).reshape(-1, 4), [], 0
    for count in np.frombuffer(counts, np.int64).tolist():
        out.append(rows[at : at + count])
        at += count
    return out


def round_hypotheses(
    z: np.ndarray,
    img_label: np.ndarray,
    batch: np.ndarray,
    quads: Sequence[QuadIndex],
    opts: FastOptions,
    sigma_px: float | np.ndarray,
    prior: tuple[float, float, float] | None,
    scale_range: tuple[float, float] | None,
    weight: np.ndarray | None = None,
) -> Hypotheses:
    """One round's hypotheses: ``a``, ``b`` (complex), image ids ``(H, 4)`` and map points ``(H, 4)``.

    Hypotheses whose image centre falls outside the prior (with a little slack: a quad's estimate of the
    centre is noisier than the final answer) or whose scale is outside ``scale_range`` are dropped.
    ``sigma_px`` is one pixel error for every point or one per point of ``batch`` (see
    :func:`_lookup_hits`); ``weight`` (per image object), the points' weights in the fit (default equal).
    """
    key_ids, rows, map_z = _lookup_hits(z, img_label, batch, quads, opts, sigma_px)
    return _hypotheses_of_hits(z, weight, key_ids, rows, map_z, prior, scale_range)


def _hypotheses_of_hits(z: np.ndarray, weight: np.ndarray | None, key_ids: np.ndarray, rows: np.ndarray,
                        map_z: np.ndarray, prior: tuple[float, float, float] | None,
                        scale_range: tuple[float, float] | None) -> Hypotheses:
    """The hits (``rows`` of the keys' image ids ``key_ids``, their map points ``map_z``) made hypotheses: each
    hit's image ids, its similarity fitted to the four points (:func:`~mapdb.match.geometry.fit_similarity_complex`'s
    arithmetic, weighted by ``weight`` of the image objects) and those :func:`allowed_poses` lets through, in hit
    order: one kernel call (``_kernel_hits.c``), not the gathers, fit and masks of numpy's."""
    centre = (0.0, 0.0, 0.0) if prior is None else (float(prior[0]), float(prior[1]), PRIOR_SLACK * prior[2])
    lo, hi = (0.0, 0.0) if scale_range is None else (float(scale_range[0]), float(scale_range[1]))
    ids, points, a, b = hits_hypotheses(
        np.ascontiguousarray(z, np.complex128), None if weight is None else np.ascontiguousarray(weight, np.float64),
        np.ascontiguousarray(key_ids, np.int64), np.ascontiguousarray(rows, np.int64),
        np.ascontiguousarray(map_z, np.complex128), prior is not None, *centre, scale_range is not None, lo, hi)
    return Hypotheses(np.frombuffer(a, np.complex128), np.frombuffer(b, np.complex128),
                      np.frombuffer(ids, np.int64).reshape(-1, 4), np.frombuffer(points, np.complex128).reshape(-1, 4))


def allowed_poses(a: np.ndarray, b: np.ndarray, prior: tuple[float, float, float] | None,
                  scale_range: tuple[float, float] | None) -> np.ndarray:
    """Which similarities ``z -> a z + b`` the search may answer: finite, the image centre ``b`` within
    ``PRIOR_SLACK`` prior radii of the prior's centre, the scale ``|a|`` within ``scale_range`` (one kernel call)."""
    ok = np.empty(len(a), bool)
    centre = (0.0, 0.0, 0.0) if prior is None else (float(prior[0]), float(prior[1]), PRIOR_SLACK * prior[2])
    lo, hi = (0.0, 0.0) if scale_range is None else (float(scale_range[0]), float(scale_range[1]))
    quads_allowed(np.ascontiguousarray(a, np.complex128), np.ascontiguousarray(b, np.complex128),
                  prior is not None, *centre, scale_range is not None, lo, hi, ok)
    return ok


# Hypotheses may put the image centre this many prior radii from the prior's centre.
PRIOR_SLACK = 1.1
# Poses are binned, to count the hypotheses that share one, in cells of this fraction of the footprint's
# diagonal, of this step in log scale (about 10 %) and of this many degrees of rotation.
POSE_BIN_FRACTION = 1.0 / 20.0
POSE_BIN_LOG_SCALE = 0.1
POSE_BIN_DEGREES = 10.0
# A quad's second longest pair may decide its frame too when it is within this many standard errors of the
# longest (the difference of two lengths, each with the pixel error of two points: sqrt(2) sigma).
FRAME_TIE_SIGMAS = 3.0


def _lookup_hits(
    z: np.ndarray,
    img_label: np.ndarray,
    quads: np.ndarray,
    indexes: Sequence[QuadIndex],
    opts: FastOptions,
    sigma_px: float | np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Look image quads up: the image ids ``(k, 4)`` of each key looked up, each hit's key row ``(H,)`` (its image
    ids ``key_ids[rows]``) and its map points ``(H, 4)`` (int64 and complex128, contiguous).

    ``sigma_px``: the pixel error of every point, or of each quad's points ``(m, 4)``."""
    empty = np.zeros((0, 4), np.int64), np.zeros(0, np.int64), np.zeros((0, 4), np.complex128)
    indexes = [ix for ix in indexes if ix.n_quads]
    if not len(quads) or not indexes:
        return empty
    # The keys with their image ids and labels (one array for every index: a prior's tiles share their query points).
    keys = _quad_keys(z[quads], opts, sigma_px, quads, img_label)
    if keys is None:
        return empty
    _, _, inv, radius, img_ids, labels = keys
    parts = _quad_parts(indexes)
    if parts is not None:  # in-memory indexes (a prior's tiles): one kernel call for all of them
        q_row, map_z = lookup_parts(parts, inv, labels, radius, opts.max_hits_per_quad)
    else:
        found = [index.lookup(inv, labels, radius, opts.max_hits_per_quad) for index in indexes]
        q_row, map_z = ((found[0][0], found[0][1]) if len(found) == 1 else
                        (np.concatenate([f[0] for f in found]), np.concatenate([f[1] for f in found])))
    return img_ids, np.ascontiguousarray(q_row, np.int64), np.ascontiguousarray(map_z, np.complex128)


def _quad_parts(indexes: Sequence) -> list[tuple[QuadIndex, tuple[complex, float] | None]] | None:
    """Each index as an in-memory :class:`QuadIndex` and the ``near`` it is looked up with (an index that says so by
    its ``quad_part()``, as the localizer's tiles do); None when one is of another kind (a stored index)."""
    parts = []
    for index in indexes:
        part = (index, None) if isinstance(index, QuadIndex) else getattr(index, "quad_part", lambda: None)()
        if part is None:
            return None
        parts.append(part)
    return parts


def _quad_keys(zq: np.ndarray, opts: FastOptions, sigma_px: float | np.ndarray, quads: np.ndarray | None = None,
               img_label: np.ndarray | None = None) -> tuple[np.ndarray, ...] | None:
    """Every frame and ordering of the quads ``zq`` (m, 4) worth looking up: quad rows, orderings (k, 4),
    invariants (k, 4) and lookup radii (k,); None when there is none.  With the quads' image ids ``quads`` (m, 4)
    and the image's labels ``img_label``, also each key's image ids ``quads[rows, orderings]`` and their labels
    (k, 4), int64, from the same call.

    ``sigma_px`` is one pixel error for every point, or one per point ``(m, 4)`` (a cut blob's is wider).
    The longest pair decides a quad's frame; when the second longest is within ``FRAME_TIE_SIGMAS`` standard errors
    of it, a noisy image can pick either, so both frames are looked up.  Each frame's invariants have a predicted
    standard error (see the module docs of decision: per point P of C, D sigma_P^2 + sigma_A^2 |1 - t|^2 +
    sigma_B^2 |t|^2, over |AB|^2, per axis), the radius ``tolerance_factor`` of them; near the canonical-order
    boundaries (within the radius) each ordering (A, B swapped or not, C, D swapped or not) is looked up too, while
    the radius is at most ``max_invariant_radius``.  Rows come frame by frame (the longest pair's, then the second
    longest's), each ordering in turn, in quad order within: one kernel call (``_kernel_quads.c``), the lengths
    ranked by a stable order (ties in pair order).
    """
    zq = np.ascontiguousarray(zq, np.complex128)
    if isinstance(sigma_px, float | int) or np.ndim(sigma_px) == 0:  # (np.ndim's dispatch costs microseconds)
        one, sigma = float(sigma_px), None
    else:
        one, sigma = 0.0, np.ascontiguousarray(np.broadcast_to(np.asarray(sigma_px, np.float64), zq.shape))
    with_ids = () if quads is None or img_label is None else (
        np.ascontiguousarray(quads, np.int64), np.ascontiguousarray(img_label, np.int64))
    out = quads_keys(zq, sigma, one, FRAME_TIE_SIGMAS * math.sqrt(2.0), float(opts.tolerance_factor),
                     float(opts.max_invariant_radius), *with_ids)
    if not out[0]:
        return None
    rows, orders, inv, radius = (np.frombuffer(out[0], np.int64), np.frombuffer(out[1], np.int64).reshape(-1, 4),
                                 np.frombuffer(out[2], np.float64).reshape(-1, 4), np.frombuffer(out[3], np.float64))
    if not with_ids:
        return rows, orders, inv, radius
    return rows, orders, inv, radius, np.frombuffer(out[4], np.int64).reshape(-1, 4), np.frombuffer(
        out[5], np.int64).reshape(-1, 4)


def pose_votes(a: np.ndarray, b: np.ndarray, diag_px: float) -> np.ndarray:
    """How many of the hypotheses share each one's coarse pose (itself included).

    Poses are binned coarsely (10 degrees of rotation, 10% of scale, a twentieth of the footprint
    diagonal in position).  The position cell follows the scale *bin*, not each hypothesis's own scale:
    map coordinates are large (UTM northings near 5,000 km), and a cell that moved with a 0.2 % difference
    of scale moved the bin of one place by hundreds of cells, so that no two hypotheses shared one.

    Examples
    --------
    >>> a = np.array([0.41 + 0j, 0.4109 + 0j, 0.41j])
    >>> pose_votes(a, np.array([4714878 + 0j, 4714878.3 + 0j, 4714878 + 0j]), 800.0).tolist()
    [2, 2, 1]
    >>> pose_votes(np.zeros(0, complex), np.zeros(0, complex), 800.0).tolist()
    []
    """
    if not len(a):
        return np.zeros(0, np.int64)
    scale_bin = np.floor(np.log(np.abs(a)) / POSE_BIN_LOG_SCALE)
    cell = np.exp((scale_bin + 0.5) * POSE_BIN_LOG_SCALE) * diag_px * POSE_BIN_FRACTION
    # One integer a bin (7 bits of scale, 6 of rotation, 25 of each coordinate): a 1-D unique is several times
    # faster than one over rows.  Coordinates wrap every 2**25 cells (thousands of kilometres), so two bins
    # that far apart may count as one: votes only rank hypotheses.
    key = (scale_bin.astype(np.int64) & 0x7F) << 56
    key |= (np.floor(np.angle(a) / math.radians(POSE_BIN_DEGREES)).astype(np.int64) & 0x3F) << 50
    key |= (np.floor(b.real / cell).astype(np.int64) & 0x1FFFFFF) << 25
    key |= np.floor(b.imag / cell).astype(np.int64) & 0x1FFFFFF
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return counts[inverse]


def prioritise(a: np.ndarray, b: np.ndarray, diag_px: float, limit: int,
               votes: np.ndarray | None = None) -> np.ndarray:
    """Indices of at most ``limit`` hypotheses, those whose pose most others share first
    (``votes``, :func:`pose_votes` if not given)."""
    if len(a) <= limit:
        return np.arange(len(a))
    return np.argsort(-(pose_votes(a, b, diag_px) if votes is None else votes), kind="stable")[:limit]
