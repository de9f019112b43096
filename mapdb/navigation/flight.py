"""A simulated flight: frames of labelled objects along a path, with the autopilot's sensors and the truth.

The aircraft flies a :class:`~mapdb.navigation.path.FlightPath` at constant speed, banking in turns as a
coordinated turn needs (``roll = atan(v^2 / (g R))``), with a little turbulence on roll and pitch.  Each
frame is the image a downward-looking camera takes at that pose, made by the single-image simulator's own
steps (its camera, :mod:`mapdb.simulation.poses`; detector errors and label confusion,
:mod:`mapdb.simulation.detector`; document and truth, :mod:`mapdb.simulation.documents`), so that a frame
is also a valid ``mapdb query`` input.

Frame document (one JSON line each; the image keys are the query schema's)::

    {"id": "frame-000012", "time_s": 1.2, "width": 640, "height": 480, "objects": [...],
     "camera": {"fov_deg": 70.0},
     "attitude": {"roll_deg": ..., "pitch_deg": ..., "yaw_deg": ...},   # the AHRS, with its errors
     "altitude_m": 151.3,                                                # barometric, with its errors
     "imu_velocity_mps": [east, north],                                  # with an IMU only
     "map_withheld": true,                                               # inside a --map-gap only
     "truth": {"x", "y", "heading_deg", "altitude_m", "roll_deg", "pitch_deg", "fov_deg", "n_visible",
               "map_index", "bound": null, "time_s", "velocity_mps": [east, north], "blackout": bool}}

Sensor error model (all draws depend only on ``seed`` and the frame number):

* attitude: true roll, pitch and heading plus independent normal errors of ``attitude_std`` degrees per
  frame; the heading also carries a constant bias drawn once (std ``heading_bias_deg``, a magnetometer's);
* barometric altitude: true height plus a constant bias (std ``baro_bias_m``) and noise (``baro_std_m``);
* inertial velocity (when ``imu_std_mps`` is given): true velocity plus a constant bias vector (std
  ``imu_bias_mps`` per axis) and noise;
* detector: the simulator's (``pixel_std``, ``miss_rate``, ``spurious_rate``, ``label_noise``); during a
  blackout (``blackouts``: ``(start_s, seconds)`` pairs) a frame has no objects at all.

With ``render`` (:mod:`mapdb.navigation.rendered`, ``mapdb simulate flight --render masks``) each frame's
objects are the blobs of a label mask rendered from the source's outlines with the frame's own pose, as
``mapdb objects`` extracts them (``area_px``, ``border``, ``bbox``), with segmentation errors in place of
the detector's; ``truth.map_index`` is then the map object covering most of each blob (-1 for none).

``map_gaps`` marks frames during which the navigator must not query the map (the matcher is off), to
measure how far frame-to-frame velocity alone drifts.

Over terrain (``terrain``: a map that holds elevation, or ``mapdb simulate flight --dem``; issue 33) every
object stands at its ground elevation and the aircraft flies a barometric altitude: a height above the
vertical datum, ``altitude_m`` above the ground under the path's start (``altitude_above="start"``, the
default: the aircraft holds one pressure altitude, and its height above the ground changes with the ground
under it), above the ground under each frame (``"ground"``: a terrain-following plan, the autopilot flying
the planned datum altitudes: the camera stays ``altitude_m`` above the ground) or above the datum itself
(``"datum"``); a ``(start, end)`` profile changes it linearly along the flight in every case.  Nothing aboard
measures the height above the ground, so a frame over terrain carries no ``altitude_m``; it carries instead::

     "baro_altitude_m": 212.4,   # the barometer: height above the datum, plus its bias and noise

and its truth adds ``ground_m`` (the ground's elevation under the nadir) and ``altitude_datum_m`` (the
camera's true height above the datum); ``truth.altitude_m`` stays the camera's height above the ground under
it.  The barometer's errors are those of the flat flight (``baro_bias_m``, ``baro_std_m``), around the datum
altitude.  The navigator subtracts the map's elevation at its position (:mod:`mapdb.navigation.terrain`).
Without terrain (a map without elevation, or ``--flat``) every frame is what it was before terrain existed,
byte for byte: ``altitude_m`` is the barometric height above the flat ground.  Rendered masks
(``render``) draw flat ground: terrain applies to ideal centroids only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .._scipy import cKDTree
from ..camera import Camera, Pose, project_points, project_to_image
from ..errors import MapdbError
from ..objects import Objects
from ..progress import ProgressLike, as_progress
from ..simulation.detector import Detector, detect, label_mix
from ..simulation.documents import image_document, truth_entry
from ..simulation.poses import Shot, placement_limits
from ..simulation.simulate import objects_of_map
from ..simulation.terrain import Terrain
from .path import FlightPath, heading_deg, survey_pattern
from .rendered import FlightRender, check_coverage, rendered_objects

__all__ = ["ALTITUDE_ABOVE", "DEFAULT_LENGTH_M", "FlightOptions", "TerrainClearanceError", "in_windows",
           "simulate_flight"]

GRAVITY = 9.80665
# The default survey's length when no path is given.
DEFAULT_LENGTH_M = 5000.0
# Over terrain, what a flight's altitude is measured from: the ground under the path's start, the ground under
# each frame (a terrain-following plan), or the datum.
ALTITUDE_ABOVE = ("start", "ground", "datum")
# Over terrain, a flight passing closer to the ground than this fraction of its planned altitude is refused.
MIN_CLEARANCE = 0.1


class TerrainClearanceError(MapdbError, ValueError):
    """A flight over terrain that would pass (nearly) at or below the ground."""


@dataclass(frozen=True)
class FlightOptions:
    """What :func:`simulate_flight` simulates (module docs); lengths in metres, angles in degrees.

    ``length_m`` None flies the whole given path, or :data:`DEFAULT_LENGTH_M` of the default survey.
    ``altitude_m`` is a constant height above ground or ``(start, end)``, changing linearly along the
    flight; over terrain, a barometric altitude measured from ``altitude_above`` (module docs).
    ``imu_std_mps`` None: no inertial velocity in the frames.
    """

    length_m: float | None = None
    speed_mps: float = 20.0
    fps: float = 10.0
    altitude_m: float | tuple[float, float] = 150.0
    fov_deg: float = 70.0
    size: tuple[int, int] = (640, 480)
    turn_radius_m: float = 75.0
    pixel_std: float = 0.0
    miss_rate: float = 0.0
    spurious_rate: float = 0.0
    label_noise: float = 0.0
    attitude_std: float = 0.0
    turbulence_deg: float = 0.5
    heading_bias_deg: float = 1.0
    baro_std_m: float = 0.3
    baro_bias_m: float = 2.0
    imu_std_mps: float | None = None
    imu_bias_mps: float = 0.2
    blackouts: tuple[tuple[float, float], ...] = field(default_factory=tuple)
    map_gaps: tuple[tuple[float, float], ...] = field(default_factory=tuple)
    seed: int = 0
    altitude_above: str = "start"

    def __post_init__(self) -> None:
        if self.altitude_above not in ALTITUDE_ABOVE:
            raise ValueError(f"altitude above {self.altitude_above!r}: not one of {', '.join(ALTITUDE_ABOVE)}")
        positive = {"speed_mps": self.speed_mps, "fps": self.fps, "turn_radius_m": self.turn_radius_m}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        heights = self.altitude_m if isinstance(self.altitude_m, tuple) else (self.altitude_m,)
        if not all(math.isfinite(h) and h > 0 for h in heights):
            raise ValueError(f"altitude must be positive, got {self.altitude_m}")
        if self.length_m is not None and not (math.isfinite(self.length_m) and self.length_m > 0):
            raise ValueError(f"length_m must be positive, got {self.length_m}")
        for start, seconds in (*self.blackouts, *self.map_gaps):
            if not (math.isfinite(start) and math.isfinite(seconds) and seconds >= 0):
                raise ValueError(f"a window is START:SECONDS with SECONDS >= 0, got {start}:{seconds}")


def in_windows(t: np.ndarray, windows: Sequence[tuple[float, float]]) -> np.ndarray:
    """Whether each time lies in one of the ``(start, seconds)`` windows (start included, end not).

    Examples
    --------
    >>> in_windows(np.array([0.9, 1.0, 2.9, 3.0]), [(1.0, 2.0)]).tolist()
    [False, True, True, False]
    """
    t = np.asarray(t, np.float64)
    inside = np.zeros(t.shape, bool)
    for start, seconds in windows:
        inside |= (t >= start) & (t < start + seconds)
    return inside


@dataclass(frozen=True)
class _Trajectory:
    """The true state at every frame time."""

    t: np.ndarray
    z: np.ndarray  # position, complex map metres
    velocity: np.ndarray  # complex m/s (east + i north)
    heading: np.ndarray
    roll: np.ndarray  # the coordinated turn's bank, before turbulence
    altitude: np.ndarray  # above the ground under the nadir
    ground: np.ndarray | None = None  # over terrain: the ground's elevation under the nadir
    datum: np.ndarray | None = None  # over terrain: the camera's height above the datum


def _trajectory(path: FlightPath, options: FlightOptions, length: float) -> _Trajectory:
    """Frame times along ``length`` metres of ``path`` and the true state at each."""
    n = int(math.floor(length / options.speed_mps * options.fps + 1e-9)) + 1
    t = np.arange(n) / options.fps
    s = options.speed_mps * t
    z, tangent, curvature = path.at(s)
    a = options.altitude_m if isinstance(options.altitude_m, tuple) else (options.altitude_m,) * 2
    altitude = a[0] + (a[1] - a[0]) * s / max(length, 1e-9)
    # A left turn (positive curvature) banks the left wing down: negative roll.
    roll = -np.degrees(np.arctan(options.speed_mps**2 * curvature / GRAVITY))
    return _Trajectory(t, z, options.speed_mps * tangent, heading_deg(tangent), roll, altitude)


def _over_terrain(truth: _Trajectory, terrain: Terrain, options: FlightOptions, map_name: str) -> _Trajectory:
    """The trajectory at a barometric altitude over ``terrain`` (module docs): the profile above the datum, the
    ground under the start or the ground under each frame; its height above the ground under each nadir."""
    ground = np.array([terrain.ground(float(z.real), float(z.imag)) for z in truth.z])
    base = {"start": ground[0], "ground": ground, "datum": 0.0}[options.altitude_above]
    datum = truth.altitude + base
    above = datum - ground
    low = np.flatnonzero(above < MIN_CLEARANCE * truth.altitude)
    if low.size:
        i = int(low[0])
        raise TerrainClearanceError(
            f"{map_name}: the flight would be {above[i]:.1f} m above the ground at {truth.t[i]:g} s (the ground "
            f"{ground[i]:.1f} m above the datum; at least {MIN_CLEARANCE:.0%} of the altitude is needed): give a "
            "higher --altitude, or --altitude-above ground")
    return _Trajectory(truth.t, truth.z, truth.velocity, truth.heading, truth.roll, above, ground, datum)


def _biases(options: FlightOptions) -> dict[str, Any]:
    """The flight's constant sensor biases, drawn once."""
    rng = np.random.default_rng([options.seed, 2])
    draws = rng.standard_normal(4)
    return {"heading": options.heading_bias_deg * draws[0], "baro": options.baro_bias_m * draws[1],
            "imu": options.imu_bias_mps * complex(draws[2], draws[3])}


