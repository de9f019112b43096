"""``mapdb navigate``: a flight's frames in, a navigated track out (particle filter + prior-aided queries)."""

from __future__ import annotations

import math
import sys
from contextlib import ExitStack
from typing import Any

import click

from mapdb.detections.images import read_image_documents
from mapdb.mapfile.reader import open_map
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.navigation.track import TrackRecord, line_path, plot_track, track_geojson, track_line_geojson
from mapdb.outputs import atomic_open, atomic_path, dumps_strict, json_line

from .evaluate import parse_plot
from .options import (
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    quiet_option,
    with_index,
)
from .query import LONLAT, _stdin_file, checked_prior, parse_prior, parse_prior_crs


def _initial(prior, prior_crs, m: Any) -> tuple[float, float, float] | None:
    """--initial in the map's CRS (converted from lon/lat with --initial-crs EPSG:4326; a warning when lon and lat
    look swapped)."""
    if prior is None:
        return None
    checked = checked_prior(prior, prior_crs == LONLAT)
    if not checked.lonlat:
        return (checked.x, checked.y, checked.radius)
    map_crs = m.crs
    if not map_crs:
        raise click.BadParameter("the map has no CRS to place a lon/lat position in", param_hint="'--initial'")
    from mapdb.geo import swapped_lonlat
    from mapdb.localize.lonlat import transformer

    swapped = swapped_lonlat(map_crs, m.bounds, checked.x, checked.y)
    if swapped:
        click.echo(f"mapdb: warning: --initial: {swapped}", err=True)

    x, y = transformer("EPSG:4326", map_crs).transform(checked.x, checked.y)
    return (float(x), float(y), checked.radius)


def _parse_mavlink(ctx: click.Context | None, param: click.Parameter | None, value: str | None) -> str | None:
    """``udpout:HOST:PORT``, checked for its form (whether it opens is checked before any frame is read)."""
    if value is None:
        return None
    from mapdb.navigation.mavlink import parse_address

    try:
        parse_address(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    return value


def _parse_mavlink_in(ctx: click.Context | None, param: click.Parameter | None, value: str | None) -> str | None:
    """``udpin:HOST:PORT``, checked for its form (whether it opens is checked before any frame is read)."""
    if value is None:
        return None
    kind, _, rest = value.partition(":")
    host, _, port = rest.rpartition(":")
    if kind != "udpin" or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise click.BadParameter(f"{value}: not udpin:HOST:PORT")
    return value


def _open_mavlink_in(address: str | None, stack: ExitStack) -> Any:
    """The autopilot's altitude input (None without ``--mavlink-in``), closed when ``stack`` closes."""
    if address is None:
        return None
    from mapdb.navigation.mavlink import MavlinkIn

    return stack.enter_context(MavlinkIn(address))


def _with_altitude(doc: Any, heard: Any, elevation: bool, home_elevation: float | None) -> Any:
    """The frame with the autopilot's latest altitude (``docs/mavlink.md``, *Input*) when it carries no altitude of
    its own and the autopilot has said one; else the frame as it is."""
    if heard is None or not isinstance(doc, dict) or "altitude_m" in doc or "baro_altitude_m" in doc:
        return doc
    fields = heard.poll().frame_fields(elevation=elevation, home_elevation_m=home_elevation)
    return {**doc, **fields} if fields else doc


def _open_mavlink(address: str | None, vision: bool, ground_alt: float, options: NavigatorOptions,
                  stack: ExitStack) -> Any:
    """The MAVLink output (None without ``--mavlink``), closed when ``stack`` closes."""
    if address is None:
        return None
    from mapdb.navigation.mavlink import MavlinkOptions, MavlinkOut

    out = MavlinkOut(address, MavlinkOptions(vision=vision, ground_alt_m=ground_alt,
                                             vert_accuracy_m=options.baro_std_m,
                                             attitude_std_deg=options.attitude_std))
    stack.enter_context(out)
    return out


def _number(doc: Any, field: str, positive: bool) -> float | None:
    """A frame's ``field`` if it is a finite number (and positive, if asked), else None: the MAVLink altitude
    from a height above ground (positive) or a barometric altitude above mean sea level (any sign)."""
    value = doc.get(field) if isinstance(doc, dict) else None
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) and (value > 0 or not positive) else None


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("flight_file", metavar="FLIGHT.jsonl", type=click.Path())
@click.option("-o", "--output", default="-", metavar="TRACK.jsonl",
              help="Track file, one JSON record per frame (default stdout, streamed).")
@click.option("--geojson", "geojson_file", default=None, metavar="TRACK.geojson",
              help="Also write the track as GeoJSON (RFC 7946, lon/lat): a point a frame in TRACK.geojson, the "
                   "path as a LineString in TRACK_line.geojson (one geometry type a file).")
@click.option("--plot", "plot_file", callback=parse_plot, default=None, metavar="TRACK.png",
              help="Also draw the track over the map.")
@click.option("--initial", callback=parse_prior, metavar="X,Y,R",
              help="Start within R metres of X,Y (map CRS, or see --initial-crs) [default: wait for a "
                   "lost-in-space fix].")
@click.option("--initial-crs", callback=parse_prior_crs, metavar="CRS", help="EPSG:4326 reads --initial as lon,lat.")
@click.option("--particles", type=click.IntRange(10, 1_000_000), default=NavigatorOptions.particles,
              show_default=True, help="Particles of the filter.")
