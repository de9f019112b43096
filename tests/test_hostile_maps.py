"""Crafted maps with valid checksums: every reading command ends in one line, never in a traceback.

A generator takes a genuine map apart (or builds one from nothing, with a page encoder written here from
``docs/format.md`` and independent of ``mapdb.mapfile``), breaks one rule of the format, and puts the file
back together with every checksum recomputed: the header's CRC-32, the directory's CRC-32 in the header,
and each page's CRC-32 in its directory record.  So nothing here is caught by a checksum; each kind must
be caught by a check of meaning.

For every kind, every command that reads a map is run in-process (``mapdb info``, ``info --json``,
``export -o x.geojson``, ``query MAP images.jsonl``, ``simulate MAP -o x.jsonl --n 3``, ``evaluate MAP
images.jsonl``), and each must exit with status 1 and exactly one line on stderr, ``mapdb: error: MAP: ...``,
naming the file and the broken rule; print nothing on stdout; leave no file behind.  The Python API
(``open_map`` then ``query_bbox`` and ``all``) must raise :class:`MapFormatError` and nothing else.

A few kinds are *harmless*: they change the file but leave it a valid map with the same objects (an unknown
header key, optional fields null, another deflate level, a CRS given as WKT instead of a code, pages
re-encoded by this module's encoder).  For those every command must succeed and say what it says for the
genuine map.

The "long" cases (big piles, maximal-density maps, 65,535-object hostile pages) are timed in
``benchmarks/hostile_maps.py``, which uses this generator.
"""

from __future__ import annotations

import copy
import json
import os
import re
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mapdb import MapdbIOError, MapFormatError, Objects
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.simulation.simulate import simulate_images

MAGIC = b"\x89MAPDB\r\n"
DIR = np.dtype([("ox", "<i8"), ("oy", "<i8"), ("ex", "<u4"), ("ey", "<u4"), ("count", "<u4"), ("length", "<u4"),
                ("crc", "<u4")])
LABELS = ("building", "park", "water")
CRS = "EPSG:32631"
X0, Y0 = 380000.0, 4700000.0


# ------------------------------------------------------------------------------------------- the generator


@dataclass
class Parts:
    """A map file taken apart; :meth:`to_bytes` puts it together with every checksum recomputed."""

    header: dict
    table: np.ndarray
    payloads: list[bytes]
    version: int = 1
    flags: int = 0
    header_text: bytes | None = None  # JSON text to deflate instead of ``header``
    header_deflated: bytes | None = None  # raw header bytes instead of deflating the text
    header_len: int | None = None  # the prefix's header length field, if not the real one
    trailing: bytes = b""
    fix_records: bool = True  # page lengths and CRCs from the payloads
    keep: set[str] = field(default_factory=set)  # header fields a kind set on purpose ("pages", ...)

    def set(self, key: str, value: object) -> Parts:
        self.header[key] = value
        self.keep.add(key)
        return self

    def drop(self, key: str) -> Parts:
        self.header.pop(key, None)
        self.keep.add(key)
        return self

    def to_bytes(self) -> bytes:
        table = self.table.copy()
        if self.fix_records:
            table["length"] = [len(p) for p in self.payloads]
            table["crc"] = [zlib.crc32(p) for p in self.payloads]
        directory = table.tobytes()
        header = dict(self.header)
        if "pages" not in self.keep:
            header["pages"] = len(table)
        if "directory_crc32" not in self.keep:
            header["directory_crc32"] = zlib.crc32(directory)
        text = self.header_text if self.header_text is not None else json.dumps(header).encode()
        deflated = self.header_deflated if self.header_deflated is not None else deflate(text)
        length = len(deflated) if self.header_len is None else self.header_len
        prefix = struct.pack("<8sHHI", MAGIC, self.version, self.flags, length) + deflated
        return prefix + struct.pack("<I", zlib.crc32(prefix)) + directory + b"".join(self.payloads) + self.trailing


def deflate(text: bytes, level: int = 9) -> bytes:
    packer = zlib.compressobj(level, zlib.DEFLATED, -15)
    return packer.compress(text) + packer.flush()


def take_apart(data: bytes) -> Parts:
    """The parts of a genuine map file."""
    _, version, flags, length = struct.unpack_from("<8sHHI", data)
    header = json.loads(zlib.decompress(data[16 : 16 + length], -15))
    start = 16 + length + 4
    table = np.frombuffer(data[start : start + DIR.itemsize * header["pages"]], DIR).copy()
    offsets = start + DIR.itemsize * len(table) + np.concatenate([[0], np.cumsum(table["length"].astype(int))])
    payloads = [data[a:b] for a, b in zip(offsets[:-1], offsets[1:])]
    return Parts(header, table, payloads, version, flags)


class Bits:
    """Fields packed most significant bit first (``docs/format.md``, "Page")."""

    def __init__(self) -> None:
        self.bits: list[int] = []

    def put(self, value: int, width: int) -> None:
        self.bits.extend((value >> (width - 1 - i)) & 1 for i in range(width))

    def to_bytes(self) -> bytes:
        return np.packbits(np.array(self.bits, np.uint8)).tobytes()


def zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def key_bits(ex: int, ey: int) -> int:
    return max(1, ((ex + 1) * (ey + 1) - 1).bit_length())


def best_k(values: list[int]) -> int:
    top = max(values).bit_length() + 1
    return min(range(top), key=lambda k: sum(v >> k for v in values) + len(values) * (k + 1))


@dataclass
class Run:
    """One label's objects in a page: sorted keys as stored (duplicates allowed here), area codes."""

    code: int
    keys: list[int]
    areas: list[int] | None = None  # area codes (default 150, about 50 m^2)
    median: int | None = None
    n: int | None = None  # the run length field, if not len(keys)


def encode_page(runs: list[Run], ex: int, ey: int, *, k: int | None = None, n_runs: int | None = None,
                pad: int = 0, extra: bytes = b"") -> bytes:
    """A page's bytes from its runs; ``k`` forces every Rice parameter, ``pad`` sets the padding bits."""
    b = Bits()
    areas = [run.areas if run.areas is not None else [150] * len(run.keys) for run in runs]
    medians = [run.median if run.median is not None else int(np.median(a)) for run, a in zip(runs, areas)]
    for run, median in zip(runs, medians):
        b.put(run.code, 8)
        b.put(len(run.keys) if run.n is None else run.n, 16)
        b.put(run.keys[0], key_bits(ex, ey))
        b.put(median, 16)
    sequences = [[run.keys[i + 1] - run.keys[i] for i in range(len(run.keys) - 1)] for run in runs]
    sequences += [[zigzag(x - m) for x in a] for a, m in zip(areas, medians)]
    blocks = [32] * len(runs) + [256] * len(runs)
    ks = []
    for values, block in zip(sequences, blocks):
        for start in range(0, len(values), block):
            chunk = values[start : start + block]
            kk = best_k(chunk) if k is None else k
            b.put(kk, 6)
            ks.append((chunk, kk))
    for chunk, kk in ks:
        for v in chunk:
            b.bits.extend([1] * (v >> kk) + [0])
    for chunk, kk in ks:
        for v in chunk:
            b.put(v & ((1 << kk) - 1), kk)
    if pad:
        b.bits.extend([1] * pad)  # nonzero padding (must stay within the last byte to be "padding")
    return bytes([len(runs) if n_runs is None else n_runs]) + b.to_bytes() + extra


@dataclass
class Page:
    """A page for :func:`handmade`: its origin and extent in quanta, its runs, and encoder options."""

    ox: int
    oy: int
    ex: int
    ey: int
    runs: list[Run]
    options: dict = field(default_factory=dict)
    payload: bytes | None = None  # bytes to use instead of encoding the runs
    count: int | None = None  # the directory count, if not the runs' total


def grid_run(code: int, points: list[tuple[int, int]], ex: int) -> Run:
    return Run(code, sorted(qy * (ex + 1) + qx for qx, qy in points))


def handmade(pages: list[Page], quantum: float = 0.1, labels: tuple[str, ...] = LABELS) -> Parts:
    """A map built from nothing: header and directory derived from the pages as a genuine writer would."""
    rows, payloads = [], []
    per_label = np.zeros(len(labels), int)
    for p in pages:
        payloads.append(p.payload if p.payload is not None else encode_page(p.runs, p.ex, p.ey, **p.options))
        n = sum(len(r.keys) for r in p.runs) if p.count is None else p.count
        for r in p.runs:
            per_label[min(r.code, len(labels) - 1)] += len(r.keys)
        per_label[0] += n - sum(len(r.keys) for r in p.runs)  # a count given on purpose: the header agrees
        rows.append((p.ox, p.oy, p.ex, p.ey, n, 0, 0))
    table = np.array(rows, DIR)
    bounds = [float(table["ox"].min() * quantum), float(table["oy"].min() * quantum),
              float((table["ox"] + table["ex"].astype(np.int64)).max() * quantum),
              float((table["oy"] + table["ey"].astype(np.int64)).max() * quantum)]
    header = {
        "format": "mapdb", "format_version": 1, "crs": CRS, "crs_wkt": None, "quantum": quantum,
        "area_log2_steps": 8, "area_floor_log2": -16, "count": int(per_label.sum()),
        "labels": [{"name": name, "code": i, "count": int(per_label[i])} for i, name in enumerate(labels)],
        "bounds": bounds, "bounds_lonlat": None, "page_capacity": 1024, "pages": len(pages),
        "directory_crc32": 0, "software": "test_hostile_maps", "created": "2024-01-01T00:00:00+00:00",
    }
    return Parts(header, table, payloads)


# Two small pages, built by hand: page 0 holds buildings and water in a 5 x 3 m box, page 1 parks in another.
OX, OY = int(X0 / 0.1), int(Y0 / 0.1)


def base_pages() -> list[Page]:
    ex, ey = 49, 29
    return [
        Page(OX, OY, ex, ey, [grid_run(0, [(0, 0), (10, 5), (20, 7), (49, 29)], ex),
                              grid_run(2, [(3, 3), (4, 4), (5, 5)], ex)]),
        Page(OX + 1000, OY, 9, 9, [grid_run(1, [(0, 0), (9, 9), (5, 2)], 9)]),
    ]


