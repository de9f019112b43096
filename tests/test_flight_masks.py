"""Flights whose frames are rendered masks (``mapdb simulate flight --render masks``), and thinned extracts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import X0, Y0, OsmXml, square

from mapdb.build.pipeline import build_map
from mapdb.camera import Camera, Pose
from mapdb.detections.masks import from_mask
from mapdb.errors import SourceError
from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.rendered import FlightRender
from mapdb.simulation.outlines import read_scene
from mapdb.simulation.render import render_mask
from mapdb.simulation.thinning import thin_extract

# A straight leg east, a left turn, a leg north: the turn banks the camera.
WAYPOINTS = np.array([complex(X0 - 60, Y0 - 40), complex(X0 + 40, Y0 - 40), complex(X0 + 40, Y0 + 60)])
FLIGHT = {"altitude_m": 60.0, "fov_deg": 60.0, "fps": 2.5, "speed_mps": 20.0, "turn_radius_m": 60.0,
          "turbulence_deg": 1.0, "length_m": 160.0}


def _town(path: Path, keep=lambda i, j: True) -> Path:
    """Buildings 12 m across every 30 m (some taller), on 240 x 240 m around the origin."""
    doc = OsmXml()
    for i in range(8):
        for j in range(8):
            if keep(i, j):
                height = "25" if (i + 2 * j) % 5 == 0 else "8"
                doc.ring(square(-105.0 + 30 * i + 3 * (j % 3), -105.0 + 30 * j, 6.0),
                         {"building": "yes", "height": height})
    return doc.write(path)


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("flight-masks")
    osm = _town(root / "town.osm")
    map_path = root / "town.mapdb"
    build_map([osm], map_path)
    return osm, map_path


def _fly(map_path: Path, osm: Path, length_m: float = 160.0, **render) -> list[dict]:
    with open_map(map_path) as m:
        scene = read_scene(osm, m.all())
        return simulate_flight(m, FlightOptions(**{**FLIGHT, "length_m": length_m}), WAYPOINTS,
                               render=FlightRender(scene, str(osm), **render))


def test_each_frame_is_its_mask_rendered_with_the_frames_pose_and_extracted_as_mapdb_objects(town) -> None:
    osm, map_path = town
    frames = _fly(map_path, osm)
    with open_map(map_path) as m:
        scene = read_scene(osm, m.all())
    banked = [f for f in frames if abs(f["truth"]["roll_deg"]) > 10.0]
    assert banked, "the turn must bank the camera"
    for frame in (frames[0], banked[len(banked) // 2]):
        t = frame["truth"]
        pose = Pose(t["x"], t["y"], t["altitude_m"], t["heading_deg"], t["roll_deg"], t["pitch_deg"])
        r = render_mask(scene, pose, Camera(640, 480, 60.0))
        assert frame["objects"] == from_mask(r.mask, r.classes, fov_deg=60.0)["objects"]
        assert len(frame["objects"]) >= 3 and all("area_px" in o and "border" in o for o in frame["objects"])
        assert all(k >= 0 for k in t["map_index"])  # every blob is a building of the map
    # The level frame would not give the banked frame's objects.
    t = banked[0]["truth"]
    level = render_mask(scene, Pose(t["x"], t["y"], t["altitude_m"], t["heading_deg"]), Camera(640, 480, 60.0))
    assert banked[0]["objects"] != from_mask(level.mask, level.classes, fov_deg=60.0)["objects"]


def test_segmentation_errors_erode_dilate_miss_and_add_blobs(town) -> None:
    osm, map_path = town
    plain = _fly(map_path, osm, 80.0)
    area = {px: sum(o["area_px"] for f in _fly(map_path, osm, 80.0, mask_offset_px=px) for o in f["objects"])
            for px in (-2, 2)}
    base = sum(o["area_px"] for f in plain for o in f["objects"])
    assert area[-2] < 0.97 * base and area[2] > 1.03 * base  # 2 px of blobs about 100 px across
    n = sum(len(f["objects"]) for f in plain)
    missed = _fly(map_path, osm, 80.0, blob_miss_rate=0.3)
    spurious = _fly(map_path, osm, 80.0, blob_spurious_rate=0.5)
    assert sum(len(f["objects"]) for f in missed) < 0.85 * n
    assert sum(len(f["objects"]) for f in spurious) > 1.15 * n
    assert sum(k == -1 for f in spurious for k in f["truth"]["map_index"]) > 0.1 * n  # the false blobs
    assert _fly(map_path, osm, 80.0, blob_spurious_rate=0.5) == spurious  # same seed, same flight
    with pytest.raises(ValueError):
        FlightRender(read_scene(osm, open_map(map_path).all()), mask_offset_px=11)


def test_simulate_flight_render_masks_command(town, tmp_path) -> None:
    osm, map_path = town
    out, masks = tmp_path / "flight.jsonl", tmp_path / "masks"
    path = tmp_path / "path.geojson"
    from pyproj import Transformer

    to_lonlat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    path.write_text(json.dumps({"type": "LineString", "coordinates": [list(to_lonlat.transform(z.real, z.imag))
                                                                       for z in WAYPOINTS]}))
    args = ["simulate", "flight", str(map_path), "-o", str(out), "--path", str(path), "--altitude", "60",
            "--fov", "60", "--fps", "5", "--length", "60", "--render", "masks", "--source", str(osm),
            "--masks-dir", str(masks), "--mask-dilate", "1", "-q"]
    runner = CliRunner()
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    frames = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(frames) == 16 and sorted(p.name for p in masks.iterdir())[:2] == ["classes.toml", "frame-000000.png"]
    again = runner.invoke(cli, ["objects", str(masks / "frame-000003.png"), "--classes", str(masks / "classes.toml"),
                                "--fov", "60", "-q"])
    assert again.exit_code == 0 and json.loads(again.output)["objects"] == frames[3]["objects"]
    nav = runner.invoke(cli, ["navigate", str(map_path), str(out), "-o", str(tmp_path / "track.jsonl"), "-q"])
    assert nav.exit_code == 0, nav.output
    assert len((tmp_path / "track.jsonl").read_text().splitlines()) == 16


def test_render_masks_flight_errors(town, tmp_path) -> None:
    osm, map_path = town
    out = tmp_path / "f.jsonl"
    base = ["simulate", "flight", str(map_path), "-o", str(out), "--length", "40", "-q"]
    runner = CliRunner()
    for extra in (["--render", "masks"], ["--mask-erode", "2"], ["--source", str(osm)],
                  ["--render", "masks", "--source", str(osm), "--mask-erode", "1", "--mask-dilate", "1"],
                  ["--render", "masks", "--source", str(osm), "--pixel-std", "1"]):
        assert runner.invoke(cli, [*base, *extra]).exit_code == 2, extra
    # An extract covering a quarter of the map's buildings: not the extract it was built from.
    part = _town(tmp_path / "part.osm", keep=lambda i, j: i < 4 and j < 4)
    wrong = runner.invoke(cli, [*base, "--render", "masks", "--source", str(part), "--masks-dir", str(tmp_path / "m")])
    assert wrong.exit_code == 1 and wrong.output.startswith("mapdb: error: ") and "Traceback" not in wrong.output
    assert len(wrong.output.strip().splitlines()) == 1 and "not the extract the map was built from" in wrong.output
    assert not out.exists() and not (tmp_path / "m").exists()


def test_a_thinned_extract_leaves_out_a_share_of_the_buildings_and_nothing_else(town, tmp_path) -> None:
    osm, _ = town
    doc = OsmXml()
    for i in range(400):
        doc.ring(square(20.0 * (i % 20), 20.0 * (i // 20), 5.0), {"building": "yes"})
    doc.ring(square(-50.0, -50.0, 10.0), {"leisure": "park"})
    big = doc.write(tmp_path / "big.osm")
    thin = tmp_path / "thin.osm"
    counts = thin_extract(big, thin, 0.15, seed=4)
    assert counts["buildings"] == 400 and 30 <= counts["left_out"] <= 90
    full_map, thin_map = tmp_path / "full.mapdb", tmp_path / "thin.mapdb"
    build_map([big], full_map)
    build_map([thin], thin_map)
    with open_map(full_map) as full, open_map(thin_map) as part:
        names = lambda m: list(np.asarray(m.all().labels)[m.all().label])  # noqa: E731
        assert names(full).count("building") - names(part).count("building") == counts["left_out"]
        assert names(part).count("park") == names(full).count("park") == 1
    assert thin_extract(big, tmp_path / "again.osm", 0.15, seed=4) == counts
    assert (tmp_path / "again.osm").read_bytes() == thin.read_bytes()
    with pytest.raises(SourceError):
        (tmp_path / "bad.osm").write_text("not xml")
        thin_extract(tmp_path / "bad.osm", tmp_path / "x.osm", 0.15)
