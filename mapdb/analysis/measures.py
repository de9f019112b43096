"""What one cell's simulated images measure: the work a task does, on any worker.

:func:`measure_cells` takes a map's *path*, the sampling configuration and a list of cells (absolute
indices), and returns their measures.  A worker process opens each map once and keeps it with one
:class:`~mapdb.localize.Localizer` (its whole-map indexes loaded once) for every task it is given.

Sample ``s`` of the cell ``(i, j)`` draws everything from ``numpy.random.default_rng([seed, i', j', s])``
(``i'``, ``j'``: the indices made non-negative), in a fixed order: its position (uniform in the cell),
heading (uniform), roll and pitch (normal), then the detector's errors and the prior's offset.  Nothing
else reaches it, and the localizer's answers depend on nothing but the image (the whole map's quad index
serves every query, with or without a prior): a cell's measures are the same bytes whichever worker, task
or run computes them.  The draws of a task's cells are made together (:mod:`mapdb.analysis.draws`: the seeds
hashed on arrays, a cell's views in one projection), the same numbers as one image at a time.

An image that shows fewer than :data:`MIN_VISIBLE` objects of the analysed labels is counted as not
localized without being simulated: the fast matcher places an image from a quad of four image objects
matched to four map objects, so with fewer than four true objects in view it cannot find the true place.

**The sequential rule** (``SampleConfig.sequential``, the default).  A cell's success share, as a fixed
run reports it, is ``k / N``: ``k`` of its ``N = samples`` images localized within the threshold.  Which of the
``N`` images *can* be localized is known cheaply, before any is simulated: the ``L`` that show at least
:data:`MIN_VISIBLE` objects (the others fail by rule).  So every pose and view is drawn, as in a fixed run
(``visible`` is the fixed run's), and only the localizable images are run, in sample order, until the share
is known to the width the outputs report: after ``m`` of the ``L`` with ``k`` successes and ``f`` false
fixes, the cell stops once ``m >= MIN_RUN`` (2) and the 95 % Wilson score interval (:func:`wilson_interval`,
``z = 1.96``) of ``k`` of ``m``, and of ``f`` of ``m``, each scaled by ``L / N``, is at most
``SampleConfig.stop_width`` wide; or once all ``L`` ran.  It reports ``success = (L / N) (k / m)`` (likewise
``false_fixes``) and the interval (``success_low``, ``success_high``; both the share itself when all ran):
an interval for the share the fixed run of the same ``N`` images would report.  ``stop_width`` is, unless
given, the widest interval a fixed run's share has around the cell's success probability (half of ``N``
successes): 0.440 for 16 images; the sequential figure is thus never further from the fixed one than the fixed
one is (at worst) from the truth.  For 16 images: a cell whose 16 images can all be localized and all succeed
stops after 5 (interval 0.566 to 1 of the fixed share); one with 8 localizable after 2, whatever they give
(at most 0.405 wide); a cell with 12 localizable, all succeeding, after 3.  Its measures are
the fixed run's when it runs every localizable image.  The rule treats the localizable images as
exchangeable and ignores that the stop looks at the data (the usual sequential caveat: coverage a little under
the nominal 95 %); error and ambiguity are medians over fewer images; a rare event, a false fix in one image
in twenty, is more likely to go unseen in 2 images than in 16.
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics
import time
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from ..answers import Answer
from ..camera import Camera, Pose
from ..detections.images import ImageObjects
from ..evaluation.evaluate import DEFAULT_FP_THRESHOLD_M
from .draws import Poses, cell_image, cell_poses, cell_views, detector_of, near_cells, positioned

__all__ = ["DECISION_LEVEL", "HINT_COLUMNS", "MIN_VISIBLE", "Z95", "CellMeasures", "SampleConfig", "ambiguity",
           "column_medians", "inferred_interval", "measure_cells", "open_for_cells", "wilson_interval", "wilson_width"]

# The fewest true objects in view from which the fast matcher can find the true place (one quad).
MIN_VISIBLE = 4
# An image's footprint is widened by this many roll/pitch standard deviations when objects are gathered.
_TILT_SIGMAS = 5.0
# Maps (with their localizers) a worker keeps open.
_KEEP_MAPS = 2
# The fewest localizable images the sequential rule runs in a cell before it may stop (a share from one image is
# all or nothing).
MIN_RUN = 2
# The success share at which a cell counts as "works here" (the summary's, outputs.SUCCESS_LEVEL; the
# adaptive rule runs a cell whose inferred interval holds it).
DECISION_LEVEL = 0.95
# What the coarse lattice tells a worker of a cell between it (mapdb.analysis.adaptive.hints), in this order.
HINT_COLUMNS = ("run", "p_low", "p_high", "p_mean", "error_m", "ambiguity")
# The normal quantile of a two-sided 95 % interval (the sequential rule's and the outputs' widths).
Z95 = 1.959963984540054
# Cells whose objects are read from the map together (as run.BLOCK_CELLS): a task's cells are one such block,
# but the warm-up's are spread over the map, and one box around them all would read every page.
_READ_BLOCK = 8


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a share of ``k`` successes in ``n`` trials ((0, 1) when ``n`` is 0).

    Examples
    --------
    >>> [round(v, 3) for v in wilson_interval(0, 5)]
    [0.0, 0.434]
    >>> [round(v, 3) for v in wilson_interval(8, 16)]
    [0.28, 0.72]
    """
    if n <= 0:
        return (0.0, 1.0)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (max(0.0, centre - half), min(1.0, centre + half))


