"""``mapdb merge``: maps of overlapping regions become one, shared objects kept once; refusals."""

from __future__ import annotations

import hashlib
import json
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import osmium
import pytest
from osmxml import OsmXml, square

from mapdb.build.merge import content_digest, merge_maps
from mapdb.build.pipeline import build_map
from mapdb.errors import SourceError
from mapdb.labels import default_label_table
from mapdb.mapfile.reader import open_map

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def strip(doc: OsmXml, first: int, last: int, shift: float = 0.0) -> OsmXml:
    """Buildings first..last of a row, 40 m apart, and a road under them with its junctions."""
    for i in range(first, last + 1):
        doc.ring(square(i * 40.0 + shift, 0.0, 8.0), {"building": "yes"})
        doc.node(i * 40.0 + 20, 30.0, {"building": "yes"})
    return doc


def two_regions(tmp_path: Path) -> tuple[Path, Path, Path]:
    """West holds buildings 0..9, east 6..15: four of each kind in both; and the whole 0..15."""
    west = strip(OsmXml(), 0, 9).write(tmp_path / "west.osm")
    east = strip(OsmXml(), 6, 15).write(tmp_path / "east.osm")
    whole = strip(OsmXml(), 0, 15).write(tmp_path / "whole.osm")
    return west, east, whole


def positions(path: Path) -> list[tuple[float, float, str, float]]:
    with open_map(path) as m:
        o = m.all()
    return sorted(zip(o.x.tolist(), o.y.tolist(), o.names().tolist(), o.area.tolist(), strict=True))


def body(path: Path) -> bytes:
    """A map's directory and pages (what the header describes)."""
    data = path.read_bytes()
    return data[20 + int.from_bytes(data[12:16], "little"):]


def test_overlapping_maps_keep_shared_objects_once(tmp_path: Path) -> None:
    west, east, whole = two_regions(tmp_path)
    for name in ("west", "east", "whole"):
        build_map([tmp_path / f"{name}.osm"], tmp_path / f"{name}.mapdb", crs="EPSG:32632")
    summary = merge_maps([tmp_path / "west.mapdb", tmp_path / "east.mapdb"], tmp_path / "merged.mapdb")
    assert summary["duplicates"] == 8 and summary["count"] == 32
    assert [i["kept"] for i in summary["inputs"]] == [20, 12]
    assert positions(tmp_path / "merged.mapdb") == positions(tmp_path / "whole.mapdb")
    assert body(tmp_path / "merged.mapdb") == body(tmp_path / "whole.mapdb")
    with open_map(tmp_path / "merged.mapdb") as m:
        sources = m.metadata["sources"]
        merged = m.metadata["build"]["merged"]
    assert [(s["name"], s["map"]) for s in sources] == [("west.osm", "west.mapdb"), ("east.osm", "east.mapdb")]
    assert [entry["name"] for entry in merged] == ["west.mapdb", "east.mapdb"]


def test_maps_in_other_crss_are_reprojected_and_still_matched(tmp_path: Path) -> None:
    west, east, whole = two_regions(tmp_path)
    build_map([west], tmp_path / "west.mapdb", crs="EPSG:32632")
    build_map([east], tmp_path / "east.mapdb", crs="EPSG:3857")
    build_map([whole], tmp_path / "whole.mapdb", crs="EPSG:32632")
    summary = merge_maps([tmp_path / "west.mapdb", tmp_path / "east.mapdb"], tmp_path / "merged.mapdb")
    assert summary["crs"] == "EPSG:32632" and summary["duplicates"] == 8 and summary["count"] == 32
    assert summary["warnings"] and "reprojected" in summary["warnings"][0]
    got, want = positions(tmp_path / "merged.mapdb"), positions(tmp_path / "whole.mapdb")
    assert [g[2] for g in got] == [w[2] for w in want]
    # Reprojected positions stay within a quantum (and a rounding) of the direct build's.
    assert max(abs(g[0] - w[0]) + abs(g[1] - w[1]) for g, w in zip(got, want, strict=True)) <= 0.2 + 1e-9
    explicit = merge_maps([tmp_path / "west.mapdb", tmp_path / "east.mapdb"], tmp_path / "m.mapdb", crs="EPSG:3857")
    assert explicit["crs"] == "EPSG:3857" and explicit["count"] == 32


