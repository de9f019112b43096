"""The map file: labelled centroids in compressed, spatially compact pages with an R-tree.

A map is one file (format described in ``docs/format.md``)::

    magic "\\x89MAPDB\\r\\n" | u16 version | u16 flags | u32 header length | header (JSON)
    | u32 CRC-32 of everything before it | page directory (36 bytes a page) | pages

(the header is deflated JSON)

Objects are split into pages of at most ``page_capacity`` objects by recursive
median cuts, so every page covers a compact area.  Inside a page, positions are
integers at the quantum relative to the page origin; each label's objects form
one run, sorted by their row-major key ``qy * (extent_x + 1) + qx`` and stored
as Rice-coded key gaps (close to the entropy of a random point set, so labels
cost nothing beyond their run headers).  Areas are log-quantized codes, stored
as Rice-coded residuals from their run's median.  The header, the directory and each page carry a CRC-32; pages are
read and checked only when a query needs them.

Reading a file never executes anything from it (JSON and fixed binary records
only), and every length and count read from it is checked against the file
size and the format's bounds before memory is allocated for it.
"""

from __future__ import annotations

import json
import os
import struct
import tempfile
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pyproj import CRS, Transformer
from rtree import index as rtree_index

from . import __version__
from .errors import EmptyMapError, MapFormatError, MapVersionError, reading
from .objects import Objects

__all__ = [
    "FORMAT_VERSION",
    "MAGIC",
    "MapBase",
    "MemoryMap",
    "MetaMap",
    "open_map",
    "write_map",
]

MAGIC = b"\x89MAPDB\r\n"
FORMAT_VERSION = 1
_PREFIX = struct.Struct("<8sHHI")
_DIR_RECORD = struct.Struct("<qqIIIII")  # origin x, y (quanta), extent x, y, count, byte length, crc32
_MAX_HEADER = 64 << 20
_MAX_PAGE_OBJECTS = 65535
_MAX_EXTENT = (1 << 24) - 1  # keeps the row-major key under 2**48
_AREA_STEPS = 8  # codes per doubling of area: +-4.4 % relative precision
_AREA_FLOOR_LOG2 = -16  # smallest non-zero area stored: 2**-16 m^2
DEFAULT_PAGE_CAPACITY = 1024
_CACHE_OBJECTS = 4_000_000

T = TypeVar("T")


# --------------------------------------------------------------------------------------------- coding


def _area_encode(area: np.ndarray) -> np.ndarray:
    code = np.zeros(area.shape, np.uint16)
    pos = area > 0
    log = (np.log2(area[pos]) - _AREA_FLOOR_LOG2) * _AREA_STEPS
    code[pos] = np.clip(np.rint(log) + 1, 1, 65535).astype(np.uint16)
    return code


def _area_decode(code: np.ndarray) -> np.ndarray:
    area = np.exp2((code.astype(np.float64) - 1) / _AREA_STEPS + _AREA_FLOOR_LOG2)
    area[code == 0] = 0.0
    return area


_GAP_BLOCK = 32  # key gaps sharing one Rice parameter: adapts to clustered objects at 6 bits a block
_AREA_BLOCK = 256  # area residuals are not clustered: one parameter for many
_K_BITS = 6


