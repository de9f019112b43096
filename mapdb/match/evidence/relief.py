"""Relief and cut objects: the final fit for objects extracted from segmentation masks.

A segmentation model's blob is not the map's footprint centroid.  Two effects dominate on masks rendered
from real outlines (``mapdb simulate --render masks``, Andorra and Monaco, 640x480, 60 degrees, buildings
extruded to their heights; measured on 80 images per row against the blob's true map object):

* **Relief.**  A building's roof and walls shift its blob's centroid *away from the nadir*, by an amount
  growing with the distance from it (``r h / (H - h)`` for the roof of a building ``h`` high seen from
  ``H``).  At 120 m the whole (uncut) building blobs lay a median 6 px (90th percentile 12 px) from where
  their footprint centroids project, and the displacement was radial: a few pixels radially, under one
  pixel tangentially, about 3-4 % of the distance from the image centre.  A similarity absorbs the mean
  displacement as scale; what is left is radial scatter from the buildings' differing heights.  Ground
  objects (road intersections, parks, water) lay within a pixel.
* **Cut objects.**  55-64 % of the blobs touched the image border at 120 m; their visible part's centroid
  is pulled inward, by a median 32-39 px and up to hundreds for large areas.  Such a blob names the right
  map object but says little about where it is.

So the final fit (:func:`fit_with_relief`) uses only whole objects when at least four are matched, and
weighs each residual by its own error model: per-axis sigma ``sigma_t`` tangentially and
``sqrt(sigma_t^2 + kappa^2 |a z|^2)`` radially, ``kappa`` estimated from the residuals (iteratively
reweighted least squares, a few iterations).  The radial term is used only when the radial residuals are
significantly larger than the tangential ones (a one-sided test at about 1 %): ideal centroids, whose
errors are isotropic, get the plain least-squares fit and its bound, unchanged.  Measured on the same
images (the blobs' true map objects, whole blobs within 25 px): the position error RMS at 300 m fell from
0.83 to 0.61 m (Andorra) with the relief weights alone.  In the matcher (``python
benchmarks/rendered_masks.py --n 150 --baseline 670ef46``, Andorra and Monaco, with heights, 300 images a
row), with cut blobs also kept out of the quads: the RMS of the correct answers fell from 0.55 to 0.34 m at
120 m, 0.60 to 0.42 m at 200 m and 0.55 to 0.35 m at 300 m; the answers more than 2 m off from 1, 1 and 6 to
0, 3 and 0; the ideal-centroid rows are unchanged (100 %, RMS 0.00 m).

The radial direction is taken from the image centre, which is the nadir for a level camera and for an
image the localizer levelled from its roll and pitch.  A tilted camera with no attitude given has its
nadir elsewhere; its residuals then show no consistent radial excess and the test leaves the fit plain.
"""

from __future__ import annotations

import math

import numpy as np

from .._kernel import fit_similarity as _fit_similarity
from .._kernel import verify_errors as _verify_errors

__all__ = ["RELIEF_ITERATIONS", "ReliefFit", "fit_with_relief", "leave_one_out_sigma", "radial_excess"]

# Reweighting rounds: the weights depend on the fit only through the radial directions and kappa, which
# settle within two or three rounds.
RELIEF_ITERATIONS = 4
# One-sided normal quantile of the log variance ratio test (about 1 %).
_Z_ONE_PERCENT = 2.33


class ReliefFit:
    """A similarity ``z -> a z + b`` with its error model: ``sigma_axis`` (tangential per-axis sigma,
    metres), ``kappa`` (radial relief sigma per metre from the nadir, 0 for the plain fit) and
    ``variance_factor`` (the position's per-axis variance over ``sigma_axis**2``)."""

    __slots__ = ("a", "b", "kappa", "sigma_axis", "variance_factor")

    def __init__(self, a: complex, b: complex, sigma_axis: float, variance_factor: float, kappa: float) -> None:
        self.a, self.b = a, b
        self.sigma_axis, self.variance_factor, self.kappa = sigma_axis, variance_factor, kappa


