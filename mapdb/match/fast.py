"""The fast matcher: indexed quad invariants, vectorised verification, an a contrario decision.

The design follows blind astrometry (astrometry.net's quads) and AC-RANSAC:

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
   ranks the hypotheses; the best are tested on every image object.
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

Lookup tolerances are tried in passes (``pixel_sigmas``): a tight one first,
a wider one only when the first finds nothing certain, so the usual image costs
the tight pass.  Every hypothesis of every round counts as a test.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
from scipy.sparse import csr_array
from scipy.sparse.csgraph import min_weight_full_bipartite_matching
from scipy.spatial import cKDTree

from ..objects import Objects
from .decision import log10_nfa_curve
from .geometry import fit_similarity_complex, prediction_variance_factor

__all__ = ["Candidate", "FastOptions", "MatchResult", "ObjectIndex", "QuadIndex", "match_fast"]

# The label key is a fifth tree coordinate, spaced far beyond any lookup radius so that a lookup never
# crosses from one label combination to another.
_LABEL_GAP = 100.0
# The six point pairs of a quad and, for each, the two other points.
_PAIRS = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
_OTHERS = np.array([(2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1)])
# Normalised residual beyond which an object counts as unmatched (a random point would be that close
# with probability 1 - e^-3 = 95%): also the search bound of the nearest-neighbour queries.
_U_MAX = 3.0
# Fixed sample of the unit disc (sunflower pattern) for the share of a density disc inside the map.
_DISC = np.sqrt((np.arange(256) + 0.5) / 256) * np.exp(1j * np.arange(256) * math.pi * (3 - math.sqrt(5)))


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
        Hypotheses screened per round (the best-supported ones when there are more).
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
    """

    map_neighbours: int = 8
    image_neighbours: int = 5
    pixel_sigmas: tuple[float, ...] = (1.5, 4.0)
    tolerance_factor: float = 2.0
    max_invariant_radius: float = 0.3
    max_hits_per_quad: int = 16
    max_verified: int = 3000
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


def neighbour_quads(
    xy: np.ndarray, neighbours: int, *, anchors: np.ndarray | None = None, with_anchor: bool = False
):
    """Quads ``(m, 4)``: each (anchor) point with every triple of its ``neighbours`` nearest.

    Rows are sorted point indices.  By default duplicates (the same four points reached from different
    anchors) are removed; with ``with_anchor`` every anchor keeps its own quads and the anchor of each
    row is returned too, so that an image can be searched anchor by anchor.

    Examples
    --------
    >>> q = neighbour_quads(np.array([[0, 0], [1, 0], [0, 1], [1, 1], [5, 5.0]]), 3)
    >>> q.shape[1], len(q) > 0, bool(np.all(np.diff(q, axis=1) > 0))
    (4, True, True)
    """
    n = len(xy)
    k = min(neighbours, n - 1)
    anchor_ids = np.arange(n) if anchors is None else np.flatnonzero(anchors)
    if k < 3 or not anchor_ids.size:
        empty = np.zeros((0, 4), dtype=np.int64)
        return (empty, np.zeros(0, np.int64)) if with_anchor else empty
    _, nn = cKDTree(xy).query(xy[anchor_ids], k + 1)
    # The point itself is usually first, but not when another point sits on it: drop it wherever it is.
    own = nn == anchor_ids[:, None]
    own[~own.any(axis=1), -1] = True
    nn = nn[~own].reshape(anchor_ids.size, k)
    triples = np.array(list(combinations(range(k), 3)))
    anchor = np.repeat(anchor_ids, len(triples))
    quads = np.concatenate([anchor[:, None], nn[:, triples].reshape(-1, 3)], axis=1)
    quads.sort(axis=1)
    if with_anchor:
        return quads, anchor
    if n < 55_000:  # n**4 fits in int64: deduplicate on one integer key, much faster than rows
        key = ((quads[:, 0] * n + quads[:, 1]) * n + quads[:, 2]) * n + quads[:, 3]
        _, first = np.unique(key, return_index=True)
        return quads[np.sort(first)]
    return np.unique(quads, axis=0)


