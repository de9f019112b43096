"""A navigated track sent to an autopilot over MAVLink: ``GPS_INPUT`` and ``GLOBAL_VISION_POSITION_ESTIMATE``.

Each :class:`~mapdb.navigation.track.TrackRecord` becomes one ``GPS_INPUT`` message (and, with
``vision=True``, one ``GLOBAL_VISION_POSITION_ESTIMATE``), sent over UDP as soon as the record is made.
``docs/mavlink.md`` documents every field; in short:

* position: the record's lon/lat in 1e-7 degree (``lat``, ``lon``); altitude the frame's barometric altitude
  above mean sea level (``baro_altitude_m``, over a map with elevation), else its barometric height above
  ground plus the ground's height above mean sea level (``ground_alt_m``);
* velocity: the track's (map grid) velocity turned to true north and scaled to ground metres;
* accuracies: ``horiz_accuracy`` the 1-sigma of the position covariance's major axis; ``speed_accuracy``
  the frame-to-frame velocity's stated 1-sigma, or ``sqrt(2) sigma / dt`` without one; ``vert_accuracy``
  the barometer's accuracy the navigator trusts;
* time: the record's ``time_s`` as GPS week and milliseconds (a Unix time, or seconds since the start of
  the flight, counted from the moment the output was opened).

The input side (:class:`AutopilotAltitude`, :func:`altitude_of`, :class:`MavlinkIn`) reads the autopilot's
altitude from its own MAVLink messages (``ALTITUDE``, ``GLOBAL_POSITION_INT``, ``VFR_HUD``) and turns it into
the frame field the navigator reads (:meth:`AutopilotAltitude.frame_fields`, ``docs/mavlink.md``, *Input*):
over a map with elevation the barometric altitude above the datum, ``baro_altitude_m`` (above mean sea level,
the datum of the DEMs mapdb reads: SRTM's EGM96 geoid), from which the navigator takes the map's ground away
(:mod:`mapdb.navigation.terrain`); over a flat map ``altitude_m``, the height above the take-off ground; a
range finder's distance to the ground is ``altitude_m`` over either.

UDP has no acknowledgement: a receiver that went away is seen only through the "port unreachable" the
kernel reports on the next send.  Such messages are counted as lost (:attr:`MavlinkOut.lost`) and the
sending goes on, so that navigation never stops for the link.

pymavlink is an optional dependency (``pip install 'mapdb[mavlink]'``), imported only when an output is
opened.
"""

from __future__ import annotations

import errno
import math
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import MapdbError, MapdbIOError
from .track import TrackRecord

__all__ = [
    "AutopilotAltitude",
    "GPS_EPOCH_UNIX_S",
    "GPS_LEAP_S",
    "MavlinkIn",
    "MavlinkMissingError",
    "MavlinkOptions",
    "MavlinkOut",
    "altitude_of",
    "ground_frame",
    "gps_input_fields",
    "message_altitude",
    "gps_time",
    "parse_address",
    "vision_fields",
]

# 1980-01-06T00:00:00Z, the start of GPS time, as a Unix time.
GPS_EPOCH_UNIX_S = 315_964_800
# GPS time runs ahead of UTC by the leap seconds since 1980: 18 since 2017-01-01 (none announced since).
GPS_LEAP_S = 18
_WEEK_S = 604_800
# GPS_INPUT's fix_type (MAVLink GPS_FIX_TYPE): no position (the source is alive), a 3D position.
FIX_NONE, FIX_3D = 1, 3
# GPS_INPUT_IGNORE_FLAGS bits.
IGNORE_ALT, IGNORE_HDOP, IGNORE_VDOP = 1, 2, 4
IGNORE_VEL_HORIZ, IGNORE_VEL_VERT, IGNORE_SPEED_ACCURACY = 8, 16, 32
IGNORE_HORIZ_ACCURACY, IGNORE_VERT_ACCURACY = 64, 128
# A map fix has no satellite geometry: DOP 1.0 says the geometry adds nothing (the accuracies carry the
# error), and ten "satellites" pass the autopilots' GPS checks (ArduPilot's EKF wants 6).  Not measurements.
NOMINAL_DOP = 1.0
NOMINAL_SATELLITES = 10
# MAV_COMP_ID_ONBOARD_COMPUTER: a companion computer beside the autopilot.
COMPANION_COMPONENT = 191
# How long close() waits for the kernel to report the last datagram refused (loopback answers at once).
_LAST_CHECK_S = 0.05


