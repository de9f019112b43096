"""Evidence models: how well projected image objects agree with the map's objects.

* :mod:`~mapdb.match.evidence.areas` - stored areas against blob areas;
* :mod:`~mapdb.match.evidence.blobs` - blobs from masks: whole and border-cut blobs placed by area;
* :mod:`~mapdb.match.evidence.relief` - the final fit for blobs from masks, relief weighed radially.
"""
