"""Terrain: each image ray cast onto the map objects' heights, where the map holds elevation (issue 33).

A level (or levelled) pinhole camera at height ``H`` above the datum, its nadir at ``b``, heading ``u``
(a unit complex number), sees a map object at elevation ``h`` and map position ``w`` at the image point

    z = f (w - b) / (u (H - h)),   so that   w = b + u z (H - h) / f.

The matcher's hypotheses are similarities ``w = a z + b``: one scale for every object, right only on flat
ground.  Over Monaco the objects inside a 120 m footprint span a median 22.5 m of elevation (a 19 % spread of
scale), so a similarity predicts the far objects metres off and the final fit is pulled 2-5 m
(``python benchmarks/terrain.py``).  With a map that holds elevation (``mapdb build --dem``), the field of
view given (``f``) and the image levelled (roll and pitch given, or a level camera), :class:`TerrainModel`:

* **predicts** each image object where its ray meets the ground (:meth:`TerrainModel.project`): from the
  hypothesis's ``b`` and ``a`` (heading, and the scale ``D / f`` at the ground under the nadir, of elevation
  ``g``, ``D = H - g``), the object's map position ``w = b + a z (D - (h - g)) / D`` with ``h`` the ground's
  elevation where the ray lands, found by casting twice from the flat prediction (``h`` read from the map
  objects around the landing point, inverse-distance weighted, so an object's own elevation once the ray lands
  on it).  ``D`` is the image's ``altitude_m`` (the camera's height above the ground under it) when given;
  without it, the hypothesis's own scale, ``|a| f``, at the elevation of the map points it was fitted to;
* **fits** the final pose to rays on the matched objects' own elevations (:meth:`TerrainModel.fit_sources`):
  the image points are rescaled to the nadir ground's scale, ``z (D - (h_j - g)) / D``, and the similarity
  fitted to them, so the unknowns stay position and heading (and a common scale absorbing the field of
  view's error).  ``D`` is the most likely height given the rays (their spread over the relief fixes it) and,
  when the image gives its altitude, the altitude as a measurement of it: the altitude is the camera's height
  above the true ground under it, and the map knows that ground only through the objects around it, so the
  measurement's error is the map's ground's under the nadir (:meth:`TerrainModel.nadir_ground`: a plane
  through the 12 nearest objects, its prediction error ``s^2 (1 + leverage)`` from the objects' scatter
  about it, plus 0.1 m a metre from the nearest object for relief nobody mapped).  The position's error then
  adds what the remaining uncertainty of ``D`` moves it (``|db/dD|^2 var(D) / 2`` per axis, computed, not
  bounded: large where the objects lie to one side of the nadir over a slope).

The decision's a-contrario test is unchanged: its residuals are measured from these predictions instead of the
similarity's, so on flat ground (every ``h = g``) they are the similarity's exactly, and a map without
elevation or an image without field of view never reaches this module (answers unchanged, byte for byte).

The numbers: 4 map objects weigh the ground's elevation at a point, 2 casts a ray, the camera's height above
the nadir's ground is searched over 11 values in 0.8-1.25 of the altitude given (31 in 0.4-2.5 of the
hypothesis's scale without one), then over 9 across the best one's neighbours, its vertex from a parabola; a
last lookup pass of 10 px is added (``mapdb.match.fast.TERRAIN_PIXEL_SIGMA``: relief bends the shape of
quads of far-apart objects) and an answer is accepted only within 0.66 m per axis
(``mapdb.match.fast.TERRAIN_MAX_SIGMA_M``: 2 m beyond it with a 1 % chance).  The ground's error model,
measured with ``python benchmarks/terrain.py --ground`` (the SRTM ground under the 500 nadirs of a row
against the plane through the map's objects): at 300 m median error 1.2 m, 90th percentile 6.7 m, largest
35 m, and the error over the modelled sigma 1.17, 2.26 and 3.08 at the 90th and 99th percentiles and the
largest (a Gaussian: 1.64, 2.58 and, in 500, about 3.0); at 120 m 0.7, 2.8 and 8.0 m, ratios 1.03, 1.83 and
2.37.  Without the unmapped-relief term the ratio's 99th percentile was 6.8 at 300 m (a hilltop between
objects: a /tmp script over the same nadirs).

Measured (``python benchmarks/terrain.py --n 500 --no-altitude --baseline main``): see the README's table.
Where it fails: images whose objects all lie 90-160 m to one side of the nadir (a camera over the sea off
Monaco's coast, or over a hilltop above its visible objects): the similarity's extrapolation to the nadir is
uncertain whatever the height (the flat control withholds the same images), and such answers are withheld;
images of 6-8 objects whose a-contrario test falls short (as on flat ground).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..._scipy import quick_tree
from ..geometry import fit_similarity_complex

__all__ = ["TerrainModel"]

# Map objects whose elevations give the ground's at a point (inverse-distance weighted).
_NEIGHBOURS = 4
# Casts of a ray onto the ground: the first from the flat prediction, the second from where it landed.
_CASTS = 2
# The camera's height above the nadir's ground is searched within these factors of its first estimate.
_WITH_ALTITUDE = (0.8, 1.25, 11)
_WITHOUT_ALTITUDE = (0.4, 2.5, 31)
# Points of the finer search across the best coarse step's two neighbours.
_FINE_STEPS = 9
# Map objects a plane is fitted to for the ground under the nadir (the altitude's reference).
_PLANE_NEIGHBOURS = 12
# How steeply the ground may rise or fall between mapped objects, for the error of the ground under a nadir
# d metres from the nearest object: 0.1 d (module docs: measured over Monaco).
_UNSEEN_SLOPE = 0.1
# The ground under the nadir is never known better than this (m^2): the map's 1 m elevation codes.
_MIN_GROUND_VARIANCE = 0.25


class TerrainModel:
    """Rays cast onto the heights of a map's objects, for one image.

    Parameters
    ----------
    index : ObjectIndex
        The map objects, with ``elevation`` (NaN where unknown).
    focal_px : float
        The camera's focal length in pixels (from the field of view).
    altitude_m : float or None
        The camera's height above the ground under it, when the image gives it.

    Examples
    --------
    A camera 100 m above flat ground at 0 m sees an object 20 m up, 40 m east, at ``40 f / 80`` pixels:

    >>> from mapdb.objects import Objects
    >>> from mapdb.match.mapobjects.object_index import ObjectIndex
    >>> o = Objects.from_names([0.0, 40.0, 0.0, -40.0], [0.0, 0.0, 40.0, 0.0], ["b"] * 4)
    >>> idx = ObjectIndex(o.with_elevation(np.array([0.0, 20.0, 0.0, 0.0])))
    >>> t = TerrainModel.of(idx, 500.0, 100.0)
    >>> w = t.project(np.array([0.2]), np.array([0j]), np.array([40 * 500 / 80 + 0j, 40 * 500 / 100 * 1j]))
    >>> np.round(w, 1).tolist()
    [[(40+0j), 40j]]
    """

    def __init__(self, index: Any, focal_px: float, altitude_m: float | None) -> None:
        self.focal = float(focal_px)
        self.altitude = altitude_m
        if index.terrain is None:
            known = np.flatnonzero(np.isfinite(index.elevation))
            xy = np.column_stack([index.z.real[known], index.z.imag[known]])
            index.terrain = (quick_tree(xy), index.elevation[known])
        self.tree, self.heights = index.terrain

    @classmethod
    def of(cls, index: Any, focal_px: float | None, altitude_m: float | None) -> TerrainModel | None:
        """The model of an image, or None where it cannot be made: a map without elevation (or too few objects
        with one), an image without its field of view."""
        elevation = getattr(index, "elevation", None)
        if elevation is None or focal_px is None or np.count_nonzero(np.isfinite(elevation)) < _NEIGHBOURS:
            return None
        return cls(index, focal_px, altitude_m)

    def ground(self, w: np.ndarray) -> np.ndarray:
        """The ground's elevation (metres) at map positions ``w`` (complex, any shape)."""
        w = np.asarray(w, np.complex128)
        flat = w.reshape(-1)
        distance, which = self.tree.query(np.column_stack([flat.real, flat.imag]), k=_NEIGHBOURS)
        weight = 1.0 / np.maximum(distance, 0.05) ** 2
        return (np.sum(weight * self.heights[which], axis=1) / np.sum(weight, axis=1)).reshape(w.shape)

    def depth(self, a: np.ndarray, b: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
        """The camera's height above the ground under each hypothesis's nadir: the altitude given, or the
        hypothesis's scale ``|a| f`` at the elevation of ``ref`` (its map points, ``(H, k)``; None: the nadir's)."""
        a = np.asarray(a)
        if self.altitude is not None:
            return np.full(a.shape, float(self.altitude))
        depth = np.abs(a) * self.focal
        if ref is not None:
            depth = depth + self.ground(ref).mean(axis=-1) - self.ground(b)
        return np.maximum(depth, 1.0)

    def project(self, a: np.ndarray, b: np.ndarray, z: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
        """Where hypotheses ``(a, b)`` (``(H,)``) put the image objects ``z`` (``(n,)``) once each ray is cast
        onto the ground: ``(H, n)`` map positions.  ``a`` is the scale at the nadir's ground, or at ``ref``'s
        (the map points each hypothesis was fitted to, ``(H, k)``) when given."""
        a, b = np.atleast_1d(a), np.atleast_1d(b)
        g = self.ground(b)
        depth = self.depth(a, b, ref)
        if ref is not None:  # the similarity's scale is its map points': the nadir ground's is larger by this
            a = a * depth / np.maximum(depth - (self.ground(ref).mean(axis=-1) - g), 1.0)
        # The scale comes from the hypothesis (fitted to the map), the depth only into the ratio of each ray's
        # drop to the nadir's: an error of a few metres in the ground under the nadir stays second order.
        ray = a[:, None] * z[None, :] / depth[:, None]
        w = a[:, None] * z[None, :] + b[:, None]
        for _ in range(_CASTS):
            h = self.ground(w)
            w = b[:, None] + ray * np.maximum(depth[:, None] - (h - g[:, None]), 1.0)
        return w

    def requad(self, a: np.ndarray, b: np.ndarray, zq: np.ndarray, map_z: np.ndarray) -> tuple[np.ndarray, ...]:
        """Hypotheses refitted to their own quads (image points ``zq``, map points ``map_z``, ``(H, 4)``) with
        the rays onto the quad's map objects' heights: the pose its quad gives over terrain, at the nadir
        ground's scale (still only the quad's own points: the decision's a-contrario rule holds)."""
        depth = self.depth(a, b, map_z)[:, None]
        rise = self.ground(map_z) - self.ground(b)[:, None]
        a_new, b_new = fit_similarity_complex(zq * np.maximum(depth - rise, 1.0) / depth, map_z)
        ok = np.isfinite(a_new) & np.isfinite(b_new)
        return np.where(ok, a_new, a), np.where(ok, b_new, b)

    def nadir_ground(self, b: complex) -> tuple[float, float]:
        """The ground's elevation under the nadir ``b`` and its error variance (m^2): a plane through the
        ``_PLANE_NEIGHBOURS`` nearest map objects with an elevation, its prediction variance at ``b`` (the
        objects' scatter about the plane, ``s^2 (1 + leverage)``) plus ``(_UNSEEN_SLOPE d)^2``, ``d`` the
        nearest object's distance: ground nobody mapped may rise or fall between objects (module docs)."""
        k = min(_PLANE_NEIGHBOURS, self.heights.size)
        distance, which = self.tree.query([b.real, b.imag], k=k)
        distance, which = np.atleast_1d(distance), np.atleast_1d(which)
        design = np.column_stack([np.ones(k), self.tree.data[which] - [b.real, b.imag]])
        coef, *_ = np.linalg.lstsq(design, self.heights[which], rcond=None)
        residual = self.heights[which] - design @ coef
        scatter = float(residual @ residual) / max(k - 3, 1)
        leverage = float(np.linalg.pinv(design.T @ design)[0, 0])
        variance = scatter * (1.0 + leverage) + (_UNSEEN_SLOPE * float(distance[0])) ** 2
        return float(coef[0]), variance if math.isfinite(variance) else math.inf

    def fit_sources(self, z: np.ndarray, dst: np.ndarray, b: complex, scale: float,
                    elevation: np.ndarray) -> tuple[np.ndarray, float]:
        """Image points rescaled to the nadir ground's scale for the rays onto their map objects' ``elevation``
        (``dst`` their positions): ``z (D - (h - g)) / D``, ``D`` (the camera's height above the nadir's ground
        ``g``) the most likely given the rays and, with the altitude given, the altitude as a measurement of it;
        and the per-axis variance (m^2) the uncertainty in ``D`` adds to the position.

        ``D`` minimises ``S(D) + sigma^2 (D - A)^2 / var_g``: ``S`` the similarity fit's sum of squared
        residuals, ``sigma^2`` the residual variance (``2n - 5`` degrees of freedom), ``A`` the altitude given
        (the camera's height above the true ground under it) and ``var_g`` the error variance of the map's
        ground under the nadir (:meth:`nadir_ground`), so ``D = A`` up to that error; without the altitude the
        rays' spread over the relief alone fixes it.  Searched on a grid, then on a finer one around the best,
        its vertex taken from a parabola.  The position's variance is ``|db/dD|^2 / 2 var(D)``,
        ``var(D) = sigma^2 / c`` from the curvature ``c`` of that objective at its minimum: where the objects
        lie to one side of the nadir over a slope, the position leans on ``D``, and says so."""
        g, g_var = self.nadir_ground(b)
        rise = np.where(np.isfinite(elevation), elevation - g, 0.0)
        first = float(self.altitude) if self.altitude is not None else max(scale * self.focal, 1.0)
        low, high, steps = _WITH_ALTITUDE if self.altitude is not None else _WITHOUT_ALTITUDE
        depths = first * np.exp(np.linspace(math.log(low), math.log(high), steps))
        cost, b_fit = _profile(z, dst, rise, depths)
        sigma2 = float(np.min(cost)) / max(2 * z.size - 5, 1)
        total = cost + self._prior(depths, sigma2, g_var)
        k = int(np.argmin(total))
        if k in (0, steps - 1):  # at the searched range's edge: the range's whole spread
            depth, variance = _depth_variance(depths, total, b_fit, k, z.size)
            return self._rescaled(z, b, g + depth, g + rise), variance
        # A finer grid across the best coarse step's neighbours (inside the searched range).
        step = math.log(high / low) / (steps - 1)
        fine = depths[k] * np.exp(np.linspace(-step, step, _FINE_STEPS))
        cost, b_fit = _profile(z, dst, rise, fine)
        total = cost + self._prior(fine, sigma2, g_var)
        depth, variance = _depth_variance(fine, total, b_fit, int(np.argmin(total)), z.size)
        return self._rescaled(z, b, g + depth, g + rise), variance

    def _rescaled(self, z: np.ndarray, b: complex, height: float, heights: np.ndarray) -> np.ndarray:
        """Image points ``z`` of objects at ``heights`` seen from ``height`` (both above the datum), rescaled to
        the scale at the ground :meth:`project` puts under the nadir ``b``, ``z (H - h) / (H - g)``: the fit's
        scale is then the one the projection expects."""
        g = float(self.ground(np.array([b]))[0])
        return z * np.maximum(height - heights, 1.0) / max(height - g, 1.0)

    def _prior(self, depths: np.ndarray, sigma2: float, g_var: float) -> np.ndarray:
        """The altitude's term of the depth objective, in the residuals' units (0 without an altitude)."""
        if self.altitude is None or not math.isfinite(g_var):
            return np.zeros(depths.shape)
        return sigma2 * (depths - float(self.altitude)) ** 2 / max(g_var, _MIN_GROUND_VARIANCE)


def _profile(z: np.ndarray, dst: np.ndarray, rise: np.ndarray, depths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The similarity fit's sum of squared residuals and position for each depth (``inf`` where undefined)."""
    src = z[None, :] * np.maximum(depths[:, None] - rise[None, :], 1.0) / depths[:, None]
    a_fit, b_fit = fit_similarity_complex(src, np.broadcast_to(dst, src.shape))
    cost = np.sum(np.abs(a_fit[:, None] * src + b_fit[:, None] - dst[None, :]) ** 2, axis=1)
    return np.where(np.isfinite(cost), cost, np.inf), b_fit


def _depth_variance(depths: np.ndarray, total: np.ndarray, b: np.ndarray, k: int, n: int) -> tuple[float, float]:
    """The depth at the vertex of the parabola through the objective ``total`` around its grid minimum ``k``
    (clipped to its neighbours), and the per-axis variance (m^2) of the position from its uncertainty (see
    :meth:`TerrainModel.fit_sources`); at the grid's edge, that depth and the searched range's spread."""
    if n <= 3 or not np.isfinite(total[k]):
        return float(depths[k]), math.inf
    sigma2 = float(total[k]) / max(2 * n - 5, 1)
    if 0 < k < depths.size - 1:
        near = slice(k - 1, k + 2)
        c2, c1, _ = np.polyfit(depths[near], total[near], 2)
        slope = abs(complex(b[k + 1] - b[k - 1])) / float(depths[k + 1] - depths[k - 1])
        if c2 > 0 and math.isfinite(slope):
            depth = float(np.clip(-c1 / (2 * c2), depths[k - 1], depths[k + 1]))
            return depth, slope**2 / 2.0 * sigma2 / float(c2)
    finite = np.isfinite(b)
    spread = float(np.max(np.abs(b[finite] - b[k])) ** 2) / 2.0 if finite.any() else math.inf
    return float(depths[k]), spread
