"""`mapdb build --dem`: elevation sampled from generated DEMs, shown by info and export, kept by merge, and every
bad DEM refused in one line (or counted per object)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from clichecks import assert_one_line_error
from click.testing import CliRunner
from mapdb_cli.main import cli
from osmxml import X0, Y0, OsmXml, small_town, square
from rasterio.transform import from_origin

from mapdb.mapfile.reader import open_map

SHARED = next((p for p in (Path(__file__).resolve().parents[2] / "shared" / "data", Path("/work/shared/data"))
               if p.is_dir()), Path(__file__).resolve().parents[2] / "shared" / "data")


def run(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def ramp(path: Path, *, crs: str | None = "EPSG:32632", units: str | None = None, nodata_hole: bool = False,
         offset_m: float = 0.0) -> Path:
    """A DEM in UTM 32N around the test town: height = 100 + x / 10 (x metres east of the town's origin),
    posts every 5 m; optionally a nodata hole over the park, or the whole DEM moved ``offset_m`` east."""
    size, post = 120, 5.0
    left, top = X0 - 200.0 + offset_m, Y0 + 300.0
    xs = left + post * (np.arange(size) + 0.5) - X0
    z = np.tile(100.0 + xs / 10.0, (size, 1)).astype(np.float32)
    if nodata_hole:
        z[40:48, 34:46] = -9999.0  # rows 40-48 from the top: y 100..60; columns: x -30..30 (the park)
    kwargs = {"crs": crs} if crs else {}
    with rasterio.open(path, "w", driver="GTiff", width=size, height=size, count=1, dtype="float32",
                       transform=from_origin(left, top, post, post), nodata=-9999.0, **kwargs) as f:
        f.write(z, 1)
        if units:
            f.set_band_unit(1, units)
    return path


def built(tmp_path: Path, *dems: Path, name: str = "town.mapdb"):
    town = small_town(tmp_path / "town.osm") if not (tmp_path / "town.osm").exists() else tmp_path / "town.osm"
    return run("build", town, "-o", tmp_path / name, *[a for d in dems for a in ("--dem", d)], "--overwrite")


def test_build_stores_each_objects_ground_elevation(tmp_path: Path) -> None:
    result = built(tmp_path, ramp(tmp_path / "ramp.tif"))
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["warnings"] == []
    with open_map(tmp_path / "town.mapdb") as m:
        objects = m.all()
        assert m.format_version == 2 and m.has_elevation
    assert objects.elevation is not None
    expected = 100.0 + (objects.x - X0) / 10.0  # the ramp, bilinear: exact on a plane
    assert np.max(np.abs(objects.elevation - expected)) <= 0.5 + 0.05  # half a step, and the 0.1 m quantum
    info = run("info", tmp_path / "town.mapdb", "--json")
    facts = json.loads(info.stdout)["elevation"]
    assert facts["known"] == len(objects) and facts["unknown"] == 0 and facts["step_m"] == 1.0
    text = run("info", tmp_path / "town.mapdb").stdout
    assert "elevation:" in text and f"{len(objects)} objects with, 0 without" in text
    export = run("export", tmp_path / "town.mapdb", "-o", tmp_path / "town.csv")
    assert export.exit_code == 0, export.output
    header, *rows = (tmp_path / "town.csv").read_text().splitlines()
    assert header.split(",")[:3] == ["label", "area_m2", "elevation_m"]
    assert sorted(float(r.split(",")[2]) for r in rows) == sorted(objects.elevation.tolist())


def test_a_map_without_dem_has_no_elevation_anywhere(tmp_path: Path) -> None:
    assert built(tmp_path).exit_code == 0
    with open_map(tmp_path / "town.mapdb") as m:
        assert m.format_version == 1 and not m.has_elevation and m.all().elevation is None
    assert "elevation" not in json.loads(run("info", tmp_path / "town.mapdb", "--json").stdout)
    run("export", tmp_path / "town.mapdb", "-o", tmp_path / "town.csv")
    assert "elevation_m" not in (tmp_path / "town.csv").read_text().splitlines()[0]


def test_a_mosaic_and_a_nodata_hole_are_counted_in_one_warning(tmp_path: Path) -> None:
    holed = ramp(tmp_path / "holed.tif", nodata_hole=True)
    result = built(tmp_path, holed)
    assert result.exit_code == 0, result.output
    warnings = json.loads(result.stdout)["warnings"]
    assert len(warnings) == 1 and "1 of 4 objects have no ground elevation (0 outside the DEM, 1 on its nodata)" \
        in warnings[0]
    assert result.stderr.count("mapdb: warning:") == 1
    with open_map(tmp_path / "town.mapdb") as m:
        z = m.all().elevation
        assert int(np.isnan(z).sum()) == 1 and m.metadata["build"]["dem"]["nodata"] == 1
    # a second DEM under the hole fills it: a mosaic, the first file winning where both have a value
    result = built(tmp_path, holed, ramp(tmp_path / "full.tif", offset_m=0.0))
    assert json.loads(result.stdout)["warnings"] == []
    with open_map(tmp_path / "town.mapdb") as m:
        assert not np.isnan(m.all().elevation).any()


@pytest.mark.parametrize("bad", ["no_crs", "feet", "elsewhere", "renamed_hgt", "missing", "not_a_raster"])
def test_bad_dems_are_refused_in_one_line_without_output(tmp_path: Path, bad: str) -> None:
    make = {
        "no_crs": lambda: ramp(tmp_path / "nocrs.tif", crs=None),
        "feet": lambda: ramp(tmp_path / "feet.tif", units="ft"),
        "elsewhere": lambda: ramp(tmp_path / "far.tif", offset_m=50_000.0),
        "renamed_hgt": lambda: _renamed_hgt(tmp_path / "monaco.hgt"),
        "missing": lambda: tmp_path / "absent.tif",
        "not_a_raster": lambda: _text(tmp_path / "notes.tif"),
    }
    needle = {"no_crs": "has no CRS", "feet": "in feet", "elsewhere": "does not cover the map",
              "renamed_hgt": "renamed", "missing": "absent.tif", "not_a_raster": "cannot read the DEM"}
    dem = make[bad]()
    result = built(tmp_path, dem)
    assert_one_line_error(result, str(dem), needle[bad])
    assert not (tmp_path / "town.mapdb").exists()


def _renamed_hgt(path: Path) -> Path:
    path.write_bytes(np.zeros((1201, 1201), ">i2").tobytes())  # a genuine tile's size and layout
    return path


def _text(path: Path) -> Path:
    path.write_text("not a raster\n")
    return path


def test_merge_keeps_elevation(tmp_path: Path) -> None:
    assert built(tmp_path, ramp(tmp_path / "ramp.tif"), name="a.mapdb").exit_code == 0
    doc = OsmXml()
    doc.ring(square(300.0, 0.0, 6.0), {"building": "yes"})
    doc.write(tmp_path / "east.osm")
    assert run("build", tmp_path / "east.osm", "-o", tmp_path / "b.mapdb").exit_code == 0  # flat
    result = run("merge", tmp_path / "a.mapdb", tmp_path / "b.mapdb", "-o", tmp_path / "ab.mapdb")
    assert result.exit_code == 0, result.output
    with open_map(tmp_path / "a.mapdb") as a, open_map(tmp_path / "ab.mapdb") as ab:
        before, after = a.all(), ab.all()
        assert ab.format_version == 2
    kept = {(round(x, 1), round(y, 1)): z for x, y, z in zip(after.x, after.y, after.elevation)}
    assert all(kept[(round(x, 1), round(y, 1))] == z for x, y, z in zip(before.x, before.y, before.elevation))
    assert int(np.isnan(after.elevation).sum()) == 1  # the flat map's building: unknown


def test_monaco_with_the_shared_srtm_tile(tmp_path: Path) -> None:
    osm, dem = SHARED / "osm" / "monaco-2021-12-03.osm.pbf", SHARED / "dem" / "N43E007.hgt"
    if not osm.is_file() or not dem.is_file():
        pytest.skip(f"real data absent: {osm} or {dem} (see ../shared/data/SOURCES.md)")
    assert run("build", osm, "--dem", dem, "-o", tmp_path / "m.mapdb").exit_code == 0
    assert run("build", osm, "-o", tmp_path / "flat.mapdb").exit_code == 0
    with open_map(tmp_path / "m.mapdb") as m:
        z = m.all().elevation
        grew = m.file_size - (tmp_path / "flat.mapdb").stat().st_size
    assert z is not None and not np.isnan(z).any()
    assert -2 <= z.min() and z.max() <= 172 and 40 <= np.median(z) <= 65  # SOURCES.md: -1..171 m, median 53
    assert grew <= len(z)  # at most a byte an object more


def _one_page_map(tmp_path: Path) -> tuple[Path, dict]:
    """A version 2 map of one page, and where its fields are."""
    from mapdb.mapfile.writer import write_map
    from mapdb.objects import Objects

    o = Objects.from_names([500000.0, 500100.0, 500050.0, 500300.0], [6e6, 6e6, 6e6 + 80, 6e6 + 10],
                           ["building", "building", "park", "building"], crs="EPSG:32635")
    path = tmp_path / "one.mapdb"
    write_map(path, o.with_elevation(np.array([10.0, 14.0, 12.0, 30.0])))
    data = path.read_bytes()
    length = int.from_bytes(data[12:16], "little")
    header = json.loads(__import__("zlib").decompress(data[16:16 + length], -15))
    return path, {"length": length, "header": header, "directory": 20 + length}


def _rewritten(path: Path, fields: dict, *, header: dict | None = None, page_bits: tuple[int, int, int] | None = None
               ) -> None:
    """The map with its header replaced or ``page_bits`` = (bit, width, value) set in its page, every checksum
    recomputed (a crafted file, not a damaged one)."""
    import struct
    import zlib

    data = bytearray(path.read_bytes())
    directory = bytearray(data[fields["directory"]:fields["directory"] + 36])
    page = bytearray(data[fields["directory"] + 36:])
    if page_bits is not None:
        bit, width, value = page_bits
        bits = "".join(f"{b:08b}" for b in page)
        bits = bits[:bit] + format(value, f"0{width}b") + bits[bit + width:]
        page = bytearray(int(bits[i:i + 8], 2) for i in range(0, len(bits), 8))
    struct.pack_into("<I", directory, 32, zlib.crc32(page))
    h = dict(header or fields["header"])
    h["directory_crc32"] = zlib.crc32(directory)
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    deflated = packer.compress(json.dumps(h).encode()) + packer.flush()
    prefix = bytes(data[:8]) + struct.pack("<HHI", 2, 0, len(deflated)) + deflated
    path.write_bytes(prefix + struct.pack("<I", zlib.crc32(prefix)) + bytes(directory) + bytes(page))


@pytest.mark.parametrize("kind", ["cells_one_more", "no_cells", "no_cell_field", "step_not_a_number"])
def test_crafted_version_2_maps_are_refused_in_one_line(tmp_path: Path, kind: str) -> None:
    from mapdb.errors import MapFormatError

    path, fields = _one_page_map(tmp_path)
    with open_map(path) as m:
        table = m.page_directory
        assert len(table) == 1
        ex, ey = int(table["ex"][0]), int(table["ey"][0])
    key_bits = max(1, ((ex + 1) * (ey + 1) - 1).bit_length())
    k_field = 8 + 2 * (8 + 16 + key_bits + 16) + 16  # the run count byte, two run heads, then E: K
    header = dict(fields["header"])
    if kind == "cells_one_more":
        _rewritten(path, fields, page_bits=(k_field, 16, 4))  # fewer cells (128 m) hold the 4 objects
        problem = "page 0: "  # the stream no longer adds up: refused, whichever rule it breaks first
    elif kind == "no_cells":
        _rewritten(path, fields, page_bits=(k_field, 16, 0))
        problem = "0 elevation cells for 4 objects"
    elif kind == "no_cell_field":
        del header["elevation_cell"]
        _rewritten(path, fields, header=header)
        problem = "lacks the field 'elevation_cell'"
    else:
        header["elevation_step_m"] = "1"
        _rewritten(path, fields, header=header)
        problem = "'elevation_step_m' must be"
    with pytest.raises(MapFormatError, match=problem) as caught:
        with open_map(path) as m:
            m.all()
    assert "\n" not in str(caught.value)
    result = run("info", path)
    assert_one_line_error(result, str(path), problem.split("'")[0])
