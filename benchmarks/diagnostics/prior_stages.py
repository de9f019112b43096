"""Where an answer's time goes, with a prior and without: wall time of each stage, no profiler.

Issue 30 asks a prior's answer at half of the same image's time without one.  This splits both by stage
(the lookup of hypotheses, the screen with the decision and refinement, the final fit, the rival search,
the document's reading and the answer's record, and the tiles a prior's disc builds), timing each stage's
calls with ``time.perf_counter`` around them, over ``benchmarks/matcher_core.py``'s images of one extract:
with a 300 m prior on a fresh localizer (its tiles built as the images reach them: "prior cold"), the same
again once every tile is built ("prior warm"), and without the prior (the whole map's index built first).
Stages nest (``match_fast`` holds the others but the record and the reading), so shares do not add up.
Last, the bound no cheaper lookup can pass: each prior image's time with its lookup of hypotheses and its tiles
taken out (as if they cost nothing), its median against the no-prior median.

Run from the repository root::

    python benchmarks/diagnostics/prior_stages.py andorra 100
"""

from __future__ import annotations

import collections
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import clocked, extract_maps  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, simulated  # noqa: E402

import mapdb.localize.localizer as localizer_module  # noqa: E402
import mapdb.match.fast as fast  # noqa: E402
from mapdb.mapfile.reader import open_map  # noqa: E402

SPENT: collections.Counter = collections.Counter()
LOOKUP, TILES = "lookup of hypotheses", "indexes (a prior's tiles)"


def main() -> None:
    name = sys.argv[1] if len(sys.argv) > 1 else "andorra"
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 100
    for owner, function, stage in [
        (fast, "round_hypotheses", LOOKUP), (fast, "screen_round", "screen, decision, refinement"),
        (fast, "polish", "final fit"), (fast, "find_rivals", "rivals"), (localizer_module, "match_fast", "match_fast"),
        (localizer_module, "_checked", "reading the document"), (localizer_module, "ok_record", "the answer's record"),
        (localizer_module.Localizer, "fast_indexes", TILES),
    ]:
        setattr(owner, function, clocked(getattr(owner, function), stage, SPENT))
    path = extract_maps([name], EXTRACTS, DATA, CACHE)[name]
    images = simulated(path, n, 3)
    without = [{k: v for k, v in image.items() if k != "prior"} for image in images]
    medians: dict[str, tuple[float, float]] = {}
    for case, documents, warm in (("prior cold", images, False), ("prior warm", images, True),
                                  ("no prior", without, True)):
        localizer = localizer_module.localizer_for(open_map(path))
        for document in documents if warm else ():
            localizer.localize(document)
        SPENT.clear()
        times, without_lookup = [], []
        for document in documents:
            looked_up = SPENT[LOOKUP] + SPENT[TILES]
            start = time.perf_counter()
            localizer.localize(document)
            times.append(time.perf_counter() - start)
            without_lookup.append(times[-1] - (SPENT[LOOKUP] + SPENT[TILES] - looked_up))
        total = sum(times)
        medians[case] = statistics.median(times), statistics.median(without_lookup)
        print(f"{name}, {case}: median {1e3 * statistics.median(times):.2f} ms, mean {1e3 * total / n:.2f} ms an image")
        for stage, seconds in SPENT.most_common():
            print(f"   {stage:30s} {1e3 * seconds / n:7.3f} ms an image  {seconds / total:6.1%}")
    # What no lookup could beat: each image's time with its lookup and its tiles taken out (as if they cost
    # nothing), against the same images' median without a prior.
    no_prior = medians["no prior"][0]
    for case in ("prior cold", "prior warm"):
        print(f"{name}, {case} with its lookup and tiles taken out: median {1e3 * medians[case][1]:.2f} ms, "
              f"{medians[case][1] / no_prior:.2f} of no prior's {1e3 * no_prior:.2f} ms")


if __name__ == "__main__":
    main()
