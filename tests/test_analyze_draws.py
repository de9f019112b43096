"""A cell's images drawn at once (mapdb.analysis.draws) against the one-image-at-a-time rule they replace:
the same generators, poses, views and images (the arrays the parser makes of the simulator's documents)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mapdb._scipy import cKDTree
from mapdb.analysis import draws
from mapdb.analysis.measures import SampleConfig
from mapdb.camera import Camera, Pose, project_to_image
from mapdb.detections.images import ImageObjects, parse_image
from mapdb.objects import Objects
from mapdb.simulation.simulate import simulate_image_at

CELL_M = 100.0


def _zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def _one_pose(seed: int, i: int, j: int, s: int, attitude_std: float) -> tuple[Pose, np.random.Generator]:
    """The documented rule, one image at a time (mapdb.analysis.measures): position, heading, roll and pitch."""
    rng = np.random.default_rng([seed, _zigzag(i), _zigzag(j), s])
    where = rng.random(2)
    heading = float(rng.uniform(0.0, 360.0))
    roll, pitch = (float(a) for a in attitude_std * rng.standard_normal(2))
    return Pose(float((i + where[0]) * CELL_M), float((j + where[1]) * CELL_M), 150.0, heading, roll, pitch), rng


def test_seeds_hash_as_default_rng_does() -> None:
    rows = np.random.default_rng(3).integers(0, 2**32, size=(300, 4))
    rows[:3] = [[0, 0, 0, 0], [2**32 - 1] * 4, [0, 1, 2, 3]]
    states = draws.pcg_states(rows)
    for row, (state, inc) in zip(rows.tolist(), states, strict=True):
        want = np.random.default_rng(row).bit_generator.state["state"]
        assert (state, inc) == (want["state"], want["inc"])


@pytest.mark.parametrize("seed", [0, 7, 2**40])  # 2**40: SeedSequence's longer mixing, through default_rng
def test_poses_are_the_one_image_rule(seed: int) -> None:
    cells = np.array([[3, 5], [-2, 7], [0, -1], [46_500, 470_100]])
    poses = draws.cell_poses(seed, cells, 16, CELL_M, 150.0, 0.05)
    for (i, j), cell in zip(cells.tolist(), poses, strict=True):
        for s in range(16):
            want, rng = _one_pose(seed, i, j, s, 0.05)
            assert cell.pose(s) == want
            # the generator an image's errors draw from starts where the pose's draws left it
            assert draws.positioned(cell, s, seed, i, j).bit_generator.state == rng.bit_generator.state
            reused = draws.positioned(cell, s, seed, i, j, np.random.default_rng(99))
            assert reused.bit_generator.state == rng.bit_generator.state


def _world(n: int = 4000, seed: int = 1) -> Objects:
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-300.0, 700.0, n), rng.uniform(-300.0, 700.0, n)
    label = rng.integers(0, 3, n).astype(np.int32)
    return Objects(x, y, label, np.zeros(n), ("building", "parking", "building_block"), "EPSG:32631")


def _one_view(objects: Objects, tree, pose: Pose, camera: Camera, reach: float) -> np.ndarray:
    near = np.sort(np.asarray(tree.query_ball_point((pose.x, pose.y), reach), np.int64))
    u, v = project_to_image(objects.x[near], objects.y[near], pose, camera)
    return near[np.isfinite(u) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)]


def _one_image(objects: Objects, tree, pose: Pose, camera: Camera, reach: float) -> tuple[np.ndarray, ...]:
    """An image's objects a detector can report (blocks left out, as the simulator does) and their pixels."""
    shown = _one_view(objects, tree, pose, camera, reach)
    shown = shown[objects.label[shown] != objects.labels.index("building_block")]
    return (shown, *project_to_image(objects.x[shown], objects.y[shown], pose, camera))


