"""A cell's images drawn at once: their poses, the objects each shows, and the image of one to localize.

Sample ``s`` of cell ``(i, j)`` draws from ``numpy.random.default_rng([seed, i', j', s])`` (see
:mod:`mapdb.analysis.measures`): its position, heading, roll and pitch, then (only if it is localized) the
detector's errors and the prior's offset.  This module draws exactly those numbers, faster:

* **The generators' seeds** of every sample of a task are hashed together (:func:`pcg_states`): numpy's
  ``SeedSequence`` mixing, then ``PCG64``'s seeding, on arrays (the 128-bit step in Python integers), so that
  one reused generator set to each state draws what ``default_rng([seed, i', j', s])`` would.  Entropy words of
  2**32 or more (a huge ``--seed``) go through ``default_rng`` itself.
* **The poses** (:func:`cell_poses`): the position and heading from the generator's raw 64-bit outputs (numpy's
  ``random`` and ``uniform`` are ``(r >> 11) * 2**-53`` and ``low + range * that``), roll and pitch from its
  ``standard_normal``.
* **The views** (:func:`cell_views`): the objects within reach of any of the cell's images are found in one
  query, and projected into all its images in one stacked product whose pixels are
  :func:`~mapdb.camera.project_to_image`'s, bit for bit (:func:`~mapdb.camera.project_to_images`).  An object
  within :data:`MARGIN_M` of an image's reach is at a place where the rounding of its distance could decide: that
  image's objects within reach are then those the tree finds, as one image's are, so that which objects an image
  shows is always what the per-image computation gives.
* **The image** of a sample that is localized (:func:`cell_image`): the objects it shows, at the pixels of its view,
  then the detector and the prior, with the generator where its pose left it:
  :func:`~mapdb.simulation.simulate.simulate_image_at`'s document, without its ``truth`` (the localizer does not
  read it), handed over as the arrays :func:`~mapdb.detections.images.parse_image` would make of it
  (:class:`~mapdb.detections.images.ImageObjects`: no document written and parsed again, the same numbers).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..camera import Camera, Pose, in_image, project_to_images, rotations_body_to_ned
from ..detections.images import MAX_OBJECTS, ImageObjects, Prior
from ..simulation.detector import Detector, detect, label_mix
from ..simulation.documents import add_hints, image_document
from ..simulation.poses import Shot
from ..simulation.simulate import detectable

__all__ = ["MARGIN_M", "Poses", "Views", "cell_image", "cell_poses", "cell_views", "detector_of", "near_cells",
           "pcg_states", "positioned", "sample_generator"]

# How close (metres) to an image's reach an object must come for the rounding of its distance (the tree's against
# numpy's) to matter: that image's objects within reach are then the tree's, as one image's are.
MARGIN_M = 1e-6

# numpy's SeedSequence (bit_generator.pyx) and PCG64 (pcg64.h) constants.
_INIT_A, _MULT_A, _INIT_B, _MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R = 0xCA01F9DD, 0x4973F715
_M32 = np.uint64(0xFFFFFFFF)
_PCG_MULT = 0x2360ED051FC65DA44385DF649FCCF645
_M128 = (1 << 128) - 1
_TO_UNIT = 1.0 / 9007199254740992.0  # 2**-53: a double from the top 53 bits of a raw output


def _natural(v: np.ndarray) -> np.ndarray:
    """Integers as non-negative ones, one to one (zigzag), as a seed needs."""
    return np.where(v >= 0, 2 * v, -2 * v - 1)


def _hash_constants(n: int, init: int, mult: int) -> list[np.uint64]:
    """The SeedSequence hash constant after each of ``n`` updates (it is the same whatever the data)."""
    out, h = [], init
    for _ in range(n):
        h = (h * mult) & 0xFFFFFFFF
        out.append(np.uint64(h))
    return out


# 4 words hashed in, then 12 mixes; 8 words of state out.
_HASH_A = _hash_constants(16, _INIT_A, _MULT_A)
_XOR_A = [np.uint64(_INIT_A)] + _HASH_A[:-1]
_HASH_B = _hash_constants(8, _INIT_B, _MULT_B)
_XOR_B = [np.uint64(_INIT_B)] + _HASH_B[:-1]


def pcg_states(entropy: np.ndarray) -> list[tuple[int, int]]:
    """The PCG64 ``(state, inc)`` of ``default_rng(row)`` for every row of four entropy words (each below 2**32).

    Examples
    --------
    >>> st = np.random.default_rng([0, 3, 4, 5]).bit_generator.state["state"]
    >>> pcg_states(np.array([[0, 3, 4, 5]])) == [(st["state"], st["inc"])]
    True
    """
    words = np.asarray(entropy, np.uint64).reshape(-1, 4)
    calls = iter(range(16))

    def hashmix(value: np.ndarray) -> np.ndarray:
        k = next(calls)
        value = ((value ^ _XOR_A[k]) * _HASH_A[k]) & _M32
        return value ^ (value >> np.uint64(16))

    def mix(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r: np.ndarray = (np.uint64(_MIX_L) * x - np.uint64(_MIX_R) * y) & _M32  # type: ignore[operator]
        return r ^ (r >> np.uint64(16))

    pool = [hashmix(words[:, k]) for k in range(4)]
    for src in range(4):
        for dst in range(4):
            if src != dst:
                pool[dst] = mix(pool[dst], hashmix(pool[src]))
    out = []
    for k in range(8):
        value = ((pool[k % 4] ^ _XOR_B[k]) * _HASH_B[k]) & _M32
        out.append(value ^ (value >> np.uint64(16)))
    halves = [(out[2 * k] | (out[2 * k + 1] << np.uint64(32))).tolist() for k in range(4)]
    states = []
    for a, b, c, d in zip(*halves, strict=True):
        inc = ((((c << 64) | d) << 1) | 1) & _M128
        states.append(((((inc + ((a << 64) | b)) & _M128) * _PCG_MULT + inc) & _M128, inc))
    return states


def sample_generator(seed: int, i: int, j: int, s: int) -> np.random.Generator:
    """Sample ``s`` of cell ``(i, j)``'s generator, before any draw."""
    return np.random.default_rng([seed, *_natural(np.array([i, j], np.int64)).tolist(), s])