def replace_page0(runs: list[Run] | None = None, ex: int = 49, ey: int = 29, count: int | None = None,
                  **options: object) -> Parts:
    pages = base_pages()
    pages[0] = Page(OX, OY, ex, ey, pages[0].runs if runs is None else runs, dict(options), count=count)
    return handmade(pages)


# ------------------------------------------------------------------------------------------------ kinds
# Each kind: a function of the genuine map's parts returning the hostile file's bytes, and what the one-line
# error must say (a regular expression), or None for a harmless kind.


def genuine_kind(edit: Callable[[Parts], object]) -> Callable[[Parts], bytes]:
    def make(genuine: Parts) -> bytes:
        parts = copy.deepcopy(genuine)
        result = edit(parts)
        return result if isinstance(result, bytes) else parts.to_bytes()

    return make


def handmade_kind(build: Callable[[], Parts | bytes]) -> Callable[[Parts], bytes]:
    def make(genuine: Parts) -> bytes:
        result = build()
        return result if isinstance(result, bytes) else result.to_bytes()

    return make


def nested(depth: int) -> bytes:
    return b'{"build": ' + b"[" * depth + b"]" * depth + b"}"


def with_header_text(parts: Parts, text: bytes) -> None:
    parts.header_text = text


def label_entry(i: int, **change: object) -> Callable[[Parts], None]:
    def edit(parts: Parts) -> None:
        parts.header["labels"][i].update(change)

    return edit


def one_label_miscounted(parts: Parts) -> None:
    """One object moved from label 0's count to label 1's: the total still adds up."""
    labels = parts.header["labels"]
    labels[0]["count"] -= 1
    labels[1]["count"] += 1


def page_record(i: int, **change: object) -> Callable[[Parts], None]:
    def edit(parts: Parts) -> None:
        for key, value in change.items():
            parts.table[key][i] = value

    return edit


def true_bounds(parts: Parts) -> None:
    """Header bounds made the box of the (moved) pages again, so that only the intended rule is broken."""
    t, q = parts.table, parts.header["quantum"]
    ex, ey = t["ex"].astype(np.int64), t["ey"].astype(np.int64)
    parts.header["bounds"] = [float(t["ox"].min() * q), float(t["oy"].min() * q),
                              float((t["ox"] + ex).max() * q), float((t["oy"] + ey).max() * q)]


def piled_pages(parts: Parts) -> None:
    """Every page moved onto page 0's origin: piles of pages on one spot."""
    for key in ("ox", "oy"):
        parts.table[key][:] = parts.table[key][0]
    true_bounds(parts)


def overlapping_pages(parts: Parts) -> None:
    """Page 1 moved so that its box overlaps page 0's by one quantum."""
    t = parts.table
    t["ox"][1] = t["ox"][0] + int(t["ex"][0])
    t["oy"][1] = t["oy"][0]
    true_bounds(parts)


def long_page(parts: Parts) -> None:
    parts.payloads[0] += bytes((1 << 20) + 1)


def inflate_bomb(parts: Parts) -> None:
    # 40 MB of JSON whitespace deflates to about 40 KB: far past the limit of 256 KiB + 16 x the deflated size
    parts.header_deflated = deflate(json.dumps(parts.header).encode()[:-1] + b" " * 40_000_000 + b"}")


def surrogate(parts: Parts) -> None:
    parts.header_text = json.dumps(parts.header).encode().replace(b'"building"', b'"\\ud800"', 1)


def duplicate_key(parts: Parts) -> None:
    parts.header_text = json.dumps(parts.header).encode()[:-1] + b', "count": 1}'


def nan_quantum(parts: Parts) -> None:
    parts.header_text = re.sub(rb'"quantum": [0-9.e-]+', b'"quantum": NaN', json.dumps(parts.header).encode())


def raw_number(key: str, literal: bytes) -> Callable[[Parts], None]:
    def edit(parts: Parts) -> None:
        parts.header[key] = "@@"
        parts.keep.add(key)
        parts.header_text = json.dumps(parts.header).encode().replace(b'"@@"', literal)

    return edit


def crs_wkt(text: str) -> Callable[[Parts], None]:
    def edit(parts: Parts) -> None:
        parts.header["crs_wkt"] = text

    return edit


def as_wkt(parts: Parts) -> None:
    import pyproj

    parts.header["crs_wkt"] = pyproj.CRS.from_user_input(parts.header["crs"]).to_wkt()


WKT1_EXTENSION = ('PROJCS["x",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
                  'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Mercator_1SP"],'
                  'UNIT["metre",1],EXTENSION["PROJ4","+proj=merc +init=/dev/zero"]]')


def trailing_bytes(parts: Parts) -> None:
    parts.trailing = b"\0" * 7


def truncated_page(parts: Parts) -> bytes:
    return parts.to_bytes()[:-3]


def flipped_version(parts: Parts) -> bytes:
    data = bytearray(parts.to_bytes())
    data[8] ^= 0x02  # version 1 -> 3, the header CRC not recomputed: damage, not a newer format
    return bytes(data)


def header_not_deflate(parts: Parts) -> None:
    parts.header_deflated = b"\xff" * 64


def deflate_trailing(parts: Parts) -> None:
    parts.header_deflated = deflate(json.dumps(parts.header).encode()) + b"junk"


