"""Image objects: the input of the localizer, read and checked.

One image is a JSON object (schema: ``mapdb/data/image.schema.json``)::

    {"id": "frame-000123", "width": 640, "height": 480,
     "objects": [{"label": "building", "x": 321.5, "y": 118.0}, ...],
     "prior": {"x": 385120.0, "y": 6671230.0, "radius": 250.0},     # optional ("lon"/"lat" also)
     "attitude": {"roll_deg": 0.4, "pitch_deg": -1.2},               # optional
     "camera": {"fov_deg": 35.0},                                     # optional
     "altitude_m": 100.0}                                             # optional

Pixels: x to the right, y down, (0, 0) the top-left corner.  A file of several
images is JSON Lines; a file holding a single (possibly pretty-printed) object
or a JSON array of objects is read too.  Other keys are ignored.

Checking is the JSON Schema plus what a schema cannot say: every number finite
(Python's JSON reader accepts ``NaN`` and ``Infinity``) and every object inside
the image.  Problems raise :class:`~mapdb.errors.ImageInputError` with a
one-line message naming the source and the offending field.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from jsonschema import Draft202012Validator

from .errors import ImageInputError, reading

__all__ = [
    "IMAGE_SCHEMA_PATH",
    "MAX_OBJECTS",
    "ImageObjects",
    "Prior",
    "image_schema",
    "parse_image",
    "read_image_documents",
    "split_image_documents",
]

IMAGE_SCHEMA_PATH = Path(str(resources.files("mapdb") / "data" / "image.schema.json"))
# A guard against documents that would take minutes: no detector reports this many objects in a frame.
MAX_OBJECTS = 20_000


@dataclass(frozen=True)
class Prior:
    """Where the map point under the image centre is known to be (``lonlat``: x, y are lon, lat degrees)."""

    x: float
    y: float
    radius: float
    lonlat: bool = False


@dataclass(frozen=True)
class ImageObjects:
    """A checked image document: pixel positions and label names as arrays, plus the optional hints.

    Examples
    --------
    >>> im = parse_image({"width": 640, "height": 480, "objects": [{"label": "building", "x": 1, "y": 2}]})
    >>> len(im), im.names.tolist(), float(im.x[0]), im.prior is None
    (1, ['building'], 1.0, True)
    """

    id: Any
    width: float
    height: float
    x: np.ndarray
    y: np.ndarray
    names: np.ndarray
    prior: Prior | None = None
    roll_deg: float | None = None
    pitch_deg: float | None = None
    fov_deg: float | None = None
    altitude_m: float | None = None

    def __len__(self) -> int:
        return int(self.x.size)


@lru_cache(maxsize=1)
def image_schema() -> dict[str, Any]:
    """The published JSON Schema of one image document."""
    return json.loads(IMAGE_SCHEMA_PATH.read_text(encoding="utf-8"))


@lru_cache(maxsize=1)
def _validator() -> Draft202012Validator:
    return Draft202012Validator(image_schema())


def _where(path: Any) -> str:
    """``["objects", 2, "x"]`` -> ``objects[2].x``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "document"


def _schema_message(error: Any) -> str:
    where = _where(error.absolute_path)
    path = list(error.absolute_path)
    if isinstance(error.instance, float) and not math.isfinite(error.instance):
        return f"{where} is {error.instance!r}, not a finite number"
    if error.validator == "minimum" and len(path) == 3 and path[0] == "objects" and path[2] in ("x", "y"):
        return f"{where} is negative ({error.instance!r}): pixel coordinates start at 0, the top-left corner"
    if error.validator == "oneOf" and path == ["prior"]:
        return "prior: give either x and y (map CRS metres) or lon and lat (degrees), and a radius"
    if error.validator == "required":
        return f"{where}: {error.message}"
    message = error.message
    if len(message) > 160:
        message = message[:157] + "..."
    return f"{where}: {message}"


def _plain_object_ok(obj: Any) -> bool:
    """The schema's rules for one entry of ``objects`` (label: non-empty string; x, y: numbers >= 0)."""
    if type(obj) is not dict:
        return False
    label, x, y = obj.get("label"), obj.get("x"), obj.get("y")
    return (
        type(label) is str
        and label != ""
        and type(x) in (int, float)
        and type(y) in (int, float)
        and x >= 0
        and y >= 0
    )


def _finite(value: Any, where: str, source: str) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ImageInputError(f"{source}: {where} is {value!r}, not a finite number")
    return v


