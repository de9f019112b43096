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


def __getattr__(name: str):
    # Objects imports numpy: loaded on first use, so that ``import mapdb`` (and ``mapdb --help``) stays light.
    if name in ("Objects", "concat"):
        from . import objects

        return getattr(objects, name)
    raise AttributeError(f"module 'mapdb' has no attribute {name!r}")


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
