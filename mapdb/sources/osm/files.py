"""OSM input files: their names, the early checks, and bounded inflation of compressed XML.

Compressed XML is inflated under a bound (:func:`inflation_limit`), so a decompression bomb costs at
most that much time, memory and temporary disk before a one-line error; coordinates libosmium cannot
parse are made out of range on the way, so that such a node is skipped and counted, not fatal.
"""

from __future__ import annotations

import bz2
import gzip
import os
import re
import tempfile
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ...errors import MapdbIOError, SourceError, reading

__all__ = ["MAX_INFLATION", "MIN_INFLATED_BYTES", "OSM_SUFFIXES", "inflation_limit", "is_osm_path"]

OSM_SUFFIXES = (".osm.pbf", ".pbf", ".osm", ".osm.bz2", ".osm.gz")
_XML_SUFFIXES = (".osm", ".osm.bz2", ".osm.gz")

# A compressed XML file may inflate to MAX_INFLATION times its size, and in any case to
# MIN_INFLATED_BYTES: real OSM XML compresses 10-30 times, so only a decompression bomb goes past.
MAX_INFLATION = 100
MIN_INFLATED_BYTES = 256 << 20
_CHUNK = 1 << 20


def is_osm_path(path: str | Path) -> bool:
    """Whether a file name has one of the OSM suffixes in :data:`OSM_SUFFIXES`.

    Examples
    --------
    >>> is_osm_path("monaco.osm.pbf"), is_osm_path("Area.OSM"), is_osm_path("map.tif")
    (True, True, False)
    """
    return str(path).lower().endswith(OSM_SUFFIXES)


def inflation_limit(compressed_bytes: int) -> int:
    """Most bytes a compressed OSM XML file of this size may inflate to (see :data:`MAX_INFLATION`).

    Examples
    --------
    >>> inflation_limit(10 << 20) == 1000 << 20, inflation_limit(1000) == MIN_INFLATED_BYTES
    (True, True)
    """
    return max(MIN_INFLATED_BYTES, MAX_INFLATION * int(compressed_bytes))

def _check_readable(path: Path) -> None:
    """Fail early with a clear message: osmium's own errors for these cases are less helpful."""
    with reading(path, "file"), path.open("rb") as f:
        first = f.read(1)
    if not first:
        raise SourceError(f"{path}: not a readable OSM file (empty file)")
    if not is_osm_path(path):
        raise SourceError(f"{path}: not a readable OSM file (name must end in {', '.join(OSM_SUFFIXES)})")


# Coordinates written plainly enough for libosmium, up to 180 degrees (it rejects signs, spaces, hex and
# some big numbers, and reads "1e400" as 0).  Any other value goes through _fix_coordinate.
_PLAIN = rb"-?(?:[0-9]{1,2}|1[0-7][0-9]|180)(?:\.[0-9]*)?"
# (A pattern that starts with a literal runs several times faster in ``re`` than one that starts with \s.)
_ODD_COORDINATE = re.compile(rb"(?:lat|lon)\s*=\s*([\"'])(?!" + _PLAIN + rb"\1)([^\"'<&]*)\1")
# Out of range but within what libosmium parses: the node gets a defined, invalid location.
_OUT_OF_RANGE = b"200"


def _fix_coordinate(match: re.Match[bytes]) -> bytes:
    start = match.start()
    if start == 0 or match.string[start - 1:start] not in b" \t\r\n":  # "minlat=", not an attribute "lat"
        return match.group(0)
    try:
        value = float(match.group(2))
    except ValueError:
        value = float("nan")
    text = f"{value:.7f}".encode() if abs(value) <= 180.0 else _OUT_OF_RANGE  # NaN compares False
    quote = match.group(1)
    return match.group(0)[:match.start(1) - start] + quote + text + quote


@contextmanager
def _xml_input(path: Path) -> Iterator[str]:
    """The name of an XML file libosmium can read in full: ``path`` itself, or a bounded, fixed copy.

    A compressed file is inflated into a temporary file, chunk by chunk, and refused (one-line
    :class:`SourceError`) once it passes :func:`inflation_limit`: memory holds one chunk and disk
    at most the limit.  libosmium reads the copy twice (relations first).  Coordinates libosmium cannot
    parse (``nan``, ``inf``, ``1e400``, text) are made out of range on the way, so that such a node is skipped
    and counted like a node at latitude 95 instead of failing the whole file (and libosmium would read
    ``1e400`` as 0); a plain file is copied only when it has such a coordinate.
    """
    name = path.name.lower()
    opener: Callable[..., Any] = gzip.open if name.endswith(".gz") else bz2.open if name.endswith(".bz2") else open
    if opener is open and not _has_odd_coordinate(path):
        yield str(path)
        return
    limit = inflation_limit(path.stat().st_size) if opener is not open else None
    with tempfile.TemporaryDirectory(prefix="mapdb-osm-") as tmp:
        copy = os.path.join(tmp, "input.osm")
        total = 0
        carry = b""
        try:
            with opener(path, "rb") as f, open(copy, "wb") as out:
                while chunk := f.read(_CHUNK):
                    total += len(chunk)
                    if limit is not None and total > limit:
                        raise SourceError(
                            f"{path}: inflates to more than {limit:,} bytes ({MAX_INFLATION} times its size, "
                            f"at least {MIN_INFLATED_BYTES >> 20} MiB): refused as a decompression bomb")
                    data = carry + chunk
                    # An attribute value never holds "<": cut there, so no coordinate is split in two.
                    cut = data.rfind(b"<")
                    if cut <= 0 or len(data) - cut > _CHUNK:
                        cut = len(data)
                    carry = data[cut:]
                    out.write(_ODD_COORDINATE.sub(_fix_coordinate, data[:cut]))
                out.write(_ODD_COORDINATE.sub(_fix_coordinate, carry))
        except (EOFError, zlib.error, gzip.BadGzipFile) as exc:  # a corrupt .gz / .bz2 file
            detail = " ".join(str(exc).split()) or exc.__class__.__name__
            raise SourceError(f"{path}: not a readable OSM file ({detail})") from None
        except OSError as exc:
            if exc.filename == copy:
                raise MapdbIOError(f"{path}: cannot write its inflated copy in {tmp} ({exc.strerror or exc})") from None
            detail = " ".join(str(exc).split()) or exc.__class__.__name__  # bz2 reports bad data as OSError
            raise SourceError(f"{path}: not a readable OSM file ({detail})") from None
        yield copy


def _has_odd_coordinate(path: Path) -> bool:
    """Whether a plain XML file holds a coordinate :func:`_fix_coordinate` would change."""
    carry = b""
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            data = carry + chunk
            if _ODD_COORDINATE.search(data):
                return True
            carry = data[-256:]  # an attribute split between two chunks is seen whole in the next
    return False
