"""The label taxonomy and the rules that map source data to labels.

The default table ships as ``mapdb/data/labels.toml`` and is read by the same
code that reads a user's file, so the two cannot drift apart.  A user's file
replaces each top-level section it gives (``labels``, ``osm``, ``raster.<name>``)
and keeps the defaults for the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import LabelTableError, open_regular, reading

__all__ = [
    "BLOCK_LABEL",
    "BUILDING_LABEL",
    "DEFAULT_LABELS_PATH",
    "MAX_LABEL_FILE_BYTES",
    "MAX_MERGE_DISTANCE_M",
    "IntersectionRule",
    "LabelTable",
    "TagRule",
    "default_label_table",
    "load_label_table",
    "read_toml",
]

DEFAULT_LABELS_PATH = Path(__file__).parent / "data" / "labels.toml"  # not importlib.resources: 0.02 s of start-up
# Blocks of touching buildings (mapdb.build.blocks) are objects of their own label, made by the builder from
# the footprints of the building label; mask images match them as buildings, point detections never.
BUILDING_LABEL = "building"
BLOCK_LABEL = "building_block"
_GEOMETRIES = {"area", "node", "way"}


@dataclass(frozen=True)
class TagRule:
    """One OSM tag rule: objects tagged ``key`` (with one of ``values``, or any value but ``exclude``)."""

    label: str
    key: str
    values: tuple[str, ...] | None = None
    exclude: tuple[str, ...] = ()
    geometry: frozenset[str] = frozenset({"area"})

    def matches(self, value: str | None) -> bool:
        if value is None or value in self.exclude:
            return False
        return self.values is None or value in self.values


@dataclass(frozen=True)
class IntersectionRule:
    """Road intersections: nodes shared by two or more distinct ways of ``highways`` classes."""

    label: str = "road_intersection"
    highways: tuple[str, ...] = ()
    merge_distance_m: float = 5.0


@dataclass(frozen=True)
class LabelTable:
    """Label names plus the OSM and raster rules that produce them."""

    labels: tuple[str, ...]
    osm_rules: tuple[TagRule, ...] = ()
    intersections: IntersectionRule | None = None
    rasters: dict[str, dict[int, str]] = field(default_factory=dict)
    source: str = "default"

    def code(self, label: str) -> int:
        return self.labels.index(label)

    def raster_classes(self, name: str) -> dict[int, str]:
        try:
            return self.rasters[name]
        except KeyError:
            raise LabelTableError(
                f"{self.source}: no raster class table named {name!r} (have: {', '.join(sorted(self.rasters))})"
            ) from None


def read_toml(path: Path) -> dict[str, Any]:
    """A label file or class table read as TOML: a regular file (a FIFO would block), size-capped, parsed."""
    with reading(path, "label file"), open_regular(path, path, "label file") as f:
        text = f.read(MAX_LABEL_FILE_BYTES + 1)
    if len(text) > MAX_LABEL_FILE_BYTES:
        raise LabelTableError(f"{path}: a label file may hold at most {MAX_LABEL_FILE_BYTES:,} bytes")
    import tomllib  # here: a query reads no label file, and its start-up counts

    try:
        return tomllib.loads(text.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise LabelTableError(f"{path}: not a valid TOML label file ({' '.join(str(exc).split())})") from None
    except RecursionError:  # tomllib recurses once per level of nested arrays or inline tables
        raise LabelTableError(f"{path}: not a valid TOML label file (nested too deep)") from None


# The schema of a label file: the keys each table may hold.  Anything else is refused by name, so a
# misspelt key ("valeus") is an error rather than a rule that silently matches everything.
_TOP_KEYS = ("labels", "osm", "raster")
_OSM_KEYS = ("rules", "intersections")
_RULE_KEYS = ("label", "key", "values", "exclude", "geometry")
_INTERSECTION_KEYS = ("label", "highways", "merge_distance_m")
# Junctions closer than this are one intersection; a bigger distance would pair up every junction
# of a city with every other (quadratic memory), and no crossing is that wide.
MAX_MERGE_DISTANCE_M = 100.0
_MAX_LABELS = 255
# The default table is 5 KB; a label file a thousand times that is not a label file.
MAX_LABEL_FILE_BYTES = 1 << 22


class _Schema:
    """Checks for one label file: each failure is one line naming the file and the key."""

    def __init__(self, where: str) -> None:
        self.where = where

    def fail(self, key: str, problem: str) -> LabelTableError:
        return LabelTableError(f"{self.where}: {key}: {problem}")

    def table(self, key: str, value: Any, allowed: tuple[str, ...]) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(key, f"must be a table, not {_kind(value)}")
        unknown = [k for k in value if k not in allowed]
        if unknown:
            raise self.fail(f"{key}.{unknown[0]}" if key else unknown[0],
                            f"unknown key (expected one of {', '.join(allowed)})")
        return value

    def strings(self, key: str, value: Any, *, empty: bool = True) -> tuple[str, ...]:
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise self.fail(key, f"must be a list of non-empty strings, not {_kind(value)}")
        if not empty and not value:
            raise self.fail(key, "must not be empty")
        return tuple(value)

    def string(self, key: str, value: Any) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"must be a non-empty string, not {_kind(value)}")
        return value

    def number(self, key: str, value: Any, low: float, high: float) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not (low <= value <= high):
            raise self.fail(key, f"must be a number in [{low:g}, {high:g}], not {_kind(value)}")
        return float(value)


def _kind(value: Any) -> str:
    """A short description of a TOML value for error messages (never the whole value)."""
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    if isinstance(value, int | float):
        return f"the number {value!r}"
    if isinstance(value, str):
        return f"the string {value[:40]!r}"
    kinds: dict[type, str] = {dict: "a table", list: "a list"}
    return kinds.get(type(value), type(value).__name__)


def _parse(doc: dict[str, Any], where: str, base: LabelTable | None) -> LabelTable:
    """A label table from a TOML document read over ``base``: labels, then OSM rules, then raster classes."""
    schema = _Schema(where)
    schema.table("", doc, _TOP_KEYS)
    labels = _parse_labels(schema, doc, base)

    def check(label: Any, key: str) -> str:
        name = schema.string(key, label)
        if name not in labels:
            raise schema.fail(key, f"unknown label {name!r} (not in labels)")
        return name

    osm_rules, intersections = _parse_osm(schema, doc, base, check)
    rasters = _parse_rasters(schema, doc, base, check)
    return LabelTable(labels, osm_rules, intersections, rasters, where)


_Check = Callable[[Any, str], str]


def _parse_labels(schema: _Schema, doc: dict[str, Any], base: LabelTable | None) -> tuple[str, ...]:
    """The document's label names, else the base table's."""
    if "labels" in doc:
        labels = schema.strings("labels", doc["labels"], empty=False)
        if len(set(labels)) != len(labels):
            raise schema.fail("labels", "must not repeat a name")
        if len(labels) > _MAX_LABELS:
            raise schema.fail("labels", f"at most {_MAX_LABELS} labels, got {len(labels)}")
        return labels
    if base is not None:
        return base.labels
    raise schema.fail("labels", "missing")


def _parse_osm(schema: _Schema, doc: dict[str, Any], base: LabelTable | None, check: _Check
               ) -> tuple[tuple[TagRule, ...], IntersectionRule | None]:
    """The ``[osm]`` rules and intersection rule, else the base table's (their labels checked)."""
    if "osm" not in doc:
        osm_rules = base.osm_rules if base else ()
        intersections = base.intersections if base else None
        for r in osm_rules:
            check(r.label, f"osm rule for {r.key} (default)")
        if intersections:
            check(intersections.label, "osm.intersections.label (default)")
        return osm_rules, intersections
    osm = schema.table("osm", doc["osm"], _OSM_KEYS)
    rule_list = osm.get("rules", [])
    if not isinstance(rule_list, list):
        raise schema.fail("osm.rules", f"must be a list of tables ([[osm.rules]]), not {_kind(rule_list)}")
    rules = [_parse_rule(schema, f"osm.rules[{i + 1}]", r, check) for i, r in enumerate(rule_list)]
    intersections = None
    if "intersections" in osm:
        inter = schema.table("osm.intersections", osm["intersections"], _INTERSECTION_KEYS)
        intersections = IntersectionRule(
            label=check(inter.get("label", "road_intersection"), "osm.intersections.label"),
            highways=schema.strings("osm.intersections.highways", inter.get("highways", [])),
            merge_distance_m=schema.number("osm.intersections.merge_distance_m",
                                           inter.get("merge_distance_m", 5.0), 0.0, MAX_MERGE_DISTANCE_M),
        )
    return tuple(rules), intersections


