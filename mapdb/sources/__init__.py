"""Readers that turn source files into :class:`~mapdb.objects.Objects`.

Each reader returns objects in its source's own CRS (OSM: lon/lat); the
builder reprojects.  The kind of a source is recognised by its file name.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import SourceError
from ..labels import LabelTable
from ..objects import Objects
from .landcover import RASTER_SUFFIXES, read_landcover
from .layers import LAYER_SUFFIXES, read_layer
from .osm import OSM_SUFFIXES, read_osm

__all__ = ["SOURCE_KINDS", "read_source", "source_kind"]

SOURCE_KINDS = {"osm": OSM_SUFFIXES, "landcover": RASTER_SUFFIXES, "layer": LAYER_SUFFIXES}


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
    min_area_m2: float = 10_000.0,
    label_column: str = "label",
    layer_crs: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> Objects:
    """Read one source of any kind, labelled with ``table``; each reader checks its own file."""
    kind = source_kind(path)
    if kind == "osm":
        return read_osm(path, table, bbox=bbox, progress=progress)
    if kind == "landcover":
        return read_landcover(path, table, classes=raster_classes, min_area_m2=min_area_m2, bbox=bbox,
                              progress=progress)
    return read_layer(path, table.labels, label_column=label_column, crs=layer_crs, bbox=bbox)
