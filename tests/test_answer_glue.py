"""An answer's work outside the matcher made cheaper (issue 30) without changing a byte: each quicker path against
the code it replaced, kept here verbatim as the reference (main at 9b40c11), on random and edge inputs: the answer's
JSON (non-finite numbers, numpy numbers, tuples, subclasses), a level image's georeference, image documents read in
the loop that checks them, the label codes, the tiles a prior's disc reaches, and the heading's angle."""

from __future__ import annotations

import dataclasses
import json
import math
import random
from typing import Any

import numpy as np
import pytest

import mapdb.localize.localizer as localizer_module
from mapdb.answers import Answer, Candidate
from mapdb.camera import image_plane
from mapdb.detections.images import ImageObjects, parse_image
from mapdb.errors import ImageInputError
from mapdb.localize.georef import georeference
from mapdb.localize.image_points import known_objects
from mapdb.localize.localizer import TILE_SIZE_M, Localizer
from mapdb.localize.records import RejectionError
from mapdb.mapfile.queries import MemoryMap
from mapdb.objects import Objects
from mapdb.outputs import json_safe

# ---------------------------------------------------------------- the references (main at 9b40c11)

_OPTIONAL = ("rejected_by", "score_without_areas", "hypotheses", "path", "skipped_labels", "notes", "error_std")
_GEOREF = ("width", "height", "transform", "transform_error_m", "footprint", "footprint_lonlat")
_POSE = ("x", "y", "lon", "lat", "crs", "inliers", "heading_deg", "scale_m_per_px", "sigma_m", "score",
         "expected_false_alarms")


def ref_candidate_json(c: Candidate) -> dict[str, Any]:
    return json_safe(dataclasses.asdict(c))


def ref_answer_json(self: Answer) -> dict[str, Any]:
    record: dict[str, Any] = {"id": self.id, "status": self.status}
    if self.ok:
        record.update((name, getattr(self, name)) for name in _POSE)
        if self.altitude_m is not None:
            record["altitude_m"] = self.altitude_m
        record["levelled"] = bool(self.levelled)
        record.update((name, getattr(self, name)) for name in _GEOREF if getattr(self, name) is not None)
    else:
        record["reason"] = self.reason
    record["candidates"] = [ref_candidate_json(c) for c in self.candidates]
    record.update((name, getattr(self, name)) for name in _OPTIONAL if getattr(self, name) is not None)
    record["time_ms"] = self.time_ms
    return json_safe(record)


def ref_level_footprint(a: complex, b: complex, width: float, height: float) -> np.ndarray | None:
    u = np.asarray([0.0, width, width, 0.0], dtype=np.float64).reshape(-1)
    v = np.asarray([0.0, 0.0, height, height], dtype=np.float64).reshape(-1)
    ground = a * image_plane(u, v, width, height) + b
    footprint = np.column_stack([ground.real, ground.imag])
    return footprint if np.all(np.isfinite(footprint)) else None


def ref_known_codes(im: ImageObjects, map_labels: tuple[str, ...]) -> np.ndarray:
    known = {name: code for code, name in enumerate(map_labels)}
    is_known = np.fromiter((name in known for name in im.names), dtype=bool, count=len(im))
    return np.fromiter((known[name] for name in im.names[is_known]), dtype=np.int64, count=int(is_known.sum()))


def ref_reached_tiles(x: float, y: float, k: int, anchor_reach: float) -> list[tuple[int, int]]:
    t = TILE_SIZE_M
    cx, cy = math.floor(x / t), math.floor(y / t)
    cells = [(ix, iy) for ix in range(cx - k, cx + k + 1) for iy in range(cy - k, cy + k + 1)]
    return [(ix, iy) for ix, iy in cells
            if max(ix * t - x, 0.0, x - (ix + 1) * t) ** 2 + max(iy * t - y, 0.0, y - (iy + 1) * t) ** 2
            <= anchor_reach**2]


# ---------------------------------------------------------------- random inputs

class _Float(float):
    pass


_ODD = [float("nan"), float("inf"), -float("inf"), -0.0, 0.0, 1e308, 5e-324, np.float64(2.5), np.float32(0.1),
        np.int64(3), np.float64("nan"), True, False, None, "text", 7, _Float(1.5), (1.0, float("nan"))]


