"""CLI manners and input interop: progress on stderr (a bar on a terminal, lines elsewhere, nothing with -q),
shell completion, outputs refused in missing directories unless --parents, lon/lat priors, priors outside
the map, unknown image labels skipped and counted, warnings for duplicate and far-apart sources."""

from __future__ import annotations

import json
import os
import pty
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import OsmXml, square
from pyproj import Transformer

SAMPLE = Path(__file__).resolve().parent.parent / "sample_maps" / "helsinki.osm.pbf"
# The labels a detector might report that the sample map does not hold.
ALIEN = "helipad"


def run(*args: object, input: str | None = None):
    return CliRunner().invoke(cli, [str(a) for a in args], input=input, catch_exceptions=False)


def in_terminal(*args: object) -> tuple[int, str, str]:
    """Run ``mapdb ARGS`` with stderr on a pseudo-terminal (stdout a pipe): (status, stdout, stderr)."""
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "mapdb_cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=slave, stdin=subprocess.DEVNULL)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # the terminal closes when the process ends
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    out = proc.stdout.read().decode()
    proc.stdout.close()
    return proc.wait(), out, b"".join(chunks).decode()


def town(path: Path, lon: float | None = None, lat: float | None = None) -> Path:
    """A tiny OSM file: four buildings and a park, near the test origin or around (lon, lat)."""
    doc = OsmXml()
    for i, (cx, cy) in enumerate([(0, 0), (60, 10), (20, 80), (90, 70), (150, 40)]):
        tags = {"leisure": "park"} if i == 4 else {"building": "yes"}
        corners = square(cx, cy, 12 if i < 4 else 120)
        if lon is None:
            doc.ring(corners, tags)
        else:  # the same layout moved to (lon, lat), ~1e-5 degrees a metre
            refs = [doc.node(lon + x * 1.2e-5, lat + y * 0.9e-5, lon_lat=True) for x, y in corners]
            doc.way(refs + refs[:1], tags)
    return doc.write(path)


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """The sample map, built once, and simulated images of it (with their truth) that the fast method places."""
    root = tmp_path_factory.mktemp("manners")
    map_path = root / "helsinki.mapdb"
    assert run("build", SAMPLE, "-o", map_path, "-q").exit_code == 0
    images_path = root / "images.jsonl"
    result = run("simulate", map_path, "-o", images_path, "--n", "4", "--min-objects", "8", "--seed", "3", "-q")
    assert result.exit_code == 0, result.output
    images = [json.loads(line) for line in images_path.read_text().splitlines()]
    return map_path, images_path, images


def answers(result) -> list[dict]:
    return [json.loads(line) for line in result.stdout.splitlines()]


def without_truth(image: dict) -> dict:
    return {k: v for k, v in image.items() if k != "truth"}


# --- progress -----------------------------------------------------------------------------------------


def test_build_progress_is_lines_off_a_terminal_and_nothing_with_q(tmp_path: Path) -> None:
    a, b = town(tmp_path / "a.osm"), town(tmp_path / "b.osm", 7.5, 43.8)
    result = run("build", a, b, "-o", tmp_path / "m.mapdb")
    assert result.exit_code == 0, result.output
    json.loads(result.stdout)  # stdout holds the summary only
    lines = result.stderr.splitlines()
    # One count over the build: each source read, the projection, the writing; each step a plain line.
    assert [line for line in lines if line.startswith("build: ")] == [f"build: {i}/4" for i in range(1, 5)]
    assert not any("\r" in line or "[#" in line for line in lines)  # no bar drawn in a log
    assert lines.index("build: 2/4") > next(i for i, line in enumerate(lines) if "from b.osm" in line)
    quiet = run("build", a, b, "-o", tmp_path / "q.mapdb", "-q")
    assert quiet.exit_code == 0 and quiet.stderr == ""


