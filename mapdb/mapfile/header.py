"""The map file's header: written (with its prefix), parsed and checked, and the page directory checked.

One set of rules for the reader (a file from a stranger) and the writer (which checks what it is about to
write, so that a genuine map always passes).  Each names the file and the broken rule in one line.
"""

from __future__ import annotations

import json
import math
import re
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from .. import __version__
from ..errors import MapFormatError
from ..outputs import creation_time
from .codec import _AREA_FLOOR_LOG2, _AREA_STEPS
from .layout import (
    _M2_PER_OBJECT,
    _MAX_EXTENT,
    _MAX_LABELS,
    _MAX_PAGE_BYTES,
    _MAX_PAGE_OBJECTS,
    _MAX_QUANTA,
    _MIN_OBJECT_BITS,
    _MIN_PAGE_BITS,
    _PILE,
    _PREFIX,
    FLAT_FORMAT_VERSION,
    FORMAT_VERSION,
    MAGIC,
)
from .pages import _too_dense

__all__: list[str] = []

_MAX_HEADER = 16 << 20  # deflated header bytes
# The inflated header may be at most this long, and at most _HEADER_FREE + _HEADER_RATIO times its deflated
# length: a genuine header (a few kilobytes, with checksums that do not compress) is far inside both, and a
# small deflate bomb cannot make a reader allocate much more than the file's own size.
_MAX_HEADER_JSON = 16 << 20
_HEADER_FREE = 256 << 10
_HEADER_RATIO = 16
_MAX_DEPTH = 32  # nesting of the header JSON (a genuine one nests 3 deep)
_PAIR_BUDGET = 1 << 20  # candidate page pairs examined at once when checking that pages do not overlap


# --------------------------------------------------------------------------------------------- writing


def _lonlat_bounds(crs: CRS, bounds: tuple[float, float, float, float]) -> list[float] | None:
    try:
        to_lonlat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lonlat = [float(v) for v in to_lonlat.transform_bounds(*bounds, densify_pts=21)]
    except Exception:  # a CRS without a lon/lat relation (engineering CRS): no geographic bounds
        return None
    return lonlat if all(map(math.isfinite, lonlat)) else None  # positions outside the projection's domain


def _map_header(crs: CRS, labels: tuple[str, ...], counts: np.ndarray, table: np.ndarray, quantum: float,
                page_capacity: int, merged: int, metadata: dict[str, Any] | None,
                elevation: tuple[float, int] | None = None) -> dict[str, Any]:
    """The header of a map of these pages and objects per label code; ``metadata`` adds entries but replaces
    none; ``elevation`` (step in metres, cell side in quanta) makes it a version 2 map's."""
    bounds = _page_span(table, quantum)
    header = {
        "format": "mapdb",
        "format_version": FLAT_FORMAT_VERSION if elevation is None else FORMAT_VERSION,
        "crs": crs.to_string(),
        # An authority code names the CRS exactly; WKT (about a kilobyte) only when there is none.
        "crs_wkt": None if crs.to_epsg() else crs.to_wkt(),
        "quantum": quantum,
        "area_log2_steps": _AREA_STEPS,
        "area_floor_log2": _AREA_FLOOR_LOG2,
        "count": int(counts.sum()),
        "merged_duplicates": int(merged),
        "labels": [{"name": name, "code": i, "count": int(counts[i])} for i, name in enumerate(labels)],
        "bounds": list(bounds),
        "bounds_lonlat": _lonlat_bounds(crs, bounds),
        "page_capacity": page_capacity,
        "pages": len(table),
        "directory_crc32": zlib.crc32(table.tobytes()),
        "software": f"mapdb {__version__}",
        "created": creation_time(),
    }
    if elevation is not None:
        header["elevation_step_m"], header["elevation_cell"] = elevation
    for key, value in (metadata or {}).items():
        header.setdefault(key, value)
    return header


def _pack_prefix(path: Path, header: dict[str, Any], table: np.ndarray, quantum: float) -> bytes:
    """The file's prefix (fixed fields, deflated header, CRC), once the reader's own checks pass on it."""
    header_json = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    header_bytes = packer.compress(header_json) + packer.flush()
    # The reader's own checks, so that a map this writes is never one the reader refuses.
    try:
        if len(header_json) > _header_json_limit(len(header_bytes)):
            raise MapFormatError(f"{path}: header of {len(header_json)} bytes is too long")
        _check_header(_parse_header_json(header_json, str(path)), str(path), header["format_version"])
        _check_directory(table, quantum, tuple(header["bounds"]), int(header["count"]), str(path))
    except MapFormatError as exc:
        raise ValueError(f"cannot write a valid map: {exc}") from None
    prefix = _PREFIX.pack(MAGIC, header["format_version"], 0, len(header_bytes)) + header_bytes
    return prefix + struct.pack("<I", zlib.crc32(prefix))


