"""The answer of one image (an :class:`mapdb.answers.Answer`): accepted with its pose, or rejected with the reason.

:func:`ok_record` and :func:`rejected` make the answer; a step that rejects the image raises a
:class:`RejectionError` carrying the reason.  ``Answer.to_json()`` gives this JSON, which ``mapdb query``
writes::

    {"id": ..., "status": "ok", "x": ..., "y": ..., "lon": ..., "lat": ..., "crs": "EPSG:...",
     "inliers": 14, "heading_deg": ..., "scale_m_per_px": ..., "sigma_m": ..., "score": ...,
     "altitude_m": ...,                      # when the field of view is known
     "levelled": false, "width": 640, "height": 480,
     "transform": [a, b, c, d, e, f], "transform_error_m": 0.0,
     "footprint": [[x, y], ...], "footprint_lonlat": [[lon, lat], ...],
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
* ``width``, ``height``: the image's size in pixels (the document's), which the next fields are of.
* ``transform``: the image-to-map affine ``(a, b, c, d, e, f)``, ``x = a col + b row + c``,
  ``y = d col + e row + f`` for a pixel position ``(col, row)`` from the image's top-left corner
  (rasterio's ``Affine`` order); for a levelled (tilted) image the best affine of the pinhole projection
  over the image, ``transform_error_m`` the largest distance between the two (0 for a level image); see
  :mod:`mapdb.localize.georef`.
* ``footprint``: the ground points of the image's corners (top-left, top-right, bottom-right,
  bottom-left) in the map's CRS; ``footprint_lonlat`` the same in lon/lat (without a CRS, left out).
  Neither, nor the transform, when a tilted image's corners reach the horizon.
* ``rejected_by`` (rejected answers, fast method, objects with ``area_px``): ``"areas"`` when the objects'
  areas are what rejected the image as not certain enough: the same test on the positions alone scored
  ``score_without_areas``, above the threshold (:func:`mapdb.match.evidence.areas.points_floor`: the area test
  is floored by the positions-only test, which must then beat the threshold by 2).  ``mapdb query --no-areas``
  (``FastOptions(areas=False)``) answers as if the objects carried no areas.
* ``path`` (fast method, only when a pose prior was given: ``Localizer.localize(..., pose=PosePrior(...))``,
  the navigator's queries): which search decided, ``"pose-prior"`` (one correspondence a hypothesis, heading
  and scale from the prior: :mod:`mapdb.match.pose_prior`) or ``"quads"`` (the lost-in-space rounds, their
  ``hypotheses`` counting the pose-prior stage's).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from ..answers import Answer, Candidate
from ..detections.images import ImageObjects
from .georef import georeference
from .lonlat import to_lonlat, to_lonlat_many

__all__ = ["FoundPose", "RejectionError", "elapsed_ms", "finite", "georef_fields", "ok_record", "rejected", "rounded"]


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


def georef_fields(crs: str, a: complex, b: complex, image: ImageObjects, levelled: bool) -> dict[str, Any]:
    """An accepted answer's ``width``, ``height``, ``transform``, ``transform_error_m``, ``footprint`` and
    ``footprint_lonlat`` (module docs), rounded as the answer's other fields are."""
    return _located(crs, a, b, image, levelled)[0]


def _located(crs: str, a: complex, b: complex, image: ImageObjects, levelled: bool
             ) -> tuple[dict[str, Any], tuple[float | None, float | None]]:
    """:func:`georef_fields` and the lon/lat of ``b``: the centre and the footprint's corners in one transform."""
    fields: dict[str, Any] = {"width": image.width, "height": image.height}
    attitude = (image.fov_deg, image.roll_deg or 0.0, image.pitch_deg or 0.0) if levelled and image.fov_deg else None
    where = georeference(a, b, image.width, image.height, attitude)
    if where is None:
        return fields, to_lonlat(crs, b.real, b.imag)
    ta, tb, tc, td, te, tf = where.transform
    # 1e-9 m a pixel is a micrometre across a 1000-pixel image; offsets to the 0.1 mm.
    fields["transform"] = [rounded(ta, 9), rounded(tb, 9), rounded(tc, 4), rounded(td, 9), rounded(te, 9),
                           rounded(tf, 4)]
    fields["transform_error_m"] = rounded(where.error_m, 3)
    # numpy's rounding of the whole array: what rounded() does to each of its numpy numbers.
    fields["footprint"] = np.round(where.footprint, 3).tolist()
    xs, ys = zip(*where.footprint.tolist(), strict=True)
    centre, *corners = to_lonlat_many(crs, [b.real, *xs], [b.imag, *ys])
    if (None, None) not in corners:  # to_lonlat_many gives a point's two numbers or two Nones
        fields["footprint_lonlat"] = [[lon, lat] for lon, lat in corners]
    return fields, centre


def ok_record(image_id: Any, crs: str, pose: FoundPose, focal_px: float | None, levelled: bool,
               start: float, image: ImageObjects | None = None, *, lonlat: bool = True, brief: bool = False) -> Answer:
    """The answer of a localized image (module docs); where it lies on the ground when ``image`` is given, its
    ``lon`` and ``lat`` unless ``lonlat`` is False (a caller that reads neither spares PROJ's transform).

    ``brief``: only the position, score, inliers, candidates and what the search adds (``hypotheses``, ``path``,
    ``notes``): no ``lon``, ``lat`` or ground, and nothing else derived from the pose (``heading_deg``,
    ``scale_m_per_px``, ``sigma_m``, ``expected_false_alarms``, ``altitude_m``) nor ``time_ms``; for a caller
    that reads no more (the analysis, thousands of answers a cell block)."""
    if brief:
        return Answer(id=image_id, status="ok", x=rounded(pose.b.real, 3), y=rounded(pose.b.imag, 3), crs=crs or None,
                      inliers=int(pose.inliers), score=pose.score, levelled=levelled, candidates=pose.candidates,
                      **pose.extra)
    a, b = pose.a, pose.b
    if image is not None:
        fields, (lon, lat) = _located(crs, a, b, image, levelled)
    else:
        fields, (lon, lat) = {}, to_lonlat(crs, b.real, b.imag) if lonlat else (None, None)
    return Answer(
        id=image_id,
        status="ok",
        x=rounded(b.real, 3),
        y=rounded(b.imag, 3),
        lon=lon,
        lat=lat,
        crs=crs or None,
        inliers=int(pose.inliers),
        # np.angle's own ufunc on the two parts (np.angle itself first makes an array of a): the same numpy number.
        heading_deg=rounded((-math.degrees(np.arctan2(a.imag, a.real))) % 360.0, 3),
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
        **fields,
        time_ms=elapsed_ms(start),
    )
