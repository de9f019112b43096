"""Simulated images as documents: the ``mapdb query`` input of one image, its hints and its truth.

:func:`image_document` is the query-input document of an image's detections; :func:`add_hints` adds the
prior, attitude and altitude a simulation was asked for; :func:`truth_entry` is the ``truth`` the
evaluation scores against, with its ``bound`` (:func:`bound_fit`: the best any matcher can do from these
pixels).  :func:`write_images` writes documents as JSON Lines.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera, level_pixels
from ..match.geometry import apply_similarity, fit_similarity
from ..objects import Objects
from ..outputs import atomic_open
from .poses import Shot

__all__ = ["add_hints", "bound_entry", "bound_fit", "image_document", "truth_entry", "write_images"]


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


def bound_entry(
    objects: Objects,
    index: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    shot: Shot,
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


def truth_entry(
    shot: Shot, cam_x: float, cam_y: float, n_visible: int, index: np.ndarray, bound: dict[str, Any] | None
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


def image_document(
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


def add_hints(
    rng: np.random.Generator,
    image: dict[str, Any],
    shot: Shot,
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


def write_images(images: Sequence[dict[str, Any]], path: str | Path | None) -> None:
    """Write image documents as strict JSON Lines to ``path`` (stdout if None or ``"-"``), atomically."""
    with atomic_open("-" if path is None else path) as f:
        for im in images:
            f.write(json.dumps(im, separators=(",", ":"), allow_nan=False) + "\n")
