"""The output rule of every command, and what ends a command early.

* An existing output (file or folder) is replaced only with ``--overwrite``: without it, one line naming the
  output and the option, exit status 1, the old bytes untouched and no temporary file left; with it, the
  output is replaced.  ``-`` (stdout) and ``/dev/null`` are exempt.  An output that is one of the command's
  inputs (the map's ``.qidx`` included) is refused even with ``--overwrite``.
* A read-only folder (a read-only bind mount in a private mount namespace, as root cannot be stopped by
  permissions) and a full disk (a file-size limit, EFBIG; and a 64 KiB tmpfs, ENOSPC) name the user's output,
  never the temporary file.
* SIGINT and SIGTERM end a command with 130 and 143, one line on stderr and nothing half-written left.
* ``mapdb merge`` reads a map given twice once, with ``build``'s warning.

Every case runs the real command on files written here: a tiny OSM town, the paper's map, images, a flight and
a mask simulated or drawn from them.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import resource
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner
from mapdb_cli.main import COMMANDS, TWO_WORD_COMMANDS, cli
from osmxml import small_town

from mapdb.build.merge import merge_maps
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.objects import Objects
from mapdb.simulation.simulate import paper_map

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def hidden(directory: Path) -> list[str]:
    """Hidden files and folders: temporaries (``.NAME.PID.X.tmp``, work folders) that must never be left."""
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


def mapdb_process(*args: object, cwd: Path, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mapdb_cli", *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, **kwargs)


def lattice_map(path: Path) -> Path:
    """Buildings 25 m apart over 150 x 150 m, and as many at random beside them: an analysis of a few cells."""
    g = np.arange(12.5, 150.0, 25.0)
    gx, gy = np.meshgrid(g, g)
    rng = np.random.default_rng(0)
    x = np.concatenate([gx.ravel(), 170.0 + rng.uniform(0, 150, gx.size)]) + 500_000.0
    y = np.concatenate([gy.ravel(), rng.uniform(0, 150, gx.size)]) + 5_000_000.0
    write_map(path, Objects.from_names(x, y, ["building"] * x.size, crs="EPSG:32631"))
    return path


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The inputs of every writing command, made by the commands themselves where they can be."""
    from PIL import Image

    d = tmp_path_factory.mktemp("rule")
    town = small_town(d / "town.osm")
    files = {"town": town, "town_map": d / "town.mapdb", "paper": d / "paper.mapdb", "images": d / "images.jsonl",
             "flight": d / "flight.jsonl", "mask": d / "mask.png", "lattice": lattice_map(d / "lattice.mapdb")}
    assert run("build", town, "-o", files["town_map"], "-q").exit_code == 0
    write_map(files["paper"], paper_map())
    assert run("index", files["paper"], "-q").exit_code == 0  # paper.mapdb.qidx: an input of every query
    assert run("simulate", files["paper"], "-o", files["images"], "--n", "2", "-q").exit_code == 0
    assert run("simulate", "flight", files["paper"], "-o", files["flight"], "--length", "10", "-q").exit_code == 0
    mask = np.zeros((64, 64), np.uint8)
    mask[8:20, 8:20] = mask[30:50, 36:56] = 255
    Image.fromarray(mask).save(files["mask"])
    files["dir"] = d
    return files


