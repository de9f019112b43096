"""Tiles of a raster: windows of whole blocks of its file, and which blocks a sparse GeoTIFF stores."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rasterio.windows import Window

from ...errors import SourceError

# Nothing public: read_landcover (mapdb.sources.landcover.reader) is the interface.
__all__: list[str] = []

# Pixels per tile: big enough that per-tile overheads vanish, small enough that the tile, its
# per-label label image (int32) and temporaries stay in the low hundreds of MB.
_TILE_PIXELS = 1 << 24
# GDAL inflates a whole block into memory to give any part of it (even an uncompressed strip): a
# block that holds data may take at most this many bytes (a 2e9-pixel strip would take 2 GB).
_MAX_BLOCK_BYTES = 1 << 28


class _Tiling:
    """A raster window cut into tiles of whole blocks, and which tiles hold any block of data.

    Tiles are aligned with the file's blocks (so each block is read once), about
    :data:`_TILE_PIXELS` pixels each, and never wider or taller than that: a block bigger than a
    tile (a 2e9-pixel strip) is read in parts, if it takes at most :data:`_MAX_BLOCK_BYTES`.  With
    ``skip_absent``, tiles whose blocks are all absent from a sparse GeoTIFF are left out.
    """

    def __init__(self, path: Path, src: Any, window: Window, skip_absent: bool,
                 shape: tuple[int, int] | None = None) -> None:
        self.path = path
        self.row0, self.col0 = int(window.row_off), int(window.col_off)
        self.row_end = self.row0 + int(window.height)
        self.col_end = self.col0 + int(window.width)
        self.block_rows, self.block_cols = (int(v) for v in src.block_shapes[0])
        self.block_bytes = self.block_rows * self.block_cols * np.dtype(src.dtypes[0]).itemsize
        self.tile_rows, self.tile_cols = shape if shape is not None else self._shape()
        self.present = _block_presence(path, src, self.block_rows, self.block_cols) if skip_absent else None

    def _shape(self) -> tuple[int, int]:
        """Whole blocks, near-square, about _TILE_PIXELS pixels, within the window's size in blocks."""
        bh, bw = self.block_rows, self.block_cols
        height, width = self.row_end - self.row0, self.col_end - self.col0
        if bh * bw > _TILE_PIXELS:  # a block bigger than a tile: read it in parts
            rows = min(bh, max(1, math.isqrt(_TILE_PIXELS)), height)
            return rows, min(bw, _TILE_PIXELS // rows)
        budget = _TILE_PIXELS // (bh * bw)  # blocks per tile
        max_r, max_c = -(-height // bh), -(-width // bw)
        kr = min(max_r, max(1, math.isqrt(budget)))
        kc = min(max_c, max(1, budget // kr))
        kr = min(max_r, max(1, budget // kc))
        return kr * bh, kc * bw

    def rows(self) -> Iterator[tuple[int, int, list[tuple[int, int, int]]]]:
        """For each row of tiles, its first and end pixel rows and its tiles ``(index, first col, end col)``."""
        th, tw = self.tile_rows, self.tile_cols
        tc = np.arange(self.col0 // tw, -(-self.col_end // tw))
        c0 = np.maximum(tc * tw, self.col0)
        c1 = np.minimum((tc + 1) * tw, self.col_end)
        for tr in range(self.row0 // th, -(-self.row_end // th)):
            r0, r1 = max(tr * th, self.row0), min((tr + 1) * th, self.row_end)
            keep: slice | np.ndarray = slice(None)
            if self.present is not None:
                # Blocks of these rows holding data, summed per tile over the block columns it covers.
                row_has = self.present[r0 // self.block_rows:(r1 - 1) // self.block_rows + 1].any(axis=0)
                total = np.concatenate([[0], np.cumsum(row_has)])
                keep = np.flatnonzero(total[(c1 - 1) // self.block_cols + 1] > total[c0 // self.block_cols])
            yield r0, r1, list(zip(tc[keep].tolist(), c0[keep].tolist(), c1[keep].tolist(), strict=True))

    def check_block_size(self, row: int, col: int) -> None:
        """Refuse to read part of a block that GDAL would inflate whole into more than _MAX_BLOCK_BYTES."""
        if self.block_bytes > _MAX_BLOCK_BYTES:
            raise SourceError(
                f"{self.path}: blocks of {self.block_cols} x {self.block_rows} pixels hold data and are too big "
                f"to read in parts (over {_MAX_BLOCK_BYTES >> 20} MiB each); retile the raster, e.g. "
                "gdal_translate -co TILED=YES")


# TIFF tags and field types needed to find which blocks a GeoTIFF stores.
_TIFF_TAGS = {256: "width", 257: "height", 277: "samples", 278: "rows_per_strip", 279: "strip_counts",
              322: "tile_width", 323: "tile_height", 325: "tile_counts"}
_TIFF_TYPES = {3: "u2", 4: "u4", 16: "u8"}


def _block_presence(path: Path, src: Any, block_rows: int, block_cols: int) -> np.ndarray | None:
    """Which blocks of a GeoTIFF are stored (True) or absent from a sparse file (False), or None if unsure.

    Read from the byte counts of the first image directory (the full-resolution image): a block GDAL
    never wrote (``SPARSE_OK``) has 0 bytes.  GDAL gives no vectorised access to these (one
    ``BLOCK_SIZE_i_j`` metadata query per block would take minutes for millions of blocks), so the
    directory is read here; anything unexpected gives None, and then every block is read.
    """
    if src.driver != "GTiff":
        return None
    try:
        with open(path, "rb") as f:
            fields = _first_ifd(f)
            if fields is None:
                return None
            # Any, not Any | None: unless both equal the raster's (int) sizes, the next line returns.
            width: Any = fields.get("width")
            height: Any = fields.get("height")
            if (width, height) != (src.width, src.height) or fields.get("samples", 1) != 1:
                return None
            if "tile_counts" in fields:
                shape = (fields.get("tile_height"), fields.get("tile_width"))
                counts = fields["tile_counts"]
            else:
                shape = (min(fields.get("rows_per_strip", height), height), width)
                counts = fields.get("strip_counts")
            if counts is None or shape != (block_rows, block_cols):
                return None
            grid = (-(-height // block_rows), -(-width // block_cols))
            if isinstance(counts, np.ndarray):
                sizes = counts
            else:
                offset, dtype, n = counts
                f.seek(offset)
                sizes = np.fromfile(f, dtype=dtype, count=n)
    except (OSError, ValueError):
        return None
    if sizes.size != grid[0] * grid[1]:
        return None
    return (sizes != 0).reshape(grid)


def _first_ifd(f: Any) -> dict[str, Any] | None:
    """The fields of a TIFF's first image directory that :func:`_block_presence` needs.

    Scalars are ints; a byte-count array is ``(file offset, numpy dtype, count)``, or the array itself
    when it is short enough to sit in its directory entry.
    """
    head = f.read(16)
    if head[:2] == b"II":
        order = "<"
    elif head[:2] == b"MM":
        order = ">"
    else:
        return None
    magic = int.from_bytes(head[2:4], "little" if order == "<" else "big")
    if magic == 42:
        big, ifd = False, int.from_bytes(head[4:8], "little" if order == "<" else "big")
    elif magic == 43:
        big, ifd = True, int.from_bytes(head[8:16], "little" if order == "<" else "big")
    else:
        return None
    f.seek(ifd)
    count_type = np.dtype(order + ("u8" if big else "u2"))
    n_entries = int(np.frombuffer(f.read(count_type.itemsize), count_type)[0])
    entry = np.dtype([("tag", order + "u2"), ("type", order + "u2"), ("count", order + ("u8" if big else "u4")),
                      ("value", "V8" if big else "V4")])
    entries = np.frombuffer(f.read(entry.itemsize * n_entries), entry)
    if entries.size != n_entries:
        return None
    inline = 8 if big else 4
    fields: dict[str, Any] = {}
    for tag, kind, count, value in entries.tolist():
        name = _TIFF_TAGS.get(tag)
        if name is None or kind not in _TIFF_TYPES:
            continue
        dtype = np.dtype(order + _TIFF_TYPES[kind])
        raw = bytes(value)
        if name.endswith("_counts"):
            if count * dtype.itemsize <= inline:  # one or two blocks: the counts are in the entry itself
                fields[name] = np.frombuffer(raw[:count * dtype.itemsize], dtype)
            else:
                offset = int(np.frombuffer(raw, np.dtype(order + ("u8" if big else "u4")))[0])
                fields[name] = (offset, dtype, int(count))
        elif count >= 1:
            fields[name] = int(np.frombuffer(raw[:dtype.itemsize], dtype)[0])
    return fields
