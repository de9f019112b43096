"""Output paths never destroy inputs; outputs are whole or absent, with the umask's mode; options and JSON are strict.

Everything runs through the ``mapdb`` command on real files: a map built from a tiny OSM document, the
paper's map and images simulated from it.  For every refused clash the input's bytes are compared
before and after.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from clichecks import assert_one_line_error as one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import small_town

from mapdb.errors import MapdbIOError
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.outputs import atomic_open, atomic_path, check_outputs, remove_stale_temporaries
from mapdb.simulation.documents import write_images
from mapdb.simulation.simulate import paper_map


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def assert_one_line_error(result, *needles: str) -> str:
    """The only line on stderr, which names the real path, never the temporary one."""
    line = one_line_error(result, *needles, alone=True)
    assert ".tmp" not in line
    return line


def hidden_files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """town.osm and its map (built by the CLI), labels.toml, the paper's map and 4 images simulated on it."""
    d = tmp_path_factory.mktemp("outputs")
    town = small_town(d / "town.osm")
    labels = d / "labels.toml"
    labels.write_text("")
    town_map = d / "town.mapdb"
    assert run("build", town, "-o", town_map, "-q").exit_code == 0
    paper = d / "paper.mapdb"
    write_map(paper, paper_map())
    images = d / "images.jsonl"
    assert run("simulate", paper, "-o", images, "--n", "4", "-q").exit_code == 0
    return {"dir": d, "town": town, "labels": labels, "town_map": town_map, "paper": paper, "images": images}


# ------------------------------------------------------------------------------------------ clashes


@pytest.mark.parametrize(("args", "victim"), [
    (["build", "{town}", "-o", "{town}"], "town"),
    (["build", "{town}", "-o", "{town}", "--overwrite"], "town"),
    (["build", "{town}", "--labels", "{labels}", "-o", "{labels}", "--overwrite"], "labels"),
    (["simulate", "{paper}", "-o", "{paper}"], "paper"),
    (["evaluate", "{paper}", "{images}", "--outcomes", "{paper}"], "paper"),
    (["evaluate", "{paper}", "{images}", "--outcomes", "{images}"], "images"),
    (["export", "{paper}", "-o", "{paper}"], "paper"),
])
def test_an_output_that_is_an_input_is_refused(files: dict[str, Path], args: list[str], victim: str) -> None:
    before = digest(files[victim])
    result = run(*(a.format(**files) for a in args))
    assert_one_line_error(result, "is the same file as input", "choose another output path")
    assert digest(files[victim]) == before
    assert hidden_files(files["dir"]) == []


@pytest.mark.parametrize(("command", "victim", "suffix"), [
    ("build", "town", ".mapdb"), ("simulate", "paper", ".jsonl"), ("evaluate-outcomes", "images", ".jsonl"),
    ("evaluate-plot", "paper", ".png"), ("export", "paper", ".gpkg"),
])
def test_symlinks_and_hard_links_to_an_input_are_seen_through(
    files: dict[str, Path], tmp_path: Path, command: str, victim: str, suffix: str
) -> None:
    target = files[victim]
    before = digest(target)
    for kind in ("symlink", "hardlink"):
        link = tmp_path / f"{kind}{suffix}"
        (link.symlink_to if kind == "symlink" else link.hardlink_to)(target)
        args = {
            "build": ["build", files["town"], "-o", link, "--overwrite"],
            "simulate": ["simulate", files["paper"], "-o", link],
            "evaluate-outcomes": ["evaluate", files["paper"], files["images"], "--outcomes", link],
            "evaluate-plot": ["evaluate", files["paper"], files["images"], "--plot", link],
            "export": ["export", files["paper"], "-o", link],
        }[command]
        assert_one_line_error(run(*args), str(link), "is the same file as input")
        assert digest(target) == before
        assert link.exists() and link.is_symlink() == (kind == "symlink")


def test_one_file_given_as_two_outputs_is_refused(files: dict[str, Path], tmp_path: Path) -> None:
    both = tmp_path / "both.png"
    result = run("evaluate", files["paper"], files["images"], "--outcomes", both, "--plot", both)
    assert_one_line_error(result, "is the same file as output")
    assert not both.exists()


