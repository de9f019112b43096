"""The localizer: similarity geometry, the false-alarm model, the fast and paper matchers, localize()."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binom

from mapdb.camera import Camera, Pose, project_to_image
from mapdb.localize.localizer import localize
from mapdb.mapfile.queries import MemoryMap
from mapdb.match.fast import ObjectIndex, QuadIndex, match_fast
from mapdb.match.geometry import fit_similarity_complex, prediction_variance_factor, similarity_from_pairs
from mapdb.match.hypotheses import pose_votes, prioritise
from mapdb.match.nfa import log10_binomial_tail, log10_nfa_curve
from mapdb.match.paper.algorithm import match_paper
from mapdb.match.quads import canonical_quads, neighbour_quads
from mapdb.objects import Objects
from mapdb.simulation.simulate import paper_map, simulate_images

CRS = "EPSG:32631"
X0, Y0 = 400_000.0, 4_700_000.0
W, H = 640, 480


def _random_map(n: int = 1200, size: float = 500.0, seed: int = 0, labels=("building", "road_intersection")):
    rng = np.random.default_rng(seed)
    names = np.array(labels, dtype=object)[rng.integers(0, len(labels), n)]
    objects = Objects.from_names(X0 + rng.uniform(0, size, n), Y0 + rng.uniform(0, size, n), names, crs=CRS,
                                 labels=("building", "road_intersection", "park"))
    return MemoryMap(objects)


def _image_of(m: MemoryMap, centre: complex, scale: float, heading_deg: float) -> dict:
    """Image document of the map's objects seen with an exact similarity (no noise)."""
    objs = m.all()
    w = objs.x + 1j * objs.y
    # Map = a * (pixels centred, y up) + centre; heading is clockwise from north, so a turns the other way.
    a = scale * np.exp(-1j * math.radians(heading_deg))
    z = (w - centre) / a
    px, py = z.real + W / 2, H / 2 - z.imag
    inside = (px >= 0) & (px <= W) & (py >= 0) & (py <= H)
    names = objs.names()
    return {
        "id": "exact",
        "width": W,
        "height": H,
        "objects": [{"label": str(names[i]), "x": float(px[i]), "y": float(py[i])} for i in np.flatnonzero(inside)],
    }


# --- geometry and decision -------------------------------------------------------------------------------


def test_batched_similarity_fits_recover_transforms() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(5, 7)) + 1j * rng.normal(size=(5, 7))
    a_true = rng.uniform(0.1, 3, 5) * np.exp(1j * rng.uniform(-np.pi, np.pi, 5))
    b_true = rng.normal(size=5) * 100 + 1j * rng.normal(size=5) * 100
    dst = a_true[:, None] * src + b_true[:, None]
    a, b = fit_similarity_complex(src, dst)
    np.testing.assert_allclose(a, a_true, rtol=1e-12)
    np.testing.assert_allclose(b, b_true, rtol=1e-12)
    a2, b2 = similarity_from_pairs(src[:, 0], src[:, 1], dst[:, 0], dst[:, 1])
    np.testing.assert_allclose(a2, a_true, rtol=1e-10)
    # A masked-out outlier does not move the fit.
    dst[:, 3] += 50.0
    mask = np.ones(src.shape)
    mask[:, 3] = 0
    a3, _ = fit_similarity_complex(src, dst, mask)
    np.testing.assert_allclose(a3, a_true, rtol=1e-12)
    # Prediction variance at the centroid is 1/n.
    assert prediction_variance_factor(src[0], at=src[0].mean()) == pytest.approx(1 / 7)


@pytest.mark.parametrize("n, p", [(10, 0.01), (40, 0.2), (300, 1e-4)])
def test_binomial_tail_matches_scipy(n: int, p: float) -> None:
    k = np.arange(0, n + 2)
    expected = np.log10(np.maximum(binom.sf(k - 1, n, p), 1e-300))
    got = log10_binomial_tail(n, k, p)
    finite = expected > -290
    np.testing.assert_allclose(got[finite], expected[finite], rtol=1e-6, atol=1e-9)
    assert got[-1] == -np.inf


