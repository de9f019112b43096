"""``docs/index_format.md`` against the code: an index read by a reader written from the document alone.

The reader below uses only the standard library and the page's words (prefix, header, sections, the packed
codes, keys); it shares no code with ``mapdb.match.index``.  Its quads, cells and neighbours must be the
library's, and every quad must lie in the cell and at the position its record gives.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match.index.stored import build_index, open_index
from mapdb.match.quads import canonical_quads
from mapdb.objects import Objects

DOC = Path(__file__).resolve().parents[1] / "docs" / "index_format.md"


class Bits:
    """Most-significant-bit-first fields of a byte string, from a byte offset."""

    def __init__(self, data: bytes, byte: int) -> None:
        self.data, self.pos = data, byte * 8

    def read(self, width: int) -> int:
        value = 0
        for _ in range(width):
            value = (value << 1) | ((self.data[self.pos >> 3] >> (7 - (self.pos & 7))) & 1)
            self.pos += 1
        return value


def _unzigzag(z: int) -> int:
    return z // 2 if z % 2 == 0 else -(z + 1) // 2


def _coords_as_documented(raw, n: int, h: dict) -> list[tuple[int, int]]:
    """Coordinates: blocks of 64 objects, offsets from the block's base at its two widths."""
    co_start = struct.unpack(f"<{len(raw('co_start')) // 8}Q", raw("co_start"))
    coords = []
    for j in range(len(co_start) - 1):
        wx, wy = raw("co_width")[2 * j : 2 * j + 2]
        bx, by = struct.unpack_from("<ii", raw("co_base"), 8 * j)
        bits = Bits(raw("co_data"), co_start[j])
        objects = range(64 * j, min(n, 64 * j + 64))
        for _ in objects:
            coords.append((bx + bits.read(wx), by + bits.read(wy)))
        assert co_start[j + 1] - co_start[j] == math.ceil(len(objects) * (wx + wy) / 8)
    assert len(coords) == n and co_start[-1] == h["co_bytes"]
    return coords


def _cells_as_documented(raw, h: dict) -> list[tuple[int, int, int]]:
    """Directory pages: every cell's key, first quad and quad count."""
    fence = [struct.unpack_from("<4Q", raw("fence"), 32 * p) for p in range(h["pages"] + 1)]
    b = h["key_cell_bits"]
    cell_of = dict((int(k), c) for k, c in h["combos"])
    cells = []  # (key, first quad, count)
    for p in range(h["pages"]):
        key, first_cell, first_quad, first_byte = fence[p]
        n_cells = fence[p + 1][1] - first_cell
        bits = Bits(raw("dir_data"), first_byte)
        wg, wc = bits.read(8), bits.read(8)
        gaps = [bits.read(wg) for _ in range(n_cells - 1)]
        counts = [bits.read(wc) + 1 for _ in range(n_cells)]
        assert fence[p + 1][3] - first_byte == math.ceil((16 + (n_cells - 1) * wg + n_cells * wc) / 8)
        label_key = key >> (4 * b)
        m = math.floor(2 / cell_of[label_key]) + 1
        g = [(key >> (b * (3 - j))) & ((1 << b) - 1) for j in range(4)]
        dense = ((g[0] * m + g[1]) * m + g[2]) * m + g[3]
        at = first_quad
        for i in range(n_cells):
            dense += gaps[i - 1] if i else 0
            d, g = dense, []
            for _ in range(4):
                g.append(d % m)
                d //= m
            g0, g1, g2, g3 = reversed(g)
            cells.append((label_key << 4 * b | g0 << 3 * b | g1 << 2 * b | g2 << b | g3, at, counts[i]))
            at += counts[i]
        assert at == fence[p + 1][2]
    return cells


