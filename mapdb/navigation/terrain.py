"""The navigator over terrain: the height above the ground from the barometer and the map's elevation (issue 33).

A barometer gives the aircraft's height above the vertical datum; the matcher needs the camera's height above
the ground under it (the image's ``altitude_m``: its scale, and over terrain the rays cast onto the objects'
heights, :mod:`mapdb.match.evidence.terrain`).  Over a map that holds elevation (``mapdb build --dem``), a
frame that carries ``baro_altitude_m`` and no ``altitude_m`` (``mapdb simulate flight`` over terrain) gets

    altitude_m = baro_altitude_m - g(p)

where ``p`` is the filter's predicted position at the frame's time and ``g`` the ground's elevation there,
from the map objects' ground elevations around it: a plane fitted to the :data:`NEIGHBOURS` nearest with an
elevation (weights falling with distance, as the simulator's :class:`~mapdb.simulation.terrain.Terrain`
does), held within their range.  Its error (1 sigma) adds, in quadrature,

* the barometer's (``NavigatorOptions.baro_std_m``),
* the plane's slope times the position's uncertainty (the largest axis of the filter's covariance): where the
  ground rises 12 m per 100 m, 5 m of position error is 0.6 m of height,
* the objects' scatter about the plane (the weighted RMS of its residuals: ground the plane does not follow).

The query is given that height only when the filter has a position and the error is at most
:data:`MAX_REL_SIGMA` of it (two sigma inside the matcher's 0.8-1.25 search of the camera's height); otherwise
the frame is localized without an altitude (the matcher's own scale search, wider and slower), and the
record's ``altitude`` says why.  Before the first fix there is no position: the first, lost-in-space, query
has no altitude.

A frame that carries ``altitude_m`` keeps it (the autopilot's height above the ground, as before terrain).  A
map without elevation is flat ground at the datum: ``baro_altitude_m`` is the height above it.  With
``NavigatorOptions.terrain`` off, ``baro_altitude_m`` is taken as the height above the ground everywhere (the
flat assumption: what the terrain hook buys is measured against it in ``benchmarks/terrain_flight.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .._scipy import cKDTree
from .filter import ParticleFilter
from .frames import MIN_ALTITUDE_M, Frame

__all__ = ["MAX_REL_SIGMA", "NEIGHBOURS", "GroundHeight", "GroundModel", "height_above_ground"]

# Map objects whose elevations give the ground's at the filter's position.
NEIGHBOURS = 12
# The largest relative error (1 sigma) of a height above ground handed to the query: the terrain matcher
# searches the camera's height within 0.8-1.25 of the altitude given.
MAX_REL_SIGMA = 0.1


@dataclass(frozen=True)
class GroundHeight:
    """The ground's elevation at a position, its slope (metres per metre) and scatter, from the map."""

    elevation_m: float
    slope: float
    scatter_m: float