def radial_excess(src: np.ndarray, dst: np.ndarray, a: complex, b: complex) -> tuple[np.ndarray, np.ndarray, bool]:
    """Radial and tangential residuals (metres) of ``a src + b`` against ``dst``, and whether the radial ones
    are significantly larger (variance ratio beyond ``exp(2.33 * 2 / sqrt(n - 2))``, the log ratio of two
    chi-square sums having standard deviation about ``2 / sqrt(dof)``).

    Examples
    --------
    >>> src = np.array([10, -10, 10j, -10j, 7 + 7j, -7 - 7j])
    >>> rho, tau, excess = radial_excess(src, src * 1.0, 1.0, 0j)
    >>> bool(np.allclose(rho, 0)), excess
    (True, False)
    >>> rho, tau, excess = radial_excess(src, src * (1 + np.array([.1, 0, .1, 0, .1, 0])) + 0.01j, 1.0, 0j)
    >>> excess
    True
    """
    # numpy's operations of ``w = a src + b``, ``exp(1j angle(a src))``, ``conj`` and ``sum`` called directly (the
    # product a src made once, angle's arctan2 and sum's add.reduce without their wrappers): the same numbers.
    moved = a * src
    w = moved + b
    radial = np.exp(1j * np.arctan2(moved.imag, moved.real))  # unit vectors away from the nadir, in map metres
    q = (w - dst) * radial.conj()
    n = src.size
    if n <= 4:
        return q.real, q.imag, False
    ratio_limit = math.exp(_Z_ONE_PERCENT * 2.0 / math.sqrt(n - 2))
    excess = bool(np.add.reduce(q.real**2) > ratio_limit * max(float(np.add.reduce(q.imag**2)), 1e-300))
    return q.real, q.imag, excess


def fit_with_relief(src: np.ndarray, dst: np.ndarray) -> ReliefFit | None:
    """The similarity taking ``src`` (image, complex, centred on the nadir) onto ``dst`` (map metres), with
    the radial relief term when the residuals call for it; None when the points cannot fix a similarity.

    Examples
    --------
    Points that fit a similarity exactly but for radial displacements: the plain fit is pulled, the relief
    fit recovers the position.

    >>> rng = np.random.default_rng(0)
    >>> src = rng.uniform(-300, 300, 30) + 1j * rng.uniform(-200, 200, 30)
    >>> true = (0.5 * src + (100 + 50j)) + 0.01 * (rng.standard_normal(30) + 1j * rng.standard_normal(30))
    >>> seen = true + 0.5 * src * rng.uniform(0, 0.06, 30) * (src.real > 0)  # relief on one side only
    >>> fit = fit_with_relief(src, seen)
    >>> from mapdb.match.geometry import fit_similarity_complex
    >>> plain = fit_similarity_complex(src, seen)[1]
    >>> bool(abs(fit.b - (100 + 50j)) < abs(plain - (100 + 50j)) / 3), fit.kappa > 0
    (True, True)
    >>> fit_with_relief(np.array([1 + 1j]), np.array([2 + 2j])) is None
    True
    """
    src = np.ascontiguousarray(src, np.complex128)
    dst = np.ascontiguousarray(dst, np.complex128)
    n = src.size
    if n < 3:
        return None
    # The kernels of fit_similarity_complex and fit_errors called on one row directly (their wrappers' shape
    # handling is most of an image's final fit): the same numbers.
    out = np.empty(2, np.complex128)
    _fit_similarity(src.reshape(1, n), dst.reshape(1, n), np.ones((1, n)), out[:1], out[1:])
    a, b = out.tolist()
    if not math.isfinite(abs(a)) or a == 0:
        return None
    rho, tau, excess = radial_excess(src, dst, a, b)
    if not excess:
        errors = np.empty(2)
        _verify_errors(src, np.hypot(rho, tau).reshape(1, n), np.ones((1, n), bool), errors[:1], errors[1:])
        sigma, variance = errors.tolist()
        return ReliefFit(a, b, sigma, variance, 0.0)
    kappa = 0.0
    for _ in range(RELIEF_ITERATIONS):
        reach2 = np.abs(a * src) ** 2
        sigma_t2 = max(float(np.sum(tau**2)) / max(src.size - 2, 1), 1e-12)
        kappa = math.sqrt(max(float(np.sum(rho**2 - sigma_t2)), 0.0) / max(float(np.sum(reach2)), 1e-300))
        sigma_r = np.sqrt(sigma_t2 + kappa**2 * reach2)
        a, b, cov = _weighted_fit(src, dst, np.exp(1j * np.angle(a * src)), sigma_r, math.sqrt(sigma_t2))
        rho, tau, _ = radial_excess(src, dst, a, b)
    sigma_t = math.sqrt(max(float(np.sum(tau**2)) / max(src.size - 2, 1), 1e-12))
    return ReliefFit(a, b, sigma_t, float(cov[2, 2] + cov[3, 3]) / 2.0 / sigma_t**2, kappa)