# Every command that writes a file: (command, its arguments with {out} the output, the output's ending, what the
# refusal calls it).  An ending "/" is a folder.
WRITERS = [
    ("build", ["build", "{town}", "-o", "{out}", "-q"], ".mapdb", "map"),
    ("merge", ["merge", "{town_map}", "-o", "{out}", "-q"], ".mapdb", "map"),
    ("export", ["export", "{paper}", "-o", "{out}"], ".csv", "file"),
    ("index", ["index", "{paper}", "-o", "{out}", "-q"], ".qidx", "index"),
    ("simulate", ["simulate", "{paper}", "-o", "{out}", "--n", "2", "-q"], ".jsonl", "file"),
    ("simulate --masks-dir", ["simulate", "{town_map}", "--render", "masks", "--source", "{town}", "--masks-dir",
                              "{out}", "-o", "-", "--n", "1", "--altitude", "60", "-q"], "/", "output folder"),
    ("simulate flight", ["simulate", "flight", "{paper}", "-o", "{out}", "--length", "10", "-q"], ".jsonl", "file"),
    ("objects", ["objects", "{mask}", "--label", "building", "-o", "{out}", "-q"], ".jsonl", "file"),
    ("query", ["query", "{paper}", "{images}", "-o", "{out}", "-q"], ".jsonl", "file"),
    ("show", ["show", "{paper}", "{images}", "-o", "{out}"], ".png", "file"),
    ("navigate", ["navigate", "{paper}", "{flight}", "-o", "{out}", "--particles", "100", "-q"], ".jsonl", "file"),
    ("navigate --geojson", ["navigate", "{paper}", "{flight}", "-o", os.devnull, "--geojson", "{out}",
                            "--particles", "100", "-q"], ".geojson", "file"),
    ("navigate --plot", ["navigate", "{paper}", "{flight}", "-o", os.devnull, "--plot", "{out}", "--particles",
                         "100", "-q"], ".png", "file"),
    ("evaluate --outcomes", ["evaluate", "{paper}", "{images}", "--outcomes", "{out}", "-q"], ".jsonl", "file"),
    ("evaluate --plot", ["evaluate", "{paper}", "{images}", "--plot", "{out}", "-q"], ".png", "file"),
    ("analyze", ["analyze", "{lattice}", "-o", "{out}", "--samples", "1", "--cell", "150", "-q"], "/",
     "output folder"),
    ("bench paper --save-map", ["bench", "paper", "--n", "1", "--paper-images", "0", "--cases", "1", "--save-map",
                                "{out}", "-q"], ".mapdb", "map"),
]


@pytest.mark.parametrize(("args", "ending", "what"), [case[1:] for case in WRITERS], ids=[c[0] for c in WRITERS])
def test_an_existing_output_is_replaced_only_with_overwrite(world: dict[str, Path], tmp_path: Path, args: list[str],
                                                            ending: str, what: str) -> None:
    folder = ending == "/"
    out = tmp_path / ("out" if folder else f"out{ending}")
    kept = out / "keep.txt" if folder else out
    kept.parent.mkdir(exist_ok=True)
    kept.write_bytes(b"someone's work\n")
    before, inode = digest(kept), out.stat().st_ino
    argv = [a.format(out=out, **world) for a in args]
    refused = run(*argv)
    assert refused.exit_code == 1, refused.output
    assert refused.stderr == f"mapdb: error: {out}: exists; pass --overwrite to replace this {what}\n"
    assert refused.stdout == ""
    assert digest(kept) == before
    assert hidden(tmp_path) == []
    replaced = run(*argv, "--overwrite")
    assert replaced.exit_code == 0, replaced.output
    if folder:
        assert not kept.exists() and any(out.iterdir())
    else:
        assert out.stat().st_size > 0 and digest(out) != before
    # A new file (or folder) renamed into place, not the old one rewritten where it was.
    assert out.stat().st_ino != inode
    assert hidden(tmp_path) == []


def test_the_default_index_beside_the_map_is_replaced_only_with_overwrite(world: dict[str, Path],
                                                                          tmp_path: Path) -> None:
    map_path = tmp_path / "a.mapdb"
    map_path.write_bytes(world["paper"].read_bytes())
    index = tmp_path / "a.mapdb.qidx"
    index.write_bytes(b"an index built with other options\n")
    refused = run("index", map_path, "-q")
    assert refused.exit_code == 1
    assert refused.stderr == f"mapdb: error: {index}: exists; pass --overwrite to replace this index\n"
    assert index.read_bytes() == b"an index built with other options\n"
    assert run("index", map_path, "-q", "--overwrite").exit_code == 0
    assert index.read_bytes()[:4] != b"an i" and hidden(tmp_path) == []


def output_options(command: click.Command) -> set[str]:
    """The parameters of a command that name a file or folder it writes."""
    writes = {"output", "outdir", "geojson_file", "plot_file", "outcomes_file", "save_map", "masks_dir"}
    return {p.name for p in command.params if p.name in writes}


