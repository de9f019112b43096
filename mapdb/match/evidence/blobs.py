"""Blob errors: where a segmentation blob's map object lies, as an anisotropic tolerance in the decision.

A blob cut by the image border shows only its visible part, whose centroid is pulled *inward*: its map
object lies outward along the normal of the border it touches, by an amount that depends on how much is
hidden, and close to it along the border.  Measured on masks rendered from the real outlines (``mapdb
simulate --render masks``, Andorra and Monaco, 120 m, 60 degrees, 640x480, buildings with heights, 160
images, blobs against their true map objects at the true pose, pixels; blobs touching one border):
buildings (699) lie outward by percentiles 5/25/50/75/95 = -26 / -1 / 20 / 44 / 129 px along the normal and
within a median 8 px (75 %: 20 px) along the border; other labels (170) 0 / 9 / 25 / 78 / 322 px and 5 px.
The median distance is 30 px either way, but most of it lies along the normal.

So each cut blob's residual is measured in an ellipse: centred ``CUT_SHIFT_PX`` outward along the normal
and stretched by ``CUT_STRETCH`` along it (``along**2 / k + across**2 * k``); whole blobs keep a disc
(``RELIEF_STRETCH`` = 1: their relief is radial but the quad's own prediction error, isotropic, is as large
at 120 m, and a radial stretch of 2 or 4 changed nothing measurable).  On the same blobs the median
equivalent radius fell from 30 to 22 px (buildings) and 36 to 18 px (others).

**Calibration.**  The ellipse has the area of the disc it replaces (``k * 1/k = 1``), so under the null of
:mod:`mapdb.match.nfa` (map objects a Poisson process independent of the image) the chance that a map
object lies within ``u = lambda pi r_eff^2`` is ``1 - exp(-u)`` for an ellipse with a fixed centre and
shape, as for a disc.  The map object measured is the Euclidean nearest to the ellipse's centre (the index
answers nearest queries): its ``u`` is ``u_disc * g(theta)``, ``E[1 / g] = 1`` over a uniform direction,
so for small ``u`` the chance is ``u`` again and for larger ``u`` at most ``1 - exp(-u)`` (Jensen): never
more evidence than chance gives (``tests/test_blob_errors.py`` checks it on random maps).  The ellipse's
centre and shape come from the blob's box alone, fixed before the map is looked at.

**Measured** (120 m, 60 degrees, 640x480, Andorra and Monaco, 80 images each, seeds 0 and 1; localized, with
cut rounds of :mod:`mapdb.match.cut_quads` too): with heights 40.0 -> 49.4 % (seed 0) and 39.4 -> 46.9 %
(seed 1, one answer 2.2 m off: the right place, its whole-blob relief fit off); flat 63.1 -> 67.5 %; 200 m
with heights 73.8 -> 75.6 %.  Wrong places: each extract's images
against the other's map (160 a row, 120 m with and without heights, 200 m): none accepted, best wrong
score 0.99 / 2.19 / 1.59 (1.76 / 1.24 / 1.59 before); the same images mirrored (no place matches a
mirror image) against their own map: none accepted, best 2.37 / 1.90 / 3.30 (1.42 / 3.60 / 2.59 before).
A later run with more images shows that mirrored images of regular blocks can be accepted: Monaco 200 m,
``sim-000045`` of seed 0, 43 m away, score 4.63 with heights (80 and 100 images a row, seeds 0 and 1).

**Cut buildings placed by their map objects' areas.**  A fixed shift cannot follow how much of a blob is
hidden, but once a hypothesis names a candidate map object, its stored area does: at the hypothesis's scale the
hidden part is ``A / |a|^2 - visible_px`` pixels, and the map object lies about ``AREA_SHIFT = 0.5`` times its
square root outward of the visible centroid (the hidden part's extent, halved, for a roughly square building).
On 323 cut buildings with one map object under them (80 images, 120 m with heights; residual along the normal /
equivalent radius, medians): the fixed 15 px ellipse 20 / 25 px, this shift in a disc 8 / 16 px (coefficient
0.3: 11 / 19; 0.7: 15 / 22; the hidden area over the box's width along the border: 7 / 16; other labels, often
drawn only in part, 64 -> 46 px at the median but hundreds beyond it: they keep the ellipse).
:func:`cut_area_residuals` measures each candidate from its own place: the regions all have the disc's area,
and under the null areas are independent of places, so the count of map objects within ``r`` of their own
places is Poisson of mean ``lambda pi r^2`` as for one disc (``tests/test_cut_area_shift.py``).

It was first taken out (commit 2bb6874): it accepted 3 Andorra images at 300 m with heights 2, 3 and 4 m off,
right places whose final fit rests on 3-5 whole blobs with model sigmas of 0.47-1.0 m.  The final fit's sigma
now includes the jackknife's (:func:`mapdb.match.refine.polish`): the two of them the same renders still give
(4.1 and 2.1 m off, model sigmas 0.85 and 0.47 m) get 1.86 and 1.32 m and are withheld, and the feature is back.
Measured (``python benchmarks/rendered_masks.py --n 80 --baseline d819766``, Andorra and Monaco, 160 images a
row; localized and answers more than 2 m off, before -> after, seed 0 then ``--seed 1``): 120 m with heights
49.4 -> 55.0 % (0 -> 0) and 46.9 -> 50.6 % (1 -> 0); flat 68.1 -> 71.2 % (1 -> 0) and 66.2 -> 66.9 %; 200 m
with heights 75.6 -> 77.5 % (1 -> 0) and 72.5 -> 71.9 % (3 -> 2); flat 86.9 -> 87.5 % (1 -> 0) and 84.4 %
both; 300 m with heights 80.0 -> 79.4 % (0 -> 0) and 75.0 -> 73.8 % (2 -> 1); flat unchanged.  Wrong places
(``/tmp`` script, 100 images per extract and row, 120 and 200 m, seeds 0 and 1): each extract against the
other's map, none accepted (best wrong score 2.59); mirrored images against their own map (no camera sees a
mirror image, but a regular block's mirror can match nearby): Monaco 120 m flat ``sim-000022`` of seed 0 is now
accepted 50 m away (score 5.09; rejected before, 3.30), beside the 43 m one that both accept (200 m,
``sim-000045``); seed 1's Monaco 200 m flat ``sim-000083`` is accepted 2 m from the truth (a symmetric block).

**The final fit** (:func:`mapdb.match.refine.polish`) places cut blobs the same way (:func:`placed_sources`)
when it must fit them (fewer than four whole blobs matched); it had taken them at their visible centroids.
Measured (``python benchmarks/rendered_masks.py --n 80 --baseline 2731d67``, seeds 0 and 1): 120 m with heights
55.0 -> 56.2 % and 50.6 -> 51.2 %, flat 71.2 -> 71.9 % and 66.9 -> 69.4 %, the other rows within one image; no
new answer more than 2 m off, and the wrong-place runs accepted the same images.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .areas import compatible

if TYPE_CHECKING:
    from ..mapobjects.object_index import ObjectIndex

__all__ = [
    "AREA_SHIFT", "CUT_SHIFT_PX", "CUT_STRETCH", "RELIEF_STRETCH", "BlobErrors", "cut_area_residuals",
    "outward_normals", "placed_sources",
]

# The cut blob's ellipse: its centre this many pixels outward along the border's normal (below the median
# 20-25 px: a shift too far costs the slightly cut blobs more than it gains on the deeply cut), its axis
# ratio CUT_STRETCH**2 (tried 1, 2, 3, 5 with shifts 0-30 px: 3 and 15-20 px localized most).
CUT_SHIFT_PX = 15.0
CUT_STRETCH = 3.0
RELIEF_STRETCH = 1.0
# A cut solid blob's map object of area A (pixels at the hypothesis's scale) lies AREA_SHIFT * sqrt(A - visible)
# outward of the visible centroid (the hidden part's extent, halved), in a disc.
AREA_SHIFT = 0.5
# Candidates per cut blob (nearest its ellipse's centre) and how far from it (pixels) they are looked for.
AREA_CANDIDATES = 24
AREA_GATE_PX = 250.0


def outward_normals(bbox: np.ndarray, width: float, height: float) -> np.ndarray:
    """Unit outward normal (complex, image frame with y up) of the border each box touches, 0 where none.

    A box touching two borders (a corner) gets the diagonal between their normals.

    Examples
    --------
    >>> n = outward_normals(np.array([[0, 10, 30, 40], [600, 0, 640, 20], [50, 50, 60, 60]]), 640, 480)
    >>> np.round(n, 3).tolist()
    [(-1+0j), (0.707+0.707j), 0j]
    """
    box = np.asarray(bbox, np.float64).reshape(-1, 4)
    out = ((box[:, 0] <= 0) * -1.0 + (box[:, 2] >= width) * 1.0
           + 1j * ((box[:, 1] <= 0) * 1.0 - (box[:, 3] >= height) * 1.0))
    size = np.abs(out)
    return np.where(size > 0, out / np.where(size > 0, size, 1.0), 0j)


@dataclass(frozen=True)
class BlobErrors:
    """Per image object: ``direction`` (complex unit, image frame y up; the axis of its error ellipse),
    ``shift_px`` (expected displacement of its map object along it) and ``stretch`` (the ellipse's axis
    ratio is ``stretch**2``, wide along ``direction``; 1: a disc)."""

    direction: np.ndarray
    shift_px: np.ndarray
    stretch: np.ndarray
    visible_px: np.ndarray | None = None

    @classmethod
    def of(cls, z: np.ndarray, outward: np.ndarray | None, solid_px: np.ndarray | None = None) -> BlobErrors | None:
        """Cut blobs (``outward`` non-zero) along their border's normal, whole ones radially; None when
        nothing is known of the image's borders.  ``solid_px``: each object's pixel area where its label is
        solid (:data:`mapdb.match.evidence.areas.SOLID_LABELS`), NaN elsewhere; the cut ones become ``visible_px``,
        which :func:`cut_area_residuals` places by their map objects' areas."""
        if outward is None:
            return None
        outward = np.asarray(outward, np.complex128)
        cut = outward != 0
        radial = np.where(np.abs(z) > 0, z / np.where(np.abs(z) > 0, np.abs(z), 1.0), 1.0)
        visible = None
        if solid_px is not None:
            visible = np.where(cut, np.asarray(solid_px, np.float64), np.nan)
            with np.errstate(invalid="ignore"):
                visible = visible if (visible > 0).any() else None
        return cls(np.where(cut, outward, radial), np.where(cut, CUT_SHIFT_PX, 0.0),
                   np.where(cut, CUT_STRETCH, RELIEF_STRETCH), visible)

    def expected(self, a: np.ndarray, b: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Where each object's map object is expected under each similarity ``z -> a z + b``: its ellipse's
        centre, ``(H, n)`` complex map metres."""
        return a[:, None] * (z + self.shift_px * self.direction)[None, :] + b[:, None]

    def r2(self, a: np.ndarray, b: np.ndarray, z: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Squared distances (map metres) from each object's expected map position to ``target`` ((H, n)
        complex), measured in its ellipse: ``along**2 / stretch + across**2 * stretch`` (area-preserving)."""
        rot = a / np.abs(a)
        d = (target - self.expected(a, b, z)) * np.conj(rot[:, None] * self.direction[None, :])
        k = self.stretch[None, :]
        return d.real**2 / k + d.imag**2 * k


def cut_area_residuals(errors: BlobErrors, a: np.ndarray, b: np.ndarray, z: np.ndarray, cols: np.ndarray,
                       index: ObjectIndex, img_label: np.ndarray, exclude: np.ndarray, lo: np.ndarray,
                       hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared residuals (map metres) and map ids ``(H, m)`` of the cut solid blobs ``cols``, each placed by
    its candidate map object's area: ``AREA_SHIFT * sqrt(A / |a|^2 - visible_px)`` outward, a disc.

    Each map object near the blob's ellipse centre (``AREA_CANDIDATES`` within ``AREA_GATE_PX``) is measured
    from where a blob of its own area would put it; the blob's residual is the smallest, among those not at
    the hypothesis's own map points (``exclude``, ``(H, s)``) and within the blob's area band (``lo``,
    ``hi``, ``(H, n)``).  The regions all have the area of a disc of radius ``r``, and under the null the
    map objects' areas are independent of their places, so the count within ``r`` is still Poisson of mean
    ``lambda pi r^2``: the residual keeps the calibration of a nearest-object distance.  A candidate missed
    by the search only makes the residual larger.  No candidate: ``inf`` and -1.
    """
    h, m = a.size, cols.size
    visible = errors.visible_px if errors.visible_px is not None else np.full(z.size, np.nan)
    centre = errors.expected(a, b, z)[:, cols].ravel()
    labels = np.broadcast_to(img_label[cols], (h, m)).ravel()
    rows, ids, _ = index.within(centre, labels, AREA_GATE_PX * float(np.abs(a).max()), AREA_CANDIDATES)
    r2 = np.full(h * m, np.inf)
    mid = np.full(h * m, -1, np.int64)
    if rows.size:
        hyp, col = rows // m, cols[rows % m]
        at = a[hyp] * _placed(errors, visible, z, col, index.log_area[ids], np.abs(a[hyp])) + b[hyp]
        d2 = np.abs(index.z[ids] - at) ** 2
        own = (np.abs(index.z[ids][:, None] - exclude[hyp]) < 1e-6).any(axis=1)
        ok = compatible(index.log_area[ids], lo[hyp, col], hi[hyp, col]) & ~own
        order = np.lexsort((np.where(ok, d2, np.inf), rows))
        first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]]
        first = first[ok[first]]
        r2[rows[first]], mid[rows[first]] = d2[first], ids[first]
    return r2.reshape(h, m), mid.reshape(h, m)


def _placed(errors: BlobErrors, visible: np.ndarray, z: np.ndarray, col: np.ndarray, log_area: np.ndarray,
            scale: np.ndarray | float) -> np.ndarray:
    """Image positions (pixels) where the blobs ``col`` put map objects of stored ``log_area`` at ``scale``
    metres per pixel: a cut solid blob ``AREA_SHIFT * sqrt(A / scale^2 - visible_px)`` outward, any other cut
    blob ``shift_px`` outward, a whole blob at its centroid."""
    with np.errstate(invalid="ignore", over="ignore"):
        hidden = np.maximum(np.exp(log_area) / np.square(scale) - visible[col], 0.0)
    shift = np.where(np.isfinite(hidden), AREA_SHIFT * np.sqrt(hidden), errors.shift_px[col])
    return z[col] + shift * errors.direction[col]


def placed_sources(errors: BlobErrors, z: np.ndarray, pairs: np.ndarray, index: ObjectIndex,
                   scale: float) -> np.ndarray:
    """Image positions (pixels, complex) where each pair's (image object, ``index`` map object) map object lies
    by its blob: a whole blob's centroid; a cut blob's moved outward along its border's normal, by the map
    object's stored area at ``scale`` metres per pixel for a solid label, else by ``shift_px``.  What the final
    fit uses when it must fit cut blobs.

    Examples
    --------
    >>> from mapdb.match.mapobjects.object_index import ObjectIndex
    >>> from mapdb.objects import Objects
    >>> index = ObjectIndex(Objects.from_names([0.0, 25.0], [0.0, 0.0], ["building"] * 2, area=[50.0, 49.0]))
    >>> errors = BlobErrors.of(np.array([0j, 100 + 0j]), np.array([0j, 1 + 0j]), np.array([np.nan, 300.0]))
    >>> placed_sources(errors, np.array([0j, 100 + 0j]), np.array([[0, 0], [1, 1]]), index, 0.25)
    array([  0.+0.j, 111.+0.j])
    """
    ids = pairs[:, 1]
    if errors.visible_px is None:  # no cut blob of a solid label: the stored areas (made on first use) not needed
        return _placed(errors, np.full(z.size, np.nan), z, pairs[:, 0], np.full(ids.size, np.nan), scale)
    return _placed(errors, errors.visible_px, z, pairs[:, 0], index.log_area[ids], scale)
