"""Where node locations live: libosmium's location index (in memory or in a temporary file), the
temporary directory of large inputs, and the release of a mapped index's pages.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import osmium

from ...errors import MapdbIOError

__all__ = ["DENSE_INDEX_BYTES", "FILE_INDEX_BYTES", "NODE_INDEXES", "choose_node_index"]

# libosmium's coordinate for a node it has no location for (a node missing from an extract).
_UNDEFINED = 2**31 - 1

# Where libosmium keeps node locations (16 bytes a node in a sparse index, 8 bytes a node id in a dense
# one).  Small inputs keep them in memory; from FILE_INDEX_BYTES of input the index is a file (mapped, its
# pages released to the page cache as the pass goes, so that the process's memory stays bounded); from
# DENSE_INDEX_BYTES, a continent or the planet, whose node ids are dense, a dense file array.
FILE_INDEX_BYTES = 64 << 20
DENSE_INDEX_BYTES = 16 << 30
NODE_INDEXES = ("auto", "flex_mem", "sparse_mem_array", "dense_mem_array", "sparse_file_array", "dense_file_array")
# Disk a file index needs, per byte of input, as checked before the pass (a full disk would make libosmium's
# mapped file fault): sparse 16 bytes a node at up to ~0.15 nodes a PBF byte, dense 8 bytes an id.
_INDEX_BYTES_PER_INPUT_BYTE = {"sparse_file_array": 3.0, "dense_file_array": 1.0}

_MADV_DONTNEED = 4  # Linux


def choose_node_index(input_bytes: int) -> str:
    """The libosmium node location index ``node_index="auto"`` uses for an input of this many bytes.

    Examples
    --------
    >>> choose_node_index(2 << 20), choose_node_index(1 << 30), choose_node_index(70 << 30)
    ('flex_mem', 'sparse_file_array', 'dense_file_array')
    """
    if input_bytes >= DENSE_INDEX_BYTES:
        return "dense_file_array"
    return "sparse_file_array" if input_bytes >= FILE_INDEX_BYTES else "flex_mem"


def _defined(location: Any) -> bool:
    """Whether a node has coordinates at all (a node missing from an extract has none)."""
    return location.x != _UNDEFINED or location.y != _UNDEFINED


class _Workspace:
    """A temporary directory under ``index_dir``, made when first needed and removed at the end."""

    def __init__(self, index_dir: str | Path | None) -> None:
        self.parent = Path(index_dir) if index_dir is not None else Path(tempfile.gettempdir())
        self._tmp: tempfile.TemporaryDirectory[str] | None = None

    def __enter__(self) -> _Workspace:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()

    def file(self, name: str, need_bytes: int = 0, what: str = "temporary files") -> str:
        """A path for a new temporary file, after checking that ``need_bytes`` fit in the directory."""
        try:
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix="mapdb-osm-", dir=self.parent)
            free = shutil.disk_usage(self._tmp.name).free
        except OSError as exc:
            raise MapdbIOError(f"{self.parent}: cannot hold the {what} ({exc.strerror or exc})") from None
        if need_bytes > free:
            raise MapdbIOError(f"{self.parent}: {free / 2**30:.1f} GiB free, the {what} need about "
                               f"{need_bytes / 2**30:.1f} GiB; free some space or choose another directory")
        return os.path.join(self._tmp.name, name)

    def node_index(self, kind: str, input_bytes: int, path: Path) -> tuple[Any, str | None]:
        """libosmium's node location index for an input of ``input_bytes`` (``kind`` "auto": by its size),
        and its file (None in memory)."""
        kind = choose_node_index(input_bytes) if kind == "auto" else kind
        if kind not in _INDEX_BYTES_PER_INPUT_BYTE:
            return osmium.index.create_map(kind), None
        need = int(_INDEX_BYTES_PER_INPUT_BYTE[kind] * input_bytes)
        location = self.file("node-locations", need, f"node location index of {path.name} ({kind})")
        try:
            return osmium.index.create_map(f"{kind},{location}"), location
        except (RuntimeError, OSError) as exc:
            raise MapdbIOError(f"{self.parent}: cannot hold the node location index ({exc})") from None


def _release_mapped(path: str) -> None:
    """Drop this process's resident pages of a shared file mapping (they stay in the page cache); Linux only."""
    try:
        with open("/proc/self/maps") as f:
            ranges = [line.split()[0] for line in f if line.rstrip().endswith(path)]
        libc = ctypes.CDLL(None, use_errno=True)
    except OSError:
        return
    for span in ranges:
        start, end = (int(v, 16) for v in span.split("-"))
        libc.madvise(ctypes.c_void_p(start), ctypes.c_size_t(end - start), _MADV_DONTNEED)
