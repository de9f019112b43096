"""Hostile frame streams for ``mapdb navigate``: whatever a line holds, it gets one record, and the flight goes on.

The cases are generated: every numeric field of a frame (time, image size, altitude, field of view, attitude,
inertial velocity, truth, id, an object's position and attributes) set to NaN, infinities, +-1e308, an integer
of 400 digits and values of the wrong type; lines that are not JSON, not objects, nested 100,000 deep, over
the 16 MiB line limit (50 MB), empty; times that go backwards, repeat, jump a billion seconds, or step by a
microsecond; thousands of objects, labels the map lacks, duplicated ids.  They are mixed with good frames
from ``mapdb simulate flight`` over the sample map and the stream is run through ``mapdb navigate MAP -``.
"""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.mapfile.reader import open_map
from mapdb.navigation.frames import MAX_SPEED_MPS, MAX_STEP_S, MAX_TIME_S, read_frame
from mapdb.navigation.navigator import Navigator, NavigatorOptions

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"
# A stream run must end well within this (the default run is a few seconds).
RUN_TIMEOUT_S = 300.0

# Values no sensor can give; each must be answered with a note, never a traceback.
BAD_NUMBERS: list[Any] = [math.nan, math.inf, -math.inf, 1e308, -1e308, 10**400, -(10**400)]
WRONG_TYPES: list[Any] = ["12", True, [1.0], {"v": 1.0}, "x" * 100_000, [[[[1e308]]]] * 1000]
# Where a frame holds a number (path of keys), and what a note about it must contain.
NUMERIC_FIELDS: dict[tuple[Any, ...], str] = {
    ("time_s",): "time_s",
    ("width",): "objects not used",
    ("height",): "objects not used",
    ("altitude_m",): "altitude_m",
    ("camera", "fov_deg"): "camera.fov_deg",
    ("attitude", "roll_deg"): "attitude.roll_deg",
    ("attitude", "pitch_deg"): "attitude.pitch_deg",
    ("attitude", "yaw_deg"): "attitude.yaw_deg",
    ("imu_velocity_mps", 0): "imu_velocity_mps",
    ("imu_velocity_mps", 1): "imu_velocity_mps",
    ("truth", "x"): "truth",
    ("truth", "y"): "truth",
    ("objects", 0, "x"): "objects not used",
    ("objects", 0, "y"): "objects not used",
    ("objects", 0, "area_px"): "objects not used",
    ("objects", 0, "bbox", 0): "objects not used",
}
# Fields that are a whole section: the wrong type of section is noted too.
SECTIONS: dict[str, str] = {"attitude": "attitude", "camera": "camera", "truth": "truth",
                            "imu_velocity_mps": "imu_velocity_mps", "objects": "objects not used",
                            "map_withheld": "map_withheld", "id": "id"}


def _run(*args: Any) -> Any:
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict]]:
    """The sample map and 3 s (31 frames) of a simulated flight over it, with an inertial velocity."""
    root = tmp_path_factory.mktemp("frames")
    map_path, flight_path = root / "helsinki.mapdb", root / "flight.jsonl"
    result = _run("build", SAMPLE, "-o", map_path, "-q")
    assert result.exit_code == 0, result.output
    result = _run("simulate", "flight", map_path, "--length", "60", "--imu-std", "0.3", "-o", flight_path, "-q")
    assert result.exit_code == 0, result.output
    frames = [json.loads(line) for line in flight_path.read_text().splitlines()]
    assert len(frames) == 31
    return map_path, frames


def navigate(map_path: Path, lines: list[bytes]) -> tuple[list[dict], int, str]:
    """``mapdb navigate MAP -`` over the lines: the records (strict JSON), the exit status and stderr."""
    proc = subprocess.run([sys.executable, "-m", "mapdb_cli", "navigate", str(map_path), "-", "--particles", "500"],
                          input=b"".join(line + b"\n" for line in lines), capture_output=True,
                          timeout=RUN_TIMEOUT_S)
    stderr = proc.stderr.decode("utf-8", "replace")
    records = [json.loads(line, parse_constant=pytest.fail) for line in proc.stdout.decode().splitlines()]
    return records, proc.returncode, stderr


def _without_times(record: dict) -> dict:
    return {k: v for k, v in record.items() if k != "time_ms"}


def _set(doc: dict, path: tuple[Any, ...], value: Any) -> dict:
    out = copy.deepcopy(doc)
    target = out
    for key in path[:-1]:
        if key == "bbox" and key not in target:
            target[key] = [0.0, 0.0, 1.0, 1.0]
        target = target[key]
    target[path[-1]] = value
    return out


