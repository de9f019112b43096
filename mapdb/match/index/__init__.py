"""The lost-in-space quad index stored beside a map (``mapdb index``, ``MAP.qidx``).

* :mod:`~mapdb.match.index.layout` - the file layout (``docs/index_format.md``);
* :mod:`~mapdb.match.index.packed` - the packed codes: quad records, neighbours, directory pages;
* :mod:`~mapdb.match.index.generate` - the quads of a map's objects;
* :mod:`~mapdb.match.index.build` - the writer (:mod:`~mapdb.match.index.sections`: its packed sections);
* :mod:`~mapdb.match.index.lookup` - what one lookup reads;
* :mod:`~mapdb.match.index.directory` - the cell directory and the neighbours as a lookup reads them;
* :mod:`~mapdb.match.index.binding` - the index checked against its map;
* :mod:`~mapdb.match.index.stored` - :class:`~mapdb.match.index.stored.StoredQuadIndex`, the reader.
"""