def every_command() -> dict[str, click.Command]:
    ctx = click.Context(cli)
    found: dict[str, click.Command] = {}
    for name in COMMANDS:
        command = cli.get_command(ctx, name)
        assert command is not None
        subcommands = command.commands if isinstance(command, click.Group) else {}
        found.update({f"{name} {sub}": c for sub, c in subcommands.items()} or {name: command})
    for words in TWO_WORD_COMMANDS:
        found[" ".join(words)] = cli.resolve_command(ctx, list(words))[1]
    return found


def test_every_command_that_writes_takes_overwrite_and_is_tested_here() -> None:
    writers = {name for name, command in every_command().items() if output_options(command)}
    assert writers == {case[0].split(" -")[0] for case in WRITERS}
    for name in writers:
        assert "overwrite" in {p.name for p in every_command()[name].params}, name


@pytest.mark.parametrize("args", [
    ["query", "{paper}", "{images}", "-o", "{paper}"],
    ["query", "{paper}", "{images}", "-o", "{paper}.qidx"],  # the index a lookup reads is an input too
    ["objects", "{mask}", "--label", "building", "-o", "{mask}"],
    ["index", "{paper}", "-o", "{paper}"],
    ["export", "{paper}", "-o", "{paper}"],
    ["simulate", "flight", "{paper}", "-o", "{paper}"],
    ["navigate", "{paper}", "{flight}", "--geojson", "{flight}"],
    ["evaluate", "{paper}", "{images}", "--outcomes", "{paper}.qidx"],
    ["merge", "{town_map}", "-o", "{town_map}"],
])
def test_no_command_destroys_one_of_its_inputs_even_with_overwrite(world: dict[str, Path], args: list[str]) -> None:
    inputs = [p for p in world["dir"].iterdir() if p.is_file()]
    before = {p: digest(p) for p in inputs}
    result = run(*(a.format(**world) for a in args), "--overwrite")
    assert result.exit_code == 1
    assert result.stderr.count("\n") == 1 and "is the same file as input" in result.stderr, result.stderr
    assert {p: digest(p) for p in inputs} == before
    assert hidden(world["dir"]) == []


def test_stdout_and_dev_null_are_never_refused(world: dict[str, Path]) -> None:
    assert run("simulate", world["paper"], "-o", os.devnull, "--n", "1", "-q").exit_code == 0
    streamed = run("query", world["paper"], world["images"], "-q")
    assert streamed.exit_code == 0 and len(streamed.stdout.splitlines()) == 2


# ------------------------------------------------------------------------------------------ N9: the real path


def namespace_run(setup: str, args: list[object], cwd: Path,
                  preexec_fn: Callable[[], None] | None = None) -> subprocess.CompletedProcess:
    """``mapdb ARGS`` after the shell commands ``setup``, in a private mount namespace (``unshare --mount``):
    mounts made there are seen by that command alone.  Skips the test where the namespace cannot be made."""
    probe = subprocess.run(["unshare", "--mount", "sh", "-c", f"{setup} && true"], cwd=cwd, capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private mount namespace here (unshare --mount: {probe.stderr.decode().strip()[:80]})")
    command = " ".join(f"'{a}'" for a in [sys.executable, "-m", "mapdb_cli", *map(str, args)])
    return subprocess.run(["unshare", "--mount", "sh", "-c", f"{setup} && exec {command}"], cwd=cwd,
                          capture_output=True, text=True, timeout=300, preexec_fn=preexec_fn)


@pytest.mark.parametrize("where", ["beside the map", "-o"])
def test_an_index_into_a_read_only_folder_names_the_index(world: dict[str, Path], tmp_path: Path, where: str) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    map_path = locked / "a.mapdb"
    map_path.write_bytes(world["paper"].read_bytes())
    # Root ignores permission bits; a read-only bind mount stops everyone (EROFS).
    read_only = "mount --bind locked locked && mount -o remount,ro,bind locked locked"
    args = ["index", "locked/a.mapdb"] if where == "beside the map" else ["index", world["paper"], "-o",
                                                                          "locked/b.qidx"]
    done = namespace_run(read_only, args, tmp_path)
    shown = "locked/a.mapdb.qidx" if where == "beside the map" else "locked/b.qidx"
    assert done.returncode == 1, done.stderr
    assert done.stderr == f"mapdb: error: {shown}: cannot write (Read-only file system)\n"
    assert sorted(p.name for p in locked.iterdir()) == ["a.mapdb"]


def _file_size_limit() -> None:
    # Writes past 16 KiB fail (EFBIG) as they do on a full disk (ENOSPC); Python ignores SIGXFSZ already, and
    # says so here for clarity.
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (16384, 16384))


