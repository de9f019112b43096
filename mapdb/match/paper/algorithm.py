"""The paper's pattern matcher (Kim, "Aerial map-based navigation using semantic segmentation and
pattern matching", Algorithm 1), as published: the reference the fast matcher is measured against.

For every 2-combination ``(o_i, o_j)`` of image objects, in polar coordinates
``(r, theta)`` about the image centre, and every 2-permutation ``(O_I, O_J)`` of
map objects with the same labels, the map point ``c`` is found from which
``O_I`` and ``O_J`` are seen with the same relative angle and radius ratio
(``Theta_I - Theta_J = theta_i - theta_j`` and ``R_I : R_J = r_i : r_j``; of the
two circle intersections, the one with the same sign of the relative angle).
Every other image object ``o_k`` is then compared with every other map object
``O_K`` of its label: it matches if ``|r_k/r_i - R_k/R_I| < delta_r`` and
``|(theta_i - theta_k) - (Theta_I - Theta_K)| < delta_theta``, with the error
``e_k`` the sum of the two.  ``N_matched`` starts at 2; a candidate with
``N_matched >= N_min`` has ``E = std({e_k})`` and replaces the best if
``N_matched >= N_best and E < E_best``.  The answer is the best candidate's ``c``.

Where the paper leaves a choice, this implementation decides as follows:

* **How many map objects one image object may match.**  Algorithm 1 increments
  ``N_matched`` inside the loop over map objects but indexes the error by the
  image object (``e_k``); we read it as one match per image object: ``o_k``
  counts once if any ``O_K`` is within both tolerances, and its ``e_k`` is the
  smallest error among those.
* **Coordinates.**  Image y points down; the image is flipped to y up before
  taking polar angles, so that "the same sign of the relative angle" means the
  same orientation as in the map (x east, y north).  Without the flip the
  algorithm would look for the mirror image of the pattern.
* **The circle intersection** is computed in closed form: the similarity taking
  ``o_i -> O_I`` and ``o_j -> O_J`` maps the image centre to the intersection
  with the right sign (it preserves both the radius ratio and the angle).
* **Angles** are in radians, differences wrapped to ``(-pi, pi]``; ``delta_theta
  = 0.2`` is read as radians, since the paper states its angles in ``(-pi, pi]``.
* **Degenerate pairs**: an image object exactly at the image centre (``r_i = 0``)
  has no ratio; such pairs are skipped.  ``std`` is the population standard
  deviation (numpy's default) of the ``e_k`` of the ``N_matched - 2`` other
  objects; the two objects of the pair carry no error.
* **Order**: pairs in lexicographic order of image indices (combinations) and
  map indices (permutations); the update rule is order-dependent, as published.

The loops over map objects and the other image objects are vectorised with
numpy (in chunks of map pairs).  The cost is ``O(n_img^3 n_map^3)``; an exact
bound (below) skips most candidates without changing the answer.

**The bound.**  Only a candidate that can still replace the best matters: one
with ``N_matched >= max(N_min, N_best)`` (``N_best`` never decreases, so the
value it has when a batch starts is safe for the whole batch).  Each other
image object ``o_k`` can only be matched by a map object of its label inside
an annular sector about ``c``: radius within ``R_I (r_k/r_i -+ delta_r)``,
direction within ``delta_theta`` of ``Theta_I - (theta_i - theta_k)``.  A
polar box ``|R - R_m| <= w``, ``|Theta - Theta_m| <= beta`` lies in the disk of
radius ``sqrt(w^2 + (R_m + w) R_m beta^2)`` about its middle point, and a grid
holding, per cell, a lower bound on the distance to the nearest map object of
each label tells in one look-up that a disk is empty.  The number of ``o_k``
whose sector may hold a map object, plus 2, bounds ``N_matched``; candidates
whose bound is below ``max(N_min, N_best)`` are skipped (first with one disk per
sector, then with 2 x 2 pieces on the survivors), and the others
go through the full test above, in the original order, with the same
arithmetic on each candidate.  A candidate with ``N_matched < N_best`` cannot
replace the best either, so its ``std`` is not computed.
``PaperOptions(prune=False)`` runs every candidate through the full test and
computes every ``std`` (the same results; for checking).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from ...objects import Objects
from .bound import NearestBound, wrap_angle
from .options import PaperOptions

__all__ = ["PaperMatch", "PaperOptions", "PaperResult", "match_paper"]


@dataclass(frozen=True)
class PaperMatch:
    """The best candidate: map point under the image centre ``b`` and the pair's similarity ``a``."""

    a: complex
    b: complex
    matched: int
    error_std: float


