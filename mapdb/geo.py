"""Longitude/latitude boxes: checking them, testing points against them, finding them in a projected CRS.

A box is ``(minlon, minlat, maxlon, maxlat)`` in degrees, edges included.  As in
GeoJSON (RFC 7946, section 5.2) a box with ``minlon > maxlon`` crosses the
antimeridian: it holds longitudes from ``minlon`` east to 180 and from -180 east
to ``maxlon``.  A box may span the whole world (``-180, -90, 180, 90``) and touch
the poles.

Selecting the objects of a projected map (or the pixels of a raster) that lie in
such a box is done in two steps, so that the answer is exact whatever the
projection:

1. a *pre-filter* in the projected CRS, :func:`projected_window`: the box is first
   cut to the lon/lat extent of the data (the map's or raster's own bounds, turned
   into lon/lat), so that only places where the projection is defined are ever
   projected; every projected point is checked by projecting it back, and when
   that fails the pre-filter gives up and keeps everything;
2. the exact test, :func:`in_bbox`, on the objects' own longitudes and latitudes.

The pre-filter only decides how much is read: it may keep too much, never too little.

A single place given in lon/lat is checked by :func:`check_lonlat` (a latitude beyond the poles is refused),
and :func:`swapped_lonlat` says when it looks given as lat, lon: off the map, while its swap is on it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from pyproj import CRS, Transformer

from .errors import MapdbError

__all__ = [
    "WORLD",
    "BBox",
    "LonLatError",
    "SwappedLonLatWarning",
    "bbox_text",
    "central_longitude",
    "check_bbox",
    "check_lonlat",
    "in_bbox",
    "intersect_bboxes",
    "lonlat_extent",
    "projected_window",
    "split_bbox",
    "swapped_lonlat",
]

BBox = tuple[float, float, float, float]
WORLD: BBox = (-180.0, -90.0, 180.0, 90.0)

# Points per side of a box when its outline is carried from one CRS to the other: extremes of the
# carried outline fall between samples, which the relative margin below covers.
_SAMPLES_PER_SIDE = 256
_MARGIN = 1e-3
# Largest disagreement (degrees) allowed when a projected sample is carried back to lon/lat.
_ROUND_TRIP_DEG = 1e-6


def check_bbox(bbox: Sequence[Any]) -> BBox:
    """A valid lon/lat box as four floats, or ValueError saying what is wrong.

    Longitudes must lie in [-180, 180] and latitudes in [-90, 90], all finite;
    ``minlat < maxlat``; ``minlon > maxlon`` is a box crossing the antimeridian,
    and ``minlon == maxlon`` is refused (empty or the whole world? ambiguous).

    Examples
    --------
    >>> check_bbox(["170", "50", "-170", "70"])
    (170.0, 50.0, -170.0, 70.0)
    >>> check_bbox((0, 91, 1, 92))
    Traceback (most recent call last):
    ValueError: latitudes must lie in [-90, 90]
    """
    try:
        values = tuple(float(v) for v in bbox)
    except (TypeError, ValueError):
        raise ValueError("a bbox is four numbers minlon,minlat,maxlon,maxlat") from None
    if len(values) != 4:
        raise ValueError(f"a bbox is four numbers minlon,minlat,maxlon,maxlat, not {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError("bbox values must be finite numbers")
    minlon, minlat, maxlon, maxlat = values
    if not (-180.0 <= minlon <= 180.0 and -180.0 <= maxlon <= 180.0):
        raise ValueError("longitudes must lie in [-180, 180]")
    if not (-90.0 <= minlat <= 90.0 and -90.0 <= maxlat <= 90.0):
        raise ValueError("latitudes must lie in [-90, 90]")
    if not minlat < maxlat:
        raise ValueError("minlat must be below maxlat")
    if minlon == maxlon:
        raise ValueError("minlon and maxlon must differ (minlon > maxlon crosses the antimeridian)")
    return values


def bbox_text(bbox: Sequence[float]) -> str:
    """``"minlon,minlat,maxlon,maxlat"`` as given on a command line.

    Examples
    --------
    >>> bbox_text((170.0, 50.0, -170.0, 70.5))
    '170,50,-170,70.5'
    """
    return ",".join(f"{float(v):g}" if float(v).is_integer() else repr(float(v)) for v in bbox)


def split_bbox(bbox: Sequence[float]) -> list[BBox]:
    """A box as one or two boxes that do not cross the antimeridian.

    Examples
    --------
    >>> split_bbox((170, 50, -170, 70))
    [(170.0, 50.0, 180.0, 70.0), (-180.0, 50.0, -170.0, 70.0)]
    """
    minlon, minlat, maxlon, maxlat = (float(v) for v in bbox)
    if minlon <= maxlon:
        return [(minlon, minlat, maxlon, maxlat)]
    return [(minlon, minlat, 180.0, maxlat), (-180.0, minlat, maxlon, maxlat)]


def in_bbox(bbox: Sequence[float], lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Which points lie in the box (edges included; longitudes 180 and -180 are one meridian).

    Examples
    --------
    >>> in_bbox((170, 50, -170, 70), np.array([175.0, -175.0, 0.0, -180.0]), np.full(4, 60.0)).tolist()
    [True, True, False, True]
    """
    lon = np.asarray(lon, dtype=np.float64)
    lat = np.asarray(lat, dtype=np.float64)
    minlon, minlat, maxlon, maxlat = (float(v) for v in bbox)

    def lon_inside(values: np.ndarray) -> np.ndarray:
        if minlon <= maxlon:
            return (values >= minlon) & (values <= maxlon)
        return (values >= minlon) | (values <= maxlon)

    inside_lon = lon_inside(lon) | ((np.abs(lon) == 180.0) & lon_inside(-lon))
    return inside_lon & (lat >= minlat) & (lat <= maxlat)


