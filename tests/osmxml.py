"""Tiny OSM documents for tests, laid out in metres and written as OSM XML."""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
from pyproj import Transformer

# Test geometry is laid out in metres around this point, then written as lon/lat.
LON0, LAT0 = 7.42, 43.73
_TO_LONLAT = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
_TO_UTM = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True)
X0, Y0 = _TO_UTM.transform(LON0, LAT0)


def lonlat(x: float, y: float) -> tuple[float, float]:
    """Metres east/north of (LON0, LAT0) -> lon, lat."""
    return _TO_LONLAT.transform(X0 + x, Y0 + y)


def metres(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    x, y = _TO_UTM.transform(lon, lat)
    return np.column_stack([np.asarray(x) - X0, np.asarray(y) - Y0])


class OsmXml:
    """A tiny OSM document built node by node: ``node`` returns the new id."""

    def __init__(self) -> None:
        self.nodes: list[str] = []
        self.ways: list[str] = []
        self.relations: list[str] = []
        self.next_id = 1

    def _id(self) -> int:
        self.next_id += 1
        return self.next_id - 1

    @staticmethod
    def _tags(tags: dict[str, str] | None) -> str:
        return "".join(f"<tag k={quoteattr(k)} v={quoteattr(v)}/>" for k, v in (tags or {}).items())

    def node(self, x: float, y: float, tags: dict[str, str] | None = None, lon_lat: bool = False) -> int:
        lon, lat = (x, y) if lon_lat else lonlat(x, y)
        nid = self._id()
        self.nodes.append(f'<node id="{nid}" version="1" lat="{lat:.9f}" lon="{lon:.9f}">{self._tags(tags)}</node>')
        return nid

    def way(self, refs: list[int], tags: dict[str, str] | None = None) -> int:
        wid = self._id()
        nds = "".join(f'<nd ref="{r}"/>' for r in refs)
        self.ways.append(f'<way id="{wid}" version="1">{nds}{self._tags(tags)}</way>')
        return wid

    def ring(self, corners: list[tuple[float, float]], tags: dict[str, str] | None = None) -> int:
        """A closed way through these corners (metres)."""
        refs = [self.node(x, y) for x, y in corners]
        return self.way(refs + refs[:1], tags)

    def relation(self, members: list[tuple[str, int, str]], tags: dict[str, str]) -> int:
        rid = self._id()
        body = "".join(f'<member type="{t}" ref="{r}" role="{role}"/>' for t, r, role in members)
        self.relations.append(f'<relation id="{rid}" version="1">{body}{self._tags(tags)}</relation>')
        return rid

    def text(self) -> str:
        return "\n".join(['<?xml version="1.0" encoding="UTF-8"?>', '<osm version="0.6" generator="test">',
                          *self.nodes, *self.ways, *self.relations, "</osm>"])

    def write(self, path: Path) -> Path:
        path.write_text(self.text(), encoding="utf-8")
        return path


def square(cx: float, cy: float, half: float) -> list[tuple[float, float]]:
    return [(cx - half, cy - half), (cx + half, cy - half), (cx + half, cy + half), (cx - half, cy + half)]


def small_town(path: Path) -> Path:
    """Three 12 m buildings in a row and a 40 m park: the smallest extract every command can run on."""
    doc = OsmXml()
    for i in range(3):
        doc.ring(square(40.0 * i, 0.0, 6.0), {"building": "yes"})
    doc.ring(square(0.0, 80.0, 20.0), {"leisure": "park"})
    return doc.write(path)
