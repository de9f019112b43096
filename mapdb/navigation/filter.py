"""A particle filter fusing frame-to-frame velocities and absolute fixes, multi-modal where fixes are.

State
-----
Each of ``N`` particles is a horizontal position ``p`` (complex: east + i north, map metres) and velocity
``v`` (complex, m/s), with a weight.  Heading and scale are not in the state: the heading comes from the last
fix and the autopilot's heading changes since, the scale from the last fix and the barometric altitude
ratio (:mod:`mapdb.navigation.navigator`); altitude is the barometer's.

Motion model (:meth:`ParticleFilter.predict`)
---------------------------------------------
Over ``dt`` seconds, with the heading change ``dpsi`` (clockwise) the autopilot reports::

    v' = v exp(-i dpsi) + a dt          a ~ N(0, accel_std^2) per axis, per particle
    p' = p + (v + v') dt / 2

The rotation makes a coordinated turn follow the aircraft's own heading, so that a turn flown without any
measurement (a detector blackout) bends the track as the aircraft did; ``a`` covers the rest.

**Drift since the last fix.**  The velocity measurements are not independent from frame to frame as the
velocity update treats them: frame-to-frame matching and an inertial unit keep an error for seconds (a
heading or scale a little off, rooftops moving faster than the ground, an IMU's bias).  Such a bias ``b``
puts the position ``b tau`` off ``tau`` seconds after the last applied fix, which no velocity update can
see.  The prediction therefore also spreads the positions so that their variance grows as ``(sigma_b
tau)^2`` per axis: each step adds ``sigma_b^2 ((tau + dt)^2 - tau^2)``, with ``sigma_b = DRIFT_FLOOR_MPS
+ DRIFT_FRACTION |v|`` unless ``drift_of`` gives it: the navigator measures the velocity's persistent
error against its fixes (:mod:`mapdb.navigation.bias`), so that an ideal flight's cloud stays as narrow
as its velocity error (a cloud far wider lets the estimate wander in it) and a rendered one covers its
bias.  An applied fix (or a new start) sets ``tau`` back to 0, so on a flight fixed
every frame the spread added is a few centimetres.  The fix gate widens with it (:meth:`update_fix`).

Measurement models
------------------
* **Velocity** (frame to frame, or an inertial unit): ``z_v = v + n``, ``n ~ N(0, R)`` with the 2x2
  covariance ``R`` the measurement states (:meth:`update_velocity`).  A measurement farther than the
  chi-square gate (99.9 %) from every plausible particle velocity is rejected as an outlier.
* **Fix** (an absolute position from the matcher, :meth:`update_fix`): a mixture over the answer and its
  runner-up candidates, ``j = 1..m``, with an outlier floor::

      L(p) = (1 - beta) sum_j pi_j N(p; c_j, s_j^2 I) + beta / A

  ``pi_j`` proportional to ``10^score_j`` (a candidate's score is ``-log10`` of its expected number of
  false alarms), ``s_j`` the candidate's stated error combined with the floor that attitude errors add,
  ``beta`` the prior probability that a fix is wrong and ``A`` the area it could have come from (the
  query's prior disc).  A wrong fix thus multiplies every particle by about the same floor and cannot drag
  the estimate; a fix whose runner-up is the filter's own place keeps the filter's mode alive.  The
  probability that the fix belongs to the estimate, ``P_in = (1 - beta) E[g] / ((1 - beta) E[g] + beta/A)``,
  decides: below one half the fix is rejected as an outlier and not applied at all.  An accepted fix is
  applied with that same ``P_in`` (``w' ∝ w (P_in g / E[g] + 1 - P_in)``), and the cloud is redrawn from
  the fix when fewer than ``MIN_EFFECTIVE`` particles lie inside it: the gate widens the sigmas by
  ``gate_sigma_m``, and an update recomputing the floor against the sharp ``g`` left a right fix 2-3 m from
  every particle "used" with no weight changed (issue 29).
* **Recovery**: particles drawn around a place (:meth:`inject`) join the cloud with a share of the weight;
  later fixes decide between the modes.  The navigator injects around fixes that were rejected several
  times in a row at mutually consistent places, which is how a filter started far off, or captured, gets
  back.

Resampling is systematic, when the effective sample size drops below half; resampled particles are
jittered by a small fraction of the cloud's spread (regularisation), so that a cloud never collapses to
copies of one particle.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["FixComponent", "FixOutcome", "ParticleFilter", "VELOCITY_GATE", "shared_sigma"]

# Chi-square, 2 degrees of freedom, 99.9 %: a velocity measurement beyond it is an outlier.
VELOCITY_GATE = 13.8
# Resampling when the effective sample size falls below this fraction of the particles.
RESAMPLE_FRACTION = 0.5
# Jitter after resampling, as a fraction of the cloud's standard deviation per axis.
JITTER = 0.1
# A position estimate is the mean of the heaviest mode: connected cells of this size (``_heaviest_mode``).
MODE_CELL_M = 10.0
MODE_GRID = 256  # at most this many cells across the cloud
# A fix leaving fewer effective particles than this redraws the cloud from the fix (``_redraw``).
MIN_EFFECTIVE = 50.0
# Kernel width of the cloud's density at a fix's components, as a fraction of its largest spread (>= 1 m).
KERNEL_FRACTION = 0.2
# The velocity error that persists between fixes (module docs, drift): per axis, a floor plus a fraction of
# the speed.  Measured on rendered-mask flights at 120 m (benchmarks/navigation_masks.py): frame-to-frame
# velocity biased by up to 0.5 m/s at 20 m/s after the first fix (rooftops), 0.35 m/s before it (a 1 degree
# heading bias, a 2 m barometer bias at 120 m); 0.1 + 0.03 x 20 = 0.7 m/s covers both.
DRIFT_FLOOR_MPS = 0.1
DRIFT_FRACTION = 0.03


@dataclass(frozen=True)
class FixComponent:
    """One place a fix says the aircraft may be: centre (complex), 1-sigma per axis, and its weight."""

    centre: complex
    sigma_m: float
    weight: float


def shared_sigma(image: Any, components: list[FixComponent]) -> float:
    """The error that consecutive fixes from blobs share, per axis: the fix's own (its stated error with the
    blob floor, as the navigator's components carry it); 0 for centroid detections.

    Relief, merging and cuts move the same buildings' centroids the same way in consecutive frames, and
    the fit's error comes from those same buildings: measured on rendered masks at 120 m (Monaco and
    Andorra, ``benchmarks/navigation_masks.py``), applied fixes were 0.5 m off per axis (RMS), with a
    correlation of 0.35-0.47 from one frame's fix to the next, and runs of six fixes 2.5 m off; fused as
    independent, ten fixes stated 0.3 m while the estimate was 1-1.7 m off (beyond 3 sigma on 2-4 % of the
    frames; 0.1-0.4 % with this floor).  ``image`` is the frame's
    :class:`~mapdb.detections.images.ImageObjects` (blobs carry ``area_px`` or ``border``), or None.
    """
    if image is None or (image.area_px is None and image.border is None) or not components:
        return 0.0
    return max(c.sigma_m for c in components if c.weight >= 1.0)


@dataclass(frozen=True)
class FixOutcome:
    """What a fix did: applied or rejected, the probability it belongs to the estimate, its distance."""

    applied: bool
    inlier_probability: float
    distance_m: float


class ParticleFilter:
    """The particle filter of the module docs; numpy arrays over particles.

    Parameters
    ----------
    n : int
        Particles.
    accel_std : float
        Per-axis acceleration noise, m/s^2 (the motion model's ``a``).
    outlier_probability : float
        ``beta``, the prior probability that a fix is wrong.
    seed : int
        The filter's random draws (same seed, same track).

    Examples
    --------
    >>> f = ParticleFilter(500, seed=1)
    >>> f.initialise(100 + 200j, 50.0, velocity=10 + 0j, velocity_sigma=1.0)
    >>> f.predict(1.0)
    >>> outcome = f.update_fix([FixComponent(110 + 200j, 0.5, 1.0)], area_m2=math.pi * 60.0**2)
    >>> outcome.applied, abs(f.estimate()[0] - (110 + 200j)) < 1.0
    (True, True)
    """

    def __init__(self, n: int = 2000, accel_std: float = 1.0, outlier_probability: float = 0.02,
                 seed: int = 0) -> None:
        if n < 10:
            raise ValueError(f"a particle filter needs at least 10 particles, got {n}")
        self.n = n
        self.accel_std = accel_std
        self.beta = outlier_probability
        self.rng = np.random.default_rng(seed)
        self.p: np.ndarray = np.zeros(n, np.complex128)
        self.v: np.ndarray = np.zeros(n, np.complex128)
        self.logw = np.full(n, -math.log(n))
        self.initialised = False
        self.velocity_known = False
        self.since_fix = 0.0  # seconds since the last applied fix or start (module docs, drift)
        self.last_dt = 0.0  # the last prediction's step (s)
        # The persistent velocity error allowed (m/s per axis) at a speed, when the navigator measures it
        # (:mod:`mapdb.navigation.bias`); None: DRIFT_FLOOR_MPS + DRIFT_FRACTION |v|.
        self.drift_of: Callable[[float], float] | None = None

    # ------------------------------------------------------------------------------------- state

    def _normal(self, size: int) -> np.ndarray:
        return self.rng.standard_normal(size) + 1j * self.rng.standard_normal(size)

    def _disc(self, centre: complex, radius: float, size: int) -> np.ndarray:
        """Uniform draws in a disc."""
        r = radius * np.sqrt(self.rng.random(size))
        return centre + r * np.exp(2j * math.pi * self.rng.random(size))

    def initialise(self, centre: complex, radius: float, velocity: complex | None = None,
                   velocity_sigma: float = 30.0) -> None:
        """Particles uniform in the disc of ``radius`` around ``centre``, velocities around ``velocity``."""
        self.p = self._disc(centre, radius, self.n)
        self.v = (velocity or 0j) + velocity_sigma / math.sqrt(2.0) * self._normal(self.n)
        self.logw = np.full(self.n, -math.log(self.n))
        self.initialised = True
        self.velocity_known = velocity is not None
        self.since_fix = 0.0
        self.last_dt = 0.0

    def snapshot(self) -> tuple[Any, ...]:
        """The whole state, random generator included, for :meth:`restore` (copies: some updates are in place)."""
        return (self.p.copy(), self.v.copy(), self.logw.copy(), self.initialised, self.velocity_known,
                self.since_fix, self.last_dt, self.rng.bit_generator.state)

    def restore(self, state: tuple[Any, ...]) -> None:
        """Back to a :meth:`snapshot`: as if the updates since had not happened."""
        (self.p, self.v, self.logw, self.initialised, self.velocity_known, self.since_fix, self.last_dt,
         rng_state) = state
        self.rng.bit_generator.state = rng_state

    def finite(self) -> bool:
        """Whether every particle's position, velocity and weight is a finite number."""
        return bool(np.isfinite(self.p).all() and np.isfinite(self.v).all() and np.isfinite(self.logw).all())

    def reset(self) -> None:
        """Forget the position and velocity: the filter waits for :meth:`initialise` again."""
        self.initialised = False
        self.velocity_known = False

    @property
    def weights(self) -> np.ndarray:
        w = np.exp(self.logw - self.logw.max())
        return w / w.sum()

    def predict(self, dt: float, turn_rad: float | None = None) -> None:
        """The motion model over ``dt`` seconds; ``turn_rad`` the heading change (clockwise), if known."""
        if not self.initialised or dt <= 0:
            return
        self.last_dt = dt
        v_new = self.v * (np.exp(-1j * turn_rad) if turn_rad else 1.0)
        v_new = v_new + self.accel_std * dt * self._normal(self.n)
        self.p = self.p + 0.5 * (self.v + v_new) * dt
        self.v = v_new
        grown = self.drift_sigma(self.since_fix + dt) ** 2 - self.drift_sigma(self.since_fix) ** 2
        self.p = self.p + math.sqrt(max(grown, 0.0)) * self._normal(self.n)
        self.since_fix += dt

    def drift_sigma(self, since: float | None = None) -> float:
        """Per-axis position error (m) a persistent velocity error gives ``since`` seconds (default: now) after
        the last applied fix (module docs, drift)."""
        since = self.since_fix if since is None else since
        speed = abs(complex(np.sum(self.weights * self.v))) if self.initialised else 0.0
        rate = DRIFT_FLOOR_MPS + DRIFT_FRACTION * speed if self.drift_of is None else self.drift_of(speed)
        return rate * since

    # ------------------------------------------------------------------------------ measurements

    def update_velocity(self, v: complex, cov: np.ndarray) -> bool:
        """Weigh particles by a velocity measurement (module docs); False if it was rejected as an outlier."""
        if not self.initialised:
            return False
        if not self.velocity_known:
            # The first velocity measured sets the velocities: weighing a broad guess by it would leave
            # few particles, and little diversity to learn the rest from.  It is the motion over the step
            # just predicted with the guess (a frame-to-frame velocity is the mean over it), so the positions
            # move as it says over that step: a start at rest would otherwise lag by one step's flight.
            root = np.linalg.cholesky(cov + 1e-9 * np.eye(2))
            draws = root @ self.rng.standard_normal((2, self.n))
            v_new = np.asarray(v + draws[0] + 1j * draws[1], np.complex128)
            self.p = self.p + (v_new - self.v) * self.last_dt
            self.v = v_new
            self.velocity_known = True
            return True
        w = self.weights
        spread = _covariance(self.v, w)
        d = self.v - v
        mean_d = np.array([np.sum(w * d.real), np.sum(w * d.imag)])
        total = cov + spread
        if float(mean_d @ np.linalg.solve(total, mean_d)) > VELOCITY_GATE:
            return False
        inv = np.linalg.inv(cov)
        m2 = inv[0, 0] * d.real**2 + 2.0 * inv[0, 1] * d.real * d.imag + inv[1, 1] * d.imag**2
        self._reweigh(-0.5 * m2)
        return True

    def update_fix(self, components: list[FixComponent], area_m2: float, gate_sigma_m: float = 2.0,
                   shared_sigma_m: float = 0.0) -> FixOutcome:
        """Weigh particles by a (multi-modal) fix with an outlier floor (module docs).

        ``gate_sigma_m``, combined with the drift since the last applied fix (:meth:`drift_sigma`), widens
        the components when deciding whether the fix is an outlier (not when applying it): a cloud a
        little too confident must not turn away a right fix a metre or two off.
        An accepted fix is then applied with the inlier probability the gate found,
        ``w' ∝ w (P_in g / E[g] + 1 - P_in)`` with ``g`` the sharp mixture: recomputing the floor against
        the sharp ``g`` would let a fix 2-3 m from every particle (``g`` far below the floor everywhere)
        pass the gate, be reported used, and change no weight (issue 29).

        ``shared_sigma_m`` is the part of the fix's error that consecutive fixes share (per axis): after
        the update the cloud's spread is kept at least that wide (:meth:`_keep_spread`), since fusing
        fixes as independent would shrink it below the error they have in common.
        """
        w = self.weights
        gate = math.hypot(gate_sigma_m, self.drift_sigma())
        inlier = (1.0 - self.beta) * float(np.sum(w * self._mixture(components, gate)))
        floor = self.beta / max(area_m2, 1.0)
        p_in = inlier / (inlier + floor)
        best = max(components, key=lambda c: c.weight).centre
        distance = abs(best - self.estimate()[0])
        if p_in < 0.5:
            return FixOutcome(False, p_in, distance)
        # In logs: a sharp fix a few metres from every particle underflows g itself.
        logg = self._log_mixture(components)
        logw = self.logw - float(np.max(self.logw))
        top = float(np.max(logw + logg))
        log_mean_g = top + math.log(float(np.sum(np.exp(logw + logg - top)) / np.sum(np.exp(logw))))
        loglik = np.logaddexp(math.log(p_in) + logg - log_mean_g, math.log1p(-p_in) if p_in < 1.0 else -np.inf)
        after = np.exp(self.logw + loglik - np.max(self.logw + loglik))
        if (self.n * self._coverage(components, w) < MIN_EFFECTIVE
                or 1.0 / np.sum((after / after.sum()) ** 2) < MIN_EFFECTIVE):
            self._redraw(components, w)
        else:
            self._reweigh(loglik)
        self._keep_spread(shared_sigma_m)
        self.since_fix = 0.0
        return FixOutcome(True, p_in, distance)

    def update_likelihood(self, loglik: np.ndarray, keep_spread_m: float = 0.0) -> float:
        """Weigh the particles by a log-likelihood a particle (the map update, :mod:`mapdb.navigation.map_update`),
        then keep the cloud at least ``keep_spread_m`` wide per axis (:meth:`_keep_spread`).  Returns the
        effective number of particles after the weighing, before any resampling."""
        ess = self._reweigh(loglik)
        self._keep_spread(keep_spread_m)
        return ess

    def _keep_spread(self, sigma_m: float) -> None:
        """Widen the cloud (positions only) so that its spread is at least ``sigma_m`` per axis.

        Adds ``N(0, sigma_m^2 - s^2)`` along each axis whose spread ``s`` is narrower: the mean stays where
        it is and the stated covariance no longer falls below an error the fixes share.
        """
        if sigma_m <= 0.0:
            return
        sd = np.sqrt(np.diag(_covariance(self.p, self.weights)))
        add = np.sqrt(np.maximum(sigma_m**2 - sd**2, 0.0))
        if np.any(add > 0.0):
            noise = self._normal(self.n)
            self.p = self.p + (add[0] * noise.real + 1j * add[1] * noise.imag)

    def _coverage(self, components: list[FixComponent], w: np.ndarray) -> float:
        """The cloud's weight inside the fix: ``sum_j pi_j sum_i w_i exp(-|p_i - c_j|^2 / 2 s_j^2)``.

        Times ``n``, about how many particles describe the posterior near the fix.  A cloud tighter than
        its error, a few metres from an accepted fix, has almost none there: reweighting would only pick
        its particles nearest the fix, still metres off, so the cloud is redrawn from the fix instead.
        """
        total = sum(c.weight for c in components)
        return float(sum((c.weight / total) * np.sum(w * np.exp(-0.5 * np.abs(self.p - c.centre) ** 2
                                                                  / max(c.sigma_m**2, 1e-12)))
                         for c in components))

    def _log_mixture(self, components: list[FixComponent]) -> np.ndarray:
        """``log sum_j pi_j N(p; c_j, s_j^2 I)`` at every particle, finite however far the particles are."""
        total = sum(c.weight for c in components)
        terms = np.empty((len(components), self.n))
        for j, c in enumerate(components):
            s2 = max(c.sigma_m**2, 1e-12)
            terms[j] = (math.log(c.weight / total) - 0.5 * np.abs(self.p - c.centre) ** 2 / s2
                        - math.log(2.0 * math.pi * s2))
        top = terms.max(axis=0)
        return np.asarray(top + np.log(np.exp(terms - top).sum(axis=0)))

    def _mixture(self, components: list[FixComponent], widen_m: float) -> np.ndarray:
        """``sum_j pi_j N(p; c_j, (s_j^2 + widen^2) I)`` at every particle."""
        total = sum(c.weight for c in components)
        g = np.zeros(self.n)
        for c in components:
            s2 = c.sigma_m**2 + widen_m**2
            g += (c.weight / total) * np.exp(-0.5 * np.abs(self.p - c.centre) ** 2 / s2) / (2.0 * math.pi * s2)
        return g

    def _redraw(self, components: list[FixComponent], w: np.ndarray) -> None:
        """New particles drawn from the fix's components, each chosen by its weight times the cloud's density
        there (a kernel estimate); velocities taken from the particles near each component.

        When a fix is much sharper than the cloud (the first fix, the first after a blackout), too few
        particles fall inside it for reweighting to describe the posterior: drawing from the fix does.
        """
        sd = np.sqrt(np.diag(_covariance(self.p, w)))
        h2 = max(float(np.max(sd)) * KERNEL_FRACTION, 1.0) ** 2
        near = np.empty((len(components), self.n))
        for j, c in enumerate(components):
            s2 = h2 + c.sigma_m**2
            near[j] = w * np.exp(-0.5 * np.abs(self.p - c.centre) ** 2 / s2) / s2
        mass = np.array([c.weight for c in components]) * near.sum(axis=1)
        if not np.isfinite(mass).all() or mass.sum() <= 0:
            # Every component far beyond the kernel (an accepted fix, but the cloud elsewhere): the fix's own
            # weights choose, rather than leaving the cloud unchanged behind a fix reported as applied.
            mass = np.array([c.weight for c in components], float)
        which = self.rng.choice(len(components), size=self.n, p=mass / mass.sum())
        p_new = np.empty(self.n, np.complex128)
        v_new = np.empty(self.n, np.complex128)
        for j in np.unique(which):
            mine = np.flatnonzero(which == j)
            c = components[int(j)]
            p_new[mine] = c.centre + c.sigma_m * self._normal(mine.size)
            source = near[j] / near[j].sum() if near[j].sum() > 0 else w
            v_new[mine] = self.v[self.rng.choice(self.n, size=mine.size, p=source)]
        self.p, self.v = p_new, v_new
        self.logw = np.full(self.n, -math.log(self.n))

    def _reweigh(self, loglik: np.ndarray) -> float:
        """Add ``loglik`` to the log weights, resampling when too few particles carry them; the effective
        number of particles after the weighing, before any resampling."""
        self.logw = self.logw + loglik
        self.logw -= self.logw.max()
        self.logw -= math.log(np.exp(self.logw).sum())
        ess = float(1.0 / np.sum(self.weights**2))
        if ess < RESAMPLE_FRACTION * self.n:
            self.resample()
        return ess

    def resample(self) -> None:
        """Systematic resampling, then a small jitter (module docs)."""
        w = self.weights
        positions = (self.rng.random() + np.arange(self.n)) / self.n
        index = np.minimum(np.searchsorted(np.cumsum(w), positions), self.n - 1)
        p_sd = np.sqrt(np.diag(_covariance(self.p, w)))
        v_sd = np.sqrt(np.diag(_covariance(self.v, w)))
        noise_p, noise_v = self._normal(self.n), self._normal(self.n)
        self.p = self.p[index] + JITTER * (p_sd[0] * noise_p.real + 1j * p_sd[1] * noise_p.imag)
        self.v = self.v[index] + JITTER * (v_sd[0] * noise_v.real + 1j * v_sd[1] * noise_v.imag)
        self.logw = np.full(self.n, -math.log(self.n))

    def inject(self, centre: complex, radius: float, share: float, velocity: complex | None = None) -> None:
        """Replace a ``share`` of the particles (resampled first) by draws in a disc around ``centre``."""
        self.resample()
        k = max(1, int(round(share * self.n)))
        chosen = self.rng.choice(self.n, size=k, replace=False)
        self.p[chosen] = self._disc(centre, radius, k)
        if velocity is not None:
            self.v[chosen] = velocity

    # ---------------------------------------------------------------------------------- estimates

    def estimate(self) -> tuple[complex, complex, np.ndarray, np.ndarray]:
        """Position (the heaviest mode's mean), velocity, and the 2x2 covariances of position and velocity.

        The position covariance is taken about the reported position over the whole cloud, so that a
        second mode shows as uncertainty.
        """
        w = self.weights
        wm = w * self._heaviest_mode(w)
        wm = wm / wm.sum() if wm.sum() > 0 else w
        position = complex(np.sum(wm * self.p))
        velocity = complex(np.sum(wm * self.v))
        return position, velocity, _covariance(self.p, w, position), _covariance(self.v, w, velocity)

    def _heaviest_mode(self, w: np.ndarray) -> np.ndarray:
        """Mask of the particles in the heaviest mode: the connected group of occupied grid cells (cells of
        ``MODE_CELL_M``, coarser for a cloud spread over kilometres) holding the most weight.  A unimodal
        cloud, however broad, is one group: its estimate is its mean."""
        from scipy.ndimage import label

        low = complex(self.p.real.min(), self.p.imag.min())
        extent = max(self.p.real.max() - low.real, self.p.imag.max() - low.imag)
        cell = max(MODE_CELL_M, extent / MODE_GRID)
        if extent <= 2.0 * cell:
            return np.ones(self.n, bool)
        ix = ((self.p.real - low.real) // cell).astype(np.int64)
        iy = ((self.p.imag - low.imag) // cell).astype(np.int64)
        grid = np.zeros((int(ix.max()) + 1, int(iy.max()) + 1), bool)
        grid[ix, iy] = True
        groups, count = label(grid, structure=np.ones((3, 3), bool))
        if count <= 1:
            return np.ones(self.n, bool)
        member = groups[ix, iy]
        return member == int(np.argmax(np.bincount(member, weights=w)))

    def radius(self, centre: complex, quantile: float = 0.99) -> float:
        """The distance from ``centre`` within which ``quantile`` of the weight lies."""
        w = self.weights
        d = np.abs(self.p - centre)
        order = np.argsort(d)
        cumulative = np.cumsum(w[order])
        return float(d[order][min(int(np.searchsorted(cumulative, quantile)), self.n - 1)])


def _covariance(z: np.ndarray, w: np.ndarray, about: complex | None = None) -> np.ndarray:
    """Weighted 2x2 covariance of complex points (about their mean, or ``about``)."""
    centre = complex(np.sum(w * z)) if about is None else about
    d = z - centre
    xx, yy, xy = np.sum(w * d.real**2), np.sum(w * d.imag**2), np.sum(w * d.real * d.imag)
    return np.array([[xx, xy], [xy, yy]])
