"""The quick schema check compiled once per schema (mapdb/detections/_quick_schema.py) against the interpreter it
replaced, kept here verbatim as the reference: the same verdict (True, False, or "cannot tell") on the image schema
and on random schemas and documents built from its keywords, odd values included (NaN, floats for integers, numpy
numbers, subclasses, unknown keywords)."""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from mapdb.detections import _quick_schema as quick
from mapdb.detections.images import image_schema

# ---------------------------------------------------------------- the reference (main at 1441f0c)

_JSON_TYPES = quick._JSON_TYPES
_DECODED = quick._DECODED
_ANNOTATIONS = quick._ANNOTATIONS
_UnsureError = quick._UnsureError


def _valid(schema: Any, value: Any) -> bool:
    if not isinstance(schema, Mapping) or type(value) not in _DECODED:
        raise _UnsureError
    for keyword, rule in schema.items():
        if keyword in _ANNOTATIONS:
            continue
        check = _KEYWORDS.get(keyword)
        if check is None:
            raise _UnsureError
        if not check(rule, value):
            return False
    return True


def _type(rule: Any, value: Any) -> bool:
    for name in [rule] if isinstance(rule, str) else rule:
        if name == "integer":
            if type(value) is float:
                raise _UnsureError  # 1.0 is an integer to draft 2020-12; jsonschema decides
            if type(value) is int:
                return True
        elif name not in _JSON_TYPES:
            raise _UnsureError
        elif type(value) in _JSON_TYPES[name]:
            return True
    return False


def _is_number(value: Any) -> bool:
    return type(value) in (int, float)


_KEYWORDS: dict[str, Callable[[Any, Any], bool]] = {
    "type": _type,
    "required": lambda rule, v: type(v) is not dict or all(key in v for key in rule),
    "properties": lambda rule, v: type(v) is not dict or all(_valid(sub, v[k]) for k, sub in rule.items() if k in v),
    "items": lambda rule, v: type(v) is not list or all(_valid(rule, item) for item in v),
    "minItems": lambda rule, v: type(v) is not list or len(v) >= rule,
    "maxItems": lambda rule, v: type(v) is not list or len(v) <= rule,
    "minLength": lambda rule, v: type(v) is not str or len(v) >= rule,
    "maxLength": lambda rule, v: type(v) is not str or len(v) <= rule,
    # Written as "not beyond" so that NaN passes, as it does in jsonschema.
    "minimum": lambda rule, v: not (_is_number(v) and v < rule),
    "maximum": lambda rule, v: not (_is_number(v) and v > rule),
    "exclusiveMinimum": lambda rule, v: not (_is_number(v) and v <= rule),
    "exclusiveMaximum": lambda rule, v: not (_is_number(v) and v >= rule),
    "allOf": lambda rule, v: all(_valid(sub, v) for sub in rule),
    "anyOf": lambda rule, v: any(_valid(sub, v) for sub in rule),
    "oneOf": lambda rule, v: sum(_valid(sub, v) for sub in rule) == 1,
    "not": lambda rule, v: not _valid(rule, v),
}


def ref_verdict(schema: Any, value: Any) -> str:
    try:
        return str(_valid(schema, value))
    except _UnsureError:
        return "unsure"


def verdict(schema: Any, value: Any) -> str:
    try:
        return str(quick._compile(schema)(value))  # uncached: the random schemas must not fill the cache
    except _UnsureError:
        return "unsure"


# ---------------------------------------------------------------- random schemas and values

class _Str(str):
    pass


_ODD = [math.nan, math.inf, -1.0, 0, 1, 2.0, 3, -7, True, None, "", "a", "abc", _Str("x"), np.float64(1.0), np.int64(2),
        [], [1], [1, 2, 3], {}, {"a": 1}, {"a": "b", "c": [1.5]}, (1, 2)]
_TYPES = ["object", "array", "string", "number", "integer", "boolean", "null", "weird"]


