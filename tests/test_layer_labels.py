"""``mapdb build --label`` and ``--label-map``: users' own layers without mapdb's label column."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import geopandas as gpd
import pytest
from click.testing import CliRunner
from mapdb_cli.main import cli
from shapely.geometry import Point, box

from mapdb.classmap import load_class_table
from mapdb.errors import LabelTableError, SourceError
from mapdb.labels import default_label_table
from mapdb.mapfile.reader import open_map
from mapdb.sources.layers import read_layer

LABELS = default_label_table().labels
X0, Y0 = 500_000.0, 5_000_000.0


def footprints(path: Path) -> Path:
    """Five features with an OSM-style ``building`` column (no ``label`` column), in UTM 32N."""
    frame = gpd.GeoDataFrame(
        {"building": ["yes", "house", "garage", None, "shed"], "kind": [1.0, 1.0, 2.0, 3.0, 1.0]},
        geometry=[box(X0 + 40 * i, Y0, X0 + 40 * i + 10, Y0 + 10) for i in range(5)], crs="EPSG:32632")
    frame.to_file(path, engine="pyogrio")
    return path


def test_one_label_for_a_layer_without_label_column(tmp_path: Path) -> None:
    path = footprints(tmp_path / "fp.gpkg")
    with pytest.raises(SourceError, match="no column 'label' .*; give every feature one label with --label NAME"):
        read_layer(path, LABELS)
    objects = read_layer(path, LABELS, label="building")
    assert objects.counts() == {"building": 5}
    assert sorted(objects.x.tolist()) == [X0 + 40 * i + 5 for i in range(5)]


def test_label_map_maps_a_column_and_counts_the_rest(tmp_path: Path) -> None:
    path = footprints(tmp_path / "fp.gpkg")
    table_path = tmp_path / "map.toml"
    table_path.write_text('column = "building"\n[classes]\nyes = "building"\nhouse = "building"\ngarage = "parking"\n')
    counts: Counter[str] = Counter()
    objects = read_layer(path, LABELS, label_map=load_class_table(table_path, LABELS, column=True), counts=counts)
    assert objects.counts() == {"building": 2, "parking": 1}
    assert counts["unmapped_labels"] == 1  # the shed; the feature with no value is skipped as a row without a label
    # Integer keys match a float column's values ("1.0"); the column comes from --label-column here.
    table_path.write_text('[classes]\n1 = "building"\n2 = "parking"\n')
    by_kind = read_layer(path, LABELS, label_column="kind", label_map=load_class_table(table_path, LABELS, column=True))
    assert by_kind.counts() == {"building": 3, "parking": 1}


def test_build_cli_label_and_label_map(tmp_path: Path) -> None:
    layer = footprints(tmp_path / "fp.geojson")
    out = tmp_path / "fp.mapdb"
    runner = CliRunner()
    result = runner.invoke(cli, ["build", str(layer), "-o", str(out), "--label", "building", "-q"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["labels"] == {"building": 5}
    with open_map(out) as m:
        assert m.label_counts == {"building": 5}
    table = tmp_path / "map.toml"
    table.write_text('column = "building"\n[classes]\nyes = "building"\nshed = "building"\n')
    mapped = runner.invoke(cli, ["build", str(layer), "-o", str(out), "--label-map", str(table), "--overwrite", "-q"])
    summary = json.loads(mapped.stdout)
    assert summary["labels"] == {"building": 2} and summary["skipped"] == {"unmapped_labels": 2}
    table.write_text('[classes]\nyes = "bulding"\n')
    bad = runner.invoke(cli, ["build", str(layer), "-o", str(tmp_path / "x.mapdb"), "--label-map", str(table)])
    assert bad.exit_code == 1 and not (tmp_path / "x.mapdb").exists()
    assert bad.stderr.startswith(f"mapdb: error: {table}: classes.yes: unknown label 'bulding'")
    unknown = runner.invoke(cli, ["build", str(layer), "-o", str(tmp_path / "x.mapdb"), "--label", "castle"])
    assert unknown.exit_code == 1 and "--label: unknown label 'castle'" in unknown.stderr


def test_label_column_wins_over_label(tmp_path: Path) -> None:
    """--label fills in only for layers that lack the column: a labelled layer keeps its own labels."""
    frame = gpd.GeoDataFrame({"label": ["park"]}, geometry=[Point(X0, Y0)], crs="EPSG:32632")
    path = tmp_path / "labelled.gpkg"
    frame.to_file(path, engine="pyogrio")
    assert read_layer(path, LABELS, label="building").counts() == {"park": 1}
    with pytest.raises(LabelTableError):
        load_class_table(tmp_path / "labelled.gpkg", LABELS)


@pytest.mark.parametrize("loader", ["mapdb.classmap:load_class_table:, ['building']", "mapdb.labels:load_label_table:"])
def test_a_fifo_as_a_class_table_or_label_file_is_refused_not_waited_on(tmp_path: Path, loader: str) -> None:
    # In a child process with a timeout: the old code blocked forever opening a FIFO with no writer.
    import os
    import subprocess
    import sys

    fifo = tmp_path / "classes.toml"
    os.mkfifo(fifo)
    module, name, more = loader.split(":")
    code = (f"import sys; from {module} import {name}\n"
            f"try:\n    {name}(sys.argv[1]{more})\nexcept Exception as exc:\n    print(type(exc).__name__, exc)\n")
    done = subprocess.run([sys.executable, "-c", code, str(fifo)], capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == f"MapdbIOError {fifo}: is a FIFO, not a label file", done.stderr
