"""The quad index file's layout (``docs/index_format.md``): constants, cell keys, the prefix and header, sections.

Shared by the writer (:mod:`~mapdb.match.index.build`) and the reader (:mod:`~mapdb.match.index.stored`), so
that both follow one definition of the format: what the prefix holds, how a quad's invariants become a cell
key and a position inside its cell, which sections there are with which dtypes and shapes, and how they are
checksummed in blocks.  Nothing here is executed from a file: a header is JSON, sections are fixed-size
little-endian arrays, and every count and extent is checked before a section is mapped.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np

from ... import __version__
from ...errors import MapdbIOError, MapFormatError, MapVersionError
from .packed import NB_BLOCK, PAD, PAGE_CELLS, record_layout

__all__ = [
    "BLOCK",
    "BLOCK_BITS",
    "BLOCKS_LEFT_OUT",
    "CELL_LADDER",
    "Counts",
    "FORMAT_NAME",
    "INDEX_MAGIC",
    "INDEX_SUFFIX",
    "INDEX_VERSION",
    "MAX_NEIGHBOURS",
    "PREFIX_SIZE",
    "SECTIONS",
    "SectionPlan",
    "QUAD_NEIGHBOURS",
    "QUAD_TRIPLES",
    "MAX_QUANTA",
    "cell_keys",
    "cells_of",
    "check_sections",
    "header_blocks",
    "header_combos",
    "header_counts",
    "index_path",
    "key_layout",
    "pread",
    "pwrite_all",
    "read_header",
    "section_shapes",
    "triples",
    "whole",
    "write_header",
]

FORMAT_NAME = "mapdb-quad-index"
INDEX_MAGIC = b"\x89MAPDBQX"
INDEX_VERSION = 4  # 4: packed coordinates, quads of the 5 nearest; 3: compact; 2: bound to its map; 1: neither
INDEX_SUFFIX = ".qidx"
# The header's ``blocks`` value for a map with blocks of buildings indexed without them (the quads of the world
# point images are matched in); the key is absent for a map without blocks.
BLOCKS_LEFT_OUT = "left out"
# magic | u16 version | u16 flags | u64 header offset | u32 header length | u32 header CRC-32 | u32 CRC-32 of
# the 28 bytes before it.  The JSON header is written last, at the end of the file, since it holds the
# section sizes and checksums.
_PREFIX = struct.Struct("<8sHHQII")
PREFIX_SIZE = _PREFIX.size + 4
_MAX_HEADER = 16 << 20
MAX_QUANTA = 1 << 52  # a map's positions in quanta stay within this (mapdb.mapfile.layout): so must an origin
ALIGN = 64  # sections start at multiples of 64 bytes (a page each would cost 5 bytes an object on Andorra)
BLOCK_BITS = 12
BLOCK = 1 << BLOCK_BITS  # checksum block of every section: a page, what a lookup's first read of it costs
QUAD_NEIGHBOURS = 5  # quads are each object with QUAD_TRIPLES of its 5 nearest (a subset of the K-neighbour quads)
# The triples of an object's nearest neighbours (0 the nearest) its quads are made of: every triple of the 4
# nearest, and the 5th with the two nearest and with the nearest and the 3rd (measured on Andorra's images: 42 %
# of their quads indexed against 31 % for the 4 nearest alone, 4.1 quads an object against 2.9).
QUAD_TRIPLES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3), (0, 1, 4), (0, 2, 4))
CELL_LADDER = 0.5 * 2.0 ** (-np.arange(12) / 2.0)  # 0.5 .. 0.011: cell sides tried per label combination
MAX_NEIGHBOURS = 12  # C(12, 3) = 220 triples fit in one byte
SECTIONS: dict[str, str] = {  # name: dtype, in the order of the checksum table (docs/index_format.md)
    "co_start": "<u8",  # first byte of each block of NB_BLOCK objects' coordinates in co_data
    "co_width": "u1",  # bit widths of each block's x and y offsets
    "co_base": "<i4",  # each block's smallest x and y (quanta relative to the origin)
    "co_data": "u1",  # coordinates, bit-packed (packed.pack_coords)
    "nb_start": "<u8",  # first byte of each block of NB_BLOCK objects' neighbours in nb_data
    "nb_width": "u1",  # bit width of each block's neighbour differences
    "nb_data": "u1",  # neighbours, bit-packed (packed.pack_neighbours)
    "quads": "u1",  # one record of record_bytes a quad, in key order (packed.pack_records)
    "dir_data": "u1",  # directory pages, bit-packed (packed.pack_pages)
    "fence": "<u8",  # a row a directory page: first cell's key, first cell, first quad, first byte; read at open
}


def index_path(map_path: str | os.PathLike[str]) -> Path:
    """The sidecar index of a map file: ``MAP`` + ``.qidx`` (``andorra.mapdb`` -> ``andorra.mapdb.qidx``)."""
    return Path(os.fspath(map_path) + INDEX_SUFFIX)


# ------------------------------------------------------------------------------------------ cell keys


def triples(k: int) -> np.ndarray:
    """The triples ``(i, j, k)`` of an object's ``k`` nearest neighbours its quads are made of, ``(t, 3)``, numbered
    as records number them: those of :data:`QUAD_TRIPLES` within ``range(k)`` (3: one; 4: all four; 5: six)."""
    return np.array([t for t in QUAD_TRIPLES if max(t) < k], dtype=np.int64).reshape(-1, 3)


def key_layout(n_labels: int) -> tuple[int, int]:
    """Bits of the label combination and of each invariant's cell in a 64-bit key."""
    label_bits = max(1, (max(n_labels, 1) ** 4 - 1).bit_length())
    return label_bits, (64 - label_bits) // 4


