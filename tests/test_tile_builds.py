"""A prior's tile build: its objects (MetaMap.query_bbox) and its anchors' nearest others (decided_nearest), each
against the code it replaced, kept here verbatim as the reference."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import shapely

from mapdb._scipy import quick_tree
from mapdb.mapfile.reader import _MAX_QUANTA, open_map
from mapdb.match.nearest import decided_nearest, nearest_others
from mapdb.match.quads import QuadIndex

_RELATIVE = Path(__file__).resolve().parents[2] / "shared" / "data"
OSM = (_RELATIVE if _RELATIVE.is_dir() else Path("/work/shared/data")) / "osm"
MONACO = OSM / "monaco-2021-12-03.osm.pbf"


def ref_nearest_others(tree, xy, ids, k, workers=1):
    """nearest_others as it was."""
    _, nn = tree.query(xy[ids], k + 1, workers=workers)
    # The point itself is usually first, but not when another point sits on it: drop it wherever it is.
    own = nn == ids[:, None]
    own[~own.any(axis=1), -1] = True
    return nn[~own].reshape(ids.size, k)


def ref_neighbours(xy, ids, k):
    """The anchors' neighbours as QuadIndex found them: cKDTree's (quick_tree), as int64."""
    return np.ascontiguousarray(ref_nearest_others(quick_tree(xy), xy, ids, k), np.int64)


def ref_query_bbox(self, minx, miny, maxx, maxy, labels=None):
    """MetaMap.query_bbox as it was."""
    box = [float(v) / self.quantum for v in (minx, miny, maxx, maxy)]
    if any(math.isnan(v) for v in box):
        return self._label_filter(self._objects([]), None)
    limit = 2.0 * _MAX_QUANTA
    box = [min(max(v, -limit), limit) for v in box]
    lo_x, lo_y, hi_x, hi_y = math.floor(box[0]), math.floor(box[1]), math.ceil(box[2]), math.ceil(box[3])
    hits = np.sort(self._tree.query(shapely.box(lo_x, lo_y, hi_x, hi_y)))
    found = self._objects(hits.tolist())
    inside = (found.x >= minx) & (found.x <= maxx) & (found.y >= miny) & (found.y <= maxy)
    return self._label_filter(found.take(inside), labels)


def same_objects(a, b) -> bool:
    fields = ("x", "y", "label", "area", "elevation")
    return a.labels == b.labels and a.crs == b.crs and all(
        (getattr(a, f) is None) == (getattr(b, f) is None)
        and (getattr(a, f) is None or (getattr(a, f).dtype == getattr(b, f).dtype
                                       and getattr(a, f).tobytes() == getattr(b, f).tobytes())) for f in fields)


def point_sets(rng):
    """Random sets, and sets where distances tie or cannot decide: lattices, duplicates, collinear and stacked points,
    signed zeros, vanishing and huge separations, rounded coordinates (a map's quanta), one far point."""
    grid = np.stack(np.meshgrid(np.arange(7.0), np.arange(6.0)), -1).reshape(-1, 2) * 10.0
    sets = [rng.normal(0, 100, (int(n), 2)) for n in rng.integers(4, 300, 25)]
    sets += [grid, np.column_stack([np.arange(12.0), np.zeros(12)]), np.repeat(rng.uniform(0, 50, (6, 2)), 3, axis=0),
             np.zeros((5, 2)), np.array([[0.0, 0.0], [-0.0, 0.0], [0.0, -0.0], [-0.0, -0.0], [1e-300, 0.0],
                                          [0.0, 1e-300]]),
             rng.uniform(-1e6, 1e6, (30, 2)) + 1e7, np.round(rng.uniform(0, 5, (40, 2))),
             np.round(rng.uniform(0, 300, (400, 2)), 1), rng.uniform(0, 1e-120, (20, 2)),
             rng.uniform(-1e200, 1e200, (20, 2)), np.vstack([rng.uniform(0, 10, (9, 2)), [[1e6, 1e6]]]),
             grid[:4], grid[:5]]
    return sets


@pytest.mark.parametrize("neighbours", [3, 6, 8])
def test_decided_nearest_is_ckdtrees(neighbours):
    rng = np.random.default_rng(30)
    for xy in point_sets(rng):
        k = min(neighbours, len(xy) - 1)
        for ids in (np.arange(len(xy)), np.flatnonzero(rng.random(len(xy)) < 0.5), np.array([len(xy) - 1])):
            got = decided_nearest(xy, ids, k)
            assert got.dtype == np.int64 and got.flags.c_contiguous and got.shape == (ids.size, k)
            assert np.array_equal(got, ref_neighbours(xy, ids, k))


def test_decided_nearest_non_finite_points():
    """Refused as cKDTree refused them (its ValueError), whatever the row."""
    rng = np.random.default_rng(31)
    for bad in (np.inf, -np.inf, np.nan):
        xy = rng.uniform(0, 100, (50, 2))
        xy[[3, 17], [0, 1]] = bad
        for call in (decided_nearest, ref_neighbours):
            with pytest.raises(ValueError, match="finite"):
                call(xy, np.arange(50), 8)


def test_decided_nearest_wrong_calls():
    xy = np.random.default_rng(32).uniform(0, 100, (6, 2))
    for k in (0, 6, 7, -1):
        with pytest.raises(ValueError, match="0 < k"):
            decided_nearest(xy, np.arange(6), k)
    with pytest.raises(IndexError):
        decided_nearest(xy, np.array([6]), 3)
    assert decided_nearest(xy, np.zeros(0, np.int64), 3).shape == (0, 3)


def test_nearest_others_as_before():
    rng = np.random.default_rng(33)
    for xy in point_sets(rng):
        if not np.isfinite(xy).all() or len(xy) < 2:
            continue
        tree, k = quick_tree(xy), min(8, len(xy) - 1)
        for ids in (np.arange(len(xy)), np.arange(len(xy))[::2], np.zeros(0, np.int64)):
            assert np.array_equal(nearest_others(tree, xy, ids, k), ref_nearest_others(tree, xy, ids, k))


def _boxes(objects, rng):
    """Tile-like boxes, boxes on objects' own coordinates (edges included), empty and inverted ones, one past the
    map."""
    x0, y0, x1, y1 = objects.x.min(), objects.y.min(), objects.x.max(), objects.y.max()
    boxes = [(x0 - 1, y0 - 1, x1 + 1, y1 + 1), (x1 + 10, y1 + 10, x1 + 20, y1 + 20), (x1, y1, x0, y0),
             (math.nan, y0, x1, y1), (-math.inf, -math.inf, math.inf, math.inf)]
    for i in rng.integers(0, len(objects), 30):
        x, y = float(objects.x[i]), float(objects.y[i])
        boxes.append((x, y, x + rng.uniform(0, 800), y + rng.uniform(0, 800)))
        boxes.append((x - 150, y - 150, x + 1150, y + 1150))
        boxes.append((x, y, x, y))
    return boxes


def _same_boxes(path):
    rng = np.random.default_rng(34)
    with open_map(path) as new, open_map(path) as old:
        objects = new.all()
        for box in _boxes(objects, rng):
            for labels in (None, [new.labels[0]]):
                assert same_objects(new.query_bbox(*box, labels=labels), ref_query_bbox(old, *box, labels=labels))
        assert sum(len(new.query_bbox(*b)) for b in _boxes(objects, rng)) > 0


def test_query_bbox_as_before(paper_setup):
    _same_boxes(paper_setup[0])


@pytest.mark.slow
@pytest.mark.skipif(not MONACO.exists(), reason=f"needs the shared OSM extract {MONACO}")
def test_tiles_of_monaco_as_before(tmp_path):
    """A real city's tiles, where rounded coordinates tie distances in most tiles: the same objects, neighbours and
    quads as before."""
    from mapdb.build.pipeline import build_map

    path = tmp_path / "monaco.mapdb"
    build_map([MONACO], path)
    _same_boxes(path)
    with open_map(path) as m:
        everything = m.all()
        undecided = 0
        for i in np.random.default_rng(35).integers(0, len(everything), 12):
            x0, y0 = np.floor(everything.x[i] / 1000) * 1000, np.floor(everything.y[i] / 1000) * 1000
            objects = m.query_bbox(x0 - 150, y0 - 150, x0 + 1150, y0 + 1150)
            xy, ids = np.column_stack([objects.x, objects.y]), np.arange(len(objects))
            assert np.array_equal(decided_nearest(xy, ids, 8), ref_neighbours(xy, ids, 8))
            index = QuadIndex(objects, 8, anchors=(objects.x >= x0) & (objects.x < x0 + 1000) & (objects.y >= y0)
                              & (objects.y < y0 + 1000), positions=True)
            assert index.n_quads > 0
            d = quick_tree(xy).query(xy, 10)[0]
            undecided += bool((np.diff(d, axis=1) == 0).any())
        assert undecided > 0  # the tie rows were exercised
