"""Pictures: one image's match over the map (:func:`plot_match`) and an evaluation (:func:`plot_evaluation`).

Both are for people checking an answer, so they show what can be wrong: image
objects that found no map object of their label, where a wrong answer landed
against the truth, what the matcher rejected and why.  Axes are the map's
projected metres with its CRS named.

:func:`match_geometry` computes what :func:`plot_match` draws (the image's objects
and footprint placed in the map, each object's nearest map object of its label,
inliers) without drawing, for tests and for other front ends.

matplotlib is imported inside the drawing functions (with the Agg backend, no
display), so that ``import mapdb`` does not pay for it.
"""

from __future__ import annotations

import math
import os
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ..answers import Answer, Candidate
from ..camera import Camera, Pose, image_plane, image_to_ground, level_pixels
from ..detections.images import ImageObjects, parse_image
from ..errors import MapdbIOError
from ..objects import Objects
from .evaluate import DEFAULT_FP_THRESHOLD_M

__all__ = [
    "MatchGeometry",
    "crs_name",
    "match_geometry",
    "plot_evaluation",
    "plot_match",
    "pyplot",
    "save_figure",
]

# The main view of a match shows this fraction of the footprint's size around it (map context).
VIEW_MARGIN = 0.25
# A truth farther than this many footprint diagonals from the answer is shown in the overview only:
# drawing both in one view would shrink the footprint to a dot.
TRUTH_IN_VIEW_DIAGONALS = 1.5
# The overview draws the map's objects only up to this many (decoding a huge map for a thumbnail is
# not worth seconds), sampled down to OVERVIEW_POINTS.
OVERVIEW_MAX_OBJECTS = 500_000
OVERVIEW_POINTS = 60_000
# Without a footprint to size it (a rejected image without truth), the view is this wide around the
# best candidate.
DEFAULT_VIEW_M = 600.0
DPI = 110
# An evaluation picture writes the error beside at most this many false positives (the largest).
MAX_ERRORS_NAMED = 12
# About the size of such a label ("12.3 m" at 7 points, 110 dpi) in pixels: closer labels would overprint.
LABEL_BOX_PX = (48.0, 14.0)
# Label colours: distinguishable, with no pure red, which marks outliers and false positives.
_PALETTE = (
    "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#17becf", "#8c564b", "#e377c2", "#bcbd22",
    "#7f7f7f", "#aec7e8", "#98df8a", "#ffbb78", "#c5b0d5", "#9edae5", "#c49c94", "#f7b6d2",
)
_OUTLIER = "#d62728"
_ANSWER = "#ffd700"


# --------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class MatchGeometry:
    """An image placed in the map by one pose: what :func:`plot_match` draws.

    Attributes
    ----------
    pose : {"answer", "truth"}
        Which pose placed the image: the localizer's answer, or (for a rejected simulated image) the
        simulator's truth.
    world : complex array (n,)
        Each image object in map metres (``x + iy``); NaN where the pose cannot place it.
    footprint : complex array (4,)
        The image corners top-left, top-right, bottom-right, bottom-left in map metres.
    up : complex
        The map point under the middle of the image's top edge (where the image's *up* points).
    position : complex
        The pose's position: the answer's ``x, y`` (the camera nadir when the image was levelled, else
        the point under the image centre) or the truth's (the nadir).
    names : array of str (n,)
        Each image object's label.
    nearest : complex array (n,)
        The nearest map object of the same label (NaN if the map has none of that label nearby).
    distance : float array (n,)
        Distance (m) to it (inf if none).
    inlier : bool array (n,)
        Whether that distance is within ``gate_m``.
    gate_m : float
        The inlier gate: ``GATE_SIGMAS`` residual sigmas of the ``expected`` nearest objects,
        and at least the farthest of them (the matcher's own rule).
    """

    pose: str
    world: np.ndarray
    footprint: np.ndarray
    up: complex
    names: np.ndarray
    nearest: np.ndarray
    distance: np.ndarray
    inlier: np.ndarray
    gate_m: float
    position: complex


