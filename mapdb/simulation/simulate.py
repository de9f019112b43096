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

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from .._scipy import cKDTree
from ..camera import Camera, Pose, in_image, project_to_image
from ..errors import EmptyMapError
from ..labels import BLOCK_LABEL
from ..objects import Objects
from ..progress import ProgressLike, as_progress
from .detector import Detector, detect, label_mix
from .documents import add_hints, bound_entry, image_document, truth_entry
from .poses import Shot, camera_area, draw_shot, place_camera

if TYPE_CHECKING:
    from .terrain import Terrain

__all__ = [
    "PAPER_CRS",
    "PAPER_ORIGIN",
    "USABLE_OBJECTS",
    "check_simulate_args",
    "detectable",
    "objects_of_map",
    "paper_density",
    "paper_map",
    "simulate_image_at",
    "simulate_images",
    "visible_objects",
    "sparse_images",
]

# The paper's map is abstract; it gets real-looking UTM metres so that every tool treats it like any
# other map (lon/lat output, CRS checks).  UTM 31N at about 45.1 N, 3 E.
PAPER_CRS = "EPSG:32631"
PAPER_ORIGIN = (500_000.0, 5_000_000.0)
# The fewest objects from which the fast matcher finds a place (one quad; analysis.measures.MIN_VISIBLE).
USABLE_OBJECTS = 4


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


def objects_of_map(map_: Any) -> tuple[Objects, dict[str, int]]:
    """All objects of a map (MetaMap-like or :class:`Objects`) and the label counts a detector's errors draw from.

    The objects keep the map's order (``truth.map_index`` indexes ``map.all()``), blocks of touching buildings
    included; the counts leave the blocks out: a detector sees buildings, so neither a spurious object nor a
    confused label is ever a block.
    """
    objects = map_ if isinstance(map_, Objects) else map_.all()
    if not len(objects):
        raise EmptyMapError(f"{getattr(map_, 'path', None) or 'map'}: the map has no objects to simulate images of")
    counts = objects.counts()
    counts.pop(BLOCK_LABEL, None)
    return objects, counts


