"""The map format as ``docs/format.md`` states it: an independent decoder, written from the document alone.

The decoder below (everything above the "Tests" line) uses nothing from mapdb: only the standard library,
numpy and pyproj, and the document's words.  It decodes every page of real maps and checks every header
field the document lists; the tests then compare what it decodes with what mapdb's own reader returns,
page by page.  A reader written by a stranger from the document must read mapdb's files: when the two
disagree, the document (or the writer) is wrong.
"""

from __future__ import annotations

import json
import math
import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from pyproj import CRS

# ------------------------------------------------------------------------ the decoder (from docs/format.md)

MAGIC = b"\x89MAPDB\r\n"
PREFIX = struct.Struct("<8sHHI")  # magic, u16 version, u16 flags, u32 H
DIRECTORY_RECORD = struct.Struct("<qqIIIII")  # origin x, y; extent x, y; count; length; crc32
GAP_BLOCK, AREA_BLOCK, K_BITS, ELEVATION_BLOCK = 32, 256, 6, 32
MAX_AREA_CODE = 8320


@dataclass
class DecodedPage:
    origin_x: int
    origin_y: int
    extent_x: int
    extent_y: int
    label: list[int]
    qx: list[int]
    qy: list[int]
    area_code: list[int]
    elevation_code: list[int | None] | None = None  # version 2: None where unknown


class Bits:
    """A page's bit stream: fields most significant bit first, bytes filled from their top bit."""

    def __init__(self, data: bytes) -> None:
        self.text = "".join(f"{byte:08b}" for byte in data)
        self.pos = 0

    def read(self, width: int) -> int:
        field = self.text[self.pos : self.pos + width]
        assert len(field) == width, "bit stream ends inside a field"
        self.pos += width
        return int(field, 2) if width else 0

    def unary(self) -> int:
        stop = self.text.index("0", self.pos)  # that many 1-bits, then a 0-bit
        value = stop - self.pos
        self.pos = stop + 1
        return value


def unzigzag(z: int) -> int:
    return z // 2 if z % 2 == 0 else -(z + 1) // 2


