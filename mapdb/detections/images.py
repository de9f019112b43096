"""Image objects: the input of the localizer, read and checked.

One image is a JSON object (schema: ``mapdb/data/image.schema.json``)::

    {"id": "frame-000123", "width": 640, "height": 480,
     "objects": [{"label": "building", "x": 321.5, "y": 118.0}, ...],
     "prior": {"x": 385120.0, "y": 6671230.0, "radius": 250.0},     # optional (lon/lat, heading_deg also)
     "attitude": {"roll_deg": 0.4, "pitch_deg": -1.2},               # optional
     "camera": {"fov_deg": 35.0},                                     # optional
     "altitude_m": 100.0}                                             # optional

Pixels: x to the right, y down, (0, 0) the top-left corner.  A file of several
images is JSON Lines, read as a stream (:func:`read_image_documents`); a file
holding a single (possibly pretty-printed) object or a JSON array of objects is
read too.  Other keys are ignored.

Checking is the JSON Schema plus what a schema cannot say: every number finite
(Python's JSON reader accepts ``NaN`` and ``Infinity``) and every object inside
the image.  Every number has a range (the schema's, also given below as
constants) that keeps all later arithmetic finite: a prior radius of ``1e308``
or an altitude of ``1e308`` is a rejected image, not an overflow.  Problems
raise :class:`~mapdb.errors.ImageInputError` with a one-line message naming the
source and the offending field.

==========================  ===========================================
field                       accepted
==========================  ===========================================
width, height               1 <= v <= ``MAX_IMAGE_SIDE_PX`` (1,000,000)
objects                     at most ``MAX_OBJECTS`` (20,000)
objects[].x, objects[].y    0 <= v <= width (height)
objects[].area_px           optional, 0 <= v <= 1e12 (pixels)
objects[].border            optional, boolean (the region touches the image border)
objects[].bbox              optional, [x0, y0, x1, y1], each 0 <= v <= 1,000,000
objects[].orientation_deg   optional, 0 <= v < 180 (the region's major axis)
objects[].elongation        optional, 1 <= v <= ``MAX_ELONGATION`` (1e6)
prior.radius                0 < r <= ``MAX_PRIOR_RADIUS_M`` (20,000 km)
prior.x, prior.y            abs(v) <= ``MAX_MAP_COORDINATE_M`` (1e8 m)
prior.lon, prior.lat        [-180, 180], [-90, 90]
prior.heading_deg (_sigma)  optional, [-360, 360] (clockwise from grid north); sigma (0, 10], default 5
altitude_m                  0 < v <= ``MAX_ALTITUDE_M`` (100 km)
camera.fov_deg              ``MIN_FOV_DEG`` (0.001) <= v < 180
attitude.roll_deg, pitch    [-89, 89]
==========================  ===========================================
"""

from __future__ import annotations

import io
import itertools
import json
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np

from ..errors import ImageInputError, reading
from ._fields import positions as _positions
from ._fields import region_fields as _region_fields
from ._quick_schema import surely_valid

if TYPE_CHECKING:
    from jsonschema import Draft202012Validator

__all__ = [
    "IMAGE_SCHEMA_PATH",
    "MAX_ALTITUDE_M",
    "MAX_ATTITUDE_DEG",
    "MAX_DOCUMENT_BYTES",
    "MAX_ELONGATION",
    "MAX_HEADING_SIGMA_DEG",
    "MAX_IMAGE_SIDE_PX",
    "MAX_MAP_COORDINATE_M",
    "MAX_OBJECTS",
    "MAX_PRIOR_RADIUS_M",
    "MIN_FOV_DEG",
    "ImageObjects",
    "Prior",
    "check_prior",
    "image_schema",
    "parse_image",
    "read_image_documents",
    "split_image_documents",
]

