"""``mapdb bench storage``: the sizes reported are the sizes of real files, cells add up to the totals, and bad
input gets one line."""

from __future__ import annotations

import json
import lzma
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import X0, Y0, OsmXml, square

from mapdb.build.pipeline import build_map
from mapdb.evaluation.storage import format_storage, storage_report, storage_reports
from mapdb.mapfile.reader import open_map

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "sample_maps" / "helsinki.osm.pbf"
OSM = REPO.parent / "shared" / "data" / "osm"


def run(*args: object):
    return CliRunner().invoke(cli, ["bench", "storage", *map(str, args)])


def row(report: dict, name: str) -> dict:
    return next(r for r in report["formats"] if r["format"] == name)




@pytest.fixture(scope="module")
def helsinki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("storage") / "helsinki.mapdb"
    build_map([SAMPLE], out)
    return out


@pytest.fixture(scope="module")
def report(helsinki: Path) -> dict:
    return storage_report(helsinki)


@pytest.fixture
def private_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The temporary directory every temporary file goes to, for checking that none is left behind."""
    where = tmp_path / "tmp"
    where.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(where))
    return where


def test_mapdb_bytes_are_the_file_and_cells_add_up(helsinki: Path, report: dict) -> None:
    mapdb = row(report, "mapdb")
    assert mapdb["bytes"] == helsinki.stat().st_size
    assert mapdb["bytes_per_object"] == pytest.approx(mapdb["bytes"] / report["objects"], abs=1e-3)
    parts = report["mapdb_parts"]
    assert parts["header"] + parts["directory"] + parts["pages"] == mapdb["bytes"]
    with open_map(helsinki) as m:
        assert report["objects"] == len(m) and report["pages"] == m.page_count
    cells = report["cells"]
    assert sum(cells["objects"]) == report["objects"] and min(cells["objects"]) >= 1
    assert report["area"]["occupied_km2"] == pytest.approx(len(cells["objects"]) * 1.0)
    for r in report["formats"]:
        if r["cell_bytes"] is not None:  # every format's cells sum to its total
            assert sum(r["cell_bytes"]) == pytest.approx(r["bytes"], abs=0.01 * len(cells["objects"]) + 0.5), r
    # a page's bytes go to the cells of its objects: a cell never costs more than the pages it meets
    # plus its objects' share of the header and directory
    overhead = (parts["header"] + parts["directory"]) / report["objects"]
    assert all(b <= w + n * overhead + 1e-6 for b, w, n in
               zip(mapdb["cell_bytes"], cells["window_bytes"], cells["objects"]))


def test_other_formats_are_files_one_can_write(helsinki: Path, report: dict, tmp_path: Path) -> None:
    with open_map(helsinki) as m:
        objects = m.all()
        q = m.quantum
    qx, qy = np.rint(objects.x / q).astype(np.int64), np.rint(objects.y / q).astype(np.int64)
    frame = objects.take(np.lexsort((qx, qy, objects.label))).to_geodataframe()
    frame.to_file(tmp_path / "a.gpkg", driver="GPKG", engine="pyogrio", layer="objects")
    frame.to_file(tmp_path / "a.fgb", driver="FlatGeobuf", engine="pyogrio", layer="objects")
    frame.to_parquet(tmp_path / "a.parquet", compression="zstd")
    assert row(report, "GeoPackage")["bytes"] == (tmp_path / "a.gpkg").stat().st_size
    assert row(report, "FlatGeobuf")["bytes"] == (tmp_path / "a.fgb").stat().st_size
    assert row(report, "GeoParquet (zstd)")["bytes"] == (tmp_path / "a.parquet").stat().st_size
    # the map is far smaller than the GIS formats, and within a few per cent of lzma on its sorted columns
    mapdb = row(report, "mapdb")["bytes"]
    assert row(report, "GeoPackage")["bytes"] > 10 * mapdb
    lz = row(report, "lzma: sorted columns, y deltas")["bytes"]
    assert 0.8 < lz / mapdb < 1.3
    assert row(report, "lzma: sorted columns")["bytes"] >= lz  # deltas help a general-purpose compressor


def test_compressed_columns_are_what_lzma_makes(helsinki: Path, report: dict) -> None:
    """The columns rebuilt here independently, from the map's objects: x, y in quanta from their minimum,
    label, area code, sorted by (label, y, x)."""
    with open_map(helsinki) as m:
        o = m.all()
        q = m.quantum
    qx, qy = np.rint(o.x / q).astype(np.int64), np.rint(o.y / q).astype(np.int64)
    code = np.where(o.area > 0, np.clip(np.rint(8 * (np.log2(np.where(o.area > 0, o.area, 1)) + 16)) + 1, 1, None), 0)
    order = np.lexsort((qx, qy, o.label))
    data = b"".join([(qx[order] - qx.min()).astype("<u4").tobytes(), (qy[order] - qy.min()).astype("<u4").tobytes(),
                     o.label[order].astype("u1").tobytes(), code[order].astype("<u2").tobytes()])
    packed = lzma.compress(data, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC32,
                           filters=[{"id": lzma.FILTER_LZMA2, "preset": 9 | lzma.PRESET_EXTREME}])
    assert row(report, "lzma: sorted columns")["bytes"] == len(packed)
    assert lzma.decompress(packed) == data
    # chunked like the map's pages, each chunk raw (no .xz container) with a 36-byte record, as a page has
    chunked = row(report, "lzma per page: y deltas, +36 B record")["bytes"] - 36 * report["pages"]
    assert abs(chunked - row(report, "lzma: sorted columns, y deltas")["bytes"]) <= 80 * report["pages"]


def test_orthophoto_is_pixels_times_bits(helsinki: Path) -> None:
    r = storage_report(helsinki, gsd_m=0.5, jpeg_bpp=2.0, cell_m=250.0)
    occupied, box = r["formats"][-2], r["formats"][-1]
    assert occupied["format"] == "JPEG 0.5 m, 2 bpp: occupied cells"
    pixels = len(r["cells"]["objects"]) * 250.0**2 / 0.5**2
    assert occupied["bytes"] == round(pixels * 2.0 / 8)
    with open_map(helsinki) as m:
        b = m.bounds
    assert box["bytes"] == round((b[2] - b[0]) * (b[3] - b[1]) / 0.25 * 2.0 / 8)
    assert box["bytes_per_km2_bbox"] == pytest.approx(1e6 / 0.25 * 2.0 / 8, rel=1e-6)
    assert box["cells"] is None and occupied["cells"]["bytes_per_km2"]["median"] == pytest.approx(1e6, rel=1e-6)


def test_cells_are_where_the_objects_are(tmp_path: Path) -> None:
    """Two towns 5 km apart, each in the middle of a 1 km cell of the map's CRS: two cells, each with its town."""
    doc = OsmXml()
    cx, cy = (math.floor(X0 / 1000) + 0.5) * 1000 - X0, (math.floor(Y0 / 1000) + 0.5) * 1000 - Y0
    for dx, n in ((0, 6), (5000, 3)):
        for i in range(n):
            doc.ring(square(cx + dx + 40 * (i % 3) - 40, cy + 40 * (i // 3), 8), {"building": "yes"})
    source = doc.write(tmp_path / "towns.osm")
    r = storage_report(source)
    assert r["objects"] == 9 and r["area"]["occupied_cells"] == 2 and r["cells"]["objects"] == [6, 3]
    assert r["cells"]["x0"] == [math.floor(X0 / 1000) * 1000.0, (math.floor(X0 / 1000) + 5) * 1000.0]
    mapdb = row(r, "mapdb")
    assert mapdb["cell_bytes"][0] > mapdb["cell_bytes"][1]  # six objects cost more than three
    whole = storage_report(source, cell_m=100_000.0)  # one cell over everything: it reads every page
    assert whole["area"]["occupied_cells"] == 1 and whole["cells"]["window_bytes"] == [whole["mapdb_parts"]["pages"]]


def test_a_source_is_built_and_nothing_is_left(helsinki: Path, report: dict, private_tmp: Path) -> None:
    built = storage_report(SAMPLE)
    assert built["built_from_source"] and built["map"] is None and built["input"] == str(SAMPLE)
    assert built["objects"] == report["objects"]
    assert abs(row(built, "mapdb")["bytes"] - row(report, "mapdb")["bytes"]) < 100  # the header's time and name
    assert row(built, "GeoPackage")["bytes"] == row(report, "GeoPackage")["bytes"]
    assert list(private_tmp.iterdir()) == []


def test_cli_json_and_tables(helsinki: Path, tmp_path: Path) -> None:
    other = tmp_path / "copy.mapdb"
    other.write_bytes(helsinki.read_bytes())
    result = run(helsinki, other, "--json", "-q")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert len(doc["maps"]) == 2 and doc["errors"] == []
    total = doc["total"]
    assert row(total, "mapdb")["bytes"] == 2 * helsinki.stat().st_size
    assert total["objects"] == 2 * doc["maps"][0]["objects"]
    assert row(total, "mapdb")["cells"]["bytes_per_km2"]["median"] > 0
    table = run(helsinki, other, "-q")
    assert table.exit_code == 0 and table.stderr == ""
    assert table.stdout.count("GeoParquet (zstd)") == 3 and "total of 2 maps" in table.stdout
    assert f"{helsinki.stat().st_size:,}" in table.stdout
    assert format_storage(storage_reports([helsinki])).startswith(str(helsinki))


@pytest.mark.parametrize("content, needle", [(b"", "empty file"), (b"hello, not a map", "not a mapdb map"),
                                             (None, "no such map file")])
def test_bad_maps_are_one_line(tmp_path: Path, content: bytes | None, needle: str) -> None:
    path = tmp_path / "bad.mapdb"
    if content is not None:
        path.write_bytes(content)
    result = run(path, "-q")
    assert_one_line_error(result, str(path), needle, alone=True)
    assert result.stdout == ""


def test_truncated_map_and_empty_source_are_one_line(helsinki: Path, tmp_path: Path, private_tmp: Path) -> None:
    cut = tmp_path / "cut.mapdb"
    cut.write_bytes(helsinki.read_bytes()[:-10])
    assert_one_line_error(run(cut), "truncated", alone=True)
    empty = OsmXml()
    empty.node(0, 0, {"amenity": "bench"})
    assert_one_line_error(run(empty.write(tmp_path / "nothing.osm"), "-q"), "no labelled objects", alone=True)
    assert list(private_tmp.iterdir()) == []


def test_a_bad_input_does_not_stop_the_others(helsinki: Path, tmp_path: Path) -> None:
    result = run(tmp_path / "missing.mapdb", helsinki, "--json", "-q")
    assert result.exit_code == 1
    assert result.stderr.strip().splitlines() == [f"mapdb: error: {tmp_path / 'missing.mapdb'}: no such map file"]
    doc = json.loads(result.stdout)
    assert [m["input"] for m in doc["maps"]] == [str(helsinki)] and len(doc["errors"]) == 1


@pytest.mark.parametrize("option", ["--cell=0", "--gsd=-1", "--jpeg-bpp=nan"])
def test_bad_options_are_usage_errors(helsinki: Path, option: str) -> None:
    assert run(helsinki, option).exit_code == 2


@pytest.mark.slow
def test_real_extracts() -> None:
    sources = sorted(OSM.glob("*.osm.pbf")) if OSM.is_dir() else []
    if not sources:
        pytest.skip(f"real data absent: {OSM} (expected ../shared/data beside the checkout, see SOURCES.md)")
    doc = storage_reports(sources)
    for r in doc["maps"]:
        mapdb = row(r, "mapdb")
        assert mapdb["bytes_per_object"] < 5
        assert row(r, "GeoPackage")["bytes"] > 20 * mapdb["bytes"]
        assert row(r, "lzma per page: y deltas, +36 B record")["bytes"] > mapdb["bytes"]
        assert r["window_bytes"]["median"] < mapdb["bytes"]
