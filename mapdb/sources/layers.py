"""Labelled vector layers (GeoJSON, GeoPackage, GeoParquet, Shapefile, FlatGeobuf, CSV) -> objects.

Every feature with a label becomes one object:

- points: the point itself, area 0 (a multipoint gives one object per point);
- polygons and multipolygons: the area centroid, with the area in square metres;
- lines: the centroid of the line (length-weighted), area 0 -- the same rule the
  OSM source applies to features drawn as lines, such as roundabouts;
- null or empty geometries, and rows without a label, are skipped.

Labels come from a column of label names (``label_column``, default ``label``); or a label map
(:mod:`mapdb.classmap`, ``mapdb build --label-map``) translates the values of a column (the map's
``column``, else ``label_column``) to labels, features whose value it does not list being skipped and
counted (``"unmapped_labels"``); or, for a layer without that column (a building footprint file),
``label`` gives every feature one label (``mapdb build --label``).

Broken input is skipped or repaired, and counted, rather than failing the read:
a labelled feature without geometry (null or empty) is skipped (``"missing_geometries"``);
a coordinate that is not finite (or, in a geographic CRS, lies outside lon
[-180, 180] / lat [-90, 90]) drops its feature (``"invalid_coordinates"``); a
polygon whose rings do not close or cross themselves is repaired with shapely
(``"repaired_geometries"``) or dropped when nothing with an area is left
(``"invalid_geometries"``).

A layer is read in batches (:func:`layer_batches`, :mod:`mapdb.sources.layerfiles`), never whole, so what
a read holds does not grow with the layer; with a box, GDAL's formats are asked only for the features whose
envelope meets it and GeoParquet's row groups outside it are skipped (:mod:`mapdb.sources.parquet`, also
for Overture Maps buildings).

Centroids and areas of polygons in a geographic layer are computed in a
Lambert azimuthal equal-area projection centred on the layer's polygons' box (areas exact,
centroids good to well under a metre for features up to a few km across) and
brought back to the layer's CRS.  Objects come back in the layer's CRS, like
every source; the caller reprojects.  In a geographic CRS ``x`` is the
longitude and ``y`` the latitude, whatever the CRS's official axis order.
"""

from __future__ import annotations

import functools
import itertools
import os
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS, Transformer
from pyproj.crs import ProjectedCRS
from pyproj.crs.coordinate_operation import LambertAzimuthalEqualAreaConversion
from pyproj.exceptions import CRSError

from ..classmap import ClassTable
from ..errors import MapdbIOError, SourceError
from ..geo import check_bbox, in_bbox
from ..objects import Objects, concat
from . import layerfiles
from .layerfiles import geometries, open_vector, sound_coordinates
from .parquet import OVERTURE_LABEL

__all__ = ["LAYER_SUFFIXES", "LayerOutlineSink", "is_layer_path", "layer_batches", "read_layer"]

# What is handed a layer's geometries when asked: the geometries, their label names, the layer's CRS.
LayerOutlineSink = Callable[[np.ndarray, np.ndarray, CRS], None]

LAYER_SUFFIXES = (".geojson", ".json", ".gpkg", ".parquet", ".geoparquet", ".shp", ".fgb", ".csv")
_LONLAT = "EPSG:4326"


