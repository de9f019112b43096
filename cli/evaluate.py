"""``mapdb evaluate``: localize simulated images and compare with their truth."""

from __future__ import annotations

import json

import click

from mapdb.errors import MapdbIOError
from mapdb.evaluate import evaluate_images, format_summary, load_images, plot_evaluation
from mapdb.store import open_map

from .options import debug_option, handle_errors, json_option, progress_printer, quiet_option


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("images_file", metavar="IMAGES.jsonl", type=click.Path())
@click.option("--method", type=click.Choice(["fast", "paper"]), default="fast", show_default=True,
              help="Localizer: the fast matcher or the paper's Algorithm 1 (seconds per image).")
@click.option("--jobs", "-j", type=click.IntRange(1, None), default=1, show_default=True, help="Worker processes.")
@click.option("--fp-threshold", type=click.FloatRange(0.0, None, min_open=True), default=2.0, show_default=True,
              help="Accepted answers farther than this many metres from the truth are false positives.")
@click.option("--plot", "plot_file", type=click.Path(), default=None, metavar="FILE.png",
              help="Save the error distribution and a map of image positions coloured by outcome.")
@click.option("--outcomes", "outcomes_file", type=click.Path(), default=None, metavar="FILE.jsonl",
              help="Also write one line per image: status, position, error, time.")
@json_option
@quiet_option
@debug_option
@handle_errors
def evaluate(map_file, images_file, method, jobs, fp_threshold, plot_file, outcomes_file, as_json, quiet, debug):
    """Localize every image of IMAGES.jsonl (from `mapdb simulate`) in MAP and measure the answers.

    Reports the RMS, median and 95th-percentile error of correct answers, the fraction rejected, false
    positives (accepted with error above --fp-threshold) as a fraction of accepted, the error of the fit
    with the true correspondences (the bound), and time per image.
    """
    images = load_images(images_file)
    with open_map(map_file) as m:
        outcomes, summary = evaluate_images(m, images, method=method, jobs=jobs, fp_threshold=fp_threshold,
                                            progress=progress_printer(quiet))
        map_objects = m.all() if plot_file else None
    if outcomes_file:
        try:
            with open(outcomes_file, "w") as f:
                f.writelines(json.dumps(o) + "\n" for o in outcomes)
        except OSError as exc:
            raise MapdbIOError(f"{outcomes_file}: cannot write outcomes ({exc.strerror or exc})") from None
    if plot_file:
        plot_evaluation(outcomes, plot_file, fp_threshold=fp_threshold, map_objects=map_objects,
                        title=f"{images_file} on {map_file} ({method})")
    summary = {"map": str(map_file), "images_file": str(images_file), "method": method, **summary}
    if as_json:
        click.echo(json.dumps(summary, indent=2))
    else:
        click.echo(format_summary(summary, title=f"{images_file} on {map_file}, method {method}"))
