"""Land-cover rasters (GeoTIFF of class codes) -> one object per patch.

A *patch* is a connected region of pixels whose class codes map to the same
label (so WorldCover's herbaceous wetland and mangroves, both ``wetland``,
form one patch where they touch).  Connectivity is 8-neighbour by default
(the FRAGSTATS / landscape-ecology convention): pixels touching only at a
corner belong to one patch, so a one-pixel-wide diagonal hedge or stream is
one object, not a string of single pixels.  Pass ``connectivity=4`` for the
stricter rule.

Each patch of at least ``min_area_m2`` becomes one object at its area-weighted
centroid, in the raster's own CRS (the caller reprojects).

The raster is read in full-width row strips aligned to the file's blocks, so
memory stays bounded whatever its size (a 36000 x 36000 WorldCover tile needs a
few hundred MB, not the 1.3 GB of its array).  Within a strip every label
present is labelled with :func:`scipy.ndimage.label`; per-component sums (area,
area-weighted column and row) are accumulated from pixel runs.  Components
that touch the strip's last row stay *open*: the next strip's first row is
joined to them across the seam with a connected-components pass over the
(open + new) components, and a component is emitted as soon as it can no
longer grow.  Only the open components and the emitted objects are kept
between strips.

Pixel area: for a projected CRS, the area of the pixel's parallelogram in
CRS units (converted to metres), the same everywhere; the projection's own
scale distortion is not corrected (fine for UTM or an equal-area CRS like
EPSG:3035, but Web Mercator areas are inflated away from the equator).  For a
geographic CRS, the exact area of each row's cell on the CRS's ellipsoid, so
centroids are area-weighted means of longitude and latitude.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.errors
from pyproj import CRS, Transformer
from rasterio.windows import Window
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import MapdbIOError, SourceError
from ..labels import LabelTable
from ..objects import Objects

__all__ = ["RASTER_SUFFIXES", "is_raster_path", "read_landcover", "raster_class_table_name"]

RASTER_SUFFIXES = (".tif", ".tiff", ".gtiff")

# Pixels per strip: big enough that per-strip overheads vanish, small enough that the strip, its
# per-label label image (int32) and temporaries stay in the low hundreds of MB.
_STRIP_PIXELS = 32_000_000
# GDAL's block cache defaults to 5% of RAM and would hold every decompressed block we read; each
# block is read once here, so a small cache is enough and keeps the peak memory bounded.
_GDAL_CACHE_MB = 64
# Up to this many class codes, label masks come from one comparison per code; beyond, from a lookup
# table (indexed by the code for up to 16-bit pixels, searched for wider ones).
_COMPARE_MAX_CODES = 16
_LUT_MAX_BITS = 16

ProgressCallback = Callable[[str], None]


def is_raster_path(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` has a raster suffix (``.tif``, ``.tiff``, ``.gtiff``; any case).

    Examples
    --------
    >>> is_raster_path("ESA_WorldCover_10m_2021_v200_N00E006_Map.TIF"), is_raster_path("a.geojson")
    (True, False)
    """
    return Path(path).suffix.lower() in RASTER_SUFFIXES


def raster_class_table_name(path: str | os.PathLike[str]) -> str:
    """Guess the class table (``worldcover`` or ``corine``) from a raster's file name.

    Raises :class:`SourceError` when the name gives no hint.

    Examples
    --------
    >>> raster_class_table_name("ESA_WorldCover_10m_2021_v200_N00E006_Map.tif")
    'worldcover'
    >>> raster_class_table_name("corine2006_lausanne_ls100_06.tif")
    'corine'
    """
    name = Path(path).name.lower()
    if "worldcover" in name:
        return "worldcover"
    if "clc" in name or "corine" in name:
        return "corine"
    raise SourceError(
        f"{path}: cannot tell the land-cover class table from the file name; "
        "name it with --raster-classes NAME (e.g. worldcover, corine, or a table from your --labels file)"
    )


