"""Drawing aids shared by the pictures of :mod:`mapdb.evaluation` and of other packages (analysis, navigation).

matplotlib's pyplot on the Agg back end, map axes in projected metres with the CRS named, a view widened
to the shape of its axes, and figures written to files.  matplotlib is imported inside the functions
(with the Agg backend, no display), so that ``import mapdb`` does not pay for it.
"""

from __future__ import annotations

import os
from functools import lru_cache
from typing import Any

from ..errors import MapdbIOError

__all__ = [
    "DPI",
    "OUTLIER_COLOUR",
    "OVERVIEW_POINTS",
    "crs_name",
    "metre_axes",
    "pyplot",
    "save_figure",
    "widened",
]

DPI = 110
# Overviews of a map draw its objects sampled down to about this many points.
OVERVIEW_POINTS = 60_000
# Marks outliers and false positives; no label colour is pure red.
OUTLIER_COLOUR = "#d62728"


@lru_cache(maxsize=16)
def crs_name(crs: str | None) -> str:
    """The CRS as a reader wants it: its code and name; ``"unknown CRS"`` if none.

    Examples
    --------
    >>> crs_name("EPSG:32631")
    'EPSG:32631 (WGS 84 / UTM zone 31N)'
    """
    if not crs:
        return "unknown CRS"
    try:
        from pyproj import CRS

        name = CRS.from_user_input(crs).name
    except Exception:  # pyproj raises several kinds; the code alone still names it
        return str(crs)
    return f"{crs} ({name})" if name and name != "unknown" else str(crs)


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg back end (pictures are files; no display is needed or opened)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def metre_axes(ax: Any, crs: str | None, nbins: int = 6) -> None:
    """Map axes: a few ticks with thousands separators, the CRS named."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]))
        axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:,.0f}"))
    ax.tick_params(labelsize=8)
    ax.set_xlabel(f"easting (m), {crs_name(crs)}", fontsize=9)
    ax.set_ylabel("northing (m)", fontsize=9)
    ax.grid(True, alpha=0.25, linewidth=0.6)


def save_figure(fig: Any, path: str | os.PathLike[str], dpi: int = DPI) -> None:
    """Write a figure (the format from the ending) and close it; an unwritable path is a :class:`MapdbIOError`."""
    plt = pyplot()
    try:
        fig.savefig(path, dpi=dpi)
    except OSError as exc:
        raise MapdbIOError(f"{path}: cannot write plot ({exc.strerror or exc})") from None
    finally:
        plt.close(fig)


def widened(ax: Any, view: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """``view`` widened along one axis to the shape of the axes: equal scale that fills them."""
    pos = ax.get_position()
    fig_w, fig_h = ax.figure.get_size_inches()
    box_ratio = (pos.height * fig_h) / (pos.width * fig_w)
    x0, y0, x1, y1 = view
    w, h = x1 - x0, y1 - y0
    if h / w < box_ratio:
        grow = (w * box_ratio - h) / 2.0
        y0, y1 = y0 - grow, y1 + grow
    else:
        grow = (h / box_ratio - w) / 2.0
        x0, x1 = x0 - grow, x1 + grow
    return x0, y0, x1, y1
