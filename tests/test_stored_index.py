"""The stored lost-in-space quad index: the same quads as QuadIndex, lookups equal to brute force, hostile files."""

from __future__ import annotations

import json
import os
import struct
import zlib

import numpy as np
import pytest
import storedrefs
from click.testing import CliRunner
from mapdb_cli.index import index as index_command

from mapdb._scipy import cKDTree
from mapdb.errors import MapdbIOError, MapFormatError
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match.index import build as index_build
from mapdb.match.index import generate as index_generate
from mapdb.match.index.layout import QUAD_NEIGHBOURS, QUAD_TRIPLES
from mapdb.match.index.stored import StoredQuadIndex, build_index, index_path, open_index
from mapdb.match.nearest import nearest_others
from mapdb.match.quads import QuadIndex, canonical_quads, label_keys, neighbour_quads
from mapdb.objects import Objects

LABELS = ("building", "road_intersection", "park")


def _objects(n: int = 1500, seed: int = 0) -> Objects:
    rng = np.random.default_rng(seed)
    # Mostly buildings, as real maps are: some label combinations are common, most are rare.
    label = rng.choice(3, n, p=[0.7, 0.25, 0.05])
    return Objects(500_000 + rng.uniform(0, 700, n), 4_650_000 + rng.uniform(0, 500, n), label, np.zeros(n),
                   LABELS, "EPSG:32631")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A map of 1500 objects in 12 pages and its index, built in many chunks, blocks and sort buckets."""
    tmp = tmp_path_factory.mktemp("qidx")
    path = tmp / "small.mapdb"
    write_map(path, _objects(), page_capacity=128)
    return path, _build_in_pieces(path)


def _build_in_pieces(path, output=None, workers=1) -> dict:
    """Build with small pieces, so that a small map goes through every path of a big build: a sample (not
    every anchor) choosing cells and buckets, several chunks of anchors and sort buckets."""
    patch = pytest.MonkeyPatch()
    for module, name, value in ((index_generate, "_SAMPLE_QUADS", 20_000), (index_build, "_BUCKET_QUADS", 9_000),
                                (index_build, "_CHUNK_ANCHORS", 300), (index_generate, "_BLOCK_ANCHORS", 70)):
        patch.setattr(module, name, value)
    try:
        return build_index(path, output, workers=workers)
    finally:
        patch.undo()


def _map_quads(objects: Objects, neighbours: int | None = None):
    """The whole-map quads as QuadIndex defines them, of every triple of ``neighbours``, by default those a stored
    index holds (each object with the triples ``QUAD_TRIPLES`` of its 5 nearest): ids in canonical order,
    invariants, label keys."""
    z = objects.x + 1j * objects.y
    xy = np.column_stack([objects.x, objects.y])
    if neighbours is None:
        nn = nearest_others(cKDTree(xy), xy, np.arange(len(xy)), QUAD_NEIGHBOURS)
        q = np.concatenate([np.repeat(np.arange(len(xy)), len(QUAD_TRIPLES))[:, None],
                            nn[:, np.array(QUAD_TRIPLES)].reshape(-1, 3)], axis=1)
        q = np.unique(np.sort(q, axis=1), axis=0)
    else:
        q = neighbour_quads(xy, neighbours)
    q = q[np.abs(z[q] - z[q[:, :1]]).max(axis=1) > 0]
    order, inv, _ = canonical_quads(z[q])
    ids = np.take_along_axis(q, order, axis=1)
    return ids, inv, label_keys(objects.label[ids], len(objects.labels))


def test_index_holds_exactly_the_quads_of_the_5_nearest_it_documents(small) -> None:
    path, summary = small
    with open_map(path) as m, open_index(index_path(path), m) as ix:
        objects = m.all()
        stored = ix.quads()
        assert ix.n_objects == len(objects) and ix.neighbours == 8
        # Ids resolve to exactly the map's coordinates (bit for bit), so invariants are QuadIndex's.
        assert np.array_equal(ix.coordinates(np.arange(len(objects))), objects.x + 1j * objects.y)
    ids, _, _ = _map_quads(objects)
    assert summary["quads"] == len(stored) == len(ids)
    assert {tuple(r) for r in stored.tolist()} == {tuple(r) for r in ids.tolist()}
    # ... every one of them a quad of the matcher's 8 neighbours (a ninth of those: each object's closest) ...
    all_ids, _, _ = _map_quads(objects, 8)
    assert {tuple(r) for r in stored.tolist()} < {tuple(r) for r in all_ids.tolist()}
    assert 5 * len(stored) < len(all_ids)
    # ... and in QuadIndex's canonical order: its stored coordinates (of all triples of the 5 nearest), mapped
    # back to ids.
    qi = QuadIndex(objects, QUAD_NEIGHBOURS)
    where = {complex(v): i for i, v in enumerate((objects.x + 1j * objects.y).tolist())}
    qi_ids = np.vectorize(lambda v: where[complex(v)])(qi.quad_z)
    assert {tuple(r) for r in stored.tolist()} < {tuple(r) for r in qi_ids.tolist()}


def _queries(objects: Objects, m: int = 400, seed: int = 1):
    ids, inv, _ = _map_quads(objects)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(ids), m, replace=False)
    labels = objects.label[ids[pick]]
    # Radii from tiny to the matcher's largest; some queries far from any quad, some of a label
    # combination no quad has.
    query = inv[pick] + rng.normal(0, 0.03, (m, 4))
    radius = np.exp(rng.uniform(np.log(0.002), np.log(0.3), m))
    labels[:5] = [2, 2, 2, 2]
    return query, labels, radius


def _brute_force(objects: Objects, query, labels, radius):
    ids, inv, keys = _map_quads(objects)
    qkeys = label_keys(labels, len(objects.labels))
    hits = []
    for i in range(len(query)):
        sel = np.flatnonzero(keys == qkeys[i])
        d = np.sqrt(((inv[sel] - query[i]) ** 2).sum(axis=1))
        hits.append(sorted((float(dd), tuple(ids[j])) for dd, j in zip(d[d <= radius[i]], sel[d <= radius[i]])))
    return hits


def test_lookup_equals_brute_force_within_the_clamped_radius(small) -> None:
    path, _ = small
    with open_map(path) as m, StoredQuadIndex.for_map(m) as ix:
        objects = m.all()
        query, labels, radius = _queries(objects)
        cell = ix.cell_size(labels)
        assert np.all(cell[5:] > 0) and 0 < np.mean(radius > cell) < 1  # some lookups are clamped, some not
        effective = np.minimum(radius, cell)
        row, ids, dist = ix.lookup(query, labels, radius, 10**6, return_distance=True)
        row3, ids3, dist3 = ix.lookup(query, labels, radius, 3, return_distance=True)
    truth = _brute_force(objects, query, labels, effective)
    assert sum(map(len, truth)) > 500
    got = {(int(r), tuple(h)) for r, h in zip(row, ids.tolist())}
    assert got == {(i, h) for i, hits in enumerate(truth) for _, h in hits}
    assert np.all(np.diff(row) >= 0) and not any(truth[:5])
    # At most k per query, the nearest ones.
    for i, hits in enumerate(truth):
        mine = np.sort(dist3[row3 == i])
        assert np.allclose(mine, [d for d, _ in hits[:3]], rtol=0, atol=1e-12)
    # Where the radius is within the cell, nothing is clamped: brute force with the radius as given.
    full = radius <= cell
    unclamped = _brute_force(objects, query[full], labels[full], radius[full])
    assert [len(h) for h in unclamped] == [int(np.sum(row == i)) for i in np.flatnonzero(full)]


def test_a_lookup_reads_only_the_cells_its_ball_reaches() -> None:
    # A query at a cell's centre with radius 0.9 cells: of the 81 cells around it, those differing in at
    # most 3 coordinates (each 0.5 cells away; four such make 1.0 > 0.9): 1 + 8 + 24 + 32.
    cell = np.array([0.1])
    q = np.array([[0.05, 0.15, 0.25, 0.35]]) - 1.0 + np.array([[10, 10, 10, 10]]) * 0.1
    which, rel, keys = storedrefs.query_cells(q, np.array([0.09]), cell, np.array([3]), 12, 256)
    assert which.tolist() == [0] * 65 and np.unique(keys).size == 65
    # The query's place relative to each cell's corner, in 1/256ths of the cell.
    assert set(np.round(rel.ravel(), 3).tolist()) <= {-128.0, 128.0, 384.0}
    assert np.sum(np.all(np.round(rel, 3) == 128.0, axis=1)) == 1


def test_lookup_of_nothing_and_bad_queries(small) -> None:
    path, _ = small
    with open_index(index_path(path)) as ix:
        row, ids = ix.lookup(np.zeros((0, 4)), np.zeros((0, 4), int), 0.1, 16)
        assert row.shape == (0,) and ids.shape == (0, 4)
        # NaN invariants, negative radius, label codes outside the table: no hits, no error.
        row, _ = ix.lookup(np.array([[np.nan, 0, 0.5, 0.1], [0.2, 0.1, 0.5, 0.1], [0.2, 0.1, 0.5, 0.1]]),
                           np.array([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 7, 0]]), np.array([0.1, -1.0, 0.1]), 16)
        assert row.size == 0
        with pytest.raises(IndexError):
            ix.coordinates(np.array([ix.n_objects]))


def test_a_map_too_small_for_quads_gets_an_empty_index(tmp_path) -> None:
    path = tmp_path / "three.mapdb"
    write_map(path, Objects(np.array([0.0, 10.0, 0.0]) + 500_000, np.array([0.0, 0.0, 10.0]) + 4_650_000,
                            np.zeros(3, int), np.zeros(3), LABELS, "EPSG:32631"))
    # What a killed build left beside the output (its process is gone) is removed by the next build.
    stale = tmp_path / ".three.mapdb.qidx.999999999.abc.build"
    stale.mkdir()
    (stale / "bucket0000").write_bytes(b"x" * 100)
    assert build_index(path)["quads"] == 0
    assert not stale.exists() and sorted(os.listdir(tmp_path)) == ["three.mapdb", "three.mapdb.qidx"]
    with open_map(path) as m, StoredQuadIndex.for_map(m) as ix:
        ix.verify()
        row, ids = ix.lookup(np.full((1, 4), 0.3), np.zeros((1, 4), int), 0.1, 16)
        assert row.size == 0 and np.allclose(ix.coordinates(np.arange(3)).real, m.all().x)


def test_build_is_deterministic_and_for_map_finds_nothing_without_a_sidecar(small, tmp_path) -> None:
    path, _ = small
    again = tmp_path / "again.qidx"
    _build_in_pieces(path, again, workers=2)  # in two processes: the same file
    a, b = index_path(path).read_bytes(), again.read_bytes()
    # Only the creation time in the header may differ: every section is the same.
    with open_index(again) as ix:
        end = ix.header["_header_offset"]
    assert a[64:end] == b[64:end]
    with open_map(path) as m:
        assert StoredQuadIndex.for_map(m, tmp_path / "none.qidx") is None
        assert StoredQuadIndex.for_map(MemoryMap(m.all())) is None


def test_with_source_date_epoch_two_builds_are_byte_identical(small, tmp_path, monkeypatch) -> None:
    path, _ = small
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    first, second = tmp_path / "first.qidx", tmp_path / "second.qidx"
    build_index(path, first)
    build_index(path, second)
    assert first.read_bytes() == second.read_bytes()
    with open_index(first) as ix:
        assert ix.header["created"] == "2023-11-14T22:13:20+00:00"


# --------------------------------------------------------------------------------------------- hostile files


def _copy(small, tmp_path):
    path, _ = small
    target = tmp_path / "copy.qidx"
    target.write_bytes(index_path(path).read_bytes())
    return path, target


def _rewrite(target, edit_header=None, patch=None, raw=None) -> None:
    """Change an index as a forger would: header values or section bytes, every checksum made right again."""
    data = bytearray(target.read_bytes())
    _, version, flags, h_off, h_len, _ = struct.unpack_from("<8sHHQII", data)
    header = json.loads(bytes(data[h_off : h_off + h_len]))
    if patch is not None:
        name, position, value = patch
        sec = header["sections"][name]
        item = np.dtype(sec["dtype"])
        data[sec["offset"] + position * item.itemsize : sec["offset"] + (position + 1) * item.itemsize] = \
            np.array([value], item).tobytes()
        crc = header["sections"]["crc"]
        table = np.frombuffer(bytes(data[crc["offset"] : crc["offset"] + crc["length"]]), "<u4").copy()
        for s in header["sections"].values():
            if "first_block" in s:
                for b in range(-(-s["length"] // 4096)):
                    start, end = s["offset"] + b * 4096, s["offset"] + s["length"]
                    table[s["first_block"] + b] = zlib.crc32(data[start : min(start + 4096, end)])
        data[crc["offset"] : crc["offset"] + crc["length"]] = table.tobytes()
        header["crc_crc32"] = zlib.crc32(table.tobytes())
    if edit_header is not None:
        edit_header(header)
    raw = json.dumps(header).encode() if raw is None else raw
    del data[h_off:]
    data += raw
    prefix = struct.pack("<8sHHQII", b"\x89MAPDBQX", version, flags, h_off, len(raw), zlib.crc32(raw))
    data[:32] = prefix + struct.pack("<I", zlib.crc32(prefix))
    target.write_bytes(bytes(data))


def _one_line_error(exc: pytest.ExceptionInfo, *words: str) -> None:
    message = str(exc.value)
    assert "\n" not in message and "copy.qidx" in message
    assert all(w in message for w in words), message


def test_truncated_and_foreign_files_are_refused(small, tmp_path) -> None:
    _, target = _copy(small, tmp_path)
    data = target.read_bytes()
    target.write_bytes(data[:-10])
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc, "truncated")
    target.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc, "truncated")
    target.write_bytes(b"PK\x03\x04" + data[4:])
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc, "not a mapdb quad index")
    target.write_bytes(b"")
    with pytest.raises(MapFormatError):
        open_index(target)
    with pytest.raises(MapdbIOError, match="no such quad index"):
        open_index(tmp_path / "missing.qidx")


def test_corrupt_bytes_fail_their_checksum(small, tmp_path) -> None:
    _, target = _copy(small, tmp_path)
    data = bytearray(target.read_bytes())
    h_off = struct.unpack_from("<Q", data, 12)[0]
    header = json.loads(bytes(data[h_off:]))
    broken = bytearray(data)
    broken[h_off + 20] ^= 0x01  # the header
    target.write_bytes(bytes(broken))
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc, "header checksum mismatch")
    # A section byte: opening (which reads no section but the fence) succeeds; every read of the block fails.
    anchor = header["sections"]["quads"]
    broken = bytearray(data)
    broken[anchor["offset"] + 8] ^= 0x40
    target.write_bytes(bytes(broken))
    with open_index(target) as ix:
        with pytest.raises(MapFormatError) as exc:
            ix.verify()
        _one_line_error(exc, "quads block 0 checksum mismatch")
        with pytest.raises(MapFormatError, match="checksum mismatch"):
            ix.quads(0, 10)


def test_a_lookup_reading_a_corrupt_quads_block_fails(small, tmp_path) -> None:
    # Lookups read the records of the cells they reach: that read is checked.
    path, target = _copy(small, tmp_path)
    with open_map(path) as m, StoredQuadIndex.for_map(m) as ix:
        ids = ix.quads(0, 8)
        _, inv, _ = canonical_quads(ix.coordinates(ids))
        labels = m.all().label[ids]
    data = bytearray(target.read_bytes())
    header = json.loads(bytes(data[struct.unpack_from("<Q", data, 12)[0] :]))
    data[header["sections"]["quads"]["offset"] + 4] ^= 0x10
    target.write_bytes(bytes(data))
    with open_index(target) as ix:
        with pytest.raises(MapFormatError) as exc:
            ix.lookup(inv, labels, 1e-9, 16)
        _one_line_error(exc, "quads block 0 checksum mismatch")


def test_an_index_of_another_map_is_refused(small, tmp_path) -> None:
    path, target = _copy(small, tmp_path)
    other = tmp_path / "other.mapdb"
    write_map(other, _objects(seed=5), page_capacity=128)
    # The same objects written again (another header: creation time, metadata) is another map too.
    same = tmp_path / "same.mapdb"
    with open_map(path) as m:
        write_map(same, m.all(), page_capacity=128, metadata={"note": "rewritten"})
    for map_path in (other, same):
        with open_map(map_path) as m:
            with pytest.raises(MapFormatError) as exc:
                open_index(target, m)
            _one_line_error(exc, "another map", "mapdb index")


@pytest.mark.parametrize("edit", [
    lambda h: h.update(quads=10**12),
    lambda h: h.update(objects=10**11),
    lambda h: h.update(cells=h["quads"] + 1),
    lambda h: h["sections"]["quads"].update(offset=10**15),
    lambda h: h["sections"]["dir_data"].update(offset=h["sections"]["quads"]["offset"]),
    lambda h: h.update(pages=10**12),
    lambda h: h.update(nb_bytes=10**15),
    lambda h: h.update(record_bytes=8),
    lambda h: h.update(quad_neighbours=9),
    lambda h: h.update(neighbours=40),
    lambda h: h.update(neighbours=3000),  # counted, not listed: listing its triples took 25 s and then ran out
    lambda h: h.update(combos=[[0, 1e-9]]),
    lambda h: h.update(format_version=1, sections=[]),
    lambda h: h.update(quads=float("inf")),
    lambda h: h.update(combos=[[1]]),
])
def test_absurd_counts_are_refused_before_any_allocation(small, tmp_path, edit) -> None:
    _, target = _copy(small, tmp_path)
    _rewrite(target, edit_header=edit)
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc)


def test_a_header_nested_past_the_parser_is_refused(small, tmp_path) -> None:
    _, target = _copy(small, tmp_path)
    _rewrite(target, raw=b"[" * 200_000 + b"]" * 200_000)
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc, "not JSON")


@pytest.mark.parametrize("patch", [("quads", 3, 255), ("nb_width", 0, 60), ("nb_start", 1, 10**9),
                                   ("dir_data", 0, 60), ("dir_data", 1, 40)])
def test_forged_ids_and_ranges_raise_instead_of_reading_past_arrays(small, tmp_path, patch) -> None:
    path, target = _copy(small, tmp_path)
    _rewrite(target, patch=patch)
    with open_map(path) as m, open_index(index_path(path)) as good:
        objects = m.all()
        # The first stored quad looked up: its cell is the directory's first.
        first = good.quads(0, 1)
        _, inv, _ = canonical_quads(good.coordinates(first))
    with open_index(target) as ix:
        ix.verify()  # the forger made the checksums right
        with pytest.raises(MapFormatError) as exc:
            ix.lookup(inv, objects.label[first], 0.001, 16)
            ix.quads()
        _one_line_error(exc, "corrupt")


def test_a_forged_fence_or_directory_out_of_order_is_refused(small, tmp_path) -> None:
    path, target = _copy(small, tmp_path)
    _rewrite(target, patch=("fence", 4, 0))  # the second page's key: no longer ascending, refused when opened
    with pytest.raises(MapFormatError) as exc:
        open_index(target)
    _one_line_error(exc, "fence out of order")
    _, target = _copy(small, tmp_path)
    with open_index(target) as ix:
        second = ix.header["sections"]["fence"]
        page_bytes = int(np.frombuffer(target.read_bytes()[second["offset"] : second["offset"] + 64], "<u8")[7])
    # The second page's gap width made 0: its cells no longer ascend (its length no longer matches, either).
    _rewrite(target, patch=("dir_data", page_bytes, 0))
    with open_map(path) as m:
        query, labels, radius = _queries(m.all())
    with open_index(target) as ix, pytest.raises(MapFormatError) as exc:
        ix.lookup(query, labels, radius, 16)
        ix._directory.decode(np.arange(ix.header["pages"]))
    _one_line_error(exc, "directory page out of range")


# --------------------------------------------------------------------------------------------- command line


def test_cli_writes_the_sidecar(small, tmp_path) -> None:
    path, _ = small
    target = tmp_path / "m.mapdb"
    target.write_bytes(path.read_bytes())
    result = CliRunner().invoke(index_command, [str(target), "--quiet"])
    assert result.exit_code == 0, result.output
    assert index_path(target).is_file()
    assert "quads" in result.output
    with open_map(target) as m, StoredQuadIndex.for_map(m) as ix:
        assert ix.n_quads > 0
    out = tmp_path / "elsewhere.qidx"
    result = CliRunner().invoke(index_command, [str(target), "-o", str(out), "--json", "--neighbours", "6"])
    assert result.exit_code == 0, result.output
    facts = json.loads(result.stdout)
    assert facts["output"] == str(out) and facts["neighbours"] == 6 and out.is_file()


def test_cli_errors_leave_no_file(tmp_path) -> None:
    bad = tmp_path / "bad.mapdb"
    bad.write_bytes(b"\x89MAPDB\r\n" + b"\x00" * 40)
    for args in ([str(bad)], [str(tmp_path / "missing.mapdb")], [str(bad), "-o", str(bad)]):
        result = CliRunner().invoke(index_command, args)
        assert result.exit_code == 1
        assert result.output.startswith("mapdb: error: ") and result.output.count("\n") == 1, result.output
    assert sorted(os.listdir(tmp_path)) == ["bad.mapdb"]


# --------------------------------------------------------------------------------------------- the document


def test_docs_index_format_lists_exactly_the_header_and_sections_written(small) -> None:
    """``docs/index_format.md`` and the writer agree: its version, every header key (``map.*`` the binding
    section's), every section; a key added to one and not the other fails here."""
    import re
    from pathlib import Path

    from mapdb.match.index.binding import IDENTITY_KEYS
    from mapdb.match.index.layout import INDEX_VERSION, SECTIONS

    doc = (Path(__file__).resolve().parents[1] / "docs" / "index_format.md").read_text()
    assert doc.startswith(f"# The lost-in-space quad index file, format version {INDEX_VERSION}\n")
    header_part = doc[doc.index("## Header (JSON)") : doc.index("## Sections")]
    documented = {key for row in re.findall(r"^\| (.+?) \|", header_part, re.M)
                  for key in re.findall(r"`([a-z_0-9.]+)`", row)} - {"key"}
    path, _ = small
    with open_index(index_path(path)) as ix:
        header = {k: v for k, v in ix.header.items() if not k.startswith("_")}
    written = set(header) | {f"map.{key}" for key in header["map"]}
    # ``blocks`` is written only for a map with blocks (tests/test_index_conformance.py reads it there).
    assert "blocks" not in written and documented == written | {"blocks"}
    assert set(header["map"]) == set(IDENTITY_KEYS)
    sections_part = doc[doc.index("## Sections") : doc.index("**A quad**")]
    assert set(re.findall(r"^\| `([a-z_]+)` \|", sections_part, re.M)) == set(SECTIONS) | {"crc"} == \
        set(header["sections"])