def parse_image(doc: Any, source: str = "<image>") -> ImageObjects:
    """Check one image document (already decoded from JSON) and turn it into arrays.

    Parameters
    ----------
    doc : dict
        The decoded JSON object.
    source : str
        Where it came from (``"images.jsonl line 3"``), for messages.

    Raises
    ------
    ImageInputError
        With a one-line message: the first schema violation, a non-finite number, or an object outside
        the image.
    """
    if not isinstance(doc, dict):
        raise ImageInputError(f"{source}: an image must be a JSON object, got {type(doc).__name__}")
    objects = doc.get("objects")
    if isinstance(objects, list) and len(objects) > MAX_OBJECTS:
        raise ImageInputError(f"{source}: {len(objects)} objects; at most {MAX_OBJECTS} are accepted")
    # The schema is checked on the document with its object list emptied (a constant cost), and the
    # objects by the same rules in one plain loop - jsonschema costs ~20 us per object, more than matching.
    # Any object failing that loop sends the whole document through the schema, which words the error.
    whole = not (isinstance(objects, list) and all(map(_plain_object_ok, objects)))
    checked = doc if whole else {**doc, "objects": []}
    errors = sorted(_validator().iter_errors(checked), key=lambda e: (len(e.absolute_path), list(map(str, e.path))))
    if errors:
        raise ImageInputError(f"{source}: {_schema_message(errors[0])}")

    width = _finite(doc["width"], "width", source)
    height = _finite(doc["height"], "height", source)
    n = len(objects)
    x = np.fromiter((o["x"] for o in objects), dtype=np.float64, count=n)
    y = np.fromiter((o["y"] for o in objects), dtype=np.float64, count=n)
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if bad.any():
        i = int(np.argmax(bad))
        axis = "x" if not math.isfinite(x[i]) else "y"
        raise ImageInputError(f"{source}: objects[{i}].{axis} is {objects[i][axis]!r}, not a finite number")
    outside = (x > width) | (y > height)
    if outside.any():
        i = int(np.argmax(outside))
        raise ImageInputError(
            f"{source}: objects[{i}] at ({x[i]:g}, {y[i]:g}) is outside the {width:g}x{height:g} image"
        )
    names = np.array([o["label"] for o in objects], dtype=object)

    prior = None
    if "prior" in doc:
        p = doc["prior"]
        lonlat = "lon" in p
        px, py = (p["lon"], p["lat"]) if lonlat else (p["x"], p["y"])
        prior = Prior(
            _finite(px, "prior.lon" if lonlat else "prior.x", source),
            _finite(py, "prior.lat" if lonlat else "prior.y", source),
            _finite(p["radius"], "prior.radius", source),
            lonlat,
        )
    attitude = doc.get("attitude") or {}
    roll = attitude.get("roll_deg")
    pitch = attitude.get("pitch_deg")
    fov = (doc.get("camera") or {}).get("fov_deg")
    altitude = doc.get("altitude_m")
    return ImageObjects(
        id=doc.get("id"),
        width=width,
        height=height,
        x=x,
        y=y,
        names=names,
        prior=prior,
        roll_deg=None if roll is None else _finite(roll, "attitude.roll_deg", source),
        pitch_deg=None if pitch is None else _finite(pitch, "attitude.pitch_deg", source),
        fov_deg=None if fov is None else _finite(fov, "camera.fov_deg", source),
        altitude_m=None if altitude is None else _finite(altitude, "altitude_m", source),
    )


def _short(exc: json.JSONDecodeError) -> str:
    return f"malformed JSON: {exc.msg} (column {exc.colno})"


def split_image_documents(text: str, source: str = "<input>") -> Iterator[tuple[str, Any]]:
    """The image documents of a file's text, each as ``(where, decoded JSON or ImageInputError)``.

    JSON Lines: one document per non-blank line, a malformed line yielding an
    :class:`ImageInputError` in its place so that the other lines are still read.
    A text that is, as a whole, one JSON object or an array of objects is read as such.

    Examples
    --------
    >>> [(w, d if isinstance(d, dict) else str(d)) for w, d in split_image_documents('{"a": 1}\\n{oops\\n', "f")]
    [('f line 1', {'a': 1}), ('f line 2', 'f line 2: malformed JSON: Expecting property name enclosed in \
double quotes (column 2)')]
    """
    stripped = text.lstrip()
    if stripped.startswith(("{", "[")) and "\n" in text.strip():
        try:
            whole = json.loads(text)
        except json.JSONDecodeError:
            whole = None  # JSON Lines (or broken): read line by line below
        if isinstance(whole, dict):
            yield f"{source}", whole
            return
        if isinstance(whole, list):
            for i, doc in enumerate(whole):
                yield f"{source} item {i}", doc
            return
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        where = f"{source} line {number}"
        try:
            yield where, json.loads(line)
        except json.JSONDecodeError as exc:
            yield where, ImageInputError(f"{where}: {_short(exc)}")
        except RecursionError:
            yield where, ImageInputError(f"{where}: malformed JSON: nested too deeply")


def read_image_documents(path: str | Path) -> list[tuple[str, Any]]:
    """Read an image file (``-`` for stdin) into :func:`split_image_documents` pairs.

    Raises
    ------
    MapdbIOError
        If the file is missing or unreadable.
    ImageInputError
        If it is not UTF-8 text.
    """
    name = "<stdin>" if str(path) == "-" else str(path)
    with reading(name, "images file"):
        raw = sys.stdin.buffer.read() if str(path) == "-" else Path(path).read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ImageInputError(f"{name}: not UTF-8 text (byte {exc.start}); expected JSON Lines") from None
    return list(split_image_documents(text, name))
