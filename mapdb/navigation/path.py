"""A flight's ground track: waypoints joined by straight legs and circular turns.

Positions are complex numbers ``x + iy`` in the map's projected metres (x east, y north).  A polyline of
waypoints becomes a smooth path by replacing each corner with the arc of a circle tangent to both legs
(radius ``turn_radius_m``, smaller where the legs are too short for it), so that an aircraft flying it at
constant speed has a continuous heading and a bank angle that only changes at the ends of a turn.

Waypoints come from a GeoJSON LineString (:func:`read_linestring`, lon/lat as RFC 7946 says) or from a
lawn-mower survey pattern placed over the densest part of a map (:func:`survey_pattern`).

Examples
--------
>>> p = FlightPath.from_waypoints(np.array([0, 100, 100 + 100j]), turn_radius_m=10.0)
>>> round(p.length, 3)  # two legs of 100 m, the corner cut by a quarter circle of radius 10
195.708
>>> z, tangent, curvature = p.at(np.array([0.0, p.length]))
>>> np.round(z, 6).tolist(), np.round(tangent, 6).tolist()
([0j, (100+100j)], [(1+0j), 1j])
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._scipy import cKDTree
from ..errors import SourceError, reading
from ..objects import Objects

__all__ = ["FlightPath", "heading_deg", "read_linestring", "survey_pattern"]

# Corners turning by less than this (radians) are flown straight through.
_STRAIGHT = 1e-9
# Grid cell (metres) of the density map that places a survey pattern; the leg lengths and orientations tried.
_DENSITY_CELL_M = 50.0
_LEGS_M = (400.0, 600.0, 1000.0, 1500.0)
_PATTERN_ANGLES_DEG = tuple(range(0, 180, 15))


@dataclass(frozen=True)
class _Piece:
    """A straight leg (``curvature == 0``) or a circular arc, from ``start`` heading along ``direction``."""

    start: complex
    direction: complex  # unit tangent at the start
    length: float
    curvature: float  # signed 1/R: positive turns left (counter-clockwise)

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.curvature == 0.0:
            return self.start + self.direction * s, np.full(s.shape, self.direction)
        turn = np.exp(1j * self.curvature * s)
        centre = self.start + 1j * self.direction / self.curvature
        return centre + (self.start - centre) * turn, self.direction * turn


class FlightPath:
    """A smooth ground track: legs and turns, evaluated by distance flown (:meth:`at`)."""

    def __init__(self, pieces: list[_Piece]) -> None:
        if not pieces:
            raise ValueError("a flight path needs at least two distinct waypoints")
        self.pieces = pieces
        self.starts = np.cumsum([0.0] + [p.length for p in pieces[:-1]])
        self.length = float(self.starts[-1] + pieces[-1].length)

    @classmethod
    def from_waypoints(cls, waypoints: np.ndarray, turn_radius_m: float = 75.0) -> FlightPath:
        """Legs between the waypoints (complex, map metres), each corner rounded by an arc.

        The arc's radius is ``turn_radius_m`` unless the legs beside the corner are too short, in which
        case it is as large as half the shorter leg allows.  Repeated waypoints are dropped.
        """
        w = np.asarray(waypoints, np.complex128).reshape(-1)
        w = w[np.concatenate([[True], np.abs(np.diff(w)) > 1e-9])] if w.size else w
        if w.size < 2:
            raise ValueError("a flight path needs at least two distinct waypoints")
        legs = np.diff(w)
        lengths, units = np.abs(legs), legs / np.abs(legs)
        cut_in = np.zeros(w.size)  # how much of the leg before each waypoint its corner's arc takes
        pieces: list[_Piece] = []
        arcs: dict[int, _Piece] = {}
        for k in range(1, w.size - 1):
            theta = float(np.angle(units[k] / units[k - 1]))
            if abs(theta) < _STRAIGHT:
                continue
            half = math.tan(abs(theta) / 2.0)
            t = min(turn_radius_m * half, 0.5 * lengths[k - 1], 0.5 * lengths[k])
            radius = t / half
            cut_in[k] = t
            arcs[k] = _Piece(w[k] - units[k - 1] * t, complex(units[k - 1]), radius * abs(theta),
                             math.copysign(1.0 / radius, theta))
        for k in range(w.size - 1):
            start = w[k] + units[k] * cut_in[k]
            length = lengths[k] - cut_in[k] - cut_in[k + 1]
            if length > 1e-9:
                pieces.append(_Piece(complex(start), complex(units[k]), float(length), 0.0))
            if k + 1 in arcs:
                pieces.append(arcs[k + 1])
        return cls(pieces)

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (complex), unit tangent (complex) and signed curvature (1/m, + left) at distances ``s``.

        Distances are clipped to ``[0, length]``.
        """
        s = np.clip(np.asarray(s, np.float64).reshape(-1), 0.0, self.length)
        which = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.pieces) - 1)
        z = np.empty(s.shape, np.complex128)
        tangent = np.empty(s.shape, np.complex128)
        curvature = np.empty(s.shape)
        for j in np.unique(which):
            mine = which == j
            piece = self.pieces[int(j)]
            z[mine], tangent[mine] = piece.at(s[mine] - self.starts[j])
            curvature[mine] = piece.curvature
        return z, tangent, curvature


def heading_deg(tangent: np.ndarray) -> np.ndarray:
    """Heading (degrees clockwise from north, in [0, 360)) of unit tangents ``east + i north``.

    Examples
    --------
    >>> heading_deg(np.array([1j, 1, -1j])).tolist()
    [0.0, 90.0, 180.0]
    """
    return np.mod(90.0 - np.degrees(np.angle(tangent)), 360.0)


