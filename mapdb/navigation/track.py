"""A navigated track: the per-frame record, its JSON and GeoJSON forms, and the picture.

One :class:`TrackRecord` per frame (``mapdb navigate`` writes its :meth:`TrackRecord.to_json` as one line)::

    {"id": "frame-000123", "time_s": 12.3, "status": "fix",
     "x": ..., "y": ..., "lon": ..., "lat": ..., "crs": "EPSG:32631",
     "velocity_mps": [east, north], "speed_mps": 20.1, "heading_deg": 90.2,
     "cov_m2": [[xx, xy], [xy, yy]], "sigma_m": 0.31,          # the largest axis of the position covariance
     "fix": {"status": "used", "x": ..., "y": ..., "score": 23.1, "inlier_probability": 1.0, ...},
     "fix_frames": [11.9, 12.1, 12.3],                      # the times of the frames whose objects the fix used
     "velocity": {"status": "used", "velocity_mps": [...], "sigma_mps": 3.1, "bias": [-0.012, 0.001],
                  "inliers": 14},                     # velocity_mps corrected by (1 + bias): mapdb.navigation.bias
     "prior_radius_m": 10.0, "notes": [...],
     "time_ms": {"total": 9.1, "query": 5.2, "velocity": 2.3, "filter": 1.2},
     "altitude": {"baro_m": 212.4, "ground_m": 92.1, "above_ground_m": 120.3, "sigma_m": 0.6, "used": true},
                                                                     # a frame with baro_altitude_m only
     "map_update": {"status": "used", "objects": 4, "ess": 1290.5},  # a frame without an applied fix
     "truth": {"x": ..., "y": ..., "error_m": 0.21}}                 # when the frame carries its truth

``status`` is ``"fix"`` (a fix was applied), ``"dead-reckoning"`` (a velocity only), ``"predicting"``
(neither), ``"not initialised"`` (no position yet: the position fields are null) or ``"skipped"`` (the
frame could not be used: no valid time, out of time order, a step outside the bounds of
:mod:`mapdb.navigation.frames`, a line that is not a frame, or its navigation failed; ``notes`` says why,
and the estimate is the previous one).  ``fix.status`` is
``"used"``, ``"initialised"`` (the first fix placed the filter), ``"rejected"`` (an outlier: ``reason``
says how far and how likely), ``"none"`` (``reason``: the matcher's, or why no query was made) or
``"withheld"`` (the flight withholds the map).

``fix_frames`` names the frames whose objects the applied fix used, by their ``time_s``, oldest first: the
frame's own time for its own query, several for a fix from the frame
stitched with the frames before it (:mod:`mapdb.navigation.stitch`: ``fix.stitched`` then gives the
stitched image's ``frames``, ``objects`` and ``carried`` objects, and ``fix.single`` what the frame's own
query gave); null when no fix was applied.  When a stitched query was tried and gave no fix, ``fix.stitched``
says why (``reason``).

``map_update`` is present on a frame of an initialised filter that got no applied fix, when the
map-likelihood update is on (``NavigatorOptions.map_update``, :mod:`mapdb.navigation.map_update`): ``status``
``"used"`` (the particles were weighed by the frame's ``objects``, its whole objects of the map's labels;
``ess``: the effective number of particles after the weighing) or ``"skipped"`` (``reason``: too few whole
objects, no heading or scale yet, a cloud too wide, the map withheld).

:func:`track_geojson` gives the track's frames as RFC 7946 GeoJSON points (lon/lat), :func:`track_line_geojson`
its path as a LineString, each a FeatureCollection of one geometry type (a GIS layer has one: ``ogrinfo``
reads a mixed file as "Unknown (any)"); ``mapdb navigate --geojson TRACK.geojson`` writes the points there and
the line beside it, in ``TRACK_line.geojson`` (:func:`line_path`).  :func:`plot_track` draws the track.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..outputs import json_safe

__all__ = ["TrackRecord", "line_path", "plot_track", "track_geojson", "track_line_geojson"]


def _r(value: float | None, digits: int) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return float(round(value, digits))


@dataclass
class TrackRecord:
    """What the navigator knows after one frame (module docs)."""

    id: Any
    time_s: float | None
    status: str
    x: float | None = None
    y: float | None = None
    lon: float | None = None
    lat: float | None = None
    crs: str | None = None
    velocity: complex | None = None
    heading_deg: float | None = None
    cov: np.ndarray | None = None
    fix: dict[str, Any] = field(default_factory=dict)
    fix_frames: list[float] | None = None
    velocity_measurement: dict[str, Any] = field(default_factory=dict)
    prior_radius_m: float | None = None
    notes: list[str] = field(default_factory=list)
    time_ms: dict[str, float] = field(default_factory=dict)
    truth: dict[str, Any] | None = None
    altitude: dict[str, Any] | None = None  # from the barometer (mapdb.navigation.terrain), when the frame has one
    map_update: dict[str, Any] | None = None  # the map-likelihood update (mapdb.navigation.map_update), if tried

    @property
    def placed(self) -> bool:
        """Whether the record has a position."""
        return self.x is not None and self.y is not None

    @property
    def sigma_m(self) -> float | None:
        """Square root of the position covariance's largest eigenvalue."""
        if self.cov is None:
            return None
        return float(math.sqrt(max(float(np.linalg.eigvalsh(self.cov)[-1]), 0.0)))

    def to_json(self) -> dict[str, Any]:
        """The JSON object ``mapdb navigate`` writes (strict: no NaN or infinity)."""
        v = self.velocity
        record: dict[str, Any] = {
            "id": self.id, "time_s": self.time_s, "status": self.status,
            "x": _r(self.x, 3), "y": _r(self.y, 3), "lon": _r(self.lon, 8), "lat": _r(self.lat, 8), "crs": self.crs,
            "velocity_mps": None if v is None else [_r(v.real, 3), _r(v.imag, 3)],
            "speed_mps": None if v is None else _r(abs(v), 3),
            "heading_deg": _r(self.heading_deg, 3),
            "cov_m2": None if self.cov is None else [[_r(float(c), 4) for c in row] for row in self.cov],
            "sigma_m": _r(self.sigma_m, 3) if self.sigma_m is not None else None,
            "fix": self.fix, "fix_frames": self.fix_frames, "velocity": self.velocity_measurement,
            "prior_radius_m": _r(self.prior_radius_m, 2),
        }
        if self.notes:
            record["notes"] = self.notes
        record["time_ms"] = {k: _r(t, 3) for k, t in self.time_ms.items()}
        if self.altitude is not None:
            record["altitude"] = self.altitude
        if self.map_update is not None:
            record["map_update"] = self.map_update
        if self.truth is not None:
            record["truth"] = self.truth
        return json_safe(record)


