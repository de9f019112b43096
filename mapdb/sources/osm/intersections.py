"""Road intersections: the road network's node ids (in memory, or in buckets on disk), the junction nodes
(three arms or more), and one object per crossing.
"""

from __future__ import annotations

import os
from array import array
from collections import Counter
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ...labels import IntersectionRule
from ...objects import Objects
from .areas import _A, _E2, _components, _Ways
from .index import _defined, _release_mapped, _Workspace
from .progress import _PROGRESS_STRIDE

__all__ = ["ROAD_REFS_IN_MEMORY"]

# Node ids of road ways kept in memory; past this many they go to a temporary file, in buckets by node
# id, and the junctions are found one bucket at a time (8 bytes a node id; 32 bytes in the buckets).
ROAD_REFS_IN_MEMORY = 1 << 19
# Buckets of road edges on disk: one per this many bytes of input (a 1 GB extract holds about 20 million
# road node ids, a bucket about a million edges), at least 2 and at most _MAX_EDGE_BUCKETS.
_INPUT_BYTES_PER_BUCKET = 16 << 20
_MAX_EDGE_BUCKETS = 1024


class _RoadNetwork:
    """The node ids of the road ways, for finding junctions: in memory, or in buckets by node id on disk.

    Up to :data:`ROAD_REFS_IN_MEMORY` ids are kept in memory (typed arrays, 8 bytes an id) and the
    junctions found by :func:`_junction_node_ids`.  Past that, each full buffer is turned into directed
    edges ``(node, neighbour)`` that are appended to temporary bucket files by ``node % buckets``, and
    the junctions are found one bucket at a time: memory holds one bucket, not the network.
    """

    def __init__(self, workspace: _Workspace, input_bytes: int) -> None:
        self.workspace = workspace
        self.bucket_count = min(_MAX_EDGE_BUCKETS, max(2, input_bytes // _INPUT_BYTES_PER_BUCKET))
        self.in_memory = ROAD_REFS_IN_MEMORY
        self.refs = array("q")
        self.lengths = array("q")
        self.buckets: list[str] = []

    def add(self, refs: list[int]) -> None:
        if len(refs) < 2:
            return
        self.refs.extend(refs)
        self.lengths.append(len(refs))
        if len(self.refs) >= self.in_memory:
            self._spill()

    def _spill(self) -> None:
        if not self.buckets:
            self.buckets = [self.workspace.file(f"road-edges-{i}", what="road network")
                            for i in range(self.bucket_count)]
        src, dst = _directed_edges(np.frombuffer(self.refs, np.int64), np.frombuffer(self.lengths, np.int64))
        bucket = (src % len(self.buckets)).astype(np.uint16)
        order = np.argsort(bucket, kind="stable")  # a radix sort on 16 bits
        bounds = np.searchsorted(bucket[order], np.arange(len(self.buckets) + 1))
        pairs = np.empty((src.size, 2), np.int64)
        pairs[:, 0], pairs[:, 1] = src[order], dst[order]
        del src, dst, order
        for i, name in enumerate(self.buckets):
            with open(name, "ab") as f:
                pairs[bounds[i]:bounds[i + 1]].tofile(f)
        self.refs, self.lengths = array("q"), array("q")

    def junctions(self) -> np.ndarray:
        """Sorted ids of the nodes with three or more arms (as :func:`_junction_node_ids`)."""
        if not self.buckets:
            return _junction_node_ids(np.frombuffer(self.refs, np.int64), np.frombuffer(self.lengths, np.int64))
        if len(self.refs):
            self._spill()
        found = []
        for name in self.buckets:
            pairs = np.fromfile(name, np.int64).reshape(-1, 2)
            os.unlink(name)
            found.append(_nodes_with_three_arms(pairs[:, 0], pairs[:, 1]))
        return np.sort(np.concatenate(found))


def _ecef(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Earth-centred metric coordinates on the ellipsoid: straight-line distances are true metres."""
    lam, phi = np.radians(lon), np.radians(lat)
    n = _A / np.sqrt(1 - _E2 * np.sin(phi) ** 2)
    return np.column_stack([n * np.cos(phi) * np.cos(lam), n * np.cos(phi) * np.sin(lam),
                            n * (1 - _E2) * np.sin(phi)])


def _ecef_to_lonlat(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.hypot(xyz[:, 0], xyz[:, 1])
    # Exact on the ellipsoid's surface; means of points metres apart lie millimetres below it.
    return np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])), np.degrees(np.arctan2(xyz[:, 2], (1 - _E2) * p))


def _junction_node_ids(refs: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Ids of nodes with three or more arms in the network of the given ways.

    Parameters
    ----------
    refs : array of int
        Node ids of all ways, concatenated.
    lengths : array of int
        Number of nodes of each way (each at least 2).

    Returns
    -------
    ndarray of int64
        Sorted ids of the nodes with edges to three or more distinct neighbour nodes.

    Notes
    -----
    "Arms" are counted as distinct neighbouring nodes over all ways.  A node where one road simply
    continues in its next way has two arms, whatever the names of the two ways (an unnamed road
    split at a bridge, a road whose name changes): it is not an intersection.  Two or more distinct
    roads meeting (a T has three arms, a crossing four) always give three or more.  This makes the
    "distinct roads" test independent of ``name``/``ref`` tagging, which is often missing.

    Examples
    --------
    A T junction: a road 1-2-3 split into two ways at node 2 and a side road 2-4.

    >>> _junction_node_ids(np.array([1, 2, 2, 3, 2, 4]), np.array([2, 2, 2])).tolist()
    [2]
    """
    refs = np.asarray(refs, np.int64)
    lengths = np.asarray(lengths, np.int64)
    if refs.size < 2:
        return np.zeros(0, np.int64)
    ids, index = np.unique(refs, return_inverse=True)
    index = index.reshape(-1)
    way = np.repeat(np.arange(lengths.size), lengths)
    inside = (way[1:] == way[:-1]) & (index[1:] != index[:-1])
    a, b = index[:-1][inside], index[1:][inside]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    edges = _sorted_unique(lo * ids.size + hi)
    arms = np.bincount(edges // ids.size, minlength=ids.size) + np.bincount(edges % ids.size, minlength=ids.size)
    return ids[arms >= 3]


def _sorted_unique(values: np.ndarray) -> np.ndarray:
    """``np.unique(values)`` by a sort (numpy 2.3's hashing ``unique`` takes seconds on millions of ids).

    Examples
    --------
    >>> _sorted_unique(np.array([3, 1, 3, 2])).tolist()
    [1, 2, 3]
    """
    values = np.sort(values)
    keep = np.ones(values.size, bool)
    keep[1:] = values[1:] != values[:-1]
    return values[keep]


def _directed_edges(refs: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both directions of every step between two different consecutive nodes of a way: (node, neighbour).

    Examples
    --------
    >>> [e.tolist() for e in _directed_edges(np.array([1, 2, 2, 3, 2, 4]), np.array([2, 2, 2]))]
    [[1, 2, 2, 2, 3, 4], [2, 3, 4, 1, 2, 2]]
    """
    way = np.repeat(np.arange(lengths.size), lengths)
    inside = (way[1:] == way[:-1]) & (refs[1:] != refs[:-1])
    a, b = refs[:-1][inside], refs[1:][inside]
    return np.concatenate([a, b]), np.concatenate([b, a])


def _nodes_with_three_arms(node: np.ndarray, neighbour: np.ndarray) -> np.ndarray:
    """Sorted ids of the nodes with three or more distinct neighbours among directed edges.

    The arms of :func:`_junction_node_ids`, counted from the edges of the nodes of one bucket.

    Examples
    --------
    >>> _nodes_with_three_arms(*_directed_edges(np.array([1, 2, 2, 3, 2, 4]), np.array([2, 2, 2]))).tolist()
    [2]
    """
    if node.size == 0:
        return np.zeros(0, np.int64)
    nodes, node_index = np.unique(node, return_inverse=True)
    others, other_index = np.unique(neighbour, return_inverse=True)
    edges = _sorted_unique(node_index.reshape(-1) * others.size + other_index.reshape(-1))
    arms = np.bincount(edges // others.size, minlength=nodes.size)
    return nodes[arms >= 3]


def _junction_locations(locations: Any, index_file: str | None, junctions: np.ndarray,
                        counts: Counter[str]) -> tuple[np.ndarray, np.ndarray]:
    """Lon/lat of the junction nodes the index ``locations`` holds (the pages of its file ``index_file``, if
    it has one, released as the lookups go)."""
    lon, lat = array("d"), array("d")
    for i, node_id in enumerate(junctions.tolist()):
        if index_file is not None and i % _PROGRESS_STRIDE == 0:
            _release_mapped(index_file)
        try:
            location = locations.get(node_id)
        except KeyError:  # a node outside the extract: no location, no object
            continue
        if not location.valid():
            counts["invalid_coordinates"] += int(_defined(location))
            continue
        lon.append(location.lon)
        lat.append(location.lat)
    if index_file is not None:
        _release_mapped(index_file)
    return np.frombuffer(lon, float), np.frombuffer(lat, float)


def _intersection_objects(roads: _RoadNetwork, ways: _Ways, locations: Any, index_file: str | None,
                          rule: IntersectionRule, labels: tuple[str, ...], counts: Counter[str]) -> Objects:
    """Junction nodes of the road network, those of one crossing within ``merge_distance_m`` merged.

    ``ways`` are the ways that are objects of their own; ``locations`` is the pass's node location index
    and ``index_file`` its file (None in memory).
    """
    junctions = roads.junctions()
    if len(ways.refs):
        # A junction on a way that is an object of its own (a roundabout ring) is part of that
        # object: the camera sees one roundabout, not one intersection per entry.
        junctions = junctions[~np.isin(junctions, np.frombuffer(ways.refs, np.int64))]
    lon, lat = _junction_locations(locations, index_file, junctions, counts)
    if not lon.size:
        return Objects.empty(labels, "EPSG:4326")
    xyz = _ecef(lon, lat)
    pairs = cKDTree(xyz).query_pairs(rule.merge_distance_m, output_type="ndarray")
    cluster = _components(len(xyz), pairs[:, 0], pairs[:, 1])
    n = int(cluster.max()) + 1
    size = np.bincount(cluster, minlength=n)
    mean = np.column_stack([np.bincount(cluster, xyz[:, k], n) / size for k in range(3)])
    out_lon, out_lat = _ecef_to_lonlat(mean)
    code = np.full(n, labels.index(rule.label), np.int32)
    return Objects(out_lon, out_lat, code, np.zeros(n), labels, "EPSG:4326")