def read_as_documented(path: Path) -> dict:
    """Everything the document says an index holds, read by its words."""
    data = path.read_bytes()
    magic, version, _flags, h_off, h_len, h_crc = struct.unpack_from("<8sHHQII", data, 0)
    assert magic == b"\x89MAPDBQX" and version == 4
    assert struct.unpack_from("<I", data, 28)[0] == zlib.crc32(data[:28])
    assert h_off + h_len == len(data) and zlib.crc32(data[h_off:]) == h_crc
    h = json.loads(data[h_off:].decode("utf-8"))
    sec = h["sections"]

    def raw(name: str) -> bytes:
        return data[sec[name]["offset"] : sec[name]["offset"] + sec[name]["length"]]

    # Every 4096-byte block of every section, its CRC in the table.
    table = struct.unpack(f"<{sec['crc']['length'] // 4}I", raw("crc"))
    assert zlib.crc32(raw("crc")) == h["crc_crc32"]
    for name, s in sec.items():
        if name != "crc":
            for b in range(-(-s["length"] // 4096)):
                assert zlib.crc32(raw(name)[b * 4096 : (b + 1) * 4096]) == table[s["first_block"] + b]
    n, ku, q = h["objects"], h["quad_neighbours"], h["quads"]
    coords = _coords_as_documented(raw, n, h)
    # Neighbours: blocks of 64 objects, zigzag differences at the block's width.
    nb_start = struct.unpack(f"<{sec['nb_start']['length'] // 8}Q", raw("nb_start"))
    widths, nb_data = raw("nb_width"), raw("nb_data")
    neighbours = []
    for j, w in enumerate(widths):
        bits = Bits(nb_data, nb_start[j])
        objects = range(64 * j, min(n, 64 * j + 64))
        for i in objects:
            neighbours.append([i + _unzigzag(bits.read(w)) for _ in range(ku)])
        assert nb_start[j + 1] - nb_start[j] == math.ceil(len(objects) * ku * w / 8)
    # Records.
    # The document's triples of places, those below KU.
    triples = [t for t in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3), (0, 1, 4), (0, 2, 4)) if max(t) < ku]
    assert h["quad_triples"] == [list(t) for t in triples]
    id_bits = max(1, (n - 1).bit_length())
    tb = max(1, (len(triples) - 1).bit_length())
    rb = math.ceil((id_bits + tb + 16) / 8)
    sb = min(8, (8 * rb - id_bits - tb) // 4)
    assert (h["record_bytes"], h["sub_bits"]) == (rb, sb)
    records = []
    for r in range(q):
        v = int.from_bytes(raw("quads")[r * rb : (r + 1) * rb], "little")
        sub = [(v >> (sb * (3 - j))) & ((1 << sb) - 1) for j in range(4)]
        v >>= 4 * sb
        anchor, triple = v >> tb, v & ((1 << tb) - 1)
        members = [anchor] + [neighbours[anchor][t] for t in triples[triple]]
        records.append((members, sub))
    cells = _cells_as_documented(raw, h)
    return {"header": h, "coords": coords, "neighbours": neighbours, "records": records, "cells": cells}


def _objects(n: int = 900) -> Objects:
    rng = np.random.default_rng(3)
    labels = ("building", "road_intersection", "park")
    return Objects(500_000 + rng.uniform(0, 500, n), 4_650_000 + rng.uniform(0, 400, n),
                   rng.choice(3, n, p=[0.7, 0.25, 0.05]), np.zeros(n), labels, "EPSG:32631")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("conformance") / "m.mapdb"
    write_map(path, _objects(), page_capacity=100)
    build_index(path, workers=1)
    return path


def test_the_document_describes_version_4() -> None:
    assert DOC.read_text().startswith("# The lost-in-space quad index file, format version 4\n")


def test_the_worked_example_of_the_document(tmp_path: Path) -> None:
    """Its three objects: no quads, one coordinate block of the bytes the document spells out."""
    x = 500_000.0 + np.array([0.3, 0.0, 0.5])
    y = 4_650_000.0 + np.array([0.0, 0.3, 0.0])
    path = tmp_path / "three.mapdb"
    write_map(path, Objects(x, y, np.zeros(3, np.int64), np.zeros(3), ("building",), "EPSG:32631"))
    build_index(path, workers=1)
    doc = read_as_documented(Path(str(path) + ".qidx"))
    h = doc["header"]
    assert (h["quads"], h["cells"], h["pages"], h["quad_neighbours"], h["quad_triples"]) == (0, 0, 0, 0, [])
    assert doc["coords"] == [(3, 0), (5, 0), (0, 3)] and doc["neighbours"] == [] and doc["cells"] == []
    data = Path(str(path) + ".qidx").read_bytes()
    co = h["sections"]["co_data"]
    assert data[co["offset"] : co["offset"] + co["length"]] == bytes([0x65, 0x06]) + bytes(8)
    with open_map(path) as m, open_index(Path(str(path) + ".qidx"), m) as ix:
        objects = m.all()
        assert np.array_equal(ix.coordinates(np.arange(3)), objects.x + 1j * objects.y)
        assert np.allclose(np.sort(objects.x), np.sort(x), rtol=0, atol=1e-6)


def test_a_reader_written_from_the_document_reads_what_the_library_reads(small) -> None:
    doc = read_as_documented(Path(str(small) + ".qidx"))
    h = doc["header"]
    with open_map(small) as m, open_index(Path(str(small) + ".qidx"), m) as ix:
        objects = m.all()
        ix.verify()
        library_quads = ix.quads()
        # Positions: the map's objects, bit for bit.
        ox, oy = h["map"]["origin"]
        quantum = h["map"]["quantum"]
        x = np.array([(c[0] + ox) * quantum for c in doc["coords"]])
        assert np.array_equal(x, objects.x)
        # Neighbours: each object's 5 nearest, as the library decodes them.
        assert np.array_equal(ix._neighbours.rows(np.arange(ix.n_objects)), np.array(doc["neighbours"]))
        # Cells: every page decoded by the library gives the same keys, first quads and counts.
        ix._directory.decode(np.arange(h["pages"]))
        d = ix._directory
        assert [(int(k), int(s), int(c)) for k, s, c in zip(d.key, d.start, d.count, strict=True)] == doc["cells"]
    assert h["quads"] == len(doc["records"]) == len(library_quads) > 2 * h["objects"]
    mine = [tuple(sorted(members)) for members, _ in doc["records"]]
    assert mine == [tuple(sorted(r)) for r in library_quads.tolist()]
    # Each quad in the cell and at the position its record and key give (the document's key formula).
    b, sb = h["key_cell_bits"], h["sub_bits"]
    cell_of = dict((int(k), c) for k, c in h["combos"])
    z = objects.x + 1j * objects.y
    for key, first, count in doc["cells"]:
        for members, sub in doc["records"][first : first + count]:
            ids = np.sort(np.array(members))
            order, inv, _ = canonical_quads(z[ids][None, :])
            lab = objects.label[ids[order[0]]]
            label_key = ((lab[0] * 3 + lab[1]) * 3 + lab[2]) * 3 + lab[3]
            assert key >> (4 * b) == label_key
            s = (inv[0] + 1.0) / cell_of[label_key]
            g = np.floor(s).astype(int)
            assert [(key >> (b * (3 - j))) & ((1 << b) - 1) for j in range(4)] == g.tolist()
            assert np.floor((s - g) * 2**sb).astype(int).tolist() == sub


def test_a_map_with_blocks_is_indexed_as_documented_without_them(tmp_path: Path) -> None:
    """The document's section "Maps with blocks": the header key, every object's neighbours the nearest objects
    that are not blocks, no quad anchored at or holding a block, the quads those of the map without blocks."""
    objects = _objects(300)
    labels = (*objects.labels, "building_block")
    # A block beside every tenth object (a label the map's table knows: the index does not care what a block is).
    near = np.arange(0, len(objects), 10)
    x = np.concatenate([objects.x, objects.x[near] + 3.0])
    y = np.concatenate([objects.y, objects.y[near] + 2.0])
    label = np.concatenate([objects.label, np.full(near.size, 3)])
    with_blocks = Objects(x, y, label, np.zeros(x.size), labels, objects.crs)
    path, plain = tmp_path / "b.mapdb", tmp_path / "n.mapdb"
    write_map(path, with_blocks, page_capacity=100)
    write_map(plain, Objects(objects.x, objects.y, objects.label, objects.area, labels, objects.crs), page_capacity=100)
    build_index(path, workers=1)
    build_index(plain, workers=1)
    doc = read_as_documented(Path(str(path) + ".qidx"))
    assert doc["header"]["blocks"] == "left out" and "blocks" not in read_as_documented(Path(str(plain) + ".qidx"))[
        "header"]
    with open_map(path) as m:
        mine = m.all()
    block = mine.label == 3
    xy = np.column_stack([mine.x, mine.y])
    world = np.flatnonzero(~block)
    ku = doc["header"]["quad_neighbours"]
    for i, nb in enumerate(doc["neighbours"]):
        d = np.hypot(*(xy[world] - xy[i]).T)
        d[world == i] = np.inf  # the object itself is not its own neighbour
        assert not block[nb].any() and np.allclose(np.sort(d)[:ku], np.hypot(*(xy[nb] - xy[i]).T))
    assert not any(block[members].any() for members, _ in doc["records"])
    # The same quads (as positions) as the index of the map without its blocks.
    theirs = read_as_documented(Path(str(plain) + ".qidx"))
    with open_map(plain) as n:
        plain_objects = n.all()

    def positions(records: list, o: Objects) -> set:
        return {tuple(sorted(zip(o.x[ms].tolist(), o.y[ms].tolist(), strict=True))) for ms, _ in records}

    assert positions(doc["records"], mine) == positions(theirs["records"], plain_objects) != set()