def test_build_draws_a_bar_on_a_terminal_and_an_error_erases_it(tmp_path: Path) -> None:
    status, out, err = in_terminal("build", town(tmp_path / "a.osm"), "-o", tmp_path / "m.mapdb")
    assert status == 0 and json.loads(out)["count"] == 5
    assert "build  [" in err and "3/3" in err and "100%" in err and "\r" in err
    assert "build: 1/3" not in err  # a bar, not lines
    assert "reading " in err and err.rstrip().endswith("\x1b[?25h")  # the cursor is given back
    bad = tmp_path / "b.osm"
    bad.write_text("<osm><node")
    status, out, err = in_terminal("build", town(tmp_path / "a.osm"), bad, "-o", tmp_path / "n.mapdb")
    assert status == 1 and out == ""
    last = err.replace("\r\n", "\n").split("\n")[-2]
    # The bar's line is erased before the error (what a terminal then shows is the error alone) and the
    # cursor is visible again.
    before, erase, shown = last.rpartition("\r\x1b[K")
    assert "build  [" in before and shown.startswith("\x1b[?25hmapdb: error: ") and "b.osm" in shown


@pytest.mark.slow  # 2 s: the paper method on real images.
def test_paper_query_reports_progress_on_stderr_only(sample, tmp_path: Path) -> None:
    map_path, _, images = sample
    two = tmp_path / "two.jsonl"
    small = [{**without_truth(im), "objects": im["objects"][:7]} for im in images[:2]]
    two.write_text("".join(json.dumps(im) + "\n" for im in small))
    result = run("query", map_path, two, "--method", "paper")
    assert result.exit_code == 0, result.output
    assert len(answers(result)) == 2  # stdout: the answers, nothing else
    assert result.stderr.splitlines() == ["localizing (paper method): 1/2", "localizing (paper method): 2/2"]
    one = tmp_path / "one.jsonl"
    one.write_text(json.dumps(small[0]) + "\n")
    assert run("query", map_path, one, "--method", "paper", "-q").stderr == ""
    assert run("query", map_path, two).stderr == ""  # the fast method answers at once: no progress
    # A program streaming frames through stdin gets answers and no chatter.
    streamed = run("query", map_path, "-", "--method", "paper", input=one.read_text())
    assert len(answers(streamed)) == 1 and streamed.stderr == ""
    status, out, err = in_terminal("query", map_path, two, "--method", "paper")
    assert status == 0 and [json.loads(line)["id"] for line in out.splitlines()] == [im["id"] for im in small]
    assert "localizing (paper method)  [" in err and "2/2" in err and "\x1b" not in out


def test_evaluate_progress_goes_to_stderr_and_q_silences_it(sample) -> None:
    map_path, images_path, _ = sample
    result = run("evaluate", map_path, images_path, "--json")
    assert result.exit_code == 0 and json.loads(result.stdout)["images"] == 4
    assert "4/4" in result.stderr
    quiet = run("evaluate", map_path, images_path, "--json", "-q")
    assert quiet.exit_code == 0 and quiet.stderr == ""


# --- completion ---------------------------------------------------------------------------------------


