"""COCO detector output -> query documents, one per COCO image.

What most detection and instance-segmentation models emit: a COCO dict (``{"images": [{"id", "width",
"height"}, ...], "annotations": [...], "categories": [{"id", "name"}, ...]}``), or a bare list of
result annotations together with the images they refer to.  Each annotation is one object:

* instance polygons (``"segmentation": [[x1, y1, x2, y2, ...], ...]``): the exact area centroid and area
  of its polygons clipped to the image (no rasterising), in time linear in their vertices (at most
  :data:`MAX_POLYGON_VERTICES` an annotation): parts are summed, which is their union when they do not
  overlap; a self-crossing polygon counts each point by its winding number (refused if its centroid so
  falls outside it);
* RLE masks (``"segmentation": {"size": [h, w], "counts": ...}``, uncompressed counts or COCO's
  compressed string; decoded here, pycocotools is not needed): the centroid of its pixels, as
  :func:`mapdb.detections.masks.from_mask` would give for that instance alone;
* boxes only (``"bbox": [x, y, w, h]``): the centre of the box, with ``"box": true``.

Coordinates follow the schema (x right, y down, (0, 0) the top-left corner of the image).  Objects
carry ``area_px``, ``border`` and ``bbox`` as masks' objects do; a polygon or box is on the border when
it comes within :data:`BORDER_PX` of an edge (contour tracers put a border pixel's vertex at 0 or
``width - 1``).  Categories are labelled through the class table by id, then by name; the others are
skipped and counted per category in ``skipped_classes``.  Annotations below ``min_score`` are
skipped and counted in ``skipped_low_score``.  An annotation whose ``image_id`` is not one of the
images, an RLE whose size is not its image's, or any malformed field is an error naming the file and
the annotation.
"""

from __future__ import annotations

import json
import math
import os
import stat
from collections import Counter
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import ImageInputError, MapdbIOError, reading
from .masks import DEFAULT_MIN_AREA_PX, MAX_MASK_PIXELS, camera_fields, finish_document, object_records

__all__ = ["BORDER_PX", "MAX_COCO_BYTES", "MAX_POLYGON_VERTICES", "MAX_RLE_COUNTS", "decode_rle", "encode_rle",
           "from_coco", "read_coco"]

BORDER_PX = 1.0
# COCO's validation annotations take 20 MB; a detector's output for a flight is smaller.  JSON makes up to 6
# times its size of Python objects (a file of zeros: 1.6 GB for 256 MiB), so the cap keeps a COCO file under a
# gigabyte (``python benchmarks/mask_limits.py coco-zeros``).
MAX_COCO_BYTES = 128 << 20
# Vertices of one annotation's polygons (all its parts): a detector's instance outline has tens to thousands.
# Their area and centroid cost time linear in the vertices (about 0.1 s a million,
# ``python benchmarks/mask_limits.py``); the cap bounds the memory of one annotation's arrays.
MAX_POLYGON_VERTICES = 1_000_000
# Counts of an RLE mask (a list's numbers, a compressed string's characters): an instance mask has thousands.
# Decoding takes about 53 bytes a character (traced: 106 MB for 2 M characters), about 210 MB at the cap.
MAX_RLE_COUNTS = 4_000_000
# A compressed RLE count of more chars than this does not fit in 64 bits.
_MAX_RLE_CHARS = 11


def read_coco(path: str | os.PathLike[str]) -> Any:
    """The decoded JSON of a COCO file, or a one-line error (missing, not a regular file, too big, not JSON)."""
    with reading(os.fspath(path), "COCO file"):
        if not stat.S_ISREG(os.stat(path).st_mode) and not os.path.isdir(path):
            # Checked before opening: reading a FIFO would wait for a writer forever, a device never end.
            raise MapdbIOError(f"{path}: not a regular file")
        with open(path, "rb") as f:
            data = f.read(MAX_COCO_BYTES + 1)
    if len(data) > MAX_COCO_BYTES:
        raise ImageInputError(f"{path}: more than {MAX_COCO_BYTES >> 20} MiB; split the COCO file")
    try:
        return json.loads(data)
    except (ValueError, RecursionError) as exc:
        raise ImageInputError(f"{path}: not a JSON file ({' '.join(str(exc).split())[:120]})") from None


