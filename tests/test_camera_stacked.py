"""Several cameras' projections at once (mapdb.camera.rotations_body_to_ned, project_to_images) against one camera's
(rotation_body_to_ned, project_to_image): the same numbers, bit for bit, whichever points go with them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapdb.camera import (
    Camera,
    Pose,
    in_image,
    project_to_image,
    project_to_images,
    rotation_body_to_ned,
    rotations_body_to_ned,
)

# Angles where a rounding could show: the axes, their neighbours, whole turns, negative and large ones.
EDGE_DEG = [0.0, -0.0, 90.0, 180.0, 270.0, 360.0, -90.0, 45.0, 1e-300, 5e-324, 89.999999, 720.5, -1e4, 1e-9]


def _attitudes(rng: np.random.Generator, n: int, tilt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return rng.uniform(0.0, 360.0, n), rng.normal(0.0, tilt, n), rng.normal(0.0, tilt, n)


def test_numpys_trigonometry_is_maths() -> None:
    # The stacked rotations take numpy's cos, sin and radians where one camera's take math's.
    x = np.concatenate([np.random.default_rng(0).uniform(-720.0, 720.0, 20_000), EDGE_DEG])
    r = np.radians(x)
    assert r.tolist() == [math.radians(a) for a in x.tolist()]
    assert np.cos(r).tolist() == [math.cos(a) for a in r.tolist()]
    assert np.sin(r).tolist() == [math.sin(a) for a in r.tolist()]


@pytest.mark.parametrize("tilt", [0.05, 5.0, 40.0])
def test_rotations_are_each_cameras(tilt: float) -> None:
    yaw, pitch, roll = _attitudes(np.random.default_rng(1), 500, tilt)
    edges = np.array(np.meshgrid(EDGE_DEG, EDGE_DEG[:6], EDGE_DEG[:6])).reshape(3, -1)
    yaw, pitch, roll = (np.concatenate([a, e]) for a, e in zip((yaw, pitch, roll), edges, strict=True))
    stacked = rotations_body_to_ned(yaw, pitch, roll)
    assert stacked.shape == (yaw.size, 3, 3)
    for k in range(yaw.size):
        one = rotation_body_to_ned(float(yaw[k]), float(pitch[k]), float(roll[k]))
        assert np.array_equal(stacked[k], one), (yaw[k], pitch[k], roll[k])
    assert rotations_body_to_ned([], [], []).shape == (0, 3, 3)
    assert np.array_equal(rotations_body_to_ned(10.0, 2.0, 3.0)[0], rotation_body_to_ned(10.0, 2.0, 3.0))


@pytest.mark.parametrize("tilt", [0.05, 3.0, 60.0])  # 60: points behind the camera and on its horizon
def test_pixels_are_each_cameras_whichever_points_go_with_them(tilt: float) -> None:
    rng = np.random.default_rng(2)
    camera = Camera(640, 480, 45.0)
    for _ in range(40):
        n, m = int(rng.integers(1, 17)), int(rng.integers(1, 400))
        cx, cy = rng.uniform(0.0, 100.0, n), rng.uniform(0.0, 100.0, n)
        yaw, pitch, roll = _attitudes(rng, n, tilt)
        x, y = rng.uniform(-300.0, 400.0, m), rng.uniform(-300.0, 400.0, m)
        x[:n], y[:n] = cx, cy  # points right under a camera
        u, v = project_to_images(x - cx[:, None], y - cy[:, None], 150.0, rotations_body_to_ned(yaw, pitch, roll),
                                 camera)
        assert u.shape == v.shape == (n, m)
        for s in range(n):
            pose = Pose(float(cx[s]), float(cy[s]), 150.0, float(yaw[s]), float(roll[s]), float(pitch[s]))
            some = np.sort(rng.choice(m, int(rng.integers(1, m + 1)), replace=False))
            for points in (some, some[:1], np.arange(m)):
                one = project_to_image(x[points], y[points], pose, camera)
                assert np.array_equal(u[s, points], one[0], equal_nan=True)
                assert np.array_equal(v[s, points], one[1], equal_nan=True)
    none = project_to_images(np.zeros((n, 0)), np.zeros((n, 0)), 150.0, rotations_body_to_ned(yaw, pitch, roll), camera)
    assert none[0].shape == (n, 0)


def test_in_image_is_the_simulators_test() -> None:
    camera = Camera(640, 480, 45.0)
    u = np.array([0.0, -1e-12, 639.999, 640.0, np.nan, np.inf, -np.inf, 320.0, 320.0])
    v = np.array([0.0, 5.0, 479.0, 5.0, 5.0, 5.0, 5.0, np.nan, 480.0])
    want = np.isfinite(u) & (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
    assert in_image(u, v, camera).tolist() == want.tolist() == [True, False, True, False, False, False, False,
                                                                False, False]