def intersect_bboxes(a: Sequence[float], b: Sequence[float]) -> list[BBox]:
    """The common part of two boxes, as boxes that do not cross the antimeridian (maybe none).

    Examples
    --------
    >>> intersect_bboxes((170, 50, -170, 70), (-175, 0, 10, 60))
    [(-175.0, 50.0, -170.0, 60.0)]
    """
    out = []
    for p in split_bbox(a):
        for q in split_bbox(b):
            box = (max(p[0], q[0]), max(p[1], q[1]), min(p[2], q[2]), min(p[3], q[3]))
            if box[0] <= box[2] and box[1] <= box[3]:
                out.append(box)
    return out


def _outline(box: Sequence[float], n: int = _SAMPLES_PER_SIDE) -> tuple[np.ndarray, np.ndarray]:
    """Points along the four sides of a box (x0, y0, x1, y1), corners included, plus a coarse inner grid."""
    x0, y0, x1, y1 = (float(v) for v in box)
    t = np.linspace(0.0, 1.0, n)
    xs = x0 + (x1 - x0) * t
    ys = y0 + (y1 - y0) * t
    gx, gy = np.meshgrid(np.linspace(x0, x1, 9), np.linspace(y0, y1, 9))
    x = np.concatenate([xs, xs, np.full(n, x0), np.full(n, x1), gx.ravel()])
    y = np.concatenate([np.full(n, y0), np.full(n, y1), ys, ys, gy.ravel()])
    return x, y


def _lon_arc(lon: np.ndarray) -> tuple[float, float]:
    """The shortest eastward arc (start, width in degrees) holding every longitude given."""
    values = np.sort(np.mod(np.asarray(lon, np.float64) + 180.0, 360.0) - 180.0)
    gaps = np.diff(np.concatenate([values, values[:1] + 360.0]))
    widest = int(np.argmax(gaps))
    start = float(values[(widest + 1) % values.size])
    return start, 360.0 - float(gaps[widest])


def central_longitude(lon: np.ndarray) -> float:
    """The median longitude, counted around the globe from its widest gap between the values given.

    Points on both sides of the antimeridian have their middle there, not at 0.

    Examples
    --------
    >>> central_longitude(np.array([179.0, 179.5, -179.8]))
    179.5
    >>> central_longitude(np.array([10.0, 12.0, 20.0]))
    12.0
    """
    start, _ = _lon_arc(lon)
    unwrapped = np.mod(np.asarray(lon, np.float64) - start, 360.0) + start
    return float((np.median(unwrapped) + 180.0) % 360.0 - 180.0)


def _arc_bbox(start: float, width: float, minlat: float, maxlat: float) -> BBox:
    """A lon/lat box from a longitude arc (antimeridian-crossing when the arc runs past 180)."""
    if width >= 360.0:
        return (-180.0, minlat, 180.0, maxlat)
    start = (start + 180.0) % 360.0 - 180.0
    end = start + width
    if end > 180.0:
        return (start, minlat, end - 360.0, maxlat)
    return (start, minlat, end, maxlat)


