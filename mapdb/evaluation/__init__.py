"""Evaluation: answers scored against the truth, benchmarks the paper reports, and pictures.

* :mod:`~mapdb.evaluation.evaluate` - ``mapdb evaluate``;
* :mod:`~mapdb.evaluation.paper_bench` - ``mapdb bench paper`` (the paper's Table 1);
* :mod:`~mapdb.evaluation.storage` - ``mapdb bench storage`` (the paper's storage argument);
* :mod:`~mapdb.evaluation.plot` - pictures of evaluations and of single matches (``mapdb show``).
"""
