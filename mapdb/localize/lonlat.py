"""Map coordinates to lon/lat and back, for answers and priors (pyproj imported on first use, not with the module)."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

__all__ = ["to_lonlat", "transformer"]


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