IMAGE_SCHEMA_PATH = Path(__file__).parents[1] / "data" / "image.schema.json"  # not importlib.resources: start-up
# The ranges of an image's numbers (module docs).  The schema states the same bounds and is what checks
# them (tests keep the two equal); here they are named for the code and the messages that need them.
# A guard against documents that would take minutes: no detector reports this many objects in a frame.
MAX_OBJECTS = 20_000
MAX_IMAGE_SIDE_PX = 1_000_000
# An object's area in pixels: at most a whole image of the largest size.
MAX_AREA_PX = 1e12
# A region's elongation: a one-pixel line across the largest image.
MAX_ELONGATION = 1e6
# The JSON decoder's numbers, exactly (bool is not one; a subclass goes to the schema).
_NUMBER = (int, float)
# Narrower than any lens; a denormal field of view made the focal length infinite.
MIN_FOV_DEG = 0.001
# Half the Earth's circumference: a wider prior excludes nothing, and a finite bound keeps the prior's
# tile arithmetic finite (1e308 + a margin overflowed).
MAX_PRIOR_RADIUS_M = 20_000_000.0
MAX_HEADING_DEG = 360.0  # a compass's heading, any turn either way
MAX_HEADING_SIGMA_DEG = 10.0  # its 1-sigma error: the pose-prior stage's bound (kept equal by the tests)
# Projected coordinates on Earth stay within about 2e7 m; five times that is surely a mistake.
MAX_MAP_COORDINATE_M = 1e8
# The edge of space; with the field of view this bounds the ground footprint, hence the map area read.
MAX_ALTITUDE_M = 100_000.0
# The levelling model breaks down towards 90 degrees (the horizon in the image).
MAX_ATTITUDE_DEG = 89.0
# The longest document read: a line of JSON Lines, or a whole multi-line JSON file.  One image of
# MAX_OBJECTS objects takes about 1 MB, so this leaves room for other keys while bounding the memory
# that one line can take before it is checked.
MAX_DOCUMENT_BYTES = 16 << 20


@dataclass(frozen=True)
class Prior:
    """Where the map point under the image centre is (``lonlat``: x, y in lon, lat degrees); heading: module docs."""

    x: float
    y: float
    radius: float
    lonlat: bool = False
    heading_deg: float | None = None
    heading_sigma_deg: float = 5.0  # a compass's error, when a heading comes without one


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
    # The optional region attributes of a mask's objects (mapdb.detections.masks), None when no object has one:
    # ``area_px`` (NaN where an object lacks it), ``border`` (False where it lacks it), ``bbox`` (n, 4;
    # NaN rows where it lacks one).
    area_px: np.ndarray | None = None
    border: np.ndarray | None = None
    bbox: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.x.size)


@lru_cache(maxsize=1)
def image_schema() -> dict[str, Any]:
    """The published JSON Schema of one image document."""
    return json.loads(IMAGE_SCHEMA_PATH.read_text(encoding="utf-8"))


@lru_cache(maxsize=2)
def _validator(part: str | None = None) -> Draft202012Validator:
    """jsonschema's validator of the image schema, or of its property ``part``; imported only when a document
    is not certainly valid (see :mod:`mapdb.detections._quick_schema`): a one-image query is spared 0.05 s."""
    from jsonschema import Draft202012Validator

    return Draft202012Validator(_schema(part))


def _schema(part: str | None) -> dict[str, Any]:
    return image_schema() if part is None else image_schema()["properties"][part]


def _first_error(doc: Any, part: str | None = None) -> Any:
    """The error to report (the shallowest, then the first by path: a stable choice), or None when the
    document (or its property ``part``) satisfies the schema."""
    if surely_valid(_schema(part), doc):
        return None
    errors = sorted(_validator(part).iter_errors(doc), key=lambda e: (len(e.absolute_path), list(map(str, e.path))))
    return errors[0] if errors else None


