"""Export a map's objects to GIS formats, and summarise a map.

Every format holds one point a object with the columns ``label``, ``area_m2`` and ``x``, ``y`` (the
position in the map's CRS, exact to the quantum).  The geometry is in WGS 84 longitude/latitude for
GeoJSON, as RFC 7946 requires (and as web maps and ``geopandas.read_file`` without a CRS assume), and in
the map's CRS for GeoPackage, FlatGeobuf and GeoParquet, which name their CRS; either can be asked for.
CSV has no geometry: it holds ``x``, ``y`` and ``lon``, ``lat``.  A Shapefile (``.shp``, with its ``.shx``,
``.dbf``, ``.prj`` and ``.cpg`` beside it) is in the map's CRS.  ``"-"`` writes GeoJSON or CSV to standard
output (``stream_format``), whole once it is ready: an error leaves nothing written.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import Transformer

from ..errors import EmptyMapError, MapdbError, MapdbIOError
from ..objects import Objects
from ..outputs import atomic_path
from .queries import MapBase
from .reader import MetaMap

__all__ = ["EXPORT_CRS", "EXPORT_FORMATS", "SHAPEFILE_PARTS", "STREAM_FORMATS", "default_export_crs", "export_map",
           "map_info", "output_files", "select_lonlat"]

# file ending -> pyogrio driver (None: written by pandas/pyarrow instead)
EXPORT_FORMATS = {
    ".gpkg": "GPKG",
    ".geojson": "GeoJSON",
    ".fgb": "FlatGeobuf",
    ".parquet": None,
    ".geoparquet": None,
    ".csv": None,
    ".shp": "ESRI Shapefile",
}
# The files a Shapefile is beside its .shp (GDAL writes these for points with a CRS and UTF-8 text).
SHAPEFILE_PARTS = (".shx", ".dbf", ".prj", ".cpg")
# What "-" (standard output) can be: the text formats.
STREAM_FORMATS = (".geojson", ".csv")
# The CRS of an export's geometries: "lonlat" is WGS 84 longitude, latitude (EPSG:4326, x = longitude).
EXPORT_CRS = ("lonlat", "map")
LONLAT_CRS = "EPSG:4326"
# CSV lon/lat decimals: 1e-8 degrees is about a millimetre, well inside any map's quantum.
_CSV_DECIMALS = 8


def default_export_crs(output: str | Path, stream_format: str | None = None) -> str:
    """``"lonlat"`` for GeoJSON (RFC 7946 has no other CRS), ``"map"`` for the formats that name their CRS.

    Examples
    --------
    >>> default_export_crs("out.geojson"), default_export_crs("out.GPKG"), default_export_crs("out.csv")
    ('lonlat', 'map', 'map')
    >>> default_export_crs("-", "geojson"), default_export_crs("-", "csv")
    ('lonlat', 'map')
    """
    return "lonlat" if _suffix(output, stream_format) == ".geojson" else "map"


def _suffix(output: str | Path, stream_format: str | None) -> str:
    """The format's file ending: the output's, or ``stream_format``'s for ``"-"`` (GeoJSON by default)."""
    if str(output) == "-":
        return "." + (stream_format or "geojson").lower().lstrip(".")
    return Path(output).suffix.lower()


def output_files(output: str | Path) -> list[str]:
    """Every file an export to ``output`` writes: the file, and a Shapefile's parts beside it.

    Examples
    --------
    >>> output_files("roads.shp")
    ['roads.shp', 'roads.shx', 'roads.dbf', 'roads.prj', 'roads.cpg']
    >>> output_files("roads.gpkg"), output_files("-")
    (['roads.gpkg'], ['-'])
    """
    path = Path(output)
    if str(output) == "-" or path.suffix.lower() != ".shp":
        return [str(output)]
    return [str(output), *(str(path.with_suffix(part)) for part in SHAPEFILE_PARTS)]


def select_lonlat(m: MapBase, bbox: Sequence[float] | None) -> Objects:
    """All objects of a map, or exactly those whose lon/lat falls in ``bbox`` (see :meth:`MapBase.query_lonlat_bbox`).

    ``bbox`` may span the world, touch the poles or cross the antimeridian (``minlon > maxlon``).
    """
    return m.all() if bbox is None else m.query_lonlat_bbox(bbox)


