"""Geometry of the objects read: areas and centroids of osmium's polygons and of groups of ways.

Computed in blocks with shapely and numpy, in local equal-area coordinates; the geometries are dropped
once their objects (position, label, area) are made.
"""

from __future__ import annotations

from array import array
from collections import Counter
from typing import Any

import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ...objects import Objects

# Nothing public: the objects are read through mapdb.sources.osm.reader.read_osm.
__all__: list[str] = []

# WGS84 ellipsoid.
_A = 6378137.0
_F = 1 / 298.257223563
_E2 = _F * (2 - _F)


# --------------------------------------------------------------------------------------------------
# Geometry: local equal-area coordinates
#
# x = N(lat0) * cos(lat) * (lon - lon0), y = M(lat0) * (lat - lat0), in radians, with the meridional
# (M) and prime-vertical (N) radii of curvature of the ellipsoid frozen at the object's reference
# latitude lat0.  The Jacobian is M(lat0) N(lat0) cos(lat): the ellipsoid's own area element with
# M and N taken constant, so areas are exact up to the change of M and N across one object (below
# 1e-3 relative for objects under 100 km).  Centroids computed in these coordinates are area
# centroids and map back exactly.


def _radii(lat0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s2 = np.sin(np.radians(lat0)) ** 2
    w = np.sqrt(1 - _E2 * s2)
    return _A * (1 - _E2) / w**3, _A / w


def _to_local(lon: np.ndarray, lat: np.ndarray, lon0: np.ndarray, lat0: np.ndarray) -> np.ndarray:
    m, n = _radii(lat0)
    x = n * np.cos(np.radians(lat)) * np.radians(lon - lon0)
    y = m * np.radians(lat - lat0)
    return np.column_stack([x, y])


def _from_local(
    x: np.ndarray, y: np.ndarray, lon0: np.ndarray, lat0: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    m, n = _radii(lat0)
    lat = lat0 + np.degrees(y / m)
    lon = lon0 + np.degrees(x / (n * np.cos(np.radians(lat))))
    return lon, lat


def _point_objects(lon: array, lat: array, code: array, labels: tuple[str, ...]) -> Objects:
    return Objects(np.frombuffer(lon, float), np.frombuffer(lat, float), np.frombuffer(code, np.int32),
                   np.zeros(len(code)), labels, "EPSG:4326")


def _area_objects(geoms: np.ndarray, codes: list[int], labels: tuple[str, ...], counts: Counter[str]) -> Objects:
    """Centroid and m^2 area of osmium's multipolygons (shapely geometries in lon/lat, whose coordinates this
    moves in place), all in a few vectorised shapely calls.

    A multipolygon that is not valid in the local equal-area coordinates (osmium checks the rings
    it assembles, so this is rare) is repaired with ``make_valid`` and counted, or dropped and counted
    when nothing of it has an area.
    """
    if not len(geoms):
        return Objects.empty(labels, "EPSG:4326")
    codes_ = np.asarray(codes, np.int32)
    bounds = shapely.bounds(geoms)
    lon0 = (bounds[:, 0] + bounds[:, 2]) / 2
    lat0 = (bounds[:, 1] + bounds[:, 3]) / 2
    coords, owner = shapely.get_coordinates(geoms, return_index=True)
    local = shapely.set_coordinates(geoms, _to_local(coords[:, 0], coords[:, 1], lon0[owner], lat0[owner]))
    invalid = ~shapely.is_valid(local)
    if invalid.any():
        local[invalid] = shapely.make_valid(local[invalid], method="structure", keep_collapsed=False)
    area = shapely.area(local)
    centroid = shapely.get_coordinates(shapely.centroid(local))
    lon, lat = _from_local(centroid[:, 0], centroid[:, 1], lon0, lat0)
    keep = np.isfinite(lon) & np.isfinite(lat) & (~invalid | (area > 0))
    counts["repaired_geometries"] += int((invalid & keep).sum())
    counts["invalid_geometries"] += int((invalid & ~keep).sum())
    return Objects(lon[keep], lat[keep], codes_[keep], area[keep], labels, "EPSG:4326")


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected-component id of each of ``n`` vertices joined by edges ``a[i]--b[i]``."""
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


class _Ways:
    """The ways matched by a "way" rule: node ids and locations of all of them, one after the other, and the
    number of nodes and label code of each (typed arrays: no long-lived Python numbers, which would pin the
    allocator's arenas between the blocks of areas)."""

    def __init__(self) -> None:
        self.refs = array("q")
        self.lon = array("d")
        self.lat = array("d")
        self.lengths = array("q")
        self.code = array("i")

    def add(self, nodes: list[Any], code: int) -> None:
        """One way, from its nodes (osmium's node refs with valid locations; at least one)."""
        self.refs.extend(n.ref for n in nodes)
        self.lon.extend(n.lon for n in nodes)
        self.lat.extend(n.lat for n in nodes)
        self.lengths.append(len(nodes))
        self.code.append(code)


def _way_objects(ways: _Ways, labels: tuple[str, ...]) -> Objects:
    """One object per group of same-label ways sharing nodes (the pieces of one roundabout).

    Centroid: length-weighted centroid of the group's lines.  Area: the convex hull of the
    group's nodes, which for a roundabout ring is the ground it encloses (0 for a straight line).
    """
    if not len(ways.code):
        return Objects.empty(labels, "EPSG:4326")
    lengths = np.frombuffer(ways.lengths, np.int64)
    way_of_node = np.repeat(np.arange(lengths.size), lengths)
    refs = np.frombuffer(ways.refs, np.int64)
    lon = np.frombuffer(ways.lon, float)
    lat = np.frombuffer(ways.lat, float)
    codes = np.frombuffer(ways.code, np.int32)

    # Ways join when they share a node and a label: components of the way--node bipartite graph,
    # nodes keyed by (id, label) so that differently labelled ways never merge.
    node_index = _pair_index(refs, codes[way_of_node])
    n_ways = lengths.size
    group_of_way = _components(n_ways + int(node_index.max()) + 1, way_of_node, n_ways + node_index)[:n_ways]
    _, group_of_way = np.unique(group_of_way, return_inverse=True)
    n_groups = int(group_of_way.max()) + 1
    group = group_of_way[way_of_node]

    count = np.bincount(group, minlength=n_groups)
    lon0 = np.bincount(group, lon, n_groups) / count
    lat0 = np.bincount(group, lat, n_groups) / count
    xy = _to_local(lon, lat, lon0[group], lat0[group])

    # Segments inside each way (not across the boundary between two consecutive ways).
    same_way = way_of_node[1:] == way_of_node[:-1]
    seg_len = np.hypot(*(xy[1:] - xy[:-1]).T) * same_way
    seg_mid = (xy[1:] + xy[:-1]) / 2
    seg_group = group[1:]
    total = np.bincount(seg_group, seg_len, n_groups)
    mean_x = np.bincount(group, xy[:, 0], n_groups) / count
    mean_y = np.bincount(group, xy[:, 1], n_groups) / count
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = np.where(total > 0, np.bincount(seg_group, seg_len * seg_mid[:, 0], n_groups) / total, mean_x)
        cy = np.where(total > 0, np.bincount(seg_group, seg_len * seg_mid[:, 1], n_groups) / total, mean_y)
    out_lon, out_lat = _from_local(cx, cy, lon0, lat0)

    area = _hull_areas(xy, group, n_groups)
    group_code = np.zeros(n_groups, np.int32)
    group_code[group_of_way] = codes
    return Objects(out_lon, out_lat, group_code, area, labels, "EPSG:4326")


def _pair_index(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The index of each pair (a[i], b[i]) among the distinct pairs in sorted order (``np.unique`` of the
    rows' inverse, without its copies of the rows).

    Examples
    --------
    >>> _pair_index(np.array([5, 3, 5, 5]), np.array([1, 2, 1, 0])).tolist()
    [2, 0, 2, 1]
    """
    order = np.lexsort((b, a))
    a_sorted, b_sorted = a[order], b[order]
    new = np.ones(order.size, bool)
    new[1:] = (a_sorted[1:] != a_sorted[:-1]) | (b_sorted[1:] != b_sorted[:-1])
    del a_sorted, b_sorted
    index = np.empty(order.size, np.int64)
    index[order] = np.cumsum(new) - 1
    return index


# Points whose convex hulls GEOS builds at once (its geometries take some 200 bytes a point).
_HULL_POINTS = 1 << 16


def _hull_areas(xy: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """The area of the convex hull of each group's points, groups taken a slice at a time so that GEOS holds a
    bounded number of points."""
    order = np.argsort(group, kind="stable")
    ends = np.cumsum(np.bincount(group, minlength=n_groups))
    area = np.empty(n_groups)
    first = 0
    while first < n_groups:
        start = ends[first - 1] if first else 0
        # Whole groups up to about _HULL_POINTS points (at least one group).
        last = max(first + 1, int(np.searchsorted(ends, start + _HULL_POINTS, side="right")))
        take = order[start:ends[last - 1]]
        points = shapely.multipoints(xy[take], indices=group[take] - first)
        area[first:last] = shapely.area(shapely.convex_hull(points))
        first = last
    return area
