"""The land-cover reader: :func:`read_landcover`, the checks of its raster, pixel areas and the scan of its tiles."""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.errors
from pyproj import CRS, Transformer
from rasterio.windows import Window

from ...errors import MapdbIOError, SourceError
from ...geo import check_bbox, in_bbox, projected_window
from ...labels import LabelTable
from ...objects import Objects
from ..suffixes import RASTER_SUFFIXES
from .classes import _ClassMasks
from .patches import _Patches
from .tiles import _Tiling

__all__ = ["ProgressCallback", "is_raster_path", "raster_class_table_name", "read_landcover"]

# GDAL's block cache defaults to 5% of RAM and would hold every decompressed block we read; each
# block is read once here, so a small cache is enough and keeps the peak memory bounded.
_GDAL_CACHE_MB = 64

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
        :data:`.tiles._TILE_PIXELS` pixels.

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
        too big to be read piecewise (more than :data:`.tiles._MAX_BLOCK_BYTES`).

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
