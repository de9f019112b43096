"""The seed paper's Algorithm 1 as published (:mod:`~mapdb.match.paper.algorithm`), the reference matcher, and
its exact pruning bound (:mod:`~mapdb.match.paper.bound`) and parameters (:mod:`~mapdb.match.paper.options`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .options import PaperOptions

if TYPE_CHECKING:
    from .algorithm import PaperMatch, PaperResult, match_paper

__all__ = [
    "PaperMatch",
    "PaperOptions",
    "PaperResult",
    "match_paper",
]


def __getattr__(name: str) -> Any:
    """The algorithm's names, imported on first use: the fast matcher's callers take only :class:`PaperOptions`
    from here."""
    if name in ("PaperMatch", "PaperResult", "match_paper"):
        from . import algorithm

        return getattr(algorithm, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
