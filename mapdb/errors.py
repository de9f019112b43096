"""Exceptions raised by mapdb.

One root, :class:`MapdbError`; each subclass also inherits the builtin that
matches its kind, so callers can catch either (``except OSError`` still sees a
missing file).  Every message is meant to stand alone on one line and name the
file it is about: the CLI prints ``str(exc)`` and nothing else.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

__all__ = [
    "AnalysisError",
    "DaskMissingError",
    "EmptyMapError",
    "ImageInputError",
    "LabelTableError",
    "MapFormatError",
    "MapVersionError",
    "MapdbError",
    "MapdbIOError",
    "OutputClashError",
    "OutputExistsError",
    "SchedulerError",
    "SourceError",
    "open_regular",
    "reading",
]


class MapdbError(Exception):
    """Root of all errors raised on purpose by mapdb."""


class MapdbIOError(MapdbError, OSError):
    """A file could not be read or written (missing, empty, unreadable)."""


class OutputClashError(MapdbError, ValueError):
    """An output path is one of the command's inputs (or another of its outputs); writing would destroy it."""


class OutputExistsError(MapdbError, FileExistsError):
    """An output file exists and the command was not told it may replace it (``--overwrite``)."""


class SourceError(MapdbError, ValueError):
    """A source file (OSM, raster, layer) is not what its name says, or lacks what a build needs."""


class LabelTableError(MapdbError, ValueError):
    """A label mapping file is malformed or names a label that is not declared."""


class MapFormatError(MapdbError, ValueError):
    """A map file is truncated, corrupted (checksum mismatch) or not a mapdb map at all."""


class MapVersionError(MapFormatError):
    """A map file was written by a newer format version than this reader supports."""


class AnalysisError(MapdbError, ValueError):
    """A region analysis cannot run as asked (a grid too fine, a bad box, a bad scenario)."""


class DaskMissingError(MapdbError, ImportError):
    """``--jobs`` or ``--scheduler`` was asked for and dask.distributed is not installed."""


class SchedulerError(MapdbIOError):
    """The Dask scheduler asked for cannot be reached (or its address cannot be read)."""


class EmptyMapError(MapdbError, ValueError):
    """A build or export selected no objects (for example a bbox over empty ground)."""


class ImageInputError(MapdbError, ValueError):
    """An image-objects document (query input) is malformed."""


@contextmanager
def reading(path: str | Path, what: str = "file") -> Iterator[None]:
    """Turn the OS errors of opening or reading ``path`` into one-line :class:`MapdbIOError` errors.

    Examples
    --------
    >>> with reading("/no/such/place.osm", "OSM file"):
    ...     open("/no/such/place.osm").close()
    Traceback (most recent call last):
    mapdb.errors.MapdbIOError: /no/such/place.osm: no such OSM file
    """
    try:
        yield
    except FileNotFoundError:
        raise MapdbIOError(f"{path}: no such {what}") from None
    except IsADirectoryError:
        raise MapdbIOError(f"{path}: is a directory, not a {what}") from None
    except OSError as exc:
        if isinstance(exc, MapdbError):
            raise
        raise MapdbIOError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None


def open_regular(path: str | Path, where: str | Path, what: str) -> IO[bytes]:
    """``path`` opened for reading if it is a regular file, else a one-line :class:`MapdbIOError`.

    Opened without blocking and checked with fstat (not stat then open, which a swap could defeat): a FIFO
    given as a map, an index or a mask would hang the command, a device would feed it endless bytes.

    Examples
    --------
    >>> open_regular("/dev/null", "/dev/null", "map file")
    Traceback (most recent call last):
    mapdb.errors.MapdbIOError: /dev/null: is a device, not a map file
    """
    with reading(where, what):
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                    else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a special file")
            raise MapdbIOError(f"{where}: is {kind}, not a {what}")
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
