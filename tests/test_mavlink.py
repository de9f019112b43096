"""``mapdb navigate --mavlink``: the track sent to an autopilot as MAVLink, decoded by a pymavlink listener.

A flight is simulated over the sample map (Helsinki), navigated with ``--mavlink udpout:127.0.0.1:PORT`` to a
UDP socket of the test, and every message is decoded and compared with the track written beside it.
"""

from __future__ import annotations

import json
import math
import re
import socket
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.build.pipeline import build_map
from mapdb.navigation.mavlink import GPS_EPOCH_UNIX_S, GPS_LEAP_S, MavlinkMissingError, MavlinkOut, gps_time

common = pytest.importorskip("pymavlink.dialects.v20.common", reason="pymavlink is not installed (mapdb[mavlink])")

SAMPLE = Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> tuple[Path, Path]:
    """The sample map and a 5 s flight over it (51 frames at 10 per second)."""
    root = tmp_path_factory.mktemp("mavlink")
    map_path = root / "helsinki.mapdb"
    build_map([SAMPLE], map_path)
    frames = root / "flight.jsonl"
    result = CliRunner().invoke(cli, ["simulate", "flight", str(map_path), "-o", str(frames), "--length", "100",
                                      "--pixel-std", "1", "--attitude-std", "0.1", "--seed", "3", "-q"])
    assert result.exit_code == 0, result.output
    return map_path, frames


def _listener() -> tuple[socket.socket, int]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    return sock, sock.getsockname()[1]


def _received(sock: socket.socket) -> list:
    """Every message waiting on the socket, decoded (a datagram that does not decode fails the test)."""
    sock.settimeout(0.5)
    parser, messages = common.MAVLink(None), []
    try:
        while True:
            decoded = parser.parse_buffer(sock.recv(65536))
            assert decoded, "a datagram that is not a MAVLink message"
            messages += decoded
    except TimeoutError:
        pass
    return messages


def _navigate(map_path: Path, frames: Path, track: Path, *extra: str):
    return CliRunner().invoke(cli, ["navigate", str(map_path), str(frames), "-o", str(track), *extra])


def test_every_record_arrives_as_gps_input_with_its_position_and_accuracies(flight, tmp_path) -> None:
    map_path, frames = flight
    sock, port = _listener()
    track = tmp_path / "track.jsonl"
    with sock:
        result = _navigate(map_path, frames, track, "--mavlink", f"udpout:127.0.0.1:{port}", "--mavlink-vision")
        assert result.exit_code == 0, result.output
        messages = _received(sock)
    records = [json.loads(line) for line in track.read_text().splitlines()]
    gps = [m for m in messages if m.get_type() == "GPS_INPUT"]
    vision = [m for m in messages if m.get_type() == "GLOBAL_VISION_POSITION_ESTIMATE"]
    assert len(records) == 51 and len(gps) == len(records) and len(vision) == sum(r["x"] is not None for r in records)
    assert f"{len(messages)} MAVLink messages sent" in result.stderr and "lost" not in result.stderr
    for record, message in zip(records, gps, strict=True):
        assert message.fix_type == 3 and record["lat"] is not None
        assert abs(message.lat / 1e7 - record["lat"]) < 1e-7 and abs(message.lon / 1e7 - record["lon"]) < 1e-7
        largest = math.sqrt(float(np.linalg.eigvalsh(np.array(record["cov_m2"]))[-1]))
        assert message.horiz_accuracy == pytest.approx(largest, rel=1e-3, abs=1e-3)
        speed = math.hypot(message.vn, message.ve)  # the ground velocity has the track's speed (UTM scale ~1)
        assert speed == pytest.approx(record["speed_mps"], rel=2e-3, abs=2e-3)
        if record["velocity"].get("status") == "used":
            assert message.speed_accuracy == pytest.approx(record["velocity"]["sigma_mps"], abs=1e-6)
    # The GPS time keeps the records' time steps.
    times = np.array([m.time_week * 604800e3 + m.time_week_ms for m in gps])
    assert np.allclose(np.diff(times), 1e3 * np.diff([r["time_s"] for r in records]), atol=1.0)
    # The vision estimate's covariance holds the position covariance (its trace, turned to true north).
    placed = [r for r in records if r["x"] is not None]
    for record, message in zip(placed, vision, strict=True):
        trace = record["cov_m2"][0][0] + record["cov_m2"][1][1]  # (written with 4 decimals)
        assert message.covariance[0] + message.covariance[6] == pytest.approx(trace, rel=2e-3, abs=3e-4)
    north = [m.x for m in vision]
    assert vision[0].x == vision[0].y == 0.0 and abs(north[-1]) + abs(vision[-1].y) > 50  # 100 m flown


def test_a_receiver_that_is_gone_costs_messages_not_the_navigation(flight, tmp_path) -> None:
    map_path, frames = flight
    sock, port = _listener()
    sock.close()  # nobody listens: every datagram is refused
    track = tmp_path / "track.jsonl"
    result = _navigate(map_path, frames, track, "--mavlink", f"udpout:127.0.0.1:{port}", "-q")
    assert result.exit_code == 0, result.output
    assert len(track.read_text().splitlines()) == 51
    assert "51 MAVLink messages sent, 51 lost" in result.stderr


