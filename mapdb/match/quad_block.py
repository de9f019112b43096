"""A block of a prior's tiles looked up as one quad index (:class:`QuadBlock`), with no tree built for it until
it has served enough lookups to pay for one."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .quads import QuadIndex, mergeable_parts

__all__ = ["MERGE_AFTER", "QuadBlock"]

# A block of tiles (QuadBlock) is merged into one tree once it has served this many lookups: 14 ms of merging on
# Monaco against 0.35 ms more a lookup in its tiles together (about 40 lookups; a flight's images in a row).
MERGE_AFTER = 32


class QuadBlock(QuadIndex):
    """Several quad indexes (a block of a prior's tiles) looked up as one: the hits of :meth:`QuadIndex.merged`'s
    index over them, with no tree built.  The kernel searches the parts' trees together, keeping each query's ``k``
    nearest of them all, equal distances in the order of the merged index's rows (the parts' in turn): a search's
    answer depends on the points and their rows, not on the tree's shape.  Merging a block's tiles costs 14 ms on
    Monaco, a lookup in the tiles together 0.75 ms against the merged tree's 0.40
    (``benchmarks/diagnostics/quad_blocks.py``): the block merges its tiles once it has served ``MERGE_AFTER``
    lookups (a flight's images in a row), as a renter buys once the rent paid would have bought; scattered images
    that meet a block a few times never pay for a merge.  The answers are the same either way.

    Examples
    --------
    >>> from mapdb.objects import Objects
    >>> rng = np.random.default_rng(0)
    >>> parts = [QuadIndex(Objects.from_names(rng.uniform(0, 100, 30), rng.uniform(0, 100, 30), ["b"] * 30))
    ...          for _ in range(2)]
    >>> block, merged = QuadBlock(parts), QuadIndex.merged(parts)
    >>> inv, labels, radius = merged.tree.data[:5, :4], np.zeros((5, 4), np.int64), np.full(5, 0.05)
    >>> all(np.array_equal(a, b) for a, b in zip(block.lookup(inv, labels, radius, 3), merged.lookup(inv, labels,
    ...                                                                                            radius, 3)))
    True
    """

    def __init__(self, parts: Sequence[QuadIndex]) -> None:  # noqa: D107 (the class says it)
        self.parts, self.labels, self.positions = mergeable_parts(parts)
        if any(isinstance(q, QuadBlock) for q in self.parts) or len(self.parts) > 256:
            raise ValueError("a block holds at most 256 quad indexes, none a block")
        self.tree = self.parts[0].tree if self.parts else None  # says the block holds quads; its parts' are searched
        self._n_quads = sum(q.n_quads for q in self.parts)
        self.lookups = 0
        self.merged_index: QuadIndex | None = None

    def searched(self) -> tuple[list[QuadIndex], bool]:
        """The indexes a lookup searches, and whether together (one lookup more counted): the parts, or once the
        block has served ``MERGE_AFTER`` lookups, their merged index."""
        self.lookups += 1
        if self.merged_index is None and self.lookups > MERGE_AFTER and len(self.parts) > 1:
            self.merged_index = QuadIndex.merged(self.parts)
        return ([self.merged_index], False) if self.merged_index is not None else (self.parts, True)

    @property
    def n_quads(self) -> int:
        return self._n_quads

    @property
    def quad_z(self) -> np.ndarray:  # type: ignore[override]  # the merged index's rows, made when asked
        return np.concatenate([q.quad_z for q in self.parts]) if self.parts else np.zeros((0, 4), np.complex128)

    def _box(self) -> tuple[float, float, float, float]:
        if self._where is None:
            boxes = [q._box() for q in self.parts]
            self._where = (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes),
                           max(b[3] for b in boxes))
        return self._where
