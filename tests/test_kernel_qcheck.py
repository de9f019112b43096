"""The kernel's CRC-32 (``_kernel_qcheck.c``) against ``zlib.crc32``, and the quads blocks a stored-index lookup
checks in the kernel: the same flags Python's sections keep, the same error for a bad block, raised before its
records are used; wrong calls raise TypeError or ValueError."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from mapdb.errors import MapFormatError
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match import _kernel
from mapdb.match.index.stored import StoredQuadIndex, build_index, index_path
from mapdb.match.quads import canonical_quads
from mapdb.objects import Objects


def test_crc32_is_zlibs_on_random_and_edge_inputs() -> None:
    rng = np.random.default_rng(7)
    sizes = [0, 1, 2, 7, 8, 9, 15, 16, 17, 63, 64, 4095, 4096, 4097, 12_345]
    for n in sizes + rng.integers(0, 20_000, 30).tolist():
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        for start in (0, 1, 0xFFFFFFFF, int(rng.integers(0, 2**32))):
            assert _kernel.qcheck_crc32(data, start) == zlib.crc32(data, start)
    for data in (b"\x00" * 5000, b"\xff" * 5000, bytes(range(256)) * 3):
        assert _kernel.qcheck_crc32(data) == zlib.crc32(data)
    # Any buffer, any alignment: an array's bytes and a view starting at an odd byte.
    array = rng.integers(0, 2**62, 1000, dtype=np.int64)
    assert _kernel.qcheck_crc32(array) == zlib.crc32(array.tobytes())
    assert _kernel.qcheck_crc32(memoryview(array.tobytes())[3:]) == zlib.crc32(array.tobytes()[3:])
    # Continued: the CRC of a whole is the CRC of its second part started from the first part's.
    whole = array.tobytes()
    assert _kernel.qcheck_crc32(whole[1001:], _kernel.qcheck_crc32(whole[:1001])) == zlib.crc32(whole)


def test_crc32_wrong_calls_raise() -> None:
    with pytest.raises(TypeError):
        _kernel.qcheck_crc32("text")
    with pytest.raises(TypeError):
        _kernel.qcheck_crc32(b"x", 1.5)
    for start in (-1, 2**32, 2**70):
        with pytest.raises(ValueError):
            _kernel.qcheck_crc32(b"x", start)
    with pytest.raises((TypeError, ValueError)):
        _kernel.qcheck_crc32(np.arange(10)[::2])  # not contiguous


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """A map of 1500 objects and its index (written in the test)."""
    rng = np.random.default_rng(3)
    n = 1500
    objects = Objects(500_000 + rng.uniform(0, 700, n), 4_650_000 + rng.uniform(0, 500, n),
                      rng.choice(3, n, p=[0.7, 0.25, 0.05]), np.zeros(n), ("building", "road_intersection", "park"),
                      "EPSG:32631")
    path = tmp_path_factory.mktemp("qcheck") / "small.mapdb"
    write_map(path, objects, page_capacity=128)
    build_index(path)
    return path


def _queries(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Invariants and labels of stored quads spread over the whole quads section."""
    with StoredQuadIndex(index_path(path)) as ix:
        at = np.linspace(0, ix.n_quads - 1, 40).astype(np.int64)
        ids = np.concatenate([ix.quads(int(a), int(a) + 1) for a in at])
        _, inv, _ = canonical_quads(ix.coordinates(ids))
        with open_map(path) as m:
            labels = m.all().label[ids]
    return inv, labels


def test_the_kernel_marks_the_quads_blocks_it_checks(small: Path) -> None:
    inv, labels = _queries(small)
    with StoredQuadIndex(index_path(small)) as ix:
        quads = ix._sections["quads"]
        assert quads.crcs.size > 1 and not quads.checked.any()
        ix._audited_at[:] = True  # no audit: every quads block read is the kernel's
        ix.lookup(inv, labels, 1e-6, 4)
        marked = np.flatnonzero(quads.checked)
        assert marked.size > 1
        # Each block marked is one whose checksum holds, and the lookup's records lie in marked blocks only.
        for b in marked.tolist():
            assert zlib.crc32(quads.raw[b * 4096 : (b + 1) * 4096].tobytes()) == int(quads.crcs[b])
        before = quads.checked.copy()
        ix.lookup(inv, labels, 1e-6, 4)  # warm: nothing more to check
        assert np.array_equal(before, quads.checked)
        ix.verify()
        assert quads.checked.all()


def _corrupt_block(path: Path, target: Path, block: int) -> None:
    data = bytearray(index_path(path).read_bytes())
    header = json.loads(bytes(data[struct.unpack_from("<Q", data, 12)[0] :]))
    data[header["sections"]["quads"]["offset"] + block * 4096 + 5] ^= 0x20
    target.write_bytes(bytes(data))


def test_a_corrupt_quads_block_the_kernel_reaches_fails_with_pythons_message(small: Path, tmp_path: Path) -> None:
    inv, labels = _queries(small)
    with StoredQuadIndex(index_path(small)) as ix:
        last = ix._sections["quads"].crcs.size - 1
    target = tmp_path / "copy.qidx"
    _corrupt_block(small, target, last)
    with StoredQuadIndex(target) as ix:
        ix._audited_at[:] = True  # the kernel, not the audit, reads the block first
        with pytest.raises(MapFormatError) as exc:
            ix.lookup(inv, labels, 1e-6, 4)
        assert str(exc.value) == f"{target}: quads block {last} checksum mismatch (file is corrupt)"
        assert not ix._sections["quads"].checked[last]
        with pytest.raises(MapFormatError, match=f"quads block {last} checksum mismatch"):  # and again
            ix.lookup(inv, labels, 1e-6, 4)
        with pytest.raises(MapFormatError) as again:  # Python's check of the same block says the same
            ix.verify()
        assert str(again.value) == str(exc.value)


def test_wrong_tables_raise(small: Path) -> None:
    inv, labels = _queries(small)
    with StoredQuadIndex(index_path(small)) as ix:
        t = ix._tables
        lk = np.zeros(1, np.int64)
        args = (inv[:1], np.ones(1), np.ones(1), lk, 3, 100)
        with pytest.raises(ValueError, match="writable"):
            flags = t[1].copy()
            flags.flags.writeable = False
            _kernel.stored_lookup(t[:1] + (flags,) + t[2:], *args)
        with pytest.raises(ValueError, match="disagree"):
            _kernel.stored_lookup(t[:15] + (t[15][:-1],) + t[16:], *args)
        with pytest.raises(TypeError):
            _kernel.stored_lookup(t[:15] + (t[15].astype(np.int64),) + t[16:], *args)
        with pytest.raises(TypeError):
            _kernel.stored_lookup(t[:15] + t[16:], *args)
