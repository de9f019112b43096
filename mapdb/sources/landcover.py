"""Land-cover rasters (GeoTIFF of class codes) -> one object per patch.

A *patch* is a connected region of pixels whose class codes map to the same
label (so WorldCover's herbaceous wetland and mangroves, both ``wetland``,
form one patch where they touch).  Connectivity is 8-neighbour by default
(the FRAGSTATS / landscape-ecology convention): pixels touching only at a
corner belong to one patch, so a one-pixel-wide diagonal hedge or stream is
one object, not a string of single pixels.  Pass ``connectivity=4`` for the
stricter rule.

Each patch of at least ``min_area_m2`` becomes one object at its area-weighted
centroid, in the raster's own CRS (the caller reprojects).

The raster is read in *tiles*: windows of whole blocks of the file (its ``block_shapes``),
a few thousand pixels each way, so that memory stays bounded whatever the raster's
width or height (a 36000 x 36000 WorldCover tile needs a few hundred MB, not the
1.3 GB of its array; a 2e9 x 1 raster needs no 2e9-wide row).  Tiles whose blocks
are all absent from a sparse GeoTIFF (written with ``SPARSE_OK``: their offsets in
the file are 0) are skipped without being read, when the value GDAL fills them
with (nodata, else 0) is not a class: a 1e6 x 1e6 raster with a few blocks of data
costs what those blocks cost.  Within a tile every label present is labelled with
:func:`scipy.ndimage.label`; per-component sums (area, area-weighted column and
row) are accumulated from pixel runs.  Components are joined across tile edges
(left and above, diagonals included with 8-connectivity) with a
connected-components pass at the end of each row of tiles; a component is
emitted as soon as it does not touch that row's last pixel row, since then it can
no longer grow.  Only these open components and the emitted objects are kept
between rows of tiles.

Pixel area: for a projected CRS, the area of the pixel's parallelogram in
CRS units (converted to metres), the same everywhere; the projection's own
scale distortion is not corrected (fine for UTM or an equal-area CRS like
EPSG:3035, but Web Mercator areas are inflated away from the equator).  For a
geographic CRS, the exact area of each row's cell on the CRS's ellipsoid, so
centroids are area-weighted means of longitude and latitude.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.errors
from pyproj import CRS, Transformer
from rasterio.windows import Window
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import MapdbIOError, SourceError
from ..geo import check_bbox, in_bbox, projected_window
from ..labels import LabelTable
from ..objects import Objects
from .suffixes import RASTER_SUFFIXES

__all__ = ["RASTER_SUFFIXES", "is_raster_path", "read_landcover", "raster_class_table_name"]

# Pixels per tile: big enough that per-tile overheads vanish, small enough that the tile, its
# per-label label image (int32) and temporaries stay in the low hundreds of MB.
_TILE_PIXELS = 1 << 24
# GDAL inflates a whole block into memory to give any part of it (even an uncompressed strip): a
# block that holds data may take at most this many bytes (a 2e9-pixel strip would take 2 GB).
_MAX_BLOCK_BYTES = 1 << 28
# GDAL's block cache defaults to 5% of RAM and would hold every decompressed block we read; each
# block is read once here, so a small cache is enough and keeps the peak memory bounded.
_GDAL_CACHE_MB = 64
# Up to this many class codes, label masks come from one comparison per code; beyond, from a lookup
# table (indexed by the code for up to 16-bit pixels, searched for wider ones).
_COMPARE_MAX_CODES = 16
_LUT_MAX_BITS = 16

ProgressCallback = Callable[[str], None]


def is_raster_path(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` has a raster suffix (``.tif``, ``.tiff``, ``.gtiff``; any case).

    Examples
    --------
    >>> is_raster_path("ESA_WorldCover_10m_2021_v200_N00E006_Map.TIF"), is_raster_path("a.geojson")
    (True, False)
    """
    return Path(path).suffix.lower() in RASTER_SUFFIXES