@pytest.mark.parametrize("disk", ["file-size limit", pytest.param("full tmpfs", marks=pytest.mark.slow)])
def test_analyze_on_a_full_disk_names_the_output_folder(world: dict[str, Path], tmp_path: Path, disk: str) -> None:
    small = tmp_path / "small"
    small.mkdir()
    args = ["analyze", world["lattice"], "-o", "small/an", "--samples", "1", "--cell", "150", "-q"]
    if disk == "file-size limit":
        done = subprocess.run([sys.executable, "-m", "mapdb_cli", *map(str, args)], cwd=tmp_path, text=True,
                              capture_output=True, timeout=300, preexec_fn=_file_size_limit)
        reason = "(File too large)"
    else:
        done = namespace_run("mount -t tmpfs -o size=64k tmpfs small", args, tmp_path)
        reason = "(No space left on device)"
    assert done.returncode == 1, done.stderr
    line = done.stderr.strip()
    assert done.stderr.count("\n") == 1 and line.startswith("mapdb: error: small/an/") and line.endswith(reason), line
    assert ".tmp" not in line and "Traceback" not in done.stderr
    assert list(small.iterdir()) == []


# ------------------------------------------------------------------------------------------ N12: signals


def wait_for(condition: Callable[[], bool], proc: subprocess.Popen, what: str, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"{what} did not happen (exit status {proc.poll()}): {proc.stderr.read().decode()[-500:]}")
        time.sleep(0.05)


def assert_ended_by(proc: subprocess.Popen, signum: int) -> None:
    """Exit status 128 + the signal, one line on stderr after whatever progress came before, no traceback."""
    _, stderr = proc.communicate(timeout=120)
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, stderr
    assert stderr.decode().splitlines()[-1] == f"mapdb: interrupted by {name}; no partial output left"
    assert b"Traceback" not in stderr


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_answers_are_written_leaves_no_answers_file(world: dict[str, Path], tmp_path: Path,
                                                                    signum: int) -> None:
    # A stream from a pipe kept open: the answers file is being written (its temporary file exists) and the
    # command waits for the next line.
    proc = mapdb_process("query", world["paper"], "-", "-o", "answers.jsonl", cwd=tmp_path, stdin=subprocess.PIPE)
    assert proc.stdin is not None
    proc.stdin.write(world["images"].read_bytes().splitlines()[0] + b"\n")
    proc.stdin.flush()
    wait_for(lambda: hidden(tmp_path) != [], proc, "the answers' temporary file")
    proc.send_signal(signum)
    assert_ended_by(proc, signum)
    assert list(tmp_path.iterdir()) == []


def test_sigint_during_a_build_keeps_the_earlier_map(tmp_path: Path) -> None:
    out = tmp_path / "h.mapdb"
    out.write_bytes(b"the earlier map\n")
    proc = mapdb_process("build", SAMPLE, "-o", out, "--overwrite", cwd=tmp_path)
    assert proc.stderr is not None
    first = proc.stderr.readline()  # the first progress line: the build is under way
    assert first.startswith(b"reading "), first
    proc.send_signal(signal.SIGINT)
    assert_ended_by(proc, signal.SIGINT)
    assert out.read_bytes() == b"the earlier map\n" and hidden(tmp_path) == []


def test_sigterm_during_a_simulation_leaves_nothing(world: dict[str, Path], tmp_path: Path) -> None:
    proc = mapdb_process("simulate", world["paper"], "-o", "images.jsonl", "--n", "20000", cwd=tmp_path)
    assert proc.stderr is not None
    first = proc.stderr.readline()  # "simulate: 2000/20000": a tenth done
    assert first.startswith(b"simulate: "), first
    proc.send_signal(signal.SIGTERM)
    assert_ended_by(proc, signal.SIGTERM)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------ N10: merge


