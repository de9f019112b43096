"""Velocity from frame to frame: the same objects matched image to image, with no map.

Two consecutive frames see mostly the same ground objects.  Each frame's objects are first levelled with
the attitude the autopilot gives (:func:`mapdb.camera.level_pixels`, so that the image is a similarity of
the ground and its centre is the nadir), then the previous frame plays the part of the map: the current
frame is matched against it by the matcher's own pieces, giving the similarity

    z_prev = a * z_cur + b        (levelled image planes, pixels from the centre, y up)

``b`` is where the current nadir lies in the previous image, ``arg(a)`` the rotation and ``|a|`` the change
of scale between the two frames.

* With a guess of the motion (the filter's velocity, the autopilot's turn) the guess is refined as the
  matcher refines its own hypotheses (:func:`mapdb.match.verify.refine`: nearest object of the same label,
  least-squares similarity, the a contrario test) and finished by its optimal one-to-one assignment
  (:func:`mapdb.match.refine.polish`);
* without one, or when the guess finds nothing certain, the translations most pairs of same-label objects
  vote for (frames a tenth of a second apart barely rotate or change scale) are refined the same way;
* failing that, the current frame is matched against the previous one by the full quad matcher
  (:func:`mapdb.match.fast.match_fast`), the previous frame as the map.

Blobs cut by the image border move at about half the ground speed (the cut moves with the image): they are
left out when both frames keep ``MIN_WHOLE_OBJECTS`` whole ones; otherwise the match uses them, and its
translation is refitted on the objects whole in both frames (at least ``MIN_WHOLE_PAIRS``); with none
whole in both, the frames give no velocity (``_whole_refit``).

A frame's levelled image maps to the ground by ``w = A z + B`` with ``A = s exp(-i heading)`` (``s`` metres
per pixel); the nadir moved by ``A_prev b`` metres, so the velocity is ``A_prev b / dt``
(:func:`velocity_from_motion`).  Its uncertainty adds, per axis: the fitted ``b``'s error, the attitude
errors of both frames (each moves the levelled nadir by ``altitude tan(error)``), and along and across the
motion the relative error of the scale and the error of the heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera, image_plane, level_pixels
from ..detections.images import ImageObjects
from ..match.fast import FastOptions, match_fast
from ..match.quads import QuadIndex
from ..match.refine import candidates, polish
from ..match.verify import ObjectIndex, refine
from ..objects import Objects

__all__ = ["FrameMotion", "FramePoints", "MIN_WHOLE_OBJECTS", "Velocity", "frame_points", "match_frames",
           "velocity_from_motion", "whole_objects"]

# A refined guess is accepted below this log10 number of false alarms with at least MIN_INLIERS objects.
# Looser than the map matcher's -4: a guess is one hypothesis, not a search of the map, the images share
# only the objects both saw (a fifth missed in each), and the filter's velocity gate stands behind it.
LOG10_EPSILON = -2.0
MIN_INLIERS = 4
# The scale between consecutive frames changes by less than this factor (a climb of a few metres).
SCALE_RANGE = (0.8, 1.25)
# Without a guess, the current nadir is looked for within this fraction of the image diagonal.
SEARCH_FRACTION = 0.5
# The similarity's error is never taken below this (pixels, per axis): a fit of few objects can look
# better than the pixels allow.
MIN_SIGMA_PX = 0.2
# Refinement iterations of a guess (the matcher uses two).
_ITERATIONS = 2
# Translation votes agreeing within this many pixels support one another; the best few peaks are refined.
VOTE_RADIUS_PX = 6.0
_PEAKS = 3
# Border-touching objects are left out when each frame keeps at least this many whole ones: a fifth of the
# objects are missed in each frame, so 8 whole objects leave about 8 x 0.8 x 0.8 = 5 seen in both frames,
# above MIN_INLIERS.
MIN_WHOLE_OBJECTS = 8
# Matched with the cut objects too, the motion is refitted on the pairs whole in both frames that it puts
# within PAIR_RADIUS_PX (plus half the displacement) of each other, at least MIN_WHOLE_PAIRS (``_whole_refit``).
PAIR_RADIUS_PX = 6.0
MIN_WHOLE_PAIRS = 1
# A whole blob's centroid moves with the ground within about a pixel (relief and merging change its shape).
PAIR_SIGMA_PX = 1.0


@dataclass(frozen=True)
class FramePoints:
    """One frame's objects as the matcher sees them: levelled (complex pixels from the centre, y up)."""

    z: np.ndarray
    codes: np.ndarray  # label codes in the navigator's label table
    width: float
    height: float
    border: np.ndarray | None = None  # True where the object's blob touches the image border

    @property
    def diag_px(self) -> float:
        return math.hypot(self.width, self.height)


