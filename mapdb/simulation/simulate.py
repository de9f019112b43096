"""Simulated aerial images of a meta-map: the paper's feasibility study (Section III) and beyond.

A pinhole camera fixed to an aircraft looks down at flat ground; the labelled
objects of a map that fall inside its image become an image-objects document
(the ``mapdb query`` input format) carrying the truth it was made from.
The camera model, its frames and sign conventions are those of :mod:`mapdb.camera`.

The truth of a simulated image is the camera *nadir* ``(x, y)``.  A localizer
that is given no attitude returns the point under the image centre, so attitude
error is part of its error, as in the paper.

Examples
--------
>>> images = simulate_images(paper_map(), 3, pixel_std=1.0, seed=1)
>>> len(images), sorted(images[0]["truth"])[:3]
(3, ['altitude_m', 'bound', 'fov_deg'])
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._scipy import cKDTree
from ..camera import Camera, Pose, footprint, image_to_ground, level_pixels, project_to_image
from ..errors import EmptyMapError
from ..match.geometry import apply_similarity, fit_similarity
from ..objects import Objects
from ..outputs import ProgressLike, as_progress, atomic_open

__all__ = [
    "PAPER_CRS",
    "PAPER_ORIGIN",
    "bound_fit",
    "map_bbox_from_lonlat",
    "paper_density",
    "paper_map",
    "simulate_image_at",
    "simulate_images",
    "write_images",
]

# The paper's map is abstract; it gets real-looking UTM metres so that every tool treats it like any
# other map (lon/lat output, CRS checks).  UTM 31N at about 45.1 N, 3 E.
PAPER_CRS = "EPSG:32631"
PAPER_ORIGIN = (500_000.0, 5_000_000.0)


def bound_fit(
    u: np.ndarray,
    v: np.ndarray,
    map_x: np.ndarray,
    map_y: np.ndarray,
    camera: Camera,
    roll_deg: float | None = None,
    pitch_deg: float | None = None,
) -> tuple[float, float] | None:
    """Position from the least-squares similarity fit of image objects onto their *true* map objects.

    This is the best any matcher can do from these pixels: the fit is given the
    correspondences.  With ``roll_deg``/``pitch_deg`` (an attitude the
    localizer is told) the pixels are levelled first and the estimate is the
    nadir; without, it is the ground point under the image centre.  None if
    fewer than two objects.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if u.size < 2:
        return None
    if roll_deg is not None or pitch_deg is not None:
        u, v = level_pixels(u, v, camera, roll_deg or 0.0, pitch_deg or 0.0)
    # Image y points down and map y north: flip so the fit needs no reflection.
    src = np.column_stack([u, -v])
    dst = np.column_stack([map_x, map_y])
    try:
        params = fit_similarity(src, dst)
    except ValueError:
        return None
    cx, cy = apply_similarity(np.array([camera.width / 2.0, -camera.height / 2.0]), *params)
    return float(cx), float(cy)


def paper_density(objects_per_image: float = 17.0, altitude: float = 100.0, camera: Camera | None = None) -> float:
    """Objects per square metre putting ``objects_per_image`` in a level image (paper: 17, 100 m, 35 deg)."""
    w, h = (camera or Camera()).footprint_m(altitude)
    return objects_per_image / (w * h)


def paper_map(
    seed: int = 0,
    width: float = 250.0,
    height: float = 150.0,
    density: float | None = None,
    label: str = "building",
) -> Objects:
    """The paper's map: objects of one label uniformly at random over ``width`` x ``height`` metres.

    The count is ``round(density * width * height)``; the default density
    (:func:`paper_density`) gives about 17 objects per 640x480 image from 100 m
    at a 35 degree field of view, 214 objects on 250x150 m.  Coordinates are
    UTM metres (:data:`PAPER_CRS`) offset by :data:`PAPER_ORIGIN`.

    Examples
    --------
    >>> m = paper_map()
    >>> len(m), m.crs, m.labels
    (214, 'EPSG:32631', ('building',))
    """
    if density is None:
        density = paper_density()
    n = int(round(density * width * height))
    rng = np.random.default_rng(seed)
    x = PAPER_ORIGIN[0] + rng.uniform(0.0, width, n)
    y = PAPER_ORIGIN[1] + rng.uniform(0.0, height, n)
    return Objects(x, y, np.zeros(n, np.int32), np.zeros(n), (label,), PAPER_CRS)


