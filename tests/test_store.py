"""The map file: round trips, queries against brute force, and every kind of damaged file."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapdb import EmptyMapError, MapdbIOError, MapFormatError, MapVersionError, Objects
from mapdb.store import MAGIC, MemoryMap, open_map, write_map

LABELS = ("building", "road_intersection", "park", "water")


def random_objects(n: int, seed: int = 0, span: float = 4000.0) -> Objects:
    rng = np.random.default_rng(seed)
    x = 385000 + rng.uniform(0, span, n)
    y = 6671000 + rng.uniform(0, span * 0.6, n)
    label = rng.integers(0, len(LABELS), n)
    area = np.where(label == 1, 0.0, rng.lognormal(5, 1.5, n))
    return Objects(x, y, label, area, LABELS, "EPSG:32635")


def matched(stored: Objects, original: Objects) -> np.ndarray:
    dist, index = cKDTree(np.c_[stored.x, stored.y]).query(np.c_[original.x, original.y])
    assert dist.max() <= 0.1 * np.sqrt(2) / 2 + 1e-9
    return index


@pytest.fixture
def written(tmp_path):
    objects = random_objects(5000)
    path = tmp_path / "m.mapdb"
    write_map(path, objects, page_capacity=256, metadata={"sources": [{"name": "x"}]})
    return path, objects


def test_round_trip_positions_labels_areas(written):
    path, objects = written
    with open_map(path) as m:
        stored = m.all()
        assert len(stored) == len(objects) == len(m)
        assert m.page_count >= 5000 // 256
        index = matched(stored, objects)
        assert np.array_equal(stored.label[index], objects.label)
        nonzero = objects.area > 0
        rel = np.abs(stored.area[index][nonzero] / objects.area[nonzero] - 1)
        assert rel.max() < 0.045
        assert np.all(stored.area[index][~nonzero] == 0)
        # positions lie on the quantum grid
        assert np.allclose(np.round(stored.x / 0.1) * 0.1, stored.x)
        assert m.label_counts == objects.counts()
        assert m.metadata["sources"] == [{"name": "x"}]
        assert m.crs == "EPSG:32635"


def test_other_quantum_and_single_object(tmp_path):
    one = Objects.from_names([500123.456], [4e6], ["water"], area=[1234.0], crs="EPSG:32632")
    write_map(tmp_path / "one.mapdb", one, quantum=1.0)
    with open_map(tmp_path / "one.mapdb") as m:
        o = m.all()
        assert (o.x[0], o.y[0]) == (500123.0, 4e6)
        assert o.names().tolist() == ["water"]


def test_many_objects_on_one_spot(tmp_path):
    n = 3000
    o = Objects(np.full(n, 500000.0), np.full(n, 4e6), np.zeros(n, int), np.zeros(n), ("building",), "EPSG:32632")
    write_map(tmp_path / "spot.mapdb", o, page_capacity=1000)
    with open_map(tmp_path / "spot.mapdb") as m:
        assert len(m.query_radius(500000.0, 4e6, 1.0)) == n


@pytest.mark.parametrize("labels", [None, ["park"], ["park", "water"]])
def test_queries_match_brute_force(written, labels):
    path, objects = written
    rng = np.random.default_rng(1)
    with open_map(path) as m:
        stored = m.all()
        for _ in range(20):
            cx, cy = rng.uniform(m.bounds[0], m.bounds[2]), rng.uniform(m.bounds[1], m.bounds[3])
            r = rng.uniform(10, 800)
            want = (stored.x - cx) ** 2 + (stored.y - cy) ** 2 <= r * r
            box = (cx - r, cy - r * 0.5, cx + r * 0.7, cy + r)
            want_box = (stored.x >= box[0]) & (stored.x <= box[2]) & (stored.y >= box[1]) & (stored.y <= box[3])
            if labels is not None:
                keep = np.isin(stored.names(), labels)
                want, want_box = want & keep, want_box & keep
            got = m.query_radius(cx, cy, r, labels)
            got_box = m.query_bbox(*box, labels=labels)
            assert sorted(zip(got.x, got.y)) == sorted(zip(stored.x[want], stored.y[want]))
            assert sorted(zip(got_box.x, got_box.y)) == sorted(zip(stored.x[want_box], stored.y[want_box]))
        assert len(m.query_bbox(0, 0, 10, 10)) == 0


def test_memory_map_matches_file(written):
    path, objects = written
    mem = MemoryMap(objects)
    with open_map(path) as m:
        a, b = m.query_radius(386000, 6672000, 300), mem.query_radius(386000, 6672000, 300)
        assert sorted(zip(a.x, a.y)) == sorted(zip(b.x, b.y))
        assert m.cached("k", lambda: [1]) is m.cached("k", lambda: [2])


def test_storage_is_compact(tmp_path):
    objects = random_objects(20000, span=3000.0)
    write_map(tmp_path / "c.mapdb", objects)
    # 20000 random objects of 4 labels over 3 x 1.8 km at 0.1 m: positions and labels carry about 2.4 bytes
    # of entropy an object, log-quantized areas about 0.6; raw float64 columns would take 25 bytes.
    assert (tmp_path / "c.mapdb").stat().st_size / len(objects) < 3.3


def test_failed_write_keeps_earlier_map(written):
    path, objects = written
    before = path.read_bytes()
    bad = Objects(np.array([np.nan]), np.array([1.0]), np.array([0]), np.array([0.0]), LABELS, "EPSG:32635")
    with pytest.raises(ValueError):
        write_map(path, bad)
    with pytest.raises(EmptyMapError):
        write_map(path, Objects.empty(LABELS, "EPSG:32635"))
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_missing_empty_and_foreign_files(tmp_path):
    with pytest.raises(MapdbIOError, match="no such map file"):
        open_map(tmp_path / "nope.mapdb")
    (tmp_path / "empty.mapdb").write_bytes(b"")
    with pytest.raises(MapFormatError, match="empty file"):
        open_map(tmp_path / "empty.mapdb")
    (tmp_path / "text.mapdb").write_text("hello, not a map")
    with pytest.raises(MapFormatError, match="not a mapdb map"):
        open_map(tmp_path / "text.mapdb")


@pytest.mark.parametrize("keep", [5, 20, 200, -1])
def test_truncated_file(written, keep):
    path, _ = written
    data = path.read_bytes()
    path.write_bytes(data[:keep] if keep > 0 else data[:-1])
    with pytest.raises(MapFormatError, match="truncated|not a mapdb|checksum"):
        open_map(path)


def test_flipped_bits_are_caught(written):
    path, _ = written
    data = bytearray(path.read_bytes())
    header_len = struct.unpack_from("<I", data, 12)[0]
    header_end = 16 + header_len + 4
    for position in (30, header_end + 3, len(data) - 5):  # header, directory, last page
        damaged = bytearray(data)
        damaged[position] ^= 0x10
        path.write_bytes(bytes(damaged))
        with pytest.raises(MapFormatError, match="checksum"):
            with open_map(path) as m:
                m.all()  # a page is only checked when read


def test_newer_version_refused(written):
    path, _ = written
    data = bytearray(path.read_bytes())
    struct.pack_into("<H", data, 8, 99)
    path.write_bytes(bytes(data))
    with pytest.raises(MapVersionError, match="newer map format"):
        open_map(path)


def forge(path, header: dict, directory: bytes = b"", pages: bytes = b"") -> None:
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    body = packer.compress(json.dumps(header).encode()) + packer.flush()
    prefix = struct.pack("<8sHHI", MAGIC, 1, 0, len(body)) + body
    path.write_bytes(prefix + struct.pack("<I", zlib.crc32(prefix)) + directory + pages)


def test_hostile_counts_do_not_allocate(tmp_path):
    """A stranger's file with consistent checksums but absurd counts is refused before any allocation."""
    base = {"pages": 0, "quantum": 0.1, "crs": "EPSG:32632", "labels": [{"name": "a", "code": 0, "count": 0}],
            "bounds": [0, 0, 1, 1], "count": 0, "format_version": 1}
    path = tmp_path / "evil.mapdb"
    forge(path, {**base, "pages": 10**12})
    with pytest.raises(MapFormatError, match="truncated"):
        open_map(path)
    # a page claiming 2**32-1 objects in a few bytes
    record = struct.pack("<qqIIIII", 0, 0, 10, 10, 2**32 - 1, 4, zlib.crc32(b"\0\0\0\0"))
    forge(path, {**base, "pages": 1, "directory_crc32": zlib.crc32(record)}, record, b"\0\0\0\0")
    with pytest.raises(MapFormatError, match="out-of-range"):
        open_map(path)
    # a plausible count whose runs do not add up
    record = struct.pack("<qqIIIII", 0, 0, 10, 10, 5, 4, zlib.crc32(b"\0\0\0\0"))
    forge(path, {**base, "pages": 1, "directory_crc32": zlib.crc32(record)}, record, b"\0\0\0\0")
    with open_map(path) as m, pytest.raises(MapFormatError):
        m.all()
    # a header that is JSON but not map metadata
    forge(path, {"hello": 1})
    with pytest.raises(MapFormatError, match="not valid map metadata"):
        open_map(path)