def test_different_quanta_or_label_tables_are_refused_saying_what_differs(tmp_path: Path) -> None:
    west, east, _ = two_regions(tmp_path)
    build_map([west], tmp_path / "west.mapdb")
    build_map([east], tmp_path / "coarse.mapdb", quantum=0.5)
    with pytest.raises(SourceError, match=r"coarse.mapdb: quantum 0.5 m, but .*west.mapdb has 0.1 m.*--quantum 0.1"):
        merge_maps([tmp_path / "west.mapdb", tmp_path / "coarse.mapdb"], tmp_path / "out.mapdb")
    labels = tmp_path / "labels.toml"
    names = ", ".join(f'"{name}"' for name in (*default_label_table().labels, "house"))
    labels.write_text(f"labels = [{names}]\n", encoding="utf-8")
    build_map([east], tmp_path / "other.mapdb", labels=labels)
    with pytest.raises(SourceError, match=r"other.mapdb: its label table differs .*only in other.mapdb: house.*"
                                          r"same --labels file"):
        merge_maps([tmp_path / "west.mapdb", tmp_path / "other.mapdb"], tmp_path / "out.mapdb")
    assert not (tmp_path / "out.mapdb").exists()


@pytest.mark.slow
def test_cli_refusals_are_one_line_and_leave_no_output(tmp_path: Path) -> None:
    west, east, _ = two_regions(tmp_path)
    build_map([west], tmp_path / "west.mapdb")
    build_map([east], tmp_path / "coarse.mapdb", quantum=0.5)
    (tmp_path / "junk.mapdb").write_bytes(b"not a map at all")
    cases = [(["west.mapdb", "coarse.mapdb", "-o", "out.mapdb"], "quantum 0.5 m"),
             (["west.mapdb", "junk.mapdb", "-o", "out.mapdb"], "junk.mapdb"),
             (["west.mapdb", "-o", "west.mapdb", "--overwrite"], "same file as input"),
             (["west.mapdb", "coarse.mapdb", "-o", "out.mapdb", "--crs", "EPSG:4326"], "projected CRS")]
    for args, words in cases:
        run = subprocess.run([sys.executable, "-m", "mapdb_cli", "merge", "-q", *args], cwd=tmp_path,
                             capture_output=True, text=True)
        assert run.returncode == 1 and run.stderr.startswith("mapdb: error:") and words in run.stderr, run.stderr
    assert not (tmp_path / "out.mapdb").exists()


def _small_file_limit() -> None:
    # Stands for a full disk: writes past 2 KiB fail (EFBIG) like writes on a full file system (ENOSPC).
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))


