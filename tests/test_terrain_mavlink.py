"""The autopilot's altitude heard over MAVLink (mapdb/navigation/mavlink.py, input side) for a map with elevation:
pymavlink messages sent over loopback UDP, decoded by :class:`MavlinkIn`, and the navigator's height above the
ground from them."""

from __future__ import annotations

import socket
import time
from dataclasses import replace

import numpy as np
import pytest
from test_terrain_flight import OPTIONS, maps, waypoints  # noqa: F401 - maps is the fixture used below

from mapdb.errors import MapdbIOError
from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import simulate_flight
from mapdb.navigation.mavlink import AutopilotAltitude, MavlinkIn
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.simulation.terrain import terrain_of

common = pytest.importorskip("pymavlink.dialects.v20.common", reason="pymavlink is not installed (mapdb[mavlink])")


class Autopilot:
    """A pymavlink sender to a port on loopback: what a flight controller (through MAVProxy) sends."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", port))
        self.mav = common.MAVLink(self, srcSystem=1, srcComponent=1)

    def write(self, data: bytes) -> None:
        self.sock.send(data)

    def altitude(self, amsl: float, relative: float, clearance: float = -1.0) -> None:
        self.mav.altitude_send(0, amsl, amsl, relative, relative, float("nan"), clearance)


def heard(link: MavlinkIn, wanted: int) -> AutopilotAltitude:
    """The altitude once ``wanted`` messages were heard (loopback delivers at once; a second at most)."""
    deadline = time.monotonic() + 1.0
    while link.heard < wanted and time.monotonic() < deadline:
        link.poll()
        time.sleep(0.001)
    assert link.heard == wanted
    return link.altitude


def test_each_altitude_message_maps_to_the_frame_field_of_its_map() -> None:
    with MavlinkIn("udpin:127.0.0.1:0") as link:
        autopilot = Autopilot(link.sock.getsockname()[1])
        autopilot.mav.global_position_int_send(0, 437_000_000, 74_200_000, 412_500, 120_250, 0, 0, 0, 0)
        said = heard(link, 1)
        assert said == AutopilotAltitude(amsl_m=412.5, relative_m=120.25)
        # A map with elevation: the barometric altitude above the datum; a flat map: the height above take-off.
        assert said.frame_fields(elevation=True) == {"baro_altitude_m": 412.5}
        assert said.frame_fields(elevation=False) == {"altitude_m": 120.25}
        autopilot.sock.send(b"not mavlink")  # skipped, not fatal
        autopilot.mav.vfr_hud_send(20.0, 20.0, 90, 50, 415.0, 0.0)
        assert heard(link, 2) == AutopilotAltitude(amsl_m=415.0, relative_m=120.25)
        autopilot.altitude(416.0, 121.0, clearance=118.5)  # a range finder: the height above the ground
        assert heard(link, 3).frame_fields(elevation=True) == {"altitude_m": 118.5}


def test_only_relative_altitudes_need_the_take_off_grounds_height() -> None:
    relative = AutopilotAltitude(relative_m=80.0)
    assert relative.frame_fields(elevation=True) == {}
    assert relative.frame_fields(elevation=True, home_elevation_m=95.5) == {"baro_altitude_m": 175.5}
    assert AutopilotAltitude(amsl_m=175.5).frame_fields(elevation=False, home_elevation_m=95.5) == {"altitude_m": 80.0}
    with pytest.raises(MapdbIOError, match="udpout:127.0.0.1:1: cannot open MAVLink input"):
        MavlinkIn("udpout:127.0.0.1:1")


def test_the_navigator_takes_the_ground_from_the_autopilots_altitude(maps) -> None:  # noqa: F811
    """A flight over the slope whose barometer arrives over MAVLink (ALTITUDE.altitude_amsl) instead of in the
    frames: each frame gets ``baro_altitude_m`` and the navigator its height above the ground, as from the
    frames' own barometer."""
    with open_map(maps["dem"]) as m:
        frames = simulate_flight(m, replace(OPTIONS, seed=7), waypoints(m), terrain=terrain_of(m))[:12]
        navigator = Navigator(m, NavigatorOptions(particles=500, seed=1))
        records = []
        with MavlinkIn("udpin:127.0.0.1:0") as link:
            autopilot = Autopilot(link.sock.getsockname()[1])
            for i, frame in enumerate(frames):
                baro = frame.pop("baro_altitude_m")
                autopilot.altitude(baro, baro - frames[0]["truth"]["ground_m"])
                frame.update(heard(link, i + 1).frame_fields(elevation=m.has_elevation))
                assert frame["baro_altitude_m"] == pytest.approx(baro, abs=1e-4)  # a float32 on the wire
                records.append(navigator.step(frame))
    given = [(r.altitude, f["truth"]) for r, f in zip(records, frames, strict=True)
             if r.altitude is not None and r.altitude.get("used")]
    assert len(given) >= len(frames) - 3
    errors = np.array([a["above_ground_m"] - t["altitude_m"] for a, t in given])
    assert np.max(np.abs(errors)) < 6.0


