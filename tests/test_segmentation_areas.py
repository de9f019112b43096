"""Area evidence against real segmentation errors (issue 29, item 6): a building mask eroded or dilated by
2 px (1 m at 0.5 m/px, what every segmentation model does on some images) must still localize where the exact
mask does.  Two versions: the SpaceNet 4 Atlanta chip (shared data; skipped when absent) and a generated town of
rectangular buildings rasterized here (no shared data: the default run covers it)."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from mapdb_cli.main import cli
from maskfiles import write_mask
from rasterio.errors import NotGeoreferencedWarning
from rasterio.features import rasterize
from scipy import ndimage
from shapely.affinity import rotate, translate
from shapely.geometry import box, mapping

from mapdb.answers import Answer
from mapdb.localize import records
from mapdb.localize.localizer import localize
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.writer import write_map
from mapdb.match.evidence.areas import POINTS_SHARE, points_floor
from mapdb.match.options import FastOptions
from mapdb.objects import Objects

_RELATIVE = Path(__file__).resolve().parents[2] / "shared" / "data"
SHARED = _RELATIVE if _RELATIVE.is_dir() else Path("/work/shared/data")
SPACENET = SHARED / "segmentation" / "spacenet4_atlanta"

# The chip's pixel size, and the generated town's.
GROUND_PX = 0.5


def run(*args: str) -> str:
    result = CliRunner().invoke(cli, list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.stdout


def segmentation_error(mask: np.ndarray, px: int, edge: bool = False) -> np.ndarray:
    """``mask`` (bool) eroded (``px < 0``) or dilated (``px > 0``) by ``|px|`` pixels, as 0/255 bytes; ``edge``:
    outside the image counts as building, so an eroded building cut by the border still touches it."""
    if px < 0:
        mask = ndimage.binary_erosion(mask, iterations=-px, border_value=int(edge))
    elif px > 0:
        mask = ndimage.binary_dilation(mask, iterations=px)
    return mask.astype(np.uint8) * 255


def localize_mask(tmp_path: Path, map_path: Path, mask: np.ndarray, name: str, *query: str) -> dict:
    """``mask`` written as a PNG, turned into objects by ``mapdb objects`` and localized by ``mapdb query``."""
    png, images, answers = tmp_path / f"{name}.png", tmp_path / f"{name}.jsonl", tmp_path / f"{name}.answers.jsonl"
    write_mask(png, mask)
    run("objects", str(png), "--label", "building", "-o", str(images), "-q")
    run("query", str(map_path), str(images), "-o", str(answers), *query)
    (answer,) = [json.loads(line) for line in answers.read_text().splitlines()]
    return answer


@pytest.fixture(scope="module")
def spacenet(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray, complex]:
    """The chip's map (its label polygons), its building mask and the map point under the image centre."""
    if not SPACENET.is_dir():
        pytest.skip(f"SpaceNet chip absent: put geotiff_labels.geojson, sample_fp_mask_from_geojson.tif and "
                    f"sample_geotiff.tif in {SPACENET} (see SOURCES.md of the shared data)")
    map_path = tmp_path_factory.mktemp("spacenet") / "atlanta.mapdb"
    run("build", str(SPACENET / "geotiff_labels.geojson"), "--label", "building", "-o", str(map_path), "-q")
    with rasterio.open(SPACENET / "sample_geotiff.tif") as ds:
        cx, cy = ds.transform @ (ds.width / 2, ds.height / 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # the mask carries no georeference: the chip does
        with rasterio.open(SPACENET / "sample_fp_mask_from_geojson.tif") as ds:
            mask = ds.read(1) > 0
    return map_path, mask, complex(cx, cy)


@pytest.mark.parametrize(("px", "edge"), [(-2, False), (-2, True), (2, False)])
def test_spacenet_chip_with_segmentation_error_localizes(spacenet, tmp_path: Path, px: int, edge: bool) -> None:
    # The erosion (scipy's default: cut buildings pulled off the border) and a model's (they stay on it).
    map_path, mask, centre = spacenet
    answer = localize_mask(tmp_path, map_path, segmentation_error(mask, px, edge), f"chip{px:+d}{edge}")
    assert answer["status"] == "ok", answer
    assert abs(complex(answer["x"], answer["y"]) - centre) < 0.1, answer
    assert abs(answer["scale_m_per_px"] / GROUND_PX - 1.0) < 0.02


def town(seed: int = 3, n: int = 90, side: float = 500.0, pairs: float = 0.0) -> list:
    """Rectangular buildings (6-22 m sides, any orientation) at random places of a ``side``-metre square of UTM
    zone 16N, more than 3 m apart, as shapely polygons; a share ``pairs`` of them is built 1 m (2 px) east of
    another one's box instead, so that a 2 px dilation merges the two blobs."""
    rng = np.random.default_rng(seed)
    placed: list = []
    while len(placed) < n:
        x, y = rng.uniform(20, side - 20, 2)
        w, h = rng.uniform(6, 22, 2)
        shape = rotate(box(x - w / 2, y - h / 2, x + w / 2, y + h / 2), rng.uniform(0, 180), use_radians=False)
        gap = 3.0
        if placed and rng.random() < pairs:
            west, south, east, _ = placed[rng.integers(len(placed))].bounds
            shape, gap = box(east + 1.0, south, east + 1.0 + w, south + h), 0.99
        if all(shape.distance(other) > gap for other in placed):
            placed.append(shape)
    return placed


def town_case(work: Path, shapes: list) -> tuple[Path, np.ndarray, complex]:
    """``shapes`` (a town's) built into a map, a 700x600 px mask of part of them at 0.5 m/px and the map point
    under its centre."""
    east, north = 733000.0, 3724000.0  # somewhere in UTM zone 16N, as the SpaceNet chip
    shapes = [translate(p, east, north) for p in shapes]
    features = [{"type": "Feature", "properties": {}, "geometry": mapping(p)} for p in shapes]
    source = work / "town.geojson"
    source.write_text(json.dumps({"type": "FeatureCollection", "features": features,
                                  "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32616"}}}))
    map_path = work / "town.mapdb"
    run("build", str(source), "--label", "building", "-o", str(map_path), "-q")
    width, height, left, top = 700, 600, east + 60.0, north + 420.0
    transform = Affine(GROUND_PX, 0.0, left, 0.0, -GROUND_PX, top)
    mask = rasterize(shapes, out_shape=(height, width), transform=transform) > 0
    centre = complex(left + width * GROUND_PX / 2, top - height * GROUND_PX / 2)
    return map_path, mask, centre


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray, complex]:
    """A generated town (:func:`town`) and its mask (:func:`town_case`)."""
    return town_case(tmp_path_factory.mktemp("town"), town())


