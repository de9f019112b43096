"""Masks rendered from source outlines: heights, projection, relief, merging, the border, seeds, the CLI."""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import shapely
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import X0, Y0, OsmXml, square

from mapdb.build.pipeline import build_map
from mapdb.camera import Camera, Pose, project_points, project_to_image
from mapdb.detections.masks import from_mask, read_mask
from mapdb.errors import SourceError
from mapdb.mapfile.reader import open_map
from mapdb.simulation.outlines import FROM_HEIGHT, FROM_LEVELS, FROM_TYPE, Scene, read_scene
from mapdb.simulation.render import blob_sources, render_mask
from mapdb.simulation.rendered import simulate_masks

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CAM = Camera(640, 480, 60.0)
F = 320.0 / math.tan(math.radians(30.0))  # focal length of CAM, from its definition
ALT = 120.0

# The test world, metres east/north of (X0, Y0) in the map's CRS (UTM 32N, as tests/osmxml lays it out).
# A level camera at 120 m with a 60 degree field of view sees 69.3 m east and west, 52.0 m north and south.
A = (0.0, 0.0, 10.0, "12")          # centre x, y, half side, height tag: under the camera
B = (35.0, 0.0, 5.0, "30 m")        # tall, 35 m east of the nadir
C1 = (-35.0, 30.0, 5.0, "6")        # C1 and C2 share an edge (x = -30): one blob
C2 = (-25.0, 30.0, 5.0, "6")
LEVELS = (-35.0, -30.0, 5.0)        # building:levels 4 -> 4 * 3 + 1 = 13 m
HOUSE = (35.0, -30.0, 5.0)          # building=house, untagged height: 6 m +- 25 %
PARK = shapely.box(-15.0, -70.0, 15.0, -38.0)  # its top shows at the bottom of the nadir view


def _world(path: Path) -> Path:
    doc = OsmXml()
    for cx, cy, half, height in (A, B, C1, C2):
        doc.ring(square(cx, cy, half), {"building": "yes", "height": height})
    doc.ring(square(*LEVELS), {"building": "apartments", "building:levels": "4"})
    doc.ring(square(*HOUSE), {"building": "house"})
    doc.ring(list(PARK.exterior.coords)[:-1], {"leisure": "park"})
    return doc.write(path)


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> tuple[Path, Path, Scene]:
    root = tmp_path_factory.mktemp("render")
    osm = _world(root / "world.osm")
    map_path = root / "world.mapdb"
    build_map([osm], map_path)
    with open_map(map_path) as m:
        assert m.crs == "EPSG:32632"
        scene = read_scene(osm, m.all(), seed=0)
    return osm, map_path, scene


def _pose(x: float = 0.0, y: float = 0.0, **kw: float) -> Pose:
    return Pose(X0 + x, Y0 + y, ALT, **kw)


def _shape_at(scene: Scene, x: float, y: float) -> int:
    """Index of the scene shape containing the test point (x, y)."""
    return int(np.flatnonzero(shapely.contains_xy(scene.geometry, X0 + x, Y0 + y))[0])


def _pixels(rendering, scene: Scene, i: int) -> np.ndarray:
    return np.argwhere(rendering.instance == i + 1)  # (row, col)


def test_heights_follow_the_documented_rules(world) -> None:
    _, _, scene = world
    expected = {A: (12.0, FROM_HEIGHT), B: (30.0, FROM_HEIGHT), LEVELS: (13.0, FROM_LEVELS)}
    for where, (height, rule) in expected.items():
        i = _shape_at(scene, where[0], where[1])
        assert scene.height[i] == height and scene.height_source[i] == rule
    house = _shape_at(scene, HOUSE[0], HOUSE[1])
    assert scene.height_source[house] == FROM_TYPE and 4.5 <= scene.height[house] <= 7.5
    park = _shape_at(scene, 0.0, -54.0)
    assert scene.height[park] == 0.0 and scene.labels[scene.label[park]] == "park"
    assert (scene.map_index >= 0).all() and np.unique(scene.map_index).size == len(scene) == 7


