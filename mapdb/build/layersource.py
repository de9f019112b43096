"""A layer source read for a build: a batch at a time into a spool, its buildings' footprints kept for blocks.

Used by :func:`mapdb.build.pipeline.read_one_source`.  Neither the objects nor the footprints of a layer are
held whole: the objects go to an :class:`~mapdb.sources.spool.ObjectSpool` (a file in the build's temporary
directory above the spool threshold) batch by batch as they are read, and the footprints past
:data:`OUTLINES_IN_MEMORY` to tile files (:mod:`mapdb.build.tiles`).
"""

from __future__ import annotations

import functools
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer

from ..labels import LabelTable
from ..objects import Objects
from ..progress import Progress
from ..sources.layers import layer_batches
from ..sources.spool import ObjectSpool
from .blocks import BUILDING_LABEL, BuildingOutlines, forms_blocks
from .tiles import OUTLINES_IN_MEMORY, SpillingOutlines

__all__ = ["OUTLINES_IN_MEMORY", "layer_spool", "source_outlines"]


def source_outlines(table: LabelTable, gap: float | None, scratch: str | None, memory: int | None = None
                    ) -> BuildingOutlines | None:
    """What keeps a source's building footprints for its blocks (None: no blocks): in memory, or, given a
    ``scratch`` directory, in tile files there past ``memory`` (default :data:`OUTLINES_IN_MEMORY`) footprints
    (:mod:`mapdb.build.tiles`)."""
    if not forms_blocks(table.labels, gap):
        return None
    code = table.code(BUILDING_LABEL)
    return BuildingOutlines(code) if scratch is None else SpillingOutlines(code, scratch, memory)


def layer_spool(path: Path, table: LabelTable, options: dict[str, Any], counts: Counter[str],
                outlines: BuildingOutlines | None, say: Progress | None, spool_dir: str | None) -> ObjectSpool:
    """A layer's objects in lon/lat, read a batch at a time into a spool (a file in ``spool_dir``)."""
    spool = ObjectSpool(table.labels, "EPSG:4326", spool_dir, "layer-")
    for objects in layer_batches(path, table.labels, options["label_column"], options["layer_crs"], options["bbox"],
                                 counts, label=options["label"], label_map=options["label_map"],
                                 outlines=outlines.add_geometries if outlines is not None else None, notes=say):
        lon, lat = _to_lonlat(objects) if len(objects) else (objects.x, objects.y)
        spool.add(Objects(lon, lat, objects.label, objects.area, objects.labels, "EPSG:4326"))
    return spool


def _to_lonlat(objects: Objects) -> tuple[np.ndarray, np.ndarray]:
    to_lonlat = _lonlat_transformer(str(objects.crs))
    if to_lonlat is None:
        return objects.x, objects.y
    lon, lat = to_lonlat.transform(objects.x, objects.y)
    return np.asarray(lon), np.asarray(lat)


@functools.lru_cache(maxsize=4)
def _lonlat_transformer(crs: str) -> Transformer | None:
    """From a layer's CRS to lon/lat (None: it is lon/lat), made once for all its batches."""
    if CRS.from_user_input(crs).equals(CRS.from_epsg(4326), ignore_axis_order=True):
        return None
    return Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