def survey_pattern(objects: Objects, length_m: float, spacing_m: float = 150.0, reach_m: float = 60.0) -> np.ndarray:
    """Waypoints of a lawn-mower survey of about ``length_m`` flown over the densest part of a map.

    Parallel legs ``spacing_m`` apart (flown with turns of radius ``spacing_m / 2``).  Each leg length of
    :data:`_LEGS_M` and orientation of :data:`_PATTERN_ANGLES_DEG` places its rectangle where it holds the
    most objects; the pattern kept is the one whose path sees objects most of the way: the mean, over
    points every 25 m along it, of the objects within ``reach_m`` (counted up to 8).
    """
    if not len(objects):
        raise ValueError("the map has no objects to survey")
    z = objects.x + 1j * objects.y
    tree = cKDTree(np.column_stack([objects.x, objects.y]))
    best: tuple[float, np.ndarray] = (-1.0, np.zeros(0, np.complex128))
    for leg in _LEGS_M:
        local = _lawn_mower(length_m, leg, spacing_m)
        height = float(local.imag.max() - local.imag.min())
        for angle in _PATTERN_ANGLES_DEG:
            rot = complex(np.exp(1j * math.radians(angle)))
            _, centre = _densest_window(z / rot, leg, height)
            waypoints = (centre + local) * rot
            samples = _along(waypoints, 25.0)
            seen = tree.query_ball_point(np.column_stack([samples.real, samples.imag]), reach_m, return_length=True)
            score = float(np.mean(np.minimum(seen, 8)))
            if score > best[0]:
                best = (score, waypoints)
    return best[1]


def _lawn_mower(length_m: float, leg_m: float, spacing_m: float) -> np.ndarray:
    """Waypoints of parallel legs along x, centred on the origin, long enough for ``length_m``."""
    turn = math.pi * spacing_m / 2.0
    # The fewest legs whose path is long enough: n legs and n - 1 turns, each turn replacing a spacing.
    n_legs = max(1, math.ceil((length_m + turn - spacing_m) / (leg_m + turn - spacing_m)))
    local = np.array([complex(leg_m * (((k + 1) // 2) % 2), k // 2 * spacing_m) for k in range(2 * n_legs)])
    return local - complex(leg_m, (n_legs - 1) * spacing_m) / 2.0


def _along(waypoints: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` along a polyline."""
    parts = [a + (b - a) * np.arange(0.0, 1.0, step_m / max(abs(b - a), step_m))
             for a, b in zip(waypoints[:-1], waypoints[1:], strict=True)]
    return np.concatenate(parts) if parts else waypoints


def _densest_window(z: np.ndarray, width: float, height: float) -> tuple[int, complex]:
    """The most objects a ``width`` x ``height`` box (axis-aligned) holds, and its centre."""
    c = _DENSITY_CELL_M
    x0, y0 = float(z.real.min()), float(z.imag.min())
    ix = ((z.real - x0) // c).astype(np.int64)
    iy = ((z.imag - y0) // c).astype(np.int64)
    grid = np.zeros((int(ix.max()) + 2, int(iy.max()) + 2))
    np.add.at(grid, (ix, iy), 1.0)
    table = np.zeros((grid.shape[0] + 1, grid.shape[1] + 1))
    table[1:, 1:] = grid.cumsum(0).cumsum(1)
    kx = max(1, min(int(round(width / c)), grid.shape[0]))
    ky = max(1, min(int(round(height / c)), grid.shape[1]))
    sums = table[kx:, ky:] - table[:-kx, ky:] - table[kx:, :-ky] + table[:-kx, :-ky]
    i, j = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(sums[i, j]), complex(x0 + (i + kx / 2.0) * c, y0 + (j + ky / 2.0) * c)


def read_linestring(path: str | Path, crs: str | None) -> np.ndarray:
    """Waypoints (complex, map metres) of the LineString in a GeoJSON file (lon/lat, RFC 7946).

    The file may hold a geometry, a Feature or a FeatureCollection; the first LineString is used.

    Raises
    ------
    MapdbIOError
        If the file cannot be read.
    SourceError
        If it is not GeoJSON, holds no LineString, or its coordinates are not lon/lat.
    """
    name = str(path)
    with reading(name, "GeoJSON file"):
        text = Path(path).read_bytes()
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError):
        raise SourceError(f"{name}: not JSON (a GeoJSON LineString was expected)") from None
    coords = _first_linestring(doc)
    if coords is None:
        raise SourceError(f"{name}: no LineString in this GeoJSON")
    try:
        lonlat = np.array([[float(c[0]), float(c[1])] for c in coords])
    except (TypeError, ValueError, IndexError):
        raise SourceError(f"{name}: LineString coordinates must be [lon, lat] numbers") from None
    if lonlat.shape[0] < 2 or not np.all(np.isfinite(lonlat)) or np.any(np.abs(lonlat[:, 0]) > 180) \
            or np.any(np.abs(lonlat[:, 1]) > 90):
        raise SourceError(f"{name}: a LineString needs at least two [lon, lat] positions within range")
    if not crs:
        raise SourceError(f"{name}: the map has no CRS to place lon/lat waypoints in")
    from ..localize.lonlat import transformer

    x, y = transformer("EPSG:4326", crs).transform(lonlat[:, 0], lonlat[:, 1])
    return np.asarray(x) + 1j * np.asarray(y)


def _first_linestring(doc: Any) -> list | None:
    if not isinstance(doc, dict):
        return None
    kind = doc.get("type")
    if kind == "LineString":
        coords = doc.get("coordinates")
        return coords if isinstance(coords, list) else None
    if kind == "Feature":
        return _first_linestring(doc.get("geometry"))
    if kind == "FeatureCollection" and isinstance(doc.get("features"), list):
        for feature in doc["features"]:
            found = _first_linestring(feature)
            if found is not None:
                return found
    return None
