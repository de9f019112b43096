"""The map's objects for verification: a KD-tree per label (the compiled kernel's), label densities, stored areas.

:class:`ObjectIndex` answers what :mod:`mapdb.match.verify` asks of the map: the nearest object of an image
object's label where a hypothesis projects it (optionally with a compatible area), objects within a gate,
densities per label in a disc or from the ``k``-th nearest.  :mod:`mapdb.match.mapobjects.paged_objects` gives the
same answers for a big map file read page by page.
"""

from __future__ import annotations

import math

import numpy as np

from ...objects import Objects
from .._kernel import first_allowed, objects_density, places_reach, screen_near_counts, verify_screen
from ..arrays import sorted_unique
from ..evidence.areas import compatible
from ..nfa import LOG10_FLOOR, log10_nfa_curve, log10_trials
from .fused_arrays import FusedArrays, fused_of
from .kd_forest import Forest
from .label_trees import LabelTrees

__all__ = ["AREA_NEIGHBOURS", "GLOBAL_REACH_M", "U_MAX", "Neighbours", "ObjectIndex"]

# Normalised residual beyond which an object counts as unmatched (a random point would be that close
# with probability 1 - e^-3 = 95%): also the search bound of the nearest-neighbour queries.
U_MAX = 3.0
# The longest search of a ranking under mean densities (see ``ObjectIndex._reach``).
GLOBAL_REACH_M = 300.0

# Neighbours looked at for an area-compatible map object when the nearest is not one (beyond the excluded).
AREA_NEIGHBOURS = 8

# Fixed sample of the unit disc (sunflower pattern) for the share of a density disc inside the map.
_DISC = np.sqrt((np.arange(256) + 0.5) / 256) * np.exp(1j * np.arange(256) * math.pi * (3 - math.sqrt(5)))


# The map positions the kernel reads when a map has no object (none is ever looked at: no neighbour is in reach).
_NO_OBJECT = np.zeros(1, np.complex128)


