"""The queries every map answers (:class:`MapBase`: boxes, radii, geometries, lon/lat), and :class:`MemoryMap`,
which answers them over objects held in memory.

A map file opened for queries is a :class:`~mapdb.mapfile.reader.MetaMap`, which reads its pages on demand.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import numpy as np
import shapely
from pyproj import Transformer

from ..objects import Objects
from .layout import DEFAULT_QUANTUM

__all__ = [
    "MapBase",
    "MemoryMap",
]

T = TypeVar("T")


class MapBase:
    """Queries shared by file-backed and in-memory maps; subclasses provide ``query_bbox`` and ``all``."""

    crs: str
    quantum: float
    labels: tuple[str, ...]
    bounds: tuple[float, float, float, float]
    metadata: dict[str, Any]

    def __init__(self) -> None:
        self._derived: dict[str, Any] = {}

    @property
    def has_elevation(self) -> bool:
        """Whether the map holds its objects' ground elevation (``Objects.elevation``; a version 2 file)."""
        return getattr(self, "elevation_step", None) is not None

    @property
    def label_counts(self) -> dict[str, int]:
        return {d["name"]: d["count"] for d in self.metadata["labels"] if d["count"]}

    def __len__(self) -> int:
        return int(self.metadata["count"])

    def __enter__(self) -> MapBase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._derived.clear()

    def cached(self, key: str, factory: Callable[[], T]) -> T:
        """A value derived from this map (an index, say), computed once per open map."""
        if key not in self._derived:
            self._derived[key] = factory()
        return self._derived[key]

    def _label_filter(self, objects: Objects, labels: Iterable[str] | None) -> Objects:
        """The objects of the named labels (all of them for None); a name the map does not know is an error.

        A mistyped name would otherwise select nothing, which looks like an answer ("no buildings here").
        """
        if labels is None:
            return objects
        names = [labels] if isinstance(labels, str) else list(labels)
        unknown = [name for name in names if name not in self.labels]
        if unknown:
            import difflib

            from ..errors import LabelTableError

            close = difflib.get_close_matches(str(unknown[0]), self.labels, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            path = getattr(self, "path", None)  # None for a map in memory
            where = f"{path}: " if path is not None else ""
            raise LabelTableError(f"{where}unknown label {unknown[0]!r}{hint}; the map's labels are "
                                  f"{', '.join(self.labels)}")
        wanted = [self.labels.index(name) for name in names]
        return objects.take(np.isin(objects.label, wanted))

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        raise NotImplementedError

    def all(self) -> Objects:
        raise NotImplementedError

    def query_radius(self, x: float, y: float, r: float, labels: Iterable[str] | None = None) -> Objects:
        """Objects within ``r`` metres of (x, y), optionally only of the named labels."""
        found = self.query_bbox(x - r, y - r, x + r, y + r, labels)
        return found.take((found.x - x) ** 2 + (found.y - y) ** 2 <= r * r)

    def query_geometry(self, geometry: shapely.Geometry, labels: Iterable[str] | None = None) -> Objects:
        """Objects inside a shapely geometry given in the map's CRS, edges included.

        The pages under the geometry's bounding box are read, then each object is tested against the
        geometry itself (vectorised, :func:`shapely.intersects_xy`: inside or on the boundary, as
        :meth:`query_bbox` includes its edges, so that a box gives what ``query_bbox`` gives).

        Parameters
        ----------
        geometry : shapely.Geometry
            A polygon, multipolygon, line or point, in the map's CRS (reproject a lon/lat geometry first,
            e.g. ``geopandas.GeoSeries([g], crs="EPSG:4326").to_crs(m.crs)[0]``).  An empty geometry
            holds nothing.
        labels : iterable of str, optional
            Only objects of these labels; a name the map does not know raises :class:`LabelTableError`.

        Returns
        -------
        Objects
            In the map's CRS; empty if nothing lies inside.

        Raises
        ------
        TypeError
            If ``geometry`` is not a shapely geometry.

        Examples
        --------
        >>> m = MemoryMap(Objects.from_names([0.0, 10.0, 50.0], [0.0, 10.0, 0.0], ["park", "water", "park"],
        ...                                  crs="EPSG:32631"))
        >>> triangle = shapely.Polygon([(-1, -1), (30, -1), (-1, 30)])
        >>> m.query_geometry(triangle).names().tolist()
        ['park', 'water']
        >>> len(m.query_geometry(triangle, labels=["water"])), len(m.query_geometry(shapely.Polygon()))
        (1, 0)
        >>> m.query_geometry(triangle, labels=["prak"])
        Traceback (most recent call last):
        mapdb.errors.LabelTableError: unknown label 'prak' (did you mean 'park'?); the map's labels are park, water
        """
        if not isinstance(geometry, shapely.Geometry):
            raise TypeError(f"query_geometry needs a shapely geometry, not {type(geometry).__name__}")
        if geometry.is_empty:
            return self._label_filter(Objects.empty(self.labels, self.crs), labels)
        minx, miny, maxx, maxy = geometry.bounds
        found = self.query_bbox(minx, miny, maxx, maxy, labels=labels)
        return found.take(shapely.intersects_xy(geometry, found.x, found.y))

    def query_lonlat_bbox(self, bbox: Iterable[float], labels: Iterable[str] | None = None) -> Objects:
        """Objects whose WGS 84 longitude and latitude fall in a lon/lat box, edges included.

        Parameters
        ----------
        bbox : (minlon, minlat, maxlon, maxlat)
            Degrees.  The box may span the world, touch the poles or cross the antimeridian
            (``minlon > maxlon``, as in GeoJSON); see :func:`mapdb.geo.check_bbox` for what is refused.
        labels : iterable of str, optional
            Only objects of these labels; a name the map does not know raises :class:`LabelTableError`.

        Returns
        -------
        Objects
            In the map's CRS (the test is made on each object's own lon/lat, so the answer does not depend
            on how the box projects); empty when the box misses the map.

        Raises
        ------
        ValueError
            If ``bbox`` is not a valid lon/lat box.

        Examples
        --------
        >>> m = MemoryMap(Objects.from_names([500000.0, 600000.0], [4649776.0, 4649776.0], ["park", "water"],
        ...                                  crs="EPSG:32631"))  # lon 3 and 4.2, lat 42
        >>> m.query_lonlat_bbox((2.9, 41.9, 3.1, 42.1)).names().tolist()
        ['park']
        >>> len(m.query_lonlat_bbox((-10.0, 0.0, -9.0, 1.0)))
        0
        >>> m.query_lonlat_bbox((3.1, 41.9, 2.9, 42.1)).names().tolist()  # crosses 180: all but lon 2.9 to 3.1
        ['water']
        >>> m.query_lonlat_bbox((2.9, 42.1, 3.1, 41.9))
        Traceback (most recent call last):
        ValueError: minlat must be below maxlat
        """
        from ..geo import check_bbox

        return self._in_lonlat_bbox(check_bbox(list(bbox)), labels)[0]

    def query_lonlat(self, lon: float, lat: float, radius_m: float, labels: Iterable[str] | None = None) -> Objects:
        """Objects within ``radius_m`` metres on the ground (geodesic, on WGS 84) of a longitude and latitude.

        Parameters
        ----------
        lon, lat : float
            WGS 84 degrees, longitude in [-180, 180], latitude in [-90, 90].
        radius_m : float
            Ground distance in metres, >= 0.  Not a distance in the map's CRS: a projection stretches
            distances (by up to 0.1 % inside a UTM zone, by 1 / cos(latitude) in Web Mercator).
        labels : iterable of str, optional
            Only objects of these labels; a name the map does not know raises :class:`LabelTableError`.

        Returns
        -------
        Objects
            In the map's CRS; empty when the place is off the map, with a
            :class:`~mapdb.geo.SwappedLonLatWarning` when ``(lat, lon)`` would have been on it.

        Raises
        ------
        LonLatError
            (a ``ValueError``) If lon or lat is out of range or not finite (lon and lat swapped often ends here).
        ValueError
            If the radius is negative or not finite.

        Examples
        --------
        >>> m = MemoryMap(Objects.from_names([500000.0, 500050.0, 500000.0], [4649776.0, 4649776.0, 4650776.0],
        ...                                  ["park", "water", "park"], crs="EPSG:32631"))
        >>> m.query_lonlat(3.0, 42.0, 100.0).names().tolist()  # the third object is 1 km north
        ['park', 'water']
        >>> len(m.query_lonlat(3.0, 42.0, 100.0, labels=["water"])), len(m.query_lonlat(3.0, 42.0, 0.5))
        (1, 1)
        >>> len(m.query_lonlat(-3.0, 42.0, 100.0))  # off the map
        0
        >>> m.query_lonlat(42.0, 95.0, 100.0)
        Traceback (most recent call last):
        mapdb.geo.LonLatError: latitude 95.0 must be a number in [-90, 90] (lon, lat swapped? longitude comes first)
        >>> import warnings
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     len(m.query_lonlat(42.0, 3.0, 100.0)), str(caught[0].message)
        (0, 'lon 42, lat 3 is off the map, and lon 3, lat 42 on it: lon and lat swapped?')
        """
        from pyproj import Geod

        from ..geo import SwappedLonLatWarning, check_lonlat, swapped_lonlat

        lon, lat = check_lonlat(lon, lat)
        if not (isinstance(radius_m, int | float | np.number) and 0.0 <= radius_m < math.inf):
            raise ValueError(f"radius_m {radius_m!r} must be a finite number >= 0")
        radius_m = float(radius_m)
        found, found_lon, found_lat = self._in_lonlat_bbox(self._disc_bbox(lon, lat, radius_m), labels)
        n = len(found)
        if not n:
            swapped = swapped_lonlat(self.crs, self.bounds, lon, lat)
            if swapped:
                warnings.warn(swapped, SwappedLonLatWarning, stacklevel=2)
        _, _, distance = Geod(ellps="WGS84").inv(np.full(n, lon), np.full(n, lat), found_lon, found_lat)
        return found.take(np.asarray(distance) <= radius_m)

    @staticmethod
    def _disc_bbox(lon: float, lat: float, radius_m: float) -> tuple[float, float, float, float]:
        """A lon/lat box sure to hold every point within ``radius_m`` metres (geodesic, WGS 84) of a place.

        Along a geodesic, latitude changes by at most 1/M radians a metre (M, the meridian's radius of
        curvature, is at least a(1 - e^2) on WGS 84) and longitude by at most 1/(N cos(latitude)), N >= a.
        The box crosses the antimeridian (``minlon > maxlon``) or spans every longitude (a pole inside).

        Examples
        --------
        >>> [round(v, 4) for v in MapBase._disc_bbox(179.99, 0.0, 10_000.0)]
        [179.9002, -0.0904, -179.9202, 0.0904]
        >>> MapBase._disc_bbox(0.0, 89.99, 2_000.0)[::2]
        (-180.0, 180.0)
        """
        half_lat = math.degrees(radius_m / 6_335_439.0) + 1e-9  # (the constant keeps a zero radius a proper box)
        south, north = max(-90.0, lat - half_lat), min(90.0, lat + half_lat)
        widest = math.radians(abs(lat) + half_lat)
        if widest >= math.pi / 2:
            return (-180.0, south, 180.0, north)
        half_lon = math.degrees(radius_m / (6_378_137.0 * math.cos(widest))) + 1e-9
        if half_lon >= 180.0:
            return (-180.0, south, 180.0, north)
        west, east = lon - half_lon, lon + half_lon
        return (west + 360.0 if west < -180.0 else west, south, east - 360.0 if east > 180.0 else east, north)

    def _in_lonlat_bbox(self, bbox: tuple[float, float, float, float],
                        labels: Iterable[str] | None) -> tuple[Objects, np.ndarray, np.ndarray]:
        """Objects in a checked lon/lat box, with their longitudes and latitudes.

        The pages are found by :func:`mapdb.geo.projected_window` (which may keep too much, never too
        little); the selection is made on each object's own lon/lat.
        """
        from ..geo import in_bbox, projected_window

        window = projected_window(self.crs, bbox, within=self.bounds)
        if window is None:
            return self._label_filter(Objects.empty(self.labels, self.crs), labels), np.zeros(0), np.zeros(0)
        found = self.query_bbox(*window, labels=labels)
        to_lonlat = self.cached("mapdb.to_lonlat", lambda: Transformer.from_crs(self.crs, "EPSG:4326",
                                                                                always_xy=True))
        lon, lat = (np.asarray(v, np.float64) for v in to_lonlat.transform(found.x, found.y))
        inside = in_bbox(bbox, lon, lat)
        return found.take(inside), lon[inside], lat[inside]


class MemoryMap(MapBase):
    """The :class:`MetaMap` interface over objects held in memory (simulations, tests).

    Positions are rounded to the quantum as a file would store them.

    Examples
    --------
    >>> m = MemoryMap(Objects.from_names([0.0, 100.0], [0.0, 0.0], ["park", "park"], crs="EPSG:3857"))
    >>> len(m.query_radius(0.0, 0.0, 10.0))
    1
    >>> len(m.query_bbox(500.0, 500.0, 600.0, 600.0))
    0
    """

    def __init__(
        self, objects: Objects, quantum: float = DEFAULT_QUANTUM, metadata: dict[str, Any] | None = None
    ) -> None:
        super().__init__()
        self.path = None
        self.quantum = quantum
        self.crs = objects.crs or ""
        self.labels = objects.labels
        x = np.rint(objects.x / quantum) * quantum
        y = np.rint(objects.y / quantum) * quantum
        self._objects = Objects(x, y, objects.label, objects.area, objects.labels, objects.crs, objects.elevation)
        self.elevation_step: float | None = None if objects.elevation is None else 0.0  # held exactly
        self.bounds = (float(x.min()), float(y.min()), float(x.max()), float(y.max())) if len(objects) else (
            0.0, 0.0, 0.0, 0.0)
        counts = np.bincount(objects.label, minlength=len(self.labels))
        self.metadata = {"count": len(objects), "crs": self.crs, "quantum": quantum, "bounds": list(self.bounds),
                         "labels": [{"name": n, "code": i, "count": int(counts[i])}
                                    for i, n in enumerate(self.labels)], **(metadata or {})}

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        o = self._objects
        inside = (o.x >= minx) & (o.x <= maxx) & (o.y >= miny) & (o.y <= maxy)
        return self._label_filter(o.take(inside), labels)

    def all(self) -> Objects:
        return self._objects
