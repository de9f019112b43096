"""Merge maps of neighbouring or overlapping regions into one map.

Maps built separately (two regional extracts that share a border strip, a country built in parts on
several machines) become one map, with every object that several of them hold kept once.

**What "the same object" means.**  The map format stores no identity per object: a map is positions,
labels and areas.  Two maps hold the same object when they hold the same label at the same stored
position: the same OSM element (a building, a junction) read from two extracts of the same data gives
bit-identical coordinates, since each object's centroid is computed from its own geometry alone, so
it lands on the same quantum in both maps; a raster patch or a layer feature read twice does too.  A
map stored in another CRS than the output is reprojected, which moves a position by up to a quantum:
its objects are the same as those of the other maps within one quantum on each axis.  Objects of one
map are never merged with each other (a map already holds at most one object per label and position).

Why not an id per object: OSM ids would cost about as much again as a whole map (20 or more bits an
object against 3 to 4 bytes for position, label and area), objects made of several OSM elements (road
intersections merged within 5 m, roundabouts drawn as several ways) have no single id, rasters and
layers have none, and maps written before would have to be rebuilt.  An object cut by the edge of one
extract (a multipolygon missing members) has another centroid there and is kept twice; extracts cut
with complete ways and multipolygons (``osmium extract --strategy smart``) have none.

Maps merge only when they share the quantum and the label table (names, in order); otherwise the
error says which differ and how to rebuild.  The header keeps every input's sources (each naming the
map it came through) and, under ``build``, the inputs' own build options.
"""

from __future__ import annotations

import hashlib
import json
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer

from .._scipy import cKDTree
from ..errors import EmptyMapError, SourceError
from ..mapfile.reader import open_map
from ..mapfile.writer import MapWriter
from ..objects import Objects
from ..progress import ProgressLike, as_progress
from .inputs import duplicate_input, file_fingerprint, file_sha256
from .pipeline import _auto_crs, _projected_crs
from .reading import _to_lonlat

__all__ = ["content_digest", "merge_maps"]


def merge_maps(inputs: Sequence[str | Path], output: str | Path, *, crs: str = "auto",
               progress: ProgressLike = None) -> dict[str, Any]:
    """Merge maps into one, keeping once the objects that several of them hold.

    Parameters
    ----------
    inputs : sequence of paths
        Map files with the same quantum and label table, in any CRSs.  A map given twice (the same file, or
        the same SHA-256 as an earlier one) is read once, with a warning, as ``build`` does for sources.
    output : path
        The merged map; written to a temporary file and renamed, so a failure (a full disk) leaves an
        earlier file of that name intact.
    crs : str
        ``"auto"``: the inputs' CRS when they share one, else the UTM zone of the objects' median place;
        or any projected CRS pyproj accepts.
    progress : Progress or callable, optional
        Receives a message per stage.

    Returns
    -------
    dict
        ``{"output", "crs", "count", "labels": {name: count}, "inputs": [{"name", "objects", "kept"}],
        "duplicates": n, "warnings": [...]}``; ``duplicates`` counts the objects dropped because an earlier
        input holds them.

    Raises
    ------
    SourceError
        No inputs, or inputs that differ in quantum or label table; a ``crs`` that is not projected.
    MapFormatError, MapdbIOError
        An input that is not a readable map; an output that cannot be written.
    EmptyMapError
        If no object projects into the output CRS.
    """
    say = as_progress(progress)
    if not inputs:
        raise SourceError("no maps to merge")
    chosen = None if crs == "auto" else _projected_crs(crs)  # a bad --crs is refused before any reading
    unique, warnings = _unique_inputs(inputs)
    maps = [_read_input(path, say, sha) for path, sha in unique]
    quantum, labels = _common_layout(maps)
    target, crs_warnings = (chosen, []) if chosen else _output_crs(maps)
    warnings += crs_warnings
    parts, kept_counts, dropped = _deduplicated(maps, target, quantum, say)
    for read in maps:
        del read["objects_"]  # the objects kept are in ``parts``: the inputs' own copies can go
    total = sum(len(p) for p in parts)
    if total == 0:
        raise EmptyMapError(f"{', '.join(str(p) for p in inputs)}: no object projects into {target}")
    say(f"writing {total:,} objects to {output} ({target}) ...")
    metadata = {"sources": [dict(s, map=m["name"]) for m in maps for s in m["sources"]],
                "build": {"merged": [{key: m[key] for key in ("name", "sha256", "crs", "objects", "build")}
                                     for m in maps], "crs": crs}}
    # Part by part into the streaming writer: no merged copy of all the parts is made.
    with MapWriter(output, quantum=quantum, metadata=metadata) as writer:
        while parts:
            writer.add(parts.pop(0).relabel(labels))
        written = writer.finish()
    return {"output": str(output), "crs": target, "count": written, "labels": writer.label_counts,
            "inputs": [{"name": m["name"], "objects": m["objects"], "kept": k} for m, k in zip(maps, kept_counts,
                                                                                            strict=True)],
            "duplicates": dropped, "warnings": warnings}


def _unique_inputs(inputs: Sequence[str | Path]) -> tuple[list[tuple[Path, str | None]], list[str]]:
    """Each input map once, with its SHA-256 when it is a regular file; a warning for each one left out.

    A map merged with itself would only have every object dropped as a duplicate: the second copy is not read.
    """
    unique: list[tuple[Path, str | None]] = []
    warnings = []
    seen: dict[Any, Path] = {}
    for path in map(Path, inputs):
        fingerprint = file_fingerprint(path)  # None for what is not a regular file: open_map says what is wrong
        duplicate = duplicate_input(path, fingerprint, seen, "map")
        if duplicate:
            warnings.append(duplicate)
        else:
            unique.append((path, fingerprint[1] if fingerprint else None))
    return unique, warnings


