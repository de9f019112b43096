"""Simulated images whose objects come from rendered label masks: ``mapdb simulate --render masks``.

The ideal simulator (:func:`mapdb.simulation.simulate.simulate_images`) puts each visible map object at its
projected centroid.  Here each image's label mask is rendered from the source's outlines
(:func:`mapdb.simulation.render.render_mask`: buildings extruded to their heights, relief, the image border,
touching objects merging, optional mask noise and missed objects) and its objects are extracted
exactly as ``mapdb objects`` does (:func:`mapdb.detections.masks.from_mask`).  The camera draws (altitude,
field of view, heading, attitude, position), the hints and the ``truth`` keys are the ideal
simulator's, so ``mapdb evaluate`` scores these images the same way.

Truth per object: ``truth.map_index[k]`` is the map object blob ``k`` stands for: in a map with blocks of
touching buildings (:mod:`mapdb.build.blocks`), the block when the blob covers two or more of its buildings
(``truth.block[k]`` true), else the map object covering most of its pixels (-1 when none does);
``truth.covers[k]`` all the map objects it covers, most pixels first, with their pixel counts in
``truth.cover_px[k]``; ``truth.n_visible`` counts the map objects with at least one pixel in
the mask; ``truth.bound`` is the true-correspondence fit of the blobs onto their ``map_index`` objects
(relief and cut blobs make it worse than the ideal simulator's); ``truth.mask`` names the mask file.

Camera positions are drawn as the ideal simulator draws them with ``min_objects`` halved (a
position must show at least ``ceil(min_objects / 2)`` map centroids), then redrawn (at most
:data:`MAX_RENDERS` times per image) until the mask holds at least ``min_objects`` blobs: uniform over
the places showing both, which leaves out only the rare places where many blobs come from few centroids.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._scipy import cKDTree
from ..build.blocks import DEFAULT_GAP_M, block_members, blocks_of
from ..detections.masks import DEFAULT_MIN_AREA_PX, from_mask
from ..errors import EmptyMapError
from ..labels import BLOCK_LABEL
from ..objects import Objects
from ..outputs import atomic_path
from ..progress import ProgressLike, as_progress
from .detector import Detector, confuse_labels, label_mix
from .documents import add_hints, bound_entry, truth_entry
from .outlines import LAYER_BUILDING, Scene
from .poses import Shot, camera_area, draw_shot, place_camera
from .render import Rendering, blob_sources, render_mask
from .simulate import check_simulate_args, objects_of_map

__all__ = ["MAX_RENDERS", "RenderedImage", "blocks_of_buildings", "png_bytes", "simulate_masks", "write_masks"]

MAX_RENDERS = 200

RenderedImage = tuple[dict[str, Any], np.ndarray]


def _render_until_enough(
    rng: np.random.Generator, objects: Any, tree: cKDTree, scene: Scene, shot: Shot, place: dict[str, Any],
    render: dict[str, Any], min_objects: int, image_id: str, map_name: str, i: int,
) -> tuple[float, float, Rendering, dict[str, Any]]:
    """Camera position, rendering and extracted document of one image with at least ``min_objects`` blobs."""
    for _ in range(MAX_RENDERS if min_objects > 0 else 1):
        cam_x, cam_y, *_ = place_camera(rng, objects, tree, shot, place["area"], place["keep_inside"],
                                        math.ceil(min_objects / 2), place["max_tries"], map_name, i)
        rendering = render_mask(scene, shot.pose(cam_x, cam_y), shot.camera, heights=render["heights"],
                                mask_noise_px=render["mask_noise_px"], miss_rate=render["miss_rate"], rng=rng)
        doc = from_mask(rendering.mask, rendering.classes, connectivity=render["connectivity"],
                        min_area=render["min_area"], image_id=image_id, fov_deg=shot.camera.fov_deg)
        if len(doc["objects"]) >= min_objects:
            return cam_x, cam_y, rendering, doc
    raise EmptyMapError(f"{map_name}: no camera position out of {MAX_RENDERS} rendered shows {min_objects} blobs "
                        f"(image {i}); lower min_objects or choose a denser bbox")


def _rendered_truth(
    objects: Any, shot: Shot, cam_x: float, cam_y: float, rendering: Rendering, scene: Scene,
    doc: dict[str, Any], render: dict[str, Any], with_attitude: bool,
) -> dict[str, Any]:
    """The ``truth`` entry: the ideal simulator's keys, with blobs in place of projected centroids."""
    covers = blob_sources(rendering, scene.map_index, doc, connectivity=render["connectivity"],
                          min_area=render["min_area"])
    index = np.array([c[0][0] if c else -1 for c in covers], np.int64)
    block = np.array([_block_of(c, render["block_of"]) for c in covers], np.int64)
    index = np.where(block >= 0, block, index)
    seen = np.unique(rendering.instance)
    seen_map = np.unique(scene.map_index[seen[seen > 0] - 1])
    u = np.array([o["x"] for o in doc["objects"]], np.float64)
    v = np.array([o["y"] for o in doc["objects"]], np.float64)
    bound = bound_entry(objects, index, u, v, shot, cam_x, cam_y, with_attitude)
    truth = truth_entry(shot, cam_x, cam_y, int((seen_map >= 0).sum()), index, bound)
    truth["block"] = (block >= 0).tolist()
    truth["covers"] = [[j for j, _ in c] for c in covers]
    truth["cover_px"] = [[px for _, px in c] for c in covers]
    truth["mask"] = f"{doc['id']}.png"
    truth["render"] = {"heights": render["heights"], "mask_noise_px": render["mask_noise_px"],
                       "miss_rate": render["miss_rate"]}
    return truth