def _line(doc: Any) -> bytes:
    # Python's writer spells NaN and Infinity as its reader accepts them: the navigator must refuse them.
    return json.dumps(doc).encode()


# ------------------------------------------------------------------------------------ read_frame


@pytest.mark.parametrize("path", list(NUMERIC_FIELDS), ids=lambda p: ".".join(map(str, p)))
def test_every_numeric_field_out_of_range_is_ignored_with_a_note(flight, path) -> None:
    _, frames = flight
    good = read_frame(frames[1], "good")
    assert good.notes == [] and good.time_s == 0.1 and good.image is not None and good.truth is not None
    for value in BAD_NUMBERS + WRONG_TYPES:
        frame = read_frame(_set(frames[1], path, value), "line 2")
        assert any(NUMERIC_FIELDS[path] in note for note in frame.notes), (path, repr(value)[:50], frame.notes)
        assert all(len(note) < 400 for note in frame.notes)  # a value is never echoed whole
        field = {"time_s": frame.time_s, "altitude_m": frame.altitude, "camera.fov_deg": frame.fov,
                 "attitude.roll_deg": frame.roll, "attitude.pitch_deg": frame.pitch, "attitude.yaw_deg": frame.yaw,
                 "imu_velocity_mps": frame.imu, "truth": frame.truth, "objects not used": frame.image}
        assert field[NUMERIC_FIELDS[path]] is None


@pytest.mark.parametrize("key", list(SECTIONS))
def test_a_section_of_the_wrong_type_is_ignored_with_a_note(flight, key) -> None:
    _, frames = flight
    values: list[Any] = ["yes", 3, [], {"x": None}, ["a", "b"]]
    if key == "objects":
        values = ["yes", 3, {"x": None}]
    elif key == "id":
        values = [3.5, True, [], {"x": None}, "x" * 1001]
    for value in values:
        if key in ("attitude", "camera") and isinstance(value, dict):
            continue  # an object without the fields is a section without sensors, not a wrong type
        frame = read_frame(_set(frames[1], (key,), value), "line 2")
        assert any(SECTIONS[key] in note for note in frame.notes), (key, value, frame.notes)


def test_the_bounds_are_plausible_flight_values(flight) -> None:
    _, frames = flight
    # A Unix-epoch clock, an unwrapped heading and a fast aircraft are within bounds; past them, not.
    assert read_frame({**frames[1], "time_s": 1.8e9}).time_s == 1.8e9
    assert read_frame({**frames[1], "time_s": MAX_TIME_S * 1.01}).time_s is None
    assert read_frame(_set(frames[1], ("attitude", "yaw_deg"), 7200.0)).yaw == 7200.0
    assert read_frame({**frames[1], "imu_velocity_mps": [0.0, MAX_SPEED_MPS]}).imu == complex(0, MAX_SPEED_MPS)
    assert read_frame({**frames[1], "imu_velocity_mps": [MAX_SPEED_MPS, 1.0]}).imu is None
    assert read_frame({**frames[1], "id": 10**17}).id == 10**17 and read_frame({**frames[1], "id": 10**18}).id is None


# ------------------------------------------------------------------------------------ the stream


def test_the_issue_frames_are_answered_and_the_stream_goes_on(flight) -> None:
    """Issue 28, N4: a ``time_s`` of 1e308 or an ``imu_velocity_mps`` of [1e308, -1e308] ended the stream."""
    map_path, frames = flight
    wild_time = {**frames[3], "time_s": 1e308}
    wild_imu = {**frames[4], "time_s": 0.35, "imu_velocity_mps": [1e308, -1e308]}
    lines = [_line(f) for f in frames[:4]] + [_line(wild_time), _line(wild_imu)] + [_line(f) for f in frames[4:9]]
    records, code, stderr = navigate(map_path, lines)
    assert code == 0 and stderr == ""
    assert len(records) == len(lines)
    assert records[4]["status"] == "skipped" and "time_s = 1e+308 is out of range" in records[4]["notes"][0]
    assert records[5]["notes"] == [f"imu_velocity_mps is faster than {MAX_SPEED_MPS:g} m/s: ignored"]
    assert [r["id"] for r in records[6:]] == [f["id"] for f in frames[4:9]]
    assert all(r["status"] == "fix" and r["truth"]["error_m"] < 3.0 for r in records[6:])


