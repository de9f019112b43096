"""The matcher's layout (issue 27): no import cycles in ``mapdb/match``, no stage importing the orchestrator, and
the fast matcher's top function calling its stages in order.

The import graph is built from the code: every ``import`` and ``from ... import`` statement, those inside
functions and under ``TYPE_CHECKING`` included, since a cycle there still ties two modules together.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MATCH = ROOT / "mapdb" / "match"


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, root: Path, known: set[str]) -> set[str]:
    """The modules of ``known`` that ``path`` imports, anywhere in its code."""
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                anchor = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{anchor}.{base}" if base else anchor
            found.add(base)
            # ``from package import module`` imports the module itself.
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return {m for m in found if m in known and m != name}


def import_graph(package_dir: Path, root: Path) -> dict[str, set[str]]:
    """Module -> the modules of the same package tree it imports."""
    paths = sorted(package_dir.rglob("*.py"))
    known = {_module_name(p, root) for p in paths}
    return {_module_name(p, root): _imports(p, root, known) for p in paths}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                found.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_imports_inside_functions_and_under_type_checking(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .b import B\n")
    (pkg / "b.py").write_text("def f():\n    from .sub import c\n")
    (pkg / "sub" / "c.py").write_text("from .. import a\n")
    (pkg / "d.py").write_text("import pkg.a\n")
    graph = import_graph(pkg, tmp_path)
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.sub", "pkg.sub.c"}
    assert graph["pkg.sub.c"] == {"pkg", "pkg.a"} and graph["pkg.d"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.b", "pkg.sub.c"]]
    (pkg / "b.py").write_text("")
    assert cycles(import_graph(pkg, tmp_path)) == []


def test_the_matcher_has_no_import_cycle() -> None:
    assert cycles(import_graph(MATCH, ROOT)) == []


def test_no_stage_imports_the_orchestrator() -> None:
    graph = import_graph(MATCH, ROOT)
    importers = sorted(m for m, deps in graph.items() if "mapdb.match.fast" in deps)
    assert importers == ["mapdb.match"]  # the package re-exports match_fast; no stage module reaches back


def test_the_evidence_models_import_no_stage() -> None:
    graph = import_graph(MATCH, ROOT)
    evidence = {m: deps for m, deps in graph.items() if m.startswith("mapdb.match.evidence")}
    assert len(evidence) >= 5
    for module, deps in evidence.items():
        stages = {d for d in deps if not d.startswith(("mapdb.match.evidence", "mapdb.match.mapobjects",
                                                       "mapdb.match.geometry"))}
        assert not stages, f"{module} imports {sorted(stages)}"


def test_match_fast_calls_its_stages_in_order() -> None:
    tree = ast.parse((MATCH / "fast.py").read_text(encoding="utf-8"))
    top = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "match_fast")
    calls = [n for n in ast.walk(top) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    called = [n.func.id for n in sorted(calls, key=lambda n: (n.lineno, n.col_offset))]
    stages = ["_search", "uncertain", "find_rivals", "ambiguous", "polish", "answer"]
    assert [c for c in called if c in stages] == stages
