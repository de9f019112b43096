"""One candidate per place (mapdb.match.refine): the merge of a big pool in array operations and the greedy
suppression over Python numbers choose what the plain loops over pose_shift choose, ties and duplicates included."""

from __future__ import annotations

import numpy as np

from mapdb.match.refine import Candidate, distinct, merge_candidates, merged_one_by_one


def _plain_merge(pool: list[Candidate], diag_px: float) -> list[Candidate]:
    return merged_one_by_one(sorted(pool, key=lambda c: (c.log10_nfa, -c.inliers)), diag_px)


def _pool(rng: np.random.Generator, n: int) -> list[Candidate]:
    """``n`` candidates around five places, some turned a half turn, scores often tied (the NFA's floor)."""
    places = 4.7e6 + 3.9e5j + rng.normal(0, 300, 5) + 1j * rng.normal(0, 300, 5)
    pool = [Candidate(a=complex(0.5 * np.exp(1j * rng.choice([0.0, 0.1, 3.0])) * (1 + rng.normal(0, 0.01))),
                      b=complex(rng.choice(places) + rng.normal(0, 20) + 1j * rng.normal(0, 20)),
                      log10_nfa=float(rng.choice([-300.0, -5.0, 1.0, rng.normal()])), inliers=int(rng.integers(3, 9)),
                      sigma_axis_m=1.0, variance_factor=1.0, pairs=np.zeros((0, 2), np.int64)) for _ in range(n)]
    if n > 3:
        pool[1] = pool[0]  # the same candidate twice
        pool[2] = Candidate(**vars(pool[3]))  # an equal one
    return pool


def test_merging_a_pool_keeps_what_the_plain_loop_keeps() -> None:
    rng = np.random.default_rng(12)
    merged_big = 0
    for n in [0, 1, 5, 15, 16, 17, 40, 90] * 6:
        pool = _pool(rng, n)
        for diag_px in (800.0, 1e-3, 1e4):
            mine, plain = merge_candidates(pool, diag_px), _plain_merge(pool, diag_px)
            assert [id(c) for c in mine] == [id(c) for c in plain]
            merged_big += n >= 16 and 1 < len(mine) < n
    assert merged_big > 10  # big pools where some candidates were merged and some kept


def test_distinct_places_are_the_plain_loops() -> None:
    rng = np.random.default_rng(13)
    for _ in range(200):
        h = int(rng.integers(1, 20))
        b = 4.7e6 + rng.normal(0, 30, h) + 1j * rng.normal(0, 30, h)
        b[rng.integers(0, h)] = b[0]
        separation = rng.choice([5.0, 20.0, rng.uniform(0, 40)], h)
        order = np.argsort(rng.normal(size=h), kind="stable")
        plain: list[int] = []
        for i in order:
            if all(abs(b[i] - b[j]) > max(separation[i], separation[j]) for j in plain):
                plain.append(int(i))
                if len(plain) >= 4:
                    break
        assert distinct(b, order, separation, 4) == plain
