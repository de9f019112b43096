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
from dataclasses import dataclass, field
from typing import Any

from .outputs import json_safe

__all__ = ["Answer", "Candidate"]


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _placed(candidate: dict[str, Any]) -> bool:
    """Whether a candidate read from a file has a position (a hand-edited one may not)."""
    return _number(candidate.get("x")) is not None and _number(candidate.get("y")) is not None


@dataclass(frozen=True)
class Candidate:
    """A place the search found for the image: where the image centre would be, and its evidence."""

    x: float
    y: float
    inliers: int
    score: float | None
    sigma_m: float | None

    def to_json(self) -> dict[str, Any]:
        return json_safe(dataclasses.asdict(self))


# Fields written only when they have a value, in this order, after the pose and before the time.
_OPTIONAL = ("rejected_by", "score_without_areas", "hypotheses", "skipped_labels", "notes", "error_std")
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
    skipped_labels: dict[str, int] | None = None
    notes: list[str] | None = None
    error_std: float | None = None
    time_ms: float = 0.0

    @property
    def ok(self) -> bool:
        """Whether the image was localized."""
        return self.status == "ok"

    def to_json(self) -> dict[str, Any]:
        """The JSON object ``mapdb query`` writes: every number finite, optional fields only when set."""
        record: dict[str, Any] = {"id": self.id, "status": self.status}
        if self.ok:
            record.update((name, getattr(self, name)) for name in _POSE)
            if self.altitude_m is not None:
                record["altitude_m"] = self.altitude_m
            record["levelled"] = bool(self.levelled)
        else:
            record["reason"] = self.reason
        record["candidates"] = [c.to_json() for c in self.candidates]
        record.update((name, getattr(self, name)) for name in _OPTIONAL if getattr(self, name) is not None)
        record["time_ms"] = self.time_ms
        return json_safe(record)

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
