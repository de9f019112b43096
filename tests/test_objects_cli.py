"""``mapdb objects``: masks and COCO files in, query documents out; a bad file never stops the batch."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import geopandas as gpd
import numpy as np
import shapely
from click.testing import CliRunner
from mapdb_cli.main import cli
from maskfiles import write_mask
from rasterio.features import rasterize
from rasterio.transform import Affine


def run(*args: str):
    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


def lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_batch_goes_on_past_bad_masks(tmp_path: Path) -> None:
    mask = np.zeros((30, 40), np.uint8)
    mask[5:10, 5:15] = 255
    mask[20:30, 30:40] = 255
    good = write_mask(tmp_path / "good.png", mask)
    bad = tmp_path / "bad.png"
    bad.write_text("a text file, not an image")
    out = tmp_path / "images.jsonl"
    result = run("objects", str(bad), str(good), str(tmp_path / "gone.png"), "--label", "building", "-o", str(out))
    assert result.exit_code == 1
    errors = result.stderr.splitlines()
    assert errors[0].startswith(f"mapdb: error: {bad}: not an image that GDAL can read")
    assert errors[1] == f"mapdb: error: {tmp_path / 'gone.png'}: no such mask"
    assert errors[2] == f"1 images, 2 objects -> {out}; 2 failed"
    (doc,) = lines(out)
    assert doc["id"] == str(good) and (doc["width"], doc["height"]) == (40, 30)
    assert [(o["x"], o["y"], o["area_px"], o["border"]) for o in doc["objects"]] == [
        (10.0, 7.5, 50, False), (35.0, 25.0, 100, True)]


def test_class_table_and_camera_options(tmp_path: Path) -> None:
    mask = np.zeros((20, 20), np.uint8)
    mask[2, 2] = mask[3, 3] = 1          # two pixels touching by a corner
    mask[10:12, 10:12] = 2
    mask[15:17, 15:17] = 9               # not in the table
    classes = tmp_path / "classes.toml"
    classes.write_text('[classes]\n1 = "building"\n2 = "water"\ncar = "parking"\n')
    path = write_mask(tmp_path / "m.tif", mask)
    out = tmp_path / "o.jsonl"
    result = run("objects", str(path), "--classes", str(classes), "--connectivity", "4", "--min-area", "1",
                 "--fov", "60", "--attitude", "1.5,-2", "--altitude", "120", "-o", str(out), "-q")
    assert result.exit_code == 0 and result.stderr == ""
    (doc,) = lines(out)
    assert [(o["label"], o["x"], o["y"]) for o in doc["objects"]] == [
        ("building", 2.5, 2.5), ("building", 3.5, 3.5), ("water", 11.0, 11.0)]
    assert doc["camera"] == {"fov_deg": 60.0} and doc["altitude_m"] == 120.0
    assert doc["attitude"] == {"roll_deg": 1.5, "pitch_deg": -2.0} and doc["skipped_classes"] == {"9": 4}
    eight = run("objects", str(path), "--classes", str(classes), "--min-area", "1", "-q")
    assert [o["area_px"] for o in json.loads(eight.stdout)["objects"]] == [2, 4]


def test_bad_options_and_class_tables_write_nothing(tmp_path: Path) -> None:
    path = write_mask(tmp_path / "m.png", np.zeros((4, 4), np.uint8))
    out = tmp_path / "o.jsonl"
    classes = tmp_path / "classes.toml"
    classes.write_text('[classes]\n1 = "biulding"\n')
    result = run("objects", str(path), "--classes", str(classes), "-o", str(out))
    assert result.exit_code == 1 and not out.exists()
    assert result.stderr.splitlines() == [f"mapdb: error: {classes}: classes.1: unknown label 'biulding' (labels: "
                                          + result.stderr.split("(labels: ", 1)[1].strip()]
    unknown = run("objects", str(path), "--label", "castle", "-o", str(out))
    assert unknown.exit_code == 1 and "--label: unknown label 'castle'" in unknown.stderr and not out.exists()
    for args, message in [((), "give MASK files, or --coco FILE"), ((str(path),), "need --classes"),
                          ((str(path), "--label", "building", "--classes", str(classes)), "not both"),
                          ((str(path), "--label", "building", "--attitude", "1"), "ROLL,PITCH"),
                          ((str(path), "--label", "building", "--fov", "180"), "--fov")]:
        usage = run("objects", *args)
        assert usage.exit_code == 2 and message in usage.stderr, (args, usage.stderr)


def test_output_over_an_input_is_refused(tmp_path: Path) -> None:
    mask = np.zeros((4, 4), np.uint8)
    path = write_mask(tmp_path / "m.png", mask)
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    result = run("objects", str(path), "--label", "building", "-o", str(path))
    assert result.exit_code == 1 and "is the same file as input" in result.stderr
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before


def test_coco_beside_masks(tmp_path: Path) -> None:
    det = tmp_path / "det.json"
    det.write_text(json.dumps({
        "images": [{"id": 1, "width": 50, "height": 40}],
        "categories": [{"id": 3, "name": "house"}],
        "annotations": [{"image_id": 1, "category_id": 3, "bbox": [10, 10, 10, 6], "score": 0.9},
                        {"image_id": 1, "category_id": 3, "segmentation": [[20, 20, 30, 20, 30, 30, 20, 30]]}],
    }))
    classes = tmp_path / "classes.toml"
    classes.write_text('[classes]\nhouse = "building"\n')
    result = run("objects", "--coco", str(det), "--classes", str(classes), "-q")
    assert result.exit_code == 0, result.stderr
    (doc,) = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(o["x"], o["y"], o.get("box", False)) for o in doc["objects"]] == [(15.0, 13.0, True), (25.0, 25.0, False)]
    # A COCO file whose annotation names an image it does not hold: one line, and the masks are still done.
    det.write_text(json.dumps({"images": [{"id": 1, "width": 50, "height": 40}],
                               "annotations": [{"image_id": 2, "category_id": 3, "bbox": [1, 1, 2, 2]}]}))
    classes.write_text('[classes]\nhouse = "building"\n255 = "building"\n')
    mask = write_mask(tmp_path / "m.png", np.full((5, 5), 255, np.uint8))
    both = run("objects", str(mask), "--coco", str(det), "--classes", str(classes), "-q")
    assert both.exit_code == 1
    assert both.stderr == f"mapdb: error: {det}: annotations[0]: image_id 2 is not one of the file's images\n"
    assert [json.loads(line)["id"] for line in both.stdout.splitlines()] == [str(mask)]


def test_footprints_to_mask_to_fix(tmp_path: Path) -> None:
    """The whole path on generated data: footprints without a label column built with --label, their mask
    drawn at 0.5 m, turned into objects and localized at the centre its georeference gives."""
    rng = np.random.default_rng(4)
    x0, y0, size = 400_000.0, 5_200_000.0, 0.5
    width, height = 400, 300
    # Houses on a jittered grid, well apart, all inside the image.
    cx, cy = np.meshgrid(np.arange(20, 190, 28.0), np.arange(20, 140, 26.0))
    cx, cy = cx.ravel() + rng.uniform(-4, 4, cx.size), cy.ravel() + rng.uniform(-4, 4, cx.size)
    houses = shapely.box(x0 + cx - 5, y0 - cy - 4, x0 + cx + rng.uniform(3, 7, cx.size), y0 - cy + 4)
    frame = gpd.GeoDataFrame({"building": ["yes"] * len(houses)}, geometry=list(houses), crs="EPSG:32633")
    layer = tmp_path / "footprints.geojson"
    frame.to_file(layer, engine="pyogrio")
    transform = Affine(size, 0.0, x0, 0.0, -size, y0)
    mask = rasterize([(g, 255) for g in houses], out_shape=(height, width), transform=transform, dtype="uint8")
    mask_path = write_mask(tmp_path / "mask.tif", mask, transform, "EPSG:32633")
    map_path = tmp_path / "houses.mapdb"
    assert run("build", str(layer), "-o", str(map_path), "--label", "building", "-q").exit_code == 0
    images = tmp_path / "images.jsonl"
    assert run("objects", str(mask_path), "--label", "building", "-o", str(images), "-q").exit_code == 0
    (doc,) = lines(images)
    assert len(doc["objects"]) == len(houses)
    result = run("query", str(map_path), str(images))
    answer = json.loads(result.stdout)
    georef = doc["georef"]
    assert answer["status"] == "ok", answer
    assert math.hypot(answer["x"] - georef["x"], answer["y"] - georef["y"]) < 0.1
    assert abs((answer["heading_deg"] + 180) % 360 - 180) < 0.1
    assert abs(answer["scale_m_per_px"] / georef["m_per_px"] - 1) < 0.005
