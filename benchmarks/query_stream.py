"""``mapdb query`` over a file of many images, this tree against a baseline commit: time an answer, the same bytes.

The images are ``matcher_core.py``'s (300 m, 60 degree field of view, random heading, 1 px, at least 6 objects; their
300 m prior in each document, the ``truth`` key left out) on each map asked for.  Two JSON Lines files are written: the
``--n`` images once, and the same images ``--passes`` times over (a stream that comes back to places it has seen, as a
flight's frames do: after the first pass the tiles around each prior are built, and what is measured is an answer's
own work).  Each ``--rounds`` round runs ``mapdb query MAP FILE -o OUT`` on both files in fresh processes for this tree
and for the baseline (its ``mapdb`` and CLI first on ``PYTHONPATH``: :func:`_baseline.cli_tree`), which goes first
alternating round by round, so both meet the same load.  Printed per map and tree, medians over the rounds: the wall
and CPU seconds of the run over the long file; the CPU milliseconds an image of the passes after the first (the long
run's CPU less the short one's, over the images it adds: reading the line, the answer, its JSON written); the median
of the later passes' answers' own ``time_ms`` (what ``localize`` measured of each); and whether the two trees' outputs
are the same bytes once each answer's ``time_ms`` is taken out.  The load average is printed beside, the machine
being shared.

Run from the repository root::

    python benchmarks/query_stream.py --baseline main --maps andorra,monaco,liechtenstein
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline import cached_maps, cli_tree  # noqa: E402
from matcher_core import CACHE, DATA, EXTRACTS, simulated  # noqa: E402

TIME_MS = re.compile(rb',"time_ms":[^,}]*')


def run(env: dict[str, str], map_path: Path, images: Path, out: Path) -> tuple[float, float]:
    """Wall and CPU seconds of one ``mapdb query`` child writing ``out``."""
    start = os.times()
    subprocess.run([str(Path(sys.executable).with_name("mapdb")), "query", str(map_path), str(images), "-o", str(out),
                    "--overwrite"], env=env, check=True, capture_output=True)
    end = os.times()
    return end.elapsed - start.elapsed, (end.children_user - start.children_user) + (end.children_system
                                                                                     - start.children_system)


def answers_ms(out: Path, skip: int) -> float:
    """The median of the answers' own ``time_ms`` after the first ``skip``."""
    return statistics.median(json.loads(line)["time_ms"] for line in out.read_bytes().splitlines()[skip:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--baseline", default="main", help="git revision to compare against")
    parser.add_argument("--maps", default="andorra,monaco,liechtenstein")
    parser.add_argument("--n", type=int, default=100, help="images a pass")
    parser.add_argument("--passes", type=int, default=4, help="passes over the images in the long file")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="query-stream-"))
    base_root = cli_tree(args.baseline, CACHE / f"cli-{args.baseline.replace('/', '_')}")
    envs = {"this tree": {**os.environ}, f"baseline {args.baseline}": {**os.environ, "PYTHONPATH": str(base_root)}}
    added = (args.passes - 1) * args.n
    print(f"mapdb query over {args.n} images x {args.passes} passes, {args.rounds} rounds; "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"  {'map':<14} {'code':<17} {'wall s':>7} {'cpu s':>7} {'cpu ms/image':>12} {'time_ms':>8} {'same':>5}")
    for name in args.maps.split(","):
        map_path = cached_maps({name: EXTRACTS[name]}, DATA, CACHE)[name]
        docs = [{k: v for k, v in im.items() if k != "truth"} for im in simulated(map_path, args.n, args.seed)]
        once, many = work / f"{name}.once.jsonl", work / f"{name}.many.jsonl"
        once.write_text("".join(json.dumps(d) + "\n" for d in docs))
        many.write_text(once.read_text() * args.passes)
        runs: dict[str, list[tuple[float, float, float]]] = {label: [] for label in envs}
        for r in range(args.rounds):
            for label, env in (list(envs.items()) if r % 2 == 0 else list(envs.items())[::-1]):
                wall, cpu = run(env, map_path, many, work / f"{label}.jsonl")
                short = run(env, map_path, once, work / f"{label}.once.out")[1]
                runs[label].append((wall, cpu, (cpu - short) / added * 1e3))
        outputs = {label: TIME_MS.sub(b"", (work / f"{label}.jsonl").read_bytes()) for label in envs}
        same = len(set(outputs.values())) == 1
        for label in envs:
            wall, cpu, per_image = (statistics.median(t[i] for t in runs[label]) for i in range(3))
            print(f"  {name:<14} {label:<17} {wall:7.2f} {cpu:7.2f} {per_image:12.2f} "
                  f"{answers_ms(work / f'{label}.jsonl', args.n):8.3f} {'yes' if same else 'NO':>5}")
    print(f"  load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
