"""GeoParquet layers read in batches with pyarrow, row groups outside a box skipped; Overture Maps buildings.

A GeoParquet file (``geo`` metadata, WKB geometries) is read a batch of rows at a time
(:func:`parquet_batches`), never whole.  With a box, row groups are skipped from the statistics of the file's
bbox column (the GeoParquet 1.1 ``covering``, or a struct column ``bbox`` of ``xmin, ymin, xmax, ymax``):
a row group whose rows' boxes all lie outside the box is not read at all.  A file without such statistics is
read whole, and the caller says so once.

**Overture Maps buildings** (theme ``buildings``, type ``building``) are GeoParquet files with the columns
``id``, ``geometry`` (WKB, lon/lat), ``bbox`` (struct ``xmin, ymin, xmax, ymax``), ``subtype``, ``class``,
``height`` and more.  A Parquet file with a ``bbox`` column and a ``subtype`` or ``class`` column is read as
one (:func:`is_overture`): without ``geo`` metadata its geometries are taken as WKB in lon/lat, as Overture
writes them, and one without ``id``, ``geometry`` or a ``bbox`` struct of the four bounds is refused in one
line before anything is read.  Every Overture building is labelled ``building`` (:data:`OVERTURE_LABEL`):
mapdb's OSM rules label every ``building=*`` so whatever its value, and Overture's ``subtype`` and ``class``
are that very value, grouped; a ``--label-map`` whose ``column`` is ``class`` or ``subtype`` maps them to
other labels (``class = "parking"`` to ``parking``, say) as it maps any layer's column.  ``height`` is not
used: a map stores positions, labels and areas.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer

from ..errors import SourceError
from ..labels import BUILDING_LABEL

__all__ = ["BBOX_FIELDS", "OVERTURE_COLUMNS", "OVERTURE_LABEL", "ParquetLayer", "is_overture", "layer_boxes",
           "open_parquet", "parquet_batches"]

# The label of every Overture building (module notes), and the columns an Overture buildings file must have.
OVERTURE_LABEL = BUILDING_LABEL
OVERTURE_COLUMNS = ("id", "geometry", "bbox")
BBOX_FIELDS = ("xmin", "ymin", "xmax", "ymax")
# Overture writes its boxes as float32 rounded outwards; a box's edge is widened by this (degrees or the
# layer's units) before row groups are compared with it, so that rounding never skips a row that belongs.
_BOX_SLACK = 1e-6


@dataclass
class ParquetLayer:
    """What :func:`open_parquet` found: the file, its geometry column, CRS (None: not named), bbox columns
    (paths of the four bounds, or None), whether it is an Overture file, and the row groups to read."""

    path: Path
    handle: Any
    geometry: str
    crs: CRS | None
    bbox: tuple[tuple[str, ...], ...] | None
    overture: bool
    columns: list[str]
    row_groups: list[int] = field(default_factory=list)
    pruned: bool = False  # whether the statistics could choose the row groups (False: all are read)


def is_overture(columns: list[str]) -> bool:
    """Whether a Parquet file's top-level columns are those of Overture buildings (``bbox`` and ``subtype`` or
    ``class``).

    Examples
    --------
    >>> is_overture(["id", "geometry", "bbox", "subtype", "class", "height"]), is_overture(["geometry", "label"])
    (True, False)
    """
    return "bbox" in columns and ("subtype" in columns or "class" in columns)


def open_parquet(path: Path, box: tuple[float, float, float, float] | None) -> ParquetLayer:
    """The file opened and checked, and the row groups that may hold features inside ``box`` (lon/lat).

    Raises
    ------
    SourceError
        Not a Parquet file; no ``geo`` metadata (unless Overture); an Overture file without its columns; a
        geometry encoding other than WKB.
    """
    import pyarrow.parquet as pq

    try:
        handle = pq.ParquetFile(path)
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: not a readable vector layer ({' '.join(str(exc).split())})") from None
    schema = handle.schema_arrow
    columns = [str(name) for name in schema.names]
    overture = is_overture(columns)
    geo = _geo_metadata(path, schema.metadata or {}, overture)
    if overture:
        _check_overture(path, schema, columns)
    name = geo.get("primary_column", "geometry")
    spec = geo.get("columns", {}).get(name, {})
    if name not in columns:
        raise SourceError(f"{path}: no geometry column {name!r} (columns: {', '.join(columns)})")
    if spec.get("encoding", "WKB").upper() != "WKB":
        raise SourceError(f"{path}: geometry encoding {spec.get('encoding')!r} is not read in batches; write the "
                          "file with WKB geometries (geopandas: to_parquet(geometry_encoding='WKB'))")
    # GeoParquet: a missing "crs" is OGC:CRS84 (lon/lat), an explicit null an unknown CRS.
    crs = CRS.from_user_input("OGC:CRS84") if "crs" not in spec else _crs(path, spec["crs"])
    layer = ParquetLayer(path, handle, name, crs, _bbox_columns(schema, spec), overture, columns)
    layer.row_groups, layer.pruned = _row_groups(layer, box)
    return layer


def parquet_batches(layer: ParquetLayer, columns: list[str], rows: int) -> Iterator[tuple[Any, np.ndarray]]:
    """The chosen row groups, ``rows`` at a time: each batch's other ``columns`` (a pyarrow table) and its
    geometries as an object array of WKB (None where missing)."""
    import pyarrow.parquet as pq

    wanted = [c for c in dict.fromkeys([layer.geometry, *columns]) if c in layer.columns]
    if not layer.row_groups:
        return
    try:
        # A reader of its own: two passes at once over one ParquetFile (a layer's extent read while its
        # batches wait) would share its position.
        handle = pq.ParquetFile(layer.path)
        # One iterator a row group: a single one over all of them holds more memory the more it has read
        # (5M rows of footprints: 405 MB against 174 MB for 1M; one a row group: 120 MB for both).
        for group in layer.row_groups:
            for batch in handle.iter_batches(batch_size=rows, row_groups=[group], columns=wanted,
                                             use_threads=False):
                wkb = batch.column(layer.geometry).to_numpy(zero_copy_only=False)
                yield batch, np.asarray(wkb, dtype=object)
    except (OSError, ValueError) as exc:  # pyarrow's errors on a damaged file derive from these
        raise SourceError(f"{layer.path}: not a readable vector layer ({' '.join(str(exc).split())})") from None


def _geo_metadata(path: Path, metadata: dict[bytes, bytes], overture: bool) -> dict[str, Any]:
    raw = metadata.get(b"geo")
    if raw is None:
        if overture:  # Overture's own files carry it; a copy without it is still WKB in lon/lat
            return {"primary_column": "geometry", "columns": {"geometry": {"encoding": "WKB"}}}
        raise SourceError(f"{path}: not a readable vector layer (a Parquet file without GeoParquet 'geo' metadata)")
    try:
        geo = json.loads(raw)
    except ValueError:
        raise SourceError(f"{path}: GeoParquet 'geo' metadata is not JSON") from None
    if not isinstance(geo, dict) or not isinstance(geo.get("columns", {}), dict):
        raise SourceError(f"{path}: GeoParquet 'geo' metadata is not an object with 'columns'")
    return geo


def _check_overture(path: Path, schema: Any, columns: list[str]) -> None:
    """An Overture buildings file must have ``id``, ``geometry`` (binary) and ``bbox`` (struct of the four
    bounds): one line naming what is missing."""
    import pyarrow as pa

    missing = [c for c in OVERTURE_COLUMNS if c not in columns]
    if missing:
        raise SourceError(f"{path}: an Overture buildings file without column(s) {', '.join(missing)} "
                          f"(columns: {', '.join(columns)})")
    if not pa.types.is_binary(schema.field("geometry").type) and not pa.types.is_large_binary(
            schema.field("geometry").type):
        raise SourceError(f"{path}: Overture column 'geometry' is {schema.field('geometry').type}, not WKB binary")
    bbox = schema.field("bbox").type
    names = [bbox.field(i).name for i in range(bbox.num_fields)] if pa.types.is_struct(bbox) else []
    if not set(BBOX_FIELDS) <= set(names):
        raise SourceError(f"{path}: Overture column 'bbox' is {bbox}, not a struct of {', '.join(BBOX_FIELDS)}")


def _crs(path: Path, value: Any) -> CRS | None:
    if value is None:
        return None
    try:
        return CRS.from_json_dict(value) if isinstance(value, dict) else CRS.from_user_input(value)
    except Exception:  # pyproj raises CRSError, or TypeError on a value of the wrong kind
        raise SourceError(f"{path}: GeoParquet 'crs' is not a CRS") from None


def _bbox_columns(schema: Any, spec: dict[str, Any]) -> tuple[tuple[str, ...], ...] | None:
    """The column paths of the four bounds: the GeoParquet 1.1 covering, else a struct column ``bbox``."""
    covering = spec.get("covering", {}).get("bbox") if isinstance(spec.get("covering"), dict) else None
    if isinstance(covering, dict) and all(isinstance(covering.get(k), list) for k in BBOX_FIELDS):
        return tuple(tuple(str(p) for p in covering[k]) for k in BBOX_FIELDS)
    import pyarrow as pa

    if "bbox" in schema.names and pa.types.is_struct(schema.field("bbox").type):
        fields = {schema.field("bbox").type.field(i).name for i in range(schema.field("bbox").type.num_fields)}
        if set(BBOX_FIELDS) <= fields:
            return tuple(("bbox", k) for k in BBOX_FIELDS)
    return None


def _row_groups(layer: ParquetLayer, box: tuple[float, float, float, float] | None) -> tuple[list[int], bool]:
    """The row groups whose bbox statistics meet ``box`` (lon/lat; all of them without a box), and whether the
    statistics decided it (False: no box, no bbox column or a row group without statistics)."""
    meta = layer.handle.metadata
    every = list(range(meta.num_row_groups))
    if box is None or layer.bbox is None:
        return every, False
    boxes = layer_boxes(layer.crs, box)
    if boxes is None:
        return every, False
    paths = [".".join(p) for p in layer.bbox]
    leaf = {meta.schema.column(i).path: i for i in range(meta.num_columns)}
    if not all(p in leaf for p in paths):
        return every, False
    kept = []
    for g in every:
        group = meta.row_group(g)
        stats = [group.column(leaf[p]).statistics for p in paths]
        if any(s is None or not s.has_min_max for s in stats):
            return every, False
        extent = (stats[0].min, stats[1].min, stats[2].max, stats[3].max)
        if any(_meets(extent, b) for b in boxes):
            kept.append(g)
    return kept, True


def layer_boxes(crs: CRS | None, box: tuple[float, float, float, float]
                ) -> list[tuple[float, float, float, float]] | None:
    """``box`` (lon/lat; ``minlon > maxlon`` crosses the antimeridian) as boxes in the layer's CRS that hold its
    whole image, widened a little; None when the CRS is unknown or the box has no finite image there.

    Examples
    --------
    >>> layer_boxes(CRS.from_epsg(4326), (170.0, -10.0, -170.0, 10.0))[1]
    (-180.000001, -10.000001, -169.999999, 10.000001)
    """
    if crs is None:
        return None
    parts = [box] if box[0] <= box[2] else [(box[0], box[1], 180.0, box[3]), (-180.0, box[1], box[2], box[3])]
    if crs.is_geographic:
        return [(p[0] - _BOX_SLACK, p[1] - _BOX_SLACK, p[2] + _BOX_SLACK, p[3] + _BOX_SLACK) for p in parts]
    to_layer = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    out = []
    for part in parts:
        x0, y0, x1, y1 = to_layer.transform_bounds(*part, densify_pts=101)
        if not np.isfinite([x0, y0, x1, y1]).all():
            return None
        # The image's edges are curves between the densified points: a margin of 1 % of the box, and a unit.
        dx, dy = 0.01 * (x1 - x0) + 1.0, 0.01 * (y1 - y0) + 1.0
        out.append((x0 - dx, y0 - dy, x1 + dx, y1 + dy))
    return out


def _meets(extent: tuple[Any, ...], box: tuple[float, float, float, float]) -> bool:
    return bool(extent[0] <= box[2] and extent[2] >= box[0] and extent[1] <= box[3] and extent[3] >= box[1])
