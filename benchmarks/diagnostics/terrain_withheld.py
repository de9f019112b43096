"""Why images over Monaco's relief are withheld: each rejected image's candidate, its sigma and the ground.

Reproduces the README's "Where it fails (300 m, altitude given, 17 of 500 withheld, none accepted wrong)"
paragraph of the terrain section (issue 33): the images of ``benchmarks/terrain.py``'s 300 m row (a level
camera, random yaw, 60 degree field of view, 640x480, 1 px noise, at least 6 objects, seed 0) localized
against Monaco's map built with the shared SRTM tile (``TERRAIN`` 1) or flat (0), with or without the
camera's height above the ground (``WITH_ALT``).  The matcher is wrapped, not changed: the candidate it
found (accepted or not) and the last terrain fit of each image are recorded.

Run from the repository root (about 2 minutes alone for 500 images)::

    python benchmarks/diagnostics/terrain_withheld.py 300 500 1 1
    python benchmarks/diagnostics/terrain_withheld.py 300 500 1 0   # the flat control

Prints the summary (images, accepted, within 2 m, accepted beyond 2 m), then one line per image not
accepted: its reason, objects seen, the distance from the nadir to the map's nearest object with a height,
to the nearest matched object and to the matched objects' centroid (objects all to one side: the ground's
extrapolation to the nadir is uncertain), the candidate's error and stated sigma, and the terrain fit's
variance (the camera height's part of sigma^2).
``--out FILE.json`` keeps every image's record.  The maps are built once into ``benchmarks/terrain.py``'s
cache.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import shared_data  # noqa: E402
from terrain import CACHE, build  # noqa: E402

import mapdb.localize.localizer as localizer_module  # noqa: E402
import mapdb.match.evidence.terrain as terrain_module  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.simulation.simulate import simulate_images  # noqa: E402
from mapdb.simulation.terrain import terrain_of  # noqa: E402

MONACO = shared_data("osm", "monaco-2021-12-03.osm.pbf")
DEM = shared_data("dem", "N43E007.hgt")


def record_matches(seen: dict[str, Any]) -> None:
    """Wrap the localizer's matcher and the terrain fit so that each image's candidate and last fit land in
    ``seen`` (the answer alone does not carry a rejected image's candidate)."""
    match_fast = localizer_module.match_fast
    fit_sources = terrain_module.TerrainModel.fit_sources

    def matched(*args: Any, **kwargs: Any) -> Any:
        result = match_fast(*args, **kwargs)
        seen.update(result=result, objects=args[2])
        return result

    def fitted(self: Any, z: np.ndarray, dst: np.ndarray, b: complex, scale: float, elevation: np.ndarray) -> Any:
        out = fit_sources(self, z, dst, b, scale, elevation)
        seen["fit_var"] = float(out[1])
        return out

    localizer_module.match_fast = matched
    terrain_module.TerrainModel.fit_sources = fitted  # type: ignore[method-assign]


def image_row(i: int, image: dict, answer: Any, seen: dict[str, Any]) -> dict:
    """One image's record: its answer, and its candidate's error, sigma and geometry when the matcher had one."""
    truth = complex(image["truth"]["x"], image["truth"]["y"])
    row: dict[str, Any] = {"i": i, "status": answer.status, "reason": answer.reason, "objects": len(image["objects"])}
    result = seen.get("result")
    cand = None
    if result is not None:
        cand = result.best if result.best is not None else (result.candidates[0] if result.candidates else None)
    terrain = getattr(seen.get("objects"), "terrain", None)
    if terrain is not None:  # the nearest map object with a height, whether matched or not
        row["map_nearest_m"] = float(terrain[0].query([truth.real, truth.imag], k=1)[0])
    if cand is None:
        return row
    mz = seen["objects"].z[cand.pairs[:, 1]]
    row.update(err_m=abs(cand.b - truth), sigma_m=cand.sigma_m, fit_var_m2=seen.get("fit_var"),
               nearest_m=float(np.min(np.abs(mz - truth))), centroid_m=float(abs(np.mean(mz) - truth)))
    return row


def run(altitude: float, n: int, with_alt: bool, terrain: bool) -> list[dict]:
    """Every image's record, simulated and localized as ``benchmarks/terrain.py`` does."""
    path = build(MONACO, CACHE / ("monaco.dem.mapdb" if terrain else "monaco.flat.mapdb"), DEM if terrain else None)
    seen: dict[str, Any] = {}
    record_matches(seen)
    rows = []
    with open_map(path) as m:
        images = simulate_images(m, n, altitude=altitude, fov_deg=60.0, size=(640, 480), yaw="random",
                                 pixel_std=1.0, with_attitude=True, with_altitude=with_alt, min_objects=6, seed=0,
                                 terrain=terrain_of(m, (DEM,)) if terrain else None)
        loc = localizer_module.Localizer(m)
        for i, image in enumerate(images):
            seen.clear()
            rows.append(image_row(i, image, loc.localize(image), seen))
    return rows


def report(rows: list[dict]) -> None:
    """The summary line and the table of images not accepted."""
    ok = [r for r in rows if r["status"] == "ok"]
    print(f"{len(rows)} images: accepted {len(ok)}, within 2 m {sum(r['err_m'] <= 2 for r in ok)},"
          f" accepted beyond 2 m {sum(r['err_m'] > 2 for r in ok)}; not accepted {len(rows) - len(ok)}")
    print(f"{'image':>5} {'objects':>7} {'map nearest m':>13} {'nearest m':>9} {'centroid m':>10} {'err m':>6}"
          f" {'sigma m':>7} {'fit var m2':>10}  reason")
    for r in rows:
        if r["status"] == "ok":
            continue
        cells = [f"{r[k]:.2f}" if r.get(k) is not None else "-" for k in
                 ("map_nearest_m", "nearest_m", "centroid_m", "err_m", "sigma_m", "fit_var_m2")]
        print(f"{r['i']:>5} {r['objects']:>7} {cells[0]:>13} {cells[1]:>9} {cells[2]:>10} {cells[3]:>6} {cells[4]:>7}"
              f" {cells[5]:>10}  {r['reason']}")


def main(argv: list[str] | None = None) -> int:
    """Parse the README's positional arguments, run, print; ``--out`` keeps the records as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("altitude", type=float, help="camera height above the ground, m (120 or 300)")
    parser.add_argument("n", type=int, help="images")
    parser.add_argument("with_alt", choices=("0", "1"), help="1: the image gives altitude_m")
    parser.add_argument("terrain", choices=("0", "1"), help="1: the map with the SRTM tile; 0: the flat control")
    parser.add_argument("--out", type=Path, help="write every image's record here (JSON)")
    args = parser.parse_args(argv)
    if not MONACO.exists() or not DEM.exists():
        print(f"needs the shared data: {MONACO} and {DEM}", file=sys.stderr)
        return 1
    CACHE.mkdir(parents=True, exist_ok=True)
    rows = run(args.altitude, args.n, args.with_alt == "1", args.terrain == "1")
    report(rows)
    if args.out:
        args.out.write_text(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
