"""The kernel's decoding of the stored index's packed blocks (``_kernel_qdecode.c``) against the numpy code it
replaced (tests/qdecoderefs.py): directory pages (their checks included), coordinate blocks and neighbour blocks
decode to identical arrays on real indexes (a map written here, Monaco) and on random and edge blocks; forged pages
are refused exactly as before; wrong calls raise TypeError or ValueError."""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest
import qdecoderefs

from mapdb.build.pipeline import build_map
from mapdb.errors import MapFormatError
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match import _kernel
from mapdb.match.index.binding import PageBoxes
from mapdb.match.index.directory import Directory
from mapdb.match.index.layout import BLOCK
from mapdb.match.index.lookup import Section
from mapdb.match.index.packed import (
    NB_BLOCK,
    PAD,
    coord_fields,
    dense_side,
    directory_pages,
    neighbour_fields,
    pack_coords,
    pack_neighbours,
)
from mapdb.match.index.stored import StoredQuadIndex, build_index, index_path
from mapdb.objects import Objects

_RELATIVE = Path(__file__).resolve().parents[2] / "shared" / "data"
OSM = (_RELATIVE if _RELATIVE.is_dir() else Path("/work/shared/data")) / "osm"
MONACO = OSM / "monaco-2021-12-03.osm.pbf"


@pytest.fixture(scope="module", params=["written", "monaco"])
def indexed(request, tmp_path_factory) -> Path:
    """A map and its ``.qidx``: 3,000 random objects written here, and Monaco (skipped when absent)."""
    path = tmp_path_factory.mktemp("qdecode") / f"{request.param}.mapdb"
    if request.param == "monaco":
        if not MONACO.exists():
            pytest.skip(f"{MONACO} is absent (the shared OSM extracts: ../shared/data/osm or /work/shared/data/osm)")
        build_map([MONACO], path)
    else:
        rng = np.random.default_rng(5)
        n = 3000
        write_map(path, Objects(500_000 + rng.uniform(0, 900, n), 4_650_000 + rng.uniform(0, 700, n),
                                rng.choice(3, n, p=[0.7, 0.25, 0.05]), np.zeros(n),
                                ("building", "road_intersection", "park"), "EPSG:32631"))
    build_index(path)
    return path


