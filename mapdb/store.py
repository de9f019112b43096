"""The map file's public API, kept where the README has always named it.

The format lives in :mod:`mapdb.mapfile` (one module a concept: layout, codec, pages, header, writer, reader);
this module re-exports what users call (:func:`open_map`, :func:`write_map`, :class:`MapWriter`, ...).
"""

from __future__ import annotations

from .mapfile.codec import area_codes
from .mapfile.layout import DEFAULT_QUANTUM, FORMAT_VERSION, MAGIC
from .mapfile.queries import MapBase, MemoryMap
from .mapfile.reader import MetaMap, open_map
from .mapfile.writer import DEFAULT_MEMORY_OBJECTS, MapWriter, write_map, write_map_from_chunks

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