def test_project_points_generalises_the_camera_model() -> None:
    pose = Pose(X0, Y0, ALT, yaw_deg=33.0, roll_deg=2.0, pitch_deg=-3.0)
    x, y = X0 + np.array([10.0, -40.0, 25.0]), Y0 + np.array([5.0, 30.0, -60.0])
    np.testing.assert_allclose(np.column_stack(project_points(x, y, 0.0, pose, CAM)),
                               np.column_stack(project_to_image(x, y, pose, CAM)), atol=1e-9)
    # A point h up is seen as a ground point from h lower.
    lower = Pose(X0, Y0, ALT - 20.0, yaw_deg=33.0, roll_deg=2.0, pitch_deg=-3.0)
    np.testing.assert_allclose(np.column_stack(project_points(x, y, 20.0, pose, CAM)),
                               np.column_stack(project_to_image(x, y, lower, CAM)), atol=1e-9)


def test_nadir_view_draws_footprints_where_the_camera_puts_them(world) -> None:
    _, _, scene = world
    flat = render_mask(scene, _pose(), CAM, heights=False)
    a = _shape_at(scene, 0.0, 0.0)
    pixels = _pixels(flat, scene, a)
    side = 20.0 * F / ALT  # 92.4 px
    assert abs(pixels.shape[0] - side**2) < 2 * side  # within one pixel row of each edge
    np.testing.assert_allclose(pixels.mean(axis=0) + 0.5, [240.0, 320.0], atol=0.5)
    over_park = render_mask(scene, _pose(0.0, -54.0), CAM, heights=False)
    park = _pixels(over_park, scene, _shape_at(scene, 0.0, -54.0))
    assert abs(park.shape[0] - PARK.area * (F / ALT) ** 2) < (30 + 32) * F / ALT
    np.testing.assert_allclose(park.mean(axis=0) + 0.5, [240.0, 320.0], atol=0.5)
    # With heights, the roof of A (centred under the camera) is the largest face: seen from 12 m closer.
    tall = render_mask(scene, _pose(), CAM)
    roof = 20.0 * F / (ALT - 12.0)
    assert abs(_pixels(tall, scene, a).shape[0] - roof**2) < 2 * roof


def test_relief_displacement_of_a_tall_building_off_nadir(world) -> None:
    _, _, scene = world
    b = _shape_at(scene, 35.0, 0.0)
    flat = _pixels(render_mask(scene, _pose(), CAM, heights=False), scene, b).mean(axis=0) + 0.5
    tall_px = _pixels(render_mask(scene, _pose(), CAM), scene, b)
    tall = tall_px.mean(axis=0) + 0.5
    # The footprint's image is a square 35 m east; the roof, 30 m up, is seen from 90 m: its image is
    # the footprint's scaled by 120 / 90 about the nadir, i.e. moved radially by h * r / (H - h) =
    # 11.7 m at footprint scale (h * r' / H with r' = 46.7 m its own image radius).  The blob is the
    # convex hull of both squares.  Burning pixels by their centres moves each edge by up to half a
    # pixel, so centroids are checked to half a pixel (0.11 m here).
    cx, cy, half, _ = B
    corners = np.array(square(cx, cy, half))
    foot = corners * F / ALT
    roof = corners * F / (ALT - 30.0)
    hull = shapely.MultiPoint(np.concatenate([foot, roof])).convex_hull
    expected_u = 320.0 + hull.centroid.x
    assert tall[0] == pytest.approx(240.0, abs=0.5)  # radial: the nadir is the image centre
    assert tall[1] == pytest.approx(expected_u, abs=0.5)
    assert flat[1] == pytest.approx(320.0 + 35.0 * F / ALT, abs=0.5)
    assert tall[1] - flat[1] > 20.0  # about 5 m at the ground scale
    # The far edge of the blob is the roof's: 40 m at the roof's scale.
    assert tall_px[:, 1].max() + 1 == pytest.approx(320.0 + 40.0 * F / (ALT - 30.0), abs=1.0)


def test_touching_buildings_merge_into_one_blob_covering_both(world) -> None:
    _, _, scene = world
    rendering = render_mask(scene, _pose(), CAM)
    doc = from_mask(rendering.mask, rendering.classes)
    covers = blob_sources(rendering, scene.map_index, doc)
    c1, c2 = (int(scene.map_index[_shape_at(scene, x, y)]) for x, y, *_ in (C1, C2))
    merged = [sorted(j for j, _ in c) for c in covers if c1 in {j for j, _ in c}]
    assert merged == [sorted([c1, c2])]
    labels = Counter(o["label"] for o in doc["objects"])
    assert labels == {"building": 5, "park": 1}  # six buildings, C1 and C2 as one


