"""Where an accepted answer puts the camera image on the ground: its footprint and its image-to-map transform.

The matcher finds a similarity ``z -> a z + b`` from the image plane (complex pixels from the image centre,
``y`` up; first levelled by :func:`mapdb.camera.level_pixels` when the roll, pitch and field of view are
known) onto the map.  :func:`pixel_to_map` is that model for any pixel ``(col, row)`` of the image (``(0, 0)``
the top-left corner of the top-left pixel, rows down, as GDAL and rasterio count them), and
:func:`georeference` gives what a GIS needs from it:

* ``footprint``: the ground points (map CRS) of the image's four corners, top-left, top-right, bottom-right,
  bottom-left, as the pinhole model projects them onto flat ground;
* ``transform``: the affine transform ``(a, b, c, d, e, f)`` from pixel to map,
  ``x = a col + b row + c``, ``y = d col + e row + f`` (rasterio's ``Affine`` order; a world file holds the
  same numbers for pixel centres, see :mod:`mapdb.localize.worldfile`);
* ``error_m``: how far that affine is from the pinhole model anywhere in the image.

**A level camera** (no attitude given, or roll and pitch of zero): the image is a similarity of flat ground,
so the affine *is* the model (``error_m`` 0) and the footprint is its corners.

**A tilted camera** (the answer is ``levelled``): the ground is a homography of the image, not an affine.
The footprint is exact (each corner projected through the homography).  The transform is the *best affine
of the pinhole projection over the image*: the least-squares affine through the projections of a
:data:`GRID` x :data:`GRID` grid of pixels spread evenly over the image (its edges included), and
``error_m`` is the largest distance between that affine and the projection over the grid (the corners are
on it, and that is where it is largest).  A world file can only hold an affine, so a GIS that places a
tilted image with it is off by up to ``error_m``; the footprint polygon is not.  An image whose corners reach
the horizon has neither (:func:`georeference` returns None).

Examples
--------
A level 640 x 480 image at 0.5 m a pixel, heading north, centred on (1000, 2000):

>>> g = georeference(0.5 + 0j, 1000 + 2000j, 640, 480)
>>> g.transform
(0.5, 0.0, 840.0, 0.0, -0.5, 2120.0)
>>> g.footprint.tolist()[0], g.error_m
([840.0, 2120.0], 0.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import IO

import numpy as np
import numpy.typing as npt

from ..answers import Answer
from ..camera import Camera, image_plane, level_pixels
from ..outputs import dumps_strict

__all__ = [
    "GRID",
    "FeatureWriter",
    "Georeference",
    "georeference",
    "pixel_to_map",
]

# Pixels a side of the grid the tilted camera's best affine is fitted over (and its error measured on).
GRID = 17


@dataclass(frozen=True)
class Georeference:
    """An answer's image on the ground (module docs): corners (4, 2) in the map CRS, the affine, its error."""

    footprint: np.ndarray
    transform: tuple[float, float, float, float, float, float]
    error_m: float