def simulate_masks(
    map: Any, scene: Scene, n: int, *,
    altitude: float | tuple[float, float] = 100.0, fov_deg: float | tuple[float, float] = 35.0,
    size: tuple[int, int] = (640, 480), yaw: float | str = 0.0, attitude_std: float = 0.0,
    miss_rate: float = 0.0, label_noise: float = 0.0, mask_noise_px: float = 0.0, heights: bool = True,
    with_prior: float | None = None, with_attitude: bool = False, with_altitude: bool = False,
    bbox: tuple[float, float, float, float] | None = None, min_objects: int = 0, max_tries: int = 10_000,
    connectivity: int = 8, min_area: int = DEFAULT_MIN_AREA_PX, seed: int = 0, id_prefix: str = "sim-",
    progress: ProgressLike = None,
) -> Iterator[RenderedImage]:
    """Simulated images of ``map`` with objects extracted from masks rendered from ``scene``, one by one.

    Parameters are those of :func:`mapdb.simulation.simulate.simulate_images` (``miss_rate``: each object is left
    out of the mask; ``label_noise``: each extracted object's label is confused; ``min_objects``: blobs
    in the mask), plus:

    scene : Scene
        The map's outlines (:func:`mapdb.simulation.outlines.read_scene` of the extract it was built from).
    mask_noise_px : float
        Largest growth or shrinkage of an object's image, pixels (:func:`mapdb.simulation.render.render_mask`).
    heights : bool
        Extrude buildings; False renders everything flat.
    connectivity, min_area
        How blobs are extracted (:func:`mapdb.detections.masks.from_mask`; ``mapdb objects``' defaults).

    Yields
    ------
    (dict, ndarray)
        Each image's query document with its ``truth`` (module docs) and its label mask (codes: label
        code + 1, 0 nothing); made as they are asked for, so that masks need not all be held at once.
    """
    check_simulate_args(n, yaw, attitude_std, 0.0, miss_rate, 0.0, label_noise, min_objects, max_tries)
    if mask_noise_px < 0:
        raise ValueError(f"mask_noise_px must be >= 0, got {mask_noise_px}")
    map_name = getattr(map, "path", None) or "map"
    objects, counts = objects_of_map(map)
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    confusion = Detector(0.0, 0.0, 0.0, label_noise, *label_mix(counts))
    area, keep_inside = camera_area(objects, bbox, map_name)
    place = {"area": area, "keep_inside": keep_inside, "max_tries": max_tries}
    render = {"heights": heights, "mask_noise_px": float(mask_noise_px), "miss_rate": float(miss_rate),
              "connectivity": connectivity, "min_area": min_area, "block_of": blocks_of_buildings(map, objects, scene)}
    return _generate(objects, tree, scene, n, (altitude, fov_deg, size, yaw, attitude_std), place, render,
                     confusion, (with_prior, with_attitude, with_altitude), min_objects, seed, id_prefix,
                     map_name, as_progress(progress))


