"""The map's objects as the matcher searches them: nearest neighbours by label in memory
(:mod:`~mapdb.match.mapobjects.object_index`, on :mod:`~mapdb.match.mapobjects.kd_forest`), or read page by
page from a big map file (:mod:`~mapdb.match.mapobjects.paged_objects`).
"""