def _map_objects(map_: Any) -> tuple[Objects, dict[str, int]]:
    """All objects of a map (MetaMap-like or :class:`Objects`) and its label counts."""
    objects = map_ if isinstance(map_, Objects) else map_.all()
    if not len(objects):
        raise EmptyMapError(f"{getattr(map_, 'path', None) or 'map'}: the map has no objects to simulate images of")
    counts = objects.counts()
    return objects, counts


def _draw_range(rng: np.random.Generator, value: float | tuple[float, float]) -> float:
    if isinstance(value, tuple | list):
        lo, hi = value
        return float(rng.uniform(lo, hi))
    return float(value)


@dataclass(frozen=True)
class _Shot:
    """One image's camera before it is placed: what every configuration draws, in a fixed order."""

    altitude: float
    camera: Camera
    heading: float
    roll: float
    pitch: float

    def pose(self, x: float = 0.0, y: float = 0.0) -> Pose:
        return Pose(x, y, self.altitude, self.heading, self.roll, self.pitch)


@dataclass(frozen=True)
class _Detector:
    """The detector's error model (see :func:`simulate_images`) and the map's label mix it draws from."""

    pixel_std: float
    miss_rate: float
    spurious_rate: float
    label_noise: float
    names: list[str]
    mix: np.ndarray


def _check_simulate_args(
    n: int,
    yaw: float | str,
    attitude_std: float,
    pixel_std: float,
    miss_rate: float,
    spurious_rate: float,
    label_noise: float,
    min_objects: int,
    max_tries: int,
) -> None:
    """ValueError on an argument of :func:`simulate_images` out of its range."""
    if n < 0:
        raise ValueError(f"number of images must be >= 0, got {n}")
    for name, rate in (("miss_rate", miss_rate), ("label_noise", label_noise)):
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {rate}")
    if min_objects < 0 or max_tries < 1:
        raise ValueError(f"min_objects must be >= 0 and max_tries >= 1, got {min_objects} and {max_tries}")
    if spurious_rate < 0 or attitude_std < 0 or pixel_std < 0:
        raise ValueError("spurious_rate, attitude_std and pixel_std must be >= 0")
    if isinstance(yaw, str) and yaw != "random":
        raise ValueError(f"yaw must be degrees or 'random', got {yaw!r}")


def _label_mix(counts: dict[str, int]) -> tuple[list[str], np.ndarray]:
    """The map's labels and the share of its objects each has."""
    names = list(counts)
    mix = np.array([counts[k] for k in names], dtype=np.float64)
    mix /= mix.sum()
    return names, mix


def _camera_area(
    objects: Objects, bbox: tuple[float, float, float, float] | None, map_name: str
) -> tuple[tuple[float, float, float, float], bool]:
    """Box in which cameras are placed, and whether their whole footprint must stay inside it."""
    if bbox is None:
        area = (
            float(objects.x.min()),
            float(objects.y.min()),
            float(objects.x.max()),
            float(objects.y.max()),
        )
        return area, True
    # Cameras go where the box and the map meet: a box spanning the world (or one side of it)
    # means the whole map, not a strip of empty ground.
    area = (
        max(float(bbox[0]), float(objects.x.min())),
        max(float(bbox[1]), float(objects.y.min())),
        min(float(bbox[2]), float(objects.x.max())),
        min(float(bbox[3]), float(objects.y.max())),
    )
    if not (area[0] <= area[2] and area[1] <= area[3]):
        raise EmptyMapError(f"{map_name}: no object inside bbox {tuple(bbox)}")
    return area, False