@pytest.mark.parametrize("margin", [draws.MARGIN_M, 1e6])  # 1e6: every image's objects within reach the tree's
def test_views_are_each_images_own(monkeypatch, margin: float) -> None:
    monkeypatch.setattr(draws, "MARGIN_M", margin)
    objects = _world()
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    cfg = SampleConfig(attitude_std=3.0)  # tilted views: objects far from the nadir come into view
    cells = np.array([[i, j] for i in range(4) for j in range(4)])
    shown = 0
    for (i, j), poses in zip(cells.tolist(), draws.cell_poses(0, cells, 16, CELL_M, 150.0, 3.0), strict=True):
        near = draws.near_cells(tree, np.array([[(i + 0.5) * CELL_M, (j + 0.5) * CELL_M]]),
                                0.5 * np.hypot(CELL_M, CELL_M), cfg.reach_m)[0]
        views = draws.cell_views(objects, tree, near, poses, cfg.camera, cfg.reach_m)
        for s in range(16):
            want = _one_view(objects, tree, poses.pose(s), cfg.camera, cfg.reach_m)
            assert np.array_equal(views.near[views.seen[s]], want)
            # the objects and pixels the image is made of are one image's, bit for bit (blocks left out)
            got, one = views.shown(s), _one_image(objects, tree, poses.pose(s), cfg.camera, cfg.reach_m)
            assert all(np.array_equal(a, b) for a, b in zip(got, one, strict=True))
            shown += want.size
    assert shown > 16 * 16 * 10  # images that show objects were compared, not empty ones


def _same_image(got: ImageObjects, want: ImageObjects) -> None:
    """Every field equal, arrays of the same dtype and values (``==`` on the dataclass compares arrays' truth)."""
    for f in dataclasses.fields(ImageObjects):
        a, b = getattr(got, f.name), getattr(want, f.name)
        if isinstance(b, np.ndarray):
            assert isinstance(a, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b), f.name
            assert [type(v) for v in a.tolist()] == [type(v) for v in b.tolist()], f.name
        else:
            assert a == b and type(a) is type(b), f.name


@pytest.mark.parametrize("prior", [50.0, None])
def test_a_localized_image_is_the_simulators(monkeypatch, prior: float | None) -> None:
    objects = _world()
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    cfg = SampleConfig(attitude_std=0.5, pixel_std=1.0, miss_rate=0.1, spurious_rate=0.2, label_noise=0.3,
                       prior=prior)
    counts = {"building": 900, "parking": 300, "building_block": 40}
    detector = draws.detector_of(counts, cfg.pixel_std, cfg.miss_rate, cfg.spurious_rate, cfg.label_noise)
    cell = draws.cell_poses(5, np.array([[1, 2]]), 16, CELL_M, 150.0, 0.5)[0]
    for s in range(16):
        pose = cell.pose(s)
        got = draws.cell_image(objects, *_one_image(objects, tree, pose, cfg.camera, cfg.reach_m), pose, cfg.camera,
                               draws.positioned(cell, s, 5, 1, 2), detector, cfg.prior, f"1,2,{s}")
        near = np.sort(np.asarray(tree.query_ball_point((pose.x, pose.y), cfg.reach_m), np.int64))
        want = simulate_image_at(objects.take(near), pose, cfg.camera, _one_pose(5, 1, 2, s, 0.5)[1],
                                 pixel_std=cfg.pixel_std, miss_rate=cfg.miss_rate, spurious_rate=cfg.spurious_rate,
                                 label_noise=cfg.label_noise, label_counts=counts, with_prior=cfg.prior,
                                 image_id=f"1,2,{s}")
        want.pop("truth")
        assert isinstance(got, ImageObjects)
        _same_image(got, parse_image(want))
        assert len(got) and (got.prior is None) == (prior is None)
    # An image of more objects than the parser takes stays a document, which the localizer refuses as before.
    monkeypatch.setattr(draws, "MAX_OBJECTS", 3)
    pose = cell.pose(0)
    got = draws.cell_image(objects, *_one_image(objects, tree, pose, cfg.camera, cfg.reach_m), pose, cfg.camera,
                           draws.positioned(cell, 0, 5, 1, 2), detector, cfg.prior, "1,2,0")
    near = np.sort(np.asarray(tree.query_ball_point((pose.x, pose.y), cfg.reach_m), np.int64))
    want = simulate_image_at(objects.take(near), pose, cfg.camera, _one_pose(5, 1, 2, 0, 0.5)[1],
                             pixel_std=cfg.pixel_std, miss_rate=cfg.miss_rate, spurious_rate=cfg.spurious_rate,
                             label_noise=cfg.label_noise, label_counts=counts, with_prior=cfg.prior, image_id="1,2,0")
    want.pop("truth")
    assert got == want and len(want["objects"]) > 3