def read_landcover(
    path: str | os.PathLike[str],
    table: LabelTable,
    classes: str | None = None,
    min_area_m2: float = 10_000.0,
    bbox: tuple[float, float, float, float] | None = None,
    progress: ProgressCallback | None = None,
    *,
    connectivity: int = 8,
    _strip_rows: int | None = None,
) -> Objects:
    """One object per land-cover patch of at least ``min_area_m2``.

    Parameters
    ----------
    path : path-like
        Single-band GeoTIFF of integer class codes, with a CRS.
    table : LabelTable
        Label table; ``table.rasters[classes]`` maps pixel codes to label names.
        Codes not in it (and the nodata value) are not objects.
    classes : str, optional
        Name of the class table (``"worldcover"``, ``"corine"``, or one from a
        user's label file).  Default: guessed from the file name, see
        :func:`raster_class_table_name`.
    min_area_m2 : float
        Smallest patch kept, in square metres.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Read only the part of the raster covering this box, and keep only
        patches whose centroid lies inside it.  Patches crossing the window
        edge are cut there (their area and centroid are those of the part read).
    progress : callable, optional
        Called with a one-line message now and then.
    connectivity : {8, 4}
        Neighbourhood that joins pixels into patches.

    Returns
    -------
    Objects
        Centroids in the raster's CRS (``crs`` set to its string), label codes
        into ``table.labels``, areas in square metres.

    Raises
    ------
    MapdbIOError
        The file is missing or unreadable.
    SourceError
        Not a raster, truncated, no CRS, more than one band, non-integer
        pixels, or no class table could be chosen.

    Examples
    --------
    >>> from mapdb.labels import default_label_table
    >>> objs = read_landcover("corine2006_lausanne_ls100_06.tif", default_label_table())  # doctest: +SKIP
    >>> objs.counts()["water"]  # doctest: +SKIP
    12
    """
    path = Path(path)
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, not {connectivity!r}")
    if not path.exists():
        raise MapdbIOError(f"{path}: no such file")
    if path.is_dir():
        raise MapdbIOError(f"{path}: is a directory, not a raster")
    name = classes if classes is not None else raster_class_table_name(path)
    if name not in table.rasters:
        raise SourceError(f"{path}: no raster class table named {name!r} (have: {', '.join(sorted(table.rasters))})")
    code_labels = table.raster_classes(name)
    labels = tuple(table.labels)

    with rasterio.Env(GDAL_CACHEMAX=_GDAL_CACHE_MB), _open_raster(path) as src:
        _check_raster(path, src)
        crs = CRS.from_user_input(src.crs.to_wkt())
        crs_string = src.crs.to_string()
        t = src.transform
        window = _bbox_window(src, bbox) if bbox is not None else Window(0, 0, src.width, src.height)
        if window is None:
            return Objects.empty(labels, crs_string)
        patches = _Patches(int(window.width), int(window.col_off), min_area_m2, connectivity)
        _scan(path, src, window, _ClassMasks(src.dtypes[0], code_labels, labels, src.nodata),
              _pixel_area_fn(path, crs, t), patches, _strip_rows or _choose_strip_rows(src, int(window.width)),
              progress)
        col, row, label_code, area = patches.result()

    x = t.a * col + t.b * row + t.c
    y = t.d * col + t.e * row + t.f
    objects = Objects(x, y, label_code - 1, area, labels, crs_string)
    if bbox is not None and len(objects):
        lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
        inside = (lon >= bbox[0]) & (lon <= bbox[2]) & (lat >= bbox[1]) & (lat <= bbox[3])
        objects = objects.take(np.flatnonzero(inside))
    return objects


def _open_raster(path: Path) -> Any:
    try:
        with warnings.catch_warnings():
            # A raster without georeferencing is reported by _check_raster as an error, not as a warning.
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            return rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise SourceError(f"{path}: not a readable raster ({_one_line(exc)})") from None


