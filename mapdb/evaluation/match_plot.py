"""The picture of one image's match over the map (:func:`plot_match`, ``mapdb show``).

It is for people checking an answer, so it shows what can be wrong: image objects that found no map
object of their label, where a wrong answer landed against the truth, what the matcher rejected and
why.  Axes are the map's projected metres with its CRS named.  What it draws is computed by
:func:`~mapdb.evaluation.match_geometry.match_geometry`.

matplotlib is imported inside the drawing functions (with the Agg backend, no display), so that
``import mapdb`` does not pay for it.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..answers import Answer
from ..detections.images import ImageObjects, parse_image
from ..objects import Objects
from .drawing import OUTLIER_COLOUR, OVERVIEW_POINTS, metre_axes, pyplot, save_figure, widened
from .match_geometry import MatchGeometry, answer_xy, match_geometry

__all__ = ["plot_match"]

# The main view of a match shows this fraction of the footprint's size around it (map context).
VIEW_MARGIN = 0.25
# A truth farther than this many footprint diagonals from the answer is shown in the overview only:
# drawing both in one view would shrink the footprint to a dot.
TRUTH_IN_VIEW_DIAGONALS = 1.5
# The overview draws the map's objects only up to this many (decoding a huge map for a thumbnail is
# not worth seconds), sampled down to drawing.OVERVIEW_POINTS.
OVERVIEW_MAX_OBJECTS = 500_000
# Without a footprint to size it (a rejected image without truth), the view is this wide around the
# best candidate.
DEFAULT_VIEW_M = 600.0
# Label colours: distinguishable, with no pure red, which marks outliers and false positives.
_PALETTE = (
    "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#17becf", "#8c564b", "#e377c2", "#bcbd22",
    "#7f7f7f", "#aec7e8", "#98df8a", "#ffbb78", "#c5b0d5", "#9edae5", "#c49c94", "#f7b6d2",
)
_ANSWER = "#ffd700"


def _label_colours(labels: Sequence[str]) -> dict[str, str]:
    """One colour per label of the map, fixed by the label's code, so that pictures of one map agree."""
    return {name: _PALETTE[i % len(_PALETTE)] for i, name in enumerate(labels)}


def _fmt(value: Any, digits: int = 2, unit: str = "") -> str:
    if not isinstance(value, int | float) or not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f}{unit}"


def _view_box(geom: MatchGeometry | None, focus: complex, truth_xy: complex | None,
              size_hint: float) -> tuple[float, float, float, float]:
    """The main view: the footprint with a margin, and the truth when it is near enough to share the view."""
    if geom is not None and np.all(np.isfinite(geom.footprint)):
        pts = list(geom.footprint)
    else:
        h = size_hint / 2.0
        pts = [focus + complex(-h, -h), focus + complex(h, h)]
    xs, ys = [p.real for p in pts], [p.imag for p in pts]
    diag = math.hypot(max(xs) - min(xs), max(ys) - min(ys))
    if truth_xy is not None and abs(truth_xy - focus) <= TRUTH_IN_VIEW_DIAGONALS * diag:
        xs.append(truth_xy.real)
        ys.append(truth_xy.imag)
    pad = VIEW_MARGIN * max(max(xs) - min(xs), max(ys) - min(ys), 1.0)
    return min(xs) - pad, min(ys) - pad, max(xs) + pad, max(ys) + pad


def _truth_xy(truth: Any) -> complex | None:
    if isinstance(truth, dict) and all(isinstance(truth.get(k), int | float) for k in ("x", "y")):
        return complex(float(truth["x"]), float(truth["y"]))
    return None


def _match_title(im: ImageObjects, answer: Answer, truth_xy: complex | None) -> str:
    name = answer.id if answer.id is not None else im.id
    head = f"{name if name is not None else 'image'}: "
    if answer.ok:
        head += f"accepted, score {_fmt(answer.score, 1)}, {answer.inliers} inliers of {len(im)}"
        head += f", sigma {_fmt(answer.sigma_m, 2, ' m')}"
        if truth_xy is not None:
            head += f", error {_fmt(abs(answer_xy(answer) - truth_xy), 2, ' m')}"
        return head
    return textwrap.fill(head + f"rejected: {answer.reason or 'no reason given'}", width=110)


