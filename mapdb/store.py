"""The map file's public API, kept where the README has always named it.

The format lives in :mod:`mapdb.mapfile`; this module re-exports what users call (:func:`open_map`,
:func:`write_map`, :class:`MapWriter`, ...).
"""

from __future__ import annotations

from .mapfile.store import (
    DEFAULT_MEMORY_OBJECTS,
    DEFAULT_QUANTUM,
    FORMAT_VERSION,
    MAGIC,
    MapBase,
    MapWriter,
    MemoryMap,
    MetaMap,
    area_codes,
    open_map,
    write_map,
    write_map_from_chunks,
)

__all__ = [
    "DEFAULT_MEMORY_OBJECTS",
    "DEFAULT_QUANTUM",
    "FORMAT_VERSION",
    "MAGIC",
    "MapBase",
    "MapWriter",
    "MemoryMap",
    "MetaMap",
    "area_codes",
    "open_map",
    "write_map",
    "write_map_from_chunks",
]