def _skipped_lines(frames: list[dict]) -> dict[int, list[bytes]]:
    """Lines that cannot be placed in the flight, to insert after good frame K: none may change the track."""
    f = frames
    deep = b'{"time_s": 0.25, "objects": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    return {
        2: [b"{oops", b"[1, 2, 3]", b"42", b'"a string"', b"null", b"\xff\xfe not UTF-8"],
        4: [_line({**f[4], "time_s": t}) for t in [math.nan, math.inf, -math.inf, 1e308, -1e308, -1.0, "0.45"]]
           + [_line({**f[4], "time_s": 10**400}), b'{"time_s": 1e400}'],
        6: [_line(f[6]), _line(f[3]), _line({**f[6], "time_s": f[6]["time_s"] + 1e-6})],  # repeated, backwards
        8: [_line({**f[8], "time_s": f[8]["time_s"] + 1e9})],  # one wild clock, not confirmed by the next frame
        10: [deep, b'{"time_s": 1.05, "id": ' + b"9" * 5000 + b"}", b"\x00\x01\x02", b"{}"],
        12: [b"{" + b" " * (50 << 20) + b"}"],  # 50 MB: over the 16 MiB line limit
        14: [b"", b"   \t", b""],  # blank lines: no document, no record
    }


@pytest.mark.slow
def test_lines_that_cannot_be_placed_leave_the_track_unchanged(flight) -> None:
    map_path, frames = flight
    good = [_line(f) for f in frames]
    clean, code, stderr = navigate(map_path, good)
    assert code == 0 and stderr == "" and len(clean) == len(frames)
    assert sum(r["status"] == "fix" for r in clean) >= 25 and all(r["truth"]["error_m"] < 3 for r in clean[5:])
    inserted = _skipped_lines(frames)
    lines: list[bytes] = []
    good_at: list[int] = []
    for k, line in enumerate(good):
        good_at.append(len(lines))
        lines.append(line)
        lines += inserted.get(k, [])
    records, code, stderr = navigate(map_path, lines)
    assert code == 0 and "Traceback" not in stderr and stderr == ""
    nonblank = [line for line in lines if line.strip(b" \t")]
    assert len(records) == len(nonblank)  # one record per non-blank line, in order
    at = {i: j for j, i in enumerate(i for i, line in enumerate(lines) if line.strip(b" \t"))}
    answered_good = [records[at[i]] for i in good_at]
    assert [_without_times(r) for r in answered_good] == [_without_times(r) for r in clean]
    bad = [r for i, r in enumerate(records) if i not in {at[g] for g in good_at}]
    assert len(bad) == sum(len(v) for v in inserted.values()) - 3
    for record in bad:
        assert record["status"] == "skipped" and record["notes"], record
        assert any(n.startswith("skipped: ") or "line" in n for n in record["notes"]), record["notes"]
    assert any("longer than 16777216 bytes" in n for r in bad for n in r["notes"])
    assert any(f"over {MAX_STEP_S:g} s" in n for r in bad for n in r["notes"])


def _noted_frames(frames: list[dict]) -> list[dict]:
    """Frames between two good ones (their own valid time) whose values are bad: each is used without them."""
    out: list[dict] = []
    base = {k: v for k, v in frames[10].items() if k != "objects"} | {"objects": []}
    for n, (path, _) in enumerate(NUMERIC_FIELDS.items()):
        if path == ("time_s",):
            continue
        for m, value in enumerate(BAD_NUMBERS + WRONG_TYPES[:4]):
            start = frames[10] if path[0] == "objects" else base
            out.append(_set(start, path, value) | {"time_s": round(1.0 + 0.0002 * (n * 20 + m + 1), 6)})
    return out