def _draw_map_objects(ax: Any, objects: Objects, colours: dict[str, str]) -> list[tuple[Any, str]]:
    handles = []
    for code, name in enumerate(objects.labels):
        mine = objects.label == code
        if mine.any():
            h = ax.scatter(objects.x[mine], objects.y[mine], s=14, color=colours.get(name, "0.5"), alpha=0.55,
                           linewidths=0, zorder=2)
            handles.append((h, f"map: {name} ({int(mine.sum())})"))
    return handles


def _draw_geometry(ax: Any, geom: MatchGeometry, colours: dict[str, str]) -> list[tuple[Any, str]]:
    handles = []
    fp = np.append(geom.footprint, geom.footprint[0])
    (h,) = ax.plot(fp.real, fp.imag, color="black", linestyle="--", linewidth=1.2, zorder=3)
    what = "image footprint" + (" (true pose)" if geom.pose == "truth" else "")
    handles.append((h, what))
    centre = geom.position
    # An arrow from the position towards the middle of the image's top edge: the image's "up" (heading).
    ax.annotate("", xy=(geom.up.real, geom.up.imag), xytext=(centre.real, centre.imag),
                arrowprops={"arrowstyle": "->", "color": "black", "lw": 1.0, "alpha": 0.6}, zorder=3)
    ahead = geom.up - centre
    ahead = ahead / abs(ahead) if abs(ahead) > 0 else 1j
    # The words sit just beyond the arrow's tip, on its line, whichever way the image points.
    ax.annotate("image up", xy=(geom.up.real, geom.up.imag), xytext=(14 * ahead.real, 14 * ahead.imag),
                textcoords="offset points", fontsize=7, color="0.25", ha="center", va="center", zorder=3)
    inl, out = geom.inlier, ~geom.inlier & np.isfinite(geom.world)
    for i in np.flatnonzero(inl):
        ax.plot([geom.world[i].real, geom.nearest[i].real], [geom.world[i].imag, geom.nearest[i].imag],
                color="black", linewidth=0.8, zorder=4)
    if inl.any():
        # Hollow, so that the map object matched shows through (its dot gives the label's colour).
        h = ax.scatter(geom.world[inl].real, geom.world[inl].imag, s=55, marker="D", facecolors="none",
                       edgecolors="black", linewidths=1.1, zorder=5)
        handles.append((h, f"image object, inlier ({int(inl.sum())}, within {geom.gate_m:.1f} m)"))
    if out.any():
        h = ax.scatter(geom.world[out].real, geom.world[out].imag, s=48, marker="X", color=OUTLIER_COLOUR,
                       edgecolors="white", linewidths=0.6, zorder=5)
        handles.append((h, f"image object, no map match ({int(out.sum())})"))
    return handles


def _draw_positions(ax: Any, answer: Answer, truth_xy: complex | None, view: tuple[float, ...] | None,
                    overview: bool = False) -> list[tuple[Any, str]]:
    """The answer (star), the truth (circled cross) and the candidates (numbered triangles) within ``view``."""
    handles = []
    scale = 0.6 if overview else 1.0

    def inside(p: complex) -> bool:
        return view is None or (view[0] <= p.real <= view[2] and view[1] <= p.imag <= view[3])

    shown = [(i, answer_xy(c)) for i, c in enumerate(answer.candidates, 1)]
    shown = [(i, p) for i, p in shown if inside(p)]
    if shown:
        h = ax.scatter([p.real for _, p in shown], [p.imag for _, p in shown], s=60 * scale, marker="^",
                       color="#9467bd", edgecolors="black", linewidths=0.6, zorder=6)
        # Offsets turn with the rank, so that the numbers of candidates close together do not overprint.
        offsets = ((4, 4), (4, -10), (-10, 4), (-10, -10))
        for i, p in shown:
            ax.annotate(str(i), (p.real, p.imag), xytext=offsets[(i - 1) % 4], textcoords="offset points",
                        fontsize=7, color="#5b3a8a", zorder=6)
        rejected = not answer.ok
        handles.append((h, "candidates (1 = best)" if rejected else "runner-up candidates"))
    if answer.ok:
        p = answer_xy(answer)
        h = ax.scatter([p.real], [p.imag], s=220 * scale, marker="*", color=_ANSWER, edgecolors="black",
                       linewidths=0.9, zorder=7)
        handles.append((h, "answer (its x, y)"))
    if truth_xy is not None and inside(truth_xy):
        h = ax.scatter([truth_xy.real], [truth_xy.imag], s=130 * scale, marker="o", facecolors="none",
                       edgecolors="black", linewidths=1.6, zorder=8)
        ax.scatter([truth_xy.real], [truth_xy.imag], s=130 * scale, marker="+", color="black", linewidths=1.2,
                   zorder=8)
        handles.append((h, "truth (camera nadir)"))
    return handles