def test_the_documented_input_fields_are_pymavlinks_and_the_ones_read() -> None:
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "mavlink.md").read_text()
    section = doc[doc.index("## Input: the autopilot's altitude"):]
    rows = [[cell.strip(" `") for cell in line.split("|")[1:3]] for line in section.splitlines()
            if line.startswith("| `") and "(" in line.split("|")[1]]
    documented = {(m.split(" ")[0].strip("`"), f) for m, f in rows}
    assert len(documented) == 6
    for message, field in documented:
        cls = getattr(common, f"MAVLink_{message.lower()}_message")
        assert field in cls.fieldnames, (message, field)
    # Each documented field changes what is heard; an undocumented one (altitude_terrain) does not.
    from mapdb.navigation.mavlink import altitude_of

    base = {"ALTITUDE": common.MAVLink_altitude_message(0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0),
            "GLOBAL_POSITION_INT": common.MAVLink_global_position_int_message(0, 0, 0, 7000, 8000, 0, 0, 0, 0),
            "VFR_HUD": common.MAVLink_vfr_hud_message(0.0, 0.0, 0, 0, 9.0, 0.0)}
    for message, field in [*documented, ("ALTITUDE", "altitude_terrain")]:
        before = altitude_of(base[message])
        changed = base[message]
        setattr(changed, field, getattr(changed, field) + 1000)
        assert (altitude_of(changed) != before) == ((message, field) in documented), (message, field)
        setattr(changed, field, getattr(changed, field) - 1000)


def test_navigate_gives_frames_without_altitude_the_autopilots(maps, tmp_path) -> None:  # noqa: F811
    """``mapdb navigate --mavlink-in``: frames that carry no altitude get the autopilot's latest (ALTITUDE, above
    mean sea level over this map with elevation); a frame with its own keeps it; a bad address is one line."""
    import json
    import threading

    from clichecks import assert_one_line_error
    from click.testing import CliRunner
    from mapdb_cli.main import cli

    with open_map(maps["dem"]) as m:
        frames = simulate_flight(m, replace(OPTIONS, seed=7), waypoints(m), terrain=terrain_of(m))[:10]
    datum, own = frames[0]["baro_altitude_m"], frames[5]["baro_altitude_m"]  # one pressure altitude, plus noise
    for i, frame in enumerate(frames):
        if i != 5:
            frame.pop("baro_altitude_m")
    flight = tmp_path / "flight.jsonl"
    flight.write_text("".join(json.dumps(f) + "\n" for f in frames))
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    stop = threading.Event()

    def autopilot() -> None:  # says its altitude every few milliseconds, as a flight controller does
        sender = Autopilot(port)
        while not stop.is_set():
            try:
                sender.altitude(datum + 0.5, 0.0)
            except ConnectionRefusedError:  # nobody listens yet (before the command binds, or after it ends)
                pass
            time.sleep(0.002)

    thread = threading.Thread(target=autopilot, daemon=True)
    thread.start()
    try:
        time.sleep(0.05)
        track = tmp_path / "track.jsonl"
        result = CliRunner().invoke(cli, ["navigate", str(maps["dem"]), str(flight), "-o", str(track),
                                          "--mavlink-in", f"udpin:127.0.0.1:{port}", "-q"])
    finally:
        stop.set()
        thread.join(timeout=2)
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in track.read_text().splitlines()]
    baro = [r.get("altitude", {}).get("baro_m") for r in records]
    heard_frames = [i for i, b in enumerate(baro) if b is not None and i != 5]
    assert len(heard_frames) >= len(frames) - 3  # the first datagrams may come after the first frames
    assert all(baro[i] == pytest.approx(datum + 0.5, abs=1e-3) for i in heard_frames)
    assert baro[5] == pytest.approx(own, abs=1e-3) and abs(own - datum - 0.5) > 0.01  # the frame's own wins
    result = CliRunner().invoke(cli, ["navigate", str(maps["dem"]), str(flight), "-o", str(tmp_path / "t2.jsonl"),
                                      "--mavlink-in", "udpin:203.0.113.1:14550"])
    assert_one_line_error(result, "udpin:203.0.113.1:14550", "cannot open MAVLink input")
    assert not (tmp_path / "t2.jsonl").exists()