def test_nfa_curve_prefers_tight_consensus_and_shapes_reduce_to_plain() -> None:
    rng = np.random.default_rng(2)
    u = np.vstack([np.r_[np.full(8, 1e-3), rng.exponential(1, 8)], rng.exponential(1, 16)])
    nfa, k = log10_nfa_curve(u, 4, 2.0)
    assert nfa[0] < -5 < 0 < nfa[1] and k[0] == 8
    shaped, k_shaped = log10_nfa_curve(u, 4, 2.0, shape=np.ones_like(u))
    np.testing.assert_allclose(shaped, nfa)
    assert k_shaped.tolist() == k.tolist()


def test_quad_invariants_survive_similarity_but_not_reflection() -> None:
    rng = np.random.default_rng(3)
    zq = rng.normal(size=(50, 4)) + 1j * rng.normal(size=(50, 4))
    order, inv, _ = canonical_quads(zq)
    moved = (0.3 - 2.1j) * zq + (5 + 7j)
    order2, inv2, _ = canonical_quads(moved[:, rng.permutation(4)])
    np.testing.assert_allclose(np.sort(inv, axis=0), np.sort(inv2, axis=0), atol=1e-9)
    mirrored = canonical_quads(np.conj(zq))[1]
    assert np.abs(mirrored - inv).max() > 0.1
    quads = neighbour_quads(np.column_stack([zq[:, 0].real, zq[:, 0].imag]), 5)
    assert len(quads) == len(np.unique(quads, axis=0)) and np.all(np.diff(quads, axis=1) > 0)


# --- fast: exact recovery, false alarms, rejections ------------------------------------------------------


@pytest.mark.parametrize("heading, scale", [(0.0, 0.1), (37.0, 0.25), (181.5, 0.08), (300.0, 0.4)])
def test_fast_recovers_a_known_similarity_exactly(heading: float, scale: float) -> None:
    m = _random_map()
    centre = complex(X0 + 250.0, Y0 + 240.0)
    doc = _image_of(m, centre, scale, heading)
    assert len(doc["objects"]) >= 6
    out = localize(doc, m)
    assert out.status == "ok", out
    assert abs(complex(out.x, out.y) - centre) < 2e-3  # output rounded to the millimetre
    assert out.heading_deg == pytest.approx(heading, abs=1e-3)
    assert out.scale_m_per_px == pytest.approx(scale, rel=1e-5)
    assert out.inliers == len(doc["objects"]) and out.score > 3 and out.sigma_m < 1e-3
    assert out.crs == CRS and 0 < out.lon < 3 and 42 < out.lat < 43


def test_fast_with_simulated_paper_images_matches_the_bound() -> None:
    m = MemoryMap(paper_map(seed=4))
    for image in simulate_images(m, 6, pixel_std=1.0, yaw="random", seed=9):
        out = localize(image, m)
        truth = image["truth"]
        assert out.status == "ok", out
        assert math.hypot(out.x - truth["bound"]["x"], out.y - truth["bound"]["y"]) < 1e-3  # mm output
        assert out.altitude_m == pytest.approx(100.0, rel=0.02)


