"""Similarity transforms between image and map coordinates.

A similarity maps a point ``p`` to ``scale * R(rotation) @ p + (tx, ty)`` where
``R(a) = [[cos a, -sin a], [sin a, cos a]]`` (counter-clockwise in a frame whose
second axis is 90 degrees counter-clockwise from the first).  No reflection: an
image with y down must be flipped to y up by the caller before fitting against a
map with y north, or the fit will find the mirror image's best rotation instead.
"""

from __future__ import annotations

import math

import numpy as np

from ._kernel import fit_similarity as _fit_similarity
from .arrays import contiguous_to

# The matcher works in complex numbers: a point (x, y) is x + iy and a similarity is z -> a z + b with
# a = scale * exp(i rotation), so that one multiplication replaces a 2x2 rotation and a batch of
# hypotheses is a pair of complex arrays.

__all__ = [
    "apply_similarity",
    "image_to_map",
    "fit_similarity",
    "fit_similarity_complex",
    "prediction_variance_factor",
    "similarity_from_pairs",
]


def fit_similarity(
    src_xy: np.ndarray, dst_xy: np.ndarray, weights: np.ndarray | None = None
) -> tuple[float, float, float, float]:
    """Least-squares similarity (Umeyama, no reflection) taking ``src_xy`` onto ``dst_xy``.

    Minimises ``sum_i w_i |dst_i - (s R src_i + t)|^2``.  In 2-D the optimum has a
    closed form: with centred points, ``s e^{i a} = sum w conj(src) dst / sum w |src|^2``
    in complex notation.

    Parameters
    ----------
    src_xy, dst_xy : array of shape (n, 2)
        Corresponding points, n >= 2 and not all ``src`` points equal.
    weights : array of shape (n,), optional
        Non-negative weights (default all 1).

    Returns
    -------
    scale, rotation_rad, tx, ty : float
        ``dst ~ scale * R(rotation_rad) @ src + (tx, ty)``.

    Examples
    --------
    >>> src = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    >>> dst = apply_similarity(src, 2.0, np.pi / 2, 10.0, 5.0)
    >>> np.round(fit_similarity(src, dst), 9).tolist()
    [2.0, 1.570796327, 10.0, 5.0]
    """
    src = np.asarray(src_xy, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(dst_xy, dtype=np.float64).reshape(-1, 2)
    if src.shape != dst.shape or len(src) < 2:
        raise ValueError(f"need two equal-length lists of >= 2 points, got {len(src)} and {len(dst)}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    wsum = w.sum()
    mu_s = (w[:, None] * src).sum(axis=0) / wsum
    mu_d = (w[:, None] * dst).sum(axis=0) / wsum
    s = src - mu_s
    d = dst - mu_d
    # Real and imaginary parts of sum w conj(s) d.
    a = float(np.sum(w * (s[:, 0] * d[:, 0] + s[:, 1] * d[:, 1])))
    b = float(np.sum(w * (s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0])))
    norm = float(np.sum(w * (s * s).sum(axis=1)))
    if norm <= 0.0:
        raise ValueError("source points are all equal: the similarity is undetermined")
    rotation = float(np.arctan2(b, a))
    scale = float(np.hypot(a, b) / norm)
    c, si = np.cos(rotation), np.sin(rotation)
    tx = float(mu_d[0] - scale * (c * mu_s[0] - si * mu_s[1]))
    ty = float(mu_d[1] - scale * (si * mu_s[0] + c * mu_s[1]))
    return scale, rotation, tx, ty


def image_to_map(scale_m_per_px: float, heading_deg: float) -> complex:
    """The image-to-map similarity's ``a = scale exp(-i heading)`` of an answer's (or a prior's) scale and heading
    (``heading_deg`` clockwise from map north, so that ``heading_deg = -arg(a)``; levelled image, y up).

    Examples
    --------
    >>> a = image_to_map(0.5, 90.0)
    >>> round(a.real, 12), round(a.imag, 12)
    (0.0, -0.5)
    """
    return scale_m_per_px * complex(np.exp(-1j * math.radians(heading_deg)))


def apply_similarity(xy: np.ndarray, scale: float, rotation_rad: float, tx: float, ty: float) -> np.ndarray:
    """Apply ``scale * R(rotation_rad) @ p + (tx, ty)`` to points of shape (n, 2) (or one point (2,))."""
    p = np.asarray(xy, dtype=np.float64)
    c, s = np.cos(rotation_rad) * scale, np.sin(rotation_rad) * scale
    out = np.empty_like(p)
    out[..., 0] = c * p[..., 0] - s * p[..., 1] + tx
    out[..., 1] = s * p[..., 0] + c * p[..., 1] + ty
    return out


def similarity_from_pairs(
    z1: np.ndarray, z2: np.ndarray, w1: np.ndarray, w2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The similarities ``z -> a z + b`` taking ``z1 -> w1`` and ``z2 -> w2`` (complex arrays, broadcast).

    Where ``z1 == z2`` the similarity is undetermined and ``a`` is NaN.

    Examples
    --------
    >>> a, b = similarity_from_pairs(np.array([0j]), np.array([1 + 0j]), np.array([5 + 5j]), np.array([5 + 7j]))
    >>> complex(a[0]), complex(b[0])
    (2j, (5+5j))
    """
    dz = np.asarray(z2) - np.asarray(z1)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(dz != 0, (np.asarray(w2) - np.asarray(w1)) / np.where(dz != 0, dz, 1.0), np.nan)
    b = np.asarray(w1) - a * np.asarray(z1)
    return a, b


def fit_similarity_complex(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Batched least-squares similarity ``dst ~ a src + b`` over the last axis (complex points).

    The same estimator as :func:`fit_similarity` (Umeyama without reflection), for many point sets at
    once: ``src`` and ``dst`` have shape ``(..., k)``; ``weights`` (same shape, >= 0, e.g. a 0/1 inlier
    mask) selects and weights the points of each set.

    Returns
    -------
    a, b : complex arrays of shape ``(...)``
        NaN where a set has fewer than two distinct weighted source points.

    Examples
    --------
    >>> src = np.array([0, 1, 1j])
    >>> a, b = fit_similarity_complex(src, (1 - 1j) * src + 3)
    >>> complex(np.round(a, 12)), complex(np.round(b, 12))
    ((1-1j), (3+0j))
    """
    src = np.asarray(src, dtype=np.complex128)
    dst = np.asarray(dst, dtype=np.complex128)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    # The usual calls need no broadcasting (np.broadcast_* cost 10 us each) and pass contiguous arrays through.
    shape = src.shape if src.shape == dst.shape and (w is None or w.shape == src.shape) else np.broadcast_shapes(
        src.shape, dst.shape, () if w is None else w.shape)
    if not shape:
        raise ValueError("the point sets must have at least one axis (the points)")
    # The compiled kernel fits each set with numpy's arithmetic (pairwise sums, its complex product and quotient).
    rows = (math.prod(shape[:-1]), shape[-1])
    a = np.empty(rows[0], np.complex128)
    b = np.empty(rows[0], np.complex128)
    _fit_similarity(_rows(src, shape, rows), _rows(dst, shape, rows),
                    np.ones(rows) if w is None else _rows(w, shape, rows), a, b)
    return a.reshape(shape[:-1])[()], b.reshape(shape[:-1])[()]


def _rows(v: np.ndarray, shape: tuple[int, ...], rows: tuple[int, int]) -> np.ndarray:
    """``v`` broadcast to ``shape`` as a contiguous ``rows``-shaped array (itself when it already is one)."""
    if v.shape == rows and v.flags.c_contiguous:
        return v
    return contiguous_to(v, shape).reshape(rows)


def prediction_variance_factor(src: np.ndarray, at: complex = 0j, weights: np.ndarray | None = None) -> np.ndarray:
    """``1/n + |at - mean|^2 / sum |src - mean|^2``: the variance of a fitted similarity's prediction at ``at``.

    With independent errors of per-axis variance ``sigma^2`` on the destination points, the position the
    least-squares similarity predicts for ``at`` has per-axis variance ``sigma^2`` times this factor
    (the classical regression result; the closed form the simulator's bound is checked against).
    """
    src = np.asarray(src, dtype=np.complex128)
    w = np.ones(src.shape) if weights is None else np.asarray(weights, dtype=np.float64)
    n = w.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = (w * src).sum(axis=-1) / n
        spread = (w * np.abs(src - mu[..., None]) ** 2).sum(axis=-1)
        return 1.0 / n + np.abs(at - mu) ** 2 / spread
