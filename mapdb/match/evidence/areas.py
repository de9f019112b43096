"""Area evidence: a blob's area, at a hypothesis's scale, against its map object's stored area.

A hypothesis ``z -> a z + b`` fixes the scale (``|a|`` metres per pixel), so an image object's pixel area
(``area_px``, as :func:`mapdb.detections.masks.from_mask` and :mod:`mapdb.detections.coco` write it) becomes
square metres and can be compared with the area the map stores for the object it lands on.  In the a contrario model of
:mod:`mapdb.match.nfa` this is a *thinning* of the null's Poisson process: under the null, map
objects' areas are independent of where an image object lands, so the map objects of a label that are
*compatible* with a blob (their area within the blob's band) form a Poisson process of density
``lambda q``, ``q`` the share of the label's map objects that are compatible.  The evidence of an image
object is then the distance to the nearest *compatible* map object, normalised as ``u = lambda q pi r^2``:
the chance ``1 - exp(-u)`` is exact under the same independence assumption as the position term, and
everything downstream (tolerance shapes, the binomial tail, the number of tests) is unchanged.  Objects
with no area (ideal centroids, points) have ``q = 1`` and the nearest object, as before.

``q`` is counted around each hypothesis (the map objects of the label inside the density disc of
:meth:`~mapdb.match.mapobjects.object_index.ObjectIndex.local_density`, ``(compatible + 1) / (count + 1)``),
so a district of small houses does not make a small blob look rarer than it is there; a map object with no stored area
(a point) is always compatible.

**Bands, measured** (``mapdb simulate --render masks``, Andorra and Monaco, 640x480, 60 degrees, 300
images a row, each blob against the map object covering most of its pixels, blob area at the nominal
scale ``altitude / focal``; ratio = blob area / map area, percentiles 0.5 / 1 / 5 / 50 / 95 / 99 / 99.5):

* whole (not border-touching) buildings, 120 m with heights: 1.08 / 1.08 / 1.12 / 1.27 / 2.14 / 2.98 /
  4.31 (relief adds the visible walls, 8-60 %; merged blobs cover 8 % of whole blobs and carry about
  their buildings' summed area: against the sum, 99 % lie below 1.97); flat: 0.96 / 0.96 / 0.96 / 1.00 /
  1.39 / 2.69 / 2.91.
* other whole area objects (parks, water, grass, forest): at most 1.05 but down to 0.02 (a blob is often
  only the visible piece of a park or a river: trees, buildings and multipolygon parts hide the rest);
  roundabouts 0.86-3.0.
* border-cut blobs: only their visible part, down to 0; buildings up to 5.1 at 99 % (merges and relief).

So a **whole building** blob (a solid object seen entire) is compatible with map areas in
``[blob / RATIO_HIGH, blob / RATIO_LOW] = [blob / 2.2, blob / 0.85]``: about 95 % of the true matches with
heights (the tail is merged blobs), nearly all flat ones, with room below the flat 0.96 for mask erosion
and a quad's scale error.  **Every other** blob with an area (cut, or not a building) only bounds its map
object from below: ``map >= blob / CUT_RATIO_HIGH = blob / 5`` (99 % of the cut buildings).  A true match
outside its band loses its evidence (its nearest compatible map object is farther), it never gains any.
Against the region's building areas (log-area standard deviation 0.94 in Andorra, 1.13 in Monaco), a
whole building's band holds about a third of the map's buildings.

**The quad's own objects.**  At 120 m a median 4 blobs are whole and they build the quad, which the
position term does not count as evidence (AC-RANSAC's rule); but the quad is looked up by its shape only,
so its four areas are independent evidence: :func:`sample_evidence` multiplies the NFA by ``prod q`` when
all four are compatible (by 1 otherwise) and by ``2 - prod q`` for the choice between the two.

**Measured** (``python benchmarks/rendered_masks.py --n 150 --baseline HEAD``, Andorra and Monaco, 300
images a row; localized, answers more than 2 m off, RMS of the correct ones, before -> after): 120 m with
heights 34.7 % -> 40.0 %, 0 -> 0, 0.34 -> 0.39 m; flat 59.0 % -> 64.0 %, 0 -> 1 (2.06 m: the right place,
whose own true-correspondence fit is 1.11 m off), 0.23 -> 0.23 m; 200 m 69.3 -> 71.3 % and 81.7 -> 82.7 %
(3 and 3 answers 2-8 m off, before and after); 300 m 77.0 -> 78.0 % and 87.0 -> 89.3 % (none off);
ideal centroids unchanged (100 %).  Wrong places: the masks of each extract against the other's map (1,800
images at 120-300 m, with and without heights) were all rejected, the best wrong candidate's score at most
1.76 (1.99 without areas; acceptance needs 4).  Under the null the area-thinned residual is calibrated
(``tests/test_area_evidence.py``: random places and areas, ``P(u <= t)`` within 1.5 points of
``1 - exp(-t)`` for ``t <= 0.2``, below it beyond).  What limits 120 m is not the decision: in 160 images
with heights, 48 never produced a hypothesis within 5 m of the truth (too few whole blobs for a quad); of
the 300, 60 were rejected as uncertain with the best candidate at the true place, 46 of them within 2 units
of the threshold.

**Segmentation errors.**  A segmentation model's outline is often a pixel or two off all round, and moving an
outline by ``k`` px changes the area by about its perimeter times ``k``: the SpaceNet 4 chip's building mask
(``../shared/data/segmentation``, 0.5 m/px) eroded by 2 px leaves whole blobs at 0.31 / 0.71 / 0.77 of their
footprints (5th / 50th / 95th percentiles; 42 of 43 below ``RATIO_LOW``), dilated by 2 px at 1.21 / 1.30 / 1.66
(inside the band).  Outside its band a true match does not merely lose its evidence: its nearest *compatible*
map object is a wrong one, far away, so with every blob outside the image scores worse than with no areas at
all (the eroded chip: log10 NFA -0.1 with areas, -125.6 on positions alone; rejected).  So the decision is
floored by the same test on the positions alone (:func:`points_floor`): the two share the false-alarm budget,
:data:`POINTS_SHARE` = 1 % to the positions (which must then beat the threshold by 2 units) and 99 % to the
test with areas (which pays 0.004), so the count stays honest whichever decides, and when the areas' share is
what rejected an image whose positions alone pass the threshold, the answer says so (``rejected_by``).
Measured (``python benchmarks/segmentation_areas.py``; README): the eroded and dilated chips localize within
0.02 m, and the rendered masks at 120 m with heights are localized exactly as before.  Tried and left out:
widening the bands by the outline's possible movement (``(sqrt(A) -/+ 2k)^2``, a square's perimeter, for
``k`` = 1 and 2 px): exact masks at 120 m with heights in Andorra, 150 images, were localized 62.0 % before,
60.7 % with a 10 % share for the positions (the area test paying 0.046) and 59.3 % with that and the wider
bands (images that pass the threshold by less than 0.3: a wider band is weaker evidence), while the wider
bands gained one image of 150 eroded by 2 px in each extract.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..arrays import sorted_unique

__all__ = [
    "CUT_RATIO_HIGH", "POINTS_SHARE", "RATIO_HIGH", "RATIO_LOW", "SOLID_LABELS", "ImageAreas", "bands", "compatible",
    "disc_chances", "points_floor", "sample_evidence", "solid_objects",
]

# Blob area (at the hypothesis's scale) over its map object's area: the bands of the module docs.  A whole
# solid blob: within [RATIO_LOW, RATIO_HIGH]; any other blob: at most CUT_RATIO_HIGH.
RATIO_LOW = 0.85
RATIO_HIGH = 2.2
CUT_RATIO_HIGH = 5.0
# The share of the decision's false-alarm budget spent on the points-only test that floors the area evidence
# (:func:`points_floor`; module docs, "Segmentation errors"): the test with areas pays log10(1 / (1 - share)),
# 0.004, the points-only one log10(1 / share), 2.
POINTS_SHARE = 0.01
# Labels whose whole blobs show the whole object (a roof and walls), so that a blob bounds its map
# object's area from above as well as from below.
SOLID_LABELS = frozenset({"building"})


@dataclass(frozen=True)
class ImageAreas:
    """An image's object areas for the decision: ``log_px`` (natural log of ``area_px``, NaN where an object
    has none) and ``two_sided`` (whole blobs of a solid label, whose band is bounded on both sides)."""

    log_px: np.ndarray
    two_sided: np.ndarray

    @classmethod
    def of(cls, area_px: np.ndarray | None, whole: np.ndarray | None, img_label: np.ndarray,
           labels: tuple[str, ...]) -> ImageAreas | None:
        """The areas of an image's objects, or None when none has a positive area (ideal centroids).

        ``whole`` says which objects do not touch the border (None: unknown, so every band is one-sided).

        Examples
        --------
        >>> ar = ImageAreas.of(np.array([100.0, np.nan, 50.0]), np.array([True, True, False]),
        ...                    np.array([0, 0, 1]), ("building", "park"))
        >>> np.isnan(ar.log_px).tolist(), ar.two_sided.tolist()
        ([False, True, False], [True, False, False])
        >>> ImageAreas.of(None, None, np.array([0]), ("building",)) is None
        True
        """
        if area_px is None:
            return None
        area = np.asarray(area_px, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_px = np.where(area > 0, np.log(area), np.nan)
        if not np.isfinite(log_px).any():
            return None
        whole_mask = np.zeros(area.size, bool) if whole is None else np.asarray(whole, bool)
        return cls(log_px, whole_mask & solid_objects(img_label, labels) & np.isfinite(log_px))


def solid_objects(img_label: np.ndarray, labels: tuple[str, ...]) -> np.ndarray:
    """Which image objects (label codes into ``labels``) are of a solid label (:data:`SOLID_LABELS`).

    Examples
    --------
    >>> solid_objects(np.array([1, 0, 1]), ("park", "building")).tolist()
    [True, False, True]
    >>> solid_objects(np.zeros(0, np.int64), ("building",)).tolist()
    []
    """
    solid = np.array([name in SOLID_LABELS for name in labels], bool)
    return solid[np.asarray(img_label, np.int64)]


def bands(areas: ImageAreas, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log map areas (square metres) compatible with each object under each hypothesis: ``(lo, hi)``, each
    ``(H, n)``; ``(-inf, inf)`` where an object has no area.

    Examples
    --------
    >>> ar = ImageAreas(np.log(np.array([400.0, 400.0])), np.array([True, False]))
    >>> lo, hi = bands(ar, np.array([0.5]))  # 100 m^2 at 0.5 m per pixel
    >>> np.round(np.exp(lo), 1).tolist(), np.exp(hi).round(1).tolist()
    ([[45.5, 20.0]], [[117.6, inf]])
    """
    log_m2 = areas.log_px[None, :] + 2.0 * np.log(np.abs(np.asarray(a)))[:, None]
    known = np.isfinite(log_m2)
    two = known & areas.two_sided[None, :]
    lo = np.where(two, log_m2 - math.log(RATIO_HIGH), np.where(known, log_m2 - math.log(CUT_RATIO_HIGH), -np.inf))
    hi = np.where(two, log_m2 - math.log(RATIO_LOW), np.inf)
    return lo, hi