def test_a_failed_write_keeps_the_old_output(tmp_path: Path) -> None:
    sides = [strip(OsmXml(), 0, 200).write(tmp_path / "a.osm"), strip(OsmXml(), 150, 400).write(tmp_path / "b.osm")]
    for side in sides:
        build_map([side], side.with_suffix(".mapdb"), crs="EPSG:32632")
    out = tmp_path / "out.mapdb"
    out.write_bytes(b"the old map")
    run = subprocess.run([sys.executable, "-m", "mapdb_cli", "merge", "a.mapdb", "b.mapdb", "-o", "out.mapdb",
                          "--overwrite", "-q"], cwd=tmp_path, capture_output=True, text=True,
                         preexec_fn=_small_file_limit)
    assert run.returncode == 1 and run.stderr.count("\n") == 1
    assert run.stderr.startswith("mapdb: error: out.mapdb: cannot write")
    assert out.read_bytes() == b"the old map"
    merge_maps([tmp_path / "a.mapdb", tmp_path / "b.mapdb"], tmp_path / "free.mapdb")
    assert (tmp_path / "free.mapdb").stat().st_size > 2048  # without the limit the merged map is bigger
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_the_cli_prints_a_json_summary(tmp_path: Path) -> None:
    west, east, _ = two_regions(tmp_path)
    build_map([west], tmp_path / "west.mapdb")
    build_map([east], tmp_path / "east.mapdb")
    run = subprocess.run([sys.executable, "-m", "mapdb_cli", "merge", "west.mapdb", "east.mapdb", "-o", "m.mapdb",
                          "-q"], cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert summary["count"] == 32 and summary["duplicates"] == 8


# ------------------------------------------------------------------------------------------ Andorra in two


def cut(source: Path, out: Path, minlon: float, maxlon: float) -> None:
    """An extract of the nodes within [minlon, maxlon], with complete ways and multipolygons (osmium's
    "smart" strategy), written with pyosmium."""
    inside, way_refs, kept_ways, members = set(), {}, set(), {}
    for obj in osmium.FileProcessor(str(source)):
        kind = obj.type_str()
        if kind == "n" and obj.location.valid() and minlon <= obj.location.lon <= maxlon:
            inside.add(obj.id)
        elif kind == "w":
            way_refs[obj.id] = [n.ref for n in obj.nodes]
            if any(r in inside for r in way_refs[obj.id]):
                kept_ways.add(obj.id)
        elif kind == "r":
            members[obj.id] = [(m.type, m.ref) for m in obj.members]
    kept_relations = {rid for rid, ms in members.items()
                      if any((t == "w" and r in kept_ways) or (t == "n" and r in inside) for t, r in ms)}
    kept_ways |= {r for rid in kept_relations for t, r in members[rid] if t == "w" and r in way_refs}
    nodes = inside | {r for w in kept_ways for r in way_refs[w]}
    keep = {"n": nodes, "w": kept_ways, "r": kept_relations}
    with osmium.SimpleWriter(str(out)) as writer:
        for obj in osmium.FileProcessor(str(source)):
            if obj.id in keep[obj.type_str()]:
                writer.add(obj)


def andorra_halves(tmp_path: Path) -> tuple[Path, list[tuple[Path, tuple[float, float, float, float]]]]:
    andorra = DATA / "osm" / "andorra-2021-06-22.osm.pbf"
    if not andorra.exists():
        pytest.skip(f"no real data at {DATA} (../shared/data beside the checkout)")
    # Two extracts overlapping by 0.07 degrees (about 6 km), each built for the region it was cut for
    # (an extract holds whole ways reaching beyond its region, and objects there may be partial).
    halves = [(tmp_path / "west.osm.pbf", (-180.0, -90.0, 1.62, 90.0)),
              (tmp_path / "east.osm.pbf", (1.55, -90.0, 180.0, 90.0))]
    for path, box in halves:
        cut(andorra, path, box[0], box[2])
    return andorra, halves


@pytest.mark.slow
def test_andorra_in_two_overlapping_halves_merges_into_the_whole(tmp_path: Path) -> None:
    andorra, halves = andorra_halves(tmp_path)
    whole = build_map([andorra], tmp_path / "whole.mapdb")
    maps = []
    for path, box in halves:
        maps.append(path.with_suffix(".mapdb"))
        build_map([path], maps[-1], bbox=box, crs=whole["crs"])
    summary = merge_maps(maps, tmp_path / "merged.mapdb")
    assert summary["duplicates"] > 1000
    assert summary["labels"] == whole["labels"] and summary["count"] == whole["count"]
    assert body(tmp_path / "merged.mapdb") == body(tmp_path / "whole.mapdb")


@pytest.mark.slow
def test_andorra_halves_built_in_parallel_on_a_local_cluster(tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    andorra, halves = andorra_halves(tmp_path)
    whole = build_map([andorra], tmp_path / "whole.mapdb")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        futures = [client.submit(build_map, [path], path.with_suffix(".mapdb"), bbox=box, crs=whole["crs"])
                   for path, box in halves]
        client.gather(futures)
    merge_maps([path.with_suffix(".mapdb") for path, _ in halves], tmp_path / "merged.mapdb")
    assert body(tmp_path / "merged.mapdb") == body(tmp_path / "whole.mapdb")
    digests = {hashlib.sha256(body(p.with_suffix(".mapdb"))).hexdigest() for p, _ in halves}
    assert len(digests) == 2


def test_content_digest_ignores_only_the_creation_time(tmp_path: Path) -> None:
    west, _, _ = two_regions(tmp_path)
    build_map([west], tmp_path / "a.mapdb")
    build_map([west], tmp_path / "b.mapdb")
    build_map([west], tmp_path / "c.mapdb", quantum=0.2)
    assert content_digest(tmp_path / "a.mapdb") == content_digest(tmp_path / "b.mapdb")
    assert content_digest(tmp_path / "a.mapdb") != content_digest(tmp_path / "c.mapdb")
    assert np.unique([content_digest(tmp_path / n) for n in ("a.mapdb", "c.mapdb")]).size == 2
