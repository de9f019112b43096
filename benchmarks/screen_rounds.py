"""A round's screen (``mapdb.match.screen.screen_round``: screen, verify, decide, refine) side by side with a baseline
revision's, on the rounds real images make.

The rounds are recorded once from this tree's matcher: ``matcher_core.py``'s images (300 m, random heading, 1 px) of
the shared extracts, with their 300 m prior and without, and, with ``--analyze MAP`` (a map indexed with ``mapdb
index``), the rounds of ``mapdb analyze MAP`` (its simulated cells' images).  Each recorded round (its hypotheses,
image, index and options) is then replayed by this tree's ``screen_round`` and by the baseline's (imported as
``mapdb_baseline`` by ``_baseline.import_baseline``, the round's objects rebuilt as the baseline's classes), the two
taking turns round set by round set (which goes first alternates).  The table gives each set's mean time a
round (the median over ``--rounds`` replays), its p95 over the rounds (the median over replays), the ratios, and
whether every round's candidates are the same (position, scale, NFA, inliers, errors and pairs, bit for bit).  The
load average and the gauge (``matcher_core.gauge_ms``) are printed beside.

Run from the repository root::

    python benchmarks/screen_rounds.py --baseline main --analyze /tmp/monaco.mapdb
"""

from __future__ import annotations

import argparse
import io
import os
import pickle
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import extract_maps, import_baseline  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, gauge_ms, simulated  # noqa: E402

import mapdb.match.fast as fast  # noqa: E402
import mapdb.match.screen as screen  # noqa: E402


def record(maps: list[str], n: int, analyze: Path | None) -> tuple[list[tuple[Any, ...]], dict[str, range]]:
    """The rounds this tree's matcher screens on each map's images (and an analysis run's): their arguments."""
    import mapdb.localize.localizer as localizer
    from mapdb.mapfile.reader import open_map

    calls: list[tuple[Any, ...]] = []
    sets: dict[str, range] = {}
    plain = fast.screen_round

    def kept(*args: Any, **kwargs: Any) -> Any:
        calls.append((args, kwargs))
        return plain(*args, **kwargs)

    fast.screen_round = kept
    try:
        for name, path in extract_maps(maps, EXTRACTS, DATA, CACHE).items():
            images = simulated(path, n, 3)
            for case in ("prior", "no prior"):
                use = images if case == "prior" else [{k: v for k, v in im.items() if k != "prior"} for im in images]
                loc, start = localizer.localizer_for(open_map(path)), len(calls)
                for image in use:
                    loc.localize(image)
                sets[f"{name}, {case}"] = range(start, len(calls))
        if analyze is not None:
            from mapdb_cli.main import cli

            start = len(calls)
            with tempfile.TemporaryDirectory() as out:
                cli(["analyze", str(analyze), "-o", out, "--overwrite", "-q"], standalone_mode=False)
            sets[f"analyze {analyze.stem}"] = range(start, len(calls))
    finally:
        fast.screen_round = plain
    return calls, sets


class _AsBaseline(pickle.Unpickler):
    """Rebuilds pickled mapdb objects as the baseline package's classes."""

    def find_class(self, module: str, name: str) -> Any:
        if module == "mapdb" or module.startswith("mapdb."):
            module = "mapdb_baseline" + module[len("mapdb"):]
        return super().find_class(module, name)


def _answers(found: list[Any]) -> str:
    return repr([(c.a, c.b, c.log10_nfa, c.inliers, c.sigma_axis_m, c.variance_factor, c.log10_nfa_points,
                  c.pairs.tolist()) for c in found])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", default="main", help="git revision compared")
    parser.add_argument("--maps", default="andorra,monaco", help="extracts whose images' rounds are replayed")
    parser.add_argument("--n", type=int, default=100, help="images a map")
    parser.add_argument("--analyze", type=Path, help="an indexed map whose analysis rounds are replayed too")
    parser.add_argument("--rounds", type=int, default=9, help="replays of every set by each version")
    args = parser.parse_args()
    calls, sets = record(args.maps.split(","), args.n, args.analyze)
    base = import_baseline(args.baseline, CACHE, "match.screen")
    theirs = _AsBaseline(io.BytesIO(pickle.dumps(calls))).load()
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; gauge {gauge_ms():.1f} ms")
    print(f"screen_round replayed, this tree against {args.baseline}, {args.rounds} replays each, taking turns")
    print("| rounds | n | this tree: mean ms a round | p95 | baseline: mean | p95 | ratio: mean | p95 | same |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, rows in sets.items():
        same = all(_answers(screen.screen_round(*calls[i][0], **calls[i][1])) == _answers(
            base.screen_round(*theirs[i][0], **theirs[i][1])) for i in rows)
        times: dict[str, list[list[float]]] = {"tree": [], "base": []}
        for k in range(args.rounds):
            for who in ("tree", "base") if k % 2 == 0 else ("base", "tree"):
                fn, given = (screen.screen_round, calls) if who == "tree" else (base.screen_round, theirs)
                each = []
                for i in rows:
                    t = time.perf_counter()
                    fn(*given[i][0], **given[i][1])
                    each.append((time.perf_counter() - t) * 1e3)
                times[who].append(each)
        med = {w: statistics.median(statistics.mean(e) for e in times[w]) for w in times}
        p95 = {w: statistics.median(statistics.quantiles(e, n=20)[-1] for e in times[w]) for w in times}
        print(f"| {label} | {len(rows)} | {med['tree']:.3f} | {p95['tree']:.3f} | {med['base']:.3f} | "
              f"{p95['base']:.3f} | {med['tree'] / med['base']:.3f} | {p95['tree'] / p95['base']:.3f} | "
              f"{'yes' if same else 'NO'} |")
    print(f"load average after: {os.getloadavg()[0]:.1f}; gauge {gauge_ms():.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