@dataclass(frozen=True)
class FrameMotion:
    """``z_prev = a z_cur + b`` between two levelled frames, and its quality."""

    a: complex
    b: complex
    sigma_px: float  # per-axis 1-sigma error of b
    inliers: int
    score: float  # -log10 of the number of false alarms
    guided: bool  # refined from a guess (True) or found by the quad matcher (False)


@dataclass(frozen=True)
class Velocity:
    """A velocity (complex m/s, east + i north) and its 2x2 covariance (east, north)."""

    v: complex
    cov: np.ndarray
    displacement_m: complex


def frame_points(im: ImageObjects, codes: np.ndarray, roll_deg: float | None, pitch_deg: float | None
                 ) -> FramePoints | None:
    """The frame's objects levelled with ``roll_deg``/``pitch_deg`` (ignored without a field of view).

    None when levelling puts an object at or above the horizon.
    """
    u, v = im.x, im.y
    if im.fov_deg is not None and (roll_deg or pitch_deg):
        u, v = level_pixels(u, v, Camera(im.width, im.height, im.fov_deg), roll_deg or 0.0, pitch_deg or 0.0)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
            return None
    border = None if im.border is None else np.asarray(im.border, bool)
    return FramePoints(image_plane(u, v, im.width, im.height), np.asarray(codes, np.int64), im.width, im.height,
                       border)


def whole_objects(prev: FramePoints, cur: FramePoints) -> tuple[FramePoints, FramePoints]:
    """Both frames without their border-touching objects, when each keeps ``MIN_WHOLE_OBJECTS`` (module docs).

    Otherwise both frames as they are: the decision is taken for the pair, so that one object is never
    whole in one frame's fit and left out of the other's for a reason that differs between them.
    """
    keep = [~p.border if p.border is not None else np.ones(p.z.size, bool) for p in (prev, cur)]
    if all(k.all() for k in keep) or min(int(k.sum()) for k in keep) < MIN_WHOLE_OBJECTS:
        return prev, cur
    prev_w, cur_w = (FramePoints(p.z[k], p.codes[k], p.width, p.height, np.zeros(int(k.sum()), bool))
                     for p, k in zip((prev, cur), keep, strict=True))
    return prev_w, cur_w


def _as_map(frame: FramePoints, n_labels: int) -> tuple[Objects, ObjectIndex]:
    """The previous frame as the matcher's map: its objects and their verification index."""
    labels = tuple(str(i) for i in range(max(n_labels, int(frame.codes.max(initial=-1)) + 1, 1)))
    objects = Objects(frame.z.real, frame.z.imag, frame.codes, np.zeros(frame.z.size), labels)
    w, h = frame.width / 2.0, frame.height / 2.0
    return objects, ObjectIndex(objects, bounds=(-w, -h, w, h))


def match_frames(prev: FramePoints, cur: FramePoints, a_guess: complex = 1 + 0j, b_guess: complex | None = None,
                 n_labels: int = 0) -> FrameMotion | str:
    """The similarity taking the current frame's objects onto the previous frame's (module docs).

    Tried in turn until one is certain: the guess ``(a_guess, b_guess)`` refined; the translations that
    most same-label pairs of objects agree on (with ``a_guess``'s rotation and scale), refined; the quad
    matcher.

    Parameters
    ----------
    prev, cur : FramePoints
    a_guess : complex
        The expected rotation and scale change (from the autopilot's turn and altitudes; 1 if unknown).
    b_guess : complex, optional
        Where the current nadir is expected in the previous image (from the filter's velocity).
    n_labels : int
        Size of the label table the codes index (codes beyond it are counted too).

    Returns
    -------
    FrameMotion, or a str saying why there is none.
    """
    found = _match(*whole_objects(prev, cur), a_guess, b_guess, n_labels)  # cut blobs move at about half speed
    return found if isinstance(found, str) else _whole_refit(found, prev, cur)


