"""Region analysis: where will a map localize an aircraft, how surely, and what does the map cost there?

For every cell of a square grid over a map (its projected CRS), images are simulated from random places
inside the cell with random headings (the camera and detector errors of ``mapdb simulate``) and localized
by the default (fast) matcher, as ``mapdb analyze`` does.  Per cell:

* **visible**: the median number of map objects (of the analysed labels) an image shows, and per label;
* **success**: the fraction of images localized within the false-positive threshold (2 m) of the truth;
* **false**: the fraction accepted farther than that; **error_m**: the median error of the correct ones;
* **ambiguity** (0 unique, 1 indistinguishable): how close the best *wrong* placement of the cell's
  pattern comes to the true one.  Each image is also localized with no prior, a lost-in-space search over
  the whole map; its answer lists the places it found (the accepted one and the runner-up candidates,
  each with its score, ``-log10`` of its number of false alarms).  A place within the matcher's own
  distance between distinct places (a twentieth of the footprint's diagonal, at least 2 m) of the truth
  is the true place; the ambiguity of the image is the best score of the other places over the true
  place's, clipped to [0, 1] (wrong places with no evidence count 0).  An accepted wrong place is 1; an
  image whose search found no evidence for the true place is 1 if a wrong place scored enough to be
  accepted (4), else has no value.  The cell's ambiguity is the median over its images that have one.
  0.5 reads "the best wrong placement explains half as much as the truth"; near 1, the pattern repeats
  elsewhere (a grid of identical houses) and a match there is a coin toss, whether or not today's
  matcher still picks the right one.  With ``prior`` set, success and false are those of the
  prior-aided search, and ambiguity stays that of the lost-in-space search;
* **objects_per_km2** and **bytes_per_km2**: the map's objects in the cell and the bytes of the map file
  they stand for (each page's bytes shared by its objects).

* **images**, **localizable**, **simulated**: the images drawn, those showing four objects or more, and
  those localized; **success_low**, **success_high**: the 95 % interval of the success share a run of every
  localizable image gives.  By default a cell localizes its images only until that interval is as narrow as
  a fixed 16-image run's widest (the sequential rule of :mod:`~mapdb.analysis.measures`); cells from which
  no image can show four objects are skipped before any work (``images`` 0, ``visible`` no value);
* **inferred** (1 or 0): by default a coarse lattice of cells (every second cell each way) is measured first,
  and a cell between it localizes no image where its neighbours and its own views give an interval within
  that width (:mod:`~mapdb.analysis.adaptive`); ``--no-adaptive`` measures every cell.

A sample that shows fewer than four objects is not simulated (the matcher needs a quad of four true
objects: success is 0 there, exactly), and cells from which no image can show four objects are decided
without simulating.  Every cell's images are drawn from ``(seed, cell)`` only, so the measures are the same
bytes whatever the number of workers, the cluster or the partitioning.

Modules: :mod:`~mapdb.analysis.grid` (cells, counts), :mod:`~mapdb.analysis.measures` (one cell's
images), :mod:`~mapdb.analysis.adaptive` (the coarse lattice and what it tells the cells between it),
:mod:`~mapdb.analysis.run` (blocks of cells as tasks, in two rounds when adaptive),
:mod:`~mapdb.analysis.outputs` (GeoTIFF, GeoPackage, summary, the output folder),
:mod:`~mapdb.analysis.pictures` (the PNG), :mod:`~mapdb.analysis.scenarios` (named configurations from TOML).
"""

from __future__ import annotations

from .grid import MAX_CELLS, AnalysisError, Grid
from .measures import MIN_VISIBLE, SampleConfig, ambiguity
from .run import MEASURES, Analysis, analyze, analyze_scenarios

__all__ = [
    "MAX_CELLS",
    "MEASURES",
    "MIN_VISIBLE",
    "Analysis",
    "AnalysisError",
    "Grid",
    "SampleConfig",
    "ambiguity",
    "analyze",
    "analyze_scenarios",
]
