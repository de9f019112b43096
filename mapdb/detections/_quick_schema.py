"""A quick "certainly valid" for a JSON document against a JSON Schema built from a few plain keywords.

jsonschema stays the judge of image documents (and words their errors), but importing it costs 0.04-0.07 s
of a one-image ``mapdb query`` and checking a document with it ~150 us of a few-millisecond match.  Most
documents are valid, so :func:`surely_valid` answers first: True only when the document certainly satisfies
the schema under draft 2020-12; False when it does not or when it cannot tell - a keyword it does not know
(``$ref``, ``pattern``, ``additionalProperties``, ...), a Python value that is not one of the JSON decoder's
own types (a numpy number, a subclass of str), a float where an integer is wanted - and then the caller asks
jsonschema.  So a True is never wrong, and a document it cannot judge costs what it cost before.

Keywords judged: ``type``, ``required``, ``properties``, ``items`` (a schema), ``minItems``, ``maxItems``,
``minLength``, ``maxLength``, ``minimum``, ``maximum``, ``exclusiveMinimum``, ``exclusiveMaximum``,
``allOf``, ``anyOf``, ``oneOf``, ``not``; ``$schema``, ``$id``, ``title`` and ``description`` are read as
the annotations they are.  As in jsonschema, a keyword applies only to the values of its kind (``minimum``
to numbers, ``required`` to objects), and NaN passes the range keywords (every comparison with it is false).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["surely_valid"]

# The JSON decoder's types, exactly (bool is not a number; a subclass is judged by jsonschema).
_JSON_TYPES: dict[str, tuple[type, ...]] = {
    "object": (dict,),
    "array": (list,),
    "string": (str,),
    "number": (int, float),
    "boolean": (bool,),
    "null": (type(None),),
}
_DECODED = frozenset(t for types in _JSON_TYPES.values() for t in types)
_ANNOTATIONS = frozenset({"$schema", "$id", "title", "description"})


class _UnsureError(Exception):
    """This checker cannot tell; jsonschema will."""


def surely_valid(schema: Mapping[str, Any], document: Any) -> bool:
    """True when ``document`` certainly satisfies ``schema``; False when it does not or when this cannot tell.

    Examples
    --------
    >>> schema = {"type": "object", "required": ["r"], "properties": {"r": {"type": "number", "minimum": 0}}}
    >>> surely_valid(schema, {"r": 2.5, "other": "ignored"}), surely_valid(schema, {"r": -1})
    (True, False)
    >>> surely_valid({"type": "string", "pattern": "^a"}, "abc")  # a keyword it does not know
    False
    """
    try:
        return _valid(schema, document)
    except _UnsureError:
        return False


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
