"""Checks shared by the CLI tests: how a command must fail on bad input."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from typing import Any

import pytest


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


def answered_one_by_one(args: Sequence[str], lines: Sequence[bytes], timeout_s: float = 60.0
                        ) -> Iterator[tuple[int, dict]]:
    """Feed ``mapdb ARGS...`` one line at a time, stdin kept open, and yield ``(i, record)`` for each line's
    record as it arrives (so it can only come from streaming); afterwards check that each line had exactly
    one record, that the output ends once the input does, and that the process exits 0.  Consume it whole."""
    proc, answers = start_piped(*args)
    assert proc.stdin is not None and proc.stderr is not None
    try:
        for i, line in enumerate(lines):
            proc.stdin.write(line + b"\n")
            proc.stdin.flush()
            try:
                got = answers.get(timeout=timeout_s)
            except queue.Empty:
                pytest.fail(f"no record for line {i + 1} within {timeout_s} s while the input stays open")
            yield i, json.loads(got)
            assert answers.empty()  # exactly one record per line
        proc.stdin.close()
        assert answers.get(timeout=timeout_s) is None  # end of output once input ends
        assert proc.wait(timeout=timeout_s) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
