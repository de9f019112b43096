"""A flight's frames whose objects come from rendered label masks: ``mapdb simulate flight --render masks``.

Each frame's label mask is rendered from the source's outlines with the frame's own camera pose (its
altitude, heading, the coordinated turn's bank and the turbulence on roll and pitch) by
:func:`mapdb.simulation.render.render_mask` (buildings extruded to their heights unless ``heights`` is
False), the segmentation errors below are applied to the mask, and its objects are extracted exactly as
``mapdb objects`` does (:func:`mapdb.detections.masks.from_mask`); the truth says which map object each
blob covers (:func:`mapdb.simulation.render.blob_sources`).

Segmentation errors, all drawn from the frame's own generator (same seed, same flight):

* ``mask_offset_px`` (an integer): every labelled region eroded (negative) or dilated (positive) by this
  many pixels with a disc: a pixel stays labelled after erosion when every pixel within the disc has its
  code; a background pixel takes the largest code within the disc after dilation.  The image border does
  not erode (a model sees no edge there): pixels outside the image repeat the nearest ones.
* ``blob_miss_rate``: each object is left out of the mask with this probability (the ground under it
  shows), as :func:`~mapdb.simulation.render.render_mask`'s ``miss_rate``;
* ``blob_spurious_rate``: about this many false blobs per object in view (a Poisson draw): squares of the
  class of a random object in view and 10-100 % of its area, at uniform random places where they touch
  no other region (a false blob of its own; given up after a few tries in a crowded image).

The source must cover the map where the aircraft flies (:func:`check_coverage`): a flight over a map built
from another extract would see only the objects the two share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._scipy import cKDTree
from ..detections.masks import DEFAULT_MIN_AREA_PX, from_mask
from ..errors import SourceError
from ..objects import Objects
from ..simulation.outlines import LAYER_MARK, Scene
from ..simulation.poses import Shot
from ..simulation.render import Rendering, blob_sources, render_mask

__all__ = ["MAX_MASK_OFFSET_PX", "MIN_COVERAGE", "FlightRender", "check_coverage", "rendered_objects"]

# The largest erosion or dilation (pixels): beyond it, masks say more about the option than about a model.
MAX_MASK_OFFSET_PX = 10
# The share of the map's objects along the flight (of labels the source draws as outlines) that must be
# outlines of the source; below it the source is another extract, or a part of the map's.
MIN_COVERAGE = 0.5
# Places tried for each false blob before it is given up (an image with no background room for it).
_SPURIOUS_TRIES = 20


@dataclass(frozen=True)
class FlightRender:
    """How a flight's frames are rendered (module docs); ``source`` names the extract in messages."""

    scene: Scene
    source: str = "source"
    heights: bool = True
    mask_offset_px: int = 0
    blob_miss_rate: float = 0.0
    blob_spurious_rate: float = 0.0
    connectivity: int = 8
    min_area: int = DEFAULT_MIN_AREA_PX

    def __post_init__(self) -> None:
        if not (isinstance(self.mask_offset_px, int | np.integer) and abs(self.mask_offset_px) <= MAX_MASK_OFFSET_PX):
            raise ValueError(f"mask_offset_px must be a whole number of pixels within +-{MAX_MASK_OFFSET_PX}, "
                             f"got {self.mask_offset_px}")
        for name in ("blob_miss_rate", "blob_spurious_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {value}")


def check_coverage(render: FlightRender, objects: Objects, points: np.ndarray, reach_m: float) -> None:
    """Raise :class:`SourceError` unless the source's outlines are most of the map's objects along the flight.

    ``points`` are complex positions along the flight, ``reach_m`` how far from them the camera sees.  Only
    objects of the labels the source draws as outlines (areas and buildings, not road marks) count.
    """
    scene = render.scene
    drawn = {scene.labels[c] for c in np.unique(scene.label[scene.layer != LAYER_MARK]).tolist()}
    codes = [c for c, name in enumerate(objects.labels) if name in drawn]
    if not codes or not objects.x.size:
        return
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    near = np.unique(np.concatenate([np.asarray(i, np.int64) for i in tree.query_ball_point(
        np.column_stack([points.real, points.imag]), reach_m)] + [np.zeros(0, np.int64)]))
    near = near[np.isin(objects.label[near], codes)]
    if not near.size:
        return
    share = float(np.isin(near, scene.map_index).mean())
    if share < MIN_COVERAGE:
        raise SourceError(f"{render.source}: its outlines are {share:.0%} of the map's {near.size:,} objects along "
                          "the flight: not the extract the map was built from (or not all of it)")


