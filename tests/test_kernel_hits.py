"""The lookup stage's fused kernels (``_kernel_hits.c``) against the numpy code they replaced, kept here verbatim:
round_hypotheses' hits made hypotheses (gather, similarity fit, pose filter), the stored index's query rows prepared
(tests/storedrefs.py's lookup) and the coordinates of its objects; on random and edge inputs (ties, duplicates,
inf/NaN, empty, one row); wrong calls raise TypeError or ValueError."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import storedrefs

from mapdb.build.pipeline import build_map
from mapdb.match import _kernel
from mapdb.match.geometry import fit_similarity_complex
from mapdb.match.hypotheses import _hypotheses_of_hits, _quad_keys, allowed_poses, anchor_batches
from mapdb.match.index.stored import StoredQuadIndex, build_index
from mapdb.match.options import FastOptions

SAMPLE = Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"


def _reference_hypotheses(z, weight, key_ids, rows, map_z, prior, scale_range):
    """round_hypotheses' tail before the kernel, verbatim (``img_ids = key_ids[rows]``)."""
    img_ids = key_ids[rows]
    a, b = fit_similarity_complex(z[img_ids], map_z, None if weight is None else weight[img_ids])
    ok = allowed_poses(a, b, prior, scale_range)
    return a[ok], b[ok], img_ids[ok], map_z[ok]


def _reference_batches(z, opts, anchorable=None):
    """anchor_batches' split before the slices, verbatim."""
    members = np.arange(z.size) if anchorable is None else np.flatnonzero(anchorable)
    quads, counts = _kernel.quads_batches(np.ascontiguousarray(z, np.complex128), members.astype(np.int64),
                                          int(opts.image_neighbours), int(opts.anchors_per_batch),
                                          int(opts.max_batches))
    ends = np.cumsum(np.frombuffer(counts, np.int64))
    if not ends.size:
        return []
    return np.split(np.frombuffer(quads, np.int64).reshape(-1, 4), ends[:-1])


def _hits(rng, n: int, keys: int, h: int):
    """An image of ``n`` objects, ``keys`` quads of them and ``h`` hits of those quads on a map some similarity
    away, with duplicates (points on one spot: no fit), ties and non-finite points."""
    z = rng.uniform(-500, 500, n) + 1j * rng.uniform(-400, 400, n)
    if n > 3:
        z[1] = z[0]  # a duplicate point
        z[2] = z[3] if rng.random() < 0.5 else z[2]
    key_ids = rng.integers(0, n, (keys, 4)) if n else np.zeros((keys, 4), np.int64)
    rows = rng.integers(0, keys, h) if keys else np.zeros(0, np.int64)
    a = 0.4 * np.exp(1j * rng.uniform(-np.pi, np.pi))
    map_z = a * z[key_ids[rows]] + (4.7e6 + 3.1e5j) + rng.normal(0, 1, (h, 4)) + 1j * rng.normal(0, 1, (h, 4))
    if h > 4:
        map_z[1] = map_z[0]  # a repeated hit
        map_z[2, 1] = np.nan
        map_z[3, 0] = np.inf
        map_z[4] = map_z[4, 0]  # four map points on one spot
    return z, key_ids.astype(np.int64), rows.astype(np.int64), map_z


