"""``mapdb query``: localize images (JSON Lines of image objects) in a map."""

from __future__ import annotations

import json
import os
import stat

import click

from mapdb.errors import ImageInputError
from mapdb.images import check_prior, read_image_documents
from mapdb.localize import METHODS, localize_documents
from mapdb.match.fast import FastOptions
from mapdb.outputs import atomic_open, check_outputs
from mapdb.store import open_map

from .options import debug_option, finite_float, handle_errors


def parse_prior(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``X,Y,R`` (map CRS metres) -> (x, y, r), or None; the ranges of an image's prior apply."""
    if value is None:
        return None
    try:
        x, y, r = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not three comma-separated numbers X,Y,R") from None
    try:
        p = check_prior(x, y, r, repr(value))
    except ImageInputError as exc:
        raise click.BadParameter(str(exc)) from None
    return (p.x, p.y, p.radius)


def _stdin_file() -> str | None:
    """``/dev/stdin`` when standard input is a regular file (``< a.jsonl -o a.jsonl`` must be refused too)."""
    try:
        return "/dev/stdin" if stat.S_ISREG(os.fstat(0).st_mode) else None
    except OSError:
        return None


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("images_file", metavar="IMAGES", type=click.Path())
@click.option("-o", "--output", default="-", metavar="OUT.jsonl",
              help="Answers file (default stdout), written whole at the end or not at all.")
@click.option("--method", type=click.Choice(METHODS), default="fast", show_default=True,
              help="The fast matcher, or the paper's Algorithm 1 (seconds to minutes per image).")
@click.option("--prior", callback=parse_prior, metavar="X,Y,R",
              help="Search within R metres of X,Y (map CRS) for images that carry no prior of their own.")
@click.option("--min-score", type=finite_float(0.0, 300.0), default=-FastOptions().log10_epsilon, show_default=True,
              help="Accept an answer only above this score (-log10 of its expected false alarms; the default "
                   "was calibrated on real places not in the map, see the README).")
@debug_option
@handle_errors
def query(map_file, images_file, output, method, prior, min_score, debug):
    """Localize every image of IMAGES (JSON Lines; '-' for stdin) in MAP.

    Writes one JSON answer per image, in input order: status "ok" with the position (map CRS and
    lon/lat), heading, scale, 1-sigma error and score, or status "rejected" with the reason.

    Every line on its own: lines are split on "\\n" only, blank lines are skipped, and each other
    line gets exactly one answer, in order.  A line that is not UTF-8, not JSON, not a JSON object,
    or has a number out of range (see the image schema) is rejected on its own; the other images
    are still answered.  A file that is one pretty-printed JSON object or array (up to 16 MiB) is
    read too.

    Streaming: input is read line by line and each answer is written (to stdout, flushed) before the
    next line is read, so a process can feed frames through a pipe one at a time.  With -o the
    answers go to a temporary file renamed to OUT.jsonl at the end: an error (a damaged map) leaves
    any earlier OUT.jsonl as it was.  OUT.jsonl may not be MAP or IMAGES.
    """
    check_outputs([output], [map_file, _stdin_file() if images_file == "-" else images_file])
    documents = read_image_documents(images_file)
    with open_map(map_file) as m, atomic_open(output) as out:
        streaming = output == "-"
        options = FastOptions(log10_epsilon=-min_score) if method == "fast" else None
        for record in localize_documents(documents, m, method, prior, options=options):
            out.write(json.dumps(record, separators=(",", ":"), allow_nan=False) + "\n")
            if streaming:
                out.flush()  # the answer reaches a reader on a pipe before the next line is read
