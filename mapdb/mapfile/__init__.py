"""The map file (format specified in ``docs/format.md``), one module a concept:

* :mod:`~mapdb.mapfile.layout`: the file's fixed fields (magic, version, prefix, directory record) and the
  format's bounds;
* :mod:`~mapdb.mapfile.codec`: area codes and the bit-level Rice code;
* :mod:`~mapdb.mapfile.pages`: cutting objects into pages, encoding a page, decoding and checking a batch;
* :mod:`~mapdb.mapfile.spill`: the writer's temporary files past its memory bound (external sort and merge);
* :mod:`~mapdb.mapfile.header`: the header written, parsed and checked, and the page directory checked;
* :mod:`~mapdb.mapfile.writer`: :class:`~mapdb.mapfile.writer.MapWriter`, ``write_map``, ``write_map_from_chunks``;
* :mod:`~mapdb.mapfile.queries`: the queries every map answers (``MapBase``) and ``MemoryMap``;
* :mod:`~mapdb.mapfile.reader`: ``open_map`` and ``MetaMap``, a map file read page by page as queries need;
* :mod:`~mapdb.mapfile.export`: a map's objects exported to GIS formats.

Each module imports only those above it in this list (no cycles); :mod:`mapdb.store` re-exports the public API.
"""
