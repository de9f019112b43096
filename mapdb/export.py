"""Export a map's objects to GIS formats, and summarise a map."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

from .errors import EmptyMapError, MapdbError, MapdbIOError
from .objects import Objects
from .outputs import atomic_path
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
    """All objects of a map, or exactly those whose lon/lat falls in ``bbox``.

    ``bbox`` may span the world, touch the poles or cross the antimeridian (``minlon > maxlon``).
    The pages read are found by :func:`mapdb.geo.projected_window`; the selection itself is made on
    each object's own lon/lat, so it does not depend on how well the box projects.
    """
    from .geo import check_bbox, in_bbox, projected_window

    if bbox is None:
        return m.all()
    bbox = check_bbox(bbox)
    window = projected_window(m.crs, bbox, within=m.bounds)
    if window is None:
        return Objects.empty(m.labels, m.crs)
    found = m.query_bbox(*window)
    lon, lat = Transformer.from_crs(m.crs, "EPSG:4326", always_xy=True).transform(found.x, found.y)
    return found.take(in_bbox(bbox, lon, lat))


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
    with atomic_path(output, keep_suffix=True) as tmp:
        if tmp.is_file():  # not a device given as output (/dev/null), only our empty temporary file
            tmp.unlink()  # some drivers refuse to write over an existing (empty) file
        try:
            _write_frame(frame, tmp, output, m.crs)
        except Exception as exc:
            if isinstance(exc, MapdbError):
                raise
            # (atomic_path puts the user's path in place of the temporary one the driver names)
            raise MapdbIOError(f"{output}: cannot write export ({exc})") from exc
    return len(objects)


def _write_frame(frame: Any, tmp: Path, output: Path, crs: str) -> None:
    suffix = output.suffix.lower()
    if suffix == ".csv":
        to_lonlat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lon, lat = to_lonlat.transform(frame["x"].to_numpy(), frame["y"].to_numpy())
        table = frame.drop(columns="geometry").assign(lon=np.round(lon, 8), lat=np.round(lat, 8))
        table.to_csv(tmp, index=False)
    elif EXPORT_FORMATS[suffix] is None:
        frame.to_parquet(tmp)
    else:
        # the layer is named after the requested file, not the temporary one
        layer = re.sub(r"\W", "_", output.stem) or "objects"
        frame.to_file(tmp, driver=EXPORT_FORMATS[suffix], engine="pyogrio", layer=layer)


def map_info(m: MetaMap, verify: bool = True) -> dict[str, Any]:
    """What ``mapdb info`` reports; ``verify`` reads and checks every page first.

    Every value comes from fields the reader has checked (``docs/format.md``); the optional ones
    (``software``, ``created``, ``bounds_lonlat``, ``sources``, ``build``) may be absent or null in a
    map, and are reported as None, [] or {} then, so that a printer needs no further checks.
    """
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
        "merged_duplicates": header.get("merged_duplicates"),
        "sources": header.get("sources") or [],
        "build": header.get("build") or {},
    }