def test_shell_completion_offers_commands_and_options() -> None:
    # Completion is keyed to the installed script's name (the variable is _MAPDB_COMPLETE), as the README uses it.
    mapdb = shutil.which("mapdb")
    if mapdb is None:
        pytest.skip("the mapdb script is not on PATH (pip install -e . puts it there)")

    def complete(words: str, cword: int) -> list[str]:
        env = {**os.environ, "_MAPDB_COMPLETE": "bash_complete", "COMP_WORDS": words, "COMP_CWORD": str(cword)}
        done = subprocess.run([mapdb], env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return [line.split(",", 1)[1] for line in done.stdout.splitlines()]

    assert complete("mapdb bu", 1) == ["build"]
    assert "--prior-crs" in complete("mapdb query m.mapdb i.jsonl --prior", 4)
    source = subprocess.run([mapdb], env={**os.environ, "_MAPDB_COMPLETE": "bash_source"}, capture_output=True,
                            text=True)
    assert "complete -o nosort -F _mapdb_completion mapdb" in source.stdout


# --- outputs in missing directories -------------------------------------------------------------------


def commands_writing(sample, out: Path) -> dict[str, list[object]]:
    map_path, images_path, _ = sample
    return {
        "build": ["build", SAMPLE, "-o", out, "-q"],
        "simulate": ["simulate", map_path, "-o", out, "--n", "2", "-q"],
        "query": ["query", map_path, images_path, "-o", out],
        "evaluate": ["evaluate", map_path, images_path, "--outcomes", out, "-q"],
        "bench": ["bench", "paper", "--save-map", out, "--n", "1", "--cases", "1", "--paper-images", "0", "-q"],
    }


@pytest.mark.parametrize("command", ["build", "simulate", "query", "evaluate", "bench"])
def test_an_output_in_a_missing_directory_is_refused(sample, tmp_path: Path, command: str) -> None:
    out = tmp_path / "no" / "such" / "out.file"
    result = run(*commands_writing(sample, out)[command])
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [f"mapdb: error: {out}: directory {out.parent} does not exist"]
    assert result.stdout == "" and not (tmp_path / "no").exists()


@pytest.mark.parametrize("command", ["build", "simulate", "query", "evaluate"])
def test_parents_makes_the_missing_directories(sample, tmp_path: Path, command: str) -> None:
    out = tmp_path / "no" / "such" / "out.file"
    result = run(*commands_writing(sample, out)[command], "--parents")
    assert result.exit_code == 0, result.output
    assert out.is_file() and out.stat().st_size > 0


# --- lon/lat priors and priors outside the map --------------------------------------------------------


def test_a_prior_in_lon_lat_with_prior_crs(sample) -> None:
    map_path, _, images = sample
    image = images[0]
    truth = image["truth"]
    crs = json.loads(run("info", map_path, "--json").stdout)["crs"]
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(truth["x"] + 40, truth["y"])
    line = json.dumps(without_truth(image)) + "\n"
    prior = f"{lon},{lat},100"
    (placed,) = answers(run("query", map_path, "-", "--prior", prior, "--prior-crs", "EPSG:4326", input=line))
    assert placed["status"] == "ok" and abs(placed["x"] - truth["x"]) < 1 and abs(placed["y"] - truth["y"]) < 1
    # The same numbers taken as map metres: thousands of km off the map, and the answer says so.
    (lost,) = answers(run("query", map_path, "-", "--prior", prior, input=line))
    assert lost["status"] == "rejected"
    assert lost["reason"].startswith(f"prior ({lon:.0f}, {lat:.0f}) is ") and " km outside the map's bounds" in \
        lost["reason"] and "lon, lat?" in lost["reason"]
    distance_km = float(lost["reason"].split(" is ")[1].split(" km")[0].replace(",", ""))
    assert 6_000 < distance_km < 7_000  # Helsinki's UTM northing is ~6,670 km from (25, 60)


def test_prior_crs_values_are_checked(sample) -> None:
    map_path, _, images = sample
    line = json.dumps(without_truth(images[0])) + "\n"
    off = run("query", map_path, "-", "--prior", "25,95,100", "--prior-crs", "EPSG:4326", input=line)
    assert off.exit_code == 2 and "prior.lat: 95.0 is greater than the maximum of 90" in off.stderr
    other = run("query", map_path, "-", "--prior", "1,2,100", "--prior-crs", "EPSG:3857", input=line)
    assert other.exit_code == 2 and "in lon/lat (EPSG:4326) or in the map's CRS (EPSG:32635)" in other.stderr
    same = run("query", map_path, "-", "--prior", f"{images[0]['truth']['x']},{images[0]['truth']['y']},50",
               "--prior-crs", "EPSG:32635", input=line)
    assert same.exit_code == 0 and answers(same)[0]["status"] == "ok"
    nonsense = run("query", map_path, "-", "--prior", "1,2,3", "--prior-crs", "EPSG:nope", input=line)
    assert nonsense.exit_code == 2 and "not a CRS that pyproj knows" in nonsense.stderr


def test_a_prior_near_the_edge_is_kept_and_one_far_off_is_rejected(sample) -> None:
    map_path, _, images = sample
    bounds = json.loads(run("info", map_path, "--json").stdout)["bounds"]
    doc = without_truth(images[0])
    # 100 m east of the map's box: the image (about 70 m across) might still see the map: searched, not refused.
    near = {**doc, "prior": {"x": bounds[2] + 100, "y": bounds[1], "radius": 10}}
    far = {**doc, "prior": {"x": bounds[2] + 2500, "y": bounds[1], "radius": 10}}
    got = answers(run("query", map_path, "-", input=json.dumps(near) + "\n" + json.dumps(far) + "\n"))
    assert "outside the map's bounds" not in got[0].get("reason", "")
    assert got[1]["reason"] == f"prior ({bounds[2] + 2500:.0f}, {bounds[1]:.0f}) is 2.5 km outside the map's " \
                               "bounds: no objects here"


# --- unknown labels -----------------------------------------------------------------------------------


def test_unknown_labels_are_skipped_and_counted(sample) -> None:
    map_path, _, images = sample
    image = images[1]
    truth = image["truth"]
    extra = [{"label": ALIEN, "x": 10.0, "y": 10.0}, {"label": ALIEN, "x": 600.0, "y": 400.0},
             {"label": "tree", "x": 300.0, "y": 20.0}]
    doc = {**without_truth(image), "objects": image["objects"] + extra}
    known = image["objects"][:2]
    too_few = {**without_truth(image), "id": "few", "objects": known + extra}
    result = run("query", map_path, "-", input=json.dumps(doc) + "\n" + json.dumps(too_few) + "\n")
    placed, few = answers(result)
    assert placed["status"] == "ok", placed
    assert placed["skipped_labels"] == {ALIEN: 2, "tree": 1}
    assert abs(placed["x"] - truth["x"]) < 1 and abs(placed["y"] - truth["y"]) < 1
    assert placed["inliers"] <= len(image["objects"])
    assert few["status"] == "rejected" and few["skipped_labels"] == {ALIEN: 2, "tree": 1}
    assert few["reason"].startswith(f"unknown labels '{ALIEN}', 'tree': the map has building")
    assert few["reason"].endswith("2 objects left: at least 3 are needed")
    # An image whose labels are all known carries no skipped_labels.
    (plain,) = answers(run("query", map_path, "-", input=json.dumps(without_truth(image)) + "\n"))
    assert plain["status"] == "ok" and "skipped_labels" not in plain


# --- build warnings -----------------------------------------------------------------------------------


def test_duplicate_sources_are_read_once_with_a_warning(tmp_path: Path) -> None:
    a = town(tmp_path / "a.osm")
    copy = tmp_path / "copy.osm"
    shutil.copyfile(a, copy)
    link = tmp_path / "link.osm"
    os.link(a, link)
    single = json.loads(run("build", a, "-o", tmp_path / "one.mapdb", "-q").stdout)
    result = run("build", a, copy, link, a, "-o", tmp_path / "m.mapdb", "-q")
    assert result.exit_code == 0
    summary = json.loads(result.stdout)
    assert summary["count"] == single["count"] == 5 and "merged_duplicates" not in summary["skipped"]
    assert summary["warnings"] == [
        f"{copy}: the same content as source {a} (SHA-256 {summary['warnings'][0].split('SHA-256 ')[1][:16]}...); "
        "read once",
        f"{link}: the same file as source {a}; read once",
        f"{a}: given twice; read once",
    ]
    # On stderr too, one line each, even with -q: warnings are not progress.
    assert result.stderr.splitlines() == [f"mapdb: warning: {w}" for w in summary["warnings"]]
    facts = json.loads(run("info", tmp_path / "m.mapdb", "--json").stdout)
    assert [s["name"] for s in facts["sources"]] == ["a.osm"]
    assert single["warnings"] == []


def test_sources_too_far_apart_for_one_utm_zone_warn(tmp_path: Path) -> None:
    atlanta = town(tmp_path / "atlanta.osm", -84.39, 33.75)
    monaco = town(tmp_path / "monaco.osm")
    result = run("build", atlanta, monaco, "-o", tmp_path / "m.mapdb", "-q")
    assert result.exit_code == 0  # a warning, not an error
    (warning,) = json.loads(result.stdout)["warnings"]
    assert warning.startswith("sources span 91.8 degrees of longitude (atlanta.osm (lon -84.4) and monaco.osm "
                              "(lon 7.4)), more than the 12 (two UTM zones)")
    assert "--crs" in warning and "one map per area" in warning
    assert result.stderr == f"mapdb: warning: {warning}\n"
    # A CRS chosen by the user, or sources within two zones: no warning.
    chosen = run("build", atlanta, monaco, "-o", tmp_path / "w.mapdb", "--crs", "EPSG:3857", "-q")
    assert chosen.exit_code == 0 and json.loads(chosen.stdout)["warnings"] == [] and chosen.stderr == ""
    near = run("build", monaco, town(tmp_path / "east.osm", 18.0, 43.7), "-o", tmp_path / "n.mapdb", "-q")
    assert json.loads(near.stdout)["warnings"] == []