def _draw_overview(ax: Any, map: Any, answer: Answer, truth_xy: complex | None,
                   view: tuple[float, float, float, float] | None) -> list[tuple[Any, str]]:
    from matplotlib.patches import Rectangle

    if 0 < len(map) <= OVERVIEW_MAX_OBJECTS:
        objects = map.all()
        step = max(1, len(objects) // OVERVIEW_POINTS)
        ax.scatter(objects.x[::step], objects.y[::step], s=0.6, color="0.72", linewidths=0, zorder=1,
                   rasterized=True)
    bx0, by0, bx1, by1 = map.bounds
    ax.add_patch(Rectangle((bx0, by0), bx1 - bx0, by1 - by0, fill=False, edgecolor="0.6", linewidth=0.6))
    if view is not None:
        x0, y0, x1, y1 = view
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="black", linewidth=1.0, zorder=5))
    handles = _draw_positions(ax, answer, truth_xy, None, overview=True)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xticks([])
    ax.set_yticks([])
    w = bx1 - bx0
    ax.set_title(f"the whole map ({w / 1000:,.1f} km wide); box: main view", fontsize=8)
    return handles


def plot_match(image: dict[str, Any] | ImageObjects, answer: Answer, map: Any, path: str | Path, *,
               truth: dict[str, Any] | None = None, title: str | None = None) -> None:
    """Save a picture of one image's match: its objects placed over the map, inliers and outliers, footprint.

    The main view shows, in map metres, the map's objects around the answer (a dot per object, coloured
    by label), the image's footprint (dashed, with an arrow to its top edge), each image object placed
    by the answer's similarity (a diamond in its label's colour, joined to the nearest map object of its
    label, when that lies within the inlier gate; a red cross when none does), the answer, the truth and
    runner-up candidates.  A small overview places the view, the candidates and the truth in the whole
    map.  A rejected image is placed by its truth pose when it has one (a simulated image); otherwise
    the view is centred on its best candidate, or shows the image's objects in pixels if there is none.

    Parameters
    ----------
    image : dict or ImageObjects
        The image document (with ``truth`` for a simulated image) or a parsed image.
    answer : dict
        Its answer from :func:`mapdb.localize.localize`.
    map : MetaMap or MemoryMap
        The map it was localized in.
    path : str or Path
        The picture; matplotlib picks the format from the ending.
    truth : dict, optional
        The truth (``x``, ``y``; with ``altitude_m``, ``heading_deg``, ``fov_deg`` a pose); default the
        document's ``truth``.
    title : str, optional
        A first title line (default: the image id, status, score, inliers, error against the truth).

    Raises
    ------
    ImageInputError
        If the image is not valid.
    MapdbIOError
        If the picture cannot be written.
    """
    im = image if isinstance(image, ImageObjects) else parse_image(image)
    if truth is None and isinstance(image, dict):
        truth = image.get("truth")
    truth_xy = _truth_xy(truth)
    plt = pyplot()
    fig = plt.figure(figsize=(11.5, 7.2))
    grid = fig.add_gridspec(2, 2, width_ratios=[2.15, 1], height_ratios=[1, 1.15], wspace=0.08, hspace=0.12,
                            left=0.08, right=0.98, bottom=0.08, top=0.9)
    ax, ax_over, ax_key = fig.add_subplot(grid[:, 0]), fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, 1])
    ax_key.axis("off")
    handles, view = _draw_main_view(ax, im, answer, map, match_geometry(im, answer, map, truth), truth_xy)
    # What only the overview shows (far candidates, a far truth) gets its legend entry too.
    named = {text for _, text in handles}
    handles += [(h, text) for h, text in _draw_overview(ax_over, map, answer, truth_xy, view) if text not in named]
    if handles:
        ax_key.legend([h for h, _ in handles], [t for _, t in handles], loc="upper left", fontsize=8,
                      frameon=False, borderaxespad=0.0)
    notes = _candidate_notes(answer, truth_xy)
    if notes:
        ax_key.text(0.0, 0.0, notes, transform=ax_key.transAxes, fontsize=7.5, va="bottom", family="monospace")
    fig.suptitle(title + "\n" + _match_title(im, answer, truth_xy) if title else _match_title(im, answer, truth_xy),
                 fontsize=11)
    save_figure(fig, path)