def test_attitude_and_field_of_view_level_the_image_to_the_nadir() -> None:
    m = _random_map(seed=5)
    cam = Camera(W, H, 40.0)
    pose = Pose(X0 + 260.0, Y0 + 250.0, 120.0, yaw_deg=75.0, roll_deg=3.0, pitch_deg=-2.0)
    objs = m.all()
    u, v = project_to_image(objs.x, objs.y, pose, cam)
    inside = np.isfinite(u) & (u >= 0) & (u <= W) & (v >= 0) & (v <= H)
    names = objs.names()
    doc = {"width": W, "height": H, "camera": {"fov_deg": 40.0},
           "objects": [{"label": str(names[i]), "x": float(u[i]), "y": float(v[i])} for i in np.flatnonzero(inside)]}
    plain = localize(doc, m)
    levelled = localize({**doc, "attitude": {"roll_deg": 3.0, "pitch_deg": -2.0}}, m)
    assert levelled.status == "ok" and levelled.levelled
    assert math.hypot(levelled.x - pose.x, levelled.y - pose.y) < 2e-3
    assert levelled.altitude_m == pytest.approx(120.0, abs=0.01)
    assert levelled.heading_deg == pytest.approx(75.0, abs=1e-3)
    # Without the attitude the answer is the point under the image centre, metres away (120 m * tan 3 deg).
    assert plain.status == "ok" and math.hypot(plain.x - pose.x, plain.y - pose.y) > 4.0


def test_images_unrelated_to_the_map_are_rejected() -> None:
    m = MemoryMap(paper_map(seed=4))
    rng = np.random.default_rng(11)
    for i in range(6):
        n = int(rng.integers(10, 30))
        doc = {"id": i, "width": W, "height": H,
               "objects": [{"label": "building", "x": float(x), "y": float(y)}
                           for x, y in zip(rng.uniform(0, W, n), rng.uniform(0, H, n), strict=True)]}
        out = localize(doc, m)
        assert out.status == "rejected", out
        assert "certain" in out.reason or "no consistent" in out.reason


def test_prior_restricts_the_search() -> None:
    m = _random_map()
    centre = complex(X0 + 250.0, Y0 + 240.0)
    doc = _image_of(m, centre, 0.12, 10.0)
    near = localize({**doc, "prior": {"x": centre.real + 30, "y": centre.imag - 20, "radius": 100}}, m)
    assert near.status == "ok" and abs(complex(near.x, near.y) - centre) < 2e-3
    # The true place lies outside this prior: nothing else there matches.
    far = localize(doc, m, prior=(centre.real + 200, centre.imag, 50.0))
    assert far.status == "rejected"
    # No map objects at all around the prior.
    empty = localize(doc, m, prior=(X0 + 50_000, Y0, 100.0))
    assert empty.status == "rejected" and "objects here" in empty.reason


@pytest.mark.parametrize(
    "objects, reason",
    [
        ([{"label": "building", "x": 1, "y": 1}] * 2, "2 objects: at least 3 are needed"),
        ([{"label": "tree", "x": 1, "y": 1}] * 5, "unknown label 'tree': the map has building"),
        ([{"label": "building", "x": -1, "y": 1}] * 5, "objects[0].x is negative"),
        ([{"label": "building", "x": float("nan"), "y": 1}] * 5, "objects[0].x is nan, not a finite number"),
        ([{"label": "building", "x": 9999, "y": 1}] * 5, "objects[0] at (9999, 1) is outside the 640x480 image"),
    ],
)
def test_bad_images_are_rejected_with_a_reason(objects, reason) -> None:
    m = _random_map(n=50)
    out = localize({"id": "bad", "width": W, "height": H, "objects": objects}, m)
    assert out.status == "rejected" and out.id == "bad"
    assert out.reason.startswith(reason), out.reason
    assert out.candidates == [] and out.time_ms >= 0


def test_match_fast_needs_four_objects_and_a_map() -> None:
    two = Objects.from_names([0.0, 1.0], [0.0, 1.0], ["b", "b"])
    objects, quads = ObjectIndex(two), [QuadIndex(two)]
    assert quads[0].n_quads == 0
    res = match_fast(np.array([0, 1, 1j, 2 + 2j]), np.zeros(4, int), objects, quads, 800.0)
    assert res.best is None and "only 2 objects here" in res.reason
    res = match_fast(np.array([0, 1, 1j]), np.zeros(3, int), objects, quads, 800.0)
    assert res.best is None and "3 objects" in res.reason