@dataclass(frozen=True)
class PaperResult:
    best: PaperMatch | None
    reason: str | None
    candidates_tested: int




def match_paper(
    z: np.ndarray, img_label: np.ndarray, objects: Objects, *, options: PaperOptions | None = None
) -> PaperResult:
    """Run Algorithm 1.

    Parameters
    ----------
    z : complex array (n,)
        Image objects in pixels relative to the image centre, y up.
    img_label : int array (n,)
        Label codes, in the same label table as ``objects``.
    objects : Objects
        The map objects to search (all of them, or those near a prior).
    options : PaperOptions, optional

    Returns
    -------
    PaperResult
        ``best`` is None when no candidate reached ``n_min`` matched objects.

    Examples
    --------
    Four points and their images under a similarity: every image pair finds the true centre.

    >>> pts = np.array([0, 10, 10j, 7 + 3j, -4 + 8j, 3 - 6j])
    >>> objs = Objects(pts.real, pts.imag, np.zeros(6, int), np.zeros(6), ("b",))
    >>> res = match_paper((pts - (2 + 2j)) / 0.5, np.zeros(6, int), objs)
    >>> complex(np.round(res.best.b, 9)), res.best.matched
    ((2+2j), 6)
    """
    opts = options or PaperOptions()
    z = np.asarray(z, dtype=np.complex128)
    img_label = np.asarray(img_label, dtype=np.int64)
    reason = _refusal(z.size, len(objects), opts)
    if reason is not None:
        return PaperResult(None, reason, 0)
    scene = _scene(z, img_label, objects, opts)
    best = _Best()
    tested = 0
    for i, j in combinations(range(z.size), 2):
        tested += _search_pair(scene, i, j, best)
    if best.match is None:
        return PaperResult(None, f"no candidate matched at least N_min = {opts.n_min} objects", tested)
    return PaperResult(best.match, None, tested)


# Slack of the float32 pre-tests (ratios and cosines): every pair they pass is re-tested exactly in float64.
_FLOAT32_SLACK = 1e-4


def _refusal(n_img: int, n_map: int, opts: PaperOptions) -> str | None:
    """Why the paper's method will not run on these counts (too few for pairs, too much work), or None."""
    if n_img < 2:
        return f"{n_img} objects: the paper's method needs pairs"
    if n_map < 2:
        return f"the map has {n_map} objects here: the paper's method needs pairs"
    work = n_img * (n_img - 1) / 2 * n_map * (n_map - 1) * n_img * n_map
    if work > opts.max_work:
        return (f"too large for the paper's method ({n_img} image objects x {n_map} map objects, about "
                f"{work:.0e} comparisons): give a prior or use the fast method")
    return None


@dataclass(frozen=True)
class _Scene:
    """What every pair's search reads: the image in polar form, the map, the bound and the options."""

    z: np.ndarray
    img_label: np.ndarray
    r: np.ndarray
    theta: np.ndarray
    map_z: np.ndarray
    map_label: np.ndarray
    single_label: bool
    bound: NearestBound | None
    opts: PaperOptions
    cos_dt32: np.float32  # cos(delta_theta), less the pre-test's slack


def _scene(z: np.ndarray, img_label: np.ndarray, objects: Objects, opts: PaperOptions) -> _Scene:
    """The search's inputs, with the bound when pruning is asked for and it can be exact."""
    map_z = objects.x + 1j * objects.y
    map_label = objects.label.astype(np.int64)
    single_label = np.unique(map_label).size <= 1 and np.unique(img_label).size <= 1
    bound = None
    if (
        opts.prune
        and opts.n_min > 2
        and opts.delta_r > 0
        and opts.delta_theta > 0
        and np.all(np.isfinite(z))
        and np.all(np.isfinite(map_z))
    ):
        keys: list[int | None] = [None] if single_label else [int(k) for k in np.unique(img_label)]
        bound = NearestBound(map_z, map_label, keys)
    cos_dt32 = np.float32(math.cos(opts.delta_theta) - _FLOAT32_SLACK)
    return _Scene(z, img_label, np.abs(z), np.angle(z), map_z, map_label, single_label, bound, opts, cos_dt32)


