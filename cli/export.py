"""``mapdb export``: a map's objects to GeoPackage, GeoJSON, GeoParquet, FlatGeobuf or CSV."""

from __future__ import annotations

import click

from mapdb.export import export_map
from mapdb.outputs import check_outputs
from mapdb.store import open_map

from .options import bbox_option, debug_option, handle_errors


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Output file; the format follows its ending (.gpkg .geojson .parquet .fgb .csv).")
@bbox_option
@debug_option
@handle_errors
def export(map_file, output, bbox, debug):
    """Export a map's objects as points in the map's CRS."""
    check_outputs([output], [map_file])
    with open_map(map_file) as m:
        n = export_map(m, output, bbox)
    click.echo(f"{n} objects written to {output}", err=True)
