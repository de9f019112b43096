"""The ``mapdb`` command: a thin layer over the library, one module per command.

Command modules are imported only when their command runs: ``mapdb --help`` and ``mapdb --version``
import neither numpy nor scipy, so a caller that starts the CLI per image pays milliseconds, not a second.

Signals are handled here, once for every command: SIGINT (Ctrl-C) and SIGTERM raise :class:`Interrupted` in
the command, so that every ``with`` block on the way out removes its temporary files (an output is written to
a temporary file and renamed only when complete), then the process ends with one line on stderr and the
shell's status, 128 + the signal's number: 130 for SIGINT, 143 for SIGTERM.  A second signal while that
unwinding runs ends the process at once (the same status); a temporary file it leaves is removed by the next
run that writes the same output.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import signal
import sys
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import click

from mapdb import __version__

# One module per command, each defining a click command named like the module, with the one-line help
# shown by ``mapdb --help`` (kept here so that listing the commands imports none of them).  Adding a
# command is one line here.
COMMANDS = {
    "build": "Build a map from OSM extracts, land-cover rasters and point/polygon layers.",
    "info": "Describe a map: CRS, bounds, objects per label, pages, size, sources.",
    "merge": "Merge maps of neighbouring or overlapping regions into one, shared objects kept once.",
    "export": "Export a map's objects as points (GeoPackage, GeoJSON, GeoParquet, FlatGeobuf, CSV).",
    "index": "Build a map's lost-in-space quad index (a checksummed file beside the map).",
    "simulate": "Simulate camera images of a map, one JSON object per line (`simulate flight`: a whole flight).",
    "objects": "Image objects from segmentation masks (PNG, GeoTIFF) and COCO detections, for query.",
    "query": "Localize every image of a JSON Lines file (or stdin, streamed) in a map.",
    "georef": "Place a localized camera image on the map: a world file and a GDAL .aux.xml beside it.",
    "evaluate": "Localize simulated images and measure the answers against their truth.",
    "analyze": "Where a map localizes: success, ambiguity, objects and storage per grid cell (GeoTIFF, PNG).",
    "show": "Draw one image's match over the map: inliers, outliers, footprint, truth, candidates.",
    "navigate": "Navigate a flight's frames: a particle filter over frame-to-frame velocities and fixes.",
    "bench": "Reproducible benchmarks: the paper's Table 1, storage against other formats and imagery.",
}


# Subcommands spelled as two words (``mapdb simulate flight``) whose first word is also a command of its
# own (``mapdb simulate MAP``): (first, second) -> module.
TWO_WORD_COMMANDS = {("simulate", "flight"): "flight"}


# The signals that end a command cleanly, and their names in the message.
SIGNALS: dict[int, str] = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}
# The signals received during this run: an Interrupted that a library swallowed (a bare ``except:``, or one
# raised in a ``__del__``, where Python only prints it) still ends the command with the signal's status.
_RECEIVED: list[int] = []


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived: raised where the command was, unwinding it like Ctrl-C (library code that
    cleans up on ``KeyboardInterrupt`` does so for SIGTERM too)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _at_once(signum: int, frame: Any) -> None:
    """A second signal while the first is unwinding: stop now."""
    os.write(2, f"mapdb: interrupted again by {SIGNALS.get(signum, signum)}; stopped at once\n".encode())
    os._exit(128 + signum)


def _after_the_command(signum: int, frame: Any) -> None:
    """A signal once the command has returned, while the interpreter shuts down (a second or more on a busy
    machine): every output is complete; end with the signal's status and line rather than die by it."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os.write(2, f"{_interrupted_line(signum)}\n".encode())
    os._exit(128 + signum)


@contextmanager
def _signals_interrupt(process: bool) -> Iterator[None]:
    """While the block runs, SIGINT and SIGTERM raise :class:`Interrupted` in this process.

    A worker forked from it (``fork`` process pools) inherits the handler: there the signal ends the worker as
    it would by default, and this process, which got the signal too or sees its pool broken, cleans up.
    ``process``: the command is the process (``mapdb ...``), which ends after the block: a signal then exits
    at once (:func:`_after_the_command`); otherwise (a caller's ``cli([...])``) the caller's handlers return.
    """
    owner = os.getpid()

    def interrupt(signum: int, frame: Any) -> None:
        if os.getpid() != owner:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        _RECEIVED.append(signum)
        for each in SIGNALS:
            signal.signal(each, _at_once)
        raise Interrupted(signum)

    try:
        previous = {each: signal.signal(each, interrupt) for each in SIGNALS}
    except ValueError:  # not the main thread (a program running the CLI in a thread): its handlers stay
        yield
        return
    hook = sys.unraisablehook
    sys.unraisablehook = _quiet_about_interrupts(hook)
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for each, handler in previous.items():
            signal.signal(each, _after_the_command if process else handler)


def _quiet_about_interrupts(hook: Any) -> Any:
    """``sys.unraisablehook`` that says nothing of an :class:`Interrupted` raised where Python cannot pass it on
    (a ``__del__``, a weakref callback): Python would print its traceback; the command ends with its one line."""

    def unraisable(report: Any) -> None:
        if not isinstance(report.exc_value, Interrupted):
            hook(report)

    return unraisable


def _interrupted(signum: int) -> None:
    """End the process after a signal: one line, status 128 + the signal.

    Every ``with`` block on the way here has removed its temporary files; outputs already renamed into place
    are complete.
    """
    click.echo(_interrupted_line(signum), err=True)
    sys.exit(128 + signum)


def _interrupted_line(signum: int) -> str:
    """The one line a command ends with after SIGINT or SIGTERM."""
    return f"mapdb: interrupted by {SIGNALS.get(signum, signum)}; no partial output left"


class LazyGroup(click.Group):
    """A group whose subcommands are imported on first use, and which ends every command the same way on a
    signal (:class:`Interrupted`)."""

    _debug = False

    def main(self, args: Any = None, *rest: Any, **options: Any) -> Any:
        self._debug = "--debug" in (sys.argv[1:] if args is None else list(args))
        _RECEIVED.clear()
        with _signals_interrupt(process=args is None):
            return super().main(args, *rest, **options)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            result = super().invoke(ctx)
        except KeyboardInterrupt as exc:  # Interrupted, or a KeyboardInterrupt raised outside our handler
            if self._debug:
                traceback.print_exc()
            _interrupted(getattr(exc, "signum", signal.SIGINT))
        if _RECEIVED:  # the Interrupted was swallowed on its way and the command went on to its end
            _interrupted(_RECEIVED[0])
        return result

    def resolve_command(self, ctx: click.Context, args: list[str]):
        module = TWO_WORD_COMMANDS.get((args[0], args[1])) if len(args) >= 2 else None
        if module is not None and importlib.util.find_spec(f"mapdb_cli.{module}") is not None:
            command = getattr(importlib.import_module(f"mapdb_cli.{module}"), module)
            return f"{args[0]} {args[1]}", command, args[2:]
        return super().resolve_command(ctx, args)

    def list_commands(self, ctx: click.Context) -> list[str]:
        return [name for name in COMMANDS if importlib.util.find_spec(f"mapdb_cli.{name}") is not None]

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS or importlib.util.find_spec(f"mapdb_cli.{name}") is None:
            return None
        return getattr(importlib.import_module(f"mapdb_cli.{name}"), name)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, COMMANDS[name]) for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="mapdb")
def cli() -> None:
    """Build labelled-object meta-maps and localize aerial images against them."""
