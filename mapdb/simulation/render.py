"""Label masks rendered from a scene's shapes through the pinhole camera of :mod:`mapdb.camera`.

What a segmentation model would output for a simulated image: one class code per pixel (0 for
nothing), made from the outlines of :class:`mapdb.simulation.outlines.Scene` seen from a camera pose.

Geometry
--------
A point ``(X, Y, Z)`` above flat ground projects as in :mod:`mapdb.camera` with the camera height
``altitude - Z`` (:func:`mapdb.camera.project_points`).  A building is a prism: its footprint at ``Z = 0``,
its roof at ``Z = height`` and one wall quad per footprint edge; the image of the prism is the union
of the images of these faces, so all are burnt into the mask with the building's value.  Vertical
lines project to lines through the nadir pixel, so a roof at ``h`` is displaced away from the nadir:
on a level camera by ``r * h / (H - h)`` in image terms, where ``r`` is the footprint point's distance
from the nadir, i.e. ``h * r / H`` metres of ground at the roof's own scale (relief displacement).
Heights are capped at :data:`MAX_HEIGHT_FRACTION` of the altitude (a taller building would hold the
camera under its roof).

Painter's order (later shapes hide earlier ones)
------------------------------------------------
1. ground areas (parks, water, pitches, ...), largest first, so a pitch inside a park stays visible;
2. marks on the ground (road rings, intersection discs), largest first;
3. buildings, farthest from the nadir first (distance from the nadir to the nearest point of the
   footprint): relief pushes roofs away from the nadir, so a nearer building can hide a farther one,
   never the reverse.

Rasterisation burns a pixel when its centre ``(col + 0.5, row + 0.5)`` lies inside a shape
(``rasterio.features.rasterize``, one call per image); the image border clips everything.  Touching
shapes of one class form one connected region of the mask, as they would in a model's output.

Imperfections (seeded by the caller's generator)
------------------------------------------------
* ``miss_rate``: each object is left out with this probability (the ground under it shows);
* ``mask_noise_px``: each object's image is grown or shrunk by a distance drawn uniformly in
  ``[-mask_noise_px, +mask_noise_px]`` pixels (a shapely buffer of the union of its faces), so
  blobs fatten, thin, merge, split or vanish as a model's masks do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from affine import Affine
from rasterio.features import rasterize

from ..camera import Camera, Pose, footprint, nadir_pixel, project_points
from ..detections.masks import DEFAULT_MIN_AREA_PX
from .outlines import LAYER_BUILDING, Scene

__all__ = ["MAX_HEIGHT_FRACTION", "Rendering", "blob_sources", "render_mask"]

MAX_HEIGHT_FRACTION = 0.9
# When the image reaches the horizon (its ground footprint is unbounded), only shapes within this many
# altitudes of the nadir are drawn (farther ones would be a few pixels at the horizon), and faces with a
# vertex at or behind the camera's horizon are left out.
_HORIZON_REACH = 50.0


@dataclass(frozen=True)
class Rendering:
    """A rendered image: ``mask`` (class codes, 0 nothing), ``instance`` (scene index + 1, 0 nothing).

    ``classes`` maps the mask's codes to label names: code ``c`` is ``labels[c - 1]``.
    """

    mask: np.ndarray
    instance: np.ndarray
    classes: dict[int, str]


def _candidates(scene: Scene, pose: Pose, camera: Camera) -> np.ndarray:
    """Indices of the shapes that may show in the image (sorted)."""
    corners = footprint(pose, camera)
    if not np.all(np.isfinite(corners)):
        area = shapely.Point(pose.x, pose.y).buffer(_HORIZON_REACH * pose.altitude)
    else:
        area = shapely.Polygon(corners)
        u, v = nadir_pixel(camera, pose.roll_deg, pose.pitch_deg)
        if not (0.0 <= u <= camera.width and 0.0 <= v <= camera.height) and len(scene):
            # Relief leans roofs away from the nadir: inward only when the nadir is outside the image.
            h = min(float(scene.height.max()), MAX_HEIGHT_FRACTION * pose.altitude)
            reach = float(np.hypot(corners[:, 0] - pose.x, corners[:, 1] - pose.y).max())
            area = area.buffer(reach * h / (pose.altitude - h))
    return np.sort(scene.tree.query(area, predicate="intersects")).astype(np.int64)


def _painter_order(scene: Scene, index: np.ndarray, pose: Pose) -> np.ndarray:
    """``index`` in drawing order (see the module docs)."""
    geoms = scene.geometry[index]
    layer = scene.layer[index]
    building = layer == LAYER_BUILDING
    size = shapely.area(geoms)
    distance = shapely.distance(shapely.Point(pose.x, pose.y), geoms)
    key = np.where(building, -distance, -size)
    return index[np.lexsort((index, key, layer))]


def _faces(
    geoms: np.ndarray, height: np.ndarray, pose: Pose, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """Image polygons of each shape's faces (footprint, and roof and walls when tall) and their owners."""
    parts, part_of = shapely.get_parts(geoms, return_index=True)
    rings, ring_of = shapely.get_rings(parts, return_index=True)
    xy, coord_of = shapely.get_coordinates(rings, return_index=True)
    owner = part_of[ring_of[coord_of]]
    z = height[owner]
    ground = np.column_stack(project_points(xy[:, 0], xy[:, 1], 0.0, pose, camera))
    # A part with a vertex behind the camera (a banked camera, a roof near its height) has no image polygon:
    # left out, as the non-finite faces are below (a ring of NaNs is not even closed).
    ground_ok = _finite_parts(ground, ring_of[coord_of], parts.size)
    faces = [shapely.transform(parts[ground_ok], lambda _: ground[ground_ok[ring_of[coord_of]]])]
    owners = [part_of[ground_ok]]
    tall_part = height[part_of] > 0
    if tall_part.any():
        top = np.column_stack(project_points(xy[:, 0], xy[:, 1], z, pose, camera))
        tall_part &= _finite_parts(top, ring_of[coord_of], parts.size) & ground_ok
        tall_coord = tall_part[ring_of[coord_of]]
        faces.append(shapely.transform(parts[tall_part], lambda _: top[tall_coord]))
        owners.append(part_of[tall_part])
        # Wall quads: consecutive vertices of one ring (rings are closed, so every edge is there).
        edge = np.flatnonzero((coord_of[1:] == coord_of[:-1]) & tall_coord[1:])
        a, b = edge, edge + 1
        quads = np.stack([ground[a], ground[b], top[b], top[a], ground[a]], axis=1)
        faces.append(shapely.polygons(quads))
        owners.append(owner[a])
    all_faces, all_owners = np.concatenate(faces), np.concatenate(owners)
    finite = np.isfinite(shapely.bounds(all_faces)).all(axis=1)
    return all_faces[finite], all_owners[finite]