class MavlinkMissingError(MapdbError, ImportError):
    """``--mavlink`` was asked for and pymavlink is not installed."""


@dataclass(frozen=True)
class MavlinkOptions:
    """What the messages carry beyond the record (module docs).

    ``ground_alt_m``: the ground's height above mean sea level, added to each frame's barometric height
    above ground for ``GPS_INPUT.alt``.  ``vert_accuracy_m``: the altitude's 1-sigma (the barometer's).
    ``attitude_std_deg``: the 1-sigma of roll, pitch and yaw in the vision message's covariance.
    """

    vision: bool = False
    ground_alt_m: float = 0.0
    vert_accuracy_m: float = 1.0
    attitude_std_deg: float = 1.0
    system: int = 1
    component: int = COMPANION_COMPONENT


def parse_address(text: str) -> tuple[str, int]:
    """``udpout:HOST:PORT`` -> ``(HOST, PORT)``; ``ValueError`` for anything else.

    Examples
    --------
    >>> parse_address("udpout:127.0.0.1:14550"), parse_address("udpout:[::1]:14551")
    (('127.0.0.1', 14550), ('::1', 14551))
    >>> parse_address("udp:127.0.0.1:14550")
    Traceback (most recent call last):
    ValueError: 'udp:127.0.0.1:14550' is not udpout:HOST:PORT
    """
    kind, _, rest = text.partition(":")
    host, _, port = rest.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")
    if kind != "udpout" or not host or not port.isdigit():
        raise ValueError(f"{text!r} is not udpout:HOST:PORT")
    if not 0 < int(port) < 65536:
        raise ValueError(f"{text!r}: port {port} is not within 1-65535")
    return host, int(port)


