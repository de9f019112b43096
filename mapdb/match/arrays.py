"""Small array helpers of the matcher's per-image path that keep its first answer quick.

numpy 2's :func:`numpy.unique` asks ``np.ma.is_masked`` when called without ``return_index``,
``return_inverse`` or ``return_counts``, and the first such call imports ``numpy.ma`` (0.05-0.1 s on the
2-core development machine: a third of a one-image ``mapdb query``'s answer).  The helpers here give the
same results for the integer arrays they are asked about (an image's labels, its objects' rows, the blocks and
pages of the stored index a lookup reaches), with a Python set and fewer numpy calls for small ones; and
:func:`contiguous_to`, an array as the compiled kernel reads it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["all_distinct", "contiguous_to", "sorted_unique"]


def contiguous_to(v: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``v`` broadcast to ``shape``, C-contiguous (the compiled kernel reads it row by row): ``v`` itself when it
    already is.

    Examples
    --------
    >>> contiguous_to(np.arange(3.0), (2, 3)).tolist()
    [[0.0, 1.0, 2.0], [0.0, 1.0, 2.0]]
    """
    return np.ascontiguousarray(v if v.shape == shape else np.broadcast_to(v, shape))


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """The distinct values of array ``values`` (flattened), sorted: :func:`numpy.unique` without ``numpy.ma``.

    A small array (an image's labels) goes through a Python set in one numpy call; a larger one (the index
    blocks or pages a lookup reaches) is sorted and its repeats dropped, in a few numpy calls.

    Examples
    --------
    >>> sorted_unique(np.array([3, 1, 3, 2])).tolist()
    [1, 2, 3]
    >>> sorted_unique(np.arange(100) % 7).tolist()
    [0, 1, 2, 3, 4, 5, 6]
    >>> sorted_unique(np.zeros(0, np.int64)).tolist()
    []
    """
    flat = values.ravel()
    if flat.size <= _SMALL:
        return np.array(sorted(set(flat.tolist())), dtype=values.dtype)
    ordered = np.sort(flat)
    keep = np.empty(ordered.size, dtype=bool)
    keep[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=keep[1:])
    return ordered[keep]


# Arrays up to this size go through a Python set (fewer numpy calls); larger ones are sorted in numpy.
_SMALL = 64


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