@dataclass
class Poses:
    """The poses of a cell's images: arrays of one value an image."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    rotations: np.ndarray  # (images, 3, 3): each image's rotation_body_to_ned (made for a task's images at once)
    altitude: float
    states: list[tuple[int, int]] | None = None  # each image's PCG64 (state, inc) before its draws, if hashed here

    def pose(self, s: int) -> Pose:
        return Pose(float(self.x[s]), float(self.y[s]), self.altitude, float(self.heading[s]), float(self.roll[s]),
                    float(self.pitch[s]))


def _draw(generator: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One pose's draws: three raw outputs (position, heading), then two standard normals (roll, pitch)."""
    return generator.bit_generator.random_raw(3), generator.standard_normal(2)


def cell_poses(seed: int, cells: np.ndarray, samples: int, cell_m: float, altitude: float,
               attitude_std: float) -> list[Poses]:
    """Every sample's pose of every cell (absolute indices, rows ``(i, j)``), as ``default_rng([seed, i', j', s])``
    draws them: position uniform in the cell, heading uniform, roll and pitch normal."""
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    n = len(cells)
    keys = np.column_stack([np.repeat(_natural(cells[:, 0]), samples), np.repeat(_natural(cells[:, 1]), samples),
                            np.tile(np.arange(samples), n)])
    states: list[tuple[int, int]] | None = None
    if seed < 2**32 and (keys < 2**32).all():
        states = pcg_states(np.column_stack([np.full(len(keys), seed), keys]))
        raws, normals = _draws_from(states)
    else:  # words of 2**32 or more: SeedSequence's own (longer) mixing
        drawn = [_draw(np.random.default_rng([seed, *row])) for row in keys.tolist()]
        raws, normals = [d[0] for d in drawn], [d[1] for d in drawn]
    raw = np.array(raws, np.uint64).reshape(-1, 3)
    normal = np.array(normals, np.float64).reshape(-1, 2)
    unit = (raw >> np.uint64(11)) * _TO_UNIT
    x = (np.repeat(cells[:, 0], samples) + unit[:, 0]) * cell_m
    y = (np.repeat(cells[:, 1], samples) + unit[:, 1]) * cell_m
    heading = 0.0 + 360.0 * unit[:, 2]
    tilt = attitude_std * normal
    rotations = rotations_body_to_ned(heading, tilt[:, 1], tilt[:, 0])
    return [Poses(x[c], y[c], heading[c], tilt[c, 0], tilt[c, 1], rotations[c], float(altitude),
                  None if states is None else states[c])
            for c in (slice(k * samples, (k + 1) * samples) for k in range(n))]


