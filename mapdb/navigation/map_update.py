"""The map-likelihood update: weak evidence from many frames weighed into the particles (Monte Carlo localization).

The matcher answers a frame only when it is decisive alone (an a-contrario number of false alarms below
``epsilon``).  Over rendered masks at 120 m many frames are not: a quarter of Andorra's frames score a log10
NFA between -4 and 0 even with the true pose as prior (real evidence, not decisive), and between fixes the
track drifts on the frame-to-frame velocity.  On a frame that gets no applied fix (none, rejected, withheld
as imprecise), :class:`MapUpdate` weighs every particle by the likelihood of the frame's objects under the
map instead, so that weak evidence accumulates across frames in the particles' weights.

**Model.**  Particle ``k`` at ``p_k`` (complex map metres) puts a whole (not border-cut) image object ``z_i``
(levelled, pixels from the nadir, y up) at ``m_ik = p_k + A z_i``, with ``A`` the frame's carried
image-to-map similarity (:class:`~mapdb.navigation.orientation.Orientation`).  Its residual ``e_ik`` from the
nearest map object of its label is split along (``r``) and across (``t``) the direction from the nadir, and
its likelihood is a robust mixture::

    l_ik = (1 - CLUTTER_SHARE) N(e_r; sigma_r) N(e_t; sigma_t) + CLUTTER_SHARE / (pi CLUTTER_RADIUS_M^2)

The clutter term stands for an object the map lacks (OSM is incomplete), a spurious or merged blob, a tall
building's roof far from its footprint: an object more than about 3 sigma from every map object of its label
counts as clutter, and a frame seen where the map has nothing moves no weight.  Per axis,
``sigma_t^2 = (blob_px s)^2 + floor^2`` (the blob's centroid, ``BLOB_FIX_FLOOR_PX`` pixels at the scale
``s``, and the attitude errors' floor) and ``sigma_r^2 = sigma_t^2 + (r_i scale_sigma)^2 + (RELIEF_KAPPA
r_i)^2``: the scale's relative error and relief move an object only along the direction from the nadir, in
proportion to its distance ``r_i = |A z_i|`` from it (blob centroids lie outward of their footprints by 3-4 %
of ``r_i`` at 120 m with heights, :mod:`mapdb.match.evidence.relief`; the carried scale comes from fixes that
absorbed the mean, the buildings' differing heights leave a scatter of that order).  Border-cut blobs are
left out: their centroids are pulled inward by a median 32-39 px.

**The heading's error is common** to all objects of a frame, so it is marginalised rather than added per
object: the frame's likelihood is evaluated at ``HEADING_NODES`` heading offsets (Gauss-Hermite) and
combined by their weights (log-sum-exp).  Heading and scale errors are the pose prior's
(:meth:`Orientation.pose_prior`: floors and growth since the last fix).

**Correlated frames.**  At 5 fps consecutive frames see the same buildings with the same relief error: the
frames' likelihoods are not independent, and multiplying them as if they were makes the cloud overconfident
(it then rejects right fixes).  The update is tempered, ``w_k <- w_k l_k^TEMPER``, and the cloud's spread is
kept at least as wide as one frame's evidence, ``sqrt(mean sigma_i^2 / n)`` per axis (the error the frames
share, as :func:`~mapdb.navigation.filter.shared_sigma` keeps it for fixes).

**Aliasing.**  The update only reweights the existing cloud: it never creates a mode.  The fix gate and the
recovery of :mod:`mapdb.navigation.navigator` still decide where the aircraft is.  A frame with fewer than
``MIN_OBJECTS`` whole objects, or a cloud wider than ``MAX_CLOUD_M``, is skipped.

**Cost.**  The nearest map object of each label comes from a grid (``CELL_M`` cells: each node holds its
nearest object, by a distance transform) over a box around the cloud and the footprint, rebuilt only when the
cloud leaves it (``MARGIN_M``): 2000 particles x 10 objects x 3 headings are a few gathers, not a tree query
each (a KD-tree query of 48,000 points took 16 ms on the shared machine, the gathers 2-3 ms).

**Numbers, measured** (rendered-mask flights of ``benchmarks/navigation_masks.py``, 120 m with heights, 3 km,
lost-in-space start; frames within 2 m of the truth after the first fix; main without the update: Andorra
80.6 %, Monaco 98.1 %).  Isotropic sigmas, clutter share 0.2, at least 2 whole objects: Andorra 95.7 %;
at least 1: 98.4 % (a frame with one whole building still constrains the cloud), but Monaco 95.8 % (one or two
objects, tall buildings and merged blobs, pulled the track 2-3 m off for a second); residuals split along and
across the direction from the nadir: Andorra 99.5 %, Monaco 97.3 %; and ``CLUTTER_SHARE`` 0.5: Andorra 99.7 %,
Monaco 98.1 %.  ``RELIEF_KAPPA`` 0.06 instead of 0.03 changed Andorra by +0.1 and Monaco by -0.3 points;
``TEMPER`` 0.5 and 0.1 instead of 0.2 (isotropic) moved Andorra by +0.4 and -0.5 points.  The heading
(``python benchmarks/map_update_variants.py --maps andorra,monaco --cases heights --starts lis``): 3 nodes
99.7 % / 98.1 % (Andorra / Monaco), 5 nodes 99.5 % / 98.1 % at 2.5-2.7 ms a frame instead of 1.6-1.9, the
heading's error added per object as if independent 99.2 % / 97.4 % at 1.0 ms.  Side by side against main
(8a173ad) on the eight flights (heights and 15 % missing, lost-in-space and ``--initial``; ``python
benchmarks/navigation_masks.py --maps andorra,monaco --cases heights,thin15 --altitudes 120 --starts
lis,initial --length 3000 --baseline main``), within 2 m: Andorra 99.7 % (main 79.9-83.6 %), largest error
2.1-2.2 m (7.0-7.4 m); Monaco 96.9-98.3 % (92.6-98.4 %), largest 2.9-3.9 m (2.9-5.5 m); no wrong fix,
beyond 3 sigma at most 0.9 %, median time a frame 1.00-1.08x main's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .filter import ParticleFilter
from .orientation import Orientation
from .velocity import FramePoints

__all__ = ["CAP_M", "CELL_M", "CLUTTER_RADIUS_M", "CLUTTER_SHARE", "HEADING_NODES", "MARGIN_M", "NearestObjects",
           "MAX_CLOUD_M", "MIN_OBJECTS", "MapUpdate", "RELIEF_KAPPA", "TEMPER", "frame_log_likelihood"]

# The share of a frame's objects that match nothing in the map (missing from it, spurious, merged), and the
# radius of the disc the clutter density is spread over: an object farther than about 3 sigma from every
# map object of its label (sigma 1-2 m) then counts as clutter.
CLUTTER_SHARE = 0.5
CLUTTER_RADIUS_M = 10.0
# Relief's radial scatter, per metre from the nadir (relief.py: 3-4 % at 120 m with heights).
RELIEF_KAPPA = 0.03
# Gauss-Hermite nodes over the frame's heading error.
HEADING_NODES = 3
# The update's exponent on a frame's likelihood: consecutive frames share most of their objects' errors.
TEMPER = 0.2
# Fewer whole objects than this: the frame is skipped.
MIN_OBJECTS = 1
# A cloud spread over more than this (metres, its box's larger side): the frame is skipped (lost or
# recovering: the matcher's search decides, and the grid would be large).
MAX_CLOUD_M = 200.0
# The nearest-object grid: cell size; the reach beyond the box whose objects are read (an object farther than
# it from every map object is clutter alike: 3 sigma is 3-6 m); the box's margin.
CELL_M = 0.5
CAP_M = 12.0
MARGIN_M = 100.0


class NearestObjects:
    """The nearest map object of each label at the nodes of a grid over a box (module docs, cost).

    Parameters
    ----------
    map : MetaMap or MemoryMap
        Read once for the box (``query_bbox``).
    box : (minx, miny, maxx, maxy)
        Map metres.
    """

    def __init__(self, map: Any, box: tuple[float, float, float, float]) -> None:
        self.box = box
        self.nx = int(math.ceil((box[2] - box[0]) / CELL_M)) + 2
        self.ny = int(math.ceil((box[3] - box[1]) / CELL_M)) + 2
        # Objects within CAP_M outside the box can still be the nearest to points inside it.
        objects = map.query_bbox(box[0] - CAP_M, box[1] - CAP_M, box[2] + CAP_M, box[3] + CAP_M)
        self._z = np.asarray(objects.x + 1j * objects.y, np.complex128)
        self._label = np.asarray(objects.label, np.int64)
        self._grids: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}

    def covers(self, box: tuple[float, float, float, float]) -> bool:
        """Whether ``box`` lies inside this field's box."""
        return (box[0] >= self.box[0] and box[1] >= self.box[1] and box[2] <= self.box[2]
                and box[3] <= self.box[3])

    def _grid(self, label: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The label's objects and the grid of the nearest one's index (None: none near the box), made on
        first use."""
        if label not in self._grids:
            z = self._z[self._label == label]
            self._grids[label] = None if z.size == 0 else (z, self._nearest(z))
        return self._grids[label]

    def _nearest(self, z: np.ndarray) -> np.ndarray:
        from scipy.ndimage import distance_transform_edt

        # Each object marks its cell (clipped into the grid: those just outside reach the edge cells); the
        # transform names each node's nearest marked cell, whose object is the node's nearest object.
        ix = np.clip(np.rint((z.real - self.box[0]) / CELL_M), 0, self.nx - 1).astype(np.int64)
        iy = np.clip(np.rint((z.imag - self.box[1]) / CELL_M), 0, self.ny - 1).astype(np.int64)
        owner = np.full((self.nx, self.ny), -1, np.int32)
        owner[ix, iy] = np.arange(z.size)
        _, (jx, jy) = distance_transform_edt(owner < 0, return_indices=True)
        return owner[jx, jy]

    def residual(self, label: int, w: np.ndarray) -> np.ndarray | None:
        """``w`` minus the label's map object nearest to it (complex metres; the nearest grid node's nearest:
        they differ only about half a cell from where two objects are equally near), or None when the label
        has no map object near the box.  Points outside the box are answered from its edge."""
        grid = self._grid(label)
        if grid is None:
            return None
        z, nearest = grid
        ix = np.clip(np.rint((w.real - self.box[0]) / CELL_M), 0, self.nx - 1).astype(np.int64)
        iy = np.clip(np.rint((w.imag - self.box[1]) / CELL_M), 0, self.ny - 1).astype(np.int64)
        return np.asarray(w - z[nearest[ix, iy]])


@dataclass(frozen=True)
class _Frame:
    """A frame's objects as the update uses them: map offsets at the nominal heading, labels, sigmas."""

    offsets: np.ndarray  # A z_i (complex metres)
    codes: np.ndarray
    sigma_t: np.ndarray  # per-axis metres, across the direction from the nadir
    sigma_r: np.ndarray  # along it
    heading_sigma_rad: float