def _scan(path: Path, src: Any, window: Window, class_masks: _ClassMasks,
          pixel_area: Callable[[int, int], np.ndarray], patches: _Patches, strip_rows: int,
          progress: ProgressCallback | None) -> None:
    """Feed ``window`` of ``src`` to ``patches`` in full-width strips of ``strip_rows`` rows."""
    row0, row_end = int(window.row_off), int(window.row_off + window.height)
    use_mask = _has_mask_band(src)
    next_report = 0.1
    r = row0
    while r < row_end:
        # Strips end on multiples of strip_rows so reads stay aligned with the file's blocks.
        r1 = min(row_end, (r // strip_rows + 1) * strip_rows)
        strip = Window(window.col_off, r, window.width, r1 - r)
        try:
            data = src.read(1, window=strip)
            valid = src.read_masks(1, window=strip) if use_mask else None
        except rasterio.errors.RasterioError as exc:
            raise SourceError(f"{path}: not a readable raster ({_one_line(exc)})") from None
        patches.add_strip(class_masks(data, valid), r, pixel_area(r, r1), last=(r1 == row_end))
        del data, valid
        r = r1
        done = (r - row0) / (row_end - row0)
        if progress is not None and (done >= next_report or r == row_end):
            progress(f"{path.name}: {r - row0}/{row_end - row0} rows, {patches.n_emitted} patches")
            next_report = done + 0.1


def _one_line(exc: BaseException) -> str:
    """The GDAL message behind a rasterio error, on one line."""
    # rasterio's read errors say "See previous exception"; the GDAL error chained below says what failed.
    while exc.__cause__ is not None and "previous exception" in str(exc):
        exc = exc.__cause__
    message = str(exc.args[2]) if len(exc.args) == 3 and isinstance(exc.args[2], str) else str(exc)
    return " ".join(message.split()) or exc.__class__.__name__


def _check_raster(path: Path, src: Any) -> None:
    if src.crs is None:
        raise SourceError(f"{path}: raster has no CRS")
    if src.count != 1:
        raise SourceError(f"{path}: raster has {src.count} bands; a land-cover raster has one band of class codes")
    if not np.issubdtype(np.dtype(src.dtypes[0]), np.integer):
        raise SourceError(f"{path}: raster pixels are {src.dtypes[0]}; land-cover class codes must be integers")


def _has_mask_band(src: Any) -> bool:
    """Whether the raster carries a mask band of its own (e.g. an internal .msk), not just nodata or none."""
    from rasterio.enums import MaskFlags

    flags = src.mask_flag_enums[0]
    return MaskFlags.per_dataset in flags and MaskFlags.nodata not in flags


def _choose_strip_rows(src: Any, width: int) -> int:
    block_rows = max(1, src.block_shapes[0][0])
    target = max(1, _STRIP_PIXELS // max(1, width))
    if block_rows * width > 4 * _STRIP_PIXELS:
        # Huge blocks (e.g. a striped TIFF stored as one strip): alignment is not worth the memory.
        return target
    return max(1, target // block_rows) * block_rows


def _bbox_window(src: Any, bbox: tuple[float, float, float, float]) -> Window | None:
    """The pixel window (rounded outwards, clipped to the raster) covering a lon/lat box, or None."""
    from rasterio.warp import transform_bounds

    try:
        minx, miny, maxx, maxy = transform_bounds("EPSG:4326", src.crs, *bbox, densify_pts=21)
    except (rasterio.errors.RasterioError, ValueError):
        return None  # the box is outside where the raster's projection is defined
    if not all(map(math.isfinite, (minx, miny, maxx, maxy))):
        return None
    inv = ~src.transform
    cols, rows = zip(*(inv @ (x, y) for x, y in ((minx, miny), (minx, maxy), (maxx, miny), (maxx, maxy))),
                     strict=True)
    c0 = max(0, math.floor(min(cols)))
    c1 = min(src.width, math.ceil(max(cols)))
    r0 = max(0, math.floor(min(rows)))
    r1 = min(src.height, math.ceil(max(rows)))
    if c0 >= c1 or r0 >= r1:
        return None
    return Window(c0, r0, c1 - c0, r1 - r0)


def _pixel_area_fn(path: Path, crs: CRS, transform: Any) -> Callable[[int, int], np.ndarray]:
    """A function giving the pixel area (m^2) of each row in [r0, r1)."""
    unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
    if not crs.is_geographic:
        area = abs(transform.a * transform.e - transform.b * transform.d) * unit * unit

        def projected(r0: int, r1: int) -> np.ndarray:
            return np.full(r1 - r0, area)

        return projected

    if transform.b != 0 or transform.d != 0:
        raise SourceError(f"{path}: rotated geographic rasters are not supported")
    ellipsoid = crs.ellipsoid
    a = ellipsoid.semi_major_metre if ellipsoid is not None else 6378137.0
    b = ellipsoid.semi_minor_metre if ellipsoid is not None else 6356752.314245179
    ecc = math.sqrt(max(0.0, 1.0 - (b * b) / (a * a)))
    dlon = abs(transform.a) * unit  # radians

    def zone(lat_units: np.ndarray) -> np.ndarray:
        # Area per radian of longitude between the equator and latitude phi on the ellipsoid.
        s = np.sin(np.clip(lat_units * unit, -math.pi / 2, math.pi / 2))
        if ecc < 1e-12:
            return b * b * s
        es = ecc * s
        return b * b / 2 * (s / (1 - es * es) + np.log((1 + es) / (1 - es)) / (2 * ecc))

    def geographic(r0: int, r1: int) -> np.ndarray:
        edges = transform.f + transform.e * np.arange(r0, r1 + 1, dtype=np.float64)
        return dlon * np.abs(np.diff(zone(edges)))

    return geographic


class _ClassMasks:
    """Pixel codes -> one boolean mask per label present (codes not in the table and nodata excluded).

    With few codes (WorldCover has 10) a comparison per code is cheapest; with many (CORINE maps 32
    codes to 11 labels) the codes first go through a lookup table to label numbers.
    """

    def __init__(self, dtype: str, code_labels: Mapping[int, str], labels: tuple[str, ...],
                 nodata: float | None) -> None:
        dtype_ = np.dtype(dtype)
        info = np.iinfo(dtype_)
        index = {name: i + 1 for i, name in enumerate(labels)}
        pairs = {int(c): index[name] for c, name in code_labels.items() if info.min <= int(c) <= info.max}
        if nodata is not None and math.isfinite(nodata) and float(nodata).is_integer():
            pairs.pop(int(nodata), None)
        self.by_class: dict[int, list[int]] = {}
        for code, cls in sorted(pairs.items()):
            self.by_class.setdefault(cls, []).append(code)
        self.use_table = len(pairs) > _COMPARE_MAX_CODES
        if self.use_table and dtype_.itemsize * 8 <= _LUT_MAX_BITS:
            # Index by the code's unsigned bit pattern so signed types need no offset arithmetic.
            self.unsigned = np.dtype(f"u{dtype_.itemsize}")
            self.table = np.zeros(1 << (8 * dtype_.itemsize), np.uint8)
            for code, cls in pairs.items():
                self.table[np.array(code, dtype_).view(self.unsigned)] = cls
        elif self.use_table:
            order = sorted(pairs)
            self.codes = np.array(order, dtype=dtype_)
            self.values = np.array([pairs[c] for c in order], dtype=np.uint8)

    def _classes(self, data: np.ndarray) -> np.ndarray:
        if hasattr(self, "table"):
            return self.table[data.view(self.unsigned)]
        pos = np.searchsorted(self.codes, data)
        np.minimum(pos, self.codes.size - 1, out=pos)
        return np.where(self.codes[pos] == data, self.values[pos], np.uint8(0))

    def __call__(self, data: np.ndarray, valid: np.ndarray | None) -> Iterator[tuple[int, int, np.ndarray]]:
        """Yield ``(class number, first row, mask of rows first..last)`` for each label present."""
        if self.use_table:
            data = self._classes(data)
            by_value = {cls: [cls] for cls in self.by_class}
        else:
            by_value = self.by_class
        values = [v for vs in by_value.values() for v in vs]
        rows_with = dict(zip(values, _rows_with_values(data, values), strict=True))
        for cls, vs in by_value.items():
            present = [v for v in vs if rows_with[v].size]
            if not present:
                continue
            r0 = min(int(rows_with[v][0]) for v in present)
            r1 = max(int(rows_with[v][-1]) for v in present) + 1
            part = data[r0:r1]
            mask = part == present[0]
            for v in present[1:]:
                mask |= part == v
            if valid is not None:
                mask &= valid[r0:r1] != 0
            yield cls, r0, mask


def _rows_with_values(data: np.ndarray, values: list[int]) -> list[np.ndarray]:
    """For each value, the rows of ``data`` where it occurs.

    One pass over ``data`` in cache-sized row chunks, comparing each chunk with every value: a
    full-size comparison per value would stream the whole strip through memory once per value.
    """
    h, w = data.shape
    chunk = max(1, 1_000_000 // max(1, w))
    found = np.zeros((len(values), h), bool)
    scratch = np.empty((chunk, w), bool)
    for r in range(0, h, chunk):
        part = data[r:r + chunk]
        out = scratch[:part.shape[0]]
        for i, v in enumerate(values):
            np.equal(part, v, out=out)
            out.any(axis=1, out=found[i, r:r + part.shape[0]])
    return [np.flatnonzero(f) for f in found]


class _Patches:
    """Connected components accumulated over row strips, emitted once they can no longer grow.

    Per component we keep the sums ``area``, ``area * col`` and ``area * row`` (pixel-centre
    coordinates in the full raster's pixel grid), from which the centroid follows.
    """

    def __init__(self, width: int, col_off: int, min_area: float, connectivity: int) -> None:
        self.width = width
        self.col_off = col_off
        self.min_area = min_area
        self.structure = ndimage.generate_binary_structure(2, 2 if connectivity == 8 else 1)
        self.diagonal = connectivity == 8
        # Open components (touching the last row read): sums, class, and which one each column holds.
        self.open_sums = np.zeros((3, 0))
        self.open_cls = np.zeros(0, np.uint8)
        self.seam = np.full(width, -1, np.int64)
        self.out: list[tuple[np.ndarray, ...]] = []
        self.n_emitted = 0
        self._buffer = np.empty(0, np.int32)

    def add_strip(self, class_masks: Iterable[tuple[int, int, np.ndarray]], row_off: int,
                  row_area: np.ndarray, last: bool) -> None:
        """Label one strip starting at raster row ``row_off``, given as ``(class, first row, mask)``."""
        h, w = row_area.size, self.width
        sums_parts = [self.open_sums]
        cls_parts = [self.open_cls]
        first = np.full(w, -1, np.int64)
        final = np.full(w, -1, np.int64)
        n_nodes = self.open_cls.size
        for c, mask_row0, mask in class_masks:
            rows = np.flatnonzero(mask.any(axis=1))
            if rows.size == 0:
                continue
            # Label only the bounding box of this class in the strip; r0, r1 are strip rows.
            crop_rows = mask[rows[0]:rows[-1] + 1]
            r0, r1 = mask_row0 + int(rows[0]), mask_row0 + int(rows[-1]) + 1
            cols = np.flatnonzero(crop_rows.any(axis=0))
            c0, c1 = int(cols[0]), int(cols[-1]) + 1
            crop = crop_rows[:, c0:c1]
            del mask, crop_rows
            comp = self._label_buffer(crop.shape)
            n = ndimage.label(crop, structure=self.structure, output=comp)
            sums = _component_sums(crop, comp, n, row_area[r0:r1], row_off + r0, self.col_off + c0)
            sums_parts.append(sums)
            cls_parts.append(np.full(n, c, np.uint8))
            # Components on the strip's first and last rows, as node numbers, for the seams.
            if r0 == 0:
                top = comp[0]
                first[c0:c1] = np.where(top > 0, top.astype(np.int64) + (n_nodes - 1), first[c0:c1])
            if r1 == h:
                bottom = comp[-1]
                final[c0:c1] = np.where(bottom > 0, bottom.astype(np.int64) + (n_nodes - 1), final[c0:c1])
            n_nodes += n
            del crop
        node_sums = np.concatenate(sums_parts, axis=1)
        node_cls = np.concatenate(cls_parts)

        group, n_groups = self._join_seam(first, node_cls, n_nodes)
        group_sums = np.stack([np.bincount(group, weights=s, minlength=n_groups) for s in node_sums])
        group_cls = np.zeros(n_groups, np.uint8)
        group_cls[group] = node_cls
        still_open = np.zeros(n_groups, bool)
        if not last:
            still_open[group[final[final >= 0]]] = True
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
        self.seam = np.full(final.size, -1, np.int64)
        on_seam = final >= 0
        self.seam[on_seam] = renumber[group[final[on_seam]]]

    def _label_buffer(self, shape: tuple[int, int]) -> np.ndarray:
        # Reused between labellings: a fresh 100+ MB array per call costs as much in page faults as
        # the labelling itself.
        size = shape[0] * shape[1]
        if self._buffer.size < size:
            self._buffer = np.empty(size, np.int32)
        return self._buffer[:size].reshape(shape)

    def _join_seam(self, first: np.ndarray, node_cls: np.ndarray, n_nodes: int) -> tuple[np.ndarray, int]:
        """Group numbers of the nodes (open components + this strip's) once joined across the seam."""
        above, below = self.seam, first
        pairs = [(above, below)]
        if self.diagonal:
            pairs += [(above[:-1], below[1:]), (above[1:], below[:-1])]
        src_parts, dst_parts = [], []
        for a, b in pairs:
            hit = (a >= 0) & (b >= 0)
            a, b = a[hit], b[hit]
            same = node_cls[a] == node_cls[b]
            src_parts.append(a[same])
            dst_parts.append(b[same])
        src = np.concatenate(src_parts)
        dst = np.concatenate(dst_parts)
        if src.size == 0:
            return np.arange(n_nodes), n_nodes
        graph = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(n_nodes, n_nodes))
        n_groups, group = connected_components(graph, directed=False)
        return group, n_groups

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
