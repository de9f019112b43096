"""``mapdb analyze``: where a map localizes an aircraft, cell by cell (see :mod:`mapdb.analysis`)."""

from __future__ import annotations

import click

from mapdb.analysis import SampleConfig
from mapdb.analysis.cputime import CpuPhases
from mapdb.analysis.grid import AnalysisError
from mapdb.analysis.outputs import cell_totals, output_folder, write_outputs
from mapdb.analysis.run import execute, plan
from mapdb.cluster import DEFAULT_TIMEOUT_S, open_client
from mapdb.match.index.stored import index_path
from mapdb.outputs import output_errors

from .options import (
    MAX_PRIOR_RADIUS,
    camera_options,
    debug_option,
    detector_error_options,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    progress_printer,
    quiet_option,
)


def _labels(value: str | None) -> tuple[str, ...] | None:
    if value is None:
        return None
    names = tuple(dict.fromkeys(name.strip() for name in value.split(",") if name.strip()))
    if not names:
        raise AnalysisError(f"--labels {value!r}: name at least one label")
    return names


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.option("-o", "--output", "outdir", required=True, type=click.Path(), metavar="OUTDIR",
              help="Output folder: analysis.tif, analysis.png, cells.gpkg, summary.json.")
@click.option("--cell", "cell_m", type=float, default=100.0, show_default=True,
              help="Cell size, metres in the map's CRS.")
@click.option("--bbox", metavar="MINLON,MINLAT,MAXLON,MAXLAT", help="Analyse only this lon/lat box of the map.")
@camera_options(altitude="150", fov="45", ranges=False)
@detector_error_options(attitude_std=0.05, pixel_std=1.0)
@click.option("--labels", metavar="LABEL,...", help="Use only these map labels (a detector that knows only them).")
@click.option("--samples", type=click.IntRange(1, 10_000), default=16, show_default=True,
              help="Images per cell, at most (random position in the cell, random heading).")
@click.option("--sequential/--no-sequential", default=True, show_default=True,
              help="Localize a cell's images only until its success share is known to --width, and skip "
                   "cells no image can localize from; --no-sequential localizes every image of every cell.")
@click.option("--adaptive/--no-adaptive", default=False, show_default=True,
              help="With --sequential: simulate every second cell each way first, and the cells between only "
                   "where those around them disagree; the others are inferred (band 'inferred': their false "
                   "fixes are not seen, their error and ambiguity are their neighbours').")
@click.option("--width", "stop_width", type=finite_float(0.0, 1.0, min_open=True), default=None, metavar="W",
              help="Width of the 95 % interval of success at which a cell stops (default: the widest "
                   "interval of a fixed --samples run, 0.44 for 16).")
@click.option("--prior", type=finite_float(0.0, MAX_PRIOR_RADIUS, min_open=True), default=None, metavar="R",
              help="Give each image a position prior of radius R metres (ambiguity stays lost-in-space).")
@click.option("--seed", type=click.IntRange(0, None), default=0, show_default=True,
              help="Same seed, same measures (whatever --jobs or --scheduler).")
@click.option("--scenarios", "scenarios_file", type=click.Path(), metavar="FILE.toml",
              help="Run several named configurations over the same cells (see mapdb.analysis.scenarios).")
@click.option("--jobs", type=click.IntRange(1, 1024), default=None, metavar="N",
              help="Run on a local Dask cluster of N worker processes (default: in this process).")
@click.option("--scheduler", metavar="tcp://HOST:PORT", help="Run on an existing Dask cluster.")
@click.option("--timeout", "timeout_s", type=finite_float(0.0, 3600.0, min_open=True), default=DEFAULT_TIMEOUT_S,
              show_default=True, help="Seconds to wait for the Dask scheduler.")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def analyze(map_file, outdir, cell_m, bbox, altitude, fov, size, attitude_std, pixel_std, miss_rate, spurious_rate,
            label_noise, labels, samples, sequential, adaptive, stop_width, prior, seed, scenarios_file, jobs,
            scheduler, timeout_s, overwrite, parents, quiet, debug):
    """Simulate images over every cell of a grid on MAP and measure where they localize.

    Per cell: objects in view, success, false positives, error, ambiguity (0: the cell's pattern is
    unique, 1: indistinguishable from another place), objects and map bytes per km², and for a map with
    elevation the relief in view (relief_m). A cell stops localizing images once its success share is
    known to --width (simulated and success_low/success_high say how many and how well). Cells from which
    no image can show 4 objects are decided without simulating; with --adaptive, cells between a coarse
    lattice's that agree are inferred from them. Writes a GeoTIFF (a band per measure),
    a PNG, a GeoPackage of the cells and summary.json into OUTDIR, which appears only when complete.
    """
    phases = CpuPhases(start=0.0)  # this process's CPU from its start: the interpreter and the imports
    if jobs is not None and scheduler is not None:
        raise click.UsageError("give --jobs (a local cluster) or --scheduler (an existing one), not both")
    from mapdb.analysis.scenarios import read_scenarios

    base = SampleConfig(altitude=altitude, fov_deg=fov, size=size, attitude_std=attitude_std, pixel_std=pixel_std,
                        miss_rate=miss_rate, spurious_rate=spurious_rate, label_noise=label_noise,
                        labels=_labels(labels), samples=samples, prior=prior, seed=seed, sequential=sequential,
                        width=stop_width, adaptive=adaptive)
    configs = read_scenarios(scenarios_file, base) if scenarios_file else {"": base}
    bbox_values = bbox.split(",") if bbox is not None else None
    say = progress_printer(quiet)
    inputs = [map_file, index_path(map_file), scenarios_file]
    with output_folder(outdir, inputs, overwrite=overwrite, parents=parents) as folder:
        planned = plan(map_file, configs, cell_m=cell_m, bbox=bbox_values, progress=say)
        with open_client(jobs, scheduler, timeout_s) as client:
            analyses = execute(planned, client, say, phases)
        with output_errors(outdir):  # a full disk names OUTDIR/analysis.png, not the folder's temporary name
            written = write_outputs(folder, analyses, phases)
    if say:
        say(phases.line(*cell_totals(analyses)))
        say(f"{', '.join(written)} -> {outdir}")
