"""The map file: round trips, queries against brute force, and every kind of damaged file."""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapdb import EmptyMapError, MapdbIOError, MapFormatError, MapVersionError, Objects
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map

LABELS = ("building", "road_intersection", "park", "water")
SOURCE = {"name": "x.osm.pbf", "kind": "osm", "size": 10, "sha256": "0" * 64, "objects": 5000}


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
    write_map(path, objects, page_capacity=256, metadata={"sources": [SOURCE]})
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
        assert m.metadata["sources"] == [SOURCE]
        assert m.crs == "EPSG:32635"


def test_other_quantum_and_single_object(tmp_path):
    one = Objects.from_names([500123.456], [4e6], ["water"], area=[1234.0], crs="EPSG:32632")
    write_map(tmp_path / "one.mapdb", one, quantum=1.0)
    with open_map(tmp_path / "one.mapdb") as m:
        o = m.all()
        assert (o.x[0], o.y[0]) == (500123.0, 4e6)
        assert o.names().tolist() == ["water"]


def test_duplicates_on_one_spot_are_merged(tmp_path):
    """One object per label and quantized position: the largest area is kept and the others counted."""
    n = 3000
    label = np.r_[np.zeros(n, int), [1, 2]]  # a pile of buildings, and a park and a water at the same spot
    area = np.r_[np.arange(n, dtype=float), [5.0, 0.0]]
    x = np.r_[np.full(n, 500000.0), 500000.04, 499999.96]  # same quantum of 0.1 m
    o = Objects(x, np.full(n + 2, 4e6), label, area, ("building", "park", "water"), "EPSG:32632")
    assert write_map(tmp_path / "spot.mapdb", o, page_capacity=1) == 3
    with open_map(tmp_path / "spot.mapdb") as m:
        found = m.query_radius(500000.0, 4e6, 1.0)
        assert sorted(found.names().tolist()) == ["building", "park", "water"]
        assert abs(found.area[found.label == 0][0] / (n - 1) - 1) < 0.045  # the largest building
        assert m.metadata["merged_duplicates"] == n - 1 and len(m) == 3
        assert m.page_count == 1  # a pile at one position is never split, whatever the page capacity


def test_pages_share_no_position_and_respect_density(tmp_path):
    """Ties at the median and a dense cluster: cuts fall between distinct coordinates, dense pages are cut."""
    rng = np.random.default_rng(3)
    gx, gy = np.meshgrid(np.arange(40), np.arange(40))  # a 40 x 40 grid of 1 m: many objects share x and y
    cluster = rng.uniform(-0.5, 0.5, (2000, 2))  # 2000 objects within one square metre (1 cm quantum)
    x = np.r_[600000.0 + gx.ravel() * 1.0, 600100.0 + cluster[:, 0]]
    y = np.r_[5e6 + gy.ravel() * 1.0, 5e6 + cluster[:, 1]]
    o = Objects(x, y, np.zeros(x.size, int), np.zeros(x.size), ("building",), "EPSG:32632")
    written = write_map(tmp_path / "dense.mapdb", o, quantum=0.01, page_capacity=300)
    with open_map(tmp_path / "dense.mapdb") as m:
        assert len(m.all()) == written == len(m)
        t = m._table  # the directory the reader checked: boxes disjoint, dense pages small
        area = (t["ex"] + 1.0) * (t["ey"] + 1.0) * 0.01**2
        assert np.all((t["count"] <= 255) | (t["count"] <= area))
        assert t["count"].max() <= 300
        m.verify()


def test_fifo_and_directory_are_not_maps(tmp_path):
    """A FIFO would block open() forever; a directory is not a file: both are refused at once."""
    fifo = tmp_path / "pipe.mapdb"
    os.mkfifo(fifo)
    with pytest.raises(MapdbIOError, match="pipe.mapdb: is a FIFO, not a map file"):
        open_map(fifo)
    with pytest.raises(MapdbIOError, match="is a directory"):
        open_map(tmp_path)


def test_writer_refuses_what_the_reader_would(tmp_path):
    o = random_objects(50)
    with pytest.raises(ValueError, match="sources"):
        write_map(tmp_path / "a.mapdb", o, metadata={"sources": [{"name": "x"}]})
    with pytest.raises(ValueError, match="not a projected CRS"):
        write_map(tmp_path / "a.mapdb", Objects(o.x / 1e5, o.y / 1e6, o.label, o.area, o.labels, "EPSG:4326"))
    with pytest.raises(ValueError, match="label 1"):
        write_map(tmp_path / "a.mapdb", Objects(o.x, o.y, o.label, o.area, ("a", "b\nc", "d", "e"), o.crs))
    with pytest.raises(ValueError, match="quanta"):
        write_map(tmp_path / "a.mapdb", Objects(o.x * 1e12, o.y, o.label, o.area, o.labels, o.crs), quantum=0.001)
    assert not any(tmp_path.iterdir())


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


def with_version(data: bytes, version: int, fix_crc: bool = True) -> bytes:
    out = bytearray(data)
    struct.pack_into("<H", out, 8, version)
    if fix_crc:
        end = 16 + struct.unpack_from("<I", out, 12)[0]
        struct.pack_into("<I", out, end, zlib.crc32(bytes(out[:end])))
    return bytes(out)


def test_versions(written):
    """Newer only when plausible: a version 3..255 whose header checksum holds; else damage or not a map.
    Version 2 (elevation) is read: a version 1 header under it breaks the header's version rule."""
    path, _ = written
    data = path.read_bytes()
    path.write_bytes(with_version(data, 2))
    with pytest.raises(MapFormatError, match="'format_version' must be 2"):
        open_map(path)
    for version in (3, 99, 255):
        path.write_bytes(with_version(data, version))
        with pytest.raises(MapVersionError, match=f"newer map format \\(version {version}\\)"):
            open_map(path)
    path.write_bytes(with_version(data, 3, fix_crc=False))  # a flipped bit in the version field
    with pytest.raises(MapFormatError, match="checksum mismatch") as caught:
        open_map(path)
    assert not isinstance(caught.value, MapVersionError)
    for version in (0, 256, 65535):
        path.write_bytes(with_version(data, version))
        with pytest.raises(MapFormatError, match=f"not a valid map \\(format version {version}\\)"):
            open_map(path)