def raster_class_table_name(path: str | os.PathLike[str]) -> str:
    """Guess the class table (``worldcover`` or ``corine``) from a raster's file name.

    Raises :class:`SourceError` when the name gives no hint.

    Examples
    --------
    >>> raster_class_table_name("ESA_WorldCover_10m_2021_v200_N00E006_Map.tif")
    'worldcover'
    >>> raster_class_table_name("corine2006_lausanne_ls100_06.tif")
    'corine'
    """
    name = Path(path).name.lower()
    if "worldcover" in name:
        return "worldcover"
    if "clc" in name or "corine" in name:
        return "corine"
    raise SourceError(
        f"{path}: cannot tell the land-cover class table from the file name; "
        "name it with --raster-classes NAME (e.g. worldcover, corine, or a table from your --labels file)"
    )


def read_landcover(path: str | os.PathLike[str], table: LabelTable, classes: str | None = None,
                   min_area_m2: float = 10_000.0, bbox: tuple[float, float, float, float] | None = None,
                   progress: ProgressCallback | None = None, *, connectivity: int = 8,
                   _tile: tuple[int, int] | None = None) -> Objects:
    """One object per land-cover patch of at least ``min_area_m2``.

    Parameters
    ----------
    path : path-like
        Single-band GeoTIFF of integer class codes, with a CRS.
    table : LabelTable
        Label table; ``table.rasters[classes]`` maps pixel codes to label names.
        Codes not in it (and the nodata value) are not objects.
    classes : str, optional
        Name of the class table (``"worldcover"``, ``"corine"``, or one from a
        user's label file).  Default: guessed from the file name, see
        :func:`raster_class_table_name`.
    min_area_m2 : float
        Smallest patch kept, in square metres.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Read only the part of the raster covering this box, and keep only
        patches whose centroid lies inside it.  Patches crossing the window
        edge are cut there (their area and centroid are those of the part read).
    progress : callable, optional
        Called with a one-line message now and then.
    connectivity : {8, 4}
        Neighbourhood that joins pixels into patches.
    _tile : (rows, cols), optional
        Tile size for tests (many tile edges on a small raster); default: whole blocks, about
        :data:`_TILE_PIXELS` pixels.

    Returns
    -------
    Objects
        Centroids in the raster's CRS (``crs`` set to its string), label codes
        into ``table.labels``, areas in square metres.

    Raises
    ------
    MapdbIOError
        The file is missing or unreadable.
    SourceError
        Not a raster, truncated, no CRS, more than one band, non-integer
        pixels, no class table could be chosen, or a block that holds data is
        too big to be read piecewise (more than :data:`_MAX_BLOCK_BYTES`).

    Examples
    --------
    >>> from mapdb.labels import default_label_table
    >>> objs = read_landcover("corine2006_lausanne_ls100_06.tif", default_label_table())  # doctest: +SKIP
    >>> objs.counts()["water"]  # doctest: +SKIP
    12
    """
    path = Path(path)
    bbox = None if bbox is None else check_bbox(bbox)
    code_labels = _class_table(path, table, classes, connectivity)
    return _read_patches(path, code_labels, tuple(table.labels), min_area_m2, bbox, progress, connectivity, _tile)


def _class_table(path: Path, table: LabelTable, classes: str | None, connectivity: int) -> dict[int, str]:
    """The raster's class table (pixel code to label), once the arguments and the path are checked."""
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, not {connectivity!r}")
    if not path.exists():
        raise MapdbIOError(f"{path}: no such file")
    if path.is_dir():
        raise MapdbIOError(f"{path}: is a directory, not a raster")
    name = classes if classes is not None else raster_class_table_name(path)
    if name not in table.rasters:
        raise SourceError(f"{path}: no raster class table named {name!r} (have: {', '.join(sorted(table.rasters))})")
    return table.raster_classes(name)