def _where(path: Any) -> str:
    """``["objects", 2, "x"]`` -> ``objects[2].x``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "document"


def _schema_message(error: Any, prefix: tuple[str, ...] = ()) -> str:
    path = [*prefix, *error.absolute_path]
    where = _where(path)
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
    """The schema's rules for one entry of ``objects`` (label: non-empty string; x, y: numbers in range)."""
    return _plain_objects([obj]) is not None


# An image's objects as plain lists: x, y, labels, and whether any object has keys besides those three.
_PlainObjects = tuple[list[Any], list[Any], list[str], bool]


def _plain_objects(objects: list[Any]) -> _PlainObjects | None:
    """The objects' positions and labels, read in the one loop that checks them by the schema's rules for an entry
    of ``objects`` (label: non-empty string; x, y: numbers in range; the region fields, :func:`_region_fields_ok`);
    None at the first object that breaks one, whose error the schema then words.  Plain objects have finite
    positions (NaN fails the range tests)."""
    xs: list[Any] = []
    ys: list[Any] = []
    labels: list[str] = []
    extra = False
    for obj in objects:
        if type(obj) is not dict:
            return None
        # Any, not Any | None: the type() tests below rule out None before the comparisons.
        label: Any = obj.get("label")
        x: Any = obj.get("x")
        y: Any = obj.get("y")
        if not (type(label) is str and label != "" and type(x) in _NUMBER and type(y) in _NUMBER
                and 0 <= x <= MAX_IMAGE_SIDE_PX and 0 <= y <= MAX_IMAGE_SIDE_PX):
            return None
        if len(obj) != 3:
            if not _region_fields_ok(obj):
                return None
            extra = True
        xs.append(x)
        ys.append(y)
        labels.append(label)
    return xs, ys, labels, extra


def _region_fields_ok(obj: dict[str, Any]) -> bool:
    """The schema's rules for an object's optional ``area_px``, ``border``, ``bbox``, ``box``, ``orientation_deg``
    and ``elongation``."""
    area: Any = obj.get("area_px", 0)
    box: Any = obj.get("bbox", (0, 0, 0, 0))
    turn: Any = obj.get("orientation_deg", 0)
    stretch: Any = obj.get("elongation", 1)
    return (
        type(area) in (int, float) and 0 <= area <= MAX_AREA_PX
        and type(turn) in (int, float) and 0 <= turn < 180
        and type(stretch) in (int, float) and 1 <= stretch <= MAX_ELONGATION
        and type(obj.get("border", False)) is bool and type(obj.get("box", False)) is bool
        and type(box) in (list, tuple) and len(box) == 4
        and all(type(v) in (int, float) and 0 <= v <= MAX_IMAGE_SIDE_PX for v in box)
    )


def _not_an_object(doc: Any, source: str) -> str:
    return f"{source}: an image must be a JSON object, got {type(doc).__name__}"


def _finite(value: Any, where: str, source: str) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ImageInputError(f"{source}: {where} is {value!r}, not a finite number")
    return v


def _make_prior(p: dict[str, Any], source: str) -> Prior:
    """A :class:`Prior` from a ``prior`` object that passed the schema (whose ranges let NaN through)."""
    lonlat = "lon" in p
    px, py = (p["lon"], p["lat"]) if lonlat else (p["x"], p["y"])
    if "heading_sigma_deg" in p and "heading_deg" not in p:
        raise ImageInputError(f"{source}: prior.heading_sigma_deg is given without prior.heading_deg")
    return Prior(
        _finite(px, "prior.lon" if lonlat else "prior.x", source),
        _finite(py, "prior.lat" if lonlat else "prior.y", source),
        _finite(p["radius"], "prior.radius", source),
        lonlat,
        _finite(p["heading_deg"], "prior.heading_deg", source) if "heading_deg" in p else None,
        _finite(p.get("heading_sigma_deg", Prior.heading_sigma_deg), "prior.heading_sigma_deg", source),
    )


