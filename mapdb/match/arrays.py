"""Small array helpers of the matcher's per-image path that keep its first answer quick.

numpy 2's :func:`numpy.unique` asks ``np.ma.is_masked`` when called without ``return_index``,
``return_inverse`` or ``return_counts``, and the first such call imports ``numpy.ma`` (0.05-0.1 s on the
2-core development machine: a third of a one-image ``mapdb query``'s answer).  The helpers here give the
same results for the small integer arrays it is asked about (an image's labels, its objects' rows), with a
Python set and fewer numpy calls.
"""

from __future__ import annotations

import numpy as np

__all__ = ["all_distinct", "sorted_unique"]


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """The distinct values of array ``values`` (flattened), sorted: :func:`numpy.unique` of a small integer array
    (an image's labels), in one numpy call and a Python set.

    Examples
    --------
    >>> sorted_unique(np.array([3, 1, 3, 2])).tolist()
    [1, 2, 3]
    >>> sorted_unique(np.zeros(0, np.int64)).tolist()
    []
    """
    return np.array(sorted(set(values.ravel().tolist())), dtype=values.dtype)


def all_distinct(values: np.ndarray) -> bool:
    """Whether no value of ``values`` (a small integer array) repeats: ``np.unique(values).size ==
    values.size``.

    Examples
    --------
    >>> all_distinct(np.array([2, 0, 1])), all_distinct(np.array([2, 0, 2]))
    (True, False)
    """
    listed = values.tolist() if values.ndim == 1 else values.ravel().tolist()
    return len(set(listed)) == len(listed)