def _match(prev: FramePoints, cur: FramePoints, a_guess: complex, b_guess: complex | None, n_labels: int
           ) -> FrameMotion | str:
    """:func:`match_frames` on the frames given."""
    if prev.z.size < 3 or cur.z.size < 3:
        return f"too few objects to match frames ({prev.z.size} and {cur.z.size}; at least 3 each)"
    objects, index = _as_map(prev, n_labels)
    guesses = ([b_guess] if b_guess is not None else []) + _translation_votes(prev, cur, a_guess)
    for b in guesses:
        found = _refine_guess((a_guess, b), cur, index)
        if found is not None:
            return found
    if prev.z.size < 4 or cur.z.size < 4:
        return "no certain match between frames (too few objects for the quad matcher)"
    options = FastOptions(max_sigma_m=None)
    centre = b_guess if b_guess is not None else 0j
    prior = (centre.real, centre.imag, SEARCH_FRACTION * cur.diag_px)
    result = match_fast(cur.z, cur.codes, index, [QuadIndex(objects, options.map_neighbours)], cur.diag_px,
                        options=options, prior=prior, scale_range=SCALE_RANGE)
    if result.best is None:
        return f"no match between frames: {result.reason}"
    best = result.best
    return FrameMotion(best.a, best.b, max(best.sigma_m, MIN_SIGMA_PX), best.inliers, best.score, False)


def _whole_refit(motion: FrameMotion, prev: FramePoints, cur: FramePoints) -> FrameMotion | str:
    """The translation refitted on the pairs of objects whole in both frames (module docs).

    When too few objects were whole to match on them alone, the match used the cut ones too, whose
    centroids move at about half the ground speed.  Pairs of objects the motion puts within
    ``PAIR_RADIUS_PX`` plus half the displacement of each other, of one label and whole in both frames,
    give the similarity (three or more pairs) or ``b`` with ``a`` kept (its error at least
    ``PAIR_SIGMA_PX`` over the square root of the pairs); with none, there is no
    velocity: the cut objects alone would read it slow by up to a half (measured: 7 m/s at 20 m/s).
    """
    if prev.border is None or cur.border is None or not (prev.border.any() or cur.border.any()):
        return motion
    d = np.abs(prev.z[None, :] - (motion.a * cur.z + motion.b)[:, None])
    d[cur.codes[:, None] != prev.codes[None, :]] = np.inf
    d[cur.border, :] = np.inf
    d[:, prev.border] = np.inf
    k = np.arange(cur.z.size)
    j = np.argmin(d, axis=1) if prev.z.size else np.zeros(cur.z.size, np.int64)
    # The match may be off by the cut objects' bias, up to half the displacement: the pairs are looked for that far.
    near = d[k, j] <= PAIR_RADIUS_PX + 0.5 * abs(motion.b) if prev.z.size else np.zeros(cur.z.size, bool)
    # One previous object for one current object: the nearest current one keeps it.
    for jj in np.unique(j[near]):
        mine = np.flatnonzero(near & (j == jj))
        near[mine[mine != mine[np.argmin(d[mine, jj])]]] = False
    n = int(near.sum())
    if n < MIN_WHOLE_PAIRS:
        return "no object whole in both frames (the cut ones would bias the velocity)"
    zp, zc = prev.z[j[near]], cur.z[k[near]]
    a = motion.a
    if n >= 3:  # the whole similarity: the cut objects may have bent the rotation and scale too
        dc, dp = zc - zc.mean(), zp - zp.mean()
        fitted = complex(np.sum(np.conj(dc) * dp) / max(float(np.sum(np.abs(dc) ** 2)), 1e-12))
        a = fitted if SCALE_RANGE[0] <= abs(fitted) <= SCALE_RANGE[1] else a
    b = complex(np.mean(zp - a * zc))
    rms = float(np.sqrt(np.mean(np.abs(zp - a * zc - b) ** 2) / 2.0))
    sigma = max(max(rms, PAIR_SIGMA_PX) / math.sqrt(n), motion.sigma_px)
    return replace(motion, a=a, b=b, sigma_px=sigma)