# --- paper -----------------------------------------------------------------------------------------------


def test_paper_method_finds_the_centre_of_a_noise_free_image() -> None:
    m = _random_map(n=40, size=200.0, seed=6, labels=("building",))
    centre = complex(X0 + 100.0, Y0 + 100.0)
    doc = _image_of(m, centre, 0.15, 30.0)
    objs = m.all()
    z = np.array([complex(o["x"] - W / 2, H / 2 - o["y"]) for o in doc["objects"]])
    res = match_paper(z, np.zeros(z.size, int), objs)
    assert res.best is not None and abs(res.best.b - centre) < 1e-6
    assert res.best.matched == z.size and res.best.error_std < 1e-9
    out = localize(doc, m, method="paper")
    assert out.status == "ok" and out.score is None
    assert out.heading_deg == pytest.approx(30.0, abs=1e-6)


def test_paper_method_rejects_below_n_min() -> None:
    m = _random_map(n=40, size=200.0, seed=6, labels=("building",))
    doc = _image_of(m, complex(X0 + 100.0, Y0 + 100.0), 0.15, 30.0)
    doc["objects"] = doc["objects"][:5]
    out = localize(doc, m, method="paper")
    assert out.status == "rejected" and "N_min = 6" in out.reason


def test_lonlat_prior_and_the_precision_gate() -> None:
    from pyproj import Transformer

    from mapdb.match.fast import FastOptions

    m = _random_map()
    centre = complex(X0 + 250.0, Y0 + 240.0)
    doc = _image_of(m, centre, 0.12, 200.0)
    lon, lat = Transformer.from_crs(CRS, "EPSG:4326", always_xy=True).transform(centre.real + 20, centre.imag)
    out = localize({**doc, "prior": {"lon": lon, "lat": lat, "radius": 60.0}}, m)
    assert out.status == "ok" and abs(complex(out.x, out.y) - centre) < 2e-3
    # An answer less precise than max_sigma_m is withheld but still offered as a candidate.
    rng = np.random.default_rng(8)
    noisy = {**doc, "objects": [{**o, "x": min(max(o["x"] + rng.normal(0, 2), 0), W),
                                 "y": min(max(o["y"] + rng.normal(0, 2), 0), H)} for o in doc["objects"]]}
    strict = localize(noisy, m, options=FastOptions(max_sigma_m=1e-4))
    assert strict.status == "rejected" and strict.reason.startswith("imprecise")
    best = strict.candidates[0]
    assert abs(complex(best.x, best.y) - centre) < 1.0 and best.sigma_m > 1e-4


def _paper_case(
    seed: int, n_labels: int, n_image: int = 9, spurious: int = 0
) -> tuple[np.ndarray, np.ndarray, Objects]:
    """A small map (40-60 objects) and a noisy image of it (pixels about the centre, y up) for the paper method."""
    rng = np.random.default_rng(seed)
    n_map = int(rng.integers(40, 61))
    x, y = X0 + rng.uniform(0, 200, n_map), Y0 + rng.uniform(0, 150, n_map)
    label = rng.integers(0, n_labels, n_map)
    objects = Objects(x, y, label, np.zeros(n_map), ("building", "road_intersection"), CRS)
    centre = complex(X0 + rng.uniform(40, 160), Y0 + rng.uniform(40, 110))
    a = rng.uniform(0.08, 0.16) * np.exp(1j * rng.uniform(-np.pi, np.pi))
    z = (x + 1j * y - centre) / a
    seen = np.flatnonzero((np.abs(z.real) < W / 2) & (np.abs(z.imag) < H / 2))[:n_image]
    z = z[seen] + rng.normal(0, 1.5, (seen.size, 2)) @ np.array([1, 1j])
    extra = rng.uniform(-W / 2, W / 2, spurious) + 1j * rng.uniform(-H / 2, H / 2, spurious)
    return np.concatenate([z, extra]), np.concatenate([label[seen], rng.integers(0, n_labels, spurious)]), objects


