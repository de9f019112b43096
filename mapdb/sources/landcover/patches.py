"""Patches: connected components of one label, accumulated tile by tile and joined across tile edges."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

# Nothing public: read_landcover (mapdb.sources.landcover.reader) is the interface.
__all__: list[str] = []


class _Patches:
    """Connected components accumulated tile by tile, emitted once they can no longer grow.

    Tiles come in rows (``begin_row``, ``add_tile`` left to right, ``end_row``); per component we
    keep the sums ``area``, ``area * col`` and ``area * row`` (pixel-centre coordinates in the full
    raster's pixel grid), from which the centroid follows.  Within a row of tiles, components are
    *nodes*: first the components left open by the row above, then each tile's own.  Pairs of nodes
    touching across a tile edge are joined at ``end_row`` by one connected-components pass.
    """

    def __init__(self, min_area: float, connectivity: int) -> None:
        self.min_area = min_area
        self.structure = ndimage.generate_binary_structure(2, 2 if connectivity == 8 else 1)
        self.diagonal = connectivity == 8
        # Open components (touching the last pixel row of the row of tiles above): sums and class,
        # and for each tile column of that row, which open component each pixel of its last row holds.
        self.open_sums: np.ndarray = np.zeros((3, 0))
        self.open_cls = np.zeros(0, np.uint8)
        self.seam: dict[int, np.ndarray] = {}
        self.out: list[tuple[np.ndarray, ...]] = []
        self.n_emitted = 0
        self._buffer = np.empty(0, np.int32)

    @property
    def has_open(self) -> bool:
        return self.open_cls.size > 0

    def begin_row(self) -> None:
        self._sums = [self.open_sums]
        self._cls = [self.open_cls]
        self._n = self.open_cls.size
        self._pairs: list[tuple[np.ndarray, np.ndarray]] = []
        self._bottoms: dict[int, np.ndarray] = {}
        self._left: tuple[int, np.ndarray] | None = None

    def add_tile(self, tc: int, col_off: int, class_masks: Iterable[tuple[int, int, np.ndarray]], row_off: int,
                 row_area: np.ndarray) -> None:
        """Label one tile (tile column ``tc``, first pixel at ``row_off, col_off``).

        ``class_masks`` gives ``(class, first row, mask of rows first..last)`` for each class present.
        """
        h = row_area.size
        w = None
        # Placeholders, replaced by full-width arrays at the first class (or never read: see "w is None").
        first = last = left = right = np.empty(0, np.int64)
        for c, mask_row0, mask in class_masks:
            if w is None:
                w = mask.shape[1]
                first, last = np.full(w, -1, np.int64), np.full(w, -1, np.int64)
                left, right = np.full(h, -1, np.int64), np.full(h, -1, np.int64)
            rows = np.flatnonzero(mask.any(axis=1))
            if rows.size == 0:
                continue
            # Label only the bounding box of this class in the tile; r0, r1 are tile rows.
            crop_rows = mask[rows[0]:rows[-1] + 1]
            r0, r1 = mask_row0 + int(rows[0]), mask_row0 + int(rows[-1]) + 1
            cols = np.flatnonzero(crop_rows.any(axis=0))
            c0, c1 = int(cols[0]), int(cols[-1]) + 1
            crop = crop_rows[:, c0:c1]
            del mask, crop_rows
            comp = self._label_buffer(crop.shape)
            n = ndimage.label(crop, structure=self.structure, output=comp)
            self._sums.append(_component_sums(crop, comp, n, row_area[r0:r1], row_off + r0, col_off + c0))
            self._cls.append(np.full(n, c, np.uint8))
            # Node numbers of the components on the tile's four edges, for the joins.
            base = self._n - 1
            for edge, at, span, pixels in ((first, r0 == 0, slice(c0, c1), comp[0]),
                                           (last, r1 == h, slice(c0, c1), comp[-1]),
                                           (left, c0 == 0, slice(r0, r1), comp[:, 0]),
                                           (right, c1 == w, slice(r0, r1), comp[:, -1])):
                if at:
                    edge[span] = np.where(pixels > 0, pixels.astype(np.int64) + base, edge[span])
            self._n += n
            del crop
        if w is None:  # no class present (the generator yielded nothing): nothing to join
            self._left = None
            return
        self._join(self.seam.get(tc), first)
        if self.diagonal:
            above_left, above_right = self.seam.get(tc - 1), self.seam.get(tc + 1)
            if above_left is not None:
                self._pairs.append((above_left[-1:], first[:1]))
            if above_right is not None:
                self._pairs.append((above_right[:1], first[-1:]))
        if self._left is not None and self._left[0] == tc - 1:
            self._join(self._left[1], left)
        self._left = (tc, right)
        if (last >= 0).any():
            self._bottoms[tc] = last

    def _join(self, a: np.ndarray | None, b: np.ndarray) -> None:
        """Node pairs facing each other across an edge (``a`` on one side, ``b`` on the other)."""
        if a is None:
            return
        self._pairs.append((a, b))
        if self.diagonal:
            self._pairs += [(a[:-1], b[1:]), (a[1:], b[:-1])]

    def end_row(self, last: bool = False) -> None:
        """Join the row's nodes, emit the components that can no longer grow, keep the others open."""
        node_sums = np.concatenate(self._sums, axis=1)
        node_cls = np.concatenate(self._cls)
        n_nodes = node_cls.size
        group, n_groups = np.arange(n_nodes), n_nodes
        if self._pairs:
            a = np.concatenate([p[0] for p in self._pairs])
            b = np.concatenate([p[1] for p in self._pairs])
            hit = (a >= 0) & (b >= 0)
            a, b = a[hit], b[hit]
            same = node_cls[a] == node_cls[b]
            a, b = a[same], b[same]
            if a.size:
                graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n_nodes, n_nodes))
                n_groups, group = connected_components(graph, directed=False)
        group_sums = np.stack([np.bincount(group, weights=s, minlength=n_groups) for s in node_sums])
        group_cls = np.zeros(n_groups, np.uint8)
        group_cls[group] = node_cls
        still_open = np.zeros(n_groups, bool)
        if not last:
            for bottom in self._bottoms.values():
                still_open[group[bottom[bottom >= 0]]] = True
        closed = ~still_open & (group_sums[0] >= self.min_area) & (group_sums[0] > 0)
        if closed.any():
            s = group_sums[:, closed]
            self.out.append((s[1] / s[0], s[2] / s[0], group_cls[closed].astype(np.int32), s[0]))
            self.n_emitted += int(closed.sum())
        open_ids = np.flatnonzero(still_open)
        renumber = np.full(n_groups, -1, np.int64)
        renumber[open_ids] = np.arange(open_ids.size)
        self.open_sums = group_sums[:, open_ids]
        self.open_cls = group_cls[open_ids]
        self.seam = {tc: np.where(bottom >= 0, renumber[group[np.maximum(bottom, 0)]], -1)
                     for tc, bottom in self._bottoms.items()}
        self.seam = {tc: ids for tc, ids in self.seam.items() if (ids >= 0).any()}

    def finish(self) -> None:
        """Emit every component still open (after the window's last row of tiles)."""
        self.begin_row()
        self.end_row(last=True)

    def _label_buffer(self, shape: tuple[int, int]) -> np.ndarray:
        # Reused between labellings: a fresh 100+ MB array per call costs as much in page faults as
        # the labelling itself.
        size = shape[0] * shape[1]
        if self._buffer.size < size:
            self._buffer = np.empty(size, np.int32)
        return self._buffer[:size].reshape(shape)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centroid column and row (pixel units, full raster), class number and area of every patch kept."""
        if not self.out:
            z = np.zeros(0)
            return z, z, np.zeros(0, np.int32), z
        return tuple(np.concatenate(part) for part in zip(*self.out, strict=True))  # type: ignore[return-value]


def _component_sums(mask: np.ndarray, comp: np.ndarray, n: int, row_area: np.ndarray, row_off: int,
                    col_off: int) -> np.ndarray:
    """Sums (area, area*col, area*row) per component 1..n of ``comp``, from the runs of ``mask``.

    Working on runs (a few per row) instead of pixels keeps this cheap for large patches.
    Coordinates are pixel centres in the full raster grid.
    """
    h, w = mask.shape
    # Nonzero where a run starts or one past where it ends; the extra column ends every run in its
    # row, so in raster order the nonzero positions alternate start, end, start, end...
    m = mask.view(np.int8)
    edges = np.empty((h, w + 1), np.int8)
    edges[:, 0] = m[:, 0]
    np.subtract(m[:, 1:], m[:, :-1], out=edges[:, 1:w])
    edges[:, w] = m[:, w - 1]
    bounds = np.flatnonzero(edges)
    del edges
    starts, ends = bounds[0::2], bounds[1::2]
    row = starts // (w + 1)
    start_col = starts - row * (w + 1)
    length = (ends - starts).astype(np.float64)
    ids = comp[row, start_col] - 1
    run_area = length * row_area[row]
    mean_col = start_col + length / 2 + col_off  # centre of the run's pixel centres
    out = np.empty((3, n))
    out[0] = np.bincount(ids, weights=run_area, minlength=n)
    out[1] = np.bincount(ids, weights=run_area * mean_col, minlength=n)
    out[2] = np.bincount(ids, weights=run_area * (row + row_off + 0.5), minlength=n)
    return out