def _flat_labels(img_label: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``np.broadcast_to(img_label, shape).ravel()`` for the usual ``(n,)`` labels of ``(H, n)`` points, in one call."""
    if img_label.ndim == 1 and len(shape) == 2 and img_label.size == shape[1]:
        return img_label[None, :].repeat(shape[0], axis=0).ravel()
    return np.broadcast_to(img_label, shape).ravel()


class Neighbours:
    """The ``k`` nearest map objects of their own label of projected image objects ``(H, n)``, found once and
    read by every query of the same points (:meth:`ObjectIndex.neighbours`).

    A round's decision, its label densities around each projected object and its refinement's first
    association all ask about the same projections; one query answers all three, and a query of the ``k``
    nearest with no bound holds the answer of any query of fewer neighbours within any bound: the first ones
    within the bound.

    Attributes
    ----------
    dist, index : arrays (H * n, k)
        Distances and indices of each point's ``k`` nearest, nearest first (``inf`` and ``len(index)`` where
        its label has fewer objects).
    shape : (H, n)
        The projections' shape.
    """

    def __init__(self, dist: np.ndarray, index: np.ndarray, shape: tuple[int, int]) -> None:
        self.dist, self.index, self.shape = dist, index, shape

    @property
    def k(self) -> int:
        """Neighbours held per point."""
        return int(self.dist.shape[1])

    def take(self, rows: np.ndarray | list[int]) -> Neighbours:
        """The table of the hypotheses ``rows`` (indices into the first axis of ``shape``), in that order."""
        h, n = self.shape
        k = self.k
        rows = np.asarray(rows, np.int64)
        return Neighbours(self.dist.reshape(h, n, k)[rows].reshape(-1, k),
                          self.index.reshape(h, n, k)[rows].reshape(-1, k), (rows.size, n))


class ObjectIndex:
    """Map objects for verification: a KD-tree per label, label densities, the region's bounds.

    ``tree`` (a :class:`~mapdb.match.mapobjects.label_trees.LabelTrees`) finds, in one call of the compiled
    kernel, the nearest objects of each query's own label whatever the mix of labels (a call costs 4-8
    microseconds of fixed cost; the cKDTree over ``(x, y, label * gap)`` it replaced cost 29-54).

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
        self._bounds = np.array(self.bounds)
        self.area = max((self.bounds[2] - self.bounds[0]) * (self.bounds[3] - self.bounds[1]), 1.0)
        self.counts = np.bincount(self.label, minlength=len(self.labels)) if n else np.zeros(len(self.labels), int)
        # Densities over the whole region only rank hypotheses; the decision uses local ones.
        self.density = np.maximum(self.counts, 1) / self.area
        # Search bounds stay below half of it (``_bound``), as when one cKDTree kept the labels apart by it: the
        # same bounds, the same answers.
        self.gap = 1e3 * (math.sqrt(self.area) + 1e4)
        self.tree: LabelTrees | Forest | None = LabelTrees(self.z, self.label, len(self.labels)) if n else None
        self._area = objects.area
        self._log_area: np.ndarray | None = None  # made on first use: only images with areas need it
        self._global_reach: tuple[np.ndarray, np.ndarray] | None = None  # (density, reaches): see ``_reach``
        # Each object's ground elevation (metres; NaN unknown), None for a flat map: the terrain evidence's
        # (:mod:`mapdb.match.evidence.terrain`), which keeps its tree in ``terrain``.
        self.elevation = objects.elevation
        self.terrain: object | None = None

    def __len__(self) -> int:
        return int(self.z.size)

    def _bound(self, reach: float) -> float:
        return float(min(reach, 0.5 * self.gap))

    def local_density(self, centres: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Objects per square metre of each label within ``radius`` of each centre (inside the bounds).

        ``centres`` (complex) and ``radius`` have shape ``(H,)``; the result ``(H, L)``.  A label with no
        object in a disc counts one, so that no density is zero.
        """
        centres = np.ascontiguousarray(np.asarray(centres, np.complex128).reshape(-1))
        radius = np.asarray(radius, np.float64)
        if radius.shape != centres.shape:  # the usual radius is one a centre (broadcast_to costs 5 us)
            radius = np.broadcast_to(radius, centres.shape)
        radius = np.ascontiguousarray(radius)
        # The disc's share inside the bounds, its area, each present label's count over the trees: one kernel call.
        out = np.empty((centres.size, len(self.labels)))
        objects_density(self._trees(), centres, radius, _DISC, self._bounds, np.flatnonzero(self.counts),
                        0.5 * self.gap, out)
        return out

    def fused_tree(self) -> LabelTrees | None:
        """The tree the compiled kernel's fused queries read: the index's :class:`LabelTrees` when it holds its
        objects in one and answers :meth:`nearest` itself, else None (an index reading pages as queries need them
        answers through its own methods)."""
        tree = self.tree
        return tree if isinstance(tree, LabelTrees) and type(self).nearest is ObjectIndex.nearest else None

    def fused(self) -> FusedArrays | None:
        """The arrays the kernel's fused queries read (:func:`~mapdb.match.mapobjects.fused_arrays.fused_of`) when
        :meth:`fused_tree` is a tree, else None."""
        return fused_of(self, _DISC)

    def _trees(self) -> list[tuple[np.ndarray, ...]]:
        """The arrays of each :class:`LabelTrees` holding the objects (none without objects)."""
        tree = self.tree
        if tree is None:
            return []
        return [tree._tree()] if isinstance(tree, LabelTrees) else [t._tree() for t in tree.trees]

    def neighbours(self, w: np.ndarray, img_label: np.ndarray, k: int) -> Neighbours | None:
        """The ``k`` nearest map objects of each projected image object's label (``w``: ``(H, n)`` complex,
        ``img_label``: ``(n,)``), for :meth:`nearest` and :meth:`knn_density` of the same ``w`` (their ``near``);
        None where one query cannot serve them (no objects; an index reading pages as queries need them)."""
        if self.tree is None or type(self).nearest is not ObjectIndex.nearest:
            return None
        labels = _flat_labels(img_label, w.shape)
        d, i = self.tree.query(w, labels, k, self._bound(0.5 * self.gap))
        return Neighbours(d, i, w.shape)

    def knn_density(self, w: np.ndarray, img_label: np.ndarray, k: int,
                    near: Neighbours | None = None) -> np.ndarray:
        """Objects per square metre of each projected image object's label around where it lands.

        ``(k - 1) / (pi d_k^2)``, ``d_k`` the distance to the ``k``-th nearest map object of that label: a
        density that follows the map's clustering (a dense old town beside empty slopes), where one
        density over the footprint would make chance alignments in the town look significant.  A label
        with a single map object gets ``1 / (pi d_1^2)``; a label absent from the map, the region's floor.
        ``w`` is ``(H, n)`` complex; ``img_label`` ``(n,)``.  Returns ``(H, n)``.  ``near``: :meth:`neighbours` of
        the same ``w`` with at least ``k`` (used instead of a query of its own).
        """
        shape = w.shape
        labels = _flat_labels(img_label, shape)
        out = np.full(labels.size, 1.0 / self.area)
        kk = np.minimum(k, self.counts[labels])
        sel = np.flatnonzero(kk > 0)
        if self.tree is None or not sel.size:
            return out.reshape(shape)
        if near is not None and near.k >= k:
            d = near.dist[sel, kk[sel] - 1]
        else:
            k_max = int(kk[sel].max())
            d, _ = self.tree.query(w.ravel()[sel], labels[sel], k_max, self._bound(0.5 * self.gap))
            d = d[np.arange(sel.size), kk[sel] - 1]
        out[sel] = np.maximum(kk[sel] - 1, 1) / (math.pi * np.maximum(d, 1e-3) ** 2)
        return out.reshape(shape)

    def nearest(
        self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray, exclude: np.ndarray | None = None,
        near: Neighbours | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance to, and index of, the nearest map object of each projected image object's label.

        ``w`` has shape ``(H, n)`` (map metres, complex); ``img_label`` is ``(n,)`` or ``(H, n)``;
        ``density`` is ``(L,)`` or ``(H, L)``.  Objects with nothing of their label within the
        normalised residual ``U_MAX`` get ``inf`` and -1.  ``exclude`` (complex, ``(H, m)``) lists map
        positions that row ``h`` may not use: the map points a hypothesis was built from.  ``near``:
        :meth:`neighbours` of the same ``w`` (read instead of a query of its own when it holds enough).
        """
        shape = w.shape
        labels = _flat_labels(img_label, shape)
        if self.tree is None:
            return np.full(shape, np.inf), np.full(shape, -1, dtype=np.int64)
        reach = self._reach(density, labels)
        k = 1 if exclude is None else 1 + exclude.shape[1]
        if near is not None and near.k >= k:
            # Its first k within the reach are what a query of k bounded by the reach finds.
            d, i = (near.dist[:, 0], near.index[:, 0]) if k == 1 else (near.dist[:, :k], near.index[:, :k])
        else:
            d, i = self.tree.query(w, labels, k, self._bound(reach.max()))
            d, i = (d[:, 0], i[:, 0]) if k == 1 else (d, i)
        if exclude is None:  # nothing to exclude: the nearest is the answer when within reach
            ok = d <= reach
            return np.where(ok, d, np.inf).reshape(shape), np.where(ok, i, -1).reshape(shape)
        dist, index = self._first_allowed(d.reshape(labels.size, k), i.reshape(labels.size, k), reach, exclude,
                                          repeat=shape[1])
        return dist.reshape(shape), index.reshape(shape)

    def _reach(self, density: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """The search reach of each object: where its normalised residual would pass ``U_MAX``.

        Under the region's mean densities (a 1-D ``density``, which only ranks hypotheses) at most
        ``GLOBAL_REACH_M``: a sparse label's mean density would send the search kilometres away, where a
        "match" means nothing (and a map read page by page would read all of it).  On 400 Andorra images
        the answers are bit-identical with and without the cap."""
        return self.label_reach(density)[labels]

    def label_reach(self, density: np.ndarray) -> np.ndarray:
        """Each label's search reach under ``density`` (``(L,)`` or ``(H, L)``: the least dense row's): :meth:`_reach`
        of every label."""
        if density is self.density:  # the region's: the same reaches for every image, computed once
            return self._label_reach()
        if np.ndim(density) > 1:  # sqrt(U_MAX / (pi min over rows)): one kernel call, not four of numpy's
            out = np.empty(np.shape(density)[1])
            places_reach(np.ascontiguousarray(density, np.float64), U_MAX, out)
            return out
        return np.minimum(np.sqrt(U_MAX / (math.pi * np.asarray(density))), GLOBAL_REACH_M)

    def _label_reach(self) -> np.ndarray:
        """Each label's reach under the region's densities (``_reach``), made once."""
        if self._global_reach is None or self._global_reach[0] is not self.density:
            self._global_reach = self.density, np.minimum(np.sqrt(U_MAX / (math.pi * self.density)), GLOBAL_REACH_M)
        return self._global_reach[1]

    def screen_nfa(self, a: np.ndarray, b: np.ndarray, z: np.ndarray, objects: np.ndarray, img_label: np.ndarray,
                   log10_tests: float) -> np.ndarray:
        """The screen's log10 NFA of each hypothesis ``z -> a z + b`` (``a``, ``b``: ``(H,)``) over its image objects
        ``objects`` (``(H, k)`` indices into ``z`` and ``img_label``): the curve of
        :func:`~mapdb.match.nfa.log10_nfa_curve` (4 samples) over ``u = density pi d^2``, ``d`` the distance to the
        nearest map object of the object's label under the region's densities (:meth:`nearest`).

        One call of the compiled kernel (``verify_screen``: projection, queries and curve), each query bounded by
        its own label's reach; an index whose ``nearest`` reads pages as queries need them answers through it."""
        h, k = objects.shape
        if h == 0 or k <= 4:
            return np.full(h, np.inf)
        offset = log10_tests + log10_trials(k - 4)
        tree = self.fused_tree()
        if tree is None:
            labels = img_label[objects]
            dist, _ = self.nearest(a[:, None] * z[objects] + b[:, None], labels, self.density)
            return log10_nfa_curve(self.density[labels] * math.pi * dist**2, 4, log10_tests)[0]
        nfa = np.empty(h)
        verify_screen(*tree._tree(), np.ascontiguousarray(a, np.complex128),
                      np.ascontiguousarray(b, np.complex128), np.ascontiguousarray(z, np.complex128),
                      np.ascontiguousarray(objects, np.int64), np.ascontiguousarray(img_label, np.int64),
                      self._label_reach(), self.density, 0.5 * self.gap, 4, offset, LOG10_FLOOR, nfa)
        return nfa

    def _first_allowed(self, d: np.ndarray, i: np.ndarray, reach: np.ndarray, exclude: np.ndarray | None,
                       allowed: np.ndarray | None = None, repeat: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Of ``k`` neighbours a query point (``d``, ``i``: ``(m, k)``), the nearest within reach, not at one of
        its ``exclude`` points (row ``q // repeat`` of ``exclude``, ``(m / repeat, e)``: its hypothesis's, closer
        than a micrometre) and ``allowed`` (``(m, k)``): distances and indices (inf and -1 if none).  The compiled
        kernel's loop: it stops at the first allowed neighbour."""
        m = d.shape[0]
        out_d, out_i = np.empty(m), np.empty(m, np.int64)
        z = np.ascontiguousarray(self.z, np.complex128) if len(self) else _NO_OBJECT
        first_allowed(
            np.ascontiguousarray(d, np.float64), np.ascontiguousarray(i, np.int64),
            np.ascontiguousarray(reach, np.float64), z,
            None if exclude is None else np.ascontiguousarray(exclude, np.complex128), repeat,
            None if allowed is None else np.ascontiguousarray(allowed, bool), out_d, out_i)
        return out_d, out_i

    @property
    def log_area(self) -> np.ndarray:
        """Natural log of each map object's stored area (NaN where it has none: points)."""
        if self._log_area is None:
            with np.errstate(divide="ignore", invalid="ignore"):
                self._log_area = np.where(self._area > 0, np.log(self._area), np.nan)
        return self._log_area

    def nearest_compatible(self, w: np.ndarray, img_label: np.ndarray, density: np.ndarray, exclude: np.ndarray | None,
                           lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`nearest`, among the map objects whose areas are compatible with each image object's band
        (``lo``, ``hi``: ``(H, n)`` log square metres, :func:`mapdb.match.evidence.areas.bands`).  Where the nearest is
        not compatible, the next ``AREA_NEIGHBOURS`` are looked at; none compatible counts as unmatched."""
        dist, index = self.nearest(w, img_label, density, exclude)  # also what a paged index loads for the reach
        ok = compatible(self.log_area[np.maximum(index, 0)], lo, hi) | (index < 0)
        redo = np.flatnonzero(~ok.ravel())
        if not redo.size:
            return dist, index
        shape = w.shape
        labels = np.broadcast_to(img_label, shape).ravel()[redo]
        reach = self._reach(density, labels)
        k = min(len(self), AREA_NEIGHBOURS + (0 if exclude is None else exclude.shape[1]))
        d, i = self.tree.query(w.ravel()[redo], labels, k, self._bound(reach.max()))  # type: ignore[union-attr]
        allowed = compatible(self.log_area[np.minimum(i, len(self) - 1)], lo.ravel()[redo][:, None],
                             hi.ravel()[redo][:, None])
        rows = redo // shape[1]
        dist, index = dist.ravel().copy(), index.ravel().copy()
        dist[redo], index[redo] = self._first_allowed(d, i, reach, None if exclude is None else exclude[rows], allowed)
        return dist.reshape(shape), index.reshape(shape)

    def at(self, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Index of the map object at each of ``points`` (complex, any shape) of ``labels`` (same shape), -1
        where there is none (within a millimetre)."""
        if self.tree is None:
            return np.full(np.shape(points), -1, np.int64)
        d, i = self.tree.query(points, labels, 1, 1e-3)
        return np.where(np.isfinite(d), i, -1).reshape(np.shape(points))

    def disc_members(self, centres: np.ndarray, radius: np.ndarray, codes: np.ndarray) -> list[list[np.ndarray]]:
        """Indices of the map objects of each label in ``codes`` within ``radius`` of each centre:
        ``out[h][code]`` (empty for the labels not asked)."""
        centres = np.atleast_1d(np.asarray(centres, np.complex128))
        radius = np.broadcast_to(np.asarray(radius, np.float64), centres.shape)
        empty = np.zeros(0, np.int64)
        out = [[empty] * len(self.labels) for _ in range(centres.size)]
        if self.tree is None:
            return out
        codes = sorted_unique(codes)
        w = np.repeat(centres, codes.size)
        found = self.tree.members(w, np.tile(codes, centres.size), np.minimum(np.repeat(radius, codes.size),
                                                                              0.5 * self.gap))
        for j, hits in enumerate(found):
            out[j // codes.size][int(codes[j % codes.size])] = hits
        return out

    def near_counts(self, a: np.ndarray, b: np.ndarray, z: np.ndarray, img_label: np.ndarray, gate: float,
                    at_least: int = 0) -> np.ndarray:
        """How many image objects each pose ``z -> a z + b`` (``a``, ``b``: ``(H,)``) puts closer than ``gate`` metres
        (at most half the label gap) to a map object of their label: ``(H,)``, the pairs :meth:`within` would find
        with ``k = 1`` counted per pose.  A count below ``at_least`` may stop short (it stays below): a caller
        asking only for the poses reaching it is spared the rest of the others' queries.  One call of the compiled
        kernel (``screen_near_counts``) on an index whose objects are in one tree; an index reading pages as queries
        need them counts through :meth:`within`."""
        tree = self.fused_tree()
        if tree is None:
            w = (a[:, None] * z[None, :] + b[:, None]).ravel()
            rows, _, _ = self.within(w, np.tile(img_label, a.size), gate, 1)
            return np.bincount(rows // z.size, minlength=a.size)
        out = np.empty(a.size, np.int64)
        screen_near_counts(*tree._tree(), np.ascontiguousarray(a, np.complex128),
                           np.ascontiguousarray(b, np.complex128), np.ascontiguousarray(z, np.complex128),
                           np.ascontiguousarray(img_label, np.int64), self._bound(gate), at_least, out)
        return out

    def within(self, w: np.ndarray, img_label: np.ndarray, gate: float, k: int) -> tuple[np.ndarray, ...]:
        """Pairs (image object, map object, squared distance) within ``gate`` metres, up to ``k`` per object."""
        if self.tree is None or not w.size:
            empty = np.zeros(0, np.int64)
            return empty, empty, np.zeros(0)
        k = max(1, min(k, len(self)))
        d, i = self.tree.query(w, img_label, k, self._bound(gate))
        rows, cols = np.nonzero(np.isfinite(d))
        return rows, i[rows, cols], d[rows, cols] ** 2
