"""Small array helpers of the matcher's per-image path that keep its first answer quick.

numpy 2's :func:`numpy.unique` asks ``np.ma.is_masked`` when called without ``return_index``,
``return_inverse`` or ``return_counts``, and the first such call imports ``numpy.ma`` (0.05-0.1 s on the
2-core development machine: a third of a one-image ``mapdb query``'s answer).  The helpers here give the
same results by sorting, without it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["all_distinct", "sorted_unique"]


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """The distinct values of ``values`` (flattened), sorted: :func:`numpy.unique` of an array without NaNs.

    Examples
    --------
    >>> sorted_unique(np.array([3, 1, 3, 2])).tolist()
    [1, 2, 3]
    >>> sorted_unique(np.zeros(0, np.int64)).tolist()
    []
    """
    ordered = np.sort(np.asarray(values).ravel())
    if ordered.size < 2:
        return ordered
    keep = np.empty(ordered.size, bool)
    keep[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=keep[1:])
    return ordered[keep]


def all_distinct(values: np.ndarray) -> bool:
    """Whether no value of ``values`` repeats (``np.unique(values).size == values.size``).

    Examples
    --------
    >>> all_distinct(np.array([2, 0, 1])), all_distinct(np.array([2, 0, 2]))
    (True, False)
    """
    ordered = np.sort(np.asarray(values).ravel())
    return bool(np.all(ordered[1:] != ordered[:-1]))
