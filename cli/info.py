"""``mapdb info``: what a map holds."""

from __future__ import annotations

import click

from mapdb.mapfile.export import map_info
from mapdb.mapfile.reader import open_map
from mapdb.outputs import dumps_strict

from .options import debug_option, handle_errors, json_option


@click.command()
@click.argument("map_file", metavar="MAP", type=click.Path())
@json_option
@debug_option
@handle_errors
def info(map_file, as_json, debug):
    """Describe a map: CRS, bounds, objects per label, pages, size, sources."""
    with open_map(map_file) as m:
        facts = map_info(m)
    if as_json:
        click.echo(dumps_strict(facts, indent=2))
        return
    b, ll = facts["bounds"], facts["bounds_lonlat"]
    lines = [
        f"map:          {facts['path']}  (format {facts['format_version']}, {facts['software']}, {facts['created']})",
        f"crs:          {facts['crs']}   quantum {facts['quantum_m']} m",
        f"bounds:       {b[0]:.1f}, {b[1]:.1f} - {b[2]:.1f}, {b[3]:.1f}",
    ]
    if ll:
        lines.append(f"lon/lat:      {ll[0]:.5f}, {ll[1]:.5f} - {ll[2]:.5f}, {ll[3]:.5f}")
    lines += [
        f"objects:      {facts['objects']} in {facts['pages']} pages",
        f"file:         {facts['file_bytes']} bytes, {facts['bytes_per_object']} bytes/object",
        *_elevation_lines(facts.get("elevation")),
        "labels:",
        *(f"  {name:<20} {count:>9}" for name, count in facts["labels"].items()),
        "sources:",
        *(f"  {s['name']} ({s['kind']}, {s['size']} bytes, {s['objects']} objects, sha256 {s['sha256'][:16]}...)"
          for s in facts["sources"]),
        "build options: " + ", ".join(f"{k}={v}" for k, v in facts["build"].items() if v is not None),
    ]
    click.echo("\n".join(lines))


def _elevation_lines(elevation: dict | None) -> list[str]:
    """The elevation line of a map that holds it (none for a flat map)."""
    if elevation is None:
        return []
    span = ("none known" if elevation["known"] == 0 else
            f"{elevation['min_m']:.1f} - {elevation['max_m']:.1f} m (median {elevation['median_m']:.1f})")
    return [f"elevation:    {span}, step {elevation['step_m']} m, {elevation['known']} objects with, "
            f"{elevation['unknown']} without"]
