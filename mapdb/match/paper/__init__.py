"""The seed paper's Algorithm 1 as published (:mod:`~mapdb.match.paper.algorithm`), the reference matcher, and
its exact pruning bound (:mod:`~mapdb.match.paper.bound`).
"""

from __future__ import annotations

from .algorithm import (
    PaperMatch,
    PaperOptions,
    PaperResult,
    match_paper,
)

__all__ = [
    "PaperMatch",
    "PaperOptions",
    "PaperResult",
    "match_paper",
]
