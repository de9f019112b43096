"""The image's side of an answer: the objects the map knows, as points of the image plane, and the scale.

Objects of labels the map lacks are left out and counted (:func:`known_objects`); the rest become complex
pixels from the image centre, levelled when the attitude is known (:func:`image_points`); a known field of
view and altitude bound the scale (:func:`scale_hints`).  A step that finds the image unusable raises
:class:`~mapdb.localize.records.RejectionError`.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from functools import lru_cache
from typing import Any

import numpy as np

from ..camera import Camera, image_plane, level_pixels
from ..detections.images import ImageObjects
from .records import RejectionError

__all__ = ["SCALE_TOLERANCE", "image_points", "known_objects", "scale_hints"]

# With a known altitude and field of view the scale is known up to terrain relief and altimeter error;
# hypotheses off by more than this factor are not considered.
SCALE_TOLERANCE = 1.5


@lru_cache(maxsize=16)
def _label_codes(map_labels: tuple[str, ...]) -> dict[str, int]:
    """Each label's code in a map (its place in the map's label table), made once per map, not per image."""
    return {name: code for code, name in enumerate(map_labels)}


def known_objects(im: ImageObjects, map_labels: tuple[str, ...]) -> tuple[ImageObjects, np.ndarray, dict]:
    """The image's objects of labels the map knows, their label codes, and the others counted.

    Objects of labels the map does not know (a detector's class the map lacks) are left out and counted:
    the others may still place the image.
    """
    n = len(im)
    if n < 3:
        raise RejectionError(f"{n} objects: at least 3 are needed")
    known = _label_codes(map_labels)
    codes = [known.get(name, -1) for name in im.names.tolist()]
    if -1 not in codes:  # the usual image: every label known, one pass
        return im, np.array(codes, np.int64), {}
    is_known = np.fromiter((name in known for name in im.names), dtype=bool, count=n)
    unknown = sorted({str(name) for name in im.names[~is_known]})
    skipped: dict[str, Any] = {}
    if unknown:
        counts = Counter(str(name) for name in im.names[~is_known])
        skipped = {"skipped_labels": {name: counts[name] for name in unknown}}
        n = int(is_known.sum())
        if n < 3:
            listed = ", ".join(repr(u) for u in unknown[:5]) + (" ..." if len(unknown) > 5 else "")
            raise RejectionError(
                f"unknown label{'s' if len(unknown) > 1 else ''} {listed}: the map has {', '.join(map_labels)}; "
                f"{n} object{'' if n == 1 else 's'} left: at least 3 are needed", **skipped)
        im = dataclasses.replace(
            im, x=im.x[is_known], y=im.y[is_known], names=im.names[is_known],
            area_px=None if im.area_px is None else im.area_px[is_known],
            border=None if im.border is None else im.border[is_known],
            bbox=None if im.bbox is None else im.bbox[is_known])
    return im, np.fromiter((known[name] for name in im.names), dtype=np.int64, count=n), skipped


def image_points(im: ImageObjects) -> tuple[np.ndarray, bool, list[str]]:
    """Objects as complex pixels from the image centre, y up; levelled first when roll, pitch and the field
    of view are given.  Also whether it was levelled, and notes for the answer."""
    u, v = im.x, im.y
    notes = []
    levelled = False
    if im.roll_deg is not None or im.pitch_deg is not None:
        if im.fov_deg is None:
            notes.append("attitude ignored: levelling the image needs camera.fov_deg")
        else:
            u, v = level_pixels(u, v, Camera(im.width, im.height, im.fov_deg), im.roll_deg or 0.0,
                                im.pitch_deg or 0.0)
            if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
                raise RejectionError("attitude puts objects at or above the horizon")
            levelled = True
    return image_plane(u, v, im.width, im.height), levelled, notes


@lru_cache(maxsize=64)
def _focal_px(width: float, height: float, fov_deg: float) -> float:
    """The camera's focal length in pixels, once per camera (a stream's images share one), not per image."""
    return Camera(width, height, fov_deg).focal_px


def scale_hints(im: ImageObjects, diag_px: float
                ) -> tuple[float | None, tuple[float, float] | None, float | None]:
    """Focal length (pixels), allowed metres per pixel and the footprint's largest half-diagonal (metres),
    each None unless the field of view (and, for the last two, the altitude) is given."""
    focal_px = None if im.fov_deg is None else _focal_px(im.width, im.height, im.fov_deg)
    if focal_px is None or im.altitude_m is None:
        return focal_px, None, None
    s0 = im.altitude_m / focal_px
    scale_range = (s0 / SCALE_TOLERANCE, s0 * SCALE_TOLERANCE)
    return focal_px, scale_range, scale_range[1] * diag_px / 2.0