def decode_rle(counts: str) -> np.ndarray:
    """COCO's compressed RLE string -> run lengths (pycocotools' ``rleFrString``).

    Each count is written 5 bits a character (offset 48), low bits first, ``0x20`` marking that more
    follow and ``0x10`` the sign of the last; from the fourth on, counts are stored as the difference
    from the count two before.

    Examples
    --------
    >>> decode_rle("52203").tolist()
    [5, 2, 2, 2, 5]
    >>> decode_rle(encode_rle(np.eye(3, dtype=bool))["counts"]).tolist()
    [0, 1, 3, 1, 3, 1]
    """
    c = np.frombuffer(counts.encode("ascii", "replace"), np.uint8).astype(np.int64) - 48
    if c.size == 0:
        return np.zeros(0, np.int64)
    if ((c < 0) | (c > 63)).any():
        raise ValueError("characters outside COCO's RLE alphabet")
    last = (c & 0x20) == 0
    if not last[-1]:
        raise ValueError("the last count is cut short")
    starts = np.flatnonzero(np.r_[True, last[:-1]])
    position = np.arange(c.size) - np.repeat(starts, np.diff(np.r_[starts, c.size]))
    if position.max() >= _MAX_RLE_CHARS:
        raise ValueError("a count too long for 64 bits")
    values = np.add.reduceat((c & 0x1F) << (5 * position), starts)
    ends = np.flatnonzero(last)
    negative = (c[ends] & 0x10) != 0
    values[negative] -= np.left_shift(1, 5 * (position[ends][negative] + 1))
    out = values.copy()
    out[1::2] = np.cumsum(values[1::2])   # count i (i > 2) adds count i - 2: two interleaved running sums
    out[2::2] = np.cumsum(values[2::2])
    return out


def encode_rle(mask: np.ndarray) -> dict[str, Any]:
    """A binary mask (H x W) -> COCO compressed RLE ``{"size": [H, W], "counts": str}`` (``rleToString``)."""
    flat = np.asarray(mask, bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.r_[0, change, flat.size]).tolist()
    if flat.size and flat[0]:
        runs = [0, *runs]
    out = []
    for i, run in enumerate(runs):
        x = run - runs[i - 2] if i > 2 else run
        more = True
        while more:
            ch = x & 0x1F
            x >>= 5
            more = x != -1 if ch & 0x10 else x != 0
            out.append(chr((ch | 0x20 if more else ch) + 48))
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": "".join(out)}


