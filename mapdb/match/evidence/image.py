"""What an image's objects know of their own errors: set up once per image, handed to every stage that weighs
evidence.

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
  not alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .areas import ImageAreas, solid_objects
from .blobs import BlobErrors

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
    """

    areas: ImageAreas | None = None
    errors: BlobErrors | None = None
    whole: np.ndarray | None = None
    anchors: np.ndarray | None = None
    jackknife: bool = False

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
