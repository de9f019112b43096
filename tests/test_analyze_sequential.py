"""``mapdb analyze``'s sequential rule against the fixed run, and the cells skipped before any work.

The map: the lattice and the irregular town of ``test_analyze.py`` and, 600 m east of the town, two lone
buildings (no image can show four objects there: those cells are skipped by the sequential rule).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli

import mapdb.analysis.measures as measures
from mapdb.analysis import SampleConfig
from mapdb.analysis.measures import wilson_interval, wilson_width
from mapdb.analysis.run import Analysis, analyze
from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects

X0, Y0 = 500_000.0, 5_000_000.0
SIDE, GAP, SPACING = 400.0, 300.0, 25.0
CELL = 200.0
LONERS = ((SIDE + GAP + SIDE + 600.0, 200.0), (SIDE + GAP + SIDE + 630.0, 210.0))


def write_world(path: Path) -> Path:
    g = np.arange(SPACING / 2, SIDE, SPACING)
    gx, gy = np.meshgrid(g, g)
    rng = np.random.default_rng(0)
    n = gx.size
    x = np.concatenate([gx.ravel(), SIDE + GAP + rng.uniform(0, SIDE, n), [p[0] for p in LONERS]]) + X0
    y = np.concatenate([gy.ravel(), rng.uniform(0, SIDE, n), [p[1] for p in LONERS]]) + Y0
    write_map(path, Objects.from_names(x, y, ["building"] * x.size, crs="EPSG:32631"))
    return path


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    return write_world(tmp_path_factory.mktemp("sequential") / "world.mapdb")


@pytest.fixture(scope="module")
def both(world: Path) -> tuple[Analysis, Analysis]:
    """The sequential run (every cell, not adaptive: tests/test_analyze_adaptive.py) and the fixed-16 run of the
    same cells."""
    sequential = analyze(str(world), SampleConfig(samples=16, adaptive=False), cell_m=CELL)
    fixed = analyze(str(world), SampleConfig(samples=16, sequential=False), cell_m=CELL)
    return sequential, fixed


def test_sequential_agrees_with_fixed_within_its_widths_with_fewer_images(both) -> None:
    sequential, fixed = both
    s, f = sequential.measures, fixed.measures
    simulated = sequential.counts.within_reach >= measures.MIN_VISIBLE
    assert simulated.sum() >= 8
    width = SampleConfig().stop_width
    for r, c in zip(*np.nonzero(simulated), strict=True):
        ready, ran = int(s["localizable"][r, c]), int(s["simulated"][r, c])
        # The same poses and views: what every image shows, and which can be localized, are the fixed run's.
        assert s["visible"][r, c] == f["visible"][r, c] and ready == f["localizable"][r, c] == f["simulated"][r, c]
        low, high = float(s["success_low"][r, c]), float(s["success_high"][r, c])
        assert low - 1e-6 <= f["success"][r, c] <= high + 1e-6, (r, c, low, high, f["success"][r, c])
        if ran == ready:  # every localizable image ran: the fixed run's figures, an interval of no width
            assert low == high == s["success"][r, c]
            for band in ("success", "false_fixes", "error_m", "ambiguity", "simulated"):
                assert np.array_equal(s[band][r, c], f[band][r, c], equal_nan=True), band
        else:  # stopped early: only once its interval was narrow enough, after at least MIN_RUN
            k = round(float(s["success"][r, c]) * 16 * ran / ready)
            expected = wilson_interval(k, ran)
            assert (low, high) == pytest.approx((expected[0] * ready / 16, expected[1] * ready / 16), abs=1e-6)
            assert measures.MIN_RUN <= ran < ready and high - low <= width + 1e-6
    stopped = simulated & (s["simulated"] < s["localizable"])
    assert stopped.sum() >= simulated.sum() / 2
    assert sequential.stats["images_localized"] <= fixed.stats["images_localized"] / 2
    assert (f["images"][fixed.reached] == 16).all()


def test_cells_no_image_can_localize_from_are_skipped(both) -> None:
    sequential, fixed = both
    s, f = sequential.measures, fixed.measures
    grid = sequential.grid
    row, col, inside = grid.locate(np.array([X0 + LONERS[0][0]]), np.array([Y0 + LONERS[0][1]]))
    assert inside[0]
    cell = (int(row[0]), int(col[0]))
    assert sequential.counts.within_reach[cell] == 2
    skipped = sequential.reached & (sequential.counts.within_reach < measures.MIN_VISIBLE)
    assert skipped[cell] and sequential.stats["cells_skipped"] == int(skipped.sum())
    # Marked: no image drawn, objects in view unknown, success and false 0 exactly (an interval of no width).
    assert (s["images"][skipped] == 0).all() and np.isnan(s["visible"][skipped]).all()
    assert np.isnan(s["visible_building"][skipped]).all() and (s["localizable"][skipped] == 0).all()
    assert (s["success"][skipped] == 0).all() and (s["success_high"][skipped] == 0).all()
    # The fixed run draws all 16 there, and none of them can be localized: the same success.
    assert (f["images"][skipped] == 16).all() and (f["simulated"][skipped] == 0).all()
    assert (f["success"][skipped] == 0).all() and fixed.stats["cells_skipped"] == 0


def test_skipped_cells_reach_no_worker(world: Path, monkeypatch) -> None:
    """The skipped cells are never handed to measure_cells (counted where the tasks arrive)."""
    import mapdb.analysis.run as run

    seen: list[np.ndarray] = []

    def counting(map_path, config, cell_m, cells, hints=None):
        seen.append(np.asarray(cells))
        return measures.measure_cells(map_path, config, cell_m, cells, hints)

    monkeypatch.setattr(run, "measure_cells", counting)
    a = analyze(str(world), SampleConfig(samples=2, adaptive=False), cell_m=CELL)
    sent = np.concatenate(seen)
    i, j = a.grid.absolute(*np.nonzero(a.counts.within_reach >= measures.MIN_VISIBLE))
    assert sorted(map(tuple, sent.tolist())) == sorted(zip(i.tolist(), j.tolist(), strict=True))


def test_the_documented_rule_is_the_code() -> None:
    """The module docstring's numbers, read against the functions."""
    doc = " ".join((measures.__doc__ or "").split())
    width = SampleConfig().stop_width
    assert f"{width:.3f} for 16 images" in doc and wilson_width(8, 16) == pytest.approx(width)
    assert f"``m >= MIN_RUN`` ({measures.MIN_RUN})" in doc

    def stops_after(ready: int) -> int:  # every image localized succeeds
        return next(m for m in range(ready + 1) if measures._known(m, 0, m, ready, 16, width))

    low = wilson_interval(5, 5)[0]
    assert f"all succeed stops after {stops_after(16)} (interval {low:.3f} to 1 of the fixed share)" in doc
    assert f"one with 8 localizable after {stops_after(8)}, whatever they give" in doc
    assert f"(at most {8 / 16 * wilson_width(1, 2):.3f} wide)" in doc
    assert f"12 localizable, all succeeding, after {stops_after(12)}" in doc
    assert not measures._known(0, 0, 1, 16, 16, 1.0)  # never before MIN_RUN, however wide the width
    assert measures._known(0, 0, 3, 3, 16, 0.01)  # always once every localizable image ran
    assert SampleConfig(width=0.3).stop_width == 0.3


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_cli_records_the_rule_and_marks_skipped_cells(world: Path, tmp_path: Path) -> None:
    import geopandas

    out = tmp_path / "seq"
    result = run("analyze", world, "-o", out, "--samples", "4", "--cell", CELL, "-q")
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    p = summary["parameters"]
    assert p["sequential"] is True and p["stop_width"] == round(wilson_width(2, 4), 4)
    assert p["images_per_cell"] == "sequential: at most 4" and p["interval"].startswith("Wilson")
    assert summary["run"]["cells_skipped"] >= 1
    assert summary["images_localized"] < summary["images_localizable"] == summary["run"]["images_localizable"]
    assert 0 < summary["success_width"]["max"] <= p["stop_width"]
    bounds, works = summary["success_at_least_95_within_interval"], summary["success_at_least_95"]
    assert bounds["low"] <= works["fraction_of_objects_bearing_area"] <= bounds["high"]
    cells = geopandas.read_file(out / "cells.gpkg")
    skipped = cells[(cells["images"] == 0) & (cells["inferred"] == 0)]
    assert len(skipped) == summary["run"]["cells_skipped"] and skipped["visible"].isna().all()
    fixed = tmp_path / "fixed"
    result = run("analyze", world, "-o", fixed, "--samples", "4", "--cell", CELL, "--no-sequential", "-q")
    assert result.exit_code == 0, result.output
    summary = json.loads((fixed / "summary.json").read_text())
    assert summary["parameters"]["sequential"] is False and summary["parameters"]["stop_width"] is None
    assert summary["run"]["cells_skipped"] == 0 and summary["success_width"]["max"] == 0
    assert summary["images_localized"] == summary["images_localizable"]
    bounds, works = summary["success_at_least_95_within_interval"], summary["success_at_least_95"]
    assert bounds["low"] == works["fraction_of_objects_bearing_area"] == bounds["high"]


@pytest.mark.parametrize("width", ["0", "-0.1", "1.5", "nan"])
def test_bad_width_is_a_usage_error(world: Path, tmp_path: Path, width: str) -> None:
    result = run("analyze", world, "-o", tmp_path / "out", "--width", width)
    assert result.exit_code == 2 and "--width" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "out").exists()
