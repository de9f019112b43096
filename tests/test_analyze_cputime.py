"""``mapdb analyze`` accounts its own CPU by phase (mapdb.analysis.cputime): start-up, cells, outputs."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli
from towns import write_town

from mapdb.analysis.cputime import PHASES, CpuPhases


@pytest.fixture(scope="module")
def town(tmp_path_factory) -> Path:
    """An irregular town of 300 buildings on 500 m x 300 m (UTM 31N): some cells to simulate, some empty."""
    return write_town(tmp_path_factory.mktemp("cputime") / "town.mapdb", 300, 3, 300.0, 300.0)


def test_phases_are_measured_and_add_up_to_at_most_the_process_cpu(town: Path, tmp_path: Path) -> None:
    """A run as its own process: every phase in summary.json, none negative, their sum within the CPU the
    operating system counted for the process; the end-of-run line says the same."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([sys.executable, "-m", "mapdb_cli", "analyze", str(town), "-o", str(tmp_path / "o"),
                           "--samples", "2", "--cell", "100"], capture_output=True, text=True, check=False)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert done.returncode == 0, done.stderr
    process = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    cpu, n = summary["cpu"], summary["area"]["cells"]
    phases = [cpu[f"{phase}_s"] for phase in PHASES]
    assert all(value >= 0 for value in phases), cpu
    assert cpu["startup_s"] > 0 and cpu["cells_s"] > 0  # the imports, and the cells' images, cost something
    # Rounded to the millisecond each (three roundings), and the clock's own granularity.
    assert sum(phases) <= process + 0.01, (cpu, process)
    assert cpu["workers_s"] == 0  # in one process: the cells' CPU is the process's own
    assert cpu["grid_cells"] == n and cpu["cells_simulated"] == summary["run"]["cells_simulated"] > 0
    assert 0 < cpu["picture_s"] <= cpu["outputs_s"]  # the picture is one of the outputs
    grown = cpu["cells_s"] + cpu["outputs_s"] - cpu["picture_s"]  # each rounded to the millisecond
    assert cpu["ms_per_cell"] == pytest.approx(1000 * grown / n, abs=3.0 / n)
    line = [x for x in done.stderr.splitlines() if x.startswith("CPU: ")]
    assert len(line) == 1 and f"{n} cells" in line[0] and "start-up" in line[0] and "picture" in line[0], done.stderr


def test_in_process_run_and_quiet(town: Path, tmp_path: Path) -> None:
    """Through the CLI in this process (as a library caller would run it): the phases sum to at most the CPU this
    process spent; -q prints nothing, the summary still records them."""
    start = time.process_time()
    result = CliRunner().invoke(cli, ["analyze", str(town), "-o", str(tmp_path / "o"), "--samples", "2", "-q"])
    end = time.process_time()
    assert result.exit_code == 0, result.output
    assert result.output == ""
    cpu = json.loads((tmp_path / "o" / "summary.json").read_text())["cpu"]
    # start-up counts from this process's start (the CLI's convention): at most all of its CPU so far.
    assert sum(cpu[f"{phase}_s"] for phase in PHASES) <= end + 0.01
    assert cpu["cells_s"] + cpu["outputs_s"] <= end - start + 0.01


def test_phases_accumulate_and_refuse_unknown_names() -> None:
    phases = CpuPhases()
    sum(k * k for k in range(200_000))  # some CPU to see
    first = phases.close("cells")
    second = phases.close("cells")
    assert first > 0 and second >= 0
    assert phases.total("cells") == pytest.approx(first + second)
    phases.workers = 2.0
    assert phases.total("cells") == pytest.approx(first + second + 2.0) and phases.total("outputs") == 0
    with pytest.raises(ValueError, match="unknown phase"):
        phases.close("lunch")


@pytest.mark.slow
def test_a_local_clusters_workers_are_counted(town: Path, tmp_path: Path) -> None:
    """With --jobs, the cells' CPU is mostly the workers' tasks': counted in ``cells`` and shown apart."""
    pytest.importorskip("distributed")
    result = CliRunner().invoke(cli, ["analyze", str(town), "-o", str(tmp_path / "o"), "--samples", "4", "--jobs",
                                      "2", "-q"])
    assert result.exit_code == 0, result.output
    cpu = json.loads((tmp_path / "o" / "summary.json").read_text())["cpu"]
    assert cpu["workers_s"] > 0 and cpu["cells_s"] >= cpu["workers_s"]
