"""Navigation over a flight: the flight simulator, frame-to-frame velocity, the particle filter, ``mapdb navigate``.

The quick tests fly a few seconds over a synthetic map of random labelled objects (as dense as an old
town); the slow ones fly long flights, and over the real extracts when ``../shared/data`` is present.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from clichecks import answered_one_by_one
from click.testing import CliRunner
from mapdb_cli.main import cli
from navworld import ERRORS, WAYPOINTS, fly, synthetic_world

from mapdb.camera import Camera
from mapdb.detections.images import parse_image
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.writer import write_map
from mapdb.navigation.filter import FixComponent, ParticleFilter
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.frames import read_frame
from mapdb.navigation.navigator import Navigator
from mapdb.navigation.path import FlightPath, read_linestring, survey_pattern
from mapdb.navigation.track import track_geojson
from mapdb.navigation.velocity import frame_points, match_frames, velocity_from_motion
from mapdb.objects import Objects
from mapdb.simulation.simulate import PAPER_CRS, PAPER_ORIGIN

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "osm"
ANSWER_TIMEOUT_S = 60.0
X0, Y0 = PAPER_ORIGIN


world = pytest.fixture(scope="module", name="world")(synthetic_world)  # the synthetic world (tests/navworld.py)
_flight = fly


def _navigate(world: MemoryMap, frames: list[dict], initial=None, **kw) -> list:
    navigator = Navigator(world, initial=initial, **kw)
    return [navigator.step(frame, f"line {i + 1}") for i, frame in enumerate(frames)]


def _errors(records) -> np.ndarray:
    return np.array([r.truth["error_m"] if r.truth["error_m"] is not None else np.inf for r in records])


# ------------------------------------------------------------------------------------------- flight


def test_a_flight_follows_its_path_with_sensors_and_truth(world) -> None:
    frames = _flight(world, 6.0, blackouts=((2.0, 1.0),), map_gaps=((4.0, 1.0),), imu_std_mps=0.3)
    assert len(frames) == 61 and [f["time_s"] for f in frames[:3]] == [0.0, 0.1, 0.2]
    for frame in frames:
        parse_image({k: v for k, v in frame.items() if k != "truth"})  # every frame is a query input
        truth = frame["truth"]
        assert abs(complex(*truth["velocity_mps"])) == pytest.approx(20.0)
        assert frame["altitude_m"] == pytest.approx(100.0, abs=10.0)  # barometric, with bias and noise
        assert abs((frame["attitude"]["yaw_deg"] - truth["heading_deg"] + 180) % 360 - 180) < 5.0
    blackout = [f for f in frames if 2.0 <= f["time_s"] < 3.0]
    assert len(blackout) == 10 and all(not f["objects"] and f["truth"]["blackout"] for f in blackout)
    assert all(f["truth"]["n_visible"] > 0 for f in blackout)  # the ground was there; the detector saw nothing
    assert [f["time_s"] for f in frames if f.get("map_withheld")] == pytest.approx(np.arange(40, 50) / 10)
    assert np.median([len(f["objects"]) for f in frames if f["objects"]]) >= 8
    # Positions advance 2 m a frame along the first leg.
    z = np.array([complex(f["truth"]["x"], f["truth"]["y"]) for f in frames[:10]])
    assert np.allclose(np.diff(z), 2.0)
    assert _flight(world, 6.0, blackouts=((2.0, 1.0),), map_gaps=((4.0, 1.0),), imu_std_mps=0.3) == frames


def test_paths_turn_smoothly_and_surveys_cover_the_dense_part(world, tmp_path) -> None:
    path = FlightPath.from_waypoints(WAYPOINTS, turn_radius_m=75.0)
    assert path.length == pytest.approx(1200 - 2 * 75 + 75 * math.pi / 2)
    s = np.linspace(0.0, path.length, 2001)
    z, tangent, curvature = path.at(s)
    assert np.max(np.abs(np.diff(z))) <= (s[1] - s[0]) * 1.0001  # continuous, speed one
    assert np.max(np.abs(np.diff(tangent))) < 0.01  # no kink in the heading
    assert set(np.round(curvature, 6)) == {0.0, round(1 / 75.0, 6)}  # a left turn
    # A survey of a map with a dense block sits on the block.
    rng = np.random.default_rng(1)
    dense = Objects.from_names(np.r_[rng.uniform(0, 5000, 200), rng.uniform(3000, 3800, 2000)],
                               np.r_[rng.uniform(0, 5000, 200), rng.uniform(1000, 1800, 2000)],
                               ["building"] * 2200, crs=PAPER_CRS)
    waypoints = survey_pattern(dense, 3000.0)
    inside = (waypoints.real > 2950) & (waypoints.real < 3850) & (waypoints.imag > 950) & (waypoints.imag < 1850)
    assert inside.all() and FlightPath.from_waypoints(waypoints).length >= 3000.0
    line = tmp_path / "line.geojson"
    line.write_text(json.dumps({"type": "Feature", "properties": {},
                                "geometry": {"type": "LineString", "coordinates": [[3.0, 45.1], [3.01, 45.1]]}}))
    w = read_linestring(line, PAPER_CRS)
    assert abs(w[1] - w[0]) == pytest.approx(788.0, rel=0.01)  # 0.01 degree of longitude at 45.1 N


# ----------------------------------------------------------------------------------------- velocity


def _frame_points(frame: dict, labels: dict[str, int]):
    im = parse_image({k: v for k, v in frame.items() if k != "truth"})
    codes = np.array([labels.setdefault(n, len(labels)) for n in im.names], np.int64)
    return frame_points(im, codes, frame["attitude"]["roll_deg"], frame["attitude"]["pitch_deg"])


def test_velocity_from_two_frames_is_the_true_motion_within_its_uncertainty(world) -> None:
    frames = _flight(world, 3.0)
    labels: dict[str, int] = {}
    points = [_frame_points(f, labels) for f in frames]
    focal = Camera(640, 480, 60.0).focal_px
    level = 100.0 * math.tan(math.radians(0.1))
    chi2, failed = [], []
    for k in range(1, len(frames)):
        prev = frames[k - 1]["truth"]
        to_map = prev["altitude_m"] / focal * complex(np.exp(-1j * math.radians(prev["heading_deg"])))
        truth = complex(*frames[k]["truth"]["velocity_mps"])
        for guess in (None, truth * 0.1 / to_map):  # votes for the translation, and the filter's guess
            motion = match_frames(points[k - 1], points[k], 1 + 0j, guess, len(labels))
            if isinstance(motion, str):  # too few objects seen in both frames: said, not guessed
                failed.append(motion)
                continue
            vel = velocity_from_motion(motion, to_map, 0.1, level_sigma_m=level)
            e = np.array([(vel.v - truth).real, (vel.v - truth).imag])
            chi2.append(float(e @ np.linalg.solve(vel.cov, e)))
    assert len(failed) <= 0.1 * len(chi2), failed
    chi2 = np.array(chi2)
    # A 2-D normal error measured by its own covariance: chi-square with 2 degrees of freedom.
    assert np.mean(chi2) == pytest.approx(2.0, abs=0.8)
    assert np.mean(chi2 < 13.8) > 0.97


# ------------------------------------------------------------------------------------------- filter


def test_a_wrong_fix_does_not_capture_the_estimate() -> None:
    f = ParticleFilter(2000, accel_std=0.5, seed=3)
    truth, v = complex(1000, 2000), complex(20, 0)
    f.initialise(truth, 5.0, velocity=v, velocity_sigma=0.5)
    for _ in range(20):  # tracking: a good fix every frame
        truth += v * 0.1
        f.predict(0.1)
        assert f.update_fix([FixComponent(truth, 0.3, 1.0)], area_m2=math.pi * 10.0**2).applied
    truth += v * 0.1
    f.predict(0.1)
    wrong = truth + complex(0, 60)
    outcome = f.update_fix([FixComponent(wrong, 0.2, 1.0)], area_m2=math.pi * 100.0**2)
    assert not outcome.applied and outcome.inlier_probability < 0.01 and outcome.distance_m > 55
    assert abs(f.estimate()[0] - truth) < 1.0
    # Multi-modal: the best place is wrong, a runner-up is right: the filter keeps to the right one.
    truth += v * 0.1
    f.predict(0.1)
    outcome = f.update_fix([FixComponent(truth + 40j, 0.2, 1.0), FixComponent(truth, 0.3, 0.1)],
                           area_m2=math.pi * 100.0**2)
    assert outcome.applied and abs(f.estimate()[0] - truth) < 1.0
    assert f.estimate()[2].max() < 1.0  # the wrong mode took no weight


def test_the_filter_recovers_when_started_200_m_off(world) -> None:
    frames = _flight(world, 8.0)
    start = frames[0]["truth"]
    records = _navigate(world, frames, initial=(start["x"] + 200.0, start["y"], 30.0))
    error = _errors(records)
    assert error[0] > 150  # it believed the wrong start ...
    recovered = int(np.argmax(error < 1.0))
    assert 0 < recovered <= 30, error[:40]  # ... and was back within 3 s
    assert np.all(error[recovered:] < 2.0) and math.sqrt(np.mean(error[recovered:] ** 2)) < 1.0
    # The frame's own fix draws them; a fix from the stitched frames may follow in the same frame (fix.single).
    reasons = [(r.fix.get("reason") or "") + ((r.fix.get("single") or {}).get("reason") or "") for r in records]
    assert any("particles drawn there" in reason for reason in reasons[: recovered + 1])


def test_a_blackout_predicts_only_and_the_track_holds(world) -> None:
    frames = _flight(world, 8.0, blackouts=((3.0, 2.0),))
    start = frames[0]["truth"]
    records = _navigate(world, frames, initial=(start["x"], start["y"], 20.0))
    error = _errors(records)
    during = [r for r, f in zip(records, frames) if f["truth"]["blackout"]]
    assert len(during) == 20
    assert all(r.status == "predicting" and r.fix == {"status": "none", "reason": "0 objects: no query"}
               for r in during)
    assert all(r.velocity_measurement["status"] == "none" for r in during)
    sigma = [r.sigma_m for r in during]
    assert sigma[-1] > 2 * sigma[0]  # the stated uncertainty grows while nothing is measured
    assert np.max(error) < 5.0 and math.sqrt(np.mean(error**2)) < 1.0
    assert records[52].status == "fix"  # fixed again as soon as the detector is back


def test_bad_frames_are_answered_with_a_reason(world) -> None:
    frames = _flight(world, 2.0)
    start = frames[0]["truth"]
    nan_frame = {**frames[3], "altitude_m": float("nan"), "attitude": {**frames[3]["attitude"], "roll_deg": "x"}}
    lost = {**frames[6], "objects": [{"label": "building", "x": 1.0, "y": 1.0}] * 2}
    stream = [frames[0], frames[1], frames[2], frames[1], nan_frame, ValueError("line 6: malformed JSON"),
              {**frames[5], "objects": []}, lost, {**frames[7], "objects": "oops"}, frames[8]]
    records = _navigate(world, stream, initial=(start["x"], start["y"], 20.0))
    assert [r.status for r in records][:3] == ["fix", "fix", "fix"]
    assert records[3].status == "skipped" and "out of time order: time_s 0.1 is not after 0.2" in records[3].notes[0]
    assert records[4].status == "fix"  # the other sensors still serve
    assert "altitude_m is nan: ignored" in records[4].notes and "attitude.roll_deg is not a number: ignored" in \
        records[4].notes
    assert records[5].status == "skipped" and records[5].notes[0] == "line 6: malformed JSON"
    assert records[6].status == "predicting" and records[6].fix["reason"] == "0 objects: no query"
    assert records[7].fix["reason"] == "2 objects: no query"
    assert any("objects not used" in n for n in records[8].notes)
    assert records[9].status == "fix" and records[9].truth["error_m"] < 1.0
    # No initial position and no possible first fix: "not initialised", no position made up.
    blind = _navigate(world, [{**f, "objects": f["objects"][:2]} for f in frames[:5]])
    assert {r.status for r in blind} == {"not initialised"} and not any(r.placed for r in blind)
    # Started outside the map: each frame says why there is no fix.
    far = _navigate(world, frames[:3], initial=(X0 - 50_000.0, Y0, 20.0))
    assert all("outside" in r.fix["reason"] for r in far)


# --------------------------------------------------------------------------------------------- CLI


def test_simulate_flight_and_navigate_commands(world, tmp_path) -> None:
    map_path = tmp_path / "world.mapdb"
    write_map(map_path, world.all())
    flight = tmp_path / "flight.jsonl"
    line = tmp_path / "line.geojson"
    lonlat = _lonlat(WAYPOINTS)
    line.write_text(json.dumps({"type": "LineString", "coordinates": lonlat}))
    result = CliRunner().invoke(cli, ["simulate", "flight", str(map_path), "-o", str(flight), "--path", str(line),
                                      "--length", "60", "--altitude", "100", "--fov", "60", "--pixel-std", "1",
                                      "--blackout", "1:0.5", "-q"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    frames = [json.loads(x) for x in flight.read_text().splitlines()]
    assert len(frames) == 31 and sum(1 for f in frames if f["truth"]["blackout"]) == 5
    track, geojson, picture = tmp_path / "track.jsonl", tmp_path / "track.geojson", tmp_path / "track.png"
    start = frames[0]["truth"]
    result = CliRunner().invoke(cli, ["navigate", str(map_path), str(flight), "-o", str(track), "--geojson",
                                      str(geojson), "--plot", str(picture), "--initial",
                                      f"{start['x']},{start['y']},20", "-q"], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    records = [json.loads(x, parse_constant=pytest.fail) for x in track.read_text().splitlines()]
    assert len(records) == 31 and all(r["truth"]["error_m"] < 2.0 for r in records)
    assert records[-1]["crs"] == PAPER_CRS and 2.9 < records[-1]["lon"] < 3.1
    # One geometry type a file: the frames as points, the path as a line beside them.
    points, line = json.loads(geojson.read_text()), json.loads((tmp_path / "track_line.geojson").read_text())
    assert "crs" not in points and {f["geometry"]["type"] for f in points["features"]} == {"Point"}
    assert len(points["features"]) == 31 and [f["geometry"]["type"] for f in line["features"]] == ["LineString"]
    coords = np.array(line["features"][0]["geometry"]["coordinates"])
    assert coords.shape == (31, 2) and np.all(np.abs(coords[:, 0] - 3.0) < 0.1) and np.all(coords[:, 1] > 45)
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A file that cannot be read is the one error.
    result = CliRunner().invoke(cli, ["navigate", str(map_path), str(tmp_path / "missing.jsonl")])
    assert result.exit_code == 1 and result.output.startswith("mapdb: error: ") and "missing.jsonl" in result.output
    assert track_geojson([])["features"] == []


def _lonlat(z: np.ndarray) -> list[list[float]]:
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(PAPER_CRS, "EPSG:4326", always_xy=True).transform(z.real, z.imag)
    return [[float(a), float(b)] for a, b in zip(lon, lat)]


def test_navigate_on_a_pipe_answers_each_frame_before_the_next_is_sent(world, tmp_path) -> None:
    map_path = tmp_path / "world.mapdb"
    write_map(map_path, world.all())
    frames = _flight(world, 0.6)
    start = frames[0]["truth"]
    lines = [json.dumps(f).encode() for f in frames[:3]] + [b"{oops"] + [json.dumps(f).encode() for f in frames[3:]]
    args = ["navigate", str(map_path), "-", "--initial", f"{start['x']},{start['y']},20"]
    for i, record in answered_one_by_one(args, lines, ANSWER_TIMEOUT_S):
        if i == 3:
            assert record["status"] == "skipped" and "<stdin> line 4: malformed JSON" in record["notes"][0]
        else:
            assert record["id"] == json.loads(lines[i])["id"] and record["status"] == "fix", record


def test_frames_read_each_sensor_on_its_own() -> None:
    frame = read_frame({"id": "f", "time_s": 2, "width": 640, "height": 480, "objects": [],
                        "imu_velocity_mps": [1.0, float("inf")], "camera": {"fov_deg": 500},
                        "attitude": {"pitch_deg": 95, "yaw_deg": True}, "map_withheld": True})
    assert (frame.time_s, frame.imu, frame.fov, frame.pitch, frame.yaw, frame.withheld) == (2.0, None, None, None,
                                                                                            None, True)
    assert len(frame.notes) == 4 and frame.image is not None and len(frame.image) == 0
    assert read_frame({"width": 640}).notes[0] == "time_s is missing"


# -------------------------------------------------------------------------------------------- slow


@pytest.mark.slow
def test_a_long_flight_with_a_blackout_and_a_map_gap(world) -> None:
    frames = _flight(world, 60.0, blackouts=((20.0, 2.0),), map_gaps=((35.0, 10.0),))
    start = frames[0]["truth"]
    records = _navigate(world, frames, initial=(start["x"], start["y"], 20.0))
    error = _errors(records)
    gap = np.array([bool(f.get("map_withheld")) for f in frames])
    assert math.sqrt(np.mean(error[~gap] ** 2)) < 1.0 and np.max(error) < 10.0
    end = int(np.flatnonzero(gap)[-1]) + 1
    assert np.all(error[end + 20:] < 1.0)  # snapped back within 2 s of the map returning
    assert all(r.fix["status"] == "withheld" for r in np.array(records, dtype=object)[gap])


@pytest.mark.slow
@pytest.mark.skipif(not SHARED.exists(), reason="../shared/data/osm (the real extracts) is not present")
def test_a_flight_over_monaco(tmp_path) -> None:
    from mapdb.build.pipeline import build_map
    from mapdb.mapfile.reader import open_map

    map_path = tmp_path / "monaco.mapdb"
    build_map([SHARED / "monaco-2021-12-03.osm.pbf"], map_path)
    with open_map(map_path) as m:
        frames = simulate_flight(m, FlightOptions(length_m=1500.0, blackouts=((20.0, 2.0),), **ERRORS))
        start = frames[0]["truth"]
        records = _navigate(m, frames, initial=(start["x"], start["y"], 30.0))
    error = _errors(records)
    assert math.sqrt(np.mean(error**2)) < 1.0 and np.max(error) < 10.0