def frame_log_likelihood(field: NearestObjects, particles: np.ndarray, offsets: np.ndarray, codes: np.ndarray,
                         sigma_t: np.ndarray, sigma_r: np.ndarray | None = None, heading_sigma_rad: float = 0.0,
                         nodes: int = HEADING_NODES) -> np.ndarray:
    """``log l_k`` of a frame's objects at every particle (module docs: the mixture, the heading marginalised).

    Parameters
    ----------
    field : NearestObjects
        Covering the particles plus the offsets.
    particles : complex array (N,)
    offsets : complex array (n,)
        The objects' map offsets from the nadir at the nominal heading, ``A z_i``.
    codes : int array (n,)
        Their labels (the map's codes).
    sigma_t, sigma_r : float arrays (n,)
        Their errors, metres, across and along the direction from the nadir (``sigma_r`` None: isotropic).
    heading_sigma_rad : float
        The heading's error, marginalised over ``nodes`` Gauss-Hermite points (1: not).
    """
    sigma_r = sigma_t if sigma_r is None else sigma_r
    x, w = np.polynomial.hermite_e.hermegauss(nodes if heading_sigma_rad > 0 else 1)
    clutter = math.log(CLUTTER_SHARE / (math.pi * CLUTTER_RADIUS_M**2))
    hit = np.log1p(-CLUTTER_SHARE) - np.log(2.0 * math.pi * sigma_t * sigma_r)
    radial = np.where(np.abs(offsets) > 0, offsets / np.maximum(np.abs(offsets), 1e-12), 1.0).conj()
    total = np.tile(np.log(w / w.sum())[:, None], (1, particles.size))
    for j, t in enumerate(x):
        turn = np.exp(-1j * t * heading_sigma_rad)  # clockwise heading: -i
        for i in range(offsets.size):
            e = field.residual(int(codes[i]), particles + offsets[i] * turn)
            if e is None:
                continue
            e = e * radial[i] * np.conj(turn)  # along (real) and across (imaginary) the direction from the nadir
            m2 = (e.real / sigma_r[i]) ** 2 + (e.imag / sigma_t[i]) ** 2
            total[j] += np.logaddexp(hit[i] - 0.5 * m2, clutter)
    top = total.max(axis=0)
    return np.asarray(top + np.log(np.exp(total - top).sum(axis=0)))


