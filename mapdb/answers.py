"""What the localizer answers, as typed values; turned into JSON only at the edge (:meth:`Answer.to_json`).

An :class:`Answer` is either accepted (``status == "ok"``: a position and the pose behind it) or
rejected (``status == "rejected"``: a ``reason``).  Both carry the runner-up :class:`Candidate` places
the search found and the time it took.  :mod:`mapdb.localize.records` documents what each field means; the JSON
form is what ``mapdb query`` writes, one object per line, and :meth:`Answer.from_json` reads it back.

Examples
--------
>>> a = Answer(id="img-1", status="rejected", reason="0 objects: at least 3 are needed", time_ms=0.1)
>>> a.ok, a.to_json()
(False, {'id': 'img-1', 'status': 'rejected', 'reason': '0 objects: at least 3 are needed', 'candidates': [], \
'time_ms': 0.1})
>>> Answer.from_json(a.to_json()) == a
True
>>> Answer.from_json({"status": "ok"}).x is None  # a partial record reads as far as it goes
True
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from .outputs import json_safe

__all__ = ["Answer", "Candidate"]


# Values json_safe returns as they are, by their exact type (a subclass is json_safe's to judge).
_AS_IS = frozenset({str, int, bool, type(None)})


def _safe(value: Any) -> Any:
    """:func:`~mapdb.outputs.json_safe` of one of an answer's values: its floats, ints, strings and lists of them
    judged here by their type (a document's few dozen values, written for every answer of a stream), anything else
    by json_safe."""
    kind = type(value)
    if kind is float:
        return value if math.isfinite(value) else None
    if kind in _AS_IS:
        return value
    if kind is list:
        return [_safe(item) for item in value]
    return json_safe(value)


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _placed(candidate: dict[str, Any]) -> bool:
    """Whether a candidate read from a file has a position (a hand-edited one may not)."""
    return _number(candidate.get("x")) is not None and _number(candidate.get("y")) is not None


def _ring(corners: Any) -> list[list[float]]:
    """A footprint's lon/lat corners as an RFC 7946 polygon ring: closed, counter-clockwise (exterior).

    Examples
    --------
    >>> _ring([[0, 1], [1, 1], [1, 0], [0, 0]])  # clockwise corners, as a north-up image's are
    [[0.0, 1.0], [0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
    """
    ring = [[float(x), float(y)] for x, y in corners]
    # Shoelace: positive twice-area for a counter-clockwise ring.
    twice_area = sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(ring, ring[1:] + ring[:1], strict=True))
    if twice_area < 0:
        ring = ring[:1] + ring[:0:-1]
    return ring + ring[:1]


@dataclass(frozen=True)
class Candidate:
    """A place the search found for the image: where the image centre would be, and its evidence."""

    x: float
    y: float
    inliers: int
    score: float | None
    sigma_m: float | None

    def to_json(self) -> dict[str, Any]:
        return {"x": _safe(self.x), "y": _safe(self.y), "inliers": _safe(self.inliers), "score": _safe(self.score),
                "sigma_m": _safe(self.sigma_m)}


# Fields written only when they have a value, in this order, after the pose and before the time.
_OPTIONAL = ("rejected_by", "score_without_areas", "hypotheses", "path", "skipped_labels", "notes", "error_std")
# Where the image lies on the ground (:mod:`mapdb.localize.georef`), written after the pose when known.
_GEOREF = ("width", "height", "transform", "transform_error_m", "footprint", "footprint_lonlat")
# Fields that are not GeoJSON properties: lists (the geometry's own, and the candidates).
_NOT_PROPERTIES = frozenset({"candidates", "transform", "footprint", "footprint_lonlat", "skipped_labels", "notes"})
# The pose's fields, written (with None where unknown) for every accepted answer.
_POSE = ("x", "y", "lon", "lat", "crs", "inliers", "heading_deg", "scale_m_per_px", "sigma_m", "score",
         "expected_false_alarms")


@dataclass
class Answer:
    """One image's answer (:func:`mapdb.localize.localize`); the module docs of :mod:`mapdb.localize.records`
    say what each field means."""

    id: str | int | None
    status: str
    reason: str | None = None
    x: float | None = None
    y: float | None = None
    lon: float | None = None
    lat: float | None = None
    crs: str | None = None
    inliers: int | None = None
    heading_deg: float | None = None
    scale_m_per_px: float | None = None
    sigma_m: float | None = None
    score: float | None = None
    expected_false_alarms: float | None = None
    altitude_m: float | None = None
    levelled: bool | None = None
    candidates: list[Candidate] = field(default_factory=list)
    rejected_by: str | None = None
    score_without_areas: float | None = None
    hypotheses: int | None = None
    path: str | None = None
    skipped_labels: dict[str, int] | None = None
    notes: list[str] | None = None
    error_std: float | None = None
    time_ms: float = 0.0
    width: float | None = None
    height: float | None = None
    transform: list[float] | None = None
    transform_error_m: float | None = None
    footprint: list[list[float]] | None = None
    footprint_lonlat: list[list[float]] | None = None

    @property
    def ok(self) -> bool:
        """Whether the image was localized."""
        return self.status == "ok"

    def to_json(self) -> dict[str, Any]:
        """The JSON object ``mapdb query`` writes: every number finite, optional fields only when set."""
        fields = self.__dict__
        record: dict[str, Any] = {"id": _safe(self.id), "status": _safe(self.status)}
        if self.ok:
            record.update((name, _safe(fields[name])) for name in _POSE)
            if self.altitude_m is not None:
                record["altitude_m"] = _safe(self.altitude_m)
            record["levelled"] = bool(self.levelled)
            record.update((name, _safe(fields[name])) for name in _GEOREF if fields[name] is not None)
        else:
            record["reason"] = _safe(self.reason)
        record["candidates"] = [c.to_json() for c in self.candidates]
        record.update((name, _safe(fields[name])) for name in _OPTIONAL if fields[name] is not None)
        record["time_ms"] = _safe(self.time_ms)
        return record

    def properties(self) -> dict[str, Any]:
        """The answer's fields as GeoJSON properties: those of :meth:`to_json` whose values are not lists or
        objects (the footprint, the transform and the candidates are not: see ``mapdb query --footprints``),
        with the notes joined by ``"; "``."""
        record = self.to_json()
        properties = {name: value for name, value in record.items() if name not in _NOT_PROPERTIES}
        if self.notes:
            properties["notes"] = "; ".join(self.notes)
        return properties

    @property
    def __geo_interface__(self) -> dict[str, Any]:
        """A GeoJSON Feature (RFC 7946): the image centre's point in lon/lat (None when rejected, or without a
        CRS), and :meth:`properties`; shapely's ``shape()`` and geopandas' ``from_features`` read it."""
        geometry = None
        if self.ok and self.lon is not None and self.lat is not None:
            geometry = {"type": "Point", "coordinates": [self.lon, self.lat]}
        return {"type": "Feature", "geometry": geometry, "properties": self.properties()}

    def footprint_feature(self) -> dict[str, Any] | None:
        """The image's footprint as a GeoJSON Polygon Feature in lon/lat (the ring counter-clockwise, as
        RFC 7946 asks) with :meth:`properties`; None without a footprint in lon/lat."""
        if not self.ok or not self.footprint_lonlat:
            return None
        geometry = {"type": "Polygon", "coordinates": [_ring(self.footprint_lonlat)]}
        return {"type": "Feature", "geometry": geometry, "properties": self.properties()}

    @classmethod
    def from_json(cls, record: dict[str, Any]) -> Answer:
        """An answer as ``mapdb query`` wrote it (unknown keys ignored, missing ones None, candidates without
        a position left out)."""
        names = {f.name for f in dataclasses.fields(cls)} - {"candidates"}
        values = {name: record[name] for name in names if name in record}
        values.setdefault("id", None)
        values.setdefault("status", "rejected")
        candidates = [Candidate(float(c["x"]), float(c["y"]), int(c.get("inliers") or 0), _number(c.get("score")),
                                _number(c.get("sigma_m")))
                      for c in record.get("candidates") or () if isinstance(c, dict) and _placed(c)]
        return cls(**values, candidates=candidates)