def test_real_indexes_decode_as_the_numpy_code(indexed: Path) -> None:
    ours, ref = StoredQuadIndex(index_path(indexed)), StoredQuadIndex(index_path(indexed))
    with open_map(indexed) as m:  # bound to the map: every block decoded is checked against its page boxes
        ours.check_map(m)
        ref.check_map(m)
    try:
        pages = ours._directory.decoded.size
        rng = np.random.default_rng(0)
        for piece in np.array_split(rng.permutation(pages), 5):  # in pieces, some pages asked for twice
            twice = np.concatenate([piece, piece[:3]])
            ours._directory.decode(twice)
            qdecoderefs.decode(ref._directory, twice)
            for name in ("decoded", "key", "count", "start"):
                assert np.array_equal(getattr(ours._directory, name), getattr(ref._directory, name)), name
        assert ours._directory.decoded.all() and ours._directory.count.sum() == ours.n_quads
        objects = np.arange(ours.n_objects)
        got = ours._coords.rows(objects)
        qdecoderefs.coordinates_decode(ref._coords, np.arange(ref._coords.decoded.size))
        assert np.array_equal(got, ref._coords.xy.astype(np.int64)) and np.array_equal(ours._coords.xy, ref._coords.xy)
        assert ours._boxes is not None and ours._boxes.checked.all()
        nb = ours._neighbours
        want = qdecoderefs.neighbour_fields(nb.data.array, nb.start.array[objects // NB_BLOCK].astype(np.int64),
                                            nb.width.array[objects // NB_BLOCK].astype(np.int64), objects, nb.k)
        assert np.array_equal(nb.rows(objects), want) and want.shape == (ours.n_objects, nb.k)
    finally:
        ours.close()
        ref.close()


def _padded(data: np.ndarray) -> np.ndarray:
    return np.concatenate([data, np.zeros(PAD, np.uint8)])


@pytest.mark.parametrize("case", ["random", "equal", "one", "wide", "empty"])
def test_coordinate_blocks_are_the_numpy_code(case: str) -> None:
    rng = np.random.default_rng(1)
    m = {"random": 1000, "equal": 130, "one": 1, "wide": 200, "empty": 0}[case]
    top = 2**31 - 1 if case == "wide" else 5000
    coords = rng.integers(0, top, (m, 2)) if case != "equal" else np.full((m, 2), 77)
    data, lengths, widths, base = pack_coords(coords, 0)
    data = _padded(data)
    start = (np.cumsum(lengths) - lengths).astype(np.int64)
    size = np.minimum(m - np.arange(start.size) * NB_BLOCK, NB_BLOCK)
    got = coord_fields(data, start, widths.astype(np.int64), base, size)
    block = np.arange(m) // NB_BLOCK
    want = qdecoderefs.coord_fields(data, start[block], widths[block].astype(np.int64), base[block], np.arange(m))
    assert got.dtype == want.dtype and np.array_equal(got, want) and np.array_equal(got, coords)


@pytest.mark.parametrize("case", ["random", "self", "one", "far"])
def test_neighbour_blocks_are_the_numpy_code(case: str) -> None:
    rng = np.random.default_rng(2)
    m, k = {"random": (700, 5), "self": (70, 3), "one": (1, 5), "far": (300, 4)}[case]
    ids = np.arange(m)[:, None]
    table = {"random": rng.integers(0, m, (m, k)), "self": np.repeat(ids, k, axis=1), "one": np.zeros((1, k), int),
             "far": np.where(rng.random((m, k)) < 0.5, 0, m - 1)}[case]
    data, lengths, widths = pack_neighbours(table, 0)
    data = _padded(data)
    start = (np.cumsum(lengths) - lengths).astype(np.int64)
    objects = rng.permutation(m)
    lo, w = start[objects // NB_BLOCK], widths[objects // NB_BLOCK].astype(np.int64)
    got = neighbour_fields(data, lo, w, objects, k)
    want = qdecoderefs.neighbour_fields(data, lo, w, objects, k)
    assert got.dtype == want.dtype and np.array_equal(got, want) and np.array_equal(got, table[objects])


def _directory(data: np.ndarray, fence: np.ndarray, combos: np.ndarray, cells: np.ndarray, n_cells: int,
               n_quads: int, bits: int, max_cell: int) -> Directory:
    data = _padded(data)
    crcs = np.array([zlib.crc32(data[b : b + BLOCK].tobytes()) for b in range(0, data.size, BLOCK)], np.uint32)
    section = Section("dir_data", data, crcs, "forged.qidx")
    return Directory(fence.astype(np.uint64), section, combos, cells,
                     (n_cells, n_quads, data.size - PAD, max_cell, fence.shape[0] - 1), bits, "forged.qidx")


def _pages(seed: int) -> tuple:
    """A directory of two label combinations' cells (random keys and counts), packed by the writer's code."""
    rng = np.random.default_rng(seed)
    bits, combos, cells = 12, np.array([3, 9]), np.array([0.05, 0.2])
    parts = []
    for lk, side in zip(combos, dense_side(cells), strict=True):
        dense = np.sort(rng.choice(side**4, 150, replace=False))
        c = np.column_stack([dense // side**3, dense // side**2 % side, dense // side % side, dense % side])
        key = np.full(dense.size, lk, np.uint64)
        for j in range(4):
            key = (key << np.uint64(bits)) | c[:, j].astype(np.uint64)
        parts.append(key)
    keys = np.concatenate(parts)
    counts = rng.integers(1, 40, keys.size)
    data, fence = directory_pages(keys, counts, combos, cells, bits)
    return data, fence, combos, cells, keys.size, int(counts.sum()), bits, int(counts.max())


def test_forged_pages_are_refused_as_before() -> None:
    """Random bytes of the packed pages changed (checksums made right): the kernel refuses exactly the pages the
    numpy code refused, with its message, and decodes the others to its arrays."""
    data, fence, *rest = _pages(3)
    genuine = _directory(data, fence, *rest)
    genuine.decode(np.arange(genuine.decoded.size))
    rng = np.random.default_rng(4)
    refused = 0
    for trial in range(150):
        forged = data.copy()
        at = rng.integers(0, data.size, 1 + trial % 3)
        forged[at] = rng.integers(0, 256, at.size) if trial % 2 else forged[at] ^ (1 << rng.integers(0, 8, at.size))
        pages = rng.choice(fence.shape[0] - 1, 2, replace=False)
        ours, ref = _directory(forged, fence, *rest), _directory(forged, fence, *rest)
        errors = []
        for d, decode in ((ours, Directory.decode), (ref, qdecoderefs.decode)):
            try:
                decode(d, pages)
                errors.append(None)
            except MapFormatError as exc:
                errors.append(str(exc))
        assert errors[0] == errors[1]
        refused += errors[0] is not None
        for name in ("decoded", "key", "count", "start"):
            assert np.array_equal(getattr(ours, name), getattr(ref, name)), name
    assert 20 < refused < 150  # both kinds of outcome were tried


@pytest.mark.parametrize("seed", range(6))
def test_page_boxes_are_the_numpy_code(seed: int) -> None:
    """Objects checked against their map pages' boxes (empty pages among them, objects on the borders, some
    outside): the same page named in the same error, or the same pages marked checked."""
    rng = np.random.default_rng(seed)
    p = 40
    table = np.zeros(p, [("ox", "<i8"), ("oy", "<i8"), ("ex", "<u4"), ("ey", "<u4"), ("count", "<u4")])
    table["ox"], table["oy"] = rng.integers(0, 1000, p), rng.integers(0, 1000, p)
    table["ex"], table["ey"] = rng.integers(0, 50, p), rng.integers(0, 50, p)
    table["count"] = rng.integers(0, 30, p) * (rng.random(p) < 0.8)
    ours, ref = PageBoxes(table, (3, 7), "x.qidx", "x.mapdb"), PageBoxes(table, (3, 7), "x.qidx", "x.mapdb")
    ids = np.sort(rng.choice(int(ours.start[-1]), 200, replace=False))
    page = np.searchsorted(ours.start, ids, side="right") - 1
    xy = ours.lo[page] + rng.integers(0, 2, (ids.size, 2)) * (ours.hi[page] - ours.lo[page])  # corners
    xy += (rng.random((ids.size, 2)) < 0.5) * rng.integers(0, 51, (ids.size, 2)).clip(max=ours.hi[page] - xy)
    if seed % 2:
        bad = rng.integers(0, ids.size)
        xy[bad, seed % 4 // 2] += 1 + ours.hi[page[bad], seed % 4 // 2] - ours.lo[page[bad], seed % 4 // 2]
    errors = []
    for boxes, check in ((ours, PageBoxes.check), (ref, qdecoderefs.page_boxes_check)):
        try:
            check(boxes, ids, xy)
            errors.append(None)
        except MapFormatError as exc:
            errors.append(str(exc))
    assert errors[0] == errors[1] and (errors[0] is None) == (seed % 2 == 0)
    assert np.array_equal(ours.checked, ref.checked) and ours.checked.any() == (seed % 2 == 0)


def test_wrong_calls_raise() -> None:
    data = np.zeros(64, np.uint8)
    one = np.zeros(1, np.int64)
    with pytest.raises(TypeError):
        _kernel.qdecode_coord_fields(data.astype(np.float64), one, np.zeros((1, 2), np.int64), np.zeros((1, 2),
                                     np.int64), one)
    with pytest.raises(ValueError):  # the field's window leaves the data
        _kernel.qdecode_coord_fields(data, np.array([60]), np.ones((1, 2), np.int64), np.zeros((1, 2), np.int64),
                                     np.array([1]))
    with pytest.raises(ValueError):  # wider than 57 bits
        _kernel.qdecode_coord_fields(data, one, np.full((1, 2), 58), np.zeros((1, 2), np.int64), np.array([1]))
    with pytest.raises(ValueError):  # more objects than a block holds
        _kernel.qdecode_coord_fields(data, one, np.ones((1, 2), np.int64), np.zeros((1, 2), np.int64),
                                     np.array([NB_BLOCK + 1]))
    with pytest.raises(ValueError):  # shapes disagree
        _kernel.qdecode_coord_fields(data, one, np.ones((2, 2), np.int64), np.zeros((1, 2), np.int64), one)
    with pytest.raises(ValueError):
        _kernel.qdecode_neighbour_fields(data, one, np.array([3]), np.array([-1]), 4)
    with pytest.raises(ValueError):
        _kernel.qdecode_neighbour_fields(data, np.array([1 << 40]), np.array([3]), one, 4)
    with pytest.raises(TypeError):
        _kernel.qdecode_neighbour_fields(data, one, np.array([3], np.int32), one, 4)
    key, count, start = np.zeros(4, np.uint64), np.zeros(4, np.int64), np.zeros(4, np.int64)
    row = np.array([[0, 2, 0, 10**4, 10, 1, 0, 2, 0]], np.int64)
    assert _kernel.qdecode_directory_pages(data, row, 12, 5, key, count, start) is False  # zero gap: refused
    assert not key.any() and not count.any()
    with pytest.raises(ValueError):  # cells past the directory's
        _kernel.qdecode_directory_pages(data, row + np.array([0, 0, 0, 0, 0, 0, 0, 0, 3]), 12, 5, key, count, start)
    with pytest.raises(ValueError):  # the page's first byte past the data
        _kernel.qdecode_directory_pages(data, row + np.array([60, 0, 0, 0, 0, 0, 0, 0, 0]), 12, 5, key, count, start)
    with pytest.raises(ValueError):
        _kernel.qdecode_directory_pages(data, row, 16, 5, key, count, start)
    with pytest.raises(ValueError):  # a read-only key array
        _kernel.qdecode_directory_pages(data, row, 12, 5, np.frombuffer(bytes(32), np.uint64), count, start)
    with pytest.raises(ValueError):
        _kernel.qdecode_directory_pages(data, row[:, :8].copy(), 12, 5, key, count, start)
    start2, box = np.array([0, 2]), np.zeros((1, 2), np.int64)
    with pytest.raises(ValueError):  # an object past the pages
        _kernel.qdecode_page_boxes(np.array([2]), box, start2, box, box, np.zeros(1, bool))
    with pytest.raises(TypeError):
        _kernel.qdecode_page_boxes(np.array([1]), box, start2, box, box, np.zeros(1, np.int64))
    with pytest.raises(ValueError):
        _kernel.qdecode_page_boxes(np.array([1]), box, np.array([0, 1, 2]), box, box, np.zeros(1, bool))
