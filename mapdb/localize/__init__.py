"""Localization of one image document: parse it, pick the map region, run a matcher, format the answer.

:class:`Localizer` holds an open map and its indexes for many images; :func:`localize` answers one.

* :mod:`~mapdb.localize.localizer` - the :class:`Localizer` (the map's indexes and caches) and :func:`localize`;
* :mod:`~mapdb.localize.batch` - :func:`localize_documents`: a batch of documents in input order;
* :mod:`~mapdb.localize.priors` - the prior that applies, how far around it to read, whether it meets the map;
* :mod:`~mapdb.localize.image_points` - the image's objects the map knows, as points of the image plane;
* :mod:`~mapdb.localize.records` - the answer, accepted or rejected (its fields are documented there);
* :mod:`~mapdb.localize.lonlat` - map coordinates to lon/lat and back.
"""

from __future__ import annotations

from .batch import localize_documents
from .image_points import SCALE_TOLERANCE
from .localizer import METHODS, Localizer, localize, localizer_for
from .priors import prior_margin

__all__ = [
    "Localizer",
    "METHODS",
    "SCALE_TOLERANCE",
    "localize",
    "localize_documents",
    "localizer_for",
    "prior_margin",
]
