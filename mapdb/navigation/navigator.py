"""The navigation loop: each frame's query uses the filter's prediction, and its answer updates the filter.

Per frame (:meth:`Navigator.step`), in this order:

1. **Read** the frame: its time, objects, attitude (roll, pitch, yaw), barometric altitude and inertial
   velocity.  A sensor that is missing or not finite is ignored for this frame (a note says so); objects
   that cannot be read leave a frame to predict from.  Every value is bounded (:mod:`mapdb.navigation.frames`).
   A frame not later than the previous one, or less than ``MIN_STEP_S`` after it, is skipped; so is a
   frame more than ``MAX_STEP_S`` after it; if the next frame continues from that one, the clock jumped:
   the filter restarts (no position until a new first fix), as after a long pause.  Whatever a
   frame holds, it gets a record: a frame whose navigation fails leaves the navigator as it was and is
   answered "skipped" with the reason, and the next frames are navigated.
2. **Predict** the particles to the frame's time, turning their velocities by the autopilot's heading change.
   Over terrain, a frame with the barometer's ``baro_altitude_m`` (above the datum) gets its height above
   the ground from the map's elevation at the predicted position (:mod:`mapdb.navigation.terrain`).
3. **Frame orientation** (:mod:`mapdb.navigation.orientation`): the image-to-ground similarity
   ``A = s exp(-i heading)``.  The heading is the last applied fix's plus the autopilot's yaw change since
   (the frame-to-frame rotation where the yaw is missing); the scale (metres per pixel) the last fix's times
   the barometric altitude ratio (the altitude over the focal length before any fix).  Both ratios
   telescope, so neither drifts frame by frame.
4. **Velocity** from the previous frame (:mod:`mapdb.navigation.velocity`), guessed from the filter's
   velocity; its persistent error, measured against the applied fixes (rooftops moving faster than the ground,
   cut blobs slower, a scale or heading a little off: :mod:`mapdb.navigation.bias`), sizes the filter's drift
   allowance and is taken out as ``velocity_bias`` says; and the inertial velocity when the frame has one.
5. **Fix**: unless the flight withholds the map, the frame is localized with the filter's prediction as the
   prior, radius from the particle cloud (99 % of the weight or its stated 3 sigma, whichever is wider,
   plus the attitude errors' floor; the cloud spreads with the time since the last applied fix), and after a
   first fix with the frame's heading and scale as a pose prior (:meth:`Orientation.pose_prior`: one
   correspondence a hypothesis, :mod:`mapdb.match.pose_prior`; the fix's ``path`` says which search decided).  After
   ``widen_after`` queries in a row without an applied fix the radius doubles every frame, and past
   ``max_radius_m`` the query is lost-in-space.  The answer and its runner-up candidates update the
   filter (a multi-modal measurement, :mod:`mapdb.navigation.filter`); a fix from blobs keeps the cloud at
   least as wide as its own error, which the next frames' fixes share (:func:`~.filter.shared_sigma`).
   Fixes rejected as outliers ``recover_after`` times in a row at places consistent with the filter's
   velocity draw half the particles to them: a filter started far off, or captured, gets back.
   When the frame alone is not decisive (no fix, or one rejected as an outlier), the objects of the last
   ``stitch_frames`` frames, carried into this one by the frame-to-frame similarities of step 4, are
   queried as one image (:mod:`mapdb.navigation.stitch`); the record's ``fix_frames`` names the frames a
   fix used.  A frame that ends without an applied fix weighs the particles by its objects' likelihood
   under the map instead (:mod:`mapdb.navigation.map_update`, ``map_update``): weak evidence, accumulated
   over frames.
6. **Record** the estimate (:class:`~mapdb.navigation.track.TrackRecord`).

Without an initial position the filter waits for a first fix with score at least ``init_min_score``
(lost-in-space, no prior); until then every frame is recorded as "not initialised".  With one (``--initial``)
the particles start in its disc with a wide velocity spread about rest; the first velocity measured (frame
to frame, or the inertial unit's) sets their velocities and carries them over the step predicted at rest,
so the estimate does not lag the aircraft (:meth:`ParticleFilter.update_velocity`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..answers import Answer
from ..localize.localizer import Localizer
from ..localize.lonlat import to_lonlat
from ..match.pose_prior import PosePrior
from .bias import VelocityBias
from .filter import FixComponent, ParticleFilter, shared_sigma
from .frames import MAX_SPEED_MPS, MAX_STEP_S, MIN_STEP_S, Frame, read_frame
from .map_update import MapUpdate
from .orientation import Orientation
from .stitch import DEFAULT_FRAMES, History, Seen, min_stitched_score
from .terrain import GroundModel, height_above_ground
from .track import TrackRecord
from .velocity import FrameMotion, FramePoints, frame_points, match_frames, velocity_from_motion

__all__ = ["BLOB_FIX_FLOOR_PX", "Navigator", "NavigatorOptions"]

# A fix from blobs (objects from a mask) is no better than this many pixels per axis (``_components``).
BLOB_FIX_FLOOR_PX = 2.0


@dataclass(frozen=True)
class NavigatorOptions:
    """Tuning of the navigator (module docs); angles in degrees, lengths in metres.

    ``attitude_std`` and ``baro_std_m`` are the accuracies the autopilot's sensors are trusted with;
    ``heading_std`` that of its heading before any fix (a magnetometer's bias); ``imu_std_mps`` that of
    an inertial velocity (bias included).  ``stitch_frames``: earlier frames stitched to a frame that is not
    decisive alone (:mod:`mapdb.navigation.stitch`; 0 queries single frames only).
    """

    particles: int = 2000
    accel_std: float = 0.5
    attitude_std: float = 0.1
    baro_std_m: float = 0.5
    heading_std: float = 3.0
    imu_std_mps: float = 0.5
    outlier_probability: float = 0.02
    min_radius_m: float = 10.0
    max_radius_m: float = 2000.0
    init_min_score: float = 6.0
    candidate_min_score: float = 4.0
    widen_after: int = 10
    recover_after: int = 3
    stitch_frames: int = DEFAULT_FRAMES
    seed: int = 0
    terrain: bool = True  # False: a frame's baro_altitude_m is its height above the ground (the flat assumption)
    velocity_bias: str = "scale"  # what of the measured bias is taken out (bias.BIAS_MODES; scale: its scale)
    pose_prior: bool = True  # queries carry the heading and scale after a fix (mapdb.match.pose_prior)
    map_update: bool = True  # frames without an applied fix weigh the particles (mapdb.navigation.map_update)


@dataclass
class _Previous:
    time_s: float | None = None
    points: FramePoints | None = None
    to_map: complex | None = None
    pending: list[tuple[float, complex]] = field(default_factory=list)  # rejected fixes: (time, place)
    misses: int = 0  # frames with objects and no applied fix
    jump: float | None = None  # the time of a frame skipped for a step over MAX_STEP_S
    extra_labels: dict[str, int] = field(default_factory=dict)  # the previous frame's labels not in the map


class Navigator:
    """Frames in, a :class:`TrackRecord` per frame out (module docs).

    Parameters
    ----------
    map : MetaMap or MemoryMap
        The map (the navigator does not close it).
    options : NavigatorOptions, optional
    initial : (x, y, radius), optional
        Where the flight starts (map CRS metres): the particles start uniform in that disc.
    localizer : Localizer, optional
        Reused if given (one per map).
    """

    def __init__(self, map: Any, options: NavigatorOptions | None = None,
                 initial: tuple[float, float, float] | None = None, localizer: Localizer | None = None) -> None:
        self.map = map
        self.options = options or NavigatorOptions()
        self.localizer = localizer or Localizer(map)
        self.filter = ParticleFilter(self.options.particles, self.options.accel_std,
                                     self.options.outlier_probability, self.options.seed)
        self.initial = initial
        self.labels: dict[str, int] = {name: code for code, name in enumerate(map.labels)}
        self.orientation = Orientation()
        self.previous = _Previous()
        self.last_velocity: complex | None = None
        self._extra_labels: dict[str, int] = {}  # this frame's labels the map lacks (``_codes``)
        self.ground = GroundModel.of(map)  # the map's elevation, for the barometer (mapdb.navigation.terrain)
        self.history = History(self.options.stitch_frames)
        self.mapper = MapUpdate(map, BLOB_FIX_FLOOR_PX)
        self._motion: FrameMotion | None = None  # the current frame's similarity to the previous one
        self._raw_velocity: complex | None = None  # this frame's velocity as measured (before the bias)
        self.bias = VelocityBias(mode=self.options.velocity_bias)  # the velocity's persistent error (fixes)
        self._imu = False  # an inertial velocity fused: its stated error is the least drift (bias unmeasured)
        self.filter.drift_of = lambda speed: self.bias.drift(speed, self.options.imu_std_mps if self._imu else 0.0)
        if initial is not None:
            self.filter.initialise(complex(initial[0], initial[1]), initial[2])

    # ------------------------------------------------------------------------------------- frames

    def step(self, doc: Any, where: str = "frame") -> TrackRecord:
        """Navigate one frame document (or the :class:`ImageInputError` that replaced an unreadable line).

        Never raises for what a frame holds: a frame whose navigation fails (an exception, or a filter
        left with non-finite particles) leaves the navigator as it was before the frame and is answered
        "skipped" with the reason.  KeyboardInterrupt and SystemExit still end the stream.
        """
        start = time.perf_counter()
        saved = self._snapshot()
        try:
            record = self._step(doc, where, start)
            if not self.filter.finite():
                raise FloatingPointError("the filter's particles became non-finite")
            return record
        except Exception as exc:  # one frame never ends the stream: whatever it held, it gets a record
            self._restore(saved)
            return self._failed(doc, where, exc, start)

    def _step(self, doc: Any, where: str, start: float) -> TrackRecord:
        frame = read_frame(doc, where)
        record = TrackRecord(id=frame.id, time_s=frame.time_s, status="predicting", notes=list(frame.notes))
        why = self._timing_fault(frame, record)
        if why is not None:
            record.notes.append(f"skipped: {why}")
            return self._finish(record, frame, "skipped", start, {})
        previous_t = self.previous.time_s
        assert frame.time_s is not None
        dt = 0.0 if previous_t is None else frame.time_s - previous_t
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        self._imu = frame.imu is not None
        self.filter.predict(dt, self.orientation.turn(frame))
        record.altitude = height_above_ground(frame, self.ground, self.filter, self.options.baro_std_m,
                                              self.options.terrain)
        self.orientation.carry(frame, self.options.heading_std)
        timing["filter"] = time.perf_counter() - t0
        points = self._points(frame)
        self._motion = None
        self._raw_velocity = None
        record.velocity_measurement = self._velocity(frame, points, dt, timing)
        self._displacement(record.velocity_measurement, dt)
        self._remember(frame, points)
        record.fix = self._fix(frame, record, timing)
        if record.fix.get("status") in ("used", "initialised"):
            record.fix_frames = record.fix.pop("frames", [frame.time_s])
        elif self.options.map_update and self.filter.initialised:
            t0 = time.perf_counter()
            record.map_update = ({"status": "skipped", "reason": "the flight withholds the map here"} if frame.withheld
                                 else self.mapper.update(self.filter, points, self.orientation, frame.time_s,
                                                         self._floor()))
            timing["map_update"] = time.perf_counter() - t0
        self.previous.time_s = frame.time_s
        self.previous.points = points
        self.previous.extra_labels = self._extra_labels if points is not None else {}
        self.previous.to_map = self.orientation.to_map()
        used = record.fix.get("status") in ("used", "initialised")
        status = "fix" if used else ("dead-reckoning" if record.velocity_measurement.get("status") == "used"
                                     else "predicting")
        return self._finish(record, frame, status, start, timing)

    def _timing_fault(self, frame: Frame, record: TrackRecord) -> str | None:
        """Why the frame cannot be placed in the flight's time, or None (module docs, step 1).

        A step over ``MAX_STEP_S`` is held back once: the frame is skipped, and a next frame continuing
        from it (within ``MAX_STEP_S`` after it) confirms that the flight's clock jumped; the filter then
        restarts, as after a long pause.  One frame with a wild time thus never strands the frames after it.
        """
        previous_t, jump = self.previous.time_s, self.previous.jump
        if frame.time_s is None:
            return "no valid time_s"
        if previous_t is None:
            return None
        dt = frame.time_s - previous_t
        if dt <= 0:
            return f"out of time order: time_s {frame.time_s:g} is not after {previous_t:g}"
        if dt < MIN_STEP_S:
            return f"time step {dt:g} s is under {MIN_STEP_S:g} s: the same instant as the previous frame"
        if dt <= MAX_STEP_S:
            self.previous.jump = None
            return None
        if jump is not None and MIN_STEP_S <= frame.time_s - jump <= MAX_STEP_S:
            self._restart()
            record.notes.append(f"the flight resumes {dt:g} s after the previous frame (over {MAX_STEP_S:g} s): "
                                "the filter restarts")
            return None
        self.previous.jump = frame.time_s
        return (f"time step {dt:g} s is over {MAX_STEP_S:g} s (a next frame continuing from this one restarts "
                "the filter)")

    def _restart(self) -> None:
        """After a jump of the clock: no position, no previous frame; heading and scale references stay."""
        self.filter.reset()
        self.previous = _Previous()
        self.last_velocity = None
        self.history.clear()
        self.bias.reset()

    def _snapshot(self) -> tuple[Any, ...]:
        previous = replace(self.previous, pending=list(self.previous.pending))
        return (self.filter.snapshot(), replace(self.orientation), previous, self.last_velocity, self.history.copy(),
                self.bias.copy())

    def _restore(self, saved: tuple[Any, ...]) -> None:
        filter_state, self.orientation, self.previous, self.last_velocity, self.history, self.bias = saved
        self.filter.restore(filter_state)

    def _failed(self, doc: Any, where: str, exc: Exception, start: float) -> TrackRecord:
        """The record of a frame whose navigation failed: the estimate before it, and why."""
        try:
            frame = read_frame(doc, where)
        except Exception:  # the frame itself is what failed: answer without its fields
            frame = Frame(id=None)
        reason = f"skipped: the frame could not be navigated ({type(exc).__name__}: {str(exc)[:200]})"
        record = TrackRecord(id=frame.id, time_s=frame.time_s, status="skipped", notes=[*frame.notes, reason])
        try:
            return self._finish(record, frame, "skipped", start, {})
        except Exception:  # the estimate itself cannot be given: the record says so without a position
            return TrackRecord(id=frame.id, time_s=frame.time_s, status="skipped",
                               notes=[*record.notes, "no estimate could be given"])

    def _finish(self, record: TrackRecord, frame: Frame, status: str, start: float,
                timing: dict[str, float]) -> TrackRecord:
        """Fill the estimate, the truth's error and the times in."""
        record.status = status if self.filter.initialised else "not initialised"
        if self.filter.initialised:
            position, velocity, cov, _ = self.filter.estimate()
            lon, lat = to_lonlat(self.map.crs, position.real, position.imag)
            record.x, record.y, record.lon, record.lat = position.real, position.imag, lon, lat
            record.velocity, record.cov, record.crs = velocity, cov, self.map.crs or None
            record.heading_deg = None if self.orientation.heading is None else self.orientation.heading % 360.0
        if frame.truth is not None:
            error = (None if record.x is None or record.y is None
                     else math.hypot(record.x - frame.truth[0], record.y - frame.truth[1]))
            record.truth = {"x": frame.truth[0], "y": frame.truth[1],
                            "error_m": None if error is None else round(error, 3)}
        record.time_ms = {"total": 1e3 * (time.perf_counter() - start),
                          **{k: 1e3 * v for k, v in timing.items()}}
        return record

    # -------------------------------------------------------------------------------------- points

    def _remember(self, frame: Frame, points: FramePoints | None) -> None:
        """Keep the frame for stitching, linked by its similarity to the previous one when step 4 found one
        (:mod:`mapdb.navigation.stitch`); a frame without objects breaks the chain."""
        if points is None or frame.image is None or frame.time_s is None:
            self.history.clear()
            return
        self.history.add(Seen(frame.time_s, points, frame.image.names, frame.image.area_px,
                              self._motion))

    def _points(self, frame: Frame) -> FramePoints | None:
        if frame.image is None or len(frame.image) == 0:
            return None
        return frame_points(frame.image, self._codes(frame.image.names), frame.roll, frame.pitch)

    def _codes(self, names: Any) -> np.ndarray:
        """Label codes: the map's, then codes for labels the map lacks, shared with the previous frame only.

        Frame-to-frame matching compares two frames, so a label the map lacks needs the same code in
        both and no other; a table of every label ever seen would grow with the stream.
        """
        previous = self.previous.extra_labels
        used = set(previous.values())
        extra: dict[str, int] = {}
        free = len(self.labels)
        codes = np.empty(len(names), np.int64)
        for i, raw in enumerate(names):
            name = str(raw)
            code = self.labels.get(name, extra.get(name, previous.get(name)))
            if code is None:
                while free in used:
                    free += 1
                code = free
                used.add(code)
            if name not in self.labels:
                extra[name] = code
            codes[i] = code
        self._extra_labels = extra
        return codes

    # --------------------------------------------------------------------------------- velocity

    def _velocity(self, frame: Frame, points: FramePoints | None, dt: float, timing: dict[str, float]
                  ) -> dict[str, Any]:
        """Frame-to-frame velocity (and the inertial one) into the filter; what happened, for the record."""
        t0 = time.perf_counter()
        out = self._frame_velocity(frame, points, dt)
        timing["velocity"] = time.perf_counter() - t0
        if frame.imu is not None and self.filter.initialised:
            cov = self.options.imu_std_mps**2 * np.eye(2)
            out["imu"] = "used" if self.filter.update_velocity(frame.imu, cov) else "rejected as an outlier"
        return out

    def _frame_velocity(self, frame: Frame, points: FramePoints | None, dt: float) -> dict[str, Any]:
        prev, opts = self.previous, self.options
        if points is None or prev.points is None or dt <= 0:
            return {"status": "none", "reason": "no objects in this or the previous frame"}
        if prev.to_map is None:
            return {"status": "none", "reason": "no heading or scale yet (attitude yaw, altitude and fov needed)"}
        if min(prev.points.z.size, points.z.size) < 3:  # the matcher's own refusal, without the filter's estimate
            return {"status": "none", "reason": str(match_frames(prev.points, points))}
        # A_cur = A_prev a: the turn and the altitude change since the previous frame, as the sensors say.
        to_map = self.orientation.to_map()
        a_guess = to_map / prev.to_map if to_map is not None else 1 + 0j
        b_guess = self.filter.estimate()[1] * dt / prev.to_map if self.filter.velocity_known else None
        n_labels = max(len(self.labels), int(prev.points.codes.max(initial=-1)) + 1,
                       int(points.codes.max(initial=-1)) + 1)
        motion = match_frames(prev.points, points, a_guess, b_guess, n_labels)
        if isinstance(motion, str):
            return {"status": "none", "reason": motion}
        if frame.yaw is None and self.orientation.heading is not None:
            self.orientation.heading -= math.degrees(np.angle(motion.a))  # no yaw: the images' own rotation
        o = self.orientation
        level = (frame.altitude or 0.0) * math.tan(math.radians(opts.attitude_std))
        baro_rel = opts.baro_std_m * math.sqrt(2.0) / max(frame.altitude or 1.0, 1.0)
        vel = velocity_from_motion(motion, prev.to_map, dt, level_sigma_m=level,
                                   scale_rel_sigma=math.hypot(o.scale_rel_sigma, baro_rel),
                                   heading_sigma_deg=o.heading_sigma)
        if not abs(vel.v) <= MAX_SPEED_MPS:  # a mismatch, or a scale from absurd sensors: not a velocity
            return {"status": "none", "reason": f"measured speed {abs(vel.v):g} m/s is over {MAX_SPEED_MPS:g} m/s"}
        raw = vel.v
        vel = replace(vel, v=self.bias.correct(raw), cov=vel.cov * abs(1.0 + self.bias.applied) ** 2)
        self.last_velocity = vel.v
        self._motion = motion
        self._raw_velocity = raw
        sigma = math.sqrt(float(np.max(np.linalg.eigvalsh(vel.cov))))
        used = self.filter.update_velocity(vel.v, vel.cov) if self.filter.initialised else False
        status = "used" if used else ("rejected" if self.filter.initialised else "measured")
        return {"status": status, "velocity_mps": [round(vel.v.real, 3), round(vel.v.imag, 3)],
                "sigma_mps": round(sigma, 3), "bias": [round(self.bias.c.real, 4), round(self.bias.c.imag, 4)],
                "inliers": motion.inliers,
                "method": "guided" if motion.guided else "quads"}

    def _displacement(self, measurement: dict[str, Any], dt: float) -> None:
        """The frame's displacement as measured, for the bias (:meth:`VelocityBias.add_frame`)."""
        if self.filter.initialised and dt > 0:
            used = self._raw_velocity if measurement.get("status") == "used" else None
            velocity = complex(np.sum(self.filter.weights * self.filter.v)) if self.filter.velocity_known else None
            self.bias.add_frame(used, velocity, dt)

    # --------------------------------------------------------------------------------------- fix

    def _prior(self) -> tuple[float, float, float] | None:
        """The query's prior from the particle cloud (module docs, step 5); None for lost-in-space."""
        if not self.filter.initialised:
            return None
        opts = self.options
        centre, _, cov, _ = self.filter.estimate()
        # The cloud's 99 % or its stated 3 sigma, whichever is wider: the radius follows the covariance as the
        # filter drifts between fixes (the filter's drift model), so that the truth stays inside the query.
        stated = 3.0 * math.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0))
        radius = max(opts.min_radius_m, max(self.filter.radius(centre), stated) + 3.0 * self._floor())
        if self.previous.misses >= opts.widen_after:
            # Doubling every frame: lost-in-space within a second when even a wide search finds nothing.
            radius *= 2.0 ** min(self.previous.misses - opts.widen_after + 1, 30)
        if radius > opts.max_radius_m:
            return None
        return (centre.real, centre.imag, radius)

    def _floor(self) -> float:
        """Per-axis error of a fix from the attitude errors: altitude times the tangent of their std."""
        altitude = self.orientation.baro or 100.0
        return max(altitude * math.tan(math.radians(self.options.attitude_std)), 0.1)

    def _fix(self, frame: Frame, record: TrackRecord, timing: dict[str, float]) -> dict[str, Any]:
        """Localize the frame with the filter's prior and update the filter (module docs, step 5)."""
        if frame.withheld:
            return {"status": "withheld", "reason": "the flight withholds the map here"}
        if frame.image is None or len(frame.image) < 3:
            n = 0 if frame.image is None else len(frame.image)
            return {"status": "none", "reason": f"{n} objects: no query"}
        prior = self._prior()
        record.prior_radius_m = None if prior is None else prior[2]
        pose = None if prior is None or not self.options.pose_prior else self.orientation.pose_prior(prior,
                                                                                                      frame.time_s)
        t0 = time.perf_counter()
        answer = self.localizer.localize(frame.image, prior=prior, pose=pose)
        timing["query"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        try:
            info = self._apply_fix(frame, answer, prior)
        finally:
            timing["filter"] = timing.get("filter", 0.0) + time.perf_counter() - t0
        if info["status"] in ("used", "initialised"):
            if answer.path is not None:
                info["path"] = answer.path
            return info
        return self._stitched_fix(frame, prior, info, timing, pose)

    def _stitched_fix(self, frame: Frame, prior: tuple[float, float, float] | None, single: dict[str, Any],
                      timing: dict[str, float], pose: PosePrior | None = None) -> dict[str, Any]:
        """The frame with the earlier frames' objects carried into it (:mod:`mapdb.navigation.stitch`): the
        stitched answer's fix when it is certain enough (the Bonferroni floor) and the filter applies it, else
        the frame's own outcome, saying why the stitched query gave none."""
        assert frame.image is not None
        stitched = self.history.stitched(frame.image, None)
        if stitched is None:
            return single
        t0 = time.perf_counter()
        answer = self.localizer.localize(stitched.image, prior=prior, pose=pose)  # the stitched plane is this frame's
        timing["stitched"] = time.perf_counter() - t0
        floor = min_stitched_score(self.localizer.fast_options.log10_epsilon)
        summary = {"frames": len(stitched.frames), "objects": len(stitched.image), "carried": stitched.carried}
        if not answer.ok or (answer.score or 0.0) < floor:
            reason = answer.reason or f"score {answer.score:g} is under the stitched floor {floor:.2f}"
            single["stitched"] = {**summary, "reason": reason}
            return single
        saved = (self.previous.misses, list(self.previous.pending))
        t0 = time.perf_counter()
        info = self._apply_fix(frame, answer, prior, recover=False)
        timing["filter"] = timing.get("filter", 0.0) + time.perf_counter() - t0
        if info["status"] in ("used", "initialised"):
            info.update(stitched=summary, frames=stitched.frames, path=answer.path,
                        single={"status": single["status"], "reason": single.get("reason")})
            return info
        self.previous.misses, self.previous.pending = saved  # the frame's miss is counted once
        single["stitched"] = {**summary, "reason": info.get("reason")}
        return single

    def _components(self, answer: Answer, frame: Frame) -> list[FixComponent]:
        """The places an answer gives (module docs of :mod:`mapdb.navigation.filter`).

        A frame of blobs (objects from a mask: ``area_px`` or ``border`` given) adds ``BLOB_FIX_FLOOR_PX``
        pixels at the fix's scale to every component's sigma: relief, merging and cuts move blob centroids
        in ways the fit's residuals understate (measured, rendered masks at 120 m: fixes stated at 0.2 m were
        0.6-1.0 m off, beyond their 3 sigma on 3.4 % of the frames).
        """
        places: list[tuple[complex, float | None, float]] = []
        if answer.ok and answer.x is not None and answer.y is not None:
            places.append((complex(answer.x, answer.y), answer.sigma_m, answer.score or 0.0))
        if answer.ok or (answer.reason or "").startswith(("ambiguous", "imprecise")):
            places += [(complex(c.x, c.y), c.sigma_m, c.score) for c in answer.candidates
                       if c.score is not None and c.score >= self.options.candidate_min_score]
        if not places:
            return []
        top = max(score for _, _, score in places)
        floor = self._floor()
        image = frame.image
        if image is not None and (image.area_px is not None or image.border is not None):
            scale = answer.scale_m_per_px or self.orientation.scale or 0.0
            floor = math.hypot(floor, BLOB_FIX_FLOOR_PX * scale)
        return [FixComponent(z, math.hypot(sigma or 1.0, floor), 10.0 ** max(score - top, -300.0))
                for z, sigma, score in places]

    def _apply_fix(self, frame: Frame, answer: Answer, prior: tuple[float, float, float] | None,
                   recover: bool = True) -> dict[str, Any]:
        components = self._components(answer, frame)
        info: dict[str, Any] = {"status": "none"}
        if answer.ok:
            info.update(x=answer.x, y=answer.y, score=answer.score, sigma_m=answer.sigma_m, inliers=answer.inliers)
        if not components:
            self.previous.misses += 1
            info["reason"] = answer.reason or "no usable place"
            return info
        if not self.filter.initialised:
            info = self._initialise(answer, components, info, frame.time_s)
            if info["status"] == "initialised" and frame.time_s is not None:
                self.bias.add_fix(frame.time_s, components[0].centre, components[0].sigma_m**2)
            return info
        x0, y0, x1, y1 = self.map.bounds  # lost in space: the fix could have come from the map's whole box
        area = math.pi * prior[2] ** 2 if prior else max((x1 - x0) * (y1 - y0), 1.0)
        outcome = self.filter.update_fix(components, area, shared_sigma_m=shared_sigma(frame.image, components))
        info["inlier_probability"] = round(outcome.inlier_probability, 4)
        info["distance_m"] = round(outcome.distance_m, 3)
        if outcome.applied:
            info["status"] = "used"
            info["components"] = len(components)
            self._fixed(answer, frame.time_s)
            if answer.ok and frame.time_s is not None:
                self.bias.add_fix(frame.time_s, components[0].centre, components[0].sigma_m**2)
            return info
        info["status"] = "rejected"
        info["reason"] = (f"outlier: {outcome.distance_m:.1f} m from the estimate, "
                          f"inlier probability {outcome.inlier_probability:.2g}")
        self.previous.misses += 1
        if recover and answer.ok and self._recover(frame, complex(answer.x or 0.0, answer.y or 0.0)):
            info["reason"] += f"; {self.options.recover_after} consistent rejected fixes: particles drawn there"
        return info

    def _initialise(self, answer: Answer, components: list[FixComponent], info: dict[str, Any],
                    time_s: float | None) -> dict[str, Any]:
        if not answer.ok or (answer.score or 0.0) < self.options.init_min_score:
            info["reason"] = (f"not initialised: needs a fix with score >= {self.options.init_min_score:g}"
                              + (f" ({answer.reason})" if answer.reason else ""))
            return info
        best = components[0]
        self.filter.initialise(best.centre, 3.0 * best.sigma_m, self.last_velocity,
                               30.0 if self.last_velocity is None else 3.0)
        self._fixed(answer, time_s)
        info["status"] = "initialised"
        return info

    def _fixed(self, answer: Answer, time_s: float | None) -> None:
        """An applied fix resets the heading and scale references and the miss count."""
        if answer.ok and answer.heading_deg is not None and answer.scale_m_per_px is not None:
            self.orientation.fixed(answer.heading_deg, answer.scale_m_per_px, self.options.attitude_std, time_s,
                                   answer.sigma_m)
        self.previous.misses = 0
        self.previous.pending.clear()

    def _recover(self, frame: Frame, place: complex) -> bool:
        """Remember a rejected fix; after ``recover_after`` consistent ones, draw half the particles there."""
        assert frame.time_s is not None
        pending = self.previous.pending
        pending.append((frame.time_s, place))
        del pending[: -self.options.recover_after]
        if len(pending) < self.options.recover_after:
            return False
        velocity = self.filter.estimate()[1]
        for (t0, z0), (t1, z1) in zip(pending, pending[1:], strict=False):
            if t1 - t0 > 1.0 or abs(z1 - z0 - velocity * (t1 - t0)) > 5.0 + 3.0 * (t1 - t0):
                return False
        self.filter.inject(place, 3.0 * self._floor() + 1.0, 0.5, velocity)
        pending.clear()
        return True