def test_check_outputs_compares_paths_not_yet_written(tmp_path: Path) -> None:
    # A source that does not exist yet cannot be compared by inode; its resolved path still clashes.
    with pytest.raises(ValueError, match="same file as input"):
        check_outputs([tmp_path / "sub" / ".." / "a.osm"], [tmp_path / "a.osm"])
    check_outputs([None, "-", tmp_path / "b.mapdb"], ["-", None, tmp_path / "a.osm"])


# ------------------------------------------------------------------------------------------ --overwrite


def test_build_over_an_existing_map_needs_overwrite(files: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    assert run("build", files["town"], "-o", out, "-q").exit_code == 0
    before = digest(out)
    assert_one_line_error(run("build", files["town"], "-o", out, "--crs", "EPSG:3857"), str(out), "--overwrite")
    assert digest(out) == before
    with open_map(out) as m:
        assert m.crs == "EPSG:32632"
    assert run("build", files["town"], "-o", out, "--crs", "EPSG:3857", "--overwrite", "-q").exit_code == 0
    with open_map(out) as m:
        assert m.crs == "EPSG:3857"
    assert hidden_files(tmp_path) == []


def test_bench_save_map_over_an_existing_file_needs_overwrite(files: dict[str, Path], tmp_path: Path) -> None:
    existing = tmp_path / "keep.mapdb"
    existing.write_bytes(files["town_map"].read_bytes())
    before = digest(existing)
    assert_one_line_error(run("bench", "paper", "--n", "1", "--paper-images", "0", "--save-map", existing),
                          "--overwrite")
    assert digest(existing) == before


def test_symlinked_output_is_written_through(files: dict[str, Path], tmp_path: Path) -> None:
    real = tmp_path / "real.jsonl"
    real.write_text("old\n")
    link = tmp_path / "latest.jsonl"
    link.symlink_to(real)
    assert run("simulate", files["paper"], "-o", link, "--n", "2", "-q", "--overwrite").exit_code == 0
    assert link.is_symlink() and len(real.read_text().splitlines()) == 2


# ------------------------------------------------------------------------------------------ mode, temporaries


@pytest.mark.parametrize("umask", [0o002, 0o027, 0o077])
def test_outputs_get_the_mode_of_the_umask(files: dict[str, Path], tmp_path: Path, umask: int) -> None:
    old = os.umask(umask)
    try:
        outs = [tmp_path / "m.mapdb", tmp_path / "i.jsonl", tmp_path / "o.gpkg", tmp_path / "o.csv",
                tmp_path / "e.jsonl", tmp_path / "e.png"]
        assert run("build", files["town"], "-o", outs[0], "-q").exit_code == 0
        assert run("simulate", files["paper"], "-o", outs[1], "--n", "2", "-q").exit_code == 0
        assert run("export", files["paper"], "-o", outs[2]).exit_code == 0  # written by SQLite under its own mode
        assert run("export", files["paper"], "-o", outs[3]).exit_code == 0
        assert run("evaluate", files["paper"], outs[1], "-q", "--outcomes", outs[4], "--plot", outs[5]).exit_code == 0
    finally:
        os.umask(old)
    for out in outs:
        assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask, out


def test_temporaries_of_killed_runs_are_cleaned_up(files: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    assert run("build", files["town"], "-o", out, "-q").exit_code == 0
    before = digest(out)
    # A real crash: a writer killed with SIGKILL in the middle of its write.
    writer = subprocess.Popen(
        [sys.executable, "-c",
         "import sys, time\nfrom mapdb.outputs import atomic_open\n"
         "with atomic_open(sys.argv[1], 'wb') as f:\n"
         "    f.write(b'half a map'); f.flush(); print('writing', flush=True); time.sleep(60)\n",
         str(out)],
        stdout=subprocess.PIPE, text=True,
    )
    assert writer.stdout.readline().strip() == "writing"
    writer.kill()
    writer.wait()
    writer.stdout.close()
    left = hidden_files(tmp_path)
    assert len(left) == 1 and left[0].startswith(f".m.mapdb.{writer.pid}.")
    assert digest(out) == before  # the kill never touches the earlier map
    # A temporary of a live process (this one) is someone's write in progress: it stays.
    live = tmp_path / f".m.mapdb.{os.getpid()}.0123abcd.tmp"
    live.write_bytes(b"")
    assert run("build", files["town"], "-o", out, "--overwrite", "-q").exit_code == 0
    assert hidden_files(tmp_path) == [live.name]


# ------------------------------------------------------------------------------------------ bad places


@pytest.mark.parametrize("command", ["build", "simulate", "evaluate-outcomes", "evaluate-plot", "export"])
def test_an_unwritable_place_is_reported_with_the_real_path(
    files: dict[str, Path], tmp_path: Path, command: str
) -> None:
    blocker = tmp_path / "afile"
    blocker.write_text("a regular file, not a directory\n")
    suffix = {"build": ".mapdb", "evaluate-plot": ".png", "export": ".csv"}.get(command, ".jsonl")
    out = blocker / f"out{suffix}"
    args = {
        "build": ["build", files["town"], "-o", out],
        "simulate": ["simulate", files["paper"], "-o", out],
        "evaluate-outcomes": ["evaluate", files["paper"], files["images"], "--outcomes", out],
        "evaluate-plot": ["evaluate", files["paper"], files["images"], "--plot", out],
        "export": ["export", files["paper"], "-o", out],
    }[command]
    assert_one_line_error(run(*args), f"{out}: cannot write")
    assert hidden_files(tmp_path) == []


def test_a_write_error_names_the_real_path() -> None:
    # /dev/full accepts opening and fails every write (ENOSPC): the device is written in place.
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    with pytest.raises(MapdbIOError, match=r"^/dev/full: cannot write \(No space left on device\)$"):
        with atomic_open("/dev/full") as f:
            f.write("x" * 100_000)


def test_a_writers_own_error_is_renamed_to_the_real_path(tmp_path: Path) -> None:
    out = tmp_path / "plot.png"
    with pytest.raises(MapdbIOError) as caught:
        with atomic_path(out, keep_suffix=True) as tmp:
            assert tmp.name.endswith(".tmp.png") and tmp.parent == tmp_path
            raise MapdbIOError(f"{tmp}: cannot write plot (disk on fire)")
    assert str(caught.value) == f"{out}: cannot write plot (disk on fire)"
    assert list(tmp_path.iterdir()) == []


def test_a_fifo_output_is_refused_without_blocking(files: dict[str, Path], tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.jsonl"
    os.mkfifo(fifo)
    # In a child process with a timeout: the bug this guards against is a command that never returns.
    for args in (["simulate", files["paper"], "-o", fifo, "--n", "2"],
                 ["evaluate", files["paper"], files["images"], "--outcomes", fifo]):
        result = subprocess.run([sys.executable, "-m", "mapdb_cli", *map(str, args)], capture_output=True, text=True,
                                timeout=120)
        assert result.returncode == 1 and result.stderr.strip() == f"mapdb: error: {fifo}: is a FIFO; an output " \
                                                                   "must be a regular file"
    assert stat.S_ISFIFO(fifo.stat().st_mode)


def test_a_directory_output_is_refused(files: dict[str, Path], tmp_path: Path) -> None:
    assert_one_line_error(run("simulate", files["paper"], "-o", tmp_path, "--n", "2"), "is a directory")


def test_dev_null_is_written_in_place(files: dict[str, Path]) -> None:
    assert run("simulate", files["paper"], "-o", os.devnull, "--n", "2", "-q").exit_code == 0
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)


# ------------------------------------------------------------------------------------------ no partial output


def test_a_failing_command_leaves_no_output(files: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "images.jsonl"
    # A thin map cannot show a million objects: the command fails after opening the map.
    assert_one_line_error(run("simulate", files["town_map"], "-o", out, "--n", "3", "--min-objects", "1000000"))
    assert list(tmp_path.iterdir()) == []
    previous = tmp_path / "objects.csv"
    previous.write_text("earlier export\n")
    assert_one_line_error(run("export", files["paper"], "-o", previous, "--bbox", "0,0,0.001,0.001", "--overwrite"),
                          "no objects")
    assert previous.read_text() == "earlier export\n"
    assert hidden_files(tmp_path) == []


def test_a_write_failing_half_way_leaves_the_earlier_file(tmp_path: Path) -> None:
    out = tmp_path / "images.jsonl"
    out.write_text("earlier\n")
    good = {"id": "a", "objects": []}
    # The second document cannot be written as strict JSON: the first line is already in the temporary file.
    with pytest.raises(ValueError, match="JSON"):
        write_images([good, {"id": "b", "radius": float("nan")}], out)
    assert out.read_text() == "earlier\n"
    assert hidden_files(tmp_path) == []


# ------------------------------------------------------------------------------------------ strict options, JSON


@pytest.mark.parametrize("args", [
    ["build", "{town}", "-o", "{tmp}/m.mapdb", "--quantum", "nan"],
    ["build", "{town}", "-o", "{tmp}/m.mapdb", "--min-area", "inf"],
    ["build", "{town}", "-o", "{tmp}/m.mapdb", "--min-area", "nan"],
    ["simulate", "{paper}", "--yaw", "nan"],
    ["simulate", "{paper}", "--yaw", "-inf"],
    ["simulate", "{paper}", "--with-prior", "inf"],
    ["simulate", "{paper}", "--with-prior", "nan"],
    ["simulate", "{paper}", "--altitude", "nan"],
    ["simulate", "{paper}", "--altitude", "50:inf"],
    ["simulate", "{paper}", "--fov", "nan"],
    ["simulate", "{paper}", "--pixel-std", "nan"],
    ["simulate", "{paper}", "--attitude-std", "inf"],
    ["simulate", "{paper}", "--miss-rate", "nan"],
    ["simulate", "{paper}", "--spurious-rate", "nan"],
    ["simulate", "{paper}", "--label-noise", "NaN"],
    ["evaluate", "{paper}", "{images}", "--fp-threshold", "nan"],
    ["evaluate", "{paper}", "{images}", "--fp-threshold", "Infinity"],
    ["bench", "paper", "--budget", "inf"],
    ["bench", "paper", "--with-prior", "nan"],
    ["bench", "paper", "--yaw", "nan"],
])
def test_non_finite_option_values_are_usage_errors(files: dict[str, Path], tmp_path: Path, args: list[str]) -> None:
    values = {"town": files["town"], "paper": files["paper"], "images": files["images"], "tmp": tmp_path}
    result = run(*(a.format(**values) for a in args))
    assert result.exit_code == 2, result.output
    assert "finite" in result.stderr or "not in the range" in result.stderr, result.stderr
    assert list(tmp_path.iterdir()) == []


def _strict(text: str):
    def refuse(constant: str):
        raise AssertionError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


def test_json_out_is_strict_even_for_non_finite_input(files: dict[str, Path], tmp_path: Path) -> None:
    # An images file (JSON allows NaN in Python's reader) whose truth carries a NaN bound error.
    docs = [json.loads(line) for line in files["images"].read_text().splitlines()]
    docs[0]["truth"]["bound"] = {"x": 0.0, "y": 0.0, "error_m": float("nan"), "n": 3}
    images = tmp_path / "nan-bound.jsonl"
    images.write_text("".join(json.dumps(d) + "\n" for d in docs))
    outcomes = tmp_path / "outcomes.jsonl"
    result = run("evaluate", files["paper"], images, "--json", "-q", "--outcomes", outcomes)
    assert result.exit_code == 0, result.output
    summary = _strict(result.stdout)
    assert summary["images"] == 4
    rows = [_strict(line) for line in outcomes.read_text().splitlines()]
    assert len(rows) == 4 and rows[0]["bound_error_m"] is None
    assert _strict(run("info", files["paper"], "--json").stdout)["objects"] == len(paper_map())
    out = tmp_path / "sim.jsonl"
    assert run("simulate", files["paper"], "-o", out, "--n", "3", "--yaw", "1e308", "--with-prior", "2e7",
               "-q").exit_code == 0
    assert len([_strict(line) for line in out.read_text().splitlines()]) == 3


def test_a_killed_builds_spill_folder_is_removed_and_a_live_ones_kept(tmp_path: Path) -> None:
    """A SIGKILLed streaming build leaves its spilled records in ``.NAME.PID.XXXX.spill`` beside the output:
    the next write to that output removes it when that process is gone, and leaves a running one's alone."""
    target = tmp_path / "world.mapdb"
    dead = tmp_path / ".world.mapdb.999999999.k2j_x9ab.spill"
    live = tmp_path / f".world.mapdb.{os.getpid()}.q1w2e3r4.spill"
    other = tmp_path / ".other.mapdb.999999999.k2j_x9ab.spill"
    for folder in (dead, live, other):
        folder.mkdir()
        (folder / "1.bin").write_bytes(b"records")
    assert remove_stale_temporaries(target) == 1
    assert not dead.exists() and live.exists() and other.exists()
