"""Localization of one image document: parse it, pick the map region, run a matcher, format the answer.

:class:`Localizer` holds an open map and its indexes for many images; :func:`localize` answers one.
"""

from __future__ import annotations

from .localizer import (
    METHODS,
    SCALE_TOLERANCE,
    Localizer,
    localize,
    localize_documents,
    localizer_for,
    prior_margin,
)

__all__ = [
    "Localizer",
    "METHODS",
    "SCALE_TOLERANCE",
    "localize",
    "localize_documents",
    "localizer_for",
    "prior_margin",
]
