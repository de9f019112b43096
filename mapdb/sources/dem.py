"""Digital elevation models: the ground's height under each map object, read from GeoTIFFs or SRTM ``.hgt`` tiles.

A build given one or more DEMs (``mapdb build ... --dem DEM``) stores each object's ground elevation in the
map (``docs/format.md``, version 2).  :class:`Dem` opens the files once, checks them, and samples them at
object positions given in any CRS:

* every file is read with rasterio, in windows of at most ``_TILE`` x ``_TILE`` posts around the objects
  that fall in them, so that a country's DEM is never read whole;
* the value at a position is the bilinear interpolation of the four posts around it (post ``(r, c)`` at the
  centre of pixel ``(r, c)``, which is where GDAL's SRTMHGT driver puts an SRTM post); a position with a
  nodata post among its four, or outside every file, has no elevation (NaN) and is counted;
* several files form a mosaic: a position takes the first file, in the order given, that has a value there.

Refused, as one :class:`~mapdb.errors.SourceError` line naming the file: a file rasterio cannot read, one
without a CRS, one whose heights are in feet (its band unit or its vertical CRS axis), and a ``.hgt`` file
whose name is not its tile's (``N43E007.hgt``): GDAL takes an SRTM tile's georeference from its name, so a
renamed tile would put every height in the wrong place.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SourceError

__all__ = ["DEM_SUFFIXES", "Dem", "DemSample"]

DEM_SUFFIXES = (".tif", ".tiff", ".gtiff", ".hgt")
# Posts read at once (a window's side): 16 MB of float64 at most, whatever the DEM's size.
_TILE = 1024
_HGT_NAME = re.compile(r"^[NS]\d{2}[EW]\d{3}$", re.IGNORECASE)
_FEET = ("ft", "foot", "feet", "us survey foot", "us_survey_foot", "ftus", "us-ft")


class DemSample(dict):
    """What :meth:`Dem.sample` found: ``"outside"`` (objects outside every DEM) and ``"nodata"`` (objects on
    a void post) counts, by name."""


class Dem:
    """One or more elevation rasters, checked when opened, sampled at object positions.

    Parameters
    ----------
    paths : sequence of paths
        GeoTIFFs or SRTM ``.hgt`` tiles, in any CRS, heights in metres; earlier files win where they overlap.

    Raises
    ------
    SourceError
        A file that is missing or unreadable, has no CRS, has heights in feet, or is a renamed ``.hgt`` tile.

    Examples
    --------
    >>> import tempfile, os, rasterio
    >>> from rasterio.transform import from_origin
    >>> p = os.path.join(tempfile.mkdtemp(), "ramp.tif")
    >>> with rasterio.open(p, "w", driver="GTiff", width=3, height=3, count=1, dtype="float32",
    ...                    crs="EPSG:32631", transform=from_origin(500000, 5000030, 10, 10)) as f:
    ...     f.write(np.array([[0, 10, 20]] * 3, np.float32), 1)
    >>> dem = Dem([p])
    >>> z, found = dem.sample(np.array([500010.0, 500020.0, 400000.0]), np.array([5000010.0] * 3), "EPSG:32631")
    >>> z[:2].tolist(), bool(np.isnan(z[2])), found["outside"]
    ([5.0, 15.0], True, 1)
    """

    def __init__(self, paths: Sequence[str | Path]) -> None:
        self.paths = [Path(p) for p in paths]
        self.names = [p.name for p in self.paths]
        for path in self.paths:
            _check_file(path)

    def sample(self, x: np.ndarray, y: np.ndarray, crs: str) -> tuple[np.ndarray, DemSample]:
        """The ground elevation (metres) at each position (``x``, ``y`` in ``crs``), NaN where no file has one;
        and the counts of positions outside every file and on a nodata post."""
        import rasterio

        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        z = np.full(x.size, np.nan)
        state = np.zeros(x.size, np.int8)  # 0 outside every file so far, 1 on a void post, 2 found
        for path in self.paths:
            todo = np.flatnonzero(state < 2)
            if not todo.size:
                break
            with _reading(path), rasterio.open(path) as src:
                values, inside = _sample_file(src, x[todo], y[todo], crs)
            state[todo[inside & np.isnan(values)]] = 1
            found = np.isfinite(values)
            z[todo[found]] = values[found]
            state[todo[found]] = 2
        return z, DemSample(outside=int((state == 0).sum()), nodata=int((state == 1).sum()))


@contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Turn rasterio's and the OS's errors while reading a DEM into one :class:`SourceError` line."""
    import rasterio.errors

    try:
        yield
    except SourceError:
        raise
    except (OSError, rasterio.errors.RasterioError, ValueError) as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise SourceError(f"{path}: cannot read the DEM ({text[:200]})") from None