def cells_of(inv: np.ndarray, cell: np.ndarray, sub_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Cell coordinates (int64) and position inside the cell (uint8, in 1/``sub_cells``) of invariants ``(m, 4)``.

    Invariants lie in [-1, 1] (``A``, ``B`` are the most distant pair), so ``t + 1`` is >= 0 and cells
    count from 0; the ladder's smallest cell keeps the largest coordinate far below ``2 ** bits``.
    """
    s = (inv + 1.0) / cell[:, None]
    k = np.floor(s)
    sub = np.clip(np.floor((s - k) * sub_cells), 0, sub_cells - 1).astype(np.uint8)
    return np.maximum(k, 0).astype(np.int64), sub


def cell_keys(label_key: np.ndarray, cells: np.ndarray, bits: int) -> np.ndarray:
    """The 64-bit keys (uint64) of cells ``(m, 4)`` of label combinations ``label_key``."""
    key = label_key.astype(np.uint64)
    for j in range(4):
        key = (key << np.uint64(bits)) | cells[:, j].astype(np.uint64)
    return key


# ------------------------------------------------------------------------------- prefix and header


def write_header(fd: int, header: dict[str, Any], offset: int) -> None:
    """Write the JSON header at ``offset``, the file's end, then the prefix that points at it."""
    header_bytes = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    pwrite_all(fd, header_bytes, offset)
    prefix = _PREFIX.pack(INDEX_MAGIC, INDEX_VERSION, 0, offset, len(header_bytes), zlib.crc32(header_bytes))
    pwrite_all(fd, prefix + struct.pack("<I", zlib.crc32(prefix)), 0)
    os.ftruncate(fd, offset + len(header_bytes))


def read_header(f: IO[bytes], size: int, where: str) -> dict[str, Any]:
    """The checked JSON header of an open index file of ``size`` bytes (its offset as ``_header_offset``)."""
    head = f.read(PREFIX_SIZE)
    if len(head) < 8 or not head.startswith(INDEX_MAGIC):
        raise MapFormatError(f"{where}: not a mapdb quad index (bad magic number)")
    if len(head) < PREFIX_SIZE:
        raise MapFormatError(f"{where}: truncated quad index")
    _, version, _flags, h_off, h_len, h_crc = _PREFIX.unpack_from(head)
    if zlib.crc32(head[: _PREFIX.size]) != struct.unpack_from("<I", head, _PREFIX.size)[0]:
        raise MapFormatError(f"{where}: quad index prefix checksum mismatch (file is corrupt)")
    if version > INDEX_VERSION:
        raise MapVersionError(f"{where}: written by a newer quad index format (version {version}); "
                              f"this mapdb {__version__} reads up to version {INDEX_VERSION}")
    if version < INDEX_VERSION:
        why = ("which does not bind the index to its map" if version < 2 else "about ten times larger" if version < 3
               else "fewer quads an object, coordinates unpacked")
        raise MapFormatError(f"{where}: quad index format version {version} ({why}); this mapdb reads version "
                             f"{INDEX_VERSION}: rebuild with mapdb index")
    if h_len > _MAX_HEADER or h_off < PREFIX_SIZE or h_off + h_len != size:
        raise MapFormatError(f"{where}: truncated quad index ({size} bytes; its header says "
                             f"{h_off + h_len})")
    f.seek(h_off)
    raw = f.read(h_len)
    if len(raw) != h_len or zlib.crc32(raw) != h_crc:
        raise MapFormatError(f"{where}: quad index header checksum mismatch (file is corrupt)")
    try:
        header = json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError):  # RecursionError: nesting deeper than the parser's stack
        raise MapFormatError(f"{where}: quad index header is not JSON") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise MapFormatError(f"{where}: not a mapdb quad index (header)")
    if header.get("format_version") != version:
        raise MapFormatError(f"{where}: quad index header says format version "
                             f"{str(header.get('format_version'))[:20]}, its prefix {version}")
    header["_header_offset"] = h_off
    return header


