"""``mapdb analyze``'s adaptive cells: a coarse lattice first, the cells between it only where it disagrees.

The rule on hand-made lattice measures (:func:`mapdb.analysis.adaptive.infer`), then whole runs on the map of
``test_analyze_sequential.py`` (a lattice of houses, an irregular town, two lone buildings) against the
sequential run of every cell and the fixed-16 run.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from mapdb_cli.main import cli
from test_analyze_sequential import CELL, write_world

import mapdb.analysis.measures as measures
from mapdb.analysis import SampleConfig, adaptive
from mapdb.analysis.grid import Grid
from mapdb.analysis.measures import wilson_interval
from mapdb.analysis.run import Analysis, analyze

BANDS = ("success", "false_fixes", "error_m", "ambiguity", "localizable", "simulated", "images")


def lattice_bands(grid: Grid, cells: dict[tuple[int, int], tuple[int, int, int, int]]) -> dict:
    """Bands with the given lattice cells' (localizable L, images run m, correct k, false) of 16 set as the
    sequential rule writes them, everything else as a cell no image can localize from; error 1 m and
    ambiguity 0.2 where a cell has a correct image."""
    bands = {name: np.zeros(grid.shape) for name in BANDS}
    bands["error_m"][:] = np.nan
    bands["ambiguity"][:] = np.nan
    for (i, j), (ready, run, k, false) in cells.items():
        r, c = grid.nrows - 1 - (j - grid.j0), i - grid.i0
        bands["images"][r, c], bands["localizable"][r, c], bands["simulated"][r, c] = 16, ready, run
        bands["success"][r, c], bands["false_fixes"][r, c] = k * ready / (16 * run), false * ready / (16 * run)
        if k:
            bands["error_m"][r, c], bands["ambiguity"][r, c] = 1.0, 0.2
    return bands


def test_the_lattice_tells_the_cells_between_it_what_it_knows() -> None:
    grid = Grid(100.0, 0, 0, 7, 3, "EPSG:32631")  # cells i 0..6, j 0..2
    bands = lattice_bands(grid, {(0, 0): (16, 5, 5, 0), (2, 0): (12, 3, 3, 0), (4, 0): (16, 6, 0, 0),
                                 (0, 2): (8, 2, 2, 0), (6, 0): (16, 6, 3, 1), (6, 2): (10, 4, 2, 0)})
    i = np.array([1, 3, 0, 5, 5, 1])
    j = np.array([0, 0, 1, 0, 2, 1])
    h = adaptive.hints(grid, bands, i, j)
    assert adaptive.HINT_COLUMNS == ("run", "p_low", "p_high", "p_mean", "error_m", "ambiguity")
    # (1, 0): between (0, 0) (5 of 5) and (2, 0) (3 of 3): p in the hull of their Wilson intervals.
    assert h[0, 0] == 0 and h[0, 1:4] == pytest.approx([wilson_interval(3, 3)[0], 1.0, 1.0])
    assert h[0, 4:].tolist() == [1.0, pytest.approx(0.2)]
    # (3, 0): (2, 0) all correct, (4, 0) none of 6: the intervals do not overlap, run.
    assert h[1, 0] == 1
    # (0, 1): (0, 0) and (0, 2) agree.  (5, 0): (6, 0) had a false fix, run.  (5, 2): (4, 2), which no image can
    # localize from, says nothing of p: the hint is (6, 2)'s alone.
    assert h[2, 0] == 0 and h[3, 0] == 1
    assert h[4, 0] == 0 and h[4, 1:3] == pytest.approx(wilson_interval(2, 4))
    # (1, 1): its four corners (0, 0), (2, 0), (0, 2), (2, 2) -- the last says nothing -- agree.
    assert h[5, 0] == 0 and h[5, 3] == 1.0
    # A cell whose neighbours say nothing (none in the grid, or none with an image run) is run.
    lone = Grid(100.0, 1, 0, 1, 1, "EPSG:32631")
    assert adaptive.hints(lone, lattice_bands(lone, {}), np.array([1]), np.array([0]))[0, 0] == 1


def test_the_inferred_interval_holds_the_fixed_share_for_every_p_of_the_hull() -> None:
    """Simulated fixed runs of ``ready`` images at probabilities across the hull: their shares fall in the
    interval at least about 95 % of the time at the worst p."""
    rng = np.random.default_rng(0)
    for p_lo, p_hi, ready in ((0.5, 0.8, 16), (0.9, 1.0, 12), (0.0, 0.2, 16), (0.3, 0.6, 4)):
        low, high = measures.inferred_interval(p_lo, p_hi, ready, 16)
        assert 0 <= low <= ready / 16 * p_lo <= ready / 16 * p_hi <= high <= ready / 16
        for p in np.linspace(p_lo, p_hi, 5):
            share = rng.binomial(ready, p, 4000) / 16
            assert ((share >= low - 1e-9) & (share <= high + 1e-9)).mean() >= 0.9, (p_lo, p_hi, ready, p)


def test_the_lattice_is_every_second_cell_each_way() -> None:
    i, j = np.meshgrid(np.arange(-3, 5), np.arange(-2, 6))
    on = adaptive.coarse(i.ravel(), j.ravel())
    assert on.sum() == on.size // 4
    assert (i.ravel()[on] % 2 == 0).all() and (j.ravel()[on] % 2 == 0).all()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Analysis, Analysis, Analysis]:
    """The adaptive run, the sequential run of every cell, the fixed-16 run (200 m cells)."""
    world = str(write_world(tmp_path_factory.mktemp("adaptive") / "world.mapdb"))
    return (analyze(world, SampleConfig(samples=16, adaptive=True), cell_m=CELL),
            analyze(world, SampleConfig(samples=16, adaptive=False), cell_m=CELL),
            analyze(world, SampleConfig(samples=16, sequential=False), cell_m=CELL))


def test_run_cells_are_the_full_runs_and_inferred_cells_follow_the_rule(runs) -> None:
    a, every, fixed = runs
    s, e = a.measures, every.measures
    heavy = a.counts.within_reach >= measures.MIN_VISIBLE
    inferred = s["inferred"] > 0
    assert inferred.sum() == a.stats["cells_inferred"] >= 1
    assert a.stats["cells_simulated"] == int((heavy & ~inferred).sum()) and not (inferred & ~heavy).any()
    # Every cell measured: the same bytes as in the run of every cell (its images depend on nothing else).
    for band in e:
        if band != "inferred":
            assert np.array_equal(s[band][~inferred], e[band][~inferred], equal_nan=True), band
    # Inferred: its own draws (the same views), no image localized, the figures the rule gives.
    for band in ("images", "localizable", "visible", "visible_building"):
        assert np.array_equal(s[band][inferred], e[band][inferred]), band
    assert (s["simulated"][inferred] == 0).all() and (s["false_fixes"][inferred] == 0).all()
    rows, cols = np.nonzero(heavy)
    i, j = a.grid.absolute(rows, cols)
    between = ~adaptive.coarse(i, j)
    hint = adaptive.hints(a.grid, e, i[between], j[between])
    width = SampleConfig().stop_width
    for (r, c), h in zip(zip(rows[between], cols[between]), hint):
        ready = int(e["localizable"][r, c])
        low, high = measures.inferred_interval(h[1], h[2], ready, 16) if not h[0] and ready else (0.0, 1.0)
        expected = not h[0] and ready and high - low <= width and not low < 0.95 <= high
        assert inferred[r, c] == bool(expected), (r, c)
        if expected:
            assert (s["success_low"][r, c], s["success_high"][r, c]) == pytest.approx((low, high), abs=1e-6)
            assert s["success"][r, c] == pytest.approx(ready / 16 * h[3], abs=1e-6)
            assert low - 1e-6 <= fixed.measures["success"][r, c] <= high + 1e-6
    assert a.stats["images_localized"] < every.stats["images_localized"]


def test_every_cell_reaches_a_worker_once(tmp_path: Path, monkeypatch) -> None:
    """Every cell that can show four objects is handed to measure_cells once (the cells between the lattice
    draw their own views there), none twice."""
    import mapdb.analysis.run as run

    world = str(write_world(tmp_path / "world.mapdb"))
    seen: list[np.ndarray] = []

    def counting(map_path, config, cell_m, cells, hints=None):
        seen.append(np.asarray(cells))
        return measures.measure_cells(map_path, config, cell_m, cells, hints)

    monkeypatch.setattr(run, "measure_cells", counting)
    a = analyze(world, SampleConfig(samples=2, adaptive=True), cell_m=CELL)
    sent = sorted(map(tuple, np.concatenate(seen).tolist()))
    i, j = a.grid.absolute(*np.nonzero(a.counts.within_reach >= measures.MIN_VISIBLE))
    assert sent == sorted(zip(i.tolist(), j.tolist(), strict=True))


def test_cli_records_the_rule_and_no_adaptive_runs_every_cell(tmp_path: Path) -> None:
    world = write_world(tmp_path / "world.mapdb")
    runner = CliRunner()
    for flag in ("--adaptive", "--no-adaptive"):
        out = tmp_path / flag
        result = runner.invoke(cli, ["analyze", str(world), "-o", str(out), "--cell", str(CELL), "-q", flag])
        assert result.exit_code == 0, result.output
        doc = json.loads((out / "summary.json").read_text())
        assert doc["parameters"]["adaptive"] is (flag == "--adaptive")
        assert (doc["cells_inferred"] > 0) is (flag == "--adaptive")
        assert doc["run"]["cells_inferred"] == doc["cells_inferred"]
        with rasterio.open(out / "analysis.tif") as src:
            inferred = src.read(list(src.descriptions).index("inferred") + 1)
        # An inferred cell's ambiguity is borrowed from its neighbours: never listed as its own.
        assert doc["most_ambiguous"] and all(inferred[c["row"], c["col"]] == 0 for c in doc["most_ambiguous"])
    assert "lattice" in doc["measures"]["inferred"]["description"]


def test_the_documented_rule_is_the_code() -> None:
    doc = " ".join((adaptive.__doc__ or "").split())
    assert f"{adaptive.DECISION_LEVEL:g}" in doc
    from mapdb.analysis.outputs import ADAPTIVE_RULE, SUCCESS_LEVEL

    assert SUCCESS_LEVEL == adaptive.DECISION_LEVEL and f"{adaptive.DECISION_LEVEL:g}" in ADAPTIVE_RULE
    assert "1.96" in ADAPTIVE_RULE and "stop_width" in ADAPTIVE_RULE
    assert all(k in adaptive._NEIGHBOURS for k in ((1, 0), (0, 1), (1, 1)))
    assert "0.44 for 16 images" in doc and f"{SampleConfig().stop_width:.2f}" == "0.44"
    assert "``z`` 1.96" in doc and f"{measures.Z95:.2f}" == "1.96"
