"""Blocks: buildings whose footprints touch, stored as map objects of their own.

A segmentation model does not separate buildings that touch: a terrace, a row of houses or a medieval
street front comes out of it as one blob, whose centroid lies near no building's.  The map knows every
footprint at build time, so it also stores what a camera sees as one blob: buildings whose footprints touch
or lie within :data:`DEFAULT_GAP_M` of each other form a *block*, and every block of two or more buildings
is stored as an object labelled :data:`BLOCK_LABEL`, at its union's centroid with its union's area, beside
its buildings (which stay in the map as they were).

How (all vectorised with shapely 2 and scipy): the footprints, projected about their median place (an equal-area
projection), are grown by half the gap; an STRtree gives every pair whose grown footprints intersect; the
connected components of that graph (:func:`scipy.sparse.csgraph.connected_components`) are the blocks; each
block's union is the ``buffer(0)`` of the multipolygon of its members' parts (one call for all blocks), whose
centroid, taken back to lon/lat, and area (square metres) are stored.

The gap: 0.75 m.  Rendered masks (``mapdb simulate --render masks``, 640x480, 60 degrees) have ground pixels of
0.22 m at 120 m and 0.54 m at 300 m: two footprints closer than about a pixel share the pixels between them,
and a model's mask closes one or two pixels more.  A gap of 0.5-1 m is that width; 0.75 m is its middle
(``benchmarks/blocks.py`` prints the share of buildings in blocks at 0, 0.5, 0.75 and 1 m).

Used by :func:`mapdb.build.pipeline.read_one_source`: the OSM reader and the layer reader hand each
building footprint they read to a :class:`BuildingOutlines` (in lon/lat), and the blocks are added as one
more set of the source's objects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import shapely
from pyproj import CRS, Transformer
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..geo import in_bbox
from ..labels import BLOCK_LABEL, BUILDING_LABEL
from ..objects import Objects
from ..progress import Progress
from ..sources.spool import ObjectSpool

__all__ = ["BLOCK_LABEL", "BUILDING_LABEL", "DEFAULT_GAP_M", "MAX_GAP_M", "BuildingOutlines", "block_members",
           "block_objects", "blocks_of", "blocks_spool", "forms_blocks"]

# BLOCK_LABEL, the label of blocks, is declared in mapdb/data/labels.toml after every other, so that no code
# moves; BUILDING_LABEL's footprints form them.
# Footprints this close (metres) join one block (module docs); the largest gap accepted.
DEFAULT_GAP_M = 0.75
MAX_GAP_M = 5.0


def block_members(footprints: np.ndarray, gap: float = DEFAULT_GAP_M) -> np.ndarray:
    """The block of each footprint: ids ``0..B-1`` for footprints in blocks of two or more, -1 for the others.

    Parameters
    ----------
    footprints : array of shapely geometries
        Polygons or multipolygons in a metric CRS (projected metres).
    gap : float
        Footprints whose distance is at most ``gap`` metres are joined (touching ones always).

    Returns
    -------
    ndarray of int64
        Block ids numbered in the order of each block's first footprint.

    Examples
    --------
    >>> import shapely
    >>> boxes = shapely.box([0, 10, 10.5, 30], 0, [10, 10.4, 20, 40], 10)
    >>> block_members(boxes, 0.75).tolist()
    [0, 0, 0, -1]
    >>> block_members(boxes, 0.0).tolist()
    [0, 0, -1, -1]
    """
    footprints = np.asarray(footprints, dtype=object)
    n = footprints.size
    if n < 2:
        return np.full(n, -1, np.int64)
    # Grown by half the gap each, two footprints meet when they were at most the gap apart; a zero gap keeps
    # them as they are (touching ones intersect).
    grown = shapely.buffer(footprints, gap / 2.0, quad_segs=2) if gap > 0 else footprints
    a, b = shapely.STRtree(grown).query(grown, predicate="intersects")
    other = a != b
    graph = coo_matrix((np.ones(int(other.sum()), np.int8), (a[other], b[other])), shape=(n, n))
    component = connected_components(graph, directed=False)[1]
    size = np.bincount(component)
    in_block = size[component] >= 2
    out = np.full(n, -1, np.int64)
    if in_block.any():
        # Renumbered 0..B-1 by first appearance, so that the stored order follows the input's.
        _, first, inverse = np.unique(component[in_block], return_index=True, return_inverse=True)
        rank = np.empty(first.size, np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(first.size)
        out[in_block] = rank[inverse.reshape(-1)]
    return out


def blocks_of(footprints: np.ndarray, gap: float = DEFAULT_GAP_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of metric footprints: each block's union centroid ``(B, 2)``, union area ``(B,)`` and
    number of buildings ``(B,)``.

    Examples
    --------
    >>> import shapely
    >>> xy, area, members = blocks_of(shapely.box([0, 10, 30], 0, [10, 20, 40], 10))
    >>> xy.tolist(), area.tolist(), members.tolist()
    ([[10.0, 5.0]], [200.0], [2])
    """
    footprints = np.asarray(footprints, dtype=object)
    block = block_members(footprints, gap)
    inside = np.flatnonzero(block >= 0)
    if not inside.size:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64)
    parts, owner = shapely.get_parts(footprints[inside], return_index=True)
    part_block = block[inside][owner]
    order = np.argsort(part_block, kind="stable")  # shapely takes the parts grouped by their multipolygon
    # buffer(0) of a multipolygon whose parts overlap is their union: every block's in one call.
    union = shapely.buffer(shapely.multipolygons(parts[order], indices=part_block[order]), 0)
    return shapely.get_coordinates(shapely.centroid(union)), shapely.area(union), np.bincount(block[inside])


