"""Type hints: ``mypy`` (configured in pyproject.toml) finds no error in the package and the CLI.

The package ships ``py.typed``, so its hints are what users' type checkers read; this keeps them true.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Modules whose mypy errors are being fixed elsewhere: while any error is reported in one of them, the
# test skips naming them instead of failing.  Empty when the whole tree is clean.
PENDING: dict[str, str] = {}


def test_package_ships_py_typed() -> None:
    assert (ROOT / "mapdb" / "py.typed").is_file()
    assert '"py.typed"' in (ROOT / "pyproject.toml").read_text(encoding="utf-8")


@pytest.mark.skipif(importlib.util.find_spec("mypy") is None, reason="mypy is not installed (pip install -e .[test])")
def test_mypy_is_clean() -> None:
    result = subprocess.run([sys.executable, "-m", "mypy", "mapdb", "cli"], cwd=ROOT, capture_output=True,
                            text=True, timeout=600)
    output = result.stdout + result.stderr
    if result.returncode != 0:
        errors = [line for line in output.splitlines() if ": error:" in line]
        files = {line.split(":", 1)[0] for line in errors}
        if errors and files <= set(PENDING):
            pytest.skip("mypy errors remain in files being fixed elsewhere: "
                        + "; ".join(f"{f} ({PENDING[f]})" for f in sorted(files)))
    assert result.returncode == 0, output
