"""The map's objects as the matcher searches them: nearest neighbours by label in memory
(:mod:`~mapdb.match.mapobjects.object_index`, on the compiled kernel's KD-trees per label:
:mod:`~mapdb.match.mapobjects.label_trees`, several over a growing set in :mod:`~mapdb.match.mapobjects.kd_forest`),
or read page by page from a big map file (:mod:`~mapdb.match.mapobjects.paged_objects`).
"""
