"""``mapdb query``: localize images (JSON Lines of image objects) in a map."""

from __future__ import annotations

import os
import stat
import sys
from contextlib import ExitStack

import click

from mapdb.detections.images import Prior, check_prior, read_image_documents
from mapdb.errors import ImageInputError
from mapdb.localize.batch import localize_documents
from mapdb.localize.georef import FeatureWriter
from mapdb.localize.localizer import METHODS
from mapdb.mapfile.reader import open_map
from mapdb.match.fast import FastOptions
from mapdb.outputs import atomic_open, json_line

from .options import (
    TerminalProgress,
    check_paths,
    debug_option,
    finite_float,
    handle_errors,
    overwrite_option,
    parents_option,
    progress_printer,
    quiet_option,
    with_index,
)

# What --prior-crs gives for a geographic WGS 84 CRS (EPSG:4326, OGC:CRS84, ...): X,Y are lon,lat.
LONLAT = "lonlat"


def parse_prior(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``X,Y,R`` -> (x, y, r), or None; checked with the image prior's ranges once --prior-crs is known."""
    if value is None:
        return None
    try:
        x, y, r = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not three comma-separated numbers X,Y,R") from None
    return (x, y, r)


def parse_heading(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``DEG[,SIGMA]`` -> (deg,) or (deg, sigma), or None; checked with the image prior's ranges with --prior."""
    if value is None:
        return None
    try:
        values = tuple(float(v) for v in value.split(","))
    except ValueError:
        values = ()
    if len(values) not in (1, 2):
        raise click.BadParameter(f"{value!r} is not DEG or DEG,SIGMA (degrees)")
    return values


def parse_prior_crs(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """:data:`LONLAT` for a geographic WGS 84 CRS, else the pyproj CRS (which must be the map's), or None."""
    if value is None:
        return None
    from pyproj import CRS

    try:
        crs = CRS.from_user_input(value)
    except Exception:  # pyproj raises several kinds for text it cannot read
        raise click.BadParameter(f"{value!r} is not a CRS that pyproj knows") from None
    return LONLAT if crs.equals(CRS.from_epsg(4326), ignore_axis_order=True) else crs


def checked_prior(values: tuple[float, float, float], lonlat: bool, heading: tuple[float, ...] = ()) -> Prior:
    """The --prior (and --heading) values checked exactly as an image's ``prior`` is (the image schema's ranges)."""
    x, y, r = values
    try:
        return check_prior(x, y, r, f"'{x:g},{y:g},{r:g}'", lonlat=lonlat, heading=heading)
    except ImageInputError as exc:
        message = str(exc)
        if "prior.heading" in message:  # named by the --heading values, not the --prior ones
            given = ",".join(f"{v:g}" for v in heading)
            raise click.BadParameter(f"'{given}': {message.split(': ', 1)[1]}", param_hint="'--heading'") from None
        raise click.BadParameter(message, param_hint="'--prior'") from None


def _prior_argument(prior: Prior, prior_crs, map_crs: str):
    """What the localizer takes: (x, y, r) in the map's CRS, or a :class:`Prior` (lon/lat, which it converts, or with
    a heading)."""
    if prior.lonlat:
        return prior
    if prior_crs is not None and not (map_crs and prior_crs.equals(map_crs)):
        raise click.BadParameter(f"{_crs_name(prior_crs)}: give the prior in lon/lat (EPSG:4326) or in the "
                                 f"map's CRS ({_crs_name(map_crs) if map_crs else 'none'})",
                                 param_hint="'--prior-crs'")
    return prior if prior.heading_deg is not None else (prior.x, prior.y, prior.radius)


def _crs_name(crs) -> str:
    """``EPSG:n`` when the CRS has an authority code, else its name (a map's CRS may be a kilobyte of WKT)."""
    from pyproj import CRS

    crs = CRS.from_user_input(crs)
    authority = crs.to_authority()
    return ":".join(authority) if authority else crs.name


def _count_documents(images_file: str) -> int | None:
    """How many answers a regular file will give (for a progress bar's total); None for a stream."""
    if images_file == "-":
        return None
    try:
        if not stat.S_ISREG(os.stat(images_file).st_mode):
            return None
    except OSError:
        return None  # the reading proper reports it
    return sum(1 for _ in read_image_documents(images_file))


def _stdin_file() -> str | None:
    """``/dev/stdin`` when standard input is a regular file (``< a.jsonl -o a.jsonl`` must be refused too)."""
    try:
        return "/dev/stdin" if stat.S_ISREG(os.fstat(0).st_mode) else None
    except OSError:
        return None


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@click.argument("images_file", metavar="IMAGES", type=click.Path())
@click.option("-o", "--output", default="-", metavar="OUT.jsonl",
              help="Answers file (default stdout), written whole at the end or not at all.")
@click.option("--method", type=click.Choice(METHODS), default="fast", show_default=True,
              help="The fast matcher, or the paper's Algorithm 1 (seconds to minutes per image).")
@click.option("--prior", callback=parse_prior, metavar="X,Y,R",
              help="Search within R metres of X,Y for images that carry no prior of their own; X,Y in the map's "
                   "CRS, or see --prior-crs.")
@click.option("--prior-crs", callback=parse_prior_crs, metavar="CRS",
              help="CRS of --prior's X,Y: EPSG:4326 for lon,lat (degrees), or the map's own [default: the map's].")
@click.option("--heading", callback=parse_heading, metavar="DEG[,SIGMA]",
              help="With --prior, for the same images: which way their up points, degrees clockwise from the map's "
                   "grid north (a compass's, corrected), with its 1-sigma error SIGMA (0 < SIGMA <= 10, default 5). "
                   "An image with altitude_m and camera.fov_deg is then first matched with its heading and scale "
                   "known; the answer's \"path\" says which search decided (\"pose-prior\" or \"quads\").")
@click.option("--min-score", type=finite_float(0.0, 300.0), default=-FastOptions().log10_epsilon, show_default=True,
              help="Accept an answer only above this score (-log10 of its expected false alarms; the default "
                   "was calibrated on real places not in the map, see the README).")
@click.option("--geojson", "geojson_file", type=click.Path(), default=None, metavar="FIXES.geojson",
              help="Also write each accepted image's position as a GeoJSON Point (RFC 7946, lon/lat) with the "
                   "answer's fields as properties.")
@click.option("--footprints", "footprints_file", type=click.Path(), default=None, metavar="FOOTPRINTS.geojson",
              help="Also write each accepted image's footprint on the ground as a GeoJSON Polygon (lon/lat).")
@click.option("--no-areas", is_flag=True,
              help="Leave the objects' pixel areas (area_px) out of the evidence: answer as if they had none "
                   "(an answer rejected because of them says \"rejected_by\": \"areas\").")
@overwrite_option
@parents_option
@quiet_option
@debug_option
@handle_errors
def query(map_file, images_file, output, method, prior, prior_crs, heading, min_score, geojson_file,
          footprints_file, no_areas, overwrite, parents, quiet, debug):
    """Localize every image of IMAGES (JSON Lines; '-' for stdin) in MAP.

    Writes one JSON answer per image, in input order: status "ok" with the position (map CRS and
    lon/lat), heading, scale, 1-sigma error and score, or status "rejected" with the reason.  Objects
    whose label the map does not know are left out and counted in "skipped_labels"; an image is
    rejected only when fewer than 3 known objects remain.  A prior whose disc (widened by the image's
    footprint) lies outside the map's bounds is rejected saying how far outside it is.

    Every line on its own: lines are split on "\\n" only, blank lines are skipped, and each other
    line gets exactly one answer, in order.  A line that is not UTF-8, not JSON, not a JSON object,
    or has a number out of range (see the image schema) is rejected on its own; the other images
    are still answered.  A file that is one pretty-printed JSON object or array (up to 16 MiB) is
    read too.

    Streaming: input is read line by line and each answer is written (to stdout, flushed) before the
    next line is read, so a process can feed frames through a pipe one at a time.  With -o the
    answers go to a temporary file renamed to OUT.jsonl at the end: an error (a damaged map) leaves
    any earlier OUT.jsonl as it was.  An existing OUT.jsonl is replaced only with --overwrite, and never
    when it is MAP, MAP.qidx or IMAGES; its directory must exist unless --parents is given.

    --geojson and --footprints write the accepted answers as GIS layers (QGIS, ogrinfo, geopandas read
    them): one feature an accepted image, one geometry type a file, written like OUT.jsonl (whole at the
    end, the same rules).

    Progress (--method paper only, on stderr): a bar on a terminal; plain lines when IMAGES is a
    file and stderr is not a terminal; nothing with -q.
    """
    if heading is not None and prior is None:
        raise click.BadParameter("a heading needs a position: give --prior X,Y,R too", param_hint="'--heading'")
    checked = None if prior is None else checked_prior(prior, prior_crs == LONLAT, heading or ())
    for name, path in (("--geojson", geojson_file), ("--footprints", footprints_file)):
        if path == "-":  # stdout is the answers'; a second document there would make neither readable
            raise click.BadParameter("a layer is written to a file, not to stdout ('-')", param_hint=f"'{name}'")
    check_paths([output, geojson_file, footprints_file],
                [*with_index(map_file), _stdin_file() if images_file == "-" else images_file],
                overwrite=overwrite, parents=parents)
    say = _progress(method, images_file, quiet)
    with open_map(map_file) as m, ExitStack() as layers:
        prior_arg = None if checked is None else _prior_argument(checked, prior_crs, m.crs)
        documents = read_image_documents(images_file)
        # The layers' temporary files are renamed only once every answer is written, after OUT.jsonl's.
        writers = [layers.enter_context(FeatureWriter(layers.enter_context(atomic_open(path)), kind))
                   for path, kind in ((geojson_file, "fixes"), (footprints_file, "footprints")) if path]
        with atomic_open(output) as out:
            streaming = output == "-"
            # The answers and the bar share a terminal: the bar's line is erased before each answer.
            erase = say.clear if isinstance(say, TerminalProgress) and streaming and sys.stdout.isatty() else None
            options = FastOptions(log10_epsilon=-min_score, areas=not no_areas) if method == "fast" else None
            for record in localize_documents(documents, m, method, prior_arg, options=options):
                if erase:
                    erase()
                out.write(json_line(record.to_json()) + "\n")
                if streaming:
                    out.flush()  # the answer reaches a reader on a pipe before the next line is read
                for writer in writers:
                    writer.write(record)
                if say:
                    say.advance()
    if say:
        say.done()


def _progress(method: str, images_file: str, quiet: bool):
    """The paper method's progress (minutes per image), started; None when there is none to show."""
    say = progress_printer(quiet or method != "paper")
    if say is None or (images_file == "-" and not isinstance(say, TerminalProgress)):
        # A program streaming frames through a pipe wants answers, not chatter on its stderr.
        return None
    say.start(_count_documents(images_file), f"localizing ({method} method)")
    return say
