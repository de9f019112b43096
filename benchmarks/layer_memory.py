"""Peak memory and time of ``mapdb build`` of big layers: CSV points and GeoParquet footprints, 1M against 5M objects.

The layers are made here from a synthetic world (``benchmarks/synthetic_world.py``: rotated copies of the
three shared extracts' maps, at least N objects), in a temporary directory deleted at the end:

* ``world-N.csv``: ``lon, lat, label``, one line an object (points);
* ``world-N.parquet``: GeoParquet 1.1 in lon/lat with an Overture-like ``bbox`` struct column (its covering)
  in row groups of 65,536 rows: objects with an area are squares of that area (buildings among them form
  blocks where their squares touch), the others points; ``label`` column.

Each is built in a fresh process (``mapdb build -q --crs EPSG:32631``, run in the temporary directory,
sampled from ``/proc`` every 0.2 s; peak RSS is the kernel's VmHWM) by the working tree ("after") and by the
commit given by ``--baseline`` ("before", extracted with ``git archive``), runs alternating, ``--repeats``
each; the medians are printed, then the ratio of the 5M peak to the 1M peak of each, and whether before and
after wrote the same bytes (``SOURCE_DATE_EPOCH`` fixed, so that the header's date is too).  Run::

    python benchmarks/layer_memory.py [--sizes 1000000 5000000] [--repeats 1] [--baseline HEAD] [--no-before]

``--blocks`` prints instead the longest block (its extent, in metres) of each shared extract, which the tile
margin of :mod:`mapdb.build.tiles` must exceed.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import build_memory as _memory  # noqa: E402
import synthetic_world as _world  # noqa: E402

CRS = "EPSG:32631"
# The shared data beside the checkout, else where a worktree's checkout finds it.
if not _world.DATA.is_dir():
    _world.DATA = Path("/work/shared/data/osm")
ROW_GROUP = 1 << 16


def write_layers(n: int, where: Path) -> tuple[Path, Path, int]:
    """The CSV and GeoParquet layers of a world of at least ``n`` objects, and its number of objects."""
    import pyarrow as pa
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq
    import pyproj
    import shapely
    from pyproj import Transformer

    world = _world.synthetic_world(_world.extract_maps(), n, seed=0)
    to_lonlat = Transformer.from_crs(world.crs, "EPSG:4326", always_xy=True)
    lon, lat = to_lonlat.transform(world.x, world.y)
    names = world.names()
    csv = where / f"world-{n}.csv"
    pacsv.write_csv(pa.table({"lon": lon, "lat": lat, "label": names}), csv)
    side = np.sqrt(world.area) / 2
    shapes = np.where(world.area > 0, shapely.box(world.x - side, world.y - side, world.x + side, world.y + side),
                      shapely.points(world.x, world.y))
    shapes = shapely.transform(shapes, lambda xy: np.column_stack(to_lonlat.transform(xy[:, 0], xy[:, 1])))
    bounds = shapely.bounds(shapes)
    table = pa.table({
        "label": names, "geometry": shapely.to_wkb(shapes),
        "bbox": pa.StructArray.from_arrays([pa.array(bounds[:, i]) for i in range(4)],
                                           ["xmin", "ymin", "xmax", "ymax"])})
    geo = {"version": "1.1.0", "primary_column": "geometry", "columns": {"geometry": {
        "encoding": "WKB", "geometry_types": [], "crs": pyproj.CRS.from_epsg(4326).to_json_dict(),
        "covering": {"bbox": {k: ["bbox", k] for k in ("xmin", "ymin", "xmax", "ymax")}}}}}
    parquet = where / f"world-{n}.parquet"
    pq.write_table(table.replace_schema_metadata({"geo": json.dumps(geo)}), parquet, row_group_size=ROW_GROUP)
    return csv, parquet, len(world)


def longest_blocks() -> None:
    """The extent of each shared extract's longest block (its box's diagonal, metres)."""
    import shapely

    from mapdb.build.blocks import DEFAULT_GAP_M, block_members
    from mapdb.mapfile.reader import open_map
    from mapdb.simulation.outlines import read_scene

    print("| extract | buildings | blocks | longest block (box diagonal) |\n|---|---|---|---|")
    for name, map_path in zip(_world.EXTRACTS, _world.extract_maps(), strict=True):
        with open_map(map_path) as m:
            scene = read_scene(_world.DATA / name, m.all())
        footprints = scene.geometry[scene.layer == 2]
        block = block_members(footprints, DEFAULT_GAP_M)
        longest = 0.0
        for b in range(int(block.max()) + 1):
            x0, y0, x1, y1 = shapely.total_bounds(footprints[block == b])
            longest = max(longest, float(np.hypot(x1 - x0, y1 - y0)))
        print(f"| {name} | {footprints.size:,} | {int(block.max()) + 1:,} | {longest:,.0f} m |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000_000, 5_000_000])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--baseline", default="HEAD", help="commit of the 'before' build (default HEAD)")
    parser.add_argument("--no-before", action="store_true", help="measure the working tree only")
    parser.add_argument("--blocks", action="store_true", help="print the longest block of each extract and stop")
    args = parser.parse_args(argv)
    if not _world.DATA.is_dir():
        print(f"no shared data at {_world.DATA}: no world to make layers of", file=sys.stderr)
        return 1
    if args.blocks:
        longest_blocks()
        return 0
    os.environ["SOURCE_DATE_EPOCH"] = "1700000000"
    with tempfile.TemporaryDirectory(prefix="layer-memory-") as tmp_name:
        tmp = Path(tmp_name)
        # The builds run here: a child's ``python -c`` looks for packages in its working directory first, and
        # from the checkout it would find the working tree's mapdb where the baseline's is meant.
        os.chdir(tmp)
        before = None if args.no_before else _memory.baseline_tree(args.baseline, tmp / "baseline")
        print(f"before: {args.baseline if before else '(not run)'}; after: the working tree; {args.repeats} "
              "repeat(s), alternating\n")
        print("| layer | objects | file | build | wall (median) | peak RSS (median) | map |\n"
              "|---|---|---|---|---|---|---|")
        peaks: dict[tuple[str, str], dict[int, float]] = {}
        for n in args.sizes:
            start = time.perf_counter()
            csv, parquet, count = write_layers(n, tmp)
            print(f"<!-- layers of {count:,} objects written in {time.perf_counter() - start:.0f} s -->")
            for layer in (csv, parquet):
                runs: dict[str, list[_memory.Run]] = {"after": [], "before": []}
                outs = {"after": tmp / "after.mapdb", "before": tmp / "before.mapdb"}
                for r in range(args.repeats):
                    order = ["after", "before"] if r % 2 == 0 else ["before", "after"]
                    for name in order:
                        if name == "before" and before is None:
                            continue
                        runs[name].append(_memory.mapdb_build(name, [layer], outs[name], ["--crs", CRS],
                                                              before if name == "before" else None))
                same = (before is not None and all(r.ok for r in runs["before"])
                        and filecmp.cmp(outs["after"], outs["before"], shallow=False))
                for name, done in runs.items():
                    if not done:
                        continue
                    m = _memory.median(done)
                    peaks.setdefault((layer.suffix, name), {})[count] = m.peak_rss_mb
                    status = "" if m.ok else f" FAILED: {m.note}"
                    bytes_note = ("same bytes" if same else "differ") if before is not None else "-"
                    print(f"| {layer.suffix[1:]} | {count:,} | {layer.stat().st_size / 1e6:,.0f} MB | {name} | "
                          f"{m.seconds:,.1f} s | {m.peak_rss_mb:,.0f} MB | {bytes_note} |{status}", flush=True)
                for out in outs.values():
                    out.unlink(missing_ok=True)
            csv.unlink()
            parquet.unlink()
        print("\n| layer | build | peak ratio, largest to smallest |\n|---|---|---|")
        for (suffix, name), by_size in sorted(peaks.items()):
            sizes = sorted(by_size)
            if len(sizes) > 1:
                print(f"| {suffix[1:]} | {name} | {by_size[sizes[-1]] / by_size[sizes[0]]:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