def _check_file(path: Path) -> None:
    """Refuse a DEM that cannot give true heights at true places (see the module docstring)."""
    import rasterio

    if path.suffix.lower() not in DEM_SUFFIXES:
        raise SourceError(f"{path}: not a DEM file (expected one of {', '.join(DEM_SUFFIXES)})")
    if not path.is_file():
        raise SourceError(f"{path}: no such DEM file" if not path.exists() else f"{path}: not a regular file")
    if path.suffix.lower() == ".hgt" and not _HGT_NAME.match(path.stem):
        raise SourceError(f"{path}: an SRTM .hgt tile takes its place from its name (such as N43E007.hgt); "
                          "this one was renamed, so its heights would be put in the wrong place")
    with _reading(path), rasterio.open(path) as src:
        if src.crs is None:
            raise SourceError(f"{path}: the DEM has no CRS, so its heights cannot be placed")
        if src.count < 1:
            raise SourceError(f"{path}: the DEM has no band")
        units = [u for u in (src.units[0] if src.units else None, _vertical_unit(src.crs)) if u]
        if any(u.strip().lower() in _FEET for u in units):
            raise SourceError(f"{path}: the DEM's heights are in feet; mapdb reads heights in metres "
                              "(convert it first, e.g. gdal_calc.py --calc='A*0.3048')")


def _vertical_unit(crs: Any) -> str | None:
    """The unit of a compound CRS's vertical axis, or None."""
    from pyproj import CRS

    try:
        axes = CRS.from_wkt(crs.to_wkt()).axis_info
    except Exception:  # a CRS pyproj cannot parse says nothing about its vertical unit
        return None
    vertical = [a.unit_name for a in axes if a.direction in ("up", "down")]
    return vertical[0] if vertical else None


def _sample_file(src: Any, x: np.ndarray, y: np.ndarray, crs: str) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear elevation from one open raster at positions in ``crs`` (NaN off it or on a void post), and
    whether each position is inside it."""
    from pyproj import Transformer

    to_dem = Transformer.from_crs(crs, src.crs.to_wkt(), always_xy=True)
    dx, dy = to_dem.transform(x, y)
    inv = ~src.transform
    dx, dy = np.asarray(dx, np.float64), np.asarray(dy, np.float64)
    col, row = inv.a * dx + inv.b * dy + inv.c, inv.d * dx + inv.e * dy + inv.f
    # Posts at pixel centres: fractional post coordinates
    col, row = np.asarray(col, np.float64) - 0.5, np.asarray(row, np.float64) - 0.5
    inside = np.isfinite(col) & np.isfinite(row) & (col >= -0.5) & (row >= -0.5) & \
        (col <= src.width - 0.5) & (row <= src.height - 0.5)
    values = np.full(x.size, np.nan)
    c0 = np.clip(np.floor(np.where(inside, col, 0)), 0, max(src.width - 2, 0)).astype(np.int64)
    r0 = np.clip(np.floor(np.where(inside, row, 0)), 0, max(src.height - 2, 0)).astype(np.int64)
    tiles = (r0 // _TILE) * (src.width // _TILE + 1) + c0 // _TILE
    for tile in np.unique(tiles[inside]):
        at = np.flatnonzero(inside & (tiles == tile))
        values[at] = _bilinear(src, row[at], col[at], r0[at], c0[at])
    return values, inside


def _bilinear(src: Any, row: np.ndarray, col: np.ndarray, r0: np.ndarray, c0: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of the four posts around each position, read in one window (NaN on nodata)."""
    from rasterio.windows import Window

    top, left = int(r0.min()), int(c0.min())
    height = min(int(r0.max()) + 2, src.height) - top
    width = min(int(c0.max()) + 2, src.width) - left
    band = src.read(1, window=Window(left, top, width, height), masked=True)
    grid = np.ma.filled(band.astype(np.float64), np.nan)
    if src.nodata is not None and not np.isnan(src.nodata):
        grid[grid == src.nodata] = np.nan
    r1, c1 = np.minimum(r0 + 1, top + height - 1), np.minimum(c0 + 1, left + width - 1)
    fr, fc = np.clip(row - r0, 0.0, 1.0), np.clip(col - c0, 0.0, 1.0)

    def post(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return grid[r - top, c - left]

    return (post(r0, c0) * (1 - fr) * (1 - fc) + post(r0, c1) * (1 - fr) * fc
            + post(r1, c0) * fr * (1 - fc) + post(r1, c1) * fr * fc)