def check_prior(x: float, y: float, radius: float, source: str = "prior", *, lonlat: bool = False,
                heading: tuple[float, ...] = ()) -> Prior:
    """A prior in map-CRS metres (``--prior X,Y,R``), or lon/lat degrees with ``lonlat``, checked as an
    image's ``prior`` is; ``heading`` is ``(heading_deg,)`` or ``(heading_deg, heading_sigma_deg)`` (``--heading``).

    Raises
    ------
    ImageInputError
        ``"SOURCE: prior.radius: ..."`` (or another field) for a value out of range (module docs) or not finite.

    Examples
    --------
    >>> check_prior(385120.0, 6671230.0, 250.0, heading=(74.0,))
    Prior(x=385120.0, y=6671230.0, radius=250.0, lonlat=False, heading_deg=74.0, heading_sigma_deg=5.0)
    >>> check_prior(1.0, 1.0, 1e308, "--prior")
    Traceback (most recent call last):
    mapdb.errors.ImageInputError: --prior: prior.radius: 1e+308 is greater than the maximum of 20000000
    """
    doc = {"lon": x, "lat": y, "radius": radius} if lonlat else {"x": x, "y": y, "radius": radius}
    doc.update(zip(("heading_deg", "heading_sigma_deg"), heading, strict=False))
    if (error := _first_error(doc, "prior")) is not None:
        raise ImageInputError(f"{source}: {_schema_message(error, ('prior',))}")
    return _make_prior(doc, source)


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
    plain = _check_schema(doc, source)
    width = _finite(doc["width"], "width", source)
    height = _finite(doc["height"], "height", source)
    objects = doc["objects"]
    if plain is not None and (not objects or (max(plain[0]) <= width and max(plain[1]) <= height)):
        # The usual document: its objects read once, by the check, and inside the image.
        xs, ys, labels, extra = plain
        x, y = np.array(xs, np.float64), np.array(ys, np.float64)
        names = np.array(labels, dtype=object)
        area_px, border, bbox = _region_fields(objects, source) if extra else (None, None, None)
    else:
        x, y = _positions(objects, width, height, source)
        names = np.array([o["label"] for o in objects], dtype=object)
        area_px, border, bbox = _region_fields(objects, source)
    prior = _make_prior(doc["prior"], source) if "prior" in doc else None
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
        area_px=area_px,
        border=border,
        bbox=bbox,
    )


def _check_schema(doc: Any, source: str) -> _PlainObjects | None:
    """Raise the first schema violation of an image document, in one line; else its objects as
    :func:`_plain_objects` reads them, or None when some object was not plain (the schema then passed it)."""
    if not isinstance(doc, dict):
        raise ImageInputError(_not_an_object(doc, source))
    objects = doc.get("objects")
    if isinstance(objects, list) and len(objects) > MAX_OBJECTS:
        raise ImageInputError(f"{source}: {len(objects)} objects; at most {MAX_OBJECTS} are accepted")
    # The schema is checked on the document with its object list emptied (a constant cost), and the objects by
    # the same rules in one plain loop (jsonschema costs ~20 us per object, more than matching); any object failing
    # it sends the whole document through the schema, which words the error.
    plain = _plain_objects(objects) if isinstance(objects, list) else None
    checked = doc if plain is None else {**doc, "objects": []}
    if (error := _first_error(checked)) is not None:
        raise ImageInputError(f"{source}: {_schema_message(error)}")
    return plain


def _short(exc: json.JSONDecodeError) -> str:
    return f"malformed JSON: {exc.msg} (column {exc.colno})"