def export_map(m: MetaMap, output: str | Path, bbox: Sequence[float] | None = None, crs: str | None = None, *,
               parents: bool = False, stream_format: str | None = None) -> int:
    """Write a map's objects, as points, to a file whose format follows its ending.

    The file is written under a temporary name and renamed, so a failure leaves nothing.

    Parameters
    ----------
    m : MetaMap
        An open map.
    output : str or Path
        ``.geojson``, ``.gpkg``, ``.fgb``, ``.parquet`` / ``.geoparquet``, ``.csv`` or ``.shp``; ``"-"``
        for standard output.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Only the objects whose lon/lat falls in this box.
    crs : {"lonlat", "map"}, optional
        The geometries' CRS: WGS 84 longitude/latitude (EPSG:4326) or the map's.  Default
        :func:`default_export_crs`.  A lon/lat GeoJSON is written as RFC 7946 says (no ``crs`` member, 7
        decimals: about 1 cm); one in the map's CRS carries GDAL's ``crs`` member (of the 2008 GeoJSON
        draft), which GDAL, QGIS and geopandas read.  CSV holds both.
    parents : bool
        Create the output's missing directories; without it a missing directory is an error, as in GDAL.
    stream_format : {"geojson", "csv"}, optional
        The format of ``"-"`` (default GeoJSON); ignored for a file, whose ending says.

    Returns
    -------
    int
        The number of objects written.

    Raises
    ------
    MapdbIOError
        If the ending is not one of the formats, the directory is missing, or the file cannot be written.
    EmptyMapError
        If no object lies in ``bbox``.
    ValueError
        If ``crs`` is not one of :data:`EXPORT_CRS`.
    """
    suffix = _suffix(output, stream_format)
    stream = str(output) == "-"
    if suffix not in (STREAM_FORMATS if stream else EXPORT_FORMATS):
        known = ", ".join(STREAM_FORMATS if stream else EXPORT_FORMATS)
        raise MapdbIOError(f"{output}: unknown export format {suffix.lstrip('.')!r} (use {known})")
    crs = default_export_crs(output, stream_format) if crs is None else crs
    if crs not in EXPORT_CRS:
        raise ValueError(f"export CRS {crs!r}: use one of {', '.join(EXPORT_CRS)}")
    objects = select_lonlat(m, bbox)
    if len(objects) == 0:
        raise EmptyMapError(f"{m.path}: no objects inside bbox {','.join(map(str, bbox or ()))}")
    frame, lon, lat = _frame(objects, crs)
    if stream:
        _write_stdout(frame, suffix, lon, lat)
    elif suffix == ".shp":
        _write_shapefile(frame, Path(output), lon, lat, parents)
    else:
        _write_file(frame, Path(output), lon, lat, parents)
    return len(objects)


def _write_file(frame: Any, output: Path, lon: np.ndarray, lat: np.ndarray, parents: bool) -> None:
    """One file, written under a temporary name and renamed."""
    with atomic_path(output, keep_suffix=True, parents=parents) as tmp:
        if tmp.is_file():  # not a device given as output (/dev/null), only our empty temporary file
            tmp.unlink()  # some drivers refuse to write over an existing (empty) file
        try:
            _write_frame(frame, tmp, output, lon, lat)
        except Exception as exc:
            if isinstance(exc, MapdbError):
                raise
            # (atomic_path puts the user's path in place of the temporary one the driver names)
            raise MapdbIOError(f"{output}: cannot write export ({exc})") from exc


def _write_stdout(frame: Any, suffix: str, lon: np.ndarray, lat: np.ndarray) -> None:
    """GeoJSON or CSV on standard output, written whole to a temporary file first (no partial output)."""
    with tempfile.TemporaryDirectory(prefix="mapdb-export-") as folder:
        tmp = Path(folder) / f"objects{suffix}"
        try:
            _write_frame(frame, tmp, Path(f"objects{suffix}"), lon, lat)
        except Exception as exc:
            if isinstance(exc, MapdbError):
                raise
            raise MapdbIOError(f"-: cannot write export ({exc})") from exc
        with open(tmp, "rb") as f:
            shutil.copyfileobj(f, sys.stdout.buffer)
        sys.stdout.buffer.flush()


