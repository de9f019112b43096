"""The streaming map writer: chunks in, the very file write_map makes of them all out, in bounded memory.

``write_map`` of a few thousand objects cuts the whole map in memory; the streaming writer given a small
``memory_objects`` goes the other way (duplicates merged bucket by bucket from temporary files, cuts found
by histogram passes over files), so equal bytes check one against the other.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from mapdb import EmptyMapError, MapdbIOError, Objects
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import MapWriter, write_map, write_map_from_chunks

LABELS = ("building", "road_intersection", "park", "water")
CRS = "EPSG:32635"


@pytest.fixture(autouse=True)
def fixed_time(monkeypatch):
    """One creation time for every write, so that equal maps are equal files."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")


def clustered(n: int, seed: int = 0) -> Objects:
    """Objects in a few dense towns and sparse country, with same-label duplicates and shared positions."""
    rng = np.random.default_rng(seed)
    towns = rng.uniform(0, 20000, (5, 2))
    town = rng.integers(0, 5, n)
    near = rng.random(n) < 0.7
    xy = np.where(near[:, None], towns[town] + rng.normal(0, 300, (n, 2)), rng.uniform(0, 20000, (n, 2)))
    xy[: n // 20] = xy[n // 20: n // 10]  # a tenth of the objects share a position with another
    label = rng.integers(0, len(LABELS), n)
    area = np.where(label == 1, 0.0, rng.lognormal(5, 1.5, n))
    return Objects(385000 + xy[:, 0], 6671000 + xy[:, 1], label, area, LABELS, CRS)


def split(objects: Objects, cuts: list[int]) -> list[Objects]:
    edges = [0, *cuts, len(objects)]
    return [objects.take(np.arange(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def spill_dirs(directory) -> list[str]:
    return [name for name in os.listdir(directory) if name.endswith(".spill")]


def assert_same_file(tmp_path, objects: Objects, chunks: list[Objects], **options) -> bytes:
    """write_map of ``objects`` and the streaming writer of ``chunks`` give the same bytes; those bytes."""
    whole, streamed = tmp_path / "whole.mapdb", tmp_path / "streamed.mapdb"
    capacity = options.pop("page_capacity", 1024)
    n = write_map(whole, objects, page_capacity=capacity, metadata={"note": "same"})
    assert write_map_from_chunks(streamed, chunks, page_capacity=capacity, metadata={"note": "same"}, **options) == n
    assert streamed.read_bytes() == whole.read_bytes()
    assert spill_dirs(tmp_path) == []  # the temporary files are gone
    return whole.read_bytes()


def test_one_chunk_in_memory_is_write_map(tmp_path):
    objects = clustered(3000)
    assert_same_file(tmp_path, objects, [objects])


def test_several_chunks_spilled_give_the_same_file(tmp_path):
    objects = clustered(20000, seed=1)
    # 400 objects in memory: the objects go to a file, duplicates are merged in ~100 buckets, and the
    # map is cut through about 50 parts found by histogram passes before any part fits in memory.
    assert_same_file(tmp_path, objects, split(objects, [1, 4000, 4001, 13000]), memory_objects=400,
                     page_capacity=64)
    with open_map(tmp_path / "streamed.mapdb") as m:
        m.verify()
        assert m.metadata["merged_duplicates"] > 0
        assert m.metadata["note"] == "same"
        assert len(m) == len(np.unique(np.c_[np.rint(objects.x / 0.1), np.rint(objects.y / 0.1), objects.label],
                                       axis=0))


def test_chunk_order_does_not_matter(tmp_path):
    objects = clustered(6000, seed=2)
    reverse = split(objects, [1000, 2500, 5999])[::-1]
    assert_same_file(tmp_path, objects, reverse, memory_objects=500, page_capacity=100)


def test_a_single_object(tmp_path):
    one = Objects.from_names([500000.0], [6e6], ["park"], area=[1200.0], crs=CRS, labels=LABELS)
    data = assert_same_file(tmp_path, one, [Objects.empty(LABELS, CRS), one, Objects.empty(LABELS, CRS)],
                            memory_objects=1)
    assert len(data) > 0
    with open_map(tmp_path / "streamed.mapdb") as m:
        assert m.label_counts == {"park": 1} and m.page_count == 1


def test_cuts_on_tied_coordinates_and_piles(tmp_path):
    """Cuts of big parts fall between distinct coordinates as in memory: columns of equal x taller than the
    memory bound, a median tie between two breaks, and piles of every label at one position."""
    column = np.repeat(np.arange(6) * 10.0, 700)  # 6 columns of 700 objects: every median sits on a tie
    y = np.tile(np.arange(700) * 0.5, 6)
    pile_x, pile_y = np.full(4 * 40, 25.0), np.full(4 * 40, 100.0)  # 40 copies of each label at one spot
    x = 500000 + np.concatenate([column, pile_x])
    y = 6e6 + np.concatenate([y, pile_y])
    label = np.concatenate([np.arange(column.size) % 4, np.repeat(np.arange(4), 40)])
    area = np.concatenate([np.full(column.size, 50.0), np.linspace(1, 1000, 160)])
    objects = Objects(x, y, label, area, LABELS, CRS)
    assert_same_file(tmp_path, objects, split(objects, [700, 2100, 4200]), memory_objects=300, page_capacity=50)
    with open_map(tmp_path / "streamed.mapdb") as m:
        m.verify()
        pile = m.query_bbox(500025.0, 6000100.0, 500025.0, 6000100.0)
        assert sorted(pile.label.tolist()) == [0, 1, 2, 3]  # one object of each label kept: the largest
        largest = np.linspace(1, 1000, 160).reshape(4, 40).max(axis=1)
        np.testing.assert_allclose(pile.area[np.argsort(pile.label)], largest, rtol=0.045)


def test_wide_span_needs_several_histogram_passes(tmp_path):
    """Positions spread over 10^7 quanta with a dense core: a pass narrows the median to a bin that still
    holds more than the memory bound, so another pass follows."""
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.uniform(0, 1e6, 500), 500000 + rng.integers(0, 3, 3000) * 0.1])
    y = np.concatenate([rng.uniform(0, 1e3, 500), rng.uniform(0, 1e-3, 3000)])
    objects = Objects(300000 + x, 6e6 + y, rng.integers(0, 4, x.size), np.zeros(x.size), LABELS, CRS)
    assert_same_file(tmp_path, objects, split(objects, [500, 1700]), memory_objects=400, page_capacity=200)


def test_nothing_to_write(tmp_path):
    out = tmp_path / "empty.mapdb"
    with pytest.raises(EmptyMapError, match="no objects to write"):
        write_map_from_chunks(out, [])
    with pytest.raises(EmptyMapError, match="no objects to write"):
        write_map_from_chunks(out, [Objects.empty(LABELS, CRS), Objects.empty(LABELS)])
    with pytest.raises(EmptyMapError):
        write_map(out, Objects.empty(LABELS, CRS))
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("bad, problem", [
    (Objects.from_names([1.0], [2.0], ["park"], crs="EPSG:32632", labels=LABELS), "CRS EPSG:32632"),
    (Objects.from_names([1.0], [2.0], ["park"], crs=CRS, labels=LABELS[::-1]), "labels"),
    (Objects.from_names([1.0], [2.0], ["park"], crs=CRS, labels=("park", "lake")), "labels"),
    (Objects.from_names([1.0], [2.0], ["park"], labels=LABELS), "need a CRS"),
    (Objects.from_names([np.nan], [2.0], ["park"], crs=CRS, labels=LABELS), "non-finite"),
    (Objects.from_names([1e16], [2.0], ["park"], crs=CRS, labels=LABELS), "beyond"),
])
def test_a_bad_chunk_is_refused_and_the_old_map_kept(tmp_path, bad, problem):
    out = tmp_path / "m.mapdb"
    out.write_bytes(b"the old map")
    good = clustered(2000)
    with pytest.raises(ValueError, match=problem):
        write_map_from_chunks(out, [good, bad], memory_objects=500)  # the good chunk went to a file already
    assert out.read_bytes() == b"the old map"
    assert spill_dirs(tmp_path) == [] and sorted(os.listdir(tmp_path)) == ["m.mapdb"]


def test_what_write_map_refuses_the_writer_refuses_at_the_first_chunk(tmp_path):
    lonlat = Objects.from_names([10.0], [50.0], ["park"], crs="EPSG:4326")
    with MapWriter(tmp_path / "m.mapdb") as writer, pytest.raises(ValueError, match="not a projected CRS|projected"):
        writer.add(lonlat)
    with pytest.raises(ValueError, match="projected"):
        write_map(tmp_path / "m.mapdb", lonlat)
    many = Objects(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), tuple(f"l{i}" for i in range(256)), CRS)
    with pytest.raises(ValueError, match="at most 255 labels"):
        write_map_from_chunks(tmp_path / "m.mapdb", [many])
    with pytest.raises(ValueError, match="quantum"):
        MapWriter(tmp_path / "m.mapdb", quantum=0.0)
    assert os.listdir(tmp_path) == []


def test_temporary_files_that_cannot_be_written_are_one_error(tmp_path):
    """A place where the spill cannot go (here a file where the directory should be) is a MapdbIOError
    naming the output, with nothing left behind."""
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    with pytest.raises(MapdbIOError, match="cannot write temporary files"):
        write_map_from_chunks(blocker / "m.mapdb", [clustered(2000)], memory_objects=500)
    assert sorted(os.listdir(tmp_path)) == ["not_a_dir"]


def test_source_date_epoch_fixes_the_creation_time(tmp_path):
    path = tmp_path / "m.mapdb"
    write_map(path, clustered(100))
    with open_map(path) as m:
        assert m.metadata["created"] == "2023-11-14T22:13:20+00:00"