def _bits_of(values: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Each value as ``width`` bits, most significant first, concatenated (a uint8 array of 0/1)."""
    if values.size == 0 or widths.max(initial=0) == 0:
        return np.zeros(0, np.uint8)
    top = int(widths.max())
    j = np.arange(top, dtype=np.int64)
    shift = (widths[:, None] - 1 - j).clip(min=0).astype(np.uint64)
    bits = ((values.astype(np.uint64)[:, None] >> shift) & np.uint64(1)).astype(np.uint8)
    return bits[j < widths[:, None]]


class _BitReader:
    """Fields of a packed bit stream (most significant bit first), read many at a time."""

    def __init__(self, packed: bytes, where: str) -> None:
        self.nbits = len(packed) * 8
        # eight zero bytes of padding so that every field can be read through a 64-bit window
        self.words = np.lib.stride_tricks.sliding_window_view(np.frombuffer(packed + bytes(8), np.uint8), 8)
        self.packed = packed
        self.where = where

    def read(self, pos: int, widths: np.ndarray) -> tuple[np.ndarray, int]:
        """Consecutive fields of the given widths (each at most 57 bits) from bit ``pos``; values and the end."""
        widths = widths.astype(np.int64)
        total = int(widths.sum())
        if pos + total > self.nbits:
            raise MapFormatError(f"{self.where}: page data is shorter than its counts")
        start = pos + np.cumsum(widths) - widths
        word = self.words[start >> 3].copy().view(">u8").reshape(-1).astype(np.uint64)
        head = (word << (start & 7).astype(np.uint64)) >> np.uint64(1)  # 63 bits, so a shift of 63 is legal
        values = head >> (63 - widths).astype(np.uint64)
        return np.where(widths > 0, values, np.uint64(0)), pos + total

    def zeros_from(self, pos: int) -> np.ndarray:
        """Positions (relative to ``pos``) of the zero bits from bit ``pos`` on."""
        bits = np.unpackbits(np.frombuffer(self.packed, np.uint8))
        return np.flatnonzero(bits[pos:] == 0)


def _rice_streams(sequences: list[np.ndarray], blocks: list[int]) -> list[np.ndarray]:
    """Block-adaptive Rice code of several sequences of non-negative integers, as three bit streams.

    For every block of ``blocks[i]`` consecutive values of sequence i, the k that codes it shortest;
    then the unary quotients ``v >> k`` of all values; then their k-bit remainders.  Page-wide streams
    (rather than one set per sequence) let a reader decode a whole page in a few vectorised steps.
    """
    k_fields, k_values, values_all = [], [], []
    for values, block in zip(sequences, blocks, strict=True):
        n = values.size
        if n == 0:
            continue
        values = values.astype(np.uint64)
        count = -(-n // block)
        padded = np.zeros(count * block, np.uint64)
        padded[:n] = values
        sizes = np.minimum(block, n - block * np.arange(count))
        ks = np.arange(int(values.max()).bit_length() + 1, dtype=np.uint64)
        # coded size of each block for each k: the quotients, plus a stop bit and k remainder bits a value
        cost = (padded.reshape(count, block)[:, :, None] >> ks).sum(axis=1) + sizes[:, None] * (ks + np.uint64(1))
        k_block = np.argmin(cost, axis=1)
        k_fields.append(k_block)
        k_values.append(np.repeat(k_block, sizes))
        values_all.append(values)
    if not values_all:
        return []
    values = np.concatenate(values_all)
    k = np.concatenate(k_values).astype(np.uint64)
    quotient = (values >> k).astype(np.int64)
    unary = np.ones(int(quotient.sum()) + values.size, np.uint8)
    unary[np.cumsum(quotient + 1) - 1] = 0
    k_all = np.concatenate(k_fields)
    return [_bits_of(k_all, np.full(k_all.size, _K_BITS)), unary,
            _bits_of(values & ((np.uint64(1) << k) - np.uint64(1)), k.astype(np.int64))]


def _read_rice_streams(reader: _BitReader, pos: int, lengths: list[int], blocks: list[int]) -> tuple[np.ndarray, int]:
    """Inverse of :func:`_rice_streams`: all values of all sequences, concatenated."""
    total = sum(lengths)
    if total == 0:
        return np.zeros(0, np.uint64), pos
    sizes = [np.minimum(b, n - b * np.arange(-(-n // b))) for n, b in zip(lengths, blocks, strict=True) if n]
    sizes = np.concatenate(sizes)
    k_block, pos = reader.read(pos, np.full(sizes.size, _K_BITS))
    if k_block.max() > 48:
        raise MapFormatError(f"{reader.where}: Rice parameter out of range")
    zeros = reader.zeros_from(pos)
    if zeros.size < total:
        raise MapFormatError(f"{reader.where}: page data is shorter than its counts")
    stops = zeros[:total]
    quotient = np.diff(stops, prepend=-1) - 1
    pos += int(stops[-1]) + 1
    k = np.repeat(k_block.astype(np.int64), sizes)
    remainder, pos = reader.read(pos, k)
    return (quotient.astype(np.uint64) << k.astype(np.uint64)) | remainder, pos


def _zigzag(v: np.ndarray) -> np.ndarray:
    return np.where(v >= 0, 2 * v, -2 * v - 1).astype(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.int64)
    return np.where(z % 2 == 0, z // 2, -(z + 1) // 2)


def _key_bits(ex: int, ey: int) -> int:
    return max(1, ((ex + 1) * (ey + 1) - 1).bit_length())


def _encode_page(qx: np.ndarray, qy: np.ndarray, label: np.ndarray, area: np.ndarray) -> tuple[bytes, tuple]:
    ox, oy = int(qx.min()), int(qy.min())
    ex, ey = int(qx.max()) - ox, int(qy.max()) - oy
    keys = (qy - oy).astype(np.uint64) * np.uint64(ex + 1) + (qx - ox).astype(np.uint64)
    order = np.lexsort((keys, label))
    keys, label, area_code = keys[order], label[order], _area_encode(area[order]).astype(np.int64)
    codes, starts, counts = np.unique(label, return_index=True, return_counts=True)
    runs = [slice(a, a + n) for a, n in zip(starts, counts, strict=True)]
    # Areas of one label cluster around a typical size: code them as residuals from the run's median.
    medians = np.array([int(np.median(area_code[r])) for r in runs], np.uint64)
    heads = np.column_stack([codes.astype(np.uint64), counts.astype(np.uint64), keys[starts], medians])
    widths = np.tile([8, 16, _key_bits(ex, ey), 16], codes.size)
    sequences = [np.diff(keys[r]) for r in runs] + [_zigzag(area_code[r] - m) for r, m in
                                                     zip(runs, medians.astype(np.int64), strict=True)]
    blocks = [_GAP_BLOCK] * len(runs) + [_AREA_BLOCK] * len(runs)
    bits = np.concatenate([_bits_of(heads.reshape(-1), widths), *_rice_streams(sequences, blocks)])
    payload = bytes([codes.size]) + np.packbits(bits).tobytes()
    return payload, (ox, oy, ex, ey, int(qx.size), len(payload), zlib.crc32(payload))


def _decode_page(payload: bytes, record: tuple, where: str) -> tuple[np.ndarray, ...]:
    ox, oy, ex, ey, count = record[:5]
    if not payload:
        raise MapFormatError(f"{where}: empty page")
    n_runs = payload[0]
    reader = _BitReader(payload[1:], where)
    heads, pos = reader.read(0, np.tile([8, 16, _key_bits(ex, ey), 16], n_runs))
    code, n, first, median = heads.reshape(n_runs, 4).T.astype(np.int64)
    if n_runs == 0 or n.min() < 1 or n.sum() != count:
        raise MapFormatError(f"{where}: page runs do not add up to its directory count {count}")
    lengths = [int(v) - 1 for v in n] + [int(v) for v in n]
    values, pos = _read_rice_streams(reader, pos, lengths, [_GAP_BLOCK] * n_runs + [_AREA_BLOCK] * n_runs)
    if reader.nbits - pos >= 8:
        raise MapFormatError(f"{where}: page contents do not match its directory record")
    gaps, residual = values[: count - n_runs], values[count - n_runs :]
    # Keys: each run starts at its first key and adds its gaps; one cumulative sum over the page with the
    # running total reset at each run start.
    starts = np.concatenate([[0], np.cumsum(n)[:-1]])
    steps = np.empty(count, np.uint64)
    run_of = np.repeat(np.arange(n_runs), n)
    is_start = np.zeros(count, bool)
    is_start[starts] = True
    steps[is_start] = first.astype(np.uint64)
    steps[~is_start] = gaps
    total = np.cumsum(steps, dtype=np.uint64)
    before = (total[starts] - first.astype(np.uint64))[run_of]
    key = total - before
    width = np.uint64(ex + 1)
    if key.max() >= width * np.uint64(ey + 1):
        raise MapFormatError(f"{where}: page position outside its extent")
    area_code = median[run_of] + _unzigzag(residual)
    if area_code.min() < 0 or area_code.max() > 65535:
        raise MapFormatError(f"{where}: page area code out of range")
    qx = (key % width).astype(np.int64) + ox
    qy = (key // width).astype(np.int64) + oy
    return qx, qy, code[run_of].astype(np.int32), _area_decode(area_code)


def _split_pages(qx: np.ndarray, qy: np.ndarray, capacity: int) -> list[np.ndarray]:
    """Recursive median cuts on the longer side until each page fits its capacity and extent bounds."""
    pages = []
    stack = [np.arange(qx.size)]
    while stack:
        idx = stack.pop()
        x, y = qx[idx], qy[idx]
        dx, dy = int(x.max() - x.min()), int(y.max() - y.min())
        if idx.size <= capacity and dx <= _MAX_EXTENT and dy <= _MAX_EXTENT:
            pages.append(idx)
            continue
        if dx == 0 and dy == 0:  # more than a page of objects on one spot: chop in order
            stack += [idx[:capacity], idx[capacity:]]
            continue
        axis = x if dx >= dy else y
        order = np.argsort(axis, kind="stable")
        half = idx.size // 2
        stack += [idx[order[:half]], idx[order[half:]]]
    return pages


# --------------------------------------------------------------------------------------------- writing


def _lonlat_bounds(crs: CRS, bounds: tuple[float, float, float, float]) -> list[float] | None:
    try:
        to_lonlat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        return [float(v) for v in to_lonlat.transform_bounds(*bounds, densify_pts=21)]
    except Exception:  # a CRS without a lon/lat relation (engineering CRS): no geographic bounds
        return None


def write_map(
    path: str | Path,
    objects: Objects,
    *,
    quantum: float = 0.1,
    metadata: dict[str, Any] | None = None,
    page_capacity: int = DEFAULT_PAGE_CAPACITY,
) -> None:
    """Write objects (in a projected CRS) to a map file, atomically.

    The file is written beside ``path`` under a temporary name and renamed into
    place, so a failed write leaves any earlier map of that name intact.

    Parameters
    ----------
    path : str or Path
        Destination ``.mapdb`` file.
    objects : Objects
        Centroids in projected metres; ``objects.crs`` names the CRS.
    quantum : float
        Stored resolution in metres; positions are rounded to multiples of it.
    metadata : dict, optional
        JSON-able entries kept in the header (``sources``, ``build`` options, ...).
    page_capacity : int
        Most objects in one page.

    Raises
    ------
    EmptyMapError
        If ``objects`` is empty.

    Examples
    --------
    >>> import tempfile, os
    >>> o = Objects.from_names([500000.0, 500010.0], [6e6, 6e6], ["park", "water"], crs="EPSG:32635")
    >>> p = os.path.join(tempfile.mkdtemp(), "two.mapdb")
    >>> write_map(p, o)
    >>> with open_map(p) as m:
    ...     m.label_counts
    {'park': 1, 'water': 1}
    """
    path = Path(path)
    if len(objects) == 0:
        raise EmptyMapError(f"{path}: no objects to write")
    if objects.crs is None:
        raise ValueError("objects need a CRS to be written to a map")
    if not (0 < quantum <= 1000) or not (1 <= page_capacity <= _MAX_PAGE_OBJECTS):
        raise ValueError(f"quantum must be in (0, 1000] m and page capacity in [1, {_MAX_PAGE_OBJECTS}]")
    if len(objects.labels) > 255:
        raise ValueError("a map holds at most 255 labels")
    finite = np.isfinite(objects.x) & np.isfinite(objects.y)
    if not finite.all():
        raise ValueError(f"{int((~finite).sum())} objects have non-finite coordinates")
    crs = CRS.from_user_input(objects.crs)
    qx = np.rint(objects.x / quantum).astype(np.int64)
    qy = np.rint(objects.y / quantum).astype(np.int64)
    area = np.where(np.isfinite(objects.area) & (objects.area > 0), objects.area, 0.0)

    pages = _split_pages(qx, qy, page_capacity)
    payloads, records = [], []
    for idx in pages:
        payload, record = _encode_page(qx[idx], qy[idx], objects.label[idx], area[idx])
        payloads.append(payload)
        records.append(record)
    directory = b"".join(_DIR_RECORD.pack(*r) for r in records)

    counts = np.bincount(objects.label, minlength=len(objects.labels))
    bounds = (float(qx.min() * quantum), float(qy.min() * quantum),
              float(qx.max() * quantum), float(qy.max() * quantum))
    header = {
        "format": "mapdb",
        "format_version": FORMAT_VERSION,
        "crs": crs.to_string(),
        # An authority code names the CRS exactly; WKT (about a kilobyte) only when there is none.
        "crs_wkt": None if crs.to_epsg() else crs.to_wkt(),
        "quantum": quantum,
        "area_log2_steps": _AREA_STEPS,
        "area_floor_log2": _AREA_FLOOR_LOG2,
        "count": len(objects),
        "labels": [{"name": name, "code": i, "count": int(counts[i])} for i, name in enumerate(objects.labels)],
        "bounds": list(bounds),
        "bounds_lonlat": _lonlat_bounds(crs, bounds),
        "page_capacity": page_capacity,
        "pages": len(records),
        "directory_crc32": zlib.crc32(directory),
        "software": f"mapdb {__version__}",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    for key, value in (metadata or {}).items():
        header.setdefault(key, value)
    header_json = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    header_bytes = packer.compress(header_json) + packer.flush()
    prefix = _PREFIX.pack(MAGIC, FORMAT_VERSION, 0, len(header_bytes)) + header_bytes
    prefix += struct.pack("<I", zlib.crc32(prefix))

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(prefix)
            f.write(directory)
            for payload in payloads:
                f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------------------------- reading


class MapBase:
    """Queries shared by file-backed and in-memory maps; subclasses provide ``query_bbox`` and ``all``."""

    crs: str
    quantum: float
    labels: tuple[str, ...]
    bounds: tuple[float, float, float, float]
    metadata: dict[str, Any]

    def __init__(self) -> None:
        self._derived: dict[str, Any] = {}

    @property
    def label_counts(self) -> dict[str, int]:
        return {d["name"]: d["count"] for d in self.metadata["labels"] if d["count"]}

    def __len__(self) -> int:
        return int(self.metadata["count"])

    def __enter__(self) -> MapBase:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._derived.clear()

    def cached(self, key: str, factory: Callable[[], T]) -> T:
        """A value derived from this map (an index, say), computed once per open map."""
        if key not in self._derived:
            self._derived[key] = factory()
        return self._derived[key]

    def _label_filter(self, objects: Objects, labels: Iterable[str] | None) -> Objects:
        if labels is None:
            return objects
        wanted = {self.labels.index(name) for name in labels if name in self.labels}
        return objects.take(np.isin(objects.label, list(wanted)))

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        raise NotImplementedError

    def all(self) -> Objects:
        raise NotImplementedError

    def query_radius(self, x: float, y: float, r: float, labels: Iterable[str] | None = None) -> Objects:
        """Objects within ``r`` metres of (x, y), optionally only of the named labels."""
        found = self.query_bbox(x - r, y - r, x + r, y + r, labels)
        return found.take((found.x - x) ** 2 + (found.y - y) ** 2 <= r * r)


class MetaMap(MapBase):
    """A map file opened for queries; pages are read, checked and decoded on demand.

    Use :func:`open_map` to get one.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = Path(path)
        where = str(self.path)
        with reading(where, "map file"):
            self._file = open(self.path, "rb")  # noqa: SIM115 - kept open for page reads until close()
        try:
            self._read_header(where)
        except BaseException:
            self._file.close()
            raise
        self._cache: OrderedDict[int, tuple[np.ndarray, ...]] = OrderedDict()
        self._cached_objects = 0

    def _read_header(self, where: str) -> None:
        size = os.fstat(self._file.fileno()).st_size
        self.file_size = size
        if size == 0:
            raise MapFormatError(f"{where}: empty file, not a map")
        head = self._file.read(_PREFIX.size)
        if len(head) < _PREFIX.size or not head.startswith(MAGIC):
            raise MapFormatError(f"{where}: not a mapdb map (bad magic number)")
        _, version, _flags, header_len = _PREFIX.unpack(head)
        if version > FORMAT_VERSION:
            raise MapVersionError(
                f"{where}: written by a newer map format (version {version}); "
                f"this mapdb {__version__} reads up to version {FORMAT_VERSION}"
            )
        if header_len > _MAX_HEADER or _PREFIX.size + header_len + 4 > size:
            raise MapFormatError(f"{where}: truncated map file (header runs past the end)")
        header_bytes = self._file.read(header_len)
        (crc,) = struct.unpack("<I", self._file.read(4))
        if zlib.crc32(head + header_bytes) != crc:
            raise MapFormatError(f"{where}: header checksum mismatch (file is corrupt)")
        try:
            unpacker = zlib.decompressobj(-15)
            header_json = unpacker.decompress(header_bytes, _MAX_HEADER)
            if unpacker.unconsumed_tail:
                raise MapFormatError(f"{where}: header inflates past {_MAX_HEADER} bytes")
            header = json.loads(header_json.decode("utf-8"))
            n_pages = int(header["pages"])
            self.quantum = float(header["quantum"])
            self.crs = str(header.get("crs_wkt") or header["crs"])
            self.labels = tuple(str(d["name"]) for d in header["labels"])
            self.bounds = tuple(float(v) for v in header["bounds"])
        except (ValueError, KeyError, TypeError, zlib.error):
            raise MapFormatError(f"{where}: header is not valid map metadata") from None
        dir_start = _PREFIX.size + header_len + 4
        dir_len = n_pages * _DIR_RECORD.size
        if n_pages < 0 or dir_start + dir_len > size:
            raise MapFormatError(f"{where}: truncated map file (page directory runs past the end)")
        directory = self._file.read(dir_len)
        if zlib.crc32(directory) != header.get("directory_crc32"):
            raise MapFormatError(f"{where}: page directory checksum mismatch (file is corrupt)")
        records = [_DIR_RECORD.unpack_from(directory, i * _DIR_RECORD.size) for i in range(n_pages)]
        lengths = np.array([r[5] for r in records], np.int64)
        self._offsets = dir_start + dir_len + np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        end = dir_start + dir_len + int(lengths.sum())
        if end > size:
            raise MapFormatError(f"{where}: truncated map file ({size} bytes, pages need {end})")
        if end < size:
            raise MapFormatError(f"{where}: {size - end} unexpected bytes after the last page")
        if any(r[4] > _MAX_PAGE_OBJECTS or r[2] > _MAX_EXTENT or r[3] > _MAX_EXTENT for r in records):
            raise MapFormatError(f"{where}: page directory holds out-of-range values")
        self._records = records
        self.metadata = header
        q = self.quantum
        boxes = [(r[0] * q, r[1] * q, (r[0] + r[2]) * q, (r[1] + r[3]) * q) for r in records]
        self._tree = rtree_index.Index((i, box, None) for i, box in enumerate(boxes)) if boxes else None

    @property
    def page_count(self) -> int:
        return len(self._records)

    def close(self) -> None:
        super().close()
        self._cache.clear()
        self._file.close()

    def _page(self, i: int) -> tuple[np.ndarray, ...]:
        hit = self._cache.get(i)
        if hit is not None:
            self._cache.move_to_end(i)
            return hit
        record = self._records[i]
        where = f"{self.path} page {i}"
        payload = os.pread(self._file.fileno(), record[5], int(self._offsets[i]))
        if len(payload) != record[5]:
            raise MapFormatError(f"{where}: truncated")
        if zlib.crc32(payload) != record[6]:
            raise MapFormatError(f"{where}: checksum mismatch (file is corrupt)")
        qx, qy, label, area = _decode_page(payload, record, where)
        if label.size and label.max() >= len(self.labels):
            raise MapFormatError(f"{where}: label code outside the label table")
        page = (qx * self.quantum, qy * self.quantum, label, area)
        self._cache[i] = page
        self._cached_objects += label.size
        while self._cached_objects > _CACHE_OBJECTS and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cached_objects -= old[2].size
        return page

    def _objects(self, pages: Iterable[int]) -> Objects:
        parts = [self._page(i) for i in pages]
        if not parts:
            return Objects.empty(self.labels, self.crs)
        return Objects(*(np.concatenate(p) for p in zip(*parts, strict=True)), self.labels, self.crs)

    def verify(self) -> None:
        """Read and check every page; raises :class:`MapFormatError` at the first bad one."""
        for i in range(self.page_count):
            self._page(i)

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        """Objects inside the box (projected metres, edges included)."""
        if self._tree is None:
            return Objects.empty(self.labels, self.crs)
        hits = sorted(self._tree.intersection((minx, miny, maxx, maxy)))
        found = self._objects(hits)
        inside = (found.x >= minx) & (found.x <= maxx) & (found.y >= miny) & (found.y <= maxy)
        return self._label_filter(found.take(inside), labels)

    def all(self) -> Objects:
        return self._objects(range(self.page_count))


class MemoryMap(MapBase):
    """The :class:`MetaMap` interface over objects held in memory (simulations, tests).

    Positions are rounded to the quantum as a file would store them.

    Examples
    --------
    >>> m = MemoryMap(Objects.from_names([0.0, 100.0], [0.0, 0.0], ["park", "park"], crs="EPSG:3857"))
    >>> len(m.query_radius(0.0, 0.0, 10.0))
    1
    >>> len(m.query_bbox(500.0, 500.0, 600.0, 600.0))
    0
    """

    def __init__(self, objects: Objects, quantum: float = 0.1, metadata: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.path = None
        self.quantum = quantum
        self.crs = objects.crs or ""
        self.labels = objects.labels
        x = np.rint(objects.x / quantum) * quantum
        y = np.rint(objects.y / quantum) * quantum
        self._objects = Objects(x, y, objects.label, objects.area, objects.labels, objects.crs)
        self.bounds = (float(x.min()), float(y.min()), float(x.max()), float(y.max())) if len(objects) else (
            0.0, 0.0, 0.0, 0.0)
        counts = np.bincount(objects.label, minlength=len(self.labels))
        self.metadata = {"count": len(objects), "crs": self.crs, "quantum": quantum, "bounds": list(self.bounds),
                         "labels": [{"name": n, "code": i, "count": int(counts[i])}
                                    for i, n in enumerate(self.labels)], **(metadata or {})}

    def query_bbox(self, minx: float, miny: float, maxx: float, maxy: float,
                   labels: Iterable[str] | None = None) -> Objects:
        o = self._objects
        inside = (o.x >= minx) & (o.x <= maxx) & (o.y >= miny) & (o.y <= maxy)
        return self._label_filter(o.take(inside), labels)

    def all(self) -> Objects:
        return self._objects


def open_map(path: str | Path) -> MetaMap:
    """Open a map file for queries (also a context manager).

    Raises
    ------
    MapdbIOError
        If the file is missing or unreadable.
    MapFormatError
        If it is not a map, is truncated or fails a checksum.
    MapVersionError
        If a newer format version wrote it.
    """
    return MetaMap(path)