class MapUpdate:
    """The map-likelihood update of a navigator (module docs): one a navigator, holding its nearest-object grid.

    Parameters
    ----------
    map : MetaMap or MemoryMap
    blob_floor_px : float
        A blob centroid's error, pixels per axis.
    temper, nodes : float, int
        ``TEMPER`` and ``HEADING_NODES`` unless given.
    """

    def __init__(self, map: Any, blob_floor_px: float = 2.0, temper: float = TEMPER,
                 nodes: int = HEADING_NODES) -> None:
        self.map = map
        self.n_labels = len(map.labels)
        self.blob_floor_px = blob_floor_px
        self.temper = temper
        self.nodes = nodes
        self.field: NearestObjects | None = None

    def update(self, flt: ParticleFilter, points: FramePoints | None, orientation: Orientation,
               time_s: float | None, floor_m: float) -> dict[str, Any]:
        """Weigh the filter's particles by the frame's objects under the map; the record's ``map_update``.

        ``floor_m`` is the attitude errors' floor per axis (the navigator's).  Returns ``{"status": "used",
        "objects": n, "ess": effective particles after the update (before any resampling)}`` or ``{"status":
        "skipped", "objects": n, "reason": ...}``.
        """
        frame = self._frame(points, orientation, time_s, floor_m)
        n = 0 if frame is None else int(frame.offsets.size)
        if frame is None or n < MIN_OBJECTS:
            why = ("no heading or scale yet" if orientation.to_map() is None
                   else f"{n} whole objects of the map's labels")
            return {"status": "skipped", "objects": n, "reason": why}
        reach = float(np.max(np.abs(frame.offsets))) + CAP_M
        box = (float(flt.p.real.min()) - reach, float(flt.p.imag.min()) - reach,
               float(flt.p.real.max()) + reach, float(flt.p.imag.max()) + reach)
        if max(box[2] - box[0], box[3] - box[1]) - 2.0 * reach > MAX_CLOUD_M:
            return {"status": "skipped", "objects": n, "reason": f"the cloud is wider than {MAX_CLOUD_M:g} m"}
        if self.field is None or not self.field.covers(box):
            self.field = NearestObjects(self.map, (box[0] - MARGIN_M, box[1] - MARGIN_M, box[2] + MARGIN_M,
                                                  box[3] + MARGIN_M))
        loglik = frame_log_likelihood(self.field, flt.p, frame.offsets, frame.codes, frame.sigma_t, frame.sigma_r,
                                      frame.heading_sigma_rad, self.nodes)
        share = math.sqrt(float(np.mean(frame.sigma_t * frame.sigma_r)) / n)
        ess = flt.update_likelihood(self.temper * (loglik - float(loglik.max())), share)
        return {"status": "used", "objects": n, "ess": round(ess, 1)}

    def _frame(self, points: FramePoints | None, orientation: Orientation, time_s: float | None,
               floor_m: float) -> _Frame | None:
        """The frame's whole objects of the map's labels, with their offsets and errors (module docs)."""
        to_map = orientation.to_map()
        if points is None or to_map is None or orientation.scale is None:
            return None
        keep = points.codes < self.n_labels
        if points.border is not None:
            keep &= ~points.border
        offsets = to_map * points.z[keep]
        heading_sigma, scale_sigma = orientation.errors(time_s)
        r = np.abs(offsets)
        blob = self.blob_floor_px * orientation.scale
        sigma_t = np.full(r.size, math.hypot(blob, floor_m))
        sigma_r = np.sqrt(sigma_t**2 + (r * scale_sigma) ** 2 + (RELIEF_KAPPA * r) ** 2)
        return _Frame(offsets, points.codes[keep], sigma_t, sigma_r, math.radians(heading_sigma))
