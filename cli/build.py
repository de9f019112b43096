"""``mapdb build``: sources to a map file."""

from __future__ import annotations

import click

from mapdb.build.blocks import DEFAULT_GAP_M, MAX_GAP_M
from mapdb.build.pipeline import SPOOL_CHOICES, build_map
from mapdb.mapfile.layout import DEFAULT_QUANTUM
from mapdb.outputs import dumps_strict
from mapdb.sources import DEFAULT_MIN_AREA_M2
from mapdb.sources.osm.index import NODE_INDEXES

from .options import (
    bbox_option,
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    progress_printer,
    quiet_option,
)


@click.command()
@click.argument("sources", nargs=-1, required=True, type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The map file to write.")
@click.option("--labels", "labels_file", type=click.Path(), help="TOML label table read over the defaults.")
@click.option("--crs", default="auto", show_default=True, help="'auto' (UTM zone of the data) or e.g. EPSG:32631.")
@bbox_option
@click.option("--quantum", default=DEFAULT_QUANTUM, show_default=True, type=finite_float(0.001, 1000),
              help="Stored resolution in metres.")
@click.option("--raster-classes", help="Class table for rasters: worldcover, corine or one from --labels.")
@click.option("--min-area", default=DEFAULT_MIN_AREA_M2, show_default=True, type=finite_float(0),
              help="Smallest land-cover patch kept, m^2.")
@click.option("--label-column", default="label", show_default=True, help="Label column of point/polygon layers.")
@click.option("--layer-crs", help="CRS of CSV layers with x,y columns.")
@click.option("--label", "layer_label", metavar="NAME",
              help="Label of every feature of a layer without a label column (e.g. building footprints).")
@click.option("--label-map", type=click.Path(), metavar="FILE.toml",
              help="Map a layer column's values to labels ([classes] table; 'column' names the column).")
@click.option("--node-index", type=click.Choice(NODE_INDEXES), default="auto", show_default=True,
              help="Where OSM node locations are kept: auto (memory for small extracts, a temporary file from "
                   "64 MiB), or a libosmium index.")
@click.option("--index-dir", type=click.Path(file_okay=False), metavar="DIR",
              help="Directory of the temporary files of large OSM extracts (default: the system's temp dir).")
@click.option("--spool", type=click.Choice(SPOOL_CHOICES), default="auto", show_default=True,
              help="Where objects read from OSM wait for the writer: auto (memory below 64 MiB of OSM input, "
                   "temporary files in --index-dir from there), memory, or file.  The map is the same.")
@click.option("--dem", "dems", multiple=True, type=click.Path(), metavar="DEM",
              help="Elevation raster (GeoTIFF or SRTM .hgt, any CRS; repeatable, a mosaic in the order given): "
                   "the map stores each object's ground elevation (format version 2).")
@click.option("--jobs", type=click.IntRange(1, 1024), default=None, metavar="N",
              help="Read the sources in parallel on a local Dask cluster of N processes.")
@click.option("--scheduler", metavar="tcp://HOST:PORT",
              help="Read the sources on an existing Dask cluster (its workers must see the same files).")
@click.option("--blocks/--no-blocks", default=True, show_default=True,
              help="Also store every group of touching buildings as one building_block object (what a "
                   "segmentation mask shows as one blob).")
@click.option("--block-gap", default=DEFAULT_GAP_M, show_default=True, type=finite_float(0, MAX_GAP_M),
              metavar="METRES", help="Buildings this close join one block.")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def build(sources, output, labels_file, crs, bbox, quantum, raster_classes, min_area, label_column, layer_crs,
          layer_label, label_map, node_index, index_dir, spool, dems, jobs, scheduler, blocks, block_gap,
          overwrite, parents, quiet, debug):
    """Build a map from OSM extracts, land-cover rasters and point/polygon layers.

    Prints a JSON summary (object counts per label, and "warnings") on stdout.  An existing OUTPUT is
    replaced only with --overwrite, and never when it is one of the sources or the labels file; its
    directory must exist unless --parents is given.

    Warnings (also on stderr, even with -q) do not stop the build: a source given twice (the same
    file, or the same SHA-256) is read once; with --crs auto, sources spanning more than 12 degrees of
    longitude (two UTM zones) are too far apart for one UTM zone: give a --crs that holds them all or
    build one map per area.

    Layers: each feature's label is read from --label-column; with --label-map FILE.toml the column's
    values are mapped to labels (values not listed are skipped and counted); a layer without the
    column gets --label NAME for every feature.

    Elevation: with --dem each object's ground elevation is sampled (bilinear) from the DEMs; objects
    outside them or on their nodata are counted in one warning, and DEMs covering none of the objects,
    without a CRS, in feet, or an SRTM .hgt tile renamed away from its tile name are refused.

    Large extracts: node locations go to a temporary file (--node-index, --index-dir) and progress
    says how much of the input is read and about how long is left.  With --jobs N or --scheduler the
    sources are read in parallel (one Dask task a source); the map is the same as without.

    Blocks (on by default): buildings of one source whose footprints touch or lie within --block-gap
    metres form a block, stored as one more object labelled building_block at the union's centroid
    with its area; the buildings stay.  Mask images are matched against buildings and blocks, point
    detections against buildings only.
    """
    if jobs is not None and scheduler is not None:
        raise click.UsageError("give --jobs (a local cluster) or --scheduler (an existing one), not both")
    check_paths([output], [*sources, labels_file, label_map, *dems], overwrite=overwrite, parents=parents,
                what="map")
    summary = build_map(sources, output, labels=labels_file, crs=crs, bbox=bbox, quantum=quantum,
                        raster_classes=raster_classes, min_area_m2=min_area, label_column=label_column,
                        layer_crs=layer_crs, label=layer_label, label_map=label_map, node_index=node_index,
                        index_dir=index_dir, spool=spool, jobs=jobs, scheduler=scheduler, dem=dems,
                        progress=progress_printer(quiet), blocks=blocks, block_gap=block_gap)
    for warning in summary["warnings"]:
        click.echo(f"mapdb: warning: {warning}", err=True)
    click.echo(dumps_strict(summary))
