"""Build a map file from sources: read, label, reproject, clip, write."""

from __future__ import annotations

import hashlib
import math
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from .errors import EmptyMapError, SourceError
from .geo import bbox_text, central_longitude, check_bbox, in_bbox
from .labels import load_label_table
from .objects import Objects, concat
from .sources import SKIPPED_KINDS, read_source, source_kind
from .store import open_map, write_map

__all__ = ["build_map", "utm_crs_for"]


def utm_crs_for(lon: float, lat: float) -> str:
    """The WGS 84 UTM zone CRS that contains a point, as ``"EPSG:n"``.

    Examples
    --------
    >>> utm_crs_for(7.42, 43.73)   # Monaco
    'EPSG:32632'
    >>> utm_crs_for(-70.0, -33.0)
    'EPSG:32719'
    """
    found = query_utm_crs_info(
        datum_name="WGS 84", area_of_interest=AreaOfInterest(lon, lat, lon, lat)
    )
    if not found:
        raise ValueError(f"no UTM zone for lon {lon}, lat {lat}")
    # Several zones touch on a zone edge; the formula's zone is the conventional choice.
    zone = int((lon + 180) // 6) % 60 + 1
    wanted = f"{326 if lat >= 0 else 327}{zone:02d}"
    codes = [c.code for c in found]
    return f"EPSG:{wanted if wanted in codes else codes[0]}"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _to_lonlat(objects: Objects) -> tuple[np.ndarray, np.ndarray]:
    crs = CRS.from_user_input(objects.crs)
    if crs.equals(CRS.from_epsg(4326), ignore_axis_order=True):
        return objects.x, objects.y
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)
    return np.asarray(lon), np.asarray(lat)