def _placed(records: Sequence[TrackRecord]) -> list[TrackRecord]:
    return [r for r in records if r.placed and r.lon is not None and r.lat is not None]


def line_path(path: str | Path) -> str:
    """Where the track's line goes beside its points: ``TRACK.geojson`` -> ``TRACK_line.geojson``.

    Examples
    --------
    >>> line_path("out/track.geojson"), line_path("track")
    ('out/track_line.geojson', 'track_line.geojson')
    """
    p = Path(path)
    return str(p.with_name(f"{p.stem}_line{p.suffix or '.geojson'}"))


def track_line_geojson(records: Sequence[TrackRecord]) -> dict[str, Any]:
    """The estimated path as an RFC 7946 FeatureCollection in lon/lat: one LineString through the placed frames
    (no feature with fewer than two)."""
    placed = _placed(records)
    features: list[dict[str, Any]] = []
    if len(placed) >= 2:
        features.append({"type": "Feature", "properties": {"track": "estimated", "frames": len(placed)},
                         "geometry": {"type": "LineString",
                                      "coordinates": [[r.lon, r.lat] for r in placed]}})
    return json_safe({"type": "FeatureCollection", "features": features})


def track_geojson(records: Sequence[TrackRecord]) -> dict[str, Any]:
    """The track's frames as an RFC 7946 FeatureCollection in lon/lat: each placed frame a Point with its time,
    status, 1-sigma and fix status (the path is :func:`track_line_geojson`)."""
    features: list[dict[str, Any]] = []
    for r in _placed(records):
        properties = {"id": r.id, "time_s": r.time_s, "status": r.status, "sigma_m": _r(r.sigma_m, 3),
                      "fix": r.fix.get("status"), "heading_deg": _r(r.heading_deg, 2)}
        features.append({"type": "Feature", "properties": properties,
                         "geometry": {"type": "Point", "coordinates": [r.lon, r.lat]}})
    return json_safe({"type": "FeatureCollection", "features": features})


