"""The kernel's stored-index lookup (``_kernel_stored.c``) against the numpy code it replaced (tests/storedrefs.py):
the same rows, ids, distances and order, ties included, on real indexes (the sample map, Andorra, Monaco) and on
edge inputs; wrong calls raise TypeError or ValueError."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import storedrefs

from mapdb.build.pipeline import build_map
from mapdb.mapfile.reader import open_map
from mapdb.match import _kernel
from mapdb.match.index import stored as stored_module
from mapdb.match.index.stored import StoredQuadIndex, build_index
from mapdb.match.quads import canonical_quads

REPO = Path(__file__).resolve().parents[1]
_RELATIVE = Path(__file__).resolve().parents[2] / "shared" / "data"
OSM = (_RELATIVE if _RELATIVE.is_dir() else Path("/work/shared/data")) / "osm"
SOURCES = {"sample": REPO / "sample_maps" / "helsinki.osm.pbf", "andorra": OSM / "andorra-2021-06-22.osm.pbf",
           "monaco": OSM / "monaco-2021-12-03.osm.pbf"}


@pytest.fixture(scope="module", params=sorted(SOURCES))
def indexed(request, tmp_path_factory) -> Path:
    """A real map (the sample map, Andorra, Monaco) and its ``.qidx``, built once."""
    source = SOURCES[request.param]
    if not source.exists():
        pytest.skip(f"{source} is absent (the shared OSM extracts: ../shared/data/osm or /work/shared/data/osm)")
    path = tmp_path_factory.mktemp("stored") / f"{request.param}.mapdb"
    build_map([source], path)
    build_index(path)
    return path


def _queries(ix: StoredQuadIndex, label: np.ndarray, m: int, seed: int) -> tuple[np.ndarray, ...]:
    """Queries near stored quads (some exactly on one, some repeated: ties), radii from tiny to past the cells."""
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, ix.n_quads, m)
    ids = np.concatenate([ix.quads(int(p), int(p) + 1) for p in pick])
    _, inv, _ = canonical_quads(ix.coordinates(ids))
    query = inv + rng.normal(0, 0.02, inv.shape) * (rng.random(m) < 0.8)[:, None]
    radius = np.exp(rng.uniform(np.log(0.001), np.log(0.4), m))
    query[1::7], radius[1::7] = query[::7][: query[1::7].shape[0]], radius[::7][: query[1::7].shape[0]]
    radius[3::11] = 0.0
    return query, label[ids], radius


def _same(ix: StoredQuadIndex, query, labels, radius, k: int) -> int:
    got = ix.lookup(query, labels, radius, k, return_distance=True)
    want = storedrefs.lookup(ix, query, labels, radius, k, return_distance=True)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert np.array_equal(g, w)
    return int(got[0].size)


@pytest.mark.parametrize("k", [1, 3, 16, 10**6])
def test_lookups_of_real_indexes_are_the_numpy_codes(indexed: Path, k: int) -> None:
    with open_map(indexed) as m, StoredQuadIndex.for_map(m) as ix:
        assert ix is not None
        label = m.all().label
        query, labels, radius = _queries(ix, label, 300, seed=k)
        hits = _same(ix, query, labels, radius, k)
        assert hits > 0
        # Row by row too (a lookup of one row), and the rows reversed.
        for i in range(0, 300, 37):
            _same(ix, query[i : i + 1], labels[i : i + 1], radius[i : i + 1], k)
        _same(ix, query[::-1], labels[::-1], radius[::-1], k)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the numpy reference casts 1e300 and NaN
def test_ties_and_edge_inputs(indexed: Path) -> None:
    with open_map(indexed) as m, StoredQuadIndex.for_map(m) as ix:
        assert ix is not None
        label = m.all().label
        query, labels, radius = _queries(ix, label, 40, seed=9)
        # The same query ten times: its hits repeat row by row, ties in the same order.
        rep = np.repeat(query[:1], 10, axis=0), np.repeat(labels[:1], 10, axis=0), np.full(10, 0.2)
        assert _same(ix, *rep, 2) > 0
        _same(ix, query[:0], labels[:0], radius[:0], 5)  # empty
        bad = query.copy()
        bad[0, 1], bad[1, 2], bad[2, 0] = np.nan, np.inf, 1e300
        edge_radius = radius.copy()
        edge_radius[3], edge_radius[4], edge_radius[5] = np.nan, -1.0, np.inf
        odd_labels = labels.copy()
        odd_labels[6] = [-1, 0, 0, 0]
        odd_labels[7] = [len(ix.labels), 0, 0, 0]
        _same(ix, bad, odd_labels, edge_radius, 4)
        _same(ix, query, labels, 0.05, 16)  # one radius for all


def test_lookups_cut_in_small_pieces_are_the_numpy_codes(indexed: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Pieces of a few candidates: a query's candidates split over several pieces (bounds and audits per piece).
    monkeypatch.setattr(stored_module, "LOOKUP_CANDIDATES", 7)
    monkeypatch.setattr(storedrefs, "LOOKUP_CANDIDATES", 7)
    with open_map(indexed) as m, StoredQuadIndex.for_map(m) as ix:
        assert ix is not None
        query, labels, radius = _queries(ix, m.all().label, 60, seed=4)
        for k in (1, 2, 16):
            _same(ix, query, labels, radius, k)


def test_resolve_is_the_numpy_code(indexed: Path) -> None:
    with StoredQuadIndex(str(indexed) + ".qidx") as ix:
        anchor, triple, _ = ix._records(np.arange(ix.n_quads))
        got = ix._resolve(anchor, triple)
        want = storedrefs._resolve(ix, anchor, triple)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert ix._resolve(anchor[:0], triple[:0])[0].shape == (0, 4)


def test_wrong_kernel_calls_raise(indexed: Path) -> None:
    with StoredQuadIndex(str(indexed) + ".qidx") as ix:
        t = ix._tables
        q, r, cell, lk = np.zeros((2, 4)), np.full(2, 0.1), np.full(2, 0.1), np.zeros(2, np.int64)
        assert _kernel.stored_lookup(t, q, r, cell, lk, 3, 100)[0] in (0, 1)
        with pytest.raises(TypeError):
            _kernel.stored_lookup(t[:-1], q, r, cell, lk, 3, 100)
        with pytest.raises(TypeError):
            _kernel.stored_lookup(t, q.astype(np.float32), r, cell, lk, 3, 100)
        with pytest.raises(TypeError):
            _kernel.stored_lookup((t[1],) + t[1:], q, r, cell, lk, 3, 100)  # a bool array for the quads
        with pytest.raises(ValueError):
            _kernel.stored_lookup(t, q, r[:1], cell, lk, 3, 100)
        with pytest.raises(ValueError):
            _kernel.stored_lookup(t, q, r, cell, lk, 0, 100)
        with pytest.raises(ValueError):
            _kernel.stored_lookup(t[:3] + (t[3][:-1],) + t[4:], q, r, cell, lk, 3, 100)  # sizes disagree
        with pytest.raises(ValueError):
            _kernel.stored_lookup(t[:-1] + ((99,) + t[-1][1:],), q, r, cell, lk, 3, 100)  # parameters out of range
        with pytest.raises(TypeError):
            _kernel.stored_resolve(t, np.zeros(2, np.int32), np.zeros(2, np.int64))
        with pytest.raises(ValueError):
            _kernel.stored_resolve(t, np.zeros(2, np.int64), np.zeros(3, np.int64))
        # An anchor out of range is the file's corruption (code 1), not a crash.
        assert _kernel.stored_resolve(t, np.array([ix.n_objects]), np.zeros(1, np.int64)) == (2, 1)
