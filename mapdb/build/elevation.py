"""Ground elevation for a build: each projected object sampled from the DEMs given (``mapdb build --dem``).

The builder hands its projected blocks through :class:`ElevationTally`, which samples the DEMs
(:class:`mapdb.sources.dem.Dem`) at each object's position and counts the objects left without an
elevation (outside every DEM, or on a void post).  Before the map is written, :meth:`ElevationTally.check`
refuses a DEM that covers none of the objects (most likely the wrong tile), and :meth:`ElevationTally.warning`
gives the one warning line for a partial cover.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from ..errors import SourceError
from ..objects import Objects
from ..sources.dem import Dem

__all__ = ["ElevationTally"]


class ElevationTally:
    """The DEMs of a build and what sampling them found.

    Parameters
    ----------
    paths : sequence of paths
        The DEM files (checked now, before any source is read: see :class:`~mapdb.sources.dem.Dem`).
    """

    def __init__(self, paths: Sequence[str | Path]) -> None:
        self.dem = Dem(paths)
        self.objects = self.outside = self.nodata = 0

    def sampled(self, blocks: Iterable[Objects]) -> Iterator[Objects]:
        """The blocks (in a projected CRS) with their objects' ground elevation, counted."""
        for block in blocks:
            z, found = self.dem.sample(block.x, block.y, str(block.crs))
            self.objects += len(block)
            self.outside += found["outside"]
            self.nodata += found["nodata"]
            yield block.with_elevation(z)

    def check(self) -> None:
        """Refuse DEMs under none of the objects: the map would hold no elevation at all."""
        if self.objects and self.outside + self.nodata == self.objects:
            names = ", ".join(str(p) for p in self.dem.paths)
            where = "lie outside it" if self.nodata == 0 else f"lie outside it or on its nodata ({self.nodata})"
            raise SourceError(f"{names}: the DEM does not cover the map (all {self.objects} objects {where})")

    def warning(self) -> str | None:
        """One line counting the objects without an elevation, or None when every object has one."""
        if not self.outside and not self.nodata:
            return None
        names = ", ".join(p.name for p in self.dem.paths)
        return (f"{self.outside + self.nodata} of {self.objects} objects have no ground elevation "
                f"({self.outside} outside the DEM, {self.nodata} on its nodata): {names}")

    def record(self) -> dict[str, Any]:
        """The build options' entry: the DEM files and the objects without elevation."""
        import hashlib

        files = [{"name": p.name, "size": p.stat().st_size, "sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
                 for p in self.dem.paths]
        return {"files": files, "outside": self.outside, "nodata": self.nodata}
