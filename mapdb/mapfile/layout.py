"""The map file's layout: its fixed fields (magic, version, prefix, page directory record) and the format's bounds.

A map is one file (format described in ``docs/format.md``)::

    magic "\\x89MAPDB\\r\\n" | u16 version | u16 flags | u32 header length | header (JSON)
    | u32 CRC-32 of everything before it | page directory (36 bytes a page) | pages

(the header is deflated JSON)

Objects are split into pages of at most ``page_capacity`` objects by recursive
median cuts, so every page covers a compact area.  Inside a page, positions are
integers at the quantum relative to the page origin; each label's objects form
one run, sorted by their row-major key ``qy * (extent_x + 1) + qx`` and stored
as Rice-coded key gaps (close to the entropy of a random point set, so labels
cost nothing beyond their run headers).  Areas are log-quantized codes, stored
as Rice-coded residuals from their run's median.  The header, the directory and each page carry a CRC-32; pages are
read and checked only when a query needs them.

Reading a file never executes anything from it (JSON and fixed binary records
only), and every length and count read from it is checked against the file
size and the format's bounds before memory is allocated for it.  The header's
meaning is checked too, not only its checksum (types, ranges, nesting, the CRS,
counts against the bytes that must hold them), and the format's layout rules
(one object per label and position, pages that share no position and are not
denser than one object a square metre beyond a pile of 255) bound what a file
of a given size can make a reader do: see "Guarantees against a hostile file"
in ``docs/format.md``.

The bounds here are shared by the writer (:mod:`~mapdb.mapfile.writer`), which never writes a map beyond them,
and the reader (:mod:`~mapdb.mapfile.reader`), which refuses one.
"""

from __future__ import annotations

import struct

import numpy as np

__all__ = [
    "DEFAULT_ELEVATION_CELL_M",
    "DEFAULT_ELEVATION_STEP",
    "DEFAULT_QUANTUM",
    "FLAT_FORMAT_VERSION",
    "FORMAT_VERSION",
    "MAGIC",
]

MAGIC = b"\x89MAPDB\r\n"
# The newest version (2: objects with their ground elevation); a map without elevation is written as version 1,
# byte for byte as before version 2 existed.
FORMAT_VERSION = 2
FLAT_FORMAT_VERSION = 1
# Version 2: elevation codes of this many metres, relative to bases per cell of this side (metres; rounded to
# whole quanta): see docs/format.md, "Elevation".
DEFAULT_ELEVATION_STEP = 1.0
DEFAULT_ELEVATION_CELL_M = 128.0
# Stored resolution of coordinates (metres) unless a map is built with another.
DEFAULT_QUANTUM = 0.1
# A version number above this is not a newer format but a damaged or foreign file.
_MAX_VERSION = 255
_PREFIX = struct.Struct("<8sHHI")
# origin x, y (quanta), extent x, y, count, byte length, crc32: the 36-byte directory record, as numpy reads it
_DIR_DTYPE = np.dtype([("ox", "<i8"), ("oy", "<i8"), ("ex", "<u4"), ("ey", "<u4"), ("count", "<u4"),
                       ("length", "<u4"), ("crc", "<u4")])
_MAX_LABELS = 255
_MAX_PAGE_OBJECTS = 65535
_MAX_PAGE_BYTES = 1 << 20  # a page of 65535 objects needs at most ~570 KB however its values are spread
_MAX_EXTENT = (1 << 24) - 1  # keeps the row-major key under 2**48
_MAX_QUANTA = 1 << 52  # positions in quanta stay exact in float64 (page boxes, bounds)
# Density: a page may hold _PILE objects whatever its area (one object of each label at one position is the
# densest thing a genuine map holds); beyond that, at most one object per _M2_PER_OBJECT of its box.
_PILE = 255
_M2_PER_OBJECT = 1.0
# The fewest bits a page of c objects can take: the run count byte, one run head (8 + 16 + 1 + 16 bits), a
# Rice parameter (6 bits), and per object at least 3 bits (a key gap >= 1 costs 2 bits, an area residual 1).
_MIN_PAGE_BITS = 53
_MIN_OBJECT_BITS = 3
