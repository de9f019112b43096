"""What an analysis writes: a GeoTIFF of every measure, a GeoPackage of the cells, ``summary.json``, all in
an output folder that appears complete or not at all.

:func:`output_folder` gives a hidden temporary folder beside the output folder, renamed to it only when
everything is written (an existing one is replaced only when asked, and never when an input lies in it).
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MapdbIOError, OutputClashError
from ..outputs import pid_alive, refuse_existing
from .adaptive import DECISION_LEVEL
from .cputime import CpuPhases
from .grid import Grid
from .measures import MIN_VISIBLE, SampleConfig
from .run import Analysis

__all__ = ["NODATA", "SUCCESS_LEVEL", "cell_totals", "comparison", "outcome", "output_folder", "parameters", "summary",
           "write_cells", "write_geotiff", "write_outputs", "write_summary", "ADAPTIVE_RULE"]

# The GeoTIFF's no-data value (error and ambiguity where there is none); NULL in the GeoPackage.
NODATA = -9999.0
# The success rate a cell must reach to count as "works here" in the summary.
SUCCESS_LEVEL = DECISION_LEVEL
# How the adaptive cells are chosen (mapdb.analysis.adaptive), as summary.json records it.
ADAPTIVE_RULE = ("cells with both absolute indices even (a coarse lattice) are measured first; a cell between "
                 "them draws its images' poses and views (L of N localizable) and is inferred, no image "
                 "localized, unless a neighbour had a false fix, its neighbours' 95 % intervals of the success "
                 "probability p of a localizable image (k of m) do not overlap or none has one, or the interval "
                 "(L / N) (p -+ 1.96 sqrt(p (1 - p) / L)) over their hull is wider than stop_width or holds 0.95 "
                 "without being above it; inferred cells (inferred 1): success (L / N) times the neighbours' mean "
                 "k / m, false_fixes 0, error_m and ambiguity the neighbours' means")
# Most ambiguous cells listed in the summary.
TOP_AMBIGUOUS = 10
# Long folder names are cut in the temporary names beside them (a name is at most 255 bytes).
_NAME_KEEP = 180


# ------------------------------------------------------------------------------------------ the folder


@contextmanager
def output_folder(outdir: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None], *,
                  overwrite: bool = False, parents: bool = False) -> Iterator[Path]:
    """A temporary folder beside ``outdir``, renamed to it when the block ends without an error (removed
    otherwise).

    Refused before any work: an existing ``outdir`` without ``overwrite``, one that is not a directory, an
    input that is ``outdir`` or lies inside it (replacing the folder would delete it), and a missing parent
    directory without ``parents``.
    """
    target = Path(outdir)
    refuse_existing(target, overwrite, "output folder")
    if target.exists() and not target.is_dir():
        raise MapdbIOError(f"{target}: exists and is not a directory")
    real = os.path.realpath(target)
    for given in inputs:
        if given is not None and os.path.commonpath([real, os.path.realpath(given)]) == real:
            raise OutputClashError(f"{target}: holds input {given}; choose another output folder")
    parent = target.absolute().parent
    if not parent.is_dir():
        if not parents:
            raise MapdbIOError(f"{target}: directory {parent} does not exist")
        parent.mkdir(parents=True, exist_ok=True)
    _remove_stale(target)
    tmp = parent / f".{target.name[:_NAME_KEEP]}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    try:
        tmp.mkdir()
    except OSError as exc:
        raise MapdbIOError(f"{target}: cannot create a folder beside it ({exc.strerror or exc})") from None
    try:
        yield tmp
        _replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _remove_stale(target: Path) -> None:
    """Remove the temporary folders of ``target`` left by runs that were killed (their process is gone)."""
    pattern = re.compile(rf"\.{re.escape(target.name[:_NAME_KEEP])}\.(\d+)\.[0-9a-f]+\.(?:tmp|old)")
    try:
        names = os.listdir(target.absolute().parent)
    except OSError:
        return
    for name in names:
        match = pattern.fullmatch(name)
        if match and not pid_alive(int(match.group(1))):
            shutil.rmtree(target.absolute().parent / name, ignore_errors=True)


def _replace(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` to ``target``, an existing ``target`` moved aside first and removed after."""
    old = None
    if target.exists():
        old = target.parent / f".{target.name[:_NAME_KEEP]}.{os.getpid()}.{secrets.token_hex(4)}.old"
        os.rename(target, old)
    try:
        os.rename(tmp, target)
    except OSError as exc:
        if old is not None:
            os.rename(old, target)
        raise MapdbIOError(f"{target}: cannot write ({exc.strerror or exc})") from None
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


