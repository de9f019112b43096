"""A heading in an image's prior (or ``mapdb query --heading``) with its altitude and field of view: a pose prior.

The image document's ``prior.heading_deg`` / ``heading_sigma_deg`` (``mapdb/detections/images.py``,
``docs/images.md``) reach the matcher's pose-prior stage (:mod:`mapdb.match.pose_prior`) through the localizer;
without a heading the answers are the ones the disc alone gives.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.build.pipeline import build_map
from mapdb.detections import images as image_docs
from mapdb.detections.images import check_prior, image_schema, parse_image
from mapdb.errors import ImageInputError
from mapdb.localize.localizer import Localizer
from mapdb.mapfile.reader import open_map
from mapdb.match import pose_prior
from mapdb.simulation.simulate import simulate_images

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"


@pytest.fixture(scope="module")
def sample(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict]]:
    """The sample map's file and four images of it at 120 m (their truth beside them), each with the true
    altitude (the scale, with the field of view) and a 20 m prior 5 m off the truth, without a heading."""
    path = tmp_path_factory.mktemp("qpose") / "helsinki.mapdb"
    build_map([SAMPLE], path)
    with open_map(path) as m:
        shots = simulate_images(m, 4, altitude=120.0, fov_deg=60.0, yaw="random", pixel_std=1.0,
                                attitude_std=0.05, min_objects=6, seed=4)
    docs = [{**im, "altitude_m": im["truth"]["altitude_m"],
             "prior": {"x": im["truth"]["x"] + 4.0, "y": im["truth"]["y"] - 3.0, "radius": 20.0}} for im in shots]
    return path, docs


def _headed(doc: dict, turn: float = 0.0, **extra: float) -> dict:
    """The document with its true heading (plus ``turn`` degrees) in its prior."""
    heading = {"heading_deg": (doc["truth"]["heading_deg"] + turn) % 360.0, **extra}
    return {**doc, "prior": {**doc["prior"], **heading}}


def _query(map_path: Path, docs: list[dict], *options: str):
    text = "".join(json.dumps(d) + "\n" for d in docs)
    return CliRunner().invoke(cli, ["query", str(map_path), "-", *options], input=text, catch_exceptions=False)


def _answers(result) -> list[dict]:
    assert result.exit_code == 0, result.output
    return [json.loads(line) for line in result.output.splitlines()]


def _off(answer: dict, doc: dict) -> float:
    return math.hypot(answer["x"] - doc["truth"]["x"], answer["y"] - doc["truth"]["y"])


def _same(one: dict, other: dict) -> bool:
    """Two answers equal but for their time."""
    return {k: v for k, v in one.items() if k != "time_ms"} == {k: v for k, v in other.items() if k != "time_ms"}


def test_a_heading_in_the_prior_answers_through_the_pose_stage(sample) -> None:
    map_path, docs = sample
    posed = _answers(_query(map_path, [_headed(d, heading_sigma_deg=2.0) for d in docs]))
    for answer, doc in zip(posed, docs, strict=True):
        assert answer["status"] == "ok" and answer["path"] == "pose-prior", answer
        assert _off(answer, doc) < 0.5
    # Without a heading: the disc alone, as before (no pose prior, so no "path"), the same answer as the
    # localizer gives for the prior handed to it apart.
    plain = _answers(_query(map_path, docs))
    with open_map(map_path) as m:
        loc = Localizer(m)
        for answer, doc in zip(plain, docs, strict=True):
            assert answer["status"] == "ok" and "path" not in answer and _off(answer, doc) < 1.0
            p = doc["prior"]
            apart = loc.localize({k: v for k, v in doc.items() if k != "prior"}, (p["x"], p["y"], p["radius"]))
            assert _same(answer, json.loads(json.dumps(apart.to_json())))


def test_a_heading_without_a_scale_is_ignored_with_a_note(sample) -> None:
    map_path, docs = sample
    doc = {k: v for k, v in _headed(docs[0]).items() if k != "altitude_m"}
    (answer,) = _answers(_query(map_path, [doc]))
    assert "path" not in answer and any("heading_deg ignored" in n for n in answer.get("notes", [])), answer


@pytest.mark.parametrize(("extra", "field"), [
    ({"heading_deg": float("nan")}, "prior.heading_deg is nan, not a finite number"),
    ({"heading_deg": 10.0, "heading_sigma_deg": 20.0}, "prior.heading_sigma_deg: 20.0 is greater than the maximum"),
    ({"heading_deg": 10.0, "heading_sigma_deg": 0.0}, "prior.heading_sigma_deg: 0.0 is less than or equal to"),
    ({"heading_deg": 400.0}, "prior.heading_deg: 400.0 is greater than the maximum of 360"),
    ({"heading_sigma_deg": 3.0}, "prior.heading_sigma_deg is given without prior.heading_deg"),
])
def test_bad_heading_values_reject_the_image_naming_the_field(sample, extra, field) -> None:
    map_path, docs = sample
    bad = {**docs[0], "prior": {**docs[0]["prior"], **extra}}
    first, second = _answers(_query(map_path, [bad, _headed(docs[1])]))
    assert first["status"] == "rejected" and field in first["reason"], first
    assert second["status"] == "ok" and second["path"] == "pose-prior"  # the other images are still answered
    with pytest.raises(ImageInputError, match=re.escape(field)):
        parse_image(bad, "f line 1")


def test_a_heading_without_a_position_is_refused(sample) -> None:
    map_path, docs = sample
    with pytest.raises(ImageInputError, match="prior: give either x and y"):
        parse_image({**docs[0], "prior": {"radius": 20.0, "heading_deg": 10.0}})
    result = _query(map_path, docs[:1], "--heading", "10")
    assert result.exit_code == 2 and "--heading" in result.output and "--prior" in result.output


@pytest.mark.parametrize(("value", "field"), [
    ("nan", "prior.heading_deg is nan, not a finite number"),
    ("10,20", "prior.heading_sigma_deg: 20.0 is greater than the maximum of 10"),
    ("1,2,3", "is not DEG or DEG,SIGMA"),
])
def test_bad_heading_options_are_one_line_usage_errors(sample, value, field) -> None:
    map_path, docs = sample
    result = _query(map_path, docs[:1], "--prior", "0,0,20", "--heading", value)
    assert result.exit_code == 2 and field in result.output and "--heading" in result.output, result.output
    # A usage error as --prior's: click's usage lines, then one line naming the option, its value and the field.
    (error,) = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert "Traceback" not in result.output and error.startswith("Error: Invalid value for '--heading': '")


def test_the_heading_option_applies_to_images_without_their_own_prior(sample) -> None:
    map_path, docs = sample
    bare = {k: v for k, v in docs[0].items() if k != "prior"}
    t = docs[0]["truth"]
    option = ["--prior", f"{t['x'] + 4.0},{t['y'] - 3.0},20", "--heading", f"{t['heading_deg']:.6f},3"]
    # The image with its own prior (no heading) keeps it: a heading half round, if applied, would reject it.
    turned = ["--prior", option[1], "--heading", f"{(t['heading_deg'] + 180.0) % 360.0:.6f}"]
    posed, own = _answers(_query(map_path, [bare, docs[1]], *option))
    assert posed["status"] == "ok" and posed["path"] == "pose-prior" and _off(posed, docs[0]) < 0.5
    (own_turned,) = _answers(_query(map_path, [docs[1]], *turned))
    (own_alone,) = _answers(_query(map_path, [docs[1]]))
    assert "path" not in own and _same(own, own_alone) and _same(own_turned, own_alone)


def test_the_ranges_are_stated_once_and_the_format_document_agrees() -> None:
    schema = image_schema()["properties"]["prior"]["properties"]
    bound = schema["heading_sigma_deg"]["maximum"]
    assert image_docs.MAX_HEADING_SIGMA_DEG == pose_prior.MAX_HEADING_SIGMA_DEG == bound
    assert schema["heading_sigma_deg"]["exclusiveMinimum"] == 0
    assert schema["heading_deg"]["maximum"] == -schema["heading_deg"]["minimum"] == image_docs.MAX_HEADING_DEG
    assert check_prior(1.0, 2.0, 3.0, heading=(350.0,)).heading_sigma_deg == image_docs.Prior.heading_sigma_deg == 5.0
    # docs/images.md's table of the prior's fields: every field the schema has, with the schema's bounds.
    doc = (REPO / "docs" / "images.md").read_text(encoding="utf-8")
    rows = dict(re.findall(r"^\| `prior\.(\w+)` \| ([^|]+) \|", doc, flags=re.M))
    assert set(rows) == set(schema)
    for name, bounds in schema.items():
        stated = {float(v) for v in re.findall(r"-?\d+(?:\.\d+)?(?:e[+-]?\d+)?", rows[name])}
        assert stated == {float(bounds[key]) for key in ("minimum", "maximum", "exclusiveMinimum") if key in bounds}
