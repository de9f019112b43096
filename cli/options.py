"""Options and error handling shared by every mapdb command.

The library raises :class:`mapdb.errors.MapdbError` subclasses with one-line
messages; here they become ``mapdb: error: ...`` on stderr and exit status 1,
with the traceback only under ``--debug``.
"""

from __future__ import annotations

import functools
import math
import os
import sys
from collections.abc import Callable
from typing import Any

import click

from mapdb.errors import MapdbError


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
overwrite_option = click.option("--overwrite", is_flag=True, help="Replace the output file if it exists.")
json_option = click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")
quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress messages on stderr.")


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


def fail(message: str) -> None:
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
            # The reader stopped (``mapdb query MAP - | head -1``): stop quietly, as ``yes | head`` does.
            # Standard output is pointed at /dev/null so that the interpreter's last flush cannot complain.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            sys.exit(141)
        except (MapdbError, OSError, MemoryError) as exc:
            if debug:
                raise
            fail(str(exc) or exc.__class__.__name__)
        except KeyboardInterrupt:
            if debug:
                raise
            fail("interrupted")

    return wrapper


def progress_printer(quiet: bool) -> Callable[[str], None] | None:
    """A progress callback that writes to stderr (stdout is for results only)."""
    if quiet:
        return None

    def report(message: str) -> None:
        click.echo(message, err=True)

    return report
