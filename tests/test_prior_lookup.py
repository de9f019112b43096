"""A prior applies before a lookup's nearest hits are taken: tile quad indexes hold where each quad lies.

On a perfect lattice every quad has thousands of copies with the same invariants.  A lookup that takes its
``k`` nearest map quads first and applies the prior after can come back with copies outside the prior's disc
only, hiding the true pose; an index with positions ranks, among equally good quads, those nearest the prior
first, and never returns one outside the disc.
"""

from __future__ import annotations

import numpy as np
import pytest

from mapdb.match.quads import QuadIndex, canonical_quads
from mapdb.objects import Objects

SPACING = 25.0
SIDE = 40  # 40 x 40 lattice: 1 km square


def lattice(jitter: float = 0.0) -> Objects:
    i, j = np.meshgrid(np.arange(SIDE), np.arange(SIDE))
    shake = np.random.default_rng(1).normal(0.0, jitter, (2, i.size))
    return Objects.from_names(i.ravel() * SPACING + shake[0], j.ravel() * SPACING + shake[1], ["building"] * i.size)


def one_quad(objects: Objects, near: complex) -> tuple[np.ndarray, np.ndarray]:
    """Invariants and labels of the map quad made of the four lattice points of a cell near ``near``."""
    z = objects.x + 1j * objects.y
    corner = np.round(near / SPACING) * SPACING
    cell = np.array([corner, corner + SPACING, corner + 1j * SPACING, corner + SPACING + 1j * SPACING])
    ids = [int(np.argmin(np.abs(z - c))) for c in cell]
    _, inv, _ = canonical_quads(z[ids][None, :])
    return inv, np.zeros((1, 4), np.int64)


@pytest.mark.parametrize("centre", [120 + 140j, 830 + 610j])
def test_hits_come_from_the_prior_disc(centre: complex) -> None:
    objects = lattice()
    index = QuadIndex(objects, positions=True)
    inv, labels = one_quad(objects, centre)
    rows, quad_z = index.lookup(inv, labels, np.array([0.01]), 16, near=(centre, 60.0))
    assert len(rows) == 16  # the cap is filled from inside the disc
    assert np.all(np.abs(quad_z.mean(axis=1) - centre) <= 60.0)


def test_without_positions_the_cap_is_filled_before_the_prior() -> None:
    """The same lookup on an index without positions, on a lattice whose copies differ by centimetres (as a street
    grid's do): the 16 nearest copies are taken first, from anywhere in the tile, and filtering them by the disc
    leaves few or none.  Exact copies tie, and ties are ranked nearest the place (tests/test_kernel_quads.py)."""
    objects = lattice(jitter=0.01)
    centre = 830 + 610j
    inv, labels = one_quad(objects, centre)
    plain = QuadIndex(objects)
    rows, _ = plain.lookup(inv, labels, np.array([0.01]), 16, near=(centre, 60.0))
    placed = QuadIndex(objects, positions=True)
    rows_placed, _ = placed.lookup(inv, labels, np.array([0.01]), 16, near=(centre, 60.0))
    assert len(rows) < len(rows_placed) // 2  # the positions' index ranks the disc's copies first
    exact = lattice()
    tied, _ = QuadIndex(exact).lookup(*one_quad(exact, centre), np.array([0.01]), 16, near=(centre, 60.0))
    assert len(tied) == 16


def test_the_radius_holds_for_the_invariants_alone() -> None:
    """A query a little off every map quad finds nothing, however near the prior it is."""
    objects = lattice()
    index = QuadIndex(objects, positions=True)
    inv, labels = one_quad(objects, 500 + 500j)
    rows, _ = index.lookup(inv + 0.05, labels, np.array([0.01]), 16, near=(500 + 500j, 1000.0))
    assert rows.size == 0
    rows, _ = index.lookup(inv + 0.004, labels, np.array([0.01]), 16, near=(500 + 500j, 1000.0))
    assert rows.size == 16


def test_merged_tiles_keep_positions_and_an_index_with_positions_needs_a_place() -> None:
    objects = lattice()
    west = QuadIndex(objects, positions=True, anchors=objects.x < 500)
    east = QuadIndex(objects, positions=True, anchors=objects.x >= 500)
    merged = QuadIndex.merged([west, east])
    assert merged.positions and merged.n_quads == west.n_quads + east.n_quads
    inv, labels = one_quad(objects, 700 + 300j)
    rows, quad_z = merged.lookup(inv, labels, np.array([0.01]), 8, near=(700 + 300j, 40.0))
    assert len(rows) == 8 and np.all(np.abs(quad_z.mean(axis=1) - (700 + 300j)) <= 40.0)
    with pytest.raises(ValueError, match="near a place"):
        merged.lookup(inv, labels, np.array([0.01]), 8)
    with pytest.raises(ValueError, match="with and without positions"):
        QuadIndex.merged([west, QuadIndex(objects)])
