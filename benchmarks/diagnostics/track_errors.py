"""Per track of ``mapdb navigate`` (simulated flights, with truth): share within 2 m and 5 m, largest errors.

Reproduces the README's "Ideal flights after these two changes" figures (issue 29): the share of all frames
within 2 m, and the largest error after the first position (the lost-in-space start) and after the first fix
applied (``fix.status`` "used").  The tracks are made with the CLI, as the README says (the sample map, 120 m,
5 fps, 1,500 m, seeds 1 and 2)::

    mapdb build sample_maps/helsinki.osm.pbf -o hel.mapdb
    mapdb simulate flight hel.mapdb -o F1.jsonl --length 1500 --fps 5 --altitude 120 --fov 60 --seed 1
    mapdb navigate hel.mapdb F1.jsonl -o T1.jsonl          # and the same with --seed 2: T2.jsonl
    python benchmarks/diagnostics/track_errors.py T1.jsonl T2.jsonl

Prints one line a track: frames, fixes used, within 2 m and 5 m (of all frames: a frame without a position
counts as beyond), median error, largest error after the first position and after the first used fix.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path


def track_line(path: Path) -> str:
    """One track's summary."""
    records = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    errors = [r["truth"]["error_m"] for r in records]
    n = len(records)
    first_position = next(i for i, r in enumerate(records) if r["x"] is not None)
    first_used = next(i for i, r in enumerate(records) if r["fix"]["status"] == "used")
    known = [e for e in errors if e is not None]
    used = sum(r["fix"]["status"] == "used" for r in records)
    return (f"{path.name}: frames {n}, fixes used {used}, within 2 m {100 * sum(e <= 2.0 for e in known) / n:.1f} %,"
            f" within 5 m {100 * sum(e <= 5.0 for e in known) / n:.1f} %, median {statistics.median(known):.3f} m,"
            f" largest after the first position {max(e for e in errors[first_position:] if e is not None):.2f} m,"
            f" after the first used fix {max(e for e in errors[first_used:] if e is not None):.2f} m")


def main(argv: list[str] | None = None) -> int:
    """Summarise each track; a track that cannot be read is reported and the others still are."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("tracks", nargs="+", type=Path, help="mapdb navigate outputs (JSON lines with truth)")
    args = parser.parse_args(argv)
    failed = 0
    for path in args.tracks:
        try:
            print(track_line(path))
        except (OSError, ValueError, KeyError, TypeError, StopIteration) as exc:
            print(f"track_errors: error: {path}: {exc.__class__.__name__} {exc}", file=sys.stderr)
            failed = 1
    return failed


if __name__ == "__main__":
    sys.exit(main())
