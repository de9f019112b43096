"""The compiled kernel's pieces side by side with an earlier commit's numpy code: microseconds a call.

Each piece runs on random tables of the sizes an image gives the matcher (a screen of 256 hypotheses of 10 objects,
a decision of 16 of 30 or, as on Monaco, of 100, a refinement round, a fit, an exclusion test), this tree's and the
baseline's taking turns call by call; median microseconds a call, their ratio, and the largest difference of
their results (0: identical).

Run from the repository root::

    python benchmarks/kernel_pieces.py --baseline main
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import import_baseline  # noqa: E402

WORK = Path(tempfile.gettempdir()) / "mapdb-bench-kernel-pieces"


def tables(rng: np.random.Generator, h: int, n: int) -> dict:
    """Random residuals, tolerance shapes, samples, associations and point sets of ``h`` hypotheses of ``n``."""
    u = rng.exponential(1.0, (h, n)) * rng.choice([1e-3, 0.1, 1.0], size=(h, 1))
    u[rng.random((h, n)) < 0.2] = np.inf
    sample = np.zeros((h, n), bool)
    for r in range(h):
        sample[r, rng.choice(n, 4, replace=False)] = True
    dist = np.sqrt(u / 0.01)
    mid = rng.integers(0, 2 * n, (h, n)).astype(np.int64)
    src = rng.normal(size=(h, n)) + 1j * rng.normal(size=(h, n))
    return {"u": u, "shape": 1.25 + 3 * rng.random((h, n)), "sample": sample, "dist": dist, "mid": mid,
            "k": rng.integers(5, n + 1, h).astype(np.int64), "src": src, "dst": (0.5 - 2j) * src + 7 + 0.01 * src**2,
            "w": rng.random((h, n)) < 0.8}


def pieces(mods: dict, t: dict) -> dict:
    """Name -> call of one module set on tables ``t``."""
    nfa, geometry, points = mods["match.nfa"], mods["match.geometry"], mods["match.evidence.points"]
    out = {
        "nfa curve (no shape)": lambda: nfa.log10_nfa_curve(t["u"], 4, 3.0),
        "nfa curve (shaped)": lambda: nfa.log10_nfa_curve(t["u"], 4, 3.0, shape=t["shape"], sample=t["sample"]),
        "similarity fit": lambda: geometry.fit_similarity_complex(t["src"], t["dst"], t["w"]),
        "residual sigmas": lambda: points.residual_sigmas(t["dist"], t["w"]),
        "first per map object": lambda: points.first_per_map_object(t["mid"], t["dist"], t["w"]),
    }
    if hasattr(points, "refinement_inliers"):
        out["refinement inliers"] = lambda: points.refinement_inliers(t["u"], t["dist"], t["mid"], t["k"])
    return out


def difference(a: object, b: object) -> float:
    """The largest absolute difference of two results (tuples of arrays or arrays; NaN where both are NaN: 0)."""
    a_parts = a if isinstance(a, tuple) else (a,)
    b_parts = b if isinstance(b, tuple) else (b,)
    worst = 0.0
    for x, y in zip(a_parts, b_parts, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        both = (x == y) | (np.isnan(x) & np.isnan(y)) if x.dtype.kind in "fc" else x == y
        if not both.all():
            worst = max(worst, float(np.nanmax(np.abs(x.astype(complex) - y.astype(complex)))))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="main", help="the git revision whose numpy code is compared")
    parser.add_argument("--calls", type=int, default=300, help="calls a piece and size")
    args = parser.parse_args()
    names = ("match.nfa", "match.geometry", "match.evidence.points")
    ours = {m: __import__(f"mapdb.{m}", fromlist=["_"]) for m in names}
    theirs = {m: import_baseline(args.baseline, WORK, m) for m in names}
    rng = np.random.default_rng(0)
    print(f"median us a call, this tree and {args.baseline} taking turns, {args.calls} calls")
    print(f"  {'piece':<22} {'H x n':>9} {'this tree':>10} {args.baseline:>10} {'ratio':>6} {'max diff':>9}")
    for h, n in ((256, 10), (16, 30), (16, 100)):
        t = tables(rng, h, n)
        mine, old = pieces(ours, t), pieces(theirs, t)
        for name, call in mine.items():
            if name not in old:
                old[name] = None
            times: dict[str, list[float]] = {"mine": [], "old": []}
            for i in range(args.calls):
                for label, fn in (("mine", call), ("old", old[name]))[:: 1 if i % 2 else -1]:
                    if fn is None:
                        continue
                    start = time.perf_counter()
                    fn()
                    times[label].append((time.perf_counter() - start) * 1e6)
            a = statistics.median(times["mine"])
            b = statistics.median(times["old"]) if times["old"] else float("nan")
            diff = difference(call(), old[name]()) if old[name] else float("nan")
            print(f"  {name:<22} {h:>4} x {n:<3} {a:10.1f} {b:10.1f} {a / b:6.2f} {diff:9.1e}")


if __name__ == "__main__":
    main()
