"""The ground under a simulated camera: map objects at their heights, the camera above the ground or the datum.

Without terrain the simulator puts every object and the ground on one plane, and a shot's altitude is the
camera's height above it.  With terrain (``mapdb simulate --terrain``) each object stands at its ground
elevation, from the map (a version 2 map, ``mapdb build --dem``) or from DEMs given to the simulator, and the
camera's height is taken either

* above the ground under it (``above="ground"``, the default: a drone holding its height above ground,
  e.g. from a radar altimeter), so that its height above the datum is the shot's altitude plus the ground's
  elevation under the nadir; or
* above the vertical datum (``above="datum"``: a barometric altitude, the ground under it varying from image
  to image), so that its height above the ground is the shot's altitude less the ground's elevation.

Either way the image document's ``altitude_m`` (with ``--with-altitude``) is what ``docs`` and the image
schema say it is, the camera's height above the ground directly under it, and the truth adds ``ground_m``
(the ground's elevation under the nadir) and ``altitude_datum_m`` (the camera's height above the datum).
The ground's elevation under the camera comes from the DEMs when given, else from the map's objects around
it (a plane fitted to the 12 nearest with an elevation): a map holds elevations at its objects only.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .._scipy import cKDTree
from ..errors import EmptyMapError
from ..objects import Objects

if TYPE_CHECKING:
    from ..sources.dem import Dem

__all__ = ["ABOVE_CHOICES", "Terrain", "terrain_of"]

ABOVE_CHOICES = ("ground", "datum")
# Nearest objects a plane is fitted to for the ground's elevation between objects.
_NEIGHBOURS = 12
# A camera less than this fraction of its altitude above the ground (barometric altitudes over high ground)
# is not placed there: the simulator draws another position.
MIN_CLEARANCE = 0.1


class Terrain:
    """Object heights and the ground's elevation anywhere, for a simulated flight over relief.

    Parameters
    ----------
    objects : Objects
        The map's objects, with ``elevation`` unless ``dem`` is given.
    dem : Dem, optional
        Elevation rasters sampled at the objects and under the camera (instead of the map's elevation).
    above : {"ground", "datum"}
        What a shot's altitude is measured from.

    Raises
    ------
    EmptyMapError
        No object has an elevation (a map without elevation and no DEM, or a DEM beside the map).

    Examples
    --------
    >>> o = Objects.from_names([0.0, 100.0, 0.0], [0.0, 0.0, 100.0], ["a"] * 3, crs="EPSG:32631")
    >>> t = Terrain(o.with_elevation(np.array([10.0, 30.0, 10.0])))
    >>> round(t.ground(0.0, 0.0), 6), t.z.tolist()
    (10.0, [10.0, 30.0, 10.0])
    """

    def __init__(self, objects: Objects, dem: Dem | None = None, above: str = "ground") -> None:
        if above not in ABOVE_CHOICES:
            raise ValueError(f"altitude above {above!r}: not one of {', '.join(ABOVE_CHOICES)}")
        self.dem, self.above, self.crs = dem, above, str(objects.crs)
        z = dem.sample(objects.x, objects.y, self.crs)[0] if dem is not None else objects.elevation
        known = np.isfinite(z) if z is not None else np.zeros(len(objects), bool)
        if not known.any():
            if dem is not None:
                raise EmptyMapError(f"{', '.join(map(str, dem.paths))}: the DEM covers none of the map's objects")
            raise EmptyMapError("no map object has an elevation: build the map with --dem, or give the simulator "
                                "a --dem under it")
        assert z is not None
        self._xy = np.column_stack([objects.x[known], objects.y[known]])
        self._known_z = z[known]
        self._tree = cKDTree(self._xy)
        # Objects of unknown elevation stand on the ground their neighbours give.
        self.z = np.where(known, z, 0.0)
        if not known.all():
            self.z[~known] = self._between(objects.x[~known], objects.y[~known])

    def _between(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The ground's elevation at these positions from the nearest objects with one: a plane fitted to
        them (weights falling with distance), held within their range; their weighted mean where they fix no
        plane (fewer than 3, or in a line)."""
        k = min(_NEIGHBOURS, len(self._known_z))
        distance, index = self._tree.query(np.column_stack([x, y]), k=k)
        distance, index = distance.reshape(len(x), k), index.reshape(len(x), k)
        weight = 1.0 / np.maximum(distance, 1.0)
        z = self._known_z[index]
        mean = np.sum(weight * z, axis=1) / np.sum(weight, axis=1)
        if k < 3:
            return mean
        design = np.stack([np.ones_like(distance), self._xy[index, 0] - x[:, None],
                           self._xy[index, 1] - y[:, None]], axis=2)
        gram = np.einsum("nki,nk,nkj->nij", design, weight, design)
        solvable = np.linalg.cond(gram) < 1e9
        plane = mean.copy()
        if solvable.any():
            rhs = np.einsum("nki,nk,nk->ni", design[solvable], weight[solvable], z[solvable])
            plane[solvable] = np.linalg.solve(gram[solvable], rhs[:, :, None])[:, 0, 0]
        return np.clip(plane, z.min(axis=1), z.max(axis=1))

    def ground(self, x: float, y: float) -> float:
        """The ground's elevation (metres above the datum) at a map position."""
        if self.dem is not None:
            z = float(self.dem.sample(np.array([x]), np.array([y]), self.crs)[0][0])
            if np.isfinite(z):
                return z
        return float(self._between(np.array([x]), np.array([y]))[0])

    def placed(self, altitude: float, x: float, y: float) -> tuple[float, float] | None:
        """The ground's elevation under a camera of this altitude (a shot's) with its nadir at ``(x, y)``, and
        the camera's height above the datum; None when a datum altitude leaves it too close to the ground."""
        ground = self.ground(x, y)
        datum = altitude + ground if self.above == "ground" else altitude
        if datum - ground < MIN_CLEARANCE * altitude:
            return None
        return ground, datum


def terrain_of(map_: Any, dems: Sequence[str | Path] = (), above: str = "ground") -> Terrain | None:
    """The terrain of a map: from ``dems`` when given, else from the map's elevation; None for a map without
    elevation and no DEM (flat ground, as before terrain existed)."""
    if not dems and not getattr(map_, "has_elevation", False):
        return None
    from ..sources.dem import Dem

    return Terrain(map_.all(), Dem(dems) if dems else None, above)