@pytest.mark.slow
def test_bad_values_are_answered_with_their_reason_and_the_flight_goes_on(flight) -> None:
    map_path, frames = flight
    noted = _noted_frames(frames)
    crowd = copy.deepcopy(frames[12])
    crowd["objects"] = [{"label": "building", "x": (37 * i) % 640, "y": (53 * i) % 480} for i in range(2000)]
    crowd["time_s"] = 1.25
    strangers = copy.deepcopy(frames[14])
    strangers["objects"] = [{**o, "label": f"unknown-{i}"} for i, o in enumerate(strangers["objects"])]
    strangers["time_s"] = 1.45
    too_many = {**frames[16], "objects": [{"label": "building", "x": 1, "y": 1}] * 20_001, "time_s": 1.65}
    twin = {**frames[18], "time_s": 1.85}  # the same id twice: ids are the caller's, both answered
    lines = ([_line(f) for f in frames[:11]] + [_line(f) for f in noted] + [_line(f) for f in frames[11:13]]
             + [_line(crowd)] + [_line(f) for f in frames[13:15]] + [_line(strangers)]
             + [_line(f) for f in frames[15:17]] + [_line(too_many)] + [_line(f) for f in frames[17:19]]
             + [_line(twin)] + [_line(f) for f in frames[19:]])
    records, code, stderr = navigate(map_path, lines)
    assert code == 0 and "Traceback" not in stderr and stderr == ""
    assert len(records) == len(lines)
    by_time = {r["time_s"]: r for r in records if r["time_s"] is not None}
    for frame in noted:
        record = by_time[frame["time_s"]]
        assert record.get("notes") and record["status"] != "skipped", (frame, record)
    assert any("20001 objects" in n for n in by_time[1.65]["notes"])
    assert by_time[1.85]["id"] == frames[18]["id"]
    assert by_time[1.25]["status"] != "skipped" and by_time[1.45]["status"] != "skipped"
    # The flight goes on: the last frames are fixed, within metres of the truth.
    last = records[-8:]
    assert [r["id"] for r in last] == [f["id"] for f in frames[-8:]]
    assert all(r["status"] == "fix" and r["truth"]["error_m"] < 3.0 for r in last), last


# ------------------------------------------------------------------------------------ the navigator


class _Failing:
    """A localizer that fails on frames of exactly ``count`` objects (a fault the frames cannot reach)."""

    def __init__(self, inner: Any, count: int, error: BaseException) -> None:
        self.inner, self.count, self.error = inner, count, error

    def localize(self, image: Any, prior: Any = None, **options: Any) -> Any:
        if len(image) == self.count:
            raise self.error
        return self.inner.localize(image, prior=prior, **options)


def test_a_frame_whose_navigation_fails_is_skipped_and_leaves_no_trace(flight) -> None:
    map_path, frames = flight
    odd = {**frames[5], "objects": frames[5]["objects"][:7], "time_s": 0.55}
    with open_map(map_path) as m:
        plain = Navigator(m, NavigatorOptions(particles=300))
        expected = [plain.step(f).to_json() for f in frames[:12]]
        failing = Navigator(m, NavigatorOptions(particles=300))
        failing.localizer = _Failing(failing.localizer, 7, RuntimeError("disk on fire"))  # type: ignore[assignment]
        got = [failing.step(f).to_json() for f in frames[:6] + [odd] + frames[6:12]]
        assert got[6]["status"] == "skipped" and "RuntimeError: disk on fire" in got[6]["notes"][-1]
        assert got[6]["x"] == got[5]["x"]  # the estimate before the frame
        assert [_without_times(r) for r in got[:6] + got[7:]] == [_without_times(r) for r in expected]
        # An interrupt is not a frame's fault: it ends the stream.
        failing.localizer = _Failing(failing.localizer, 7, KeyboardInterrupt())  # type: ignore[assignment]
        with pytest.raises(KeyboardInterrupt):
            failing.step({**odd, "time_s": 5.0})


def test_a_clock_jump_confirmed_by_the_next_frame_restarts_the_filter(flight) -> None:
    map_path, frames = flight
    later = [{**f, "time_s": f["time_s"] + 1e6} for f in frames[10:16]]
    with open_map(map_path) as m:
        navigator = Navigator(m, NavigatorOptions(particles=300))
        before = [navigator.step(f) for f in frames[:10]]
        after = [navigator.step(f) for f in later]
    assert before[-1].status == "fix"
    assert after[0].status == "skipped" and "over 300 s" in after[0].notes[-1]
    assert any("the filter restarts" in n for n in after[1].notes) and after[1].fix["status"] == "initialised"
    assert all(r.status == "fix" and r.truth is not None and r.truth["error_m"] < 3.0 for r in after[1:])


def test_labels_the_map_lacks_are_kept_for_one_frame_only(flight) -> None:
    map_path, frames = flight
    with open_map(map_path) as m:
        navigator = Navigator(m, NavigatorOptions(particles=300))
        for k, f in enumerate(frames[:12]):
            renamed = [{**o, "label": f"new-{k}-{o['label']}"} for o in f["objects"]]
            navigator.step({**f, "objects": renamed})
        known = len(m.labels)
    # The label table is the map's; the unknown labels held are the last frame's alone.
    assert len(navigator.labels) == known
    assert set(navigator.previous.extra_labels) == {f"new-11-{o['label']}" for o in frames[11]["objects"]}
