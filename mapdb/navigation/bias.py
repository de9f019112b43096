"""The frame-to-frame velocity's persistent error, measured against the applied fixes.

Frame-to-frame velocity carries errors that do not average out from frame to frame: whole rooftops of tall
buildings move faster across the image than the ground (relief parallax: measured +0.25 m/s at 20 m/s over
Monaco at 120 m), blobs cut by the border move slower (Andorra, -0.3 to -0.7 m/s over stretches where most
blobs are cut), the scale and heading taken from the last fix are a little off.  Each makes the measured
displacement a nearly fixed complex multiple of the true one::

    true displacement = (1 + c) measured displacement        (c complex: scale and rotation errors)

:class:`VelocityBias` estimates ``c`` from the flight itself.  Between two applied fixes at least
``MIN_SPAN_S`` apart, the fixes' displacement ``dF`` and the sum of the frame-to-frame displacements ``dM``
(the filter's velocity, unbiased back, on frames without a measurement) give one sample
``c_k = (dF - dM) / dM`` of weight ``w_k = |dM|^2 / s_k^2``, ``s_k^2`` the two fixes' variances (per axis,
summed): over 5 s at 20 m/s and fixes of 0.3 m, a sample is good to 0.4 % (0.08 m/s).  Samples are
weighted by ``FORGET`` per newer sample (the bias changes with the buildings below, so about the last
``1 / (1 - FORGET)`` samples count), with a prior ``c = 0`` of weight ``1 / PRIOR_SIGMA^2``:

    c = sum f_k w_k c_k / (1 / PRIOR_SIGMA^2 + sum f_k w_k)

The navigator multiplies each frame-to-frame velocity by ``1 + c_applied`` (:meth:`VelocityBias.correct`),
``c_applied`` by ``mode`` (the navigator's ``velocity_bias`` option): ``"scale"`` (the default) its real
part, the scale at which the blobs move against the scale the last fix gave (below); ``"full"`` the
estimate ``c``; ``"off"`` nothing (the estimate only sizes the allowance); ``"fixed"`` nothing, and the
allowance always the prior's below; ``"significant"`` its real part (the scale) and
its imaginary part (the rotation) each only when beyond ``SIGNIFICANT`` standard errors, after
``MIN_SAMPLES`` samples (an estimate within its noise would only add that noise to the velocity).  The
standard error per axis is ``sqrt(1 / W + excess / (2 n))``, ``excess`` the samples' spread beyond their
fixes' errors (below) and ``n`` the forgetting-weighted number of samples.

**Why the scale only.**  Measured on the rendered-mask flights of ``benchmarks/navigation_masks.py`` (3 km,
120 m, buildings with heights; ``benchmarks/diagnostics/velocity_bias.py`` splits the error by cause): the
bias is a scale error, never a rotation.  A fix's similarity absorbs the mean relief displacement of the
buildings it matched (roofs lie ``H / (H - h)`` of their footprints' distance from the nadir) as a scale
1.2-1.7 % too small, while the frame-to-frame motion is a mean of whole blobs, roofs moving ``H / (H - h)``
faster than the ground and ground objects (road intersections, parks) at its speed, weighed unlike the fix
(Andorra's large blocks are mostly cut, so its motion is mostly ground objects'): -0.24 m/s along track
over Andorra, +0.10 over Monaco, the across-track part 0.01 m/s from the heading.  The rotation part of
``c`` from 5 s fix pairs is noise of a few tenths of a percent (the fixes' own heading is better), which
``"full"`` turned into across-track error (+0.17 m/s over Andorra in an earlier run) and up to 4 points fewer
frames within 2 m than ``"scale"`` over Andorra (same run as below).  Taken out, the scale leaves -0.01 / +0.02 m/s
along over Andorra (heights / 15 % of buildings missing from the map) and +0.08 / +0.08 over Monaco
(standard errors 0.07-0.11), within 5 m 93 -> 97 % and 91 -> 95 % over Andorra; ideal-centroid flights
unchanged (|bias| <= 0.02 m/s).

**The drift allowance** (:meth:`VelocityBias.drift`, the particle filter's ``sigma_b``, :mod:`.filter`) is
what remains of the error after that correction, per axis, as a fraction of the speed: the estimate's own
uncertainty ``1 / sqrt(total weight)`` and, when the samples scatter more than their fix errors explain
(the bias changing from stretch to stretch, velocity noise integrated over the span), that excess spread::

    sigma_c^2 = 1 / W + max(0, var_w(c_k) - 2 mean_w(1 / w_k)) / 2 + |c - c_applied|^2 / 2
                                                         (per axis; var_w over both)

the last term the part of the estimate ``mode`` leaves in the velocity.

Until ``MIN_SAMPLES`` samples exist the allowance is the prior's (``DRIFT_FLOOR_MPS + PRIOR_SIGMA |v|``,
0.7 m/s at 20 m/s: a 1 degree heading bias and rooftops before any fix could measure them); after, the
floor is ``CALIBRATED_FLOOR_MPS``.  On ideal centroid flights the samples agree to their fix errors and the
allowance falls to a few hundredths of a metre per second, the drift those flights have; on rendered masks
it stays at the spread the stretches show.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

__all__ = ["BIAS_MODES", "CALIBRATED_FLOOR_MPS", "DRIFT_FLOOR_MPS", "FORGET", "MIN_SAMPLES", "MIN_SPAN_S",
           "PRIOR_SIGMA", "SIGNIFICANT", "VelocityBias"]

# Before any sample: the allowance of the consistent filter (0.1 m/s + 3 % of the speed, module docs).
DRIFT_FLOOR_MPS = 0.1
PRIOR_SIGMA = 0.03
# A sample needs fixes at least this far apart: over shorter spans the fixes' own errors swamp the bias.
MIN_SPAN_S = 5.0
# Spans longer than this (a long gap) say as much as this one would: the bias may have changed within it.
MAX_SPAN_S = 60.0
# Weight kept by a sample for each newer one (about the last 10 samples, 50 s or more, count).
FORGET = 0.9
MIN_SAMPLES = 3
CALIBRATED_FLOOR_MPS = 0.02
# A sample farther than this from the estimate is a bad fix pair (never a bias of tens of percent): ignored.
MAX_SAMPLE = 0.2
# The estimate is never taken beyond this (a tenth of the speed).
MAX_C = 0.1
# What is taken out of the velocity: "scale" its real part (module docs), "full" the estimate, "off" nothing
# (the estimate only sizes the allowance), "significant" its scale and its rotation each only when beyond
# SIGNIFICANT standard errors, "fixed" nothing and the allowance always the prior's (an older rule).
BIAS_MODES = ("full", "off", "significant", "fixed", "scale")
SIGNIFICANT = 2.0


@dataclass
class _Anchor:
    time_s: float
    place: complex
    var_m2: float  # the fix's variance per axis
    measured: complex = 0j  # the frame-to-frame displacement summed since


@dataclass
class VelocityBias:
    """The estimate of the module docs: feed it each frame's displacement and each applied fix.

    Examples
    --------
    A velocity measured 5 % fast, fixes every 5 s on the truth (20 m/s east):

    >>> b = VelocityBias()
    >>> for k in range(8):
    ...     b.add_fix(5.0 * k, complex(100.0 * k, 0.0), 0.09)
    ...     for _ in range(25):
    ...         b.add_displacement(21.0 * 0.2)
    >>> round(b.c.real, 3), b.samples
    (-0.047, 7)
    """

    c: complex = 0j
    samples: int = 0
    mode: str = "full"  # of BIAS_MODES: what :meth:`correct` takes out
    _weight: float = 0.0  # sum f_k w_k
    _sum_c: complex = 0j  # sum f_k w_k c_k
    _sum_c2: float = 0.0  # sum f_k w_k |c_k|^2
    _sum_n: float = 0.0  # sum f_k (the noise terms w_k / w_k)
    _count: float = 0.0  # sum f_k
    _anchor: _Anchor | None = field(default=None)

    def copy(self) -> VelocityBias:
        """An independent copy (the navigator's snapshot of a frame)."""
        return replace(self, _anchor=None if self._anchor is None else replace(self._anchor))

    def reset(self) -> None:
        """Forget the anchor (a restart of the filter); the estimate stays."""
        self._anchor = None

    @property
    def applied(self) -> complex:
        """The part of the estimate :meth:`correct` takes out (``mode``, :data:`BIAS_MODES`)."""
        if self.mode in ("off", "fixed") or (self.mode == "significant" and self.samples < MIN_SAMPLES):
            return 0j
        if self.mode == "full":
            return self.c
        if self.mode == "scale":
            return complex(self.c.real, 0.0)
        # Significant: an estimate within its noise would only add that noise to a better velocity.
        se = SIGNIFICANT * self.standard_error()
        return complex(self.c.real if abs(self.c.real) > se else 0.0, self.c.imag if abs(self.c.imag) > se else 0.0)

    def standard_error(self) -> float:
        """The estimate's standard error per axis: the fixes' share and the samples' excess spread's."""
        if self._weight <= 0.0:
            return PRIOR_SIGMA
        total = PRIOR_SIGMA**-2 + self._weight
        return math.sqrt(1.0 / total + self._excess() / 2.0 / max(self._count, 1.0))

    def _excess(self) -> float:
        """The samples' spread (both axes) beyond what the fixes' errors alone give it."""
        mean = self._sum_c / self._weight
        spread = max(self._sum_c2 / self._weight - abs(mean) ** 2, 0.0)  # var_w(c_k), both axes
        noise = 2.0 * self._sum_n / self._weight
        return max(spread - noise, 0.0)

    def correct(self, v: complex) -> complex:
        """The velocity (or displacement) with the estimated bias taken out."""
        return v * (1.0 + self.applied)

    def uncorrect(self, v: complex) -> complex:
        """The raw measurement a corrected velocity corresponds to (the filter's, on frames without one)."""
        return v / (1.0 + self.applied)

    def add_displacement(self, raw: complex) -> None:
        """One frame's frame-to-frame displacement (metres, as measured, uncorrected)."""
        if self._anchor is not None:
            self._anchor.measured += raw

    def add_frame(self, measured: complex | None, filter_velocity: complex | None, dt: float) -> None:
        """One frame's step of ``dt`` seconds: the velocity measured (uncorrected) when the filter used it,
        else the filter's velocity unbiased back (module docs); neither: nothing is added."""
        if measured is not None:
            self.add_displacement(measured * dt)
        elif filter_velocity is not None:
            self.add_displacement(self.uncorrect(filter_velocity) * dt)

    def add_fix(self, time_s: float, place: complex, var_m2: float) -> None:
        """An applied fix at ``place`` with per-axis variance ``var_m2``: a sample when the anchor is far
        enough back, and the new anchor (module docs)."""
        a = self._anchor
        if a is not None and time_s - a.time_s < MIN_SPAN_S:
            return
        if a is not None and time_s - a.time_s <= MAX_SPAN_S and abs(a.measured) > 1.0:
            self._sample((place - a.place - a.measured) / a.measured,
                         abs(a.measured) ** 2 / max(a.var_m2 + var_m2, 1e-6))
        self._anchor = _Anchor(time_s, place, var_m2)

    def _sample(self, c_k: complex, w_k: float) -> None:
        if abs(c_k - self.c) > MAX_SAMPLE:
            return
        self._weight, self._sum_c, self._sum_c2 = FORGET * self._weight, FORGET * self._sum_c, FORGET * self._sum_c2
        self._sum_n, self._count = FORGET * self._sum_n, FORGET * self._count
        self._weight += w_k
        self._sum_c += w_k * c_k
        self._sum_c2 += w_k * abs(c_k) ** 2
        self._sum_n += 1.0
        self._count += 1.0
        self.samples += 1
        c = self._sum_c / (PRIOR_SIGMA**-2 + self._weight)
        self.c = c if abs(c) <= MAX_C else c / abs(c) * MAX_C

    def drift(self, speed_mps: float, least_mps: float = 0.0) -> float:
        """The per-axis velocity error allowed between fixes (m/s), the filter's ``sigma_b`` (module docs), at
        least ``least_mps`` (an inertial velocity's stated error: its bias is not measured here)."""
        return max(self._drift(speed_mps), least_mps)

    def _drift(self, speed_mps: float) -> float:
        if self.samples < MIN_SAMPLES or self.mode == "fixed":
            return DRIFT_FLOOR_MPS + PRIOR_SIGMA * speed_mps
        total = PRIOR_SIGMA**-2 + self._weight
        # The part of the estimate left in the velocity (mode) is error the allowance must hold too.
        left = abs(self.c - self.applied) ** 2 / 2.0
        sigma_c = math.sqrt(1.0 / total + self._excess() / 2.0 + left)
        return CALIBRATED_FLOOR_MPS + min(sigma_c, MAX_C) * speed_mps
