"""Issue 29: the frame-to-frame velocity's persistent error measured against the applied fixes
(:mod:`mapdb.navigation.bias`): it corrects the velocity and sizes the filter's drift allowance."""

from __future__ import annotations

import cmath

import numpy as np
import pytest
from navworld import fly, synthetic_world

from mapdb.navigation.bias import BIAS_MODES, DRIFT_FLOOR_MPS, MIN_SAMPLES, PRIOR_SIGMA, SIGNIFICANT, VelocityBias
from mapdb.navigation.navigator import Navigator, NavigatorOptions

world = pytest.fixture(scope="module", name="world")(synthetic_world)  # the synthetic world (tests/navworld.py)


def _fly(bias: VelocityBias, true_c: complex, seconds: float, fix_std: float, seed: int = 0,
         frame_std: float = 0.0) -> None:
    """Fixes every 5 s at the truth (plus noise), 25 frames between them measured with ``1 / (1 + c)`` of
    the true displacement (plus noise): the estimate should find ``c``."""
    rng = np.random.default_rng(seed)
    truth = 0j
    step = 20.0 * 0.2 * cmath.exp(0.3j)
    for k in range(int(seconds / 5.0) + 1):
        noise = fix_std * complex(*rng.standard_normal(2))
        bias.add_fix(5.0 * k, truth + noise, fix_std**2)
        for _ in range(25):
            truth += step
            bias.add_displacement(step / (1.0 + true_c) + frame_std * complex(*rng.standard_normal(2)))


def test_the_bias_is_found_and_taken_out() -> None:
    # 4 % fast and turned by half a degree (rooftops, a heading a little off): found within a few tenths of
    # a percent from fixes good to 0.3 m, and the corrected velocity is the true one.
    c = -0.04 + 0.009j
    bias = VelocityBias()
    _fly(bias, c, 120.0, 0.3)
    assert bias.samples >= 20
    assert abs(bias.c - c) < 0.003, bias.c
    assert abs(bias.correct(20.0 / (1.0 + c)) - 20.0) < 0.06


def test_the_allowance_falls_on_consistent_fixes_and_stays_on_scattered_ones() -> None:
    prior = DRIFT_FLOOR_MPS + PRIOR_SIGMA * 20.0
    fresh = VelocityBias()
    assert fresh.drift(20.0) == pytest.approx(prior)  # nothing measured yet: the prior's allowance
    steady = VelocityBias()
    _fly(steady, 0.01, 120.0, 0.1)
    assert steady.samples >= MIN_SAMPLES and steady.drift(20.0) < 0.06, steady.drift(20.0)
    # A velocity whose error changes from stretch to stretch (frame noise that sums to metres over 5 s):
    # the samples scatter far beyond their fixes' errors, and the allowance keeps that spread.
    noisy = VelocityBias()
    _fly(noisy, 0.0, 120.0, 0.1, frame_std=0.5)
    assert noisy.drift(20.0) > 3.0 * steady.drift(20.0), (noisy.drift(20.0), steady.drift(20.0))


def test_a_wild_fix_pair_is_not_taken_as_a_bias() -> None:
    bias = VelocityBias()
    _fly(bias, 0.0, 60.0, 0.1)
    before = bias.c
    bias.add_displacement(100.0 + 0j)
    bias.add_fix(1000.0, 10_000.0 + 0j, 0.01)  # a span too long, then a fix a kilometre off
    bias.add_displacement(100.0 + 0j)
    bias.add_fix(1006.0, 10_000.0 + 500.0 + 0j, 0.01)
    assert bias.c == before


def test_an_ideal_flight_calibrates_and_narrows_the_drift_allowance(world) -> None:
    # Centroid detections fixed nearly every frame: after 26 s (5 samples) the allowance is measured, far under the
    # prior's 0.1 m/s + 3 % of the speed, and the velocity's bias is under a tenth of a percent of it.
    frames = fly(world, 26.0, fps=2.5)
    start = frames[0]["truth"]
    navigator = Navigator(world, initial=(start["x"], start["y"], 20.0))
    for f in frames:
        navigator.step(f)
    assert navigator.bias.samples >= MIN_SAMPLES
    assert navigator.bias.drift(20.0) < 0.5 * (DRIFT_FLOOR_MPS + PRIOR_SIGMA * 20.0), navigator.bias.drift(20.0)
    assert abs(navigator.bias.c) < 0.01


def test_significant_mode_takes_out_only_what_stands_above_its_noise() -> None:
    # A 4 % scale error and no rotation, fixes good to 0.5 m: the scale is taken out, the rotation estimate
    # (noise only) is not; a velocity without bias is left as measured.
    biased = VelocityBias(mode="significant")
    _fly(biased, -0.04, 120.0, 0.5, seed=3)
    se = biased.standard_error()
    assert abs(biased.c.real) > SIGNIFICANT * se and biased.applied.real == biased.c.real
    assert biased.c.imag != 0.0 and abs(biased.c.imag) < SIGNIFICANT * se and biased.applied.imag == 0.0
    unbiased = VelocityBias(mode="significant")
    _fly(unbiased, 0.0, 120.0, 0.5, seed=4)
    assert unbiased.c != 0j and unbiased.applied == 0j
    assert unbiased.correct(20.0 + 0j) == 20.0 + 0j


def test_off_mode_corrects_nothing_and_allows_for_the_bias_it_leaves() -> None:
    full, off = VelocityBias(mode="full"), VelocityBias(mode="off")
    for b in (full, off):
        _fly(b, -0.04, 120.0, 0.3)
    assert off.c == full.c and off.applied == 0j and off.correct(20.0 + 0j) == 20.0 + 0j
    # The 4 % left in the velocity (0.8 m/s at 20 m/s, 0.57 per axis) is in the allowance.
    assert off.drift(20.0) > 0.5 > full.drift(20.0), (off.drift(20.0), full.drift(20.0))
    fixed = VelocityBias(mode="fixed")  # main's rule: no correction, the prior's allowance throughout
    _fly(fixed, -0.04, 120.0, 0.3)
    assert fixed.c == full.c and fixed.applied == 0j
    assert fixed.drift(20.0) == pytest.approx(DRIFT_FLOOR_MPS + PRIOR_SIGMA * 20.0)


def test_the_navigator_takes_its_mode_from_the_options(world) -> None:
    for mode in BIAS_MODES:
        assert Navigator(world, options=NavigatorOptions(velocity_bias=mode)).bias.mode == mode


def test_scale_mode_takes_out_the_scale_and_allows_for_the_rotation_it_leaves() -> None:
    # A 4 % scale error and a quarter-degree turn: the scale is taken out, the rotation (which the fixes'
    # own heading measures better) is left in the velocity and in the allowance.
    scale, full = VelocityBias(mode="scale"), VelocityBias(mode="full")
    for b in (scale, full):
        _fly(b, -0.04 + 0.0045j, 120.0, 0.3)
    assert scale.c == full.c and scale.applied == complex(full.c.real, 0.0)
    assert abs(scale.correct(20.0 / (1.0 - 0.04)).real - 20.0) < 0.06
    assert scale.drift(20.0) > full.drift(20.0)