class Counts(NamedTuple):
    """A header's counts and layout, checked (:func:`header_counts`)."""

    objects: int
    neighbours: int  # the matcher's K the quads serve (every quad is one of the K-neighbour quads)
    quad_neighbours: int  # the nearest neighbours the quads are drawn from
    quads: int
    cells: int
    pages: int
    max_cell: int
    origin: tuple[int, ...]
    cell_bits: int
    nb_bytes: int
    co_bytes: int
    dir_bytes: int
    record_bytes: int
    sub_bits: int
    triple_bits: int


def whole(value: Any, where: str, what: str, low: int = 0, high: int = 2**63 - 1) -> int:
    """A header integer within ``[low, high]``: a JSON integer, not a float, a string or a boolean."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise MapFormatError(f"{where}: quad index header field {what} is {str(value)[:40]!r}, not an integer "
                             f"in [{low}, {high}]")
    return value


def header_counts(h: dict[str, Any], n_labels: int, identity: dict[str, Any], where: str) -> Counts:
    """The header's counts, checked against each other, the map's (``identity``) and the format's bounds.

    Every field must be a JSON integer in range (no float, string or boolean read as one); the origin
    within the positions a map can hold, so that no coordinate computed from it overflows; the quantum a
    finite number a map can have; the record and key layouts the ones the counts give.
    """
    n, k, ku, q, d, p, max_cell, nb_bytes, co_bytes, dir_bytes = (
        whole(h[key], where, key) for key in ("objects", "neighbours", "quad_neighbours", "quads", "cells", "pages",
                                              "max_cell", "nb_bytes", "co_bytes", "dir_bytes"))
    origin = identity["origin"]
    if not isinstance(origin, list) or len(origin) != 2:
        raise MapFormatError(f"{where}: quad index header field origin is not two integers")
    origin = tuple(whole(v, where, "origin", -MAX_QUANTA, MAX_QUANTA) for v in origin)
    quantum = identity["quantum"]
    if isinstance(quantum, bool) or not isinstance(quantum, int | float) or not 0 < quantum <= 1000:
        raise MapFormatError(f"{where}: quad index header field quantum is {str(quantum)[:40]!r}, not a number "
                             f"in (0, 1000]")
    label_bits, bits = whole(h["key_label_bits"], where, "key_label_bits"), whole(h["key_cell_bits"], where,
                                                                                 "key_cell_bits")
    n_triples = len(triples(ku)) if 3 <= ku <= QUAD_NEIGHBOURS else 0
    if h["quad_triples"] != triples(ku).tolist():
        raise MapFormatError(f"{where}: quad index header field quad_triples is not the format's")
    rb, sb, tb = record_layout(n, n_triples)
    if ((label_bits, bits) != key_layout(n_labels) or whole(h["block_size"], where, "block_size") != BLOCK
            or (whole(h["record_bytes"], where, "record_bytes"), whole(h["sub_bits"], where, "sub_bits")) != (rb, sb)
            or whole(h["page_cells"], where, "page_cells") != PAGE_CELLS
            or whole(h["nb_block"], where, "nb_block") != NB_BLOCK):
        raise MapFormatError(f"{where}: unsupported key or record layout")
    if not (0 <= n < 2**32 and n == whole(identity["count"], where, "count")
            and (k == ku == 0 or 3 <= ku == min(k, QUAD_NEIGHBOURS) and k <= MAX_NEIGHBOURS)
            and 0 <= q <= n * n_triples and 0 <= d <= q and 0 <= max_cell <= q and d <= p * PAGE_CELLS and p <= d
            and (d > 0) == (q > 0) and (max_cell > 0) == (q > 0) and (nb_bytes > 0) == (ku > 0 and n > 0)
            and (co_bytes == 0 or n > 0)):
        raise MapFormatError(f"{where}: quad index counts out of range (objects {n}, neighbours {k}, "
                             f"quads {q}, cells {d}, pages {p})")
    return Counts(n, k, ku, q, d, p, max_cell, origin, bits, nb_bytes, co_bytes, dir_bytes, rb, sb, tb)


def header_combos(combos: Any, quads: int, n_labels: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """The header's label-combination keys (ascending, int64) and their cell sides (float64), checked."""
    if not isinstance(combos, list) or len(combos) > max(quads, 0):
        raise MapFormatError(f"{where}: quad index label combinations out of range")
    if quads > 0 and not combos:
        raise MapFormatError(f"{where}: quad index lists no label combination for its {quads} quads")
    try:  # one array of pairs (vectorised: a map of many labels has thousands of combinations)
        table = np.array(combos, dtype=np.float64) if combos else np.zeros((0, 2))
    except (TypeError, ValueError):
        raise MapFormatError(f"{where}: quad index label combinations out of range") from None
    if table.shape != (len(combos), 2) or not np.all(table[:, 0] == np.floor(table[:, 0])):
        raise MapFormatError(f"{where}: quad index label combinations out of range")
    # Label keys stay below L^4 (checked below), far below 2^53: exact in float64.
    ck = np.clip(table[:, 0], -1, 2**62).astype(np.int64)
    cc = table[:, 1]
    # A cell side is one of the ladder's, as written (a JSON float reads back bit for bit).
    # (A set, not np.isin: its np.unique imports numpy.ma, 0.05 s of a first answer.)
    if ck.size and not set(cc.tolist()) <= set(CELL_LADDER.tolist()):
        raise MapFormatError(f"{where}: quad index cell sides are not the format's")
    if ck.size and (np.any(np.diff(ck) <= 0) or ck[0] < 0 or ck[-1] >= max(n_labels, 1) ** 4
                    or not np.all((cc >= CELL_LADDER[-1] * 0.999) & (cc <= CELL_LADDER[0] * 1.001))):
        raise MapFormatError(f"{where}: quad index label combinations out of range")
    return ck, cc


