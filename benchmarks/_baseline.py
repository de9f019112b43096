"""Run code of this tree and of an earlier commit side by side (shared by the benchmarks)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def baseline_code(rev: str, workdir: Path) -> Path:
    """The ``mapdb`` package of git revision ``rev``, extracted under ``workdir``; a PYTHONPATH entry."""
    base = workdir / f"baseline-{rev}"
    base.mkdir(exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "mapdb"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
    return base


def run_python(code_dir: Path | None, script: str, *args: str, cwd: Path) -> str:
    """Run ``script`` (Python source) with the mapdb of ``code_dir`` (None: this tree's); its stdout.

    It runs from ``cwd``: ``python -c`` puts the current directory first on sys.path, and from the
    repository root that would shadow the baseline's code.
    """
    env = dict(os.environ)
    if code_dir is not None:
        env["PYTHONPATH"] = str(code_dir)
    return subprocess.run([sys.executable, "-c", script, *args], check=True, env=env, cwd=cwd,
                          capture_output=True, text=True).stdout