# --------------------------------------------------------------------------------------------- checking


def _header_json_limit(deflated: int) -> int:
    """The longest inflated header a deflated header of ``deflated`` bytes may have."""
    return min(_MAX_HEADER_JSON, _HEADER_FREE + _HEADER_RATIO * deflated)


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:20]} is not a finite number")
    return value


def _short_int(text: str) -> int:
    # Python converts long digit strings in quadratic time; no header integer needs more than 20 digits.
    if len(text.lstrip("-")) > 20:
        raise ValueError(f"an integer of {len(text)} digits")
    return int(text)


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    doc = dict(pairs)
    if len(doc) != len(pairs):
        raise ValueError("an object repeats a key")
    return doc


def _one_line(text: object, limit: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _parse_header_json(text: bytes, where: str) -> Any:
    """Decode the header JSON: strict numbers, unique keys, bounded nesting, every string valid Unicode."""
    try:
        doc = json.loads(text.decode("utf-8"), parse_constant=_refuse_constant, parse_float=_finite_float,
                         parse_int=_short_int, object_pairs_hook=_unique_keys)
    except RecursionError:
        # json's C scanner counts its recursion against the interpreter's limit (about 1000 levels), so a
        # deeply nested header ends here long before the C stack is at risk.
        raise MapFormatError(f"{where}: header nests deeper than {_MAX_DEPTH} levels") from None
    except ValueError as exc:  # includes JSONDecodeError and UnicodeDecodeError
        raise MapFormatError(f"{where}: header is not valid JSON ({_one_line(exc, 80)})") from None
    # Walk it without recursion: nesting depth, and strings that can be printed (no lone surrogates).
    stack = [(doc, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict | list):
            if depth > _MAX_DEPTH:
                raise MapFormatError(f"{where}: header nests deeper than {_MAX_DEPTH} levels")
            items = value.items() if isinstance(value, dict) else ((None, v) for v in value)
            for key, item in items:
                if key is not None:
                    stack.append((key, depth))
                stack.append((item, depth + 1))
        elif isinstance(value, str):
            try:
                value.encode("utf-8")
            except UnicodeEncodeError:
                raise MapFormatError(f"{where}: header holds a string that is not valid Unicode") from None
    return doc


def _shown(value: Any) -> str:
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    return _one_line(repr(value[:40] if isinstance(value, str) else value), 48)


def _is_int(value: Any) -> bool:
    return type(value) is int  # not bool


def _is_number(value: Any) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


_MISSING = object()
_AUTHORITY_CODE = re.compile(r"[A-Za-z][A-Za-z0-9_.-]{0,31}:[A-Za-z0-9_.-]{1,32}")
_WKT_START = re.compile(r"\s*[A-Za-z][A-Za-z0-9_]*\s*\[")
# WKT constructs that name files (grids) or embed a PROJ string (which can name files): a map's CRS is
# resolved from PROJ's own database only.
_WKT_FILE_WORDS = re.compile(r"PARAMETERFILE|EXTENSION", re.IGNORECASE)


def _field(header: dict[str, Any], key: str, where: str, ok: Callable[[Any], bool], rule: str,
           required: bool = True) -> Any:
    """``header[key]`` if ``ok`` says it is well formed (None if optional and missing or null)."""
    value = header.get(key, _MISSING)
    if value is _MISSING or (value is None and not required):
        if required:
            raise MapFormatError(f"{where}: header lacks the field {key!r}")
        return None
    if not ok(value):
        raise MapFormatError(f"{where}: header field {key!r} must be {rule} (got {_shown(value)})")
    return value


def _check_crs(crs: str, crs_wkt: str | None, where: str) -> str:
    """The CRS text readers will use (WKT if given, else the authority code), checked to be projected."""
    if crs_wkt is None:
        if not _AUTHORITY_CODE.fullmatch(crs):
            raise MapFormatError(f"{where}: header field 'crs' must be AUTHORITY:CODE when there is no crs_wkt "
                                 f"(got {_shown(crs)})")
        text = crs
    else:
        if not _WKT_START.match(crs_wkt) or _WKT_FILE_WORDS.search(crs_wkt):
            raise MapFormatError(f"{where}: header field 'crs_wkt' is not a self-contained WKT CRS")
        text = crs_wkt
    try:
        parsed = CRS.from_user_input(text)
    except CRSError as exc:
        raise MapFormatError(f"{where}: the map's CRS is not one pyproj knows ({_one_line(exc, 100)})") from None
    if not parsed.is_projected:
        raise MapFormatError(f"{where}: the map's CRS {_shown(parsed.name)} is not a projected CRS")
    return text


def _is_source(entry: Any) -> bool:
    return (isinstance(entry, dict) and all(isinstance(entry.get(k), str) for k in ("name", "kind", "sha256"))
            and all(_is_int(entry.get(k)) and entry[k] >= 0 for k in ("size", "objects")))


def _check_header(header: Any, where: str, version: int) -> dict[str, Any]:
    """Check a decoded header's meaning; returns the fields a reader uses (``crs`` is the text to parse)."""
    if not isinstance(header, dict):
        raise MapFormatError(f"{where}: header is not a JSON object")
    _field(header, "format", where, lambda v: v == "mapdb", '"mapdb"')
    _field(header, "format_version", where, lambda v: _is_int(v) and v == version,
           f"{version}, the version in the file's first bytes")
    _field(header, "area_log2_steps", where, lambda v: _is_int(v) and v == _AREA_STEPS, str(_AREA_STEPS))
    _field(header, "area_floor_log2", where, lambda v: _is_int(v) and v == _AREA_FLOOR_LOG2, str(_AREA_FLOOR_LOG2))
    quantum = float(_field(header, "quantum", where, lambda v: _is_number(v) and 0 < v <= 1000,
                           "a number in (0, 1000]"))
    count = _field(header, "count", where, lambda v: _is_int(v) and v >= 1, "a positive integer")
    pages = _field(header, "pages", where, lambda v: _is_int(v) and v >= 1, "a positive integer")
    crc = _field(header, "directory_crc32", where, lambda v: _is_int(v) and 0 <= v < 1 << 32, "a CRC-32")
    bounds = _field(header, "bounds", where, lambda v: isinstance(v, list) and len(v) == 4 and all(map(
        _is_number, v)) and v[0] <= v[2] and v[1] <= v[3], "[minx, miny, maxx, maxy], finite, min <= max")
    _field(header, "bounds_lonlat", where, lambda v: isinstance(v, list) and len(v) == 4 and all(map(
        _is_number, v)), "null or four numbers", required=False)
    _field(header, "page_capacity", where, lambda v: _is_int(v) and 1 <= v <= _MAX_PAGE_OBJECTS,
           f"an integer in [1, {_MAX_PAGE_OBJECTS}]", required=False)
    _field(header, "merged_duplicates", where, lambda v: _is_int(v) and v >= 0, "a count", required=False)
    for key in ("software", "created"):
        _field(header, key, where, lambda v: isinstance(v, str), "null or a string", required=False)
    _field(header, "sources", where, lambda v: isinstance(v, list) and all(map(_is_source, v)),
           "a list of {name, kind, size, sha256, objects}", required=False)
    _field(header, "build", where, lambda v: isinstance(v, dict), "an object", required=False)
    labels = _field(header, "labels", where, lambda v: isinstance(v, list) and 1 <= len(v) <= _MAX_LABELS,
                    f"a list of 1 to {_MAX_LABELS} labels")
    names = []
    for i, entry in enumerate(labels):
        if not (isinstance(entry, dict) and isinstance(entry.get("name"), str) and 0 < len(entry["name"]) <= 100
                and entry["name"].isprintable() and entry.get("code") == i and _is_int(entry.get("code"))
                and _is_int(entry.get("count")) and entry["count"] >= 0):
            raise MapFormatError(f"{where}: header label {i} must be {{name: printable text, code: {i}, "
                                 f"count: integer >= 0}} (got {_shown(entry)})")
        names.append(entry["name"])
    if len(set(names)) != len(names):
        raise MapFormatError(f"{where}: header names a label twice")
    if sum(entry["count"] for entry in labels) != count:
        raise MapFormatError(f"{where}: header label counts do not add up to its count {count}")
    crs = _field(header, "crs", where, lambda v: isinstance(v, str) and 0 < len(v) <= 4096, "a CRS name")
    crs_wkt = _field(header, "crs_wkt", where, lambda v: isinstance(v, str) and len(v) <= 1 << 20,
                     "null or WKT text", required=False)
    return {"quantum": quantum, "count": count, "pages": pages, "directory_crc32": crc,
            "bounds": tuple(float(v) for v in bounds), "labels": tuple(names), "crs": _check_crs(crs, crs_wkt, where),
            **_elevation_fields(header, where, version)}


def _elevation_fields(header: dict[str, Any], where: str, version: int) -> dict[str, Any]:
    """A version 2 header's elevation code step (metres) and cell side (quanta); nothing for version 1."""
    if version < 2:
        return {}
    step = _field(header, "elevation_step_m", where, lambda v: _is_number(v) and 0 < v <= 1000,
                  "a number in (0, 1000]")
    cell = _field(header, "elevation_cell", where, lambda v: _is_int(v) and 1 <= v <= _MAX_EXTENT + 1,
                  f"an integer in [1, {_MAX_EXTENT + 1}]")
    return {"elevation_step_m": float(step), "elevation_cell": int(cell)}


def _page_span(table: np.ndarray, quantum: float) -> tuple[float, float, float, float]:
    """The box of all page boxes in metres: the header bounds of a map with this directory."""
    ex, ey = table["ex"].astype(np.int64), table["ey"].astype(np.int64)
    return (float(table["ox"].min() * quantum), float(table["oy"].min() * quantum),
            float((table["ox"] + ex).max() * quantum), float((table["oy"] + ey).max() * quantum))


def _check_directory(table: np.ndarray, quantum: float, bounds: tuple[float, ...], count: int,
                     where: str) -> shapely.STRtree:
    """Check the page records against the format's limits and each other; returns their R-tree (in quanta).

    Vectorised, so that a directory of many tiny pages costs little more than a genuine one.
    """
    ox, oy = table["ox"], table["oy"]
    ex, ey = table["ex"].astype(np.int64), table["ey"].astype(np.int64)
    n, length = table["count"].astype(np.int64), table["length"].astype(np.int64)

    def refuse(bad: np.ndarray, problem: str) -> None:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise MapFormatError(f"{where}: page {i} {problem.format(n=int(n[i]), length=int(length[i]))}")

    refuse((n < 1) | (n > _MAX_PAGE_OBJECTS), f"holds {{n}} objects (1 to {_MAX_PAGE_OBJECTS} allowed)")
    refuse((ex > _MAX_EXTENT) | (ey > _MAX_EXTENT), f"extends {1 << 24} quanta or more")
    far = _MAX_QUANTA - _MAX_EXTENT
    refuse((ox > far) | (ox < -far) | (oy > far) | (oy < -far), f"lies beyond {far} quanta from the origin")
    refuse(8 * length < _MIN_PAGE_BITS + _MIN_OBJECT_BITS * n, "has {length} bytes, too few for {n} objects")
    refuse(length > _MAX_PAGE_BYTES, f"has {{length}} bytes (at most {_MAX_PAGE_BYTES})")
    refuse(_too_dense(n, ex, ey, quantum), f"is too dense: {{n}} objects, more than {_PILE} and more than one "
           f"per {_M2_PER_OBJECT:g} m2 of its box")
    if int(n.sum()) != count:
        raise MapFormatError(f"{where}: pages hold {int(n.sum())} objects, the header counts {count}")
    span = _page_span(table, quantum)
    if span != tuple(bounds):
        raise MapFormatError(f"{where}: header bounds {list(bounds)} are not the pages' box {list(span)}")
    # Page boxes as closed boxes of whole quanta: two pages overlap exactly when they share a position.
    boxes = shapely.box(ox, oy, ox + ex, oy + ey)
    tree = shapely.STRtree(boxes)
    step = max(1, _PAIR_BUDGET // len(boxes))  # a directory of pages piled on one spot cannot blow up the pairs
    for start in range(0, len(boxes), step):
        pairs = tree.query(boxes[start : start + step])
        other = pairs[1] != pairs[0] + start
        if other.any():
            j = int(np.flatnonzero(other)[0])
            raise MapFormatError(f"{where}: pages {int(pairs[0][j]) + start} and {int(pairs[1][j])} overlap")
    return tree