def _read_patches(path: Path, code_labels: dict[int, str], labels: tuple[str, ...], min_area_m2: float,
                  bbox: tuple[float, float, float, float] | None, progress: ProgressCallback | None,
                  connectivity: int, tile: tuple[int, int] | None) -> Objects:
    """The patches of the raster (of its part under ``bbox``), as objects in its CRS."""
    with rasterio.Env(GDAL_CACHEMAX=_GDAL_CACHE_MB), _open_raster(path) as src:
        _check_raster(path, src)
        crs = CRS.from_user_input(src.crs.to_wkt())
        crs_string = src.crs.to_string()
        t = src.transform
        window = _bbox_window(src, bbox) if bbox is not None else Window(0, 0, src.width, src.height)
        if window is None:
            return Objects.empty(labels, crs_string)
        class_masks = _ClassMasks(src.dtypes[0], code_labels, labels, src.nodata)
        # GDAL gives an absent block of a sparse file the nodata value, else 0: when that is a class,
        # absent blocks are patches and must be read like the others.
        fill = src.nodata if src.nodata is not None else 0
        tiling = _Tiling(path, src, window, skip_absent=not class_masks.is_class(fill), shape=tile)
        patches = _Patches(min_area_m2, connectivity)
        _scan(path, src, tiling, class_masks, _pixel_area_fn(path, crs, t), patches, progress)
        col, row, label_code, area = patches.result()

    x = t.a * col + t.b * row + t.c
    y = t.d * col + t.e * row + t.f
    objects = Objects(x, y, label_code - 1, area, labels, crs_string)
    if bbox is not None and len(objects):
        lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
        objects = objects.take(np.flatnonzero(in_bbox(bbox, lon, lat)))
    return objects


def _open_raster(path: Path) -> Any:
    try:
        with warnings.catch_warnings():
            # A raster without georeferencing is reported by _check_raster as an error, not as a warning.
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            return rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise SourceError(f"{path}: not a readable raster ({_one_line(exc)})") from None


def _scan(path: Path, src: Any, tiling: _Tiling, class_masks: _ClassMasks,
          pixel_area: Callable[[int, int], np.ndarray], patches: _Patches,
          progress: ProgressCallback | None) -> None:
    """Feed the tiles of ``tiling`` that hold data to ``patches``, row of tiles by row of tiles."""
    use_mask = _has_mask_band(src)
    next_report = 0.1
    span = tiling.row_end - tiling.row0
    for r0, r1, tiles in tiling.rows():
        if tiles or patches.has_open:
            patches.begin_row()
            area = pixel_area(r0, r1)
            for tc, c0, c1 in tiles:
                tiling.check_block_size(r0, c0)
                window = Window(c0, r0, c1 - c0, r1 - r0)
                try:
                    data = src.read(1, window=window)
                    valid = src.read_masks(1, window=window) if use_mask else None
                except rasterio.errors.RasterioError as exc:
                    raise SourceError(f"{path}: not a readable raster ({_one_line(exc)})") from None
                patches.add_tile(tc, c0, class_masks(data, valid), r0, area)
                del data, valid
            patches.end_row()
        done = (r1 - tiling.row0) / span
        if progress is not None and (done >= next_report or r1 == tiling.row_end):
            progress(f"{path.name}: {r1 - tiling.row0}/{span} rows, {patches.n_emitted} patches")
            next_report = done + 0.1
    patches.finish()


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


def _one_line(exc: BaseException) -> str:
    """The GDAL message behind a rasterio error, on one line."""
    # rasterio's read errors say "See previous exception"; the GDAL error chained below says what failed.
    while exc.__cause__ is not None and "previous exception" in str(exc):
        exc = exc.__cause__
    message = str(exc.args[2]) if len(exc.args) == 3 and isinstance(exc.args[2], str) else str(exc)
    return " ".join(message.split()) or exc.__class__.__name__


def _check_raster(path: Path, src: Any) -> None:
    if src.crs is None:
        raise SourceError(f"{path}: raster has no CRS")
    if src.count != 1:
        raise SourceError(f"{path}: raster has {src.count} bands; a land-cover raster has one band of class codes")
    if not np.issubdtype(np.dtype(src.dtypes[0]), np.integer):
        raise SourceError(f"{path}: raster pixels are {src.dtypes[0]}; land-cover class codes must be integers")


