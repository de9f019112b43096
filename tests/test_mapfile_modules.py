"""The map file package's shape (issue 27): one concept a module, none over 600 lines, no import cycle between
them, and the public API still where the README names it (``mapdb.store``)."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "mapdb" / "mapfile"
MAX_MODULE_LINES = 600


def _modules() -> dict[str, Path]:
    return {p.stem: p for p in sorted(PACKAGE.glob("*.py")) if p.stem != "__init__"}


def _sibling_imports(path: Path) -> set[str]:
    """The modules of ``mapdb.mapfile`` that a module imports, at import time or inside a function."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module:  # from .codec import ...
                found.add(node.module.split(".")[0])
            elif node.level == 1:  # from . import codec
                found |= {alias.name for alias in node.names}
            elif node.level == 0 and (node.module or "").startswith("mapdb.mapfile."):
                found.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            found |= {a.name.split(".")[2] for a in node.names if a.name.startswith("mapdb.mapfile.")}
    return found


def test_the_old_single_module_is_gone_and_no_module_is_over_600_lines() -> None:
    modules = _modules()
    assert "store" not in modules
    assert {"layout", "codec", "pages", "spill", "header", "writer", "queries", "reader"} <= set(modules)
    sizes = {name: len(p.read_text(encoding="utf-8").splitlines()) for name, p in modules.items()}
    assert {name: n for name, n in sizes.items() if n > MAX_MODULE_LINES} == {}


def test_the_modules_import_each_other_without_a_cycle() -> None:
    graph = {name: _sibling_imports(path) & set(_modules()) for name, path in _modules().items()}
    assert graph["codec"] == set() and graph["layout"] == set(), "the leaves import no sibling"
    done: set[str] = set()

    def visit(name: str, path: tuple[str, ...]) -> None:
        assert name not in path, f"import cycle: {' -> '.join((*path, name))}"
        if name not in done:
            for other in sorted(graph[name]):
                visit(other, (*path, name))
            done.add(name)

    for name in graph:
        visit(name, ())


def test_the_cycle_check_sees_imports_inside_functions(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from .reader import open_map\n    from mapdb.mapfile.codec import area_codes\n")
    assert _sibling_imports(module) == {"reader", "codec"}


@pytest.mark.parametrize("name", sorted(_modules()))
def test_every_module_names_its_public_api(name: str) -> None:
    module = importlib.import_module(f"mapdb.mapfile.{name}")
    assert isinstance(module.__all__, list)
    assert all(hasattr(module, item) for item in module.__all__)


def test_the_public_api_is_still_mapdb_store() -> None:
    import mapdb.store as public

    assert set(public.__all__) == {"DEFAULT_MEMORY_OBJECTS", "DEFAULT_QUANTUM", "FORMAT_VERSION", "MAGIC", "MapBase",
                                   "MapWriter", "MemoryMap", "MetaMap", "area_codes", "open_map", "write_map",
                                   "write_map_from_chunks"}
    for item in public.__all__:
        home = getattr(public, item)
        owners = [name for name in _modules() if item in importlib.import_module(f"mapdb.mapfile.{name}").__all__]
        assert len(owners) == 1, f"{item} should have one home, has {owners}"
        assert getattr(importlib.import_module(f"mapdb.mapfile.{owners[0]}"), item) is home
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("mapdb.mapfile.store")
