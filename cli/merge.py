"""``mapdb merge``: maps of neighbouring or overlapping regions into one map."""

from __future__ import annotations

import click

from mapdb.build.merge import merge_maps
from mapdb.outputs import dumps_strict

from .options import (
    check_paths,
    debug_option,
    handle_errors,
    overwrite_option,
    parents_option,
    progress_printer,
    quiet_option,
)


@click.command()
@click.argument("maps", nargs=-1, required=True, type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The merged map to write.")
@click.option("--crs", default="auto", show_default=True,
              help="'auto' (the maps' CRS when they share one, else the UTM zone of the data) or e.g. EPSG:32631.")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def merge(maps, output, crs, overwrite, parents, quiet, debug):
    """Merge maps of neighbouring or overlapping regions into one map.

    An object held by several maps (the same label at the same stored position; within one quantum for
    a map reprojected to the output CRS) is kept once, from the first map that holds it.  The maps must
    share the quantum and the label table.  The header keeps every map's sources.  Prints a JSON summary.
    A map given twice (the same file, or the same SHA-256) is read once, with a warning.
    """
    check_paths([output], list(maps), overwrite=overwrite, parents=parents, what="map")
    summary = merge_maps(maps, output, crs=crs, progress=progress_printer(quiet))
    for warning in summary["warnings"]:
        click.echo(f"mapdb: warning: {warning}", err=True)
    click.echo(dumps_strict(summary))