def test_merge_reads_a_map_given_twice_once(world: dict[str, Path], tmp_path: Path) -> None:
    copy = tmp_path / "copy.mapdb"
    copy.write_bytes(world["town_map"].read_bytes())
    town = str(world["town_map"])
    result = run("merge", town, town, copy, "-o", tmp_path / "m.mapdb")
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("mapdb: warning: ")]
    assert warnings == [f"mapdb: warning: {town}: given twice; read once",
                        f"mapdb: warning: {copy}: the same content as map {town} "
                        f"(SHA-256 {digest(copy)[:16]}...); read once"]
    summary = json.loads(result.stdout)
    with open_map(world["town_map"]) as m:
        count = len(m.all())
    assert summary["inputs"] == [{"name": "town.mapdb", "objects": count, "kept": count}]
    assert summary["count"] == count and summary["duplicates"] == 0
    # The library says the same in its summary.
    again = merge_maps([world["town_map"], copy], tmp_path / "again.mapdb")
    assert len(again["warnings"]) == 1 and "the same content as map" in again["warnings"][0]


# ------------------------------------------------------------------------------------------ the CLI's imports


def test_the_cli_modules_import_each_other_one_way() -> None:
    """No cycle among the command modules, counting imports inside functions (options.py imported simulate.py
    inside its functions, and simulate.py imported options.py)."""
    graph: dict[str, set[str]] = {}
    for path in sorted((REPO / "cli").glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        graph[path.stem] = {node.module.split(".")[0] for node in ast.walk(tree)
                            if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module}
    assert graph["options"] == set()

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        return any(n == goal or (n not in seen and reaches(n, goal, seen | {n})) for n in graph.get(start, ()))

    assert [name for name in graph if reaches(name, name, set())] == []


SWALLOWED = {
    "bare except": """
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except BaseException:  # what some libraries do
            pass
    """,
    "__del__": """
        class Finalized:
            def __del__(self):  # Python prints what is raised here ("Exception ignored in ...") and goes on
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.5)
        Finalized()
    """,
}


@pytest.mark.parametrize("where", SWALLOWED)
def test_a_signal_a_library_swallows_still_ends_with_its_status(tmp_path: Path, where: str) -> None:
    # Python runs a signal handler between any two bytecodes: in a bare ``except:`` of a library or a ``__del__``,
    # the Interrupted it raises is lost and the command goes on.  It still ends with 143, after its work, and
    # with the one line only.
    body = textwrap.indent(textwrap.dedent(SWALLOWED[where]), "    ")
    code = textwrap.dedent("""
        import importlib.machinery, os, signal, sys, time, types
        import click
        import mapdb_cli.main as main

        @click.command()
        def swallow():
    """) + body + "    click.echo('went on')\n" + textwrap.dedent("""
        module = types.ModuleType("mapdb_cli.swallow")
        module.__spec__ = importlib.machinery.ModuleSpec("mapdb_cli.swallow", None)
        module.swallow = swallow
        sys.modules["mapdb_cli.swallow"] = module
        main.COMMANDS["swallow"] = "A command whose library swallows the interruption."
        main.cli(["swallow"])
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert (done.returncode, done.stdout) == (143, "went on\n")
    assert done.stderr == "mapdb: interrupted by SIGTERM; no partial output left\n"


def test_a_signal_after_the_command_while_python_shuts_down_ends_with_its_status(world: dict[str, Path],
                                                                                 tmp_path: Path) -> None:
    # The command is done (its output complete); the signal comes while the interpreter shuts down (an atexit
    # hook stands for a slow shutdown on a busy machine): the same status and line, not a death by the signal.
    code = textwrap.dedent("""
        import atexit, os, signal, sys, time
        atexit.register(lambda: (os.kill(os.getpid(), signal.SIGTERM), time.sleep(5)))
        sys.argv = ["mapdb", "info", sys.argv[1], "--json"]
        from mapdb_cli.main import cli
        cli()
    """)
    done = subprocess.run([sys.executable, "-c", code, str(world["paper"])], capture_output=True, text=True,
                          timeout=60, cwd=tmp_path)
    assert done.returncode == 143
    with open_map(world["paper"]) as m:
        assert json.loads(done.stdout)["objects"] == len(m.all())  # written whole before the signal
    assert done.stderr == "mapdb: interrupted by SIGTERM; no partial output left\n"