def test_a_receiver_that_goes_away_mid_flight_is_counted(flight, tmp_path) -> None:
    map_path, frames = flight
    sock, port = _listener()
    heard: list[bytes] = []

    def listen_then_leave() -> None:
        with sock:
            while len(heard) < 10:
                heard.append(sock.recv(65536))

    listener = threading.Thread(target=listen_then_leave, daemon=True)
    listener.start()
    track = tmp_path / "track.jsonl"
    result = _navigate(map_path, frames, track, "--mavlink", f"udpout:127.0.0.1:{port}", "-q")
    listener.join(timeout=5)
    assert result.exit_code == 0 and len(track.read_text().splitlines()) == 51
    lost = int(re.search(r"51 MAVLink messages sent, (\d+) lost", result.stderr).group(1))
    # datagrams queued in the socket when it closed are neither heard nor seen refused: at most 51 - 10
    assert len(heard) == 10 and 1 <= lost <= 51 - 10


def test_an_address_that_cannot_be_opened_is_one_line_before_any_frame(flight, tmp_path) -> None:
    map_path, _ = flight
    track = tmp_path / "track.jsonl"
    # stdin holds no frames: the error must come before any is read, and leave no output
    result = CliRunner().invoke(cli, ["navigate", str(map_path), "-", "-o", str(track), "--mavlink",
                                      "udpout:no-such-host.invalid:14550"], input="")
    assert_one_line_error(result, "udpout:no-such-host.invalid:14550", "cannot open MAVLink output")
    assert not track.exists()
    result = CliRunner().invoke(cli, ["navigate", str(map_path), "-", "--mavlink", "tcp:127.0.0.1:5760"])
    assert result.exit_code == 2 and "udpout:HOST:PORT" in result.output


def test_without_pymavlink_the_option_says_what_to_install(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "pymavlink.dialects.v20", None)  # as when the package is absent
    with pytest.raises(MavlinkMissingError, match=r"pip install 'mapdb\[mavlink\]'"):
        MavlinkOut("udpout:127.0.0.1:9")


def test_gps_time_counts_weeks_from_1980_with_the_leap_seconds() -> None:
    # 2024-01-01T00:00:00Z is GPS week 2295, 86418 s into it (Monday, plus the 18 leap seconds).
    assert gps_time(1704067200.0) == (2295, 86_418_000)
    assert gps_time(GPS_EPOCH_UNIX_S - GPS_LEAP_S) == (0, 0)


def test_help_does_not_import_pymavlink() -> None:
    code = textwrap.dedent("""
        import sys
        from mapdb_cli.main import cli
        for args in (["--help"], ["navigate", "--help"]):
            try:
                cli(args, standalone_mode=False)
            except SystemExit:
                pass
        print("pymavlink" in sys.modules)
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.splitlines()[-1] == "False", done.stderr[-2000:]


def test_docs_name_every_field_and_flag_as_pymavlink_defines_them() -> None:
    doc = (Path(__file__).resolve().parents[1] / "docs" / "mavlink.md").read_text()
    rows = {cell.strip("` ") for line in doc.splitlines() if line.startswith("| `")
            for cell in line.split("|")[1].split(",")}
    for message in (common.MAVLink_gps_input_message, common.MAVLink_global_vision_position_estimate_message):
        assert set(message.fieldnames) <= rows, set(message.fieldnames) - rows
    for name in ("ALT", "VEL_HORIZ", "VEL_VERT", "SPEED_ACCURACY", "VERTICAL_ACCURACY"):
        value = getattr(common, f"GPS_INPUT_IGNORE_FLAG_{name}")
        assert f"`{name}` ({value})" in doc or f"`GPS_INPUT_IGNORE_FLAG_{name}` ({value})" in doc, name


def test_a_barometric_altitude_above_sea_level_is_sent_as_it_is(flight, tmp_path) -> None:
    """A frame's ``baro_altitude_m`` (above mean sea level) is GPS_INPUT's altitude itself; ``altitude_m``
    (above ground) gets ``--mavlink-ground-alt`` added; a frame with neither leaves the altitude ignored."""
    map_path, frames = flight
    docs = [json.loads(line) for line in frames.read_text().splitlines()]
    for i, doc in enumerate(docs):
        doc.pop("altitude_m", None)
        if i % 3 == 0:
            doc["baro_altitude_m"] = 512.5 + i
        elif i % 3 == 1:
            doc["altitude_m"] = 100.0 + i
    edited = tmp_path / "baro.jsonl"
    edited.write_text("".join(json.dumps(doc) + "\n" for doc in docs))
    sock, port = _listener()
    with sock:
        result = _navigate(map_path, edited, tmp_path / "track.jsonl", "--mavlink", f"udpout:127.0.0.1:{port}",
                           "--mavlink-ground-alt", "30", "-q")
        assert result.exit_code == 0, result.output
        gps = [m for m in _received(sock) if m.get_type() == "GPS_INPUT"]
    assert len(gps) == len(docs)
    placed = [(i, m) for i, m in enumerate(gps) if m.fix_type == 3]
    assert len(placed) > 20
    for i, message in placed:
        ignored = bool(message.ignore_flags & 1)
        if i % 3 == 0:
            assert not ignored and message.alt == pytest.approx(512.5 + i)
        elif i % 3 == 1:
            assert not ignored and message.alt == pytest.approx(130.0 + i)
        else:
            assert ignored