def _visible(objects: Objects, tree: cKDTree, shot: Shot, x: float, y: float, terrain: Terrain | None = None,
             datum: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Map indices and pixels of the objects inside the image of a camera at ``(x, y)``; over ``terrain`` the
    objects at their heights and the camera ``datum`` metres above the datum."""
    # Over terrain the lowest ground is seen farthest out: the reach of a camera that high above it.
    wide = shot if terrain is None else replace(shot, altitude=datum - float(terrain.z.min()))
    _, _, reach = placement_limits(wide, (x, y, x, y), False)
    near = np.asarray(tree.query_ball_point([x, y], reach * 1.001 + 1e-6), dtype=np.int64)
    near.sort()
    if terrain is None:
        u, v = project_to_image(objects.x[near], objects.y[near], shot.pose(x, y), shot.camera)
    else:
        pose = Pose(x, y, datum, shot.heading, shot.roll, shot.pitch)
        u, v = project_points(objects.x[near], objects.y[near], terrain.z[near], pose, shot.camera)
    seen = np.isfinite(u) & (u >= 0) & (u < shot.camera.width) & (v >= 0) & (v < shot.camera.height)
    return near[seen], u[seen], v[seen]


def _sensors(rng: np.random.Generator, options: FlightOptions, biases: dict[str, Any], shot: Shot,
             velocity: complex, datum: float | None = None) -> dict[str, Any]:
    """What the autopilot reports of the true ``shot`` and velocity (module docs); over terrain the barometer
    reads the ``datum`` altitude, as ``baro_altitude_m``."""
    err = rng.standard_normal(6)
    att = options.attitude_std
    baro = (shot.altitude if datum is None else datum) + biases["baro"] + options.baro_std_m * err[3]
    out: dict[str, Any] = {
        "attitude": {"roll_deg": float(shot.roll + att * err[0]), "pitch_deg": float(shot.pitch + att * err[1]),
                     "yaw_deg": float((shot.heading + biases["heading"] + att * err[2]) % 360.0)},
        "altitude_m" if datum is None else "baro_altitude_m": float(baro),
    }
    if options.imu_std_mps is not None:
        measured = velocity + biases["imu"] + options.imu_std_mps * complex(err[4], err[5])
        out["imu_velocity_mps"] = [float(measured.real), float(measured.imag)]
    return out


# What renders a flight's masks, and what receives each mask (frame id, mask); None: ideal centroids.
_Render = tuple[FlightRender, Callable[[str, np.ndarray], None] | None] | None


# The world a flight's camera sees: the map's objects, their tree, the detector, and the terrain (None: flat).
_World = tuple[Objects, cKDTree, Detector, Terrain | None]


def _frame(i: int, truth: _Trajectory, options: FlightOptions, world: _World,
           biases: dict[str, Any], blackout: bool, withheld: bool, render: _Render) -> dict[str, Any]:
    """Frame ``i``: the camera's objects (centroids, or blobs of a rendered mask), the sensors, the truth."""
    objects, tree, detector, terrain = world
    datum = None if truth.datum is None else float(truth.datum[i])
    rng = np.random.default_rng([options.seed, i])
    wobble = options.turbulence_deg * rng.standard_normal(2)
    camera = Camera(options.size[0], options.size[1], options.fov_deg)
    shot = Shot(float(truth.altitude[i]), camera, float(truth.heading[i]), float(truth.roll[i] + wobble[0]),
                float(wobble[1]))
    x, y = float(truth.z[i].real), float(truth.z[i].imag)
    frame_id = f"frame-{i:06d}"
    if render is not None:
        doc, index, n_visible, mask = rendered_objects(render[0], shot, x, y, rng, frame_id)
        if blackout:
            doc["objects"], index = [], index[:0]
        if render[1] is not None:
            render[1](frame_id, mask)
    else:
        index, u, v = _visible(objects, tree, shot, x, y, terrain, datum or 0.0)
        n_visible = index.size
        if blackout:
            index, u, v, names = index[:0], u[:0], v[:0], np.zeros(0, object)
        else:
            index, u, v, names = detect(rng, objects, index, u, v, camera, detector)
        doc = image_document(frame_id, camera, names, u, v)
    doc = {"id": doc.pop("id"), "time_s": round(float(truth.t[i]), 6), **doc}
    doc.update(_sensors(np.random.default_rng([options.seed, i, 1]), options, biases, shot, complex(truth.velocity[i]),
                        datum))
    if withheld:
        doc["map_withheld"] = True
    doc["truth"] = {**truth_entry(shot, x, y, n_visible, index, None), "time_s": doc["time_s"],
                    "velocity_mps": [float(truth.velocity[i].real), float(truth.velocity[i].imag)],
                    "blackout": bool(blackout)}
    if truth.ground is not None and datum is not None:
        doc["truth"].update(ground_m=float(truth.ground[i]), altitude_datum_m=datum)
    return doc


def simulate_flight(map: Any, options: FlightOptions | None = None, waypoints: np.ndarray | None = None,
                    progress: ProgressLike = None, render: FlightRender | None = None,
                    on_mask: Callable[[str, np.ndarray], None] | None = None,
                    terrain: Terrain | None = None) -> list[dict[str, Any]]:
    """Frames of a simulated flight over a map (module docs).

    Parameters
    ----------
    map : MetaMap, MemoryMap or Objects
        The map the camera sees (all its objects are read).
    options : FlightOptions, optional
    waypoints : complex array, optional
        The path's waypoints in map metres (:func:`~mapdb.navigation.path.read_linestring`); by default a
        survey pattern over the map's densest part (:func:`~mapdb.navigation.path.survey_pattern`).
    progress : Progress or callable, optional
        Counts the frames made.
    render : FlightRender, optional
        Each frame's objects extracted from a label mask rendered from these outlines
        (:mod:`mapdb.navigation.rendered`); by default each visible map object at its projected centroid,
        with the detector's errors of ``options``.
    on_mask : callable, optional
        With ``render``: called with each frame's id and mask (class codes: label code + 1), in order.
    terrain : Terrain, optional
        The objects at their heights and a barometric altitude (module docs;
        :func:`~mapdb.simulation.terrain.terrain_of`); not with ``render``.  None: flat ground.

    Raises
    ------
    SourceError
        ``render``'s outlines do not cover the map's objects along the flight.
    ValueError
        ``render`` and ``terrain`` both given.
    TerrainClearanceError
        Over terrain, the flight passes lower than ``MIN_CLEARANCE`` times its altitude above the ground.

    Returns
    -------
    list of dict
        One frame document per ``1 / fps`` seconds, from the path's start.
    """
    options = options or FlightOptions()
    objects, counts = objects_of_map(map)
    wanted = options.length_m
    if waypoints is None:
        wanted = wanted or DEFAULT_LENGTH_M
        waypoints = survey_pattern(objects, wanted)
    path = FlightPath.from_waypoints(waypoints, options.turn_radius_m)
    length = min(wanted or path.length, path.length)
    truth = _trajectory(path, options, length)
    if terrain is not None:
        if render is not None:
            raise ValueError("rendered masks draw flat ground: a flight over terrain has ideal centroids")
        truth = _over_terrain(truth, terrain, options, str(getattr(map, "path", None) or "map"))
    if render is not None:
        altitude = float(np.max(truth.altitude))
        camera = Camera(options.size[0], options.size[1], options.fov_deg)
        check_coverage(render, objects, truth.z, altitude * math.hypot(*options.size) / 2.0 / camera.focal_px)
    names, mix = label_mix(counts)
    detector = Detector(options.pixel_std, options.miss_rate, options.spurious_rate, options.label_noise, names, mix)
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    biases = _biases(options)
    blackout = in_windows(truth.t, options.blackouts)
    withheld = in_windows(truth.t, options.map_gaps)
    say = as_progress(progress)
    say.start(truth.t.size, "simulate flight")
    frames = []
    for i in range(truth.t.size):
        frames.append(_frame(i, truth, options, (objects, tree, detector, terrain), biases, bool(blackout[i]),
                             bool(withheld[i]), None if render is None else (render, on_mask)))
        say.advance()
    say.done()
    return frames