def leave_one_out_sigma(src: np.ndarray, dst: np.ndarray, fit: ReliefFit) -> float:
    """Jackknife estimate of the per-axis error (metres) of ``fit.b``, the map point under the nadir.

    Each point is left out in turn and the fit's weighted least squares (its radial and tangential sigmas
    held fixed) solved again, in closed form from the hat matrix's 2x2 blocks; the spread of the ``n``
    positions, ``sqrt((n - 1) / n * sum |b_i - mean|^2 / 2)``, is the jackknife's per-axis sigma.  Unlike
    ``sigma_axis * sqrt(variance_factor)``, which trusts the residuals to be independent and alike, it
    feels one point far off with a long lever (a partly hidden park, a merged blob among four or five whole
    ones): on masks rendered at 120-300 m the 2 m errors the model's sigma passed as 0.5-1.0 m had jackknife
    sigmas of 1.3-2.0 m (:mod:`mapdb.match.refine`).  Infinite when a point is needed to fix the fit (fewer
    than three points, or one whose removal leaves the rest degenerate).

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> src = rng.uniform(-300, 300, 40) + 1j * rng.uniform(-200, 200, 40)
    >>> dst = 0.5 * src + (10 + 5j) + 0.3 * (rng.standard_normal(40) + 1j * rng.standard_normal(40))
    >>> fit = fit_with_relief(src, dst)
    >>> model = fit.sigma_axis * math.sqrt(fit.variance_factor)
    >>> bool(0.6 < leave_one_out_sigma(src, dst, fit) / model < 1.6)
    True
    >>> dst[0] += 30.0  # one gross error: the jackknife sees it
    >>> bool(leave_one_out_sigma(src, dst, fit_with_relief(src, dst)) > 2 * model)
    True
    >>> leave_one_out_sigma(src[:2], dst[:2], fit)
    inf
    """
    src = np.asarray(src, np.complex128)
    dst = np.asarray(dst, np.complex128)
    n = src.size
    if n < 3:
        return math.inf
    if fit.kappa == 0.0:
        b = _plain_leave_one_out(src, dst)
    else:
        b = _weighted_leave_one_out(src, dst, fit)
    if b is None:
        return math.inf
    return float(math.sqrt((n - 1) / n * float(np.sum(np.abs(b - b.mean()) ** 2)) / 2.0))


