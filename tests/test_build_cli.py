"""`mapdb build`, `info` and `export` end to end on real files, and every bad input through the CLI."""

from __future__ import annotations

import hashlib
import json
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import OsmXml, lonlat, square

from mapdb.mapfile.reader import open_map


def run(*args: str):
    return CliRunner().invoke(cli, [str(a) for a in args])




@pytest.fixture
def town(tmp_path: Path) -> Path:
    """Three buildings, a park, a building node and a T junction of two residential roads."""
    doc = OsmXml()
    for i in range(3):
        doc.ring(square(40.0 * i, 0.0, 6.0), {"building": "yes"})
    doc.ring(square(0.0, 80.0, 20.0), {"leisure": "park"})
    doc.node(100.0, 100.0, {"building": "hut"})
    a, b, c = doc.node(-50.0, -40.0), doc.node(30.0, -40.0), doc.node(110.0, -40.0)
    d = doc.node(30.0, -120.0)
    doc.way([a, b, c], {"highway": "residential", "name": "Main"})
    doc.way([b, d], {"highway": "residential", "name": "Side"})
    return doc.write(tmp_path / "town.osm")


def test_build_info_and_metadata(town: Path, tmp_path: Path) -> None:
    out = tmp_path / "town.mapdb"
    result = run("build", town, "-o", out)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["labels"] == {"building": 4, "park": 1, "road_intersection": 1}
    assert summary["crs"] == "EPSG:32632"  # UTM zone of lon 7.42
    facts = json.loads(run("info", out, "--json").stdout)
    assert facts["objects"] == 6 and facts["labels"] == summary["labels"]
    assert facts["sources"][0]["sha256"] == hashlib.sha256(town.read_bytes()).hexdigest()
    assert facts["sources"][0]["size"] == town.stat().st_size
    assert facts["bytes_per_object"] == pytest.approx(out.stat().st_size / 6, abs=0.01)
    lon, lat = lonlat(0.0, 0.0)
    assert facts["bounds_lonlat"][0] < lon < facts["bounds_lonlat"][2]
    text = run("info", out).stdout
    assert "building" in text and "EPSG:32632" in text


def test_progress_on_stderr_results_on_stdout(town: Path, tmp_path: Path) -> None:
    result = run("build", town, "-o", tmp_path / "m.mapdb")
    assert "reading" in result.stderr
    json.loads(result.stdout)  # nothing but the summary
    quiet = run("build", town, "-o", tmp_path / "m.mapdb", "-q", "--overwrite")
    assert quiet.stderr == ""


