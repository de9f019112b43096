"""The ``mapdb`` command: a thin layer over the library, one module per command."""

from __future__ import annotations

import importlib

import click

from mapdb import __version__

# One module per command, each defining a click command named like the module.  Adding a command
# is one line here.
COMMANDS = [
    "build",
    "info",
    "export",
    "simulate",
    "evaluate",
    "bench",
    "query",
]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="mapdb")
def cli() -> None:
    """Build labelled-object meta-maps and localize aerial images against them."""


for _name in COMMANDS:
    cli.add_command(getattr(importlib.import_module(f"mapdb_cli.{_name}"), _name))
