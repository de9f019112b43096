"""The simulated detector: which visible objects it reports, where, and with which label.

Its error model (pixel noise, misses, spurious objects, confused labels; see
:func:`~mapdb.simulation.simulate.simulate_images`) is a :class:`Detector`; :func:`detect` applies it to
the map objects in one image.  Spurious and confused labels are drawn from the map's label mix
(:func:`label_mix`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..camera import Camera, in_image
from ..objects import Objects

__all__ = ["Detector", "confuse_labels", "detect", "label_mix"]


@dataclass(frozen=True)
class Detector:
    """The detector's error model (see :func:`~mapdb.simulation.simulate.simulate_images`) and the map's label
    mix it draws from."""

    pixel_std: float
    miss_rate: float
    spurious_rate: float
    label_noise: float
    names: list[str]
    mix: np.ndarray


def label_mix(counts: dict[str, int]) -> tuple[list[str], np.ndarray]:
    """The map's labels and the share of its objects each has."""
    names = list(counts)
    mix = np.array([counts[k] for k in names], dtype=np.float64)
    mix /= mix.sum()
    return names, mix


def detect(
    rng: np.random.Generator,
    objects: Objects,
    index: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    camera: Camera,
    detector: Detector,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the detector reports of the visible objects: ``(map_index, u, v, label)``, -1 for spurious."""
    width, height = camera.width, camera.height
    n_visible = index.size
    noise = detector.pixel_std * rng.standard_normal((2, u.size))
    u, v = u + noise[0], v + noise[1]
    # A detector reports positions inside its image: noise that pushes an object out drops it.  The misses are drawn
    # whatever their rate (the draws after them stay where they are); a rate of 0 misses none.
    missed = rng.random(u.size)
    # Most images keep every object: four extremes (NaN fails them) decide that without the per-object test.
    inside = u.size and u.min() >= 0 and u.max() < width and v.min() >= 0 and v.max() < height
    if not inside or detector.miss_rate > 0:
        kept = in_image(u, v, camera)
        if detector.miss_rate > 0:
            kept &= missed >= detector.miss_rate
        index, u, v = index[kept], u[kept], v[kept]
    label_names = _names(objects.labels)[objects.label[index]]

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


@lru_cache(maxsize=16)
def _names(labels: tuple[str, ...]) -> np.ndarray:
    """A label table as an object array (indexed by code), made once a table, not once an image (never written:
    indexing it copies)."""
    return np.asarray(labels, dtype=object)


def confuse_labels(rng: np.random.Generator, label_names: np.ndarray, detector: Detector) -> None:
    """Give each label, with probability ``label_noise``, another label of the map's mix (in place)."""
    names, mix = detector.names, detector.mix
    if detector.label_noise > 0 and len(names) > 1 and label_names.size:
        flip = np.flatnonzero(rng.random(label_names.size) < detector.label_noise)
        code_of = {k: j for j, k in enumerate(names)}
        for j in flip:  # few objects per image; the mix changes per object (own label excluded)
            p = mix.copy()
            p[code_of[label_names[j]]] = 0.0
            if p.sum() > 0:
                label_names[j] = names[int(rng.choice(len(names), p=p / p.sum()))]