def _draws_from(states: list[tuple[int, int]]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each state's pose draws (:func:`_draw`), one generator set to each in turn (through one state record, whose
    numbers are replaced: the setter copies them)."""
    generator = np.random.Generator(np.random.PCG64(0))
    bits = generator.bit_generator
    pcg = {"state": 0, "inc": 0}
    record = {"bit_generator": "PCG64", "state": pcg, "has_uint32": 0, "uinteger": 0}
    raw, normal = bits.random_raw, generator.standard_normal
    raws, normals = [], []
    for state, inc in states:
        pcg["state"], pcg["inc"] = state, inc
        bits.state = record
        raws.append(raw(3))
        normals.append(normal(2))
    return raws, normals


def _restated(generator: np.random.Generator, state: tuple[int, int]) -> np.random.Generator:
    """``generator`` (a PCG64 one) set to a PCG64 ``(state, inc)``, no value buffered."""
    generator.bit_generator.state = {"bit_generator": "PCG64", "state": {"state": state[0], "inc": state[1]},
                                     "has_uint32": 0, "uinteger": 0}
    return generator


@dataclass
class Views:
    """What a cell's images show: ``near`` (indices into the objects, sorted) within reach of any of them,
    ``seen`` (images, near): whether each image shows each, ``u``, ``v`` (images, near): their pixels in each
    image (:func:`~mapdb.camera.project_to_image`'s numbers), and ``detectable`` (near): which of them a detector
    can report (None: all; :func:`~mapdb.simulation.simulate.detectable`)."""

    near: np.ndarray
    seen: np.ndarray
    u: np.ndarray
    v: np.ndarray
    detectable: np.ndarray | None = None

    def shown(self, s: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The objects image ``s`` shows that a detector can report (sorted indices into the objects), and their
        pixels: what :func:`cell_image` takes."""
        seen = self.seen[s] if self.detectable is None else self.seen[s] & self.detectable
        return self.near[seen], self.u[s][seen], self.v[s][seen]  # a row, then its mask: numpy's quicker path


def near_cells(tree: Any, centres: np.ndarray, radius: float, reach: float) -> list[np.ndarray]:
    """For each cell (its centre a row of ``centres``, its cameras within ``radius`` of it), the objects its images
    can show: sorted indices of those within ``radius + reach`` (and a metre) of its centre, found in one query of
    ``tree`` (None: no objects)."""
    if tree is None:
        return [np.zeros(0, np.int64) for _ in range(len(centres))]
    found = tree.query_ball_point(np.asarray(centres, np.float64).reshape(-1, 2), radius + reach + 1.0,
                                  return_sorted=True)
    return [np.asarray(one, np.int64) for one in found]


def cell_views(objects: Any, tree: Any, near: np.ndarray, poses: Poses, camera: Camera, reach: float) -> Views:
    """Which objects each of a cell's images shows: those within ``reach`` of its camera that project inside
    it.  ``tree`` indexes ``objects``; ``near`` (sorted indices into them) holds every object within reach of
    any of its cameras (:func:`near_cells`)."""
    n = poses.x.size
    if not near.size:
        none = np.zeros((n, 0))
        return Views(near, np.zeros((n, 0), bool), none, none)
    ox, oy = objects.x[near], objects.y[near]
    dx, dy = ox - poses.x[:, None], oy - poses.y[:, None]
    u, v = project_to_images(dx, dy, poses.altitude, poses.rotations, camera)
    dist = np.hypot(dx, dy)
    seen = (dist <= reach) & in_image(u, v, camera)
    if np.abs(dist - reach).min() < MARGIN_M:
        # The tree's distance test (the per-image way) may round differently from this one at the reach itself.
        for s in np.flatnonzero((np.abs(dist - reach) < MARGIN_M).any(axis=1)).tolist():
            own = np.searchsorted(near, np.asarray(tree.query_ball_point((poses.x[s], poses.y[s]), reach), np.int64))
            seen[s] = False
            seen[s, own] = in_image(u[s, own], v[s, own], camera)
    return Views(near, seen, u, v, detectable(objects.label[near], objects.labels))


def cell_image(objects: Any, shown: np.ndarray, u: np.ndarray, v: np.ndarray, pose: Pose, camera: Camera,
               generator: np.random.Generator, detector: Detector, prior: float | None,
               image_id: str) -> ImageObjects | dict[str, Any]:
    """The image a sample is localized from (``generator`` where its pose's draws left it):
    :func:`~mapdb.simulation.simulate.simulate_image_at` of the objects it shows (``shown``, sorted indices into
    ``objects`` of those a detector can report, and their pixels ``u``, ``v``: :meth:`Views.shown`), without its
    truth, as the :class:`~mapdb.detections.images.ImageObjects` that :func:`~mapdb.detections.images.parse_image`
    makes of that document.

    Only the objects shown are detected (the simulator projects all those within reach): a point's pixels do
    not depend on the other points projected with it, and the objects not shown draw nothing.  The arrays pass
    every check of the parser: the detector keeps pixels inside the image (``0 <= u < width``), the camera and the
    prior are the configuration's (checked in range), and the prior's centre lies within its radius of the map.
    An image of more than ``MAX_OBJECTS`` objects, which the parser refuses, is its document, so that the
    localizer refuses it as before.
    """
    _, u, v, label_names = detect(generator, objects, shown, u, v, camera, detector)
    hints: dict[str, Any] = {}
    if prior is not None:  # the only hint an analysis gives (add_hints draws nothing for the others)
        shot = Shot(pose.altitude, camera, pose.yaw_deg, pose.roll_deg, pose.pitch_deg)
        add_hints(generator, hints, shot, pose.x, pose.y, prior, False, False)
    if u.size > MAX_OBJECTS:
        return {**image_document(image_id, camera, label_names, u, v), **hints}
    disc = hints.get("prior")
    # The parser's types: float64 pixels, labels as Python strings in an object array (the map's and the detector's
    # names are, detector_of), floats for the rest.
    return ImageObjects(id=image_id, width=float(camera.width), height=float(camera.height),
                        x=np.asarray(u, np.float64), y=np.asarray(v, np.float64), names=label_names,
                        prior=None if disc is None else Prior(float(disc["x"]), float(disc["y"]), disc["radius"]),
                        fov_deg=float(camera.fov_deg))


def detector_of(label_counts: dict[str, int], pixel_std: float, miss_rate: float, spurious_rate: float,
                label_noise: float) -> Detector:
    """The detector every image of an analysis uses (its label mix that of ``label_counts``, not empty; the names as
    Python strings, as an image document's labels are parsed)."""
    names, mix = label_mix({str(name): count for name, count in label_counts.items()})
    return Detector(pixel_std, miss_rate, spurious_rate, label_noise, names, mix)


def positioned(poses: Poses, s: int, seed: int, i: int, j: int,
               reuse: np.random.Generator | None = None) -> np.random.Generator:
    """Sample ``s``'s generator where its pose's draws leave it (its image's errors start there): ``reuse`` (a
    PCG64 generator, which this sets) when given and the poses kept their states, else a new one."""
    if reuse is not None and poses.states is not None:
        generator = _restated(reuse, poses.states[s])
    else:
        generator = sample_generator(seed, i, j, s)
    _draw(generator)
    return generator

