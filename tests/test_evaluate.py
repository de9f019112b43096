"""Evaluation statistics on hand-made results, image-file errors, the plot, and the command end to end."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.answers import Answer
from mapdb.errors import ImageInputError, MapdbIOError
from mapdb.evaluation.evaluate import evaluate_images, format_summary, load_images, outcome, summarize
from mapdb.evaluation.evaluation_plot import plot_evaluation
from mapdb.evaluation.paper_bench import bench_paper, format_bench
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.writer import write_map
from mapdb.simulation.simulate import paper_map, simulate_images

HAS_LOCALIZER = importlib.util.find_spec("mapdb.localize.localizer") is not None


def _image(i: int, x: float, y: float, bound_error: float | None, n_true: int) -> dict:
    bound = None if bound_error is None else {"x": x + bound_error, "y": y, "error_m": bound_error, "n": n_true}
    return {"id": f"im{i}", "width": 640, "height": 480,
            "objects": [{"label": "building", "x": 10.0, "y": 10.0}] * (n_true + 1),
            "truth": {"x": x, "y": y, "map_index": [0] * n_true + [-1], "bound": bound}}


def test_statistics_of_correct_rejected_and_false_positive_answers() -> None:
    images = [_image(i, 1000.0 * i, 50.0, 0.1 * (i + 1), 8) for i in range(6)]
    images.append(_image(6, 0.0, 0.0, None, 2))  # too few objects: rejected, no bound
    results = [
        {"status": "ok", "x": 0.0 + 0.3, "y": 50.0 + 0.4},  # error 0.5
        {"status": "ok", "x": 1000.0, "y": 50.0 - 1.0},  # error 1.0
        {"status": "ok", "x": 2000.0, "y": 52.0},  # error exactly 2.0: not above the threshold
        {"status": "ok", "x": 3000.0 + 30.0, "y": 50.0 + 40.0},  # error 50: false positive
        {"status": "rejected", "reason": "no match"},
        {"status": "ok", "x": 5000.0 - 2.1, "y": 50.0},  # error 2.1: false positive
        {"status": "rejected", "reason": "fewer than 3 objects"},
    ]
    times = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    outcomes = [outcome(im, Answer.from_json(r), t) for im, r, t in zip(images, results, times, strict=True)]
    assert outcomes[0]["error_m"] == pytest.approx(0.5)
    assert outcomes[4]["error_m"] is None and outcomes[4]["reason"] == "no match"
    assert outcomes[6]["n_true"] == 2 and outcomes[6]["bound_error_m"] is None

    s = summarize(outcomes, fp_threshold=2.0)
    assert (s["images"], s["accepted"], s["rejected"], s["errors"]) == (7, 5, 2, 0)
    assert s["rejected_fraction"] == pytest.approx(2 / 7)
    assert s["false_positives"] == 2 and s["false_positive_fraction"] == pytest.approx(2 / 5)
    assert s["correct"] == 3
    assert s["rms_m"] == pytest.approx(math.sqrt((0.25 + 1.0 + 4.0) / 3))
    assert s["median_m"] == pytest.approx(1.0)
    assert s["max_m"] == pytest.approx(2.0)
    assert s["p95_m"] == pytest.approx(np.percentile([0.5, 1.0, 2.0], 95))
    # Bound over the six images that have one, and over the three answered correctly (errors 0.1, 0.2, 0.3).
    assert s["bound_rms_m"] == pytest.approx(math.sqrt(np.mean((0.1 * np.arange(1, 7)) ** 2)))
    assert s["bound_rms_correct_m"] == pytest.approx(math.sqrt((0.01 + 0.04 + 0.09) / 3))
    assert s["rms_over_bound"] == pytest.approx(s["rms_m"] / s["bound_rms_correct_m"])
    # Rejections among images with >= 6 true objects: one of six.
    assert s["images_min_objects"] == 6 and s["rejected_fraction_min_objects"] == pytest.approx(1 / 6)
    assert s["time_median_ms"] == pytest.approx(4.0)
    assert s["time_p95_ms"] == pytest.approx(np.percentile(times, 95))
    # A stricter threshold turns the 2 m answer into a false positive.
    assert summarize(outcomes, fp_threshold=1.5)["false_positives"] == 3
    table = format_summary(s)
    assert "2/5 accepted" in table and "rejected: 2" in table


def test_empty_statistics_are_none() -> None:
    images = [_image(0, 0.0, 0.0, 0.2, 5)]
    s = summarize([outcome(images[0], Answer(id=0, status="rejected"), 1.0)])
    assert s["rms_m"] is None and s["false_positive_fraction"] is None and s["rejected_fraction"] == 1.0
    assert "-" in format_summary(s)


def test_load_images_reports_bad_files(tmp_path: Path) -> None:
    good = tmp_path / "good.jsonl"
    good.write_text("\n".join(json.dumps(im) for im in simulate_images(paper_map(), 3)) + "\n\n")
    assert len(load_images(good)) == 3
    bad = tmp_path / "bad.jsonl"
    bad.write_text(good.read_text().splitlines()[0] + "\n{not json\n")
    with pytest.raises(ImageInputError, match=r"bad.jsonl line 2: malformed JSON"):
        load_images(bad)
    no_truth = tmp_path / "query.jsonl"
    no_truth.write_text(json.dumps({"width": 640, "height": 480, "objects": []}) + "\n")
    with pytest.raises(ImageInputError, match="no truth"):
        load_images(no_truth)
    with pytest.raises(MapdbIOError, match="no such images file"):
        load_images(tmp_path / "missing.jsonl")


def test_plot_is_written(tmp_path: Path) -> None:
    images = [_image(i, 10.0 * i, 5.0, 0.1, 8) for i in range(4)]
    results = [{"status": "ok", "x": 0.2, "y": 5.0}, {"status": "rejected"}, {"status": "ok", "x": 60.0, "y": 5.0},
               {"status": "ok", "x": 30.0, "y": 5.5}]
    outcomes = [outcome(im, Answer.from_json(r), 1.0) for im, r in zip(images, results, strict=True)]
    png = tmp_path / "eval.png"
    plot_evaluation(outcomes, png, map_objects=paper_map())
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.skipif(not HAS_LOCALIZER, reason="mapdb.localize.localizer is not written yet")
def test_evaluate_command_on_simulated_images(tmp_path: Path) -> None:
    map_path = tmp_path / "paper.mapdb"
    write_map(map_path, paper_map())
    images = tmp_path / "images.jsonl"
    runner = CliRunner()
    result = runner.invoke(cli, ["simulate", str(map_path), "-o", str(images), "--n", "6", "--pixel-std", "1",
                                 "--quiet"])
    assert result.exit_code == 0, result.output
    png = tmp_path / "eval.png"
    result = runner.invoke(cli, ["evaluate", str(map_path), str(images), "--json", "--quiet", "--plot", str(png),
                                 "--jobs", "2"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["images"] == 6 and summary["accepted"] + summary["rejected"] == 6
    assert summary["errors"] == 0
    assert png.exists()
    result = runner.invoke(cli, ["evaluate", str(map_path), str(tmp_path / "missing.jsonl")])
    assert result.exit_code == 1 and result.output.startswith("mapdb: error:")


@pytest.mark.skipif(not HAS_LOCALIZER, reason="mapdb.localize.localizer is not written yet")
def test_evaluate_images_in_process_and_within_a_budget() -> None:
    m = MemoryMap(paper_map())
    images = simulate_images(m, 4, seed=5)
    outcomes, summary = evaluate_images(m, images, method="fast")
    assert [o["id"] for o in outcomes] == [im["id"] for im in images]
    assert summary["accepted"] == 4 and summary["max_m"] < 0.01  # zero error: exact answers
    # The budget is a hard limit: with none left, images already started are stopped and left out.
    outcomes, summary = evaluate_images(m, images, method="fast", budget_s=0.0)
    assert outcomes == [] and summary["images"] == 0
    # A budget that suffices answers every image, in input order, in worker processes.
    outcomes, summary = evaluate_images(m, images, method="fast", budget_s=600.0, jobs=2)
    assert [o["id"] for o in outcomes] == [im["id"] for im in images] and summary["accepted"] == 4


@pytest.mark.skipif(not HAS_LOCALIZER, reason="mapdb.localize.localizer is not written yet")
def test_bench_paper_table_shape() -> None:
    result = bench_paper(n=4, methods=("fast",), cases=[1, 5], budget_s=None)
    assert [c["case"] for c in result["cases"]] == [1, 5]
    assert all(c["fast"]["images"] == 4 and "paper" not in c for c in result["cases"])
    assert result["cases"][1]["objects_mean"] > result["cases"][0]["objects_mean"]  # wider field of view
    table = format_bench(result)
    assert "0/500 (0.0%)" in table and "9/500 (1.8%)" in table and "Case 5" in table
