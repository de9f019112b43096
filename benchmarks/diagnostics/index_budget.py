"""Where a stored quad index's bytes go, an object: coordinates, neighbours, quad records, directory, the rest.

Reproduces the README's "Byte budget of the 1M world's index (``build_index`` summary and header ...):
coordinates 3.9 B/object (``co_*``), neighbours 7.3 (5 an object, 11.7 bits each), quad records 4.2 x 5 = 20.9,
directory 1.4 plus fence and header" ("A compact index").  Reads the JSON header of ``MAP.qidx`` (format 4,
``docs/index_format.md``): its sections' lengths, grouped (``co_*`` the coordinates, ``nb_*`` the
neighbours, ``quads`` the records, ``dir_*`` the directory, ``fence``, ``crc``), and the summary's
``co_bytes``, ``nb_bytes``, ``quads``, ``record_bytes``; the rest of the file is the prefix, the header and
the sections' alignment.  The index is built beside the map first when it is missing (``--build``).

Run from the repository root::

    python benchmarks/synthetic_world.py 1000000 --jitter 2 -o world-1M.mapdb    # the README's world
    python benchmarks/diagnostics/index_budget.py world-1M.mapdb --build   # the build: 107 s on the 1M world
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
from pathlib import Path


def header(index: Path) -> dict:
    """The index's JSON header (its place is in the 28-byte prefix)."""
    with open(index, "rb") as f:
        _, version, _, offset, length, _ = struct.unpack("<8sHHQII", f.read(28))
        f.seek(offset)
        return {"prefix_version": version, **json.loads(f.read(length))}


def budget(index: Path) -> list[tuple[str, float, str]]:
    """Bytes an object of each group of sections (``co_*``, ``nb_*``, ``quads``, ``dir_*``, ``fence``, ``crc``),
    with how it is made up, then the rest of the file (prefix, header, alignment) and the whole."""
    h = header(index)
    n = h["objects"]
    size = index.stat().st_size
    groups: dict[str, int] = {}
    for name, section in h["sections"].items():
        group = name.split("_")[0] + "_*" if "_" in name else name
        groups[group] = groups.get(group, 0) + section["length"]
    bits = 8 * h["nb_bytes"] / max(n * h["quad_neighbours"], 1)
    notes = {"co_*": f"packed data {h['co_bytes'] / n:.2f}, the rest block starts, widths and bases",
             "nb_*": f"{h['quad_neighbours']} an object, {bits:.1f} bits each ({h['nb_bytes'] / n:.2f} packed)",
             "quads": f"{h['quads'] / n:.2f} quads an object x {h['record_bytes']} bytes",
             "dir_*": f"{h['pages']} pages, {h['cells']} cells", "fence": "a row a directory page"}
    parts = [(group, length / n, notes.get(group, "")) for group, length in groups.items()]
    parts.append(("prefix, header, alignment", (size - sum(groups.values())) / n, ""))
    parts.append(("whole file", size / n, f"{size:,} bytes, {n:,} objects, format {h['format_version']}"))
    return parts


def main(argv: list[str] | None = None) -> int:
    """Build the index if asked and missing, then print its budget."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("map", type=Path, help="a .mapdb file (its index is MAP.qidx)")
    parser.add_argument("--build", action="store_true", help="build the index when it is missing")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    index = Path(str(args.map) + ".qidx")
    if not index.exists() and args.build:
        from mapdb.match.index.stored import build_index

        print(json.dumps(build_index(args.map, workers=args.workers)))
    if not index.exists():
        print(f"index_budget: error: {index}: no index (build it with mapdb index, or pass --build)", file=sys.stderr)
        return 1
    for name, per_object, note in budget(index):
        print(f"{name:<28} {per_object:7.2f} B/object  {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
