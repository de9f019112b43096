"""Simulation: camera images of a map with their truth.

* :mod:`~mapdb.simulation.simulate` - pinhole images of a map's objects (ideal centroids);
* :mod:`~mapdb.simulation.outlines` - the outlines a camera would see, read from an OSM extract;
* :mod:`~mapdb.simulation.render` - label masks rendered from those outlines;
* :mod:`~mapdb.simulation.rendered` - images whose objects come from rendered masks.
"""
