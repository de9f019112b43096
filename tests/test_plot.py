"""Pictures: ``mapdb show`` (one match) and ``evaluate --plot``; the geometry they draw is checked too."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli
from mapdb_cli.show import show
from PIL import Image

from mapdb.answers import Answer, Candidate
from mapdb.evaluation.drawing import crs_name
from mapdb.evaluation.evaluate import outcome
from mapdb.evaluation.evaluation_plot import plot_evaluation
from mapdb.evaluation.match_geometry import match_geometry
from mapdb.evaluation.match_plot import plot_match
from mapdb.localize.localizer import localize
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects
from mapdb.simulation.simulate import paper_map, simulate_images

matplotlib.use("Agg")

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _two_label_map(seed: int = 2) -> Objects:
    """The paper's map with two labels, so that label colours and per-label matching are exercised."""
    base = paper_map(seed=seed)
    names = np.where(np.random.default_rng(seed).random(len(base)) < 0.7, "building", "park")
    return Objects.from_names(base.x, base.y, names, crs=base.crs)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A map file, simulated images of it (one with a tilt given, one scrambled so that it is rejected)."""
    root = tmp_path_factory.mktemp("plot")
    map_path = root / "two.mapdb"
    write_map(map_path, _two_label_map())
    with open_map(map_path) as m:
        images = simulate_images(m, 2, pixel_std=1.0, yaw="random", spurious_rate=0.3, seed=4)
        images += simulate_images(m, 1, pixel_std=1.0, yaw="random", attitude_std=3.0, with_attitude=True, seed=5,
                                  id_prefix="tilted-")
    scrambled = json.loads(json.dumps(images[0]))
    rng = np.random.default_rng(0)
    for obj in scrambled["objects"]:  # the same labels at random pixels: nothing in the map looks like it
        obj["x"], obj["y"] = float(rng.uniform(0, 640)), float(rng.uniform(0, 480))
    scrambled["id"] = "scrambled"
    images.append(scrambled)
    images_path = root / "images.jsonl"
    images_path.write_text("".join(json.dumps(im) + "\n" for im in images))
    return map_path, images_path, images


def _run(*args: object):
    return CliRunner().invoke(show, [str(a) for a in args], catch_exceptions=False)


def _assert_png(path: Path) -> None:
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    with Image.open(path) as im:
        im.verify()
    with Image.open(path) as im:
        w, h = im.size
    assert 800 <= w <= 2000 and 500 <= h <= 1500 and w > h, (w, h)


def _hidden(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


# ----------------------------------------------------------------------------------------- show


def test_show_draws_an_accepted_image(setup, tmp_path: Path) -> None:
    map_path, images_path, images = setup
    out = tmp_path / "match.png"
    result = _run(map_path, images_path, "--id", images[1]["id"], "-o", out)
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"{images[1]['id']}: ok at ") and result.output.rstrip().endswith(str(out))
    _assert_png(out)
    assert _hidden(tmp_path) == []


def test_show_draws_a_rejected_image_by_line(setup, tmp_path: Path) -> None:
    map_path, images_path, images = setup
    out = tmp_path / "rejected.png"
    result = _run(map_path, images_path, "--line", len(images), "-o", out)
    assert result.exit_code == 0, result.output
    assert result.output.startswith("scrambled: rejected (")
    _assert_png(out)


def test_show_draws_the_first_image_by_default_and_other_formats(setup, tmp_path: Path) -> None:
    map_path, images_path, images = setup
    out = tmp_path / "first.svg"
    result = _run(map_path, images_path, "-o", out)
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"{images[0]['id']}: ")
    assert out.read_text().lstrip().startswith("<?xml")


@pytest.mark.parametrize("args, message", [
    (["--id", "no-such-image"], "images.jsonl: no image with id 'no-such-image'"),
    (["--line", "99"], "images.jsonl: no image on line 99"),
])
def test_show_with_a_bad_choice_is_a_one_line_error_and_writes_nothing(setup, tmp_path: Path, args, message) -> None:
    map_path, images_path, _ = setup
    out = tmp_path / "match.png"
    result = _run(map_path, images_path, *args, "-o", out)
    assert result.exit_code == 1
    assert result.output.count("\n") == 1 and result.output.startswith("mapdb: error: ")
    assert result.output.rstrip().endswith(message)
    assert not out.exists() and _hidden(tmp_path) == []


def test_show_refuses_bad_arguments_before_any_work(setup, tmp_path: Path) -> None:
    map_path, images_path, images = setup
    both = _run(map_path, images_path, "--id", "x", "--line", "1", "-o", tmp_path / "a.png")
    assert both.exit_code == 2 and "give --id or --line, not both" in both.output
    unknown_ending = _run(map_path, images_path, "-o", tmp_path / "a.nopicture")
    assert unknown_ending.exit_code == 2 and "must end in one of" in unknown_ending.output
    # An output that is an input is refused, and the input is left as it was.
    copy = tmp_path / "map.png"
    copy.write_bytes(map_path.read_bytes())
    clash = _run(copy, images_path, "-o", copy)
    assert clash.exit_code == 1 and "is the same file as input" in clash.output
    assert copy.read_bytes() == map_path.read_bytes()
    # A missing output directory is refused, as GDAL does, unless --parents asks for it.
    missing = tmp_path / "new" / "dir" / "m.png"
    refused = _run(map_path, images_path, "-o", missing)
    assert refused.exit_code == 1 and refused.output.startswith("mapdb: error: ") and not missing.parent.exists()
    made = _run(map_path, images_path, "-o", missing, "--parents")
    assert made.exit_code == 0, made.output
    _assert_png(missing)
    # A bad image line, when chosen, is its own one-line error.
    bad = tmp_path / "bad.jsonl"
    bad.write_text(json.dumps(images[0]) + "\n{oops\n")
    broken = _run(map_path, bad, "--line", "2", "-o", tmp_path / "b.png")
    assert broken.exit_code == 1 and broken.output.startswith("mapdb: error: ") and "line 2" in broken.output
    assert not (tmp_path / "b.png").exists()


# ---------------------------------------------------------------------------------- geometry drawn


def _true_pairs(images: list[dict], m, k: int):
    """Image objects of image ``k`` that come from the map, with the map position each came from."""
    index = np.asarray(images[k]["truth"]["map_index"])
    objects = m.all()
    true = index >= 0
    return true, objects.x[index[true]] + 1j * objects.y[index[true]]


@pytest.mark.parametrize("k", [1, 2])  # level, and tilted (the answer's levelled pixels)
def test_the_answer_places_true_objects_on_their_map_objects(setup, k: int) -> None:
    map_path, _, images = setup
    with open_map(map_path) as m:
        answer = localize(images[k], m)
        assert answer.status == "ok" and answer.levelled == (k == 2)
        geom = match_geometry(images[k], answer, m)
        true, where = _true_pairs(images, m, k)
    assert geom is not None and geom.pose == "answer"
    # Pixel noise of 1 px at ~0.1 m/px: a sign or angle error in the similarity would put them metres off.
    assert np.max(np.abs(geom.world[true] - where)) < 1.0
    assert geom.inlier[true].all() and geom.inlier.sum() >= answer.inliers
    assert np.all(geom.distance[geom.inlier] <= geom.gate_m)
    assert geom.position == complex(answer.x, answer.y)
    if k == 1:  # a level image's footprint is centred on the answer (a tilted one's is not)
        assert abs(np.mean(geom.footprint) - geom.position) < 1e-6


def test_a_rejected_simulated_image_is_placed_by_its_true_pose(setup) -> None:
    map_path, _, images = setup
    with open_map(map_path) as m:
        answer = localize(images[-1], m)
        assert answer.status == "rejected"
        geom = match_geometry(images[-1], answer, m)
        # The unscrambled original under its true pose: its true objects sit on their map objects.
        original = match_geometry(images[0], Answer(id=None, status="rejected"), m)
        true, where = _true_pairs(images, m, 0)
    assert geom is not None and geom.pose == "truth"
    assert geom.position == complex(images[-1]["truth"]["x"], images[-1]["truth"]["y"])
    assert abs(np.mean(geom.footprint) - geom.position) < 1e-6  # simulated level: centred on the truth
    assert original is not None and np.max(np.abs(original.world[true] - where)) < 1.0


def test_objects_of_a_label_the_map_lacks_are_outliers(setup) -> None:
    map_path, _, images = setup
    doc = json.loads(json.dumps(images[1]))
    with open_map(map_path) as m:
        answer = localize(doc, m)
        doc["objects"].append({"label": "lighthouse", "x": 320.0, "y": 240.0})
        geom = match_geometry(doc, answer, m)
    assert geom is not None
    assert not geom.inlier[-1] and math.isinf(geom.distance[-1]) and geom.inlier[:-1].sum() >= answer.inliers


def test_pictures_without_a_pose_still_draw(setup, tmp_path: Path) -> None:
    map_path, _, images = setup
    doc = {k: v for k, v in images[-1].items() if k != "truth"}
    with open_map(map_path) as m:
        answer = localize(doc, m)
        assert answer.status == "rejected" and match_geometry(doc, answer, m) is None
        # Around the best candidate, and (with none) the image's own objects in pixels.
        with_candidate = dataclasses.replace(answer, candidates=[
            Candidate(images[0]["truth"]["x"], images[0]["truth"]["y"], inliers=4, score=-1.0, sigma_m=None)])
        plot_match(doc, with_candidate, m, tmp_path / "candidate.png")
        plot_match(doc, dataclasses.replace(answer, candidates=[]), m, tmp_path / "pixels.png")
    _assert_png(tmp_path / "candidate.png")
    _assert_png(tmp_path / "pixels.png")


# -------------------------------------------------------------------------------------- evaluation


def test_evaluation_picture_with_false_positives_rejections_and_no_answers(tmp_path: Path) -> None:
    images = [{"id": f"im{i}", "objects": [], "truth": {"x": 500_000.0 + 40 * i, "y": 5_000_050.0,
                                                        "bound": {"error_m": 0.05}}} for i in range(5)]
    results: list[dict] = [{"status": "ok", "x": 500_000.1, "y": 5_000_050.0},
               {"status": "ok", "x": 500_900.0, "y": 5_000_400.0},  # a false positive, far away
               {"status": "rejected", "reason": "no match"},
               {"status": "ok", "x": 500_123.0, "y": 5_000_050.0},  # a false positive, 3 m off
               {"status": "ok", "x": 500_160.0, "y": 5_000_050.2}]
    outcomes = [outcome(im, Answer.from_json(r), 1.0) for im, r in zip(images, results, strict=True)]
    plot_evaluation(outcomes, tmp_path / "eval.png", map_objects=paper_map(), title="t")
    _assert_png(tmp_path / "eval.png")
    rejected = [outcome(im, Answer(id=im["id"], status="rejected"), 1.0) for im in images]  # nothing accepted: no curve
    plot_evaluation(rejected, tmp_path / "none.png", crs="EPSG:32631")
    _assert_png(tmp_path / "none.png")


def test_evaluate_plot_command_still_works(setup, tmp_path: Path) -> None:
    map_path, images_path, _ = setup
    png = tmp_path / "eval.png"
    result = CliRunner().invoke(cli, ["evaluate", str(map_path), str(images_path), "--quiet", "--json",
                                      "--plot", str(png)], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["images"] == 4
    _assert_png(png)
    assert _hidden(tmp_path) == []


# ----------------------------------------------------------------------------------------- small


def test_crs_is_named_for_people() -> None:
    assert crs_name("EPSG:32631") == "EPSG:32631 (WGS 84 / UTM zone 31N)"
    assert crs_name(None) == "unknown CRS" and crs_name("") == "unknown CRS"
    assert crs_name("not a crs") == "not a crs"


def test_importing_the_pictures_modules_does_not_import_matplotlib() -> None:
    code = ("import sys, mapdb.evaluation.evaluation_plot, mapdb.evaluation.match_plot, mapdb.evaluation.evaluate; "
            "print('matplotlib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_the_evaluation_does_not_import_its_pictures() -> None:
    # The pictures take their defaults from the evaluation, never the other way round: no import cycle.
    code = ("import sys, mapdb.evaluation.evaluate; "
            "print(sorted(m for m in sys.modules if m.endswith(('_plot', '.drawing', '.match_geometry'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