class BuildingOutlines:
    """Building footprints handed over by a reader as it goes (lon/lat), made into blocks once it is done.

    Parameters
    ----------
    code : int
        The building label's code in the reader's label table: the only footprints kept.

    Examples
    --------
    >>> import shapely
    >>> outlines = BuildingOutlines(0)
    >>> boxes = shapely.box([7.0, 7.0001, 7.01], 45.0, [7.0001, 7.0002, 7.0101], 45.0001)
    >>> outlines.add_wkb(shapely.to_wkb(boxes, hex=True).tolist(), [0, 0, 0])
    >>> blocks = outlines.blocks(["building", "building_block"])
    >>> len(outlines), len(blocks), blocks.names().tolist(), round(float(blocks.area[0]))
    (3, 1, ['building_block'], 175)
    """

    def __init__(self, code: int) -> None:
        self.code = code
        self.wkb: list[Any] = []

    def add_wkb(self, wkbs: Sequence[Any], codes: Sequence[int] | np.ndarray) -> None:
        """Footprints as WKB (bytes or hex) in lon/lat, with their label codes (other labels are ignored)."""
        keep = np.flatnonzero(np.asarray(codes) == self.code)
        if keep.size:
            # Through keep(): kept as binary WKB (half osmium's hex text) in memory, or in tile files past a bound
            # (mapdb.build.tiles.SpillingOutlines), until the blocks are made.
            self.keep(shapely.from_wkb(np.asarray(wkbs, dtype=object)[keep]))

    def add_areas(self, geoms: np.ndarray, codes: Sequence[int] | np.ndarray) -> None:
        """Footprints as shapely geometries in lon/lat, with their label codes (other labels are ignored): an OSM
        reader's areas (:data:`mapdb.sources.osm.scan.OutlineSink`), kept as WKB before the call returns."""
        keep = np.flatnonzero(np.asarray(codes) == self.code)
        if keep.size:
            self.keep(np.asarray(geoms, dtype=object)[keep])

    def add_geometries(self, geoms: np.ndarray, names: np.ndarray, crs: Any) -> None:
        """A layer's geometries in ``crs`` with their label names: the building polygons, taken to lon/lat."""
        geoms = np.asarray(geoms, dtype=object)
        polygonal = np.isin(shapely.get_type_id(geoms), (3, 6)) & ~shapely.is_empty(geoms)
        geoms = geoms[polygonal & (np.asarray(names, dtype=object) == BUILDING_LABEL)]
        if not geoms.size:
            return
        source = CRS.from_user_input(crs)
        if not source.equals(CRS.from_epsg(4326), ignore_axis_order=True):
            to_lonlat = Transformer.from_crs(source, "EPSG:4326", always_xy=True)
            geoms = shapely.transform(geoms, lambda xy: np.column_stack(to_lonlat.transform(xy[:, 0], xy[:, 1])))
        self.keep(geoms)

    def keep(self, geoms: np.ndarray) -> None:
        """Keep footprints in lon/lat until the blocks are made (here: in memory, as binary WKB)."""
        self.wkb.extend(shapely.to_wkb(geoms).tolist())

    def spool(self, labels: Sequence[str], gap: float, bbox: tuple[float, float, float, float] | None,
              say: Progress | None) -> ObjectSpool:
        """The blocks, as one more spool of the source's objects (in memory: blocks are a few percent of the
        objects); the footprints are then dropped."""
        blocks = self.blocks(labels, gap, bbox)
        if say is not None:
            say(f"  {len(blocks):,} blocks of touching buildings (gap {gap:g} m) from {len(self):,} footprints")
        self.wkb.clear()
        spool = ObjectSpool(labels, "EPSG:4326")
        spool.add(blocks)
        return spool

    def __len__(self) -> int:
        return len(self.wkb)

    def blocks(self, labels: Sequence[str], gap: float = DEFAULT_GAP_M,
               bbox: tuple[float, float, float, float] | None = None) -> Objects:
        """The blocks of the footprints handed over, as objects labelled :data:`BLOCK_LABEL` in lon/lat.

        ``labels`` is the reader's label table (it must hold :data:`BLOCK_LABEL`); ``bbox`` keeps the blocks
        whose centroid lies inside, as the readers keep objects.
        """
        labels = tuple(labels)
        empty = Objects.empty(labels, "EPSG:4326")
        if len(self.wkb) < 2:
            return empty
        geoms = shapely.from_wkb(np.asarray(self.wkb, dtype=object))
        lon, lat = shapely.get_coordinates(shapely.centroid(geoms)).T
        finite = np.isfinite(lon) & np.isfinite(lat)
        if finite.sum() < 2:
            return empty
        geoms = geoms[finite]
        # A Lambert azimuthal equal-area projection about the footprints' median place: areas exact, distances
        # within 0.3 % up to 1,000 km from it (a gap of 0.75 m stays within 2 mm).
        zone = (f"+proj=laea +lat_0={float(np.median(lat[finite])):.6f} +lon_0={float(np.median(lon[finite])):.6f} "
                "+datum=WGS84 +units=m +no_defs")
        to_zone = Transformer.from_crs("EPSG:4326", zone, always_xy=True)
        metric = shapely.transform(geoms, lambda xy: np.column_stack(to_zone.transform(xy[:, 0], xy[:, 1])))
        invalid = ~shapely.is_valid(metric)  # a ring crossing itself: GEOS's predicates may refuse it as it is
        if invalid.any():
            metric[invalid] = shapely.make_valid(metric[invalid], method="structure", keep_collapsed=False)
        xy, area, _ = blocks_of(metric, gap)
        if not len(area):
            return empty
        back = Transformer.from_crs(zone, "EPSG:4326", always_xy=True)
        return block_objects(xy, area, back, labels, bbox)


