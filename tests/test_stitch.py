"""Fixes from several frames (:mod:`mapdb.navigation.stitch`): frames too sparse alone, fixed when stitched; never a
wrong place.

The flights are ideal ones (``mapdb simulate flight``) over synthetic towns of random labelled objects, with every
frame thinned to the objects of a sparse share of the ground (the same ground objects in every frame, as a
detector that misses some buildings misses them from frame to frame): a handful an image, too few for a frame's
query to be certain alone.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mapdb.detections.images import parse_image
from mapdb.mapfile.queries import MemoryMap
from mapdb.navigation.flight import FlightOptions, simulate_flight
from mapdb.navigation.navigator import Navigator, NavigatorOptions
from mapdb.navigation.stitch import GATE_PX, History, Seen, min_stitched_score
from mapdb.navigation.velocity import FrameMotion, frame_points
from mapdb.objects import Objects
from mapdb.simulation.simulate import PAPER_CRS, PAPER_ORIGIN

X0, Y0 = PAPER_ORIGIN
WAYPOINTS = np.array([complex(X0 + 300, Y0 + 300), complex(X0 + 900, Y0 + 300), complex(X0 + 900, Y0 + 900)])
SHARED = next((p for p in (Path(__file__).resolve().parents[2] / "shared" / "data" / "osm",
                           Path("/work/shared/data/osm")) if p.exists()), None)


def _town(seed: int) -> MemoryMap:
    """1.2 x 1.2 km of random objects of three labels (about 15 in a 100 m, 60 degree image)."""
    rng = np.random.default_rng(seed)
    n = 2200
    names = rng.choice(["building", "road_intersection", "parking"], size=n, p=[0.7, 0.2, 0.1])
    return MemoryMap(Objects.from_names(X0 + rng.uniform(0, 1200, n), Y0 + rng.uniform(0, 1200, n), names,
                                        crs=PAPER_CRS))


@pytest.fixture(scope="module")
def town() -> MemoryMap:
    return _town(7)


def _sparse(frames: list[dict], keep_every: int) -> list[dict]:
    """Each frame with only the objects of every ``keep_every``-th map object (the same ground objects in all)."""
    out = []
    for f in frames:
        index = f["truth"]["map_index"]
        objects = [o for o, i in zip(f["objects"], index, strict=True) if i >= 0 and i % keep_every == 0]
        out.append({**f, "objects": objects})
    return out


def _flight(town: MemoryMap, seconds: float, keep_every: int = 3) -> list[dict]:
    options = FlightOptions(length_m=20.0 * seconds, altitude_m=100.0, fov_deg=60.0, pixel_std=0.5,
                            attitude_std=0.1, fps=5.0)
    return _sparse(simulate_flight(town, options, WAYPOINTS), keep_every)


def _navigate(map_: MemoryMap, frames: list[dict], stitch: int, initial=None, pose_prior: bool = True) -> list:
    navigator = Navigator(map_, NavigatorOptions(stitch_frames=stitch, pose_prior=pose_prior), initial=initial)
    return [navigator.step(f, f"frame {i}") for i, f in enumerate(frames)]


def test_frames_with_too_few_objects_get_fixes_from_the_stitched_frames_and_the_record_names_them(town) -> None:
    """An ideal flight whose every other frame from 4 s on keeps only its 5 objects nearest the centre."""
    options = FlightOptions(length_m=160.0, altitude_m=100.0, fov_deg=60.0, pixel_std=0.5, attitude_std=0.1, fps=5.0)
    frames = simulate_flight(town, options, WAYPOINTS)
    thinned = list(range(20, 36, 2))
    for k in thinned:
        objects = sorted(frames[k]["objects"], key=lambda o: (o["x"] - 320.0) ** 2 + (o["y"] - 240.0) ** 2)
        frames[k] = {**frames[k], "objects": objects[:5]}
    # Without the pose prior (which places most five-object frames alone: tests/test_pose_prior.py).
    alone = _navigate(town, frames, stitch=0, pose_prior=False)
    stitched = _navigate(town, frames, stitch=5, pose_prior=False)
    # Alone, some thinned frames get no fix; stitched with the frames before them, they do.
    rescued = [k for k in thinned if alone[k].fix_frames is None and stitched[k].fix_frames is not None]
    assert rescued
    for k in rescued:
        r = stitched[k]
        assert r.fix["single"]["status"] != "used" and r.fix["stitched"]["carried"] > 0
        assert r.fix_frames is not None and len(r.fix_frames) > 1 and r.fix_frames[-1] == r.time_s
        assert r.fix_frames == sorted(r.fix_frames) and r.time_s - r.fix_frames[0] <= 5 * 0.2 + 1e-9
        assert r.to_json()["fix_frames"] == r.fix_frames
        truth = frames[k]["truth"]
        assert math.hypot(r.fix["x"] - truth["x"], r.fix["y"] - truth["y"]) < 1.0
    assert all(r.fix_frames in (None, [r.time_s]) for r in alone)  # single frames name themselves
    errors = [r.truth["error_m"] for r in stitched]
    assert max(errors) < 2.0


def test_a_frame_stitched_is_a_level_image_centred_on_the_current_nadir(town) -> None:
    frames = _flight(town, 1.0, keep_every=1)[:3]
    history = History(frames=2)
    images = [parse_image(f) for f in frames]
    codes = [np.zeros(len(im), np.int64) for im in images]
    points = [frame_points(im, c, None, None) for im, c in zip(images, codes, strict=True)]
    # A known motion: each frame is the previous one moved 10 px down (z_prev = z_cur + 10j), sigma 0.3 px.
    link = FrameMotion(1 + 0j, 10j, 0.3, 10, 10.0, True)
    for k, (im, p) in enumerate(zip(images, points, strict=True)):
        assert p is not None
        history.add(Seen(float(k), p, im.names, im.area_px, None if k == 0 else link))
    out = history.stitched(images[2], 100.0)
    assert out is not None and out.frames[-1] == 2.0 and out.carried > 0
    im = out.image
    assert im.roll_deg == 0.0 and im.width >= images[2].width and im.height >= images[2].height
    assert np.all((im.x >= 0) & (im.x <= im.width) & (im.y >= 0) & (im.y <= im.height))
    # The current frame's objects keep their place about the centre; an earlier frame's are moved by the chain.
    z = (im.x - im.width / 2) + 1j * (im.height / 2 - im.y)
    assert np.min(np.abs(z[:, None] - points[2].z[None, :]), axis=0).max() < 1e-9
    carried = points[0].z - 20j  # two links back
    near = np.min(np.abs(z[:, None] - carried[None, :]), axis=0)
    assert np.all(near <= GATE_PX)  # each carried object is in the image, or merged with one within the gate
    assert min_stitched_score(-4.0) > 4.0


def test_stitching_never_accepts_a_place_in_another_town(town) -> None:
    """Sparse frames of one town navigated against another town's map: no stitched query is accepted."""
    other = _town(8)
    frames = _flight(town, 5.0, keep_every=2)
    start = frames[0]["truth"]
    for initial in (None, (start["x"], start["y"], 30.0)):
        records = _navigate(other, frames, stitch=5, initial=initial)
        tried = [r for r in records if "stitched" in r.fix]
        assert len(tried) > 5  # stitched images were made and queried
        assert not any(r.fix.get("status") in ("used", "initialised") for r in records)
        assert all(r.fix_frames is None for r in records)


