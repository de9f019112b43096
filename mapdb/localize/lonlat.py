"""Map coordinates to lon/lat and back, for answers and priors (pyproj imported on first use, not with the module)."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

__all__ = ["to_lonlat", "to_lonlat_many", "transformer"]


@lru_cache(maxsize=16)
def transformer(src: str, dst: str) -> Any:
    """The pyproj transformer from ``src`` to ``dst`` (x, y order: lon before lat), one per pair of CRSs."""
    from pyproj import Transformer

    return Transformer.from_crs(src, dst, always_xy=True)


def to_lonlat(crs: str, x: float, y: float) -> tuple[float | None, float | None]:
    """A map point's lon, lat (degrees, 8 decimals), or None, None where the CRS is unknown or cannot say."""
    if not crs:
        return None, None
    try:
        lon, lat = transformer(crs, "EPSG:4326").transform(x, y)
    except Exception:  # pyproj raises several kinds; lon/lat is a convenience, not the answer
        return None, None
    if not (math.isfinite(lon) and math.isfinite(lat)):
        return None, None
    return float(round(lon, 8)), float(round(lat, 8))


def to_lonlat_many(crs: str, x: list[float], y: list[float]) -> list[tuple[float | None, float | None]]:
    """:func:`to_lonlat` of several map points in one transform (an answer's centre and footprint corners: one
    call into PROJ instead of five), the same numbers point by point.

    Examples
    --------
    >>> to_lonlat_many("EPSG:32631", [500000.0, 500000.0], [0.0, float("inf")])
    [(3.0, 0.0), (None, None)]
    >>> to_lonlat_many("", [1.0], [2.0])
    [(None, None)]
    """
    if not crs:
        return [(None, None)] * len(x)
    try:
        lons, lats = transformer(crs, "EPSG:4326").transform(x, y)
    except Exception:  # one point's failure must not take the others': point by point
        return [to_lonlat(crs, u, v) for u, v in zip(x, y, strict=True)]
    # Python floats, rounded as to_lonlat rounds them (Python's round, not numpy's).
    return [(float(round(lon, 8)), float(round(lat, 8))) if math.isfinite(lon) and math.isfinite(lat)
            else (None, None) for lon, lat in zip(map(float, lons), map(float, lats), strict=True)]
