"""Segmentation masks to image objects: the "image processing" block of the paper's Fig. 1.

A label image (one class code per pixel) becomes a query document (``mapdb/data/image.schema.json``):
each connected region of one class (4- or 8-connected) of at least ``min_area`` pixels is one object
at the centroid of its pixels, labelled through a class table.  Pixels follow the schema: x to the
right, y down, (0, 0) the top-left corner of the top-left pixel, so the centroid of the single pixel
at column ``c``, row ``r`` is ``(c + 0.5, r + 0.5)``.  Each object also carries what a matcher can use
beyond its position: ``area_px`` (its pixel count), ``border`` (whether it touches the image's edge,
so that part of it may lie outside and its centroid is pulled inward), ``bbox`` ``[x0, y0, x1, y1]``
(pixel edges: the region covers columns ``x0 .. x1 - 1`` and rows ``y0 .. y1 - 1``), and the major axis of
its pixels' second moments (each pixel a unit square): ``orientation_deg``, counter-clockwise from the x axis
with y up, in [0, 180), and ``elongation``, the square root of the larger over the smaller moment.  A whole
building's blob keeps its footprint's axis within a few degrees, relief and all
(``python benchmarks/blob_shapes.py``): evidence for a map that stores footprints' axes.

Regions of different classes are found separately, so two touching objects of different classes stay
two objects; touching objects of one class are one region, as a segmentation model sees them.  Code 0
is the background unless the class table maps it; other codes the table does not map are skipped and
their pixels counted in the document's ``skipped_classes`` (``{"7": 1234}``).

Everything is vectorised (``scipy.ndimage.label`` per class into int32 labels, then ``numpy.bincount`` over
the runs of each label along the rows, a strip of rows at a time, and ``ndimage.find_objects`` for the
boxes of the regions kept): a 4000x3000 mask of three classes with about 500 objects takes a few tenths of
a second (``python benchmarks/objects_mask.py``).  Memory is the pixels, one boolean image and the labels
(about 6 bytes a pixel for a mask of bytes) plus one strip's work: a 10000x10000 mask of one region, or of
25 M specks, stays under 800 MB (``python benchmarks/mask_limits.py``).  Regions beyond the
:data:`~mapdb.detections.images.MAX_OBJECTS` a query accepts are only counted, never measured.

Masks are read from PNG or GeoTIFF (anything GDAL reads, :func:`read_mask`), strictly
(:mod:`mapdb.detections.mask_files`: regular files only, whole or refused); a mask with a plausible
georeference also gives the ground position of its centre (the document's ``georef``, which the
query ignores and a test can compare with the answer).  COCO detector output is read by
:mod:`mapdb.detections.coco`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ImageInputError, reading
from .images import MAX_ELONGATION, MAX_IMAGE_SIDE_PX, MAX_OBJECTS, parse_image
from .mask_files import check_png_chunks, check_regular_file, georef, strict_gdal

__all__ = [
    "DEFAULT_MIN_AREA_PX",
    "MAX_MASK_BYTES",
    "MAX_MASK_PIXELS",
    "Mask",
    "camera_fields",
    "from_mask",
    "major_axes",
    "mask_document",
    "read_mask",
]

# Smaller regions are specks of segmentation noise, not objects a map holds.
DEFAULT_MIN_AREA_PX = 4
# A mask is held whole (regions cross any tiling): its pixels, a boolean image of one class and int32 labels,
# 6 bytes a pixel for a mask of bytes (``python benchmarks/mask_limits.py``).  A file claiming more pixels, or
# more bytes of pixels (a PNG or GeoTIFF header is a few bytes), is refused before any pixel is read.
MAX_MASK_PIXELS = 100_000_000
MAX_MASK_BYTES = 200 << 20
# Codes spanning less than this are counted with one bincount; wider ones with a sort.
_BINCOUNT_SPAN = 1 << 20
_CHUNK = 1 << 18


def _structure(connectivity: int) -> np.ndarray:
    if connectivity == 4:
        return np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)
    if connectivity == 8:
        return np.ones((3, 3), bool)
    raise ValueError(f"connectivity must be 4 or 8, not {connectivity!r}")


def _checked_mask(mask: Any, source: str) -> np.ndarray:
    """A 2-D integer array (booleans and integral floats accepted), or a one-line ImageInputError.

    Floats are checked a strip at a time and cast to the narrowest integer type that holds their range: a
    float mask costs no 64-bit copy of itself.
    """
    array = np.asarray(mask)
    if array.ndim != 2:
        raise ImageInputError(f"{source}: a mask must be a 2-D image, got {array.ndim} dimensions {array.shape}")
    height, width = array.shape
    if not (1 <= width <= MAX_IMAGE_SIDE_PX and 1 <= height <= MAX_IMAGE_SIDE_PX):
        raise ImageInputError(f"{source}: a {width}x{height} mask; each side must be 1 to {MAX_IMAGE_SIDE_PX} px")
    if array.dtype == bool:
        return array.view(np.uint8)
    if array.dtype.kind == "f":
        flat = array.ravel()
        for start in range(0, flat.size, _CHUNK):
            chunk = flat[start:start + _CHUNK]
            if not (np.isfinite(chunk).all() and (chunk == np.round(chunk)).all()):
                raise ImageInputError(f"{source}: pixels are not whole numbers; a mask holds integer class codes")
        low, high = float(array.min()), float(array.max())
        if not -2.0 ** 63 <= low <= high < 2.0 ** 63:
            raise ImageInputError(f"{source}: class codes beyond 64-bit integers")
        narrow = np.result_type(np.min_scalar_type(int(low)), np.min_scalar_type(int(high)))
        return array.astype(narrow if narrow.kind in "iu" else np.int64)
    if array.dtype.kind not in "iu":
        raise ImageInputError(f"{source}: pixels of type {array.dtype}; a mask holds integer class codes")
    return array


def _code_counts(array: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The codes present in the mask and their pixel counts, ascending."""
    low, high = int(array.min()), int(array.max())
    if high - low >= _BINCOUNT_SPAN:
        return np.unique(array, return_counts=True)
    flat = array.ravel()
    counts = np.zeros(high - low + 1, np.int64)
    # In chunks: bincount copies its input to 64-bit integers, 8 times a uint8 mask's memory at once.
    for start in range(0, flat.size, _CHUNK):
        chunk = flat[start:start + _CHUNK]
        counts += np.bincount(np.subtract(chunk, low, dtype=np.int64) if low else chunk, minlength=counts.size)
    present = np.flatnonzero(counts)
    return present + low, counts[present]