def test_a_building_cut_by_the_border_is_flagged(world) -> None:
    _, _, scene = world
    # Camera 65 m west of A's centre: the image's right edge (320 px, 69.3 m east of the nadir at 120 m
    # and 60 degrees) runs through A, flat, at x = 4.3 m.
    rendering = render_mask(scene, _pose(x=-65.0), CAM, heights=False)
    doc = from_mask(rendering.mask, rendering.classes)
    covers = blob_sources(rendering, scene.map_index, doc)
    a = int(scene.map_index[_shape_at(scene, 0.0, 0.0)])
    (k,) = [k for k, c in enumerate(covers) if c and c[0][0] == a]
    obj = doc["objects"][k]
    assert obj["border"] is True and obj["bbox"][2] == 640
    seen_m = 320.0 * ALT / F - 65.0 + 10.0  # the visible width of A, metres
    assert obj["area_px"] == pytest.approx(seen_m * 20.0 * (F / ALT) ** 2, rel=0.02)
    projected_centre = 320.0 + 65.0 * F / ALT
    assert obj["x"] < projected_centre - 10.0  # pulled inward
    border = {frozenset(j for j, _ in c): o["border"] for c, o in zip(covers, doc["objects"], strict=True)}
    c1, c2, levels, park = (int(scene.map_index[_shape_at(scene, x, y)]) for x, y in
                            ((C1[0], C1[1]), (C2[0], C2[1]), (LEVELS[0], LEVELS[1]), (0.0, -54.0)))
    assert border == {frozenset({a}): True, frozenset({c1, c2}): False, frozenset({levels}): False,
                      frozenset({park}): True}


def test_same_seed_same_masks_and_imperfections(world) -> None:
    _, map_path, scene = world
    options = dict(altitude=40.0, fov_deg=60.0, yaw="random", mask_noise_px=3.0, miss_rate=0.2, min_objects=2, seed=5)
    with open_map(map_path) as m:
        first = list(simulate_masks(m, scene, 4, **options))
        again = list(simulate_masks(m, scene, 4, **options))
        other = list(simulate_masks(m, scene, 4, **{**options, "seed": 6}))
        clean = list(simulate_masks(m, scene, 4, **{**options, "mask_noise_px": 0.0, "miss_rate": 0.0}))
    for (doc, mask), (doc2, mask2) in zip(first, again, strict=True):
        assert np.array_equal(mask, mask2) and doc == doc2
    assert any(not np.array_equal(a[1], b[1]) for a, b in zip(first, other, strict=True))
    # The camera draws come first: noise changes the masks, not where the camera is.
    assert [d["truth"]["heading_deg"] for d, _ in first] == [d["truth"]["heading_deg"] for d, _ in clean]
    assert any(not np.array_equal(a[1], b[1]) for a, b in zip(first, clean, strict=True))
    for doc, _mask in first:
        assert len(doc["objects"]) >= 2 and doc["truth"]["mask"] == f"{doc['id']}.png"
        assert len(doc["truth"]["map_index"]) == len(doc["truth"]["covers"]) == len(doc["objects"])
    with open_map(map_path) as m:
        (doc, mask), = simulate_masks(m, scene, 1, altitude=40.0, fov_deg=60.0, miss_rate=1.0, seed=1)
    assert not mask.any() and doc["objects"] == []


