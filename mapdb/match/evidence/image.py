"""What an image's objects know of their own errors: set up once per image, handed to every stage that weighs
evidence, and the one interface through which the stages call the evidence models.

The stages ask two questions of the evidence: the decision (:func:`mapdb.match.verify.decision_nfa`) asks
how far each image object lies from a map object it could be (:meth:`ImageEvidence.residuals`), and the final
fit (:func:`mapdb.match.refine.polish`) asks for the similarity and its error from the pairs it settled on
(:meth:`ImageEvidence.fit`, :meth:`ImageEvidence.error`).

Ideal centroids (points) carry nothing but their position: the point residuals of
:mod:`~mapdb.match.evidence.points` are all the evidence there is.  Objects extracted from masks bring more,
and each extra model reads its part of :class:`ImageEvidence`:

* ``areas`` (:mod:`~mapdb.match.evidence.areas`): the decision asks each object's map object for a compatible
  stored area;
* ``errors`` (:mod:`~mapdb.match.evidence.blobs`): blobs cut by the image border are looked for along their
  border's normal, in the hypotheses of the cut rounds, the decision and the final fit;
* ``whole`` and ``anchors``: which blobs are whole (the cut rounds' quads), and which may build the first
  rounds' quads and the final fit (:mod:`~mapdb.match.evidence.relief`);
* ``jackknife``: the final fit's error is the larger of its model's and the jackknife's (blobs' errors are
  not alike);
* ``terrain`` (:mod:`~mapdb.match.evidence.terrain`): a map with elevation and an image with its field of view:
  the decision's predictions and the final fit cast each ray onto the objects' heights.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .areas import ImageAreas, bands, compatible, disc_chances, sample_evidence, solid_objects
from .blobs import BlobErrors, cut_area_residuals, placed_sources
from .relief import ReliefFit, fit_with_relief, leave_one_out_sigma
from .terrain import TerrainModel

if TYPE_CHECKING:
    from ..mapobjects.object_index import Neighbours, ObjectIndex

__all__ = ["ImageEvidence"]


@dataclass(frozen=True)
class ImageEvidence:
    """An image's evidence models beyond its objects' positions (all None / False for ideal centroids).

    Attributes
    ----------
    areas : ImageAreas or None
        The objects' pixel areas, for the decision's area evidence.
    errors : BlobErrors or None
        The objects' error ellipses (blobs cut by the border), for lookups, the decision and the final fit.
    whole : bool array (n,) or None
        Objects not cut by the image border, as given (None: unknown, all whole).
    anchors : bool array (n,) or None
        Objects that may build the first rounds' quads and the final fit: ``whole`` when at least four are,
        else None (all).
    jackknife : bool
        The final fit's error includes the jackknife's (objects extracted from masks).
    terrain : TerrainModel or None
        Rays cast onto the map objects' heights (a map with elevation, an image with its field of view).
    """

    areas: ImageAreas | None = None
    errors: BlobErrors | None = None
    whole: np.ndarray | None = None
    anchors: np.ndarray | None = None
    jackknife: bool = False
    terrain: TerrainModel | None = None

    def project(self, a: np.ndarray, b: np.ndarray, z: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
        """Where hypotheses ``z -> a z + b`` (``(H,)``) put the image objects: ``(H, n)``; over terrain each ray
        cast onto the ground (:meth:`~mapdb.match.evidence.terrain.TerrainModel.project`, ``ref`` the map points
        each hypothesis was fitted to)."""
        if self.terrain is None:
            return a[:, None] * z[None, :] + b[:, None]
        return self.terrain.project(a, b, z, ref)

    @classmethod
    def of(cls, z: np.ndarray, img_label: np.ndarray, labels: tuple[str, ...], anchorable: np.ndarray | None = None,
           area_px: np.ndarray | None = None, outward: np.ndarray | None = None) -> ImageEvidence:
        """The evidence of image objects ``z`` (labels ``img_label``, codes into ``labels``) from what the image
        document gives: ``anchorable`` (whole), ``area_px`` and ``outward`` (see
        :func:`mapdb.match.fast.match_fast`).

        Examples
        --------
        >>> ev = ImageEvidence.of(np.zeros(3, complex), np.zeros(3, np.int64), ("building",))
        >>> ev.areas is None and ev.errors is None and not ev.jackknife
        True
        """
        areas = ImageAreas.of(area_px, anchorable, img_label, labels)
        solid_px = None if area_px is None else np.where(solid_objects(img_label, labels), area_px, np.nan)
        errors = BlobErrors.of(z, outward, solid_px)
        anchors = None if anchorable is not None and anchorable.sum() < 4 else anchorable
        return cls(areas, errors, anchorable, anchors, errors is not None or areas is not None)

    def residuals(self, w: np.ndarray, a: np.ndarray, b: np.ndarray, img_ids: np.ndarray, map_z: np.ndarray,
                  z: np.ndarray, img_label: np.ndarray, index: ObjectIndex, density: np.ndarray,
                  area_radius: np.ndarray | None = None, near: Neighbours | None = None
                  ) -> tuple[np.ndarray, np.ndarray | float, np.ndarray]:
        """The decision's evidence under hypotheses ``z -> a z + b`` (``w``: the objects so projected, ``(H, n)``)
        built from the quads ``img_ids``, ``map_z`` (``(H, 4)``).

        Returns the squared residual ``(H, n)`` of each object to its map object, the hypothesis's own map
        points excluded (point residuals; with ``errors``, measured in each blob's error ellipse), the share of
        its label's map objects it could be (with ``areas`` and ``area_radius``, the density disc's radius per
        hypothesis: those of a compatible area; else 1), and a log10 factor ``(H,)`` from the areas of each
        quad's own objects (else 0).  ``near``: the neighbours of ``w`` (:meth:`~mapdb.match.mapobjects.object_index.
        ObjectIndex.neighbours`), read instead of a query where the residuals are measured from ``w`` itself.
        """
        errors, areas = self.errors, self.areas
        expected = w if errors is None else errors.expected(a, b, z)
        share: np.ndarray | float = 1.0  # of the map objects compatible with each object's area
        from_sample = np.zeros(len(a))  # log10 factor from the areas of each quad's own objects
        if areas is not None and area_radius is not None:
            lo, hi = bands(areas, a)
            dist, mid = index.nearest_compatible(expected, img_label, density, map_z, lo, hi)
            share = disc_chances(index.log_area, index.disc_members(b, area_radius, img_label), img_label, lo, hi)
            rows = np.arange(len(a))[:, None]
            at = index.at(map_z, img_label[img_ids])
            fits = compatible(np.where(at >= 0, index.log_area[np.maximum(at, 0)], np.nan), lo[rows, img_ids],
                              hi[rows, img_ids])
            from_sample = sample_evidence(fits, share[rows, img_ids])
        else:
            # ``near`` holds the neighbours of ``w``: of use only where the residuals are measured from it.
            dist, mid = index.nearest(expected, img_label, density, exclude=map_z,
                                      near=near if errors is None else None)
        if errors is None:
            return dist**2, share, from_sample
        r2 = np.where(mid >= 0, errors.r2(a, b, z, index.z[np.maximum(mid, 0)]), np.inf)
        if errors.visible_px is not None and areas is not None and area_radius is not None:
            # Cut solid blobs: each map object measured from where a blob of its own area would put it.
            cut = np.flatnonzero(np.isfinite(errors.visible_px))
            r2[:, cut] = cut_area_residuals(errors, a, b, z, cut, index, img_label, map_z, lo, hi)[0]
        return r2, share, from_sample

    def fitted(self, pairs: np.ndarray) -> np.ndarray:
        """The pairs (image id, map id) the final fit uses: those of ``anchors`` when at least four are, else all."""
        whole = self.anchors
        if whole is not None and np.count_nonzero(whole[pairs[:, 0]]) >= 4:
            return pairs[whole[pairs[:, 0]]]
        return pairs

    def sources(self, z: np.ndarray, index: ObjectIndex, pairs: np.ndarray, scale: float) -> np.ndarray:
        """The image positions the fit takes the ``pairs`` from: blobs placed by their errors when known
        (:func:`~mapdb.match.evidence.blobs.placed_sources`, cut buildings by their map objects' areas at
        ``scale`` metres per pixel), else the objects' own."""
        return z[pairs[:, 0]] if self.errors is None else placed_sources(self.errors, z, pairs, index, scale)

    def fit(self, z: np.ndarray, index: ObjectIndex, pairs: np.ndarray, scale: float = 1.0,
            nadir: complex = 0j) -> ReliefFit | None:
        """The similarity fitted to ``pairs`` (:meth:`fitted` of them), relief weighed radially
        (:func:`~mapdb.match.evidence.relief.fit_with_relief`), or None when they cannot fix one.  Over terrain
        the image points are first rescaled for their map objects' heights around ``nadir``
        (:meth:`~mapdb.match.evidence.terrain.TerrainModel.fit_sources`)."""
        pairs = self.fitted(pairs)
        if len(pairs) < 3:
            return None
        src, dst = self.sources(z, index, pairs, scale), index.z[pairs[:, 1]]
        if self.terrain is not None and index.elevation is not None:
            src = self.terrain.fit_sources(src, dst, nadir, scale, index.elevation[pairs[:, 1]])[0]
        return fit_with_relief(src, dst)

    def error(self, z: np.ndarray, index: ObjectIndex, pairs: np.ndarray, fit: ReliefFit,
              scale: float) -> tuple[float, float]:
        """The final fit's per-axis sigma and variance factor: its model's (over ``terrain`` with the variance
        the search of the camera's height adds, :meth:`~mapdb.match.evidence.terrain.TerrainModel.fit_sources`),
        or with ``jackknife`` the variance factor raised to the jackknife's
        (:func:`~mapdb.match.evidence.relief.leave_one_out_sigma`) when larger."""
        sigma_axis, variance = fit.sigma_axis, fit.variance_factor
        if not self.jackknife and self.terrain is None:
            return sigma_axis, variance
        used = self.fitted(pairs)
        sigma_axis = max(sigma_axis, 1e-12)  # an exact fit (no residual) must not hide an infinite jackknife
        src, dst = self.sources(z, index, used, scale), index.z[used[:, 1]]
        depth_variance = 0.0
        if self.terrain is not None and index.elevation is not None:
            # Over terrain the fit also chose the camera's height: its uncertainty moves the position (most
            # where the objects lie to one side of the nadir).
            src, depth_variance = self.terrain.fit_sources(src, dst, fit.b, scale, index.elevation[used[:, 1]])
            variance += depth_variance / sigma_axis**2
            if not self.jackknife:
                return sigma_axis, variance
        return sigma_axis, max(variance, (leave_one_out_sigma(src, dst, fit) / sigma_axis) ** 2)