def _check_number(name: str, value: float, low: float, high: float, low_open: bool) -> float:
    """A finite number within [low, high] (or (low, high]), as a SourceError saying which option is wrong."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SourceError(f"{name} {value!r}: not a number") from None
    below = number <= low if low_open else number < low
    if not math.isfinite(number) or below or number > high:
        raise SourceError(f"{name} {value!r}: must be a finite number in {'(' if low_open else '['}{low:g}, {high:g}]")
    return number


def _projected_crs(crs: str) -> str:
    try:
        parsed = CRS.from_user_input(crs)
    except Exception:
        raise SourceError(f"--crs {crs}: not a CRS that pyproj knows") from None
    if not parsed.is_projected:
        raise SourceError(f"--crs {crs}: a map needs a projected CRS in metres")
    return parsed.to_string()


def build_map(
    sources: Sequence[str | Path],
    output: str | Path,
    *,
    labels: str | Path | None = None,
    crs: str = "auto",
    bbox: tuple[float, float, float, float] | None = None,
    quantum: float = 0.1,
    raster_classes: str | None = None,
    min_area_m2: float = 10_000.0,
    label_column: str = "label",
    layer_crs: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Read every source, reproject to one metric CRS, clip and write one map file.

    Parameters
    ----------
    sources : sequence of paths
        OSM extracts, land-cover GeoTIFFs and point/polygon layers, in any mix.
    output : path
        The ``.mapdb`` file; replaced atomically, left untouched on failure.
    labels : path, optional
        A TOML label table read over the defaults (see ``mapdb/data/labels.toml``).
    crs : str
        ``"auto"`` for the UTM zone of the data, or any CRS pyproj accepts.
    bbox : (minlon, minlat, maxlon, maxlat), optional
        Keep only objects whose centroid falls inside.  The box may span the world, touch the poles
        or cross the antimeridian (``minlon > maxlon``, as in GeoJSON).
    quantum : float
        Stored resolution in metres, in (0, 1000].
    min_area_m2 : float
        Smallest land-cover patch kept, finite and >= 0.

    Returns
    -------
    dict
        ``{"count": n, "labels": {name: count}, "crs": ..., "output": ..., "skipped": {kind: n}}``;
        ``skipped`` counts what the readers skipped or repaired instead of failing (kinds in
        :data:`mapdb.sources.SKIPPED_KINDS`), also recorded per source in the map's metadata.

    Raises
    ------
    SourceError
        A bad source, or an argument out of range (``quantum``, ``min_area_m2``, ``bbox``).
    EmptyMapError
        If no object survives (for example a bbox over empty ground).
    """
    if not sources:
        raise SourceError("no sources given")
    quantum = _check_number("quantum", quantum, 0.0, 1000.0, low_open=True)
    min_area_m2 = _check_number("min_area_m2", min_area_m2, 0.0, math.inf, low_open=False)
    if bbox is not None:
        try:
            bbox = check_bbox(bbox)
        except ValueError as exc:
            raise SourceError(f"bbox {bbox!r}: {exc}") from None
    for path in sources:  # fail on a bad name before spending time on the others
        source_kind(path)
    target = None if crs == "auto" else _projected_crs(crs)
    table = load_label_table(labels)
    say = progress or (lambda message: None)
    parts, described, skipped = [], [], []
    for path in sources:
        path = Path(path)
        say(f"reading {path} ...")
        counts: Counter[str] = Counter()
        objects = read_source(path, table, bbox=bbox, raster_classes=raster_classes, min_area_m2=min_area_m2,
                              label_column=label_column, layer_crs=layer_crs, progress=progress, counts=counts)
        if len(objects):
            # Every source, whatever its CRS, must give places on Earth: a point whose lon/lat is not
            # finite or out of range (a projected layer outside its projection) is dropped and counted.
            lon, lat = _to_lonlat(objects)
            valid = np.isfinite(lon) & np.isfinite(lat) & (np.abs(lon) <= 180) & (np.abs(lat) <= 90)
            counts["invalid_coordinates"] += int((~valid).sum())
            objects = objects.take(valid)
        say(f"  {len(objects)} objects from {path.name}")
        parts.append(objects)
        skipped.append(counts)
        described.append({"name": path.name, "kind": source_kind(path), "size": path.stat().st_size,
                          "sha256": _sha256(path), "objects": len(objects)})

    lonlat = [_to_lonlat(p) if len(p) else (np.zeros(0), np.zeros(0)) for p in parts]
    if bbox is not None:
        keep = [in_bbox(bbox, lon, lat) for lon, lat in lonlat]
        parts = [p.take(k) for p, k in zip(parts, keep, strict=True)]
        lonlat = [(lon[k], lat[k]) for (lon, lat), k in zip(lonlat, keep, strict=True)]
    total = sum(len(p) for p in parts)
    names = ", ".join(str(s) for s in sources)
    if total == 0:
        where = f" inside bbox {bbox_text(bbox)}" if bbox else ""
        raise EmptyMapError(f"{names}: no labelled objects{where}")

    if crs == "auto":
        all_lon = np.concatenate([lon for lon, _ in lonlat])
        all_lat = np.concatenate([lat for _, lat in lonlat])
        # The median longitude taken around the globe's widest empty gap: data on both sides of the
        # antimeridian (Fiji) get the zone at 180, not the one at 0.
        target = utm_crs_for(central_longitude(all_lon), float(np.median(all_lat)))
    projected = []
    to_target = Transformer.from_crs("EPSG:4326", target, always_xy=True)
    for p, (lon, lat), counts in zip(parts, lonlat, skipped, strict=True):
        x, y = to_target.transform(lon, lat)
        finite = np.isfinite(x) & np.isfinite(y)
        counts["outside_crs"] += int((~finite).sum())
        projected.append(Objects(x, y, p.label, p.area, p.labels, target).take(finite))
    merged = concat(projected, labels=table.labels)
    if len(merged) == 0:
        raise EmptyMapError(f"{names}: no object projects into {target}")
    for entry, counts in zip(described, skipped, strict=True):
        entry["skipped"] = {kind: n for kind, n in sorted(counts.items()) if n}
    totals = sum(skipped, Counter())
    for kind, n in sorted(totals.items()):
        if n:
            say(f"  {n:,} {SKIPPED_KINDS.get(kind, kind)}")

    say(f"writing {len(merged)} objects to {output} ({target}, quantum {quantum} m) ...")
    metadata = {
        "sources": described,
        "build": {
            "crs": crs, "bbox": list(bbox) if bbox else None, "quantum": quantum,
            "labels_file": Path(labels).name if labels else None,
            "labels_sha256": _sha256(Path(labels)) if labels else None, "raster_classes": raster_classes,
            "min_area_m2": min_area_m2, "label_column": label_column, "layer_crs": layer_crs,
        },
    }
    written = write_map(output, merged, quantum=quantum, metadata=metadata)
    if written < len(merged):
        totals["merged_duplicates"] += len(merged) - written
    with open_map(output) as m:
        labels = m.label_counts  # after the writer merged same-label duplicates
    return {"output": str(output), "crs": target, "count": written, "labels": labels,
            "skipped": {kind: n for kind, n in sorted(totals.items()) if n}}
