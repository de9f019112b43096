"""Image-objects input: the published schema, parsing into arrays, and one-line errors for bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from jsonschema import Draft202012Validator

from mapdb.detections.images import (
    IMAGE_SCHEMA_PATH,
    MAX_OBJECTS,
    image_schema,
    parse_image,
    read_image_documents,
    split_image_documents,
)
from mapdb.errors import ImageInputError, MapdbIOError


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
        ({"height": 0}, "height: 0 is less than the minimum of 1"),
        ({"width": 2e6, "objects": []}, "width: 2000000.0 is greater than the maximum of 1000000"),
        ({"prior": {"x": 1, "y": 3, "radius": 1e308}}, "prior.radius: 1e+308 is greater than the maximum of 20000000"),
        ({"prior": {"x": 1, "y": 3, "radius": float("inf")}}, "prior.radius is inf, not a finite number"),
        ({"prior": {"x": 1, "y": float("nan"), "radius": 5}}, "prior.y is nan, not a finite number"),
        ({"prior": {"x": -2e8, "y": 3, "radius": 5}}, "prior.x: -200000000.0 is less than the minimum of -100000000"),
        ({"prior": {"lon": 200, "lat": 3, "radius": 5}}, "prior.lon: 200 is greater than the maximum of 180"),
        ({"prior": {"lon": 2, "lat": -91, "radius": 5}}, "prior.lat: -91 is less than the minimum of -90"),
        ({"altitude_m": 1e308}, "altitude_m: 1e+308 is greater than the maximum of 100000"),
        ({"altitude_m": 0}, "altitude_m: 0 is less than or equal to the minimum of 0"),
        ({"camera": {"fov_deg": 0}}, "camera.fov_deg: 0 is less than the minimum of 0.001"),
        ({"attitude": {"roll_deg": 95}}, "attitude.roll_deg: 95 is greater than the maximum of 89"),
        ({"attitude": {"pitch_deg": float("-inf")}}, "attitude.pitch_deg is -inf, not a finite number"),
        ({"objects": [{"label": "building", "x": 1, "y": float("inf")}]}, "objects[0].y is inf, not a finite number"),
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
        read_image_documents(tmp_path / "missing.jsonl")  # at the call, before any document is asked for
    with pytest.raises(MapdbIOError, match="is a directory"):
        read_image_documents(tmp_path)
    good = tmp_path / "ok.jsonl"
    good.write_text(json.dumps(_doc()) + "\n")
    documents = read_image_documents(good)
    assert not isinstance(documents, list) and iter(documents) is documents  # a stream, not a list
    (where, doc), = documents
    assert where.endswith("ok.jsonl line 1") and parse_image(doc).id == "frame-1"


def _read(data: bytes, tmp_path, **kwargs) -> list:
    path = tmp_path / "in.jsonl"
    path.write_bytes(data)
    return [(w.removeprefix(f"{path} "), d if isinstance(d, dict) else str(d).removeprefix(f"{path} "))
            for w, d in read_image_documents(path, **kwargs)]


def test_a_non_utf8_line_is_one_rejection_and_the_others_are_read(tmp_path) -> None:
    docs = _read(b'{"id": 1}\n{"id": "\xff\xfe"}\n\xff\xfe\x00garbage\n{"id": 4}\n', tmp_path)
    assert [w for w, _ in docs] == ["line 1", "line 2", "line 3", "line 4"]
    assert docs[0][1] == {"id": 1} and docs[3][1] == {"id": 4}
    assert docs[1][1] == "line 2: not UTF-8 (byte 0xff at column 9); expected JSON text"
    assert docs[2][1].startswith("line 3: not UTF-8 (byte 0xff at column 1)")


def test_lines_split_on_newline_only(tmp_path) -> None:
    # U+2028, U+0085 and a lone CR inside a line, a CRLF ending, a BOM: none of them makes a line.
    data = ('\ufeff{"id": "a\u2028b"}\r\n{"id": "c\u0085d"}\n{"id": 1}\r{"id": 2}\n'
            '{"id": "e\x0cf"}\n\x0c\n \t\r\n{"id": "g\u2029h"}').encode()
    docs = _read(data, tmp_path)
    assert [w for w, _ in docs] == ["line 1", "line 2", "line 3", "line 4", "line 5", "line 7"]
    assert docs[0][1] == {"id": "a\u2028b"} and docs[1][1] == {"id": "c\x85d"} and docs[5][1] == {"id": "g\u2029h"}
    assert docs[2][1].startswith("line 3: malformed JSON: Extra data")  # the lone CR did not split it
    assert docs[3][1].startswith("line 4: malformed JSON: Invalid control character")  # strict JSON strings
    assert docs[4][1].startswith("line 5: malformed JSON")  # a form feed alone is not a blank line
    # The in-memory reader is the same code.
    assert [w for w, _ in split_image_documents(data.decode("utf-8"), "t")] == [f"t {w}" for w, _ in docs]


@pytest.mark.parametrize(
    "line, reason",
    [
        (b"[1, 2]", "an image must be a JSON object, got list"),
        (b"[]", "an image must be a JSON object, got list"),
        (b"42", "an image must be a JSON object, got int"),
        (b'"frame"', "an image must be a JSON object, got str"),
        (b"null", "an image must be a JSON object, got NoneType"),
        (b"[" * 50_000 + b"]" * 50_000, "malformed JSON: nested too deeply"),
        (b'{"id": 1' + b"0" * 5000 + b"}", "malformed JSON: a number with too many digits"),
        (b"{oops", "malformed JSON: Expecting property name"),
    ],
)
def test_every_kind_of_bad_line_is_one_rejection_in_its_place(line, reason, tmp_path) -> None:
    docs = _read(b'{"id": "before"}\n' + line + b'\n{"id": "after"}\n', tmp_path)
    assert [w for w, _ in docs] == ["line 1", "line 2", "line 3"]
    assert docs[0][1] == {"id": "before"} and docs[2][1] == {"id": "after"}
    assert docs[1][1].startswith(f"line 2: {reason}")


def test_a_line_longer_than_the_limit_is_rejected_without_being_held(tmp_path) -> None:
    long_line = b'{"id": "' + b"x" * 5000 + b'"}'
    docs = _read(b'{"id": 1}\n' + long_line + b'\n{"id": 3}\n' + long_line, tmp_path, max_bytes=1000)
    assert [w for w, _ in docs] == ["line 1", "line 2", "line 3", "line 4"]
    assert docs[1][1].startswith("line 2: longer than 1000 bytes") and docs[3][1].startswith("line 4: longer")
    assert docs[2][1] == {"id": 3}
    exact = b'{"id": "' + b"y" * 990 + b'"}'  # 1000 bytes, with a CRLF: still accepted
    assert len(exact) == 1000 and _read(exact + b"\r\n", tmp_path, max_bytes=1000)[0][1] == {"id": "y" * 990}


def test_multi_line_documents_are_recognised_without_reading_json_lines_whole(tmp_path) -> None:
    pretty = json.dumps(_doc(id="p"), indent=2).encode()
    assert _read(pretty, tmp_path) == [(str(tmp_path / "in.jsonl"), _doc(id="p"))]
    array = json.dumps([_doc(id="x"), [1], _doc(id="y")], indent=1).encode()
    docs = _read(array, tmp_path)
    assert [w for w, _ in docs] == ["item 0", "item 1", "item 2"]
    assert [d["id"] if isinstance(d, dict) else d for _, d in docs] == [
        "x", "item 1: an image must be a JSON object, got list", "y"]
    # A first line that is malformed before its end is a bad JSON Lines line, not the start of a document.
    docs = _read(b'{oops\n{"id": 2}\n', tmp_path)
    assert [w for w, _ in docs] == ["line 1", "line 2"] and docs[1][1] == {"id": 2}
    # A first line cut short, and no document after all: read line by line, numbers intact.
    docs = _read(b'\n{"id": 1,\n{"id": 3}\n', tmp_path)
    assert [w for w, _ in docs] == ["line 2", "line 3"] and docs[1][1] == {"id": 3}
    # A multi-line document over the limit is read as lines, the first rejection saying why.
    docs = _read(pretty, tmp_path, max_bytes=40)
    assert len(docs) == len([ln for ln in pretty.splitlines() if ln.strip()])
    assert docs[0][1].startswith("line 1: malformed JSON") and "read whole only up to 40 bytes" in docs[0][1]


def test_ranges_are_stated_once_and_the_schema_agrees() -> None:
    from mapdb.detections import images

    props = image_schema()["properties"]
    prior = props["prior"]["properties"]
    assert props["width"]["maximum"] == props["height"]["maximum"] == images.MAX_IMAGE_SIDE_PX
    assert props["objects"]["maxItems"] == MAX_OBJECTS
    item = props["objects"]["items"]["properties"]
    assert item["x"]["maximum"] == item["y"]["maximum"] == images.MAX_IMAGE_SIDE_PX
    assert prior["radius"]["maximum"] == images.MAX_PRIOR_RADIUS_M
    assert prior["x"]["maximum"] == -prior["x"]["minimum"] == images.MAX_MAP_COORDINATE_M
    assert prior["y"]["maximum"] == -prior["y"]["minimum"] == images.MAX_MAP_COORDINATE_M
    assert props["altitude_m"]["maximum"] == images.MAX_ALTITUDE_M
    assert props["camera"]["properties"]["fov_deg"]["minimum"] == images.MIN_FOV_DEG
    for angle in ("roll_deg", "pitch_deg"):
        bounds = props["attitude"]["properties"][angle]
        assert bounds["maximum"] == -bounds["minimum"] == images.MAX_ATTITUDE_DEG


def test_a_prior_given_apart_is_checked_like_an_image_prior() -> None:
    from mapdb.detections.images import check_prior

    assert check_prior(1.0, -2.0, 20_000_000.0).radius == 20_000_000.0
    for values, message in [((1.0, 1.0, 1e308), "prior.radius: 1e+308 is greater than the maximum"),
                            ((1.0, 1.0, 0.0), "prior.radius: 0.0 is less than or equal to the minimum of 0"),
                            ((float("nan"), 1.0, 5.0), "prior.x is nan, not a finite number"),
                            ((1.0, 2e8, 5.0), "prior.y: 200000000.0 is greater than the maximum")]:
        with pytest.raises(ImageInputError, match="^--prior: ") as err:
            check_prior(*values, "--prior")
        assert message in str(err.value)


def test_the_fast_object_check_agrees_with_the_schema() -> None:
    from mapdb.detections.images import _plain_object_ok

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
        {"label": "b", "x": 1e6, "y": 1},
        {"label": "b", "x": 1, "y": 1e6 + 1},
        {"label": "b", "x": float("inf"), "y": 1},
        {"label": "b", "y": 1},
        {"x": 1, "y": 1},
        ["b", 1, 1],
        None,
        # A region's major axis: [0, 180) degrees, elongation in [1, 1e6].
        {"label": "b", "x": 1, "y": 1, "orientation_deg": 0, "elongation": 1},
        {"label": "b", "x": 1, "y": 1, "orientation_deg": 179.9, "elongation": 1e6},
        {"label": "b", "x": 1, "y": 1, "orientation_deg": 180},
        {"label": "b", "x": 1, "y": 1, "orientation_deg": -0.1},
        {"label": "b", "x": 1, "y": 1, "orientation_deg": "north"},
        {"label": "b", "x": 1, "y": 1, "elongation": 0.99},
        {"label": "b", "x": 1, "y": 1, "elongation": 1e6 + 1},
        {"label": "b", "x": 1, "y": 1, "elongation": True},
    ]
    for entry in entries:
        assert _plain_object_ok(entry) == validator.is_valid(entry), entry
