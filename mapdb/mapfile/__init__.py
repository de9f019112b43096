"""The map file: its format (codec, pages, header), writer and reader (:mod:`~mapdb.mapfile.store`), and
exports of a map's objects to GIS formats (:mod:`~mapdb.mapfile.export`).

The format is specified in ``docs/format.md``.
"""
