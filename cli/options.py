"""Options and error handling shared by every mapdb command.

The library raises :class:`mapdb.errors.MapdbError` subclasses with one-line
messages; here they become ``mapdb: error: ...`` on stderr and exit status 1,
with the traceback only under ``--debug``.

Progress goes to stderr (stdout is for results): a ``click.progressbar`` when stderr is a terminal,
plain lines when it is not (a log, a pipe), nothing with ``-q``.  The library reports through its
:class:`mapdb.progress.Progress` protocol and never imports click.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import time
from collections.abc import Callable, Iterable
from typing import Any

import click

from mapdb.errors import MapdbError
from mapdb.outputs import check_outputs
from mapdb.progress import LineProgress, Progress


class FiniteFloat(click.FloatRange):
    """A float option that refuses NaN and infinities (``click.FloatRange`` lets NaN through, since every
    comparison with NaN is false), optionally within a range."""

    name = "float"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv


def finite_float(min: float | None = None, max: float | None = None, *, min_open: bool = False,
                 max_open: bool = False) -> FiniteFloat:
    """The click type of every float option: finite, and within ``[min, max]`` (or open ends)."""
    return FiniteFloat(min, max, min_open=min_open, max_open=max_open)


def finite(text: str) -> float:
    """``float(text)`` for option callbacks, refusing NaN and infinities with ``ValueError``."""
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not finite")
    return value


debug_option = click.option("--debug", is_flag=True, help="Show tracebacks for errors.")
overwrite_option = click.option("--overwrite", is_flag=True,
                                help="Replace existing outputs (never an input); without it an existing output is "
                                     "refused before any work.")
json_option = click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")
quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress messages on stderr.")
parents_option = click.option("--parents", is_flag=True,
                               help="Create the output's missing directories (as mkdir -p); without it a "
                                    "missing directory is an error.")


def parse_bbox(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``minlon,minlat,maxlon,maxlat`` -> tuple of four floats, or None.

    ``minlon > maxlon`` is a box crossing the antimeridian (GeoJSON's convention); see
    :func:`mapdb.geo.check_bbox` for what is refused.
    """
    from mapdb.geo import check_bbox  # the library's rule, so that the CLI and the API agree

    if value is None:
        return None
    try:
        return check_bbox(value.split(","))
    except ValueError as exc:
        raise click.BadParameter(f"{value!r}: {exc}") from None


bbox_option = click.option(
    "--bbox", callback=parse_bbox, metavar="MINLON,MINLAT,MAXLON,MAXLAT", help="Clip to this lon/lat box."
)


def check_paths(outputs: Iterable[str | os.PathLike[str] | None], inputs: Iterable[str | os.PathLike[str] | None],
                *, overwrite: bool, parents: bool = False, what: str = "file") -> None:
    """The output rule of every command, applied before any work (:func:`mapdb.outputs.check_outputs`).

    An output that is one of ``inputs`` is refused even with ``--overwrite``; an existing output is refused
    without it (``OUT: exists; pass --overwrite to replace this WHAT``); ``-`` (stdout) and character
    devices (``/dev/null``) are exempt; the outputs' directories are made (``--parents``) only once every
    check has passed.
    """
    check_outputs(outputs, inputs, parents=parents, overwrite=overwrite, what=what)


def with_index(map_file: str) -> list[str]:
    """A map and its quad index (``MAP.qidx``, read by lost-in-space lookups): inputs no output may replace."""
    from mapdb.match.index.layout import index_path

    return [map_file, str(index_path(map_file))]


def fail(message: str) -> None:
    _abandon_bars()
    click.echo(f"mapdb: error: {message}", err=True)
    sys.exit(1)