def _read_input(path: Path, say: Any, sha: str | None = None) -> dict[str, Any]:
    """One input map's objects and what the merge needs of its header (``sha``: its SHA-256, if known)."""
    say(f"reading {path} ...")
    with open_map(path) as m:
        objects = m.all()
        header = m.metadata
    sources = header.get("sources") if isinstance(header.get("sources"), list) else []
    return {"path": path, "name": path.name, "sha256": sha or file_sha256(path), "objects_": objects,
            "objects": len(objects), "crs": objects.crs, "quantum": float(header["quantum"]), "labels": objects.labels,
            "sources": sources, "build": header.get("build")}


def _common_layout(maps: list[dict[str, Any]]) -> tuple[float, tuple[str, ...]]:
    """The quantum and label table every input shares; a SourceError saying what differs otherwise."""
    first = maps[0]
    for m in maps[1:]:
        if m["quantum"] != first["quantum"]:
            raise SourceError(
                f"{m['path']}: quantum {m['quantum']:g} m, but {first['path']} has {first['quantum']:g} m; maps "
                f"merge only at one quantum: rebuild {m['name']} with --quantum {first['quantum']:g}")
        if m["labels"] != first["labels"]:
            raise SourceError(f"{m['path']}: {_label_difference(first, m)}; maps merge only with one label table: "
                              f"rebuild both with the same --labels file")
    return first["quantum"], first["labels"]


def _label_difference(a: dict[str, Any], b: dict[str, Any]) -> str:
    """What differs between two label tables, in words.

    Examples
    --------
    >>> _label_difference({"name": "a.mapdb", "labels": ("x", "y")}, {"name": "b.mapdb", "labels": ("y", "z")})
    'its label table differs from the one of a.mapdb (only in b.mapdb: z; only in a.mapdb: x)'
    >>> _label_difference({"name": "a.mapdb", "labels": ("x", "y")}, {"name": "b.mapdb", "labels": ("y", "x")})
    'its label table differs from the one of a.mapdb (the same labels in another order)'
    """
    extra = [n for n in b["labels"] if n not in a["labels"]]
    missing = [n for n in a["labels"] if n not in b["labels"]]
    parts = ([f"only in {b['name']}: {', '.join(extra)}"] if extra else []) + \
        ([f"only in {a['name']}: {', '.join(missing)}"] if missing else [])
    detail = "; ".join(parts) if parts else "the same labels in another order"
    return f"its label table differs from the one of {a['name']} ({detail})"


def _output_crs(maps: list[dict[str, Any]]) -> tuple[str, list[str]]:
    """The automatic output CRS and the warnings about it."""
    crss = [CRS.from_user_input(m["crs"]) for m in maps]
    if all(c == crss[0] for c in crss[1:]):
        return maps[0]["crs"], []
    lonlat = [_to_lonlat(m["objects_"]) for m in maps]
    target = _auto_crs(lonlat)
    names = ", ".join(f"{m['name']} ({m['crs']})" for m in maps)
    return target, [f"maps in different CRSs ({names}) reprojected to {target}; pass --crs to choose"]


def _deduplicated(maps: list[dict[str, Any]], target: str, quantum: float, say: Any
                  ) -> tuple[list[Objects], list[int], int]:
    """Each input's objects in ``target``, less those an earlier input holds; the counts kept and dropped."""
    parts: list[Objects] = []
    kept_counts = []
    keys = np.zeros((0, 3))  # (qx, qy, label * _LABEL_GAP) of the objects kept so far
    exact = True  # whether every map so far was stored in the target CRS
    target_crs = CRS.from_user_input(target)
    dropped = 0
    for m in maps:
        objects: Objects = m["objects_"]
        moved = CRS.from_user_input(objects.crs) != target_crs
        if moved:
            objects = _reprojected(objects, target)
        exact = exact and not moved
        mine = np.column_stack([np.rint(objects.x / quantum), np.rint(objects.y / quantum),
                                objects.label.astype(np.float64) * _LABEL_GAP])
        if len(keys) and len(objects):
            # Chebyshev distance in quanta: 0 is the same stored position; 1 allows a reprojected map's shift.
            reach = 0.5 if exact else 1.5
            distance, _ = cKDTree(keys).query(mine, k=1, p=np.inf, distance_upper_bound=reach)
            new = ~np.isfinite(distance)
        else:
            new = np.ones(len(objects), bool)
        dropped += int((~new).sum())
        parts.append(objects.take(new))
        kept_counts.append(int(new.sum()))
        keys = np.concatenate([keys, mine[new]])
        say(f"  {m['name']}: {int(new.sum()):,} of {len(objects):,} objects kept, {int((~new).sum()):,} held already")
    return parts, kept_counts, dropped


# Label codes are spread this far apart (in quanta) in the search keys, so that only one label matches.
_LABEL_GAP = 16.0


def _reprojected(objects: Objects, target: str) -> Objects:
    """Objects moved into ``target``; those without a position there dropped."""
    x, y = Transformer.from_crs(objects.crs, target, always_xy=True).transform(objects.x, objects.y)
    x, y = np.asarray(x, float), np.asarray(y, float)
    finite = np.isfinite(x) & np.isfinite(y)
    return Objects(x, y, objects.label, objects.area, objects.labels, target, objects.elevation).take(finite)


def content_digest(path: str | Path) -> str:
    """SHA-256 of a map file as it would be without its creation time: equal for equal builds.

    Two builds of the same sources with the same options give the same digest (the header's
    ``created`` time is left out; everything else, header and pages, counts).
    """
    data = Path(path).read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    header = json.loads(zlib.decompress(data[16:16 + length], -15))
    header.pop("created", None)
    h = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
    h.update(data[20 + length:])
    return h.hexdigest()