def _schema(rng: random.Random, depth: int = 0) -> Any:
    if rng.random() < 0.03:
        return rng.choice([True, [], "string"])  # not a schema object
    out: dict[str, Any] = {}
    for _ in range(rng.randint(0, 4)):
        keyword = rng.choice([*_KEYWORDS, "title", "$id", "pattern", "additionalProperties"])
        if keyword == "properties":
            keys = rng.sample("abc", rng.randint(0, 3)) if depth < 3 else []
            out[keyword] = {k: _schema(rng, depth + 1) for k in keys}
        elif keyword in ("items", "not"):
            out[keyword] = _schema(rng, depth + 1) if depth < 3 else {}
        elif keyword in ("allOf", "anyOf", "oneOf"):
            out[keyword] = [_schema(rng, depth + 1) for _ in range(rng.randint(0, 3))] if depth < 3 else []
        elif keyword == "type":
            out[keyword] = rng.choice(_TYPES) if rng.random() < 0.6 else rng.sample(_TYPES, rng.randint(1, 3))
        elif keyword == "required":
            out[keyword] = rng.sample("abc", rng.randint(0, 2))
        elif keyword in ("title", "$id", "pattern"):
            out[keyword] = "x"
        elif keyword == "additionalProperties":
            out[keyword] = False
        else:
            out[keyword] = rng.choice([0, 1, 2, 2.5, -1])
    return out


def _value(rng: random.Random, depth: int = 0) -> Any:
    roll = rng.random()
    if depth < 3 and roll < 0.2:
        return [_value(rng, depth + 1) for _ in range(rng.randint(0, 3))]
    if depth < 3 and roll < 0.4:
        return {k: _value(rng, depth + 1) for k in rng.sample("abcd", rng.randint(0, 3))}
    return rng.choice(_ODD)


def test_compiled_gives_the_interpreters_verdict_on_random_schemas():
    rng = random.Random(11)
    verdicts = set()
    for _ in range(3000):
        schema = _schema(rng)
        for _ in range(4):
            value = _value(rng)
            want = ref_verdict(schema, value)
            assert verdict(schema, value) == want, (schema, value)
            verdicts.add(want)
    assert verdicts == {"True", "False", "unsure"}  # every verdict reached


def test_compiled_gives_the_interpreters_verdict_on_the_image_schema():
    schema = image_schema()
    good = {"id": "a", "width": 640, "height": 480, "objects": [{"label": "building", "x": 1.0, "y": 2}],
            "prior": {"x": 1.0, "y": 2.0, "radius": 300.0}, "attitude": {"roll_deg": 0.5},
            "camera": {"fov_deg": 60}}
    rng = random.Random(3)
    docs = [good]
    for _ in range(400):
        doc = {**good}
        key = rng.choice([*good, "altitude_m", "extra"])
        if isinstance(good.get(key), dict) and rng.random() < 0.5:  # one field of a part made odd
            doc[key] = {**good[key], rng.choice(["x", "y", "radius", "lon", "roll_deg", "fov_deg"]): rng.choice(_ODD)}
        else:
            doc[key] = _value(rng)
        docs.append(doc)
    verdicts = [verdict(schema, d) for d in docs]
    assert verdicts == [ref_verdict(schema, d) for d in docs]
    assert [quick.surely_valid(schema, d) for d in docs] == [v == "True" for v in verdicts]
    assert verdicts[0] == "True" and {"True", "False"} <= set(verdicts)
    assert quick.compiled(schema) is quick.compiled(schema)  # compiled once


def test_a_numbers_schema_compiled_as_one_function_gives_the_interpreters_verdict():
    """``{"type": "number"}`` with range keywords after it (an image document's leaves) is one function, not a check a
    keyword: the same verdicts, NaN rules and values, strings against numbers and unknown types included."""
    rng = random.Random(5)
    values = [*_ODD, 1e6, 1e6 + 1, -0.0, -math.inf, 2.5, [1], {"a": 1}]
    for _ in range(1500):
        schema: dict[str, Any] = {"description": "a leaf", "type": "number"}
        for keyword in rng.sample(["minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"], rng.randint(0, 4)):
            schema[keyword] = rng.choice([0, 1, 2.5, -1, 1e6, math.nan, True])
        for value in values:
            assert verdict(schema, value) == ref_verdict(schema, value), (schema, value)
    assert quick._compile({"type": "number", "minimum": 0}).__qualname__ == "_number.<locals>.check"