def wilson_width(k: int, n: int, z: float = Z95) -> float:
    """Width of :func:`wilson_interval` (1 when ``n`` is 0).

    Examples
    --------
    >>> round(wilson_width(8, 16), 3), round(wilson_width(0, 16), 3)
    (0.44, 0.194)
    """
    low, high = wilson_interval(k, n, z)
    return high - low


@dataclass(frozen=True)
class SampleConfig:
    """How each cell is sampled: the camera, the detector's errors, the labels, the prior.

    ``labels`` None means all the map's labels; ``prior`` a radius (m) of a position prior given with each
    image (success is then that of the prior-aided search; ambiguity stays that of the search without
    one).  ``fp_threshold`` is the error (m) above which an accepted answer is false.  ``sequential``: a
    cell stops drawing images once its shares are known to ``stop_width`` (see :mod:`mapdb.analysis.measures`);
    ``width`` overrides that width; ``samples`` is then the most images a cell draws.  ``adaptive`` (with
    ``sequential`` only): a coarse lattice of cells first, the cells between it only where it disagrees, the
    others inferred (see :mod:`mapdb.analysis.adaptive`).
    """

    altitude: float = 150.0
    fov_deg: float = 45.0
    size: tuple[int, int] = (640, 480)
    attitude_std: float = 0.0
    pixel_std: float = 0.0
    miss_rate: float = 0.0
    spurious_rate: float = 0.0
    label_noise: float = 0.0
    labels: tuple[str, ...] | None = None
    samples: int = 16
    prior: float | None = None
    seed: int = 0
    fp_threshold: float = DEFAULT_FP_THRESHOLD_M
    sequential: bool = True
    width: float | None = None
    adaptive: bool = False  # opt-in: an inferred cell's false fixes are not seen (mapdb.analysis.adaptive)

    @property
    def stop_width(self) -> float:
        """The width of a cell's 95 % success interval at which the sequential rule stops it: ``width``, or
        the widest interval of a fixed run of ``samples`` images (half of them successes)."""
        return float(self.width) if self.width is not None else wilson_width(self.samples // 2, self.samples)

    @property
    def camera(self) -> Camera:
        return Camera(int(self.size[0]), int(self.size[1]), float(self.fov_deg))

    @property
    def reach_m(self) -> float:
        """How far from the camera an object in its image can be (the level footprint's half-diagonal,
        widened for the tilts the attitude error allows)."""
        w, h = self.camera.footprint_m(self.altitude)
        tilt = min(_TILT_SIGMAS * self.attitude_std, 80.0)
        return 1.01 * math.hypot(w, h) / 2.0 + 2.0 * self.altitude * math.tan(math.radians(tilt)) + 1.0

    @property
    def separation_m(self) -> float:
        """Places at least this far from the truth are *wrong* places: the matcher's own distance between
        distinct places (a twentieth of the footprint's diagonal), and never below ``fp_threshold``."""
        from ..match.refine import PLACE_FRACTION

        w, h = self.camera.footprint_m(self.altitude)
        return max(PLACE_FRACTION * math.hypot(w, h), self.fp_threshold)


@dataclass
class CellMeasures:
    """Measures of a list of cells (one row each); NaN where a measure has no value."""

    visible: np.ndarray        # median objects (analysed labels) in view
    per_label: np.ndarray      # (cells, labels): median objects of each analysed label in view
    success: np.ndarray        # fraction localized within fp_threshold of the truth
    false: np.ndarray          # fraction accepted farther than fp_threshold
    error: np.ndarray          # median error of the correct answers (m)
    ambiguity: np.ndarray      # median over the samples of the ambiguity (0 unique .. 1 indistinguishable)
    simulated: np.ndarray      # samples simulated and localized (the others showed < MIN_VISIBLE objects)
    images: np.ndarray         # samples drawn (their poses and the objects they show)
    localizable: np.ndarray    # of them, those showing at least MIN_VISIBLE objects (``simulated`` of them ran)
    low: np.ndarray            # 95 % interval of the success share a run of every localizable image reports
    high: np.ndarray
    inferred: np.ndarray       # 1: no image localized, the figures inferred (mapdb.analysis.adaptive)
    seconds: float = 0.0       # time spent measuring (set-up excluded)
    cpu_s: float = 0.0         # CPU of the task's thread, map opening included (mapdb.analysis.cputime)
    label_names: tuple[str, ...] = field(default=())

    @classmethod
    def empty(cls, n: int, label_names: tuple[str, ...]) -> CellMeasures:
        """Measures of ``n`` cells where nothing is in view: no objects, no success, no error or ambiguity."""
        nothing = np.full(n, np.nan, np.float32)
        return cls(np.zeros(n, np.float32), np.zeros((n, len(label_names)), np.float32), np.zeros(n, np.float32),
                   np.zeros(n, np.float32), nothing, nothing.copy(), np.zeros(n, np.int32),
                   np.zeros(n, np.int32), np.zeros(n, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32),
                   np.zeros(n, np.int8), label_names=label_names)


def ambiguity(answer: Answer, x: float, y: float, separation: float, min_score: float = 4.0) -> float:
    """How close the best wrong place comes to the true one in a search's answer: 0 unique, 1 indistinguishable.

    The places are the answer's own (if accepted) and its runner-up candidates, each with its score
    (``-log10`` of its number of false alarms).  A place within ``separation`` of the truth ``(x, y)`` is
    the true one, any other a wrong one.  The value is the best wrong place's score over the true place's,
    clipped to [0, 1] (a wrong place with no evidence, a score <= 0, counts 0).  An accepted wrong place is
    1; when the search found no evidence for the true place, 1 if a wrong place scores ``min_score`` (what
    acceptance needs), else NaN (nothing to compare).

    Examples
    --------
    >>> from mapdb.answers import Candidate
    >>> ok = Answer(id=None, status="ok", x=0.0, y=0.0, score=20.0,
    ...             candidates=[Candidate(40.0, 0.0, 6, 15.0, 0.5)])
    >>> ambiguity(ok, 0.5, 0.0, 5.0)
    0.75
    >>> ambiguity(ok, 40.0, 0.0, 5.0)  # the accepted place is the wrong one
    1.0
    """
    places = [(answer.x, answer.y, answer.score)] if answer.ok else []
    places += [(c.x, c.y, c.score) for c in answer.candidates]
    true_score = wrong_score = -math.inf
    for px, py, score in places:
        if px is None or py is None or score is None:
            continue
        if math.hypot(px - x, py - y) <= separation:
            true_score = max(true_score, score)
        else:
            wrong_score = max(wrong_score, score)
    if answer.ok and answer.x is not None and answer.y is not None and \
            math.hypot(answer.x - x, answer.y - y) > separation:
        return 1.0
    if true_score <= 0.0:
        return 1.0 if wrong_score >= min_score else math.nan
    return float(min(max(wrong_score, 0.0) / true_score, 1.0))


# ------------------------------------------------------------------------------------------ a worker's maps

_OPEN: dict[tuple[str, int, int], tuple[Any, Any]] = {}


def _opened(map_path: str) -> tuple[Any, Any]:
    """This process's open map and localizer for a path (opened once; reopened if the file changed)."""
    from ..localize.localizer import Localizer
    from ..mapfile.reader import open_map

    st = os.stat(map_path)
    key = (os.path.realpath(map_path), st.st_mtime_ns, st.st_size)
    if key not in _OPEN:
        while len(_OPEN) >= _KEEP_MAPS:
            _OPEN.pop(next(iter(_OPEN)))[0].close()
        m = open_map(map_path)
        localizer = Localizer(m)
        # With the whole map's quad index loaded, every query (with a prior too) looks hypotheses up in it:
        # an answer then never depends on which images a worker answered before.  The images are points (no
        # building areas): the view of a map with blocks folded in is never searched, and not built.
        localizer.whole_map_indexes(masks=False)
        _OPEN[key] = (m, localizer)
    return _OPEN[key]


def open_for_cells(map_path: str) -> None:
    """Open now, in this process, the map and localizer the cells' tasks use (as their first call would)."""
    _opened(map_path)


# ------------------------------------------------------------------------------------------ the cells


@dataclass
class _Context:
    """What every sample of a task needs (the configuration's derived values computed once)."""

    config: SampleConfig
    cell_m: float
    localizer: Any
    objects: Any               # the analysed labels' objects around the task's cells
    tree: Any                  # their KD-tree
    codes: np.ndarray          # label codes (in the map) of the analysed labels
    label_counts: dict[str, int]
    camera: Camera = field(default_factory=Camera)
    reach: float = 0.0
    separation: float = 0.0
    stop_width: float = 0.0
    detector: Any = None       # the images' detector (None: no analysed label has objects in the map)
    generator: Any = None      # a generator each localized image's draws are set into, in turn (one a task)

    def __post_init__(self) -> None:
        self.camera, self.reach, self.separation, self.stop_width, self.detector = _derived(
            self.config, tuple(self.label_counts.items()))
        self.generator = np.random.Generator(np.random.PCG64(0))


@lru_cache(maxsize=8)
def _derived(cfg: SampleConfig, label_counts: tuple[tuple[str, int], ...]) -> tuple[Camera, float, float, float, Any]:
    """The configuration's derived values a task's cells share: its camera, reach, separation, stop width and
    detector (None when no analysed label has objects); once a configuration, not once a block of cells."""
    detector = detector_of(dict(label_counts), cfg.pixel_std, cfg.miss_rate, cfg.spurious_rate,
                           cfg.label_noise) if label_counts else None
    return cfg.camera, cfg.reach_m, cfg.separation_m, cfg.stop_width, detector


def measure_cells(map_path: str, config: SampleConfig, cell_m: float, cells: np.ndarray,
                  hints: np.ndarray | None = None) -> CellMeasures:
    """The measures of cells given by absolute indices (rows ``(i, j)`` of ``cells``).

    The objects images can show are read block by block (cells of one ``_READ_BLOCK`` square, with an image's
    reach around them): only the map pages around the cells, whatever their spread.  ``hints`` (one row a
    cell, :data:`HINT_COLUMNS`, from :func:`mapdb.analysis.adaptive.hints`): cells between the coarse lattice,
    each inferred from its own draws and its hint where the rule of :mod:`mapdb.analysis.adaptive` allows.
    """
    cpu = time.thread_time()
    m, localizer = _opened(map_path)
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    # All the map's labels that have objects, in the map's order (as the run's bands are).
    names = config.labels or tuple(m.label_counts)
    codes = np.array([m.labels.index(n) for n in names], np.int64)
    n = len(cells)
    out = CellMeasures.empty(n, names)
    if not n:
        return out
    start = time.perf_counter()
    from ..simulation.simulate import check_simulate_args

    check_simulate_args(1, 0.0, 0.0, config.pixel_std, config.miss_rate, config.spurious_rate, config.label_noise,
                        0, 1)
    counts = m.label_counts
    label_counts = {k: counts[k] for k in names if counts.get(k)}
    # Every image's pose of every cell of the task, drawn at once.
    poses = cell_poses(config.seed, cells, config.samples, cell_m, config.altitude, config.attitude_std)
    # Labels None: every label with objects is analysed, and the map's own are all of them (no filter to run).
    read = None if config.labels is None else names
    for rows in _read_groups(cells):
        ctx = _context(m, localizer, config, cell_m, cells[rows], read, codes, label_counts)
        centres = (cells[rows] + 0.5) * cell_m
        for row, near in zip(rows.tolist(), near_cells(ctx.tree, centres, _cell_radius(cell_m), ctx.reach),
                             strict=True):
            hint = None if hints is None else hints[row]
            _measure_cell(ctx, int(cells[row, 0]), int(cells[row, 1]), near, poses[row], out, row, hint)
    out.seconds = time.perf_counter() - start
    out.cpu_s = time.thread_time() - cpu
    return out


def _read_groups(cells: np.ndarray) -> list[np.ndarray]:
    """The rows of the cells whose objects are read from the map together: all of them when they fit in a
    ``_READ_BLOCK`` square (a task's block), else those of each square of the absolute grid (the warm-up's cells,
    spread over the map).  Which objects a cell's images show, and in which order, does not depend on the box
    read around it (a box's objects are in the map's order, a larger box's the same ones with others between)."""
    if (cells.max(axis=0) - cells.min(axis=0) < _READ_BLOCK).all():
        return [np.arange(len(cells))]
    blocks = cells // _READ_BLOCK
    return [np.flatnonzero((blocks == block).all(axis=1)) for block in np.unique(blocks, axis=0)]


def _cell_radius(cell_m: float) -> float:
    """How far from its cell's centre a camera can be (half the cell's diagonal)."""
    half = 0.5 * cell_m
    return math.hypot(half, half)


def _context(m: Any, localizer: Any, config: SampleConfig, cell_m: float, cells: np.ndarray,
             names: tuple[str, ...] | None, codes: np.ndarray, label_counts: dict[str, int]) -> _Context:
    """The analysed objects an image from these cells can show (their box and an image's reach around it; ``names``
    None: the map's objects of every label)."""
    from .._scipy import cKDTree

    reach = config.reach_m
    lo, hi = cells.min(axis=0) * cell_m - reach, (cells.max(axis=0) + 1) * cell_m + reach
    objects = m.query_bbox(lo[0], lo[1], hi[0], hi[1], labels=None if names is None else list(names))
    if not all(type(name) is str for name in objects.labels):  # an image's labels are Python strings (cell_image)
        objects = dataclasses.replace(objects, labels=tuple(str(name) for name in objects.labels))
    tree = cKDTree(np.column_stack([objects.x, objects.y])) if len(objects) else None
    return _Context(config, cell_m, localizer, objects, tree, codes, label_counts)


def _known(successes: int, false: int, run: int, ready: int, drawn: int, width: float) -> bool:
    """Whether the sequential rule stops a cell after ``run`` of its ``ready`` localizable images (of ``drawn``):
    all of them run, or at least :data:`MIN_RUN` and both shares' intervals at most ``width`` wide."""
    if run >= ready:
        return True
    if run < MIN_RUN:
        return False
    scale = ready / drawn
    return scale * wilson_width(successes, run) <= width and scale * wilson_width(false, run) <= width


def _measure_cell(ctx: _Context, i: int, j: int, near: np.ndarray, poses: Poses, out: CellMeasures, row: int,
                  hint: np.ndarray | None) -> None:
    """Sample one cell (every localizable image, or until the sequential rule stops it, or none where its
    ``hint`` lets it be inferred) and write its measures into row ``row`` of ``out``.  ``near``: the objects
    within reach of the cell (:func:`~mapdb.analysis.draws.near_cells`)."""
    cfg = ctx.config
    views = cell_views(ctx.objects, ctx.tree, near, poses, ctx.camera, ctx.reach)
    # Objects of each analysed label each image shows (a label's column; the labels of the objects near).
    labels = ctx.objects.label[views.near]
    visible = views.seen @ (labels[:, None] == ctx.codes[None, :]).astype(np.int64)
    ready = np.flatnonzero(views.seen.sum(axis=1) >= MIN_VISIBLE).tolist()
    middle = column_medians(np.concatenate([visible.sum(axis=1, keepdims=True), visible], axis=1))
    out.visible[row] = middle[0]
    out.per_label[row] = middle[1:]
    out.images[row] = cfg.samples
    out.localizable[row] = len(ready)
    if hint is not None and _inferred(hint, len(ready), cfg, out, row):
        return
    correct: list[float] = []
    amb: list[float] = []
    false = run = 0
    for s in ready:
        if cfg.sequential and _known(len(correct), false, run, len(ready), cfg.samples, ctx.stop_width):
            break
        run += 1
        pose = poses.pose(s)
        generator = positioned(poses, s, cfg.seed, i, j, ctx.generator)
        error, lost = _localize(ctx, views.shown(s), pose, generator, f"{i},{j},{s}")
        if error is not None and error <= cfg.fp_threshold:
            correct.append(error)
        elif error is not None:
            false += 1
        amb.append(ambiguity(lost, pose.x, pose.y, ctx.separation))
    # The shares the fixed run would report: the localizable share (known) times the share of those that ran
    # (integers divided once: the fixed run's k / samples exactly when every localizable image ran).
    n, k = cfg.samples * max(run, 1), len(correct)
    out.success[row] = k * len(ready) / n
    out.false[row] = false * len(ready) / n
    out.simulated[row] = run
    low, high = wilson_interval(k, run) if run < len(ready) else (k / max(run, 1), k / max(run, 1))
    out.low[row], out.high[row] = low * len(ready) / cfg.samples, high * len(ready) / cfg.samples
    if correct:
        out.error[row] = statistics.median(correct)  # np.median's value: (a + b) / 2 of the middle two
    defined = [a for a in amb if not math.isnan(a)]
    if defined:
        out.ambiguity[row] = statistics.median(defined)


def column_medians(values: np.ndarray) -> np.ndarray:
    """``np.median(values, axis=0)`` of a small integer array (a row an image), without its overhead (most of its
    time on a cell's 16 rows): the middle row of the sorted columns, or the mean of the middle two, as float64
    (exact: integers below 2**53).

    Examples
    --------
    >>> column_medians(np.array([[3, 0], [1, 5], [2, 7], [9, 9]])).tolist()
    [2.5, 6.0]
    """
    ordered = np.sort(np.asarray(values), axis=0)
    half = len(ordered) // 2
    if len(ordered) % 2:
        return ordered[half].astype(np.float64)
    return (ordered[half - 1] + ordered[half]) / 2


def inferred_interval(p_lo: float, p_hi: float, ready: int, samples: int, z: float = Z95) -> tuple[float, float]:
    """The share ``k / samples`` a fixed run reports, ``k`` of its ``ready`` localizable images correct, each with
    a probability anywhere in ``[p_lo, p_hi]``: ``ready / samples`` times ``p -+ z sqrt(p (1 - p) / ready)``,
    its extremes over the range (taken at 33 points of it), clipped to [0, 1].

    Examples
    --------
    >>> [round(v, 3) for v in inferred_interval(0.8, 1.0, 16, 16)]
    [0.604, 1.0]
    >>> [round(v, 3) for v in inferred_interval(0.0, 0.3, 2, 16)]  # at most 2 / 16, whatever p
    [0.0, 0.117]
    """
    p = np.linspace(p_lo, p_hi, 33)
    spread = z * np.sqrt(p * (1.0 - p) / ready)
    scale = ready / samples
    return scale * float(np.clip(p - spread, 0.0, 1.0).min()), scale * float(np.clip(p + spread, 0.0, 1.0).max())


def _inferred(hint: np.ndarray, ready: int, cfg: SampleConfig, out: CellMeasures, row: int) -> bool:
    """Infer a cell between the coarse lattice from its hint (:data:`HINT_COLUMNS`) and its ``ready`` localizable
    images, if the rule of :mod:`mapdb.analysis.adaptive` lets it (its figures then written): whether it did."""
    run, p_lo, p_hi, p_mean, error, amb = (float(v) for v in hint)
    if run or not ready:  # no localizable image: no image to run anyway (success 0 exactly, not inferred)
        return False
    low, high = inferred_interval(p_lo, p_hi, ready, cfg.samples)
    if high - low > cfg.stop_width or low < DECISION_LEVEL <= high:
        return False
    out.success[row] = ready / cfg.samples * p_mean
    out.low[row], out.high[row] = low, high
    out.error[row], out.ambiguity[row] = error, amb
    out.inferred[row] = 1
    return True


def _localize(ctx: _Context, shown: tuple[np.ndarray, np.ndarray, np.ndarray], pose: Pose,
              generator: np.random.Generator, image_id: str) -> tuple[float | None, Answer]:
    """Simulate the image (``shown``: the objects it shows and their pixels, :meth:`~.draws.Views.shown`), localize
    it: the error of an accepted answer (None if rejected), and the answer of the search without a prior (the one
    ambiguity is read from)."""
    cfg = ctx.config
    # An image is localized only when it shows MIN_VISIBLE analysed objects, so the map holds some: the detector
    # exists (it is None only for a map without any).
    assert ctx.detector is not None
    image = cell_image(ctx.objects, *shown, pose, ctx.camera, generator, ctx.detector, cfg.prior, image_id)
    # Brief answers: the position, score and candidates are all a cell's measures read.
    answer = ctx.localizer.localize(image, brief=True)
    lost = answer
    if cfg.prior is not None:
        alone = dataclasses.replace(image, prior=None) if isinstance(image, ImageObjects) else \
            {key: value for key, value in image.items() if key != "prior"}
        lost = ctx.localizer.localize(alone, brief=True)
    if not answer.ok or answer.x is None or answer.y is None:
        return None, lost
    return math.hypot(answer.x - pose.x, answer.y - pose.y), lost
