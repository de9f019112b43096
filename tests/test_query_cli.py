"""``mapdb query``: JSON Lines in, one answer per line out, in order; bad lines rejected, not fatal."""

from __future__ import annotations

import json
import math

from click.testing import CliRunner
from mapdb_cli.main import cli


def _run(*args: str, input: str | None = None):
    return CliRunner().invoke(cli, ["query", *args], input=input, catch_exceptions=False)


def test_round_trip_with_a_malformed_line(paper_setup, tmp_path) -> None:
    map_path, images = paper_setup
    lines = [json.dumps(images[0]), "{this is not json", json.dumps(images[1]), "", json.dumps(images[2])]
    images_path = tmp_path / "in.jsonl"
    images_path.write_text("\n".join(lines) + "\n")
    out_path = tmp_path / "out.jsonl"
    result = _run(str(map_path), str(images_path), "-o", str(out_path))
    assert result.exit_code == 0, result.output
    answers = [json.loads(line) for line in out_path.read_text().splitlines()]
    assert len(answers) == 4  # the blank line is not an image
    assert [a["id"] for a in answers] == [images[0]["id"], None, images[1]["id"], images[2]["id"]]
    bad = answers[1]
    assert bad["status"] == "rejected" and "line 2: malformed JSON" in bad["reason"]
    for answer, image in zip([answers[0], answers[2], answers[3]], images, strict=True):
        assert answer["status"] == "ok", answer
        truth = image["truth"]
        assert math.hypot(answer["x"] - truth["x"], answer["y"] - truth["y"]) < 1.0
        assert answer["crs"] == "EPSG:32631" and answer["lon"] is not None
        assert set(answer) >= {"inliers", "heading_deg", "scale_m_per_px", "sigma_m", "score", "candidates",
                               "time_ms", "altitude_m"}


def test_stdin_stdout_prior_option_and_paper_method(paper_setup) -> None:
    map_path, images = paper_setup
    truth = images[0]["truth"]
    doc = {k: v for k, v in images[0].items() if k != "truth"}
    result = _run(str(map_path), "-", "--prior", f"{truth['x'] + 5},{truth['y'] - 5},30", input=json.dumps(doc) + "\n")
    assert result.exit_code == 0, result.output
    (answer,) = [json.loads(line) for line in result.output.splitlines()]
    assert answer["status"] == "ok" and math.hypot(answer["x"] - truth["x"], answer["y"] - truth["y"]) < 1.0
    # A prior elsewhere on the map: the image is not there.
    far = _run(str(map_path), "-", "--prior", f"{truth['x'] + 120},{truth['y']},10", input=json.dumps(doc) + "\n")
    assert json.loads(far.output)["status"] == "rejected"
    # The paper's method, on a cut-down image and a small prior so that the test stays fast.
    small = {**doc, "objects": doc["objects"][:7], "altitude_m": 100.0,
             "prior": {"x": truth["x"], "y": truth["y"], "radius": 5.0}}
    paper = _run(str(map_path), "-", "--method", "paper", input=json.dumps(small) + "\n")
    answer = json.loads(paper.output)
    assert answer["status"] == "ok", answer
    assert answer["score"] is None and answer["sigma_m"] is None and answer["error_std"] >= 0
    assert answer["inliers"] >= 6


def test_errors_are_one_line_messages(paper_setup, tmp_path) -> None:
    map_path, _ = paper_setup
    missing = _run(str(map_path), str(tmp_path / "nope.jsonl"))
    assert missing.exit_code == 1
    assert missing.output.strip().startswith("mapdb: error: ") and "no such images file" in missing.output
    assert len(missing.output.strip().splitlines()) == 1
    images_path = tmp_path / "one.jsonl"
    images_path.write_text('{"width": 10, "height": 10, "objects": []}\n')
    no_map = _run(str(tmp_path / "nomap.mapdb"), str(images_path))
    assert no_map.exit_code == 1 and "mapdb: error:" in no_map.output and "Traceback" not in no_map.output
    bad_prior = _run(str(map_path), str(images_path), "--prior", "1,2")
    assert bad_prior.exit_code == 2 and "X,Y,R" in bad_prior.output
