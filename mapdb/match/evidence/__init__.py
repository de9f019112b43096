"""Evidence models: how well projected image objects agree with the map's objects.

* :mod:`~mapdb.match.evidence.points` - point residuals, the model every image starts from;
* :mod:`~mapdb.match.evidence.areas` - stored areas against blob areas;
* :mod:`~mapdb.match.evidence.blobs` - blobs from masks: whole and border-cut blobs placed by area;
* :mod:`~mapdb.match.evidence.relief` - the final fit for blobs from masks, relief weighed radially;
* :mod:`~mapdb.match.evidence.terrain` - rays cast onto the map objects' heights (maps with elevation);
* :mod:`~mapdb.match.evidence.image` - :class:`~mapdb.match.evidence.image.ImageEvidence`, an image's models beyond
  point residuals, set up once and handed to the stages.
"""