def test_paper_bound_never_undercounts_a_candidate() -> None:
    # Brute force: every hypothesis's float64 N_matched (before the float32 pre-test, so at least the
    # matcher's) must be within the bound, for thresholds from 3 to "every object".
    from itertools import combinations

    from mapdb.match.paper.algorithm import PaperOptions
    from mapdb.match.paper.bound import NearestBound, wrap_angle

    opts = PaperOptions()
    for seed, n_labels in ((11, 1), (12, 2)):
        z, codes, objects = _paper_case(seed, n_labels, n_image=7, spurious=1)
        map_z, map_label = objects.x + 1j * objects.y, objects.label.astype(np.int64)
        keys = [None] if n_labels == 1 else [0, 1]
        bound = NearestBound(map_z, map_label, keys)
        r, theta = np.abs(z), np.angle(z)
        checked = pruned = 0
        for i, j in combinations(range(z.size), 2):
            others = np.array([k for k in range(z.size) if k not in (i, j)], dtype=np.int64)
            perm = [(p, q) for p in np.flatnonzero(map_label == codes[i]) for q in np.flatnonzero(map_label == codes[j])
                    if p != q]
            big_i, big_j = np.array(perm).T
            a = (map_z[big_j] - map_z[big_i]) / (z[j] - z[i])
            centre = map_z[big_i] - a * z[i]
            rel = map_z[None, :] - centre[:, None]
            ratio_map = np.abs(rel) / np.abs(rel[np.arange(big_i.size), big_i])[:, None]
            angle_map = np.angle(rel[np.arange(big_i.size), big_i])[:, None] - np.angle(rel)
            ratio_map[np.arange(big_i.size), big_i] = ratio_map[np.arange(big_i.size), big_j] = np.inf
            count = np.full(big_i.size, 2)
            for k in others:
                ok = np.abs(r[k] / r[i] - ratio_map) < opts.delta_r
                ok &= np.abs(wrap_angle(wrap_angle(theta[i] - theta[k]) - angle_map)) < opts.delta_theta
                if n_labels > 1:
                    ok &= map_label[None, :] == codes[k]
                count += ok.any(axis=1)
            key_k = [None] * others.size if n_labels == 1 else [int(c) for c in codes[others]]
            for need in (3, opts.n_min, others.size + 2):
                kept, most = bound.survivors(centre, map_z[big_i] - centre, r[others] / r[i],
                                             wrap_angle(theta[i] - theta[others]), key_k, need, opts)
                upper = np.zeros(big_i.size, dtype=int)
                upper[kept] = most
                reach = count >= need
                assert np.all(upper[reach] >= count[reach]), (seed, i, j, need)
                checked += int(reach.sum())
                pruned += big_i.size - kept.size
        assert checked > 0 and pruned > 0  # the check covered candidates, and the bound did rule some out


@pytest.mark.slow  # 2 s: the full test of the paper method, unpruned.
def test_paper_pruning_gives_the_same_results_as_the_full_test() -> None:
    from mapdb.match.paper.algorithm import PaperOptions

    outcomes = set()
    cases = [(21, 1, 9, 0), (22, 2, 9, 2), (23, 2, 8, 1), (24, 1, 9, 3), (25, 2, 5, 0), (26, 1, 2, 0)]
    for seed, n_labels, n_image, spurious in cases:
        z, codes, objects = _paper_case(seed, n_labels, n_image, spurious)
        full = match_paper(z, codes, objects, options=PaperOptions(prune=False))
        pruned = match_paper(z, codes, objects, options=PaperOptions(prune=True))
        assert pruned.candidates_tested == full.candidates_tested
        assert pruned.reason == full.reason
        assert (pruned.best is None) == (full.best is None)
        if full.best is not None:
            # Bit for bit: the same candidate, found by the same arithmetic.
            assert (pruned.best.a, pruned.best.b) == (full.best.a, full.best.b)
            assert (pruned.best.matched, pruned.best.error_std) == (full.best.matched, full.best.error_std)
        outcomes.add(full.best is not None)
    assert outcomes == {True, False}  # both accepted and rejected images were compared