def _parse_rule(schema: _Schema, ctx: str, r: Any, check: _Check) -> TagRule:
    """One ``[[osm.rules]]`` table."""
    schema.table(ctx, r, _RULE_KEYS)
    geometry = frozenset(schema.strings(f"{ctx}.geometry", r.get("geometry", ["area"]), empty=False))
    if geometry - _GEOMETRIES:
        raise schema.fail(f"{ctx}.geometry", f"must be among {', '.join(sorted(_GEOMETRIES))}")
    values = r.get("values")
    return TagRule(
        label=check(r.get("label"), f"{ctx}.label"),
        key=schema.string(f"{ctx}.key", r.get("key")),
        values=None if values is None else schema.strings(f"{ctx}.values", values),
        exclude=schema.strings(f"{ctx}.exclude", r.get("exclude", [])),
        geometry=geometry,
    )


def _parse_rasters(schema: _Schema, doc: dict[str, Any], base: LabelTable | None, check: _Check
                   ) -> dict[str, dict[int, str]]:
    """The base table's raster class tables with the document's ``[raster.NAME]`` tables over them."""
    rasters = {name: dict(t) for name, t in (base.rasters.items() if base else ())}
    raster_doc = doc.get("raster", {})
    if not isinstance(raster_doc, dict):
        raise schema.fail("raster", f"must be a table of class tables ([raster.NAME]), not {_kind(raster_doc)}")
    for name, table in raster_doc.items():
        if not isinstance(table, dict):
            raise schema.fail(f"raster.{name}", f"must map class codes to labels, not {_kind(table)}")
        parsed = {}
        for code, label in table.items():
            try:
                number = int(code)
            except ValueError:
                raise schema.fail(f"raster.{name}.{code}", "a class code must be an integer") from None
            if not -(2**63) <= number < 2**64:
                raise schema.fail(f"raster.{name}.{code}", "a class code must fit in 64 bits")
            parsed[number] = check(label, f"raster.{name}.{code}")
        rasters[name] = parsed
    if "labels" in doc and "raster" not in doc:
        for name, table in rasters.items():
            for code, label in table.items():
                check(label, f"raster.{name}.{code} (default)")
    return rasters


_DEFAULT: LabelTable | None = None


def default_label_table() -> LabelTable:
    """The table shipped with mapdb.

    Examples
    --------
    >>> t = default_label_table()
    >>> "building" in t.labels and "road_intersection" in t.labels
    True
    >>> t.raster_classes("worldcover")[80]
    'water'
    """
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = _parse(read_toml(DEFAULT_LABELS_PATH), "default", None)
    return _DEFAULT


def load_label_table(path: str | Path | None = None) -> LabelTable:
    """Read a user's label file over the defaults; ``None`` gives the default table.

    Raises :class:`LabelTableError` for a rule that names a label not declared
    in ``labels``, and :class:`MapdbIOError` for a missing file.
    """
    if path is None:
        return default_label_table()
    path = Path(path)
    return _parse(read_toml(path), str(path), default_label_table())
