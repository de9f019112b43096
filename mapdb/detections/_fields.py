"""An image document's object fields read into arrays with every value checked: the reading that words the error.

:func:`~mapdb.detections.images.parse_image` reads the usual document's objects in the loop that checks them by the
schema's rules; a document with objects that loop does not take (a value the schema lets through, NaN or an object
outside the image; the region fields of mask blobs) is read here, field by field, so that the first bad value is
named.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import ImageInputError

__all__ = ["positions", "region_fields"]


def positions(objects: list[dict[str, Any]], width: float, height: float, source: str
              ) -> tuple[np.ndarray, np.ndarray]:
    """The objects' pixel positions, each finite and inside the image, or the error naming the first that is not."""
    n = len(objects)
    x = np.fromiter((o["x"] for o in objects), dtype=np.float64, count=n)
    y = np.fromiter((o["y"] for o in objects), dtype=np.float64, count=n)
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if bad.any():
        i = int(np.argmax(bad))
        axis = "x" if not math.isfinite(x[i]) else "y"
        raise ImageInputError(f"{source}: objects[{i}].{axis} is {objects[i][axis]!r}, not a finite number")
    outside = (x > width) | (y > height)
    if outside.any():
        i = int(np.argmax(outside))
        raise ImageInputError(
            f"{source}: objects[{i}] at ({x[i]:g}, {y[i]:g}) is outside the {width:g}x{height:g} image"
        )
    return x, y


def region_fields(objects: list[dict[str, Any]], source: str
                  ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The objects' optional ``area_px``, ``border`` and ``bbox`` as arrays (None when no object has one)."""
    has = {key for o in objects for key in ("area_px", "border", "bbox") if key in o}  # one pass for the three
    area = np.array([o.get("area_px", math.nan) for o in objects], np.float64) if "area_px" in has else None
    border = np.array([o.get("border", False) for o in objects], bool) if "border" in has else None
    bbox = np.array([o.get("bbox", (math.nan,) * 4) for o in objects], np.float64).reshape(-1, 4) \
        if "bbox" in has else None
    # The schema lets NaN and infinities through (JSON's readers accept them): a value given must be finite.
    for name, values in (("area_px", area), ("bbox", bbox)):
        if values is None:
            continue
        given = np.array([name in o for o in objects], bool)
        bad = given & ~np.isfinite(values.reshape(len(objects), -1)).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise ImageInputError(f"{source}: objects[{i}].{name} is {objects[i][name]!r}, not finite")
    return area, border, bbox
