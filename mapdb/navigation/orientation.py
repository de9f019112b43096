"""The frame's orientation: the image-to-ground similarity's heading and scale, carried from frame to frame.

The navigator (:mod:`mapdb.navigation.navigator`, step 3) keeps one :class:`Orientation`: the image-to-ground
similarity ``A = s exp(-i heading)`` (levelled image plane, pixels from the nadir, y up, to map metres).  The
heading is the last applied fix's plus the autopilot's yaw change since (the frame-to-frame rotation where the
yaw is missing); the scale (metres per pixel) the last fix's times the barometric altitude ratio (the altitude
over the focal length before any fix).  Both ratios telescope, so neither drifts frame by frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..camera import Camera
from ..match.geometry import image_to_map
from ..match.pose_prior import ALTITUDE_SCALE_REL_SIGMA, PosePrior
from .frames import Frame

__all__ = ["FIX_LEVER_PX", "FIX_SCALE_FLOOR", "HEADING_DRIFT_DEG_S", "HEADING_FLOOR_DEG", "Orientation",
           "SCALE_DRIFT_S",
           "SCALE_FLOOR", "wrap_deg"]

# The pose prior's heading and scale errors (:meth:`Orientation.pose_prior`): at least a fit's of a few blobs
# (5 blobs 300 px apart with 1 m errors at 0.2 m a pixel turn a fit by about 1 degree and scale it by 1 %),
# growing with the time since the fix that set them (the yaw's and the barometer's drifts, and the ground's
# height changing under the aircraft while the barometer's ratio assumes it flat).
HEADING_FLOOR_DEG = 1.0
SCALE_FLOOR = 0.01
HEADING_DRIFT_DEG_S = 0.2
SCALE_DRIFT_S = 0.002
# The lever (pixels) a fix's inliers give its rotation and scale, and the least relative error of a fix's
# similarity (:meth:`Orientation.fixed`).
FIX_LEVER_PX = 200.0
FIX_SCALE_FLOOR = 0.002


def wrap_deg(deg: float) -> float:
    """An angle in degrees wrapped into ``[-180, 180)``.

    Examples
    --------
    >>> wrap_deg(190.0), wrap_deg(-180.0)
    (-170.0, -180.0)
    """
    return (deg + 180.0) % 360.0 - 180.0


@dataclass
class Orientation:
    """The image-to-ground similarity's heading and scale, with their references (module docs).

    Attributes
    ----------
    heading, heading_sigma : float
        Degrees clockwise from map north, and its 1-sigma error (None / 180 before any).
    scale, scale_rel_sigma : float
        Metres per pixel, and its relative 1-sigma error (None / 1 before any).
    yaw, baro : float or None
        The autopilot's yaw and the barometric altitude at the previous frame.
    fixed_s : float or None
        The time of the last fix that set the heading and scale (None: none yet).
    """

    heading: float | None = None
    scale: float | None = None
    heading_sigma: float = 180.0
    scale_rel_sigma: float = 1.0
    yaw: float | None = None
    baro: float | None = None
    fixed_s: float | None = None

    def to_map(self) -> complex | None:
        """The similarity ``A = s exp(-i heading)``, or None while heading or scale is unknown."""
        if self.heading is None or self.scale is None:
            return None
        return image_to_map(self.scale, self.heading)

    def turn(self, frame: Frame) -> float | None:
        """The heading change since the previous frame (radians, clockwise), from the autopilot's yaw."""
        if frame.yaw is None or self.yaw is None:
            return None
        return math.radians(wrap_deg(frame.yaw - self.yaw))

    def carry(self, frame: Frame, heading_std: float) -> None:
        """Carry the heading and scale to this frame (module docs); ``heading_std`` is the heading's error before
        any fix (a magnetometer's bias)."""
        if self.heading is None and frame.yaw is not None:
            self.heading, self.heading_sigma = frame.yaw, heading_std
        elif self.heading is not None and frame.yaw is not None and self.yaw is not None:
            self.heading = self.heading + wrap_deg(frame.yaw - self.yaw)
        if frame.altitude is not None and frame.fov is not None and self.scale is None:
            self.scale = frame.altitude / Camera(frame.width, frame.height, frame.fov).focal_px
            self.scale_rel_sigma = ALTITUDE_SCALE_REL_SIGMA  # a barometer's bias against the height above ground
        elif frame.altitude is not None and self.baro is not None and self.scale is not None:
            self.scale *= frame.altitude / self.baro
        self.yaw = frame.yaw if frame.yaw is not None else self.yaw
        self.baro = frame.altitude if frame.altitude is not None else self.baro

    def fixed(self, heading: float, scale: float, attitude_std: float, time_s: float | None,
              sigma_m: float | None = None) -> None:
        """A fix's heading and scale, weighed against the carried ones (each by its variance).

        A fix's similarity is known to about ``sigma_m / (scale FIX_LEVER_PX)`` (relative; its position's error
        over the lever its inliers give the rotation and the scale), at least the yaw's two readings'
        (``sqrt(2) attitude_std``) and ``FIX_SCALE_FLOOR``: a fit of five blobs placed to a metre turns the
        heading by a degree and the scale by 2 % (measured, rendered masks at 120 m), which taken as the new
        reference would bias every frame-to-frame velocity until the next fix.  The carried values are known to
        their sigmas grown since the last fix (:meth:`pose_prior`'s drifts)."""
        rel = max((sigma_m if sigma_m is not None else 1.0) / (scale * FIX_LEVER_PX), FIX_SCALE_FLOOR)
        fix_heading_sigma = max(math.degrees(rel), math.sqrt(2.0) * attitude_std)
        if self.heading is None or self.scale is None:
            self.heading, self.scale = heading, scale
            self.heading_sigma, self.scale_rel_sigma = fix_heading_sigma, rel
            self.fixed_s = time_s
            return
        age = self.age(time_s)
        old_h = math.hypot(self.heading_sigma, HEADING_DRIFT_DEG_S * age)
        old_s = math.hypot(self.scale_rel_sigma, SCALE_DRIFT_S * age)
        k_h = old_h**2 / (old_h**2 + fix_heading_sigma**2)
        k_s = old_s**2 / (old_s**2 + rel**2)
        self.heading = self.heading + k_h * wrap_deg(heading - self.heading)
        self.scale = self.scale * math.exp(k_s * math.log(scale / self.scale))
        self.heading_sigma = math.sqrt(k_h) * fix_heading_sigma  # the weighted mean's sigma
        self.scale_rel_sigma = math.sqrt(k_s) * rel
        self.fixed_s = time_s

    def age(self, time_s: float | None) -> float:
        """Seconds since the fix that set the heading and scale (0 without a fix or a time)."""
        return max(time_s - self.fixed_s, 0.0) if time_s is not None and self.fixed_s is not None else 0.0

    def pose_prior(self, disc: tuple[float, float, float], time_s: float | None) -> PosePrior | None:
        """The query's pose prior (:mod:`mapdb.match.pose_prior`): the disc, this frame's heading and scale, their
        errors widened to at least ``HEADING_FLOOR_DEG`` and ``SCALE_FLOOR`` and grown by ``HEADING_DRIFT_DEG_S``
        and ``SCALE_DRIFT_S`` a second since the last fix; None before a fix set them."""
        if self.heading is None or self.scale is None or self.fixed_s is None:
            return None
        heading_sigma, scale_sigma = self.errors(time_s)
        return PosePrior(disc[0], disc[1], disc[2], self.heading % 360.0, heading_sigma, self.scale, scale_sigma)

    def errors(self, time_s: float | None) -> tuple[float, float]:
        """The heading's error (degrees) and the scale's relative error at ``time_s``: the carried ones widened to
        at least ``HEADING_FLOOR_DEG`` and ``SCALE_FLOOR`` and grown by ``HEADING_DRIFT_DEG_S`` and
        ``SCALE_DRIFT_S`` a second since the last fix (the pose prior's and the map update's)."""
        age = self.age(time_s)
        return (math.hypot(max(self.heading_sigma, HEADING_FLOOR_DEG), HEADING_DRIFT_DEG_S * age),
                math.hypot(max(self.scale_rel_sigma, SCALE_FLOOR), SCALE_DRIFT_S * age))
