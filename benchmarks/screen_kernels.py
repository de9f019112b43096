"""The matcher's cheap screens (``mapdb/match/_kernel_screen.c``) against the code they replaced, call by call.

1. The screen's neighbours of image objects (``screen.screen_neighbours``): each image object's 12 nearest image
   objects, by the kernel's ``screen_knn`` and by a scipy cKDTree built over the image and queried (the code before
   it), for images of 6 to 256 objects (uniform in a 1000 x 800 px frame; the benchmark images of
   ``matcher_core.py`` hold 6-136 objects, median 12 on Andorra and 42 on Monaco).
2. The rivals' quick count (``ObjectIndex.near_counts``): how many of an image's objects each of ``h`` places puts
   within 10 m of a map object of their label, by the kernel's ``screen_near_counts`` and by the numpy before it
   (every projection queried, then counted), on the map of a town (uniform buildings, three labels).

Each call's median and p95 (microseconds, ``--repeats`` calls of each, the two taking turns) and their ratio;
every answer checked identical (the counts: those reaching the share a refit needs, which is all the caller
reads; the others stay below it).  The load average and a gauge (``matcher_core.gauge_ms``) are printed beside.

Run from the repository root::

    python benchmarks/screen_kernels.py
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from matcher_core import gauge_ms  # noqa: E402

from mapdb._scipy import cKDTree  # noqa: E402
from mapdb.match.mapobjects.object_index import ObjectIndex  # noqa: E402
from mapdb.match.options import FastOptions  # noqa: E402
from mapdb.match.screen import screen_neighbours  # noqa: E402
from mapdb.objects import Objects  # noqa: E402


def scipy_neighbours(z: np.ndarray, opts: FastOptions) -> np.ndarray:
    """``screen_neighbours`` before the kernel (main at 9b40c11)."""
    n = z.size
    xy = np.column_stack([z.real, z.imag])
    return cKDTree(xy).query(xy, k=min(opts.screen_objects, n))[1].reshape(n, -1)


def numpy_counts(index: ObjectIndex, a, b, z, img_label, gate: float) -> np.ndarray:
    """``rivals._near_counts`` before the kernel (main at 9b40c11)."""
    w = (a[:, None] * z[None, :] + b[:, None]).ravel()
    rows, _, _ = index.within(w, np.tile(img_label, a.size), gate, 1)
    return np.bincount(rows // z.size, minlength=a.size)


def _timed(calls: list, repeats: int) -> list[list[float]]:
    """Microseconds of each call, ``repeats`` times, the calls taking turns (which goes first alternates)."""
    times: list[list[float]] = [[] for _ in calls]
    for r in range(repeats):
        order = range(len(calls)) if r % 2 == 0 else reversed(range(len(calls)))
        for j in order:
            t = time.perf_counter()
            calls[j]()
            times[j].append((time.perf_counter() - t) * 1e6)
    return times


def _row(label: str, times: list[list[float]]) -> str:
    new, old = (statistics.median(t) for t in times)
    p95 = [float(np.percentile(t, 95)) for t in times]
    return (f"  {label:<26} {new:>9.1f} {p95[0]:>9.1f} {old:>9.1f} {p95[1]:>9.1f} {new / old:>6.2f} "
            f"{p95[0] / p95[1]:>6.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=300, help="calls of each, taking turns")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    print(f"load average {os.getloadavg()[0]:.1f}; gauge (fixed numpy workload) {gauge_ms():.1f} ms")
    head = f"  {'case':<26} {'kernel us':>9} {'p95':>9} {'before us':>9} {'p95':>9} {'ratio':>6} {'p95':>6}"
    print("1. the screen's neighbours of image objects (12 nearest), kernel against cKDTree")
    print(head)
    opts = FastOptions()
    for n in (6, 12, 25, 50, 100, 256):
        z = rng.uniform(-500, 500, n) + 1j * rng.uniform(-400, 400, n)
        assert np.array_equal(screen_neighbours(z, opts), scipy_neighbours(z, opts))
        print(_row(f"{n} objects", _timed([lambda z=z: screen_neighbours(z, opts),
                                           lambda z=z: scipy_neighbours(z, opts)], args.repeats)))
    print("2. the rivals' quick count (within 10 m), kernel against numpy")
    print(head)
    m = 20_000
    town = Objects(rng.uniform(0, 4000, m), rng.uniform(0, 4000, m), rng.integers(0, 3, m), np.zeros(m),
                   ("building", "tree", "junction"))
    index = ObjectIndex(town)
    for h, n in ((10, 12), (40, 25), (160, 40), (400, 60)):
        a = 0.4 * np.exp(1j * rng.uniform(-np.pi, np.pi, h))
        b = rng.uniform(500, 3500, h) + 1j * rng.uniform(500, 3500, h)
        z = rng.uniform(-500, 500, n) + 1j * rng.uniform(-400, 400, n)
        lab = rng.integers(0, 3, n)
        need = int(np.ceil(max(4.0, 0.7 * n)))
        full, short = numpy_counts(index, a, b, z, lab, 10.0), index.near_counts(a, b, z, lab, 10.0, need)
        assert np.array_equal(full >= need, short >= need) and np.array_equal(full[full >= need], short[full >= need])
        print(_row(f"{h} places x {n} objects", _timed([lambda a=a, b=b, z=z, lab=lab, need=need: index.near_counts(
            a, b, z, lab, 10.0, need), lambda a=a, b=b, z=z, lab=lab: numpy_counts(index, a, b, z, lab, 10.0)],
            args.repeats)))
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
