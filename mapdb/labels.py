"""The label taxonomy and the rules that map source data to labels.

The default table ships as ``mapdb/data/labels.toml`` and is read by the same
code that reads a user's file, so the two cannot drift apart.  A user's file
replaces each top-level section it gives (``labels``, ``osm``, ``raster.<name>``)
and keeps the defaults for the others.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from .errors import LabelTableError, reading

__all__ = [
    "DEFAULT_LABELS_PATH",
    "IntersectionRule",
    "LabelTable",
    "TagRule",
    "default_label_table",
    "load_label_table",
]

DEFAULT_LABELS_PATH = Path(str(resources.files("mapdb") / "data" / "labels.toml"))
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


def _read_toml(path: Path) -> dict[str, Any]:
    with reading(path, "label file"):
        text = path.read_bytes()
    try:
        return tomllib.loads(text.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise LabelTableError(f"{path}: not a valid TOML label file ({exc})") from None


def _str_list(where: str, value: Any, what: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise LabelTableError(f"{where}: {what} must be a list of strings")
    return tuple(value)


def _parse(doc: dict[str, Any], where: str, base: LabelTable | None) -> LabelTable:
    unknown = set(doc) - {"labels", "osm", "raster"}
    if unknown:
        raise LabelTableError(f"{where}: unknown section(s) {', '.join(sorted(unknown))}")
    if "labels" in doc:
        labels = _str_list(where, doc["labels"], "labels")
        if len(set(labels)) != len(labels) or not labels:
            raise LabelTableError(f"{where}: labels must be a non-empty list without repeats")
        if len(labels) > 255:
            raise LabelTableError(f"{where}: at most 255 labels, got {len(labels)}")
    elif base is not None:
        labels = base.labels
    else:
        raise LabelTableError(f"{where}: no labels list")

    def check(label: Any, context: str) -> str:
        if not isinstance(label, str) or label not in labels:
            raise LabelTableError(f"{where}: {context} maps to unknown label {label!r} (not in labels)")
        return label

    if "osm" in doc:
        osm = doc["osm"]
        if not isinstance(osm, dict):
            raise LabelTableError(f"{where}: [osm] must be a table")
        rules = []
        for i, r in enumerate(osm.get("rules", [])):
            ctx = f"osm rule {i + 1}"
            if not isinstance(r, dict) or not isinstance(r.get("key"), str):
                raise LabelTableError(f"{where}: {ctx} needs a string 'key'")
            geometry = frozenset(_str_list(where, r.get("geometry", ["area"]), f"{ctx} geometry"))
            if not geometry or geometry - _GEOMETRIES:
                raise LabelTableError(f"{where}: {ctx} geometry must be among {sorted(_GEOMETRIES)}")
            values = r.get("values")
            rules.append(TagRule(
                label=check(r.get("label"), ctx),
                key=r["key"],
                values=None if values is None else _str_list(where, values, f"{ctx} values"),
                exclude=_str_list(where, r.get("exclude", []), f"{ctx} exclude"),
                geometry=geometry,
            ))
        inter = osm.get("intersections")
        intersections = None
        if inter is not None:
            dist = inter.get("merge_distance_m", 5.0)
            if not isinstance(dist, int | float) or dist < 0:
                raise LabelTableError(f"{where}: intersections merge_distance_m must be a number >= 0")
            intersections = IntersectionRule(
                label=check(inter.get("label", "road_intersection"), "osm intersections"),
                highways=_str_list(where, inter.get("highways", []), "intersections highways"),
                merge_distance_m=float(dist),
            )
        osm_rules: tuple[TagRule, ...] = tuple(rules)
    else:
        osm_rules = base.osm_rules if base else ()
        intersections = base.intersections if base else None
        for r in osm_rules:
            check(r.label, f"default osm rule for {r.key}")
        if intersections:
            check(intersections.label, "default osm intersections")

    rasters = {name: dict(t) for name, t in (base.rasters.items() if base else ())}
    raster_doc = doc.get("raster", {})
    if not isinstance(raster_doc, dict):
        raise LabelTableError(f"{where}: [raster] must be a table of class tables")
    for name, table in raster_doc.items():
        if not isinstance(table, dict):
            raise LabelTableError(f"{where}: [raster.{name}] must map class codes to labels")
        parsed = {}
        for code, label in table.items():
            try:
                parsed[int(code)] = check(label, f"raster.{name} class {code}")
            except ValueError:
                raise LabelTableError(f"{where}: raster.{name} class {code!r} is not an integer") from None
        rasters[name] = parsed
    if "labels" in doc and "raster" not in doc:
        for name, table in rasters.items():
            for code, label in table.items():
                check(label, f"default raster.{name} class {code}")
    return LabelTable(labels, osm_rules, intersections, rasters, where)


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
        _DEFAULT = _parse(_read_toml(DEFAULT_LABELS_PATH), "default", None)
    return _DEFAULT


def load_label_table(path: str | Path | None = None) -> LabelTable:
    """Read a user's label file over the defaults; ``None`` gives the default table.

    Raises :class:`LabelTableError` for a rule that names a label not declared
    in ``labels``, and :class:`MapdbIOError` for a missing file.
    """
    if path is None:
        return default_label_table()
    path = Path(path)
    return _parse(_read_toml(path), str(path), default_label_table())
