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

The modules: :mod:`.reader` (:func:`read_landcover`, the raster's checks, pixel areas, the scan),
:mod:`.tiles` (tiles of whole blocks, the blocks a sparse GeoTIFF stores), :mod:`.classes` (pixel
codes to label masks) and :mod:`.patches` (components joined across tiles).  This package re-exports
the public names.
"""

from __future__ import annotations

from ..suffixes import RASTER_SUFFIXES
from .reader import is_raster_path, raster_class_table_name, read_landcover

__all__ = ["RASTER_SUFFIXES", "is_raster_path", "read_landcover", "raster_class_table_name"]
