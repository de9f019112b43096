"""What keeps a small build quick gives the same map: objects kept in memory or in files (chosen by the inputs'
size, or forced), and the UTM zone found without a query of the whole CRS database."""

from __future__ import annotations

from pathlib import Path

import pytest
from osmxml import OsmXml, square
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from mapdb.build.pipeline import build_map, utm_crs_for
from mapdb.build.reading import SPOOL_INPUT_BYTES, _Spooling
from mapdb.errors import SourceError


def village() -> OsmXml:
    doc = OsmXml()
    for i in range(4):
        doc.ring(square(i * 40.0, 0.0, 8), {"building": "yes"})
        doc.ring(square(i * 40.0, 60.0, 12), {"leisure": "park"})
        doc.node(i * 40.0, 30.0, {"building": "yes"})
    return doc


@pytest.mark.parametrize("spool", ["file", "memory"])
def test_objects_in_memory_or_in_files_give_the_automatic_choices_map(tmp_path: Path, spool: str,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")  # the header's creation time, so bytes compare
    source = village().write(tmp_path / "village.osm")
    work = tmp_path / "work"
    work.mkdir()
    spooled: dict[str, bool] = {}

    def build(choice: str) -> bytes:
        def say(message: str) -> None:
            if message.startswith("projecting"):  # every source read: are its objects in files?
                spooled[choice] = any(p.name.startswith("osm-") for p in work.rglob("*"))
        out = tmp_path / f"{choice}.mapdb"
        build_map([source], out, spool=choice, index_dir=work, progress=say)
        return out.read_bytes()

    assert build("auto") == build(spool)
    assert spooled == {"auto": False, spool: spool == "file"}  # a village's objects stay in memory
    assert list(work.iterdir()) == []


def test_the_automatic_choice_holds_up_to_so_many_bytes_of_input_in_memory(tmp_path: Path) -> None:
    def sized(name: str, size: int) -> Path:
        path = tmp_path / name
        with open(path, "wb") as f:
            f.truncate(size)  # sparse: only the size counts
        return path

    small, big = sized("small.osm.pbf", 1000), sized("big.osm.pbf", SPOOL_INPUT_BYTES)
    half, other_half = sized("a.osm.pbf", SPOOL_INPUT_BYTES // 2), sized("b.osm.pbf", SPOOL_INPUT_BYTES // 2)
    raster = sized("land.tif", 2 * SPOOL_INPUT_BYTES)  # read into memory whatever the choice: not counted
    auto, where = _Spooling("DIR", "auto"), "DIR"
    assert auto.spool_dirs([small, big]) == [None, where]
    assert auto.spool_dirs([half, raster, other_half, small]) == [None, None, where, None]
    assert _Spooling("DIR", "memory").spool_dirs([big, small]) == [None, None]
    assert _Spooling("DIR", "file").spool_dirs([small, big]) == [where, where]


def test_a_spool_that_is_no_choice_is_refused(tmp_path: Path) -> None:
    source = village().write(tmp_path / "village.osm")
    with pytest.raises(SourceError, match="spool 'disk'"):
        build_map([source], tmp_path / "m.mapdb", spool="disk")
    assert not (tmp_path / "m.mapdb").exists()


def _zone_by_query(lon: float, lat: float) -> str:
    """The zone as utm_crs_for found it before: the database's zones holding the point, the formula's first."""
    found = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat))
    wanted = f"{326 if lat >= 0 else 327}{int((lon + 180) // 6) % 60 + 1:02d}"
    codes = [c.code for c in found]
    return f"EPSG:{wanted if wanted in codes else codes[0]}"


@pytest.mark.parametrize(("lon", "lat"), [(1.52, 42.51), (-70.0, -33.0), (179.9, -10.0), (7.0, 60.0),
                                          (3.0, 83.99), (3.0, -79.99), (6.0, 10.0), (3.0, 0.0), (180.0, 10.0)])
def test_the_utm_zone_is_the_one_the_database_query_gives(lon: float, lat: float) -> None:
    # Inside a zone it comes without the query; on a zone's edge (the last three) from it, as before.
    assert utm_crs_for(lon, lat) == _zone_by_query(lon, lat)


def test_the_cli_spool_option_forces_files_and_refuses_other_words(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from click.testing import CliRunner
    from mapdb_cli.main import cli

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    source = village().write(tmp_path / "village.osm")
    work = tmp_path / "work"
    work.mkdir()
    maps = {}
    for choice in ("auto", "file"):
        maps[choice] = tmp_path / f"{choice}.mapdb"
        done = CliRunner().invoke(cli, ["build", str(source), "-o", str(maps[choice]), "--spool", choice,
                                        "--index-dir", str(work), "-q"])
        assert done.exit_code == 0, done.output
    assert maps["auto"].read_bytes() == maps["file"].read_bytes()
    assert list(work.iterdir()) == []
    refused = CliRunner().invoke(cli, ["build", str(source), "-o", str(tmp_path / "x.mapdb"), "--spool", "disk"])
    assert refused.exit_code == 2 and "disk" in refused.output
    assert not (tmp_path / "x.mapdb").exists()
