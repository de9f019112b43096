"""The stored index of a map with blocks (``mapdb index``): built without the blocks, it serves the point images
(the answers of the map built without blocks and its index) and leaves the mask images to the in-memory search."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from mapdb.labels import BLOCK_LABEL, default_label_table
from mapdb.localize.localizer import Localizer, StoredQuads
from mapdb.mapfile.queries import MemoryMap
from mapdb.mapfile.reader import open_map
from mapdb.mapfile.writer import write_map
from mapdb.match.index.stored import StoredQuadIndex, build_index, index_path
from mapdb.match.quads import QuadIndex
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_images


def _town() -> Objects:
    """A grid of houses where every fourth pair touches (a block at the pair's centre, of their two areas)."""
    rng = np.random.default_rng(5)
    x, y = np.meshgrid(np.arange(0.0, 600.0, 23.0), np.arange(0.0, 600.0, 29.0))
    x, y = x.ravel() + rng.uniform(-6, 6, x.size) + 500_000, y.ravel() + rng.uniform(-6, 6, x.size) + 5_000_000
    pairs = np.arange(0, x.size - 1, 4)
    bx, by = (x[pairs] + x[pairs + 1]) / 2, (y[pairs] + y[pairs + 1]) / 2
    names = ["building"] * x.size + [BLOCK_LABEL] * pairs.size
    area = np.concatenate([np.full(x.size, 100.0), np.full(pairs.size, 200.0)])
    return Objects.from_names(np.concatenate([x, bx]), np.concatenate([y, by]), names, area=area, crs="EPSG:32632",
                              labels=default_label_table().labels)


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> tuple[Path, Path]:
    """The town with its blocks and without them, each with its index."""
    d = tmp_path_factory.mktemp("blocks_index")
    town = _town()
    write_map(d / "blocks.mapdb", town)
    write_map(d / "plain.mapdb", town.take(town.names() != BLOCK_LABEL))
    for name in ("blocks", "plain"):
        build_index(d / f"{name}.mapdb", workers=1)
    return d / "blocks.mapdb", d / "plain.mapdb"


def _images(path: Path) -> list[dict]:
    with open_map(path) as m:
        plain = MemoryMap(m.all().take(m.all().names() != BLOCK_LABEL))
    return simulate_images(plain, 8, altitude=150.0, fov_deg=60.0, yaw="random", min_objects=10, seed=2)


def _masks(images: list[dict]) -> list[dict]:
    """The images with a pixel area on every building: the mask blobs the folded view is searched for."""
    masks = copy.deepcopy(images)
    for im in masks:
        for o in im["objects"]:
            o["area_px"] = 400.0
    return masks


def _answers(path: Path, images: list[dict], warnings: list[str]) -> tuple[list, Localizer]:
    with open_map(path) as m:
        loc = Localizer(m)
        loc.warn = warnings.append
        found = [(a.status, a.x, a.y, a.inliers) for a in (loc.localize(im) for im in images)]
    return found, loc


def test_point_images_use_the_index_and_answer_as_the_map_without_blocks(maps) -> None:
    with_blocks, plain = maps
    images = _images(with_blocks)
    said: list[str] = []
    mine, loc = _answers(with_blocks, images, said)
    theirs, plain_loc = _answers(plain, images, [])
    assert isinstance(loc._views[False]._whole_quads, StoredQuads) and True not in loc._views
    assert isinstance(plain_loc._whole_quads, StoredQuads)
    assert mine == theirs and sum(status == "ok" for status, *_ in mine) >= 6
    assert said == []  # no warning: the index serves every image of the run


def _quad_positions(path: Path) -> set:
    """Every quad of a map's stored index, as the sorted positions of its four objects."""
    with open_map(path) as m, StoredQuadIndex.for_map(m) as ix:
        ids = ix.quads()
        z = ix.coordinates(ids.ravel()).reshape(ids.shape)
    return {tuple(sorted(zip(row.real.tolist(), row.imag.tolist(), strict=True))) for row in z}


def test_the_index_holds_the_quads_of_the_map_without_blocks(maps) -> None:
    with_blocks, plain = maps
    mine = _quad_positions(with_blocks)
    with open_map(with_blocks) as m:
        objects = m.all()
    blocks = set(zip(objects.x[objects.names() == BLOCK_LABEL].tolist(),
                     objects.y[objects.names() == BLOCK_LABEL].tolist(), strict=True))
    assert mine == _quad_positions(plain) and len(mine) > len(objects)
    assert not any(blocks.intersection(quad) for quad in mine)


def test_mask_images_answer_as_the_in_memory_search_saying_so_once(maps, tmp_path: Path) -> None:
    with_blocks, _ = maps
    bare = tmp_path / "bare.mapdb"  # the same map without its index: the in-memory search of both views
    bare.write_bytes(with_blocks.read_bytes())
    masks = _masks(_images(with_blocks))
    said: list[str] = []
    mine, loc = _answers(with_blocks, masks, said)
    theirs, _ = _answers(bare, masks, [])
    assert mine == theirs and sum(status == "ok" for status, *_ in mine) >= 4
    assert isinstance(loc._views[True]._whole_quads, QuadIndex)
    assert len(said) == 1 and "serves point images only" in said[0]


def test_an_index_mixing_blocks_and_buildings_is_not_used(maps, tmp_path: Path, monkeypatch) -> None:
    with_blocks, _ = maps
    old = tmp_path / "old.mapdb"
    old.write_bytes(with_blocks.read_bytes())
    # The index an earlier mapdb wrote: the map's objects as one world, blocks among them.
    monkeypatch.setattr("mapdb.match.index.build.block_free_world", lambda map_, objects: None)
    build_index(old, workers=1)
    monkeypatch.undo()
    with StoredQuadIndex(index_path(old)) as ix:
        assert not ix.blocks_left_out
    images = _images(with_blocks)
    said: list[str] = []
    mine, loc = _answers(old, images, said)
    assert isinstance(loc._views[False]._whole_quads, QuadIndex)
    assert len(said) == 1 and "one world" in said[0] and "rebuild with mapdb index" in said[0]
    bare = tmp_path / "bare.mapdb"
    bare.write_bytes(with_blocks.read_bytes())
    assert mine == _answers(bare, images, [])[0]