def deflate_cut(parts: Parts) -> None:
    parts.header_deflated = deflate(json.dumps(parts.header).encode())[:-6]


def deflate_level_1(parts: Parts) -> None:
    parts.header_deflated = deflate(json.dumps(parts.header).encode(), level=1)


def optional_nulls(parts: Parts) -> None:
    for key in ("software", "created", "bounds_lonlat", "sources", "build"):
        parts.header[key] = None
    parts.header.pop("page_capacity")
    parts.header.pop("merged_duplicates")


def pages_off_by_one(parts: Parts) -> None:
    """One more page than there are records, with a directory CRC that matches the bytes read for them."""
    parts.set("pages", len(parts.table) + 1)
    parts.fix_records = True
    table = parts.table.copy()
    table["length"] = [len(p) for p in parts.payloads]
    table["crc"] = [zlib.crc32(p) for p in parts.payloads]
    directory = table.tobytes() + b"".join(parts.payloads)[: DIR.itemsize]
    parts.set("directory_crc32", zlib.crc32(directory))


def dense_page() -> Parts:
    """1,000 objects of one label in a 4 x 3 m box: far more than one per square metre."""
    ex, ey = 39, 29  # 1,200 positions of 0.1 m
    keys = list(range(1000)) + [(ey + 1) * (ex + 1) - 1]
    return replace_page0([Run(0, keys)], ex, ey)


def pile_page() -> Parts:
    """200 buildings on one spot (duplicate keys); the box is one position, so the density rule allows 255."""
    return replace_page0([Run(0, [0] * 200)], 0, 0)


def out_of_extent() -> Parts:
    runs = base_pages()[0].runs
    runs[1].keys[-1] = 50 * 30  # one past the last position of a 50 x 30 box
    return replace_page0(runs)


def not_filling() -> Parts:
    """The directory box is one quantum wider than the objects: the R-tree and bounds would lie."""
    runs = [grid_run(0, [(0, 0), (10, 5), (20, 7), (48, 29)], 49), grid_run(2, [(3, 3), (4, 4), (5, 5)], 49)]
    return replace_page0(runs)


def duplicate_keys() -> Parts:
    runs = base_pages()[0].runs
    runs[1].keys[1] = runs[1].keys[0]
    return replace_page0(runs)


def runs_out_of_order() -> Parts:
    runs = base_pages()[0].runs
    return replace_page0(runs[::-1])


def label_outside_table() -> Parts:
    runs = base_pages()[0].runs
    runs[1].code = 3  # the map has labels 0..2
    return replace_page0(runs)


def run_counts_off() -> Parts:
    runs = base_pages()[0].runs
    runs[0].n = len(runs[0].keys) + 1
    return replace_page0(runs)


def area_out_of_range() -> Parts:
    runs = base_pages()[0].runs
    runs[0].areas, runs[0].median = [65535, 65535, 65535, 65535 + 40], 65535
    return replace_page0(runs)


def area_beyond_float64() -> Parts:
    """Area code 9000: 2**1108.9 square metres, infinite as a float64."""
    runs = base_pages()[0].runs
    runs[0].areas, runs[0].median = [9000] * 4, 9000
    return replace_page0(runs)


def rice_value_overflow() -> Parts:
    """A key gap of 2**48 + 5 in Rice code with k = 48: it would wrap round in 64-bit arithmetic."""
    return replace_page0([Run(0, [0, (1 << 48) + 5])], 49, 29, k=48)


def pages_with(build: Callable[[list[Page]], object]) -> Callable[[], Parts]:
    def make() -> Parts:
        pages = base_pages()
        build(pages)
        return handmade(pages)

    return make


def set_payload(i: int, payload: bytes) -> Callable[[list[Page]], None]:
    def edit(pages: list[Page]) -> None:
        pages[i].payload = payload

    return edit


def page0_options(**options: object) -> Callable[[list[Page]], None]:
    def edit(pages: list[Page]) -> None:
        pages[0].options.update(options)

    return edit


def page0_count(count: int) -> Callable[[list[Page]], None]:
    def edit(pages: list[Page]) -> None:
        pages[0].count = count

    return edit


def rice_k(value: int) -> Callable[[], Parts]:
    """Page 0 a single object whose Rice parameter is ``value`` (above 48 is out of range)."""
    return lambda: replace_page0([Run(0, [0])], 0, 0, k=value)


def many_labels(n: int) -> Callable[[Parts], None]:
    def edit(parts: Parts) -> None:
        extra = [{"name": f"l{i}", "code": i, "count": 0} for i in range(len(parts.header["labels"]), n)]
        parts.header["labels"] += extra

    return edit


REQUIRED = ("format", "format_version", "crs", "quantum", "count", "labels", "bounds", "pages", "directory_crc32",
            "area_log2_steps", "area_floor_log2")