# ------------------------------------------------------------------------------------------ rasters


def _transform(grid: Grid) -> Any:
    """Cell (row 0, column 0) is the north-west one; rows go south."""
    from rasterio.transform import Affine

    x0, _, _, y1 = grid.bounds
    return Affine(grid.cell_m, 0.0, x0, 0.0, -grid.cell_m, y1)


def write_geotiff(path: str | os.PathLike[str], analysis: Analysis) -> None:
    """One float32 band per measure, named by its description, in the map's CRS, nodata :data:`NODATA`."""
    import rasterio
    from rasterio.crs import CRS

    bands = analysis.measures
    grid = analysis.grid
    profile = {"driver": "GTiff", "width": grid.ncols, "height": grid.nrows, "count": len(bands),
               "dtype": "float32", "crs": CRS.from_user_input(grid.crs), "transform": _transform(grid),
               "nodata": NODATA, "compress": "deflate", "predictor": 3, "tiled": grid.ncols >= 256,
               "blockxsize": 256, "blockysize": 256}
    if not profile["tiled"]:
        del profile["blockxsize"], profile["blockysize"]
    with rasterio.open(path, "w", **profile) as dst:
        for k, (name, values) in enumerate(bands.items(), start=1):
            dst.write(np.where(np.isnan(values), NODATA, values).astype(np.float32), k)
            dst.set_band_description(k, name)
            dst.set_band_unit(k, analysis.units(name))  # GDAL's band unit, which QGIS and gdalinfo show
            dst.update_tags(k, units=analysis.units(name), description=analysis.description(name))
        dst.update_tags(**{"mapdb_analysis": json.dumps(parameters(analysis), sort_keys=True)})


# ------------------------------------------------------------------------------------------ cells


def write_cells(path: str | os.PathLike[str], analyses: Sequence[Analysis]) -> None:
    """The cells within an image's reach of a map object, as polygons with every measure (one layer per
    analysis, named after it, ``cells`` for a single one); NULL where a measure has no value."""
    import geopandas
    import shapely

    for analysis in analyses:
        grid = analysis.grid
        rows, cols = np.nonzero(analysis.reached)
        i, j = grid.absolute(rows, cols)
        c = grid.cell_m
        frame = geopandas.GeoDataFrame(
            {"grid_row": rows.astype(np.int32), "grid_col": cols.astype(np.int32),
             **{name: values[rows, cols].astype(np.float64) for name, values in analysis.measures.items()}},
            geometry=shapely.box(i * c, j * c, (i + 1) * c, (j + 1) * c), crs=grid.crs)
        frame.to_file(path, layer=analysis.name or "cells", driver="GPKG", engine="pyogrio")


# ------------------------------------------------------------------------------------------ summary


def parameters(analysis: Analysis) -> dict[str, Any]:
    """What was simulated, as the summary and the GeoTIFF's tags record it."""
    cfg = analysis.config
    return {"cell_m": analysis.grid.cell_m, "altitude_m": cfg.altitude, "fov_deg": cfg.fov_deg,
            "size": f"{cfg.size[0]}x{cfg.size[1]}", "attitude_std_deg": cfg.attitude_std,
            "pixel_std": cfg.pixel_std, "miss_rate": cfg.miss_rate, "spurious_rate": cfg.spurious_rate,
            "label_noise": cfg.label_noise, "labels": list(cfg.labels) if cfg.labels else "all",
            "samples": cfg.samples, "prior_m": cfg.prior, "seed": cfg.seed,
            "fp_threshold_m": cfg.fp_threshold, "heading": "random", "position": "uniform in the cell",
            "method": "fast", "min_visible": MIN_VISIBLE, "ambiguity_separation_m": round(cfg.separation_m, 3),
            **_rule(cfg)}


