"""Where one image lands in the map by a pose: what :func:`~mapdb.evaluation.match_plot.plot_match` draws.

:func:`match_geometry` places an image's objects and footprint in the map by the localizer's answer (or,
for a rejected simulated image, by its true pose), finds each object's nearest map object of its label
and which of them the matcher's own inlier rule accepts, without drawing: for tests and other front ends.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..answers import Answer, Candidate
from ..camera import Camera, Pose, image_plane, image_to_ground, level_pixels
from ..detections.images import ImageObjects, parse_image
from ..match.geometry import image_to_map
from ..objects import Objects

__all__ = ["MatchGeometry", "answer_xy", "match_geometry"]


@dataclass(frozen=True)
class MatchGeometry:
    """An image placed in the map by one pose: what :func:`~mapdb.evaluation.match_plot.plot_match` draws.

    Attributes
    ----------
    pose : {"answer", "truth"}
        Which pose placed the image: the localizer's answer, or (for a rejected simulated image) the
        simulator's truth.
    world : complex array (n,)
        Each image object in map metres (``x + iy``); NaN where the pose cannot place it.
    footprint : complex array (4,)
        The image corners top-left, top-right, bottom-right, bottom-left in map metres.
    up : complex
        The map point under the middle of the image's top edge (where the image's *up* points).
    position : complex
        The pose's position: the answer's ``x, y`` (the camera nadir when the image was levelled, else
        the point under the image centre) or the truth's (the nadir).
    names : array of str (n,)
        Each image object's label.
    nearest : complex array (n,)
        The nearest map object of the same label (NaN if the map has none of that label nearby).
    distance : float array (n,)
        Distance (m) to it (inf if none).
    inlier : bool array (n,)
        Whether that distance is within ``gate_m``.
    gate_m : float
        The inlier gate: ``GATE_SIGMAS`` residual sigmas of the ``expected`` nearest objects,
        and at least the farthest of them (the matcher's own rule).
    """

    pose: str
    world: np.ndarray
    footprint: np.ndarray
    up: complex
    names: np.ndarray
    nearest: np.ndarray
    distance: np.ndarray
    inlier: np.ndarray
    gate_m: float
    position: complex


def _answer_placer(im: ImageObjects, answer: Answer):
    """Pixels -> map (complex) by the answer's similarity ``z -> a z + b``, as the localizer fitted it.

    ``a = scale * exp(-i heading)`` (``heading_deg`` is ``-arg(a)``, clockwise from north) and ``b`` is
    ``(x, y)``.  The pixels are levelled first when the localizer levelled them.
    """
    assert answer.scale_m_per_px is not None and answer.heading_deg is not None
    a = image_to_map(answer.scale_m_per_px, answer.heading_deg)
    b = answer_xy(answer)
    fov = im.fov_deg if answer.levelled else None

    def place(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
        if fov is not None:
            u, v = level_pixels(u, v, _camera(im, fov), im.roll_deg or 0.0, im.pitch_deg or 0.0)
        return a * image_plane(u, v, im.width, im.height) + b

    return place


def _camera(im: ImageObjects, fov_deg: float) -> Camera:
    """The image's camera, sized as the localizer sizes it (an image's width may be fractional)."""
    return Camera(im.width, im.height, fov_deg)


def _truth_placer(im: ImageObjects, truth: dict[str, Any]):
    """Pixels -> map (complex) by the simulator's true pose (the full camera model, tilt included)."""
    pose = Pose(float(truth["x"]), float(truth["y"]), float(truth["altitude_m"]), float(truth["heading_deg"]),
                float(truth.get("roll_deg") or 0.0), float(truth.get("pitch_deg") or 0.0))
    camera = _camera(im, float(truth.get("fov_deg") or im.fov_deg or 0.0))

    def place(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        gx, gy = image_to_ground(np.asarray(u, np.float64), np.asarray(v, np.float64), pose, camera)
        return gx + 1j * gy

    return place


def _has_pose(answer: Answer) -> bool:
    return answer.ok and all(
        isinstance(getattr(answer, k), int | float) for k in ("x", "y", "heading_deg", "scale_m_per_px"))


def answer_xy(answer: Answer | Candidate) -> complex:
    """An answer's (or candidate's) position as ``x + iy`` in map metres; a missing coordinate counts as 0."""
    return complex(float(answer.x or 0.0), float(answer.y or 0.0))


def _truth_pose(truth: dict[str, Any] | None, im: ImageObjects) -> bool:
    if not isinstance(truth, dict):
        return False
    keys = ("x", "y", "altitude_m", "heading_deg")
    return all(isinstance(truth.get(k), int | float) for k in keys) and (
        isinstance(truth.get("fov_deg"), int | float) or im.fov_deg is not None)


def _nearest_of_label(world: np.ndarray, names: np.ndarray, objects: Objects) -> tuple[np.ndarray, np.ndarray]:
    from .._scipy import cKDTree

    nearest = np.full(world.shape, np.nan + 0j)
    distance = np.full(world.shape, np.inf)
    codes = {name: code for code, name in enumerate(objects.labels)}
    for name in np.unique(names):
        mine = (names == name) & np.isfinite(world)
        code = codes.get(str(name))
        if code is None or not mine.any():
            continue
        of_label = objects.label == code
        if not of_label.any():
            continue
        tree = cKDTree(np.column_stack([objects.x[of_label], objects.y[of_label]]))
        d, j = tree.query(np.column_stack([world[mine].real, world[mine].imag]))
        distance[mine] = d
        nearest[mine] = objects.x[of_label][j] + 1j * objects.y[of_label][j]
    return nearest, distance


def _gate(distance: np.ndarray, expected: int) -> float:
    """The inlier gate from the ``expected`` smallest distances (the matcher's residual sigma and rule)."""
    from ..match.evidence.points import GATE_SIGMAS
    from ..match.refine import residual_sigma

    finite = np.sort(distance[np.isfinite(distance)])
    k = min(max(int(expected), 3), finite.size)
    if k == 0:
        return 0.0
    best = finite[:k]
    return max(GATE_SIGMAS * residual_sigma(best), float(best[-1]), 1e-9)


def match_geometry(image: dict[str, Any] | ImageObjects, answer: Answer, map: Any,
                   truth: dict[str, Any] | None = None) -> MatchGeometry | None:
    """Place an image's objects and footprint in the map, and find which meet a map object of their label.

    Parameters
    ----------
    image : dict or ImageObjects
        The image document (or parsed image) that was localized.
    answer : dict
        Its answer (:func:`mapdb.localize.localize`).  An accepted answer's pose places the image.
    map : MetaMap or MemoryMap
        The map it was localized in.
    truth : dict, optional
        The simulator's truth (``x``, ``y``, ``altitude_m``, ``heading_deg``, and ``fov_deg`` unless the
        image has a camera); its pose places a rejected image.  Defaults to the document's ``truth``.

    Returns
    -------
    MatchGeometry or None
        None when neither an accepted answer nor a truth pose can place the image.

    Raises
    ------
    ImageInputError
        If the image document is not valid.
    """
    im = image if isinstance(image, ImageObjects) else parse_image(image)
    if truth is None and isinstance(image, dict):
        truth = image.get("truth")
    if _has_pose(answer):
        pose, place = "answer", _answer_placer(im, answer)
        position = answer_xy(answer)
        expected = int(answer.inliers or 0)
    elif _truth_pose(truth, im):
        assert truth is not None
        pose, place = "truth", _truth_placer(im, truth)
        position = complex(float(truth["x"]), float(truth["y"]))
        index = truth.get("map_index")
        # The true objects are the ones expected to meet their map object.
        expected = int(np.sum(np.asarray(index) >= 0)) if isinstance(index, list) else len(im) // 2
    else:
        return None
    world = place(im.x, im.y)
    corners = place(np.array([0.0, im.width, im.width, 0.0]), np.array([0.0, 0.0, im.height, im.height]))
    up = complex(place(np.array([im.width / 2.0]), np.array([0.0]))[0])
    finite = world[np.isfinite(world)]
    reach = np.concatenate([corners[np.isfinite(corners)], finite])
    if reach.size:
        pad = 0.1 * max(float(np.ptp(reach.real)), float(np.ptp(reach.imag)), 1.0)
        objects = map.query_bbox(float(reach.real.min() - pad), float(reach.imag.min() - pad),
                                 float(reach.real.max() + pad), float(reach.imag.max() + pad))
    else:
        objects = Objects.empty(map.labels, map.crs)
    nearest, distance = _nearest_of_label(world, im.names, objects)
    gate = _gate(distance, expected)
    return MatchGeometry(pose=pose, world=world, footprint=corners, up=up, names=np.asarray(im.names),
                         nearest=nearest, distance=distance, inlier=distance <= gate, gate_m=gate,
                         position=position)
