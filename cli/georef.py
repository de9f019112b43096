"""``mapdb georef``: place a camera image on the map (a world file and a GDAL ``.aux.xml`` beside it)."""

from __future__ import annotations

import json
import warnings

import click

from mapdb.answers import Answer
from mapdb.errors import ImageInputError, MapdbIOError
from mapdb.localize.worldfile import aux_xml_name, aux_xml_text, checked_answer, world_file_name, world_file_text
from mapdb.outputs import atomic_open

from .options import check_paths, debug_option, handle_errors, overwrite_option, quiet_option


def read_answers(path: str) -> list[Answer]:
    """Every answer of a ``mapdb query`` output (JSON Lines); a line that is not a JSON object is an error."""
    answers = []
    try:
        with open(path, encoding="utf-8") as f:
            lines = f.read().split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise MapdbIOError(f"{path}: cannot be read ({getattr(exc, 'strerror', None) or exc})") from None
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            record = None
        if not isinstance(record, dict) or "status" not in record:
            raise ImageInputError(f"{path}:{number}: not an answer of mapdb query (a JSON object with a status)")
        answers.append(Answer.from_json(record))
    return answers


def image_size(path: str) -> tuple[int, int]:
    """The width and height in pixels of the image GDAL reads at ``path``."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)  # a camera image has none: that is the point
            with rasterio.open(path) as ds:
                return int(ds.width), int(ds.height)
    except RasterioError as exc:
        problem = " ".join(str(exc).split())[:160]
        raise MapdbIOError(f"{path}: not an image GDAL can read ({problem})") from None


@click.command()
@click.argument("answers_file", metavar="ANSWERS.jsonl", type=click.Path())
@click.argument("image", metavar="IMAGE", type=click.Path())
@click.option("--id", "image_id", default=None, metavar="ID",
              help="The answer whose id this is [default: the only accepted answer of ANSWERS.jsonl].")
@overwrite_option
@quiet_option
@debug_option
@handle_errors
def georef(answers_file, image, image_id, overwrite, quiet, debug):
    """Place IMAGE, the camera image an answer of ANSWERS.jsonl (from `mapdb query`) localized, on the map.

    Writes beside IMAGE its world file (IMAGE.pgw for a .png, .tfw for a .tif, .jgw for a .jpg, .wld
    otherwise: the answer's transform) and IMAGE.aux.xml (GDAL's sidecar: the map's CRS and the same
    transform), so that QGIS, gdalinfo and rasterio show IMAGE where the answer puts it.  IMAGE must have
    the width and height of the answer's image.  For a tilted camera the transform is the best affine
    over the image, within the answer's transform_error_m of the pinhole projection.  Existing sidecars
    are replaced only with --overwrite; nothing is written when anything is wrong.
    """
    world, aux = world_file_name(image), aux_xml_name(image)
    check_paths([world, aux], [answers_file, image], overwrite=overwrite)
    answer = checked_answer(read_answers(answers_file), image_id, answers_file, image, image_size(image))
    assert answer.transform is not None and answer.crs is not None  # checked_answer says so
    aux_text = aux_xml_text(answer.crs, answer.transform)
    with atomic_open(world) as w, atomic_open(aux) as x:
        w.write(world_file_text(answer.transform))
        x.write(aux_text)
    if not quiet:
        click.echo(f"{image}: placed by answer {answer.id!r} -> {world}, {aux}", err=True)
