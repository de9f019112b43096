"""The simulated detector made cheaper (the image's four extremes tested before each object, the label table as an
object array made once) against the code it replaced, kept here verbatim as the reference (main at bc671ca): the
same reports and the generator left in the same state, on random and edge inputs (objects pushed out of the image by
the noise, misses, spurious objects, confused labels, no object, one object)."""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.camera import Camera
from mapdb.objects import Objects
from mapdb.simulation.detector import Detector, confuse_labels, detect, label_mix


def ref_detect(rng, objects, index, u, v, camera, detector):
    """mapdb.simulation.detector.detect at bc671ca."""
    width, height = camera.width, camera.height
    n_visible = index.size
    noise = detector.pixel_std * rng.standard_normal((2, u.size))
    u, v = u + noise[0], v + noise[1]
    kept = (u >= 0) & (u < width) & (v >= 0) & (v < height) & (rng.random(u.size) >= detector.miss_rate)
    index, u, v = index[kept], u[kept], v[kept]
    label_names = np.asarray(objects.labels, dtype=object)[objects.label[index]]

    names, mix = detector.names, detector.mix
    n_spurious = int(rng.poisson(detector.spurious_rate * n_visible)) if detector.spurious_rate > 0 else 0
    if n_spurious:
        u = np.concatenate([u, rng.uniform(0.0, width, n_spurious)])
        v = np.concatenate([v, rng.uniform(0.0, height, n_spurious)])
        index = np.concatenate([index, np.full(n_spurious, -1, np.int64)])
        label_names = np.concatenate(
            [label_names, np.asarray(names, dtype=object)[rng.choice(len(names), n_spurious, p=mix)]]
        )
    confuse_labels(rng, label_names, detector)
    order = rng.permutation(index.size)
    return index[order], u[order], v[order], label_names[order]


CAMERA = Camera(640, 480, 45.0)
LABELS = ("building", "parking", "tree", "building_block")  # blocks are never detected: no object of theirs


def _objects(n: int, rng: np.random.Generator) -> Objects:
    return Objects(rng.uniform(0.0, 100.0, n), rng.uniform(0.0, 100.0, n), rng.integers(0, 3, n).astype(
        np.int32), np.zeros(n), LABELS, "EPSG:32631")


@pytest.mark.parametrize("pixel_std, miss_rate, spurious_rate, label_noise", [
    (0.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (40.0, 0.0, 0.0, 0.0), (1.0, 0.3, 0.0, 0.0), (1.0, 0.0, 0.5, 0.0),
    (1.0, 0.0, 0.0, 0.4), (25.0, 0.2, 0.3, 0.3), (0.0, 1.0, 0.0, 0.0)])
def test_detect_is_the_references(pixel_std: float, miss_rate: float, spurious_rate: float,
                                  label_noise: float) -> None:
    rng = np.random.default_rng(7)
    detector = Detector(pixel_std, miss_rate, spurious_rate, label_noise, *label_mix({"building": 50, "parking": 9,
                                                                                       "tree": 30}))
    for trial in range(300):
        n = int(rng.integers(0, 25)) if trial > 2 else trial  # no object, one, two, then any
        objects = _objects(max(n, 1), rng)
        index = np.sort(rng.choice(max(n, 1), n, replace=False)).astype(np.int64)
        u, v = rng.uniform(0.0, 640.0, n), rng.uniform(0.0, 480.0, n)
        if trial % 5 == 0 and n:  # objects on the edges, where the noise decides
            u[0], v[-1] = 0.0, 479.999999
        seed = int(rng.integers(0, 2**32))
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        got, want = detect(a, objects, index, u, v, CAMERA, detector), ref_detect(b, objects, index, u, v, CAMERA,
                                                                                 detector)
        for x, y in zip(got, want, strict=True):
            assert x.dtype == y.dtype and np.array_equal(x, y)
            assert [type(e) for e in x.tolist()] == [type(e) for e in y.tolist()]
        assert a.bit_generator.state == b.bit_generator.state  # the draws after it (the prior's) the same
