"""The layout rules of ``docs/architecture.md``, checked from the code on every run.

* no import cycle between modules of ``mapdb/`` and ``cli/``, counting every import: at module level, inside
  functions and under ``TYPE_CHECKING`` (a cycle hidden in a function still means two modules that cannot be
  understood, or changed, one without the other);
* no module of ``mapdb/`` or ``cli/`` over 600 lines;
* at most 12 modules at the root of ``mapdb/`` (the vocabulary every stage shares; everything else lives in the
  package of its stage);
* every package of ``mapdb/`` is named in ``docs/architecture.md``, and every name the README documents imports;
* the README's Python example runs as written.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from importgraph import cycles, import_graph, module_name

ROOT = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 600
MAX_ROOT_MODULES = 12


def test_the_cycle_finder_finds_a_cycle_through_a_function_level_import(tmp_path: Path) -> None:
    package = tmp_path / "mapdb"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from .b import f\n")
    (package / "b.py").write_text("def f():\n    from . import c\n")
    (package / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import f\n")
    (package / "d.py").write_text("from . import a\n")
    assert cycles(import_graph(tmp_path)) == [["mapdb.a", "mapdb.b", "mapdb.c"]]
    (package / "c.py").write_text("")
    assert cycles(import_graph(tmp_path)) == []


def test_no_import_cycles() -> None:
    graph = import_graph()
    assert "mapdb.match.fast" in graph and "mapdb_cli.main" in graph, "the graph missed the code"
    assert cycles(graph) == []


def test_no_module_is_over_600_lines() -> None:
    paths = [*ROOT.glob("mapdb/**/*.py"), *ROOT.glob("cli/*.py")]
    sizes = {str(p.relative_to(ROOT)): len(p.read_text(encoding="utf-8").splitlines()) for p in paths}
    assert len(sizes) > 50
    assert {path: n for path, n in sizes.items() if n > MAX_MODULE_LINES} == {}


def test_the_package_root_holds_at_most_12_modules() -> None:
    modules = sorted(p.name for p in (ROOT / "mapdb").glob("*.py") if p.name != "__init__.py")
    assert len(modules) <= MAX_ROOT_MODULES, modules


def test_the_architecture_page_names_every_package() -> None:
    page = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    packages = sorted(module_name(p) for p in ROOT.glob("mapdb/**/__init__.py"))
    assert len(packages) > 8
    assert [name for name in packages if f"`{name.replace('.', '/')}/`" not in page] == []


def readme_python() -> str:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(encoding="utf-8"), re.S)
    assert blocks, "the README has no Python example"
    return "\n".join(blocks)


def test_every_name_the_readme_imports_exists() -> None:
    imports = re.findall(r"^from (mapdb[\w.]*) import (.+)$", readme_python(), re.M)
    assert imports
    for module, names in imports:
        imported = __import__(module, fromlist=["_"])
        for name in (part.strip() for part in names.split(",")):
            assert hasattr(imported, name), f"{module}.{name}"


def test_the_readme_python_example_runs_as_written(tmp_path: Path) -> None:
    # Run from a copy of the files it names, as a user at the repository root would, so that its ``out/``
    # lands in tmp_path.
    sample = Path("sample_maps") / "helsinki.osm.pbf"
    (tmp_path / "sample_maps").mkdir()
    (tmp_path / sample).write_bytes((ROOT / sample).read_bytes())
    env = {**os.environ, "PYTHONWARNINGS": "error::DeprecationWarning:mapdb"}
    done = subprocess.run([sys.executable, "-c", readme_python()], cwd=tmp_path, capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "localized" in done.stdout
    assert (tmp_path / "out" / "helsinki.mapdb").is_file()


@pytest.mark.parametrize("module", ["mapdb.store", "mapdb.build", "mapdb.localize", "mapdb.match"])
def test_public_modules_export_what_they_list(module: str) -> None:
    imported = __import__(module, fromlist=["_"])
    assert imported.__all__
    assert [name for name in imported.__all__ if not hasattr(imported, name)] == []