def _translation_votes(prev: FramePoints, cur: FramePoints, a: complex) -> list[complex]:
    """The translations most same-label pairs agree on (a Hough vote), best first, at most ``_PEAKS``.

    Every pair of a current and a previous object of one label votes ``b = z_prev - a z_cur``; the true
    motion gathers a vote from every object seen in both frames, chance ones are scattered.
    """
    same = cur.codes[:, None] == prev.codes[None, :]
    votes = (prev.z[None, :] - a * cur.z[:, None])[same]
    if votes.size < 3:
        return []
    from .._scipy import cKDTree

    xy = np.column_stack([votes.real, votes.imag])
    support = np.asarray(cKDTree(xy).query_ball_point(xy, VOTE_RADIUS_PX, return_length=True))
    peaks: list[complex] = []
    for i in np.argsort(-support, kind="stable"):
        if support[i] < 3 or len(peaks) == _PEAKS:
            break
        if all(abs(votes[i] - p) > 2 * VOTE_RADIUS_PX for p in peaks):
            peaks.append(complex(votes[i]))
    return peaks


def _refine_guess(guess: tuple[complex, complex], cur: FramePoints, index: ObjectIndex) -> FrameMotion | None:
    """The guess refined as the matcher refines a hypothesis; None when the result is not certain."""
    a0, b0 = np.array([guess[0]], np.complex128), np.array([guess[1]], np.complex128)
    a, b, nfa, inlier, mid, dist = refine(a0, b0, cur.z, cur.codes, index, index.density, 0.0, _ITERATIONS)
    found = candidates(a, b, nfa, inlier, mid, dist, cur.z)
    if not found or found[0].log10_nfa >= LOG10_EPSILON or found[0].inliers < MIN_INLIERS:
        return None
    best = polish(found[0], cur.z, cur.codes, index)
    scale = abs(best.a)
    if not (SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]):
        return None
    return FrameMotion(best.a, best.b, max(best.sigma_m, MIN_SIGMA_PX), best.inliers, best.score, True)


def velocity_from_motion(motion: FrameMotion, prev_to_map: complex, dt: float, *, level_sigma_m: float = 0.0,
                         scale_rel_sigma: float = 0.0, heading_sigma_deg: float = 0.0) -> Velocity:
    """The ground velocity a frame-to-frame motion gives (module docs).

    Parameters
    ----------
    motion : FrameMotion
    prev_to_map : complex
        ``A_prev = s exp(-i heading)`` of the previous frame (metres per pixel, heading clockwise from north).
    dt : float
        Seconds between the frames (> 0).
    level_sigma_m : float
        Per-axis error (metres) of one frame's levelled nadir from its attitude error.
    scale_rel_sigma, heading_sigma_deg : float
        Relative error of ``|A_prev|`` and error of its heading.

    Examples
    --------
    A nadir that moved 10 pixels up the image of a camera heading east at 0.5 m/px, in 0.1 s: 50 m/s east.

    >>> m = FrameMotion(1 + 0j, 10j, 0.5, 12, 20.0, True)
    >>> vel = velocity_from_motion(m, 0.5 * np.exp(-1j * np.pi / 2), 0.1)
    >>> complex(np.round(vel.v, 9)), np.round(np.sqrt(np.diag(vel.cov)), 6).tolist()
    ((50+0j), [2.5, 2.5])
    """
    d = prev_to_map * motion.b
    per_axis = (abs(prev_to_map) * motion.sigma_px) ** 2 + 2.0 * level_sigma_m**2
    along = (scale_rel_sigma * abs(d)) ** 2
    across = (math.radians(heading_sigma_deg) * abs(d)) ** 2
    unit = d / abs(d) if abs(d) > 0 else 1 + 0j
    e = np.array([unit.real, unit.imag])
    n = np.array([-unit.imag, unit.real])
    cov = per_axis * np.eye(2) + along * np.outer(e, e) + across * np.outer(n, n)
    return Velocity(d / dt, cov / dt**2, d)
