"""``mapdb export``: a map's objects to GeoJSON, GeoPackage, GeoParquet, FlatGeobuf or CSV."""

from __future__ import annotations

import click

from mapdb.mapfile.export import EXPORT_CRS, LONLAT_CRS, default_export_crs, export_map
from mapdb.mapfile.reader import open_map

from .options import bbox_option, check_paths, debug_option, handle_errors, overwrite_option, parents_option


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="Output file; the format follows its ending (.geojson .gpkg .parquet .fgb .csv).")
@click.option("--crs", "crs", type=click.Choice(EXPORT_CRS), default=None,
              help="CRS of the points: 'lonlat' (WGS 84 longitude, latitude; EPSG:4326) or 'map' (the map's "
                   "projected CRS).  Default: lonlat for .geojson, as RFC 7946 requires; map for .gpkg .fgb "
                   ".parquet, which name their CRS.  A .geojson in the map CRS is not RFC 7946 (GDAL and "
                   "QGIS read its 'crs' member, web tools assume lon/lat).  CSV always has x,y and lon,lat.")
@bbox_option
@overwrite_option
@parents_option
@debug_option
@handle_errors
def export(map_file, output, crs, bbox, overwrite, parents, debug):
    """Export a map's objects as points with their label and area (m2).

    Every format also keeps each object's position in the map's CRS (columns x, y, exact to the
    map's quantum).  An existing OUTPUT is replaced only with --overwrite; its directory must exist unless
    --parents is given.
    """
    check_paths([output], [map_file], overwrite=overwrite, parents=parents)
    crs = crs or default_export_crs(output)
    with open_map(map_file) as m:
        n = export_map(m, output, bbox, crs=crs, parents=parents)
        map_crs = m.metadata["crs"]  # the CRS's name (m.crs may be a kilobyte of WKT)
        shown = f"in WGS 84 lon/lat ({LONLAT_CRS})" if crs == "lonlat" else f"in {map_crs}"
        if output.lower().endswith(".csv"):
            shown = f"with x,y in {map_crs} and WGS 84 lon,lat"
    click.echo(f"{n} objects written to {output} {shown}", err=True)