@pytest.mark.parametrize("seed", range(12))
def test_hypotheses_of_hits_are_the_numpy_code(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, keys, h = [(0, 0, 0), (4, 1, 1), (5, 3, 0), (30, 40, 200), (12, 6, 60)][seed % 5]
    z, key_ids, rows, map_z = _hits(rng, n, keys, h)
    weight = None if seed % 3 == 0 else rng.choice([0.0, 0.5, 1.0, 2.0], n)
    centre = complex(np.mean(map_z[np.isfinite(map_z)])) if h else 0j
    priors = [None, (centre.real, centre.imag, 50.0), (centre.real, centre.imag, 1e9)]
    scales = [None, (0.3, 0.5), (0.41, 0.41)]
    for prior in priors:
        for scale in scales:
            got = _hypotheses_of_hits(z, weight, key_ids, rows, map_z, prior, scale)
            want = _reference_hypotheses(z, weight, key_ids, rows, map_z, prior, scale)
            for g, w in zip((got.a, got.b, got.img_ids, got.map_z), want, strict=True):
                assert g.dtype == w.dtype and g.shape == w.shape
                assert np.array_equal(g, w, equal_nan=True)
    if h >= 60:  # the fit is not vacuous: some hits survive without filters, and none of the degenerate ones
        kept = _hypotheses_of_hits(z, weight, key_ids, rows, map_z, None, None)
        assert 0 < len(kept) and np.isfinite(kept.a).all()


def test_hypotheses_of_hits_wrong_calls_raise() -> None:
    z, key_ids, rows, map_z = _hits(np.random.default_rng(1), 10, 5, 20)
    args = (False, 0.0, 0.0, 0.0, False, 0.0, 0.0)
    assert len(_kernel.hits_hypotheses(z, None, key_ids, rows, map_z, *args)) == 4
    with pytest.raises(TypeError):
        _kernel.hits_hypotheses(z.real.copy(), None, key_ids, rows, map_z, *args)
    with pytest.raises(TypeError):
        _kernel.hits_hypotheses(z, None, key_ids.astype(np.int32), rows, map_z, *args)
    with pytest.raises(ValueError):
        _kernel.hits_hypotheses(z, np.ones(3), key_ids, rows, map_z, *args)
    with pytest.raises(ValueError):
        _kernel.hits_hypotheses(z, None, key_ids[:, :3].copy(), rows, map_z, *args)
    with pytest.raises(ValueError):
        _kernel.hits_hypotheses(z, None, key_ids, rows[:-1].copy(), map_z, *args)
    with pytest.raises(ValueError):  # a hit of a key row that is not there
        _kernel.hits_hypotheses(z, None, key_ids, np.array([5], np.int64), map_z[:1].copy(), *args)
    with pytest.raises(ValueError):  # a key naming an image object that is not there
        _kernel.hits_hypotheses(z[:3].copy(), None, key_ids, rows, map_z, *args)


@pytest.mark.parametrize("seed", range(6))
def test_anchor_batches_are_np_split(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = [0, 1, 4, 9, 30, 60][seed]
    z = rng.uniform(0, 800, n) + 1j * rng.uniform(0, 600, n)
    if n > 4:
        z[2] = z[1]
    opts = FastOptions()
    for anchorable in (None, rng.random(n) < 0.7):
        got, want = anchor_batches(z, opts, anchorable), _reference_batches(z, opts, anchorable)
        assert len(got) == len(want)
        assert all(g.shape == w.shape and np.array_equal(g, w) for g, w in zip(got, want, strict=True))


@pytest.mark.parametrize("seed", range(6))
def test_keys_ids_and_labels_are_the_numpy_gathers(seed: int) -> None:
    """_lookup_hits' gathers before the kernel gave them, verbatim: ``quads[row[:, None], order]`` and
    ``img_label[img_ids]``."""
    rng = np.random.default_rng(seed)
    n = [4, 5, 9, 20, 40, 60][seed]
    z = rng.uniform(0, 800, n) + 1j * rng.uniform(0, 600, n)
    z[1] = z[0] if seed % 2 else z[1]  # a duplicate point (a quad without a frame)
    quads = np.concatenate([q for q in anchor_batches(z, FastOptions())] or [np.zeros((0, 4), np.int64)])
    label = rng.integers(0, 5, n)
    for sigma in (1.0, rng.uniform(0.5, 3.0, quads.shape)):
        got = _quad_keys(z[quads], FastOptions(), sigma, quads, label)
        want = _quad_keys(z[quads], FastOptions(), sigma)
        if want is None:
            assert got is None
            continue
        row, order = want[0], want[1]
        img_ids = quads[row[:, None], order]
        for g, w in zip(got, (*want, img_ids, label[img_ids]), strict=True):
            assert g.shape == w.shape and np.array_equal(g, w)
    one = (1.0, 3.0, 4.0, 0.3)
    zq = np.ascontiguousarray(z[quads], np.complex128)
    with pytest.raises(ValueError):  # the ids without the labels
        _kernel.quads_keys(zq, None, *one, quads)
    with pytest.raises(ValueError):  # an id the labels do not have
        _kernel.quads_keys(zq, None, *one, quads, label[:1].copy())
    with pytest.raises(TypeError):
        _kernel.quads_keys(zq, None, *one, quads.astype(np.int32), label)


@pytest.fixture(scope="module")
def sample_index(tmp_path_factory) -> Path:
    """The sample map and its ``.qidx``, built once."""
    path = tmp_path_factory.mktemp("hits") / "sample.mapdb"
    build_map([SAMPLE], path)
    build_index(path)
    return Path(str(path) + ".qidx")


def _edge_queries(ix: StoredQuadIndex, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Queries on stored quads (ties: repeated rows) with NaN and inf invariants, inf, NaN, negative and zero radii,
    labels out of range and combinations the index does not hold."""
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, ix.n_quads, 40)
    ids = np.concatenate([ix.quads(int(p), int(p) + 1) for p in pick])
    from mapdb.match.quads import canonical_quads

    _, inv, _ = canonical_quads(ix.coordinates(ids))
    labels = rng.integers(0, len(ix.labels), (40, 4))
    labels[::2] = ix._combo_keys[rng.integers(0, ix._combo_keys.size, 20)][:, None] // (
        len(ix.labels) ** np.arange(3, -1, -1)) % len(ix.labels)
    query = inv + rng.normal(0, 0.01, inv.shape)
    radius = rng.uniform(0.001, 0.5, 40)
    query[5], radius[5] = query[4], radius[4]  # a tie
    labels[5] = labels[4]
    query[6, 2], query[7, 0], radius[8], radius[9], radius[10], radius[11] = np.nan, np.inf, np.inf, np.nan, -0.1, 0.0
    labels[12, 1], labels[13, 3] = -1, len(ix.labels)
    return query, labels, radius


def _same_lookup(ix: StoredQuadIndex, query, labels, radius, k: int) -> None:
    got = ix.lookup(query, labels, radius, k, return_distance=True)
    want = storedrefs.lookup(ix, query, labels, radius, k, return_distance=True)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert np.array_equal(g, w)


@pytest.mark.parametrize("seed", range(3))
def test_stored_lookup_rows_are_the_numpy_code(sample_index: Path, seed: int) -> None:
    query, labels, radius = _edge_queries(StoredQuadIndex(sample_index), seed)
    with StoredQuadIndex(sample_index) as ix:  # fresh: its combinations audited as the lookups reach them
        found = 0
        for k in (1, 3, 16):
            _same_lookup(ix, query, labels, radius, k)
            found += ix.lookup(query, labels, radius, k)[0].size
        assert found > 0
        _same_lookup(ix, query[:1], labels[:1], radius[:1], 4)  # one row
        _same_lookup(ix, query[:0], labels[:0], radius[:0], 4)  # none
        _same_lookup(ix, query, labels, 0.05, 4)  # one radius for all
        _same_lookup(ix, query[6:13], labels[6:13], radius[6:13], 4)  # nothing worth looking up
        with pytest.raises(ValueError):
            ix.lookup(query, labels[:-1], radius, 4)
        with pytest.raises(ValueError):
            ix.lookup(query, labels, radius[:-1], 4)


def test_stored_coordinates_are_the_numpy_code(sample_index: Path) -> None:
    with StoredQuadIndex(sample_index) as ix:
        ids = np.random.default_rng(0).integers(0, ix.n_objects, (30, 4))
        first = ix.coordinates(ids)  # blocks decoded now (the numpy path), then read by the kernel
        again = ix.coordinates(ids)
        c = ix._coords.rows(ids.reshape(-1))
        want = (((c[:, 0] + ix.origin[0]) * ix.quantum) + 1j * ((c[:, 1] + ix.origin[1]) * ix.quantum)).reshape(
            ids.shape)
        assert np.array_equal(first, want) and np.array_equal(again, want) and again.flags.writeable
        assert ix.coordinates(ids[:0]).shape == (0, 4)
        with pytest.raises(IndexError):
            ix.coordinates(np.array([ix.n_objects]))
        with pytest.raises(IndexError):
            ix.coordinates(np.array([-1]))
        with pytest.raises(TypeError):
            _kernel.hits_points(ix._tables, ids.reshape(-1).astype(np.int32))
        with pytest.raises(TypeError):
            _kernel.hits_points(ix._tables[:-1], ids.reshape(-1))
        assert _kernel.hits_points(ix._tables, np.array([ix.n_objects], np.int64)) == (2,)


def test_stored_lookup_wrong_kernel_calls_raise(sample_index: Path) -> None:
    with StoredQuadIndex(sample_index) as ix:
        t = ix._tables
        q, lab, r = np.zeros((2, 4)), np.zeros((2, 4), np.int64), np.full(2, 0.1)
        keys, cells, audited = ix._combo_keys, ix._combo_cell, np.ones(ix._combo_keys.size, bool)
        n = len(ix.labels)
        assert _kernel.hits_stored_lookup(t, q, lab, r, keys, cells, n, audited, 3, 100)[0] in (0, 1)
        with pytest.raises(TypeError):
            _kernel.hits_stored_lookup(t[:-1], q, lab, r, keys, cells, n, audited, 3, 100)
        with pytest.raises(TypeError):
            _kernel.hits_stored_lookup(t, q.astype(np.float32), lab, r, keys, cells, n, audited, 3, 100)
        with pytest.raises(TypeError):
            _kernel.hits_stored_lookup(t, q, lab.astype(np.int32), r, keys, cells, n, audited, 3, 100)
        with pytest.raises(ValueError):
            _kernel.hits_stored_lookup(t, q, lab[:1].copy(), r, keys, cells, n, audited, 3, 100)
        with pytest.raises(ValueError):
            _kernel.hits_stored_lookup(t, q, lab, r, keys, cells[:-1].copy(), n, audited, 3, 100)
        with pytest.raises(ValueError):
            _kernel.hits_stored_lookup(t, q, lab, r, keys, cells, n, audited, 0, 100)
        with pytest.raises(ValueError):
            _kernel.hits_stored_lookup(t[:3] + (t[3][:-1],) + t[4:], q, lab, r, keys, cells, n, audited, 3, 100)