def _number(rng: random.Random) -> Any:
    return rng.choice(_ODD) if rng.random() < 0.3 else rng.uniform(-1e7, 1e7)


def _answer(rng: random.Random) -> Answer:
    candidates = [Candidate(_number(rng), _number(rng), rng.randint(0, 30), _number(rng), _number(rng))
                  for _ in range(rng.randint(0, 3))]
    fields: dict[str, Any] = {name: _number(rng) for name in ("x", "y", "lon", "lat", "heading_deg", "scale_m_per_px",
                                                               "sigma_m", "score", "expected_false_alarms",
                                                               "altitude_m", "transform_error_m", "error_std",
                                                               "score_without_areas", "time_ms")
                              if rng.random() < 0.8}
    if rng.random() < 0.7:
        fields["footprint"] = [[_number(rng), _number(rng)] for _ in range(4)]
        fields["transform"] = [_number(rng) for _ in range(6)]
        fields["footprint_lonlat"] = [(_number(rng), _number(rng)) for _ in range(4)]
    if rng.random() < 0.3:
        fields.update(skipped_labels={"tree": np.int64(2)}, notes=["a note"], hypotheses=rng.randint(0, 99),
                      path="quads", rejected_by="areas")
    status = rng.choice(["ok", "rejected"])
    return Answer(id=rng.choice(["img", 3, None]), status=status, reason=None if status == "ok" else "no match",
                  crs=rng.choice(["EPSG:32631", None]), inliers=rng.randint(3, 20), levelled=rng.random() < 0.5,
                  width=640, height=480, candidates=candidates, **fields)


# ---------------------------------------------------------------- tests

def test_answer_json_is_the_references_byte_for_byte() -> None:
    rng = random.Random(7)
    for _ in range(3000):
        answer = _answer(rng)
        got, want = answer.to_json(), ref_answer_json(answer)
        assert json.dumps(got) == json.dumps(want), answer
        assert [type(v) for v in got.values()] == [type(v) for v in want.values()]
        for c in answer.candidates:
            assert json.dumps(c.to_json()) == json.dumps(ref_candidate_json(c))


def test_a_level_images_georeference_is_the_references() -> None:
    rng = random.Random(3)
    odd = [float("nan"), float("inf"), 1e300, -0.0]
    for i in range(3000):
        a = complex(rng.gauss(0, 1) * 10 ** rng.uniform(-3, 1), rng.gauss(0, 1) * 10 ** rng.uniform(-3, 1))
        b = complex(rng.uniform(-1e7, 1e7), rng.uniform(-1e7, 1e7))
        if i % 50 == 0:
            a, b = complex(rng.choice(odd), a.imag), complex(b.real, rng.choice(odd))
        width, height = rng.choice([(640, 480), (640.0, 480.0), (1, 1), (1e6, 3.5), (4000, 3000)])
        with np.errstate(all="ignore"):  # the odd values overflow, as they did
            want = ref_level_footprint(a, b, width, height)
            got = georeference(a, b, width, height)
        if want is None:
            assert got is None
            continue
        assert got is not None and got.footprint.shape == (4, 2) and got.error_m == 0.0
        assert got.footprint.tolist() == want.tolist()
        with np.errstate(all="ignore"):
            assert np.round(got.footprint, 3).tolist() == np.round(want, 3).tolist()


def _document(rng: random.Random) -> dict[str, Any]:
    objects = []
    for _ in range(rng.randint(0, 12)):
        obj: dict[str, Any] = {"label": rng.choice(["building", "park", "x"]),
                               "x": rng.choice([rng.uniform(0, 640), rng.randint(0, 640)]),
                               "y": rng.choice([rng.uniform(0, 480), rng.randint(0, 480)])}
        roll = rng.random()
        if roll < 0.1:
            obj["area_px"] = rng.uniform(0, 1e4)
        elif roll < 0.15:
            obj["border"] = True
        elif roll < 0.2:
            obj["x"] = rng.choice([700.0, float("nan"), -1, "1", True])  # outside, not finite, not a number
        elif roll < 0.25:
            obj["score"] = 0.9
        objects.append(obj)
    return {"id": "d", "width": 640, "height": 480, "objects": objects, "camera": {"fov_deg": 60}}