def check_simulate_args(
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
    terrain: Terrain | None = None,
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
        Counts the images made (:class:`mapdb.progress.Progress`).
    terrain : Terrain, optional
        Objects at their ground elevations and ``altitude`` above the ground under the camera or above the
        datum (:mod:`mapdb.simulation.terrain`); the documents' ``altitude_m`` is then the camera's height
        above the ground under it, and the truth adds ``ground_m`` and ``altitude_datum_m``.

    Returns
    -------
    list of dict
        Query-input documents (``id``, ``width``, ``height``, ``objects``, ``camera``, optional ``prior``,
        ``attitude``, ``altitude_m``) with a ``truth`` entry: ``x``, ``y`` (the camera nadir),
        ``heading_deg``, ``altitude_m``, ``roll_deg``, ``pitch_deg``, ``fov_deg``, ``map_index`` (per
        object, its index in ``map.all()``, or -1 for a spurious object) and ``bound`` (``x``, ``y``,
        ``error_m``, ``n`` of the least-squares fit with the true correspondences; None with < 2).
    """
    check_simulate_args(n, yaw, attitude_std, pixel_std, miss_rate, spurious_rate, label_noise, min_objects, max_tries)
    map_name = getattr(map, "path", None) or "map"
    objects, counts = objects_of_map(map)
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    names, mix = label_mix(counts)
    detector = Detector(pixel_std, miss_rate, spurious_rate, label_noise, names, mix)
    area, keep_inside = camera_area(objects, bbox, map_name)

    say = as_progress(progress)
    say.start(n, "simulate")
    images = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        shot = draw_shot(rng, altitude, fov_deg, size, yaw, attitude_std)
        cam_x, cam_y, index, u, v = place_camera(
            rng, objects, tree, shot, area, keep_inside, min_objects, max_tries, map_name, i, terrain
        )
        placed = terrain.placed(shot.altitude, cam_x, cam_y) if terrain is not None else None
        if placed is not None:  # what an altimeter over this ground reads: the height above it
            shot = replace(shot, altitude=placed[1] - placed[0])
        n_visible = index.size
        index, u, v, label_names = detect(rng, objects, index, u, v, shot.camera, detector)
        bound = bound_entry(objects, index, u, v, shot, cam_x, cam_y, with_attitude)
        image = image_document(f"{id_prefix}{i:06d}", shot.camera, label_names, u, v)
        add_hints(rng, image, shot, cam_x, cam_y, with_prior, with_attitude, with_altitude)
        image["truth"] = truth_entry(shot, cam_x, cam_y, n_visible, index, bound)
        if placed is not None:
            image["truth"].update(ground_m=placed[0], altitude_datum_m=placed[1])
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
    check_simulate_args(1, 0.0, 0.0, pixel_std, miss_rate, spurious_rate, label_noise, 0, 1)
    # (with no objects at all nothing is ever drawn from the mix; a placeholder keeps it well defined)
    own = {name: n for name, n in objects.counts().items() if name != BLOCK_LABEL}  # blocks are never detected
    names, mix = label_mix(label_counts or own or {"": 1})
    detector = Detector(pixel_std, miss_rate, spurious_rate, label_noise, names, mix)
    shot = Shot(pose.altitude, camera, pose.yaw_deg, pose.roll_deg, pose.pitch_deg)
    u, v, seen = visible_objects(objects, pose, camera)
    index = np.flatnonzero(seen).astype(np.int64)
    index, u, v, label_names = detect(rng, objects, index, u[seen], v[seen], camera, detector)
    bound = bound_entry(objects, index, u, v, shot, pose.x, pose.y, False)
    image = image_document(image_id, camera, label_names, u, v)
    add_hints(rng, image, shot, pose.x, pose.y, with_prior, False, False)
    image["truth"] = truth_entry(shot, pose.x, pose.y, int(seen.sum()), index, bound)
    return image


def sparse_images(images: Sequence[dict[str, Any]], map_name: str) -> str | None:
    """Why most of ``images`` cannot be localized, or None: a median below :data:`USABLE_OBJECTS` objects an image.

    Camera positions are uniform over the map's bounds (or the bbox) unless ``min_objects`` is given: over an
    extract that is mostly empty ground (mountains, sea) or with a narrow view, most images show nothing to
    match.  The message names the median and the option that fixes it.

    Examples
    --------
    >>> print(sparse_images([{"objects": [1]}, {"objects": []}, {"objects": [1, 2]}], "a.mapdb"))  # doctest: +ELLIPSIS
    a.mapdb: a median of 1 objects an image (3 of 3 images show fewer than 4, ... --min-objects 6 draws them ...
    >>> sparse_images([{"objects": [1, 2, 3, 4]}], "a.mapdb") is None
    True
    """
    counts = np.array([len(im.get("objects", ())) for im in images])
    if not counts.size or float(np.median(counts)) >= USABLE_OBJECTS:
        return None
    few = int((counts < USABLE_OBJECTS).sum())
    return (f"{map_name}: a median of {float(np.median(counts)):g} objects an image ({few} of {counts.size} images "
            f"show fewer than {USABLE_OBJECTS}, the fewest the matcher localizes from): camera positions are drawn "
            "uniformly over the map's bounds, where most places show no object at this altitude and field of view; "
            "--min-objects 6 draws them where 6 objects are in view (or widen the view: --altitude, --fov)")


def visible_objects(objects: Objects, pose: Pose, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every object's pixels ``u, v`` under ``pose`` and which of them the camera sees (bool): those inside the
    image, blocks left out (a camera sees the buildings of a block, never the block: :func:`place_camera`).

    Examples
    --------
    >>> u, v, seen = visible_objects(paper_map(), Pose(500_125.0, 5_000_075.0, 100.0), Camera())
    >>> bool(seen.any()), u.shape == seen.shape
    (True, True)
    """
    u, v = project_to_image(objects.x, objects.y, pose, camera)
    seen = in_image(u, v, camera)
    shown = detectable(objects.label, objects.labels)
    return u, v, seen if shown is None else seen & shown


def detectable(label: np.ndarray, labels: Sequence[str]) -> np.ndarray | None:
    """Which objects (their label codes ``label`` in ``labels``) a camera can show: all but blocks (it sees the
    buildings of a block, never the block: :func:`place_camera`); None when every one can (no blocks)."""
    return label != labels.index(BLOCK_LABEL) if BLOCK_LABEL in labels else None