def _has_mask_band(src: Any) -> bool:
    """Whether the raster carries a mask band of its own (e.g. an internal .msk), not just nodata or none."""
    from rasterio.enums import MaskFlags

    flags = src.mask_flag_enums[0]
    return MaskFlags.per_dataset in flags and MaskFlags.nodata not in flags


def _bbox_window(src: Any, bbox: tuple[float, float, float, float]) -> Window | None:
    """The pixel window (rounded outwards, clipped to the raster) that may hold a lon/lat box, or None.

    Found with :func:`mapdb.geo.projected_window`: a box that spans the world, touches a pole or crosses
    the antimeridian still gives the right window (at worst the whole raster); the exact test is made on
    the patches' centroids.
    """
    b = src.bounds
    found = projected_window(src.crs.to_wkt(), bbox, within=(b.left, b.bottom, b.right, b.top))
    if found is None:
        return None
    minx, miny, maxx, maxy = found
    inv = ~src.transform
    cols, rows = zip(*(inv @ (x, y) for x, y in ((minx, miny), (minx, maxy), (maxx, miny), (maxx, maxy))),
                     strict=True)
    c0 = max(0, math.floor(min(cols)))
    c1 = min(src.width, math.ceil(max(cols)))
    r0 = max(0, math.floor(min(rows)))
    r1 = min(src.height, math.ceil(max(rows)))
    if c0 >= c1 or r0 >= r1:
        return None
    return Window(c0, r0, c1 - c0, r1 - r0)


def _pixel_area_fn(path: Path, crs: CRS, transform: Any) -> Callable[[int, int], np.ndarray]:
    """A function giving the pixel area (m^2) of each row in [r0, r1)."""
    unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
    if not crs.is_geographic:
        area = abs(transform.a * transform.e - transform.b * transform.d) * unit * unit

        def projected(r0: int, r1: int) -> np.ndarray:
            return np.full(r1 - r0, area)

        return projected

    if transform.b != 0 or transform.d != 0:
        raise SourceError(f"{path}: rotated geographic rasters are not supported")
    ellipsoid = crs.ellipsoid
    a = ellipsoid.semi_major_metre if ellipsoid is not None else 6378137.0
    b = ellipsoid.semi_minor_metre if ellipsoid is not None else 6356752.314245179
    ecc = math.sqrt(max(0.0, 1.0 - (b * b) / (a * a)))
    dlon = abs(transform.a) * unit  # radians

    def zone(lat_units: np.ndarray) -> np.ndarray:
        # Area per radian of longitude between the equator and latitude phi on the ellipsoid.
        s = np.sin(np.clip(lat_units * unit, -math.pi / 2, math.pi / 2))
        if ecc < 1e-12:
            return b * b * s
        es = ecc * s
        return b * b / 2 * (s / (1 - es * es) + np.log((1 + es) / (1 - es)) / (2 * ecc))

    def geographic(r0: int, r1: int) -> np.ndarray:
        edges = transform.f + transform.e * np.arange(r0, r1 + 1, dtype=np.float64)
        return dlon * np.abs(np.diff(zone(edges)))

    return geographic