def block_objects(xy: np.ndarray, area: np.ndarray, back: Transformer, labels: Sequence[str],
                  bbox: Sequence[float] | None) -> Objects:
    """Blocks found in a metric zone as lon/lat :class:`Objects` of :data:`BLOCK_LABEL`.

    ``back`` turns the zone's ``xy`` (n x 2 metres) into lon/lat; blocks whose centroid does not come back
    finite, or lies outside ``bbox``, are dropped, as the readers drop objects.
    """
    block_lon, block_lat = (np.asarray(v) for v in back.transform(xy[:, 0], xy[:, 1]))
    keep = np.isfinite(block_lon) & np.isfinite(block_lat)
    if bbox is not None:
        keep &= in_bbox(bbox, block_lon, block_lat)
    code = np.full(int(keep.sum()), list(labels).index(BLOCK_LABEL), np.int32)
    return Objects(block_lon[keep], block_lat[keep], code, area[keep], tuple(labels), "EPSG:4326")


def forms_blocks(labels: Sequence[str], gap: float | None) -> bool:
    """Whether a source is to form blocks: asked for (a gap), and the label table has both labels."""
    return gap is not None and BUILDING_LABEL in labels and BLOCK_LABEL in labels


def blocks_spool(outlines: BuildingOutlines, labels: Sequence[str], gap: float,
                 bbox: tuple[float, float, float, float] | None, say: Progress | None) -> ObjectSpool:
    """The blocks of a source's building footprints, as one more spool of the source's objects
    (:meth:`BuildingOutlines.spool`); the footprints are then dropped."""
    return outlines.spool(labels, gap, bbox, say)
