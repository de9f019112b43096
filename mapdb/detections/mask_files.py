"""Mask files read strictly: what GDAL is not asked to open, what it must read without a complaint, and georeferencing.

A mask is evidence the matcher trusts pixel by pixel, so a file that cannot be read whole is refused rather
than read as far as it goes:

* only regular files are opened (:func:`check_regular_file`): GDAL would block forever on a FIFO and
  read a device without end;
* a PNG must hold its chunks whole up to ``IEND`` (:func:`check_png_chunks`), and its pixels are decoded
  by libpng, which checks each chunk's CRC and the zlib stream (:func:`strict_gdal` turns GDAL's faster
  whole-image decoder off: it returns the rows of a truncated file that it could not decode, with no
  error);
* any warning GDAL gives while it opens or reads the file is an error (:func:`strict_gdal`);
* the georeference (:func:`georef`) is kept only when it is finite and plausible; otherwise it is
  dropped with a :class:`GeorefWarning` and the objects are still written.
"""

from __future__ import annotations

import logging
import math
import os
import stat
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..errors import ImageInputError, MapdbIOError
from .images import MAX_MAP_COORDINATE_M

__all__ = [
    "MAX_M_PER_PX",
    "GeorefWarning",
    "check_png_chunks",
    "check_regular_file",
    "georef",
    "strict_gdal",
]

# A ground pixel larger than this (1000 km) is no camera's; a georeference claiming it is damaged.
MAX_M_PER_PX = 1e6
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# IEND: length 0, its type, and the CRC of its type (a constant).
_PNG_IEND_CRC = b"\xaeB`\x82"


class GeorefWarning(UserWarning):
    """A mask's georeference is not finite or not plausible: it is dropped, the objects are still written."""


def check_regular_file(path: Path) -> None:
    """Refuse a mask that is missing, a directory or no regular file (a FIFO, a device), before any open.

    Raises
    ------
    MapdbIOError
        ``PATH: no such mask``, ``PATH: is a directory, not a mask`` or ``PATH: not a regular file``.
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise MapdbIOError(f"{path}: no such mask") from None
    except OSError as exc:
        raise MapdbIOError(f"{path}: cannot read mask ({exc.strerror or exc})") from None
    if stat.S_ISDIR(mode):
        raise MapdbIOError(f"{path}: is a directory, not a mask")
    if not stat.S_ISREG(mode):
        raise MapdbIOError(f"{path}: not a regular file")


def check_png_chunks(path: Path) -> None:
    """If ``path`` is a PNG, check that its chunks are whole and end with ``IEND``; other files pass.

    Only the 8-byte chunk headers are read (the data is skipped), so the cost follows the number of chunks.

    Raises
    ------
    ImageInputError
        ``PATH: cannot read its pixels (truncated or damaged PNG: ...)``.
    """
    with open(path, "rb") as f:
        if f.read(len(_PNG_SIGNATURE)) != _PNG_SIGNATURE:
            return
        size = os.fstat(f.fileno()).st_size
        position = len(_PNG_SIGNATURE)
        while True:
            head = f.read(8)
            if len(head) < 8:
                problem = f"its chunks end at byte {position} before IEND"
                break
            length = int.from_bytes(head[:4], "big")
            if head[4:] == b"IEND":
                if length == 0 and f.read(4) == _PNG_IEND_CRC:
                    return
                problem = "a damaged IEND chunk"
                break
            position += 12 + length
            if length >= 1 << 31 or position > size:
                problem = f"a {head[4:].decode('latin-1')!r} chunk runs past the end of the file ({size} bytes)"
                break
            f.seek(position)
    raise ImageInputError(f"{path}: cannot read its pixels (truncated or damaged PNG: {problem})")


class _Collect(logging.Handler):
    """Keeps the messages of the records it is given (rasterio logs GDAL's warnings as records)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(" ".join(record.getMessage().split()))


@contextmanager
def strict_gdal() -> Iterator[list[str]]:
    """A GDAL environment for reading a mask: the list it yields collects GDAL's warnings and errors.

    rasterio reports GDAL's warnings through the ``rasterio._env`` logger; the caller refuses the file if any
    was seen.  libpng decodes PNGs (``GDAL_PNG_WHOLE_IMAGE_OPTIM=NO``): the whole-image decoder GDAL uses
    otherwise fills a truncated file's missing rows without a word.
    """
    import rasterio

    logger = logging.getLogger("rasterio._env")
    handler = _Collect()
    level = logger.level
    logger.addHandler(handler)
    if logger.getEffectiveLevel() > logging.WARNING:
        logger.setLevel(logging.WARNING)
    try:
        with rasterio.Env(GDAL_PNG_WHOLE_IMAGE_OPTIM="NO"):
            yield handler.messages
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def georef(crs_wkt: str | None, transform: Any, width: int, height: int, source: str) -> dict[str, Any] | None:
    """Where the centre of a georeferenced raster is: map x, y (its CRS), lon, lat, heading, ground size of a pixel.

    ``heading_deg`` is where the image's up points, clockwise from the CRS's north (as a query answers).
    None when the raster has no georeference; also None, with a :class:`GeorefWarning` naming ``source``,
    when its numbers are not finite, its pixels have no size, its centre is further than
    :data:`~mapdb.detections.images.MAX_MAP_COORDINATE_M` from the CRS's origin or off the globe, or its
    pixel size exceeds :data:`MAX_M_PER_PX`.
    """
    from pyproj import CRS, Transformer
    from pyproj.exceptions import ProjError

    t = transform
    if crs_wkt is None or t.is_identity:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # inf - inf in the transform: caught below as non-finite
        try:
            crs = CRS.from_user_input(crs_wkt)
            cx, cy = t @ (width / 2.0, height / 2.0)
            lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(cx, cy)
            authority = crs.to_authority()
            out: dict[str, Any] = {"crs": ":".join(authority) if authority else crs.to_wkt(), "x": cx, "y": cy,
                                   "lon": lon, "lat": lat,
                                   "heading_deg": math.degrees(math.atan2(-t.b, -t.e)) % 360.0}
            if crs.is_projected:
                unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
                out["m_per_px"] = math.sqrt(abs(t.determinant)) * unit
        except (ProjError, ValueError, ArithmeticError) as exc:
            problem: str | None = f"cannot be converted ({' '.join(str(exc).split())[:120]})"
        else:
            problem = _implausible(out, t)
    if problem is not None:
        warnings.warn(f"{source}: georeference dropped: {problem}", GeorefWarning, stacklevel=2)
        return None
    return out


def _implausible(out: dict[str, Any], t: Any) -> str | None:
    """Why a computed georeference cannot be right, or None."""
    if not all(math.isfinite(v) for v in tuple(t)[:6]):
        return "its pixel size or position is not finite"
    if t.determinant == 0:
        return "its pixels have no area"
    if max(abs(out["x"]), abs(out["y"])) > MAX_MAP_COORDINATE_M:
        return f"its centre is more than {MAX_MAP_COORDINATE_M:.0e} from the origin of its CRS"
    if not all(math.isfinite(v) for v in out.values() if isinstance(v, float)):
        return "its centre has no finite longitude and latitude"
    if not (-180.0 <= out["lon"] <= 180.0 and -90.0 <= out["lat"] <= 90.0):
        return "its centre is not on the globe"
    if not 0.0 < out.get("m_per_px", 1.0) <= MAX_M_PER_PX:
        return f"a pixel of {out['m_per_px']:.3g} m"
    return None