KINDS: dict[str, tuple[Callable[[Parts], bytes], str | None]] = {
    # --- the prefix and the frame around the header
    "version_0": (genuine_kind(lambda p: setattr(p, "version", 0)), r"not a valid map \(format version 0\)"),
    "version_3": (genuine_kind(lambda p: setattr(p, "version", 3)), r"newer map format \(version 3\)"),
    "version_2_header_1": (genuine_kind(lambda p: setattr(p, "version", 2)), r"'format_version' must be 2"),
    "version_65535": (genuine_kind(lambda p: setattr(p, "version", 65535)), r"not a valid map \(format version 65535"),
    "version_byte_flipped": (genuine_kind(flipped_version), r"header checksum mismatch"),
    "flags_set": (genuine_kind(lambda p: setattr(p, "flags", 1)), r"not a valid map \(flags 0x0001"),
    "header_length_past_end": (genuine_kind(lambda p: setattr(p, "header_len", 10_000_000)), r"truncated"),
    "header_length_4gib": (genuine_kind(lambda p: setattr(p, "header_len", 2**32 - 1)), r"truncated"),
    "header_not_deflate": (genuine_kind(header_not_deflate), r"not valid DEFLATE"),
    "header_deflate_trailing": (genuine_kind(deflate_trailing), r"DEFLATE stream does not fill"),
    "header_deflate_cut": (genuine_kind(deflate_cut), r"DEFLATE stream does not fill|not valid DEFLATE"),
    "inflate_bomb": (genuine_kind(inflate_bomb), r"header inflates past \d+ bytes"),
    # --- the header's JSON
    "header_not_utf8": (genuine_kind(lambda p: with_header_text(p, b'{"a": "\xff"}')), r"not valid JSON"),
    "header_not_json": (genuine_kind(lambda p: with_header_text(p, b"{pages: 3")), r"not valid JSON"),
    "header_empty": (genuine_kind(lambda p: with_header_text(p, b"")), r"not valid JSON"),
    "header_is_a_list": (genuine_kind(lambda p: with_header_text(p, b"[1, 2, 3]")), r"not a JSON object"),
    "nesting_200000": (genuine_kind(lambda p: with_header_text(p, nested(200_000))),
                       r"nests deeper than 32|inflates past"),
    "nesting_100000": (genuine_kind(lambda p: with_header_text(p, nested(100_000))), r"nests deeper than 32"),
    "nesting_40": (genuine_kind(lambda p: with_header_text(p, nested(40))), r"nests deeper than 32"),
    "nan_literal": (genuine_kind(nan_quantum), r"not valid JSON \(NaN is not a finite number"),
    "duplicate_key": (genuine_kind(duplicate_key), r"not valid JSON \(an object repeats a key"),
    "lone_surrogate": (genuine_kind(surrogate), r"not valid Unicode"),
    "integer_30_digits": (genuine_kind(raw_number("pages", b"1" * 30)), r"not valid JSON \(an integer of 30"),
    # --- types and ranges of every field
    "pages_1e400": (genuine_kind(raw_number("pages", b"1e400")), r"not valid JSON \(1e400 is not a finite"),
    "pages_string": (genuine_kind(lambda p: p.set("pages", "3")), r"'pages' must be a positive integer"),
    "pages_true": (genuine_kind(lambda p: p.set("pages", True)), r"'pages' must be a positive integer"),
    "pages_float": (genuine_kind(lambda p: p.set("pages", 3.0)), r"'pages' must be a positive integer"),
    "pages_negative": (genuine_kind(lambda p: p.set("pages", -1)), r"'pages' must be a positive integer"),
    "pages_zero": (genuine_kind(lambda p: p.set("pages", 0)), r"'pages' must be a positive integer"),
    "pages_10e12": (genuine_kind(lambda p: p.set("pages", 10**12)), r"page directory runs past the end"),
    "pages_off_by_one": (genuine_kind(pages_off_by_one), r"page|truncated|bytes"),
    "count_plus_one": (genuine_kind(lambda p: p.header.update(count=p.header["count"] + 1)), r"do not add up"),
    "count_string": (genuine_kind(lambda p: p.set("count", "40")), r"'count' must be a positive integer"),
    "count_zero": (genuine_kind(lambda p: p.set("count", 0)), r"'count' must be a positive integer"),
    "count_all_consistent_but_false": (genuine_kind(lambda p: [p.header.update(count=p.header["count"] + 1),
                                                               p.header["labels"][0].update(
                                                                   count=p.header["labels"][0]["count"] + 1)]),
                                       r"pages hold \d+ objects, the header counts"),
    "label_counts_moved": (genuine_kind(one_label_miscounted), r"counts per label disagree with the pages"),
    "quantum_zero": (genuine_kind(lambda p: p.set("quantum", 0)), r"'quantum' must be a number in \(0, 1000\]"),
    "quantum_negative": (genuine_kind(lambda p: p.set("quantum", -0.1)), r"'quantum' must be"),
    "quantum_2000": (genuine_kind(lambda p: p.set("quantum", 2000.0)), r"'quantum' must be"),
    "quantum_1e400": (genuine_kind(raw_number("quantum", b"1e400")), r"not a finite number"),
    "quantum_string": (genuine_kind(lambda p: p.set("quantum", "0.1")), r"'quantum' must be"),
    "quantum_doubled": (genuine_kind(lambda p: p.set("quantum", 0.2)), r"header bounds .* are not the pages' box"),
    "bounds_three": (genuine_kind(lambda p: p.set("bounds", p.header["bounds"][:3])), r"'bounds' must be"),
    "bounds_min_above_max": (genuine_kind(lambda p: p.set("bounds", [1.0, 0.0, 0.0, 1.0])), r"'bounds' must be"),
    "bounds_strings": (genuine_kind(lambda p: p.set("bounds", ["0", "0", "1", "1"])), r"'bounds' must be"),
    "bounds_1e400": (genuine_kind(raw_number("bounds", b"[0, 0, 1e400, 1]")), r"not a finite number"),
    "bounds_too_wide": (genuine_kind(lambda p: p.set("bounds", [b - 1000.0 if i < 2 else b + 1000.0 for i, b in
                                                                enumerate(p.header["bounds"])])),
                        r"header bounds .* are not the pages' box"),
    "bounds_lonlat_text": (genuine_kind(lambda p: p.set("bounds_lonlat", "everywhere")), r"'bounds_lonlat' must"),
    "crs_unknown_code": (genuine_kind(lambda p: p.set("crs", "EPSG:999999")), r"CRS is not one pyproj knows"),
    "crs_garbage": (genuine_kind(lambda p: p.set("crs", "not a crs")), r"'crs' must be AUTHORITY:CODE"),
    "crs_proj_string": (genuine_kind(lambda p: p.set("crs", "+proj=utm +zone=31 +init=/dev/zero")),
                        r"'crs' must be AUTHORITY:CODE"),
    "crs_geographic": (genuine_kind(lambda p: p.set("crs", "EPSG:4326")), r"is not a projected CRS"),
    "crs_number": (genuine_kind(lambda p: p.set("crs", 32631)), r"'crs' must be a CRS name"),
    "crs_empty": (genuine_kind(lambda p: p.set("crs", "")), r"'crs' must be a CRS name"),
    "crs_wkt_garbage": (genuine_kind(crs_wkt("PROJCRS[garbage")), r"CRS is not one pyproj knows"),
    "crs_wkt_extension": (genuine_kind(crs_wkt(WKT1_EXTENSION)), r"'crs_wkt' is not a self-contained WKT"),
    "crs_wkt_number": (genuine_kind(crs_wkt(7)), r"'crs_wkt' must be null or WKT"),
    "labels_not_a_list": (genuine_kind(lambda p: p.set("labels", {"building": 1})), r"'labels' must be a list"),
    "labels_empty": (genuine_kind(lambda p: p.set("labels", [])), r"'labels' must be a list of 1 to 255"),
    "labels_256": (genuine_kind(many_labels(256)), r"'labels' must be a list of 1 to 255"),
    "label_name_repeated": (genuine_kind(label_entry(1, name="building")), r"names a label twice"),
    "label_name_number": (genuine_kind(label_entry(1, name=5)), r"header label 1 must be"),
    "label_name_newline": (genuine_kind(label_entry(1, name="par\nk")), r"header label 1 must be"),
    "label_name_empty": (genuine_kind(label_entry(0, name="")), r"header label 0 must be"),
    "label_code_shifted": (genuine_kind(label_entry(0, code=1)), r"header label 0 must be"),
    "label_count_negative": (genuine_kind(label_entry(2, count=-1)), r"header label 2 must be"),
    "label_not_object": (genuine_kind(lambda p: p.header["labels"].__setitem__(0, "building")),
                         r"header label 0 must be"),
    "format_wrong": (genuine_kind(lambda p: p.set("format", "mapdc")), r"'format' must be \"mapdb\""),
    "format_version_2_in_header": (genuine_kind(lambda p: p.set("format_version", 2)), r"'format_version' must be 1"),
    "area_steps_9": (genuine_kind(lambda p: p.set("area_log2_steps", 9)), r"'area_log2_steps' must be 8"),
    "area_floor_string": (genuine_kind(lambda p: p.set("area_floor_log2", "-16")), r"'area_floor_log2' must be"),
    "directory_crc_string": (genuine_kind(lambda p: p.set("directory_crc32", "1234")),
                             r"'directory_crc32' must be a CRC-32"),
    "directory_crc_wrong": (genuine_kind(lambda p: p.set("directory_crc32", 1234)), r"directory checksum mismatch"),
    "page_capacity_0": (genuine_kind(lambda p: p.set("page_capacity", 0)), r"'page_capacity' must be"),
    "sources_numbers": (genuine_kind(lambda p: p.set("sources", [1, 2])), r"'sources' must be a list of"),
    "sources_entry_partial": (genuine_kind(lambda p: p.set("sources", [{"name": "x"}])), r"'sources' must be"),
    "build_a_list": (genuine_kind(lambda p: p.set("build", [])), r"'build' must be an object"),
    "software_number": (genuine_kind(lambda p: p.set("software", 3)), r"'software' must be null or a string"),
    "merged_negative": (genuine_kind(lambda p: p.set("merged_duplicates", -1)), r"'merged_duplicates' must be"),
    **{f"missing_{key}": (genuine_kind(lambda p, key=key: p.drop(key)), f"header lacks the field '{key}'")
       for key in REQUIRED},
    # --- the page directory
    "dir_count_zero": (genuine_kind(page_record(0, count=0)), r"page 0 holds 0 objects"),
    "dir_count_65536": (genuine_kind(page_record(0, count=65536)), r"page 0 holds 65536 objects"),
    "dir_count_4g": (genuine_kind(page_record(0, count=2**32 - 1)), r"page 0 holds 4294967295 objects"),
    "dir_count_above_bytes": (genuine_kind(page_record(1, count=65535)), r"page 1 has \d+ bytes, too few for 65535"),
    "dir_extent_2_24": (genuine_kind(page_record(0, ex=1 << 24)), r"page 0 extends 16777216 quanta"),
    "dir_origin_far": (genuine_kind(page_record(0, ox=1 << 60)), r"page 0 lies beyond"),
    "dir_origin_int64_min": (genuine_kind(page_record(0, oy=-(1 << 63))), r"page 0 lies beyond"),
    "dir_box_outside_bounds": (genuine_kind(page_record(0, ox=-(10**9))), r"header bounds .* are not the pages' box"),
    "pages_overlap": (genuine_kind(overlapping_pages), r"pages \d+ and \d+ overlap"),
    "pages_piled": (genuine_kind(piled_pages), r"pages 0 and \d+ overlap"),
    "page_longer_than_1mib": (genuine_kind(long_page), r"page 0 has 1048\d+ bytes \(at most 1048576\)"),
    "trailing_bytes": (genuine_kind(trailing_bytes), r"7 unexpected bytes after the last page"),
    "truncated_last_page": (genuine_kind(truncated_page), r"truncated map file"),
    "dense_page": (handmade_kind(dense_page), r"page 0 is too dense: 1001 objects"),
    # --- pages (caught when read)
    "page_pile_on_one_spot": (handmade_kind(pile_page), r"page 0 has \d+ bytes, too few for 200 objects"),
    "page_duplicate_position": (handmade_kind(duplicate_keys), r"two objects of one label at one position"),
    "page_key_outside_extent": (handmade_kind(out_of_extent), r"page position outside its extent"),
    "page_box_not_filled": (handmade_kind(not_filling), r"objects do not fill the page's box"),
    "page_runs_out_of_order": (handmade_kind(runs_out_of_order), r"label runs out of order"),
    "page_label_outside_table": (handmade_kind(label_outside_table), r"outside the label table"),
    "page_runs_do_not_add_up": (handmade_kind(run_counts_off), r"runs do not add up|shorter than its counts"),
    "page_zero_runs": (handmade_kind(pages_with(page0_options(n_runs=0))), r"0 label runs"),
    "page_more_runs_than_labels": (handmade_kind(pages_with(page0_options(n_runs=4))), r"4 label runs"),
    "page_area_code_out_of_range": (handmade_kind(area_out_of_range), r"area code out of range"),
    "page_area_code_infinite": (handmade_kind(area_beyond_float64), r"area code out of range"),
    "page_rice_k_49": (handmade_kind(rice_k(49)), r"Rice parameter out of range"),
    "page_rice_k_63": (handmade_kind(rice_k(63)), r"Rice parameter out of range"),
    "page_rice_value_overflow": (handmade_kind(rice_value_overflow), r"Rice-coded value out of range"),
    "page_nonzero_padding": (handmade_kind(pages_with(page0_options(pad=1))), r"contents do not match"),
    "page_extra_byte": (handmade_kind(pages_with(page0_options(extra=b"\0"))), r"contents do not match"),
    "page_cut_short": (handmade_kind(pages_with(set_payload(0, encode_page(base_pages()[0].runs, 49, 29)[:-2]))),
                       r"shorter than its counts"),
    "page_all_ones": (handmade_kind(pages_with(set_payload(0, bytes([1]) + b"\xff" * 40))),
                      r"outside the label table|shorter than its counts|out of order"),
    "page_count_above_runs": (handmade_kind(pages_with(page0_count(8))), r"runs do not add up"),
    # --- harmless: still a valid map with the same objects
    "harmless_unknown_key": (genuine_kind(lambda p: p.header.update(comment="made by hand")), None),
    "harmless_optional_nulls": (genuine_kind(optional_nulls), None),
    "harmless_deflate_level_1": (genuine_kind(deflate_level_1), None),
    "harmless_crs_as_wkt": (genuine_kind(as_wkt), None),
    "harmless_independent_encoder": (handmade_kind(lambda: handmade(base_pages())), None),
}