def is_layer_path(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` has a vector-layer suffix (any case).

    Examples
    --------
    >>> is_layer_path("pitches.GeoJSON"), is_layer_path("points.csv"), is_layer_path("clc.tif")
    (True, True, False)
    """
    return Path(path).suffix.lower() in LAYER_SUFFIXES


def read_layer(path: str | os.PathLike[str], labels: Sequence[str], label_column: str = "label",
               crs: str | None = None, bbox: tuple[float, float, float, float] | None = None,
               counts: Counter[str] | None = None, *, label: str | None = None,
               label_map: ClassTable | None = None, outlines: LayerOutlineSink | None = None) -> Objects:
    """Read a labelled point or polygon layer as objects.

    Parameters
    ----------
    path : path-like
        A vector file (see :data:`LAYER_SUFFIXES`).  CSV files have columns
        ``x, y`` (projected, CRS given by ``crs``) or ``lon, lat`` (EPSG:4326),
        plus the label column.
    labels : sequence of str
        The label names allowed (the label table's); they fix the label codes.
    label_column : str
        Column holding each feature's label name.
    crs : str, optional
        CRS of a CSV's ``x, y`` columns, or of a layer file that carries none
        (a shapefile without ``.prj``).  Ignored when the file names its CRS.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Keep only objects whose centroid lies inside this box (``minlon > maxlon`` crosses the
        antimeridian).
    counts : Counter, optional
        Incremented with the features skipped or repaired (see the module notes).
    label : str, optional
        The label of every feature when the layer has no label column.
    label_map : ClassTable, optional
        Translates the values of its ``column`` (else ``label_column``) to labels; values it does not
        list are skipped and counted as ``"unmapped_labels"``.
    outlines : callable, optional
        Handed the layer's sound polygonal and point geometries, their label names and the layer's CRS, a
        batch at a time (the builder's blocks of touching buildings, :class:`mapdb.build.blocks.BuildingOutlines`).

    Returns
    -------
    Objects
        In the layer's CRS, ``labels=tuple(labels)``; areas in square metres
        for polygons, 0 for points and lines.

    Raises
    ------
    MapdbIOError
        The file is missing.
    SourceError
        Unreadable file, no CRS, no label column, labels not in ``labels``.

    Examples
    --------
    >>> import pathlib, tempfile
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "poi.csv"
    >>> _ = p.write_text("lon,lat,label\\n7.44,46.95,stadium\\n")
    >>> objs = read_layer(p, ["building", "stadium"])
    >>> objs.crs, objs.names().tolist(), objs.x.tolist()
    ('EPSG:4326', ['stadium'], [7.44])
    """
    parts = list(layer_batches(path, labels, label_column, crs, bbox, counts, label=label, label_map=label_map,
                               outlines=outlines))
    if len(parts) == 1:
        return parts[0]
    return concat(parts, labels=tuple(labels)) if parts else Objects.empty(tuple(labels))


def layer_batches(path: str | os.PathLike[str], labels: Sequence[str], label_column: str = "label",
                  crs: str | None = None, bbox: tuple[float, float, float, float] | None = None,
                  counts: Counter[str] | None = None, *, label: str | None = None,
                  label_map: ClassTable | None = None, outlines: LayerOutlineSink | None = None,
                  rows: int | None = None, notes: Callable[[str], None] | None = None) -> Iterator[Objects]:
    """:func:`read_layer`'s objects a batch of at most ``rows`` features (default
    :data:`~mapdb.sources.layerfiles.BATCH_ROWS`) at a time (multipoints split), in the layer's CRS: what a
    read holds does not grow with the layer (:mod:`mapdb.sources.layerfiles`).

    The same objects as :func:`read_layer`, in the same order batch by batch; the first batch is always
    given, empty when the layer has no object.  ``notes`` is handed what is said once about the file (a
    GeoParquet without the statistics to skip row groups outside ``bbox``).
    """
    path = Path(path)
    labels = tuple(labels)
    counts = counts if counts is not None else Counter()
    bbox = None if bbox is None else check_bbox(bbox)
    rows = rows or layerfiles.BATCH_ROWS  # looked up now: a test may make batches small
    _check_path(path)
    rule = _LabelRule(label_map.column or label_column if label_map else label_column, label,
                      _map_lookup(label_map) if label_map else None)
    if path.suffix.lower() == ".csv":
        batches = _csv_batches(path, rule, crs, counts, rows)
    else:
        batches = _vector_batches(path, rule, crs, counts, outlines, rows, bbox, notes)
    for x, y, names, area, layer_crs in batches:
        _check_labels(path, names, labels, rule.column)
        objects = Objects.from_names(x, y, names, area=area, crs=layer_crs.to_string(), labels=labels)
        if bbox is not None and len(objects):
            lon, lat = _to_lonlat(layer_crs, objects.x, objects.y)
            objects = objects.take(np.flatnonzero(in_bbox(bbox, lon, lat)))
        yield objects


@dataclass(frozen=True)
class _LabelRule:
    """Where a layer's labels come from: ``column`` (names, or values that ``values`` maps), else ``label``."""

    column: str
    label: str | None = None
    values: Mapping[str, str] | None = None


def _map_lookup(table: ClassTable) -> dict[str, str]:
    """A label map's values as looked up in a column: an integer key also matches a float column's ``"3.0"``."""
    lookup = dict(table.classes)
    lookup.update({f"{code}.0": name for code, name in table.codes.items() if f"{code}.0" not in lookup})
    return lookup


def _feature_labels(path: Path, frame: Any, rule: _LabelRule, columns: list[str], counts: Counter[str]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Each row's label name (object array) and which rows have one, after ``rule``."""
    if rule.column not in frame.columns:
        if rule.label is not None:
            return np.full(len(frame), rule.label, dtype=object), np.ones(len(frame), bool)
        raise SourceError(f"{path}: no column {rule.column!r} (columns: {', '.join(columns) or 'none'}); "
                          "give every feature one label with --label NAME")
    names, keep = _label_strings(frame[rule.column].to_numpy())
    if rule.values is not None:
        mapped = np.array([rule.values.get(v) for v in names], dtype=object)
        unmapped = keep & np.array([m is None for m in mapped], bool)
        counts["unmapped_labels"] += int(unmapped.sum())
        names, keep = mapped, keep & ~unmapped
    return names, keep


def _check_path(path: Path) -> None:
    """A one-line error for a missing file or a directory (a file geodatabase ``.gdb`` is one)."""
    if not path.exists():
        raise MapdbIOError(f"{path}: no such file")
    if path.is_dir() and path.suffix.lower() != ".gdb":
        raise MapdbIOError(f"{path}: is a directory, not a layer file")


def _check_labels(path: Path, names: np.ndarray, labels: tuple[str, ...], label_column: str) -> None:
    """Refuse a layer with label names not in ``labels`` (the first ten named)."""
    unknown = sorted(set(np.unique(names).tolist()) - set(labels)) if names.size else []
    if unknown:
        shown = ", ".join(repr(u) for u in unknown[:10])
        if len(unknown) > 10:
            shown += f" and {len(unknown) - 10} more"
        raise SourceError(
            f"{path}: unknown label(s) {shown} in column {label_column!r}; declare them in a --labels file"
        )


def _parse_crs(path: Path, crs: str) -> CRS:
    try:
        return CRS.from_user_input(crs)
    except CRSError as exc:
        raise SourceError(f"{path}: {crs!r} is not a CRS ({exc})") from None


def _to_lonlat(crs: CRS, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if crs.is_geographic:
        return x, y
    lon, lat = _lonlat_from(crs).transform(x, y)
    return np.asarray(lon), np.asarray(lat)


@functools.lru_cache(maxsize=4)
def _lonlat_from(crs: CRS) -> Transformer:
    return Transformer.from_crs(crs, _LONLAT, always_xy=True)


def _label_strings(values: Any) -> tuple[np.ndarray, np.ndarray]:
    """Label names as an object array of str, and which rows have one (not null, not blank)."""
    import pandas as pd

    series = pd.Series(values)
    names = series.astype(str).str.strip().to_numpy(dtype=object)
    return names, series.notna().to_numpy() & (names != "")


def _csv_batches(path: Path, rule: _LabelRule, crs: str | None, counts: Counter[str], rows: int
                 ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, CRS]]:
    """A CSV layer's points, ``rows`` lines at a time (pandas' parser in chunks; a file without data lines
    gives one empty batch after its header is checked)."""
    import pandas as pd

    try:
        reader = pd.read_csv(path, skipinitialspace=True, chunksize=rows)
        with reader:
            given = False
            for table in reader:
                given = True
                yield _csv_points(path, table, rule, crs, counts)
        if not given:
            yield _csv_points(path, pd.read_csv(path, skipinitialspace=True, nrows=0), rule, crs, counts)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise SourceError(f"{path}: not a readable CSV file ({' '.join(str(exc).split())})") from None


def _csv_points(path: Path, table: Any, rule: _LabelRule, crs: str | None, counts: Counter[str]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, CRS]:
    """One chunk of a CSV layer as points (its index counts the file's data lines from 0)."""
    import pandas as pd

    columns = [str(c) for c in table.columns]
    names, keep = _feature_labels(path, table, rule, columns, counts)
    has_xy, has_lonlat = {"x", "y"} <= set(table.columns), {"lon", "lat"} <= set(table.columns)
    if has_xy and crs is not None:
        xcol, ycol, layer_crs = "x", "y", _parse_crs(path, crs)
    elif has_lonlat:
        xcol, ycol, layer_crs = "lon", "lat", CRS.from_user_input(_LONLAT)
    elif has_xy:
        raise SourceError(f"{path}: CSV with x,y columns needs their CRS (--layer-crs EPSG:n on the command line)")
    else:
        raise SourceError(f"{path}: CSV needs columns x,y or lon,lat (columns: {', '.join(columns)})")
    raw = table[[xcol, ycol]]
    coords = raw.apply(pd.to_numeric, errors="coerce").to_numpy(dtype=np.float64)
    # Text that is no number at all is a broken file; an empty cell, "nan", "inf" or a number out of
    # range is a bad coordinate: that row is skipped and counted.
    text = (raw.notna() & np.isnan(coords)).to_numpy().any(axis=1)
    bad = keep & text
    if bad.any():
        line = int(np.asarray(table.index)[np.flatnonzero(bad)[0]]) + 2  # 1-based, after the header line
        raise SourceError(f"{path}: line {line}: {xcol},{ycol} are not numbers")
    valid = sound_coordinates(layer_crs, coords[:, 0], coords[:, 1])
    counts["invalid_coordinates"] += int((keep & ~valid).sum())
    keep &= valid
    x, y = coords[keep, 0], coords[keep, 1]
    return x, y, names[keep], np.zeros(x.size), layer_crs


def _vector_batches(path: Path, rule: _LabelRule, crs: str | None, counts: Counter[str],
                    outlines: LayerOutlineSink | None, rows: int, bbox: tuple[float, float, float, float] | None,
                    notes: Callable[[str], None] | None
                    ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, CRS]]:
    """A vector layer's features, a batch at a time.

    A geographic layer's polygons are measured in an equal-area projection centred on the box of the
    layer's polygons: on the one batch's when the layer is one batch, else on the whole layer's, read first
    in a pass over the geometries alone, so that every batch is measured in the same projection.
    """
    layer = open_vector(path, bbox)
    if layer.note is not None and notes is not None:
        notes(layer.note)
    if layer.crs is None:
        if crs is None:
            raise SourceError(f"{path}: layer has no CRS (add one to the file, e.g. a .prj, or pass crs=...)")
        layer_crs = _parse_crs(path, crs)
    else:
        layer_crs = layer.crs
    if layer.overture and rule.label is None and rule.column not in layer.columns:
        rule = _LabelRule(rule.column, OVERTURE_LABEL, rule.values)
    if rule.column not in layer.columns and rule.label is None:
        raise SourceError(f"{path}: no column {rule.column!r} (columns: {', '.join(layer.columns) or 'none'}); "
                          "give every feature one label with --label NAME")
    batches = layer.batches([rule.column], bbox, rows)
    first = next(batches, None)
    second = next(batches, None) if first is not None else None
    centre = None
    if second is not None and layer_crs.is_geographic:
        extent = layer.extent(layer_crs)
        centre = None if extent is None else ((extent[0] + extent[2]) / 2, (extent[1] + extent[3]) / 2)
    if first is None:
        first = (_empty_batch(rule.column), np.zeros(0, dtype=object))
    for table, wkb in itertools.chain([first], [second] if second is not None else [], batches):
        yield _vector_objects(path, table, wkb, rule, layer_crs, counts, outlines, centre)


def _empty_batch(column: str) -> Any:
    import pyarrow as pa

    return pa.table({column: pa.array([], pa.string())})


def _vector_objects(path: Path, table: Any, wkb: np.ndarray, rule: _LabelRule, layer_crs: CRS,
                    counts: Counter[str], outlines: LayerOutlineSink | None, centre: tuple[float, float] | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, CRS]:
    """One batch's features as objects: labelled, sound, multipoints split, centroids and areas."""
    frame = _Columns(table)
    names, keep = _feature_labels(path, frame, rule, frame.columns, counts)
    geoms = geometries(path, wkb, counts)
    missing = shapely.is_missing(geoms) | shapely.is_empty(geoms)
    counts["missing_geometries"] += int((keep & missing).sum())
    keep &= ~missing
    geoms, names = geoms[keep], names[keep]
    geoms, names = _sound_geometries(geoms, names, layer_crs, counts)
    if outlines is not None:
        outlines(geoms, names, layer_crs)

    # Multipoints become one object per point; everything else one object per feature.
    kind = shapely.get_type_id(geoms)
    is_multipoint = kind == shapely.GeometryType.MULTIPOINT
    if is_multipoint.any():
        parts, owner = shapely.get_parts(geoms[is_multipoint], return_index=True)
        names = np.concatenate([names[~is_multipoint], names[is_multipoint][owner]])
        geoms = np.concatenate([geoms[~is_multipoint], parts])
        kind = shapely.get_type_id(geoms)

    x = np.empty(geoms.size)
    y = np.empty(geoms.size)
    area = np.zeros(geoms.size)
    is_point = kind == shapely.GeometryType.POINT
    x[is_point] = shapely.get_x(geoms[is_point])
    y[is_point] = shapely.get_y(geoms[is_point])
    other = ~is_point
    if other.any():
        x[other], y[other], area[other] = _centroids_and_areas(geoms[other], layer_crs, centre)
    return x, y, names, area, layer_crs


class _Columns:
    """A pyarrow batch's columns as the label rule reads them (pandas Series by name, its length)."""

    def __init__(self, table: Any) -> None:
        self.table = table
        self.columns = [str(c) for c in table.schema.names]

    def __len__(self) -> int:
        return int(self.table.num_rows)

    def __getitem__(self, name: str) -> Any:
        return self.table.column(name).to_pandas()


def _sound_geometries(geoms: np.ndarray, names: np.ndarray, crs: CRS, counts: Counter[str]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Drop features with a bad coordinate; repair polygons that are not valid (or drop them if nothing is left)."""
    coords, owner = shapely.get_coordinates(geoms, return_index=True)
    bad = np.zeros(geoms.size, bool)
    bad[owner[~sound_coordinates(crs, coords[:, 0], coords[:, 1])]] = True
    counts["invalid_coordinates"] += int(bad.sum())
    geoms, names = geoms[~bad], names[~bad]
    polygonal = np.isin(shapely.get_type_id(geoms), [shapely.GeometryType.POLYGON, shapely.GeometryType.MULTIPOLYGON])
    invalid = polygonal & ~shapely.is_valid(geoms)
    if not invalid.any():
        return geoms, names
    geoms = geoms.copy()
    geoms[invalid] = shapely.make_valid(geoms[invalid], method="structure", keep_collapsed=False)
    lost = invalid & (shapely.is_empty(geoms) | (shapely.area(geoms) <= 0))
    counts["repaired_geometries"] += int((invalid & ~lost).sum())
    counts["invalid_geometries"] += int(lost.sum())
    return geoms[~lost], names[~lost]


def _centroids_and_areas(geoms: np.ndarray, crs: CRS, centre: tuple[float, float] | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid (in ``crs``) and area (m^2; 0 for lines) of non-point geometries.

    Geographic layers go through an equal-area projection centred on ``centre`` (lon, lat; by default the
    middle of the geometries' box), where planar centroids and areas are meaningful; projected layers are
    measured in their own units (converted to metres).
    """
    if crs.is_geographic:
        if centre is None:
            minx, miny, maxx, maxy = shapely.total_bounds(geoms)
            centre = ((minx + maxx) / 2, (miny + maxy) / 2)
        forward, back = _equal_area(crs, (float(centre[0]), float(centre[1])))
        projected = shapely.transform(geoms, lambda xy: np.column_stack(forward.transform(xy[:, 0], xy[:, 1])))
        centroids = shapely.centroid(projected)
        area = shapely.area(projected)
        x, y = back.transform(shapely.get_x(centroids), shapely.get_y(centroids))
        return np.asarray(x), np.asarray(y), area
    unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
    centroids = shapely.centroid(geoms)
    return shapely.get_x(centroids), shapely.get_y(centroids), shapely.area(geoms) * unit * unit


@functools.lru_cache(maxsize=4)
def _equal_area(crs: CRS, centre: tuple[float, float]) -> tuple[Transformer, Transformer]:
    """The transformations to and from the Lambert azimuthal equal-area projection about ``centre`` (lon, lat),
    made once for all the batches of a layer (each takes a tenth of a second or more)."""
    # On the layer's own datum, so going there and back involves no datum shift.
    local = ProjectedCRS(LambertAzimuthalEqualAreaConversion(centre[1], centre[0]), geodetic_crs=crs.geodetic_crs)
    return Transformer.from_crs(crs, local, always_xy=True), Transformer.from_crs(local, crs, always_xy=True)
