"""The seed paper's Algorithm 1 as published (:mod:`~mapdb.match.paper.algorithm`), the reference matcher, and
its exact pruning bound (:mod:`~mapdb.match.paper.bound`) and parameters (:mod:`~mapdb.match.paper.options`).
"""

from __future__ import annotations

from .algorithm import (
    PaperMatch,
    PaperResult,
    match_paper,
)
from .options import PaperOptions

__all__ = [
    "PaperMatch",
    "PaperOptions",
    "PaperResult",
    "match_paper",
]
