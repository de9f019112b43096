"""``mapdb analyze``: measures known by construction, read back from the files a user opens.

The synthetic map: a perfectly periodic square lattice of buildings (25 m apart) on the west, an empty gap,
and an irregular town of as many buildings (uniform at random, same density) on the east.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyogrio
import pytest
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from sqlwords import sql_keywords_among

from mapdb.analysis import SampleConfig
from mapdb.analysis.measures import measure_cells
from mapdb.analysis.run import analyze
from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects

X0, Y0 = 500_000.0, 5_000_000.0
SIDE, GAP, SPACING = 400.0, 300.0, 25.0
CELL = 100.0
SAMPLES = "2"


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])




def write_synthetic(path: Path) -> Path:
    """The lattice (west), the gap, the irregular town (east), all buildings, in UTM 31N."""
    g = np.arange(SPACING / 2, SIDE, SPACING)
    gx, gy = np.meshgrid(g, g)
    rng = np.random.default_rng(0)
    n = gx.size
    x = np.concatenate([gx.ravel(), SIDE + GAP + rng.uniform(0, SIDE, n)]) + X0
    y = np.concatenate([gy.ravel(), rng.uniform(0, SIDE, n)]) + Y0
    write_map(path, Objects.from_names(x, y, ["building"] * x.size, crs="EPSG:32631"))
    return path


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    return write_synthetic(tmp_path_factory.mktemp("analyze") / "synthetic.mapdb")


@pytest.fixture(scope="module")
def analysed(synthetic: Path) -> Path:
    """One in-process analysis of the synthetic map through the CLI (beside a folder a killed run left)."""
    out = synthetic.parent / "out"
    stale = synthetic.parent / ".out.999999999.deadbeef.tmp"
    stale.mkdir()
    (stale / "analysis.tif").write_bytes(b"half")
    result = run("analyze", synthetic, "-o", out, "--samples", SAMPLES, "-q")
    assert result.exit_code == 0, result.output
    return out


def read_bands(tif: Path) -> tuple[dict[str, np.ndarray], object]:
    import rasterio

    with rasterio.open(tif) as src:
        bands = {name: src.read(k + 1, masked=True) for k, name in enumerate(src.descriptions)}
        return bands, src


def cell_at(src, x: float, y: float) -> tuple[int, int]:
    row, col = src.index(X0 + x, Y0 + y)
    return int(row), int(col)


def test_geotiff_reads_back_known_cells(analysed: Path) -> None:
    import rasterio

    with rasterio.open(analysed / "analysis.tif") as src:
        assert src.crs.to_epsg() == 32631
        assert src.nodata == -9999.0
        assert src.res == (CELL, CELL)
        names = list(src.descriptions)
        assert names[:5] == ["success", "false_fixes", "error_m", "ambiguity", "visible"]
        # GDAL's band units (gdalinfo's "Unit Type", QGIS's): every band has one, as the measures define it
        assert all(src.units) and len(src.units) == len(names) == src.count
        assert src.units[:3] == ("fraction", "fraction", "m")
        assert src.units[names.index("visible_building")] == "objects"
        assert sql_keywords_among(names) == []
        assert "visible_building" in names and "bytes_per_km2" in names
        bands = {name: src.read(k + 1) for k, name in enumerate(names)}
        empty = cell_at(src, SIDE + GAP / 2, SIDE / 2)     # middle of the gap: nothing within reach
        town = cell_at(src, SIDE + GAP + SIDE / 2, SIDE / 2)
        lattice = cell_at(src, SIDE / 2 - 10, SIDE / 2 - 10)
    # The transform puts every cell where it is: the lattice cell holds exactly its 4 x 4 buildings.
    assert bands["objects_per_km2"][lattice] == pytest.approx(16 / (CELL * CELL / 1e6))
    assert bands["objects_per_km2"][empty] == 0 and bands["visible"][empty] == 0
    assert bands["success"][empty] == 0 and bands["simulated"][empty] == 0
    assert bands["ambiguity"][empty] == -9999.0 and bands["error_m"][empty] == -9999.0  # no value there
    assert bands["success"][town] >= 2 / 3 and bands["visible"][town] >= 8
    assert 0 <= bands["error_m"][town] < 2.0
    assert bands["bytes_per_km2"][town] > 0


def test_periodic_lattice_is_ambiguous_and_the_town_is_not(analysed: Path) -> None:
    bands, src = read_bands(analysed / "analysis.tif")
    amb = bands["ambiguity"]
    # Interior cells: every image's footprint stays in its part.
    lattice = [amb[cell_at(src, x, y)] for x in (150, 250) for y in (150, 250)]
    town = [amb[cell_at(src, SIDE + GAP + x, y)] for x in (150, 250) for y in (150, 250)]
    assert not any(np.ma.is_masked(v) for v in lattice + town)
    assert min(lattice) >= 0.8, lattice
    assert max(town) <= 0.2, town


def test_outputs_are_complete_and_nothing_is_left_beside(analysed: Path) -> None:
    """Four files; no temporary folder beside, not even the one a killed run had left."""
    import geopandas

    assert sorted(os.listdir(analysed)) == ["analysis.png", "analysis.tif", "cells.gpkg", "summary.json"]
    assert not [p for p in os.listdir(analysed.parent) if p.startswith(".")]
    summary = json.loads((analysed / "summary.json").read_text())
    assert summary["software"].startswith("mapdb ")
    assert summary["parameters"]["altitude_m"] == 150 and summary["parameters"]["samples"] == int(SAMPLES)
    assert summary["area"]["objects"] == 512
    assert summary["most_ambiguous"][0]["ambiguity"] >= 0.8
    assert summary["most_ambiguous"][0]["x"] < X0 + SIDE  # in the lattice
    fraction = summary["success_at_least_95"]["fraction_of_objects_bearing_area"]
    assert 0.2 < fraction < 0.8  # the town works, the lattice does not
    cells = geopandas.read_file(analysed / "cells.gpkg")
    assert cells.crs.to_epsg() == 32631 and {"success", "ambiguity", "bytes_per_km2"} <= set(cells.columns)
    assert sql_keywords_among(cells.columns) == [] and "false_fixes" in cells.columns
    assert [str(kind) for kind in pyogrio.list_layers(analysed / "cells.gpkg")[:, 1]] == ["Polygon"]
    assert np.allclose(cells.geometry.area, CELL * CELL)
    assert (analysed / "analysis.png").stat().st_size > 10_000


def test_within_reach_bounds_what_images_see(synthetic: Path) -> None:
    a = analyze(str(synthetic), SampleConfig(samples=2), cell_m=CELL)
    assert (a.measures["visible"] <= a.counts.within_reach).all()
    assert (a.measures["simulated"][a.counts.within_reach < 4] == 0).all()


def test_measures_do_not_depend_on_how_cells_are_grouped(synthetic: Path) -> None:
    cells = np.array([[5003, 50001], [5008, 50002], [5009, 50001]])
    config = SampleConfig(samples=2, pixel_std=1.0, prior=300.0)
    together = measure_cells(str(synthetic), config, CELL, cells)
    apart = [measure_cells(str(synthetic), config, CELL, cells[k:k + 1]) for k in (2, 0, 1)]
    for name in ("visible", "success", "false", "error", "ambiguity", "simulated", "per_label"):
        joined = np.concatenate([getattr(apart[k], name) for k in (1, 2, 0)])
        assert np.array_equal(getattr(together, name), joined, equal_nan=True), name


# ------------------------------------------------------------------------------------------ Dask


def compare_runs(first: Path, second: Path) -> None:
    import rasterio

    with rasterio.open(first / "analysis.tif") as a, rasterio.open(second / "analysis.tif") as b:
        assert a.descriptions == b.descriptions and a.transform == b.transform
        assert a.read().tobytes() == b.read().tobytes()


@pytest.mark.slow
def test_local_cluster_gives_the_same_bytes(synthetic: Path, analysed: Path, tmp_path: Path) -> None:
    result = run("analyze", synthetic, "-o", tmp_path / "jobs", "--samples", SAMPLES, "--jobs", 2, "-q")
    assert result.exit_code == 0, result.output
    compare_runs(analysed, tmp_path / "jobs")


@pytest.mark.slow
def test_existing_scheduler_gives_the_same_bytes(synthetic: Path, analysed: Path, tmp_path: Path) -> None:
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        result = run("analyze", synthetic, "-o", tmp_path / "sched", "--samples", SAMPLES, "--scheduler",
                     cluster.scheduler_address, "-q")
    assert result.exit_code == 0, result.output
    compare_runs(analysed, tmp_path / "sched")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unreachable_scheduler_is_one_line_within_the_timeout(synthetic: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = run("analyze", synthetic, "-o", out, "--scheduler", f"tcp://127.0.0.1:{free_port()}",
                 "--timeout", "1", "-q")
    assert_one_line_error(result, "no Dask scheduler answered within 1 s")
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_without_dask_jobs_say_how_to_install_it(synthetic: Path, tmp_path: Path) -> None:
    code = ("import sys; sys.modules['distributed'] = None; from mapdb_cli.main import cli; "
            "cli(sys.argv[1:], prog_name='mapdb')")
    done = subprocess.run([sys.executable, "-c", code, "analyze", str(synthetic), "-o", str(tmp_path / "o"),
                           "--jobs", "2", "-q"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        'mapdb: error: --jobs needs dask.distributed, which is not installed: pip install "mapdb[dask]"']


# ------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(("args", "needle"), [
    (["--cell", "0"], "cell size must be a positive number"),
    (["--cell", "-5"], "cell size must be a positive number"),
    (["--cell", "0.01"], "more than the limit of 40,000,000"),
    (["--bbox", "3.0,45.0,3.0,45.1"], "minlon and maxlon must differ"),
    (["--bbox", "10,10,11,11"], "does not meet the map"),
    (["--bbox", "3.0,45.0,3.1,45.1,7"], "bbox"),
    (["--labels", "building,roads"], "unknown label 'roads'"),
])
def test_bad_input_is_one_line(synthetic: Path, tmp_path: Path, args: list[str], needle: str) -> None:
    out = tmp_path / "out"
    assert_one_line_error(run("analyze", synthetic, "-o", out, "-q", *args), needle)
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".")]


def test_not_a_map_is_one_line(tmp_path: Path) -> None:
    fake = tmp_path / "fake.mapdb"
    fake.write_text("hello\n")
    assert_one_line_error(run("analyze", fake, "-o", tmp_path / "out"), "not a mapdb map")
    assert not (tmp_path / "out").exists()


def test_existing_output_and_an_input_inside_it_are_refused(synthetic: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine\n")
    assert_one_line_error(run("analyze", synthetic, "-o", out), "exists; pass --overwrite")
    inside = write_synthetic(out / "inside.mapdb")
    assert_one_line_error(run("analyze", inside, "-o", out, "--overwrite"), "holds input")
    assert (out / "keep.txt").read_text() == "mine\n" and inside.exists()


def test_scenarios_with_unknown_keys_are_refused(synthetic: Path, tmp_path: Path) -> None:
    toml = tmp_path / "s.toml"
    toml.write_text('[scenario."buildings only"]\nlabels = ["building"]\nheight = 300\n')
    assert_one_line_error(run("analyze", synthetic, "-o", tmp_path / "out", "--scenarios", toml),
                          "scenario 'buildings only': unknown key 'height'")
    toml.write_text('[scenarios.low]\naltitude = 80\n')
    assert_one_line_error(run("analyze", synthetic, "-o", tmp_path / "out", "--scenarios", toml),
                          "unknown key 'scenarios'")
    toml.write_text('[scenario.low]\naltitude = -80\n')
    assert_one_line_error(run("analyze", synthetic, "-o", tmp_path / "out", "--scenarios", toml),
                          "altitude must be above 0")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_scenarios_compare_over_the_same_cells(synthetic: Path, tmp_path: Path) -> None:
    toml = tmp_path / "s.toml"
    toml.write_text('[scenario."150 m"]\n\n[scenario."60 m"]\naltitude = 60\n')
    out = tmp_path / "out"
    result = run("analyze", synthetic, "-o", out, "--samples", "2", "--scenarios", toml, "-q")
    assert result.exit_code == 0, result.output
    assert sorted(os.listdir(out)) == ["150_m.tif", "60_m.tif", "cells.gpkg", "scenarios.png", "summary.json"]
    summary = json.loads((out / "summary.json").read_text())
    rows = {row["scenario"]: row for row in summary["comparison"]}
    assert rows["60 m"]["altitude_m"] == 60 and rows["150 m"]["altitude_m"] == 150
    lower, higher = read_bands(out / "60_m.tif")[0], read_bands(out / "150_m.tif")[0]
    # Lower, an image sees fewer objects: the same cells, a smaller footprint.
    assert np.ma.median(lower["visible"]) < np.ma.median(higher["visible"])
