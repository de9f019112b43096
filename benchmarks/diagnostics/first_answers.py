"""A fresh process's first answer, this tree against earlier revisions: wall and CPU time, alternating.

Reproduces the README's table "First answer of a fresh process (map and index dropped from the page cache,
open_map to the answer; 7 images, the three versions' processes alternating image by image ...)" of "A
compact index" (format 4 against format 3, 8fe1ca2, and format 2, a9181bd, on the 1M world).  Each image
(``benchmarks/lost_in_space_index.py``'s, seed 1) is answered by one fresh process a version, the versions'
order reversed every other image; each process drops the map and its index from the page cache, then times
``open_map`` and ``Localizer.localize`` (wall and CPU: on a loaded machine the wall time is mostly waiting
for a CPU).  ``benchmarks/lost_in_space_index.py --first-answers`` measures the same without the CPU time.

Each version answers from its own index of the map, built when missing by that version
(``_lis_children.BUILD``) beside a hard link of the map under ``--workdir``: this tree's under a digest of
``mapdb/match/index/``, a revision's under its commit.  Run from the repository root::

    python benchmarks/synthetic_world.py 1000000 --jitter 2 -o world-1M.mapdb    # the README's world
    python benchmarks/diagnostics/first_answers.py world-1M.mapdb 7 --baselines 8fe1ca2 a9181bd
    python benchmarks/diagnostics/first_answers.py andorra 7 --baselines 8fe1ca2 a9181bd   # quicker

``MAP`` is a map file or a shared extract's name (built once into a temporary folder).  The 1M world's
index builds take some 6 minutes each (three of them on the first run).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _baseline import ROOT, map_argument  # noqa: E402
from _lis_children import BUILD, FIRST_ANSWER, _child  # noqa: E402
from lost_in_space_index import _images  # noqa: E402

WORKDIR = Path(tempfile.gettempdir()) / "mapdb-diagnostics" / "first-answers"



def index_digest() -> str:
    """A digest of this tree's index code: an index built by other code is not reused."""
    digest = hashlib.sha256()
    for path in sorted((ROOT / "mapdb" / "match" / "index").glob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:10]


def version_map(map_path: Path, rev: str, workdir: Path) -> Path:
    """A link to the map in the version's folder, with that version's index built beside it when missing."""
    name = f"tree-{index_digest()}" if not rev else "rev-" + subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short=10", rev], check=True, capture_output=True,
        text=True).stdout.strip()
    target = workdir / name / map_path.name
    target.parent.mkdir(parents=True, exist_ok=True)
    if not target.exists():
        try:
            os.link(map_path, target)
        except OSError:
            shutil.copyfile(map_path, target)
    if not Path(str(target) + ".qidx").exists():
        built = _child(BUILD, str(target), "2", *((rev, str(workdir)) if rev else ()))
        print(f"{name}: index built in {built['wall_s']:.0f} s", flush=True)
    return target


def first_answers(images: list[dict], versions: list[tuple[str, Path, str]], workdir: Path) -> dict:
    """Each version's first answers, one fresh process an image, the versions alternating image by image."""
    results: dict[str, list[dict]] = {name: [] for name, _, _ in versions}
    for i, image in enumerate(images):
        for name, path, rev in versions if i % 2 == 0 else versions[::-1]:
            out = subprocess.run([sys.executable, "-c", FIRST_ANSWER, str(path), json.dumps(image), rev, str(workdir)],
                                 capture_output=True, text=True, check=True, cwd=ROOT).stdout
            results[name].append(json.loads(out.strip().splitlines()[-1]))
    return results


def main(argv: list[str] | None = None) -> int:
    """Build the versions' indexes where missing, then answer the images and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("map", help="a .mapdb file, or a shared extract's name (andorra, liechtenstein, monaco)")
    parser.add_argument("images", type=int, help="images (one fresh process each a version)")
    parser.add_argument("--baselines", nargs="*", default=[], metavar="REV", help="earlier revisions to compare")
    parser.add_argument("--workdir", type=Path, default=WORKDIR, help="where the versions' indexes are built")
    args = parser.parse_args(argv)
    path = map_argument(args.map, WORKDIR.parent)
    if path is None:
        return 1
    versions = [(rev or "this tree", version_map(path, rev, args.workdir), rev) for rev in ["", *args.baselines]]
    results = first_answers(_images(path, args.images, 1), versions, args.workdir)
    print(f"{path.name}, {args.images} images, first answer from open_map (map and index dropped from the cache):")
    print(f"{'version':<12} {'wall median (max) s':>20} {'CPU median (max) s':>19} {'ok':>6}")
    for name, r in results.items():
        wall, cpu = [x["open_to_answer_s"] for x in r], [x["open_to_answer_cpu_s"] for x in r]
        print(f"{name:<12} {statistics.median(wall):>11.2f} ({max(wall):5.2f}) {statistics.median(cpu):>10.2f}"
              f" ({max(cpu):5.2f}) {sum(x['status'] == 'ok' for x in r):>3}/{len(r)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
