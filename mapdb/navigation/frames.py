"""A flight's frame as the navigator reads it: every sensor checked on its own.

A frame document is an image document (the ``mapdb query`` schema: ``width``, ``height``, ``objects``,
``camera``, ``attitude``, ``altitude_m``) with the autopilot's fields beside it: ``time_s`` (seconds,
required, increasing), ``attitude.yaw_deg`` (heading, degrees clockwise from north),
``imu_velocity_mps`` (``[east, north]``, optional), ``map_withheld`` (optional) and ``truth`` (a simulated
frame's ``x``, ``y``; used only to report the error).  :mod:`mapdb.navigation.flight` writes them.

Bad sensor values do not cost the frame: a field that is missing, not a number, not finite or out of
range is left out, with a note, and the rest of the frame is used.  Objects that cannot be read leave a
frame without objects (the filter predicts); a frame without a valid time cannot be placed in the flight
and is skipped by the navigator.

Examples
--------
>>> f = read_frame({"time_s": 1.5, "width": 640, "height": 480, "objects": [],
...                 "attitude": {"roll_deg": float("nan"), "yaw_deg": 90}}, "line 1")
>>> f.time_s, f.roll, f.yaw, f.notes
(1.5, None, 90.0, ['attitude.roll_deg is nan: ignored'])
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..detections.images import MAX_ALTITUDE_M, MAX_ATTITUDE_DEG, MIN_FOV_DEG, ImageObjects, parse_image
from ..errors import ImageInputError

__all__ = ["Frame", "read_frame"]

# The image keys handed to the localizer (the others are the autopilot's or the simulator's).
_IMAGE_KEYS = ("id", "width", "height", "objects")


@dataclass
class Frame:
    """One frame's usable contents (None where a value is missing or was ignored)."""

    id: Any
    time_s: float | None = None
    image: ImageObjects | None = None
    width: float = 0.0
    height: float = 0.0
    fov: float | None = None
    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    altitude: float | None = None
    imu: complex | None = None
    withheld: bool = False
    truth: tuple[float, float] | None = None
    notes: list[str] = field(default_factory=list)


def _number(doc: Any, key: str, where: str, notes: list[str], low: float = -math.inf, high: float = math.inf,
            required: bool = False) -> float | None:
    """``doc[key]`` as a finite float within ``[low, high]``, else None with a note (silent if absent)."""
    if not isinstance(doc, dict) or key not in doc:
        if required:
            notes.append(f"{where} is missing")
        return None
    value = doc[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        notes.append(f"{where} is not a number: ignored")
        return None
    if not math.isfinite(value):
        notes.append(f"{where} is {value!r}: ignored")
        return None
    if not low <= value <= high:
        notes.append(f"{where} = {value:g} is out of range [{low:g}, {high:g}]: ignored")
        return None
    return float(value)


def _imu(doc: dict[str, Any], notes: list[str]) -> complex | None:
    value = doc.get("imu_velocity_mps")
    if value is None:
        return None
    if (isinstance(value, list) and len(value) == 2
            and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)):
        return complex(float(value[0]), float(value[1]))
    notes.append("imu_velocity_mps is not two finite numbers: ignored")
    return None


def _truth(doc: dict[str, Any]) -> tuple[float, float] | None:
    truth = doc.get("truth")
    if isinstance(truth, dict):
        x, y = truth.get("x"), truth.get("y")
        if all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in (x, y)):
            return float(x), float(y)  # type: ignore[arg-type]
    return None


def read_frame(doc: Any, where: str = "frame") -> Frame:
    """The usable contents of a frame document (module docs); never raises.

    ``doc`` may also be the :class:`~mapdb.errors.ImageInputError` that replaced an unreadable line.
    """
    if isinstance(doc, Exception):
        return Frame(id=None, notes=[str(doc)])
    if not isinstance(doc, dict):
        return Frame(id=None, notes=[f"{where}: a frame must be a JSON object, got {type(doc).__name__}"])
    notes: list[str] = []
    frame_id = doc.get("id") if isinstance(doc.get("id"), str | int) and not isinstance(doc.get("id"), bool) else None
    attitude = doc.get("attitude") if isinstance(doc.get("attitude"), dict) else {}
    camera = doc.get("camera") if isinstance(doc.get("camera"), dict) else {}
    frame = Frame(
        id=frame_id,
        time_s=_number(doc, "time_s", "time_s", notes, 0.0, required=True),
        fov=_number(camera, "fov_deg", "camera.fov_deg", notes, MIN_FOV_DEG, 179.999),
        roll=_number(attitude, "roll_deg", "attitude.roll_deg", notes, -MAX_ATTITUDE_DEG, MAX_ATTITUDE_DEG),
        pitch=_number(attitude, "pitch_deg", "attitude.pitch_deg", notes, -MAX_ATTITUDE_DEG, MAX_ATTITUDE_DEG),
        yaw=_number(attitude, "yaw_deg", "attitude.yaw_deg", notes),
        altitude=_number(doc, "altitude_m", "altitude_m", notes, 1e-3, MAX_ALTITUDE_M),
        imu=_imu(doc, notes),
        withheld=doc.get("map_withheld") is True,
        truth=_truth(doc),
        notes=notes,
    )
    _read_image(doc, frame, where)
    return frame


def _read_image(doc: dict[str, Any], frame: Frame, where: str) -> None:
    """The frame's objects, checked as a query image with the sensor values that survived."""
    image: dict[str, Any] = {key: doc[key] for key in _IMAGE_KEYS if key in doc}
    if frame.fov is not None:
        image["camera"] = {"fov_deg": frame.fov}
    attitude = {k: v for k, v in (("roll_deg", frame.roll), ("pitch_deg", frame.pitch)) if v is not None}
    if attitude:
        image["attitude"] = attitude
    if frame.altitude is not None:
        image["altitude_m"] = frame.altitude
    try:
        frame.image = parse_image(image, where)
    except ImageInputError as exc:
        frame.notes.append(f"objects not used: {exc}")
        return
    frame.width, frame.height = frame.image.width, frame.image.height