def _decode(text: str, where: str) -> Any:
    """One JSON document, or the :class:`ImageInputError` that rejects it (never raises)."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        return ImageInputError(f"{where}: {_short(exc)}")
    except RecursionError:
        return ImageInputError(f"{where}: malformed JSON: nested too deeply")
    except ValueError:  # Python refuses to convert integers of more than 4300 digits
        return ImageInputError(f"{where}: malformed JSON: a number with too many digits")
    return doc if isinstance(doc, dict) else ImageInputError(_not_an_object(doc, where))


def _decode_line(line: bytes | None, where: str, max_bytes: int) -> Any:
    if line is None:
        return ImageInputError(f"{where}: longer than {max_bytes} bytes; one image per line, "
                               f"at most {MAX_OBJECTS} objects")
    try:
        text = line.decode("utf-8")
    except UnicodeDecodeError as exc:
        return ImageInputError(
            f"{where}: not UTF-8 (byte 0x{line[exc.start]:02x} at column {exc.start + 1}); expected JSON text"
        )
    return _decode(text, where)


def _blank(line: bytes | None) -> bool:
    # JSON's own whitespace only: a line holding a form feed or U+2028 is not blank, it is a bad line.
    return line is not None and not line.strip(b" \t\r")


def _physical_lines(stream: BinaryIO, name: str, max_bytes: int) -> Iterator[tuple[int, bytes | None]]:
    """``(number, line)`` for each line of ``stream`` split on ``\\n`` only, as it arrives.

    The ``\\n`` and a ``\\r`` before it are removed, and a UTF-8 byte-order mark at the start of the
    first line.  A line longer than ``max_bytes`` comes as None; its bytes past the limit are
    skipped, never held.
    """
    number = 0
    while True:
        with reading(name, "images file"):
            line = stream.readline(max_bytes + 2)  # the content, a "\r" and the "\n"
        if not line:
            return
        number += 1
        if not line.endswith(b"\n") and len(line) == max_bytes + 2:
            with reading(name, "images file"):
                while (chunk := stream.readline(1 << 20)) and not chunk.endswith(b"\n"):
                    pass
            yield number, None
            continue
        line = line.removesuffix(b"\n").removesuffix(b"\r")
        if number == 1:
            line = line.removeprefix(b"\xef\xbb\xbf")
        yield number, (None if len(line) > max_bytes else line)


def _opens_a_document(line: bytes) -> bool:
    """Whether a first line is the start of a multi-line JSON document: ``{`` or ``[`` and JSON cut short.

    A malformed line fails before its end (``{oops``), a cut-short one only at its end (``{``,
    ``[{"id": 1},``): only the latter waits for more lines.
    """
    if not line.lstrip(b" \t\r").startswith((b"{", b"[")):
        return False
    try:
        text = line.decode("utf-8").rstrip(" \t\r")
        json.loads(text)
    except json.JSONDecodeError as exc:
        return exc.pos >= len(text)
    except (ValueError, RecursionError):  # not UTF-8, or a line that is malformed anyway
        return False
    return False


def _documents(stream: BinaryIO, name: str, max_bytes: int) -> Iterator[tuple[str, Any]]:
    """The reading logic behind :func:`split_image_documents` and :func:`read_image_documents`."""
    lines = _physical_lines(stream, name, max_bytes)
    head: list[tuple[int, bytes | None]] = []  # lines read ahead to recognise one multi-line document
    for number, line in lines:
        head.append((number, line))
        if not _blank(line):
            break
    overflow = False
    if head and head[-1][1] is not None and _opens_a_document(head[-1][1]):
        size = sum(len(line or b"") + 1 for _, line in head)  # all bytes here: blanks, then an opening line
        for number, line in lines:
            head.append((number, line))
            size += max_bytes + 1 if line is None else len(line) + 1
            if size > max_bytes:
                overflow = True
                break
        if not overflow:
            try:
                # No None here: an over-long line would have counted max_bytes + 1 and overflowed.
                whole = json.loads(b"\n".join(line or b"" for _, line in head).decode("utf-8"))
            except (ValueError, RecursionError):
                whole = None  # JSON Lines after all (or broken): line by line below
            if isinstance(whole, dict):
                yield name, whole
                return
            if isinstance(whole, list):
                for i, doc in enumerate(whole):
                    where = f"{name} item {i}"
                    yield where, doc if isinstance(doc, dict) else ImageInputError(_not_an_object(doc, where))
                return
    first = True
    for number, line in itertools.chain(head, lines):
        if _blank(line):
            continue
        where = f"{name} line {number}"
        doc = _decode_line(line, where, max_bytes)
        if first and overflow and isinstance(doc, ImageInputError):
            doc = ImageInputError(f"{doc} (a multi-line JSON document is read whole only up to {max_bytes} "
                                  "bytes; write one image per line)")
        first = False
        yield where, doc


def split_image_documents(
    text: str, source: str = "<input>", *, max_bytes: int = MAX_DOCUMENT_BYTES
) -> Iterator[tuple[str, Any]]:
    """The image documents of a file's text, each as ``(where, document or ImageInputError)``.

    The same reading as :func:`read_image_documents`, over text already in memory.

    Examples
    --------
    >>> [(w, d if isinstance(d, dict) else str(d)) for w, d in split_image_documents('{"a": 1}\\n{oops\\n', "f")]
    [('f line 1', {'a': 1}), ('f line 2', 'f line 2: malformed JSON: Expecting property name enclosed in \
double quotes (column 2)')]
    """
    return _documents(io.BytesIO(text.encode("utf-8", "surrogatepass")), source, max_bytes)


def _closing(documents: Iterator[tuple[str, Any]], stream: BinaryIO) -> Iterator[tuple[str, Any]]:
    try:
        yield from documents
    finally:
        stream.close()


def read_image_documents(
    path: str | Path, *, max_bytes: int = MAX_DOCUMENT_BYTES
) -> Iterator[tuple[str, Any]]:
    """Stream the image documents of a file (``-`` for stdin), each as ``(where, document or ImageInputError)``.

    The file is read line by line as the documents are asked for (a pipe is answered line by line),
    so memory does not grow with the file:

    * JSON Lines: each non-blank line is one document, ``where`` is ``"FILE line N"``.  Lines are split
      on ``\\n`` only (a ``\\r`` before it and a byte-order mark at the start are dropped), so a
      U+2028, U+0085, form feed or lone ``\\r`` inside a line never splits it.  Blank lines (spaces,
      tabs) are skipped: the documents are the non-blank lines, in order.
    * Each line is decoded on its own: a line that is not UTF-8, not JSON, JSON but not an object, or
      longer than ``max_bytes``, comes as an :class:`ImageInputError` in its place (its message names
      the file and line) and the other lines are still read.
    * A file whose first non-blank line opens a JSON object or array that it does not close (a
      pretty-printed document) is read whole, up to ``max_bytes``, and if it is one JSON object it
      is one document (``where`` is ``"FILE"``), if an array each item is one (``"FILE item I"``).
      Otherwise, or past ``max_bytes``, it is read as JSON Lines.  (Such a file on a pipe is answered
      once it ends; JSON Lines are answered as they arrive.)

    Parameters
    ----------
    path : str or Path
        The file, or ``"-"`` for standard input.
    max_bytes : int
        The longest document read (a line, or a multi-line document); default 16 MiB, which holds
        :data:`MAX_OBJECTS` objects many times over.

    Returns
    -------
    iterator of (str, dict or ImageInputError)
        Lazy: the file is opened now and read as the iterator is consumed, and closed when it is
        exhausted.

    Raises
    ------
    MapdbIOError
        If the file is missing or unreadable (when called, or while reading).
    """
    if str(path) == "-":
        return _documents(sys.stdin.buffer, "<stdin>", max_bytes)
    name = str(path)
    with reading(name, "images file"):
        stream = open(path, "rb")  # noqa: SIM115 - closed by _closing when the documents are consumed
    return _closing(_documents(stream, name, max_bytes), stream)
