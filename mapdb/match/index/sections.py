"""Writing a version-4 index's packed sections (:mod:`~mapdb.match.index.build` writes the quad records).

The coordinates and the neighbours (:func:`write_objects`), the directory pages and their fence
(:func:`write_directory`); each placed with the build's :class:`~mapdb.match.index.layout.SectionPlan`, the layout
of ``docs/index_format.md``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from .layout import SectionPlan, pwrite_all
from .packed import NB_BLOCK, PAD, pack_coords, pack_neighbours

__all__ = ["write_directory", "write_objects"]

_NB_STEP = NB_BLOCK * 1024  # objects whose neighbours are packed at once (bit arrays: some 40 MB)


def write_objects(out_path: str | os.PathLike[str], workdir: Path, layout: SectionPlan, coords: np.ndarray,
                  table: np.ndarray) -> tuple[int, int]:
    """Write the packed coordinates (``co_*``) and each object's neighbours ``table`` (``nb_*``), packed into work
    files in ``workdir`` first, since the block tables come before the data; return the two data sections' bytes."""
    n = len(table)
    blocks = -(-n // NB_BLOCK)
    co_len, co_width, co_base = np.zeros(blocks, np.int64), np.zeros((blocks, 2), np.uint8), np.zeros((blocks, 2),
                                                                                                      np.int64)
    nb_blocks = blocks if table.shape[1] else 0
    nb_len, nb_width = np.zeros(nb_blocks, np.int64), np.zeros(nb_blocks, np.uint8)
    with open(workdir / "co_data", "wb") as co, open(workdir / "nb_data", "wb") as nb:
        for lo in range(0, n, _NB_STEP):
            at = slice(lo // NB_BLOCK, lo // NB_BLOCK + -(-min(_NB_STEP, n - lo) // NB_BLOCK))
            data, co_len[at], co_width[at], co_base[at] = pack_coords(coords[lo : lo + _NB_STEP], lo)
            co.write(data.tobytes())
            if nb_blocks:
                data, nb_len[at], nb_width[at] = pack_neighbours(table[lo : lo + _NB_STEP], lo)
                nb.write(data.tobytes())
        co.write(bytes(PAD))
        nb.write(bytes(PAD))
    co_bytes, nb_bytes = int(co_len.sum()), int(nb_len.sum())
    arrays = {"co_start": _starts(co_len), "co_width": co_width, "co_base": co_base.astype("<i4"),
              "nb_start": _starts(nb_len), "nb_width": nb_width}
    with open(out_path, "r+b") as out:
        for name, size in (("co", co_bytes), ("nb", nb_bytes)):
            for part in ("start", "width", "base"):
                if f"{name}_{part}" in arrays:
                    array = arrays[f"{name}_{part}"]
                    layout.place(f"{name}_{part}", array.dtype.str if array.itemsize > 1 else "u1", array.shape)
                    pwrite_all(out.fileno(), array.tobytes(), layout[f"{name}_{part}"]["offset"])
            layout.place(f"{name}_data", "u1", (size + PAD,))
            out.seek(layout[f"{name}_data"]["offset"])
            with open(workdir / f"{name}_data", "rb") as src:
                shutil.copyfileobj(src, out, 16 << 20)
    return co_bytes, nb_bytes


def _starts(lengths: np.ndarray) -> np.ndarray:
    """Each block's first byte and the end (``<u8``)."""
    return np.concatenate([[0], np.cumsum(lengths)]).astype("<u8")


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
