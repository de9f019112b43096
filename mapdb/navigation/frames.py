"""A flight's frame as the navigator reads it: every sensor checked on its own.

A frame document is an image document (the ``mapdb query`` schema: ``width``, ``height``, ``objects``,
``camera``, ``attitude``, ``altitude_m``) with the autopilot's fields beside it: ``time_s`` (seconds,
required, increasing), ``attitude.yaw_deg`` (heading, degrees clockwise from north), ``baro_altitude_m``
(the barometer's height above the datum, over terrain: :mod:`mapdb.navigation.terrain`),
``imu_velocity_mps`` (``[east, north]``, optional), ``map_withheld`` (optional) and ``truth`` (a simulated
frame's ``x``, ``y``; used only to report the error).  :mod:`mapdb.navigation.flight` writes them.

Bad sensor values do not cost the frame: a field that is missing, not a number, not finite or out of
range is left out, with a note, and the rest of the frame is used.  Objects that cannot be read leave a
frame without objects (the filter predicts); a frame without a valid time cannot be placed in the flight
and is skipped by the navigator.

Every value a frame hands on is bounded (the constants below; the image fields by the query's own
limits in :mod:`mapdb.detections.images`):

==========================  =============================================================
``time_s``                  ``0 <= t <= MAX_TIME_S`` (1e10 s)
time step                   ``MIN_STEP_S <= dt <= MAX_STEP_S`` (navigator, module docs)
``attitude.yaw_deg``        ``abs(v) <= MAX_YAW_DEG`` (1e6)
``attitude.roll/pitch_deg`` ``abs(v) <= MAX_ATTITUDE_DEG`` (89)
``camera.fov_deg``          ``MIN_FOV_DEG <= v <= MAX_FOV_DEG``
``altitude_m``              ``MIN_ALTITUDE_M <= v <= MAX_ALTITUDE_M`` (1 mm to 100 km)
``baro_altitude_m``         ``MIN_BARO_M <= v <= MAX_ALTITUDE_M`` (-1 km to 100 km; above the datum)
``imu_velocity_mps``        two numbers, speed ``<= MAX_SPEED_MPS`` (1000 m/s)
``truth.x``, ``truth.y``    ``abs(v) <= MAX_MAP_COORDINATE_M`` (1e8 m)
``id``                      a string of at most ``MAX_ID_CHARS`` characters or an integer
                            of at most 18 digits
==========================  =============================================================

A field of the wrong type (``"attitude": 3``, ``"map_withheld": "yes"``) is ignored with a note too.

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

from ..detections.images import (
    MAX_ALTITUDE_M,
    MAX_ATTITUDE_DEG,
    MAX_MAP_COORDINATE_M,
    MIN_FOV_DEG,
    ImageObjects,
    parse_image,
)
from ..errors import ImageInputError

__all__ = [
    "MAX_FOV_DEG",
    "MAX_ID_CHARS",
    "MAX_SPEED_MPS",
    "MAX_STEP_S",
    "MAX_TIME_S",
    "MAX_YAW_DEG",
    "MIN_ALTITUDE_M",
    "MIN_BARO_M",
    "MIN_STEP_S",
    "Frame",
    "read_frame",
]

# Seconds since the flight's start or since the Unix epoch (until the year 2286): float64 still resolves
# 2 microseconds there, far finer than a frame interval, and a time step never overflows.
MAX_TIME_S = 1e10
# Frames closer in time than this (a 10 kHz camera) are the same instant: a velocity over such a step
# divides by nearly zero.  The navigator skips them.
MIN_STEP_S = 1e-4
# Past five minutes without a frame the motion model says nothing: its acceleration noise alone (0.5 m/s^2)
# spreads the particles over tens of kilometres.  A longer step is a jump of the flight's clock: the
# navigator skips the frame, and restarts the filter when a second frame continues from it.
MAX_STEP_S = 300.0
# A heading may come unwrapped (turns counted on); float64 resolves 1e-10 degree at a million degrees.
MAX_YAW_DEG = 1e6
# Wider than any lens (the focal length tends to zero at 180 degrees).
MAX_FOV_DEG = 179.999
# A barometric altitude must be positive for the ground scale; one millimetre is the floor.
MIN_ALTITUDE_M = 1e-3
# A barometric altitude is above the datum: the shores of the Dead Sea are 430 m below it.
MIN_BARO_M = -1000.0
# Faster than any aircraft that flies a downward camera (Mach 3): an inertial or frame-to-frame velocity
# above it is a sensor or matching fault, and squared in a covariance it would overflow the filter.
MAX_SPEED_MPS = 1000.0
# An id is echoed in the frame's record: a longer string (or a longer integer, which JSON writers cannot
# all read) is dropped with a note rather than copied into every output.
MAX_ID_CHARS = 1000
_MAX_ID_INT = 10**18
# A reason quoted from the image reader is cut here (it may quote a value of thousands of characters).
MAX_NOTE_CHARS = 300

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
    baro_altitude: float | None = None
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
    number = _float(value)
    if number is None:  # an integer of hundreds of digits: not printed, it may be longer than a line
        notes.append(f"{where} is an integer too large for a float: ignored")
        return None
    if not math.isfinite(number):
        notes.append(f"{where} is {number!r}: ignored")
        return None
    if not low <= number <= high:
        notes.append(f"{where} = {number:g} is out of range [{low:g}, {high:g}]: ignored")
        return None
    return number


def _float(value: int | float) -> float | None:
    """A JSON number as a float; None for an integer too large for one (JSON allows any digits)."""
    try:
        return float(value)
    except OverflowError:
        return None


def _finite(value: Any) -> bool:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    number = _float(value)
    return number is not None and math.isfinite(number)


def _imu(doc: dict[str, Any], notes: list[str]) -> complex | None:
    value = doc.get("imu_velocity_mps")
    if value is None:
        return None
    if not (isinstance(value, list) and len(value) == 2 and all(_finite(v) for v in value)):
        notes.append("imu_velocity_mps is not two finite numbers: ignored")
        return None
    velocity = complex(float(value[0]), float(value[1]))
    if not abs(velocity) <= MAX_SPEED_MPS:  # abs() of two finite floats can still overflow to inf
        notes.append(f"imu_velocity_mps is faster than {MAX_SPEED_MPS:g} m/s: ignored")
        return None
    return velocity


def _truth(doc: dict[str, Any], notes: list[str]) -> tuple[float, float] | None:
    truth = doc.get("truth")
    if truth is None:
        return None
    if isinstance(truth, dict):
        x, y = (float(v) if _finite(v) else math.nan for v in (truth.get("x"), truth.get("y")))  # type: ignore[arg-type]
        if abs(x) <= MAX_MAP_COORDINATE_M and abs(y) <= MAX_MAP_COORDINATE_M:  # False for NaN
            return x, y
    notes.append(f"truth is not an x, y within {MAX_MAP_COORDINATE_M:g} m: ignored")
    return None


def _id(doc: dict[str, Any], notes: list[str]) -> str | int | None:
    value = doc.get("id")
    if value is None:
        return None
    if isinstance(value, str) and len(value) <= MAX_ID_CHARS:
        return value
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) < _MAX_ID_INT:
        return value
    notes.append(f"id is not a string of at most {MAX_ID_CHARS} characters or an integer of at most 18 digits: "
                 "ignored")
    return None


def _section(doc: dict[str, Any], key: str, notes: list[str]) -> dict[str, Any]:
    """``doc[key]`` if an object; {} with a note if it is something else."""
    value = doc.get(key)
    if isinstance(value, dict):
        return value
    if value is not None:
        notes.append(f"{key} is not a JSON object: ignored")
    return {}


def _withheld(doc: dict[str, Any], notes: list[str]) -> bool:
    value = doc.get("map_withheld")
    if value is not None and not isinstance(value, bool):
        notes.append("map_withheld is not true or false: ignored")
    return value is True


def read_frame(doc: Any, where: str = "frame") -> Frame:
    """The usable contents of a frame document (module docs); never raises.

    ``doc`` may also be the :class:`~mapdb.errors.ImageInputError` that replaced an unreadable line.
    """
    if isinstance(doc, Exception):
        return Frame(id=None, notes=[str(doc)])
    if not isinstance(doc, dict):
        return Frame(id=None, notes=[f"{where}: a frame must be a JSON object, got {type(doc).__name__}"])
    notes: list[str] = []
    attitude = _section(doc, "attitude", notes)
    camera = _section(doc, "camera", notes)
    frame = Frame(
        id=_id(doc, notes),
        time_s=_number(doc, "time_s", "time_s", notes, 0.0, MAX_TIME_S, required=True),
        fov=_number(camera, "fov_deg", "camera.fov_deg", notes, MIN_FOV_DEG, MAX_FOV_DEG),
        roll=_number(attitude, "roll_deg", "attitude.roll_deg", notes, -MAX_ATTITUDE_DEG, MAX_ATTITUDE_DEG),
        pitch=_number(attitude, "pitch_deg", "attitude.pitch_deg", notes, -MAX_ATTITUDE_DEG, MAX_ATTITUDE_DEG),
        yaw=_number(attitude, "yaw_deg", "attitude.yaw_deg", notes, -MAX_YAW_DEG, MAX_YAW_DEG),
        altitude=_number(doc, "altitude_m", "altitude_m", notes, MIN_ALTITUDE_M, MAX_ALTITUDE_M),
        baro_altitude=_number(doc, "baro_altitude_m", "baro_altitude_m", notes, MIN_BARO_M, MAX_ALTITUDE_M),
        imu=_imu(doc, notes),
        withheld=_withheld(doc, notes),
        truth=_truth(doc, notes),
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
        message = str(exc)  # may quote the offending value: a record line stays short
        if len(message) > MAX_NOTE_CHARS:
            message = message[:MAX_NOTE_CHARS] + "..."
        frame.notes.append(f"objects not used: {message}")
        return
    frame.width, frame.height = frame.image.width, frame.image.height
