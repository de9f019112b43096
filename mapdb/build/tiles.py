"""Blocks of a large source's buildings formed tile by tile, the footprints waiting on disk, not in memory.

:class:`mapdb.build.blocks.BuildingOutlines` keeps every footprint of a source (about 200 bytes a
building) until the source is read, then forms the blocks at once.  A layer or an OSM extract of more than
:data:`OUTLINES_IN_MEMORY` buildings hands them to :class:`FootprintTiles` instead, which writes each footprint
(WKB, lon/lat) to the file of its *home tile* (the tile of :data:`TILE_DEG` degrees that holds its centroid) and
to the file of every other tile whose *reach* (the tile widened by ``margin_m`` metres on each side) its box
meets.  Blocks are then formed one tile at a time from the footprints within its reach, so a build holds one
tile's footprints at a time.

Which tile stores a block: the components of the tile's footprints (:func:`~mapdb.build.blocks.block_members`)
are its candidate blocks.  A component none of whose footprints (grown by the gap) leaves the reach is a
whole block, stored by the tile where its first footprint (in reading order) has its home: it is the block
the whole layer gives, with the same members in the same order, measured in the same projection (about the
median of all the footprints' centroids, as :meth:`BuildingOutlines.blocks` does), so the same centroid and
area to the last bit.  **A block longer than the margin** may reach beyond a tile's reach: the tile then
stores the part of it made of the buildings whose home it is (if two or more), so such a block is cut along
tile edges into parts, each stored as a block, counted in :attr:`FootprintTiles.cut`.  A block shorter than
the margin is always whole (every tile that holds one of its buildings' homes sees all of it); a longer one
whole in one tile's reach and cut in another's may be stored both whole and in a part.
The margin, 750 m, is half as long again as the longest block of the shared extracts (the box diagonals
of the longest: Andorra 336 m, Liechtenstein 321 m, Monaco 506 m; ``python benchmarks/layer_memory.py
--blocks``).  A tile of 0.1 degrees is 80 km^2 at 50 degrees of latitude and its reach 1.37 times that: the
footprints formed into blocks twice (those of the margins) cost that much more time than blocks formed at
once, and a city's densest tile (2,000 buildings a km^2) holds some 220,000 footprints, about 250 MB while
its blocks are formed, whatever the size of the layer.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import shapely
from pyproj import Transformer

from ..errors import MapdbIOError
from ..objects import Objects
from ..progress import Progress
from ..sources.spool import ObjectSpool
from .blocks import DEFAULT_GAP_M, BuildingOutlines, block_members, block_objects
from .blockstats import median_of

__all__ = ["DEFAULT_MARGIN_M", "OUTLINES_IN_MEMORY", "TILE_DEG", "FootprintTiles", "SpillingOutlines", "balanced_runs",
           "tile_blocks_spool"]

# Footprints a source's outlines keep in memory (about 13 MB of WKB); past them, they go to tile files.  An OSM
# extract's footprints held whole were the peak of its build: 767 MB of 456,355 objects (Andorra copied 64 times).
OUTLINES_IN_MEMORY = 1 << 16

TILE_DEG = 0.1
DEFAULT_MARGIN_M = 750.0
_M_PER_DEG = 111_000.0  # metres a degree of latitude, a little under the least (110,574 m at the equator)
_ROUND = 1e-9  # degrees: float rounding of the boxes' edges, never the difference between in and out


class FootprintTiles:
    """Building footprints (lon/lat) in tile files under a temporary directory, made into blocks tile by tile.

    Parameters
    ----------
    directory : path
        Where the temporary directory is made (removed by :meth:`discard`, and with the build's own).
    margin_m : float
        How far beyond its tile a tile's footprints are read (module notes).

    Examples
    --------
    >>> import tempfile, shapely
    >>> tiles = FootprintTiles(tempfile.mkdtemp())
    >>> tiles.add(shapely.box([7.0, 7.0001, 7.01], 45.0, [7.0001, 7.0002, 7.0101], 45.0001))
    >>> [len(b) for b in tiles.blocks(("building", "building_block"))], len(tiles)
    ([1], 3)
    >>> tiles.discard()
    """

    def __init__(self, directory: str | os.PathLike[str], margin_m: float = DEFAULT_MARGIN_M) -> None:
        try:
            self.directory = Path(tempfile.mkdtemp(prefix="footprints-", dir=directory))
        except OSError as exc:
            raise MapdbIOError(f"{directory}: cannot hold the footprints read ({exc.strerror or exc})") from None
        self.margin_m = float(margin_m)
        self.count = 0
        self.cut = 0  # blocks longer than the margin, stored in parts
        self.homes: set[tuple[int, int]] = set()
        self._zone: str | None = None

    def __len__(self) -> int:
        return self.count

    def add(self, geoms: np.ndarray) -> None:
        """Footprints in lon/lat, in reading order (those without a finite centroid are left out, as
        :meth:`BuildingOutlines.blocks` leaves them)."""
        geoms = np.asarray(geoms, dtype=object)
        centre = shapely.get_coordinates(shapely.centroid(geoms))
        finite = np.isfinite(centre).all(axis=1) if len(centre) == len(geoms) else np.zeros(len(geoms), bool)
        geoms, centre = geoms[finite], centre[finite]
        if not geoms.size:
            return
        seq = np.arange(self.count, self.count + geoms.size, dtype=np.int64)
        self.count += geoms.size
        home = np.floor(centre / TILE_DEG).astype(np.int64)
        bounds = shapely.bounds(geoms)
        wkb = np.asarray(shapely.to_wkb(geoms), dtype=object)
        self._append_centres(centre)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                tile = home + np.array([di, dj])
                meets = _meets_reach(bounds, tile, self.margin_m)
                if meets.any():
                    self._write(tile[meets], seq[meets], (di == 0) & (dj == 0), wkb[meets])
        self.homes.update(map(tuple, np.unique(home, axis=0).tolist()))
        self._zone = None

    def blocks(self, labels: Sequence[str], gap: float = DEFAULT_GAP_M,
               bbox: tuple[float, float, float, float] | None = None,
               tiles: Sequence[tuple[int, int]] | None = None) -> Iterator[Objects]:
        """Each tile's blocks, as objects labelled :data:`BLOCK_LABEL` in lon/lat (``bbox`` keeps those whose
        centroid lies inside), tile by tile: of every home tile in order, or of ``tiles`` (a group of
        :meth:`groups`) only."""
        labels = tuple(labels)
        if self.count < 2:
            return
        zone = self.zone()
        to_zone = Transformer.from_crs("EPSG:4326", zone, always_xy=True)
        back = Transformer.from_crs(zone, "EPSG:4326", always_xy=True)
        for tile in sorted(self.homes) if tiles is None else tiles:
            xy, area = self._tile_blocks((int(tile[0]), int(tile[1])), to_zone, gap)
            if not len(area):
                continue
            yield block_objects(xy, area, back, labels, bbox)

    def said(self, blocks: int, gap: float, tasks: str = "") -> str:
        """What a build says of the ``blocks`` formed from these footprints (``tasks``: on how many)."""
        cut = f"; {self.cut:,} longer than the {self.margin_m:g} m margin, stored in parts" if self.cut else ""
        return (f"  {blocks:,} blocks of touching buildings (gap {gap:g} m) from {self.count:,} footprints, "
                f"in {len(self.homes):,} tiles{tasks}{cut}")

    def zone(self) -> str:
        """The projection blocks are measured in: about the median of all the footprints' centroids, as
        :meth:`BuildingOutlines.blocks` takes it (read from disk once, then kept, so that the groups of tiles
        made into blocks elsewhere need not read every centroid again)."""
        if self._zone is None:
            lon = median_of(lambda: (c[:, 0] for c in self._centres()))
            lat = median_of(lambda: (c[:, 1] for c in self._centres()))
            self._zone = f"+proj=laea +lat_0={float(lat):.6f} +lon_0={float(lon):.6f} +datum=WGS84 +units=m +no_defs"
        return self._zone

    def groups(self, n: int) -> list[list[tuple[int, int]]]:
        """The home tiles in order, cut into at most ``n`` runs of about equal weight (:func:`balanced_runs` of
        the tile files' sizes): their blocks, formed apart (one task each) and joined in this order, are those
        of :meth:`blocks`."""
        tiles = sorted(self.homes)
        sizes = [self._path(tile).stat().st_size for tile in tiles]
        return [tiles[run.start:run.stop] for run in balanced_runs(sizes, n)]

    def discard(self) -> None:
        """Remove the tile files."""
        shutil.rmtree(self.directory, ignore_errors=True)
        self.homes.clear()

    def _tile_blocks(self, tile: tuple[int, int], to_zone: Transformer, gap: float
                     ) -> tuple[np.ndarray, np.ndarray]:
        """The blocks a tile stores: centroids (metres, in the zone) and areas, as :func:`blocks_of` gives them."""
        seq, home, wkb = self._read(tile)
        order = np.argsort(seq, kind="stable")
        seq, home, geoms = seq[order], home[order], shapely.from_wkb(wkb[order])
        metric = shapely.transform(geoms, lambda xy: np.column_stack(to_zone.transform(xy[:, 0], xy[:, 1])))
        invalid = ~shapely.is_valid(metric)  # a ring crossing itself: as BuildingOutlines.blocks repairs it
        if invalid.any():
            metric[invalid] = shapely.make_valid(metric[invalid], method="structure", keep_collapsed=False)
        block = block_members(metric, gap)
        inside = np.flatnonzero(block >= 0)
        if not inside.size:
            return np.zeros((0, 2)), np.zeros(0)
        first = np.full(int(block.max()) + 1, len(block), np.int64)
        np.minimum.at(first, block[inside], inside)  # each block's first footprint (lowest position: seq order)
        near = _near_edge(shapely.bounds(geoms), tile, self.margin_m, gap)
        cut = np.zeros(first.size, bool)
        cut[block[inside][near[inside]]] = True
        # A whole block is stored by its first footprint's tile; of a cut one, each tile stores its own buildings.
        taken = np.zeros(block.size, bool)
        taken[inside] = np.where(cut[block[inside]], home[inside], home[first[block[inside]]])
        size = np.bincount(block[taken], minlength=first.size)
        taken[inside] &= size[block[inside]] >= 2
        self.cut += int((cut & (size >= 2)).sum())
        members = np.flatnonzero(taken)
        if not members.size:
            return np.zeros((0, 2)), np.zeros(0)
        # The stored blocks' members in their order, parts grouped by block: blocks_of's union, block by block.
        parts, owner = shapely.get_parts(metric[members], return_index=True)
        part_block = np.searchsorted(np.unique(block[members]), block[members])[owner]
        order = np.argsort(part_block, kind="stable")
        union = shapely.buffer(shapely.multipolygons(parts[order], indices=part_block[order]), 0)
        return shapely.get_coordinates(shapely.centroid(union)), shapely.area(union)

    def _path(self, tile: Sequence[int]) -> Path:
        return self.directory / f"{int(tile[0])}_{int(tile[1])}.tile"

    def _write(self, tiles: np.ndarray, seq: np.ndarray, home: bool, wkb: np.ndarray) -> None:
        """Append footprints to their tiles' files: a frame a tile (count, seq, home flags, WKB lengths, WKB)."""
        order = np.lexsort((tiles[:, 1], tiles[:, 0]))
        tiles, seq, wkb = tiles[order], seq[order], wkb[order]
        cuts = np.flatnonzero((np.diff(tiles, axis=0) != 0).any(axis=1)) + 1
        try:
            for part in np.split(np.arange(len(seq)), cuts):
                blob = wkb[part]
                lengths = np.fromiter((len(b) for b in blob), np.int32, len(blob))
                with open(self._path(tiles[part[0]]), "ab") as f:
                    f.write(np.int64(len(part)).tobytes())
                    f.write(seq[part].tobytes())
                    f.write(np.full(len(part), home, np.uint8).tobytes())
                    f.write(lengths.tobytes())
                    f.write(b"".join(blob))
        except OSError as exc:
            raise MapdbIOError(f"{self.directory.parent}: cannot hold the footprints read ({exc.strerror or exc}); "
                               "free some space or choose another directory") from None

    def _read(self, tile: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        data = self._path(tile).read_bytes()
        seqs: list[np.ndarray] = []
        homes: list[np.ndarray] = []
        blobs: list[bytes] = []
        at = 0
        while at < len(data):
            n = int(np.frombuffer(data, np.int64, 1, at)[0])
            at += 8
            seqs.append(np.frombuffer(data, np.int64, n, at))
            at += 8 * n
            homes.append(np.frombuffer(data, np.uint8, n, at).astype(bool))
            at += n
            lengths = np.frombuffer(data, np.int32, n, at)
            at += 4 * n
            ends = at + np.cumsum(lengths)
            blobs.extend(data[s:e] for s, e in zip(ends - lengths, ends, strict=True))
            at = int(ends[-1]) if n else at
        return np.concatenate(seqs), np.concatenate(homes), np.asarray(blobs, dtype=object)

    def _append_centres(self, centre: np.ndarray) -> None:
        with open(self.directory / "centres", "ab") as f:
            f.write(np.ascontiguousarray(centre, np.float64).tobytes())

    def _centres(self) -> Iterator[np.ndarray]:
        with open(self.directory / "centres", "rb") as f:
            while True:
                block = np.fromfile(f, np.float64, count=2 << 18)
                if not block.size:
                    return
                yield block.reshape(-1, 2)


def balanced_runs(weights: Sequence[float], n: int) -> list[range]:
    """``weights`` cut into at most ``n`` consecutive runs of about equal total weight (none empty).

    Each cut is put where the running total comes nearest to a multiple of the total over ``n``: a run weighs
    the total over ``n`` give or take the heaviest item, whatever the order of the weights.

    Examples
    --------
    >>> balanced_runs([5, 1, 1, 1, 1, 1, 5, 1], 2)
    [range(0, 4), range(4, 8)]
    >>> balanced_runs([1, 1], 4)
    [range(0, 1), range(1, 2)]
    """
    total = np.cumsum(np.asarray(weights, np.float64))
    if not total.size or n <= 1:
        return [range(0, total.size)] if total.size else []
    ends = [0]
    for k in range(1, n):
        target = total[-1] * k / n
        at = int(np.searchsorted(total, target))  # the first item whose running total reaches the target
        # Cut after it or before it, whichever running total is nearer the target.
        end = at + 1 if at < total.size and (at == 0 or total[at] - target <= target - total[at - 1]) else at
        ends.append(min(max(end, ends[-1]), total.size))
    ends.append(total.size)
    return [range(a, b) for a, b in zip(ends[:-1], ends[1:], strict=True) if b > a]


def _reach(tile: np.ndarray, margin_m: float) -> tuple[np.ndarray, ...]:
    """The reach of tiles ``(n, 2)``: west, south, east, north (degrees), the margin in degrees of longitude
    taken at the tile's latitude farthest from the equator."""
    west, south = tile[:, 0] * TILE_DEG, tile[:, 1] * TILE_DEG
    far = np.minimum(np.maximum(np.abs(south), np.abs(south + TILE_DEG)), 89.0)
    # At most a tile: footprints are sorted into the eight tiles around their home (near the poles, where a
    # tile is narrower than the margin, blocks are cut sooner).
    my = min(margin_m / _M_PER_DEG, TILE_DEG)
    mx = np.minimum(margin_m / (_M_PER_DEG * np.cos(np.radians(far))), TILE_DEG)
    return west - mx, south - my, west + TILE_DEG + mx, south + TILE_DEG + my


def _meets_reach(bounds: np.ndarray, tile: np.ndarray, margin_m: float) -> np.ndarray:
    x0, y0, x1, y1 = _reach(tile, margin_m)
    return ((bounds[:, 0] <= x1 + _ROUND) & (bounds[:, 2] >= x0 - _ROUND) & (bounds[:, 1] <= y1 + _ROUND)
            & (bounds[:, 3] >= y0 - _ROUND))


def _near_edge(bounds: np.ndarray, tile: tuple[int, int], margin_m: float, gap: float) -> np.ndarray:
    """Footprints that may lie within ``gap`` of one outside the tile's reach (their box grown by the gap
    leaves it): a block holding one may go on beyond the reach."""
    x0, y0, x1, y1 = (float(v[0]) for v in _reach(np.array([tile]), margin_m))
    lat = np.minimum(np.maximum(np.abs(bounds[:, 1]), np.abs(bounds[:, 3])), 89.0)
    gy = 2 * gap / _M_PER_DEG
    gx = 2 * gap / (_M_PER_DEG * np.cos(np.radians(lat)))
    return ((bounds[:, 0] - gx < x0 + _ROUND) | (bounds[:, 2] + gx > x1 - _ROUND) | (bounds[:, 1] - gy < y0 + _ROUND)
            | (bounds[:, 3] + gy > y1 - _ROUND))


class SpillingOutlines(BuildingOutlines):
    """:class:`BuildingOutlines` that keep up to ``memory`` footprints in memory and then move them all to
    :class:`FootprintTiles` in ``directory``; blocks are then formed tile by tile and spooled to a file.

    Below ``memory`` footprints the blocks are those of :class:`BuildingOutlines`, by the same code.
    """

    def __init__(self, code: int, directory: str | os.PathLike[str], memory: int | None = None,
                 margin_m: float = DEFAULT_MARGIN_M) -> None:
        super().__init__(code)
        self.directory = directory
        self.memory = OUTLINES_IN_MEMORY if memory is None else memory
        self.margin_m = margin_m
        self.tiles: FootprintTiles | None = None

    def __len__(self) -> int:
        return len(self.wkb) + (len(self.tiles) if self.tiles is not None else 0)

    def keep(self, geoms: np.ndarray) -> None:
        if self.tiles is None and len(self.wkb) + len(geoms) <= self.memory:
            super().keep(geoms)
            return
        if self.tiles is None:
            self.tiles = FootprintTiles(self.directory, self.margin_m)
            if self.wkb:
                self.tiles.add(shapely.from_wkb(np.asarray(self.wkb, dtype=object)))
                self.wkb.clear()
        self.tiles.add(geoms)

    def spool(self, labels: Sequence[str], gap: float, bbox: tuple[float, float, float, float] | None,
              say: Progress | None) -> ObjectSpool:
        if self.tiles is None:
            return super().spool(labels, gap, bbox, say)
        try:
            spool, _ = tile_blocks_spool(self.tiles, labels, gap, bbox)
            if say is not None:
                say(self.tiles.said(len(spool), gap))
        finally:
            self.tiles.discard()
        return spool


def tile_blocks_spool(tiles: FootprintTiles, labels: Sequence[str], gap: float,
                      bbox: tuple[float, float, float, float] | None,
                      group: Sequence[tuple[int, int]] | None = None) -> tuple[ObjectSpool, int]:
    """The blocks of every home tile, or of a ``group`` of them (:meth:`FootprintTiles.groups`), spooled to a
    file beside the tiles' directory; and how many of them were longer than the margin (stored in parts).

    The unit of work of a parallel build's blocks (:mod:`mapdb.build.reading`): the groups' spools, joined
    in the groups' order, hold the objects of the spool of all the tiles, in the same order.
    """
    spool = ObjectSpool(labels, "EPSG:4326", tiles.directory.parent, "blocks-")
    cut = tiles.cut
    for blocks in tiles.blocks(labels, gap, bbox, group):
        spool.add(blocks)
    return spool, tiles.cut - cut
