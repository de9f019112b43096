"""Simulation: camera images of a map with their truth.

* :mod:`~mapdb.simulation.simulate` - pinhole images of a map's objects (ideal centroids), and the paper's map;
* :mod:`~mapdb.simulation.poses` - the camera of each image: altitude, field of view, attitude, and its place;
* :mod:`~mapdb.simulation.detector` - the detector's errors: noise, misses, spurious objects, confused labels;
* :mod:`~mapdb.simulation.documents` - an image's query document, its hints and truth, written as JSON Lines;
* :mod:`~mapdb.simulation.outlines` - the outlines a camera would see, read from an OSM extract;
* :mod:`~mapdb.simulation.render` - label masks rendered from those outlines;
* :mod:`~mapdb.simulation.rendered` - images whose objects come from rendered masks.
"""
