"""mapdb: GNSS-free aerial localization by matching labelled ground objects against a meta-map."""

from __future__ import annotations

__version__ = "0.1.0"

from .errors import (  # noqa: E402
    EmptyMapError,
    ImageInputError,
    LabelTableError,
    MapdbError,
    MapdbIOError,
    MapFormatError,
    MapVersionError,
    SourceError,
)
from .objects import Objects, concat  # noqa: E402

__all__ = [
    "EmptyMapError",
    "ImageInputError",
    "LabelTableError",
    "MapFormatError",
    "MapVersionError",
    "MapdbError",
    "MapdbIOError",
    "Objects",
    "SourceError",
    "__version__",
    "concat",
]
