"""Simulated images: projection signs, the true-correspondence bound, determinism, real maps, the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.camera import Camera, Pose, image_to_ground, level_pixels, nadir_pixel, project_to_image
from mapdb.errors import EmptyMapError
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match.geometry import apply_similarity, fit_similarity
from mapdb.objects import Objects
from mapdb.simulation.simulate import paper_map, simulate_images

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# Focal length of a 640 px wide image with a 35 degree horizontal field of view, written out from its
# definition f = (w / 2) / tan(fov / 2) rather than taken from Camera.
F = 320.0 / math.tan(math.radians(17.5))
T10 = math.tan(math.radians(10.0))
CAM = Camera(640, 480, 35.0)
X0, Y0, ALT = 500_000.0, 5_000_000.0, 100.0
# Exact up to rounding: map coordinates near 5e6 m carry about 1e-9 m, i.e. 1e-8 px, of float error.
EXACT = 1e-6


def _pixels(dx: list[float], dy: list[float], **attitude: float) -> np.ndarray:
    """Pixels of map points offset (east dx, north dy) from a camera at (X0, Y0, 100 m)."""
    u, v = project_to_image(X0 + np.array(dx), Y0 + np.array(dy), Pose(X0, Y0, ALT, **attitude), CAM)
    return np.column_stack([u, v])


def test_projection_level_heading_north_is_a_map_seen_from_above() -> None:
    # Pinhole: u = 320 + F * east / 100, v = 240 - F * north / 100.
    got = _pixels([0.0, 20.0, 0.0, -15.0], [0.0, 10.0, -30.0, 5.0])
    expected = [[320.0, 240.0], [320.0 + 0.2 * F, 240.0 - 0.1 * F], [320.0, 240.0 + 0.3 * F],
                [320.0 - 0.15 * F, 240.0 - 0.05 * F]]
    np.testing.assert_allclose(got, expected, rtol=0, atol=EXACT)


def test_projection_yaw_is_a_clockwise_heading() -> None:
    # Heading east (yaw 90): image up is east, so a point 20 m east is above the centre and a point
    # 10 m north is to the left (north rotated counter-clockwise on the displayed image).
    got = _pixels([20.0, 0.0], [0.0, 10.0], yaw_deg=90.0)
    np.testing.assert_allclose(got, [[320.0, 240.0 - 0.2 * F], [320.0 - 0.1 * F, 240.0]], rtol=0, atol=EXACT)
    # Yaw 30: forward = north cos30 + east sin30, right = -north sin30 + east cos30.
    got = _pixels([0.0], [10.0], yaw_deg=30.0)
    c30 = math.sqrt(3.0) / 2.0
    np.testing.assert_allclose(got, [[320.0 - 0.05 * F, 240.0 - 0.1 * c30 * F]], rtol=0, atol=EXACT)


def test_projection_pitch_nose_up_looks_ahead() -> None:
    # Nose up 10 deg: the point 100 tan(10) m ahead (north) is at the centre; the nadir is F tan(10) below it.
    got = _pixels([0.0, 0.0], [100.0 * T10, 0.0], pitch_deg=10.0)
    np.testing.assert_allclose(got, [[320.0, 240.0], [320.0, 240.0 + F * T10]], rtol=0, atol=EXACT)


def test_projection_roll_right_wing_down_looks_left() -> None:
    # Right wing down 10 deg: the point 100 tan(10) m to the left (west) is at the centre; the nadir
    # appears F tan(10) right of it.
    got = _pixels([-100.0 * T10, 0.0], [0.0, 0.0], roll_deg=10.0)
    np.testing.assert_allclose(got, [[320.0, 240.0], [320.0 + F * T10, 240.0]], rtol=0, atol=EXACT)


def test_projection_attitude_follows_the_heading() -> None:
    # Heading east: nose up looks further east; right wing down looks left of the heading, i.e. north.
    got = _pixels([100.0 * T10, 0.0], [0.0, 100.0 * T10], yaw_deg=90.0, pitch_deg=10.0)
    np.testing.assert_allclose(got[0], [320.0, 240.0], rtol=0, atol=EXACT)
    got = _pixels([0.0, 0.0], [100.0 * T10, 0.0], yaw_deg=90.0, roll_deg=10.0)
    np.testing.assert_allclose(got, [[320.0, 240.0], [320.0 + F * T10, 240.0]], rtol=0, atol=EXACT)


def test_inverse_projection_and_levelling_undo_the_projection() -> None:
    rng = np.random.default_rng(4)
    gx, gy = X0 + rng.uniform(-30, 30, 20), Y0 + rng.uniform(-20, 20, 20)
    pose = Pose(X0, Y0, ALT, yaw_deg=37.0, roll_deg=1.5, pitch_deg=-2.0)
    u, v = project_to_image(gx, gy, pose, CAM)
    bx, by = image_to_ground(u, v, pose, CAM)
    np.testing.assert_allclose(np.column_stack([bx, by]), np.column_stack([gx, gy]), rtol=0, atol=1e-6)
    # Levelled pixels are those of a level camera at the same place and heading.
    lu, lv = level_pixels(u, v, CAM, roll_deg=1.5, pitch_deg=-2.0)
    eu, ev = project_to_image(gx, gy, Pose(X0, Y0, ALT, yaw_deg=37.0), CAM)
    np.testing.assert_allclose(np.column_stack([lu, lv]), np.column_stack([eu, ev]), rtol=0, atol=1e-8)
    nu, nv = nadir_pixel(CAM, roll_deg=1.5, pitch_deg=-2.0)
    pu, pv = project_to_image([X0], [Y0], pose, CAM)
    assert (nu, nv) == pytest.approx((float(pu[0]), float(pv[0])), abs=1e-9)


def test_fit_similarity_recovers_a_known_transform() -> None:
    rng = np.random.default_rng(0)
    src = rng.uniform(-100, 100, (10, 2))
    dst = apply_similarity(src, 0.3, -2.5, 1000.0, -20.0)
    s, a, tx, ty = fit_similarity(src, dst)
    assert (s, a, tx, ty) == pytest.approx((0.3, -2.5, 1000.0, -20.0), abs=1e-9)
    with pytest.raises(ValueError):
        fit_similarity(src[:1], dst[:1])


def test_paper_map_has_the_paper_density() -> None:
    m = paper_map()
    assert 210 <= len(m) <= 222
    assert m.labels == ("building",) and m.crs == "EPSG:32631"
    assert m.x.max() - m.x.min() <= 250.0 and m.y.max() - m.y.min() <= 150.0
    counts = [len(im["objects"]) for im in simulate_images(m, 200, seed=2)]
    assert 14.0 < np.mean(counts) < 20.0  # about 17 per image, as in the paper


def test_zero_error_images_are_exact_and_stay_inside_the_map() -> None:
    m = MemoryMap(paper_map(seed=5))
    objects = m.all()
    images = simulate_images(m, 50, yaw="random", seed=3)
    minx, miny, maxx, maxy = m.bounds
    for im in images:
        t = im["truth"]
        assert minx <= t["x"] <= maxx and miny <= t["y"] <= maxy
        corners_x, corners_y = image_to_ground([0, 640, 640, 0], [0, 0, 480, 480],
                                               Pose(t["x"], t["y"], 100.0, t["heading_deg"]), CAM)
        assert corners_x.min() >= minx - 1e-6 and corners_x.max() <= maxx + 1e-6
        assert corners_y.min() >= miny - 1e-6 and corners_y.max() <= maxy + 1e-6
        idx = np.array(t["map_index"])
        u, v = project_to_image(objects.x[idx], objects.y[idx], Pose(t["x"], t["y"], 100.0, t["heading_deg"]), CAM)
        got = np.array([[o["x"], o["y"]] for o in im["objects"]])
        np.testing.assert_allclose(got, np.column_stack([u, v]), rtol=0, atol=EXACT)
        assert t["bound"]["error_m"] < 1e-6
        # Every map object inside the footprint is in the image.
        pu, pv = project_to_image(objects.x, objects.y, Pose(t["x"], t["y"], 100.0, t["heading_deg"]), CAM)
        assert np.sum((pu >= 0) & (pu < 640) & (pv >= 0) & (pv < 480)) == len(im["objects"])


def test_bound_matches_its_closed_form() -> None:
    # Eight objects around a fixed camera; only the pixel noise varies between draws.  For a similarity
    # fit the per-axis variance of the estimate at the image centre is
    # (sigma_px * GSD)^2 * (1/N + D^2 / sum r_i^2), D the distance from the objects' centroid to the centre.
    rng = np.random.default_rng(1)
    ox = X0 + rng.uniform(-25.0, 25.0, 8)
    oy = Y0 + rng.uniform(-18.0, 18.0, 8)
    ox[0], oy[0] = X0 + 25.0, Y0 + 15.0  # pull the centroid off the centre so D matters
    objects = Objects(ox, oy, np.zeros(8, np.int32), np.zeros(8), ("building",), "EPSG:32631")
    sigma, n_draws = 2.0, 3000
    images = simulate_images(objects, n_draws, pixel_std=sigma, bbox=(X0, Y0, X0, Y0), seed=11)
    assert all(im["truth"]["bound"]["n"] == 8 for im in images)
    err = np.array([[im["truth"]["bound"]["x"] - X0, im["truth"]["bound"]["y"] - Y0] for im in images])

    u, v = project_to_image(ox, oy, Pose(X0, Y0, ALT), CAM)
    pix = np.column_stack([u, v])
    centroid = pix.mean(axis=0)
    d2 = float(np.sum((centroid - [320.0, 240.0]) ** 2))
    sum_r2 = float(np.sum((pix - centroid) ** 2))
    gsd = ALT / F
    expected = (sigma * gsd) ** 2 * (1.0 / 8 + d2 / sum_r2)
    # The sample variance of 3000 normal draws has a relative standard deviation of sqrt(2/3000) = 2.6%.
    assert np.abs(err.mean(axis=0)).max() < 4 * math.sqrt(expected / n_draws)
    np.testing.assert_allclose(err.var(axis=0), [expected, expected], rtol=0.1)


def test_same_seed_same_images() -> None:
    m = paper_map()
    kwargs = dict(yaw="random", attitude_std=0.1, pixel_std=2.0, miss_rate=0.2, spurious_rate=0.2,
                  with_prior=100.0, with_attitude=True)
    a = simulate_images(m, 20, seed=7, **kwargs)
    b = simulate_images(m, 20, seed=7, **kwargs)
    c = simulate_images(m, 20, seed=8, **kwargs)
    assert json.dumps(a) == json.dumps(b)
    assert json.dumps(a) != json.dumps(c)
    assert json.dumps(simulate_images(m, 5, seed=7, **kwargs)) == json.dumps(a[:5])


def test_detector_errors_and_inputs() -> None:
    labels = ("building", "intersection", "park")
    rng = np.random.default_rng(0)
    n = 3000
    objects = Objects(X0 + rng.uniform(0, 500, n), Y0 + rng.uniform(0, 500, n), rng.integers(0, 3, n),
                      np.zeros(n), labels, "EPSG:32631")
    clean = simulate_images(objects, 100, seed=1)
    noisy = simulate_images(objects, 100, seed=1, miss_rate=0.3, spurious_rate=0.5, label_noise=0.25,
                            with_prior=50.0, with_attitude=True, with_altitude=True, attitude_std=1.0)
    n_clean = sum(len(im["objects"]) for im in clean)
    idx = np.concatenate([im["truth"]["map_index"] for im in noisy])
    n_true = int(np.sum(idx >= 0))
    assert 0.6 < n_true / n_clean < 0.8  # 30% missed
    assert 0.4 < np.sum(idx < 0) / n_clean < 0.6  # half a spurious object per visible one
    truth_labels = np.asarray(labels)[objects.label[idx[idx >= 0]]]
    given = np.array([o["label"] for im in noisy for o in im["objects"]])[idx >= 0]
    assert 0.18 < np.mean(truth_labels != given) < 0.32
    for im in noisy:
        t = im["truth"]
        assert math.hypot(im["prior"]["x"] - t["x"], im["prior"]["y"] - t["y"]) <= 50.0
        assert im["attitude"] == {"roll_deg": t["roll_deg"], "pitch_deg": t["pitch_deg"]}
        assert im["altitude_m"] == 100.0
        assert all(0 <= o["x"] < 640 and 0 <= o["y"] < 480 for o in im["objects"])


def test_simulator_over_a_real_map(tmp_path: Path) -> None:
    source = DATA / "osm" / "monaco-2021-12-03.osm.pbf"
    if not source.exists():
        pytest.skip(f"real data not found: {source}")
    from mapdb.build.pipeline import build_map

    path = tmp_path / "monaco.mapdb"
    build_map([source], path)
    with open_map(path) as m:
        images = simulate_images(m, 30, yaw="random", altitude=(60.0, 400.0), fov_deg=(35.0, 60.0), seed=0)
        objects = m.all()
        minx, miny, maxx, maxy = m.bounds
    assert len(images) == 30
    assert sum(len(im["objects"]) for im in images) > 0
    for im in images:
        t = im["truth"]
        assert minx <= t["x"] <= maxx and miny <= t["y"] <= maxy
        assert 60.0 <= t["altitude_m"] <= 400.0 and 35.0 <= t["fov_deg"] <= 60.0
        idx = np.array(t["map_index"], dtype=int)
        names = np.asarray(objects.labels)[objects.label[idx]] if idx.size else np.zeros(0)
        assert [o["label"] for o in im["objects"]] == names.tolist()
        if t["bound"] is not None:
            assert t["bound"]["error_m"] < 1e-6


def test_simulate_command_writes_json_lines(tmp_path: Path) -> None:
    map_path = tmp_path / "paper.mapdb"
    write_map(map_path, paper_map())
    out = tmp_path / "images.jsonl"
    runner = CliRunner()
    result = runner.invoke(cli, ["simulate", str(map_path), "-o", str(out), "--n", "12", "--pixel-std", "1",
                                 "--yaw", "random", "--with-prior", "80", "--seed", "3", "--quiet"])
    assert result.exit_code == 0, result.output
    lines = out.read_text().splitlines()
    assert len(lines) == 12
    first = json.loads(lines[0])
    assert first["width"] == 640 and first["prior"]["radius"] == 80.0 and "truth" in first
    again = tmp_path / "again.jsonl"
    runner.invoke(cli, ["simulate", str(map_path), "-o", str(again), "--n", "12", "--pixel-std", "1",
                        "--yaw", "random", "--with-prior", "80", "--seed", "3", "--quiet"])
    assert again.read_text() == out.read_text()
    bad = runner.invoke(cli, ["simulate", str(tmp_path / "missing.mapdb"), "-o", str(again)])
    assert bad.exit_code == 1 and "mapdb: error:" in bad.output and "Traceback" not in bad.output
    bad = runner.invoke(cli, ["simulate", str(map_path), "-o", str(again), "--size", "640by480"])
    assert bad.exit_code == 2


def test_min_objects_redraws_positions_over_empty_ground() -> None:
    # A dense cluster in one corner of a large, otherwise empty map.
    rng = np.random.default_rng(3)
    x = np.concatenate([X0 + rng.uniform(0, 100, 300), [X0 + 2000.0]])
    y = np.concatenate([Y0 + rng.uniform(0, 100, 300), [Y0 + 2000.0]])
    objects = Objects(x, y, np.zeros(x.size, np.int32), np.zeros(x.size), ("building",), "EPSG:32631")
    plain = simulate_images(objects, 20, seed=0)
    assert sum(len(im["objects"]) >= 6 for im in plain) < 5
    dense = simulate_images(objects, 20, seed=0, min_objects=6)
    assert all(len(im["objects"]) >= 6 for im in dense)
    with pytest.raises(EmptyMapError, match="no camera position"):
        simulate_images(objects, 1, seed=0, min_objects=10_000, max_tries=50)


@pytest.mark.slow  # 5 s: thousands of images drawn to test uniformity.
def test_min_objects_positions_are_uniform_over_qualifying_places() -> None:
    # Two clusters of different density; a place qualifies if it shows >= 6 objects.  The share of images
    # over the left cluster must match the share of qualifying area there (found by brute force), not the
    # share of objects (which the object-anchored proposal would give without its acceptance step).
    rng = np.random.default_rng(8)
    left = (X0 + rng.uniform(0, 120, 400), Y0 + rng.uniform(0, 120, 400))
    right = (X0 + 600 + rng.uniform(0, 200, 150), Y0 + rng.uniform(0, 200, 150))
    x, y = np.concatenate([left[0], right[0]]), np.concatenate([left[1], right[1]])
    objects = Objects(x, y, np.zeros(x.size, np.int32), np.zeros(x.size), ("building",), "EPSG:32631")
    images = simulate_images(objects, 1500, min_objects=6, seed=4)
    share = np.mean([im["truth"]["x"] < X0 + 400 for im in images])

    probe = simulate_images(objects, 6000, seed=5)  # uniform positions, footprint inside the map
    qualifies = np.array([len(im["objects"]) >= 6 for im in probe])
    probe_left = np.array([im["truth"]["x"] < X0 + 400 for im in probe])
    expected = probe_left[qualifies].mean()
    assert 0.2 < expected < 0.8  # both clusters matter
    assert abs(share - expected) < 0.06


def test_first_contact_on_the_sample_map_warns_and_the_named_option_localizes(tmp_path: Path) -> None:
    """``mapdb simulate MAP`` with the defaults over the sample map: images with too few objects to match (a
    63 x 47 m view at 100 m and 35 degrees, positions uniform over the map's bounds) come with a warning naming
    the median and ``--min-objects``; with that option every image can be localized."""
    from mapdb.build.pipeline import build_map
    from mapdb.simulation.simulate import USABLE_OBJECTS

    map_path = tmp_path / "helsinki.mapdb"
    build_map([Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"], map_path)
    plain, dense = tmp_path / "plain.jsonl", tmp_path / "dense.jsonl"
    result = CliRunner().invoke(cli, ["simulate", str(map_path), "-o", str(plain), "--n", "20", "--seed", "2", "-q"])
    assert result.exit_code == 0, result.output
    counts = [len(json.loads(line)["objects"]) for line in plain.read_text().splitlines()]
    median = float(np.median(counts))
    assert median < USABLE_OBJECTS  # what the warning is about
    assert f"mapdb: warning: {map_path}: a median of {median:g} objects an image" in result.stderr
    assert "--min-objects 6" in result.stderr
    result = CliRunner().invoke(cli, ["simulate", str(map_path), "-o", str(dense), "--n", "20", "--seed", "2", "-q",
                                      "--min-objects", "6"])
    assert result.exit_code == 0 and "warning" not in result.stderr
    answers = CliRunner().invoke(cli, ["query", str(map_path), str(dense)])
    localized = [json.loads(line)["status"] != "rejected" for line in answers.stdout.splitlines()]
    assert len(localized) == 20 and sum(localized) >= 18, answers.stdout[-2000:]