def test_forced_crs_and_bbox(town: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    assert run("build", town, "-o", out, "--crs", "EPSG:3857").exit_code == 0
    with open_map(out) as m:
        assert m.crs == "EPSG:3857"
    lon0, lat0 = lonlat(-15.0, -10.0)
    lon1, lat1 = lonlat(15.0, 10.0)
    assert run("build", town, "-o", out, "--bbox", f"{lon0},{lat0},{lon1},{lat1}", "--overwrite").exit_code == 0
    with open_map(out) as m:
        assert m.label_counts == {"building": 1}
    assert_one_line_error(run("build", town, "-o", out, "--crs", "EPSG:4326", "--overwrite"), "projected")


@pytest.mark.parametrize("suffix", [".gpkg", ".geojson", ".parquet", ".fgb", ".csv"])
def test_export_round_trip(town: Path, tmp_path: Path, suffix: str) -> None:
    out = tmp_path / "m.mapdb"
    run("build", town, "-o", out)
    target = tmp_path / f"objects{suffix}"
    result = run("export", out, "-o", target)
    assert result.exit_code == 0, result.output
    with open_map(out) as m:
        stored = m.all()
        crs = m.crs
    if suffix == ".csv":
        frame = pd.read_csv(target)
    elif suffix == ".parquet":
        frame = gpd.read_parquet(target)
    else:
        frame = gpd.read_file(target)
        assert frame.crs.to_string() == ("EPSG:4326" if suffix == ".geojson" else crs)  # GeoJSON: RFC 7946 lon/lat
        if suffix != ".geojson":
            assert np.allclose(frame.geometry.x, frame["x"]) and np.allclose(frame.geometry.y, frame["y"])
    order_a = np.lexsort((stored.y, stored.x))
    order_b = np.lexsort((frame["y"].to_numpy(), frame["x"].to_numpy()))
    assert np.allclose(frame["x"].to_numpy()[order_b], stored.x[order_a], atol=1e-6)
    assert np.allclose(frame["y"].to_numpy()[order_b], stored.y[order_a], atol=1e-6)
    assert list(frame["label"].to_numpy()[order_b]) == list(stored.names()[order_a])


def test_exported_positions_lie_on_the_osm_data(town: Path, tmp_path: Path) -> None:
    """The building node is a point: its exported lon/lat must equal the OSM node within the quantum."""
    out, csv = tmp_path / "m.mapdb", tmp_path / "o.csv"
    run("build", town, "-o", out)
    run("export", out, "-o", csv)
    frame = pd.read_csv(csv)
    hut = frame[(frame["label"] == "building") & (frame["area_m2"] == 0)]
    lon, lat = lonlat(100.0, 100.0)
    assert abs(hut["lon"].iloc[0] - lon) * 80_000 < 0.08 and abs(hut["lat"].iloc[0] - lat) * 111_000 < 0.08


def test_export_bbox_and_empty_bbox(town: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    run("build", town, "-o", out)
    lon0, lat0 = lonlat(-30.0, 60.0)
    lon1, lat1 = lonlat(30.0, 100.0)
    target = tmp_path / "park.geojson"
    assert run("export", out, "-o", target, "--bbox", f"{lon0},{lat0},{lon1},{lat1}").exit_code == 0
    assert list(gpd.read_file(target)["label"]) == ["park"]
    empty = tmp_path / "none.geojson"
    assert_one_line_error(run("export", out, "-o", empty, "--bbox", "0,0,0.001,0.001"), str(out))
    assert not empty.exists()


def test_osm_and_csv_layer_in_one_map(town: Path, tmp_path: Path) -> None:
    lon, lat = lonlat(200.0, 200.0)
    layer = tmp_path / "mine.csv"
    layer.write_text(f"lon,lat,label\n{lon},{lat},water\n{lon + 0.0005},{lat},stadium\n")
    out = tmp_path / "m.mapdb"
    result = run("build", town, layer, "-o", out)
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["labels"] == {
        "building": 4, "park": 1, "road_intersection": 1, "water": 1, "stadium": 1}
    with open_map(out) as m:
        assert [s["kind"] for s in m.metadata["sources"]] == ["osm", "layer"]


# ------------------------------------------------------------------------------------------ bad input


def test_bad_sources(town: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    assert_one_line_error(run("build", tmp_path / "missing.osm.pbf", "-o", out), "missing.osm.pbf", "no such file")
    (tmp_path / "empty.osm").write_bytes(b"")
    assert_one_line_error(run("build", tmp_path / "empty.osm", "-o", out), "empty.osm")
    (tmp_path / "notes.osm").write_text("this is not OSM\n")
    assert_one_line_error(run("build", tmp_path / "notes.osm", "-o", out), "notes.osm")
    (tmp_path / "data.xyz").write_text("1,2\n")
    assert_one_line_error(run("build", tmp_path / "data.xyz", "-o", out), "data.xyz", "unknown kind")
    truncated = tmp_path / "cut.osm"
    truncated.write_bytes(town.read_bytes()[: town.stat().st_size // 2])
    assert_one_line_error(run("build", truncated, "-o", out), "cut.osm")
    assert not out.exists()


def test_unknown_label_in_mapping_file(town: Path, tmp_path: Path) -> None:
    labels = tmp_path / "labels.toml"
    labels.write_text('[[osm.rules]]\nlabel = "castle"\nkey = "historic"\n')
    out = tmp_path / "m.mapdb"
    assert_one_line_error(run("build", town, "-o", out, "--labels", labels), "labels.toml", "castle")
    assert not out.exists()


def test_empty_bbox_keeps_the_earlier_map(town: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    run("build", town, "-o", out)
    before = out.read_bytes()
    assert_one_line_error(run("build", town, "-o", out, "--bbox", "0,0,0.01,0.01", "--overwrite"),
                          "no labelled objects")
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.mapdb", "town.osm"]


def _with_version(data: bytes, version: int) -> bytes:
    """The map with another format version and its header checksum recomputed (a genuinely newer file)."""
    d = bytearray(data)
    struct.pack_into("<H", d, 8, version)
    end = 16 + struct.unpack_from("<I", d, 12)[0]
    struct.pack_into("<I", d, end, zlib.crc32(bytes(d[:end])))
    return bytes(d)


def test_damaged_maps(town: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.mapdb"
    run("build", town, "-o", out)
    data = out.read_bytes()
    cases = {
        "truncated.mapdb": (data[: len(data) // 2], "truncated"),
        "flipped.mapdb": (data[:-3] + bytes([data[-3] ^ 1]) + data[-2:], "checksum"),
        "newer.mapdb": (_with_version(data, 7), "newer map format"),
        "version-flipped.mapdb": (data[:8] + struct.pack("<H", 7) + data[10:], "checksum"),
        "text.mapdb": (b"hello", "not a mapdb map"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        assert_one_line_error(run("info", tmp_path / name), name, message)
        target = tmp_path / f"{name}.gpkg"
        assert_one_line_error(run("export", tmp_path / name, "-o", target), name)
        assert not target.exists()
    assert_one_line_error(run("info", tmp_path / "absent.mapdb"), "absent.mapdb", "no such map file")


def test_console_script_error_has_no_traceback(tmp_path: Path) -> None:
    """The installed `mapdb` command, run as a user would."""
    bad = tmp_path / "bad.mapdb"
    bad.write_bytes(b"\x89MAPDB\r\n\x01")
    proc = subprocess.run([sys.executable, "-m", "mapdb_cli", "info", str(bad)], capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0 and "bad.mapdb" in proc.stderr
    debug = subprocess.run([sys.executable, "-m", "mapdb_cli", "info", str(bad), "--debug"],
                           capture_output=True, text=True)
    assert debug.returncode != 0 and "Traceback" in debug.stderr