@dataclass(frozen=True)
class _Others:
    """The image objects other than a pair ``(o_i, o_j)``, seen from ``o_i``: what map objects are tested on."""

    ratio: np.ndarray  # r_k / r_i
    dtheta: np.ndarray  # theta_i - theta_k, wrapped
    lo32: np.ndarray  # float32 pre-test bounds on the map's radius ratio
    hi32: np.ndarray
    cos32: np.ndarray  # float32 cos and sin of dtheta
    sin32: np.ndarray
    same_label: np.ndarray | None  # (k, n_map): which map objects may stand for each; None: all (one label)
    keys: list[int | None]  # their labels as the bound knows them


def _others_of(scene: _Scene, i: int, j: int) -> _Others:
    """The other image objects of the pair ``(o_i, o_j)``."""
    n_img, opts = scene.z.size, scene.opts
    others = np.array([k for k in range(n_img) if k != i and k != j], dtype=np.int64)
    ratio_k = scene.r[others] / scene.r[i]
    dtheta_k = wrap_angle(scene.theta[i] - scene.theta[others])
    return _Others(
        ratio=ratio_k,
        dtheta=dtheta_k,
        lo32=(ratio_k - opts.delta_r - _FLOAT32_SLACK).astype(np.float32),
        hi32=(ratio_k + opts.delta_r + _FLOAT32_SLACK).astype(np.float32),
        cos32=np.cos(dtheta_k).astype(np.float32),
        sin32=np.sin(dtheta_k).astype(np.float32),
        same_label=None if scene.single_label else scene.img_label[others][:, None] == scene.map_label[None, :],
        keys=[None] * others.size if scene.single_label else [int(k) for k in scene.img_label[others]],
    )


def _map_pairs(scene: _Scene, i: int, j: int) -> tuple[np.ndarray, ...] | None:
    """The map 2-permutations ``(O_I, O_J)`` with the pair's labels, lexicographic in ``(I, J)``, and each one's
    similarity ``a`` and centre ``c`` (``perm_i, perm_j, a, c``); None when a label has no map object."""
    big_i = np.flatnonzero(scene.map_label == scene.img_label[i])
    big_j = np.flatnonzero(scene.map_label == scene.img_label[j])
    if not big_i.size or not big_j.size:
        return None
    pi_, pj_ = np.meshgrid(big_i, big_j, indexing="ij")
    keep = pi_ != pj_
    perm_i, perm_j = pi_[keep], pj_[keep]
    map_z, z = scene.map_z, scene.z
    a_all = (map_z[perm_j] - map_z[perm_i]) / (z[j] - z[i])
    centre_all = map_z[perm_i] - a_all * z[i]
    return perm_i, perm_j, a_all, centre_all


def _search_pair(scene: _Scene, i: int, j: int, best: _Best) -> int:
    """Test the image pair ``(o_i, o_j)`` against every map 2-permutation, offering each candidate to ``best``;
    the number of candidates (tested or ruled out by the bound)."""
    opts = scene.opts
    if scene.r[i] == 0.0 or scene.z[j] == scene.z[i]:
        return 0
    others = _others_of(scene, i, j)
    pairs = _map_pairs(scene, i, j)
    if pairs is None:
        return 0
    perm_i, perm_j, a_all, centre_all = pairs
    if scene.bound is None:
        order, n_bound = np.arange(perm_i.size), None
    else:
        order, n_bound = scene.bound.survivors(centre_all, scene.map_z[perm_i] - centre_all, others.ratio,
                                               others.dtheta, others.keys, max(opts.n_min, best.n), opts)
    for lo in range(0, order.size, opts.chunk):
        batch = order[lo : lo + opts.chunk]
        if n_bound is not None:
            # N_best may have grown since the bound was applied.
            batch = batch[n_bound[lo : lo + opts.chunk] >= max(opts.n_min, best.n)]
            if not batch.size:
                continue
        e_k = _errors(scene, others, centre_all[batch], perm_i[batch], perm_j[batch])
        best.offer(e_k, a_all[batch], centre_all[batch], opts)
    return perm_i.size


