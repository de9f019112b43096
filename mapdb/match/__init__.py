"""Pattern matchers: image objects against map objects.

* :mod:`mapdb.match.fast` - the default, :func:`match_fast`, a pipeline whose top function hands each stage
  the previous one's result, in this order:

  1. :mod:`~mapdb.match.hypotheses` - image quads (:mod:`~mapdb.match.cut_quads` for quads holding blobs cut
     by the border) looked up in the map's quad index (:mod:`~mapdb.match.quads`, or the stored one in
     :mod:`~mapdb.match.index`), each hit a similarity: a round's ``Hypotheses``;
  2. :mod:`~mapdb.match.screen` - each round's hypotheses screened, verified (:mod:`~mapdb.match.verify`
     against the map's objects held by :mod:`~mapdb.match.mapobjects`), each place decided and refined:
     candidates;
  3. :mod:`~mapdb.match.decide` - the best candidate certain enough (the false-alarm model of
     :mod:`~mapdb.match.nfa`), or the rejection;
  4. :mod:`~mapdb.match.rivals` - other places where the map repeats the winner's pattern, compared under one
     density: ambiguous or not;
  5. :mod:`~mapdb.match.refine` - the final association and fit (:func:`~mapdb.match.refine.polish`), and
     the answer unless its error is too large.

  Every stage reads :class:`~mapdb.match.options.FastOptions`; the evidence models (:mod:`mapdb.match.evidence`:
  point residuals, areas, cut blobs, relief) reach the stages through one
  :class:`~mapdb.match.evidence.image.ImageEvidence` an image.
* :mod:`mapdb.match.paper.algorithm` - the seed paper's Algorithm 1 as published, the reference (its exact pruning
  bound in :mod:`~mapdb.match.paper.bound`, its parameters in :mod:`~mapdb.match.paper.options`).
* :mod:`mapdb.match.geometry` - similarity fits.
* :mod:`mapdb.match.index.stored` - the lost-in-space quad index stored beside a map (``mapdb index``), read
  by :class:`~mapdb.match.index.stored.StoredQuadIndex`; its file layout in :mod:`~mapdb.match.index.layout`,
  its writer in :mod:`~mapdb.match.index.build` (quads from :mod:`~mapdb.match.index.generate`), what a
  lookup reads in :mod:`~mapdb.match.index.lookup`.

Most callers want :func:`mapdb.localize.localize` (or a :class:`mapdb.localize.Localizer`), which parses
an image document, picks the map region and formats the answer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .fast import MatchResult, ObjectIndex, QuadIndex, match_fast
from .options import FastOptions
from .paper.options import PaperOptions

if TYPE_CHECKING:
    from .paper.algorithm import PaperResult, match_paper

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


def __getattr__(name: str) -> Any:
    """The paper's matcher, imported on first use: a fast-method process (a one-image ``mapdb query``) never
    loads it."""
    if name in ("PaperResult", "match_paper"):
        from .paper import algorithm

        return getattr(algorithm, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