def test_an_image_with_thousands_of_objects_is_matched_on_its_central_ones() -> None:
    """Work per image is bounded: a 20,000-object image (the input limit) is answered, and a true image
    buried among distant clutter is still localized from the objects nearest its centre."""
    m = MemoryMap(paper_map(seed=0))
    image = simulate_images(m, 1, pixel_std=0.5, seed=4)[0]
    truth = image["truth"]
    rng = np.random.default_rng(1)
    # The same image inside a 4000x3000 frame (same centre offsets, so the same truth), with clutter
    # beyond the true objects: the 256 objects nearest the centre are the true ones and a little clutter.
    w, h = 4000, 3000
    dx, dy = (w - image["width"]) / 2, (h - image["height"]) / 2
    true_objects = [{**o, "x": o["x"] + dx, "y": o["y"] + dy} for o in image["objects"]]
    angle = rng.uniform(0, 2 * math.pi, 20_000 - len(true_objects))
    radius = rng.uniform(420.0, 1400.0, angle.size)
    clutter = [{"label": "building", "x": float(w / 2 + r * math.cos(t)), "y": float(h / 2 + r * math.sin(t))}
               for r, t in zip(radius, angle)]
    crowded = {**image, "width": w, "height": h, "objects": true_objects + clutter}
    answer = localize(crowded, m)
    assert answer.status == "ok", answer.reason
    assert math.hypot(answer.x - truth["x"], answer.y - truth["y"]) < 1.0
    noise = {"width": 4000, "height": 3000, "objects": [
        {"label": "building", "x": float(x), "y": float(y)}
        for x, y in zip(rng.uniform(0, 4000, 20_000), rng.uniform(0, 3000, 20_000))]}
    assert localize(noise, m).status == "rejected"


def test_the_localizer_uses_a_stored_lost_in_space_index_beside_the_map(tmp_path) -> None:
    """With ``MAP.qidx`` beside the map, lost-in-space lookups go to it (no quad index built in memory) and
    images are localized as with the in-memory index."""
    from mapdb.localize.localizer import Localizer, StoredQuads
    from mapdb.mapfile.reader import open_map
    from mapdb.mapfile.writer import write_map
    from mapdb.match.index.stored import build_index

    path = tmp_path / "paper.mapdb"
    write_map(path, paper_map(seed=0))
    build_index(path, workers=1)
    with open_map(path) as m:
        images = simulate_images(m, 5, pixel_std=0.5, yaw="random", seed=6)
        stored, memory = Localizer(m), Localizer(m)
        memory._stored_index = lambda: None  # the same map, as if it had no index file
        for im in images:
            a, b = stored.localize(im), memory.localize(im)
            assert a.status == b.status == "ok"
            assert math.hypot(a.x - im["truth"]["x"], a.y - im["truth"]["y"]) < 1.0
        assert isinstance(stored.whole_map_indexes()[1], StoredQuads)
        assert isinstance(memory.whole_map_indexes()[1], QuadIndex)


def test_prioritise_screens_the_most_shared_pose_first_and_at_most_the_limit() -> None:
    rng = np.random.default_rng(3)
    # 40 hypotheses of one pose (a right place, found by many image quads) among 400 scattered lookalikes.
    shared_a = 0.3 * np.exp(0.7j) * (1 + 0.002 * rng.standard_normal(40))
    shared_b = 5000 + 5000j + rng.standard_normal(40)
    other_a = 0.3 * np.exp(1j * rng.uniform(-np.pi, np.pi, 400))
    other_b = rng.uniform(0, 1e6, 400) + 1j * rng.uniform(0, 1e6, 400)
    a, b = np.concatenate([other_a, shared_a]), np.concatenate([other_b, shared_b])
    kept = prioritise(a, b, 800.0, 64)
    assert kept.size == 64 and np.unique(kept).size == 64
    # Most of the shared pose's hypotheses land in one pose bin and come first.
    assert np.count_nonzero(kept[:30] >= 400) == 30
    assert prioritise(a[:50], b[:50], 800.0, 64).tolist() == list(range(50))  # under the limit: all, in order


