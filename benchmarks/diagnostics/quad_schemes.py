"""Which quads a stored index should hold: how many of an image's true quads each choice of triples keeps.

Reproduces the README's figures behind format 4's choice of quads ("A compact index"): "31 % with the 4
nearest, 42 % with these six triples (4.1 quads an object), 67 % with all ten triples of the 5 nearest (6.8
quads an object) ...; images with fewer than 3 indexed true quads: 28 of 300, 12 of 300".  Each scheme is
a set of triples of an object's nearest others (ranks 0-5); the object with each triple is a quad.  The
images are ``benchmarks/lost_in_space_index.py``'s (60-400 m, 35-60 degrees, random heading, 1 px, seed 1);
an image's quads are each object with every triple of its 5 nearest in the image, and a quad counts when its
four objects are all map objects and the scheme holds those four.

Run from the repository root (a minute or two for Andorra)::

    python benchmarks/diagnostics/quad_schemes.py andorra 300
    python benchmarks/diagnostics/quad_schemes.py path/to/some.mapdb 100

``MAP`` is a map file, or the name of a shared OSM extract (andorra, liechtenstein, monaco) whose map is
built once into a temporary folder.  Prints, per scheme: quads an object, the share of the images' true
quads it holds, and the images where it holds fewer than 3, 5 and 8.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import map_argument  # noqa: E402
from lost_in_space_index import _image_arrays, _images  # noqa: E402

from mapdb._scipy import cKDTree  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402
from mapdb.match.nearest import nearest_others  # noqa: E402
from mapdb.match.quads import neighbour_quads  # noqa: E402

CACHE = Path(tempfile.gettempdir()) / "mapdb-diagnostics"
FOUR = list(itertools.combinations(range(4), 3))
SCHEMES = {
    "every triple of the 4 nearest": FOUR,
    "every triple of the 5 nearest": list(itertools.combinations(range(5), 3)),
    "4 nearest + (0,1,4)": FOUR + [(0, 1, 4)],
    "4 nearest + (0,1,4) (0,2,4) [format 4]": FOUR + [(0, 1, 4), (0, 2, 4)],
    "4 nearest + (0,1,4) (0,2,4) (1,2,4)": FOUR + [(0, 1, 4), (0, 2, 4), (1, 2, 4)],
    "4 nearest + (0,1,4) (0,2,4) (0,3,4)": FOUR + [(0, 1, 4), (0, 2, 4), (0, 3, 4)],
    "4 nearest + (0,1,4) (0,1,5)": FOUR + [(0, 1, 4), (0, 1, 5)],
}


def scheme_sets(xy: np.ndarray) -> dict[str, set[tuple[int, ...]]]:
    """Each scheme's quads over the map (sorted object ids)."""
    n = len(xy)
    table = nearest_others(cKDTree(xy), xy, np.arange(n), 6, 1)
    sets = {}
    for name, triples in SCHEMES.items():
        tr = np.array(triples)
        quads = np.concatenate([np.repeat(np.arange(n), len(tr))[:, None], table[:, tr].reshape(-1, 3)], axis=1)
        quads.sort(axis=1)
        sets[name] = set(map(tuple, quads.tolist()))
    return sets


def held(path: Path, n_images: int, sets: dict[str, set[tuple[int, ...]]], labels: tuple[str, ...]
         ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Each image's true quads, and how many of them each scheme holds."""
    found: dict[str, list[int]] = {name: [] for name in sets}
    totals = []
    for image in _images(path, n_images, 1):
        z, _, truth = _image_arrays(image, labels)
        mapped = truth[neighbour_quads(np.column_stack([z.real, z.imag]), 5)]
        true_quads = {tuple(sorted(q)) for q in mapped[(mapped >= 0).all(axis=1)].tolist()}
        totals.append(len(true_quads))
        for name, quads in sets.items():
            found[name].append(sum(q in quads for q in true_quads))
    return np.array(totals), {name: np.array(v) for name, v in found.items()}


def main(argv: list[str] | None = None) -> int:
    """Build the schemes over the map, count the images' true quads each holds, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("map", help="a .mapdb file, or a shared extract's name (andorra, liechtenstein, monaco)")
    parser.add_argument("images", type=int, help="simulated images")
    args = parser.parse_args(argv)
    path = map_argument(args.map, CACHE)
    if path is None:
        return 1
    with open_map(path) as m:
        objects, labels = m.all(), tuple(m.labels)
    xy = np.column_stack([objects.x, objects.y])
    sets = scheme_sets(xy)
    totals, found = held(path, args.images, sets, labels)
    print(f"{path.name}: {len(xy)} objects, {args.images} images, {totals.sum()} true image quads")
    print(f"{'scheme':<40} {'quads/object':>12} {'held':>6} {'images <3':>9} {'<5':>4} {'<8':>4} {'median':>6}")
    for name, v in found.items():
        print(f"{name:<40} {len(sets[name]) / len(xy):>12.2f} {v.sum() / totals.sum():>6.1%} {(v < 3).sum():>9}"
              f" {(v < 5).sum():>4} {(v < 8).sum():>4} {np.median(v):>6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
