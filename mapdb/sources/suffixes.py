"""File-name suffixes of the raster sources, known without importing their reader.

The land-cover reader imports rasterio and scipy.ndimage (0.3-0.6 s in a fresh process); a build of OSM
extracts only needs to know that its files are not rasters.
"""

from __future__ import annotations

__all__ = ["RASTER_SUFFIXES"]

RASTER_SUFFIXES = (".tif", ".tiff", ".gtiff")
