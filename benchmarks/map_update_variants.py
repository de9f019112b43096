"""The map-likelihood update's heading treatment, measured: marginalised over Gauss-Hermite nodes or added per object.

The frame's heading error is common to all its objects (:mod:`mapdb.navigation.map_update`).  This navigates the
rendered-mask flights of ``benchmarks/navigation_masks.py`` (the same cache, the same figures per row) with the
navigator's map update in each of these forms, side by side in one process, frame by frame alternating which
goes first:

* ``nodes3`` (the default) and ``nodes5``: the frame's likelihood at 3 or 5 heading offsets, combined by their
  Gauss-Hermite weights;
* ``independent``: no marginalisation; the heading's error added to each object's sigma across the direction
  from the nadir (``|A z| sigma_heading``), as if independent from object to object;
* ``off``: ``NavigatorOptions(map_update=False)``.

The last column is the update's own median time on the frames it was used.  Run from the repository root::

    python benchmarks/map_update_variants.py --maps andorra,monaco --cases heights,thin15 --starts lis \\
        --cache /tmp/pose-cache
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import navigation_masks as nm  # noqa: E402

from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.navigation import map_update as mu  # noqa: E402
from mapdb.navigation.navigator import BLOB_FIX_FLOOR_PX, Navigator, NavigatorOptions  # noqa: E402

VARIANTS = ("nodes3", "nodes5", "independent", "off")


class Independent(mu.MapUpdate):
    """The update with the heading's error added per object instead of marginalised (module docs)."""

    def _frame(self, *args: Any, **kwargs: Any) -> Any:
        frame = super()._frame(*args, **kwargs)
        if frame is None:
            return None
        across = np.abs(frame.offsets) * frame.heading_sigma_rad
        return dataclasses.replace(frame, sigma_t=np.hypot(frame.sigma_t, across), heading_sigma_rad=0.0)


def _navigator(m: Any, variant: str, initial: tuple[float, float, float] | None) -> Navigator:
    nav = Navigator(m, NavigatorOptions(map_update=variant != "off"), initial=initial)
    if variant == "nodes5":
        nav.mapper = mu.MapUpdate(m, BLOB_FIX_FLOOR_PX, nodes=5)
    elif variant == "independent":
        nav.mapper = Independent(m, BLOB_FIX_FLOOR_PX)
    return nav


def _flight_rows(name: str, case: str, start: str, length: float, cache: Path) -> None:
    frames = nm._flight(name, case, 120.0, length, cache)
    full, thin = nm._maps(name, cache)
    truth = frames[0]["truth"]
    initial = (truth["x"], truth["y"], nm.START_RADIUS_M) if start == "initial" else None
    with open_map(thin if case == "thin15" else full) as m:
        navigators = [_navigator(m, v, initial) for v in VARIANTS]
        records = nm._navigate(navigators, frames)
    for variant, recs in zip(VARIANTS, records, strict=True):
        used = [r.time_ms.get("map_update", 0.0) for r in recs if (r.map_update or {}).get("status") == "used"]
        row = nm._row(recs, frames)
        print(f"| {name} {case} 120 m {start} ({variant}) | {row['fix']:.1%} | {row['within2']:.1%} "
              f"| {row['within5']:.1%} | {row['max']:.1f} | {row['wrong']} | {row['beyond']:.1%} "
              f"| {row['median_ms']:.0f} | {np.median(used) if used else 0.0:.2f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--maps", default="andorra,monaco")
    parser.add_argument("--cases", default="heights,thin15", help="of heights, thin15")
    parser.add_argument("--starts", default="lis", help="lis, initial")
    parser.add_argument("--length", type=float, default=3000.0, help="metres flown")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/pose-cache"))
    args = parser.parse_args()
    print("| flight | fix | <=2 m | <=5 m | max m | wrong | >3 sigma | ms median | update ms median |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.maps.split(","):
        for case in args.cases.split(","):
            for start in args.starts.split(","):
                _flight_rows(name, case, start, args.length, args.cache)


if __name__ == "__main__":
    main()
