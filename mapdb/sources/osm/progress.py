"""Progress of the pass over an OSM file: bytes read, time left, and the objects seen."""

from __future__ import annotations

import math
import os
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from .index import _release_mapped

__all__ = ["Progress"]

# How often (seconds) a long read reports progress, and how many objects pass between clock checks.
_PROGRESS_SECONDS = 2.0
_PROGRESS_STRIDE = 4096
_ETA_WINDOW_SECONDS = 60.0

Progress = Callable[[str], None]


class _ByteProgress:
    """Progress of the pass by bytes of input read, with the time left; releases a file index's pages.

    The bytes read are the position of libosmium's descriptor of the input (``/proc/self/fdinfo``, Linux);
    elsewhere only the objects are counted.  A file node index is a shared mapping: its pages stay in the
    page cache, which the kernel reclaims under pressure, and are released from the process (``madvise``)
    at each report so that its resident memory does not grow with the input.
    """

    def __init__(self, path: Path, source: str, report: Progress, index_file: str | None) -> None:
        self.path, self.report = path, report
        self.size = max(1, os.path.getsize(source))
        self.identity = _file_identity(source)
        self.last = time.monotonic()
        self.index_file = index_file
        # (time, bytes read) of the last minute or so: the rate of the recent past gives the time left,
        # since nodes (most of a PBF's bytes) go much faster than ways and areas.
        self.history: deque[tuple[float, int]] = deque()

    def tick(self, seen: int) -> None:
        now = time.monotonic()
        if now - self.last < _PROGRESS_SECONDS:
            return
        self.last = now
        self.release()
        done = _bytes_read(self.identity)
        if done is None:
            self.report(f"{self.path}: {seen:,} tagged objects read")
            return
        self.history.append((now, done))
        while len(self.history) > 2 and now - self.history[1][0] >= _ETA_WINDOW_SECONDS:
            self.history.popleft()
        then, before = self.history[0]
        rate = (done - before) / (now - then) if now > then else 0.0
        left = (self.size - done) / rate if rate > 0 else float("nan")
        self.report(f"{self.path}: {min(1.0, done / self.size):.0%} of {self.size / 2**20:,.1f} MiB read, "
                    f"{seen:,} tagged objects, about {_duration(left)} left")

    def release(self) -> None:
        if self.index_file is not None:
            _release_mapped(self.index_file)


def _duration(seconds: float) -> str:
    """``"2 h 05 min"``, ``"3 min 20 s"``, ``"40 s"``; ``"?"`` when not known.

    Examples
    --------
    >>> _duration(40.2), _duration(200), _duration(7500), _duration(float("nan"))
    ('40 s', '3 min 20 s', '2 h 05 min', '?')
    """
    if not math.isfinite(seconds):
        return "?"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def _file_identity(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _bytes_read(identity: tuple[int, int] | None) -> int | None:
    """How far this process has read the file of this (device, inode), or None if that cannot be told."""
    if identity is None:
        return None
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return None
    positions = []
    for fd in fds:
        try:
            st = os.stat(f"/proc/self/fd/{fd}")
            if (st.st_dev, st.st_ino) != identity:
                continue
            with open(f"/proc/self/fdinfo/{fd}") as f:
                positions += [int(line.split()[1]) for line in f if line.startswith("pos:")]
        except (OSError, ValueError, IndexError):
            continue
    return max(positions) if positions else None
