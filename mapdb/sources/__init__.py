"""Readers that turn source files into :class:`~mapdb.objects.Objects`.

Each reader returns objects in its source's own CRS (OSM: lon/lat); the
builder reprojects.  The kind of a source is recognised by its file name.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import SourceError
from ..labels import LabelTable
from ..objects import Objects
from .layers import LAYER_SUFFIXES, LayerOutlineSink, read_layer
from .osm.files import OSM_SUFFIXES
from .osm.reader import read_osm
from .suffixes import RASTER_SUFFIXES

if TYPE_CHECKING:
    from ..classmap import ClassTable

__all__ = ["DEFAULT_MIN_AREA_M2", "SKIPPED_KINDS", "SOURCE_KINDS", "read_source", "source_kind"]

# Land-cover patches smaller than this (m^2) are dropped by the raster reader (read_landcover's min_area_m2).
DEFAULT_MIN_AREA_M2 = 10_000.0

SOURCE_KINDS = {"osm": OSM_SUFFIXES, "landcover": RASTER_SUFFIXES, "layer": LAYER_SUFFIXES}

# What a reader may skip or repair instead of failing, as counted in ``read_source(counts=...)``.
SKIPPED_KINDS = {
    "invalid_coordinates": "objects skipped: a coordinate not a finite number, or outside lon [-180, 180] / "
                           "lat [-90, 90]",
    "unclosed_rings": "ways tagged as areas skipped: they do not close",
    "missing_nodes": "ways tagged as areas skipped: a node missing from the extract (cut by a clipped extract's "
                     "border)",
    "incomplete_relations": "multipolygon relations skipped: a member way or node missing from the extract (cut "
                            "by a clipped extract's border) or out of range",
    "invalid_geometries": "invalid polygons skipped: nothing with an area left after repair",
    "repaired_geometries": "invalid polygons repaired (shapely make_valid) and kept",
    "outside_crs": "objects skipped: no position in the map's CRS",
    "unmapped_labels": "layer features skipped: their value is not in the --label-map",
    "missing_geometries": "layer features skipped: a label but no geometry (null or empty)",
}


def source_kind(path: str | Path) -> str:
    """``"osm"``, ``"landcover"`` or ``"layer"`` from the file name.

    Examples
    --------
    >>> source_kind("monaco.osm.pbf"), source_kind("clc.TIF"), source_kind("mine.gpkg")
    ('osm', 'landcover', 'layer')
    """
    name = Path(path).name.lower()
    for kind, suffixes in SOURCE_KINDS.items():
        if name.endswith(suffixes):
            return kind
    known = ", ".join(s for suffixes in SOURCE_KINDS.values() for s in suffixes)
    raise SourceError(f"{path}: unknown kind of source (expected one of {known})")


def read_source(
    path: str | Path,
    table: LabelTable,
    *,
    bbox: tuple[float, float, float, float] | None = None,
    raster_classes: str | None = None,
    min_area_m2: float = DEFAULT_MIN_AREA_M2,
    label_column: str = "label",
    layer_crs: str | None = None,
    label: str | None = None,
    label_map: ClassTable | None = None,
    progress: Callable[[str], None] | None = None,
    counts: Counter[str] | None = None,
    outlines: LayerOutlineSink | None = None,
) -> Objects:
    """Read one source of any kind, labelled with ``table``; each reader checks its own file.

    ``label`` and ``label_map`` label a layer's features (:func:`~mapdb.sources.layers.read_layer`).
    ``counts`` is incremented with what the reader skipped or repaired (keys of :data:`SKIPPED_KINDS`).
    ``outlines`` is handed a layer's geometries (:func:`~mapdb.sources.layers.read_layer`); an OSM source's
    go through :func:`~mapdb.sources.osm.reader.read_osm_spooled`, a raster has none.
    """
    kind = source_kind(path)
    if kind == "osm":
        return read_osm(path, table, bbox=bbox, progress=progress, counts=counts)
    if kind == "landcover":
        from .landcover.reader import read_landcover  # rasterio and scipy.ndimage: only a build with rasters pays

        return read_landcover(path, table, classes=raster_classes, min_area_m2=min_area_m2, bbox=bbox,
                              progress=progress)
    return read_layer(path, table.labels, label_column=label_column, crs=layer_crs, bbox=bbox, counts=counts,
                      label=label, label_map=label_map, outlines=outlines)
