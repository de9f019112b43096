"""GIS conventions of what mapdb writes: one geometry type a layer, no field named by an SQL keyword, exports to
standard output and to Shapefile, lon/lat refused beyond the poles and flagged when it looks swapped.

Every file is written by the commands themselves, over the sample map (Helsinki), and read back with pyogrio
(GDAL), as ``ogrinfo`` would read it.  The analysis outputs (``analysis.tif``, ``cells.gpkg``) are checked the
same way in ``test_analyze.py``.
"""

from __future__ import annotations

import csv
import io
import json
import warnings
from pathlib import Path

import pyogrio
import pytest
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from sqlwords import sql_keywords_among

from mapdb.build.pipeline import build_map
from mapdb.errors import MapdbError
from mapdb.geo import LonLatError, SwappedLonLatWarning
from mapdb.mapfile.reader import open_map

SAMPLE = Path(__file__).resolve().parents[1] / "sample_maps" / "helsinki.osm.pbf"
# Helsinki's centre, and the objects the sample map holds.
LON, LAT = 24.945, 60.166


@pytest.fixture(scope="module")
def helsinki(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("conventions") / "helsinki.mapdb"
    build_map([SAMPLE], out)
    return out


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def written(helsinki: Path, tmp_path_factory) -> dict[str, Path]:
    """Every vector file the commands write over the sample map: each export format, and a track's GeoJSON."""
    root = tmp_path_factory.mktemp("written")
    files = {}
    for suffix in (".geojson", ".gpkg", ".fgb", ".parquet", ".csv", ".shp"):
        files[suffix] = root / f"objects{suffix}"
        result = run("export", helsinki, "-o", files[suffix])
        assert result.exit_code == 0, result.output
    flight, track = root / "flight.jsonl", root / "track.jsonl"
    assert run("simulate", "flight", helsinki, "-o", flight, "--length", "40", "-q").exit_code == 0
    result = run("navigate", helsinki, flight, "-o", track, "--geojson", root / "track.geojson", "-q")
    assert result.exit_code == 0, result.output
    files["track points"], files["track line"] = root / "track.geojson", root / "track_line.geojson"
    return files


def _fields(path: Path) -> list[str]:
    if path.suffix == ".csv":
        return next(csv.reader(io.StringIO(path.read_text())))
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        return [name for name in pq.read_schema(path).names if name != "geometry"]
    return [str(name) for name in pyogrio.read_info(path)["fields"]]


def test_no_field_mapdb_writes_is_an_sql_keyword(written: dict[str, Path]) -> None:
    for what, path in written.items():
        fields = _fields(path)
        assert fields and sql_keywords_among(fields) == [], (what, fields)
    assert sql_keywords_among(["label", "false", "Row", "x"]) == ["Row", "false"]  # the check can fail


def test_every_layer_has_one_geometry_type(written: dict[str, Path]) -> None:
    expected = {".geojson": "Point", ".gpkg": "Point", ".fgb": "Point", ".shp": "Point",
                "track points": "Point", "track line": "LineString"}
    for what, kind in expected.items():
        layers = pyogrio.list_layers(written[what])
        assert [str(k) for k in layers[:, 1]] == [kind], (what, layers)  # GDAL's own reading: not "Unknown"
    points = json.loads(written["track points"].read_text())
    assert len(points["features"]) == 21 and {f["geometry"]["type"] for f in points["features"]} == {"Point"}


def test_export_to_standard_output_is_the_file_s_content(helsinki: Path, written: dict[str, Path]) -> None:
    result = run("export", helsinki, "-")
    assert result.exit_code == 0, result.output
    streamed, saved = json.loads(result.stdout), json.loads(written[".geojson"].read_text())
    n_objects = len(open_map(helsinki).all())
    assert streamed["features"] == saved["features"] and len(saved["features"]) == n_objects
    assert f"{n_objects} objects written to standard output" in result.stderr
    result = run("export", helsinki, "-o", "-", "--format", "csv")
    assert result.exit_code == 0 and result.stdout == written[".csv"].read_text()
    # a binary format has no place on a terminal; a file's ending says its own format
    assert run("export", helsinki, "-", "--format", "gpkg").exit_code == 2
    assert run("export", helsinki, written[".csv"].with_name("x.csv"), "--format", "csv").exit_code == 2
    assert run("export", helsinki).exit_code == 2


def test_a_shapefile_is_chosen_by_its_ending_and_written_whole(helsinki: Path, written: dict[str, Path],
                                                              tmp_path: Path) -> None:
    shp = written[".shp"]
    assert sorted(p.suffix for p in shp.parent.glob("objects.*") if p.suffix in (".shp", ".shx", ".dbf", ".prj",
                                                                                ".cpg")) == [
        ".cpg", ".dbf", ".prj", ".shp", ".shx"]
    info, n_objects = pyogrio.read_info(shp), len(open_map(helsinki).all())
    assert info["features"] == n_objects and info["crs"] == "EPSG:32635" and info["geometry_type"] == "Point"
    assert not [p for p in shp.parent.iterdir() if p.name.startswith(".")]  # no temporary left beside
    # a part of an existing Shapefile is an output too: replaced only with --overwrite
    (tmp_path / "lone.dbf").write_bytes(b"not ours")
    assert_one_line_error(run("export", helsinki, tmp_path / "lone.shp"), "lone.dbf", "--overwrite")
    assert run("export", helsinki, tmp_path / "lone.shp", "--overwrite").exit_code == 0
    assert pyogrio.read_info(tmp_path / "lone.shp")["features"] == n_objects


def test_lonlat_beyond_the_poles_is_refused_and_a_swap_is_flagged(helsinki: Path) -> None:
    with open_map(helsinki) as m:
        with pytest.raises(LonLatError, match=r"latitude 91\.0 must be a number in \[-90, 90\]"):
            m.query_lonlat(LON, 91.0, 100.0)
        assert issubclass(LonLatError, MapdbError) and issubclass(LonLatError, ValueError)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the right order gives no warning
            assert len(m.query_lonlat(LON, LAT, 300.0)) > 10
        with pytest.warns(SwappedLonLatWarning, match="lon and lat swapped"):
            assert len(m.query_lonlat(LAT, LON, 300.0)) == 0
    flight = helsinki.with_name("one.jsonl")
    assert run("simulate", "flight", helsinki, "-o", flight, "--length", "5", "-q", "--overwrite").exit_code == 0
    result = run("navigate", helsinki, flight, "-o", "/dev/null", "--initial", f"{LAT},{LON},50", "--initial-crs",
                 "EPSG:4326", "-q")
    assert result.exit_code == 0 and "mapdb: warning: --initial: lon 60.166, lat 24.945 is off the map" in result.stderr