def _seen_from(map_z: np.ndarray, centre: np.ndarray, pi_c: np.ndarray, pj_c: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each map object seen from each candidate centre: radius ratio to ``O_I`` (inf for ``O_I`` and ``O_J``,
    which stand for no other object) and ``exp(i (Theta_I - Theta_K))``, both ``(C, n_map)``."""
    rows = np.arange(pi_c.size)
    rel = map_z[None, :] - centre[:, None]  # (C, n_map)
    radius = np.abs(rel)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio_map = radius / radius[rows, pi_c][:, None]
        # exp(i (Theta_I - Theta_K)) without trigonometry: unit vector of O_I times the conjugate of O_K's.
        unit = rel / radius
        turn = unit[rows, pi_c][:, None] * np.conj(unit)
    ratio_map[rows, pi_c] = np.inf
    ratio_map[rows, pj_c] = np.inf
    return ratio_map, turn


def _pretest(ratio_map: np.ndarray, turn: np.ndarray, others: _Others, cos_dt32: np.float32) -> tuple[np.ndarray, ...]:
    """(candidate, other image object, map object) triples that may pass both tolerances, from float32 tests.

    Every other image object against every other map object, one image object at a time (a (C, n_map) slab
    stays in cache).  The tests run in float32 with a hair of slack and the angle test as
    cos(a - b) > cos(delta) (the same set for delta < pi, without trigonometry); the caller re-tests every
    triple exactly in float64, so the outcome is the exact one.
    """
    ratio32 = ratio_map.astype(np.float32)
    cos32, sin32 = turn.real.astype(np.float32), turn.imag.astype(np.float32)
    # (Seeded with empties: a 2-object image has no other objects, and concatenate needs an array.)
    found_c, found_k, found_m = [np.empty(0, np.intp)], [np.empty(0, np.intp)], [np.empty(0, np.intp)]
    for col in range(others.ratio.size):
        ok = (ratio32 > others.lo32[col]) & (ratio32 < others.hi32[col])
        ok &= cos32 * others.cos32[col] + sin32 * others.sin32[col] > cos_dt32
        if others.same_label is not None:
            ok &= others.same_label[col][None, :]
        c_idx, m_idx = np.nonzero(ok)
        found_c.append(c_idx)
        found_m.append(m_idx)
        found_k.append(np.full(c_idx.size, col))
    return np.concatenate(found_c), np.concatenate(found_k), np.concatenate(found_m)


def _errors(scene: _Scene, others: _Others, centre: np.ndarray, pi_c: np.ndarray, pj_c: np.ndarray) -> np.ndarray:
    """``e_k`` of each candidate ``(C, n_others)``: each other image object's smallest error over the map objects
    within both tolerances (inf where none is)."""
    opts = scene.opts
    ratio_map, turn = _seen_from(scene.map_z, centre, pi_c, pj_c)
    c_idx, k_idx, m_idx = _pretest(ratio_map, turn, others, scene.cos_dt32)
    ratio_err = np.abs(others.ratio[k_idx] - ratio_map[c_idx, m_idx])
    angle_err = np.abs(wrap_angle(others.dtheta[k_idx] - np.angle(turn[c_idx, m_idx])))
    exact = (ratio_err < opts.delta_r) & (angle_err < opts.delta_theta)
    c_idx, k_idx = c_idx[exact], k_idx[exact]
    err = ratio_err[exact] + angle_err[exact]
    e_k = np.full((pi_c.size, others.ratio.size), np.inf)
    np.minimum.at(e_k, (c_idx, k_idx), err)  # best map match of each image object
    return e_k


@dataclass
class _Best:
    """Algorithm 1's running best: ``N_best``, ``E_best`` and its candidate."""

    n: int = 0
    e: float = math.inf
    match: PaperMatch | None = None

    def offer(self, e_k: np.ndarray, a: np.ndarray, centre: np.ndarray, opts: PaperOptions) -> None:
        """The update rule, candidate by candidate in order (it is sequential): ``e_k`` as from :func:`_errors`."""
        matched_k = np.isfinite(e_k)
        n_matched = 2 + matched_k.sum(axis=1)
        for c in np.flatnonzero(n_matched >= opts.n_min):  # few
            if opts.prune and n_matched[c] < self.n:
                continue  # cannot replace the best: its std is not needed
            e_ij = float(np.std(e_k[c, matched_k[c]]))
            if n_matched[c] >= self.n and e_ij < self.e:
                self.n, self.e = int(n_matched[c]), e_ij
                self.match = PaperMatch(complex(a[c]), complex(centre[c]), self.n, e_ij)