def _answer_placer(im: ImageObjects, answer: Answer):
    """Pixels -> map (complex) by the answer's similarity ``z -> a z + b``, as the localizer fitted it.

    ``a = scale * exp(-i heading)`` (``heading_deg`` is ``-arg(a)``, clockwise from north) and ``b`` is
    ``(x, y)``.  The pixels are levelled first when the localizer levelled them.
    """
    assert answer.scale_m_per_px is not None and answer.heading_deg is not None
    a = answer.scale_m_per_px * complex(np.exp(-1j * math.radians(answer.heading_deg)))
    b = _xy(answer)
    fov = im.fov_deg if answer.levelled else None

    def place(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
        if fov is not None:
            u, v = level_pixels(u, v, _camera(im, fov), im.roll_deg or 0.0, im.pitch_deg or 0.0)
        return a * image_plane(u, v, im.width, im.height) + b

    return place


def _camera(im: ImageObjects, fov_deg: float) -> Camera:
    """The image's camera, sized as the localizer sizes it (an image's width may be fractional)."""
    return Camera(im.width, im.height, fov_deg)


def _truth_placer(im: ImageObjects, truth: dict[str, Any]):
    """Pixels -> map (complex) by the simulator's true pose (the full camera model, tilt included)."""
    pose = Pose(float(truth["x"]), float(truth["y"]), float(truth["altitude_m"]), float(truth["heading_deg"]),
                float(truth.get("roll_deg") or 0.0), float(truth.get("pitch_deg") or 0.0))
    camera = _camera(im, float(truth.get("fov_deg") or im.fov_deg or 0.0))

    def place(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        gx, gy = image_to_ground(np.asarray(u, np.float64), np.asarray(v, np.float64), pose, camera)
        return gx + 1j * gy

    return place


def _has_pose(answer: Answer) -> bool:
    return answer.ok and all(
        isinstance(getattr(answer, k), int | float) for k in ("x", "y", "heading_deg", "scale_m_per_px"))


def _xy(answer: Answer | Candidate) -> complex:
    return complex(float(answer.x or 0.0), float(answer.y or 0.0))



def _truth_pose(truth: dict[str, Any] | None, im: ImageObjects) -> bool:
    if not isinstance(truth, dict):
        return False
    keys = ("x", "y", "altitude_m", "heading_deg")
    return all(isinstance(truth.get(k), int | float) for k in keys) and (
        isinstance(truth.get("fov_deg"), int | float) or im.fov_deg is not None)


def _nearest_of_label(world: np.ndarray, names: np.ndarray, objects: Objects) -> tuple[np.ndarray, np.ndarray]:
    from .._scipy import cKDTree

    nearest = np.full(world.shape, np.nan + 0j)
    distance = np.full(world.shape, np.inf)
    codes = {name: code for code, name in enumerate(objects.labels)}
    for name in np.unique(names):
        mine = (names == name) & np.isfinite(world)
        code = codes.get(str(name))
        if code is None or not mine.any():
            continue
        of_label = objects.label == code
        if not of_label.any():
            continue
        tree = cKDTree(np.column_stack([objects.x[of_label], objects.y[of_label]]))
        d, j = tree.query(np.column_stack([world[mine].real, world[mine].imag]))
        distance[mine] = d
        nearest[mine] = objects.x[of_label][j] + 1j * objects.y[of_label][j]
    return nearest, distance


def _gate(distance: np.ndarray, expected: int) -> float:
    """The inlier gate from the ``expected`` smallest distances (the matcher's residual sigma and rule)."""
    from ..match.refine import residual_sigma
    from ..match.verify import GATE_SIGMAS

    finite = np.sort(distance[np.isfinite(distance)])
    k = min(max(int(expected), 3), finite.size)
    if k == 0:
        return 0.0
    best = finite[:k]
    return max(GATE_SIGMAS * residual_sigma(best), float(best[-1]), 1e-9)


def match_geometry(image: dict[str, Any] | ImageObjects, answer: Answer, map: Any,
                   truth: dict[str, Any] | None = None) -> MatchGeometry | None:
    """Place an image's objects and footprint in the map, and find which meet a map object of their label.

    Parameters
    ----------
    image : dict or ImageObjects
        The image document (or parsed image) that was localized.
    answer : dict
        Its answer (:func:`mapdb.localize.localize`).  An accepted answer's pose places the image.
    map : MetaMap or MemoryMap
        The map it was localized in.
    truth : dict, optional
        The simulator's truth (``x``, ``y``, ``altitude_m``, ``heading_deg``, and ``fov_deg`` unless the
        image has a camera); its pose places a rejected image.  Defaults to the document's ``truth``.

    Returns
    -------
    MatchGeometry or None
        None when neither an accepted answer nor a truth pose can place the image.

    Raises
    ------
    ImageInputError
        If the image document is not valid.
    """
    im = image if isinstance(image, ImageObjects) else parse_image(image)
    if truth is None and isinstance(image, dict):
        truth = image.get("truth")
    if _has_pose(answer):
        pose, place = "answer", _answer_placer(im, answer)
        position = _xy(answer)
        expected = int(answer.inliers or 0)
    elif _truth_pose(truth, im):
        assert truth is not None
        pose, place = "truth", _truth_placer(im, truth)
        position = complex(float(truth["x"]), float(truth["y"]))
        index = truth.get("map_index")
        # The true objects are the ones expected to meet their map object.
        expected = int(np.sum(np.asarray(index) >= 0)) if isinstance(index, list) else len(im) // 2
    else:
        return None
    world = place(im.x, im.y)
    corners = place(np.array([0.0, im.width, im.width, 0.0]), np.array([0.0, 0.0, im.height, im.height]))
    up = complex(place(np.array([im.width / 2.0]), np.array([0.0]))[0])
    finite = world[np.isfinite(world)]
    reach = np.concatenate([corners[np.isfinite(corners)], finite])
    if reach.size:
        pad = 0.1 * max(float(np.ptp(reach.real)), float(np.ptp(reach.imag)), 1.0)
        objects = map.query_bbox(float(reach.real.min() - pad), float(reach.imag.min() - pad),
                                 float(reach.real.max() + pad), float(reach.imag.max() + pad))
    else:
        objects = Objects.empty(map.labels, map.crs)
    nearest, distance = _nearest_of_label(world, im.names, objects)
    gate = _gate(distance, expected)
    return MatchGeometry(pose=pose, world=world, footprint=corners, up=up, names=np.asarray(im.names),
                         nearest=nearest, distance=distance, inlier=distance <= gate, gate_m=gate,
                         position=position)


# ------------------------------------------------------------------------------------- drawing aids


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


def _metre_axes(ax: Any, crs: str | None, nbins: int = 6) -> None:
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


def _label_colours(labels: Sequence[str]) -> dict[str, str]:
    """One colour per label of the map, fixed by the label's code, so that pictures of one map agree."""
    return {name: _PALETTE[i % len(_PALETTE)] for i, name in enumerate(labels)}


def _fmt(value: Any, digits: int = 2, unit: str = "") -> str:
    if not isinstance(value, int | float) or not math.isfinite(value):
        return "-"
    return f"{value:.{digits}f}{unit}"


# ------------------------------------------------------------------------------------ one match


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


def _widened(ax: Any, view: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
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
            head += f", error {_fmt(abs(_xy(answer) - truth_xy), 2, ' m')}"
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
        h = ax.scatter(geom.world[out].real, geom.world[out].imag, s=48, marker="X", color=_OUTLIER,
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

    shown = [(i, _xy(c)) for i, c in enumerate(answer.candidates, 1)]
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
        p = _xy(answer)
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
        focus = _xy(cands[0])
    else:
        # Nothing places the image in the map: show what it holds, in pixels.
        return _draw_pixels(ax, im, colours), None
    view = _widened(ax, _view_box(geom, focus, truth_xy, _size_hint(im)))
    handles = _draw_map_objects(ax, map.query_bbox(*view), colours)
    if geom is not None:
        handles += _draw_geometry(ax, geom, colours)
    handles += _draw_positions(ax, answer, truth_xy, view)
    ax.set_xlim(view[0], view[2])
    ax.set_ylim(view[1], view[3])
    ax.set_aspect("equal", adjustable="box")
    _metre_axes(ax, map.crs)
    ax.set_title(_view_title(geom, answer, focus, truth_xy), fontsize=9)
    return handles, view


def _candidate_notes(answer: Answer, truth_xy: complex | None, limit: int = 5) -> str:
    """A small table of the candidates: inliers, score, and distance from the answer or the truth."""
    cands = answer.candidates[:limit]
    if not cands:
        return ""
    ok = answer.ok
    ref = _xy(answer) if ok else truth_xy
    what = "from answer" if ok else "from truth"
    rows = [("runner-up" if ok else "candidate") + f"  inliers  score  {what if ref is not None else ''}"]
    for i, c in enumerate(cands, 1):
        far = "" if ref is None else f"{abs(_xy(c) - ref):,.0f} m"
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


# ------------------------------------------------------------------------------------- evaluation


def plot_evaluation(
    outcomes: Sequence[dict[str, Any]],
    path: str | Path,
    *,
    fp_threshold: float = DEFAULT_FP_THRESHOLD_M,
    map_objects: Objects | None = None,
    title: str | None = None,
    crs: str | None = None,
) -> None:
    """Save a figure of an evaluation: where each image was and what became of it, and the error distribution.

    The map panel shows every image at its true position: correct answers (green), rejected images (grey
    rings) and false positives (a red ring at the truth, a red cross where the answer landed, a line
    between).  Beside it, the cumulative distribution of the error of accepted answers with the bound
    (the fit with the true correspondences) and the false-positive threshold.

    Parameters
    ----------
    outcomes : sequence of dict
        From :func:`mapdb.evaluation.evaluate.outcome` (``status``, ``x``, ``y``, ``truth_x``, ``truth_y``,
        ``error_m``, ``bound_error_m``).
    path : str or Path
        The picture; matplotlib picks the format from the ending.
    fp_threshold : float
        Accepted answers farther than this (m) from the truth are false positives.
    map_objects : Objects, optional
        Drawn faintly under the images.
    title : str, optional
        The figure's title.
    crs : str, optional
        The CRS to name on the axes (default: that of ``map_objects``).

    Raises
    ------
    MapdbIOError
        If the picture cannot be written.
    """
    status = np.array([o["status"] for o in outcomes], dtype=object)
    ok = status == "ok"
    error = np.array([o["error_m"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    fp = ok & (error > fp_threshold)
    plt = pyplot()
    fig, (ax_err, ax_map) = plt.subplots(1, 2, figsize=(12.5, 5.8), gridspec_kw={"width_ratios": [1, 1.35]})
    _draw_error_cdf(ax_err, outcomes, error, ok, fp, fp_threshold)
    _draw_outcome_map(ax_map, outcomes, ok, fp, map_objects, crs or (map_objects.crs if map_objects else None))
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    if fp.any():
        _name_errors(ax_map, outcomes, fp)
    save_figure(fig, path)


def _draw_error_cdf(ax: Any, outcomes: Sequence[dict[str, Any]], error: np.ndarray, ok: np.ndarray,
                    fp: np.ndarray, fp_threshold: float) -> None:
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    bound = np.array([np.nan if o["bound_error_m"] is None else o["bound_error_m"] for o in outcomes])
    floor = 1e-4  # an error of exactly 0 (a noiseless simulation) still has a place on the log axis
    n = len(outcomes)
    drawn = False
    for values, name, colour in (
        (error[ok], "localizer (accepted answers)", "tab:blue"),
        (bound[np.isfinite(bound)], "bound (fit with the true correspondences)", "0.45"),
    ):
        if values.size:
            v = np.sort(np.maximum(values, floor))
            ax.step(np.concatenate([[v[0]], v]), np.arange(0, v.size + 1) / max(n, 1), where="post", label=name,
                    color=colour, linewidth=1.6)
            drawn = True
    ax.axvline(fp_threshold, color=_OUTLIER, linestyle="--", linewidth=1.0,
               label=f"false-positive threshold ({fp_threshold:g} m)")
    if ok.any():
        ax.axhline(ok.sum() / max(n, 1), color="tab:blue", linestyle=":", linewidth=0.8)
    ax.set_xscale("log")
    if not drawn:
        ax.set_xlim(0.01, 100.0)
    lo, hi = ax.get_xlim()
    # Over a few decades, 1-2-5 steps label enough of the axis to read it; over more they would crowd it.
    subs = (1.0, 2.0, 5.0) if math.log10(hi / lo) <= 3.0 else (1.0,)
    ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=subs, numticks=12))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylim(0.0, 1.02)
    ax.tick_params(labelsize=8)
    ax.set_xlabel("horizontal error (m, log scale)", fontsize=9)
    ax.set_ylabel("fraction of all images with at most this error", fontsize=9)
    ax.set_title("error distribution (cumulative)", fontsize=10)
    ax.grid(True, which="major", alpha=0.3)
    ax.grid(True, which="minor", alpha=0.1)
    correct = int((ok & ~fp).sum())
    rejected = int((~ok).sum())
    good = error[ok & ~fp]
    rms = f"{math.sqrt(float(np.mean(good**2))):.2f} m" if good.size else "-"
    text = (f"{n} images: {correct} correct (RMS {rms}), {int(fp.sum())} false positive(s), {rejected} rejected\n"
            "dotted line: fraction accepted")
    ax.text(0.02, 0.98, text, transform=ax.transAxes, fontsize=8, va="top",
            bbox={"boxstyle": "round", "facecolor": "white", "edgecolor": "0.8"})
    ax.legend(loc="lower right", fontsize=8)


def _name_errors(ax: Any, outcomes: Sequence[dict[str, Any]], fp: np.ndarray) -> None:
    """Write the error beside false positives, largest first, skipping any that would overprint another.

    An error of metres is invisible at the scale of a map; its size in words is not.  Call once the
    figure's layout is done: overlaps are judged in pixels.
    """
    ax.apply_aspect()
    where = ax.transData.transform([(o["x"], o["y"]) if f else (0.0, 0.0) for o, f in zip(outcomes, fp, strict=True)])
    error = np.array([o["error_m"] if f else 0.0 for o, f in zip(outcomes, fp, strict=True)], dtype=np.float64)
    width, height = LABEL_BOX_PX
    placed: list[np.ndarray] = []
    for i in sorted(np.flatnonzero(fp).tolist(), key=lambda i: -error[i]):
        if any(abs(where[i, 0] - p[0]) < width and abs(where[i, 1] - p[1]) < height for p in placed):
            continue
        placed.append(where[i])
        o = outcomes[i]
        ax.annotate(f"{error[i]:,.0f} m" if error[i] >= 10 else f"{error[i]:.1f} m", (o["x"], o["y"]), xytext=(5, -3),
                    textcoords="offset points", fontsize=7, color=_OUTLIER, zorder=6)
        if len(placed) >= MAX_ERRORS_NAMED:
            break


def _draw_outcome_map(ax: Any, outcomes: Sequence[dict[str, Any]], ok: np.ndarray, fp: np.ndarray,
                      map_objects: Objects | None, crs: str | None) -> None:
    tx = np.array([o["truth_x"] for o in outcomes], dtype=np.float64)
    ty = np.array([o["truth_y"] for o in outcomes], dtype=np.float64)
    ex = np.array([o["x"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    ey = np.array([o["y"] if o["status"] == "ok" else np.nan for o in outcomes], dtype=np.float64)
    if map_objects is not None and len(map_objects):
        step = max(1, len(map_objects) // OVERVIEW_POINTS)
        ax.scatter(map_objects.x[::step], map_objects.y[::step], s=1.0, color="0.8", linewidths=0, zorder=1,
                   label="map objects", rasterized=True)
    correct = ok & ~fp
    if correct.any():
        ax.scatter(tx[correct], ty[correct], s=16, color="tab:green", edgecolors="none", zorder=3,
                   label=f"correct ({int(correct.sum())})")
    if (~ok).any():
        ax.scatter(tx[~ok], ty[~ok], s=30, facecolors="none", edgecolors="0.25", linewidths=1.0, zorder=3,
                   label=f"rejected ({int((~ok).sum())}), at the truth")
    if fp.any():
        for i in np.flatnonzero(fp):
            ax.plot([tx[i], ex[i]], [ty[i], ey[i]], color=_OUTLIER, linewidth=0.9, alpha=0.8, zorder=4)
        ax.scatter(tx[fp], ty[fp], s=36, facecolors="none", edgecolors=_OUTLIER, linewidths=1.3, zorder=5,
                   label=f"false positive ({int(fp.sum())}): truth")
        ax.scatter(ex[fp], ey[fp], s=40, marker="X", color=_OUTLIER, edgecolors="white", linewidths=0.5, zorder=5,
                   label="false positive: where it landed")
    ax.set_aspect("equal", adjustable="datalim")
    _metre_axes(ax, crs)
    ax.set_title("images at their true position, by outcome", fontsize=10)
    ax.legend(loc="best", fontsize=8, framealpha=0.9)