def gps_time(unix_s: float) -> tuple[int, int]:
    """A Unix time as GPS week and milliseconds into the week.

    Examples
    --------
    >>> gps_time(GPS_EPOCH_UNIX_S - GPS_LEAP_S + 7 * 86400 + 1.5)
    (1, 1500)
    """
    gps_s = unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_S
    week = int(gps_s // _WEEK_S)
    ms = int(round((gps_s - week * _WEEK_S) * 1000.0))
    if ms >= _WEEK_S * 1000:  # rounded up into the next week
        week, ms = week + 1, ms - _WEEK_S * 1000
    return week, ms


def ground_frame(record: TrackRecord) -> np.ndarray:
    """The 2x2 matrix from the map grid's (east, north) metres to true (north, east) ground metres at the
    record's position: the meridian convergence and the projection's scale, measured by pyproj."""
    from pyproj import Geod

    from ..localize.lonlat import transformer

    assert record.x is not None and record.y is not None and record.crs
    to_lonlat = transformer(record.crs, "EPSG:4326")
    lon0, lat0 = to_lonlat.transform(record.x, record.y)
    columns = []
    for dx, dy in ((1.0, 0.0), (0.0, 1.0)):  # one grid metre east, then north
        lon1, lat1 = to_lonlat.transform(record.x + dx, record.y + dy)
        azimuth, _, distance = Geod(ellps="WGS84").inv(lon0, lat0, lon1, lat1)
        a = math.radians(azimuth)
        columns.append((distance * math.cos(a), distance * math.sin(a)))
    return np.array(columns).T  # [[n/east, n/north], [e/east, e/north]]


def _time_unix(record: TrackRecord, start_unix: float) -> float:
    """The record's time as a Unix time: ``time_s`` itself once past 1980, else seconds since ``start_unix``."""
    assert record.time_s is not None
    return record.time_s if record.time_s >= GPS_EPOCH_UNIX_S else start_unix + record.time_s


def _speed_accuracy(record: TrackRecord, dt: float | None) -> float | None:
    """The frame-to-frame velocity's stated 1-sigma, else that of a velocity from two positions ``dt`` apart."""
    measured = record.velocity_measurement
    if measured.get("status") == "used" and isinstance(measured.get("sigma_mps"), int | float):
        return float(measured["sigma_mps"])
    sigma = record.sigma_m
    if sigma is None or not dt or dt <= 0:
        return None
    return math.sqrt(2.0) * sigma / dt


def message_altitude(altitude_m: float | None, amsl_m: float | None, options: MavlinkOptions) -> float | None:
    """The altitude the messages carry, metres above mean sea level: the frame's barometric altitude above the
    datum (``amsl_m``, a frame's ``baro_altitude_m``) when it has one, else its height above ground
    (``altitude_m``) plus ``options.ground_alt_m``; None when the frame gives neither."""
    if amsl_m is not None:
        return float(amsl_m)
    return None if altitude_m is None else float(options.ground_alt_m + altitude_m)


def gps_input_fields(record: TrackRecord, altitude_m: float | None, options: MavlinkOptions, start_unix: float,
                     dt: float | None = None, amsl_m: float | None = None) -> dict[str, Any]:
    """The ``GPS_INPUT`` fields of a record (module docs; ``docs/mavlink.md``).

    ``altitude_m``: the frame's barometric height above ground; ``amsl_m``: its barometric altitude above mean
    sea level, which wins (both None: altitude ignored); ``dt``: seconds since the previous record (for the
    speed accuracy without a measured velocity).
    """
    unix = _time_unix(record, start_unix)
    week, week_ms = gps_time(unix)
    fields: dict[str, Any] = {
        "time_usec": int(round(unix * 1e6)), "gps_id": 0, "time_week_ms": week_ms, "time_week": week,
        "fix_type": FIX_NONE, "lat": 0, "lon": 0, "alt": 0.0, "hdop": 0.0, "vdop": 0.0, "vn": 0.0, "ve": 0.0,
        "vd": 0.0, "speed_accuracy": 0.0, "horiz_accuracy": 0.0, "vert_accuracy": 0.0, "satellites_visible": 0,
        "yaw": 0,  # 0: not available (the image heading is not the aircraft's yaw)
        "ignore_flags": 255,
    }
    if not record.placed or record.lon is None or record.lat is None or record.cov is None:
        return fields
    ignore = IGNORE_VEL_VERT
    fields.update(fix_type=FIX_3D, lat=int(round(record.lat * 1e7)), lon=int(round(record.lon * 1e7)),
                  hdop=NOMINAL_DOP, vdop=NOMINAL_DOP, satellites_visible=NOMINAL_SATELLITES,
                  horiz_accuracy=float(record.sigma_m or 0.0))
    alt = message_altitude(altitude_m, amsl_m, options)
    if alt is None:
        ignore |= IGNORE_ALT | IGNORE_VERT_ACCURACY
    else:
        fields.update(alt=alt, vert_accuracy=float(options.vert_accuracy_m))
    if record.velocity is None:
        ignore |= IGNORE_VEL_HORIZ | IGNORE_SPEED_ACCURACY
    else:
        north, east = ground_frame(record) @ np.array([record.velocity.real, record.velocity.imag])
        fields.update(vn=float(north), ve=float(east))
        speed_accuracy = _speed_accuracy(record, dt)
        if speed_accuracy is None:
            ignore |= IGNORE_SPEED_ACCURACY
        else:
            fields["speed_accuracy"] = float(speed_accuracy)
    fields["ignore_flags"] = ignore
    return fields


def _upper_triangle(matrix: np.ndarray) -> list[float]:
    """A symmetric 6x6 matrix's upper-right triangle, row by row (MAVLink's 21-float covariance)."""
    return [float(matrix[i, j]) for i in range(6) for j in range(i, 6)]


def vision_fields(record: TrackRecord, altitude_m: float | None, origin: tuple[float, float, float],
                  options: MavlinkOptions, start_unix: float, reset_counter: int) -> dict[str, Any]:
    """The ``GLOBAL_VISION_POSITION_ESTIMATE`` fields of a placed record: metres north, east and down of
    ``origin`` (lon, lat, altitude of the first placed record), with the 6x6 covariance; ``altitude_m`` the
    record's altitude as :func:`message_altitude` gives it, None when unknown."""
    from ..localize.lonlat import transformer

    assert record.lon is not None and record.lat is not None and record.cov is not None
    lon0, lat0, alt0 = origin
    local = f"+proj=aeqd +lat_0={lat0!r} +lon_0={lon0!r} +datum=WGS84 +units=m"
    east, north = transformer("EPSG:4326", local).transform(record.lon, record.lat)
    frame = ground_frame(record)
    cov = np.zeros((6, 6))
    cov[:2, :2] = frame @ record.cov @ frame.T  # grid (east, north) -> ground (north, east)
    cov[2, 2] = options.vert_accuracy_m**2 if altitude_m is not None else 0.0
    cov[3, 3] = cov[4, 4] = cov[5, 5] = math.radians(options.attitude_std_deg) ** 2
    yaw = math.radians(record.heading_deg) if record.heading_deg is not None else 0.0
    return {"usec": int(round(_time_unix(record, start_unix) * 1e6)), "x": float(north), "y": float(east),
            "z": -float((altitude_m if altitude_m is not None else alt0) - alt0),
            "roll": 0.0, "pitch": 0.0, "yaw": float(math.atan2(math.sin(yaw), math.cos(yaw))),
            "covariance": _upper_triangle(cov), "reset_counter": reset_counter % 256}


def _dialect() -> Any:
    try:
        from pymavlink.dialects.v20 import common
    except ImportError:
        raise MavlinkMissingError("--mavlink needs pymavlink: pip install 'mapdb[mavlink]'") from None
    return common


class _Link:
    """A connected UDP socket that counts the datagrams the receiver refused (module docs)."""

    def __init__(self, address: str) -> None:
        try:
            host, port = parse_address(address)
        except ValueError as exc:
            raise MapdbIOError(f"{address}: cannot open MAVLink output ({exc})") from None
        try:
            family, kind, proto, _, where = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
            self.sock = socket.socket(family, kind, proto)
        except OSError as exc:
            raise MapdbIOError(f"{address}: cannot open MAVLink output ({exc.strerror or exc})") from None
        try:
            self.sock.connect(where)  # connected: the kernel reports a refused datagram on the next send
        except OSError as exc:
            self.sock.close()
            raise MapdbIOError(f"{address}: cannot open MAVLink output ({exc.strerror or exc})") from None
        self.address, self.lost, self.pending = address, 0, False

    def write(self, data: bytes) -> None:
        """Send one datagram; a refusal reported for the previous one counts it lost, and this one is retried."""
        for _ in range(2):
            try:
                self.sock.send(data)
            except ConnectionRefusedError:  # the previous datagram met a closed port
                self.lost += int(self.pending)
                self.pending = False
                continue
            except OSError:  # no route, no buffer: this datagram is lost
                self.lost += 1
                self.pending = False
                return
            self.pending = True
            return
        self.lost += 1

    def close(self) -> None:
        """Close, counting the last datagram if the receiver refused it."""
        if self.pending:
            time.sleep(_LAST_CHECK_S)
            if self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == errno.ECONNREFUSED:
                self.lost += 1
        self.sock.close()


class MavlinkOut:
    """The track's MAVLink output to ``udpout:HOST:PORT`` (module docs).

    Opened at once (an address that cannot be opened raises :class:`~mapdb.errors.MapdbIOError` before any
    frame is read); :meth:`send` one record at a time; :meth:`close` and :meth:`summary` at the end.
    """

    def __init__(self, address: str, options: MavlinkOptions | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        self.options = options or MavlinkOptions()
        dialect = _dialect()
        self.link = _Link(address)
        self.mav = dialect.MAVLink(self.link, srcSystem=self.options.system, srcComponent=self.options.component)
        self.start_unix = clock()
        self.sent = self.untimed = 0
        self.previous_time: float | None = None
        self.origin: tuple[float, float, float] | None = None
        self.resets, self.was_placed = 0, False

    @property
    def lost(self) -> int:
        """Messages the receiver refused (or that could not be sent)."""
        return self.link.lost

    def send(self, record: TrackRecord, altitude_m: float | None = None, amsl_m: float | None = None) -> None:
        """Send a record as ``GPS_INPUT`` (and the vision estimate); a record without a time is not sent.

        ``altitude_m``: the frame's barometric height above ground; ``amsl_m``: its barometric altitude above
        mean sea level (``baro_altitude_m``), which wins (:func:`message_altitude`).
        """
        if record.time_s is None:
            self.untimed += 1
            return
        dt = None if self.previous_time is None else record.time_s - self.previous_time
        self.previous_time = record.time_s
        self.mav.gps_input_send(**gps_input_fields(record, altitude_m, self.options, self.start_unix, dt, amsl_m))
        altitude = message_altitude(altitude_m, amsl_m, self.options)
        self.sent += 1
        placed = record.placed and record.cov is not None and record.lon is not None and record.lat is not None
        if placed and not self.was_placed and self.origin is not None:
            self.resets += 1  # the filter restarted: the vision estimate's frame starts again
        self.was_placed = placed
        if self.options.vision and placed:
            if self.origin is None:
                assert record.lon is not None and record.lat is not None
                self.origin = (record.lon, record.lat, altitude or 0.0)
            self.mav.global_vision_position_estimate_send(
                **vision_fields(record, altitude, self.origin, self.options, self.start_unix, self.resets))
            self.sent += 1

    def close(self) -> None:
        self.link.close()

    def summary(self) -> str:
        """One line for stderr: what was sent, and what was lost."""
        line = f"{self.link.address}: {self.sent} MAVLink messages sent"
        if self.lost:
            line += f", {self.lost} lost (the receiver refused them: is it still listening?)"
        if self.untimed:
            line += f"; {self.untimed} records without a time not sent"
        return line

    def __enter__(self) -> MavlinkOut:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- Input: the autopilot's altitude for the frames ---

# ALTITUDE.altitude_terrain below this means unknown (MAVLink's definition); an unknown bottom_clearance is
# negative.  Neither field is read here but bottom_clearance (a range finder: a measured height).
_UNKNOWN_CLEARANCE = 0.0


def _finite(value: Any, scale: float = 1.0) -> float | None:
    """A message field as metres (``scale`` from its unit), None when it is not a finite number."""
    try:
        number = float(value) * scale
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


@dataclass(frozen=True)
class AutopilotAltitude:
    """What an autopilot says of its altitude, metres (None: not said).

    ``amsl_m``: above mean sea level (the barometric altitude the autopilot flies by); ``relative_m``: above
    its home (take-off) position; ``clearance_m``: a range finder's distance to the ground below it.
    """

    amsl_m: float | None = None
    relative_m: float | None = None
    clearance_m: float | None = None

    def merged(self, newer: AutopilotAltitude) -> AutopilotAltitude:
        """This altitude updated by the fields a newer message says."""
        return AutopilotAltitude(*(b if b is not None else a for a, b in (
            (self.amsl_m, newer.amsl_m), (self.relative_m, newer.relative_m), (self.clearance_m, newer.clearance_m))))

    def frame_fields(self, elevation: bool, home_elevation_m: float | None = None) -> dict[str, float]:
        """The frame's altitude field (``docs/frames.md``): empty when nothing usable was said.

        Parameters
        ----------
        elevation : bool
            Whether the map holds elevation (``mapdb build --dem``): then the barometric altitude is the height
            above the datum, ``baro_altitude_m``, from ``amsl_m`` or ``relative_m + home_elevation_m``; else
            the height above the (flat) ground, ``altitude_m``, from ``relative_m`` (the take-off ground's
            height) or ``amsl_m - home_elevation_m``.
        home_elevation_m : float, optional
            The take-off ground's height above mean sea level.

        A range finder's ``clearance_m`` is the height above the ground itself: ``altitude_m`` in either case.

        Examples
        --------
        >>> AutopilotAltitude(amsl_m=412.0, relative_m=120.0).frame_fields(elevation=True)
        {'baro_altitude_m': 412.0}
        >>> AutopilotAltitude(relative_m=120.0).frame_fields(elevation=True, home_elevation_m=292.0)
        {'baro_altitude_m': 412.0}
        >>> AutopilotAltitude(amsl_m=412.0, relative_m=120.0).frame_fields(elevation=False)
        {'altitude_m': 120.0}
        >>> AutopilotAltitude(relative_m=120.0).frame_fields(elevation=True)  # the home's height unknown
        {}
        """
        if self.clearance_m is not None:
            return {"altitude_m": self.clearance_m}
        if elevation:
            if self.amsl_m is not None:
                return {"baro_altitude_m": self.amsl_m}
            if self.relative_m is not None and home_elevation_m is not None:
                return {"baro_altitude_m": self.relative_m + home_elevation_m}
            return {}
        if self.relative_m is not None:
            return {"altitude_m": self.relative_m}
        if self.amsl_m is not None and home_elevation_m is not None:
            return {"altitude_m": self.amsl_m - home_elevation_m}
        return {}


def altitude_of(message: Any) -> AutopilotAltitude | None:
    """The altitude a decoded pymavlink message says, or None for a message that says none.

    ``ALTITUDE`` (141): ``altitude_amsl``, ``altitude_relative``, ``bottom_clearance`` (metres; NaN, or a
    negative clearance, unknown); ``GLOBAL_POSITION_INT`` (33): ``alt`` and ``relative_alt`` (millimetres);
    ``VFR_HUD`` (74): ``alt`` (metres above mean sea level).
    """
    kind = message.get_type() if hasattr(message, "get_type") else None
    if kind == "ALTITUDE":
        clearance = _finite(message.bottom_clearance)
        return AutopilotAltitude(_finite(message.altitude_amsl), _finite(message.altitude_relative),
                                 clearance if clearance is not None and clearance > _UNKNOWN_CLEARANCE else None)
    if kind == "GLOBAL_POSITION_INT":
        return AutopilotAltitude(_finite(message.alt, 1e-3), _finite(message.relative_alt, 1e-3))
    if kind == "VFR_HUD":
        return AutopilotAltitude(_finite(message.alt))
    return None


class MavlinkIn:
    """The autopilot's altitude, heard on ``udpin:HOST:PORT`` (the port MAVProxy or mavlink-router forwards the
    autopilot's messages to): :meth:`poll` reads what has arrived without waiting, and :attr:`altitude` holds
    the latest of each kind (:meth:`AutopilotAltitude.merged`)."""

    def __init__(self, address: str) -> None:
        dialect = _dialect()
        kind, _, rest = address.partition(":")
        host, _, port = rest.rpartition(":")
        if kind != "udpin" or not host or not port.isdigit():
            raise MapdbIOError(f"{address}: cannot open MAVLink input (not udpin:HOST:PORT)")
        try:
            self.sock = socket.socket(socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET,
                                      socket.SOCK_DGRAM)
            self.sock.bind((host.strip("[]"), int(port)))
        except OSError as exc:
            raise MapdbIOError(f"{address}: cannot open MAVLink input ({exc.strerror or exc})") from None
        self.sock.setblocking(False)
        self.dialect = dialect
        self.parser = dialect.MAVLink(None)
        self.address, self.altitude, self.heard = address, AutopilotAltitude(), 0

    def poll(self) -> AutopilotAltitude:
        """Every datagram waiting decoded (what does not decode is skipped), and the latest altitude."""
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return self.altitude
            try:
                messages = self.parser.parse_buffer(data) or []
            except self.dialect.MAVError:  # not MAVLink (or damaged): skipped, with what the parser held of it
                self.parser = self.dialect.MAVLink(None)
                continue
            for message in messages:
                said = altitude_of(message)
                if said is not None:
                    self.altitude, self.heard = self.altitude.merged(said), self.heard + 1

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> MavlinkIn:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