@click.option("--attitude-std", type=finite_float(0.0, 10.0), default=NavigatorOptions.attitude_std,
              show_default=True, help="Accuracy of the frames' roll, pitch and yaw, degrees.")
@click.option("--seed", type=int, default=0, show_default=True, help="The filter's random draws.")
@click.option("--mavlink", "mavlink", callback=_parse_mavlink, default=None, metavar="udpout:HOST:PORT",
              help="Also send each record to an autopilot as MAVLink GPS_INPUT over UDP (needs "
                   "'mapdb[mavlink]'; docs/mavlink.md).")
@click.option("--mavlink-vision", is_flag=True,
              help="With --mavlink, also send GLOBAL_VISION_POSITION_ESTIMATE with its covariance.")
@click.option("--mavlink-ground-alt", type=finite_float(-1000.0, 10000.0), default=0.0, show_default=True,
              metavar="M", help="With --mavlink, the ground's height above mean sea level, added to each "
                                "frame's altitude_m (height above ground) for GPS_INPUT's altitude (a frame's "
                                "baro_altitude_m, above mean sea level, is sent as it is).")
@click.option("--mavlink-in", "mavlink_in", callback=_parse_mavlink_in, default=None, metavar="udpin:HOST:PORT",
              help="Hear the autopilot's altitude (ALTITUDE, GLOBAL_POSITION_INT, VFR_HUD) on this UDP port and give "
                   "the latest to each frame that carries no altitude of its own (a live stream; needs "
                   "'mapdb[mavlink]'; docs/mavlink.md).")
@click.option("--home-elevation", type=finite_float(-1000.0, 10000.0), default=None, metavar="M",
              help="With --mavlink-in, the take-off ground's height above mean sea level, for an autopilot that "
                   "says only its altitude above home.")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def navigate(map_file, flight_file, output, geojson_file, plot_file, initial, initial_crs, particles, attitude_std,
             seed, mavlink, mavlink_vision, mavlink_ground_alt, mavlink_in, home_elevation, overwrite, parents, quiet,
             debug):
    """Navigate the frames of FLIGHT.jsonl ('-' for stdin) over MAP: one track record per frame.

    A particle filter fuses the velocity from frame to frame with absolute fixes (the answer and its
    runner-up candidates); each frame's query uses the filter's prediction as its prior.  Per frame:
    position (map CRS and lon/lat), velocity, heading, covariance, the fix used or why none, the time
    spent.  Frames are read as they arrive and each record is written, flushed, before the next frame is
    read.  A bad frame (out of time order, no objects, a NaN or out-of-range sensor, not JSON, a line over
    16 MiB) is answered with its reason, and the next frames still are; only a file that cannot be read at
    all is an error.  One record per non-blank line.

    With --mavlink each record is also sent to an autopilot as it is made; a receiver that goes away
    does not stop the navigation: the messages it refused are counted and reported at the end.  With
    --mavlink-in a frame without an altitude gets the one the autopilot said last before the frame was read.
    """
    check_paths([output, geojson_file, geojson_file and line_path(geojson_file), plot_file],
                [*with_index(map_file), _stdin_file() if flight_file == "-" else flight_file], overwrite=overwrite,
                parents=parents)
    options = NavigatorOptions(particles=particles, attitude_std=attitude_std, seed=seed)
    # Records are kept only for the GeoJSON and the picture: a stream alone runs in constant memory.
    keep = bool(geojson_file or plot_file)
    records, frames, placed = [], 0, 0
    with ExitStack() as stack, open_map(map_file) as m:
        link = _open_mavlink(mavlink, mavlink_vision, mavlink_ground_alt, options, stack)  # before any frame
        heard = _open_mavlink_in(mavlink_in, stack)
        navigator = Navigator(m, options, initial=_initial(initial, initial_crs, m))
        documents = read_image_documents(flight_file)
        with atomic_open(output) as out:
            streaming = output == "-"
            for where, doc in documents:
                doc = _with_altitude(doc, heard, m.has_elevation, home_elevation)
                record = navigator.step(doc, where)
                out.write(_line(record, where) + "\n")
                if streaming:
                    out.flush()  # the record reaches a reader on a pipe before the next frame is read
                if link is not None:
                    link.send(record, _number(doc, "altitude_m", True), _number(doc, "baro_altitude_m", False))
                frames, placed = frames + 1, placed + record.placed
                if keep:
                    records.append(record)
        if geojson_file:
            with atomic_open(geojson_file) as f:
                f.write(dumps_strict(track_geojson(records)) + "\n")
            with atomic_open(line_path(geojson_file)) as f:
                f.write(dumps_strict(track_line_geojson(records)) + "\n")
        if plot_file:
            # the temporary name keeps the ending, from which matplotlib picks the format
            with atomic_path(plot_file, keep_suffix=True) as tmp:
                plot_track(records, m, tmp, title=f"{flight_file}: {frames} frames over {map_file}")
    if not quiet and output != "-":
        print(f"{frames} frames, {placed} placed -> {output}", file=sys.stderr)
    if link is not None and (link.lost or link.untimed or not quiet):
        print(link.summary(), file=sys.stderr)


def _line(record: TrackRecord, where: str) -> str:
    """The record's JSON line; a record that cannot be written becomes one that says so (the stream goes on)."""
    try:
        return json_line(record.to_json())
    except (ValueError, TypeError, OverflowError) as exc:
        fallback = {"id": None, "time_s": None, "status": "skipped",
                    "notes": [f"{where}: the frame's record could not be written ({type(exc).__name__})"]}
        return json_line(fallback)