# ------------------------------------------------------------------------------------------ picture


def _scale_bar(ax: Any, width_m: float) -> None:
    """A scale bar of a round length, about a fifth of the view, at the lower left."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar  # type: ignore[import-untyped]

    target = width_m / 5.0
    step = 10.0 ** math.floor(math.log10(max(target, 1e-9)))
    length = max(m * step for m in (1, 2, 5) if m * step <= target) if target >= step else step
    label = f"{length / 1000:g} km" if length >= 1000 else f"{length:g} m"
    ax.add_artist(AnchoredSizeBar(ax.transData, length, label, "lower left", pad=0.6, sep=4, frameon=True,
                                  size_vertical=width_m / 400.0, fontproperties={"size": 8}))


def _series(records: Sequence[TrackRecord]) -> dict[str, np.ndarray]:
    placed = [r for r in records if r.placed]
    truth = [r for r in placed if r.truth is not None]
    return {
        "z": np.array([complex(r.x or 0.0, r.y or 0.0) for r in placed]),
        "t": np.array([r.time_s or 0.0 for r in placed]),
        "sigma": np.array([r.sigma_m or 0.0 for r in placed]),
        "no_fix": np.array([r.status != "fix" for r in placed], bool),
        "truth": np.array([complex(r.truth["x"], r.truth["y"]) for r in truth if r.truth]),
        "truth_t": np.array([r.time_s or 0.0 for r in truth]),
        "error": np.array([r.truth.get("error_m") or 0.0 for r in truth if r.truth]),
        "used": np.array([complex(r.fix["x"], r.fix["y"]) for r in records
                          if r.fix.get("status") in ("used", "initialised") and "x" in r.fix]),
        "rejected": np.array([complex(r.fix["x"], r.fix["y"]) for r in records
                              if r.fix.get("status") == "rejected" and "x" in r.fix]),
    }


# Colours: map objects recede (grey), the estimate and what moved it stand out.
_ESTIMATE = "#1f4fd1"
_NO_FIX = "#ff7f0e"
_USED = "#2ca02c"
_REJECTED = "#d62728"


def _draw_track(ax: Any, s: dict[str, np.ndarray], objects: Any) -> None:
    if objects is not None and len(objects):
        ax.scatter(objects.x, objects.y, s=6, color="0.62", linewidths=0, zorder=2,
                   label=f"map objects ({len(objects):,})")
    if s["truth"].size:
        ax.plot(s["truth"].real, s["truth"].imag, color="black", lw=3.0, alpha=0.3, label="true track", zorder=3)
    z, sigma = s["z"], s["sigma"]
    every = max(1, z.size // 300)
    for c, r in zip(z[::every], sigma[::every], strict=True):
        ax.add_patch(_circle(c, 3.0 * r))
    if s["used"].size:  # under the estimate: fixes are many, the estimate is what is read
        ax.scatter(s["used"].real, s["used"].imag, s=4, color=_USED, alpha=0.5, linewidths=0, zorder=4,
                   label=f"fixes used ({s['used'].size})")
    ax.plot(z.real, z.imag, color=_ESTIMATE, lw=0.9, label="estimate (3-sigma discs)", zorder=5)
    if s["no_fix"].any():
        ax.scatter(z[s["no_fix"]].real, z[s["no_fix"]].imag, s=5, color=_NO_FIX, linewidths=0, zorder=6,
                   label=f"frames without a fix ({int(s['no_fix'].sum())})")
    if s["rejected"].size:
        ax.scatter(s["rejected"].real, s["rejected"].imag, s=36, marker="x", color=_REJECTED, zorder=7,
                   label=f"fixes rejected ({s['rejected'].size})")


def _circle(centre: complex, radius: float) -> Any:
    from matplotlib.patches import Circle

    return Circle((centre.real, centre.imag), radius, color=_ESTIMATE, alpha=0.15, lw=0, zorder=3)


def _draw_errors(ax: Any, s: dict[str, np.ndarray]) -> None:
    from matplotlib.ticker import FuncFormatter

    floor = 0.01
    if s["no_fix"].any():
        ax.fill_between(s["t"], floor, 1e6, where=s["no_fix"], color=_NO_FIX, alpha=0.15, lw=0, step="mid",
                        label="no fix")
    ax.plot(s["t"], np.maximum(3.0 * s["sigma"], floor), color=_ESTIMATE, lw=0.8, label="3-sigma (stated)")
    top = float(np.max(3.0 * s["sigma"])) if s["sigma"].size else 1.0
    if s["error"].size:
        ax.plot(s["truth_t"], np.maximum(s["error"], floor), color="black", lw=0.8, label="error against the truth")
        rms = math.sqrt(float(np.mean(s["error"] ** 2)))
        top = max(top, float(np.max(s["error"])))
        ax.set_title(f"error: RMS {rms:.2f} m, max {float(np.max(s['error'])):.2f} m", fontsize=9)
    ax.set_yscale("log")
    ax.set_ylim(floor, max(2.0 * top, 1.0))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.set_xlabel("time (s)", fontsize=9)
    ax.set_ylabel("metres", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.25)
    ax.legend(fontsize=7, loc="upper right", ncol=3)


def plot_track(records: Sequence[TrackRecord], map: Any, path: str | Path, *, title: str | None = None) -> None:
    """Draw a track over its map: map objects, the true track (when known), the estimate with its 3-sigma
    discs, fixes used and rejected; below, the stated 3-sigma and the true error against time.  Axes in
    metres of the map's CRS (named), with a scale bar."""
    from ..evaluation.drawing import metre_axes, pyplot, save_figure, widened

    s = _series(records)
    plt = pyplot()
    fig, (ax, ax_err) = plt.subplots(2, 1, figsize=(8.0, 9.5), gridspec_kw={"height_ratios": [3.2, 1]})
    points = np.concatenate([s["z"], s["truth"]]) if s["z"].size or s["truth"].size else np.zeros(1, complex)
    pad = 0.08 * max(float(np.ptp(points.real)), float(np.ptp(points.imag)), 200.0)
    box = (float(points.real.min() - pad), float(points.imag.min() - pad),
           float(points.real.max() + pad), float(points.imag.max() + pad))
    view = widened(ax, box)  # the view's shape made the axes' shape: equal scale that fills them
    _draw_track(ax, s, map.query_bbox(*view) if map is not None else None)
    ax.set_xlim(view[0], view[2])
    ax.set_ylim(view[1], view[3])
    ax.set_aspect("equal", adjustable="box")
    metre_axes(ax, getattr(map, "crs", None))
    _scale_bar(ax, box[2] - box[0])
    ax.legend(fontsize=7, loc="upper right", markerscale=1.5, ncol=2)
    ax.set_title(title or f"navigated track: {len(records)} frames", fontsize=10)
    _draw_errors(ax_err, s)
    fig.tight_layout()
    save_figure(fig, path)
