"""Issue 29: a frame-to-frame velocity that cut blobs do not bias, a filter whose stated covariance covers
its error while it drifts, and ``--initial`` that starts with the aircraft's velocity."""

from __future__ import annotations

import numpy as np

from mapdb.navigation.velocity import MIN_WHOLE_OBJECTS, FramePoints, match_frames

W, H = 640.0, 480.0


def _frames(n_whole: int, n_cut: int, b: complex, seed: int = 3) -> tuple[FramePoints, FramePoints]:
    """Two frames of the same objects: the whole ones moved by ``b`` (pixels), the cut ones by half of it."""
    rng = np.random.default_rng(seed)
    n = n_whole + n_cut
    z = rng.uniform(-280, 280, n) + 1j * rng.uniform(-200, 200, n)
    codes = rng.integers(0, 3, n)
    cut = np.arange(n) >= n_whole
    moved = np.where(cut, 0.5 * b, b)
    return FramePoints(z, codes, W, H, cut), FramePoints(z - moved, codes, W, H, cut)


def test_cut_blobs_do_not_bias_the_frame_to_frame_translation() -> None:
    # Too few whole objects to match on them alone (MIN_WHOLE_OBJECTS): the match uses the cut ones, whose
    # centroids move at half the speed, and the translation is refitted on the whole ones.
    b = 14.0 + 9.0j
    for n_whole in (1, 3, MIN_WHOLE_OBJECTS - 1):
        prev, cur = _frames(n_whole, 14, b)
        motion = match_frames(prev, cur, 1 + 0j, b * 0.8)
        assert not isinstance(motion, str), motion
        assert abs(motion.b - b) < 0.05, (n_whole, motion.b)
    # Every object cut in one frame or the other: no velocity rather than a slow one.
    prev, cur = _frames(0, 14, b)
    assert isinstance(match_frames(prev, cur, 1 + 0j, b * 0.8), str)