def _draw_main_view(ax: Any, im: ImageObjects, answer: Answer, map: Any, geom: MatchGeometry | None,
                    truth_xy: complex | None) -> tuple[list[tuple[Any, str]], tuple[float, float, float, float] | None]:
    """The large view: around the pose, else the best candidate, else the image in pixels.  (handles, view)"""
    colours = _label_colours(map.labels)
    cands = answer.candidates
    if geom is not None:
        focus = geom.position
    elif cands:
        focus = answer_xy(cands[0])
    else:
        # Nothing places the image in the map: show what it holds, in pixels.
        return _draw_pixels(ax, im, colours), None
    view = widened(ax, _view_box(geom, focus, truth_xy, _size_hint(im)))
    handles = _draw_map_objects(ax, map.query_bbox(*view), colours)
    if geom is not None:
        handles += _draw_geometry(ax, geom, colours)
    handles += _draw_positions(ax, answer, truth_xy, view)
    ax.set_xlim(view[0], view[2])
    ax.set_ylim(view[1], view[3])
    ax.set_aspect("equal", adjustable="box")
    metre_axes(ax, map.crs)
    ax.set_title(_view_title(geom, answer, focus, truth_xy), fontsize=9)
    return handles, view


def _candidate_notes(answer: Answer, truth_xy: complex | None, limit: int = 5) -> str:
    """A small table of the candidates: inliers, score, and distance from the answer or the truth."""
    cands = answer.candidates[:limit]
    if not cands:
        return ""
    ok = answer.ok
    ref = answer_xy(answer) if ok else truth_xy
    what = "from answer" if ok else "from truth"
    rows = [("runner-up" if ok else "candidate") + f"  inliers  score  {what if ref is not None else ''}"]
    for i, c in enumerate(cands, 1):
        far = "" if ref is None else f"{abs(answer_xy(c) - ref):,.0f} m"
        rows.append(f"{i:>9}  {c.inliers if c.inliers is not None else '-'!s:>7}  {_fmt(c.score, 1):>5}  {far:>9}")
    return "\n".join(rows)


def _size_hint(im: ImageObjects) -> float:
    """The ground width of the image if its altitude and field of view say it, else a default."""
    if im.altitude_m is not None and im.fov_deg is not None:
        return 2.0 * im.altitude_m * math.tan(math.radians(im.fov_deg) / 2.0) * 1.3
    return DEFAULT_VIEW_M


def _view_title(geom: MatchGeometry | None, answer: Answer, focus: complex, truth_xy: complex | None) -> str:
    if geom is None:
        return "best candidate; a rejected answer has no pose to place the image's objects by"
    if geom.pose == "answer":
        parts = [f"image placed by the answer: heading {answer.heading_deg:.1f} deg, "
                 f"{answer.scale_m_per_px:.3f} m/pixel"]
    else:
        parts = ["image placed by its TRUE pose (the answer was rejected)"]
    if truth_xy is not None and geom.pose == "answer":
        far = abs(truth_xy - focus)
        diag = abs(geom.footprint[2] - geom.footprint[0])
        if far > TRUTH_IN_VIEW_DIAGONALS * diag:
            parts.append(f"truth {far:,.0f} m away (see the overview)")
    return "; ".join(parts)


def _draw_pixels(ax: Any, im: ImageObjects, colours: dict[str, str]) -> list[tuple[Any, str]]:
    handles = []
    for name in np.unique(im.names):
        mine = im.names == name
        h = ax.scatter(im.x[mine], im.y[mine], s=30, marker="D", color=colours.get(str(name), "0.5"))
        handles.append((h, f"image: {name} ({int(mine.sum())})"))
    ax.set_xlim(0, im.width)
    ax.set_ylim(im.height, 0)  # pixels: y down
    ax.set_aspect("equal")
    ax.set_xlabel("x (pixels)", fontsize=9)
    ax.set_ylabel("y (pixels)", fontsize=9)
    ax.set_title("no candidate: the image's objects, in pixels", fontsize=9)
    return handles
