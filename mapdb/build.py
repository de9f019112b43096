"""Build a map file from sources: read, label, reproject, clip, write."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS, Transformer
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info

from .errors import EmptyMapError, SourceError
from .labels import load_label_table
from .objects import Objects, concat
from .sources import read_source, source_kind
from .store import write_map

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
    return Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(objects.x, objects.y)


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
        Keep only objects whose centroid falls inside.
    quantum : float
        Stored resolution in metres.

    Returns
    -------
    dict
        ``{"count": n, "labels": {name: count}, "crs": ..., "output": ...}``.

    Raises
    ------
    EmptyMapError
        If no object survives (for example a bbox over empty ground).
    """
    if not sources:
        raise SourceError("no sources given")
    for path in sources:  # fail on a bad name before spending time on the others
        source_kind(path)
    target = None if crs == "auto" else _projected_crs(crs)
    table = load_label_table(labels)
    say = progress or (lambda message: None)
    parts, described = [], []
    for path in sources:
        path = Path(path)
        say(f"reading {path} ...")
        objects = read_source(path, table, bbox=bbox, raster_classes=raster_classes, min_area_m2=min_area_m2,
                              label_column=label_column, layer_crs=layer_crs, progress=progress)
        say(f"  {len(objects)} objects from {path.name}")
        parts.append(objects)
        described.append({"name": path.name, "kind": source_kind(path), "size": path.stat().st_size,
                          "sha256": _sha256(path), "objects": len(objects)})

    lonlat = [_to_lonlat(p) if len(p) else (np.zeros(0), np.zeros(0)) for p in parts]
    if bbox is not None:
        minlon, minlat, maxlon, maxlat = bbox
        keep = [(lon >= minlon) & (lon <= maxlon) & (lat >= minlat) & (lat <= maxlat) for lon, lat in lonlat]
        parts = [p.take(k) for p, k in zip(parts, keep, strict=True)]
        lonlat = [(lon[k], lat[k]) for (lon, lat), k in zip(lonlat, keep, strict=True)]
    total = sum(len(p) for p in parts)
    names = ", ".join(str(s) for s in sources)
    if total == 0:
        where = f" inside bbox {','.join(map(str, bbox))}" if bbox else ""
        raise EmptyMapError(f"{names}: no labelled objects{where}")

    if crs == "auto":
        all_lon = np.concatenate([lon for lon, _ in lonlat])
        all_lat = np.concatenate([lat for _, lat in lonlat])
        target = utm_crs_for(float(np.median(all_lon)), float(np.median(all_lat)))
    projected = []
    to_target = Transformer.from_crs("EPSG:4326", target, always_xy=True)
    for p, (lon, lat) in zip(parts, lonlat, strict=True):
        x, y = to_target.transform(lon, lat)
        projected.append(Objects(x, y, p.label, p.area, p.labels, target))
    merged = concat(projected, labels=table.labels)
    finite = np.isfinite(merged.x) & np.isfinite(merged.y)
    merged = merged.take(finite)
    if len(merged) == 0:
        raise EmptyMapError(f"{names}: no object projects into {target}")

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
    write_map(output, merged, quantum=quantum, metadata=metadata)
    return {"output": str(output), "crs": target, "count": len(merged), "labels": merged.counts()}