# ----------------------------------------------------------------------------------------- sections


def section_shapes(c: Counts) -> dict[str, tuple[tuple[int, ...], str]]:
    """Shape and dtype of every section but ``crc`` for the counts ``c`` (packed sections end in 8 zero bytes)."""
    objects = -(-c.objects // NB_BLOCK)
    blocks = objects if c.quad_neighbours else 0
    shapes: dict[str, tuple[int, ...]] = {
        "co_start": (objects + 1,), "co_width": (objects, 2), "co_base": (objects, 2), "co_data": (c.co_bytes + PAD,),
        "nb_start": (blocks + 1,), "nb_width": (blocks,), "nb_data": (c.nb_bytes + PAD,),
        "quads": (c.quads, c.record_bytes), "dir_data": (c.dir_bytes + PAD,), "fence": (c.pages + 1, 4)}
    return {name: (shape, SECTIONS[name]) for name, shape in shapes.items()}


def check_sections(layout: dict[str, Any], shapes: dict[str, tuple[tuple[int, ...], str]], end: int,
                   where: str) -> int:
    """Check the header's ``sections`` against the counts and the file; return the number of checksum blocks.

    Every section must have the dtype, shape and length the counts give and lie between the prefix and
    the header (``end``) without overlapping another, so that nothing mapped is larger than the file.
    """
    spans = []
    total_blocks = 0
    for name, (shape, dtype) in shapes.items():
        sec = layout[name]
        length = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        if sec["dtype"] != dtype or [int(v) for v in sec["shape"]] != list(shape) or int(sec["length"]) != length:
            raise MapFormatError(f"{where}: quad index section {name} does not match the counts")
        total_blocks += -(-length // BLOCK)
        spans.append((whole(sec["offset"], where, f"{name} offset"), length, name))
    crc_sec = layout["crc"]
    if crc_sec["dtype"] != "<u4" or [int(v) for v in crc_sec["shape"]] != [total_blocks] or \
            int(crc_sec["length"]) != 4 * total_blocks:
        raise MapFormatError(f"{where}: quad index checksum table does not match the sections")
    spans.append((whole(crc_sec["offset"], where, "crc offset"), 4 * total_blocks, "crc"))
    spans.sort()
    at = PREFIX_SIZE
    for off, length, name in spans:
        if off < at or off + length > end:
            raise MapFormatError(f"{where}: truncated or overlapping quad index section {name}")
        at = off + length
    return total_blocks


class SectionPlan:
    """Where a writer puts each section: one after another, each at an ``ALIGN``-byte boundary, from ``ALIGN``
    on; ``sections`` is the header's ``sections``, ``offset`` the end of the last one."""

    def __init__(self) -> None:
        self.sections: dict[str, dict[str, Any]] = {}
        self.offset = -(-PREFIX_SIZE // ALIGN) * ALIGN

    def place(self, name: str, dtype: str, shape: tuple[int, ...]) -> None:
        """Put the next section at ``offset``."""
        length = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        self.sections[name] = {"offset": self.offset, "length": length, "dtype": dtype, "shape": list(shape)}
        self.offset += -(-length // ALIGN) * ALIGN

    def __getitem__(self, name: str) -> dict[str, Any]:
        return self.sections[name]

    def checksums(self, path: str | os.PathLike[str]) -> np.ndarray:
        """The ``crc`` table of the sections written to ``path``: the CRC-32 of every block of every section,
        in ``SECTIONS`` order (each section's ``first_block`` is set)."""
        crcs: list[np.ndarray] = []
        with open(path, "rb") as f:
            for name in SECTIONS:
                sec = self.sections[name]
                sec["first_block"] = sum(len(c) for c in crcs)
                crcs.append(_block_crcs(f, sec["offset"], sec["length"]))
        return np.concatenate(crcs).astype("<u4") if crcs else np.zeros(0, "<u4")


def _block_crcs(f: IO[bytes], offset: int, length: int) -> np.ndarray:
    """CRC-32 of every ``BLOCK`` bytes of ``length`` bytes at ``offset`` of ``f`` (the last block may be shorter)."""
    out = np.zeros(-(-length // BLOCK), np.uint32)
    f.seek(offset)
    done = 0
    step = 4096 * BLOCK
    while done < length:
        chunk = f.read(min(step, length - done))
        if not chunk:
            raise MapdbIOError(f"{f.name}: could not read back what was written")
        view = memoryview(chunk)
        for i in range(0, len(chunk), BLOCK):
            out[(done + i) // BLOCK] = zlib.crc32(view[i : i + BLOCK])
        done += len(chunk)
    return out


def pread(fd: int, offset: int, length: int, where: str) -> bytes:
    """Exactly ``length`` bytes at ``offset`` (a short read means a truncated index)."""
    data = os.pread(fd, length, offset) if length else b""
    if len(data) != length:
        raise MapFormatError(f"{where}: truncated quad index")
    return data


def pwrite_all(fd: int, data: bytes, offset: int) -> None:
    """Write all of ``data`` at ``offset`` (``os.pwrite`` may write less than asked)."""
    view = memoryview(data)
    while view:
        written = os.pwrite(fd, view, offset)
        view, offset = view[written:], offset + written


def header_blocks(h: dict[str, Any], where: str) -> bool:
    """Whether the header says its map's blocks are left out of the quads (key ``blocks``; absent: no blocks)."""
    if "blocks" not in h:
        return False
    if h["blocks"] != BLOCKS_LEFT_OUT:
        raise MapFormatError(f"{where}: quad index header field blocks is {str(h['blocks'])[:40]!r}, not "
                             f"{BLOCKS_LEFT_OUT!r}")
    return True
