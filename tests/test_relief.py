"""Objects from masks: cut blobs do not build hypotheses or steer the final fit; relief is fitted radially."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from mapdb.localize import localize
from mapdb.match.fast import FastOptions
from mapdb.match.geometry import fit_similarity_complex
from mapdb.match.hypotheses import anchor_batches
from mapdb.match.relief import fit_with_relief, radial_excess
from mapdb.simulate import paper_map, simulate_images
from mapdb.store import MemoryMap


@pytest.fixture(scope="module")
def paper() -> MemoryMap:
    return MemoryMap(paper_map(seed=4))


def test_objects_cut_by_the_border_build_no_quad() -> None:
    rng = np.random.default_rng(1)
    z = rng.uniform(-300, 300, 30) + 1j * rng.uniform(-200, 200, 30)
    anchorable = np.abs(z.real) < 200  # the objects near the left and right edges are "cut"
    quads = np.concatenate(anchor_batches(z, FastOptions(), anchorable))
    assert len(quads) and anchorable[quads].all()
    everything = np.concatenate(anchor_batches(z, FastOptions()))
    assert not anchorable[everything].all()  # without the mask the edge objects do build quads


def _pulled(image: dict, which: np.ndarray, pull_px: float, flag: bool) -> dict:
    doc = copy.deepcopy(image)
    for k, obj in enumerate(doc["objects"]):
        if k in which:
            obj["x"] -= pull_px  # a cut blob's centroid is pulled inward, away from the hidden part
        if flag:
            obj["border"] = bool(k in which)
    return doc


def test_blobs_flagged_as_cut_count_as_inliers_but_do_not_move_the_answer(paper: MemoryMap) -> None:
    for image in simulate_images(paper, 4, pixel_std=2.0, yaw="random", seed=9):
        right = np.argsort([-o["x"] for o in image["objects"]])[:3]
        flagged = [localize(_pulled(image, right, pull, True), paper) for pull in (3.0, 6.0)]
        plain = [localize(_pulled(image, right, pull, False), paper) for pull in (3.0, 6.0)]
        assert all(a.status == "ok" for a in flagged + plain)
        assert flagged[0].inliers == flagged[1].inliers == len(image["objects"])
        # Where exactly the cut blobs lie does not move the flagged answer, and does move the plain one.
        assert (flagged[0].x, flagged[0].y) == (flagged[1].x, flagged[1].y)
        assert (plain[0].x, plain[0].y) != (plain[1].x, plain[1].y)


def test_border_flags_follow_their_objects_when_unknown_labels_are_dropped(paper: MemoryMap) -> None:
    image = simulate_images(paper, 1, pixel_std=2.0, yaw="random", seed=5)[0]
    right = np.argsort([-o["x"] for o in image["objects"]])[:3]
    doc = _pulled(image, right, 6.0, True)
    extra = copy.deepcopy(doc)
    extra["objects"].insert(0, {"label": "no-such-label", "x": 10.0, "y": 10.0, "border": False})
    a, b = localize(doc, paper), localize(extra, paper)
    assert a.status == b.status == "ok"
    assert (a.x, a.y, a.inliers) == (b.x, b.y, b.inliers)


def _relief_image(seed: int, relief: float) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    src = rng.uniform(-320, 320, 25) + 1j * rng.uniform(-240, 240, 25)
    truth = 0.3 * np.exp(0.7j) * src + (1000 + 2000j)
    noise = 0.3 * 0.3 * (rng.standard_normal(25) + 1j * rng.standard_normal(25))
    tall = src.real > 0  # taller buildings on one side: relief the plain fit cannot absorb as scale
    seen = truth + noise + 0.3 * np.exp(0.7j) * src * rng.uniform(0.0, relief, 25) * tall
    return src, seen


def test_relief_fit_removes_the_bias_of_one_sided_relief() -> None:
    plain_errors, relief_errors = [], []
    for seed in range(10):
        src, seen = _relief_image(seed, 0.06)
        fit = fit_with_relief(src, seen)
        assert fit is not None and fit.kappa > 0
        plain_errors.append(abs(complex(fit_similarity_complex(src, seen)[1]) - (1000 + 2000j)))
        relief_errors.append(abs(fit.b - (1000 + 2000j)))
    assert np.sqrt(np.mean(np.square(relief_errors))) < 0.5 * np.sqrt(np.mean(np.square(plain_errors)))


def test_isotropic_errors_keep_the_plain_least_squares_fit() -> None:
    kept = 0
    for seed in range(40):
        src, seen = _relief_image(seed, 0.0)
        fit = fit_with_relief(src, seen)
        a, b = fit_similarity_complex(src, seen)
        if fit.kappa == 0.0:
            kept += 1
            assert (fit.a, fit.b) == (complex(a), complex(b))
            residual = np.abs(a * src + b - seen)
            assert fit.sigma_axis == pytest.approx(math.sqrt(np.sum(residual**2) / (2 * src.size - 4)))
    assert kept >= 36  # the radial-excess test fires on about 1 % of isotropic images


def test_radial_excess_needs_more_than_four_points() -> None:
    src = np.array([1 + 0j, -1, 1j, -1j])
    assert radial_excess(src, src * 1.5, 1.0, 0j)[2] is False
