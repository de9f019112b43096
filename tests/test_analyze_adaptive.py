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
from click.testing import CliRunner
from mapdb_cli.main import cli
from test_analyze_sequential import CELL, write_world

import mapdb.analysis.measures as measures
from mapdb.analysis import SampleConfig, adaptive
from mapdb.analysis.grid import Grid
from mapdb.analysis.run import Analysis, analyze

BANDS = ("success", "false_fixes", "error_m", "ambiguity", "success_low", "success_high")


def lattice_bands(grid: Grid, cells: dict[tuple[int, int], tuple[float, float, float, float]]) -> dict:
    """Bands with the given lattice cells' (success, low, high, false) set, everything else 0 (no image can
    localize there): error 1 m and ambiguity 0.2 where a cell has success."""
    bands = {name: np.zeros(grid.shape) for name in BANDS}
    bands["error_m"][:] = np.nan
    bands["ambiguity"][:] = np.nan
    for (i, j), (success, low, high, false) in cells.items():
        r, c = grid.nrows - 1 - (j - grid.j0), i - grid.i0
        bands["success"][r, c], bands["success_low"][r, c], bands["success_high"][r, c] = success, low, high
        bands["false_fixes"][r, c] = false
        if success:
            bands["error_m"][r, c], bands["ambiguity"][r, c] = 1.0, 0.2
    return bands


def test_the_rule_on_hand_made_lattice_measures() -> None:
    grid = Grid(100.0, 0, 0, 7, 3, "EPSG:32631")  # cells i 0..6, j 0..2
    bands = lattice_bands(grid, {(0, 0): (0.5, 0.3, 0.7, 0.0), (2, 0): (0.6, 0.4, 0.8, 0.0),
                                 (4, 0): (0.1, 0.0, 0.3, 0.0), (0, 2): (0.5, 0.35, 0.65, 0.0),
                                 (2, 2): (0.97, 0.6, 1.0, 0.0), (6, 0): (0.2, 0.05, 0.4, 0.0625),
                                 (6, 2): (0.2, 0.05, 0.4, 0.0)})
    i = np.array([1, 3, 0, 1, 5, 5])
    j = np.array([0, 0, 1, 1, 0, 2])
    d = adaptive.infer(grid, bands, i, j)
    # (1, 0): between (0, 0) and (2, 0), overlapping, both below 0.95: inferred, the union of their intervals.
    # (3, 0): (2, 0) and (4, 0) do not overlap (0.4 > 0.3): run.
    # (0, 1): (0, 0) and (0, 2) agree: inferred.  (1, 1): its four corners include (2, 2) at 0.97: run.
    # (5, 0): (6, 0) had a false fix: run.  (5, 2): (4, 2) (no image can localize: [0, 0]) and (6, 2) overlap at
    # 0... no: 0.05 > 0, the intervals do not overlap: run.
    assert d.run.tolist() == [1, 3, 4, 5] and d.infer.tolist() == [0, 2]
    assert d.low.tolist() == [0.3, 0.3] and d.high.tolist() == [0.8, 0.7]
    assert d.success == pytest.approx([0.55, 0.5]) and d.false.tolist() == [0.0, 0.0]
    assert d.error.tolist() == [1.0, 1.0] and d.ambiguity == pytest.approx([0.2, 0.2])
    # A cell with no neighbour in the grid is run.
    lone = Grid(100.0, 1, 0, 1, 1, "EPSG:32631")
    assert adaptive.infer(lone, lattice_bands(lone, {}), np.array([1]), np.array([0])).run.tolist() == [0]


def test_the_lattice_is_every_second_cell_each_way() -> None:
    i, j = np.meshgrid(np.arange(-3, 5), np.arange(-2, 6))
    on = adaptive.coarse(i.ravel(), j.ravel())
    assert on.sum() == on.size // 4
    assert (i.ravel()[on] % 2 == 0).all() and (j.ravel()[on] % 2 == 0).all()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Analysis, Analysis, Analysis]:
    """The adaptive run, the sequential run of every cell, the fixed-16 run (200 m cells)."""
    world = str(write_world(tmp_path_factory.mktemp("adaptive") / "world.mapdb"))
    return (analyze(world, SampleConfig(samples=16), cell_m=CELL),
            analyze(world, SampleConfig(samples=16, adaptive=False), cell_m=CELL),
            analyze(world, SampleConfig(samples=16, sequential=False), cell_m=CELL))


def test_run_cells_are_the_full_runs_and_inferred_cells_follow_the_rule(runs) -> None:
    a, every, _ = runs
    s, e = a.measures, every.measures
    heavy = a.counts.within_reach >= measures.MIN_VISIBLE
    inferred = s["inferred"] > 0
    assert inferred.sum() == a.stats["cells_inferred"] >= 1
    assert a.stats["cells_simulated"] == int((heavy & ~inferred).sum()) and not (inferred & ~heavy).any()
    # Every cell simulated: the same bytes as in the run of every cell (its images depend on nothing else).
    for band in e:
        if band != "inferred":
            assert np.array_equal(s[band][~inferred], e[band][~inferred], equal_nan=True), band
    # Inferred: no image, objects in view unknown, the figures those the rule gives from the lattice's.
    assert (s["images"][inferred] == 0).all() and (s["simulated"][inferred] == 0).all()
    assert np.isnan(s["visible"][inferred]).all()
    rows, cols = np.nonzero(heavy)
    i, j = a.grid.absolute(rows, cols)
    between = ~adaptive.coarse(i, j)
    d = adaptive.infer(a.grid, e, i[between], j[between])
    r, c = rows[between][d.infer], cols[between][d.infer]
    assert inferred[r, c].all() and inferred.sum() == r.size
    assert np.array_equal(s["success_low"][r, c], d.low.astype(np.float32))
    assert np.array_equal(s["success_high"][r, c], d.high.astype(np.float32))
    assert ((s["success_low"] <= s["success"]) & (s["success"] <= s["success_high"]))[inferred].all()
    assert a.stats["images_localized"] < every.stats["images_localized"]


def test_inferred_cells_reach_no_worker(tmp_path: Path, monkeypatch) -> None:
    """Only the lattice's cells and the cells between it that are run are handed to measure_cells."""
    import mapdb.analysis.run as run

    world = str(write_world(tmp_path / "world.mapdb"))
    seen: list[np.ndarray] = []

    def counting(map_path, config, cell_m, cells):
        seen.append(np.asarray(cells))
        return measures.measure_cells(map_path, config, cell_m, cells)

    monkeypatch.setattr(run, "measure_cells", counting)
    a = analyze(world, SampleConfig(samples=2), cell_m=CELL)
    sent = sorted(map(tuple, np.concatenate(seen).tolist()))
    ran = (a.counts.within_reach >= measures.MIN_VISIBLE) & (a.measures["inferred"] == 0)
    i, j = a.grid.absolute(*np.nonzero(ran))
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
    assert "lattice" in doc["measures"]["inferred"]["description"]


def test_the_documented_rule_is_the_code() -> None:
    doc = " ".join((adaptive.__doc__ or "").split())
    assert f"{adaptive.DECISION_LEVEL:g}" in doc
    from mapdb.analysis.outputs import ADAPTIVE_RULE, SUCCESS_LEVEL

    assert SUCCESS_LEVEL == adaptive.DECISION_LEVEL and f"{adaptive.DECISION_LEVEL:g}" in ADAPTIVE_RULE
    assert all(k in adaptive._NEIGHBOURS for k in ((1, 0), (0, 1), (1, 1)))
