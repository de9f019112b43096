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

import operator
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

    The schema is compiled once (:func:`compiled`) and must not change afterwards: the image schema is read once and
    shared.

    Examples
    --------
    >>> schema = {"type": "object", "required": ["r"], "properties": {"r": {"type": "number", "minimum": 0}}}
    >>> surely_valid(schema, {"r": 2.5, "other": "ignored"}), surely_valid(schema, {"r": -1})
    (True, False)
    >>> surely_valid({"type": "string", "pattern": "^a"}, "abc")  # a keyword it does not know
    False
    """
    try:
        return compiled(schema)(document)
    except _UnsureError:
        return False


# Compiled schemas by id, each beside the schema it was compiled from (held, so that its id is not reused).
_COMPILED: dict[int, tuple[Any, Callable[[Any], bool]]] = {}


def compiled(schema: Any) -> Callable[[Any], bool]:
    """``schema`` as one function of a value: the verdict of walking the schema keyword by keyword (False at the
    first failing one, :class:`_UnsureError` at the first it does not know or at a value of a type the JSON decoder
    does not make), compiled once instead of walking the schema's dictionaries for every document.

    Examples
    --------
    >>> check = compiled({"type": "array", "items": {"type": "integer"}, "maxItems": 2})
    >>> check([1, 2]), check([1, 2, 3]), check([True])
    (True, False, False)
    """
    found = _COMPILED.get(id(schema))
    if found is not None and found[0] is schema:
        return found[1]
    check = _compile(schema)
    if len(_COMPILED) < 64:  # a few schemas in a process; others are compiled at each call
        _COMPILED[id(schema)] = (schema, check)
    return check


def _compile(schema: Any) -> Callable[[Any], bool]:
    """The function :func:`compiled` returns (uncached)."""
    if not isinstance(schema, Mapping):
        return _unsure
    rules = [(keyword, rule) for keyword, rule in schema.items() if keyword not in _ANNOTATIONS]
    if rules and rules[0] == ("type", "number") and all(keyword in _RANGES for keyword, _ in rules[1:]):
        return _number(tuple((_RANGES[keyword], rule) for keyword, rule in rules[1:]))
    checks: list[Callable[[Any], bool]] = []
    for keyword, rule in schema.items():
        if keyword in _ANNOTATIONS:
            continue
        build = _COMPILERS.get(keyword)
        if build is None:
            checks.append(_unsure)  # raises when reached, after the keywords before it have passed
            break
        checks.append(build(rule))
    return _all_of(checks)


def _all_of(checks: list[Callable[[Any], bool]]) -> Callable[[Any], bool]:
    """A value's check by ``checks`` in order: False at the first failing one; a value of a type the JSON decoder
    does not make is judged by jsonschema."""
    decoded = _DECODED

    def check(value: Any) -> bool:
        if type(value) not in decoded:
            raise _UnsureError
        for one in checks:
            if not one(value):
                return False
        return True

    return check


# The range keywords, each as the comparison that fails a number (NaN fails none, as in jsonschema).
_RANGES = {"minimum": operator.lt, "maximum": operator.gt, "exclusiveMinimum": operator.le,
           "exclusiveMaximum": operator.ge}


def _number(ranges: tuple[tuple[Callable[[Any, Any], bool], Any], ...]) -> Callable[[Any], bool]:
    """A number's schema, ``{"type": "number"}`` and range keywords after it (most of an image document's leaves), as
    one function: the verdict of :func:`_all_of` over their checks, with no call a keyword."""
    decoded = _DECODED

    def check(value: Any) -> bool:
        if type(value) not in decoded:
            raise _UnsureError
        if type(value) not in _NUMBER:
            return False
        for fails, rule in ranges:
            if fails(value, rule):
                return False
        return True

    return check


def _unsure(value: Any) -> bool:
    raise _UnsureError


def _compile_type(rule: Any) -> Callable[[Any], bool]:
    if isinstance(rule, str) and rule in _JSON_TYPES:  # one plain type, the usual rule: a set membership
        types = _JSON_TYPES[rule]
        return lambda value: type(value) in types
    if rule == "integer":
        return _integer
    return lambda value: _type(rule, value)


def _integer(value: Any) -> bool:
    if type(value) is float:
        raise _UnsureError  # 1.0 is an integer to draft 2020-12; jsonschema decides
    return type(value) is int


def _compile_properties(rule: Any) -> Callable[[Any], bool]:
    subs = [(key, _compile(sub)) for key, sub in rule.items()]

    def check(v: Any) -> bool:
        if type(v) is dict:
            for key, sub in subs:
                if key in v and not sub(v[key]):
                    return False
        return True

    return check


# The keywords holding a list of subschemas (or one for items) are loops, not generators: no generator's frame
# resumed for each subschema a document meets.

def _compile_items(rule: Any) -> Callable[[Any], bool]:
    check = _compile(rule)

    def items(v: Any) -> bool:
        if type(v) is list:
            for item in v:
                if not check(item):
                    return False
        return True

    return items


def _compile_all(rule: Any) -> Callable[[Any], bool]:
    subs = [_compile(sub) for sub in rule]

    def all_of(v: Any) -> bool:
        for check in subs:
            if not check(v):
                return False
        return True

    return all_of


def _compile_any(rule: Any) -> Callable[[Any], bool]:
    subs = [_compile(sub) for sub in rule]

    def any_of(v: Any) -> bool:
        for check in subs:
            if check(v):
                return True
        return False

    return any_of


def _compile_one(rule: Any) -> Callable[[Any], bool]:
    subs = [_compile(sub) for sub in rule]

    def one_of(v: Any) -> bool:
        passed = 0
        for check in subs:  # every one, in order, as jsonschema counts them
            passed += check(v)
        return passed == 1

    return one_of


def _compile_not(rule: Any) -> Callable[[Any], bool]:
    check = _compile(rule)
    return lambda v: not check(v)


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


_NUMBER = (int, float)


# The keywords whose rule is a plain value: each compiled by closing over its rule, its test made inline in the closure
# (one call a keyword when a document is checked).
_KEYWORDS: dict[str, Callable[[Any], Callable[[Any], bool]]] = {
    "minItems": lambda rule: lambda v: type(v) is not list or len(v) >= rule,
    "maxItems": lambda rule: lambda v: type(v) is not list or len(v) <= rule,
    "minLength": lambda rule: lambda v: type(v) is not str or len(v) >= rule,
    "maxLength": lambda rule: lambda v: type(v) is not str or len(v) <= rule,
    # Written as "not beyond" so that NaN passes, as it does in jsonschema.
    "minimum": lambda rule: lambda v: not (type(v) in _NUMBER and v < rule),
    "maximum": lambda rule: lambda v: not (type(v) in _NUMBER and v > rule),
    "exclusiveMinimum": lambda rule: lambda v: not (type(v) in _NUMBER and v <= rule),
    "exclusiveMaximum": lambda rule: lambda v: not (type(v) in _NUMBER and v >= rule),
}


def _compile_required(rule: Any) -> Callable[[Any], bool]:
    if type(rule) is list and all(type(key) is str for key in rule):  # the usual rule: one set comparison
        keys = frozenset(rule)
        return lambda v: type(v) is not dict or v.keys() >= keys
    return lambda v: type(v) is not dict or all(key in v for key in rule)


# How each keyword compiles: the ones whose rule holds subschemas (or a type) compile it once; the others close over
# their rule.
_COMPILERS: dict[str, Callable[[Any], Callable[[Any], bool]]] = {
    **_KEYWORDS,
    "required": _compile_required,
    "type": _compile_type,
    "properties": _compile_properties,
    "items": _compile_items,
    "allOf": _compile_all,
    "anyOf": _compile_any,
    "oneOf": _compile_one,
    "not": _compile_not,
}
