"""Where the simulated camera is: its altitude, field of view, heading and attitude, and its place over the map.

The steps that :func:`~mapdb.simulation.simulate.simulate_images` and the rendered-mask simulator
(:mod:`mapdb.simulation.rendered`) take for each image, and the flight simulator
(:mod:`mapdb.navigation.flight`) for each frame: draw a :class:`Shot` (the camera before it is placed),
find the box cameras may go in (:func:`camera_area`), and place the camera where it sees enough of the
map (:func:`place_camera`).  The camera model and its conventions are :mod:`mapdb.camera`'s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._scipy import cKDTree
from ..camera import Camera, Pose, footprint, image_to_ground, project_points, project_to_image
from ..errors import EmptyMapError
from ..labels import BLOCK_LABEL
from ..objects import Objects

if TYPE_CHECKING:
    from .terrain import Terrain

__all__ = [
    "Shot",
    "camera_area",
    "draw_shot",
    "map_bbox_from_lonlat",
    "place_camera",
    "placement_limits",
]


@dataclass(frozen=True)
class Shot:
    """One image's camera before it is placed: what every configuration draws, in a fixed order."""

    altitude: float
    camera: Camera
    heading: float
    roll: float
    pitch: float

    def pose(self, x: float = 0.0, y: float = 0.0) -> Pose:
        """This camera placed with its nadir at ``(x, y)`` (map metres)."""
        return Pose(x, y, self.altitude, self.heading, self.roll, self.pitch)


def _draw_range(rng: np.random.Generator, value: float | tuple[float, float]) -> float:
    if isinstance(value, tuple | list):
        lo, hi = value
        return float(rng.uniform(lo, hi))
    return float(value)


def draw_shot(
    rng: np.random.Generator,
    altitude: float | tuple[float, float],
    fov_deg: float | tuple[float, float],
    size: tuple[int, int],
    yaw: float | str,
    attitude_std: float,
) -> Shot:
    """Altitude, field of view, heading and attitude of one image."""
    # Draws that every configuration makes, in a fixed order, so that cases differing only in their
    # error levels share camera positions (a paired comparison).
    alt = _draw_range(rng, altitude)
    camera = Camera(int(size[0]), int(size[1]), _draw_range(rng, fov_deg))
    yaw_draw = float(rng.uniform(0.0, 360.0))
    heading = yaw_draw if isinstance(yaw, str) else float(yaw)
    roll, pitch = (float(a) for a in attitude_std * rng.standard_normal(2))
    return Shot(alt, camera, heading, roll, pitch)


def camera_area(
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


def placement_limits(
    shot: Shot, area: tuple[float, float, float, float], keep_inside: bool
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


def place_camera(
    rng: np.random.Generator,
    objects: Objects,
    tree: cKDTree,
    shot: Shot,
    area: tuple[float, float, float, float],
    keep_inside: bool,
    min_objects: int,
    max_tries: int,
    map_name: str,
    i: int,
    terrain: Terrain | None = None,
) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """Camera position and the map objects in its image: ``(x, y, map_index, u, v)``; with ``terrain`` the
    objects at their heights and the camera above the ground or the datum (:mod:`~mapdb.simulation.terrain`).

    A map's blocks of touching buildings (:mod:`mapdb.build.blocks`) are never seen: a camera sees their
    buildings, and only a mask merges them (:mod:`mapdb.simulation.rendered` says which blobs stand for blocks).
    """
    width, height = shot.camera.width, shot.camera.height
    lo, hi, reach = placement_limits(shot, area, keep_inside)
    if terrain is not None:  # ground below the nadir's is seen farther out
        reach *= 1.0 + float(np.ptp(terrain.z)) / shot.altitude
    block = objects.labels.index(BLOCK_LABEL) if BLOCK_LABEL in objects.labels else -1
    for _attempt in range(max_tries if min_objects > 0 or terrain is not None else 1):
        if min_objects > 0:
            # Sparse maps: propose a camera that puts a random map object at a random pixel, so that
            # proposals land where there is something to see.  Their density is proportional to the
            # number of objects in view, n; accepting with probability min_objects / n makes the
            # accepted positions uniform over those showing at least min_objects objects.
            anchor = int(rng.integers(len(objects)))
            if objects.label[anchor] == block:
                continue  # proposals anchored on what a camera sees, so that they stay uniform over it
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
        if terrain is None:
            u, v = project_to_image(objects.x[near], objects.y[near], shot.pose(cam_x, cam_y), shot.camera)
        else:
            placed = terrain.placed(shot.altitude, cam_x, cam_y)
            if placed is None:  # a datum altitude too close to the ground here: another place
                continue
            pose = Pose(cam_x, cam_y, placed[1], shot.heading, shot.roll, shot.pitch)
            u, v = project_points(objects.x[near], objects.y[near], terrain.z[near], pose, shot.camera)
        seen = np.isfinite(u) & (u >= 0) & (u < width) & (v >= 0) & (v < height) & (objects.label[near] != block)
        n_seen = int(seen.sum())
        if min_objects == 0 or (n_seen >= min_objects and rng.random() * n_seen < min_objects):
            return cam_x, cam_y, near[seen], u[seen], v[seen]
    raise EmptyMapError(
        f"{map_name}: no camera position out of {max_tries} tried shows "
        f"{min_objects} objects (image {i}); lower min_objects or choose a denser bbox"
    )


def map_bbox_from_lonlat(
    crs: str,
    bbox: tuple[float, float, float, float],
    within: tuple[float, float, float, float] | None = None,
) -> tuple[float, float, float, float]:
    """A box of the map's projected CRS holding every place of ``within`` whose lon/lat is in ``bbox``.

    ``bbox`` may span the world, touch the poles or cross the antimeridian (``minlon > maxlon``).
    ``within`` is where the map lies (its ``bounds``); without it, the CRS's area of use.  The box
    may be larger than needed, and is unbounded (infinite) when the CRS cannot say;
    :func:`~mapdb.simulation.simulate.simulate_images` cuts it to the map's objects.  :class:`EmptyMapError`
    if the two do not meet.
    """
    from ..geo import bbox_text, check_bbox, projected_window

    window = projected_window(crs, check_bbox(bbox), within=within)
    if window is None:
        raise EmptyMapError(f"bbox {bbox_text(bbox)} does not meet the map")
    return window
