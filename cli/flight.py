"""``mapdb simulate flight``: a simulated flight over a map, one frame document per line."""

from __future__ import annotations

import click

from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import ALTITUDE_ABOVE, FlightOptions, simulate_flight
from mapdb.navigation.path import read_linestring
from mapdb.navigation.rendered import MAX_MASK_OFFSET_PX
from mapdb.simulation.documents import write_images
from mapdb.simulation.terrain import terrain_of

from .options import (
    MAX_ATTITUDE_STD,
    MAX_PIXEL_STD,
    MAX_SPURIOUS_RATE,
    check_paths,
    debug_option,
    finite,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    parse_fov,
    parse_size,
    progress_printer,
    quiet_option,
    rate,
    rendered_masks_options,
)


def parse_windows(ctx: click.Context | None, param: click.Parameter | None, values: tuple[str, ...]):
    """``START:SECONDS`` (repeatable) -> ((start, seconds), ...)."""
    windows = []
    for value in values:
        try:
            start, seconds = (finite(v) for v in value.split(":"))
        except ValueError:
            raise click.BadParameter(f"{value!r} is not START:SECONDS (two finite numbers)") from None
        if start < 0 or seconds <= 0:
            raise click.BadParameter(f"{value!r}: START must be >= 0 and SECONDS > 0")
        windows.append((start, seconds))
    return tuple(windows)


def parse_profile(ctx: click.Context | None, param: click.Parameter | None, value: str):
    """``"150"`` -> 150.0; ``"120:180"`` -> (120.0, 180.0), from the first height to the second along the flight."""
    try:
        parts = tuple(finite(v) for v in value.split(":"))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a height in metres or START:END") from None
    if len(parts) not in (1, 2) or min(parts) <= 0 or max(parts) > 100_000:
        raise click.BadParameter(f"{value!r}: one or two heights, each in (0, 100000] metres")
    return parts[0] if len(parts) == 1 else parts


positive = finite_float(0.0, 1e6, min_open=True)
std = finite_float(0.0, 1e4)


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.option("-o", "--output", default="-", metavar="FLIGHT.jsonl", help="Output file (default stdout).")
@click.option("--path", "path_file", type=click.Path(), metavar="LINE.geojson",
              help="Fly this GeoJSON LineString (lon/lat) [default: a survey pattern over the map's densest part].")
@click.option("--length", type=positive, default=None, metavar="M",
              help="Metres flown [default: the whole --path, or 5000 of the survey].")
@click.option("--speed", type=positive, default=20.0, show_default=True, help="Ground speed, m/s.")
@click.option("--fps", type=positive, default=10.0, show_default=True, help="Frames per second.")
@click.option("--altitude", default="150", callback=parse_profile, show_default=True,
              help="Height above ground, metres, or START:END changing linearly along the flight; over terrain "
                   "a barometric altitude (see --altitude-above).")
@click.option("--fov", default="70", callback=parse_fov, show_default=True, help="Horizontal field of view, degrees.")
@click.option("--size", default="640x480", callback=parse_size, show_default=True, help="Image size WxH.")
@click.option("--turn-radius", type=positive, default=75.0, show_default=True, help="Radius of the turns, metres.")
@click.option("--pixel-std", type=finite_float(0.0, MAX_PIXEL_STD), default=0.0, show_default=True,
              help="Detector position error std per axis, pixels.")
@click.option("--miss-rate", type=rate, default=0.0, show_default=True, help="Fraction of visible objects missed.")
@click.option("--spurious-rate", type=finite_float(0.0, MAX_SPURIOUS_RATE), default=0.0, show_default=True,
              help="Extra objects per true object, at random pixels.")
@click.option("--label-noise", type=rate, default=0.0, show_default=True, help="Fraction of objects mislabelled.")
@click.option("--attitude-std", type=finite_float(0.0, MAX_ATTITUDE_STD), default=0.0, show_default=True,
              help="Error std of the reported roll, pitch and yaw, degrees per frame.")
@click.option("--turbulence", type=finite_float(0.0, 30.0), default=0.5, show_default=True,
              help="True roll and pitch wobble std, degrees (reported, with --attitude-std error).")
@click.option("--heading-bias", type=std, default=1.0, show_default=True,
              help="Std of the yaw's constant bias (a magnetometer's), degrees.")
@click.option("--baro-std", type=std, default=0.3, show_default=True, help="Barometric altitude noise std, m.")
@click.option("--baro-bias", type=std, default=2.0, show_default=True, help="Std of its constant bias, m.")
@click.option("--imu-std", type=std, default=None, metavar="MPS",
              help="Add an inertial velocity with this noise std per axis, m/s [default: none].")