def handle_errors(func: Callable[..., Any]) -> Callable[..., Any]:
    """Turn library errors (and a few builtins that bad input raises) into one-line messages.

    The wrapped command must take a ``debug`` keyword (add :data:`debug_option`).
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        debug = kwargs.get("debug", False)
        try:
            return func(*args, **kwargs)
        except BrokenPipeError:
            _abandon_bars()
            # The reader stopped (``mapdb query MAP - | head -1``): stop quietly, as ``yes | head`` does.
            # Standard output is pointed at /dev/null so that the interpreter's last flush cannot complain.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(141)
        except (MapdbError, OSError, MemoryError) as exc:
            if debug:
                raise
            fail(str(exc) or exc.__class__.__name__)
        # KeyboardInterrupt (SIGINT, and SIGTERM as cli.main raises it) passes on to cli.main, which ends the
        # process with 130 or 143 once every ``with`` block has removed its temporary files.
        finally:
            _abandon_bars()  # a traceback under --debug must not leave the terminal's cursor hidden

    return wrapper


# Bars drawn and not yet done: an error erases them before its message.
_LIVE_BARS: list[TerminalProgress] = []
# Erase the current terminal line, and show the cursor again (click hides it while a bar is drawn).
_ERASE_LINE = "\r\033[K"
_SHOW_CURSOR = "\033[?25h"
# A bar is redrawn at most this often: a fast count (a million images) would otherwise spend its time on
# the terminal.
_REDRAW_S = 0.1


class TerminalProgress:
    """:class:`mapdb.progress.Progress` drawn with ``click.progressbar`` on a terminal.

    A count is a bar (position, percentage and time left; a moving mark and the position when the
    total is not known); messages are printed on lines of their own above it.
    """

    def __init__(self, stream: Any) -> None:
        self.stream = stream
        self.bar: Any = None
        self._pending = 0  # steps counted and not yet drawn
        self._drawn_at = 0.0

    def __call__(self, message: str) -> None:
        self.clear()
        click.echo(message, file=self.stream)
        self._redraw()

    def start(self, total: int | None, label: str) -> None:
        self.done()
        # click takes the length from an iterable; one without a length makes a bar of unknown total.
        nothing: tuple[int, ...] = ()
        unsized = None if total is not None else (item for item in nothing)
        self.bar = click.progressbar(unsized, length=total, label=label, file=self.stream, show_pos=True,
                                     show_percent=total is not None)
        self.bar.__enter__()
        self._pending, self._drawn_at = 0, time.monotonic()
        _LIVE_BARS.append(self)

    def advance(self, n: int = 1) -> None:
        if self.bar is None:
            return
        self._pending += n
        if time.monotonic() - self._drawn_at >= _REDRAW_S:
            self._flush()

    def _flush(self) -> None:
        self.bar.update(self._pending)
        self._pending, self._drawn_at = 0, time.monotonic()

    def done(self) -> None:
        if self.bar is None:
            return
        self._flush()
        self.bar.finished = True  # a bar of unknown total is drawn full at its end
        self._redraw()
        self.bar.render_finish()
        self._forget()

    def clear(self) -> None:
        """Erase the bar's line (before writing a line of text on the same terminal)."""
        if self.bar is not None:
            self.stream.write(_ERASE_LINE)
            self.stream.flush()

    def abandon(self) -> None:
        """Erase the bar and give the cursor back (an error follows)."""
        if self.bar is not None:
            self.stream.write(_ERASE_LINE + _SHOW_CURSOR)
            self.stream.flush()
            self._forget()

    def _redraw(self) -> None:
        if self.bar is not None:
            self.bar._last_line = None  # click redraws only a changed line, and ours was just erased
            self.bar.render_progress()

    def _forget(self) -> None:
        self.bar = None
        if self in _LIVE_BARS:
            _LIVE_BARS.remove(self)


def _abandon_bars() -> None:
    while _LIVE_BARS:
        _LIVE_BARS[-1].abandon()


def progress_printer(quiet: bool) -> Progress | None:
    """Where a command's progress goes: stderr (stdout is for results only), or nowhere with ``quiet``.

    A bar on a terminal (:class:`TerminalProgress`), plain lines otherwise (:class:`mapdb.progress.LineProgress`).
    Either is also a plain message callback.
    """
    if quiet:
        return None
    stream = sys.stderr
    if stream.isatty():
        return TerminalProgress(stream)
    return LineProgress(lambda message: click.echo(message, err=True))


# ------------------------------------------------------------------------------ camera and detector options
# The parsers, limits and options of the commands that simulate images (``simulate``, ``simulate flight``,
# ``analyze``, ``bench paper``): defined here, so that every command module imports this one and none another.

