"""Which inputs a command was given: a file's SHA-256, and the same input given twice.

``build`` (sources) and ``merge`` (maps) read an input given twice once, with a warning; the identity is the
file's device and inode, or its bytes' SHA-256 (a copy under another name).
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path
from typing import Any

__all__ = ["duplicate_input", "file_fingerprint", "file_sha256"]


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, read in blocks (sources and tables are recorded by it)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def file_fingerprint(path: Path) -> tuple[tuple[int, int], str] | None:
    """(device and inode, SHA-256) of a regular file; None for anything else (its reader says what is wrong)."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            return None
        return (st.st_dev, st.st_ino), file_sha256(path)
    except OSError:
        return None


def duplicate_input(path: Path, fingerprint: tuple[tuple[int, int], str] | None, seen: dict[Any, Path],
               what: str = "source") -> str | None:
    """The warning for an input already given (the same file, or the same bytes), else None; ``seen`` learns it.

    Shared by ``build`` (sources) and ``merge`` (maps, ``what="map"``)."""
    if fingerprint is None:
        return None
    identity, sha = fingerprint
    if identity in seen:
        first = seen[identity]
        return f"{path}: given twice; read once" if first == path else \
            f"{path}: the same file as {what} {first}; read once"
    if sha in seen:
        return f"{path}: the same content as {what} {seen[sha]} (SHA-256 {sha[:16]}...); read once"
    seen[identity] = seen[sha] = path
    return None
