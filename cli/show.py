"""``mapdb show``: a picture of one image's match, the first thing to look at when an answer looks wrong."""

from __future__ import annotations

from typing import Any

import click

from mapdb.answers import Answer
from mapdb.detections.images import parse_image, read_image_documents
from mapdb.errors import ImageInputError
from mapdb.evaluation.match_plot import plot_match
from mapdb.localize.localizer import METHODS, localize
from mapdb.mapfile.reader import open_map
from mapdb.match.fast import FastOptions
from mapdb.outputs import atomic_path

from .evaluate import parse_plot
from .options import (
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    with_index,
)


def _matches_line(where: str, name: str, line: int) -> bool:
    """Whether a document read from ``name`` at ``where`` is the one on ``line`` (or item ``line`` of an array)."""
    return where in (f"{name} line {line}", f"{name} item {line - 1}") or (where == name and line == 1)


def find_image(images_file: str, image_id: str | None, line: int | None) -> tuple[str, dict[str, Any]]:
    """The document chosen by ``--id`` or ``--line`` (the first one by default), as ``(where, document)``.

    A bad line is skipped while looking for an id (its id cannot be read), but is an error when chosen.
    """
    for where, doc in read_image_documents(images_file):
        if image_id is not None:
            if isinstance(doc, dict) and str(doc.get("id")) == image_id:
                return where, doc
            continue
        if line is not None and not _matches_line(where, images_file, line):
            continue
        if isinstance(doc, ImageInputError):
            raise doc
        return where, doc
    if image_id is not None:
        raise ImageInputError(f"{images_file}: no image with id {image_id!r}")
    if line is not None:
        raise ImageInputError(f"{images_file}: no image on line {line}")
    raise ImageInputError(f"{images_file}: no images")


def _summary(answer: Answer) -> str:
    if answer.ok:
        return f"{answer.id}: ok at {answer.x:.1f}, {answer.y:.1f} ({answer.inliers} inliers, score {answer.score})"
    return f"{answer.id}: rejected ({answer.reason})"


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("images_file", metavar="IMAGES.jsonl", type=click.Path())
@click.option("--id", "image_id", default=None, metavar="ID", help="The image with this id.")
@click.option("--line", type=click.IntRange(1, None), default=None, metavar="N",
              help="The image on line N of a JSON Lines file (item N of a JSON array).  Default: the first image.")
@click.option("-o", "--output", required=True, callback=parse_plot, metavar="FILE.png",
              help="The picture (the format follows the ending: .png, .svg, .pdf, ...).")
@click.option("--method", type=click.Choice(METHODS), default="fast", show_default=True,
              help="The localizer, as for `mapdb query`.")
@click.option("--min-score", type=finite_float(0.0, 300.0), default=-FastOptions().log10_epsilon, show_default=True,
              help="Accept an answer only above this score, as for `mapdb query`.")
@overwrite_option
@parents_option
@debug_option
@handle_errors
def show(map_file, images_file, image_id, line, output, method, min_score, overwrite, parents, debug):
    """Localize one image of IMAGES.jsonl in MAP and draw the match.

    The picture shows, in map metres, the map's objects around the answer (coloured by label), the
    image's footprint, each image object placed by the answer: joined to the map object of its label
    that it matched (inlier) or marked as finding none (outlier); the answer, the truth of a simulated
    image and the runner-up candidates, with a small overview of the whole map.  A rejected image is
    drawn at its true pose when it has one, else around its best candidate; the title gives the reason.
    """
    if image_id is not None and line is not None:
        raise click.UsageError("give --id or --line, not both")
    check_paths([output], [*with_index(map_file), images_file], overwrite=overwrite, parents=parents)
    where, doc = find_image(images_file, image_id, line)
    parse_image(doc, where)  # a bad image is an error here, not a picture of a rejection
    with open_map(map_file) as m:
        options = FastOptions(log10_epsilon=-min_score) if method == "fast" else None
        answer = localize(doc, m, method, options=options, source=where)
        # the temporary name keeps the ending, from which matplotlib picks the format
        with atomic_path(output, keep_suffix=True, parents=parents) as tmp:
            plot_match(doc, answer, m, tmp)
    click.echo(f"{_summary(answer)} -> {output}")
