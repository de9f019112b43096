"""``mapdb query``: localize images (JSON Lines of image objects) in a map."""

from __future__ import annotations

import json
import sys

import click

from mapdb.errors import MapdbIOError
from mapdb.images import read_image_documents
from mapdb.localize import METHODS, localize_documents
from mapdb.store import open_map

from .options import debug_option, handle_errors


def parse_prior(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``X,Y,R`` (map CRS metres) -> (x, y, r), or None."""
    if value is None:
        return None
    try:
        x, y, r = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not three comma-separated numbers X,Y,R") from None
    if not all(map(lambda v: v == v and abs(v) != float("inf"), (x, y, r))) or r <= 0:
        raise click.BadParameter(f"{value!r}: X and Y must be finite and R positive")
    return (x, y, r)


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("images_file", metavar="IMAGES", type=click.Path())
@click.option("-o", "--output", default="-", metavar="OUT.jsonl", help="Answers file (default stdout).")
@click.option("--method", type=click.Choice(METHODS), default="fast", show_default=True,
              help="The fast matcher, or the paper's Algorithm 1 (seconds to minutes per image).")
@click.option("--prior", callback=parse_prior, metavar="X,Y,R",
              help="Search within R metres of X,Y (map CRS) for images that carry no prior of their own.")
@debug_option
@handle_errors
def query(map_file, images_file, output, method, prior, debug):
    """Localize every image of IMAGES (JSON Lines; '-' for stdin) in MAP.

    Writes one JSON answer per image, in input order: status "ok" with the position (map CRS and
    lon/lat), heading, scale, 1-sigma error and score, or status "rejected" with the reason.  A malformed
    line is rejected on its own; the other images are still answered.
    """
    documents = read_image_documents(images_file)
    with open_map(map_file) as m:
        try:
            out = sys.stdout if output == "-" else open(output, "w", encoding="utf-8")  # noqa: SIM115
        except OSError as exc:
            raise MapdbIOError(f"{output}: cannot write answers ({exc.strerror or exc})") from None
        try:
            for record in localize_documents(documents, m, method, prior):
                line = json.dumps(record, separators=(",", ":")) + "\n"
                try:
                    out.write(line)
                    out.flush()  # a long batch streams its answers
                except OSError as exc:
                    raise MapdbIOError(f"{output}: cannot write answers ({exc.strerror or exc})") from None
        finally:
            if out is not sys.stdout:
                out.close()