def _rle_object(counts: np.ndarray, height: int, width: int) -> tuple[float, float, int, list[int]] | None:
    """Pixel centroid, area and box of an RLE mask (column-major runs), without drawing it.

    Each run of ones is cut into its pieces within one column; memory follows the runs, not the pixels.
    """
    ends = np.cumsum(counts)
    start, stop = (ends - counts)[1::2], ends[1::2]
    start, stop = start[stop > start], stop[stop > start]
    if start.size == 0:
        return None
    first, last = start // height, (stop - 1) // height
    pieces = last - first + 1
    run = np.repeat(np.arange(start.size), pieces)
    col = first[run] + np.arange(run.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    r0 = np.maximum(start[run], col * height) - col * height
    r1 = np.minimum(stop[run], (col + 1) * height) - col * height
    n = r1 - r0
    area = int(n.sum())
    x = float((col * n).sum()) / area + 0.5
    y = float(((r0 + r1 - 1) * n).sum()) / (2 * area) + 0.5
    return x, y, area, [int(col.min()), int(r0.min()), int(col.max()) + 1, int(r1.max())]


def _edge_box(bounds: tuple[float, float, float, float], width: int, height: int) -> list[int]:
    """An integer box of continuous bounds; edges within BORDER_PX of the image's are put on them."""
    x0, y0, x1, y1 = bounds
    return [0 if x0 <= BORDER_PX else math.floor(x0), 0 if y0 <= BORDER_PX else math.floor(y0),
            width if x1 >= width - BORDER_PX else math.ceil(x1), height if y1 >= height - BORDER_PX else math.ceil(y1)]


def _clipped(xy: np.ndarray, axis: int, limit: float, keep_below: bool) -> np.ndarray:
    """The ring ``xy`` (n x 2, closing edge implied) clipped to one side of the line ``xy[:, axis] == limit``.

    Sutherland-Hodgman, vectorised: each edge gives its start if inside, then its crossing point if it
    crosses.  The clipped ring may run along the line (zero-area bridges), which no integral below sees.
    """
    if xy.shape[0] == 0:
        return xy
    side = (limit - xy[:, axis]) if keep_below else (xy[:, axis] - limit)
    inside = side >= 0
    if inside.all():  # the usual case: a polygon within the image is its own clip
        return xy
    nxt = np.roll(xy, -1, axis=0)
    inside_next = np.roll(inside, -1)
    crossing = inside != inside_next
    with np.errstate(invalid="ignore", divide="ignore"):  # edges along the line: their (unused) cut is NaN
        t = (limit - xy[:, axis]) / (nxt[:, axis] - xy[:, axis])
        cut = xy + t[:, None] * (nxt - xy)
    cut[:, axis] = limit
    points = np.stack([xy, cut], axis=1).reshape(-1, 2)
    return points[np.stack([inside, crossing], axis=1).ravel()]


def _ring_integrals(xy: np.ndarray, width: int, height: int) -> tuple[float, float, float]:
    """Area and first moments (x, y) of one ring clipped to the image, oriented to a positive area."""
    for axis, limit, below in ((0, 0.0, False), (0, float(width), True), (1, 0.0, False), (1, float(height), True)):
        xy = _clipped(xy, axis, limit, below)
    if xy.shape[0] < 3:
        return 0.0, 0.0, 0.0
    x, y = xy[:, 0], xy[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    area = float(cross.sum()) / 2.0
    mx, my = float(((x + x1) * cross).sum()) / 6.0, float(((y + y1) * cross).sum()) / 6.0
    sign = -1.0 if area < 0 else 1.0
    return sign * area, sign * mx, sign * my


def _ring_bounds(xy: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest x, y of a ring's part inside the image, in linear time.

    The clipped ring's vertices will not do: its bridges along one edge of the image, cut by the next, leave
    points the region does not reach.  The extremes are among the ring's vertices inside, its edges'
    crossings of the image's edges, and the image's corners inside the ring (even-odd rule).
    """
    size = np.array([width, height], np.float64)
    within = ((xy >= 0) & (xy <= size)).all(axis=1)
    if within.all():
        return xy.min(axis=0), xy.max(axis=0)
    found = [xy[within]]
    nxt = np.roll(xy, -1, axis=0)
    for axis in (0, 1):
        for limit in (0.0, size[axis]):
            a, b = xy[:, axis] - limit, nxt[:, axis] - limit
            crosses = (a * b <= 0) & (a != b)
            t = (a[crosses] / (a[crosses] - b[crosses]))[:, None]
            cut = xy[crosses] + t * (nxt[crosses] - xy[crosses])
            cut[:, axis] = limit
            found.append(cut[(cut[:, 1 - axis] >= 0) & (cut[:, 1 - axis] <= size[1 - axis])])
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
    for corner in corners:
        spans = (xy[:, 1] > corner[1]) != (nxt[:, 1] > corner[1])
        with np.errstate(invalid="ignore", divide="ignore"):
            at = xy[spans, 0] + (corner[1] - xy[spans, 1]) * (nxt[spans, 0] - xy[spans, 0]) / (
                nxt[spans, 1] - xy[spans, 1])
        if np.count_nonzero(corner[0] < at) % 2:
            found.append(corner[None])
    points = np.concatenate(found)
    return points.min(axis=0), points.max(axis=0)


def _polygon_object(parts: list[Any], width: int, height: int, where: str
                    ) -> tuple[float, float, float, list[int]] | None:
    """Area centroid, area and box of an annotation's polygons clipped to the image, in time linear in vertices.

    Each part is integrated by the shoelace formula after clipping: a simple polygon's exact area and
    centroid, whichever way it turns; parts are summed, which is their union's when they do not overlap.  A
    self-crossing part counts each point by its winding number (the two lobes of a figure eight cancel),
    and overlapping parts count their overlap twice; when that puts the centroid outside the polygon's
    bounds the annotation is refused.  No overlay is computed: its cost grows with the square of the
    crossings (GEOS took minutes to repair a polygon of 200 random vertices).
    """
    if not all(isinstance(part, list) for part in parts):
        raise ImageInputError(f"{where}.segmentation: must be a list of polygons, each a list of numbers")
    vertices = sum(len(part) for part in parts) // 2
    if vertices > MAX_POLYGON_VERTICES:
        raise ImageInputError(f"{where}.segmentation: {vertices:,} vertices, more than the {MAX_POLYGON_VERTICES:,} "
                              "a polygon annotation may have")
    area = mx = my = 0.0
    corners = []
    for part in parts:
        xy = _numbers(part, where + ".segmentation")
        if xy.size % 2 or xy.size < 6:
            raise ImageInputError(f"{where}.segmentation: a polygon needs x, y pairs, at least 3 of them")
        a, x, y = _ring_integrals(xy.reshape(-1, 2), width, height)
        if a > 0:
            area, mx, my = area + a, mx + x, my + y
            corners.append(_ring_bounds(xy.reshape(-1, 2), width, height))
    if area <= 0:
        return None
    low, high = np.min([c[0] for c in corners], axis=0), np.max([c[1] for c in corners], axis=0)
    x, y = mx / area, my / area
    if not (low[0] <= x <= high[0] and low[1] <= y <= high[1]):
        # Lobes of opposite turn cancel in the integrals: what is left is no region, and no place to report.
        raise ImageInputError(f"{where}.segmentation: a polygon crossing itself (its centroid by winding number "
                              "falls outside it); give simple polygons")
    bounds = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
    return x, y, area, _edge_box(bounds, width, height)


def _box_object(box: Any, width: int, height: int, where: str) -> tuple[float, float, float, list[int]] | None:
    b = _numbers(box, where + ".bbox")
    if b.size != 4 or b[2] < 0 or b[3] < 0:
        raise ImageInputError(f"{where}.bbox: must be [x, y, width, height] with width, height >= 0")
    x0, y0 = max(b[0], 0.0), max(b[1], 0.0)
    x1, y1 = min(b[0] + b[2], width), min(b[1] + b[3], height)
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) * (y1 - y0), _edge_box((x0, y0, x1, y1), width, height)


def _numbers(value: Any, where: str) -> np.ndarray:
    if not isinstance(value, list) or not set(map(type, value)) <= {int, float}:
        raise ImageInputError(f"{where}: must be a list of numbers")
    out = np.asarray(value, np.float64)
    if not np.isfinite(out).all():
        raise ImageInputError(f"{where}: numbers must be finite")
    return out


def _rle_counts(segmentation: dict[str, Any], width: int, height: int, where: str) -> np.ndarray:
    size, counts = segmentation.get("size"), segmentation.get("counts")
    if size != [height, width]:
        raise ImageInputError(f"{where}.segmentation.size: {size!r} disagrees with its image's height and width "
                              f"[{height}, {width}]")
    if isinstance(counts, str | list) and len(counts) > MAX_RLE_COUNTS:
        raise ImageInputError(f"{where}.segmentation.counts: {len(counts):,} counts or characters, more than the "
                              f"{MAX_RLE_COUNTS:,} an RLE mask may have")
    if isinstance(counts, str):
        try:
            runs = decode_rle(counts)
        except ValueError as exc:
            raise ImageInputError(f"{where}.segmentation.counts: not COCO's compressed RLE ({exc})") from None
    elif isinstance(counts, list) and all(type(v) is int for v in counts):
        runs = np.asarray(counts, np.int64) if counts else np.zeros(0, np.int64)
    else:
        raise ImageInputError(f"{where}.segmentation.counts: must be a list of integers or a compressed string")
    if (runs < 0).any() or int(runs.sum()) != width * height:
        raise ImageInputError(f"{where}.segmentation.counts: runs must be >= 0 and sum to {width}x{height} pixels")
    return runs


def _annotation_object(ann: dict[str, Any], width: int, height: int, where: str
                       ) -> tuple[tuple[float, float, float, list[int]] | None, bool]:
    """The object of one annotation (None if it covers nothing inside the image), and whether it is a box."""
    seg = ann.get("segmentation")
    if isinstance(seg, dict):
        return _rle_object(_rle_counts(seg, width, height, where), height, width), False
    if isinstance(seg, list) and seg:
        return _polygon_object(seg, width, height, where), False
    if "bbox" not in ann:
        raise ImageInputError(f"{where}: no segmentation and no bbox")
    return _box_object(ann["bbox"], width, height, where), True


def _images(images: Any, source: str) -> dict[Any, dict[str, Any]]:
    """The images by id, checked (ids unique, sizes whole numbers within the schema's range)."""
    if not isinstance(images, list):
        raise ImageInputError(f"{source}: images: must be a list of {{id, width, height}}")
    out: dict[Any, dict[str, Any]] = {}
    for i, im in enumerate(images):
        where = f"{source}: images[{i}]"
        if not isinstance(im, dict) or type(im.get("id")) not in (int, str):
            raise ImageInputError(f"{where}: must be an object with an integer or string id")
        w, h = im.get("width"), im.get("height")
        if type(w) is not int or type(h) is not int or not (0 < w and 0 < h and w * h <= MAX_MASK_PIXELS):
            raise ImageInputError(f"{where}: width and height must be positive integers (at most "
                                  f"{MAX_MASK_PIXELS:,} pixels)")
        if im["id"] in out:
            raise ImageInputError(f"{where}: id {im['id']!r} given twice")
        out[im["id"]] = im
    return out


def _category_names(doc: Any) -> dict[Any, str]:
    cats = doc.get("categories", []) if isinstance(doc, dict) else []
    return {c["id"]: str(c["name"]) for c in cats if isinstance(c, dict) and "id" in c and "name" in c}


def _label(category: Any, names: dict[Any, str], classes: Mapping[Any, str]) -> tuple[str | None, str]:
    """The label of a category (by id, its text, then its name), and the key it is counted under if skipped."""
    name = names.get(category)
    for key in (category, str(category), name):
        if key is not None and key in classes:
            return classes[key], str(category)
    return None, name or str(category)


def _parts(doc_or_path: Any, images: Any, source: str | None) -> tuple[str, Any, Any, dict[Any, str]]:
    """The source name, the annotations, the images and the category names of a COCO input."""
    if isinstance(doc_or_path, str | os.PathLike):
        source = source or str(doc_or_path)
        doc = read_coco(doc_or_path)
    else:
        source, doc = source or "<coco>", doc_or_path
    if isinstance(images, str | os.PathLike):
        images = read_coco(images)
    if isinstance(images, dict):
        images = images.get("images")
    if isinstance(doc, dict):
        annotations = doc.get("annotations")
        images = doc.get("images") if images is None else images
    else:
        annotations = doc
    if not isinstance(annotations, list):
        raise ImageInputError(f"{source}: not COCO: expected a dict with 'images' and 'annotations', or a list of "
                              "detections")
    if images is None:
        raise ImageInputError(f"{source}: a list of detections names no image sizes; give the images "
                              "(a COCO file with 'images')")
    return source, annotations, images, _category_names(doc)


def from_coco(doc_or_path: Any, classes: Mapping[Any, str], *, images: Any = None,
              min_area: float = DEFAULT_MIN_AREA_PX, min_score: float = 0.0, fov_deg: float | None = None,
              attitude: tuple[float, float] | None = None, altitude: float | None = None,
              source: str | None = None) -> list[dict[str, Any]]:
    """COCO detections -> one query document per COCO image (module docs), in the order of its images.

    Parameters
    ----------
    doc_or_path : dict, list or path-like
        A COCO dict (``images``, ``annotations``, optional ``categories``), a list of result
        annotations, or the file holding either.
    classes : mapping
        Category id (int or its text) or category name -> mapdb label.
    images : list, dict or path-like, optional
        The images (``{"id", "width", "height"}``) when ``doc_or_path`` is a bare list of detections: the
        list itself, or a COCO dict or file whose ``images`` are used.  Given with a COCO dict, it
        replaces the dict's images.
    min_area, min_score
        Objects smaller (pixels) or less confident (the annotation's ``score``, when it has one) are dropped.
    fov_deg, attitude, altitude
        Written into every document, as :func:`mapdb.detections.masks.from_mask` does.

    Raises
    ------
    ImageInputError
        One line naming the file and the annotation or image at fault.

    Examples
    --------
    >>> coco = {"images": [{"id": 7, "width": 100, "height": 80}],
    ...         "categories": [{"id": 1, "name": "house"}, {"id": 2, "name": "car"}],
    ...         "annotations": [{"image_id": 7, "category_id": 1, "segmentation": [[10, 10, 30, 10, 30, 20, 10, 20]]},
    ...                         {"image_id": 7, "category_id": 1, "bbox": [90, 60, 10, 20]},
    ...                         {"image_id": 7, "category_id": 2, "bbox": [0, 0, 4, 4]}]}
    >>> (doc,) = from_coco(coco, {"house": "building"})
    >>> [(o["x"], o["y"], o["area_px"], o["border"], o.get("box", False)) for o in doc["objects"]]
    [(20.0, 15.0, 200.0, False, False), (95.0, 70.0, 200.0, True, True)]
    >>> doc["id"], doc["skipped_classes"]
    (7, {'car': 1})
    """
    source, annotations, images, names = _parts(doc_or_path, images, source)
    by_id = _images(images, source)
    found: dict[Any, list[tuple[str, tuple[float, float, float, list[int]], bool]]] = {k: [] for k in by_id}
    skipped: dict[Any, Counter[str]] = {k: Counter() for k in by_id}
    low: Counter[Any] = Counter()
    for i, ann in enumerate(annotations):
        where = f"{source}: annotations[{i}]"
        if not isinstance(ann, dict):
            raise ImageInputError(f"{where}: must be an object")
        image_id = ann.get("image_id")
        if type(image_id) not in (int, str) or image_id not in by_id:
            raise ImageInputError(f"{where}: image_id {image_id!r} is not one of the file's images")
        score = ann.get("score", math.inf)
        if type(score) not in (int, float) or math.isnan(score):
            raise ImageInputError(f"{where}.score: must be a number")
        label, key = _label(ann.get("category_id"), names, classes)
        if label is None:
            skipped[image_id][key] += 1
            continue
        if score < min_score:
            low[image_id] += 1
            continue
        im = by_id[image_id]
        obj, is_box = _annotation_object(ann, im["width"], im["height"], where)
        if obj is not None and obj[2] >= min_area and obj[2] > 0:
            found[image_id].append((label, obj, is_box))
    extra = camera_fields(fov_deg, attitude, altitude)
    return [_document(im, found[k], skipped[k], low[k], extra, f"{source}: image {k!r}") for k, im in by_id.items()]


def _document(image: dict[str, Any], found: list[tuple[str, tuple[float, float, float, list[int]], bool]],
              skipped: Counter[str], low: int, extra: dict[str, Any], where: str) -> dict[str, Any]:
    width, height = image["width"], image["height"]
    xs, ys, areas = (np.array([f[1][k] for f in found], np.float64) for k in range(3))
    bbox = np.array([f[1][3] for f in found], np.int64).reshape(-1, 4)
    # Polygon and box areas are exact, not pixel counts: kept to 0.01 px.
    objects = object_records([f[0] for f in found], xs, ys, np.round(areas, 2), bbox, width, height)
    for o, f in zip(objects, found, strict=True):
        if f[2]:
            o["box"] = True
    doc = {"id": image["id"], "width": width, "height": height, "objects": objects, **extra,
           "skipped_classes": dict(sorted(skipped.items())), "skipped_low_score": low}
    if "file_name" in image:
        doc["file_name"] = image["file_name"]
    return finish_document(doc, where)