def _draw_shot(
    rng: np.random.Generator,
    altitude: float | tuple[float, float],
    fov_deg: float | tuple[float, float],
    size: tuple[int, int],
    yaw: float | str,
    attitude_std: float,
) -> _Shot:
    """Altitude, field of view, heading and attitude of one image."""
    # Draws that every configuration makes, in a fixed order, so that cases differing only in their
    # error levels share camera positions (a paired comparison).
    alt = _draw_range(rng, altitude)
    camera = Camera(int(size[0]), int(size[1]), _draw_range(rng, fov_deg))
    yaw_draw = float(rng.uniform(0.0, 360.0))
    heading = yaw_draw if isinstance(yaw, str) else float(yaw)
    roll, pitch = (float(a) for a in attitude_std * rng.standard_normal(2))
    return _Shot(alt, camera, heading, roll, pitch)


def _placement_limits(
    shot: _Shot, area: tuple[float, float, float, float], keep_inside: bool
) -> tuple[tuple[float, float], tuple[float, float], float]:
    """Lowest and highest camera position allowed, and the ground distance the image can reach."""
    # Footprint corners relative to the camera decide how far from the edge the camera may be.
    corners = footprint(shot.pose(), shot.camera)
    finite = bool(np.all(np.isfinite(corners)))
    if keep_inside and finite:
        lo = area[0] - corners[:, 0].min(), area[1] - corners[:, 1].min()
        hi = area[2] - corners[:, 0].max(), area[3] - corners[:, 1].max()
    else:
        lo, hi = area[:2], area[2:]
    reach = np.nanmax(np.hypot(corners[:, 0], corners[:, 1])) if finite else 50 * shot.altitude
    return lo, hi, reach