def test_pose_votes_group_one_place_at_utm_coordinates() -> None:
    # A right place found by 40 image quads, its poses 0.2 % apart in scale and 0.3 m in position, at a UTM
    # northing of 4,714 km: a position cell that followed each hypothesis's own scale split them all.
    rng = np.random.default_rng(5)
    a = 0.41 * np.exp(0.7j) * (1 + 0.002 * rng.standard_normal(40))
    b = 387532 + 4714878j + 0.3 * (rng.standard_normal(40) + 1j * rng.standard_normal(40))
    chance_a = 0.41 * np.exp(1j * rng.uniform(-np.pi, np.pi, 200)) * np.exp(rng.uniform(-1, 1, 200))
    chance_b = 387532 + 4714878j + rng.uniform(-5e4, 5e4, 200) + 1j * rng.uniform(-5e4, 5e4, 200)
    votes = pose_votes(np.concatenate([a, chance_a]), np.concatenate([b, chance_b]), 800.0)
    assert np.median(votes[:40]) >= 20  # most of the place's hypotheses share a bin (bins may split it in a few)
    assert np.count_nonzero(votes[40:] >= 2) <= 4  # chance hits rarely share one


def test_a_round_screens_shared_poses_first_and_the_whole_round_when_they_fail() -> None:
    """A right place found by one image quad alone, among chance hits whose poses come in pairs, is still
    answered: the shared poses are screened first, and when they give nothing the whole round is."""
    from scipy.spatial import cKDTree

    from mapdb.match.hypotheses import Hypotheses
    from mapdb.match.options import FastOptions
    from mapdb.match.screen import screen_round

    m = _random_map()
    objs = m.all()
    w = objs.x + 1j * objs.y
    centre, a_true = complex(X0 + 250.0, Y0 + 240.0), 0.2 * np.exp(-0.6j)
    z_all = (w - centre) / a_true
    seen = np.flatnonzero((np.abs(z_all.real) <= W / 2) & (np.abs(z_all.imag) <= H / 2))
    z, label = z_all[seen], objs.label[seen].astype(np.int64)
    quad = np.argsort(np.abs(z))[:4]
    rng = np.random.default_rng(8)
    # 20 wrong places, each found twice (the same pose): their quads' map points where the pose puts them.
    wrong_a = np.repeat(0.2 * np.exp(1j * rng.uniform(-np.pi, np.pi, 20)), 2)
    wrong_b = np.repeat(complex(X0, Y0) + rng.uniform(0, 500, 20) + 1j * rng.uniform(0, 500, 20), 2)
    a, b = np.concatenate([wrong_a, [a_true]]), np.concatenate([wrong_b, [centre]])
    img_ids = np.tile(quad, (a.size, 1))
    map_z = a[:, None] * z[img_ids] + b[:, None]
    map_z[-1] = w[seen[quad]]
    pts = np.column_stack([z.real, z.imag])
    screen_of = cKDTree(pts).query(pts, k=min(12, z.size))[1]
    opts = FastOptions()
    found = screen_round(Hypotheses(a, b, img_ids, map_z), z, label, ObjectIndex(objs), screen_of, math.hypot(W, H),
                         math.log10(a.size), opts)
    best = min(found, key=lambda c: c.log10_nfa)
    assert best.log10_nfa < opts.log10_epsilon
    assert abs(best.b - centre) < 1e-6
