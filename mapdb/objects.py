"""Labelled ground objects as parallel numpy arrays.

Every stage of mapdb passes objects around as :class:`Objects`: centroids
``x``, ``y`` (in the CRS named by ``crs``), a small integer ``label`` code per
object indexing into ``labels`` (the names), and ``area`` in square metres
(0 for point objects).  Arrays, not per-object Python values, so that sources,
the store and the matcher stay vectorised.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # geopandas is imported when a GeoDataFrame is asked for: it takes half a second to load
    import geopandas

__all__ = ["Objects", "concat"]


@dataclass(frozen=True)
class Objects:
    """A set of labelled objects.

    Parameters
    ----------
    x, y : array_like of float
        Centroid coordinates in ``crs`` units (projected metres once in a map).
    label : array_like of int
        Index into ``labels`` for each object.
    area : array_like of float
        Area in square metres, 0 for points.
    labels : sequence of str
        Label names; ``labels[label[i]]`` is the name of object ``i``.
    crs : str or None
        Anything pyproj understands (``"EPSG:32631"``, WKT), or None if unknown.
    elevation : array_like of float, optional
        The ground's height under each object (metres above the DEM's datum; NaN where unknown), or None
        for objects of a map without elevation (flat ground).

    Examples
    --------
    >>> o = Objects.from_names([0.0, 10.0], [0.0, 5.0], ["building", "park"])
    >>> len(o), o.names().tolist()
    (2, ['building', 'park'])
    >>> len(Objects.empty())
    0
    """

    x: np.ndarray
    y: np.ndarray
    label: np.ndarray
    area: np.ndarray
    labels: tuple[str, ...] = ()
    crs: str | None = None
    elevation: np.ndarray | None = None

    def __post_init__(self) -> None:
        x = np.ascontiguousarray(self.x, dtype=np.float64).reshape(-1)
        y = np.ascontiguousarray(self.y, dtype=np.float64).reshape(-1)
        label = np.ascontiguousarray(self.label, dtype=np.int32).reshape(-1)
        area = np.ascontiguousarray(self.area, dtype=np.float64).reshape(-1)
        n = x.size
        if not (y.size == label.size == area.size == n):
            raise ValueError(f"x, y, label and area differ in length: {n}, {y.size}, {label.size}, {area.size}")
        if n and (label.min() < 0 or label.max() >= len(self.labels)):
            raise ValueError(f"label codes must index into the {len(self.labels)} label names")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "label", label)
        object.__setattr__(self, "area", area)
        object.__setattr__(self, "labels", tuple(self.labels))
        if self.elevation is not None:
            elevation = np.ascontiguousarray(self.elevation, dtype=np.float64).reshape(-1)
            if elevation.size != n:
                raise ValueError(f"elevation has {elevation.size} values for {n} objects")
            object.__setattr__(self, "elevation", elevation)

    @classmethod
    def empty(cls, labels: Sequence[str] = (), crs: str | None = None) -> Objects:
        z = np.zeros(0)
        return cls(z, z, np.zeros(0, np.int32), z, tuple(labels), crs)

    @classmethod
    def from_names(
        cls,
        x: Sequence[float] | np.ndarray,
        y: Sequence[float] | np.ndarray,
        names: Sequence[str] | np.ndarray,
        area: Sequence[float] | np.ndarray | None = None,
        crs: str | None = None,
        labels: Sequence[str] | None = None,
    ) -> Objects:
        """Build from label names; ``labels`` fixes the code order (default: sorted unique names)."""
        names = np.asarray(names, dtype=object)
        if labels is None:
            labels = sorted(set(names.tolist()))
        index = {name: i for i, name in enumerate(labels)}
        try:
            codes = np.fromiter((index[n] for n in names), dtype=np.int32, count=names.size)
        except KeyError as exc:
            raise ValueError(f"label {exc.args[0]!r} is not among {list(labels)}") from None
        xs = np.asarray(x, dtype=np.float64)
        areas = np.zeros(xs.size) if area is None else np.asarray(area, dtype=np.float64)
        return cls(xs, np.asarray(y, dtype=np.float64), codes, areas, tuple(labels), crs)

    def __len__(self) -> int:
        return int(self.x.size)

    def names(self) -> np.ndarray:
        """Label name of every object (object array)."""
        return np.asarray(self.labels, dtype=object)[self.label] if len(self) else np.zeros(0, object)

    def take(self, index: np.ndarray) -> Objects:
        """The subset selected by an integer or boolean index."""
        return Objects(self.x[index], self.y[index], self.label[index], self.area[index], self.labels, self.crs,
                       None if self.elevation is None else self.elevation[index])

    def with_elevation(self, elevation: np.ndarray | None) -> Objects:
        """The same objects with these ground elevations (metres, NaN where unknown; None: none)."""
        return Objects(self.x, self.y, self.label, self.area, self.labels, self.crs, elevation)

    def relabel(self, labels: Sequence[str]) -> Objects:
        """The same objects with codes into another label table that contains all names used here."""
        labels = tuple(labels)
        if labels == self.labels:
            return self
        index = {name: i for i, name in enumerate(labels)}
        used = set(np.unique(self.label).tolist())
        missing = [name for i, name in enumerate(self.labels) if i in used and name not in index]
        if missing:
            raise ValueError(f"labels {missing} are not in the target table")
        lut = np.array([index.get(name, -1) for name in self.labels] or [0], dtype=np.int32)
        return Objects(self.x, self.y, lut[self.label], self.area, labels, self.crs, self.elevation)

    def to_geodataframe(self) -> geopandas.GeoDataFrame:
        """The objects as a GeoDataFrame of points in their CRS, one row an object.

        Returns
        -------
        geopandas.GeoDataFrame
            Columns ``label`` (the name), ``area_m2`` (square metres, 0 for point objects) and
            ``geometry`` (points at ``x``, ``y``), with ``crs`` set to the objects' CRS (none when
            ``crs`` is None).  The area column is not called ``area``: ``frame.area`` is geopandas'
            own geometry area (0 for points), which such a column could not override.

        Examples
        --------
        >>> o = Objects.from_names([385440.0], [6671470.0], ["park"], area=[1200.0], crs="EPSG:32635")
        >>> frame = o.to_geodataframe()
        >>> frame[["label", "area_m2"]].values.tolist(), frame.crs.to_epsg(), frame.geometry.x.tolist()
        ([['park', 1200.0]], 32635, [385440.0])

        No objects give an empty frame that still names the CRS; no CRS gives a frame without one:

        >>> empty = Objects.empty(["park"], crs="EPSG:32635").to_geodataframe()
        >>> len(empty), list(empty.columns), empty.crs.to_epsg()
        (0, ['label', 'area_m2', 'geometry'], 32635)
        >>> Objects.from_names([0.0], [0.0], ["park"]).to_geodataframe().crs is None
        True
        """
        import geopandas

        return geopandas.GeoDataFrame({"label": self.names(), "area_m2": self.area},
                                      geometry=geopandas.points_from_xy(self.x, self.y), crs=self.crs)

    def counts(self) -> dict[str, int]:
        """Number of objects per label name (labels with no object left out)."""
        c = np.bincount(self.label, minlength=len(self.labels))
        return {name: int(n) for name, n in zip(self.labels, c, strict=True) if n}


def concat(parts: Sequence[Objects], labels: Sequence[str] | None = None) -> Objects:
    """Concatenate object sets that share a CRS, re-coding labels into one table.

    Examples
    --------
    >>> a = Objects.from_names([0.0], [0.0], ["park"])
    >>> b = Objects.from_names([1.0], [1.0], ["building"])
    >>> concat([a, b]).names().tolist()
    ['park', 'building']
    >>> len(concat([]))
    0
    """
    parts = [p for p in parts if p is not None]
    if labels is None:
        seen: dict[str, None] = {}
        for p in parts:
            seen.update(dict.fromkeys(p.labels))
        labels = tuple(seen)
    if not parts:
        return Objects.empty(labels)
    crs = {p.crs for p in parts if len(p)}
    if len(crs) > 1:
        raise ValueError(f"cannot concatenate objects in different CRSs: {sorted(map(str, crs))}")
    parts = [p.relabel(labels) for p in parts]
    # Elevation is kept when any part has it; the objects of parts without it are unknown (NaN).
    elevation = None if all(p.elevation is None for p in parts) else np.concatenate(
        [np.full(len(p), np.nan) if p.elevation is None else p.elevation for p in parts])
    return Objects(
        np.concatenate([p.x for p in parts]),
        np.concatenate([p.y for p in parts]),
        np.concatenate([p.label for p in parts]),
        np.concatenate([p.area for p in parts]),
        tuple(labels),
        crs.pop() if crs else parts[0].crs,
        elevation,
    )
