"""Image-objects input: the published schema, parsing into arrays, and one-line errors for bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from jsonschema import Draft202012Validator

from mapdb.errors import ImageInputError, MapdbIOError
from mapdb.images import (
    IMAGE_SCHEMA_PATH,
    MAX_OBJECTS,
    image_schema,
    parse_image,
    read_image_documents,
    split_image_documents,
)


def _doc(**extra):
    doc = {
        "id": "frame-1",
        "width": 640,
        "height": 480,
        "objects": [
            {"label": "building", "x": 10.5, "y": 20.0},
            {"label": "road_intersection", "x": 640, "y": 0},
        ],
    }
    doc.update(extra)
    return doc


def test_schema_file_is_a_valid_json_schema_and_accepts_the_issue_example() -> None:
    Draft202012Validator.check_schema(image_schema())
    assert IMAGE_SCHEMA_PATH.name == "image.schema.json"
    example = _doc(
        prior={"x": 385120.0, "y": 6671230.0, "radius": 250.0},
        attitude={"roll_deg": 0.4, "pitch_deg": -1.2},
        camera={"fov_deg": 35.0},
        altitude_m=100.0,
        truth={"x": 1.0},  # other keys are ignored
    )
    assert not list(Draft202012Validator(image_schema()).iter_errors(example))


def test_parse_gives_arrays_and_hints() -> None:
    im = parse_image(
        _doc(prior={"lon": 7.42, "lat": 43.73, "radius": 300}, attitude={"roll_deg": 1.0},
             camera={"fov_deg": 45}, altitude_m=120)
    )
    assert im.id == "frame-1" and len(im) == 2
    assert im.x.dtype == np.float64 and im.x.tolist() == [10.5, 640.0] and im.y.tolist() == [20.0, 0.0]
    assert im.names.tolist() == ["building", "road_intersection"]
    assert im.prior.lonlat and (im.prior.x, im.prior.y, im.prior.radius) == (7.42, 43.73, 300.0)
    assert (im.roll_deg, im.pitch_deg, im.fov_deg, im.altitude_m) == (1.0, None, 45.0, 120.0)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"width": None}, "width: None is not of type 'number'"),
        ({"height": 0}, "height: 0 is less than or equal to the minimum of 0"),
        ({"objects": [{"label": "building", "x": -3, "y": 5}]}, "objects[0].x is negative (-3)"),
        ({"objects": [{"label": "building", "x": 3}]}, "objects[0]: 'y' is a required property"),
        ({"objects": [{"label": "", "x": 3, "y": 4}]}, "objects[0].label"),
        ({"objects": [{"label": "building", "x": 700, "y": 5}]}, "objects[0] at (700, 5) is outside the 640x480"),
        ({"objects": [{"label": "building", "x": 5, "y": 480.5}]}, "outside the 640x480 image"),
        ({"prior": {"x": 1, "lon": 2, "y": 3, "radius": 1}}, "prior: give either x and y"),
        ({"prior": {"x": 1, "y": 3}}, "prior: 'radius' is a required property"),
        ({"camera": {"fov_deg": 180}}, "camera.fov_deg"),
    ],
)
def test_bad_documents_raise_one_line_errors_naming_the_field(change, message) -> None:
    doc = _doc()
    doc.update(change)
    with pytest.raises(ImageInputError) as err:
        parse_image(doc, "images.jsonl line 4")
    text = str(err.value)
    assert text.startswith("images.jsonl line 4: ") and message in text and "\n" not in text


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_numbers_from_python_json_are_rejected(literal: str) -> None:
    template = '{"width": 640, "height": 480, "objects": [{"label": "b", "x": 1, "y": LITERAL}]}'
    line = template.replace("LITERAL", literal)
    doc = json.loads(line)  # Python's reader accepts these literals
    assert not math.isfinite(doc["objects"][0]["y"])
    with pytest.raises(ImageInputError, match=r"objects\[0\]\.y is .*not a finite number"):
        parse_image(doc, "f")
    with pytest.raises(ImageInputError, match="altitude_m is nan, not a finite number"):
        parse_image(_doc(altitude_m=float("nan")), "f")


def test_not_an_object_and_too_many_objects() -> None:
    with pytest.raises(ImageInputError, match="an image must be a JSON object, got list"):
        parse_image([1, 2], "f")
    many = _doc(objects=[{"label": "b", "x": 1, "y": 1}] * (MAX_OBJECTS + 1))
    with pytest.raises(ImageInputError, match=f"at most {MAX_OBJECTS}"):
        parse_image(many, "f")


def test_json_lines_with_a_malformed_line_keep_the_others() -> None:
    text = json.dumps(_doc(id="a")) + "\n\n{not json\n" + json.dumps(_doc(id="c")) + "\n"
    docs = list(split_image_documents(text, "in.jsonl"))
    assert [w for w, _ in docs] == ["in.jsonl line 1", "in.jsonl line 3", "in.jsonl line 4"]
    assert docs[0][1]["id"] == "a" and docs[2][1]["id"] == "c"
    assert isinstance(docs[1][1], ImageInputError)
    assert str(docs[1][1]).startswith("in.jsonl line 3: malformed JSON")


def test_a_pretty_printed_object_or_an_array_is_read_whole() -> None:
    docs = list(split_image_documents(json.dumps(_doc(id="p"), indent=2), "one.json"))
    assert len(docs) == 1 and docs[0][1]["id"] == "p"
    docs = list(split_image_documents(json.dumps([_doc(id="x"), _doc(id="y")], indent=1), "arr.json"))
    assert [d["id"] for _, d in docs] == ["x", "y"]


def test_reading_files(tmp_path) -> None:
    with pytest.raises(MapdbIOError, match="no such images file"):
        read_image_documents(tmp_path / "missing.jsonl")
    binary = tmp_path / "bin.jsonl"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ImageInputError, match="not UTF-8"):
        read_image_documents(binary)
    good = tmp_path / "ok.jsonl"
    good.write_text(json.dumps(_doc()) + "\n")
    (where, doc), = read_image_documents(good)
    assert where.endswith("ok.jsonl line 1") and parse_image(doc).id == "frame-1"


def test_the_fast_object_check_agrees_with_the_schema() -> None:
    from mapdb.images import _plain_object_ok

    item_schema = {**image_schema()["properties"]["objects"]["items"]}
    validator = Draft202012Validator(item_schema)
    entries = [
        {"label": "b", "x": 0, "y": 0},
        {"label": "b", "x": 1.5, "y": 2, "score": 0.9},
        {"label": "", "x": 1, "y": 1},
        {"label": 3, "x": 1, "y": 1},
        {"label": "b", "x": True, "y": 1},
        {"label": "b", "x": "1", "y": 1},
        {"label": "b", "x": -0.1, "y": 1},
        {"label": "b", "y": 1},
        {"x": 1, "y": 1},
        ["b", 1, 1],
        None,
    ]
    for entry in entries:
        assert _plain_object_ok(entry) == validator.is_valid(entry), entry