def pixel_to_map(col: npt.ArrayLike, row: npt.ArrayLike, a: complex, b: complex, width: float, height: float,
                 attitude: tuple[float, float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Map ``x, y`` of the ground seen at pixels ``(col, row)`` by an answer's pose.

    Parameters
    ----------
    col, row : array_like
        Pixel coordinates (``(0, 0)`` the top-left corner of the image, rows down).
    a, b : complex
        The answer's similarity from the image plane to the map (``b`` the map point under the image
        centre, or under the camera when the image was levelled).
    width, height : float
        The image size in pixels.
    attitude : (fov_deg, roll_deg, pitch_deg), optional
        Given when the answer levelled the image: pixels are levelled the same way first.

    Returns
    -------
    x, y : ndarray
        NaN where a tilted camera's ray does not reach the ground.
    """
    u = np.asarray(col, dtype=np.float64).reshape(-1)
    v = np.asarray(row, dtype=np.float64).reshape(-1)
    if attitude is not None:
        fov_deg, roll_deg, pitch_deg = attitude
        u, v = level_pixels(u, v, Camera(width, height, fov_deg), roll_deg, pitch_deg)
    ground = a * image_plane(u, v, width, height) + b
    return ground.real, ground.imag


@lru_cache(maxsize=16)
def _corners(width: float, height: float) -> np.ndarray:
    """The image-plane points (:func:`~mapdb.camera.image_plane`) of the image's corners (top-left, top-right,
    bottom-right, bottom-left), made once per image size (a stream's images share one); read-only, being shared."""
    corners = image_plane([0.0, width, width, 0.0], [0.0, 0.0, height, height], width, height)
    corners.flags.writeable = False
    return corners


def _similarity_affine(a: complex, b: complex, width: float, height: float) -> tuple[float, ...]:
    """The exact affine of a level image: ``z = (col - w/2) + i (h/2 - row)`` then ``a z + b``."""
    ar, ai = a.real, a.imag
    return (ar, ai, b.real - ar * width / 2.0 - ai * height / 2.0,
            ai, -ar, b.imag - ai * width / 2.0 + ar * height / 2.0)


def georeference(a: complex, b: complex, width: float, height: float,
                 attitude: tuple[float, float, float] | None = None) -> Georeference | None:
    """The footprint and image-to-map affine of an answer's pose (module docs); None when the image's corners
    reach the horizon (a tilted camera's ground is then unbounded).

    Parameters are those of :func:`pixel_to_map`; ``attitude`` only when the answer levelled the image.

    Examples
    --------
    A camera pitched 10 degrees nose up sees a trapezoid, wider at the top; the affine is off at the corners:

    >>> g = georeference(0.2 + 0j, 0j, 640, 480, attitude=(60.0, 0.0, 10.0))
    >>> bool(g.footprint[1, 0] - g.footprint[0, 0] > g.footprint[2, 0] - g.footprint[3, 0]), g.error_m > 1.0
    (True, True)
    """
    if attitude is None:
        # A level image: pixel_to_map's similarity of the corners in two numpy calls, not a dozen (every accepted
        # answer pays them); the complex points viewed as their (x, y) rows.
        ground = a * _corners(width, height) + b
        if not np.isfinite(ground).all():
            return None
        footprint = ground.view(np.float64).reshape(4, 2)
        return Georeference(footprint, _similarity_affine(a, b, width, height), 0.0)  # type: ignore[arg-type]
    corners_x, corners_y = pixel_to_map([0.0, width, width, 0.0], [0.0, 0.0, height, height], a, b, width, height,
                                        attitude)
    footprint = np.column_stack([corners_x, corners_y])
    if not np.all(np.isfinite(footprint)):
        return None
    cols, rows = np.meshgrid(np.linspace(0.0, width, GRID), np.linspace(0.0, height, GRID))
    gx, gy = pixel_to_map(cols, rows, a, b, width, height, attitude)
    if not (np.all(np.isfinite(gx)) and np.all(np.isfinite(gy))):
        return None
    design = np.column_stack([cols.ravel(), rows.ravel(), np.ones(cols.size)])
    (ta, tb, tc), *_ = np.linalg.lstsq(design, gx, rcond=None)
    (td, te, tf), *_ = np.linalg.lstsq(design, gy, rcond=None)
    error = float(np.max(np.hypot(design @ (ta, tb, tc) - gx, design @ (td, te, tf) - gy)))
    transform = tuple(float(t) for t in (ta, tb, tc, td, te, tf))
    return Georeference(footprint, transform, error)  # type: ignore[arg-type]



class FeatureWriter:
    """Answers as an RFC 7946 GeoJSON FeatureCollection in lon/lat, written one feature at a time (a stream of
    any length in bounded memory): ``kind`` ``"fixes"`` gives each accepted answer's centre as a Point
    (:attr:`mapdb.answers.Answer.__geo_interface__`), ``"footprints"`` its footprint as a Polygon
    (:meth:`mapdb.answers.Answer.footprint_feature`).  Rejected answers, and answers without a lon/lat, are
    left out, so every feature has a geometry of the one type.

    Examples
    --------
    >>> import io
    >>> from mapdb.answers import Answer
    >>> out = io.StringIO()
    >>> with FeatureWriter(out, "fixes") as w:
    ...     w.write(Answer(id="a", status="ok", lon=2.5, lat=42.5))
    ...     w.write(Answer(id="b", status="rejected", reason="no match"))
    >>> import json; [f["geometry"] for f in json.loads(out.getvalue())["features"]]
    [{'type': 'Point', 'coordinates': [2.5, 42.5]}]
    """

    def __init__(self, file: IO[str], kind: str) -> None:
        if kind not in ("fixes", "footprints"):
            raise ValueError(f"kind must be 'fixes' or 'footprints', not {kind!r}")
        self.file, self.kind, self.count = file, kind, 0

    def __enter__(self) -> FeatureWriter:
        self.file.write('{"type":"FeatureCollection","features":[\n')
        return self

    def write(self, answer: Answer) -> None:
        """Add the answer's feature (nothing for a rejected answer or one without lon/lat)."""
        if self.kind == "fixes":
            feature = answer.__geo_interface__ if answer.ok else None
            if feature is not None and feature["geometry"] is None:
                feature = None
        else:
            feature = answer.footprint_feature()
        if feature is None:
            return
        self.file.write(("" if self.count == 0 else ",\n") + dumps_strict(feature, separators=(",", ":")))
        self.count += 1

    def __exit__(self, *exc: object) -> None:
        self.file.write("\n]}\n")