@click.option("--imu-bias", type=std, default=0.2, show_default=True, help="Std of its constant bias per axis, m/s.")
@click.option("--blackout", "blackouts", multiple=True, callback=parse_windows, metavar="START:SECONDS",
              help="No detections at all from START for SECONDS (repeatable).")
@click.option("--map-gap", "map_gaps", multiple=True, callback=parse_windows, metavar="START:SECONDS",
              help="Mark frames from START for SECONDS as map-withheld: navigate does not query the map there.")
@click.option("--seed", type=int, default=0, show_default=True, help="Same seed, same flight.")
@rendered_masks_options(
    render_help=("centroids: each visible map object at its projected centroid; masks: each frame's objects "
                 "extracted from a label mask rendered from the --source outlines with the frame's pose."),
    masks_dir_help=("With --render masks: also write each frame's mask as ID.png, with classes.toml (the folder "
                    "appears whole; an existing one, not empty, is replaced only with --overwrite)."))
@click.option("--no-heights", is_flag=True, help="With --render masks: draw buildings flat (no relief).")
@click.option("--mask-erode", type=click.IntRange(0, MAX_MASK_OFFSET_PX), default=0, metavar="PX",
              help="With --render masks: erode every region of the mask by PX pixels.")
@click.option("--mask-dilate", type=click.IntRange(0, MAX_MASK_OFFSET_PX), default=0, metavar="PX",
              help="With --render masks: dilate every region of the mask by PX pixels.")
@click.option("--blob-miss-rate", type=rate, default=0.0, show_default=True,
              help="With --render masks: fraction of objects left out of the masks.")
@click.option("--blob-spurious-rate", type=rate, default=0.0, show_default=True,
              help="With --render masks: false blobs per object in view, painted on the background.")
@click.option("--dem", "dems", multiple=True, type=click.Path(), metavar="DEM",
              help="Elevation raster(s) giving the objects' and the ground's heights (else the map's own, if it "
                   "holds elevation).")
@click.option("--altitude-above", type=click.Choice(ALTITUDE_ABOVE), default="start", show_default=True,
              help="Over terrain: the aircraft flies a barometric altitude, --altitude above the ground under the "
                   "path's start (one pressure altitude), above the ground under each frame (a terrain-following "
                   "plan), or above the datum.")
@click.option("--flat", is_flag=True, help="Ignore the map's elevation: every object on one plane.")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def flight(map_file, output, path_file, length, speed, fps, altitude, fov, size, turn_radius, pixel_std, miss_rate,
           spurious_rate, label_noise, attitude_std, turbulence, heading_bias, baro_std, baro_bias, imu_std, imu_bias,
           blackouts, map_gaps, seed, render, source_file, masks_dir, no_heights, mask_erode, mask_dilate,
           blob_miss_rate, blob_spurious_rate, dems, altitude_above, flat, overwrite, parents, quiet, debug):
    """Simulate a flight over MAP: one frame document per line (JSON Lines).

    Each frame is a `mapdb query` image (objects, camera, attitude, altitude_m) with the autopilot's
    sensors beside it (time_s, attitude.yaw_deg, barometric altitude_m, optionally imu_velocity_mps),
    "map_withheld" inside a --map-gap, and the truth (x, y, heading, altitude, velocity).

    With --render masks each frame's objects are the blobs of a label mask rendered from the --source
    outlines (buildings extruded to their heights, the frame's roll, pitch and bank), as `mapdb objects`
    extracts them, with the segmentation errors --mask-erode/--mask-dilate, --blob-miss-rate and
    --blob-spurious-rate in place of the detector's.

    Terrain: over a map that holds elevation (mapdb build --dem), or with --dem, every object stands at
    its ground elevation and the aircraft flies a barometric altitude: --altitude above the ground under
    the path's start (--altitude-above ground: under each frame, a terrain-following plan; datum: above
    the datum).  Each frame then carries
    baro_altitude_m (the barometer: above the datum, with its bias and noise) and no altitude_m (nothing
    aboard measures the height above the ground); the truth adds ground_m and altitude_datum_m.  --flat
    ignores the map's elevation (the frames of a flight before terrain, byte for byte).
    """
    if isinstance(fov, tuple):
        raise click.BadParameter("give one field of view, not a range", param_hint="'--fov'")
    masks = dict(source_file=source_file, masks_dir=masks_dir, no_heights=no_heights, erode=mask_erode,
                 dilate=mask_dilate, miss=blob_miss_rate, spurious=blob_spurious_rate)
    _check_render(render, masks, {"--pixel-std": pixel_std, "--miss-rate": miss_rate,
                                  "--spurious-rate": spurious_rate, "--label-noise": label_noise})
    if render == "masks" and (dems or altitude_above != "start"):
        raise click.UsageError("--dem and --altitude-above apply to --render centroids (masks draw flat ground)")
    if flat and dems:
        raise click.UsageError("--flat and --dem contradict each other")
    check_paths([output], [map_file, path_file, source_file, *dems], overwrite=overwrite, parents=parents)
    options = FlightOptions(
        length_m=length, speed_mps=speed, fps=fps, altitude_m=altitude, fov_deg=fov, size=size,
        turn_radius_m=turn_radius, pixel_std=pixel_std, miss_rate=miss_rate, spurious_rate=spurious_rate,
        label_noise=label_noise, attitude_std=attitude_std, turbulence_deg=turbulence,
        heading_bias_deg=heading_bias, baro_std_m=baro_std, baro_bias_m=baro_bias, imu_std_mps=imu_std,
        imu_bias_mps=imu_bias, blackouts=blackouts, map_gaps=map_gaps, seed=seed, altitude_above=altitude_above,
    )
    say = progress_printer(quiet)
    if render == "masks":
        frames = _masks_flight(map_file, path_file, options, masks, (overwrite, parents), say)
    else:
        with open_map(map_file) as m:
            waypoints = read_linestring(path_file, m.crs) if path_file else None
            terrain = None if flat else terrain_of(m, dems)
            frames = simulate_flight(m, options, waypoints, progress=say, terrain=terrain)
    write_images(frames, output)
    if say:
        seconds = frames[-1]["time_s"] if frames else 0.0
        n_obj = sum(len(f["objects"]) for f in frames) / max(len(frames), 1)
        say(f"{len(frames)} frames, {seconds:g} s, {n_obj:.1f} objects per frame -> {output}")


