"""The pinhole camera model shared by the simulator, the localizer and the pictures.

A camera fixed to an aircraft looks down at flat ground: :func:`project_to_image`
maps ground points to pixels, :func:`image_to_ground` is its inverse,
:func:`level_pixels` removes a known roll and pitch.  Only numpy is needed, so
that the localizer can import it without the simulator's dependencies.

Frames and sign conventions
---------------------------
* **Map**: ``x`` east, ``y`` north (projected metres), ground at ``z = 0``, ``z`` up.
* **Aircraft body**: forward-right-down (FRD).  Its attitude against local
  north-east-down (NED) is the aerospace Z-Y-X Euler sequence
  ``R_body_to_ned = Rz(yaw) @ Ry(pitch) @ Rx(roll)``:

  - ``yaw`` (= heading) is measured clockwise from north: 0 flies north, 90 flies east;
  - ``pitch`` is positive nose up;
  - ``roll`` is positive right wing down.
* **Camera**: fixed to the body, optical axis along body *down*; image *right*
  is body right and image *up* is body forward.  Pixels: ``u`` (x) to the
  right, ``v`` (y) down, (0, 0) the top-left corner of the top-left pixel, the
  principal point at ``(width / 2, height / 2)``, square pixels, focal length
  ``f = (width / 2) / tan(fov_deg / 2)`` with ``fov_deg`` the *horizontal* field of view.

Projection of a map point ``(X, Y, 0)`` seen from a camera at ``(x, y, altitude)``::

    n = (Y - y, X - x, altitude)                  # NED vector camera -> point
    (f_b, r_b, d_b) = R_body_to_ned.T @ n         # the same vector in the body frame
    u = width / 2 + f * r_b / d_b
    v = height / 2 - f * f_b / d_b

What each angle does to the view:

* ``yaw = 0``: image up is map north and image right is map east (a map seen
  from above, not mirrored).  ``yaw = psi``: image up points along the heading
  ``psi``, so map north appears rotated *counter-clockwise* by ``psi`` on the
  displayed image (at ``yaw = 90`` north points to the image's left edge).
* ``pitch > 0`` (nose up): the optical axis tilts forward; the ground point
  under the image centre lies ``altitude * tan(pitch)`` ahead of the aircraft and
  the nadir (the point straight below the camera) appears *below* the image
  centre (``v > height / 2``).
* ``roll > 0`` (right wing down): the optical axis tilts to the left; the ground
  point under the image centre lies ``altitude * tan(roll)`` to the left and the
  nadir appears *right* of the image centre (``u > width / 2``).

:func:`level_pixels` removes a known roll and pitch (it re-projects pixels to
those of a level camera at the same place and heading, in which the nadir is
the image centre); :func:`image_to_ground` is the full inverse projection.

Examples
--------
>>> cam = Camera(640, 480, 35.0)
>>> u, v = project_to_image([500.0], [1000.0], Pose(500.0, 1000.0, 100.0), cam)
>>> float(u[0]), float(v[0])
(320.0, 240.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "Camera",
    "Pose",
    "footprint",
    "image_plane",
    "image_to_ground",
    "level_pixels",
    "nadir_pixel",
    "in_image",
    "project_points",
    "project_to_image",
    "project_to_images",
    "rotation_body_to_ned",
    "rotations_body_to_ned",
]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size in pixels and horizontal field of view in degrees.

    The size may be fractional: the localizer sizes the camera as an image document gives it.
    """

    width: float = 640
    height: float = 480
    fov_deg: float = 35.0

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"field of view must be in (0, 180) degrees, got {self.fov_deg}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return (self.width / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)

    def gsd(self, altitude: float) -> float:
        """Ground size of a pixel at the image centre of a level camera (metres per pixel)."""
        return altitude / self.focal_px

    def footprint_m(self, altitude: float) -> tuple[float, float]:
        """Ground width and height (metres) seen by a level camera at ``altitude``."""
        g = self.gsd(altitude)
        return self.width * g, self.height * g


@dataclass(frozen=True)
class Pose:
    """Camera position (map metres, altitude above ground) and attitude in degrees (see module docs)."""

    x: float
    y: float
    altitude: float
    yaw_deg: float = 0.0
    roll_deg: float = 0.0
    pitch_deg: float = 0.0


