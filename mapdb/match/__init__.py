"""Pattern matchers: image objects against map objects.

* :mod:`mapdb.match.fast` - the default, :func:`match_fast`, a driver handing each stage the next:
  :mod:`~mapdb.match.quads` (quad invariants and the map's quad index), :mod:`~mapdb.match.hypotheses`
  (image quads looked up, similarity hypotheses), :mod:`~mapdb.match.verify` (projected objects against
  the map's objects, held by :mod:`~mapdb.match.mapobjects.object_index`, or for a big map file read page by page by
  :mod:`~mapdb.match.mapobjects.paged_objects`; stored areas weighed by :mod:`~mapdb.match.evidence.areas`),
  :mod:`~mapdb.match.decision` (the number of false alarms) and
  :mod:`~mapdb.match.refine` (one candidate per place, the final least-squares fit), with
  :mod:`~mapdb.match.evidence.relief` (the final fit for blobs from masks: cut blobs left out, relief weighed
  radially) and :mod:`~mapdb.match.ambiguity` (rival places looked for on purpose, where the map repeats
  the winner's pattern, and compared under one density).
* :mod:`mapdb.match.paper.algorithm` - the seed paper's Algorithm 1 as published, the reference (its exact pruning
  bound in :mod:`~mapdb.match.paper.bound`).
* :mod:`mapdb.match.geometry` - similarity fits.
* :mod:`mapdb.match.index.stored` - the lost-in-space quad index stored beside a map (``mapdb index``), read
  by :class:`~mapdb.match.index.stored.StoredQuadIndex`; its file layout in :mod:`~mapdb.match.index.layout`,
  its writer in :mod:`~mapdb.match.index.build` (quads from :mod:`~mapdb.match.index.generate`), what a
  lookup reads in :mod:`~mapdb.match.index.lookup`.

Most callers want :func:`mapdb.localize.localize` (or a :class:`mapdb.localize.Localizer`), which parses
an image document, picks the map region and formats the answer.
"""

from __future__ import annotations

from .fast import FastOptions, MatchResult, ObjectIndex, QuadIndex, match_fast
from .paper.algorithm import PaperOptions, PaperResult, match_paper

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
