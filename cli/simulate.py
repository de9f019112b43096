"""``mapdb simulate``: simulated camera images of a map, in the query input format, with their truth."""

from __future__ import annotations

import click

from mapdb.mapfile.reader import open_map
from mapdb.outputs import check_outputs
from mapdb.simulation.documents import write_images
from mapdb.simulation.poses import map_bbox_from_lonlat
from mapdb.simulation.simulate import simulate_images

from .options import (
    bbox_option,
    debug_option,
    finite,
    finite_float,
    handle_errors,
    parents_option,
    progress_printer,
    quiet_option,
)


def parse_range(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``"100"`` -> 100.0; ``"60:400"`` -> (60.0, 400.0), drawn uniformly per image."""
    if value is None:
        return None
    try:
        parts = [finite(v) for v in value.split(":")]
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a finite number or LOW:HIGH") from None
    if len(parts) == 1 and parts[0] > 0:
        return parts[0]
    if len(parts) == 2 and 0 < parts[0] <= parts[1]:
        return (parts[0], parts[1])
    raise click.BadParameter(f"{value!r} must be a positive number or LOW:HIGH with 0 < LOW <= HIGH")


def parse_fov(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """Like :func:`parse_range`, and below 180 degrees."""
    fov = parse_range(ctx, param, value)
    if fov is not None and max(fov if isinstance(fov, tuple) else (fov,)) >= 180.0:
        raise click.BadParameter(f"{value!r}: a field of view must be below 180 degrees")
    return fov


def parse_size(ctx: click.Context | None, param: click.Parameter | None, value: str):
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not WIDTHxHEIGHT (e.g. 640x480)") from None
    if w <= 0 or h <= 0:
        raise click.BadParameter(f"{value!r}: width and height must be positive")
    return w, h


def parse_yaw(ctx: click.Context | None, param: click.Parameter | None, value: str):
    if value.lower() == "random":
        return "random"
    try:
        return finite(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not finite degrees or 'random'") from None


rate = finite_float(0.0, 1.0)
# Past these the simulation means nothing, and huge values only cost memory or overflow.
MAX_SPURIOUS_RATE = 100.0
MAX_ATTITUDE_STD = 90.0
MAX_PRIOR_RADIUS = 2.0e7  # half the Earth's circumference, metres
MAX_PIXEL_STD = 1.0e6
MAX_MASK_NOISE_PX = 1000.0


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
@click.option("--render", type=click.Choice(["centroids", "masks"]), default="centroids", show_default=True,
              help="centroids: each visible map object at its projected centroid; masks: objects extracted from "
                   "label masks rendered from the --source outlines (heights, relief, border, merging).")
@click.option("--source", "source_file", type=click.Path(), metavar="EXTRACT.osm.pbf",
              help="With --render masks: the OSM extract the map was built from (its outlines are drawn).")
@click.option("--masks-dir", type=click.Path(file_okay=False), metavar="DIR",
              help="With --render masks: each image's mask is written here as ID.png, with classes.toml.")
@click.option("--mask-noise", type=finite_float(0.0, MAX_MASK_NOISE_PX), default=0.0, show_default=True,
              metavar="PX", help="With --render masks: grow or shrink each object's image by up to PX pixels.")
@click.option("--no-heights", is_flag=True, help="With --render masks: draw buildings flat (no relief).")
@bbox_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def simulate(map_file, output, n_images, altitude, fov, size, yaw, attitude_std, pixel_std, miss_rate,
             spurious_rate, label_noise, with_prior, with_attitude, with_altitude, min_objects, seed, render,
             source_file, masks_dir, mask_noise, no_heights, bbox, parents, quiet, debug):
    """Simulate downward-looking camera images of MAP, one JSON object per line.

    Camera positions are uniform over the map (or --bbox), keeping the image footprint inside it. Each
    image carries its "truth": camera nadir x, y (map CRS), heading, altitude, roll, pitch, the map
    objects it shows, and the "bound" (the fit with the true correspondences).

    With --render masks, each image's label mask is rendered from the outlines of --source (buildings
    extruded to their heights) and its objects are extracted as `mapdb objects` does; --miss-rate then
    leaves objects out of the mask, --min-objects counts blobs, and the truth says which map objects
    each blob covers.
    """
    if render == "masks":
        _check_render_options(source_file, masks_dir, pixel_std, spurious_rate)
        return _simulate_masks(map_file, output, n_images, source_file, masks_dir, parents, quiet, seed, bbox,
                               dict(altitude=altitude, fov_deg=fov, size=size, yaw=yaw, attitude_std=attitude_std,
                                    miss_rate=miss_rate, label_noise=label_noise, mask_noise_px=mask_noise,
                                    heights=not no_heights, with_prior=with_prior, with_attitude=with_attitude,
                                    with_altitude=with_altitude, min_objects=min_objects, seed=seed))
    if source_file is not None or masks_dir is not None or mask_noise or no_heights:
        raise click.UsageError("--source, --masks-dir, --mask-noise and --no-heights need --render masks")
    check_outputs([output], [map_file], parents=parents)
    say = progress_printer(quiet)
    with open_map(map_file) as m:
        area = map_bbox_from_lonlat(m.crs, bbox, within=m.bounds) if bbox else None
        images = simulate_images(
            m, n_images, altitude=altitude, fov_deg=fov, size=size, yaw=yaw, attitude_std=attitude_std,
            pixel_std=pixel_std, miss_rate=miss_rate, spurious_rate=spurious_rate, label_noise=label_noise,
            with_prior=with_prior, with_attitude=with_attitude, with_altitude=with_altitude, bbox=area,
            min_objects=min_objects, seed=seed, progress=say,
        )
    write_images(images, output)
    if say:
        n_obj = sum(len(im["objects"]) for im in images)
        say(f"{len(images)} images, {n_obj / max(len(images), 1):.1f} objects per image -> {output}")


def _check_render_options(source_file, masks_dir, pixel_std, spurious_rate) -> None:
    """Usage errors for --render masks: what it needs and the ideal-detector options it has no use for."""
    if source_file is None or masks_dir is None:
        raise click.UsageError("--render masks needs --source EXTRACT.osm.pbf and --masks-dir DIR")
    if pixel_std or spurious_rate:
        raise click.UsageError("--pixel-std and --spurious-rate describe the centroid detector; with --render masks "
                               "use --mask-noise")


def _simulate_masks(map_file, output, n_images, source_file, masks_dir, parents, quiet, seed, bbox, options) -> None:
    """``--render masks``: render, extract, and write the masks, then the documents (each file atomically)."""
    from collections import Counter
    from pathlib import Path

    from mapdb.errors import MapdbIOError
    from mapdb.simulation.outlines import read_scene
    from mapdb.simulation.rendered import png_bytes, simulate_masks, write_masks

    directory = Path(masks_dir)
    if directory.exists() and not directory.is_dir():
        raise MapdbIOError(f"{directory}: exists and is not a directory")
    if not directory.exists() and not parents and not directory.absolute().parent.is_dir():
        raise MapdbIOError(f"{directory}: directory {directory.absolute().parent} does not exist")
    check_outputs([output, directory / "classes.toml"] if directory.is_dir() else [output],
                  [map_file, source_file], parents=parents)
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
    write_masks(masks, masks_dir)
    write_images(images, output)
    if say:
        n_obj = sum(len(im["objects"]) for im in images)
        say(f"{len(images)} images, {n_obj / max(len(images), 1):.1f} blobs per image -> {output}, "
            f"masks in {masks_dir}")
