"""``mapdb query`` as a stream: every line on its own, answers as lines arrive, outputs that never destroy inputs.

The reliability guarantees of the query path, each asserted on real files:

* a batch mixing valid images with bad lines of every kind gets exactly one answer per non-blank line,
  in order, each carrying its line's ``id``, and every valid image is answered;
* ``mapdb query MAP -`` answers a line before the next one is written (a subprocess on a pipe);
* ``-o`` may not be the map or the images file (also through a symlink, a hard link or stdin), and a
  damaged map leaves an existing answers file as it was;
* every number an image may carry, at the corners of its accepted range, gives an answer in strict JSON.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys

import pytest
from clichecks import answered_one_by_one
from click.testing import CliRunner
from mapdb_cli.main import cli

from mapdb.detections.images import MAX_OBJECTS, split_image_documents
from mapdb.localize.batch import localize_documents
from mapdb.mapfile.reader import open_map

# A generous bound for one answer (the first one builds the map's index); a reader that waited for the
# end of its input would never answer at all, so this only has to be finite.
ANSWER_TIMEOUT_S = 60.0




def _line(doc, **changes) -> bytes:
    return json.dumps({**doc, **changes}, ensure_ascii=False).encode("utf-8")


def _run(*args: str, input: bytes | None = None):
    return CliRunner().invoke(cli, ["query", *args], input=input, catch_exceptions=False)


def _batch(images) -> tuple[list[bytes], list[tuple]]:
    """Lines of a batch, and per non-blank line what its answer must be: (id, status, reason part)."""
    a, b, c = images
    raw_nan = _line(a, id="raw-nan", altitude_m=12345.5).replace(b"12345.5", b"NaN")
    nested = b"[" * 100_000 + b"]" * 100_000
    rows = [
        (_line(a), (a["id"], "ok", None)),
        (_line(a, id="huge-radius", prior={"x": 1.0, "y": 1.0, "radius": 1e308}),
         ("huge-radius", "rejected", "prior.radius: 1e+308 is greater than the maximum of 20000000")),
        (raw_nan, ("raw-nan", "rejected", "altitude_m is nan, not a finite number")),
        (_line(b, id="not-utf8").replace(b"not-utf8", b"not-\xff\xfeutf8"), (None, "rejected", "line 4: not UTF-8")),
        (_line(b, id="para\u2028graph"), ("para\u2028graph", "ok", None)),
        (_line(c, id="next\u0085line"), ("next\u0085line", "ok", None)),
        (_line(c, id="form-feed").replace(b"form-feed", b"form\x0cfeed"),
         (None, "rejected", "line 7: malformed JSON: Invalid control character")),
        (b"[" + _line(a) + b"]", (None, "rejected", "line 8: an image must be a JSON object, got list")),
        (b"12345", (None, "rejected", "line 9: an image must be a JSON object, got int")),
        (nested, (None, "rejected", "line 10: malformed JSON: nested too deeply")),
        (b"{}", (None, "rejected", "line 11: document: 'width' is a required property")),
        (b"", None),
        (b"  \t", None),
        (_line(a, id="high", altitude_m=1e308), ("high", "rejected", "altitude_m: 1e+308 is greater than the maximum")),
        (_line(a, id="wide-fov", camera={"fov_deg": 180}), ("wide-fov", "rejected", "camera.fov_deg: 180 is greater")),
        (_line(a, id="rolled", attitude={"roll_deg": 95.0}),
         ("rolled", "rejected", "attitude.roll_deg: 95.0 is greater")),
        (_line(a, id="huge-image", width=2e6), ("huge-image", "rejected", "width: 2000000.0 is greater than")),
        (_line(a, id="far-prior", prior={"x": 1e9, "y": 0.0, "radius": 5.0}),
         ("far-prior", "rejected", "prior.x: 1000000000.0 is greater than the maximum")),
        (_line(a, id="bad-lon", prior={"lon": 200.0, "lat": 0.0, "radius": 5.0}),
         ("bad-lon", "rejected", "prior.lon: 200.0 is greater than the maximum of 180")),
        (_line(a, id="inf-prior").replace(b'"id": "inf-prior"', b'"id": "inf-prior", "prior": '
                                           b'{"x": Infinity, "y": 0, "radius": 5}'),
         ("inf-prior", "rejected", "prior.x is inf, not a finite number")),
        (_line(a, id="outside", objects=[{"label": "building", "x": 700.0, "y": 5.0}] * 4),
         ("outside", "rejected", "objects[0] at (700, 5) is outside the 640x480 image")),
        (_line(a, id="crowded", objects=[{"label": "building", "x": 1, "y": 1}] * (MAX_OBJECTS + 1)),
         ("crowded", "rejected", f"at most {MAX_OBJECTS} are accepted")),
        (b'{"id": 1' + b"0" * 5000 + b"}",
         (None, "rejected", "line 23: malformed JSON: a number with too many digits")),
        (_line(b) + b"\r", (b["id"], "ok", None)),  # a CRLF line ending
        (_line(c, id="last, no newline"), ("last, no newline", "ok", None)),
    ]
    return [line for line, _ in rows], [expect for _, expect in rows if expect is not None]


def test_a_batch_of_bad_lines_of_every_kind_keeps_count_order_and_ids(paper_setup, tmp_path) -> None:
    map_path, images = paper_setup
    lines, expected = _batch(images)
    data = b"\n".join(lines)
    assert b"\xe2\x80\xa8" in data and b"\xc2\x85" in data and b"\x0c" in data and b"\xff" in data
    images_path = tmp_path / "batch.jsonl"
    images_path.write_bytes(data)
    out_path = tmp_path / "answers.jsonl"
    result = _run(str(map_path), str(images_path), "-o", str(out_path))
    assert result.exit_code == 0, result.output
    text = out_path.read_text(encoding="ascii")  # strict JSON, non-ASCII escaped: no U+2028 to split on
    answers = [json.loads(line, parse_constant=pytest.fail) for line in text.split("\n")[:-1]]
    assert len(answers) == len([ln for ln in lines if ln.strip()])
    assert [(a["id"], a["status"]) for a in answers] == [(i, s) for i, s, _ in expected]
    for answer, (_, status, reason) in zip(answers, expected, strict=True):
        if status == "rejected":
            assert reason in answer["reason"], answer
    # Every valid line is answered, at its image's true position.
    truth_by_objects = {json.dumps(im["objects"]): im["truth"] for im in images}
    valid = [json.loads(ln) for ln, (_, s, _) in zip([ln for ln in lines if ln.strip()], expected, strict=True)
             if s == "ok"]
    oks = [a for a in answers if a["status"] == "ok"]
    assert len(oks) == len(valid) == 5
    for answer, doc in zip(oks, valid, strict=True):
        truth = truth_by_objects[json.dumps(doc["objects"])]
        assert math.hypot(answer["x"] - truth["x"], answer["y"] - truth["y"]) < 1.0, answer
    # The same batch on stdin gives the same answers, on stdout.
    piped = _run(str(map_path), "-", input=data)
    assert piped.exit_code == 0
    def same(answer: dict) -> str:
        return json.dumps({k: v for k, v in answer.items() if k != "time_ms"}).replace(str(images_path), "<stdin>")

    assert [same(json.loads(ln)) for ln in piped.output.splitlines()] == [same(a) for a in answers]


def test_query_on_a_pipe_answers_each_line_before_the_next_is_sent(paper_setup) -> None:
    map_path, images = paper_setup
    sent = [_line(images[0]), b"[1, 2]", _line(images[1]), b"{oops", _line(images[2])]
    for i, answer in answered_one_by_one(["query", str(map_path), "-"], sent, ANSWER_TIMEOUT_S):
        if i % 2 == 0:
            assert answer["status"] == "ok" and answer["id"] == images[i // 2]["id"], answer
        else:
            assert answer["status"] == "rejected" and f"<stdin> line {i + 1}: " in answer["reason"], answer


def test_the_answers_file_may_not_be_an_input(paper_setup, tmp_path) -> None:
    map_path, images = paper_setup
    map_copy = tmp_path / "map.mapdb"
    map_copy.write_bytes(map_path.read_bytes())
    images_path = tmp_path / "in.jsonl"
    images_path.write_bytes(_line(images[0]) + b"\n")
    (tmp_path / "map-link").symlink_to(map_copy)
    os.link(images_path, tmp_path / "in-hardlink.jsonl")
    before = {p: p.read_bytes() for p in (map_copy, images_path)}
    for out, clash in [(map_copy, map_copy), (tmp_path / "map-link", map_copy), (images_path, images_path),
                       (tmp_path / "in-hardlink.jsonl", images_path), (tmp_path / "." / "map.mapdb", map_copy)]:
        result = _run(str(map_copy), str(images_path), "-o", str(out))
        assert result.exit_code == 1, (out, result.output)
        assert result.output == f"mapdb: error: {out}: is the same file as input {clash}; choose another output path\n"
        assert {p: p.read_bytes() for p in before} == before
    # Standard input redirected from the file the answers would replace.
    with open(images_path, "rb") as stdin:
        proc = subprocess.run([sys.executable, "-m", "mapdb_cli", "query", str(map_copy), "-", "-o", str(images_path)],
                              stdin=stdin, capture_output=True, timeout=120)
    assert proc.returncode == 1 and b"is the same file as input /dev/stdin" in proc.stderr, proc.stderr
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in-hardlink.jsonl", "in.jsonl", "map-link", "map.mapdb"]


def test_a_damaged_map_leaves_the_previous_answers_file_untouched(paper_setup, tmp_path) -> None:
    map_path, images = paper_setup
    damaged = tmp_path / "damaged.mapdb"
    data = bytearray(map_path.read_bytes())
    data[-1] ^= 0xFF  # the last page: the header opens, the page fails its checksum when read
    damaged.write_bytes(bytes(data))
    images_path = tmp_path / "in.jsonl"
    images_path.write_bytes(b"\n".join(_line(im) for im in images) + b"\n")
    out_path = tmp_path / "answers.jsonl"
    out_path.write_text("previous answers\n")
    for bad_map in (damaged, images_path):  # a damaged map, and a file that is no map at all
        result = _run(str(bad_map), str(images_path), "-o", str(out_path), "--overwrite")
        assert result.exit_code == 1 and result.output.startswith("mapdb: error: "), result.output
        assert len(result.output.splitlines()) == 1 and "Traceback" not in result.output
        assert out_path.read_text() == "previous answers\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["answers.jsonl", "damaged.mapdb", "in.jsonl"]
    # No answers file at all is created by a failed run, and a good run replaces the old one whole.
    fresh = tmp_path / "fresh.jsonl"
    assert _run(str(damaged), str(images_path), "-o", str(fresh)).exit_code == 1 and not fresh.exists()
    assert _run(str(map_path), str(images_path), "-o", str(out_path), "--overwrite").exit_code == 0
    assert [json.loads(line)["status"] for line in out_path.read_text().splitlines()] == ["ok"] * 3


@pytest.mark.parametrize(
    "value, message",
    [
        ("1,1,1e308", "prior.radius: 1e+308 is greater than the maximum of 20000000"),
        ("nan,1,5", "prior.x is nan, not a finite number"),
        ("1,inf,5", "prior.y is inf, not a finite number"),
        ("1e9,1,5", "prior.x: 1000000000.0 is greater than the maximum"),
        ("1,1,0", "prior.radius: 0.0 is less than or equal to the minimum of 0"),
        ("1,2", "is not three comma-separated numbers X,Y,R"),
    ],
)
def test_prior_option_has_the_image_prior_ranges(paper_setup, tmp_path, value, message) -> None:
    map_path, images = paper_setup
    result = _run(str(map_path), "-", "--prior", value, input=_line(images[0]) + b"\n")
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output


def test_numbers_at_the_corners_of_their_ranges_give_strict_json_answers(paper_setup) -> None:
    map_path, images = paper_setup
    base = images[0]
    lines = []
    for side, fov, altitude, radius, attitude in itertools.product(
        (1.0, 1e6), (0.001, 179.99999999999997), (5e-324, 1e5), (None, 5e-324, 2e7), (None, 89.0)
    ):
        # The image's objects scaled into the image's size; a prior at the far corner of the map CRS.
        objects = [{"label": o["label"], "x": o["x"] / 640 * side, "y": o["y"] / 480 * side * 0.75}
                   for o in base["objects"]]
        doc = {"id": len(lines), "width": side, "height": side * 0.75, "objects": objects,
               "camera": {"fov_deg": fov}, "altitude_m": altitude}
        if radius is not None:
            doc["prior"] = {"x": 1e8, "y": -1e8, "radius": radius}
        if attitude is not None:
            doc["attitude"] = {"roll_deg": attitude, "pitch_deg": -attitude}
        lines.append(json.dumps(doc))
    with open_map(map_path) as m:
        answers = [a.to_json() for a in localize_documents(split_image_documents("\n".join(lines)), m)]
    assert [a["id"] for a in answers] == list(range(len(lines)))
    for answer in answers:
        json.dumps(answer, allow_nan=False)  # raises on NaN or infinity anywhere
        assert answer["status"] in ("ok", "rejected")
