"""``mapdb simulate``: simulated camera images of a map, in the query input format, with their truth."""

from __future__ import annotations

import click

from mapdb.mapfile.reader import open_map
from mapdb.simulation.documents import write_images
from mapdb.simulation.poses import map_bbox_from_lonlat
from mapdb.simulation.simulate import simulate_images, sparse_images
from mapdb.simulation.terrain import terrain_of

from .options import (
    MAX_ATTITUDE_STD,
    MAX_MASK_NOISE_PX,
    MAX_PIXEL_STD,
    MAX_PRIOR_RADIUS,
    MAX_SPURIOUS_RATE,
    bbox_option,
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    parse_fov,
    parse_range,
    parse_size,
    parse_yaw,
    progress_printer,
    quiet_option,
    rate,
    rendered_masks_options,
)


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.option("-o", "--output", default="-", metavar="IMAGES.jsonl", help="Output file (default stdout).")
@click.option("--n", "n_images", type=click.IntRange(0, None), default=100, show_default=True, help="Images.")
@click.option("--altitude", default="100", callback=parse_range, show_default=True,
              help="Height above ground, metres, or LOW:HIGH drawn per image.")
@click.option("--fov", default="35", callback=parse_fov, show_default=True,
              help="Horizontal field of view, degrees, or LOW:HIGH drawn per image.")
@click.option("--size", default="640x480", callback=parse_size, show_default=True, help="Image size WxH.")
@click.option("--yaw", default="0", callback=parse_yaw, show_default=True,
              help="Heading, degrees clockwise from north, or 'random'.")
@click.option("--attitude-std", type=finite_float(0.0, MAX_ATTITUDE_STD), default=0.0, show_default=True,
              help="Roll and pitch error std, degrees.")
@click.option("--pixel-std", type=finite_float(0.0, MAX_PIXEL_STD), default=0.0, show_default=True,
              help="Detector position error std per axis, pixels.")
@click.option("--miss-rate", type=rate, default=0.0, show_default=True,
              help="Fraction of visible objects the detector misses.")
@click.option("--spurious-rate", type=finite_float(0.0, MAX_SPURIOUS_RATE), default=0.0, show_default=True,
              help="Extra objects per true object, at random pixels.")
@click.option("--label-noise", type=rate, default=0.0, show_default=True,
              help="Fraction of objects given a wrong label.")
@click.option("--with-prior", type=finite_float(0.0, MAX_PRIOR_RADIUS, min_open=True), default=None, metavar="R",
              help="Add a prior of radius R metres centred within R of the truth.")
@click.option("--with-attitude", is_flag=True, help="Add the true roll and pitch (as an AHRS would).")
@click.option("--with-altitude", is_flag=True, help="Add the true height above ground (as an altimeter would).")
@click.option("--min-objects", type=click.IntRange(0, None), default=0, show_default=True,
              help="Redraw camera positions until at least this many map objects are in view (sparse maps).")
@click.option("--seed", type=int, default=0, show_default=True, help="Same seed, same images.")
@rendered_masks_options(
    render_help=("centroids: each visible map object at its projected centroid; masks: objects extracted from "
                   "label masks rendered from the --source outlines (heights, relief, border, merging)."),
    masks_dir_help=("With --render masks: each image's mask is written here as ID.png, with classes.toml; the folder "
                   "appears whole, and an existing one (not empty) is replaced only with --overwrite."))
@click.option("--mask-noise", type=finite_float(0.0, MAX_MASK_NOISE_PX), default=0.0, show_default=True,
              metavar="PX", help="With --render masks: grow or shrink each object's image by up to PX pixels.")
@click.option("--no-heights", is_flag=True, help="With --render masks: draw buildings flat (no relief).")
@click.option("--dem", "dems", multiple=True, type=click.Path(), metavar="DEM",
              help="Elevation raster(s) giving the objects' and the ground's heights (else the map's own, if it "
                   "holds elevation).")
@click.option("--altitude-above", type=click.Choice(["ground", "datum"]), default="ground", show_default=True,
              help="Over terrain: --altitude is the camera's height above the ground under it, or above the "
                   "datum (a barometric altitude).")