def _place_camera(
    rng: np.random.Generator,
    objects: Objects,
    tree: cKDTree,
    shot: _Shot,
    area: tuple[float, float, float, float],
    keep_inside: bool,
    min_objects: int,
    max_tries: int,
    map_name: str,
    i: int,
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """Camera position and the map objects in its image: ``(x, y, map_index, u, v)``."""
    width, height = shot.camera.width, shot.camera.height
    lo, hi, reach = _placement_limits(shot, area, keep_inside)
    for _attempt in range(max_tries if min_objects > 0 else 1):
        if min_objects > 0:
            # Sparse maps: propose a camera that puts a random map object at a random pixel, so that
            # proposals land where there is something to see.  Their density is proportional to the
            # number of objects in view, n; accepting with probability min_objects / n makes the
            # accepted positions uniform over those showing at least min_objects objects.
            anchor = int(rng.integers(len(objects)))
            off_x, off_y = image_to_ground(rng.random() * width, rng.random() * height, shot.pose(), shot.camera)
            cam_x = float(objects.x[anchor] - off_x[0])
            cam_y = float(objects.y[anchor] - off_y[0])
            if not (lo[0] <= cam_x <= hi[0] and lo[1] <= cam_y <= hi[1]):
                continue
        else:
            where = rng.random(2)
            cam_x = lo[0] + where[0] * (hi[0] - lo[0]) if hi[0] > lo[0] else (area[0] + area[2]) / 2.0
            cam_y = lo[1] + where[1] * (hi[1] - lo[1]) if hi[1] > lo[1] else (area[1] + area[3]) / 2.0
            cam_x, cam_y = float(cam_x), float(cam_y)
        near = np.asarray(tree.query_ball_point([cam_x, cam_y], reach * 1.001 + 1e-6), dtype=np.int64)
        near.sort()
        u, v = project_to_image(objects.x[near], objects.y[near], shot.pose(cam_x, cam_y), shot.camera)
        seen = np.isfinite(u) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        n_seen = int(seen.sum())
        if min_objects == 0 or (n_seen >= min_objects and rng.random() * n_seen < min_objects):
            return cam_x, cam_y, near[seen], u[seen], v[seen]
    raise EmptyMapError(
        f"{map_name}: no camera position out of {max_tries} tried shows "
        f"{min_objects} objects (image {i}); lower min_objects or choose a denser bbox"
    )


def _detect(
    rng: np.random.Generator,
    objects: Objects,
    index: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    camera: Camera,
    detector: _Detector,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the detector reports of the visible objects: ``(map_index, u, v, label)``, -1 for spurious."""
    width, height = camera.width, camera.height
    n_visible = index.size
    noise = detector.pixel_std * rng.standard_normal((2, u.size))
    u, v = u + noise[0], v + noise[1]
    # A detector reports positions inside its image: noise that pushes an object out drops it.
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
    _confuse_labels(rng, label_names, detector)
    order = rng.permutation(index.size)
    return index[order], u[order], v[order], label_names[order]


def _confuse_labels(rng: np.random.Generator, label_names: np.ndarray, detector: _Detector) -> None:
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


def _bound(
    objects: Objects,
    index: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    shot: _Shot,
    cam_x: float,
    cam_y: float,
    with_attitude: bool,
) -> dict[str, Any] | None:
    """The truth's ``bound`` entry: :func:`bound_fit` on the true objects and its error."""
    true = index >= 0
    att = (shot.roll, shot.pitch) if with_attitude else (None, None)
    fit = bound_fit(u[true], v[true], objects.x[index[true]], objects.y[index[true]], shot.camera, *att)
    if fit is None:
        return None
    return {
        "x": fit[0],
        "y": fit[1],
        "error_m": math.hypot(fit[0] - cam_x, fit[1] - cam_y),
        "n": int(true.sum()),
    }


def _truth(
    shot: _Shot, cam_x: float, cam_y: float, n_visible: int, index: np.ndarray, bound: dict[str, Any] | None
) -> dict[str, Any]:
    """The ``truth`` entry of an image document."""
    return {
        "x": cam_x,
        "y": cam_y,
        "heading_deg": shot.heading,
        "altitude_m": shot.altitude,
        "roll_deg": shot.roll,
        "pitch_deg": shot.pitch,
        "fov_deg": shot.camera.fov_deg,
        "n_visible": int(n_visible),
        "map_index": index.tolist(),
        "bound": bound,
    }


def _image_document(
    image_id: str, camera: Camera, label_names: np.ndarray, u: np.ndarray, v: np.ndarray
) -> dict[str, Any]:
    """The query-input document of one image, without hints or truth."""
    image: dict[str, Any] = {
        "id": image_id,
        "width": camera.width,
        "height": camera.height,
        "objects": [
            {"label": str(lab), "x": float(px), "y": float(py)} for lab, px, py in zip(label_names, u, v, strict=True)
        ],
        "camera": {"fov_deg": camera.fov_deg},
    }
    return image


def _add_hints(
    rng: np.random.Generator,
    image: dict[str, Any],
    shot: _Shot,
    cam_x: float,
    cam_y: float,
    with_prior: float | None,
    with_attitude: bool,
    with_altitude: bool,
) -> None:
    """Add the position prior, attitude and altitude hints asked for to ``image`` (in place)."""
    if with_prior is not None:
        r = with_prior * math.sqrt(rng.random())
        a = rng.uniform(0.0, 2.0 * math.pi)
        image["prior"] = {
            "x": cam_x + r * math.cos(a),
            "y": cam_y + r * math.sin(a),
            "radius": float(with_prior),
        }
    if with_attitude:
        image["attitude"] = {"roll_deg": shot.roll, "pitch_deg": shot.pitch}
    if with_altitude:
        image["altitude_m"] = shot.altitude


def simulate_images(
    map: Any,
    n: int,
    *,
    altitude: float | tuple[float, float] = 100.0,
    fov_deg: float | tuple[float, float] = 35.0,
    size: tuple[int, int] = (640, 480),
    yaw: float | str = 0.0,
    attitude_std: float = 0.0,
    pixel_std: float = 0.0,
    miss_rate: float = 0.0,
    spurious_rate: float = 0.0,
    label_noise: float = 0.0,
    with_prior: float | None = None,
    with_attitude: bool = False,
    with_altitude: bool = False,
    bbox: tuple[float, float, float, float] | None = None,
    min_objects: int = 0,
    max_tries: int = 10_000,
    seed: int = 0,
    id_prefix: str = "sim-",
    progress: ProgressLike = None,
) -> list[dict[str, Any]]:
    """Simulated image-objects documents over a map, each with its truth.

    Parameters
    ----------
    map : MetaMap or Objects
        Anything with ``.all()`` returning :class:`Objects` in projected metres, or the objects themselves.
    n : int
        Number of images.
    altitude, fov_deg : float or (low, high)
        Height above ground (m) and horizontal field of view (degrees); a pair draws uniformly per image.
    size : (width, height)
        Image size in pixels.
    yaw : float or "random"
        Heading in degrees (clockwise from north), or uniform in [0, 360) per image.
    attitude_std : float
        Standard deviation (degrees) of the roll and pitch (normal, independent): the camera's tilt error.
    pixel_std : float
        Standard deviation (pixels) of the detector's error on each object's x and y.
    miss_rate : float
        Probability that the detector misses each visible object.
    spurious_rate : float
        Mean number of extra objects per visible true object (Poisson), at uniform random pixels, labels
        drawn from the map's label mix.
    label_noise : float
        Probability that an object (true or spurious) is given a wrong label, drawn from the map's label mix
        without its own label; no effect on a map with a single label.
    with_prior : float, optional
        Adds ``"prior": {"x", "y", "radius": with_prior}`` centred at an offset drawn uniformly within the
        radius of the truth.
    with_attitude : bool
        Adds the true roll and pitch as ``"attitude"`` (an AHRS).
    with_altitude : bool
        Adds the true height above ground as ``"altitude_m"`` (an altimeter).
    bbox : (minx, miny, maxx, maxy), optional
        Map-CRS box in which camera positions are drawn.  By default the map's extent, shrunk so that the
        whole footprint stays inside it.
    min_objects : int
        Draw camera positions (up to ``max_tries`` proposals, else :class:`EmptyMapError`) uniformly over
        the places from which at least this many map objects are in the image, before detector errors.  For
        sparse real maps, where most of the bounding box shows nothing.
    max_tries : int
        Position draws per image allowed by ``min_objects``.
    seed : int
        Image ``i`` depends only on ``(seed, i)``: the same seed gives the same images, and the first
        images of a longer run are those of a shorter one.
    id_prefix : str
        Images are named ``f"{id_prefix}{i:06d}"``.
    progress : Progress or callable, optional
        Counts the images made (:class:`mapdb.outputs.Progress`).

    Returns
    -------
    list of dict
        Query-input documents (``id``, ``width``, ``height``, ``objects``, ``camera``, optional ``prior``,
        ``attitude``, ``altitude_m``) with a ``truth`` entry: ``x``, ``y`` (the camera nadir),
        ``heading_deg``, ``altitude_m``, ``roll_deg``, ``pitch_deg``, ``fov_deg``, ``map_index`` (per
        object, its index in ``map.all()``, or -1 for a spurious object) and ``bound`` (``x``, ``y``,
        ``error_m``, ``n`` of the least-squares fit with the true correspondences; None with < 2).
    """
    _check_simulate_args(n, yaw, attitude_std, pixel_std, miss_rate, spurious_rate, label_noise, min_objects, max_tries)
    map_name = getattr(map, "path", None) or "map"
    objects, counts = _map_objects(map)
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    names, mix = _label_mix(counts)
    detector = _Detector(pixel_std, miss_rate, spurious_rate, label_noise, names, mix)
    area, keep_inside = _camera_area(objects, bbox, map_name)

    say = as_progress(progress)
    say.start(n, "simulate")
    images = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        shot = _draw_shot(rng, altitude, fov_deg, size, yaw, attitude_std)
        cam_x, cam_y, index, u, v = _place_camera(
            rng, objects, tree, shot, area, keep_inside, min_objects, max_tries, map_name, i
        )
        n_visible = index.size
        index, u, v, label_names = _detect(rng, objects, index, u, v, shot.camera, detector)
        bound = _bound(objects, index, u, v, shot, cam_x, cam_y, with_attitude)
        image = _image_document(f"{id_prefix}{i:06d}", shot.camera, label_names, u, v)
        _add_hints(rng, image, shot, cam_x, cam_y, with_prior, with_attitude, with_altitude)
        image["truth"] = _truth(shot, cam_x, cam_y, n_visible, index, bound)
        images.append(image)
        say.advance()
    say.done()
    return images


def simulate_image_at(
    objects: Objects,
    pose: Pose,
    camera: Camera,
    rng: np.random.Generator,
    *,
    pixel_std: float = 0.0,
    miss_rate: float = 0.0,
    spurious_rate: float = 0.0,
    label_noise: float = 0.0,
    label_counts: dict[str, int] | None = None,
    with_prior: float | None = None,
    image_id: str = "sim",
) -> dict[str, Any]:
    """One simulated image taken from a given pose: the steps of :func:`simulate_images` without the draw
    of the camera's place.

    Parameters
    ----------
    objects : Objects
        Map objects the camera may see (those around ``pose`` are enough); ``truth.map_index`` indexes them.
    pose : Pose
        Camera position (map metres), altitude, heading, roll and pitch (degrees).
    camera : Camera
        Image size and field of view.
    rng : numpy.random.Generator
        Draws the detector's errors and the prior's offset, in the order :func:`simulate_images` draws them.
    pixel_std, miss_rate, spurious_rate, label_noise : float
        The detector's error model, as for :func:`simulate_images`.
    label_counts : dict, optional
        Objects per label that spurious and confused labels are drawn from (the whole map's, so that a
        place's own mix does not leak into its errors); by default those of ``objects``.
    with_prior : float, optional
        Adds a prior of this radius centred within it of the truth.
    image_id : str
        The document's ``id``.

    Returns
    -------
    dict
        A query-input document with its ``truth``, as :func:`simulate_images` makes them.

    Examples
    --------
    >>> image = simulate_image_at(paper_map(), Pose(500_125.0, 5_000_075.0, 100.0), Camera(),
    ...                           np.random.default_rng(1))
    >>> len(image["objects"]) == image["truth"]["n_visible"] > 0
    True
    """
    _check_simulate_args(1, 0.0, 0.0, pixel_std, miss_rate, spurious_rate, label_noise, 0, 1)
    # (with no objects at all nothing is ever drawn from the mix; a placeholder keeps it well defined)
    names, mix = _label_mix(label_counts or objects.counts() or {"": 1})
    detector = _Detector(pixel_std, miss_rate, spurious_rate, label_noise, names, mix)
    shot = _Shot(pose.altitude, camera, pose.yaw_deg, pose.roll_deg, pose.pitch_deg)
    u, v = project_to_image(objects.x, objects.y, pose, camera)
    seen = np.isfinite(u) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    index = np.flatnonzero(seen).astype(np.int64)
    index, u, v, label_names = _detect(rng, objects, index, u[seen], v[seen], camera, detector)
    bound = _bound(objects, index, u, v, shot, pose.x, pose.y, False)
    image = _image_document(image_id, camera, label_names, u, v)
    _add_hints(rng, image, shot, pose.x, pose.y, with_prior, False, False)
    image["truth"] = _truth(shot, pose.x, pose.y, int(seen.sum()), index, bound)
    return image


def map_bbox_from_lonlat(
    crs: str,
    bbox: tuple[float, float, float, float],
    within: tuple[float, float, float, float] | None = None,
) -> tuple[float, float, float, float]:
    """A box of the map's projected CRS holding every place of ``within`` whose lon/lat is in ``bbox``.

    ``bbox`` may span the world, touch the poles or cross the antimeridian (``minlon > maxlon``).
    ``within`` is where the map lies (its ``bounds``); without it, the CRS's area of use.  The box
    may be larger than needed, and is unbounded (infinite) when the CRS cannot say;
    :func:`simulate_images` cuts it to the map's objects.  :class:`EmptyMapError` if the two do not meet.
    """
    from ..geo import bbox_text, check_bbox, projected_window

    window = projected_window(crs, check_bbox(bbox), within=within)
    if window is None:
        raise EmptyMapError(f"bbox {bbox_text(bbox)} does not meet the map")
    return window


def write_images(images: Sequence[dict[str, Any]], path: str | Path | None) -> None:
    """Write image documents as strict JSON Lines to ``path`` (stdout if None or ``"-"``), atomically."""
    with atomic_open("-" if path is None else path) as f:
        for im in images:
            f.write(json.dumps(im, separators=(",", ":"), allow_nan=False) + "\n")