def _strips(shape: tuple[int, ...]) -> Iterator[slice]:
    """Row slices of about ``_CHUNK`` pixels each: what the region sums hold at once."""
    rows = max(1, _CHUNK // max(shape[1], 1))
    for start in range(0, shape[0], rows):
        yield slice(start, start + rows)


def _runs(block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The runs of one label along the rows of ``block`` (2-D labels), background left out: label, row, first
    column and column past the last of each.

    A region of a mask is a few runs a row, so the sums below cost the runs, not the pixels.
    """
    flat = block.ravel()
    change = np.empty(flat.size, bool)
    change[0] = True
    np.not_equal(flat[1:], flat[:-1], out=change[1:])
    change[::block.shape[1]] = True  # a run ends with its row
    starts = np.flatnonzero(change)
    ends = np.empty_like(starts)
    ends[:-1], ends[-1] = starts[1:], flat.size
    ids = flat[starts]
    labelled = ids != 0
    starts, ends, ids = starts[labelled], ends[labelled], ids[labelled]
    row = starts // block.shape[1]
    return ids, row, starts - row * block.shape[1], ends - row * block.shape[1]


def _label_areas(labelled: np.ndarray, n: int) -> np.ndarray:
    """Pixel count of each label 1..n (index 0 unused), from the runs of a strip at a time.

    A strip's labels usually span a narrow range (labels are numbered in raster order), counted with one
    bincount over that range; a strip whose labels span far more than its runs (a region that started
    long before, beside many new small ones) is counted with ``np.add.at``, so no strip costs O(n).
    """
    # 4 bytes a label while no region can hold 2**31 pixels: the count of 25 M specks takes 100 MB, not 200.
    area: np.ndarray = np.zeros(n + 1, np.int32 if labelled.size < 2**31 else np.int64)
    for rows in _strips(labelled.shape):
        ids, _, first, stop = _runs(labelled[rows])
        if ids.size == 0:
            continue
        low, high = int(ids.min()), int(ids.max())
        if high - low <= 4 * ids.size:
            area[low:high + 1] += np.bincount(ids - low, weights=stop - first, minlength=high - low + 1).astype(
                area.dtype)
        else:
            np.add.at(area, ids, (stop - first).astype(area.dtype))
    return area


def _moments(labelled: np.ndarray, k: int) -> tuple[np.ndarray, ...]:
    """Sums over each label 1..k of 1, x, y, x*x, y*y and x*y (pixel column and row), a strip at a time.

    Each run of columns ``a .. b - 1`` adds its closed forms (``(b - a) (a + b - 1) / 2`` for x, differences
    of ``m (m + 1) (2m + 1) / 6`` for x*x).  The sums are of whole numbers, exact in float64 below 2**53
    whatever their order: they are the bits a sum over the pixels one by one gives.
    """
    sums = np.zeros((6, k + 1))
    for rows in _strips(labelled.shape):
        ids, row, first, stop = _runs(labelled[rows])
        if ids.size == 0:
            continue
        row += rows.start
        count = stop - first
        sx = count * (first + stop - 1) // 2
        sxx = _squares(stop - 1) - _squares(first - 1)
        for i, weights in enumerate((count, sx, row * count, sxx, row * row * count, row * sx)):
            sums[i] += np.bincount(ids, weights=weights, minlength=k + 1)
    return tuple(sums[:, 1:])


def _squares(m: np.ndarray) -> np.ndarray:
    """0**2 + 1**2 + ... + m**2, for m >= -1 (0 for -1 and 0)."""
    return m * (m + 1) * (2 * m + 1) // 6


def _regions(binary: np.ndarray, structure: np.ndarray, min_area: int, room: int) -> dict[str, np.ndarray]:
    """Pixel centroid, area and box of each connected region of ``binary`` with at least ``min_area`` pixels.

    Memory is the int32 labels (4 bytes a pixel) and sums a strip of pixels at a time, so a mask of
    :data:`MAX_MASK_PIXELS` fits in well under a gigabyte.  If more than ``room`` regions are kept, only their
    number is returned (``{"count": ...}``): the caller refuses the mask, and nothing is spent on them.
    """
    from scipy import ndimage

    labelled = np.empty(binary.shape, np.int32)
    n = int(ndimage.label(binary, structure=structure, output=labelled))
    keep = _label_areas(labelled, n) >= max(min_area, 1)
    keep[0] = False
    k = int(np.count_nonzero(keep))
    if k > room:
        return {"count": np.array(k)}
    # Kept regions renumbered 1..k in their order (dropped ones to 0), in place, a strip at a time.
    renumber = np.zeros(n + 1, np.int32)
    renumber[keep] = np.arange(1, k + 1, dtype=np.int32)
    for rows in _strips(labelled.shape):
        labelled[rows] = renumber[labelled[rows]]
    del renumber, keep
    area, sx, sy, sxx, syy, sxy = _moments(labelled, k)
    with np.errstate(invalid="ignore", divide="ignore"):
        cx, cy = sx / area, sy / area
        # Second moments about the centroid, each pixel a unit square (its own 1/12 added): a one-pixel line
        # has a finite elongation.
        orientation, elongation = major_axes(sxx / area - cx * cx + 1.0 / 12.0, syy / area - cy * cy + 1.0 / 12.0,
                                             sxy / area - cx * cy)
    # find_objects scans the labels once in C; with the dropped regions at 0 it lists only the k kept.
    bbox = np.array([(b[1].start, b[0].start, b[1].stop, b[0].stop) for b in ndimage.find_objects(labelled, k)],
                    dtype=np.int64).reshape(-1, 4)
    return {"x": cx + 0.5, "y": cy + 0.5, "area": area.astype(np.int64), "bbox": bbox,
            "orientation": orientation, "elongation": elongation, "count": np.array(k)}


def major_axes(sxx: np.ndarray, syy: np.ndarray, sxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Major axis (degrees in [0, 180), counter-clockwise from the image's x axis with y *up*) and elongation
    (square root of the larger over the smaller eigenvalue, >= 1) of second moments given with y *down*,
    as pixel rows count.

    Examples
    --------
    >>> major_axes(np.array([4.0, 1.0, 2.5]), np.array([1.0, 4.0, 2.5]), np.array([0.0, 0.0, 1.5]))
    (array([  0.,  90., 135.]), array([2., 2., 2.]))
    """
    half_trace = (sxx + syy) / 2.0
    root = np.sqrt(np.maximum(((sxx - syy) / 2.0) ** 2 + sxy * sxy, 0.0))
    # Rows grow downward, so an axis turning toward larger rows turns clockwise as seen: the angle's sign flips.
    orientation = np.degrees(0.5 * np.arctan2(-2.0 * sxy, sxx - syy)) % 180.0
    with np.errstate(invalid="ignore", divide="ignore"):
        elongation = np.sqrt((half_trace + root) / (half_trace - root))
    return orientation, elongation


def camera_fields(fov_deg: float | None = None, attitude: tuple[float, float] | None = None,
                  altitude: float | None = None) -> dict[str, Any]:
    """The query document's optional camera keys: ``camera.fov_deg``, ``attitude`` (roll, pitch), ``altitude_m``.

    Examples
    --------
    >>> camera_fields(60.0, (1.5, -2.0))
    {'camera': {'fov_deg': 60.0}, 'attitude': {'roll_deg': 1.5, 'pitch_deg': -2.0}}
    """
    out: dict[str, Any] = {}
    if fov_deg is not None:
        out["camera"] = {"fov_deg": float(fov_deg)}
    if attitude is not None:
        roll, pitch = attitude
        out["attitude"] = {"roll_deg": float(roll), "pitch_deg": float(pitch)}
    if altitude is not None:
        out["altitude_m"] = float(altitude)
    return out


def object_records(labels: list[str], x: np.ndarray, y: np.ndarray, area: np.ndarray, bbox: np.ndarray,
                   width: int, height: int, orientation: np.ndarray | None = None,
                   elongation: np.ndarray | None = None) -> list[dict[str, Any]]:
    """The documents' ``objects`` entries; ``border`` when the box reaches an edge of the image, and the major
    axis (``orientation_deg``, ``elongation``) when given."""
    border = (bbox[:, 0] <= 0) | (bbox[:, 1] <= 0) | (bbox[:, 2] >= width) | (bbox[:, 3] >= height)
    records = [
        {"label": label, "x": xi, "y": yi, "area_px": a, "border": b, "bbox": box}
        for label, xi, yi, a, b, box in zip(labels, np.round(x, 3).tolist(), np.round(y, 3).tolist(),
                                            area.tolist(), border.tolist(), bbox.tolist(), strict=True)
    ]
    if orientation is not None and elongation is not None:
        # Rounding may carry 179.96 to 180.0, outside [0, 180): the same axis as 0.
        turned = np.round(orientation, 1) % 180.0
        stretched = np.clip(np.round(elongation, 3), 1.0, MAX_ELONGATION)
        for record, o, e in zip(records, turned.tolist(), stretched.tolist(), strict=True):
            record["orientation_deg"], record["elongation"] = o, e
    return records


def finish_document(doc: dict[str, Any], source: str) -> dict[str, Any]:
    """``doc`` once it is checked as ``mapdb query`` checks it (so that no written document is rejected)."""
    if len(doc["objects"]) > MAX_OBJECTS:
        raise ImageInputError(f"{source}: {len(doc['objects'])} objects, more than the {MAX_OBJECTS} a query "
                              "accepts; raise the minimum area")
    parse_image(doc, source)
    return doc


def from_mask(mask: np.ndarray, classes: Mapping[int, str], *, connectivity: int = 8,
              min_area: int = DEFAULT_MIN_AREA_PX, image_id: str | int | None = None, fov_deg: float | None = None,
              attitude: tuple[float, float] | None = None, altitude: float | None = None,
              source: str = "<mask>") -> dict[str, Any]:
    """A label image (H x W integer array, one class code per pixel) -> a query document (module docs).

    Parameters
    ----------
    mask : ndarray
        2-D integer array (booleans, and floats holding whole numbers, are accepted).
    classes : mapping of int to str
        Class code -> mapdb label.  Code 0 is the background unless mapped here.
    connectivity : {4, 8}
        Pixels touching by an edge (4) or also by a corner (8) belong to one region.
    min_area : int
        Smaller regions (pixels) are dropped.
    image_id, fov_deg, attitude, altitude
        Written as the document's ``id``, ``camera.fov_deg``, ``attitude`` (roll, pitch in degrees) and
        ``altitude_m`` (those not given are left out).
    source : str
        Names the mask in error messages.

    Returns
    -------
    dict
        ``{"id", "width", "height", "objects": [{"label", "x", "y", "area_px", "border", "bbox"}, ...],
        "skipped_classes": {code: pixels}}`` plus the camera keys given; it passes
        :func:`mapdb.detections.images.parse_image`.

    Raises
    ------
    ImageInputError
        Not a 2-D integer image, a side out of range, a camera value out of the schema's range, or more
        objects than a query accepts.

    Examples
    --------
    >>> m = np.zeros((4, 6), np.uint8); m[0:2, 0:2] = 1; m[2:4, 3:6] = 2; m[3, 0] = 9
    >>> doc = from_mask(m, {1: "building", 2: "water"}, min_area=1, image_id="a")
    >>> [(o["label"], o["x"], o["y"], o["area_px"], o["border"], o["bbox"]) for o in doc["objects"]]
    [('building', 1.0, 1.0, 4, True, [0, 0, 2, 2]), ('water', 4.5, 3.0, 6, True, [3, 2, 6, 4])]
    >>> doc["skipped_classes"], doc["width"], doc["height"]
    ({'9': 1}, 6, 4)
    """
    array = _checked_mask(mask, source)
    structure = _structure(connectivity)
    height, width = array.shape
    labels: list[str] = []
    found: list[dict[str, np.ndarray]] = []
    skipped: dict[str, int] = {}
    codes, counts = _code_counts(array)
    present = set(codes.tolist())
    n_objects = 0
    for code, count in zip(codes.tolist(), counts.tolist(), strict=True):
        if code in classes:
            # A mask holding only this code (and background) is its own binary image: no copy of it.
            binary = array if present <= {0, code} else array == code
            regions = _regions(binary, structure, min_area, room=MAX_OBJECTS - n_objects)
            del binary
            n_objects += int(regions["count"])
            if n_objects <= MAX_OBJECTS:
                found.append(regions)
                labels += [classes[code]] * regions["x"].size
        elif code != 0:
            skipped[str(code)] = count
    if n_objects > MAX_OBJECTS:
        # The regions of the other classes were only counted: the message says how many there are.
        raise ImageInputError(f"{source}: {n_objects} objects, more than the {MAX_OBJECTS} a query accepts; "
                              "raise the minimum area")
    x, y, area, bbox, orientation, elongation = (
        np.concatenate([r[k] for r in found]) if found else np.zeros((0, 4) if k == "bbox" else 0)
        for k in ("x", "y", "area", "bbox", "orientation", "elongation"))
    doc: dict[str, Any] = {"id": image_id, "width": width, "height": height,
                           "objects": object_records(labels, x, y, area.astype(np.int64), bbox.astype(np.int64),
                                                     width, height, orientation, elongation),
                           **camera_fields(fov_deg, attitude, altitude), "skipped_classes": skipped}
    return finish_document(doc, source)


@dataclass(frozen=True)
class Mask:
    """A mask read from a file: its pixels and, when the file is georeferenced, where its centre is."""

    array: np.ndarray
    georef: dict[str, Any] | None = None


def _open_raster(path: Path) -> Any:
    """The file opened with rasterio, or a one-line error (not an image)."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(path)
    except RasterioIOError as exc:
        raise ImageInputError(f"{path}: not an image that GDAL can read ({_gdal_message(exc, path)})") from None


def _gdal_message(exc: BaseException, path: Path) -> str:
    """GDAL's own words for ``exc`` (rasterio's "see previous exception" points to its cause), without the path."""
    cause = exc.__cause__ or exc.__context__
    text = str(cause) if cause is not None and "previous exception" in str(exc) else str(exc)
    text = " ".join(text.split()).replace(f"'{path}'", "").replace(str(path), "").strip(": ,")
    return text[:160] or "unreadable"


def _read_pixels(ds: Any, path: Path) -> np.ndarray:
    """The one band of class codes of an open raster (identical colour bands are one, alpha is ignored)."""
    from rasterio.windows import Window

    itemsize = np.dtype(ds.dtypes[0]).itemsize
    if ds.width * ds.height > MAX_MASK_PIXELS or ds.width * ds.height * itemsize > MAX_MASK_BYTES:
        raise ImageInputError(f"{path}: a {ds.width}x{ds.height} mask of {ds.dtypes[0]} is more than the "
                              f"{MAX_MASK_PIXELS:,} pixels or {MAX_MASK_BYTES >> 20} MiB read at once")
    colour = [i for i, c in enumerate(ds.colorinterp, start=1) if c.name != "alpha"] or [1]
    array = ds.read(colour[0])
    if len(colour) > 1:
        # The other bands a strip at a time, all of them at once (so that a PNG is decoded once more, not per band).
        rows = max(1, _CHUNK // (ds.width * (len(colour) - 1)))
        for start in range(0, ds.height, rows):
            block = ds.read(colour[1:], window=Window(0, start, ds.width, min(rows, ds.height - start)))
            if not (block == array[None, start:start + rows]).all():
                raise ImageInputError(f"{path}: {len(colour)} different bands; a mask has one band of class codes")
    return array


def read_mask(path: str | os.PathLike[str]) -> Mask:
    """Read a mask file (PNG, GeoTIFF, anything GDAL reads) of one band, strictly.

    A file of several identical bands (a grey mask saved as RGB) is read as one band; an alpha band is
    ignored.  Only a regular file is opened; a PNG must be whole up to its ``IEND`` chunk; any warning or
    error GDAL gives while reading refuses the file (:mod:`mapdb.detections.mask_files`).  A georeference that
    is not finite or not plausible is dropped with a :class:`~mapdb.detections.mask_files.GeorefWarning`.

    Raises
    ------
    MapdbIOError
        Missing, a directory, not a regular file, or unreadable.
    ImageInputError
        Not an image, pixels that cannot be read whole, several different bands, more than
        :data:`MAX_MASK_PIXELS` pixels or :data:`MAX_MASK_BYTES` bytes, pixels that are not whole numbers.
    """
    from rasterio.errors import RasterioError

    path = Path(path)
    check_regular_file(path)
    with reading(path, "mask"):
        check_png_chunks(path)
        with strict_gdal() as complaints, _open_raster(path) as ds:
            try:
                array = _read_pixels(ds, path)
            except RasterioError as exc:
                raise ImageInputError(f"{path}: cannot read its pixels ({_gdal_message(exc, path)})") from None
            if complaints:
                raise ImageInputError(f"{path}: cannot read its pixels ({complaints[0][:160]})")
            crs = None if ds.crs is None else ds.crs.to_wkt()
            transform, width, height = ds.transform, ds.width, ds.height
    return Mask(_checked_mask(array, str(path)), georef(crs, transform, width, height, str(path)))


def mask_document(path: str | os.PathLike[str], classes: Mapping[int, str] | None = None, *,
                  label: str | None = None, **options: Any) -> dict[str, Any]:
    """:func:`read_mask` then :func:`from_mask`; the document's ``id`` is the path, ``georef`` its centre.

    With ``label``, the mask is a single-class mask: every non-zero pixel (255 in a 0/255 mask) is that
    label and ``classes`` is not used.  ``options`` are :func:`from_mask`'s keywords.
    """
    if (classes is None) == (label is None):
        raise ValueError("give either a class table or a label")
    mask = read_mask(path)
    array, where = mask.array, mask.georef
    del mask  # with a label, the pixels are replaced by a boolean image: the codes are not kept beside it
    if label is not None:
        array, classes = array != 0, {1: label}
    assert classes is not None
    options.setdefault("image_id", str(path))
    doc = from_mask(array, classes, source=str(path), **options)
    if where is not None:
        doc["georef"] = where
    return doc