rate = finite_float(0.0, 1.0)
# Past these the simulation means nothing, and huge values only cost memory or overflow.
MAX_SPURIOUS_RATE = 100.0
MAX_ATTITUDE_STD = 90.0
MAX_PRIOR_RADIUS = 2.0e7  # half the Earth's circumference, metres
MAX_PIXEL_STD = 1.0e6
MAX_MASK_NOISE_PX = 1000.0


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
    """``"640x480"`` -> (640, 480)."""
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not WIDTHxHEIGHT (e.g. 640x480)") from None
    if w <= 0 or h <= 0:
        raise click.BadParameter(f"{value!r}: width and height must be positive")
    return w, h


def parse_yaw(ctx: click.Context | None, param: click.Parameter | None, value: str):
    """Finite degrees, or ``"random"``."""
    if value.lower() == "random":
        return "random"
    try:
        return finite(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not finite degrees or 'random'") from None


def _stack(options: list[Callable[..., Any]]) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """One decorator applying ``options`` in order (the first is listed first in ``--help``)."""

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        for option in reversed(options):
            func = option(func)
        return func

    return decorate


def _one_value(parse: Callable[..., Any]) -> Callable[..., Any]:
    """A ``LOW:HIGH`` parser that refuses a range (where every image must share one value)."""

    def callback(ctx: click.Context | None, param: click.Parameter | None, value: str | None) -> Any:
        parsed = parse(ctx, param, value)
        if isinstance(parsed, tuple):
            raise click.BadParameter(f"{value!r}: one value here (compare several with --scenarios)")
        return parsed

    return callback


def camera_options(altitude: str = "100", fov: str = "35", *,
                   ranges: bool = True) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--altitude``, ``--fov`` and ``--size`` with these defaults; ``ranges`` allows ``LOW:HIGH`` drawn per
    image."""
    drawn = ", or LOW:HIGH drawn per image" if ranges else ""
    return _stack([
        click.option("--altitude", default=altitude, callback=parse_range if ranges else _one_value(parse_range),
                     show_default=True, help=f"Height above ground, metres{drawn}."),
        click.option("--fov", default=fov, callback=parse_fov if ranges else _one_value(parse_fov),
                     show_default=True, help=f"Horizontal field of view, degrees{drawn}."),
        click.option("--size", default="640x480", callback=parse_size, show_default=True, help="Image size WxH."),
    ])


def detector_error_options(attitude_std: float = 0.0,
                           pixel_std: float = 0.0) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--attitude-std``, ``--pixel-std``, ``--miss-rate``, ``--spurious-rate``, ``--label-noise``."""
    return _stack([
        click.option("--attitude-std", type=finite_float(0.0, MAX_ATTITUDE_STD), default=attitude_std,
                     show_default=True, help="Roll and pitch error std, degrees."),
        click.option("--pixel-std", type=finite_float(0.0, MAX_PIXEL_STD), default=pixel_std, show_default=True,
                     help="Detector position error std per axis, pixels."),
        click.option("--miss-rate", type=rate, default=0.0, show_default=True,
                     help="Fraction of visible objects the detector misses."),
        click.option("--spurious-rate", type=finite_float(0.0, MAX_SPURIOUS_RATE), default=0.0, show_default=True,
                     help="Extra objects per true object, at random pixels."),
        click.option("--label-noise", type=rate, default=0.0, show_default=True,
                     help="Fraction of objects given a wrong label."),
    ])


def rendered_masks_options(render_help: str, masks_dir_help: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--render centroids|masks``, ``--source EXTRACT`` and ``--masks-dir DIR``: objects from label masks
    rendered from an extract's outlines (``simulate`` and ``simulate flight`` word what each renders)."""
    return _stack([
        click.option("--render", type=click.Choice(["centroids", "masks"]), default="centroids", show_default=True,
                     help=render_help),
        click.option("--source", "source_file", type=click.Path(), metavar="EXTRACT.osm.pbf",
                     help="With --render masks: the OSM extract the map was built from (its outlines are drawn)."),
        click.option("--masks-dir", type=click.Path(file_okay=False), metavar="DIR", help=masks_dir_help),
    ])

