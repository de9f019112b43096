"""The paper's storage argument, measured: a map's bytes per object and per km², against other ways to store
the same objects, per region cell and in total.

For one map (or a source, built into a temporary map first) the same objects are written as GeoPackage,
GeoParquet (zstd) and FlatGeobuf (points in the map CRS with ``label`` and ``area_m2``, as
:meth:`Objects.to_geodataframe` gives them), and their columns, sorted and quantised as the map stores them,
through a general-purpose compressor (lzma; zstd too when the ``zstandard`` module is installed).  Each
file is written in a temporary directory, its size taken, and removed.  An orthophoto of the same area is
costed, not rendered: ``pixels * bits per pixel / 8`` bytes.

**Cells.** A square grid of ``cell_m`` in the map CRS, aligned on its multiples (cell ``(i, j)`` spans
``[i cell, (i + 1) cell) x [j cell, (j + 1) cell)``).  The *occupied area* is that of the cells holding at
least one object; the *bounding-box area* that of the map's bounds.  A map's bytes are attributed to cells
through its pages: each page's bytes and its 36-byte directory record are shared equally by the page's
objects, the header (prefix, CRS, labels, provenance, checksum) by all objects, and a cell gets the shares
of its objects, so the cells' bytes sum to the file size.  The other formats have no pages; their bytes are
shared equally by all objects (the chunked compressor's by its chunks, which are the map's pages).  The
*window* of a cell is the bytes of the map's pages whose box meets the cell: what a reader reads from disk
to answer a query of that cell (after the header and directory, read once when the map is opened).
"""

from __future__ import annotations

import importlib.util
import lzma
import os
import stat
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from ..build.pipeline import build_map
from ..errors import MapdbError, MapdbIOError, MapFormatError
from ..mapfile.codec import area_codes
from ..mapfile.layout import MAGIC
from ..mapfile.reader import MetaMap, open_map
from ..objects import Objects
from ..progress import ProgressLike, as_progress

__all__ = ["DEFAULT_CELL_M", "DEFAULT_GSD_M", "DEFAULT_JPEG_BPP", "format_storage", "sorted_columns",
           "storage_report", "storage_reports", "storage_total"]

DEFAULT_CELL_M = 1000.0
DEFAULT_GSD_M = 0.3
# Bits per pixel of an RGB orthophoto stored as JPEG: an assumption, not a measurement.  24-bit colour at
# about 16:1 (JPEG quality around 75-85 with 4:2:0 chroma, as orthophoto services commonly deliver) gives
# 1.5; the cost scales linearly, so a reader can rescale it.
DEFAULT_JPEG_BPP = 1.5
_DIR_RECORD = 36  # bytes of a page's directory record (docs/format.md)
_LZMA_FILTERS = [{"id": lzma.FILTER_LZMA2, "preset": 9 | lzma.PRESET_EXTREME}]
_M2_PER_KM2 = 1e6


# ------------------------------------------------------------------------------------------ columns


def sorted_columns(objects: Objects, quantum: float, *, deltas: bool = True) -> bytes:
    """The objects as a general-purpose compressor is given them, quantised as a map stores them.

    Rows sorted by (label, y, x); then column after column, little-endian: x and y in whole quanta from
    their minimum (u32 each), the label code (u8), the area's map code (u16, the map's +-4.4 %).  With
    ``deltas`` each y is its step from the previous object of its label (the first keeps its value):
    sorted rows make those steps small, the one transform a general-purpose compressor cannot find itself.

    Examples
    --------
    >>> o = Objects.from_names([0.0, 10.0, 5.0], [0.0, 0.0, 2.0], ["park", "park", "building"], area=[0, 0, 64])
    >>> len(sorted_columns(o, 0.1))  # 3 objects of 4 + 4 + 1 + 2 bytes
    33
    """
    qx, qy = (np.rint(v / quantum).astype(np.int64) for v in (objects.x, objects.y))
    return _columns(qx, qy, objects.label, area_codes(objects.area), deltas=deltas)


