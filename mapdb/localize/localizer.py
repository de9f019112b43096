"""Localize images in a map: image objects in, position (or a reasoned rejection) out.

A :class:`Localizer` holds an open map with the matcher's indexes and options and answers images one after
another; :func:`localize` answers one image with the localizer kept for its map (:func:`localizer_for`).
Each answer takes the same steps: parse the image and pick the prior that applies
(:mod:`mapdb.localize.priors`), keep the objects the map knows as points of the image plane
(:mod:`mapdb.localize.image_points`), run the matcher on the indexes of the map region the prior reaches,
and make the answer (:mod:`mapdb.localize.records`, which documents its fields).  A batch of documents is
answered by :func:`mapdb.localize.batch.localize_documents`.
"""

from __future__ import annotations

import math
import sys
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..answers import Answer, Candidate
from ..detections.images import ImageObjects, parse_image
from ..errors import ImageInputError, MapdbError
from ..mapfile.reader import MetaMap
from ..match.evidence.blobs import outward_normals
from ..match.fast import FastOptions, ObjectIndex, QuadIndex, match_fast
from ..match.hypotheses import PRIOR_SLACK
from ..match.index.layout import index_path
from ..match.mapobjects.blocks_view import BlocksView, block_quads, has_blocks, wants_blocks
from ..match.mapobjects.paged_objects import PAGED_FROM_OBJECTS, WholeMapObjects
from ..match.paper.options import PaperOptions
from ..match.pose_prior import PosePrior
from ..match.quad_block import QuadBlock
from ..match.quads import near_only
from ..objects import Objects
from .image_points import image_points, known_objects, scale_hints
from .priors import outside_bounds, pose_prior, prior_margin, resolve_prior
from .records import FoundPose, RejectionError, finite, ok_record, rejected, rounded

if TYPE_CHECKING:  # imported where used: an answer with a prior never opens the stored index
    from ..match.index.stored import StoredQuadIndex

__all__ = ["METHODS", "Localizer", "localize", "localizer_for"]

METHODS = ("fast", "paper")
# With a prior, quad indexes are built and cached per square tile of the map (only the pages near the
# prior are read); a tile's anchors find their neighbours within this margin around it.
TILE_SIZE_M = 1000.0
TILE_PAD_M = 150.0
# A prior reaching over more tiles than this is served by the whole map's index instead.
MAX_PRIOR_TILES = 64
# A map of at most this many objects answers priors from one quad index of the whole map (with the quads'
# positions) instead of tiles: building it costs about what the tiles of one prior's disc cost.
SMALL_MAP_OBJECTS = 2_000
# Blocks of tiles around a prior (their tiles looked up as one quad index: QuadBlock) kept in memory, the least
# recently used dropped first: a flight wandering over 3 x 3 tiles never rebuilds one.
MAX_CACHED_BLOCKS = 9
# Quads of the tiles' own indexes kept in memory (about 100 bytes each), the least recently used tile
# dropped first: a long flight's memory stays bounded.
MAX_CACHED_QUADS = 4_000_000


def _image_id(image: Any) -> Any:
    if isinstance(image, ImageObjects):
        return image.id
    if isinstance(image, dict):
        value = image.get("id")
        return value if isinstance(value, str | int) and not isinstance(value, bool) else None
    return None


class _Recent:
    """A least-recently-used cache holding at most ``limit`` units (entries, or the ``size`` of each)."""

    def __init__(self, limit: int, size: Callable[[Any], int] = lambda value: 1) -> None:
        self.limit = limit
        self.size = size
        self.entries: OrderedDict = OrderedDict()
        self.held = 0

    def __contains__(self, key: Any) -> bool:
        return key in self.entries

    def recent(self, key: Any) -> Any:
        """The entry of ``key``, now the most recently used, or None when there is none."""
        value = self.entries.get(key)
        if value is not None:
            self.entries.move_to_end(key)
        return value

    def get(self, key: Any, factory: Callable[[], Any]) -> Any:
        value = self.recent(key)  # else factory()'s value (never None), kept
        if value is not None:
            return value
        value = factory()
        self.entries[key] = value
        self.held += self.size(value)
        while self.held > self.limit and len(self.entries) > 1:
            _, old = self.entries.popitem(last=False)
            self.held -= self.size(old)
        return value