def _round_trip_ok(lon: np.ndarray, lat: np.ndarray, back_lon: np.ndarray, back_lat: np.ndarray) -> bool:
    """Whether points carried to a CRS and back came home (longitude is free at the poles)."""
    if not (np.isfinite(back_lon).all() and np.isfinite(back_lat).all()):
        return False
    dlon = np.abs((np.asarray(back_lon) - lon + 180.0) % 360.0 - 180.0)
    near_pole = np.abs(lat) > 90.0 - 1e-6
    return bool((np.abs(np.asarray(back_lat) - lat) <= _ROUND_TRIP_DEG).all()
                and (dlon[~near_pole] <= _ROUND_TRIP_DEG).all())


def _transformers(crs: Any) -> tuple[Transformer, Transformer]:
    parsed = CRS.from_user_input(crs)
    return (Transformer.from_crs("EPSG:4326", parsed, always_xy=True),
            Transformer.from_crs(parsed, "EPSG:4326", always_xy=True))


def lonlat_extent(crs: Any, bounds: Sequence[float]) -> BBox | None:
    """The lon/lat box (possibly crossing the antimeridian) holding every point of a projected box.

    Parameters
    ----------
    crs : anything pyproj accepts
        The CRS of ``bounds``.
    bounds : (minx, miny, maxx, maxy)
        A box in that CRS (a map's or a raster's bounds).

    Returns
    -------
    tuple or None
        A slightly generous box (a margin covers what falls between the sampled points), or None
        when some point of ``bounds`` has no longitude and latitude (outside the projection's domain).
    """
    try:
        to_crs, to_lonlat = _transformers(crs)
        x, y = _outline(bounds)
        lon, lat = (np.asarray(v) for v in to_lonlat.transform(x, y))
    except Exception:  # a CRS pyproj cannot relate to lon/lat: nothing can be said
        return None
    if not (np.isfinite(lon).all() and np.isfinite(lat).all()):
        return None
    minlat, maxlat = float(lat.min()), float(lat.max())
    start, width = _lon_arc(lon)
    # A pole inside the box: every longitude, and the latitude reaches it.
    x0, y0, x1, y1 = (float(v) for v in bounds)
    for pole in (90.0, -90.0):
        px, py = (float(v) for v in to_crs.transform(0.0, pole))
        if math.isfinite(px) and math.isfinite(py) and x0 <= px <= x1 and y0 <= py <= y1:
            start, width = -180.0, 360.0
            minlat, maxlat = min(minlat, pole), max(maxlat, pole)
    lat_margin = _MARGIN * (maxlat - minlat) + 1e-7
    lon_margin = _MARGIN * width + 1e-7
    return _arc_bbox(start - lon_margin, width + 2 * lon_margin,
                     max(-90.0, minlat - lat_margin), min(90.0, maxlat + lat_margin))


def _area_of_use(crs: Any) -> BBox:
    try:
        area = CRS.from_user_input(crs).area_of_use
    except Exception:
        area = None
    if area is None:
        return WORLD
    west, south, east, north = (float(v) for v in area.bounds)
    return (west, south, east, north) if west != east else WORLD


def projected_window(
    crs: Any, bbox: Sequence[float], within: Sequence[float] | None = None
) -> BBox | None:
    """A box of ``crs`` holding every point of ``within`` whose lon/lat lies in ``bbox``; None if there is none.

    Parameters
    ----------
    crs : anything pyproj accepts
        A projected (or geographic) CRS.
    bbox : (minlon, minlat, maxlon, maxlat)
        A lon/lat box, possibly crossing the antimeridian (see :func:`check_bbox`).
    within : (minx, miny, maxx, maxy), optional
        Where the data lie, in ``crs`` (a map's bounds, a raster's extent).  The answer never
        leaves it.  Default: the CRS's area of use (unbounded when it has none).

    Returns
    -------
    tuple or None
        The box, or None when ``bbox`` and the data's lon/lat extent do not meet.  When the box
        cannot be found reliably (the transform fails or does not come back to where it started),
        the whole of ``within`` (or an unbounded box): a pre-filter may keep too much, never too little.
    """
    everything: BBox = tuple(float(v) for v in within) if within is not None else (  # type: ignore[assignment]
        -math.inf, -math.inf, math.inf, math.inf)
    if within is not None:
        domain = lonlat_extent(crs, within)
        if domain is None:
            return everything
    else:
        domain = _area_of_use(crs)
    parts = intersect_bboxes(bbox, domain)
    if not parts:
        return None
    projected = _project_outlines(crs, parts)
    if projected is None:
        return everything
    box = _padded_box(*projected)
    if within is None:
        return box
    return _clip_box(box, everything)