def _disc(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return np.asarray((r[:, None] ** 2 + r[None, :] ** 2) <= radius**2)


def _offset(rendering: Rendering, px: int) -> Rendering:
    """The rendering with every region eroded (``px < 0``) or dilated (``px > 0``) by ``|px|`` (module docs)."""
    from scipy import ndimage

    if px == 0:
        return rendering
    disc = _disc(abs(px))
    mask = rendering.mask
    if px < 0:
        same = ((ndimage.minimum_filter(mask, footprint=disc, mode="nearest") == mask)
                & (ndimage.maximum_filter(mask, footprint=disc, mode="nearest") == mask))
        return Rendering(np.where(same, mask, 0).astype(mask.dtype), np.where(same, rendering.instance, 0),
                         rendering.classes)
    grown = ndimage.maximum_filter(mask, footprint=disc, mode="nearest")
    new = np.where(mask == 0, grown, mask).astype(mask.dtype)
    return Rendering(new, rendering.instance, rendering.classes)  # grown pixels cover no map object


def _spurious(rendering: Rendering, rate: float, rng: np.random.Generator) -> Rendering:
    """False blobs painted on the background (module docs)."""
    instance = rendering.instance
    pixels = np.bincount(instance.ravel())
    present = np.flatnonzero(pixels)
    present = present[present > 0]
    n = int(rng.poisson(rate * present.size)) if present.size else 0
    if n == 0:
        return rendering
    mask = rendering.mask.copy()
    rows, cols = mask.shape
    for k in rng.choice(present, size=n).tolist():
        side = max(3, int(round(math.sqrt(pixels[k] * rng.uniform(0.1, 1.0)))))
        code = mask.ravel()[int(np.argmax(instance.ravel() == k))]
        for _ in range(_SPURIOUS_TRIES):
            # A place on the background with a pixel's margin, so that the blob is one of its own.
            r0, c0 = int(rng.integers(-side // 2, rows - side // 2)), int(rng.integers(-side // 2, cols - side // 2))
            around = mask[max(r0 - 1, 0):r0 + side + 1, max(c0 - 1, 0):c0 + side + 1]
            if not around.any():
                mask[max(r0, 0):r0 + side, max(c0, 0):c0 + side] = code
                break
    return Rendering(mask, instance, rendering.classes)


def rendered_objects(render: FlightRender, shot: Shot, x: float, y: float, rng: np.random.Generator,
                     image_id: str) -> tuple[dict[str, Any], np.ndarray, int, np.ndarray]:
    """One frame's document, its blobs' map objects, the map objects in view, and its mask (module docs).

    Returns
    -------
    (dict, ndarray, int, ndarray)
        The ``from_mask`` document (``id``, ``width``, ``height``, ``objects``, ``camera``), the map
        object covering most of each blob (-1 for none), how many map objects show in the mask, and the
        mask (class codes: label code + 1).
    """
    scene = render.scene
    rendering = render_mask(scene, shot.pose(x, y), shot.camera, heights=render.heights,
                            miss_rate=render.blob_miss_rate, rng=rng)
    rendering = _offset(rendering, int(render.mask_offset_px))
    if render.blob_spurious_rate > 0:
        rendering = _spurious(rendering, render.blob_spurious_rate, rng)
    doc = from_mask(rendering.mask, rendering.classes, connectivity=render.connectivity, min_area=render.min_area,
                    image_id=image_id, fov_deg=shot.camera.fov_deg)
    covers = blob_sources(rendering, scene.map_index, doc, connectivity=render.connectivity,
                          min_area=render.min_area)
    index = np.array([c[0][0] if c else -1 for c in covers], np.int64)
    seen = np.unique(rendering.instance)
    seen_map = np.unique(scene.map_index[seen[seen > 0] - 1])
    doc.pop("skipped_classes", None)
    return doc, index, int((seen_map >= 0).sum()), rendering.mask