def test_generated_town_with_merged_blobs_localizes(tmp_path: Path) -> None:
    # Pairs of buildings 1 m apart: a 2 px dilation merges each pair into one blob of about their summed area
    # at the pair's centroid, which no map object has.  (Answered before the floor too: it guards that merged
    # blobs, whose areas fit nothing, never cost the answer.)
    map_path, mask, centre = town_case(tmp_path, town(seed=4, n=110, pairs=0.4))
    exact = ndimage.label(mask, np.ones((3, 3)))[1]
    dilated = segmentation_error(mask, 2) > 0
    assert ndimage.label(dilated, np.ones((3, 3)))[1] <= exact - 10  # at least ten pairs merged in view
    answer = localize_mask(tmp_path, map_path, segmentation_error(mask, 2), "merged")
    assert answer["status"] == "ok", answer
    assert abs(complex(answer["x"], answer["y"]) - centre) < 0.1, answer


@pytest.mark.parametrize("px", [0, -2, 2])
def test_generated_town_with_segmentation_error_localizes(generated, tmp_path: Path, px: int) -> None:
    map_path, mask, centre = generated
    answer = localize_mask(tmp_path, map_path, segmentation_error(mask, px), f"town{px:+d}")
    assert answer["status"] == "ok", answer
    assert abs(complex(answer["x"], answer["y"]) - centre) < 0.1, answer


