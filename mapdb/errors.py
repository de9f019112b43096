"""Exceptions raised by mapdb.

One root, :class:`MapdbError`; each subclass also inherits the builtin that
matches its kind, so callers can catch either (``except OSError`` still sees a
missing file).  Every message is meant to stand alone on one line and name the
file it is about: the CLI prints ``str(exc)`` and nothing else.
"""

from __future__ import annotations

__all__ = [
    "EmptyMapError",
    "ImageInputError",
    "LabelTableError",
    "MapFormatError",
    "MapVersionError",
    "MapdbError",
    "MapdbIOError",
    "SourceError",
]


class MapdbError(Exception):
    """Root of all errors raised on purpose by mapdb."""


class MapdbIOError(MapdbError, OSError):
    """A file could not be read or written (missing, empty, unreadable)."""


class SourceError(MapdbError, ValueError):
    """A source file (OSM, raster, layer) is not what its name says, or lacks what a build needs."""


class LabelTableError(MapdbError, ValueError):
    """A label mapping file is malformed or names a label that is not declared."""


class MapFormatError(MapdbError, ValueError):
    """A map file is truncated, corrupted (checksum mismatch) or not a mapdb map at all."""


class MapVersionError(MapFormatError):
    """A map file was written by a newer format version than this reader supports."""


class EmptyMapError(MapdbError, ValueError):
    """A build or export selected no objects (for example a bbox over empty ground)."""


class ImageInputError(MapdbError, ValueError):
    """An image-objects document (query input) is malformed."""
