"""First contact: ``mapdb simulate MAP -o - --n 20 --seed 2 | mapdb query MAP -`` with the defaults, and with
``--min-objects 6``, over the sample map and the shared extracts (issue 32, first contact).

Run from the repository root::

    python benchmarks/first_contact.py [--n 20] [--seed 2]

Prints, per map and per way of simulating: the median objects an image, the images localized (not rejected)
out of ``--n``, and whether ``simulate`` warned.  Counts, not timings: the same command gives the same table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

DATA = next((p for p in (Path(__file__).resolve().parents[2] / "shared" / "data" / "osm",
                         Path("/work/shared/data/osm")) if p.exists()), None)
SAMPLE = Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"
EXTRACTS = ("andorra-2021-06-22.osm.pbf", "liechtenstein-2013-08-03.osm.pbf", "monaco-2021-12-03.osm.pbf")


def mapdb(*args: str, stdin: bytes | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapdb_cli", *args], input=stdin, capture_output=True, check=True)


def row(map_path: Path, n: int, seed: int, extra: list[str]) -> tuple[float, int, bool]:
    """Median objects an image, images localized, and whether simulate warned."""
    sim = mapdb("simulate", str(map_path), "-o", "-", "--n", str(n), "--seed", str(seed), "-q", *extra)
    images = [json.loads(line) for line in sim.stdout.splitlines()]
    answers = mapdb("query", str(map_path), "-", stdin=sim.stdout)
    localized = sum(json.loads(line)["status"] != "rejected" for line in answers.stdout.splitlines())
    return statistics.median(len(im["objects"]) for im in images), localized, b"mapdb: warning:" in sim.stderr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--seed", type=int, default=2)
    args = parser.parse_args()
    sources = [SAMPLE] + ([DATA / name for name in EXTRACTS] if DATA else [])
    if DATA is None:
        print("(../shared/data/osm not found: the sample map only)")
    print("| map | simulate | median objects an image | localized | warned |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for source in sources:
            map_path = Path(tmp) / (source.name.split("-")[0].split(".")[0] + ".mapdb")
            mapdb("build", str(source), "-o", str(map_path), "-q")
            for label, extra in (("defaults", []), ("--min-objects 6", ["--min-objects", "6"])):
                median, localized, warned = row(map_path, args.n, args.seed, extra)
                warning = "yes" if warned else "no"
                print(f"| {map_path.name} | {label} | {median:g} | {localized}/{args.n} | {warning} |")


if __name__ == "__main__":
    main()