class StoredQuads:
    """A stored lost-in-space index (:class:`~mapdb.match.index.stored.StoredQuadIndex`) in the matcher's
    lookup interface: the query row of each hit and the hit's four map points."""

    def __init__(self, stored: StoredQuadIndex) -> None:
        self.stored = stored
        self.n_quads = stored.n_quads

    def lookup(self, invariants: np.ndarray, labels: np.ndarray, radius: np.ndarray, k: int,
               near: tuple[complex, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        try:
            rows, ids = self.stored.lookup(invariants, labels, radius, k)
            points = self.stored.coordinates(ids)
        except MapdbError as exc:  # a damaged block, a quad not where it is filed: the index, not the map
            raise _StoredIndexError(str(exc)) from None
        return near_only(rows, points, near)  # the stored index knows no positions


class _StoredIndexError(Exception):
    """A stored index found damaged (or not its map's) during a lookup: the image is answered again without."""


def _warn_stderr(message: str) -> None:
    """Say ``mapdb: warning: MESSAGE`` on one line of standard error (the default of :attr:`Localizer.warn`)."""
    print(f"mapdb: warning: {message}", file=sys.stderr, flush=True)


class NearQuads:
    """A quad index looked up only for quads within ``reach`` metres of ``centre``: where a prior lets an
    image's quads lie (its disc widened by the footprint).  Tiles hold quad positions, so there the prior
    applies before a lookup's nearest hits are taken (:class:`~mapdb.match.quads.QuadIndex`)."""

    def __init__(self, index: QuadIndex | StoredQuads, centre: complex, reach: float) -> None:
        self.index, self.near = index, (centre, reach)
        self.n_quads = index.n_quads

    def lookup(self, invariants: np.ndarray, labels: np.ndarray, radius: np.ndarray,
               k: int) -> tuple[np.ndarray, np.ndarray]:
        return self.index.lookup(invariants, labels, radius, k, near=self.near)

    def quad_part(self) -> tuple[QuadIndex, tuple[complex, float]] | None:
        """The in-memory index and the disc it is looked up in, for one kernel call over a prior's tiles
        (:func:`~mapdb.match.quads.lookup_parts`); None for a stored index."""
        return (self.index, self.near) if isinstance(self.index, QuadIndex) else None


class Localizer:
    """A map with the matcher's indexes and options: answers images one after another.

    One object owns every cache the matcher needs, each bounded: the whole map's indexes (built on
    the first image without a prior), the quad index of each map tile a prior reached (at most
    ``MAX_CACHED_QUADS`` quads in all, the least recently used dropped first), and the last
    ``MAX_CACHED_BLOCKS`` blocks of tiles, each looked up as one index (:class:`~mapdb.match.quad_block.QuadBlock`,
    merged into one tree once a flight has used it often).  A flight's images fall in the same block
    and cost no index building.  Every answer verifies against the whole map's object index (for a big
    map file, only the pages its queries reach), so a pose scores the same with a prior as without.

    Parameters
    ----------
    map : MetaMap or MemoryMap
        The map (:func:`mapdb.mapfile.reader.open_map`); the localizer does not close it.
    method : {"fast", "paper"}
    options : FastOptions or PaperOptions, optional
        The method's tuning (defaults when None or of the other method).
    prior : (x, y, radius), optional
        Map-CRS metres; used for images that carry no prior of their own.
    blocks : bool
        For a map holding blocks of touching buildings (``mapdb build --blocks``): match the images whose
        buildings come with pixel areas (mask blobs) against buildings and blocks, the others against
        buildings alone (:mod:`mapdb.match.mapobjects.blocks_view`).  False: every image against buildings
        alone, as if the map had no blocks.

    Examples
    --------
    >>> from mapdb.objects import Objects
    >>> from mapdb.mapfile.queries import MemoryMap
    >>> loc = Localizer(MemoryMap(Objects.from_names([0.0, 50.0], [0.0, 0.0], ["park"] * 2, crs="EPSG:32631")))
    >>> loc.localize({"width": 640, "height": 480, "objects": []}).reason
    '0 objects: at least 3 are needed'
    """

    def __init__(self, map: Any, method: str = "fast", options: FastOptions | PaperOptions | None = None,
                 prior: tuple[float, float, float] | None = None, blocks: bool = True) -> None:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        self.map = map
        self.method = method
        wanted = FastOptions if method == "fast" else PaperOptions
        self.options = options if isinstance(options, wanted) else wanted()
        self.prior = prior
        self._whole_objects: WholeMapObjects | None = None
        self._whole_quads: QuadIndex | StoredQuads | None = None
        self._small_map_quads: QuadIndex | None = None
        self._tiles = _Recent(MAX_CACHED_QUADS, size=lambda quads: max(quads.n_quads, 1))
        self._block_quads = _Recent(MAX_CACHED_BLOCKS)
        self._previous_block: tuple | None = None
        # Says why the map's stored index is not used (once): a callable taking one line.
        self.warn: Callable[[str], None] = _warn_stderr
        self._stored_failed = False
        # A map with blocks is searched through a view (blocks folded into buildings, or left out), each with
        # its own localizer and indexes, made when an image first needs it.
        self.blocks = blocks
        self._has_blocks = has_blocks(map)
        self._views: dict[bool, Localizer] = {}
        # Set by whole_map_indexes(masks=False): a view made later gets its whole-map indexes when it is made, so
        # that its answers, like the other view's, never depend on the images answered before.
        self._whole_views = False

    def matcher_for(self, codes: np.ndarray, area_px: np.ndarray | None) -> Localizer:
        """The localizer whose indexes an image is matched in: this one for a map without blocks, else the one
        of the view the image needs (:func:`~mapdb.match.mapobjects.blocks_view.wants_blocks`)."""
        if not self._has_blocks:
            return self
        return self._view(self.blocks and wants_blocks(codes, tuple(self.map.labels), area_px))

    def _view(self, fold: bool) -> Localizer:
        """The localizer of a map with blocks seen with them folded into buildings, or left out."""
        view = self._views.get(fold)
        if view is None:
            if fold:
                self._no_stored_index_for_masks()
            view = Localizer(BlocksView(self.map, fold), self.method, self.options, self.prior)
            view.warn = self.warn
            self._views[fold] = view
            if self._whole_views:
                view.whole_map_indexes()
        return view

    def localize(self, image: dict[str, Any] | ImageObjects, prior: tuple[float, float, float] | None = None, *,
                 source: str = "image", pose: PosePrior | None = None, brief: bool = False) -> Answer:
        """Answer one image (see :func:`localize`); ``prior`` overrides the localizer's own.

        ``pose`` (fast method): where the camera is, which way it points and at what scale
        (:mod:`mapdb.match.pose_prior`); its disc is the prior when ``prior`` is None.  Without it, a prior with a
        heading (the image's own, else ``prior`` as a :class:`~mapdb.detections.images.Prior`) on an image with
        ``altitude_m`` and a field of view gives one (:func:`~mapdb.localize.priors.pose_prior`).  The answer's
        ``path`` then says which search decided (``"pose-prior"`` or ``"quads"``).

        A stored index found damaged during the answer is dropped (saying so once) and the image answered
        again with the quad index built in memory: the answer is the in-memory search's.

        ``image`` as :class:`~mapdb.detections.images.ImageObjects` is taken as checked (what
        :func:`~mapdb.detections.images.parse_image` returns; a caller making its own, as the analysis does from
        simulated arrays, vouches for the same ranges).  ``brief``: an accepted answer with only its position,
        score, inliers, candidates and what the search adds (:func:`~mapdb.localize.records.ok_record`), for
        callers that read no more (the analysis); a rejected answer is the same.
        """
        if prior is None and pose is not None:
            prior = pose.disc
        try:
            return _answer(self, image, self.prior if prior is None else prior, source, pose, brief)
        except _StoredIndexError as exc:
            self._drop_stored(str(exc))
            return _answer(self, image, self.prior if prior is None else prior, source, pose, brief)

    def _no_stored_index_for_masks(self) -> None:
        """Say once that a map's stored index does not serve the images matched against its blocks: it holds the
        quads of the map without them, which the view without blocks searches, but not those of the folded view's
        second world (:mod:`mapdb.match.mapobjects.blocks_view`)."""
        path = getattr(self.map, "path", None)
        if self.method == "fast" and path is not None and index_path(path).exists():
            self.warn(f"{index_path(path)}: serves point images only on a map with blocks of buildings; images with "
                      "building areas (mask blobs) are answered with the in-memory search")

    @property
    def fast_options(self) -> FastOptions:
        """The fast method's options (its defaults for a paper-method localizer, whose indexes are never built)."""
        return self.options if isinstance(self.options, FastOptions) else FastOptions()

    @property
    def paper_options(self) -> PaperOptions:
        """The paper method's options (its defaults for a fast-method localizer)."""
        return self.options if isinstance(self.options, PaperOptions) else PaperOptions()

    # ------------------------------------------------------------------------------------ indexes

    def whole_map_indexes(self, *, masks: bool = True) -> tuple[ObjectIndex, QuadIndex | StoredQuads]:
        """The whole map's object and quad indexes, for one answer.

        Quads: the stored lost-in-space index beside the map file when there is one (``mapdb index MAP``;
        opened in milliseconds, read as needed), else a quad index built in memory on first use.  Objects:
        for a big map file, read page by page where the answers need them until the whole index, built in
        the background from the second answer on, is ready (:class:`WholeMapObjects`); the same answers.

        A map with blocks is searched through its views (:meth:`_views_for`), the view without blocks' returned;
        ``masks`` False (images that are points, as the analysis's) leaves the folded view, which only images with
        building areas are matched in, until one comes (the same answers; Andorra's folded quads: 1.2 s).
        """
        if self._has_blocks:
            return [view.whole_map_indexes() for view in self._views_for(masks)][-1]
        if self._whole_quads is None:
            stored = self._stored_index()
            self._whole_quads = StoredQuads(stored) if stored is not None else self._quad_index(self._quad_objects())
        return self._objects(lost_in_space=True), self._whole_quads

    def _views_for(self, masks: bool) -> list[Localizer]:
        """A map with blocks' views: both if blocks are used and ``masks``, else the one without (see above)."""
        self._whole_views = self._whole_views or not masks
        return [self._view(fold) for fold in ((True, False) if self.blocks and masks else (False,))]

    def _objects(self, lost_in_space: bool) -> ObjectIndex:
        """The whole map's object index (read page by page for a big map file), for one answer.

        Answers with a prior verify against it too, not against the objects around the prior alone: a
        k-th-nearest label density cut at the edge of a read box would make the same pose score differently
        with a prior than without (a lone house of its label in the box looked like a dense town).
        """
        if self._whole_objects is None:
            self._whole_objects = WholeMapObjects(self.map)
        return self._whole_objects.index(lost_in_space)

    def whole_map_ready(self, timeout: float | None = None, masks: bool = True) -> bool:
        """Build the whole map's object index now (in the background for a big map file) and wait up to
        ``timeout`` seconds for it: True once lost-in-space answers use it.  A long-running process that
        expects many lost-in-space images calls it at start-up; the answers are the same either way.  ``masks``
        as in :meth:`whole_map_indexes` (the folded view has no stored index: a world of 1M objects, 20 GB)."""
        if self._has_blocks:
            return all([view.whole_map_ready(timeout) for view in self._views_for(masks)])
        self.whole_map_indexes()
        assert self._whole_objects is not None
        self._whole_objects.start()
        return self._whole_objects.wait(timeout)

    def _stored_index(self) -> StoredQuadIndex | None:
        """The map's stored quad index, if it has one built with the matcher's number of neighbours.

        An index that cannot be used (damaged, of another map, not a regular file) is not: the quad index is
        built in memory instead, saying so once (:attr:`warn`).  Where the whole map is decoded anyway (a
        map the object index holds whole), the index's coordinates are checked against it exactly.  The index of
        a map with blocks holds the quads of the map without them (``docs/index_format.md``): it serves the view
        without blocks only, and an index without that mark (blocks and buildings as one world) none.
        """
        # A map with blocks: only its view without blocks is served, by an index of the map without them.
        base = self.map.raw if isinstance(self.map, BlocksView) else self.map
        if not isinstance(base, MetaMap) or self._stored_failed or self._folds_blocks():
            return None
        # Here, not at the top: its reader and writer (multiprocessing, the label tables) cost a one-image query
        # with a prior some 0.03 s of imports it never needs.
        from ..match.index.stored import StoredQuadIndex

        try:
            stored = StoredQuadIndex.for_map(base)
        except MapdbError as exc:
            self._drop_stored(str(exc))
            return None
        if stored is None or stored.neighbours != self.fast_options.map_neighbours:
            if stored is not None:
                stored.close()
            return None
        if stored.blocks_left_out != (base is not self.map):
            stored.close()
            why = ("its header says the map has blocks" if stored.blocks_left_out else "its quads mix the map's "
                   "blocks and buildings in one world (written before mapdb indexed a map with blocks without them)")
            self._drop_stored(f"{stored.path}: {why}")
            return None
        if len(base) < PAGED_FROM_OBJECTS:
            try:
                objects = base.all()  # a damaged map page is the map's error, raised as without an index
            except BaseException:
                stored.close()
                raise
            try:
                stored.check_positions(objects.x, objects.y)
            except MapdbError as exc:
                stored.close()
                self._drop_stored(str(exc))
                return None
        return stored

    def _drop_stored(self, reason: str) -> None:
        """Stop using the stored index (it failed a check), say so once, and search in memory from now on."""
        if isinstance(self._whole_quads, StoredQuads):
            self._whole_quads.stored.close()
            self._whole_quads = None
        if not self._stored_failed:
            rebuild = "" if "rebuild with" in reason else f"; rebuild with mapdb index {self.map.path}"
            self.warn(f"{reason}{rebuild}; answering with the in-memory search")
        self._stored_failed = True

    def fast_indexes(self, prior: tuple[float, float, float] | None, margin: float):
        """Objects to verify against and quad indexes to look hypotheses up in.

        Without a prior: the whole map's.  With one, the prior is applied before any quad is read: the
        quads anchored in the map tiles that ``1.1 radius + margin`` around its centre reaches; the objects
        are the whole map's object index (for a big map file, only the pages its queries reach are read).
        Tiles are cached; a flight's consecutive images fall in the same block of tiles, which is then
        looked up as one index (one lookup instead of one per tile: :class:`~mapdb.match.quad_block.QuadBlock`).
        The whole map's quad index, when already in memory, serves every prior instead of the tiles'; so does,
        on a map of at most ``SMALL_MAP_OBJECTS`` objects, one index of its quads with their positions, built on
        the first prior (the same hits as the tiles': ``tests/test_small_map_prior.py``).
        """
        if prior is None:
            objects, quads = self.whole_map_indexes()
            return objects, [quads]
        x, y, r = prior
        # Hypotheses may put the image centre 1.1 radius away; its objects, and so the anchors of the map
        # quads that can match, reach ``margin`` beyond.
        anchor_reach = PRIOR_SLACK * r + margin
        t = TILE_SIZE_M
        k = max(1, math.ceil(anchor_reach / t))
        if (2 * k + 1) ** 2 > MAX_PRIOR_TILES:
            # A prior this wide covers much of the map: the whole map's indexes serve it (and later images).
            return self.fast_indexes(None, 0.0)
        objects = self._objects(lost_in_space=False)
        centre = complex(x, y)
        if self._whole_quads is not None:
            return objects, [NearQuads(self._whole_quads, centre, anchor_reach)]
        if len(self.map) <= SMALL_MAP_OBJECTS:
            # A small map's quads in one index with their positions, built once: about the cost of the tiles one
            # disc reaches (Monaco's 1,794 objects: 31 ms against 5-10 ms a tile), and no tile built afterwards.
            if self._small_map_quads is None:
                self._small_map_quads = self._quad_index(self._quad_objects(), positions=True)
            return objects, [NearQuads(self._small_map_quads, centre, anchor_reach)]
        cx, cy = math.floor(x / t), math.floor(y / t)
        block = (cx, cy, k)
        previous, self._previous_block = self._previous_block, block
        if block not in self._block_quads and block != previous:
            # Look up in the tiles the disc reaches, one by one.  A block (all its tiles built, and merged once
            # used often) pays for images in a row that fall in it, as a flight's do; scattered images would build
            # a block's tiles beyond their discs.  A tile's squared distance from the centre is its column's plus
            # its row's, each found once.
            columns = [(ix, max(ix * t - x, 0.0, x - (ix + 1) * t) ** 2) for ix in range(cx - k, cx + k + 1)]
            rows = [(iy, max(iy * t - y, 0.0, y - (iy + 1) * t) ** 2) for iy in range(cy - k, cy + k + 1)]
            reach2 = anchor_reach**2
            reached = [NearQuads(self._tile(ix, iy), centre, anchor_reach)
                       for ix, dx2 in columns for iy, dy2 in rows if dx2 + dy2 <= reach2]
            return objects, reached
        # The block's tiles looked up as one index (their k nearest together), with no merged tree built: the
        # same hits as one tree over their quads (QuadIndex.merged), without its 10-15 ms a block on Monaco.
        cells = [(ix, iy) for ix in range(cx - k, cx + k + 1) for iy in range(cy - k, cy + k + 1)]
        quads = self._block_quads.get(block, lambda: QuadBlock([self._tile(ix, iy) for ix, iy in cells]))
        return objects, [NearQuads(quads, centre, anchor_reach)]

    def _folds_blocks(self) -> bool:
        return isinstance(self.map, BlocksView) and self.map.fold

    def _quad_objects(self, box: tuple[float, float, float, float] | None = None) -> Objects:
        """The objects quads are made of, the whole map's or a box's: a view folding blocks hands its map's
        own (blocks under their label), which :func:`block_quads` makes its two worlds of."""
        source = self.map.raw if self._folds_blocks() else self.map
        return source.all() if box is None else source.query_bbox(*box)

    def _quad_index(self, objects: Objects, anchors: np.ndarray | None = None, positions: bool = False) -> QuadIndex:
        """A quad index over :meth:`_quad_objects`' objects."""
        if self._folds_blocks():
            return block_quads(objects, self.fast_options.map_neighbours, anchors=anchors, positions=positions)
        return QuadIndex(objects, self.fast_options.map_neighbours, anchors=anchors, positions=positions)

    def _tile(self, ix: int, iy: int) -> QuadIndex:
        """Quads anchored in one tile; neighbours are read from a margin around it."""
        tile = self._tiles.recent((ix, iy))
        if tile is not None:  # the usual case: no builder made
            return tile

        def build() -> QuadIndex:
            t, pad = TILE_SIZE_M, TILE_PAD_M
            x0, y0 = ix * t, iy * t
            objects = self._quad_objects((x0 - pad, y0 - pad, x0 + t + pad, y0 + t + pad))
            # Half-open tiles: an object on a shared edge anchors its quads in one tile only.
            anchors = (objects.x >= x0) & (objects.x < x0 + t) & (objects.y >= y0) & (objects.y < y0 + t)
            return self._quad_index(objects, anchors=anchors, positions=True)

        return self._tiles.get((ix, iy), build)


def localizer_for(map: Any, method: str = "fast", options: FastOptions | PaperOptions | None = None) -> Localizer:
    """The :class:`Localizer` that :func:`localize` keeps for this map, method and options (in the map's own
    cache of derived values, so that its indexes go when the map is closed)."""
    return map.cached(f"mapdb.localize.localizer/{method}/{options!r}", lambda: Localizer(map, method, options))


def localize(
    image: dict[str, Any] | ImageObjects,
    map: Any,
    method: str = "fast",
    prior: tuple[float, float, float] | None = None,
    *,
    options: FastOptions | PaperOptions | None = None,
    source: str = "image",
) -> Answer:
    """Find where an image was taken.

    Parameters
    ----------
    image : dict or ImageObjects
        An image document (see :mod:`mapdb.detections.images`) or an already parsed one.
    map : MetaMap or MemoryMap
        The map (:func:`mapdb.mapfile.reader.open_map`).  Calls on one map share one :class:`Localizer` (its indexes).
    method : {"fast", "paper"}
        The fast matcher (:mod:`mapdb.match.fast`) or the paper's Algorithm 1 (:mod:`mapdb.match.paper.algorithm`;
        seconds to minutes per image).
    prior : (x, y, radius), optional
        Map-CRS metres; used for images that carry no prior of their own.
    options : FastOptions or PaperOptions, optional
        The method's tuning.
    source : str
        Names the image in rejection reasons.

    Returns
    -------
    Answer
        The answer (module docs).  Bad input gives ``status == "rejected"`` with the reason; nothing
        about the image raises.

    Examples
    --------
    >>> from mapdb.objects import Objects
    >>> from mapdb.mapfile.queries import MemoryMap
    >>> m = MemoryMap(Objects.from_names([0.0, 50.0], [0.0, 0.0], ["building"] * 2, crs="EPSG:32631"))
    >>> localize({"width": 640, "height": 480, "objects": []}, m).reason
    '0 objects: at least 3 are needed'
    """
    return localizer_for(map, method, options).localize(image, prior, source=source)


def _answer(localizer: Localizer, image: dict[str, Any] | ImageObjects, prior: tuple[float, float, float] | None,
            source: str, pose: PosePrior | None = None, brief: bool = False) -> Answer:
    start = time.perf_counter()
    image_id = _image_id(image)
    try:
        im, disc = _checked(image, localizer.map.crs, prior, source)
    except ImageInputError as exc:
        message = str(exc)
        return rejected(image_id, message[len(source) + 2 :] if message.startswith(f"{source}: ") else message,
                         start)
    image_id = im.id if isinstance(im.id, str | int) else None
    skipped: dict[str, Any] = {}
    try:
        im, codes, skipped = known_objects(im, tuple(localizer.map.labels))
        z, levelled, notes = image_points(im)
        diag_px = math.hypot(im.width, im.height)
        focal_px, scale_range, half_diag_m = scale_hints(im, diag_px)
        if pose is None:
            pose = pose_prior(im, prior, disc, focal_px, notes, localizer.method)
        margin = prior_margin(disc[2], half_diag_m) if disc is not None else 0.0
        outside = None if disc is None else outside_bounds(disc, margin, localizer.map.bounds)
        if outside:
            raise RejectionError(outside)
        anchorable = None if im.border is None else ~im.border
        # A levelled image's pixel areas and boxes are not the level camera's: they are left out.
        outward = None if im.bbox is None or levelled else outward_normals(im.bbox, im.width, im.height)
        matcher = localizer.matcher_for(codes, im.area_px)  # a map's blocks, for mask blobs only
        found = _match(matcher, z, codes, diag_px, disc, margin, scale_range, notes, skipped, anchorable,
                       None if levelled else im.area_px, outward, (focal_px, im.altitude_m), pose)
    except RejectionError as rejection:
        return rejected(image_id, rejection.reason, start, rejection.candidates, **{**rejection.extra, **skipped})
    return ok_record(image_id, localizer.map.crs, found, focal_px, levelled, start, None if brief else im,
                     lonlat=not brief, brief=brief)


def _checked(image: dict[str, Any] | ImageObjects, crs: str, prior: tuple[float, float, float] | None,
             source: str) -> tuple[ImageObjects, tuple[float, float, float] | None]:
    """The parsed image and the prior that applies to it (its own, else the caller's)."""
    im = image if isinstance(image, ImageObjects) else parse_image(image, source)
    return im, resolve_prior(im, crs, prior)


def _match(localizer: Localizer, z: np.ndarray, codes: np.ndarray, diag_px: float,
           prior: tuple[float, float, float] | None, margin: float, scale_range: tuple[float, float] | None,
           notes: list[str], skipped: dict[str, Any], anchorable: np.ndarray | None = None,
           area_px: np.ndarray | None = None, outward: np.ndarray | None = None,
           camera: tuple[float | None, float | None] = (None, None), pose: PosePrior | None = None) -> FoundPose:
    """Run the localizer's method on the image plane; the pose, or a :class:`~mapdb.localize.records.RejectionError`.
    ``camera`` is the focal length (pixels) and the altitude above ground, when the image gives them (terrain)."""
    if localizer.method == "fast":
        objects, quads = localizer.fast_indexes(prior, margin)
        found = match_fast(z, codes, objects, quads, diag_px, options=localizer.fast_options, prior=prior,
                           scale_range=scale_range, anchorable=anchorable, area_px=area_px, outward=outward,
                           focal_px=camera[0], altitude_m=camera[1], pose_prior=pose)
        candidates = [
            Candidate(x=rounded(c.b.real, 3), y=rounded(c.b.imag, 3), inliers=c.inliers,
                      score=finite(c.score, 2), sigma_m=finite(c.sigma_m, 3))
            for c in found.candidates
        ]
        extra: dict[str, Any] = {"hypotheses": found.n_hypotheses, **skipped}
        if found.path is not None:
            extra["path"] = found.path
        if notes:
            extra["notes"] = notes
        if found.best is None:
            if found.rejected_by is not None and found.log10_nfa_points is not None:
                extra.update(rejected_by=found.rejected_by, score_without_areas=finite(-found.log10_nfa_points, 2))
            raise RejectionError(found.reason or "no match", candidates, **extra)
        best = found.best
        return FoundPose(best.a, best.b, best.inliers, best.sigma_m, rounded(best.score, 2), candidates, extra)
    from ..match.paper.algorithm import match_paper  # the reference matcher: seconds an image, imported when used

    map_ = localizer.map
    objects = map_.query_radius(prior[0], prior[1], prior[2] + margin) if prior is not None else map_.all()
    answer = match_paper(z, codes, objects, options=localizer.paper_options)
    extra = {"notes": notes, **skipped} if notes else {**skipped}
    if answer.best is None:
        raise RejectionError(answer.reason or "no match", [], **extra)
    extra["error_std"] = rounded(answer.best.error_std, 6)
    return FoundPose(answer.best.a, answer.best.b, answer.best.matched, None, None, [], extra)