# --------------------------------------------------------------------------------------------- fixtures


def genuine_objects() -> Objects:
    rng = np.random.default_rng(7)
    n = 60
    return Objects(X0 + rng.uniform(0, 200, n), Y0 + rng.uniform(0, 150, n), rng.integers(0, 3, n),
                   rng.lognormal(4, 1, n), LABELS, CRS)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The genuine map's parts, images of it (with their truth) and the commands' answers on the genuine map."""
    where = tmp_path_factory.mktemp("genuine")
    path = where / "genuine.mapdb"
    write_map(path, genuine_objects(), page_capacity=16,
              metadata={"sources": [{"name": "g", "kind": "osm", "size": 1, "sha256": "0" * 64, "objects": 60}],
                        "build": {"quantum": 0.1}})
    with open_map(path) as m:
        images = simulate_images(m, 2, altitude=120.0, min_objects=5, seed=1)
    images_path = where / "images.jsonl"
    images_path.write_text("".join(json.dumps(im) + "\n" for im in images))
    parts = take_apart(path.read_bytes())
    assert len(parts.table) >= 3
    return {"parts": parts, "path": path, "images": images_path, "answers": run_all(path, images_path, where)}


def commands(map_path: Path, images: Path, out: Path) -> dict[str, list[str]]:
    return {
        "info": ["info", str(map_path)],
        "info --json": ["info", str(map_path), "--json"],
        "export": ["export", str(map_path), "-o", str(out / "x.geojson")],
        "query": ["query", str(map_path), str(images)],
        "simulate": ["simulate", str(map_path), "-o", str(out / "x.jsonl"), "--n", "3"],
        "evaluate": ["evaluate", str(map_path), str(images)],
    }


def run_all(map_path: Path, images: Path, out: Path) -> dict[str, object]:
    from mapdb_cli.main import cli

    runner = CliRunner()
    return {name: runner.invoke(cli, args) for name, args in commands(map_path, images, out).items()}


def comparable(name: str, result: object) -> object:
    """What must be equal between a harmless variant and the genuine map (times and paths aside)."""
    if name == "info --json":
        facts = json.loads(result.stdout)
        return {k: facts[k] for k in ("objects", "labels", "bounds", "quantum_m", "pages")}
    if name == "query":
        return [{k: v for k, v in json.loads(line).items() if k not in ("time_ms", "crs")}
                for line in result.stdout.splitlines()]
    if name == "evaluate":
        return [line for line in result.stdout.splitlines()[1:] if not line.startswith("time per image")]
    return None


# ------------------------------------------------------------------------------------------------ tests


def test_generator_makes_at_least_55_kinds_with_valid_checksums(world):
    """Every hostile file passes every checksum: header CRC, directory CRC in the header, page CRCs."""
    assert len(KINDS) >= 55
    for name, (make, _) in KINDS.items():
        data = make(world["parts"])
        if name in ("version_byte_flipped", "truncated_last_page", "header_length_past_end", "header_length_4gib"):
            continue  # these break the frame on purpose
        length = struct.unpack_from("<I", data, 12)[0]
        assert struct.unpack_from("<I", data, 16 + length)[0] == zlib.crc32(data[: 16 + length]), name


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_command_on_a_hostile_map(kind, world, tmp_path):
    make, expect = KINDS[kind]
    map_path = tmp_path / f"{kind}.mapdb"
    map_path.write_bytes(make(world["parts"]))
    results = run_all(map_path, world["images"], tmp_path)
    for name, result in results.items():
        assert result.exception is None or isinstance(result.exception, SystemExit), (name, result.exception)
        assert "Traceback" not in result.output, name
        if expect is None:
            assert result.exit_code == 0, (name, result.output)
            if kind != "harmless_independent_encoder":  # the others hold the genuine map's objects
                assert comparable(name, result) == comparable(name, world["answers"][name]), name
            continue
        assert result.exit_code == 1, (name, result.output)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"mapdb: error: {map_path}"), (name, result.stderr)
        assert re.search(expect, lines[0]), (name, lines[0])
        assert result.stdout == "", name
    if expect is not None:  # nothing written, not even a hidden temporary file
        assert sorted(p.name for p in tmp_path.iterdir()) == [map_path.name]


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_python_api_raises_map_format_error_only(kind, world, tmp_path):
    make, expect = KINDS[kind]
    path = tmp_path / "m.mapdb"
    path.write_bytes(make(world["parts"]))

    def read() -> int:
        with open_map(path) as m:
            m.query_bbox(*m.bounds)
            return len(m.all())

    if expect is None:
        assert read() == (60 if kind != "harmless_independent_encoder" else 10)
        return
    with pytest.raises(MapFormatError) as caught:
        read()
    assert re.search(expect, str(caught.value)) and "\n" not in str(caught.value)


@pytest.mark.parametrize("what", ["fifo", "directory"])
def test_a_map_that_is_not_a_regular_file(what, world, tmp_path):
    """A FIFO given as a map would block every command in open(); a directory is not a map either."""
    map_path = tmp_path / "m.mapdb"
    if what == "fifo":
        os.mkfifo(map_path)
    else:
        map_path.mkdir()
    for name, result in run_all(map_path, world["images"], tmp_path).items():
        assert result.exit_code == 1, (name, result.output)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0] == f"mapdb: error: {map_path}: is a {'FIFO' if what == 'fifo' else what}" \
            ", not a map file", (name, result.stderr)
    with pytest.raises(MapdbIOError):
        open_map(map_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.mapdb"]


def test_evaluate_on_a_corrupt_page_fails_in_worker_processes_too(world, tmp_path):
    """The map error of a worker ends the run (it used to be counted as 500 per-image "errors")."""
    from mapdb_cli.main import cli

    path = tmp_path / "m.mapdb"
    path.write_bytes(KINDS["page_duplicate_position"][0](world["parts"]))
    result = CliRunner().invoke(cli, ["evaluate", str(path), str(world["images"]), "--jobs", "2", "-q"])
    assert result.exit_code == 1 and result.stdout == ""
    assert result.stderr.strip() == f"mapdb: error: {path} page 0: two objects of one label at one position"