def _project_outlines(crs: Any, parts: list[BBox]) -> tuple[np.ndarray, np.ndarray] | None:
    """Points of the outlines of lon/lat boxes in ``crs``; None when the transform fails or does not come back."""
    try:
        to_crs, _ = _transformers(crs)
    except Exception:
        return None
    xs, ys = [], []
    for part in parts:
        lon, lat = _outline(part)
        try:
            x, y = (np.asarray(v) for v in to_crs.transform(lon, lat))
            back_lon, back_lat = to_crs.transform(x, y, direction="INVERSE")
        except Exception:
            return None
        if not (np.isfinite(x).all() and np.isfinite(y).all()) or not _round_trip_ok(lon, lat, back_lon, back_lat):
            return None
        xs.append(x)
        ys.append(y)
    return np.concatenate(xs), np.concatenate(ys)


def _padded_box(x: np.ndarray, y: np.ndarray) -> BBox:
    """The box of the points, grown by a margin (relative, and for rounding at large coordinates)."""
    mx = _MARGIN * (float(x.max()) - float(x.min())) + 1e-9 * float(np.abs(x).max()) + 1e-6
    my = _MARGIN * (float(y.max()) - float(y.min())) + 1e-9 * float(np.abs(y).max()) + 1e-6
    return (float(x.min()) - mx, float(y.min()) - my, float(x.max()) + mx, float(y.max()) + my)


def _clip_box(box: BBox, limit: BBox) -> BBox | None:
    """The part of ``box`` inside ``limit``; None if they do not meet."""
    clipped = (max(box[0], limit[0]), max(box[1], limit[1]), min(box[2], limit[2]), min(box[3], limit[3]))
    if clipped[0] > clipped[2] or clipped[1] > clipped[3]:
        return None
    return clipped



# ------------------------------------------------------------------------------------------ one place


class LonLatError(MapdbError, ValueError):
    """A longitude or latitude that is not a number within its range."""


class SwappedLonLatWarning(UserWarning):
    """A lon/lat that falls off the map while its swap falls on it: probably given as lat, lon."""


def check_lonlat(lon: Any, lat: Any) -> tuple[float, float]:
    """``(lon, lat)`` as floats, or :class:`LonLatError` for a value that is not a finite number within
    [-180, 180] (longitude) or [-90, 90] (latitude).

    Examples
    --------
    >>> check_lonlat(24.94, 60.17)
    (24.94, 60.17)
    >>> check_lonlat(100.0, 95.0)
    Traceback (most recent call last):
    mapdb.geo.LonLatError: latitude 95.0 must be a number in [-90, 90]
    >>> check_lonlat(3.0, -120.0)
    Traceback (most recent call last):
    mapdb.geo.LonLatError: latitude -120.0 must be a number in [-90, 90] (lon, lat swapped? longitude comes first)
    """
    for name, value, limit in (("longitude", lon, 180.0), ("latitude", lat, 90.0)):
        number = isinstance(value, int | float | np.number) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and abs(value) <= limit):
            swapped = number and name == "latitude" and abs(lat) <= 180.0 and abs(lon) <= 90.0
            hint = " (lon, lat swapped? longitude comes first)" if swapped else ""
            raise LonLatError(f"{name} {value!r} must be a number in [{-limit:g}, {limit:g}]{hint}")
    return float(lon), float(lat)


def swapped_lonlat(crs: Any, bounds: Sequence[float], lon: float, lat: float) -> str | None:
    """Why ``(lon, lat)`` looks swapped for a map of ``crs`` and ``bounds`` (minx, miny, maxx, maxy in its CRS),
    or None: the place falls outside the bounds while ``(lat, lon)`` falls inside.

    Examples
    --------
    >>> utm35 = "EPSG:32635"; helsinki = (385400.0, 6671400.0, 386500.0, 6673200.0)
    >>> swapped_lonlat(utm35, helsinki, 60.166, 24.945)
    'lon 60.166, lat 24.945 is off the map, and lon 24.945, lat 60.166 on it: lon and lat swapped?'
    >>> swapped_lonlat(utm35, helsinki, 24.945, 60.166) is None
    True
    """
    if not crs or abs(lon) > 90.0 or not all(math.isfinite(v) for v in bounds):
        return None
    x0, y0, x1, y1 = bounds
    forward = _transformers(crs)[0]

    def on_map(a: float, b: float) -> bool:
        try:
            x, y = forward.transform(a, b)
        except Exception:  # pyproj raises several kinds for places a projection cannot take
            return False
        return bool(x0 <= x <= x1 and y0 <= y <= y1)

    if on_map(lon, lat) or not on_map(lat, lon):
        return None
    return f"lon {lon:g}, lat {lat:g} is off the map, and lon {lat:g}, lat {lon:g} on it: lon and lat swapped?"