def _write_shapefile(frame: Any, output: Path, lon: np.ndarray, lat: np.ndarray, parents: bool) -> None:
    """A Shapefile's parts written in a hidden folder beside ``output``, then each renamed into place (the
    ``.shp`` last, so that a reader never finds it without its parts)."""
    if parents:
        output.parent.mkdir(parents=True, exist_ok=True)
    try:
        folder = tempfile.mkdtemp(prefix=f".{output.name[:100]}.", suffix=".tmp", dir=output.parent)
    except OSError as exc:
        raise MapdbIOError(f"{output}: cannot write ({exc.strerror or exc})") from None
    try:
        tmp = Path(folder) / output.name
        try:
            _write_frame(frame, tmp, output, lon, lat)
        except Exception as exc:
            if isinstance(exc, MapdbError):
                raise
            raise MapdbIOError(f"{output}: cannot write export ({str(exc).replace(folder, str(output.parent))})") \
                from exc
        for part in (*SHAPEFILE_PARTS, output.suffix):
            if tmp.with_suffix(part).exists():
                os.replace(tmp.with_suffix(part), output.with_suffix(part))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _frame(objects: Objects, crs: str) -> tuple[Any, np.ndarray, np.ndarray]:
    """The export's table (points in ``crs``, "lonlat" or "map"), and every object's lon/lat."""
    import geopandas as gpd

    to_lonlat = Transformer.from_crs(objects.crs, LONLAT_CRS, always_xy=True)
    lon, lat = (np.asarray(v) for v in to_lonlat.transform(objects.x, objects.y))
    frame = objects.to_geodataframe().assign(x=objects.x, y=objects.y)
    columns = ["label", "area_m2", "x", "y", "geometry"]
    if objects.elevation is not None:  # a map with elevation (version 2): the ground's height, empty if unknown
        frame = frame.assign(elevation_m=objects.elevation)
        columns.insert(2, "elevation_m")
    if crs == "lonlat":
        frame = frame.set_geometry(gpd.points_from_xy(lon, lat), crs=LONLAT_CRS)
    return frame[columns], lon, lat


def _write_frame(frame: Any, tmp: Path, output: Path, lon: np.ndarray, lat: np.ndarray) -> None:
    suffix = output.suffix.lower()
    if suffix == ".csv":
        table = frame.drop(columns="geometry").assign(lon=np.round(lon, _CSV_DECIMALS),
                                                      lat=np.round(lat, _CSV_DECIMALS))
        table.to_csv(tmp, index=False)
    elif EXPORT_FORMATS[suffix] is None:
        frame.to_parquet(tmp)
    else:
        # the layer is named after the requested file, not the temporary one
        layer = re.sub(r"\W", "_", output.stem) or "objects"
        # GDAL's RFC 7946 mode: no "crs" member, 7 decimals; it applies only to lon/lat (GDAL would reproject)
        rfc7946 = {"RFC7946": "YES"} if suffix == ".geojson" and frame.crs.to_epsg() == 4326 else {}
        frame.to_file(tmp, driver=EXPORT_FORMATS[suffix], engine="pyogrio", layer=layer, **rfc7946)


def map_info(m: MetaMap, verify: bool = True) -> dict[str, Any]:
    """What ``mapdb info`` reports; ``verify`` reads and checks every page first.

    Every value comes from fields the reader has checked (``docs/format.md``); the optional ones
    (``software``, ``created``, ``bounds_lonlat``, ``sources``, ``build``) may be absent or null in a
    map, and are reported as None, [] or {} then, so that a printer needs no further checks.
    """
    if verify:
        m.verify()
    header = m.metadata
    return {**_basic_info(m, header), **({"elevation": elevation_info(m)} if m.has_elevation else {})}


def elevation_info(m: MetaMap) -> dict[str, Any]:
    """A map's elevation (version 2): its code step and cell (metres), the objects with and without an
    elevation, and the lowest, median and highest one (metres; None when no object has one)."""
    z = np.concatenate([np.zeros(0), *(o.elevation for o in m.scan() if o.elevation is not None)])
    known = z[np.isfinite(z)]
    low, mid, high = (float(v) for v in np.percentile(known, [0, 50, 100])) if known.size else (None,) * 3
    return {"step_m": m.elevation_step, "cell_m": float(m.metadata["elevation_cell"]) * m.quantum,
            "known": int(known.size), "unknown": int(z.size - known.size), "min_m": low, "median_m": mid,
            "max_m": high}


def _basic_info(m: MetaMap, header: dict[str, Any]) -> dict[str, Any]:
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