def _check_render(render: str, masks: dict, detector: dict) -> None:
    """Usage errors: the mask options need --render masks, which needs --source and has no use for the centroid
    detector's errors."""
    if render != "masks":
        given = [name for name, value in (("--source", masks["source_file"]), ("--masks-dir", masks["masks_dir"]),
                                          ("--no-heights", masks["no_heights"]), ("--mask-erode", masks["erode"]),
                                          ("--mask-dilate", masks["dilate"]), ("--blob-miss-rate", masks["miss"]),
                                          ("--blob-spurious-rate", masks["spurious"])) if value]
        if given:
            raise click.UsageError(f"{', '.join(given)} {'needs' if len(given) == 1 else 'need'} --render masks")
        return
    if masks["source_file"] is None:
        raise click.UsageError("--render masks needs --source EXTRACT.osm.pbf")
    if masks["erode"] and masks["dilate"]:
        raise click.UsageError("give --mask-erode or --mask-dilate, not both")
    used = [name for name, value in detector.items() if value]
    if used:
        raise click.UsageError(f"{', '.join(used)} describe the centroid detector; with --render masks use "
                               "--mask-erode/--mask-dilate, --blob-miss-rate and --blob-spurious-rate")


def _masks_flight(map_file, path_file, options: FlightOptions, masks: dict, rule: tuple[bool, bool], say) -> list:
    """``--render masks``: the outlines read, the flight rendered, the masks folder written whole (when asked)
    before the frames; ``rule`` is (overwrite, parents)."""
    from contextlib import nullcontext

    from mapdb.analysis.outputs import output_folder
    from mapdb.navigation.rendered import FlightRender
    from mapdb.simulation.outlines import read_scene
    from mapdb.simulation.rendered import png_bytes, write_masks

    overwrite, parents = rule
    source = masks["source_file"]
    folder_rule = (output_folder(masks["masks_dir"], [map_file, source], overwrite=overwrite, parents=parents)
                   if masks["masks_dir"] else nullcontext(None))
    with folder_rule as folder, open_map(map_file) as m:
        waypoints = read_linestring(path_file, m.crs) if path_file else None
        scene = read_scene(source, m.all(), seed=options.seed)
        render = FlightRender(scene, str(source), heights=not masks["no_heights"],
                              mask_offset_px=int(masks["dilate"] - masks["erode"]), blob_miss_rate=masks["miss"],
                              blob_spurious_rate=masks["spurious"])
        pngs: list[tuple[str, bytes]] = []
        keep = (lambda frame_id, mask: pngs.append((f"{frame_id}.png", png_bytes(mask)))) if folder else None
        frames = simulate_flight(m, options, waypoints, progress=say, render=render, on_mask=keep)
        if folder is not None:
            classes = "".join(f'{code + 1} = "{name}"\n' for code, name in enumerate(scene.labels))
            pngs.append(("classes.toml", f"# mask codes of mapdb simulate flight --render masks\n[classes]\n"
                                         f"{classes}".encode()))
            write_masks(pngs, folder)
    return frames