def _generate(objects: Any, tree: cKDTree, scene: Scene, n: int, camera: tuple[Any, ...], place: dict[str, Any],
              render: dict[str, Any], confusion: Detector, hints: tuple[float | None, bool, bool],
              min_objects: int, seed: int, id_prefix: str, map_name: str, say: Any) -> Iterator[RenderedImage]:
    """The images of :func:`simulate_masks`, image ``i`` drawn from ``(seed, i)`` alone."""
    with_prior, with_attitude, with_altitude = hints
    say.start(n, "render")
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        shot = draw_shot(rng, *camera)
        cam_x, cam_y, rendering, doc = _render_until_enough(rng, objects, tree, scene, shot, place, render,
                                                            min_objects, f"{id_prefix}{i:06d}", map_name, i)
        truth = _rendered_truth(objects, shot, cam_x, cam_y, rendering, scene, doc, render, with_attitude)
        labels = np.array([o["label"] for o in doc["objects"]], dtype=object)
        confuse_labels(rng, labels, confusion)
        for o, label in zip(doc["objects"], labels, strict=True):
            o["label"] = str(label)
        add_hints(rng, doc, shot, cam_x, cam_y, with_prior, with_attitude, with_altitude)
        doc["truth"] = truth
        yield doc, rendering.mask
        say.advance()
    say.done()


def blocks_of_buildings(map_: Any, objects: Objects, scene: Scene) -> dict[int, int]:
    """The map's block (index in ``objects``, :func:`~mapdb.simulation.simulate.objects_of_map`) of every building
    of the scene that is in one: the scene's building outlines grouped as the builder groups footprints
    (:func:`mapdb.build.blocks.block_members`, with the gap the map was built with), each group matched to the
    map's block at its union's centroid (within a metre).  Empty for a map without blocks."""
    if BLOCK_LABEL not in objects.labels:
        return {}
    blocks = np.flatnonzero(objects.label == objects.labels.index(BLOCK_LABEL))
    building = np.flatnonzero((scene.layer == LAYER_BUILDING) & (scene.map_index >= 0))
    if not blocks.size or building.size < 2:
        return {}
    gap = (getattr(map_, "metadata", None) or {}).get("build", {}).get("block_gap_m") or DEFAULT_GAP_M
    group = block_members(scene.geometry[building], float(gap))
    inside = group >= 0
    if not inside.any():
        return {}
    centre, _, _ = blocks_of(scene.geometry[building], float(gap))
    dist, nearest = cKDTree(np.column_stack([objects.x[blocks], objects.y[blocks]])).query(centre)
    found = np.where(dist <= 1.0, blocks[np.minimum(nearest, blocks.size - 1)], -1)[group[inside]]
    members = scene.map_index[building[inside]]
    return {int(m): int(b) for m, b in zip(members.tolist(), found.tolist(), strict=True) if b >= 0}


def _block_of(covered: list[tuple[int, int]], block_of: dict[int, int]) -> int:
    """The block a blob stands for: the one two or more of the buildings it covers belong to (the one
    covering most pixels, if several), else -1."""
    pixels: dict[int, list[int]] = {}
    for j, px in covered:
        if j in block_of:
            pixels.setdefault(block_of[j], []).append(px)
    best = max(((sum(px), b) for b, px in pixels.items() if len(px) >= 2), default=(0, -1))
    return best[1]


def png_bytes(mask: np.ndarray) -> bytes:
    """A mask as PNG (8-bit grey, or 16-bit for codes above 255)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(mask if mask.dtype == np.uint8 else mask.astype(np.uint16)).save(buffer, format="PNG")
    return buffer.getvalue()


def write_masks(images: Sequence[tuple[str, bytes]], directory: str | Path) -> None:
    """Write ``(file name, PNG bytes)`` pairs into ``directory`` (made if missing), each file atomically."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name, data in images:
        with atomic_path(directory / name) as tmp:
            tmp.write_bytes(data)
