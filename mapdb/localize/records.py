"""The answer of one image (an :class:`mapdb.answers.Answer`): accepted with its pose, or rejected with the reason.

:func:`ok_record` and :func:`rejected` make the answer; a step that rejects the image raises a
:class:`RejectionError` carrying the reason.  ``Answer.to_json()`` gives this JSON, which ``mapdb query``
writes::

    {"id": ..., "status": "ok", "x": ..., "y": ..., "lon": ..., "lat": ..., "crs": "EPSG:...",
     "inliers": 14, "heading_deg": ..., "scale_m_per_px": ..., "sigma_m": ..., "score": ...,
     "altitude_m": ...,                      # when the field of view is known
     "candidates": [{"x": ..., "y": ..., "inliers": ..., "score": ...}, ...], "time_ms": ...}
    {"id": ..., "status": "rejected", "reason": "...", "candidates": [...], "time_ms": ...}

* ``x``, ``y``: the map point under the image centre; when roll, pitch and the
  field of view are given, the image is first levelled
  (:func:`mapdb.camera.level_pixels`) and the point is the camera nadir.
* ``heading_deg``: the direction the image's *up* points to, clockwise from map
  north (the simulator's yaw).
* ``scale_m_per_px``: ground size of a pixel at the image centre.
* ``sigma_m``: estimated 1-sigma error of ``x`` (and of ``y``) in metres, from the
  fit residuals and the inliers' spread; errors that shift all objects alike
  (an attitude error not given) are not in it.
* ``score``: ``-log10`` of the number of false alarms (fast method): above 3
  means fewer than one chance in a thousand that so good a match arises from
  objects unrelated to the map.  None for the paper method, which has no such
  measure.  ``expected_false_alarms`` is that number, ``10 ** -score``.
* ``rejected_by`` (rejected answers, fast method, objects with ``area_px``): ``"areas"`` when the objects'
  areas are what rejected the image as not certain enough: the same test on the positions alone scored
  ``score_without_areas``, above the threshold (:func:`mapdb.match.evidence.areas.points_floor`: the area test
  is floored by the positions-only test, which must then beat the threshold by 2).  ``mapdb query --no-areas``
  (``FastOptions(areas=False)``) answers as if the objects carried no areas.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from ..answers import Answer, Candidate
from .lonlat import to_lonlat

__all__ = ["FoundPose", "RejectionError", "elapsed_ms", "finite", "ok_record", "rejected", "rounded"]


def rounded(value: float, digits: int) -> float:
    """``value`` rounded to ``digits`` decimals, as a plain float (what the answer's JSON holds)."""
    return float(round(value, digits))


def finite(value: float, digits: int) -> float | None:
    """Rounded, or None where there is no finite value (a candidate without evidence scores -inf)."""
    return rounded(value, digits) if math.isfinite(value) else None


class RejectionError(Exception):
    """A step's reason to reject the image (with what the answer should still carry)."""

    def __init__(self, reason: str, candidates: list[Candidate] | None = None, **extra: Any) -> None:
        super().__init__(reason)
        self.reason, self.candidates, self.extra = reason, candidates, extra


@dataclasses.dataclass
class FoundPose:
    """What a matcher found: ``z -> a z + b``, its quality and what the answer carries besides."""

    a: complex
    b: complex
    inliers: int
    sigma_m: float | None
    score: float | None
    candidates: list[Candidate]
    extra: dict[str, Any]


def elapsed_ms(start: float) -> float:
    """Milliseconds since ``start`` (a :func:`time.perf_counter` reading), to the microsecond."""
    return rounded((time.perf_counter() - start) * 1000.0, 3)


def rejected(image_id: Any, reason: str, start: float, candidates: list[Candidate] | None = None,
              **extra: Any) -> Answer:
    """The answer of a rejected image: the reason, the candidates found, and what else it carries."""
    return Answer(id=image_id, status="rejected", reason=reason, candidates=candidates or [], **extra,
                  time_ms=elapsed_ms(start))


def ok_record(image_id: Any, crs: str, pose: FoundPose, focal_px: float | None, levelled: bool,
               start: float) -> Answer:
    """The answer of a localized image (module docs)."""
    a, b = pose.a, pose.b
    lon, lat = to_lonlat(crs, b.real, b.imag)
    return Answer(
        id=image_id,
        status="ok",
        x=rounded(b.real, 3),
        y=rounded(b.imag, 3),
        lon=lon,
        lat=lat,
        crs=crs or None,
        inliers=int(pose.inliers),
        heading_deg=rounded((-math.degrees(np.angle(a))) % 360.0, 3),
        scale_m_per_px=rounded(abs(a), 6),
        sigma_m=None if pose.sigma_m is None else rounded(pose.sigma_m, 3),
        score=pose.score,
        # The number of false alarms the score stands for: how many answers this good the search would be
        # expected to find by chance in a map that does not hold the place (benchmarks/false_alarms.py
        # measures how that holds on real places not in the map).
        expected_false_alarms=None if pose.score is None else float(f"{10.0 ** -pose.score:.3g}"),
        altitude_m=None if focal_px is None else rounded(abs(a) * focal_px, 2),
        levelled=levelled,
        candidates=pose.candidates,
        **pose.extra,
        time_ms=elapsed_ms(start),
    )
