"""Progress reports: what a long run tells the user while it works (on stderr, never with the results).

:class:`Progress` is how long library functions report to the user (the CLI draws a bar on a terminal, plain
lines otherwise); :class:`LineProgress` writes plain lines; :func:`as_progress` turns a plain message callback
into a :class:`Progress`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

__all__ = ["LineProgress", "Progress", "ProgressLike", "as_progress"]


@runtime_checkable
class Progress(Protocol):
    """What a long library function reports its progress to.

    Calling it with a message reports a stage or an event (``"reading monaco.osm.pbf ..."``); ``start``
    begins a count of ``total`` steps (None when not known in advance) named ``label``, ``advance`` counts
    steps done and ``done`` ends the count (a new ``start`` ends the previous count too).  The library
    never imports click: the CLI implements this with ``click.progressbar`` on a terminal and with
    :class:`LineProgress` elsewhere.  Functions take any :data:`ProgressLike` and call
    :func:`as_progress` on it.
    """

    def __call__(self, message: str) -> None: ...

    def start(self, total: int | None, label: str) -> None: ...

    def advance(self, n: int = 1) -> None: ...

    def done(self) -> None: ...


#: What a ``progress`` argument may be: a :class:`Progress`, a plain message callback, or None (silence).
ProgressLike = Progress | Callable[[str], None] | None

# A count without a known total prints at most one line per this many seconds.
_LINE_INTERVAL_S = 1.0
# A count with a total prints a line at each of this many equal parts of it.
_LINE_PARTS = 10


class LineProgress:
    """A :class:`Progress` written as plain lines through a message callback: for logs, pipes, files.

    A count prints ``"LABEL: I/TOTAL"`` at each tenth of its total (at every step of a count of ten or
    fewer), and with no total known ``"LABEL: I"`` at most once a second; ``done`` prints the final count
    unless it was the last line.  Nothing is printed when a count starts: a run that fails at once says
    only what went wrong.

    Parameters
    ----------
    say : callable or None
        Receives each line; None discards them.

    Examples
    --------
    >>> lines = []
    >>> p = LineProgress(lines.append)
    >>> p("reading a.osm ...")
    >>> p.start(20, "fast"); p.advance(9); p.advance(); p.advance(10); p.done()
    >>> lines
    ['reading a.osm ...', 'fast: 9/20', 'fast: 10/20', 'fast: 20/20']
    """

    def __init__(self, say: Callable[[str], None] | None) -> None:
        self.say = say
        self.label = ""
        self.total: int | None = None
        self.pos = 0
        self._shown = -1  # the count last printed
        self._shown_at = 0.0
        self._active = False

    def __call__(self, message: str) -> None:
        if self.say is not None:
            self.say(message)

    def _show(self) -> None:
        self._shown, self._shown_at = self.pos, time.monotonic()
        self(f"{self.label}: {self.pos}" + ("" if self.total is None else f"/{self.total}"))

    def start(self, total: int | None, label: str) -> None:
        self.label, self.total, self.pos, self._active = label, total, 0, True
        self._shown, self._shown_at = 0, time.monotonic()

    def advance(self, n: int = 1) -> None:
        before, self.pos = self.pos, self.pos + n
        if self.total is None:
            due = time.monotonic() - self._shown_at >= _LINE_INTERVAL_S
        else:
            part = max(1, math.ceil(self.total / _LINE_PARTS))
            due = self.pos // part > before // part or self.pos >= self.total > before
        if due:
            self._show()

    def done(self) -> None:
        if self._active and self._shown != self.pos:
            self._show()
        self._active = False


def as_progress(progress: ProgressLike) -> Progress:
    """``progress`` as a :class:`Progress`: a plain callback becomes a :class:`LineProgress`, None a silent one.

    Examples
    --------
    >>> p = as_progress(print)
    >>> p.start(2, "images"); p.advance(); p.advance(); p.done()
    images: 1/2
    images: 2/2
    >>> as_progress(None).start(5, "nothing printed")
    """
    if isinstance(progress, Progress):
        return progress
    return LineProgress(progress)