class _ClassMasks:
    """Pixel codes -> one boolean mask per label present (codes not in the table and nodata excluded).

    With few codes (WorldCover has 10) a comparison per code is cheapest; with many (CORINE maps 32
    codes to 11 labels) the codes first go through a lookup table to label numbers.
    """

    def __init__(self, dtype: str, code_labels: Mapping[int, str], labels: tuple[str, ...],
                 nodata: float | None) -> None:
        dtype_ = np.dtype(dtype)
        info = np.iinfo(dtype_)
        index = {name: i + 1 for i, name in enumerate(labels)}
        pairs = {int(c): index[name] for c, name in code_labels.items() if info.min <= int(c) <= info.max}
        if nodata is not None and math.isfinite(nodata) and float(nodata).is_integer():
            pairs.pop(int(nodata), None)
        self.codes_present = frozenset(pairs)
        self.by_class: dict[int, list[int]] = {}
        for code, cls in sorted(pairs.items()):
            self.by_class.setdefault(cls, []).append(code)
        self.use_table = len(pairs) > _COMPARE_MAX_CODES
        if self.use_table and dtype_.itemsize * 8 <= _LUT_MAX_BITS:
            # Index by the code's unsigned bit pattern so signed types need no offset arithmetic.
            self.unsigned = np.dtype(f"u{dtype_.itemsize}")
            self.table = np.zeros(1 << (8 * dtype_.itemsize), np.uint8)
            for code, cls in pairs.items():
                self.table[np.array(code, dtype_).view(self.unsigned)] = cls
        elif self.use_table:
            order = sorted(pairs)
            self.codes = np.array(order, dtype=dtype_)
            self.values = np.array([pairs[c] for c in order], dtype=np.uint8)

    def is_class(self, value: float) -> bool:
        """Whether pixels of this value belong to some label."""
        return float(value).is_integer() and int(value) in self.codes_present

    def _classes(self, data: np.ndarray) -> np.ndarray:
        if hasattr(self, "table"):
            return self.table[data.view(self.unsigned)]
        pos = np.searchsorted(self.codes, data)
        np.minimum(pos, self.codes.size - 1, out=pos)
        return np.where(self.codes[pos] == data, self.values[pos], np.uint8(0))

    def __call__(self, data: np.ndarray, valid: np.ndarray | None) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(class number, first row, mask of rows first..last)`` for each label present."""
        if self.use_table:
            data = self._classes(data)
            by_value = {cls: [cls] for cls in self.by_class}
        else:
            by_value = self.by_class
        values = [v for vs in by_value.values() for v in vs]
        rows_with = dict(zip(values, _rows_with_values(data, values), strict=True))
        for cls, vs in by_value.items():
            present = [v for v in vs if rows_with[v].size]
            if not present:
                continue
            r0 = min(int(rows_with[v][0]) for v in present)
            r1 = max(int(rows_with[v][-1]) for v in present) + 1
            part = data[r0:r1]
            mask = part == present[0]
            for v in present[1:]:
                mask |= part == v
            if valid is not None:
                mask &= valid[r0:r1] != 0
            yield cls, r0, mask


def _rows_with_values(data: np.ndarray, values: list[int]) -> list[np.ndarray]:
    """For each value, the rows of ``data`` where it occurs.

    One pass over ``data`` in cache-sized row chunks, comparing each chunk with every value: a
    full-size comparison per value would stream the whole tile through memory once per value.
    """
    h, w = data.shape
    chunk = max(1, 1_000_000 // max(1, w))
    found = np.zeros((len(values), h), bool)
    scratch = np.empty((chunk, w), bool)
    for r in range(0, h, chunk):
        part = data[r:r + chunk]
        out = scratch[:part.shape[0]]
        for i, v in enumerate(values):
            np.equal(part, v, out=out)
            out.any(axis=1, out=found[i, r:r + part.shape[0]])
    return [np.flatnonzero(f) for f in found]


class _Patches:
    """Connected components accumulated tile by tile, emitted once they can no longer grow.

    Tiles come in rows (``begin_row``, ``add_tile`` left to right, ``end_row``); per component we
    keep the sums ``area``, ``area * col`` and ``area * row`` (pixel-centre coordinates in the full
    raster's pixel grid), from which the centroid follows.  Within a row of tiles, components are
    *nodes*: first the components left open by the row above, then each tile's own.  Pairs of nodes
    touching across a tile edge are joined at ``end_row`` by one connected-components pass.
    """

    def __init__(self, min_area: float, connectivity: int) -> None:
        self.min_area = min_area
        self.structure = ndimage.generate_binary_structure(2, 2 if connectivity == 8 else 1)
        self.diagonal = connectivity == 8
        # Open components (touching the last pixel row of the row of tiles above): sums and class,
        # and for each tile column of that row, which open component each pixel of its last row holds.
        self.open_sums: np.ndarray = np.zeros((3, 0))
        self.open_cls = np.zeros(0, np.uint8)
        self.seam: dict[int, np.ndarray] = {}
        self.out: list[tuple[np.ndarray, ...]] = []
        self.n_emitted = 0
        self._buffer = np.empty(0, np.int32)

    @property
    def has_open(self) -> bool:
        return self.open_cls.size > 0

    def begin_row(self) -> None:
        self._sums = [self.open_sums]
        self._cls = [self.open_cls]
        self._n = self.open_cls.size
        self._pairs: list[tuple[np.ndarray, np.ndarray]] = []
        self._bottoms: dict[int, np.ndarray] = {}
        self._left: tuple[int, np.ndarray] | None = None

    def add_tile(self, tc: int, col_off: int, class_masks: Iterable[tuple[int, int, np.ndarray]], row_off: int,
                 row_area: np.ndarray) -> None:
        """Label one tile (tile column ``tc``, first pixel at ``row_off, col_off``).

        ``class_masks`` gives ``(class, first row, mask of rows first..last)`` for each class present.
        """
        h = row_area.size
        w = None
        # Placeholders, replaced by full-width arrays at the first class (or never read: see "w is None").
        first = last = left = right = np.empty(0, np.int64)
        for c, mask_row0, mask in class_masks:
            if w is None:
                w = mask.shape[1]
                first, last = np.full(w, -1, np.int64), np.full(w, -1, np.int64)
                left, right = np.full(h, -1, np.int64), np.full(h, -1, np.int64)
            rows = np.flatnonzero(mask.any(axis=1))
            if rows.size == 0:
                continue
            # Label only the bounding box of this class in the tile; r0, r1 are tile rows.
            crop_rows = mask[rows[0]:rows[-1] + 1]
            r0, r1 = mask_row0 + int(rows[0]), mask_row0 + int(rows[-1]) + 1
            cols = np.flatnonzero(crop_rows.any(axis=0))
            c0, c1 = int(cols[0]), int(cols[-1]) + 1
            crop = crop_rows[:, c0:c1]
            del mask, crop_rows
            comp = self._label_buffer(crop.shape)
            n = ndimage.label(crop, structure=self.structure, output=comp)
            self._sums.append(_component_sums(crop, comp, n, row_area[r0:r1], row_off + r0, col_off + c0))
            self._cls.append(np.full(n, c, np.uint8))
            # Node numbers of the components on the tile's four edges, for the joins.
            base = self._n - 1
            for edge, at, span, pixels in ((first, r0 == 0, slice(c0, c1), comp[0]),
                                           (last, r1 == h, slice(c0, c1), comp[-1]),
                                           (left, c0 == 0, slice(r0, r1), comp[:, 0]),
                                           (right, c1 == w, slice(r0, r1), comp[:, -1])):
                if at:
                    edge[span] = np.where(pixels > 0, pixels.astype(np.int64) + base, edge[span])
            self._n += n
            del crop
        if w is None:  # no class present (the generator yielded nothing): nothing to join
            self._left = None
            return
        self._join(self.seam.get(tc), first)
        if self.diagonal:
            above_left, above_right = self.seam.get(tc - 1), self.seam.get(tc + 1)
            if above_left is not None:
                self._pairs.append((above_left[-1:], first[:1]))
            if above_right is not None:
                self._pairs.append((above_right[:1], first[-1:]))
        if self._left is not None and self._left[0] == tc - 1:
            self._join(self._left[1], left)
        self._left = (tc, right)
        if (last >= 0).any():
            self._bottoms[tc] = last

    def _join(self, a: np.ndarray | None, b: np.ndarray) -> None:
        """Node pairs facing each other across an edge (``a`` on one side, ``b`` on the other)."""
        if a is None:
            return
        self._pairs.append((a, b))
        if self.diagonal:
            self._pairs += [(a[:-1], b[1:]), (a[1:], b[:-1])]

    def end_row(self, last: bool = False) -> None:
        """Join the row's nodes, emit the components that can no longer grow, keep the others open."""
        node_sums = np.concatenate(self._sums, axis=1)
        node_cls = np.concatenate(self._cls)
        n_nodes = node_cls.size
        group, n_groups = np.arange(n_nodes), n_nodes
        if self._pairs:
            a = np.concatenate([p[0] for p in self._pairs])
            b = np.concatenate([p[1] for p in self._pairs])
            hit = (a >= 0) & (b >= 0)
            a, b = a[hit], b[hit]
            same = node_cls[a] == node_cls[b]
            a, b = a[same], b[same]
            if a.size:
                graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n_nodes, n_nodes))
                n_groups, group = connected_components(graph, directed=False)
        group_sums = np.stack([np.bincount(group, weights=s, minlength=n_groups) for s in node_sums])
        group_cls = np.zeros(n_groups, np.uint8)
        group_cls[group] = node_cls
        still_open = np.zeros(n_groups, bool)
        if not last:
            for bottom in self._bottoms.values():
                still_open[group[bottom[bottom >= 0]]] = True
        closed = ~still_open & (group_sums[0] >= self.min_area) & (group_sums[0] > 0)
        if closed.any():
            s = group_sums[:, closed]
            self.out.append((s[1] / s[0], s[2] / s[0], group_cls[closed].astype(np.int32), s[0]))
            self.n_emitted += int(closed.sum())
        open_ids = np.flatnonzero(still_open)
        renumber = np.full(n_groups, -1, np.int64)
        renumber[open_ids] = np.arange(open_ids.size)
        self.open_sums = group_sums[:, open_ids]
        self.open_cls = group_cls[open_ids]
        self.seam = {tc: np.where(bottom >= 0, renumber[group[np.maximum(bottom, 0)]], -1)
                     for tc, bottom in self._bottoms.items()}
        self.seam = {tc: ids for tc, ids in self.seam.items() if (ids >= 0).any()}

    def finish(self) -> None:
        """Emit every component still open (after the window's last row of tiles)."""
        self.begin_row()
        self.end_row(last=True)

    def _label_buffer(self, shape: tuple[int, int]) -> np.ndarray:
        # Reused between labellings: a fresh 100+ MB array per call costs as much in page faults as
        # the labelling itself.
        size = shape[0] * shape[1]
        if self._buffer.size < size:
            self._buffer = np.empty(size, np.int32)
        return self._buffer[:size].reshape(shape)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centroid column and row (pixel units, full raster), class number and area of every patch kept."""
        if not self.out:
            z = np.zeros(0)
            return z, z, np.zeros(0, np.int32), z
        return tuple(np.concatenate(part) for part in zip(*self.out, strict=True))  # type: ignore[return-value]


def _component_sums(mask: np.ndarray, comp: np.ndarray, n: int, row_area: np.ndarray, row_off: int,
                    col_off: int) -> np.ndarray:
    """Sums (area, area*col, area*row) per component 1..n of ``comp``, from the runs of ``mask``.

    Working on runs (a few per row) instead of pixels keeps this cheap for large patches.
    Coordinates are pixel centres in the full raster grid.
    """
    h, w = mask.shape
    # Nonzero where a run starts or one past where it ends; the extra column ends every run in its
    # row, so in raster order the nonzero positions alternate start, end, start, end...
    m = mask.view(np.int8)
    edges = np.empty((h, w + 1), np.int8)
    edges[:, 0] = m[:, 0]
    np.subtract(m[:, 1:], m[:, :-1], out=edges[:, 1:w])
    edges[:, w] = m[:, w - 1]
    bounds = np.flatnonzero(edges)
    del edges
    starts, ends = bounds[0::2], bounds[1::2]
    row = starts // (w + 1)
    start_col = starts - row * (w + 1)
    length = (ends - starts).astype(np.float64)
    ids = comp[row, start_col] - 1
    run_area = length * row_area[row]
    mean_col = start_col + length / 2 + col_off  # centre of the run's pixel centres
    out = np.empty((3, n))
    out[0] = np.bincount(ids, weights=run_area, minlength=n)
    out[1] = np.bincount(ids, weights=run_area * mean_col, minlength=n)
    out[2] = np.bincount(ids, weights=run_area * (row + row_off + 0.5), minlength=n)
    return out
