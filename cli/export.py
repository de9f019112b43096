"""``mapdb export``: a map's objects to GeoJSON, GeoPackage, GeoParquet, FlatGeobuf, CSV or Shapefile."""

from __future__ import annotations

import click

from mapdb.mapfile.export import EXPORT_CRS, LONLAT_CRS, default_export_crs, export_map, output_files
from mapdb.mapfile.reader import open_map

from .options import bbox_option, check_paths, debug_option, handle_errors, overwrite_option, parents_option


def _output(given: str | None, option: str | None) -> str:
    """OUTPUT as an argument or as -o (one of them)."""
    if given and option and given != option:
        raise click.UsageError("give OUTPUT once: as an argument or with -o")
    output = given or option
    if not output:
        raise click.UsageError("missing OUTPUT (a file, or '-' for standard output)")
    return output


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("output", metavar="[OUTPUT]", required=False, type=click.Path(dir_okay=False,
                                                                                         allow_dash=True))
@click.option("-o", "--output", "output_option", type=click.Path(dir_okay=False, allow_dash=True),
              help="Output file; the format follows its ending (.geojson .gpkg .parquet .fgb .csv .shp); '-' "
                   "writes GeoJSON (or --format csv) to standard output.")
@click.option("--format", "stream_format", type=click.Choice(["geojson", "csv"]), default=None,
              help="The format of '-' (standard output) [default: geojson]; a file's ending says its own.")
@click.option("--crs", "crs", type=click.Choice(EXPORT_CRS), default=None,
              help="CRS of the points: 'lonlat' (WGS 84 longitude, latitude; EPSG:4326) or 'map' (the map's "
                   "projected CRS).  Default: lonlat for .geojson, as RFC 7946 requires; map for .gpkg .fgb "
                   ".parquet .shp, which name their CRS.  A .geojson in the map CRS is not RFC 7946 (GDAL and "
                   "QGIS read its 'crs' member, web tools assume lon/lat).  CSV always has x,y and lon,lat.")
@bbox_option
@overwrite_option
@parents_option
@debug_option
@handle_errors
def export(map_file, output, output_option, stream_format, crs, bbox, overwrite, parents, debug):
    """Export a map's objects as points with their label and area (m2), to OUTPUT ('-': standard output).

    Every format also keeps each object's position in the map's CRS (columns x, y, exact to the
    map's quantum).  A Shapefile (.shp) is written with its .shx, .dbf, .prj and .cpg beside it.  An existing
    OUTPUT (or Shapefile part) is replaced only with --overwrite; its directory must exist unless --parents is
    given.
    """
    output = _output(output, output_option)
    if stream_format and output != "-":
        raise click.BadParameter("only for '-' (standard output): a file's ending says its format",
                                 param_hint="'--format'")
    check_paths(output_files(output), [map_file], overwrite=overwrite, parents=parents)
    crs = crs or default_export_crs(output, stream_format)
    with open_map(map_file) as m:
        n = export_map(m, output, bbox, crs=crs, parents=parents, stream_format=stream_format)
        map_crs = m.metadata["crs"]  # the CRS's name (m.crs may be a kilobyte of WKT)
        shown = f"in WGS 84 lon/lat ({LONLAT_CRS})" if crs == "lonlat" else f"in {map_crs}"
        if output.lower().endswith(".csv") or (output == "-" and stream_format == "csv"):
            shown = f"with x,y in {map_crs} and WGS 84 lon,lat"
    click.echo(f"{n} objects written to {'standard output' if output == '-' else output} {shown}", err=True)