def rotation_body_to_ned(yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``: body (forward, right, down) vectors to (north, east, down)."""
    cy, sy = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    cp, sp = math.cos(math.radians(pitch_deg)), math.sin(math.radians(pitch_deg))
    cr, sr = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def rotations_body_to_ned(yaw_deg: npt.ArrayLike, pitch_deg: npt.ArrayLike, roll_deg: npt.ArrayLike) -> np.ndarray:
    """(n, 3, 3): :func:`rotation_body_to_ned` of each of ``n`` attitudes, the same numbers.

    The same products, one 3 x 3 matrix at a time (numpy's stacked ``@`` calls BLAS once a matrix, with the
    strides of one matrix), of the same cosines and sines (numpy's ``cos``, ``sin`` and ``radians`` give
    ``math``'s numbers: ``tests/test_camera_stacked.py``); the written-out product would differ in the last bit
    where the compiled product fuses a multiply and an add.

    Examples
    --------
    >>> r = rotations_body_to_ned([30.0, 200.0], [1.0, -2.0], [0.5, 3.0])
    >>> r.shape, bool((r[1] == rotation_body_to_ned(200.0, -2.0, 3.0)).all())
    ((2, 3, 3), True)
    """
    yaw, pitch, roll = (np.radians(np.asarray(a, np.float64).reshape(-1)) for a in (yaw_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    zero, one = np.zeros(cy.size), np.ones(cy.size)
    rz = np.stack([cy, -sy, zero, sy, cy, zero, zero, zero, one], axis=1).reshape(-1, 3, 3)
    ry = np.stack([cp, zero, sp, zero, one, zero, -sp, zero, cp], axis=1).reshape(-1, 3, 3)
    rx = np.stack([one, zero, zero, zero, cr, -sr, zero, sr, cr], axis=1).reshape(-1, 3, 3)
    return rz @ ry @ rx


def _body_to_pixels(frd: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame vectors (..., 3, n) -> pixels (..., n); NaN for points not in front of the camera."""
    down = frd[..., 2, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(down > 0.0, down, np.nan)
        # f * front / d and f * right / d, the two rows in one product and one quotient.
        scaled = camera.focal_px * frd[..., :2, :]
        scaled /= d[..., None, :]
    return camera.width / 2.0 + scaled[..., 1, :], camera.height / 2.0 - scaled[..., 0, :]


def _pixels_to_body(u: npt.ArrayLike, v: npt.ArrayLike, camera: Camera) -> np.ndarray:
    """Pixels -> body-frame ray directions (3, n) with unit down component."""
    f = camera.focal_px
    uu = np.asarray(u, dtype=np.float64).reshape(-1)
    vv = np.asarray(v, dtype=np.float64).reshape(-1)
    return np.stack([-(vv - camera.height / 2.0) / f, (uu - camera.width / 2.0) / f, np.ones_like(uu)])


def project_to_image(
    x: npt.ArrayLike, y: npt.ArrayLike, pose: Pose, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions of ground points ``(x, y, 0)`` seen from ``pose``.

    Points behind the camera (or on its horizon) get NaN; points outside the
    image are returned as they are (callers decide what is visible).

    Examples
    --------
    A point 10 m north of a level camera at 100 m, heading north, is ``10 * f / 100`` pixels above the centre:

    >>> cam = Camera(640, 480, 35.0)
    >>> u, v = project_to_image([0.0], [10.0], Pose(0.0, 0.0, 100.0), cam)
    >>> round(float(u[0]), 6), round(float(240.0 - v[0]), 6) == round(cam.focal_px / 10.0, 6)
    (320.0, True)
    """
    return project_points(x, y, 0.0, pose, camera)


def project_points(
    x: npt.ArrayLike, y: npt.ArrayLike, z: npt.ArrayLike, pose: Pose, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of map points ``(x, y, z)``, ``z`` metres above the ground (:func:`project_to_image` generalised to a
    height; NaN for points at or above the camera).

    Examples
    --------
    A roof corner 20 m up, 30 m east of a level camera at 120 m, appears 30 * f / 100 pixels right of
    the centre, where its footprint appears at 30 * f / 120:

    >>> cam = Camera(640, 480, 60.0)
    >>> u, v = project_points([30.0, 30.0], [0.0, 0.0], [0.0, 20.0], Pose(0.0, 0.0, 120.0), cam)
    >>> [round(float(d / cam.focal_px), 6) for d in u - 320.0]
    [0.25, 0.3]
    """
    xs = np.asarray(x, dtype=np.float64).reshape(-1)
    ys = np.asarray(y, dtype=np.float64).reshape(-1)
    zs = np.broadcast_to(np.asarray(z, dtype=np.float64), xs.shape)
    ned = np.stack([ys - pose.y, xs - pose.x, pose.altitude - zs])
    frd = rotation_body_to_ned(pose.yaw_deg, pose.pitch_deg, pose.roll_deg).T @ ned
    return _body_to_pixels(frd, camera)


def project_to_images(east: np.ndarray, north: np.ndarray, altitude: float, rotations: np.ndarray,
                      camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (cameras, points) of ground points seen from several cameras at one ``altitude`` with attitudes
    ``rotations`` (:func:`rotations_body_to_ned`), the points given by their offsets (cameras, points) from each
    camera, ``east = x - cam_x`` and ``north = y - cam_y``: each row :func:`project_to_image`'s numbers for that
    camera, bit for bit, whichever points are projected with it (the stacked product is BLAS's product of each
    camera's matrix, column by column).

    Examples
    --------
    >>> cam = Camera(640, 480, 45.0)
    >>> x, y = np.array([3.0, -40.0, 25.0]), np.array([10.0, 7.0, -30.0])
    >>> cx, cy = np.array([0.0, 5.0]), np.array([1.0, 2.0])
    >>> u, v = project_to_images(x - cx[:, None], y - cy[:, None], 120.0,
    ...                          rotations_body_to_ned([10.0, 250.0], [0.5, 1.0], [-1.0, 0.2]), cam)
    >>> one = project_to_image(x[1:], y[1:], Pose(5.0, 2.0, 120.0, 250.0, 0.2, 1.0), cam)
    >>> bool((u[1, 1:] == one[0]).all() and (v[1, 1:] == one[1]).all())
    True
    """
    ned = np.empty((east.shape[0], 3, east.shape[1]))
    ned[:, 0], ned[:, 1], ned[:, 2] = north, east, altitude
    return _body_to_pixels(rotations.transpose(0, 2, 1) @ ned, camera)


def in_image(u: np.ndarray, v: np.ndarray, camera: Camera) -> np.ndarray:
    """Whether pixels lie inside the image: ``0 <= u < width`` and ``0 <= v < height`` (False for NaN).

    Examples
    --------
    >>> in_image(np.array([0.0, 640.0, np.nan, 10.0]), np.array([0.0, 5.0, 5.0, 479.5]), Camera()).tolist()
    [True, False, False, True]
    """
    return (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def image_to_ground(
    u: npt.ArrayLike, v: npt.ArrayLike, pose: Pose, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """Map ``(x, y)`` of the ground points seen at pixels ``(u, v)``: the inverse of :func:`project_to_image`.

    NaN where the pixel's ray does not reach the ground (at or above the horizon).
    """
    ned = rotation_body_to_ned(pose.yaw_deg, pose.pitch_deg, pose.roll_deg) @ _pixels_to_body(u, v, camera)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(ned[2] > 0.0, pose.altitude / ned[2], np.nan)
    return pose.x + t * ned[1], pose.y + t * ned[0]


def level_pixels(
    u: npt.ArrayLike,
    v: npt.ArrayLike,
    camera: Camera,
    roll_deg: float = 0.0,
    pitch_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Where pixels seen with ``roll_deg``/``pitch_deg`` would be in a level camera (same place and heading).

    A homography that needs neither altitude nor heading, only the field of
    view: after it, the camera nadir is the image centre and the image is a
    similarity of the map (for flat ground).  NaN for pixels at or above the horizon.

    Examples
    --------
    >>> cam = Camera(640, 480, 35.0)
    >>> u, v = nadir_pixel(cam, roll_deg=2.0, pitch_deg=-1.0)
    >>> [round(float(c), 9) for c in np.concatenate(level_pixels(u, v, cam, 2.0, -1.0))]
    [320.0, 240.0]
    """
    level = rotation_body_to_ned(0.0, pitch_deg, roll_deg) @ _pixels_to_body(u, v, camera)
    return _body_to_pixels(level, camera)


def image_plane(u: npt.ArrayLike, v: npt.ArrayLike, width: float, height: float) -> np.ndarray:
    """Pixels as the matcher sees them: complex ``x + iy`` from the image centre, ``y`` up (pixels have it down).

    Examples
    --------
    >>> image_plane([0.0, 640.0], [0.0, 240.0], 640, 480).tolist()
    [(-320+240j), (320+0j)]
    >>> image_plane([], [], 640, 480).size
    0
    """
    return (np.asarray(u, np.float64) - width / 2.0) + 1j * (height / 2.0 - np.asarray(v, np.float64))


def nadir_pixel(camera: Camera, roll_deg: float = 0.0, pitch_deg: float = 0.0) -> tuple[float, float]:
    """The pixel at which the point straight below the camera appears, given roll and pitch."""
    frd = rotation_body_to_ned(0.0, pitch_deg, roll_deg).T @ np.array([[0.0], [0.0], [1.0]])
    u, v = _body_to_pixels(frd, camera)
    return float(u[0]), float(v[0])


def footprint(pose: Pose, camera: Camera) -> np.ndarray:
    """Ground ``(x, y)`` of the image corners (top-left, top-right, bottom-right, bottom-left), (4, 2)."""
    w, h = camera.width, camera.height
    gx, gy = image_to_ground([0.0, w, w, 0.0], [0.0, 0.0, h, h], pose, camera)
    return np.column_stack([gx, gy])
