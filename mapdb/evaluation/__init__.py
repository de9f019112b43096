"""Evaluation: answers scored against the truth, benchmarks the paper reports, and pictures.

* :mod:`~mapdb.evaluation.evaluate` - ``mapdb evaluate``;
* :mod:`~mapdb.evaluation.paper_bench` - ``mapdb bench paper`` (the paper's Table 1);
* :mod:`~mapdb.evaluation.storage` - ``mapdb bench storage`` (the paper's storage argument);
* :mod:`~mapdb.evaluation.evaluation_plot` - the picture of an evaluation (``mapdb evaluate --plot``);
* :mod:`~mapdb.evaluation.match_plot` - the picture of one image's match (``mapdb show``);
* :mod:`~mapdb.evaluation.match_geometry` - where an image lands in the map by a pose (what ``mapdb show`` draws);
* :mod:`~mapdb.evaluation.drawing` - drawing aids the pictures share (pyplot, map axes, saving).
"""
