"""Pattern matchers: image objects against map objects.

* :mod:`mapdb.match.fast` - the default: quad invariants looked up in an index, every hypothesis verified
  at once, an a contrario decision (number of false alarms), a least-squares fit over all inliers.
* :mod:`mapdb.match.paper` - the seed paper's Algorithm 1 as published, the reference.
* :mod:`mapdb.match.decision` - the false-alarm model; :mod:`mapdb.match.geometry` - similarity fits.

Most callers want :func:`mapdb.localize.localize`, which parses an image document, picks the map
region and formats the answer.
"""

from __future__ import annotations

from .fast import FastOptions, MatchResult, ObjectIndex, QuadIndex, match_fast
from .paper import PaperOptions, PaperResult, match_paper

__all__ = [
    "FastOptions",
    "MatchResult",
    "ObjectIndex",
    "PaperOptions",
    "PaperResult",
    "QuadIndex",
    "match_fast",
    "match_paper",
]
