"""Hypotheses from quads that hold blobs cut by the image border: rounds after the whole blobs' quads.

At 120 m (60 degrees, 640x480) an image of a town shows a median 12 blobs of which only 4 are whole; in 55
of 160 rendered images (Andorra and Monaco, with heights) 3 or fewer were, and none of those was localized:
the whole blobs alone form no quad, and quads of cut blobs at their centroids (pulled inward by a median 30
px) miss the map's.  These rounds come after every whole-blob round has failed.  Their quads hold as many
whole blobs as the image has, up to three, and at least one cut blob, anchored at whole blobs nearest the
centre.  Each cut blob is looked up at its expected place (:data:`~mapdb.match.evidence.blobs.CUT_SHIFT_PX` outward
along its border's normal) with a wider pixel error, ``CUT_SIGMA_PX``, in the lookup radius; the
similarity is fitted with the cut blobs weighted ``CUT_FIT_WEIGHT``.  Every hypothesis counts as a test,
as in every round.

Measured (the images of :mod:`mapdb.match.evidence.blobs`' figures: 160, 120 m with heights): 47.5 %
localized with the blob ellipses alone, 49.4 % with these rounds too (with quads from each whole blob's
nearest neighbours instead: CUT_SIGMA_PX 8, 12, 20 px: 50.0, 50.0, 49.4 %; fit weight 0.1 or 0.3: 50.0,
48.8 %).  Images with 3 or fewer whole blobs still rarely
reach the decision's threshold: their evidence is the cut blobs only.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations
from typing import TYPE_CHECKING

import numpy as np

from .hypotheses import Hypotheses, round_hypotheses
from .options import FastOptions
from .quads import QuadIndex

if TYPE_CHECKING:
    from .evidence.blobs import BlobErrors

__all__ = ["CUT_FIT_WEIGHT", "CUT_SIGMA_PX", "cut_batches", "cut_round_hypotheses"]

# Pixel error (1 sigma) assumed for a cut blob's shifted centroid in a lookup (the lookup's radius is capped by
# FastOptions.max_invariant_radius, so a wider one finds nothing more), and its weight in the quad's fit.
CUT_SIGMA_PX = 12.0
CUT_FIT_WEIGHT = 0.1
# Cut blobs (nearest a whole anchor, or the whole blobs' centroid) that may join its quads.
CUT_NEIGHBOURS = 5


def cut_batches(z: np.ndarray, whole: np.ndarray, opts: FastOptions) -> list[np.ndarray]:
    """Quads ``(m, 4)`` of sorted object ids holding as many whole blobs as the image has, up to three, and
    cut ones for the rest, in rounds.

    With three whole blobs or fewer, one round: all of them with every choice of the others among the
    ``CUT_NEIGHBOURS`` cut blobs nearest their centroid.  With more, whole anchors nearest the image centre
    first (``opts.anchors_per_batch`` a round, at most ``opts.max_batches`` rounds): each anchor, two of its
    three nearest whole blobs and one of its ``CUT_NEIGHBOURS`` nearest cut ones.
    """
    whole_ids, cut_ids = np.flatnonzero(whole), np.flatnonzero(~whole)
    if z.size < 4 or not cut_ids.size:
        return []
    if whole_ids.size <= 3:
        centre = z[whole_ids].mean() if whole_ids.size else 0j
        near = cut_ids[np.argsort(np.abs(z[cut_ids] - centre), kind="stable")[:CUT_NEIGHBOURS]]
        rows = [sorted([*whole_ids, *extra]) for extra in combinations(near, 4 - whole_ids.size)]
        return [np.array(rows, np.int64).reshape(-1, 4)] if rows else []
    anchors = whole_ids[np.argsort(np.abs(z[whole_ids]), kind="stable")]
    batches: list[np.ndarray] = []
    seen: set[tuple[int, ...]] = set()
    for start in range(0, min(anchors.size, opts.max_batches * opts.anchors_per_batch), opts.anchors_per_batch):
        found: list[tuple[int, ...]] = []
        for anchor in anchors[start : start + opts.anchors_per_batch]:
            others = whole_ids[whole_ids != anchor]
            mates = others[np.argsort(np.abs(z[others] - z[anchor]), kind="stable")[:3]]
            cuts = cut_ids[np.argsort(np.abs(z[cut_ids] - z[anchor]), kind="stable")[:CUT_NEIGHBOURS]]
            for pair in combinations(mates, 2):
                for cut in cuts:
                    quad = tuple(sorted((int(anchor), int(pair[0]), int(pair[1]), int(cut))))
                    if quad not in seen:
                        seen.add(quad)
                        found.append(quad)
        if found:
            batches.append(np.array(found, np.int64))
    return batches


def cut_round_hypotheses(
    z: np.ndarray, img_label: np.ndarray, batch: np.ndarray, quads: Sequence[QuadIndex], opts: FastOptions,
    sigma_px: float, errors: BlobErrors, whole: np.ndarray, prior: tuple[float, float, float] | None,
    scale_range: tuple[float, float] | None,
) -> Hypotheses:
    """:func:`~mapdb.match.hypotheses.round_hypotheses` for quads with cut blobs: each cut blob looked up at its
    expected place (``errors``' shift along its border's normal) with a pixel error ``CUT_SIGMA_PX``, and the
    similarity fitted mostly to the whole blobs.  Returns ``a``, ``b``, image ids ``(H, 4)``, map points."""
    looked = z + errors.shift_px * errors.direction * ~whole
    return round_hypotheses(looked, img_label, batch, quads, opts, np.where(whole[batch], sigma_px, CUT_SIGMA_PX),
                            prior, scale_range, weight=np.where(whole, 1.0, CUT_FIT_WEIGHT))
