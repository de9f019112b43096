"""A vector layer's features read in batches: attribute columns and WKB geometries, a batch at a time.

A layer is never read whole: GDAL's formats (GeoPackage, FlatGeobuf, Shapefile, GeoJSON) through pyogrio's
Arrow stream (:func:`pyogrio.open_arrow`, ``batch_size`` rows, a bbox filter in the layer's CRS), GeoParquet
and Overture Maps buildings through pyarrow (:mod:`mapdb.sources.parquet`: row groups outside the box
skipped).  A batch holds :data:`BATCH_ROWS` features, so what a read holds does not grow with the layer.
CSV layers are read in chunks by :mod:`mapdb.sources.layers` itself (pandas' parser, as before).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS

from ..errors import SourceError
from .parquet import ParquetLayer, layer_boxes, open_parquet, parquet_batches

__all__ = ["BATCH_ROWS", "PARQUET_SUFFIXES", "VectorFile", "open_vector"]

# Features a batch (about 10-30 MB of geometries and attributes for building footprints).
BATCH_ROWS = 1 << 16
PARQUET_SUFFIXES = (".parquet", ".geoparquet")


@dataclass
class VectorFile:
    """A vector layer opened for reading in batches.

    ``crs`` is the file's CRS (None: it names none), ``columns`` its attribute columns, ``parquet`` the
    GeoParquet reader's state (None for GDAL's formats), ``note`` what the caller is to say once (a file read
    without pruning).
    """

    path: Path
    crs: CRS | None
    columns: list[str]
    parquet: ParquetLayer | None = None
    note: str | None = None

    @property
    def overture(self) -> bool:
        return self.parquet is not None and self.parquet.overture

    def batches(self, columns: list[str], box: tuple[float, float, float, float] | None,
                rows: int = BATCH_ROWS) -> Iterator[tuple[Any, np.ndarray]]:
        """Each batch's attribute ``columns`` (a pyarrow table or batch) and its geometries (object array of WKB,
        None where missing).  ``box`` (lon/lat, for GDAL's formats) keeps at least every feature whose envelope
        meets it; a Parquet file's row groups were chosen when it was opened."""
        if self.parquet is not None:
            yield from parquet_batches(self.parquet, columns, rows)
            return
        yield from _ogr_batches(self.path, [c for c in columns if c in self.columns], _ogr_box(self.crs, box), rows)

    def extent(self, crs: CRS) -> tuple[float, float, float, float] | None:
        """The box of the layer's non-point geometries whose coordinates are sound in ``crs``, read in batches
        (without any box): where a geographic layer's equal-area projection is centred (None: no such geometry)."""
        low, high = np.full(2, np.inf), np.full(2, -np.inf)
        for _, wkb in self.batches([], None):
            geoms = shapely.from_wkb(wkb, on_invalid="ignore")
            geoms = geoms[~(shapely.is_missing(geoms) | shapely.is_empty(geoms))]
            kind = shapely.get_type_id(geoms)
            geoms = geoms[(kind != shapely.GeometryType.POINT) & (kind != shapely.GeometryType.MULTIPOINT)]
            coords, owner = shapely.get_coordinates(geoms, return_index=True)
            bad = np.unique(owner[~sound_coordinates(crs, coords[:, 0], coords[:, 1])])
            if bad.size:
                geoms = np.delete(geoms, bad)
            if geoms.size:
                bounds = shapely.total_bounds(geoms)
                low, high = np.minimum(low, bounds[:2]), np.maximum(high, bounds[2:])
        return None if not np.isfinite(low).all() else (float(low[0]), float(low[1]), float(high[0]), float(high[1]))


def sound_coordinates(crs: CRS, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Finite, and in a geographic CRS within lon [-180, 180] and lat [-90, 90]."""
    ok = np.isfinite(x) & np.isfinite(y)
    if crs.is_geographic:
        ok &= (np.abs(x) <= 180.0) & (np.abs(y) <= 90.0)
    return ok


def open_vector(path: Path, box: tuple[float, float, float, float] | None) -> VectorFile:
    """Open a vector layer (not CSV) for reading in batches; SourceError if it is not a readable one."""
    if path.suffix.lower() in PARQUET_SUFFIXES:
        layer = open_parquet(path, box)
        note = None
        if box is not None and not layer.pruned:
            note = (f"{path.name}: no bbox statistics (a bbox column with per-row-group min/max): every row group "
                    "read, none skipped by --bbox")
        return VectorFile(path, layer.crs, [c for c in layer.columns if c != layer.geometry], layer, note)
    meta = _ogr_call(path, lambda: _ogr_info(path))
    return VectorFile(path, None if meta["crs"] is None else CRS.from_user_input(meta["crs"]),
                      [str(f) for f in meta["fields"]])


def geometries(path: Path, wkb: np.ndarray, counts: Any) -> np.ndarray:
    """WKB to shapely geometries; a ring that does not close is fixed by shapely where it can be (counted as
    repaired) or the feature lost (counted as invalid)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # shapely's note on a NaN coordinate: counted later
            return shapely.from_wkb(wkb)
    except shapely.errors.ShapelyError:
        broken = shapely.is_missing(shapely.from_wkb(wkb, on_invalid="ignore")) & np.asarray(
            [w is not None for w in wkb], bool)
        fixed = shapely.from_wkb(wkb, on_invalid="fix")
        counts["repaired_geometries"] += int((broken & ~shapely.is_missing(fixed)).sum())
        counts["invalid_geometries"] += int((broken & shapely.is_missing(fixed)).sum())
        return fixed


def _ogr_info(path: Path) -> dict[str, Any]:
    import pyogrio

    with pyogrio.open_arrow(path, batch_size=1, max_features=0, use_pyarrow=True) as (meta, _):
        return dict(meta)


def _ogr_call(path: Path, call: Callable[[], Any]) -> Any:
    """``call()``, GDAL's and pyarrow's errors on a file that is no readable layer made one SourceError."""
    import pyogrio.errors

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # GDAL's note on unclosed rings: counted by the caller
            return call()
    except (pyogrio.errors.DataSourceError, pyogrio.errors.DataLayerError, pyogrio.errors.GeometryError,
            pyogrio.errors.FieldError, shapely.errors.ShapelyError, ValueError, OSError) as exc:
        message = " ".join(str(exc).split()) or exc.__class__.__name__
        raise SourceError(f"{path}: not a readable vector layer ({message})") from None


def _ogr_batches(path: Path, columns: list[str], box: tuple[float, float, float, float] | None, rows: int
                 ) -> Iterator[tuple[Any, np.ndarray]]:
    import pyogrio

    def stream() -> Iterator[tuple[Any, np.ndarray]]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            with pyogrio.open_arrow(path, columns=columns, bbox=box, batch_size=rows, use_pyarrow=True) as (meta,
                                                                                                           reader):
                name = meta["geometry_name"] or "wkb_geometry"
                for batch in reader:
                    wkb = np.asarray(batch.column(name).to_numpy(zero_copy_only=False), dtype=object)
                    yield batch, wkb

    batches = stream()
    while True:
        item = _ogr_call(path, lambda: next(batches, None))
        if item is None:
            return
        yield item


def _ogr_box(crs: CRS | None, box: tuple[float, float, float, float] | None
             ) -> tuple[float, float, float, float] | None:
    """A lon/lat box as a box in the layer's CRS that holds at least every feature meeting it (None: no filter:
    no box, a box across the antimeridian, a layer without CRS)."""
    if box is None or box[0] > box[2]:
        return None
    boxes = layer_boxes(crs, box)
    return None if boxes is None else boxes[0]
