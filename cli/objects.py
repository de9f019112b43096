"""``mapdb objects``: segmentation masks and COCO detections to image objects (the query's input)."""

from __future__ import annotations

import sys
import warnings
from typing import Any

import click

from mapdb.detections.masks import DEFAULT_MIN_AREA_PX
from mapdb.errors import MapdbError
from mapdb.outputs import atomic_open, json_line

from .options import (
    check_paths,
    debug_option,
    finite,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    quiet_option,
)


def parse_attitude(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``ROLL,PITCH`` in degrees -> (roll, pitch), each within +-89 (the query schema's range), or None."""
    if value is None:
        return None
    try:
        roll, pitch = (finite(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not two finite numbers ROLL,PITCH (degrees)") from None
    if abs(roll) > 89 or abs(pitch) > 89:
        raise click.BadParameter(f"{value!r}: roll and pitch must be within +-89 degrees")
    return roll, pitch


def _write(out: Any, doc: dict[str, Any]) -> int:
    out.write(json_line(doc) + "\n")
    return len(doc["objects"])


@click.command()
@click.argument("masks", nargs=-1, type=click.Path(), metavar="[MASK]...")
@click.option("-o", "--output", default="-", metavar="IMAGES.jsonl", help="Output file (default stdout).")
@click.option("--classes", "classes_file", type=click.Path(), metavar="FILE.toml",
              help="Class table: [classes] mapping mask codes, COCO category ids or names to labels.")
@click.option("--label", metavar="NAME", help="Single-class masks: every non-zero pixel is this label.")
@click.option("--labels", "labels_file", type=click.Path(), metavar="FILE.toml",
              help="Label table the class table is checked against (default: mapdb's).")
@click.option("--connectivity", type=click.Choice(["4", "8"]), default="8", show_default=True,
              help="Pixels touching by an edge (4) or also by a corner (8) are one object.")
@click.option("--min-area", type=click.IntRange(0, None), default=DEFAULT_MIN_AREA_PX, show_default=True,
              help="Smallest object kept, pixels.")
@click.option("--fov", type=finite_float(0.001, 180.0, max_open=True), metavar="DEG",
              help="Camera: horizontal field of view, degrees (written into every document).")
@click.option("--attitude", callback=parse_attitude, metavar="ROLL,PITCH",
              help="Camera: roll and pitch, degrees (written into every document).")
@click.option("--altitude", type=finite_float(0.0, 100_000.0, min_open=True), metavar="M",
              help="Camera: height above ground, metres (written into every document).")
@click.option("--coco", "coco_file", type=click.Path(), metavar="FILE.json",
              help="COCO detections (polygons, RLE masks or boxes): one document per COCO image.")
@click.option("--coco-images", type=click.Path(), metavar="FILE.json",
              help="The images (id, width, height) of a --coco file that is a bare list of detections.")
@click.option("--min-score", type=finite_float(), default=0.0, show_default=True,
              help="COCO detections scoring less are skipped (counted in skipped_low_score).")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def objects(masks, output, classes_file, label, labels_file, connectivity, min_area, fov, attitude, altitude,
            coco_file, coco_images, min_score, overwrite, parents, quiet, debug):
    """Image objects from segmentation masks (PNG, GeoTIFF) and COCO detections, one JSON document per line.

    Each connected region of a class of at least --min-area pixels becomes one object at the
    centroid of its pixels, with its area, bounding box and whether it touches the image border.
    Masks hold one class code per pixel, mapped to labels by --classes (codes not listed are skipped
    and counted in "skipped_classes"); or they are 0/255 masks of one class, --label NAME.  A
    georeferenced mask also gets "georef": the map position of its centre, its heading and its ground
    pixel size.  The documents are what `mapdb query` reads.

    A mask that cannot be read is reported on stderr (mapdb: error: FILE: problem) and the others are
    still processed; the exit status is then 1.  The output is written whole at the end; when every
    input fails, nothing is written (only the errors are printed).  Only regular files are read: a FIFO or
    a device is refused before it is opened.  A PNG must be whole (every chunk up to IEND) and any
    warning GDAL gives while reading a mask refuses it.  A georeference that is not finite or not
    plausible is dropped with a warning (mapdb: warning: FILE: georeference dropped: ...).
    """
    from mapdb.classmap import check_label, load_class_table
    from mapdb.labels import load_label_table

    if not masks and not coco_file:
        raise click.UsageError("give MASK files, or --coco FILE")
    if label is not None and classes_file is not None:
        raise click.UsageError("give --classes or --label, not both")
    if masks and label is None and classes_file is None:
        raise click.UsageError("masks need --classes FILE.toml (class codes to labels) or --label NAME (0/255 masks)")
    if coco_file and classes_file is None:
        raise click.UsageError("--coco needs --classes FILE.toml (category ids or names to labels)")
    check_paths([output], [*masks, classes_file, labels_file, coco_file, coco_images], overwrite=overwrite,
                parents=parents)
    table = load_label_table(labels_file)
    classes = None if classes_file is None else load_class_table(classes_file, table.labels)
    if label is not None:
        check_label(label, table.labels, "--label")
    camera = {"fov_deg": fov, "attitude": attitude, "altitude": altitude}
    try:
        with atomic_open(output) as out:
            n_docs, n_objects, failed = _convert(out, masks, classes, label, int(connectivity), min_area, camera,
                                                 (coco_file, coco_images, min_score))
    except _NothingReadError:
        sys.exit(1)  # each failure is already reported; there is nothing to sum up
    if not quiet:
        click.echo(f"{n_docs} images, {n_objects} objects -> {output}" + (f"; {failed} failed" if failed else ""),
                   err=True)
    if failed:
        sys.exit(1)


class _NothingReadError(Exception):
    """Every input failed: the output is not written (an empty file would pass for an answer)."""

    def __init__(self, failed: int) -> None:
        super().__init__(f"{failed} inputs failed")
        self.failed = failed


def _convert(out: Any, masks: tuple[str, ...], classes: Any, label: str | None, connectivity: int, min_area: int,
             camera: dict[str, Any], coco: tuple[str | None, str | None, float]) -> tuple[int, int, int]:
    """Write the documents of the masks, then of the COCO file; (documents, objects, inputs failed).

    An input that fails is reported on stderr and the others are still written.

    Raises
    ------
    _NothingReadError
        Every input failed.
    """
    coco_file, coco_images, min_score = coco
    failed = n_docs = n_objects = 0
    for path in masks:
        try:
            doc = _mask(path, classes, label, connectivity, min_area, camera)
        except (MapdbError, OSError) as exc:
            click.echo(f"mapdb: error: {exc}", err=True)
            failed += 1
            continue
        n_objects += _write(out, doc)
        n_docs += 1
    if coco_file:
        assert classes is not None
        try:
            docs = _coco(coco_file, classes.classes, coco_images, min_area, min_score, camera)
        except (MapdbError, OSError) as exc:
            click.echo(f"mapdb: error: {exc}", err=True)
            failed += 1
            docs = []
        for doc in docs:
            n_objects += _write(out, doc)
        n_docs += len(docs)
    if failed and not n_docs:
        raise _NothingReadError(failed)
    return n_docs, n_objects, failed


def _mask(path: str, classes: Any, label: str | None, connectivity: int, min_area: int,
          camera: dict[str, Any]) -> dict[str, Any]:
    from mapdb.detections.mask_files import GeorefWarning
    from mapdb.detections.masks import mask_document

    codes = None if classes is None else classes.codes
    if codes is not None and not codes:
        raise MapdbError(f"{classes.source}: no integer class codes, which a mask's pixels hold")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GeorefWarning)
        doc = mask_document(path, codes, label=label, connectivity=connectivity, min_area=min_area, **camera)
    for warning in caught:
        if issubclass(warning.category, GeorefWarning):
            click.echo(f"mapdb: warning: {warning.message}", err=True)
    return doc


def _coco(path: str, classes: dict[str, str], images: str | None, min_area: int, min_score: float,
          camera: dict[str, Any]) -> list[dict[str, Any]]:
    from mapdb.detections.coco import from_coco

    return from_coco(path, classes, images=images, min_area=min_area, min_score=min_score, **camera)
