"""``mapdb index``: build a map's lost-in-space quad index."""

from __future__ import annotations

import click

from .options import (
    check_paths,
    debug_option,
    handle_errors,
    json_option,
    overwrite_option,
    progress_printer,
    quiet_option,
)


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.option("-o", "--output", type=click.Path(), help="Index file [default: MAP.qidx, beside the map].")
@click.option("--neighbours", default=8, show_default=True, type=click.IntRange(3, 12),
              help="The fast matcher's map_neighbours the index serves (its quads are each object's with "
                   "triples of its 5 nearest, a subset of these).")
@click.option("--workers", type=click.IntRange(1, 64), help="Processes generating quads [default: up to 2].")
@overwrite_option
@json_option
@quiet_option
@debug_option
@handle_errors
def index(map_file, output, neighbours, workers, overwrite, as_json, quiet, debug):
    """Build a map's lost-in-space quad index (a checksummed file beside the map).

    Lookups without a prior then read the index (memory-mapped, opened in milliseconds) instead of
    building one in memory.  The index records which map it was built from and is refused for any
    other, or for the map once rewritten: rebuild it then.  A map with blocks of buildings is indexed without
    its blocks: the index serves point images; images with building areas (mask blobs) search in memory.  An
    existing index (or OUTPUT) is replaced only with --overwrite.
    """
    from mapdb.match.index.stored import build_index, index_path
    from mapdb.outputs import dumps_strict

    target = output or index_path(map_file)
    check_paths([target], [map_file], overwrite=overwrite, what="index")
    summary = build_index(map_file, target, neighbours=neighbours, workers=workers, progress=progress_printer(quiet))
    if as_json:
        click.echo(dumps_strict(summary))
        return
    click.echo(f"{target}: {summary['quads']} quads of {summary['objects']} objects (of each object's "
               f"{summary['quad_neighbours']} nearest, for {summary['neighbours']} neighbours), {summary['cells']} "
               f"cells, {summary['bytes']} bytes "
               f"({summary['bytes'] / max(summary['objects'], 1):.0f} bytes/object), {summary['seconds']:.1f} s")
