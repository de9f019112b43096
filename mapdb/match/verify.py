"""Verification: how well a hypothesis explains the image, against the map's objects.

Image objects are projected into the map by each hypothesis and matched to the nearest map object of
their label (:class:`ObjectIndex`); residuals become normalised ``u = lambda pi r^2`` and the a contrario
model of :mod:`mapdb.match.decision` turns them into a number of false alarms.  :func:`screen` ranks many
hypotheses cheaply, :func:`decision_nfa` is the full test, :func:`refine` re-associates and refits.
"""

from __future__ import annotations

import math

import numpy as np

from .._scipy import cKDTree
from ..objects import Objects
from .decision import log10_nfa_curve
from .geometry import fit_similarity_complex

# Residual sigmas within which an association is kept (refinement's second net, the final assignment's gate).
GATE_SIGMAS = 3.5

__all__ = [
    "GATE_SIGMAS", "U_MAX", "ObjectIndex", "decision_nfa", "first_per_map_object", "refine", "residual_sigmas",
    "screen",
]

# Normalised residual beyond which an object counts as unmatched (a random point would be that close
# with probability 1 - e^-3 = 95%): also the search bound of the nearest-neighbour queries.
U_MAX = 3.0

# Fixed sample of the unit disc (sunflower pattern) for the share of a density disc inside the map.
_DISC = np.sqrt((np.arange(256) + 0.5) / 256) * np.exp(1j * np.arange(256) * math.pi * (3 - math.sqrt(5)))



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
        normalised residual ``U_MAX`` get ``inf`` and -1.  ``exclude`` (complex, ``(H, m)``) lists map
        positions that row ``h`` may not use: the map points a hypothesis was built from.
        """
        shape = w.shape
        labels = np.broadcast_to(img_label, shape).ravel()
        dist = np.full(labels.size, np.inf)
        index = np.full(labels.size, -1, dtype=np.int64)
        if self.tree is None:
            return dist.reshape(shape), index.reshape(shape)
        lam = np.min(density, axis=0) if np.ndim(density) > 1 else np.asarray(density)
        reach = np.sqrt(U_MAX / (math.pi * lam))[labels]
        k = 1 if exclude is None else 1 + exclude.shape[1]
        d, i = self.tree.query(self._points(w.ravel(), labels), k=k, distance_upper_bound=self._bound(reach.max()))
        if k == 1:  # nothing to exclude: the nearest is the answer when within reach
            ok = d <= reach
            return np.where(ok, d, np.inf).reshape(shape), np.where(ok, i, -1).reshape(shape)
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
    hypothesis predicts positions best."""
    objects = screen_of[img_ids[:, 0]]
    dist, _ = index.nearest(a[:, None] * z[objects] + b[:, None], img_label[objects], index.density)
    u = index.density[img_label[objects]] * math.pi * dist**2
    nfa, _ = log10_nfa_curve(u, 4, log10_tests)
    return np.argsort(nfa, kind="stable")[:keep]


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


def refine(
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
    previous: tuple[np.ndarray, np.ndarray] | None = None
    for it in range(iterations + 1):
        w = a[:, None] * z[None, :] + b[:, None]
        dist, mid = index.nearest(w, img_label, density)
        lam = density[:, img_label] if density.ndim > 1 else density[img_label][None, :]
        u = lam * math.pi * dist**2
        nfa, k_best = log10_nfa_curve(u, 4, log10_tests)
        u_sorted = np.sort(u, axis=1)
        u_cut = u_sorted[rows, np.clip(k_best - 1, 0, n - 1)]
        inlier = (u <= u_cut[:, None]) & np.isfinite(dist)
        # A generous second net: everything within GATE_SIGMAS sigmas of the current fit (sigma from its inliers),
        # so that the final fit uses every true correspondence, as the bound does.
        sigma = residual_sigmas(dist, inlier)
        inlier |= (dist <= GATE_SIGMAS * sigma[:, None]) & np.isfinite(dist)
        inlier &= first_per_map_object(mid, dist, inlier)
        if it == iterations:
            break
        if previous is not None and np.array_equal(previous[0], inlier) and np.array_equal(previous[1], mid):
            # The same association as the fit that gave (a, b): refitting gives (a, b) again, and every
            # further round the same association, so this is where the iterations would end.
            break
        previous = inlier, mid
        target = index.z[np.maximum(mid, 0)]
        a_new, b_new = fit_similarity_complex(z[None, :], target, inlier)
        ok = np.isfinite(a_new) & (inlier.sum(axis=1) >= 3)
        a = np.where(ok, a_new, a)
        b = np.where(ok, b_new, b)
    return a, b, nfa, inlier, mid, dist


def residual_sigmas(dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Per-axis error of each row's similarity fitted to its inliers: ``sqrt(sum r^2 / (2k - 4))``.

    ``dist`` and ``inlier`` are ``(H, n)``; 4 parameters are fitted, so ``2k - 4`` degrees of freedom
    (at least 1).
    """
    k = inlier.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.where(inlier, dist**2, 0.0).sum(axis=1) / np.maximum(2 * k - 4, 1))


def first_per_map_object(mid: np.ndarray, dist: np.ndarray, inlier: np.ndarray) -> np.ndarray:
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
