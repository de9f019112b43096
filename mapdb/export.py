"""Export a map's objects to GIS formats, and summarise a map."""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

from .errors import EmptyMapError, MapdbIOError
from .objects import Objects
from .store import MetaMap

__all__ = ["EXPORT_FORMATS", "export_map", "map_info", "select_lonlat"]

# file ending -> pyogrio driver (None: written by pandas/pyarrow instead)
EXPORT_FORMATS = {
    ".gpkg": "GPKG",
    ".geojson": "GeoJSON",
    ".fgb": "FlatGeobuf",
    ".parquet": None,
    ".geoparquet": None,
    ".csv": None,
}


def select_lonlat(m: MetaMap, bbox: tuple[float, float, float, float] | None) -> Objects:
    """All objects of a map, or those whose lon/lat falls in ``bbox``."""
    if bbox is None:
        return m.all()
    to_map = Transformer.from_crs("EPSG:4326", m.crs, always_xy=True)
    found = m.query_bbox(*to_map.transform_bounds(*bbox, densify_pts=21))
    lon, lat = Transformer.from_crs(m.crs, "EPSG:4326", always_xy=True).transform(found.x, found.y)
    minlon, minlat, maxlon, maxlat = bbox
    return found.take((lon >= minlon) & (lon <= maxlon) & (lat >= minlat) & (lat <= maxlat))


def export_map(m: MetaMap, output: str | Path, bbox: tuple[float, float, float, float] | None = None) -> int:
    """Write a map's objects (points in the map's CRS) to a file chosen by its ending.

    Columns: ``label``, ``area_m2``, ``x``, ``y`` (and ``lon``, ``lat`` in CSV). The
    file is written under a temporary name and renamed, so a failure leaves nothing.
    Returns the number of objects written.
    """
    import geopandas as gpd

    output = Path(output)
    suffix = output.suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise MapdbIOError(f"{output}: unknown export format (use {', '.join(EXPORT_FORMATS)})")
    objects = select_lonlat(m, bbox)
    if len(objects) == 0:
        raise EmptyMapError(f"{m.path}: no objects inside bbox {','.join(map(str, bbox or ()))}")
    columns = {"label": objects.names().astype(str), "area_m2": objects.area, "x": objects.x, "y": objects.y}
    frame = gpd.GeoDataFrame(columns, geometry=gpd.points_from_xy(objects.x, objects.y), crs=m.crs)
    output.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{output.stem}.", suffix=suffix, dir=output.parent)
    os.close(fd)
    os.unlink(tmp)  # some drivers refuse to write over an existing (empty) file
    try:
        if suffix == ".csv":
            lon, lat = Transformer.from_crs(m.crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
            table = frame.drop(columns="geometry").assign(lon=np.round(lon, 8), lat=np.round(lat, 8))
            table.to_csv(tmp, index=False)
        elif EXPORT_FORMATS[suffix] is None:
            frame.to_parquet(tmp)
        else:
            # the layer is named after the requested file, not the temporary one
            layer = re.sub(r"\W", "_", output.stem) or "objects"
            frame.to_file(tmp, driver=EXPORT_FORMATS[suffix], engine="pyogrio", layer=layer)
        os.replace(tmp, output)
    except Exception as exc:
        Path(tmp).unlink(missing_ok=True)
        raise MapdbIOError(f"{output}: cannot write export ({exc})") from exc
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return len(objects)


def map_info(m: MetaMap, verify: bool = True) -> dict[str, Any]:
    """What ``mapdb info`` reports; ``verify`` reads and checks every page first."""
    if verify:
        m.verify()
    header = m.metadata
    return {
        "path": str(m.path),
        "format_version": header["format_version"],
        "software": header.get("software"),
        "created": header.get("created"),
        "crs": header["crs"],
        "quantum_m": m.quantum,
        "bounds": list(m.bounds),
        "bounds_lonlat": header.get("bounds_lonlat"),
        "objects": len(m),
        "labels": m.label_counts,
        "pages": m.page_count,
        "file_bytes": m.file_size,
        "bytes_per_object": round(m.file_size / max(len(m), 1), 3),
        "sources": header.get("sources", []),
        "build": header.get("build", {}),
    }
