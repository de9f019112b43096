"""Objects from masks: cut blobs do not build hypotheses or steer the final fit; relief is fitted radially."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from mapdb.localize.localizer import localize
from mapdb.mapfile.queries import MemoryMap
from mapdb.match.evidence.image import ImageEvidence
from mapdb.match.evidence.relief import ReliefFit, _whitened, fit_with_relief, leave_one_out_sigma, radial_excess
from mapdb.match.fast import FastOptions
from mapdb.match.geometry import fit_similarity_complex
from mapdb.match.hypotheses import anchor_batches
from mapdb.match.mapobjects.object_index import ObjectIndex
from mapdb.match.refine import Candidate, polish
from mapdb.objects import Objects
from mapdb.simulation.simulate import paper_map, simulate_images


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


def _jackknife_by_refits(src: np.ndarray, dst: np.ndarray, fit: ReliefFit) -> float:
    """The jackknife sigma of ``b`` the slow way: one weighted least squares per point left out."""
    radial = np.exp(1j * np.angle(fit.a * src))
    sigma_r = np.sqrt(fit.sigma_axis**2 + fit.kappa**2 * np.abs(fit.a * src) ** 2)
    b = []
    for i in range(src.size):
        keep = np.arange(src.size) != i
        design, target = _whitened(src[keep], dst[keep], radial[keep], sigma_r[keep], fit.sigma_axis)
        p = np.linalg.lstsq(design, target, rcond=None)[0]
        b.append(complex(p[2], p[3]))
    b = np.array(b)
    return math.sqrt((src.size - 1) / src.size * np.sum(np.abs(b - b.mean()) ** 2) / 2.0)


@pytest.mark.parametrize("kappa", [0.0, 0.02])
def test_leave_one_out_sigma_equals_refitting_without_each_point(kappa: float) -> None:
    src, seen = _relief_image(3, 0.06)
    src, seen = src[:9], seen[:9]
    plain = fit_with_relief(src, seen)
    fit = plain if kappa == 0.0 else ReliefFit(plain.a, plain.b, plain.sigma_axis, 1.0, kappa)
    assert leave_one_out_sigma(src, seen, fit) == pytest.approx(_jackknife_by_refits(src, seen, fit), rel=1e-9)


def test_one_far_point_among_few_makes_the_answer_imprecise() -> None:
    # Six points, one at the edge carrying a 1.5 m error: the model's sigma trusts the small residuals,
    # the jackknife feels the lever of the far point.
    src = np.array([-300 + 200j, -250 - 150j, -200 + 20j, -150 + 180j, -100 - 60j, 300 + 0j])
    truth = 0.3 * src + (500 + 500j)
    rng = np.random.default_rng(0)
    seen = truth + 0.05 * (rng.standard_normal(6) + 1j * rng.standard_normal(6))
    seen[-1] += 1.5
    fit = fit_with_relief(src, seen)
    model = fit.sigma_axis * math.sqrt(fit.variance_factor)
    error = abs(fit.b - (500 + 500j))
    assert model < error / 3  # the model calls the answer far better than it is
    assert leave_one_out_sigma(src, seen, fit) > error / 3
    assert leave_one_out_sigma(src[:2], seen[:2], fit) == math.inf
    # The final fit reports the larger of the two, so max_sigma_m withholds such an answer.
    index = ObjectIndex(Objects.from_names(seen.real, seen.imag, ["building"] * 6))
    cand = Candidate(a=0.3, b=500 + 500j, log10_nfa=-9.0, inliers=6, sigma_axis_m=0.6, variance_factor=0.2,
                     pairs=np.column_stack([np.arange(6), np.arange(6)]))
    final = polish(cand, src, np.zeros(6, np.int64), index, evidence=ImageEvidence(jackknife=True))
    assert polish(cand, src, np.zeros(6, np.int64), index).sigma_m == pytest.approx(model)  # points: the model
    assert final.inliers == 6 and abs(final.b - fit.b) < 1e-6
    assert final.sigma_m == pytest.approx(leave_one_out_sigma(src, seen, fit)) and final.sigma_m > model