@pytest.mark.slow
@pytest.mark.skipif(SHARED is None, reason="the shared OSM extracts (../shared/data/osm) are not present")
def test_stitching_never_accepts_monaco_frames_in_the_andorra_map(tmp_path) -> None:
    """Ideal frames over Monaco, thinned, navigated lost in space against the Andorra map."""
    from mapdb.build.pipeline import build_map
    from mapdb.mapfile.reader import open_map

    assert SHARED is not None
    monaco, andorra = tmp_path / "monaco.mapdb", tmp_path / "andorra.mapdb"
    build_map([SHARED / "monaco-2021-12-03.osm.pbf"], monaco)
    build_map([SHARED / "andorra-2021-06-22.osm.pbf"], andorra)
    with open_map(monaco) as m:
        frames = _sparse(simulate_flight(m, FlightOptions(length_m=600.0, altitude_m=120.0, fov_deg=60.0,
                                                          fps=5.0, pixel_std=1.0)), 2)
    with open_map(andorra) as m:
        records = _navigate(m, frames, stitch=5)
    assert sum("stitched" in r.fix for r in records) > 10
    assert not any(r.fix.get("status") in ("used", "initialised") for r in records)


def test_the_track_record_fields_are_the_documented_ones() -> None:
    """The record's example in :mod:`mapdb.navigation.track` names every top-level field ``to_json`` writes."""
    import re

    import mapdb.navigation.track as track

    doc = track.__doc__ or ""
    example = doc[doc.index("::") + 2: doc.index("``status`` is")]
    # Top-level keys: those opening a line of the example, or following a value on the same line at depth one.
    depth, keys, i = 0, set(), 0
    while i < len(example):
        c = example[i]
        if c in "{[":
            depth += 1
        elif c in "}]":
            depth -= 1
        elif c == '"':
            end = example.index('"', i + 1)
            if depth == 1 and re.match(r"\s*:", example[end + 1:]):
                keys.add(example[i + 1:end])
            i = end
        i += 1
    record = track.TrackRecord(id="f", time_s=0.0, status="fix", notes=["n"], truth={"x": 0.0, "y": 0.0},
                               fix_frames=[0.0], altitude={"baro_m": 212.4},  # altitude, map_update: when set
                               map_update={"status": "used", "objects": 4, "ess": 1290.5})
    assert keys == set(record.to_json())
