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

Everything is vectorised (``scipy.ndimage.label`` per class, then ``numpy.bincount`` over the region
pixels only and ``ndimage.find_objects`` for the boxes): a 4000x3000 mask of three classes with about
500 objects takes a few tenths of a second (``python benchmarks/objects_mask.py``).

Masks are read from PNG or GeoTIFF (anything GDAL reads, :func:`read_mask`); a mask with a
georeference also gives the ground position of its centre (the document's ``georef``, which the
query ignores and a test can compare with the answer).  COCO detector output is read by
:mod:`mapdb.detections.coco`.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ImageInputError, MapdbIOError
from .images import MAX_ELONGATION, MAX_IMAGE_SIDE_PX, MAX_OBJECTS, parse_image

__all__ = [
    "DEFAULT_MIN_AREA_PX",
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
# A mask is held whole (regions cross any tiling): about 1 GB of working memory at this size.  A file
# claiming more (a PNG header is a few bytes) is refused before any pixel is read.
MAX_MASK_PIXELS = 100_000_000
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
    """A 2-D integer array (booleans and integral floats accepted), or a one-line ImageInputError."""
    array = np.asarray(mask)
    if array.ndim != 2:
        raise ImageInputError(f"{source}: a mask must be a 2-D image, got {array.ndim} dimensions {array.shape}")
    height, width = array.shape
    if not (1 <= width <= MAX_IMAGE_SIDE_PX and 1 <= height <= MAX_IMAGE_SIDE_PX):
        raise ImageInputError(f"{source}: a {width}x{height} mask; each side must be 1 to {MAX_IMAGE_SIDE_PX} px")
    if array.dtype == bool:
        return array.view(np.uint8)
    if array.dtype.kind == "f":
        if not (np.isfinite(array).all() and (array == np.round(array)).all()):
            raise ImageInputError(f"{source}: pixels are not whole numbers; a mask holds integer class codes")
        return array.astype(np.int64)
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


def _regions(binary: np.ndarray, structure: np.ndarray, min_area: int) -> dict[str, np.ndarray]:
    """Pixel centroid, area and box of each connected region of ``binary`` with at least ``min_area`` pixels.

    The sums visit only the region pixels (found in the boolean image, 4 times cheaper to scan than the
    labels), so their memory follows the objects' area, not the image's.
    """
    from scipy import ndimage

    labelled, n = ndimage.label(binary, structure=structure)
    width = binary.shape[1]
    where = np.flatnonzero(binary.ravel())
    ids = labelled.ravel()[where]
    rows, cols = np.divmod(where, width)
    area = np.bincount(ids, minlength=n + 1)[1:]

    def mean(weights: np.ndarray) -> np.ndarray:
        return np.bincount(ids, weights=weights, minlength=n + 1)[1:] / area

    with np.errstate(invalid="ignore", divide="ignore"):
        cx, cy = mean(cols), mean(rows)
        # Second moments about the centroid, each pixel a unit square (its own 1/12 added): a one-pixel line
        # has a finite elongation.
        sxx = mean(cols * cols) - cx * cx + 1.0 / 12.0
        syy = mean(rows * rows) - cy * cy + 1.0 / 12.0
        sxy = mean(cols * rows) - cx * cy
        orientation, elongation = major_axes(sxx, syy, sxy)
    # find_objects scans the labels once in C: cheaper than reducing over the pixels when objects are large.
    bbox = np.array([(b[1].start, b[0].start, b[1].stop, b[0].stop) for b in ndimage.find_objects(labelled)],
                    dtype=np.int64).reshape(-1, 4)
    keep = area >= max(min_area, 1)
    return {"x": cx[keep] + 0.5, "y": cy[keep] + 0.5, "area": area[keep], "bbox": bbox[keep],
            "orientation": orientation[keep], "elongation": elongation[keep]}


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
    for code, count in zip(codes.tolist(), counts.tolist(), strict=True):
        if code in classes:
            regions = _regions(array == code, structure, min_area)
            found.append(regions)
            labels += [classes[code]] * regions["x"].size
        elif code != 0:
            skipped[str(code)] = count
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
    """The file opened with rasterio, or a one-line error (missing, a directory, not an image)."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioIOError

    if not path.exists():
        raise MapdbIOError(f"{path}: no such mask")
    if path.is_dir():
        raise MapdbIOError(f"{path}: is a directory, not a mask")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            return rasterio.open(path)
    except RasterioIOError as exc:
        message = " ".join(str(exc).split()).replace(f"'{path}'", "").replace(str(path), "").strip(": ")
        raise ImageInputError(f"{path}: not an image that GDAL can read ({message[:160] or 'unreadable'})") from None


def read_mask(path: str | os.PathLike[str]) -> Mask:
    """Read a mask file (PNG, GeoTIFF, anything GDAL reads) of one band.

    A file of several identical bands (a grey mask saved as RGB) is read as one band; an alpha band is
    ignored.

    Raises
    ------
    MapdbIOError
        Missing or unreadable.
    ImageInputError
        Not an image, several different bands, more than :data:`MAX_MASK_PIXELS` pixels, pixels that
        are not whole numbers.
    """
    from rasterio.errors import RasterioError

    path = Path(path)
    with _open_raster(path) as ds:
        if ds.width * ds.height > MAX_MASK_PIXELS:
            raise ImageInputError(f"{path}: a {ds.width}x{ds.height} mask is more than the {MAX_MASK_PIXELS:,} "
                                  "pixels read at once")
        try:
            colour = [i for i, c in enumerate(ds.colorinterp, start=1) if c.name != "alpha"] or [1]
            array = ds.read(colour[0])
            for band in colour[1:]:
                if not np.array_equal(ds.read(band), array):
                    raise ImageInputError(f"{path}: {len(colour)} different bands; a mask has one band of class "
                                          "codes")
        except RasterioError as exc:
            raise ImageInputError(f"{path}: cannot read its pixels ({' '.join(str(exc).split())[:160]})") from None
        georef = _georef(ds)
    return Mask(_checked_mask(array, str(path)), georef)


def _georef(ds: Any) -> dict[str, Any] | None:
    """Where the centre of a georeferenced raster is: map x, y (its CRS), lon, lat, heading, ground size of a pixel.

    ``heading_deg`` is where the image's up points, clockwise from the CRS's north (as a query answers).
    """
    from pyproj import CRS, Transformer

    t = ds.transform
    if ds.crs is None or t.is_identity:
        return None
    crs = CRS.from_user_input(ds.crs.to_wkt())
    cx, cy = t @ (ds.width / 2.0, ds.height / 2.0)
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(cx, cy)
    authority = crs.to_authority()
    out: dict[str, Any] = {"crs": ":".join(authority) if authority else crs.to_wkt(), "x": cx, "y": cy,
                           "lon": lon, "lat": lat, "heading_deg": math.degrees(math.atan2(-t.b, -t.e)) % 360.0}
    if crs.is_projected:
        unit = crs.axis_info[0].unit_conversion_factor if crs.axis_info else 1.0
        out["m_per_px"] = math.sqrt(abs(t.determinant)) * unit
    return out


def mask_document(path: str | os.PathLike[str], classes: Mapping[int, str] | None = None, *,
                  label: str | None = None, **options: Any) -> dict[str, Any]:
    """:func:`read_mask` then :func:`from_mask`; the document's ``id`` is the path, ``georef`` its centre.

    With ``label``, the mask is a single-class mask: every non-zero pixel (255 in a 0/255 mask) is that
    label and ``classes`` is not used.  ``options`` are :func:`from_mask`'s keywords.
    """
    if (classes is None) == (label is None):
        raise ValueError("give either a class table or a label")
    mask = read_mask(path)
    array = mask.array
    if label is not None:
        array, classes = array != 0, {1: label}
    assert classes is not None
    options.setdefault("image_id", str(path))
    doc = from_mask(array, classes, source=str(path), **options)
    if mask.georef is not None:
        doc["georef"] = mask.georef
    return doc