def test_image_documents_read_as_before() -> None:
    """The arrays a document gives, or its error's message, as the separate reads of positions, names and region
    fields gave them (those reads, still the path of a document whose objects are not plain, are the reference)."""
    from mapdb.detections import images

    rng = random.Random(5)
    for _ in range(1500):
        doc = _document(rng)
        try:
            im = parse_image(doc, "s")
        except ImageInputError as exc:
            with pytest.raises(ImageInputError) as ref:
                images._check_schema(doc, "s")
                images._positions(doc["objects"], 640.0, 480.0, "s")
                images._region_fields(doc["objects"], "s")
            assert str(exc) == str(ref.value)
            continue
        x, y = images._positions(doc["objects"], 640.0, 480.0, "s")
        area, border, bbox = images._region_fields(doc["objects"], "s")
        assert im.x.dtype == im.y.dtype == np.float64 and im.names.dtype == object
        assert im.x.tolist() == x.tolist() and im.y.tolist() == y.tolist()
        assert im.names.tolist() == [o["label"] for o in doc["objects"]]
        for got, want in ((im.area_px, area), (im.border, border), (im.bbox, bbox)):
            assert (got is None) == (want is None) and (got is None or np.array_equal(got, want, equal_nan=True))


def test_label_codes_are_the_references() -> None:
    rng = random.Random(9)
    labels = ("building", "park", "water", "forest")
    for _ in range(500):
        names = [rng.choice([*labels, "tree", "car"]) for _ in range(rng.randint(3, 9))]
        im = parse_image({"width": 10, "height": 10, "objects": [{"label": n, "x": 1, "y": 1} for n in names]})
        try:
            _, codes, skipped = known_objects(im, labels)
        except RejectionError:
            assert sum(n in labels for n in names) < 3
            continue
        assert codes.dtype == np.int64 and codes.tolist() == ref_known_codes(im, labels).tolist()
        assert bool(skipped) == any(n not in labels for n in names)


def test_a_priors_tiles_are_the_references(monkeypatch: pytest.MonkeyPatch) -> None:
    """With no block of tiles cached, a prior's disc is looked up in the tiles the reference reaches, in its order
    (on any map: a map this small would otherwise answer priors from one index of its whole map)."""
    monkeypatch.setattr(localizer_module, "SMALL_MAP_OBJECTS", 0)
    objects = Objects.from_names([0.0, 50.0, 2500.0], [0.0, 60.0, 2500.0], ["park"] * 3, crs="EPSG:32631")
    rng = random.Random(2)
    for _ in range(200):
        localizer = Localizer(MemoryMap(objects))
        x, y, r = rng.uniform(-3000, 6000), rng.uniform(-3000, 6000), rng.choice([50.0, 300.0, 900.0])
        margin = rng.choice([0.0, 300.0, 1200.0])
        _, reached = localizer.fast_indexes((x, y, r), margin)
        reach = 1.1 * r + margin
        k = max(1, math.ceil(reach / TILE_SIZE_M))
        if (2 * k + 1) ** 2 > 64:
            continue
        assert [quads.index for quads in reached] == [localizer._tile(ix, iy)
                                                      for ix, iy in ref_reached_tiles(x, y, k, reach)]


def test_the_headings_angle_is_np_angles() -> None:
    rng = random.Random(4)
    values = [0j, -0j, complex(-0.0, 0.0), complex(-1.0, -0.0), complex(math.inf, 1.0), complex(math.nan, 1.0)]
    values += [complex(rng.gauss(0, 1) * 10 ** rng.uniform(-6, 3), rng.gauss(0, 1) * 10 ** rng.uniform(-6, 3))
               for _ in range(20000)]
    for a in values:
        want, got = np.angle(a), np.arctan2(a.imag, a.real)
        assert type(got) is type(want) and (got == want or (math.isnan(got) and math.isnan(want)))
        assert math.copysign(1.0, got) == math.copysign(1.0, want)