def compatible(log_area: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Whether map objects of log areas ``log_area`` (NaN: no stored area, always compatible) lie in the bands."""
    with np.errstate(invalid="ignore"):
        return np.isnan(log_area) | ((log_area >= lo) & (log_area <= hi))


def disc_chances(log_area: np.ndarray, members: list[list[np.ndarray]], img_label: np.ndarray, lo: np.ndarray,
                 hi: np.ndarray) -> np.ndarray:
    """``q[h, i]``: the share of the map objects of object ``i``'s label around hypothesis ``h`` (indices
    ``members[h][label]``) compatible with its band, as ``(compatible + 1) / (count + 1)``.

    Examples
    --------
    >>> log_area = np.log(np.array([10.0, 100.0, 1000.0, np.nan]))
    >>> members = [[np.array([0, 1, 2, 3])]]
    >>> lo, hi = np.log(np.array([[50.0, 1.0]])), np.log(np.array([[500.0, 5.0]]))
    >>> disc_chances(log_area, members, np.array([0, 0]), lo, hi).tolist()  # 100 and the point; the point
    [[0.6, 0.4]]
    """
    h, n = lo.shape
    q = np.ones((h, n))
    for row in range(h):
        for code in sorted_unique(img_label):
            cols = np.flatnonzero((img_label == code) & (np.isfinite(lo[row]) | np.isfinite(hi[row])))
            if not cols.size:
                continue
            near = log_area[members[row][code]]
            unknown = int(np.isnan(near).sum())
            known = np.sort(near[~np.isnan(near)])
            inside = np.searchsorted(known, hi[row, cols], "right") - np.searchsorted(known, lo[row, cols], "left")
            q[row, cols] = (inside + unknown + 1.0) / (near.size + 1.0)
    return q


def sample_evidence(sample_compatible: np.ndarray, sample_share: np.ndarray) -> np.ndarray:
    """log10 factor on each hypothesis's NFA from the areas of the objects that built it: ``(H,)``.

    A quad is found by its shape alone, so under the null its map objects' areas are independent of its
    image objects' areas: all four compatible has chance ``Q = prod q``.  The statistic multiplies the
    position NFA by ``Q`` when all are compatible and by 1 otherwise.  Under the null the first branch
    reaches a threshold ``eps`` with chance ``Q * eps / Q`` and the second with ``(1 - Q) eps``, so the NFA
    carries the factor ``2 - Q`` for the two (1 when the sample has no areas, at most 2).

    ``sample_compatible`` and ``sample_share`` are ``(H, s)``.

    Examples
    --------
    >>> sample_evidence(np.array([[True] * 4, [True, True, True, False]]), np.full((2, 4), 0.5)).round(2).tolist()
    [-0.92, 0.29]
    >>> sample_evidence(np.ones((1, 4), bool), np.ones((1, 4))).tolist()  # no areas: no change
    [0.0]
    """
    log_q = np.log10(np.clip(sample_share, 1e-300, 1.0)).sum(axis=1)
    return np.where(sample_compatible.all(axis=1), log_q, 0.0) + np.log10(2.0 - 10.0**log_q)


def points_floor(with_areas: np.ndarray, points: np.ndarray, share: float = POINTS_SHARE) -> np.ndarray:
    """The decision's log10 NFA: the test with areas, floored by the same test on positions alone (``(H,)`` each).

    The two tests of a hypothesis share the false-alarm budget (Bonferroni: ``NFA = min(NFA_areas / (1 - share),
    NFA_points / share)``), so the number of false alarms stays honest whichever decides, and an image whose
    areas are off (a mask eroded by a few pixels, merged blobs) is still accepted when its positions alone beat
    the threshold by ``log10(1 / share)``.

    Examples
    --------
    >>> points_floor(np.array([-10.0, -1.0]), np.array([-3.0, -8.0])).round(3).tolist()
    [-9.996, -6.0]
    """
    return np.minimum(np.asarray(with_areas) - math.log10(1.0 - share), np.asarray(points) - math.log10(share))
