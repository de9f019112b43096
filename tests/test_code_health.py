"""The code-health rules the project holds itself to, checked on every run (see the README's "Code").

* every function of the library and the CLI is at most 60 lines of code (its docstring not counted:
  numpydoc parameters and examples are documentation, not length);
* no module of ``mapdb/match/`` is over 400 lines;
* the library never imports click or the CLI.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION_LINES = 60
MAX_MATCH_MODULE_LINES = 400


def _sources(*patterns: str) -> list[Path]:
    return sorted(p for pattern in patterns for p in ROOT.glob(pattern))


def _code_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    lines = (node.end_lineno or node.lineno) - node.lineno + 1
    first = node.body[0] if node.body else None
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        lines -= (first.end_lineno or first.lineno) - first.lineno + 1
    return lines


def _long_functions(path: Path, root: Path = ROOT) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [f"{path.relative_to(root)}:{node.lineno} {node.name} ({_code_lines(node)} lines)"
            for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _code_lines(node) > MAX_FUNCTION_LINES]


def test_the_rule_counts_code_not_docstrings(tmp_path: Path) -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    long_doc = '    """' + "\n".join(["doc"] * 100) + '"""\n'
    fits = tmp_path / "fits.py"
    fits.write_text(f"def f():\n{long_doc}{body[: body.rfind(chr(10))]}\n")
    too_long = tmp_path / "long.py"
    too_long.write_text(f"def f():\n{body}\n    return 0\n")
    assert _long_functions(fits, tmp_path) == []
    assert _long_functions(too_long, tmp_path) == [f"long.py:1 f ({MAX_FUNCTION_LINES + 2} lines)"]


def test_every_function_is_at_most_60_lines() -> None:
    found = [entry for path in _sources("mapdb/**/*.py", "cli/*.py") for entry in _long_functions(path)]
    assert found == [], "\n".join(found)


def test_no_matcher_module_is_over_400_lines() -> None:
    sizes = {str(p.relative_to(ROOT)): len(p.read_text(encoding="utf-8").splitlines())
             for p in _sources("mapdb/match/**/*.py")}
    assert sizes, "no matcher modules found"
    assert {name: n for name, n in sizes.items() if n > MAX_MATCH_MODULE_LINES} == {}


@pytest.mark.parametrize("path", _sources("mapdb/**/*.py"), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_library_never_imports_click_or_the_cli(path: Path) -> None:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                for alias in node.names}
    imported |= {(node.module or "").split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.level == 0}
    assert not imported & {"click", "mapdb_cli", "cli"}