def _columns(qx: np.ndarray, qy: np.ndarray, label: np.ndarray, code: np.ndarray, *, deltas: bool) -> bytes:
    """:func:`sorted_columns` of positions in quanta and area codes."""
    order = np.lexsort((qx, qy, label))
    x, y, lab = qx[order] - qx.min(), qy[order] - qy.min(), label[order]
    if deltas and y.size:
        first = np.r_[True, lab[1:] != lab[:-1]]
        y = np.where(first, y, y - np.r_[0, y[:-1]])
    return b"".join([x.astype("<u4").tobytes(), y.astype("<u4").tobytes(), lab.astype("u1").tobytes(),
                     code[order].astype("<u2").tobytes()])


def _lzma(data: bytes, raw: bool = False) -> int:
    """Bytes of ``data`` as an .xz file (with its CRC-32, as map pages have theirs) or, ``raw``, as a bare
    LZMA2 chunk (whose length and checksum go in a directory record beside it)."""
    if raw:
        return len(lzma.compress(data, format=lzma.FORMAT_RAW, filters=_LZMA_FILTERS))
    return len(lzma.compress(data, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC32, filters=_LZMA_FILTERS))


def _compressors() -> list[tuple[str, Callable[[bytes], int]]]:
    """(name, compressed size) of the general-purpose compressors at hand: lzma, and zstd if installed."""
    found: list[tuple[str, Callable[[bytes], int]]] = [("lzma", _lzma)]
    if importlib.util.find_spec("zstandard") is not None:  # never installed on purpose: used when present
        zstd = importlib.import_module("zstandard")
        found.append(("zstd -19", lambda data: len(zstd.ZstdCompressor(level=19).compress(data))))
    return found


# ------------------------------------------------------------------------------------------ the map


