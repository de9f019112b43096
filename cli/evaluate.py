"""``mapdb evaluate``: localize simulated images and compare with their truth."""

from __future__ import annotations

from pathlib import Path

import click

from mapdb.evaluation.evaluate import DEFAULT_FP_THRESHOLD_M, evaluate_images, format_summary, load_images
from mapdb.evaluation.evaluation_plot import plot_evaluation
from mapdb.mapfile.reader import open_map
from mapdb.outputs import atomic_open, atomic_path, dumps_strict

from .options import (
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    json_option,
    overwrite_option,
    parents_option,
    progress_printer,
    quiet_option,
    with_index,
)


def parse_plot(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """A picture path whose ending matplotlib knows (it picks the format from it)."""
    if value is None:
        return None
    from matplotlib.backend_bases import FigureCanvasBase

    known = FigureCanvasBase.get_supported_filetypes()
    if Path(value).suffix.lower().lstrip(".") not in known:
        raise click.BadParameter(f"{value!r}: the file name must end in one of .{', .'.join(sorted(known))}")
    return value


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("images_file", metavar="IMAGES.jsonl", type=click.Path())
@click.option("--method", type=click.Choice(["fast", "paper"]), default="fast", show_default=True,
              help="Localizer: the fast matcher or the paper's Algorithm 1 (seconds per image).")
@click.option("--jobs", "-j", type=click.IntRange(1, None), default=1, show_default=True, help="Worker processes.")
@click.option("--fp-threshold", type=finite_float(0.0, None, min_open=True), default=DEFAULT_FP_THRESHOLD_M,
              show_default=True,
              help="Accepted answers farther than this many metres from the truth are false positives.")
@click.option("--plot", "plot_file", callback=parse_plot, default=None, metavar="FILE.png",
              help="Save the error distribution and a map of image positions coloured by outcome.")
@click.option("--outcomes", "outcomes_file", type=click.Path(), default=None, metavar="FILE.jsonl",
              help="Also write one line per image: status, position, error, time.")
@overwrite_option
@parents_option
@json_option
@quiet_option
@debug_option
@handle_errors
def evaluate(map_file, images_file, method, jobs, fp_threshold, plot_file, outcomes_file, overwrite, parents, as_json,
             quiet, debug):
    """Localize every image of IMAGES.jsonl in MAP and measure the answers against each image's truth.

    The truth is the document's "truth" (`mapdb simulate`), or else its "georef" (`mapdb objects` on a
    georeferenced mask: the chip's centre, heading and pixel size, which must be in MAP's CRS).

    Reports the RMS, median and 95th-percentile error of correct answers, their heading error, the
    fraction rejected, false positives (accepted with error above --fp-threshold) as a fraction of
    accepted, the error of the fit with the true correspondences (the bound: point detections only, as
    the ideal simulator makes them; blobs from masks have no true correspondences and no bound), and time
    per image.
    """
    check_paths([outcomes_file, plot_file], [*with_index(map_file), images_file], overwrite=overwrite, parents=parents)
    images = load_images(images_file)
    with open_map(map_file) as m:
        outcomes, summary = evaluate_images(m, images, method=method, jobs=jobs, fp_threshold=fp_threshold,
                                            progress=progress_printer(quiet))
        map_objects = m.all() if plot_file else None
    if outcomes_file:
        with atomic_open(outcomes_file) as f:
            f.writelines(dumps_strict(o) + "\n" for o in outcomes)
    if plot_file:
        # the temporary name keeps the ending, from which matplotlib picks the format
        with atomic_path(plot_file, keep_suffix=True) as tmp:
            plot_evaluation(outcomes, tmp, fp_threshold=fp_threshold, map_objects=map_objects,
                            title=f"{images_file} on {map_file} ({method})")
    summary = {"map": str(map_file), "images_file": str(images_file), "method": method, **summary}
    if as_json:
        click.echo(dumps_strict(summary, indent=2))
    else:
        click.echo(format_summary(summary, title=f"{images_file} on {map_file}, method {method}"))
