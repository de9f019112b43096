"""What a building cut by an extract's border would become if its ring were closed from the nodes present.

An OSM extract clipped at its border (``osmium extract --strategy simple``, most regional downloads'
edges) keeps a way whose nodes lie partly outside, but not those nodes: the way references nodes the
file does not hold.  ``read_osm`` skips such areas and counts them (``missing_nodes``).  This script
measures, on a complete extract, what keeping them instead would put in a map: it cuts the extract
with a grid of straight borders (every ``--step`` degrees of longitude, then of latitude; the nodes
beyond each border dropped), closes each cut building's ring from the nodes left on the near side, and
compares that polygon with the whole building: how far its centroid moves and what fraction of the
area is left, by how many nodes were dropped.

Run::

    python benchmarks/clipped_areas.py [EXTRACT.osm.pbf] [--step DEGREES]

The extract defaults to Andorra in ``../shared/data/osm`` beside the checkout.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import osmium
import shapely
from pyproj import Transformer

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "osm"
if not DATA.is_dir():
    DATA = Path("/work/shared/data/osm")


class _Buildings(osmium.SimpleHandler):
    """The closed building ways of a file, as arrays of node lon/lat (ways with a node missing left out)."""

    def __init__(self) -> None:
        super().__init__()
        self.rings: list[np.ndarray] = []

    def way(self, w: osmium.osm.Way) -> None:
        value = w.tags.get("building")
        if value is None or value == "no" or not w.is_closed() or len(w.nodes) < 4:
            return
        if all(n.location.valid() for n in w.nodes):
            self.rings.append(np.array([(n.lon, n.lat) for n in w.nodes])[:-1])


def _cut(ring: np.ndarray, keep: np.ndarray) -> tuple[int, float, float] | None:
    """(nodes dropped, centroid shift in m, area left / area) of a ring (metres) closed from the kept nodes;
    None when the border misses the ring or too few nodes are left for a valid polygon."""
    dropped = int((~keep).sum())
    if dropped == 0 or dropped == keep.size:
        return None
    whole = shapely.Polygon(ring)
    if not whole.is_valid or whole.area <= 0:
        return None
    part = shapely.Polygon(ring[keep]) if keep.sum() >= 3 else None
    if part is None or not part.is_valid or part.area <= 0:
        return dropped, float("nan"), 0.0
    return dropped, float(shapely.distance(whole.centroid, part.centroid)), part.area / whole.area


def measure(path: Path, step: float) -> list[tuple[int, float, float]]:
    """One row (nodes dropped, centroid shift, area left) per building cut by a border of the grid."""
    handler = _Buildings()
    handler.apply_file(str(path), locations=True)
    rings = handler.rings
    lon0 = float(np.median([r[:, 0].mean() for r in rings]))
    zone = int((lon0 + 180) // 6) + 1
    to_m = Transformer.from_crs("EPSG:4326", f"EPSG:{32600 + zone}", always_xy=True)
    rows = []
    for ring in rings:
        xy = np.column_stack(to_m.transform(ring[:, 0], ring[:, 1]))
        for axis in (0, 1):
            values = ring[:, axis]
            # Every border of the grid that passes between the ring's nodes cuts it (far side dropped).
            for border in np.arange(np.ceil(values.min() / step), np.floor(values.max() / step) + 1) * step:
                if values.min() < border < values.max():
                    row = _cut(xy, values <= border)
                    if row is not None:
                        rows.append(row)
    return rows


def _table(rows: list[tuple[int, float, float]]) -> None:
    print("| nodes dropped | cut buildings | no valid ring left | centroid shift median / p90 (m) "
          "| area left median / p10 |")
    print("|---|---|---|---|---|")
    data = np.array(rows, dtype=float)
    for label, lo, hi in (("1", 1, 1), ("2", 2, 2), ("3-5", 3, 5), ("6+", 6, 10**9), ("all", 1, 10**9)):
        sel = data[(data[:, 0] >= lo) & (data[:, 0] <= hi)]
        if not len(sel):
            continue
        ok = sel[np.isfinite(sel[:, 1])]
        shift = f"{np.median(ok[:, 1]):.1f} / {np.percentile(ok[:, 1], 90):.1f}" if len(ok) else "-"
        area = f"{np.median(ok[:, 2]):.2f} / {np.percentile(ok[:, 2], 10):.2f}" if len(ok) else "-"
        print(f"| {label} | {len(sel):,} | {len(sel) - len(ok):,} | {shift} | {area} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("extract", nargs="?", type=Path, default=DATA / "andorra-2021-06-22.osm.pbf")
    parser.add_argument("--step", type=float, default=0.002, help="degrees between borders of the grid")
    args = parser.parse_args()
    if not args.extract.exists():
        sys.exit(f"{args.extract}: no such file (the shared data is not beside the checkout)")
    rows = measure(args.extract, args.step)
    print(f"{args.extract.name}: building ways cut by borders every {args.step} degrees of lon, then of lat")
    _table(rows)


if __name__ == "__main__":
    main()