def _plain_leave_one_out(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """``b`` of the plain least-squares similarity with each point left out (complex linear regression of
    ``dst`` on ``(src, 1)``: ``beta_i = beta - G^-1 x_i^H e_i / (1 - h_i)``), or None when one is undefined."""
    n = src.size
    mean = src.mean()
    centred = src - mean
    spread = np.vdot(centred, centred).real
    if spread <= 0.0:
        return None
    a = np.vdot(centred, dst) / spread  # sum conj(centred) dst: the centred dst's mean adds nothing
    b = dst.mean() - a * mean
    e = dst - (a * src + b)
    keep = 1.0 - (1.0 / n + (centred.real**2 + centred.imag**2) / spread)  # one minus each point's leverage
    if keep.min() < 1e-9:
        return None
    # The b row of G^-1 = [[n, -sum conj z], [-sum z, sum |z|^2]] / (n * spread), times (conj z_i, 1).
    row = (np.vdot(src, src).real - n * mean * np.conj(src)) / (n * spread)
    return b - row * e / keep


def _weighted_leave_one_out(src: np.ndarray, dst: np.ndarray, fit: ReliefFit) -> np.ndarray | None:
    """``b`` of the relief fit's weighted least squares (its sigmas held fixed) with each point left out, from
    the hat matrix's 2x2 diagonal blocks, or None when one is undefined."""
    n = src.size
    radial = np.exp(1j * np.angle(fit.a * src))
    sigma_r = np.sqrt(fit.sigma_axis**2 + fit.kappa**2 * np.abs(fit.a * src) ** 2)
    design, target = _whitened(src, dst, radial, np.maximum(sigma_r, 1e-12), max(fit.sigma_axis, 1e-12))
    # Rows (radial, tangential) of each point together: the hat matrix's 2x2 diagonal blocks.
    d = np.stack([design[:n], design[n:]], axis=1)  # (n, 2, 4)
    t = np.stack([target[:n], target[n:]], axis=1)  # (n, 2)
    gram_inv = np.linalg.pinv(design.T @ design)
    p = gram_inv @ (design.T @ target)
    e = t - d @ p
    hat = d @ gram_inv @ d.transpose(0, 2, 1)
    keep = np.eye(2)[None, :, :] - hat
    det = keep[:, 0, 0] * keep[:, 1, 1] - keep[:, 0, 1] * keep[:, 1, 0]
    if np.any(np.abs(det) < 1e-9):
        return None
    step = np.linalg.solve(keep, e[:, :, None])[:, :, 0]  # (I - H_ii)^-1 e_i
    loo = p[None, :] - (gram_inv @ (d.transpose(0, 2, 1) @ step[:, :, None])[:, :, 0].T).T
    return loo[:, 2] + 1j * loo[:, 3]


def _weighted_fit(src: np.ndarray, dst: np.ndarray, radial: np.ndarray, sigma_r: np.ndarray,
                  sigma_t: float) -> tuple[complex, complex, np.ndarray]:
    """Weighted least squares of ``(a, b)`` (four real unknowns) with residuals split into the radial and
    tangential directions, each scaled by its sigma; the fit and the unknowns' covariance."""
    design, target = _whitened(src, dst, radial, sigma_r, sigma_t)
    p, *_ = np.linalg.lstsq(design, target, rcond=None)
    cov = np.linalg.pinv(design.T @ design)
    return complex(p[0], p[1]), complex(p[2], p[3]), cov


def _whitened(src: np.ndarray, dst: np.ndarray, radial: np.ndarray, sigma_r: np.ndarray,
              sigma_t: float) -> tuple[np.ndarray, np.ndarray]:
    """The design ``(2n, 4)`` and target of ``(a1, a2, b1, b2)``: every point's radial rows, then its
    tangential ones, each scaled by its sigma."""
    n = src.size
    ones, zeros = np.ones(n), np.zeros(n)
    real_rows = np.column_stack([src.real, -src.imag, ones, zeros])  # Re(a z + b) in (a1, a2, b1, b2)
    imag_rows = np.column_stack([src.imag, src.real, zeros, ones])
    dr, di = radial.real[:, None], radial.imag[:, None]
    design = np.vstack([(dr * real_rows + di * imag_rows) / sigma_r[:, None],
                        (dr * imag_rows - di * real_rows) / sigma_t])
    target = np.concatenate([(radial.real * dst.real + radial.imag * dst.imag) / sigma_r,
                             (radial.real * dst.imag - radial.imag * dst.real) / sigma_t])
    return design, target