def _page_of_objects(m: MetaMap, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
    """The page holding each object: the one page whose box holds its position (page boxes are disjoint)."""
    table, where = m.page_directory, str(m.path)
    hits = m.pages_meeting(shapely.points(qx, qy))
    page = np.full(qx.size, -1, np.int64)
    page[hits[0]] = hits[1]
    if hits.shape[1] != qx.size or (page < 0).any() or \
            not np.array_equal(np.bincount(page, minlength=len(table)), table["count"]):
        raise MapFormatError(f"{where}: objects and page boxes disagree")
    return page


def _window_bytes(m: MetaMap, cells: np.ndarray, cell_q: float) -> np.ndarray:
    """Bytes of the pages whose box meets each cell (cells as (i, j) rows, ``cell_q`` quanta a side)."""
    table = m.page_directory
    lo = cells * cell_q
    hits = m.pages_meeting(shapely.box(lo[:, 0], lo[:, 1], lo[:, 0] + cell_q, lo[:, 1] + cell_q))
    return np.bincount(hits[0], weights=table["length"][hits[1]].astype(np.float64), minlength=len(cells))


def _geo_formats(objects: Objects, order: np.ndarray, tmp: Path) -> list[tuple[str, int]]:
    """(name, file size) of the objects written as GeoPackage, GeoParquet (zstd) and FlatGeobuf."""
    frame = objects.take(order).to_geodataframe()
    sizes = []
    for name, file in (("GeoPackage", "objects.gpkg"), ("GeoParquet (zstd)", "objects.parquet"),
                       ("FlatGeobuf", "objects.fgb")):
        path = tmp / file
        try:
            if file.endswith(".parquet"):
                frame.to_parquet(path, compression="zstd")
            else:
                frame.to_file(path, driver="GPKG" if file.endswith(".gpkg") else "FlatGeobuf", engine="pyogrio",
                              layer="objects")
        except Exception as exc:  # a driver's own error types: what failed is our temporary file
            raise MapdbIOError(f"{path}: cannot write {name} ({exc})") from exc
        sizes.append((name, path.stat().st_size))
    return sizes


# ------------------------------------------------------------------------------------------ measuring


def _stats(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {"median": None, "p95": None, "max": None}
    return {"median": round(float(np.median(values)), 3), "p95": round(float(np.percentile(values, 95)), 3),
            "max": round(float(values.max()), 3)}


def _row(name: str, total: float, cell_bytes: np.ndarray | None, geometry: dict[str, Any],
         attributed_by: str) -> dict[str, Any]:
    """One format's figures, from its bytes in all and in each occupied cell (None: not per cell)."""
    n, area_km2, bbox_km2 = geometry["objects"], geometry["area_km2"], geometry["bbox_km2"]
    return {
        "format": name, "bytes": int(round(total)), "bytes_per_object": round(total / n, 3),
        "bytes_per_km2": round(total / area_km2, 1),
        "bytes_per_km2_bbox": round(total / bbox_km2, 1) if bbox_km2 > 0 else None,
        "attributed_by": attributed_by,
        "cells": None if cell_bytes is None else _cell_stats(cell_bytes, geometry["cell_objects"],
                                                             geometry["cell_km2"]),
        "cell_bytes": None if cell_bytes is None else np.round(cell_bytes, 3).tolist(),
    }


def _per_cell(geometry: dict[str, Any], per_object: np.ndarray) -> np.ndarray:
    """Each occupied cell's bytes: the sum of its objects' shares."""
    return np.bincount(geometry["cell_of"], weights=per_object, minlength=len(geometry["cell_objects"]))


def _cell_stats(cell_bytes: np.ndarray, cell_objects: np.ndarray, cell_km2: float) -> dict[str, Any]:
    """Median, 95th percentile and maximum over cells of bytes per km² and per object."""
    return {"bytes_per_km2": _stats(cell_bytes / cell_km2), "bytes_per_object": _stats(cell_bytes / cell_objects)}


def _compressor_rows(objects: Objects, q: tuple[np.ndarray, ...], page: np.ndarray, table: np.ndarray,
                     geometry: dict[str, Any]) -> list[dict[str, Any]]:
    """The sorted columns through each compressor, whole, and (lzma) in chunks that are the map's pages."""
    n = len(objects)
    qx, qy, code = q
    rows = []
    for name, size in _compressors():
        for deltas, what in ((False, "sorted columns"), (True, "sorted columns, y deltas")):
            total = size(_columns(qx, qy, objects.label, code, deltas=deltas))
            rows.append(_row(f"{name}: {what}", total, _per_cell(geometry, np.full(n, total / n)), geometry,
                             "objects"))
    # Chunked like the map's pages, each with a directory record as the map has: the same random access.
    order = np.argsort(page, kind="stable")
    ends = np.cumsum(table["count"].astype(np.int64))
    per_page = np.array([_lzma(_columns(*(a[order[e - c:e]] for a in (qx, qy, objects.label, code)),
                                              deltas=True), raw=True)
                         for e, c in zip(ends, table["count"].astype(np.int64), strict=True)], np.float64)
    per_page += _DIR_RECORD
    share = (per_page / table["count"])[page]
    rows.append(_row("lzma per page: y deltas, +36 B record", float(per_page.sum()), _per_cell(geometry, share),
                     geometry, "pages"))
    return rows


def _cells_of(qx: np.ndarray, qy: np.ndarray, quantum: float, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells ((i, j) rows, sorted) and each object's cell (an index into them)."""
    ij = np.stack([np.floor(qx * quantum / cell_m), np.floor(qy * quantum / cell_m)], axis=1).astype(np.int64)
    cells, cell_of = np.unique(ij, axis=0, return_inverse=True)
    return cells, cell_of.reshape(-1)


def _orthophoto_rows(geometry: dict[str, Any], gsd_m: float, jpeg_bpp: float) -> list[dict[str, Any]]:
    """An orthophoto of the occupied cells and of the bounding box, costed at ``jpeg_bpp`` bits a pixel."""
    per_km2 = jpeg_bpp / 8 / gsd_m**2 * _M2_PER_KM2
    name = f"JPEG {gsd_m:g} m, {jpeg_bpp:g} bpp"
    cell_bytes = np.full(len(geometry["cell_objects"]), geometry["cell_km2"] * per_km2)
    # (a bounding box is not made of the occupied cells: no figures per cell)
    return [_row(f"{name}: occupied cells", geometry["area_km2"] * per_km2, cell_bytes, geometry, "area"),
            _row(f"{name}: bounding box", geometry["bbox_km2"] * per_km2, None, geometry, "area")]


def _geometry(m: MetaMap, qx: np.ndarray, qy: np.ndarray, cell_m: float) -> tuple[np.ndarray, dict[str, Any]]:
    """The occupied cells, and what every row needs of them: counts, areas, each object's cell."""
    cells, cell_of = _cells_of(qx, qy, m.quantum, cell_m)
    b = m.bounds
    return cells, {"objects": qx.size, "cell_of": cell_of, "cell_objects": np.bincount(cell_of, minlength=len(cells)),
                   "cell_km2": cell_m**2 / _M2_PER_KM2, "area_km2": len(cells) * cell_m**2 / _M2_PER_KM2,
                   "bbox_km2": (b[2] - b[0]) * (b[3] - b[1]) / _M2_PER_KM2}


def _measure(m: MetaMap, tmp: Path, cell_m: float, gsd_m: float, jpeg_bpp: float) -> dict[str, Any]:
    """Every row of one open map; ``tmp`` is an empty directory for the files written to be measured."""
    objects = m.all()
    n, where = len(objects), str(m.path)
    qx, qy = (np.rint(v / m.quantum).astype(np.int64) for v in (objects.x, objects.y))
    table = m.page_directory
    page = _page_of_objects(m, qx, qy)
    cells, geometry = _geometry(m, qx, qy, cell_m)
    share = m.page_shares()[page]
    rows = [_row("mapdb", m.file_size, _per_cell(geometry, share), geometry, "pages")]
    order = np.lexsort((qx, qy, objects.label))
    rows += [_row(name, size, _per_cell(geometry, np.full(n, size / n)), geometry, "objects")
             for name, size in _geo_formats(objects, order, tmp)]
    rows += _compressor_rows(objects, (qx, qy, area_codes(objects.area)), page, table, geometry)
    rows += _orthophoto_rows(geometry, gsd_m, jpeg_bpp)
    for row in rows:
        row["ratio_to_mapdb"] = round(row["bytes"] / m.file_size, 3)
    window = _window_bytes(m, cells, cell_m / m.quantum)
    return {
        "map": where, "crs": m.crs, "quantum_m": m.quantum, "objects": n, "pages": len(table),
        "area": {"cell_m": cell_m, "occupied_cells": len(cells), "occupied_km2": round(geometry["area_km2"], 6),
                 "bbox_km2": round(geometry["bbox_km2"], 6)},
        "mapdb_parts": {"header": m.file_size - _DIR_RECORD * len(table) - int(table["length"].sum()),
                        "directory": _DIR_RECORD * len(table),
                        "pages": int(table["length"].sum())},
        "window_bytes": {**_stats(window), "file": m.file_size},
        "formats": rows,
        "cells": {"x0": (cells[:, 0] * cell_m).tolist(), "y0": (cells[:, 1] * cell_m).tolist(),
                  "objects": geometry["cell_objects"].tolist(), "window_bytes": window.astype(np.int64).tolist()},
    }


# ------------------------------------------------------------------------------------------ inputs


def _is_map(path: Path) -> bool:
    """Whether ``path`` is to be read as a map: a ``.mapdb`` name, a regular file starting with the magic, or
    something that is no regular file (a directory, a FIFO: :func:`open_map` refuses it, saying what it is).

    Anything else is a source to build: the builder reports a missing or unreadable one.
    """
    if path.suffix.lower() == ".mapdb":
        return True
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return True
        with open(path, "rb") as f:  # a regular file: reading its first bytes cannot block
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


@contextmanager
def _opened(source: str | Path, tmp: Path, progress: ProgressLike) -> Iterator[tuple[MetaMap, bool]]:
    """The map ``source`` is, or the map built from it in ``tmp``; and whether it was built."""
    path = Path(source)
    built = not _is_map(path)
    if built:
        path = tmp / "built.mapdb"
        build_map([source], path, progress=progress)
    m = open_map(path)
    try:
        yield m, built
    finally:
        m.close()


def storage_report(source: str | Path, *, cell_m: float = DEFAULT_CELL_M, gsd_m: float = DEFAULT_GSD_M,
                   jpeg_bpp: float = DEFAULT_JPEG_BPP, progress: ProgressLike = None) -> dict[str, Any]:
    """Bytes of a map, per object and per km², against other formats, per cell and in total.

    Parameters
    ----------
    source : path
        A map, or anything :func:`mapdb.build.pipeline.build_map` reads (built with its defaults into a temporary
        map that is removed afterwards).
    cell_m : float
        Side of the grid's cells in the map CRS, metres (at least 1).
    gsd_m, jpeg_bpp : float
        The orthophoto costed for comparison: ground sample distance (metres a pixel) and JPEG bits a pixel.

    Returns
    -------
    dict
        ``map``, ``crs``, ``objects``, ``pages``, ``area`` (occupied cells and their km², bounding-box km²),
        ``mapdb_parts`` (header, directory, pages), ``window_bytes`` (over cells: the bytes of the pages a
        query of one cell reads), ``formats`` (one row a format: ``bytes``, ``bytes_per_object``,
        ``bytes_per_km2`` over the occupied area, ``bytes_per_km2_bbox``, ``ratio_to_mapdb``, ``cells``
        statistics and ``cell_bytes`` in the order of ``cells``) and ``cells`` (each occupied cell's
        corner, objects and window bytes).  See the module's description for the attribution.

    Raises
    ------
    MapdbError
        A map that cannot be read (:class:`~mapdb.errors.MapFormatError`, ...) or a source that cannot be
        built (:class:`~mapdb.errors.SourceError`, :class:`~mapdb.errors.EmptyMapError`, ...).
    ValueError
        A ``cell_m`` below 1, a ``gsd_m`` or ``jpeg_bpp`` that is not a positive finite number.
    """
    # Cells of at least a metre keep every cell index of a valid map (within 2**52 quanta of at most 1 km of
    # the origin) inside int64.
    for name, value, low in (("cell_m", cell_m, 1.0), ("gsd_m", gsd_m, 0.0), ("jpeg_bpp", jpeg_bpp, 0.0)):
        if not (np.isfinite(value) and value > 0 and value >= low):
            raise ValueError(f"{name} must be a finite number above 0 and at least {low:g}, not {value!r}")
    say = as_progress(progress)
    with tempfile.TemporaryDirectory(prefix="mapdb-storage-") as tmp, _opened(source, Path(tmp), say) as (m, built):
        say(f"measuring {source} ({len(m)} objects) ...")
        report = _measure(m, Path(tmp), cell_m, gsd_m, jpeg_bpp)
    report["input"], report["built_from_source"] = str(source), built
    if built:
        report["map"] = None  # the temporary map is gone
    return report


def storage_reports(sources: Sequence[str | Path], *, cell_m: float = DEFAULT_CELL_M, gsd_m: float = DEFAULT_GSD_M,
                    jpeg_bpp: float = DEFAULT_JPEG_BPP, progress: ProgressLike = None,
                    on_error: Callable[[MapdbError | OSError], None] | None = None) -> dict[str, Any]:
    """:func:`storage_report` of every source, and their total.

    With ``on_error``, a source that fails is reported to it and left out, and the others are still
    measured (the errors are also listed in the result); without it, the first error is raised.

    Returns
    -------
    dict
        ``parameters``, ``maps`` (one :func:`storage_report` each), ``total`` (:func:`storage_total`, None
        when no source was measured) and ``errors`` (``{"input", "error"}``).
    """
    reports, errors = [], []
    for source in sources:
        try:
            reports.append(storage_report(source, cell_m=cell_m, gsd_m=gsd_m, jpeg_bpp=jpeg_bpp, progress=progress))
        except (MapdbError, OSError) as exc:
            if on_error is None:
                raise
            on_error(exc)
            errors.append({"input": str(source), "error": str(exc)})
    parameters = {"cell_m": cell_m, "gsd_m": gsd_m, "jpeg_bpp": jpeg_bpp, "jpeg_bpp_is": "assumed",
                  "compressors": [name for name, _ in _compressors()]}
    return {"parameters": parameters, "maps": reports, "total": storage_total(reports) if reports else None,
            "errors": errors}


def storage_total(reports: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The maps of several :func:`storage_report` results taken together (same options); cells pooled."""
    cell_m = reports[0]["area"]["cell_m"]
    objects = [np.asarray(r["cells"]["objects"], np.float64) for r in reports]
    geometry = {"objects": sum(r["objects"] for r in reports), "cell_objects": np.concatenate(objects),
                "cell_km2": cell_m**2 / _M2_PER_KM2, "area_km2": sum(r["area"]["occupied_km2"] for r in reports),
                "bbox_km2": sum(r["area"]["bbox_km2"] for r in reports)}
    rows = []
    for i, first in enumerate(reports[0]["formats"]):
        same = [r["formats"][i] for r in reports]
        cells = None if any(s["cell_bytes"] is None for s in same) else \
            np.concatenate([np.asarray(s["cell_bytes"], np.float64) for s in same])
        rows.append(_row(first["format"], sum(s["bytes"] for s in same), cells, geometry, first["attributed_by"]))
        del rows[-1]["cell_bytes"]  # each map's are in its report
    for row in rows:
        row["ratio_to_mapdb"] = round(row["bytes"] / rows[0]["bytes"], 3)
    return {"maps": len(reports), "objects": geometry["objects"], "pages": sum(r["pages"] for r in reports),
            "area": {"cell_m": cell_m, "occupied_cells": int(geometry["cell_objects"].size),
                     "occupied_km2": round(geometry["area_km2"], 6), "bbox_km2": round(geometry["bbox_km2"], 6)},
            "formats": rows}


# ------------------------------------------------------------------------------------------ the table


def _n(value: float | None, decimals: int = 0) -> str:
    return "-" if value is None else f"{value:,.{decimals}f}"


def format_storage(result: dict[str, Any]) -> str:
    """A :func:`storage_reports` result as tables for people: one a map, the total of several, and notes."""
    tables = [_table(report) for report in result["maps"]]
    if len(result["maps"]) > 1:
        tables.append(_table(result["total"]))
    p = result["parameters"]
    notes = (f"Cells: {p['cell_m'] / 1000:g} km squares of the map CRS; B/km² is over the cells holding objects, "
             f"B/km² bbox over the map's bounding box.  JPEG: pixels at {p['gsd_m']:g} m x {p['jpeg_bpp']:g} "
             "bits a pixel / 8, an assumed rate (no image is made).")
    return "\n\n".join([*tables, notes]) if tables else ""


def _table(report: dict[str, Any]) -> str:
    """One :func:`storage_report` (or :func:`storage_total`) as a table."""
    area = report["area"]
    if "maps" in report:
        title = f"total of {report['maps']} maps: {report['objects']:,} objects in {report['pages']:,} pages"
    else:
        built = " (built from the source)" if report["built_from_source"] else ""
        title = (f"{report['input']}{built}: {report['objects']:,} objects in {report['pages']:,} pages, "
                 f"{report['crs']}, quantum {report['quantum_m']:g} m")
    lines = [title,
             f"area: {area['occupied_cells']:,} cells of {area['cell_m'] / 1000:g} km with objects = "
             f"{_n(area['occupied_km2'], 2)} km²; bounding box {_n(area['bbox_km2'], 2)} km²",
             f"{'format':<42}{'bytes':>15}{'B/object':>12}{'B/km²':>13}{'B/km² bbox':>13}{'x mapdb':>11}"]
    for row in report["formats"]:
        lines.append(f"{row['format']:<42}{_n(row['bytes']):>15}{_n(row['bytes_per_object'], 2):>12}"
                     f"{_n(row['bytes_per_km2']):>13}{_n(row['bytes_per_km2_bbox']):>13}"
                     f"{_n(row['ratio_to_mapdb'], 3 if row['ratio_to_mapdb'] < 10 else 0):>11}")
    cells = report["formats"][0]["cells"]["bytes_per_km2"]
    lines.append(f"mapdb per cell: median {_n(cells['median'], 1)} B/km², 95th percentile {_n(cells['p95'], 1)}, "
                 f"max {_n(cells['max'], 1)}")
    if "window_bytes" in report:
        parts, w = report["mapdb_parts"], report["window_bytes"]
        lines.append(f"mapdb file: header {parts['header']:,} B (CRS, labels, sources, checksum), directory "
                     f"{parts['directory']:,} B, pages {parts['pages']:,} B; a query of one cell reads pages of "
                     f"median {_n(w['median'])} B (95th percentile {_n(w['p95'])} B)")
    return "\n".join(lines)