@click.option("--flat", is_flag=True, help="Ignore the map's elevation: every object on one plane.")
@bbox_option
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def simulate(map_file, output, n_images, altitude, fov, size, yaw, attitude_std, pixel_std, miss_rate,
             spurious_rate, label_noise, with_prior, with_attitude, with_altitude, min_objects, seed, render,
             source_file, masks_dir, mask_noise, no_heights, dems, altitude_above, flat, bbox, overwrite, parents,
             quiet, debug):
    """Simulate downward-looking camera images of MAP, one JSON object per line.

    Camera positions are uniform over the map (or --bbox), keeping the image footprint inside it. Each
    image carries its "truth": camera nadir x, y (map CRS), heading, altitude, roll, pitch, the map
    objects it shows, and the "bound" (the fit with the true correspondences).

    With --render masks, each image's label mask is rendered from the outlines of --source (buildings
    extruded to their heights) and its objects are extracted as `mapdb objects` does; --miss-rate then
    leaves objects out of the mask, --min-objects counts blobs, and the truth says which map objects
    each blob covers.

    Terrain: over a map that holds elevation (mapdb build --dem), or with --dem, every object stands at
    its ground elevation and the camera flies --altitude above the ground under it, or above the datum
    with --altitude-above datum.  The document's altitude_m (--with-altitude) is always the camera's
    height above the ground under it; the truth adds ground_m and altitude_datum_m.  --flat ignores
    the map's elevation.
    """
    if render == "masks":
        if dems or flat or altitude_above != "ground":
            raise click.UsageError("--dem, --flat and --altitude-above apply to --render centroids")
        _check_render_options(source_file, masks_dir, pixel_std, spurious_rate)
        rule = (overwrite, parents)
        return _simulate_masks(map_file, output, n_images, source_file, masks_dir, rule, quiet, seed, bbox,
                               dict(altitude=altitude, fov_deg=fov, size=size, yaw=yaw, attitude_std=attitude_std,
                                    miss_rate=miss_rate, label_noise=label_noise, mask_noise_px=mask_noise,
                                    heights=not no_heights, with_prior=with_prior, with_attitude=with_attitude,
                                    with_altitude=with_altitude, min_objects=min_objects, seed=seed))
    if source_file is not None or masks_dir is not None or mask_noise or no_heights:
        raise click.UsageError("--source, --masks-dir, --mask-noise and --no-heights need --render masks")
    if flat and dems:
        raise click.UsageError("--flat and --dem contradict each other")
    check_paths([output], [map_file, *dems], overwrite=overwrite, parents=parents)
    say = progress_printer(quiet)
    with open_map(map_file) as m:
        area = map_bbox_from_lonlat(m.crs, bbox, within=m.bounds) if bbox else None
        terrain = None if flat else terrain_of(m, dems, altitude_above)
        images = simulate_images(
            m, n_images, altitude=altitude, fov_deg=fov, size=size, yaw=yaw, attitude_std=attitude_std,
            pixel_std=pixel_std, miss_rate=miss_rate, spurious_rate=spurious_rate, label_noise=label_noise,
            with_prior=with_prior, with_attitude=with_attitude, with_altitude=with_altitude, bbox=area,
            min_objects=min_objects, seed=seed, progress=say, terrain=terrain,
        )
    write_images(images, output)
    if say:
        n_obj = sum(len(im["objects"]) for im in images)
        say(f"{len(images)} images, {n_obj / max(len(images), 1):.1f} objects per image -> {output}")
    _warn_if_sparse(images, map_file)


def _warn_if_sparse(images, map_file) -> None:
    """A warning (even with -q: the images are written, and mostly useless) when most images show too little."""
    sparse = sparse_images(images, map_file)
    if sparse:
        click.echo(f"mapdb: warning: {sparse}", err=True)


def _check_render_options(source_file, masks_dir, pixel_std, spurious_rate) -> None:
    """Usage errors for --render masks: what it needs and the ideal-detector options it has no use for."""
    if source_file is None or masks_dir is None:
        raise click.UsageError("--render masks needs --source EXTRACT.osm.pbf and --masks-dir DIR")
    if pixel_std or spurious_rate:
        raise click.UsageError("--pixel-std and --spurious-rate describe the centroid detector; with --render masks "
                               "use --mask-noise")


def _simulate_masks(map_file, output, n_images, source_file, masks_dir, rule, quiet, seed, bbox, options) -> None:
    """``--render masks``: render, extract, and write the masks folder (whole: it appears complete or not at all),
    then the documents.  ``rule`` is (overwrite, parents): an existing folder or OUTPUT is replaced only with
    --overwrite, and never when it is or holds an input."""
    from collections import Counter

    from mapdb.analysis.outputs import output_folder
    from mapdb.simulation.outlines import read_scene
    from mapdb.simulation.rendered import png_bytes, simulate_masks, write_masks

    overwrite, parents = rule
    inputs = [map_file, source_file]
    with output_folder(masks_dir, inputs, overwrite=overwrite, parents=parents) as folder:
        # after the folder's own checks: OUTPUT may lie in it, and --parents then makes the folder
        check_paths([output], inputs, overwrite=overwrite, parents=parents)
        say = progress_printer(quiet)
        with open_map(map_file) as m:
            area = map_bbox_from_lonlat(m.crs, bbox, within=m.bounds) if bbox else None
            counts: Counter[str] = Counter()
            scene = read_scene(source_file, m.all(), seed=seed, counts=counts)
            skipped = ", ".join(f"{n:,} {kind.replace('_', ' ')}" for kind, n in sorted(counts.items()) if n)
            if say and skipped:
                say(f"{source_file}: outlines left out: {skipped}")
            images, masks = [], []
            for doc, mask in simulate_masks(m, scene, n_images, bbox=area, progress=say, **options):
                images.append(doc)
                masks.append((doc["truth"]["mask"], png_bytes(mask)))
        classes = "".join(f'{code + 1} = "{name}"\n' for code, name in enumerate(scene.labels))
        masks.append(("classes.toml", f"# mask codes of mapdb simulate --render masks\n[classes]\n{classes}".encode()))
        write_masks(masks, folder)
    write_images(images, output)
    if say:
        n_obj = sum(len(im["objects"]) for im in images)
        say(f"{len(images)} images, {n_obj / max(len(images), 1):.1f} blobs per image -> {output}, "
            f"masks in {masks_dir}")
    _warn_if_sparse(images, map_file)