def test_simulate_render_masks_command(world, tmp_path: Path) -> None:
    osm, map_path, _ = world
    out, masks = tmp_path / "images.jsonl", tmp_path / "masks"
    args = ["simulate", str(map_path), "--render", "masks", "--source", str(osm), "--masks-dir", str(masks),
            "-o", str(out), "--n", "3", "--altitude", "40", "--fov", "60", "--yaw", "random", "--min-objects", "2",
            "--mask-noise", "1", "--quiet"]
    runner = CliRunner()
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    docs = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(docs) == 3 and sorted(p.name for p in masks.iterdir()) == [
        "classes.toml", "sim-000000.png", "sim-000001.png", "sim-000002.png"]
    for doc in docs:
        # The PNG gives back the same objects, through the written class table.
        again = runner.invoke(cli, ["objects", str(masks / doc["truth"]["mask"]), "--classes",
                                    str(masks / "classes.toml"), "--fov", "60", "-q"])
        assert again.exit_code == 0, again.output
        assert json.loads(again.output)["objects"] == doc["objects"]
        assert read_mask(masks / doc["truth"]["mask"]).array.shape == (480, 640)
    query = runner.invoke(cli, ["query", str(map_path), str(out)])
    assert query.exit_code == 0, query.output
    assert len(query.output.strip().splitlines()) == 3
    evaluate = runner.invoke(cli, ["evaluate", str(map_path), str(out), "--json"])
    assert evaluate.exit_code == 0, evaluate.output
    # Same seed, same files.
    out2, masks2 = tmp_path / "again.jsonl", tmp_path / "masks2"
    again_args = [str(masks2) if a == str(masks) else str(out2) if a == str(out) else a for a in args]
    assert runner.invoke(cli, again_args).exit_code == 0
    assert out2.read_text() == out.read_text()
    assert all((masks2 / p.name).read_bytes() == p.read_bytes() for p in masks.iterdir())


def test_render_masks_command_errors(world, tmp_path: Path) -> None:
    osm, map_path, _ = world
    runner = CliRunner()
    out = tmp_path / "images.jsonl"
    base = ["simulate", str(map_path), "-o", str(out), "--n", "1", "-q"]
    assert runner.invoke(cli, [*base, "--render", "masks"]).exit_code == 2
    assert runner.invoke(cli, [*base, "--mask-noise", "2"]).exit_code == 2
    used = runner.invoke(cli, [*base, "--render", "masks", "--source", str(osm), "--masks-dir", str(tmp_path / "m"),
                               "--pixel-std", "1"])
    assert used.exit_code == 2 and "--mask-noise" in used.output
    not_osm = tmp_path / "bad.osm"
    not_osm.write_text("this is not xml")
    bad = runner.invoke(cli, [*base, "--render", "masks", "--source", str(not_osm), "--masks-dir",
                              str(tmp_path / "m")])
    assert bad.exit_code == 1 and "mapdb: error:" in bad.output and "Traceback" not in bad.output
    assert not out.exists() and not (tmp_path / "m").exists()
    with pytest.raises(SourceError):
        with open_map(map_path) as m:
            read_scene(not_osm, m.all())
    # An extract the map was not built from: no outline is a map object.
    elsewhere = OsmXml()
    elsewhere.ring(square(5000.0, 5000.0, 10.0), {"building": "yes"})
    wrong = runner.invoke(cli, [*base, "--render", "masks", "--source", str(elsewhere.write(tmp_path / "x.osm")),
                                "--masks-dir", str(tmp_path / "m")])
    assert wrong.exit_code == 1 and "none of its 1 outlines is an object of the map" in wrong.output
    assert not out.exists() and not (tmp_path / "m").exists()


def test_flat_masks_of_a_real_extract_put_single_blobs_on_their_map_objects(tmp_path: Path) -> None:
    source = DATA / "osm" / "monaco-2021-12-03.osm.pbf"
    if not source.exists():
        pytest.skip(f"real data not found: {source} (put the shared data set beside the checkout)")
    map_path = tmp_path / "monaco.mapdb"
    build_map([source], map_path)
    with open_map(map_path) as m:
        objects = m.all()
        scene = read_scene(source, objects)
        images = list(simulate_masks(m, scene, 10, altitude=ALT, fov_deg=60.0, yaw="random", heights=False,
                                     min_objects=8, seed=2))
    assert (scene.map_index >= 0).mean() > 0.99
    errors = []
    for doc, _ in images:
        truth = doc["truth"]
        assert len(doc["objects"]) >= 8
        pose = Pose(truth["x"], truth["y"], ALT, truth["heading_deg"])
        for obj, covers in zip(doc["objects"], truth["covers"], strict=True):
            if len(covers) != 1 or obj["border"]:
                continue
            # One whole flat object: its blob's centroid is its projected centroid, to the pixel
            # (a road ring's pieces and intersection discs overlapping it aside).
            assert obj["label"] == objects.labels[objects.label[covers[0]]]
            u, v = project_to_image(objects.x[covers[0]], objects.y[covers[0]], pose, CAM)
            errors.append(math.hypot(obj["x"] - u[0], obj["y"] - v[0]))
    assert len(errors) > 50 and np.median(errors) < 0.5
