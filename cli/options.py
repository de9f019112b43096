"""Options and error handling shared by every mapdb command.

The library raises :class:`mapdb.errors.MapdbError` subclasses with one-line
messages; here they become ``mapdb: error: ...`` on stderr and exit status 1,
with the traceback only under ``--debug``.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any

import click

from mapdb.errors import MapdbError

debug_option = click.option("--debug", is_flag=True, help="Show tracebacks for errors.")
json_option = click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")
quiet_option = click.option("--quiet", "-q", is_flag=True, help="No progress messages on stderr.")


def parse_bbox(ctx: click.Context | None, param: click.Parameter | None, value: str | None):
    """``minlon,minlat,maxlon,maxlat`` -> tuple of four floats, or None."""
    if value is None:
        return None
    try:
        parts = tuple(float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not four comma-separated numbers") from None
    if len(parts) != 4 or not (parts[0] < parts[2] and parts[1] < parts[3]):
        raise click.BadParameter(f"{value!r} must be minlon,minlat,maxlon,maxlat with min < max")
    return parts


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
