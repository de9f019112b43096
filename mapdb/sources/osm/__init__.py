"""OpenStreetMap source: labelled objects from ``.osm`` / ``.osm.pbf`` extracts.

One pass of pyosmium's :class:`osmium.FileProcessor` with its node-location
index and multipolygon assembly.  Tag filters run in C++, so only objects that
some rule of the label table may match ever reach Python:

* areas (closed ways and multipolygon relations, assembled by osmium) whose
  tags match an ``"area"`` rule become one object at the area centroid, with
  the area of the outer rings minus the inner rings;
* tagged nodes matching a ``"node"`` rule become point objects (area 0);
* ways matching a ``"way"`` rule (roundabouts drawn as rings) become one object
  per group of such ways that share nodes, at the centroid of their lines;
* road intersections are computed from the node lists of the highway ways named
  in the table's intersection rule.

Per object, Python does only the tag test and asks osmium for WKB; geometry
(areas, centroids) is computed in blocks of :data:`AREA_BLOCK` areas with shapely
and numpy as the pass goes, and the geometries are dropped: the blocks of compact
objects (position, label, area) go to spools (:func:`read_osm_spooled`: temporary
files, 28 bytes an object), the road network's node ids to temporary files past
:data:`ROAD_REFS_IN_MEMORY`, and the node location index lives in a file for inputs
from :data:`FILE_INDEX_BYTES` up (:func:`choose_node_index`).  libosmium keeps the
multipolygon relations of the first pass, with their members, until they are complete:
only those some area rule labels are given to it.  Coordinates stay in lon/lat
(``EPSG:4326``); areas are in square metres.

Broken data is skipped or repaired and counted (``read_osm(counts=...)``), never
silently moved and never a traceback: nodes whose coordinates are out of range
or not numbers, ways tagged as areas that do not close, areas cut by a clipped
extract's border (a node or member way missing from the file), rings that cross
themselves (rebuilt with shapely's ``make_valid``).  Compressed XML is inflated
under a bound (:func:`inflation_limit`), so a decompression bomb costs at most
that much time, memory and temporary disk before a one-line error.

The modules, one concept each: :mod:`.reader` (:func:`read_osm`, the pass and what follows it),
:mod:`.scan` (pyosmium's reader with its C++ tag filters, each object's handling, the repair of
self-crossing rings), :mod:`.files` (file checks, bounded inflation of compressed XML),
:mod:`.index` (the node location index and the temporary files of large inputs), :mod:`.progress`,
:mod:`.areas` (areas, centroids and ways in local equal-area coordinates) and :mod:`.intersections`
(the road network and its junctions).  This package re-exports their public names.
"""

from __future__ import annotations

from .files import MAX_INFLATION, MIN_INFLATED_BYTES, OSM_SUFFIXES, inflation_limit, is_osm_path
from .index import DENSE_INDEX_BYTES, FILE_INDEX_BYTES, NODE_INDEXES, choose_node_index
from .intersections import ROAD_REFS_IN_MEMORY
from .reader import TRIM_INPUT_BYTES, read_osm, read_osm_spooled
from .scan import AREA_BLOCK, POINT_BLOCK

__all__ = ["AREA_BLOCK", "DENSE_INDEX_BYTES", "FILE_INDEX_BYTES", "MAX_INFLATION", "MIN_INFLATED_BYTES",
           "NODE_INDEXES", "OSM_SUFFIXES", "POINT_BLOCK", "ROAD_REFS_IN_MEMORY", "TRIM_INPUT_BYTES",
           "choose_node_index", "inflation_limit", "is_osm_path", "read_osm", "read_osm_spooled"]
