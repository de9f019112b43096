"""Class tables: the codes or names of a user's data mapped to mapdb labels, read from TOML and checked.

One format serves ``mapdb objects --classes`` (mask pixel values, COCO category ids or names) and
``mapdb build --label-map`` (the values of a layer's column)::

    # codes (integers) or names -> mapdb labels; anything not listed is skipped and counted
    column = "building"        # label maps only: the column whose values are mapped
    [classes]
    1 = "building"
    2 = "water"
    house = "building"

Every label must be one of the label table's (the default, or ``--labels FILE.toml``); a label that
is not is an error naming the file and the key, as in a label file.  Keys are text: a key that is an
integer (``1``, ``-3``) also serves as a code (:attr:`ClassTable.codes`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .errors import LabelTableError
from .labels import read_toml

__all__ = ["ClassTable", "check_label", "load_class_table"]

_INTEGER = re.compile(r"[+-]?[0-9]+")
# Mask codes are integers of at most 64 bits; a longer key cannot match any pixel.
_CODE_RANGE = (-(2**63), 2**64)


@dataclass(frozen=True)
class ClassTable:
    """A checked class table: ``classes`` maps key text to a label; ``column`` is a label map's column."""

    classes: dict[str, str]
    column: str | None = None
    source: str = "<classes>"

    @property
    def codes(self) -> dict[int, str]:
        """The integer keys as codes (mask pixel values, COCO category ids).

        Examples
        --------
        >>> ClassTable({"1": "building", "house": "building", "-2": "water"}).codes
        {1: 'building', -2: 'water'}
        """
        return {int(k): v for k, v in self.classes.items() if _INTEGER.fullmatch(k)}


def check_label(label: str, labels: Sequence[str], where: str) -> str:
    """``label`` if it is one of ``labels``, else a :class:`LabelTableError` naming ``where``.

    Examples
    --------
    >>> check_label("building", ["building", "park"], "--label")
    'building'
    >>> check_label("buildings", ["building", "park"], "--label")
    Traceback (most recent call last):
    mapdb.errors.LabelTableError: --label: unknown label 'buildings' (labels: building, park)
    """
    if not isinstance(label, str) or label not in labels:
        raise LabelTableError(f"{where}: unknown label {label!r} (labels: {', '.join(labels)})")
    return label


def load_class_table(path: str | Path, labels: Sequence[str], *, column: bool = False) -> ClassTable:
    """Read and check a class table (module docs).

    Parameters
    ----------
    path : path-like
        The TOML file.
    labels : sequence of str
        The label names allowed (the label table's).
    column : bool
        Whether the file may name a ``column`` (label maps of ``mapdb build``).

    Raises
    ------
    LabelTableError
        Not TOML, an unknown key, no ``[classes]`` table, a label that is not in ``labels``, a code
        out of 64-bit range; one line naming the file and the key.
    MapdbIOError
        The file is missing or unreadable.
    """
    path = Path(path)
    doc = read_toml(path)
    allowed = ("classes", "column") if column else ("classes",)
    for key in doc:
        if key not in allowed:
            raise LabelTableError(f"{path}: {key}: unknown key (expected {' or '.join(allowed)})")
    table = doc.get("classes")
    if not isinstance(table, dict) or not table:
        raise LabelTableError(f"{path}: classes: missing or empty; a [classes] table maps codes or names to labels")
    name = doc.get("column")
    if name is not None and (not isinstance(name, str) or not name):
        raise LabelTableError(f"{path}: column: must be a non-empty string")
    classes = {}
    for key, label in table.items():
        where = f"{path}: classes.{key}"
        if isinstance(label, dict):  # a dotted key such as 1.5 = "x" makes a nested table
            raise LabelTableError(f"{where}: must map to a label name, not a table (quote keys with dots)")
        if _INTEGER.fullmatch(key) and not _CODE_RANGE[0] <= int(key) < _CODE_RANGE[1]:
            raise LabelTableError(f"{where}: a code must fit in 64 bits")
        classes[key.strip()] = check_label(label, labels, where)
    return ClassTable(classes, name, str(path))
