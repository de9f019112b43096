"""Priors: which applies to an image, how far beyond it map objects are read, and whether it can meet the map.

An image's own prior comes first, else the caller's (map-CRS metres, or lon/lat as ``mapdb query
--prior-crs EPSG:4326`` gives it).  A prior whose disc, widened by the image's footprint, misses the map's
bounds rejects the image with how far outside it is.  A prior with a heading, on an image whose altitude and
field of view give its scale, is a pose prior (:func:`pose_prior`, :mod:`mapdb.match.pose_prior`).
"""

from __future__ import annotations

import math
from functools import lru_cache

from ..detections.images import ImageObjects, Prior, check_prior
from ..errors import ImageInputError
from ..match.pose_prior import ALTITUDE_SCALE_REL_SIGMA, PosePrior
from .lonlat import transformer

__all__ = ["DEFAULT_PRIOR_MARGIN_M", "SCALE_REL_SIGMA", "checked_caller_prior", "outside_bounds", "pose_prior",
           "prior_margin", "resolve_prior"]

# With a prior but no known scale, objects this far beyond the prior radius (or the radius itself, if
# larger) are read so that the edges of the image are matched too.
DEFAULT_PRIOR_MARGIN_M = 300.0
# The relative 1-sigma error of the scale an image's altitude and field of view give, for the pose prior
# (:data:`~mapdb.match.pose_prior.ALTITUDE_SCALE_REL_SIGMA`): the scale range's factor
# (image_points.SCALE_TOLERANCE, 1.5) is a bound on hypotheses, not an error the stage could shape its
# tolerances with.
SCALE_REL_SIGMA = ALTITUDE_SCALE_REL_SIGMA


def prior_margin(radius: float, half_diagonal_m: float | None) -> float:
    """How far beyond a prior's radius map objects are read: the footprint's half-diagonal if known."""
    if half_diagonal_m is not None:
        return 1.2 * half_diagonal_m
    return max(radius, DEFAULT_PRIOR_MARGIN_M)


@lru_cache(maxsize=64)
def checked_caller_prior(x: float, y: float, radius: float) -> tuple[float, float, float]:
    """A caller's prior, checked against the same ranges as an image's (a radius of 1e308 would overflow the
    tiles); once per prior, not per image of a batch that shares it."""
    checked = check_prior(x, y, radius, source="prior argument")
    return (checked.x, checked.y, checked.radius)


def resolve_prior(im: ImageObjects, crs: str,
                  prior: tuple[float, float, float] | Prior | None) -> tuple[float, float, float] | None:
    """The prior that applies, as (x, y, radius) in the map's CRS: the image's own, else the caller's.

    The caller's is (x, y, radius) in the map's CRS or a :class:`mapdb.detections.images.Prior` (``lonlat=True``:
    x, y are lon, lat degrees), as ``mapdb query --prior-crs EPSG:4326`` gives it.
    """
    p = im.prior
    if p is None:
        if prior is None:
            return None
        if not isinstance(prior, Prior):
            return checked_caller_prior(*prior)
        p = prior
    if not p.lonlat:
        return (p.x, p.y, p.radius)
    if not crs:
        raise ImageInputError("prior: given in lon/lat but the map has no CRS to convert it to")
    try:
        x, y = transformer("EPSG:4326", crs).transform(p.x, p.y)
    except Exception:  # pyproj raises several kinds for points a projection cannot take
        x = y = math.nan
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ImageInputError(f"prior: lon {p.x}, lat {p.y} is outside the map's CRS ({crs})")
    return (float(x), float(y), p.radius)


def outside_bounds(prior: tuple[float, float, float], margin: float, bounds: tuple[float, ...]) -> str | None:
    """Why a prior cannot meet the map, or None: its disc, widened by ``margin``, misses the map's bounds.

    The margin is how far beyond the disc the image's objects may lie (:func:`prior_margin`): a prior
    just off the map's edge can still see the map.  A prior given in metres whose numbers look like
    lon/lat gets a hint, the usual mistake.
    """
    x, y, r = prior
    x0, y0, x1, y1 = bounds
    if not all(map(math.isfinite, bounds)):
        return None  # nothing known about where the map is
    gap = math.hypot(max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1))
    if gap <= r + margin:
        return None
    far = f"{gap / 1000.0:,.1f} km" if gap >= 1000.0 else f"{gap:.0f} m"
    hint = " (lon, lat? give the prior in lon/lat)" if abs(x) <= 180.0 and abs(y) <= 90.0 else ""
    return f"prior ({x:.0f}, {y:.0f}) is {far} outside the map's bounds{hint}: no objects here"


def pose_prior(im: ImageObjects, caller: tuple[float, float, float] | Prior | None,
               disc: tuple[float, float, float] | None, focal_px: float | None, notes: list[str],
               method: str = "fast") -> PosePrior | None:
    """The pose prior of an image, or None: the heading of the prior that applies (the image's own, else the
    caller's :class:`~mapdb.detections.images.Prior`) and the scale its ``altitude_m`` and field of view give.

    ``disc`` is the prior's (x, y, radius) in the map's CRS (:func:`resolve_prior`).  A heading that cannot be used
    (no scale, or the paper method) is said in ``notes`` and the image answered with its disc alone.
    """
    p = im.prior if im.prior is not None else caller if isinstance(caller, Prior) else None
    if p is None or p.heading_deg is None or disc is None:
        return None
    if method != "fast":
        notes.append("prior.heading_deg ignored: the paper method has no pose-prior stage")
        return None
    if focal_px is None or im.altitude_m is None:
        notes.append("prior.heading_deg ignored: the pose prior's scale needs altitude_m and camera.fov_deg")
        return None
    return PosePrior(*disc, heading_deg=p.heading_deg % 360.0, heading_sigma_deg=p.heading_sigma_deg,
                     scale_m_per_px=im.altitude_m / focal_px, scale_rel_sigma=SCALE_REL_SIGMA)