def _finite_parts(image: np.ndarray, part_of_coord: np.ndarray, n: int) -> np.ndarray:
    """Whether every projected vertex of each of ``n`` parts is finite."""
    bad = np.bincount(part_of_coord, weights=~np.isfinite(image).all(axis=1), minlength=n)
    return np.asarray(bad == 0)


def _noisy(
    faces: np.ndarray, owner: np.ndarray, n: int, noise_px: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Each owner's faces merged and grown or shrunk by a uniform random distance (pixels)."""
    distance = rng.uniform(-noise_px, noise_px, n)
    order = np.argsort(owner, kind="stable")
    starts = np.searchsorted(owner[order], np.arange(n + 1))
    merged = np.array(
        [shapely.union_all(faces[order[starts[k]:starts[k + 1]]]) for k in range(n)], dtype=object
    )  # one union per object in view: tens to hundreds per image
    return shapely.buffer(merged, distance, quad_segs=4), np.arange(n)


def _burn(faces: np.ndarray, values: np.ndarray, rank: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """An int32 raster of ``values`` burnt face by face in ``rank`` order (later faces over earlier)."""
    keep = ~shapely.is_empty(faces)
    order = np.flatnonzero(keep)[np.argsort(rank[keep], kind="stable")]  # an object's faces together
    if not order.size:
        return np.zeros(shape, np.int32)
    return rasterize(zip(faces[order], values[order].tolist(), strict=True), out_shape=shape, fill=0,
                     transform=Affine.identity(), dtype="int32")


def render_mask(
    scene: Scene,
    pose: Pose,
    camera: Camera,
    *,
    heights: bool = True,
    mask_noise_px: float = 0.0,
    miss_rate: float = 0.0,
    rng: np.random.Generator | None = None,
) -> Rendering:
    """The label mask of the image a camera at ``pose`` takes of ``scene`` (see the module docs).

    Parameters
    ----------
    scene : Scene
        Shapes in the map's CRS (:func:`mapdb.simulation.outlines.read_scene`).
    pose, camera : Pose, Camera
        Where the camera is and what it is (:mod:`mapdb.camera`); the mask is ``ceil(height)`` by
        ``ceil(width)`` pixels.
    heights : bool
        Extrude buildings to their heights; False draws every shape flat on the ground.
    mask_noise_px : float
        Largest distance (pixels) by which an object's image is grown or shrunk.
    miss_rate : float
        Probability that an object is left out.
    rng : numpy Generator, optional
        Draws the noise and the misses (needed when either is non-zero).

    Examples
    --------
    >>> from mapdb.simulation.outlines import Scene
    >>> square = shapely.box(-5.0, -5.0, 5.0, 5.0)
    >>> scene = Scene(np.array([square]), np.array([0]), np.array([0.0]), np.array([2]), np.array([0]),
    ...               np.array([0]), ("building",), "EPSG:32632")
    >>> cam = Camera(64, 48, 60.0)
    >>> r = render_mask(scene, Pose(0.0, 0.0, 20.0), cam)  # a flat 10 m square seen from 20 m: 27.7 px a side
    >>> side = 10.0 * cam.focal_px / 20.0
    >>> r.classes, r.mask.shape, bool(abs((r.mask == 1).sum() - side**2) < 2 * side)
    ({1: 'building'}, (48, 64), True)
    """
    if (mask_noise_px > 0 or miss_rate > 0) and rng is None:
        raise ValueError("mask noise and missed objects need a random generator (rng)")
    shape = (math.ceil(camera.height), math.ceil(camera.width))
    index = _candidates(scene, pose, camera)
    if miss_rate > 0 and rng is not None:
        index = index[rng.random(index.size) >= miss_rate]
    index = _painter_order(scene, index, pose)
    height = np.minimum(scene.height[index], MAX_HEIGHT_FRACTION * pose.altitude) if heights else np.zeros(index.size)
    faces, owner = _faces(scene.geometry[index], height, pose, camera)
    if mask_noise_px > 0 and rng is not None:
        faces, owner = _noisy(faces, owner, index.size, mask_noise_px, rng)
    instance = _burn(faces, index[owner] + 1, owner, shape)
    dtype = np.uint8 if len(scene.labels) < 255 else np.uint16
    lut = np.concatenate([[0], scene.label.astype(np.int64) + 1]).astype(dtype)
    classes = {code + 1: name for code, name in enumerate(scene.labels)}
    return Rendering(lut[instance], instance, classes)


def blob_sources(
    rendering: Rendering,
    map_index: np.ndarray,
    doc: dict[str, Any],
    *,
    connectivity: int = 8,
    min_area: int = DEFAULT_MIN_AREA_PX,
) -> list[list[tuple[int, int]]]:
    """For each object of ``doc`` (:func:`mapdb.detections.masks.from_mask` of ``rendering.mask``), the map objects its
    blob covers: ``(map index, pixels)`` pairs, most pixels first (shapes linked to no map object left out).

    ``map_index`` is the scene's (:attr:`Scene.map_index`).  The blobs are found again as ``from_mask``
    finds them (each class in ascending code order, its regions in scan order, those of at least
    ``min_area`` pixels), and checked against the document's centroids.
    """
    from scipy import ndimage

    structure = np.ones((3, 3), bool) if connectivity == 8 else ndimage.generate_binary_structure(2, 1)
    # Each pixel's map object, renumbered 0..m-1 over those present (-1, no map object, among them).
    map_of_instance = np.concatenate([[-1], np.asarray(map_index, np.int64)])
    present_instances = np.flatnonzero(np.bincount(rendering.instance.ravel()))
    present_maps, compact = np.unique(map_of_instance[present_instances], return_inverse=True)
    lut = np.zeros(map_of_instance.size, np.int64)
    lut[present_instances] = compact.reshape(-1)
    pixel_map = lut[rendering.instance.ravel()]
    m = present_maps.size
    out: list[list[tuple[int, int]]] = []
    centroids: list[np.ndarray] = []
    for code in sorted(c for c in np.unique(rendering.mask).tolist() if c in rendering.classes):
        labelled, n = ndimage.label(rendering.mask == code, structure=structure)
        where = np.flatnonzero(labelled.ravel())
        blob = labelled.ravel()[where]
        area = np.bincount(blob, minlength=n + 1)
        rows, cols = np.divmod(where, rendering.mask.shape[1])
        with np.errstate(invalid="ignore", divide="ignore"):
            cx = np.bincount(blob, cols, n + 1) / area + 0.5
            cy = np.bincount(blob, rows, n + 1) / area + 0.5
        kept = np.flatnonzero(area >= max(min_area, 1))
        kept = kept[kept > 0]
        centroids.append(np.column_stack([cx[kept], cy[kept]]))
        px = np.bincount(blob * m + pixel_map[where], minlength=(n + 1) * m).reshape(n + 1, m)
        for k in kept.tolist():
            found = np.flatnonzero((px[k] > 0) & (present_maps >= 0))
            found = found[np.argsort(-px[k, found], kind="stable")]
            out.append([(int(present_maps[j]), int(px[k, j])) for j in found])
    got = np.array([[o["x"], o["y"]] for o in doc["objects"]], np.float64).reshape(-1, 2)
    mine_xy = np.concatenate(centroids) if centroids else np.zeros((0, 2))
    if got.shape != mine_xy.shape or not np.allclose(got, mine_xy, atol=1e-3):
        raise ValueError("the document's objects are not the blobs of this rendering")
    return out
