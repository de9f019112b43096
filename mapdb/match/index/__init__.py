"""The lost-in-space quad index stored beside a map (``mapdb index``, ``MAP.qidx``).

* :mod:`~mapdb.match.index.layout` - the file layout (``docs/index_format.md``);
* :mod:`~mapdb.match.index.generate` - the quads of a map's objects;
* :mod:`~mapdb.match.index.build` - the writer;
* :mod:`~mapdb.match.index.lookup` - what one lookup reads;
* :mod:`~mapdb.match.index.binding` - the index checked against its map;
* :mod:`~mapdb.match.index.stored` - :class:`~mapdb.match.index.stored.StoredQuadIndex`, the reader.
"""
