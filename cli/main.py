"""The ``mapdb`` command: a thin layer over the library, one module per command.

Command modules are imported only when their command runs: ``mapdb --help`` and ``mapdb --version``
import neither numpy nor scipy, so a caller that starts the CLI per image pays milliseconds, not a second.
"""

from __future__ import annotations

import importlib
import importlib.util

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
    "evaluate": "Localize simulated images and measure the answers against their truth.",
    "analyze": "Where a map localizes: success, ambiguity, objects and storage per grid cell (GeoTIFF, PNG).",
    "show": "Draw one image's match over the map: inliers, outliers, footprint, truth, candidates.",
    "navigate": "Navigate a flight's frames: a particle filter over frame-to-frame velocities and fixes.",
    "bench": "Reproducible benchmarks: the paper's Table 1, storage against other formats and imagery.",
}


# Subcommands spelled as two words (``mapdb simulate flight``) whose first word is also a command of its
# own (``mapdb simulate MAP``): (first, second) -> module.
TWO_WORD_COMMANDS = {("simulate", "flight"): "flight"}


class LazyGroup(click.Group):
    """A group whose subcommands are imported on first use."""

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
