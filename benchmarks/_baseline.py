"""The mapdb of an earlier commit beside this tree's, in one process (shared by the benchmarks).

Timing two versions in separate runs on a shared, noisy machine compares the load more than the code;
importing both into one process lets a benchmark alternate between them image by image.
"""

from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def shared_data(*parts: str) -> Path:
    """``../shared/data/PARTS`` beside the checkout, or the machine's shared copy for a git worktree elsewhere.

    Returns the path beside the checkout when neither exists, so that the caller's message names it.
    """
    beside = ROOT.parent.joinpath("shared", "data", *parts)
    machine = Path("/work/shared/data").joinpath(*parts)
    return next((p for p in (beside, machine) if p.exists()), beside)


def import_baseline(rev: str, workdir: Path, module: str = "localize") -> ModuleType:
    """``mapdb.<module>`` as of git revision ``rev``, imported as package ``mapdb_baseline``.

    The revision's ``mapdb/`` is extracted under ``workdir/baseline-COMMIT`` (once per commit): into a
    temporary folder renamed into place, so that two benchmarks started at once on the same workdir each
    import a complete copy (the first rename wins; the other's copy is dropped).

    mapdb's modules import each other relatively, so the old package works under another name.
    """
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{rev}^{{commit}}"], check=True,
                            capture_output=True, text=True).stdout.strip()
    pkg_dir = workdir / f"baseline-{commit}"
    if not (pkg_dir / "mapdb_baseline").is_dir():
        workdir.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".baseline-", dir=workdir))
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "mapdb"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(staging)], input=archive, check=True)
        _build_kernel(rev, staging)
        (staging / "mapdb").rename(staging / "mapdb_baseline")
        try:
            staging.rename(pkg_dir)
        except OSError:  # another benchmark's copy got there first
            shutil.rmtree(staging, ignore_errors=True)
    if str(pkg_dir) not in sys.path:
        sys.path.insert(0, str(pkg_dir))
    return importlib.import_module(f"mapdb_baseline.{module}")


def _build_kernel(rev: str, staging: Path) -> None:
    """Build the revision's compiled kernel in place (``staging/mapdb``), by its own ``setup.py``, when it has one:
    the baseline package must import as installed."""
    if not (staging / "mapdb" / "match" / "_kernel.c").exists():
        return
    setup = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:setup.py"], check=True,
                           capture_output=True).stdout
    (staging / "setup.py").write_bytes(setup)
    subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--inplace"], cwd=staging, check=True,
                   capture_output=True)


def code_digest() -> str:
    """A digest of the code that writes maps (build, sources, map file): cached maps built by other code (an
    older tree, another worktree) are not reused, as a map built before blocks existed once was."""
    import hashlib

    digest = hashlib.sha256()
    for folder in ("build", "sources", "mapfile"):
        for path in sorted((ROOT / "mapdb" / folder).rglob("*.py")):
            digest.update(path.read_bytes())
    return digest.hexdigest()[:10]


def cli_tree(rev: str, root: Path) -> Path:
    """``root`` holding revision ``rev``'s ``mapdb`` (its compiled kernel built) and its CLI as ``mapdb_cli``
    (extracted once): first on ``PYTHONPATH``, the installed ``mapdb`` script runs that revision (the editable
    install's finder comes after the path)."""
    if not (root / "mapdb_cli").is_dir():
        root.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "mapdb", "cli"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(root)], input=archive, check=True)
        _build_kernel(rev, root)  # a revision with a compiled kernel runs only with it built
        (root / "cli").rename(root / "mapdb_cli")
    return root


# The shared OSM extracts by name (``../shared/data/osm``).
OSM_EXTRACTS = {"andorra": "andorra-2021-06-22.osm.pbf", "liechtenstein": "liechtenstein-2013-08-03.osm.pbf",
                "monaco": "monaco-2021-12-03.osm.pbf"}


def map_argument(value: str, cache: Path) -> Path | None:
    """A script's MAP argument: a shared extract's name (its map built once into ``cache``) or a map file's
    path; None, said on stderr, when the extract named is not in the shared data."""
    if value not in OSM_EXTRACTS:
        return Path(value).resolve()
    data = shared_data("osm")
    if not (data / OSM_EXTRACTS[value]).exists():
        print(f"needs the shared data: {data / OSM_EXTRACTS[value]}", file=sys.stderr)
        return None
    return cached_maps({value: OSM_EXTRACTS[value]}, data, cache)[value]


def as_json(answer: Any) -> dict:
    """An answer as JSON, from this revision (an :class:`mapdb.answers.Answer`) or an older one (a dict)."""
    return answer.to_json() if hasattr(answer, "to_json") else answer


def extract_maps(names: list[str], extracts: dict[str, str], data: Path, cache: Path) -> dict[str, Path]:
    """:func:`cached_maps` of the extracts ``names`` (keys of ``extracts``); the script exits saying it skipped when
    one of their files is not under ``data``."""
    if not all((data / extracts[n]).exists() for n in names):
        sys.exit(f"skipped: the extracts are not all in {data}")
    return cached_maps({n: extracts[n] for n in names}, data, cache)


def cached_maps(extracts: dict[str, str], data: Path, cache: Path) -> dict[str, Path]:
    """Each extract's map (``name -> file name`` under ``data``), built once into ``cache``, outside the
    repository, by this tree's map-writing code (:func:`code_digest` in the file name)."""
    from mapdb.build.pipeline import build_map

    cache.mkdir(exist_ok=True)
    paths = {}
    for name, pbf in extracts.items():
        path = cache / f"{name}.{code_digest()}.mapdb"
        if not path.exists():
            build_map([data / pbf], path)
        paths[name] = path
    return paths


def clocked(function: Any, label: str, totals: Any, clock: Callable[[], float] = time.perf_counter) -> Any:
    """``function`` wrapped so that each call adds its time by ``clock`` (wall by default; ``time.process_time`` for
    the process's CPU) to ``totals[label]`` (a ``collections.Counter``): a stage's share of a run, no profiler."""
    def timed(*args: Any, **kwargs: Any) -> Any:
        start = clock()
        try:
            return function(*args, **kwargs)
        finally:
            totals[label] += clock() - start

    return timed
