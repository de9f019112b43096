"""Fixes from several frames: the objects of the last frames carried into the current one and matched as one image.

A frame at 120 m over rendered masks often holds too little evidence for the map matcher alone (a third of
the images have three or fewer whole blobs).  The frames before it saw more of the ground, and the
navigator already knows how each frame maps onto the one before: the frame-to-frame similarity
``z_prev = a z_cur + b`` of :func:`mapdb.navigation.velocity.match_frames` (levelled image planes, pixels
from the nadir, y up).  When the current frame alone is not decisive (its query gave no fix, or a fix the
filter rejected), :class:`History` builds a **stitched image**:

* **Which frames.**  The current frame and up to ``K`` frames before it (``NavigatorOptions.stitch_frames``),
  each linked to the next by a similarity (an unbroken chain: a frame without one starts the history
  again), none more than ``MAX_AGE_S`` seconds older than the current frame.
* **Carried.**  Each earlier frame's objects are composed through the chain into the current frame's
  levelled plane: with ``z_i = a_i z_{i+1} + b_i`` per link, ``z_cur = A z_i + B`` with ``A = 1 / prod a``.
* **Uncertainty.**  Each link's translation is known to ``sigma_b`` pixels per axis (``FrameMotion.sigma_px``);
  a similarity fitted on objects spread over the frame has rotation and scale errors of about
  ``sigma_b / R`` (``R`` the half diagonal), which move a point ``|z|`` from the nadir by ``sigma_b |z| / R``
  more.  A carried object's per-axis error is thus ``sqrt(sum sigma_b**2) (1 + |z| / R)``; objects whose
  error exceeds ``MAX_CARRIED_SIGMA_PX`` (4 px: the widest pixel error the matcher's lookups assume,
  ``FastOptions.pixel_sigmas``) are left out.  Over rendered masks at 120 m the links' ``sigma_b`` is
  0.3-5 px (median about 1 px: blobs change with relief and cuts from frame to frame), so this keeps the
  last 2-10 frames' objects near the current nadir and fewer far from it.  A limit of 2 px (the floor the
  navigator puts under a blob's own centroid) kept one or two links and stitched 2 fixes on 151 frames of the
  Monaco flight below; 4 px stitched 13.
* **One object per ground object.**  Objects are taken newest frame first; one of the same label within
  ``GATE_PX`` of an object already taken (3 times the carried object's error when wider; when either is cut
  by the border, within the larger blob's equivalent radius ``sqrt(area / pi)``) is the same ground object:
  two views of one object left in would count as two matches of one map object, evidence the null does not
  allow.  A whole blob replaces a cut one (an
  object cut by the border in one frame but whole in another is whole, at its whole centroid); of two
  whole ones the newest is kept (the least carried).
* **The virtual image.**  The merged objects are the pixels of a larger level image centred on the
  current nadir: its width and height grow to hold them, its field of view grows with them at the current
  focal length (so the scale the matcher expects is unchanged), its attitude is level (the points are
  levelled already, so the localizer, like for any levelled image, leaves pixel areas and boxes out).
  The answer's position is the current nadir's, like the single frame's.

**The number of tests.**  The matcher's a-contrario decision counts the stitched objects as the image's
(``n`` is the stitched image's), and every hypothesis it tries on them.  The stitched query is one more
test of the same frame: a frame is now tested twice, so the stitched answer is accepted only when its
number of false alarms is below ``epsilon / STITCH_TESTS`` (its score at least ``-log10 epsilon +
log10 STITCH_TESTS``, Bonferroni over the frame's two tests): the frame's expected number of false alarms
stays within the single query's ``epsilon`` plus half of it.  Only one stitched image is tried a frame (not
one per ``K``), so the factor does not grow with ``K``.  Consecutive stitched images share objects, but an
expectation adds whatever the dependence.  After a first fix the stitched query carries the frame's pose prior
like the frame's own (the stitched plane is the current frame's levelled plane at its focal length, so the
heading and scale are the frame's: :mod:`mapdb.match.pose_prior`); its pose-prior stage's hypotheses are among
the stitched query's tests.

**K, measured** (rendered-mask flights of ``benchmarks/navigation_masks.py``, 120 m with heights, 3 km, 751
frames, from lost-in-space; K = 0 is the navigator without stitching, the same as ``main``'s; ``python
benchmarks/navigation_masks.py --maps monaco,andorra --cases heights --altitudes 120 --starts lis,initial
--stitch 0,3,5 --baseline main``):

| flight | K | frames fixed | within 2 m | largest error | wrong fixes | stitched fixes | ms median |
|---|---|---|---|---|---|---|---|
| Monaco | 0 (main) | 48.5 % | 90.9 % | 4.5 m | 0 | 0 | 43 |
| Monaco | 3 | 55.4 % | 89.0 % | 5.0 m | 0 | 53 | 52 |
| Monaco | 5 | 55.8 % | 92.6 % | 4.8 m | 0 | 56 | 52 |
| Andorra | 0 (main) | 23.6 % | 68.8 % | 15.0 m | 0 | 0 | 36 |
| Andorra | 3 | 27.8 % | 69.8 % | 14.1 m | 0 | 32 | 45 |
| Andorra | 5 | 28.1 % | 71.0 % | 13.3 m | 0 | 34 | 45 |

``DEFAULT_FRAMES`` is 5: more frames fixed and more within 2 m than with 3 on both towns (from ``--initial``
alike: Monaco 91.6 %, Andorra 71.1 % within 2 m).  More frames add little: at 20 m/s and 5 fps the chain's
errors leave out most objects older than about a second (``MAX_CARRIED_SIGMA_PX``), and on a 600 m Monaco
flight 10 and 15 fixed what 5 fixed.  The stitched fixes are as accurate as the single frames' (Monaco,
K = 5: 56 stitched fixes, median error 0.38 m, largest 1.31 m; 339 single-frame fixes, 0.38 m and 2.46 m).
What stitching cannot mend is the drift between fixes where the frames before were sparse too (Andorra).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..camera import Camera
from ..detections.images import ImageObjects
from .velocity import FrameMotion, FramePoints

__all__ = ["DEFAULT_FRAMES", "GATE_PX", "MAX_AGE_S", "MAX_CARRIED_SIGMA_PX", "STITCH_TESTS", "History", "Seen",
           "Stitched", "min_stitched_score"]

# Earlier frames stitched to the current one (module docs: chosen by measurement).
DEFAULT_FRAMES = 5
# No frame older than this is stitched: the chain's errors grow with it, and the aircraft may have turned.
MAX_AGE_S = 3.0
# Carried objects less certain than this (pixels per axis) are left out: the matcher's widest lookup (module docs).
MAX_CARRIED_SIGMA_PX = 4.0
# Two whole blobs of one label this close (pixels) in the current plane are one ground object (1.3 m at 120 m:
# distinct buildings' centroids are farther apart); a carried object's gate widens to 3 times its error.
GATE_PX = 6.0
# The frame's tests: its own query and the stitched one (module docs, the number of tests).
STITCH_TESTS = 2


def min_stitched_score(log10_epsilon: float) -> float:
    """The least score a stitched answer needs: the matcher's threshold with the Bonferroni factor (module docs).

    Examples
    --------
    >>> round(min_stitched_score(-4.0), 3)
    4.301
    """
    return -log10_epsilon + math.log10(STITCH_TESTS)


@dataclass(frozen=True)
class Seen:
    """One frame's objects kept for stitching.

    ``link`` is the similarity to the frame before it (``z_prev = a z_this + b``), None when there is none:
    the chain is broken there.
    """

    time_s: float
    points: FramePoints
    names: np.ndarray
    area_px: np.ndarray | None
    link: FrameMotion | None


@dataclass(frozen=True)
class Stitched:
    """A stitched image and where its objects came from."""

    image: ImageObjects
    frames: list[float]  # the times of the frames that gave at least one object, oldest first
    carried: int  # objects from earlier frames (after merging)
    merged: int  # objects left out as another frame's view of an object already taken


@dataclass
class _Merged:
    """The stitched objects, built newest frame first."""

    z: list[complex] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    border: list[bool] = field(default_factory=list)
    area: list[float] = field(default_factory=list)
    frame: list[float] = field(default_factory=list)  # the time of the frame each object comes from
    merged: int = 0

    def add(self, z: complex, name: str, border: bool, area: float, frame: float, sigma: float) -> None:
        """Take one object (carried with ``sigma`` pixels per axis), or merge it with the same ground object
        taken already (module docs)."""
        for k, (zk, nk) in enumerate(zip(self.z, self.names, strict=True)):
            if nk != name:
                continue
            gate = max(GATE_PX, 3.0 * sigma)
            if border or self.border[k]:
                gate = max(gate, math.sqrt(max(area, self.area[k], 0.0) / math.pi))
            if abs(z - zk) > gate:
                continue
            self.merged += 1
            if self.border[k] and (not border or area > self.area[k]):  # whole beats cut; a larger cut, a smaller
                self.z[k], self.border[k], self.area[k], self.frame[k] = z, border, area, frame
            return
        self.z.append(z)
        self.names.append(name)
        self.border.append(border)
        self.area.append(area)
        self.frame.append(frame)


class History:
    """The recent frames linked by their similarities (module docs).

    Parameters
    ----------
    frames : int
        ``K``: earlier frames stitched to the current one (0: no stitching).
    max_age_s : float
        No frame older than this (seconds before the current one) is stitched.
    """

    def __init__(self, frames: int = DEFAULT_FRAMES, max_age_s: float = MAX_AGE_S) -> None:
        self.frames = frames
        self.max_age_s = max_age_s
        self.seen: list[Seen] = []

    def add(self, seen: Seen) -> None:
        """Keep the current frame; a frame without a link to the previous one starts the history again."""
        if seen.link is None or not self.seen:
            self.seen = [seen]
        else:
            self.seen.append(seen)
        self.seen = [s for s in self.seen[-(self.frames + 1):] if seen.time_s - s.time_s <= self.max_age_s]
        # A frame's link leads to the frame before it: the oldest kept needs none, the others must chain.
        while len(self.seen) > 1 and any(s.link is None for s in self.seen[1:]):
            self.seen.pop(0)

    def clear(self) -> None:
        """Forget every frame (the flight restarted)."""
        self.seen = []

    def copy(self) -> History:
        """A copy whose list of frames is its own (a navigator's snapshot)."""
        other = History(self.frames, self.max_age_s)
        other.seen = list(self.seen)
        return other

    def stitched(self, image: ImageObjects, altitude_m: float | None) -> Stitched | None:
        """The current frame (the last one added, read as ``image``) with the earlier frames' objects carried
        into it, as one level image (module docs); None when no earlier frame adds an object."""
        if len(self.seen) < 2 or self.frames <= 0 or image.fov_deg is None:
            return None
        current = self.seen[-1]
        radius = current.points.diag_px / 2.0
        merged = _Merged()
        gain, var = 1 + 0j, 0.0  # z_cur = gain z_i + shift; var: the chain's summed sigma_b**2
        shift = 0j
        for k in range(len(self.seen) - 1, -1, -1):
            s = self.seen[k]
            z = gain * s.points.z + shift
            sigma = math.sqrt(var) * (1.0 + np.abs(z) / radius)
            border = s.points.border if s.points.border is not None else np.zeros(z.size, bool)
            area = s.area_px if s.area_px is not None else np.zeros(z.size)
            for j in np.flatnonzero(sigma <= MAX_CARRIED_SIGMA_PX):
                merged.add(complex(z[j]), str(s.names[j]), bool(border[j]),
                           float(area[j]) if math.isfinite(area[j]) else 0.0, s.time_s, float(sigma[j]))
            if k == 0 or s.link is None:
                break
            a, b = s.link.a, s.link.b  # z_{k-1} = a z_k + b, so z_k = (z_{k-1} - b) / a
            shift, gain = shift - gain * b / a, gain / a
            var += (abs(gain) * s.link.sigma_px) ** 2
        carried = sum(1 for f in merged.frame if f != current.time_s)
        if carried == 0:
            return None
        return Stitched(_virtual_image(merged, image, altitude_m), sorted(set(merged.frame)), carried, merged.merged)


def _virtual_image(merged: _Merged, image: ImageObjects, altitude_m: float | None) -> ImageObjects:
    """The merged objects as a level image centred on the current nadir, grown to hold them (module docs)."""
    assert image.fov_deg is not None
    z = np.array(merged.z, np.complex128)
    focal = Camera(image.width, image.height, image.fov_deg).focal_px
    half_w = max(image.width / 2.0, float(np.max(np.abs(z.real))) + 1.0)
    half_h = max(image.height / 2.0, float(np.max(np.abs(z.imag))) + 1.0)
    fov = math.degrees(2.0 * math.atan(half_w / focal))  # the same focal length over the wider image
    area = np.array(merged.area)
    kwargs: dict[str, Any] = {"area_px": area if image.area_px is not None else None,
                              "border": np.array(merged.border, bool) if image.border is not None else None}
    return ImageObjects(id=image.id, width=2.0 * half_w, height=2.0 * half_h, x=z.real + half_w,
                        y=half_h - z.imag, names=np.array(merged.names, dtype=object), roll_deg=0.0,
                        pitch_deg=0.0, fov_deg=fov, altitude_m=altitude_m if altitude_m is not None
                        else image.altitude_m, **kwargs)
