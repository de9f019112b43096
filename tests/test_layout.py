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

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 600
MAX_ROOT_MODULES = 12


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[0] == "cli":
        parts[0] = "mapdb_cli"
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Every module of ``mapdb/`` and ``cli/`` -> the modules of the two it imports, anywhere in its code.

    ``from package import name`` counts as an import of ``package.name`` when that is a module, else of
    ``package`` (whose ``__init__`` then runs).
    """
    paths = {module_name(p, root): p for p in [*root.glob("mapdb/**/*.py"), *root.glob("cli/*.py")]}
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found |= {alias.name for alias in node.names if alias.name in paths}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join([*base, *([node.module] if node.module else [])])
                else:
                    target = node.module or ""
                for alias in node.names:
                    child = f"{target}.{alias.name}"
                    found.add(child if child in paths else target)
        graph[name] = {module for module in found if module in paths and module != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


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
