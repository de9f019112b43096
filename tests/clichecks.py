"""Checks shared by the CLI tests: how a command must fail on bad input."""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
from typing import Any


def assert_one_line_error(result: Any, *needles: str, alone: bool = False) -> str:
    """Exit status 1, exactly one ``mapdb: error:`` line holding every needle, and no traceback; the line.

    The error is the last line on stderr (progress lines may come before it), or with ``alone`` the only one.
    """
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("mapdb: error: ")]
    if alone:
        assert len(lines) == 1 and len(errors) == 1, result.stderr
    else:
        assert len(errors) == 1 and lines[-1] == errors[0], result.stderr
    assert "Traceback" not in result.output
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


def start_piped(*args: str) -> tuple[subprocess.Popen, queue.Queue]:
    """``mapdb ARGS...`` with stdin and stdout on pipes, and a queue that receives each line it writes (None at
    the end): a test can send one line, wait for its answer, and see that it came before the next was sent."""
    proc = subprocess.Popen([sys.executable, "-m", "mapdb_cli", *args],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    lines: queue.Queue = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=read, daemon=True).start()
    return proc, lines
