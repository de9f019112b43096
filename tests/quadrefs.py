"""The numpy code of the quads' paths the compiled kernel replaced, kept verbatim as the tests' reference (shared by
the quad tests): ``first_rows`` and ``neighbour_quads(..., with_anchor=True)`` as mapdb/match/quads.py had them at
41de106, before the image's rounds (``_kernel_image_quads.c``) and a tile's distinct quads (``_kernel_map_quads.c``)
left them without a caller in the library."""

from __future__ import annotations

from itertools import combinations

import numpy as np

from mapdb._scipy import quick_tree
from mapdb.match.nearest import nearest_others
from mapdb.match.quads import _PACKABLE

SORT4 = ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2))  # a sorting network of four


def first_rows(quads: np.ndarray, n: int) -> np.ndarray:
    """Index of the first occurrence of each distinct row of ``quads`` (ids below ``n``), in row order."""
    if not len(quads):
        return np.zeros(0, np.int64)
    if n < _PACKABLE:
        key = ((quads[:, 0] * n + quads[:, 1]) * n + quads[:, 2]) * n + quads[:, 3]
        perm = np.argsort(key)
        ordered = key[perm]
        first = np.minimum.reduceat(perm, np.flatnonzero(np.concatenate(([True], ordered[1:] != ordered[:-1]))))
    else:
        _, first = np.unique(quads, axis=0, return_index=True)
    return first


def anchored_quads(xy: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """``neighbour_quads(xy, neighbours, with_anchor=True)``: every anchor's own quads (rows sorted) and each row's
    anchor."""
    n = len(xy)
    k = min(neighbours, n - 1)
    anchor_ids = np.arange(n)
    if k < 3 or not anchor_ids.size:
        return np.zeros((0, 4), dtype=np.int64), np.zeros(0, np.int64)
    nn = nearest_others(quick_tree(xy), xy, anchor_ids, k)
    triples = np.array(list(combinations(range(nn.shape[1]), 3)))
    anchor = np.repeat(anchor_ids, len(triples))
    cols = [anchor, *(nn[:, triples[:, j]].ravel() for j in range(3))]
    for i, j in SORT4:  # each row sorted by five compare-exchanges of columns: faster than sorting rows
        cols[i], cols[j] = np.minimum(cols[i], cols[j]), np.maximum(cols[i], cols[j])
    return np.column_stack(cols), anchor