def _frames(zq: np.ndarray, pair: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertex order ``(A, B, C, D)`` per quad for the chosen pair index, and ``t_C``, ``t_D``."""
    rows = np.arange(len(zq))
    order = np.concatenate([_PAIRS[pair], _OTHERS[pair]], axis=1)
    a, b = zq[rows, order[:, 0]], zq[rows, order[:, 1]]
    t = (zq[rows[:, None], order[:, 2:]] - a[:, None]) / (b - a)[:, None]
    return order, t


def canonical_quads(zq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canonical vertex order and invariants of quads given as complex points ``(m, 4)``.

    ``A, B`` is the most distant pair, ordered so that ``Re t_C + Re t_D <= 1``; ``C, D`` are ordered
    so that ``Re t_C <= Re t_D``.

    Returns
    -------
    order : (m, 4) int
        Positions (0..3) of ``A, B, C, D`` in each input row.
    invariants : (m, 4) float
        ``Re t_C, Im t_C, Re t_D, Im t_D``.
    ab : (m,) float
        Length of ``AB``.
    """
    d = np.abs(zq[:, _PAIRS[:, 0]] - zq[:, _PAIRS[:, 1]])
    pair = np.argmax(d, axis=1)
    order, t = _frames(zq, pair)
    swap_ab = t.real.sum(axis=1) > 1.0
    order[swap_ab, :2] = order[swap_ab, 1::-1]
    t[swap_ab] = 1.0 - t[swap_ab]
    swap_cd = t[:, 0].real > t[:, 1].real
    order[swap_cd, 2:] = order[swap_cd, :1:-1]
    t[swap_cd] = t[swap_cd, ::-1]
    return order, np.column_stack([t[:, 0].real, t[:, 0].imag, t[:, 1].real, t[:, 1].imag]), d[
        np.arange(len(zq)), pair
    ]


def _label_keys(labels: np.ndarray, n_labels: int) -> np.ndarray:
    """One number per ordered label 4-tuple ``(m, 4)``."""
    base = max(n_labels, 1)
    key = np.zeros(len(labels), dtype=np.float64)
    for j in range(4):
        key = key * base + labels[:, j]
    return key


class ObjectIndex:
    """Map objects for verification: one cKDTree over all labels, label densities, the region's bounds.

    The tree holds ``(x, y, label * gap)``: with a search bound below the gap, one query finds the
    nearest objects of each query's own label, whatever the mix of labels, instead of one query per
    label (a cKDTree query costs tens of microseconds whatever its size).

    Parameters
    ----------
    objects : Objects
        Map objects in projected metres (the whole map, or those read around a prior).
    bounds : (minx, miny, maxx, maxy), optional
        The region the objects were read from (default their bounding box): outside it the density
        estimate knows there is no map.

    Examples
    --------
    >>> idx = ObjectIndex(Objects.from_names([0.0, 10.0, 20.0], [0.0, 0.0, 5.0], ["b", "b", "p"]))
    >>> len(idx), idx.counts.tolist()
    (3, [2, 1])
    >>> dist, which = idx.nearest(np.array([[1.0 + 0j, 19.0 + 4j]]), np.array([0, 1]), idx.density)
    >>> dist.round(2).tolist(), which.tolist()
    ([[1.0, 1.41]], [[0, 2]])
    >>> len(ObjectIndex(Objects.empty(["b"])))
    0
    """

    def __init__(self, objects: Objects, bounds: tuple[float, float, float, float] | None = None) -> None:
        self.labels = tuple(objects.labels)
        self.z = objects.x + 1j * objects.y
        self.label = objects.label.astype(np.int64)
        n = len(objects)
        if bounds is None:
            bounds = (
                (float(objects.x.min()), float(objects.y.min()), float(objects.x.max()), float(objects.y.max()))
                if n
                else (0.0, 0.0, 0.0, 0.0)
            )
        self.bounds = tuple(float(v) for v in bounds)
        self.area = max((self.bounds[2] - self.bounds[0]) * (self.bounds[3] - self.bounds[1]), 1.0)
        self.counts = np.bincount(self.label, minlength=len(self.labels)) if n else np.zeros(len(self.labels), int)
        # Densities over the whole region only rank hypotheses; the decision uses local ones.
        self.density = np.maximum(self.counts, 1) / self.area
        # Far beyond any search bound (those stay below the region's size, see ``_bound``), so a bounded
        # search never crosses from one label to another.
        self.gap = 1e3 * (math.sqrt(self.area) + 1e4)
        self.tree = cKDTree(np.column_stack([objects.x, objects.y, self.label * self.gap])) if n else None

    def __len__(self) -> int:
        return int(self.z.size)

    def _points(self, w: np.ndarray, labels: np.ndarray) -> np.ndarray:
        return np.column_stack([w.real, w.imag, labels * self.gap])

    def _bound(self, reach: float) -> float:
        return float(min(reach, 0.5 * self.gap))

    def local_density(self, centres: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Objects per square metre of each label within ``radius`` of each centre (inside the bounds).

        ``centres`` (complex) and ``radius`` have shape ``(H,)``; the result ``(H, L)``.  A label with no
        object in a disc counts one, so that no density is zero.
        """
        centres = np.atleast_1d(np.asarray(centres, np.complex128))
        radius = np.broadcast_to(np.asarray(radius, np.float64), centres.shape)
        h, n_labels = centres.size, len(self.labels)
        minx, miny, maxx, maxy = self.bounds
        disc = centres[:, None] + radius[:, None] * _DISC[None, :]
        inside = (disc.real >= minx) & (disc.real <= maxx) & (disc.imag >= miny) & (disc.imag <= maxy)
        area = math.pi * radius**2 * np.maximum(inside.mean(axis=1), 1.0 / _DISC.size)
        count = np.ones((h, n_labels))
        present = np.flatnonzero(self.counts)
        if self.tree is not None and present.size:
            w = np.repeat(centres, present.size)
            codes = np.tile(present, h)
            r = np.minimum(np.repeat(radius, present.size), 0.5 * self.gap)
            found = self.tree.query_ball_point(self._points(w, codes), r, return_length=True)
            count[:, present] = np.maximum(np.asarray(found).reshape(h, present.size), 1)
        return count / area[:, None]

    def knn_density(self, w: np.ndarray, img_label: np.ndarray, k: int) -> np.ndarray:
        """Objects per square metre of each projected image object's label around where it lands.

        ``(k - 1) / (pi d_k^2)``, ``d_k`` the distance to the ``k``-th nearest map object of that label: a
        density that follows the map's clustering (a dense old town beside empty slopes), where one
        density over the footprint would make chance alignments in the town look significant.  A label
        with a single map object gets ``1 / (pi d_1^2)``; a label absent from the map, the region's floor.
        ``w`` is ``(H, n)`` complex; ``img_label`` ``(n,)``.  Returns ``(H, n)``.
        """
        shape = w.shape
        labels = np.broadcast_to(img_label, shape).ravel()
        out = np.full(labels.size, 1.0 / self.area)
        kk = np.minimum(k, self.counts[labels])
        sel = np.flatnonzero(kk > 0)
        if self.tree is None or not sel.size:
            return out.reshape(shape)
        k_max = int(kk[sel].max())
        d, _ = self.tree.query(self._points(w.ravel()[sel], labels[sel]), k=k_max,
                               distance_upper_bound=self._bound(0.5 * self.gap))
        d = d.reshape(sel.size, k_max)[np.arange(sel.size), kk[sel] - 1]
        out[sel] = np.maximum(kk[sel] - 1, 1) / (math.pi * np.maximum(d, 1e-3) ** 2)
        return out.reshape(shape)

    def nearest(
        self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray, exclude: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance to, and index of, the nearest map object of each projected image object's label.

        ``w`` has shape ``(H, n)`` (map metres, complex); ``img_label`` is ``(n,)`` or ``(H, n)``;
        ``density`` is ``(L,)`` or ``(H, L)``.  Objects with nothing of their label within the
        normalised residual ``_U_MAX`` get ``inf`` and -1.  ``exclude`` (complex, ``(H, m)``) lists map
        positions that row ``h`` may not use: the map points a hypothesis was built from.
        """
        shape = w.shape
        labels = np.broadcast_to(img_label, shape).ravel()
        dist = np.full(labels.size, np.inf)
        index = np.full(labels.size, -1, dtype=np.int64)
        if self.tree is None:
            return dist.reshape(shape), index.reshape(shape)
        lam = np.min(density, axis=0) if np.ndim(density) > 1 else np.asarray(density)
        reach = np.sqrt(_U_MAX / (math.pi * lam))[labels]
        k = 1 if exclude is None else 1 + exclude.shape[1]
        d, i = self.tree.query(self._points(w.ravel(), labels), k=k, distance_upper_bound=self._bound(reach.max()))
        d, i = d.reshape(labels.size, k), i.reshape(labels.size, k)
        found = d <= reach[:, None]
        if exclude is not None:
            rows = np.repeat(np.arange(shape[0]), shape[1])
            near = np.abs(self.z[np.minimum(i, len(self) - 1)][:, :, None] - exclude[rows][:, None, :])
            found &= ~(near < 1e-6).any(axis=2)
        first = np.argmax(found, axis=1)  # nearest allowed (column 0 if none: then not found)
        pick = np.arange(labels.size)
        ok = found[pick, first]
        dist[ok] = d[pick, first][ok]
        index[ok] = i[pick, first][ok]
        return dist.reshape(shape), index.reshape(shape)

    def within(self, w: np.ndarray, img_label: np.ndarray, gate: float, k: int) -> tuple[np.ndarray, ...]:
        """Pairs (image object, map object, squared distance) within ``gate`` metres, up to ``k`` per object."""
        if self.tree is None or not w.size:
            empty = np.zeros(0, np.int64)
            return empty, empty, np.zeros(0)
        k = max(1, min(k, len(self)))
        d, i = self.tree.query(self._points(w, img_label), k=k, distance_upper_bound=self._bound(gate))
        d, i = d.reshape(w.size, k), i.reshape(w.size, k)
        rows, cols = np.nonzero(np.isfinite(d))
        return rows, i[rows, cols], d[rows, cols] ** 2


class QuadIndex:
    """Quad invariants of map objects in a cKDTree: where image quads are looked up.

    A quad index keeps the map coordinates of its quads' points (not indices into a map), so that
    indexes of separate tiles of a map can be built, cached and searched independently.

    Parameters
    ----------
    objects : Objects
        Map objects in projected metres: the anchors and everything that may be their neighbours.
    neighbours : int
        Neighbours per anchor in the quads (``FastOptions.map_neighbours``).
    anchors : bool array, optional
        Which objects anchor quads (default all): a tile anchors its own objects and reads a margin
        around them for their neighbours.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> idx = QuadIndex(Objects.from_names(rng.uniform(0, 100, 50), rng.uniform(0, 100, 50), ["b"] * 50))
    >>> idx.n_quads > 0, idx.quad_z.shape[1]
    (True, 4)
    """

    def __init__(self, objects: Objects, neighbours: int = 8, anchors: np.ndarray | None = None) -> None:
        self.labels = tuple(objects.labels)
        z = objects.x + 1j * objects.y
        label = objects.label.astype(np.int64)
        if len(objects) >= 4:
            quads = neighbour_quads(np.column_stack([objects.x, objects.y]), neighbours, anchors=anchors)
        else:
            quads = np.zeros((0, 4), np.int64)
        if len(quads):
            # Four objects on one spot (duplicates in the sources) have no frame.
            quads = quads[np.abs(z[quads] - z[quads[:, :1]]).max(axis=1) > 0.0]
        if len(quads):
            order, inv, _ = canonical_quads(z[quads])
            quads = np.take_along_axis(quads, order, axis=1)
            keys = _label_keys(label[quads], len(self.labels))
            self.tree: cKDTree | None = cKDTree(
                np.column_stack([inv, keys * _LABEL_GAP]), balanced_tree=False, compact_nodes=False
            )
        else:
            self.tree = None
        self.quad_z = z[quads]
        self.quad_label = label[quads]

    @property
    def n_quads(self) -> int:
        return int(len(self.quad_z))

    def lookup(
        self, invariants: np.ndarray, labels: np.ndarray, radius: np.ndarray, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Map quads near image quads: the query row of each hit and the hit's four map points.

        Parameters
        ----------
        invariants : (m, 4) float
            ``Re t_C, Im t_C, Re t_D, Im t_D`` of each image quad in its (canonical) vertex order.
        labels : (m, 4) int
            Label codes of ``A, B, C, D``.
        radius : (m,) float
            Lookup radius in invariant space, per query.
        k : int
            At most this many nearest map quads per query.

        Returns
        -------
        rows : (h,) int
            Query row of each hit.
        map_z : (h, 4) complex
            The hit's map points ``A, B, C, D`` (projected metres).
        """
        if self.tree is None or not len(invariants):
            return np.zeros(0, np.int64), np.zeros((0, 4), np.complex128)
        query = np.column_stack([invariants, _label_keys(labels, len(self.labels)) * _LABEL_GAP])
        k = min(k, self.n_quads)
        dist, hit = self.tree.query(query, k=k, distance_upper_bound=float(radius.max()))
        dist = dist.reshape(len(query), k)
        hit = hit.reshape(len(query), k)
        rows, cols = np.nonzero(dist <= radius[:, None])
        return rows, self.quad_z[hit[rows, cols]]

    @classmethod
    def merged(cls, parts: Sequence[QuadIndex]) -> QuadIndex:
        """One index over the quads of several (the tiles around a prior): one lookup instead of one per part.

        Examples
        --------
        >>> rng = np.random.default_rng(0)
        >>> parts = [QuadIndex(Objects.from_names(rng.uniform(0, 100, 30), rng.uniform(0, 100, 30), ["b"] * 30))
        ...          for _ in range(2)]
        >>> QuadIndex.merged(parts).n_quads == parts[0].n_quads + parts[1].n_quads
        True
        """
        parts = [q for q in parts if q.tree is not None]
        merged = cls.__new__(cls)
        merged.labels = parts[0].labels if parts else ()
        if not parts:
            merged.tree = None
            merged.quad_z = np.zeros((0, 4), np.complex128)
            merged.quad_label = np.zeros((0, 4), np.int64)
            return merged
        merged.tree = cKDTree(
            np.concatenate([q.tree.data for q in parts]), balanced_tree=False, compact_nodes=False
        )
        merged.quad_z = np.concatenate([q.quad_z for q in parts])
        merged.quad_label = np.concatenate([q.quad_label for q in parts])
        return merged


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

    @property
    def score(self) -> float:
        return -self.log10_nfa

    @property
    def sigma_m(self) -> float:
        """Estimated 1-sigma error (per axis, metres) of the map point under the image centre."""
        return self.sigma_axis_m * math.sqrt(self.variance_factor)


@dataclass
class MatchResult:
    """What :func:`match_fast` found: ``best`` is None when the image is rejected (``reason`` says why)."""

    best: Candidate | None
    candidates: list[Candidate]
    reason: str | None
    n_hypotheses: int
    rounds: int


def _image_hypotheses(
    z: np.ndarray,
    img_label: np.ndarray,
    quads: np.ndarray,
    indexes: Sequence[QuadIndex],
    opts: FastOptions,
    sigma_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Look image quads up: correspondences ``(H, 4)``, image ids and the map points (complex)."""
    empty = np.zeros((0, 4), np.int64)
    indexes = [ix for ix in indexes if ix.n_quads]
    if not len(quads) or not indexes:
        return empty, np.zeros((0, 4), np.complex128)
    zq = z[quads]
    d = np.abs(zq[:, _PAIRS[:, 0]] - zq[:, _PAIRS[:, 1]])
    by_length = np.argsort(-d, axis=1)
    longest = d[np.arange(len(d)), by_length[:, 0]]
    rows, orders, invs, radii = [], [], [], []
    # The longest pair decides the frame; when the second longest is within noise of it, a noisy image can
    # pick either, so both frames are looked up.
    for rank in (0, 1):
        pair = by_length[:, rank]
        length = d[np.arange(len(d)), pair]
        use = np.ones(len(d), bool) if rank == 0 else longest - length < 3.0 * math.sqrt(2.0) * sigma_px
        use &= length > 0.0  # four objects on one spot have no frame
        if not use.any():
            continue
        sel = np.flatnonzero(use)
        order0, t0 = _frames(zq[sel], pair[sel])
        # Predicted standard error of the four invariants (see the module docs of decision): per point
        # sigma^2 (1 + |1 - t|^2 + |t|^2) / |AB|^2 per axis.
        spread = (1.0 + np.abs(1.0 - t0) ** 2 + np.abs(t0) ** 2).sum(axis=1)
        radius = opts.tolerance_factor * sigma_px * np.sqrt(spread) / length[sel]
        for swap_ab in (False, True):
            for swap_cd in (False, True):
                order = order0.copy()
                t = t0.copy()
                if swap_ab:
                    order[:, :2] = order[:, 1::-1]
                    t = 1.0 - t
                if swap_cd:
                    order[:, 2:] = order[:, :1:-1]
                    t = t[:, ::-1]
                # Only orderings that could be the canonical one within the lookup radius.
                slack = radius * math.sqrt(2.0)
                ok = (t.real.sum(axis=1) - 1.0 <= slack) & (t[:, 0].real - t[:, 1].real <= slack)
                ok &= radius <= opts.max_invariant_radius
                if not ok.any():
                    continue
                rows.append(sel[ok])
                orders.append(order[ok])
                invs.append(np.column_stack([t[ok, 0].real, t[ok, 0].imag, t[ok, 1].real, t[ok, 1].imag]))
                radii.append(radius[ok])
    if not rows:
        return empty, np.zeros((0, 4), np.complex128)
    row = np.concatenate(rows)
    order = np.concatenate(orders)
    img_ids = np.take_along_axis(quads[row], order, axis=1)
    inv = np.concatenate(invs)
    radius = np.concatenate(radii)
    found_img, found_map = [], []
    for index in indexes:
        q_row, map_z = index.lookup(inv, img_label[img_ids], radius, opts.max_hits_per_quad)
        found_img.append(img_ids[q_row])
        found_map.append(map_z)
    return np.concatenate(found_img), np.concatenate(found_map)


def _decision_nfa(
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
) -> np.ndarray:
    """log10 NFA of quad hypotheses over all image objects, tolerances shaped by each quad's geometry.

    A similarity fitted to four points predicts the others with an error growing with their distance
    from the quad: per-axis variance ``sigma^2 (1 + 1/4 + |z - mean|^2 / spread)``.  The tolerance disc of
    each object scales with that, so a near object must match tightly and a far one loosely.
    """
    h, n = len(a), z.size
    w = a[:, None] * z[None, :] + b[:, None]
    # The hypothesis's own map points are not evidence: an image object next to one of its quad's points
    # would find that point next to its projection by construction, not by chance.
    dist, _ = index.nearest(w, img_label, density, exclude=map_z)
    lam = density[:, img_label] if density.ndim > 1 else density[img_label][None, :]
    if local_neighbours:
        # The larger of the two densities: neither a dense old town beside empty slopes (the footprint's
        # mean density is too low there) nor an isolated object on a slope (its neighbours' distances
        # say the map is emptier than it is around the footprint) makes a chance alignment look rarer.
        lam = np.maximum(lam, index.knn_density(w, img_label, local_neighbours))
    u = lam * math.pi * dist**2
    zq = z[img_ids]
    mean = zq.mean(axis=1)
    spread = (np.abs(zq - mean[:, None]) ** 2).sum(axis=1)
    shape = 1.25 + np.abs(z[None, :] - mean[:, None]) ** 2 / spread[:, None]
    sample = np.zeros((h, n), bool)
    sample[np.arange(h)[:, None], img_ids] = True
    nfa, _ = log10_nfa_curve(u, 4, log10_tests, shape=shape, sample=sample)
    return nfa


def _prioritise(a: np.ndarray, b: np.ndarray, diag_px: float, limit: int) -> np.ndarray:
    """Indices of at most ``limit`` hypotheses, those whose pose most others share first.

    Poses are binned coarsely (10 degrees of rotation, 10% of scale, a twentieth of the footprint
    diagonal in position) and each hypothesis counts the hypotheses in its bin.
    """
    if len(a) <= limit:
        return np.arange(len(a))
    scale = np.abs(a)
    cell = scale * diag_px / 20.0
    key = np.column_stack(
        [
            np.floor(np.log(scale) / 0.1),
            np.floor(np.angle(a) / math.radians(10.0)),
            np.floor(b.real / cell),
            np.floor(b.imag / cell),
        ]
    ).astype(np.int64)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    votes = counts[inverse.reshape(-1)]
    return np.argsort(-votes, kind="stable")[:limit]


def _refine(
    a: np.ndarray,
    b: np.ndarray,
    z: np.ndarray,
    img_label: np.ndarray,
    index: ObjectIndex,
    density: np.ndarray,
    log10_tests: float,
    iterations: int,
) -> tuple[np.ndarray, ...]:
    """Re-associate and refit ``H`` hypotheses; returns a, b, log10 NFA, inlier mask, map ids, distances."""
    h, n = len(a), z.size
    rows = np.arange(h)
    for it in range(iterations + 1):
        w = a[:, None] * z[None, :] + b[:, None]
        dist, mid = index.nearest(w, img_label, density)
        lam = density[:, img_label] if density.ndim > 1 else density[img_label][None, :]
        u = lam * math.pi * dist**2
        nfa, k_best = log10_nfa_curve(u, 4, log10_tests)
        u_sorted = np.sort(u, axis=1)
        u_cut = u_sorted[rows, np.clip(k_best - 1, 0, n - 1)]
        inlier = (u <= u_cut[:, None]) & np.isfinite(dist)
        k = inlier.sum(axis=1)
        # A generous second net: everything within 3.5 sigma of the current fit (sigma from its inliers),
        # so that the final fit uses every true correspondence, as the bound does.
        with np.errstate(invalid="ignore", divide="ignore"):
            sigma = np.sqrt(np.where(inlier, dist**2, 0.0).sum(axis=1) / np.maximum(2 * k - 4, 1))
        inlier |= (dist <= 3.5 * sigma[:, None]) & np.isfinite(dist)
        inlier &= _first_per_map_object(mid, dist, inlier)
        if it == iterations:
            break
        target = index.z[np.maximum(mid, 0)]
        a_new, b_new = fit_similarity_complex(z[None, :], target, inlier)
        ok = np.isfinite(a_new) & (inlier.sum(axis=1) >= 3)
        a = np.where(ok, a_new, a)
        b = np.where(ok, b_new, b)
    return a, b, nfa, inlier, mid, dist


def _first_per_map_object(mid: np.ndarray, dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Mask keeping, per row and map object, only the closest of the image objects matched to it."""
    h, n = mid.shape
    keep = np.ones((h, n), bool)
    r, c = np.nonzero(inlier)
    if r.size == 0:
        return keep
    order = np.lexsort((dist[r, c], mid[r, c], r))
    r, c = r[order], c[order]
    dup = np.zeros(r.size, bool)
    dup[1:] = (r[1:] == r[:-1]) & (mid[r[1:], c[1:]] == mid[r[:-1], c[:-1]])
    keep[r[dup], c[dup]] = False
    return keep


def _distinct(b: np.ndarray, order: np.ndarray, separation: np.ndarray, limit: int) -> list[int]:
    """Greedy non-maximum suppression: indices (in ``order``) at least ``separation`` apart."""
    chosen: list[int] = []
    for i in order:
        if all(abs(b[i] - b[j]) > max(separation[i], separation[j]) for j in chosen):
            chosen.append(int(i))
            if len(chosen) >= limit:
                break
    return chosen


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
        Where hypotheses are looked up (the whole map's, or the tiles around a prior).
    diag_px : float
        Image diagonal in pixels (sets the footprint for densities and pose bins).
    options : FastOptions, optional
    prior : (x, y, radius), optional
        The map point under the image centre must lie within ``radius`` of ``(x, y)`` (hypotheses
        within 1.1 times the radius are tried).
    scale_range : (low, high), optional
        Allowed metres per pixel (from a known altitude and field of view).

    Returns
    -------
    MatchResult
    """
    opts = options or FastOptions()
    z = np.asarray(z, dtype=np.complex128)
    img_label = np.asarray(img_label, dtype=np.int64)
    if z.size > opts.max_objects:
        central = np.sort(np.argsort(np.abs(z), kind="stable")[: opts.max_objects])
        z, img_label = z[central], img_label[central]
    n = z.size
    if n < 4:
        return MatchResult(None, [], f"{n} objects: the fast matcher needs at least 4", 0, 0)
    index = objects
    if len(index) < 4:
        return MatchResult(None, [], f"the map has only {len(index)} objects here: at least 4 are needed", 0, 0)
    if not any(q.n_quads for q in quads):
        return MatchResult(None, [], f"the map's {len(index)} objects here form no pattern to match", 0, 0)

    # Each hypothesis is screened on the image objects around its quad (the neighbours of its first
    # point), where a right hypothesis predicts positions best.
    screen_of = cKDTree(np.column_stack([z.real, z.imag])).query(
        np.column_stack([z.real, z.imag]), k=min(opts.screen_objects, n)
    )[1].reshape(n, -1)
    # Anchors nearest the image centre first: their neighbourhoods are least cut by the image edge.
    img_quads, anchor = neighbour_quads(np.column_stack([z.real, z.imag]), opts.image_neighbours, with_anchor=True)
    rank = np.empty(n, np.int64)
    rank[np.argsort(np.abs(z), kind="stable")] = np.arange(n)
    batch_of = rank[anchor] // opts.anchors_per_batch
    by_batch = np.argsort(batch_of, kind="stable")
    _, first = np.unique(img_quads[by_batch], axis=0, return_index=True)
    keep = np.zeros(len(img_quads), bool)
    keep[by_batch[first]] = True  # each quad once, in its earliest batch
    n_batches = min(int(batch_of.max()) + 1, opts.max_batches) if len(img_quads) else 0
    batches = [img_quads[keep & (batch_of == i)] for i in range(n_batches)]

    n_tests = 0
    pool: list[Candidate] = []
    done_rounds = 0
    rounds = [(sigma_px, batch) for sigma_px in opts.pixel_sigmas for batch in batches if len(batch)]
    for sigma_px, batch in rounds:
        done_rounds += 1
        img_ids, map_z = _image_hypotheses(z, img_label, batch, quads, opts, sigma_px)
        if not len(img_ids):
            continue
        a, b = fit_similarity_complex(z[img_ids], map_z)
        ok = np.isfinite(a) & (np.abs(a) > 0)
        if prior is not None:
            # A little slack: a quad's estimate of the centre is noisier than the final answer.
            ok &= np.abs(b - complex(prior[0], prior[1])) <= 1.1 * prior[2]
        if scale_range is not None:
            ok &= (np.abs(a) >= scale_range[0]) & (np.abs(a) <= scale_range[1])
        a, b, img_ids, map_z = a[ok], b[ok], img_ids[ok], map_z[ok]
        n_tests += a.size
        if not a.size:
            continue
        log10_tests = math.log10(n_tests)

        # Screen: a cheap NFA (the region's mean densities, the objects around each quad) ranks them ...
        pick = _prioritise(a, b, diag_px, opts.max_verified)
        a, b, img_ids, map_z = a[pick], b[pick], img_ids[pick], map_z[pick]
        screen = screen_of[img_ids[:, 0]]
        dist, _ = index.nearest(a[:, None] * z[screen] + b[:, None], img_label[screen], index.density)
        u = index.density[img_label[screen]] * math.pi * dist**2
        screen_nfa, _ = log10_nfa_curve(u, 4, log10_tests)
        top = np.argsort(screen_nfa, kind="stable")[: opts.shortlist]
        a, b, img_ids, map_z = a[top], b[top], img_ids[top], map_z[top]
        # ... the shortlist gets the full test (all objects, tolerances shaped by each quad's geometry) ...
        nfa = _decision_nfa(a, b, img_ids, map_z, z, img_label, index, index.density, log10_tests)
        chosen = _distinct(b, np.argsort(nfa, kind="stable"), np.abs(a) * diag_px / 20.0, opts.refine_candidates)
        a, b, img_ids, map_z = a[chosen], b[chosen], img_ids[chosen], map_z[chosen]
        # ... and the decision is that test with the label densities around each place.  It is taken on the
        # hypotheses as they came from their quads (AC-RANSAC's rule: a model refitted to its own inliers
        # looks better than chance says); refinement then only improves the position.
        radius = opts.density_radius_factor * np.abs(a) * diag_px / 2.0
        density = index.local_density(b, radius)
        nfa = _decision_nfa(a, b, img_ids, map_z, z, img_label, index, density, log10_tests,
                            opts.density_neighbours)
        a, b, _, inlier, mid, dist = _refine(a, b, z, img_label, index, density, log10_tests, 2)
        for j in range(len(a)):
            k = int(inlier[j].sum())
            if not np.isfinite(a[j]) or k < 3:
                continue
            sigma = math.sqrt(float(np.sum(dist[j, inlier[j]] ** 2)) / max(2 * k - 4, 1))
            pool.append(
                Candidate(
                    a=complex(a[j]),
                    b=complex(b[j]),
                    log10_nfa=float(nfa[j]),
                    inliers=k,
                    sigma_axis_m=sigma,
                    variance_factor=float(prediction_variance_factor(z[inlier[j]])),
                    pairs=np.column_stack([np.flatnonzero(inlier[j]), mid[j, inlier[j]]]),
                )
            )
        pool = _merge(pool, diag_px)
        if pool and pool[0].log10_nfa < opts.log10_epsilon:
            break

    if not pool:
        return MatchResult(None, [], "no consistent pattern found in the map", n_tests, done_rounds)
    best, rest = pool[0], pool[1 : 1 + opts.max_candidates]
    if best.log10_nfa >= opts.log10_epsilon:
        return MatchResult(
            None,
            pool[: opts.max_candidates],
            f"no match is certain enough (best log10 NFA {best.log10_nfa:.1f} with {best.inliers} inliers; "
            f"needs < {opts.log10_epsilon:g})",
            n_tests,
            done_rounds,
        )
    if rest and rest[0].log10_nfa < opts.log10_epsilon and rest[0].score > best.score - opts.ambiguity_margin:
        return MatchResult(
            None,
            pool[: opts.max_candidates],
            f"ambiguous: two places match about equally well (scores {best.score:.1f} and {rest[0].score:.1f})",
            n_tests,
            done_rounds,
        )
    best = _polish(best, z, img_label, index)
    if opts.max_sigma_m is not None and best.sigma_m > opts.max_sigma_m:
        return MatchResult(
            None,
            [best, *rest][: opts.max_candidates],
            f"imprecise: estimated 1-sigma error {best.sigma_m:.2f} m exceeds {opts.max_sigma_m:g} m "
            f"({best.inliers} inliers)",
            n_tests,
            done_rounds,
        )
    return MatchResult(best, rest, None, n_tests, done_rounds)


def _polish(
    cand: Candidate, z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, iterations: int = 2
) -> Candidate:
    """Final association by optimal assignment, then the least-squares fit over it.

    Nearest-neighbour association with one image object per map object loses a true pair when two map
    objects lie closer together than the noise (the loser's own map object is its second nearest).
    Here every image object may take any map object of its label within the gate (3.5 sigma of the
    current fit, and at least its farthest inlier), and the pairs minimising the total squared
    distance are kept (a minimum-weight full bipartite matching).
    """
    a, b = cand.a, cand.b
    farthest = float(np.max(np.abs(a * z[cand.pairs[:, 0]] + b - index.z[cand.pairs[:, 1]])))
    gate = max(3.5 * cand.sigma_axis_m, farthest, 1e-9)
    pairs = cand.pairs
    for _ in range(iterations):
        w = a * z + b
        rows, cols, costs = index.within(w, img_label, gate, 3)
        if not rows.size:
            return cand
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
        pairs = np.column_stack([img_u[r_opt[good]], map_u[c_opt[good]]])
        if len(pairs) < 3:
            return cand
        a_new, b_new = fit_similarity_complex(z[pairs[:, 0]], index.z[pairs[:, 1]])
        if not np.isfinite(a_new):
            return cand
        a, b = complex(a_new), complex(b_new)
    dist = np.abs(a * z[pairs[:, 0]] + b - index.z[pairs[:, 1]])
    k = len(pairs)
    return Candidate(
        a=a,
        b=b,
        log10_nfa=cand.log10_nfa,
        inliers=k,
        sigma_axis_m=math.sqrt(float(np.sum(dist**2)) / max(2 * k - 4, 1)),
        variance_factor=float(prediction_variance_factor(z[pairs[:, 0]])),
        pairs=pairs,
    )


def _merge(pool: list[Candidate], diag_px: float) -> list[Candidate]:
    """Best first, one candidate per place (refinement often brings several hypotheses to one pose)."""
    pool = sorted(pool, key=lambda c: (c.log10_nfa, -c.inliers))
    kept: list[Candidate] = []
    for c in pool:
        sep = abs(c.a) * diag_px / 20.0
        if all(abs(c.b - k.b) > sep for k in kept):
            kept.append(c)
    return kept
