"""``mapdb bench``: reproducible benchmarks; ``mapdb bench paper`` reproduces the paper's Table 1, ``mapdb bench
storage`` measures a map's bytes against other formats and imagery."""

from __future__ import annotations

import sys

import click

from mapdb.evaluation.paper_bench import bench_paper, format_bench
from mapdb.evaluation.storage import DEFAULT_GSD_M, DEFAULT_JPEG_BPP, format_storage, storage_reports
from mapdb.mapfile.writer import write_map
from mapdb.outputs import dumps_strict
from mapdb.simulation.simulate import paper_map

from .options import (
    MAX_PRIOR_RADIUS,
    MAX_SPURIOUS_RATE,
    TerminalProgress,
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    json_option,
    overwrite_option,
    parents_option,
    parse_yaw,
    progress_printer,
    quiet_option,
)


@click.group()
def bench() -> None:
    """Reproducible benchmarks."""


@bench.command()
@click.option("--n", "n_images", type=click.IntRange(1, None), default=500, show_default=True,
              help="Images per case for --method fast and the bound (the paper: 500).")
@click.option("--paper-images", type=click.IntRange(0, None), default=500, show_default=True,
              help="At most this many images per case for --method paper (minutes each); 0 skips it.")
@click.option("--budget", type=finite_float(0.0, None), default=540.0, show_default=True,
              help="Wall-clock seconds for the whole run: --method paper runs on the images predicted to fit "
                   "(round-robin over the cases); 0 for no limit.")
@click.option("--cases", default="1,2,3,4,5", show_default=True, help="Comma-separated case numbers.")
@click.option("--yaw", default="0", callback=parse_yaw, show_default=True, help="Degrees, or 'random'.")
@click.option("--miss-rate", type=finite_float(0.0, 1.0), default=0.0, show_default=True)
@click.option("--spurious-rate", type=finite_float(0.0, MAX_SPURIOUS_RATE), default=0.0, show_default=True)
@click.option("--label-noise", type=finite_float(0.0, 1.0), default=0.0, show_default=True)
@click.option("--with-prior", type=finite_float(0.0, MAX_PRIOR_RADIUS, min_open=True), default=None, metavar="R",
              help="Give each image a prior of radius R metres.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the images.")
@click.option("--map-seed", type=int, default=0, show_default=True, help="Seed of the paper's map.")
@click.option("--jobs", "-j", type=click.IntRange(1, None), default=2, show_default=True, help="Worker processes.")
@click.option("--save-map", type=click.Path(), default=None, metavar="FILE.mapdb",
              help="Also write the paper's map, for `mapdb simulate` / `mapdb evaluate`.")
@overwrite_option
@parents_option
@json_option
@quiet_option
@debug_option
@handle_errors
def paper(n_images, paper_images, budget, cases, yaw, miss_rate, spurious_rate, label_noise, with_prior, seed, map_seed,
          jobs, save_map, overwrite, parents, as_json, quiet, debug):
    """Reproduce the paper's Table 1: published figures, --method paper, --method fast and the bound."""
    try:
        chosen = sorted({int(c) for c in cases.split(",")})
    except ValueError:
        raise click.BadParameter(f"{cases!r} is not a list of case numbers", param_hint="--cases") from None
    if not chosen or not set(chosen) <= {1, 2, 3, 4, 5}:
        raise click.BadParameter(f"{cases!r}: cases are numbered 1 to 5", param_hint="--cases")
    check_paths([save_map], [], overwrite=overwrite, parents=parents, what="map")
    if save_map:
        write_map(save_map, paper_map(seed=map_seed), metadata={"description": "paper Table 1 map"})
    result = bench_paper(n=n_images, paper_images=paper_images, budget_s=budget or None, cases=chosen, yaw=yaw,
                         miss_rate=miss_rate, spurious_rate=spurious_rate, label_noise=label_noise,
                         with_prior=with_prior, seed=seed, map_seed=map_seed, jobs=jobs,
                         progress=progress_printer(quiet))
    click.echo(dumps_strict(result, indent=2) if as_json else format_bench(result))


@bench.command()
@click.argument("sources", nargs=-1, required=True, type=click.Path(), metavar="MAP_OR_SOURCE...")
@click.option("--cell", type=finite_float(0.001, 1000.0), default=1.0, show_default=True,
              help="Side of the region cells, km, in the map's CRS.")
@click.option("--gsd", type=finite_float(0.01, 100.0), default=DEFAULT_GSD_M, show_default=True,
              help="Ground sample distance of the orthophoto compared, metres a pixel.")
@click.option("--jpeg-bpp", type=finite_float(0.01, 24.0), default=DEFAULT_JPEG_BPP, show_default=True,
              help="Bits a pixel of that orthophoto as JPEG (an assumed rate: 24-bit RGB at 16:1).")
@json_option
@quiet_option
@debug_option
@handle_errors
def storage(sources, cell, gsd, jpeg_bpp, as_json, quiet, debug):
    """The paper's storage argument, measured: bytes per object and per km² of each map against the same
    objects as GeoPackage, GeoParquet (zstd), FlatGeobuf, their sorted columns through lzma (whole, and
    in chunks that are the map's pages) and an orthophoto of the same area as JPEG; per cell and in total.

    Each MAP_OR_SOURCE is a map, or a source `mapdb build` reads (built with its defaults into a
    temporary map).  Nothing is left on disk.  One table a map, and their total; a source that fails
    gets one error line and the others are still measured (exit status 1).
    """
    progress = progress_printer(quiet)

    def report_error(exc: Exception) -> None:
        if debug:
            raise exc
        if isinstance(progress, TerminalProgress):
            progress.abandon()  # the error goes on a line of its own, not over a half-drawn bar
        click.echo(f"mapdb: error: {exc}", err=True)

    result = storage_reports(sources, cell_m=cell * 1000.0, gsd_m=gsd, jpeg_bpp=jpeg_bpp, progress=progress,
                             on_error=report_error)
    if result["maps"]:
        click.echo(dumps_strict(result, indent=2) if as_json else format_storage(result))
    if result["errors"]:
        sys.exit(1)