class GroundModel:
    """The ground's elevation anywhere from a map's objects (module docs).

    Parameters
    ----------
    x, y, elevation : numpy.ndarray
        The map objects' positions (map metres) and ground elevations (NaN where unknown).

    Raises
    ------
    ValueError
        No object has a finite elevation.

    Examples
    --------
    >>> x = np.array([0.0, 100.0, 0.0, 100.0]); y = np.array([0.0, 0.0, 100.0, 100.0])
    >>> g = GroundModel(x, y, 10.0 + 0.1 * x).at(50.0, 50.0)
    >>> round(g.elevation_m, 6), round(g.slope, 6), round(g.scatter_m, 6)
    (15.0, 0.1, 0.0)
    """

    def __init__(self, x: np.ndarray, y: np.ndarray, elevation: np.ndarray) -> None:
        known = np.isfinite(elevation)
        if not known.any():
            raise ValueError("no object has an elevation")
        self._xy = np.column_stack([x[known], y[known]])
        self._z = np.asarray(elevation[known], np.float64)
        self._tree = cKDTree(self._xy)

    @classmethod
    def of(cls, map_: Any) -> GroundModel | None:
        """The ground of a map that holds elevation; None for one without (flat ground)."""
        if not getattr(map_, "has_elevation", False):
            return None
        objects = map_.all()
        if objects.elevation is None or not np.isfinite(objects.elevation).any():
            return None
        return cls(objects.x, objects.y, objects.elevation)

    def at(self, x: float, y: float) -> GroundHeight:
        """The ground at map position ``(x, y)``: a weighted plane through the nearest objects (module docs)."""
        k = min(NEIGHBOURS, self._z.size)
        distance, index = self._tree.query([x, y], k=k)
        distance, index = np.atleast_1d(distance), np.atleast_1d(index)
        weight = 1.0 / np.maximum(distance, 1.0)
        z = self._z[index]
        mean = float(np.sum(weight * z) / np.sum(weight))
        if k < 3:
            return GroundHeight(mean, 0.0, float(np.ptp(z)) / 2.0)
        design = np.column_stack([np.ones(k), self._xy[index, 0] - x, self._xy[index, 1] - y])
        gram = design.T @ (weight[:, None] * design)
        if np.linalg.cond(gram) >= 1e9:  # objects in a line fix no plane: their mean, their spread as error
            return GroundHeight(mean, 0.0, float(np.ptp(z)) / 2.0)
        plane = np.linalg.solve(gram, design.T @ (weight * z))
        residual = z - design @ plane
        scatter = math.sqrt(float(np.sum(weight * residual**2) / np.sum(weight)))
        elevation = float(np.clip(plane[0], z.min(), z.max()))
        return GroundHeight(elevation, float(math.hypot(plane[1], plane[2])), scatter)


def height_above_ground(frame: Frame, ground: GroundModel | None, filter_: ParticleFilter, baro_std_m: float,
                        terrain: bool = True) -> dict[str, Any] | None:
    """Give ``frame`` its height above the ground from its barometer (module docs); what was done, or None.

    Parameters
    ----------
    frame : Frame
        Changed in place: ``altitude`` and its image's ``altitude_m`` set when a height is given.
    ground : GroundModel or None
        The map's ground; None for a map without elevation (flat ground at the datum).
    filter_ : ParticleFilter
        The navigator's filter, predicted to the frame's time: its position (map metres) and the largest axis
        of its covariance (1 sigma).
    baro_std_m : float
        The barometer's error (1 sigma, metres).
    terrain : bool
        False: the barometric altitude is taken as the height above the ground (the flat assumption).

    Returns
    -------
    dict or None
        None when the frame has its own ``altitude_m`` or no barometer (nothing done); else the record's
        ``altitude``: ``baro_m``, and ``above_ground_m``, ``ground_m``, ``sigma_m`` and ``used`` over terrain.
    """
    baro = frame.baro_altitude
    if frame.altitude is not None or baro is None:
        return None
    if ground is None or not terrain:
        _give(frame, baro)
        return {"baro_m": round(baro, 3), "above_ground_m": round(baro, 3), "used": frame.altitude is not None}
    if not filter_.initialised:
        return {"baro_m": round(baro, 3), "used": False, "reason": "no position yet: no ground under it"}
    centre, _, cov, _ = filter_.estimate()
    spread = math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))
    here = ground.at(centre.real, centre.imag)
    above = baro - here.elevation_m
    sigma = math.sqrt(baro_std_m**2 + (here.slope * spread) ** 2 + here.scatter_m**2)
    out: dict[str, Any] = {"baro_m": round(baro, 3), "ground_m": round(here.elevation_m, 3),
                           "above_ground_m": round(above, 3), "sigma_m": round(sigma, 3)}
    if above < MIN_ALTITUDE_M or sigma > MAX_REL_SIGMA * above:
        out.update(used=False, reason=f"height above ground {above:.1f} +- {sigma:.1f} m: too uncertain for the "
                                      "query's scale")
        return out
    _give(frame, above)
    out["used"] = frame.altitude is not None
    return out


def _give(frame: Frame, altitude: float) -> None:
    """The frame's altitude and its image's ``altitude_m`` (the query's scale) set to ``altitude``."""
    if not altitude >= MIN_ALTITUDE_M:  # below the ground (or NaN): the query goes without
        return
    frame.altitude = altitude
    if frame.image is not None:
        frame.image = replace(frame.image, altitude_m=altitude)
