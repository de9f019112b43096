"""The matcher's layout (issue 27): no stage importing the orchestrator, evidence models importing no stage,
and the fast matcher's top function calling its stages in order (import cycles: ``test_layout``)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

from importgraph import import_graph

ROOT = Path(__file__).resolve().parents[1]
MATCH = ROOT / "mapdb" / "match"


@functools.cache
def match_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """The import graph restricted to ``mapdb.match`` and its subpackages (built once: the tests only read it)."""
    graph = import_graph(root)
    inside = {m for m in graph if m == "mapdb.match" or m.startswith("mapdb.match.")}
    return {m: graph[m] & inside for m in inside}


def test_no_stage_imports_the_orchestrator() -> None:
    graph = match_graph()
    importers = sorted(m for m, deps in graph.items() if "mapdb.match.fast" in deps)
    assert importers == ["mapdb.match"]  # the package re-exports match_fast; no stage module reaches back


def test_the_evidence_models_import_no_stage() -> None:
    graph = match_graph()
    evidence = {m: deps for m, deps in graph.items() if m.startswith("mapdb.match.evidence")}
    assert len(evidence) >= 5
    for module, deps in evidence.items():
        stages = {d for d in deps if not d.startswith(("mapdb.match.evidence", "mapdb.match.mapobjects",
                                                       "mapdb.match.geometry", "mapdb.match.arrays"))}
        assert not stages, f"{module} imports {sorted(stages)}"


def test_match_fast_calls_its_stages_in_order() -> None:
    tree = ast.parse((MATCH / "fast.py").read_text(encoding="utf-8"))
    top = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "match_fast")
    calls = [n for n in ast.walk(top) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    called = [n.func.id for n in sorted(calls, key=lambda n: (n.lineno, n.col_offset))]
    stages = ["_search", "uncertain", "find_rivals", "ambiguous", "polish", "answer"]
    assert [c for c in called if c in stages] == stages
