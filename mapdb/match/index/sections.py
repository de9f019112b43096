"""Writing a version-3 index's packed sections (:mod:`~mapdb.match.index.build` writes the quad records).

The coordinates and the neighbours (:func:`write_neighbours`), the directory pages and their fence
(:func:`write_directory`); each placed with the build's :class:`~mapdb.match.index.layout.SectionPlan`, the layout
of ``docs/index_format.md``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from .layout import SectionPlan, pwrite_all
from .packed import NB_BLOCK, PAD, pack_neighbours

__all__ = ["write_directory", "write_neighbours"]

_NB_STEP = NB_BLOCK * 1024  # objects whose neighbours are packed at once (bit arrays: some 40 MB)


def write_neighbours(out_path: str | os.PathLike[str], work: Path, layout: SectionPlan, coords: np.ndarray,
                     table: np.ndarray) -> int:
    """Write the coordinates and each object's neighbours ``table`` (``nb_start``, ``nb_width``, ``nb_data``,
    packed into the work file ``work`` first, since ``nb_start`` comes before them); return their bytes."""
    n = len(table)
    blocks = -(-n // NB_BLOCK) if table.shape[1] else 0
    lengths, widths = np.zeros(blocks, np.int64), np.zeros(blocks, np.uint8)
    with open(work, "wb") as f:
        for lo in range(0, n if blocks else 0, _NB_STEP):
            data, length, width = pack_neighbours(table[lo : lo + _NB_STEP], lo)
            f.write(data.tobytes())
            lengths[lo // NB_BLOCK : lo // NB_BLOCK + length.size] = length
            widths[lo // NB_BLOCK : lo // NB_BLOCK + width.size] = width
        f.write(bytes(PAD))
    nb_bytes = int(lengths.sum())
    layout.place("nb_start", "<u8", (blocks + 1,))
    layout.place("nb_width", "u1", (blocks,))
    layout.place("nb_data", "u1", (nb_bytes + PAD,))
    with open(out_path, "r+b") as out:
        fd = out.fileno()
        pwrite_all(fd, coords.tobytes(), layout["coords"]["offset"])
        pwrite_all(fd, np.concatenate([[0], np.cumsum(lengths)]).astype("<u8").tobytes(),
                   layout["nb_start"]["offset"])
        pwrite_all(fd, widths.tobytes(), layout["nb_width"]["offset"])
        out.seek(layout["nb_data"]["offset"])
        with open(work, "rb") as src:
            shutil.copyfileobj(src, out, 16 << 20)
    return nb_bytes


def write_directory(out_path: str | os.PathLike[str], layout: SectionPlan,
                    pages: tuple[np.ndarray, np.ndarray]) -> tuple[int, int]:
    """Write the directory ``pages`` (packed data and fence, :func:`~mapdb.match.index.packed.directory_pages`);
    return the data's bytes and the number of pages."""
    data, fence = pages
    layout.place("dir_data", "u1", (data.size + PAD,))
    layout.place("fence", "<u8", fence.shape)
    with open(out_path, "r+b") as out:
        pwrite_all(out.fileno(), data.tobytes() + bytes(PAD), layout["dir_data"]["offset"])
        pwrite_all(out.fileno(), fence.tobytes(), layout["fence"]["offset"])
    return int(data.size), fence.shape[0] - 1
