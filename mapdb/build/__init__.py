"""Building maps: sources read, projected and written into one map file (:mod:`~mapdb.build.pipeline`, the
sources read by :mod:`~mapdb.build.reading`), and
maps merged into one (:mod:`~mapdb.build.merge`).

:func:`build_map` is the entry point; :mod:`~mapdb.build.blockstats` chooses the automatic CRS from objects
read back in blocks.
"""

from __future__ import annotations

from .pipeline import (
    MAX_AUTO_CRS_SPAN_DEG,
    SPOOL_CHOICES,
    SPOOL_INPUT_BYTES,
    build_map,
    utm_crs_for,
)
from .reading import read_one_source

__all__ = [
    "MAX_AUTO_CRS_SPAN_DEG",
    "SPOOL_CHOICES",
    "SPOOL_INPUT_BYTES",
    "build_map",
    "read_one_source",
    "utm_crs_for",
]