def _rule(cfg: SampleConfig) -> dict[str, Any]:
    """How many images a cell drew: the sequential rule and its width, or a fixed number (see
    :mod:`mapdb.analysis.measures`)."""
    if not cfg.sequential:
        return {"images_per_cell": f"fixed: {cfg.samples}", "sequential": False,
                "interval": "Wilson score, 95 %", "stop_width": None}
    return {"images_per_cell": f"sequential: at most {cfg.samples}", "sequential": True,
            "interval": "Wilson score, 95 %", "stop_width": round(cfg.stop_width, 4), "adaptive": cfg.adaptive,
            **({"adaptive_rule": ADAPTIVE_RULE} if cfg.adaptive else {}),
            "stop_rule": "every image's pose and view is drawn; of the localizable ones (at least min_visible "
                         "objects in view), a cell localizes at least 2, in order, until the 95 % Wilson "
                         "intervals of its success and false shares, times the localizable share, are each at "
                         "most stop_width wide; cells with fewer than min_visible analysed objects within reach "
                         "are skipped (images 0)"}


def _fraction(mask: np.ndarray, within: np.ndarray) -> float | None:
    n = int(within.sum())
    return None if not n else round(float((mask & within).sum()) / n, 6)


def _lonlat(crs: str, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return np.asarray(lon), np.asarray(lat)


def _most_ambiguous(analysis: Analysis) -> list[dict[str, Any]]:
    """The cells of highest ambiguity among those (not inferred) where at least half the images drawn showed
    enough objects to be localized (a cell whose one lucky image saw four objects says little about its
    pattern), most ambiguous first."""
    amb = analysis.measures["ambiguity"]
    m = analysis.measures
    # An inferred cell's ambiguity is its neighbours': not listed as its own.
    seen = (m["localizable"] >= m["images"] / 2) & (m["images"] > 0) & (m["inferred"] == 0)
    rows, cols = np.nonzero(~np.isnan(amb) & seen)
    if not rows.size:
        return []
    order = np.lexsort((cols, rows, -amb[rows, cols]))[:TOP_AMBIGUOUS]
    rows, cols = rows[order], cols[order]
    x, y = analysis.grid.centres(rows, cols)
    lon, lat = _lonlat(analysis.grid.crs, x, y)
    m = analysis.measures
    return [{"row": int(r), "col": int(c), "x": float(xx), "y": float(yy), "lon": round(float(lo), 6),
             "lat": round(float(la), 6), "ambiguity": round(float(m["ambiguity"][r, c]), 4),
             "success": round(float(m["success"][r, c]), 4), "visible": float(m["visible"][r, c])}
            for r, c, xx, yy, lo, la in zip(rows, cols, x, y, lon, lat, strict=True)]


def outcome(analysis: Analysis) -> dict[str, Any]:
    """The figures a planner reads first: where it works, where it can be fooled, how ambiguous."""
    m = analysis.measures
    everywhere = np.ones(analysis.grid.shape, bool)
    bearing = analysis.counts.objects > 0
    works, fooled = m["success"] >= SUCCESS_LEVEL, m["false_fixes"] > 0
    amb = m["ambiguity"][~np.isnan(m["ambiguity"])]
    inferred = m["inferred"] > 0
    simulated = (analysis.counts.within_reach >= MIN_VISIBLE) & ~inferred
    return {
        "success_at_least_95": {"fraction_of_area": _fraction(works, everywhere),
                                "fraction_of_objects_bearing_area": _fraction(works, bearing)},
        # The sequential rule's interval carried through the classification: the share of the area where
        # success is certainly (low end) and possibly (high end) at least the level (the same for a fixed run).
        "success_at_least_95_within_interval": {
            "low": _fraction(m["success_low"] >= SUCCESS_LEVEL, bearing),
            "high": _fraction(m["success_high"] >= SUCCESS_LEVEL, bearing), "of": "objects-bearing area"},
        "false_above_0": {"fraction_of_area": _fraction(fooled, everywhere),
                          "fraction_of_objects_bearing_area": _fraction(fooled, bearing)},
        "mean_success_objects_bearing_area": None if not bearing.any() else round(float(m["success"][bearing].mean()),
                                                                                 6),
        "ambiguity": {"cells_with_a_value": int(amb.size),
                      "median": None if not amb.size else round(float(np.median(amb)), 4),
                      "cells_at_least_0.5": int((amb >= 0.5).sum())},
        "images_localized": analysis.stats.get("images_localized"),
        "images_localizable": analysis.stats.get("images_localizable"),
        "images_localized_per_simulated_cell": _per_cell(m["simulated"], simulated),
        "success_width": _widths(m["success_high"] - m["success_low"], simulated),
        "cells_inferred": int(inferred.sum()),
        "success_width_inferred": _widths(m["success_high"] - m["success_low"], inferred),
    }


def _per_cell(images: np.ndarray, simulated: np.ndarray) -> float | None:
    return None if not simulated.any() else round(float(images[simulated].mean()), 4)


def _widths(width: np.ndarray, simulated: np.ndarray) -> dict[str, float | None]:
    """The 95 % interval widths of success over the cells images were simulated in."""
    if not simulated.any():
        return {"median": None, "max": None}
    return {"median": round(float(np.median(width[simulated])), 4), "max": round(float(width[simulated].max()), 4)}


def summary(analyses: Sequence[Analysis], cpu: dict[str, Any] | None = None) -> dict[str, Any]:
    """``summary.json``: the area, the map, the outcome, the most ambiguous cells, the parameters, the
    software; with several analyses (scenarios), one comparison table; ``cpu`` (the run's CPU by phase,
    :meth:`mapdb.analysis.cputime.CpuPhases.record`) last, if given."""
    first = analyses[0]
    grid = first.grid
    lon, lat = _lonlat(grid.crs, np.array(grid.bounds[::2]), np.array(grid.bounds[1::2]))
    bearing = first.counts.objects > 0
    doc: dict[str, Any] = {
        "software": first.map_info["software"],
        "map": {k: first.map_info[k] for k in ("path", "crs", "objects", "file_bytes")},
        "area": {"cells": grid.size, "cell_m": grid.cell_m, "km2": round(grid.size * grid.cell_km2, 4),
                 "bounds": list(grid.bounds), "lonlat_bounds": [round(float(v), 6) for v in
                                                                (lon[0], lat[0], lon[1], lat[1])],
                 "objects_bearing_cells": int(bearing.sum()),
                 "objects_bearing_km2": round(float(bearing.sum()) * grid.cell_km2, 4),
                 "objects": int(first.counts.objects.sum()), "map_bytes": round(float(first.counts.bytes.sum()))},
        "measures": {name: {"units": first.units(name), "description": first.description(name)}
                     for name in first.measures},
    }
    runs = [{"name": a.name or "analysis", "parameters": parameters(a), **outcome(a),
             "most_ambiguous": _most_ambiguous(a), "run": a.stats} for a in analyses]
    if len(analyses) == 1:
        doc.update({k: v for k, v in runs[0].items() if k != "name"})
    else:
        doc["scenarios"] = runs
        doc["comparison"] = comparison(analyses)
    if cpu is not None:
        doc["cpu"] = cpu
    return doc


def comparison(analyses: Sequence[Analysis]) -> list[dict[str, Any]]:
    """One row per scenario: what it simulated and how it came out, side by side."""
    rows = []
    for a in analyses:
        o = outcome(a)
        p = parameters(a)
        rows.append({"scenario": a.name, "labels": p["labels"], "altitude_m": p["altitude_m"],
                     "fov_deg": p["fov_deg"], "pixel_std": p["pixel_std"], "prior_m": p["prior_m"],
                     "success_at_least_95_of_objects_bearing_area":
                         o["success_at_least_95"]["fraction_of_objects_bearing_area"],
                     "mean_success_objects_bearing_area": o["mean_success_objects_bearing_area"],
                     "false_above_0_of_area": o["false_above_0"]["fraction_of_area"],
                     "median_ambiguity": o["ambiguity"]["median"],
                     "images_localized": o["images_localized"], "seconds": a.stats.get("seconds")})
    return rows


def write_summary(path: str | os.PathLike[str], analyses: Sequence[Analysis],
                  cpu: dict[str, Any] | None = None) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(summary(analyses, cpu), f, indent=2, allow_nan=False)
        f.write("\n")


# ------------------------------------------------------------------------------------------ everything


def _import_writers() -> None:
    """Import what the writers use (GDAL through rasterio and pyogrio, geopandas, matplotlib): about a second of
    CPU, the same for a cell or a country."""
    import geopandas  # noqa: F401
    import pyogrio  # noqa: F401
    import rasterio  # noqa: F401
    import shapely  # noqa: F401

    from ..evaluation.drawing import pyplot

    pyplot()


def cell_totals(analyses: Sequence[Analysis]) -> tuple[int, int]:
    """The cells of every analysis's grid (each scenario's counted), and of them those images ran in."""
    return (sum(a.grid.size for a in analyses),
            sum(int(a.stats.get("cells_simulated", 0)) for a in analyses))


def _slug(name: str, taken: set[str]) -> str:
    """A file name for a scenario: its name with anything but letters, digits, ``.``, ``_``, ``-`` as ``_``."""
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "scenario"
    slug, k = base, 1
    while slug.lower() in taken:
        k += 1
        slug = f"{base}_{k}"
    taken.add(slug.lower())
    return slug


def write_outputs(folder: str | os.PathLike[str], analyses: Sequence[Analysis],
                  phases: CpuPhases | None = None) -> list[str]:
    """Every output of an analysis (or of its scenarios) into ``folder``; the file names written.

    One analysis: ``analysis.tif``, ``analysis.png``, ``cells.gpkg``, ``summary.json``.  Scenarios: a GeoTIFF
    per scenario (``NAME.tif``), ``cells.gpkg`` with a layer per scenario, ``scenarios.png`` (small
    multiples) and ``summary.json`` with the comparison table.  With ``phases``, the writers' libraries are
    imported first and counted in ``startup`` (a run pays them once, whatever its cells); ``outputs`` closes
    before ``summary.json``, which then records every phase (``cpu``).
    """
    from .pictures import plot_analysis, plot_scenarios

    if phases is not None:
        _import_writers()
        phases.close("startup")

    out = Path(folder)
    if len(analyses) == 1:
        write_geotiff(out / "analysis.tif", analyses[0])
        drawn = time.process_time()
        plot_analysis(out / "analysis.png", analyses[0])
        names = ["analysis.tif", "analysis.png"]
    else:
        taken: set[str] = {"summary", "cells", "scenarios"}
        names = []
        for analysis in analyses:
            name = f"{_slug(analysis.name, taken)}.tif"
            write_geotiff(out / name, analysis)
            names.append(name)
        drawn = time.process_time()
        plot_scenarios(out / "scenarios.png", analyses)
        names.append("scenarios.png")
    drawn = time.process_time() - drawn  # the picture's CPU: a bounded figure, nearly the same for any area
    write_cells(out / "cells.gpkg", analyses)
    cpu = None
    if phases is not None:
        phases.close("outputs")
        phases.picture += drawn
        cpu = phases.record(*cell_totals(analyses))
    write_summary(out / "summary.json", analyses, cpu)
    return [*names, "cells.gpkg", "summary.json"]