def decode_page(payload: bytes, extent_x: int, extent_y: int, count: int, n_labels: int,
                elevation_cell: int | None = None, origin: tuple[int, int] = (0, 0)) -> DecodedPage:
    """One page; a version 2 page when ``elevation_cell`` (the header's, in quanta) is given."""
    runs = payload[0]
    bits = Bits(payload[1:])
    key_bits = max(1, ((extent_x + 1) * (extent_y + 1) - 1).bit_length())
    heads = []
    for _ in range(runs):
        code, n, first_key = bits.read(8), bits.read(16), bits.read(key_bits)
        heads.append((code, n, first_key, bits.read(16)))
    codes = [h[0] for h in heads]
    assert codes == sorted(set(codes)) and all(c < n_labels for c in codes), "runs not in ascending label code"
    assert sum(h[1] for h in heads) == count and all(h[1] >= 1 for h in heads)
    # The 2R sequences: key gaps of each run, then area residuals of each run; blocks of 32 and 256.
    lengths = [n - 1 for _, n, _, _ in heads] + [n for _, n, _, _ in heads]
    blocks = [GAP_BLOCK] * runs + [AREA_BLOCK] * runs
    if elevation_cell is not None:  # version 2: E, K; then K - 1 base steps and count residuals, blocks of 32
        first_base, cells = bits.read(16) - 32768, bits.read(16)
        assert 1 <= cells <= count
        lengths += [cells - 1, count]
        blocks += [ELEVATION_BLOCK, ELEVATION_BLOCK]
    parameters = [[bits.read(K_BITS) for _ in range(math.ceil(length / block))]
                  for length, block in zip(lengths, blocks)]
    assert all(k <= 48 for ks in parameters for k in ks)
    k_of_value = [ks[i // block] for ks, length, block in zip(parameters, lengths, blocks) for i in range(length)]
    quotients = [bits.unary() for _ in k_of_value]
    values = [(q << k) | bits.read(k) for q, k in zip(quotients, k_of_value)]
    padding = bits.text[bits.pos :]
    assert len(padding) < 8 and set(padding) <= {"0"}, "the page does not end with its zero padding"
    sequences, start = [], 0
    for length in lengths:
        sequences.append(values[start : start + length])
        start += length
    page = DecodedPage(0, 0, extent_x, extent_y, [], [], [], [])
    for r, (code, _n, first_key, reference) in enumerate(heads):
        keys = [first_key]
        for gap in sequences[r]:
            assert gap >= 1, "keys of a run must ascend strictly"
            keys.append(keys[-1] + gap)
        assert keys[-1] < (extent_x + 1) * (extent_y + 1)
        for key, residual in zip(keys, sequences[runs + r]):
            page.label.append(code)
            page.qx.append(key % (extent_x + 1))
            page.qy.append(key // (extent_x + 1))
            page.area_code.append(reference + unzigzag(residual))
    assert min(page.qx) == 0 and max(page.qx) == extent_x and min(page.qy) == 0 and max(page.qy) == extent_y
    assert all(0 <= c <= MAX_AREA_CODE for c in page.area_code)
    if elevation_cell is not None:
        page.elevation_code = elevations(page, origin, elevation_cell, first_base, cells, sequences[-2],
                                         sequences[-1])
    return page


def elevations(page: DecodedPage, origin: tuple[int, int], cell: int, first_base: int, cells: int,
               steps: list[int], residuals: list[int]) -> list[int | None]:
    """Version 2: each object's elevation code from its cell's base (cells in ascending (cell y, cell x))."""
    of_object = [((origin[1] + qy) // cell, (origin[0] + qx) // cell) for qx, qy in zip(page.qx, page.qy)]
    order = sorted(set(of_object))
    assert len(order) == cells, "K must count the page's distinct cells"
    bases = [first_base]
    for step in steps:
        bases.append(bases[-1] + unzigzag(step))
    assert all(-32768 <= b <= 32767 for b in bases)
    base_of = dict(zip(order, bases))
    codes = [None if r == 0 else base_of[c] + unzigzag(r - 1) for c, r in zip(of_object, residuals)]
    assert all(c is None or -32768 <= c <= 32767 for c in codes)
    return codes


def area_of(code: int) -> float:
    return 0.0 if code == 0 else 2.0 ** ((code - 1) / 8 - 16)


def decode_map(data: bytes) -> tuple[dict, list[DecodedPage]]:
    """The header and every page of a map file, every checksum and layout rule checked on the way."""
    magic, version, flags, header_length = PREFIX.unpack_from(data)
    assert magic == MAGIC and version in (1, 2) and flags == 0
    (header_crc,) = struct.unpack_from("<I", data, 16 + header_length)
    assert zlib.crc32(data[: 16 + header_length]) == header_crc
    inflater = zlib.decompressobj(-15)  # raw DEFLATE, no zlib header
    text = inflater.decompress(data[16 : 16 + header_length])
    assert inflater.eof and not inflater.unused_data, "the DEFLATE stream must fill H bytes exactly"
    header = json.loads(text.decode("utf-8"))
    pages = header["pages"]
    directory_start = 20 + header_length
    directory = data[directory_start : directory_start + DIRECTORY_RECORD.size * pages]
    assert zlib.crc32(directory) == header["directory_crc32"]
    offset = directory_start + DIRECTORY_RECORD.size * pages
    decoded = []
    for i in range(pages):
        ox, oy, ex, ey, count, length, crc = DIRECTORY_RECORD.unpack_from(directory, DIRECTORY_RECORD.size * i)
        payload = data[offset : offset + length]
        offset += length
        assert len(payload) == length and zlib.crc32(payload) == crc, f"page {i}"
        assert header["format_version"] == version
        page = decode_page(payload, ex, ey, count, len(header["labels"]), header.get("elevation_cell")
                           if version == 2 else None, (ox, oy))
        page.origin_x, page.origin_y = ox, oy
        decoded.append(page)
    assert offset == len(data), "the pages must fill the rest of the file exactly"
    return header, decoded


def positions(page: DecodedPage, quantum: float) -> tuple[np.ndarray, np.ndarray]:
    """Map positions: the integer sum, then one float64 multiplication."""
    return ((page.origin_x + np.array(page.qx, np.int64)) * quantum,
            (page.origin_y + np.array(page.qy, np.int64)) * quantum)


def is_int(v: object) -> bool:
    return type(v) is int


def is_number(v: object) -> bool:
    return type(v) in (int, float) and math.isfinite(v)


def check_header(header: dict, pages: list[DecodedPage]) -> None:
    """Every field of the header table, with its stated type and rule."""
    assert header["format"] == "mapdb"
    assert is_int(header["format_version"]) and header["format_version"] in (1, 2)
    if header["format_version"] == 2:
        assert is_number(header["elevation_step_m"]) and 0 < header["elevation_step_m"] <= 1000
        assert is_int(header["elevation_cell"]) and 1 <= header["elevation_cell"] <= 1 << 24
    else:
        assert "elevation_step_m" not in header and "elevation_cell" not in header
    assert isinstance(header["crs"], str) and 1 <= len(header["crs"]) <= 4096
    wkt = header.get("crs_wkt")
    assert wkt is None or (isinstance(wkt, str) and len(wkt) <= 1 << 20)
    if wkt is None:
        assert re.fullmatch(r"[A-Za-z][A-Za-z0-9_.-]*:[A-Za-z0-9_.-]+", header["crs"])
    assert CRS.from_user_input(wkt or header["crs"]).is_projected
    assert is_number(header["quantum"]) and 0 < header["quantum"] <= 1000
    assert header["area_log2_steps"] == 8 and header["area_floor_log2"] == -16
    assert is_int(header["area_log2_steps"]) and is_int(header["area_floor_log2"])
    labels = header["labels"]
    assert isinstance(labels, list) and 1 <= len(labels) <= 255
    for i, entry in enumerate(labels):
        assert entry["code"] == i and is_int(entry["code"]) and is_int(entry["count"]) and entry["count"] >= 0
        assert isinstance(entry["name"], str) and 1 <= len(entry["name"]) <= 100 and entry["name"].isprintable()
    assert len({entry["name"] for entry in labels}) == len(labels)
    per_label = np.bincount(np.concatenate([p.label for p in pages]), minlength=len(labels))
    assert [entry["count"] for entry in labels] == per_label.tolist()
    assert is_int(header["count"]) and header["count"] == sum(len(p.label) for p in pages) == per_label.sum()
    assert is_int(header["pages"]) and header["pages"] == len(pages) >= 1
    assert is_int(header["directory_crc32"]) and 0 <= header["directory_crc32"] < 1 << 32
    q = header["quantum"]
    box = [min(p.origin_x for p in pages) * q, min(p.origin_y for p in pages) * q,
           max(p.origin_x + p.extent_x for p in pages) * q, max(p.origin_y + p.extent_y for p in pages) * q]
    bounds = header["bounds"]
    assert len(bounds) == 4 and all(map(is_number, bounds)) and bounds == box  # exactly the page boxes' box
    lonlat = header.get("bounds_lonlat")
    assert lonlat is None or (len(lonlat) == 4 and all(map(is_number, lonlat)))
    assert header.get("page_capacity") is None or (is_int(header["page_capacity"])
                                                   and 1 <= header["page_capacity"] <= 65535)
    assert header.get("merged_duplicates") is None or (is_int(header["merged_duplicates"])
                                                       and header["merged_duplicates"] >= 0)
    for key in ("software", "created"):
        assert header.get(key) is None or isinstance(header[key], str)
    for source in header.get("sources") or []:
        assert all(isinstance(source[k], str) for k in ("name", "kind", "sha256"))
        assert all(is_int(source[k]) and source[k] >= 0 for k in ("size", "objects"))
    assert header.get("build") is None or isinstance(header["build"], dict)


# ------------------------------------------------------------------------------------------------ Tests

from mapdb.build.pipeline import build_map  # noqa: E402  (the maps are built, and read back, by mapdb itself)
from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.mapfile.writer import write_map  # noqa: E402
from mapdb.objects import Objects  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "format.md"
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"
# ../shared/data beside the checkout; a worktree elsewhere falls back on the machine's copy
SHARED = next((p for p in (REPO.parent / "shared" / "data", Path("/work/shared/data")) if p.is_dir()),
              REPO.parent / "shared" / "data")
OSM = SHARED / "osm"
EXTRACTS = ["monaco-2021-12-03.osm.pbf", "andorra-2021-06-22.osm.pbf", "liechtenstein-2013-08-03.osm.pbf"]


def assert_decodes_like_mapdb(path: Path) -> tuple[dict, list[DecodedPage]]:
    """Decode a map independently; every page must equal what mapdb's reader returns for it."""
    header, pages = decode_map(path.read_bytes())
    check_header(header, pages)
    with open_map(path) as m:
        reference = m.all()
        assert m.page_count == len(pages)
    names = [entry["name"] for entry in header["labels"]]
    assert reference.labels == tuple(names)
    start = 0
    for i, page in enumerate(pages):
        n = len(page.label)
        x, y = positions(page, header["quantum"])
        part = reference.take(slice(start, start + n))
        start += n
        assert np.array_equal(x, part.x) and np.array_equal(y, part.y), f"page {i} positions"
        assert [names[c] for c in page.label] == part.names().tolist(), f"page {i} labels"
        area = np.array([area_of(c) for c in page.area_code])
        # both decode the same area code: equal up to float rounding, far inside the format's 4.4 %
        assert np.allclose(area, part.area, rtol=1e-12, atol=0), f"page {i} areas"
        if page.elevation_code is None:
            assert part.elevation is None
        else:
            step = header["elevation_step_m"]
            z = np.array([np.nan if c is None else c * step for c in page.elevation_code])
            assert np.array_equal(z, part.elevation, equal_nan=True), f"page {i} elevations"
    assert start == len(reference)
    return header, pages


@pytest.mark.parametrize("name", EXTRACTS)
def test_spec_decodes_maps_of_real_extracts(name: str, tmp_path: Path) -> None:
    source = OSM / name
    if not source.is_file():
        pytest.skip(f"real data absent: {source} (expected ../shared/data beside the checkout, see SOURCES.md)")
    out = tmp_path / "map.mapdb"
    build_map([source], out)
    header, pages = assert_decodes_like_mapdb(out)
    assert header["count"] > 1000 and len(pages) > 1  # a real map of several pages, not a toy
    # runs long enough to use several Rice blocks of key gaps and of area residuals
    assert max(max(np.bincount(p.label)) for p in pages) > AREA_BLOCK


def test_spec_decodes_the_sample_map(tmp_path: Path) -> None:
    out = tmp_path / "helsinki.mapdb"
    build_map([SAMPLE], out)
    header, pages = assert_decodes_like_mapdb(out)
    assert header["count"] == sum(len(p.label) for p in pages) > 500
    assert header["sources"][0]["name"] == SAMPLE.name


def test_spec_decodes_a_crs_without_code_and_keeps_areas_within_its_precision(tmp_path: Path) -> None:
    """A WKT CRS, a coarser quantum, small pages, point objects, and the stated area precision (4.4 %)."""
    rng = np.random.default_rng(7)
    n = 3000
    qx = rng.choice(40_000, n, replace=False)  # distinct positions: nothing merged
    x, y = qx * 0.25 + 500_000.0, rng.integers(0, 40_000, n) * 0.25 + 6_000_000.0
    area = np.where(rng.random(n) < 0.2, 0.0, np.exp(rng.uniform(np.log(1e-4), np.log(1e9), n)))
    names = [f"label{i}" for i in range(12)]
    crs = "+proj=tmerc +lat_0=0 +lon_0=10 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
    objects = Objects(x, y, rng.integers(0, 12, n), area, names, crs)
    out = tmp_path / "synthetic.mapdb"
    write_map(out, objects, quantum=0.25, page_capacity=300)
    header, pages = assert_decodes_like_mapdb(out)
    assert header["crs_wkt"] is not None and len(pages) >= 10
    stored = {}
    for page in pages:
        x_out, y_out = positions(page, 0.25)
        for label, xi, yi, code in zip(page.label, x_out, y_out, page.area_code):
            stored[(label, xi, yi)] = area_of(code)
    for label, xi, yi, a in zip(objects.label, x, y, area):
        got = stored[(int(label), xi, yi)]
        if a == 0:
            assert got == 0
        else:
            assert abs(math.log2(got / a)) <= 1 / 16 + 1e-12  # within a factor 2^(1/16): 4.4 %


def test_the_worked_example_of_the_document_decodes_as_stated(tmp_path: Path) -> None:
    text = DOC.read_text(encoding="utf-8")
    found = re.search(r"page bytes \(hex\): ([0-9a-f ]+)", text)
    assert found, "docs/format.md lost its worked example"
    payload = bytes.fromhex(found.group(1))
    assert "origin (10, 20), extent (2, 1), count 3, length 17" in text
    page = decode_page(payload, 2, 1, 3, n_labels=2)
    page.origin_x, page.origin_y = 10, 20
    x, y = positions(page, 1.0)
    decoded = [(label, float(xi), float(yi), round(area_of(c), 2))
               for label, xi, yi, c in zip(page.label, x, y, page.area_code)]
    assert decoded == [(0, 10.0, 20.0, 98.70), (0, 12.0, 21.0, 0.0), (1, 11.0, 20.0, 4870.99)]
    # and mapdb writes exactly these bytes for the objects the document describes (one page, the file's end)
    objects = Objects.from_names([10.0, 12.0, 11.0], [20.0, 21.0, 20.0], ["building", "building", "park"],
                                 area=[100.0, 0.0, 5000.0], crs="EPSG:32631", labels=["building", "park"])
    write_map(tmp_path / "example.mapdb", objects, quantum=1.0)
    assert (tmp_path / "example.mapdb").read_bytes()[-17:] == payload


DEM = OSM.parent / "dem" / "N43E007.hgt"


def test_spec_decodes_a_map_with_elevation_from_the_shared_dem(tmp_path: Path) -> None:
    """Version 2: Monaco with the shared SRTM tile, decoded independently, elevations as the DEM's."""
    source = OSM / EXTRACTS[0]
    if not source.is_file() or not DEM.is_file():
        pytest.skip(f"real data absent: {source} or {DEM} (expected ../shared/data beside the checkout)")
    out = tmp_path / "monaco.mapdb"
    build_map([source], out, dem=[DEM])
    header, pages = assert_decodes_like_mapdb(out)
    assert header["format_version"] == 2 and len(pages) > 1
    codes = [c for p in pages for c in p.elevation_code or []]
    assert None not in codes and -2 <= min(codes) and max(codes) <= 175  # SOURCES.md: -1..171 m


def test_spec_decodes_elevation_with_unknowns_negatives_and_many_cells(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 2500
    x, y = rng.uniform(0, 5000, n) + 500_000.0, rng.uniform(0, 5000, n) - 3000.0  # negative y: floor division
    z = -50 + 0.2 * (x - 500_000.0) + rng.normal(0, 3, n)
    z[::13] = np.nan
    objects = Objects.from_names(x, y, rng.choice(["a", "b"], n), crs="EPSG:32631").with_elevation(z)
    out = tmp_path / "relief.mapdb"
    write_map(out, objects, page_capacity=200)
    header, pages = assert_decodes_like_mapdb(out)
    assert header["format_version"] == 2 and header["elevation_step_m"] == 1.0 and len(pages) >= 10
    with open_map(out) as m:
        back = m.all()
    got = {(round(a, 1), round(b, 1)): e for a, b, e in zip(back.x, back.y, back.elevation)}
    stored = np.array([got[(round(a, 1), round(b, 1))] for a, b in zip(np.rint(x * 10) / 10, np.rint(y * 10) / 10)])
    assert np.array_equal(np.isnan(stored), np.isnan(z))
    assert np.nanmax(np.abs(stored - z)) <= 0.5 + 1e-9  # half a step


def test_the_worked_elevation_example_of_the_document(tmp_path: Path) -> None:
    text = " ".join(DOC.read_text(encoding="utf-8").split())
    assert "K = 1, E = 32768 + 53" in text and "are zigzag(0) + 1 = 1, 0 and zigzag(2) + 1 = 5" in text
    objects = Objects.from_names([10.0, 12.0, 11.0], [20.0, 21.0, 20.0], ["building", "building", "park"],
                                 area=[100.0, 0.0, 5000.0], crs="EPSG:32631", labels=["building", "park"])
    out = tmp_path / "example2.mapdb"
    from mapdb.mapfile.writer import MapWriter

    with MapWriter(out, quantum=1.0, elevation_step=1.0, elevation_cell_m=10.0) as writer:
        writer.add(objects.with_elevation(np.array([53.0, np.nan, 55.0])))
        writer.finish()
    header, pages = assert_decodes_like_mapdb(out)
    assert header["elevation_cell"] == 10 and len(pages) == 1
    assert pages[0].elevation_code == [53, None, 55]
    # the page after the version 1 run heads: E = 32768 + 53 and K = 1, as the document says
    head_bits = "".join(f"{b:08b}" for b in out.read_bytes()[-pages_length(out):][1:])
    run_heads = 2 * (8 + 16 + 3 + 16)
    assert int(head_bits[run_heads:run_heads + 16], 2) == 32768 + 53 and int(head_bits[run_heads + 16:
                                                                                       run_heads + 32], 2) == 1


def pages_length(path: Path) -> int:
    """The one page's length, from the directory record at the end of a one-page map's prefix."""
    with open_map(path) as m:
        return int(m.page_directory["length"][0])
