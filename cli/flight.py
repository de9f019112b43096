"""``mapdb simulate flight``: a simulated flight over a map, one frame document per line."""

from __future__ import annotations

import click

from mapdb.mapfile.reader import open_map
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.path import read_linestring
from mapdb.simulation.documents import write_images

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
              help="Height above ground, metres, or START:END changing linearly along the flight.")
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
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def flight(map_file, output, path_file, length, speed, fps, altitude, fov, size, turn_radius, pixel_std, miss_rate,
           spurious_rate, label_noise, attitude_std, turbulence, heading_bias, baro_std, baro_bias, imu_std, imu_bias,
           blackouts, map_gaps, seed, overwrite, parents, quiet, debug):
    """Simulate a flight over MAP: one frame document per line (JSON Lines).

    Each frame is a `mapdb query` image (objects, camera, attitude, altitude_m) with the autopilot's
    sensors beside it (time_s, attitude.yaw_deg, barometric altitude_m, optionally imu_velocity_mps),
    "map_withheld" inside a --map-gap, and the truth (x, y, heading, altitude, velocity).
    """
    if isinstance(fov, tuple):
        raise click.BadParameter("give one field of view, not a range", param_hint="'--fov'")
    check_paths([output], [map_file, path_file], overwrite=overwrite, parents=parents)
    options = FlightOptions(
        length_m=length, speed_mps=speed, fps=fps, altitude_m=altitude, fov_deg=fov, size=size,
        turn_radius_m=turn_radius, pixel_std=pixel_std, miss_rate=miss_rate, spurious_rate=spurious_rate,
        label_noise=label_noise, attitude_std=attitude_std, turbulence_deg=turbulence,
        heading_bias_deg=heading_bias, baro_std_m=baro_std, baro_bias_m=baro_bias, imu_std_mps=imu_std,
        imu_bias_mps=imu_bias, blackouts=blackouts, map_gaps=map_gaps, seed=seed,
    )
    say = progress_printer(quiet)
    with open_map(map_file) as m:
        waypoints = read_linestring(path_file, m.crs) if path_file else None
        frames = simulate_flight(m, options, waypoints, progress=say)
    write_images(frames, output)
    if say:
        seconds = frames[-1]["time_s"] if frames else 0.0
        n_obj = sum(len(f["objects"]) for f in frames) / max(len(frames), 1)
        say(f"{len(frames)} frames, {seconds:g} s, {n_obj:.1f} objects per frame -> {output}")
