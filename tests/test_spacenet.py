"""The SpaceNet 4 Atlanta chip end to end (issue 11's done-when): its label polygons built into a map with
``--label building``, its building mask turned into objects, the objects localized; the answer checked
against the chip's own georeference (the image GeoTIFF's; the mask carries none)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import rasterio
from click.testing import CliRunner
from mapdb_cli.main import cli

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "segmentation" / "spacenet4_atlanta"


def run(*args: str):
    result = CliRunner().invoke(cli, list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result


def test_spacenet_chip_mask_to_fix(tmp_path: Path) -> None:
    if not DATA.is_dir():
        pytest.skip(f"SpaceNet chip absent: put geotiff_labels.geojson, sample_fp_mask_from_geojson.tif and "
                    f"sample_geotiff.tif in {DATA} (see ../shared/data/SOURCES.md)")
    map_path, images, answers = tmp_path / "atlanta.mapdb", tmp_path / "chip.jsonl", tmp_path / "fix.jsonl"
    built = json.loads(run("build", str(DATA / "geotiff_labels.geojson"), "--label", "building", "-o", str(map_path),
                           "-q").stdout)
    assert built["labels"] == {"building": 43}
    run("objects", str(DATA / "sample_fp_mask_from_geojson.tif"), "--label", "building", "-o", str(images), "-q")
    run("query", str(map_path), str(images), "-o", str(answers))
    (doc,) = [json.loads(line) for line in images.read_text().splitlines()]
    (answer,) = [json.loads(line) for line in answers.read_text().splitlines()]
    with rasterio.open(DATA / "sample_geotiff.tif") as ds:
        assert (ds.width, ds.height) == (doc["width"], doc["height"])
        cx, cy = ds.transform @ (ds.width / 2, ds.height / 2)
        ground_px = math.sqrt(abs(ds.transform.determinant))
    assert answer["status"] == "ok", answer
    # Figures of the run the README quotes: 43 blobs, 42 inliers, 0.008 m, 0.004 degrees, 0.500027 m/px.
    assert len(doc["objects"]) >= 40 and answer["inliers"] >= 30
    assert math.hypot(answer["x"] - cx, answer["y"] - cy) < 1.0
    assert abs((answer["heading_deg"] + 180.0) % 360.0 - 180.0) < 1.0
    assert ground_px == 0.5 and abs(answer["scale_m_per_px"] / ground_px - 1.0) < 0.02