def test_points_floor_never_costs_more_than_its_share() -> None:
    # Whatever the two tests say, the decision is at most the points-only test plus log10(1 / share) and at
    # most the area test plus log10(1 / (1 - share)): the areas can only lift a right answer over the threshold.
    rng = np.random.default_rng(0)
    with_areas, points = rng.uniform(-50, 10, 1000), rng.uniform(-50, 10, 1000)
    nfa = points_floor(with_areas, points)
    assert np.all(nfa <= points - math.log10(POINTS_SHARE) + 1e-12)
    assert np.all(nfa <= with_areas - math.log10(1 - POINTS_SHARE) + 1e-12)
    assert np.all((nfa == points - math.log10(POINTS_SHARE)) | (nfa == with_areas - math.log10(1 - POINTS_SHARE)))


def _town_view(area_factor: float) -> tuple[Objects, dict]:
    """A random town's 800x800 image at 0.4 m/px as an image document, every blob ``area_factor`` times its
    building's area (10: no building near has a compatible area)."""
    rng = np.random.default_rng(5)
    n = 400
    x, y = rng.uniform(0, 1000, n), rng.uniform(0, 1000, n)
    area = np.exp(rng.normal(math.log(200.0), 1.0, n))
    objects = Objects.from_names(x, y, np.full(n, "building"), area=area)
    pix = (x + 1j * y - (500 + 500j)) / 0.4
    keep = np.flatnonzero((np.abs(pix.real) < 390) & (np.abs(pix.imag) < 390))[:12]
    doc = {"width": 800, "height": 800, "objects": [
        {"label": "building", "x": 400 + pix[k].real, "y": 400 - pix[k].imag, "area_px": area_factor * area[k] / 0.16,
         "border": False} for k in keep]}
    return objects, doc


def test_a_rejection_the_areas_decided_says_so() -> None:
    objects, doc = _town_view(10.0)
    m = MemoryMap(objects)
    first = localize(doc, m).to_json()
    assert first["status"] == "ok" and abs(complex(first["x"], first["y"]) - (500 + 500j)) < 0.5, first
    without = localize(doc, m, options=FastOptions(areas=False)).to_json()
    # A threshold the positions alone pass but the areas' wrong sizes do not: half a unit above their score.
    strict = FastOptions(log10_epsilon=-(without["score"] - 0.5))
    rejected = localize(doc, m, options=strict).to_json()
    assert rejected["status"] == "rejected", rejected
    assert rejected["rejected_by"] == "areas" and rejected["score_without_areas"] == pytest.approx(without["score"],
                                                                                                   abs=0.02)
    accepted = localize(doc, m, options=replace(strict, areas=False)).to_json()
    assert accepted["status"] == "ok" and accepted["x"] == without["x"]
    # Areas that fit: the same threshold is passed, and nothing says "rejected_by".
    _, right = _town_view(1.0)
    fitting = localize(right, m, options=strict).to_json()
    assert fitting["status"] == "ok" and "rejected_by" not in fitting, fitting
    # A rejection the areas did not decide (a threshold the positions alone do not pass) says nothing either.
    hopeless = localize(doc, m, options=FastOptions(log10_epsilon=-(without["score"] + 5.0))).to_json()
    assert hopeless["status"] == "rejected" and "rejected_by" not in hopeless


def test_query_no_areas_and_the_record_fields(tmp_path: Path) -> None:
    objects, doc = _town_view(10.0)
    map_path, images = tmp_path / "town.mapdb", tmp_path / "images.jsonl"
    write_map(map_path, replace(objects, crs="EPSG:32616"))
    images.write_text(json.dumps(doc) + "\n")
    free = json.loads(run("query", str(map_path), str(images), "--no-areas"))
    strict = f"{free['score'] - 0.5:.2f}"
    rejected = json.loads(run("query", str(map_path), str(images), "--min-score", strict))
    accepted = json.loads(run("query", str(map_path), str(images), "--min-score", strict, "--no-areas"))
    assert rejected["status"] == "rejected" and rejected["rejected_by"] == "areas"
    assert rejected["score_without_areas"] > float(strict) and accepted["status"] == "ok"
    # The record's documentation names both fields (mapdb.localize.records), and the answer reads them back.
    for name in ("rejected_by", "score_without_areas"):
        assert f"``{name}``" in records.__doc__
    assert Answer.from_json(rejected).rejected_by == "areas"
